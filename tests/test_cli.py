"""The user-facing commands infer, evaluate and render, on every detection format."""

from __future__ import annotations

import argparse
import json
import os
import re

import cv2
import numpy as np
import pytest

from mvpose_jax.cli import main
from mvpose_jax.data import load_recording, save_openpose, save_recording
from mvpose_jax.data.calibration import load_rig, save_rig
from mvpose_jax.data.poses import load_poses
from mvpose_jax.synthetic import generate_recording

COMMANDS = [
    "rig",
    "generate",
    "synthetic-figure",
    "convert",
    "train-matcher",
    "train-estimator",
    "infer",
    "evaluate",
    "render",
]


@pytest.fixture(scope="module")
def recording():
    return generate_recording(load_rig("panoptic5"), num_people=2, num_frames=4, seed=11)


@pytest.fixture(scope="module")
def files(recording, tmp_path_factory):
    """The recording in every input format the tools read."""
    root = tmp_path_factory.mktemp("formats")
    paths = {
        "native": root / "scene.json",
        "npz": root / "scene.npz",
        "original": root / "scene_original.json",
        "openpose": root / "openpose",
    }
    save_recording(recording, paths["native"])
    save_recording(recording, paths["npz"])
    save_recording(recording, paths["original"], format="original")
    save_openpose(recording, paths["openpose"])
    return paths


@pytest.mark.parametrize("fmt", ["native", "npz", "original", "openpose"])
def test_infer_reads_every_format(files, recording, fmt, tmp_path, capsys):
    out = tmp_path / "poses"
    assert (
        main(["infer", "--rig", "panoptic5", "--detections", str(files[fmt]), "--out", str(out)])
        == 0
    )
    assert "frames" in capsys.readouterr().out
    res = load_poses(out / "poses.npz")
    doc = json.loads((out / "poses.json").read_text())
    F = recording.num_frames
    assert doc["format"] == "mvpose-jax.poses" and len(doc["frames"]) == F
    assert res.poses.xyz.shape[0] == F and res.poses.valid.any()
    # The JSON and the npz say the same.
    from_json = load_poses(out / "poses.json")
    np.testing.assert_array_equal(
        from_json.poses.valid[:, : res.poses.valid.shape[1]], res.poses.valid
    )
    np.testing.assert_allclose(
        from_json.poses.xyz[:, : res.poses.valid.shape[1]], res.poses.xyz, atol=1e-4
    )
    assert sum(len(f["people"]) for f in doc["frames"]) == int(res.poses.valid.sum())
    person = next(p for f in doc["frames"] for p in f["people"])
    assert set(person["skeletons"]) <= set(recording.cameras) and len(person["keypoints"]) == 18


def test_infer_with_a_calibration_file_and_evaluate(files, recording, tmp_path, capsys):
    calib = tmp_path / "rig.json"
    save_rig(load_rig("panoptic5"), calib)
    out = tmp_path / "poses"
    assert (
        main(
            [
                "infer",
                "--rig",
                str(calib),
                "--detections",
                str(files["native"]),
                "--out",
                str(out),
                "--method",
                "centroid",
            ]
        )
        == 0
    )
    metrics = tmp_path / "metrics.json"
    assert (
        main(
            [
                "evaluate",
                "--rig",
                str(calib),
                "--detections",
                str(files["native"]),
                "--poses",
                str(out),
                "--out",
                str(metrics),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "MPJPE" in text and "ARI" in text and "trackera" in text
    m = json.loads(metrics.read_text())
    assert 0 < m["pose"]["mpjpe_mm"] < 60
    assert m["matching"]["ari"] > 0.9
    assert all(v["count"] > 0 for v in m["reprojection_px"].values())


def test_evaluate_without_ground_truth_gives_reprojection_only(files, recording, tmp_path, capsys):
    bare = tmp_path / "bare.json"
    rec = load_recording(files["native"])
    import dataclasses

    save_recording(dataclasses.replace(rec, ground_truth=None, identity=None, projected=None), bare)
    out = tmp_path / "poses"
    assert main(["infer", "--rig", "panoptic5", "--detections", str(bare), "--out", str(out)]) == 0
    assert (
        main(["evaluate", "--rig", "panoptic5", "--detections", str(bare), "--poses", str(out)])
        == 0
    )
    text = capsys.readouterr().out
    assert "reprojection error" in text and "MPJPE" not in text


def test_render_writes_images_video_and_3d_figures(files, tmp_path, capsys):
    out = tmp_path / "poses"
    assert (
        main(["infer", "--rig", "panoptic5", "--detections", str(files["npz"]), "--out", str(out)])
        == 0
    )
    pics = tmp_path / "render"
    assert (
        main(
            [
                "render",
                "--rig",
                "panoptic5",
                "--detections",
                str(files["npz"]),
                "--poses",
                str(out),
                "--frames",
                "0",
                "2",
                "--figures-3d",
                "--out",
                str(pics),
            ]
        )
        == 0
    )
    names = sorted(p.name for p in pics.iterdir())
    assert names == [
        "frame_000000.png",
        "frame_000000_3d.png",
        "frame_000002.png",
        "frame_000002_3d.png",
    ]
    img = cv2.imread(str(pics / "frame_000000.png"))
    assert img is not None and img.shape[0] > 100 and (img < 200).any(), "something was drawn"
    video = tmp_path / "poses.mp4"
    assert (
        main(
            [
                "render",
                "--rig",
                "panoptic5",
                "--detections",
                str(files["npz"]),
                "--poses",
                str(out),
                "--out",
                str(video),
            ]
        )
        == 0
    )
    cap = cv2.VideoCapture(str(video))
    frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cap.release()
    assert frames == 4


def test_bad_input_is_one_clear_line(files, tmp_path, capsys):
    out = tmp_path / "poses"
    assert (
        main(
            [
                "infer",
                "--rig",
                "panoptic5",
                "--detections",
                str(tmp_path / "missing.json"),
                "--out",
                str(out),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "missing.json" in err and "Traceback" not in err
    assert not out.exists()
    assert (
        main(
            [
                "render",
                "--rig",
                "panoptic5",
                "--detections",
                str(files["npz"]),
                "--poses",
                str(tmp_path),
                "--out",
                str(tmp_path / "r"),
            ]
        )
        == 2
    )
    assert "poses.npz" in capsys.readouterr().err


def test_every_command_is_tested_below():
    from mvpose_jax.cli import _COMMANDS

    assert sorted(_COMMANDS) == sorted(COMMANDS)


@pytest.mark.parametrize("name", COMMANDS)
def test_every_command_explains_every_option(name, capsys):
    with pytest.raises(SystemExit):
        main([name, "--help"])
    text = capsys.readouterr().out
    import re

    options = set(re.findall(r"(--[a-z0-9-]+)", text.split("options:")[1]))
    for opt in options - {"--help"}:
        # every option is followed by some help text somewhere after its first mention
        assert re.search(re.escape(opt) + r"[^\n]*\n?\s+\S", text), opt


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert re.fullmatch(r"mvpose-jax \S+\n", capsys.readouterr().out)


@pytest.mark.parametrize("name", COMMANDS)
def test_every_option_with_a_default_shows_it(name):
    from mvpose_jax.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[
        name
    ]
    text = sub.format_help().split("options:", 1)[1]
    for action in sub._actions:
        if action.default in (None, False, argparse.SUPPRESS) or action.nargs == 0:
            continue
        opt = action.option_strings[-1]
        after = text.split(opt + " ", 1)[1]
        block = re.split(r"\n  -", after, maxsplit=1)[0]  # this option's help, up to the next
        assert "default" in block, (name, opt, block)


def test_render_fps_comes_from_the_recording():
    from mvpose_jax.cli import _recording_fps

    assert _recording_fps(np.arange(10) / 30.0) == pytest.approx(30.0)
    assert _recording_fps(np.arange(10) / 12.5) == pytest.approx(12.5)
    assert _recording_fps(None) == 30.0


def test_rig_warnings_and_unit_errors_are_one_plain_line(tmp_path, capsys):
    from tests.helpers import toml_text

    path = tmp_path / "Calib.toml"
    path.write_text(toml_text(load_rig("arplab6"), scale=1e-3))  # millimetres
    assert main(["rig", "--rig", str(path)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mvpose-jax: warning: ")
    assert "--translation-scale 0.001" in err[0]
    assert main(["rig", "--rig", str(path), "--translation-scale", "0.001"]) == 0
    assert capsys.readouterr().err == ""
    assert main(["rig", "--rig", str(path), "--translation-scale", "0"]) == 2
    assert "translation scale must be a positive number" in capsys.readouterr().err


def test_outputs_are_checked_before_any_work(files, tmp_path, capsys):
    a_file = tmp_path / "taken"
    a_file.write_text("x")
    args = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"]), "--out"]
    assert main([*args, str(a_file)]) == 2
    err = capsys.readouterr().err
    assert "is a file, but an output folder must go here" in err and str(a_file) in err
    assert main([*args, str(a_file / "below")]) == 2
    assert "is a file, so nothing can be written below it" in capsys.readouterr().err
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if not os.access(locked, os.W_OK):  # root may write anywhere: then only the above holds
            assert main([*args, str(locked / "poses")]) == 2
            assert "permission denied" in capsys.readouterr().err
    finally:
        locked.chmod(0o700)
    out = tmp_path / "scene.json"
    assert main(["generate", "--rig", "panoptic5", "--frames", "2", "--out", str(tmp_path)]) == 2
    assert "is a folder, but an output file must go here" in capsys.readouterr().err
    assert not out.exists()


def test_a_mistyped_model_folder_is_an_error_and_creates_nothing(files, tmp_path, capsys):
    missing = tmp_path / "estimatr"
    args = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"]), "--out"]
    assert main([*args, str(tmp_path / "p"), "--estimator", str(missing)]) == 2
    assert "not a trained model (no such folder" in capsys.readouterr().err
    assert not missing.exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([*args, str(tmp_path / "p"), "--matcher", str(empty)]) == 2
    assert "no best/ checkpoint folder" in capsys.readouterr().err
    assert list(empty.iterdir()) == []


@pytest.mark.parametrize(
    "extra, reason",
    [
        (["--min-views", "9"], "--min-views 9, but no frame has skeletons in more than 5"),
        (["--threshold", "1.5"], "--threshold 1.5: match scores lie in [0, 1]"),
    ],
)
def test_a_recording_without_people_says_which_setting(files, tmp_path, capsys, extra, reason):
    args = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"]), "--out"]
    assert main([*args, str(tmp_path / "p"), *extra]) == 0
    err = capsys.readouterr().err
    assert "mvpose-jax: warning: no person in any frame: " in err and reason in err


def test_training_commands_read_openpose_folders(tmp_path, capsys):
    from mvpose_jax.cli import _recordings_in
    from mvpose_jax.synthetic import generate_single_person_recordings

    recs = generate_single_person_recordings(
        load_rig("panoptic5"), num_recordings=3, num_frames=6, seed=2
    )
    train = tmp_path / "train"
    save_openpose(recs[0], train / "walk_a")  # an OpenPose folder: one recording
    save_recording(recs[1], train / "walk_b.npz")
    save_recording(recs[2], train / "more" / "walk_c.json")
    found = _recordings_in(str(train), None)
    assert len(found) == 3
    from mvpose_jax.features import single_person_samples

    in_order = [recs[2], recs[0], recs[1]]  # sorted by path: more/, walk_a/, walk_b.npz
    for rec, want in zip(found, in_order, strict=True):  # the same people (OpenPose drops padding)
        got, expected = single_person_samples([rec]), single_person_samples([want])
        np.testing.assert_allclose(got[0], expected[0], atol=1e-3)
        np.testing.assert_allclose(got[1], expected[1], atol=1e-4)
    assert len(_recordings_in(str(train / "walk_a"), None)) == 1  # the folder itself
    out = tmp_path / "est"
    args = ["train-estimator", "--rig", "panoptic5", "--train", str(train), "--out", str(out)]
    assert main([*args, "--steps", "2", "--batch-size", "8"]) == 0
    assert (out / "best").is_dir()


def test_convert_between_every_format(files, recording, tmp_path, capsys):
    steps = [
        (files["npz"], tmp_path / "op", "openpose"),
        (tmp_path / "op", tmp_path / "scene.json", "native"),
        (tmp_path / "scene.json", tmp_path / "orig.json", "original"),
        (tmp_path / "orig.json", tmp_path / "back.npz", None),
    ]
    for src, dst, fmt in steps:
        args = ["convert", "--detections", str(src), "--out", str(dst)]
        assert main(args + (["--format", fmt] if fmt else [])) == 0, capsys.readouterr().err
    capsys.readouterr()
    back = load_recording(tmp_path / "back.npz")
    assert back.cameras == recording.cameras and back.layout == recording.layout
    np.testing.assert_array_equal(back.detections.count, recording.detections.count)
    for f, c in zip(*np.nonzero(np.asarray(recording.detections.count)), strict=True):
        n = int(recording.detections.count[f, c])
        np.testing.assert_allclose(
            back.detections.score[f, c, :n], recording.detections.score[f, c, :n], atol=1e-4
        )
        seen = np.asarray(recording.detections.score[f, c, :n]) > 0
        np.testing.assert_allclose(
            np.asarray(back.detections.xy[f, c, :n])[seen],
            np.asarray(recording.detections.xy[f, c, :n])[seen],
            atol=1e-3,
        )
    # Camera selection and a layout conversion on the way.
    assert (
        main(
            [
                "convert",
                "--detections",
                str(files["npz"]),
                "--out",
                str(tmp_path / "two.npz"),
                "--cameras",
                recording.cameras[1],
                recording.cameras[0],
                "--layout",
                "coco17",
            ]
        )
        == 0
    )
    two = load_recording(tmp_path / "two.npz")
    assert two.cameras == (recording.cameras[1], recording.cameras[0]) and two.layout == "coco17"


def test_infer_reads_pose2sim_folders_and_skips_stray_cameras(recording, tmp_path, capsys):
    import shutil

    root = tmp_path / "session"
    save_openpose(recording, root)
    for i, cam in enumerate(recording.cameras):
        shutil.move(root / cam, root / f"view{i}")
    (root / "uncalibrated").mkdir()
    (root / "uncalibrated" / "000000000000_keypoints.json").write_text("{ broken")
    cmap = ",".join(f"view{i}={cam}" for i, cam in enumerate(recording.cameras))
    args = ["infer", "--rig", "panoptic5", "--detections", str(root), "--out", str(tmp_path / "p")]
    assert main([*args, "--camera-map", cmap, "--cameras", *recording.cameras]) == 0
    assert load_poses(tmp_path / "p").cameras == recording.cameras
    capsys.readouterr()
    assert main([*args, "--camera-map", cmap]) == 2  # the stray folder, named
    assert "uncalibrated" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*args, "--camera-map", "view0"])
    assert "expected FOLDER=CAMERA" in capsys.readouterr().err


def test_source_layout_reaches_the_openpose_reader(tmp_path, capsys):
    import json as json_

    # 17 keypoints per person could be coco17; --source-layout says which layout the files use.
    root = tmp_path / "op"
    for cam in ("a", "b"):
        (root / cam).mkdir(parents=True)
        doc = {"people": [{"pose_keypoints_2d": [10.0, 20.0, 0.9] + [0.0] * 48}]}
        (root / cam / "000000000000_keypoints.json").write_text(json_.dumps(doc))
    out = tmp_path / "r.npz"
    args = ["convert", "--detections", str(root), "--out", str(out)]
    assert main([*args, "--source-layout", "coco17", "--layout", "coco17"]) == 0
    assert load_recording(out).layout == "coco17"
    assert main([*args, "--source-layout", "body25"]) == 2  # 17 numbers are not BODY_25's 25
    assert "body25" in capsys.readouterr().err


# --------------------------------------------------------------------------- streaming infer


@pytest.fixture(scope="module")
def long_files(tmp_path_factory):
    """A 13-frame recording as npz and as an OpenPose folder (chunks of 4: 4 + 4 + 4 + 1)."""
    rec = generate_recording(load_rig("panoptic5"), num_people=3, num_frames=13, seed=5)
    root = tmp_path_factory.mktemp("long")
    save_recording(rec, root / "scene.npz")
    save_openpose(rec, root / "openpose")
    return rec, root


def _infer_args(detections, out, *extra):
    return ["infer", "--rig", "panoptic5", "--detections", str(detections), "--out", str(out)] + [
        "--chunk-frames",
        "4",
        *extra,
    ]


def _same_results(a, b):
    for field in ("confidence", "members", "identity", "timestamps", "cameras", "layout"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    for field in ("xyz", "valid", "keypoint_valid"):
        np.testing.assert_array_equal(getattr(a.poses, field), getattr(b.poses, field), field)


def test_infer_streams_the_recording_and_equals_the_whole_run(
    long_files, tmp_path, monkeypatch, capsys
):
    """infer reads the npz a chunk at a time (never the whole file) and writes what the
    whole-recording library path writes, array for array and byte for byte in the JSON."""
    from mvpose_jax.data import npz
    from mvpose_jax.data.poses import PoseResults, save_poses
    from mvpose_jax.inference import run_pipeline

    rec, root = long_files
    rig = load_rig("panoptic5")
    whole = load_recording(root / "scene.npz")
    res = run_pipeline(rig, whole.detections, chunk_frames=4)
    save_poses(
        PoseResults(
            res.poses,
            res.confidence,
            res.members,
            res.identity,
            res.cameras,
            whole.layout,
            whole.timestamps,
        ),
        tmp_path / "whole",
    )
    ranges = []
    read_frames = npz.NpzStream.read_frames

    def spy(self, start, stop):
        ranges.append((start, stop))
        return read_frames(self, start, stop)

    def whole_read(*args, **kwargs):
        raise AssertionError("infer read the whole recording")

    monkeypatch.setattr(npz.NpzStream, "read_frames", spy)
    monkeypatch.setattr(npz, "read_npz", whole_read)
    assert main(_infer_args(root / "scene.npz", tmp_path / "out")) == 0
    assert ranges == [(0, 4), (4, 8), (8, 12), (12, 13)]
    assert "13 frames" in capsys.readouterr().out
    streamed = load_poses(tmp_path / "out")
    assert not streamed.partial and streamed.frames_total is None
    _same_results(streamed, load_poses(tmp_path / "whole"))
    text = (tmp_path / "out" / "poses.json").read_text()
    assert text == (tmp_path / "whole" / "poses.json").read_text()
    assert not (tmp_path / "out" / "chunks").exists()  # removed once the results are written


def _interrupt_on_chunk(monkeypatch, chunk: int, error: BaseException):
    """The 3D stage raises ``error`` on the given chunk (0-based), once."""
    from mvpose_jax import inference

    calls = []
    original = inference.poses_of_members

    def flaky(*args, **kwargs):
        calls.append(1)
        if len(calls) == chunk + 1:
            raise error
        return original(*args, **kwargs)

    monkeypatch.setattr(inference, "poses_of_members", flaky)


@pytest.mark.parametrize("source", ["scene.npz", "openpose"])
def test_ctrl_c_keeps_finished_chunks_as_partial_results_and_resume_finishes(
    long_files, tmp_path, monkeypatch, capsys, source
):
    _, root = long_files
    detections = root / source
    assert main(_infer_args(detections, tmp_path / "whole")) == 0
    full = load_poses(tmp_path / "whole")

    out = tmp_path / "out"
    with monkeypatch.context() as m:
        _interrupt_on_chunk(m, 2, KeyboardInterrupt())
        assert main(_infer_args(detections, out)) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "frames 0-7 of 13" in err and "--resume" in err
    # A valid partial result: the two finished chunks, marked partial, in both files.
    for name in ("poses.npz", "poses.json"):
        part = load_poses(out / name)
        assert part.partial and part.frames_total == 13 and len(part.confidence) == 8
        G = part.poses.valid.shape[1]
        np.testing.assert_array_equal(part.poses.valid, full.poses.valid[:8, :G])
        np.testing.assert_allclose(part.poses.xyz, full.poses.xyz[:8, :G], atol=1e-4)
    doc = json.loads((out / "poses.json").read_text())
    assert doc["partial"] is True and doc["frames_total"] == 13 and len(doc["frames"]) == 8
    assert sorted(p.name for p in (out / "chunks").iterdir()) == [
        "chunk_000000.npz",
        "chunk_000001.npz",
        "manifest.json",
    ]

    computed = []
    from mvpose_jax import inference

    original = inference.poses_of_members
    monkeypatch.setattr(
        inference,
        "poses_of_members",
        lambda *a, **k: computed.append(1) or original(*a, **k),
    )
    assert main(_infer_args(detections, out, "--resume")) == 0
    assert "resuming at frame 8 of 13" in capsys.readouterr().out
    assert len(computed) == 2  # chunks 2 and 3 only
    resumed = load_poses(out)
    assert not resumed.partial
    _same_results(resumed, full)
    assert (out / "poses.json").read_text() == (tmp_path / "whole" / "poses.json").read_text()
    assert not (out / "chunks").exists()


@pytest.mark.parametrize(
    "changed, option",
    [
        (["--threshold", "0.3"], "--threshold"),
        (["--chunk-frames", "5"], "--chunk-frames"),
        (["--min-views", "3"], "--min-views"),
        (["--cameras", "trackera", "trackerb", "trackerc"], "--cameras"),
        (["--method", "centroid"], "--method"),
    ],
)
def test_resume_refuses_changed_settings_naming_them(
    long_files, tmp_path, monkeypatch, capsys, changed, option
):
    _, root = long_files
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        _interrupt_on_chunk(m, 1, KeyboardInterrupt())
        assert main(_infer_args(root / "scene.npz", out)) == 130
    capsys.readouterr()
    assert main(_infer_args(root / "scene.npz", out, "--resume", *changed)) == 2
    err = capsys.readouterr().err
    assert f"field '{option}'" in err and "unfinished run" in err and "without --resume" in err
    # Nothing was lost: the chunk and the partial results are still there.
    assert (out / "chunks" / "chunk_000000.npz").exists() and load_poses(out).partial


def test_infer_without_resume_starts_over_and_says_so(long_files, tmp_path, monkeypatch, capsys):
    _, root = long_files
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        _interrupt_on_chunk(m, 1, KeyboardInterrupt())
        assert main(_infer_args(root / "scene.npz", out)) == 130
    capsys.readouterr()
    assert main(_infer_args(root / "scene.npz", out, "--keep-chunks")) == 0
    assert "held 1 finished chunk(s) of an earlier unfinished run" in capsys.readouterr().err
    assert not load_poses(out).partial
    assert len(list((out / "chunks").glob("chunk_*.npz"))) == 4  # --keep-chunks


def test_an_input_error_mid_run_keeps_the_chunks_before_it(long_files, tmp_path, capsys):
    """A bad OpenPose file in frame 9: the error names frame 9 (not its place in the chunk), the
    first two chunks are written as partial results, and once fixed --resume finishes."""
    import shutil

    _, root = long_files
    folder = tmp_path / "openpose"
    shutil.copytree(root / "openpose", folder)
    bad = folder / "trackerc" / f"{9:012d}_keypoints.json"
    good = bad.read_text()
    doc = json.loads(good)
    doc["people"][0]["pose_keypoints_2d"][2] = 7.0  # a score of 7
    bad.write_text(json.dumps(doc))
    out = tmp_path / "out"
    assert main(_infer_args(folder, out)) == 2
    err = capsys.readouterr().err
    assert "frame 9, camera 'trackerc'" in err and "score 7.0" in err
    assert "frames 0-7 of 13" in err and "--resume" in err
    assert load_poses(out).frames_total == 13 and len(load_poses(out).confidence) == 8
    bad.write_text(good)
    assert main(_infer_args(folder, out, "--resume")) == 0
    assert "resuming at frame 8" in capsys.readouterr().out
    assert main(_infer_args(folder, tmp_path / "whole")) == 0
    _same_results(load_poses(out), load_poses(tmp_path / "whole"))


def test_ctrl_c_before_the_first_chunk_and_evaluating_partial_results(
    long_files, tmp_path, monkeypatch, capsys
):
    _, root = long_files
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        _interrupt_on_chunk(m, 0, KeyboardInterrupt())
        assert main(_infer_args(root / "scene.npz", out)) == 130
    assert "no frame of 13 (no chunk had finished)" in capsys.readouterr().err
    empty = load_poses(out)
    assert empty.partial and empty.frames_total == 13 and len(empty.confidence) == 0
    with monkeypatch.context() as m:
        _interrupt_on_chunk(m, 1, KeyboardInterrupt())
        assert main(_infer_args(root / "scene.npz", out)) == 130
    capsys.readouterr()
    args = ["evaluate", "--rig", "panoptic5", "--detections", str(root / "scene.npz")]
    assert main(args + ["--poses", str(out)]) == 2
    err = capsys.readouterr().err
    assert "poses have 4 frames" in err and "partial results" in err and "--resume" in err
