"""Rig-agnostic models on the evaluation rigs' synthetic scenes, without training anything:
``python -m experiments.pretrained_synthetic --out DIR [--matchers NAME=FOLDER ...]
[--estimators NAME=FOLDER ...]``.

The pretraining experiments (`experiments.pretrain`, `experiments.pretrain_matcher`) compare one
pretrained model with models trained on each evaluation rig, which is most of their time. This
one scores given model folders (by default the ones shipped in the package) on the same rigs and
scenes (`pretrain.evaluation_data`: the paper's two rigs and one rig of each held-out family,
scenes seed ``--scenes-seed``, 1-8 people, the default detector), so that two pretraining recipes
can be compared on the validation scenes before one is chosen, and reported on the test scenes:

* each matcher at the threshold in its folder, and at the threshold chosen on frames composed from
  the rig's dev recordings (no training); the epipolar matcher beside them (`matcher_rows`: ARI,
  people per frame, PCP / MPJPE of robust triangulation of the proposals);
* each estimator alone and in the blend on the true groupings, beside robust triangulation
  (`pretrain.stage_rows`: PCP / MPJPE).

Writes ``DIR/pretrained_synthetic.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from experiments.config import SCALES, SPLITS
from experiments.fitting import choose_settings_on_dev, free_compiled_programs
from experiments.pretrain import evaluation_data, stage_rows
from experiments.pretrain_matcher import matcher_rows
from experiments.records import report_json
from experiments.tables import rounded_tree
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.synthetic.rigs import HELD_OUT_FAMILIES
from mvpose_jax.trained import PRETRAINED, load_estimator, load_matcher, read_proposal_threshold

RIGS = ("panoptic5", "arplab6", *HELD_OUT_FAMILIES)


def named_folders(pairs: list[str] | None) -> dict[str, str]:
    """``["NAME=FOLDER", ...]`` as {name: folder}; none given: {"shipped": the package's}."""
    if not pairs:
        return {"shipped": PRETRAINED}
    out = {}
    for pair in pairs:
        name, sep, folder = pair.partition("=")
        if not sep or not name or not folder or name in out:
            raise SystemExit(f"expected distinct NAME=FOLDER pairs, got {pair!r}")
        out[name] = folder
    return out


def run(matchers: dict, estimators: dict, rigs, scale: str, scenes_seed: int, seed: int) -> dict:
    """Every named model on every evaluation rig in ``rigs``, both splits; returns the report."""
    sc = SCALES[scale]
    report = {
        "scale": scale,
        "scenes_seed": scenes_seed,
        "recordings_seed": seed,
        "matchers": matchers,
        "estimators": estimators,
        "rigs": {},
    }
    for name, rig, data in evaluation_data(rigs, sc, scenes_seed, seed, progress=False):
        t0 = time.perf_counter()
        candidates, thresholds, cutoff = {}, {}, None
        for who, folder in matchers.items():
            m = load_matcher(folder, rig)
            own = choose_settings_on_dev(m, data, sc.threshold_frames, seed)
            # The epipolar row's cutoff: chosen on the same composed frames (any matcher's call).
            cutoff = own["geometric_cutoff_px"]
            thresholds[who] = {"folder": read_proposal_threshold(folder), "rig's": own["threshold"]}
            candidates[who] = (m, thresholds[who]["folder"])
            candidates[f"{who}, rig's threshold"] = (m, own["threshold"])
        loaded = {who: load_estimator(folder, rig) for who, folder in estimators.items()}
        entry = {"cameras": rig.num_cameras, "thresholds": thresholds}
        for split in SPLITS:
            entry[split] = {
                "matching": matcher_rows(data, split, candidates, cutoff) if candidates else {},
                "3d": stage_rows(data, split, loaded),
            }
        entry["seconds"] = time.perf_counter() - t0
        report["rigs"][name] = rounded_tree(entry)
        free_compiled_programs()
    return report


def markdown(report: dict) -> str:
    rigs = report["rigs"]
    head = "| {} | " + " | ".join(f"{r} ({v['cameras']} cams)" for r, v in rigs.items()) + " |"
    rule = "|---" * (len(rigs) + 1) + "|"
    lines = [
        "# Rig-agnostic models on the evaluation rigs' synthetic scenes (no training)",
        "",
        f"Scale {report['scale']}, scenes seed {report['scenes_seed']}, dev recordings seed "
        f"{report['recordings_seed']}. Matchers: "
        + ", ".join(f"{k} = {v}" for k, v in report["matchers"].items())
        + "; estimators: "
        + ", ".join(f"{k} = {v}" for k, v in report["estimators"].items())
        + ".",
    ]
    for split in ("validation", "test"):
        first = next(iter(rigs.values()))[split] if rigs else {"matching": {}, "3d": {}}
        if first["matching"]:
            lines += ["", f"Matching, {split} scenes (ARI · people per frame · PCP / MPJPE mm):"]
            lines += ["", head.format("matcher"), rule]
            for row in [r for r in first["matching"] if r != "true_people_per_frame"]:
                cells = []
                for v in rigs.values():
                    c = v[split]["matching"][row]
                    cells.append(
                        f"{c['ari']:.4f} · {c['people_per_frame']:.2f} · {c['pcp']:.1f} / "
                        f"{c['mpjpe_mm']:.1f}"
                    )
                lines.append(f"| {row} | " + " | ".join(cells) + " |")
        lines += ["", f"3D stage on true groupings, {split} scenes (avg PCP % / MPJPE mm):"]
        lines += ["", head.format("3D stage"), rule]
        for row in first["3d"]:
            cells = [
                f"{v[split]['3d'][row]['pcp']:.1f} / {v[split]['3d'][row]['mpjpe_mm']:.1f}"
                for v in rigs.values()
            ]
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--matchers", nargs="*", help="NAME=FOLDER ... (default: shipped=the package's)")
    p.add_argument("--estimators", nargs="*", help="NAME=FOLDER ... (default: the package's)")
    p.add_argument("--rigs", nargs="+", choices=RIGS, help="default: all of them")
    p.add_argument("--scale", default="quick", choices=sorted(SCALES))
    p.add_argument("--scenes-seed", type=int, default=0)
    p.add_argument("--seed", type=int, default=0, help="seed of the rigs' dev recordings")
    args = p.parse_args(argv)
    start = time.perf_counter()
    matchers = {} if args.matchers == [] else named_folders(args.matchers)
    estimators = {} if args.estimators == [] else named_folders(args.estimators)
    report = run(
        matchers,
        estimators,
        tuple(args.rigs) if args.rigs else None,
        args.scale,
        args.scenes_seed,
        args.seed,
    )
    report["seconds"] = round(time.perf_counter() - start, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "pretrained_synthetic.json", report_json(report))
    text = markdown(report)
    atomic_write_text(args.out / "pretrained_synthetic.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
