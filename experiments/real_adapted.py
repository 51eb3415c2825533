"""The paper's models adapted to the real recording itself, without a label: ``python -m
experiments.real_adapted --out DIR [--models DIR] [--smoke]`` (issue 37: item 4, and the
acceptance's target for the paper's method).

For each real recording of ``../shared/real/`` (MVOR days 1-2; Pose2Sim's demo, the two-person
trial), the model pair ``python -m experiments.real`` trains on synthetic recordings of its rig
(the paper's GAT and the small residual MLP, `real_models.synthetic_models`, training seed 0;
``--models``: that experiment's models folder, trained there where missing), and the same pair
adapted to the recording's own detections as ``mvpose-jax adapt --matcher-out`` adapts them:

1. the GAT fine-tuned on every cross-view pair of the recording, labelled by the combined
   matcher's groups (`adapt.adapt_matcher`; pseudo-labels, no truth), its proposal threshold
   chosen again on the recording's held-out frames against those pseudo-labels;
2. the MLP fine-tuned by the reprojection loss on the people the adapted matcher's combined
   proposals build (`adapt.adapt_estimator`); for the paper's method also, as ``--proposals
   gat`` adapts it, behind the adapted GAT's own proposals (`BEHIND_GAT`).

The budgets are the adaptation's defaults in steps (matcher 400, estimator 300, held-out frames
stop each earlier) with no wall-clock cap (``max_seconds`` = `NO_CAP_SECONDS`), so that the
result does not depend on the machine's speed. Nothing here is tuned on these recordings: the
adaptation's settings were chosen on the synthetic domain-shift experiment's validation scenes.
Each of ``--seeds`` (default 0, 1, 2) is a training seed of both pairs and the seed of their
adaptation; seed 0's pairs are ``experiments.real``'s, the others are kept beside them
(``mvor-synthetic-seed1/``, ...). The full tables are the first seed's; the figures that move
most from seed to seed (the paper's method, the GAT alone) are given for every seed.

Scored as ``experiments.real`` scores them:

* MVOR (evaluation only): the MVOR protocol (`mvor_protocol.evaluate`) of the geometric default
  and, with each pair, the ``infer`` default (combined + blend), combined + MLP, the paper's
  method (GAT + MLP), GAT + robust triangulation (the grouping alone) and GAT + blend;
* the demo (no labels): the label-free score of the geometric default and, with each pair, the
  ``infer`` default and the paper's method. The estimator's adaptation minimises the
  reprojection error in these same views, which that score measures: read its rows with that in
  mind (the grouping's figures below are not so affected);
* the GAT alone (issue 37 item 4: it should build as many people as the geometric grouping):
  people per frame and ARI against the geometric grouping, the combined matcher's (the
  pseudo-labels) and, on MVOR, the true groups.

Writes ``DIR/real_adapted.md`` and ``DIR/real_adapted.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from experiments import pose2sim_demo as demo
from experiments import real
from experiments.detector_like import (
    GEOMETRIC,
    demo_table,
    mvor_rows,
    mvor_table,
    people_per_frame,
)
from experiments.fitting import Models, combined_config
from experiments.mvor import DEFAULT_ROOT, load_mvor, select_frames, true_identity
from experiments.real_models import MODELS_RECIPE, SEED, synthetic_models
from experiments.records import report_json
from mvpose_jax.adapt import (
    AdaptConfig,
    MatcherAdaptConfig,
    adapt_estimator,
    adapt_matcher,
    save_adapted_estimator,
    save_adapted_matcher,
)
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.pose2sim import find_trials
from mvpose_jax.floor import estimate_floor_from_detections
from mvpose_jax.inference import run_pipeline
from mvpose_jax.matching import gat_match_table
from mvpose_jax.metrics import matching_scores
from mvpose_jax.proposals import propose_people
from mvpose_jax.skeletons import Detections

SEEDS = (0, 1, 2)
SOURCES = (("trained", "as trained"), ("adapted", "adapted to the recording"))
# The paper's method as `mvpose-jax adapt --matcher-out ... --proposals gat` adapts it: the
# same adapted matcher, the MLP adapted behind the adapted GAT's own proposals.
BEHIND_GAT = ("adapted-gat", "adapted, the MLP behind the GAT")
PAPER_ROW = ("paper's method (GAT + MLP)", "gat", "mlp")
MVOR_MODEL_ROWS = (
    ("infer default (combined + blend)", "combined", "blend"),
    ("combined + MLP", "combined", "mlp"),
    PAPER_ROW,
    ("GAT + robust triangulation", "gat", "robust"),
    ("GAT + blend", "gat", "blend"),
)
# A wall-clock cap no adaptation here reaches: steps and held-out frames decide, not the machine.
NO_CAP_SECONDS = 3600.0
MATCHER_ADAPT = MatcherAdaptConfig(max_seconds=NO_CAP_SECONDS)
ESTIMATOR_ADAPT = AdaptConfig(max_seconds=NO_CAP_SECONDS)
# A few frames (CI): blocks of one frame, every other one held out, two steps.
SMOKE_MATCHER_ADAPT = dataclasses.replace(
    MATCHER_ADAPT, max_steps=2, check_every=1, block_frames=1, holdout_every=2, min_frames=2
)
SMOKE_ESTIMATOR_ADAPT = dataclasses.replace(
    ESTIMATOR_ADAPT, max_steps=2, check_every=1, block_frames=1, holdout_every=2, min_people=2
)


def adapted_pair(rig, detections: Detections, models: Models, smoke: bool):
    """``models`` adapted to ``detections`` (module docstring): the matcher on its combined
    proposals, then the estimator behind the adapted matcher's, both with the pair's training
    seed; the returned pairs' fit records carry the adapted GAT's threshold. Returns (the pair,
    the pair with the estimator adapted behind the GAT alone instead (`behind_gat`), {"matcher":
    its `MatcherAdaptReport`, "estimator", "estimator_behind_gat": the `AdaptReport`s})."""
    combined = combined_config(models.fit)
    matcher_config = SMOKE_MATCHER_ADAPT if smoke else MATCHER_ADAPT
    estimator_config = SMOKE_ESTIMATOR_ADAPT if smoke else ESTIMATOR_ADAPT
    matcher, matcher_report = adapt_matcher(
        rig,
        detections,
        models.matcher,
        combined=combined,
        config=dataclasses.replace(matcher_config, seed=models.seed),
        progress=not smoke,
    )
    estimator, estimator_report = adapt_estimator(
        rig,
        detections,
        models.estimator,
        matcher=matcher,
        combined=combined,
        config=dataclasses.replace(estimator_config, seed=models.seed),
        progress=not smoke,
    )
    fit = {**models.fit, "threshold": matcher_report.threshold}
    adapted = Models(matcher, estimator, fit, models.seed)
    gat_pair, gat_report = behind_gat(rig, detections, adapted, models, smoke)
    reports = {
        "matcher": matcher_report,
        "estimator": estimator_report,
        "estimator_behind_gat": gat_report,
    }
    return adapted, gat_pair, reports


def behind_gat(rig, detections: Detections, adapted: Models, trained: Models, smoke: bool):
    """``trained``'s estimator adapted behind the proposals of ``adapted``'s GAT alone, at its
    threshold (`BEHIND_GAT`). Returns (the pair: ``adapted`` with that estimator, its
    `AdaptReport`)."""
    config = SMOKE_ESTIMATOR_ADAPT if smoke else ESTIMATOR_ADAPT
    estimator, report = adapt_estimator(
        rig,
        detections,
        trained.estimator,
        matcher=adapted.matcher,
        proposals="gat",
        threshold=adapted.fit["threshold"],
        config=dataclasses.replace(config, seed=trained.seed),
        progress=not smoke,
    )
    return adapted._replace(estimator=estimator), report


def adaptation_record(reports: dict) -> dict:
    """The adaptation reports ({name: report}), without their step histories."""
    return {
        name: {k: v for k, v in r.to_json().items() if k != "history"}
        for name, r in reports.items()
    }


def gat_grouping(pairs: dict, detections: Detections, references: dict) -> dict:
    """The GAT alone (the paper's greedy grouping at each pair's threshold) on ``detections``:
    people per frame (groups of 2+ views) and ARI against each of ``references`` ({name: (F, C, P)
    identity}), for each pair of ``pairs`` ({`SOURCES` key: Models})."""
    out = {}
    for key, models in pairs.items():
        rows, scores = gat_match_table(models.matcher, detections)
        threshold = float(models.fit["threshold"])
        grouped = propose_people(
            rows,
            scores,
            detections.count,
            num_skeletons=detections.score.shape[2],
            threshold=threshold,
        ).identity
        out[key] = {
            "threshold": threshold,
            "people_per_frame": people_per_frame(grouped),
            **{
                f"ari_vs_{ref}": matching_scores(truth, grouped, detections.count)["ari"]
                for ref, truth in references.items()
            },
        }
    out["references"] = {ref: people_per_frame(t) for ref, t in references.items()}
    return out


def combined_identity(rig, detections: Detections, models: Models, layout: str) -> np.ndarray:
    """The combined matcher's grouping (F, C, P) with ``models`` (the adaptation's
    pseudo-labels), a reference the GAT is compared with."""
    return np.asarray(
        run_pipeline(
            rig,
            detections,
            matcher=models.matcher,
            proposals="combined",
            combined=combined_config(models.fit),
            layout=layout,
        ).identity
    )


def geometric_identity(rig, detections: Detections, layout: str) -> np.ndarray:
    """The geometric default's grouping (F, C, P), a reference the GAT is compared with."""
    return np.asarray(run_pipeline(rig, detections, layout=layout).identity)


def model_folder(models_dir: Path, name: Path, seed: int) -> Path:
    """Where the pair of training seed ``seed`` is kept: ``experiments.real``'s own folder for
    seed 0, a ``-seed<n>`` sibling for the others."""
    return models_dir / name if seed == SEED else models_dir / f"{name}-seed{seed}"


def mvor_part(root: str, models_dir: Path, seeds: tuple[int, ...], smoke: bool) -> dict:
    data = load_mvor(root)
    floor = estimate_floor_from_detections(data.rig, data.detections, layout=data.layout)
    trained_pairs = {
        seed: synthetic_models(
            data.rig,
            floor,
            model_folder(models_dir, Path("mvor-synthetic"), seed),
            smoke=smoke,
            progress=True,
            seed=seed,
        )
        for seed in seeds
    }
    if smoke:
        data = select_frames(data, real.smoke_frames(data))
    out = {"split": real.SPLIT, "frames": int(data.num_frames), "seeds": {}}
    geometric = geometric_identity(data.rig, data.detections, data.layout)
    truth = true_identity(data)
    for seed, trained in trained_pairs.items():
        adapted, gat_pair, reports = adapted_pair(data.rig, data.detections, trained, smoke)
        pairs = {"trained": trained, "adapted": adapted}
        references = {
            "geometric": geometric,
            "combined": combined_identity(data.rig, data.detections, trained, data.layout),
            "true groups": truth,
        }
        rows = mvor_rows(data, pairs, SOURCES, MVOR_MODEL_ROWS)
        rows += mvor_rows(
            data, {BEHIND_GAT[0]: gat_pair}, (BEHIND_GAT,), (PAPER_ROW,), geometric=False
        )
        out["seeds"][str(seed)] = {
            "adaptation": adaptation_record(reports),
            "rows": rows,
            "gat_alone": gat_grouping(pairs, data.detections, references),
        }
    return out


def demo_part(data: Path, models_dir: Path, seeds: tuple[int, ...], smoke: bool) -> dict:
    trial = {t.name: t for t in find_trials(data, pose_folders=("pose",)).trials}[demo.MULTI_TRIAL]
    frames = demo.SMOKE_FRAMES if smoke else None
    rig, detections = demo.raw_detections(trial, frames)
    floor = estimate_floor_from_detections(
        rig, demo.raw_detections(trial, None)[1], layout=demo.LAYOUT
    )
    out = {
        "split": demo.SPLIT,
        "trial": demo.MULTI_TRIAL,
        "frames": int(detections.score.shape[0]),
        "seeds": {},
    }
    geometric = geometric_identity(rig, detections, demo.LAYOUT)
    with tempfile.TemporaryDirectory() as tmp:
        # The geometric default as `infer` runs it: one row, the same beside every seed.
        result, seconds = demo.our_result(trial, "robust", Path(tmp) / "geometric", frames)
        geometric_row = {
            "row": GEOMETRIC[0],
            "seconds": seconds,
            **demo.score_row(result, rig, detections),
        }
    for seed in seeds:
        folder = model_folder(models_dir, Path("pose2sim-demo") / "synthetic", seed)
        trained = synthetic_models(rig, floor, folder, smoke=smoke, progress=True, seed=seed)
        adapted, gat_pair, reports = adapted_pair(rig, detections, trained, smoke)
        pairs = {"trained": trained, "adapted": adapted}
        rows = [geometric_row]
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            # The adapted pairs as `mvpose-jax adapt` writes them, for `infer` to run.
            for name, pair, estimator_report in (
                ("adapted", adapted, reports["estimator"]),
                ("adapted-gat", gat_pair, reports["estimator_behind_gat"]),
            ):
                save_adapted_matcher(
                    tmp / name / "matcher",
                    pair.matcher,
                    reports["matcher"],
                    settings_from=folder / "matcher",
                )
                save_adapted_estimator(tmp / name / "estimator", pair.estimator, estimator_report)
            plan = []
            for key, label in SOURCES:
                pair_folder = folder if key == "trained" else tmp / "adapted"
                plan += [
                    (f"infer default (combined + blend), {label}", pair_folder, None, None),
                    (f"{PAPER_ROW[0]}, {label}", pair_folder, "mlp", "gat"),
                ]
            plan.append((f"{PAPER_ROW[0]}, {BEHIND_GAT[1]}", tmp / "adapted-gat", "mlp", "gat"))
            for i, (name, pair_folder, method, proposals) in enumerate(plan):
                result, seconds = demo.our_result(
                    trial, method, tmp / f"row{i}", frames, models=pair_folder, proposals=proposals
                )
                rows.append(
                    {"row": name, "seconds": seconds, **demo.score_row(result, rig, detections)}
                )
        out["seeds"][str(seed)] = {
            "adaptation": adaptation_record(reports),
            "rows": rows,
            "gat_alone": gat_grouping(
                pairs,
                detections,
                {
                    "geometric": geometric,
                    "combined": combined_identity(rig, detections, trained, demo.LAYOUT),
                },
            ),
        }
    return out


def _row(seed_record: dict, name: str) -> dict:
    return next(r for r in seed_record["rows"] if r["row"] == name)


PAPER = ("paper's method (GAT + MLP)", "GAT + MLP")
DEFAULT = ("infer default (combined + blend)", "infer default")


def row_columns(pipeline: tuple[str, str], fields, sources=SOURCES) -> tuple:
    """Seed-table columns ((header, value of a seed's record, format), as `seed_lines` takes) of
    one pipeline's row (``pipeline``: its row name and short name) with each of ``sources``'
    pairs, for each of ``fields`` ((header, key of the row, scale, format))."""
    name, short = pipeline
    return tuple(
        (
            f"{short} {what}, {key}",
            (lambda r, f=field, x=scale, lb=label: x * _row(r, f"{name}, {lb}")[f]),
            fmt,
        )
        for what, field, scale, fmt in fields
        for key, label in sources
    )


MVOR_FIELDS = (
    ("MPJPE mm", "mpjpe_mm", 1, ".1f"),
    ("PCK3D@150 %", "pck3d_150", 1, ".1f"),
    ("PCP %", "pcp_upper", 1, ".1f"),
)
DEMO_FIELDS = (("within 20 px %", "within_20px_all_skeletons", 100, ".1f"),)
# The figures compared over training seeds, per recording: one table per pipeline.
SEED_TABLES = {
    "mvor": (
        row_columns(PAPER, MVOR_FIELDS, (*SOURCES, BEHIND_GAT)),
        row_columns(DEFAULT, MVOR_FIELDS),
    ),
    "pose2sim_demo": (
        row_columns(PAPER, DEMO_FIELDS, (*SOURCES, BEHIND_GAT)),
        row_columns(DEFAULT, DEMO_FIELDS),
    ),
}
GAT_SEED_COLUMNS = tuple(
    (f"GAT alone {what}, {key}", (lambda r, k=key, f=field: r["gat_alone"][k][f]), fmt)
    for what, field, fmt in (
        ("people / frame", "people_per_frame", ".2f"),
        ("ARI vs geometric", "ari_vs_geometric", ".3f"),
    )
    for key, _ in SOURCES
)


def seed_lines(seeds: dict, columns) -> list[str]:
    """A table of ``columns`` ((header, value of a seed's record, format)) by training seed, with
    the mean and range over the seeds."""
    lines = [
        "| seed | " + " | ".join(h for h, _, _ in columns) + " |",
        "|---|" + "---|" * len(columns),
    ]
    values = {seed: [get(r) for _, get, _ in columns] for seed, r in seeds.items()}
    for seed, vs in values.items():
        lines.append(
            f"| {seed} | "
            + " | ".join(f"{v:{fmt}}" for v, (_, _, fmt) in zip(vs, columns, strict=True))
            + " |"
        )
    if len(values) > 1:
        by_column = np.array(list(values.values()), float).T
        lines.append(
            "| mean (min-max) | "
            + " | ".join(
                f"{c.mean():{fmt}} ({c.min():{fmt}}-{c.max():{fmt}})"
                for c, (_, _, fmt) in zip(by_column, columns, strict=True)
            )
            + " |"
        )
    return lines


def markdown(report: dict) -> str:
    lines = [
        "# The paper's models adapted to the real recording, without a label",
        "",
        f"Models: {report['recipe']} (training seeds {', '.join(report['seeds'])}); adapted to "
        "each recording's own detections as `mvpose-jax adapt --matcher-out` adapts them (the "
        "matcher on the combined matcher's groups, its threshold chosen again on held-out frames "
        "against them; then the estimator; adaptation seed = training seed). Nothing is tuned on "
        "these recordings.",
        "",
    ]
    for part, title in (("mvor", "MVOR days 1-2"), ("pose2sim_demo", "Pose2Sim demo")):
        if part not in report:
            continue
        p = report[part]
        first = next(iter(p["seeds"]))
        r0 = p["seeds"][first]
        m, e = r0["adaptation"]["matcher"], r0["adaptation"]["estimator"]
        lines += [
            f"## {title} ({p['split']}; {p['frames']} frames)",
            "",
            f"Training seed {first}. Matcher adaptation: {m['steps']} steps (best "
            f"{m['best_step']}, stopped by {m['stopped']}), held-out pseudo-label loss "
            f"{m['heldout_loss_before']:.4f} -> {m['heldout_loss_after']:.4f}, threshold "
            f"{m['threshold']:g}, {m['seconds']:.0f} s. Estimator adaptation: {e['steps']} steps "
            f"(best {e['best_step']}, stopped by {e['stopped']}), {e['seconds']:.0f} s.",
            "",
        ]
        lines += mvor_table(r0["rows"]) if part == "mvor" else demo_table(r0["rows"])
        g = r0["gat_alone"]
        refs = list(g["references"])
        lines += [
            "",
            f"The GAT alone (the paper's greedy grouping), training seed {first}, against "
            "reference groupings:",
            "",
            "| GAT | threshold | people / frame | "
            + " | ".join(f"ARI vs {ref}" for ref in refs)
            + " |",
            "|---|---|---|" + "---|" * len(refs),
        ]
        for key, label in SOURCES:
            lines.append(
                f"| {label} | {g[key]['threshold']:g} | {g[key]['people_per_frame']:.2f} | "
                + " | ".join(f"{g[key][f'ari_vs_{ref}']:.3f}" for ref in refs)
                + " |"
            )
        lines += [
            "| references: people / frame | | | "
            + " | ".join(f"{g['references'][ref]:.2f}" for ref in refs)
            + " |",
            "",
            "Over training seeds:",
            "",
        ]
        for columns in (*SEED_TABLES[part], GAT_SEED_COLUMNS):
            lines += [*seed_lines(p["seeds"], columns), ""]
    lines += [f"Seconds, with training: {report['seconds']:.0f}."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="folder for real_adapted.md/.json")
    p.add_argument("--data", default=str(DEFAULT_ROOT), help="the MVOR days 1-2 folder")
    p.add_argument("--pose2sim", default=str(demo.DEFAULT_DATA), help="Pose2Sim's demo session")
    p.add_argument(
        "--models",
        help="experiments.real's models folder (its mvor-synthetic/ and pose2sim-demo/synthetic/ "
        "pairs), trained there where missing; default OUT/models",
    )
    p.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=list(SEEDS),
        help="training seeds of the model pairs (0: experiments.real's)",
    )
    p.add_argument("--smoke", action="store_true", help="smoke-size models, a few frames (CI)")
    args = p.parse_args(argv)
    start = time.perf_counter()
    out = Path(args.out)
    models_dir = Path(args.models) if args.models else out / "models"
    seeds = tuple(dict.fromkeys(args.seeds))
    report: dict = {"recipe": MODELS_RECIPE, "smoke": args.smoke, "seeds": [str(s) for s in seeds]}
    report["mvor"] = mvor_part(args.data, models_dir, seeds, args.smoke)
    if Path(args.pose2sim).is_dir():
        report["pose2sim_demo"] = demo_part(Path(args.pose2sim), models_dir, seeds, args.smoke)
    report["seconds"] = time.perf_counter() - start
    atomic_write_text(out / "real_adapted.json", report_json(report))
    text = markdown(report)
    atomic_write_text(out / "real_adapted.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
