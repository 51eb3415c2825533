"""Detection recordings on disk: native JSON, the original repository's JSON, npz.

Round trips on random recordings, a hand-written original-format sample, conversions between
formats, precise errors on bad input, and fuzzing (a reader either loads or raises InputError).
"""

from __future__ import annotations

import json
import os
import tempfile
from functools import partial
from pathlib import Path

import hypothesis.strategies as st
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from mvpose_jax.data import (
    Recording,
    load_recording,
    read_native,
    read_native_rig,
    read_npz,
    read_original,
    save_recording,
    write_native,
    write_npz,
    write_original,
)
from mvpose_jax.data.calibration import load_preset
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Detections, Poses3D, get_layout
from tests.helpers import json_paths

FUZZ = settings(
    max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


# --------------------------------------------------------------------------- random recordings


def random_recording(
    seed: int,
    *,
    layout: str | None = None,
    cameras: tuple[str, ...] | None = None,
    extras: bool = True,
) -> Recording:
    """A random recording with padding, missing keypoints, identities, ground truth, timestamps.

    Every ground-truth person is present in some frame and some view has P people, so that the
    readers (which pad to what the file holds) give back the same shapes.
    """
    rng = np.random.default_rng(seed)
    layout = layout or str(rng.choice(["coco18", "coco17", "body25"]))
    K = get_layout(layout).num_keypoints
    F = int(rng.integers(1, 5))
    C = len(cameras) if cameras else int(rng.integers(1, 4))
    cameras = cameras or tuple(["cam0", "câm 1", "c2"][:C])
    P, G = int(rng.integers(1, 4)), int(rng.integers(1, 4))
    count = rng.integers(0, P + 1, (F, C)).astype(np.int32)
    count[rng.integers(F), rng.integers(C)] = P
    row = np.arange(P) < count[..., None]  # (F, C, P)
    score = rng.uniform(0.0, 1.0, (F, C, P, K)).astype(np.float32)
    score[rng.random(score.shape) < 0.05] = 1.0
    score[rng.random(score.shape) < 0.3] = 0.0  # missing keypoints
    score *= row[..., None]
    xy = rng.uniform(-50, 2000, (F, C, P, K, 2)).astype(np.float32) * (score > 0)[..., None]
    if not extras:
        return Recording(Detections(xy, score, count), cameras, layout)

    valid = rng.random((F, G)) < 0.6
    valid[rng.integers(F, size=G), np.arange(G)] = True
    kvalid = valid[..., None] & (rng.random((F, G, K)) < 0.8)
    xyz = (rng.normal(0, 2, (F, G, K, 3)) * kvalid[..., None]).astype(np.float32)
    identity = np.full((F, C, P), -1, np.int32)
    for f, c, p in np.argwhere(row):
        choices = np.flatnonzero(valid[f]).tolist() + [-1]
        identity[f, c, p] = rng.choice(choices)
    projected = (rng.uniform(0, 1920, (F, C, P, K, 2)) * row[..., None, None]).astype(np.float32)
    timestamps = 1.6e9 + np.cumsum(rng.uniform(0.01, 0.1, F))
    image_names = np.array([[f"{cam}/{f:06d}.jpg" for cam in cameras] for f in range(F)])
    return Recording(
        Detections(xy, score, count),
        cameras,
        layout,
        Poses3D(xyz, valid, kvalid),
        identity,
        timestamps,
        image_names,
        projected,
    )


def assert_detections_equal(a: Recording, b: Recording) -> None:
    assert a.cameras == b.cameras and a.layout == b.layout
    for name in ("xy", "score", "count"):
        x, y = np.asarray(getattr(a.detections, name)), np.asarray(getattr(b.detections, name))
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)


def assert_recordings_equal(a: Recording, b: Recording) -> None:
    assert_detections_equal(a, b)
    for name in ("identity", "timestamps", "image_names", "projected"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert np.asarray(x).dtype == np.asarray(y).dtype, name
            np.testing.assert_array_equal(x, y, err_msg=name)
    assert (a.ground_truth is None) == (b.ground_truth is None)
    if a.ground_truth is not None:
        for x, y in zip(a.ground_truth, b.ground_truth, strict=True):
            assert np.asarray(x).dtype == np.asarray(y).dtype
            np.testing.assert_array_equal(x, y)


def compact_ground_truth(gt: Poses3D) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Per frame, the present people in G order: what the original format (no ids) keeps."""
    return [
        [(gt.xyz[f, g], gt.keypoint_valid[f, g]) for g in np.flatnonzero(gt.valid[f])]
        for f in range(gt.valid.shape[0])
    ]


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("seed", range(6))
def test_native_round_trip(tmp_path, seed):
    rec = random_recording(seed)
    write_native(rec, tmp_path / "r.json")
    assert_recordings_equal(read_native(tmp_path / "r.json"), rec)
    assert_recordings_equal(load_recording(tmp_path / "r.json"), rec)


@pytest.mark.parametrize("seed", range(6))
def test_npz_round_trip(tmp_path, seed):
    rec = random_recording(seed)
    write_npz(rec, tmp_path / "r.npz")
    assert_recordings_equal(read_npz(tmp_path / "r.npz"), rec)
    save_recording(rec, tmp_path / "s.npz")
    assert_recordings_equal(load_recording(tmp_path / "s.npz"), rec)


@pytest.mark.parametrize("seed", range(6))
def test_original_round_trip(tmp_path, seed):
    rec = random_recording(seed)
    write_original(rec, tmp_path / "o.json")
    back = read_original(tmp_path / "o.json", layout=rec.layout)
    assert_detections_equal(back, rec)
    np.testing.assert_array_equal(back.timestamps, rec.timestamps)
    np.testing.assert_array_equal(back.image_names, rec.image_names)
    assert back.identity is None and back.projected is None  # the format has no place for them
    for people_a, people_b in zip(
        compact_ground_truth(back.ground_truth), compact_ground_truth(rec.ground_truth), strict=True
    ):
        assert len(people_a) == len(people_b)
        for (xa, ka), (xb, kb) in zip(people_a, people_b, strict=True):
            np.testing.assert_array_equal(ka, kb)
            np.testing.assert_array_equal(xa, xb)  # cm on disk, yet exact in float32 metres


def test_minimal_recordings_round_trip(tmp_path):
    """Nothing optional, and a recording where nobody is seen at all."""
    for seed in range(3):
        rec = random_recording(seed, extras=False)
        for name, write, read in (
            ("n.json", write_native, read_native),
            ("n.npz", write_npz, read_npz),
        ):
            write(rec, tmp_path / name)
            assert_recordings_equal(read(tmp_path / name), rec)
        write_original(rec, tmp_path / "o.json")
        assert_detections_equal(read_original(tmp_path / "o.json", layout=rec.layout), rec)
    empty = Recording(
        Detections(
            np.zeros((2, 1, 1, 18, 2), np.float32),
            np.zeros((2, 1, 1, 18), np.float32),
            np.zeros((2, 1), np.int32),
        ),
        ("a",),
    )
    for name in ("e.json", "e.npz"):
        save_recording(empty, tmp_path / name)
        assert_recordings_equal(load_recording(tmp_path / name), empty)


def test_conversion_between_formats_preserves_detections(tmp_path):
    rec = random_recording(11, layout="coco18")
    save_recording(rec, tmp_path / "a.json")  # native by suffix
    save_recording(load_recording(tmp_path / "a.json"), tmp_path / "b.npz")
    save_recording(load_recording(tmp_path / "b.npz"), tmp_path / "c.json", format="original")
    from_original = load_recording(tmp_path / "c.json")  # a JSON list: the original format
    assert from_original.identity is None
    save_recording(from_original, tmp_path / "d.json")
    final = load_recording(tmp_path / "d.json")
    assert_detections_equal(final, rec)
    np.testing.assert_array_equal(final.timestamps, rec.timestamps)
    np.testing.assert_array_equal(final.image_names, rec.image_names)


def test_native_embeds_the_rig(tmp_path):
    rig = load_preset("panoptic5")
    rec = random_recording(3, cameras=("trackerc", "trackera"))
    save_recording(rec, tmp_path / "r.json", rig=rig)
    back = read_native_rig(tmp_path / "r.json")
    assert back.names == rig.names
    np.testing.assert_allclose(np.asarray(back.K), np.asarray(rig.K))
    np.testing.assert_allclose(np.asarray(back.t), np.asarray(rig.t))
    assert_recordings_equal(read_native(tmp_path / "r.json"), rec)
    write_native(rec, tmp_path / "plain.json")
    assert read_native_rig(tmp_path / "plain.json") is None
    with pytest.raises(InputError) as e:  # npz has no place for a rig: refuse, don't drop it
        save_recording(rec, tmp_path / "r.npz", rig=rig)
    assert e.value.field == "rig"
    with pytest.raises(InputError) as e:
        write_native(rec, tmp_path / "x.json", rig=load_preset("arplab6").select(["trackerb"]))
    assert e.value.camera == "trackerc" and e.value.field == "rig"


def test_load_recording_selects_cameras_and_converts_layout(tmp_path):
    rec = random_recording(5, layout="coco18", cameras=("a", "b", "c"))
    save_recording(rec, tmp_path / "r.npz")
    sub = load_recording(tmp_path / "r.npz", cameras=["c", "a"], layout="coco17")
    assert sub.cameras == ("c", "a") and sub.layout == "coco17"
    P = sub.detections.score.shape[2]
    np.testing.assert_array_equal(sub.detections.count, rec.detections.count[:, [2, 0]])
    # coco17 is coco18 without its last keypoint (the neck).
    np.testing.assert_array_equal(sub.detections.score, rec.detections.score[:, [2, 0], :P, :17])
    np.testing.assert_array_equal(sub.detections.xy, rec.detections.xy[:, [2, 0], :P, :17])
    np.testing.assert_array_equal(sub.ground_truth.xyz, rec.ground_truth.xyz[:, :, :17])
    np.testing.assert_array_equal(sub.identity, rec.identity[:, [2, 0], :P])


def test_failed_write_leaves_the_old_file(tmp_path):
    rec = random_recording(1)
    for name in ("r.json", "r.npz", "o.json"):
        save_recording(rec, tmp_path / name, format="original" if name == "o.json" else None)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    xy = np.array(rec.detections.xy)
    xy[0, 0, 0, 0, 0] = np.nan
    bad = Recording(
        Detections(xy, rec.detections.score, rec.detections.count), rec.cameras, rec.layout
    )
    for name in before:
        with pytest.raises(InputError) as e:
            save_recording(bad, tmp_path / name, format="original" if name == "o.json" else None)
        assert e.value.file == str(tmp_path / name) and e.value.field == "xy"
        assert e.value.frame == 0 and e.value.camera == rec.cameras[0]
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no temp files either


# --------------------------------------------------------------------------- hand-written samples

# The original repository's format, written by hand from its description: 2 frames, 2 cameras;
# frame 0 has gt3d (centimetres) in both camera entries, frame 1 lacks camera "trackerb". (The
# skeletons string cannot be wrapped: JSON strings hold no newlines.)
ORIGINAL_SAMPLE = r"""[
 {"trackera": [
   "[{\"0\": [0, 100.5, 200.25, 1, 0.9], \"17\": [17, 110.0, 260.0, 1, 0.75]}, {\"5\": [5, 640.0, 360.0, 1, 0.5], \"6\": [6, 650.0, 362.5, 0, 0.8]}]",
   1000.5, "a/000000.jpg", [{"0": [10.0, -150.0, 300.0], "17": [12.5, -130.0, 301.0]}]],
  "trackerb": ["[{\"1\": [1, 5.0, 6.0, 1, 1.0]}]", 1000.52, "b/000000.jpg",
               [{"0": [10.0, -150.0, 300.0], "17": [12.5, -130.0, 301.0]}]]},
 {"trackera": ["[]", 1000.54, "a/000001.jpg"]}
]"""


def test_original_reads_hand_written_sample(tmp_path):
    path = tmp_path / "sample.json"
    path.write_text(ORIGINAL_SAMPLE)
    rec = read_original(path)
    assert rec.cameras == ("trackera", "trackerb") and rec.layout == "coco18"
    det = rec.detections
    assert det.xy.shape == (2, 2, 2, 18, 2) and det.xy.dtype == np.float32
    np.testing.assert_array_equal(det.count, [[2, 1], [0, 0]])
    expected_score = np.zeros((2, 2, 2, 18), np.float32)
    expected_xy = np.zeros((2, 2, 2, 18, 2), np.float32)
    expected_score[0, 0, 0, [0, 17]] = [0.9, 0.75]
    expected_xy[0, 0, 0, [0, 17]] = [[100.5, 200.25], [110.0, 260.0]]
    expected_score[0, 0, 1, 5] = 0.5  # keypoint 6 has visible 0: missing, although scored
    expected_xy[0, 0, 1, 5] = [640.0, 360.0]
    expected_score[0, 1, 0, 1] = 1.0
    expected_xy[0, 1, 0, 1] = [5.0, 6.0]
    np.testing.assert_array_equal(det.score, expected_score)
    np.testing.assert_array_equal(det.xy, expected_xy)
    np.testing.assert_array_equal(rec.timestamps, [1000.5, 1000.54])
    np.testing.assert_array_equal(
        rec.image_names, [["a/000000.jpg", "b/000000.jpg"], ["a/000001.jpg", ""]]
    )
    assert rec.identity is None and rec.projected is None
    gt = rec.ground_truth
    np.testing.assert_array_equal(gt.valid, [[True], [False]])
    np.testing.assert_array_equal(np.flatnonzero(gt.keypoint_valid[0, 0]), [0, 17])
    np.testing.assert_allclose(
        gt.xyz[0, 0, 0], [0.1, -1.5, 3.0], rtol=1e-7
    )  # centimetres -> metres
    np.testing.assert_allclose(gt.xyz[0, 0, 17], [0.125, -1.3, 3.01], rtol=1e-7)
    assert not gt.xyz[1].any()
    # Explicit camera choice and order; dispatch by content gives the same.
    only_b = read_original(path, cameras=["trackerb"])
    assert only_b.cameras == ("trackerb",) and only_b.detections.score.shape == (2, 1, 1, 18)
    assert_detections_equal(load_recording(path), rec)


def test_original_gt3d_union_and_original_tool_keys(tmp_path):
    """The original tools' multi-person files: each camera lists the people IT sees, gt3d has the
    body centre under "-1", skeletons may hold an "ID"; the frame's people are the union."""
    p1 = {"0": [100.0, 0.0, 0.0], "-1": [1.0, 2.0, 3.0]}
    p2 = {"5": [0.0, 200.0, 0.0]}
    doc = [
        {
            "a": ['[{"ID": 4, "0": [0, 1.0, 2.0, 1, 0.5]}]', 0.0, "no_image", [p1]],
            "b": ["[]", 0.0, "no_image", [p2, p1]],
            "c": ["[]", 0.0, "no_image", []],
        },
        {"a": ["[]", 0.1, "no_image", [p2]]},
    ]
    path = _write(tmp_path / "o.json", doc)
    rec = read_original(path)
    gt = rec.ground_truth
    np.testing.assert_array_equal(gt.valid, [[True, True], [True, False]])
    np.testing.assert_array_equal(gt.xyz[0, 0, 0], [1.0, 0.0, 0.0])  # p1 first (camera a)
    np.testing.assert_array_equal(gt.xyz[0, 1, 5], [0.0, 2.0, 0.0])
    np.testing.assert_array_equal(gt.xyz[1, 0, 5], [0.0, 2.0, 0.0])
    assert gt.keypoint_valid[0, 0].sum() == 1  # "-1" is no keypoint of coco18
    np.testing.assert_array_equal(rec.detections.score[0, 0, 0, :2], [0.5, 0.0])


def test_native_reads_hand_written_sample_with_sparse_ids(tmp_path):
    kp = lambda x: [[x, x + 1.0, 0.5]] + [[0, 0, 0]] * 16 + [None]  # noqa: E731
    doc = {
        "format": "mvpose-jax.detections",
        "version": 1,
        "layout": "coco18",
        "cameras": ["a", "b"],
        "frames": [
            {
                "index": 0,
                "timestamp": 0.0,
                "views": {
                    "a": [{"keypoints": kp(1.0), "identity": 7}, {"keypoints": kp(2.0)}],
                    "b": [{"keypoints": kp(3.0), "identity": -1}],
                },
                "ground_truth": [{"id": 7, "keypoints": [[0.5, 1.0, 2.0]] + [None] * 17}],
            },
            {
                "index": 1,
                "timestamp": 0.04,
                "views": {"b": [{"keypoints": kp(4.0), "identity": 3}]},
                "ground_truth": [{"id": 3}],
            },
        ],
    }
    (tmp_path / "n.json").write_text(json.dumps(doc))
    rec = read_native(tmp_path / "n.json")
    np.testing.assert_array_equal(rec.detections.count, [[2, 1], [0, 1]])
    np.testing.assert_array_equal(rec.detections.xy[0, 0, 1, 0], [2.0, 3.0])
    np.testing.assert_array_equal(rec.detections.score[0, 0, 1], [0.5] + [0.0] * 17)
    # ids {3, 7} -> G indices {0, 1}; the same person keeps its index across frames.
    np.testing.assert_array_equal(rec.identity, [[[1, -1], [-1, -1]], [[-1, -1], [0, -1]]])
    np.testing.assert_array_equal(rec.ground_truth.valid, [[False, True], [True, False]])
    np.testing.assert_array_equal(rec.ground_truth.xyz[0, 1, 0], np.float32([0.5, 1.0, 2.0]))
    assert not rec.ground_truth.keypoint_valid[1, 0].any()
    np.testing.assert_array_equal(rec.timestamps, [0.0, 0.04])


# --------------------------------------------------------------------------- bad input


def _native_doc(K: int = 18) -> dict:
    row = lambda x: [[x + k, 2.0 * k, 0.5] for k in range(K)]  # noqa: E731
    return {
        "format": "mvpose-jax.detections",
        "version": 1,
        "layout": "coco18",
        "cameras": ["a", "b"],
        "frames": [
            {"views": {"a": [{"keypoints": row(1.0)}], "b": []}},
            {
                "views": {
                    "a": [{"keypoints": row(2.0)}],
                    "b": [{"keypoints": row(3.0)}, {"keypoints": row(4.0)}],
                }
            },
        ],
    }


def _original_doc(skeleton_b: str = '[{"3": [3, 5.0, 6.0, 1, 0.5]}]') -> list:
    return [
        {"a": ['[{"0": [0, 1.0, 2.0, 1, 0.9]}]', 0.0, "a0.jpg"], "b": ["[]", 0.0, "b0.jpg"]},
        {"a": ["[]", 0.1, "a1.jpg"], "b": [skeleton_b, 0.1, "b1.jpg"]},
    ]


def _write(path: Path, doc) -> Path:
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def _expect(call, *, file, frame=None, camera=None, field=None) -> InputError:
    """Runs ``call()``; checks it raises InputError at exactly this place."""
    with pytest.raises(InputError) as info:
        call()
    e = info.value
    assert e.file == str(file), e
    assert (e.frame, e.camera, e.field) == (frame, camera, field), e
    assert str(file) in str(e)
    return e


@pytest.mark.parametrize("reader", [read_native, read_original, read_npz, load_recording])
def test_empty_and_missing_files(tmp_path, reader):
    path = tmp_path / ("x.npz" if reader is read_npz else "x.json")
    path.write_bytes(b"")
    assert "empty" in str(_expect(partial(reader, path), file=path))
    _expect(partial(reader, tmp_path / "missing.json"), file=tmp_path / "missing.json")


@pytest.mark.parametrize("reader", [read_native, read_original, load_recording])
def test_malformed_json(tmp_path, reader):
    text = json.dumps(_native_doc() if reader is read_native else _original_doc())
    path = _write(tmp_path / "x.json", text[: len(text) // 2])
    assert "malformed JSON" in str(_expect(partial(reader, path), file=path))


def test_malformed_embedded_skeletons(tmp_path):
    path = _write(tmp_path / "o.json", _original_doc('[{"3": [3, 5.0'))
    _expect(partial(read_original, path), file=path, frame=1, camera="b", field="skeletons")


def test_unknown_camera(tmp_path):
    doc = _native_doc()
    doc["frames"][1]["views"]["zed"] = []
    path = _write(tmp_path / "n.json", doc)
    _expect(partial(read_native, path), file=path, frame=1, camera="zed", field="views")
    orig = _write(tmp_path / "o.json", _original_doc())
    _expect(
        partial(read_original, orig, cameras=["a", "zed"]), file=orig, camera="zed", field="cameras"
    )
    write_npz(random_recording(0, cameras=("a", "b")), tmp_path / "r.npz")
    _expect(
        partial(load_recording, tmp_path / "r.npz", cameras=["zed"]),
        file=tmp_path / "r.npz",
        camera="zed",
        field="cameras",
    )


def test_wrong_keypoint_count(tmp_path):
    doc = _native_doc()
    doc["frames"][1]["views"]["b"][1]["keypoints"].pop()
    path = _write(tmp_path / "n.json", doc)
    e = _expect(
        partial(read_native, path), file=path, frame=1, camera="b", field="skeleton[1].keypoints"
    )
    assert "expected 18 keypoints, got 17" in str(e)
    orig = _write(tmp_path / "o.json", _original_doc('[{"18": [18, 5.0, 6.0, 1, 0.5]}]'))
    _expect(
        partial(read_original, orig),
        file=orig,
        frame=1,
        camera="b",
        field="skeleton[0].keypoints[18]",
    )
    # The same file is fine for a layout with more keypoints.
    assert read_original(orig, layout="body25").detections.score[1, 1, 0, 18] == 0.5
    # npz: arrays whose K disagrees with the layout.
    write_npz(random_recording(0, layout="coco18"), tmp_path / "r.npz")
    arrays = dict(np.load(tmp_path / "r.npz"))
    arrays["layout"] = np.asarray("coco17")
    np.savez(tmp_path / "bad.npz", **arrays)
    _expect(partial(read_npz, tmp_path / "bad.npz"), file=tmp_path / "bad.npz", field="xy")


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_coordinates(tmp_path, token):
    text = json.dumps(_native_doc()).replace("[4.0, 0.0, 0.5]", f"[{token}, 0.0, 0.5]")
    path = _write(tmp_path / "n.json", text)
    _expect(
        partial(read_native, path), file=path, frame=1, camera="b", field="skeleton[1].keypoints[0]"
    )
    orig = _write(
        tmp_path / "o.json",
        _original_doc(f'[{{"3": [3, 5.0, 6.0, 1, 0.5]}}, {{"4": [4, 1.0, {token}, 1, 0.5]}}]'),
    )
    _expect(
        partial(read_original, orig),
        file=orig,
        frame=1,
        camera="b",
        field="skeleton[1].keypoints[4]",
    )
    rec = random_recording(2, cameras=("a", "b"))
    write_npz(rec, tmp_path / "r.npz")
    arrays = dict(np.load(tmp_path / "r.npz"))
    f, c = np.argwhere(rec.detections.count > 0)[-1]
    arrays["xy"][f, c, 0, 3, 1] = float(token)
    arrays["score"][f, c, 0, 3] = 0.5  # a keypoint the detector claims to have seen
    np.savez(tmp_path / "bad.npz", **arrays)
    _expect(
        partial(read_npz, tmp_path / "bad.npz"),
        file=tmp_path / "bad.npz",
        frame=int(f),
        camera=rec.cameras[c],
        field="xy",
    )


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_coordinates_of_a_missing_keypoint_read_as_missing(tmp_path, token):
    # How several detectors mark a keypoint they did not find: NaN (or inf) with score 0.
    text = json.dumps(_native_doc()).replace("[4.0, 0.0, 0.5]", f"[{token}, {token}, 0.0]")
    rec = read_native(_write(tmp_path / "n.json", text))
    xy, score = np.asarray(rec.detections.xy), np.asarray(rec.detections.score)
    assert np.isfinite(xy).all() and score[1, 1, 1, 0] == 0 and (xy[1, 1, 1, 0] == 0).all()
    orig = _write(
        tmp_path / "o.json",
        _original_doc(f'[{{"3": [3, 5.0, 6.0, 1, 0.5]}}, {{"4": [4, {token}, {token}, 1, 0]}}]'),
    )
    rec = read_original(orig)
    assert np.isfinite(np.asarray(rec.detections.xy)).all()
    assert np.asarray(rec.detections.score)[1, 1, 1, 4] == 0
    src = random_recording(2, cameras=("a", "b"))
    write_npz(src, tmp_path / "r.npz")
    arrays = dict(np.load(tmp_path / "r.npz"))
    f, c = np.argwhere(src.detections.count > 0)[-1]
    arrays["xy"][f, c, 0, 3] = float(token)
    arrays["score"][f, c, 0, 3] = 0.0
    np.savez(tmp_path / "missing.npz", **arrays)
    rec = read_npz(tmp_path / "missing.npz")
    assert np.isfinite(np.asarray(rec.detections.xy)).all()
    assert (np.asarray(rec.detections.xy)[f, c, 0, 3] == 0).all()


def test_non_finite_ground_truth(tmp_path):
    doc = _native_doc()
    doc["frames"][0]["ground_truth"] = [
        {"id": 0, "keypoints": [[1.0, 2.0, 3.0]] * 17 + [[1.0, 1e999, 3.0]]}
    ]
    path = _write(tmp_path / "n.json", doc)
    _expect(partial(read_native, path), file=path, frame=0, field="ground_truth[0].keypoints[17]")
    gt3d = [{"0": [1.0, 2.0, 3.0]}, {"4": [1.0, 2.0, 3.0], "5": [1.0, float("nan"), 3.0]}]
    doc = _original_doc()
    doc[1]["b"].append(gt3d)
    path = _write(tmp_path / "o.json", doc)
    _expect(
        partial(read_original, path), file=path, frame=1, camera="b", field="gt3d[1].keypoints[5]"
    )


@pytest.mark.parametrize("bad_score", [-0.5, 1.51, 3.0])
def test_scores_outside_the_accepted_range(tmp_path, bad_score):
    text = json.dumps(_native_doc()).replace("[4.0, 0.0, 0.5]", f"[4.0, 0.0, {bad_score}]")
    path = _write(tmp_path / "n.json", text)
    _expect(
        partial(read_native, path),
        file=path,
        frame=1,
        camera="b",
        field="skeleton[1].keypoints[0].score",
    )
    orig = _write(tmp_path / "o.json", _original_doc(f'[{{"3": [3, 5.0, 6.0, 1, {bad_score}]}}]'))
    _expect(
        partial(read_original, orig),
        file=orig,
        frame=1,
        camera="b",
        field="skeleton[0].keypoints[3].score",
    )
    rec = random_recording(4, cameras=("a", "b"))
    write_npz(rec, tmp_path / "r.npz")
    arrays = dict(np.load(tmp_path / "r.npz"))
    f, c = np.argwhere(rec.detections.count > 0)[0]
    arrays["score"][f, c, 0, 2] = bad_score
    np.savez(tmp_path / "bad.npz", **arrays)
    _expect(
        partial(read_npz, tmp_path / "bad.npz"),
        file=tmp_path / "bad.npz",
        frame=int(f),
        camera=rec.cameras[c],
        field="score",
    )


def test_scores_up_to_1_5_are_clipped_in_every_format(tmp_path):
    from mvpose_jax.data.checks import ScoreClippedWarning

    text = json.dumps(_native_doc()).replace("[4.0, 0.0, 0.5]", "[4.0, 0.0, 1.2]")
    with pytest.warns(ScoreClippedWarning, match="1 keypoint scores above 1 \\(largest 1.2\\)"):
        rec = read_native(_write(tmp_path / "n.json", text))
    assert np.asarray(rec.detections.score)[1, 1, 1, 0] == 1.0
    orig = _write(tmp_path / "o.json", _original_doc('[{"3": [3, 5.0, 6.0, 1, 1.5]}]'))
    with pytest.warns(ScoreClippedWarning, match="largest 1.5"):
        rec = read_original(orig)
    assert np.asarray(rec.detections.score)[1, 1, 0, 3] == 1.0
    src = random_recording(4, cameras=("a", "b"))
    write_npz(src, tmp_path / "r.npz")
    arrays = dict(np.load(tmp_path / "r.npz"))
    f, c = np.argwhere(src.detections.count > 0)[0]
    arrays["score"][f, c, 0, 2] = 1.04
    np.savez(tmp_path / "high.npz", **arrays)
    with pytest.warns(ScoreClippedWarning, match=str(tmp_path / "high.npz")):
        rec = read_npz(tmp_path / "high.npz")
    assert np.asarray(rec.detections.score).max() <= 1.0 and rec.detections.score[f, c, 0, 2] == 1.0


def test_native_structure_errors(tmp_path):
    cases = [
        # Identities refer to ground-truth ids of the SAME frame (5 is only in frame 0).
        (
            lambda d: (
                d["frames"][0].update(ground_truth=[{"id": 5}]),
                d["frames"][1]["views"]["b"][0].update(identity=5),
            ),
            1,
            "b",
            "skeleton[0].identity",
        ),
        (
            lambda d: d["frames"][0]["views"]["a"][0].update(keypont=[]),
            0,
            "a",
            "skeleton[0].keypont",
        ),
        (
            lambda d: d["frames"][0]["views"]["a"][0]["keypoints"].__setitem__(2, [1, "2", 3]),
            0,
            "a",
            "skeleton[0].keypoints[2]",
        ),
        (
            lambda d: d["frames"][0]["views"]["a"][0]["keypoints"].__setitem__(2, [1, 2]),
            0,
            "a",
            "skeleton[0].keypoints[2]",
        ),
        (lambda d: d["frames"][1]["views"].__setitem__("a", {}), 1, "a", "views"),
        (lambda d: d["frames"][1].update(index=7), 1, None, "index"),
        (lambda d: d["frames"][0].update(timestamp=1.0), 1, None, "timestamp"),
        (lambda d: d["frames"].append(3), 2, None, "frames[2]"),
        (lambda d: d.update(frames={}), None, None, "frames"),
        (lambda d: d.update(cameras=["a", "a"]), None, None, "cameras"),
        (lambda d: d.update(layout="coco99"), None, None, "layout"),
        (lambda d: d.update(version=2), None, None, "version"),
    ]
    for i, (mutate, frame, camera, field) in enumerate(cases):
        doc = _native_doc()
        mutate(doc)
        path = _write(tmp_path / f"n{i}.json", doc)
        _expect(partial(read_native, path), file=path, frame=frame, camera=camera, field=field)


def test_original_structure_errors(tmp_path):
    cases = [
        ([{"a": ["[]", 0.0]}], 0, "a", None),
        ([{"a": ["[]", "zero", "x.jpg"]}], 0, "a", "timestamp"),
        ([{"a": ["[]", 0.0, 7]}], 0, "a", "image_name"),
        ([{"a": ['[{"x": [0, 1, 2, 1, 1]}]', 0.0, "i"]}], 0, "a", "skeleton[0].keypoints[x]"),
        ([{"a": ['[{"2": [3, 1, 2, 1, 1]}]', 0.0, "i"]}], 0, "a", "skeleton[0].keypoints[2]"),
        ([{"a": ['[{"2": [2, 1, 2, 1]}]', 0.0, "i"]}], 0, "a", "skeleton[0].keypoints[2]"),
        ([{"a": ["[]", 0.0, "i", [{"0": [1.0, 2.0]}]]}], 0, "a", "gt3d[0].keypoints[0]"),
        ([{"a": ["[]", 0.0, "i"]}, []], 1, None, None),
        ({"a": 1}, None, None, None),
    ]
    for i, (doc, frame, camera, field) in enumerate(cases):
        path = _write(tmp_path / f"o{i}.json", doc)
        reader = read_original if isinstance(doc, list) else load_recording
        _expect(partial(reader, path), file=path, frame=frame, camera=camera, field=field)


def test_npz_refuses_pickles_and_strangers(tmp_path):
    write_npz(random_recording(0), tmp_path / "r.npz")
    arrays = dict(np.load(tmp_path / "r.npz"))
    for name, mutate in [
        ("cameras", lambda a: a.update(cameras=np.array([object()], dtype=object))),
        ("extra", lambda a: a.update(extra=np.zeros(3))),
        ("count", lambda a: a.pop("count")),
        ("score", lambda a: a.update(score=a["score"].astype(np.int32))),
    ]:
        bad = dict(arrays)
        mutate(bad)
        np.savez(tmp_path / f"{name}.npz", **bad)
        e = _expect(
            partial(read_npz, tmp_path / f"{name}.npz"), file=tmp_path / f"{name}.npz", field=name
        )
        if name == "cameras":  # the object array must be refused, never unpickled
            assert "pickle" in str(e)
    data = (tmp_path / "r.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    _expect(partial(read_npz, tmp_path / "cut.npz"), file=tmp_path / "cut.npz")
    (tmp_path / "text.npz").write_text("hello")
    _expect(partial(read_npz, tmp_path / "text.npz"), file=tmp_path / "text.npz")


# --------------------------------------------------------------------------- fuzzing

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4)
    ),
    max_leaves=30,
)


@pytest.fixture(scope="module")
def fuzz_dir():
    with tempfile.TemporaryDirectory() as d:
        yield Path(d)


def _loads_or_input_error(call) -> None:
    try:
        result = call()
    except InputError:
        return
    assert isinstance(result, Recording)


READERS = [read_native, read_original, load_recording]


@FUZZ
@given(data=st.binary(max_size=200))
def test_fuzz_bytes(fuzz_dir, data):
    for suffix, readers in ((".json", READERS), (".npz", [read_npz, load_recording])):
        path = fuzz_dir / f"bytes{suffix}"
        path.write_bytes(data)
        for reader in readers:
            _loads_or_input_error(partial(reader, path))


@FUZZ
@given(value=json_values)
def test_fuzz_json_values(fuzz_dir, value):
    path = fuzz_dir / "value.json"
    path.write_text(json.dumps(value))
    for reader in READERS:
        _loads_or_input_error(partial(reader, path))


def _replace(doc, path, value):
    if not path:
        return value
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return doc


def _valid_documents() -> list:
    rec = random_recording(7, layout="coco17")
    with tempfile.TemporaryDirectory() as d:
        write_native(rec, Path(d) / "n.json")
        write_original(rec, Path(d) / "o.json")
        return [json.loads((Path(d) / name).read_text()) for name in ("n.json", "o.json")]


VALID_DOCS = _valid_documents()


@FUZZ
@given(
    which=st.integers(0, 1), pick=st.integers(0, 10**6), value=json_values, as_string=st.booleans()
)
def test_fuzz_mutated_documents(fuzz_dir, which, pick, value, as_string):
    """A valid document with one node replaced: loads or raises InputError, nothing else."""
    doc = json.loads(json.dumps(VALID_DOCS[which]))
    paths = list(json_paths(doc))
    path = paths[pick % len(paths)]
    # The original format nests JSON in strings: mutate inside them too.
    if as_string and which == 1 and len(path) == 3 and path[2] == 0:
        inner = json.loads(doc[path[0]][path[1]][0])
        inner_paths = list(json_paths(inner))
        inner = _replace(inner, inner_paths[pick % len(inner_paths)], value)
        doc = _replace(doc, path, json.dumps(inner))
    else:
        doc = _replace(doc, path, value)
    file = fuzz_dir / "mutated.json"
    file.write_text(json.dumps(doc))
    for reader in (read_native, read_original, load_recording):
        _loads_or_input_error(partial(reader, file))
    _loads_or_input_error(partial(read_original, file, layout="coco17"))


@FUZZ
@given(
    cut=st.integers(0, 10**6),
    flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), max_size=4),
)
def test_fuzz_corrupted_npz(fuzz_dir, cut, flips):
    path = fuzz_dir / "c.npz"
    write_npz(random_recording(3), path)
    data = bytearray(path.read_bytes())
    for pos, x in flips:
        data[pos % len(data)] ^= x
    data = data[: max(1, cut % (len(data) + 1))]
    path.write_bytes(bytes(data))
    _loads_or_input_error(partial(read_npz, path))
    os.remove(path)


# --------------------------------------------------------------------------- reading in ranges


def _long_recording(seed: int = 0, num_frames: int = 11) -> Recording:
    from mvpose_jax.synthetic import generate_recording

    return generate_recording(
        load_preset("panoptic5"), num_people=3, num_frames=num_frames, seed=seed
    )


def _assert_same_recording(got: Recording, want: Recording) -> None:
    assert got.cameras == want.cameras and got.layout == want.layout
    for name in ("xy", "score", "count"):
        a, b = np.asarray(getattr(got.detections, name)), np.asarray(getattr(want.detections, name))
        assert a.dtype == b.dtype, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    for name in ("identity", "timestamps", "image_names", "projected"):
        a, b = getattr(got, name), getattr(want, name)
        assert (a is None) == (b is None), name
        if a is not None:
            np.testing.assert_array_equal(a, b, err_msg=name)
    if want.ground_truth is not None:
        for a, b in zip(got.ground_truth, want.ground_truth, strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("storage", ["deflated", "stored", "fortran"])
@pytest.mark.parametrize(
    "options",
    [{}, {"cameras": ["trackerd", "trackera"]}, {"layout": "coco17"}],
    ids=["all", "cameras", "layout"],
)
@pytest.mark.parametrize("chunk", [1, 4, 11, 50])
def test_npz_read_in_ranges_equals_the_whole_file(tmp_path, storage, options, chunk):
    """open_recording reads an npz (stored or deflated members, or a Fortran-ordered one) range by
    range, with camera selection and layout conversion per range: the ranges joined are what
    load_recording reads (ranges have P of their own; joined, the whole file's)."""
    from tests.helpers import read_in_chunks

    path = tmp_path / "r.npz"
    write_npz(_long_recording(), path)
    if storage != "deflated":
        arrays = dict(np.load(path))
        if storage == "fortran":
            arrays["xy"] = np.asfortranarray(arrays["xy"])
        np.savez(path, **arrays)
    whole = load_recording(path, **options)
    joined, sizes = read_in_chunks(path, chunk, **options)
    _assert_same_recording(joined, whole)
    if "cameras" not in options:
        assert set(sizes) == {np.shape(whole.detections.score)[2]}  # the file's P in every range


def test_npz_range_reads_only_its_rows(tmp_path):
    """A range is read from the members without materialising them: frames never asked for are
    never checked (a NaN in frame 9 does not stop reading frames 0-7), and the error of the range
    holding it names frame 9 of the file."""
    from mvpose_jax.data import open_recording

    rec = _long_recording()
    path = tmp_path / "r.npz"
    write_npz(rec, path)
    arrays = dict(np.load(path))
    f, c = 9, int(np.argmax(arrays["count"][9] > 0))
    arrays["xy"][f, c, 0, 3] = np.nan
    arrays["score"][f, c, 0, 3] = 0.9
    np.savez_compressed(path, **arrays)
    with open_recording(path) as stream:
        assert stream.streamed and stream.num_frames == 11
        part = stream.read_frames(0, 8)
        np.testing.assert_array_equal(part.detections.xy, np.asarray(rec.detections.xy)[:8])
        with pytest.raises(InputError) as e:
            stream.read_frames(8, 11)
    assert e.value.frame == 9 and e.value.camera == rec.cameras[c] and e.value.field == "xy"
    with pytest.raises(InputError) as whole:
        load_recording(path)
    assert str(whole.value) == str(e.value)


def test_npz_ranges_give_one_clipping_warning_per_file(tmp_path):
    from mvpose_jax.data import open_recording
    from mvpose_jax.data.checks import ScoreClippedWarning

    path = tmp_path / "r.npz"
    write_npz(_long_recording(), path)
    arrays = dict(np.load(path))
    for f, value in ((0, 1.01), (5, 1.02), (10, 1.03)):
        c = int(np.argmax(arrays["count"][f] > 0))
        arrays["score"][f, c, 0, 0] = value
    np.savez(path, **arrays)
    with pytest.warns(ScoreClippedWarning) as caught, open_recording(path) as stream:
        parts = [r for _, r in stream.chunks(2)]
    assert len(caught) == 1
    assert "3 keypoint scores above 1 (largest 1.03)" in str(caught[0].message)
    assert max(float(np.max(r.detections.score)) for r in parts) == 1.0


def test_npz_truncated_member_is_an_error_when_its_range_is_read(tmp_path):
    """A member whose bytes end early (its zip entry claims more) fails the range that needs
    them, naming the file and member."""
    import zipfile

    from mvpose_jax.data import open_recording

    path = tmp_path / "r.npz"
    write_npz(_long_recording(), path)
    with zipfile.ZipFile(path) as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    cut = tmp_path / "cut.npz"
    with zipfile.ZipFile(cut, "w", zipfile.ZIP_STORED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    raw = bytearray(cut.read_bytes())
    # Corrupt the stored bytes of score's last frames: the CRC check at the member's end fails.
    with zipfile.ZipFile(cut) as zf:
        info = zf.getinfo("score.npy")
    end = info.header_offset + len(info.FileHeader()) + info.compress_size
    raw[end - 8 : end] = b"\xff" * 8
    cut.write_bytes(bytes(raw))
    with open_recording(cut) as stream:
        stream.read_frames(0, 5)
        with pytest.raises(InputError) as e:
            stream.read_frames(5, 11)
    assert e.value.field == "score" and e.value.file == str(cut)


@pytest.mark.parametrize("fmt", ["native", "original"])
def test_json_formats_are_loaded_whole_and_handed_out_in_ranges(tmp_path, fmt):
    from tests.helpers import read_in_chunks

    path = tmp_path / "r.json"
    save_recording(_long_recording(), path, format=fmt)
    from mvpose_jax.data import open_recording

    with open_recording(path) as stream:
        assert not stream.streamed
    joined, _ = read_in_chunks(path, 3, cameras=["trackerb", "trackerc"])
    _assert_same_recording(joined, load_recording(path, cameras=["trackerb", "trackerc"]))


def test_assembled_poses_equal_saved_poses_with_every_optional_member(tmp_path):
    """poses.npz / poses.json assembled chunk by chunk (people padded across chunks) equal
    save_poses of the joined results, tracks and filled keypoints included; partial when the
    chunks stop short of the recording."""
    from mvpose_jax.data.poses import (
        PoseResults,
        assemble_poses,
        load_poses,
        save_poses,
        save_poses_chunk,
    )

    rng = np.random.default_rng(0)
    K, C = 18, 3
    parts = []
    for F, G, P in ((3, 2, 4), (2, 4, 2), (1, 1, 3)):
        valid = rng.random((F, G)) < 0.7
        parts.append(
            PoseResults(
                Poses3D(
                    rng.normal(size=(F, G, K, 3)).astype(np.float32),
                    valid,
                    (rng.random((F, G, K)) < 0.8) & valid[..., None],
                ),
                rng.random((F, G)).astype(np.float32),
                np.where(valid[..., None], rng.integers(-1, P, (F, G, C)), -1).astype(np.int32),
                rng.integers(-1, G, (F, C, P)).astype(np.int32),
                ("a", "b", "c"),
                "coco18",
                rng.random(F),
                np.where(valid, rng.integers(0, 9, (F, G)), -1).astype(np.int32),
                rng.random((F, G, K)) < 0.1,
            )
        )
    paths, first = [], 0
    for i, part in enumerate(parts):
        paths.append(tmp_path / f"chunk_{i}.npz")
        save_poses_chunk(part, paths[-1], first_frame=first)
        first += len(part.confidence)

    def pad(a, size, axis, fill):
        widths = [(0, 0)] * a.ndim
        widths[axis] = (0, size - a.shape[axis])
        return np.pad(a, widths, constant_values=fill)

    def joined(parts, frames_total=None):
        cat = lambda get, fill=0, size=4, axis=1: np.concatenate(  # noqa: E731
            [pad(np.asarray(get(p)), size, axis, fill) for p in parts]
        )
        return PoseResults(
            Poses3D(
                cat(lambda p: p.poses.xyz),
                cat(lambda p: p.poses.valid, False),
                cat(lambda p: p.poses.keypoint_valid, False),
            ),
            cat(lambda p: p.confidence),
            cat(lambda p: p.members, -1),
            cat(lambda p: p.identity, -1, size=4, axis=2),
            ("a", "b", "c"),
            "coco18",
            np.concatenate([p.timestamps for p in parts]),
            cat(lambda p: p.track, -1),
            cat(lambda p: p.filled, False),
            frames_total,
        )

    for chunks, total in ((paths, 6), (paths[:2], 6)):
        want = joined(parts[: len(chunks)], None if len(chunks) == 3 else total)
        save_poses(want, tmp_path / "saved")
        npz_path, json_path, frames = assemble_poses(chunks, tmp_path / "out", frames_total=total)
        assert frames == len(want.confidence)
        assert json_path.read_text() == (tmp_path / "saved" / "poses.json").read_text()
        got = load_poses(npz_path)
        assert got.frames_total == want.frames_total and got.partial == (len(chunks) < 3)
        for name in ("confidence", "members", "identity", "timestamps", "track", "filled"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), name)
        for a, b in zip(got.poses, want.poses, strict=True):
            np.testing.assert_array_equal(a, b)
        assert load_poses(json_path).frames_total == want.frames_total
