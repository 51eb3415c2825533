"""Training: train states, jit-compiled steps, the fit loop, early stopping, orbax checkpoints.

Shape of every model's training (STYLE.md §4): an explicit `TrainState` pytree; one pure step
``(state, batch) -> (state, metrics)`` compiled once; a Python `fit` loop that evaluates every
``eval_every`` epochs, stops after ``patience`` checks without improvement, keeps the best
parameters, and checkpoints best and latest with orbax (the only orbax import in the package).

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
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from mvpose_jax.cameras import Rig, rig_centre_and_radius
from mvpose_jax.data.recording import Recording
from mvpose_jax.errors import InputError
from mvpose_jax.features import EstimatorInputs, assemble_features, estimator_inputs
from mvpose_jax.graphs import GraphBatch, make_pool, sample_batches
from mvpose_jax.losses import masked_mean, match_mse, reprojection_error_l1
from mvpose_jax.models import GATConfig, MatchingGAT, MLPConfig, PoseMLP, to_world


class TrainState(NamedTuple):
    """Everything that changes during training."""

    step: jax.Array  # () int32
    params: nnx.State  # trainable nnx.Param leaves
    opt_state: optax.OptState


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (defaults: the paper's for the 3D estimator).

    Attributes:
      learning_rate: Adam's step size (paper 1e-4).
      clip_norm: global gradient-norm clip (paper 10).
      batch_size: seed samples per step (augmented ones come on top).
      max_epochs: hard limit on passes over the training set.
      max_steps: optional hard limit on steps (None: epochs decide).
      eval_every: validate every this many epochs.
      patience: stop after this many validations without improvement (paper 20).
      seed: seeds initialisation, shuffling and augmentation.
      final_lr_fraction: 1.0 keeps the step size constant (the paper); below 1 it decays on a
        cosine to this fraction of ``learning_rate`` at the last step (shorter CPU runs).
    """

    learning_rate: float = 1e-4
    clip_norm: float = 10.0
    batch_size: int = 256
    max_epochs: int = 10_000
    max_steps: int | None = None
    eval_every: int = 1
    patience: int = 20
    seed: int = 0
    final_lr_fraction: float = 1.0


def make_optimizer(config: TrainConfig, steps_per_epoch: int = 1) -> optax.GradientTransformation:
    """Adam with global-norm clipping; below ``final_lr_fraction`` 1, a cosine decay over the run
    (``max_steps``, else ``max_epochs * steps_per_epoch``)."""
    lr = config.learning_rate
    if config.final_lr_fraction < 1.0:
        total = config.max_steps or config.max_epochs * steps_per_epoch
        lr = optax.cosine_decay_schedule(config.learning_rate, total, alpha=config.final_lr_fraction)
    return optax.chain(optax.clip_by_global_norm(config.clip_norm), optax.adam(lr))


def init_train_state(model: nnx.Module, tx: optax.GradientTransformation):
    """Splits a model once; returns (graphdef, rest, TrainState) with committed, typed leaves."""
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    # An explicit int32 counter and device_put avoid a recompile after a checkpoint restore.
    state = TrainState(jnp.zeros((), jnp.int32), params, tx.init(params))
    return graphdef, rest, jax.device_put(state)


def make_train_step(graphdef, rest, tx, loss_fn: Callable):
    """A jitted ``(state, batch) -> (state, metrics)``.

    ``loss_fn(model, batch, key) -> (per_item, mask, metrics)``: unreduced losses and their mask;
    the step reduces them with `masked_mean`. ``key`` is folded from the step, so a resumed run
    draws the same randomness as an uninterrupted one.
    """

    @functools.partial(jax.jit, donate_argnums=0)
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


# --------------------------------------------------------------------------- checkpoints


class Checkpoints:
    """Best and latest checkpoints of a run (orbax), each with the run's config as JSON.

    ``directory/best`` keeps the state with the lowest validation loss, ``directory/latest`` the
    newest; both are written atomically by orbax (temporary folder, then rename).
    """

    def __init__(self, directory: str | Path):
        import orbax.checkpoint as ocp

        self._ocp = ocp
        self.directory = Path(directory).absolute()
        opts = dict(enable_async_checkpointing=False)
        self.best = ocp.CheckpointManager(
            self.directory / "best",
            options=ocp.CheckpointManagerOptions(
                max_to_keep=1, best_fn=lambda m: m["val_loss"], best_mode="min", **opts
            ),
            item_names=("state", "config"),
        )
        self.latest = ocp.CheckpointManager(
            self.directory / "latest",
            options=ocp.CheckpointManagerOptions(max_to_keep=1, **opts),
            item_names=("state", "config"),
        )

    def _args(self, state, config):
        ocp = self._ocp
        return ocp.args.Composite(state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config))

    def save_latest(self, state: TrainState, config: dict) -> None:
        self.latest.save(int(state.step), args=self._args(state, config), force=True)

    def save_best(self, state: TrainState, config: dict, val_loss: float) -> None:
        self.best.save(
            int(state.step), args=self._args(state, config), metrics={"val_loss": float(val_loss)}, force=True
        )

    def restore(self, abstract_state: TrainState, which: str = "best") -> tuple[TrainState, dict]:
        """Restores ``which`` ("best" or "latest") against an abstract target."""
        ocp = self._ocp
        manager = self.best if which == "best" else self.latest
        step = manager.best_step() if which == "best" else manager.latest_step()
        if step is None:
            raise InputError(f"no {which} checkpoint", file=self.directory / which)
        try:
            out = manager.restore(
                step,
                args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(abstract_state), config=ocp.args.JsonRestore()
                ),
            )
        except (ValueError, KeyError, TypeError, FileNotFoundError) as e:
            raise InputError(
                f"checkpoint does not match this model or is damaged ({type(e).__name__}: {e})",
                file=self.directory / which / str(step),
            ) from None
        return jax.device_put(out.state), dict(out.config)

    def read_config(self, which: str = "best") -> dict:
        """The run config saved with the ``which`` checkpoint (to rebuild the model first)."""
        ocp = self._ocp
        manager = self.best if which == "best" else self.latest
        step = manager.best_step() if which == "best" else manager.latest_step()
        if step is None:
            raise InputError(f"no {which} checkpoint", file=self.directory / which)
        out = manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
        return dict(out.config)

    def close(self) -> None:
        self.best.close()
        self.latest.close()


# --------------------------------------------------------------------------- the fit loop


@dataclasses.dataclass
class FitResult:
    """What `fit` returns: the best state, its validation loss and the per-check history."""

    state: TrainState
    best_val_loss: float
    history: list[dict[str, float]]
    seconds: float
    steps: int


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
) -> FitResult:
    """Trains until ``max_epochs``/``max_steps`` or early stopping; returns the best state.

    Args:
      state: the initial `TrainState`.
      train_step: a jitted ``(state, batch, key) -> (state, metrics)`` (`make_train_step`).
      epoch_batches: ``epoch -> iterable of batches`` (deterministic given the epoch).
      evaluate: ``state -> {"val_loss": ..., ...}`` on held-out data.
      steps_per_epoch: for the progress bar.
      checkpoints: where to save best and latest (optional).
      run_config: JSON-able config saved with every checkpoint.
      best_val_loss, best_state: the best so far (when resuming; default: none yet).

    A state whose step is not 0 (a restored checkpoint) continues where it stopped: the epoch's
    batches are deterministic and the step's randomness is folded from the step, so the run
    goes on as if never interrupted (early-stopping patience restarts from zero).
    """
    from tqdm.auto import tqdm

    base_key = jax.random.key(config.seed)
    max_steps = config.max_steps or config.max_epochs * steps_per_epoch
    total = min(max_steps, config.max_epochs * steps_per_epoch)
    best_state = jax.tree.map(jnp.copy, state if best_state is None else best_state)
    best, bad_checks, history = best_val_loss, 0, []
    step = int(state.step)
    first_epoch, skip = divmod(step, steps_per_epoch)
    start = time.perf_counter()
    bar = tqdm(total=total, initial=min(step, total), desc=desc, unit="step", disable=not progress,
               dynamic_ncols=True)  # fmt: skip
    try:
        for epoch in range(first_epoch, config.max_epochs):
            if step >= max_steps:
                break
            train_metrics = []
            for i, batch in enumerate(epoch_batches(epoch)):
                if epoch == first_epoch and i < skip:
                    continue  # done before the interruption
                state, metrics = train_step(state, batch, base_key)
                train_metrics.append(metrics)
                step += 1
                bar.update(1)
                if step >= max_steps:
                    break
            stop = step >= max_steps
            if train_metrics and ((epoch + 1) % config.eval_every == 0 or stop):
                record = {k: float(np.mean([float(m[k]) for m in train_metrics])) for k in train_metrics[0]}
                record = {f"train_{k}": v for k, v in record.items()}
                record.update({k: float(v) for k, v in evaluate(state).items()})
                record.update(epoch=epoch + 1, step=step, seconds=time.perf_counter() - start)
                history.append(record)
                improved = record["val_loss"] < best
                if improved:
                    best, bad_checks = record["val_loss"], 0
                    best_state = jax.tree.map(jnp.copy, state)
                    if checkpoints is not None:
                        checkpoints.save_best(state, run_config or {}, best)
                else:
                    bad_checks += 1
                if checkpoints is not None:
                    checkpoints.save_latest(state, run_config or {})
                bar.set_postfix(loss=f"{record['train_loss']:.4g}", val=f"{record['val_loss']:.4g}",
                                best=f"{best:.4g}")  # fmt: skip
                if bad_checks >= config.patience:
                    break
            if stop:
                break
    finally:
        bar.close()
    return FitResult(best_state, best, history, time.perf_counter() - start, step)


def resume_state(
    checkpoints: Checkpoints, state: TrainState, run_config: dict
) -> tuple[TrainState, TrainState, float]:
    """(latest state, best state, best validation loss) of an interrupted run, or the fresh
    ``state`` (twice) and inf when the folder has no checkpoint yet.

    Raises:
      InputError when the checkpoint was written by a run with another config (a different
      model or data would make "resuming" a silent restart of something else). Only the
      length of training (max_steps, max_epochs) may change, to extend a run.
    """
    if checkpoints.latest.latest_step() is None:
        return state, state, math.inf
    saved = _without_length(checkpoints.read_config("latest"))
    wanted = _without_length(run_config)
    if saved != wanted:
        diff = sorted(k for k in set(saved) | set(wanted) if saved.get(k) != wanted.get(k))
        raise InputError(f"checkpoint was written with another config (differs in {diff}); "
                         "use another folder or the same settings", file=checkpoints.directory)  # fmt: skip
    abstract = jax.eval_shape(lambda: state)
    latest, _ = checkpoints.restore(abstract, "latest")
    if checkpoints.best.best_step() is None:
        return latest, latest, math.inf
    best, _ = checkpoints.restore(abstract, "best")
    return latest, best, float(checkpoints.best.metrics(checkpoints.best.best_step())["val_loss"])


def _without_length(config: dict) -> dict:
    config = json.loads(json.dumps(_jsonable(config)))  # tuples -> lists, as saved
    for key in ("max_steps", "max_epochs"):
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
    rig_train: Rig, infer_cameras: Sequence[int], xy: jax.Array, score: jax.Array
) -> EstimatorBatch:
    """Builds estimator samples from people's detections in the training cameras.

    Args:
      rig_train: the training cameras C_t.
      infer_cameras: indices into C_t of the inference cameras C_i.
      xy: (N, C_t, K, 2) pixels; score: (N, C_t, K).
    """
    idx = np.asarray(infer_cameras)
    rig_infer = rig_train.select(list(idx))
    xy = jnp.asarray(xy, jnp.float32)
    score = jnp.asarray(score, jnp.float32)
    inputs = estimator_inputs(rig_infer, xy[:, idx], score[:, idx])
    available = (score[:, idx] > 0).any(axis=-1)
    return EstimatorBatch(inputs, available, xy, score)


def random_view_subsets(key: jax.Array, available: jax.Array, num: int) -> tuple[jax.Array, jax.Array]:
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
    size = 1 + jnp.floor(jax.random.uniform(k_size, (num, N)) * jnp.maximum(n_avail - 1, 1)[None]).astype(jnp.int32)
    priority = jnp.where(available[None], jax.random.uniform(k_order, (num, N, C)), -1.0)
    rank = jnp.argsort(jnp.argsort(-priority, axis=-1), axis=-1)  # 0 = highest priority
    masks = (rank < size[..., None]) & available[None]
    return masks, jnp.broadcast_to(n_avail >= 2, (num, N))


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
    """A 3D estimator: its cameras, network and training.

    Attributes:
      train_cameras: names of C_t (None: every camera of the rig).
      infer_cameras: names of C_i, a subset of C_t (None: C_t).
      mlp: the network.
      train: optimisation.
      num_augment: derived view-subset samples per seed sample (paper: up to 4).
      loss_power: the per-sample loss is e_d ** loss_power, e_d the summed Manhattan
        reprojection error; 2 is the paper's. 1 weighs every sample alike, so a few samples
        with gross detector errors (swapped limbs, a false positive taken for the person)
        cannot drown the rest.
    """

    train_cameras: tuple[str, ...] | None = None
    infer_cameras: tuple[str, ...] | None = None
    mlp: MLPConfig = MLPConfig()
    train: TrainConfig = TrainConfig()
    num_augment: int = 4
    loss_power: float = 2.0


class Estimator(NamedTuple):
    """A trained 3D estimator: what inference needs."""

    graphdef: Any
    rest: Any
    params: Any
    rig_infer: Rig
    config: EstimatorConfig


def estimator_loss_fn(rig_train: Rig, rig_infer: Rig, num_augment: int, loss_power: float = 2.0):
    """``loss_fn(model, batch, key)`` of the estimator, for `make_train_step`."""
    centre, radius = rig_centre_and_radius(rig_infer)

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
      resume: continue from the latest checkpoint in ``checkpoint_dir`` (same config required).
    Returns:
      (the best `Estimator`, the `FitResult`).
    """
    train_names = config.train_cameras or rig.names
    infer_names = config.infer_cameras or train_names
    rig_train = rig.select(list(train_names))
    missing = [c for c in infer_names if c not in train_names]
    if missing:
        raise InputError(f"inference cameras {missing} are not training cameras", field="infer_cameras")
    infer_idx = [train_names.index(c) for c in infer_names]
    rig_infer = rig_train.select(infer_idx)
    K = train_xy.shape[-2]
    tcfg = config.train

    def batches_of(xy, score, chunk=4096):
        parts = [make_estimator_batch(rig_train, infer_idx, xy[i : i + chunk], score[i : i + chunk])
                 for i in range(0, len(xy), chunk)]  # fmt: skip
        return jax.tree.map(lambda *a: jnp.concatenate(a), *parts)

    train_data = batches_of(train_xy, train_score)
    dev_data = batches_of(dev_xy, dev_score)

    n_train = len(train_xy)
    batch = min(tcfg.batch_size, n_train)
    steps_per_epoch = math.ceil(n_train / batch)
    model = PoseMLP(len(infer_idx), K, config.mlp, rngs=nnx.Rngs(tcfg.seed))
    tx = make_optimizer(tcfg, steps_per_epoch)
    graphdef, rest, state = init_train_state(model, tx)
    loss_fn = estimator_loss_fn(rig_train, rig_infer, config.num_augment, config.loss_power)
    step = make_train_step(graphdef, rest, tx, loss_fn)
    eval_loss = jax.jit(
        functools.partial(_estimator_eval, graphdef, rest, rig_train, rig_infer, config.loss_power)
    )

    def epoch_batches(epoch):
        for idx in shuffled_batches(n_train, batch, tcfg.seed, epoch):
            yield jax.tree.map(lambda a: a[idx], train_data)

    def evaluate(state):
        return {k: float(v) for k, v in eval_loss(state.params, dev_data).items()}

    checkpoints = Checkpoints(checkpoint_dir) if checkpoint_dir is not None else None
    run_config = _jsonable(dataclasses.asdict(config))
    # What restoring needs beyond the config: the resolved cameras and the keypoint count.
    run_config.update(train_cameras=list(train_names), infer_cameras=list(infer_names), num_keypoints=int(K))
    try:
        best_state, best = None, math.inf
        if resume and checkpoints is not None:
            state, best_state, best = resume_state(checkpoints, state, run_config)
        result = fit(
            state, step, epoch_batches, evaluate, tcfg, steps_per_epoch=steps_per_epoch,
            checkpoints=checkpoints, run_config=run_config, desc="estimator", progress=progress,
            best_val_loss=best, best_state=best_state,
        )  # fmt: skip
    finally:
        if checkpoints is not None:
            checkpoints.close()
    return Estimator(graphdef, rest, result.state.params, rig_infer, config), result


def estimator_config_from_dict(d: dict) -> EstimatorConfig:
    """Rebuilds an `EstimatorConfig` from its saved JSON form (`dataclasses.asdict`)."""
    tup = lambda v: None if v is None else tuple(v)  # noqa: E731
    try:
        mlp = MLPConfig(**{**d["mlp"], "widths": tuple(d["mlp"]["widths"])})
        return EstimatorConfig(
            train_cameras=tup(d["train_cameras"]), infer_cameras=tup(d["infer_cameras"]), mlp=mlp,
            train=TrainConfig(**d["train"]), num_augment=d["num_augment"], loss_power=d["loss_power"],
        )  # fmt: skip
    except (KeyError, TypeError) as e:
        raise InputError(f"not an estimator config ({e})", field="config") from None


def load_estimator(directory: str | Path, rig: Rig, which: str = "best") -> Estimator:
    """Restores an estimator saved by `train_estimator` (its config comes with the checkpoint).

    Args:
      directory: the ``checkpoint_dir`` of training.
      rig: a rig holding the estimator's inference cameras (by name).
    """
    checkpoints = Checkpoints(directory)
    try:
        saved = checkpoints.read_config(which)
        config = estimator_config_from_dict(saved)
        if "num_keypoints" not in saved:
            raise InputError("checkpoint config lacks num_keypoints", file=directory, field="config")
        rig_infer = rig.select(list(config.infer_cameras or config.train_cameras or rig.names))
        K = int(saved["num_keypoints"])
        model = PoseMLP(rig_infer.num_cameras, K, config.mlp, rngs=nnx.Rngs(0))
        graphdef, rest, state = init_train_state(model, make_optimizer(config.train))
        state, _ = checkpoints.restore(jax.eval_shape(lambda: state), which)
    finally:
        checkpoints.close()
    return Estimator(graphdef, rest, state.params, rig_infer, config)


def _estimator_eval(graphdef, rest, rig_train, rig_infer, loss_power, params, data: EstimatorBatch):
    centre, radius = rig_centre_and_radius(rig_infer)
    model = nnx.merge(graphdef, params, rest)
    feats = assemble_features(data.inputs, data.available)
    xyz = to_world(model(feats), centre, radius)
    err = reprojection_error_l1(rig_train, xyz, data.xy, data.score)
    ok = data.available.any(-1)
    n_kp = jnp.maximum((data.score > 0).sum(axis=(1, 2)), 1)
    return {"val_loss": masked_mean(err**loss_power, ok), "val_px_per_keypoint": masked_mean(err / n_kp, ok)}


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


# =========================================================================== skeleton matching
# (DESIGN.md §1.2) Self-supervised: labels come from composing single-person recordings.


# The paper's matcher optimisation: Adam 1e-4, 15 graphs per batch, validation every 5 epochs,
# early stop after 5 checks without improvement. (Gradient clipping at 10 is ours; it only acts
# on rare spikes.)
MATCHER_TRAIN = TrainConfig(learning_rate=1e-4, batch_size=15, max_epochs=1000, eval_every=5, patience=5)


@dataclasses.dataclass(frozen=True)
class MatcherConfig:
    """A skeleton matcher: its cameras, network, training and training-sample composition.

    Attributes:
      cameras: names of the inference cameras C_i (None: every camera of the rig).
      gat: the network.
      train: optimisation; ``batch_size`` counts graphs (frames) per step.
      max_people: most single-person frames composed into one training frame. The paper draws
        up to the number of recordings; we cap it (default 8, the largest test scene) so graph
        sizes stay those of real scenes however many recordings there are.
      samples_per_epoch: composed training frames per epoch (samples are streamed, never stored).
      num_dev_samples: composed validation frames, drawn once from the dev recordings.
      subset_probability: share of samples that keep only a random subset of the views.
      min_views: the smallest view subset kept by augmentation.
    """

    cameras: tuple[str, ...] | None = None
    gat: GATConfig = GATConfig()
    train: TrainConfig = MATCHER_TRAIN
    max_people: int = 8
    samples_per_epoch: int = 1500
    num_dev_samples: int = 300
    subset_probability: float = 0.5
    min_views: int = 2

    @property
    def steps_per_epoch(self) -> int:
        return max(1, self.samples_per_epoch // self.train.batch_size)

    @classmethod
    def quick(cls, cameras: tuple[str, ...] | None = None) -> MatcherConfig:
        """The small network, a larger step size and short epochs (tests, quick experiments)."""
        train = dataclasses.replace(MATCHER_TRAIN, learning_rate=1e-3, max_epochs=50, eval_every=2)
        return cls(cameras=cameras, gat=GATConfig.quick(), train=train, samples_per_epoch=300,
                   num_dev_samples=90)  # fmt: skip


class Matcher(NamedTuple):
    """A trained skeleton matcher: what inference needs."""

    graphdef: Any
    rest: Any
    params: Any
    rig: Rig  # the inference cameras C_i, in the order of the features' camera slots
    config: MatcherConfig


def matcher_loss_fn(model: MatchingGAT, batch: GraphBatch, key) -> tuple[jax.Array, jax.Array, dict]:
    """``loss_fn(model, batch, key)`` of the matcher for `make_train_step`: MSE on match nodes."""
    del key  # augmentation happens on the host, when samples are composed
    scores = model(batch)
    mask = batch.is_match & batch.node_mask
    correct = (scores > 0.5) == (batch.label > 0.5)
    return match_mse(scores, batch.label), mask, {"accuracy": masked_mean(correct.astype(jnp.float32), mask)}


def train_matcher(
    rig: Rig,
    train_recordings: Sequence[Recording],
    dev_recordings: Sequence[Recording],
    config: MatcherConfig = MatcherConfig(),
    *,
    checkpoint_dir: str | Path | None = None,
    progress: bool = True,
) -> tuple[Matcher, FitResult]:
    """Trains a skeleton matcher from single-person recordings alone (no association labels).

    Args:
      rig: a rig holding (at least) the inference cameras.
      train_recordings, dev_recordings: single-person recordings (each needs the cameras).
      config: `MatcherConfig`.
      checkpoint_dir: where best and latest checkpoints go (optional).
    Returns:
      (the best `Matcher`, the `FitResult`).
    """
    tcfg = config.train
    rig_infer = rig.select(list(config.cameras or rig.names))
    train_pool = make_pool(rig_infer, train_recordings)
    dev_pool = make_pool(rig_infer, dev_recordings)
    compose = dict(max_people=config.max_people, subset_probability=config.subset_probability,
                   min_views=config.min_views)  # fmt: skip
    per_batch = tcfg.batch_size
    steps_per_epoch = config.steps_per_epoch
    num_dev = max(1, math.ceil(config.num_dev_samples / per_batch))
    dev_batches = sample_batches(dev_pool, np.random.default_rng([tcfg.seed, 1 << 30]), num_dev, per_batch, **compose)

    K = train_recordings[0].num_keypoints
    model = MatchingGAT(rig_infer.num_cameras, K, config.gat, rngs=nnx.Rngs(tcfg.seed))
    tx = make_optimizer(config.train, config.steps_per_epoch)
    graphdef, rest, state = init_train_state(model, tx)
    step = make_train_step(graphdef, rest, tx, matcher_loss_fn)
    eval_batch = jax.jit(functools.partial(_matcher_eval, graphdef, rest))

    def epoch_batches(epoch):
        rng = np.random.default_rng([tcfg.seed, epoch])
        # Built lazily: the host builds batch i+1 while the device runs step i (async dispatch).
        for _ in range(steps_per_epoch):
            yield sample_batches(train_pool, rng, 1, per_batch, **compose)[0]

    def evaluate(state):
        sums = [eval_batch(state.params, b) for b in dev_batches]
        total = {k: sum(float(s[k]) for s in sums) for k in sums[0]}
        n = max(total["count"], 1.0)
        return {"val_loss": total["sq_error"] / n, "val_accuracy": total["correct"] / n}

    checkpoints = Checkpoints(checkpoint_dir) if checkpoint_dir is not None else None
    try:
        result = fit(
            state, step, epoch_batches, evaluate, tcfg, steps_per_epoch=steps_per_epoch,
            checkpoints=checkpoints, run_config={**_jsonable(dataclasses.asdict(config)), "num_keypoints": K},
            desc="matcher",
            progress=progress,
        )  # fmt: skip
    finally:
        if checkpoints is not None:
            checkpoints.close()
    return Matcher(graphdef, rest, result.state.params, rig_infer, config), result


def matcher_config_from_dict(d: dict) -> MatcherConfig:
    """Rebuilds a `MatcherConfig` from its saved JSON form (`dataclasses.asdict`)."""
    try:
        gat = GATConfig(**{**d["gat"], "widths": tuple(d["gat"]["widths"]), "heads": tuple(d["gat"]["heads"])})
        fields = {f.name for f in dataclasses.fields(MatcherConfig)} - {"cameras", "gat", "train"}
        return MatcherConfig(cameras=None if d["cameras"] is None else tuple(d["cameras"]), gat=gat,
                             train=TrainConfig(**d["train"]), **{k: d[k] for k in fields if k in d})  # fmt: skip
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"not a matcher config ({e})", field="config") from None


def load_matcher(directory: str | Path, rig: Rig, config: MatcherConfig | None = None,
                 num_keypoints: int | None = None, which: str = "best") -> Matcher:  # fmt: skip
    """Restores a matcher saved by `train_matcher`.

    ``config`` and ``num_keypoints`` default to those saved with the checkpoint (checkpoints of
    older runs lack the keypoint count and need it passed).
    """
    if config is None or num_keypoints is None:
        checkpoints = Checkpoints(directory)
        try:
            saved = checkpoints.read_config(which)
        finally:
            checkpoints.close()
        config = config or matcher_config_from_dict(saved)
        if num_keypoints is None:
            if "num_keypoints" not in saved:
                raise InputError("checkpoint config lacks num_keypoints; pass it", file=directory, field="config")
            num_keypoints = int(saved["num_keypoints"])
    rig_infer = rig.select(list(config.cameras or rig.names))
    model = MatchingGAT(rig_infer.num_cameras, num_keypoints, config.gat, rngs=nnx.Rngs(0))
    graphdef, rest, state = init_train_state(model, make_optimizer(config.train, config.steps_per_epoch))
    checkpoints = Checkpoints(directory)
    try:
        state, _ = checkpoints.restore(jax.eval_shape(lambda: state), which)
    finally:
        checkpoints.close()
    return Matcher(graphdef, rest, state.params, rig_infer, config)


def _matcher_eval(graphdef, rest, params, batch: GraphBatch) -> dict[str, jax.Array]:
    scores = nnx.merge(graphdef, params, rest)(batch)
    mask = (batch.is_match & batch.node_mask).astype(jnp.float32)
    correct = ((scores > 0.5) == (batch.label > 0.5)).astype(jnp.float32)
    return {"sq_error": jnp.sum(match_mse(scores, batch.label) * mask), "correct": jnp.sum(correct * mask),
            "count": jnp.sum(mask)}  # fmt: skip
