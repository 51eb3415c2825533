"""Matching graphs (DESIGN.md §1.2): host-side numpy building, padded jraph batches, training samples.

One graph per frame. Detection nodes: one per skeleton per inference view. Match nodes: one per
unordered pair of detection nodes of DIFFERENT views. Edges: each match node is joined both ways
to its two detection nodes, and every node has a self-loop; detection nodes are never joined
directly. Within a graph the nodes are ordered detections first (by camera, then skeleton), then
match nodes; edges are self-loops first, then four per match node.

Node features are the paper's ``2 + C·K·10`` numbers: a one-hot [detection, match], then one
``K·10`` slot per camera, filled only in the slot of the node's own camera (`features
.keypoint_features`). A match node is all zeros but the one-hot. Stored factorised because the
slots are almost all zero: ``graphs.nodes`` holds the (N, 2) one-hot and ``det_features`` the
(D, C·K·10) camera slots of the detection nodes only. The GAT's first layer then multiplies the
square ``W1`` by detection rows alone (D ≈ N/10 in a crowded frame), the same numbers as the dense
product at a tenth of its cost; `dense_node_features` rebuilds the paper's (N, 2 + C·K·10) matrix.

Padding follows ``jraph.pad_with_graphs`` exactly (one padding graph holding every padding node
and edge, padding edges on the first padding node, then empty graphs) but is built directly,
vectorised over all frames of a batch. Budgets are powers of two and their halfway points, 1.5
times a power of two (`graph_budget`): a stream of random frames compiles a handful of shapes,
and padding costs at most a third of the work (a half with powers of two alone; the attention
layers' segment sums cost in proportion to the padded edges).

Training samples (`compose_samples`) put ``n`` single-person frames of ``n`` DIFFERENT recordings
into one frame; per view a recording's main skeleton (most keypoints) is its person, any other
skeleton a false detection; a match node is labelled 1 when both ends are main skeletons of the
same recording.

Letters: F frames (graphs), C cameras, P skeletons per view, K keypoints, N nodes, D detection
rows, E edges, G graphs (padded), R recordings, T pooled frames.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import jraph
import numpy as np

from mvpose_jax import compiled
from mvpose_jax.cameras import Rig
from mvpose_jax.errors import InputError
from mvpose_jax.features import NUM_KEYPOINT_FEATURES, keypoint_features

if TYPE_CHECKING:  # annotations only: importing data.recording loads every reader
    from mvpose_jax.data.recording import Recording

DETECTION, MATCH = 0, 1  # positions in the one-hot
MIN_NODES = 64
MIN_DETECTIONS = 16


class GraphBatch(NamedTuple):
    """Padded matching graphs of F frames (a jit-able pytree; numpy on the host).

    ``graphs`` is a jraph `GraphsTuple` padded as ``jraph.pad_with_graphs`` pads: the real graphs,
    one padding graph with every padding node and edge, then empty graphs.
    """

    graphs: jraph.GraphsTuple  # nodes (N, 2) one-hot; senders, receivers (E,); n_node, n_edge (G,)
    det_features: jax.Array  # (D, C*K*10) camera slots of detection rows; zeros on padding rows
    det_node: jax.Array  # (D,) int32 node id of each detection row (padding rows: a padding node)
    det_mask: jax.Array  # (D,) bool, real detection rows
    node_mask: jax.Array  # (N,) bool = jraph.get_node_padding_mask(graphs)
    is_match: jax.Array  # (N,) bool, real match nodes
    label: jax.Array  # (N,) float32 0/1 target of match nodes (0 elsewhere)
    pair: jax.Array  # (N, 2) int32 the two detection-node ids of a match node (-1 elsewhere)
    node_camera: jax.Array  # (N,) int32 camera of a detection node (-1 elsewhere)
    node_skeleton: jax.Array  # (N,) int32 skeleton index p in its view (-1 elsewhere)


@dataclasses.dataclass(frozen=True)
class Budget:
    """Padded sizes of a `GraphBatch`: nodes, detection rows, edges, graphs."""

    nodes: int
    dets: int
    edges: int
    graphs: int


def next_power_of_two(n: int) -> int:
    """The smallest power of two >= n (1 for n <= 1): padded sizes of people and frame batches,
    so a single frame's few people are not padded to a batch (the MLP's cost grows with the
    rows) and a long recording still compiles only log2(N) shapes."""
    return 1 << max(0, int(n - 1).bit_length())


def next_quarter_bucket(n: int) -> int:
    """The smallest size >= n among 1, 2, 4, 8 and, above, a power of two times 1.25, 1.5, 1.75
    or 2 (10, 12, 14, 16, 20, ...): padded sizes of large batches (a chunk's people) waste at
    most a quarter, not up to half, at four shapes per doubling of the batch."""
    p = next_power_of_two(n)
    if p <= 8:
        return p
    step = p // 8  # a quarter of the octave below p
    return p // 2 + step * -(-(n - p // 2) // step)


def next_bucket(n: int) -> int:
    """The smallest power of two or 1.5 times a power of two that is >= n (1, 2, 3, 4, 6, 8, 12, ...)."""
    p = next_power_of_two(n)
    return 3 * p // 4 if p >= 4 and n <= 3 * p // 4 else p


def graph_budget(num_dets: int, num_matches: int, num_graphs: int) -> Budget:
    """The bucket of a batch: node and detection budgets are `next_bucket` sizes.

    The edge budget follows from the node budget (every real node has a self-loop and every match
    node four more edges, so E = N + 4M <= 5N), which keeps the buckets one-dimensional in nodes
    and detections. Node and graph budgets leave room for `jraph.pad_with_graphs`' padding node
    and padding graph.
    """
    nodes = max(MIN_NODES, next_bucket(num_dets + num_matches + 1))
    dets = max(MIN_DETECTIONS, next_bucket(num_dets))
    return Budget(nodes=nodes, dets=dets, edges=5 * nodes, graphs=num_graphs + 1)


def detection_features(
    rig: Rig, xy: np.ndarray, score: np.ndarray, normalisation=None
) -> np.ndarray:
    """The 10 numbers per keypoint of every skeleton (`features.keypoint_features`), flattened.

    Args:
      rig: the C cameras of the views.
      xy: (F, C, P, K, 2) pixels; score: (F, C, P, K), 0 = missing.
      normalisation: (centre, radius) of the world vectors' frame; default the rig's own.
    Returns:
      (F, C, P, K*10) float32 numpy.
    """
    # One jit call with the axis moves inside: run eagerly, each move was a dispatch of its own,
    # and together they cost more than the features of a frame.
    # np.array: a writable copy, as before (np.asarray of a jax.Array is read-only).
    return np.array(
        _detection_features(
            rig, np.asarray(xy, np.float32), np.asarray(score, np.float32), normalisation
        )
    )


@compiled.jit
def _detection_features(rig: Rig, xy: jax.Array, score: jax.Array, normalisation) -> jax.Array:
    F, C, P, K = score.shape
    feats = keypoint_features(
        rig, jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0), normalisation
    )  # (C, F, P, K, 10)
    return jnp.moveaxis(feats, 0, 1).reshape(F, C, P, K * NUM_KEYPOINT_FEATURES)


def build_graphs(
    features: np.ndarray,
    valid: np.ndarray,
    identity: np.ndarray | None = None,
    *,
    num_graphs: int | None = None,
    budget: Budget | None = None,
) -> GraphBatch:
    """Builds the padded matching graphs of F frames, vectorised over frames.

    Args:
      features: (F, C, P, K*10) per-skeleton features (`detection_features`).
      valid: (F, C, P) bool, the skeleton exists (a detection node).
      identity: optional (F, C, P) int, the person of each skeleton, -1 for a false detection;
        match labels are 1 where both ends share a person >= 0. None: all labels 0.
      num_graphs: graphs the batch must hold (>= F; default F): fix it to keep one graph budget.
      budget: explicit padded sizes (default `graph_budget` of the batch).
    Returns:
      A `GraphBatch` of numpy arrays; graph f is frame f.
    Raises:
      InputError when ``budget`` is too small.
    """
    features = np.asarray(features, np.float32)
    valid = np.asarray(valid, bool)
    F, C, P, KF = features.shape
    num_graphs = F if num_graphs is None else num_graphs
    if num_graphs < F:
        raise InputError(f"num_graphs {num_graphs} < {F} frames", field="num_graphs")
    ident = np.full((F, C, P), -1, np.int64) if identity is None else np.asarray(identity, np.int64)

    # Detection rows in (frame, camera, skeleton) order: graph-contiguous, as jraph needs.
    f_d, c_d, p_d = np.nonzero(valid)  # (D,)
    D = len(f_d)
    n_det = np.bincount(f_d, minlength=F)  # (F,)
    det_start = np.concatenate([[0], np.cumsum(n_det)[:-1]])
    local = np.arange(D) - det_start[f_d]  # index of the detection within its frame

    # Every pair (i < j) of a frame's detections from different cameras is a match node.
    width = max(1, int(n_det.max(initial=0)))
    slot = np.full((F, width), -1, np.int64)
    slot[f_d, local] = np.arange(D)
    cam = np.append(c_d, -1)[slot]  # (F, width); slot -1 picks the appended -1
    i_idx, j_idx = np.triu_indices(width, k=1)
    ok = (slot[:, i_idx] >= 0) & (slot[:, j_idx] >= 0) & (cam[:, i_idx] != cam[:, j_idx])
    f_m, q = np.nonzero(ok)  # (M,) sorted by frame
    a_row, b_row = slot[f_m, i_idx[q]], slot[f_m, j_idx[q]]
    M = len(f_m)
    n_match = np.bincount(f_m, minlength=F)

    n_node = n_det + n_match
    node_start = np.concatenate([[0], np.cumsum(n_node)[:-1]])
    det_node = node_start[f_d] + local  # (D,)
    match_start = np.concatenate([[0], np.cumsum(n_match)[:-1]])
    match_node = node_start[f_m] + n_det[f_m] + (np.arange(M) - match_start[f_m])  # (M,)
    a_node, b_node = det_node[a_row], det_node[b_row]
    N_real = int(n_node.sum())

    # Edges, grouped by graph: its self-loops, then det->match, det->match, match->det, match->det.
    loops = np.arange(N_real)
    loop_graph = np.repeat(np.arange(F), n_node)
    m_send = np.stack([a_node, b_node, match_node, match_node], axis=1).reshape(-1)
    m_recv = np.stack([match_node, match_node, a_node, b_node], axis=1).reshape(-1)
    senders = np.concatenate([loops, m_send])
    receivers = np.concatenate([loops, m_recv])
    order = np.argsort(np.concatenate([loop_graph, np.repeat(f_m, 4)]), kind="stable")
    senders, receivers = senders[order], receivers[order]
    n_edge = n_node + 4 * n_match
    E_real = len(senders)

    budget = budget or graph_budget(D, M, num_graphs)
    if budget.nodes <= N_real or budget.edges < E_real or budget.graphs <= F or budget.dets < D:
        raise InputError(
            f"budget {budget} too small for {N_real} nodes, {D} detections, {E_real} edges, "
            f"{F} graphs",
            field="budget",
        )
    N, E, G, Db = budget.nodes, budget.edges, budget.graphs, budget.dets
    pad_node = N_real  # first padding node: jraph points every padding edge at it

    kind = np.zeros((N, 2), np.float32)
    kind[det_node, DETECTION] = 1.0
    kind[match_node, MATCH] = 1.0
    graph_n_node = np.zeros(G, np.int32)
    graph_n_edge = np.zeros(G, np.int32)
    graph_n_node[:F], graph_n_edge[:F] = n_node, n_edge
    graph_n_node[F], graph_n_edge[F] = N - N_real, E - E_real
    graphs = jraph.GraphsTuple(
        nodes=kind,
        edges=None,
        senders=np.concatenate([senders, np.full(E - E_real, pad_node)]).astype(np.int32),
        receivers=np.concatenate([receivers, np.full(E - E_real, pad_node)]).astype(np.int32),
        n_node=graph_n_node,
        n_edge=graph_n_edge,
        globals=None,
    )

    det_features = np.zeros((Db, C, KF), np.float32)
    det_features[np.arange(D), c_d] = features[f_d, c_d, p_d]
    det_node_p = np.full(Db, pad_node, np.int32)
    det_node_p[:D] = det_node
    det_mask = np.arange(Db) < D

    node_mask = np.arange(N) < N_real
    is_match = np.zeros(N, bool)
    is_match[match_node] = True
    person = ident[f_d, c_d, p_d]  # (D,)
    label = np.zeros(N, np.float32)
    label[match_node] = ((person[a_row] >= 0) & (person[a_row] == person[b_row])).astype(np.float32)
    pair = np.full((N, 2), -1, np.int32)
    pair[match_node, 0], pair[match_node, 1] = a_node, b_node
    node_camera = np.full(N, -1, np.int32)
    node_skeleton = np.full(N, -1, np.int32)
    node_camera[det_node], node_skeleton[det_node] = c_d, p_d

    return GraphBatch(
        graphs=graphs,
        det_features=det_features.reshape(Db, C * KF),
        det_node=det_node_p,
        det_mask=det_mask,
        node_mask=node_mask,
        is_match=is_match,
        label=label,
        pair=pair,
        node_camera=node_camera,
        node_skeleton=node_skeleton,
    )


def dense_node_features(batch: GraphBatch) -> np.ndarray:
    """The paper's node feature matrix (N, 2 + C*K*10): one-hot, then the camera slots."""
    kind = np.asarray(batch.graphs.nodes)
    dense = np.zeros((kind.shape[0], np.shape(batch.det_features)[1]), np.float32)
    mask = np.asarray(batch.det_mask)
    dense[np.asarray(batch.det_node)[mask]] = np.asarray(batch.det_features)[mask]
    return np.concatenate([kind, dense], axis=1)


def node_graph(batch: GraphBatch) -> np.ndarray:
    """Graph (frame) index of every node: (N,) int (padding nodes: the padding graph's index)."""
    n_node = np.asarray(batch.graphs.n_node)
    return np.repeat(np.arange(len(n_node)), n_node)


def match_table(batch: GraphBatch, scores: np.ndarray) -> np.ndarray:
    """The real match nodes as rows ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]``.

    Args:
      batch: a `GraphBatch`.
      scores: (N,) node outputs.
    Returns:
      (M, 5) int64 rows and (M,) float scores, in node order.
    """
    is_match = np.asarray(batch.is_match)
    pair = np.asarray(batch.pair)[is_match]
    cam, skel = np.asarray(batch.node_camera), np.asarray(batch.node_skeleton)
    frame = node_graph(batch)[is_match]
    rows = np.stack(
        [frame, cam[pair[:, 0]], skel[pair[:, 0]], cam[pair[:, 1]], skel[pair[:, 1]]], axis=1
    )
    return rows.astype(np.int64), np.asarray(scores)[is_match]


# --------------------------------------------------------------------------- training samples


@dataclasses.dataclass(frozen=True)
class SkeletonPool:
    """Single-person frames of R recordings, ready to be composed into training graphs.

    Host-side numpy; T = total frames of all recordings, P = the largest view's skeleton count.
    """

    features: np.ndarray  # (T, C, P, K*10) float32 per-skeleton features
    valid: np.ndarray  # (T, C, P) bool, the skeleton exists
    main: np.ndarray  # (T, C, P) bool, the main skeleton of its view (the recording's person)
    starts: np.ndarray  # (R,) first pooled frame of each recording
    lengths: np.ndarray  # (R,) frames of each recording
    xy: np.ndarray | None = None  # (T, C, P, K, 2) the detections themselves, pixels
    score: np.ndarray | None = None  # (T, C, P, K), 0 = missing

    @property
    def num_recordings(self) -> int:
        return len(self.starts)


def make_pool(rig: Rig, recordings: Sequence[Recording], normalisation=None) -> SkeletonPool:
    """Pools single-person recordings for `compose_samples`.

    Args:
      rig: the inference cameras C_i; every recording must have them (by name; others are
        dropped, order follows the rig).
      recordings: R >= 1 single-person recordings.
      normalisation: (centre, radius) of the features' world vectors (default the rig's own;
        a rig-agnostic matcher pretrains in metres, `features.rig_agnostic_frame`).
    Raises:
      InputError when a recording lacks a camera or has no frames, or keypoint counts differ.
    """
    if not recordings:
        raise InputError("no recordings to train the matcher on", field="recordings")
    feats, valid, main, lengths, raw_xy, raw_score = [], [], [], [], [], []
    K = None
    for r, rec in enumerate(recordings):
        missing = [c for c in rig.names if c not in rec.cameras]
        if missing:
            raise InputError(
                f"recording {r} lacks cameras {missing}", camera=missing[0], field="cameras"
            )
        if K is not None and rec.num_keypoints != K:
            raise InputError(
                f"recording {r} has {rec.num_keypoints} keypoints, others {K}", field="layout"
            )
        K = rec.num_keypoints
        idx = np.array([rec.cameras.index(c) for c in rig.names])
        det = rec.detections
        xy = np.asarray(det.xy, np.float32)[:, idx]
        score = np.asarray(det.score, np.float32)[:, idx]
        count = np.asarray(det.count)[:, idx]
        ok = np.arange(score.shape[2])[None, None] < count[..., None]  # (F, C, P)
        n_kp = np.where(ok, (score > 0).sum(-1), -1)
        # The view's main skeleton: the one with most keypoints (ties: the first listed).
        best = n_kp.argmax(-1)
        is_main = (np.arange(score.shape[2])[None, None] == best[..., None]) & ok
        feats.append(detection_features(rig, xy, score, normalisation))
        raw_xy.append(xy)
        raw_score.append(np.where(ok[..., None], score, 0.0))
        valid.append(ok)
        main.append(is_main)
        lengths.append(rec.num_frames)
    P = max(f.shape[2] for f in feats)
    pad = lambda a: np.pad(a, [(0, 0), (0, 0), (0, P - a.shape[2])] + [(0, 0)] * (a.ndim - 3))  # noqa: E731
    lengths = np.asarray(lengths, np.int64)
    if np.any(lengths == 0):
        raise InputError("a recording has no frames", field="recordings")
    return SkeletonPool(
        features=np.concatenate([pad(f) for f in feats]),
        valid=np.concatenate([pad(v) for v in valid]),
        main=np.concatenate([pad(m) for m in main]),
        starts=np.concatenate([[0], np.cumsum(lengths)[:-1]]),
        lengths=lengths,
        xy=np.concatenate([pad(a) for a in raw_xy]),
        score=np.concatenate([pad(a) for a in raw_score]),
    )


def compose_samples(
    pool: SkeletonPool,
    rng: np.random.Generator,
    num_samples: int,
    *,
    max_people: int = 8,
    subset_probability: float = 0.5,
    min_views: int = 2,
    keypoint_dropout: float = 0.0,
    with_detections: bool = False,
) -> tuple[np.ndarray, ...]:
    """Multi-person training frames from single-person ones (DESIGN.md §1.2), vectorised.

    Each sample takes ``n`` frames of ``n`` different recordings, ``n`` uniform in
    ``1..min(R, max_people)`` (the paper draws up to R; capping it keeps graphs the size of the
    test scenes, 1-8 people). With probability ``subset_probability`` only a random subset of the
    views is kept, of size uniform in ``min_views..C`` (view-subset augmentation: the network sees
    people missing from some views). With ``keypoint_dropout`` > 0, each skeleton loses each of
    its keypoints with a probability drawn uniformly in ``[0, keypoint_dropout)`` per skeleton
    (missing-keypoint augmentation: in multi-person scenes people hide each other's keypoints,
    which single-person recordings never show; a skeleton always keeps at least one keypoint).
    Labels do not change. At 0 (the paper) no random numbers are drawn for it.

    Returns:
      features (S, C, Q, K*10), valid (S, C, Q), identity (S, C, Q) with Q = n_max * P; identity
      is the sample's person slot for main skeletons and -1 for false detections. With
      ``with_detections`` also the composed skeletons themselves, xy (S, C, Q, K, 2) and score
      (S, C, Q, K) (0 where dropped, missing or not valid), drawn with the same random numbers.
    """
    R = pool.num_recordings
    n_max = max(1, min(R, max_people))
    S = num_samples
    _, C, P, KF = pool.features.shape
    n = rng.integers(1, n_max + 1, S)  # (S,)
    recs = np.argsort(rng.random((S, R)), axis=1)[:, :n_max]  # distinct recordings per sample
    frame = pool.starts[recs] + (rng.random((S, n_max)) * pool.lengths[recs]).astype(np.int64)
    active = np.arange(n_max)[None] < n[:, None]  # (S, n_max)

    # Views kept: all, or a random subset of min_views..C of them.
    k_views = np.minimum(C, min_views)
    size = rng.integers(k_views, C + 1, S)
    size = np.where(rng.random(S) < subset_probability, size, C)
    rank = np.argsort(np.argsort(rng.random((S, C)), axis=1), axis=1)
    kept = rank < size[:, None]  # (S, C)

    t = frame.reshape(-1)
    to_views = lambda a: np.moveaxis(a.reshape((S, n_max) + a.shape[1:]), 1, 2)  # noqa: E731
    feats = to_views(pool.features[t]).reshape(S, C, n_max * P, KF)
    valid = to_views(pool.valid[t]) & active[:, None, :, None] & kept[:, :, None, None]
    main = to_views(pool.main[t])
    keep = None
    if keypoint_dropout > 0:
        K = KF // NUM_KEYPOINT_FEATURES
        Q = n_max * P
        per_keypoint = feats.reshape(S, C, Q, K, NUM_KEYPOINT_FEATURES)
        rate = rng.random((S, C, Q, 1)) * keypoint_dropout
        keep = rng.random((S, C, Q, K)) >= rate
        # A skeleton whose every seen keypoint was drawn out keeps them all (detectors never
        # report an empty skeleton); [..., 0] is the visible flag.
        keep |= ~(keep & (per_keypoint[..., 0] > 0)).any(axis=-1, keepdims=True)
        feats = (per_keypoint * keep[..., None]).reshape(S, C, Q, KF)
    slot = np.broadcast_to(np.arange(n_max)[None, None, :, None], main.shape)
    identity = np.where(main, slot, -1)
    valid = valid.reshape(S, C, n_max * P)
    if not with_detections:
        return feats, valid, identity.reshape(S, C, n_max * P)
    K = pool.score.shape[-1]
    xy = to_views(pool.xy[t]).reshape(S, C, n_max * P, K, 2)
    score = to_views(pool.score[t]).reshape(S, C, n_max * P, K) * valid[..., None]
    if keep is not None:
        score = score * keep
    return feats, valid, identity.reshape(S, C, n_max * P), xy, score


def sample_batches(
    pool: SkeletonPool,
    rng: np.random.Generator,
    num_batches: int,
    graphs_per_batch: int,
    **compose_kwargs,
) -> list[GraphBatch]:
    """``num_batches`` padded training batches of ``graphs_per_batch`` composed frames each."""
    feats, valid, identity = compose_samples(
        pool, rng, num_batches * graphs_per_batch, **compose_kwargs
    )
    out = []
    for b in range(num_batches):
        sl = slice(b * graphs_per_batch, (b + 1) * graphs_per_batch)
        out.append(build_graphs(feats[sl], valid[sl], identity[sl]))
    return out


# --------------------------------------------------------------------------- splitting for devices


def split_graph_batch(batch: GraphBatch, num_shards: int) -> tuple[GraphBatch, np.ndarray]:
    """Splits a padded graph batch by whole graphs into ``num_shards`` batches of one budget, stacked.

    A graph batch cannot be cut along its node axis (edges, detection rows and pairs hold global
    node ids), so each shard gets whole graphs: the F real graphs in order, ceil(F / S) per shard
    (the last shards may hold fewer, or none), re-indexed from 0 and padded as
    `graphs.build_graphs` pads (one padding graph holding every padding node and edge, then empty
    graphs) to the largest shard's power-of-two budget. The GAT never mixes graphs and padding
    never changes real nodes' outputs, so every real node scores as in the whole batch. One shard
    is the batch itself when it was built with as many graphs as frames (training batches).
    Host-side numpy.

    Args:
      batch: a `GraphBatch` (numpy or jax arrays).
      num_shards: S >= 1, usually the device count.
    Returns:
      (the shards as one `GraphBatch` whose leaves have a leading (S,) axis; origin (S, N_s)
      int64: each shard node's id in ``batch``, -1 for padding).
    """
    b = jax.tree.map(np.asarray, batch)
    g = b.graphs
    n_node, n_edge = g.n_node.astype(np.int64), g.n_edge.astype(np.int64)
    nonempty = np.nonzero(n_node)[0]
    # jraph's rule: the last non-empty graph is the padding graph (it holds >= 1 padding node);
    # it and the empty graphs after it are padding, every graph before it is real.
    F = int(nonempty[-1]) if len(nonempty) else 0
    per = max(1, math.ceil(F / num_shards))
    node_start = np.concatenate([[0], np.cumsum(n_node)])
    edge_start = np.concatenate([[0], np.cumsum(n_edge)])
    real_dets = int(np.asarray(b.det_mask).sum())
    det_node = b.det_node[:real_dets]  # real rows come first, in node order

    ranges = []
    for s in range(num_shards):
        g0, g1 = min(F, s * per), min(F, (s + 1) * per)
        n0, n1 = int(node_start[g0]), int(node_start[g1])
        d0, d1 = (int(i) for i in np.searchsorted(det_node, [n0, n1]))
        ranges.append((g0, g1, n0, n1, int(edge_start[g0]), int(edge_start[g1]), d0, d1))
    max_nodes = max(r[3] - r[2] for r in ranges)
    max_dets = max(r[7] - r[6] for r in ranges)
    budget = graph_budget(max_dets, max_nodes - max_dets, per)
    N, E, D, G = budget.nodes, budget.edges, budget.dets, budget.graphs

    shards, origin = [], np.full((num_shards, N), -1, np.int64)
    for s, (g0, g1, n0, n1, e0, e1, d0, d1) in enumerate(ranges):
        n, e, d, k = n1 - n0, e1 - e0, d1 - d0, g1 - g0
        pad_node = n  # the first padding node: padding edges and rows point at it (as in jraph)

        def fill(a, size, value, count, start, shift=0):
            out = np.full((size,) + a.shape[1:], value, a.dtype)
            out[:count] = a[start : start + count] - shift
            return out

        def counts(a, total, used, g0=g0, g1=g1, k=k):
            return np.concatenate([a[g0:g1], [total - used], np.zeros(G - k - 1, a.dtype)])

        graphs = g._replace(
            nodes=fill(g.nodes, N, 0, n, n0),
            senders=fill(g.senders, E, pad_node, e, e0, n0),
            receivers=fill(g.receivers, E, pad_node, e, e0, n0),
            n_node=counts(g.n_node, N, n).astype(g.n_node.dtype),
            n_edge=counts(g.n_edge, E, e).astype(g.n_edge.dtype),
        )
        pair = fill(b.pair, N, -1, n, n0)
        pair[:n] = np.where(b.pair[n0:n1] >= 0, b.pair[n0:n1] - n0, -1)
        shards.append(
            GraphBatch(
                graphs=graphs,
                det_features=fill(b.det_features, D, 0, d, d0),
                det_node=fill(b.det_node, D, pad_node, d, d0, n0),
                det_mask=np.arange(D) < d,
                node_mask=np.arange(N) < n,
                is_match=fill(b.is_match, N, False, n, n0),
                label=fill(b.label, N, 0, n, n0),
                pair=pair,
                node_camera=fill(b.node_camera, N, -1, n, n0),
                node_skeleton=fill(b.node_skeleton, N, -1, n, n0),
            )
        )
        origin[s, :n] = np.arange(n0, n1)
    return jax.tree.map(lambda *a: np.stack(a), *shards), origin
