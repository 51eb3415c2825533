"""The MVOR protocol (`evaluate`): per frame, predicted people are matched to true ones by the
Hungarian method on the mean distance over the joints both have (pairs farther than
``mvor.GATE_MM`` apart never matched); MPJPE (mm) over the matched people's annotated joints that
the prediction produced; PCK3D at 100 and 150 mm over EVERY annotated joint of every true person
(a missed person's joints and a joint not produced are wrong); missed people counted; upper-body
PCP on 6 limbs; per day and overall. The reader is `mvor`."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from experiments.mvor import GATE_MM, JOINTS, PCK_MM, PCP_RATIO, UPPER_BODY_LIMBS, MvorData
from mvpose_jax.skeletons import Poses3D


class TruthMatches(NamedTuple):
    """Each true person's match (`match_truth`); H true person slots, J joints, L limbs."""

    matched: np.ndarray  # (F, H) bool, a prediction was matched to the person
    joint_error: np.ndarray  # (F, H, J) metres; NaN: no match, joint not produced or not annotated
    limb_correct: np.ndarray  # (F, H, L) bool, upper-body PCP's verdict per limb


def match_truth(pred: Poses3D, gt: Poses3D, *, gate_mm: float = GATE_MM) -> TruthMatches:
    """Per frame, predicted people matched to true people (the protocol's matching).

    The Hungarian method on the mean distance over the joints both have (prediction produced,
    truth annotated); a pair sharing no joint or farther apart than ``gate_mm`` is never matched.

    Args:
      pred: xyz (F, P, J, 3) metres, valid (F, P), keypoint_valid (F, P, J) in MVOR's joints.
      gt: xyz (F, H, J, 3), valid (F, H), keypoint_valid (F, H, J) (annotated joints).
    Raises:
      ValueError: the predictions and the truth cover different numbers of frames.
    """
    from scipy.optimize import linear_sum_assignment

    F, H = np.shape(gt.valid)
    if np.shape(pred.valid)[0] != F:
        raise ValueError(f"predictions cover {np.shape(pred.valid)[0]} frames, the truth {F}")
    p_xyz = np.asarray(pred.xyz, np.float64)
    p_ok = np.asarray(pred.keypoint_valid, bool) & np.asarray(pred.valid, bool)[..., None]
    p_ok &= np.isfinite(p_xyz).all(-1)
    g_xyz = np.asarray(gt.xyz, np.float64)
    g_ok = np.asarray(gt.keypoint_valid, bool) & np.asarray(gt.valid, bool)[..., None]
    err = np.full((F, H, len(JOINTS)), np.nan)
    matched = np.zeros((F, H), bool)
    limb_correct = np.zeros((F, H, len(UPPER_BODY_LIMBS)), bool)
    for f in range(F):
        gi = np.flatnonzero(g_ok[f].any(-1))
        pi = np.flatnonzero(p_ok[f].any(-1))
        if len(gi) == 0 or len(pi) == 0:
            continue
        both = p_ok[f][pi][:, None] & g_ok[f][gi][None]  # (p, g, J)
        d = np.linalg.norm(p_xyz[f][pi][:, None] - g_xyz[f][gi][None], axis=-1)
        n = both.sum(-1)
        mean = np.where(both, d, 0).sum(-1) / np.maximum(n, 1)
        ok = (n > 0) & (mean * 1000 <= gate_mm)
        rows, cols = linear_sum_assignment(np.where(ok, mean, 1e9))
        for r, c in zip(rows, cols, strict=True):
            if not ok[r, c]:
                continue
            g, p = gi[c], pi[r]
            matched[f, g] = True
            err[f, g] = np.where(both[r, c], d[r, c], np.nan)
            limb_correct[f, g] = _limbs_correct(p_xyz[f, p], p_ok[f, p], g_xyz[f, g], g_ok[f, g])
    return TruthMatches(matched, err, limb_correct)


def evaluate(
    pred: Poses3D,
    data: MvorData,
    *,
    gate_mm: float = GATE_MM,
    unreachable: np.ndarray | None = None,
) -> dict:
    """The MVOR protocol on predictions in MVOR's joints (`poses_to_joints`).

    Args:
      pred: xyz (F, P, J, 3) metres, valid (F, P), keypoint_valid (F, P, J), the frames of
        ``data``.
      gate_mm: a predicted and a true person farther apart than this (mean over shared joints)
        are never matched.
      unreachable: optional (F, H) bool, true people the detections cannot place (e.g. seen in
        fewer than two views): a match of one of them counts in ``matched_unreachable`` (it was
        built from someone else's skeletons).
    Returns:
      {"overall": scores, "day<d>": scores}; scores: people, missed, mpjpe_mm,
      mpjpe_mm_without_hips, pck3d_<t> (%), pcp_upper (%), pcp_by_limb {limb: %}, produced (% of
      annotated joints of all true people the matched predictions produced), joints (annotated),
      joint_mm {joint: MPJPE}, joint_pck3d_150 {joint: %}, and with ``unreachable``
      matched_unreachable.
    Raises:
      ValueError: the predictions do not cover the data's frames.
    """
    gt = data.gt
    F = np.shape(gt.valid)[0]
    m = match_truth(pred, gt, gate_mm=gate_mm)
    g_ok = np.asarray(gt.keypoint_valid, bool) & np.asarray(gt.valid, bool)[..., None]
    counted_limbs = _limbs_counted(g_ok)
    has_joints = g_ok.any(-1)
    out = {}
    for name, sel in [("overall", np.ones(F, bool))] + [
        (f"day{int(d)}", data.day == d) for d in np.unique(data.day)
    ]:
        out[name] = _scores(
            err=m.joint_error[sel],
            annotated=g_ok[sel],
            matched=m.matched[sel],
            person=has_joints[sel],
            limb_hit=m.limb_correct[sel] & counted_limbs[sel],
            limb_counted=counted_limbs[sel],
        )
        if unreachable is not None:
            hit = m.matched[sel] & np.asarray(unreachable, bool)[sel]
            out[name]["matched_unreachable"] = int(hit.sum())
    return out


def versus(pred: Poses3D, reference: Poses3D, data: MvorData, *, gate_mm: float = GATE_MM) -> dict:
    """Two results on the true people both place (issue 37's MPJPE criterion: "no worse than
    geometry's on the people both place"): each matched by the protocol in both results.

    Returns (overall):
      people: true people both place; mpjpe_mm, reference_mpjpe_mm: each result's MPJPE over
      its own produced joints of those people; joints, reference_joints: how many; common_joints
      and mpjpe_common_mm, reference_mpjpe_common_mm: over the joints both produced.
    """
    a = match_truth(pred, data.gt, gate_mm=gate_mm)
    b = match_truth(reference, data.gt, gate_mm=gate_mm)
    both = a.matched & b.matched  # (F, H)
    ea, eb = a.joint_error[both], b.joint_error[both]  # (n, J) metres, NaN: not produced
    pa, pb = np.isfinite(ea), np.isfinite(eb)
    common = pa & pb
    return {
        "people": int(both.sum()),
        "mpjpe_mm": _mean_mm(ea[pa]),
        "reference_mpjpe_mm": _mean_mm(eb[pb]),
        "joints": int(pa.sum()),
        "reference_joints": int(pb.sum()),
        "common_joints": int(common.sum()),
        "mpjpe_common_mm": _mean_mm(ea[common]),
        "reference_mpjpe_common_mm": _mean_mm(eb[common]),
    }


def _scores(*, err, annotated, matched, person, limb_hit, limb_counted) -> dict:
    """Pooled scores of a set of frames: err (n, H, J) metres (NaN: none), annotated (n, H, J),
    matched and person (n, H), limb_hit and limb_counted (n, H, L)."""
    produced = annotated & np.isfinite(err)
    e = err[produced] * 1000
    pct = lambda a, b: 100.0 * float(a) / max(float(b), 1.0)  # noqa: E731
    scores = {
        "people": int(person.sum()),
        "missed": int((person & ~matched).sum()),
        "mpjpe_mm": float(e.mean()) if e.size else float("nan"),
        "mpjpe_mm_without_hips": _mean_mm(err[..., _NOT_HIPS][produced[..., _NOT_HIPS]]),
        **{f"pck3d_{int(t)}": pct((e <= t).sum(), annotated.sum()) for t in PCK_MM},
        "pcp_upper": pct(limb_hit.sum(), limb_counted.sum()),
        "pcp_by_limb": {
            limb: pct(limb_hit[..., i].sum(), limb_counted[..., i].sum())
            for i, (limb, _, _) in enumerate(UPPER_BODY_LIMBS)
        },
        "produced": pct(produced.sum(), annotated.sum()),
        "joints": int(annotated.sum()),
        "joint_mm": {},
        "joint_pck3d_150": {},
    }
    for j, joint in enumerate(JOINTS):
        ej = err[..., j][produced[..., j]] * 1000
        scores["joint_mm"][joint] = float(ej.mean()) if ej.size else float("nan")
        scores["joint_pck3d_150"][joint] = pct((ej <= 150).sum(), annotated[..., j].sum())
    return scores


def _mean_mm(err_m: np.ndarray) -> float:
    return float(err_m.mean() * 1000) if err_m.size else float("nan")


# MVOR's hips are not COCO's (130-140 mm higher, README): MPJPE without them is reported too.
_NOT_HIPS = np.array([j not in ("l_hip", "r_hip") for j in JOINTS])


def _limb_ends(xyz: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., J, 3), (..., J) -> the 6 limbs' ends (..., L, 2, 3) and whether they exist (..., L)."""
    hip = 0.5 * (xyz[..., JOINTS.index("l_hip"), :] + xyz[..., JOINTS.index("r_hip"), :])
    hip_ok = ok[..., JOINTS.index("l_hip")] & ok[..., JOINTS.index("r_hip")]

    def point(name: str):
        if name == "mid_hip":
            return hip, hip_ok
        return xyz[..., JOINTS.index(name), :], ok[..., JOINTS.index(name)]

    ends, have = [], []
    for _, a, b in UPPER_BODY_LIMBS:
        (pa, oa), (pb, ob) = point(a), point(b)
        ends.append(np.stack([pa, pb], axis=-2))
        have.append(oa & ob)
    return np.stack(ends, axis=-3), np.stack(have, axis=-1)


def _limbs_counted(gt_ok: np.ndarray) -> np.ndarray:
    """(..., J) annotated joints -> (..., L) limbs whose true ends are annotated."""
    return _limb_ends(np.zeros(gt_ok.shape + (3,)), gt_ok)[1]


def _limbs_correct(p_xyz, p_ok, g_xyz, g_ok) -> np.ndarray:
    """One matched pair: (L,) limbs whose ends' mean error is at most `PCP_RATIO` of the true
    limb's length (both ends produced, both annotated)."""
    p_ends, p_have = _limb_ends(p_xyz, p_ok)
    g_ends, g_have = _limb_ends(g_xyz, g_ok)
    length = np.linalg.norm(g_ends[:, 0] - g_ends[:, 1], axis=-1)
    mean_err = np.linalg.norm(p_ends - g_ends, axis=-1).mean(-1)
    return p_have & g_have & (mean_err <= PCP_RATIO * length)
