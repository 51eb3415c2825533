"""Evaluation, as the paper reports it (DESIGN.md §1.4). Host-side numpy; metrics are not a hot path.

3D poses:
  * `match_people`: per frame, the assignment of predictions to ground truth that minimises the
    total error (Hungarian, scipy), on the evaluation keypoints both have.
  * `pose_metrics`: MPJPE (mm) over matched pairs; AP at 25..150 mm and their mean (mAP) and mean
    recall (mR), computed the way VoxelPose's evaluation (which the paper follows) does: every
    prediction is matched to its nearest ground truth, predictions are ranked by confidence, a
    prediction is a true positive when its MPJPE is under the threshold and its ground truth is not
    taken yet; PCP (a bone is correct when the mean error of its two ends is at most half its
    length); completeness (share of ground-truth keypoints that got a prediction).
  * `reprojection_errors`: per camera, the pixel distances between projected predictions and the
    detections they came from (mean and median; the paper's Table 7, no ground truth needed).
"""

from __future__ import annotations

import numpy as np

from mvpose_jax.cameras import Rig, project_points
from mvpose_jax.skeletons import Poses3D, evaluation_keypoints, get_layout

AP_THRESHOLDS_MM = (25, 50, 75, 100, 125, 150)


def _pair_errors(pred_xyz, pred_kv, gt_xyz, gt_kv):
    """Mean keypoint error (m) of every (prediction, ground truth) pair of one frame.

    pred_xyz (P, K, 3), pred_kv (P, K), gt_xyz (G, K, 3), gt_kv (G, K) -> (P, G), inf where no
    keypoint is shared.
    """
    d = np.linalg.norm(pred_xyz[:, None] - gt_xyz[None], axis=-1)  # (P, G, K)
    both = pred_kv[:, None] & gt_kv[None]
    n = both.sum(axis=-1)
    err = np.where(both, d, 0.0).sum(axis=-1) / np.maximum(n, 1)
    return np.where(n > 0, err, np.inf)


def match_people(pred: Poses3D, gt: Poses3D, keypoints: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame, the minimum-total-error assignment of valid predictions to valid ground truth.

    Args:
      pred, gt: `Poses3D` (numpy) of F frames.
      keypoints: the keypoint indices to compare on.
    Returns:
      per frame (pred_index, gt_index) arrays of the matched pairs.
    """
    from scipy.optimize import linear_sum_assignment

    out = []
    for f in range(np.shape(gt.valid)[0]):
        p_idx = np.flatnonzero(pred.valid[f])
        g_idx = np.flatnonzero(gt.valid[f])
        if len(p_idx) == 0 or len(g_idx) == 0:
            out.append((np.zeros(0, int), np.zeros(0, int)))
            continue
        err = _pair_errors(
            pred.xyz[f][p_idx][:, keypoints], pred.keypoint_valid[f][p_idx][:, keypoints],
            gt.xyz[f][g_idx][:, keypoints], gt.keypoint_valid[f][g_idx][:, keypoints],
        )  # fmt: skip
        cost = np.where(np.isfinite(err), err, 1e6)
        rows, cols = linear_sum_assignment(cost)
        keep = np.isfinite(err[rows, cols])
        out.append((p_idx[rows[keep]], g_idx[cols[keep]]))
    return out


def pose_metrics(
    pred: Poses3D,
    gt: Poses3D,
    *,
    layout: str = "coco18",
    confidence: np.ndarray | None = None,
    thresholds_mm: tuple[float, ...] = AP_THRESHOLDS_MM,
) -> dict[str, float]:
    """The paper's 3D metrics over a recording.

    Args:
      pred: predicted `Poses3D` (F, P, K); keypoints not produced have keypoint_valid False.
      gt: ground truth `Poses3D` (F, G, K).
      layout: keypoint layout (the evaluation keypoints are all but eyes and ears).
      confidence: optional (F, P) ranking score of each prediction for AP (default: all equal,
        ranked by frame order).
    Returns:
      mpjpe_mm, ap_<th> (percent) per threshold, map, mean_recall (percent), pcp (percent),
      completeness (percent), num_gt, num_pred.
    """
    pred = Poses3D(*(np.asarray(a) for a in pred))
    gt = Poses3D(*(np.asarray(a) for a in gt))
    kps = evaluation_keypoints(layout)
    lay = get_layout(layout)
    bones = [(a, b) for a, b in lay.bones if a in kps and b in kps]

    # MPJPE, PCP and completeness over the minimum-total-error matching.
    errors, pcp_hits, pcp_total, produced, gt_kp_total = [], 0, 0, 0, 0
    matches = match_people(pred, gt, kps)
    for f, (pi, gi) in enumerate(matches):
        gt_kp_total += int(gt.keypoint_valid[f][gt.valid[f]][:, kps].sum())
        for p, g in zip(pi, gi, strict=True):
            both = pred.keypoint_valid[f, p, kps] & gt.keypoint_valid[f, g, kps]
            d = np.linalg.norm(pred.xyz[f, p, kps] - gt.xyz[f, g, kps], axis=-1)
            errors.append(d[both])
            produced += int(both.sum())
            for a, b in bones:
                if gt.keypoint_valid[f, g, a] and gt.keypoint_valid[f, g, b]:
                    pcp_total += 1
                    if pred.keypoint_valid[f, p, a] and pred.keypoint_valid[f, p, b]:
                        length = np.linalg.norm(gt.xyz[f, g, a] - gt.xyz[f, g, b])
                        ea = np.linalg.norm(pred.xyz[f, p, a] - gt.xyz[f, g, a])
                        eb = np.linalg.norm(pred.xyz[f, p, b] - gt.xyz[f, g, b])
                        pcp_hits += int((ea + eb) / 2 <= 0.5 * length)
    all_err = np.concatenate(errors) if errors else np.zeros(0)
    out = {
        "mpjpe_mm": float(all_err.mean() * 1000) if all_err.size else float("nan"),
        "pcp": 100.0 * pcp_hits / max(pcp_total, 1),
        "completeness": 100.0 * produced / max(gt_kp_total, 1),
    }
    out.update(_ap_and_recall(pred, gt, kps, confidence, thresholds_mm))
    return out


def _ap_and_recall(pred, gt, kps, confidence, thresholds_mm):
    """VoxelPose-style AP and recall: each prediction against its nearest ground truth."""
    records = []  # (confidence, mpjpe_mm, frame, gt index)
    num_gt = int(np.asarray(gt.valid).sum())
    F = np.shape(gt.valid)[0]
    for f in range(F):
        p_idx = np.flatnonzero(pred.valid[f])
        g_idx = np.flatnonzero(gt.valid[f])
        if len(p_idx) == 0:
            continue
        if len(g_idx) == 0:
            for p in p_idx:
                records.append((_conf(confidence, f, p), np.inf, f, -1))
            continue
        err = _pair_errors(pred.xyz[f][p_idx][:, kps], pred.keypoint_valid[f][p_idx][:, kps],
                           gt.xyz[f][g_idx][:, kps], gt.keypoint_valid[f][g_idx][:, kps])  # fmt: skip
        nearest = err.argmin(axis=1)
        for i, p in enumerate(p_idx):
            records.append((_conf(confidence, f, p), 1000.0 * err[i, nearest[i]], f, g_idx[nearest[i]]))
    # Highest confidence first; ties keep frame order (stable).
    order = sorted(range(len(records)), key=lambda i: -records[i][0])
    out = {"num_gt": float(num_gt), "num_pred": float(len(records))}
    aps, recalls = [], []
    for th in thresholds_mm:
        taken, tp = set(), np.zeros(len(order))
        for rank, i in enumerate(order):
            _, e, f, g = records[i]
            if e < th and (f, g) not in taken:
                tp[rank] = 1
                taken.add((f, g))
        ctp = np.cumsum(tp)
        recall = ctp / max(num_gt, 1)
        precision = ctp / np.arange(1, len(order) + 1) if len(order) else np.zeros(0)
        ap = _average_precision(recall, precision)
        out[f"ap_{int(th)}"] = 100.0 * ap
        aps.append(ap)
        recalls.append(recall[-1] if len(recall) else 0.0)
    out["map"] = 100.0 * float(np.mean(aps))
    out["mean_recall"] = 100.0 * float(np.mean(recalls))
    return out


def _conf(confidence, f, p):
    return 0.0 if confidence is None else float(confidence[f, p])


def _average_precision(recall: np.ndarray, precision: np.ndarray) -> float:
    """Area under the precision envelope (VOC-style, all points), as VoxelPose computes AP."""
    if recall.size == 0:
        return 0.0
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.concatenate([[0.0], precision, [0.0]])
    for i in range(len(mpre) - 2, -1, -1):
        mpre[i] = max(mpre[i], mpre[i + 1])
    idx = np.flatnonzero(mrec[1:] != mrec[:-1])
    return float(np.sum((mrec[idx + 1] - mrec[idx]) * mpre[idx + 1]))


def reprojection_errors(
    rig: Rig, xyz: np.ndarray, keypoint_valid: np.ndarray, xy: np.ndarray, score: np.ndarray
) -> dict[str, dict[str, float]]:
    """Pixel distances between projected 3D keypoints and the detections, per camera.

    Args:
      rig: C cameras (the detections' cameras).
      xyz: (N, K, 3) people's keypoints, metres; keypoint_valid: (N, K).
      xy: (N, C, K, 2) each person's detections; score: (N, C, K), 0 = missing.
    Returns:
      {camera name: {"mean": px, "median": px, "count": n}}.
    """
    px = np.moveaxis(np.asarray(project_points(rig, np.asarray(xyz, np.float32))), 0, 1)  # (N, C, K, 2)
    d = np.linalg.norm(px - np.asarray(xy), axis=-1)  # (N, C, K)
    use = (np.asarray(score) > 0) & np.asarray(keypoint_valid)[:, None, :]
    out = {}
    for c, name in enumerate(rig.names):
        e = d[:, c][use[:, c]]
        out[name] = {
            "mean": float(e.mean()) if e.size else float("nan"),
            "median": float(np.median(e)) if e.size else float("nan"),
            "count": float(e.size),
        }
    return out
