"""A label-free score of any 3D result: how well it agrees with the 2D detections it came from.

Users have no 3D labels; what they have is the detections of every camera. For each camera c the
score compares c's own skeletons with two things (issue 36):

* **the result** (`LabelFreeReport.result`): the result's own 3D keypoints projected into c. This
  scores the method. It is not held out (the method may have used c), which any result allows:
  the method cannot be re-run without c. A keypoint c shows (score above
  ``LabelFreeConfig.visible_score``) of a person the result contains but that the result does not
  produce is a MISS: it counts in the denominator of ``share_within_px`` and never as within, so
  abstaining never scores better than guessing (a per-method score that skipped missing keypoints
  rewarded abstaining on real footage).
* **leave-one-camera-out re-triangulation** (`LabelFreeReport.leave_one_out`): each person's
  keypoints triangulated from the OTHER cameras' skeletons of the same person (the result's
  grouping, ``members``), projected into c. This is a reference: it scores the grouping and the
  detectors' agreement, the same for every 3D method on one grouping.

Read ``share_of_all_within_px["20"]`` first: the share of every keypoint of every skeleton of every
camera that the result's projection puts within 20 px. Its denominator is the same for every
result on the same detections, so leaving out a keypoint or a whole person never helps; the
matched-people shares cannot see a person the result leaves out (on synthetic scenes,
``experiments/label_free_synthetic.py``, it was the number that ranked variants most as PCP does).

Keypoints seen by fewer than two other views have no held-out re-triangulation (they are
`Agreement.blind` of ``leave_one_out``); a keypoint only one camera shows of a person is
unverifiable in the result's own projection too (any point on that camera's ray reprojects onto
it) and is scored as not produced (``result``'s `Agreement.blind`); see `BLIND_SPOTS`. `reference_reprojection` projects a reference (the ground
truth where one exists) the same way: the detections' own spread around it, the noise floor below
which differences measure agreement with the detector, not with the truth.

Besides: bone-length spread per track, jitter (acceleration), people per frame against the views'
detections, and track fragments. `write_label_free_report` writes the JSON and one figure.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mvpose_jax.cameras import Rig, point_depths, project_points, project_points_per_camera
from mvpose_jax.data.files import atomic_write_text, to_jsonable
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.data.recording import recording_fps
from mvpose_jax.errors import InputError
from mvpose_jax.lifting import TRIANGULATION_METHODS, group_people, triangulate_people
from mvpose_jax.metrics import jitter, track_major
from mvpose_jax.skeletons import Detections, get_layout
from mvpose_jax.triangulate import OUTLIER_PX, VIEW_OUTLIER_PX

BLIND_SPOTS = (
    "A keypoint that camera c shows but fewer than two OTHER cameras' skeletons of the same "
    "person show has no leave-one-out re-triangulation: it is counted in leave_one_out.blind "
    "and left out of leave_one_out's pixel numbers.",
    "The result's own projection is compared wherever the result has the keypoint and a second "
    "camera shows it for the same person; where the result lacks a keypoint that camera c "
    "shows, it is a miss (in the denominator of share_within_px, never within), counted only "
    "where camera c sees it.",
    "A keypoint only one camera shows of a person (and every keypoint of a person one camera "
    "alone sees) is unverifiable: any point on that camera's ray lands on its skeleton, so a "
    "result that produces it is scored as one that does not (counted in result.blind, in the "
    "denominator, never within, left out of the pixel numbers). Geometry cannot produce it, a "
    "learned 3D stage can; the score neither rewards nor penalises that guess.",
    "The result's projection into c is not held out: the method may have used c's skeleton, so "
    "the score measures agreement with the detections, and a method that copies a detector's "
    "error is not penalised for it. Differences below noise_floor (the detections' own spread "
    "around a reference) measure agreement with the detector, not with the truth.",
    "Skeletons of c that belong to no person of the result are counted (unmatched_skeletons), "
    "not scored: some are false positives. share_of_all_within_px divides by every keypoint of "
    "every skeleton, the same denominator for every result on the same detections.",
    "A person nobody detected in any view, and a keypoint no camera shows, are invisible to "
    "this score.",
)


@dataclasses.dataclass(frozen=True)
class LabelFreeConfig:
    """The score's settings.

    Attributes:
      thresholds_px: the pixel radii of ``share_within_px``.
      visible_score: a detected keypoint counts as shown by its camera when its score exceeds
        this.
      method: the leave-one-out triangulation, one of `lifting.TRIANGULATION_METHODS`.
      outlier_px, view_outlier_px: robust triangulation's thresholds (method "robust").
      short_track_frames: a track with fewer frames than this is a fragment.
      min_bone_frames: a bone's length spread needs this many frames with both ends.
    """

    thresholds_px: tuple[float, ...] = (10.0, 20.0)
    visible_score: float = 0.0
    method: str = "robust"
    outlier_px: float = OUTLIER_PX
    view_outlier_px: float = VIEW_OUTLIER_PX
    short_track_frames: int = 10
    min_bone_frames: int = 3


@dataclasses.dataclass(frozen=True)
class Agreement:
    """Pixel agreement of projected 3D keypoints with one camera's (or all cameras') skeletons.

    Attributes:
      visible: keypoints the camera shows of the people scored (the denominator).
      produced: of those, how many have a projection that can be checked (the result has them
        and a second camera shows them for the person; for the leave-one-out reference: two or
        more other views triangulated them).
      blind: visible keypoints nothing can check: for the result, those only this one camera
        shows of the person (unverifiable, never produced); for leave-one-out, those fewer
        than two other views show.
      coverage: produced / visible.
      median_px: median distance over the produced ones (NaN: none).
      share_within_px: {radius: share of ALL visible keypoints projected within it}; a keypoint
        not produced is never within.
    """

    visible: int
    produced: int
    blind: int
    coverage: float
    median_px: float
    share_within_px: dict[str, float]


@dataclasses.dataclass(frozen=True)
class CameraTables:
    """One comparison pooled, per camera and per keypoint.

    Attributes:
      overall: all cameras and keypoints pooled.
      by_camera: {camera name: Agreement}.
      by_keypoint: {keypoint name: Agreement}.
      share_by_camera_keypoint: {radius: (C, K) nested lists of share_within (NaN: nothing
        visible)}.
    """

    overall: Agreement
    by_camera: dict[str, Agreement]
    by_keypoint: dict[str, Agreement]
    share_by_camera_keypoint: dict[str, list[list[float]]]


@dataclasses.dataclass(frozen=True)
class BoneSpread:
    """Bone-length spread per track: coefficient of variation (population std / mean) of each
    bone's length over the track's frames, median over the bones with ``min_bone_frames``.

    Attributes:
      median_cv: median over tracks (NaN: no track has a bone measured often enough).
      by_track: {track id: its median CV}.
    """

    median_cv: float
    by_track: dict[str, float]


@dataclasses.dataclass(frozen=True)
class PeopleCount:
    """People per frame of the result against the views' skeletons (false positives included).

    Attributes:
      mean_result: mean people per frame in the result.
      mean_most_in_a_view, mean_median_of_views: means over frames of the largest and of the
        median skeleton count of the views.
      mean_abs_diff_most, mean_abs_diff_median: mean |result - that count| over frames.
    """

    mean_result: float
    mean_most_in_a_view: float
    mean_median_of_views: float
    mean_abs_diff_most: float
    mean_abs_diff_median: float


@dataclasses.dataclass(frozen=True)
class TrackFragments:
    """Tracks of the result: how many, how long (frames with the person), how many short ones."""

    num_tracks: int
    mean_length_frames: float
    short_tracks: int
    short_track_frames: int


@dataclasses.dataclass(frozen=True)
class LabelFreeReport:
    """The label-free score of one result (see the module docstring).

    Attributes:
      layout, cameras, keypoints, frames: what was scored.
      result: the result's 3D projected into each camera (scores the method; misses counted).
      leave_one_out: re-triangulation from the other views (the grouping's reference).
      share_of_all_within_px: {radius: share of every visible keypoint of every skeleton of
        every camera that the result's projection puts within it} (one denominator for all
        results on the same detections; unmatched skeletons count as not within).
      unmatched_skeletons: {camera: skeletons (with a visible keypoint) of no person}.
      bone_spread, jitter_m_s2, tracks: None without tracks. jitter_m_s2: mean acceleration
        magnitude of tracked keypoints over three consecutive frames, m/s² (NaN: none).
      people_count: per-frame people against the views' skeletons.
      fps: frames per second the jitter used (from the timestamps, 30 without).
      noise_floor: the detections' spread around a reference (`reference_reprojection`), or None.
      blind_spots: what the score cannot see and how it treats it (`BLIND_SPOTS`).
      config: the settings.
    """

    layout: str
    cameras: tuple[str, ...]
    keypoints: tuple[str, ...]
    frames: int
    result: CameraTables
    leave_one_out: CameraTables
    share_of_all_within_px: dict[str, float]
    unmatched_skeletons: dict[str, int]
    bone_spread: BoneSpread | None
    jitter_m_s2: float | None
    people_count: PeopleCount
    tracks: TrackFragments | None
    fps: float
    noise_floor: CameraTables | None
    blind_spots: tuple[str, ...]
    config: LabelFreeConfig

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able values (NaN as None)."""
        return _nan_as_none(to_jsonable(dataclasses.asdict(self)))


def label_free_score(
    poses: PoseResults,
    rig: Rig,
    detections: Detections,
    *,
    layout: str,
    config: LabelFreeConfig = LabelFreeConfig(),
    noise_floor: CameraTables | None = None,
) -> LabelFreeReport:
    """Scores a 3D result against the detections it was built from, without 3D labels.

    Args:
      poses: the result: xyz (F, G, K, 3) metres, members (F, G, C), identity (F, C, P'), on the
        cameras ``poses.cameras``; track and timestamps optional.
      rig: a rig holding ``poses.cameras`` (by name; it may hold more).
      detections: xy (F, C, P, K, 2), score (F, C, P, K), count (F, C), the camera axis in the
        order of ``poses.cameras``.
      layout: the keypoints' layout (names and bones).
      config: the score's settings.
      noise_floor: a `reference_reprojection` to state with the report.
    Returns:
      A `LabelFreeReport`.
    Raises:
      InputError: detections that do not fit the result (frames, cameras, people, keypoints),
        or an unknown leave-one-out method.
    """
    if config.method not in TRIANGULATION_METHODS:
        raise InputError(
            f"leave-one-out method must be one of {TRIANGULATION_METHODS}", field="method"
        )
    lay = get_layout(layout)
    cams = tuple(poses.cameras)
    sub = rig.select(cams)
    xy, score, count = _checked_detections(detections, poses, lay.num_keypoints)
    visible = score > config.visible_score  # (F, C, P, K)
    xyz = np.asarray(poses.poses.xyz, np.float64)
    exists = np.asarray(poses.poses.valid, bool)
    kv = np.asarray(poses.poses.keypoint_valid, bool) & exists[..., None]
    members = np.where(exists[..., None], np.asarray(poses.members), -1)  # (F, G, C)

    # The result's 3D in each camera, per person: (C, F, G, K, 2) and its depth (C, F, G, K).
    projected = np.asarray(project_points(sub, xyz), np.float64)
    in_front = np.asarray(point_depths(sub, xyz)) > 0
    g_xy, g_score = group_people(xy, score, members)  # (F, G, C, K, 2), (F, G, C, K)
    g_vis = g_score > config.visible_score
    # A keypoint only camera c shows of a person can be put anywhere on c's ray and still land
    # on c's skeleton (a one-view lift reprojects at 0 px by construction): unverifiable, so it
    # is scored as not produced, never within, like a keypoint the result lacks.
    unverifiable = np.moveaxis(g_vis, 2, 0) & (g_vis.sum(axis=2) == 1)[None]  # (C, F, G, K)
    result_err = np.where(
        unverifiable, np.nan, _distances(projected, in_front, kv[None], g_xy, g_vis)
    )

    loo_xyz, loo_ok = _leave_one_out(sub, g_xy, np.where(g_vis, g_score, 0.0), exists, config)
    loo_proj = np.asarray(project_points_per_camera(sub, loo_xyz), np.float64)
    loo_depth = (
        np.einsum("cj,c...j->c...", np.asarray(sub.R)[:, 2], loo_xyz)
        + np.asarray(sub.t)[:, 2, None, None, None]
    )
    loo_err = _distances(loo_proj, loo_depth > 0, loo_ok, g_xy, g_vis)
    blind = np.moveaxis(g_vis, 2, 0) & ~loo_ok  # (C, F, G, K)

    scored = np.moveaxis(g_vis, 2, 0)  # (C, F, G, K) visible keypoints of the result's people
    thresholds = config.thresholds_px
    tables = _tables(result_err, scored, unverifiable, cams, lay.keypoints, thresholds)
    loo = _tables(loo_err, scored, blind, cams, lay.keypoints, thresholds)

    # Every visible keypoint of every skeleton: the result's people's hits over all of them.
    total_visible = int(visible.sum())
    hits = {
        _key(r): float(((result_err <= r) & scored).sum()) / max(total_visible, 1)
        for r in thresholds
    }
    assigned = np.zeros(visible.shape[:3], bool)  # (F, C, P) skeletons some person holds
    f, g, c = np.nonzero(members >= 0)
    assigned[f, c, members[f, g, c]] = True
    shown = visible.any(-1)
    unmatched = {cam: int((shown & ~assigned)[:, i].sum()) for i, cam in enumerate(cams)}

    fps = recording_fps(poses.timestamps)
    tracked = poses.track is not None
    return LabelFreeReport(
        layout=lay.name,
        cameras=cams,
        keypoints=lay.keypoints,
        frames=int(exists.shape[0]),
        result=tables,
        leave_one_out=loo,
        share_of_all_within_px=hits,
        unmatched_skeletons=unmatched,
        bone_spread=bone_spread(
            xyz, kv, exists, poses.track, lay.bones, min_frames=config.min_bone_frames
        )
        if tracked
        else None,
        jitter_m_s2=track_jitter(xyz, kv, exists, poses.track, fps) if tracked else None,
        people_count=people_count(exists, count),
        tracks=track_fragments(exists, poses.track, config.short_track_frames) if tracked else None,
        fps=fps,
        noise_floor=noise_floor,
        blind_spots=BLIND_SPOTS,
        config=config,
    )


def reference_reprojection(
    truth_xyz: np.ndarray,
    truth_valid: np.ndarray,
    rig: Rig,
    detections: Detections,
    identity: np.ndarray,
    *,
    cameras: Sequence[str] | None = None,
    layout: str = "coco18",
    config: LabelFreeConfig = LabelFreeConfig(),
) -> CameraTables:
    """The detections' spread around a reference: the noise floor of the label-free score.

    Each skeleton of a known person is compared with that person's reference keypoints
    projected into its camera, as `label_free_score` compares a result (a reference keypoint
    missing where the camera shows one is a miss).

    Args:
      truth_xyz: (F, H, K, 3) reference keypoints, metres (e.g. the ground truth).
      truth_valid: (F, H, K) which exist.
      rig: a rig holding ``cameras``.
      detections: xy (F, C, P, K, 2), score (F, C, P, K), the camera axis ``cameras``' order.
      identity: (F, C, P) each skeleton's reference person (0..H-1), -1 none.
      cameras: the detections' camera names (default: ``rig.names``).
      layout: the keypoints' layout.
    Returns:
      `CameraTables` (no leave-one-out: ``blind`` is 0).
    """
    cams = tuple(rig.names if cameras is None else cameras)
    sub = rig.select(cams)
    lay = get_layout(layout)
    xy = np.asarray(detections.xy, np.float64)
    score = np.asarray(detections.score)
    identity = np.asarray(identity)
    F, C, P, K = score.shape
    if identity.shape[:2] != (F, C) or identity.shape[2] > P:
        raise InputError(f"shape {identity.shape}, expected ({F}, {C}, <= {P})", field="identity")
    identity = np.pad(identity, [(0, 0), (0, 0), (0, P - identity.shape[2])], constant_values=-1)
    truth_xyz = np.asarray(truth_xyz, np.float64)
    truth_valid = np.asarray(truth_valid, bool)
    members = np.full((F, truth_xyz.shape[1], C), -1, np.int64)
    f, c, p = np.nonzero(identity >= 0)
    members[f, identity[f, c, p], c] = p
    projected = np.asarray(project_points(sub, truth_xyz), np.float64)
    in_front = np.asarray(point_depths(sub, truth_xyz)) > 0
    g_xy, g_score = group_people(xy, score, members)
    g_vis = g_score > config.visible_score
    err = _distances(projected, in_front, truth_valid[None], g_xy, g_vis)
    scored = np.moveaxis(g_vis, 2, 0)
    return _tables(err, scored, np.zeros_like(scored), cams, lay.keypoints, config.thresholds_px)


def bone_spread(
    xyz: np.ndarray,
    keypoint_valid: np.ndarray,
    valid: np.ndarray,
    track: np.ndarray,
    bones: Sequence[tuple[int, int]],
    *,
    min_frames: int = 3,
) -> BoneSpread:
    """Coefficient of variation of each bone's length along each track (see `BoneSpread`).

    Args:
      xyz: (F, G, K, 3) metres; keypoint_valid: (F, G, K); valid: (F, G); track: (F, G), -1 none.
      bones: keypoint index pairs (the layout's ``bones``).
      min_frames: frames with both ends a bone needs to count.
    """
    ids, series, mask = track_major(xyz, keypoint_valid, valid, track)  # (T,), (T,F,K,3), (T,F,K)
    a, b = np.asarray(bones).T
    length = np.linalg.norm(series[:, :, a] - series[:, :, b], axis=-1)  # (T, F, B)
    both = mask[:, :, a] & mask[:, :, b]
    n = both.sum(1)  # (T, B)
    mean = np.where(both, length, 0).sum(1) / np.maximum(n, 1)
    var = np.where(both, (length - mean[:, None]) ** 2, 0).sum(1) / np.maximum(n, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cv = np.where((n >= min_frames) & (mean > 0), np.sqrt(var) / mean, np.nan)
    by_track = {}
    for t, row in zip(ids, cv, strict=True):
        if np.isfinite(row).any():
            by_track[str(int(t))] = float(np.nanmedian(row))
    values = list(by_track.values())
    return BoneSpread(float(np.median(values)) if values else math.nan, by_track)


def track_jitter(
    xyz: np.ndarray, keypoint_valid: np.ndarray, valid: np.ndarray, track: np.ndarray, fps: float
) -> float:
    """Mean acceleration magnitude of tracked keypoints, m/s² (`metrics.jitter`'s second
    difference over three consecutive frames with the keypoint, times fps²); NaN: none."""
    return jitter(xyz, keypoint_valid, valid, track) / 1000.0 * fps**2


def people_count(valid: np.ndarray, count: np.ndarray) -> PeopleCount:
    """People per frame (valid (F, G)) against the views' skeleton counts (count (F, C))."""
    people = np.asarray(valid, bool).sum(-1).astype(np.float64)
    count = np.asarray(count, np.float64)
    most, median = count.max(-1), np.median(count, axis=-1)
    if len(people) == 0:
        return PeopleCount(*([math.nan] * 5))
    return PeopleCount(
        float(people.mean()),
        float(most.mean()),
        float(median.mean()),
        float(np.abs(people - most).mean()),
        float(np.abs(people - median).mean()),
    )


def track_fragments(valid: np.ndarray, track: np.ndarray, short_frames: int = 10) -> TrackFragments:
    """Tracks (track (F, G), -1 none; valid (F, G)): their count, mean length and short ones."""
    ids = np.asarray(track)[np.asarray(valid, bool) & (np.asarray(track) >= 0)]
    _, lengths = np.unique(ids, return_counts=True)
    return TrackFragments(
        int(len(lengths)),
        float(lengths.mean()) if len(lengths) else math.nan,
        int((lengths < short_frames).sum()),
        short_frames,
    )


def write_label_free_report(report: LabelFreeReport, out: str | os.PathLike) -> tuple[Path, Path]:
    """Writes the report as JSON and its figure (atomically); returns (JSON path, PNG path).

    ``out``: a folder (``out/label_free.json`` and ``out/label_free.png``) or a ``.json`` file
    (the figure beside it, the same name ending ``.png``).

    The figure: the share of each camera's keypoints the result puts within the largest radius
    (a heatmap, cameras by keypoints) and each track's bone-length spread.
    """
    import json

    from mvpose_jax.render import save_figure

    out = Path(out)
    if out.suffix.lower() == ".json":
        json_path, png_path = out, out.with_suffix(".png")
    else:
        json_path, png_path = out / "label_free.json", out / "label_free.png"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(json_path, json.dumps(report.to_dict(), indent=1, allow_nan=False) + "\n")
    return json_path, save_figure(_figure(report), png_path)


# ------------------------------------------------------------------------------- internals


def _key(radius: float) -> str:
    return f"{radius:g}"


def _checked_detections(detections: Detections, poses: PoseResults, num_keypoints: int):
    score = np.asarray(detections.score)
    xy = np.asarray(detections.xy, np.float64)
    F = np.shape(poses.poses.valid)[0]
    C = len(poses.cameras)
    if score.ndim != 4 or score.shape[:2] != (F, C) or score.shape[3] != num_keypoints:
        raise InputError(
            f"detections of shape {score.shape}, expected ({F}, {C}, P, {num_keypoints}): "
            f"the result's frames, its cameras {list(poses.cameras)} and the layout's keypoints",
            field="score",
        )
    P = score.shape[2]
    members = np.asarray(poses.members)
    if members.size and members.max() >= P:
        raise InputError(f"a person holds skeleton {members.max()} of {P}", field="members")
    bad = ~np.isfinite(xy).all(-1) & (score > 0)
    if bad.any():
        f, c, _, _ = np.argwhere(bad)[0]
        raise InputError(
            "a detected keypoint is not finite", frame=int(f), camera=poses.cameras[c], field="xy"
        )
    return xy, score, np.asarray(detections.count)


def _distances(projected, in_front, produced, g_xy, g_vis) -> np.ndarray:
    """Pixel distances (C, F, G, K) between projections (C, F, G, K, 2) and each person's
    skeletons g_xy (F, G, C, K, 2); inf where the projection is missing, behind the camera or
    the camera does not show the keypoint."""
    det = np.moveaxis(g_xy, 2, 0)
    vis = np.moveaxis(g_vis, 2, 0)
    d = np.linalg.norm(projected - det, axis=-1)
    ok = produced & in_front & vis & np.isfinite(d)
    return np.where(ok, d, np.inf)


def _leave_one_out(rig: Rig, g_xy, g_weight, exists, config: LabelFreeConfig):
    """Each person's keypoints triangulated without each camera in turn.

    Returns xyz (C, F, G, K, 3) and valid (C, F, G, K) (two or more other views)."""
    F, G, C, K = g_weight.shape
    xyz = np.zeros((C, F, G, K, 3))
    ok = np.zeros((C, F, G, K), bool)
    if not exists.any():
        return xyz, ok
    xy_n, w_n = g_xy[exists], g_weight[exists]  # (N, C, K, 2), (N, C, K)
    for c in range(C):
        w = w_n.copy()
        w[:, c] = 0.0
        # Only people another two views see: the rest cannot be triangulated anyway.
        some = (w > 0).any(-1).sum(-1) >= 2
        if not some.any():
            continue
        robust = {}
        if config.method == "robust":
            robust = {"outlier_px": config.outlier_px, "view_outlier_px": config.view_outlier_px}
        p, v = triangulate_people(rig, xy_n[some], w[some], config.method, **robust)
        full_p = np.zeros((len(w), K, 3))
        full_v = np.zeros((len(w), K), bool)
        full_p[some], full_v[some] = p, v & np.isfinite(p).all(-1)
        xyz[c][exists], ok[c][exists] = full_p, full_v
    return xyz, ok


def _agreement(err: np.ndarray, scored: np.ndarray, blind: np.ndarray, thresholds) -> Agreement:
    visible = int(scored.sum())
    e = err[scored]
    produced = e[np.isfinite(e)]
    return Agreement(
        visible=visible,
        produced=int(produced.size),
        blind=int((blind & scored).sum()),
        coverage=produced.size / visible if visible else math.nan,
        median_px=float(np.median(produced)) if produced.size else math.nan,
        share_within_px={
            _key(r): float((produced <= r).sum()) / visible if visible else math.nan
            for r in thresholds
        },
    )


def _tables(err, scored, blind, cameras, keypoints, thresholds) -> CameraTables:
    """err, scored, blind: (C, F, G, K)."""
    C, K = len(cameras), len(keypoints)
    by_cam = {c: _agreement(err[i], scored[i], blind[i], thresholds) for i, c in enumerate(cameras)}
    by_kp = {
        k: _agreement(err[..., j], scored[..., j], blind[..., j], thresholds)
        for j, k in enumerate(keypoints)
    }
    grid = {}
    for r in thresholds:
        hit = ((err <= r) & scored).sum(axis=(1, 2))  # (C, K)
        n = scored.sum(axis=(1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            grid[_key(r)] = np.where(n > 0, hit / np.maximum(n, 1), np.nan).reshape(C, K).tolist()
    return CameraTables(_agreement(err, scored, blind, thresholds), by_cam, by_kp, grid)


def _nan_as_none(value):
    if isinstance(value, dict):
        return {k: _nan_as_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nan_as_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _figure(report: LabelFreeReport):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    radius = _key(max(report.config.thresholds_px))
    share = np.array(report.result.share_by_camera_keypoint[radius], np.float64)
    fig, (ax0, ax1) = plt.subplots(
        1, 2, figsize=(13, 4.4), gridspec_kw={"width_ratios": [3, 1]}, dpi=110, layout="constrained"
    )
    im = ax0.imshow(np.ma.masked_invalid(share), vmin=0, vmax=1, cmap="viridis", aspect="auto")
    ax0.set_xticks(range(len(report.keypoints)), report.keypoints, rotation=70, fontsize=7)
    ax0.set_yticks(range(len(report.cameras)), report.cameras, fontsize=8)
    ax0.set_title(f"share of each camera's keypoints within {radius} px (misses count)")
    fig.colorbar(im, ax=ax0, fraction=0.03, pad=0.01)
    if report.bone_spread is not None and report.bone_spread.by_track:
        tracks = list(report.bone_spread.by_track)
        ax1.bar(range(len(tracks)), [report.bone_spread.by_track[t] for t in tracks])
        ax1.set_xticks(range(len(tracks)), tracks, rotation=90, fontsize=6)
        ax1.set_xlabel("track")
        ax1.set_ylabel("bone-length CV (median over bones)")
    else:
        ax1.text(0.5, 0.5, "no tracks", ha="center", va="center", transform=ax1.transAxes)
        ax1.set_axis_off()
    ax1.set_title("bone-length spread per track")
    return fig
