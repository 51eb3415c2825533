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


def _view_normals(Rt: jax.Array, xy: jax.Array, w: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each view's share of the weighted linear-triangulation normal equations.

    DLT minimises |A[:, :3] X + A[:, 3]|^2 over two rows per view, x P[2] - P[0] and
    y P[2] - P[1], scaled by the view's weight; the 3x3 normal equations are a sum over views,
    so any subset of views (a camera pair) is a sum of these terms.

    Args:
      Rt: (C, 3, 4) normalised projection matrices; xy: (B, C, 2) normalised image points;
      w: (B, C) non-negative weights, 0 = not seen.
    Returns:
      m (B, C, 3, 3) and b (B, C, 3): view c contributes m[:, c] X = b[:, c].
    """
    P = Rt[None]  # (1, C, 3, 4)
    rows = jnp.stack(
        [xy[..., 0:1] * P[..., 2, :] - P[..., 0, :], xy[..., 1:2] * P[..., 2, :] - P[..., 1, :]],
        axis=-2,
    )
    rows = rows * w[..., None, None]  # (B, C, 2, 4)
    a, c = rows[..., :3], rows[..., 3]
    return jnp.einsum("...ri,...rj->...ij", a, a), -jnp.einsum("...ri,...r->...i", a, c)


def _solve_normals(m: jax.Array, b: jax.Array, num_views: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Solves symmetric 3x3 normal equations in closed form (cofactors over the determinant).

    Elementwise arithmetic on the whole batch: a batched eigendecomposition and LU solve per point
    cost several times more on a CPU (and this runs for every keypoint of every camera pair).

    Args:
      m: (..., 3, 3) symmetric positive semi-definite; b: (..., 3); num_views: (...) views seen.
    Returns:
      xyz (..., 3), 0 where invalid, and valid (...): two or more views and a normal matrix that
      is not (nearly) singular, i.e. rays not (nearly) parallel nor all through one centre.
    """
    r0, r1, r2 = m[..., 0, :], m[..., 1, :], m[..., 2, :]
    cof = jnp.stack(
        [jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-2
    )  # adj(m), symmetric
    det = jnp.sum(r0 * cof[..., 0, :], axis=-1)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # det = l_min l_mid l_max and trace >= l_max >= l_mid: det > rtol trace^3 implies
    # l_min > rtol l_max, a scale-free rank test (rays at an angle, not one line).
    ok = (num_views >= 2) & (trace > 0) & (det > _SINGULAR_RTOL * trace**3)
    xyz = jnp.einsum("...ij,...j->...i", cof, b) / jnp.where(ok, det, 1.0)[..., None]
    ok = ok & jnp.all(jnp.isfinite(xyz), axis=-1)
    return jnp.where(ok[..., None], xyz, 0.0), ok


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
def triangulate_points(rig: Rig, px: jax.Array, weight: jax.Array) -> tuple[jax.Array, jax.Array]:
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
    m, b = _view_normals(Rt, xy, w)
    xyz, ok = _solve_normals(m.sum(axis=1), b.sum(axis=1), jnp.sum(w > 0, axis=1))
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
    m, b = _view_normals(Rt, xy, seen)  # each view's terms once, then summed per pair
    i, j = pairs[:, 0], pairs[:, 1]
    # (B, Q, 3), (B, Q)
    xyz, ok = _solve_normals(m[:, i] + m[:, j], b[:, i] + b[:, j], seen[:, i] + seen[:, j])
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
