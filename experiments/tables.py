"""Table cells from the runs of several training seeds: ``mean ± sd`` of a value found by its
path in each run's record, signed differences, and the rounding of the records' numbers."""

from __future__ import annotations

import numpy as np


def value_at(r: dict, path: str | tuple[str, ...]):
    """A nested value by its keys: a tuple, or one string of them joined by '/' (for keys that
    hold no '/'; model names such as M_2/6 do, and go as tuples)."""
    for key in path.split("/") if isinstance(path, str) else path:
        r = r[key]
    return r


def mean_sd(runs: list[dict], path: str | tuple[str, ...], nd: int = 2) -> str:
    """A result across training seeds: ``mean ± sd`` (sample sd), or the value for one seed."""
    v = np.array([float(value_at(r, path)) for r in runs])
    if len(v) == 1:
        return f"{v[0]:.{nd}f}"
    return f"{v.mean():.{nd}f} ± {v.std(ddof=1):.{nd}f}"


def seeds_line(runs: list[dict]) -> str:
    """The sentence that says which training seeds a table's cells come from."""
    n = len(runs)
    return (
        f"One training seed ({runs[0]['seed']})."
        if n == 1
        else f"Mean ± sample standard deviation over {n} training seeds ({', '.join(str(r['seed']) for r in runs)})."
    )


def has_value(run: dict, path: tuple[str, ...]) -> bool:
    """Whether a run's record holds ``path`` (records of older runs lack later columns)."""
    try:
        value_at(run, path)
    except (KeyError, TypeError):
        return False
    return True


def diff_mean_sd(runs: list[dict], a: tuple[str, ...], b: tuple[str, ...], nd: int) -> str:
    """``a - b`` per training seed, as `signed_mean_sd`."""
    return signed_mean_sd([float(value_at(r, a)) - float(value_at(r, b)) for r in runs], nd)


def signed_mean_sd(values: list[float], nd: int) -> str:
    """Signed ``mean ± sd`` of per-seed values (the value alone for one seed)."""
    v = np.asarray(values, float)
    if len(v) == 1:
        return f"{v[0]:+.{nd}f}"
    return f"{v.mean():+.{nd}f} ± {v.std(ddof=1):.{nd}f}"


def rounded(d):
    """A nested dict of numbers, each rounded to 3 decimals."""
    if isinstance(d, dict):
        return {k: rounded(v) for k, v in d.items()}
    return round(float(d), 3)


def rounded_tree(d):
    """Nested dicts and lists of numbers: integers kept, the others rounded to 4 decimals."""
    if isinstance(d, dict):
        return {k: rounded_tree(v) for k, v in d.items()}
    if isinstance(d, list):
        return [rounded_tree(v) for v in d]
    if isinstance(d, (int, np.integer)):
        return int(d)
    return round(float(d), 4)
