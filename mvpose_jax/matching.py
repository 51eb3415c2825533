"""Skeleton matching: match tables (learned and epipolar) and the proposals made from them.

A "match table" is the common currency of the learned and the geometric matcher: rows
``[frame, camera_a, skeleton_a, camera_b, skeleton_b]`` (M, 5) and their scores (M,), many frames
per jit call (DESIGN.md §1.2); proposals group them into people (host-side union-find,
`proposals`). The ways of proposing are registered by name in `stages.PROPOSALS`; each is a
``propose_*`` function below with the registry's contract.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax import compiled
from mvpose_jax.cameras import Rig, undistort_points
from mvpose_jax.compiled import bound_model_fn
from mvpose_jax.errors import InputError
from mvpose_jax.features import NUM_KEYPOINT_FEATURES, keypoint_features
from mvpose_jax.graphs import (
    Budget,
    GraphBatch,
    build_graphs,
    graph_budget,
    match_table,
    next_power_of_two,
)
from mvpose_jax.models import MatchingGAT
from mvpose_jax.proposals import CombinedConfig, Proposals, propose_combined, propose_people
from mvpose_jax.skeletons import Detections, skeleton_slots, zero_padded
from mvpose_jax.trained import Matcher
from mvpose_jax.triangulate import camera_pairs, nanmedian_by_rank


@dataclasses.dataclass(frozen=True)
class MatchingConfig:
    """How skeletons are grouped into people.

    Attributes:
      proposals: a `stages.PROPOSALS` name; None: "combined" with a matcher, "epipolar" without.
      threshold: "gat" and "epipolar": the least match score that joins two skeletons.
      min_views: a person needs skeletons in this many views (`proposals.propose_people`).
      half_score_px: "epipolar": the symmetric epipolar distance (px) that scores 0.5.
      combined: "combined": its settings (None: `CombinedConfig()`; a trained matcher's are in
        its folder).
    """

    proposals: str | None = None
    threshold: float = 0.5
    min_views: int = 2
    half_score_px: float = 30.0
    combined: CombinedConfig | None = None

    def mode(self, has_matcher: bool) -> str:
        """The proposals to run: ``proposals``, or the default for a pipeline with or without a
        matcher."""
        return self.proposals or ("combined" if has_matcher else "epipolar")


FRAMES_PER_CALL = 32


def frame_chunks(num_frames: int, frames_per_call: int) -> tuple[list[tuple[int, int]], int]:
    """``num_frames`` frames cut into the fewest calls of at most ``frames_per_call`` frames, of
    (nearly) equal length, and the frames every call is padded to: the next power of two of the
    longest call (capped at ``frames_per_call``).

    Equal calls share one padded shape: cut 32 at a time, 300 frames would end in a call of 12
    frames, padded to 16 and compiled on its own (a recording's tail costs every jitted stage
    it meets a compilation of seconds); cut evenly they are ten calls of 30, all padded to 32.
    The frames of a call are independent graphs and rows, so the cut changes no result.

    Returns:
      ([(start, stop), ...] in order, the padded frames of every call).
    """
    if num_frames <= 0:
        return [], 0
    calls = -(-num_frames // frames_per_call)
    size, longer = divmod(num_frames, calls)  # the first ``longer`` calls take one frame more
    stops = np.cumsum([size + 1] * longer + [size] * (calls - longer))
    bounds = list(zip([0, *stops[:-1].tolist()], stops.tolist(), strict=True))
    return bounds, min(frames_per_call, next_power_of_two(size + (longer > 0)))


def _match_scores_fn(graphdef, rest, params, batch: GraphBatch) -> jax.Array:
    return nnx.merge(graphdef, params, rest)(batch)


def _match_scores(graphdef, rest, params, batch: GraphBatch) -> jax.Array:
    return bound_model_fn(_match_scores_fn, graphdef, xla_kernels=True)(rest, params, batch)


def match_scores(
    matcher: Matcher, batch: GraphBatch, *, mesh: jax.sharding.Mesh | None = None
) -> np.ndarray:
    """The matcher's (N,) node scores for a padded batch of graphs (one jit call).

    With a data ``mesh`` (`parallel.make_data_mesh`) the graphs are split, whole, over its
    devices (`graphs.split_graph_batch`: one padded block per device, graphs padded to a multiple
    of the device count) and the scores put back in ``batch``'s node order; padding nodes score 0.
    """
    if mesh is None:
        return np.asarray(_match_scores(matcher.graphdef, matcher.rest, matcher.params, batch))
    # Local imports: this function is the only place inference needs the mesh helpers.
    from mvpose_jax.graphs import split_graph_batch
    from mvpose_jax.models import stacked_match_scores
    from mvpose_jax.parallel import mesh_size, replicate, shard_batch, to_host

    stacked, origin = split_graph_batch(batch, mesh_size(mesh))  # (S, ...), origin (S, N_s)
    out = stacked_match_scores(
        matcher.graphdef, matcher.rest, replicate(mesh, matcher.params), shard_batch(mesh, stacked)
    )
    scores = np.zeros(np.shape(batch.node_mask), np.float32)
    real = origin >= 0
    scores[origin[real]] = to_host(out)[real]
    return scores


class _FrameGraphs(NamedTuple):
    """The matching graphs of a chunk of frames, without features: what depends on counts alone."""

    batch: GraphBatch  # device-resident; det_features has width 0
    det_source: jax.Array  # (D,) int32 flat (frame, camera, skeleton) index of each detection row
    det_camera: jax.Array  # (D,) int32 camera of each detection row
    match_nodes: np.ndarray  # (M,) node ids of the real match nodes
    rows: np.ndarray  # (M, 5) their ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]``


def _frame_graphs(
    count_bytes: bytes,
    num_frames: int,
    num_cameras: int,
    num_skeletons: int,
    num_graphs: int,
    budget: Budget | None = None,
) -> _FrameGraphs:
    """The graphs of frames with these skeleton counts ((F, C) int64 as bytes), padded to
    ``budget`` (default: `graphs.graph_budget` of the frames)."""
    F, C, P = num_frames, num_cameras, num_skeletons
    count = np.frombuffer(count_bytes, np.int64).reshape(F, C)
    valid = np.arange(P)[None, None] < count[..., None]
    batch = build_graphs(
        np.zeros((F, C, P, 0), np.float32), valid, num_graphs=num_graphs, budget=budget
    )
    node = batch.det_node
    frame = np.repeat(np.arange(len(batch.graphs.n_node)), batch.graphs.n_node)[node]
    cam, skel = batch.node_camera[node], batch.node_skeleton[node]
    source = np.where(batch.det_mask, (frame * C + cam) * P + skel, 0).astype(np.int32)
    rows, _ = match_table(batch, np.zeros(len(batch.node_mask), np.float32))
    return _FrameGraphs(
        jax.device_put(batch),
        jax.device_put(source),
        jax.device_put(np.maximum(cam, 0)),
        np.flatnonzero(batch.is_match),
        rows,
    )


class _GraphCache:
    """Least-recently-used single-frame graphs, bounded by their bytes (not by their number).

    One frame at a time (a live stream) meets a few hundred skeleton-count patterns over and over
    (a 200-frame, 5-view, 4-person synthetic recording: 61; 8 people: 133): cached, such a frame
    neither builds its graph nor moves it to the device (0.5 ms). A graph takes 20 KB (5 views, 6
    skeletons) to 340 KB (5 views, 16), so a count limit is either too small for small rigs or
    unbounded in memory for large ones. Multi-frame chunks rarely repeat (and amortise the build),
    so they are not kept.
    """

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._entries: collections.OrderedDict[tuple, tuple[_FrameGraphs, int]] = (
            collections.OrderedDict()
        )
        self._bytes = 0

    @staticmethod
    def _size(g: _FrameGraphs) -> int:
        return sum(int(getattr(x, "nbytes", 0)) for x in jax.tree.leaves(g))

    def __call__(self, *key) -> _FrameGraphs:
        entry = self._entries.get(key)
        if entry is not None:
            self._entries.move_to_end(key)
            return entry[0]
        g = _frame_graphs(*key)
        self._entries[key] = (g, self._size(g))
        self._bytes += self._entries[key][1]
        while self._bytes > self.max_bytes and len(self._entries) > 1:
            self._bytes -= self._entries.popitem(last=False)[1][1]
        return g

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()
        self._bytes = 0


_single_frame_graphs = _GraphCache(max_bytes=64 << 20)


def _largest_budget(count: np.ndarray, bounds: list[tuple[int, int]], num_graphs: int) -> Budget:
    """The largest `graphs.graph_budget` of the calls ``bounds`` cut ``count`` (F, C) into.

    All calls of a chunk then share one padded shape: a recording compiles one GAT program per
    chunk, not one per call's bucket (the main job's tracks section met 17 buckets in 8 scenes,
    2 s of compilation each). Padding changes no real node's score (tested bit for bit)."""
    budgets = []
    for start, stop in bounds:
        c = count[start:stop].astype(np.int64)
        per_frame = c.sum(1)
        pairs = (per_frame**2 - (c**2).sum(1)) // 2  # skeleton pairs of different cameras
        budgets.append(graph_budget(int(per_frame.sum()), int(pairs.sum()), num_graphs))
    return Budget(
        nodes=max(b.nodes for b in budgets),
        dets=max(b.dets for b in budgets),
        edges=max(b.edges for b in budgets),
        graphs=num_graphs + 1,
    )


def _frame_scores_fn(
    graphdef, rest, params, rig: Rig, xy, score, batch: GraphBatch, det_source, det_camera
):
    """Detection features (`graphs.detection_features`) and the GAT in one call.

    xy (F, C, P, K, 2), score (F, C, P, K) -> (N,) node scores of ``batch`` (the same numbers as
    `match_scores` on the batch `graphs.build_graphs` makes from the features).
    """
    F, C, P, K = score.shape
    feats = keypoint_features(
        rig, jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0)
    )  # (C, F, P, K, 10)
    model = nnx.merge(graphdef, params, rest)
    if isinstance(model, MatchingGAT) and F > 1:
        # The paper's camera slots: each camera's skeleton slots meet their own slot of W1
        # alone, then each detection row takes its slot's product. On a chunk that is the
        # fifth of the dense product's work it looks; on a live frame (one graph) the batched
        # small products and the gather cost more than they save (the GAT 1.3-1.4x slower
        # there, `benchmarks.ab`), so a single frame keeps the dense rows.
        per_slot = model.slot_products(feats.reshape(C, F * P, K * NUM_KEYPOINT_FEATURES))
        pre = jnp.moveaxis(per_slot.reshape(C, F, P, -1), 0, 1).reshape(F * C * P, -1)
        return model(batch, det_pre=pre[det_source])
    rows = jnp.moveaxis(feats, 0, 1).reshape(F * C * P, K * NUM_KEYPOINT_FEATURES)[
        det_source
    ]  # (D, K*10)
    in_slot = (det_camera[:, None] == jnp.arange(C)[None]) & batch.det_mask[:, None]  # (D, C)
    det = jnp.where(in_slot[..., None], rows[:, None, :], 0.0).reshape(rows.shape[0], -1)
    return model(batch._replace(det_features=det))


def _frame_scores_and_epipolar_fn(
    graphdef,
    rest,
    params,
    rig: Rig,
    xy,
    score,
    batch: GraphBatch,
    det_source,
    det_camera,
    min_shared: int,
):
    """`_frame_scores_fn` and the chunk's epipolar mean and median distances
    (`_epipolar_distances`, (Q, F, P, P)) in one call: the combined matcher needs both, and a
    live frame pays per launch and per fetch, not per number."""
    scores = _frame_scores_fn(graphdef, rest, params, rig, xy, score, batch, det_source, det_camera)
    mean, median = _epipolar_distances(
        rig,
        jnp.moveaxis(xy, 1, 0),
        jnp.moveaxis(score, 1, 0),
        min_shared=min_shared,
        median=True,
    )
    return scores, mean, median


@functools.cache
def _fused_fn(min_shared: int):
    """`_frame_scores_and_epipolar_fn` at ``min_shared`` (a Python int inside the jit), one
    object per value so that `compiled.bound_model_fn` compiles it once."""
    return functools.partial(_frame_scores_and_epipolar_fn, min_shared=min_shared)


def gat_match_table(
    matcher: Matcher, detections: Detections, *, frames_per_call: int = FRAMES_PER_CALL
) -> tuple[np.ndarray, np.ndarray]:
    """Match scores of every cross-view skeleton pair of every frame, by the learned matcher.

    Frames go through the network at most ``frames_per_call`` at a time, in calls of equal
    length (`frame_chunks`), each one padded graph batch (padded with empty frames to the next
    power of two, so jit compiles a handful of shapes for a whole recording, and a single frame
    is one graph). Features and
    network run as one jit call; the graphs, which depend on the skeleton counts alone, are
    built once per count pattern and kept on the device.

    Args:
      matcher: a trained `Matcher`.
      detections: `Detections` with xy (F, C, P, K, 2) in the matcher's camera order
        (``matcher.rig.names``; use `data.select_cameras` on a recording).
    Returns:
      rows (M, 5) ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]`` and scores (M,).
    """
    rows, scores, _, _ = _gat_tables(matcher, detections, frames_per_call, epipolar_min_shared=None)
    return rows, scores


def combined_match_tables(
    matcher: Matcher,
    detections: Detections,
    *,
    min_shared: int = 3,
    frames_per_call: int = FRAMES_PER_CALL,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`gat_match_table` and `epipolar_distances_of_rows` of its rows, in one jit call per chunk
    of frames (what the combined matcher reads).

    Returns:
      rows (M, 5), GAT scores (M,), mean and median epipolar distances (M,) pixels (inf where
      fewer than ``min_shared`` keypoints are shared), shared keypoints (M,) int32.
    """
    rows, scores, mean, median = _gat_tables(
        matcher, detections, frames_per_call, epipolar_min_shared=min_shared
    )
    if mean is None:  # no pair to score
        empty = np.zeros(0, np.float32)
        return rows, scores, empty, empty, np.zeros(0, np.int32)
    return (rows, scores) + _distances_of_rows(mean, median, rows, detections)


def _gat_tables(
    matcher: Matcher,
    detections: Detections,
    frames_per_call: int,
    *,
    epipolar_min_shared: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """`gat_match_table`'s rows and scores and, with ``epipolar_min_shared``, the dense epipolar
    mean and median (Q, F, P, P) of the same frames from the same calls (else None, None)."""
    xy = np.asarray(detections.xy, np.float32)
    score = np.asarray(detections.score, np.float32)
    count = np.asarray(detections.count, np.int64)
    F, C, P, K = score.shape
    if matcher.rig.num_cameras != C:
        raise InputError(
            f"detections have {C} cameras, the matcher {matcher.rig.num_cameras}", field="cameras"
        )
    with_epipolar = epipolar_min_shared is not None
    if with_epipolar:
        scores_fn = bound_model_fn(
            _fused_fn(epipolar_min_shared), matcher.graphdef, xla_kernels=True
        )
    else:
        scores_fn = bound_model_fn(_frame_scores_fn, matcher.graphdef, xla_kernels=True)
    rows, scores, means, medians = [], [], [], []
    bounds, n_graphs = frame_chunks(F, frames_per_call)
    # The pipeline's skeleton slots: a table of the same frames then reuses its programs.
    S = skeleton_slots(P)
    budget = _largest_budget(count, bounds, n_graphs) if len(bounds) > 1 else None
    for start, stop in bounds:
        xy_c = zero_padded(xy[start:stop], (n_graphs, C, S, K, 2))
        score_c = zero_padded(score[start:stop], (n_graphs, C, S, K))
        key = (np.ascontiguousarray(count[start:stop]).tobytes(), stop - start, C, S, n_graphs)
        graphs = _single_frame_graphs(*key) if stop - start == 1 else _frame_graphs(*key, budget)
        out = scores_fn(
            matcher.rest,
            matcher.params,
            matcher.rig,
            xy_c,
            score_c,
            graphs.batch,
            graphs.det_source,
            graphs.det_camera,
        )
        if with_epipolar:
            out, mean, median = jax.device_get(out)  # one fetch for the three
            means.append(mean[:, : stop - start, :P, :P])
            medians.append(median[:, : stop - start, :P, :P])
        r = graphs.rows.copy()
        r[:, 0] += start
        rows.append(r)
        scores.append(np.asarray(out)[graphs.match_nodes])
    if not rows:
        return np.zeros((0, 5), np.int64), np.zeros(0, np.float32), None, None
    if not with_epipolar:
        return np.concatenate(rows), np.concatenate(scores), None, None
    return (
        np.concatenate(rows),
        np.concatenate(scores),
        np.concatenate(means, axis=1),
        np.concatenate(medians, axis=1),
    )


@compiled.jit(static_argnames=("min_shared", "median"))
def _epipolar_distances(
    rig: Rig, xy: jax.Array, score: jax.Array, *, min_shared: int, median: bool = False
) -> tuple[jax.Array, jax.Array | None]:
    """Mean and median symmetric epipolar distance (px) of every skeleton pair of every camera pair.

    xy: (C, F, P, K, 2) distorted pixels; score: (C, F, P, K). Returns two (Q, F, P, P) (the
    median None unless ``median``), inf where fewer than ``min_shared`` keypoints are seen in
    both views. The median is the robust one: a few wrong keypoints (a limb of another person)
    do not move it.
    """
    u = undistort_points(rig, xy)
    u_h = jnp.concatenate([u, jnp.ones_like(u[..., :1])], axis=-1)  # (C, F, P, K, 3)
    k_inv = jnp.linalg.inv(rig.K)
    means, medians = [], []
    for i, j in camera_pairs(rig.num_cameras):
        r_rel = rig.R[j] @ rig.R[i].T
        t_rel = rig.t[j] - r_rel @ rig.t[i]
        tx = jnp.array(
            [[0.0, -t_rel[2], t_rel[1]], [t_rel[2], 0.0, -t_rel[0]], [-t_rel[1], t_rel[0], 0.0]]
        )
        fund = k_inv[j].T @ tx @ r_rel @ k_inv[i]  # x_j^T F x_i = 0
        line_j = jnp.einsum("ab,fpkb->fpka", fund, u_h[i])  # lines in view j of view i's points
        line_i = jnp.einsum("ba,fqkb->fqka", fund, u_h[j])
        num = jnp.abs(jnp.einsum("fpka,fqka->fpqk", line_j, u_h[j]))
        d_j = num / jnp.maximum(jnp.linalg.norm(line_j[..., :2], axis=-1), 1e-9)[:, :, None, :]
        d_i = num / jnp.maximum(jnp.linalg.norm(line_i[..., :2], axis=-1), 1e-9)[:, None, :, :]
        shared = (score[i] > 0)[:, :, None, :] & (score[j] > 0)[:, None, :, :]  # (F, P, P, K)
        n = shared.sum(-1)
        d = jnp.where(shared, 0.5 * (d_i + d_j), 0.0).sum(-1) / jnp.maximum(n, 1)
        means.append(jnp.where(n >= min_shared, d, jnp.inf))
        if median:
            med = nanmedian_by_rank(jnp.where(shared, 0.5 * (d_i + d_j), jnp.nan), axis=-1)
            medians.append(jnp.where(n >= min_shared, med, jnp.inf))
    return jnp.stack(means), jnp.stack(medians) if median else None


def geometric_match_table(
    rig: Rig,
    detections: Detections,
    *,
    half_score_px: float = 20.0,
    min_shared: int = 3,
    frames_per_call: int = FRAMES_PER_CALL,
) -> tuple[np.ndarray, np.ndarray]:
    """The non-learned baseline: scores from the symmetric epipolar distance of skeleton pairs.

    ``score = 2^(-d / half_score_px)`` of the pair's distance d (`epipolar_match_distances`) is 0.5
    at ``half_score_px`` (so the proposal threshold 0.5 means ``d < half_score_px``: the two
    settings act only through that one cutoff), and 0 when fewer than ``min_shared`` keypoints
    are shared.

    Args:
      rig: the C cameras of the detections, in their order.
      detections: xy (F, C, P, K, 2), score (F, C, P, K), count (F, C).
    Returns:
      rows (M, 5) and scores (M,), as `gat_match_table`.
    """
    rows, d = epipolar_match_distances(
        rig, detections, min_shared=min_shared, frames_per_call=frames_per_call
    )
    return rows, np.exp2(-d / half_score_px).astype(np.float32)


def epipolar_match_distances(
    rig: Rig, detections: Detections, *, min_shared: int = 3, frames_per_call: int = FRAMES_PER_CALL
) -> tuple[np.ndarray, np.ndarray]:
    """The symmetric epipolar distance of every cross-view skeleton pair of every frame.

    The distance of a pair is the mean, over keypoints seen in both views, of the symmetric
    epipolar distance of the undistorted pixels; inf when fewer than ``min_shared`` are shared.

    Returns:
      rows (M, 5) as `gat_match_table`, distances (M,) pixels.
    """
    count = np.asarray(detections.count)
    F, C, P, _ = np.shape(detections.score)
    pairs = camera_pairs(C)
    if C < 2 or F == 0:
        return np.zeros((0, 5), np.int64), np.zeros(0, np.float32)
    dist, _ = _epipolar_dense(rig, detections, min_shared, frames_per_call, median=False)
    ok = np.arange(P)[None, None] < count[..., None]  # (F, C, P)
    both = ok[:, pairs[:, 0], :, None] & ok[:, pairs[:, 1], None, :]  # (F, Q, P, P)
    f, q, pa, pb = np.nonzero(both)
    rows = np.stack([f, pairs[q, 0], pa, pairs[q, 1], pb], axis=1).astype(np.int64)
    return rows, dist[q, f, pa, pb]


def epipolar_distances_of_rows(
    rig: Rig,
    detections: Detections,
    rows: np.ndarray,
    *,
    min_shared: int = 3,
    frames_per_call: int = FRAMES_PER_CALL,
) -> tuple[np.ndarray, np.ndarray]:
    """The mean and the median symmetric epipolar distance of given skeleton pairs.

    Args:
      rig: the C cameras of the detections; detections: xy (F, C, P, K, 2), score (F, C, P, K).
      rows: (M, 5) ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]`` (e.g. a GAT table's).
    Returns:
      mean (M,) and median (M,) pixels over the keypoints seen in both views, inf when fewer
      than ``min_shared`` are; shared (M,) int32, how many keypoints both views see.
    """
    rows = np.asarray(rows, np.int64).reshape(-1, 5)
    if len(rows) == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32)
    mean, median = _epipolar_dense(rig, detections, min_shared, frames_per_call, median=True)
    return _distances_of_rows(mean, median, rows, detections)


def _distances_of_rows(
    mean: np.ndarray, median: np.ndarray, rows: np.ndarray, detections: Detections
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The dense (Q, F, P, P) mean and median tables at the pairs ``rows`` (M, 5), and how many
    keypoints each pair's two skeletons share."""
    C = np.shape(detections.score)[1]
    pairs = camera_pairs(C)
    pair_of = np.full((C, C), -1, np.int64)
    pair_of[pairs[:, 0], pairs[:, 1]] = np.arange(len(pairs))
    # The dense tables hold (lower camera, higher camera); a row may name them the other way.
    swap = rows[:, 1] > rows[:, 3]
    lo, hi = np.where(swap, rows[:, 3], rows[:, 1]), np.where(swap, rows[:, 1], rows[:, 3])
    p_lo, p_hi = np.where(swap, rows[:, 4], rows[:, 2]), np.where(swap, rows[:, 2], rows[:, 4])
    q = pair_of[lo, hi]
    seen = np.asarray(detections.score) > 0
    shared = (
        seen[rows[:, 0], rows[:, 1], rows[:, 2]] & seen[rows[:, 0], rows[:, 3], rows[:, 4]]
    ).sum(-1)
    return (
        mean[q, rows[:, 0], p_lo, p_hi],
        median[q, rows[:, 0], p_lo, p_hi],
        shared.astype(np.int32),
    )


def _epipolar_dense(
    rig: Rig, detections: Detections, min_shared: int, frames_per_call: int, *, median: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """`_epipolar_distances` of a whole recording, at most ``frames_per_call`` frames per jit call
    (`frame_chunks`): mean and (if ``median``) median, (Q, F, P, P) numpy."""
    xy = np.asarray(detections.xy, np.float32)
    score = np.asarray(detections.score, np.float32)
    F, C, P, K = score.shape
    S = skeleton_slots(P)  # the pipeline's slots, so that its programs serve here too
    means, medians = [], []
    bounds, n_frames = frame_chunks(F, frames_per_call)
    for start, stop in bounds:
        xy_c = np.moveaxis(zero_padded(xy[start:stop], (n_frames, C, S, K, 2)), 1, 0)
        sc_c = np.moveaxis(zero_padded(score[start:stop], (n_frames, C, S, K)), 1, 0)
        mean, med = _epipolar_distances(rig, xy_c, sc_c, min_shared=min_shared, median=median)
        means.append(np.asarray(mean)[:, : stop - start, :P, :P])
        if median:
            medians.append(np.asarray(med)[:, : stop - start, :P, :P])
    return np.concatenate(means, axis=1), np.concatenate(medians, axis=1) if median else None


def propose_with_matcher(
    matcher: Matcher,
    detections: Detections,
    *,
    threshold: float = 0.5,
    min_views: int = 2,
    mode: str = "gat",
    combined: CombinedConfig | None = None,
    repair_splits: bool = False,
) -> Proposals:
    """`gat_match_table` then `propose_people` (single-camera matchers: one person per skeleton;
    ``repair_splits``: `propose_people`'s).

    With ``mode="combined"`` the GAT's scores are joined with the pairs' epipolar distances on
    the matcher's cameras (`proposals.propose_combined`, settings ``combined``, default
    `CombinedConfig()`; ``threshold`` and ``repair_splits`` are not used).
    """
    if mode not in ("gat", "combined"):
        raise ValueError(f"mode must be 'gat' or 'combined', not {mode!r}")
    count = np.asarray(detections.count)
    P = np.shape(detections.score)[2]
    if matcher.rig.num_cameras == 1:  # no pair to score
        rows, scores = np.zeros((0, 5), np.int64), np.zeros(0)
        mean, median, shared = np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, int)
    elif mode == "combined":
        rows, scores, mean, median, shared = combined_match_tables(matcher, detections)
    else:
        rows, scores = gat_match_table(matcher, detections)
    if mode == "combined":
        proposals, _ = propose_combined(
            rows,
            scores,
            mean,
            median,
            count,
            shared_keypoints=shared,
            config=combined or CombinedConfig(),
            num_skeletons=P,
            min_views=min_views,
        )
        return proposals
    return propose_people(
        rows,
        scores,
        count,
        num_skeletons=P,
        threshold=threshold,
        min_views=min_views,
        repair_splits=repair_splits,
    )


def propose_geometric(
    rig: Rig, detections: Detections, *, threshold: float = 0.5, min_views: int = 2, **kwargs
) -> Proposals:
    """`geometric_match_table` then `propose_people`."""
    rows, scores = geometric_match_table(rig, detections, **kwargs)
    return propose_people(
        rows,
        scores,
        np.asarray(detections.count),
        num_skeletons=np.shape(detections.score)[2],
        threshold=threshold,
        min_views=min_views,
    )


# ------------------------------------------------------------------ the registered proposals
# `stages.PROPOSALS`' contract: the proposal cameras' rig and detections, the config and the
# matcher (None for a geometric one) in, `Proposals` out.


def propose_epipolar(rig: Rig, detections: Detections, config: MatchingConfig, *, matcher=None):
    """Registered proposals "epipolar": `propose_geometric` at ``config``'s cutoff."""
    del matcher
    return propose_geometric(
        rig,
        detections,
        threshold=config.threshold,
        min_views=config.min_views,
        half_score_px=config.half_score_px,
    )


def propose_gat(rig: Rig, detections: Detections, config: MatchingConfig, *, matcher: Matcher):
    """Registered proposals "gat": the matcher's scores alone (`propose_with_matcher`)."""
    del rig
    return propose_with_matcher(
        matcher, detections, threshold=config.threshold, min_views=config.min_views, mode="gat"
    )


def propose_gat_repaired(
    rig: Rig, detections: Detections, config: MatchingConfig, *, matcher: Matcher
):
    """Registered proposals "gat-repaired": the matcher's scores alone, grouped as "gat", then a
    person split over two groups by a duplicate or fragment skeleton in one view made one again
    (`proposals.propose_people`'s ``repair_splits``; no geometry)."""
    del rig
    return propose_with_matcher(
        matcher,
        detections,
        threshold=config.threshold,
        min_views=config.min_views,
        mode="gat",
        repair_splits=True,
    )


def propose_combined_matcher(
    rig: Rig, detections: Detections, config: MatchingConfig, *, matcher: Matcher
):
    """Registered proposals "combined": the matcher's scores joined with epipolar geometry
    (`propose_with_matcher` with mode "combined")."""
    del rig
    return propose_with_matcher(
        matcher,
        detections,
        threshold=config.threshold,
        min_views=config.min_views,
        mode="combined",
        combined=config.combined,
    )
