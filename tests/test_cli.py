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
from mvpose_jax.skeletons import get_layout
from mvpose_jax.synthetic import generate_recording

COMMANDS = [
    "rig",
    "generate",
    "synthetic-figure",
    "convert",
    "train-matcher",
    "train-estimator",
    "train-temporal",
    "adapt",
    "infer",
    "smooth",
    "evaluate",
    "render",
    "export",
    "view",
    "score",
    "batch",
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


def test_infer_robust_triangulation(files, tmp_path, capsys):
    outs = {}
    for method, extra in (("dlt", []), ("robust", ["--outlier-px", "25"])):
        out = outs[method] = tmp_path / method
        argv = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"]), "--out", str(out)]
        assert main(argv + ["--method", method, *extra]) == 0
    dlt, robust = (load_poses(outs[m] / "poses.npz") for m in ("dlt", "robust"))
    # Same people (same proposals), and the clean synthetic views keep robust close to DLT.
    np.testing.assert_array_equal(dlt.poses.valid, robust.poses.valid)
    both = robust.poses.keypoint_valid & dlt.poses.keypoint_valid
    assert both.any() and np.abs(robust.poses.xyz - dlt.poses.xyz)[both].max() < 0.2


@pytest.mark.slow  # trains an estimator for two steps
def test_infer_blend_of_estimator_and_robust_triangulation(files, tmp_path, capsys):
    # Untracked: the poses as the 3D stage gives them (tracked ones are filtered).
    base = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"]), "--no-track"]
    # The method and the estimator must go together; nothing is written otherwise.
    assert main([*base, "--out", str(tmp_path / "a"), "--method", "blend"]) == 2
    assert "--method blend needs --estimator" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    from mvpose_jax.synthetic import generate_single_person_recordings

    recs = generate_single_person_recordings(
        load_rig("panoptic5"), num_recordings=2, num_frames=6, seed=3
    )
    for i, rec in enumerate(recs):
        save_recording(rec, tmp_path / "train" / f"walk_{i}.npz")
    est = tmp_path / "est"
    train = ["train-estimator", "--rig", "panoptic5", "--train", str(tmp_path / "train")]
    assert main([*train, "--out", str(est), "--steps", "2", "--batch-size", "8"]) == 0
    with_est = [*base, "--estimator", str(est)]
    assert main([*with_est, "--out", str(tmp_path / "b"), "--method", "robust"]) == 2
    assert "would not use --estimator" in capsys.readouterr().err
    outs = {}
    for method, argv in (
        ("robust", [*base, "--method", "robust"]),
        ("mlp", [*with_est, "--method", "mlp"]),
        ("blend", with_est),  # the default with an estimator
    ):
        outs[method] = tmp_path / method
        assert main([*argv, "--out", str(outs[method])]) == 0
    robust, mlp, blend = (
        load_poses(outs[m] / "poses.npz").poses for m in ("robust", "mlp", "blend")
    )
    np.testing.assert_array_equal(blend.valid, mlp.valid)  # the same people ...
    assert blend.keypoint_valid[blend.valid].all()  # ... every keypoint, like the estimator ...
    tri = robust.keypoint_valid & blend.valid[..., None]
    assert tri.any()
    np.testing.assert_allclose(blend.xyz[tri], robust.xyz[tri], atol=1e-4)  # ... triangulated


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
    assert main([*args, "--camera-map", "view0"]) == 2
    assert "field '--camera-map': expected FOLDER=CAMERA" in capsys.readouterr().err
    # Pairs separated by spaces, and a repeated option: every pair counts.
    pairs = cmap.split(",")
    base = ["infer", "--rig", "panoptic5", "--detections", str(root)]
    base += ["--cameras", *recording.cameras]
    spaced = ["--camera-map", *pairs]
    repeated = [a for pair in pairs for a in ("--camera-map", pair)]
    for i, how in enumerate((spaced, repeated)):
        assert main([*base, *how, "--out", str(tmp_path / f"q{i}")]) == 0
        assert load_poses(tmp_path / f"q{i}").cameras == recording.cameras


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


def test_source_layout_help_names_every_layout_and_count():
    from mvpose_jax.cli import SOURCE_LAYOUT_HELP
    from mvpose_jax.data.openpose import LAYOUT_OF_COUNT
    from mvpose_jax.skeletons import LAYOUTS

    named = set(re.findall(r"[a-z][a-z0-9_]*\d[a-z0-9_]*|blazepose|mpii", SOURCE_LAYOUT_HELP))
    assert set(LAYOUTS) <= named
    for count, layout in LAYOUT_OF_COUNT.items():
        assert f"{count} {layout}" in SOURCE_LAYOUT_HELP
    assert "--source-layout body25b" in SOURCE_LAYOUT_HELP


# --------------------------------------------------------------------------- export


@pytest.fixture(scope="module")
def three_people(tmp_path_factory):
    """A 3-person recording, its inferred poses with tracks from the true identities, in
    shuffled slots: (recording, folder of tracked poses, PoseResults)."""
    import dataclasses

    from mvpose_jax.data.poses import save_poses

    root = tmp_path_factory.mktemp("three")
    rec = generate_recording(load_rig("panoptic5"), num_people=3, num_frames=6, seed=4)
    save_recording(rec, root / "scene.npz")
    args = ["infer", "--rig", "panoptic5", "--detections", str(root / "scene.npz")]
    assert main([*args, "--out", str(root / "poses")]) == 0
    res = load_poses(root / "poses")
    F, G, C = res.members.shape
    # each slot's person: the true identity its detections agree on
    track = np.full((F, G), -1, np.int32)
    for f, g in zip(*np.nonzero(res.poses.valid), strict=True):
        cams = np.nonzero(res.members[f, g] >= 0)[0]
        ids = rec.identity[f, cams, res.members[f, g, cams]]
        track[f, g] = np.bincount(ids[ids >= 0]).argmax()
    assert sorted(set(track[res.poses.valid].tolist())) == [0, 1, 2]
    order = np.stack([np.random.default_rng(f).permutation(G) for f in range(F)])
    rows = np.arange(F)[:, None]

    def shuffled(a):
        return None if a is None else np.asarray(a)[rows, order]

    tracked = dataclasses.replace(
        res,
        poses=type(res.poses)(*(shuffled(a) for a in res.poses)),
        confidence=shuffled(res.confidence),
        members=shuffled(res.members),
        track=shuffled(track),
    )
    save_poses(tracked, root / "tracked")
    return rec, root / "tracked", tracked


def _track_positions(res, track_id):
    """(F, K, 3) world metres of one track, NaN where absent."""
    F, G, K, _ = res.poses.xyz.shape
    out = np.full((F, K, 3), np.nan)
    for f, g in zip(*np.nonzero(res.poses.valid & (res.track == track_id)), strict=True):
        kv = res.poses.keypoint_valid[f, g]
        out[f, kv] = res.poses.xyz[f, g, kv]
    return out


def test_export_writes_trc_and_c3d_of_three_people_read_back_independently(
    three_people, tmp_path, capsys
):
    from mvpose_jax.data.exports import opensim_from_world
    from tests.helpers import read_c3d, read_trc

    rec, poses, res = three_people
    out = tmp_path / "opensim"
    args = ["export", "--poses", str(poses), "--format", "trc,c3d", "--format", "csv"]
    assert main([*args, "--rig", "panoptic5", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "wrote 7 files (mm, OpenSim axes (Y = up [0.0, -1.0, 0.0]))" in text
    R = opensim_from_world((0, -1, 0))  # panoptic5's calibrated up
    fps = 1 / np.median(np.diff(rec.timestamps))
    keypoints = list(get_layout(res.layout).keypoints)
    for t in (0, 1, 2):
        want = _track_positions(res, t)
        present = np.nonzero(~np.isnan(want[..., 0]).all(axis=1))[0]
        want = want[present[0] : present[-1] + 1]
        trc = read_trc(out / f"poses_track{t}.trc")
        c3d = read_c3d(out / f"poses_track{t}.c3d")
        assert trc["names"] == keypoints and c3d["labels"] == keypoints
        assert float(trc["header"]["DataRate"]) == pytest.approx(fps)
        assert c3d["rate"] == pytest.approx(fps)
        assert trc["frame"][0] == c3d["first_frame"] == present[0] + 1
        for got in (trc["xyz"], c3d["xyz"]):
            np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
            world = got / 1000 @ R  # undo the documented rotation and units
            np.testing.assert_allclose(world, want, atol=0.01e-3)  # 0.01 mm
    ezc3d = pytest.importorskip("ezc3d")
    c = ezc3d.c3d(str(out / "poses_track1.c3d"))
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(fps)
    got = c["data"]["points"][:3].transpose(2, 1, 0) / 1000 @ R
    want = _track_positions(res, 1)
    present = np.nonzero(~np.isnan(want[..., 0]).all(axis=1))[0]
    np.testing.assert_allclose(got, want[present[0] : present[-1] + 1], atol=0.01e-3)


def test_export_one_file_in_metres_to_a_named_file(three_people, tmp_path, capsys):
    from mvpose_jax.data.exports import opensim_from_world
    from tests.helpers import read_trc

    _, poses, res = three_people
    args = ["export", "--poses", str(poses), "--format", "trc", "--one-file", "--units", "m"]
    assert main([*args, "--up", "0,0,2", "--out", str(tmp_path / "walk.trc")]) == 0
    trc = read_trc(tmp_path / "walk.trc")
    assert trc["header"]["Units"] == "m"
    keypoints = get_layout(res.layout).keypoints
    assert trc["names"] == [f"t{t}_{k}" for t in (0, 1, 2) for k in keypoints]
    want = np.concatenate([_track_positions(res, t) for t in (0, 1, 2)], axis=1)
    got = trc["xyz"] @ opensim_from_world((0, 0, 1))
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got, want, atol=0.01e-3)


def test_infer_exports_after_the_poses(three_people, tmp_path, capsys):
    from tests.helpers import read_trc

    rec, _, _ = three_people
    scene = tmp_path / "scene.npz"
    save_recording(rec, scene)
    out = tmp_path / "poses"
    args = ["infer", "--rig", "panoptic5", "--detections", str(scene), "--out", str(out)]
    assert main([*args, "--export", "trc,c3d"]) == 0
    captured = capsys.readouterr()
    # infer tracks: one file per track, no warning about slots
    assert "slot is not the same person over time" not in captured.err
    res = load_poses(out)
    # (-1: people on tentative tracks, not exported)
    tracks = sorted({int(t) for t in res.track[res.poses.valid]} - {-1})
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(
        ["infer.json", "poses.json", "poses.npz"]
        + [f"poses_track{t}.{e}" for t in tracks for e in ("trc", "c3d")]
    )
    assert "exported" in captured.out
    trc = read_trc(out / f"poses_track{tracks[0]}.trc")
    assert float(trc["header"]["DataRate"]) == pytest.approx(1 / np.median(np.diff(rec.timestamps)))
    # Without the tracker each slot is exported as a track, and the user is told so.
    untracked = tmp_path / "untracked"
    args[-1] = str(untracked)
    assert main([*args, "--export", "trc", "--no-track"]) == 0
    assert "slot is not the same person over time" in capsys.readouterr().err
    slots = sorted({int(g) for g in np.nonzero(load_poses(untracked).poses.valid)[1]})
    assert sorted(p.name for p in untracked.glob("*.trc")) == [f"poses_track{g}.trc" for g in slots]


def test_export_errors_are_clear_and_write_nothing(three_people, tmp_path, capsys):
    import dataclasses

    from mvpose_jax.data.poses import save_poses

    rec, poses, res = three_people
    no_time = tmp_path / "no_time"
    save_poses(dataclasses.replace(res, timestamps=None), no_time)
    out = tmp_path / "out"
    base = ["export", "--poses", str(poses), "--rig", "panoptic5", "--out", str(out)]
    assert main([*base, "--format", "trc,fbx"]) == 2
    assert "field '--format': unknown format 'fbx'; choose from trc, c3d, csv" in (
        capsys.readouterr().err
    )
    args = ["export", "--poses", str(no_time), "--format", "trc", "--rig", "panoptic5"]
    assert main([*args, "--out", str(out)]) == 2
    assert "the poses have no timestamps, so the frame rate is unknown: give it (--fps)" in (
        capsys.readouterr().err
    )
    assert main([*args, "--out", str(out), "--fps", "30"]) == 0
    assert (out / "poses_track0.trc").exists()
    capsys.readouterr()
    no_up = ["export", "--poses", str(poses), "--format", "trc", "--out", str(tmp_path / "o2")]
    assert main(no_up) == 2
    assert "the OpenSim axes need the world's up: give --rig" in capsys.readouterr().err
    assert main([*no_up, "--rig", "panoptic5", "--up", "0,0,1"]) == 2
    assert "--rig or --up, not both" in capsys.readouterr().err
    assert main([*no_up, "--up", "0,1"]) == 2
    assert "expected three numbers X,Y,Z" in capsys.readouterr().err
    a_file = tmp_path / "taken"
    a_file.write_text("x")
    assert main([*base[:-1], str(a_file), "--format", "trc"]) == 2
    assert "is a file, but an output folder must go here" in capsys.readouterr().err
    assert main([*base[:-1], str(a_file / "walk.trc"), "--format", "trc"]) == 2
    assert "is a file, so nothing can be written below it" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()
    # infer --export without timestamps or --fps fails before the work
    bare = tmp_path / "bare.npz"
    save_recording(dataclasses.replace(rec, timestamps=None), bare)
    infer = ["infer", "--rig", "panoptic5", "--detections", str(bare), "--export", "c3d"]
    assert main([*infer, "--out", str(tmp_path / "p")]) == 2
    assert "give it (--fps)" in capsys.readouterr().err
    assert not (tmp_path / "p" / "poses.npz").exists()


def test_infer_tracks_filters_and_smooth_refilters(files, recording, tmp_path, capsys):
    out = tmp_path / "poses"
    args = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"])]
    assert main(args + ["--out", str(out)]) == 0
    assert "2 tracks" in capsys.readouterr().out
    res = load_poses(out)
    assert res.track is not None and res.filled is not None
    # Two true people, two tracks, from the first frame (tentative in the first two frames,
    # labelled once confirmed).
    assert set(np.unique(res.track[res.poses.valid])) == {0, 1}
    doc = json.loads((out / "poses.json").read_text())
    assert all("track" in p for f in doc["frames"] for p in f["people"])

    raw = tmp_path / "raw"
    assert main(args + ["--out", str(raw), "--filter", "none", "--fill-gap-s", "0"]) == 0
    unfiltered = load_poses(raw)
    assert not unfiltered.filled.any()
    # `smooth` on the unfiltered output gives what infer's default gives.
    again = tmp_path / "again"
    assert main(["smooth", "--poses", str(raw), "--out", str(again), "--fps", "30"]) == 0
    assert "butterworth filter" in capsys.readouterr().out
    np.testing.assert_allclose(load_poses(again).poses.xyz, res.poses.xyz, atol=1e-6)

    euro = tmp_path / "euro"
    assert main(args + ["--out", str(euro), "--filter", "one-euro"]) == 0
    # The first frame passes through the causal filter unchanged.
    np.testing.assert_allclose(load_poses(euro).poses.xyz[0], unfiltered.poses.xyz[0], atol=1e-6)

    bare = tmp_path / "bare"
    assert main(args + ["--out", str(bare), "--no-track"]) == 0
    assert load_poses(bare).track is None
    capsys.readouterr()
    assert main(["smooth", "--poses", str(bare), "--out", str(tmp_path / "x")]) == 2
    assert "no tracks" in capsys.readouterr().err
    assert main(args + ["--out", str(bare), "--cutoff-hz", "-1"]) == 2
    assert "--cutoff-hz" in capsys.readouterr().err


@pytest.mark.slow  # measures a floor twice (the geometric pipeline and robust triangulation)
def test_floor_from_detections_end_to_end(tmp_path, capsys):
    from mvpose_jax.synthetic import estimate_floor_height

    rig = load_rig("panoptic5")
    guess = estimate_floor_height(rig)
    # "Your" recording: people on a floor half a metre below where the cameras suggest.
    mine = tmp_path / "mine.npz"
    argv = ["generate", "--rig", "panoptic5", "--people", "4", "--frames", "40"]
    assert main([*argv, "--floor-height", f"{guess - 0.5}", "--out", str(mine)]) == 0
    assert "guess" not in capsys.readouterr().err  # a floor was given: no warning
    assert main(["rig", "--rig", "panoptic5", "--detections", str(mine)]) == 0
    out = capsys.readouterr().out
    assert "measured from the people" in out and "guessed from the cameras" in out
    off = float(out.split("the guess is ")[1].split(" m off")[0])
    assert abs(off - 0.5) < 0.03
    train = tmp_path / "train"
    argv = ["generate", "--rig", "panoptic5", "--single-person-recordings", "2", "--frames", "5"]
    assert main([*argv, "--floor-from", str(mine), "--out", str(train), "--format", "npz"]) == 0
    captured = capsys.readouterr()
    assert "floor measured from" in captured.out and "guess" not in captured.err
    for path in sorted(train.iterdir()):  # the training people stand near the measured floor
        rec = load_recording(path)
        h = np.asarray(rec.ground_truth.xyz)[:, :, 15:17] @ np.array([0.0, -1.0, 0.0])
        # Measured floor +- the training jitter (0.3 m), ankles 0.07 m above it.
        assert abs(np.median(h.min(-1)) - 0.07 - (guess - 0.5)) < 0.3 + 0.05


def test_generate_warns_that_the_floor_is_a_guess(tmp_path, capsys):
    argv = ["generate", "--rig", "panoptic5", "--people", "1", "--frames", "2"]
    assert main([*argv, "--out", str(tmp_path / "a.npz")]) == 0
    err = capsys.readouterr().err
    assert "warning: the floor height is a guess from the camera positions" in err
    assert "--floor-from DETECTIONS" in err
    assert main([*argv, "--floor-height", "0", "--out", str(tmp_path / "b.npz")]) == 0
    assert "guess" not in capsys.readouterr().err
    # Too few people to measure a floor from: a clear error, nothing written.
    few = ["--floor-from", str(tmp_path / "a.npz"), "--out", str(tmp_path / "c.npz")]
    assert main([*argv, *few]) == 2
    assert "cannot measure the floor" in capsys.readouterr().err
    assert not (tmp_path / "c.npz").exists()
    with pytest.raises(SystemExit):  # argparse: not both
        main([*argv, "--floor-height", "0", *few])
    assert "not allowed with argument" in capsys.readouterr().err


# --------------------------------------------------------------------------- streaming infer


@pytest.fixture(scope="module")
def long_files(tmp_path_factory):
    """A 13-frame recording as npz and as an OpenPose folder (chunks of 4: 4 + 4 + 4 + 1)."""
    rec = generate_recording(load_rig("panoptic5"), num_people=3, num_frames=13, seed=5)
    root = tmp_path_factory.mktemp("long")
    save_recording(rec, root / "scene.npz")
    save_openpose(rec, root / "openpose")
    return rec, root


def _infer_args(detections, out, *extra, track=False):
    """infer in chunks of 4 frames; untracked unless ``track`` (tracks restart on --resume, so
    exact equality with an uninterrupted run holds for untracked results)."""
    args = ["infer", "--rig", "panoptic5", "--detections", str(detections), "--out", str(out)]
    return args + ["--chunk-frames", "4", *extra] + ([] if track else ["--no-track"])


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
    # the first frames once for the frame rate (at most 8), then chunk by chunk
    assert ranges == [(0, 8), (0, 4), (4, 8), (8, 12), (12, 13)]
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


def test_infer_tracks_across_a_resume_without_reusing_ids(
    long_files, tmp_path, monkeypatch, capsys
):
    rec, root = long_files
    out = tmp_path / "out"
    _interrupt_on_chunk(monkeypatch, 2, KeyboardInterrupt())
    assert main(_infer_args(root / "scene.npz", out, track=True)) == 130
    before = load_poses(out)
    assert before.partial and before.track is not None
    monkeypatch.undo()
    assert main(_infer_args(root / "scene.npz", out, "--resume", track=True)) == 0
    after = load_poses(out)
    assert not after.partial and len(after.confidence) == rec.num_frames
    F0 = len(before.confidence)
    old = set(after.track[:F0][after.poses.valid[:F0]].tolist()) - {-1}  # -1: tentative
    new = set(after.track[F0:][after.poses.valid[F0:]].tolist()) - {-1}
    assert old and new and min(new) > max(old)  # restarted tracks take fresh ids


@pytest.mark.slow  # trains a tiny matcher for two steps, then four infer runs
def test_infer_proposals_option_combined_by_default_with_a_matcher(
    files, recording, tmp_path, monkeypatch, capsys
):
    import mvpose_jax.jobs.infer as infer_job
    from mvpose_jax.inference import run_pipeline
    from mvpose_jax.matcher_training import train_matcher
    from mvpose_jax.models import GATConfig
    from mvpose_jax.proposals import CombinedConfig
    from mvpose_jax.synthetic import generate_single_person_recordings
    from mvpose_jax.trained import (
        MatcherConfig,
        TrainConfig,
        load_matcher,
        write_proposal_threshold,
    )

    rig = load_rig("panoptic5")
    recs = generate_single_person_recordings(rig, num_recordings=3, num_frames=4, seed=2)
    config = MatcherConfig(
        gat=GATConfig(widths=(8, 1), heads=(2, 1)),
        train=TrainConfig(max_steps=2, batch_size=4, eval_every=1),
        samples_per_epoch=4,
        num_dev_samples=4,
    )
    folder = tmp_path / "matcher"
    train_matcher(rig, recs[:2], recs[2:], config, checkpoint_dir=folder, progress=False)
    chosen = CombinedConfig(threshold=0.3, epipolar_cutoff_px=60.0)
    write_proposal_threshold(folder, 0.4, {0.4: 1.0}, 4, combined=chosen)
    matcher = load_matcher(str(folder), rig)
    base = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"])]
    base += ["--matcher", str(folder), "--no-track"]
    expected = {
        None: dict(combined=chosen),  # the default with --matcher: the folder's settings
        "gat": dict(proposals="gat", threshold=0.4),
        "epipolar": dict(proposals="epipolar", half_score_px=30.0),
    }
    seen = []
    stream_pipeline = infer_job.stream_pipeline

    def spy(rig, chunks, config, **kwargs):
        seen.append(config.matching)
        return stream_pipeline(rig, chunks, config, **kwargs)

    monkeypatch.setattr(infer_job, "stream_pipeline", spy)
    for mode, kwargs in expected.items():
        out = tmp_path / f"poses-{mode}"
        assert main([*base, "--out", str(out)] + (["--proposals", mode] if mode else [])) == 0
        assert seen[-1].proposals == (mode or "combined")
        assert seen[-1].combined == (chosen if mode is None else None)
        got = load_poses(out / "poses.npz")
        want = run_pipeline(rig, recording.detections, matcher=matcher, **kwargs)
        np.testing.assert_array_equal(got.identity, want.identity)
    capsys.readouterr()
    argv = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"]), "--out"]
    assert main([*argv, str(tmp_path / "x"), "--proposals", "combined"]) == 2
    assert "--proposals combined needs --matcher" in capsys.readouterr().err
    # A threshold the combined matcher would not read is refused, in infer and in adapt.
    for command in ("infer", "adapt"):
        argv = [command, "--rig", "panoptic5", "--detections", str(files["npz"])]
        argv += ["--matcher", str(folder), "--threshold", "0.3", "--out", str(tmp_path / "y")]
        argv += ["--estimator", str(tmp_path / "no-estimator")] if command == "adapt" else []
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "--threshold" in err and "--proposals gat" in err, err


def _infer_on_all_and_three_cameras(files, tmp_path, models: list[str]) -> None:
    """`infer` with ``models`` (shipped, rig-agnostic) on panoptic5's 5 cameras and on 3 of them:
    people with finite keypoints both times."""
    base = ["infer", "--rig", "panoptic5", "--detections", str(files["npz"]), "--no-track"]
    for name, extra in (("all", []), ("three", ["--cameras", "trackera", "trackerc", "trackere"])):
        assert main([*base, *extra, *models, "--out", str(tmp_path / name)]) == 0
        poses = load_poses(tmp_path / name / "poses.npz").poses
        assert poses.valid.any() and np.isfinite(poses.xyz[poses.keypoint_valid]).all()


def _save_walks(folder, num_recordings: int) -> None:
    """Single-person panoptic5 recordings (6 frames, seed 3) saved into ``folder``."""
    from mvpose_jax.synthetic import generate_single_person_recordings

    recs = generate_single_person_recordings(
        load_rig("panoptic5"), num_recordings=num_recordings, num_frames=6, seed=3
    )
    for i, rec in enumerate(recs):
        save_recording(rec, folder / f"walk_{i}.npz")


def test_the_shipped_pretrained_estimator_runs_on_any_rig_and_fine_tunes(files, tmp_path, capsys):
    """`--estimator pretrained` needs no training: it loads the package's rig-agnostic estimator
    for this rig (5 cameras) and for a 3-camera subset of it; `train-estimator --start
    pretrained` fine-tunes it into a folder that loads as the same kind of model."""
    from mvpose_jax.trained import PRETRAINED, load_estimator, pretrained_folder

    assert (pretrained_folder("estimator") / "pretrain_report.json").is_file()
    _infer_on_all_and_three_cameras(files, tmp_path, ["--estimator", PRETRAINED])
    _save_walks(tmp_path / "train", num_recordings=2)
    out = tmp_path / "tuned"
    train = ["train-estimator", "--rig", "panoptic5", "--train", str(tmp_path / "train")]
    assert (
        main(
            [*train, "--out", str(out), "--start", PRETRAINED, "--steps", "2", "--batch-size", "8"]
        )
        == 0
    )
    tuned = load_estimator(out, load_rig("panoptic5"))
    assert tuned.config.mlp.views == "pooled"
    capsys.readouterr()


def test_the_shipped_pretrained_matcher_runs_on_any_rig_and_fine_tunes(files, tmp_path, capsys):
    """`--matcher pretrained` needs no training: the package's rig-agnostic matcher groups this
    rig's skeletons (5 cameras, and 3 of them) at its shipped threshold; `train-matcher --start
    pretrained` fine-tunes it into a folder that loads as the same kind of model."""
    import json

    from mvpose_jax.trained import (
        PRETRAINED,
        load_matcher,
        pretrained_folder,
        read_proposal_threshold,
    )

    report = json.loads((pretrained_folder("matcher") / "pretrain_report.json").read_text())
    # infer reads the threshold chosen in pretraining, from the shipped folder.
    assert read_proposal_threshold(PRETRAINED) == report["pretraining"]["threshold"]
    _infer_on_all_and_three_cameras(
        files, tmp_path, ["--matcher", PRETRAINED, "--proposals", "gat"]
    )
    _save_walks(tmp_path / "train", num_recordings=3)
    out = tmp_path / "tuned"
    train = ["train-matcher", "--rig", "panoptic5", "--train", str(tmp_path / "train")]
    train += ["--dev", str(tmp_path / "train"), "--quick", "--max-epochs", "1"]
    assert main([*train, "--out", str(out), "--start", PRETRAINED]) == 0
    tuned = load_matcher(out, load_rig("panoptic5"))
    assert tuned.config.gat.views == "pooled"
    capsys.readouterr()


def test_train_temporal_then_infer_with_it_and_fine_tune_on_the_recording(tmp_path, capsys):
    # (and `infer --associate`, the other stage that works on tracked people)
    """`train-temporal` on single-person recordings, `infer --temporal` with it (every keypoint of
    each tracked person; robust triangulation's keypoints unchanged), then `train-temporal
    --multi-person --start` fine-tunes it on the multi-person recording's own tracks."""
    from mvpose_jax.synthetic import generate_single_person_recordings
    from mvpose_jax.temporal import cached_temporal

    rig = load_rig("panoptic5")
    for i, rec in enumerate(
        generate_single_person_recordings(rig, num_recordings=3, num_frames=20, seed=5)
    ):
        save_recording(rec, tmp_path / "train" / f"walk_{i}.npz")
    scene = generate_recording(rig, num_people=2, num_frames=20, seed=6)
    save_recording(scene, tmp_path / "scene.npz")
    model = tmp_path / "temporal"
    train = ["train-temporal", "--rig", "panoptic5", "--window", "8", "--steps", "3"]
    assert main([*train, "--train", str(tmp_path / "train"), "--out", str(model)]) == 0
    assert "infer --temporal" in capsys.readouterr().out
    assert cached_temporal(str(model)).config.window == 8
    base = ["infer", "--rig", "panoptic5", "--detections", str(tmp_path / "scene.npz")]
    base += ["--method", "robust", "--filter", "none", "--fill-gap-s", "0", "--outlier-m", "0"]
    assert main([*base, "--out", str(tmp_path / "robust")]) == 0
    assert main([*base, "--temporal", str(model), "--out", str(tmp_path / "temporal")]) == 0
    a = load_poses(tmp_path / "robust").poses
    b = load_poses(tmp_path / "temporal").poses
    np.testing.assert_array_equal(a.valid, b.valid)
    assert b.keypoint_valid[b.valid].all() and not a.keypoint_valid[a.valid].all()
    kept = a.keypoint_valid & a.valid[..., None]
    np.testing.assert_allclose(b.xyz[kept], a.xyz[kept], atol=1e-4)
    tuned = tmp_path / "tuned"
    args = [*train, "--train", str(tmp_path / "scene.npz"), "--multi-person"]
    assert main([*args, "--start", str(model), "--out", str(tuned)]) == 0
    assert cached_temporal(str(tuned)).config.window == 8
    capsys.readouterr()
    assert main([*base, "--temporal", str(model), "--no-track", "--out", str(tmp_path / "x")]) == 2
    assert "--temporal" in capsys.readouterr().err
    assert main([*base, "--temporal", str(tmp_path / "none"), "--out", str(tmp_path / "y")]) == 2
    assert "temporal model" in capsys.readouterr().err
    # Track-level association: these people are grouped right already, so nothing changes.
    assert main([*base, "--associate", "--out", str(tmp_path / "assoc")]) == 0
    c = load_poses(tmp_path / "assoc").poses
    np.testing.assert_array_equal(c.valid.sum(1), a.valid.sum(1))
    capsys.readouterr()
    assert main([*base, "--associate", "--no-track", "--out", str(tmp_path / "z")]) == 2
    assert "--associate" in capsys.readouterr().err
