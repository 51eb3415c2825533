"""Filtering and gap filling of tracked 3D poses, per track and keypoint.

Three parts, all host-side numpy/scipy, vectorised over tracks and keypoints:

* `one_euro_update` / `one_euro_frames`: the One-Euro filter (Casiez, Roussel and Vogel, CHI
  2012), causal and per frame, its state carried per track id: what a stream uses (it runs
  inside `inference.stream_pipeline`). The adaptive cut-off follows each keypoint's speed (the
  norm of its smoothed 3D velocity, m/s): ``min_cutoff_hz + beta * speed``, so a still keypoint
  is smoothed hard and a fast one follows with little lag.
* `butterworth` on a `TrackSeries`: zero-phase low-pass (``scipy.signal.butter`` as second-order
  sections, then ``sosfiltfilt``: forwards and backwards, no lag), the biomechanics default
  (Pose2Sim's, order 4; our default cut-off 2 Hz). Each run of samples of one keypoint of one
  track is filtered on its own: the filter never reaches across a gap that was not filled.
* `reject_outliers`: drops samples far from their local median (gross errors a linear filter
  would only spread).
* `fill_gaps`: interior gaps of at most ``max_frames`` frames of one keypoint of one track are
  filled with the cubic through the two nearest samples on each side (the cubic
  ``scipy.interpolate.CubicSpline`` fits to those four points; a quadratic or a line where a side
  has one sample). Local rather than one spline through the whole track: a global interpolating
  spline through noisy samples rings, and a gap's values should depend on its surroundings only.
  Not PCHIP: its shape-preserving slopes flatten the motion at every extremum and it does not
  reproduce a cubic. Gaps at the start or end of a track are never filled (no extrapolation),
  longer gaps are left whole, and a filled person-frame whose person was absent takes a free slot
  (no skeletons, confidence 0). Filled keypoints are flagged.

`smooth_poses` runs them on `PoseResults`: optionally One-Euro (causal, first), then outlier
rejection, gap filling, and optionally Butterworth over the filled runs (Pose2Sim's order: the
zero-phase filter also smooths the joins between measured and filled samples; filling after
filtering left kinks there that doubled the jitter on the validation scenes). The result stays
slot-major, with ``filled`` set.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Sequence
from pathlib import Path

import numba
import numpy as np
from scipy.signal import butter, sosfiltfilt

from mvpose_jax.data.poses import PoseResults, load_poses_chunk, save_poses_chunk
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Poses3D
from mvpose_jax.triangulate import insert_sorted, sorted_median

FILTERS = ("none", "one-euro", "butterworth")


# =========================================================================== One-Euro (streaming)


@dataclasses.dataclass(frozen=True)
class OneEuroConfig:
    """The One-Euro filter's settings (Casiez et al. 2012). The defaults were chosen on the
    validation scenes (geometric pipeline, 1-8 people): the least jitter whose MPJPE is no worse
    than unfiltered on every scene.

    Attributes:
      min_cutoff_hz: cut-off frequency of a still keypoint (Hz); lower: smoother, more lag.
      beta: how fast the cut-off rises with speed (Hz per m/s); higher: less lag when moving.
      d_cutoff_hz: cut-off of the velocity estimate that drives the adaptation (Hz).
    """

    min_cutoff_hz: float = 1.0
    beta: float = 7.0
    d_cutoff_hz: float = 1.0


@dataclasses.dataclass(frozen=True)
class OneEuroState:
    """The filter's memory per track (T rows, ids increasing).

    Attributes:
      ids: (T,) int64 track ids.
      xyz: (T, K, 3) the last filtered positions (metres).
      velocity: (T, K, 3) the last filtered velocities (m/s).
      time: (T, K) seconds of each keypoint's last sample (NaN: never seen).
    """

    ids: np.ndarray
    xyz: np.ndarray
    velocity: np.ndarray
    time: np.ndarray


def one_euro_initial(num_keypoints: int) -> OneEuroState:
    """No track filtered yet."""
    K = num_keypoints
    return OneEuroState(
        np.zeros(0, np.int64), np.zeros((0, K, 3)), np.zeros((0, K, 3)), np.zeros((0, K))
    )


def _norm(a: np.ndarray, axis: int = -1, keepdims: bool = False) -> np.ndarray:
    """Euclidean norm over an axis (np.linalg.norm's overhead matters per frame on small arrays)."""
    return np.sqrt(np.square(a).sum(axis, keepdims=keepdims))


@numba.njit(cache=True)
def _alpha(cutoff_hz: float, dt: float) -> float:
    """The smoothing factor of a first-order low-pass with this cut-off over a step dt."""
    tau = 1.0 / (2 * np.pi * cutoff_hz)
    return 1.0 / (1.0 + tau / dt)


@numba.njit(cache=True)
def _one_euro_step(rows, time, xyz, kv, memory_xyz, memory_v, memory_t, min_cutoff, beta, d_cutoff):
    """One frame of the filter, compiled (a frame is a few people: numpy's per-call overhead
    would dominate). Updates the memory rows (T, K, 3), (T, K, 3), (T, K) in place.

    Args:
      rows: (D,) each person's memory row; xyz (D, K, 3) metres; kv (D, K) measured keypoints.
    Returns:
      (D, K, 3) filtered positions (unmeasured keypoints pass through).
    """
    out = xyz.copy()
    for i in range(len(rows)):
        r = rows[i]
        for k in range(xyz.shape[1]):
            if not kv[i, k]:
                continue
            if np.isnan(memory_t[r, k]):  # a keypoint's first sample passes through
                memory_xyz[r, k] = xyz[i, k]
                memory_v[r, k] = 0.0
                memory_t[r, k] = time
                continue
            dt = max(time - memory_t[r, k], 1e-9)
            x_prev, v_prev = memory_xyz[r, k], memory_v[r, k]
            v_hat = v_prev + _alpha(d_cutoff, dt) * ((xyz[i, k] - x_prev) / dt - v_prev)
            cutoff = min_cutoff + beta * np.sqrt(np.sum(v_hat**2))
            x_hat = x_prev + _alpha(cutoff, dt) * (xyz[i, k] - x_prev)
            memory_xyz[r, k] = x_hat
            memory_v[r, k] = v_hat
            memory_t[r, k] = time
            out[i, k] = x_hat
    return out


def one_euro_update(
    state: OneEuroState,
    *,
    time: float,
    track: np.ndarray,
    xyz: np.ndarray,
    keypoint_valid: np.ndarray,
    config: OneEuroConfig = OneEuroConfig(),
) -> tuple[OneEuroState, np.ndarray]:
    """One frame of the One-Euro filter for D tracked people.

    Args:
      state: the filter's memory before this frame.
      time: the frame's time (seconds).
      track: (D,) track ids (each at most once).
      xyz: (D, K, 3) metres; keypoint_valid (D, K) which keypoints were measured (the others
        pass through and leave the memory as it was).
    Returns:
      (the new state, (D, K, 3) filtered positions). A keypoint's first sample passes through.
    """
    track = np.asarray(track, np.int64)
    ids = state.ids
    rows = np.searchsorted(ids, track)
    found = (
        (rows < len(ids)) & (ids[np.minimum(rows, len(ids) - 1)] == track) if len(ids) else rows < 0
    )
    if not found.all():
        new = np.unique(track[~found])
        K = xyz.shape[1]
        ids = np.concatenate([ids, new])
        order = np.argsort(ids, kind="stable")
        state = OneEuroState(
            ids[order],
            np.concatenate([state.xyz, np.zeros((len(new), K, 3))])[order],
            np.concatenate([state.velocity, np.zeros((len(new), K, 3))])[order],
            np.concatenate([state.time, np.full((len(new), K), np.nan)])[order],
        )
        ids = state.ids
        rows = np.searchsorted(ids, track)
    new_x, new_v, new_t = state.xyz.copy(), state.velocity.copy(), state.time.copy()
    out = _one_euro_step(
        rows,
        float(time),
        np.asarray(xyz, np.float64),
        np.asarray(keypoint_valid, bool),
        new_x,
        new_v,
        new_t,
        config.min_cutoff_hz,
        config.beta,
        config.d_cutoff_hz,
    )
    return OneEuroState(ids, new_x, new_v, new_t), out


def one_euro_frames(
    state: OneEuroState,
    *,
    times: np.ndarray,
    track: np.ndarray,
    xyz: np.ndarray,
    keypoint_valid: np.ndarray,
    config: OneEuroConfig = OneEuroConfig(),
) -> tuple[OneEuroState, np.ndarray]:
    """`one_euro_update` over F frames of slot-major poses.

    Args:
      times: (F,) seconds; track (F, G) ids (-1: no person); xyz (F, G, K, 3) metres;
        keypoint_valid (F, G, K).
    Returns:
      (the state after the last frame, (F, G, K, 3) filtered xyz; untracked slots unchanged).
    """
    out = np.array(xyz, np.float64)
    track = np.asarray(track)
    for f in range(len(track)):
        (g,) = np.nonzero(track[f] >= 0)
        if len(g):
            state, out[f, g] = one_euro_update(
                state,
                time=float(times[f]),
                track=track[f, g],
                xyz=out[f, g],
                keypoint_valid=np.asarray(keypoint_valid[f, g], bool),
                config=config,
            )
    return state, out


def one_euro_keep(state: OneEuroState, ids: np.ndarray) -> OneEuroState:
    """The memory of the tracks in ``ids`` only (ended tracks never come back)."""
    keep = np.isin(state.ids, ids)
    return OneEuroState(*(a[keep] for a in dataclasses.astuple(state)))


# =========================================================================== track series


@dataclasses.dataclass(frozen=True)
class TrackSeries:
    """Poses by track over each track's lifetime (first to last frame seen): N rows, track-major.

    Rows of one track are consecutive, one per frame from its first to its last appearance,
    so per-track time series are contiguous and memory stays about that of the slot-major poses.

    Attributes:
      track: (N,) int64 track id of each row; frame: (N,) its frame.
      slot: (N,) the row's slot in the slot-major poses, -1 where the person is absent.
      xyz: (N, K, 3) metres; keypoint_valid (N, K) measured (or already filled) keypoints.
    """

    track: np.ndarray
    frame: np.ndarray
    slot: np.ndarray
    xyz: np.ndarray
    keypoint_valid: np.ndarray

    @property
    def starts(self) -> np.ndarray:
        """(N,) True on each track's first row."""
        s = np.ones(len(self.track), bool)
        s[1:] = self.track[1:] != self.track[:-1]
        return s


def track_series(
    track: np.ndarray, valid: np.ndarray, xyz: np.ndarray, keypoint_valid: np.ndarray
) -> TrackSeries:
    """Slot-major (F, G) poses -> a `TrackSeries`.

    Args:
      track: (F, G) track ids, -1 none; valid (F, G); xyz (F, G, K, 3); keypoint_valid (F, G, K).
    Raises:
      InputError when a track holds two slots of one frame.
    """
    track = np.asarray(track, np.int64)
    f, g = np.nonzero(np.asarray(valid, bool) & (track >= 0))
    tid = track[f, g]
    K = np.shape(keypoint_valid)[-1]
    if len(tid) == 0:
        z = np.zeros(0, np.int64)
        return TrackSeries(z, z, z, np.zeros((0, K, 3)), np.zeros((0, K), bool))
    uniq, inv = np.unique(tid, return_inverse=True)
    first = np.full(len(uniq), np.iinfo(np.int64).max)
    last = np.full(len(uniq), -1)
    np.minimum.at(first, inv, f)
    np.maximum.at(last, inv, f)
    length = last - first + 1
    offset = np.concatenate([[0], np.cumsum(length)[:-1]])
    N = int(length.sum())
    row_track = np.repeat(uniq, length)
    row_frame = np.arange(N) - np.repeat(offset - first, length)
    row = offset[inv] + f - first[inv]
    if len(np.unique(row)) != len(row):
        dup = np.nonzero(np.bincount(row) > 1)[0][0]
        raise InputError(
            f"track {row_track[dup]} holds two people in one frame",
            frame=int(row_frame[dup]),
            field="track",
        )
    slot = np.full(N, -1, np.int64)
    slot[row] = g
    out_xyz = np.zeros((N, K, 3))
    out_kv = np.zeros((N, K), bool)
    out_xyz[row] = np.asarray(xyz)[f, g]
    out_kv[row] = np.asarray(keypoint_valid, bool)[f, g]
    return TrackSeries(row_track, row_frame, slot, out_xyz, out_kv)


def _runs(mask: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximal runs of True down each column of mask (N, K) that never cross a track start.

    Returns:
      (keypoint (R,), first row (R,), length (R,)), runs ordered by keypoint then row.
    """
    m = np.asarray(mask, bool).T  # (K, N)
    before = np.zeros_like(m)
    before[:, 1:] = m[:, :-1] & ~starts[None, 1:]
    after = np.zeros_like(m)
    after[:, :-1] = m[:, 1:] & ~starts[None, 1:]
    k, s = np.nonzero(m & ~before)
    _, e = np.nonzero(m & ~after)
    return k, s, e - s + 1


def reject_outliers(
    series: TrackSeries, *, max_deviation_m: float, half_window: int = 3
) -> tuple[TrackSeries, np.ndarray]:
    """Drops samples far from their track's local median (a Hampel-style test, per keypoint).

    A linear filter only spreads a gross error (a keypoint triangulated from two people's
    skeletons, a left/right swap) over its neighbours; removed here, it becomes a gap to fill.

    Args:
      series: the poses by track.
      max_deviation_m: a sample further than this (metres) from the median of its keypoint's
        samples within ``half_window`` frames either side (same track, itself included; only
        offsets measured on both sides, so a run's first and last samples are kept) is dropped.
    Returns:
      (the series without the outliers, (N, K) bool: the dropped samples).
    """
    x, kv = series.xyz, series.keypoint_valid
    # (N, K, 3); NaN for a window without a sample.
    med = _window_medians(
        np.asarray(x, np.float64), np.asarray(kv, bool), np.asarray(series.track), half_window
    )
    out = kv & (_norm(x - med, axis=-1) > max_deviation_m)
    return dataclasses.replace(series, keypoint_valid=kv & ~out), out


@numba.njit(cache=True)
def _window_medians(x, kv, track, half_window):
    """`reject_outliers`'s local medians: x (N, K, 3) metres, kv (N, K), track (N,) ->
    (N, K, 3) the median of each coordinate over the keypoint's samples at offsets
    -half_window..half_window of the same track, taken in pairs (offset -o only with +o), NaN
    where there is none (``np.nanmedian`` of those samples: a NaN coordinate is no sample).
    Compiled: as numpy, the windows' sort cost more than the Butterworth filter itself."""
    N, K = kv.shape
    W = 2 * half_window + 1
    med = np.empty((N, K, 3))
    pairs = np.empty((W, 2), np.int64)  # the sample's window: rows j, j2 = i + o, i - o
    rows = np.empty(W, np.int64)
    buf = np.empty(W)
    for i in range(N):
        P = 0
        for o in range(-half_window, half_window + 1):
            j, j2 = i + o, i - o
            if 0 <= j < N and 0 <= j2 < N and track[j] == track[i] and track[j2] == track[i]:
                pairs[P, 0], pairs[P, 1] = j, j2
                P += 1
        for k in range(K):
            R = 0
            for p in range(P):
                if kv[pairs[p, 0], k] and kv[pairs[p, 1], k]:
                    rows[R] = pairs[p, 0]
                    R += 1
            for a in range(3):
                n = 0
                for r in range(R):
                    if not np.isnan(x[rows[r], k, a]):
                        n = insert_sorted(buf, n, x[rows[r], k, a])
                med[i, k, a] = sorted_median(buf, n)
    return med


@functools.lru_cache(maxsize=32)
def _low_pass(order: int, cutoff_hz: float, fps: float) -> np.ndarray:
    """The Butterworth low-pass's second-order sections (designed once per setting: the design
    costs about 2 ms, as much as filtering a 256-frame chunk of a few tracks)."""
    return butter(order, cutoff_hz, btype="low", fs=fps, output="sos")


def butterworth(
    series: TrackSeries, *, fps: float, cutoff_hz: float = 6.0, order: int = 4
) -> TrackSeries:
    """Zero-phase Butterworth low-pass of every run of measured samples (gaps are never crossed).

    Args:
      series: the poses by track.
      fps: frames per second; cutoff_hz below fps / 2.
      order: of the low-pass (the zero-phase result's is twice this).
    Returns:
      The series with filtered xyz.
    """
    if not 0 < cutoff_hz < fps / 2:
        raise InputError(
            f"the cut-off {cutoff_hz:g} Hz must lie between 0 and half the frame rate ({fps / 2:g} Hz)",
            field="cutoff_hz",
        )
    # A copy: scipy's filter wants a writable array, and the cached one must stay as designed.
    sos = _low_pass(order, float(cutoff_hz), float(fps)).copy()
    # sosfiltfilt's own default edge padding; shorter runs are padded by what they have.
    pad = 3 * (2 * len(sos) + 1 - min((sos[:, 2] == 0).sum(), (sos[:, 5] == 0).sum()))
    k, s, n = _runs(series.keypoint_valid, series.starts)
    xyz = series.xyz.copy()
    for length in np.unique(n[n >= 2]):
        sel = n == length
        rows = s[sel, None] + np.arange(length)  # (R, L)
        kk = k[sel, None]
        xyz[rows, kk] = sosfiltfilt(sos, xyz[rows, kk], axis=1, padlen=min(pad, length - 1))
    return dataclasses.replace(series, xyz=xyz)


def fill_gaps(series: TrackSeries, *, max_frames: int) -> tuple[TrackSeries, np.ndarray]:
    """Fills interior gaps of at most ``max_frames`` frames (see the module docstring).

    Returns:
      (the series with the gaps filled and marked valid, (N, K) bool: the filled keypoints).
    """
    kv = series.keypoint_valid
    N, K = kv.shape
    filled = np.zeros((N, K), bool)
    if max_frames < 1 or N == 0:
        return series, filled
    starts = series.starts
    k, s, n = _runs(~kv, starts)
    e = s + n  # the first row after the gap
    interior = ~starts[s] & (e < N)
    interior[interior] &= ~starts[e[interior]]
    keep = interior & (n <= max_frames)
    k, s, n, e = k[keep], s[keep], n[keep], e[keep]
    if len(k) == 0:
        return series, filled
    # Nodes: two samples before the gap and two after, where they are measured and in the track.
    node = np.stack([s - 2, s - 1, e, e + 1], axis=1)  # (R, 4) rows
    inside = (node >= 0) & (node < N)
    nc = np.clip(node, 0, N - 1)
    ok = inside & kv[nc, k[:, None]]
    ok[:, 0] &= ~starts[s - 1]  # s-2 belongs to the track only if s-1 is not its first row
    ok[:, 3] &= inside[:, 3] & ~starts[np.clip(e + 1, 0, N - 1)]
    # Evaluation points: every row of every gap.
    gap = np.repeat(np.arange(len(k)), n)
    rows = s[gap] + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
    x = series.frame[rows].astype(np.float64)  # (Q,)
    xn = series.frame[nc].astype(np.float64)[gap]  # (Q, 4)
    okq = ok[gap]
    yn = series.xyz[nc[gap], k[gap, None]]  # (Q, 4, 3)
    # Lagrange basis over the available nodes.
    diff = xn[:, :, None] - xn[:, None, :]  # (Q, j, m)
    use = okq[:, None, :] & ~np.eye(4, dtype=bool)[None]
    num = np.where(use, x[:, None, None] - xn[:, None, :], 1.0).prod(-1)
    den = np.where(use, diff, 1.0).prod(-1)
    basis = np.divide(num, den, out=np.zeros_like(num), where=okq)  # (Q, 4)
    xyz = series.xyz.copy()
    xyz[rows, k[gap]] = (basis[..., None] * yn).sum(1)
    filled[rows, k[gap]] = True
    return dataclasses.replace(series, xyz=xyz, keypoint_valid=kv | filled), filled


# =========================================================================== on PoseResults


def smooth_poses(
    results: PoseResults,
    *,
    fps: float,
    filter: str = "butterworth",
    cutoff_hz: float = 2.0,
    order: int = 4,
    fill_gap_s: float = 0.5,
    outlier_m: float | None = 0.1,
    one_euro: OneEuroConfig = OneEuroConfig(),
) -> PoseResults:
    """Filters each track and fills its short gaps; returns slot-major results with ``filled``.

    Args:
      results: tracked poses (``results.track`` set).
      fps: frames per second of the recording.
      filter: "none", "one-euro" (causal, as the stream runs it) or "butterworth" (zero-phase).
      cutoff_hz, order: the Butterworth low-pass (2 Hz: chosen on the validation tracking scenes
        for both the learned and the geometric pipeline, see docs/tracking.md; the
        biomechanics default, Pose2Sim's, is 6 Hz, which leaves about 4x the true jitter here).
      outlier_m: first drop samples this far (metres) from their local median
        (`reject_outliers`); None: keep all.
      fill_gap_s: gaps of at most this long (seconds) are filled; 0: none.
      one_euro: the One-Euro settings.
    Raises:
      InputError when the results have no tracks or a setting is out of range.
    """
    if filter not in FILTERS:
        raise InputError(f"unknown filter {filter!r}; one of {FILTERS}", field="filter")
    if results.track is None:
        raise InputError(
            "the poses have no tracks (run infer with tracking on, i.e. without --no-track)",
            field="track",
        )
    if fps <= 0 or fill_gap_s < 0:
        raise InputError(f"fps {fps:g} must be > 0 and fill_gap_s {fill_gap_s:g} >= 0")
    poses = results.poses
    xyz = np.asarray(poses.xyz, np.float64)
    valid = np.asarray(poses.valid, bool)
    kv = np.asarray(poses.keypoint_valid, bool) & valid[..., None]
    F, G, K = kv.shape
    if filter == "one-euro":
        _, xyz = one_euro_frames(
            one_euro_initial(K),
            times=np.arange(F) / fps,
            track=np.where(valid, results.track, -1),
            xyz=xyz,
            keypoint_valid=kv,
            config=one_euro,
        )
    series = track_series(results.track, valid, xyz, kv)
    if outlier_m is not None:
        series, _ = reject_outliers(series, max_deviation_m=outlier_m)
    series, filled = fill_gaps(series, max_frames=int(np.floor(fill_gap_s * fps + 1e-9)))
    if filter == "butterworth":
        series = butterworth(series, fps=fps, cutoff_hz=cutoff_hz, order=order)
    return _to_slots(results, series, filled, xyz)


def _to_slots(
    results: PoseResults, series: TrackSeries, filled: np.ndarray, xyz: np.ndarray
) -> PoseResults:
    """Writes a series back into slot-major results; absent person-frames with filled keypoints
    take free slots (the person axis grows if a frame has none free)."""
    valid = np.asarray(results.poses.valid, bool)
    F, G, K = np.shape(results.poses.keypoint_valid)
    gained = (series.slot < 0) & series.keypoint_valid.any(-1)
    # Free slots per frame, in order; the k-th newcomer of a frame takes the k-th free slot.
    new_f = series.frame[gained]
    order = np.argsort(new_f, kind="stable")
    new_f_sorted = new_f[order]
    first_of_frame = np.searchsorted(new_f_sorted, new_f_sorted, side="left")
    rank = np.empty(len(new_f), np.int64)
    rank[order] = np.arange(len(new_f)) - first_of_frame
    need = np.bincount(new_f, minlength=F) if len(new_f) else np.zeros(F, np.int64)
    G2 = max(G, int((valid.sum(1) + need).max(initial=0)))
    pad = G2 - G

    def grow(a, fill):
        a = np.asarray(a)
        return np.pad(a, [(0, 0), (0, pad)] + [(0, 0)] * (a.ndim - 2), constant_values=fill).copy()

    valid2 = grow(valid, False)
    free = np.argsort(valid2, axis=1, kind="stable")  # free slots first, in slot order
    slot = series.slot.copy()
    slot[np.nonzero(gained)[0]] = free[new_f, rank]

    out_xyz = grow(xyz, 0.0)
    out_kv = grow(np.asarray(results.poses.keypoint_valid, bool) & valid[..., None], False)
    out_filled = grow(
        np.zeros((F, G, K), bool) if results.filled is None else results.filled, False
    )
    track = grow(results.track, -1)
    conf = grow(results.confidence, 0.0)
    members = grow(results.members, -1)
    have = slot >= 0
    f, g = series.frame[have], slot[have]
    out_xyz[f, g] = series.xyz[have]
    out_kv[f, g] = series.keypoint_valid[have]
    out_filled[f, g] |= filled[have]
    valid2[f, g] = True
    track[f, g] = series.track[have]
    return dataclasses.replace(
        results,
        poses=Poses3D(out_xyz.astype(np.float32), valid2, out_kv),
        confidence=conf,
        members=members,
        track=track,
        filled=out_filled,
    )


# =========================================================================== chunk by chunk

#: Frames of context on each side of a chunk when it is smoothed apart from the rest, in
#: seconds: beyond the outlier window, the longest filled gap (0.5 s by default) and the
#: Butterworth filter's response (at the 2 Hz default its impulse response is ~1e-6 of its peak
#: after 1 s), so a chunk comes out as it would from the whole recording.
CHUNK_CONTEXT_S = 3.0


def smooth_chunk_files(
    paths: Sequence[str | os.PathLike],
    folder: str | os.PathLike,
    *,
    fps: float,
    context_s: float = CHUNK_CONTEXT_S,
    **kwargs,
) -> list[Path]:
    """`smooth_poses` over a recording held as consecutive chunk files, in bounded memory.

    Each chunk is smoothed together with ``context_s`` seconds of its neighbours on each side
    (whole neighbouring chunks, as many as that takes), and only its own frames are kept; so
    memory is bounded by a chunk and its context, never the recording, and the result equals
    smoothing the whole recording up to the filter's response beyond the context (well under
    0.1 mm with the defaults; tested).

    Args:
      paths: chunk files (`data.poses.save_poses_chunk`) in frame order, tracked.
      folder: where the smoothed chunk files go (same names).
      fps, kwargs: as `smooth_poses`.
    Returns:
      the smoothed chunk files, in order.
    """
    paths = [Path(p) for p in paths]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    context = int(np.ceil(context_s * fps))
    cache: dict[int, tuple[int, PoseResults]] = {}

    def chunk(j: int) -> tuple[int, PoseResults]:
        if j not in cache:
            cache[j] = load_poses_chunk(paths[j])
        return cache[j]

    out = []
    for i, path in enumerate(paths):
        lo, covered = i, 0
        while lo > 0 and covered < context:
            lo -= 1
            covered += len(chunk(lo)[1].confidence)
        hi, covered = i, 0
        while hi + 1 < len(paths) and covered < context:
            hi += 1
            covered += len(chunk(hi)[1].confidence)
        for j in [j for j in cache if j < lo]:  # behind the window: never needed again
            del cache[j]
        parts = [chunk(j) for j in range(lo, hi + 1)]
        first, own = chunk(i)
        offset = first - parts[0][0]
        smoothed = smooth_poses(_joined([r for _, r in parts]), fps=fps, **kwargs)
        save_poses_chunk(
            _frames(smoothed, offset, offset + len(own.confidence)),
            folder / path.name,
            first_frame=first,
        )
        out.append(folder / path.name)
    return out


def _joined(parts: Sequence[PoseResults]) -> PoseResults:
    """Consecutive results along frames, people padded to the largest G, skeletons to P."""
    G = max(np.shape(r.confidence)[1] for r in parts)
    P = max(np.shape(r.identity)[2] for r in parts)

    def cat(get, fill=0, axis=1, size=G):
        arrays = []
        for r in parts:
            a = np.asarray(get(r))
            width = [(0, 0)] * a.ndim
            width[axis] = (0, size - a.shape[axis])
            arrays.append(np.pad(a, width, constant_values=fill))
        return np.concatenate(arrays)

    r0 = parts[0]
    has = lambda name: all(getattr(r, name) is not None for r in parts)  # noqa: E731
    return dataclasses.replace(
        r0,
        poses=Poses3D(
            cat(lambda r: r.poses.xyz),
            cat(lambda r: r.poses.valid),
            cat(lambda r: r.poses.keypoint_valid),
        ),
        confidence=cat(lambda r: r.confidence),
        members=cat(lambda r: r.members, -1),
        identity=cat(lambda r: r.identity, -1, axis=2, size=P),
        timestamps=np.concatenate([r.timestamps for r in parts]) if has("timestamps") else None,
        track=cat(lambda r: r.track, -1) if has("track") else None,
        filled=cat(lambda r: r.filled, False) if has("filled") else None,
        frames_total=None,
    )


def _frames(results: PoseResults, start: int, stop: int) -> PoseResults:
    """Frames ``start:stop`` of the results."""
    cut = lambda a: None if a is None else np.asarray(a)[start:stop]  # noqa: E731
    return dataclasses.replace(
        results,
        poses=Poses3D(*(cut(a) for a in results.poses)),
        confidence=cut(results.confidence),
        members=cut(results.members),
        identity=cut(results.identity),
        timestamps=cut(results.timestamps),
        track=cut(results.track),
        filled=cut(results.filled),
    )
