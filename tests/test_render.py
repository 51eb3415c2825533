"""Drawing and atomic figure/video writing (mvpose_jax.render) and the poses files (data.poses)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mvpose_jax.cameras import project_points
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.poses import PoseResults, load_poses, save_poses
from mvpose_jax.errors import InputError
from mvpose_jax.render import (
    VideoWriter,
    curves_figure,
    draw_view,
    person_colour,
    render_frame_figure,
    save_figure,
    skeleton_figure,
    tile,
    write_image,
)
from mvpose_jax.skeletons import Poses3D


def _person(rig):
    """A standing person 1 m tall in front of camera 0 (18 keypoints, a vertical line)."""
    c = 0
    R, t = np.asarray(rig.R)[c], np.asarray(rig.t)[c]
    centre = -R.T @ t
    front = centre + 3.0 * R[2]
    up = -R[1]  # image up
    return (front[None] + np.linspace(-0.5, 0.5, 18)[:, None] * up[None]).astype(np.float32)


def test_draw_view_puts_the_person_where_the_camera_sees_it():
    rig = load_rig("panoptic5")
    xyz = _person(rig)[None]
    img = draw_view(rig, 0, "coco18", xyz=xyz, scale=1.0)
    px = np.asarray(project_points(rig, xyz))[0, 0]  # (K, 2) in camera 0
    k = 17  # a keypoint away from the ends
    x, y = np.round(px[k]).astype(int)
    assert tuple(img[y, x]) == person_colour(0)
    w, h = np.asarray(rig.size)[0].astype(int)
    assert img.shape == (h, w, 3)


def test_draw_view_ignores_points_behind_and_nonfinite():
    rig = load_rig("panoptic5")
    xyz = _person(rig)
    R, t = np.asarray(rig.R)[0], np.asarray(rig.t)[0]
    centre = -R.T @ t
    behind = (2 * centre - xyz).astype(np.float32)  # mirrored through the camera centre
    nan = np.full_like(xyz, np.nan)
    img = draw_view(rig, 0, "coco18", xyz=np.stack([behind, nan]), scale=0.25)
    assert (img == 255).sum() > 0.95 * img.size  # only the camera name is drawn


def test_tile_and_atomic_writers(tmp_path):
    a = np.zeros((10, 20, 3), np.uint8)
    b = np.full((20, 20, 3), 100, np.uint8)
    t = tile([a, b, a, b], columns=3)
    assert t.shape == (20, 3 * 20, 3)
    path = write_image(tmp_path / "x.png", t)
    assert cv2.imread(str(path)).shape == t.shape
    assert [p.name for p in tmp_path.iterdir()] == ["x.png"]  # no temporary left
    with pytest.raises(RuntimeError), VideoWriter(tmp_path / "v.mp4") as v:
        v.write(t)
        raise RuntimeError("interrupted")
    assert not (tmp_path / "v.mp4").exists() and [p.name for p in tmp_path.iterdir()] == ["x.png"]
    with VideoWriter(tmp_path / "v.mp4", fps=5) as v:
        for _ in range(3):
            v.write(t)
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 3


def test_figures_are_written(tmp_path):
    rig = load_rig("panoptic5")
    xyz = _person(rig)[None]
    fig = skeleton_figure(
        {"a": (xyz, np.ones((1, 18), bool)), "empty": (xyz[:0], np.zeros((0, 18), bool))},
        "coco18",
        rig=rig,
    )
    assert save_figure(fig, tmp_path / "f.png").stat().st_size > 1000
    hist = [{"step": s, "train_loss": 1.0 / s, "val_loss": 1.2 / s} for s in (1, 2, 3)]
    assert save_figure(curves_figure({"run": hist}), tmp_path / "c.png").stat().st_size > 1000


def test_frame_figure_is_written_as_png_with_nothing_left_beside(tmp_path):
    from mvpose_jax.synthetic import generate_recording

    rig = load_rig("panoptic5")
    rec = generate_recording(rig, num_people=2, num_frames=3, seed=0)
    out = render_frame_figure(rec, rig, 2, tmp_path / "sub" / "frame.png", title="t")
    assert out == tmp_path / "sub" / "frame.png" and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in out.parent.iterdir()] == ["frame.png"]


def _results(F=3, G=2, C=2, P=3, K=18, seed=0):
    rng = np.random.default_rng(seed)
    valid = rng.random((F, G)) > 0.3
    kv = (rng.random((F, G, K)) > 0.2) & valid[..., None]
    xyz = np.where(kv[..., None], rng.normal(size=(F, G, K, 3)), 0).astype(np.float32)
    members = np.where(valid[..., None], rng.integers(0, P, (F, G, C)), -1).astype(np.int32)
    members[:, 1] = (
        np.where(members[:, 1] >= 0, (members[:, 0] + 1) % P, -1) if G > 1 else members[:, 1]
    )
    identity = np.full((F, C, P), -1, np.int32)
    f, g, c = np.nonzero(members >= 0)
    identity[f, c, members[f, g, c]] = g
    return PoseResults(
        Poses3D(xyz, valid, kv),
        rng.random((F, G)).astype(np.float32),
        members,
        identity,
        ("a", "b"),
        "coco18",
        np.arange(F) / 25.0,
    )


def test_poses_round_trip_npz_and_json(tmp_path):
    res = _results()
    npz, js = save_poses(res, tmp_path)
    for path in (npz, js):
        back = load_poses(path)
        np.testing.assert_array_equal(back.poses.valid, res.poses.valid)
        np.testing.assert_array_equal(back.poses.keypoint_valid, res.poses.keypoint_valid)
        np.testing.assert_allclose(back.poses.xyz, res.poses.xyz, atol=1e-4)
        np.testing.assert_array_equal(back.members, res.members)
        assert back.cameras == res.cameras and back.layout == "coco18"


def test_poses_round_trip_keeps_tracks_filled_keypoints_and_timestamps(tmp_path):
    import dataclasses

    res = _results(F=4)
    rng = np.random.default_rng(1)
    track = np.where(res.poses.valid, rng.integers(0, 5, res.poses.valid.shape), -1)
    filled = (rng.random(res.poses.keypoint_valid.shape) > 0.7) & res.poses.keypoint_valid
    res = dataclasses.replace(res, track=track.astype(np.int32), filled=filled)
    npz, js = save_poses(res, tmp_path)
    for path in (npz, js):
        back = load_poses(path)
        np.testing.assert_array_equal(back.track, res.track)
        np.testing.assert_array_equal(back.filled, res.filled)
        np.testing.assert_allclose(back.timestamps, res.timestamps)
    untracked = load_poses(save_poses(_results(), tmp_path / "u")[1])
    assert untracked.track is None and untracked.filled is None
    with pytest.raises(InputError, match="track"):
        dataclasses.replace(res, track=track[:, :1])


def test_poses_reader_rejects_other_files(tmp_path):
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="junk.npz"):
        load_poses(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(InputError, match="missing"):
        load_poses(tmp_path / "other.npz")
    (tmp_path / "x.json").write_text('{"format": "something else"}')
    with pytest.raises(InputError, match="format"):
        load_poses(tmp_path / "x.json")
    with pytest.raises(InputError, match="shape"):
        PoseResults(
            Poses3D(np.zeros((2, 1, 18, 3)), np.zeros((2, 1), bool), np.zeros((2, 1, 18), bool)),
            np.zeros((2, 2)),
            np.zeros((2, 1, 2), np.int32),
            np.zeros((2, 2, 1), np.int32),
            ("a", "b"),
            "coco18",
        )
