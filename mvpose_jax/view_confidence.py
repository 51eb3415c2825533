"""Learned confidence inside the geometry: p(inlier) of each (person, keypoint, view).

Robust triangulation (`triangulate.triangulate_skeletons_robust`) rejects a view by fixed
reprojection thresholds; an inverted or jittered wrist that stays under them is kept. Here a
small network scores each view of each keypoint from cues computable at inference, with no
label (`view_features`):

* the detection score;
* the view's reprojection error against the leave-this-view-out robust consensus
  (`triangulate.leave_one_view_out`), in pixels and relative to the person's size in the view,
  and against the all-view robust fit, with whether that fit kept the view;
* how many views see the keypoint, and how many the consensus kept;
* where it lies in the image (normalised position, distance to the border);
* the inversion cue: the left/right twin keypoint's error under swap against the consensus;
* the bone lengths to its neighbours in the view against the consensus's bones there.

The network sees no keypoint identity, so a model trained on the simulator's coco18 runs on any
layout. It is trained (`view_confidence_training`) with binary cross-entropy on synthetic
recordings made with the detector fitted to the user's recording (`detector_fit`): the
simulator knows which 2D keypoints it corrupted, free labels of "this view is an outlier".
`triangulate_confident` uses it: weights = score * p, views with p below a threshold dropped
(never below two views), then robust triangulation (or DLT).
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, project_points_per_camera
from mvpose_jax.checkpoints import Checkpoints, save_params_folder
from mvpose_jax.errors import InputError
from mvpose_jax.skeletons import Layout, get_layout
from mvpose_jax.triangulate import (
    OUTLIER_PX,
    VIEW_OUTLIER_PX,
    leave_one_view_out,
    triangulate_points,
    triangulate_skeletons_robust,
)

NUM_FEATURES = 14
CONFIG_FILE = "view_confidence.json"
# Keypoints of a view the person's image size is measured over (fewer: the size is unreliable).
_MIN_SIZE_PX = 20.0


@dataclasses.dataclass(frozen=True)
class ConfidenceConfig:
    """The network and its use.

    Attributes:
      widths: hidden layer widths of the per-view MLP.
      threshold: views with p(inlier) below it are dropped (never below two views); chosen on
        validation scenes (`view_confidence_training.choose_threshold`).
      then: what triangulates the kept, reweighted views: "robust" or "dlt".
    """

    widths: tuple[int, ...] = (64, 64)
    threshold: float = 0.5
    then: str = "robust"


class ConfidenceNet(nnx.Module):
    """Per-view MLP: features (..., NUM_FEATURES) -> logit of p(inlier) (...)."""

    def __init__(self, config: ConfidenceConfig, *, rngs: nnx.Rngs):
        sizes = (NUM_FEATURES, *config.widths)
        self.hidden = nnx.List(
            [nnx.Linear(a, b, rngs=rngs) for a, b in zip(sizes[:-1], sizes[1:], strict=True)]
        )
        self.out = nnx.Linear(sizes[-1], 1, rngs=rngs)

    def __call__(self, features: jax.Array) -> jax.Array:
        h = features
        for layer in self.hidden:
            h = nnx.gelu(layer(h))
        return self.out(h)[..., 0]


class ViewConfidence(NamedTuple):
    """A trained confidence model: split NNX parts and its config."""

    graphdef: Any
    rest: Any
    params: Any
    config: ConfidenceConfig


def init_model(config: ConfidenceConfig = ConfidenceConfig(), seed: int = 0) -> ViewConfidence:
    """An untrained model (the training's starting point)."""
    graphdef, params, rest = nnx.split(ConfidenceNet(config, rngs=nnx.Rngs(seed)), nnx.Param, ...)
    return ViewConfidence(graphdef, rest, params, config)


def layout_tables(layout: str | Layout) -> tuple[np.ndarray, np.ndarray]:
    """(K,) mirror indices and (B, 2) bones of a layout, as `view_features` takes them."""
    lay = get_layout(layout)
    bones = np.asarray(lay.bones, np.int32).reshape(-1, 2)
    return np.asarray(lay.flip, np.int32), bones


@jax.jit
def view_features(
    rig: Rig, xy: jax.Array, score: jax.Array, flip: jax.Array, bones: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """The label-free cues of each view of each keypoint of N grouped people.

    Args:
      rig: the C cameras.
      xy: (N, C, K, 2) distorted pixels; score: (N, C, K), 0 = not seen.
      flip: (K,) mirror keypoint indices; bones: (B, 2) keypoint pairs (`layout_tables`).
    Returns:
      features (N, C, K, NUM_FEATURES) float32 and seen (N, C, K) bool (score > 0).
    """
    px, w = jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0)  # (C, N, K, 2), (C, N, K)
    seen = w > 0
    C, K = w.shape[0], w.shape[-1]
    tri, ok, kept = triangulate_skeletons_robust(rig, px, w)  # (N, K, 3), (N, K), (C, N, K)
    loo, loo_ok, loo_views = leave_one_view_out(rig, px, w)  # (C, N, K, 3), (C, N, K)
    loo_ok = loo_ok & (loo_views >= 2)
    proj_loo = project_points_per_camera(rig, loo)  # (C, N, K, 2)
    proj_full = project_points_per_camera(rig, jnp.broadcast_to(tri, (C,) + tri.shape))
    junk = jnp.where(seen[..., None], px, 0.0)

    def dist(a, b):
        return jnp.sqrt(jnp.sum((a - b) ** 2, axis=-1))

    err_loo = jnp.where(loo_ok & seen, dist(junk, proj_loo), 0.0)
    err_full = jnp.where(ok[None] & seen, dist(junk, proj_full), 0.0)
    # The person's size in the view: the diagonal of its seen keypoints' box.
    lo = jnp.min(jnp.where(seen[..., None], px, jnp.inf), axis=-2)
    hi = jnp.max(jnp.where(seen[..., None], px, -jnp.inf), axis=-2)
    size = jnp.sqrt(jnp.sum(jnp.where(jnp.isfinite(hi - lo), hi - lo, 0.0) ** 2, axis=-1))
    size = jnp.maximum(size, _MIN_SIZE_PX)[..., None]  # (C, N, 1)
    # Inversion: the twin's detection against this keypoint's consensus.
    twin_xy, twin_seen = junk[..., flip, :], seen[..., flip]
    has_twin = (flip != jnp.arange(K))[None, None] & twin_seen & loo_ok & seen
    err_swap = dist(twin_xy, proj_loo)
    swap_cue = jnp.where(has_twin, jnp.log((err_swap + 5.0) / (err_loo + 5.0)), 0.0)
    # Bones in the view against the consensus's bones projected there.
    a, b = bones[:, 0], bones[:, 1]
    both = seen[..., a] & seen[..., b] & ok[None][..., a] & ok[None][..., b]
    det_len = dist(junk[..., a, :], junk[..., b, :])
    con_len = dist(proj_full[..., a, :], proj_full[..., b, :])
    bone_dev = jnp.where(both, jnp.abs(jnp.log((det_len + 2.0) / (con_len + 2.0))), 0.0)
    incident = (a[:, None] == jnp.arange(K)[None]) | (b[:, None] == jnp.arange(K)[None])  # (B, K)
    bone_dev = jnp.max(
        jnp.where(incident[None, None], bone_dev[..., :, None], 0.0), axis=-2, initial=0.0
    )
    wh = rig.size.reshape(C, 1, 1, 2)
    pos = junk / wh
    border = jnp.min(jnp.stack([pos[..., 0], 1 - pos[..., 0], pos[..., 1], 1 - pos[..., 1]]), 0)
    n_seen = jnp.broadcast_to(seen.sum(0), seen.shape).astype(jnp.float32)
    feats = jnp.stack(
        [
            w,
            jnp.log1p(err_loo / 10.0),
            jnp.log1p(20.0 * err_loo / size),
            loo_ok.astype(jnp.float32),
            jnp.log1p(err_full / 10.0),
            kept.astype(jnp.float32),
            swap_cue,
            n_seen / 4.0,
            loo_views / 4.0,
            pos[..., 0],
            pos[..., 1],
            4.0 * jnp.clip(border, -0.25, 0.5),
            jnp.minimum(bone_dev, 3.0),
            jnp.broadcast_to(jnp.log1p(size / 100.0), w.shape),
        ],
        axis=-1,
    )
    feats = jnp.where(seen[..., None] & jnp.isfinite(feats), feats, 0.0).astype(jnp.float32)
    return jnp.moveaxis(feats, 0, 1), jnp.moveaxis(seen, 0, 1)


def inlier_logits(model: ViewConfidence, features: jax.Array) -> jax.Array:
    """Logits of p(inlier), features (..., NUM_FEATURES) -> (...)."""
    return nnx.merge(model.graphdef, model.params, model.rest)(features)


@functools.partial(jax.jit, static_argnums=0)
def _probabilities(graphdef, rest, params, rig, xy, score, flip, bones):
    feats, seen = view_features(rig, xy, score, flip, bones)
    p = jax.nn.sigmoid(nnx.merge(graphdef, params, rest)(feats))
    return jnp.where(seen, p, 0.0)


def inlier_probability(
    model: ViewConfidence, rig: Rig, xy, score, layout: str | Layout = "coco18"
) -> np.ndarray:
    """p(inlier) (N, C, K) of grouped people xy (N, C, K, 2), score (N, C, K); 0 where unseen."""
    flip, bones = layout_tables(layout)
    return np.asarray(
        _probabilities(
            model.graphdef,
            model.rest,
            model.params,
            rig,
            jnp.asarray(xy, jnp.float32),
            jnp.asarray(score, jnp.float32),
            flip,
            bones,
        )
    )


def confident_weights(weight: jax.Array, p: jax.Array, threshold: float) -> jax.Array:
    """score * p on the views whose p reaches ``threshold``; where fewer than two seen views
    do, the two most likely seen views stay (a keypoint two views see is never lost by this).

    Args:
      weight: (C, ...) scores, 0 = not seen; p: (C, ...) p(inlier).
    Returns:
      (C, ...) weights, 0 = dropped or not seen.
    """
    seen = weight > 0
    keep = seen & (p >= threshold)
    ranked = jnp.where(seen, p, -1.0)
    second = -jnp.sort(-ranked, axis=0)[jnp.minimum(1, ranked.shape[0] - 1)]
    top2 = seen & (ranked >= second[None])
    keep = jnp.where((keep.sum(0) >= 2)[None], keep, top2)
    return jnp.where(keep, weight * p, 0.0)


def triangulate_confident(
    rig: Rig,
    px: jax.Array,
    weight: jax.Array,
    p: jax.Array,
    *,
    threshold: float = 0.5,
    then: str = "robust",
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
) -> tuple[jax.Array, jax.Array]:
    """Triangulation weighted by learned confidence (`confident_weights`), then robust or DLT.

    Args:
      rig: the C cameras.
      px: (C, ..., K, 2) distorted pixels; weight: (C, ..., K) scores; p: (C, ..., K) p(inlier).
      threshold: views below it are dropped (never below two seen views).
      then: "robust" (`triangulate.triangulate_skeletons_robust`) or "dlt".
    Returns:
      xyz (..., K, 3) metres, valid (..., K).
    """
    w = confident_weights(jnp.asarray(weight), jnp.asarray(p), threshold)
    if then == "robust":
        xyz, ok, _ = triangulate_skeletons_robust(
            rig, px, w, outlier_px=outlier_px, view_outlier_px=view_outlier_px
        )
        return xyz, ok
    if then == "dlt":
        return triangulate_points(rig, px, w)
    raise ValueError(f"then must be 'robust' or 'dlt', not {then!r}")


# ------------------------------------------------------------------ the model folder


def save_view_confidence(folder: str | Path, model: ViewConfidence, val_loss: float) -> Path:
    """Writes the parameters (orbax, ``folder/best``) and the config (JSON) to ``folder``
    (`checkpoints.save_params_folder`: never half written, an older model replaced whole)."""
    config = dataclasses.asdict(model.config)
    text = json.dumps(config, indent=1)
    return save_params_folder(folder, model.params, config, {CONFIG_FILE: text}, val_loss)


def load_view_confidence(folder: str | Path) -> ViewConfidence:
    """The model `save_view_confidence` wrote (parameters alone, no optimiser).

    Raises:
      InputError: no such folder or config, or a checkpoint of another shape.
    """
    folder = Path(folder)
    path = folder / CONFIG_FILE
    if not path.is_file():
        raise InputError(f"no view-confidence model here ({CONFIG_FILE} missing)", file=str(folder))
    d = json.loads(path.read_text())
    config = ConfidenceConfig(
        widths=tuple(int(v) for v in d["widths"]),
        threshold=float(d["threshold"]),
        then=str(d["then"]),
    )
    blank = init_model(config)
    params = Checkpoints(folder).restore_params(blank.params)
    return blank._replace(params=params)


@functools.lru_cache(maxsize=4)
def cached_view_confidence(folder: str) -> ViewConfidence:
    """`load_view_confidence`, read once per folder (the pipeline asks for it every chunk)."""
    return load_view_confidence(folder)
