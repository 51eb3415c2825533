"""Training the temporal stage without labels (`fit_temporal`).

Data are windows of one person's views over ``T`` frames: single-person synthetic recordings
(`windows_of_recordings`, the main skeleton of each view) or a user's own tracked people
(`windows_of_tracks`, for fine-tuning on the recording itself). No 3D ground truth is an input
of anything here. Per window, the loss is

* the paper's reprojection error, confidence-weighted: each frame's predicted keypoints are
  projected into every view and the Manhattan distances to the detections (each truncated at
  ``max_error_px``), weighted by their scores, averaged (pixels of a camera of
  `REFERENCE_FOCAL_PX` focal length), raised to
  ``loss_power``, averaged over the window's frames; the inputs meanwhile lose views, keypoints
  and a run of one keypoint in all views but at most one (`drop_inputs`) while the loss keeps
  every detection: the model learns to infer what it was not given from the other views and
  from time;
* bone-length constancy: the variance of each bone's length over the window's frames (cm^2);
* left/right symmetry: the squared difference of mirrored bones' mean lengths (cm^2).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, project_points
from mvpose_jax.data.recording import Recording
from mvpose_jax.features import main_skeletons
from mvpose_jax.losses import keypoint_l1, masked_mean
from mvpose_jax.pretraining import REFERENCE_FOCAL_PX  # the loss's pixel unit
from mvpose_jax.progress import progress_bar
from mvpose_jax.skeletons import get_layout
from mvpose_jax.temporal import (
    TemporalConfig,
    TemporalModel,
    apply_windows,
    init_temporal,
    track_windows,
)
from mvpose_jax.train import init_train_state, make_optimizer, make_train_step
from mvpose_jax.trained import TrainConfig

_CM = 0.01


class TemporalBatch(NamedTuple):
    """Windows of one person's views: xy (B, T, C, K, 2) pixels, score (B, T, C, K) (0 =
    missing), present (B, T) bool (the person is in the frame)."""

    xy: np.ndarray
    score: np.ndarray
    present: np.ndarray


@dataclasses.dataclass(frozen=True)
class TemporalTrainConfig:
    """How the temporal model is trained.

    Attributes:
      steps, batch_size (windows), learning_rate: the optimisation (Adam, gradient clipping,
        the step size decaying on a cosine to a tenth, `train.make_optimizer`).
      loss_power: each frame's mean reprojection error is raised to it (the paper: 2; 1, as our
        estimator recipe: a few frames with gross detector errors cannot drown the rest).
      max_error_px: each keypoint-view's Manhattan error is truncated here (reference pixels).
      bone_weight, symmetry_weight: the bone-constancy and symmetry terms' weights (per cm^2,
        against the squared pixels of the reprojection term).
      view_drop: each window drops each view of each frame with a rate drawn in [0, view_drop].
      keypoint_drop: and each keypoint of each view with a rate drawn in [0, keypoint_drop].
      run_drop: probability that a window loses one random keypoint over a random run of
        frames in every view but (half of the time) one.
      eval_every: steps between evaluations on the dev windows; the best parameters are kept.
      seed: of the initialisation, batches and augmentation.
    """

    steps: int = 2000
    batch_size: int = 32
    learning_rate: float = 1e-3
    loss_power: float = 1.0
    max_error_px: float = 100.0
    bone_weight: float = 0.1
    symmetry_weight: float = 0.1
    view_drop: float = 0.5
    keypoint_drop: float = 0.2
    run_drop: float = 0.5
    eval_every: int = 200
    seed: int = 0


def _cut(xy, score, present, window: int) -> TemporalBatch:
    """One sequence (F, ...) cut into windows of ``window`` frames overlapping by half."""
    F = len(present)
    if window > F:
        pad = window - F
        xy = np.concatenate([xy, np.zeros((pad,) + xy.shape[1:], xy.dtype)])
        score = np.concatenate([score, np.zeros((pad,) + score.shape[1:], score.dtype)])
        present = np.concatenate([present, np.zeros(pad, bool)])
        F = window
    starts = list(range(0, F - window + 1, max(1, window // 2)))
    if starts[-1] + window < F:
        starts.append(F - window)
    idx = np.asarray(starts)[:, None] + np.arange(window)[None]
    keep = present[idx].sum(1) >= 2
    idx = idx[keep]
    return TemporalBatch(xy[idx], score[idx], present[idx])


def _joined(parts: Sequence[TemporalBatch], window: int, C: int, K: int) -> TemporalBatch:
    if not parts:
        return TemporalBatch(
            np.zeros((0, window, C, K, 2), np.float32),
            np.zeros((0, window, C, K), np.float32),
            np.zeros((0, window), bool),
        )
    return TemporalBatch(*(np.concatenate(a) for a in zip(*parts, strict=True)))


def windows_of_recordings(recordings: Sequence[Recording], window: int) -> TemporalBatch:
    """Windows of single-person recordings (each view's skeleton with the most keypoints)."""
    parts = []
    for rec in recordings:
        xy, score = main_skeletons(
            np.asarray(rec.detections.xy, np.float32), np.asarray(rec.detections.score, np.float32)
        )
        present = (score > 0).any(axis=(1, 2))
        parts.append(_cut(xy, score, present, window))
    _, C, _, K = np.shape(recordings[0].detections.score) if recordings else (0, 0, 0, 0)
    return _joined(parts, window, C, K)


def windows_of_tracks(
    xy: np.ndarray, score: np.ndarray, track: np.ndarray, valid: np.ndarray, window: int
) -> TemporalBatch:
    """Windows of tracked people (xy (F, G, C, K, 2), score (F, G, C, K), track and valid
    (F, G)), as `temporal.refine_tracks` cuts them (the fine-tuning data of a recording)."""
    F, G, C, K = np.shape(score)
    win = track_windows(track, valid, window)
    here = win.rows >= 0
    r = np.maximum(win.rows, 0)
    xy = np.asarray(xy, np.float32).reshape(F * G, C, K, 2)[r]
    score = np.asarray(score, np.float32).reshape(F * G, C, K)[r]
    keep = here.sum(1) >= 2
    return TemporalBatch(
        np.where(here[..., None, None, None], xy, 0.0)[keep],
        np.where(here[..., None, None], score, 0.0)[keep],
        here[keep],
    )


def drop_inputs(key: jax.Array, score: jax.Array, config: TemporalTrainConfig) -> jax.Array:
    """The scores the model is given: (B, T, C, K) with random views, keypoints and one run of
    one keypoint set to 0 (`TemporalTrainConfig`)."""
    B, T, C, K = score.shape
    k = jax.random.split(key, 9)
    view_rate = jax.random.uniform(k[0], (B, 1, 1)) * config.view_drop
    kp_rate = jax.random.uniform(k[1], (B, 1, 1, 1)) * config.keypoint_drop
    keep = jax.random.uniform(k[2], (B, T, C)) >= view_rate
    keep = keep[..., None] & (jax.random.uniform(k[3], (B, T, C, K)) >= kp_rate)
    # One keypoint lost over a run of frames, in every view but (half of the time) one.
    has_run = jax.random.uniform(k[4], (B,)) < config.run_drop
    kp = jax.random.randint(k[5], (B,), 0, K)
    start = jax.random.randint(k[6], (B,), 0, T)
    length = jax.random.randint(k[7], (B,), 1, T // 2 + 1)
    t = jnp.arange(T)[None]
    in_run = has_run[:, None] & (t >= start[:, None]) & (t < (start + length)[:, None])
    spare = jax.random.randint(k[8], (B,), -C, C)  # < 0: no view spared
    lost = (
        in_run[:, :, None, None]
        & (jnp.arange(K)[None, None, None, :] == kp[:, None, None, None])
        & (jnp.arange(C)[None, None, :, None] != spare[:, None, None, None])
    )
    return jnp.where(keep & ~lost, score, 0.0)


def _bone_tables(layout: str) -> tuple[np.ndarray, np.ndarray]:
    """(bones (J, 2), mirrored bone pairs (M, 2) of bone indices)."""
    lay = get_layout(layout)
    bones = np.asarray(lay.bones, np.int64).reshape(-1, 2)
    flip = np.asarray(lay.flip)
    index = {tuple(sorted(b)): i for i, b in enumerate(bones.tolist())}
    pairs = []
    for i, (a, b) in enumerate(bones.tolist()):
        j = index.get(tuple(sorted((int(flip[a]), int(flip[b])))))
        if j is not None and j > i:
            pairs.append((i, j))
    return bones, np.asarray(pairs, np.int64).reshape(-1, 2)


def window_terms(
    rig: Rig, xyz, batch: TemporalBatch, bones, pairs, loss_power: float, max_error_px: float
):
    """Per window (B,): (reprojection term, mean px per keypoint, bone variance cm^2,
    symmetry cm^2). xyz (B, T, K, 3) world metres; every detection of ``batch`` is a target."""
    scale = REFERENCE_FOCAL_PX / rig.K[:, 0, 0]  # (C,)
    px = jnp.moveaxis(project_points(rig, xyz), 0, 2)  # (B, T, C, K, 2)
    w = batch.score
    seen = w > 0
    # Truncated: a detector's gross error (a swapped limb, a keypoint of someone else) or a
    # point near a camera's plane weighs no more than max_error_px, and pulls on nothing.
    l1 = jnp.minimum(keypoint_l1(px, batch.xy, seen) * scale[None, None, :, None], max_error_px)
    frame_err = jnp.sum(w * l1, axis=(2, 3)) / jnp.maximum(w.sum(axis=(2, 3)), 1e-6)  # (B, T)
    here = batch.present & seen.any(axis=(2, 3))
    hw = here.astype(xyz.dtype)
    n = jnp.maximum(hw.sum(1), 1.0)
    rep = jnp.sum(frame_err**loss_power * hw, 1) / n
    px_mean = jnp.sum(frame_err * hw, 1) / n
    # A safe norm: an untrained model puts a frame without evidence at one point (length 0).
    d = xyz[..., bones[:, 0], :] - xyz[..., bones[:, 1], :]
    length = jnp.sqrt(jnp.sum(jnp.square(d), -1) + 1e-12)  # (B, T, J)
    mean_len = jnp.sum(length * hw[..., None], 1) / n[:, None]  # (B, J)
    var = jnp.sum(jnp.square(length - mean_len[:, None, :]) * hw[..., None], 1) / n[:, None]
    bone = jnp.mean(var, -1) / _CM**2
    if len(pairs):
        sym = jnp.mean(jnp.square(mean_len[:, pairs[:, 0]] - mean_len[:, pairs[:, 1]]), -1) / _CM**2
    else:
        sym = jnp.zeros_like(bone)
    return rep, px_mean, bone, sym, here.any(1)


def temporal_loss_fn(rig: Rig, config: TemporalTrainConfig, layout: str):
    """``loss_fn(model, batch, key)`` for `train.make_train_step`."""
    bones, pairs = _bone_tables(layout)

    def loss_fn(net, batch: TemporalBatch, key):
        given = drop_inputs(key, batch.score, config)
        xyz = apply_windows(net, rig, batch.xy, given, batch.present)
        rep, px, bone, sym, ok = window_terms(
            rig, xyz, batch, bones, pairs, config.loss_power, config.max_error_px
        )
        loss = rep + config.bone_weight * bone + config.symmetry_weight * sym
        metrics = {
            "px_per_keypoint": masked_mean(px, ok),
            "bone_cm2": masked_mean(bone, ok),
            "symmetry_cm2": masked_mean(sym, ok),
        }
        return loss, ok, metrics

    return loss_fn


def _as_jnp(batch: TemporalBatch) -> TemporalBatch:
    return TemporalBatch(*(jnp.asarray(a) for a in batch))


def fit_temporal(
    rig: Rig,
    train: TemporalBatch,
    dev: TemporalBatch,
    model_config: TemporalConfig = TemporalConfig(),
    config: TemporalTrainConfig = TemporalTrainConfig(),
    *,
    start: TemporalModel | None = None,
    progress: bool = False,
) -> tuple[TemporalModel, dict]:
    """Trains (or, from ``start``, fine-tunes) the temporal model on ``rig``'s windows.

    The dev windows are scored with the training loss under a fixed draw of the input
    dropout every ``eval_every`` steps; the parameters with the lowest dev loss are kept.

    Returns:
      (model, record: dev losses, the best step, the history).
    """
    if len(train.present) == 0 or len(dev.present) == 0:
        raise ValueError("fit_temporal needs training and dev windows")
    K = train.score.shape[-1]
    blank = start or init_temporal(K, model_config, rig=rig, seed=config.seed)
    # A copy: the train step donates its state, and ``start`` stays the caller's.
    net = nnx.merge(blank.graphdef, jax.tree.map(jnp.copy, blank.params), blank.rest)
    tx = make_optimizer(
        TrainConfig(
            learning_rate=config.learning_rate,
            max_steps=config.steps,
            seed=config.seed,
            final_lr_fraction=0.1,
        )
    )
    loss_fn = temporal_loss_fn(rig, config, blank.config.layout)
    graphdef, rest, state = init_train_state(net, tx)
    step_fn = make_train_step(graphdef, rest, tx, loss_fn)
    dev_j = _as_jnp(dev)
    dev_key = jax.random.key(config.seed + 1)

    @jax.jit
    def dev_loss(params):
        model = nnx.merge(graphdef, params, rest)
        per, ok, metrics = loss_fn(model, dev_j, dev_key)
        return masked_mean(per, ok), metrics

    rng = np.random.default_rng(config.seed)
    key = jax.random.key(config.seed)
    history = []
    best_loss, _ = dev_loss(state.params)
    best = (float(best_loss), jax.tree.map(jnp.copy, state.params), 0)
    history.append({"step": 0, "dev_loss": best[0]})
    n = len(train.present)
    bar = progress_bar(total=config.steps, unit="step", desc="temporal", disable=not progress)
    for step in range(config.steps):
        idx = rng.integers(0, n, config.batch_size)
        batch = TemporalBatch(*(jnp.asarray(a[idx]) for a in train))
        state, metrics = step_fn(state, batch, key)
        bar.update(1)
        if (step + 1) % config.eval_every == 0 or step + 1 == config.steps:
            val, dm = dev_loss(state.params)
            entry = {
                "step": step + 1,
                "train_loss": float(metrics["loss"]),
                "dev_loss": float(val),
                **{f"dev_{k}": float(v) for k, v in dm.items()},
            }
            history.append(entry)
            bar.set_postfix(dev=f"{float(val):.1f}")
            if float(val) < best[0]:
                best = (float(val), jax.tree.map(jnp.copy, state.params), step + 1)
    bar.close()
    model = TemporalModel(graphdef, rest, best[1], blank.config, K)
    record = {
        "dev_loss": best[0],
        "best_step": best[2],
        "initial_dev_loss": history[0]["dev_loss"],
        "train_windows": int(n),
        "dev_windows": int(len(dev.present)),
        "config": dataclasses.asdict(config),
        "history": history,
    }
    return model, record
