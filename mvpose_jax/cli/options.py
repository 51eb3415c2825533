"""Options several subcommands share, and how they become the jobs' configs.

Nothing here imports jax: ``--help`` stays fast (the jobs' configs are plain dataclasses).
"""

from __future__ import annotations

import argparse

from mvpose_jax import stages
from mvpose_jax.jobs.adapt import AdaptSettings
from mvpose_jax.jobs.common import DetectionsSource, ProposalOptions, RigSource
from mvpose_jax.jobs.smooth import SmoothingOptions
from mvpose_jax.jobs.train import TrainingRun

# The layouts --source-layout takes (mvpose_jax.skeletons.LAYOUTS, written out so that --help
# does not import the library; tests/test_cli.py holds them equal) and what the count says.
SOURCE_LAYOUT_HELP = (
    "the files' keypoint layout: body25, body25b (OpenPose's experimental BODY_25B), body135, "
    "openpose_coco18, coco18, coco17, coco133 (COCO-WholeBody), halpe26, halpe68, halpe136, "
    "mpii, blazepose (MediaPipe). Default: from the keypoint count (25 body25, 18 "
    "openpose_coco18, 17 coco17, 26 halpe26, 68 halpe68, 136 halpe136, 133 coco133, 135 body135, "
    "33 blazepose, 16 mpii); BODY_25B files, 25 keypoints too, need --source-layout body25b"
)


def check_writable(path: str, *, folder: bool) -> object:
    """`data.files.check_writable` of an output option (imported when used: `--help` stays fast)."""
    from mvpose_jax.data.files import check_writable as check

    return check(path, folder=folder)


def add_rig_argument(
    p: argparse.ArgumentParser, default: str | None = "panoptic5", required: bool | None = None
) -> None:
    """The ``--rig`` option every subcommand that needs cameras shares (required when it has no
    default, unless ``required`` says otherwise)."""
    p.add_argument(
        "--rig",
        default=default,
        required=default is None if required is None else required,
        help="preset name (panoptic5, arplab6) or calibration file (.json native or CMU Panoptic, "
        ".toml anipose/Pose2Sim)",
    )
    p.add_argument(
        "--translation-scale",
        type=float,
        default=1.0,
        help="TOML calibrations only: metres per translation unit (0.001 for millimetres)",
    )
    p.add_argument(
        "--orthonormalise",
        action="store_true",
        help="replace each camera's R by the nearest rotation (calibrations written with few "
        "decimals); the largest change is reported",
    )


def add_detection_options(p: argparse.ArgumentParser, *, what: str) -> None:
    """How to read an OpenPose folder given to ``what`` (camera names, layout, missing frames)."""
    p.add_argument(
        "--missing-frames",
        choices=("error", "empty"),
        default=None,
        help=f"OpenPose folders ({what}): a frame missing in some cameras is an error (default) "
        "or empty there",
    )
    p.add_argument(
        "--camera-map",
        action="append",
        nargs="+",
        default=None,
        metavar="FOLDER=CAMERA",
        help=f"OpenPose folders ({what}): the calibration's camera name of each camera folder, "
        "e.g. cam01_json=cam01 cam02_json=cam02 (spaces or commas; repeatable; default: the "
        "folder's name, less suffixes such as _json)",
    )
    p.add_argument(
        "--source-layout",
        default=None,
        help=f"OpenPose folders ({what}): {SOURCE_LAYOUT_HELP}",
    )


def detection_arguments(p: argparse.ArgumentParser, *, required: bool = True) -> None:
    """--rig and --detections (required unless ``required`` is False: infer's --session finds
    both) and how the detections are read."""
    add_rig_argument(p, default=None, required=required)
    p.add_argument(
        "--detections",
        required=required,
        help="2D detections: native JSON, the original repository's JSON, .npz, or an OpenPose "
        "folder (one subfolder per camera of per-frame *_keypoints.json, BODY_25 or COCO)",
    )
    p.add_argument(
        "--layout",
        default=None,
        help="keypoint layout to work in (default: the file's; coco18 for OpenPose and the original format)",
    )
    p.add_argument(
        "--missing-frames",
        choices=("error", "empty"),
        default=None,
        help="OpenPose folders: a frame missing in some cameras is an error (default) or empty there",
    )
    p.add_argument(
        "--camera-map",
        action="append",
        nargs="+",
        default=None,
        metavar="FOLDER=CAMERA",
        help="OpenPose folders: the calibration's camera name of each camera folder, e.g. "
        "cam01_json=cam01 cam02_json=cam02 (pairs separated by spaces or commas; the option may "
        "be repeated; default: the folder's name, or it without a suffix tools add: _json, "
        "_img, _images, _keypoints)",
    )
    p.add_argument(
        "--source-layout",
        default=None,
        help=f"OpenPose folders: {SOURCE_LAYOUT_HELP}",
    )


def add_proposal_arguments(p: argparse.ArgumentParser) -> None:
    """How detections are grouped into people (infer and adapt; `proposal_options` reads them)."""
    p.add_argument(
        "--proposals",
        choices=stages.names("proposals"),
        default=None,
        help="how skeletons are grouped into people: combined (the default with --matcher: the "
        "GAT's scores joined with epipolar geometry, each frame kept on the grouping that agrees "
        "better with the geometry; settings from the --matcher folder), gat (the GAT's scores "
        "alone, --threshold; the paper's), gat-repaired (as gat, then a person split by a "
        "duplicate or fragment skeleton made one again) or epipolar (the default without "
        "--matcher: symmetric epipolar distance, --half-score-px)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=None,
        help="--proposals gat, gat-repaired or epipolar: least match score to join two skeletons (default: the "
        "one train-matcher chose, in the --matcher folder's proposal_threshold.json; else 0.5, "
        "the paper's)",
    )
    p.add_argument("--min-views", type=int, default=2, help="proposals: least views of a person")
    p.add_argument(
        "--half-score-px",
        type=float,
        default=30.0,
        help="geometric matcher: epipolar distance (px) that scores 0.5",
    )


def add_training_arguments(p: argparse.ArgumentParser, *, dev_help: str | None = None) -> None:
    """Options every training command shares: rig, data, output folder, layout and seed; devices
    (data parallelism, several hosts) and the checkpoint cadence."""

    def devices(value: str) -> str | int:
        if value == "all" or (value.isdigit() and int(value) >= 1):
            return value if value == "all" else int(value)
        raise argparse.ArgumentTypeError(f"expected a device count >= 1 or 'all', got {value!r}")

    add_rig_argument(p, default=None)
    p.add_argument(
        "--train",
        required=True,
        help="single-person recordings: a file, an OpenPose folder, or a folder of them (any "
        "format: .npz, .json, OpenPose folders)",
    )
    p.add_argument(
        "--dev",
        required=dev_help is None,
        help=dev_help or "single-person validation recordings, as --train",
    )
    p.add_argument("--out", required=True, help="folder for the best and latest checkpoints")
    p.add_argument("--layout", default=None, help="keypoint layout to convert the recordings to")
    p.add_argument(
        "--source-layout",
        default=None,
        help=f"OpenPose folders: {SOURCE_LAYOUT_HELP}",
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seeds initialisation, sample order and augmentation"
    )
    p.add_argument(
        "--devices",
        type=devices,
        default=None,
        metavar="N|all",
        help="data-parallel training over N devices (all: every device of every host): each "
        "batch is split over them, parameters are replicated; default: one device",
    )
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=500,
        metavar="STEPS",
        help="also save the latest state every this many steps (0: only at validations)",
    )
    p.add_argument(
        "--coordinator-address",
        metavar="HOST:PORT",
        help="several hosts: process 0's address (every host runs the same command; or set "
        "JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID)",
    )
    p.add_argument("--num-processes", type=int, help="several hosts: how many processes take part")
    p.add_argument("--process-id", type=int, help="several hosts: this process's index, 0 .. N-1")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue from the latest checkpoint in --out (same settings; training may be lengthened)",
    )


def add_adapt_arguments(p: argparse.ArgumentParser, *, prefix: str = "") -> None:
    """The settings of an adaptation (`adapt.AdaptConfig`), as ``adapt`` and ``infer --adapt``
    take them (``prefix`` before each option's name)."""
    what = "--adapt: " if prefix else ""
    p.add_argument(
        f"--{prefix}max-steps", type=int, default=300, help=f"{what}most fine-tuning steps"
    )
    p.add_argument(
        f"--{prefix}max-seconds",
        type=float,
        default=None,
        help=f"{what}wall-clock budget of the adaptation, proposals and compilation included "
        "(default: 120 s per 1,000 frames, at least 30 s)",
    )
    p.add_argument(
        f"--{prefix}learning-rate",
        type=float,
        default=1e-3,
        help=f"{what}Adam's initial step size (a cosine decay to a tenth of it over --max-steps)",
    )
    p.add_argument(
        f"--{prefix}holdout-every",
        type=int,
        default=5,
        help=f"{what}hold out every N-th block of frames; their reprojection loss decides when to "
        "stop, and the best parameters are kept",
    )
    p.add_argument(
        f"--{prefix}block-frames",
        type=int,
        default=10,
        help=f"{what}frames per held-out block (contiguous, so neighbouring frames do not leak)",
    )
    p.add_argument(
        f"--{prefix}patience",
        type=int,
        default=5,
        help=f"{what}held-out checks (every 20 steps) without improvement before stopping",
    )


def print_adapt_report(report) -> None:
    """One paragraph on what an adaptation did (`adapt.AdaptReport`)."""
    print(
        f"adapted on {report.people_adapt} people of {report.frames_adapt} frames "
        f"({report.settings['grouping']} proposals), {report.people_heldout} people of "
        f"{report.frames_heldout} frames held out: held-out reprojection "
        f"{report.heldout_px_before:.2f} -> {report.heldout_px_after:.2f} px per keypoint "
        f"(best at step {report.best_step} of {report.steps}, stopped by {report.stopped}, "
        f"{report.seconds:.0f} s)"
    )


def add_smoothing_arguments(p: argparse.ArgumentParser, *, default_filter: str) -> None:
    """The filter and gap-filling options of ``infer`` and ``smooth``."""
    p.add_argument(
        "--filter",
        choices=stages.names("filters"),
        default=default_filter,
        help="per-track filter: butterworth (zero-phase, offline, over each whole track after "
        "the stream), one-euro (causal, per frame, as a live stream runs it) or none",
    )
    p.add_argument(
        "--cutoff-hz",
        type=float,
        default=2.0,
        help="butterworth: cut-off frequency (Hz, order 4; chosen on validation scenes)",
    )
    p.add_argument(
        "--fill-gap-s",
        type=float,
        default=0.5,
        help="fill gaps of a track's keypoints up to this long (seconds; cubic; 0: none); "
        "filled keypoints are flagged in the output",
    )
    p.add_argument(
        "--outlier-m",
        type=float,
        default=0.1,
        help="before filling and filtering, drop samples further than this (metres) from "
        "their keypoint's 7-frame median (0: keep all)",
    )
    p.add_argument(
        "--min-cutoff", type=float, default=1.0, help="one-euro: cut-off when still (Hz)"
    )
    p.add_argument(
        "--beta", type=float, default=7.0, help="one-euro: cut-off rise per speed (Hz per m/s)"
    )
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="frame rate (default: the recording's, from its timestamps; without them, tracking "
        "and filters assume 30, and infer --export refuses to guess)",
    )


def rig_source(args: argparse.Namespace) -> RigSource:
    """The rig of `add_rig_argument`'s options."""
    return RigSource(args.rig, args.translation_scale, args.orthonormalise)


def detections_source(args: argparse.Namespace, path: str | None = None) -> DetectionsSource:
    """The recording of `detection_arguments`' options (``path``: another option's file, read
    with the same OpenPose options), with ``--cameras`` when the command has it."""
    cameras = getattr(args, "cameras", None)
    return DetectionsSource(
        args.detections if path is None else path,
        layout=getattr(args, "layout", None),
        missing_frames=getattr(args, "missing_frames", None),
        camera_map=_camera_map(getattr(args, "camera_map", None)),
        source_layout=getattr(args, "source_layout", None),
        cameras=tuple(cameras) if cameras else None,
    )


def _camera_map(values) -> dict[str, str] | None:
    """``--camera-map``'s pairs (every repetition, spaces or commas) as one map, or None."""
    if not values:
        return None
    from mvpose_jax.data.openpose import parse_camera_map

    return parse_camera_map(values)


def reading_options(args: argparse.Namespace) -> dict:
    """The reading options given (OpenPose folders' options and the camera selection)."""
    return detections_source(args).reading_options()


def proposal_options(args: argparse.Namespace) -> ProposalOptions:
    """The grouping of `add_proposal_arguments`' options."""
    return ProposalOptions(args.proposals, args.threshold, args.min_views, args.half_score_px)


def training_run(args: argparse.Namespace) -> TrainingRun:
    """The data, folder and devices of `add_training_arguments`' options."""
    return TrainingRun(
        rig=rig_source(args),
        train=args.train,
        dev=args.dev,
        out=args.out,
        layout=args.layout,
        source_layout=args.source_layout,
        seed=args.seed,
        devices=args.devices,
        checkpoint_every=args.checkpoint_every,
        coordinator_address=args.coordinator_address,
        num_processes=args.num_processes,
        process_id=args.process_id,
        resume=args.resume,
    )


def adapt_settings(args: argparse.Namespace, *, prefix: str = "") -> AdaptSettings:
    """The adaptation of `add_adapt_arguments`' options."""

    def get(name):
        return getattr(args, prefix.replace("-", "_") + name)

    return AdaptSettings(
        max_steps=get("max_steps"),
        max_seconds=get("max_seconds"),
        learning_rate=get("learning_rate"),
        holdout_every=get("holdout_every"),
        block_frames=get("block_frames"),
        patience=get("patience"),
    )


def adapt_config(args: argparse.Namespace, *, prefix: str = ""):
    """The `adapt.AdaptConfig` of `add_adapt_arguments`' options."""
    from mvpose_jax.jobs.adapt import adapt_config as config

    return config(
        adapt_settings(args, prefix=prefix),
        min_views=getattr(args, "min_views", 2),
        seed=getattr(args, "seed", 0),
    )


def smoothing_options(args: argparse.Namespace) -> SmoothingOptions:
    """The filter and gap filling of `add_smoothing_arguments`' options."""
    return SmoothingOptions(
        filter=args.filter,
        cutoff_hz=args.cutoff_hz,
        fill_gap_s=args.fill_gap_s,
        outlier_m=args.outlier_m,
        min_cutoff=args.min_cutoff,
        beta=args.beta,
        fps=args.fps,
    )


def print_dev_quality(quality: dict | None) -> None:
    """The estimator against triangulation on the dev people (`jobs.common.read_dev_quality`)."""
    if quality is not None:
        q = quality
        verdict = "better" if q["estimator_px"] <= q["triangulation_px"] else "WORSE"
        print(
            f"dev reprojection on the {q['keypoints']} keypoints triangulation reconstructs: "
            f"estimator {q['estimator_px']:.2f} px, triangulation {q['triangulation_px']:.2f} px "
            f"({verdict} than triangulation)"
        )


def add_pool_arguments(p: argparse.ArgumentParser) -> None:
    """The Ray workers' options (``batch``, ``generate --recordings``; `pool_config` reads them)."""
    p.add_argument(
        "--address",
        help="the Ray cluster to join (`ray start --head` prints it; 'auto': the one this machine "
        "belongs to); default: a Ray on this machine's CPUs, started and stopped by the command",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="Ray workers (default: the cluster's CPUs / --cpus-per-worker, at most one per "
        "recording); each loads JAX, compiles and loads the models once",
    )
    p.add_argument(
        "--cpus-per-worker",
        type=int,
        default=1,
        help="CPUs each worker reserves, and the threads of its XLA pool",
    )
    p.add_argument(
        "--retries",
        type=int,
        default=2,
        help="times a recording whose worker died (killed, out of memory, machine lost) is run "
        "again, from its start, on a fresh worker",
    )


def pool_config(args: argparse.Namespace):
    """The `jobs.batch.PoolConfig` of `add_pool_arguments`' options."""
    from mvpose_jax.jobs.batch import PoolConfig

    return PoolConfig(args.address, args.workers, args.cpus_per_worker, args.retries)
