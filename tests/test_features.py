"""features.py: the 10/14-number features, view masks, and grouping people."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from mvpose_jax import cameras, features, triangulate
from tests.helpers import random_rig, scene_points


def _people(rig, n, seed=0):
    rng = np.random.default_rng(seed)
    X = scene_points(rig, seed, (n, 18))
    xy = np.moveaxis(np.asarray(cameras.project_points(rig, jnp.asarray(X, jnp.float32))), 0, 1)
    score = rng.uniform(0.3, 1.0, size=xy.shape[:-1]).astype(np.float32)
    score[rng.uniform(size=score.shape) < 0.2] = 0.0
    return X, xy.astype(np.float32), score


def test_keypoint_features_layout(ring_rig):
    _, xy, score = _people(ring_rig, 3)
    f = np.asarray(
        features.keypoint_features(ring_rig, jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0))
    )
    f = np.moveaxis(f, 0, 1)  # (N, C, K, 10)
    seen = score > 0
    assert np.all(f[~seen] == 0)  # a missing keypoint is all zeros
    np.testing.assert_array_equal(f[..., 0], seen)
    wh = np.asarray(ring_rig.size)[None, :, None, :]
    np.testing.assert_allclose(f[..., 1:3][seen], (2 * xy / wh - 1)[seen], atol=1e-6)
    np.testing.assert_allclose(f[..., 3][seen], score[seen])
    centre, radius = cameras.rig_centre_and_radius(ring_rig)
    cams = (np.asarray(cameras.camera_centres(ring_rig)) - np.asarray(centre)) / float(radius)
    np.testing.assert_allclose(
        f[..., 4:7], np.where(seen[..., None], cams[None, :, None], 0), atol=1e-6
    )
    rays = np.moveaxis(np.asarray(cameras.pixel_rays(ring_rig, jnp.moveaxis(xy, 1, 0))), 0, 1)
    np.testing.assert_allclose(f[..., 7:10][seen], rays[seen], atol=1e-6)


def test_features_of_a_person_do_not_depend_on_the_others(ring_rig):
    _, xy, score = _people(ring_rig, 6, seed=1)
    order = np.array([3, 0, 5, 1, 4, 2])
    a = features.estimator_inputs(ring_rig, jnp.asarray(xy), jnp.asarray(score))
    b = features.estimator_inputs(ring_rig, jnp.asarray(xy[order]), jnp.asarray(score[order]))
    mask = jnp.asarray((score > 0).any(-1))
    fa = np.asarray(features.assemble_features(a, mask))
    fb = np.asarray(features.assemble_features(b, mask[order]))
    np.testing.assert_allclose(fb, fa[order], atol=1e-6)
    # A person alone gives the same features as in a crowd.
    alone = features.estimator_inputs(ring_rig, jnp.asarray(xy[2:3]), jnp.asarray(score[2:3]))
    np.testing.assert_allclose(features.assemble_features(alone, mask[2:3])[0], fa[2], atol=1e-6)


def test_initial_estimate_uses_only_the_kept_views(ring_rig):
    X, xy, score = _people(ring_rig, 4, seed=2)
    inputs = features.estimator_inputs(ring_rig, jnp.asarray(xy), jnp.asarray(score))
    keep = np.array([[1, 1, 0, 1], [1, 0, 0, 1], [0, 1, 1, 1], [1, 0, 0, 0]], bool)
    f = np.asarray(features.assemble_features(inputs, jnp.asarray(keep)))
    centre, radius = cameras.rig_centre_and_radius(ring_rig)
    for n in range(4):
        kept = np.flatnonzero(keep[n])
        sub = ring_rig.select(list(kept))
        ref, ok = triangulate.triangulate_pairwise_centroid(
            sub, jnp.asarray(xy[n, kept]), jnp.asarray(score[n, kept])
        )
        ref = (np.asarray(ref) - np.asarray(centre)) / float(radius)
        for c in range(4):
            slot = f[n, c]
            if not keep[n, c]:
                assert np.all(slot == 0)  # a slot with no view is all zeros
                continue
            np.testing.assert_array_equal(slot[:, 10], np.asarray(ok))
            np.testing.assert_allclose(
                slot[:, 11:14][np.asarray(ok)], ref[np.asarray(ok)], atol=1e-5
            )
    assert not f[3, :, :, 10].any()  # one view: no triangulation


def test_main_skeletons_picks_the_fullest():
    score = np.zeros((2, 3, 4, 5), np.float32)
    xy = np.random.default_rng(0).uniform(size=(2, 3, 4, 5, 2)).astype(np.float32)
    score[0, 0, 1, :4] = 0.9  # 4 keypoints: the person
    score[0, 0, 2, :2] = 0.9  # 2 keypoints: a false detection
    score[1, 2, 3, :] = 0.5
    mxy, msc = features.main_skeletons(xy, score)
    np.testing.assert_array_equal(msc[0, 0], score[0, 0, 1])
    np.testing.assert_array_equal(mxy[1, 2], xy[1, 2, 3])
    assert not msc[0, 1].any()  # no skeleton in that view


def test_people_from_identity_groups_views():
    rng = np.random.default_rng(1)
    xy = rng.uniform(size=(1, 2, 3, 4, 2)).astype(np.float32)
    score = np.ones((1, 2, 3, 4), np.float32)
    identity = np.array([[[1, -1, 0], [0, 1, -1]]])
    pxy, psc = features.people_from_identity(xy, score, identity, 2)
    np.testing.assert_array_equal(pxy[0, 1, 0], xy[0, 0, 0])
    np.testing.assert_array_equal(pxy[0, 0, 0], xy[0, 0, 2])
    np.testing.assert_array_equal(pxy[0, 1, 1], xy[0, 1, 1])
    assert psc.shape == (1, 2, 2, 4) and psc.all()


def test_random_rig_features_are_finite_with_junk_in_missing_slots():
    rig = random_rig(seed=4, num_cameras=3)
    _, xy, score = _people(rig, 5, seed=3)
    xy[score == 0] = np.nan  # detectors may leave anything where a keypoint is missing
    inputs = features.estimator_inputs(rig, jnp.asarray(xy), jnp.asarray(score))
    f = features.assemble_features(inputs, jnp.asarray((score > 0).any(-1)))
    assert np.all(np.isfinite(np.asarray(f)))
