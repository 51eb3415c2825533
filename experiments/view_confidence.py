"""Learned view confidence on real footage: ``python -m experiments.view_confidence --out DIR``.

For each real recording (MVOR days 1-2, 3 cameras; Pose2Sim's demo multi-person trial, 4
cameras): the detector is fitted to the recording's own detections (`detector_fit.fit_detector`,
no label), synthetic recordings of its rig are made with it (floor measured from the
recording's people), and the view-confidence network (`view_confidence`) is trained on them
(`view_confidence_training`); its drop threshold is chosen on synthetic validation scenes of the
same rig (never on the real recording). Then:

* MVOR (evaluation only, `experiments.real`'s split and protocol): the geometric default
  (epipolar + robust) beside epipolar + learned confidence, and the same two on the true
  groupings;
* Pose2Sim's demo: the label-free score (`label_free.label_free_score`) of the two.

Writes ``DIR/view_confidence.json`` and ``DIR/view_confidence.md``; models in ``DIR/models``.
``--smoke``: tiny training and a few frames (CI-sized).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from experiments import pose2sim_demo as demo
from experiments.mvor import DEFAULT_ROOT, load_mvor, poses_to_joints, select_frames, true_identity
from experiments.mvor_protocol import evaluate
from experiments.real import MIN_VIEWS, pipeline_result, smoke_frames
from mvpose_jax.cameras import Rig
from mvpose_jax.data.files import atomic_write_text, to_jsonable
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.detector_fit import fit_detector
from mvpose_jax.floor import estimate_floor_from_detections
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import members_from_identity
from mvpose_jax.skeletons import Detections
from mvpose_jax.synthetic import SyntheticConfig, simulate
from mvpose_jax.view_confidence import (
    ConfidenceConfig,
    save_view_confidence,
)
from mvpose_jax.view_confidence_training import (
    INLIER_FRACTION,
    choose_threshold,
    examples_from_recordings,
    features_of,
    fit_view_confidence,
    triangulation_errors,
)

SPLIT = (
    "trained on synthetic recordings of each rig with the detector fitted to its own detections; "
    "threshold chosen on synthetic validation scenes of the rig; MVOR days 1-2 evaluation only"
)
# (train scenes, dev scenes, frames per scene, people, training steps)
FULL = (12, 4, 100, 3, 3000)
SMOKE = (2, 1, 20, 2, 100)


def train_for_rig(
    rig: Rig,
    detections: Detections,
    layout: str,
    folder: Path,
    *,
    smoke: bool,
    seed: int = 0,
    fraction: float = INLIER_FRACTION,
) -> dict:
    """Fits the detector, simulates, trains and saves the model to ``folder``; returns a record."""
    n_train, n_dev, frames, people, steps = SMOKE if smoke else FULL
    start = time.perf_counter()
    fit = fit_detector(rig, detections, layout=layout, max_frames=100 if smoke else 600)
    floor = estimate_floor_from_detections(rig, detections, layout=layout)
    config = SyntheticConfig().replace(detector=fit.config)
    config = config.with_scene(floor_height=floor.height, up=floor.measured_up)
    scenes = simulate(
        rig,
        num_people=people,
        num_frames=frames,
        num_scenes=n_train + n_dev,
        config=config,
        seed=seed,
    )
    train = examples_from_recordings([s.recording for s in scenes[:n_train]], fraction)
    dev = examples_from_recordings([s.recording for s in scenes[n_train:]], fraction)
    x, y, _ = features_of(rig, train)
    dx, dy, _ = features_of(rig, dev)
    model, record = fit_view_confidence((x, y), (dx, dy), ConfidenceConfig(), steps=steps)
    errors = triangulation_errors(model, rig, dev)
    threshold = choose_threshold(errors, "robust")
    model = model._replace(config=dataclasses.replace(model.config, threshold=threshold))
    save_view_confidence(folder, model, record["dev_loss"])
    return {
        "detector": fit.to_dict(),
        "train_views": int(len(y)),
        "train_outlier_share": float(1 - y.mean()),
        "fit": {k: v for k, v in record.items() if k != "history"},
        "dev_errors_mm": {k: round(v[0], 2) for k, v in errors.items()},
        "dev_keypoints": next(iter(errors.values()))[1],
        "threshold": threshold,
        "inlier_fraction": fraction,
        "seconds": time.perf_counter() - start,
    }


def mvor_rows(data, folder: Path) -> dict:
    """The geometric default and learned confidence on MVOR, epipolar and true groupings."""
    identity = true_identity(data)
    H = data.gt.valid.shape[1]
    members = members_from_identity(identity, H)
    views = (members >= 0).sum(-1)
    rows = {}
    for name, grouping, settings in (
        ("geometric default (epipolar + robust)", "epipolar", {"method": "robust"}),
        (
            "epipolar + learned confidence",
            "epipolar",
            {"method": "confident", "confidence": str(folder)},
        ),
        ("true groups + robust", "true", {"method": "robust"}),
        (
            "true groups + learned confidence",
            "true",
            {"method": "confident", "confidence": str(folder)},
        ),
    ):
        start = time.perf_counter()
        result = pipeline_result(data, grouping, settings, identity, members)
        scores = evaluate(
            poses_to_joints(result.poses, data.layout), data, unreachable=views < MIN_VIEWS
        )
        rows[name] = {"seconds": time.perf_counter() - start, **scores}
    return rows


def pose2sim_rows(
    data: Path, folder: Path, smoke: bool, fraction: float = INLIER_FRACTION
) -> tuple[dict, dict | None]:
    """Label-free scores of the geometric default and of learned confidence on the demo's
    multi-person trial (raw ``pose/`` detections); trains the demo rig's model into ``folder``."""
    raw = {t.name: t for t in demo.find_trials(data, pose_folders=("pose",)).trials}
    rig, whole = demo.raw_detections(raw[demo.MULTI_TRIAL], None)
    record = train_for_rig(rig, whole, demo.LAYOUT, folder, smoke=smoke, fraction=fraction)
    det = Detections(*(np.asarray(a)[: demo.SMOKE_FRAMES] for a in whole)) if smoke else whole
    rows = {}
    for name, settings in (
        ("geometric default (epipolar + robust)", {"method": "robust"}),
        ("epipolar + learned confidence", {"method": "confident", "confidence": str(folder)}),
    ):
        r = run_pipeline(rig, det, layout=demo.LAYOUT, **settings)
        result = PoseResults(
            r.poses, r.confidence, r.members, r.identity, r.cameras, demo.LAYOUT, None, None
        )
        rows[name] = demo.score_row(result, rig, det)
    return rows, record


def markdown(report: dict) -> str:
    lines = [
        "# Learned view confidence on real footage",
        "",
        f"Split: {report['split']}.",
        "",
        "## MVOR days 1-2 (evaluation only)",
        "",
        "| pipeline | people missed | MPJPE mm | PCK3D@150 % |",
        "|---|---|---|---|",
    ]
    for name, row in report["mvor"]["rows"].items():
        o = row["overall"]
        lines.append(
            f"| {name} | {o['missed']} of {o['people']} | {o['mpjpe_mm']:.1f} | "
            f"{o['pck3d_150']:.1f} |"
        )
    m = report["mvor"]["model"]
    lines += [
        "",
        f"Model: {m['train_views']} training views ({100 * m['train_outlier_share']:.1f} % "
        f"outliers at inlier fraction {m['inlier_fraction']:g}), dev accuracy "
        f"{m['fit']['dev_accuracy']:.3f}, outlier recall "
        f"{m['fit']['dev_outlier_recall']:.3f}, threshold {m['threshold']:g}; synthetic dev "
        "3D error (mm) by row: " + ", ".join(f"{k} {v}" for k, v in m["dev_errors_mm"].items()),
    ]
    if "pose2sim" in report:
        lines += ["", "## Pose2Sim demo, label-free score", "", "```"]
        lines += [json.dumps(report["pose2sim"]["rows"], indent=1), "```"]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--data", default=str(DEFAULT_ROOT))
    p.add_argument("--pose2sim", default=str(demo.DEFAULT_DATA))
    p.add_argument("--smoke", action="store_true")
    p.add_argument(
        "--inlier-fraction",
        type=float,
        default=INLIER_FRACTION,
        help="a synthetic view's keypoint is an inlier within this fraction of the person's "
        "image size of its truth (the training labels)",
    )
    args = p.parse_args(argv)
    out = Path(args.out)
    data = load_mvor(args.data)
    folder = out / "models" / "mvor-view-confidence"
    report = {"split": SPLIT}
    record = train_for_rig(
        data.rig,
        data.detections,
        data.layout,
        folder,
        smoke=args.smoke,
        fraction=args.inlier_fraction,
    )
    if args.smoke:
        data = select_frames(data, smoke_frames(data))
    report["mvor"] = {"model": record, "rows": mvor_rows(data, folder)}
    if Path(args.pose2sim).is_dir():
        rows, rec = pose2sim_rows(
            Path(args.pose2sim),
            out / "models" / "pose2sim-view-confidence",
            args.smoke,
            args.inlier_fraction,
        )
        report["pose2sim"] = {"model": rec, "rows": rows}
    atomic_write_text(out / "view_confidence.json", json.dumps(to_jsonable(report), indent=1))
    text = markdown(report)
    atomic_write_text(out / "view_confidence.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
