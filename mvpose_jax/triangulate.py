"""Triangulation of keypoints seen by several cameras: batched, masked, jit-able.

Two estimators, both on UNDISTORTED normalised image coordinates and in a world frame centred on
the rig (which keeps float32 well conditioned, unlike DLT on raw pixels and world coordinates):

* `triangulate_points`: score-weighted linear (DLT) least squares over all views at once.
* `triangulate_pairwise_centroid`: the paper's initial estimate and baseline; every pair of views
  that both see the keypoint is triangulated on its own and the results are averaged.

Both take the camera axis first, like `cameras`: ``px (C, ..., 2)``, ``weight (C, ...)``, and return
``xyz (..., 3)`` with ``valid (...)``. A keypoint is valid when at least two views see it and their
rays are not (nearly) parallel.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from mvpose_jax.cameras import Rig, rig_centre_and_radius, undistort_normalized

# Relative size, against the largest, below which the normal matrix counts as singular (rays
# parallel, or fewer than two views): such keypoints are reported invalid instead of exploding.
_SINGULAR_RTOL = 1e-6


def _centred_extrinsics(rig: Rig) -> tuple[jax.Array, jax.Array, jax.Array]:
    """[R | t'] of every camera in a world frame centred on the rig and scaled by its radius."""
    centre, radius = rig_centre_and_radius(rig)
    # x_cam = R x + t = R (centre + radius x') + t  =>  x_cam / radius = R x' + (R centre + t) / radius
    t_c = (jnp.einsum("cij,j->ci", rig.R, centre) + rig.t) / radius
    return jnp.concatenate([rig.R, t_c[..., None]], axis=-1), centre, radius


def _dlt(Rt: jax.Array, xy: jax.Array, w: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Weighted linear triangulation of one point.

    Args:
      Rt: (C, 3, 4) normalised projection matrices; xy: (C, 2) normalised image points;
      w: (C,) non-negative weights, 0 = not seen.
    Returns:
      xyz (3,) in the frame of Rt, and valid () bool.
    """
    # Two rows per view: x * P[2] - P[0] and y * P[2] - P[1], scaled by the view's weight.
    rows = jnp.stack(
        [xy[:, 0:1] * Rt[:, 2] - Rt[:, 0], xy[:, 1:2] * Rt[:, 2] - Rt[:, 1]], axis=1
    )  # (C, 2, 4)
    rows = (rows * w[:, None, None]).reshape(-1, 4)
    # Inhomogeneous least squares: minimise |A[:, :3] X + A[:, 3]|^2 via the 3x3 normal equations.
    m = rows[:, :3].T @ rows[:, :3]
    b = -rows[:, :3].T @ rows[:, 3]
    scale = jnp.max(jnp.abs(m))
    # Two views with non-parallel rays make m full rank; compare the smallest eigenvalue with the
    # largest rather than trusting the count, which also catches rays through one camera centre.
    eig = jnp.linalg.eigvalsh(m)
    enough = (jnp.sum(w > 0) >= 2) & (eig[0] > _SINGULAR_RTOL * jnp.maximum(eig[-1], 1e-30))
    ok = enough & (scale > 0)
    m_safe = jnp.where(ok, m, jnp.eye(3, dtype=m.dtype))
    b_safe = jnp.where(ok, b, jnp.zeros_like(b))
    xyz = jnp.linalg.solve(m_safe, b_safe)
    ok = ok & jnp.all(jnp.isfinite(xyz))
    return jnp.where(ok, xyz, 0.0), ok


def _flatten(rig: Rig, px: jax.Array, weight: jax.Array):
    xy = undistort_normalized(rig, px)  # (C, ..., 2)
    C = xy.shape[0]
    batch = xy.shape[1:-1]
    xy = jnp.moveaxis(xy.reshape(C, -1, 2), 0, 1)  # (B, C, 2)
    w = jnp.moveaxis(jnp.broadcast_to(weight, (C,) + batch).reshape(C, -1), 0, 1)  # (B, C)
    w = jnp.maximum(w, 0.0).astype(xy.dtype)
    # Unseen points may hold junk (NaN, huge): zero them so that 0 * junk cannot make a NaN.
    xy = jnp.where((w > 0)[..., None] & jnp.isfinite(xy), xy, 0.0)
    return xy, w, batch


@jax.jit
def triangulate_points(
    rig: Rig, px: jax.Array, weight: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Score-weighted DLT triangulation over any number of views, batched.

    Args:
      rig: the C cameras.
      px: (C, ..., 2) distorted pixel coordinates, as detected.
      weight: (C, ...) per-view weights (detection scores); 0 = the view does not see the point.
    Returns:
      xyz: (..., 3) world points, metres (0 where invalid).
      valid: (...) bool, at least two views with non-parallel rays.
    """
    Rt, centre, radius = _centred_extrinsics(rig)
    xy, w, batch = _flatten(rig, px, weight)
    xyz, ok = jax.vmap(_dlt, in_axes=(None, 0, 0))(Rt, xy, w)
    xyz = jnp.where(ok[:, None], xyz * radius + centre[None], 0.0)
    return xyz.reshape(batch + (3,)), ok.reshape(batch)


def camera_pairs(num_cameras: int) -> np.ndarray:
    """All unordered camera pairs (i < j): (num_pairs, 2) int32."""
    return np.array(list(itertools.combinations(range(num_cameras), 2)), np.int32).reshape(-1, 2)


@jax.jit
def triangulate_pairs(rig: Rig, px: jax.Array, visible: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Two-view triangulation of every camera pair (unweighted DLT on the pair alone).

    Args:
      px: (C, ..., 2) distorted pixels.
      visible: (C, ...) bool or scores (> 0 = seen).
    Returns:
      xyz: (..., Q, 3) metres, one point per pair of `camera_pairs(C)` (0 where invalid);
      valid: (..., Q) bool, both views see the point and their rays are not parallel.
    """
    Rt, centre, radius = _centred_extrinsics(rig)
    xy, w, batch = _flatten(rig, px, visible)
    seen = (w > 0).astype(xy.dtype)  # (B, C)
    pairs = jnp.asarray(camera_pairs(rig.num_cameras))  # (Q, 2)
    Q = pairs.shape[0]
    if Q == 0:
        return jnp.zeros(batch + (0, 3), xy.dtype), jnp.zeros(batch + (0,), bool)
    one_pair = lambda pair, xy_b, seen_b: _dlt(Rt[pair], xy_b[pair], seen_b[pair])  # noqa: E731
    # (B, Q, 3), (B, Q)
    xyz, ok = jax.vmap(lambda x, s: jax.vmap(lambda p: one_pair(p, x, s))(pairs))(xy, seen)
    xyz = jnp.where(ok[..., None], xyz * radius + centre[None, None], 0.0)
    return xyz.reshape(batch + (Q, 3)), ok.reshape(batch + (Q,))


@jax.jit
def triangulate_pairwise_centroid(
    rig: Rig, px: jax.Array, visible: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """The paper's estimate: the centroid of the two-view triangulations of every camera pair.

    Each pair of views that both see a keypoint is triangulated alone (unweighted two-view DLT);
    the pairs' points are averaged. This is the initial 3D the estimator is given and the paper's
    triangulation baseline.

    Args:
      px: (C, ..., 2) distorted pixels.
      visible: (C, ...) bool or scores (> 0 = seen).
    Returns:
      xyz: (..., 3) metres (0 where invalid); valid: (...) bool, at least one usable pair.
    """
    xyz_q, ok_q = triangulate_pairs(rig, px, visible)
    return centroid_of_pairs(xyz_q, ok_q)


def centroid_of_pairs(xyz: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Mean of the valid pair points. xyz: (..., Q, 3); valid: (..., Q) -> (..., 3), (...)."""
    n = valid.sum(axis=-1)
    mean = jnp.sum(jnp.where(valid[..., None], xyz, 0.0), axis=-2) / jnp.maximum(n, 1)[..., None]
    return jnp.where((n > 0)[..., None], mean, 0.0), n > 0
