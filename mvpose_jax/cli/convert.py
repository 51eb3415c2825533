"""``mvpose-jax convert``: a recording between the formats the tools read."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import SOURCE_LAYOUT_HELP
from mvpose_jax.cli.registry import command
from mvpose_jax.jobs.convert import ConvertConfig, convert


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
    config = ConvertConfig(
        detections=args.detections,
        out=args.out,
        format=args.format,
        layout=args.layout,
        cameras=tuple(args.cameras) if args.cameras else None,
        missing_frames=args.missing_frames,
        source_layout=args.source_layout,
    )
    done = convert(config)
    print(
        f"{done.frames} frames, {len(done.cameras)} cameras ({', '.join(done.cameras)}), layout "
        f"{done.layout}: wrote {args.out}"
    )
    return 0
