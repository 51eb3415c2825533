"""``mvpose-jax render``: infer's 3D poses drawn over each camera's view."""

from __future__ import annotations

import argparse

from mvpose_jax.cli.options import detection_arguments, detections_source, rig_source
from mvpose_jax.cli.registry import command
from mvpose_jax.jobs.render import RenderConfig, render


def _render_arguments(p: argparse.ArgumentParser) -> None:
    detection_arguments(p)
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
    config = RenderConfig(
        rig=rig_source(args),
        detections=detections_source(args),
        poses=args.poses,
        out=args.out,
        frames=tuple(args.frames) if args.frames else None,
        every=args.every,
        images=args.images,
        scale=args.scale,
        fps=args.fps,
        figures_3d=args.figures_3d,
    )
    done = render(config)
    print(f"wrote {done.frames} frames to {done.out}")
    return 0
