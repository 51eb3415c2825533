"""Natural movement on the floor: paths, gait and on-the-spot activities.

Two stages:

1. `plan_paths`: a small crowd simulation at ``MotionConfig.sim_dt`` (5 Hz by default), vectorised
   over people. Each person alternates between walking to a goal in the capture area and doing
   one activity on the spot (stand, turn, reach, wave, crouch, bend). Walkers steer around others
   (social forces, with a keep-right bias so two people meeting head-on pass each other), and a
   hard constraint keeps every two people's footprints (circles whose radius grows with the
   activity: a reaching arm needs more room) ``personal_distance`` apart, so bodies never
   interpenetrate. Positions and headings are then interpolated to the frame rate with
   Catmull-Rom splines (smooth velocities).
2. `pose_angles`: per frame joint angles. Walking uses a gait cycle whose cadence and amplitude
   follow the speed (hip flexion-extension, two-peak knee flexion, counter-swinging arms, pelvis
   and trunk rotation); activities blend their target angles in and out with smooth envelopes;
   slow random drifts (sums of low-frequency sinusoids) keep still people alive.

Only stage 1 steps through time, at 5 Hz, not per frame; everything per frame is vectorised.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from mvpose_jax.synthetic.body import Bodies, PoseAngles
from mvpose_jax.synthetic.config import MotionConfig
from mvpose_jax.synthetic.scene import SceneGeometry

# Activities done on the spot.
STAND, TURN, REACH, WAVE, CROUCH, BEND = range(6)
ACTIVITIES = ("stand", "turn", "reach", "wave", "crouch", "bend")
# Footprint radius per activity and for walking, fraction of the height: the farthest any body
# volume reaches horizontally from the person's support point (measured on the body model, plus
# a margin), so that disjoint footprints mean disjoint bodies.
_FOOTPRINT = np.array([0.21, 0.21, 0.47, 0.30, 0.38, 0.50])
_FOOTPRINT_WALK = 0.30
_RAMP = 0.8  # seconds for an activity to blend in or out


class Paths(NamedTuple):
    """Planned movement of G people over F frames (floor coordinates)."""

    root: np.ndarray  # (F, G, 2) metres
    heading: np.ndarray  # (F, G) radians
    speed: np.ndarray  # (F, G) m/s
    # On-the-spot activity segments, S of them: person, kind, start and end time (seconds).
    seg_person: np.ndarray  # (S,) int
    seg_kind: np.ndarray  # (S,) int
    seg_start: np.ndarray  # (S,) float
    seg_end: np.ndarray  # (S,) float


def envelope(t: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Smooth 0 -> 1 -> 0 blend of an activity over [start, end] (seconds)."""
    ramp = np.minimum(_RAMP, np.maximum(end - start, 1e-3) / 3)
    a = np.clip((t - start) / ramp, 0, 1)
    b = np.clip((end - t) / ramp, 0, 1)
    return _smoothstep(a) * _smoothstep(b)


def plan_paths(
    geometry: SceneGeometry,
    bodies: Bodies,
    group: np.ndarray,
    num_frames: int,
    config: MotionConfig,
    rng: np.random.Generator,
) -> Paths:
    """Plans where G people walk and when they do what.

    Args:
      geometry: the rig's floor and capture area.
      bodies: the people's bodies (heights set their footprints and stride).
      group: (G,) int, people of the same group share a scene (they avoid each other); people of
        different groups never interact (independent recordings simulated together).
      num_frames: F.
      config: motion settings.
      rng: random generator.
    """
    G = bodies.num_people
    dt = config.sim_dt
    duration = num_frames / config.fps
    num_steps = int(np.ceil(duration / dt)) + 4
    times = (np.arange(num_steps) - 1) * dt  # one step before t = 0 for the spline
    cells = geometry.cells
    height = bodies.height
    same = (group[:, None] == group[None, :]) & ~np.eye(G, dtype=bool)
    interacting = bool(same.any())
    pd = config.personal_distance
    weights = np.asarray(config.activity_weights, np.float64)
    weights = weights / weights.sum()

    def sample_cells(n: int) -> np.ndarray:
        jitter = (rng.random((n, 2)) - 0.5) * geometry.cell_size
        return cells[rng.integers(0, len(cells), n)] + jitter

    # Initial positions: in the area, footprints apart (rejection per person: G is small).
    pos = sample_cells(G)
    for g in range(G):
        others = np.flatnonzero(same[g, :g])
        for _ in range(200):
            if others.size == 0:
                break
            gap = (
                np.linalg.norm(pos[others] - pos[g], axis=-1)
                - (height[others] + height[g]) * 0.3
                - pd
            )
            if gap.min() > 0:
                break
            pos[g] = sample_cells(1)[0]
    vel = np.zeros((G, 2))
    heading = rng.uniform(-np.pi, np.pi, G)
    target_heading = heading.copy()
    speed_pref = rng.uniform(*config.speed_range, G)
    walking = np.zeros(G, bool)
    goal = pos.copy()
    walk_deadline = np.zeros(G)
    # Everybody starts with a short on-the-spot activity (staggered starts).
    seg_person, seg_kind, seg_start, seg_end = [], [], [], []
    kind = rng.choice(6, G, p=weights)
    t_end = rng.uniform(0.3, config.activity_duration[1], G)
    t_begin = np.full(G, times[0])
    for g in range(G):
        (
            seg_person.append(g),
            seg_kind.append(kind[g]),
            seg_start.append(times[0]),
            seg_end.append(t_end[g]),
        )

    out_pos = np.empty((num_steps, G, 2))
    out_head = np.empty((num_steps, G))
    for k, t in enumerate(times):
        # --- transitions
        done_still = ~walking & (t >= t_end)
        arrived = walking & ((np.linalg.norm(goal - pos, axis=-1) < 0.3) | (t > walk_deadline))
        if done_still.any():
            to_walk = done_still & (rng.random(G) < config.walk_probability)
            idx = np.flatnonzero(to_walk)
            if idx.size:
                new_goal = sample_cells(idx.size)
                # Prefer goals at least a metre away (one redraw keeps it vectorised).
                near = np.linalg.norm(new_goal - pos[idx], axis=-1) < 1.0
                new_goal[near] = sample_cells(int(near.sum()))
                goal[idx] = new_goal
                walking[idx] = True
                dist = np.linalg.norm(new_goal - pos[idx], axis=-1)
                walk_deadline[idx] = t + 3.0 * dist / speed_pref[idx] + 2.0
            start_still = done_still & ~to_walk
        else:
            start_still = done_still
        start_still = start_still | arrived
        if start_still.any():
            idx = np.flatnonzero(start_still)
            walking[idx] = False
            new_kind = rng.choice(6, idx.size, p=weights)
            new_end = t + rng.uniform(*config.activity_duration, idx.size)
            kind[idx], t_end[idx], t_begin[idx] = new_kind, new_end, t
            turn = rng.random(idx.size) < 0.5
            turn |= new_kind == TURN
            new_target = np.where(turn, rng.uniform(-np.pi, np.pi, idx.size), target_heading[idx])
            if interacting:
                # Face the nearest person of the scene (a conversation) some of the time.
                d = np.linalg.norm(pos[idx, None] - pos[None], axis=-1)
                d = np.where(same[idx], d, np.inf)
                nearest = d.argmin(-1)
                face = (
                    turn
                    & np.isfinite(d.min(-1))
                    & (rng.random(idx.size) < config.face_others_probability)
                )
                to = pos[nearest] - pos[idx]
                new_target = np.where(face, np.arctan2(to[:, 1], to[:, 0]), new_target)
            target_heading[idx] = new_target
            seg_person.extend(idx.tolist())
            seg_kind.extend(new_kind.tolist())
            seg_start.extend([t] * idx.size)
            seg_end.extend(new_end.tolist())

        # --- footprints: grow with the activity's envelope, walking people need stride room
        env = envelope(t, t_begin, t_end)
        radius = height * np.where(
            walking, _FOOTPRINT_WALK, _FOOTPRINT[0] + env * (_FOOTPRINT[kind] - _FOOTPRINT[0])
        )

        # --- desired velocity: towards the goal, slowing down in the last half metre
        to_goal = goal - pos
        dist = np.linalg.norm(to_goal, axis=-1, keepdims=True)
        v_des = np.where(
            walking[:, None],
            to_goal / np.maximum(dist, 1e-9) * speed_pref[:, None] * np.minimum(1, dist / 0.5),
            0,
        )
        if interacting:
            diff = pos[:, None] - pos[None]  # (G, G, 2) from others to me
            d = np.linalg.norm(diff, axis=-1)
            gap = d - radius[:, None] - radius[None] - pd
            unit = diff / np.maximum(d, 1e-9)[..., None]
            # Social force, rotated a little to the right so that head-on meetings resolve.
            strength = np.where(same, 1.2 * np.exp(-np.maximum(gap, 0) / 0.4), 0.0)
            rot = unit @ np.array([[np.cos(-0.4), np.sin(-0.4)], [-np.sin(-0.4), np.cos(-0.4)]])
            push = (strength[..., None] * rot).sum(1)
            v_des = v_des + np.where(walking[:, None], push, 0)
        dv = v_des - vel
        dv_norm = np.linalg.norm(dv, axis=-1, keepdims=True)
        vel = vel + dv * np.minimum(1, config.acceleration * dt / np.maximum(dv_norm, 1e-9))
        pos = pos + vel * dt

        # --- hard constraint: footprints (plus the personal distance) never overlap
        if interacting:
            for _ in range(3):
                diff = pos[:, None] - pos[None]
                d = np.linalg.norm(diff, axis=-1)
                need = radius[:, None] + radius[None] + pd + 0.02
                deficit = np.where(same, np.maximum(need - d, 0), 0)
                if not deficit.any():
                    break
                unit = diff / np.maximum(d, 1e-9)[..., None]
                pos = pos + 0.5 * (deficit[..., None] * unit).sum(1)

        # --- heading: along the walking direction, else towards the chosen target
        moving = np.linalg.norm(vel, axis=-1) > 0.25
        want = np.where(moving, np.arctan2(vel[:, 1], vel[:, 0]), target_heading)
        delta = _wrap(want - heading)
        max_turn = np.radians(config.max_turn_rate) * dt
        heading = heading + np.clip(delta, -max_turn, max_turn)
        target_heading = np.where(moving, heading, target_heading)
        out_pos[k], out_head[k] = pos, heading

    # Interpolate to frame times (Catmull-Rom on positions and unwrapped headings).
    frame_t = np.arange(num_frames) / config.fps
    root = _catmull_rom(out_pos, times, frame_t)
    head = _catmull_rom(np.unwrap(out_head, axis=0), times, frame_t)
    vel_f = np.gradient(root, axis=0) * config.fps if num_frames > 1 else np.zeros_like(root)
    return Paths(
        root,
        head,
        np.linalg.norm(vel_f, axis=-1),
        np.asarray(seg_person, np.int64),
        np.asarray(seg_kind, np.int64),
        np.asarray(seg_start, np.float64),
        np.asarray(seg_end, np.float64),
    )


def pose_angles(
    paths: Paths, bodies: Bodies, config: MotionConfig, rng: np.random.Generator
) -> PoseAngles:
    """Joint angles of every frame from the paths and activities (vectorised over frames)."""
    F, G = paths.heading.shape
    t = (np.arange(F) / config.fps)[:, None]  # (F, 1)
    deg = np.radians
    speed = paths.speed
    # Gait: cadence (steps/s) grows with speed and falls with leg length; amplitude with speed.
    leg = (bodies.thigh + bodies.shin)[None, :]
    cadence = 1.8 * (np.maximum(speed, 0.05) / 1.3) ** 0.45 * np.sqrt(0.85 / leg)
    walk = np.clip(speed / 0.5, 0, 1)
    phase0 = rng.random(G)
    phase = phase0 + np.cumsum(0.5 * cadence * walk, axis=0) / config.fps  # gait cycles
    amp = np.clip(speed / 1.3, 0, 1.4)
    both = np.stack([phase, phase + 0.5], -1)  # (F, G, 2) left, right
    cyc = np.cos(2 * np.pi * both)
    a2 = amp[..., None]

    def vm(c: float, kappa: float) -> np.ndarray:
        return np.exp(kappa * (np.cos(2 * np.pi * (both - c)) - 1))

    hip_flex = deg(2) + a2 * deg(5 + 20 * cyc)
    knee = deg(4) + a2 * (deg(12) * vm(0.1, 8) + deg(55) * vm(0.72, 6))
    arm_flex = deg(3) - a2 * deg(17) * cyc
    fore_flex = arm_flex + deg(12) + a2 * deg(12 - 10 * cyc)
    sway = lambda scale, n=1: _drift(rng, F, G, config.fps, scale, n)  # noqa: E731
    hip_abd = deg(4) + sway(deg(2.0), 2)
    arm_abd = deg(7) + sway(deg(3.0), 2)
    fore_abd = arm_abd.copy()
    hip_flex = hip_flex + sway(deg(2.0), 2) * (1 - a2)
    knee = knee + np.abs(sway(deg(4.0), 2)) * (1 - a2)
    arm_flex = arm_flex + sway(deg(4.0), 2) * (1 - a2)
    fore_flex = fore_flex + sway(deg(6.0), 2) * (1 - a2)
    s2 = np.sin(2 * np.pi * phase)
    pelvis_yaw = amp * deg(5) * s2
    trunk_yaw = -amp * deg(4) * s2 + sway(deg(4.0))
    trunk_flex = deg(3) + amp * deg(4) + sway(deg(2.0))
    trunk_lean = sway(deg(2.0))
    head_yaw = sway(deg(25.0)) * (1 - 0.6 * walk)
    head_pitch = deg(8) + sway(deg(8.0))

    # Activities: per frame, the (at most one) on-the-spot segment of each person.
    n_seg = paths.seg_kind.size
    if n_seg:
        act = _active_segment(paths, t[:, 0], G)  # (F, G) segment index or -1
        on = act >= 0
        a_ = np.where(on, act, 0)
        e = np.where(on, envelope(t, paths.seg_start[a_], paths.seg_end[a_]), 0.0)  # (F, G)
        kind = np.where(on, paths.seg_kind[a_], -1)
        # Per-segment random targets (vectorised over segments), gathered per frame.
        u = lambda lo, hi: rng.uniform(lo, hi, n_seg)[a_]  # noqa: E731
        side = rng.choice(3, n_seg, p=[0.4, 0.4, 0.2])[a_]  # left, right, both
        use = np.stack([side != 1, side != 0], -1).astype(np.float64)  # (F, G, 2) left, right
        reach_type = rng.choice(3, n_seg, p=[0.5, 0.25, 0.25])[a_]  # forward, up, side
        r_flex = np.select(
            [reach_type == 0, reach_type == 1], [u(60, 100), u(*config.reach_up_deg)], u(0, 25)
        )
        r_abd = np.where(reach_type == 2, u(70, 95), u(0, 20))
        w_freq, w_phase = u(1.5, 3.0), u(0, 2 * np.pi)
        crouch_d, bend_d = u(*config.crouch_depth), u(*config.bend_deg)

        def apply(angle: np.ndarray, target, mask: np.ndarray, pair_use=None) -> np.ndarray:
            """Blends targets (F, G) into angles (F, G) or (F, G, 2) where mask (F, G)."""
            w = e * mask
            if angle.ndim == 3:
                w = w[..., None] * (1.0 if pair_use is None else pair_use)
                target = np.asarray(target)[..., None] if np.ndim(target) == 2 else target
            return angle * (1 - w) + w * target

        is_reach, is_wave = kind == REACH, kind == WAVE
        is_crouch, is_bend = kind == CROUCH, kind == BEND
        wave_osc = deg(165) + deg(22) * np.sin(2 * np.pi * w_freq * t + w_phase)  # (F, G)
        arm_flex = apply(arm_flex, deg(r_flex), is_reach, use)
        arm_abd = apply(arm_abd, deg(r_abd), is_reach, use)
        fore_flex = apply(fore_flex, deg(r_flex + 8), is_reach, use)
        fore_abd = apply(fore_abd, deg(r_abd), is_reach, use)
        trunk_flex = apply(trunk_flex, deg(np.where(reach_type == 0, 12, 0) + 3), is_reach)
        wave_use = np.stack([side != 1, side == 1], -1).astype(np.float64)  # one arm
        arm_flex = apply(arm_flex, deg(30), is_wave, wave_use)
        arm_abd = apply(arm_abd, deg(85), is_wave, wave_use)
        fore_flex = apply(fore_flex, -deg(10), is_wave, wave_use)
        fore_abd = apply(fore_abd, wave_osc, is_wave, wave_use)
        hip_flex = apply(hip_flex, deg(95) * crouch_d, is_crouch)
        knee = apply(knee, deg(118) * crouch_d, is_crouch)
        trunk_flex = apply(trunk_flex, deg(config.crouch_trunk_deg) * crouch_d, is_crouch)
        arm_flex = apply(arm_flex, deg(40), is_crouch)
        fore_flex = apply(fore_flex, deg(65), is_crouch)
        trunk_flex = apply(trunk_flex, deg(bend_d), is_bend)
        knee = apply(knee, deg(15), is_bend)
        hip_flex = apply(hip_flex, deg(3), is_bend)
        arm_flex = apply(arm_flex, deg(0.6 * bend_d), is_bend)
        fore_flex = apply(fore_flex, deg(0.6 * bend_d + 8), is_bend)
        arm_abd = apply(arm_abd, deg(10), is_bend | is_crouch)
        fore_abd = apply(fore_abd, deg(10), is_bend | is_crouch)

    return PoseAngles(
        root=paths.root,
        heading=paths.heading,
        anchor=1.0 - walk,
        pelvis_yaw=pelvis_yaw,
        trunk_flex=trunk_flex,
        trunk_lean=trunk_lean,
        trunk_yaw=trunk_yaw,
        head_yaw=head_yaw,
        head_pitch=head_pitch,
        hip_flex=hip_flex,
        hip_abd=hip_abd,
        knee=knee,
        arm_flex=arm_flex,
        arm_abd=arm_abd,
        fore_flex=fore_flex,
        fore_abd=fore_abd,
    )


# --------------------------------------------------------------------------- helpers


def _active_segment(paths: Paths, t: np.ndarray, G: int) -> np.ndarray:
    """(F, G) index of the segment each person is doing at each frame time, or -1."""
    span = float(max(paths.seg_end.max(), t.max()) - min(paths.seg_start.min(), 0.0)) + 10.0
    key = paths.seg_person * span + paths.seg_start
    order = np.argsort(key, kind="stable")
    query = np.arange(G)[None, :] * span + t[:, None]  # (F, G)
    pos = np.searchsorted(key[order], query, side="right") - 1
    cand = order[np.clip(pos, 0, None)]
    ok = (
        (pos >= 0)
        & (paths.seg_person[cand] == np.arange(G)[None])
        & (t[:, None] < paths.seg_end[cand])
    )
    return np.where(ok, cand, -1)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    return x * x * (3 - 2 * x)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _drift(
    rng: np.random.Generator, F: int, G: int, fps: float, scale: float, n: int = 1
) -> np.ndarray:
    """Slow random drift: a sum of 3 sinusoids of 0.05-0.5 Hz with random phases.

    Returns (F, G) or, for n = 2, (F, G, 2); standard deviation about ``scale``.
    """
    shape = (G, n, 3)
    freq = rng.uniform(0.05, 0.5, shape)
    ph = rng.uniform(0, 2 * np.pi, shape)
    amp = rng.uniform(0.5, 1.0, shape)
    amp *= scale * np.sqrt(2.0) / np.sqrt((amp**2).sum(-1, keepdims=True))
    t = np.arange(F) / fps
    out = np.einsum(
        "fgnk->fgn", amp[None] * np.sin(2 * np.pi * freq[None] * t[:, None, None, None] + ph[None])
    )
    return out[..., 0] if n == 1 else out


def _catmull_rom(values: np.ndarray, times: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Catmull-Rom spline through values (T, ...) at uniform times, evaluated at query (Q,)."""
    dt = times[1] - times[0]
    s = (query - times[0]) / dt
    i = np.clip(np.floor(s).astype(np.int64), 1, len(times) - 3)
    u = (s - i).reshape((-1,) + (1,) * (values.ndim - 1))
    p0, p1, p2, p3 = values[i - 1], values[i], values[i + 1], values[i + 2]
    return 0.5 * (
        2 * p1
        + (-p0 + p2) * u
        + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2
        + (-p0 + 3 * p1 - 3 * p2 + p3) * u**3
    )
