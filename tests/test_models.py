"""models.py: the matching GAT and the 3D MLP as functions of arrays (shapes, padding, the
paper's architecture, parameter counts), and that the GAT can learn."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from mvpose_jax.graphs import (
    Budget,
    build_graphs,
    dense_node_features,
)
from mvpose_jax.models import (
    GATConfig,
    MatchingGAT,
    MLPConfig,
    PoseMLP,
    count_params,
    estimator_model,
    initialised,
    matcher_model,
)
from tests.helpers import C, K, random_frames
from tests.helpers import tiny_matcher_train_state as _train_state


@pytest.fixture(scope="module")
def model():
    return MatchingGAT(C, K, GATConfig(), rngs=nnx.Rngs(0))


def test_factorised_first_layer_equals_dense_gat(model):
    b = build_graphs(*random_frames(np.random.default_rng(0), 4))
    fast = np.asarray(jax.jit(lambda m, x: m(x))(model, b))
    dense = np.asarray(
        jax.jit(lambda m, x, g: m.dense_forward(x, g))(model, dense_node_features(b), b.graphs)
    )
    np.testing.assert_allclose(fast[b.node_mask], dense[b.node_mask], atol=1e-5)


def test_slot_products_give_the_dense_first_layer(model):
    """Rows held per camera, each multiplied by its camera's slot of W1 (`slot_products`, what
    inference uses on chunks), give the scores of the dense slot rows."""
    feats, valid, _ = random_frames(np.random.default_rng(2), 4)  # (F, C, P, K*10)
    b = build_graphs(feats, valid)
    F, Cf, P, KF = feats.shape
    per_camera = jnp.moveaxis(jnp.asarray(feats), 1, 0).reshape(Cf, F * P, KF)
    f_d, c_d, p_d = np.nonzero(valid)  # detection rows in (frame, camera, skeleton) order
    source = np.zeros(b.det_mask.shape[0], np.int64)
    source[: len(f_d)] = (c_d * F + f_d) * P + p_d

    def with_slots(m, batch):
        pre = m.slot_products(per_camera).reshape(Cf * F * P, -1)[source]
        return m(batch, det_pre=pre)

    slots = np.asarray(jax.jit(with_slots)(model, b))
    dense = np.asarray(jax.jit(lambda m, x: m(x))(model, b))
    np.testing.assert_allclose(slots[b.node_mask], dense[b.node_mask], atol=1e-5)


def test_padding_never_changes_real_scores(model):
    feats, valid, identity = random_frames(np.random.default_rng(1), 3)
    small = build_graphs(feats, valid, identity)
    big = build_graphs(
        feats,
        valid,
        identity,
        num_graphs=9,
        budget=Budget(small.graphs.nodes.shape[0] * 4, 128, small.graphs.nodes.shape[0] * 20, 10),
    )
    f = jax.jit(lambda m, x: m(x))
    a, b = np.asarray(f(model, small)), np.asarray(f(model, big))
    n = int(small.node_mask.sum())
    assert np.isfinite(a).all() and np.isfinite(b).all()
    np.testing.assert_allclose(a[:n], b[:n], atol=1e-6)


def test_gat_config_validates():
    with pytest.raises(ValueError):
        GATConfig(widths=(40, 1), heads=(3, 1))
    with pytest.raises(ValueError):
        GATConfig(widths=(40, 2), heads=(10, 1))


def test_tiny_model_overfits_tiny_dataset():
    # Identity is written into the features, so a perfect matcher exists.
    rng = np.random.default_rng(2)
    feats, valid, identity = random_frames(rng, 6)
    feats[..., :3] = (
        np.eye(3, dtype=np.float32)[np.maximum(identity, 0)] * (identity >= 0)[..., None]
    )
    batch = jax.device_put(build_graphs(feats, valid, identity))
    # 3e-3: at 1e-2 Adam sometimes parks this tiny net on a plateau (seed-dependent); at 3e-3
    # every initialisation tried converges (loss / 1e4 within 300 steps).
    _, _, state, step = _train_state(GATConfig(widths=(16, 16, 1), heads=(2, 2, 1)), lr=3e-3)
    key = jax.random.key(0)
    losses = []
    for _ in range(300):
        state, metrics = step(state, batch, key)
        losses.append(float(metrics["loss"]))
    assert np.isfinite(losses).all()
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


def test_mlp_accepts_any_leading_batch():
    model = PoseMLP(
        3, 18, dataclasses.replace(MLPConfig.quick(), output="anchored"), rngs=nnx.Rngs(0)
    )
    x = jnp.zeros((2, 5, 3, 18, 14))
    assert model(x).shape == (2, 5, 18, 3)


def test_mlp_is_the_plain_dense_stack():
    # The feature-major layout (kernels stored (out, in)) must compute rows @ kernel.T + bias.
    model = PoseMLP(2, 4, MLPConfig(widths=(16, 8)), rngs=nnx.Rngs(0))
    x = np.random.default_rng(0).standard_normal((3, 2, 4, 14)).astype(np.float32)
    h = x.reshape(3, -1).astype(np.float64)
    for layer in model.hidden:
        h = h @ np.asarray(layer.kernel[...]).T + np.asarray(layer.bias[...])
        h = np.where(h > 0, h, 0.1 * h)
    out = h @ np.asarray(model.out.kernel[...]).T + np.asarray(model.out.bias[...])
    np.testing.assert_allclose(
        np.asarray(model(jnp.asarray(x))), out.reshape(3, 4, 3), rtol=1e-4, atol=1e-5
    )
    # lecun-normal fan-in: the first kernel's spread is 1/sqrt(inputs), not 1/sqrt(outputs).
    first = PoseMLP(5, 18, MLPConfig(widths=(64,)), rngs=nnx.Rngs(0)).hidden[0].kernel[...]
    assert first.shape == (64, 5 * 18 * 14)
    assert np.std(np.asarray(first)) == pytest.approx(1 / np.sqrt(5 * 18 * 14), rel=0.1)


@pytest.mark.parametrize(
    "widths, millions",
    [
        ((3072, 3072, 2048, 2048, 1024, 1024, 1024), 28.06),  # the paper's widths
        (
            (3072, 3072, 2048, 2048, 1024, 1024, 1024, 1024),
            29.11,
        ),  # the original code's (DESIGN §5)
    ],
)
def test_paper_size_mlp_parameter_count(widths, millions):
    model = nnx.eval_shape(lambda: PoseMLP(5, 18, MLPConfig(widths=widths), rngs=nnx.Rngs(0)))
    _, params = nnx.split(model, nnx.Param)
    sizes = (5 * 18 * 14,) + widths + (18 * 3,)
    expected = sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:], strict=True))
    assert count_params(params) == expected
    assert expected / 1e6 == pytest.approx(millions, abs=0.01)


@pytest.mark.parametrize(
    "make",
    [
        lambda: matcher_model(3, K, GATConfig.quick(), rngs=nnx.Rngs(5)),
        lambda: matcher_model(0, K, GATConfig.pooled(), rngs=nnx.Rngs(1)),
        lambda: estimator_model(C, K, MLPConfig(widths=(64, 32)), rngs=nnx.Rngs(2)),
        lambda: estimator_model(0, K, MLPConfig.pooled(), rngs=nnx.Rngs(3)),
    ],
    ids=["gat", "gat-pooled", "mlp", "mlp-pooled"],
)
def test_initialised_draws_the_eager_initial_parameters_bit_for_bit(make):
    want, got = nnx.state(make()), nnx.state(initialised(make))
    assert jax.tree.structure(got) == jax.tree.structure(want)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
