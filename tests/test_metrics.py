"""metrics.py, 3D part: MPJPE with the minimum-total-error assignment, AP/recall, PCP, completeness,
reprojection errors; on hand-made cases with known answers."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from mvpose_jax import cameras, metrics
from mvpose_jax.skeletons import Poses3D, get_layout
from tests.conftest import scene_points


def _poses(xyz, valid=None, kv=None):
    xyz = np.asarray(xyz, np.float32)
    F, P, K, _ = xyz.shape
    valid = np.ones((F, P), bool) if valid is None else np.asarray(valid)
    kv = np.ones((F, P, K), bool) if kv is None else np.asarray(kv)
    return Poses3D(xyz, valid, kv & valid[..., None])


def _gt(seed=0, F=2, G=3):
    rng = np.random.default_rng(seed)
    centres = np.array([[0, 0, 0], [2, 0, 0], [0, 0, 2]], float)[:G]
    return _poses(rng.normal(size=(F, G, 18, 3)) * 0.3 + centres[None, :, None])


def test_mpjpe_uses_the_minimum_total_error_assignment():
    gt = _gt()
    pred = gt.xyz[:, ::-1].copy()  # people listed in another order ...
    pred[..., 0] += 0.010  # ... and 10 mm off along x
    m = metrics.pose_metrics(_poses(pred), gt)
    assert m["mpjpe_mm"] == pytest.approx(10.0, abs=1e-3)
    assert m["completeness"] == pytest.approx(100.0)
    assert m["pcp"] == pytest.approx(100.0)
    # All correct from 25 mm up: AP = recall = 100 at every threshold.
    assert m["map"] == pytest.approx(100.0) and m["mean_recall"] == pytest.approx(100.0)


def test_ap_thresholds_and_recall():
    gt = _gt(F=1, G=2)
    pred = gt.xyz.copy()
    pred[0, 0] += np.array([0.030, 0, 0])  # person 0: 30 mm off: correct from 50 mm
    pred[0, 1] += np.array([0, 0.110, 0])  # person 1: 110 mm off: correct from 125 mm
    m = metrics.pose_metrics(_poses(pred), gt, confidence=np.array([[0.9, 0.5]]))
    assert m["ap_25"] == 0.0
    assert m["ap_50"] == pytest.approx(50.0) and m["ap_100"] == pytest.approx(50.0)
    assert m["ap_125"] == pytest.approx(100.0) and m["ap_150"] == pytest.approx(100.0)
    assert m["mean_recall"] == pytest.approx(100 * (0 + 0.5 + 0.5 + 0.5 + 1 + 1) / 6)
    assert m["mpjpe_mm"] == pytest.approx(70.0, abs=1e-3)


def test_false_positives_lower_precision_not_recall():
    gt = _gt(F=1, G=1)
    pred = np.concatenate([gt.xyz, gt.xyz + 5.0], axis=1)  # a correct pose and a phantom
    conf = np.array([[0.2, 0.9]])  # the phantom ranked first
    m = metrics.pose_metrics(_poses(pred), gt, confidence=conf)
    assert m["mean_recall"] == pytest.approx(100.0)
    assert m["map"] == pytest.approx(50.0)  # precision 1/2 at full recall


def test_incomplete_predictions_score_mpjpe_on_what_they_have_but_fail_ap():
    gt = _gt(F=1, G=1)
    kv = np.ones((1, 1, 18), bool)
    kv[0, 0, get_layout("coco18").index("l_wrist")] = False
    m = metrics.pose_metrics(_poses(gt.xyz, kv=kv), gt)
    assert m["mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)
    assert m["completeness"] == pytest.approx(100 * 13 / 14)
    assert m["mean_recall"] == 0.0
    m = metrics.pose_metrics(_poses(gt.xyz, kv=kv), gt, require_complete=False)
    assert m["mean_recall"] == pytest.approx(100.0)


def test_pcp_half_limb_rule():
    gt = _gt(F=1, G=1)
    lay = get_layout("coco18")
    a, b = lay.index("l_elbow"), lay.index("l_wrist")
    pred = gt.xyz.copy()
    length = np.linalg.norm(gt.xyz[0, 0, a] - gt.xyz[0, 0, b])
    pred[0, 0, b] += [0.9 * length, 0, 0]  # the wrist off by 0.9 limb: mean of ends 0.45 < 0.5
    m_ok = metrics.pose_metrics(_poses(pred), gt)
    pred[0, 0, b] += [0.2 * length, 0, 0]  # now 1.1 limb: 0.55 > 0.5, the forearm fails
    m_bad = metrics.pose_metrics(_poses(pred), gt)
    bones = [(x, y) for x, y in lay.bones if x in metrics.evaluation_keypoints("coco18")
             and y in metrics.evaluation_keypoints("coco18")]  # fmt: skip
    assert m_ok["pcp"] == pytest.approx(100.0)
    assert m_bad["pcp"] == pytest.approx(100.0 * (len(bones) - 1) / len(bones))


def test_missing_people_lower_recall():
    gt = _gt(F=2, G=3)
    valid = np.array([[True, True, False], [True, True, True]])
    m = metrics.pose_metrics(_poses(gt.xyz, valid=valid), gt)
    assert m["mean_recall"] == pytest.approx(100 * 5 / 6)
    assert m["mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)


def test_reprojection_errors_per_camera(ring_rig):
    X = scene_points(ring_rig, 0, (5, 18))
    xy = np.array(np.moveaxis(np.asarray(cameras.project_points(ring_rig, jnp.asarray(X))), 0, 1))
    xy[:, 1] += [3.0, 4.0]  # camera 1 is 5 px off
    score = np.ones(xy.shape[:-1], np.float32)
    score[:, 2] = 0.0  # camera 2 saw nothing
    err = metrics.reprojection_errors(ring_rig, X, np.ones((5, 18), bool), xy, score)
    assert err["cam0"]["mean"] == pytest.approx(0.0, abs=1e-3)
    assert err["cam1"]["mean"] == pytest.approx(5.0, abs=1e-3)
    assert err["cam1"]["median"] == pytest.approx(5.0, abs=1e-3)
    assert err["cam2"]["count"] == 0 and np.isnan(err["cam2"]["mean"])


def test_choose_proposal_threshold_takes_the_band_that_separates_true_from_false_pairs():
    # Camera 0 sees people A and B, camera 1 sees A and a false detection X.
    identity = np.array([[[0, 1], [0, -1]]])
    count = np.array([[2, 2]])
    rows = np.array([[0, 0, 0, 1, 0],   # A-A, true
                     [0, 0, 1, 1, 1],   # B-X, false
                     [0, 0, 0, 1, 1],   # A-X, false
                     [0, 0, 1, 1, 0]])  # B-A, false  # fmt: skip
    scores = np.array([0.3, 0.1, 0.05, 0.04])
    best, ari = metrics.choose_proposal_threshold(rows, scores, identity, count)
    # A pair is taken when its score is above the threshold: from 0.1 (B-X refused) to below 0.3
    # (A-A taken) every threshold is perfect, and 0.2 is the nearest to 0.5.
    assert best == 0.2
    assert ari[0.1] == ari[0.15] == ari[0.2] == pytest.approx(1.0)
    assert ari[0.05] < 1.0 and ari[0.3] < 1.0 and ari[0.5] < 1.0
