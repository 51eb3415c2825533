"""triangulate.py: exact recovery, OpenCV agreement, masks and degenerate geometry."""

from __future__ import annotations

import itertools

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mvpose_jax import cameras, triangulate
from tests.helpers import random_rig, scene_points


@pytest.mark.parametrize(
    "fn", [triangulate.triangulate_points, triangulate.triangulate_pairwise_centroid]
)
def test_noise_free_points_are_recovered_exactly(preset_rig, fn):
    X = scene_points(preset_rig, 0, (4, 18))
    with jax.enable_x64(True):
        rig64 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), preset_rig)
        X64 = jnp.asarray(X, jnp.float64)
        px = cameras.project_points(rig64, X64)
        xyz, ok = jax.jit(fn)(rig64, px, jnp.ones(px.shape[:-1]))
        assert bool(ok.all())
        np.testing.assert_allclose(xyz, X64, atol=1e-6, rtol=0)
    # float32, as the pipeline runs: a tenth of a millimetre.
    px = cameras.project_points(preset_rig, jnp.asarray(X))
    xyz, ok = jax.jit(fn)(preset_rig, px, jnp.ones(px.shape[:-1]))
    np.testing.assert_allclose(xyz, X, atol=1e-4, rtol=0)


def _cv_two_view(rig, i, j, px_i, px_j):
    """cv2.triangulatePoints on undistorted pixels with P = K [R | t]."""
    P = np.asarray(cameras.projection_matrices(rig), np.float64)
    und = []
    for c, px in ((i, px_i), (j, px_j)):
        K, D = np.asarray(rig.K[c], np.float64), np.asarray(rig.dist[c], np.float64)
        und.append(cv2.undistortPoints(px[:, None].astype(np.float64), K, D, P=K)[:, 0].T)
    Xh = cv2.triangulatePoints(P[i], P[j], und[0], und[1])
    return (Xh[:3] / Xh[3]).T


def test_two_views_agree_with_opencv_under_noise(preset_rig):
    X = scene_points(preset_rig, 1, (40,))
    px = np.asarray(cameras.project_points(preset_rig, jnp.asarray(X)))
    px = px + np.random.default_rng(2).normal(scale=1.0, size=px.shape)  # 1 px detector noise
    for i, j in [(0, 1), (1, 2)]:
        w = np.zeros(px.shape[:-1], np.float32)
        w[[i, j]] = 1.0
        ours, ok = triangulate.triangulate_points(
            preset_rig, jnp.asarray(px, jnp.float32), jnp.asarray(w)
        )
        ref = _cv_two_view(preset_rig, i, j, px[i], px[j])
        assert bool(ok.all())
        # Both minimise an algebraic error, in different frames: they agree to a millimetre.
        np.testing.assert_allclose(ours, ref, atol=1e-3)


def test_pairwise_centroid_is_the_mean_of_opencv_pairs(ring_rig):
    X = scene_points(ring_rig, 3, (25,))
    px = np.asarray(cameras.project_points(ring_rig, jnp.asarray(X)))
    px = px + np.random.default_rng(4).normal(scale=1.5, size=px.shape)
    vis = np.ones(px.shape[:-1], bool)
    vis[0, :10] = False  # camera 0 misses the first 10 points
    ours, ok = triangulate.triangulate_pairwise_centroid(
        ring_rig, jnp.asarray(px, jnp.float32), jnp.asarray(vis)
    )
    ref = np.zeros_like(X, dtype=np.float64)
    n = np.zeros(len(X))
    for i, j in itertools.combinations(range(ring_rig.num_cameras), 2):
        both = vis[i] & vis[j]
        ref[both] += _cv_two_view(ring_rig, i, j, px[i], px[j])[both]
        n[both] += 1
    np.testing.assert_allclose(ours, ref / n[:, None], atol=1e-3)
    assert bool(ok.all())


def test_weights_mask_views_out(ring_rig):
    X = scene_points(ring_rig, 5, (10,))
    px = np.array(cameras.project_points(ring_rig, jnp.asarray(X)))
    px[1] += 300.0  # camera 1's observations are garbage ...
    w = np.ones(px.shape[:-1], np.float32)
    w[1] = 0.0  # ... and masked out
    xyz, ok = triangulate.triangulate_points(ring_rig, jnp.asarray(px), jnp.asarray(w))
    np.testing.assert_allclose(xyz, X, atol=1e-4)
    assert bool(ok.all())


def test_score_weighting_pulls_towards_confident_views(ring_rig):
    X = scene_points(ring_rig, 6, (10,))
    px = np.array(cameras.project_points(ring_rig, jnp.asarray(X)))
    px[2] += 20.0  # one view is off by 20 px
    err = []
    for weight in (1.0, 0.05):
        w = np.ones(px.shape[:-1], np.float32)
        w[2] = weight
        xyz, _ = triangulate.triangulate_points(ring_rig, jnp.asarray(px), jnp.asarray(w))
        err.append(np.linalg.norm(np.asarray(xyz) - X, axis=-1).mean())
    assert err[1] < 0.2 * err[0]


@pytest.mark.parametrize("batch", [(), (1,), (3, 2, 4)])
def test_batch_shapes(ring_rig, batch):
    X = scene_points(ring_rig, 7, batch)
    px = cameras.project_points(ring_rig, jnp.asarray(X))
    for fn in (triangulate.triangulate_points, triangulate.triangulate_pairwise_centroid):
        xyz, ok = fn(ring_rig, px, jnp.ones(px.shape[:-1]))
        assert xyz.shape == batch + (3,) and ok.shape == batch
        np.testing.assert_allclose(xyz, X, atol=1e-4)


def test_degenerate_inputs_are_invalid_never_nan():
    # Two cameras at the same centre (rays through one point are parallel) plus one far away.
    rig = random_rig(seed=3, num_cameras=3)
    same = cameras.make_rig(
        np.asarray(rig.K),
        np.asarray(rig.dist),
        np.stack([np.asarray(rig.R[0]), np.asarray(rig.R[0]), np.asarray(rig.R[2])]),
        np.stack([np.asarray(rig.t[0]), np.asarray(rig.t[0]), np.asarray(rig.t[2])]),
        np.asarray(rig.size),
        ["a", "b", "c"],
    )
    X = scene_points(same, 8, (6,))
    px = cameras.project_points(same, jnp.asarray(X))
    for fn in (triangulate.triangulate_points, triangulate.triangulate_pairwise_centroid):
        # Only the two coincident cameras see the points: no depth information at all.
        w = jnp.asarray([[1.0] * 6, [1.0] * 6, [0.0] * 6])
        xyz, ok = fn(same, px, w)
        assert not bool(ok.any()) and np.all(np.isfinite(xyz))
        # One view only.
        xyz, ok = fn(same, px, jnp.asarray([[1.0] * 6, [0.0] * 6, [0.0] * 6]))
        assert not bool(ok.any()) and np.all(np.isfinite(xyz))
        # No view.
        xyz, ok = fn(same, px, jnp.zeros((3, 6)))
        assert not bool(ok.any()) and np.all(np.isfinite(xyz))


def test_vmaps_over_frames_and_people(ring_rig):
    X = scene_points(ring_rig, 9, (5, 3, 18))  # (F, P, K, 3)
    px = cameras.project_points(ring_rig, jnp.asarray(X))  # (C, F, P, K, 2)
    per_frame = jax.vmap(
        lambda p: triangulate.triangulate_points(ring_rig, p, jnp.ones(p.shape[:-1]))[0], in_axes=1
    )(px)
    np.testing.assert_allclose(per_frame, X, atol=1e-4)


def test_junk_in_unseen_views_does_not_leak(ring_rig):
    X = scene_points(ring_rig, 10, (8,))
    px = np.array(cameras.project_points(ring_rig, jnp.asarray(X)))
    px[0] = np.nan  # camera 0 saw nothing; its coordinates are junk
    px[1, :4] = 1e30
    w = np.ones(px.shape[:-1], np.float32)
    w[0] = 0.0
    w[1, :4] = 0.0
    for fn in (triangulate.triangulate_points, triangulate.triangulate_pairwise_centroid):
        xyz, ok = fn(ring_rig, jnp.asarray(px), jnp.asarray(w))
        assert bool(ok.all())
        np.testing.assert_allclose(xyz, X, atol=1e-4)
