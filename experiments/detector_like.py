"""Models trained on a detector like the recording's: ``python -m experiments.detector_like --out
DIR [--baseline-models DIR] [--smoke]`` (issue 37, items 1 and 4).

For each real recording of ``../shared/real/``, two model pairs (the paper's GAT and the small
residual MLP, `real_models.REAL_SCALE`, training seed 0), both trained without a label on
synthetic single-person recordings of its rig with the floor measured from its people:

* **default detector**: the simulator's default detector (`real_models.synthetic_models`, what
  ``python -m experiments.real`` trains; ``--baseline-models`` reuses its models folder);
* **detector like the recording's**: the detector fitted to the recording's own detections
  without a label (`detector_fit.fit_detector`: jitter, left/right swaps, dropped keypoints,
  missed people, false skeletons, border margin, scores; `real_models.synthetic_models` with ``detector``,
  what ``mvpose-jax generate --detector-like`` gives a user). The GAT's and the combined
  matcher's thresholds are chosen on frames composed from dev recordings of the same simulator.

Scored as ``experiments.real`` scores them (nothing is tuned on these recordings):

* MVOR days 1-2 (evaluation only): the MVOR protocol (`mvor_protocol.evaluate`) for the geometric
  default and, with each pair, the ``infer`` default (combined + blend), combined + MLP, the
  paper's GAT + MLP, the GAT with split people made one again (``--proposals gat-repaired``)
  + MLP and true groups + blend; and people built per frame (issue 37 item 4: the
  paper's GAT alone should build as many as the geometric grouping);
* Pose2Sim's demo, the two-person trial (no labels): the label-free score (share of every
  skeleton's keypoints within 20 px, median px, people per frame) of the ``infer`` default and the
  paper's method with each pair (`pose2sim_demo.run`'s rows) and of the GAT with splits repaired
  + MLP, beside the geometric default;
* the GAT's scores of cross-view skeleton pairs against a reference grouping (MVOR's true groups
  and the geometric default's; the demo's geometric default): ROC AUC and the shares of pairs on
  the wrong side of the chosen threshold (`pair_separation`).
* the grouping rule on the GAT's scores (`grouping_rules`): the paper's greedy union-find
  (`proposals.propose_people`) against average linkage (`proposals.propose_people_linked`, a
  person's pairs weighed together), each at the threshold with the best ARI on the composed dev
  frames; people per frame and ARI against the reference groupings on the real recordings.

Writes ``DIR/detector_like.md`` and ``DIR/detector_like.json``; the models go to ``DIR/models``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.stats import mannwhitneyu

from experiments import pose2sim_demo as demo
from experiments import real
from experiments.data import make_data
from experiments.mvor import DEFAULT_ROOT, load_mvor, poses_to_joints, select_frames, true_identity
from experiments.mvor_protocol import evaluate
from experiments.real_models import (
    MODELS_RECIPE,
    SEED,
    scale,
    synthetic_models,
    training_record,
)
from experiments.records import report_json
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.pose2sim import find_trials
from mvpose_jax.detector_fit import fit_detector
from mvpose_jax.floor import estimate_floor_from_detections
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import members_from_identity
from mvpose_jax.matcher_settings import composed_match_table
from mvpose_jax.matching import gat_match_table
from mvpose_jax.metrics import matching_scores
from mvpose_jax.proposals import choose_proposal_threshold, propose_people, propose_people_linked
from mvpose_jax.trained import Matcher

# The model pairs: (key, label).
SOURCES = (("default", "default detector"), ("fitted", "detector like the recording's"))
# MVOR rows with models: (label, grouping, 3D method) as `real.MODEL_PIPELINES` names them.
MVOR_MODEL_ROWS = (
    ("infer default (combined + blend)", "combined", "blend"),
    ("combined + MLP", "combined", "mlp"),
    ("paper's method (GAT + MLP)", "gat", "mlp"),
    ("GAT with splits repaired + MLP", "gat-repaired", "mlp"),
    ("true groups + blend", "true", "blend"),
)
GEOMETRIC = ("geometric default (epipolar + robust)", "epipolar", "robust")
# The grouping rules compared on the GAT's scores (`grouping_rules`).
GROUPING_RULES = (("greedy", propose_people), ("average linkage", propose_people_linked))
# The demo's rows: `pose2sim_demo.MODEL_SOURCES` keys of the two pairs.
DEMO_SOURCE = {"default": "synthetic", "fitted": "detector-like"}


def mvor_rows(
    data, pairs: dict, sources=SOURCES, model_rows=MVOR_MODEL_ROWS, geometric: bool = True
) -> list[dict]:
    """The MVOR protocol's overall numbers (and people built per frame) of the geometric default
    (first; left out with ``geometric`` False) and of ``model_rows`` ((name, grouping, method),
    as `MVOR_MODEL_ROWS`) with each model pair of ``pairs`` ({``sources`` key: Models};
    ``sources``: (key, label), as `SOURCES`)."""
    identity = true_identity(data)
    members = members_from_identity(identity, data.gt.valid.shape[1])
    views = (members >= 0).sum(-1)
    plan = [(GEOMETRIC[0], None, GEOMETRIC[1], {"method": GEOMETRIC[2]})] if geometric else []
    for key, label in sources:
        for name, grouping, method in model_rows:
            settings = real.model_settings(grouping, method, pairs[key])
            plan.append((f"{name}, {label}", key, grouping, settings))
    rows = []
    for name, key, grouping, settings in plan:
        start = time.perf_counter()
        result = real.pipeline_result(data, grouping, settings, identity, members)
        seconds = time.perf_counter() - start
        joints = poses_to_joints(result.poses, data.layout)
        s = evaluate(joints, data, unreachable=views < real.MIN_VIEWS)["overall"]
        built = int(np.asarray(result.poses.valid, bool).sum())
        rows.append(
            {
                "row": name,
                "models": key,
                "missed": s["missed"],
                "people": s["people"],
                "mpjpe_mm": s["mpjpe_mm"],
                "pck3d_150": s["pck3d_150"],
                "pcp_upper": s["pcp_upper"],
                "produced": s["produced"],
                "people_per_frame": built / data.num_frames,
                "seconds": seconds,
            }
        )
    return rows


def pair_separation(matcher: Matcher, threshold: float, detections, identity) -> dict:
    """How the GAT's scores of cross-view skeleton pairs separate the pairs of one person from the
    others, by a reference grouping ``identity`` (F, C, P; -1: no person, left out); see
    `score_separation`."""
    rows, scores = gat_match_table(matcher, detections)
    f, ca, sa, cb, sb = rows.T
    a, b = identity[f, ca, sa], identity[f, cb, sb]
    known = (a >= 0) & (b >= 0)
    return score_separation(scores[known], (a == b)[known], threshold)


def score_separation(scores: np.ndarray, same: np.ndarray, threshold: float) -> dict:
    """ROC AUC of ``scores`` (n,) for telling ``same`` (n,) bool pairs from the others, the
    median score of each kind, and the shares on the wrong side of ``threshold`` (a pair of one
    person below it can split them)."""
    s, same = np.asarray(scores, np.float64), np.asarray(same, bool)
    return {
        "pairs": int(same.size),
        "same_person_pairs": int(same.sum()),
        # ROC AUC as the Mann-Whitney U over the pairs of kinds (ties count a half).
        "auc": float(mannwhitneyu(s[same], s[~same]).statistic / (same.sum() * (~same).sum())),
        "median_same": float(np.median(s[same])),
        "median_other": float(np.median(s[~same])),
        "same_below_threshold": float((s[same] < threshold).mean()),
        "other_above_threshold": float((s[~same] >= threshold).mean()),
        "threshold": threshold,
    }


def grouping_rules(models, rig, floor, detector, smoke: bool, detections, references: dict) -> dict:
    """The GAT's scores grouped by each of `GROUPING_RULES`, each at the threshold with the best
    per-frame ARI on frames composed from the pair's dev recordings (regenerated as
    `real_models.synthetic_models` made them: same scale, seed, floor and ``detector``;
    `proposals.choose_proposal_threshold` with the rule as its grouping), then on the real
    ``detections``: people per frame (the groups of 2+ views) and ARI against each of
    ``references`` ({name: (F, C, P) identity})."""
    sc = scale(smoke)
    data = make_data(
        rig, {}, sc, SEED, False, floor_height=floor.height, up=floor.measured_up, detector=detector
    )
    dev_rows, dev_scores, identity, dev_count = composed_match_table(
        models.matcher, data.dev, num_samples=sc.threshold_frames, seed=SEED
    )
    rows, scores = gat_match_table(models.matcher, detections)
    out = {}
    for name, rule in GROUPING_RULES:
        best, ari = choose_proposal_threshold(
            dev_rows, dev_scores, identity, dev_count, grouping=rule
        )
        grouped = rule(
            rows, scores, detections.count, num_skeletons=detections.score.shape[2], threshold=best
        ).identity
        out[name] = {
            "threshold": best,
            "dev_ari": ari[best],
            "dev_ari_by_threshold": {str(k): v for k, v in ari.items()},
            "people_per_frame": people_per_frame(grouped),
            **{
                f"ari_vs_{ref}": matching_scores(truth, grouped, detections.count)["ari"]
                for ref, truth in references.items()
            },
        }
    out["references"] = {ref: people_per_frame(t) for ref, t in references.items()}
    return out


def people_per_frame(identity: np.ndarray) -> float:
    """Mean number of people (distinct identities >= 0) per frame of (F, C, P) identities."""
    ident = np.asarray(identity).reshape(len(identity), -1)
    return float(np.mean([len(np.unique(f[f >= 0])) for f in ident]))


def demo_rows(table: dict) -> list[dict]:
    """The demo's geometric default and model rows of ``table`` (`pose2sim_demo.run`), with the
    headline numbers."""
    wanted = {demo.OUR_ROWS[0][0]: None} | {
        label: key
        for label, source, _ in demo.MODEL_ROWS
        for key, s in DEMO_SOURCE.items()
        if s == source
    }
    return [
        _headline(row) | {"models": wanted[row["row"]]}
        for row in table["multi_person"]["rows"]
        if row["row"] in wanted
    ]


def _headline(row: dict) -> dict:
    n = row["all_keypoints"]
    keys = ("within_20px_all_skeletons", "median_px", "coverage", "people_per_frame", "jitter_m_s2")
    return {"row": row["row"], **{k: n[k] for k in keys}}


def fitted_fields(fit) -> dict:
    """The fitted detector's fields that differ from the default (value, samples)."""
    return {
        f.name: {"value": f.value, "samples": f.samples, "fitted": f.fitted} for f in fit.fields
    }


def mvor_table(rows: list[dict]) -> list[str]:
    """`mvor_rows`' rows as a markdown table."""
    lines = [
        "| pipeline | missed / people | MPJPE mm | PCK3D@150 % | PCP upper % "
        "| joints produced % | people built / frame |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['row']} | {r['missed']} / {r['people']} | {r['mpjpe_mm']:.1f} "
            f"| {r['pck3d_150']:.1f} | {r['pcp_upper']:.1f} | {r['produced']:.1f} "
            f"| {r['people_per_frame']:.2f} |"
        )
    return lines


def demo_table(rows: list[dict]) -> list[str]:
    """Label-free score rows (`pose2sim_demo.score_row`'s numbers and a ``row`` name) as a
    markdown table."""
    lines = [
        "| result | within 20 px (all skeletons) % | median px | coverage % | people / frame "
        "| jitter m/s² |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['row']} | {100 * r['within_20px_all_skeletons']:.1f} "
            f"| {r['median_px']:.2f} | {100 * r['coverage']:.1f} "
            f"| {r['people_per_frame']:.2f} | {r['jitter_m_s2']:.2f} |"
        )
    return lines


def markdown(report: dict) -> str:
    lines = [
        "# Models trained on a detector like the recording's",
        "",
        f"Models: {report['recipe']}. One pair with the simulator's default detector, one with "
        "the detector fitted to the recording's own detections (no label). Nothing is tuned on "
        "these recordings.",
        "",
    ]
    if "mvor" in report:
        m = report["mvor"]
        lines += [f"## MVOR days 1-2 ({m['split']})", "", *mvor_table(m["rows"]), ""]
    if "pose2sim_demo" in report:
        d = report["pose2sim_demo"]
        lines += [
            f"## Pose2Sim demo, {d['trial']} (no labels: the label-free score)",
            "",
            *demo_table(d["rows"]),
            "",
        ]
    lines += [
        "## The GAT's pair scores (same person or not, by a reference grouping)",
        "",
        "| recording | models' detector | reference | pairs (same person) | ROC AUC | median score, "
        "same / other | threshold | same below it % | other above it % |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for rec in ("mvor", "pose2sim_demo"):
        for key, by_reference in report.get(rec, {}).get("pair_separation", {}).items():
            for reference, p in by_reference.items():
                lines.append(
                    f"| {rec} | {dict(SOURCES)[key]} | {reference} | {p['pairs']} "
                    f"({p['same_person_pairs']}) | {p['auc']:.3f} | {p['median_same']:.2f} / "
                    f"{p['median_other']:.3f} | {p['threshold']:g} "
                    f"| {100 * p['same_below_threshold']:.1f} "
                    f"| {100 * p['other_above_threshold']:.1f} |"
                )
    lines += [
        "",
        "## The grouping rule on the GAT's scores (threshold chosen on composed dev frames)",
        "",
        "| recording | models' detector | rule | threshold | dev ARI | people / frame "
        "| ARI vs true groups | ARI vs geometric |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for rec in ("mvor", "pose2sim_demo"):
        for key, by_rule in report.get(rec, {}).get("grouping_rules", {}).items():
            refs = by_rule["references"]
            for rule, _ in GROUPING_RULES:
                g = by_rule[rule]
                cells = [
                    f"{g[f'ari_vs_{ref}']:.3f}" if f"ari_vs_{ref}" in g else "-"
                    for ref in ("true groups", "geometric")
                ]
                lines.append(
                    f"| {rec} | {dict(SOURCES)[key]} | {rule} | {g['threshold']:g} "
                    f"| {g['dev_ari']:.4f} | {g['people_per_frame']:.2f} | {' | '.join(cells)} |"
                )
            lines.append(
                f"| {rec} | | references: "
                + ", ".join(f"{ref} {v:.2f} people / frame" for ref, v in refs.items())
                + " | | | | | |"
            )
    lines += ["", f"Seconds, with training: {report['seconds']:.0f}."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="folder for detector_like.md/.json and models")
    p.add_argument("--data", default=str(DEFAULT_ROOT), help="the MVOR days 1-2 folder")
    p.add_argument("--pose2sim", default=str(demo.DEFAULT_DATA), help="Pose2Sim's demo session")
    p.add_argument(
        "--baseline-models",
        help="experiments.real's models folder (its mvor-synthetic/ and pose2sim-demo/synthetic/ "
        "are the default detector's pairs); default OUT/models, trained there where missing",
    )
    p.add_argument("--smoke", action="store_true", help="smoke-size models, a few frames (CI)")
    args = p.parse_args(argv)
    start = time.perf_counter()
    out = Path(args.out)
    base = Path(args.baseline_models) if args.baseline_models else out / "models"
    report: dict = {"recipe": MODELS_RECIPE, "smoke": args.smoke}

    data = load_mvor(args.data)
    floor = estimate_floor_from_detections(data.rig, data.detections, layout=data.layout)
    fit = fit_detector(data.rig, data.detections, layout=data.layout)
    print("\n".join([f"{args.data}: fitted detector", *fit.describe()]))
    detector_of = {"default": None, "fitted": fit.config}
    pairs = {
        "default": synthetic_models(
            data.rig, floor, base / "mvor-synthetic", smoke=args.smoke, progress=True
        ),
        "fitted": synthetic_models(
            data.rig,
            floor,
            out / "models" / "mvor-detector-like",
            smoke=args.smoke,
            progress=True,
            detector=fit.config,
        ),
    }
    if args.smoke:
        data = select_frames(data, real.smoke_frames(data))
    truth = true_identity(data)
    geometric = np.asarray(run_pipeline(data.rig, data.detections, layout=data.layout).identity)
    report["mvor"] = {
        "split": real.SPLIT,
        "detector": fitted_fields(fit),
        "training": {k: training_record(m, floor) for k, m in pairs.items()},
        "rows": mvor_rows(data, pairs),
        "pair_separation": {
            k: {
                reference: pair_separation(m.matcher, m.fit["threshold"], data.detections, ident)
                for reference, ident in (("true groups", truth), ("geometric", geometric))
            }
            for k, m in pairs.items()
        },
        "grouping_rules": {
            k: grouping_rules(
                m,
                data.rig,
                floor,
                detector_of[k],
                args.smoke,
                data.detections,
                {"true groups": truth, "geometric": geometric},
            )
            for k, m in pairs.items()
        },
    }

    demo_data = Path(args.pose2sim)
    if demo_data.is_dir():
        trial = {t.name: t for t in find_trials(demo_data, pose_folders=("pose",)).trials}[
            demo.MULTI_TRIAL
        ]
        rig, detections = demo.raw_detections(trial, None)
        floor = estimate_floor_from_detections(rig, detections, layout=demo.LAYOUT)
        fit = fit_detector(rig, detections, layout=demo.LAYOUT)
        print("\n".join([f"{trial.folder}: fitted detector", *fit.describe()]))
        detector_of = {"default": None, "fitted": fit.config}
        folders = {
            "default": base / "pose2sim-demo" / "synthetic",
            "fitted": out / "models" / "pose2sim-demo-detector-like",
        }
        pairs = {
            "default": synthetic_models(rig, floor, folders["default"], smoke=args.smoke),
            "fitted": synthetic_models(
                rig, floor, folders["fitted"], smoke=args.smoke, progress=True, detector=fit.config
            ),
        }
        table = demo.run(
            demo_data,
            smoke=args.smoke,
            models={DEMO_SOURCE[k]: folder for k, folder in folders.items()},
        )
        frames = demo.SMOKE_FRAMES if args.smoke else None
        repaired = []
        with tempfile.TemporaryDirectory() as tmp:
            for key, label in SOURCES:
                result, _ = demo.our_result(
                    trial,
                    "mlp",
                    Path(tmp) / key,
                    frames,
                    models=folders[key],
                    proposals="gat-repaired",
                )
                scored = demo.raw_detections(trial, frames)[1]
                repaired.append(
                    {
                        "row": f"{label}: GAT with splits repaired + MLP, pose/",
                        "all_keypoints": demo.score_row(result, rig, scored),
                    }
                )
        geometric = np.asarray(run_pipeline(rig, detections, layout=demo.LAYOUT).identity)
        report["pose2sim_demo"] = {
            "split": demo.SPLIT,
            "trial": demo.MULTI_TRIAL,
            "detector": fitted_fields(fit),
            "training": {k: training_record(m, floor) for k, m in pairs.items()},
            "rows": demo_rows(table)
            + [_headline(r) | {"models": k} for (k, _), r in zip(SOURCES, repaired, strict=True)],
            "pair_separation": {
                k: {
                    "geometric": pair_separation(
                        m.matcher, m.fit["threshold"], detections, geometric
                    )
                }
                for k, m in pairs.items()
            },
            "grouping_rules": {
                k: grouping_rules(
                    m,
                    rig,
                    floor,
                    detector_of[k],
                    args.smoke,
                    detections,
                    {"geometric": geometric},
                )
                for k, m in pairs.items()
            },
        }
    report["seconds"] = time.perf_counter() - start
    atomic_write_text(out / "detector_like.json", report_json(report))
    text = markdown(report)
    atomic_write_text(out / "detector_like.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
