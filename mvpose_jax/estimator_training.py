"""The 3D estimator's training (DESIGN.md §1.3): `train_estimator`.

Inputs from the inference cameras C_i, reprojection loss over all training cameras C_t,
view-subset augmentation inside the step (each seed sample gets ``num_augment`` derived samples
with random non-empty proper subsets of its available views; their initial 3D is recomputed from
the kept views; their loss uses every view of the seed). Its set-up (cameras, model, optimiser,
step, evaluation) is written once, `estimator_training`, for `train_estimator`, `adapt` and the
benchmarks. The fit loop, resuming and data parallelism are `train`'s. No 3D ground truth is an
input of anything here.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, project_points, rig_centre_and_radius
from mvpose_jax.checkpoints import TrainState  # TrainState: defined with what holds it
from mvpose_jax.data.files import to_jsonable
from mvpose_jax.errors import InputError
from mvpose_jax.features import (
    EstimatorInputs,
    assemble_features,
    estimator_inputs,
)
from mvpose_jax.losses import masked_mean, reprojection_error_l1
from mvpose_jax.models import estimator_model, initialised, to_world
from mvpose_jax.parallel import mesh_size, replicate, shard_batch
from mvpose_jax.trained import (
    Estimator,
    EstimatorConfig,
    ModelFolder,
    rig_agnostic_estimator,
)
from mvpose_jax.triangulate import triangulate_points

if TYPE_CHECKING:  # annotations only: importing data.recording loads every reader
    pass

from mvpose_jax.train import (
    FitResult,
    fit_resumable,
    init_train_state,
    make_optimizer,
    make_train_step,
    shuffled_batches,
    training_mesh,
)


class EstimatorBatch(NamedTuple):
    """Seed samples of the 3D estimator: one person each, with all training views."""

    inputs: EstimatorInputs  # features of the inference views (N, C_i, ...)
    available: jax.Array  # (N, C_i) bool, the inference view has at least one keypoint
    xy: jax.Array  # (N, C_t, K, 2) detections in every training camera (loss targets)
    score: jax.Array  # (N, C_t, K) scores, 0 = missing


def make_estimator_batch(
    rig_train: Rig,
    infer_cameras: Sequence[int],
    xy: jax.Array,
    score: jax.Array,
    normalisation: tuple[Any, Any] | None = None,
) -> EstimatorBatch:
    """Builds estimator samples from people's detections in the training cameras.

    Args:
      rig_train: the training cameras C_t.
      infer_cameras: indices into C_t of the inference cameras C_i.
      xy: (N, C_t, K, 2) pixels; score: (N, C_t, K).
      normalisation: (centre (3,), radius ()) of the normalised space; default ``rig_train``'s
        (an estimator trained elsewhere, `Estimator.normalisation`, keeps its own).
    """
    idx = np.asarray(infer_cameras)
    rig_infer = rig_train.select(list(idx))
    xy = jnp.asarray(xy, jnp.float32)
    score = jnp.asarray(score, jnp.float32)
    inputs = estimator_inputs(
        rig_infer,
        xy[:, idx],
        score[:, idx],
        rig_centre_and_radius(rig_train) if normalisation is None else normalisation,
    )
    available = (score[:, idx] > 0).any(axis=-1)
    return EstimatorBatch(inputs, available, xy, score)


def random_view_subsets(
    key: jax.Array, available: jax.Array, num: int
) -> tuple[jax.Array, jax.Array]:
    """Random non-empty proper subsets of each sample's available views.

    Args:
      available: (N, C) bool.
      num: subsets per sample.
    Returns:
      masks (num, N, C) bool and valid (num, N): False where the sample has < 2 views (no
      non-empty proper subset exists).
    """
    N, C = available.shape
    n_avail = available.sum(axis=-1)  # (N,)
    k_size, k_order = jax.random.split(key)
    # Subset size uniform in 1 .. n_avail - 1, then that many views chosen at random.
    size = 1 + jnp.floor(
        jax.random.uniform(k_size, (num, N)) * jnp.maximum(n_avail - 1, 1)[None]
    ).astype(jnp.int32)
    priority = jnp.where(available[None], jax.random.uniform(k_order, (num, N, C)), -1.0)
    rank = jnp.argsort(jnp.argsort(-priority, axis=-1), axis=-1)  # 0 = highest priority
    masks = (rank < size[..., None]) & available[None]
    return masks, jnp.broadcast_to(n_avail >= 2, (num, N))


def estimator_loss_fn(
    rig_train: Rig,
    rig_infer: Rig,
    num_augment: int,
    loss_power: float = 2.0,
    normalisation: tuple[Any, Any] | None = None,
):
    """``loss_fn(model, batch, key)`` of the estimator, for `make_train_step`; ``normalisation``
    as `make_estimator_batch`."""
    centre, radius = rig_centre_and_radius(rig_train) if normalisation is None else normalisation

    def loss_fn(model, batch: EstimatorBatch, key):
        subsets, subset_ok = random_view_subsets(key, batch.available, num_augment)
        masks = jnp.concatenate([batch.available[None], subsets], axis=0)  # (1+A, N, C_i)
        ok = jnp.concatenate([batch.available.any(-1)[None], subset_ok], axis=0)  # (1+A, N)
        feats = jax.vmap(assemble_features, in_axes=(None, 0))(batch.inputs, masks)
        xyz = to_world(model(feats), centre, radius)  # (1+A, N, K, 3)
        err = jax.vmap(reprojection_error_l1, in_axes=(None, 0, None, None))(
            rig_train, xyz, batch.xy, batch.score
        )  # (1+A, N)
        n_kp = jnp.maximum((batch.score > 0).sum(axis=(1, 2)), 1)
        metrics = {"px_per_keypoint": masked_mean(err[0] / n_kp, ok[0])}
        return err**loss_power, ok, metrics

    return loss_fn


class EstimatorTraining(NamedTuple):
    """One estimator's training set-up (`estimator_training`), the same for training, adaptation
    and the benchmark."""

    graphdef: Any
    rest: Any
    state: TrainState  # the starting state (replicated over ``mesh`` when there is one)
    train_step: Callable  # jitted (state, EstimatorBatch, key) -> (state, metrics)
    # jitted (params, EstimatorBatch) -> {"val_loss", "val_px_per_keypoint"}: no augmentation
    evaluate: Callable
    rig_train: Rig  # the loss cameras C_t
    rig_infer: Rig  # the input cameras C_i
    infer_idx: tuple[int, ...]  # C_i's indices in C_t
    normalisation: tuple[Any, Any] | None  # as `make_estimator_batch` (None: rig_train's)
    mesh: jax.sharding.Mesh | None  # data parallelism (`TrainConfig.num_devices`)

    def batches(self, xy, score, chunk: int = 4096) -> EstimatorBatch:
        """People's detections (N, C_t, K, 2) and scores (N, C_t, K) in the training cameras as
        one `EstimatorBatch` (built ``chunk`` people at a time, to bound the host's memory)."""
        parts = [
            make_estimator_batch(
                self.rig_train,
                self.infer_idx,
                xy[i : i + chunk],
                score[i : i + chunk],
                self.normalisation,
            )
            for i in range(0, len(xy), chunk)
        ]
        return jax.tree.map(lambda *a: jnp.concatenate(a), *parts)


def estimator_training(
    rig: Rig,
    config: EstimatorConfig,
    num_keypoints: int,
    *,
    steps_per_epoch: int = 1,
    start: Estimator | None = None,
) -> EstimatorTraining:
    """The estimator's training set-up: cameras, model, optimiser, train step and evaluation.

    Args:
      rig: a rig holding (at least) ``config.train_cameras`` (None: all of ``rig``).
      config: the estimator's `EstimatorConfig`; ``config.train`` the optimisation (its seed
        initialises a fresh model, its ``num_devices`` makes the mesh).
      num_keypoints: K.
      steps_per_epoch: for the optimiser's schedule (`make_optimizer`).
      start: a trained estimator to go on from (adaptation): its parameters (copied: the step
        donates its state) and its normalised frame; None: a fresh model in ``rig_train``'s frame.
    Raises:
      InputError on inference cameras that are not training cameras, or a mesh that cannot be
      made.
    """
    train_names = config.train_cameras or rig.names
    infer_names = config.infer_cameras or train_names
    missing = [c for c in infer_names if c not in train_names]
    if missing:
        raise InputError(
            f"inference cameras {missing} are not training cameras", field="infer_cameras"
        )
    rig_train = rig.select(list(train_names))
    infer_idx = tuple(list(train_names).index(c) for c in infer_names)
    rig_infer = rig_train.select(list(infer_idx))
    tcfg = config.train
    mesh = training_mesh(tcfg)
    if start is None:
        model = initialised(
            lambda: estimator_model(
                len(infer_idx), num_keypoints, config.mlp, rngs=nnx.Rngs(tcfg.seed)
            )
        )
        normalisation = None
        if config.mlp.views == "pooled":  # as `trained.rig_agnostic_estimator` loads it
            graphdef, params, rest = nnx.split(model, nnx.Param, ...)
            start = rig_agnostic_estimator(graphdef, rest, params, config, rig_train)
            model = nnx.merge(start.graphdef, start.params, start.rest)
            normalisation = start.normalisation
    else:
        params = jax.tree.map(jnp.copy, start.params)
        model = nnx.merge(start.graphdef, params, start.rest)
        normalisation = start.normalisation
    tx = make_optimizer(tcfg, steps_per_epoch)
    graphdef, rest, state = init_train_state(model, tx)
    loss_fn = estimator_loss_fn(
        rig_train, rig_infer, config.num_augment, config.loss_power, normalisation
    )
    train_step = make_train_step(graphdef, rest, tx, loss_fn, mesh=mesh, xla_kernels=True)
    evaluate = make_estimator_eval(graphdef, rest, rig_train, config.loss_power, normalisation)
    if mesh is not None:
        state = replicate(mesh, state)
    return EstimatorTraining(
        graphdef,
        rest,
        state,
        train_step,
        evaluate,
        rig_train,
        rig_infer,
        infer_idx,
        normalisation,
        mesh,
    )


def train_estimator(
    rig: Rig,
    train_xy: np.ndarray,
    train_score: np.ndarray,
    dev_xy: np.ndarray,
    dev_score: np.ndarray,
    config: EstimatorConfig = EstimatorConfig(),
    *,
    checkpoint_dir: str | Path | None = None,
    progress: bool = True,
    resume: bool = False,
    start: Estimator | None = None,
) -> tuple[Estimator, FitResult]:
    """Trains a 3D estimator from people's 2D detections alone (no 3D labels).

    Args:
      rig: a rig holding (at least) the training cameras.
      train_xy, dev_xy: (N, C_t, K, 2) per-person detections in the training cameras, in the
        order of ``config.train_cameras``; train_score, dev_score: (N, C_t, K).
      config: `EstimatorConfig`.
      checkpoint_dir: where best and latest checkpoints go (optional).
      resume: continue from the latest checkpoint in ``checkpoint_dir`` (same config required),
        exactly where it stopped.
      start: an estimator to fine-tune (its network and frame; e.g. the pretrained rig-agnostic
        one set up for ``rig``, `trained.rig_agnostic_estimator`); None: a fresh network.
    Returns:
      (the best `Estimator`, the `FitResult`).
    Raises:
      InputError on cameras missing from the rig, a batch size that does not split over
      ``config.train.num_devices``, or (resuming) a checkpoint of another config or a damaged one.
    """
    tcfg = config.train
    n_train = len(train_xy)
    batch = min(tcfg.batch_size, n_train)
    steps_per_epoch = math.ceil(n_train / batch)
    setup = estimator_training(
        rig, config, train_xy.shape[-2], steps_per_epoch=steps_per_epoch, start=start
    )
    mesh, graphdef, rest, state = setup.mesh, setup.graphdef, setup.rest, setup.state
    if mesh is not None and batch % mesh_size(mesh):
        raise InputError(
            f"batch size {batch} does not split over {mesh_size(mesh)} devices; use a multiple of "
            f"{mesh_size(mesh)}",
            field="batch_size",
        )
    train_data = setup.batches(train_xy, train_score)
    dev_data = setup.batches(dev_xy, dev_score)
    if mesh is not None:
        dev_data = replicate(mesh, dev_data)  # evaluated whole on each device (it is small)

    def epoch_batches(epoch):
        for idx in shuffled_batches(n_train, batch, tcfg.seed, epoch):
            samples = jax.tree.map(lambda a: a[idx], train_data)
            # The global batch (the same on every host), split over the devices.
            yield samples if mesh is None else shard_batch(mesh, samples)

    def evaluate(state):
        return {k: float(v) for k, v in setup.evaluate(state.params, dev_data).items()}

    run_config = to_jsonable(dataclasses.asdict(config))
    # What restoring needs beyond the config: the resolved cameras and the keypoint count.
    run_config.update(
        train_cameras=list(setup.rig_train.names),
        infer_cameras=list(setup.rig_infer.names),
        num_keypoints=int(train_xy.shape[-2]),
    )
    centre, radius = setup.normalisation or rig_centre_and_radius(setup.rig_train)
    # The normalised frame travels with the model (inference may hold only the inference cameras);
    # a rig-agnostic model takes every rig's own (`trained.rig_agnostic_estimator`).
    run_config["frame"] = (
        "rig-centre-metres"
        if config.mlp.views == "pooled"
        else [float(x) for x in np.asarray(centre)] + [float(radius)]
    )
    result = fit_resumable(
        state,
        setup.train_step,
        epoch_batches,
        evaluate,
        tcfg,
        steps_per_epoch=steps_per_epoch,
        checkpoint_dir=checkpoint_dir,
        run_config=run_config,
        resume=resume,
        desc="estimator",
        progress=progress,
    )
    if checkpoint_dir is not None and jax.process_index() == 0:
        # The yardstick a user needs before trusting the model on their rig: its reprojection
        # error on the dev people against triangulation's, on the keypoints both reconstruct.
        quality = compare_with_triangulation(
            graphdef,
            rest,
            jax.device_get(result.state.params),
            setup.rig_train,
            setup.infer_idx,
            dev_xy,
            dev_score,
            setup.normalisation,
        )
        ModelFolder(checkpoint_dir).write_dev_quality(quality)
    return Estimator(
        graphdef, rest, result.state.params, setup.rig_infer, config, (centre, radius)
    ), result


def compare_with_triangulation(
    graphdef,
    rest,
    params,
    rig_train: Rig,
    infer_idx: Sequence[int],
    xy,
    score,
    normalisation: tuple[Any, Any] | None = None,
) -> dict:
    """Mean reprojection error (px per detected keypoint and training camera) of an estimator's
    people and of DLT triangulation from the same inference views, on the keypoints the
    triangulation reconstructs (seen in 2+ inference views).

    Args:
      xy: (N, C_t, K, 2), score: (N, C_t, K): people of the dev recordings, training cameras.
      normalisation: as `make_estimator_batch`.
    Returns:
      {"estimator_px", "triangulation_px", "keypoints"}.
    """
    data = make_estimator_batch(rig_train, infer_idx, xy, score, normalisation)
    centre, radius = rig_centre_and_radius(rig_train) if normalisation is None else normalisation
    model = nnx.merge(graphdef, params, rest)
    xyz_est = to_world(model(assemble_features(data.inputs, data.available)), centre, radius)
    idx = np.asarray(infer_idx)
    xy_i, score_i = jnp.moveaxis(data.xy[:, idx], 1, 0), jnp.moveaxis(data.score[:, idx], 1, 0)
    xyz_tri, ok = triangulate_points(rig_train.select(list(idx)), xy_i, score_i)  # (N, K, 3)
    seen = (data.score > 0) & ok[:, None, :]  # (N, C_t, K)

    def per_keypoint(xyz):
        px = jnp.moveaxis(project_points(rig_train, xyz), 0, 1)  # (N, C_t, K, 2)
        err = jnp.abs(px - data.xy).sum(-1)
        return float(jnp.where(seen, err, 0.0).sum() / jnp.maximum(seen.sum(), 1))

    return {
        "estimator_px": round(per_keypoint(xyz_est), 4),
        "triangulation_px": round(per_keypoint(xyz_tri), 4),
        "keypoints": int(seen.sum()),
        "how": "mean L1 reprojection error per detected keypoint, over the training cameras, of "
        "the dev people's keypoints that DLT triangulates from the inference cameras",
    }


def make_estimator_eval(
    graphdef, rest, rig_train: Rig, loss_power: float, normalisation: tuple[Any, Any] | None = None
) -> Callable:
    """A jitted ``(params, EstimatorBatch) -> {"val_loss", "val_px_per_keypoint"}``: the
    reprojection loss over ``rig_train``'s cameras (no augmentation) and the mean error per
    detected keypoint; ``normalisation`` as `make_estimator_batch`."""
    return jax.jit(
        functools.partial(
            _estimator_eval,
            graphdef,
            rest,
            rig_train,
            None,
            loss_power,
            normalisation=normalisation,
        )
    )


def _estimator_eval(
    graphdef,
    rest,
    rig_train,
    rig_infer,
    loss_power,
    params,
    data: EstimatorBatch,
    normalisation=None,
):
    centre, radius = rig_centre_and_radius(rig_train) if normalisation is None else normalisation
    model = nnx.merge(graphdef, params, rest)
    feats = assemble_features(data.inputs, data.available)
    xyz = to_world(model(feats), centre, radius)
    err = reprojection_error_l1(rig_train, xyz, data.xy, data.score)
    ok = data.available.any(-1)
    n_kp = jnp.maximum((data.score > 0).sum(axis=(1, 2)), 1)
    return {
        "val_loss": masked_mean(err**loss_power, ok),
        "val_px_per_keypoint": masked_mean(err / n_kp, ok),
    }
