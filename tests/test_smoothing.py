"""Filters and gap filling against scipy and closed forms; never across a gap, never past the
limit, never at the ends; absent person-frames filled into free slots and flagged."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.interpolate import CubicSpline
from scipy.signal import butter, sosfiltfilt

from mvpose_jax import smoothing
from mvpose_jax.data.poses import PoseResults, load_poses_chunk
from mvpose_jax.skeletons import Poses3D
from mvpose_jax.smoothing import (
    OneEuroConfig,
    butterworth,
    fill_gaps,
    one_euro_frames,
    one_euro_initial,
    one_euro_update,
    reject_outliers,
    smooth_poses,
    track_series,
)

FPS = 30.0


def _series(xyz, kv=None, track=None):
    """(F, K, 3) one person (or (F, G, K, 3)) -> a TrackSeries."""
    xyz = np.asarray(xyz, np.float64)
    if xyz.ndim == 3:
        xyz = xyz[:, None]
    F, G, K, _ = xyz.shape
    kv = np.ones((F, G, K), bool) if kv is None else np.asarray(kv).reshape(F, G, K)
    track = np.tile(np.arange(G), (F, 1)) if track is None else track
    return track_series(track, kv.any(-1), xyz, kv)


def test_butterworth_is_scipys_sosfiltfilt_on_a_gapless_series():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(120, 4, 3))
    got = butterworth(_series(x), fps=FPS, cutoff_hz=6.0).xyz
    sos = butter(4, 6.0, fs=FPS, output="sos")
    np.testing.assert_allclose(got, sosfiltfilt(sos, x, axis=0), atol=1e-12)


@pytest.mark.parametrize("freq_hz", [1.0, 3.0, 6.0, 9.0])
def test_butterworth_gain_on_a_sinusoid_is_the_closed_form(freq_hz):
    cutoff, order, F = 4.0, 4, 600
    t = np.arange(F) / FPS
    x = np.zeros((F, 1, 3))
    x[:, 0, 0] = np.sin(2 * np.pi * freq_hz * t)
    got = butterworth(_series(x), fps=FPS, cutoff_hz=cutoff, order=order).xyz[:, 0, 0]
    # The bilinear-transform Butterworth's magnitude, squared by the forward-backward pass.
    ratio = np.tan(np.pi * freq_hz / FPS) / np.tan(np.pi * cutoff / FPS)
    gain = 1.0 / (1.0 + ratio ** (2 * order))
    middle = slice(200, 400)  # away from the edges
    np.testing.assert_allclose(got[middle], gain * x[middle, 0, 0], atol=2e-3)


def test_butterworth_never_filters_across_an_unfilled_gap():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(100, 2, 3))
    kv = np.ones((100, 2), bool)
    kv[40:60, 0] = False  # 20 missing frames of keypoint 0
    got = butterworth(_series(x, kv), fps=FPS, cutoff_hz=5.0).xyz
    sos = butter(4, 5.0, fs=FPS, output="sos")
    np.testing.assert_allclose(got[:40, 0], sosfiltfilt(sos, x[:40, 0], axis=0), atol=1e-12)
    np.testing.assert_allclose(got[60:, 0], sosfiltfilt(sos, x[60:, 0], axis=0), atol=1e-12)
    np.testing.assert_allclose(got[:, 1], sosfiltfilt(sos, x[:, 1], axis=0), atol=1e-12)
    np.testing.assert_array_equal(got[40:60, 0], x[40:60, 0])  # untouched, still invalid
    with pytest.raises(Exception, match="cut-off"):
        butterworth(_series(x), fps=FPS, cutoff_hz=15.0)


def test_one_euro_constant_stays_constant_and_the_first_sample_passes():
    x = np.tile(np.array([0.3, -1.0, 2.0]), (50, 1, 4, 1))  # (F, G=1, K=4, 3)
    track = np.zeros((50, 1), int)
    _, out = one_euro_frames(
        one_euro_initial(4),
        times=np.arange(50) / FPS,
        track=track,
        xyz=x,
        keypoint_valid=np.ones((50, 1, 4), bool),
    )
    np.testing.assert_allclose(out, x, atol=1e-12)
    state, first = one_euro_update(
        one_euro_initial(4),
        time=0.0,
        track=np.array([5]),
        xyz=np.full((1, 4, 3), 7.0),
        keypoint_valid=np.ones((1, 4), bool),
    )
    np.testing.assert_array_equal(first, np.full((1, 4, 3), 7.0))
    assert state.ids.tolist() == [5]


def test_one_euro_with_beta_zero_is_the_closed_form_exponential_smoother():
    rng = np.random.default_rng(2)
    F, min_cutoff = 40, 2.0
    x = rng.normal(size=(F, 1, 1, 3))
    _, out = one_euro_frames(
        one_euro_initial(1),
        times=np.arange(F) / FPS,
        track=np.zeros((F, 1), int),
        xyz=x,
        keypoint_valid=np.ones((F, 1, 1), bool),
        config=OneEuroConfig(min_cutoff_hz=min_cutoff, beta=0.0),
    )
    tau = 1 / (2 * np.pi * min_cutoff)
    alpha = 1 / (1 + tau * FPS)
    ref = np.empty_like(x)
    ref[0] = x[0]
    for f in range(1, F):
        ref[f] = ref[f - 1] + alpha * (x[f] - ref[f - 1])
    np.testing.assert_allclose(out, ref, atol=1e-12)


def test_one_euro_keeps_each_tracks_memory_apart():
    # Two tracks in swapped slots: filtered as if each were alone.
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 30, 1, 2, 3))
    xyz = np.concatenate([a, b], axis=1)
    track = np.tile([0, 1], (30, 1))
    xyz[1::2] = xyz[1::2, ::-1]
    track[1::2] = track[1::2, ::-1]
    kv = np.ones((30, 2, 2), bool)
    _, both = one_euro_frames(
        one_euro_initial(2), times=np.arange(30) / FPS, track=track, xyz=xyz, keypoint_valid=kv
    )
    _, alone = one_euro_frames(
        one_euro_initial(2),
        times=np.arange(30) / FPS,
        track=np.zeros((30, 1), int),
        xyz=a,
        keypoint_valid=kv[:, :1],
    )
    np.testing.assert_allclose(both[track == 0], alone[:, 0], atol=1e-12)


def _cubic(t):
    return np.stack([0.01 * t**3 - 0.2 * t**2 + t, -0.003 * t**3 + 2.0, 0.5 * t], -1)


def test_gap_filling_is_exact_on_a_cubic_never_past_the_limit_never_at_the_ends():
    F = 60
    t = np.arange(F, dtype=float)
    x = np.repeat(_cubic(t)[:, None], 3, axis=1)  # (F, K=3, 3)
    kv = np.ones((F, 3), bool)
    kv[10:15, 0] = False  # 5 frames: filled
    kv[30:36, 0] = False  # 6 frames: longer than the limit, left whole
    kv[:4, 1] = False  # the start: never extrapolated
    kv[57:, 1] = False  # the end: never extrapolated
    kv[20, 2] = kv[22, 2] = False  # one sample between two gaps
    series, filled = fill_gaps(_series(x, kv), max_frames=5)
    np.testing.assert_allclose(series.xyz[10:15, 0], x[10:15, 0], atol=1e-9)
    assert filled[10:15, 0].all() and series.keypoint_valid[10:15, 0].all()
    assert not filled[30:36, 0].any() and not series.keypoint_valid[30:36, 0].any()
    assert not filled[:4, 1].any() and not filled[57:, 1].any()
    assert filled[[20, 22], 2].all()
    assert filled.sum() == 5 + 2
    # A side with one sample: the parabola through the three nodes (scipy's CubicSpline on
    # three points), frames 18, 19, 21 for the gap at 20 and 21, 23, 24 for the one at 22.
    for f, nodes in ((20, [18.0, 19, 21]), (22, [21.0, 23, 24])):
        ref = CubicSpline(nodes, _cubic(np.array(nodes)))(float(f))
        np.testing.assert_allclose(series.xyz[f, 2], ref, atol=1e-9)


def test_outliers_are_dropped():
    x = np.repeat(_cubic(np.arange(40.0) / 10)[:, None], 2, axis=1)
    x[17, 1] += [0.3, 0.0, 0.0]
    series, dropped = reject_outliers(_series(x), max_deviation_m=0.1)
    assert dropped.sum() == 1 and dropped[17, 1]
    assert not series.keypoint_valid[17, 1]


@pytest.mark.parametrize("half_window", [1, 3])
def test_outlier_medians_are_nanmedians_of_the_paired_windows(half_window):
    """The compiled window medians against `numpy.nanmedian` of the windows written out: the
    keypoint's samples at offsets -h..h of the same track, each offset only with its opposite,
    NaN coordinates no sample; random tracks, gaps and ties."""
    rng = np.random.default_rng(half_window)
    for case in range(40):
        N, K = int(rng.integers(1, 120)), int(rng.integers(1, 6))
        track = np.sort(rng.integers(0, 4, N))
        x = rng.normal(size=(N, K, 3))
        if case % 2:
            x = np.round(x, 1)  # ties
        x[rng.random(x.shape) < 0.03] = np.nan
        kv = rng.random((N, K)) < 0.8
        got = smoothing._window_medians(x, kv, track, half_window)
        for i in range(N):
            for k in range(K):
                rows = [
                    i + o
                    for o in range(-half_window, half_window + 1)
                    if 0 <= i + o < N
                    and 0 <= i - o < N
                    and track[i + o] == track[i] == track[i - o]
                    and kv[i + o, k]
                    and kv[i - o, k]
                ]
                for a in range(3):
                    v = x[rows, k, a]
                    want = np.median(v[~np.isnan(v)]) if (~np.isnan(v)).any() else np.nan
                    # (== : a tie of 0.0 and -0.0 sorts either way)
                    assert got[i, k, a] == want or (np.isnan(want) and np.isnan(got[i, k, a]))


def _results(xyz, valid, track, kv=None):
    F, G, K, _ = xyz.shape
    kv = np.repeat(valid[..., None], K, -1) if kv is None else kv
    return PoseResults(
        Poses3D(xyz.astype(np.float32), valid, kv),
        np.where(valid, 0.9, 0.0).astype(np.float32),
        np.where(valid[..., None], 0, -1).astype(np.int32) * np.ones((1, 1, 2), np.int32),
        np.zeros((F, 2, 1), np.int32),
        ("a", "b"),
        "coco18",
        None,
        track.astype(np.int32),
    )


def test_an_absent_person_frame_is_filled_into_a_free_slot_and_flagged():
    F, K = 20, 18
    t = np.arange(F, dtype=float) / 10
    p0 = np.repeat(_cubic(t)[:, None], K, 1)
    p1 = p0 + [2.0, 0.0, 0.0]
    xyz = np.stack([p0, p1], 1)
    valid = np.ones((F, 2), bool)
    track = np.tile([3, 8], (F, 1))
    valid[7:9, 0] = False  # track 3 absent in frames 7-8
    valid[9, 1] = False  # track 8 absent in frame 9
    track = np.where(valid, track, -1)
    valid[8, 1] = False  # frame 8: nobody at all
    track[8, 1] = -1
    out = smooth_poses(
        _results(xyz, valid, track), fps=10.0, filter="none", fill_gap_s=0.3, outlier_m=None
    )
    assert out.poses.valid.all()  # every person-frame now present
    for tid, ref in ((3, p0), (8, p1)):
        f, g = np.nonzero(out.track == tid)
        assert sorted(f.tolist()) == list(range(F))
        np.testing.assert_allclose(out.poses.xyz[f, g], ref[f], atol=1e-5)
    gained = ~valid & out.poses.valid[:, :2]
    assert out.filled[gained].all() and not out.filled[valid].any()
    assert (out.members[gained] == -1).all() and (out.confidence[gained] == 0).all()
    # Past the limit nothing is filled.
    short = smooth_poses(
        _results(xyz, valid, track), fps=10.0, filter="none", fill_gap_s=0.1, outlier_m=None
    )
    assert short.poses.valid.sum() == valid.sum() and not short.filled.any()  # gaps of 2 frames
    with pytest.raises(Exception, match="no tracks"):
        smooth_poses(
            _results(xyz, valid, track).__class__(
                **{**_results(xyz, valid, track).__dict__, "track": None}
            ),
            fps=10.0,
        )


def test_chunk_files_smoothed_with_their_neighbours_equal_the_whole_recording(tmp_path):
    from mvpose_jax.data.poses import save_poses_chunk
    from mvpose_jax.smoothing import smooth_chunk_files

    rng = np.random.default_rng(0)
    F, K, fps = 400, 18, 30.0
    t = np.arange(F) / fps
    walk = np.stack([np.sin(t), 0.5 * t, 0.1 * np.cos(3 * t)], -1)  # (F, 3)
    xyz = np.stack([walk, walk + [1.5, 0.0, 0.0]], 1)[:, :, None] + rng.normal(0, 0.2, (1, 2, K, 3))
    xyz = xyz + rng.normal(0, 0.01, xyz.shape)  # detector noise
    valid = np.ones((F, 2), bool)
    valid[100:105, 0] = False  # a short gap, filled
    kv = np.repeat(valid[..., None], K, -1)
    kv[200:260, 1, 3] = False  # a long one, left
    track = np.where(valid, np.tile([5, 9], (F, 1)), -1)
    res = _results(xyz, valid, track, kv)
    res = dataclasses.replace(res, timestamps=t)
    whole = smooth_poses(res, fps=fps)
    paths = []
    for first in range(0, F, 32):  # chunks much shorter than the 3 s of context
        path = tmp_path / f"chunk_{first:06d}.npz"
        save_poses_chunk(smoothing._frames(res, first, first + 32), path, first_frame=first)
        paths.append(path)
    out = smooth_chunk_files(paths, tmp_path / "smoothed", fps=fps)
    parts = [load_poses_chunk(p)[1] for p in out]
    joined = smoothing._joined(parts)
    np.testing.assert_array_equal(joined.poses.keypoint_valid, whole.poses.keypoint_valid)
    np.testing.assert_array_equal(joined.filled, whole.filled)
    np.testing.assert_array_equal(joined.track, whole.track)
    kvw = whole.poses.keypoint_valid
    err = np.abs(joined.poses.xyz - whole.poses.xyz)[kvw]
    assert err.max() < 1e-4  # 0.1 mm
    # ... and the context matters: without it the chunks' edges differ.
    bare = smooth_chunk_files(paths, tmp_path / "bare", fps=fps, context_s=0.0)
    cut = smoothing._joined([load_poses_chunk(p)[1] for p in bare])
    assert np.abs(cut.poses.xyz - whole.poses.xyz)[kvw].max() > 1e-3


def test_one_euro_follows_the_published_recurrence_with_gaps():
    """Casiez et al.'s filter written out per keypoint in plain Python (speed-adaptive cut-off,
    derivative filtered at d_cutoff), with a keypoint missing for some frames: it passes through
    there and the filter resumes from its memory, over the real elapsed time."""
    cfg = OneEuroConfig(min_cutoff_hz=1.5, beta=3.0, d_cutoff_hz=1.0)
    rng = np.random.default_rng(3)
    F, K = 30, 2
    x = np.cumsum(rng.normal(0, 0.05, (F, 1, K, 3)), axis=0)
    kv = np.ones((F, 1, K), bool)
    kv[10:14, 0, 1] = False
    _, out = one_euro_frames(
        one_euro_initial(K),
        times=np.arange(F) / FPS,
        track=np.zeros((F, 1), int),
        xyz=x,
        keypoint_valid=kv,
        config=cfg,
    )

    def alpha(cutoff, dt):
        return 1.0 / (1.0 + 1.0 / (2 * np.pi * cutoff * dt))

    for k in range(K):
        prev = None
        for f in range(F):
            if not kv[f, 0, k]:
                np.testing.assert_array_equal(out[f, 0, k], x[f, 0, k])
                continue
            if prev is None:
                x_hat, dx_hat = x[f, 0, k], np.zeros(3)
            else:
                t0, x0, dx0 = prev
                dt = f / FPS - t0
                dx_hat = dx0 + alpha(cfg.d_cutoff_hz, dt) * ((x[f, 0, k] - x0) / dt - dx0)
                cutoff = cfg.min_cutoff_hz + cfg.beta * np.linalg.norm(dx_hat)
                x_hat = x0 + alpha(cutoff, dt) * (x[f, 0, k] - x0)
            np.testing.assert_allclose(out[f, 0, k], x_hat, rtol=1e-10, atol=1e-12)
            prev = (f / FPS, x_hat, dx_hat)
