"""experiments.pose2sim_demo: the TRC reader (a Pose2Sim-style file and our own exporter's), the
TRC-to-coco18 mapping, the axis search, the identity assignment, and the smoke run."""

import json

import numpy as np
import pytest

from experiments import pose2sim_demo as demo
from mvpose_jax.cameras import project_points
from mvpose_jax.data.exports import ExportConfig, export_poses, opensim_from_world
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Detections, Poses3D, get_layout
from tests.helpers import random_rig, scene_points

# A Pose2Sim-style TRC (header as Pose2Sim writes it), millimetres, Y up: frame 2 lacks LHip
# (empty fields) and frame 3 has RHip as "nan".
POSE2SIM_TRC = (
    "PathFileType\t4\t(X/Y/Z)\tdemo.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\t"
    "OrigNumFrames\n"
    "60\t60\t3\t3\tmm\t60\t0\t3\n"
    "Frame#\tTime\tRHip\t\t\tLHip\t\t\tNeck\t\t\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\tX3\tY3\tZ3\n"
    "\n"
    "1\t0.016667\t100\t900\t-50\t300\t910\t-40\t200\t1500\t-45\n"
    "2\t0.033333\t110\t901\t-51\t\t\t\t210\t1501\t-46\n"
    "3\t0.05\tnan\tnan\tnan\t320\t912\t-42\t220\t1502\t-47\t\n"
)


def test_read_trc_pose2sim_style(tmp_path):
    path = tmp_path / "demo.trc"
    path.write_text(POSE2SIM_TRC)
    trc = demo.read_trc(path)
    assert trc.names == ("RHip", "LHip", "Neck")
    assert trc.units == "mm" and trc.rate == 60.0
    np.testing.assert_array_equal(trc.frame, [1, 2, 3])
    np.testing.assert_allclose(trc.time, [0.016667, 0.033333, 0.05])
    np.testing.assert_array_equal(trc.present, [[1, 1, 1], [1, 0, 1], [0, 1, 1]])
    # Millimetres to metres.
    np.testing.assert_allclose(trc.xyz[0, 0], [0.1, 0.9, -0.05])
    np.testing.assert_allclose(trc.xyz[2, 2], [0.22, 1.502, -0.047])
    assert np.isnan(trc.xyz[1, 1]).all() and np.isnan(trc.xyz[2, 0]).all()


def test_read_trc_refuses_a_wrong_marker_count(tmp_path):
    path = tmp_path / "bad.trc"
    path.write_text(POSE2SIM_TRC.replace("60\t60\t3\t3\tmm", "60\t60\t3\t4\tmm"))
    with pytest.raises(InputError, match="NumMarkers"):
        demo.read_trc(path)


def test_read_trc_refuses_a_row_with_more_values_than_markers(tmp_path):
    path = tmp_path / "bad.trc"
    path.write_text(POSE2SIM_TRC.replace("-47\t\n", "-47\t1.0\n"))
    with pytest.raises(InputError, match="line 9"):
        demo.read_trc(path)


def test_read_trc_reads_back_our_exporter(tmp_path):
    """What `data.exports` writes (OpenSim axes, mm, per track) reads back as R @ world, m."""
    rng = np.random.default_rng(0)
    F, G, K = 5, 1, 18
    xyz = rng.normal(size=(F, G, K, 3)).astype(np.float32)
    kv = np.ones((F, G, K), bool)
    kv[2, 0, 3] = False  # an absent keypoint: empty fields
    results = PoseResults(
        Poses3D(xyz, np.ones((F, G), bool), kv),
        np.ones((F, G), np.float32),
        np.full((F, G, 1), -1, np.int32),
        np.full((F, 1, 1), -1, np.int32),
        ("a",),
        "coco18",
        None,
        np.full((F, G), 7),
    )
    up = (0.0, 0.0, 1.0)
    (path,) = export_poses(results, tmp_path / "poses", ExportConfig(fps=60.0, up=up))
    trc = demo.read_trc(path)
    assert trc.names == get_layout("coco18").keypoints
    assert trc.units == "mm" and trc.rate == 60.0
    np.testing.assert_array_equal(trc.frame, np.arange(1, F + 1))
    np.testing.assert_array_equal(trc.present, kv[:, 0])
    want = xyz[:, 0].astype(np.float64) @ opensim_from_world(up).T
    np.testing.assert_allclose(trc.xyz[trc.present], want[kv[:, 0]], atol=1e-6)


def test_trc_keypoints_maps_by_name_and_builds_the_neck():
    names = ("Neck", "LShoulder", "RShoulder", "Nose", "Head")
    xyz = np.arange(2 * 5 * 3, dtype=float).reshape(2, 5, 3)
    present = np.ones((2, 5), bool)
    present[1, 1] = False  # no left shoulder in the TRC's second row: no neck either
    # Rows are frames 1 and 3 (a gap at frame 2) of a 4-frame recording.
    trc = demo.Trc(names, np.array([1, 3]), np.array([0.0, 0.1]), xyz, present, "m", 60.0)
    out, have = demo.trc_keypoints(trc, 4)
    kp = get_layout("coco18").keypoints
    i = {n: kp.index(n) for n in ("nose", "l_shoulder", "r_shoulder", "neck", "l_eye", "l_ear")}
    np.testing.assert_allclose(out[0, i["nose"]], xyz[0, 3])
    np.testing.assert_allclose(out[0, i["neck"]], (xyz[0, 1] + xyz[0, 2]) / 2)
    assert have[0, i["neck"]] and not have[2, i["neck"]]
    assert have[2, i["r_shoulder"]] and not have[2, i["l_shoulder"]]
    assert not have[1].any() and not have[3].any()  # frames the TRC has no row for
    assert not have[:, i["l_eye"]].any() and not have[:, i["l_ear"]].any()
    # Pose2Sim's Neck (the upper neck) is not coco18's neck.
    assert not np.allclose(out[0, i["neck"]], xyz[0, 0])


def _scene(seed=0):
    """Two people (F=3, K=18) and the rig's skeletons of them in a shuffled order, plus a decoy
    skeleton far from both."""
    rig = random_rig(seed)
    F, G, K = 3, 2, 18
    xyz = scene_points(rig, seed, (F, G, K)).astype(np.float64)
    xyz[:, 1] += np.array([0.8, 0.0, 0.0])  # the second person beside the first
    proj = np.asarray(project_points(rig, xyz))  # (C, F, G, K, 2)
    C, P = len(rig.names), 3
    rng = np.random.default_rng(seed)
    xy = np.zeros((F, C, P, K, 2))
    score = np.zeros((F, C, P, K))
    truth = np.full((F, C, P), -1)
    for f in range(F):
        for c in range(C):
            order = rng.permutation(P)  # slot order[g] holds person g; order[2] the decoy
            for g in range(G):
                xy[f, c, order[g]] = proj[c, f, g] + rng.normal(scale=2.0, size=(K, 2))
                score[f, c, order[g]] = 0.9
                truth[f, c, order[g]] = g
            xy[f, c, order[2]] = proj[c, f, 0] + 400.0
            score[f, c, order[2]] = 0.8
    detections = Detections(xy, score, np.full((F, C), P))
    return rig, xyz, detections, truth


def test_assign_identity_recovers_the_shuffled_skeletons_and_leaves_the_decoy():
    rig, xyz, detections, truth = _scene()
    present = np.ones(xyz.shape[:3], bool)
    members, identity = demo.assign_identity(xyz, present, rig, detections)
    np.testing.assert_array_equal(identity, truth)
    F, C = truth.shape[:2]
    for f in range(F):
        for c in range(C):
            for g in range(2):
                assert truth[f, c, members[f, g, c]] == g


def test_assign_identity_gate_and_shared_keypoints():
    rig, xyz, detections, truth = _scene(1)
    xy, score = np.array(detections.xy), np.array(detections.score)
    # Frame 0, camera 0: person 1's skeleton 80 px off (beyond the 50 px gate); frame 1, camera
    # 1: person 0's skeleton shows only two keypoints (fewer than MIN_SHARED).
    p1 = int(np.nonzero(truth[0, 0] == 1)[0][0])
    xy[0, 0, p1] += 80.0
    p0 = int(np.nonzero(truth[1, 1] == 0)[0][0])
    score[1, 1, p0, 2:] = 0.0
    members, identity = demo.assign_identity(
        xyz, np.ones(xyz.shape[:3], bool), rig, detections._replace(xy=xy, score=score)
    )
    assert members[0, 1, 0] == -1 and identity[0, 0, p1] == -1
    assert members[1, 0, 1] == -1 and identity[1, 1, p0] == -1
    assert members[0, 0, 0] == int(np.nonzero(truth[0, 0] == 0)[0][0])


def test_trc_axes_finds_the_rotation():
    rig, xyz, detections, _ = _scene(2)
    rotation = demo.axis_rotations()[7]
    in_trc = xyz @ rotation  # p_trc = R^T p_world
    found, median_px, next_px = demo.trc_axes(in_trc, np.ones(xyz.shape[:3], bool), rig, detections)
    np.testing.assert_array_equal(found, rotation)
    assert median_px < 5.0 < 50.0 < next_px
    assert len(demo.axis_rotations()) == 24


@pytest.mark.slow
@pytest.mark.skipif(not demo.DEFAULT_DATA.is_dir(), reason="the Pose2Sim demo is not here")
def test_smoke_run(tmp_path):
    assert demo.main(["--out", str(tmp_path), "--smoke"]) == 0
    report = json.loads((tmp_path / "pose2sim_demo.json").read_text())
    assert report["split"] == demo.SPLIT
    multi = report["multi_person"]
    assert multi["frames"] == demo.SMOKE_FRAMES
    labels = [r["row"] for r in multi["rows"]]
    assert labels == [r[0] for r in demo.OUR_ROWS] + [r[0] for r in demo.PEER_ROWS]
    for row in multi["rows"]:
        n = row["all_keypoints"]
        assert 0.0 < n["within_20px_all_skeletons"] <= 1.0
        assert n["people_per_frame"] >= 2.0
    # Pose2Sim's TRC: Y up, put back into the calibration's Z-up world; the two participants.
    for info in multi["pose2sim_trc"].values():
        assert info["rotation_world_from_trc"] == [[0, 0, 1], [1, 0, 0], [0, 1, 0]]
        assert info["axes_median_px"] < 30.0 < info["axes_next_best_median_px"]
        assert len(info["files"]) == 2
    timings = json.loads((tmp_path / "timings.json").read_text())
    assert all(timings[r[0]] > 0 for r in demo.OUR_ROWS)
    assert "seconds" not in json.dumps(report)
    assert "| Pose2Sim, Butterworth TRC |" in (tmp_path / "pose2sim_demo.md").read_text()


@pytest.mark.skipif(not demo.DEFAULT_DATA.is_dir(), reason="the Pose2Sim demo is not here")
def test_the_single_person_trials_split_into_training_and_dev_recordings():
    train, dev = demo.trial_recordings(demo.DEFAULT_DATA)
    # 3 training recordings (two static trials, the balancing trial's first 80 frames) and 2 dev
    # ones (its last 20 frames, participant 2's static trial): 104 and 32 frames.
    assert sorted(r.num_frames for r in train) == [12, 12, 100 - demo.BALANCE_DEV_FRAMES]
    assert sorted(r.num_frames for r in dev) == [12, demo.BALANCE_DEV_FRAMES]
    for rec in train + dev:
        assert rec.cameras == ("cam_01", "cam_02", "cam_03", "cam_04") and rec.layout == "coco18"
        assert (np.asarray(rec.detections.count) >= 1).mean() > 0.9  # the participant, seen
