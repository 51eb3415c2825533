"""The ``score`` job (`mvpose_jax.jobs.score`): files in, the label-free report out."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from mvpose_jax.data import save_recording, select_cameras
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.poses import PoseResults, save_poses
from mvpose_jax.errors import InputError
from mvpose_jax.inference import run_pipeline
from mvpose_jax.jobs.common import DetectionsSource, RigSource
from mvpose_jax.jobs.score import ScoreConfig, run_score, summary_lines
from mvpose_jax.label_free import label_free_score, reference_reprojection
from mvpose_jax.lifting import members_from_identity
from mvpose_jax.skeletons import Detections, Poses3D
from mvpose_jax.synthetic import detection_variants, generate_recording

LAYOUT = "coco18"
RIG = "panoptic5"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 2-person synthetic recording (detector noise) and its exact version, on disk."""
    rig = load_rig(RIG)
    rec = generate_recording(rig, num_people=2, num_frames=6, seed=11)
    folder = tmp_path_factory.mktemp("scene")
    save_recording(rec, folder / "noisy.json", rig=rig)
    exact = detection_variants(rec)["projected"]
    save_recording(exact, folder / "exact.json", rig=rig)
    return rig, rec, exact, folder


def _truth_result(rec) -> PoseResults:
    gt = rec.ground_truth
    members = members_from_identity(np.asarray(rec.identity), gt.valid.shape[1])
    poses = Poses3D(
        np.asarray(gt.xyz, np.float32), np.asarray(gt.valid), np.asarray(gt.keypoint_valid)
    )
    ones = np.ones(gt.valid.shape, np.float32)
    return PoseResults(poses, ones, members, np.asarray(rec.identity), rec.cameras, LAYOUT)


def _config(poses, detections, out, **kw) -> ScoreConfig:
    return ScoreConfig(
        str(poses), RigSource(RIG), DetectionsSource(str(detections)), str(out), **kw
    )


def test_the_truth_on_exact_detections_scores_every_keypoint_within_0_px(scene, tmp_path):
    _, _, exact, folder = scene
    save_poses(_truth_result(exact), tmp_path / "truth")
    report, (json_path, png_path) = run_score(
        _config(tmp_path / "truth", folder / "exact.json", tmp_path / "score.json")
    )
    assert json_path == tmp_path / "score.json" and png_path == tmp_path / "score.png"
    assert png_path.stat().st_size > 0
    written = json.loads(json_path.read_text())
    assert written["share_of_all_within_px"]["20"] == pytest.approx(
        report.share_of_all_within_px["20"]
    )
    r = report.result.overall
    # Every keypoint a second camera can check (the others are unverifiable: result.blind).
    assert r.produced + r.blind == r.visible and r.median_px < 0.01 and r.visible > 100
    # The recording holds its ground truth: the noise floor is stated, and nil here.
    assert report.noise_floor is not None and report.noise_floor.overall.median_px < 0.01
    lines = summary_lines(report)
    # Every checkable keypoint of the people is hit; the false positives' keypoints and the
    # people's unverifiable ones are not.
    share = report.share_of_all_within_px["20"]
    assert share * int((np.asarray(exact.detections.score) > 0).sum()) == pytest.approx(r.produced)
    assert sum(report.unmatched_skeletons.values()) > 0 and share < 1.0
    assert any("read this first" in line and f"{100 * share:.1f} %" in line for line in lines)
    assert any(line.startswith("noise floor (detections") for line in lines)
    assert any("not tracked" in line for line in lines)


def test_a_pipeline_result_on_disk_scores_as_it_does_in_memory(scene, tmp_path):
    rig, rec, _, folder = scene
    result = run_pipeline(rig, rec.detections, layout=LAYOUT, method="robust")
    poses = PoseResults(
        result.poses,
        result.confidence,
        result.members,
        result.identity,
        result.cameras,
        LAYOUT,
        rec.timestamps,
        result.track,
    )
    save_poses(poses, tmp_path / "run")
    report, (json_path, png_path) = run_score(
        _config(tmp_path / "run" / "poses.json", folder / "noisy.json", tmp_path / "report")
    )
    assert json_path == tmp_path / "report" / "label_free.json" and png_path.exists()
    floor = reference_reprojection(
        rec.ground_truth.xyz,
        np.asarray(rec.ground_truth.keypoint_valid) & np.asarray(rec.ground_truth.valid)[..., None],
        rig,
        rec.detections,
        rec.identity,
        cameras=rec.cameras,
    )
    direct = label_free_score(poses, rig, rec.detections, layout=LAYOUT, noise_floor=floor)
    a, b = report.to_dict(), direct.to_dict()
    # The JSON poses file rounds to 0.1 mm: pixel numbers agree to a fraction of a pixel.
    assert a["result"]["overall"]["visible"] == b["result"]["overall"]["visible"]
    assert a["result"]["overall"]["produced"] == b["result"]["overall"]["produced"]
    assert a["result"]["overall"]["median_px"] == pytest.approx(
        b["result"]["overall"]["median_px"], abs=0.05
    )
    assert a["leave_one_out"] == b["leave_one_out"]  # from the detections alone
    assert a["noise_floor"] == b["noise_floor"]
    # Realistic detector noise: the truth itself is some pixels off the detections.
    assert report.noise_floor.overall.median_px > 1.0


def test_partial_results_are_scored_on_the_frames_they_cover(scene, tmp_path):
    _, _, exact, folder = scene
    full = _truth_result(exact)
    first = PoseResults(
        Poses3D(*(np.asarray(a)[:4] for a in full.poses)),
        full.confidence[:4],
        full.members[:4],
        full.identity[:4],
        full.cameras,
        LAYOUT,
        frames_total=6,
    )
    save_poses(first, tmp_path / "partial")
    report, _ = run_score(_config(tmp_path / "partial", folder / "exact.json", tmp_path / "o"))
    assert report.frames == 4 and report.result.overall.median_px < 0.01


def test_poses_whose_cameras_the_calibration_lacks_are_named(scene, tmp_path):
    _, _, exact, folder = scene
    renamed = dataclasses.replace(_truth_result(exact), cameras=("x",) + exact.cameras[1:])
    save_poses(renamed, tmp_path / "p")
    with pytest.raises(InputError) as e:
        run_score(_config(tmp_path / "p", folder / "exact.json", tmp_path / "o"))
    assert e.value.field == "cameras" and "'x'" in e.value.reason
    assert e.value.file.endswith("p")


def test_detections_of_another_length_are_named(scene, tmp_path):
    rig, _, exact, _ = scene
    save_poses(_truth_result(exact), tmp_path / "p")
    d = exact.detections
    shorter = dataclasses.replace(
        exact,
        detections=Detections(d.xy[:5], d.score[:5], d.count[:5]),
        ground_truth=Poses3D(*(np.asarray(a)[:5] for a in exact.ground_truth)),
        identity=exact.identity[:5],
        timestamps=None if exact.timestamps is None else exact.timestamps[:5],
        projected=None,
    )
    save_recording(shorter, tmp_path / "short.json", rig=rig)
    with pytest.raises(InputError) as e:
        run_score(_config(tmp_path / "p", tmp_path / "short.json", tmp_path / "o"))
    assert e.value.field == "frames" and e.value.file.endswith("short.json")
    assert "5 frames" in e.value.reason and "6 frames" in e.value.reason


def test_a_skeleton_the_detections_lack_is_named_with_frame_and_camera(scene, tmp_path):
    rig, _, exact, _ = scene
    truth = _truth_result(exact)
    save_poses(truth, tmp_path / "p")
    # Camera 2 of frame 3 loses its skeletons: the poses still use them.
    d = exact.detections
    count = np.asarray(d.count).copy()
    score = np.asarray(d.score).copy()
    count[3, 2] = 0
    score[3, 2] = 0
    fewer = dataclasses.replace(
        exact,
        detections=Detections(np.asarray(d.xy), score, count),
        identity=np.where(count[..., None] > np.arange(score.shape[2]), exact.identity, -1),
        projected=None,
    )
    save_recording(fewer, tmp_path / "fewer.json", rig=rig)
    with pytest.raises(InputError) as e:
        run_score(_config(tmp_path / "p", tmp_path / "fewer.json", tmp_path / "o"))
    assert e.value.field == "skeletons" and e.value.frame == 3
    assert e.value.camera == exact.cameras[2] and e.value.file.endswith("fewer.json")


def test_detections_without_one_of_the_poses_cameras_are_named(scene, tmp_path):
    rig, _, exact, _ = scene
    save_poses(_truth_result(exact), tmp_path / "p")
    save_recording(select_cameras(exact, exact.cameras[:3]), tmp_path / "three.json", rig=rig)
    with pytest.raises(InputError) as e:
        run_score(_config(tmp_path / "p", tmp_path / "three.json", tmp_path / "o"))
    assert e.value.field == "cameras" and e.value.camera == exact.cameras[3]
    assert e.value.file.endswith("three.json")
