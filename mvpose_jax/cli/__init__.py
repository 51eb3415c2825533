"""The ``mvpose-jax`` command line: one entry point, one subcommand per job.

Each subcommand parses its options into a job's config, calls the job (``mvpose_jax.jobs``) and
prints its result; nothing here computes.
Bad input ends with a one-line error naming the file, frame, camera and field (exit status 2).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Sequence

# The command modules register their subcommands on import, in the order --help lists them.
# isort: off
from mvpose_jax.cli import rig, generate, train, adapt, convert, infer  # noqa: F401
from mvpose_jax.cli import smooth, evaluate, render, export, view, score  # noqa: F401
from mvpose_jax.cli import batch  # noqa: F401

# isort: on
from mvpose_jax.cli.options import SOURCE_LAYOUT_HELP
from mvpose_jax.cli.registry import _COMMANDS, command
from mvpose_jax.compiled import enable_compilation_cache
from mvpose_jax.data.recording import recording_fps as _recording_fps
from mvpose_jax.errors import MvposeError, MvposeWarning
from mvpose_jax.jobs.adapt import MATCHER_ADAPT_STEPS
from mvpose_jax.jobs.common import recordings_in as _recordings_in

__all__ = [
    "MATCHER_ADAPT_STEPS",
    "SOURCE_LAYOUT_HELP",
    "_COMMANDS",
    "_recording_fps",
    "_recordings_in",
    "build_parser",
    "command",
    "main",
    "version",
]


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
        # Before the first compile: the next run of a command reuses this one's programs.
        enable_compilation_cache()
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
