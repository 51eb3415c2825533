"""synthetic-summary: no training; what a synthetic recording holds and the triangulation
baseline on its true groupings (``panoptic5``, 4 people)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments.config import Scale
from mvpose_jax.cameras import up_vector
from mvpose_jax.data import save_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.features import people_from_identity
from mvpose_jax.lifting import triangulate_grouped
from mvpose_jax.metrics import pose_metrics
from mvpose_jax.synthetic import detection_variants, generate_recording


def run(
    sc: Scale, seeds: list[int], data_seed: int, out: Path, progress: bool
) -> tuple[list[dict], list[str]]:
    """A recording's contents and the triangulation baseline on its true groupings (no training)."""
    rig = load_rig("panoptic5")
    rec = generate_recording(
        rig,
        num_people=4,
        num_frames=max(30, 12 * sc.test_frames),
        seed=data_seed,
        progress=progress,
    )
    ident = np.asarray(rec.identity)
    score = np.asarray(rec.detections.score)
    G = rec.ground_truth.valid.shape[1]
    res = {"seed": data_seed, "frames": rec.num_frames, "people": G, "variants": {}}
    lines = [
        "### Triangulation on the true groupings, panoptic5 (4 people)",
        "",
        "| variant | method | PCP | MPJPE mm | mAP | mR | complete % |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, variant in detection_variants(rec).items():
        xy, sc_ = people_from_identity(np.asarray(variant.detections.xy), score, ident, G)
        for method in ("centroid", "dlt"):
            poses, conf = triangulate_grouped(rig, xy, sc_, method)
            m = pose_metrics(poses, rec.ground_truth, confidence=conf, up=up_vector(rig))
            res["variants"].setdefault(name, {})[method] = m
            lines.append(
                f"| D-{name} | {method} | {m['pcp']:.2f} | {m['mpjpe_mm']:.2f} | {m['map']:.2f} | "
                f"{m['mean_recall']:.2f} | {m['completeness']:.2f} |"
            )
    save_recording(rec, out / "recording.json")
    return [res], lines + [""]
