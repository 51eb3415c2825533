"""Scoring infer's 3D poses: against ground truth when the recording has it (MPJPE, AP, recall,
PCP, matching), and by their reprojection error in every camera always."""

from __future__ import annotations

import dataclasses
from typing import Any

from mvpose_jax.jobs.common import DetectionsSource, RigSource, poses_and_detections


@dataclasses.dataclass(frozen=True)
class EvaluateConfig:
    """Attributes: rig and detections (the recording infer read), poses (its poses.npz /
    poses.json or their folder), out (also write the metrics to this JSON file; None: not)."""

    rig: RigSource
    detections: DetectionsSource
    poses: str
    out: str | None = None


def evaluate(config: EvaluateConfig) -> dict[str, Any]:
    """The metrics: ``frames``, ``people``, ``pose`` (`metrics.pose_metrics`; with ground truth),
    ``matching`` (`metrics.matching_scores`; with true identities) and ``reprojection_px``
    (camera -> mean, median, count; px). Written to ``config.out`` when given."""
    import json

    import numpy as np

    from mvpose_jax.data.files import atomic_write_text, check_writable
    from mvpose_jax.lifting import group_people
    from mvpose_jax.metrics import matching_scores, pose_metrics, reprojection_errors

    if config.out:
        check_writable(config.out, folder=False)
    poses, rec, rig = poses_and_detections(config.rig, config.detections, config.poses)
    out: dict[str, Any] = {"frames": rec.num_frames, "people": int(poses.poses.valid.sum())}
    if rec.ground_truth is not None:
        out["pose"] = pose_metrics(
            poses.poses, rec.ground_truth, layout=rec.layout, confidence=poses.confidence
        )
    if rec.identity is not None:
        P = np.shape(rec.detections.score)[2]
        ident = np.pad(
            poses.identity, [(0, 0), (0, 0), (0, P - poses.identity.shape[2])], constant_values=-1
        )
        out["matching"] = matching_scores(
            np.asarray(rec.identity), ident, np.asarray(rec.detections.count)
        )
    p_xy, p_sc = group_people(rec.detections.xy, rec.detections.score, poses.members)
    v = np.asarray(poses.poses.valid)
    out["reprojection_px"] = reprojection_errors(
        rig, poses.poses.xyz[v], poses.poses.keypoint_valid[v], p_xy[v], p_sc[v]
    )
    if config.out:
        atomic_write_text(config.out, json.dumps(out, indent=1) + "\n")
    return out
