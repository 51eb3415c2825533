"""Inference: 3D poses of grouped people, batched; the triangulation baseline on the same groups.

People arrive grouped (by proposals, or by true identities for stage-only evaluation) as
``xy (N, C_i, K, 2)``, ``score (N, C_i, K)``. The estimator runs as one jitted, batched call over
all of them; N is padded to a power of two (at least 16) so a long recording compiles a handful
of shapes, not one per frame.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, rig_centre_and_radius
from mvpose_jax.features import assemble_features, estimator_inputs
from mvpose_jax.models import to_world
from mvpose_jax.skeletons import Poses3D
from mvpose_jax.train import Estimator
from mvpose_jax.triangulate import triangulate_pairwise_centroid, triangulate_points

MIN_BUCKET = 16


def bucket_size(n: int, minimum: int = MIN_BUCKET) -> int:
    """The padded batch size for n items: the next power of two, at least ``minimum``."""
    return max(minimum, 1 << max(0, int(n - 1).bit_length()))


@functools.partial(jax.jit, static_argnums=0)
def _predict(graphdef, rest, params, rig: Rig, xy, score):
    centre, radius = rig_centre_and_radius(rig)
    inputs = estimator_inputs(rig, xy, score)
    feats = assemble_features(inputs, (score > 0).any(axis=-1))
    return to_world(nnx.merge(graphdef, params, rest)(feats), centre, radius)


def predict_people(estimator: Estimator, xy: np.ndarray, score: np.ndarray) -> np.ndarray:
    """3D keypoints of N people from their views in the estimator's inference cameras.

    Args:
      estimator: a trained `Estimator`.
      xy: (N, C_i, K, 2) pixels; score: (N, C_i, K), 0 = missing.
    Returns:
      (N, K, 3) metres: every keypoint, seen or not.
    """
    n = len(xy)
    size = bucket_size(n)
    pad = [(0, size - n)] + [(0, 0)] * (np.ndim(xy) - 1)
    xy_p = jnp.asarray(np.pad(np.asarray(xy, np.float32), pad))
    score_p = jnp.asarray(np.pad(np.asarray(score, np.float32), pad[:-1]))
    out = _predict(estimator.graphdef, estimator.rest, estimator.params, estimator.rig_infer, xy_p, score_p)
    return np.asarray(out)[:n]


def triangulate_people(
    rig: Rig, xy: np.ndarray, score: np.ndarray, method: str = "centroid"
) -> tuple[np.ndarray, np.ndarray]:
    """The triangulation baseline on grouped people.

    Args:
      rig: the C cameras of the views.
      xy: (N, C, K, 2); score: (N, C, K).
      method: "centroid" (the paper's pairwise centroid) or "dlt" (score-weighted DLT).
    Returns:
      xyz (N, K, 3) and keypoint_valid (N, K): which keypoints two or more views reconstructed.
    """
    fn = {"centroid": triangulate_pairwise_centroid, "dlt": triangulate_points}[method]
    n = len(xy)
    size = bucket_size(n)
    pad = [(0, size - n)] + [(0, 0)] * (np.ndim(xy) - 1)
    xy_c = jnp.moveaxis(jnp.asarray(np.pad(np.asarray(xy, np.float32), pad)), 1, 0)
    score_c = jnp.moveaxis(jnp.asarray(np.pad(np.asarray(score, np.float32), pad[:-1])), 1, 0)
    xyz, ok = fn(rig, xy_c, score_c)
    return np.asarray(xyz)[:n], np.asarray(ok)[:n]


def poses_from_people(
    xyz: np.ndarray, keypoint_valid: np.ndarray, exists: np.ndarray
) -> Poses3D:
    """Packs per-person results (F, G, K, 3) / (F, G, K) / (F, G) into `Poses3D` (numpy)."""
    kv = keypoint_valid & exists[..., None]
    return Poses3D(np.where(kv[..., None], xyz, 0.0).astype(np.float32), exists.astype(bool), kv.astype(bool))


def estimate_grouped(
    estimator: Estimator, xy: np.ndarray, score: np.ndarray, min_views: int = 2
) -> tuple[Poses3D, np.ndarray]:
    """Estimator poses for people grouped per frame, (F, G, C_i, K, ...) in, `Poses3D` out.

    A person exists when at least ``min_views`` inference views (1 with a single inference
    camera) have a skeleton of them.

    Returns:
      (poses, confidence (F, G): the mean detection score of the person's keypoints).
    """
    F, G, C, K = score.shape
    views = (score > 0).any(axis=-1).sum(axis=-1)  # (F, G)
    exists = views >= min(min_views, C)
    flat_xy, flat_score = xy[exists], score[exists]
    out = np.zeros((F, G, K, 3), np.float32)
    if exists.any():
        out[exists] = predict_people(estimator, flat_xy, flat_score)
    poses = poses_from_people(out, np.ones((F, G, K), bool), exists)
    return poses, _confidence(score)


def triangulate_grouped(
    rig: Rig, xy: np.ndarray, score: np.ndarray, method: str = "centroid", min_views: int = 2
) -> tuple[Poses3D, np.ndarray]:
    """The triangulation baseline for grouped people (same grouping as `estimate_grouped`)."""
    F, G, C, K = score.shape
    views = (score > 0).any(axis=-1).sum(axis=-1)
    exists = views >= min(min_views, C)
    out = np.zeros((F, G, K, 3), np.float32)
    kv = np.zeros((F, G, K), bool)
    if exists.any():
        out[exists], kv[exists] = triangulate_people(rig, xy[exists], score[exists], method)
    exists = exists & kv.any(axis=-1)
    return poses_from_people(out, kv, exists), _confidence(score)


def _confidence(score: np.ndarray) -> np.ndarray:
    seen = score > 0
    return np.where(seen, score, 0).sum(axis=(-1, -2)) / np.maximum(seen.sum(axis=(-1, -2)), 1)
