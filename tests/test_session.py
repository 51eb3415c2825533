"""jobs/session.py and `infer --session`: a Pose2Sim project reconstructed trial by trial, seen in
rerun, scored without labels; the `view` and `score` commands on any result."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mvpose_jax.cli import main
from mvpose_jax.data import save_openpose
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.poses import load_poses
from mvpose_jax.synthetic import generate_recording
from tests.helpers import toml_text

# Detection folders named unlike the calibration's cameras: paired by sorted position.
FOLDERS = ("cam01_json", "cam02_json", "cam03_json", "cam04_json", "cam05_json")


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> tuple[Path, dict]:
    """session / participant / trial, three config levels, two trials (2 and 1 people), one
    skeleton entry without keypoints and one keypoint outside the image."""
    rig = load_rig("panoptic5")
    root = tmp_path_factory.mktemp("p2s") / "S00_Session"
    (root / "S00_Calibration").mkdir(parents=True)
    (root / "S00_Calibration" / "Calib_synthetic.toml").write_text(toml_text(rig))
    (root / "Config.toml").write_text(
        "[project]\nframe_rate = 25\nframe_range = []\n[pose]\npose_model = 'COCO'\n"
    )
    (root / "P01").mkdir()
    (root / "P01" / "Config.toml").write_text("[project]\nframe_rate = 30\n")
    trials = {}
    for name, people, seed in (("T01_two", 2, 5), ("T02_one", 1, 6)):
        rec = generate_recording(rig, num_people=people, num_frames=12, seed=seed)
        pose = root / "P01" / name / "pose"
        save_openpose(rec, pose)
        for cam, folder in zip(rec.cameras, FOLDERS, strict=True):
            (pose / cam).rename(pose / folder)
        (root / "P01" / name / "Config.toml").write_text("[pose]\npose_model = 'COCO'\n")
        trials[name] = rec
    # What real detectors write: an entry with no keypoints, a keypoint outside the image.
    first = sorted((root / "P01" / "T01_two" / "pose" / FOLDERS[0]).iterdir())[0]
    doc = json.loads(first.read_text())
    doc["people"].insert(0, {"person_id": [-1], "pose_keypoints_2d": []})
    doc["people"][1]["pose_keypoints_2d"][0:3] = [-12.5, -3.0, 1.0]
    first.write_text(json.dumps(doc))
    return root, trials


def test_infer_session_reconstructs_every_trial(project, tmp_path, capsys):
    root, trials = project
    out = tmp_path / "out"
    assert main(["infer", "--session", str(root), "--out", str(out), "--view"]) == 0
    text = capsys.readouterr().out
    # The pairing is printed, by sorted position.
    for folder, cam in zip(FOLDERS, trials["T01_two"].cameras, strict=True):
        assert f"{folder} -> {cam}" in text
    assert "30 fps" in text  # the participant's config overrides the session's
    assert "1 skeleton entries without keypoints skipped" in text
    for name, rec in trials.items():
        res = load_poses(out / name)
        assert len(res.confidence) == rec.num_frames
        people = len(np.unique(np.asarray(rec.identity)[np.asarray(rec.identity) >= 0]))
        assert res.poses.valid.sum(axis=1).max() == people
        trc = sorted(p.name for p in (out / name / "pose-3d").iterdir())
        if people == 1:
            assert trc == [f"{name}_0-12.trc"]
        else:
            assert trc == [f"{name}_P{k}_0-12.trc" for k in range(1, people + 1)]
        assert (out / name / "poses.rrd").is_file()
    # `--detections` on a trial folder does the same for that trial.
    assert (
        main(["infer", "--detections", str(root / "P01" / "T02_one"), "--out", str(tmp_path / "t")])
        == 0
    )
    a, b = load_poses(tmp_path / "t" / "T02_one"), load_poses(out / "T02_one")
    np.testing.assert_array_equal(a.poses.xyz, b.poses.xyz)


def test_a_session_refuses_options_it_reads_itself(project, tmp_path, capsys):
    root, _ = project
    argv = ["infer", "--session", str(root), "--out", str(tmp_path / "x")]
    assert main([*argv, "--rig", "panoptic5"]) == 2
    assert "field '--rig'" in capsys.readouterr().err
    assert main([*argv, "--camera-map", "a=b"]) == 2
    assert "field '--camera-map'" in capsys.readouterr().err


def test_view_and_score_any_result(project, tmp_path, capsys):
    pytest.importorskip("rerun")
    root, trials = project
    out = tmp_path / "out"
    assert main(["infer", "--session", str(root / "P01" / "T01_two"), "--out", str(out)]) == 0
    calib = str(root / "S00_Calibration" / "Calib_synthetic.toml")
    dets = str(root / "P01" / "T01_two" / "pose")
    cmap = [f"{f}={c}" for f, c in zip(FOLDERS, trials["T01_two"].cameras, strict=True)]
    rrd = tmp_path / "v.rrd"
    args = ["--rig", calib, "--detections", dets, "--camera-map", *cmap]
    capsys.readouterr()
    assert main(["view", str(out / "T01_two"), *args, "--out", str(rrd)]) == 0
    assert rrd.is_file() and rrd.stat().st_size > 0
    report = tmp_path / "score.json"
    assert main(["score", str(out / "T01_two"), *args, "--json", str(report)]) == 0
    assert "within 20 px" in capsys.readouterr().out
    doc = json.loads(report.read_text())
    assert report.with_suffix(".png").is_file() and doc
