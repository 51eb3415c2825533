"""The ``mvpose-jax`` command line: one entry point, one subcommand per job.

Each subcommand parses its options and calls the library; nothing here computes.
Bad input ends with a one-line error naming the file, frame, camera and field (exit status 2).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from mvpose_jax.errors import MvposeError

# name -> (help, add_arguments(parser), run(args) -> exit status)
_COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {}


def command(name: str, help: str, arguments: Callable[[argparse.ArgumentParser], None]):
    """Registers the decorated ``run(args) -> exit status`` as subcommand ``name``."""

    def register(run):
        _COMMANDS[name] = (help, arguments, run)
        return run

    return register


def add_rig_argument(p: argparse.ArgumentParser, default: str | None = "panoptic5") -> None:
    """The ``--rig`` option every subcommand that needs cameras shares."""
    p.add_argument(
        "--rig", default=default, required=default is None,
        help="preset name (panoptic5, arplab6) or calibration file (.json native or CMU Panoptic, "
        ".toml anipose/Pose2Sim)",
    )  # fmt: skip
    p.add_argument(
        "--translation-scale", type=float, default=1.0,
        help="TOML calibrations only: metres per translation unit (0.001 for millimetres)",
    )  # fmt: skip


@command("rig", "Show a rig (preset or calibration file): cameras, centres, image sizes, up.", add_rig_argument)
def _rig(args: argparse.Namespace) -> int:
    import numpy as np

    from mvpose_jax.cameras import camera_centres, rig_centre_and_radius, up_vector
    from mvpose_jax.data.calibration import load_rig

    rig = load_rig(args.rig, translation_scale=args.translation_scale)
    centres = np.asarray(camera_centres(rig))
    centre, radius = rig_centre_and_radius(rig)
    print(f"{rig.num_cameras} cameras; up {np.round(up_vector(rig), 3).tolist()}"
          f"{' (inferred)' if rig.up is None else ''}; centre {np.round(np.asarray(centre), 3).tolist()} m,"
          f" radius {float(radius):.3f} m")
    for c, name in enumerate(rig.names):
        w, h = np.asarray(rig.size[c]).astype(int)
        print(f"  {name:>12s}  {w}x{h}  f={float(rig.K[c, 0, 0]):.1f}px  centre {np.round(centres[c], 3).tolist()}")
    return 0


def _generate_arguments(p: argparse.ArgumentParser) -> None:
    from mvpose_jax.data.synthetic.cli import add_generate_arguments

    add_rig_argument(p)
    add_generate_arguments(p)


@command(
    "generate",
    "Generate a synthetic recording (or single-person training recordings) on any rig.",
    _generate_arguments,
)
def _generate(args: argparse.Namespace) -> int:
    from mvpose_jax.data.synthetic.cli import run_generate

    return run_generate(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mvpose-jax", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_, add, _) in _COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        add(p)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _COMMANDS[args.command][2](args) or 0
    except MvposeError as e:
        print(f"mvpose-jax {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
