"""The main job: ``python -m experiments.run [--experiment NAME] [--out DIR]``.

The default experiment, ``synthetic-summary``, runs on the embedded default (the ``panoptic5``
rig): it generates a short synthetic multi-person recording, prints what is in it (people,
detections, occlusion, misses, false positives) and the triangulation baseline on the true person
groupings for the paper's three detection variants (D-detected, D-projected, D-average), and writes
``results/<experiment>/summary.json``, ``summary.md`` and the recording itself (native JSON).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from mvpose_jax.data import save_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.files import atomic_write_text
from mvpose_jax.data.synthetic import detection_variants, generate_recording
from mvpose_jax.features import people_from_identity
from mvpose_jax.inference import triangulate_grouped
from mvpose_jax.metrics import pose_metrics


def synthetic_summary(rig_name: str, num_people: int, num_frames: int, seed: int, out: Path) -> dict:
    """Generates a recording and summarises it with the triangulation baseline."""
    rig = load_rig(rig_name)
    t0 = time.perf_counter()
    rec = generate_recording(rig, num_people=num_people, num_frames=num_frames, seed=seed, progress=True)
    gen_s = time.perf_counter() - t0
    det = rec.detections
    score = np.asarray(det.score)
    count = np.asarray(det.count)
    ident = np.asarray(rec.identity)
    real = ident >= 0
    rows = np.arange(score.shape[2])[None, None] < count[..., None]
    G = rec.ground_truth.valid.shape[1]
    per_view_people = np.stack([(ident == g).any(axis=-1) for g in range(G)], axis=-1)  # (F, C, G)
    summary = {
        "rig": rig_name,
        "cameras": list(rig.names),
        "frames": rec.num_frames,
        "people": G,
        "seconds_to_generate": round(gen_s, 3),
        "skeletons": int(rows.sum()),
        "true_skeletons": int((real & rows).sum()),
        "false_positive_skeletons": int((~real & rows).sum()),
        "people_detected_per_view_percent": round(100.0 * per_view_people.mean(), 2),
        "keypoints_detected_per_true_skeleton": round(float((score[real] > 0).sum(-1).mean()), 2),
        "variants": {},
    }
    for name, variant in detection_variants(rec).items():
        xy, sc = people_from_identity(np.asarray(variant.detections.xy), score, ident, G)
        rows_out = {}
        for method in ("centroid", "dlt"):
            poses, conf = triangulate_grouped(rig, xy, sc, method)
            m = pose_metrics(poses, rec.ground_truth, confidence=conf)
            rows_out[method] = {k: round(v, 2) for k, v in m.items()}
        summary["variants"][name] = rows_out
    out.mkdir(parents=True, exist_ok=True)
    save_recording(rec, out / "recording.json", rig=rig)
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    atomic_write_text(out / "summary.md", summary_markdown(summary))
    return summary


def summary_markdown(s: dict) -> str:
    lines = [
        f"# Synthetic recording on `{s['rig']}`",
        "",
        f"{s['frames']} frames, {s['people']} people, cameras {', '.join(s['cameras'])}; "
        f"generated in {s['seconds_to_generate']} s.",
        f"{s['skeletons']} skeletons: {s['true_skeletons']} of people, {s['false_positive_skeletons']} "
        f"false positives; each person is detected in {s['people_detected_per_view_percent']}% of views, "
        f"with {s['keypoints_detected_per_true_skeleton']} of 18 keypoints on average.",
        "",
        "Triangulation baseline on the true person groupings (the end-to-end run with the learned",
        "models joins this job with the pipeline; `python -m experiments.estimator` and",
        "`python -m experiments.matching` train and measure each stage today). AP and recall count a",
        "pose missing a keypoint as wrong; MPJPE is over the reconstructed keypoints.",
        "",
        "| variant | method | MPJPE (mm) | mAP | mR | PCP | completeness (%) |",
        "|---|---|---|---|---|---|---|",
    ]
    for variant, methods in s["variants"].items():
        for method, m in methods.items():
            lines.append(
                f"| D-{variant} | {method} | {m['mpjpe_mm']:.2f} | {m['map']:.2f} | {m['mean_recall']:.2f} "
                f"| {m['pcp']:.2f} | {m['completeness']:.2f} |"
            )
    return "\n".join(lines) + "\n"


EXPERIMENTS = {"synthetic-summary": synthetic_summary}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.run", description=__doc__.splitlines()[0])
    p.add_argument("--experiment", default="synthetic-summary", choices=sorted(EXPERIMENTS))
    p.add_argument("--rig", default="panoptic5", help="rig preset or calibration file")
    p.add_argument("--people", type=int, default=4)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="results folder (default results/<experiment>)")
    args = p.parse_args(argv)
    out = args.out or Path("results") / args.experiment
    summary = EXPERIMENTS[args.experiment](args.rig, args.people, args.frames, args.seed, out)
    print(summary_markdown(summary))
    print(f"written: {out}/summary.json, summary.md, recording.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
