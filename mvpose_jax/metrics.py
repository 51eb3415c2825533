"""Evaluation, as the paper reports it (DESIGN.md §1.4). Host-side numpy; metrics are not a hot path.

3D poses:
  * `match_people`: per frame, the assignment of predictions to ground truth that minimises the
    total error (Hungarian, scipy), on the evaluation keypoints both have.
  * `pose_metrics`: MPJPE (mm) over matched pairs, on the keypoints a prediction has (so an
    incomplete triangulation is scored on what it reconstructed, as the paper scores it); AP at
    25..150 mm and their mean (mAP) and mean recall (mR), computed the way VoxelPose's evaluation
    (which the paper follows) does: every prediction is matched to its nearest ground truth,
    predictions are ranked by confidence, a prediction is a true positive when its MPJPE is under
    the threshold and its ground truth is not taken yet. For AP and recall a prediction must be
    complete: a ground-truth evaluation keypoint it did not produce makes its error infinite
    (``require_complete``; this is what makes the paper's triangulation, 22.63 mm MPJPE, score
    a lower mAP and mR than its network). PCP (a bone is correct when the mean error of its two
    ends is at most half its length); completeness (share of ground-truth keypoints that got a
    prediction).
  * `reprojection_errors`: per camera, the pixel distances between projected predictions and the
    detections they came from (mean and median; the paper's Table 7, no ground truth needed).
"""

from __future__ import annotations

import numpy as np

from mvpose_jax.cameras import Rig, project_points
from mvpose_jax.inference import propose_people
from mvpose_jax.skeletons import Poses3D, evaluation_keypoints, get_layout

AP_THRESHOLDS_MM = (25, 50, 75, 100, 125, 150)


def _pair_errors(pred_xyz, pred_kv, gt_xyz, gt_kv, require_complete=False):
    """Mean keypoint error (m) of every (prediction, ground truth) pair of one frame.

    pred_xyz (P, K, 3), pred_kv (P, K), gt_xyz (G, K, 3), gt_kv (G, K) -> (P, G), inf where no
    keypoint is shared or, with ``require_complete``, where the prediction lacks a keypoint the
    ground truth has.
    """
    d = np.linalg.norm(pred_xyz[:, None] - gt_xyz[None], axis=-1)  # (P, G, K)
    both = pred_kv[:, None] & gt_kv[None]
    n = both.sum(axis=-1)
    err = np.where(both, d, 0.0).sum(axis=-1) / np.maximum(n, 1)
    bad = n == 0
    if require_complete:
        bad |= (gt_kv[None] & ~pred_kv[:, None]).any(axis=-1)
    return np.where(bad, np.inf, err)


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
    require_complete: bool = True,
) -> dict[str, float]:
    """The paper's 3D metrics over a recording.

    Args:
      pred: predicted `Poses3D` (F, P, K); keypoints not produced have keypoint_valid False.
      gt: ground truth `Poses3D` (F, G, K).
      layout: keypoint layout (the evaluation keypoints are all but eyes and ears).
      confidence: optional (F, P) ranking score of each prediction for AP (default: all equal,
        ranked by frame order).
      require_complete: for AP and recall, a prediction missing an evaluation keypoint of its
        ground truth is never correct.
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
    out.update(_ap_and_recall(pred, gt, kps, confidence, thresholds_mm, require_complete))
    return out


def _ap_and_recall(pred, gt, kps, confidence, thresholds_mm, require_complete):
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
        args = (pred.xyz[f][p_idx][:, kps], pred.keypoint_valid[f][p_idx][:, kps],
                gt.xyz[f][g_idx][:, kps], gt.keypoint_valid[f][g_idx][:, kps])  # fmt: skip
        # The nearest ground truth by shared keypoints; its error for AP may then be infinite.
        nearest = _pair_errors(*args).argmin(axis=1)
        err = _pair_errors(*args, require_complete=require_complete)
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


# =========================================================================== matching as clustering
# (DESIGN.md §1.4, Tables 3-4) Detections are the samples; persons (true or proposed) the clusters.
# The formulas are those of Hubert & Arabie (ARI) and Rosenberg & Hirschberg (V-measure), computed
# from the non-zero cells of the contingency table, with scikit-learn's conventions for the
# degenerate cases (so the numbers equal `sklearn.metrics`' exactly).


def clustering_scores(labels_true: np.ndarray, labels_pred: np.ndarray) -> dict[str, float]:
    """Adjusted Rand index, homogeneity, completeness and V-measure (beta = 1).

    Args:
      labels_true: (n,) int class of each sample.
      labels_pred: (n,) int cluster of each sample.
    Returns:
      {"ari", "homogeneity", "completeness", "v_measure"}.
    """
    labels_true = np.asarray(labels_true).reshape(-1)
    labels_pred = np.asarray(labels_pred).reshape(-1)
    if labels_true.shape != labels_pred.shape:
        raise ValueError(f"{labels_true.shape} true labels, {labels_pred.shape} predicted")
    n = labels_true.size
    if n == 0:
        return {"ari": 1.0, "homogeneity": 1.0, "completeness": 1.0, "v_measure": 1.0}
    _, t = np.unique(labels_true, return_inverse=True)
    _, p = np.unique(labels_pred, return_inverse=True)
    cells, n_ij = np.unique(t.astype(np.int64) * (p.max() + 1) + p, return_counts=True)
    row, col = cells // (p.max() + 1), cells % (p.max() + 1)
    a = np.bincount(t).astype(np.int64)  # class sizes
    b = np.bincount(p).astype(np.int64)  # cluster sizes

    # ARI from the pair confusion matrix (ordered pairs), in Python integers (no overflow).
    sum_sq = int(np.sum(n_ij * n_ij))
    tp = sum_sq - n
    fp = int(np.sum(n_ij * b[col])) - sum_sq
    fn = int(np.sum(n_ij * a[row])) - sum_sq
    tn = n * n - fp - fn - sum_sq
    if fn == 0 and fp == 0:
        ari = 1.0
    else:
        ari = 2.0 * (tp * tn - fn * fp) / ((tp + fn) * (fn + tn) + (tp + fp) * (fp + tn))

    def entropy(sizes: np.ndarray) -> float:
        if sizes.size == 1:
            return 0.0
        return float(-np.sum(sizes / n * (np.log(sizes) - np.log(n))))

    h_true, h_pred = entropy(a), entropy(b)
    if a.size == 1 or b.size == 1:
        mi = 0.0
    else:
        # I = sum_ij n_ij/n * log(n * n_ij / (a_i * b_j))
        terms = n_ij / n * (np.log(n_ij) - np.log(n) - np.log(a[row] * b[col]) + 2 * np.log(n))
        terms = np.where(np.abs(terms) < np.finfo(np.float64).eps, 0.0, terms)
        mi = max(float(np.sum(terms)), 0.0)
    homogeneity = mi / h_true if h_true else 1.0
    completeness = mi / h_pred if h_pred else 1.0
    total = homogeneity + completeness
    v = 0.0 if total == 0 else 2.0 * homogeneity * completeness / total
    return {"ari": float(ari), "homogeneity": float(homogeneity), "completeness": float(completeness),
            "v_measure": float(v)}  # fmt: skip


def detection_clusters(identity: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Cluster labels of every real detection of F frames, unique across frames.

    A detection with identity -1 (a false positive, or one left out of every proposal) is a
    cluster of its own.

    Args:
      identity: (F, C, P) int, the person of each detection within its frame, -1 for none.
      count: (F, C) detections per view (rows ``p >= count`` are padding and are skipped).
    Returns:
      (n,) int64 labels, in (frame, camera, skeleton) order of the real detections.
    """
    identity = np.asarray(identity, np.int64)
    F, C, P = identity.shape
    ok = np.arange(P)[None, None] < np.asarray(count)[..., None]
    f, c, p = np.nonzero(ok)
    person = identity[f, c, p]
    width = max(1, int(identity.max(initial=-1)) + 1)
    singleton = width * F + np.arange(len(f))  # beyond every person label
    return np.where(person >= 0, f * width + person, singleton)


def matching_scores(true_identity: np.ndarray, pred_identity: np.ndarray, count: np.ndarray) -> dict[str, float]:
    """Clustering scores of proposals against the truth, pooled over all detections of F frames.

    Pooled: every detection of the test set is one sample (labels made unique per frame), which is
    how a dataset-level table is computed; ``frame_mean_*`` adds the mean of per-frame scores.

    Args:
      true_identity: (F, C, P) true person of each detection (-1: false positive, a singleton).
      pred_identity: (F, C, P) proposed person (-1: in no proposal, a singleton).
      count: (F, C) detections per view.
    Returns:
      {"ari", "homogeneity", "completeness", "v_measure", "frame_mean_ari", "frame_mean_v_measure",
      "detections", "frames"}.
    """
    t = detection_clusters(true_identity, count)
    p = detection_clusters(pred_identity, count)
    out = clustering_scores(t, p)
    per = [clustering_scores(detection_clusters(true_identity[f : f + 1], count[f : f + 1]),
                             detection_clusters(pred_identity[f : f + 1], count[f : f + 1]))
           for f in range(len(count))]  # fmt: skip
    out["frame_mean_ari"] = float(np.mean([s["ari"] for s in per])) if per else 1.0
    out["frame_mean_v_measure"] = float(np.mean([s["v_measure"] for s in per])) if per else 1.0
    out["detections"] = float(len(t))
    out["frames"] = float(len(count))
    return out


PROPOSAL_THRESHOLDS = (0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)


def choose_proposal_threshold(
    rows: np.ndarray,
    scores: np.ndarray,
    identity: np.ndarray,
    count: np.ndarray,
    *,
    thresholds: tuple[float, ...] = PROPOSAL_THRESHOLDS,
    min_views: int = 2,
) -> tuple[float, dict[float, float]]:
    """The proposal threshold with the best adjusted Rand index on labelled frames.

    Meant for frames composed from held-out single-person recordings
    (`inference.composed_match_table`): the proposal step's exclusivity (one skeleton per camera
    per person) already rejects most wrong pairs, so the best threshold is often well below the
    paper's 0.5, and the network's scores, fitted to 0/1 labels, need not be calibrated for it.
    Ties go to the threshold nearest 0.5.

    Args:
      rows (M, 5), scores (M,): scored pairs; identity (F, C, P): true person of each skeleton
        (-1 false detection); count (F, C).
    Returns:
      (the threshold, {threshold: ARI}).
    """
    count = np.asarray(count)
    P = np.shape(identity)[2]
    ari = {}
    for th in thresholds:
        pred = propose_people(rows, scores, count, num_skeletons=P, threshold=th, min_views=min_views)
        ari[float(th)] = matching_scores(identity, pred.identity, count)["ari"]
    best = max(ari, key=lambda th: (round(ari[th], 6), -abs(th - 0.5)))
    return best, ari
