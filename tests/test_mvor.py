"""MVOR's reader and protocol (`experiments.mvor`) and the real-footage benchmark (`experiments.real`).

A tiny MVOR-format dataset is written here from known cameras and people (the file conventions
of the README: extrinsics to camera 1, camera 1 to the room, 3D in camera 1's frame, millimetres),
so the reader is checked against numbers it did not make; hostile copies of it must fail naming
file, frame, camera and field. The real files are used when present (skipped otherwise).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from experiments import mvor
from experiments.mvor import (
    JOINTS,
    load_mvor,
    poses_to_joints,
    reprojection_of_truth,
    select_frames,
    to_joints,
    true_identity,
)
from experiments.mvor_protocol import evaluate, versus
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Poses3D

REAL = mvor.DEFAULT_ROOT
needs_real = pytest.mark.skipif(
    not (REAL / mvor.ANNOTATIONS).is_file(), reason="MVOR days 1-2 are not beside the checkout"
)
FOCAL, PRINCIPAL = 540.0, (320.0, 240.0)


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """cam_from_room (4x4, millimetres) of an OpenCV camera at ``centre`` (m) looking at ``target``."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ centre * 1000.0
    return T


CAM_FROM_ROOM = [
    _look_at(np.array(c), np.array([0.0, 0.0, 0.0]))
    for c in ([3.5, 0.5, 1.6], [-0.5, 3.5, 1.7], [-3.0, -2.5, 1.5])
]


def _project(c: int, xyz_m: np.ndarray) -> np.ndarray:
    """Pinhole projection (no distortion) of room points (..., 3) metres into camera c."""
    x = xyz_m * 1000.0 @ CAM_FROM_ROOM[c][:3, :3].T + CAM_FROM_ROOM[c][:3, 3]
    return np.stack(
        [
            FOCAL * x[..., 0] / x[..., 2] + PRINCIPAL[0],
            FOCAL * x[..., 1] / x[..., 2] + PRINCIPAL[1],
        ],
        axis=-1,
    )


def _person(x: float, y: float) -> np.ndarray:
    """A standing person's 10 MVOR joints (metres, room frame); the neck is the shoulders' midpoint
    (as coco18 builds it), so a perfect triangulation matches every joint."""
    j = {
        "head": (0.0, 0.0, 0.75),
        "l_shoulder": (0.0, 0.2, 0.45),
        "r_shoulder": (0.0, -0.2, 0.45),
        "l_hip": (0.0, 0.12, -0.05),
        "r_hip": (0.0, -0.12, -0.05),
        "l_elbow": (0.05, 0.25, 0.15),
        "r_elbow": (0.05, -0.25, 0.15),
        "l_wrist": (0.25, 0.2, 0.0),
        "r_wrist": (0.25, -0.2, 0.0),
    }
    j["neck"] = tuple(np.mean([j["l_shoulder"], j["r_shoulder"]], axis=0))
    return np.array([j[n] for n in JOINTS]) + [x, y, 0.0]


# Two frames (day 1, then day 2): frame 0 has two people, frame 1 one.
PEOPLE = [[_person(0.6, -0.6), _person(-0.6, 0.7)], [_person(0.0, 0.1)]]


def _coco(head, joints_2d) -> list[float]:
    """COCO-17 (x, y, score) of a skeleton: face points at the head, knees and ankles missing."""
    by = dict(zip(JOINTS, joints_2d, strict=True))
    out = []
    for name in mvor.get_layout("coco17").keypoints:
        if name in ("nose", "l_eye", "r_eye", "l_ear", "r_ear"):
            out += [*head, 0.9]
        elif name in by:
            out += [*by[name], 0.9]
        else:
            out += [0.0, 0.0, 0.0]
    return [float(v) for v in out]


def write_tiny_mvor(root) -> None:
    """A two-frame, three-camera dataset in MVOR's files (README's conventions)."""
    room_from_cam1 = np.linalg.inv(CAM_FROM_ROOM[0])
    images, multiview, annotations, annotations3d, detections = [], [], [], [], []
    for f, people in enumerate(PEOPLE):
        day, frame = f + 1, 10 + f
        ids = [day * 10**10 + (c + 1) * 10**7 + frame for c in range(3)]
        records = [
            {"id": i, "cam_id": c + 1, "day_id": day, "file_name": f"day{day}/cam{c + 1}/x.png"}
            for c, i in enumerate(ids)
        ]
        images += records
        mv_id = "_".join(str(i) for i in ids)
        multiview.append({"images": records, "id": mv_id})
        for pid, xyz in enumerate(people):
            in_cam1 = (xyz * 1000.0) @ CAM_FROM_ROOM[0][:3, :3].T + CAM_FROM_ROOM[0][:3, 3]
            kp3 = np.concatenate([in_cam1, np.full((10, 1), 2.0)], axis=1)
            hands = np.concatenate([in_cam1[-2:], np.ones((2, 1))], axis=1)
            annotations3d.append(
                {
                    "image_ids": mv_id,
                    "person_id": pid,
                    "ref_camera": 1,
                    "id": str(len(annotations3d)),
                    "keypoints3D": np.concatenate([kp3, hands]).ravel().tolist(),
                }
            )
            for c in range(3):
                px = _project(c, xyz)
                kp = np.concatenate([px, np.full((10, 1), 2.0)], axis=1).ravel().tolist()
                lo, hi = px.min(0) - 10, px.max(0) + 10
                annotations.append(
                    {
                        "image_id": ids[c],
                        "person_id": pid,
                        "keypoints": kp,
                        "bbox": [*lo.tolist(), *(hi - lo).tolist()],
                        "only_bbox": 0,
                        "person_role": "clinician",
                    }
                )
                detections.append(
                    {"image_id": ids[c], "score": 0.8, "coco_keypoints": _coco(px[0], px)}
                )
    cam_params = {
        "firstCamToRoomRef": room_from_cam1.ravel().tolist(),
        "extrinsics": [
            (CAM_FROM_ROOM[0] @ np.linalg.inv(T)).ravel().tolist() for T in CAM_FROM_ROOM
        ],
        "intrinsics": [
            {
                "focallength": [FOCAL, FOCAL],
                "principalpoint": list(PRINCIPAL),
                "distortion": [0.1, -0.2, 0.3, 0.0, 0.0],
                "imagesize": [640, 480],
            }
            for _ in range(3)
        ],
    }
    doc = {
        "images": images,
        "multiview_images": multiview,
        "annotations": annotations,
        "annotations3D": annotations3d,
        "cameras_info": {"camParams": cam_params},
    }
    (root / "annotations").mkdir(parents=True)
    (root / "detections_results").mkdir()
    (root / mvor.ANNOTATIONS).write_text(json.dumps(doc))
    (root / mvor.DETECTIONS).write_text(json.dumps(detections))


@pytest.fixture()
def tiny(tmp_path):
    root = tmp_path / "mvor"
    write_tiny_mvor(root)
    return root


def test_reader_recovers_the_room_the_people_and_the_projections(tiny):
    data = load_mvor(tiny)
    assert data.num_frames == 2 and list(data.day) == [1, 2]
    assert data.num_records_3d == 3 and data.num_detections == 9
    # 3D truth: back in the room frame, metres, every joint annotated (flag 2).
    for f, people in enumerate(PEOPLE):
        for h, xyz in enumerate(people):
            np.testing.assert_allclose(data.gt.xyz[f, h], xyz, atol=1e-9)
    assert data.gt.valid.tolist() == [[True, True], [True, False]]
    assert data.gt.keypoint_valid[data.gt.valid].all()
    # The rig projects the room as the test's own pinhole cameras do.
    assert reprojection_of_truth(data)["overall"]["median"] < 1e-2
    # Detections: coco18, the neck the shoulders' midpoint; three views of every person.
    det = data.detections
    assert det.xy.shape == (2, 3, 2, 18, 2) and det.count.tolist() == [[2, 2, 2], [1, 1, 1]]
    joints, ok = to_joints(det.xy[0, 0, 0], det.score[0, 0, 0], data.layout)
    assert ok.all()
    px = _project(0, PEOPLE[0][0])
    # In the image the neck is the projected shoulders' midpoint (not the midpoint's projection).
    px[JOINTS.index("neck")] = px[[JOINTS.index("l_shoulder"), JOINTS.index("r_shoulder")]].mean(0)
    np.testing.assert_allclose(joints, px, atol=1e-3)
    identity = true_identity(data)
    assert identity[0].tolist() == [[0, 1]] * 3 and identity[1].tolist() == [[0, -1]] * 3


def test_the_stored_distortion_is_read_in_mvor_order(tiny):
    rig = load_mvor(tiny, distortion=True).rig
    # MVOR stores [k1, k2, k3, p1, p2]; the rig holds OpenCV's [k1, k2, p1, p2, k3].
    np.testing.assert_allclose(np.asarray(rig.dist[0]), [0.1, -0.2, 0.0, 0.0, 0.3], rtol=1e-6)
    assert not np.asarray(load_mvor(tiny).rig.dist).any()


def test_to_joints_takes_the_first_alternative_that_exists():
    layout = mvor.get_layout("coco18")
    xy = np.zeros((18, 2))
    score = np.zeros(18)
    for name, at in (("nose", 1.0), ("l_eye", 2.0), ("r_eye", 4.0), ("l_ear", 10.0)):
        xy[layout.index(name)], score[layout.index(name)] = at, 1.0
    joints, ok = to_joints(xy, score)
    assert ok[0] and joints[0, 0] == 3.0  # one ear only: the eyes' midpoint
    score[layout.index("r_ear")], xy[layout.index("r_ear")] = 1.0, 20.0
    assert to_joints(xy, score)[0][0, 0] == 15.0  # both ears: their midpoint
    assert not to_joints(xy, np.zeros(18))[1].any()


def _shifted(data, metres: float, drop=()) -> Poses3D:
    """The truth as predictions, every joint moved ``metres`` along x; ``drop``: (frame, slot)s
    left out."""
    valid = np.asarray(data.gt.valid).copy()
    for f, h in drop:
        valid[f, h] = False
    return Poses3D(
        data.gt.xyz + [metres, 0.0, 0.0], valid, data.gt.keypoint_valid & valid[..., None]
    )


def test_protocol_on_known_errors(tiny):
    data = load_mvor(tiny)
    perfect = evaluate(_shifted(data, 0.0), data)["overall"]
    assert perfect["missed"] == 0 and perfect["people"] == 3
    assert perfect["mpjpe_mm"] == pytest.approx(0.0, abs=1e-9)
    assert perfect["pck3d_100"] == perfect["pck3d_150"] == perfect["pcp_upper"] == 100.0
    off = evaluate(_shifted(data, 0.12), data, unreachable=np.eye(2, dtype=bool))
    assert off["overall"]["mpjpe_mm"] == pytest.approx(120.0)
    assert off["overall"]["mpjpe_mm_without_hips"] == pytest.approx(120.0)
    # Slots (0, 0) and (1, 1) are marked unreachable; only (0, 0) is a person, and matched.
    assert off["overall"]["matched_unreachable"] == 1
    assert off["overall"]["pck3d_100"] == 0.0 and off["overall"]["pck3d_150"] == 100.0
    # The shortest limb (head to neck, 0.3 m) tolerates 0.15 m of mean error: all correct.
    assert off["overall"]["pcp_upper"] == 100.0
    # A missed person's joints are wrong in PCK and PCP, absent from MPJPE; days apart.
    missed = evaluate(_shifted(data, 0.0, drop=[(0, 1)]), data)
    assert missed["day1"]["missed"] == 1 and missed["day2"]["missed"] == 0
    assert missed["day1"]["pck3d_150"] == pytest.approx(50.0)
    assert missed["overall"]["pck3d_150"] == pytest.approx(200 / 3)
    assert missed["day1"]["pcp_upper"] == pytest.approx(50.0)
    assert missed["overall"]["mpjpe_mm"] == pytest.approx(0.0, abs=1e-9)
    # Beyond the gate nobody is matched.
    far = evaluate(_shifted(data, 0.6), data)["overall"]
    assert far["missed"] == 3 and far["pck3d_150"] == 0.0 and math.isnan(far["mpjpe_mm"])
    # A joint not produced is wrong in PCK, left out of MPJPE.
    partial = _shifted(data, 0.0)
    kv = np.asarray(partial.keypoint_valid).copy()
    kv[..., JOINTS.index("l_wrist")] = False
    scores = evaluate(Poses3D(partial.xyz, partial.valid, kv), data)["overall"]
    assert scores["pck3d_150"] == pytest.approx(90.0) and scores["missed"] == 0
    assert math.isnan(scores["joint_mm"]["l_wrist"]) and scores["pcp_by_limb"]["l_lower_arm"] == 0


def test_versus_compares_two_results_on_the_people_both_place(tiny):
    data = load_mvor(tiny)
    # The reference misses person (0, 1); the row is 0.1 m off everywhere and lacks wrists.
    row = _shifted(data, 0.1)
    kv = np.asarray(row.keypoint_valid).copy()
    kv[..., JOINTS.index("l_wrist")] = False
    row = Poses3D(row.xyz, row.valid, kv)
    reference = _shifted(data, 0.05, drop=[(0, 1)])
    v = versus(row, reference, data)
    assert v["people"] == 2  # of the 3 annotated: the reference's miss is not compared
    assert v["joints"] == 2 * 9 and v["reference_joints"] == 2 * 10 and v["common_joints"] == 18
    assert v["mpjpe_mm"] == pytest.approx(100.0) and v["reference_mpjpe_mm"] == pytest.approx(50.0)
    assert v["mpjpe_common_mm"] == pytest.approx(100.0)
    assert v["reference_mpjpe_common_mm"] == pytest.approx(50.0)
    # Against itself: every person, every joint, the same error.
    same = versus(reference, reference, data)
    assert same["people"] == 2 and same["mpjpe_mm"] == same["reference_mpjpe_mm"]


def test_geometric_pipelines_recover_the_tiny_scene(tiny):
    from experiments.real import CORRUPTED, run

    report = run(load_mvor(tiny))
    for name, row in report["rows"].items():
        s = row["overall"]
        assert s["missed"] == 0, name
        assert s["mpjpe_mm"] < 1.0, name
        assert s["pck3d_100"] == 100.0, name
        # Every row places the three people geometry places, with the same sub-mm error.
        v = row["vs_geometric"]
        assert v["people"] == 3 and v["reference_mpjpe_mm"] < 1.0 and v["mpjpe_mm"] < 1.0, name
    joints = poses_to_joints(
        Poses3D(np.zeros((1, 1, 18, 3)), np.ones((1, 1), bool), np.ones((1, 1, 18), bool))
    )
    assert joints.xyz.shape == (1, 1, 10, 3) and joints.keypoint_valid.all()

    # The label-free validation: exact detections, so every honest variant explains every
    # keypoint of every skeleton (3 people x 3 cameras x 14 keypoints the files give) at 0 px.
    v = report["label_free_validation"]
    corrupt = {name for name, _ in CORRUPTED}
    assert len(v["variants"]) >= 8 + len(corrupt)
    for name, row in v["variants"].items():
        lf = row["label_free"]
        assert row["leave_one_out_visible_keypoints"] == 126, name
        assert row["leave_one_out_blind_keypoints"] == 0, name  # 3 views: 2 others everywhere
        if name not in corrupt:
            assert lf["all skeletons within 20 px"] == 1.0 and lf["median px"] < 0.01, name
    # Without its wrists a result explains 12 of each skeleton's 14 keypoints.
    wrists = v["variants"]["geometric default, wrists dropped"]["label_free"]
    assert wrists["coverage"] == pytest.approx(12 / 14)
    assert wrists["all skeletons within 20 px"] == pytest.approx(12 / 14)
    # The detections are the truth's projections: the noise floor is nil; nobody is blind.
    arms = v["noise_floor"]["arms"]["overall"]
    assert arms["median_px"] < 0.01 and arms["visible"] == 3 * 3 * 6
    assert v["blind"]["annotated_people"] == 3 and v["blind"]["seen_in_fewer_than_2_views"] == 0
    # Only the corruptions change the ranking: the share agrees with PCK3D@150 (ties aside).
    assert v["spearman"]["all skeletons within 20 px"]["PCK3D@150"] > 0.9


def test_corruptions_move_a_tenth_of_keypoints_5_cm_or_drop_them():
    from experiments.real import corrupted

    rng = np.random.default_rng(0)
    F, G, K = 40, 3, 18
    xyz = rng.normal(size=(F, G, K, 3)).astype(np.float32)
    result = PoseResults(
        Poses3D(xyz, np.ones((F, G), bool), np.ones((F, G, K), bool)),
        np.ones((F, G), np.float32),
        np.zeros((F, G, 1), np.int32),
        np.zeros((F, 1, 1), np.int32),
        ("cam1",),
        "coco18",
    )
    moved = corrupted(result, "move", np.random.default_rng(1))
    d = np.linalg.norm(moved.poses.xyz - xyz, axis=-1)
    changed = d > 1e-6
    assert 0.07 < changed.mean() < 0.13
    np.testing.assert_allclose(d[changed], 0.05, atol=1e-5)
    no_wrists = corrupted(result, "wrists", rng).poses.keypoint_valid
    assert (~no_wrists).sum(-1).max() == 2 and not no_wrists[..., [9, 10]].any()
    dropped = corrupted(result, "drop", rng).poses.keypoint_valid
    assert 0.15 < 1 - dropped.mean() < 0.25
    with pytest.raises(ValueError):
        corrupted(result, "bend", rng)


# ------------------------------------------------------------------------------- hostile input


def _edit(root, name, change):
    path = root / name
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def test_a_multiview_record_missing_a_camera_names_it(tiny):
    _edit(tiny, mvor.ANNOTATIONS, lambda d: d["multiview_images"][1]["images"].pop(2))
    with pytest.raises(InputError) as e:
        load_mvor(tiny)
    err = e.value
    assert err.file.endswith("camma_mvor_2018.json") and err.camera == "cam3"
    assert err.frame == "20010000011_20020000011_20030000011"
    assert err.field == "multiview_images[1].images"


def test_a_nan_detection_names_file_frame_camera_and_keypoint(tiny):
    def poison(dets):
        dets[4]["coco_keypoints"][3 * 5] = float("nan")  # l_shoulder x, score 0.9

    _edit(tiny, mvor.DETECTIONS, poison)
    with pytest.raises(InputError, match="not finite") as e:
        load_mvor(tiny)
    err = e.value
    assert err.file.endswith("openpose_kps.json")
    assert (err.frame, err.camera) == ("10010000010_10020000010_10030000010", "cam2")
    assert err.field == "[4].coco_keypoints[5]"


def test_nan_and_malformed_annotations_are_located(tiny):
    _edit(
        tiny, mvor.ANNOTATIONS, lambda d: d["annotations3D"][2]["keypoints3D"].__setitem__(7, None)
    )
    with pytest.raises(InputError) as e:
        load_mvor(tiny)
    assert e.value.field == "annotations3D[2].keypoints3D[7]"
    assert e.value.frame == "20010000011_20020000011_20030000011"

    write_tiny_mvor(tiny.parent / "b")
    root = tiny.parent / "b"
    _edit(
        root,
        mvor.ANNOTATIONS,
        lambda d: d["annotations"][4]["keypoints"].__setitem__(0, float("nan")),
    )
    with pytest.raises(InputError) as e:
        load_mvor(root)
    assert (e.value.camera, e.value.field) == ("cam2", "annotations[4].keypoints[0]")

    write_tiny_mvor(tiny.parent / "c")
    root = tiny.parent / "c"
    _edit(root, mvor.ANNOTATIONS, lambda d: d["cameras_info"]["camParams"]["intrinsics"].pop())
    with pytest.raises(InputError, match="one entry per camera"):
        load_mvor(root)
    with pytest.raises(InputError, match="no such file"):
        load_mvor(tiny.parent / "nowhere")


def test_duplicate_records_unknown_ids_and_bad_flags(tiny):
    # A 3D record stored twice (MVOR's ids 718 and 719) is kept once; two different ones fail.
    _edit(tiny, mvor.ANNOTATIONS, lambda d: d["annotations3D"].append(d["annotations3D"][0]))
    data = load_mvor(tiny)
    assert data.num_records_3d == 4 and int(data.gt.valid.sum()) == 3

    def differ(d):
        d["annotations3D"][-1] = json.loads(json.dumps(d["annotations3D"][0]))
        d["annotations3D"][-1]["keypoints3D"][0] += 1.0

    _edit(tiny, mvor.ANNOTATIONS, differ)
    with pytest.raises(InputError, match="two different 3D records") as e:
        load_mvor(tiny)
    assert e.value.field == "annotations3D[3]"

    for name, change, field in (
        (mvor.DETECTIONS, lambda d: d[2].__setitem__("image_id", 5), "[2].image_id"),
        (
            mvor.ANNOTATIONS,
            lambda d: d["annotations"][1]["keypoints"].__setitem__(2, 3),
            "annotations[1].keypoints[2]",
        ),
        (
            mvor.ANNOTATIONS,
            lambda d: d["annotations3D"][0].__setitem__("image_ids", "1_2_3"),
            "annotations3D[0].image_ids",
        ),
    ):
        root = tiny.parent / f"copy{len(field)}"
        write_tiny_mvor(root)
        _edit(root, name, change)
        with pytest.raises(InputError) as e:
            load_mvor(root)
        assert e.value.field == field and e.value.file.endswith(str(name.name))


def test_select_frames_keeps_every_array_aligned(tiny):
    data = load_mvor(tiny)
    one = select_frames(data, [1])
    assert one.frame_ids == data.frame_ids[1:] and one.day.tolist() == [2]
    np.testing.assert_array_equal(one.gt.xyz, data.gt.xyz[1:])
    np.testing.assert_array_equal(one.detections.xy, data.detections.xy[1:])


# ------------------------------------------------------------------------------- the real files


@needs_real
def test_real_counts_and_ground_truth_reprojection():
    data = load_mvor(REAL)
    # README: 387 multi-view frames (57 on day 1, 330 on day 2), 573 3D records of which one is
    # a duplicate (ids 718 and 719), 2284 detections, 4 scores slightly above 1.
    assert data.num_frames == 387
    assert np.bincount(data.day).tolist() == [0, 57, 330]
    assert data.num_records_3d == 573 and int(data.gt.valid.sum()) == 572
    assert data.num_detections == 2284 and int(data.detections.count.sum()) == 2284
    assert data.clipped_scores == 4 and float(data.detections.score.max()) == 1.0
    # Measured: the 3D truth projects 6.6 px (day 1) and 7.4 px (day 2) median from the 2D
    # annotations without distortion, 8.1 px overall with the stored coefficients (README too).
    check = reprojection_of_truth(data)
    assert check["day1"]["all"]["median"] < 7.0 and check["day2"]["all"]["median"] < 8.0
    with_distortion = reprojection_of_truth(load_mvor(REAL, distortion=True))["overall"]
    assert with_distortion["median"] > check["overall"]["median"]


@needs_real
@pytest.mark.slow  # the benchmark's smoke run, with models, then again without them
def test_real_smoke_run_writes_its_files_deterministically(tmp_path):
    from experiments.pose2sim_demo import DEFAULT_DATA, MODEL_ROWS, OUR_ROWS, PEER_ROWS
    from experiments.real import MODEL_PIPELINES, PIPELINES, main

    # Smoke-size training: the code path, not the numbers. The second run, without models,
    # must give the rows without models as the first did.
    assert main(["--smoke", "--out", str(tmp_path / "a"), "--models", str(tmp_path / "m")]) == 0
    assert main(["--smoke", "--out", str(tmp_path / "b"), "--no-models"]) == 0
    a, b = (json.loads((tmp_path / n / "real.json").read_text()) for n in "ab")
    assert a["scale"] == "smoke" and a["split"].startswith("MVOR days 1-2")
    assert list(a["rows"]) == [row[0] for row in PIPELINES + MODEL_PIPELINES]
    assert list(b["rows"]) == [row[0] for row in PIPELINES]
    for row in a["rows"].values():
        one, more = row["by_views"]["1"], row["by_views"]["2+"]
        # Geometry and min_views 2 never build a person from one view.
        assert row["min_views"] == 1 or one["predicted"] == 0
        assert more["matched"] <= more["predicted"]
    assert [a["rows"][n]["models"] for n in a["rows"]] == [False] * len(PIPELINES) + [True] * len(
        MODEL_PIPELINES
    )
    # The models' floor: MVOR's feet are hidden, so the upright people's shoulders; the README
    # estimates -1.0 m.
    floor = a["models"]["mvor-synthetic"]["floor"]
    assert floor["basis"] == "upper_body" and abs(floor["height"] + 1.0) < 0.1
    assert (tmp_path / "m" / "mvor-synthetic" / "matcher").is_dir()
    for name in b["rows"]:
        for row in (a, b):
            row["rows"][name].pop("seconds")
        assert a["rows"][name] == b["rows"][name]
    assert (tmp_path / "a" / "real_joints.png").stat().st_size > 0
    assert "MPJPE per joint" in (tmp_path / "a" / "real.md").read_text()
    # The label-free validation: as deterministic, a second table.
    va, vb = (r["label_free_validation"] for r in (a, b))
    for v in (va, vb):
        for row in v["variants"].values():
            row.pop("seconds_label_free")
    assert len(va["variants"]) == len(vb["variants"]) + len(MODEL_PIPELINES) >= 8
    for name, row in vb["variants"].items():
        assert va["variants"][name] == row
    assert set(va["spearman"]["all skeletons within 20 px"]) == {
        "PCK3D@150",
        "PCP upper",
        "MPJPE",
        "missed people",
    }
    text = (tmp_path / "a" / "real.md").read_text()
    assert "## The label-free score against the labelled one" in text and "Noise floor" in text
    # The Pose2Sim demo's table, with the rows of its three model pairs.
    if not DEFAULT_DATA.is_dir():
        return
    demo, plain = a["pose2sim_demo"], b["pose2sim_demo"]
    rows = {r["row"]: r for r in demo["multi_person"]["rows"]}
    assert [r["row"] for r in plain["multi_person"]["rows"]] == [r[0] for r in OUR_ROWS + PEER_ROWS]
    for row in plain["multi_person"]["rows"]:
        assert rows[row["row"]] == row
    assert all(label in rows for label, source, _ in MODEL_ROWS if source == "synthetic")
    assert set(demo["models"]) == {"synthetic"}  # a smoke run's one pair
    assert demo["models"]["synthetic"]["floor"]["up_source"] == "people"
    assert "Pose2Sim's demo session" in text and "The models of the rows with models" in text


@needs_real
def test_pretrained_real_smoke_scores_the_rows_asked_for(tmp_path):
    """`experiments.pretrained_real --rows`: the geometric default (the reference) and the rows
    named, on MVOR and on the demo (no true groups there); no rig model trained for them."""
    from experiments.pose2sim_demo import DEFAULT_DATA
    from experiments.pretrained_real import main

    rows = ["GAT + robust, pretrained matcher", "true groups + robust"]
    argv = ["--smoke", "--out", str(tmp_path), "--matcher", "pretrained", "--rows", *rows]
    assert main(argv) == 0
    report = json.loads((tmp_path / "pretrained_real.json").read_text())
    assert report["models"] == {"estimator": "pretrained", "matcher": "pretrained"}
    geometric = "geometric default (epipolar + robust)"
    assert list(report["mvor"]) == [geometric, *rows]
    assert report["mvor"][geometric]["vs_geometric"]["mpjpe_mm"] == pytest.approx(
        report["mvor"][geometric]["mpjpe_mm"]
    )
    assert not (tmp_path / "models").exists()
    assert all(r["people_per_frame"] > 0 for r in report["mvor"].values())
    if DEFAULT_DATA.is_dir():
        assert list(report["demo"]) == [geometric, rows[0]]
    with pytest.raises(SystemExit):
        main(["--smoke", "--out", str(tmp_path), "--rows", "no such row"])
