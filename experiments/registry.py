"""The experiments by name: what ``python -m experiments.run --only NAME`` runs.

An experiment is one module with ``run(scale, seeds, scenes_seed, out, progress) -> (runs,
lines)`` (one record per training seed, the lines of tables.md after its head) and, where its
tables can be rebuilt from saved runs (``--tables-from``), ``tables(runs) -> lines``. A new
experiment is one module and one line here.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from experiments import domain_shift, paper_arp, paper_panoptic, synthetic_summary
from experiments.config import Scale

RunFn = Callable[[Scale, list[int], int, Path, bool], tuple[list[dict], list[str]]]
TablesFn = Callable[[list[dict]], list[str]]


class Experiment(NamedTuple):
    """One experiment: how to run it, and how to write its tables from saved runs (None: it has
    none to rebuild)."""

    run: RunFn
    tables: TablesFn | None
    summary: str  # one line, for --help


EXPERIMENTS: dict[str, Experiment] = {
    "paper-panoptic": Experiment(
        paper_panoptic.run,
        paper_panoptic.tables,
        "the paper's Tables 3 and 6 on panoptic5, and tracks over time",
    ),
    "paper-arp": Experiment(
        paper_arp.run, paper_arp.tables, "the paper's Tables 4 and 7 on arplab6"
    ),
    "synthetic-summary": Experiment(
        synthetic_summary.run, None, "a synthetic recording and triangulation on it; no training"
    ),
    "domain-shift": Experiment(
        domain_shift.run,
        domain_shift.tables,
        "the 5-view models on scenes made with every shift of synthetic.SHIFTS",
    ),
}

# What `python -m experiments.run` runs without --only (the reported tables of the README).
DEFAULT = "paper-panoptic"
