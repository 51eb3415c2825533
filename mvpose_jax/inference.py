"""The pipeline: detections of many frames -> match scores -> proposals -> 3D poses -> tracks.

Frames go through in chunks: every stage is batched over a chunk (padded, so a long recording
compiles a handful of shapes), and memory is bounded by the chunk, not the recording. What each
stage does is chosen by name in one frozen `PipelineConfig` (the registries in `stages`); the
stages themselves live in `matching` (proposals), `lifting` (3D), `tracking` and `smoothing`
(time).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, NamedTuple

import numpy as np
from flax import nnx

from mvpose_jax import stages
from mvpose_jax.cameras import Rig
from mvpose_jax.compiled import kept_per_object
from mvpose_jax.errors import InputError
from mvpose_jax.lifting import (
    LiftingConfig,
    _camera_columns,
    check_method,
    group_people,
    poses_of_members,
)
from mvpose_jax.matching import MatchingConfig
from mvpose_jax.progress import progress_bar
from mvpose_jax.proposals import CombinedConfig, Proposals
from mvpose_jax.skeletons import Detections, Poses3D, skeleton_slots, zero_padded
from mvpose_jax.smoothing import OneEuroConfig, one_euro_frames, one_euro_initial, one_euro_keep
from mvpose_jax.temporal import cached_temporal, for_rig, refine_tracks
from mvpose_jax.tracking import (
    AssociationConfig,
    TrackingConfig,
    associate_skeletons,
    regroup,
    track_anchors,
    track_frames,
)
from mvpose_jax.tracking import initial_state as tracker_initial_state
from mvpose_jax.trained import Estimator, Matcher


@dataclasses.dataclass(frozen=True)
class FilterConfig:
    """Per-track filtering of tracked people (`smoothing`).

    Attributes:
      name: a `stages.FILTERS` name: "none", "one-euro" (causal, in the stream, as a live loop
        runs it) or "butterworth" (zero-phase, over each track's chunks with their neighbours
        while the results are assembled: `smoothing.smooth_chunk_files`).
      one_euro: the One-Euro filter's settings.
      cutoff_hz: the Butterworth filter's cut-off (order 4).
      fill_gap_s: while assembling, gaps of a track's keypoints up to this long are filled (0:
        none).
      outlier_m: while assembling, samples further than this from their keypoint's 7-frame
        median are dropped first (None: keep all).
    """

    name: str = "none"
    one_euro: OneEuroConfig = OneEuroConfig()
    cutoff_hz: float = 2.0
    fill_gap_s: float = 0.5
    outlier_m: float | None = 0.1

    @property
    def streaming(self) -> bool:
        """Whether the filter runs in the stream (else while assembling)."""
        return stages.lookup("filters", self.name, what="filter").streaming


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Everything that decides what the pipeline computes from a recording (its defaults: the
    library's, geometric without models; `mvpose-jax infer` sets its own, e.g. tracking and the
    Butterworth filter).

    Attributes:
      matching: how skeletons are grouped into people.
      lifting: the 3D stage.
      tracking: persistent person ids (`tracking.track_frames`, each person's 2D skeletons as
        evidence); None: no tracks (and no filter).
      filtering: with ``tracking``, each track's keypoints are filtered.
      chunk_frames: frames per chunk (memory is bounded by it; results do not depend on it
        except through tracking: its restarts on resume, and its backfill of a new track's
        tentative first frames, which stays within a chunk (`TrackingConfig.backfill`): a track
        confirmed just after a chunk's end leaves that chunk's last frames without its id).
      temporal: with ``tracking``, the folder of a learned temporal model
        (`temporal.save_temporal`): each chunk's tracks are refined by it (`temporal.refine_tracks`,
        method "blend": robust triangulation where it reconstructs a keypoint, the model
        elsewhere) before any filter; tracks are cut at chunk boundaries. None: no such stage.
      association: with ``tracking``, track-level association: after the chunk is tracked, each
        2D skeleton joins the tracked person (of the chunk, or of the last frames before it) it
        fits in its view (`tracking.associate_skeletons`); the people are regrouped, lifted and
        tracked again. A person the proposals split over two groups is one again; one they
        merged from two people's skeletons is parted. None: the proposals' groups stand.
    """

    matching: MatchingConfig = MatchingConfig()
    lifting: LiftingConfig = LiftingConfig()
    tracking: TrackingConfig | None = None
    filtering: FilterConfig = FilterConfig()
    chunk_frames: int = 256
    temporal: str | None = None
    association: AssociationConfig | None = None

    def to_dict(self) -> dict[str, Any]:
        """The config as plain JSON-able values (the manifest's and the model folder's record)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PipelineConfig:
        """The inverse of `to_dict`."""
        m = dict(d.get("matching") or {})
        if m.get("combined") is not None:
            m["combined"] = CombinedConfig(**m["combined"])
        f = dict(d.get("filtering") or {})
        if f.get("one_euro") is not None:
            f["one_euro"] = OneEuroConfig(**f["one_euro"])
        tracking = d.get("tracking")
        return cls(
            matching=MatchingConfig(**m),
            lifting=LiftingConfig(**(d.get("lifting") or {})),
            tracking=None if tracking is None else TrackingConfig(**tracking),
            filtering=FilterConfig(**f),
            chunk_frames=int(d.get("chunk_frames", 256)),
            temporal=d.get("temporal"),
            association=None
            if d.get("association") is None
            else AssociationConfig(**d["association"]),
        )

    @classmethod
    def of(
        cls,
        *,
        method: str | None = None,
        proposals: str | None = None,
        combined: CombinedConfig | None = None,
        threshold: float = 0.5,
        min_views: int = 2,
        half_score_px: float = 30.0,
        outlier_px: float | None = None,
        view_outlier_px: float | None = None,
        max_spread_m: float | None = None,
        confidence: str | None = None,
        tracking: TrackingConfig | None = None,
        one_euro: OneEuroConfig | None = None,
        chunk_frames: int = 256,
    ) -> PipelineConfig:
        """A config from the stages' settings by their own names (a shorthand for experiments
        that vary one or two of them); ``one_euro``: with ``tracking``, the One-Euro filter in
        the stream. A threshold left None keeps the stage's default."""
        lifting = {
            k: v
            for k, v in (
                ("outlier_px", outlier_px),
                ("view_outlier_px", view_outlier_px),
                ("max_spread_m", max_spread_m),
                ("confidence", confidence),
            )
            if v is not None
        }
        return cls(
            matching=MatchingConfig(proposals, threshold, min_views, half_score_px, combined),
            lifting=LiftingConfig(method, **lifting),
            tracking=tracking,
            filtering=FilterConfig("one-euro", one_euro)
            if one_euro is not None
            else FilterConfig(),
            chunk_frames=chunk_frames,
        )


class PipelineResult(NamedTuple):
    """3D people of F frames and the detections each was built from.

    poses: `Poses3D` with xyz (F, G, K, 3) metres, valid (F, G), keypoint_valid (F, G, K); G is
      the most people in any frame (padded; ``valid`` says which exist).
    confidence: (F, G) mean detection score of each person's keypoints.
    members: (F, G, C) int32: each person's skeleton index in each proposal camera, -1 none.
    identity: (F, C, P) int32: the person of each detected skeleton, -1 none.
    cameras: the proposal cameras (the C axis of ``members`` and ``identity``).
    seconds: wall time of each stage over all frames, {"proposals": s, "poses": s} (and
      "tracking": s when tracked).
    track: (F, G) int32 each person's track id over the whole stream (-1 none), or None
      when not tracked (`tracking`).
    """

    poses: Poses3D
    confidence: np.ndarray
    members: np.ndarray
    identity: np.ndarray
    cameras: tuple[str, ...]
    seconds: dict[str, float]
    track: np.ndarray | None = None


def stream_pipeline(
    rig: Rig,
    detections: Detections | Iterable[tuple[int, Detections]],
    config: PipelineConfig = PipelineConfig(),
    *,
    matcher: Matcher | None = None,
    estimator: Estimator | None = None,
    layout: str = "coco18",
    fps: float = 30.0,
    progress: bool = False,
    num_frames: int | None = None,
    first_track_id: int = 0,
) -> Iterator[tuple[int, PipelineResult]]:
    """The pipeline over a recording, one chunk of frames at a time: yields (first frame, result).

    Args:
      rig: the cameras of the detections, in their order (``rig.names``).
      detections: the whole recording, xy (F, C, P, K, 2) pixels, score (F, C, P, K), count
        (F, C), cut into chunks of ``config.chunk_frames``; or the chunks themselves, an
        iterable of (first frame, `Detections`) (e.g. from `mvpose_jax.data.RecordingStream.chunks`:
        then only one chunk is in memory at a time).
      config: what each stage does (`PipelineConfig`). Proposals (``config.matching``) run on
        the matcher's cameras (``matcher.rig.names``) if there is a matcher, else on every
        camera; "combined" (the default with a matcher) and "gat" need one, "epipolar" (the
        default without) does not. The 3D method (``config.lifting.method``; default "mlp" with
        an estimator, else "dlt") runs on the estimator's inference cameras (a subset of the
        proposal cameras) if it needs an estimator; a triangulation ignores the estimator.
      matcher, estimator: trained models (`trained.load_matcher`, `trained.load_estimator`).
      layout: the keypoints' layout (method "blend": where the legs are).
      fps: frames per second (the tracker's and the filter's clock: frame i is at i / fps).
      progress: show a progress bar.
      num_frames: frames the chunks hold in all (the progress bar's length) when ``detections``
        is an iterable of chunks; default: unknown.
      first_track_id: the first new track's id (a resumed stream continues after the ids it gave).
    Raises:
      InputError: detections whose cameras or keypoints do not fit the rig or the models
        (checked before the first chunk of a whole recording, on each chunk of an iterable).
      ValueError: a stage name that is not registered, or a stage without the model it needs.
    """
    mode = config.matching.mode(matcher is not None)
    stage = stages.lookup("proposals", mode)
    if stage.needs_matcher and matcher is None:
        raise ValueError(f"proposals {mode!r} need a matcher")
    propose = stage.function()
    prop_cams = tuple(matcher.rig.names) if matcher is not None else tuple(rig.names)
    prop_idx = _camera_columns(rig.names, prop_cams, "the matcher's")
    prop_rig = rig.select(list(prop_cams))
    method = check_method(config.lifting.method, estimator)
    if stages.lookup("lifting", method).needs_estimator:
        _camera_columns(prop_cams, estimator.rig_infer.names, "the estimator's inference")
    else:
        estimator = None  # a triangulation: the estimator is neither checked nor used

    if config.association is not None and config.tracking is None:
        raise InputError("track-level association needs tracking", field="association")
    temporal = None
    if config.temporal is not None:
        if config.tracking is None:
            raise InputError(
                "the temporal stage refines tracks: it needs tracking", field="temporal"
            )
        temporal = for_rig(cached_temporal(str(config.temporal)), prop_rig)

    checked_keypoints: list[int] = []

    def check(det: Detections) -> None:
        _, num_cameras, _, K = np.shape(det.score)
        if num_cameras != rig.num_cameras:
            raise InputError(
                f"detections have {num_cameras} cameras, the rig {rig.num_cameras}",
                field="cameras",
            )
        if checked_keypoints == [K]:
            return  # the models' keypoint counts cost a model merge: checked once
        for what, model in (("matcher", matcher), ("estimator", estimator)):
            if model is not None and (trained_on := _model_keypoints(model)) != K:
                raise InputError(
                    f"the {what} was trained on {trained_on} keypoints, the detections have {K} "
                    "(convert the layout)",
                    field="keypoints",
                )
        checked_keypoints[:] = [K]

    if isinstance(detections, Detections):
        check(detections)
        chunks = _chunks_of(detections, config.chunk_frames)
        num_frames = len(detections.count)
    else:
        chunks = iter(detections)
    tracker, smoother = None, None  # made at the first chunk, which tells K
    bar = progress_bar(
        total=num_frames, desc="pipeline", unit="frame", disable=not progress, dynamic_ncols=True
    )
    try:
        for start, chunk in chunks:
            check(chunk)
            det = _padded_skeletons(
                Detections(
                    np.asarray(chunk.xy, np.float32)[:, prop_idx],
                    np.asarray(chunk.score, np.float32)[:, prop_idx],
                    np.asarray(chunk.count)[:, prop_idx],
                )
            )
            num_skeletons = np.shape(chunk.score)[2]
            stop = start + len(det.count)
            t0 = time.perf_counter()
            grouped = propose(prop_rig, det, config.matching, matcher=matcher)
            members = _members_table(grouped, stop - start, len(prop_cams))
            t1 = time.perf_counter()

            def lift(members, det=det):
                poses, conf = poses_of_members(
                    prop_rig,
                    det,
                    members,
                    estimator=estimator,
                    method=method,
                    min_views=config.matching.min_views,
                    outlier_px=config.lifting.outlier_px,
                    view_outlier_px=config.lifting.view_outlier_px,
                    layout=layout,
                    max_spread_m=config.lifting.max_spread_m,
                    confidence=config.lifting.confidence,
                )
                # A person is kept only where the 3D stage produced one; its members say so.
                members = np.where(poses.valid[..., None], members, -1).astype(np.int32)
                return poses, conf, members

            poses, conf, members = lift(members)
            t2 = time.perf_counter()
            seconds, track = {"proposals": t1 - t0, "poses": t2 - t1}, None
            if config.tracking is not None:
                if tracker is None:
                    K = np.shape(det.score)[3]
                    tracker = dataclasses.replace(
                        tracker_initial_state(K, len(prop_cams)), next_id=first_track_id
                    )
                    smoother = one_euro_initial(K)
                before = (tracker, smoother)
                tracker, smoother, track, poses = _track_chunk(
                    *before, det, members, poses, start, fps, prop_rig, config
                )
                if config.association is not None:
                    # Track-level association: the skeletons regrouped by the tracked people
                    # they fit, then lifted and tracked again from the same tracker state.
                    regrouped = _regrouped(
                        before[0], det, members, poses, track, start, fps, prop_rig, config
                    )
                    if regrouped is not None:
                        poses, conf, members = lift(regrouped)
                        tracker, smoother, track, poses = _track_chunk(
                            *before, det, members, poses, start, fps, prop_rig, config
                        )
                seconds["tracking"] = time.perf_counter() - t2
                if temporal is not None:
                    t3 = time.perf_counter()
                    poses = _temporal_chunk(temporal, prop_rig, det, members, poses, track, config)
                    seconds["temporal"] = time.perf_counter() - t3
            identity = _identity_from_members(
                members, (stop - start, len(prop_cams), num_skeletons)
            )
            yield (
                start,
                PipelineResult(poses, conf, members, identity, prop_cams, seconds, track),
            )
            bar.update(stop - start)
    finally:
        bar.close()


def _track_chunk(tracker, smoother, det, members, poses, start, fps, rig, config: PipelineConfig):
    """Tracks (and, with a streaming filter, filters) one chunk: (tracker, smoother, track,
    poses)."""
    xy, score = group_people(det.xy, det.score, members)
    times = (start + np.arange(len(members))) / fps
    kv = np.asarray(poses.keypoint_valid)
    tracker, track = track_frames(
        tracker,
        times=times,
        xyz=poses.xyz,
        keypoint_valid=kv,
        valid=poses.valid,
        xy=xy,
        score=score,
        rig=rig,
        config=config.tracking,
    )
    if config.filtering.streaming:
        smoother, xyz = one_euro_frames(
            smoother,
            times=times,
            track=track,
            xyz=poses.xyz,
            keypoint_valid=kv,
            config=config.filtering.one_euro,
        )
        smoother = one_euro_keep(smoother, tracker.ids)
        poses = poses._replace(xyz=np.where(kv[..., None], xyz, poses.xyz).astype(np.float32))
    return tracker, smoother, track, poses


def _regrouped(tracker, det, members, poses, track, start, fps, rig, config: PipelineConfig):
    """The chunk's skeletons grouped by the tracked people they fit (`tracking.track_anchors`,
    `tracking.associate_skeletons`, `tracking.regroup`); None where that changes nothing."""
    times = (start + np.arange(len(members))) / fps
    anchor_xyz, anchor_ok = track_anchors(
        tracker,
        times=times,
        track=track,
        valid=poses.valid,
        xyz=poses.xyz,
        keypoint_valid=poses.keypoint_valid,
        config=config.tracking,
        association=config.association,
    )
    owner = associate_skeletons(rig, det.xy, det.score, anchor_xyz, anchor_ok, config.association)
    if not (owner >= 0).any():
        return None
    regrouped = regroup(members, owner, anchor_xyz.shape[1])
    return None if _same_groups(members, regrouped) else regrouped


def _same_groups(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two (F, G, C) person tables hold the same people in every frame (in any slot
    order; empty slots ignored)."""

    def people(m: np.ndarray) -> np.ndarray:
        f, g = np.nonzero((m >= 0).any(-1))
        rows = np.concatenate([f[:, None], m[f, g]], axis=1)
        return rows[np.lexsort(rows.T[::-1])]

    pa, pb = people(np.asarray(a)), people(np.asarray(b))
    return pa.shape == pb.shape and bool((pa == pb).all())


def _temporal_chunk(model, rig, det, members, poses, track, config: PipelineConfig) -> Poses3D:
    """One chunk's tracked people refined by the temporal model: every keypoint of each person
    (robust triangulation where it reconstructs one, the model elsewhere)."""
    xy, score = group_people(det.xy, det.score, members)
    valid = np.asarray(poses.valid, bool)
    if not valid.any():
        return poses
    xyz, _ = refine_tracks(
        model,
        rig,
        xy,
        score,
        track,
        valid,
        method="blend",
        outlier_px=config.lifting.outlier_px,
        view_outlier_px=config.lifting.view_outlier_px,
    )
    return Poses3D(
        np.where(valid[..., None, None], xyz, poses.xyz).astype(np.float32),
        poses.valid,
        np.asarray(poses.keypoint_valid, bool) | valid[..., None],
    )


def _padded_skeletons(det: Detections) -> Detections:
    """``det`` with its skeleton axis zero-padded to `skeleton_slots` (counts unchanged)."""
    F, C, P, K = np.shape(det.score)
    slots = skeleton_slots(P)
    if slots == P:
        return det
    return Detections(
        zero_padded(det.xy, (F, C, slots, K, 2)),
        zero_padded(det.score, (F, C, slots, K)),
        det.count,
    )


def _chunks_of(detections: Detections, chunk_frames: int) -> Iterator[tuple[int, Detections]]:
    """A whole recording's detections as (first frame, chunk) pairs."""
    xy = np.asarray(detections.xy, np.float32)
    score = np.asarray(detections.score, np.float32)
    count = np.asarray(detections.count)
    for start in range(0, len(count), chunk_frames):
        stop = start + chunk_frames
        yield start, Detections(xy[start:stop], score[start:stop], count[start:stop])


def run_pipeline(
    rig: Rig,
    detections: Detections,
    config: PipelineConfig | None = None,
    *,
    matcher: Matcher | None = None,
    estimator: Estimator | None = None,
    layout: str = "coco18",
    fps: float = 30.0,
    progress: bool = False,
    **settings,
) -> PipelineResult:
    """`stream_pipeline` over a whole recording, its chunks joined (people padded to the most in
    any frame). ``settings``: instead of ``config``, the stages' settings by name
    (`PipelineConfig.of`)."""
    if settings:
        if config is not None:
            raise TypeError("give a config or its settings, not both")
        config = PipelineConfig.of(**settings)
    config = config or PipelineConfig()
    parts = [
        r
        for _, r in stream_pipeline(
            rig,
            detections,
            config,
            matcher=matcher,
            estimator=estimator,
            layout=layout,
            fps=fps,
            progress=progress,
        )
    ]
    if not parts:
        F, C, P, K = np.shape(detections.score)
        cams = tuple(matcher.rig.names) if matcher is not None else tuple(rig.names)
        return PipelineResult(
            Poses3D(
                np.zeros((0, 1, K, 3), np.float32),
                np.zeros((0, 1), bool),
                np.zeros((0, 1, K), bool),
            ),
            np.zeros((0, 1), np.float32),
            np.zeros((0, 1, len(cams)), np.int32),
            np.zeros((0, len(cams), P), np.int32),
            cams,
            {"proposals": 0.0, "poses": 0.0},
            np.zeros((0, 1), np.int32) if config.tracking is not None else None,
        )
    return concat_results(parts)


def concat_results(parts: Sequence[PipelineResult]) -> PipelineResult:
    """Joins consecutive chunks' results along the frame axis (people padded to the largest G,
    skeletons of ``identity`` to the largest P)."""
    G = max(1, max(r.poses.valid.shape[1] for r in parts))
    P = max(np.shape(r.identity)[2] for r in parts)

    def pad(a, fill=0):
        a = np.asarray(a)
        return np.pad(
            a, [(0, 0), (0, G - a.shape[1])] + [(0, 0)] * (a.ndim - 2), constant_values=fill
        )

    cat = lambda get, fill=0: np.concatenate([pad(get(r), fill) for r in parts])  # noqa: E731
    poses = Poses3D(
        cat(lambda r: r.poses.xyz),
        cat(lambda r: r.poses.valid),
        cat(lambda r: r.poses.keypoint_valid),
    )
    seconds = {k: float(sum(r.seconds[k] for r in parts)) for k in parts[0].seconds}
    tracked = all(r.track is not None for r in parts)
    return PipelineResult(
        poses,
        cat(lambda r: r.confidence),
        cat(lambda r: r.members, -1),
        # Chunks read in ranges may differ in P (the most skeletons in a view of the range).
        np.concatenate([_pad_skeletons(r.identity, P) for r in parts]),
        parts[0].cameras,
        seconds,
        cat(lambda r: r.track, -1) if tracked else None,
    )


def _pad_skeletons(identity: np.ndarray, num_skeletons: int) -> np.ndarray:
    """(F, C, P) identity padded with -1 to P = ``num_skeletons``."""
    identity = np.asarray(identity)
    pad = num_skeletons - identity.shape[2]
    return np.pad(identity, [(0, 0), (0, 0), (0, pad)], constant_values=-1)


# Models' keypoint counts by GraphDef (a static attribute of the model: equal GraphDefs, equal
# counts). Merging a model to read it costs about 1 ms, as much as a live frame: a stream of
# one-frame chunks (`stream_pipeline` per live session) would pay it at every start.
_KEYPOINTS_BY_GRAPHDEF: dict[int, tuple[Any, int]] = {}


def _model_keypoints(model: Estimator | Matcher) -> int:
    return kept_per_object(
        _KEYPOINTS_BY_GRAPHDEF,
        model.graphdef,
        lambda: nnx.merge(model.graphdef, model.params, model.rest).num_keypoints,
        max_entries=256,
    )


def _members_table(proposals: Proposals, num_frames: int, num_cameras: int) -> np.ndarray:
    """`Proposals.people` (per frame, ragged) as one (F, G, C) table, -1 padded."""
    G = max([1] + [len(p) for p in proposals.people])
    table = np.full((num_frames, G, num_cameras), -1, np.int32)
    for f, people in enumerate(proposals.people):
        table[f, : len(people)] = people
    return table


def _identity_from_members(members: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """(F, G, C) members -> (F, C, P) person of each skeleton (-1 none)."""
    identity = np.full(shape, -1, np.int32)
    f, g, c = np.nonzero(members >= 0)
    identity[f, c, members[f, g, c]] = g
    return identity
