"""The combined matcher on the domain-shift scenes without training anything:
``python -m experiments.combined_matching --models DIR [DIR1 DIR2] [--splits validation]
[--shifts a,b]``.

Loads quick-scale 5-view matchers and estimators, one models folder per training seed
(`experiments.fitting.cached_models`: the model folders ``mvpose-jax train-matcher`` and
``train-estimator`` write, and the matcher's fit record; trained as ``experiments.run`` trains
them; the first is trained here with seed 0 when its folder is missing; `experiments.
filter_cutoffs` shares them), runs `experiments.domain_shift.shift_rows` (every matcher's
per-frame ARI, every grouping with every 3D method) on each chosen shift and split of the scenes
of seed 0 (``--scenes-seed``), and prints the domain-shift summary tables of each split (with
several folders, their mean ± sd). The combined matcher's settings are the ones recorded with
each matcher (``fit["combined"]``), else the library's defaults at the matcher's epipolar cutoff
(`experiments.fitting.combined_config`; ``--library-switches``: its on/off switches at the
library's defaults). One shift and split takes about a minute on 2 busy CPU cores per folder.
The pickles these models were kept in before are refused (train the folder again).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from experiments.config import SCALES
from experiments.data import Data, make_shifted_scenes
from experiments.domain_shift import shift_rows
from experiments.domain_shift import tables as shift_tables
from experiments.fitting import cached_models, combined_config, load_models
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.errors import InputError
from mvpose_jax.proposals import CombinedConfig
from mvpose_jax.synthetic import SHIFTS

# The combined matcher's on/off settings, chosen on validation scenes for the library (not per
# matcher, unlike its threshold and cutoff, which are chosen on each matcher's dev frames).
SWITCHES = ("repair_splits", "drop_duplicates")


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
        metavar="DIR",
        help="models folders (experiments.fitting.cached_models: matcher/ and estimator/ model "
        "folders and fit.json), one per training seed; the first is trained with seed 0 and "
        "written there if missing; a folder's training seed is in its fit.json (old .pkl files "
        "are refused)",
    )
    ap.add_argument("--splits", default="validation", help="validation and/or test (comma list)")
    ap.add_argument("--shifts", default=",".join(SHIFTS), help="comma list of shift names")
    ap.add_argument(
        "--out", type=Path, help="write every number as JSON (a list, a run per models folder)"
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
    # Paths that cannot hold models fail now, not after the scenes and the first models are made.
    for i, path in enumerate(args.models):
        if path is not None and path.is_file():
            ap.error(
                f"--models {path}: a file; the models are kept as model folders now (not "
                "pickles): give a folder (the first is trained and written there if missing)"
            )
        if i > 0 and not path.exists():
            ap.error(f"--models {path}: no such folder (only the first is trained when missing)")
    splits = args.splits.split(",")
    scenes = {
        name: Data(
            rig, [], [], make_shifted_scenes(rig, SCALES["quick"], args.scenes_seed, SHIFTS[name])
        )
        for name in args.shifts.split(",")
    }
    runs = []
    for i, path in enumerate(args.models):
        try:
            m = cached_models(rig, path) if i == 0 else load_models(rig, path)
        except InputError as e:
            raise SystemExit(str(e)) from None
        fit = dict(m.fit)
        if args.library_switches:
            default = CombinedConfig()
            fit["combined"] = dataclasses.asdict(combined_config(fit)) | {
                k: getattr(default, k) for k in SWITCHES
            }
        run = {
            "seed": m.seed,
            "models": None if path is None else str(path),
            "scenes_seed": args.scenes_seed,
            "combined": dataclasses.asdict(combined_config(fit)),
            "shifts": {},
        }
        for name, data in scenes.items():
            run["shifts"][name] = {
                split: shift_rows(
                    data,
                    split,
                    m.matcher,
                    m.estimator,
                    fit,
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
