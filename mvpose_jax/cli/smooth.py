"""``mvpose-jax smooth``: tracked 3D poses filtered per track, short gaps filled."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import add_smoothing_arguments, smoothing_options
from mvpose_jax.cli.registry import command
from mvpose_jax.jobs.smooth import SmoothConfig, smooth


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
    done = smooth(SmoothConfig(args.poses, args.out, smoothing_options(args)))
    print(
        f"{done.frames} frames, {done.tracks} tracks at "
        f"{done.fps:g} fps; {args.filter} filter, {done.filled} keypoints filled; wrote "
        f"{done.json} and {done.npz}"
    )
    return 0
