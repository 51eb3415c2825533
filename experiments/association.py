"""Track-level association on real footage (issue 37, item 4):
``python -m experiments.association --out DIR [--models DIR] [--smoke]``.

The Pose2Sim demo's two-person trial (no labels): each grouping with and without track-level
association (`PipelineConfig.association`: after a chunk is tracked, each 2D skeleton joins the
tracked person it fits in its view, and the people are lifted and tracked again), as
``infer --session`` runs it, tracked and unfiltered (no Butterworth, no gap filling, no outlier
rejection: the grouping and the 3D stage are compared, not the filter). The models are those of
the rig trained on synthetic recordings with the floor measured from the trial's people
(`real_models.synthetic_models`, loaded from ``--models`` when it holds them). Each row gets the
label-free score (`label_free.label_free_score`): people per frame against the geometric
grouping's, and the share of every skeleton's keypoints the result's projection puts within
20 px. Also live (one frame a chunk: only the tracked people of the last frames are anchors).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from experiments import pose2sim_demo as demo
from experiments.config import seed_stream
from experiments.real_models import synthetic_models
from experiments.records import report_json
from mvpose_jax.cameras import up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.pose2sim import find_trials
from mvpose_jax.floor import estimate_floor_from_detections
from mvpose_jax.inference import FilterConfig, PipelineConfig, run_pipeline
from mvpose_jax.jobs.infer import INFER_PIPELINE
from mvpose_jax.lifting import LiftingConfig
from mvpose_jax.metrics import pose_metrics
from mvpose_jax.synthetic import generate_recording
from mvpose_jax.tracking import AssociationConfig, TrackingConfig

# (row, models used, proposals, 3D method)
GROUPINGS = (
    ("geometric: epipolar + robust", False, "epipolar", "robust"),
    ("paper: GAT + MLP", True, "gat", "mlp"),
    ("GAT repaired + MLP", True, "gat-repaired", "mlp"),
    ("default: combined + blend", True, "combined", "blend"),
)
UNFILTERED = FilterConfig("none", fill_gap_s=0.0, outlier_m=None)


def result_of(trial, out: Path, frames, models, proposals, method, association, chunk_frames):
    """One row's poses, as ``infer --session`` makes them, with its wall time in seconds."""
    pipeline = dataclasses.replace(
        INFER_PIPELINE,
        matching=dataclasses.replace(INFER_PIPELINE.matching, proposals=proposals),
        lifting=LiftingConfig(method),
        filtering=UNFILTERED,
        association=association,
        chunk_frames=chunk_frames,
    )
    return demo.our_result(trial, None, out, frames, models=models, pipeline=pipeline)


GATES = (0.1, 0.15, 0.25)
# Epipolar cutoffs: the default, and one so strict that it splits people (a stand-in for a
# matcher that splits them, as the GAT does on real footage).
CUTOFFS = {"default cutoff 30 px": 30.0, "strict cutoff 6 px (splits people)": 6.0}


def synthetic_part(smoke: bool) -> dict:
    """Geometric groupings on synthetic panoptic5 tracking scenes (2, 4 and 8 people), with and
    without association: the gate chosen on the validation scenes, the test scenes reported."""
    rig = load_rig("panoptic5")
    people, frames = ((2,), 20) if smoke else ((2, 4, 8), 300)
    scenes = {
        split: [
            generate_recording(rig, num_people=n, num_frames=frames, seed=seed_stream(split, 0, n))
            for n in people
        ]
        for split in ("validation", "test")
    }

    def score(split: str, cutoff: float, assoc: AssociationConfig | None) -> dict:
        pcp, n, count, truth = 0.0, 0, 0.0, 0.0
        for rec in scenes[split]:
            config = PipelineConfig.of(
                method="robust", tracking=TrackingConfig(), half_score_px=cutoff
            )
            res = run_pipeline(rig, rec.detections, dataclasses.replace(config, association=assoc))
            m = pose_metrics(res.poses, rec.ground_truth, up=up_vector(rig))
            g = int(np.asarray(rec.ground_truth.valid).sum())
            pcp, n = pcp + m["pcp"] * g, n + g
            count += float(np.asarray(res.poses.valid).sum())
            truth += g
        return {"pcp": pcp / max(n, 1), "people_per_true_person": count / max(truth, 1)}

    tables = {}
    for split in ("validation", "test"):
        rows = {}
        for name, cutoff in CUTOFFS.items():
            rows[name] = score(split, cutoff, None)
            for gate in GATES:
                rows[f"{name} + association, gate {gate:g}"] = score(
                    split, cutoff, AssociationConfig(gate=gate)
                )
        tables[split] = rows
    # The gate: the best mean PCP over both groupings on the validation scenes.
    chosen = max(
        GATES,
        key=lambda g: np.mean(
            [tables["validation"][f"{c} + association, gate {g:g}"]["pcp"] for c in CUTOFFS]
        ),
    )
    return {
        "rig": "panoptic5",
        "people": people,
        "frames": frames,
        "tables": tables,
        "gate": chosen,
    }


def run(data: Path, out: Path, models: Path | None, smoke: bool, gate: float) -> dict:
    trial = {t.name: t for t in find_trials(data, pose_folders=("pose",)).trials}[demo.MULTI_TRIAL]
    frames = demo.SMOKE_FRAMES if smoke else None
    rig, det = demo.raw_detections(trial, frames)
    if models is None:
        models = out / "models"
    # The floor from every frame of the trial (a smoke run's few frames cannot measure it).
    floor = estimate_floor_from_detections(
        rig, demo.raw_detections(trial, None)[1], layout=demo.LAYOUT
    )
    synthetic_models(rig, floor, models, smoke=smoke)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, needs_models, proposals, method in GROUPINGS:
            for assoc in (None, AssociationConfig(gate=gate)):
                modes = ((256, "offline"), (1, "live")) if assoc is not None else ((256, ""),)
                for chunk, mode in modes:
                    label = name + (f" + association ({mode})" if assoc is not None else "")
                    res, seconds = result_of(
                        trial,
                        Path(tmp) / f"{len(rows)}",
                        frames,
                        models if needs_models else None,
                        proposals,
                        method,
                        assoc,
                        chunk,
                    )
                    numbers = demo.score_row(res, rig, det)
                    rows[label] = {
                        k: numbers[k]
                        for k in (
                            "people_per_frame",
                            "views_median_people",
                            "within_20px_all_skeletons",
                            "median_px",
                            "tracks",
                            "short_tracks",
                        )
                    } | {"seconds": seconds}
    return {
        "trial": demo.MULTI_TRIAL,
        "frames": int(det.score.shape[0]),
        "split": demo.SPLIT,
        "models": str(models),
        "association": dataclasses.asdict(AssociationConfig(gate=gate)),
        "filter": "none (no gap filling, no outlier rejection), tracked",
        "rows": rows,
    }


def _markdown(report: dict) -> str:
    lines = []
    syn = report.get("synthetic")
    if syn:
        lines.append(
            f"## Synthetic {syn['rig']}, {syn['people']} people, {syn['frames']} frames a scene; "
            f"gate chosen on validation: {syn['gate']:g}\n"
        )
        for split in ("validation", "test"):
            lines += [
                f"### {split}\n",
                "| grouping | PCP % | people per true person |",
                "|---|---|---|",
            ]
            for row, v in syn["tables"][split].items():
                lines.append(f"| {row} | {v['pcp']:.1f} | {v['people_per_true_person']:.3f} |")
            lines.append("")
    lines += [
        f"## {report['trial']} ({report['frames']} frames), tracked, unfiltered\n",
        "| grouping | people per frame | share within 20 px (all skeletons) % | median px | tracks "
        "(short) |",
        "|---|---|---|---|---|",
    ]
    for row, v in report["rows"].items():
        lines.append(
            f"| {row} | {v['people_per_frame']:.2f} | {100 * v['within_20px_all_skeletons']:.1f} "
            f"| {v['median_px']:.1f} | {v['tracks']} ({v['short_tracks']}) |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--models", type=Path, help="the demo rig's models (trained when missing)")
    ap.add_argument("--data", type=Path, default=demo.DEFAULT_DATA, help="the Pose2Sim demo")
    ap.add_argument("--smoke", action="store_true")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    synthetic = synthetic_part(args.smoke)
    report = run(args.data, args.out, args.models, args.smoke, synthetic["gate"])
    report["synthetic"] = synthetic
    report["command"] = "python -m experiments.association " + " ".join(argv or [])
    report["seconds"] = time.time() - t0
    atomic_write_text(args.out / "association.json", report_json(report))
    atomic_write_text(args.out / "association.md", _markdown(report))
    print(_markdown(report))


if __name__ == "__main__":
    main()
