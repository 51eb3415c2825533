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
    a lower mAP and mR than its network); completeness (share of ground-truth keypoints that
    got a prediction).
  * `pcp_scores`: PCP over the literature's 10 limbs (head, torso, upper and lower arms and legs;
    a limb is correct when the mean error of its two ends is at most half its true length), per
    limb class and per person; every limb of a ground-truth person nobody predicted is wrong.
  * Every frame counts: predictions must cover the ground truth's frames, and a frame where a
    method proposed nobody scores its people as missed.
  * `identity_metrics`: tracks over time against ground-truth identities, by the CLEAR-MOT and
    identity (IDF1) definitions, computed by py-motmetrics; a prediction and a ground-truth person
    may match in a frame when their mean keypoint error is under ``max_distance_m``.
  * `jitter`: mean |second difference| of each keypoint along a track (mm per frame²).
  * `reprojection_errors`: per camera, the pixel distances between projected predictions and the
    detections they came from (mean and median; the paper's Table 7, no ground truth needed).
"""

from __future__ import annotations

import numpy as np

from mvpose_jax.cameras import Rig, project_points
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


def match_people(
    pred: Poses3D, gt: Poses3D, keypoints: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray]]:
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
            pred.xyz[f][p_idx][:, keypoints],
            pred.keypoint_valid[f][p_idx][:, keypoints],
            gt.xyz[f][g_idx][:, keypoints],
            gt.keypoint_valid[f][g_idx][:, keypoints],
        )
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
    up: np.ndarray | None = None,
    person_ids: np.ndarray | None = None,
) -> dict:
    """The paper's 3D metrics over a recording, every frame and every ground-truth person counted.

    Args:
      pred: predicted `Poses3D` (F, P, K); keypoints not produced have keypoint_valid False, and a
        non-finite keypoint counts as not produced. A frame with no prediction is a frame where
        the method found nobody: its people count as missed, never skipped.
      gt: ground truth `Poses3D` (F, G, K), the same F frames.
      layout: keypoint layout (the evaluation keypoints are all but eyes and ears).
      confidence: optional (F, P) ranking score of each prediction for AP (default: all equal,
        ranked by frame order).
      require_complete: for AP and recall, a prediction missing an evaluation keypoint of its
        ground truth is never correct.
      up, person_ids: for PCP, see `pcp_scores`.
    Returns:
      mpjpe_mm, ap_<th> (percent) per threshold, map, mean_recall (percent), pcp (percent, 10
      limbs, missed people's limbs wrong) with pcp_by_limb and pcp_by_person, completeness
      (percent of ground-truth keypoints produced), num_gt, num_pred.
    Raises:
      ValueError when the predictions and the ground truth do not cover the same frames.
    """
    pred = _finite_only(Poses3D(*(np.asarray(a) for a in pred)))
    gt = Poses3D(*(np.asarray(a) for a in gt))
    if pred.valid.shape[0] != gt.valid.shape[0]:
        raise ValueError(
            f"predictions cover {pred.valid.shape[0]} frames, the ground truth {gt.valid.shape[0]}: "
            "every frame must be scored"
        )
    kps = evaluation_keypoints(layout)

    # MPJPE and completeness over the minimum-total-error matching.
    errors, produced = [], 0
    matches = match_people(pred, gt, kps)
    gt_kp_total = int(gt.keypoint_valid[gt.valid][:, kps].sum())
    for f, (pi, gi) in enumerate(matches):
        for p, g in zip(pi, gi, strict=True):
            both = pred.keypoint_valid[f, p, kps] & gt.keypoint_valid[f, g, kps]
            d = np.linalg.norm(pred.xyz[f, p, kps] - gt.xyz[f, g, kps], axis=-1)
            errors.append(d[both])
            produced += int(both.sum())
    all_err = np.concatenate(errors) if errors else np.zeros(0)
    out = {
        "mpjpe_mm": float(all_err.mean() * 1000) if all_err.size else float("nan"),
        "completeness": 100.0 * produced / max(gt_kp_total, 1),
    }
    out.update(pcp_scores(pred, gt, matches, layout=layout, up=up, person_ids=person_ids))
    out.update(_ap_and_recall(pred, gt, kps, confidence, thresholds_mm, require_complete))
    return out


def mpjpe_on_reference_keypoints(
    poses: Poses3D, reference: Poses3D, gt: Poses3D, *, layout: str = "coco18"
) -> float:
    """MPJPE (mm) of ``poses`` on the ground-truth keypoints that ``reference`` also produces.

    Each is matched to the ground truth on its own (`match_people`, as `pose_metrics` matches),
    so the two need not hold the same people in the same order (two groupings): like with like
    between a method and another that reconstructs fewer keypoints. A person the reference
    missed adds nothing. NaN when nothing is left.
    """
    kps = evaluation_keypoints(layout)
    poses = _finite_only(Poses3D(*(np.asarray(a) for a in poses)))
    reference = _finite_only(Poses3D(*(np.asarray(a) for a in reference)))
    gt = Poses3D(*(np.asarray(a) for a in gt))
    errors = []
    for f, ((pa, ga), (pb, gb)) in enumerate(
        zip(match_people(poses, gt, kps), match_people(reference, gt, kps), strict=True)
    ):
        of_gt = dict(zip(gb.tolist(), pb.tolist(), strict=True))
        for p, g in zip(pa.tolist(), ga.tolist(), strict=True):
            if g not in of_gt:
                continue  # the reference missed this person: none of its keypoints count
            both = (
                poses.keypoint_valid[f, p, kps]
                & gt.keypoint_valid[f, g, kps]
                & reference.keypoint_valid[f, of_gt[g], kps]
            )
            d = np.linalg.norm(poses.xyz[f, p, kps] - gt.xyz[f, g, kps], axis=-1)
            errors.append(d[both])
    err = np.concatenate(errors) if errors else np.zeros(0)
    return float(err.mean() * 1000) if err.size else float("nan")


def _finite_only(poses: Poses3D) -> Poses3D:
    """A non-finite keypoint is one the method failed to produce (so it is scored as missing)."""
    finite = np.isfinite(poses.xyz).all(-1)
    kv = poses.keypoint_valid.astype(bool) & finite & poses.valid.astype(bool)[..., None]
    return Poses3D(np.where(kv[..., None], poses.xyz, 0.0), poses.valid.astype(bool), kv)


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
        args = (
            pred.xyz[f][p_idx][:, kps],
            pred.keypoint_valid[f][p_idx][:, kps],
            gt.xyz[f][g_idx][:, kps],
            gt.keypoint_valid[f][g_idx][:, kps],
        )
        # The nearest ground truth by shared keypoints; its error for AP may then be infinite.
        nearest = _pair_errors(*args).argmin(axis=1)
        err = _pair_errors(*args, require_complete=require_complete)
        for i, p in enumerate(p_idx):
            records.append(
                (_conf(confidence, f, p), 1000.0 * err[i, nearest[i]], f, g_idx[nearest[i]])
            )
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


# =========================================================================== PCP, 10 limbs
# The limbs the multi-view literature scores (Shelf, Campus; Belagiannis et al., VoxelPose): head,
# torso, upper and lower arms, upper and lower legs. Head and torso ends are not COCO keypoints;
# they are derived from the nose, shoulders and hips as VoxelPose converts COCO poses to Shelf's:
# the bottom of the head halfway from the shoulders' midpoint to the nose, the top of the head at
# that offset scaled 0.75 across and 1.5 along the vertical, the torso from the hips' midpoint to
# the bottom of the head.
PCP_LIMBS = (
    ("head", "head_bottom", "head_top"),
    ("torso", "hip_mid", "head_bottom"),
    ("l_upper_arm", "l_shoulder", "l_elbow"),
    ("r_upper_arm", "r_shoulder", "r_elbow"),
    ("l_lower_arm", "l_elbow", "l_wrist"),
    ("r_lower_arm", "r_elbow", "r_wrist"),
    ("l_upper_leg", "l_hip", "l_knee"),
    ("r_upper_leg", "r_hip", "r_knee"),
    ("l_lower_leg", "l_knee", "l_ankle"),
    ("r_lower_leg", "r_knee", "r_ankle"),
)
PCP_CLASSES = {
    "head": ("head",),
    "torso": ("torso",),
    "upper_arm": ("l_upper_arm", "r_upper_arm"),
    "lower_arm": ("l_lower_arm", "r_lower_arm"),
    "upper_leg": ("l_upper_leg", "r_upper_leg"),
    "lower_leg": ("l_lower_leg", "r_lower_leg"),
}


def limb_endpoints(
    xyz: np.ndarray, keypoint_valid: np.ndarray, layout: str, up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The two ends of each of the 10 PCP limbs (`PCP_LIMBS`).

    Args:
      xyz: (..., K, 3) keypoints; keypoint_valid: (..., K).
      layout: their keypoint layout (needs nose, shoulders, elbows, wrists, hips, knees, ankles).
      up: (..., 3) or (3,) unit vertical, for the top of the head.
    Returns:
      ends (..., 10, 2, 3) and valid (..., 10): a limb is valid when every keypoint its ends are
      made of is.
    """
    lay = get_layout(layout)
    xyz = np.asarray(xyz, np.float64)
    kv = np.asarray(keypoint_valid, bool) & np.isfinite(xyz).all(-1)
    point = {
        n: (xyz[..., lay.index(n), :], kv[..., lay.index(n)])
        for n in ("nose", "l_shoulder", "r_shoulder", "l_hip", "r_hip")
    }

    def mid(a: str, b: str):
        return 0.5 * (point[a][0] + point[b][0]), point[a][1] & point[b][1]

    shoulders, ok_s = mid("l_shoulder", "r_shoulder")
    hips, ok_h = mid("l_hip", "r_hip")
    nose, ok_n = point["nose"]
    offset = nose - shoulders
    up = np.broadcast_to(np.asarray(up, np.float64), offset.shape)
    along = np.sum(offset * up, axis=-1, keepdims=True) * up
    derived = {
        "head_bottom": (shoulders + 0.5 * offset, ok_s & ok_n),
        "head_top": (shoulders + 0.75 * (offset - along) + 1.5 * along, ok_s & ok_n),
        "hip_mid": (hips, ok_h),
    }

    def get(name: str):
        if name in derived:
            return derived[name]
        k = lay.index(name)
        return xyz[..., k, :], kv[..., k]

    ends, valid = [], []
    for _, a, b in PCP_LIMBS:
        (pa, va), (pb, vb) = get(a), get(b)
        ends.append(np.stack([pa, pb], axis=-2))
        valid.append(va & vb)
    return np.stack(ends, axis=-3), np.stack(valid, axis=-1)


def pcp_scores(
    pred: Poses3D,
    gt: Poses3D,
    matches: list[tuple[np.ndarray, np.ndarray]],
    *,
    layout: str = "coco18",
    up: np.ndarray | None = None,
    person_ids: np.ndarray | None = None,
) -> dict:
    """Percentage of correct parts over the 10 limbs, counting every ground-truth person.

    A limb of a ground-truth person is correct when the person was matched to a prediction that
    has the limb and the mean of the errors of its two ends is at most half the true limb's length.
    Every limb of a ground-truth person nobody predicted is wrong (the Shelf/Campus protocol), so a
    method that drops people cannot score higher for it.

    Args:
      pred, gt: `Poses3D` (numpy) of the same F frames.
      matches: per frame (pred_index, gt_index), as `match_people` returns.
      up: (3,) world vertical for the head's top; None: each ground-truth person's own torso axis
        (hips' midpoint to shoulders' midpoint), used for its prediction too.
      person_ids: (F, G) int, who each ground-truth slot is (for the per-person scores); default
        the slot index.
    Returns:
      {"pcp": %, "pcp_by_limb": {class: %}, "pcp_by_person": {id: %}, "pcp_limbs": counted limbs}.
    """
    lay = get_layout(layout)
    gt_xyz = np.asarray(gt.xyz, np.float64)
    gt_kv = np.asarray(gt.keypoint_valid, bool)
    if up is None:
        hips = 0.5 * (gt_xyz[..., lay.index("l_hip"), :] + gt_xyz[..., lay.index("r_hip"), :])
        shoulders = 0.5 * (
            gt_xyz[..., lay.index("l_shoulder"), :] + gt_xyz[..., lay.index("r_shoulder"), :]
        )
        axis = shoulders - hips
        gt_up = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9)
    else:
        u = np.asarray(up, np.float64)
        gt_up = np.broadcast_to(u / np.linalg.norm(u), gt_xyz.shape[:-2] + (3,))
    gt_ends, gt_ok = limb_endpoints(gt_xyz, gt_kv, lay, gt_up)  # (F, G, L, 2, 3), (F, G, L)
    counted = gt_ok & np.asarray(gt.valid, bool)[..., None]
    hit = np.zeros_like(counted)
    for f, (pi, gi) in enumerate(matches):
        if len(pi) == 0:
            continue
        ends, ok = limb_endpoints(pred.xyz[f][pi], pred.keypoint_valid[f][pi], lay, gt_up[f][gi])
        truth = gt_ends[f][gi]
        length = np.linalg.norm(truth[..., 0, :] - truth[..., 1, :], axis=-1)
        err = np.linalg.norm(ends - truth, axis=-1).mean(-1)
        with np.errstate(invalid="ignore"):
            hit[f, gi] = ok & counted[f, gi] & (err <= 0.5 * length)
    pct = lambda h, n: 100.0 * float(h) / max(float(n), 1.0)  # noqa: E731
    names = [n for n, _, _ in PCP_LIMBS]
    by_limb = {
        c: pct(
            hit[..., [names.index(m) for m in members]].sum(),
            counted[..., [names.index(m) for m in members]].sum(),
        )
        for c, members in PCP_CLASSES.items()
    }
    ids = (
        np.broadcast_to(np.arange(counted.shape[1]), counted.shape[:2])
        if person_ids is None
        else person_ids
    )
    ids = np.asarray(ids)
    by_person = {}
    for pid in np.unique(ids[counted.any(-1)]):
        sel = ids == pid
        by_person[int(pid)] = pct(hit[sel].sum(), counted[sel].sum())
    return {
        "pcp": pct(hit.sum(), counted.sum()),
        "pcp_by_limb": by_limb,
        "pcp_by_person": by_person,
        "pcp_limbs": int(counted.sum()),
    }


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
    px = np.moveaxis(
        np.asarray(project_points(rig, np.asarray(xyz, np.float32))), 0, 1
    )  # (N, C, K, 2)
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
    return {
        "ari": float(ari),
        "homogeneity": float(homogeneity),
        "completeness": float(completeness),
        "v_measure": float(v),
    }


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


def matching_scores(
    true_identity: np.ndarray, pred_identity: np.ndarray, count: np.ndarray
) -> dict[str, float]:
    """Clustering scores of proposals against the truth: per-frame means (the paper's) and pooled.

    The paper's evaluation scores every frame's detections as one clustering and averages the
    scores over frames (``ari``, ``homogeneity``, ``completeness``, ``v_measure``); a frame where
    the method proposed nobody (every detection a singleton) counts like any other. Frames without
    a single detection have nothing to cluster and are left out of the means (``frames`` counts
    those scored). ``pooled_*`` scores all detections of all frames as one clustering (labels
    made unique per frame), which is more lenient: a frame's errors weigh by its size.

    Args:
      true_identity: (F, C, P) true person of each detection (-1: false positive, a singleton).
      pred_identity: (F, C, P) proposed person (-1: in no proposal, a singleton).
      count: (F, C) detections per view.
    Returns:
      {"ari", "homogeneity", "completeness", "v_measure", "pooled_ari", "pooled_homogeneity",
      "pooled_completeness", "pooled_v_measure", "detections", "frames"}.
    """
    count = np.asarray(count)
    true_identity, pred_identity = np.asarray(true_identity), np.asarray(pred_identity)
    if true_identity.shape != pred_identity.shape or true_identity.shape[:2] != count.shape:
        raise ValueError(
            f"identities {true_identity.shape} and {pred_identity.shape} do not cover "
            f"the same detections (count {count.shape})"
        )
    t = detection_clusters(true_identity, count)
    pooled = clustering_scores(t, detection_clusters(pred_identity, count))
    per = [
        clustering_scores(
            detection_clusters(true_identity[f : f + 1], count[f : f + 1]),
            detection_clusters(pred_identity[f : f + 1], count[f : f + 1]),
        )
        for f in np.flatnonzero(count.sum(-1) > 0)
    ]
    out = {k: float(np.mean([s[k] for s in per])) if per else 1.0 for k in CLUSTERING_SCORES}
    out.update({f"pooled_{k}": pooled[k] for k in CLUSTERING_SCORES})
    out["detections"] = float(len(t))
    out["frames"] = float(len(per))
    return out


CLUSTERING_SCORES = ("ari", "homogeneity", "completeness", "v_measure")


# --------------------------------------------------------------------------- tracks over time


def identity_metrics(
    pred: Poses3D,
    pred_track: np.ndarray,
    gt: Poses3D,
    *,
    gt_ids: np.ndarray | None = None,
    layout: str = "coco18",
    max_distance_m: float = 0.5,
    ignore: np.ndarray | None = None,
) -> dict:
    """How well predicted tracks keep people's identities (multi-object tracking metrics).

    Each frame, py-motmetrics matches predictions to ground truth by the CLEAR-MOT procedure
    (correspondences of the previous frame kept while under the distance, then a minimum-cost
    assignment of the rest); IDF1 comes from the one global track-to-identity assignment.

    Args:
      pred: predicted `Poses3D` (F, P, K) (slot-major: P is an order within each frame).
      pred_track: (F, P) int, each prediction's track id (-1: none; such predictions count as
        false positives when valid).
      gt: ground truth `Poses3D` (F, G, K).
      gt_ids: optional (F, G) int identities of the ground truth (default: the G index).
      layout: the evaluation keypoints' layout (the mean keypoint error is over them).
      max_distance_m: a pair farther apart (mean keypoint error, metres) never matches.
      ignore: optional (F, G) bool, ground-truth people that are "don't care" in a frame (as
        MOTChallenge's ignore regions; e.g. people only one camera sees, whom no multi-view
        method can place): each frame's tracked predictions are first assigned (minimum total
        error, under ``max_distance_m``) to the ground truth counted and ignored together; those
        that take an ignored person are left out, neither right nor false, and ignored people
        are never missed. Must be False where ``gt.valid`` is False.
    Returns:
      idf1, idp, idr (fractions), mota (fraction), id_switches, false_positives, misses,
      person_frames (ground-truth person-frames), switches_per_1000 (per 1,000 person-frames),
      num_tracks (distinct predicted tracks), num_ids (distinct ground-truth identities).
    """
    import motmetrics as mm

    pred = _finite_only(Poses3D(*(np.asarray(a) for a in pred)))
    gt = Poses3D(*(np.asarray(a) for a in gt))
    pred_track = np.asarray(pred_track)
    F = gt.valid.shape[0]
    if pred.valid.shape[0] != F or pred_track.shape != pred.valid.shape:
        raise ValueError(
            f"predictions cover {pred.valid.shape[0]} frames (tracks {pred_track.shape}), the "
            f"ground truth {F}: every frame must be scored"
        )
    if gt_ids is None:
        gt_ids = np.broadcast_to(np.arange(gt.valid.shape[1]), gt.valid.shape)
    ignore = np.zeros(gt.valid.shape, bool) if ignore is None else np.asarray(ignore, bool)
    if ignore.shape != gt.valid.shape or (ignore & ~gt.valid).any():
        raise ValueError("ignore must be (F, G) like the ground truth, and only where it is valid")
    kps = evaluation_keypoints(layout)
    acc = mm.MOTAccumulator(auto_id=True)
    untracked = 0
    for f in range(F):
        g_idx = np.flatnonzero(gt.valid[f])
        p_idx = np.flatnonzero(pred.valid[f])
        untracked += int((pred_track[f, p_idx] < 0).sum())
        p_idx = p_idx[pred_track[f, p_idx] >= 0]
        if ignore[f].any():
            g_idx, p_idx = _without_ignored(
                pred, gt, f, g_idx, p_idx, ignore[f], kps, max_distance_m
            )
        err = _pair_errors(
            pred.xyz[f][p_idx][:, kps],
            pred.keypoint_valid[f][p_idx][:, kps],
            gt.xyz[f][g_idx][:, kps],
            gt.keypoint_valid[f][g_idx][:, kps],
        ).T  # (G, P): motmetrics wants objects (ground truth) by hypotheses
        dist = np.where(err < max_distance_m, err, np.nan)
        acc.update([int(i) for i in gt_ids[f, g_idx]], [int(t) for t in pred_track[f, p_idx]], dist)
    names = ["idf1", "idp", "idr", "mota", "num_switches", "num_false_positives", "num_misses"]
    names += ["num_objects", "num_unique_objects"]
    row = mm.metrics.create().compute(acc, metrics=names, name="all").iloc[0]
    person_frames = int(row["num_objects"])
    switches = int(row["num_switches"])
    fp = int(row["num_false_positives"]) + untracked
    misses = int(row["num_misses"])
    tracks = np.unique(pred_track[pred.valid & (pred_track >= 0)])
    return {
        "idf1": _nan_as_zero(row["idf1"]),
        "idp": _nan_as_zero(row["idp"]),
        "idr": _nan_as_zero(row["idr"]),
        # MOTA again from its definition, so that untracked predictions count as false positives.
        "mota": 1.0 - (misses + fp + switches) / max(person_frames, 1),
        "id_switches": switches,
        "false_positives": fp,
        "misses": misses,
        "person_frames": person_frames,
        "switches_per_1000": 1000.0 * switches / max(person_frames, 1),
        "num_tracks": len(tracks),
        "num_ids": int(row["num_unique_objects"]),
    }


def _without_ignored(pred, gt, f, g_idx, p_idx, ignore_f, kps, max_distance_m):
    """Frame f's counted ground truth and the predictions not taken by an ignored person."""
    from scipy.optimize import linear_sum_assignment

    err = _pair_errors(
        pred.xyz[f][p_idx][:, kps],
        pred.keypoint_valid[f][p_idx][:, kps],
        gt.xyz[f][g_idx][:, kps],
        gt.keypoint_valid[f][g_idx][:, kps],
    )  # (P, G)
    near = err < max_distance_m
    rows, cols = linear_sum_assignment(np.where(near, err, 1e6))
    taken = near[rows, cols] & ignore_f[g_idx[cols]]
    return g_idx[~ignore_f[g_idx]], np.delete(p_idx, rows[taken])


def _nan_as_zero(x) -> float:
    x = float(x)
    return 0.0 if np.isnan(x) else x


def track_major(
    xyz: np.ndarray, keypoint_valid: np.ndarray, valid: np.ndarray, track: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slot-major people (a person's slot may change every frame) as one series per track.

    Args:
      xyz: (F, G, K, 3); keypoint_valid: (F, G, K); valid: (F, G); track: (F, G) int, -1 none.
    Returns:
      (ids (T,), xyz (T, F, K, 3), keypoint mask (T, F, K)): track ids[t]'s keypoints in each
      frame, the mask False where the track has no person or the keypoint was not produced.
    Raises:
      ValueError when a frame holds one track twice.
    """
    track = np.where(np.asarray(valid), np.asarray(track), -1)
    ids = np.unique(track[track >= 0])
    F, G, K = np.shape(keypoint_valid)
    out = np.zeros((len(ids), F, K, 3), np.float64)
    mask = np.zeros((len(ids), F, K), bool)
    f, g = np.nonzero(track >= 0)
    t = np.searchsorted(ids, track[f, g])
    if len(np.unique(t * F + f)) != len(t):
        raise ValueError("a track appears twice in one frame")
    out[t, f] = np.asarray(xyz)[f, g]
    mask[t, f] = np.asarray(keypoint_valid)[f, g]
    return ids, out, mask


def jitter(
    xyz: np.ndarray, keypoint_valid: np.ndarray, valid: np.ndarray, track: np.ndarray
) -> float:
    """Mean |second difference| of keypoints along tracks, in mm per frame².

    Over every (track, keypoint, frame f) where the keypoint exists at f-1, f and f+1 (a gap
    breaks the series). Ground truth's own jitter: pass its identities as ``track``.

    Args:
      xyz (F, G, K, 3) metres, keypoint_valid (F, G, K), valid (F, G), track (F, G) int (-1 none).
    Returns:
      the mean in millimetres per frame², NaN when no keypoint has three consecutive frames.
    """
    _, series, mask = track_major(xyz, keypoint_valid, valid, track)
    acc = series[:, 2:] - 2 * series[:, 1:-1] + series[:, :-2]  # (T, F-2, K, 3)
    ok = mask[:, 2:] & mask[:, 1:-1] & mask[:, :-2]
    if not ok.any():
        return float("nan")
    return float(np.linalg.norm(acc, axis=-1)[ok].mean() * 1000)
