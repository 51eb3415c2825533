"""The experiments' entry point: ``python -m experiments.run [--only NAME] [--scale quick|paper]
[--smoke]``.

Runs one experiment of `experiments.registry.EXPERIMENTS` (default ``paper-panoptic``, at
``--scale quick``); every number in its results comes from the run, and the paper's numbers are
printed beside ours and labelled as the paper's:

* ``paper-panoptic``: the paper's Tables 3 and 6 on ``panoptic5``, and tracks over time
  (`experiments.paper_panoptic`).
* ``paper-arp``: Tables 4 and 7 on ``arplab6`` (`experiments.paper_arp`).
* ``synthetic-summary``: no training; a synthetic recording and the triangulation baseline on it
  (`experiments.synthetic_summary`).
* ``domain-shift``: the 5-view models on scenes made with detectors, people and rigs they never
  saw (`experiments.domain_shift`).

What they share: scales, splits and seed streams (`experiments.config`), data
(`experiments.data`), training and model folders (`experiments.fitting`), table cells
(`experiments.tables`), the paper's numbers (`experiments.paper`).

Scales: ``quick`` (small networks, minutes on a 2-core CPU), ``paper`` (the paper's network sizes
and training lengths: hours on a CPU). ``--smoke`` is a seconds-long run of the same code (tests).
``--experiment NAME`` is the deprecated spelling of ``--only NAME``.

Writes ``results/<experiment>/`` (or ``--out``): ``metrics.json``, ``tables.md`` and ``figures/``
(3D skeletons of sample frames, ground truth beside ours and triangulation; training curves).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import jax

from experiments.config import SCALES
from experiments.records import runs_from_files
from experiments.registry import DEFAULT, EXPERIMENTS
from mvpose_jax.compiled import enable_compilation_cache
from mvpose_jax.data.files import atomic_write_text, to_jsonable
from mvpose_jax.synthetic import SHIFTS


def machine() -> dict:
    """The CPU, its cores, jax's version and the device the run used (for the tables' head)."""
    cpu = (
        next(
            (
                ln.split(":", 1)[1].strip()
                for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")
            ),
            platform.processor(),
        )
        if Path("/proc/cpuinfo").exists()
        else platform.processor()
    )
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "jax": jax.__version__,
        "device": f"{jax.devices()[0].platform} ({jax.devices()[0].device_kind})",
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m experiments.run", description=__doc__.splitlines()[0]
    )
    ap.add_argument(
        "--only",
        choices=sorted(EXPERIMENTS),
        metavar="NAME",
        help=f"run this experiment (default {DEFAULT}): "
        + "; ".join(f"{name}: {e.summary}" for name, e in EXPERIMENTS.items()),
    )
    ap.add_argument(
        "--experiment",
        choices=sorted(EXPERIMENTS),
        metavar="NAME",
        help="deprecated: the old name of --only",
    )
    ap.add_argument(
        "--scale",
        choices=("quick", "quick-long", "paper"),
        default="quick",
        help="quick: small networks, minutes; quick-long: the same networks with the quick "
        "scale's longer budgets until December 2026 (2- and 3-view matchers 24000 and 20000 "
        "steps, the estimator 6000); paper: the paper's sizes and training lengths",
    )
    ap.add_argument(
        "--smoke", action="store_true", help="a seconds-long run of the same code (tests)"
    )
    ap.add_argument(
        "--seed",
        type=int,
        default=0,
        help="the scenes' seed and the first training seed (default 0)",
    )
    ap.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="training seeds (seed, seed+1, ...): tables give their mean ± sd (default 1; "
        "the reported tables use 3)",
    )
    ap.add_argument(
        "--train-floor-jitter",
        type=float,
        default=None,
        metavar="M",
        help="training and dev recordings each get their own floor within M metres of the "
        "rig's (models that tolerate a wrong floor; default 0: one floor, the paper's setting)",
    )
    ap.add_argument(
        "--train-floor-offset",
        type=float,
        default=None,
        metavar="M",
        help="training and dev recordings on a floor M metres above the rig's (negative: below), "
        "the test scenes on the rig's: models trained on a wrong floor (default 0)",
    )
    ap.add_argument(
        "--shifts",
        type=lambda text: tuple(text.split(",")),
        metavar="NAME,...",
        help="domain-shift: test only these shifts (default: all; 'none' is the unshifted "
        f"reference): {', '.join(SHIFTS)}",
    )
    ap.add_argument("--out", type=Path, help="output folder (default results/<experiment>)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument(
        "--scenes-seed",
        type=int,
        default=None,
        help="the validation and test scenes' seed (default: --seed); with it, the training seeds "
        "of one table can run in several parts (--seed 1 --seeds 2 --scenes-seed 0)",
    )
    ap.add_argument(
        "--tables-from",
        type=Path,
        nargs="+",
        metavar="RUNS_JSON",
        help="write the tables from the finished seeds of earlier runs (their runs_partial.json "
        "or metrics.json; several parts of one multi-seed run are joined) instead of running",
    )
    args = ap.parse_args(argv)
    # Before the first compile: a second run (another seed, another experiment on the same
    # scenes) loads the programs this one compiled instead of compiling them again.
    enable_compilation_cache()
    name = _experiment_name(ap, args)
    scale = "smoke" if args.smoke else args.scale
    out = args.out or Path("results") / name
    out.mkdir(parents=True, exist_ok=True)
    command = " ".join(
        ["python -m experiments.run", *(argv if argv is not None else sys.argv[1:])]
    ).strip()
    t0 = time.perf_counter()
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    seeds = [args.seed + i for i in range(args.seeds)]
    scenes_seed = args.seed if args.scenes_seed is None else args.scenes_seed
    given = {
        "scenes_seed": args.scenes_seed,
        "train_floor_jitter_m": args.train_floor_jitter,
        "train_floor_offset_m": args.train_floor_offset,
    }
    if args.tables_from is not None:
        if args.shifts is not None:
            ap.error("--shifts applies to a run, not to --tables-from (its runs' shifts are used)")
        tables = EXPERIMENTS[name].tables
        try:
            runs, given = runs_from_files(args.tables_from, given)
        except ValueError as e:
            ap.error(str(e))
        seeds = [r["seed"] for r in runs]
        scenes_seed = given["scenes_seed"]
        if tables is None:
            with_tables = sorted(k for k, e in EXPERIMENTS.items() if e.tables is not None)
            ap.error(f"--tables-from applies to {with_tables}")
        lines = tables(runs)
        sources = ", ".join(str(p) for p in args.tables_from)
        command += f" (the runs of {sources}; their training seeds {seeds})"
    else:
        for key in ("train_floor_jitter_m", "train_floor_offset_m"):
            given[key] = given[key] or 0.0
        if given["train_floor_jitter_m"] < 0:
            ap.error("--train-floor-jitter must be >= 0")
        if args.shifts is not None:
            if name != "domain-shift":
                ap.error("--shifts applies to --only domain-shift")
            unknown = sorted(set(args.shifts) - set(SHIFTS))
            if unknown:
                ap.error(f"--shifts: no shift named {unknown}; the shifts: {', '.join(SHIFTS)}")
        settings = {
            "train_floor_jitter_m": given["train_floor_jitter_m"],
            "train_floor_offset_m": given["train_floor_offset_m"],
            "shifts": args.shifts,
        }
        runs, lines = EXPERIMENTS[name].run(
            dataclasses.replace(SCALES[scale], **settings),
            seeds,
            scenes_seed,
            out,
            not args.no_progress,
        )
    seconds = time.perf_counter() - t0
    meta = {
        "experiment": name,
        "scale": scale,
        "seed": args.seed,
        "scenes_seed": scenes_seed,
        "seeds": seeds,
        "train_floor_jitter_m": given["train_floor_jitter_m"],
        "train_floor_offset_m": given["train_floor_offset_m"],
        "command": command,
        "seconds": round(seconds, 1),
        "machine": machine(),
    }
    head = [
        f"# {name} ({scale} scale)",
        "",
        f"Command: `{command}`; {seconds / 60:.1f} min on {meta['machine']['cpu']} "
        f"({meta['machine']['cores']} cores, jax {meta['machine']['jax']}, {meta['machine']['device']}).",
        "Synthetic data on the paper's real camera geometry; trained from scratch in this run, no 3D labels."
        + (
            f" Training and dev recordings each on their own floor within {meta['train_floor_jitter_m']:g} m"
            " of the rig's (--train-floor-jitter)."
            if meta["train_floor_jitter_m"]
            else ""
        )
        + (
            f" Training and dev recordings on a floor {meta['train_floor_offset_m']:+g} m from the rig's"
            " (--train-floor-offset: a wrong floor guess); the scenes on the rig's."
            if meta["train_floor_offset_m"]
            else ""
        ),
        "Splits: single-person training and dev recordings per training seed; multi-person validation scenes",
        "(every setting a person picks is picked on them) and test scenes (read only for the reported",
        f"tables), both from seed {scenes_seed}. Proposal settings (GAT threshold, epipolar cutoff) are chosen on",
        "frames composed from the dev recordings.",
        "",
    ]
    text = "\n".join(head + lines) + "\n"
    atomic_write_text(
        out / "metrics.json", json.dumps({**meta, "runs": to_jsonable(runs)}, indent=1) + "\n"
    )
    atomic_write_text(out / "tables.md", text)
    # The reported (test) tables on the terminal; the validation ones, where settings were
    # chosen, only in tables.md, so a log of the run stays a page long.
    shown, _, rest = text.partition("\n## Validation scenes")
    print(shown.rstrip() + "\n")
    if rest:
        print(f"(the validation scenes' tables, where the settings were chosen: {out}/tables.md)")
    print(f"wrote {out}/metrics.json, tables.md and figures/")
    return 0


def _experiment_name(ap: argparse.ArgumentParser, args: argparse.Namespace) -> str:
    """The experiment --only names (or the deprecated --experiment), else the default."""
    if args.experiment is not None:
        warnings.warn(
            "--experiment is deprecated; use --only " + args.experiment, FutureWarning, stacklevel=3
        )
        if args.only is not None and args.only != args.experiment:
            ap.error(f"--only {args.only} and --experiment {args.experiment} name two experiments")
    return args.only or args.experiment or DEFAULT


if __name__ == "__main__":
    sys.exit(main())
