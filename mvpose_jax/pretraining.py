"""One 3D estimator and one skeleton matcher for many rigs (`pretrain_estimator`,
`pretrain_matcher`): the paper's training without labels, over people recorded by rigs of every
kind, for `models.ViewPooledMLP` and `models.RigAgnosticGAT`.

The recipe is `estimator_training`'s (reprojection loss over all of a person's views, view-subset
augmentation, initial 3D from the kept views), with two changes that a model for any rig needs:

* each person carries its own rig: the loss projects into that person's cameras;
* the frame is the rig's centre in metres (`rig_agnostic_frame`), not its radius: a body is then
  the same size in the inputs of a stereo pair and of a 10 m studio. World vectors are taken in
  a z-up world (training rigs are drawn so; at inference `trained.rig_agnostic_estimator` turns
  the user's up to +z inside the model).

People are padded to a few camera counts (`CAMERA_BUCKETS`; padded views have no keypoint) so
that the step compiles once per bucket; a batch holds one bucket's people.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, project_points
from mvpose_jax.data.files import to_jsonable
from mvpose_jax.errors import InputError
from mvpose_jax.estimator_training import random_view_subsets
from mvpose_jax.features import (
    NUM_KEYPOINT_FEATURES,
    EstimatorInputs,
    assemble_features,
    estimator_inputs,
    rig_agnostic_frame,
)
from mvpose_jax.graphs import GraphBatch, SkeletonPool, build_graphs, compose_samples, make_pool
from mvpose_jax.losses import keypoint_l1, masked_mean
from mvpose_jax.matcher_training import fit_matcher_model
from mvpose_jax.models import estimator_model, initialised, matcher_model
from mvpose_jax.train import (
    FitResult,
    fit_resumable,
    init_train_state,
    make_optimizer,
    make_train_step,
)
from mvpose_jax.trained import EstimatorConfig, MatcherConfig

if TYPE_CHECKING:  # annotations only: importing data.recording loads every reader
    from mvpose_jax.data.recording import Recording

# The loss's pixel unit: a pixel of a camera of this focal length (about a 1080p camera's).
REFERENCE_FOCAL_PX = 1000.0

# People are padded to the first of these camera counts that holds their rig.
CAMERA_BUCKETS = (3, 6, 10)


class RigPeople(NamedTuple):
    """Single people seen by one rig (training data of `pretrain_estimator`).

    ``xy``: (N, C, K, 2) pixels; ``score``: (N, C, K), 0 = missing
    (`features.single_person_samples` of the rig's recordings).
    """

    rig: Rig
    xy: np.ndarray
    score: np.ndarray


class PooledBatch(NamedTuple):
    """People of several rigs, padded to one camera count C (a bucket)."""

    inputs: EstimatorInputs  # (N, C, ...) in each person's rig frame
    available: jax.Array  # (N, C) bool
    xy: jax.Array  # (N, C, K, 2) loss targets
    score: jax.Array  # (N, C, K)
    rig: Rig  # each person's cameras: every leaf (N, C, ...)
    centre: jax.Array  # (N, 3) each person's frame origin, metres (unit: 1 m)


def bucket_for(num_cameras: int) -> int:
    """The padded camera count of a rig of ``num_cameras`` cameras."""
    for b in CAMERA_BUCKETS:
        if num_cameras <= b:
            return b
    raise InputError(
        f"a rig of {num_cameras} cameras is larger than the largest bucket {CAMERA_BUCKETS[-1]}",
        field="cameras",
    )


def pad_rig(rig: Rig, num_cameras: int) -> Rig:
    """The rig padded to ``num_cameras`` with copies of its first camera (they never see a
    keypoint), names ``v0..`` and no ``up``: rigs of one bucket then stack into one pytree."""
    C = rig.num_cameras
    idx = np.concatenate([np.arange(C), np.zeros(num_cameras - C, int)])
    take = lambda a: jnp.asarray(a)[idx]  # noqa: E731
    names = tuple(f"v{i}" for i in range(num_cameras))
    return Rig(take(rig.K), take(rig.dist), take(rig.R), take(rig.t), take(rig.size), names)


def pooled_batch(people: RigPeople) -> PooledBatch:
    """One rig's people as a `PooledBatch` of its bucket."""
    rig = people.rig
    C = bucket_for(rig.num_cameras)
    pad = C - rig.num_cameras
    xy = jnp.asarray(np.pad(people.xy, ((0, 0), (0, pad), (0, 0), (0, 0))), jnp.float32)
    score = jnp.asarray(np.pad(people.score, ((0, 0), (0, pad), (0, 0))), jnp.float32)
    padded = pad_rig(rig, C)
    frame = rig_agnostic_frame(rig)
    inputs = estimator_inputs(padded, xy, score, frame)
    N = len(xy)
    per_person = jax.tree.map(lambda a: jnp.broadcast_to(a, (N,) + a.shape), padded)
    return PooledBatch(
        inputs,
        (score > 0).any(-1),
        xy,
        score,
        per_person,
        jnp.broadcast_to(frame[0], (N, 3)),
    )


def bucketed(people: Sequence[RigPeople]) -> dict[int, PooledBatch]:
    """Every rig's people, concatenated per bucket."""
    parts: dict[int, list[PooledBatch]] = {}
    for p in people:
        if len(p.xy):
            parts.setdefault(bucket_for(p.rig.num_cameras), []).append(pooled_batch(p))
    return {c: jax.tree.map(lambda *a: jnp.concatenate(a), *b) for c, b in sorted(parts.items())}


def _person_error(rig: Rig, xyz, xy, score):
    """One person's summed Manhattan reprojection error in pixels of a camera of focal length
    `REFERENCE_FOCAL_PX` (each camera's pixels scaled by it over the camera's own focal length),
    so that people of a 640-pixel camera weigh as much as those of a 4K one."""
    scale = REFERENCE_FOCAL_PX / rig.K[:, 0, 0]  # (C,)
    per_camera = keypoint_l1(project_points(rig, xyz), xy, score > 0).sum(-1)  # (C,)
    return jnp.sum(per_camera * scale)


def pooled_loss_fn(num_augment: int, loss_power: float):
    """``loss_fn(model, PooledBatch, key)`` for `make_train_step`: as
    `estimator_training.estimator_loss_fn`, each person projected into its own rig."""

    def loss_fn(model, batch: PooledBatch, key):
        subsets, subset_ok = random_view_subsets(key, batch.available, num_augment)
        masks = jnp.concatenate([batch.available[None], subsets], axis=0)  # (1+A, N, C)
        ok = jnp.concatenate([batch.available.any(-1)[None], subset_ok], axis=0)
        feats = jax.vmap(assemble_features, in_axes=(None, 0))(batch.inputs, masks)
        xyz = model(feats) + batch.centre[None, :, None, :]  # unit 1 m
        err = jax.vmap(jax.vmap(_person_error), in_axes=(None, 0, None, None))(
            batch.rig, xyz, batch.xy, batch.score
        )  # (1+A, N)
        n_kp = jnp.maximum((batch.score > 0).sum(axis=(1, 2)), 1)
        metrics = {"px_per_keypoint": masked_mean(err[0] / n_kp, ok[0])}
        return err**loss_power, ok, metrics

    return loss_fn


@functools.partial(jax.jit, static_argnums=(0, 4))
def _eval_sums(graphdef, rest, params, batch: PooledBatch, loss_power):
    model = nnx.merge(graphdef, params, rest)
    xyz = model(assemble_features(batch.inputs, batch.available)) + batch.centre[:, None, :]
    err = jax.vmap(_person_error)(batch.rig, xyz, batch.xy, batch.score)
    ok = batch.available.any(-1)
    n_kp = jnp.maximum((batch.score > 0).sum(axis=(1, 2)), 1)
    return jnp.stack(
        [
            jnp.sum(jnp.where(ok, err**loss_power, 0.0)),
            jnp.sum(jnp.where(ok, err / n_kp, 0.0)),
            jnp.sum(ok),
        ]
    )


def pooled_eval(graphdef, rest, params, data: dict[int, PooledBatch], loss_power: float) -> dict:
    """``{"val_loss", "val_px_per_keypoint"}`` over every bucket's people (all their views)."""
    sums = sum(np.asarray(_eval_sums(graphdef, rest, params, b, loss_power)) for b in data.values())
    n = max(float(sums[2]), 1.0)
    return {"val_loss": float(sums[0] / n), "val_px_per_keypoint": float(sums[1] / n)}


def _epoch_batches(
    data: dict[int, PooledBatch], batch_size: int, seed: int, epoch: int
) -> Iterator[PooledBatch]:
    """One epoch: each bucket shuffled and cut into full batches (a short tail wraps around),
    the buckets' batches interleaved at random; reproducible from (seed, epoch)."""
    rng = np.random.default_rng([seed, epoch])
    plan = []
    for c, b in data.items():
        n = len(b.available)
        order = np.resize(rng.permutation(n), max(1, math.ceil(n / batch_size)) * batch_size)
        plan += [(c, order[i : i + batch_size]) for i in range(0, len(order), batch_size)]
    for i in rng.permutation(len(plan)):
        c, idx = plan[i]
        yield jax.tree.map(lambda a, idx=idx: a[idx], data[c])


def pretrain_estimator(
    train: Sequence[RigPeople],
    dev: Sequence[RigPeople],
    config: EstimatorConfig,
    *,
    checkpoint_dir: str | Path | None = None,
    progress: bool = True,
    resume: bool = False,
) -> tuple[tuple[Any, Any, Any], FitResult]:
    """Trains a rig-agnostic 3D estimator on people of many rigs, without labels.

    Args:
      train, dev: people per rig (`RigPeople`); dev picks the best checkpoint.
      config: an `EstimatorConfig` whose ``mlp.views`` is "pooled" (``train_cameras`` and
        ``infer_cameras`` must be None: the model has no cameras of its own).
      checkpoint_dir: a model folder for the checkpoints (optional); `trained.load_estimator`
        reads it back for any rig.
    Returns:
      ((graphdef, rest, params) of the best model, the `FitResult`).
    Raises:
      InputError: a config that is not rig-agnostic, or no training people.
    """
    if config.mlp.views != "pooled" or config.train_cameras or config.infer_cameras:
        raise InputError(
            "pretraining needs a rig-agnostic estimator: MLPConfig.views='pooled' and no cameras",
            field="mlp.views",
        )
    train_data, dev_data = bucketed(train), bucketed(dev)
    if not train_data or not dev_data:
        raise InputError("no training or dev people to pretrain on", field="recordings")
    K = next(iter(train_data.values())).xy.shape[-2]
    tcfg = config.train
    batch = tcfg.batch_size
    steps_per_epoch = sum(max(1, math.ceil(len(b.available) / batch)) for b in train_data.values())
    model = initialised(
        lambda: estimator_model(CAMERA_BUCKETS[-1], K, config.mlp, rngs=nnx.Rngs(tcfg.seed))
    )
    tx = make_optimizer(tcfg, steps_per_epoch)
    graphdef, rest, state = init_train_state(model, tx)
    step = make_train_step(
        graphdef, rest, tx, pooled_loss_fn(config.num_augment, config.loss_power)
    )
    run_config = to_jsonable(dataclasses.asdict(config))
    run_config.update(
        train_cameras=None,
        infer_cameras=None,
        num_keypoints=int(K),
        frame="rig-centre-metres",
        rigs={"train": len(train), "dev": len(dev)},
        people={
            "train": int(sum(len(p.xy) for p in train)),
            "dev": int(sum(len(p.xy) for p in dev)),
        },
    )
    result = fit_resumable(
        state,
        step,
        lambda epoch: _epoch_batches(train_data, batch, tcfg.seed, epoch),
        lambda s: pooled_eval(graphdef, rest, s.params, dev_data, config.loss_power),
        tcfg,
        steps_per_epoch=steps_per_epoch,
        checkpoint_dir=checkpoint_dir,
        run_config=run_config,
        resume=resume,
        desc="pretrain estimator",
        progress=progress,
    )
    return (graphdef, rest, jax.device_get(result.state.params)), result


# =========================================================================== the matcher


def rig_pool(rig: Rig, recordings: Sequence[Recording]) -> SkeletonPool:
    """Single-person recordings of one rig pooled for `pretrain_matcher`: their skeletons'
    features in the rig-agnostic frame (the rig's centre, metres; `rig_agnostic_frame`)."""
    return make_pool(rig, recordings, rig_agnostic_frame(rig))


def compose_rig_samples(
    pools: Sequence[SkeletonPool], rng: np.random.Generator, num_samples: int, **compose
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training frames of many rigs: each sample draws a rig, then composes its people from
    that rig's recordings (`graphs.compose_samples`); rigs of fewer cameras or skeletons are
    padded with empty views and skeletons (no node: padding costs nothing in the graph).

    Returns:
      features (S, C, Q, K*10), valid (S, C, Q), identity (S, C, Q); C the largest camera
      bucket (or the largest rig drawn), Q the most skeleton slots drawn.
    """
    rigs = rng.integers(len(pools), size=num_samples)
    parts = []
    for r in np.unique(rigs):
        where = np.flatnonzero(rigs == r)
        parts.append((where, *compose_samples(pools[r], rng, len(where), **compose)))
    # Camera slots: always the largest bucket, so that the batches' feature width is one shape.
    C = max([CAMERA_BUCKETS[-1]] + [p[1].shape[1] for p in parts])
    Q = max(p[1].shape[2] for p in parts)
    KF = parts[0][1].shape[3]
    features = np.zeros((num_samples, C, Q, KF), np.float32)
    valid = np.zeros((num_samples, C, Q), bool)
    identity = np.full((num_samples, C, Q), -1, np.int64)
    for where, f, v, i in parts:
        c, q = f.shape[1:3]
        features[where, :c, :q] = f
        valid[where, :c, :q] = v
        identity[where, :c, :q] = i
    return features, valid, identity


def rig_batches(
    pools: Sequence[SkeletonPool],
    rng: np.random.Generator,
    num_batches: int,
    graphs_per_batch: int,
    **compose,
) -> Iterator[GraphBatch]:
    """``num_batches`` padded graph batches of frames composed on random rigs."""
    for _ in range(num_batches):
        yield build_graphs(*compose_rig_samples(pools, rng, graphs_per_batch, **compose))


def pretrain_matcher(
    train: Sequence[SkeletonPool],
    dev: Sequence[SkeletonPool],
    config: MatcherConfig,
    *,
    checkpoint_dir: str | Path | None = None,
    progress: bool = True,
    resume: bool = False,
) -> tuple[tuple[Any, Any, Any], FitResult]:
    """Trains a rig-agnostic skeleton matcher (`models.RigAgnosticGAT`) on many rigs, without
    labels: the paper's composed frames (`graphs.compose_samples`), each of one random rig.

    Args:
      train, dev: one `rig_pool` per rig (features in the rig-agnostic frame, z up); dev picks
        the best checkpoint.
      config: a `MatcherConfig` whose ``gat.views`` is "pooled" and ``cameras`` None.
    Returns:
      ((graphdef, rest, params) of the best model, the `FitResult`);
      `trained.rig_agnostic_matcher` sets it up for a rig.
    Raises:
      InputError: a config that is not rig-agnostic, or no pools.
    """
    if config.gat.views != "pooled" or config.cameras:
        raise InputError(
            "pretraining needs a rig-agnostic matcher: GATConfig.views='pooled' and no cameras",
            field="gat.views",
        )
    if not train or not dev:
        raise InputError("no training or dev rigs to pretrain on", field="recordings")
    K = train[0].features.shape[-1] // NUM_KEYPOINT_FEATURES
    tcfg = config.train
    compose = config.composition()
    num_dev = max(1, math.ceil(config.num_dev_samples / tcfg.batch_size))
    dev_batches = list(
        rig_batches(
            dev, np.random.default_rng([tcfg.seed, 1 << 30]), num_dev, tcfg.batch_size, **compose
        )
    )
    model = initialised(lambda: matcher_model(0, K, config.gat, rngs=nnx.Rngs(tcfg.seed)))

    def epoch_batches(epoch):
        rng = np.random.default_rng([tcfg.seed, epoch])
        return rig_batches(train, rng, config.steps_per_epoch, tcfg.batch_size, **compose)

    run_config = to_jsonable(dataclasses.asdict(config))
    run_config.update(
        num_keypoints=int(K),
        frame="rig-centre-metres",
        rigs={"train": len(train), "dev": len(dev)},
        frames={
            "train": int(sum(len(p.features) for p in train)),
            "dev": int(sum(len(p.features) for p in dev)),
        },
    )
    graphdef, rest, result = fit_matcher_model(
        model,
        epoch_batches,
        dev_batches,
        config,
        checkpoint_dir=checkpoint_dir,
        run_config=run_config,
        progress=progress,
        resume=resume,
        desc="pretrain matcher",
    )
    return (graphdef, rest, jax.device_get(result.state.params)), result
