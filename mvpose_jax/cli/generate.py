"""``mvpose-jax generate`` and ``synthetic-figure``: synthetic recordings on any rig."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import (
    add_detection_options,
    add_pool_arguments,
    add_rig_argument,
    detections_source,
    pool_config,
    rig_source,
)
from mvpose_jax.cli.registry import command
from mvpose_jax.errors import InputError
from mvpose_jax.jobs.generate import (
    RATE_OPTIONS,
    TRAINING_FLOOR_JITTER_M,
    GenerateConfig,
    SyntheticFigureConfig,
    generate,
    synthetic_figure,
)

#   mvpose-jax generate --rig panoptic5 --people 4 --frames 500 --seed 0 --out scene.json
#   mvpose-jax generate --rig arplab6 --single-person-recordings 20 --frames 1000 --out train/


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
        "--recordings",
        type=int,
        default=0,
        metavar="N",
        help="write N recordings into the --out folder or fsspec URL (recording_<i>.json or "
        ".npz), recording "
        "i with seed --seed + i, on a pool of Ray workers (--workers, --address; "
        'pip install "mvpose-jax[cluster]"): the same files whatever the number of workers',
    )
    p.add_argument(
        "--single-person",
        action="store_true",
        help="with --recordings: one-person training recordings (the floor jittered as "
        "--single-person-recordings' are) instead of scenes of --people",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="with --recordings: skip the recordings OUT/batch.json records as written",
    )
    add_pool_arguments(p)
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
    p.add_argument(
        "--detector-like",
        metavar="DETECTIONS",
        default=None,
        help="simulate a detector that behaves like yours: its noise, left/right swaps, missed "
        "keypoints and people, false skeletons, limb mixes, border losses and scores, fitted "
        "without labels to your own detections on this rig (native JSON, original JSON, .npz or "
        "an OpenPose folder) by comparing each camera with the other cameras' triangulation",
    )
    add_detection_options(p, what="--floor-from, --detector-like")
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
    for option, field in RATE_OPTIONS.items():
        p.add_argument(
            f"--{option}",
            type=float,
            default=None,
            help=f"detector {field.replace('_', ' ')} (default {getattr(defaults, field):g})",
        )


@command(
    "generate",
    "Generate a synthetic recording (or single-person training recordings) on any rig.",
    _generate_arguments,
)
def _generate(args: argparse.Namespace) -> int:
    rates = {
        field: getattr(args, option.replace("-", "_"))
        for option, field in RATE_OPTIONS.items()
        if getattr(args, option.replace("-", "_")) is not None
    }
    config = GenerateConfig(
        rig=rig_source(args),
        out=args.out,
        people=args.people,
        frames=args.frames,
        seed=args.seed,
        single_person_recordings=args.single_person_recordings,
        format=args.format,
        fps=args.fps,
        floor_height=args.floor_height,
        floor_from=detections_source(args, args.floor_from) if args.floor_from else None,
        floor_jitter=args.floor_jitter,
        clean=args.clean,
        detector_like=(detections_source(args, args.detector_like) if args.detector_like else None),
        rates=rates,
    )
    if args.recordings:
        return _generate_recordings(args, config)
    if args.single_person or args.resume:
        raise InputError(
            "goes with --recordings", field="--single-person" if args.single_person else "--resume"
        )
    done = generate(config)
    if done.floor is not None:
        measured = done.floor
        print(f"floor measured from {args.floor_from}: {measured.describe()}")
    if done.detector is not None:
        print(f"{args.detector_like}: " + "\n".join(done.detector.describe()))
    if args.single_person_recordings > 0:
        print(
            f"wrote {done.recordings} single-person recordings of {args.frames} frames to {done.out}/"
        )
        return 0
    print(
        f"wrote {done.out}: {done.frames} frames, {done.cameras} cameras, {args.people} people, "
        f"{done.detections} detections"
    )
    return 0


def _generate_recordings(args: argparse.Namespace, config: GenerateConfig) -> int:
    """``--recordings N``: the recordings on the Ray pool (`jobs.batch.run_generate_batch`)."""
    from mvpose_jax.cli.batch import print_summary
    from mvpose_jax.jobs.batch import run_generate_batch

    res = run_generate_batch(
        config,
        args.recordings,
        pool_config(args),
        single_person=args.single_person,
        resume=args.resume,
    )
    return print_summary(res, "generate")


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
    config = SyntheticFigureConfig(
        rig=rig_source(args),
        out=args.out,
        people=args.people,
        frames=args.frames,
        frame=args.frame,
        seed=args.seed,
    )
    print(synthetic_figure(config))
    return 0
