"""``mvpose-jax infer``: 3D poses from a calibration and 2D detections, a chunk at a time.

Options -> one `jobs.infer.InferConfig` (or, with ``--session``, a `jobs.session.SessionConfig`)
-> `jobs.infer.run_infer` -> the summary printed. The combinations of options are checked here so
that a refusal names them; a config path in a job's error is named by its option
(`_OPTION_OF_SETTING`).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

from mvpose_jax import stages
from mvpose_jax.cli.options import (
    adapt_config,
    add_adapt_arguments,
    add_proposal_arguments,
    add_smoothing_arguments,
    check_writable,
    detection_arguments,
    detections_source,
    print_adapt_report,
    rig_source,
    smoothing_options,
)
from mvpose_jax.cli.registry import command
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.jobs.common import proposal_mode
from mvpose_jax.jobs.export import export_formats
from mvpose_jax.jobs.smooth import smoothing_settings


def add_pipeline_arguments(p: argparse.ArgumentParser) -> None:
    """The models and the pipeline's stages (``infer``, ``batch``; `pipeline_config` reads them)."""
    p.add_argument(
        "--matcher",
        help="folder of a trained matcher (train-matcher --out); default: the geometric "
        "matcher (symmetric epipolar distance) on every camera",
    )
    p.add_argument(
        "--estimator",
        help="folder of a trained estimator (train-estimator --out), or 'pretrained' (the "
        "rig-agnostic estimator shipped in the package: any calibrated rig, no training; "
        "docs/pretrained.md); default: triangulation of the keypoints seen in 2+ views",
    )
    p.add_argument(
        "--method",
        choices=stages.names("lifting"),
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
    p.add_argument(
        "--confidence",
        metavar="MODEL",
        help="--method confident: a view-confidence model folder (docs/view_confidence.md)",
    )
    p.add_argument(
        "--temporal",
        metavar="MODEL",
        help="a learned temporal model folder (`mvpose-jax train-temporal`, docs/temporal.md): "
        "each track's keypoints that robust triangulation cannot place are predicted from its "
        "other views and frames, before the filter (needs tracking)",
    )
    p.add_argument(
        "--associate",
        action="store_true",
        help="track-level association: after tracking, each 2D skeleton joins the tracked person "
        "it fits in its view, and people are regrouped, lifted and tracked again (mends people "
        "the grouping split or merged; needs tracking)",
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


def add_tracking_arguments(p: argparse.ArgumentParser) -> None:
    """Tracking and smoothing (``infer``, ``batch``; `pipeline_config` reads them)."""
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


def _infer_arguments(p: argparse.ArgumentParser) -> None:
    detection_arguments(p, required=False)
    p.add_argument(
        "--session",
        metavar="DIR",
        help="a Pose2Sim project (session, participant or trial folder) read as Pose2Sim reads "
        "it: its Config.toml files, its calibration, the detection folders paired with the "
        "calibration's cameras by sorted position; every trial is reconstructed into OUT/<trial>/ "
        "with Pose2Sim-named TRC files in OUT/<trial>/pose-3d/ (--detections on such a folder "
        "does the same)",
    )
    p.add_argument(
        "--cameras", nargs="+", help="use only these cameras of the recording (default: all)"
    )
    add_pipeline_arguments(p)
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
    add_tracking_arguments(p)
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
    p.add_argument(
        "--view",
        action="store_true",
        help="also write OUT/poses.rrd: the results with the cameras and the detections as a "
        "rerun recording (`rerun OUT/poses.rrd` opens it; needs the viewer extra: "
        'pip install "mvpose-jax[viewer]")',
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
    from mvpose_jax.data.pose2sim import is_pose2sim_project

    check_writable(args.out, folder=True)
    session = args.session or (
        args.detections if args.detections and is_pose2sim_project(args.detections) else None
    )
    if session is not None:
        return _infer_session(args, session)
    if not args.detections:
        raise InputError("give --detections (or --session for a Pose2Sim project)", field="--rig")
    if not args.rig:
        raise InputError("give the calibration of --detections", field="--rig")
    from mvpose_jax.jobs.infer import run_infer

    try:
        res = run_infer(infer_config(args), notify=_notify)
    except InputError as e:
        raise named_by_option(e) from None
    return _print_result(res, args)


def _infer_session(args: argparse.Namespace, session: str) -> int:
    """``--session``: every trial of a Pose2Sim project, one output folder each."""
    from mvpose_jax.jobs.session import SessionConfig, run_session

    if args.rig:
        raise InputError(
            "a Pose2Sim project's calibration is found in it (its *calib* folder): leave --rig out",
            field="--rig",
        )
    for option, given in (
        ("--camera-map", args.camera_map),
        ("--cameras", args.cameras),
        ("--adapt", args.adapt),
        ("--export", args.export),
    ):
        if given:
            raise InputError(
                "is read from the Pose2Sim project (cameras paired by position, TRC files "
                "written in each trial's pose-3d/)",
                field=option,
            )
    config = SessionConfig(
        session,
        args.out,
        pipeline_config(args),
        matcher=args.matcher,
        estimator=args.estimator,
        layout=args.layout,
        fps=args.fps,
        resume=args.resume,
        keep_chunks=args.keep_chunks,
        view=args.view,
    )

    def on_trial(trial) -> None:
        print(trial.describe())

    try:
        trials = run_session(config, on_trial=on_trial, notify=_notify)
    except InputError as e:
        raise named_by_option(e) from None
    status = 0
    for t in trials:
        status = _print_result(t.result, args) or status
    if trials and not trials[-1].result.interrupted:
        print(f"{len(trials)} trials in {args.out}")
    return status


def _notify(kind: str, message: str) -> None:
    if kind == "resuming":
        print(message)
    else:
        print(f"mvpose-jax infer: {message}", file=sys.stderr)


def _print_result(res, args: argparse.Namespace) -> int:
    """The summary of one `jobs.infer.InferResult`; the exit status (130: interrupted)."""
    from mvpose_jax.jobs.infer import covered

    if res.adapted is not None:
        print_adapt_report(res.adapted)
    F, start, done = res.frames_total, res.start, res.written
    if res.interrupted and done is None:
        print(
            "mvpose-jax infer: interrupted while writing the results; every chunk is done "
            f"({os.path.join(args.out, 'chunks')}): the same command with --resume writes them",
            file=sys.stderr,
        )
        return 130
    if res.interrupted:
        print(
            f"mvpose-jax infer: interrupted: wrote partial results, {covered(done, F)}, to "
            f"{done.json} and {done.npz}; the same command with --resume continues",
            file=sys.stderr,
        )
        return 130
    frames, people = res.frames, res.people
    if people == 0 and frames > 0 and start == 0:
        why = _why_nobody(res.max_views, res.cameras, args, res.pipeline.matching.threshold)
        warnings.warn(why, MvposeWarning, stacklevel=1)
    resumed = f" ({start} finished before, {frames} now)" if start else ""
    tracks = ""
    if res.tracks is not None:
        tracks = f", {res.tracks} tracks, {res.filled} keypoints filled ({args.filter} filter)"
    print(
        f"{F} frames{resumed}, {people} people{' in those run now' if start else ''} "
        f"({people / max(frames, 1):.2f} per frame){tracks}; proposals "
        f"{1000 * res.seconds['proposals'] / max(frames, 1):.2f} ms/frame, 3D "
        f"{1000 * res.seconds['poses'] / max(frames, 1):.2f} ms/frame; wrote {done.json} and "
        f"{done.npz}"
    )
    for note in res.read_notes:
        print(f"  read as it was: {note}")
    if res.exported:
        folder = res.exported[0].parent
        names = ", ".join(p.name for p in res.exported)
        print(f"exported {len(res.exported)} files to {folder}: {names}")
    if res.view is not None:
        print(f"wrote {res.view} (rerun {res.view} shows it)")
    return 0


# The infer job's config paths (`jobs.infer.resume_record`, its errors' fields) and the options
# that set them, so that an error names what the user typed.
_OPTION_OF_SETTING = {
    "source.detections": "--detections",
    "source.rig": "--rig",
    "source.translation_scale": "--translation-scale",
    "source.orthonormalise": "--orthonormalise",
    "source.layout": "--layout",
    "source.cameras": "--cameras",
    "source.missing_frames": "--missing-frames",
    "source.camera_map": "--camera-map",
    "source.source_layout": "--source-layout",
    "source.matcher": "--matcher",
    "source.estimator": "--estimator",
    "source.adapt": "--adapt",
    "source.fps": "--fps",
    "source.frames": "--detections",
    "adapt": "--adapt",
    "frames": "--detections",
    "chunk_frames": "--chunk-frames",
    "pipeline.chunk_frames": "--chunk-frames",
    "pipeline.matching.proposals": "--proposals",
    "pipeline.matching.threshold": "--threshold",
    "pipeline.matching.min_views": "--min-views",
    "pipeline.matching.half_score_px": "--half-score-px",
    "pipeline.lifting.method": "--method",
    "pipeline.lifting.outlier_px": "--outlier-px",
    "pipeline.lifting.view_outlier_px": "--view-outlier-px",
    "pipeline.lifting.confidence": "--confidence",
    "pipeline.temporal": "--temporal",
    "pipeline.association": "--associate",
    "pipeline.association.gate": "--associate",
    "pipeline.association.min_keypoints": "--associate",
    "pipeline.association.hold_frames": "--associate",
    "association": "--associate",
    "temporal": "--temporal",
    "pipeline.tracked": "--no-track",
    "pipeline.tracking.max_gap_s": "--max-gap-s",
    "pipeline.filtering.name": "--filter",
    "pipeline.filtering.cutoff_hz": "--cutoff-hz",
    "pipeline.filtering.fill_gap_s": "--fill-gap-s",
    "pipeline.filtering.outlier_m": "--outlier-m",
    "pipeline.filtering.one_euro.min_cutoff_hz": "--min-cutoff",
    "pipeline.filtering.one_euro.beta": "--beta",
}


def named_by_option(e: InputError) -> InputError:
    """``e`` with its field (a config path) replaced by the option that sets it."""
    option = _OPTION_OF_SETTING.get(e.field or "")
    if option is None:
        return e
    return InputError(e.reason, file=e.file, frame=e.frame, camera=e.camera, field=option)


def pipeline_config(args: argparse.Namespace):
    """The `inference.PipelineConfig` of infer's options (the combinations of options checked
    here, so that a refusal names them)."""
    from mvpose_jax.inference import FilterConfig, PipelineConfig
    from mvpose_jax.lifting import LiftingConfig
    from mvpose_jax.matching import MatchingConfig
    from mvpose_jax.tracking import AssociationConfig, TrackingConfig

    needs_estimator = args.method and stages.lookup("lifting", args.method).needs_estimator
    if needs_estimator and not args.estimator:
        raise InputError(f"--method {args.method} needs --estimator", field="--method")
    if args.method and not needs_estimator and args.estimator:
        raise InputError(
            f"--method {args.method} triangulates: it would not use --estimator (mlp or blend do)",
            field="--method",
        )
    if (args.method == "confident") != bool(args.confidence):
        raise InputError(
            "--method confident and --confidence MODEL go together", field="--confidence"
        )
    if args.associate and args.no_track:
        raise InputError("association is with tracked people: drop --no-track", field="--associate")
    if args.temporal and args.no_track:
        raise InputError("the temporal stage refines tracks: drop --no-track", field="--temporal")
    if args.chunk_frames < 1:
        raise InputError("must be at least 1", field="--chunk-frames")
    proposal_mode(args.proposals, args.threshold, bool(args.matcher))
    if args.max_gap_s < 0:
        raise InputError("must be >= 0", field="--max-gap-s")
    one_euro, _ = _smoothing(args)
    lifting = {
        k: v
        for k, v in (("outlier_px", args.outlier_px), ("view_outlier_px", args.view_outlier_px))
        if v is not None
    }
    return PipelineConfig(
        matching=MatchingConfig(args.proposals, args.threshold, args.min_views, args.half_score_px),
        lifting=LiftingConfig(args.method, **lifting, confidence=args.confidence),
        tracking=None if args.no_track else TrackingConfig(max_gap_s=args.max_gap_s),
        filtering=FilterConfig(
            args.filter, one_euro, args.cutoff_hz, args.fill_gap_s, args.outlier_m or None
        ),
        chunk_frames=args.chunk_frames,
        temporal=args.temporal,
        association=AssociationConfig() if args.associate else None,
    )


def infer_config(args: argparse.Namespace):
    """The `jobs.infer.InferConfig` of infer's options."""
    from mvpose_jax.jobs.infer import InferConfig

    if args.adapt and not args.estimator:
        raise InputError("adapts an estimator: give --estimator", field="--adapt")
    if args.adapt and args.resume:
        raise InputError(
            "an in-memory adaptation cannot be resumed: run `mvpose-jax adapt --out NEW` once, "
            "then `infer --estimator NEW` (which --resume continues)",
            field="--adapt",
        )
    pipeline = pipeline_config(args)
    return InferConfig(
        rig_source(args),
        detections_source(args),
        args.out,
        pipeline,
        matcher=args.matcher,
        estimator=args.estimator,
        fps=args.fps,
        resume=args.resume,
        keep_chunks=args.keep_chunks,
        export=export_formats(args.export) if args.export else (),
        adapt=adapt_config(args, prefix="adapt-") if args.adapt else None,
        view=args.view,
    )


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
