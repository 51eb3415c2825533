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

Each model's own training builds on this module: `estimator_training` (the 3D estimator) and
`matcher_training` (the skeleton matcher). No 3D ground truth is an input of anything here.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from mvpose_jax.checkpoints import Checkpoints, TrainState  # TrainState: defined with what holds it
from mvpose_jax.compiled import xla_kernel_options
from mvpose_jax.data.files import to_jsonable
from mvpose_jax.errors import InputError
from mvpose_jax.losses import masked_mean
from mvpose_jax.parallel import make_data_mesh, replicated
from mvpose_jax.trained import (
    ModelFolder,
    TrainConfig,
)

if TYPE_CHECKING:  # annotations only: importing data.recording loads every reader
    pass


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
    graphdef,
    rest,
    tx,
    loss_fn: Callable,
    *,
    mesh: jax.sharding.Mesh | None = None,
    xla_kernels: bool = False,
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

    ``xla_kernels``: compiled with `compiled.xla_kernel_options` (XLA's own CPU kernels, not its
    YNNPACK fusions; nothing changes on a GPU). The matcher's and the estimator's steps take it:
    on 2 CPU cores they run 13 and 17 % faster (the quick scale's 5-view GAT, its MLP), the same
    arithmetic in another order.
    """
    out_shardings = None if mesh is None else replicated(mesh)
    options = (xla_kernel_options() or None) if xla_kernels else None

    @functools.partial(
        jax.jit, donate_argnums=0, out_shardings=out_shardings, compiler_options=options
    )
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
    from mvpose_jax.progress import progress_bar

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

    bar = progress_bar(
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


def training_mesh(config: TrainConfig) -> jax.sharding.Mesh | None:
    """The data-parallel mesh of ``config.num_devices`` (None: one device, no mesh)."""
    if config.num_devices is None:
        return None
    try:
        return make_data_mesh(config.num_devices)
    except ValueError as e:
        raise InputError(str(e), field="num_devices") from None


def fit_resumable(
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
