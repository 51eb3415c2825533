"""cameras.py against OpenCV (the reference camera model) and closed-form cases."""

from __future__ import annotations

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mvpose_jax import cameras
from mvpose_jax.errors import InputError
from tests.helpers import random_rig


def _cam(rig, c):
    return (
        np.asarray(rig.K[c], np.float64),
        np.asarray(rig.dist[c], np.float64),
        np.asarray(rig.R[c], np.float64),
        np.asarray(rig.t[c], np.float64),
    )


def _cv_undistort(px, K, D, iters=None):
    """cv2.undistortPoints; with ``iters``, run to that many iterations or convergence."""
    if iters is None:
        return cv2.undistortPoints(px[:, None], K, D)[:, 0]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iters, 1e-14)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        return cv2.undistortPointsIter(px[:, None], K, D, None, None, crit)[:, 0]
    return cv2.undistortPoints(px[:, None], K, D, None, None, None, crit)[:, 0]  # OpenCV 5


def _image_points(rig, c, n=9):
    """A pixel grid covering the whole image of camera c, corners included: (n*n, 2)."""
    w, h = np.asarray(rig.size[c], np.float64)
    u, v = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    return np.stack([u.ravel(), v.ravel()], axis=-1)


def _world_points_seen_at(rig, c, px, rng):
    """World points that camera c sees at (distorted) pixels px, at random depths 1-8 m."""
    K, D, R, t = _cam(rig, c)
    xy = _cv_undistort(px, K, D, iters=200)
    depth = rng.uniform(1.0, 8.0, size=(len(px), 1))
    p_cam = np.concatenate([xy, np.ones((len(px), 1))], axis=1) * depth
    return (p_cam - t) @ R  # R^T (p_cam - t)


def _rigs(preset_rig, ring_rig):
    return [preset_rig, ring_rig]


def test_project_points_matches_opencv_on_every_camera(preset_rig, ring_rig):
    rng = np.random.default_rng(0)
    project = jax.jit(cameras.project_points)
    for rig in _rigs(preset_rig, ring_rig):
        for c in range(rig.num_cameras):
            K, D, R, t = _cam(rig, c)
            # Points seen near the image corners and edges, where distortion is strongest.
            X = _world_points_seen_at(rig, c, _image_points(rig, c), rng)
            ref, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, D)
            ours = np.asarray(project(rig, jnp.asarray(X, jnp.float32)))[c]
            np.testing.assert_allclose(ours, ref[:, 0], atol=1e-3, rtol=0, err_msg=rig.names[c])


def test_undistort_points_matches_opencv_on_every_camera(preset_rig, ring_rig):
    undistort = jax.jit(cameras.undistort_points, static_argnames="num_iters")
    for rig in _rigs(preset_rig, ring_rig):
        px = np.stack([_image_points(rig, c) for c in range(rig.num_cameras)])
        ours5 = np.asarray(undistort(rig, jnp.asarray(px, jnp.float32), num_iters=5))
        ours = np.asarray(undistort(rig, jnp.asarray(px, jnp.float32)))
        for c in range(rig.num_cameras):
            K, D, _, _ = _cam(rig, c)
            to_px = lambda xy: xy @ K[:2, :2].T + K[:2, 2]  # noqa: E731
            # OpenCV's default stops after 5 iterations: num_iters=5 reproduces it exactly.
            np.testing.assert_allclose(
                ours5[c], to_px(_cv_undistort(px[c], K, D)), atol=1e-3, rtol=0
            )
            # Our default iterates to convergence; compare with OpenCV run to convergence.
            np.testing.assert_allclose(
                ours[c], to_px(_cv_undistort(px[c], K, D, 200)), atol=1e-3, rtol=0
            )


@pytest.mark.parametrize("num_iters", [5, 20])
def test_undistortion_stopped_at_its_fixed_point_is_the_fixed_count_bit_for_bit(
    preset_rig, ring_rig, num_iters
):
    """The early stop (a block of steps that changes no point) returns exactly what running every
    step returns: the same steps written out as a fixed loop are the reference."""

    def fixed(K, dist, px):
        k1, k2, p1, p2, k3 = dist
        y0 = (px[..., 1] - K[1, 2]) / K[1, 1]
        x0 = (px[..., 0] - K[0, 2] - K[0, 1] * y0) / K[0, 0]
        x, y = x0, y0
        for _ in range(num_iters):
            r2 = x * x + y * y
            icdist = 1.0 / (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            ok = icdist > 0
            x, y = jnp.where(ok, (x0 - dx) * icdist, x0), jnp.where(ok, (y0 - dy) * icdist, y0)
        return jnp.stack([x, y], axis=-1)

    reference = jax.jit(jax.vmap(fixed))
    weak = dataclasses.replace(ring_rig, dist=ring_rig.dist * 0.01)  # settles within a block
    for rig in (*_rigs(preset_rig, ring_rig), weak):
        px = jnp.asarray(
            np.stack([_image_points(rig, c) for c in range(rig.num_cameras)]), jnp.float32
        )
        ours = cameras.undistort_normalized(rig, px, num_iters=num_iters)
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(reference(rig.K, rig.dist, px)))


def test_undistort_inverts_project(ring_rig):
    rng = np.random.default_rng(1)
    X = rng.uniform(-1.0, 1.0, size=(50, 3)) + [0.0, -1.0, 0.0]
    px = cameras.project_points(ring_rig, jnp.asarray(X, jnp.float32))
    und = cameras.undistort_normalized(ring_rig, px)
    p_cam = cameras.world_to_camera(ring_rig, jnp.asarray(X, jnp.float32))
    np.testing.assert_allclose(und, p_cam[..., :2] / p_cam[..., 2:], atol=2e-6)


@pytest.mark.parametrize("batch", [(), (1,), (3, 2)])
def test_project_points_batch_shapes(ring_rig, batch):
    X = jnp.asarray(np.random.default_rng(2).normal(size=batch + (3,)), jnp.float32)
    px = jax.jit(cameras.project_points)(ring_rig, X)
    assert px.shape == (ring_rig.num_cameras,) + batch + (2,)
    per_cam = cameras.project_points_per_camera(
        ring_rig, jnp.broadcast_to(X, (ring_rig.num_cameras,) + X.shape)
    )
    np.testing.assert_allclose(per_cam, px, atol=1e-4)


def test_camera_centres_and_rays(ring_rig):
    centres = np.asarray(cameras.camera_centres(ring_rig))
    # The centre maps to the camera origin.
    p = np.einsum("cij,cj->ci", np.asarray(ring_rig.R), centres) + np.asarray(ring_rig.t)
    np.testing.assert_allclose(p, 0.0, atol=1e-5)
    # The ray through the projection of X passes through X.
    X = np.array([[0.3, -1.2, 0.4], [-0.5, -0.2, 0.1]], np.float32)
    px = cameras.project_points(ring_rig, jnp.asarray(X))
    d = np.asarray(cameras.pixel_rays(ring_rig, px))
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)
    to_x = X[None] - centres[:, None]
    to_x /= np.linalg.norm(to_x, axis=-1, keepdims=True)
    np.testing.assert_allclose(d, to_x, atol=1e-5)


def test_points_behind_camera_are_finite_with_finite_gradients(ring_rig):
    centre = cameras.camera_centres(ring_rig)[0]
    behind = centre - 2.0 * ring_rig.R[0, 2]  # 2 m behind camera 0
    px = cameras.project_points(ring_rig, behind)
    assert np.all(np.isfinite(px))
    assert float(cameras.point_depths(ring_rig, behind)[0]) < 0
    g = jax.grad(lambda x: cameras.project_points(ring_rig, x).sum())(behind)
    assert np.all(np.isfinite(g))


def test_normalise_pixels_maps_image_corners_to_unit_square(preset_rig):
    w, h = np.asarray(preset_rig.size).T
    corners = np.stack([np.stack([0 * w, 0 * h], -1), np.stack([w, h], -1)], axis=1)  # (C, 2, 2)
    out = np.asarray(cameras.normalise_pixels(preset_rig, jnp.asarray(corners)))
    np.testing.assert_allclose(out[:, 0], -1.0)
    np.testing.assert_allclose(out[:, 1], 1.0)


def test_rig_is_a_pytree_and_does_not_recompile(ring_rig):
    f = jax.jit(lambda rig, x: cameras.project_points(rig, x))  # a fresh cache
    X = jnp.zeros((4, 3), jnp.float32)
    f(ring_rig, X)
    f(random_rig(seed=5), X)  # same shapes and names: no new trace
    assert f._cache_size() == 1
    leaves = jax.tree_util.tree_leaves(ring_rig)
    assert len(leaves) == 5  # K, dist, R, t, size; names and up are static


def test_select_and_camera_index(preset_rig):
    names = preset_rig.names
    sub = preset_rig.select([names[-1], names[0]])
    assert sub.names == (names[-1], names[0])
    np.testing.assert_array_equal(sub.K[0], preset_rig.K[-1])
    with pytest.raises(InputError) as e:
        preset_rig.select(["nope"])
    assert e.value.camera == "nope"


def test_select_gives_the_same_cameras_eagerly_and_under_jit(preset_rig):
    names = preset_rig.names
    order = [names[2], names[0], names[-1]]
    eager = preset_rig.select(order)
    traced = jax.jit(lambda rig: rig.select(order))(preset_rig)
    for field in ("K", "dist", "R", "t", "size"):
        a, b = getattr(eager, field), getattr(traced, field)
        assert isinstance(a, jax.Array) and a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, np.asarray(getattr(preset_rig, field))[[2, 0, -1]])
    assert preset_rig.select(list(names)) is preset_rig  # all cameras in order: nothing to copy
    assert preset_rig.select(list(range(len(names)))) is preset_rig


def test_up_vector_inferred_from_cameras_matches_calibration(preset_rig):
    inferred = cameras.up_vector(cameras.Rig(**{**preset_rig.__dict__, "up": None}))
    # Level cameras pin up down to a few degrees (the mean image-up alone is 6-10 degrees off).
    assert np.dot(inferred, cameras.up_vector(preset_rig)) > np.cos(np.radians(3.0))


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("R", np.diag([1.0, 1.0, 1.1]), "orthonormal"),
        ("R", np.diag([1.0, 1.0, -1.0]), "reflection"),
        ("K", np.zeros((3, 3)), "K"),
        ("K", np.array([[1000.0, 0, 960], [0, 0, 540], [0, 0, 1]]), "singular"),
        ("t", np.array([0.0, np.nan, 1.0]), "NaN"),
        ("dist", np.array([0.1, np.inf, 0, 0, 0]), "NaN"),
        ("size", np.array([0.0, 1080.0]), "positive"),
    ],
)
def test_make_rig_rejects_bad_cameras(field, value, message):
    good = dict(
        K=np.eye(3)[None],
        dist=np.zeros((1, 5)),
        R=np.eye(3)[None],
        t=np.zeros((1, 3)),
        size=np.array([[1920.0, 1080.0]]),
    )
    bad = {**good, field: value[None]}
    with pytest.raises(InputError, match=message) as e:
        cameras.make_rig(**bad, names=["cam0"], file="calib.json")
    assert e.value.file == "calib.json" and e.value.field == field
    if message != "K":
        assert e.value.camera == "cam0"
