"""Data parallelism: 4 CPU devices compute what 1 device computes, for training and inference.

The main pytest process has imported jax with one CPU device, and the device count is fixed at
import, so the multi-device checks run in ONE subprocess started with
``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (`_worker` below); each test asserts on
its part of the worker's JSON report. `split_graph_batch` is also checked here, on one device.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import nnx

from mvpose_jax.graphs import build_graphs, split_graph_batch
from mvpose_jax.models import GATConfig, MatchingGAT, stacked_match_scores
from tests.helpers import random_frames

pytestmark = pytest.mark.slow  # one subprocess with 4 host devices trains both models

ROOT = Path(__file__).resolve().parents[1]
NUM_DEVICES = 4
TINY_GAT = GATConfig(widths=(8, 8, 1), heads=(2, 2, 1))


# --------------------------------------------------------------------------- the worker


def _worker() -> None:
    """Runs in a subprocess with 4 host devices; prints one JSON report."""
    from mvpose_jax.data.calibration import load_preset
    from mvpose_jax.errors import InputError
    from mvpose_jax.estimator_training import train_estimator
    from mvpose_jax.features import single_person_samples
    from mvpose_jax.lifting import predict_people
    from mvpose_jax.matcher_training import train_matcher
    from mvpose_jax.matching import match_scores
    from mvpose_jax.models import MLPConfig
    from mvpose_jax.parallel import make_data_mesh
    from mvpose_jax.synthetic import generate_single_person_recordings
    from mvpose_jax.trained import EstimatorConfig, MatcherConfig, TrainConfig

    assert jax.device_count() == NUM_DEVICES, jax.devices()
    report = {}
    rig = load_preset("panoptic5").select(["trackera", "trackerb", "trackerc"])
    recs = generate_single_person_recordings(rig, num_recordings=4, num_frames=6, seed=0)

    # The estimator: 24 people, batch 24 = one step per epoch, so the history has each step.
    xy, score = single_person_samples(recs)
    est_cfg = EstimatorConfig(
        mlp=MLPConfig(widths=(32,), output="residual"),
        num_augment=2,
        train=TrainConfig(learning_rate=1e-3, batch_size=24, max_steps=3, patience=100),
    )
    est = {}
    for n in (None, NUM_DEVICES):
        cfg = dataclasses.replace(est_cfg, train=dataclasses.replace(est_cfg.train, num_devices=n))
        model, fit = train_estimator(
            rig, xy, score, xy, score, cfg, progress=False
        )  # dev = train: one shape
        est[n] = model
        report[f"estimator_{n}"] = dict(
            train_loss=[h["train_loss"] for h in fit.history],
            val_loss=[h["val_loss"] for h in fit.history],
            params=[np.asarray(p).ravel()[:50].tolist() for p in jax.tree.leaves(model.params)],
            param_devices=len(jax.tree.leaves(model.params)[0].sharding.device_set),
        )
    for name, change in (
        ("too_many_devices", dict(num_devices=5)),
        ("uneven_batch", dict(num_devices=NUM_DEVICES, batch_size=18)),
    ):
        try:
            cfg = dataclasses.replace(est_cfg, train=dataclasses.replace(est_cfg.train, **change))
            train_estimator(rig, xy, score, xy, score, cfg, progress=False)
            report[name] = "no error"
        except InputError as e:
            report[name] = str(e)

    # The matcher: 6 graphs per step over 4 devices (2, 2, 2 and 0 graphs: one device holds only
    # padding), one step per epoch, validation (split by graphs too) after each.
    base = MatcherConfig.quick()
    # (max_people 2: with this seed every training batch falls in one graph budget, one compile.)
    cfg = dataclasses.replace(
        base,
        gat=TINY_GAT,
        samples_per_epoch=6,
        num_dev_samples=6,
        max_people=2,
        train=dataclasses.replace(base.train, batch_size=6, max_epochs=2, eval_every=1),
    )
    for n in (None, NUM_DEVICES):
        run = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, num_devices=n))
        matcher, fit = train_matcher(rig, recs[:3], recs[3:], run, progress=False)
        report[f"matcher_{n}"] = dict(
            history=[
                [h["train_loss"], h["train_accuracy"], h["val_loss"], h["val_accuracy"]]
                for h in fit.history
            ],
            params=[np.asarray(p).ravel().tolist() for p in jax.tree.leaves(matcher.params)],
            param_devices=len(jax.tree.leaves(matcher.params)[0].sharding.device_set),
        )

    # Sharded inference equals unsharded: 21 people (padded to 32), 5 frames in 9 graph slots.
    mesh = make_data_mesh(NUM_DEVICES)
    report["predict"] = [
        predict_people(est[None], xy[:21], score[:21]).tolist(),
        predict_people(est[None], xy[:21], score[:21], mesh=mesh).tolist(),
    ]
    batch = build_graphs(
        *random_frames(np.random.default_rng(0), 5, K=recs[0].num_keypoints), num_graphs=9
    )
    mask = np.asarray(batch.node_mask)
    one, many = (match_scores(matcher, batch), match_scores(matcher, batch, mesh=mesh))
    report["match_scores"] = [one[mask].tolist(), many[mask].tolist()]
    print("REPORT" + json.dumps(report))


@pytest.fixture(scope="module")
def report():
    env = dict(
        os.environ,
        XLA_FLAGS=f"--xla_force_host_platform_device_count={NUM_DEVICES}",
        JAX_PLATFORMS="cpu",
        PYTHONPATH=str(ROOT),
    )
    out = subprocess.run(
        [sys.executable, "-c", "from tests.test_parallel import _worker; _worker()"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [line for line in out.stdout.splitlines() if line.startswith("REPORT")]
    assert out.returncode == 0 and lines, out.stderr[-3000:]
    return json.loads(lines[-1][len("REPORT") :])


# --------------------------------------------------------------------------- the checks


def test_estimator_on_4_devices_takes_the_steps_of_1_device(report):
    one, four = report["estimator_None"], report[f"estimator_{NUM_DEVICES}"]
    assert len(one["train_loss"]) == 3
    np.testing.assert_allclose(four["train_loss"], one["train_loss"], rtol=1e-5)
    np.testing.assert_allclose(four["val_loss"], one["val_loss"], rtol=1e-5)
    for a, b in zip(four["params"], one["params"], strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    assert four["param_devices"] == NUM_DEVICES and one["param_devices"] == 1  # replicated
    assert "asked for 5 devices, 4 available" in report["too_many_devices"]
    assert "batch size 18 does not split over 4 devices" in report["uneven_batch"]


def test_matcher_on_4_devices_takes_the_steps_of_1_device(report):
    one, four = report["matcher_None"], report[f"matcher_{NUM_DEVICES}"]
    assert len(one["history"]) == 2
    # Per step: training loss and accuracy, validation loss and accuracy.
    np.testing.assert_allclose(four["history"], one["history"], rtol=1e-5)
    for a, b in zip(four["params"], one["params"], strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    assert four["param_devices"] == NUM_DEVICES and one["param_devices"] == 1


@pytest.mark.parametrize("name", ["predict", "match_scores"])
def test_inference_on_4_devices_gives_the_numbers_of_1_device(report, name):
    """Sharded `predict_people` (21 people padded to 32, 8 per device) and `match_scores` (5
    frames' graphs padded to 9 slots, split whole over the devices) equal the unsharded results
    for every real person and node: padding and the split change nothing.

    Not bit-exact: each device computes a smaller block, which XLA may compile with sums rounded
    in another order (differences up to about 1e-6 relative seen: 9e-6 m on 13 m, 6e-8 on scores
    near 0.5); a person or node put back in the wrong place would differ by far more.
    """
    one, four = (np.asarray(r, np.float64) for r in report[name])
    assert one.shape == four.shape and len(one) > 0
    assert name != "predict" or len(one) == 21  # the padding people are cut off
    assert np.ptp(one) > 1e-3  # not all alike: rows in the wrong places would not match
    np.testing.assert_allclose(four, one, rtol=1e-5, atol=1e-5 if name == "predict" else 1e-6)


def test_matcher_stacked_on_one_device_is_todays_loss():
    """``num_devices=1``: the one block is today's batch itself, and the lifted loss is today's."""
    from mvpose_jax.losses import masked_mean
    from mvpose_jax.matcher_training import matcher_loss_fn
    from mvpose_jax.train import stacked_loss_fn

    batch = build_graphs(*random_frames(np.random.default_rng(4), 5))
    stacked, origin = split_graph_batch(batch, 1)
    for a, b in zip(jax.tree.leaves(stacked), jax.tree.leaves(batch), strict=True):
        np.testing.assert_array_equal(a, np.asarray(b)[None])
    np.testing.assert_array_equal(origin[0][batch.node_mask], np.nonzero(batch.node_mask)[0])
    model = MatchingGAT(3, 4, TINY_GAT, rngs=nnx.Rngs(0))

    @jax.jit
    def both(model, batch, stacked):
        key = jax.random.key(0)
        (p1, m1, a1), (p2, m2, a2) = (
            matcher_loss_fn(model, batch, key),
            stacked_loss_fn(matcher_loss_fn)(model, stacked, key),
        )
        return masked_mean(p1, m1), a1["accuracy"], masked_mean(p2, m2), a2["accuracy"]

    loss, acc, stacked_loss, stacked_acc = (float(x) for x in both(model, batch, stacked))
    assert (
        loss > 0
        and stacked_loss == pytest.approx(loss, rel=1e-6)
        and stacked_acc == pytest.approx(acc, rel=1e-6)
    )


def test_split_graph_batch_keeps_every_real_node_score():
    feats, valid, identity = random_frames(np.random.default_rng(1), 7)
    batch = build_graphs(feats, valid, identity, num_graphs=10)
    model = MatchingGAT(3, 4, TINY_GAT, rngs=nnx.Rngs(0))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    whole = np.asarray(
        stacked_match_scores(
            graphdef, rest, params, jax.tree.map(lambda a: np.asarray(a)[None], batch)
        )
    )[0]
    real = np.asarray(batch.node_mask)
    for shards in (1, 3, 8):  # 8 shards of 7 graphs: the last shard is all padding
        stacked, origin = split_graph_batch(batch, shards)
        assert stacked.graphs.nodes.shape[0] == shards and origin.shape == stacked.node_mask.shape
        assert np.array_equal(origin >= 0, stacked.node_mask)
        assert (
            sorted(origin[origin >= 0].tolist()) == np.nonzero(real)[0].tolist()
        )  # each real node once
        for s in range(shards):  # every shard is a valid padded batch: edges stay in the shard
            n_node = stacked.graphs.n_node[s]
            assert (
                n_node.sum() == stacked.node_mask.shape[1]
                and stacked.graphs.n_edge[s].sum() == stacked.graphs.senders.shape[1]
            )
        scores = np.asarray(stacked_match_scores(graphdef, rest, params, stacked))
        np.testing.assert_allclose(scores[origin >= 0], whole[origin[origin >= 0]], atol=1e-6)
        # Labels and pairs follow their nodes.
        keep = origin >= 0
        np.testing.assert_array_equal(stacked.label[keep], np.asarray(batch.label)[origin[keep]])
        pair = stacked.pair[keep]
        back = np.where(pair >= 0, pair + (origin[keep] - np.nonzero(keep)[1])[:, None], -1)
        np.testing.assert_array_equal(back, np.asarray(batch.pair)[origin[keep]])
