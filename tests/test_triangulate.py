"""triangulate.py: exact recovery, OpenCV agreement, masks and degenerate geometry."""

from __future__ import annotations

import itertools
import warnings

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


# --------------------------------------------------------------------------- robust triangulation

ROBUST = (
    lambda rig, px, w: triangulate.triangulate_robust(rig, px, w),
    lambda rig, px, w: triangulate.triangulate_skeletons_robust(rig, px, w),
)


@pytest.mark.parametrize("fn", ROBUST, ids=["per-keypoint", "skeleton"])
def test_robust_equals_dlt_without_outliers(fn):
    rig = random_rig(seed=11, num_cameras=5)
    X = scene_points(rig, 12, (4, 18))
    px = np.asarray(cameras.project_points(rig, jnp.asarray(X)))
    px = px + np.random.default_rng(13).normal(scale=1.5, size=px.shape)  # detector noise
    w = np.random.default_rng(14).uniform(0.3, 1.0, px.shape[:-1]).astype(np.float32)
    w[0, :, :5] = 0.0  # and some unseen keypoints
    dlt, ok = triangulate.triangulate_points(rig, jnp.asarray(px, jnp.float32), jnp.asarray(w))
    xyz, valid, kept = jax.jit(fn)(rig, jnp.asarray(px, jnp.float32), jnp.asarray(w))
    np.testing.assert_array_equal(kept, w > 0)  # nothing dropped ...
    np.testing.assert_array_equal(valid, ok)
    np.testing.assert_allclose(xyz, dlt, atol=1e-6)  # ... so it is the DLT


def test_robust_two_views_is_opencv(preset_rig):
    X = scene_points(preset_rig, 15, (30,))
    px = np.asarray(cameras.project_points(preset_rig, jnp.asarray(X)))
    px = px + np.random.default_rng(16).normal(scale=1.0, size=px.shape)
    w = np.zeros(px.shape[:-1], np.float32)
    w[[0, 1]] = 1.0
    xyz, ok, kept = triangulate.triangulate_robust(
        preset_rig, jnp.asarray(px, jnp.float32), jnp.asarray(w)
    )
    assert bool(ok.all()) and bool(kept[:2].all()) and not bool(kept[2:].any())
    np.testing.assert_allclose(xyz, _cv_two_view(preset_rig, 0, 1, px[0], px[1]), atol=1e-3)
    # Far off: with two views nothing can say which one is wrong, so both stay (plain DLT).
    px[1, :10] += 80.0
    xyz, ok, kept = triangulate.triangulate_robust(
        preset_rig, jnp.asarray(px, jnp.float32), jnp.asarray(w)
    )
    dlt, _ = triangulate.triangulate_points(preset_rig, jnp.asarray(px, jnp.float32), w)
    assert bool(kept[:2].all())
    np.testing.assert_allclose(xyz, dlt, atol=1e-6)


@pytest.mark.parametrize("num_cameras", [4, 5])
def test_robust_rejects_a_wild_view_of_each_point(num_cameras):
    rig = random_rig(seed=17, num_cameras=num_cameras)
    X = scene_points(rig, 18, (60,))
    px = np.asarray(cameras.project_points(rig, jnp.asarray(X)))
    rng = np.random.default_rng(19)
    px = px + rng.normal(scale=1.0, size=px.shape)
    bad = rng.integers(0, num_cameras, len(X))  # each point: one view is a wild point
    wild = rng.uniform([0, 0], [1920, 1080], (len(X), 2))
    # ... far enough to be an outlier (a few land within 40 px of the truth: those are not).
    wild = np.where(
        np.linalg.norm(wild - px[bad, np.arange(len(X))], axis=-1)[:, None] < 150,
        wild + 300.0,
        wild,
    )
    px[bad, np.arange(len(X))] = wild
    w = np.ones(px.shape[:-1], np.float32)
    xyz, ok, kept = triangulate.triangulate_robust(rig, jnp.asarray(px, jnp.float32), w)
    dlt, _ = triangulate.triangulate_points(rig, jnp.asarray(px, jnp.float32), w)
    err = np.linalg.norm(np.asarray(xyz) - X, axis=-1)
    assert bool(ok.all())
    assert np.median(np.linalg.norm(np.asarray(dlt) - X, axis=-1)) > 0.05  # DLT is pulled off
    assert err.max() < 0.01  # within a centimetre of the truth
    expected = np.ones_like(w, bool)
    expected[bad, np.arange(len(X))] = False
    np.testing.assert_array_equal(kept, expected)  # exactly the wild views are dropped


def test_robust_skeleton_rejects_another_persons_view():
    rig = random_rig(seed=20, num_cameras=5)
    X = scene_points(rig, 21, (2, 18))  # two people (random keypoint clouds)
    X[1] = X[0] + np.array([0.6, 0.0, 0.3], np.float32)  # the other stands beside the first
    px = np.asarray(cameras.project_points(rig, jnp.asarray(X)))
    px = px + np.random.default_rng(22).normal(scale=1.0, size=px.shape)
    # Person 0's group holds person 1's skeleton in camera 2 (a wrong match); camera 3 sees
    # only a few of person 0's keypoints, so some keypoints have two views, one of them wrong.
    px[2, 0] = px[2, 1]
    w = np.ones(px.shape[:-1], np.float32)
    w[3, 0, 6:] = 0.0
    w[[0, 1], 0, 12:] = 0.0  # keypoints 12-17: cameras 2 (wrong) and 4 only
    xyz, ok, kept = triangulate.triangulate_skeletons_robust(
        rig, jnp.asarray(px, jnp.float32), jnp.asarray(w)
    )
    kept = np.asarray(kept)
    assert not kept[2, 0].any()  # the wrong view is dropped for the whole person ...
    assert kept[:, 1].all()  # ... and nothing of the other person
    err = np.linalg.norm(np.asarray(xyz) - X, axis=-1)
    assert err[0, :12].max() < 0.01 and err[1].max() < 0.01
    # Keypoints left with one view are invalid, not another person's point.
    assert not np.asarray(ok)[0, 12:].any()
    # The per-keypoint stage alone cannot tell which of two views is wrong.
    only_kp, ok_kp, _ = triangulate.triangulate_robust(
        rig, jnp.asarray(px, jnp.float32), jnp.asarray(w)
    )
    assert (
        bool(ok_kp[0, 12:].all())
        and np.linalg.norm(only_kp[0, 12:] - X[0, 12:], axis=-1).min() > 0.05
    )


def test_robust_never_below_two_views_and_respects_masks():
    rig = random_rig(seed=23, num_cameras=5)
    X = scene_points(rig, 24, (40,))
    rng = np.random.default_rng(25)
    # Every view is garbage: the worst error always exceeds any threshold.
    px = rng.uniform([0, 0], [1920, 1080], (5, len(X), 2)).astype(np.float32)
    w = (rng.random((5, len(X))) < 0.7).astype(np.float32)
    px[w == 0] = np.nan  # junk where unseen must not leak
    xyz, ok, kept = triangulate.triangulate_robust(rig, jnp.asarray(px), jnp.asarray(w))
    kept, seen = np.asarray(kept), w > 0
    assert not (kept & ~seen).any()  # a masked view is never used
    n = seen.sum(0)
    np.testing.assert_array_equal(kept.sum(0), np.minimum(n, 2) * (n >= 2) + (n < 2) * n)
    assert np.isfinite(np.asarray(xyz)).all()
    xyz, ok, kept = triangulate.triangulate_skeletons_robust(
        rig, jnp.asarray(px.reshape(5, 4, 10, 2)), jnp.asarray(w.reshape(5, 4, 10))
    )
    # Whole views are dropped per person, never below two of the person's views (a keypoint
    # may then keep one view: it is invalid, not another person's point).
    kept = np.asarray(kept)
    assert not (kept.reshape(5, -1) & ~seen).any()
    person_views = seen.reshape(5, 4, 10).any(-1).sum(0)
    np.testing.assert_array_equal(kept.any(-1).sum(0), np.minimum(person_views, 2))
    assert np.isfinite(np.asarray(xyz)).all()


def test_robust_thresholds_do_not_recompile(ring_rig):
    X = scene_points(ring_rig, 26, (3, 18))
    px = cameras.project_points(ring_rig, jnp.asarray(X))
    w = jnp.ones(px.shape[:-1])
    fn = triangulate.triangulate_skeletons_robust
    fn(ring_rig, px, w, outlier_px=10.0, view_outlier_px=20.0)
    before = fn._cache_size()
    fn(ring_rig, px, w, outlier_px=25.0, view_outlier_px=jnp.inf)
    assert fn._cache_size() == before


# --------------------------------------------------------------------------- blend with a model


def _blend(rig, px, w, model):
    px, w = jnp.asarray(px, jnp.float32), jnp.asarray(w, jnp.float32)
    tri, ok, kept = triangulate.triangulate_skeletons_robust(rig, px, w)
    xyz, from_tri = triangulate.blend_skeletons(
        rig, px, w, model_xyz=jnp.asarray(model), tri_xyz=tri, tri_valid=ok, kept=kept
    )
    return np.asarray(xyz), np.asarray(from_tri), np.asarray(ok)


def _pinhole_error(rig, X, px):
    """Independent reference: distance between the undistorted detection (OpenCV) and the pinhole
    projection of X, in pixels, per camera. X: (N, 3); px: (C, N, 2)."""
    out = []
    for c in range(rig.num_cameras):
        K, D = np.asarray(rig.K[c], np.float64), np.asarray(rig.dist[c], np.float64)
        und = cv2.undistortPoints(px[c][:, None].astype(np.float64), K, D, P=K)[:, 0]
        cam = X.astype(np.float64) @ np.asarray(rig.R[c], np.float64).T + np.asarray(rig.t[c])
        proj = (cam @ K.T)[:, :2] / (cam @ K.T)[:, 2:]
        out.append(np.linalg.norm(proj - und, axis=-1))
    return np.stack(out)


def test_reprojection_errors_match_opencv(ring_rig):
    X = scene_points(ring_rig, 30, (12,))
    px = np.asarray(cameras.project_points(ring_rig, jnp.asarray(X)))
    px = px + np.random.default_rng(31).normal(scale=5.0, size=px.shape)
    ours = np.asarray(triangulate.reprojection_errors_px(ring_rig, jnp.asarray(X), jnp.asarray(px)))
    np.testing.assert_allclose(ours, _pinhole_error(ring_rig, X, px), atol=0.05)
    # A point behind a camera has no reprojection there.
    behind = np.asarray(cameras.camera_centres(ring_rig))[0] - 2.0 * np.asarray(ring_rig.R)[0, 2]
    err = triangulate.reprojection_errors_px(ring_rig, jnp.asarray(behind), jnp.asarray(px[:, 0]))
    assert np.isinf(np.asarray(err)[0])


def test_blend_takes_triangulation_where_it_exists():
    """A model far off on keypoints two or more views see: exact triangulation wins there; the
    same model off by a constant on every keypoint is moved back by the person's offset where
    only the model answers."""
    rig = random_rig(seed=32, num_cameras=4)
    X = scene_points(rig, 33, (3, 18))  # three people
    px = np.asarray(cameras.project_points(rig, jnp.asarray(X)))
    w = np.ones(px.shape[:-1], np.float32)
    w[:, :, 17] = 0.0  # keypoint 17 nobody sees
    model = X.copy()
    model[0, :8] += np.array([0.5, -0.3, 0.2], np.float32)  # person 0: far off on 8 keypoints
    model[1] += np.array([0.0, 0.6, 0.0], np.float32)  # person 1: a constant (a floor off)
    xyz, from_tri, ok = _blend(rig, px, w, model)
    assert from_tri[:, :17].all() and not from_tri[:, 17].any()
    np.testing.assert_allclose(xyz[:, :17], X[:, :17], atol=1e-3)  # triangulation, not the model
    # Keypoint 17: person 1's model moved back by its offset; person 2's model untouched;
    # person 0's offset is the median over its keypoints (most agree with the model): zero.
    np.testing.assert_allclose(xyz[1, 17], X[1, 17], atol=1e-3)
    np.testing.assert_allclose(xyz[2, 17], X[2, 17], atol=1e-3)
    np.testing.assert_allclose(xyz[0, 17], model[0, 17], atol=1e-3)


def test_blend_rejects_an_outlier_view_and_snaps_a_one_view_keypoint_to_its_ray():
    rig = random_rig(seed=34, num_cameras=5)
    X = scene_points(rig, 35, (1, 18))
    px = np.array(cameras.project_points(rig, jnp.asarray(X)))
    w = np.ones(px.shape[:-1], np.float32)
    px[3, 0, 4] += np.array([150.0, -120.0], np.float32)  # a wild view of keypoint 4
    w[1:, 0, 9] = 0.0  # keypoint 9: camera 0 only
    w[:, 0, 10] = 0.0  # keypoint 10: camera 2 only (the rest of the view is fine)
    w[2, 0, 10] = 1.0
    model = X + np.random.default_rng(36).normal(scale=0.08, size=X.shape).astype(np.float32)
    xyz, from_tri, _ = _blend(rig, px, w, model)
    # The wild view is rejected: keypoint 4 is exact, not the DLT pulled off nor the model.
    np.testing.assert_allclose(xyz[0, 4], X[0, 4], atol=1e-3)
    dlt, _ = triangulate.triangulate_points(rig, jnp.asarray(px), jnp.asarray(w))
    assert np.linalg.norm(np.asarray(dlt)[0, 4] - X[0, 4]) > 0.02
    # One view: the closest point of that view's ray to the (offset-corrected) model point.
    for k, c in ((9, 0), (10, 2)):
        assert not from_tri[0, k]
        tri_ok = np.ones(18, bool)
        tri_ok[[9, 10]] = False
        offset = np.median(X[0, tri_ok] - model[0, tri_ok], axis=0)
        moved = model[0, k] + offset
        o = np.asarray(cameras.camera_centres(rig))[c]
        r = (X[0, k] - o) / np.linalg.norm(X[0, k] - o)  # the ray through the exact detection
        expected = o + r * np.dot(moved - o, r)
        np.testing.assert_allclose(xyz[0, k], expected, atol=2e-3)
        err = triangulate.reprojection_errors_px(
            rig, jnp.asarray(xyz[0, k]), jnp.asarray(px[:, 0, k])
        )
        assert float(np.asarray(err)[c]) < 0.1  # it projects onto its detection


@pytest.mark.parametrize("batch", [(), (2,), (2, 3)])
def test_blend_shapes_masks_and_padding(ring_rig, batch):
    K = 6
    X = scene_points(ring_rig, 37, batch + (K,))
    px = np.array(cameras.project_points(ring_rig, jnp.asarray(X)))
    rng = np.random.default_rng(38)
    w = (rng.random(px.shape[:-1]) < 0.6).astype(np.float32)
    px[w == 0] = np.nan  # junk where unseen must not leak
    if batch:  # a padding person: nothing seen, the model's output comes back as it is
        w[:, 0] = 0.0
    model = (X + 0.05).astype(np.float32)
    xyz, from_tri, ok = _blend(ring_rig, px, w, model)
    assert xyz.shape == batch + (K, 3) and from_tri.shape == batch + (K,)
    assert np.isfinite(xyz).all()
    np.testing.assert_array_equal(from_tri, ok)
    if batch:
        np.testing.assert_allclose(xyz[0], model[0], atol=1e-6)


def _lower_on_ray_by_search(origin, ray, parent, length, up):
    """Brute-force reference for `hang_on_ray`: depths in front of the camera, on a fine grid."""
    t = np.linspace(1e-3, 20.0, 2_000_001)
    pts = origin + t[:, None] * ray
    d = np.linalg.norm(pts - parent, axis=-1)
    hits = np.abs(d - length) < 2e-5
    if not hits.any():  # the ray passes farther than the length: its closest point
        return pts[np.argmin(d)]
    return pts[hits][np.argmin(pts[hits] @ up)]


@pytest.mark.parametrize(
    "climb, offset, length",
    [(-0.7, 0.2, 0.5), (0.4, 0.2, 0.5), (-0.7, 0.2, 0.1), (0.4, 0.05, 3.5)],
)
def test_hang_on_ray_is_the_lower_point_at_the_length(climb, offset, length):
    """Descending and climbing rays, a ray that passes too far, a near point behind the camera."""
    up = np.array([0.0, 0.0, 1.0])
    origin = np.array([0.3, -0.2, 2.5])
    ray = np.array([1.0, 0.2, climb])
    ray /= np.linalg.norm(ray)
    side = np.cross(ray, up)
    side /= np.linalg.norm(side)
    parent = origin + 3.0 * ray + offset * side
    got = np.asarray(
        triangulate.hang_on_ray(
            *(jnp.asarray(a, jnp.float32) for a in (origin, ray, parent, length, up))
        )
    )
    want = _lower_on_ray_by_search(origin, ray, parent, length, up)
    np.testing.assert_allclose(got, want, atol=1e-3)
    assert np.dot(got - origin, ray) > 0


def _legs_person(rig, seed):
    """A person whose hips, knees and ankles (coco18) hang below each other, the world's up
    being the rig's (-y); other keypoints around them."""
    X = scene_points(rig, seed, (18,))
    down = np.array([0.0, 1.0, 0.0], np.float32)
    hip = X.mean(axis=0)
    for side, dx, lean in ((11, 0.12, 0.08), (12, -0.12, -0.08)):  # l_hip, r_hip: one length
        X[side] = hip + np.array([dx, 0.0, 0.0], np.float32)
        X[side + 2] = X[side] + 0.45 * down + np.array([0.0, 0.0, lean], np.float32)  # knee
        X[side + 4] = X[side + 2] + 0.42 * down - np.array([0.0, 0.0, lean], np.float32)  # ankle
    return X


def test_blend_hangs_one_view_knees_and_ankles_at_their_bone_length():
    """A knee or ankle one view sees, the model's depth off along the ray (a wrong floor): it is
    put back where the ray meets the other leg's bone length below its parent; without the leg
    chains, it stays at the model's depth."""
    from mvpose_jax.skeletons import leg_chains

    rig = random_rig(seed=40, num_cameras=5)
    X = np.stack([_legs_person(rig, 41), _legs_person(rig, 42)])
    px = np.array(cameras.project_points(rig, jnp.asarray(X)))
    w = np.ones(px.shape[:-1], np.float32)
    w[1:, 0, 15] = 0.0  # person 0: left ankle in camera 0 only
    w[[0, 2, 3, 4], 1, 14] = 0.0  # person 1: right knee and ankle in camera 1 only
    w[[0, 2, 3, 4], 1, 16] = 0.0
    centres = np.asarray(cameras.camera_centres(rig))
    model = X.copy()
    for n, k, c in ((0, 15, 0), (1, 14, 1), (1, 16, 1)):
        ray = (X[n, k] - centres[c]) / np.linalg.norm(X[n, k] - centres[c])
        model[n, k] += 0.5 * ray  # on the ray, 0.5 m too deep
    up = np.array([0.0, -1.0, 0.0], np.float32)
    for n, k, c, parent in ((0, 15, 0, 13), (1, 14, 1, 12), (1, 16, 1, 14)):
        # The set-up's truth is the lower of the ray's two points at the bone length.
        ray = (X[n, k] - centres[c]) / np.linalg.norm(X[n, k] - centres[c])
        length = np.linalg.norm(X[n, k] - X[n, parent])
        want = _lower_on_ray_by_search(centres[c], ray, X[n, parent], length, up)
        np.testing.assert_allclose(want, X[n, k], atol=1e-3)
    pxj, wj = jnp.asarray(px, jnp.float32), jnp.asarray(w, jnp.float32)
    tri, ok, kept = triangulate.triangulate_skeletons_robust(rig, pxj, wj)
    kw = dict(model_xyz=jnp.asarray(model), tri_xyz=tri, tri_valid=ok, kept=kept)
    hung, from_tri = triangulate.blend_skeletons(
        rig, pxj, wj, **kw, legs=jnp.asarray(leg_chains("coco18")), up=jnp.asarray(up)
    )
    plain, _ = triangulate.blend_skeletons(rig, pxj, wj, **kw)
    hung, plain = np.asarray(hung), np.asarray(plain)
    for n, k in ((0, 15), (1, 14), (1, 16)):
        assert not np.asarray(from_tri)[n, k]
        np.testing.assert_allclose(hung[n, k], X[n, k], atol=2e-3)
        np.testing.assert_allclose(plain[n, k], model[n, k], atol=2e-3)
    # Every other keypoint is the plain blend's.
    other = np.ones((2, 18), bool)
    other[0, 15] = other[1, 14] = other[1, 16] = False
    np.testing.assert_allclose(hung[other], plain[other], atol=1e-6)
    # A layout without legs changes nothing.
    none, _ = triangulate.blend_skeletons(
        rig, pxj, wj, **kw, legs=jnp.zeros((0, 4), jnp.int32), up=jnp.asarray(up)
    )
    np.testing.assert_allclose(np.asarray(none), plain, atol=1e-6)


def test_leg_chains_name_the_layouts_legs_parents_first():
    from mvpose_jax.skeletons import get_layout, leg_chains

    for name in ("coco18", "body25", "halpe26", "openpose_coco18"):
        lay = get_layout(name)
        rows = [[lay.keypoints[i] for i in row] for row in leg_chains(name)]
        assert rows == [
            ["l_hip", "l_knee", "r_hip", "r_knee"],
            ["l_knee", "l_ankle", "r_knee", "r_ankle"],
            ["r_hip", "r_knee", "l_hip", "l_knee"],
            ["r_knee", "r_ankle", "l_knee", "l_ankle"],
        ]
    assert leg_chains("mpii").shape == (4, 4)


def test_skeleton_spread_is_the_median_distance_from_the_median_point():
    xyz = np.zeros((3, 6, 3))
    xyz[0, :5, 0] = [0.0, 1.0, 2.0, 3.0, 10.0]  # median point x = 2: distances 2, 1, 0, 1, 8
    xyz[0, 5] = 1e6  # not valid: junk that must not count
    valid = np.zeros((3, 6), bool)
    valid[0, :5] = True
    valid[1, 2] = True  # one keypoint: nothing to judge
    xyz[2] = np.random.default_rng(3).normal(scale=0.3, size=(6, 3))
    valid[2] = True
    spread = triangulate.skeleton_spread(xyz, valid)
    centre = np.median(xyz[2], axis=0)
    np.testing.assert_allclose(
        spread, [1.0, 0.0, np.median(np.linalg.norm(xyz[2] - centre, axis=-1))]
    )
    # The spread scales with the skeleton and ignores where it stands.
    np.testing.assert_allclose(
        triangulate.skeleton_spread(4.0 * xyz[2] + 7.0, valid[2]), 4.0 * spread[2]
    )
    assert triangulate.human_sized(xyz, valid, 0.99).tolist() == [False, True, True]
    assert triangulate.human_sized(xyz, valid, np.inf).all()


def test_skeleton_spread_is_numpys_nanmedians_bit_for_bit():
    """The compiled spread against its definition in numpy (np.nanmedian; a NaN coordinate of a
    valid keypoint is no sample), on random people with ties, NaNs and few valid keypoints."""
    rng = np.random.default_rng(31)
    xyz = rng.normal(size=(400, 3, 12, 3))
    xyz[::3] = np.round(xyz[::3], 1)  # ties
    xyz[rng.random(xyz.shape) < 0.03] = np.nan
    valid = rng.random((400, 3, 12)) < rng.random((400, 3, 1))
    xyz[0, 0, :, 0], valid[0, 0, :2] = np.nan, True  # valid keypoints without an x: NaN
    got = triangulate.skeleton_spread(xyz, valid)
    want = np.zeros(valid.shape[:-1])
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices
        for idx in np.ndindex(valid.shape[:-1]):
            if valid[idx].sum() >= 2:
                pts = np.where(valid[idx][:, None], xyz[idx], np.nan)
                d = pts - np.nanmedian(pts, axis=0)
                want[idx] = np.nanmedian(np.sqrt((d * d).sum(-1)))
    np.testing.assert_array_equal(got, want)
    assert np.isnan(got).any() and (got == 0).any()  # both edge cases were drawn


@pytest.mark.parametrize("axis", [-1, -2])
def test_nanmedian_by_rank_is_jnp_nanmedian_bit_for_bit(axis):
    rng = np.random.default_rng(30)
    a = rng.normal(size=(7, 5, 18, 6)).astype(np.float32)
    a[rng.random(a.shape) < 0.3] = np.nan
    a[..., 3, :] = a[..., 5, :]  # ties
    a[0, 0] = np.nan  # slices with no number
    a[1, 1, :2] = np.inf
    a[1, 2, :3] = -np.inf
    ours = np.asarray(jax.jit(triangulate.nanmedian_by_rank, static_argnums=1)(a, axis))
    ref = np.asarray(jnp.nanmedian(a, axis=axis))
    np.testing.assert_array_equal(ours, ref)  # NaN where jnp gives NaN, equal elsewhere


@pytest.mark.parametrize("axis", [-1, -2, 1])
def test_nanmedian_along_is_numpys(axis):
    rng = np.random.default_rng(31)
    a = rng.normal(size=(6, 9, 3))
    a[rng.random(a.shape) < 0.4] = np.nan
    a[0, :, :] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy warns on all-NaN slices
        ref = np.nanmedian(a, axis=axis)
    np.testing.assert_array_equal(triangulate.nanmedian_along(a, axis), ref)


def _wild_scene(num_points: int, wild_fraction: float, seed: int):
    rig = random_rig(seed=seed, num_cameras=5)
    X = scene_points(rig, seed + 1, (num_points // 18, 18))
    px = np.asarray(cameras.project_points(rig, jnp.asarray(X)))
    rng = np.random.default_rng(seed + 2)
    px = px + rng.normal(scale=1.0, size=px.shape)
    wild = rng.random(px.shape[:-1]) < wild_fraction / 5
    px = np.where(wild[..., None], px + rng.choice([-1.0, 1.0], px.shape) * 200.0, px)
    w = (rng.random(px.shape[:-1]) > 0.1).astype(np.float32)
    return rig, jnp.asarray(px, jnp.float32), jnp.asarray(w)


@pytest.mark.parametrize("wild_fraction", [0.02, 0.15, 0.8])
def test_robust_on_the_needed_rows_alone_equals_every_row(monkeypatch, wild_fraction):
    # The needed rows fill one block (0.02), several (0.15), or most of the batch (0.8).
    rig, px, w = _wild_scene(36 * 18, wild_fraction, seed=32)
    gathered = [np.asarray(a) for a in triangulate.triangulate_skeletons_robust(rig, px, w)]
    monkeypatch.setattr(triangulate, "_MIN_ROWS_TO_COMPACT", 10**9)
    jax.clear_caches()  # the jitted function must be traced again without the gathers
    whole = [np.asarray(a) for a in triangulate.triangulate_skeletons_robust(rig, px, w)]
    jax.clear_caches()
    np.testing.assert_array_equal(gathered[1], whole[1])
    np.testing.assert_array_equal(gathered[2], whole[2])
    np.testing.assert_allclose(gathered[0], whole[0], atol=1e-6, rtol=0)
    assert not np.asarray(whole[2]).all()  # some views were dropped
