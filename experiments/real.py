"""Real footage with labels: ``python -m experiments.real --out DIR [--smoke] [--data ROOT]``.

MVOR days 1-2 (`experiments.mvor`: the operating room, 3 cameras, OpenPose detections, 3D ground
truth of 10 upper-body joints), every frame, evaluation only: nothing is tuned on it. Each pipeline
that needs no model runs on the detections as given (frames are snapshots about 75 s apart:
no tracking, no filter):

* epipolar grouping (`inference.run_pipeline`'s geometric proposals) with each triangulation:
  DLT, the paper's pairwise centroid, and robust triangulation (the geometric default of
  ``mvpose-jax infer --method robust``);
* the ground-truth groupings (`mvor.true_identity`: detections assigned to the annotated people)
  with the same three triangulations (`lifting.poses_of_members`), to separate matching from 3D.

Scored with the MVOR protocol (`mvor.evaluate`). Writes ``DIR/real.md``, ``DIR/real.json`` (the
table, per day and overall, per joint) and ``DIR/real_joints.png`` (MPJPE per joint and method).
``--smoke`` runs three frames of each day (CI).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from experiments.mvor import (
    DEFAULT_ROOT,
    GATE_MM,
    GROUPING_GATE,
    JOINTS,
    PCK_MM,
    PCP_RATIO,
    UPPER_BODY_LIMBS,
    MvorData,
    evaluate,
    load_mvor,
    poses_to_joints,
    reprojection_of_truth,
    select_frames,
    true_identity,
)
from mvpose_jax.data.files import atomic_write_text, to_jsonable
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import members_from_identity, poses_of_members

SPLIT = "MVOR days 1-2, all frames: evaluation only, nothing tuned on it"
# (row name, grouping, 3D method)
PIPELINES = (
    ("epipolar + DLT", "epipolar", "dlt"),
    ("epipolar + centroid", "epipolar", "centroid"),
    ("geometric default (epipolar + robust)", "epipolar", "robust"),
    ("true groups + DLT", "true", "dlt"),
    ("true groups + centroid", "true", "centroid"),
    ("true groups + robust", "true", "robust"),
)
MIN_VIEWS = 2
SMOKE_FRAMES_PER_DAY = 3
SENSITIVITY_GATES_MM = (300.0, 500.0, 1000.0)
# The first look (epipolar + DLT), quoted for comparison: missed, people, MPJPE, PCK3D@150.
FIRST_LOOK = {"day1": (20, 96, 127.0, 46.0), "day2": (145, 476, 109.0, 48.0)}


def run(data: MvorData) -> dict:
    """Every pipeline of `PIPELINES` on ``data``, scored. Returns the report (JSON-able)."""
    identity = true_identity(data)
    H = data.gt.valid.shape[1]
    members = members_from_identity(identity, H)  # (F, H, C)
    views = (members >= 0).sum(-1)  # (F, H) detected views of each true person
    rows, gate_sensitivity = {}, {}
    for name, grouping, method in PIPELINES:
        start = time.perf_counter()
        if grouping == "epipolar":
            result = run_pipeline(
                data.rig, data.detections, layout=data.layout, method=method, min_views=MIN_VIEWS
            )
            poses = result.poses
        else:
            poses, _ = poses_of_members(
                data.rig,
                data.detections,
                members,
                method=method,
                min_views=MIN_VIEWS,
                layout=data.layout,
            )
        seconds = time.perf_counter() - start
        joints = poses_to_joints(poses, data.layout)
        scores = evaluate(joints, data, unreachable=views < MIN_VIEWS)
        rows[name] = {"grouping": grouping, "method": method, "seconds": seconds, **scores}
        if name == PIPELINES[0][0]:
            # How much the first row's numbers owe to the protocol's gate.
            gate_sensitivity = {
                str(int(g)): evaluate(joints, data, gate_mm=g, unreachable=views < MIN_VIEWS)
                for g in SENSITIVITY_GATES_MM
            }
    people = data.gt.valid & np.asarray(data.gt.keypoint_valid).any(-1)
    reachable = {
        key: int((people[sel] & (views[sel] >= MIN_VIEWS)).sum())
        for key, sel in [("overall", np.ones(data.num_frames, bool))]
        + [(f"day{int(d)}", data.day == d) for d in np.unique(data.day)]
    }
    return {
        "split": SPLIT,
        "protocol": {
            "gate_mm": GATE_MM,
            "pck_mm": list(PCK_MM),
            "pcp_ratio": PCP_RATIO,
            "pcp_limbs": [limb for limb, _, _ in UPPER_BODY_LIMBS],
            "ground_truth_joints": "flag 2 (annotated); flag 1 (estimated, placeholders) left out",
            "min_views": MIN_VIEWS,
            "true_grouping_gate": GROUPING_GATE,
        },
        "data": {
            "frames": data.num_frames,
            "frames_by_day": {
                f"day{int(d)}": int((data.day == d).sum()) for d in np.unique(data.day)
            },
            "people_3d": int(data.gt.valid.sum()),
            "records_3d": data.num_records_3d,
            "detections": data.num_detections,
            "detections_in_true_groups": int((identity >= 0).sum()),
            "people_detected_in_2_views": reachable,
            "ground_truth_reprojection_px": reprojection_of_truth(data),
            "scores_clipped": data.clipped_scores,
        },
        "rows": rows,
        "gate_sensitivity": {"pipeline": PIPELINES[0][0], "by_gate_mm": gate_sensitivity},
    }


def markdown(report: dict) -> str:
    """The report as Markdown: the table per day and overall, then MPJPE per joint."""
    keys = ["overall"] + sorted(k for k in report["rows"][PIPELINES[0][0]] if k.startswith("day"))
    p = report["protocol"]
    lines = [
        "# Real footage: MVOR days 1-2",
        "",
        f"Split: {report['split']}. Frames: {report['data']['frames']} "
        f"({report['data']['frames_by_day']}), {report['data']['people_3d']} people with 3D "
        f"ground truth, {report['data']['detections']} OpenPose detections.",
        "",
        f"Protocol: per frame, Hungarian matching of predicted and true people on the mean "
        f"distance over shared joints, gate {p['gate_mm']:.0f} mm; MPJPE over matched people's "
        f"annotated joints (flag 2) that were produced; PCK3D over every annotated joint of every "
        f"true person (missed people and joints not produced are wrong); upper-body PCP on 6 "
        f"limbs ({', '.join(p['pcp_limbs'])}), ratio {p['pcp_ratio']}. People need skeletons in "
        f"{p['min_views']} views. True groups: detections assigned to people by their 2D "
        f"annotation, or their projected 3D truth where a view has none (gate "
        f"{p['true_grouping_gate']} of the diagonal of the reference joints' box).",
        "",
        "People OpenPose sees in 2+ views (true groups), the most geometry can place: "
        + ", ".join(f"{k} {v}" for k, v in report["data"]["people_detected_in_2_views"].items())
        + ".",
        "",
    ]
    for key in keys:
        lines += [
            f"## {key}",
            "",
            "| pipeline | missed / people | MPJPE mm | MPJPE mm, no hips | PCK3D@100 % "
            "| PCK3D@150 % | PCP upper % | joints produced % | matched, seen in < 2 views | s, with compiling |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name, row in report["rows"].items():
            s = row[key]
            lines.append(
                f"| {name} | {s['missed']} / {s['people']} | {_num(s['mpjpe_mm'])} "
                f"| {_num(s['mpjpe_mm_without_hips'])} | {_num(s['pck3d_100'])} "
                f"| {_num(s['pck3d_150'])} | {_num(s['pcp_upper'])} | {_num(s['produced'])} "
                f"| {s['matched_unreachable']} | {row['seconds']:.2f} |"
            )
        if key in FIRST_LOOK:
            missed, people, mm, pck = FIRST_LOOK[key]
            lines.append(
                f"| issue 36's first look (epipolar + DLT) | {missed} / {people} | {mm:.0f} "
                f"| | | {pck:.0f} | | | | |"
            )
        lines.append("")
    lines += [
        "## MPJPE per joint (mm, overall)",
        "",
        "| pipeline | " + " | ".join(JOINTS) + " |",
        "|---" * (len(JOINTS) + 1) + "|",
    ]
    for name, row in report["rows"].items():
        lines.append(
            f"| {name} | " + " | ".join(_num(row["overall"]["joint_mm"][j]) for j in JOINTS) + " |"
        )
    sens = report["gate_sensitivity"]
    lines += [
        "",
        f"## The matching gate's share ({sens['pipeline']})",
        "",
        "| gate mm | day | missed / people | MPJPE mm | PCK3D@150 % | matched, seen in < 2 views |",
        "|---|---|---|---|---|---|",
    ]
    for gate, scores in sens["by_gate_mm"].items():
        for key in keys:
            s = scores[key]
            lines.append(
                f"| {gate} | {key} | {s['missed']} / {s['people']} | {_num(s['mpjpe_mm'])} "
                f"| {_num(s['pck3d_150'])} | {s['matched_unreachable']} |"
            )
    check = report["data"]["ground_truth_reprojection_px"]
    lines += [
        "",
        "3D ground truth projected into the cameras (distortion-free) vs the 2D annotations, "
        "median / 90th percentile px: "
        + ", ".join(
            f"{k} {v['all']['median']:.1f} / {v['all']['p90']:.1f}"
            for k, v in check.items()
            if k != "overall"
        )
        + ".",
        "",
        f"Run time: {report.get('seconds', float('nan')):.0f} s.",
        "",
    ]
    return "\n".join(lines)


def joint_figure(report: dict, path: Path) -> None:
    """MPJPE per joint (overall) for each pipeline, grouped bars, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mvpose_jax.render import save_figure

    names = list(report["rows"])
    highest = 0.0
    fig, ax = plt.subplots(figsize=(11, 4.2))
    width = 0.8 / len(names)
    x = np.arange(len(JOINTS))
    for i, name in enumerate(names):
        mm = [report["rows"][name]["overall"]["joint_mm"][j] for j in JOINTS]
        ax.bar(x + (i - (len(names) - 1) / 2) * width, mm, width, label=name)
        highest = max([highest] + [v for v in mm if math.isfinite(v)])
    ax.set_xticks(x, JOINTS, rotation=30)
    ax.set_ylabel("MPJPE (mm), matched people")
    ax.set_title("MVOR days 1-2: error per joint")
    ax.set_ylim(0, 1.35 * highest if highest > 0 else 1.0)  # room for the legend above the bars
    ax.legend(fontsize=7, ncol=3, loc="upper center")
    ax.grid(axis="y", alpha=0.3)
    save_figure(fig, path)


def smoke_frames(data: MvorData) -> np.ndarray:
    """The first few frames with 3D ground truth of each day."""
    has = np.asarray(data.gt.valid).any(-1)
    return np.concatenate(
        [np.flatnonzero(has & (data.day == d))[:SMOKE_FRAMES_PER_DAY] for d in np.unique(data.day)]
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="folder for real.md, real.json and the figure")
    p.add_argument("--data", default=str(DEFAULT_ROOT), help="the MVOR days 1-2 folder")
    p.add_argument("--smoke", action="store_true", help="a few frames of each day (CI)")
    args = p.parse_args(argv)
    start = time.perf_counter()
    data = load_mvor(args.data)
    if args.smoke:
        data = select_frames(data, smoke_frames(data))
    report = run(data)
    report["scale"] = "smoke" if args.smoke else "full"
    report["seconds"] = time.perf_counter() - start
    out = Path(args.out)
    atomic_write_text(out / "real.json", json.dumps(_no_nan(to_jsonable(report)), indent=1))
    text = markdown(report)
    atomic_write_text(out / "real.md", text)
    joint_figure(report, out / "real_joints.png")
    print(text)
    return 0


def _num(v: float) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.1f}"


def _no_nan(value):
    """NaN (no error to average) as JSON null."""
    if isinstance(value, dict):
        return {k: _no_nan(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_no_nan(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


if __name__ == "__main__":
    raise SystemExit(main())
