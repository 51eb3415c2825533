"""The networks, in Flax NNX, used functionally (split once, merge inside plain jax.jit).

* `PoseMLP`: the 3D estimator (DESIGN.md §1.3): the (C_i, K, 14) features of one person,
  flattened, through LeakyReLU(0.1) hidden layers to a linear (K, 3) output in the rig-normalised
  frame (`features`); `to_world` maps it to metres.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import nnx

from mvpose_jax.features import NUM_ESTIMATOR_FEATURES

PAPER_MLP_WIDTHS = (3072, 3072, 2048, 2048, 1024, 1024, 1024)


@dataclasses.dataclass(frozen=True)
class MLPConfig:
    """The 3D estimator's architecture.

    Attributes:
      widths: hidden layer widths; the paper's by default (29.1 M parameters for 5 views and 18
        keypoints), `quick()` gives a small one for fast runs.
      slope: negative slope of the LeakyReLU after each hidden layer (paper: 0.1).
    """

    widths: tuple[int, ...] = PAPER_MLP_WIDTHS
    slope: float = 0.1

    @classmethod
    def quick(cls) -> MLPConfig:
        return cls(widths=(512, 512, 256))


class PoseMLP(nnx.Module):
    """Per-person 3D regressor: (C, K, 14) features -> (K, 3) rig-normalised coordinates.

    Works on any leading batch shape: (..., C, K, 14) -> (..., K, 3).
    """

    def __init__(self, num_cameras: int, num_keypoints: int, config: MLPConfig, *, rngs: nnx.Rngs):
        self.num_keypoints = num_keypoints
        self.slope = config.slope
        sizes = (num_cameras * num_keypoints * NUM_ESTIMATOR_FEATURES,) + tuple(config.widths)
        self.hidden = nnx.List(
            [nnx.Linear(a, b, rngs=rngs) for a, b in zip(sizes[:-1], sizes[1:], strict=True)]
        )
        self.out = nnx.Linear(sizes[-1], num_keypoints * 3, rngs=rngs)

    def __call__(self, features: jax.Array) -> jax.Array:
        h = features.reshape(features.shape[:-3] + (-1,))
        for layer in self.hidden:
            h = jax.nn.leaky_relu(layer(h), self.slope)
        return self.out(h).reshape(features.shape[:-3] + (self.num_keypoints, 3))


def to_world(xyz_normalised: jax.Array, centre: jax.Array, radius: jax.Array) -> jax.Array:
    """Rig-normalised coordinates to metres. xyz: (..., 3); centre: (3,); radius: ()."""
    return xyz_normalised * radius + centre.reshape((1,) * (xyz_normalised.ndim - 1) + (3,))


def count_params(params) -> int:
    """Number of scalars in a parameter pytree."""
    return int(sum(jnp.size(x) for x in jax.tree_util.tree_leaves(params)))
