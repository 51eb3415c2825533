"""The label-free score (`mvpose_jax.label_free`) against closed-form cases and OpenCV."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.errors import InputError
from mvpose_jax.inference import run_pipeline
from mvpose_jax.label_free import (
    BLIND_SPOTS,
    LabelFreeConfig,
    bone_spread,
    label_free_score,
    people_count,
    reference_reprojection,
    track_fragments,
    track_jitter,
    write_label_free_report,
)
from mvpose_jax.lifting import members_from_identity
from mvpose_jax.skeletons import Detections, Poses3D, get_layout
from mvpose_jax.synthetic import detection_variants, generate_recording

LAYOUT = "coco18"


@pytest.fixture(scope="module")
def rig():
    return load_rig("panoptic5")


def _scene(rig, num_people: int, seed: int):
    rec = generate_recording(rig, num_people=num_people, num_frames=8, seed=seed)
    return rec, detection_variants(rec)["projected"]


@pytest.fixture(scope="module")
def two_people(rig):
    return _scene(rig, 2, seed=3)


@pytest.fixture(scope="module")
def one_person(rig):
    return _scene(rig, 1, seed=4)


def _truth_result(rec, xyz=None, keypoint_valid=None) -> PoseResults:
    """The ground truth as a result, grouped by the true identities."""
    gt = rec.ground_truth
    members = members_from_identity(np.asarray(rec.identity), gt.valid.shape[1])
    poses = Poses3D(
        np.asarray(gt.xyz if xyz is None else xyz, np.float32),
        np.asarray(gt.valid),
        np.asarray(gt.keypoint_valid if keypoint_valid is None else keypoint_valid),
    )
    return PoseResults(
        poses, np.ones(gt.valid.shape, np.float32), members, rec.identity, rec.cameras, LAYOUT
    )


def test_the_truth_on_noise_free_detections_scores_zero_px_and_every_keypoint(rig, two_people):
    rec, exact = two_people
    report = label_free_score(_truth_result(exact), rig, exact.detections, layout=LAYOUT)
    r = report.result.overall
    # Every keypoint a second camera can check is produced; those one camera alone shows are
    # unverifiable (`test_blind_keypoints_...` counts them independently).
    assert r.visible > 100 and r.produced + r.blind == r.visible and 0 < r.blind < 0.05 * r.visible
    assert r.median_px < 1e-2
    assert r.share_within_px == {"10": r.coverage, "20": r.coverage}
    # Leave-one-out triangulation of exact detections is exact too, where 2+ other views see.
    loo = report.leave_one_out.overall
    assert loo.median_px < 1e-2 and loo.produced + loo.blind == loo.visible
    # The reference spread of exact detections around the truth is nil.
    floor = reference_reprojection(
        rec.ground_truth.xyz,
        rec.ground_truth.keypoint_valid,
        rig,
        exact.detections,
        rec.identity,
        cameras=rec.cameras,
    )
    assert floor.overall.median_px < 1e-2 and floor.overall.share_within_px["20"] == 1.0
    assert report.blind_spots == BLIND_SPOTS


def test_blind_keypoints_are_those_fewer_than_two_other_views_show(rig, two_people):
    rec, exact = two_people
    report = label_free_score(_truth_result(exact), rig, exact.detections, layout=LAYOUT)
    members = members_from_identity(np.asarray(rec.identity), rec.ground_truth.valid.shape[1])
    score = np.asarray(exact.detections.score)
    F, G, C = members.shape
    shows = np.zeros((F, G, C, score.shape[-1]), bool)
    for f, g, c in zip(*np.nonzero(members >= 0), strict=True):
        shows[f, g, c] = score[f, c, members[f, g, c]] > 0
    others = shows.sum(2, keepdims=True) - shows
    for i, cam in enumerate(rec.cameras):
        expected = int((shows[:, :, i] & (others[:, :, i] < 2)).sum())
        assert report.leave_one_out.by_camera[cam].blind == expected
        # The result's own projection: unverifiable where no other camera shows the keypoint.
        alone = int((shows[:, :, i] & (others[:, :, i] == 0)).sum())
        assert report.result.by_camera[cam].blind == alone


def test_a_one_view_guess_scores_as_a_miss_not_as_a_hit(rig, two_people):
    """A keypoint one camera alone shows reprojects onto it wherever the result puts it on that
    camera's ray: producing it must score the same as leaving it out."""
    rec, exact = two_people
    truth = _truth_result(exact)
    kv = np.asarray(truth.poses.keypoint_valid).copy()
    members = np.asarray(truth.members)
    score = np.asarray(exact.detections.score)
    F, G, C = members.shape
    shows = np.zeros((F, G, C, score.shape[-1]), bool)
    for f, g, c in zip(*np.nonzero(members >= 0), strict=True):
        shows[f, g, c] = score[f, c, members[f, g, c]] > 0
    alone = shows.sum(2) == 1  # (F, G, K)
    assert alone.any()
    without = _truth_result(exact, keypoint_valid=kv & ~alone)
    a = label_free_score(truth, rig, exact.detections, layout=LAYOUT)
    b = label_free_score(without, rig, exact.detections, layout=LAYOUT)
    assert a.share_of_all_within_px == b.share_of_all_within_px
    assert a.result.overall == b.result.overall


def test_a_shifted_person_reprojects_as_opencv_projects_it(rig, one_person):
    rec, exact = one_person
    shift = np.array([0.2, 0.0, 0.0])
    xyz = np.asarray(rec.ground_truth.xyz, np.float64) + shift
    report = label_free_score(_truth_result(exact, xyz=xyz), rig, exact.detections, layout=LAYOUT)
    score = np.asarray(exact.detections.score)
    ident = np.asarray(exact.identity)
    for i, cam in enumerate(rec.cameras):
        c = rig.names.index(cam)
        rvec, _ = cv2.Rodrigues(np.asarray(rig.R[c], np.float64))
        errors = []
        for f in range(xyz.shape[0]):
            for p in np.nonzero(ident[f, i] == 0)[0]:
                seen = score[f, i, p] > 0
                shifted, _ = cv2.projectPoints(
                    xyz[f, 0][seen],
                    rvec,
                    np.asarray(rig.t[c], np.float64),
                    np.asarray(rig.K[c], np.float64),
                    np.asarray(rig.dist[c], np.float64),
                )
                true, _ = cv2.projectPoints(
                    np.asarray(rec.ground_truth.xyz[f, 0], np.float64)[seen],
                    rvec,
                    np.asarray(rig.t[c], np.float64),
                    np.asarray(rig.K[c], np.float64),
                    np.asarray(rig.dist[c], np.float64),
                )
                errors.append(np.linalg.norm(shifted[:, 0] - true[:, 0], axis=-1))
        expected = np.concatenate(errors)
        got = report.result.by_camera[cam]
        assert got.visible == expected.size
        assert got.median_px == pytest.approx(np.median(expected), rel=1e-3, abs=1e-2)
        assert got.share_within_px["20"] == pytest.approx(np.mean(expected <= 20), abs=1e-9)
        assert got.median_px > 5  # 0.2 m is many pixels at these distances


def test_a_keypoint_not_produced_is_a_miss_and_abstaining_never_scores_better(rig, two_people):
    rec, _ = two_people
    det = rec.detections  # with the simulated detector's noise
    res = run_pipeline(rig, det, method="robust")
    full = PoseResults(res.poses, res.confidence, res.members, res.identity, res.cameras, LAYOUT)
    wrists = [get_layout(LAYOUT).index(k) for k in ("l_wrist", "r_wrist")]
    kv = np.asarray(res.poses.keypoint_valid).copy()
    kv[..., wrists] = False
    dropped = dataclasses.replace(full, poses=res.poses._replace(keypoint_valid=kv))
    a = label_free_score(full, rig, det, layout=LAYOUT)
    b = label_free_score(dropped, rig, det, layout=LAYOUT)
    assert b.result.overall.visible == a.result.overall.visible  # misses stay in the denominator
    lost = sum(a.result.by_keypoint[k].produced for k in ("l_wrist", "r_wrist"))
    assert lost > 0 and b.result.overall.produced == a.result.overall.produced - lost
    assert b.result.overall.coverage < a.result.overall.coverage
    for r in ("10", "20"):
        assert b.result.overall.share_within_px[r] < a.result.overall.share_within_px[r]
        assert b.share_of_all_within_px[r] < a.share_of_all_within_px[r]
        assert b.result.by_keypoint["l_wrist"].share_within_px[r] == 0.0
    # A random fifth of the keypoints left out: never better, whatever the median does.
    rng = np.random.default_rng(0)
    kv2 = np.asarray(res.poses.keypoint_valid) & (rng.random(kv.shape) > 0.2)
    c = label_free_score(
        dataclasses.replace(full, poses=res.poses._replace(keypoint_valid=kv2)),
        rig,
        det,
        layout=LAYOUT,
    )
    assert c.result.overall.share_within_px["20"] < a.result.overall.share_within_px["20"]


def test_bone_spread_is_zero_for_a_rigid_skeleton_and_matches_a_hand_computation():
    F, K = 6, 3
    rng = np.random.default_rng(1)
    base = rng.normal(size=(K, 3))
    # A rigid skeleton moving through space: every bone keeps its length.
    xyz = base[None, None] + np.arange(F)[:, None, None, None] * np.array([0.1, 0.0, 0.05])
    ones = np.ones((F, 1, K), bool)
    track = np.zeros((F, 1), int)
    rigid = bone_spread(xyz, ones, ones[..., 0], track, [(0, 1), (1, 2)])
    assert rigid.median_cv == pytest.approx(0.0, abs=1e-12)
    # Bone (0, 1) of lengths 1, 2, 3 (then absent) and bone (1, 2) of lengths 2, 2, 2, 2.
    xyz = np.zeros((4, 1, K, 3))
    xyz[:3, 0, 1, 0] = [1.0, 2.0, 3.0]
    xyz[:, 0, 2] = xyz[:, 0, 1] + [0.0, 2.0, 0.0]
    kv = np.ones((4, 1, K), bool)
    kv[3, 0, 0] = False
    out = bone_spread(xyz, kv, kv.any(-1), np.zeros((4, 1), int), [(0, 1), (1, 2)])
    cv01 = np.sqrt(((np.array([1, 2, 3]) - 2.0) ** 2).mean()) / 2.0
    assert out.by_track == {"0": pytest.approx(np.median([cv01, 0.0]))}
    # Fewer frames than min_frames: the bone does not count.
    assert (
        bone_spread(xyz, kv, kv.any(-1), np.zeros((4, 1), int), [(0, 1)], min_frames=4).by_track
        == {}
    )


def test_jitter_is_zero_at_constant_velocity_and_the_acceleration_in_m_per_s2():
    fps, F = 25.0, 12
    t = np.arange(F) / fps
    ones = np.ones((F, 1, 2), bool)
    track = np.zeros((F, 1), int)
    line = (t[:, None] * np.array([1.0, -0.5, 0.2]))[:, None, None] + np.zeros((1, 1, 2, 3))
    assert track_jitter(line, ones, ones[..., 0], track, fps) == pytest.approx(0.0, abs=1e-9)
    a = 3.0  # m/s², along x
    parabola = np.zeros((F, 1, 2, 3))
    parabola[..., 0] = 0.5 * a * t[:, None, None] ** 2
    assert track_jitter(parabola, ones, ones[..., 0], track, fps) == pytest.approx(a, rel=1e-6)


def test_people_count_and_track_fragments_by_hand():
    valid = np.array([[1, 1, 0], [1, 0, 0], [1, 1, 1]], bool)
    count = np.array([[2, 3, 1], [1, 1, 1], [2, 2, 4]])
    pc = people_count(valid, count)
    assert pc.mean_result == pytest.approx(2.0)
    assert pc.mean_abs_diff_most == pytest.approx((1 + 0 + 1) / 3)
    assert pc.mean_abs_diff_median == pytest.approx((0 + 0 + 1) / 3)
    track = np.array([[0, 1, -1], [0, -1, -1], [0, 2, 1]])
    frag = track_fragments(valid, track, short_frames=3)
    assert (frag.num_tracks, frag.short_tracks) == (3, 2)
    assert frag.mean_length_frames == pytest.approx((3 + 2 + 1) / 3)


def test_the_report_is_written_as_json_and_a_figure(rig, two_people, tmp_path):
    rec, exact = two_people
    result = _truth_result(exact)
    F, G = result.poses.valid.shape
    tracked = dataclasses.replace(
        result, track=np.broadcast_to(np.arange(G), (F, G)).copy(), timestamps=rec.timestamps
    )
    report = label_free_score(tracked, rig, exact.detections, layout=LAYOUT)
    assert report.tracks.num_tracks == G and report.bone_spread.median_cv < 1e-6
    json_path, png_path = write_label_free_report(report, tmp_path)
    data = json.loads(json_path.read_text())
    assert data["result"]["overall"]["share_within_px"]["20"] == report.result.overall.coverage
    assert data["blind_spots"] == list(BLIND_SPOTS)
    assert set(data["result"]["by_camera"]) == set(rec.cameras)
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_detections_are_named(rig, two_people):
    _, exact = two_people
    result = _truth_result(exact)
    det = exact.detections
    with pytest.raises(InputError, match="detections of shape"):
        label_free_score(
            result, rig, Detections(det.xy[:-1], det.score[:-1], det.count[:-1]), layout=LAYOUT
        )
    xy = np.asarray(det.xy).copy()
    f, c, p, k = np.argwhere(np.asarray(det.score) > 0)[5]
    xy[f, c, p, k, 0] = np.nan
    with pytest.raises(InputError) as e:
        label_free_score(result, rig, det._replace(xy=xy), layout=LAYOUT)
    assert e.value.frame == f and e.value.camera == exact.cameras[c] and e.value.field == "xy"
    with pytest.raises(InputError, match="method"):
        label_free_score(result, rig, det, layout=LAYOUT, config=LabelFreeConfig(method="mlp"))


def test_a_person_left_out_lowers_only_the_share_of_all_skeletons(rig, two_people):
    """Matched-people shares cannot see a person the result leaves out; the share over every
    skeleton's keypoints (one denominator for every result) can."""
    rec, exact = two_people
    result = _truth_result(exact)
    valid = np.asarray(result.poses.valid).copy()
    valid[:, 0] = False
    without = dataclasses.replace(result, poses=result.poses._replace(valid=valid))
    report = label_free_score(without, rig, exact.detections, layout=LAYOUT)
    r = report.result.overall
    assert r.share_within_px["20"] == r.coverage == (r.visible - r.blind) / r.visible
    shown = np.asarray(exact.detections.score) > 0
    ident = np.asarray(exact.identity)
    kept = int(shown[ident >= 1].sum())  # the other person's skeletons' keypoints
    # ... less its keypoints only one camera shows (unverifiable: never within).
    assert report.share_of_all_within_px["20"] == pytest.approx((kept - r.blind) / shown.sum())
    assert sum(report.unmatched_skeletons.values()) == int((shown.any(-1) & (ident != 1)).sum())


@pytest.mark.slow  # 13 variants on 4 small scenes (~30 s)
def test_the_synthetic_validation_writes_its_table_and_correlations(tmp_path):
    from experiments import label_free_synthetic

    assert label_free_synthetic.main(["--out", str(tmp_path), "--frames", "6"]) == 0
    record = json.loads((tmp_path / "label_free_synthetic.json").read_text())
    assert len(record["variants"]) >= 8
    for c in record["spearman"].values():
        assert set(c) >= {"pcp", "mpjpe", "pck3d_50", "pck3d_100", "same_winner_as_pcp"}
    # A fifth of the keypoints dropped is worse than the result it was made from, both ways.
    v = record["variants"]
    key = "share of all skeletons' keypoints within 20 px"
    assert v["robust, 20% keypoints dropped"][key] < v["robust"][key]
    assert v["robust, 20% keypoints dropped"]["pcp"] < v["robust"]["pcp"]
    assert "Spearman" in (tmp_path / "label_free_synthetic.md").read_text()
    assert (tmp_path / "report" / "label_free.png").exists()
