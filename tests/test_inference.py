"""inference.py: match tables (learned and epipolar), composed dev frames, the graph caches and
compilation budget, and the pipeline (run_pipeline / stream_pipeline) end to end with its
numerical safety."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from flax import nnx

from mvpose_jax.cameras import make_rig
from mvpose_jax.compiled import bound_model_fn
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.errors import InputError
from mvpose_jax.estimator_training import train_estimator
from mvpose_jax.features import single_person_samples
from mvpose_jax.graphs import (
    build_graphs,
    detection_features,
    match_table,
)
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import members_from_identity, poses_of_members
from mvpose_jax.matcher_training import train_matcher
from mvpose_jax.matching import (
    _match_scores,
    _match_scores_fn,
    frame_chunks,
    gat_match_table,
    geometric_match_table,
    match_scores,
)
from mvpose_jax.metrics import matching_scores, pose_metrics
from mvpose_jax.models import GATConfig, MatchingGAT, MLPConfig
from mvpose_jax.proposals import propose_people
from mvpose_jax.skeletons import Detections
from mvpose_jax.synthetic import generate_recording, generate_single_person_recordings
from mvpose_jax.tracking import TrackingConfig
from mvpose_jax.trained import EstimatorConfig, MatcherConfig, TrainConfig
from mvpose_jax.triangulate import skeleton_spread
from tests.helpers import TINY_GAT as TINY
from tests.helpers import random_frames, untrained_estimator
from tests.helpers import tiny_matcher_train_state as _train_state


@pytest.fixture(scope="module")
def scene():
    rig = load_rig("panoptic5")
    return rig, generate_recording(rig, num_people=3, num_frames=8, seed=5)


@pytest.fixture(scope="module")
def models():
    """A matcher and an estimator trained for a few steps (the test is about plumbing, not skill)."""
    rig = load_rig("panoptic5")
    recs = generate_single_person_recordings(rig, num_recordings=4, num_frames=20, seed=7)
    train = dataclasses.replace(
        TrainConfig(), learning_rate=1e-3, batch_size=8, max_steps=4, eval_every=1
    )
    matcher, _ = train_matcher(
        rig,
        recs[:3],
        recs[3:],
        MatcherConfig(gat=GATConfig.quick(), train=train, samples_per_epoch=16, num_dev_samples=8),
        progress=False,
    )
    xy, score = single_person_samples(recs)
    config = EstimatorConfig(
        mlp=MLPConfig(widths=(32,), output="residual"),
        train=TrainConfig(batch_size=16, max_steps=4, learning_rate=1e-3),
    )
    estimator, _ = train_estimator(
        rig, xy[:60], score[:60], xy[60:], score[60:], config, progress=False
    )
    return matcher, estimator


def _consistent(res, count):
    """members and identity describe the same groups; at most one skeleton per camera per person."""
    F, G, C = res.members.shape
    for f in range(F):
        for g in range(G):
            for c in range(C):
                p = res.members[f, g, c]
                if p >= 0:
                    assert p < count[f, c]
                    assert res.identity[f, c, p] == g
    f, c, p = np.nonzero(res.identity >= 0)
    assert (res.members[f, res.identity[f, c, p], c] == p).all()
    # A person exists exactly when it has members.
    np.testing.assert_array_equal(res.poses.valid, (res.members >= 0).any(-1))


@pytest.mark.slow  # uses the trained `models`
def test_pipeline_with_trained_estimator_gives_one_pose_per_person(scene, models):
    rig, rec = scene
    _, estimator = models
    res = run_pipeline(rig, rec.detections, estimator=estimator)
    F, C, P, K = np.shape(rec.detections.score)
    G = res.poses.valid.shape[1]
    assert res.poses.xyz.shape == (F, G, K, 3) and res.confidence.shape == (F, G)
    assert res.members.shape == (F, G, C) and res.identity.shape == (F, C, P)
    # One pose per true person seen in 2+ views, every keypoint produced, near the truth.
    ident = np.asarray(rec.identity)
    seen_in = np.stack(
        [(ident == g).any(-1).sum(-1) for g in range(rec.ground_truth.valid.shape[1])], -1
    )
    np.testing.assert_array_equal(res.poses.valid.sum(-1), (seen_in >= 2).sum(-1))
    assert res.poses.keypoint_valid[res.poses.valid].all()
    assert np.isfinite(res.poses.xyz).all()
    # 4 training steps: the residual MLP is still close to its anchor (triangulation with a
    # ray fallback for unseen keypoints), so only "near": skill is tested in test_estimator.
    assert pose_metrics(res.poses, rec.ground_truth)["mpjpe_mm"] < 200
    assert matching_scores(ident, res.identity, np.asarray(rec.detections.count))["ari"] > 0.95
    _consistent(res, np.asarray(rec.detections.count))


@pytest.mark.slow  # uses the trained `models`
def test_pipeline_with_learned_matcher_has_consistent_groups(scene, models):
    rig, rec = scene
    matcher, estimator = models
    res = run_pipeline(rig, rec.detections, matcher=matcher, estimator=estimator, threshold=0.0)
    _consistent(res, np.asarray(rec.detections.count))
    assert res.cameras == rig.names
    assert np.isfinite(res.poses.xyz).all()
    # threshold 0 joins every allowed pair: nobody is left alone in a frame with two views of people.
    assert res.poses.valid.any()


def test_members_from_identity_inverts_the_pipeline_identity(scene):
    rig, rec = scene
    res = run_pipeline(rig, rec.detections, threshold=0.5)
    G = res.members.shape[1]
    np.testing.assert_array_equal(members_from_identity(res.identity, G), res.members)
    # Hand-made: frame 0, person 1 is skeleton 2 of camera 0 and skeleton 0 of camera 1.
    identity = np.array([[[-1, -1, 1], [1, -1, -1]]])
    np.testing.assert_array_equal(members_from_identity(identity, 2), [[[-1, -1], [2, 0]]])


def test_chunks_give_the_same_result_as_one_batch(scene):
    rig, rec = scene
    whole = run_pipeline(rig, rec.detections, chunk_frames=256)
    chunked = run_pipeline(rig, rec.detections, chunk_frames=3)
    G = whole.poses.valid.shape[1]
    assert chunked.poses.valid.shape[1] == G
    for a, b in zip(whole.poses, chunked.poses, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_array_equal(whole.members, chunked.members)
    np.testing.assert_array_equal(whole.identity, chunked.identity)


@pytest.mark.slow  # the learned default's stages, compiled at two skeleton-slot counts
def test_padded_skeleton_slots_change_no_result(scene, monkeypatch):
    """The pipeline pads each camera's skeleton slots (`skeleton_slots`) so that recordings of
    different sizes share compiled programs: the learned default (combined + blend, tracked)
    gives bit-identical results with and without it, and identity keeps the input's slots."""
    from mvpose_jax import inference

    rig, rec = scene
    det = rec.detections
    extra = 5 - np.shape(det.score)[2]  # 5 slots: padded to 8
    assert extra > 0
    pad = [(0, 0), (0, 0), (0, extra), (0, 0)]
    det5 = Detections(np.pad(det.xy, pad + [(0, 0)]), np.pad(det.score, pad), det.count)
    kw = dict(
        matcher=_untrained_matcher(rig),
        estimator=untrained_estimator(rig),
        method="blend",
        tracking=TrackingConfig(),
    )
    assert np.shape(inference._padded_skeletons(det5).score)[2] == 8
    padded = run_pipeline(rig, det5, **kw)
    monkeypatch.setattr(inference, "_padded_skeletons", lambda d: d)
    as_given = run_pipeline(rig, det5, **kw)
    unpadded = run_pipeline(rig, det, **kw)
    assert padded.identity.shape == as_given.identity.shape == np.shape(det5.score)[:3]
    for a, b in zip(padded, as_given, strict=True):
        if isinstance(a, tuple):
            for u, v in zip(a, b, strict=True):
                np.testing.assert_array_equal(u, v)
        elif isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(padded.members, unpadded.members)
    np.testing.assert_array_equal(padded.identity[..., : np.shape(det.score)[2]], unpadded.identity)
    assert (padded.identity[..., np.shape(det.score)[2] :] == -1).all()


def test_stream_pipeline_takes_chunks_from_a_reader(scene, tmp_path):
    """Chunks handed in one at a time (here from a recording read in ranges, whose person axis
    is the most people in that range, not the file's) give the whole recording's results, and
    each chunk's cameras are checked as they arrive."""
    from mvpose_jax.data import open_recording, save_recording
    from mvpose_jax.inference import concat_results, stream_pipeline
    from mvpose_jax.skeletons import Detections

    rig, rec = scene
    whole = run_pipeline(rig, rec.detections, chunk_frames=3)
    save_recording(rec, tmp_path / "scene.npz")
    names = list(rig.names)  # cameras selected: each range's P is its own
    with open_recording(tmp_path / "scene.npz", cameras=names) as stream:
        chunks = ((s, r.detections) for s, r in stream.chunks(3))
        parts = list(stream_pipeline(rig.select(names), chunks, num_frames=stream.num_frames))
    assert [s for s, _ in parts] == list(range(0, rec.num_frames, 3))
    joined = concat_results([r for _, r in parts])
    assert joined.cameras == tuple(names)
    for a, b in zip(whole.poses, joined.poses, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(whole.members, joined.members)
    np.testing.assert_array_equal(whole.identity, joined.identity)
    assert len({r.identity.shape[2] for _, r in parts}) > 1  # the ranges' P differ
    det = rec.detections
    two = Detections(det.xy[:2, :2], det.score[:2, :2], det.count[:2, :2])
    with pytest.raises(InputError, match="detections have 2 cameras, the rig 5"):
        list(stream_pipeline(rig, iter([(0, two)])))


def test_triangulation_on_the_pipeline_groups_matches_direct_call(scene):
    rig, rec = scene
    res = run_pipeline(rig, rec.detections, method="centroid")
    poses, _ = poses_of_members(rig, rec.detections, res.members, method="centroid")
    np.testing.assert_allclose(poses.xyz, res.poses.xyz, atol=1e-6)


def test_robust_triangulation_survives_a_wrong_skeleton_in_a_group(scene):
    rig, rec = scene
    ident = np.asarray(rec.identity)
    members = members_from_identity(ident, 3)  # the true groups ...
    gt = rec.ground_truth
    clean = {
        m: pose_metrics(poses_of_members(rig, rec.detections, members, method=m)[0], gt)
        for m in ("dlt", "robust")
    }
    # ... then person 0's group holds person 1's skeleton in one of its views, every frame.
    wrong = members.copy()
    for f in range(len(members)):
        cams = np.nonzero((members[f, 0] >= 0) & (members[f, 1] >= 0))[0]
        if (members[f, 0] >= 0).sum() >= 3 and len(cams):
            wrong[f, 0, cams[0]] = members[f, 1, cams[0]]
    assert (wrong != members).any()
    bad = {
        m: pose_metrics(poses_of_members(rig, rec.detections, wrong, method=m)[0], gt)
        for m in ("dlt", "robust")
    }
    assert bad["dlt"]["mpjpe_mm"] > clean["dlt"]["mpjpe_mm"] + 20  # DLT is pulled off ...
    assert bad["robust"]["mpjpe_mm"] < clean["dlt"]["mpjpe_mm"] + 5  # ... robust barely moves
    assert clean["robust"]["mpjpe_mm"] <= clean["dlt"]["mpjpe_mm"] + 0.5
    res = run_pipeline(rig, rec.detections, method="robust")
    poses, _ = poses_of_members(rig, rec.detections, res.members, method="robust")
    np.testing.assert_allclose(poses.xyz, res.poses.xyz, atol=1e-6)
    with pytest.raises(ValueError, match="robust"):
        run_pipeline(rig, rec.detections, method="median")


def _person_and_ghost(rig, rec, depth_factor):
    """One frame: person 0 of the scene seen by cameras 0-2, and a two-view "ghost" group
    (camera 0's view of the person, camera 3's of the person pushed ``depth_factor`` times
    farther along camera 0's rays): a pair of views that agrees with one large, far skeleton.
    Returns (detections, members, the person (K, 3))."""
    from mvpose_jax.cameras import camera_centres, point_depths, project_points

    X = np.asarray(rec.ground_truth.xyz[0, 0], np.float32)  # (K, 3)
    c0 = np.asarray(camera_centres(rig))[0]
    far = (c0 + depth_factor * (X - c0)).astype(np.float32)
    assert (np.asarray(point_depths(rig, far))[3] > 0).all()  # in front of camera 3
    px = np.asarray(project_points(rig, np.stack([X, far])))  # (C, 2, K, 2)
    C, K = rig.num_cameras, X.shape[0]
    xy = np.zeros((1, C, 2, K, 2), np.float32)
    score = np.zeros((1, C, 2, K), np.float32)
    xy[0, :3, 0], score[0, :3, 0] = px[:3, 0], 1.0  # the person, cameras 0-2
    xy[0, 0, 1], score[0, 0, 1] = px[0, 0], 1.0  # camera 0's duplicate of the person ...
    xy[0, 3, 1], score[0, 3, 1] = px[3, 1], 1.0  # ... with camera 3's view of the far skeleton
    count = (score > 0).any(-1).sum(-1).astype(np.int32)
    members = np.full((1, 2, C), -1, np.int32)
    members[0, 0, :3] = 0
    members[0, 1, [0, 3]] = 1
    return Detections(xy, score, count), members, X


@pytest.mark.parametrize("method", ["robust", "blend"])
def test_a_group_larger_than_a_body_is_not_a_person(scene, method):
    rig, rec = scene
    det, members, X = _person_and_ghost(rig, rec, depth_factor=3.0)
    est = untrained_estimator(rig) if method == "blend" else None
    poses, _ = poses_of_members(rig, det, members, estimator=est, method=method)
    assert poses.valid[0].tolist() == [True, False]  # the ghost is dropped, the person kept
    np.testing.assert_allclose(poses.xyz[0, 0], X, atol=1e-3)
    # Without the check the ghost is reconstructed: metres behind the person, far larger.
    kept, _ = poses_of_members(rig, det, members, estimator=est, method=method, max_spread_m=np.inf)
    assert kept.valid[0].tolist() == [True, True]
    tri = kept.keypoint_valid[0, 1] if method != "blend" else np.ones(len(X), bool)
    assert skeleton_spread(kept.xyz[0, 1], tri) > 2.0 * skeleton_spread(X, np.ones(len(X), bool))
    assert np.linalg.norm(kept.xyz[0, 1].mean(0) - X.mean(0)) > 2.0
    # A person only somewhat larger than the bound's body (1.4 times) is kept: the bound is
    # on size, and a group of another person's views behind the first is far larger.
    near, near_members, _ = _person_and_ghost(rig, rec, depth_factor=1.4)
    assert poses_of_members(rig, near, near_members, estimator=est, method=method)[0].valid.all()
    res = run_pipeline(rig, det, estimator=est, method=method)  # the pipeline drops it too
    assert res.poses.valid.sum() == 1 and (res.members[res.poses.valid] >= 0).sum() == 3
    # The plain triangulations keep every group (one wrong view would stretch theirs too).
    for plain in ("dlt", "centroid"):
        assert poses_of_members(rig, det, members, method=plain)[0].valid.all()


@pytest.mark.parametrize("method", ["robust", "blend"])
def test_a_calibration_in_the_wrong_units_is_named_when_everyone_is_too_large(scene, method):
    from mvpose_jax.errors import MvposeWarning

    rig, rec = scene
    members = members_from_identity(np.asarray(rec.identity), 3)
    # Translations in mm read as metres: the same cameras, every distance 1000 times larger.
    mm = make_rig(rig.K, rig.dist, rig.R, 1000 * np.asarray(rig.t), rig.size, rig.names, rig.up)
    est = untrained_estimator(mm) if method == "blend" else None
    with pytest.warns(MvposeWarning, match="translation-scale 0.001"):
        poses, _ = poses_of_members(mm, rec.detections, members, estimator=est, method=method)
    assert not poses.valid.any()


@pytest.mark.slow  # the 3D stage five ways and the pipeline (compilations)
def test_blend_is_robust_triangulation_where_it_reconstructs_and_the_estimator_elsewhere(scene):
    rig, rec = scene
    det = rec.detections
    members = members_from_identity(np.asarray(rec.identity), 3)
    est = untrained_estimator(rig)  # returns its initial 3D: robust triangulation, for "blend"
    blend, conf = poses_of_members(rig, det, members, estimator=est, method="blend")
    robust, _ = poses_of_members(rig, det, members, method="robust")
    mlp, mlp_conf = poses_of_members(rig, det, members, estimator=est)  # "mlp" is the default
    np.testing.assert_array_equal(blend.valid, mlp.valid)
    np.testing.assert_array_equal(conf, mlp_conf)
    assert blend.keypoint_valid[blend.valid].all()  # every keypoint, like the estimator
    tri = robust.keypoint_valid & blend.valid[..., None]
    assert tri.any() and (~tri & blend.keypoint_valid).any()
    np.testing.assert_allclose(blend.xyz[tri], robust.xyz[tri], atol=1e-5)
    # A keypoint one view sees: on that view's ray, as far from the camera as the person's
    # triangulated keypoints' mean (the untrained network's start; the blend's offset is 0).
    from mvpose_jax.cameras import camera_centres, pixel_rays
    from mvpose_jax.lifting import group_people

    xy, score = group_people(det.xy, det.score, members)  # (F, G, C, K, ...)
    one = ((score > 0).sum(axis=2) == 1) & blend.valid[..., None]  # (F, G, K)
    assert one.any()
    cam = np.argmax(score > 0, axis=2)  # (F, G, K) the one view
    rays = np.moveaxis(np.asarray(pixel_rays(rig, np.moveaxis(xy, 2, 0))), 0, 2)
    ray = np.take_along_axis(rays, cam[:, :, None, :, None], axis=2)[:, :, 0]
    origin = np.asarray(camera_centres(rig))[cam]
    kv = robust.keypoint_valid[..., None]
    anchor = (robust.xyz * kv).sum(-2) / np.maximum(kv.sum(-2), 1)  # (F, G, 3)
    depth = np.linalg.norm(anchor[:, :, None] - origin, axis=-1, keepdims=True)
    legs = np.zeros(one.shape[-1], bool)
    legs[[13, 14, 15, 16]] = True  # knees and ankles hang from their parents instead
    np.testing.assert_allclose(
        blend.xyz[one & ~legs], (origin + ray * depth)[one & ~legs], atol=1e-4
    )
    # ... still on their ray (tests/test_triangulate.py checks where on it).
    assert (one & legs).any()
    v = blend.xyz - origin
    off_ray = np.linalg.norm(v - ray * np.sum(v * ray, -1, keepdims=True), axis=-1)
    assert off_ray[one & legs].max() < 1e-3
    from mvpose_jax.errors import InputError

    with pytest.raises(InputError, match="layout 'body25' has 25 keypoints"):
        poses_of_members(rig, det, members, estimator=est, method="blend", layout="body25")
    # The pipeline gives the same, and the method is checked.
    res = run_pipeline(rig, det, estimator=est, method="blend")
    again, _ = poses_of_members(rig, det, res.members, estimator=est, method="blend")
    np.testing.assert_allclose(again.xyz, res.poses.xyz, atol=1e-6)
    for method in ("blend", "mlp"):
        with pytest.raises(ValueError, match="needs an estimator"):
            poses_of_members(rig, det, members, method=method)
    with pytest.raises(ValueError, match="blend"):
        run_pipeline(rig, det, estimator=est, method="median")
    # A triangulation method ignores the estimator.
    dlt_est, _ = poses_of_members(rig, det, members, estimator=est, method="dlt")
    dlt, _ = poses_of_members(rig, det, members, method="dlt")
    np.testing.assert_array_equal(dlt_est.xyz, dlt.xyz)


@pytest.mark.slow  # uses the trained `models`
def test_keypoint_count_mismatch_is_a_clear_error(scene, models):
    rig, rec = scene
    _, estimator = models
    det = rec.detections
    det25 = Detections(
        np.zeros(np.shape(det.xy)[:3] + (25, 2), np.float32),
        np.zeros(np.shape(det.score)[:3] + (25,)),
        det.count,
    )
    with pytest.raises(InputError, match="18 keypoints"):
        run_pipeline(rig, det25, estimator=estimator)
    # After a run with the right keypoints (the model's count is then kept), still an error.
    two = Detections(*(np.asarray(a)[:2] for a in det))
    run_pipeline(rig, two, estimator=estimator)
    with pytest.raises(InputError, match="the estimator was trained on 18 keypoints"):
        run_pipeline(rig, det25, estimator=estimator)


@pytest.mark.slow  # uses the trained `models`
def test_estimator_cameras_must_be_proposal_cameras(scene, models):
    rig, rec = scene
    _, estimator = models
    sub = rig.select(list(rig.names[:3]))
    det = rec.detections
    det3 = Detections(
        np.asarray(det.xy)[:, :3], np.asarray(det.score)[:, :3], np.asarray(det.count)[:, :3]
    )
    with pytest.raises(InputError, match="inference"):
        run_pipeline(sub, det3, estimator=estimator)


# --------------------------------------------------------------------------- numerical safety


def _degenerate_detections(rig, K=18):
    """Frame 0: a person seen in one view only, with keypoints in the other views missing.
    Frame 1: a person whose 'second view' is a single keypoint. Frame 2: huge/odd pixels (points
    far outside the image, behind-camera-like geometry). Frame 3: nobody at all."""
    C = rig.num_cameras
    F, P = 4, 2
    xy = np.zeros((F, C, P, K, 2), np.float32)
    score = np.zeros((F, C, P, K), np.float32)
    count = np.zeros((F, C), np.int32)
    w, h = (float(v) for v in np.asarray(rig.size)[0])
    rng = np.random.default_rng(0)
    xy[0, 0, 0] = rng.uniform([0, 0], [w, h], size=(K, 2))
    score[0, 0, 0] = 0.9
    count[0, 0] = 1
    for c in range(C):
        count[1, c] = 1
        xy[1, c, 0, 0] = [w / 2, h / 2]
        score[1, c, 0, 0] = 0.9
    for c in range(C):
        count[2, c] = 1
        xy[2, c, 0] = rng.uniform(-1e6, 1e6, size=(K, 2))
        score[2, c, 0] = 0.5
    return Detections(xy, score, count)


@pytest.mark.slow  # uses the trained `models`
@pytest.mark.parametrize("use_estimator", [False, True])
def test_no_nan_leaves_the_pipeline_on_degenerate_input(scene, models, use_estimator):
    rig, _ = scene
    det = _degenerate_detections(rig)
    estimator = models[1] if use_estimator else None
    # threshold 0 so that even the junk frame's skeletons get grouped and reach the 3D stage.
    for method in ("mlp", "blend") if use_estimator else ("dlt", "centroid", "robust"):
        res = run_pipeline(rig, det, estimator=estimator, method=method, threshold=0.0)
        assert np.isfinite(res.poses.xyz).all() and np.isfinite(res.confidence).all()
        # Invalid keypoints are zeroed, invalid people have no valid keypoint.
        assert (res.poses.xyz[~res.poses.keypoint_valid] == 0).all()
        assert not res.poses.keypoint_valid[~res.poses.valid].any()
        assert not res.poses.valid[0].any(), "one view is not a person"
        assert not res.poses.valid[3].any()
        if not use_estimator:
            # Triangulation needs 2 views per keypoint: frame 1's people have one keypoint each.
            assert res.poses.keypoint_valid[1].sum(-1).max() <= 1


def test_colinear_cameras_give_invalid_not_nan():
    """Three cameras on one line looking along it: every ray through the centre is the same line,
    so its depth is undetermined; triangulation must flag it, never return NaN/inf."""
    K = [[[1000.0, 0, 500], [0, 1000.0, 500], [0, 0, 1]]] * 3
    R = [np.eye(3)] * 3
    t = [[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, -2.0]]  # centres at z = 0, 1, 2 on the axis
    rig = make_rig(K, [[0.0] * 5] * 3, R, t, [[1000, 1000]] * 3, ["a", "b", "c"])
    Kp = 18
    xy = np.full((1, 3, 1, Kp, 2), 500.0, np.float32)  # every keypoint on the principal point
    score = np.full((1, 3, 1, Kp), 0.9, np.float32)
    det = Detections(xy, score, np.ones((1, 3), np.int32))
    members = np.zeros((1, 1, 3), np.int32)
    for method in ("dlt", "centroid", "robust"):
        poses, conf = poses_of_members(rig, det, members, method=method)
        assert np.isfinite(poses.xyz).all() and np.isfinite(conf).all()
        assert not poses.keypoint_valid.any() and not poses.valid.any()


def test_no_recompilation_beyond_buckets():
    graphdef, rest, state, step = _train_state()
    params = state.params
    rng = np.random.default_rng(3)
    budgets = set()
    jitted = bound_model_fn(_match_scores_fn, graphdef, xla_kernels=True)  # _match_scores'
    before = jitted._cache_size()
    for _ in range(40):
        F = 5
        P = int(rng.integers(1, 4))  # frames of any size, padded to buckets
        feats, valid, identity = random_frames(rng, F, P=P, p_valid=rng.uniform(0.2, 1.0))
        b = build_graphs(feats, valid, identity, num_graphs=F)
        budgets.add((b.graphs.nodes.shape[0], b.det_features.shape[0]))
        _match_scores(graphdef, rest, params, b)
    assert jitted._cache_size() - before <= len(budgets) <= 6


def test_bound_model_fn_is_built_once_per_graphdef():
    graphdef, _, _, _ = _train_state()
    again, _, _, _ = _train_state()  # an equal GraphDef, another object
    f = bound_model_fn(_match_scores_fn, graphdef)
    assert bound_model_fn(_match_scores_fn, graphdef) is f
    assert again is not graphdef and bound_model_fn(_match_scores_fn, again) is f
    other, _, _, _ = _train_state(GATConfig(widths=(16, 16, 1), heads=(2, 2, 1)))
    assert bound_model_fn(_match_scores_fn, other) is not f


@pytest.mark.parametrize("frames", [1, 5, 12, 31, 32, 33, 300, 1024])
@pytest.mark.parametrize("per_call", [1, 4, 32])
def test_frame_chunks_cut_evenly_into_one_padded_shape(frames, per_call):
    bounds, padded = frame_chunks(frames, per_call)
    # Every frame once, in order, in as few calls as the cap allows.
    np.testing.assert_array_equal(
        np.concatenate([np.arange(a, b) for a, b in bounds]), np.arange(frames)
    )
    assert len(bounds) == -(-frames // per_call)
    lengths = [b - a for a, b in bounds]
    assert max(lengths) - min(lengths) <= 1
    # One padded size for all: the next power of two of the longest call, within the cap.
    assert max(lengths) <= padded <= per_call and padded & (padded - 1) == 0
    assert padded < 2 * max(lengths)


def test_frame_chunks_of_a_tracking_scene_and_of_nothing():
    # 300 frames at 32 a call: ten calls of 30, not nine of 32 and a tail of 12 padded to 16.
    assert frame_chunks(300, 32) == ([(30 * i, 30 * i + 30) for i in range(10)], 32)
    assert frame_chunks(0, 32) == ([], 0)


def test_gat_match_table_equals_features_then_graphs_then_network(ring_rig):
    """The fused path (features in the GAT's jit, graphs cached by count) gives the two-step numbers."""
    from mvpose_jax.skeletons import Detections
    from mvpose_jax.trained import Matcher

    rec = generate_recording(ring_rig, num_people=3, num_frames=5, seed=4)
    d = rec.detections
    count = np.asarray(d.count).copy()
    count[2] = 0  # a frame without any skeleton
    count[3, 0] = 0  # and a camera without one
    det = Detections(np.asarray(d.xy), np.asarray(d.score), count)
    model = MatchingGAT(ring_rig.num_cameras, rec.num_keypoints, TINY, rngs=nnx.Rngs(1))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    matcher = Matcher(graphdef, rest, params, ring_rig, MatcherConfig(gat=TINY))
    F, C, P, _ = det.score.shape
    valid = np.arange(P)[None, None] < count[..., None]
    feats = detection_features(ring_rig, det.xy, det.score)
    for per_call in (1, 2, 8):
        want_rows, want_scores = [], []
        for start in range(0, F, per_call):
            sl = slice(start, min(F, start + per_call))
            b = build_graphs(feats[sl], valid[sl])
            r, s = match_table(b, match_scores(matcher, b))
            r[:, 0] += start
            want_rows.append(r)
            want_scores.append(s)
        for _ in range(2):  # the second pass meets cached single-frame graphs
            rows, scores = gat_match_table(matcher, det, frames_per_call=per_call)
            np.testing.assert_array_equal(rows, np.concatenate(want_rows))
            np.testing.assert_allclose(scores, np.concatenate(want_scores), atol=1e-6)
    assert not (rows[:, 0] == 2).any()


def test_a_chunks_calls_share_one_graph_budget(ring_rig):
    """Calls of a chunk whose frames hold few and many skeletons compile one program (the
    largest call's budget), and the padding moves no score: the same numbers, bit for bit, as
    each call in a budget of its own."""
    from mvpose_jax.matching import _frame_scores_fn
    from mvpose_jax.trained import Matcher

    rec = generate_recording(ring_rig, num_people=3, num_frames=12, seed=6)
    d = rec.detections
    count = np.asarray(d.count).copy()
    count[:4] = np.minimum(count[:4], 1)  # the first call: a skeleton a view at most
    det = Detections(np.asarray(d.xy), np.asarray(d.score), count)
    model = MatchingGAT(ring_rig.num_cameras, rec.num_keypoints, TINY, rngs=nnx.Rngs(3))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    matcher = Matcher(graphdef, rest, params, ring_rig, MatcherConfig(gat=TINY))
    jitted = bound_model_fn(_frame_scores_fn, graphdef, xla_kernels=True)
    before = jitted._cache_size()
    rows, scores = gat_match_table(matcher, det, frames_per_call=4)
    assert jitted._cache_size() - before == 1
    for start in range(0, 12, 4):  # each call alone: its own, smaller budget
        part = Detections(
            det.xy[start : start + 4], det.score[start : start + 4], count[start : start + 4]
        )
        r, s = gat_match_table(matcher, part, frames_per_call=4)
        in_call = (rows[:, 0] >= start) & (rows[:, 0] < start + 4)
        np.testing.assert_array_equal(rows[in_call][:, 1:], r[:, 1:])
        np.testing.assert_array_equal(scores[in_call], s)
    assert jitted._cache_size() - before > 1  # the calls alone did need other budgets


def test_combined_match_tables_are_the_gat_table_and_its_rows_epipolar_distances(ring_rig):
    """One jit call per chunk for both tables gives the two calls' numbers."""
    from mvpose_jax.matching import combined_match_tables, epipolar_distances_of_rows
    from mvpose_jax.trained import Matcher

    rec = generate_recording(ring_rig, num_people=3, num_frames=5, seed=5)
    model = MatchingGAT(ring_rig.num_cameras, rec.num_keypoints, TINY, rngs=nnx.Rngs(2))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    matcher = Matcher(graphdef, rest, params, ring_rig, MatcherConfig(gat=TINY))
    for per_call in (1, 4):
        rows, scores = gat_match_table(matcher, rec.detections, frames_per_call=per_call)
        want = epipolar_distances_of_rows(ring_rig, rec.detections, rows)
        got = combined_match_tables(matcher, rec.detections, frames_per_call=per_call)
        np.testing.assert_array_equal(got[0], rows)
        np.testing.assert_allclose(got[1], scores, atol=1e-6)
        for a, b in zip(got[2:], want, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)  # inf where inf
        assert np.isfinite(got[2]).mean() > 0.5


def test_match_tables_reuse_the_pipelines_programs(scene):
    """A table of the frames the pipeline has just run (the experiments' diagnostics) pads the
    skeleton slots as the pipeline does, so it compiles nothing more: the GAT's program, the
    combined one and the epipolar one are all the pipeline's, at the same numbers."""
    from mvpose_jax.matching import (
        _epipolar_distances,
        _frame_scores_fn,
        _fused_fn,
        combined_match_tables,
        epipolar_match_distances,
    )

    rig, rec = scene
    d = rec.detections
    pad = [(0, 0), (0, 0), (0, 5 - np.shape(d.score)[2]), (0, 0)]  # 5 slots: padded to 8
    det = Detections(np.pad(d.xy, pad + [(0, 0)]), np.pad(d.score, pad), d.count)
    matcher = _untrained_matcher(rig)
    run_pipeline(rig, det, matcher=matcher, proposals="gat")
    run_pipeline(rig, det, matcher=matcher)  # combined
    run_pipeline(rig, det)  # epipolar
    programs = [
        bound_model_fn(_frame_scores_fn, matcher.graphdef, xla_kernels=True),
        bound_model_fn(_fused_fn(3), matcher.graphdef, xla_kernels=True),
        _epipolar_distances,
    ]
    before = [f._cache_size() for f in programs]
    gat_match_table(matcher, det)
    combined_match_tables(matcher, det)
    epipolar_match_distances(rig, det)
    assert [f._cache_size() for f in programs] == before


def test_geometric_baseline_groups_true_people(ring_rig):
    from mvpose_jax.synthetic import generate_recording

    rec = generate_recording(ring_rig, num_people=3, num_frames=4, seed=3)
    rows, scores = geometric_match_table(ring_rig, rec.detections)
    ident = rec.identity
    same = (
        ident[rows[:, 0], rows[:, 1], rows[:, 2]] == ident[rows[:, 0], rows[:, 3], rows[:, 4]]
    ) & (ident[rows[:, 0], rows[:, 1], rows[:, 2]] >= 0)
    assert scores[same].mean() > 0.5 > scores[~same].mean()
    p = propose_people(rows, scores, rec.detections.count, num_skeletons=ident.shape[2])
    assert matching_scores(ident, p.identity, np.asarray(rec.detections.count))["ari"] > 0.9


def test_single_frame_graph_cache_is_lru_and_bounded_by_bytes():
    from mvpose_jax.matching import _frame_graphs, _GraphCache

    def key(*counts):
        return (np.array([counts], np.int64).tobytes(), 1, 3, 4, 1)

    one = _GraphCache._size(_frame_graphs(*key(2, 2, 2)))
    cache = _GraphCache(max_bytes=int(2.5 * one))  # room for two graphs of this size
    a = cache(*key(2, 2, 2))
    assert cache(*key(2, 2, 2)) is a  # a hit returns the stored graph
    b = cache(*key(1, 2, 2))
    assert cache(*key(2, 2, 2)) is a  # touched: key(1, 2, 2) is now the oldest
    cache(*key(2, 1, 2))
    assert len(cache) == 2
    assert cache(*key(2, 2, 2)) is a  # kept
    assert cache(*key(1, 2, 2)) is not b  # evicted, rebuilt
    np.testing.assert_array_equal(cache(*key(1, 2, 2)).rows, b.rows)


def test_composed_match_table_scores_the_composed_skeletons_with_their_identities(ring_rig):
    from mvpose_jax.matcher_settings import composed_match_table
    from mvpose_jax.trained import Matcher

    recs = generate_single_person_recordings(ring_rig, num_recordings=5, num_frames=4, seed=2)
    model = MatchingGAT(ring_rig.num_cameras, recs[0].num_keypoints, TINY, rngs=nnx.Rngs(0))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    config = MatcherConfig(gat=TINY, max_people=3, keypoint_dropout=0.3)
    matcher = Matcher(graphdef, rest, params, ring_rig, config)
    rows, scores, identity, count = composed_match_table(
        matcher, recs, num_samples=40, seed=1, frames_per_call=16
    )
    S, C, Q = identity.shape
    assert S == 40 and count.shape == (S, C)
    present = np.arange(Q)[None, None] < count[..., None]
    assert (identity[~present] == -1).all()
    assert identity.max() < 3 and (identity[present] >= 0).any()
    f, ca, sa, cb, sb = rows.T
    assert (ca < cb).all() and (sa < count[f, ca]).all() and (sb < count[f, cb]).all()
    # Every cross-view pair of present skeletons is scored once, and the same seed gives the same table.
    want = sum(
        int(count[s, a]) * int(count[s, b])
        for s in range(S)
        for a in range(C)
        for b in range(a + 1, C)
    )
    assert len(rows) == len(scores) == want
    again = composed_match_table(matcher, recs, num_samples=40, seed=1, frames_per_call=16)
    np.testing.assert_array_equal(again[0], rows)
    np.testing.assert_allclose(again[1], scores)


def test_composed_frames_are_the_training_composition_as_detections(ring_rig):
    from mvpose_jax.graphs import compose_samples, detection_features, make_pool
    from mvpose_jax.matcher_settings import composed_frames
    from mvpose_jax.synthetic import generate_single_person_recordings

    recs = generate_single_person_recordings(ring_rig, num_recordings=5, num_frames=4, seed=2)
    det, identity = composed_frames(
        ring_rig, recs, num_samples=30, seed=3, max_people=3, keypoint_dropout=0.4
    )
    pool = make_pool(ring_rig, recs)
    feats, valid, ident = compose_samples(
        pool, np.random.default_rng([3, 1 << 29]), 30, max_people=3, keypoint_dropout=0.4
    )
    # The same draws: per frame and view, the detections' features are the training features of
    # the valid skeletons, in order, and the identities theirs.
    ours = np.asarray(detection_features(ring_rig, det.xy, det.score))
    count = np.asarray(det.count)
    np.testing.assert_array_equal(count, valid.sum(-1))
    for s in range(30):
        for c in range(ring_rig.num_cameras):
            n = count[s, c]
            np.testing.assert_allclose(ours[s, c, :n], feats[s, c][valid[s, c]], atol=1e-6)
            np.testing.assert_array_equal(identity[s, c, :n], ident[s, c][valid[s, c]])
            assert (np.asarray(det.score)[s, c, n:] == 0).all() and (identity[s, c, n:] == -1).all()


def test_epipolar_distances_give_the_geometric_scores(ring_rig):
    from mvpose_jax.matching import epipolar_match_distances
    from mvpose_jax.synthetic import generate_recording

    rec = generate_recording(ring_rig, num_people=3, num_frames=3, seed=5)
    rows, scores = geometric_match_table(ring_rig, rec.detections, half_score_px=25.0)
    rows_d, d = epipolar_match_distances(ring_rig, rec.detections)
    np.testing.assert_array_equal(rows, rows_d)
    np.testing.assert_allclose(scores, np.exp2(-d / 25.0), rtol=1e-6)


@pytest.mark.slow  # compiles the epipolar distances with the median (~20 s on a busy CPU)
def test_epipolar_distances_of_rows_mean_median_and_either_camera_order(ring_rig):
    import cv2

    from mvpose_jax.matching import epipolar_distances_of_rows, epipolar_match_distances

    rec = generate_recording(ring_rig, num_people=2, num_frames=2, seed=3)
    det = rec.detections
    rows, d = epipolar_match_distances(ring_rig, det)
    mean, median, shared_count = epipolar_distances_of_rows(ring_rig, det, rows)
    np.testing.assert_allclose(mean, d, rtol=1e-6)
    swapped = rows[:, [0, 3, 4, 1, 2]]  # the same pairs named (camera_b, camera_a)
    got_all = epipolar_distances_of_rows(ring_rig, det, swapped)
    for got, want in zip(got_all, (mean, median, shared_count), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-6)
    # The median against OpenCV: undistorted pixels, the fundamental matrix of the two cameras,
    # cv2.computeCorrespondEpilines, point-line distances, their numpy median.
    xy, score = np.asarray(det.xy, np.float64), np.asarray(det.score)
    K, dist = np.asarray(ring_rig.K, np.float64), np.asarray(ring_rig.dist, np.float64)
    R, t = np.asarray(ring_rig.R, np.float64), np.asarray(ring_rig.t, np.float64)

    def undistorted(c, pts):
        return cv2.undistortPoints(pts.reshape(-1, 1, 2), K[c], dist[c], P=K[c]).reshape(-1, 2)

    def line_distance(lines, pts):
        return np.abs((lines[:, :2] * pts).sum(1) + lines[:, 2]) / np.hypot(*lines[:, :2].T)

    for i in range(0, len(rows), 7):
        (f, ca, pa, cb, pb), want = rows[i], median[i]
        shared = (score[f, ca, pa] > 0) & (score[f, cb, pb] > 0)
        assert shared_count[i] == shared.sum()
        if shared.sum() < 3:
            assert want == np.inf
            continue
        ua, ub = undistorted(ca, xy[f, ca, pa][shared]), undistorted(cb, xy[f, cb, pb][shared])
        r_rel = R[cb] @ R[ca].T
        t_rel = t[cb] - r_rel @ t[ca]
        tx = np.array(
            [[0, -t_rel[2], t_rel[1]], [t_rel[2], 0, -t_rel[0]], [-t_rel[1], t_rel[0], 0]]
        )
        fund = np.linalg.inv(K[cb]).T @ tx @ r_rel @ np.linalg.inv(K[ca])
        in_b = cv2.computeCorrespondEpilines(ua.reshape(-1, 1, 2), 1, fund).reshape(-1, 3)
        in_a = cv2.computeCorrespondEpilines(ub.reshape(-1, 1, 2), 2, fund).reshape(-1, 3)
        ref = np.median(0.5 * (line_distance(in_b, ub) + line_distance(in_a, ua)))
        np.testing.assert_allclose(want, ref, rtol=1e-3, atol=1e-3)


def _untrained_matcher(rig):
    from mvpose_jax.trained import Matcher

    tiny = GATConfig(widths=(8, 1), heads=(2, 1))
    graphdef, params, rest = nnx.split(
        MatchingGAT(rig.num_cameras, 18, tiny, rngs=nnx.Rngs(0)), nnx.Param, ...
    )
    return Matcher(graphdef, rest, params, rig, MatcherConfig(gat=tiny))


@pytest.mark.slow  # four pipelines, a GAT among them
def test_pipeline_proposal_modes_with_a_matcher(scene):
    """An untrained matcher (scores near-random): the default, combined proposals still group the
    people as the epipolar matcher does; "gat" is the GAT alone; "epipolar" ignores it."""
    from mvpose_jax.matching import propose_with_matcher
    from mvpose_jax.proposals import CombinedConfig

    rig, rec = scene
    det, count = rec.detections, np.asarray(rec.detections.count)
    matcher = _untrained_matcher(rig)
    ident = np.asarray(rec.identity)
    epipolar = run_pipeline(rig, det, half_score_px=100.0)
    combined = run_pipeline(rig, det, matcher=matcher)
    assert matching_scores(ident, combined.identity, count)["ari"] >= (
        matching_scores(ident, epipolar.identity, count)["ari"] - 1e-9
    )
    assert matching_scores(ident, combined.identity, count)["ari"] > 0.95
    gat = run_pipeline(rig, det, matcher=matcher, proposals="gat", threshold=0.3)
    alone = propose_with_matcher(matcher, det, threshold=0.3)
    np.testing.assert_array_equal(gat.identity, alone.identity)
    # "gat-repaired": the same scores, grouped with propose_people's split repair.
    repaired = run_pipeline(rig, det, matcher=matcher, proposals="gat-repaired", threshold=0.3)
    rows, scores = gat_match_table(matcher, det)
    P = np.shape(det.score)[2]
    want = propose_people(rows, scores, count, num_skeletons=P, threshold=0.3, repair_splits=True)
    np.testing.assert_array_equal(repaired.identity, want.identity)
    explicit = run_pipeline(
        rig, det, matcher=matcher, proposals="combined", combined=CombinedConfig()
    )
    np.testing.assert_array_equal(explicit.identity, combined.identity)
    geo = run_pipeline(rig, det, matcher=matcher, proposals="epipolar", half_score_px=100.0)
    np.testing.assert_array_equal(geo.identity, epipolar.identity)
    with pytest.raises(ValueError, match="need a matcher"):
        run_pipeline(rig, det, proposals="combined")
    with pytest.raises(ValueError, match="proposals must be one of"):
        run_pipeline(rig, det, matcher=matcher, proposals="learned")


@pytest.mark.parametrize("method", ["robust", "dlt", "blend", "mlp"])
def test_people_in_blocks_give_one_calls_results_bit_for_bit(scene, method, monkeypatch):
    """Beyond `lifting.PEOPLE_PER_CALL` people the 3D stage runs in blocks of that size (the
    last padded to it), so a chunk compiles one shape however many people it holds: every
    method's keypoints and validity are those of one call on the whole batch, bit for bit."""
    from mvpose_jax import lifting

    rig, rec = scene
    det = rec.detections
    members = members_from_identity(np.asarray(rec.identity), 3)
    xy, score = lifting.group_people(np.asarray(det.xy), np.asarray(det.score), members)
    present = (score > 0).any(-1).sum(-1) >= 2  # (F, G) people seen in 2+ views
    xy, score = xy[present], score[present]  # (N, C, K, 2), N = 24 people
    estimator = untrained_estimator(rig)

    def lift(per_call):
        monkeypatch.setattr(lifting, "PEOPLE_PER_CALL", per_call)
        if method in ("robust", "dlt"):
            return lifting.triangulate_people(rig, xy, score, method)
        return lifting._estimate_people(
            estimator,
            xy,
            score,
            method=method,
            outlier_px=lifting.OUTLIER_PX,
            view_outlier_px=lifting.VIEW_OUTLIER_PX,
            layout="coco18",
            mesh=None,
        )

    assert len(xy) == 24 and lifting._people_blocks(24) == [(0, 24, 24)]
    whole = lift(512)
    blocks = lift(10)  # the last block padded: 4 people in a call of 10
    assert lifting._people_blocks(24) == [(0, 10, 10), (10, 20, 10), (20, 24, 10)]
    for a, b in zip(whole, blocks, strict=True):
        if a is None:
            assert b is None
        else:
            assert a.shape[0] == len(xy)
            np.testing.assert_array_equal(a, b)
