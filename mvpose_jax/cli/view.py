"""``mvpose-jax view``: any pose result as a rerun recording (`jobs.view`)."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import (
    add_detection_options,
    add_rig_argument,
    check_writable,
    detections_source,
    rig_source,
)
from mvpose_jax.cli.registry import command


def _view_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("poses", help="poses.npz / poses.json (or their folder), as infer writes them")
    add_rig_argument(p, default=None)
    p.add_argument(
        "--detections",
        help="the detections the poses were made from (drawn in each camera beside the poses' "
        "reprojections); default: none",
    )
    add_detection_options(p, what="--detections")
    p.add_argument("--out", required=True, help="the rerun recording to write (FILE.rrd)")
    p.add_argument(
        "--floor-height",
        type=float,
        default=None,
        help="the floor's height along the rig's up, metres (default: under the people's lowest "
        "keypoints)",
    )
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="frame rate of the timeline when neither the poses nor the detections have "
        "timestamps (default: a frame timeline only)",
    )
    p.add_argument(
        "--spawn",
        action="store_true",
        help="open rerun's viewer on the file afterwards (needs a display)",
    )


@command(
    "view",
    "Write 3D poses, their cameras and the detections as a rerun recording (.rrd) to look at in "
    '3D over time (needs the viewer extra: pip install "mvpose-jax[viewer]").',
    _view_arguments,
)
def _view(args: argparse.Namespace) -> int:
    from mvpose_jax.jobs.view import ViewConfig, run_view

    check_writable(args.out, folder=False)
    config = ViewConfig(
        args.poses,
        rig_source(args),
        args.out,
        detections=detections_source(args) if args.detections else None,
        floor_height=args.floor_height,
        fps=args.fps,
        spawn=args.spawn,
    )
    path = run_view(config)
    print(f"wrote {path} (rerun {path} shows it)")
    return 0
