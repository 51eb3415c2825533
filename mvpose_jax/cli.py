"""The ``mvpose-jax`` command line: one entry point, one subcommand per job.

Each subcommand parses its options and calls the library; nothing here computes.
Bad input ends with a one-line error naming the file, frame, camera and field (exit status 2).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from mvpose_jax import stages
from mvpose_jax.errors import InputError, MvposeError, MvposeWarning

if TYPE_CHECKING:
    from mvpose_jax.synthetic import SyntheticConfig

# name -> (help, add_arguments(parser), run(args) -> exit status)
_COMMANDS: dict[
    str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]
] = {}


def command(name: str, help: str, arguments: Callable[[argparse.ArgumentParser], None]):
    """Registers the decorated ``run(args) -> exit status`` as subcommand ``name``."""

    def register(run):
        _COMMANDS[name] = (help, arguments, run)
        return run

    return register


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


def _rig_arguments(p: argparse.ArgumentParser) -> None:
    add_rig_argument(p)
    p.add_argument(
        "--detections",
        default=None,
        help="also measure the floor from these detections (any format --detections takes "
        "elsewhere, OpenPose folders included) and compare it with the guess from the cameras",
    )
    add_detection_options(p, what="--detections")


@command(
    "rig",
    "Show a rig (preset or calibration file): cameras, centres, image sizes, up; with "
    "--detections, the floor measured from the people against the camera-based guess.",
    _rig_arguments,
)
def _rig(args: argparse.Namespace) -> int:
    import numpy as np

    from mvpose_jax.cameras import camera_centres, rig_centre_and_radius, up_vector
    from mvpose_jax.data.calibration import load_rig

    rig = load_rig(
        args.rig, translation_scale=args.translation_scale, orthonormalise=args.orthonormalise
    )
    centres = np.asarray(camera_centres(rig), np.float64)
    centre, radius = rig_centre_and_radius(rig)
    print(
        f"{rig.num_cameras} cameras; up {np.round(up_vector(rig), 3).tolist()}"
        f"{' (inferred)' if rig.up is None else ''}; centre {np.round(np.asarray(centre, np.float64), 3).tolist()} m,"
        f" radius {float(radius):.3f} m"
    )
    for c, name in enumerate(rig.names):
        w, h = np.asarray(rig.size[c]).astype(int)
        print(
            f"  {name:>12s}  {w}x{h}  f={float(rig.K[c, 0, 0]):.1f}px  centre {np.round(centres[c], 3).tolist()}"
        )
    if args.detections:
        from mvpose_jax.synthetic import estimate_floor_height

        measured = measure_floor(rig, args.detections, args)
        guess = estimate_floor_height(rig)
        print(
            f"floor along up: {measured.height:.3f} m measured from the people (spread "
            f"{measured.spread:.3f} m over {measured.num_samples} person-frames of "
            f"{measured.num_frames} frames); {guess:.3f} m guessed from the cameras; the guess is "
            f"{guess - measured.height:+.3f} m off"
        )
    return 0


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
        type=camera_map,
        default=None,
        metavar="FOLDER=CAMERA,...",
        help=f"OpenPose folders ({what}): the calibration's camera name of each camera folder, "
        "e.g. cam01_json=cam01 (default: the folder's name, less suffixes such as _json)",
    )
    p.add_argument(
        "--source-layout",
        default=None,
        help=f"OpenPose folders ({what}): {SOURCE_LAYOUT_HELP}",
    )


def measure_floor(rig, path: str, args: argparse.Namespace):
    """`floor.estimate_floor_from_detections` on the recording at ``path`` (read with the
    OpenPose options of `add_detection_options`), on the rig's cameras it holds."""
    from mvpose_jax.data import load_recording
    from mvpose_jax.floor import estimate_floor_from_detections

    kwargs = {
        k: v
        for k in ("missing_frames", "camera_map", "source_layout")
        if (v := getattr(args, k, None))
    }
    rec = load_recording(path, rig=rig, **kwargs)
    return estimate_floor_from_detections(
        rig.select(list(rec.cameras)), rec.detections, layout=rec.layout
    )


# --------------------------------------------------------------------------- generate
#   mvpose-jax generate --rig panoptic5 --people 4 --frames 500 --seed 0 --out scene.json
#   mvpose-jax generate --rig arplab6 --single-person-recordings 20 --frames 1000 --out train/

# Detector rates exposed as options: option name -> DetectorConfig field.
_RATE_OPTIONS = {
    "miss-rate": "miss_rate",
    "false-positive-rate": "false_positive_rate",
    "swap-rate": "swap_rate",
    "occluded-drop-rate": "occluded_drop_rate",
    "keypoint-drop-rate": "keypoint_drop_rate",
    "noise-relative": "noise_relative",
    "offset-scale": "offset_scale",
}


def _generate_arguments(p: argparse.ArgumentParser) -> None:
    from mvpose_jax.synthetic import DetectorConfig, MotionConfig

    add_rig_argument(p)
    p.add_argument("--people", type=int, default=4, help="people in the scene (default 4)")
    p.add_argument("--frames", type=int, default=500, help="frames per recording (default 500)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--out",
        required=True,
        help="output file (.json native, .npz) or, with --single-person-recordings, a folder",
    )
    p.add_argument(
        "--single-person-recordings",
        type=int,
        default=0,
        metavar="N",
        help="write N one-person training recordings into the --out folder instead of one scene",
    )
    p.add_argument(
        "--format",
        choices=("native", "npz"),
        default=None,
        help="file format for the single-person recordings (default native JSON)",
    )
    p.add_argument(
        "--fps",
        type=float,
        default=MotionConfig.fps,
        help=f"frame rate (default {MotionConfig.fps:g})",
    )
    floor = p.add_mutually_exclusive_group()
    floor.add_argument(
        "--floor-height",
        type=float,
        default=None,
        help="floor height along the up vector, metres (default: measured with --floor-from, "
        "else guessed from the camera positions, with a warning)",
    )
    floor.add_argument(
        "--floor-from",
        metavar="DETECTIONS",
        default=None,
        help="measure the floor from your own detections of people on this rig (native JSON, "
        "original JSON, .npz or an OpenPose folder): the triangulated feet of people seen by 3+ "
        "cameras",
    )
    add_detection_options(p, what="--floor-from")
    p.add_argument(
        "--floor-jitter",
        type=float,
        default=None,
        metavar="METRES",
        help="each recording's floor is drawn within this distance of the floor height (its "
        "capture area follows), so that models trained on them tolerate a floor that is off "
        f"(default {TRAINING_FLOOR_JITTER_M:g} with --single-person-recordings, the training "
        "data; 0 for a scene)",
    )
    p.add_argument(
        "--clean",
        action="store_true",
        help="a perfect detector: no noise, offsets, drops, misses, false positives or swaps",
    )
    defaults = DetectorConfig()
    for option, field in _RATE_OPTIONS.items():
        p.add_argument(
            f"--{option}",
            type=float,
            default=None,
            help=f"detector {field.replace('_', ' ')} (default {getattr(defaults, field):g})",
        )


# Floor jitter of `generate --single-person-recordings` (training data): the measured or guessed
# floor may be off by a few decimetres, and training on one exact floor ties the models to it.
TRAINING_FLOOR_JITTER_M = 0.3


def synthetic_config_from_args(
    args: argparse.Namespace, floor_height: float | None = None
) -> SyntheticConfig:
    """The `SyntheticConfig` the options of ``generate`` describe (``floor_height``: the
    measured floor, when ``--floor-height`` is not given)."""
    import dataclasses

    from mvpose_jax.synthetic import DetectorConfig, MotionConfig, SceneConfig, SyntheticConfig

    detector = DetectorConfig().clean() if args.clean else DetectorConfig()
    changes = {
        field: getattr(args, option.replace("-", "_"))
        for option, field in _RATE_OPTIONS.items()
        if getattr(args, option.replace("-", "_")) is not None
    }
    return SyntheticConfig(
        detector=dataclasses.replace(detector, **changes),
        motion=dataclasses.replace(MotionConfig(), fps=args.fps),
        scene=dataclasses.replace(
            SceneConfig(),
            floor_height=args.floor_height if args.floor_height is not None else floor_height,
            floor_jitter_m=_floor_jitter(args),
        ),
    )


def _floor_jitter(args: argparse.Namespace) -> float:
    jitter = getattr(args, "floor_jitter", None)
    if jitter is None:
        return TRAINING_FLOOR_JITTER_M if getattr(args, "single_person_recordings", 0) > 0 else 0.0
    if not jitter >= 0:
        raise InputError(f"must be >= 0, not {jitter}", field="--floor-jitter")
    return jitter


@command(
    "generate",
    "Generate a synthetic recording (or single-person training recordings) on any rig.",
    _generate_arguments,
)
def _generate(args: argparse.Namespace) -> int:

    from mvpose_jax.data import save_recording
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.synthetic import generate_recording, generate_single_person_recordings

    rig = load_rig(
        args.rig,
        translation_scale=getattr(args, "translation_scale", 1.0),
        orthonormalise=getattr(args, "orthonormalise", False),
    )
    out = check_writable(args.out, folder=args.single_person_recordings > 0)
    measured = None
    if args.floor_from:
        measured = measure_floor(rig, args.floor_from, args)
        print(
            f"floor measured from {args.floor_from}: {measured.height:.3f} m along up (spread "
            f"{measured.spread:.3f} m over {measured.num_samples} person-frames)"
        )
    config = synthetic_config_from_args(args, None if measured is None else measured.height)
    if config.scene.floor_height is None:
        from mvpose_jax.synthetic import scene_geometry

        guess = scene_geometry(rig, config.scene).floor_height
        warnings.warn(
            f"the floor height is a guess from the camera positions ({guess:.3f} m along up), "
            "which can be half a metre off on a real rig, and models trained on a wrong floor "
            "fail on the real one; pass --floor-height or --floor-from DETECTIONS",
            MvposeWarning,
            stacklevel=1,
        )
    if args.single_person_recordings > 0:
        recordings = generate_single_person_recordings(
            rig,
            num_recordings=args.single_person_recordings,
            num_frames=args.frames,
            config=config,
            seed=args.seed,
            progress=True,
        )
        suffix = ".npz" if args.format == "npz" else ".json"
        width = len(str(len(recordings) - 1))
        for i, rec in enumerate(recordings):
            path = out / f"person_{i:0{width}d}{suffix}"
            save_recording(rec, path, rig=rig if suffix == ".json" else None)
        print(f"wrote {len(recordings)} single-person recordings of {args.frames} frames to {out}/")
        return 0
    rec = generate_recording(
        rig,
        num_people=args.people,
        num_frames=args.frames,
        config=config,
        seed=args.seed,
        progress=True,
    )
    native = out.suffix.lower() != ".npz"
    save_recording(rec, out, rig=rig if native else None)
    det = rec.detections
    print(
        f"wrote {out}: {rec.num_frames} frames, {len(rec.cameras)} cameras, {args.people} people, "
        f"{int(det.count.sum())} detections"
    )
    return 0


def _synthetic_figure_arguments(p: argparse.ArgumentParser) -> None:
    add_rig_argument(p)
    p.add_argument("--people", type=int, default=4, help="people in the scene (default 4)")
    p.add_argument("--frames", type=int, default=150, help="frames to simulate (default 150)")
    p.add_argument("--frame", type=int, default=-1, help="frame to draw (default: the last)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--out",
        default="results/synthetic_frame.png",
        help="output PNG (default results/synthetic_frame.png)",
    )


@command(
    "synthetic-figure",
    "Draw one frame of a synthetic recording: the detections in every camera (coloured by true "
    "identity, false positives grey) and the 3D ground truth.",
    _synthetic_figure_arguments,
)
def _synthetic_figure(args: argparse.Namespace) -> int:
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.render import render_frame_figure
    from mvpose_jax.synthetic import generate_recording

    rig = load_rig(
        args.rig, translation_scale=args.translation_scale, orthonormalise=args.orthonormalise
    )
    check_writable(args.out, folder=False)
    rec = generate_recording(rig, num_people=args.people, num_frames=args.frames, seed=args.seed)
    frame = args.frame % rec.num_frames
    out = render_frame_figure(
        rec,
        rig,
        frame,
        args.out,
        title=f"synthetic {args.rig}: {args.people} people, frame {frame}, seed {args.seed}",
    )
    print(out)
    return 0


# --------------------------------------------------------------------------- train-matcher


def _recordings_in(path: str, layout: str | None, source_layout: str | None = None) -> list:
    """Every recording in a file or (recursively) a folder, in any readable format: .npz and
    .json files, and OpenPose folders (one subfolder per camera), each one recording."""
    from pathlib import Path

    from mvpose_jax.data import load_recording
    from mvpose_jax.data.openpose import is_openpose_folder

    root = Path(path)
    if not root.exists():
        raise InputError("no such file or folder", file=root)

    def found(folder: Path):
        if is_openpose_folder(folder):
            yield folder
            return
        for p in sorted(folder.iterdir()):
            if p.is_dir():
                yield from found(p)
            elif p.suffix.lower() in (".npz", ".json"):
                yield p

    sources = list(found(root)) if root.is_dir() else [root]
    if not sources:
        raise InputError("no recordings (.npz, .json or OpenPose folders) here", file=root)

    def load(source: Path):
        if source_layout and source.is_dir():
            return load_recording(source, layout=layout, source_layout=source_layout)
        return load_recording(source, layout=layout)

    return [load(s) for s in sources]


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


def _train_matcher_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p)
    p.add_argument(
        "--cameras", nargs="+", help="inference cameras C_i (default: every camera of the rig)"
    )
    p.add_argument("--quick", action="store_true", help="small network and short epochs")
    p.add_argument("--max-epochs", type=int, help="override the epoch limit")
    p.add_argument("--learning-rate", type=float, help="override Adam's step size (paper 1e-4)")
    p.add_argument(
        "--max-people", type=int, help="most recordings composed into one frame (default 8)"
    )
    p.add_argument(
        "--keypoint-dropout",
        type=float,
        help="missing-keypoint augmentation: largest per-skeleton drop rate (default 0, the paper; "
        "python -m experiments.run uses 0.5)",
    )


@command(
    "train-matcher",
    "Train the skeleton-matching GAT from single-person recordings (no labels needed).",
    _train_matcher_arguments,
)
def _train_matcher(args: argparse.Namespace) -> int:
    import dataclasses

    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.matcher_settings import choose_matcher_settings
    from mvpose_jax.parallel import initialize_distributed, resolve_num_devices
    from mvpose_jax.proposals import write_proposal_threshold
    from mvpose_jax.train import train_matcher
    from mvpose_jax.trained import MatcherConfig

    check_writable(args.out, folder=True)
    # Before anything touches a device: a multi-host run must join its coordinator first.
    initialize_distributed(args.coordinator_address, args.num_processes, args.process_id)
    rig = load_rig(
        args.rig, translation_scale=args.translation_scale, orthonormalise=args.orthonormalise
    )
    config = MatcherConfig.quick() if args.quick else MatcherConfig()
    train = dataclasses.replace(
        config.train,
        seed=args.seed,
        num_devices=resolve_num_devices(args.devices),
        checkpoint_every_steps=args.checkpoint_every,
        **{
            k: v
            for k, v in (("max_epochs", args.max_epochs), ("learning_rate", args.learning_rate))
            if v is not None
        },
    )
    config = dataclasses.replace(
        config,
        train=train,
        cameras=tuple(args.cameras) if args.cameras else None,
        **({"max_people": args.max_people} if args.max_people else {}),
        **(
            {"keypoint_dropout": args.keypoint_dropout} if args.keypoint_dropout is not None else {}
        ),
    )
    if not 0 <= config.keypoint_dropout < 1:
        raise InputError(
            f"--keypoint-dropout must be in [0, 1), not {config.keypoint_dropout}",
            field="keypoint_dropout",
        )
    train_recs = _recordings_in(args.train, args.layout, args.source_layout)
    dev_recs = _recordings_in(args.dev, args.layout, args.source_layout)
    matcher, fit = train_matcher(
        rig, train_recs, dev_recs, config, checkpoint_dir=args.out, resume=args.resume
    )
    print(
        f"best validation loss {fit.best_val_loss:.5f} after {fit.steps} steps ({fit.seconds:.0f} s); "
        f"checkpoints in {args.out}"
    )
    import jax

    if jax.process_index() == 0:
        chosen = choose_matcher_settings(matcher, dev_recs, seed=args.seed)
        threshold, ari, combined = chosen.threshold, chosen.ari_by_threshold, chosen.combined
        write_proposal_threshold(
            args.out,
            threshold,
            ari,
            chosen.composed_frames,
            combined=combined,
            combined_ari=chosen.ari_by_combined_threshold,
        )
        print(
            f"proposal threshold {threshold} (ARI {ari[threshold]:.4f} on multi-person frames composed from "
            f"--dev; 0.5: {ari[0.5]:.4f}); combined matcher: threshold {combined.threshold}, "
            f"epipolar cutoff {combined.epipolar_cutoff_px:g} px (ARI "
            f"{chosen.ari_by_combined_threshold[combined.threshold]:.4f}); used by "
            f"`infer --matcher {args.out}`"
        )
    return 0


def _train_estimator_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(
        p, dev_help="validation recordings (default: the last 10%% of --train's frames)"
    )
    p.add_argument(
        "--train-cameras", nargs="+", help="training cameras C_t (default: every camera of the rig)"
    )
    p.add_argument(
        "--infer-cameras", nargs="+", help="inference cameras C_i, a subset of C_t (default: C_t)"
    )
    p.add_argument(
        "--paper-size",
        action="store_true",
        help="the paper's widths (3072 ... 1024); default: quick",
    )
    p.add_argument(
        "--output",
        choices=("absolute", "anchored", "residual"),
        default="residual",
        help="what the MLP predicts: absolute = the paper's; residual = offsets from the "
        "triangulated initial estimate (default; see models.MLPConfig)",
    )
    p.add_argument(
        "--loss-power",
        type=float,
        default=1.0,
        help="per-sample loss e^power (paper: 2; 1 resists gross detector errors)",
    )
    p.add_argument(
        "--augment", type=int, default=4, help="view-subset samples per seed sample (paper: 4)"
    )
    p.add_argument("--steps", type=int, default=4000, help="training steps")
    p.add_argument("--batch-size", type=int, default=256, help="people per training step")
    p.add_argument("--learning-rate", type=float, default=1e-3, help="Adam's initial step size")
    p.add_argument("--constant-lr", action="store_true", help="no cosine decay (the paper's)")
    p.add_argument(
        "--patience", type=int, default=20, help="validations without improvement before stopping"
    )


@command(
    "train-estimator",
    "Train the 3D estimator from single-person recordings with the reprojection loss (no 3D labels).",
    _train_estimator_arguments,
)
def _train_estimator(args: argparse.Namespace) -> int:

    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.features import single_person_samples
    from mvpose_jax.models import MLPConfig
    from mvpose_jax.parallel import initialize_distributed, resolve_num_devices
    from mvpose_jax.train import train_estimator
    from mvpose_jax.trained import EstimatorConfig, TrainConfig

    check_writable(args.out, folder=True)
    # Before anything touches a device: a multi-host run must join its coordinator first.
    initialize_distributed(args.coordinator_address, args.num_processes, args.process_id)
    rig = load_rig(
        args.rig, translation_scale=args.translation_scale, orthonormalise=args.orthonormalise
    )
    train_cams = tuple(args.train_cameras or rig.names)
    infer_cams = tuple(args.infer_cameras or train_cams)
    for c in train_cams:
        rig.camera_index(c)  # unknown names fail here, naming the camera

    xy, score = single_person_samples(
        _recordings_in(args.train, args.layout, args.source_layout), train_cams
    )
    if args.dev:
        dev_xy, dev_score = single_person_samples(
            _recordings_in(args.dev, args.layout, args.source_layout), train_cams
        )
    else:
        n = max(1, len(xy) // 10)
        xy, score, dev_xy, dev_score = xy[:-n], score[:-n], xy[-n:], score[-n:]
    mlp = MLPConfig() if args.paper_size else MLPConfig.quick()
    config = EstimatorConfig(
        train_cameras=train_cams,
        infer_cameras=infer_cams,
        mlp=MLPConfig(widths=mlp.widths, output=args.output),
        num_augment=args.augment,
        loss_power=args.loss_power,
        train=TrainConfig(
            learning_rate=args.learning_rate,
            batch_size=args.batch_size,
            max_steps=args.steps,
            patience=args.patience,
            seed=args.seed,
            final_lr_fraction=1.0 if args.constant_lr else 0.01,
            num_devices=resolve_num_devices(args.devices),
            checkpoint_every_steps=args.checkpoint_every,
        ),
    )
    _, fit = train_estimator(
        rig.select(list(train_cams)),
        xy,
        score,
        dev_xy,
        dev_score,
        config,
        checkpoint_dir=args.out,
        resume=args.resume,
    )
    best = min(fit.history, key=lambda h: h["val_loss"]) if fit.history else {}
    print(
        f"{len(xy)} training people; best validation reprojection error "
        f"{best.get('val_px_per_keypoint', float('nan')):.2f} px per keypoint after {fit.steps} steps "
        f"({fit.seconds:.0f} s); checkpoints in {args.out}"
    )
    _print_dev_quality(args.out)
    return 0


# --------------------------------------------------------------------------- adapt
#   mvpose-jax adapt --rig calib.toml --detections rec.npz --estimator est/ --out est_rec/


# `adapt.MatcherAdaptConfig`'s default, without importing jax to build the parser.
MATCHER_ADAPT_STEPS = 400


def _adapt_arguments(p: argparse.ArgumentParser) -> None:
    _detection_arguments(p)
    p.add_argument(
        "--cameras", nargs="+", help="use only these cameras of the recording (default: all)"
    )
    p.add_argument(
        "--estimator",
        "--model",
        dest="estimator",
        required=True,
        help="folder of the trained estimator to start from (train-estimator --out, or an "
        "earlier adapt --out)",
    )
    p.add_argument(
        "--matcher",
        help="group the detections into people with this trained matcher (train-matcher --out); "
        "default: the geometric matcher (symmetric epipolar distance) on every camera",
    )
    _proposal_arguments(p)
    p.add_argument("--out", required=True, help="the adapted model's folder (new or empty)")
    p.add_argument(
        "--matcher-out",
        help="also adapt the matcher (--matcher) to the recording first, on the combined "
        "proposals' groups as labels (no truth), and write it to this folder (new or empty; "
        "`infer --matcher` loads it); the estimator then adapts behind its proposals",
    )
    p.add_argument(
        "--matcher-max-steps",
        type=int,
        default=MATCHER_ADAPT_STEPS,
        help="--matcher-out: most steps of the matcher's adaptation (held-out frames stop it "
        "earlier); the command keeps one wall-clock budget (--max-seconds), of which the "
        "matcher takes at most half",
    )
    p.add_argument("--seed", type=int, default=0, help="batch order and augmentation")
    add_adapt_arguments(p)


@command(
    "adapt",
    "Fine-tune a trained 3D estimator on a recording's own detections (no labels: grouped by "
    "the proposals, reprojection loss, held-out frames stop it); writes a model infer loads.",
    _adapt_arguments,
)
def _adapt(args: argparse.Namespace) -> int:
    from pathlib import Path

    from mvpose_jax.adapt import adapt_estimator, save_adapted_estimator
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.trained import load_estimator, load_matcher

    out = check_writable(args.out, folder=True)
    if out.exists() and any(out.iterdir()):
        raise InputError("exists and is not empty; choose a new folder", file=out, field="--out")
    if args.matcher_out is not None:
        if not args.matcher:
            raise InputError("adapts a matcher: give --matcher", field="--matcher-out")
        matcher_out = check_writable(args.matcher_out, folder=True)
        if matcher_out.exists() and any(matcher_out.iterdir()):
            raise InputError(
                "exists and is not empty; choose a new folder",
                file=matcher_out,
                field="--matcher-out",
            )
    config = adapt_config(args)
    config.check()
    rig_all = load_rig(
        args.rig, translation_scale=args.translation_scale, orthonormalise=args.orthonormalise
    )
    rec, rig = _load_detections(args, rig_all)
    matcher = load_matcher(args.matcher, rig) if args.matcher else None
    # The grouping infer makes with the same options (by default: the combined matcher).
    proposals, threshold, combined = _proposal_settings(args, matcher)
    if args.matcher_out is not None:
        import dataclasses

        from mvpose_jax.adapt import MatcherAdaptConfig, adapt_matcher, save_adapted_matcher
        from mvpose_jax.proposals import read_combined_config

        # One budget for the whole command (the estimator's, --max-seconds or its default
        # rule): the matcher gets at most half of it, the estimator what is left.
        total = config.budget_seconds(len(rec.detections.count))
        matcher, matcher_report = adapt_matcher(
            rig,
            rec.detections,
            matcher,
            combined=read_combined_config(args.matcher),
            config=MatcherAdaptConfig(
                max_steps=args.matcher_max_steps, max_seconds=total / 2, seed=args.seed
            ),
        )
        config = dataclasses.replace(config, max_seconds=max(1.0, total - matcher_report.seconds))
        matcher_report.settings["matcher"] = str(Path(args.matcher).resolve())
        save_adapted_matcher(args.matcher_out, matcher, matcher_report, settings_from=args.matcher)
        r = matcher_report
        print(
            f"adapted the matcher on {r.frames_adapt} frames ({r.pairs_adapt} pairs labelled by "
            f"the combined proposals): held-out pseudo-label loss {r.heldout_loss_before:.4f} -> "
            f"{r.heldout_loss_after:.4f} (agreement {r.heldout_accuracy_before:.3f} -> "
            f"{r.heldout_accuracy_after:.3f}), step {r.best_step} of {r.steps} ({r.stopped}), "
            f"{r.seconds:.0f} s; wrote {args.matcher_out}"
        )
    estimator = load_estimator(args.estimator, rig)
    adapted, report = adapt_estimator(
        rig,
        rec.detections,
        estimator,
        matcher=matcher,
        threshold=threshold,
        half_score_px=args.half_score_px,
        proposals=proposals,
        combined=combined,
        config=config,
    )
    report.settings["estimator"] = str(Path(args.estimator).resolve())
    report.settings["detections"] = str(Path(args.detections).resolve())
    save_adapted_estimator(args.out, adapted, report)
    print_adapt_report(report)
    print(
        f"wrote {args.out} (`infer --estimator {args.out}` loads it) and its report "
        f"{Path(args.out) / 'adapt_report.json'}"
    )
    _print_dev_quality(args.out)
    return 0


# --------------------------------------------------------------------------- infer / evaluate / render


def _load_detections(args: argparse.Namespace, rig):
    """The recording of ``--detections`` (any format; an OpenPose folder too) on the rig's cameras."""
    from mvpose_jax.data import load_recording

    rec = load_recording(args.detections, layout=args.layout, rig=rig, **_reading_options(args))
    return rec, rig.select(list(rec.cameras))


def _reading_options(args: argparse.Namespace) -> dict:
    """The reading options given (OpenPose folders' options and the camera selection)."""
    kwargs = {}
    if getattr(args, "missing_frames", None):
        kwargs["missing_frames"] = args.missing_frames
    if getattr(args, "camera_map", None):
        kwargs["camera_map"] = args.camera_map
    if getattr(args, "source_layout", None):
        kwargs["source_layout"] = args.source_layout
    # Cameras are chosen while loading: an OpenPose folder's other folders (a stray or
    # uncalibrated camera) are never read.
    kwargs["cameras"] = getattr(args, "cameras", None) or None
    return kwargs


def _detection_arguments(p: argparse.ArgumentParser) -> None:
    add_rig_argument(p, default=None)
    p.add_argument(
        "--detections",
        required=True,
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
        type=camera_map,
        default=None,
        metavar="FOLDER=CAMERA,...",
        help="OpenPose folders: the calibration's camera name of each camera folder, e.g. "
        "cam01_json=cam01,cam02_json=cam02 (default: the folder's name, or it without a suffix "
        "tools add: _json, _img, _images, _keypoints)",
    )
    p.add_argument(
        "--source-layout",
        default=None,
        help=f"OpenPose folders: {SOURCE_LAYOUT_HELP}",
    )


def camera_map(text: str) -> dict[str, str]:
    """``FOLDER=CAMERA,...`` as a dict (the ``--camera-map`` option's type)."""
    out = {}
    for item in text.split(","):
        folder, sep, camera = item.partition("=")
        if not sep or not folder.strip() or not camera.strip():
            raise argparse.ArgumentTypeError(f"expected FOLDER=CAMERA, got {item!r}")
        out[folder.strip()] = camera.strip()
    return out


def _convert_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--detections",
        required=True,
        help="the recording to convert: native JSON, the original repository's JSON, .npz, or an "
        "OpenPose folder",
    )
    p.add_argument(
        "--format",
        choices=("native", "original", "npz", "openpose"),
        default=None,
        help="output format (default: npz for a .npz --out, else native JSON)",
    )
    p.add_argument(
        "--layout",
        default=None,
        help="keypoint layout to write (default: the recording's; coco18 for OpenPose input)",
    )
    p.add_argument(
        "--cameras", nargs="+", help="write only these cameras, in this order (default: all)"
    )
    p.add_argument(
        "--missing-frames",
        choices=("error", "empty"),
        default=None,
        help="OpenPose input: a frame missing in some cameras is an error (default) or empty there",
    )
    p.add_argument(
        "--source-layout",
        default=None,
        help=f"OpenPose folders: {SOURCE_LAYOUT_HELP}",
    )
    p.add_argument("--out", required=True, help="output file (a folder for --format openpose)")


@command(
    "convert",
    "Convert a recording between the formats the tools read (native, original, npz, OpenPose).",
    _convert_arguments,
)
def _convert(args: argparse.Namespace) -> int:
    from mvpose_jax.data import load_recording, save_recording, select_cameras

    check_writable(args.out, folder=args.format == "openpose")
    kwargs = {"missing_frames": args.missing_frames} if args.missing_frames else {}
    if args.source_layout:
        kwargs["source_layout"] = args.source_layout
    rec = load_recording(args.detections, layout=args.layout, **kwargs)
    if args.cameras:
        rec = select_cameras(rec, args.cameras, file=args.detections)
    save_recording(rec, args.out, format=args.format)
    print(
        f"{rec.num_frames} frames, {len(rec.cameras)} cameras ({', '.join(rec.cameras)}), layout "
        f"{rec.layout}: wrote {args.out}"
    )
    return 0


def _proposal_arguments(p: argparse.ArgumentParser) -> None:
    """How detections are grouped into people (infer and adapt; `_proposal_settings` reads them)."""
    p.add_argument(
        "--proposals",
        choices=stages.names("proposals"),
        default=None,
        help="how skeletons are grouped into people: combined (the default with --matcher: the "
        "GAT's scores joined with epipolar geometry, each frame kept on the grouping that agrees "
        "better with the geometry; settings from the --matcher folder), gat (the GAT's scores "
        "alone, --threshold; the paper's) or epipolar (the default without --matcher: symmetric "
        "epipolar distance, --half-score-px)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=None,
        help="--proposals gat or epipolar: least match score to join two skeletons (default: the "
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


def _proposal_settings(args: argparse.Namespace, matcher):
    """(proposals, threshold, combined config or None) of `_proposal_arguments`' options.

    --threshold is the GAT's and the epipolar matcher's setting; the combined matcher's come from
    the --matcher folder, so a given one would be silently ignored: it is refused instead.
    """
    from mvpose_jax.proposals import read_combined_config, read_proposal_threshold

    proposals = args.proposals or ("combined" if matcher is not None else "epipolar")
    if proposals != "epipolar" and matcher is None:
        raise InputError(f"--proposals {proposals} needs --matcher", field="--proposals")
    if args.threshold is not None and proposals == "combined":
        raise InputError(
            "sets the GAT's or the epipolar matcher's proposals, not the combined matcher's (its "
            "settings are the --matcher folder's proposal_threshold.json); add --proposals gat "
            "to group by the GAT alone at this threshold",
            field="--threshold",
        )
    threshold = read_proposal_threshold(args.matcher, args.threshold)
    combined = read_combined_config(args.matcher) if proposals == "combined" else None
    return proposals, threshold, combined


def _infer_arguments(p: argparse.ArgumentParser) -> None:
    _detection_arguments(p)
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
    _proposal_arguments(p)
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


def adapt_config(args: argparse.Namespace, *, prefix: str = ""):
    """The `adapt.AdaptConfig` of `add_adapt_arguments`' options."""
    from mvpose_jax.adapt import AdaptConfig

    def get(name):
        return getattr(args, prefix.replace("-", "_") + name)

    return AdaptConfig(
        learning_rate=get("learning_rate"),
        max_steps=get("max_steps"),
        max_seconds=get("max_seconds"),
        patience=get("patience"),
        holdout_every=get("holdout_every"),
        block_frames=get("block_frames"),
        min_views=getattr(args, "min_views", 2),
        seed=getattr(args, "seed", 0),
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


def _smoothing(args: argparse.Namespace):
    """The smoothing options as (OneEuroConfig, smooth_poses keyword arguments)."""
    from mvpose_jax.smoothing import OneEuroConfig

    for name in ("cutoff_hz", "min_cutoff", "fps"):
        value = getattr(args, name)
        if value is not None and value <= 0:
            raise InputError("must be > 0", field="--" + name.replace("_", "-"))
    for name in ("fill_gap_s", "outlier_m", "beta"):
        if getattr(args, name) < 0:
            raise InputError("must be >= 0", field="--" + name.replace("_", "-"))
    one_euro = OneEuroConfig(min_cutoff_hz=args.min_cutoff, beta=args.beta)
    return one_euro, {
        "cutoff_hz": args.cutoff_hz,
        "fill_gap_s": args.fill_gap_s,
        "outlier_m": args.outlier_m or None,
        "one_euro": one_euro,
    }


@command(
    "infer",
    "3D poses from a calibration and 2D detections: matching, proposals, estimator or "
    "triangulation; a chunk of frames at a time (Ctrl-C keeps the finished chunks: --resume).",
    _infer_arguments,
)
def _infer(args: argparse.Namespace) -> int:
    from mvpose_jax.jobs.infer import covered, run_infer

    check_writable(args.out, folder=True)
    config = infer_config(args)

    def notify(kind: str, message: str) -> None:
        if kind == "resuming":
            print(message)
        else:
            print(f"mvpose-jax infer: {message}", file=sys.stderr)

    try:
        res = run_infer(config, notify=notify)
    except InputError as e:
        raise _named_by_option(e) from None
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
    threshold = res.pipeline.matching.threshold
    if people == 0 and frames > 0 and start == 0:
        warnings.warn(
            _why_nobody(res.max_views, res.cameras, args, threshold), MvposeWarning, stacklevel=1
        )
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
    if res.exported:
        print(f"exported {len(res.exported)} files: " + ", ".join(p.name for p in res.exported))
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
    "adapt": "--adapt",
    "chunk_frames": "--chunk-frames",
    "pipeline.chunk_frames": "--chunk-frames",
    "pipeline.matching.proposals": "--proposals",
    "pipeline.matching.threshold": "--threshold",
    "pipeline.matching.min_views": "--min-views",
    "pipeline.matching.half_score_px": "--half-score-px",
    "pipeline.lifting.method": "--method",
    "pipeline.lifting.outlier_px": "--outlier-px",
    "pipeline.lifting.view_outlier_px": "--view-outlier-px",
    "pipeline.tracked": "--no-track",
    "pipeline.tracking.max_gap_s": "--max-gap-s",
    "pipeline.filtering.name": "--filter",
    "pipeline.filtering.cutoff_hz": "--cutoff-hz",
    "pipeline.filtering.fill_gap_s": "--fill-gap-s",
    "pipeline.filtering.outlier_m": "--outlier-m",
    "pipeline.filtering.one_euro.min_cutoff_hz": "--min-cutoff",
    "pipeline.filtering.one_euro.beta": "--beta",
}


def _named_by_option(e: InputError) -> InputError:
    """``e`` with its field (a config path) replaced by the option that sets it."""
    option = _OPTION_OF_SETTING.get(e.field or "")
    if option is None:
        return e
    return InputError(e.reason, file=e.file, frame=e.frame, camera=e.camera, field=option)


def infer_config(args: argparse.Namespace):
    """The `jobs.infer.InferConfig` of infer's options (the combinations of options checked
    here, so that a refusal names them)."""
    from mvpose_jax.inference import FilterConfig, PipelineConfig
    from mvpose_jax.jobs.infer import InferConfig, RecordingSource
    from mvpose_jax.lifting import LiftingConfig
    from mvpose_jax.matching import MatchingConfig
    from mvpose_jax.tracking import TrackingConfig

    needs_estimator = args.method and stages.lookup("lifting", args.method).needs_estimator
    if needs_estimator and not args.estimator:
        raise InputError(f"--method {args.method} needs --estimator", field="--method")
    if args.method and not needs_estimator and args.estimator:
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
    proposals = args.proposals or ("combined" if args.matcher else "epipolar")
    if stages.lookup("proposals", proposals).needs_matcher and not args.matcher:
        raise InputError(f"--proposals {proposals} needs --matcher", field="--proposals")
    if args.threshold is not None and proposals == "combined":
        raise InputError(
            "sets the GAT's or the epipolar matcher's proposals, not the combined matcher's (its "
            "settings are the --matcher folder's proposal_threshold.json); add --proposals gat "
            "to group by the GAT alone at this threshold",
            field="--threshold",
        )
    if args.max_gap_s < 0:
        raise InputError("must be >= 0", field="--max-gap-s")
    one_euro, _ = _smoothing(args)
    adapt = adapt_config(args, prefix="adapt-") if args.adapt else None
    lifting = {
        k: v
        for k, v in (("outlier_px", args.outlier_px), ("view_outlier_px", args.view_outlier_px))
        if v is not None
    }
    pipeline = PipelineConfig(
        matching=MatchingConfig(args.proposals, args.threshold, args.min_views, args.half_score_px),
        lifting=LiftingConfig(args.method, **lifting),
        tracking=None if args.no_track else TrackingConfig(max_gap_s=args.max_gap_s),
        filtering=FilterConfig(
            args.filter, one_euro, args.cutoff_hz, args.fill_gap_s, args.outlier_m or None
        ),
        chunk_frames=args.chunk_frames,
    )
    source = RecordingSource(
        rig=args.rig,
        detections=args.detections,
        translation_scale=args.translation_scale,
        orthonormalise=args.orthonormalise,
        layout=args.layout,
        cameras=tuple(args.cameras) if args.cameras else None,
        missing_frames=args.missing_frames,
        camera_map=tuple(args.camera_map.items()) if args.camera_map else None,
        source_layout=args.source_layout,
    )
    return InferConfig(
        source,
        args.out,
        pipeline,
        matcher=args.matcher,
        estimator=args.estimator,
        fps=args.fps,
        resume=args.resume,
        keep_chunks=args.keep_chunks,
        export=_export_formats(args.export) if args.export else (),
        adapt=adapt,
    )


def _smooth_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--poses", required=True, help="tracked poses.npz / poses.json (or their folder) from infer"
    )
    add_smoothing_arguments(p, default_filter="butterworth")
    p.add_argument("--out", required=True, help="output folder: poses.json and poses.npz")


@command(
    "smooth",
    "Filter tracked 3D poses per track (Butterworth or One-Euro) and fill short gaps, flagging "
    "the filled keypoints.",
    _smooth_arguments,
)
def _smooth(args: argparse.Namespace) -> int:
    import numpy as np

    from mvpose_jax.data.poses import load_poses, save_poses
    from mvpose_jax.smoothing import smooth_poses

    check_writable(args.out, folder=True)
    _, smooth_kwargs = _smoothing(args)
    poses = load_poses(args.poses)
    fps = args.fps or _recording_fps(poses.timestamps)
    try:
        out = smooth_poses(poses, fps=fps, filter=args.filter, **smooth_kwargs)
    except InputError as e:
        raise e.at(file=args.poses) from None
    npz_path, json_path = save_poses(out, args.out)
    print(
        f"{len(out.confidence)} frames, {len(np.unique(out.track[out.poses.valid & (out.track >= 0)]))} tracks at "
        f"{fps:g} fps; {args.filter} filter, {int(out.filled.sum())} keypoints filled; wrote "
        f"{json_path} and {npz_path}"
    )
    return 0


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


def _poses_and_detections(args: argparse.Namespace):
    """``--poses`` (written by infer) and the ``--detections`` they were made from, on their
    cameras: (PoseResults, Recording, Rig). Poses that cannot come from these detections (another
    layout, frame count or more skeletons per view) are an error."""
    import numpy as np

    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.data.poses import load_poses

    rig_all = load_rig(
        args.rig, translation_scale=args.translation_scale, orthonormalise=args.orthonormalise
    )
    poses = load_poses(args.poses)
    args.cameras = list(poses.cameras)
    rec, rig = _load_detections(args, rig_all)
    if rec.layout != poses.layout:
        raise InputError(
            f"poses are in layout {poses.layout!r}, the detections in {rec.layout!r}; pass --layout",
            file=args.poses,
            field="layout",
        )
    F, P = rec.num_frames, np.shape(rec.detections.score)[2]
    if len(poses.confidence) != F or poses.identity.shape[2] > P:
        partial = (
            f" (partial results of an interrupted infer, {poses.frames_total} frames in all: "
            "finish them with infer --resume)"
            if poses.partial
            else ""
        )
        raise InputError(
            f"poses have {len(poses.confidence)} frames and {poses.identity.shape[2]} skeletons per "
            f"view; the detections {F} and {P}{partial}",
            file=args.poses,
            field="frames",
        )
    return poses, rec, rig


def _evaluate_arguments(p: argparse.ArgumentParser) -> None:
    _detection_arguments(p)
    p.add_argument(
        "--poses", required=True, help="poses.npz / poses.json (or their folder) written by infer"
    )
    p.add_argument("--out", help="also write the metrics to this JSON file")


@command(
    "evaluate",
    "Score 3D poses: MPJPE, AP, recall, PCP and matching against ground truth when the recording has "
    "it; reprojection error per camera always.",
    _evaluate_arguments,
)
def _evaluate(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from mvpose_jax.data.files import atomic_write_text
    from mvpose_jax.lifting import group_people
    from mvpose_jax.metrics import matching_scores, pose_metrics, reprojection_errors

    if args.out:
        check_writable(args.out, folder=False)

    poses, rec, rig = _poses_and_detections(args)
    F = rec.num_frames
    out = {"frames": F, "people": int(poses.poses.valid.sum())}
    if rec.ground_truth is not None:
        out["pose"] = pose_metrics(
            poses.poses, rec.ground_truth, layout=rec.layout, confidence=poses.confidence
        )
    if rec.identity is not None:
        P = np.shape(rec.detections.score)[2]
        ident = np.pad(
            poses.identity, [(0, 0), (0, 0), (0, P - poses.identity.shape[2])], constant_values=-1
        )
        out["matching"] = matching_scores(
            np.asarray(rec.identity), ident, np.asarray(rec.detections.count)
        )
    p_xy, p_sc = group_people(rec.detections.xy, rec.detections.score, poses.members)
    v = np.asarray(poses.poses.valid)
    out["reprojection_px"] = reprojection_errors(
        rig, poses.poses.xyz[v], poses.poses.keypoint_valid[v], p_xy[v], p_sc[v]
    )
    lines = [f"{F} frames, {out['people']} people"]
    if "pose" in out:
        m = out["pose"]
        lines.append(
            f"3D vs ground truth: MPJPE {m['mpjpe_mm']:.2f} mm, mAP {m['map']:.2f}, mean recall "
            f"{m['mean_recall']:.2f}, PCP {m['pcp']:.2f}, completeness {m['completeness']:.2f} %"
        )
    if "matching" in out:
        m = out["matching"]
        lines.append(
            f"matching vs true identities: ARI {m['ari']:.4f}, H {m['homogeneity']:.4f}, "
            f"C {m['completeness']:.4f}, Vm {m['v_measure']:.4f}"
        )
    lines.append("reprojection error (px, mean / median / keypoints):")
    for cam, e in out["reprojection_px"].items():
        lines.append(f"  {cam:>12s}  {e['mean']:8.2f} / {e['median']:8.2f} / {int(e['count'])}")
    print("\n".join(lines))
    if args.out:
        atomic_write_text(args.out, json.dumps(out, indent=1) + "\n")
    return 0


def _render_arguments(p: argparse.ArgumentParser) -> None:
    _detection_arguments(p)
    p.add_argument(
        "--poses", required=True, help="poses.npz / poses.json (or their folder) written by infer"
    )
    p.add_argument(
        "--out", required=True, help="output folder (per-frame PNGs, figures) or an .mp4 file"
    )
    p.add_argument(
        "--frames", type=int, nargs="+", help="frames to draw (default: every --every-th frame)"
    )
    p.add_argument("--every", type=int, default=1, help="draw every N-th frame (default 1)")
    p.add_argument(
        "--images",
        help="folder of the camera images (the recording's image names, relative to it); "
        "default: a white canvas",
    )
    p.add_argument(
        "--scale", type=float, default=0.5, help="size of each camera view (default 0.5)"
    )
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="frame rate of an .mp4 (default: the recording's, from its timestamps; else 30)",
    )
    p.add_argument(
        "--figures-3d",
        action="store_true",
        help="also a 3D skeleton figure per frame (folder output)",
    )


@command(
    "render",
    "Draw 3D poses over each camera's view (detections thin, reprojected people thick, one colour "
    "per person: per track when tracked) as images or an mp4, and 3D skeleton figures.",
    _render_arguments,
)
def _render(args: argparse.Namespace) -> int:
    from pathlib import Path

    import cv2
    import numpy as np
    from tqdm.auto import tqdm

    from mvpose_jax.render import (
        VideoWriter,
        draw_view,
        save_figure,
        skeleton_figure,
        tile,
        write_image,
    )

    check_writable(args.out, folder=Path(args.out).suffix.lower() != ".mp4")
    poses, rec, rig = _poses_and_detections(args)
    F = rec.num_frames
    if args.every < 1 or args.scale <= 0:
        raise InputError("--every must be >= 1 and --scale > 0", field="--every/--scale")
    frames = args.frames if args.frames else list(range(0, F, args.every))
    bad = [f for f in frames if not 0 <= f < F]
    if bad:
        raise InputError(f"frames {bad} are outside 0..{F - 1}", frame=bad[0], field="--frames")
    out = Path(args.out)
    video = out.suffix.lower() == ".mp4"
    xy, score = np.asarray(rec.detections.xy), np.asarray(rec.detections.score)
    count = np.asarray(rec.detections.count)
    P = poses.identity.shape[2]

    def image_of(f, c):
        if not args.images or rec.image_names is None:
            return None
        path = Path(args.images) / str(rec.image_names[f, c])
        img = cv2.imread(str(path))
        if img is None:
            raise InputError("cannot read this image", file=path, frame=f, camera=rec.cameras[c])
        return img

    def picture(f):
        v = poses.poses.valid[f]
        views = []
        for c in range(len(rec.cameras)):
            n = int(count[f, c])
            ident = poses.identity[f, c, :n] if n <= P else np.full(n, -1)
            xyz = np.where(v[:, None, None], poses.poses.xyz[f], np.nan)
            views.append(
                draw_view(
                    rig,
                    c,
                    rec.layout,
                    image=image_of(f, c),
                    detections=(xy[f, c, :n], score[f, c, :n]),
                    identity=ident,
                    xyz=xyz,
                    keypoint_valid=poses.poses.keypoint_valid[f] & v[:, None],
                    colours=None if poses.track is None else poses.track[f],
                    scale=args.scale,
                )
            )
        img = tile(views)
        cv2.putText(
            img,
            f"frame {f}",
            (8, img.shape[0] - 10),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.6,
            (40, 40, 40),
            1,
            cv2.LINE_AA,
        )
        return img

    written = 0
    if video:
        with VideoWriter(out, args.fps or _recording_fps(rec.timestamps)) as writer:
            for f in tqdm(frames, desc="render", unit="frame"):
                writer.write(picture(f))
                written += 1
        print(f"wrote {written} frames to {out}")
        return 0
    for f in tqdm(frames, desc="render", unit="frame"):
        write_image(out / f"frame_{f:06d}.png", picture(f))
        if args.figures_3d:
            v = poses.poses.valid[f]
            panels = {"ours": (poses.poses.xyz[f][v], poses.poses.keypoint_valid[f][v])}
            if rec.ground_truth is not None:
                gv = np.asarray(rec.ground_truth.valid[f])
                panels = {
                    "ground truth": (
                        np.asarray(rec.ground_truth.xyz[f])[gv],
                        np.asarray(rec.ground_truth.keypoint_valid[f])[gv],
                    ),
                    **panels,
                }
            save_figure(
                skeleton_figure(panels, rec.layout, rig=rig, title=f"frame {f}"),
                out / f"frame_{f:06d}_3d.png",
            )
        written += 1
    print(f"wrote {written} frames to {out}")
    return 0


# --------------------------------------------------------------------------- export
#   mvpose-jax export --poses poses/ --format trc,c3d --rig calib.toml --out opensim/

_EXPORT_SUFFIXES = (".trc", ".c3d", ".csv")


def _export_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--poses", required=True, help="poses.npz / poses.json (or their folder) written by infer"
    )
    p.add_argument(
        "--format",
        action="append",
        required=True,
        metavar="FORMATS",
        help="trc, c3d and/or csv: a comma list, or the option given several times",
    )
    p.add_argument(
        "--out",
        required=True,
        help="output folder (files named poses_track<id>.trc, poses.csv ...) or a file "
        "(walk.trc: walk_track<id>.trc, walk_track<id>.c3d, walk.csv ...)",
    )
    add_rig_argument(p, default=None, required=False)
    p.add_argument(
        "--up",
        help="the world's up direction X,Y,Z, instead of the rig's (--rig); the OpenSim axes "
        "need one of the two",
    )
    p.add_argument(
        "--axes",
        choices=("opensim", "world"),
        default="opensim",
        help="opensim: rotate so that Y is up (X the world axis most orthogonal to up, in the "
        "floor plane; see docs/exports.md); world: the calibration's axes as they are",
    )
    p.add_argument("--units", choices=("mm", "m"), default="mm", help="units of the coordinates")
    p.add_argument(
        "--fps",
        type=float,
        help="frame rate (default: from the poses' timestamps; required without them)",
    )
    files = p.add_mutually_exclusive_group()
    files.add_argument(
        "--per-track",
        dest="per_track",
        action="store_true",
        default=True,
        help="one TRC/C3D file per track, markers named after the keypoints (the default)",
    )
    files.add_argument(
        "--one-file",
        dest="per_track",
        action="store_false",
        help="one TRC/C3D file of every track, markers named t<id>_<keypoint>",
    )


def _export_formats(values: Sequence[str]) -> tuple[str, ...]:
    """``--format trc,c3d --format csv`` -> ("trc", "c3d", "csv"); an unknown one is an error."""
    from mvpose_jax.data.exports import EXPORT_FORMATS

    formats = []
    for value in values:
        for fmt in value.split(","):
            fmt = fmt.strip().lower()
            if fmt not in EXPORT_FORMATS:
                raise InputError(
                    f"unknown format {fmt!r}; choose from {', '.join(EXPORT_FORMATS)}",
                    field="--format",
                )
            if fmt not in formats:
                formats.append(fmt)
    return tuple(formats)


def _up_option(text: str) -> tuple[float, float, float]:
    try:
        up = tuple(float(v) for v in text.split(","))
    except ValueError:
        up = ()
    if len(up) != 3:
        raise InputError(f"expected three numbers X,Y,Z, got {text!r}", field="--up")
    return up


@command(
    "export",
    "Write 3D poses (infer's) as TRC and C3D marker files for OpenSim and motion-capture tools, "
    "or as a tidy CSV.",
    _export_arguments,
)
def _export(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from mvpose_jax.cameras import up_vector
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.data.exports import ExportConfig, export_poses
    from mvpose_jax.data.poses import load_poses

    formats = _export_formats(args.format)
    out = Path(args.out)
    to_file = out.suffix.lower() in _EXPORT_SUFFIXES
    check_writable(args.out, folder=not to_file)
    stem = out.with_suffix("") if to_file else out / "poses"
    up = None
    if args.axes == "opensim":
        if args.rig and args.up:
            raise InputError("give the up direction once: --rig or --up, not both", field="--up")
        if args.up:
            up = _up_option(args.up)
        elif args.rig:
            rig = load_rig(
                args.rig,
                translation_scale=args.translation_scale,
                orthonormalise=args.orthonormalise,
            )
            up = tuple(float(v) for v in up_vector(rig))
        else:
            raise InputError(
                "the OpenSim axes need the world's up: give --rig (the calibration infer used) "
                "or --up X,Y,Z, or keep the calibration's axes with --axes world",
                field="--rig",
            )
    config = ExportConfig(formats, args.units, args.per_track, args.fps, args.axes, up)
    paths = export_poses(load_poses(args.poses), stem, config, progress=True)
    axes = "world axes" if up is None else f"OpenSim axes (Y = up {np.round(up, 3).tolist()})"
    print(f"wrote {len(paths)} files ({args.units}, {axes}) to {stem.parent}")
    for path in paths:
        print(f"  {path.name}")
    return 0


def _print_dev_quality(folder: str) -> None:
    """The estimator against triangulation on the dev people (`train.compare_with_triangulation`)."""
    import json
    from pathlib import Path

    from mvpose_jax.trained import DEV_QUALITY_FILE

    path = Path(folder) / DEV_QUALITY_FILE
    if path.is_file():
        q = json.loads(path.read_text())
        verdict = "better" if q["estimator_px"] <= q["triangulation_px"] else "WORSE"
        print(
            f"dev reprojection on the {q['keypoints']} keypoints triangulation reconstructs: "
            f"estimator {q['estimator_px']:.2f} px, triangulation {q['triangulation_px']:.2f} px "
            f"({verdict} than triangulation)"
        )


def _recording_fps(timestamps) -> float:
    """Frames per second from a recording's timestamps (their median step); 30 without them."""
    from mvpose_jax.data.recording import recording_fps

    return recording_fps(timestamps)


class _DefaultsHelpFormatter(argparse.HelpFormatter):
    """Every option's help ends with its default, unless the help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        shown = action.default not in (None, argparse.SUPPRESS, False) and action.nargs != 0
        if shown and "default" not in text and "%(default)" not in text:
            text += " (default: %(default)s)"
        return text


def version() -> str:
    """The installed package's version (read without importing jax)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as package_version

    try:
        return package_version("mvpose-jax")
    except PackageNotFoundError:  # a source checkout that was never installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mvpose-jax",
        description=__doc__.splitlines()[0],
        formatter_class=_DefaultsHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mvpose-jax {version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_, add, _) in _COMMANDS.items():
        p = sub.add_parser(
            name, help=help_, description=help_, formatter_class=_DefaultsHelpFormatter
        )
        add(p)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """The package's warnings as one plain line (no source location); others as Python shows them."""
    if issubclass(category, MvposeWarning):
        print(f"mvpose-jax: warning: {message}", file=sys.stderr)
    else:
        _python_show_warning(message, category, filename, lineno, file, line)


_python_show_warning = warnings.showwarning


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return _COMMANDS[args.command][2](args) or 0
    except MvposeError as e:
        print(f"mvpose-jax {args.command}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader went away (`mvpose-jax rig | head`): not our error; silence the final flush.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
