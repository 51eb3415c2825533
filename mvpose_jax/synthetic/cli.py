"""``mvpose-jax generate``: synthetic recordings from the command line (wired in by `mvpose_jax.cli`).

    mvpose-jax generate --rig panoptic5 --people 4 --frames 500 --seed 0 --out scene.json
    mvpose-jax generate --rig arplab6 --single-person-recordings 20 --frames 1000 --out train/
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from mvpose_jax.synthetic.config import DetectorConfig, MotionConfig, SceneConfig, SyntheticConfig

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


def add_generate_arguments(parser: argparse.ArgumentParser) -> None:
    """Adds the options of ``generate`` to a parser (``--rig`` comes from `mvpose_jax.cli`)."""
    parser.add_argument("--people", type=int, default=4, help="people in the scene (default 4)")
    parser.add_argument("--frames", type=int, default=500, help="frames per recording (default 500)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--out", required=True,
        help="output file (.json native, .npz) or, with --single-person-recordings, a folder",
    )  # fmt: skip
    parser.add_argument(
        "--single-person-recordings", type=int, default=0, metavar="N",
        help="write N one-person training recordings into the --out folder instead of one scene",
    )  # fmt: skip
    parser.add_argument(
        "--format", choices=("native", "npz"), default=None,
        help="file format for the single-person recordings (default native JSON)",
    )  # fmt: skip
    parser.add_argument("--fps", type=float, default=MotionConfig.fps, help=f"frame rate (default {MotionConfig.fps:g})")
    parser.add_argument(
        "--floor-height", type=float, default=None,
        help="floor height along the up vector, metres (default: estimated from the cameras)",
    )  # fmt: skip
    parser.add_argument(
        "--clean", action="store_true",
        help="a perfect detector: no noise, offsets, drops, misses, false positives or swaps",
    )  # fmt: skip
    defaults = DetectorConfig()
    for option, field in _RATE_OPTIONS.items():
        parser.add_argument(
            f"--{option}", type=float, default=None,
            help=f"detector {field.replace('_', ' ')} (default {getattr(defaults, field):g})",
        )  # fmt: skip


def config_from_args(args: argparse.Namespace) -> SyntheticConfig:
    """The `SyntheticConfig` the options describe."""
    detector = DetectorConfig().clean() if args.clean else DetectorConfig()
    changes = {
        field: getattr(args, option.replace("-", "_"))
        for option, field in _RATE_OPTIONS.items()
        if getattr(args, option.replace("-", "_")) is not None
    }
    return SyntheticConfig(
        detector=dataclasses.replace(detector, **changes),
        motion=dataclasses.replace(MotionConfig(), fps=args.fps),
        scene=dataclasses.replace(SceneConfig(), floor_height=args.floor_height),
    )


def run_generate(args: argparse.Namespace) -> int:
    """Generates and writes the recording(s); returns the exit status."""
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.data.formats import save_recording
    from mvpose_jax.synthetic.generate import generate_recording, generate_single_person_recordings

    rig = load_rig(args.rig, translation_scale=getattr(args, "translation_scale", 1.0))
    config = config_from_args(args)
    out = Path(args.out)
    if args.single_person_recordings > 0:
        recordings = generate_single_person_recordings(
            rig, num_recordings=args.single_person_recordings, num_frames=args.frames,
            config=config, seed=args.seed, progress=True,
        )  # fmt: skip
        suffix = ".npz" if args.format == "npz" else ".json"
        width = len(str(len(recordings) - 1))
        for i, rec in enumerate(recordings):
            path = out / f"person_{i:0{width}d}{suffix}"
            save_recording(rec, path, rig=rig if suffix == ".json" else None)
        print(f"wrote {len(recordings)} single-person recordings of {args.frames} frames to {out}/")
        return 0
    rec = generate_recording(
        rig, num_people=args.people, num_frames=args.frames, config=config, seed=args.seed,
        progress=True,
    )  # fmt: skip
    native = out.suffix.lower() != ".npz"
    save_recording(rec, out, rig=rig if native else None)
    det = rec.detections
    print(
        f"wrote {out}: {rec.num_frames} frames, {len(rec.cameras)} cameras, {args.people} people, "
        f"{int(det.count.sum())} detections"
    )
    return 0
