"""The subcommands by name: each command module registers its parser and its run function."""

from __future__ import annotations

import argparse
from collections.abc import Callable

# name -> (help, add_arguments(parser), run(args) -> exit status)
_COMMANDS: dict[
    str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]
] = {}


def command(name: str, help: str, arguments: Callable[[argparse.ArgumentParser], None]):
    """Registers the decorated ``run(args) -> exit status`` as subcommand ``name``."""

    def register(run):
        _COMMANDS[name] = (help, arguments, run)
        return run

    return register
