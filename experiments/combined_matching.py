"""The combined matcher on the domain-shift scenes without training anything:
``python -m experiments.combined_matching --models M.pkl [M1.pkl M2.pkl] [--splits validation]
[--shifts a,b]``.

Loads quick-scale 5-view matchers and estimators, one pickle per training seed (as
`experiments.filter_cutoffs` writes them, trained as ``experiments.run`` trains them; the first
is trained here with seed 0 when its file is missing), runs `experiments.run.shift_rows` (every
matcher's per-frame ARI, every grouping with every 3D method) on each chosen shift and split of
the scenes of seed 0 (``--scenes-seed``), and prints the domain-shift summary tables of each
split (with several pickles, their mean ± sd). The combined matcher's settings are the ones
recorded with each matcher (``fit["combined"]``), else the library's defaults at the matcher's
epipolar cutoff (`experiments.run.combined_config`; ``--library-switches``: its on/off switches
at the library's defaults). One shift and split takes about a minute on 2 busy CPU cores per
pickle.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
from pathlib import Path

from experiments.filter_cutoffs import models
from experiments.run import (
    SCALES,
    Data,
    combined_config,
    make_shifted_scenes,
    shift_rows,
    shift_tables,
)
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.proposals import CombinedConfig
from mvpose_jax.synthetic import SHIFTS

# The combined matcher's on/off settings, chosen on validation scenes for the library (not per
# matcher, unlike its threshold and cutoff, which are chosen on each matcher's dev frames).
SWITCHES = ("repair_splits", "drop_duplicates")


def _load(path: Path) -> dict:
    if not path.exists():
        raise SystemExit(f"{path}: no such models pickle (only the first is trained when missing)")
    with open(path, "rb") as f:
        return pickle.load(f)


def _runs_of(path: Path) -> list[dict]:
    runs = json.loads(path.read_text())
    return runs if isinstance(runs, list) else [runs]  # older files held one run


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.combined_matching")
    ap.add_argument(
        "--models",
        type=Path,
        nargs="+",
        default=[None],
        help="pickles of trained models, one per training seed (the first made if missing); a "
        "pickle's training seed is its 'seed' entry, else its position (0, 1, ...)",
    )
    ap.add_argument("--splits", default="validation", help="validation and/or test (comma list)")
    ap.add_argument("--shifts", default=",".join(SHIFTS), help="comma list of shift names")
    ap.add_argument(
        "--out", type=Path, help="write every number as JSON (a list, a run per pickle)"
    )
    ap.add_argument(
        "--scenes-seed",
        type=int,
        default=0,
        help="the validation and test scenes' seed (default 0, as experiments.run's tables); "
        "other seeds give more validation scenes to choose on",
    )
    ap.add_argument(
        "--library-switches",
        action="store_true",
        help="the combined matcher's switches (repair_splits, drop_duplicates) at the library's "
        "defaults, not as each matcher's record has them (its threshold and cutoff are kept)",
    )
    ap.add_argument(
        "--adapt", action="store_true", help="also the rows after adapt (quick scale's settings)"
    )
    ap.add_argument(
        "--adapt-matcher",
        action="store_true",
        help="also the ARI after the matcher is adapted to each split's own detections "
        "(adapt.adapt_matcher, the combined proposals as pseudo-labels)",
    )
    ap.add_argument(
        "--tables-from",
        type=Path,
        nargs="+",
        metavar="OUT_JSON",
        help="print the tables of earlier runs' --out files together (mean ± sd), run nothing",
    )
    args = ap.parse_args(argv)
    if args.tables_from:
        runs = [run for path in args.tables_from for run in _runs_of(path)]
        print("\n".join(shift_tables(runs)))
        return 0
    rig = load_rig("panoptic5")
    splits = args.splits.split(",")
    scenes = {
        name: Data(
            rig, [], [], make_shifted_scenes(rig, SCALES["quick"], args.scenes_seed, SHIFTS[name])
        )
        for name in args.shifts.split(",")
    }
    runs = []
    for i, path in enumerate(args.models):
        m = models(rig, path) if i == 0 else _load(path)
        if args.library_switches:
            default = CombinedConfig()
            m["fit"]["combined"] = dataclasses.asdict(combined_config(m["fit"])) | {
                k: getattr(default, k) for k in SWITCHES
            }
        run = {
            "seed": int(m.get("seed", i)),
            "models": None if path is None else str(path),
            "scenes_seed": args.scenes_seed,
            "combined": dataclasses.asdict(combined_config(m["fit"])),
            "shifts": {},
        }
        for name, data in scenes.items():
            run["shifts"][name] = {
                split: shift_rows(
                    data,
                    split,
                    m["matcher"],
                    m["estimator"],
                    m["fit"],
                    adapt=SCALES["quick"].adapt if args.adapt else None,
                    matcher_adapt=SCALES["quick"].matcher_adapt if args.adapt_matcher else None,
                )
                for split in splits
            }
            print(f"{path} {name}: {json.dumps(run['shifts'][name])}", flush=True)
        runs.append(run)
    if args.out is not None:  # before the tables, so that a table's failure loses no numbers
        atomic_write_text(args.out, json.dumps(runs, indent=1) + "\n")
    print("\n".join(shift_tables(runs)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
