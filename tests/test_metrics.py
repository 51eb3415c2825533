"""metrics.py, 3D part: MPJPE with the minimum-total-error assignment, AP/recall, PCP, completeness,
reprojection errors; on hand-made cases with known answers."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from mvpose_jax import cameras, metrics
from mvpose_jax.metrics import clustering_scores, detection_clusters, matching_scores
from mvpose_jax.skeletons import Poses3D, get_layout
from tests.helpers import scene_points


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


def test_mpjpe_on_reference_keypoints_is_like_with_like_across_groupings():
    gt = _gt(F=1)
    kps = metrics.evaluation_keypoints("coco18")
    # The method: every person, 10 mm off for person 0 and 30 mm off for person 1 and 2.
    pred = gt.xyz.copy()
    pred[0, 0, :, 0] += 0.010
    pred[0, 1:, :, 0] += 0.030
    # The reference (another grouping): person 2 and person 0 in that order, person 0 with only
    # half of the evaluation keypoints, person 1 missed.
    ref_kv = np.ones((1, 2, 18), bool)
    ref_kv[0, 1, kps[::2]] = False
    ref = _poses(gt.xyz[:, [2, 0]], kv=ref_kv)
    got = metrics.mpjpe_on_reference_keypoints(_poses(pred), ref, gt)
    n0, n2 = len(kps) - len(kps[::2]), len(kps)
    assert got == pytest.approx((10.0 * n0 + 30.0 * n2) / (n0 + n2), abs=1e-3)
    # On all of its own keypoints the method's MPJPE differs: the reference's set is the point.
    assert metrics.pose_metrics(_poses(pred), gt)["mpjpe_mm"] == pytest.approx(70 / 3, abs=1e-3)
    # A keypoint the method did not produce (NaN) counts for nothing; nothing left: NaN.
    pred[0, 2] = np.nan
    got = metrics.mpjpe_on_reference_keypoints(_poses(pred), ref, gt)
    assert got == pytest.approx(10.0, abs=1e-3)
    nobody = _poses(gt.xyz[:, :1], valid=np.zeros((1, 1), bool))
    assert np.isnan(metrics.mpjpe_on_reference_keypoints(_poses(pred), nobody, gt))


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


def _standing(x=0.0, y=0.0):
    """A hand-placed coco18 person standing at (x, y) with z up: (18, 3) metres."""
    lay = get_layout("coco18")
    at = {
        "nose": (0, 0.05, 1.60),
        "l_eye": (0.03, 0.06, 1.63),
        "r_eye": (-0.03, 0.06, 1.63),
        "l_ear": (0.07, 0, 1.61),
        "r_ear": (-0.07, 0, 1.61),
        "l_shoulder": (0.2, 0, 1.45),
        "r_shoulder": (-0.2, 0, 1.45),
        "l_elbow": (0.25, 0, 1.15),
        "r_elbow": (-0.25, 0, 1.15),
        "l_wrist": (0.27, 0, 0.90),
        "r_wrist": (-0.27, 0, 0.90),
        "l_hip": (0.12, 0, 0.95),
        "r_hip": (-0.12, 0, 0.95),
        "l_knee": (0.13, 0, 0.52),
        "r_knee": (-0.13, 0, 0.52),
        "l_ankle": (0.13, 0, 0.10),
        "r_ankle": (-0.13, 0, 0.10),
        "neck": (0, 0, 1.45),
    }
    return np.array([at[k] for k in lay.keypoints]) + [x, y, 0.0]


def test_pcp_is_over_the_10_limbs_with_the_half_limb_rule():
    gt = _poses(_standing()[None, None])
    lay = get_layout("coco18")
    a, b = lay.index("l_elbow"), lay.index("l_wrist")
    length = np.linalg.norm(gt.xyz[0, 0, a] - gt.xyz[0, 0, b])
    pred = gt.xyz.copy()
    pred[0, 0, b] += [0.9 * length, 0, 0]  # the wrist off by 0.9 limb: mean of ends 0.45 < 0.5
    m_ok = metrics.pose_metrics(_poses(pred), gt, up=[0, 0, 1])
    pred[0, 0, b] += [0.2 * length, 0, 0]  # now 1.1 limb: 0.55 > 0.5, the forearm fails
    m_bad = metrics.pose_metrics(_poses(pred), gt, up=[0, 0, 1])
    assert m_ok["pcp"] == pytest.approx(100.0) and m_ok["pcp_limbs"] == 10
    assert m_bad["pcp"] == pytest.approx(90.0)
    assert m_bad["pcp_by_limb"]["lower_arm"] == pytest.approx(50.0)
    assert all(
        m_bad["pcp_by_limb"][c] == 100.0
        for c in ("head", "torso", "upper_arm", "upper_leg", "lower_leg")
    )


@pytest.mark.parametrize("up", [[0, 0, 1], None])
def test_pcp_head_and_torso_ends_in_closed_form(up):
    # Shoulders' midpoint (0, 0, 1.45), nose (0, 0.05, 1.60): offset v = (0, 0.05, 0.15).
    # Head bottom = mid + v/2 = (0, 0.025, 1.525); head top = mid + 0.75 v_across + 1.5 v_up =
    # (0, 0.0375, 1.675); head length = |(0, 0.0125, 0.15)| = 0.1505.
    person = _standing()
    ends, ok = metrics.limb_endpoints(person, np.ones(18, bool), "coco18", np.array([0.0, 0, 1]))
    names = [n for n, _, _ in metrics.PCP_LIMBS]
    np.testing.assert_allclose(
        ends[names.index("head")], [[0, 0.025, 1.525], [0, 0.0375, 1.675]], atol=1e-12
    )
    np.testing.assert_allclose(
        ends[names.index("torso")], [[0, 0, 0.95], [0, 0.025, 1.525]], atol=1e-12
    )
    assert ok.all()
    # Moving the nose by dx across moves the head's ends by dx/2 and 0.75 dx: mean error
    # 0.625 dx, correct while 0.625 dx <= 0.1505 / 2, i.e. dx <= 0.1204.
    gt = _poses(person[None, None])
    nose = get_layout("coco18").index("nose")
    for dx, correct in ((0.118, True), (0.123, False)):
        pred = gt.xyz.copy()
        pred[0, 0, nose, 0] += dx
        m = metrics.pose_metrics(_poses(pred), gt, up=up)
        assert m["pcp_by_limb"]["head"] == (100.0 if correct else 0.0), dx
        assert m["pcp_by_limb"]["torso"] == 100.0


def test_pcp_counts_every_limb_of_a_missed_person_as_wrong():
    # Three people, one predicted perfectly: PCP 33.3, not 100 (the Shelf/Campus protocol).
    gt = _poses(np.stack([_standing(0, 0), _standing(2, 0), _standing(0, 2)])[None])
    pred = _poses(gt.xyz[:, 1:2])
    m = metrics.pose_metrics(pred, gt, up=[0, 0, 1])
    assert m["pcp"] == pytest.approx(100 / 3)
    assert m["pcp_limbs"] == 30
    assert m["pcp_by_person"] == {0: 0.0, 1: 100.0, 2: 0.0}
    assert all(v == pytest.approx(100 / 3) for v in m["pcp_by_limb"].values())
    assert m["mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)  # MPJPE is over the matched person
    assert m["completeness"] == pytest.approx(100 / 3)
    assert m["mean_recall"] == pytest.approx(100 / 3)


def test_pcp_per_person_follows_the_given_identities():
    gt = _poses(np.stack([_standing(0, 0), _standing(2, 0)])[None].repeat(2, axis=0))
    pred = gt.xyz.copy()
    pred[1, 0] += 1.0  # frame 1: slot 0's prediction is a metre off (every limb wrong)
    ids = np.array([[7, 8], [8, 7]])  # slot 0 is person 7 in frame 0, person 8 in frame 1
    m = metrics.pose_metrics(_poses(pred), gt, up=[0, 0, 1], person_ids=ids)
    assert m["pcp_by_person"] == {7: 100.0, 8: 50.0}
    assert m["pcp"] == pytest.approx(75.0)


def test_every_frame_counts_a_frame_with_nobody_predicted_is_a_miss():
    gt = _poses(np.stack([_standing(0, 0), _standing(2, 0)])[None].repeat(2, axis=0))
    valid = np.array([[True, True], [False, False]])  # the method found nobody in frame 1
    m = metrics.pose_metrics(_poses(gt.xyz, valid=valid), gt, up=[0, 0, 1])
    assert m["pcp"] == pytest.approx(50.0)
    assert m["mean_recall"] == pytest.approx(50.0)
    assert m["completeness"] == pytest.approx(50.0)
    with pytest.raises(
        ValueError, match="every frame"
    ):  # a dropped frame is never skipped silently
        metrics.pose_metrics(_poses(gt.xyz[:1]), gt)


def test_non_finite_keypoints_count_as_not_produced():
    gt = _poses(_standing()[None, None])
    pred = gt.xyz.copy()
    wrist = get_layout("coco18").index("l_wrist")
    pred[0, 0, wrist] = np.nan
    m = metrics.pose_metrics(_poses(pred), gt, up=[0, 0, 1])
    assert np.isfinite(m["mpjpe_mm"]) and m["mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)
    assert m["pcp"] == pytest.approx(90.0)  # the forearm without its wrist is wrong
    assert m["completeness"] == pytest.approx(100 * 13 / 14)
    assert m["mean_recall"] == 0.0  # incomplete poses fail AP and recall


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


def test_clustering_scores_equal_sklearn():
    from sklearn import metrics as sk

    rng = np.random.default_rng(4)
    for i in range(200):
        n = int(rng.integers(0, 40))
        a = rng.integers(0, int(rng.integers(1, 8)), n)
        b = a.copy() if i % 4 == 0 else rng.integers(0, int(rng.integers(1, 8)), n)
        b[rng.random(n) < 0.1] = 50
        ours = clustering_scores(a, b)
        h, c, v = sk.homogeneity_completeness_v_measure(a, b)
        assert ours["ari"] == pytest.approx(sk.adjusted_rand_score(a, b), abs=1e-12)
        assert (ours["homogeneity"], ours["completeness"], ours["v_measure"]) == pytest.approx(
            (h, c, v), abs=1e-12
        )


def test_detection_clusters_make_singletons_and_frame_unique_labels():
    identity = np.array([[[0, -1], [0, 1]], [[0, -1], [-1, -1]]])  # (F=2, C=2, P=2)
    count = np.array([[2, 2], [1, 1]])
    labels = detection_clusters(identity, count)
    assert len(labels) == 6
    assert labels[0] == labels[2] and len(set(labels.tolist())) == 5  # frame 1's person 0 differs
    perfect = matching_scores(identity, identity, count)
    assert perfect["ari"] == 1.0 and perfect["v_measure"] == 1.0


def test_matching_scores_average_per_frame_and_pool_beside():
    from sklearn import metrics as sk

    # Frame 0: two people over 3 views, perfectly grouped (6 detections). Frame 1: one person in
    # two views, split in two (2 detections). Frame 2: nobody proposed at all (3 detections of 2
    # people, each left a singleton). Frame 3: no detection (nothing to score, left out).
    true = np.full((4, 3, 2), -1)
    pred = np.full((4, 3, 2), -1)
    true[0] = [[0, 1], [1, 0], [0, 1]]
    pred[0] = [[5, 6], [6, 5], [5, 6]]
    true[1, :2, 0] = 0
    pred[1, :2, 0] = [0, 1]
    true[2, :, 0] = [0, 0, 1]
    count = np.array([[2, 2, 2], [1, 1, 0], [1, 1, 1], [0, 0, 0]])
    s = matching_scores(true, pred, count)

    def frame_labels(a, f):
        ok = np.arange(2)[None] < count[f][:, None]
        x = a[f][ok]
        return np.where(x >= 0, x, 100 + np.arange(len(x)))  # -1: a singleton each

    frames = [0, 1, 2]
    want = np.mean(
        [sk.adjusted_rand_score(frame_labels(true, f), frame_labels(pred, f)) for f in frames]
    )
    want_v = np.mean(
        [sk.v_measure_score(frame_labels(true, f), frame_labels(pred, f)) for f in frames]
    )
    assert s["ari"] == pytest.approx(want, abs=1e-12) and s["v_measure"] == pytest.approx(
        want_v, abs=1e-12
    )
    assert s["frames"] == 3 and s["detections"] == 11
    pooled_t = np.concatenate([frame_labels(true, f) + 1000 * f for f in frames])
    pooled_p = np.concatenate([frame_labels(pred, f) + 1000 * f for f in frames])
    assert s["pooled_ari"] == pytest.approx(sk.adjusted_rand_score(pooled_t, pooled_p), abs=1e-12)
    # Pooling is more lenient: the big perfect frame outweighs the two small failed ones.
    assert s["pooled_ari"] > s["ari"] + 0.2
    # Frame 2, where nobody was proposed, is scored (ARI 0), not skipped.
    without = matching_scores(true[:2], pred[:2], count[:2])
    assert s["ari"] < without["ari"]


# --------------------------------------------------------------------------- tracks over time


def _walkers(F=10, G=2, K=18, seed=0):
    """G people walking in parallel lines 1 m apart, (F, G, K, 3) metres."""
    rng = np.random.default_rng(seed)
    body = rng.normal(scale=0.2, size=(G, K, 3))
    t = np.arange(F)[:, None, None, None] * np.array([0.03, 0.0, 0.0])
    offset = np.arange(G)[None, :, None, None] * np.array([0.0, 1.0, 0.0])
    xyz = body[None] + t + offset
    return Poses3D(xyz, np.ones((F, G), bool), np.ones((F, G, K), bool))


def test_identity_metrics_perfect_tracks_with_slots_shuffled_every_frame():
    gt = _walkers()
    rng = np.random.default_rng(1)
    order = np.stack([rng.permutation(2) for _ in range(10)])  # slot order changes per frame
    f = np.arange(10)[:, None]
    pred = Poses3D(gt.xyz[f, order], gt.valid[f, order], gt.keypoint_valid[f, order])
    m = metrics.identity_metrics(pred, order + 7, gt)  # track ids need not be 0..G-1
    assert m["idf1"] == 1.0 and m["id_switches"] == 0 and m["mota"] == 1.0
    assert m["person_frames"] == 20 and m["num_tracks"] == 2 and m["num_ids"] == 2


def test_identity_metrics_one_swap_by_the_definitions():
    # Tracks swap people at frame 5: the best global track-to-person assignment keeps 5 of each
    # person's 10 frames, so IDF1 = 2 IDTP / (GT + predictions) = 2 * 10 / 40; CLEAR-MOT counts
    # one switch per person at the swap, MOTA = 1 - 2 / 20.
    gt = _walkers()
    track = np.tile([0, 1], (10, 1))
    track[5:] = [1, 0]
    m = metrics.identity_metrics(gt, track, gt)
    assert m["idf1"] == pytest.approx(0.5)
    assert m["id_switches"] == 2 and m["mota"] == pytest.approx(0.9)
    assert m["switches_per_1000"] == pytest.approx(100.0)


def test_identity_metrics_far_and_untracked_predictions_are_errors():
    gt = _walkers(F=4)
    far = Poses3D(gt.xyz + np.array([0.0, 0.0, 2.0]), gt.valid, gt.keypoint_valid)
    m = metrics.identity_metrics(far, np.tile([0, 1], (4, 1)), gt, max_distance_m=0.5)
    assert m["misses"] == 8 and m["false_positives"] == 8 and m["idf1"] == 0.0
    untracked = np.tile([0, -1], (4, 1))  # the second person is never given a track
    m = metrics.identity_metrics(gt, untracked, gt)
    assert m["misses"] == 4 and m["false_positives"] == 4
    assert m["mota"] == pytest.approx(1 - 8 / 8)
    with pytest.raises(ValueError, match="frames"):
        metrics.identity_metrics(gt, np.zeros((3, 2), int), gt)


def test_identity_metrics_ignored_people_are_neither_missed_nor_false():
    gt = _walkers(F=10, G=3)
    track = np.tile([0, 1, 2], (10, 1))
    ignore = np.zeros((10, 3), bool)
    ignore[:5, 2] = True  # the third person is "don't care" in frames 0-4
    m = metrics.identity_metrics(gt, track, gt, ignore=ignore)
    # Frames 0-4 of the third person's track are left out: IDF1 = 2 * 25 / (25 + 25).
    assert m["idf1"] == 1.0 and m["person_frames"] == 25 and m["false_positives"] == 0
    # Not predicted while ignored: not missed either.
    valid = gt.valid.copy()
    valid[:5, 2] = False
    m = metrics.identity_metrics(gt._replace(valid=valid), track, gt, ignore=ignore)
    assert m["idf1"] == 1.0 and m["misses"] == 0
    # A prediction near no one stays false even beside an ignored person, and the counted
    # people's misses stay misses: frames 0-4 of person 0 predicted 2 m off.
    far = gt.xyz.copy()
    far[:5, 0] += np.array([0.0, 0.0, 2.0])
    m = metrics.identity_metrics(gt._replace(xyz=far), track, gt, ignore=ignore)
    assert m["false_positives"] == 5 and m["misses"] == 5
    assert m["idf1"] == pytest.approx(2 * 20 / (25 + 25))
    with pytest.raises(ValueError, match="ignore"):
        metrics.identity_metrics(gt, track, gt, ignore=np.zeros((10, 2), bool))


def test_jitter_closed_form_and_gaps():
    # x = a f^2 has second difference 2a everywhere; a gap breaks the series.
    F, K, a = 12, 18, 0.004
    x = a * np.arange(F, dtype=float) ** 2
    xyz = np.zeros((F, 1, K, 3))
    xyz[..., 0] = x[:, None, None]
    kv = np.ones((F, 1, K), bool)
    valid = np.ones((F, 1), bool)
    assert metrics.jitter(xyz, kv, valid, np.zeros((F, 1), int)) == pytest.approx(2 * a * 1000)
    # The same person in slot 1 on odd frames: tracks follow the person, not the slot.
    swapped = np.zeros((F, 2, K, 3))
    track = np.full((F, 2), -1)
    for f in range(F):
        swapped[f, f % 2] = xyz[f, 0]
        track[f, f % 2] = 3
    both = np.ones((F, 2), bool)
    got = metrics.jitter(swapped, np.ones((F, 2, K), bool), both & (track >= 0), track)
    assert got == pytest.approx(2 * a * 1000)
    # Frame 6 missing: the triples that straddle it are skipped, and a jump after it is unseen.
    xyz2 = xyz.copy()
    xyz2[7:] += 1.0
    kv2 = kv.copy()
    kv2[6] = False
    assert metrics.jitter(xyz2, kv2, valid, np.zeros((F, 1), int)) == pytest.approx(2 * a * 1000)
    assert np.isnan(metrics.jitter(xyz[:2], kv[:2], valid[:2], np.zeros((2, 1), int)))


def test_jitter_of_two_tracks_is_the_mean_second_difference():
    F = 30
    t = np.arange(F, dtype=float)
    xyz = np.zeros((F, 2, 1, 3))
    xyz[:, 0, 0, 0] = 0.001 * t**2  # second difference 2 mm per frame²
    xyz[:, 1, 0, 1] = 0.002 * t**2 + 5.0  # 4 mm per frame²
    kv = np.ones((F, 2, 1), bool)
    both = np.ones((F, 2), bool)
    assert metrics.jitter(xyz, kv, both, np.tile([0, 1], (F, 1))) == pytest.approx(3.0)
    # A track switch between the two people would be a huge jump; ids keep them apart.
    swapped = np.tile([0, 1], (F, 1))
    xyz_s = xyz.copy()
    xyz_s[::2] = xyz_s[::2, ::-1]
    swapped[::2] = swapped[::2, ::-1]
    assert metrics.jitter(xyz_s, kv, both, swapped) == pytest.approx(3.0)
