"""TRC, C3D and CSV exports, read back by readers that share no code with the writers: the
format descriptions (tests/helpers.py), ezc3d, OpenSim's own TRC reader, the csv module."""

from __future__ import annotations

import csv
import warnings

import numpy as np
import pytest

from mvpose_jax.data.exports import (
    ExportConfig,
    export_poses,
    frame_times,
    opensim_from_world,
    tracked_keypoints,
)
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.skeletons import Poses3D, get_layout
from tests.helpers import read_c3d, read_trc

KEYPOINTS = get_layout("coco18").keypoints
TOLERANCE_MM = 0.01


def tracked_results(
    *, num_frames=8, tracks=(0, 5, 9), slots=4, seed=0, timestamps=True, shuffle=True
):
    """People with known tracks in shuffled slots, some keypoints missing, some filled, the last
    track absent from frames 2 and 3. Returns (PoseResults, truth, filled): truth[track] (F, K, 3)
    world metres, NaN where the keypoint is not there; filled[track] (F, K) bool."""
    rng = np.random.default_rng(seed)
    F, G, K = num_frames, slots, len(KEYPOINTS)
    truth = {t: rng.normal(size=(F, K, 3)) * 2 + [0, 0, 1] for t in tracks}
    filled_truth = {t: rng.random((F, K)) < 0.2 for t in tracks}
    truth[tracks[-1]][2:4] = np.nan  # the last track leaves for frames 2 and 3
    for t in tracks:
        truth[t][rng.random((F, K)) < 0.15] = np.nan
        filled_truth[t] &= ~np.isnan(truth[t][..., 0])
    xyz = np.zeros((F, G, K, 3), np.float32)
    kv = np.zeros((F, G, K), bool)
    valid = np.zeros((F, G), bool)
    track = np.full((F, G), -1, np.int32)
    filled = np.zeros((F, G, K), bool)
    for f in range(F):
        order = rng.permutation(G) if shuffle else np.arange(G)
        for i, t in enumerate(tracks):
            g = order[i]
            here = ~np.isnan(truth[t][f, :, 0])
            if not here.any():
                continue
            valid[f, g], track[f, g] = True, t
            kv[f, g] = here
            xyz[f, g] = np.nan_to_num(truth[t][f])
            filled[f, g] = filled_truth[t][f]
    results = PoseResults(
        Poses3D(xyz, valid, kv),
        np.ones((F, G), np.float32),
        np.full((F, G, 2), -1, np.int32),
        np.full((F, 2, 1), -1, np.int32),
        ("a", "b"),
        "coco18",
        np.arange(F) / 25.0 + 100.0 if timestamps else None,
        track,
        filled,
    )
    # The poses hold float32: compare with what they hold.
    truth = {t: v.astype(np.float32).astype(np.float64) for t, v in truth.items()}
    return results, truth, filled_truth


@pytest.mark.parametrize(
    "up, expected",
    [
        ((0, 0, 1), [[1, 0, 0], [0, 0, 1], [0, -1, 0]]),
        ((0, -1, 0), [[1, 0, 0], [0, -1, 0], [0, 0, -1]]),
        ((0, 2, 0), np.eye(3)),
        ((0, 0, -3), [[1, 0, 0], [0, 0, -1], [0, 1, 0]]),
        ((1, 0, 0), [[0, 1, 0], [1, 0, 0], [0, 0, -1]]),
    ],
)
def test_the_opensim_rotation_of_axis_ups_in_closed_form(up, expected):
    np.testing.assert_allclose(opensim_from_world(up), expected, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_the_opensim_rotation_is_proper_with_y_along_up(seed):
    up = np.random.default_rng(seed).normal(size=3)
    R = opensim_from_world(up)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ (up / np.linalg.norm(up)), [0, 1, 0], atol=1e-12)
    # X is the world axis most orthogonal to up, moved into the floor plane
    axis = np.argmin(np.abs(up))
    assert np.argmax(np.abs(R[0])) == axis and R[0, axis] > 0


@pytest.mark.parametrize("up", [(0, 0, 0), (np.nan, 0, 1), (np.inf, 0, 0)])
def test_no_rotation_without_a_finite_up(up):
    with pytest.raises(InputError, match="up must be a non-zero finite vector"):
        opensim_from_world(up)


def test_tracks_regroup_shuffled_slots():
    results, truth, filled_truth = tracked_results()
    tracks = tracked_keypoints(results)
    assert tracks.ids.tolist() == [0, 5, 9]
    for i, t in enumerate(tracks.ids):
        here = ~np.isnan(truth[t][..., 0])
        np.testing.assert_array_equal(tracks.present[i], here)
        np.testing.assert_array_equal(tracks.xyz[i][here], truth[t][here])
        np.testing.assert_array_equal(tracks.filled[i], filled_truth[t])
    np.testing.assert_array_equal(tracks.in_frame[2], [1, 1, 0, 0, 1, 1, 1, 1])


def test_without_tracks_each_slot_is_a_track_with_a_warning():
    results, _, _ = tracked_results(shuffle=False)
    untracked = PoseResults(**{**results.__dict__, "track": None})
    with pytest.warns(MvposeWarning, match="slot is not the same person over time"):
        tracks = tracked_keypoints(untracked)
    assert tracks.ids.tolist() == [0, 1, 2]


def test_a_track_in_two_slots_of_a_frame_is_an_error_naming_the_frame():
    results, _, _ = tracked_results()
    track = results.track.copy()
    track[3][results.poses.valid[3]] = 5
    with pytest.raises(InputError, match="track 5 is in two slots of one frame") as e:
        tracked_keypoints(PoseResults(**{**results.__dict__, "track": track}))
    assert e.value.frame == 3


def test_people_without_a_track_are_left_out_with_a_warning():
    results, _, _ = tracked_results()
    track = results.track.copy()
    track[track == 5] = -1
    with pytest.warns(MvposeWarning, match="8 people .* have no track"):
        tracks = tracked_keypoints(PoseResults(**{**results.__dict__, "track": track}))
    assert tracks.ids.tolist() == [0, 9]


def test_frame_times():
    rate, times = frame_times(np.arange(5) / 50.0 + 7.0, 5)
    assert rate == pytest.approx(50.0)
    np.testing.assert_allclose(times, np.arange(5) / 50.0, atol=1e-9)
    rate, times = frame_times(None, 3, fps=10)
    assert rate == 10.0 and times.tolist() == [0.0, 0.1, 0.2]
    with pytest.raises(InputError, match="no timestamps, so the frame rate is unknown"):
        frame_times(None, 3)
    with pytest.raises(InputError, match="do not increase"):
        frame_times(np.zeros(3), 3)
    with pytest.raises(InputError, match="positive number of frames per second"):
        frame_times(None, 3, fps=0)
    with pytest.warns(MvposeWarning, match="C3D assumes a constant rate"):
        frame_times(np.array([0.0, 0.1, 0.2, 0.5, 0.6]), 5)


def to_world(xyz_file, R, per_metre):
    """Undoes the documented rotation and units: (..., 3) file -> world metres."""
    return xyz_file / per_metre @ R


@pytest.mark.parametrize("units, per_metre", [("mm", 1000.0), ("m", 1.0)])
def test_per_track_trc_and_c3d_read_back_independently(units, per_metre, tmp_path, monkeypatch):
    monkeypatch.setattr("mvpose_jax.data.exports._ROWS_PER_BLOCK", 3)  # text written in blocks
    results, truth, filled_truth = tracked_results()
    up = (0.0, 0.0, 1.0)
    R = opensim_from_world(up)
    config = ExportConfig(formats=("trc", "c3d"), units=units, up=up)
    paths = export_poses(results, tmp_path / "walk", config)
    assert [p.name for p in paths] == [
        f"walk_track{t}.{ext}" for ext in ("trc", "c3d") for t in (0, 5, 9)
    ]
    tol = TOLERANCE_MM / 1000
    for t in (0, 5, 9):
        trc = read_trc(tmp_path / f"walk_track{t}.trc")
        c3d = read_c3d(tmp_path / f"walk_track{t}.c3d")
        assert trc["names"] == list(KEYPOINTS) and c3d["labels"] == list(KEYPOINTS)
        assert trc["header"]["Units"] == units and c3d["parameters"]["POINT"]["UNITS"] == [units]
        assert float(trc["header"]["DataRate"]) == pytest.approx(25.0)
        assert c3d["rate"] == pytest.approx(25.0)
        assert float(c3d["parameters"]["POINT"]["RATE"]) == pytest.approx(25.0)
        np.testing.assert_allclose(c3d["parameters"]["MVPOSE"]["ROTATION"], R, atol=1e-7)
        assert trc["frame"].tolist() == list(range(1, 9)) and c3d["first_frame"] == 1
        np.testing.assert_allclose(trc["time"], np.arange(8) / 25.0, atol=1e-6)
        for got in (trc["xyz"], c3d["xyz"]):
            np.testing.assert_array_equal(np.isnan(got), np.isnan(truth[t]))
            np.testing.assert_allclose(to_world(got, R, per_metre), truth[t], atol=tol)
        # residual: -1 missing, 0 filled, positive measured
        here = ~np.isnan(truth[t][..., 0])
        np.testing.assert_array_equal(c3d["residual"] < 0, ~here)
        np.testing.assert_array_equal(c3d["residual"] == 0, filled_truth[t])
        assert (c3d["residual"][here & ~filled_truth[t]] > 0).all()


def test_world_axes_keep_the_coordinates(tmp_path):
    results, truth, _ = tracked_results()
    export_poses(results, tmp_path / "p", ExportConfig(formats=("trc",), axes="world"))
    got = read_trc(tmp_path / "p_track5.trc")["xyz"]
    np.testing.assert_allclose(got / 1000, truth[5], atol=TOLERANCE_MM / 1000)


def test_a_track_file_spans_the_track_with_the_recordings_frame_numbers(tmp_path):
    results, truth, _ = tracked_results()
    valid = results.poses.valid.copy()
    valid[:3][results.track[:3] == 0] = False  # track 0 appears at frame 3 (the 4th)
    results = PoseResults(**{**results.__dict__, "poses": results.poses._replace(valid=valid)})
    export_poses(results, tmp_path / "p", ExportConfig(formats=("trc", "c3d"), up=(0, 0, 1)))
    trc = read_trc(tmp_path / "p_track0.trc")
    assert trc["frame"].tolist() == [4, 5, 6, 7, 8]
    assert trc["header"]["OrigDataStartFrame"] == "4"
    np.testing.assert_allclose(trc["time"], np.arange(3, 8) / 25.0, atol=1e-6)
    c3d = read_c3d(tmp_path / "p_track0.c3d")
    assert c3d["first_frame"] == 4 and len(c3d["xyz"]) == 5


def test_one_file_names_markers_by_track_and_holds_more_than_255(tmp_path):
    tracks = tuple(range(0, 30, 2))  # 15 tracks x 18 keypoints = 270 markers
    results, truth, _ = tracked_results(tracks=tracks, slots=16, num_frames=5)
    up = (0.0, -1.0, 0.0)
    R = opensim_from_world(up)
    config = ExportConfig(formats=("trc", "c3d"), per_track=False, up=up)
    assert [p.name for p in export_poses(results, tmp_path / "all", config)] == [
        "all.trc",
        "all.c3d",
    ]
    names = [f"t{t}_{k}" for t in tracks for k in KEYPOINTS]
    want = np.concatenate([truth[t] for t in tracks], axis=1)  # (F, 270, 3)
    trc = read_trc(tmp_path / "all.trc")
    c3d = read_c3d(tmp_path / "all.c3d")
    assert trc["names"] == names and c3d["labels"] == names
    assert len(c3d["parameters"]["POINT"]["LABELS"]) == 255
    assert len(c3d["parameters"]["POINT"]["LABELS2"]) == 15
    for got in (trc["xyz"], c3d["xyz"]):
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_allclose(to_world(got, R, 1000.0), want, atol=TOLERANCE_MM / 1000)


def test_c3d_reads_back_with_ezc3d(tmp_path):
    ezc3d = pytest.importorskip("ezc3d")
    tracks = tuple(range(0, 30, 2))
    results, truth, _ = tracked_results(tracks=tracks, slots=16, num_frames=5)
    up = (0.3, 0.2, 0.9)
    R = opensim_from_world(up)
    for per_track in (True, False):
        export_poses(
            results, tmp_path / "p", ExportConfig(formats=("c3d",), per_track=per_track, up=up)
        )
    c = ezc3d.c3d(str(tmp_path / "p_track4.c3d"))
    point = c["parameters"]["POINT"]
    assert point["RATE"]["value"][0] == pytest.approx(25.0)
    assert point["UNITS"]["value"] == ["mm"] and point["LABELS"]["value"] == list(KEYPOINTS)
    got = c["data"]["points"][:3].transpose(2, 1, 0)  # (3, M, N) -> (N, M, 3)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(truth[4]))
    np.testing.assert_allclose(to_world(got, R, 1000.0), truth[4], atol=TOLERANCE_MM / 1000)
    c = ezc3d.c3d(str(tmp_path / "p.c3d"))
    point = c["parameters"]["POINT"]
    labels = point["LABELS"]["value"] + point["LABELS2"]["value"]
    assert labels == [f"t{t}_{k}" for t in tracks for k in KEYPOINTS]
    want = np.concatenate([truth[t] for t in tracks], axis=1)
    got = c["data"]["points"][:3].transpose(2, 1, 0)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(to_world(got, R, 1000.0), want, atol=TOLERANCE_MM / 1000)
    np.testing.assert_allclose(c["parameters"]["MVPOSE"]["ROTATION"]["value"], R, atol=1e-7)


def test_trc_reads_back_with_opensim(tmp_path):
    opensim = pytest.importorskip("opensim")
    results, truth, _ = tracked_results()
    up = (0.0, 0.0, 1.0)
    R = opensim_from_world(up)
    for per_track in (True, False):
        export_poses(
            results, tmp_path / "p", ExportConfig(formats=("trc",), per_track=per_track, up=up)
        )
    for name, markers, want in [
        ("p_track9.trc", list(KEYPOINTS), truth[9]),
        (
            "p.trc",
            [f"t{t}_{k}" for t in (0, 5, 9) for k in KEYPOINTS],
            np.concatenate([truth[t] for t in (0, 5, 9)], axis=1),
        ),
    ]:
        table = opensim.TimeSeriesTableVec3(str(tmp_path / name))
        assert list(table.getColumnLabels()) == markers
        assert table.getTableMetaDataAsString("DataRate") == "25"
        assert table.getTableMetaDataAsString("Units") == "mm"
        np.testing.assert_allclose(list(table.getIndependentColumn()), np.arange(8) / 25.0)
        got = np.array(
            [
                [[row[m].get(i) for i in range(3)] for m in range(len(markers))]
                for row in (table.getRowAtIndex(n) for n in range(table.getNumRows()))
            ]
        )
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_allclose(to_world(got, R, 1000.0), want, atol=TOLERANCE_MM / 1000)


def test_the_csv_is_one_tidy_row_per_keypoint(tmp_path, monkeypatch):
    monkeypatch.setattr("mvpose_jax.data.exports._ROWS_PER_BLOCK", 7)  # text written in blocks
    results, truth, filled_truth = tracked_results()
    R = opensim_from_world((0, 0, 1))
    export_poses(results, tmp_path / "p", ExportConfig(formats=("csv",), up=(0, 0, 1)))
    with open(tmp_path / "p.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["frame", "time", "track", "keypoint", "x", "y", "z", "filled"]
    assert len(rows) == sum(int((~np.isnan(v[..., 0])).sum()) for v in truth.values())
    keys = [(int(r["frame"]), int(r["track"]), KEYPOINTS.index(r["keypoint"])) for r in rows]
    assert keys == sorted(keys)
    for r, (f, t, k) in zip(rows, keys, strict=True):
        xyz = np.array([float(r["x"]), float(r["y"]), float(r["z"])])
        np.testing.assert_allclose(to_world(xyz, R, 1000.0), truth[t][f, k], atol=1e-5)
        assert float(r["time"]) == pytest.approx(f / 25.0, abs=1e-6)
        assert r["filled"] == str(int(filled_truth[t][f, k]))
    pandas = pytest.importorskip("pandas")
    table = pandas.read_csv(tmp_path / "p.csv")
    assert table["x"].dtype == float and table["filled"].dtype == int


@pytest.mark.parametrize(
    "config, match",
    [
        (ExportConfig(formats=("trc", "fbx"), up=(0, 0, 1)), "unknown export format 'fbx'"),
        (ExportConfig(formats=("trc",), units="cm", up=(0, 0, 1)), "unknown unit 'cm'"),
        (ExportConfig(formats=("trc",)), "the OpenSim axes need the world's up direction"),
        (ExportConfig(formats=("trc",), up=(0, 0, 1)), "no timestamps, so the frame rate"),
    ],
)
def test_bad_settings_fail_before_any_file(config, match, tmp_path):
    results, _, _ = tracked_results(timestamps=False)
    with pytest.raises(InputError, match=match):
        export_poses(results, tmp_path / "p", config)
    assert list(tmp_path.iterdir()) == []


def test_fps_replaces_missing_timestamps(tmp_path):
    results, _, _ = tracked_results(timestamps=False)
    export_poses(results, tmp_path / "p", ExportConfig(formats=("trc",), fps=120, up=(0, 1, 0)))
    trc = read_trc(tmp_path / "p_track0.trc")
    assert trc["header"]["DataRate"] == "120"
    np.testing.assert_allclose(trc["time"], np.arange(8) / 120, atol=1e-6)


def test_nobody_to_export_warns_and_writes_nothing(tmp_path):
    results, _, _ = tracked_results()
    nobody = PoseResults(
        **{
            **results.__dict__,
            "poses": results.poses._replace(valid=np.zeros_like(results.poses.valid)),
        }
    )
    with pytest.warns(MvposeWarning, match="nothing exported"):
        assert export_poses(nobody, tmp_path / "p", ExportConfig(up=(0, 0, 1))) == []
    assert list(tmp_path.iterdir()) == []


def test_the_c3d_writer_says_nothing_about_analog_channels(tmp_path):
    results, _, _ = tracked_results()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        export_poses(results, tmp_path / "p", ExportConfig(formats=("c3d",), up=(0, 0, 1)))
