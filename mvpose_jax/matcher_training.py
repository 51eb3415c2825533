"""The skeleton matcher's training (DESIGN.md §1.2): `train_matcher`, on multi-person samples
composed from single-person recordings (`graphs.sample_batches`), split by whole graphs over
devices. The fit loop, resuming and data parallelism are `train`'s."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig
from mvpose_jax.data.files import to_jsonable
from mvpose_jax.errors import InputError
from mvpose_jax.graphs import GraphBatch, make_pool, sample_batches, split_graph_batch
from mvpose_jax.losses import masked_mean, match_mse
from mvpose_jax.models import MatchingGAT, initialised, matcher_model
from mvpose_jax.parallel import mesh_size, replicate, shard_batch
from mvpose_jax.trained import (
    Matcher,
    MatcherConfig,
    rig_agnostic_matcher,
)

if TYPE_CHECKING:  # annotations only: importing data.recording loads every reader
    from mvpose_jax.data.recording import Recording

from mvpose_jax.train import (
    FitResult,
    fit_resumable,
    init_train_state,
    make_optimizer,
    make_train_step,
    stacked_loss_fn,
    training_mesh,
)

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
    start: Matcher | None = None,
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
      start: a rig-agnostic matcher to start from (fine-tuning; e.g. `trained.load_matcher` of
        `trained.PRETRAINED`): its network and parameters replace ``config.gat``'s fresh ones.
    Returns:
      (the best `Matcher`, the `FitResult`).
    """
    tcfg = config.train
    if start is not None:
        if start.config.gat.views != "pooled":
            raise InputError(
                "only a rig-agnostic matcher (GATConfig.views='pooled') can start training on "
                "another rig",
                field="start",
            )
        config = dataclasses.replace(config, gat=start.config.gat)
    rig_infer = rig.select(list(config.cameras or rig.names))
    train_pool = make_pool(rig_infer, train_recordings)
    dev_pool = make_pool(rig_infer, dev_recordings)
    K = train_recordings[0].num_keypoints
    if start is not None and nnx.merge(start.graphdef, start.params, start.rest).num_keypoints != K:
        raise InputError(f"the starting matcher is not a {K}-keypoint network", field="start")
    compose = config.composition()
    per_batch = tcfg.batch_size
    num_dev = max(1, math.ceil(config.num_dev_samples / per_batch))
    dev_batches = sample_batches(
        dev_pool, np.random.default_rng([tcfg.seed, 1 << 30]), num_dev, per_batch, **compose
    )

    model = initialised(
        lambda: matcher_model(rig_infer.num_cameras, K, config.gat, rngs=nnx.Rngs(tcfg.seed))
    )
    if config.gat.views == "pooled":
        # The rig's frame (its features come rig-normalised, the model reads metres, z up).
        graphdef, params, rest = nnx.split(model, nnx.Param, ...)
        if start is not None:
            # A copy: the train step donates its state's buffers, and ``start`` stays usable.
            params = jax.tree.map(jnp.array, start.params)
        framed = rig_agnostic_matcher(graphdef, rest, params, config, rig_infer)
        model = nnx.merge(framed.graphdef, framed.params, framed.rest)

    def epoch_batches(epoch):
        rng = np.random.default_rng([tcfg.seed, epoch])
        # Built lazily: the host builds batch i+1 while the device runs step i (async dispatch).
        for _ in range(config.steps_per_epoch):
            yield sample_batches(train_pool, rng, 1, per_batch, **compose)[0]

    graphdef, rest, result = fit_matcher_model(
        model,
        epoch_batches,
        dev_batches,
        config,
        checkpoint_dir=checkpoint_dir,
        run_config={**to_jsonable(dataclasses.asdict(config)), "num_keypoints": K},
        progress=progress,
        resume=resume,
        desc="matcher",
    )
    return Matcher(graphdef, rest, result.state.params, rig_infer, config), result


def fit_matcher_model(
    model: nnx.Module,
    epoch_batches: Callable[[int], Iterator[GraphBatch]],
    dev_batches: Sequence[GraphBatch],
    config: MatcherConfig,
    *,
    checkpoint_dir: str | Path | None,
    run_config: dict,
    progress: bool,
    resume: bool,
    desc: str,
) -> tuple[Any, Any, FitResult]:
    """The matcher's fit loop (`train.fit_resumable`) over any source of graph batches: the
    MSE on match nodes, validated on ``dev_batches`` (mean squared error and accuracy at 0.5).

    With ``config.train.num_devices``, every batch is split by whole graphs over the devices.

    Returns:
      (graphdef, rest, the `FitResult`); the best parameters are ``result.state.params``.
    """
    tcfg = config.train
    tx = make_optimizer(tcfg, config.steps_per_epoch)
    graphdef, rest, state = init_train_state(model, tx)
    mesh = training_mesh(tcfg)
    if mesh is None:
        step = make_train_step(graphdef, rest, tx, matcher_loss_fn, xla_kernels=True)
        eval_batch = jax.jit(functools.partial(matcher_eval_sums, graphdef, rest))
        batches = epoch_batches
    else:
        step = make_train_step(
            graphdef, rest, tx, stacked_loss_fn(matcher_loss_fn), mesh=mesh, xla_kernels=True
        )
        eval_batch = jax.jit(functools.partial(_stacked_matcher_eval, graphdef, rest))
        state = replicate(mesh, state)
        shard = lambda b: shard_batch(mesh, split_graph_batch(b, mesh_size(mesh))[0])  # noqa: E731
        dev_batches = [shard(b) for b in dev_batches]

        def batches(epoch):
            # The global batch (the same on every host), one padded block of graphs per device.
            return (shard(b) for b in epoch_batches(epoch))

    def evaluate(state):
        sums = [eval_batch(state.params, b) for b in dev_batches]
        total = {k: sum(float(s[k]) for s in sums) for k in sums[0]}
        n = max(total["count"], 1.0)
        return {"val_loss": total["sq_error"] / n, "val_accuracy": total["correct"] / n}

    result = fit_resumable(
        state,
        step,
        batches,
        evaluate,
        tcfg,
        steps_per_epoch=config.steps_per_epoch,
        checkpoint_dir=checkpoint_dir,
        run_config=run_config,
        resume=resume,
        desc=desc,
        progress=progress,
    )
    return graphdef, rest, result


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
