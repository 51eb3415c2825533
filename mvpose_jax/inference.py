"""Inference: 3D poses of grouped people, batched; the triangulation baseline on the same groups.

People arrive grouped (by proposals, or by true identities for stage-only evaluation) as
``xy (N, C_i, K, 2)``, ``score (N, C_i, K)``. The estimator runs as one jitted, batched call over
all of them; N is padded to a power of two so a long recording compiles a handful of shapes, not one per
frame.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, undistort_points, up_vector
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.features import (
    NUM_KEYPOINT_FEATURES,
    assemble_features,
    estimator_inputs,
    keypoint_features,
)
from mvpose_jax.graphs import (
    GraphBatch,
    build_graphs,
    compose_samples,
    make_pool,
    match_table,
    next_power_of_two,
)
from mvpose_jax.models import to_world
from mvpose_jax.proposals import (
    CombinedConfig,
    Proposals,
    choose_combined_threshold,
    choose_geometric_cutoff,
    choose_proposal_threshold,
    propose_combined,
    propose_people,
)
from mvpose_jax.skeletons import Detections, Poses3D, get_layout, leg_chains
from mvpose_jax.smoothing import OneEuroConfig, one_euro_frames, one_euro_initial, one_euro_keep
from mvpose_jax.tracking import TrackingConfig, track_frames
from mvpose_jax.tracking import initial_state as tracker_initial_state
from mvpose_jax.trained import Estimator, Matcher
from mvpose_jax.triangulate import (
    MAX_SPREAD_M,
    OUTLIER_PX,
    VIEW_OUTLIER_PX,
    blend_skeletons,
    camera_pairs,
    human_sized,
    triangulate_pairwise_centroid,
    triangulate_points,
    triangulate_skeletons_robust,
)

# The triangulation methods of the 3D stage without an estimator.
TRIANGULATION_METHODS = ("dlt", "centroid", "robust")
# The methods of the 3D stage with an estimator: its own output, or robust triangulation where it
# reconstructs a keypoint and the estimator elsewhere (`triangulate.blend_skeletons`).
ESTIMATOR_METHODS = ("mlp", "blend")

# Models are called through jit-compiled functions with their NNX GraphDef closed over, one per
# GraphDef: passed as a static argument, a GraphDef is hashed on every call, and hashing one
# costs about 70 µs (a twentieth of a frame's 3D stage). Equal GraphDefs share one function (and
# its compiled programs); the id cache keeps a strong reference, so an id is never reused.
_BOUND_BY_ID: dict[tuple, tuple] = {}
_BOUND_BY_VALUE: dict[tuple, Callable] = {}
_MAX_BOUND = 256


def bound_model_fn(fn: Callable, graphdef) -> Callable:
    """``jax.jit(functools.partial(fn, graphdef))``, built once per (fn, GraphDef).

    ``fn(graphdef, *args)`` must be a pure function of arrays besides its GraphDef.
    """
    hit = _BOUND_BY_ID.get((fn, id(graphdef)))
    if hit is not None and hit[0] is graphdef:
        return hit[1]
    if len(_BOUND_BY_ID) >= _MAX_BOUND:
        _BOUND_BY_ID.clear()
        _BOUND_BY_VALUE.clear()
    jitted = _BOUND_BY_VALUE.get((fn, graphdef))
    if jitted is None:
        jitted = _BOUND_BY_VALUE[(fn, graphdef)] = jax.jit(functools.partial(fn, graphdef))
    _BOUND_BY_ID[(fn, id(graphdef))] = (graphdef, jitted)
    return jitted


def _predict_fn(graphdef, rest, params, rig: Rig, normalisation, xy, score):
    centre, radius = normalisation
    inputs = estimator_inputs(rig, xy, score, normalisation)
    feats = assemble_features(inputs, (score > 0).any(axis=-1))
    return to_world(nnx.merge(graphdef, params, rest)(feats), centre, radius)


def _blend_fn(graphdef, rest, params, rig: Rig, normalisation, xy, score, thresholds, legs, up):
    """Method "blend": robust triangulation once, as the estimator's initial 3D (in place of the
    pairwise centroid it was trained on: on validation scenes that helped on every shift, most
    with wrong groupings) and where it reconstructs a keypoint (`triangulate.blend_skeletons`)."""
    centre, radius = normalisation
    px, w = jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0)
    tri, ok, kept = triangulate_skeletons_robust(
        rig, px, w, outlier_px=thresholds[0], view_outlier_px=thresholds[1]
    )
    initial = ((tri - centre.reshape(1, 1, 3)) / radius, ok)
    inputs = estimator_inputs(rig, xy, score, normalisation)
    feats = assemble_features(inputs, (score > 0).any(axis=-1), initial)
    model = to_world(nnx.merge(graphdef, params, rest)(feats), centre, radius)
    return blend_skeletons(
        rig, px, w, model_xyz=model, tri_xyz=tri, tri_valid=ok, kept=kept, legs=legs, up=up
    )


def predict_people(
    estimator: Estimator,
    xy: np.ndarray,
    score: np.ndarray,
    *,
    method: str = "mlp",
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
    layout: str = "coco18",
    mesh: jax.sharding.Mesh | None = None,
) -> np.ndarray:
    """3D keypoints of N people from their views in the estimator's inference cameras.

    Args:
      estimator: a trained `Estimator`.
      xy: (N, C_i, K, 2) pixels; score: (N, C_i, K), 0 = missing.
      method: "mlp", the estimator's output; or "blend", robust triangulation
        (`triangulate.triangulate_skeletons_robust` with ``outlier_px``, ``view_outlier_px``)
        where it reconstructs a keypoint and the estimator, given it as its initial 3D,
        elsewhere (`triangulate.blend_skeletons`, legs placed by their bones' lengths).
      layout: the keypoints' layout ("blend": where the legs are).
      mesh: optional data mesh (`parallel.make_data_mesh`): people are split over its devices
        (padded to a multiple of the device count), parameters replicated.
    Returns:
      (N, K, 3) metres: every keypoint, seen or not.
    """
    return _estimate_people(
        estimator,
        xy,
        score,
        method=method,
        outlier_px=outlier_px,
        view_outlier_px=view_outlier_px,
        layout=layout,
        mesh=mesh,
    )[0]


def _estimate_people(
    estimator: Estimator,
    xy: np.ndarray,
    score: np.ndarray,
    *,
    method: str,
    outlier_px: float,
    view_outlier_px: float,
    layout: str,
    mesh: jax.sharding.Mesh | None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """`predict_people`, with (method "blend") which keypoints robust triangulation gave (N, K)
    bool; None for "mlp"."""
    if method not in ESTIMATOR_METHODS:
        raise ValueError(f"method must be one of {ESTIMATOR_METHODS}, not {method!r}")
    fn = _predict_fn if method == "mlp" else _blend_fn
    extra = ()
    if method == "blend":
        lay = get_layout(layout)
        if lay.num_keypoints != np.shape(score)[-1]:
            raise InputError(
                f"layout {lay.name!r} has {lay.num_keypoints} keypoints, the people "
                f"{np.shape(score)[-1]}",
                field="layout",
            )
        thresholds = np.array([outlier_px, view_outlier_px], np.float32)
        up = np.asarray(up_vector(estimator.rig_infer), np.float32)
        extra = (thresholds, leg_chains(lay), up)
    xy_p, score_p = _pad_people(xy, score)
    jitted = bound_model_fn(fn, estimator.graphdef)
    if mesh is None:
        out = jitted(
            estimator.rest,
            estimator.params,
            estimator.rig_infer,
            estimator.normalisation,
            xy_p,
            score_p,
            *extra,
        )
        return _unpadded(out, np.asarray, len(xy))
    # Local imports: this function is the only place inference needs the mesh helpers.
    from mvpose_jax.parallel import mesh_size, pad_leading, replicate, shard_batch, to_host

    n = mesh_size(mesh)
    xy_p, score_p = shard_batch(
        mesh, (pad_leading(xy_p, n), pad_leading(score_p, n))
    )  # (B, ...) split
    out = jitted(
        estimator.rest,
        replicate(mesh, estimator.params),
        estimator.rig_infer,
        replicate(mesh, estimator.normalisation),
        xy_p,
        score_p,
        *(replicate(mesh, e) for e in extra),
    )
    return _unpadded(out, to_host, len(xy))


def _unpadded(out, to_numpy, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    """A model function's output (xyz, or "blend"'s (xyz, from triangulation)) as host arrays of
    the ``n`` real people."""
    if isinstance(out, tuple):
        return to_numpy(out[0])[:n], to_numpy(out[1])[:n]
    return to_numpy(out)[:n], None


def _pad_people(xy: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, C, K, 2) / (N, C, K) zero-padded to `graphs.next_power_of_two(N)` people, float32 numpy.

    Host arrays: the jitted call they go to moves them to the device itself, for less than an
    explicit transfer per array costs.
    """
    n = len(xy)
    xy_p = np.zeros((next_power_of_two(n),) + np.shape(xy)[1:], np.float32)
    score_p = np.zeros((next_power_of_two(n),) + np.shape(score)[1:], np.float32)
    xy_p[:n], score_p[:n] = xy, score
    return xy_p, score_p


def triangulate_people(
    rig: Rig,
    xy: np.ndarray,
    score: np.ndarray,
    method: str = "centroid",
    *,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
) -> tuple[np.ndarray, np.ndarray]:
    """The triangulation baseline on grouped people.

    Args:
      rig: the C cameras of the views.
      xy: (N, C, K, 2); score: (N, C, K).
      method: "centroid" (the paper's pairwise centroid), "dlt" (score-weighted DLT) or "robust"
        (score-weighted DLT that rejects a person's wrong views, then each keypoint's outlier
        views: `triangulate.triangulate_skeletons_robust`).
      outlier_px, view_outlier_px: "robust" only: the keypoint and whole-view thresholds, px.
    Returns:
      xyz (N, K, 3) and keypoint_valid (N, K): which keypoints two or more views reconstructed.
    """
    if method not in TRIANGULATION_METHODS:
        raise ValueError(f"method must be one of {TRIANGULATION_METHODS}, not {method!r}")
    xy_p, score_p = _pad_people(xy, score)
    px, w = np.moveaxis(xy_p, 1, 0), np.moveaxis(score_p, 1, 0)
    if method == "robust":
        xyz, ok, _ = triangulate_skeletons_robust(
            rig, px, w, outlier_px=outlier_px, view_outlier_px=view_outlier_px
        )
    else:
        fn = {"centroid": triangulate_pairwise_centroid, "dlt": triangulate_points}[method]
        xyz, ok = fn(rig, px, w)
    return np.asarray(xyz)[: len(xy)], np.asarray(ok)[: len(xy)]


def poses_from_people(xyz: np.ndarray, keypoint_valid: np.ndarray, exists: np.ndarray) -> Poses3D:
    """Packs per-person results (F, G, K, 3) / (F, G, K) / (F, G) into `Poses3D` (numpy).

    The one gate every 3D result leaves through: a non-finite keypoint (degenerate geometry) is
    flagged invalid and zeroed, and a person left with no valid keypoint does not exist, so no
    NaN or inf ever leaves inference.
    """
    xyz = np.asarray(xyz)
    kv = keypoint_valid & exists[..., None] & np.isfinite(xyz).all(axis=-1)
    exists = exists & kv.any(axis=-1)
    return Poses3D(
        np.where(kv[..., None], xyz, 0.0).astype(np.float32), exists.astype(bool), kv.astype(bool)
    )


def estimate_grouped(
    estimator: Estimator,
    xy: np.ndarray,
    score: np.ndarray,
    min_views: int = 2,
    method: str = "mlp",
    *,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
    layout: str = "coco18",
    max_spread_m: float = MAX_SPREAD_M,
) -> tuple[Poses3D, np.ndarray]:
    """Estimator poses for people grouped per frame, (F, G, C_i, K, ...) in, `Poses3D` out.

    A person exists when at least ``min_views`` inference views (1 with a single inference
    camera) have a skeleton of them and, with method "blend", its triangulated keypoints are no
    larger than a body (`triangulate.human_sized` with ``max_spread_m``: a group of two people's
    views is not a person). ``method``, ``outlier_px``, ``view_outlier_px``, ``layout``:
    `predict_people`'s.

    Returns:
      (poses, confidence (F, G): the mean detection score of the person's keypoints).
    """
    F, G, C, K = score.shape
    exists = _present(score, min_views)
    out = np.zeros((F, G, K, 3), np.float32)
    if exists.any():
        out[exists], from_tri = _estimate_people(
            estimator,
            xy[exists],
            score[exists],
            method=method,
            outlier_px=outlier_px,
            view_outlier_px=view_outlier_px,
            layout=layout,
            mesh=None,
        )
        if from_tri is not None:
            exists[exists] = _body_sized(out[exists], from_tri, max_spread_m)
    poses = poses_from_people(out, np.ones((F, G, K), bool), exists)
    return poses, _confidence(score)


def triangulate_grouped(
    rig: Rig,
    xy: np.ndarray,
    score: np.ndarray,
    method: str = "centroid",
    min_views: int = 2,
    *,
    max_spread_m: float = MAX_SPREAD_M,
    **robust,
) -> tuple[Poses3D, np.ndarray]:
    """The triangulation baseline for grouped people (same grouping as `estimate_grouped`).

    With method "robust", a person whose triangulated keypoints are larger than a body
    (`triangulate.human_sized` with ``max_spread_m``) is not one: after its wrong views are
    rejected, what is left is the group itself. "dlt" and "centroid" keep every group: one wrong
    view among right ones stretches their skeleton too, and they are the plain baselines.
    ``robust``: `triangulate_people`'s thresholds for method "robust".
    """
    F, G, C, K = score.shape
    exists = _present(score, min_views)
    out = np.zeros((F, G, K, 3), np.float32)
    kv = np.zeros((F, G, K), bool)
    if exists.any():
        out[exists], kv[exists] = triangulate_people(
            rig, xy[exists], score[exists], method, **robust
        )
    exists = exists & kv.any(axis=-1)
    if method == "robust":
        exists[exists] = _body_sized(out[exists], kv[exists], max_spread_m)
    return poses_from_people(out, kv, exists), _confidence(score)


def _body_sized(xyz: np.ndarray, valid: np.ndarray, max_spread_m: float) -> np.ndarray:
    """`triangulate.human_sized` of N people (N, K, 3) / (N, K), with a warning when it leaves
    out most of them: then the calibration's units, not the groups, are the likely cause."""
    keep = human_sized(xyz, valid, max_spread_m)
    dropped = int((~keep).sum())
    if dropped >= 2 and dropped > keep.size / 2:
        warnings.warn(
            f"most people triangulated larger than a body (keypoints a median of more than "
            f"{max_spread_m:g} m from their middle) and were left out: check the calibration's "
            "units (a translation in mm read as metres: --translation-scale 0.001)",
            MvposeWarning,
            stacklevel=2,
        )
    return keep


def _present(score: np.ndarray, min_views: int) -> np.ndarray:
    """(F, G) people with a skeleton in at least ``min_views`` views (all, with fewer cameras)."""
    views = (score > 0).any(axis=-1).sum(axis=-1)
    return views >= min(min_views, score.shape[-2])


def _confidence(score: np.ndarray) -> np.ndarray:
    seen = score > 0
    return np.where(seen, score, 0).sum(axis=(-1, -2)) / np.maximum(seen.sum(axis=(-1, -2)), 1)


# =========================================================================== skeleton matching
# (DESIGN.md §1.2) Match scores for many frames per jit call, then proposals (host-side union-find).
# A "match table" is the common currency of the learned and the geometric matcher: rows
# ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]`` (M, 5) and their scores (M,).


FRAMES_PER_CALL = 32


def _match_scores_fn(graphdef, rest, params, batch: GraphBatch) -> jax.Array:
    return nnx.merge(graphdef, params, rest)(batch)


def _match_scores(graphdef, rest, params, batch: GraphBatch) -> jax.Array:
    return bound_model_fn(_match_scores_fn, graphdef)(rest, params, batch)


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
    count_bytes: bytes, num_frames: int, num_cameras: int, num_skeletons: int, num_graphs: int
) -> _FrameGraphs:
    """The graphs of frames with these skeleton counts ((F, C) int64 as bytes)."""
    F, C, P = num_frames, num_cameras, num_skeletons
    count = np.frombuffer(count_bytes, np.int64).reshape(F, C)
    valid = np.arange(P)[None, None] < count[..., None]
    batch = build_graphs(np.zeros((F, C, P, 0), np.float32), valid, num_graphs=num_graphs)
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
    rows = jnp.moveaxis(feats, 0, 1).reshape(F * C * P, K * NUM_KEYPOINT_FEATURES)[
        det_source
    ]  # (D, K*10)
    in_slot = (det_camera[:, None] == jnp.arange(C)[None]) & batch.det_mask[:, None]  # (D, C)
    det = jnp.where(in_slot[..., None], rows[:, None, :], 0.0).reshape(rows.shape[0], -1)
    return nnx.merge(graphdef, params, rest)(batch._replace(det_features=det))


def gat_match_table(
    matcher: Matcher, detections: Detections, *, frames_per_call: int = FRAMES_PER_CALL
) -> tuple[np.ndarray, np.ndarray]:
    """Match scores of every cross-view skeleton pair of every frame, by the learned matcher.

    Frames go through the network ``frames_per_call`` at a time, as one padded graph batch each
    (a shorter chunk is padded with empty frames to the next power of two, so jit compiles a
    handful of shapes for a whole recording, and a single frame is one graph). Features and
    network run as one jit call; the graphs, which depend on the skeleton counts alone, are
    built once per count pattern and kept on the device.

    Args:
      matcher: a trained `Matcher`.
      detections: `Detections` with xy (F, C, P, K, 2) in the matcher's camera order
        (``matcher.rig.names``; use `data.select_cameras` on a recording).
    Returns:
      rows (M, 5) ``[frame, camera_a, skeleton_a, camera_b, skeleton_b]`` and scores (M,).
    """
    xy = np.asarray(detections.xy, np.float32)
    score = np.asarray(detections.score, np.float32)
    count = np.asarray(detections.count, np.int64)
    F, C, P, K = score.shape
    if matcher.rig.num_cameras != C:
        raise InputError(
            f"detections have {C} cameras, the matcher {matcher.rig.num_cameras}", field="cameras"
        )
    scores_fn = bound_model_fn(_frame_scores_fn, matcher.graphdef)
    rows, scores = [], []
    for start in range(0, F, frames_per_call):
        stop = min(F, start + frames_per_call)
        # A short (or single-frame) chunk is padded only to the next power of two of frames.
        n_graphs = min(frames_per_call, next_power_of_two(stop - start))
        xy_c, score_c = xy[start:stop], score[start:stop]
        if n_graphs > stop - start:
            xy_c = np.concatenate(
                [xy_c, np.zeros((n_graphs - (stop - start),) + xy.shape[1:], np.float32)]
            )
            score_c = np.concatenate(
                [score_c, np.zeros((n_graphs - (stop - start),) + score.shape[1:], np.float32)]
            )
        build = _single_frame_graphs if stop - start == 1 else _frame_graphs
        graphs = build(
            np.ascontiguousarray(count[start:stop]).tobytes(), stop - start, C, P, n_graphs
        )
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
        r = graphs.rows.copy()
        r[:, 0] += start
        rows.append(r)
        scores.append(np.asarray(out)[graphs.match_nodes])
    if not rows:
        return np.zeros((0, 5), np.int64), np.zeros(0, np.float32)
    return np.concatenate(rows), np.concatenate(scores)


@functools.partial(jax.jit, static_argnames=("min_shared", "median"))
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
            med = jnp.nanmedian(jnp.where(shared, 0.5 * (d_i + d_j), jnp.nan), axis=-1)
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
    C = np.shape(detections.score)[1]
    if len(rows) == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32)
    mean, median = _epipolar_dense(rig, detections, min_shared, frames_per_call, median=True)
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
    """`_epipolar_distances` of a whole recording, ``frames_per_call`` frames per jit call
    (shorter chunks padded to the next power of two): mean and (if ``median``) median,
    (Q, F, P, P) numpy."""
    xy = np.asarray(detections.xy, np.float32)
    score = np.asarray(detections.score, np.float32)
    F = len(score)
    means, medians = [], []
    for start in range(0, F, frames_per_call):
        stop = min(F, start + frames_per_call)
        pad = [(0, min(frames_per_call, next_power_of_two(stop - start)) - (stop - start))] + [
            (0, 0)
        ] * 3
        xy_c = np.moveaxis(np.pad(xy[start:stop], pad + [(0, 0)]), 1, 0)
        sc_c = np.moveaxis(np.pad(score[start:stop], pad), 1, 0)
        mean, med = _epipolar_distances(rig, xy_c, sc_c, min_shared=min_shared, median=median)
        means.append(np.asarray(mean)[:, : stop - start])
        if median:
            medians.append(np.asarray(med)[:, : stop - start])
    return np.concatenate(means, axis=1), np.concatenate(medians, axis=1) if median else None


def composed_frames(
    rig: Rig,
    recordings: Sequence,
    *,
    num_samples: int = 1024,
    seed: int = 0,
    max_people: int = 8,
    subset_probability: float = 0.5,
    min_views: int = 2,
    keypoint_dropout: float = 0.0,
) -> tuple[Detections, np.ndarray]:
    """Multi-person frames composed from single-person recordings, with their true identities.

    Composed as the matcher's training composes them (`graphs.compose_samples`), so held-out
    single-person recordings give a labelled multi-person set without a single label: the set
    every proposal setting is chosen on (the GAT's threshold, the epipolar matcher's cutoff).

    Args:
      rig: the cameras to compose in (every recording must hold them).
      recordings: single-person recordings.
      num_samples: composed frames; the other settings as `graphs.compose_samples`.
    Returns:
      (`Detections` (S, C, Q, ...) with each view's skeletons first, identity (S, C, Q): the
      frame's person of each skeleton, -1 for false detections and padding).
    """
    pool = make_pool(rig, recordings)
    _, valid, ident, xy, score = compose_samples(
        pool,
        np.random.default_rng([seed, 1 << 29]),
        num_samples,
        max_people=max_people,
        subset_probability=subset_probability,
        min_views=min_views,
        keypoint_dropout=keypoint_dropout,
        with_detections=True,
    )
    # Each view's skeletons first, padding after: the layout `count` describes.
    order = np.argsort(~valid, axis=-1, kind="stable")
    valid = np.take_along_axis(valid, order, axis=-1)
    xy = np.take_along_axis(xy, order[..., None, None], axis=2)
    score = np.take_along_axis(score, order[..., None], axis=2)
    ident = np.where(valid, np.take_along_axis(ident, order, axis=-1), -1)
    return Detections(
        xy.astype(np.float32), score.astype(np.float32), valid.sum(-1).astype(np.int32)
    ), ident


def composed_match_table(
    matcher: Matcher,
    recordings: Sequence,
    *,
    num_samples: int = 1024,
    seed: int = 0,
    frames_per_call: int = FRAMES_PER_CALL,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The matcher's scores on frames composed from single-person recordings (`composed_frames`,
    with the matcher's own composition settings), for `metrics.choose_proposal_threshold`.

    Returns:
      rows (M, 5) and scores (M,) as `gat_match_table`, identity (S, C, Q) and count (S, C).
    """
    det, ident = _composed_for(matcher, recordings, num_samples=num_samples, seed=seed)
    rows, scores = gat_match_table(matcher, det, frames_per_call=frames_per_call)
    return rows, scores, ident, np.asarray(det.count)


def _composed_for(
    matcher: Matcher, recordings: Sequence, *, num_samples: int, seed: int
) -> tuple[Detections, np.ndarray]:
    """`composed_frames` on the matcher's cameras with the matcher's own composition settings."""
    cfg = matcher.config
    return composed_frames(
        matcher.rig,
        recordings,
        num_samples=num_samples,
        seed=seed,
        max_people=cfg.max_people,
        subset_probability=cfg.subset_probability,
        min_views=cfg.min_views,
        keypoint_dropout=cfg.keypoint_dropout,
    )


def choose_matcher_threshold(
    matcher: Matcher, dev_recordings: Sequence, *, num_samples: int = 1024, seed: int = 0
) -> tuple[float, dict[float, float], int]:
    """A matcher's proposal threshold, chosen on frames composed from held-out single-person
    recordings (`composed_match_table`, `proposals.choose_proposal_threshold`).

    Returns:
      (the threshold, {threshold: per-frame ARI}, number of composed frames).
    """
    rows, scores, identity, count = composed_match_table(
        matcher, dev_recordings, num_samples=num_samples, seed=seed
    )
    threshold, ari = choose_proposal_threshold(rows, scores, identity, count)
    return threshold, ari, len(count)


class MatcherSettings(NamedTuple):
    """A matcher's proposal settings chosen on frames composed from dev recordings
    (`choose_matcher_settings`), with the per-frame ARI of every candidate."""

    threshold: float  # the GAT's proposal threshold
    ari_by_threshold: dict[float, float]
    geometric_cutoff_px: float  # the epipolar matcher's cutoff on the matcher's cameras
    ari_by_cutoff_px: dict[float, float]
    combined: CombinedConfig  # the combined matcher (its threshold and cutoff chosen here)
    ari_by_combined_threshold: dict[float, float]
    composed_frames: int


def choose_matcher_settings(
    matcher: Matcher,
    dev_recordings: Sequence,
    *,
    num_samples: int = 1024,
    seed: int = 0,
    combined: CombinedConfig = CombinedConfig(),
) -> MatcherSettings:
    """Every proposal setting of a matcher by one rule (the best per-frame ARI) on one set of
    frames composed from held-out single-person recordings: the GAT's threshold, the epipolar
    cutoff on the matcher's cameras, then the combined matcher's threshold at that cutoff
    (``combined``'s weight and half-score distance kept).
    """
    det, identity = _composed_for(matcher, dev_recordings, num_samples=num_samples, seed=seed)
    count = np.asarray(det.count)
    rows, scores = gat_match_table(matcher, det)
    threshold, ari = choose_proposal_threshold(rows, scores, identity, count)
    mean, median, shared = epipolar_distances_of_rows(matcher.rig, det, rows)
    cutoff, ari_cut = choose_geometric_cutoff(rows, mean, identity, count)
    config = dataclasses.replace(combined, epipolar_cutoff_px=cutoff)
    th, ari_comb = choose_combined_threshold(
        rows, scores, mean, median, identity, count, config=config, shared_keypoints=shared
    )
    return MatcherSettings(
        threshold,
        ari,
        cutoff,
        ari_cut,
        dataclasses.replace(config, threshold=th),
        ari_comb,
        len(count),
    )


# How a pipeline with a learned matcher makes its proposals: the GAT's scores alone (the paper's),
# the epipolar matcher alone (on the matcher's cameras), or both (`proposals.propose_combined`).
PROPOSAL_MODES = ("gat", "epipolar", "combined")


def propose_with_matcher(
    matcher: Matcher,
    detections: Detections,
    *,
    threshold: float = 0.5,
    min_views: int = 2,
    mode: str = "gat",
    combined: CombinedConfig | None = None,
) -> Proposals:
    """`gat_match_table` then `propose_people` (single-camera matchers: one person per skeleton).

    With ``mode="combined"`` the GAT's scores are joined with the pairs' epipolar distances on
    the matcher's cameras (`proposals.propose_combined`, settings ``combined``, default
    `CombinedConfig()`; ``threshold`` is not used).
    """
    if mode not in ("gat", "combined"):
        raise ValueError(f"mode must be 'gat' or 'combined', not {mode!r}")
    count = np.asarray(detections.count)
    P = np.shape(detections.score)[2]
    if matcher.rig.num_cameras == 1:
        rows, scores = np.zeros((0, 5), np.int64), np.zeros(0)
    else:
        rows, scores = gat_match_table(matcher, detections)
    if mode == "combined":
        mean, median, shared = epipolar_distances_of_rows(matcher.rig, detections, rows)
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
        rows, scores, count, num_skeletons=P, threshold=threshold, min_views=min_views
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


# =========================================================================== the pipeline
# Detections of many frames -> match scores -> proposals -> per-person inputs -> 3D poses.
# Frames go through in chunks: every stage is batched over a chunk (padded, so a long recording
# compiles a handful of shapes), and memory is bounded by the chunk, not the recording.


class PipelineResult(NamedTuple):
    """3D people of F frames and the detections each was built from.

    poses: `Poses3D` with xyz (F, G, K, 3) metres, valid (F, G), keypoint_valid (F, G, K); G is
      the most people in any frame (padded; ``valid`` says which exist).
    confidence: (F, G) mean detection score of each person's keypoints.
    members: (F, G, C) int32: each person's skeleton index in each proposal camera, -1 none.
    identity: (F, C, P) int32: the person of each detected skeleton, -1 none.
    cameras: the proposal cameras (the C axis of ``members`` and ``identity``).
    seconds: wall time of each stage over all frames, {"proposals": s, "poses": s} (and
      "tracking": s when tracked).
    track: (F, G) int32 each person's track id over the whole stream (-1 none), or None
      when not tracked (`tracking`).
    """

    poses: Poses3D
    confidence: np.ndarray
    members: np.ndarray
    identity: np.ndarray
    cameras: tuple[str, ...]
    seconds: dict[str, float]
    track: np.ndarray | None = None


def group_people(
    xy: np.ndarray, score: np.ndarray, members: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Gathers each proposed person's skeletons: xy (F, C, P, K, 2), score (F, C, P, K) and
    members (F, G, C) -> xy (F, G, C, K, 2), score (F, G, C, K) (zeros where a person has no
    skeleton in a camera)."""
    F, C, P, K = np.shape(score)
    f = np.arange(F)[:, None, None]
    c = np.arange(C)[None, None, :]
    p = np.maximum(members, 0)
    have = members >= 0
    return (
        np.where(have[..., None, None], np.asarray(xy)[f, c, p], 0.0).astype(np.float32),
        np.where(have[..., None], np.asarray(score)[f, c, p], 0.0).astype(np.float32),
    )


def poses_of_members(
    rig: Rig,
    detections: Detections,
    members: np.ndarray,
    *,
    estimator: Estimator | None = None,
    method: str | None = None,
    min_views: int = 2,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
    layout: str = "coco18",
    max_spread_m: float = MAX_SPREAD_M,
) -> tuple[Poses3D, np.ndarray]:
    """The 3D stage on given person groupings (proposals, or any other).

    Args:
      rig: the C cameras of the detections and of ``members``.
      detections: xy (F, C, P, K, 2), score (F, C, P, K).
      members: (F, G, C) each person's skeleton index per camera, -1 none.
      estimator: a trained estimator, on its inference cameras (found by name in ``rig``), for
        the methods "mlp" and "blend".
      method: "mlp" (the estimator's output) or "blend" (robust triangulation where it
        reconstructs a keypoint, the estimator elsewhere; `predict_people`), both with an
        estimator; or a triangulation of keypoints seen in 2+ views ("dlt", "centroid" or
        "robust", see `triangulate_people`). Default: "mlp" with an estimator, else "dlt".
      min_views: a person needs skeletons in this many (inference) views.
      outlier_px, view_outlier_px: the thresholds of robust triangulation (methods "robust" and
        "blend"; `triangulate_people`).
      layout: the keypoints' layout (method "blend", `predict_people`).
      max_spread_m: methods "robust" and "blend": a person whose robustly triangulated keypoints
        lie farther than this (median, metres) from their median point is not one
        (`triangulate.human_sized`; a group of two people's views, often metres large); inf: no
        such check.
    Returns:
      (`Poses3D` (F, G, ...), confidence (F, G)).
    Raises:
      ValueError: an unknown method, or "mlp" / "blend" without an estimator.
    """
    method = check_method(method, estimator)
    p_xy, p_score = group_people(detections.xy, detections.score, members)
    robust = {"outlier_px": outlier_px, "view_outlier_px": view_outlier_px}
    if method in TRIANGULATION_METHODS:
        return triangulate_grouped(
            rig, p_xy, p_score, method, min_views, max_spread_m=max_spread_m, **robust
        )
    if tuple(rig.names) != tuple(estimator.rig_infer.names):
        idx = _camera_columns(rig.names, estimator.rig_infer.names, "the estimator's inference")
        p_xy, p_score = p_xy[:, :, idx], p_score[:, :, idx]
    if method == "mlp":
        return estimate_grouped(estimator, p_xy, p_score, min_views)
    return estimate_grouped(
        estimator,
        p_xy,
        p_score,
        min_views,
        method,
        **robust,
        layout=layout,
        max_spread_m=max_spread_m,
    )


def check_method(method: str | None, estimator: Estimator | None) -> str:
    """The 3D method to run: ``method``, or the default ("mlp" with an estimator, else "dlt").

    Raises:
      ValueError: an unknown method, or an estimator method without an estimator.
    """
    if method is None:
        return "mlp" if estimator is not None else "dlt"
    if method in ESTIMATOR_METHODS and estimator is None:
        raise ValueError(f"method {method!r} needs an estimator")
    if method not in TRIANGULATION_METHODS + ESTIMATOR_METHODS:
        raise ValueError(
            f"method must be one of {TRIANGULATION_METHODS + ESTIMATOR_METHODS}, not {method!r}"
        )
    return method


def _camera_columns(names: Sequence[str], wanted: Sequence[str], what: str) -> list[int]:
    missing = [c for c in wanted if c not in names]
    if missing:
        raise InputError(
            f"{what} cameras {missing} are not among the detections' cameras {list(names)}",
            field="cameras",
        )
    return [list(names).index(c) for c in wanted]


def stream_pipeline(
    rig: Rig,
    detections: Detections | Iterable[tuple[int, Detections]],
    *,
    matcher: Matcher | None = None,
    estimator: Estimator | None = None,
    method: str | None = None,
    proposals: str | None = None,
    combined: CombinedConfig | None = None,
    threshold: float = 0.5,
    min_views: int = 2,
    half_score_px: float = 30.0,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
    layout: str = "coco18",
    max_spread_m: float = MAX_SPREAD_M,
    chunk_frames: int = 256,
    progress: bool = False,
    num_frames: int | None = None,
    tracking: TrackingConfig | None = None,
    one_euro: OneEuroConfig | None = None,
    fps: float = 30.0,
    first_track_id: int = 0,
) -> Iterator[tuple[int, PipelineResult]]:
    """The pipeline over a recording, one chunk of frames at a time: yields (first frame, result).

    Args:
      rig: the cameras of the detections, in their order (``rig.names``).
      detections: the whole recording, xy (F, C, P, K, 2) pixels, score (F, C, P, K), count
        (F, C), cut into chunks of ``chunk_frames``; or the chunks themselves, an iterable of
        (first frame, `Detections`) (e.g. from `mvpose_jax.data.RecordingStream.chunks`: then
        only one chunk is in memory at a time, and ``chunk_frames`` is not used).
      matcher: proposals from this learned matcher, on its cameras (``matcher.rig.names``); None:
        the geometric matcher (symmetric epipolar distance, ``half_score_px``) on every camera.
      proposals: how proposals are made (`PROPOSAL_MODES`): "combined" (the default with a
        ``matcher``: its scores joined with epipolar geometry, `proposals.propose_combined`,
        never worse than the epipolar matcher on the domain-shift experiment's validation
        scenes), "gat" (its scores alone, ``threshold``; the paper's) or "epipolar" (the default
        without a matcher: symmetric epipolar distance, ``half_score_px``, on the matcher's
        cameras if there is one).
      combined: the combined matcher's settings (default `CombinedConfig()`; a trained matcher's
        are in its folder: `proposals.read_combined_config`).
      estimator: a trained estimator, on its inference cameras (a subset of the proposal
        cameras), for the methods "mlp" and "blend".
      method: the 3D stage (`poses_of_members`): with an estimator "mlp" (its output, the
        default) or "blend" (robust triangulation where it reconstructs a keypoint, the
        estimator elsewhere); or triangulation of every keypoint seen in 2+ views: "dlt" (the
        default without an estimator), "centroid" (the paper's pairwise centroid), or "robust"
        (DLT that rejects outlier views). A triangulation method ignores the estimator.
      threshold, min_views: the proposal step (`propose_people`).
      outlier_px, view_outlier_px: the thresholds of robust triangulation, methods "robust"
        and "blend" (`triangulate_people`).
      layout: the keypoints' layout (method "blend": `predict_people`).
      max_spread_m: people larger than a body are not people (`poses_of_members`).
      chunk_frames: frames per chunk (memory is bounded by it).
      progress: show a progress bar.
      num_frames: frames the chunks hold in all (the progress bar's length) when ``detections``
        is an iterable of chunks; default: unknown.
      tracking: persistent person ids (`tracking.track_frames`, with each person's 2D skeletons
        as evidence), the tracker's state carried from chunk to chunk; None: no tracks.
      one_euro: with ``tracking``, each track's keypoints are filtered causally by this One-Euro
        filter (`smoothing.one_euro_frames`, its state carried too); None: unfiltered.
      fps: frames per second (the tracker's and the filter's clock: frame i is at i / fps).
      first_track_id: the first new track's id (a resumed stream continues after the ids it gave).
    Raises:
      InputError: detections whose cameras or keypoints do not fit the rig or the models
        (checked before the first chunk of a whole recording, on each chunk of an iterable).
    """
    from tqdm.auto import tqdm

    mode = proposals or ("combined" if matcher is not None else "epipolar")
    if mode not in PROPOSAL_MODES:
        raise ValueError(f"proposals must be one of {PROPOSAL_MODES}, not {mode!r}")
    if mode != "epipolar" and matcher is None:
        raise ValueError(f"proposals {mode!r} need a matcher")
    prop_cams = tuple(matcher.rig.names) if matcher is not None else tuple(rig.names)
    prop_idx = _camera_columns(rig.names, prop_cams, "the matcher's")
    prop_rig = rig.select(list(prop_cams))
    method = check_method(method, estimator)
    if method in ESTIMATOR_METHODS:
        _camera_columns(prop_cams, estimator.rig_infer.names, "the estimator's inference")
    else:
        estimator = None  # a triangulation: the estimator is neither checked nor used
    checked_keypoints: list[int] = []

    def check(det: Detections) -> None:
        _, num_cameras, _, K = np.shape(det.score)
        if num_cameras != rig.num_cameras:
            raise InputError(
                f"detections have {num_cameras} cameras, the rig {rig.num_cameras}",
                field="cameras",
            )
        if checked_keypoints == [K]:
            return  # the models' keypoint counts cost a model merge: checked once
        for what, model, k_of in (
            ("matcher", matcher, _matcher_keypoints),
            ("estimator", estimator, _estimator_keypoints),
        ):
            if model is not None and k_of(model) != K:
                raise InputError(
                    f"the {what} was trained on {k_of(model)} keypoints, the detections have {K} "
                    "(convert the layout)",
                    field="keypoints",
                )
        checked_keypoints[:] = [K]

    if isinstance(detections, Detections):
        check(detections)
        chunks = _chunks_of(detections, chunk_frames)
        num_frames = len(detections.count)
    else:
        chunks = iter(detections)
    tracker, smoother = None, None  # made at the first chunk, which tells K
    bar = tqdm(
        total=num_frames, desc="pipeline", unit="frame", disable=not progress, dynamic_ncols=True
    )
    try:
        for start, chunk in chunks:
            check(chunk)
            det = Detections(
                np.asarray(chunk.xy, np.float32)[:, prop_idx],
                np.asarray(chunk.score, np.float32)[:, prop_idx],
                np.asarray(chunk.count)[:, prop_idx],
            )
            stop = start + len(det.count)
            t0 = time.perf_counter()
            if mode == "epipolar":
                grouped = propose_geometric(
                    prop_rig,
                    det,
                    threshold=threshold,
                    min_views=min_views,
                    half_score_px=half_score_px,
                )
            else:
                grouped = propose_with_matcher(
                    matcher,
                    det,
                    threshold=threshold,
                    min_views=min_views,
                    mode=mode,
                    combined=combined,
                )
            members = _members_table(grouped, stop - start, len(prop_cams))
            t1 = time.perf_counter()
            poses, conf = poses_of_members(
                prop_rig,
                det,
                members,
                estimator=estimator,
                method=method,
                min_views=min_views,
                outlier_px=outlier_px,
                view_outlier_px=view_outlier_px,
                layout=layout,
                max_spread_m=max_spread_m,
            )
            t2 = time.perf_counter()
            # A person is kept only where the 3D stage produced one; its members say so too.
            members = np.where(poses.valid[..., None], members, -1).astype(np.int32)
            identity = _identity_from_members(members, det.score.shape[:3])
            seconds, track = {"proposals": t1 - t0, "poses": t2 - t1}, None
            if tracking is not None:
                if tracker is None:
                    K = np.shape(det.score)[3]
                    tracker = dataclasses.replace(
                        tracker_initial_state(K, len(prop_cams)), next_id=first_track_id
                    )
                    smoother = one_euro_initial(K)
                tracker, smoother, track, poses = _track_chunk(
                    tracker, smoother, det, members, poses, start, fps, prop_rig, tracking, one_euro
                )
                seconds["tracking"] = time.perf_counter() - t2
            yield (
                start,
                PipelineResult(poses, conf, members, identity, prop_cams, seconds, track),
            )
            bar.update(stop - start)
    finally:
        bar.close()


def _track_chunk(tracker, smoother, det, members, poses, start, fps, rig, tracking, one_euro):
    """Tracks (and optionally One-Euro filters) one chunk: (tracker, smoother, track, poses)."""
    xy, score = group_people(det.xy, det.score, members)
    times = (start + np.arange(len(members))) / fps
    kv = np.asarray(poses.keypoint_valid)
    tracker, track = track_frames(
        tracker,
        times=times,
        xyz=poses.xyz,
        keypoint_valid=kv,
        valid=poses.valid,
        xy=xy,
        score=score,
        rig=rig,
        config=tracking,
    )
    if one_euro is not None:
        smoother, xyz = one_euro_frames(
            smoother, times=times, track=track, xyz=poses.xyz, keypoint_valid=kv, config=one_euro
        )
        smoother = one_euro_keep(smoother, tracker.ids)
        poses = poses._replace(xyz=np.where(kv[..., None], xyz, poses.xyz).astype(np.float32))
    return tracker, smoother, track, poses


def _chunks_of(detections: Detections, chunk_frames: int) -> Iterator[tuple[int, Detections]]:
    """A whole recording's detections as (first frame, chunk) pairs."""
    xy = np.asarray(detections.xy, np.float32)
    score = np.asarray(detections.score, np.float32)
    count = np.asarray(detections.count)
    for start in range(0, len(count), chunk_frames):
        stop = start + chunk_frames
        yield start, Detections(xy[start:stop], score[start:stop], count[start:stop])


def run_pipeline(rig: Rig, detections: Detections, **kwargs) -> PipelineResult:
    """`stream_pipeline` over a whole recording, its chunks joined (people padded to the most in
    any frame). Takes the same arguments."""
    parts = [r for _, r in stream_pipeline(rig, detections, **kwargs)]
    if not parts:
        F, C, P, K = np.shape(detections.score)
        cams = (
            tuple(kwargs["matcher"].rig.names)
            if kwargs.get("matcher") is not None
            else tuple(rig.names)
        )
        return PipelineResult(
            Poses3D(
                np.zeros((0, 1, K, 3), np.float32),
                np.zeros((0, 1), bool),
                np.zeros((0, 1, K), bool),
            ),
            np.zeros((0, 1), np.float32),
            np.zeros((0, 1, len(cams)), np.int32),
            np.zeros((0, len(cams), P), np.int32),
            cams,
            {"proposals": 0.0, "poses": 0.0},
            np.zeros((0, 1), np.int32) if kwargs.get("tracking") is not None else None,
        )
    return concat_results(parts)


def concat_results(parts: Sequence[PipelineResult]) -> PipelineResult:
    """Joins consecutive chunks' results along the frame axis (people padded to the largest G,
    skeletons of ``identity`` to the largest P)."""
    G = max(1, max(r.poses.valid.shape[1] for r in parts))
    P = max(np.shape(r.identity)[2] for r in parts)

    def pad(a, fill=0):
        a = np.asarray(a)
        return np.pad(
            a, [(0, 0), (0, G - a.shape[1])] + [(0, 0)] * (a.ndim - 2), constant_values=fill
        )

    cat = lambda get, fill=0: np.concatenate([pad(get(r), fill) for r in parts])  # noqa: E731
    poses = Poses3D(
        cat(lambda r: r.poses.xyz),
        cat(lambda r: r.poses.valid),
        cat(lambda r: r.poses.keypoint_valid),
    )
    seconds = {k: float(sum(r.seconds[k] for r in parts)) for k in parts[0].seconds}
    tracked = all(r.track is not None for r in parts)
    return PipelineResult(
        poses,
        cat(lambda r: r.confidence),
        cat(lambda r: r.members, -1),
        # Chunks read in ranges may differ in P (the most skeletons in a view of the range).
        np.concatenate([_pad_skeletons(r.identity, P) for r in parts]),
        parts[0].cameras,
        seconds,
        cat(lambda r: r.track, -1) if tracked else None,
    )


def _pad_skeletons(identity: np.ndarray, num_skeletons: int) -> np.ndarray:
    """(F, C, P) identity padded with -1 to P = ``num_skeletons``."""
    identity = np.asarray(identity)
    pad = num_skeletons - identity.shape[2]
    return np.pad(identity, [(0, 0), (0, 0), (0, pad)], constant_values=-1)


def _estimator_keypoints(estimator: Estimator) -> int:
    return nnx.merge(estimator.graphdef, estimator.params, estimator.rest).num_keypoints


def _matcher_keypoints(matcher: Matcher) -> int:
    model = nnx.merge(matcher.graphdef, matcher.params, matcher.rest)
    return (model.in_dim - 2) // (matcher.rig.num_cameras * NUM_KEYPOINT_FEATURES)


def _members_table(proposals: Proposals, num_frames: int, num_cameras: int) -> np.ndarray:
    """`Proposals.people` (per frame, ragged) as one (F, G, C) table, -1 padded."""
    G = max([1] + [len(p) for p in proposals.people])
    table = np.full((num_frames, G, num_cameras), -1, np.int32)
    for f, people in enumerate(proposals.people):
        table[f, : len(people)] = people
    return table


def members_from_identity(identity: np.ndarray, num_people: int) -> np.ndarray:
    """A per-detection assignment as the pipeline's person table (e.g. true proposals).

    Args:
      identity: (F, C, P) int, the person (0..G-1) of each skeleton, -1 for none.
      num_people: G, the size of the person axis.
    Returns:
      members (F, G, C): each person's skeleton index in each camera, -1 for none (the inverse
      of `PipelineResult.identity`).
    """
    F, C, _ = np.shape(identity)
    members = np.full((F, num_people, C), -1, np.int32)
    f, c, p = np.nonzero(np.asarray(identity) >= 0)
    members[f, np.asarray(identity)[f, c, p], c] = p
    return members


def _identity_from_members(members: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """(F, G, C) members -> (F, C, P) person of each skeleton (-1 none)."""
    identity = np.full(shape, -1, np.int32)
    f, g, c = np.nonzero(members >= 0)
    identity[f, c, members[f, g, c]] = g
    return identity
