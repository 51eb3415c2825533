"""The combined matcher on the domain-shift scenes without training anything:
``python -m experiments.combined_matching --models M.pkl [--splits validation] [--shifts a,b]``.

Loads the seed-0 quick-scale 5-view matcher and estimator (a pickle `experiments.filter_cutoffs`
writes, trained as ``experiments.run`` trains them; trained here when the file is missing), runs
`experiments.run.shift_rows` (every matcher's per-frame ARI, every grouping with every 3D method)
on each chosen shift and split, and prints the domain-shift summary table of each split. The
combined matcher's settings are the ones recorded with the matcher (``fit["combined"]``), else
the library's defaults at the matcher's epipolar cutoff (`experiments.run.combined_config`). One
shift and split takes about a minute on 2 busy CPU cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
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
from mvpose_jax.synthetic import SHIFTS


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.combined_matching")
    ap.add_argument("--models", type=Path, help="pickle of the trained models (made if missing)")
    ap.add_argument("--splits", default="validation", help="validation and/or test (comma list)")
    ap.add_argument("--shifts", default=",".join(SHIFTS), help="comma list of shift names")
    ap.add_argument("--out", type=Path, help="write every number as JSON")
    ap.add_argument(
        "--adapt", action="store_true", help="also the rows after adapt (quick scale's settings)"
    )
    args = ap.parse_args(argv)
    rig = load_rig("panoptic5")
    m = models(rig, args.models)
    splits = args.splits.split(",")
    run = {"seed": 0, "combined": dataclasses.asdict(combined_config(m["fit"])), "shifts": {}}
    for name in args.shifts.split(","):
        scenes = Data(rig, [], [], make_shifted_scenes(rig, SCALES["quick"], 0, SHIFTS[name]))
        run["shifts"][name] = {
            split: shift_rows(
                scenes,
                split,
                m["matcher"],
                m["estimator"],
                m["fit"],
                adapt=SCALES["quick"].adapt if args.adapt else None,
            )
            for split in splits
        }
        print(f"{name}: {json.dumps(run['shifts'][name])}", flush=True)
    print("\n".join(shift_tables([run])))
    if args.out is not None:
        args.out.write_text(json.dumps(run, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
