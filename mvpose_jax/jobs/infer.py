"""The ``infer`` job: a recording's 3D poses, a chunk of frames at a time, resumable.

One call, `run_infer(InferConfig) -> InferResult`, is what ``mvpose-jax infer`` runs and what the
experiments, the benchmarks and any other caller run to get the same results. Per chunk: read
(`data.open_recording`), the pipeline (`inference.stream_pipeline`), the chunk written to
``OUT/chunks/`` (`data.chunks.ChunkStore`, atomically); at the end (or after Ctrl-C or an error,
as partial results) ``poses.npz`` / ``poses.json`` assembled from the chunks, tracked results
smoothed over each chunk's neighbours on the way (`smoothing.smooth_chunk_files`), then the
exports. ``--resume`` compares the recorded inputs and the effective `PipelineConfig` with the
unfinished run's.
"""

from __future__ import annotations

import dataclasses
import json
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from mvpose_jax import stages
from mvpose_jax.adapt import AdaptConfig, AdaptReport
from mvpose_jax.data import open_recording
from mvpose_jax.data.chunks import Assembled, ChunkStore
from mvpose_jax.data.files import atomic_write_text, read_json, to_jsonable
from mvpose_jax.data.poses import PoseResults, load_poses, load_poses_chunk
from mvpose_jax.data.recording import recording_fps
from mvpose_jax.data.stream import FrameRangeStream
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.inference import FilterConfig, PipelineConfig, stream_pipeline
from mvpose_jax.jobs.common import DetectionsSource, RigSource, proposal_mode
from mvpose_jax.lifting import LiftingConfig
from mvpose_jax.matching import MatchingConfig
from mvpose_jax.smoothing import smooth_chunk_files
from mvpose_jax.tracking import TrackingConfig
from mvpose_jax.trained import (
    load_estimator,
    load_matcher,
    read_combined_config,
    read_proposal_threshold,
    resolve_model_folder,
)

# infer's defaults (those of `mvpose-jax infer`): tracked, Butterworth-filtered, the proposals'
# threshold and the 3D method left to the models given (`resolve_pipeline`).
INFER_PIPELINE = PipelineConfig(
    matching=MatchingConfig(threshold=None),
    lifting=LiftingConfig(),
    tracking=TrackingConfig(max_gap_s=1.0),
    filtering=FilterConfig("butterworth"),
)


@dataclasses.dataclass(frozen=True)
class InferConfig:
    """One ``infer`` run.

    Attributes:
      rig: the calibration.
      detections: the recording and how it is read.
      out: the output folder (``poses.json``, ``poses.npz``; ``chunks/`` while the run lasts).
      pipeline: what the pipeline computes. Left to the job (None fields): the proposals'
        threshold (the ``matcher`` folder's chosen one, else 0.5), the combined matcher's
        settings (the ``matcher`` folder's) and the 3D method ("blend" with an ``estimator``,
        else "dlt").
      matcher, estimator: folders of trained models (None: geometry).
      fps: frames per second (None: from the recording's timestamps, 30 without them).
      resume: continue an unfinished run in ``out`` (same inputs and config, else an error).
      keep_chunks: keep ``out/chunks/`` after writing the results.
      export: also write the results as these formats (`data.exports.EXPORT_FORMATS`).
      adapt: first fine-tune the estimator on this recording (`adapt.adapt_estimator`), in
        memory.
      frames: (first, stop): only these frames of the recording, stop excluded (cut to the
        recording's length); None: every frame. The results' frame 0 is frame ``first``.
      view: also write ``OUT/poses.rrd``, the results with the cameras and the detections as
        a rerun recording (`viewer.write_rerun`; reads the whole recording).
      progress: show a progress bar (a line every few seconds when not on a terminal).
    """

    rig: RigSource
    detections: DetectionsSource
    out: str
    pipeline: PipelineConfig = INFER_PIPELINE
    matcher: str | None = None
    estimator: str | None = None
    fps: float | None = None
    resume: bool = False
    keep_chunks: bool = False
    export: tuple[str, ...] = ()
    adapt: AdaptConfig | None = None
    frames: tuple[int, int] | None = None
    view: bool = False
    progress: bool = True


class InferResult(NamedTuple):
    """What `run_infer` did.

    frames_total: frames in the recording; start: the first frame computed by this call (0
    unless resumed); frames, people: frames computed and people found by this call; max_views:
    the most proposal cameras with skeletons in any of those frames; cameras: the proposal
    cameras; tracks, filled: distinct track ids and filled keypoints in the results (None
    untracked); seconds: wall time per stage; written: the files (`data.chunks.Assembled`);
    interrupted: stopped by Ctrl-C (``written`` holds the partial results, or is None when the
    interruption came while writing the results of finished chunks); pipeline: the
    effective config; fps: the clock used; adapted: the adaptation's report; exported: the
    export files; view: the rerun recording; read_notes: what the reader took as it was (entries
    without keypoints skipped, frames a camera lacks read as empty: `data.stream.ReadReport`).
    """

    frames_total: int
    start: int
    frames: int
    people: int
    max_views: int
    cameras: tuple[str, ...]
    tracks: int | None
    filled: int
    seconds: dict[str, float]
    written: Assembled | None
    interrupted: bool
    pipeline: PipelineConfig
    fps: float
    adapted: AdaptReport | None = None
    exported: tuple[Path, ...] = ()
    view: Path | None = None
    read_notes: tuple[str, ...] = ()


def resolve_pipeline(config: PipelineConfig, matcher_folder: str | None, *, estimator: bool):
    """The job's defaults filled in (`InferConfig.pipeline`), checked.

    Raises:
      InputError: proposals that need a matcher without one, a threshold given to the combined
        matcher (its settings are the matcher folder's), a 3D method that needs an estimator
        without one or would ignore the one given, or an unknown stage name.
    """
    m, lift = config.matching, config.lifting
    mode = proposal_mode(m.proposals, m.threshold, matcher_folder is not None)
    threshold = read_proposal_threshold(matcher_folder, m.threshold)
    combined = m.combined
    if mode == "combined" and combined is None:
        combined = read_combined_config(matcher_folder)
    method = lift.method or ("blend" if estimator else "dlt")
    try:
        needs = stages.lookup("lifting", method, what="method").needs_estimator
    except ValueError as e:
        raise InputError(str(e), field="pipeline.lifting.method") from None
    if needs and not estimator:
        raise InputError(f"method {method} needs an estimator", field="pipeline.lifting.method")
    if not needs and estimator:
        raise InputError(
            f"method {method} triangulates: it would not use the estimator (mlp or blend do)",
            field="pipeline.lifting.method",
        )
    if config.chunk_frames < 1:
        raise InputError("must be at least 1", field="pipeline.chunk_frames")
    if config.tracking is not None and config.tracking.max_gap_s < 0:
        raise InputError("must be >= 0", field="pipeline.tracking.max_gap_s")
    filt = config.filtering
    stages.lookup("filters", filt.name, what="filter")
    for name, value in (
        ("cutoff_hz", filt.cutoff_hz),
        ("one_euro.min_cutoff_hz", filt.one_euro.min_cutoff_hz),
    ):
        if value <= 0:
            raise InputError("must be > 0", field=f"pipeline.filtering.{name}")
    for name, value in (
        ("fill_gap_s", filt.fill_gap_s),
        ("outlier_m", filt.outlier_m or 0),
        ("one_euro.beta", filt.one_euro.beta),
    ):
        if value < 0:
            raise InputError("must be >= 0", field=f"pipeline.filtering.{name}")
    return dataclasses.replace(
        config,
        matching=dataclasses.replace(
            m,
            proposals=mode,
            threshold=threshold,
            combined=combined if mode == "combined" else None,
        ),
        lifting=dataclasses.replace(lift, method=method),
    )


def _flat(d: dict, prefix: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def resume_record(config: PipelineConfig, inputs: dict[str, Any]) -> dict[str, Any]:
    """What an unfinished run must share with the call that resumes it, flat by config path: the
    inputs, and the settings of the stages that made the chunks (a setting of a stage not run,
    or one that acts only while assembling, may differ)."""
    d = config.to_dict()
    m, lift = d["matching"], d["lifting"]
    if m["proposals"] != "epipolar":
        m.pop("half_score_px")
    if m["proposals"] == "combined":
        m.pop("threshold")  # the combined matcher's own is in ``combined``
    if m["combined"] is None:
        m.pop("combined")
    if lift["method"] not in ("robust", "blend"):
        lift.pop("outlier_px")
        lift.pop("view_outlier_px")
        lift.pop("max_spread_m")
    if lift["method"] != "confident":
        lift.pop("confidence")
    for stage in ("temporal", "association"):
        if d[stage] is None:
            d.pop(stage)  # as manifests written before the stage existed
    filt = d.pop("filtering")
    if d["tracking"] is not None and config.filtering.streaming:
        d["filtering"] = {"name": filt["name"], "one_euro": filt["one_euro"]}
    d.pop("chunk_frames")  # the chunk store records it itself
    d["tracked"] = d["tracking"] is not None
    return {**_flat(inputs, "source."), **_flat(d, "pipeline.")}


def run_infer(
    config: InferConfig,
    *,
    notify: Callable[[str, str], None] = lambda kind, message: None,
    models: dict | None = None,
) -> InferResult:
    """Runs ``infer`` (the module docstring); ``notify(kind, message)`` gets what a person
    watching should know while it runs: "resuming" (where), "partial" (partial results written
    before an error is raised). ``models``: a cache of loaded models the caller keeps between
    runs (a ``batch`` worker: models loaded once per process, `load_models`); None: loaded here.

    Raises:
      InputError: bad input or settings (named); an error while running leaves the finished
        chunks assembled as partial results (``notify`` says where) and is raised.
    """
    src = config.detections
    if config.adapt is not None:
        if not config.estimator:
            raise InputError("adapts an estimator: give one", field="adapt")
        if config.resume:
            raise InputError(
                "an in-memory adaptation cannot be resumed: run `mvpose-jax adapt --out NEW` "
                "once, then `infer --estimator NEW` (which --resume continues)",
                field="adapt",
            )
        config.adapt.check()
    pipeline = resolve_pipeline(config.pipeline, config.matcher, estimator=bool(config.estimator))
    rig_all = config.rig.load()
    stream = open_recording(src.path, layout=src.layout, rig=rig_all, **src.reading_options())
    if config.frames is not None:
        first, stop = int(config.frames[0]), min(int(config.frames[1]), stream.num_frames)
        if not 0 <= first < stop:
            stream.close()
            raise InputError(
                f"frames {first}-{config.frames[1]} hold none of the recording's "
                f"{stream.num_frames} frames",
                file=src.path,
                field="frames",
            )
        stream = FrameRangeStream(stream, first, stop)
    with stream:
        rig = rig_all.select(list(stream.cameras))
        F = stream.num_frames
        # The frame rate (the tracker's, the filters' and the exports' clock) from the first
        # frames' timestamps: a long recording is never read whole for it.
        head = stream.read_frames(0, min(F, 8)) if F else None
        export = _exporter(config, rig_all, head)  # checks its settings before the work
        fps = config.fps or recording_fps(head.timestamps if head is not None else None)
        matcher, estimator = load_models(config, rig, {} if models is None else models)
        adapted = None
        if config.adapt is not None:
            from mvpose_jax.adapt import adapt_estimator

            m = pipeline.matching
            estimator, adapted = adapt_estimator(
                rig,
                stream.read_frames(0, F).detections,
                estimator,
                matcher=matcher,
                threshold=m.threshold,
                half_score_px=m.half_score_px,
                proposals=m.proposals,
                combined=m.combined,
                config=config.adapt,
            )
        inputs = _inputs(config, stream, fps, pipeline)
        store = ChunkStore(
            os.path.join(config.out, "chunks"),
            settings=resume_record(pipeline, inputs),
            frames_total=F,
            chunk_frames=pipeline.chunk_frames,
        )
        start = store.begin(resume=config.resume)
        if store.discarded:
            warnings.warn(
                f"{store.folder} held {store.discarded} finished chunk(s) of an earlier unfinished "
                "run: removed, starting over (--resume continues such a run)",
                MvposeWarning,
                stacklevel=2,
            )
        first_track = 0
        if start:
            notify(
                "resuming",
                f"resuming at frame {start} of {F} ({start // pipeline.chunk_frames} chunks done)",
            )
            if pipeline.tracking is not None:
                # The tracker's memory is not kept with the chunks: tracks restart here, with
                # ids after every earlier one (never reused).
                first_track = store.next_track_id()
        summary = {"tracks": set(), "filled": 0}
        transform = _smoother(pipeline, fps, summary) if pipeline.tracking is not None else None
        # What a chunk's results need of its recording besides the detections, by first frame.
        timestamps: dict[int, object] = {}
        counts: dict[int, np.ndarray] = {}

        def chunks():
            for first, rec in stream.chunks(pipeline.chunk_frames, start=start):
                timestamps[first] = rec.timestamps
                counts[first] = np.asarray(rec.detections.count)
                yield first, rec.detections

        frames = people = views = 0
        seconds = {"proposals": 0.0, "poses": 0.0}
        cameras = tuple(matcher.rig.names) if matcher is not None else tuple(rig.names)
        try:
            for first, res in stream_pipeline(
                rig,
                chunks(),
                pipeline,
                matcher=matcher,
                estimator=estimator,
                layout=stream.layout,
                fps=fps,
                progress=config.progress,
                num_frames=F - start,
                first_track_id=first_track,
            ):
                store.save(
                    first,
                    PoseResults(
                        res.poses,
                        res.confidence,
                        res.members,
                        res.identity,
                        res.cameras,
                        stream.layout,
                        timestamps.pop(first),
                        res.track,
                    ),
                )
                idx = [stream.cameras.index(c) for c in res.cameras]
                count = counts.pop(first)[:, idx]
                views = max(views, int((count > 0).sum(axis=1).max(initial=0)))
                frames += len(res.confidence)
                people += int(np.asarray(res.poses.valid).sum())
                for k in seconds:
                    seconds[k] += res.seconds[k]
        except KeyboardInterrupt:
            done = store.assemble(config.out, transform=transform)
            return InferResult(
                F, start, frames, people, views, cameras, None, 0, seconds, done, True,
                pipeline, fps, adapted,
            )  # fmt: skip
        except BaseException:
            done = store.assemble(config.out, transform=transform)
            if done.frames:
                notify(
                    "partial",
                    f"stopped by the error below: wrote partial results, {covered(done, F)}, to "
                    f"{done.json} and {done.npz}; once it is fixed, the same command with "
                    "--resume continues",
                )
            raise
        try:
            done = store.assemble(config.out, transform=transform)
        except KeyboardInterrupt:  # every chunk is done: a resume only writes the results
            return InferResult(
                F, start, frames, people, views, cameras, None, 0, seconds, None, True,
                pipeline, fps, adapted,
            )  # fmt: skip
        if not config.keep_chunks:
            store.remove()
        _write_run_record(config, inputs, pipeline, F)
        read_notes = tuple(stream.report().lines())
    exported = tuple(export(load_poses(done.npz))) if export else ()
    view = _write_view(config, rig_all, done, fps) if config.view else None
    tracked = pipeline.tracking is not None
    return InferResult(
        F,
        start,
        frames,
        people,
        views,
        cameras,
        len(summary["tracks"]) if tracked else None,
        summary["filled"],
        seconds,
        done,
        False,
        pipeline,
        fps,
        adapted,
        exported,
        view,
        read_notes,
    )


def load_models(config: InferConfig, rig, cache: dict) -> tuple[Any, Any]:
    """(matcher, estimator) of ``config`` for ``rig`` (None where not given), taken from
    ``cache`` when loaded before for the same folder and cameras, else loaded and kept there."""

    def key(kind: str, folder: str):
        arrays = (rig.K, rig.dist, rig.R, rig.t, rig.size)
        cams = b"".join(np.asarray(a, np.float64).tobytes() for a in arrays)
        return kind, str(Path(folder).resolve()), tuple(rig.names), hash(cams)

    out = []
    for kind, folder, load in (
        ("matcher", config.matcher, load_matcher),
        ("estimator", config.estimator, load_estimator),
    ):
        if not folder:
            out.append(None)
            continue
        k = key(kind, folder)
        if k not in cache:
            cache[k] = load(folder, rig)
        out.append(cache[k])
    return out[0], out[1]


def _write_view(config: InferConfig, rig_all, done: Assembled, fps: float) -> Path:
    """``OUT/poses.rrd``: the results, their cameras and detections (`viewer.write_rerun`)."""
    from mvpose_jax.data import load_recording
    from mvpose_jax.data.recording import slice_frames
    from mvpose_jax.viewer import write_rerun

    poses = load_poses(done.npz)
    src = config.detections
    options = {**src.reading_options(), "cameras": list(poses.cameras)}
    detections = load_recording(src.path, layout=poses.layout, rig=rig_all, **options)
    if config.frames is not None:
        first = config.frames[0]
        detections = slice_frames(detections, first, first + len(poses.confidence))
    rig = rig_all.select(list(poses.cameras))
    out = Path(config.out) / "poses.rrd"
    return write_rerun(out, poses, rig, detections=detections, fps=fps, progress=config.progress)


RUN_RECORD = "infer.json"


def _write_run_record(config: InferConfig, inputs: dict, pipeline: PipelineConfig, frames: int):
    """``OUT/infer.json``: what made the results (inputs, the effective `PipelineConfig`), so a
    result can be reproduced or compared; `read_run_record` reads it back."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        ours = version("mvpose-jax")
    except PackageNotFoundError:  # a checkout that was never installed
        ours = None
    doc = {
        "format": "mvpose-jax.infer-run",
        "version": 1,
        "mvpose_jax": ours,
        "frames": frames,
        "inputs": inputs,
        "pipeline": pipeline.to_dict(),
    }
    atomic_write_text(Path(config.out) / RUN_RECORD, json.dumps(to_jsonable(doc), indent=1) + "\n")


def read_run_record(folder: str | os.PathLike) -> tuple[dict, PipelineConfig]:
    """The inputs and the `PipelineConfig` of the ``infer`` run that wrote ``folder``."""
    doc = read_json(Path(folder) / RUN_RECORD)
    if not isinstance(doc, dict) or doc.get("format") != "mvpose-jax.infer-run":
        raise InputError("not an infer run record", file=Path(folder) / RUN_RECORD, field="format")
    return doc["inputs"], PipelineConfig.from_dict(doc["pipeline"])


def covered(done: Assembled, num_frames: int) -> str:
    """The frames (partial) results cover, in words."""
    if not done.frames:
        return f"no frame of {num_frames} (no chunk had finished)"
    return f"frames 0-{done.frames - 1} of {num_frames}"


def _inputs(config: InferConfig, stream, fps: float, pipeline: PipelineConfig) -> dict:
    """The inputs that change an infer run's results (resolved paths, the cameras read)."""

    def where(path):
        return None if path is None else str(Path(path).resolve())

    src = config.detections
    rig_file = Path(config.rig.rig)
    inputs = {
        "detections": where(src.path),
        "rig": where(rig_file) if rig_file.exists() else config.rig.rig,
        "translation_scale": config.rig.translation_scale,
        "orthonormalise": config.rig.orthonormalise,
        "layout": stream.layout,
        "cameras": list(stream.cameras),
        "missing_frames": src.missing_frames,
        "camera_map": dict(src.camera_map) if src.camera_map else None,
        "source_layout": src.source_layout,
        "frames": list(config.frames) if config.frames is not None else None,
        "matcher": where(config.matcher and resolve_model_folder(config.matcher, "matcher")),
        # "pretrained": the shipped folder, so that a reinstalled package's other weights count.
        "estimator": where(
            config.estimator and resolve_model_folder(config.estimator, "estimator")
        ),
        "adapt": config.adapt is not None,
    }
    if pipeline.tracking is not None:
        inputs["fps"] = fps
    return inputs


def _smoother(pipeline: PipelineConfig, fps: float, summary: dict):
    """The chunk transform that smooths tracked results while assembling (outliers, gap
    filling, and the Butterworth filter), counting tracks and filled keypoints in ``summary``;
    memory stays bounded by the chunk."""
    filt = pipeline.filtering
    name = "none" if filt.streaming else filt.name  # a streaming filter ran already

    def transform(paths, folder):
        out = smooth_chunk_files(
            paths,
            folder,
            fps=fps,
            filter=name,
            cutoff_hz=filt.cutoff_hz,
            fill_gap_s=filt.fill_gap_s,
            outlier_m=filt.outlier_m or None,
            one_euro=filt.one_euro,
        )
        summary.update(tracks=set(), filled=0)
        for path in out:  # the summary's counts, one chunk in memory at a time
            res = load_poses_chunk(path)[1]
            summary["tracks"].update(res.track[res.poses.valid & (res.track >= 0)].tolist())
            summary["filled"] += int(res.filled.sum()) if res.filled is not None else 0
        return out

    return transform


def _exporter(config: InferConfig, rig, head) -> Callable | None:
    """``export(results) -> paths`` for `InferConfig.export` (checked now), or None."""
    if not config.export:
        return None
    from mvpose_jax.cameras import up_vector
    from mvpose_jax.data.exports import ExportConfig, export_poses, frame_times

    with warnings.catch_warnings():  # uneven timestamps are warned about once, when exporting
        warnings.simplefilter("ignore", MvposeWarning)
        if head is not None:
            frame_times(head.timestamps, head.num_frames, config.fps)
    export = ExportConfig(
        tuple(config.export), fps=config.fps, up=tuple(float(v) for v in up_vector(rig))
    )

    def run(results):
        return export_poses(results, Path(config.out) / "poses", export, progress=config.progress)

    return run
