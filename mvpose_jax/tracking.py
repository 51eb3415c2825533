"""Persistent person identities over time: a track id for every reconstructed person.

The pipeline's person axis is a slot within one frame; this module links slots of consecutive
frames into tracks. Host-side, one frame at a time (the problem is sequential): the numeric core
of a frame is compiled with numba, the assignment is scipy's, the tracks' bookkeeping numpy. Over
a chunk (`track_frames`), the frames where nothing happens but matches of the people already
tracked (most of them) run whole in one compiled loop, with the same arithmetic.

Per frame (`update_tracks`):

1. Each active track predicts its pose at the frame's time: its last keypoints moved by its
   velocity (constant velocity, m/s) times the time since it was last seen.
2. Cost of track t and person d: the median distance (metres) between the prediction and the
   person over the keypoints both have (the distance of their centres of valid keypoints when
   they share fewer than ``min_common_keypoints``); where the track was seen in the previous
   frame and both have 2D skeletons in a camera, the 2D evidence joins in: the mean pixel distance
   between the track's last skeleton and the person's skeleton in that camera, times the person's
   metres per pixel there (depth / focal length), averaged over cameras and blended with weight
   ``view_weight``. 2D detections are more precise than their triangulation, and a person's
   skeletons in one camera barely move between frames.
3. Gate: no match whose 3D distance exceeds ``gate_m + gate_speed_mps * (time since the track
   was seen)``.
4. `scipy.optimize.linear_sum_assignment` on the gated cost, confirmed tracks first, then
   tentative ones on the people left. A person left within ``split_m`` of a track matched in
   the frame is a second proposal of that person (no new track; the one with more keypoints
   keeps the track). Other people start tentative tracks (track -1), confirmed after
   ``confirm_hits`` consecutive matches and ended at their first miss.
5. A newly confirmed track takes up a lost one (unseen up to ``relink_gap_s``) last seen near
   it with the same body size (keypoint-pair distances); else it gets a new id (ids count up,
   never reused). Tracks unseen for more than ``max_gap_s`` are lost: only a re-link finds them.

The state is explicit (`TrackerState`), so a stream carries it from chunk to chunk and a chunked
run gives the same ids as a whole-recording run.
"""

from __future__ import annotations

import dataclasses
import functools

import numba
import numpy as np
from scipy.optimize import linear_sum_assignment

from mvpose_jax.cameras import Rig, point_depths, project_points
from mvpose_jax.compiled import kept_per_object
from mvpose_jax.triangulate import nanmedian_along

# A cost larger than any gate: "no match" for the assignment.
_NO_MATCH = 1e6
# No 2D evidence: `_match_costs`'s 2D arguments, typed as the real ones (one compiled version).
_NO_XY = np.zeros((0, 0, 0, 2), np.float32)
_NO_SCORE = np.zeros((0, 0, 0), np.float32)
_NO_RECENT = np.zeros(0, bool)
_NO_PER_PX = np.zeros((0, 0))


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Settings of the tracker (defaults chosen on the validation tracking scenes,
    `experiments.tracking_scenes`).

    Attributes:
      max_gap_s: a track unseen for longer than this (seconds) is lost; a person seen again within
        it keeps their id.
      gate_m: the largest cost (metres) of a match one frame after the track was seen.
      gate_speed_mps: the gate grows by this (m/s) with the time since the track was seen (a
        person may have moved off the constant-velocity prediction meanwhile).
      view_weight: weight of the 2D evidence in the cost (0: 3D only).
      min_common_keypoints: fewer shared keypoints than this: the cost is the centres' distance.
      velocity_smoothing: weight of a new velocity measurement against the previous estimate
        (1: the last displacement only).
      max_speed_mps: velocity estimates are clipped to this speed (a wrong match cannot launch a
        track across the room).
      confirm_hits: a new track is tentative until matched in this many consecutive frames; a
        tentative track has no id (its people get track -1) and ends at its first miss, so a
        ghost (a person built from two people's skeletons) that lasts fewer frames leaves no
        track. Confirmed tracks are matched first. 1: every new person is a track at once.
      keypoint_ttl_s: a keypoint missing from (or far off in) a track's matches for longer than
        this (seconds) is forgotten and taken afresh from the next person matched, so a stale
        or wrong keypoint (one of a ghost's) cannot decide later matches. inf: kept for the
        track's life.
      split_m: a person left unmatched whose 3D cost to a track matched in the same frame is under
        this (metres) is part of that track's person (one person proposed twice, from different
        views): it starts no track and gets track -1; of the two, the one with more keypoints
        stays on the track. 0: off.
      relink_gap_s: a confirmed track unseen for up to this long (seconds, beyond ``max_gap_s``)
        may be taken up again by a new track when it is confirmed: the new track started after
        the old one was last seen, within ``gate_m + gate_speed_mps * (time unseen)`` of where
        it was last seen, with the same body size (``relink_size_tolerance``). It then keeps the
        old id. 0 (or not above ``max_gap_s`` with no unmatched candidate): off.
      relink_size_tolerance: the largest median relative difference of the two tracks' mean
        keypoint-pair distances (over the pairs rigid in the old track, such as limb lengths)
        for a re-link; with fewer than ``relink_min_pairs`` such pairs in common, position alone
        decides.
      relink_min_pairs: see ``relink_size_tolerance``.
      backfill: in `track_frames`, a track's tentative first frames get its id once it is
        confirmed (within the same call: in the pipeline, the same chunk), so a person is
        tracked from the frame they appear, not ``confirm_hits - 1`` frames later. A tentative
        track that ends unconfirmed (a ghost's) still leaves no id. False: those frames keep -1
        (what a strictly causal consumer of `update_tracks` sees).
    """

    max_gap_s: float = 1.0
    gate_m: float = 0.5
    gate_speed_mps: float = 1.0
    view_weight: float = 0.5
    min_common_keypoints: int = 3
    velocity_smoothing: float = 0.5
    max_speed_mps: float = 4.0
    confirm_hits: int = 3
    keypoint_ttl_s: float = 0.5
    split_m: float = 0.15
    relink_gap_s: float = 3.0
    relink_size_tolerance: float = 0.1
    relink_min_pairs: int = 1
    backfill: bool = True


# A keypoint pair is rigid in a track (a limb, not wrist to ankle) when its distance's standard
# deviation is under this share of its mean, over at least _RIGID_MIN_SAMPLES frames.
_RIGID_CV = 0.1
_RIGID_MIN_SAMPLES = 3
# Body size samples: every this many matches of a track (limb lengths are constant; sampling
# all frames would double the tracker's time per frame for nothing).
_SIZE_EVERY = 5


@dataclasses.dataclass(frozen=True)
class TrackerState:
    """The tracks (T of them: confirmed, tentative and lost ones) and the next new id.

    Attributes:
      ids: (T,) int64 track ids; -1 for a tentative track (it gets an id when confirmed).
      xyz: (T, K, 3) metres, the last pose (keypoints not seen in the last match were moved with
        the track's velocity).
      keypoint_valid: (T, K) which keypoints of ``xyz`` hold a measurement (seen within
        ``keypoint_ttl_s`` of the track's last match).
      keypoint_time: (T, K) seconds when each keypoint was last seen.
      velocity: (T, 3) m/s.
      first_time: (T,) seconds when each track was first matched.
      last_time: (T,) seconds when each track was last matched.
      hits: (T,) int64 frames matched so far.
      xy: (T, C, K, 2) pixels, the last matched person's 2D skeletons; score (T, C, K) their
        scores (0: no skeleton or keypoint).
      serial: (T,) int64 a number unique to each track over the stream, tentative ones
        included (their people are followed by it until they have an id).
      size_n, size_sum, size_sq: (T, K (K - 1) / 2) count, sum and sum of squares (metres) of
        each keypoint pair's distance (pairs i < j in `numpy.triu_indices` order), sampled every
        ``_SIZE_EVERY`` matches of the track from its first: its body size, for re-linking.
      time: the time of the last update (seconds; -inf before the first).
      next_id: the id the next confirmed track gets.
      next_serial: the serial the next new track gets.
    """

    ids: np.ndarray
    xyz: np.ndarray
    keypoint_valid: np.ndarray
    keypoint_time: np.ndarray
    velocity: np.ndarray
    first_time: np.ndarray
    last_time: np.ndarray
    hits: np.ndarray
    xy: np.ndarray
    score: np.ndarray
    size_n: np.ndarray
    size_sum: np.ndarray
    size_sq: np.ndarray
    serial: np.ndarray
    time: float = -np.inf
    next_id: int = 0
    next_serial: int = 0


# The per-track fields of `TrackerState` (rows are added and removed together).
_TRACK_FIELDS = tuple(f.name for f in dataclasses.fields(TrackerState))[:-3]


def initial_state(num_keypoints: int, num_cameras: int = 0) -> TrackerState:
    """No track yet: K keypoints per person, C cameras of 2D evidence (0: none)."""
    K, C = num_keypoints, num_cameras
    return TrackerState(
        ids=np.zeros(0, np.int64),
        xyz=np.zeros((0, K, 3)),
        keypoint_valid=np.zeros((0, K), bool),
        keypoint_time=np.zeros((0, K)),
        velocity=np.zeros((0, 3)),
        first_time=np.zeros(0),
        last_time=np.zeros(0),
        hits=np.zeros(0, np.int64),
        xy=np.zeros((0, C, K, 2), np.float32),
        score=np.zeros((0, C, K), np.float32),
        size_n=np.zeros((0, K * (K - 1) // 2), np.int32),
        size_sum=np.zeros((0, K * (K - 1) // 2)),
        size_sq=np.zeros((0, K * (K - 1) // 2)),
        serial=np.zeros(0, np.int64),
    )


def metres_per_pixel(rig: Rig, centre: np.ndarray) -> np.ndarray:
    """How many metres one pixel spans at a point's depth in each camera.

    Args:
      rig: C cameras.
      centre: (..., 3) world points (metres).
    Returns:
      (..., C) depth / focal length (metres per pixel); inf behind a camera.
    """
    axis, offset, focal = _depth_terms(rig)
    depth = np.einsum("cj,...j->...c", axis, centre) + offset
    return np.where(depth > 0, depth / focal, np.inf)


# Each rig's depth terms as host arrays, by rig (its arrays are immutable jax arrays). Fetching
# them from the device at every frame cost three round trips, about 30 us of a live frame's
# tracking.
_DEPTH_TERMS: dict[int, tuple[Rig, tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}


def _depth_terms(rig: Rig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(C, 3) the cameras' optical axes in world coordinates (R's last row), (C,) t's depth
    and (C,) the mean focal length (pixels), float64."""

    def fetch():
        R, t, K = (np.asarray(a, np.float64) for a in (rig.R, rig.t, rig.K))
        return R[:, 2], t[:, 2], 0.5 * (K[:, 0, 0] + K[:, 1, 1])

    return kept_per_object(_DEPTH_TERMS, rig, fetch, max_entries=64)


def _norm(a: np.ndarray, axis: int = -1, keepdims: bool = False) -> np.ndarray:
    """Euclidean norm over an axis (np.linalg.norm's overhead matters per frame on small arrays)."""
    return np.sqrt(np.square(a).sum(axis, keepdims=keepdims))


def _centres(xyz: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N, K, 3), (N, K) -> (N, 3) mean of the valid keypoints (0 where none)."""
    n = valid.sum(-1, keepdims=True)
    return (xyz * valid[..., None]).sum(-2) / np.maximum(n, 1)


# ------------------------------------------------------------------ compiled per-frame kernels
# The tracker runs once per frame on a handful of people: as numpy, every small array operation
# costs its call overhead (about 2 us here), and a lone person's frame needs about a hundred of
# them. The numeric core is therefore compiled with numba (loops over tracks, people, cameras and
# keypoints), leaving the assignment (scipy) and the bookkeeping of tracks in Python.


@numba.njit(cache=True)
def _lower_median(buf: np.ndarray, n: int) -> float:
    """The lower median of buf[:n] (inf when n is 0). Robust where the mean is not: a few
    keypoints of a person built from two people's skeletons lie far off, and must not decide the
    match or the velocity."""
    if n == 0:
        return np.inf
    # Insertion sort of buf[:n] in place (the callers' scratch): n is a skeleton's keypoints or
    # fewer, where it beats np.sort's copy and call. NaN sorts last, as in np.sort.
    for i in range(1, n):
        v = buf[i]
        j = i - 1
        while j >= 0 and (buf[j] > v or (np.isnan(buf[j]) and not np.isnan(v))):
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = v
    return buf[(n - 1) // 2]


@numba.njit(cache=True)
def _row_medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(N, P) values -> (N,) the lower median of each row's masked ones; inf where none."""
    N, P = values.shape
    out = np.empty(N)
    buf = np.empty(P)
    for i in range(N):
        n = 0
        for p in range(P):
            if mask[i, p]:
                buf[n] = values[i, p]
                n += 1
        out[i] = _lower_median(buf, n)
    return out


@numba.njit(cache=True)
def _centre(xyz: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(K, 3), (K,) -> (3,) mean of the valid keypoints (0 where none)."""
    out = np.zeros(3)
    n = 0
    for k in range(xyz.shape[0]):
        if valid[k]:
            out += xyz[k]
            n += 1
    return out / max(n, 1)


@numba.njit(cache=True)
def _match_costs(
    pred, kv_track, xyz, kv, min_common, track_xy, track_score, recent, xy, score, m_per_px, w
):
    """The costs of matching T tracks to D people.

    Args:
      pred: (T, K, 3) metres, the tracks' predicted poses; kv_track (T, K) their valid keypoints.
      xyz: (D, K, 3) metres, the people; kv (D, K).
      min_common: fewer shared keypoints: the 3D cost is the distance of the centres.
      track_xy, track_score: (T, C, K, 2) pixels and (T, C, K) scores of the tracks' last
        skeletons; recent (T,) whether they are from the previous frame.
      xy, score: (D, C, K, 2), (D, C, K) the people's skeletons; m_per_px (D, C).
      w: weight of the 2D evidence (0: none; then the 2D arrays may hold no camera).
    Returns:
      dist (T, D, K) keypoint distances (metres), d3 (T, D) 3D cost (metres), cost (T, D) with
      the 2D evidence blended in.
    """
    T, K = kv_track.shape
    D = kv.shape[0]
    C = track_xy.shape[1]
    dist = np.empty((T, D, K))
    d3 = np.empty((T, D))
    cost = np.empty((T, D))
    buf = np.empty(K)
    for t in range(T):
        for d in range(D):
            n = 0
            for k in range(K):
                e = np.sqrt(
                    (pred[t, k, 0] - xyz[d, k, 0]) ** 2
                    + (pred[t, k, 1] - xyz[d, k, 1]) ** 2
                    + (pred[t, k, 2] - xyz[d, k, 2]) ** 2
                )
                dist[t, d, k] = e
                if kv_track[t, k] and kv[d, k]:
                    buf[n] = e
                    n += 1
            if n >= min_common:
                c3 = _lower_median(buf, n)
            else:
                c3 = np.sqrt(np.sum((_centre(pred[t], kv_track[t]) - _centre(xyz[d], kv[d])) ** 2))
            d3[t, d] = c3
            cost[t, d] = c3
            if w <= 0 or not recent[t]:
                continue
            # Per camera: mean pixel distance of the two skeletons, in metres at the person.
            acc, views = 0.0, 0
            for c in range(C):
                if not np.isfinite(m_per_px[d, c]):
                    continue
                n2, px = 0, 0.0
                for k in range(K):
                    if track_score[t, c, k] > 0 and score[d, c, k] > 0:
                        px += np.sqrt(
                            (track_xy[t, c, k, 0] - xy[d, c, k, 0]) ** 2
                            + (track_xy[t, c, k, 1] - xy[d, c, k, 1]) ** 2
                        )
                        n2 += 1
                if n2 >= min_common:
                    acc += px / n2 * m_per_px[d, c]
                    views += 1
            if views:
                cost[t, d] = (1 - w) * c3 + w * acc / views
    return dist, d3, cost


@numba.njit(cache=True)
def _add_size_samples(t, xyz, kv, pair_i, pair_j, size_n, size_sum, size_sq):
    """Adds one person's keypoint-pair distances (xyz (K, 3) metres, valid where kv (K,); pairs
    pair_i, pair_j (P,)) to the body size sums of track row t (size_n, size_sum, size_sq
    (T, P)), in place."""
    for p in range(len(pair_i)):
        a, b = pair_i[p], pair_j[p]
        sq = 0.0
        for c in range(3):
            sq += (xyz[a, c] - xyz[b, c]) ** 2
        if kv[a] and kv[b]:
            size_n[t, p] += 1
            size_sum[t, p] += np.sqrt(sq)
            size_sq[t, p] += sq


@numba.njit(cache=True)
def _move_tracks(
    t_idx,
    d_idx,
    xyz,
    kv,
    dist,
    gate,
    dt,
    time,
    track_xyz,
    track_kv,
    velocity,
    keypoint_time,
    hits,
    smoothing,
    max_speed,
):
    """Moves matched track rows t_idx (M,) to their people d_idx (M,), in place.

    Per track: the velocity is the median displacement of the keypoints the track and the person
    share (the centres' displacement when none), clipped to ``max_speed`` and blended with the
    estimate (weight ``smoothing``; the first measurement whole); measured keypoints are stored,
    the others moved by the velocity. A keypoint beyond the track's gate from its prediction (a
    gross reconstruction error) is neither used nor stored where the track has it.

    Args:
      xyz: (D, K, 3) metres, the people; kv (D, K); dist (T, D, K) metres from the predictions
        (`_match_costs`); gate (T,) metres; dt (T,) seconds since each track was seen.
      track_xyz, track_kv, velocity, keypoint_time, hits: the track rows' fields (updated).
    Returns:
      (M, K) the keypoints stored from each person.
    """
    M = len(t_idx)
    K = kv.shape[1]
    stored = np.zeros((M, K), np.bool_)
    buf = np.empty((3, K))
    for m in range(M):
        t, d = t_idx[m], d_idx[m]
        step = max(dt[t], 1e-9)
        off = dist[t, d] > gate[t]
        n = 0
        for k in range(K):
            if track_kv[t, k] and kv[d, k] and not off[k]:
                for a in range(3):
                    buf[a, n] = xyz[d, k, a] - track_xyz[t, k, a]
                n += 1
        v = np.empty(3)
        if n:
            for a in range(3):
                v[a] = _lower_median(buf[a], n) / step
        else:
            v[:] = (_centre(xyz[d], kv[d]) - _centre(track_xyz[t], track_kv[t])) / step
        speed = np.sqrt(np.sum(v**2))
        v *= min(1.0, max_speed / max(speed, 1e-12))
        a_new = 1.0 if hits[t] == 1 else smoothing
        velocity[t] = a_new * v + (1 - a_new) * velocity[t]
        for k in range(K):
            keep = kv[d, k] and not (off[k] and track_kv[t, k])
            stored[m, k] = keep
            if keep:
                track_xyz[t, k] = xyz[d, k]
                track_kv[t, k] = True
                keypoint_time[t, k] = time
            else:
                track_xyz[t, k] += v * dt[t]
    return stored


# `_steady_frames`'s 2D evidence where there is none (typed as the real ones).
_NO_CHUNK_XY = np.zeros((0, 0, 0, 0, 2), np.float32)
_NO_CHUNK_SCORE = np.zeros((0, 0, 0, 0), np.float32)
_NO_CHUNK_PER_PX = np.zeros((0, 0, 0))


def _steady_config(config: TrackingConfig) -> tuple:
    """The settings `_steady_frames` reads, as a tuple of numbers."""
    return (
        float(config.max_gap_s),
        float(config.gate_m),
        float(config.gate_speed_mps),
        float(config.view_weight),
        int(config.min_common_keypoints),
        float(config.velocity_smoothing),
        float(config.max_speed_mps),
        float(config.keypoint_ttl_s),
        float(config.split_m),
        float(max(config.max_gap_s, config.relink_gap_s)),
        bool(config.relink_gap_s > 0),
    )


@numba.njit(cache=True)
def _steady_frames(
    f,
    times,
    xyz,
    kv,
    valid,
    xy,
    score,
    per_px,
    views,
    state_time,
    ids,
    track_xyz,
    track_kv,
    keypoint_time,
    velocity,
    last_time,
    hits,
    track_xy,
    track_score,
    size_n,
    size_sum,
    size_sq,
    pair_i,
    pair_j,
    config,
    track,
):
    """`_update_tracks` over frames f, f + 1, ... of a chunk for as long as nothing but matches
    happens, in place on the track rows; returns (the first frame left for `_update_tracks`, the
    state's time).

    A frame is taken here when every track is confirmed, none ends, the assignment is decided by
    the gate (each track within the gate of at most one person and each person of at most one
    track) and every person is matched or is part of a matched track's person: a frame of people
    already tracked, the common case. Any other frame (a new person, a tentative track, a
    confirmation, a re-link, an assignment to search, a track ending) is returned untouched to
    `_update_tracks`. The arithmetic is `_update_tracks`'s, in the same order, so the result is
    its bit for bit (`tests/test_tracking.py`).

    Args:
      times (F,), xyz (F, G, K, 3), kv (F, G, K), valid (F, G): the chunk (see `track_frames`);
        xy (F, G, C, K, 2), score (F, G, C, K), per_px (F, G, C) its 2D evidence where
        ``views``.
      ids ... size_sq: the `TrackerState` fields of the same names (``xyz`` as track_xyz,
        ``keypoint_valid`` as track_kv, ``xy``/``score`` as track_xy/track_score); pair_i,
        pair_j the keypoint pairs (`_pairs`).
      config: `TrackingConfig`'s numbers in `_steady_config`'s order.
      track: (F, G) int32 track ids, written for the frames taken.
    """
    (
        max_gap_s,
        gate_m,
        gate_speed,
        view_weight,
        min_common,
        smoothing,
        max_speed,
        ttl,
        split_m,
        keep_s,
        relink,
    ) = config
    F, G, K = kv.shape
    T = len(ids)
    no_xy = np.zeros((0, 0, 0, 2), np.float32)
    no_score = np.zeros((0, 0, 0), np.float32)
    no_recent = np.zeros(0, np.bool_)
    no_px = np.zeros((0, 0))
    for t in range(T):
        if ids[t] < 0:
            return f, state_time
    while f < F:
        time = times[f]
        for t in range(T):
            if time - last_time[t] > keep_s:
                return f, state_time
        d_idx = np.nonzero(valid[f])[0]
        D = len(d_idx)
        if D and not T:
            return f, state_time
        if np.isfinite(ttl):
            # Idempotent: a frame returned to `_update_tracks` after this computes the same.
            for t in range(T):
                for k in range(K):
                    if last_time[t] - keypoint_time[t, k] > ttl:
                        track_kv[t, k] = False
        if D:
            dt = time - last_time
            active = state_time - last_time <= max_gap_s
            pred = np.empty((T, K, 3))
            for t in range(T):
                for k in range(K):
                    for a in range(3):
                        pred[t, k, a] = track_xyz[t, k, a] + velocity[t, a] * dt[t]
            people = xyz[f][d_idx]
            people_kv = kv[f][d_idx]
            # One track and one person: the gate (3D) alone decides, as in `_update_tracks`.
            if views and view_weight > 0 and T * D > 1:
                t_xy, t_score, recent = track_xy, track_score, last_time == state_time
                p_xy, p_score, p_px, w = (
                    xy[f][d_idx],
                    score[f][d_idx],
                    per_px[f][d_idx],
                    view_weight,
                )
            else:
                t_xy, t_score, recent = no_xy, no_score, no_recent
                p_xy, p_score, p_px, w = no_xy, no_score, no_px, 0.0
            dist, d3, cost = _match_costs(
                pred,
                track_kv,
                people,
                people_kv,
                min_common,
                t_xy,
                t_score,
                recent,
                p_xy,
                p_score,
                p_px,
                w,
            )
            gate = gate_m + gate_speed * dt
            matched = np.full(D, -1, np.int64)
            if T * D == 1:
                if d3[0, 0] <= gate[0] and active[0]:
                    matched[0] = 0
            else:
                per_person = np.zeros(D, np.int64)
                for t in range(T):
                    n = 0
                    for d in range(D):
                        if d3[t, d] <= gate[t] and active[t]:
                            n += 1
                            per_person[d] += 1
                            matched[d] = t
                    if n > 1:
                        return f, state_time  # an assignment to search
                for d in range(D):
                    if per_person[d] > 1:
                        return f, state_time
            fragment = np.zeros(D, np.bool_)
            if split_m > 0 and T * D > 1 and (matched < 0).any():
                _split_people(d3, people_kv, matched, fragment, split_m)
            for d in range(D):
                if matched[d] < 0 and not fragment[d]:
                    # A new track: `_update_tracks` starts it. Nothing was changed but the
                    # keypoints' expiry, which it repeats.
                    return f, state_time
            m = np.nonzero(matched >= 0)[0]
            t_idx = matched[m]
            new_kv = _move_tracks(
                t_idx,
                m,
                people,
                people_kv,
                dist,
                gate,
                dt,
                time,
                track_xyz,
                track_kv,
                velocity,
                keypoint_time,
                hits,
                smoothing,
                max_speed,
            )
            for i in range(len(m)):
                t, d = t_idx[i], m[i]
                last_time[t] = time
                hits[t] += 1
                if views:
                    track_xy[t] = xy[f, d_idx[d]]
                    track_score[t] = score[f, d_idx[d]]
                if relink and hits[t] % _SIZE_EVERY == 1:
                    _add_size_samples(
                        t, people[d], new_kv[i], pair_i, pair_j, size_n, size_sum, size_sq
                    )
            for d in range(D):
                track[f, d_idx[d]] = ids[matched[d]] if matched[d] >= 0 else -1
        state_time = time
        f += 1
    return f, state_time


def update_tracks(
    state: TrackerState,
    *,
    time: float,
    xyz: np.ndarray,
    keypoint_valid: np.ndarray,
    xy: np.ndarray | None = None,
    score: np.ndarray | None = None,
    metres_per_px: np.ndarray | None = None,
    config: TrackingConfig = TrackingConfig(),
) -> tuple[TrackerState, np.ndarray]:
    """One frame: matches its D people to the tracks.

    Args:
      state: the tracks before this frame.
      time: the frame's time (seconds), later than ``state.time``.
      xyz: (D, K, 3) metres, the frame's people; keypoint_valid (D, K).
      xy, score: optional 2D evidence: (D, C, K, 2) pixels and (D, C, K) scores of each person's
        skeleton in each camera (score 0: none); metres_per_px (D, C) at the person (see
        `metres_per_pixel`).
      config: the tracker's settings.
    Returns:
      (the new state, (D,) int64 track id of each person; -1 for a person on a tentative track
      or part of a person already on a track, see ``TrackingConfig.confirm_hits`` and
      ``split_m``).
    """
    views = xy is not None
    state, track, _ = _update_tracks(
        state,
        time=time,
        xyz=np.asarray(xyz, np.float64),
        keypoint_valid=np.asarray(keypoint_valid, bool),
        xy=np.asarray(xy, np.float32) if views else None,
        score=np.asarray(score, np.float32) if views else None,
        metres_per_px=np.asarray(metres_per_px, np.float64) if views else None,
        config=config,
    )
    return state, track


def _update_tracks(
    state: TrackerState,
    *,
    time: float,
    xyz: np.ndarray,
    keypoint_valid: np.ndarray,
    xy: np.ndarray | None,
    score: np.ndarray | None,
    metres_per_px: np.ndarray | None,
    config: TrackingConfig,
) -> tuple[TrackerState, np.ndarray, np.ndarray]:
    """`update_tracks`, also returning the (D,) serial of each person's track (-1: none)."""
    D, K = keypoint_valid.shape
    T = len(state.ids)
    dt = time - state.last_time  # (T,)
    views = xy is not None and config.view_weight > 0 and state.xy.shape[1] > 0
    confirmed = state.ids >= 0
    # Lost tracks (unseen beyond the gap) wait for a re-link only; they are not matched.
    active = state.time - state.last_time <= config.max_gap_s
    # Keypoints the track's matches have lacked for too long are forgotten (not the keypoints
    # of a track unseen: its last pose is all there is to find it again).
    kv_track = state.keypoint_valid.copy()
    if np.isfinite(config.keypoint_ttl_s):
        kv_track &= state.last_time[:, None] - state.keypoint_time <= config.keypoint_ttl_s
    matched_track = np.full(D, -1, np.int64)
    fragment = np.zeros(D, bool)
    if T and D:
        # (T, K, 3) constant-velocity prediction.
        pred = state.xyz + state.velocity[:, None] * dt[:, None, None]
        # One track and one person: the assignment is decided by the gate (3D) alone.
        if views and T * D > 1:
            recent = state.last_time == state.time  # tracks seen in the previous frame
            evidence = (state.xy, state.score, recent, xy, score, metres_per_px)
            w = config.view_weight
        else:
            evidence = (_NO_XY, _NO_SCORE, _NO_RECENT, _NO_XY, _NO_SCORE, _NO_PER_PX)
            w = 0.0
        dist, d3, cost = _match_costs(
            pred, kv_track, xyz, keypoint_valid, config.min_common_keypoints, *evidence, w
        )
        # The gate is on the 3D distance alone: a wrong grouping (a ghost built from this
        # person's skeletons and another's) shares 2D skeletons with the person but lies apart.
        gate = config.gate_m + config.gate_speed_mps * dt  # (T,)
        ok = (d3 <= gate[:, None]) & active[:, None]
        # Confirmed tracks first: a tentative track (perhaps a ghost's) cannot take their people.
        _assign(cost, ok & confirmed[:, None], matched_track)
        if config.split_m > 0 and T * D > 1 and (matched_track < 0).any():
            _split_people(d3, keypoint_valid, matched_track, fragment, config.split_m)
        if not confirmed.all():
            free = (matched_track < 0) & ~fragment
            _assign(cost, ok & ~confirmed[:, None] & free[None], matched_track)

    # Update the matched tracks.
    # kv_track is already this frame's copy of the keypoints' validity.
    rows = {
        name: kv_track if name == "keypoint_valid" else getattr(state, name).copy()
        for name in _TRACK_FIELDS
    }
    relink = config.relink_gap_s > 0
    m = matched_track >= 0
    if m.any():
        t_idx, d_idx = matched_track[m], np.nonzero(m)[0]
        new_kv = _move_tracks(
            t_idx,
            d_idx,
            xyz,
            keypoint_valid,
            dist,
            gate,
            dt,
            time,
            rows["xyz"],
            rows["keypoint_valid"],
            rows["velocity"],
            rows["keypoint_time"],
            rows["hits"],
            config.velocity_smoothing,
            config.max_speed_mps,
        )
        rows["last_time"][t_idx] = time
        rows["hits"][t_idx] += 1
        if views:
            rows["xy"][t_idx], rows["score"][t_idx] = xy[d_idx], score[d_idx]
        if relink:
            sample = rows["hits"][t_idx] % _SIZE_EVERY == 1
            if sample.any():
                _add_sizes(rows, t_idx[sample], xyz[d_idx[sample]], new_kv[sample])

    # New tentative tracks for the people left (not for parts of a person already on a track).
    new = np.nonzero(~m & ~fragment)[0]
    if len(new):
        C = rows["xy"].shape[1]
        n = len(new)
        added = {
            "ids": np.full(n, -1, np.int64),
            "xyz": xyz[new],
            "keypoint_valid": keypoint_valid[new],
            "keypoint_time": np.where(keypoint_valid[new], time, -np.inf),
            "velocity": np.zeros((n, 3)),
            "first_time": np.full(n, time),
            "last_time": np.full(n, time),
            "hits": np.ones(n, np.int64),
            "xy": xy[new] if views else np.zeros((n, C, K, 2), np.float32),
            "score": score[new] if views else np.zeros((n, C, K), np.float32),
            "size_n": np.zeros((n,) + state.size_n.shape[1:], np.int32),
            "size_sum": np.zeros((n,) + state.size_n.shape[1:]),
            "size_sq": np.zeros((n,) + state.size_n.shape[1:]),
            "serial": state.next_serial + np.arange(n, dtype=np.int64),
        }
        rows = {name: np.concatenate([rows[name], added[name]]) for name in _TRACK_FIELDS}
        if relink:
            _add_sizes(rows, T + np.arange(n), xyz[new], keypoint_valid[new])
        matched_track[new] = T + np.arange(n)

    # Tentative tracks matched often enough are confirmed: an old track's id, or a new one.
    next_id = state.next_id
    ids = rows["ids"]
    tentative = ids < 0
    keep_s = max(config.max_gap_s, config.relink_gap_s)
    keep = time - rows["last_time"] <= keep_s
    if tentative.any():
        seen_now = rows["last_time"] == time
        for r in np.nonzero(tentative & seen_now & (rows["hits"] >= config.confirm_hits))[0]:
            old = _relink_candidate(rows, r, time, ~keep, config) if relink else -1
            if old >= 0:
                _merge_into(rows, old, r)
                keep[r] = False
                ids[r] = ids[old]
            else:
                ids[r] = next_id
                next_id += 1
        # Tentative tracks end at their first miss.
        keep &= seen_now | (ids >= 0)
    on = np.maximum(matched_track, 0)
    track = np.where(matched_track >= 0, ids[on], -1)
    serial = np.where(matched_track >= 0, rows["serial"][on], -1)

    # Confirmed tracks end once beyond any re-link.
    if not keep.all():
        rows = {name: a[keep] for name, a in rows.items()}
    next_serial = state.next_serial + len(new)
    return TrackerState(**rows, time=time, next_id=next_id, next_serial=next_serial), track, serial


def _assign(cost: np.ndarray, ok: np.ndarray, matched_track: np.ndarray) -> None:
    """Minimum-cost assignment of tracks (rows) to people (columns) where ``ok`` (T, D);
    writes each matched person's track row into ``matched_track`` (D,)."""
    if ok.size == 1:  # one track and one person (the common case of a lone person): no search
        if ok[0, 0]:
            matched_track[0] = 0
        return
    if (ok.sum(0) <= 1).all() and (ok.sum(1) <= 1).all():
        # Each track within the gate of at most one person and each person of at most one
        # track (people apart, the common case; no allowed pair at all, or one): the allowed
        # pairs are a matching, and the minimum-cost assignment takes all of them (leaving one
        # out costs a _NO_MATCH), so they are its result without the search.
        t, d = np.nonzero(ok)
        matched_track[d] = t
        return
    r_idx, c_idx = np.nonzero(ok.any(1))[0], np.nonzero(ok.any(0))[0]
    sub_ok = ok[r_idx][:, c_idx]
    rows, cols = linear_sum_assignment(np.where(sub_ok, cost[r_idx][:, c_idx], _NO_MATCH))
    keep = sub_ok[rows, cols]
    matched_track[c_idx[cols[keep]]] = r_idx[rows[keep]]


@numba.njit(cache=True)
def _split_people(
    d3: np.ndarray,
    keypoint_valid: np.ndarray,
    matched_track: np.ndarray,
    fragment: np.ndarray,
    split_m: float,
) -> None:
    """Marks the unmatched people within ``split_m`` (3D cost d3 (T, D)) of a matched track as
    parts of its person (``fragment``, (D,)); the one of them with the most keypoints (the
    first of equals), if it has more than the track's person, takes the track's place
    (``matched_track`` (D,)). Compiled: both tracker paths (`_update_tracks`, `_steady_frames`)
    call it."""
    support = keypoint_valid.sum(1)  # (D,)
    D = len(matched_track)
    for d in np.nonzero(matched_track >= 0)[0]:
        t = matched_track[d]
        best = -1
        for e in range(D):
            if matched_track[e] < 0 and not fragment[e] and d3[t, e] < split_m:
                fragment[e] = True
                if best < 0 or support[e] > support[best]:
                    best = e
        if best >= 0 and support[best] > support[d]:
            matched_track[best], matched_track[d] = t, -1
            fragment[best], fragment[d] = False, True


@functools.cache
def _pairs(num_keypoints: int) -> tuple[np.ndarray, np.ndarray]:
    """`numpy.triu_indices(num_keypoints, 1)`, made once (it costs more than a frame's sums)."""
    i, j = np.triu_indices(num_keypoints, 1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


def _add_sizes(rows: dict, t_idx: np.ndarray, xyz: np.ndarray, kv: np.ndarray) -> None:
    """Adds the people's (M, K, 3) keypoint-pair distances (valid where kv (M, K)) to the body
    size sums of track rows t_idx (M,)."""
    i, j = _pairs(kv.shape[-1])
    for m in range(len(t_idx)):
        _add_size_samples(
            t_idx[m], xyz[m], kv[m], i, j, rows["size_n"], rows["size_sum"], rows["size_sq"]
        )


def _relink_candidate(
    rows: dict, r: int, time: float, taken: np.ndarray, config: TrackingConfig
) -> int:
    """The row of the confirmed track that track row ``r`` continues, or -1.

    Candidates: confirmed tracks not seen since before ``r`` started, unseen for at most
    ``relink_gap_s``, last seen within the gate's reach of where ``r`` is now, with the same body
    size; the nearest of them.
    """
    ids, last = rows["ids"], rows["last_time"]
    gap = time - last
    cand = (ids >= 0) & ~taken & (last < rows["first_time"][r]) & (gap <= config.relink_gap_s)
    if not cand.any():
        return -1
    (c,) = np.nonzero(cand)
    # Where each was last seen: the keypoints of its last match (expired ones included).
    last_seen = rows["keypoint_time"] == last[:, None]  # (T, K)
    centre = _centres(rows["xyz"][c], last_seen[c])
    here = _centres(rows["xyz"][r][None], last_seen[r][None])[0]
    dist = _norm(centre - here)
    near = dist <= config.gate_m + config.gate_speed_mps * gap[c]
    # Body size: mean pair distances, over the pairs rigid in the old track.
    n_old = rows["size_n"][c]
    mean_old = rows["size_sum"][c] / np.maximum(n_old, 1)
    var_old = rows["size_sq"][c] / np.maximum(n_old, 1) - mean_old**2
    rigid = (n_old >= _RIGID_MIN_SAMPLES) & (var_old <= (_RIGID_CV * mean_old) ** 2)
    rigid &= mean_old > 0
    n_new = rows["size_n"][r]
    mean_new = rows["size_sum"][r] / np.maximum(n_new, 1)
    pairs = rigid & (n_new > 0)[None]  # (N, P)
    n_pairs = pairs.sum(-1)
    rel = np.abs(mean_new[None] - mean_old) / np.where(mean_old > 0, mean_old, 1.0)
    rel_med = _row_medians(rel, pairs)
    same_size = np.where(
        n_pairs >= config.relink_min_pairs, rel_med <= config.relink_size_tolerance, True
    )
    ok = near & same_size
    if not ok.any():
        return -1
    return int(c[ok][np.argmin(dist[ok])])


def _merge_into(rows: dict, old: int, r: int) -> None:
    """Track row ``old`` takes up track row ``r``'s present (pose, velocity, skeletons) and adds
    its body size samples."""
    for name in ("xyz", "keypoint_valid", "keypoint_time", "velocity", "last_time", "xy", "score"):
        rows[name][old] = rows[name][r]
    for name in ("hits", "size_n", "size_sum", "size_sq"):
        rows[name][old] += rows[name][r]


def track_frames(
    state: TrackerState,
    *,
    times: np.ndarray,
    xyz: np.ndarray,
    keypoint_valid: np.ndarray,
    valid: np.ndarray,
    xy: np.ndarray | None = None,
    score: np.ndarray | None = None,
    rig: Rig | None = None,
    config: TrackingConfig = TrackingConfig(),
) -> tuple[TrackerState, np.ndarray]:
    """`update_tracks` over F frames in order (a chunk of the pipeline's output).

    Args:
      state: the tracks before the first frame (`initial_state` for a new stream).
      times: (F,) seconds of each frame.
      xyz: (F, G, K, 3) metres; keypoint_valid (F, G, K); valid (F, G) which slots hold people.
      xy, score, rig: optional 2D evidence: each person's skeletons (F, G, C, K, 2) pixels and
        (F, G, C, K) scores (`inference.group_people`) in the C cameras of ``rig``.
      config: the tracker's settings.
    Returns:
      (the state after the last frame, (F, G) int32 track id of each slot, -1 where empty or
      not on a confirmed track; see ``TrackingConfig.backfill`` for a track's first frames).
    """
    times = np.asarray(times, np.float64)
    xyz = np.asarray(xyz, np.float64)
    keypoint_valid = np.asarray(keypoint_valid, bool)
    valid = np.asarray(valid, bool)
    F, G = valid.shape
    views = xy is not None and rig is not None and config.view_weight > 0
    if views and state.xy.shape[1] != rig.num_cameras:
        if len(state.ids):
            raise ValueError(
                f"the tracker state holds {state.xy.shape[1]} cameras, the rig {rig.num_cameras}"
            )
        state = initial_state(keypoint_valid.shape[-1], rig.num_cameras)
    if views:
        xy, score = np.asarray(xy, np.float32), np.asarray(score, np.float32)
        per_px = metres_per_pixel(rig, _centres(xyz, keypoint_valid))  # (F, G, C)
    track = np.full((F, G), -1, np.int32)
    # Tentative tracks' people so far, by track serial: (frames, slots), labelled once confirmed.
    pending: dict[int, tuple[list[int], list[int]]] = {}
    # The track rows, copied once: the frames of people already tracked update them in place
    # (`_steady_frames`); the others go through `_update_tracks`, which returns new ones.
    rows = {name: getattr(state, name).copy() for name in _TRACK_FIELDS}
    steady_config = _steady_config(config)
    pair_i, pair_j = _pairs(keypoint_valid.shape[-1])
    # `_steady_frames`'s 2D arguments: the chunk's evidence, or empty arrays of their types.
    chunk_2d = (xy, score, per_px) if views else (_NO_CHUNK_XY, _NO_CHUNK_SCORE, _NO_CHUNK_PER_PX)
    t_now = state.time
    f = 0
    while True:
        f, t_now = _steady_frames(
            f,
            times,
            xyz,
            keypoint_valid,
            valid,
            *chunk_2d,
            views,
            t_now,
            rows["ids"],
            rows["xyz"],
            rows["keypoint_valid"],
            rows["keypoint_time"],
            rows["velocity"],
            rows["last_time"],
            rows["hits"],
            rows["xy"],
            rows["score"],
            rows["size_n"],
            rows["size_sum"],
            rows["size_sq"],
            pair_i,
            pair_j,
            steady_config,
            track,
        )
        if f == F:
            break
        (d,) = np.nonzero(valid[f])
        state = dataclasses.replace(state, **rows, time=t_now)
        state, ids, serial = _update_tracks(
            state,
            time=float(times[f]),
            xyz=xyz[f, d],
            keypoint_valid=keypoint_valid[f, d],
            xy=xy[f, d] if views else None,
            score=score[f, d] if views else None,
            metres_per_px=per_px[f, d] if views else None,
            config=config,
        )
        rows = {name: getattr(state, name) for name in _TRACK_FIELDS}
        t_now = state.time
        track[f, d] = ids
        if config.backfill:
            for i in np.nonzero(serial >= 0)[0]:
                key = int(serial[i])
                if ids[i] < 0:
                    frames, slots = pending.setdefault(key, ([], []))
                    frames.append(f)
                    slots.append(int(d[i]))
                elif key in pending:
                    frames, slots = pending.pop(key)
                    track[frames, slots] = ids[i]
            if pending:
                # Tentative tracks end at their first miss: drop the ghosts that ended.
                alive = set(state.serial[state.ids < 0].tolist())
                pending = {k: v for k, v in pending.items() if k in alive}
        f += 1
    state = dataclasses.replace(state, **rows, time=t_now)
    return state, track


# =========================================================================== track-level association


@dataclasses.dataclass(frozen=True)
class AssociationConfig:
    """Skeletons grouped by the tracked people they fit (`associate_skeletons`, `regroup`).

    Attributes:
      gate: a skeleton joins a tracked person when the median distance of its keypoints to the
        person's projected keypoints is under this share of the person's image size (the
        diagonal of the projected keypoints' box).
      min_keypoints: fewer keypoints in common than this: the skeleton cannot join.
      hold_frames: a tracked person absent from a frame is held there from its nearest frame
        within this many (a person the grouping split or lost for a frame or two).
    """

    gate: float = 0.15
    min_keypoints: int = 3
    hold_frames: int = 3


def track_anchors(
    state: TrackerState,
    *,
    times: np.ndarray,
    track: np.ndarray,
    valid: np.ndarray,
    xyz: np.ndarray,
    keypoint_valid: np.ndarray,
    config: TrackingConfig,
    association: AssociationConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """The tracked people of a chunk of F frames, as anchors for `associate_skeletons`.

    Two sources: the chunk's own tracked people (ids >= 0; each held in frames it misses from its
    nearest frame within ``hold_frames``), and the confirmed tracks of ``state`` (the tracker
    before the chunk: the people of the last frames) that the chunk does not hold, moved by
    their velocity to each frame's time while unseen for at most ``config.max_gap_s``. A live
    stream (one frame a chunk) has only the second source.

    Args:
      state: the tracker's state before the chunk.
      times: (F,) seconds; track (F, G) ids of the chunk's people (-1 none); valid (F, G);
        xyz (F, G, K, 3); keypoint_valid (F, G, K).
    Returns:
      anchor xyz (F, A, K, 3) metres and keypoint validity (F, A, K).
    """
    track = np.where(np.asarray(valid, bool), np.asarray(track), -1)
    F, G, K = np.shape(keypoint_valid)
    ids = np.unique(track[track >= 0])
    out = np.zeros((F, len(ids), K, 3))
    ok = np.zeros((F, len(ids), K), bool)
    f, g = np.nonzero(track >= 0)
    a = np.searchsorted(ids, track[f, g])
    out[f, a] = np.asarray(xyz)[f, g]
    ok[f, a] = np.asarray(keypoint_valid, bool)[f, g]
    present = np.zeros((F, len(ids)), bool)
    present[f, a] = True
    held_from = np.where(present, np.arange(F)[:, None], -1)
    distance = np.where(present, 0, association.hold_frames + 1)
    for step in range(1, association.hold_frames + 1):
        for shift in (step, -step):  # nearest first, the earlier frame on a tie
            src = np.arange(F) - shift
            inside = (src >= 0) & (src < F)
            take = inside[:, None] & (distance > step) & present[np.clip(src, 0, F - 1)]
            held_from = np.where(take, np.clip(src, 0, F - 1)[:, None], held_from)
            distance = np.where(take, step, distance)
    fh, ah = np.nonzero((held_from >= 0) & ~present)
    out[fh, ah] = out[held_from[fh, ah], ah]
    ok[fh, ah] = ok[held_from[fh, ah], ah]
    # The tracker's people of the last frames that the chunk does not hold.
    old = (state.ids >= 0) & ~np.isin(state.ids, ids)
    if old.any():
        dt = np.asarray(times, np.float64)[:, None] - state.last_time[old][None]  # (F, T)
        live = (dt >= 0) & (dt <= config.max_gap_s)
        moved = state.xyz[old][None] + state.velocity[old][None, :, None, :] * dt[..., None, None]
        out = np.concatenate([out, np.where(live[..., None, None], moved, 0.0)], axis=1)
        ok = np.concatenate([ok, live[..., None] & state.keypoint_valid[old][None]], axis=1)
    return out, ok


def associate_skeletons(
    rig: Rig,
    xy: np.ndarray,
    score: np.ndarray,
    anchor_xyz: np.ndarray,
    anchor_ok: np.ndarray,
    config: AssociationConfig = AssociationConfig(),
) -> np.ndarray:
    """Each 2D skeleton's tracked person: the anchor it fits best in its view, one skeleton per
    anchor and view (greedy by distance, within the gate).

    Args:
      rig: the C cameras; xy (F, C, P, K, 2) pixels; score (F, C, P, K), 0 = missing.
      anchor_xyz: (F, A, K, 3) metres; anchor_ok (F, A, K) (`track_anchors`).
    Returns:
      (F, C, P) int: the anchor of each skeleton, -1 none.
    """
    F, C, P, K = np.shape(score)
    A = anchor_xyz.shape[1]
    owner = np.full((F, C, P), -1, np.int64)
    if A == 0 or P == 0:
        return owner
    pts = np.asarray(anchor_xyz, np.float32)
    px = np.moveaxis(np.asarray(project_points(rig, pts)), 0, 2)  # (F, A, C, K, 2)
    front = np.moveaxis(np.asarray(point_depths(rig, pts)) > 0, 0, 2)  # (F, A, C, K)
    usable = np.asarray(anchor_ok, bool)[:, :, None, :] & front  # (F, A, C, K)
    lo = np.where(usable[..., None], px, np.inf).min(axis=3)
    hi = np.where(usable[..., None], px, -np.inf).max(axis=3)
    size = np.linalg.norm(hi - lo, axis=-1)  # (F, A, C), inf/nan where nothing projects
    d = np.linalg.norm(
        np.asarray(xy)[:, :, :, None] - np.moveaxis(px, 1, 2)[:, :, None], axis=-1
    )  # (F, C, P, A, K)
    both = (np.asarray(score) > 0)[:, :, :, None, :] & np.moveaxis(usable, 1, 2)[:, :, None]
    med = nanmedian_along(np.where(both, d, np.nan), axis=-1)  # (F, C, P, A)
    rel = med / np.moveaxis(size, 1, 2)[:, :, None, :]
    fits = (both.sum(-1) >= config.min_keypoints) & (rel < config.gate) & np.isfinite(rel)
    cost = np.where(fits, rel, np.inf)
    flat = cost.reshape(F * C, P * A)
    own = owner.reshape(F * C, P)
    for _ in range(min(P, A)):
        best = flat.argmin(axis=1)
        found = np.isfinite(flat[np.arange(F * C), best])
        if not found.any():
            break
        r = np.nonzero(found)[0]
        p, a = np.divmod(best[r], A)
        own[r, p] = a
        block = flat.reshape(F * C, P, A)
        block[r, p, :] = np.inf
        block[r, :, a] = np.inf
    return own.reshape(F, C, P)


def regroup(members: np.ndarray, owner: np.ndarray, num_anchors: int) -> np.ndarray:
    """People from skeletons' anchors first, then what is left of the given people.

    Args:
      members: (F, G, C) each person's skeleton per camera, -1 none.
      owner: (F, C, P) each skeleton's anchor (-1 none), `associate_skeletons`.
    Returns:
      (F, G', C): the anchors' people (one per anchor with a skeleton in the frame), then the
      given people without the skeletons an anchor took, compacted to the front of each frame.
    """
    F, G, C = members.shape
    P = owner.shape[2]
    anchored = np.full((F, num_anchors, C), -1, np.int64)
    f, c, p = np.nonzero(owner >= 0)
    anchored[f, owner[f, c, p], c] = p
    m = np.asarray(members, np.int64)
    taken = np.take_along_axis(
        np.concatenate([owner, np.full((F, C, 1), -1)], axis=2),
        np.where(m >= 0, m, P).transpose(0, 2, 1),
        axis=2,
    ).transpose(0, 2, 1)  # (F, G, C): the anchor that took each member, -1 none
    left = np.where(taken >= 0, -1, m)
    both = np.concatenate([anchored, left], axis=1)
    filled = (both >= 0).any(-1)
    order = np.argsort(~filled, axis=1, kind="stable")
    both = np.take_along_axis(both, order[..., None], axis=1)
    width = max(1, int(filled.sum(1).max(initial=0)))
    return both[:, :width].astype(np.int32)
