"""Losses, per item and unreduced (like optax's), plus the one masked reduction.

* `reprojection_error_l1`: the paper's self-supervised per-sample error: project the predicted
  keypoints into every TRAINING camera (lens distortion included) and sum the Manhattan distances
  to the detected keypoints; missing detections add nothing. The loss is ``mean_d e_d^2``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mvpose_jax.cameras import Rig, project_points


def masked_mean(values: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean of ``values`` where ``mask``; 0 (not NaN) when nothing is masked in."""
    mask = mask.astype(values.dtype)
    return jnp.sum(values * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def keypoint_l1(px: jax.Array, xy: jax.Array, seen: jax.Array) -> jax.Array:
    """Manhattan distance of each projected keypoint to its detection, 0 where none.

    Args:
      px: (..., K, 2) projected keypoints, pixels.
      xy: (..., K, 2) detected keypoints, pixels (junk allowed where not seen).
      seen: (..., K) bool, the keypoint was detected.
    Returns:
      (..., K) pixels.
    """
    # Double-where: missing detections may hold junk, keep it out of values and gradients.
    diff = jnp.where(seen[..., None], px - jnp.where(seen[..., None], xy, 0.0), 0.0)
    return jnp.abs(diff).sum(-1)


def reprojection_error_l1(rig: Rig, xyz: jax.Array, xy: jax.Array, score: jax.Array) -> jax.Array:
    """Per-sample Manhattan reprojection error, summed over cameras and detected keypoints.

    Args:
      rig: the training cameras C_t.
      xyz: (N, K, 3) predicted keypoints, metres.
      xy: (N, C_t, K, 2) detected keypoints, pixels.
      score: (N, C_t, K) detection scores; 0 = not detected (contributes nothing).
    Returns:
      (N,) e_d in pixels.
    """
    px = jnp.moveaxis(project_points(rig, xyz), 0, 1)  # (N, C_t, K, 2)
    return jnp.sum(keypoint_l1(px, xy, score > 0), axis=(1, 2))


def reprojection_loss(rig: Rig, xyz: jax.Array, xy: jax.Array, score: jax.Array) -> jax.Array:
    """Per-sample loss e_d^2 (reduce with `masked_mean`). Shapes as `reprojection_error_l1`."""
    return jnp.square(reprojection_error_l1(rig, xyz, xy, score))


# =========================================================================== skeleton matching


def match_mse(scores: jax.Array, labels: jax.Array) -> jax.Array:
    """The matcher's per-node loss (paper: MSE): ``(score - label)^2``.

    Reduce with `masked_mean` over real match nodes only (``is_match & node_mask``).

    Args:
      scores: (N,) sigmoid outputs in [0, 1].
      labels: (N,) 0/1 targets.
    Returns:
      (N,) squared errors.
    """
    return jnp.square(scores - labels)
