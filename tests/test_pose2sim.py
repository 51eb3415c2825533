"""Pose2Sim projects read as they are: trials, merged configs, calibration, pairing by position.

Most tests write a small Pose2Sim-style project themselves; the last ones read Pose2Sim's own demo
session from ../shared/real when it is there (skipped otherwise).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.formats import open_recording
from mvpose_jax.data.pose2sim import (
    POSE_MODELS,
    find_trials,
    is_pose2sim_project,
    merge_configs,
    open_trial,
    trc_name,
)
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import get_layout

K25B = get_layout("body25b").num_keypoints  # 25
# The calibration's cameras in the file's order, which is not their sorted order: Pose2Sim pairs
# the sorted detection folders with them by position.
CAMERAS = ("north", "east", "south")
FOLDERS = ("vid_a_json", "vid_b_json", "vid_c_json")
DEMO = Path(__file__).resolve().parents[2] / "shared" / "real" / "pose2sim-demo-s00"


def _calibration_toml(cameras=CAMERAS) -> str:
    out = []
    for i, name in enumerate(cameras):
        out += [
            f"[cam_{i + 1}]",
            f'name = "{name}"',
            "size = [ 1920.0, 1080.0,]",
            "matrix = [ [ 1000.0, 0.0, 960.0,], [ 0.0, 1000.0, 540.0,], [ 0.0, 0.0, 1.0,],]",
            "distortions = [ 0.0, 0.0, 0.0, 0.0,]",
            f"rotation = [ 0.0, {0.3 * i}, 0.0,]",
            f"translation = [ {i - 1.0}, 0.5, 4.0,]",
            "fisheye = false",
            "",
        ]
    return "\n".join(out + ["[metadata]", "adjusted = false", "error = 0.0", ""])


def _person(seed: float) -> list[float]:
    """A BODY_25B skeleton: keypoint k at (seed + 10 k, 2 seed + 5 k), score 0.5 + k / 100."""
    return [v for k in range(K25B) for v in (seed + 10.0 * k, 2 * seed + 5.0 * k, 0.5 + k / 100)]


def _write(path: Path, doc) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))


def _frames(pose: Path, people_of, num_frames: int = 4) -> None:
    """One OpenPose folder per camera folder; people_of(camera index, frame) -> entries."""
    for c, folder in enumerate(FOLDERS):
        for f in range(num_frames):
            people = people_of(c, f)
            if people is not None:
                name = f"{folder[:5]}_{f:012d}_keypoints.json"
                _write(pose / folder / name, {"version": 1.3, "people": people})


def _entry(flat: list[float]) -> dict:
    return {"person_id": [-1], "pose_keypoints_2d": flat, "face_keypoints_2d": []}


def _t1_people(c: int, f: int):
    if (c, f) == (2, 2):
        return None  # camera vid_c_json has no file for frame 2
    people = [_entry(_person(100.0 * c + f))]
    if (c, f) == (0, 1):
        people.insert(0, _entry([]))  # what real detectors write
    if (c, f) == (1, 3):
        flat = _person(7.0)
        flat[0:3] = [-42.5, -3.25, 1.0]  # a keypoint outside the image, score 1
        people.append(_entry(flat))
    return people


@pytest.fixture
def project(tmp_path) -> Path:
    """session / participant / trial, three config levels with overrides, two calibration folders
    (the first sorted is used, its first sorted .toml), folders named unlike the cameras."""
    s = tmp_path / "session"
    _write(
        s / "Config.toml",
        "[project]\nframe_rate = 50\nframe_range = []\n"
        "exclude_from_batch = ['P1/T9_excluded']\n\n"
        "[pose]\npose_model = 'BODY_25B'\n\n"
        "[filtering.butterworth]\norder = 4\ncut_off_frequency = 6\n",
    )
    _write(s / "A_Calib" / "calib_a.toml", _calibration_toml())
    _write(s / "A_Calib" / "calib_b.toml", "not a calibration [")  # later in sorted order
    _write(s / "B_calibration" / "calib.toml", "not a calibration either [")
    _write(
        s / "P1" / "Config.toml", "[project]\nframe_rate = 30\n[filtering.butterworth]\norder = 2\n"
    )
    _write(s / "P1" / "T1" / "Config.toml", "[project]\nframe_range = [1, 3]\n")
    _frames(s / "P1" / "T1" / "pose", _t1_people)
    (s / "P1" / "T1" / "pose" / "notes").mkdir()  # no "json" in its name: not a camera
    # T2: no Config.toml of its own; Pose2Sim's association output comes before pose/.
    _frames(s / "P1" / "T2" / "pose", lambda c, f: [_entry(_person(1.0))])
    _frames(s / "P1" / "T2" / "pose-associated", lambda c, f: [_entry(_person(2.0)), {}])
    _frames(s / "P1" / "T9_excluded" / "pose", lambda c, f: [])
    _write(
        s / "P2" / "T3" / "Config.toml",
        "[project]\nframe_rate = 'auto'\n[pose]\npose_model = 'halpe_26'\n",
    )
    _frames(s / "P2" / "T3" / "pose-sync", lambda c, f: [])
    return s


def test_trials_are_found_in_sorted_order_and_excluded_ones_listed(project):
    session = find_trials(project)
    assert session.root == project
    assert [t.name for t in session.trials] == ["T1", "T2", "T3"]
    assert session.excluded == (project / "P1" / "T9_excluded",)
    t1, t2, t3 = session.trials
    assert t1.detections == project / "P1" / "T1" / "pose"
    assert t2.detections == project / "P1" / "T2" / "pose-associated"
    assert t3.detections == project / "P2" / "T3" / "pose-sync"
    for trial in session.trials:
        assert trial.calibration == project / "A_Calib" / "calib_a.toml"
    # A participant folder: its trials, with the session's settings above it.
    participant = find_trials(project / "P1")
    assert participant.root == project
    assert [t.name for t in participant.trials] == ["T1", "T2"]
    # A trial given alone is read even when the session excludes it from batches.
    alone = find_trials(project / "P1" / "T9_excluded")
    assert [t.name for t in alone.trials] == ["T9_excluded"] and alone.excluded == ()
    assert alone.trials[0].config_files == (project / "Config.toml", project / "P1" / "Config.toml")


def test_is_pose2sim_project(project, tmp_path):
    for folder in (project, project / "P1", project / "P1" / "T1"):
        assert is_pose2sim_project(folder)
    assert not is_pose2sim_project(project / "P1" / "T1" / "pose")  # an OpenPose folder
    assert not is_pose2sim_project(project / "P1" / "T1" / "Config.toml")
    assert not is_pose2sim_project(tmp_path / "nowhere")
    bare = tmp_path / "bare"
    _frames(bare / "pose", lambda c, f: [])  # a trial's shape but no Config.toml anywhere
    assert not is_pose2sim_project(bare)
    with pytest.raises(InputError, match="not a Pose2Sim project"):
        find_trials(bare)


def test_deeper_configs_override_key_by_key(project):
    t1, t2, t3 = find_trials(project).trials
    assert t1.config_files == (
        project / "Config.toml",
        project / "P1" / "Config.toml",
        project / "P1" / "T1" / "Config.toml",
    )
    assert t1.config["project"]["frame_rate"] == 30  # the participant's
    assert t1.config["project"]["frame_range"] == [1, 3]  # the trial's
    assert t1.config["project"]["exclude_from_batch"] == ["P1/T9_excluded"]  # the session's
    assert t1.config["filtering"]["butterworth"] == {"order": 2, "cut_off_frequency": 6}
    assert (t1.fps, t1.frame_range) == (30.0, (1, 3))
    assert (t2.fps, t2.frame_range) == (30.0, None)
    assert t3.config["filtering"]["butterworth"] == {"order": 4, "cut_off_frequency": 6}
    assert t3.fps is None and any("'auto'" in note for note in t3.notes)
    assert (t1.pose_model, t1.source_layout) == ("BODY_25B", "body25b")
    assert (t3.pose_model, t3.source_layout) == ("halpe_26", "halpe26")  # any case


def test_merge_configs_leaves_its_inputs_alone():
    base = {"a": {"b": 1, "c": {"d": 2}}, "e": [1]}
    over = {"a": {"c": {"d": 3, "f": 4}}, "e": [2]}
    assert merge_configs(base, over) == {"a": {"b": 1, "c": {"d": 3, "f": 4}}, "e": [2]}
    assert base == {"a": {"b": 1, "c": {"d": 2}}, "e": [1]}
    assert over == {"a": {"c": {"d": 3, "f": 4}}, "e": [2]}


def test_camera_folders_pair_with_the_calibration_by_sorted_position(project):
    t1 = find_trials(project).trials[0]
    assert dict(t1.camera_map) == dict(zip(FOLDERS, CAMERAS, strict=True))
    assert t1.pairing_lines() == [
        "vid_a_json -> north",
        "vid_b_json -> east",
        "vid_c_json -> south",
    ]
    text = t1.describe()
    assert "vid_b_json -> east" in text and "30 fps" in text and "body25b" in text


def test_folders_named_after_other_cameras_are_paired_by_position_with_a_note(project):
    """Pose2Sim's rule is position, even when the names say otherwise: the pairing follows the
    rule and a note says which names disagree."""
    pose = project / "P1" / "T1" / "pose"
    for folder, camera in zip(FOLDERS, ("east_json", "north_json", "south_json"), strict=True):
        (pose / folder).rename(pose / camera)
    t1 = find_trials(project).trials[0]
    assert t1.pairing_lines() == [
        "east_json -> north",
        "north_json -> east",
        "south_json -> south",
    ]
    assert len(t1.notes) == 2 and "though camera east has its name" in t1.notes[0]


def test_the_trial_reads_as_written(project):
    """Empty keypoint lists skipped and counted, negative coordinates kept, a missing frame read
    as nobody seen and counted, cameras in the rig's order through the pairing."""
    t1 = find_trials(project).trials[0]
    rig = load_rig(t1.calibration)
    assert rig.names == CAMERAS
    with pytest.raises(InputError, match=r"folders \['notes'\] are not cameras of the rig"):
        open_recording(t1.detections, rig=rig, camera_map=t1.camera_map)  # every subfolder
    assert t1.cameras == CAMERAS
    with open_recording(
        t1.detections,
        rig=rig,
        cameras=t1.cameras,
        camera_map=t1.camera_map,
        source_layout=t1.source_layout,
        layout="body25b",
        missing_frames="empty",
    ) as stream:
        assert stream.cameras == CAMERAS and stream.num_frames == 4
        rec = stream.read_frames(0, 4)
        report = stream.report()
    with open_trial(t1, layout="body25b") as same:
        assert same.cameras == CAMERAS
        _assert_same(same.read_frames(0, 4), rec)
        assert same.report() == report
    assert dict(report.empty_entries) == {"north": 1, "east": 0, "south": 0}
    assert dict(report.missing_frames) == {"north": 0, "east": 0, "south": 1}
    det = rec.detections
    want_count = [[1, 1, 1], [1, 1, 1], [1, 1, 0], [1, 2, 1]]
    np.testing.assert_array_equal(det.count, want_count)
    for c in range(3):
        for f in range(4):
            if (c, f) == (2, 2):
                continue
            flat = np.array(_person(100.0 * c + f)).reshape(K25B, 3)
            np.testing.assert_allclose(det.xy[f, c, 0], flat[:, :2], rtol=1e-6)
            np.testing.assert_allclose(det.score[f, c, 0], flat[:, 2], rtol=1e-6)
    np.testing.assert_allclose(det.xy[3, 1, 1, 0], [-42.5, -3.25])
    assert det.score[3, 1, 1, 0] == 1.0
    assert t1.frame_span(stream.num_frames) == (1, 3)
    assert trc_name(t1.name, *t1.frame_span(4)) == "T1_1-3.trc"


def _assert_same(a, b) -> None:
    assert (a.cameras, a.layout) == (b.cameras, b.layout)
    for x, y in zip(a.detections, b.detections, strict=True):
        np.testing.assert_array_equal(x, y)


def test_trc_names_follow_pose2sim():
    assert trc_name("S00_P00_T01_BalancingTrial", 0, 100) == "S00_P00_T01_BalancingTrial_0-100.trc"
    assert trc_name("T", 10, 300, person=2) == "T_P2_10-300.trc"


def test_frame_range_beyond_the_recording_names_the_config(project):
    _write(project / "P1" / "T1" / "Config.toml", "[project]\nframe_range = [5, 9]\n")
    t1 = find_trials(project).trials[0]
    assert t1.frame_span(10) == (5, 9) and t1.frame_span(7) == (5, 7)
    with pytest.raises(InputError, match="holds none") as e:
        t1.frame_span(4)
    assert e.value.file == str(project / "P1" / "T1" / "Config.toml")
    assert e.value.field == "[project] frame_range"


def test_a_folder_count_mismatch_names_both_lists(project):
    (project / "P1" / "T1" / "pose" / "vid_d_json").mkdir()
    with pytest.raises(InputError) as e:
        find_trials(project)
    message = str(e.value)
    assert "['vid_a_json', 'vid_b_json', 'vid_c_json', 'vid_d_json']" in message
    assert "['north', 'east', 'south']" in message
    assert e.value.file == str(project / "P1" / "T1" / "pose")
    assert e.value.field == "cameras"


@pytest.mark.parametrize(
    "text, field, match",
    [
        ("[pose]\npose_model = 'SUPER_POSE'\n", "[pose] pose_model", "unknown pose model"),
        ("[pose]\npose_model = 25\n", "[pose] pose_model", "unknown pose model"),
        ("[project]\nframe_rate = 'fast'\n", "[project] frame_rate", "positive number"),
        ("[project]\nframe_rate = -60\n", "[project] frame_rate", "positive number"),
        ("[project]\nframe_range = [3, 1]\n", "[project] frame_range", "first < stop"),
        ("[project]\nframe_range = 'some'\n", "[project] frame_range", "first < stop"),
        ("[project]\nexclude_from_batch = 'T1'\n", "[project] exclude_from_batch", "list"),
    ],
)
def test_bad_settings_name_the_config_and_field(project, text, field, match):
    config = project / "P1" / "T2" / "Config.toml"
    _write(config, text)
    with pytest.raises(InputError, match=match) as e:
        find_trials(project)
    assert (e.value.file, e.value.field) == (str(config), field)


def test_every_pose2sim_model_maps_to_a_layout():
    for model, layout in POSE_MODELS.items():
        assert get_layout(layout).name == layout, model
    assert POSE_MODELS["COCO"] == "openpose_coco18"  # OpenPose's 18, in OpenPose's order


def test_calibration_problems_are_clear(project):
    for f in (project / "A_Calib").iterdir():
        f.unlink()
    with pytest.raises(InputError, match="holds no .toml") as e:
        find_trials(project)
    assert e.value.file == str(project / "A_Calib")
    (project / "A_Calib").rmdir()
    with pytest.raises(InputError, match="malformed TOML") as e:  # the next folder's is read
        find_trials(project)
    assert e.value.file == str(project / "B_calibration" / "calib.toml")
    _write(project / "B_calibration" / "calib.toml", _calibration_toml())
    assert find_trials(project).trials[0].calibration == project / "B_calibration" / "calib.toml"
    for f in (project / "B_calibration").iterdir():
        f.unlink()
    (project / "B_calibration").rmdir()
    with pytest.raises(InputError, match="no calibration") as e:
        find_trials(project)
    assert e.value.field == "calibration"


# --------------------------------------------------------------------------- Pose2Sim's own demo

needs_demo = pytest.mark.skipif(not DEMO.is_dir(), reason="../shared/real/pose2sim-demo-s00 absent")
DEMO_TRIALS = {  # trial -> frames
    "S00_P00_T00_StaticTrial": 12,
    "S00_P00_T01_BalancingTrial": 100,
    "S00_P01_T00_StaticTrialParticipant1": 12,
    "S00_P01_T01_StaticTrialParticipant2": 12,
    "S00_P01_T02_Participants1-2": 100,
}


@needs_demo
def test_the_demo_session_is_found_with_pose2sim_settings():
    session = find_trials(DEMO)
    assert [t.name for t in session.trials] == list(DEMO_TRIALS)
    for trial in session.trials:
        assert trial.calibration == DEMO / "S00_Calibration" / "Calib_qualisys.toml"
        assert trial.detections.name == "pose-associated"
        assert trial.pairing_lines() == [f"cam0{i}_json -> cam_0{i}" for i in range(1, 5)]
        assert (trial.fps, trial.source_layout, trial.frame_range) == (60.0, "body25b", None)
        # Pose2Sim's own TRC of this trial has the name we give ours.
        trc = trc_name(trial.name, 0, DEMO_TRIALS[trial.name])
        if trial.name != "S00_P01_T02_Participants1-2":
            assert (trial.folder / "pose-3d" / trc).is_file()
    multi = session.trials[-1]
    assert multi.config["project"]["multi_person"] is True  # the trial's own override
    assert (multi.folder / "pose-3d" / trc_name(multi.name, 0, 100, person=1)).is_file()


@needs_demo
@pytest.mark.parametrize("pose_folders", [("pose-associated",), ("pose",)])
def test_every_demo_trial_reads_every_frame(pose_folders):
    for trial in find_trials(DEMO, pose_folders=pose_folders).trials:
        with open_recording(
            trial.detections,
            rig=load_rig(trial.calibration),
            camera_map=trial.camera_map,
            source_layout=trial.source_layout,
            layout="coco18",
        ) as stream:
            assert stream.num_frames == DEMO_TRIALS[trial.name]
            rec = stream.read_frames(0, stream.num_frames)
            report = stream.report()
        assert rec.cameras == ("cam_01", "cam_02", "cam_03", "cam_04")
        # People per camera and frame as the files hold them, counted here independently.
        want = [
            [
                sum(
                    bool(person.get("pose_keypoints_2d"))
                    for person in json.loads(f.read_text())["people"]
                )
                for f in sorted((trial.detections / folder).glob("*.json"))
            ]
            for folder in trial.camera_map
        ]
        np.testing.assert_array_equal(rec.detections.count, np.array(want).T)
        assert report.total_missing == 0
        if trial.name == "S00_P01_T02_Participants1-2":
            # The README's real-world quirks: an empty pose_keypoints_2d list in pose/, empty
            # objects for people a camera does not see in Pose2Sim's association, and negative
            # coordinates with score 1 in camera 1.
            assert report.total_empty == (3 if pose_folders == ("pose-associated",) else 1)
            xy, score = rec.detections.xy[:, 0], rec.detections.score[:, 0]
            assert ((xy < 0).any(axis=-1) & (score == 1.0)).any()
