"""Matching graphs: construction, padding, composition of training samples."""

from __future__ import annotations

import dataclasses

import jraph
import numpy as np
import pytest

from mvpose_jax.graphs import (
    DETECTION,
    MATCH,
    Budget,
    build_graphs,
    compose_samples,
    dense_node_features,
    detection_features,
    graph_budget,
    make_pool,
    match_table,
    next_bucket,
    next_quarter_bucket,
)
from mvpose_jax.synthetic import generate_single_person_recordings

KF = 4 * 10  # K = 4 keypoints


def _frame(counts, seed=0):
    """Features (1, C, P, KF) whose values encode (camera, skeleton), and validity from counts."""
    C, P = len(counts), max(max(counts), 1)
    feats = np.zeros((1, C, P, KF), np.float32)
    for c in range(C):
        for p in range(P):
            feats[0, c, p] = 100 * (c + 1) + p + np.arange(KF) / 100
    valid = np.arange(P)[None, None] < np.asarray(counts)[None, :, None]
    return feats, valid


def test_counts_on_hand_built_frame():
    # 3 cameras with 2, 1 and 3 skeletons: 6 detections, 2*1 + 2*3 + 1*3 = 11 match nodes.
    feats, valid = _frame([2, 1, 3])
    b = build_graphs(feats, valid)
    n_node, n_edge = b.graphs.n_node, b.graphs.n_edge
    assert n_node[0] == 6 + 11
    assert n_edge[0] == 17 + 4 * 11  # self-loops + four edges per match node
    kind = b.graphs.nodes
    assert kind[:6, DETECTION].all() and not kind[:6, MATCH].any()
    assert kind[6:17, MATCH].all() and not kind[6:17, DETECTION].any()
    assert not kind[17:].any()  # padding
    assert b.is_match.sum() == 11 and b.node_mask.sum() == 17
    assert np.array_equal(b.node_mask, np.asarray(jraph.get_node_padding_mask(b.graphs)))
    # Match nodes join detections of different cameras, every unordered pair once.
    cam = b.node_camera
    pairs = b.pair[b.is_match]
    assert (cam[pairs[:, 0]] != cam[pairs[:, 1]]).all()
    assert len({tuple(sorted(p)) for p in pairs.tolist()}) == 11
    # Edges: self-loops on every real node; match <-> detection both ways; never det <-> det.
    s, r = b.graphs.senders[: n_edge[0]], b.graphs.receivers[: n_edge[0]]
    edges = set(zip(s.tolist(), r.tolist(), strict=True))
    assert all((i, i) in edges for i in range(17))
    for m in np.flatnonzero(b.is_match):
        a, c = b.pair[m]
        assert {(a, m), (m, a), (c, m), (m, c)} <= edges
    non_loop = s != r
    assert (b.is_match[s[non_loop]] != b.is_match[r[non_loop]]).all()


def test_features_fill_only_own_camera_slot():
    feats, valid = _frame([2, 1, 3])
    b = build_graphs(feats, valid)
    dense = dense_node_features(b)
    C = 3
    assert dense.shape[1] == 2 + C * KF
    for node in np.flatnonzero(b.node_mask):
        slots = dense[node, 2:].reshape(C, KF)
        if b.is_match[node]:
            assert not slots.any() and dense[node, MATCH] == 1
        else:
            c, p = b.node_camera[node], b.node_skeleton[node]
            np.testing.assert_array_equal(slots[c], feats[0, c, p])
            assert not np.delete(slots, c, axis=0).any()


def test_labels_from_identity():
    feats, valid = _frame([2, 2, 1])
    identity = np.array([[[0, 1, -1], [1, -1, -1], [0, -1, -1]]])[:, :, :2]
    b = build_graphs(feats, valid, identity)
    rows, _ = match_table(b, np.zeros(len(b.label)))
    lab = b.label[b.is_match]
    for (f, ca, pa, cb, pb), y in zip(rows, lab, strict=True):
        same = identity[f, ca, pa] >= 0 and identity[f, ca, pa] == identity[f, cb, pb]
        assert y == float(same)
    assert lab.sum() == 2  # (cam0 p0, cam2 p0) and (cam0 p1, cam1 p0)


def test_batch_equals_jraph_batch_and_pad():
    rng = np.random.default_rng(1)
    feats = rng.normal(size=(4, 3, 3, KF)).astype(np.float32)
    valid = rng.random((4, 3, 3)) < 0.6
    b = build_graphs(feats, valid, num_graphs=6)
    singles = []
    for f in range(4):
        s = build_graphs(feats[f : f + 1], valid[f : f + 1], budget=Budget(4096, 64, 20000, 2))
        n, e = s.graphs.n_node[0], s.graphs.n_edge[0]
        singles.append(
            jraph.GraphsTuple(
                nodes=s.graphs.nodes[:n],
                edges=None,
                senders=s.graphs.senders[:e],
                receivers=s.graphs.receivers[:e],
                n_node=s.graphs.n_node[:1],
                n_edge=s.graphs.n_edge[:1],
                globals=None,
            )
        )
    ref = jraph.pad_with_graphs(jraph.batch(singles), len(b.graphs.nodes), len(b.graphs.senders), 7)
    for field in ("nodes", "senders", "receivers", "n_node", "n_edge"):
        np.testing.assert_array_equal(np.asarray(getattr(ref, field)), getattr(b.graphs, field))


def test_empty_frames_and_budget_errors():
    feats = np.zeros((2, 2, 1, KF), np.float32)
    b = build_graphs(feats, np.zeros((2, 2, 1), bool))
    assert b.node_mask.sum() == 0 and b.graphs.n_node[:2].tolist() == [0, 0]
    with pytest.raises(ValueError):
        build_graphs(*_frame([3, 3]), budget=Budget(8, 16, 40, 2))


def test_budgets_are_buckets_with_room_for_padding():
    b = graph_budget(num_dets=16, num_matches=47, num_graphs=15)
    assert b.nodes == 64 and b.dets == 16 and b.graphs == 16 and b.edges == 5 * 64
    assert graph_budget(16, 48, 15).nodes == 96  # 64 real nodes need a padding node
    assert graph_budget(20, 76, 1).nodes == 128 and graph_budget(17, 0, 1).dets == 24


def test_next_bucket_is_the_smallest_power_of_two_or_one_and_a_half_times_one():
    sizes = sorted({2**k for k in range(16)} | {3 * 2**k for k in range(15)})
    for n in range(1, 5000):
        assert next_bucket(n) == next(s for s in sizes if s >= n), n


@pytest.fixture(scope="module")
def pool_and_rig(ring_rig):

    recs = generate_single_person_recordings(ring_rig, num_recordings=4, num_frames=6, seed=0)
    return make_pool(ring_rig, recs), ring_rig, recs


def test_pool_main_skeleton_is_the_fullest(pool_and_rig):
    pool, _, recs = pool_and_rig
    rec = recs[0]
    score = np.asarray(rec.detections.score)
    n_kp = np.where(
        pool.valid[: rec.num_frames], (score > 0).sum(-1)[..., : pool.valid.shape[2]], -1
    )
    has = pool.valid[: rec.num_frames].any(-1)
    main = pool.main[: rec.num_frames]
    assert (main.sum(-1) == has).all()  # one main skeleton per non-empty view
    assert (n_kp[main] == n_kp.max(-1)[has]).all()


def test_composed_samples_use_distinct_recordings_and_are_reproducible(pool_and_rig):
    pool, _, _ = pool_and_rig
    a = compose_samples(pool, np.random.default_rng(5), 50, max_people=3)
    b = compose_samples(pool, np.random.default_rng(5), 50, max_people=3)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    feats, valid, identity = a
    assert identity.max() <= 2
    # Every person slot holds at most one main skeleton per view (one recording per slot).
    for s in range(50):
        for c in range(valid.shape[1]):
            ids = identity[s, c][valid[s, c] & (identity[s, c] >= 0)]
            assert len(ids) == len(set(ids.tolist()))
    # View-subset augmentation keeps 2..C views (seen on a pool where every view has skeletons).
    full = dataclasses.replace(
        pool, valid=np.ones_like(pool.valid), main=pool.main | ~pool.valid.any(-1, keepdims=True)
    )
    valid_all = compose_samples(
        full, np.random.default_rng(6), 200, max_people=3, subset_probability=1.0
    )[1]
    views = valid_all.any(-1).sum(-1)
    assert views.min() == 2 and views.max() == valid_all.shape[1]


def test_keypoint_dropout_only_removes_whole_keypoints(pool_and_rig):
    pool, _, _ = pool_and_rig
    plain = compose_samples(pool, np.random.default_rng(7), 60, max_people=3)
    dropped = compose_samples(
        pool, np.random.default_rng(7), 60, max_people=3, keypoint_dropout=0.6
    )
    # Same frames, views and labels: the augmentation draws after the composition.
    np.testing.assert_array_equal(plain[1], dropped[1])
    np.testing.assert_array_equal(plain[2], dropped[2])
    S, C, Q, KF = plain[0].shape
    a = plain[0].reshape(S, C, Q, KF // 10, 10)
    b = dropped[0].reshape(S, C, Q, KF // 10, 10)
    same = (a == b).all(-1)
    zeroed = (b == 0).all(-1)
    assert (same | zeroed).all()  # each keypoint kept whole or removed whole
    seen_a, seen_b = a[..., 0] > 0, b[..., 0] > 0
    assert 0.1 < 1 - seen_b.sum() / seen_a.sum() < 0.5  # about 0.3 of the keypoints on average
    has = seen_a.any(-1)
    assert (seen_b.any(-1) == has).all()  # no skeleton is emptied


def test_detection_features_match_keypoint_features(ring_rig):
    from mvpose_jax.features import keypoint_features

    rng = np.random.default_rng(0)
    xy = rng.uniform(100, 900, (2, 4, 3, 5, 2)).astype(np.float32)
    score = (rng.random((2, 4, 3, 5)) > 0.3).astype(np.float32)
    out = detection_features(ring_rig, xy, score)
    ref = np.asarray(keypoint_features(ring_rig, np.moveaxis(xy, 1, 0), np.moveaxis(score, 1, 0)))
    np.testing.assert_allclose(out, np.moveaxis(ref, 0, 1).reshape(2, 4, 3, 50), atol=1e-6)


def test_budget_of_a_batch_is_a_bucket():
    b = graph_budget(3, 3, 1)
    assert (b.nodes, b.dets) == (64, 16)


def test_next_quarter_bucket_is_the_smallest_of_its_sizes():
    sizes = sorted({1, 2, 4, 8} | {p * q // 4 for p in (8, 16, 32, 64, 128) for q in (5, 6, 7, 8)})
    for n in range(1, 257):
        assert next_quarter_bucket(n) == next(s for s in sizes if s >= n), n
    assert next_quarter_bucket(1025) == 1280  # a chunk of 256 frames of 4 people, and one more
