"""A 3D body model for the coco18 layout: anthropometric bodies and forward kinematics.

Lengths are fractions of the standing height H (floor to top of head), after the segment tables
of Drillis & Contini as summarised by Winter, "Biomechanics and Motor Control of Human Movement":
ankle 0.039 H, knee 0.285 H, hip joint 0.530 H, shoulder 0.818 H; upper arm 0.186 H, forearm
0.146 H; shoulder joints 0.20 H apart. Per person the segments vary (`BodyConfig`) and are then
rescaled so the standing height is exactly H; they never change over time, because every
keypoint is placed by forward kinematics from joint angles.

Angles (radians) live in a person's heading frame (f forward, l left, u up; gravity aligned).
A limb's direction is ``limb_direction(flex, abd, side)``: ``flex`` swings it forward from hanging
straight down, ``abd`` lifts it sideways away from the body; ``side`` is +1 for left limbs, -1 for
right ones.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from mvpose_jax.synthetic.config import BodyConfig

# coco18 keypoint indices.
NOSE, L_EYE, R_EYE, L_EAR, R_EAR = 0, 1, 2, 3, 4
L_SHOULDER, R_SHOULDER, L_ELBOW, R_ELBOW, L_WRIST, R_WRIST = 5, 6, 7, 8, 9, 10
L_HIP, R_HIP, L_KNEE, R_KNEE, L_ANKLE, R_ANKLE, NECK = 11, 12, 13, 14, 15, 16, 17
NUM_KEYPOINTS = 18
# Two more points the body volumes use: the pelvis centre and the head centre.
PELVIS, HEAD = 18, 19
NUM_POINTS = 20

# Face points in the head frame (forward, left, up), in units of H: nose, eyes, ears, head centre.
_FACE = {
    NOSE: (0.050, 0.0, 0.095),
    L_EYE: (0.038, 0.018, 0.113),
    R_EYE: (0.038, -0.018, 0.113),
    L_EAR: (-0.012, 0.042, 0.103),
    R_EAR: (-0.012, -0.042, 0.103),
    HEAD: (0.0, 0.0, 0.105),
}
_HEAD_TOP = 0.180  # neck to top of head, H
_HEAD_RADIUS = 0.056  # H

# Body volumes: capsules (point a, point b, radius in H). A keypoint is never occluded by a
# capsule it is an end of; face keypoints use a facing test against the head instead.
CAPSULES: tuple[tuple[int, int, float], ...] = (
    (L_SHOULDER, L_ELBOW, 0.025),
    (L_ELBOW, L_WRIST, 0.020),
    (R_SHOULDER, R_ELBOW, 0.025),
    (R_ELBOW, R_WRIST, 0.020),
    (L_HIP, L_KNEE, 0.040),
    (L_KNEE, L_ANKLE, 0.028),
    (R_HIP, R_KNEE, 0.040),
    (R_KNEE, R_ANKLE, 0.028),
    (L_SHOULDER, L_HIP, 0.050),
    (R_SHOULDER, R_HIP, 0.050),
    (NECK, PELVIS, 0.060),
    (HEAD, HEAD, _HEAD_RADIUS),
)
NUM_CAPSULES = len(CAPSULES)
TORSO_CAPSULES = (8, 9, 10, 11)  # torso and head: the volumes people must never share
FACE_KEYPOINTS = (NOSE, L_EYE, R_EYE, L_EAR, R_EAR)


def capsule_exempt() -> np.ndarray:
    """(K, S) bool: keypoint k cannot be occluded by its own body's capsule s."""
    ex = np.zeros((NUM_KEYPOINTS, NUM_CAPSULES), bool)
    for s, (a, b, _) in enumerate(CAPSULES):
        for p in (a, b):
            if p < NUM_KEYPOINTS:
                ex[p, s] = True
    ex[list(FACE_KEYPOINTS), NUM_CAPSULES - 1] = True
    return ex


@dataclasses.dataclass(frozen=True)
class Bodies:
    """Body shapes of G people (metres). Constant over time."""

    height: np.ndarray  # (G,) standing height
    male: np.ndarray  # (G,) bool
    ankle_height: np.ndarray  # (G,) ankle joint above the floor
    shin: np.ndarray  # (G,) knee to ankle
    thigh: np.ndarray  # (G,) hip to knee
    trunk: np.ndarray  # (G,) pelvis centre to neck
    upper_arm: np.ndarray  # (G,) shoulder to elbow
    forearm: np.ndarray  # (G,) elbow to wrist
    shoulder_half: np.ndarray  # (G,) neck to each shoulder, sideways
    shoulder_drop: np.ndarray  # (G,) shoulders below the neck
    hip_half: np.ndarray  # (G,) pelvis centre to each hip, sideways
    head: np.ndarray  # (G,) head scale: face offsets are ``head * _FACE`` (metres)
    radii: np.ndarray  # (G, S) capsule radii

    @property
    def num_people(self) -> int:
        return int(self.height.shape[0])

    def take(self, idx) -> Bodies:
        """Bodies of a subset of people."""
        return Bodies(**{f.name: getattr(self, f.name)[idx] for f in dataclasses.fields(self)})


def sample_bodies(
    rng: np.random.Generator, num_people: int, config: BodyConfig = BodyConfig()
) -> Bodies:
    """Draws ``num_people`` bodies from the population of ``config``."""
    n = num_people
    male = rng.random(n) < config.male_fraction
    lo, hi = config.height_range
    mean = np.where(male, config.height_mean[1], config.height_mean[0])
    # Truncated normal by resampling the few draws outside the range (vectorised, bounded).
    height = mean + config.height_std * rng.standard_normal(n)
    for _ in range(20):
        bad = (height < lo) | (height > hi)
        if not bad.any():
            break
        height[bad] = mean[bad] + config.height_std * rng.standard_normal(bad.sum())
    height = np.clip(height, lo, hi)
    # Children (a domain shift; off by default, and then no random numbers are drawn for it).
    child = np.zeros(n, bool)
    if config.child_fraction > 0:
        child = rng.random(n) < config.child_fraction
        height = np.where(child, rng.uniform(*config.child_height_range, n), height)

    def factor(std: float, size=n) -> np.ndarray:
        return np.exp(std * rng.standard_normal(size))

    ps = config.proportion_std
    leg, leg_ratio, trunk_f, arm, arm_ratio = (factor(ps) for _ in range(5))
    head = factor(config.head_std)
    if child.any():
        head = np.where(child, head * config.child_head_factor, head)
    # Vertical chain of a straight standing body (fractions of H), then rescaled to height H.
    ankle = 0.039 * leg
    shin = 0.246 * leg / np.sqrt(leg_ratio)
    thigh = 0.245 * leg * np.sqrt(leg_ratio)
    trunk = 0.290 * trunk_f
    top = _HEAD_TOP * head
    scale = height / (ankle + shin + thigh + trunk + top)
    # Men have relatively broader shoulders, women relatively broader hips.
    sex = np.where(male, 1.0, -1.0)
    shoulder = 0.100 * (1 + 0.04 * sex) * factor(config.width_std) * height
    hip = 0.060 * (1 - 0.03 * sex) * factor(config.width_std) * height
    girth = factor(config.girth_std)
    radii = np.array([r for _, _, r in CAPSULES])[None, :] * height[:, None] * girth[:, None]
    radii[:, -1] = _HEAD_RADIUS * head * height  # the head grows with head size, not girth
    return Bodies(
        height=height,
        male=male,
        ankle_height=ankle * scale,
        shin=shin * scale,
        thigh=thigh * scale,
        trunk=trunk * scale,
        upper_arm=0.186 * arm / np.sqrt(arm_ratio) * height,
        forearm=0.146 * arm * np.sqrt(arm_ratio) * height,
        shoulder_half=shoulder,
        shoulder_drop=0.012 * height,
        hip_half=hip,
        head=head * scale,
        radii=radii,
    )


class PoseAngles(NamedTuple):
    """Joint angles and root placement of G people over F frames (radians, floor metres).

    Pairs (..., 2) are (left, right).
    """

    root: np.ndarray  # (F, G, 2) floor coordinates of the body's support point
    heading: np.ndarray  # (F, G) facing direction, angle from the floor axis e1 towards e2
    anchor: np.ndarray  # (F, G) 0: pelvis above root (walking), 1: centre of the ankles (still)
    pelvis_yaw: np.ndarray  # (F, G)
    trunk_flex: np.ndarray  # (F, G) forward bend
    trunk_lean: np.ndarray  # (F, G) sideways, to the left
    trunk_yaw: np.ndarray  # (F, G) twist to the left
    head_yaw: np.ndarray  # (F, G) to the left
    head_pitch: np.ndarray  # (F, G) looking down
    hip_flex: np.ndarray  # (F, G, 2)
    hip_abd: np.ndarray  # (F, G, 2)
    knee: np.ndarray  # (F, G, 2) flexion (the shin swings back)
    arm_flex: np.ndarray  # (F, G, 2)
    arm_abd: np.ndarray  # (F, G, 2)
    fore_flex: np.ndarray  # (F, G, 2) forearm direction, heading frame
    fore_abd: np.ndarray  # (F, G, 2)


def limb_direction(flex: np.ndarray, abd: np.ndarray, side: np.ndarray | float) -> np.ndarray:
    """Unit direction (..., 3) in (f, l, u) of a limb swung forward by flex and out by abd."""
    ca = np.cos(abd)
    return np.stack([np.sin(flex) * ca, side * np.sin(abd), -np.cos(flex) * ca], axis=-1)


def forward_kinematics(bodies: Bodies, pose: PoseAngles) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of every person in every frame, in floor coordinates.

    Args:
      bodies: G bodies.
      pose: angles for F frames.
    Returns:
      points (F, G, NUM_POINTS, 3): (a, b, height above the floor) of the 18 keypoints, then
      the pelvis centre and the head centre; frames (F, G, 3, 3): rows f, l, u of each heading
      frame in floor coordinates.
    """
    F, G = pose.heading.shape
    dt = np.float64
    col = lambda a: a[None, :, None]  # noqa: E731  (G,) -> (1, G, 1) against (F, G, 3)
    side = np.array([1.0, -1.0])  # left, right

    # Local points in the heading frame (f, l, u), pelvis centre at the origin for now.
    pts = np.zeros((F, G, NUM_POINTS, 3), dt)
    # Pelvis and hips.
    left_p = np.stack(
        [-np.sin(pose.pelvis_yaw), np.cos(pose.pelvis_yaw), np.zeros_like(pose.pelvis_yaw)], -1
    )
    hips = side[:, None] * left_p[:, :, None, :] * bodies.hip_half[None, :, None, None]  # (F,G,2,3)
    thigh_dir = limb_direction(pose.hip_flex, pose.hip_abd, side)  # (F, G, 2, 3)
    shin_dir = limb_direction(pose.hip_flex - pose.knee, pose.hip_abd, side)
    knees = hips + thigh_dir * bodies.thigh[None, :, None, None]
    ankles = knees + shin_dir * bodies.shin[None, :, None, None]
    # Trunk frame: up_t from forward flexion and sideways lean, left_t twisted by the trunk yaw.
    cb, sb = np.cos(pose.trunk_flex), np.sin(pose.trunk_flex)
    cl, sl = np.cos(pose.trunk_lean), np.sin(pose.trunk_lean)
    up_t = np.stack([sb * cl, sl, cb * cl], -1)
    left0 = np.array([0.0, 1.0, 0.0]) - up_t[..., 1:2] * up_t
    left0 /= np.linalg.norm(left0, axis=-1, keepdims=True)
    left_t = np.cos(pose.trunk_yaw)[..., None] * left0 + np.sin(pose.trunk_yaw)[
        ..., None
    ] * np.cross(up_t, left0)
    fwd_t = np.cross(left_t, up_t)
    neck = up_t * col(bodies.trunk)
    shoulders = (
        neck[:, :, None]
        + side[:, None] * left_t[:, :, None] * bodies.shoulder_half[None, :, None, None]
        - up_t[:, :, None] * bodies.shoulder_drop[None, :, None, None]
    )  # (F, G, 2, 3)
    elbows = (
        shoulders
        + limb_direction(pose.arm_flex, pose.arm_abd, side) * bodies.upper_arm[None, :, None, None]
    )
    wrists = (
        elbows
        + limb_direction(pose.fore_flex, pose.fore_abd, side) * bodies.forearm[None, :, None, None]
    )
    # Head: pitched forward from the trunk; bending the trunk extends the neck (eyes stay ahead).
    pitch = pose.head_pitch - 0.45 * pose.trunk_flex
    cp, sp = np.cos(pitch)[..., None], np.sin(pitch)[..., None]
    up_h = cp * up_t + sp * fwd_t
    fwd_h0 = cp * fwd_t - sp * up_t
    cy, sy = np.cos(pose.head_yaw)[..., None], np.sin(pose.head_yaw)[..., None]
    fwd_h = cy * fwd_h0 + sy * left_t
    left_h = cy * left_t - sy * fwd_h0
    head_axes = np.stack([fwd_h, left_h, up_h], axis=-2)  # (F, G, 3, 3)
    face_idx = list(_FACE)
    face_local = np.array([_FACE[k] for k in face_idx]) * 1.0  # (6, 3) in H-units of head
    face = (
        neck[:, :, None]
        + np.einsum("pj,fgjk->fgpk", face_local, head_axes) * bodies.head[None, :, None, None]
    )

    pts[:, :, [L_HIP, R_HIP]] = hips
    pts[:, :, [L_KNEE, R_KNEE]] = knees
    pts[:, :, [L_ANKLE, R_ANKLE]] = ankles
    pts[:, :, NECK] = neck
    pts[:, :, [L_SHOULDER, R_SHOULDER]] = shoulders
    pts[:, :, [L_ELBOW, R_ELBOW]] = elbows
    pts[:, :, [L_WRIST, R_WRIST]] = wrists
    pts[:, :, face_idx] = face
    # PELVIS stays at the origin.

    # Stand on the lower ankle: the pelvis height makes it touch ankle height above the floor.
    low = ankles[..., 2].min(-1)  # (F, G)
    lift = bodies.ankle_height[None, :] - low
    # Horizontal anchor: still people keep their feet on the spot, walking people their pelvis.
    shift = -pose.anchor[..., None] * ankles[..., :2].mean(-2)  # (F, G, 2)
    pts[..., :2] += shift[:, :, None]
    pts[..., 2] += lift[:, :, None]

    # Heading frame to floor coordinates: f = (cos h, sin h, 0), l = (-sin h, cos h, 0), u.
    ch, sh = np.cos(pose.heading), np.sin(pose.heading)
    z = np.zeros_like(ch)
    frames = np.stack(
        [np.stack([ch, sh, z], -1), np.stack([-sh, ch, z], -1), np.stack([z, z, z + 1], -1)], -2
    )  # (F, G, 3, 3)
    out = np.einsum("fgpj,fgjk->fgpk", pts, frames)
    out[..., :2] += pose.root[:, :, None, :]
    return out, frames


def clearance(
    points: np.ndarray, radii: np.ndarray, capsules: tuple[int, ...] | None = None
) -> np.ndarray:
    """Smallest gap between the body volumes of every two people, per frame.

    Args:
      points: (F, G, NUM_POINTS, 3) points from `forward_kinematics` (any frame of reference
        with metres).
      radii: (G, S) capsule radii.
      capsules: indices of the capsules to use (default: all).
    Returns:
      (F, G, G) metres: the distance between the closest surfaces of the two people's capsules
      (negative where they interpenetrate); +inf on the diagonal.
    """
    idx = np.arange(NUM_CAPSULES) if capsules is None else np.asarray(capsules)
    ia = np.array([CAPSULES[s][0] for s in idx])
    ib = np.array([CAPSULES[s][1] for s in idx])
    a, b = points[:, :, ia], points[:, :, ib]  # (F, G, S, 3)
    r = radii[:, idx]
    # All capsule pairs of all people pairs: (F, G, G, S, S).
    d = _segment_distance(
        a[:, :, None, :, None],
        b[:, :, None, :, None],
        a[:, None, :, None, :],
        b[:, None, :, None, :],
    )
    gap = d - r[:, None, :, None] - r[None, :, None, :]
    out = gap.min(axis=(-1, -2))
    G = points.shape[1]
    out[:, np.arange(G), np.arange(G)] = np.inf
    return out


def _segment_distance(p1, q1, p2, q2):
    """Distance between segments p1-q1 and p2-q2 (..., 3), broadcasting (Ericson, 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = (d1 * d1).sum(-1)
    e = (d2 * d2).sum(-1)
    f = (d2 * r).sum(-1)
    c = (d1 * r).sum(-1)
    b = (d1 * d2).sum(-1)
    denom = a * e - b * b
    eps = 1e-12
    s = np.where(denom > eps, np.clip((b * f - c * e) / np.maximum(denom, eps), 0, 1), 0.0)
    t = (b * s + f) / np.maximum(e, eps)
    # Clamp t to [0, 1] and recompute s for the clamped t.
    s = np.where(
        t < 0,
        np.clip(-c / np.maximum(a, eps), 0, 1),
        np.where(t > 1, np.clip((b - c) / np.maximum(a, eps), 0, 1), s),
    )
    t = np.clip(t, 0, 1)
    s = np.where(a <= eps, 0.0, s)
    t = np.where(e <= eps, 0.0, np.where(a <= eps, np.clip(f / np.maximum(e, eps), 0, 1), t))
    diff = (p1 + d1 * s[..., None]) - (p2 + d2 * t[..., None])
    return np.sqrt((diff * diff).sum(-1))
