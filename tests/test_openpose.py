"""OpenPose per-frame JSON folders: layouts mapped to coco18, frame alignment, errors, round trip."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mvpose_jax.data import (
    Recording,
    load_recording,
    read_openpose,
    save_openpose,
    save_recording,
)
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.openpose import OpenPoseStream, parse_camera_map
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Detections, get_layout
from mvpose_jax.synthetic import generate_recording

COCO18 = get_layout("coco18")


def _flat(K: int, points: dict[int, tuple[float, float, float]]) -> list[float]:
    """pose_keypoints_2d with the given keypoints set and the rest undetected (0, 0, 0)."""
    out = [0.0] * (3 * K)
    for k, xyc in points.items():
        out[3 * k : 3 * k + 3] = xyc
    return out


def _write_frame(path: Path, people: list[list[float]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "version": 1.3,
        "people": [
            {"person_id": [-1], "pose_keypoints_2d": flat, "face_keypoints_2d": []}
            for flat in people
        ],
    }
    path.write_text(json.dumps(doc))


# OpenPose COCO (18): 0 nose, 1 neck, 2 r_shoulder, 5 l_shoulder, 8 r_hip, 14 r_eye, 17 l_ear.
COCO_PERSON = {
    0: (10.0, 20.0, 0.9),
    1: (30.0, 40.0, 0.8),
    2: (50.0, 60.0, 0.7),
    5: (70.0, 80.0, 0.6),
    8: (90.0, 100.0, 0.5),
    14: (1.0, 2.0, 0.4),
    17: (3.0, 4.0, 0.3),
}
# Where each lands in the project's coco18.
COCO_TO_OURS = {0: 0, 1: 17, 2: 6, 5: 5, 8: 12, 14: 2, 17: 3}
# BODY_25: 1 neck, 2 r_shoulder, 8 mid_hip (no coco18 slot), 9 r_hip, 14 l_ankle, 19 l_big_toe
# (no slot), 24 r_heel (no slot).
BODY25_PERSON = {
    1: (11.0, 12.0, 0.95),
    2: (13.0, 14.0, 0.85),
    8: (15.0, 16.0, 0.75),
    9: (17.0, 18.0, 0.65),
    14: (19.0, 20.0, 0.55),
    19: (21.0, 22.0, 0.45),
    24: (23.0, 24.0, 0.35),
}
BODY25_TO_OURS = {1: 17, 2: 6, 9: 12, 14: 15}
# HALPE_26 (RTMPose / Pose2Sim): 0 nose, 6 r_shoulder, 11 l_hip, 17 head (no coco18 slot), 18 neck,
# 19 mid_hip (no slot), 24 l_heel (no slot).
HALPE26_PERSON = {
    0: (31.0, 32.0, 0.9),
    6: (33.0, 34.0, 0.8),
    11: (35.0, 36.0, 0.7),
    17: (37.0, 38.0, 0.6),
    18: (39.0, 40.0, 0.5),
    19: (41.0, 42.0, 0.4),
    24: (43.0, 44.0, 0.3),
}
HALPE26_TO_OURS = {0: 0, 6: 6, 11: 11, 18: 17}


def _tiny_folder(root: Path, K: int, person: dict) -> Path:
    """2 cameras, 2 frames (OpenPose numbers 0 and 1, different prefixes per camera).

    Frame 0: camera a sees `person` and a second person with only the nose; camera b sees
    `person` shifted by +100 px. Frame 1: camera a sees nobody, camera b sees `person`.
    """
    shifted = {k: (x + 100.0, y + 100.0, c) for k, (x, y, c) in person.items()}
    _write_frame(
        root / "a" / "clipA_000000000000_keypoints.json",
        [_flat(K, person), _flat(K, {0: (5.0, 6.0, 1.0)})],
    )
    _write_frame(root / "a" / "clipA_000000000001_keypoints.json", [])
    _write_frame(root / "b" / "clipB_000000000000_keypoints.json", [_flat(K, shifted)])
    _write_frame(root / "b" / "clipB_000000000001_keypoints.json", [_flat(K, person)])
    return root


@pytest.mark.parametrize(
    "K, person, mapping",
    [
        (18, COCO_PERSON, COCO_TO_OURS),
        (25, BODY25_PERSON, BODY25_TO_OURS),
        (26, HALPE26_PERSON, HALPE26_TO_OURS),
    ],
    ids=["coco", "body25", "halpe26"],
)
def test_hand_written_folder_lands_in_coco18(tmp_path, K, person, mapping):
    root = _tiny_folder(tmp_path / "op", K, person)
    rec = load_recording(root)
    assert rec.layout == "coco18" and rec.cameras == ("a", "b")
    det = rec.detections
    assert det.xy.shape == (2, 2, 2, 18, 2) and det.xy.dtype == np.float32
    np.testing.assert_array_equal(det.count, [[2, 1], [0, 1]])
    expected_xy = np.zeros((18, 2), np.float32)
    expected_score = np.zeros(18, np.float32)
    for src, ours in mapping.items():
        x, y, c = person[src]
        expected_xy[ours], expected_score[ours] = (x, y), c
    np.testing.assert_array_equal(det.xy[0, 0, 0], expected_xy)
    np.testing.assert_array_equal(det.score[0, 0, 0], expected_score)
    np.testing.assert_array_equal(det.xy[1, 1, 0], expected_xy)
    shifted = np.where(expected_score[:, None] > 0, expected_xy + 100.0, 0.0)
    np.testing.assert_array_equal(det.xy[0, 1, 0], shifted)
    # Exactly the mapped keypoints are present; every other slot (undetected in the file, or a
    # keypoint coco18 has no slot for) is missing with xy 0.
    assert set(np.flatnonzero(det.score[0, 0, 0])) == set(mapping.values())
    np.testing.assert_array_equal(det.score[0, 0, 1], np.eye(18, dtype=np.float32)[0])
    assert not det.score[1, 0].any() and not det.xy[1, 0].any()
    if K == 18:
        # Spelled out: OpenPose's neck (1) is our 17, its right shoulder (2) our 6.
        assert COCO18.keypoints[17] == "neck" and COCO18.keypoints[6] == "r_shoulder"
        np.testing.assert_array_equal(det.xy[0, 0, 0, 17], [30.0, 40.0])
        np.testing.assert_array_equal(det.xy[0, 0, 0, 6], [50.0, 60.0])
        assert det.score[0, 0, 0, 17] == np.float32(0.8)


# Files of the other layouts Pose2Sim reads, by their documented indices (the sources are cited
# in tests/test_skeletons.py, DOCUMENTED_INDICES): K, the source layout passed (None: from the
# count), the layout they are read as, {file index: coco18 keypoint}, and a point coco18 has no
# slot for (a face, hand, foot or head point).
WHOLE_BODY_FILES = [
    (133, None, "coco133", {0: "nose", 5: "l_shoulder", 6: "r_shoulder", 15: "l_ankle"}, 100),
    (135, None, "body135", {0: "nose", 5: "l_shoulder", 6: "r_shoulder", 9: "l_wrist"}, 70),
    (136, None, "halpe136", {0: "nose", 5: "l_shoulder", 6: "r_shoulder", 18: "neck"}, 120),
    (68, None, "halpe68", {3: "l_ear", 5: "l_shoulder", 6: "r_shoulder", 18: "neck"}, 50),
    (33, None, "blazepose", {0: "nose", 11: "l_shoulder", 12: "r_shoulder", 28: "r_ankle"}, 31),
    (16, None, "mpii", {0: "r_ankle", 12: "r_shoulder", 13: "l_shoulder", 15: "l_wrist"}, 9),
    (25, "body25b", "body25b", {2: "r_eye", 5: "l_shoulder", 6: "r_shoulder"}, 18),
]


@pytest.mark.parametrize(
    "K, source_layout, layout, mapping, extra",
    WHOLE_BODY_FILES,
    ids=[row[2] for row in WHOLE_BODY_FILES],
)
def test_whole_body_files_are_read_by_count_or_source_layout(
    tmp_path, K, source_layout, layout, mapping, extra
):
    rng = np.random.default_rng(K)
    person = {k: (*rng.uniform(0, 1000, 2).round(2), 0.5 + 0.1 * i) for i, k in enumerate(mapping)}
    person[extra] = (7.0, 8.0, 0.99)
    root = _tiny_folder(tmp_path / "op", K, person)
    kwargs = {"source_layout": source_layout} if source_layout else {}
    rec = load_recording(root, **kwargs)
    assert rec.layout == "coco18"
    xy, score = rec.detections.xy[0, 0, 0], rec.detections.score[0, 0, 0]
    for k, name in mapping.items():
        np.testing.assert_allclose(xy[COCO18.index(name)], person[k][:2], rtol=1e-6)
        assert score[COCO18.index(name)] == np.float32(person[k][2])
    present = set(mapping.values())
    if "neck" not in present:  # the neck is the shoulders' midpoint, at the lower score
        ls, rs = (
            next(k for k, n in mapping.items() if n == s) for s in ("l_shoulder", "r_shoulder")
        )
        mid = (np.array(person[ls][:2]) + np.array(person[rs][:2])) / 2
        np.testing.assert_allclose(xy[COCO18.index("neck")], mid, rtol=1e-6)
        assert score[COCO18.index("neck")] == np.float32(min(person[ls][2], person[rs][2]))
        present.add("neck")
    # The extra point is dropped: only the mapped keypoints (and the built neck) are present.
    assert {COCO18.keypoints[k] for k in np.flatnonzero(score)} == present
    # Read in the files' own layout, every point is carried.
    own = read_openpose(root, layout=layout, **kwargs)
    assert own.layout == layout and own.detections.xy.shape[-2] == K
    np.testing.assert_array_equal(own.detections.xy[0, 0, 0, extra], [7.0, 8.0])
    assert own.detections.score[0, 0, 0, extra] == np.float32(0.99)


def test_a_wrong_source_layout_names_the_file_and_the_layouts_of_the_count(tmp_path):
    root = _tiny_folder(tmp_path / "op", 133, {0: (1.0, 2.0, 0.9)})
    with pytest.raises(InputError, match="files of 133 keypoints are coco133") as e:
        read_openpose(root, source_layout="body135")
    assert "layout 'body135' has 135 keypoints" in str(e.value)
    assert (e.value.camera, e.value.frame) == ("a", 0)
    assert e.value.file.endswith("clipA_000000000000_keypoints.json")
    body = _tiny_folder(tmp_path / "body", 25, {0: (1.0, 2.0, 0.9)})
    with pytest.raises(InputError, match="files of 25 keypoints are body25 or body25b"):
        read_openpose(body, source_layout="mpii")


def test_layout_options(tmp_path):
    body = _tiny_folder(tmp_path / "body", 25, BODY25_PERSON)
    as_body25 = read_openpose(body, layout="body25")
    assert as_body25.layout == "body25"
    np.testing.assert_array_equal(
        as_body25.detections.xy[0, 0, 0, 19], BODY25_PERSON[19][:2]
    )  # the file's own slots
    coco = _tiny_folder(tmp_path / "coco", 18, COCO_PERSON)
    # 18 keypoints that already follow the project's order: no remapping.
    as_is = load_recording(coco, source_layout="coco18")
    np.testing.assert_array_equal(as_is.detections.xy[0, 0, 0, 1], COCO_PERSON[1][:2])
    # coco18 -> coco17 drops the neck.
    assert read_openpose(coco, layout="coco17").detections.score.shape[-1] == 17
    with pytest.raises(InputError, match="layout 'body25' has 25 keypoints") as e:
        read_openpose(coco, source_layout="body25")
    assert e.value.camera == "a" and e.value.frame == 0
    assert e.value.field == "people[0].pose_keypoints_2d"
    # An unknown count names the file and suggests source_layout.
    _write_frame(tmp_path / "odd" / "a" / "0_keypoints.json", [[1.0, 2.0, 0.5] * 20])
    with pytest.raises(InputError, match="source_layout") as e:
        read_openpose(tmp_path / "odd")
    assert e.value.file.endswith("0_keypoints.json")
    # Counts must agree across files.
    _write_frame(tmp_path / "coco" / "b" / "clipB_000000000002_keypoints.json", [[0.0] * 75])
    _write_frame(tmp_path / "coco" / "a" / "clipA_000000000002_keypoints.json", [])
    with pytest.raises(InputError, match="25 keypoints") as e:
        read_openpose(tmp_path / "coco")
    assert (e.value.camera, e.value.frame) == ("b", 2)


def _recording(layout: str = "coco18") -> tuple[Recording, object]:
    rig = load_rig("panoptic5")
    rec = generate_recording(rig, num_people=2, num_frames=3, seed=0)
    if layout != "coco18":
        from mvpose_jax.data import convert_layout

        rec = convert_layout(rec, layout)
    return rec, rig


def _assert_same_detections(a: Recording, b: Recording) -> None:
    assert a.cameras == b.cameras and a.layout == b.layout
    P = a.detections.score.shape[2]
    np.testing.assert_array_equal(a.detections.count, b.detections.count)
    assert int(np.max(b.detections.count)) == P  # readers pad to what the files hold
    np.testing.assert_array_equal(a.detections.score, b.detections.score[:, :, :P])
    np.testing.assert_array_equal(a.detections.xy, b.detections.xy[:, :, :P])
    assert a.detections.xy.dtype == np.float32 and a.detections.score.dtype == np.float32


@pytest.mark.parametrize("layout", ["coco18", "body25", "coco17"])
def test_round_trip(tmp_path, layout):
    rec, rig = _recording(layout)
    save_openpose(rec, tmp_path / "op")
    if layout == "coco18":  # written in OpenPose's own order, which OpenPose tools expect
        f, c = np.argwhere(rec.detections.count > 0)[0]
        file = tmp_path / "op" / rec.cameras[c] / f"{f:012d}_keypoints.json"
        person = json.loads(file.read_text())["people"][0]["pose_keypoints_2d"]
        np.testing.assert_allclose(
            person[3:5], rec.detections.xy[f, c, 0, 17], rtol=1e-6
        )  # OpenPose index 1 = the neck
    back = load_recording(tmp_path / "op", layout=layout, rig=rig)
    _assert_same_detections(back, Recording(rec.detections, rec.cameras, rec.layout))
    save_recording(rec, tmp_path / "again", format="openpose")  # the same through save_recording
    _assert_same_detections(load_recording(tmp_path / "again", layout=layout), back)
    # Writing again over the same folder is fine (every file is replaced) ...
    save_openpose(rec, tmp_path / "op")
    # ... but a folder holding other frames is refused: they would be read back as frames.
    fewer = Recording(
        Detections(*(np.asarray(a)[:2] for a in rec.detections)), rec.cameras, rec.layout
    )
    save_openpose(fewer, tmp_path / "fewer")
    with pytest.raises(InputError, match="other frame file"):
        save_openpose(fewer, tmp_path / "op")


def test_frame_numbers(tmp_path):
    """Numbers from the names align cameras (gaps are no frames); else natural sorted order."""
    p = [[1.0, 2.0, 0.5] * 18]
    for cam, prefix in (("a", "x"), ("b", "other_7_")):  # a digit run elsewhere in the name
        for n in (5, 12, 100):
            name = f"{prefix}{n:012d}_keypoints.json"
            _write_frame(tmp_path / "num" / cam / name, p * (n % 3 + 1))
    rec = read_openpose(tmp_path / "num")
    np.testing.assert_array_equal(rec.detections.count, [[3, 3], [1, 1], [2, 2]])
    for n in (2, 10, 1):
        _write_frame(tmp_path / "plain" / "a" / f"{n}.json", p * n)
        _write_frame(tmp_path / "plain" / "b" / f"f{n}.json", p * n)
    rec = read_openpose(tmp_path / "plain")
    np.testing.assert_array_equal(rec.detections.count[:, 0], [1, 2, 10])  # 2 before 10
    # Mixing named and unnamed files would misalign cameras: refused, naming the file.
    _write_frame(tmp_path / "num" / "b" / "extra.json", p)
    with pytest.raises(InputError, match="no such name") as e:
        read_openpose(tmp_path / "num")
    assert e.value.file.endswith("extra.json") and e.value.camera == "b"
    # Two files for one frame of one camera.
    (tmp_path / "num" / "b" / "extra.json").unlink()
    _write_frame(tmp_path / "num" / "b" / "y_12_keypoints.json", p)
    with pytest.raises(InputError, match="two files for frame 12") as e:
        read_openpose(tmp_path / "num")
    assert (e.value.camera, e.value.frame) == ("b", 12)


def test_missing_frames(tmp_path):
    root = _tiny_folder(tmp_path / "op", 18, COCO_PERSON)
    (root / "b" / "clipB_000000000001_keypoints.json").unlink()
    with pytest.raises(InputError, match="missing_frames='empty'") as e:
        load_recording(root)
    assert (e.value.camera, e.value.frame, e.value.field) == ("b", 1, "frames")
    assert "clipA_000000000001_keypoints.json" in str(e.value)  # which camera has it
    rec = load_recording(root, missing_frames="empty")
    np.testing.assert_array_equal(rec.detections.count, [[2, 1], [0, 0]])
    full = load_recording(_tiny_folder(tmp_path / "full", 18, COCO_PERSON))
    np.testing.assert_array_equal(rec.detections.xy[0], full.detections.xy[0])
    # A camera folder with no files at all misses every frame.
    (root / "c").mkdir()
    with pytest.raises(InputError) as e:
        load_recording(root, cameras=["c", "a"])
    assert (e.value.camera, e.value.frame) == ("c", 0)
    assert load_recording(root, missing_frames="empty").detections.count[:, 2].tolist() == [0, 0]
    with pytest.raises(InputError, match="missing_frames"):
        read_openpose(root, missing_frames="skip")


def test_entries_without_keypoints_are_skipped_and_counted(tmp_path):
    """An empty pose_keypoints_2d list (real detectors) and an empty object (Pose2Sim's person
    association) are no person: the others keep their values, the count says how many."""
    root = _tiny_folder(tmp_path / "op", 18, COCO_PERSON)
    full = load_recording(root)
    target = root / "a" / "clipA_000000000000_keypoints.json"
    doc = json.loads(target.read_text())
    empty = {"person_id": [-1], "pose_keypoints_2d": [], "face_keypoints_2d": []}
    doc["people"] = [empty, doc["people"][0], {}, doc["people"][1]]
    target.write_text(json.dumps(doc))
    (root / "b" / "clipB_000000000001_keypoints.json").write_text(json.dumps({"people": [{}]}))
    with OpenPoseStream(root) as stream:
        assert stream.report().total_empty == 0  # nothing read yet
        rec = stream.read_frames(0, 2)
        stream.read_frames(0, 1)  # reading a frame again does not count it twice
        report = stream.report()
    assert dict(report.empty_entries) == {"a": 2, "b": 1}
    assert report.total_empty == 3 and report.total_missing == 0
    assert report.lines() == ["3 skeleton entries without keypoints skipped (a 2, b 1)"]
    np.testing.assert_array_equal(rec.detections.count, [[2, 1], [0, 0]])
    np.testing.assert_array_equal(rec.detections.xy[0], full.detections.xy[0])
    np.testing.assert_array_equal(rec.detections.score[0], full.detections.score[0])
    # An entry with other fields but no body keypoints is still an error, named by its index in
    # the file (not its row after the skipped entries).
    doc["people"] = [{}, {"face_keypoints_2d": [1.0, 2.0, 0.5]}]
    target.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="missing field") as e:
        load_recording(root)
    assert e.value.field == "people[1].pose_keypoints_2d"


def test_skeletons_partly_outside_the_image_are_taken_as_they_are(tmp_path):
    root = tmp_path / "op"
    outside = {0: (-42.5, 520.25, 1.0), 1: (16.75, -3.5, 1.0), 5: (70.0, 80.0, 1.0)}
    for cam in ("a", "b"):
        _write_frame(root / cam / "x_0_keypoints.json", [_flat(18, outside)])
    rec = load_recording(root, layout="openpose_coco18")
    np.testing.assert_array_equal(
        rec.detections.xy[0, 0, 0, [0, 1, 5]], [v[:2] for v in outside.values()]
    )
    np.testing.assert_array_equal(rec.detections.score[0, 0, 0, [0, 1, 5]], [1.0, 1.0, 1.0])


def test_missing_frames_are_counted_per_camera(tmp_path):
    root = _tiny_folder(tmp_path / "op", 18, COCO_PERSON)
    (root / "b" / "clipB_000000000001_keypoints.json").unlink()
    with OpenPoseStream(root, missing_frames="empty") as stream:
        report = stream.report()
    assert dict(report.missing_frames) == {"a": 0, "b": 1}
    assert report.lines() == ["frames without a file, read as nobody seen: b 1"]


@pytest.mark.parametrize(
    "values",
    [
        ["a=cam_1,b=cam_2 c=cam_3"],
        ["a=cam_1", "b=cam_2", "c=cam_3"],  # nargs="+"
        [["a=cam_1"], ["b=cam_2, c=cam_3"]],  # action="append", nargs="+"
        [["a=cam_1", "b=cam_2"], ["c=cam_3", "a=cam_1"]],  # the same pair twice
    ],
)
def test_parse_camera_map_takes_commas_spaces_and_repeated_options(values):
    assert parse_camera_map(values) == {"a": "cam_1", "b": "cam_2", "c": "cam_3"}


@pytest.mark.parametrize(
    "values, match",
    [
        ([["a=cam_1"], ["a=cam_2"]], "'a' is given two cameras"),
        (["a=cam_1 b"], "FOLDER=CAMERA"),
        (["=cam_1"], "FOLDER=CAMERA"),
        (["a="], "FOLDER=CAMERA"),
        (["a=b=c"], "FOLDER=CAMERA"),
    ],
)
def test_parse_camera_map_errors_name_the_option(values, match):
    with pytest.raises(InputError, match=match) as e:
        parse_camera_map(values)
    assert e.value.field == "--camera-map"


def test_cameras_and_rig(tmp_path):
    rig = load_rig("panoptic5")
    root = tmp_path / "op"
    for cam in ("trackerc", "trackera", "kitchen"):
        _write_frame(root / cam / "0_keypoints.json", [])
    with pytest.raises(InputError) as e:
        load_recording(root, rig=rig)
    message = str(e.value)
    assert e.value.camera == "kitchen" and e.value.field == "cameras"
    assert "kitchen" in message and "trackera" in message and "trackere" in message
    rec = load_recording(root, rig=rig, cameras=["trackerc", "trackera"])
    assert rec.cameras == ("trackerc", "trackera")
    (root / "kitchen" / "0_keypoints.json").unlink()
    (root / "kitchen").rmdir()
    assert load_recording(root, rig=rig).cameras == ("trackera", "trackerc")  # the rig's order
    assert load_recording(root).cameras == ("trackera", "trackerc")  # sorted names
    with pytest.raises(InputError, match="no camera folder") as e:
        load_recording(root, cameras=["trackerb"])
    assert e.value.camera == "trackerb"
    # The rig check applies to single-file formats too.
    rec, _ = _recording()
    save_recording(rec, tmp_path / "r.npz")
    with pytest.raises(InputError, match="not cameras of the rig") as e:
        load_recording(tmp_path / "r.npz", rig=load_rig("arplab6"))
    assert e.value.camera == "trackere"  # arplab6 has trackera-d


def test_bad_values_name_file_frame_camera_field(tmp_path):
    root = _tiny_folder(tmp_path / "op", 18, COCO_PERSON)
    target = root / "b" / "clipB_000000000001_keypoints.json"
    doc = json.loads(target.read_text())
    doc["people"][0]["pose_keypoints_2d"][3 * 4 + 2] = 1.51  # keypoint 4's confidence
    target.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"score 1.51 is outside \[0, 1.5\]") as e:
        load_recording(root)
    err = e.value
    assert (err.file, err.frame, err.camera) == (str(target), 1, "b")
    assert err.field == "people[0].pose_keypoints_2d[keypoint 4].c"
    text = json.dumps(json.loads(_tiny_text(root)))
    target.write_text(text.replace("30.0", "NaN", 1))
    with pytest.raises(InputError, match="not finite") as e:
        load_recording(root)
    assert e.value.field == "people[0].pose_keypoints_2d[keypoint 1]"
    for bad, field in (
        ({"people": [{"pose_keypoints_2d": [1, 2]}]}, "people[0].pose_keypoints_2d"),
        ({"people": [{"pose_keypoints_2d": [1, "2", 3]}]}, "people[0].pose_keypoints_2d[1]"),
        ({"people": [{"face_keypoints_2d": []}]}, "people[0].pose_keypoints_2d"),
        ({"people": [{}, {"pose_keypoints_2d": [1, 2]}]}, "people[1].pose_keypoints_2d"),
        ({"people": {}}, "people"),
        ({"version": 1.3}, "people"),
        ([], None),
    ):
        target.write_text(json.dumps(bad))
        with pytest.raises(InputError) as e:
            load_recording(root)
        assert (e.value.file, e.value.frame, e.value.camera, e.value.field) == (
            str(target),
            1,
            "b",
            field,
        )


def _tiny_text(root: Path) -> str:
    return (root / "a" / "clipA_000000000000_keypoints.json").read_text()


def test_folder_mistakes(tmp_path):
    _write_frame(tmp_path / "cam" / "0_keypoints.json", [])
    with pytest.raises(InputError, match="folder ABOVE"):
        load_recording(tmp_path / "cam")  # one camera's folder, not the root
    with pytest.raises(InputError, match="no such folder"):
        read_openpose(tmp_path / "nowhere")
    with pytest.raises(InputError, match="not a folder"):
        read_openpose(tmp_path / "cam" / "0_keypoints.json")
    (tmp_path / "empty" / "a").mkdir(parents=True)
    with pytest.raises(InputError, match="no frame files"):
        load_recording(tmp_path / "empty")
    rec, _ = _recording()
    save_recording(rec, tmp_path / "r.npz")
    with pytest.raises(InputError, match="OpenPose folders only") as e:
        load_recording(tmp_path / "r.npz", missing_frames="empty")
    assert e.value.field == "missing_frames"
    bad = Recording(rec.detections, ("a/b",) + rec.cameras[1:], rec.layout)
    with pytest.raises(InputError, match="folder name") as e:
        save_openpose(bad, tmp_path / "out")
    assert e.value.camera == "a/b" and not (tmp_path / "out").exists()


def test_scores_slightly_above_1_are_clipped_with_one_warning(tmp_path):
    from mvpose_jax.data.checks import ScoreClippedWarning

    # OpenPose heatmap peaks exceed 1: a real recording had five such keypoints (1.008-1.037).
    person = {**COCO_PERSON, 0: (10.0, 20.0, 1.037), 1: (30.0, 40.0, 1.008)}
    root = _tiny_folder(tmp_path / "op", 18, person)
    with pytest.warns(ScoreClippedWarning) as caught:
        rec = load_recording(root)
    assert len(caught) == 1  # one summary for the recording, not one per keypoint
    message = str(caught[0].message)
    assert "6 keypoint scores above 1" in message and "largest 1.037" in message
    assert str(root) in message
    score = np.asarray(rec.detections.score)
    assert score.max() == 1.0
    assert score[0, 0, 0, 0] == 1.0 and score[0, 0, 0, 17] == 1.0  # nose and neck, clipped


def test_scores_far_above_1_are_an_error_with_a_plain_number(tmp_path):
    root = _tiny_folder(tmp_path / "op", 18, {**COCO_PERSON, 2: (50.0, 60.0, 1.6)})
    with pytest.raises(InputError) as e:
        load_recording(root)
    assert "score 1.6 is outside [0, 1.5]" in str(e.value)
    assert "np.float" not in str(e.value)
    assert e.value.camera == "a" and e.value.frame == 0
    assert e.value.field == "people[0].pose_keypoints_2d[keypoint 2].c"


def test_nan_coordinates_with_score_0_are_missing_keypoints(tmp_path):
    nan = float("nan")
    root = _tiny_folder(
        tmp_path / "op", 18, {**COCO_PERSON, 3: (nan, nan, 0.0), 4: (nan, 7.0, 0.0)}
    )
    rec = load_recording(root)
    xy, score = np.asarray(rec.detections.xy), np.asarray(rec.detections.score)
    assert np.isfinite(xy).all()
    for op_index in (3, 4):  # OpenPose's r_elbow and r_wrist: missing, at 0 as every missing one
        ours = COCO18.index(("r_elbow", "r_wrist")[op_index - 3])
        assert score[0, 0, 0, ours] == 0 and (xy[0, 0, 0, ours] == 0).all()
    # A NaN on a keypoint the detector claims to have seen is still an error, named.
    bad = _tiny_folder(tmp_path / "bad", 18, {**COCO_PERSON, 3: (nan, nan, 0.4)})
    with pytest.raises(InputError, match="not finite") as e:
        load_recording(bad)
    assert e.value.camera == "a" and e.value.field == "people[0].pose_keypoints_2d[keypoint 3]"


def test_pose2sim_style_folders_map_to_the_rig_and_strays_can_be_skipped(tmp_path):
    rec, rig = _recording()
    save_openpose(rec, tmp_path / "op")
    for cam in rec.cameras:  # Pose2Sim names its folders cam01_json, ...
        (tmp_path / "op" / cam).rename(tmp_path / "op" / f"{cam}_json")
    stray = tmp_path / "op" / "extra_cam"
    stray.mkdir()
    (stray / "000000000000_keypoints.json").write_text("{ not json")  # never read when skipped
    with pytest.raises(InputError, match="not cameras of the rig") as e:
        load_recording(tmp_path / "op", rig=rig)
    assert "extra_cam" in str(e.value) and "--camera-map" in str(e.value)
    back = load_recording(tmp_path / "op", rig=rig, cameras=list(rec.cameras))
    assert back.cameras == rec.cameras
    _assert_same_detections(back, rec)
    # An explicit map, for names no rule can guess; its cameras can be selected by their names.
    for i, cam in enumerate(rec.cameras):
        (tmp_path / "op" / f"{cam}_json").rename(tmp_path / "op" / f"view{i}")
    cmap = {f"view{i}": cam for i, cam in enumerate(rec.cameras)}
    two = load_recording(tmp_path / "op", rig=rig, camera_map=cmap, cameras=list(rec.cameras[:2]))
    assert two.cameras == rec.cameras[:2]
    with pytest.raises(InputError, match="camera map names folder 'nope'"):
        load_recording(tmp_path / "op", camera_map={"nope": "x"}, cameras=["x"])
    with pytest.raises(InputError, match="camera_map applies to OpenPose folders only"):
        save_recording(rec, tmp_path / "r.npz")
        load_recording(tmp_path / "r.npz", camera_map={"a": "b"})


# --------------------------------------------------------------------------- reading in ranges


@pytest.fixture(scope="module")
def long_folder(tmp_path_factory):
    """A 12-frame, 5-camera OpenPose folder (BODY_25 files) with a gap: camera trackerb lacks
    frames 5 and 6, and no camera sees anybody in frames 0-2 (so the files' layout is learnt
    only from frame 3 on), plus the folder names tools give (trackera_json ...)."""
    rec = generate_recording(load_rig("panoptic5"), num_people=3, num_frames=12, seed=2)
    root = tmp_path_factory.mktemp("long_op") / "op"
    save_openpose(rec, root, layout="body25")
    for cam in rec.cameras:
        for f in range(3):
            _write_frame(root / cam / f"{f:012d}_keypoints.json", [])
    for f in (5, 6):
        (root / "trackerb" / f"{f:012d}_keypoints.json").unlink()
    for cam in rec.cameras:
        (root / cam).rename(root / f"{cam}_json")
    return root


@pytest.mark.parametrize("chunk", [1, 2, 5, 12])
@pytest.mark.parametrize(
    "options",
    [
        {},
        {"cameras": ["trackere", "trackerb"]},
        {"camera_map": {"trackera_json": "A", "trackerb_json": "B"}, "cameras": ["B", "A"]},
        {"layout": "body25"},
    ],
    ids=["rig order", "cameras", "camera map", "body25"],
)
def test_openpose_read_in_ranges_equals_the_whole_folder(long_folder, chunk, options):
    """Range by range (only the range's files parsed), with camera selection, a camera map,
    missing frames read as empty and the layout learnt from the first person met: the ranges
    joined are what load_recording reads."""
    from tests.helpers import read_in_chunks

    if "camera_map" in options:
        options = {**options, "rig": None}
    else:
        options = {**options, "rig": load_rig("panoptic5")}
    whole = load_recording(long_folder, missing_frames="empty", **options)
    joined, sizes = read_in_chunks(long_folder, chunk, missing_frames="empty", **options)
    assert joined.cameras == whole.cameras and joined.layout == whole.layout
    for a, b in zip(joined.detections, whole.detections, strict=True):
        np.testing.assert_array_equal(a, np.asarray(b))
    assert max(sizes) == np.shape(whole.detections.score)[2]


def test_openpose_ranges_parse_only_their_files_and_name_frames_absolutely(
    long_folder, tmp_path, monkeypatch
):
    import shutil

    from mvpose_jax.data import open_recording, openpose

    root = tmp_path / "op"
    shutil.copytree(long_folder, root)
    bad = root / "trackerd_json" / f"{10:012d}_keypoints.json"
    doc = json.loads(bad.read_text())
    doc["people"][0]["pose_keypoints_2d"][0] = float("nan")
    doc["people"][0]["pose_keypoints_2d"][2] = 0.5
    bad.write_text(json.dumps(doc))
    parsed = []
    people = openpose._people
    monkeypatch.setattr(
        openpose, "_people", lambda path, *a: parsed.append(path) or people(path, *a)
    )
    rig = load_rig("panoptic5")
    with open_recording(root, rig=rig, missing_frames="empty") as stream:
        assert stream.streamed and stream.num_frames == 12
        assert not parsed  # opening lists the folders, it reads no frame
        stream.read_frames(4, 8)
        assert sorted({int(p.name[:12]) for p in parsed}) == [4, 5, 6, 7]
        with pytest.raises(InputError) as e:
            stream.read_frames(8, 12)
    assert e.value.frame == 10 and e.value.camera == "trackerd_json"
    assert e.value.file == str(bad)
    with pytest.raises(InputError) as whole:
        load_recording(root, rig=rig, missing_frames="empty")
    assert str(whole.value) == str(e.value)


def test_openpose_ranges_give_one_clipping_warning_per_folder(tmp_path):
    from mvpose_jax.data import open_recording
    from mvpose_jax.data.checks import ScoreClippedWarning

    person = {**COCO_PERSON, 0: (10.0, 20.0, 1.037)}
    root = _tiny_folder(tmp_path / "op", 18, person)
    with pytest.warns(ScoreClippedWarning) as caught, open_recording(root) as stream:
        parts = [r for _, r in stream.chunks(1)]
    assert len(parts) == 2 and len(caught) == 1  # one for the folder, not one per range
    with pytest.warns(ScoreClippedWarning) as whole:
        load_recording(root)
    assert str(caught[0].message) == str(whole[0].message)
    assert "3 keypoint scores above 1" in str(caught[0].message)
