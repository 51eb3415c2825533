"""losses.py: the self-supervised reprojection loss."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mvpose_jax import cameras, losses
from tests.helpers import scene_points


def test_loss_is_zero_at_the_true_3d_of_noise_free_detections(preset_rig):
    X = scene_points(preset_rig, 0, (3, 18))
    xy = jnp.moveaxis(cameras.project_points(preset_rig, jnp.asarray(X)), 0, 1)
    score = jnp.ones(xy.shape[:-1])
    e = losses.reprojection_error_l1(preset_rig, jnp.asarray(X), xy, score)
    np.testing.assert_allclose(e, 0.0, atol=1e-3 * 18 * preset_rig.num_cameras)
    # Moving one keypoint 1 cm costs pixels in every view that sees it.
    moved = X.copy()
    moved[0, 5, 0] += 0.01
    e2 = np.asarray(losses.reprojection_error_l1(preset_rig, jnp.asarray(moved), xy, score))
    assert e2[0] > 1.0 and np.allclose(e2[1:], 0.0, atol=0.1)


def test_missing_detections_contribute_nothing(ring_rig):
    X = scene_points(ring_rig, 1, (2, 18))
    xy = np.array(jnp.moveaxis(cameras.project_points(ring_rig, jnp.asarray(X)), 0, 1))
    score = np.ones(xy.shape[:-1], np.float32)
    xy[0, 1, :5] = np.nan  # junk where nothing was detected ...
    score[0, 1, :5] = 0.0  # ... masked out
    e, g = jax.value_and_grad(
        lambda x: losses.reprojection_loss(ring_rig, x, jnp.asarray(xy), jnp.asarray(score)).sum()
    )(jnp.asarray(X))
    assert np.isfinite(float(e)) and np.all(np.isfinite(np.asarray(g)))
    assert float(e) < 1.0


def test_gradient_matches_finite_differences(ring_rig):
    rng = np.random.default_rng(2)
    with jax.enable_x64(True):
        rig = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), ring_rig)
        X = scene_points(ring_rig, 2, (2, 18)).astype(np.float64)
        xy = (
            jnp.moveaxis(cameras.project_points(rig, jnp.asarray(X)), 0, 1)
            + rng.normal(size=(2, 4, 18, 2)) * 3
        )
        score = jnp.asarray((rng.uniform(size=(2, 4, 18)) > 0.2).astype(np.float64))
        # Off the kinks of |.|: evaluate away from zero residuals (noise above keeps them away).
        f = lambda x: jnp.sum(losses.reprojection_loss(rig, x, xy, score))  # noqa: E731
        x0 = jnp.asarray(X + rng.normal(size=X.shape) * 0.01)
        g = np.asarray(jax.grad(f)(x0))
        eps = 1e-6
        for idx in [(0, 0, 0), (0, 5, 1), (1, 10, 2), (1, 17, 0)]:
            d = np.zeros(X.shape)
            d[idx] = eps
            fd = (float(f(x0 + d)) - float(f(x0 - d))) / (2 * eps)
            np.testing.assert_allclose(g[idx], fd, rtol=1e-5, atol=1e-3)


def test_masked_mean_of_nothing_is_zero():
    assert float(losses.masked_mean(jnp.ones(3), jnp.zeros(3, bool))) == 0.0
    assert (
        float(losses.masked_mean(jnp.array([1.0, 3.0, 100.0]), jnp.array([1, 1, 0], bool))) == 2.0
    )
