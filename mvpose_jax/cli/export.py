"""``mvpose-jax export``: infer's 3D poses as TRC, C3D or CSV files."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import add_rig_argument, rig_source
from mvpose_jax.cli.registry import command
from mvpose_jax.jobs.export import ExportJob, export

#   mvpose-jax export --poses poses/ --format trc,c3d --rig calib.toml --out opensim/


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


@command(
    "export",
    "Write 3D poses (infer's) as TRC and C3D marker files for OpenSim and motion-capture tools, "
    "or as a tidy CSV.",
    _export_arguments,
)
def _export(args: argparse.Namespace) -> int:
    import numpy as np

    job = ExportJob(
        poses=args.poses,
        formats=tuple(args.format),
        out=args.out,
        rig=rig_source(args) if args.rig else None,
        up=args.up,
        axes=args.axes,
        units=args.units,
        fps=args.fps,
        per_track=args.per_track,
    )
    done = export(job)
    up = done.up
    axes = "world axes" if up is None else f"OpenSim axes (Y = up {np.round(up, 3).tolist()})"
    print(f"wrote {len(done.paths)} files ({args.units}, {axes}) to {done.folder}")
    for path in done.paths:
        print(f"  {path.name}")
    return 0
