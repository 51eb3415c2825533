"""Skeleton matching: the GAT, its training, proposals, clustering metrics, the geometric baseline."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from flax import nnx
from hypothesis import given, settings
from hypothesis import strategies as st

from mvpose_jax.graphs import (
    Budget,
    build_graphs,
    dense_node_features,
    detection_features,
    graph_budget,
    match_table,
)
from mvpose_jax.inference import (
    _match_scores,
    _match_scores_fn,
    bound_model_fn,
    gat_match_table,
    geometric_match_table,
    match_scores,
)
from mvpose_jax.metrics import clustering_scores, detection_clusters, matching_scores
from mvpose_jax.models import GATConfig, MatchingGAT
from mvpose_jax.proposals import propose_people, union_find_exclusive
from mvpose_jax.synthetic import generate_recording, generate_single_person_recordings
from mvpose_jax.train import (
    init_train_state,
    make_optimizer,
    make_train_step,
    matcher_loss_fn,
    train_matcher,
)
from mvpose_jax.trained import MatcherConfig
from tests.helpers import random_frames

C, K = 3, 4
TINY = GATConfig(widths=(8, 8, 1), heads=(2, 2, 1))


@pytest.fixture(scope="module")
def model():
    return MatchingGAT(C, K, GATConfig(), rngs=nnx.Rngs(0))


def test_factorised_first_layer_equals_dense_gat(model):
    b = build_graphs(*random_frames(np.random.default_rng(0), 4))
    fast = np.asarray(jax.jit(lambda m, x: m(x))(model, b))
    dense = np.asarray(jax.jit(lambda m, x, g: m.dense_forward(x, g))(model, dense_node_features(b), b.graphs))
    np.testing.assert_allclose(fast[b.node_mask], dense[b.node_mask], atol=1e-5)


def test_padding_never_changes_real_scores(model):
    feats, valid, identity = random_frames(np.random.default_rng(1), 3)
    small = build_graphs(feats, valid, identity)
    big = build_graphs(feats, valid, identity, num_graphs=9,
                       budget=Budget(small.graphs.nodes.shape[0] * 4, 128, small.graphs.nodes.shape[0] * 20, 10))  # fmt: skip
    f = jax.jit(lambda m, x: m(x))
    a, b = np.asarray(f(model, small)), np.asarray(f(model, big))
    n = int(small.node_mask.sum())
    assert np.isfinite(a).all() and np.isfinite(b).all()
    np.testing.assert_allclose(a[:n], b[:n], atol=1e-6)


def test_gat_config_validates():
    with pytest.raises(ValueError):
        GATConfig(widths=(40, 1), heads=(3, 1))
    with pytest.raises(ValueError):
        GATConfig(widths=(40, 2), heads=(10, 1))


def _train_state(config=TINY, lr=3e-3, seed=0):
    m = MatchingGAT(C, K, config, rngs=nnx.Rngs(seed))
    tx = make_optimizer(dataclasses.replace(MatcherConfig().train, learning_rate=lr))
    graphdef, rest, state = init_train_state(m, tx)
    return graphdef, rest, state, make_train_step(graphdef, rest, tx, matcher_loss_fn)


def test_tiny_model_overfits_tiny_dataset():
    # Identity is written into the features, so a perfect matcher exists.
    rng = np.random.default_rng(2)
    feats, valid, identity = random_frames(rng, 6)
    feats[..., :3] = np.eye(3, dtype=np.float32)[np.maximum(identity, 0)] * (identity >= 0)[..., None]
    batch = jax.device_put(build_graphs(feats, valid, identity))
    # 3e-3: at 1e-2 Adam sometimes parks this tiny net on a plateau (seed-dependent); at 3e-3
    # every initialisation tried converges (loss / 1e4 within 300 steps).
    _, _, state, step = _train_state(GATConfig(widths=(16, 16, 1), heads=(2, 2, 1)), lr=3e-3)
    key = jax.random.key(0)
    losses = []
    for _ in range(300):
        state, metrics = step(state, batch, key)
        losses.append(float(metrics["loss"]))
    assert np.isfinite(losses).all()
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


def test_no_recompilation_beyond_buckets():
    graphdef, rest, state, step = _train_state()
    params = state.params
    rng = np.random.default_rng(3)
    budgets = set()
    jitted = bound_model_fn(_match_scores_fn, graphdef)
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


def test_train_matcher_quick_runs_and_checkpoints(ring_rig, tmp_path):
    from mvpose_jax.synthetic import generate_single_person_recordings
    from mvpose_jax.trained import load_matcher

    recs = generate_single_person_recordings(ring_rig, num_recordings=4, num_frames=5, seed=1)
    cfg = MatcherConfig.quick()
    cfg = dataclasses.replace(cfg, gat=TINY, samples_per_epoch=30, num_dev_samples=15,
                              train=dataclasses.replace(cfg.train, max_epochs=2, eval_every=1))  # fmt: skip
    matcher, fit = train_matcher(ring_rig, recs[:3], recs[3:], cfg, checkpoint_dir=tmp_path, progress=False)
    assert fit.steps == 4 and np.isfinite(fit.best_val_loss)
    again = load_matcher(tmp_path, ring_rig, cfg, num_keypoints=recs[0].num_keypoints)
    for a, b in zip(jax.tree.leaves(matcher.params), jax.tree.leaves(again.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# --------------------------------------------------------------------------- proposals


def test_proposals_join_best_first_and_respect_cameras():
    count = np.array([[2, 2, 1]])  # one frame, 3 cameras
    rows = np.array([
        [0, 0, 0, 1, 0],  # a: 0.9
        [0, 0, 0, 1, 1],  # would put two camera-1 skeletons in a's person: refused
        [0, 0, 1, 1, 1],  # b: 0.8
        [0, 1, 0, 2, 0],  # a gets camera 2
        [0, 0, 1, 2, 0],  # refused: camera 2 taken
    ])  # fmt: skip
    scores = np.array([0.9, 0.85, 0.8, 0.7, 0.95])
    p = propose_people(rows, scores, count)
    # The best pair (0,1)-(2,0) goes first: b = {(0,1), (2,0)}, then (0,0)-(1,0), then (1,1) joins b.
    ident = p.identity[0]
    assert ident[0, 1] == ident[2, 0] == ident[1, 1]
    assert ident[0, 0] == ident[1, 0] != ident[0, 1]
    assert len(p.people[0]) == 2
    for person in p.people[0]:
        assert (person >= 0).sum() >= 2


def test_proposals_threshold_min_views_and_single_camera():
    count = np.array([[1, 1], [2, 0]])
    rows = np.array([[0, 0, 0, 1, 0]])
    assert (propose_people(rows, np.array([0.4]), count).identity[0] == -1).all()
    assert (propose_people(rows, np.array([0.6]), count).identity[0, :, 0] == 0).all()
    single = propose_people(np.zeros((0, 5), int), np.zeros(0), np.array([[3], [0]]))
    assert single.identity[0, 0].tolist() == [0, 1, 2] and len(single.people[1]) == 0


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 4), st.integers(2, 4), st.integers(1, 4), st.integers(0, 2**31 - 1))
def test_proposals_never_give_a_person_two_skeletons_of_one_camera(F, cams, P, seed):
    rng = np.random.default_rng(seed)
    count = rng.integers(0, P + 1, (F, cams))
    f, ca, pa, cb, pb = np.meshgrid(np.arange(F), np.arange(cams), np.arange(P), np.arange(cams), np.arange(P),
                                    indexing="ij")  # fmt: skip
    rows = np.stack([a.ravel() for a in (f, ca, pa, cb, pb)], 1)
    rows = rows[(rows[:, 1] < rows[:, 3]) & (rows[:, 2] < count[rows[:, 0], rows[:, 1]])
                & (rows[:, 4] < count[rows[:, 0], rows[:, 3]])]  # fmt: skip
    p = propose_people(rows, rng.random(len(rows)), count, num_skeletons=P, min_views=2)
    for fr in range(F):
        ident = p.identity[fr]
        for person in np.unique(ident[ident >= 0]):
            per_cam = (ident == person).sum(axis=1)
            assert per_cam.max() == 1 and per_cam.sum() >= 2
        assert len(p.people[fr]) == len(np.unique(ident[ident >= 0]))
        for g, person in enumerate(p.people[fr]):
            for c, sk in enumerate(person):
                assert (sk < 0) or ident[c, sk] == g


def test_union_find_exclusive_plain():
    roots = union_find_exclusive(4, [0, 1, 2], [1, 2, 3], np.array([0, 1, 0, 2]))
    assert roots.tolist() == [0, 0, 2, 2]  # 1-2 refused (camera 0 twice), 2-3 joined


# --------------------------------------------------------------------------- metrics


def test_clustering_scores_equal_sklearn():
    from sklearn import metrics as sk

    rng = np.random.default_rng(4)
    for i in range(200):
        n = int(rng.integers(0, 40))
        a = rng.integers(0, int(rng.integers(1, 8)), n)
        b = a.copy() if i % 4 == 0 else rng.integers(0, int(rng.integers(1, 8)), n)
        b[rng.random(n) < 0.1] = 50
        ours = clustering_scores(a, b)
        h, c, v = sk.homogeneity_completeness_v_measure(a, b)
        assert ours["ari"] == pytest.approx(sk.adjusted_rand_score(a, b), abs=1e-12)
        assert (ours["homogeneity"], ours["completeness"], ours["v_measure"]) == pytest.approx((h, c, v), abs=1e-12)


def test_detection_clusters_make_singletons_and_frame_unique_labels():
    identity = np.array([[[0, -1], [0, 1]], [[0, -1], [-1, -1]]])  # (F=2, C=2, P=2)
    count = np.array([[2, 2], [1, 1]])
    labels = detection_clusters(identity, count)
    assert len(labels) == 6
    assert labels[0] == labels[2] and len(set(labels.tolist())) == 5  # frame 1's person 0 differs
    perfect = matching_scores(identity, identity, count)
    assert perfect["ari"] == 1.0 and perfect["v_measure"] == 1.0


# --------------------------------------------------------------------------- geometric baseline


def test_geometric_baseline_groups_true_people(ring_rig):
    from mvpose_jax.synthetic import generate_recording

    rec = generate_recording(ring_rig, num_people=3, num_frames=4, seed=3)
    rows, scores = geometric_match_table(ring_rig, rec.detections)
    ident = rec.identity
    same = (ident[rows[:, 0], rows[:, 1], rows[:, 2]] == ident[rows[:, 0], rows[:, 3], rows[:, 4]]) & (
        ident[rows[:, 0], rows[:, 1], rows[:, 2]] >= 0)  # fmt: skip
    assert scores[same].mean() > 0.5 > scores[~same].mean()
    p = propose_people(rows, scores, rec.detections.count, num_skeletons=ident.shape[2])
    assert matching_scores(ident, p.identity, np.asarray(rec.detections.count))["ari"] > 0.9


def test_budget_of_a_batch_is_a_bucket():
    b = graph_budget(3, 3, 1)
    assert (b.nodes, b.dets) == (64, 16)


def test_single_frame_graph_cache_is_lru_and_bounded_by_bytes():
    from mvpose_jax.inference import _frame_graphs, _GraphCache

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
    from mvpose_jax.inference import composed_match_table
    from mvpose_jax.trained import Matcher

    recs = generate_single_person_recordings(ring_rig, num_recordings=5, num_frames=4, seed=2)
    model = MatchingGAT(ring_rig.num_cameras, recs[0].num_keypoints, TINY, rngs=nnx.Rngs(0))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    config = MatcherConfig(gat=TINY, max_people=3, keypoint_dropout=0.3)
    matcher = Matcher(graphdef, rest, params, ring_rig, config)
    rows, scores, identity, count = composed_match_table(matcher, recs, num_samples=40, seed=1, frames_per_call=16)
    S, C, Q = identity.shape
    assert S == 40 and count.shape == (S, C)
    present = np.arange(Q)[None, None] < count[..., None]
    assert (identity[~present] == -1).all()
    assert identity.max() < 3 and (identity[present] >= 0).any()
    f, ca, sa, cb, sb = rows.T
    assert (ca < cb).all() and (sa < count[f, ca]).all() and (sb < count[f, cb]).all()
    # Every cross-view pair of present skeletons is scored once, and the same seed gives the same table.
    want = sum(int(count[s, a]) * int(count[s, b]) for s in range(S) for a in range(C) for b in range(a + 1, C))
    assert len(rows) == len(scores) == want
    again = composed_match_table(matcher, recs, num_samples=40, seed=1, frames_per_call=16)
    np.testing.assert_array_equal(again[0], rows)
    np.testing.assert_allclose(again[1], scores)


def test_matching_scores_average_per_frame_and_pool_beside():
    from sklearn import metrics as sk

    # Frame 0: two people over 3 views, perfectly grouped (6 detections). Frame 1: one person in
    # two views, split in two (2 detections). Frame 2: nobody proposed at all (3 detections of 2
    # people, each left a singleton). Frame 3: no detection (nothing to score, left out).
    true = np.full((4, 3, 2), -1)
    pred = np.full((4, 3, 2), -1)
    true[0] = [[0, 1], [1, 0], [0, 1]]
    pred[0] = [[5, 6], [6, 5], [5, 6]]
    true[1, :2, 0] = 0
    pred[1, :2, 0] = [0, 1]
    true[2, :, 0] = [0, 0, 1]
    count = np.array([[2, 2, 2], [1, 1, 0], [1, 1, 1], [0, 0, 0]])
    s = matching_scores(true, pred, count)

    def frame_labels(a, f):
        ok = np.arange(2)[None] < count[f][:, None]
        x = a[f][ok]
        return np.where(x >= 0, x, 100 + np.arange(len(x)))  # -1: a singleton each

    frames = [0, 1, 2]
    want = np.mean([sk.adjusted_rand_score(frame_labels(true, f), frame_labels(pred, f)) for f in frames])
    want_v = np.mean([sk.v_measure_score(frame_labels(true, f), frame_labels(pred, f)) for f in frames])
    assert s["ari"] == pytest.approx(want, abs=1e-12) and s["v_measure"] == pytest.approx(want_v, abs=1e-12)
    assert s["frames"] == 3 and s["detections"] == 11
    pooled_t = np.concatenate([frame_labels(true, f) + 1000 * f for f in frames])
    pooled_p = np.concatenate([frame_labels(pred, f) + 1000 * f for f in frames])
    assert s["pooled_ari"] == pytest.approx(sk.adjusted_rand_score(pooled_t, pooled_p), abs=1e-12)
    # Pooling is more lenient: the big perfect frame outweighs the two small failed ones.
    assert s["pooled_ari"] > s["ari"] + 0.2
    # Frame 2, where nobody was proposed, is scored (ARI 0), not skipped.
    without = matching_scores(true[:2], pred[:2], count[:2])
    assert s["ari"] < without["ari"]


def test_composed_frames_are_the_training_composition_as_detections(ring_rig):
    from mvpose_jax.graphs import compose_samples, detection_features, make_pool
    from mvpose_jax.inference import composed_frames
    from mvpose_jax.synthetic import generate_single_person_recordings

    recs = generate_single_person_recordings(ring_rig, num_recordings=5, num_frames=4, seed=2)
    det, identity = composed_frames(ring_rig, recs, num_samples=30, seed=3, max_people=3, keypoint_dropout=0.4)
    pool = make_pool(ring_rig, recs)
    feats, valid, ident = compose_samples(pool, np.random.default_rng([3, 1 << 29]), 30, max_people=3,
                                          keypoint_dropout=0.4)  # fmt: skip
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
    from mvpose_jax.inference import epipolar_match_distances
    from mvpose_jax.synthetic import generate_recording

    rec = generate_recording(ring_rig, num_people=3, num_frames=3, seed=5)
    rows, scores = geometric_match_table(ring_rig, rec.detections, half_score_px=25.0)
    rows_d, d = epipolar_match_distances(ring_rig, rec.detections)
    np.testing.assert_array_equal(rows, rows_d)
    np.testing.assert_allclose(scores, np.exp2(-d / 25.0), rtol=1e-6)
