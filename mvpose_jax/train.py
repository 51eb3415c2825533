"""Training: train states, jit-compiled steps, the fit loop, early stopping, resuming.

Shape of every model's training (STYLE.md §4): an explicit `TrainState` pytree; one pure step
``(state, batch) -> (state, metrics)`` compiled once; a Python `fit` loop that evaluates every
``eval_every`` epochs, stops after ``patience`` checks without improvement, keeps the best
parameters, and checkpoints best and latest (`checkpoints.Checkpoints`). The configs and the
trained-model bundles it returns live in `trained`, which inference uses without this module.

Data parallelism (``TrainConfig.num_devices``, `parallel`): the batch is split along a ``"data"``
mesh axis, parameters and optimiser state are replicated. The estimator's batch has a leading
sample axis and is split as it is. A matcher batch is many graphs concatenated (edges index
global nodes, so its node axis cannot be cut anywhere): it is split by whole graphs into one
padded batch per device (`split_graph_batch`), stacked on a leading device axis, and the
per-device loss is vmapped (`stacked_loss_fn`); the loss is the masked mean over every device's
items, the same number as on the whole batch.

Resuming (`fit`, `Checkpoints`, `resume_state`): the latest state is checkpointed every
``checkpoint_every_steps`` steps and at each validation, with the loop's own state (`FitProgress`:
data-stream position, best validation loss, early-stopping counter, history), so a killed run
resumed from its folder ends with the parameters an uninterrupted run ends with.

The 3D estimator's training (DESIGN.md §1.3) is `train_estimator`: inputs from the inference
cameras C_i, reprojection loss over all training cameras C_t, view-subset augmentation inside the
step (each seed sample gets ``num_augment`` derived samples with random non-empty proper subsets
of its available views; their initial 3D is recomputed from the kept views; their loss uses every
view of the seed). No 3D ground truth is an input of anything here.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from mvpose_jax.cameras import Rig, project_points, rig_centre_and_radius
from mvpose_jax.checkpoints import Checkpoints, TrainState  # TrainState: defined with what holds it
from mvpose_jax.data.files import to_jsonable
from mvpose_jax.errors import InputError
from mvpose_jax.features import EstimatorInputs, assemble_features, estimator_inputs
from mvpose_jax.graphs import GraphBatch, make_pool, sample_batches, split_graph_batch
from mvpose_jax.losses import masked_mean, match_mse, reprojection_error_l1
from mvpose_jax.models import MatchingGAT, PoseMLP, to_world
from mvpose_jax.parallel import make_data_mesh, mesh_size, replicate, replicated, shard_batch
from mvpose_jax.trained import (
    Estimator,
    EstimatorConfig,
    Matcher,
    MatcherConfig,
    ModelFolder,
    TrainConfig,
)
from mvpose_jax.triangulate import triangulate_points

if TYPE_CHECKING:  # annotations only: importing data.recording loads every reader
    from mvpose_jax.data.recording import Recording


def make_optimizer(config: TrainConfig, steps_per_epoch: int = 1) -> optax.GradientTransformation:
    """Adam with global-norm clipping; below ``final_lr_fraction`` 1, a cosine decay over the run
    (``max_steps``, else ``max_epochs * steps_per_epoch``)."""
    lr = config.learning_rate
    if config.final_lr_fraction < 1.0:
        total = config.max_steps or config.max_epochs * steps_per_epoch
        lr = optax.cosine_decay_schedule(
            config.learning_rate, total, alpha=config.final_lr_fraction
        )
    return optax.chain(optax.clip_by_global_norm(config.clip_norm), optax.adam(lr))


def init_train_state(model: nnx.Module, tx: optax.GradientTransformation):
    """Splits a model once; returns (graphdef, rest, TrainState) with committed, typed leaves."""
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    # An explicit int32 counter and device_put avoid a recompile after a checkpoint restore.
    state = TrainState(jnp.zeros((), jnp.int32), params, tx.init(params))
    return graphdef, rest, jax.device_put(state)


def make_train_step(
    graphdef, rest, tx, loss_fn: Callable, *, mesh: jax.sharding.Mesh | None = None
):
    """A jitted ``(state, batch, key) -> (state, metrics)``.

    ``loss_fn(model, batch, key) -> (per_item, mask, metrics)``: unreduced losses and their mask;
    the step reduces them with `masked_mean`. ``key`` is folded from the step, so a resumed run
    draws the same randomness as an uninterrupted one.

    With a ``mesh`` (`parallel.make_data_mesh`), pass a replicated state and a batch split along
    the data axis (`parallel.replicate`, `parallel.shard_batch`): the compiler partitions the
    step from those shardings (each device its block, one all-reduce of the gradients). The new
    state and the metrics come back replicated, so the next call has the same input shardings
    and the step compiles once.
    """
    out_shardings = None if mesh is None else replicated(mesh)

    @functools.partial(jax.jit, donate_argnums=0, out_shardings=out_shardings)
    def train_step(state: TrainState, batch, base_key):
        key = jax.random.fold_in(base_key, state.step)

        def objective(params):
            model = nnx.merge(graphdef, params, rest)
            per_item, mask, aux = loss_fn(model, batch, key)
            return masked_mean(per_item, mask), aux

        (loss, aux), grads = jax.value_and_grad(objective, has_aux=True)(state.params)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads), **aux}
        return TrainState(state.step + 1, params, opt_state), metrics

    return train_step


def stacked_loss_fn(loss_fn: Callable) -> Callable:
    """Lifts ``loss_fn(model, batch, key)`` to S batches stacked on a leading axis (one per device).

    The per-item losses and masks come back (S, ...), so the step's `masked_mean` runs over the
    items of every shard: the loss of the whole global batch, whatever the split. Shard s draws
    its randomness from ``fold_in(key, s)``. Each scalar metric is averaged over shards weighted
    by their masked-in item counts (exact for metrics that are masked means over the loss mask,
    such as the matcher's accuracy).
    """

    def lifted(model, batch, key):
        num = jax.tree.leaves(batch)[0].shape[0]
        per_item, mask, aux = jax.vmap(lambda b, s: loss_fn(model, b, jax.random.fold_in(key, s)))(
            batch, jnp.arange(num)
        )
        weight = mask.reshape(num, -1).sum(axis=1).astype(jnp.float32)  # (S,)
        aux = {k: jnp.sum(v * weight) / jnp.maximum(jnp.sum(weight), 1.0) for k, v in aux.items()}
        return per_item, mask, aux

    return lifted


# --------------------------------------------------------------------------- the fit loop


@dataclasses.dataclass
class FitResult:
    """What `fit` returns: the best state, its validation loss and the per-check history."""

    state: TrainState
    best_val_loss: float
    history: list[dict[str, float]]
    seconds: float
    steps: int


@dataclasses.dataclass(frozen=True)
class FitProgress:
    """The fit loop's own state, saved (as JSON) with every latest checkpoint.

    With the `TrainState` (step, parameters, optimiser state) it is everything a run needs to go
    on exactly as if never stopped: batches are deterministic from (seed, epoch) and skipped up
    to ``index``; the step's randomness is folded from the step.

    Attributes:
      step: the train state's step when saved (a consistency check).
      epoch, index: the data-stream position of the NEXT batch (epoch, index within the epoch).
      seed: ``TrainConfig.seed``, the seed of the data stream and of the step's randomness.
      best_val_loss: the lowest validation loss so far (inf: none yet).
      best_step: the step of that validation (its state is the ``best`` checkpoint).
      bad_checks: validations since the last improvement (early stopping).
      history: one record per validation so far.
      train_metrics: per-step training metrics of the current epoch so far (they are averaged
        into the next validation record).
      seconds: training time so far.
    """

    step: int
    epoch: int
    index: int
    seed: int
    best_val_loss: float = math.inf
    best_step: int | None = None
    bad_checks: int = 0
    history: tuple[dict[str, float], ...] = ()
    train_metrics: tuple[dict[str, float], ...] = ()
    seconds: float = 0.0

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["best_val_loss"] = (
            None if math.isinf(self.best_val_loss) else self.best_val_loss
        )  # JSON has no inf
        d["history"], d["train_metrics"] = list(self.history), list(self.train_metrics)
        return d

    @classmethod
    def from_json(cls, d: dict) -> FitProgress:
        """Raises `InputError` on a malformed record (a damaged checkpoint)."""
        try:
            best = d["best_val_loss"]
            return cls(
                step=int(d["step"]),
                epoch=int(d["epoch"]),
                index=int(d["index"]),
                seed=int(d["seed"]),
                best_val_loss=math.inf if best is None else float(best),
                best_step=None if d["best_step"] is None else int(d["best_step"]),
                bad_checks=int(d["bad_checks"]),
                history=tuple(dict(h) for h in d["history"]),
                train_metrics=tuple(dict(m) for m in d["train_metrics"]),
                seconds=float(d["seconds"]),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(
                f"checkpoint's fit state is malformed ({type(e).__name__}: {e})", field="fit"
            ) from None


def fit(
    state: TrainState,
    train_step: Callable,
    epoch_batches: Callable[[int], Iterable[Any]],
    evaluate: Callable[[TrainState], dict[str, float]],
    config: TrainConfig,
    *,
    steps_per_epoch: int,
    checkpoints: Checkpoints | None = None,
    run_config: dict | None = None,
    desc: str = "train",
    progress: bool = True,
    best_val_loss: float = math.inf,
    best_state: TrainState | None = None,
    resume_from: FitProgress | None = None,
    max_seconds: float | None = None,
) -> FitResult:
    """Trains until ``max_epochs``/``max_steps``, early stopping or ``max_seconds``; returns the
    best state.

    Args:
      state: the initial `TrainState`.
      train_step: a jitted ``(state, batch, key) -> (state, metrics)`` (`make_train_step`).
      epoch_batches: ``epoch -> iterable of batches`` (deterministic given the epoch).
      evaluate: ``state -> {"val_loss": ..., ...}`` on held-out data.
      steps_per_epoch: batches per epoch.
      checkpoints: where to save best and latest (optional): latest every
        ``config.checkpoint_every_steps`` steps and at each validation, best on improvement.
      run_config: JSON-able config saved with every checkpoint.
      best_val_loss, best_state: the best so far (when resuming; default: none yet).
      resume_from: the loop state saved with the checkpoint ``state`` comes from (`resume_state`):
        the run goes on exactly as if never interrupted. Without it, a state whose step is not 0
        continues at the batch its step implies, with a fresh history and patience.
      max_seconds: a wall-clock budget of this call (None: none): once spent, the loop stops
        after the step that ran over it, validates that state and returns the best one.

    Raises:
      InputError when ``resume_from`` belongs to another step than ``state``.
    """
    from tqdm.auto import tqdm

    base_key = jax.random.key(config.seed)
    max_steps = config.max_steps or config.max_epochs * steps_per_epoch
    total = min(max_steps, config.max_epochs * steps_per_epoch)
    best_state = jax.tree.map(jnp.copy, state if best_state is None else best_state)
    step = int(state.step)
    if resume_from is None:
        resume_from = FitProgress(
            step, *divmod(step, steps_per_epoch), seed=config.seed, best_val_loss=best_val_loss
        )
    if resume_from.step != step or resume_from.seed != config.seed:
        raise InputError(
            f"fit state of step {resume_from.step} (seed {resume_from.seed}) does not go with a train "
            f"state of step {step} (seed {config.seed})",
            field="fit",
        )
    first_epoch, skip = resume_from.epoch, resume_from.index
    best, best_step, bad_checks = best_val_loss, resume_from.best_step, resume_from.bad_checks
    history = [dict(h) for h in resume_from.history]
    every = config.checkpoint_every_steps
    last_saved = step  # the starting point is on disk already (or trivial)
    start = time.perf_counter() - resume_from.seconds
    deadline = math.inf if max_seconds is None else time.perf_counter() + max_seconds

    def progress_at(epoch: int, index: int, train_metrics: list) -> dict:
        # Floats, in place: later saves and the epoch's mean need no further transfers.
        train_metrics[:] = [{k: float(v) for k, v in m.items()} for m in train_metrics]
        return FitProgress(
            step,
            epoch,
            index,
            config.seed,
            best,
            best_step,
            bad_checks,
            tuple(history),
            tuple(train_metrics),
            time.perf_counter() - start,
        ).to_json()

    bar = tqdm(
        total=total,
        initial=min(step, total),
        desc=desc,
        unit="step",
        disable=not progress,
        dynamic_ncols=True,
    )
    try:
        for epoch in range(first_epoch, config.max_epochs):
            if step >= max_steps or bad_checks >= config.patience:
                break  # (a resumed run that had stopped early stays stopped)
            train_metrics = (
                [dict(m) for m in resume_from.train_metrics] if epoch == first_epoch else []
            )
            next_index, exhausted = 0, True
            for i, batch in enumerate(epoch_batches(epoch)):
                if epoch == first_epoch and i < skip:
                    continue  # done before the interruption
                if checkpoints is not None and every and step % every == 0 and step != last_saved:
                    # Saved before running batch i, never between a step and its epoch's
                    # validation: every checkpoint is a point the loop can resume from as is.
                    checkpoints.save_latest(
                        state, run_config or {}, progress_at(epoch, i, train_metrics)
                    )
                    last_saved = step
                state, metrics = train_step(state, batch, base_key)
                train_metrics.append(metrics)
                step += 1
                next_index = i + 1
                bar.update(1)
                if step >= max_steps or time.perf_counter() >= deadline:
                    exhausted = False
                    break
            stop = step >= max_steps or time.perf_counter() >= deadline
            if train_metrics and ((epoch + 1) % config.eval_every == 0 or stop):
                record = {
                    k: float(np.mean([float(m[k]) for m in train_metrics]))
                    for k in train_metrics[0]
                }
                record = {f"train_{k}": v for k, v in record.items()}
                record.update({k: float(v) for k, v in evaluate(state).items()})
                record.update(epoch=epoch + 1, step=step, seconds=time.perf_counter() - start)
                history.append(record)
                improved = record["val_loss"] < best
                if improved:
                    best, best_step, bad_checks = record["val_loss"], step, 0
                    best_state = jax.tree.map(jnp.copy, state)
                    if checkpoints is not None:
                        # Best before latest: a kill between the two leaves a latest from before
                        # this step, and the resumed run reaches (and improves at) it again.
                        checkpoints.save_best(state, run_config or {}, best)
                else:
                    bad_checks += 1
                if checkpoints is not None:
                    position = (epoch + 1, 0) if exhausted else (epoch, next_index)
                    checkpoints.save_latest(
                        state, run_config or {}, progress_at(*position, train_metrics)
                    )
                    last_saved = step
                bar.set_postfix(
                    loss=f"{record['train_loss']:.4g}",
                    val=f"{record['val_loss']:.4g}",
                    best=f"{best:.4g}",
                )
                if bad_checks >= config.patience:
                    break
            if stop:
                break
    finally:
        bar.close()
    return FitResult(best_state, best, history, time.perf_counter() - start, step)


class Resumed(NamedTuple):
    """What `resume_state` hands to `fit`."""

    state: TrainState  # the latest state (or the fresh one)
    best_state: TrainState  # the best so far (or the latest / fresh one when there is none)
    best_val_loss: float  # inf: no validation yet
    progress: FitProgress | None  # the loop state (None: fresh, or a checkpoint without one)


def resume_state(checkpoints: Checkpoints, state: TrainState, run_config: dict) -> Resumed:
    """The latest state of an interrupted run with its loop state and best state, or the fresh
    ``state`` when the folder has no checkpoint yet.

    ``state`` may be replicated over a mesh: the restored states come back with its shardings.

    Raises:
      InputError when the checkpoint was written by a run with another config (a different
      model or data would make "resuming" a silent restart of something else), or cannot be
      read (damaged). Only the length of training (max_steps, max_epochs) and how it is executed
      (num_devices, checkpoint cadence) may change.
    """
    step = checkpoints.latest.latest_step()
    if step is None:
        return Resumed(state, state, math.inf, None)
    saved = _without_length(checkpoints.read_config("latest"))
    wanted = _without_length(run_config)
    if saved != wanted:
        diff = sorted(k for k in set(saved) | set(wanted) if saved.get(k) != wanted.get(k))
        train = sorted(
            k
            for k in set(saved.get("train", {})) | set(wanted.get("train", {}))
            if saved.get("train", {}).get(k) != wanted.get("train", {}).get(k)
        )
        where = diff if diff != ["train"] else [f"train.{k}" for k in train]
        raise InputError(
            f"checkpoint was written with another config (differs in {where}); "
            "use another folder or the same settings",
            file=checkpoints.directory,
        )
    abstract = jax.tree.map(
        lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=_sharding_of(a)), state
    )
    latest, _ = checkpoints.restore(abstract, "latest", step)
    raw = checkpoints.read_progress(step)
    if raw is None:  # a checkpoint of an older version: position from the step, fresh patience
        if checkpoints.best.best_step() is None:
            return Resumed(latest, latest, math.inf, None)
        best, _ = checkpoints.restore(abstract, "best")
        return Resumed(
            latest,
            best,
            float(checkpoints.best.metrics(checkpoints.best.best_step())["val_loss"]),
            None,
        )
    try:
        progress = FitProgress.from_json(raw)
    except InputError as e:
        raise e.at(file=checkpoints.directory / "latest" / str(step)) from None
    if progress.best_step is not None and progress.best_step in checkpoints.best.all_steps():
        best, _ = checkpoints.restore(abstract, "best", progress.best_step)
    else:
        # No validation yet, or the run was killed between saving a new best and the latest:
        # the best on disk is then newer than the latest, and the resumed run reaches that step
        # (and improves at it) again before it can end, so the latest is only a placeholder.
        best = jax.tree.map(jnp.copy, latest)
    return Resumed(latest, best, progress.best_val_loss, progress)


def _sharding_of(a):
    sharding = getattr(a, "sharding", None)
    # Only mesh shardings travel to the restore target: a single-device array restores as today.
    return sharding if isinstance(sharding, jax.sharding.NamedSharding) else None


# Keys of TrainConfig that say how a run is executed, not what it computes.
_EXECUTION_KEYS = (
    "max_steps",
    "max_epochs",
    "num_devices",
    "checkpoint_every_steps",
    "max_to_keep",
)


def _without_length(config: dict) -> dict:
    config = json.loads(json.dumps(to_jsonable(config)))  # tuples -> lists, as saved
    for key in _EXECUTION_KEYS:
        config.get("train", {}).pop(key, None)
    return config


def shuffled_batches(num_items: int, batch_size: int, seed: int, epoch: int) -> list[np.ndarray]:
    """Index batches of one epoch, reproducible from (seed, epoch); the last short batch is
    padded by wrapping around, so every batch has the same shape (one compilation)."""
    rng = np.random.default_rng([seed, epoch])
    order = rng.permutation(num_items)
    n = max(1, math.ceil(num_items / batch_size))
    order = np.resize(order, n * batch_size)
    return [order[i * batch_size : (i + 1) * batch_size] for i in range(n)]


# --------------------------------------------------------------------------- the 3D estimator


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
    mesh = _mesh(tcfg)
    if start is None:
        model = PoseMLP(len(infer_idx), num_keypoints, config.mlp, rngs=nnx.Rngs(tcfg.seed))
        normalisation = None
    else:
        params = jax.tree.map(jnp.copy, start.params)
        model = nnx.merge(start.graphdef, params, start.rest)
        normalisation = start.normalisation
    tx = make_optimizer(tcfg, steps_per_epoch)
    graphdef, rest, state = init_train_state(model, tx)
    loss_fn = estimator_loss_fn(
        rig_train, rig_infer, config.num_augment, config.loss_power, normalisation
    )
    train_step = make_train_step(graphdef, rest, tx, loss_fn, mesh=mesh)
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
    setup = estimator_training(rig, config, train_xy.shape[-2], steps_per_epoch=steps_per_epoch)
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
    centre, radius = rig_centre_and_radius(setup.rig_train)
    # The normalised frame travels with the model (inference may hold only the inference cameras).
    run_config["frame"] = [float(x) for x in np.asarray(centre)] + [float(radius)]
    result = _fit_resumable(
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


def _mesh(config: TrainConfig) -> jax.sharding.Mesh | None:
    """The data-parallel mesh of ``config.num_devices`` (None: one device, no mesh)."""
    if config.num_devices is None:
        return None
    try:
        return make_data_mesh(config.num_devices)
    except ValueError as e:
        raise InputError(str(e), field="num_devices") from None


def _fit_resumable(
    state,
    train_step,
    epoch_batches,
    evaluate,
    config: TrainConfig,
    *,
    steps_per_epoch: int,
    checkpoint_dir: str | Path | None,
    run_config: dict,
    resume: bool,
    desc: str,
    progress: bool,
) -> FitResult:
    """`fit` with the checkpoints of ``checkpoint_dir`` (optional), continuing the latest one
    when ``resume`` (`resume_state`); both trainers' loop."""
    checkpoints = (
        None
        if checkpoint_dir is None
        else ModelFolder(checkpoint_dir).checkpoints(max_to_keep=config.max_to_keep)
    )
    try:
        resumed = Resumed(state, None, math.inf, None)
        if resume and checkpoints is not None:
            resumed = resume_state(checkpoints, state, run_config)
        return fit(
            resumed.state,
            train_step,
            epoch_batches,
            evaluate,
            config,
            steps_per_epoch=steps_per_epoch,
            checkpoints=checkpoints,
            run_config=run_config,
            desc=desc,
            progress=progress,
            best_val_loss=resumed.best_val_loss,
            best_state=resumed.best_state,
            resume_from=resumed.progress,
        )
    finally:
        if checkpoints is not None:
            checkpoints.close()


# =========================================================================== skeleton matching
# (DESIGN.md §1.2) Self-supervised: labels come from composing single-person recordings.


# The paper's matcher optimisation: Adam 1e-4, 15 graphs per batch, validation every 5 epochs,
# early stop after 5 checks without improvement. (Gradient clipping at 10 is ours; it only acts
# on rare spikes.)
def matcher_loss_fn(
    model: MatchingGAT, batch: GraphBatch, key
) -> tuple[jax.Array, jax.Array, dict]:
    """``loss_fn(model, batch, key)`` of the matcher for `make_train_step`: MSE on match nodes."""
    del key  # augmentation happens on the host, when samples are composed
    scores = model(batch)
    mask = batch.is_match & batch.node_mask
    correct = (scores > 0.5) == (batch.label > 0.5)
    return (
        match_mse(scores, batch.label),
        mask,
        {"accuracy": masked_mean(correct.astype(jnp.float32), mask)},
    )


def train_matcher(
    rig: Rig,
    train_recordings: Sequence[Recording],
    dev_recordings: Sequence[Recording],
    config: MatcherConfig = MatcherConfig(),
    *,
    checkpoint_dir: str | Path | None = None,
    progress: bool = True,
    resume: bool = False,
) -> tuple[Matcher, FitResult]:
    """Trains a skeleton matcher from single-person recordings alone (no association labels).

    With ``config.train.num_devices``, each step's graphs are split by whole graphs over the
    devices (`split_graph_batch`), the same samples in the same order as on one device.

    Args:
      rig: a rig holding (at least) the inference cameras.
      train_recordings, dev_recordings: single-person recordings (each needs the cameras).
      config: `MatcherConfig`.
      checkpoint_dir: where best and latest checkpoints go (optional).
      resume: continue from the latest checkpoint in ``checkpoint_dir`` (same config required).
    Returns:
      (the best `Matcher`, the `FitResult`).
    """
    tcfg = config.train
    rig_infer = rig.select(list(config.cameras or rig.names))
    train_pool = make_pool(rig_infer, train_recordings)
    dev_pool = make_pool(rig_infer, dev_recordings)
    compose = dict(
        max_people=config.max_people,
        subset_probability=config.subset_probability,
        min_views=config.min_views,
        keypoint_dropout=config.keypoint_dropout,
    )
    per_batch = tcfg.batch_size
    steps_per_epoch = config.steps_per_epoch
    num_dev = max(1, math.ceil(config.num_dev_samples / per_batch))
    dev_batches = sample_batches(
        dev_pool, np.random.default_rng([tcfg.seed, 1 << 30]), num_dev, per_batch, **compose
    )

    K = train_recordings[0].num_keypoints
    model = MatchingGAT(rig_infer.num_cameras, K, config.gat, rngs=nnx.Rngs(tcfg.seed))
    tx = make_optimizer(config.train, config.steps_per_epoch)
    graphdef, rest, state = init_train_state(model, tx)
    mesh = _mesh(tcfg)
    if mesh is None:
        step = make_train_step(graphdef, rest, tx, matcher_loss_fn)
        eval_batch = jax.jit(functools.partial(matcher_eval_sums, graphdef, rest))
    else:
        step = make_train_step(graphdef, rest, tx, stacked_loss_fn(matcher_loss_fn), mesh=mesh)
        eval_batch = jax.jit(functools.partial(_stacked_matcher_eval, graphdef, rest))
        state = replicate(mesh, state)
        dev_batches = [
            shard_batch(mesh, split_graph_batch(b, mesh_size(mesh))[0]) for b in dev_batches
        ]

    def epoch_batches(epoch):
        rng = np.random.default_rng([tcfg.seed, epoch])
        # Built lazily: the host builds batch i+1 while the device runs step i (async dispatch).
        for _ in range(steps_per_epoch):
            batch = sample_batches(train_pool, rng, 1, per_batch, **compose)[0]
            # The global batch (the same on every host), one padded block of graphs per device.
            yield (
                batch
                if mesh is None
                else shard_batch(mesh, split_graph_batch(batch, mesh_size(mesh))[0])
            )

    def evaluate(state):
        sums = [eval_batch(state.params, b) for b in dev_batches]
        total = {k: sum(float(s[k]) for s in sums) for k in sums[0]}
        n = max(total["count"], 1.0)
        return {"val_loss": total["sq_error"] / n, "val_accuracy": total["correct"] / n}

    run_config = {**to_jsonable(dataclasses.asdict(config)), "num_keypoints": K}
    result = _fit_resumable(
        state,
        step,
        epoch_batches,
        evaluate,
        tcfg,
        steps_per_epoch=steps_per_epoch,
        checkpoint_dir=checkpoint_dir,
        run_config=run_config,
        resume=resume,
        desc="matcher",
        progress=progress,
    )
    return Matcher(graphdef, rest, result.state.params, rig_infer, config), result


def matcher_eval_sums(graphdef, rest, params, batch: GraphBatch) -> dict[str, jax.Array]:
    """The matcher's squared errors, correct decisions (at 0.5) and count over a batch's real
    match nodes (sums, so that batches add up)."""
    scores = nnx.merge(graphdef, params, rest)(batch)
    mask = (batch.is_match & batch.node_mask).astype(jnp.float32)
    correct = ((scores > 0.5) == (batch.label > 0.5)).astype(jnp.float32)
    return {
        "sq_error": jnp.sum(match_mse(scores, batch.label) * mask),
        "correct": jnp.sum(correct * mask),
        "count": jnp.sum(mask),
    }


def _stacked_matcher_eval(graphdef, rest, params, batch: GraphBatch) -> dict[str, jax.Array]:
    sums = jax.vmap(lambda b: matcher_eval_sums(graphdef, rest, params, b))(batch)  # (S,) each
    return {k: jnp.sum(v) for k, v in sums.items()}
