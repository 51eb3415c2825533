"""The shipped rig-agnostic estimator and matcher on real footage: ``python -m
experiments.pretrained_real --out DIR [--models MODELS]``.

Beside the geometric default and the estimator trained on synthetic recordings of each real rig
(what a user gets today after training, `real_models.synthetic_models`), with the same proposals:

* MVOR days 1-2 (labelled, 3 cameras): the MVOR protocol (annotated people missed, MPJPE,
  PCK3D@150) of epipolar proposals + robust triangulation, + the blend and + the estimator alone
  (``mlp``), of each matcher's GAT proposals + robust triangulation, of the combined matcher +
  the blend with each pair of models (`infer --matcher M --estimator E`), and of the true
  groupings + each estimator;
* the Pose2Sim demo's two-person trial (no labels, 4 cameras): the label-free yardstick
  (`label_free.label_free_score`: share of all skeletons within 20 px, people per frame).

Untracked and unfiltered (MVOR's frames are snapshots; the demo rows are compared alike).
Nothing is tuned on either: evaluation only. Writes ``DIR/pretrained_real.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from experiments import pose2sim_demo as demo
from experiments.mvor import DEFAULT_ROOT, load_mvor, poses_to_joints, select_frames, true_identity
from experiments.mvor_protocol import evaluate, versus
from experiments.real import MIN_VIEWS, pipeline_result, smoke_frames
from experiments.real_models import synthetic_models
from experiments.records import report_json
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.pose2sim import find_trials
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.floor import estimate_floor_from_detections
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import members_from_identity
from mvpose_jax.trained import (
    PRETRAINED,
    load_estimator,
    load_matcher,
    read_combined_config,
    read_proposal_threshold,
)

# (row, grouping, 3D method, estimator, matcher): estimator and matcher None, "rig" (trained on
# the rig's synthetic recordings) or "pretrained" (shipped); the matcher's proposals at the
# settings chosen with it (the rig's: on its composed dev frames; the shipped one's: on frames
# composed on its dev rigs).
ROWS = (
    ("geometric default (epipolar + robust)", "epipolar", "robust", None, None),
    ("epipolar + blend, rig's estimator", "epipolar", "blend", "rig", None),
    ("epipolar + blend, pretrained", "epipolar", "blend", "pretrained", None),
    ("epipolar + MLP, rig's estimator", "epipolar", "mlp", "rig", None),
    ("epipolar + MLP, pretrained", "epipolar", "mlp", "pretrained", None),
    ("GAT + robust, rig's matcher", "gat", "robust", None, "rig"),
    ("GAT + robust, pretrained matcher", "gat", "robust", None, "pretrained"),
    ("combined + blend, rig's models", "combined", "blend", "rig", "rig"),
    ("combined + blend, pretrained models", "combined", "blend", "pretrained", "pretrained"),
    ("true groups + robust", "true", "robust", None, None),
    ("true groups + MLP, rig's estimator", "true", "mlp", "rig", None),
    ("true groups + MLP, pretrained", "true", "mlp", "pretrained", None),
)


@dataclasses.dataclass(frozen=True)
class Scored:
    """What a run scores: the rig-agnostic ``estimator`` and ``matcher`` folders ("pretrained":
    the package's) and the ``rows`` named (`selected`; None: all)."""

    estimator: str = PRETRAINED
    matcher: str = PRETRAINED
    rows: tuple[str, ...] | None = None


def selected(names: tuple[str, ...] | None) -> tuple:
    """`ROWS` named in ``names`` (all when None), always with the geometric default first (the
    reference of the last two MVOR columns)."""
    if names is None:
        return ROWS
    unknown = set(names) - {r[0] for r in ROWS}
    if unknown:
        raise SystemExit(f"no such rows: {sorted(unknown)}; rows: {[r[0] for r in ROWS]}")
    return (ROWS[0], *(r for r in ROWS[1:] if r[0] in names))


def row_models(chosen, rig, scored: Scored, rig_pair) -> tuple[dict, dict]:
    """The estimators and ``(matcher, folder)`` pairs the ``chosen`` rows use, by kind
    ("pretrained": ``scored``'s, "rig"); ``rig_pair()`` gives the rig's (estimator, matcher,
    matcher folder), trained where missing, and is called only when a row uses the rig's models."""
    estimators = {"pretrained": load_estimator(scored.estimator, rig)}
    matchers = {"pretrained": (load_matcher(scored.matcher, rig), scored.matcher)}
    if "rig" in {kind for row in chosen for kind in row[3:]}:
        estimator, rig_matcher, folder = rig_pair()
        estimators["rig"], matchers["rig"] = estimator, (rig_matcher, folder)
    return estimators, matchers


def row_settings(method: str, estimator, matcher, grouping: str) -> dict:
    """A row's `run_pipeline` settings: its models, and its matcher's (``(matcher, folder)``)
    proposal settings as ``infer --matcher FOLDER`` reads them from the folder."""
    settings = {"method": method}
    if estimator is not None:
        settings["estimator"] = estimator
    if matcher is not None:
        settings["matcher"], folder = matcher
        if grouping == "gat":
            settings["threshold"] = read_proposal_threshold(folder)
        elif grouping == "combined":
            settings["combined"] = read_combined_config(folder)
    return settings


def mvor_rows(root: Path, models: Path, smoke: bool, scored: Scored = Scored()) -> dict:
    data = load_mvor(root)
    chosen = selected(scored.rows)

    def rig_pair():
        floor = estimate_floor_from_detections(data.rig, data.detections, layout=data.layout)
        pair = synthetic_models(data.rig, floor, models / "mvor-synthetic", smoke=smoke)
        return pair.estimator, pair.matcher, models / "mvor-synthetic" / "matcher"

    estimators, matchers = row_models(chosen, data.rig, scored, rig_pair)
    if smoke:
        data = select_frames(data, smoke_frames(data))
    identity = true_identity(data)
    members = members_from_identity(identity, data.gt.valid.shape[1])
    views = (members >= 0).sum(-1)
    rows, geometric = {}, None
    for name, grouping, method, which, matcher in chosen:
        settings = row_settings(
            method,
            estimators[which] if which else None,
            matchers[matcher] if matcher else None,
            grouping,
        )
        result = pipeline_result(data, grouping, settings, identity, members)
        joints = poses_to_joints(result.poses, data.layout)
        geometric = joints if geometric is None else geometric  # ROWS[0]
        rows[name] = evaluate(joints, data, unreachable=views < MIN_VIEWS)["overall"]
        rows[name]["vs_geometric"] = versus(joints, geometric, data)
        rows[name]["people_per_frame"] = float(np.asarray(result.poses.valid).sum(-1).mean())
    return rows


def demo_rows(data: Path, models: Path, smoke: bool, scored: Scored = Scored()) -> dict:
    trial = {t.name: t for t in find_trials(data, pose_folders=("pose",)).trials}[demo.MULTI_TRIAL]
    rig, det = demo.raw_detections(trial, demo.SMOKE_FRAMES if smoke else None)
    chosen = selected(scored.rows)

    def rig_pair():
        folder = demo.demo_models(data, models / "pose2sim-demo", smoke)["synthetic"][0]
        m = folder / "matcher"
        return load_estimator(folder / "estimator", rig), load_matcher(m, rig), m

    estimators, matchers = row_models(chosen, rig, scored, rig_pair)
    rows = {}
    for name, grouping, method, which, matcher in chosen:
        if grouping == "true":
            continue  # no true groupings without labels
        settings = row_settings(
            method,
            estimators[which] if which else None,
            matchers[matcher] if matcher else None,
            grouping,
        )
        if grouping != "epipolar":
            settings["proposals"] = grouping
        r = run_pipeline(rig, det, layout=demo.LAYOUT, **settings)
        result = PoseResults(
            r.poses, r.confidence, r.members, r.identity, r.cameras, demo.LAYOUT, None, None
        )
        rows[name] = demo.score_row(result, rig, det)
    return rows


def markdown(report: dict) -> str:
    lines = [
        "# The shipped rig-agnostic estimator and matcher on real footage",
        "",
        "Evaluation only, untracked and unfiltered. The rig's estimator: trained on synthetic "
        "recordings of that rig (the recipe of `experiments.real`). The rig-agnostic models "
        f'("pretrained" rows): estimator {report["models"]["estimator"]}, matcher '
        f"{report['models']['matcher']}.",
        "",
        "## MVOR days 1-2 (labelled; the MVOR protocol, all frames)",
        "",
        "The last two columns put each row beside the geometric default on the annotated people "
        "both place (issue 37's MPJPE criterion): MPJPE mm over each one's own joints of those "
        "people, then over the joints both produced (row / geometric default).",
        "",
        "| pipeline | missed (of annotated) | MPJPE mm | PCK3D@150 % | people both place: MPJPE "
        "| joints both produce: MPJPE | people built per frame |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in report["mvor"].items():
        v = r["vs_geometric"]
        lines.append(
            f"| {name} | {r['missed']} of {r['people']} | {r['mpjpe_mm']:.1f} | "
            f"{r['pck3d_150']:.1f} | {v['mpjpe_mm']:.1f} / {v['reference_mpjpe_mm']:.1f} "
            f"({v['people']} people) | {v['mpjpe_common_mm']:.1f} / "
            f"{v['reference_mpjpe_common_mm']:.1f} ({v['common_joints']} joints) | "
            f"{r['people_per_frame']:.2f} |"
        )
    if "demo" in report:
        lines += [
            "",
            "## Pose2Sim demo, two-person trial (no labels; the label-free yardstick)",
            "",
            "| pipeline | skeletons within 20 px | people per frame |",
            "|---|---|---|",
        ]
        for name, r in report["demo"].items():
            share = r.get("within_20px_all_skeletons")
            lines.append(
                f"| {name} | {'-' if share is None else f'{100 * share:.1f} %'} | "
                f"{r['people_per_frame']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--data", default=str(DEFAULT_ROOT), help="the MVOR days 1-2 folder")
    p.add_argument("--pose2sim", default=str(demo.DEFAULT_DATA), help="Pose2Sim's demo session")
    p.add_argument(
        "--models",
        type=Path,
        help="folder of the rigs' trained models, as experiments.real writes them (default "
        "OUT/models): reused where it holds them, trained into it where not",
    )
    p.add_argument(
        "--estimator",
        default=PRETRAINED,
        help="the rig-agnostic estimator (default: the one shipped in the package)",
    )
    p.add_argument(
        "--matcher",
        default=PRETRAINED,
        help="the rig-agnostic matcher, with its proposal settings (default: the shipped one)",
    )
    p.add_argument(
        "--rows", nargs="+", help="only these rows (names as in the tables; default: all)"
    )
    p.add_argument("--smoke", action="store_true", help="a few frames (CI)")
    args = p.parse_args(argv)
    scored = Scored(args.estimator, args.matcher, tuple(args.rows) if args.rows else None)
    start = time.perf_counter()
    models = args.models or args.out / "models"
    report = {"models": {"estimator": str(args.estimator), "matcher": str(args.matcher)}}
    report["mvor"] = mvor_rows(Path(args.data), models, args.smoke, scored)
    if Path(args.pose2sim).is_dir():
        report["demo"] = demo_rows(Path(args.pose2sim), models, args.smoke, scored)
    report["seconds"] = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "pretrained_real.json", report_json(report))
    text = markdown(report)
    atomic_write_text(args.out / "pretrained_real.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
