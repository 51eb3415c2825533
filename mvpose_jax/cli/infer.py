"""``mvpose-jax infer``: 3D poses from a calibration and 2D detections, a chunk at a time.

Moved here as it was in ``cli.py``; its job (chunk store, manifest, resume, partial results,
smoothing window, exports) is to move into ``mvpose_jax.jobs.infer``.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

from mvpose_jax.cli.options import (
    adapt_config,
    add_adapt_arguments,
    add_proposal_arguments,
    add_smoothing_arguments,
    check_writable,
    detection_arguments,
    print_adapt_report,
    proposal_options,
    reading_options,
    smoothing_options,
)
from mvpose_jax.cli.registry import command
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.jobs.common import proposal_settings, recording_fps
from mvpose_jax.jobs.export import export_formats
from mvpose_jax.jobs.smooth import smoothing_settings


def _infer_arguments(p: argparse.ArgumentParser) -> None:
    detection_arguments(p)
    p.add_argument(
        "--cameras", nargs="+", help="use only these cameras of the recording (default: all)"
    )
    p.add_argument(
        "--matcher",
        help="folder of a trained matcher (train-matcher --out); default: the geometric "
        "matcher (symmetric epipolar distance) on every camera",
    )
    p.add_argument(
        "--estimator",
        help="folder of a trained estimator (train-estimator --out); default: "
        "triangulation of the keypoints seen in 2+ views",
    )
    p.add_argument(
        "--method",
        choices=("mlp", "blend", "dlt", "centroid", "robust"),
        default=None,
        help="the 3D stage. With --estimator: blend (the default: robust triangulation "
        "wherever 2+ inlier views see a keypoint, the estimator elsewhere, placed by the "
        "person's triangulated keypoints; it beat both on every shift of the domain-shift "
        "experiment, docs/blend.md) or mlp (the estimator's output alone, the paper's). Without: dlt (score-weighted "
        "DLT; the default), centroid (the paper's pairwise centroid) or robust (DLT that drops "
        "a person's views that are not theirs, by the median keypoint reprojection error, then "
        "each keypoint's outlier views; never below 2)",
    )
    p.add_argument(
        "--outlier-px",
        type=float,
        default=None,
        help="--method robust or blend: reprojection error (px) that marks a keypoint's view as "
        "an outlier (default 30, chosen on validation scenes)",
    )
    p.add_argument(
        "--view-outlier-px",
        type=float,
        default=None,
        help="--method robust or blend: median keypoint reprojection error (px) that marks a "
        "whole view as not the person's (default 30)",
    )
    add_proposal_arguments(p)
    p.add_argument(
        "--chunk-frames",
        type=int,
        default=256,
        help="frames per chunk: .npz files and OpenPose folders are read, processed and written "
        "a chunk at a time, so memory does not grow with the recording (native and original "
        "JSON are one document and are loaded whole: convert long ones to .npz)",
    )
    p.add_argument(
        "--out",
        required=True,
        help="output folder: poses.json and poses.npz; finished chunks go to OUT/chunks/ while "
        "the run lasts",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue an interrupted run from the chunks it finished (OUT/chunks/), with the "
        "same settings (a changed one is refused, named); without an unfinished run, start over",
    )
    p.add_argument(
        "--keep-chunks",
        action="store_true",
        help="keep OUT/chunks/ (each chunk's results and the run's settings) after writing the "
        "results; default: removed once poses.json and poses.npz are written",
    )
    p.add_argument(
        "--no-track",
        action="store_true",
        help="no track ids (each frame's people stand alone; no filtering or gap filling)",
    )
    p.add_argument(
        "--max-gap-s",
        type=float,
        default=1.0,
        help="tracking: a person unseen for up to this many seconds keeps their track id",
    )
    add_smoothing_arguments(p, default_filter="butterworth")
    p.add_argument(
        "--export",
        action="append",
        metavar="FORMATS",
        help="also write the poses as trc, c3d and/or csv (comma list) in --out, as `export` "
        "does with its defaults: one file per track, mm, OpenSim axes from the rig's up",
    )
    p.add_argument(
        "--adapt",
        action="store_true",
        help="first fine-tune --estimator on this recording's own detections, grouped by the "
        "proposals (no labels; as `mvpose-jax adapt`, in memory; reads the whole recording), "
        "then infer with it",
    )
    add_adapt_arguments(p, prefix="adapt-")


def _smoothing(args: argparse.Namespace):
    """The smoothing options as (OneEuroConfig, smooth_poses keyword arguments)."""
    return smoothing_settings(smoothing_options(args))


@command(
    "infer",
    "3D poses from a calibration and 2D detections: matching, proposals, estimator or "
    "triangulation; a chunk of frames at a time (Ctrl-C keeps the finished chunks: --resume).",
    _infer_arguments,
)
def _infer(args: argparse.Namespace) -> int:
    import numpy as np

    from mvpose_jax.data import open_recording
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.data.chunks import ChunkStore
    from mvpose_jax.data.poses import PoseResults, load_poses, load_poses_chunk
    from mvpose_jax.inference import stream_pipeline
    from mvpose_jax.smoothing import smooth_chunk_files
    from mvpose_jax.tracking import TrackingConfig
    from mvpose_jax.trained import load_estimator, load_matcher

    check_writable(args.out, folder=True)
    if args.method in ("mlp", "blend") and not args.estimator:
        raise InputError(f"--method {args.method} needs --estimator", field="--method")
    if args.method in ("dlt", "centroid", "robust") and args.estimator:
        raise InputError(
            f"--method {args.method} triangulates: it would not use --estimator (mlp or blend do)",
            field="--method",
        )
    if args.chunk_frames < 1:
        raise InputError("must be at least 1", field="--chunk-frames")
    if args.adapt and not args.estimator:
        raise InputError("adapts an estimator: give --estimator", field="--adapt")
    if args.adapt and args.resume:
        raise InputError(
            "an in-memory adaptation cannot be resumed: run `mvpose-jax adapt --out NEW` once, "
            "then `infer --estimator NEW` (which --resume continues)",
            field="--adapt",
        )
    adapt = adapt_config(args, prefix="adapt-") if args.adapt else None
    if adapt is not None:
        adapt.check()
    one_euro, smooth_kwargs = _smoothing(args)
    if args.max_gap_s < 0:
        raise InputError("must be >= 0", field="--max-gap-s")
    rig_all = load_rig(
        args.rig, translation_scale=args.translation_scale, orthonormalise=args.orthonormalise
    )
    stream = open_recording(
        args.detections, layout=args.layout, rig=rig_all, **reading_options(args)
    )
    with stream:
        rig = rig_all.select(list(stream.cameras))
        F = stream.num_frames
        # The frame rate (the tracker's and the filters' clock, and the exports') from the first
        # frames' timestamps: a long recording is never read whole for it.
        head = stream.read_frames(0, min(F, 8)) if F else None
        export = _export_after_infer(args, rig_all, head)  # None without --export; checks first
        fps = args.fps or recording_fps(head.timestamps if head is not None else None)
        matcher = load_matcher(args.matcher, rig) if args.matcher else None
        estimator = load_estimator(args.estimator, rig) if args.estimator else None
        proposals, threshold, combined = _proposal_settings(args, matcher)
        if adapt is not None:
            from mvpose_jax.adapt import adapt_estimator

            estimator, report = adapt_estimator(
                rig,
                stream.read_frames(0, F).detections,
                estimator,
                matcher=matcher,
                threshold=threshold,
                half_score_px=args.half_score_px,
                proposals=proposals,
                combined=combined,
                config=adapt,
            )
            print_adapt_report(report)
        tracking = None if args.no_track else TrackingConfig(max_gap_s=args.max_gap_s)
        store = ChunkStore(
            os.path.join(args.out, "chunks"),
            settings=_infer_settings(args, stream, threshold, fps, proposals, combined),
            frames_total=F,
            chunk_frames=args.chunk_frames,
        )
        start = store.begin(resume=args.resume)
        if store.discarded:
            warnings.warn(
                f"{store.folder} held {store.discarded} finished chunk(s) of an earlier unfinished "
                "run: removed, starting over (--resume continues such a run)",
                MvposeWarning,
                stacklevel=1,
            )
        first_track = 0
        if start:
            print(f"resuming at frame {start} of {F} ({start // args.chunk_frames} chunks done)")
            if tracking is not None:
                # The tracker's memory is not kept with the chunks: tracks restart here, with
                # ids after every earlier one (never reused).
                first_track = store.next_track_id()
        # Tracked results are smoothed (outliers, gap filling, Butterworth) chunk by chunk with
        # their neighbours while assembling, so memory stays bounded by the chunk.
        transform = None
        summary = {"tracks": set(), "filled": 0}
        if tracking is not None:
            filt = "butterworth" if args.filter == "butterworth" else "none"

            def transform(paths, folder):
                out = smooth_chunk_files(paths, folder, fps=fps, filter=filt, **smooth_kwargs)
                summary.update(tracks=set(), filled=0)
                for path in out:  # the summary line's counts, one chunk in memory at a time
                    res = load_poses_chunk(path)[1]
                    summary["tracks"].update(res.track[res.poses.valid & (res.track >= 0)].tolist())
                    summary["filled"] += int(res.filled.sum()) if res.filled is not None else 0
                return out

        # What a chunk's results need of its recording besides the detections, by first frame.
        timestamps: dict[int, object] = {}
        counts: dict[int, np.ndarray] = {}

        def chunks():
            for first, rec in stream.chunks(args.chunk_frames, start=start):
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
                matcher=matcher,
                estimator=estimator,
                method=_infer_method(args),
                proposals=proposals,
                combined=combined,
                threshold=threshold,
                min_views=args.min_views,
                half_score_px=args.half_score_px,
                layout=stream.layout,
                num_frames=F - start,
                progress=True,
                tracking=tracking,
                one_euro=one_euro if tracking is not None and args.filter == "one-euro" else None,
                fps=fps,
                first_track_id=first_track,
                **{
                    k: v
                    for k, v in (
                        ("outlier_px", args.outlier_px),
                        ("view_outlier_px", args.view_outlier_px),
                    )
                    if v is not None
                },
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
            done = store.assemble(args.out, transform=transform)
            print(
                f"mvpose-jax infer: interrupted: wrote partial results, {_covered(done, F)}, to "
                f"{done.json} and {done.npz}; the same command with --resume continues",
                file=sys.stderr,
            )
            return 130
        except BaseException:
            done = store.assemble(args.out, transform=transform)
            if done.frames:
                print(
                    f"mvpose-jax infer: stopped by the error below: wrote partial results, "
                    f"{_covered(done, F)}, to {done.json} and {done.npz}; once it is fixed, the "
                    "same command with --resume continues",
                    file=sys.stderr,
                )
            raise
        try:
            done = store.assemble(args.out, transform=transform)
        except KeyboardInterrupt:
            print(
                f"mvpose-jax infer: interrupted while writing the results; every chunk is done "
                f"({store.folder}): the same command with --resume writes them",
                file=sys.stderr,
            )
            return 130
        if not args.keep_chunks:
            store.remove()
    if people == 0 and frames > 0 and start == 0:
        warnings.warn(_why_nobody(views, cameras, args, threshold), MvposeWarning, stacklevel=1)
    resumed = f" ({start} finished before, {frames} now)" if start else ""
    tracks = ""
    if tracking is not None:
        tracks = (
            f", {len(summary['tracks'])} tracks, {summary['filled']} keypoints filled "
            f"({args.filter} filter)"
        )
    print(
        f"{F} frames{resumed}, {people} people{' in those run now' if start else ''} "
        f"({people / max(frames, 1):.2f} per frame){tracks}; proposals "
        f"{1000 * seconds['proposals'] / max(frames, 1):.2f} ms/frame, 3D "
        f"{1000 * seconds['poses'] / max(frames, 1):.2f} ms/frame; wrote {done.json} and {done.npz}"
    )
    if export:
        export(load_poses(done.npz))  # exports read the whole result (memory grows with it)
    return 0


def _covered(done, num_frames: int) -> str:
    """The frames partial results cover, in words."""
    if not done.frames:
        return f"no frame of {num_frames} (no chunk had finished)"
    return f"frames 0-{done.frames - 1} of {num_frames}"


def _infer_method(args) -> str:
    """infer's 3D stage: --method, by default blend with an estimator and dlt without."""
    return args.method or ("blend" if args.estimator else "dlt")


def _infer_settings(
    args: argparse.Namespace, stream, threshold: float, fps: float, proposals: str, combined
) -> dict:
    """Every input and setting of ``infer`` that changes its results, by option name (what an
    unfinished run must share with the command that resumes it)."""
    import dataclasses
    from pathlib import Path

    def where(path):
        return None if path is None else str(Path(path).resolve())

    rig_file = Path(args.rig)
    settings = {
        "--detections": where(args.detections),
        "--rig": where(rig_file) if rig_file.exists() else args.rig,
        "--translation-scale": args.translation_scale,
        "--orthonormalise": args.orthonormalise,
        "--layout": stream.layout,
        "--cameras": list(stream.cameras),
        "--missing-frames": args.missing_frames,
        "--camera-map": args.camera_map,
        "--source-layout": args.source_layout,
        "--matcher": where(args.matcher),
        "--estimator": where(args.estimator),
        "--threshold": threshold,
        "--min-views": args.min_views,
    }
    if args.matcher is not None:  # without one, proposals are always epipolar
        settings["--proposals"] = proposals
    if combined is not None:
        settings["combined"] = dataclasses.asdict(combined)
    method = _infer_method(args)
    if method != "mlp":  # runs with an estimator before --method blend existed recorded none
        settings["--method"] = method
    if args.adapt:
        # (Only when given: the manifests of runs without it stay as they were.) Such a run is
        # never resumed (`_infer` refuses), and a run without --adapt cannot resume its chunks.
        settings["--adapt"] = True
    if proposals == "epipolar":
        settings["--half-score-px"] = args.half_score_px
    if method in ("robust", "blend"):
        settings["--outlier-px"] = args.outlier_px
        settings["--view-outlier-px"] = args.view_outlier_px
    # What the chunks hold also depends on the tracker and the streaming filter (Butterworth,
    # outliers and gap filling act only while assembling: they may change on resume).
    settings["--no-track"] = args.no_track
    if not args.no_track:
        settings["--max-gap-s"] = args.max_gap_s
        settings["--fps"] = fps
        if args.filter == "one-euro":
            settings["--min-cutoff"] = args.min_cutoff
            settings["--beta"] = args.beta
    return settings


def _why_nobody(views: int, cameras, args: argparse.Namespace, threshold: float) -> str:
    """Which setting left a whole recording without a single person (``views``: the most
    proposal cameras with skeletons in any frame)."""
    head = "no person in any frame: "
    if views == 0:
        return head + "the recording has no skeleton in the proposal cameras " + ", ".join(cameras)
    if args.min_views > views:
        return head + (
            f"--min-views {args.min_views}, but no frame has skeletons in more than {views} of "
            f"the {len(cameras)} proposal cameras"
        )
    if threshold >= 1:
        return head + f"--threshold {threshold:g}: match scores lie in [0, 1], so no pair can join"
    how = (
        f"the matcher in {args.matcher}"
        if args.matcher
        else f"--half-score-px {args.half_score_px:g}"
    )
    return head + (
        f"no pair of skeletons in different cameras scored above --threshold {threshold:g} "
        f"({how}); check the calibration (units, camera names) or lower --threshold"
    )


def _export_after_infer(args: argparse.Namespace, rig, rec):
    """``infer --export``: checks the settings before the work; returns ``export(results)``, or
    None without --export."""
    if not args.export:
        return None
    from pathlib import Path

    from mvpose_jax.cameras import up_vector
    from mvpose_jax.data.exports import ExportConfig, export_poses, frame_times

    formats = export_formats(args.export)
    with warnings.catch_warnings():  # uneven timestamps are warned about once, when exporting
        warnings.simplefilter("ignore", MvposeWarning)
        if rec is not None:
            frame_times(rec.timestamps, rec.num_frames, args.fps)
    config = ExportConfig(formats, fps=args.fps, up=tuple(float(v) for v in up_vector(rig)))

    def export(results) -> None:
        paths = export_poses(results, Path(args.out) / "poses", config, progress=True)
        print(f"exported {len(paths)} files: " + ", ".join(p.name for p in paths))

    return export


def _proposal_settings(args: argparse.Namespace, matcher):
    """(proposals, threshold, combined config or None) of the proposal options
    (`jobs.common.proposal_settings`)."""
    return proposal_settings(proposal_options(args), args.matcher, matcher)
