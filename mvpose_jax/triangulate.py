"""Triangulation of keypoints seen by several cameras: batched, masked, jit-able.

Estimators on UNDISTORTED normalised image coordinates and in a world frame centred on the rig
(which keeps float32 well conditioned, unlike DLT on raw pixels and world coordinates):

* `triangulate_points`: score-weighted linear (DLT) least squares over all views at once.
* `triangulate_pairwise_centroid`: the paper's initial estimate and baseline; every pair of views
  that both see the keypoint is triangulated on its own and the results are averaged.
* `triangulate_robust` / `triangulate_skeletons_robust`: the DLT after rejecting views whose
  reprojection error marks them as outliers (per point; per skeleton, whole views first).
* `blend_skeletons`: robust triangulation where it reconstructs a keypoint, a model's skeleton
  (placed by the triangulated keypoints) elsewhere.
* `human_sized`: whether a triangulated person is no larger than a body (a wrong group of two
  views is often metres large).

Both take the camera axis first, like `cameras`: ``px (C, ..., 2)``, ``weight (C, ...)``, and return
``xyz (..., 3)`` with ``valid (...)``. A keypoint is valid when at least two views see it and their
rays are not (nearly) parallel.
"""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numba
import numpy as np

from mvpose_jax import compiled
from mvpose_jax.cameras import (
    Rig,
    camera_centres,
    pixel_rays,
    rig_centre_and_radius,
    undistort_normalized,
)

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


@compiled.jit
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


@compiled.jit
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


@compiled.jit
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


# =========================================================================== robust triangulation
# A view can be wrong: a left/right swap or a stray keypoint in one camera, or, after a wrong
# match, another person's skeleton (or a fragment) in the person's group. Such a view is wrong on
# one keypoint, or on most of the skeleton at once, and DLT spreads its error over every view.
# The robust estimator rejects views whose reprojection error marks them as outliers, in two
# stages: whole views of a person first (a view whose MEDIAN keypoint error is an outlier is not
# this person's skeleton), then single keypoints. Each stage is a greedy backward selection with a
# fixed number of steps (C - 2, masks, no data-dependent control flow): while the worst view's
# error exceeds the threshold and three or more views remain, drop the view whose removal leaves
# the most consistent rest (the least largest error of the remaining views, each triangulated
# without the candidate). Leaving each candidate out, rather than dropping the view with the
# largest error under the all-view fit, matters with few views: an outlier pulls the joint fit
# towards itself, so with three views a good view often shows the largest error. The leave-one-out
# fits cost little: the normal equations are sums over views (`_view_normals`), so each candidate
# set is one more 3x3 closed-form solve. RANSAC over view pairs would need more solves and a
# random or exhaustive pair choice for the same outcome with C <= 8 views; iterative reweighting
# has no fixed step count to a clean rejection and keeps a small pull from every outlier.

# Reprojection error (undistorted pixels) above which a keypoint's view is an outlier, and above
# which a view's median keypoint error marks the whole skeleton as not this person's. Chosen on
# the validation scenes (`python -m experiments.robust_triangulation`, docs/robust_triangulation.md); a view's detections are 8-12 px (mean)
# from the truth on panoptic5-sized people, so inliers stay well below both.
OUTLIER_PX = 30.0
VIEW_OUTLIER_PX = 30.0
# A view's median is judged only over at least this many keypoints it shares with the fit: the
# median of one or two keypoints is one keypoint's verdict, which the per-keypoint stage gives.
_MIN_KEYPOINTS_FOR_VIEW = 3


def _focal_lengths(rig: Rig) -> jax.Array:
    """(C, 2) fx, fy: normalised image coordinates times these are (undistorted) pixels."""
    return jnp.stack([rig.K[:, 0, 0], rig.K[:, 1, 1]], axis=-1)


def _reprojection_px(Rt: jax.Array, focal: jax.Array, X: jax.Array, xy: jax.Array) -> jax.Array:
    """Undistorted-pixel distance between each camera's projection of X and its observation.

    Args:
      Rt: (C, 3, 4) centred projection matrices; focal: (C, 2) pixels.
      X: (..., 3) points in the centred frame; xy: (..., C, 2) normalised observations.
    Returns:
      (..., C) pixels; inf where the point is not in front of the camera.
    """
    lead = (1,) * (X.ndim - 1)  # explicit broadcasting (the tests raise on rank promotion)
    cam = jnp.einsum("cij,...j->...ci", Rt[:, :, :3], X) + Rt[:, :, 3].reshape(lead + (-1, 3))
    z = cam[..., 2]
    front = z > 1e-6
    proj = cam[..., :2] / jnp.where(front, z, 1.0)[..., None]  # (..., C, 2)
    d = (proj - xy) * focal.reshape(lead + (-1, 2))
    err = jnp.sqrt(jnp.sum(d * d, axis=-1))
    return jnp.where(front & jnp.isfinite(err), err, jnp.inf)


@compiled.jit
def reprojection_errors_px(rig: Rig, xyz: jax.Array, px: jax.Array) -> jax.Array:
    """Undistorted-pixel distance, per camera, between a point's projection and a detection.

    Args:
      rig: the C cameras.
      xyz: (..., 3) world points, metres.
      px: (C, ..., 2) distorted pixels (as detected); junk where a view has no detection.
    Returns:
      (C, ...) pixels of an ideal pinhole camera with the same K (the errors robust
      triangulation thresholds); inf where the point is not in front of the camera.
    """
    Rt, centre, radius = _centred_extrinsics(rig)
    xy = jnp.moveaxis(undistort_normalized(rig, px), 0, -2)  # (..., C, 2)
    X = (xyz - centre.reshape((1,) * (xyz.ndim - 1) + (3,))) / radius
    return jnp.moveaxis(_reprojection_px(Rt, _focal_lengths(rig), X, xy), -1, 0)


def _masked_sums(mask: jax.Array, m: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Normal equations of the views in ``mask`` (..., C): sums of m (..., C, 3, 3), b (..., C, 3).

    ``mask`` may carry extra leading axes before the view axis that ``m`` lacks (one per
    candidate set); the sum is exact per set, never a difference of sums.
    """
    a = mask.astype(m.dtype)
    return jnp.einsum("...c,...cij->...ij", a, m), jnp.einsum("...c,...ci->...i", a, b)


def _drop_one(
    active: jax.Array, spread: jax.Array, worst: jax.Array, threshold: jax.Array
) -> jax.Array:
    """One greedy step: drop argmin(spread) where the worst error exceeds the threshold and at
    least three views remain. active (B, C) bool, spread (B, C) (inf: not a candidate), worst (B,)."""
    C = active.shape[-1]
    best = jnp.argmin(spread, axis=-1)
    drop = (active.sum(-1) >= 3) & (worst > threshold) & jnp.isfinite(jnp.min(spread, axis=-1))
    return active & ~(drop[:, None] & (jnp.arange(C)[None] == best[:, None]))


def _keypoint_selection(
    Rt: jax.Array,
    focal: jax.Array,
    m: jax.Array,
    b: jax.Array,
    xy: jax.Array,
    active: jax.Array,
    threshold: jax.Array,
) -> jax.Array:
    """Per-point greedy view rejection. m (B, C, 3, 3), b (B, C, 3), xy (B, C, 2), active (B, C)
    -> the views kept (B, C)."""
    C = active.shape[-1]
    others = ~jnp.eye(C, dtype=bool)  # (candidate, view): the views left without the candidate

    def spread_of(active, m, b, xy):  # (n, C): the largest error left without each candidate
        rest = active[:, None, :] & others[None]  # (n, Q, C), Q = candidates
        X_q, ok_q = _solve_normals(*_masked_sums(rest, m[:, None], b[:, None]), rest.sum(-1))
        err_q = _reprojection_px(Rt, focal, X_q, xy[:, None])  # (n, Q, C)
        spread = jnp.max(jnp.where(rest, err_q, -jnp.inf), axis=-1)
        return jnp.where(active & ok_q, spread, jnp.inf)

    def step(active):
        X, ok = _solve_normals(*_masked_sums(active, m, b), active.sum(-1))
        err = _reprojection_px(Rt, focal, X, xy)  # (B, C)
        worst = jnp.where(ok, jnp.max(jnp.where(active, err, -jnp.inf), axis=-1), -jnp.inf)
        need = (active.sum(-1) >= 3) & (worst > threshold)
        spread = _where_needed(need, spread_of, jnp.inf, active, m, b, xy)
        return _drop_one(active, spread, worst, threshold)

    return _greedy_steps(step, active, max(C - 2, 0))


def _greedy_steps(step, state: jax.Array, max_steps: int) -> jax.Array:
    """``step`` applied up to ``max_steps`` times, stopping once a step changes nothing: the
    state is then a fixed point (a step drops only where an error exceeds the threshold, and the
    same state gives the same errors), so the result is that of all ``max_steps`` steps."""

    def cond(carry):
        i, _, changed = carry
        return (i < max_steps) & changed

    def body(carry):
        i, state, _ = carry
        new = step(state)
        return i + 1, new, jnp.any(new != state)

    return jax.lax.while_loop(cond, body, (0, state, jnp.asarray(max_steps > 0)))[1]


# Below this many rows a batch is evaluated whole: gathering the few rows that need the
# leave-one-out fits costs more launches than it saves arithmetic (a live frame's people).
_MIN_ROWS_TO_COMPACT = 256
# The needed rows are gathered in blocks of this fraction of the batch: about 1.5% of keypoints
# and 1% of people need them on synthetic scenes (one block), more on real ones (a block more
# per 1/32 of the batch).
_GATHER_FRACTION = 32


def _where_needed(need: jax.Array, fn, fill: float, *rows: jax.Array) -> jax.Array:
    """``fn(*rows)`` (each argument and the result with the rows first) where ``need`` (B,) is
    True, ``fill`` elsewhere; computed on the needed rows alone when they are few.

    The leave-one-out fits are most of robust triangulation's arithmetic (C solves and C^2
    reprojections per row and step), and only rows whose worst error exceeds the threshold use
    them. The needed rows go through ``fn`` in blocks of B / `_GATHER_FRACTION`, in a loop of as
    many blocks as they fill: the arithmetic follows their number, and the program holds ``fn``
    once (each copy of it costs robust triangulation's compilation about a second; the former
    choice between gathers of 1/32, 1/4 and all of the batch held it three times). The same
    arithmetic per row on every path, so the result does not depend on how many rows need it.
    """
    B = need.shape[0]

    if B < _MIN_ROWS_TO_COMPACT:
        # Usually no row needs them (a live frame's people agree with their views): skipped.
        def whole(_):
            out = fn(*rows)
            return jnp.where(_expand(need, out), out, fill)

        out_shape = jax.eval_shape(fn, *rows)
        return jax.lax.cond(
            jnp.any(need),
            whole,
            lambda _: jnp.full(out_shape.shape, fill, out_shape.dtype),
            None,
        )

    size = max(1, B // _GATHER_FRACTION)
    # The needed rows' indices first, then B (out of range: the scatter drops it).
    (order,) = jnp.nonzero(need, size=B, fill_value=B)
    out_shape = jax.eval_shape(fn, *(r[:size] for r in rows))

    def block(i, full):
        # The last block may start earlier than i * size (dynamic_slice keeps it inside the
        # batch) and repeat rows of the one before: they get the same values again.
        idx = jax.lax.dynamic_slice_in_dim(order, i * size, size)
        out = fn(*(jnp.take(r, idx, axis=0, mode="clip") for r in rows))
        return full.at[idx].set(out, mode="drop")

    full = jnp.full((B,) + out_shape.shape[1:], fill, out_shape.dtype)
    blocks = (jnp.sum(need) + size - 1) // size
    return jax.lax.fori_loop(0, blocks, block, full)


def _expand(mask: jax.Array, like: jax.Array) -> jax.Array:
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))


def nanmedian_by_rank(a: jax.Array, axis: int = -1) -> jax.Array:
    """``jnp.nanmedian(a, axis)``, bit for bit, for a short axis (a skeleton's keypoints, its
    views): each value's rank among the others by comparison, no sort. XLA's sort on the CPU
    costs about ten times the O(n^2) comparisons for n <= 30 (18 keypoints: 97 vs 10 ms on
    4.4M values), and the medians of robust triangulation and the epipolar matcher run on every
    person and pair of skeletons.

    Returns:
      ``a`` without ``axis``; NaN where the axis holds no number.
    """
    a = jnp.moveaxis(a, axis, -1)
    n_axis = a.shape[-1]
    ok = ~jnp.isnan(a)
    v_i, v_j = a[..., :, None], a[..., None, :]
    earlier = jnp.arange(n_axis)[None, :] < jnp.arange(n_axis)[:, None]  # j < i: ties in order
    earlier = earlier.reshape((1,) * (a.ndim - 1) + earlier.shape)
    below = ok[..., :, None] & ok[..., None, :] & ((v_j < v_i) | ((v_j == v_i) & earlier))
    rank = jnp.sum(below, axis=-1)  # (..., n): 0..count-1 over the numbers
    count = jnp.sum(ok, axis=-1, keepdims=True)
    lo = jnp.sum(jnp.where(ok & (rank == (count - 1) // 2), a, 0.0), axis=-1)
    hi = jnp.sum(jnp.where(ok & (rank == count // 2), a, 0.0), axis=-1)
    # jnp.nanmedian's linear interpolation at the half: lo * 0.5 + hi * 0.5.
    return jnp.where(count[..., 0] > 0, lo * 0.5 + hi * 0.5, jnp.nan)


def _view_medians(err: jax.Array, use: jax.Array) -> jax.Array:
    """Median over keypoints of each view's error. err, use: (..., K, C) -> (..., C), NaN where
    fewer than `_MIN_KEYPOINTS_FOR_VIEW` keypoints are used."""
    med = nanmedian_by_rank(jnp.where(use, err, jnp.nan), axis=-2)
    return jnp.where(use.sum(-2) >= _MIN_KEYPOINTS_FOR_VIEW, med, jnp.nan)


def _skeleton_selection(
    Rt: jax.Array,
    focal: jax.Array,
    m: jax.Array,
    b: jax.Array,
    xy: jax.Array,
    seen: jax.Array,
    threshold: jax.Array,
) -> jax.Array:
    """Per-person greedy rejection of whole views by their median keypoint error.

    m (N, K, C, 3, 3), b (N, K, C, 3), xy (N, K, C, 2), seen (N, K, C) -> views kept (N, C).
    """
    C = seen.shape[-1]
    others = ~jnp.eye(C, dtype=bool)

    def spread_of(views, seen, m, b, xy):  # (n, C): the largest median left without each
        rest = views[:, None, :] & others[None]  # (n, Q, C)
        use_q = seen[:, None] & rest[:, :, None, :]  # (n, Q, K, C)
        X_q, ok_q = _solve_normals(*_masked_sums(use_q, m[:, None], b[:, None]), use_q.sum(-1))
        err_q = _reprojection_px(Rt, focal, X_q, xy[:, None])  # (n, Q, K, C)
        med_q = _view_medians(err_q, use_q & ok_q[..., None])  # (n, Q, C)
        spread = jnp.nanmax(jnp.where(rest, med_q, jnp.nan), axis=-1)  # (n, Q)
        return jnp.where(views & ~jnp.isnan(spread), spread, jnp.inf)

    def step(views):  # views: (N, C)
        use = seen & views[:, None, :]  # (N, K, C)
        X, ok = _solve_normals(*_masked_sums(use, m, b), use.sum(-1))  # (N, K, 3)
        med = _view_medians(_reprojection_px(Rt, focal, X, xy), use & ok[..., None])  # (N, C)
        worst = jnp.nanmax(jnp.where(views, med, jnp.nan), axis=-1)
        worst = jnp.where(jnp.isnan(worst), -jnp.inf, worst)
        need = (views.sum(-1) >= 3) & (worst > threshold)
        spread = _where_needed(need, spread_of, jnp.inf, views, seen, m, b, xy)
        return _drop_one(views, spread, worst, threshold)

    return _greedy_steps(step, seen.any(axis=1), max(C - 2, 0))


@compiled.jit
def triangulate_robust(
    rig: Rig, px: jax.Array, weight: jax.Array, *, outlier_px: float = OUTLIER_PX
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Score-weighted DLT that rejects outlier views of each point.

    While the worst view's reprojection error exceeds ``outlier_px`` and three or more views
    remain, the view whose removal leaves the most consistent rest is dropped (C - 2 steps at
    most, so never below two views); then DLT on the views kept. Without outliers it is
    `triangulate_points`.

    Args:
      rig: the C cameras.
      px: (C, ..., 2) distorted pixels; weight: (C, ...) scores, 0 = not seen.
      outlier_px: reprojection error (undistorted pixels) that marks a view as an outlier.
    Returns:
      xyz (..., 3) metres (0 where invalid), valid (...), kept (C, ...) bool: the views used.
    """
    Rt, centre, radius = _centred_extrinsics(rig)
    xy, w, batch = _flatten(rig, px, weight)
    m, b = _view_normals(Rt, xy, w)
    kept = _keypoint_selection(
        Rt, _focal_lengths(rig), m, b, xy, w > 0, jnp.asarray(outlier_px, xy.dtype)
    )
    return _finish(m, b, kept, centre, radius, batch)


@compiled.jit
def triangulate_skeletons_robust(
    rig: Rig,
    px: jax.Array,
    weight: jax.Array,
    *,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Robust triangulation of whole skeletons: wrong views of the person, then of each keypoint.

    First, per person, while the largest median keypoint error of a view exceeds
    ``view_outlier_px`` and three or more views remain, the view whose removal leaves the most
    consistent rest is dropped for every keypoint (another person's skeleton, or a fragment, in
    the person's group). Then `triangulate_robust`'s per-keypoint rejection on the views left.

    Args:
      rig: the C cameras.
      px: (C, ..., K, 2) distorted pixels, the last batch axis the skeleton's K keypoints.
      weight: (C, ..., K) scores, 0 = not seen.
      outlier_px: per-keypoint outlier threshold, undistorted pixels.
      view_outlier_px: whole-view threshold on the median keypoint error; inf: no whole-view
        stage.
    Returns:
      xyz (..., K, 3) metres (0 where invalid), valid (..., K), kept (C, ..., K) bool.
    """
    Rt, centre, radius = _centred_extrinsics(rig)
    if np.ndim(weight) < 2:
        raise ValueError("weight must be (C, ..., K): a keypoint axis after the cameras")
    xy, w, batch = _flatten(rig, px, weight)  # (B, C, 2), (B, C) with B = N * K
    C, K = w.shape[1], batch[-1]
    N = xy.shape[0] // max(K, 1)
    m, b = _view_normals(Rt, xy, w)
    focal = _focal_lengths(rig)
    views = _skeleton_selection(
        Rt,
        focal,
        m.reshape(N, K, C, 3, 3),
        b.reshape(N, K, C, 3),
        xy.reshape(N, K, C, 2),
        (w > 0).reshape(N, K, C),
        jnp.asarray(view_outlier_px, xy.dtype),
    )  # (N, C)
    active = (w > 0) & jnp.repeat(views, K, axis=0)  # (B, C)
    kept = _keypoint_selection(Rt, focal, m, b, xy, active, jnp.asarray(outlier_px, xy.dtype))
    return _finish(m, b, kept, centre, radius, batch)


def leave_one_view_out(
    rig: Rig,
    px: jax.Array,
    weight: jax.Array,
    *,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`triangulate_skeletons_robust` of each skeleton without each camera in turn: the consensus
    of the OTHER views, against which a view is judged (`detector_fit`, `view_confidence`).

    One compiled shape for all C calls (the left-out camera's weights are zeroed).

    Args:
      rig: the C cameras.
      px: (C, ..., K, 2) distorted pixels; weight: (C, ..., K) scores, 0 = not seen.
    Returns:
      xyz (C, ..., K, 3) metres (row c: without camera c; 0 where invalid), valid (C, ..., K),
      views (C, ..., K) int: how many views the row's consensus kept.
    """
    weight = jnp.asarray(weight)
    C = weight.shape[0]
    out = []
    for c in range(C):
        w_c = weight.at[c].set(0.0)
        xyz, ok, kept = triangulate_skeletons_robust(
            rig, px, w_c, outlier_px=outlier_px, view_outlier_px=view_outlier_px
        )
        out.append((xyz, ok, kept.sum(axis=0)))
    return tuple(jnp.stack(a) for a in zip(*out, strict=True))


def _finish(m, b, kept, centre, radius, batch):
    """DLT on the kept views, back to world metres, reshaped to the batch."""
    xyz, ok = _solve_normals(*_masked_sums(kept, m, b), kept.sum(-1))
    xyz = jnp.where(ok[:, None], xyz * radius + centre[None], 0.0)
    return (
        xyz.reshape(batch + (3,)),
        ok.reshape(batch),
        jnp.moveaxis(kept, 1, 0).reshape((kept.shape[1],) + batch),
    )


# =========================================================================== blend with a model
# A learned estimator (the MLP) returns every keypoint, also those no two views see, but on the
# keypoints two or more views agree on it is less accurate than robust triangulation: on the
# validation scenes of every shift the triangulation was closer to the truth in each bin of
# inlier-view count (2-5) and of the difference of their reprojection errors over the inlier
# views, and preferring the network where it reprojects within a margin of the triangulation
# only lost millimetres (docs/blend.md). Under a shift the network was not trained for (the
# floor 0.6 m off) it is off by decimetres while triangulation is not. So the blend takes the
# triangulation wherever it exists, and the network's keypoint only where it does not, made
# consistent with the person's triangulated keypoints and with the one view that sees it.


@compiled.jit
def blend_skeletons(
    rig: Rig,
    px: jax.Array,
    weight: jax.Array,
    *,
    model_xyz: jax.Array,
    tri_xyz: jax.Array,
    tri_valid: jax.Array,
    kept: jax.Array,
    legs: jax.Array | None = None,
    up: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Robust triangulation where it reconstructs a keypoint, a model's keypoint elsewhere.

    Where the triangulation is invalid (fewer than two inlier views), the model's keypoint is
    moved by the person's median offset from the model to the triangulation over the keypoints
    both give (the model's shape, the triangulation's placement: a model off by a constant, e.g.
    on a floor it was not trained for, is put back), then, when exactly one inlier view sees the
    keypoint, onto that view's ray (the closest point of the ray: it then projects onto the
    detection).

    With ``legs``, a knee or ankle that exactly one inlier view sees, below a reconstructed
    parent (hip, knee: triangulated, or placed so itself), is put where its ray lies at the
    bone's length from the parent, on the lower of the two such points (`hang_on_ray`): legs
    hang below their parent, whatever floor the model learnt. The length is the other leg's
    triangulated bone where there is one, else the model's. The model's own depth along the ray
    comes from what it learnt of the floor, and is off by as much as the floor it trained on
    (validation scenes, models trained 0.6 m below the floor: lower-leg PCP 94.7 -> 98.7).

    Args:
      rig: the C cameras.
      px: (C, ..., K, 2) distorted pixels; weight: (C, ..., K) scores, 0 = not seen.
      model_xyz: (..., K, 3) the model's keypoints, metres.
      tri_xyz, tri_valid, kept: `triangulate_skeletons_robust` of the same detections:
        (..., K, 3), (..., K), (C, ..., K).
      legs: optional (J, 4) int rows (parent, child, mirrored parent, mirrored child),
        `skeletons.leg_chains` (parents first).
      up: (3,) the world's up (`cameras.up_vector`); needed with ``legs``.
    Returns:
      xyz (..., K, 3) metres, every keypoint; from_triangulation (..., K) bool.
    """
    model_xyz = model_xyz.astype(tri_xyz.dtype)
    # The person's offset: median per axis, so a few keypoints the model gets wrong do not move it.
    offset = nanmedian_by_rank(
        jnp.where(tri_valid[..., None], tri_xyz - model_xyz, jnp.nan), axis=-2
    )
    offset = jnp.where(tri_valid.any(axis=-1)[..., None], offset, 0.0)  # (..., 3)
    moved = model_xyz + offset[..., None, :]
    # The one inlier view's ray (unseen pixels may be junk: the image centre stands in).
    lead = (1,) * (px.ndim - 2)
    centre_px = 0.5 * rig.size.reshape((-1,) + lead + (2,))
    one = kept & (kept.sum(axis=0, keepdims=True) == 1)  # (C, ..., K)
    rays = pixel_rays(rig, jnp.where(one[..., None], px, centre_px))  # (C, ..., K, 3)
    ray = jnp.sum(jnp.where(one[..., None], rays, 0.0), axis=0)  # (..., K, 3)
    cam = camera_centres(rig).reshape((-1,) + lead + (3,))
    origin = jnp.sum(jnp.where(one[..., None], cam, 0.0), axis=0)
    depth = jnp.sum((moved - origin) * ray, axis=-1, keepdims=True)
    on_ray = one.any(axis=0) & (depth[..., 0] > 0)  # a point behind the camera stays put
    moved = jnp.where(on_ray[..., None], origin + ray * depth, moved)
    xyz = jnp.where(tri_valid[..., None], tri_xyz, moved)
    if legs is None or legs.shape[0] == 0:
        return xyz, tri_valid
    known = tri_valid
    for j in range(legs.shape[0]):  # in order: a knee placed here is the ankle's parent
        parent, child, m_parent, m_child = (legs[j, i] for i in range(4))
        mirrored = tri_valid[..., m_parent] & tri_valid[..., m_child]
        length = jnp.where(
            mirrored,
            jnp.linalg.norm(tri_xyz[..., m_child, :] - tri_xyz[..., m_parent, :], axis=-1),
            jnp.linalg.norm(model_xyz[..., child, :] - model_xyz[..., parent, :], axis=-1),
        )
        hung = hang_on_ray(
            origin[..., child, :], ray[..., child, :], xyz[..., parent, :], length, up
        )
        place = known[..., parent] & on_ray[..., child] & ~tri_valid[..., child]
        xyz = xyz.at[..., child, :].set(jnp.where(place[..., None], hung, xyz[..., child, :]))
        known = known.at[..., child].set(known[..., child] | place)
    return xyz, tri_valid


def hang_on_ray(
    origin: jax.Array, ray: jax.Array, parent: jax.Array, length: jax.Array, up: jax.Array
) -> jax.Array:
    """The point of a ray at ``length`` from ``parent``: the lower one (along ``up``) of the two
    in front of the camera; the ray's point closest to ``parent`` where the ray passes farther.

    Args:
      origin, ray: (..., 3) the ray's start (camera centre) and unit direction.
      parent: (..., 3); length: (...) metres.
      up: (3,) unit vector.
    Returns:
      (..., 3).
    """
    t0 = jnp.sum((parent - origin) * ray, axis=-1)
    miss2 = jnp.sum((parent - origin - t0[..., None] * ray) ** 2, axis=-1)
    h = jnp.sqrt(jnp.maximum(length**2 - miss2, 0.0))
    near, far = t0 - h, t0 + h  # depths along the ray
    slope = jnp.einsum("...i,i->...", ray, up)  # height gained per metre of depth
    # The lower point: the nearer one where the ray climbs, the farther where it descends; a
    # point behind the camera is not on the ray.
    lower = jnp.where(slope > 0, near, far)
    depth = jnp.where(lower > 0, lower, far)
    return origin + depth[..., None] * ray


# =========================================================================== a person's size
# A triangulation of two views that hold two different people (a wrong group that epipolar
# geometry could not rule out: their skeletons lie near each other's epipolar lines) lands where
# the rays cross, often metres behind the scene, as a skeleton scaled by that depth. No person
# is that large: over the validation scenes of every domain shift (quick models, combined and
# true groupings, robust triangulation) a person's keypoints lay at a median 0.33-0.42 m from
# their median point, 0.74 m at most; one such ghost on the part-mixing test scenes lay at
# 20 m. The bound is a fact about bodies, not a setting chosen on scenes: about twice an adult's
# spread (a tall adult lying with arms stretched overhead is near 0.6 m).
MAX_SPREAD_M = 1.0


def skeleton_spread(xyz: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """A person's size: the median distance (m) of its valid keypoints from their median point.

    Args:
      xyz: (..., K, 3) metres; valid: (..., K) bool.
    Returns:
      (...,) metres; 0 where fewer than two keypoints are valid (nothing to judge).
    """
    xyz, valid = np.asarray(xyz, np.float64), np.asarray(valid, bool)
    lead, K = valid.shape[:-1], valid.shape[-1]
    return _skeleton_spreads(xyz.reshape(-1, K, 3), valid.reshape(-1, K)).reshape(lead)


# Compiled: a live frame checks a few people, where numpy's calls (two sorts, masks, indexing)
# cost about 0.1 ms, a tenth of the frame.
@numba.njit(cache=True)
def _skeleton_spreads(xyz, valid):
    """`skeleton_spread` of (N, K, 3) float64 / (N, K): the same medians (np.nanmedian's: a NaN
    coordinate is no sample), the distance's sum of squares in numpy's order."""
    N, K = valid.shape
    out = np.zeros(N)
    buf = np.empty(K)
    centre = np.empty(3)
    dist = np.empty(K)
    for i in range(N):
        n_valid = 0
        for k in range(K):
            n_valid += valid[i, k]
        if n_valid < 2:
            continue
        for a in range(3):
            n = 0
            for k in range(K):
                if valid[i, k] and not np.isnan(xyz[i, k, a]):
                    n = insert_sorted(buf, n, xyz[i, k, a])
            centre[a] = sorted_median(buf, n)
        n = 0
        for k in range(K):
            if valid[i, k]:
                d0 = xyz[i, k, 0] - centre[0]
                d1 = xyz[i, k, 1] - centre[1]
                d2 = xyz[i, k, 2] - centre[2]
                e = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                if not np.isnan(e):
                    n = insert_sorted(dist, n, e)
        out[i] = sorted_median(dist, n)
    return out


# Medians of a few numbers in compiled host loops (a skeleton's keypoints, a filter's window):
# each number inserted into a sorted scratch buffer, then np.nanmedian's middle of the n.
@numba.njit(cache=True)
def insert_sorted(buf, n, v):
    """Inserts the number v into the sorted buf[:n]; returns n + 1."""
    m = n
    while m > 0 and buf[m - 1] > v:
        buf[m] = buf[m - 1]
        m -= 1
    buf[m] = v
    return n + 1


@numba.njit(cache=True)
def sorted_median(buf, n):
    """The median of the sorted buf[:n], as np.nanmedian gives it (the mean of the two middle
    numbers when n is even); NaN when n is 0."""
    return (buf[(n - 1) // 2] + buf[n // 2]) / 2 if n else np.nan


def nanmedian_along(a: np.ndarray, axis: int) -> np.ndarray:
    """``np.nanmedian(a, axis)``, equal to it (NaN where a slice is all NaN, without a warning),
    by one sort (NaN last): numpy's own takes a masked-array path on small arrays, 0.3 ms a
    call, the cost of a whole live frame's triangulation."""
    s = np.moveaxis(np.sort(a, axis=axis), axis, -1)
    lead, length = s.shape[:-1], s.shape[-1]
    rows = s.reshape(math.prod(lead), length)  # a copy only where the axis was not last
    n = length - np.isnan(rows).sum(axis=-1)  # the numbers come first
    i = np.arange(len(rows))
    # Plain row indexing, not np.take_along_axis (whose index building is most of a small call).
    return ((rows[i, (n - 1) // 2] + rows[i, n // 2]) / 2).reshape(lead)


def human_sized(
    xyz: np.ndarray, valid: np.ndarray, max_spread_m: float = MAX_SPREAD_M
) -> np.ndarray:
    """(...,) bool: the person's triangulated keypoints (..., K, 3) / (..., K) are no larger than
    a body (`skeleton_spread` <= ``max_spread_m``; inf: every person is)."""
    return skeleton_spread(xyz, valid) <= max_spread_m
