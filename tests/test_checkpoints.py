"""checkpoints.py: the whole train state round-trips; inference restores the parameters alone
(no optimiser state is read or needed), and another model's checkpoint is refused by name."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from flax import nnx

from mvpose_jax.checkpoints import Checkpoints
from mvpose_jax.errors import InputError
from mvpose_jax.models import MLPConfig, PoseMLP
from mvpose_jax.train import init_train_state, make_optimizer
from mvpose_jax.trained import TrainConfig


def _saved(tmp_path, widths=(8, 8)):
    model = PoseMLP(2, 4, MLPConfig(widths=widths), rngs=nnx.Rngs(3))
    _, _, state = init_train_state(model, make_optimizer(TrainConfig()))
    ck = Checkpoints(tmp_path)
    try:
        ck.save_best(state, {"run": "test"}, 0.25)
    finally:
        ck.close()
    return state


def _abstract_params(widths=(8, 8)):
    _, params, _ = nnx.split(
        PoseMLP(2, 4, MLPConfig(widths=widths), rngs=nnx.Rngs(0)), nnx.Param, ...
    )
    return jax.eval_shape(lambda: params)


def test_params_alone_restore_without_an_optimiser(tmp_path):
    state = _saved(tmp_path)
    ck = Checkpoints(tmp_path)
    try:
        params = ck.restore_params(_abstract_params())
        whole, config = ck.restore(jax.eval_shape(lambda: state))
    finally:
        ck.close()
    assert config == {"run": "test"}
    assert jax.tree.structure(params) == jax.tree.structure(state.params)
    for a, b, c in zip(
        jax.tree.leaves(params),
        jax.tree.leaves(state.params),
        jax.tree.leaves(whole.params),
        strict=True,
    ):
        assert isinstance(a, jax.Array)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_params_of_another_model_are_refused_by_name(tmp_path):
    _saved(tmp_path, widths=(8, 8))
    ck = Checkpoints(tmp_path)
    try:
        with pytest.raises(InputError, match="another model") as e:
            ck.restore_params(_abstract_params(widths=(16, 8)))
    finally:
        ck.close()
    assert "params" in str(e.value) and "best" in str(e.value.file)


def test_no_checkpoint_is_a_clear_error(tmp_path):
    ck = Checkpoints(tmp_path / "empty")
    try:
        with pytest.raises(InputError, match="no best checkpoint"):
            ck.restore_params(_abstract_params())
    finally:
        ck.close()
