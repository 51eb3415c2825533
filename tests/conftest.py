"""Shared fixtures. Rank promotion raises, so shape bugs fail loudly instead of broadcasting."""

from __future__ import annotations

import jax
import numpy as np
import pytest

jax.config.update("jax_numpy_rank_promotion", "raise")

from mvpose_jax.cameras import make_rig  # noqa: E402
from mvpose_jax.data.calibration import PRESETS, load_preset  # noqa: E402


@pytest.fixture(scope="session", params=PRESETS)
def preset_rig(request):
    """Each rig preset in turn."""
    return load_preset(request.param)


def random_rig(seed: int = 0, num_cameras: int = 4):
    """Cameras on a ring looking at the origin, with strong radial AND tangential distortion.

    The distortion stays invertible over the image (as any real calibration's does there).
    """
    rng = np.random.default_rng(seed)
    K, dist, R, t = [], [], [], []
    for c in range(num_cameras):
        angle = 2 * np.pi * c / num_cameras + rng.uniform(-0.2, 0.2)
        centre = np.array([4 * np.cos(angle), -1.5 + rng.uniform(-0.3, 0.3), 4 * np.sin(angle)])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross(forward, [0.0, -1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rot = np.stack([right, down, forward])  # cam_from_world rows: x right, y down, z forward
        R.append(rot)
        t.append(-rot @ centre)
        f = rng.uniform(1200, 1600)
        K.append([[f, 0, 960 + rng.uniform(-20, 20)], [0, f * rng.uniform(0.99, 1.01), 540], [0, 0, 1]])
        dist.append([rng.uniform(-0.28, -0.1), rng.uniform(0.0, 0.15), rng.uniform(-2e-3, 2e-3),
                     rng.uniform(-2e-3, 2e-3), rng.uniform(-0.03, 0.02)])  # fmt: skip
    return make_rig(K, dist, R, t, [[1920, 1080]] * num_cameras, [f"cam{c}" for c in range(num_cameras)])


def scene_points(rig, seed, shape):
    """Points in front of every camera of the rig, near where the cameras look: shape + (3,)."""
    from mvpose_jax.cameras import camera_centres

    centres = np.asarray(camera_centres(rig))
    looks = centres + 3.0 * np.asarray(rig.R)[:, 2]  # 3 m along each optical axis
    rng = np.random.default_rng(seed)
    return (rng.normal(size=tuple(shape) + (3,)) * 0.4 + looks.mean(axis=0)).astype(np.float32)


@pytest.fixture(scope="session")
def ring_rig():
    return random_rig()
