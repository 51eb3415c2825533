"""Random camera rigs of several families, for models that must work on any rig (pretraining).

Every rig is drawn in a z-up world with its floor at a random height and the whole rig turned
by a random yaw and moved by a random offset on the floor (users' calibrations put the origin
anywhere). A camera looks at a random point of the capture space, without roll (a small one,
as mounts have); its intrinsics and distortion are drawn per camera.

Families (`RIG_FAMILIES`), as users build them:

* ``ring``: 3-10 cameras around the room at 1.8-3.2 m, looking at its middle (the paper's
  Panoptic studio, mocap labs).
* ``arc``: 2-6 cameras on a half circle on one side of the room (a stage, a treadmill).
* ``wall``: 2-6 cameras in a line along one wall at 1.8-2.8 m (a corridor, a shop).
* ``corners``: 4 cameras in the room's upper corners, 2.5-3.2 m (a surveillance room, an
  operating room: MVOR's rig).
* ``two-level``: 4-10 cameras around the room, alternately low (0.8-1.4 m) and high
  (2.2-3.2 m) (a gait lab, the paper's ARPlab).
* ``ceiling``: 3-8 cameras high up (3.0-4.5 m) near the middle, looking steeply down.
* ``pair``: a robot's stereo pair, 0.06-0.5 m apart at 1.0-1.6 m, looking ahead.
* ``tripods``: 2-6 cameras on low tripods (0.6-1.2 m) spread in front of the people, looking
  slightly up (field recordings, Pose2Sim's demo).

`PRETRAIN_FAMILIES` are the families pretraining uses; the others are held out to test that
a model works on rigs whose kind it never saw.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvpose_jax.cameras import Rig, make_rig
from mvpose_jax.errors import InputError
from mvpose_jax.synthetic.config import SceneConfig
from mvpose_jax.synthetic.scene import scene_geometry

RIG_FAMILIES = ("ring", "arc", "wall", "corners", "two-level", "ceiling", "pair", "tripods")
PRETRAIN_FAMILIES = ("ring", "arc", "wall", "corners", "two-level")
HELD_OUT_FAMILIES = ("ceiling", "pair", "tripods")

# Image sizes (width, height) of common cameras, pixels.
IMAGE_SIZES = ((640, 480), (1280, 720), (1920, 1080), (1024, 1024), (2048, 1536), (720, 1280))

UP = np.array([0.0, 0.0, 1.0])


def look_at(centre: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Camera-from-world rotation (OpenCV: x right, y down, z forward) of a camera at ``centre``
    looking at ``target`` in a z-up world, turned by ``roll`` radians about its axis."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, UP)
    if np.linalg.norm(x) < 1e-6:  # looking straight down or up: any heading
        x = np.array([1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z])


def _intrinsics(rng: np.random.Generator, size: tuple[int, int], fov_deg: tuple[float, float]):
    """K (3, 3) and dist (5,) of one camera: horizontal field of view drawn in ``fov_deg``;
    wider lenses get more barrel distortion."""
    w, h = size
    fov = np.deg2rad(rng.uniform(*fov_deg))
    f = 0.5 * max(w, h) / np.tan(0.5 * fov)
    K = np.array(
        [
            [f, 0.0, w * (0.5 + rng.uniform(-0.02, 0.02))],
            [0.0, f * rng.uniform(0.99, 1.01), h * (0.5 + rng.uniform(-0.02, 0.02))],
            [0.0, 0.0, 1.0],
        ]
    )
    wide = np.clip((np.rad2deg(fov) - 50.0) / 50.0, 0.0, 1.0)  # 0 at 50 deg, 1 at 100 deg
    k1 = -rng.uniform(0.0, 0.3) * wide + rng.uniform(-0.03, 0.03)
    k2 = -0.3 * k1 * rng.uniform(0.0, 1.0)
    p = rng.uniform(-1e-3, 1e-3, 2)
    return K, np.array([k1, k2, p[0], p[1], 0.0])


def _placements(family: str, rng: np.random.Generator):
    """Camera centres (C, 3) and look-at targets (C, 3) relative to the floor point under the
    capture space's middle, before the rig's yaw and offset."""
    room = rng.uniform(2.0, 6.0)  # radius of the space the cameras stand around, metres

    def target(n, spread=0.6, lo=0.6, hi=1.3):
        xy = rng.uniform(-spread, spread, (n, 2))
        return np.concatenate([xy, rng.uniform(lo, hi, (n, 1))], axis=1)

    def on_circle(angles, radius, heights):
        r = radius * rng.uniform(0.9, 1.1, len(angles))
        return np.stack([r * np.cos(angles), r * np.sin(angles), heights], axis=1)

    if family == "ring":
        n = int(rng.integers(3, 11))
        a = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.25, 0.25, n)
        return on_circle(a, room, rng.uniform(1.8, 3.2, n)), target(n)
    if family == "arc":
        n = int(rng.integers(2, 7))
        a = np.linspace(-0.5 * np.pi, 0.5 * np.pi, n) + rng.uniform(-0.15, 0.15, n)
        return on_circle(a, room, rng.uniform(1.5, 2.8, n)), target(n)
    if family == "wall":
        n = int(rng.integers(2, 7))
        along = np.linspace(-room, room, n) * rng.uniform(0.5, 1.0)
        centres = np.stack([np.full(n, room), along, rng.uniform(1.8, 2.8, n)], axis=1)
        centres[:, 0] += rng.uniform(-0.2, 0.2, n)
        return centres, target(n, spread=0.8)
    if family == "corners":
        a = np.array([0.25, 0.75, 1.25, 1.75]) * np.pi + rng.uniform(-0.1, 0.1, 4)
        return on_circle(a, room * np.sqrt(2) * 0.8, rng.uniform(2.5, 3.2, 4)), target(4)
    if family == "two-level":
        n = int(rng.integers(4, 11))
        a = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.2, 0.2, n)
        low = np.arange(n) % 2 == 0
        h = np.where(low, rng.uniform(0.8, 1.4, n), rng.uniform(2.2, 3.2, n))
        return on_circle(a, room, h), target(n)
    if family == "ceiling":
        n = int(rng.integers(3, 9))
        a = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.3, 0.3, n)
        r = rng.uniform(1.5, 3.0)
        return on_circle(a, r, rng.uniform(3.0, 4.5, n)), target(n, spread=0.4, lo=0.3, hi=0.9)
    if family == "pair":
        base = rng.uniform(0.06, 0.5)
        h = rng.uniform(1.0, 1.6)
        centres = np.array([[-room, -base / 2, h], [-room, base / 2, h]])
        aim = np.array([0.0, 0.0, rng.uniform(0.6, 1.2)])
        return centres, np.stack([aim + [0, -base / 2, 0], aim + [0, base / 2, 0]])
    if family == "tripods":
        n = int(rng.integers(2, 7))
        a = np.linspace(-0.4 * np.pi, 0.4 * np.pi, n) + np.pi + rng.uniform(-0.1, 0.1, n)
        return on_circle(a, room, rng.uniform(0.6, 1.2, n)), target(n, lo=0.8, hi=1.2)
    raise ValueError(f"unknown rig family {family!r}; choose from {RIG_FAMILIES}")


def random_rig(
    family: str,
    seed: int | Sequence[int] | np.random.Generator = 0,
    *,
    name: str = "cam",
) -> tuple[Rig, float]:
    """A random rig of ``family`` (see the module docstring) in a z-up world, with a capture area
    (a floor region that 2 cameras see a standing person in whole: a draw without one is drawn
    again).

    Returns:
      (the rig, with ``up`` = +z; the floor height along up, metres).
    Raises:
      InputError when 50 draws in a row have no capture area (not seen for these families).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    for _ in range(50):
        rig, floor = _draw_rig(family, rng, name)
        try:
            scene_geometry(rig, SceneConfig(up=tuple(UP), floor_height=floor))
        except InputError:
            continue
        return rig, floor
    raise InputError(f"no {family} rig with a capture area in 50 draws", field="family")


def _draw_rig(family: str, rng: np.random.Generator, name: str) -> tuple[Rig, float]:
    centres, targets = _placements(family, rng)
    C = len(centres)
    floor = rng.uniform(-1.5, 1.5)
    yaw = rng.uniform(0, 2 * np.pi)
    turn = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    offset = np.concatenate([rng.uniform(-3, 3, 2), [floor]])
    centres = centres @ turn.T + offset
    targets = targets @ turn.T + offset
    fov = (60.0, 100.0) if family in ("pair", "tripods") else (45.0, 95.0)
    size = IMAGE_SIZES[int(rng.integers(len(IMAGE_SIZES)))]
    K, dist, R, t = [], [], [], []
    for c in range(C):
        k, d = _intrinsics(rng, size, fov)
        rot = look_at(centres[c], targets[c], roll=rng.normal(0.0, 0.02))
        K.append(k)
        dist.append(d)
        R.append(rot)
        t.append(-rot @ centres[c])
    rig = make_rig(
        np.stack(K),
        np.stack(dist),
        np.stack(R),
        np.stack(t),
        np.tile(np.asarray(size, np.float64), (C, 1)),
        [f"{name}{c}" for c in range(C)],
        up=tuple(UP),
    )
    return rig, float(floor)
