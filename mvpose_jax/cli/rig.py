"""``mvpose-jax rig``: a rig's cameras, centre and up; the floor measured from people on it."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import (
    add_detection_options,
    add_rig_argument,
    detections_source,
    rig_source,
)
from mvpose_jax.cli.registry import command
from mvpose_jax.jobs.rig import RigConfig, describe_rig


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

    detections = detections_source(args) if args.detections else None
    d = describe_rig(RigConfig(rig_source(args), detections))
    rig = d.rig
    print(
        f"{rig.num_cameras} cameras; up {np.round(d.up, 3).tolist()}"
        f"{' (inferred)' if rig.up is None else ''}; centre {np.round(d.centre, 3).tolist()} m,"
        f" radius {d.radius:.3f} m"
    )
    for c, name in enumerate(rig.names):
        w, h = np.asarray(rig.size[c]).astype(int)
        print(
            f"  {name:>12s}  {w}x{h}  f={float(rig.K[c, 0, 0]):.1f}px  centre {np.round(d.centres[c], 3).tolist()}"
        )
    if d.floor is not None:
        measured, guess = d.floor, d.floor_guess
        print(
            f"floor measured from the people: {measured.describe()}; {guess:.3f} m guessed "
            f"from the cameras; the guess is {guess - measured.height:+.3f} m off"
        )
    return 0
