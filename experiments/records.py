"""A run's record: what each training seed's results hold beyond its numbers, the partial file a
long run keeps, and the records of earlier runs read back (``--tables-from``)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from experiments.config import Scale
from mvpose_jax.data.files import atomic_write_text, to_jsonable

# What a table's runs must share to be averaged (`--tables-from` checks them).
RUN_SETTINGS = ("scenes_seed", "train_floor_jitter_m", "train_floor_offset_m")


def run_record(seed: int, scenes_seed: int, sc: Scale) -> dict:
    """The head of one training seed's record: its seed and what its tables depend on."""
    return {
        "seed": seed,
        "scenes_seed": scenes_seed,
        "train_floor_jitter_m": sc.train_floor_jitter_m,
        "train_floor_offset_m": sc.train_floor_offset_m,
    }


def report_json(report) -> str:
    """``report`` as JSON text: arrays and dataclasses as `to_jsonable` writes them, NaN (no
    error to average) and infinities as null, which JSON lacks."""
    return json.dumps(_finite(to_jsonable(report)), indent=1) + "\n"


def _finite(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def save_partial(runs: list[dict], out: Path) -> None:
    """The seeds finished so far (a long multi-seed run keeps them if it is stopped)."""
    atomic_write_text(out / "runs_partial.json", json.dumps(to_jsonable(runs), indent=1) + "\n")


# The option that sets each of `RUN_SETTINGS` (named in the messages that ask for it).
SETTING_OPTIONS = {
    "scenes_seed": "--scenes-seed",
    "train_floor_jitter_m": "--train-floor-jitter",
    "train_floor_offset_m": "--train-floor-offset",
}


def runs_from_files(paths: list[Path], given: dict) -> tuple[list[dict], dict]:
    """The finished seeds of earlier runs (their runs_partial.json or metrics.json), joined.

    Args:
      paths: the files; several parts of one multi-seed run are joined.
      given: `RUN_SETTINGS` as the command line says them (None: not said).
    Returns:
      (the runs, each with `RUN_SETTINGS`; the settings they share).
    Raises:
      ValueError (its message for the user) when there is no run, a training seed repeats, the
      runs differ in a setting, or a run lacks a setting the command line does not say.
    """
    given = dict(given)
    runs = []
    for path in paths:
        saved = json.loads(path.read_text())
        for run in saved["runs"] if isinstance(saved, dict) else saved:
            # Older runs record these only in their metrics.json's header.
            header = saved if isinstance(saved, dict) else {}
            runs.append({k: header.get(k) for k in RUN_SETTINGS} | run)
    if not runs:
        raise ValueError("--tables-from: no finished run in " + ", ".join(map(str, paths)))
    seeds = [r["seed"] for r in runs]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"the runs repeat training seeds: {seeds}")
    # A table's seeds are measured on the same scenes after training on the same floors, or
    # their mean means nothing.
    for key in RUN_SETTINGS:
        option = SETTING_OPTIONS[key]
        for run in runs:
            if run[key] is None:
                if given[key] is None:
                    raise ValueError(
                        f"the run of training seed {run['seed']} does not record its {key} "
                        f"(an older runs_partial.json): say it with {option}"
                    )
                run[key] = given[key]
        values = sorted({r[key] for r in runs})
        if len(values) > 1:
            raise ValueError(f"the runs differ in {key} ({values}): re-run them with one {option}")
        if given[key] is not None and values != [given[key]]:
            raise ValueError(f"{option} {given[key]}: the runs' {key} is {values[0]}")
        given[key] = values[0]
    return runs, given
