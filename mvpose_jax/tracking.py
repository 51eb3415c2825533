"""Persistent person identities over time: a track id for every reconstructed person.

The pipeline's person axis is a slot within one frame; this module links slots of consecutive
frames into tracks. Host-side numpy, one frame at a time (the problem is sequential), vectorised
over tracks, people, cameras and keypoints.

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
4. `scipy.optimize.linear_sum_assignment` on the gated cost; unmatched people start new tracks
   (ids count up, never reused); tracks unseen for more than ``max_gap_s`` end.

The state is explicit (`TrackerState`), so a stream carries it from chunk to chunk and a chunked
run gives the same ids as a whole-recording run.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import linear_sum_assignment

from mvpose_jax.cameras import Rig

# A cost larger than any gate: "no match" for the assignment.
_NO_MATCH = 1e6


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Settings of the tracker.

    Attributes:
      max_gap_s: a track unseen for longer than this (seconds) ends; a person seen again within
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
    """

    max_gap_s: float = 1.0
    gate_m: float = 0.5
    gate_speed_mps: float = 1.0
    view_weight: float = 0.5
    min_common_keypoints: int = 3
    velocity_smoothing: float = 0.5
    max_speed_mps: float = 4.0


@dataclasses.dataclass(frozen=True)
class TrackerState:
    """The active tracks (T of them) and the next new id.

    Attributes:
      ids: (T,) int64 track ids, increasing (new tracks are appended with larger ids).
      xyz: (T, K, 3) metres, the last pose (keypoints not seen in the last match were moved with
        the track's velocity).
      keypoint_valid: (T, K) which keypoints of ``xyz`` were ever seen.
      velocity: (T, 3) m/s.
      last_time: (T,) seconds when each track was last matched.
      hits: (T,) int64 frames matched so far.
      xy: (T, C, K, 2) pixels, the last matched person's 2D skeletons; score (T, C, K) their
        scores (0: no skeleton or keypoint).
      time: the time of the last update (seconds; -inf before the first).
      next_id: the id the next new track gets.
    """

    ids: np.ndarray
    xyz: np.ndarray
    keypoint_valid: np.ndarray
    velocity: np.ndarray
    last_time: np.ndarray
    hits: np.ndarray
    xy: np.ndarray
    score: np.ndarray
    time: float = -np.inf
    next_id: int = 0


def initial_state(num_keypoints: int, num_cameras: int = 0) -> TrackerState:
    """No track yet: K keypoints per person, C cameras of 2D evidence (0: none)."""
    K, C = num_keypoints, num_cameras
    return TrackerState(
        ids=np.zeros(0, np.int64),
        xyz=np.zeros((0, K, 3)),
        keypoint_valid=np.zeros((0, K), bool),
        velocity=np.zeros((0, 3)),
        last_time=np.zeros(0),
        hits=np.zeros(0, np.int64),
        xy=np.zeros((0, C, K, 2), np.float32),
        score=np.zeros((0, C, K), np.float32),
    )


def metres_per_pixel(rig: Rig, centre: np.ndarray) -> np.ndarray:
    """How many metres one pixel spans at a point's depth in each camera.

    Args:
      rig: C cameras.
      centre: (..., 3) world points (metres).
    Returns:
      (..., C) depth / focal length (metres per pixel); inf behind a camera.
    """
    R, t, K = (np.asarray(a, np.float64) for a in (rig.R, rig.t, rig.K))
    depth = np.einsum("cj,...j->...c", R[:, 2], centre) + t[:, 2]
    focal = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    return np.where(depth > 0, depth / focal, np.inf)


def _norm(a: np.ndarray, axis: int = -1, keepdims: bool = False) -> np.ndarray:
    """Euclidean norm over an axis (np.linalg.norm's overhead matters per frame on small arrays)."""
    return np.sqrt(np.square(a).sum(axis, keepdims=keepdims))


def _masked_median(values: np.ndarray, mask: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(..., K) values -> (...) the (lower) median of the masked ones; inf where none.

    Robust where the mean is not: a few keypoints of a person built from two people's skeletons
    lie far off, and must not decide the match or the velocity.
    """
    ranked = np.sort(np.where(mask, values, np.inf), axis=-1)
    at = np.maximum((count - 1) // 2, 0)[..., None]
    return np.take_along_axis(ranked, at, axis=-1)[..., 0]


def _centres(xyz: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N, K, 3), (N, K) -> (N, 3) mean of the valid keypoints (0 where none)."""
    n = valid.sum(-1, keepdims=True)
    return (xyz * valid[..., None]).sum(-2) / np.maximum(n, 1)


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
    """One frame: matches its D people to the active tracks.

    Args:
      state: the tracks before this frame.
      time: the frame's time (seconds), later than ``state.time``.
      xyz: (D, K, 3) metres, the frame's people; keypoint_valid (D, K).
      xy, score: optional 2D evidence: (D, C, K, 2) pixels and (D, C, K) scores of each person's
        skeleton in each camera (score 0: none); metres_per_px (D, C) at the person (see
        `metres_per_pixel`).
      config: the tracker's settings.
    Returns:
      (the new state, (D,) int64 track id of each person).
    """
    D, K = keypoint_valid.shape
    T = len(state.ids)
    dt = time - state.last_time  # (T,)
    views = xy is not None and config.view_weight > 0 and state.xy.shape[1] > 0
    matched_track = np.full(D, -1, np.int64)
    if T and D:
        # (T, K, 3) constant-velocity prediction.
        pred = state.xyz + state.velocity[:, None] * dt[:, None, None]
        common = state.keypoint_valid[:, None] & keypoint_valid[None]  # (T, D, K)
        n_common = common.sum(-1)
        dist = _norm(pred[:, None] - xyz[None], axis=-1)  # (T, D, K)
        d_kp = _masked_median(dist, common, n_common)
        few = n_common < config.min_common_keypoints
        d3 = d_kp  # (T, D)
        if few.any():
            d_centre = _norm(
                _centres(pred, state.keypoint_valid)[:, None] - _centres(xyz, keypoint_valid)[None]
            )
            d3 = np.where(few, d_centre, d_kp)
        cost = d3
        # One track and one person: the assignment is decided by the gate (3D) alone.
        if views and T * D > 1:
            # Tracks seen in the previous frame, against each person's skeletons per camera.
            recent = state.last_time == state.time  # (T,)
            both = (state.score[:, None] > 0) & (score[None] > 0)  # (T, D, C, K)
            n2 = both.sum(-1)  # (T, D, C)
            px = _norm(state.xy[:, None] - xy[None], axis=-1)  # (T, D, C, K)
            d_px = (px * both).sum(-1) / np.maximum(n2, 1)
            have = (n2 >= config.min_common_keypoints) & recent[:, None, None]
            have &= np.isfinite(metres_per_px)[None]
            m_per_px = np.where(np.isfinite(metres_per_px), metres_per_px, 0.0)
            d_view = (d_px * m_per_px[None] * have).sum(-1) / np.maximum(have.sum(-1), 1)
            w = config.view_weight
            cost = np.where(have.any(-1), (1 - w) * cost + w * d_view, cost)
        # The gate is on the 3D distance alone: a wrong grouping (a ghost built from this
        # person's skeletons and another's) shares 2D skeletons with the person but lies apart.
        gate = config.gate_m + config.gate_speed_mps * dt  # (T,)
        ok = d3 <= gate[:, None]
        if T * D == 1:
            rows, cols = np.zeros(1, np.int64), np.zeros(1, np.int64)
        else:
            rows, cols = linear_sum_assignment(np.where(ok, cost, _NO_MATCH))
        keep = ok[rows, cols]
        rows, cols = rows[keep], cols[keep]
        matched_track[cols] = rows

    # Update the matched tracks.
    ids, xyz_t, kv_t = state.ids, state.xyz.copy(), state.keypoint_valid.copy()
    vel, last_time, hits = state.velocity.copy(), state.last_time.copy(), state.hits.copy()
    st_xy, st_score = state.xy.copy(), state.score.copy()
    m = matched_track >= 0
    if m.any():
        t_idx, d_idx = matched_track[m], np.nonzero(m)[0]
        dt_m = dt[t_idx][:, None]  # (M, 1)
        new_kv = keypoint_valid[d_idx]
        # A keypoint far off the prediction (a gross reconstruction error) neither moves the
        # track nor is stored: the track keeps its prediction there.
        off = dist[t_idx, d_idx] > gate[t_idx, None]  # (M, K)
        common = kv_t[t_idx] & new_kv & ~off
        n_common = common.sum(-1)
        disp = xyz[d_idx] - xyz_t[t_idx]  # (M, K, 3)
        disp_kp = _masked_median(disp.transpose(0, 2, 1), common[:, None], n_common[:, None])
        if (n_common == 0).any():
            disp_centre = _centres(xyz[d_idx], new_kv) - _centres(xyz_t[t_idx], kv_t[t_idx])
            disp_kp = np.where(n_common[:, None] >= 1, disp_kp, disp_centre)
        v_new = disp_kp / np.maximum(dt_m, 1e-9)
        new_kv = new_kv & ~(off & kv_t[t_idx])
        speed = _norm(v_new, axis=-1, keepdims=True)
        v_new *= np.minimum(1.0, config.max_speed_mps / np.maximum(speed, 1e-12))
        # The first measured velocity is taken whole; later ones blended with the estimate.
        a = np.where(hits[t_idx] == 1, 1.0, config.velocity_smoothing)[:, None]
        vel[t_idx] = a * v_new + (1 - a) * vel[t_idx]
        moved = xyz_t[t_idx] + (v_new * dt_m)[:, None]
        xyz_t[t_idx] = np.where(new_kv[..., None], xyz[d_idx], moved)
        kv_t[t_idx] |= new_kv
        last_time[t_idx] = time
        hits[t_idx] += 1
        if views:
            st_xy[t_idx], st_score[t_idx] = xy[d_idx], score[d_idx]

    # New tracks for the unmatched people.
    new = np.nonzero(~m)[0]
    new_ids = state.next_id + np.arange(len(new))
    track = matched_track.copy()
    track[m] = ids[matched_track[m]]
    track[new] = new_ids
    if len(new):
        C = st_xy.shape[1]
        ids = np.concatenate([ids, new_ids])
        xyz_t = np.concatenate([xyz_t, xyz[new]])
        kv_t = np.concatenate([kv_t, keypoint_valid[new]])
        vel = np.concatenate([vel, np.zeros((len(new), 3))])
        last_time = np.concatenate([last_time, np.full(len(new), time)])
        hits = np.concatenate([hits, np.ones(len(new), np.int64)])
        if views:
            st_xy = np.concatenate([st_xy, xy[new]])
            st_score = np.concatenate([st_score, score[new]])
        else:
            st_xy = np.concatenate([st_xy, np.zeros((len(new), C, K, 2), st_xy.dtype)])
            st_score = np.concatenate([st_score, np.zeros((len(new), C, K), st_score.dtype)])

    # Tracks unseen for longer than the gap end.
    alive = time - last_time <= config.max_gap_s
    if not alive.all():
        ids, xyz_t, kv_t, vel, last_time, hits, st_xy, st_score = (
            a[alive] for a in (ids, xyz_t, kv_t, vel, last_time, hits, st_xy, st_score)
        )
    return (
        TrackerState(
            ids, xyz_t, kv_t, vel, last_time, hits, st_xy, st_score, time, state.next_id + len(new)
        ),
        track,
    )


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
      (the state after the last frame, (F, G) int32 track id of each slot, -1 where empty).
    """
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
    for f in range(F):
        (d,) = np.nonzero(valid[f])
        state, ids = update_tracks(
            state,
            time=float(times[f]),
            xyz=xyz[f, d],
            keypoint_valid=keypoint_valid[f, d],
            xy=xy[f, d] if views else None,
            score=score[f, d] if views else None,
            metres_per_px=per_px[f, d] if views else None,
            config=config,
        )
        track[f, d] = ids
    return state, track
