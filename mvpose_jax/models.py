"""The networks, in Flax NNX, used functionally (split once, merge inside plain jax.jit).

* `PoseMLP`: the 3D estimator (DESIGN.md §1.3): the (C_i, K, 14) features of one person,
  flattened, through LeakyReLU(0.1) hidden layers to a linear (K, 3) output in the rig-normalised
  frame (`features`); `to_world` maps it to metres.
* `ViewPooledMLP`: a 3D estimator for any rig: each view encoded by shared weights, pooled over
  the views present, so that the number and order of cameras do not matter (`estimator_model`
  picks one of the two from `MLPConfig.views`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import jraph
import numpy as np
from flax import nnx

from mvpose_jax.features import NUM_ESTIMATOR_FEATURES, NUM_KEYPOINT_FEATURES
from mvpose_jax.graphs import DETECTION, MATCH, GraphBatch

PAPER_MLP_WIDTHS = (3072, 3072, 2048, 2048, 1024, 1024, 1024)


@dataclasses.dataclass(frozen=True)
class MLPConfig:
    """The 3D estimator's architecture.

    Attributes:
      widths: hidden layer widths; the paper's by default (29.1 M parameters for 5 views and 18
        keypoints), `quick()` gives a small one for fast runs.
      slope: negative slope of the LeakyReLU after each hidden layer (paper: 0.1).
      output: what the linear output layer predicts. "absolute" (the paper): the keypoints
        themselves. "anchored": offsets from the person's anchor, the mean of its initial 3D
        estimates. "residual": offsets from each keypoint's initial 3D estimate where it has
        one, else from the anchor. All three read only the network's own inputs.
      views: how the views enter. "slots" (the paper): one slot of inputs per camera, so the
        network is tied to its cameras' number and order. "pooled": `ViewPooledMLP`, the same
        network for any number and order of cameras (needs ``output="residual"``).
      view_widths: the per-view encoder's layer widths ("pooled" only).
    """

    widths: tuple[int, ...] = PAPER_MLP_WIDTHS
    slope: float = 0.1
    output: str = "absolute"
    views: str = "slots"
    view_widths: tuple[int, ...] = (256, 256)

    def __post_init__(self):
        if self.views not in ("slots", "pooled"):
            raise ValueError(f"MLPConfig.views must be slots or pooled, not {self.views!r}")
        if self.views == "pooled" and self.output != "residual":
            raise ValueError("MLPConfig: views='pooled' predicts residuals (output='residual')")

    @classmethod
    def quick(cls) -> MLPConfig:
        return cls(widths=(512, 512, 256))

    @classmethod
    def pooled(cls) -> MLPConfig:
        """The rig-agnostic estimator's sizes (`ViewPooledMLP`, about 0.9 M parameters)."""
        return cls(widths=(512, 512), output="residual", views="pooled", view_widths=(256, 256))


class FeatureMajorLinear(nnx.Module):
    """A dense layer on feature-major activations: (in, M) -> (out, M), kernel stored (out, in).

    Same function as ``nnx.Linear`` (lecun-normal kernel, zero bias by default), laid out for the
    estimator's hot path: with the weights stored (out, in) and the rows as columns, the product
    is a matrix times a thin matrix, which XLA:CPU runs near the weight-streaming speed for a few
    rows, while ``rows @ kernel(in, out)`` costs about one extra weight pass per added row
    (benchmarks/README.md); on big batches both run at the matmul peak.
    """

    def __init__(self, in_features: int, out_features: int, *, kernel_init=None, rngs: nnx.Rngs):
        init = kernel_init or nnx.initializers.lecun_normal()
        # lecun_normal reads fan-in from axis -2 of an (in, out) shape: draw it so, store it (out, in).
        self.kernel = nnx.Param(init(rngs.params(), (in_features, out_features), jnp.float32).T)
        self.bias = nnx.Param(jnp.zeros((out_features,), jnp.float32))

    def __call__(self, h: jax.Array) -> jax.Array:
        """h: (in, M) -> (out, M)."""
        return self.kernel[...] @ h + self.bias[...][:, None]


class PoseMLP(nnx.Module):
    """Per-person 3D regressor: (C, K, 14) features -> (K, 3) rig-normalised coordinates.

    Works on any leading batch shape: (..., C, K, 14) -> (..., K, 3).
    """

    def __init__(self, num_cameras: int, num_keypoints: int, config: MLPConfig, *, rngs: nnx.Rngs):
        if config.output not in ("absolute", "anchored", "residual"):
            raise ValueError(
                f"MLPConfig.output must be absolute, anchored or residual, not {config.output!r}"
            )
        self.num_keypoints = num_keypoints
        self.slope = config.slope
        self.output = config.output
        num_inputs = num_cameras * num_keypoints * NUM_ESTIMATOR_FEATURES
        if config.output != "absolute":
            num_inputs += num_keypoints * 4  # the pose-relative initial estimate, see __call__
        sizes = (num_inputs,) + tuple(config.widths)
        self.hidden = nnx.List(
            [
                FeatureMajorLinear(a, b, rngs=rngs)
                for a, b in zip(sizes[:-1], sizes[1:], strict=True)
            ]
        )
        # Offset outputs start at zero, so an untrained network returns its anchor (the
        # triangulation, for "residual") instead of noise around it.
        init = (
            nnx.initializers.zeros
            if config.output != "absolute"
            else nnx.initializers.lecun_normal()
        )
        self.out = FeatureMajorLinear(sizes[-1], num_keypoints * 3, kernel_init=init, rngs=rngs)

    def __call__(self, features: jax.Array) -> jax.Array:
        batch = features.shape[:-3]
        h = features.reshape(batch + (-1,))
        if self.output != "absolute":
            # The initial estimate once per keypoint, relative to the person's anchor: the
            # per-slot copies are zero in absent views, so reading them needs a division by
            # the number of views, which an MLP learns slowly; relative coordinates make the
            # pose's shape independent of where the person stands.
            xyz, has, anchor = initial_estimate_parts(features)
            rel = jnp.where(has[..., None] > 0, xyz - anchor[..., None, :], 0.0)
            h = jnp.concatenate(
                [h, jnp.concatenate([has[..., None], rel], -1).reshape(batch + (-1,))], -1
            )
        # Rows become columns once, for the whole stack (see FeatureMajorLinear).
        h = h.reshape(-1, h.shape[-1]).T
        for layer in self.hidden:
            h = jax.nn.leaky_relu(layer(h), self.slope)
        out = self.out(h).T.reshape(batch + (self.num_keypoints, 3))
        if self.output == "absolute":
            return out
        return out + initial_estimate(features, per_keypoint=self.output == "residual")


def initial_estimate_parts(features: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(xyz (..., K, 3), has (..., K), anchor (..., 3)) read from estimator features."""
    flag = features[..., 10]  # (..., C, K): 1 in present views of keypoints with an estimate
    has = flag.max(axis=-2)  # (..., K)
    # Every present slot holds the same estimate: their mean is it.
    xyz = (
        jnp.sum(features[..., 11:14] * flag[..., None], axis=-3)
        / jnp.maximum(flag.sum(axis=-2), 1.0)[..., None]
    )
    anchor = jnp.sum(xyz * has[..., None], axis=-2) / jnp.maximum(has.sum(axis=-1), 1.0)[..., None]
    return xyz, has, anchor


def initial_estimate(features: jax.Array, per_keypoint: bool) -> jax.Array:
    """The initial 3D carried in the estimator features (rig-normalised).

    Args:
      features: (..., C, K, 14) as `features.assemble_features` makes them.
      per_keypoint: each keypoint's own initial estimate where it has one; for a keypoint one
        view sees, the point on its ray at the anchor's distance from that camera (for a person
        without any initial estimate, e.g. seen by one camera, the anchor is the rig centre);
        else the anchor. False: the anchor (mean of the person's initial estimates) for every
        keypoint.
    Returns:
      (..., K, 3); zeros (the rig centre) for keypoints no view sees of a person without any
      initial estimate.
    """
    xyz, has, anchor = initial_estimate_parts(features)
    anchor = jnp.broadcast_to(anchor[..., None, :], xyz.shape)
    if not per_keypoint:
        return anchor
    # A keypoint one view sees lies on that view's ray: take the point of the ray as far from the
    # camera as the anchor is (bodies are shallow next to camera distances).
    seen = features[..., 0]  # (..., C, K) visible flags
    cam = jnp.sum(
        features[..., 4:7] * seen[..., None], axis=-3
    )  # the one view's camera (..., K, 3)
    ray = jnp.sum(features[..., 7:10] * seen[..., None], axis=-3)  # and its unit ray
    depth = jnp.linalg.norm(anchor - cam, axis=-1, keepdims=True)
    on_ray = cam + ray * depth
    # Also without any estimate (one camera): on the ray at the rig centre's distance, so the
    # start projects onto the detection in that camera instead of at the rig centre.
    one_view = seen.sum(axis=-2) == 1
    fallback = jnp.where(one_view[..., None], on_ray, anchor)
    return jnp.where(has[..., None] > 0, xyz, fallback)


class FrameRotation(nnx.Variable):
    """A fixed rotation a model applies to its inputs' world vectors (not trained): the rig's
    world turned so that its up is +z, the frame a rig-agnostic model was trained in."""


def rotation_to_z_up(up) -> np.ndarray:
    """(3, 3) rotation Q with ``Q @ up = +z`` (the smallest turn; identity for up = +z)."""
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(u, z), float(u @ z)
    if c < -1 + 1e-9:  # upside down: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def turned_features(features: jax.Array, q: jax.Array) -> jax.Array:
    """Estimator features (..., 14) with their world vectors (camera centre, ray, initial 3D)
    turned by the rotation ``q`` (3, 3) into a model's frame (`FrameRotation`)."""
    turn = lambda v: v @ q.T  # noqa: E731  (row vectors)
    return jnp.concatenate(
        [
            features[..., :4],
            turn(features[..., 4:7]),
            turn(features[..., 7:10]),
            features[..., 10:11],
            turn(features[..., 11:14]),
        ],
        axis=-1,
    )


class ViewPooledMLP(nnx.Module):
    """A 3D estimator for any rig: (..., C, K, 14) features -> (..., K, 3), any C, any order.

    Each present view (one with a keypoint) becomes one vector through an encoder shared by all
    views: its keypoints' image evidence (visible, x, y, score), rays, and its camera's centre
    relative to the person's anchor (the mean of its initial 3D). The views are pooled (masked
    mean and max), each view is encoded again beside that summary (one set layer, so that a
    view's meaning can depend on the others), pooled again, and a decoder reads the pool with
    the initial 3D relative to the anchor and predicts offsets from each keypoint's initial
    estimate (`initial_estimate`, per keypoint). Nothing depends on the cameras' number or order;
    world vectors are read after `FrameRotation` (identity unless set: a rig whose up is not +z
    is turned to the z-up world the model was trained in, and its output turned back).
    """

    def __init__(self, num_keypoints: int, config: MLPConfig, *, rngs: nnx.Rngs):
        if config.views != "pooled":
            raise ValueError("ViewPooledMLP needs MLPConfig(views='pooled')")
        self.num_keypoints = num_keypoints
        self.slope = config.slope
        K = num_keypoints
        widths = tuple(config.view_widths)
        # Per view: K x (visible, x, y, score, ray 3) and the camera relative to the anchor.
        sizes = (K * 7 + 3,) + widths
        self.encode = nnx.List(
            [nnx.Linear(a, b, rngs=rngs) for a, b in zip(sizes[:-1], sizes[1:], strict=True)]
        )
        self.relate = nnx.Linear(widths[-1] * 3, widths[-1], rngs=rngs)
        dec = (widths[-1] * 2 + K * 4,) + tuple(config.widths)
        self.decode = nnx.List(
            [nnx.Linear(a, b, rngs=rngs) for a, b in zip(dec[:-1], dec[1:], strict=True)]
        )
        # Offsets start at zero: an untrained model returns the initial estimate.
        self.out = nnx.Linear(dec[-1], K * 3, kernel_init=nnx.initializers.zeros, rngs=rngs)
        self.rotation = FrameRotation(jnp.eye(3, dtype=jnp.float32))

    def __call__(self, features: jax.Array) -> jax.Array:
        q = self.rotation[...]
        features = turned_features(features, q)
        xyz, has, anchor = initial_estimate_parts(features)  # (..., K, 3), (..., K), (..., 3)
        seen = features[..., 0]  # (..., C, K)
        present = seen.max(axis=-1) > 0  # (..., C)
        # The view's camera: the same in every visible keypoint's slot, zero elsewhere.
        camera = (
            jnp.sum(features[..., 4:7] * seen[..., None], axis=-2)
            / jnp.maximum(seen.sum(-1), 1.0)[..., None]
        )  # (..., C, 3)
        per_view = jnp.concatenate(
            [
                features[..., :4].reshape(features.shape[:-2] + (-1,)),
                features[..., 7:10].reshape(features.shape[:-2] + (-1,)),
                jnp.where(present[..., None], camera - anchor[..., None, :], 0.0),
            ],
            axis=-1,
        )  # (..., C, K*7 + 3)
        h = per_view
        for layer in self.encode:
            h = jax.nn.leaky_relu(layer(h), self.slope)
        pooled = masked_view_pool(h, present)  # (..., 2W)
        context = jnp.broadcast_to(pooled[..., None, :], h.shape[:-1] + pooled.shape[-1:])
        h = jax.nn.leaky_relu(self.relate(jnp.concatenate([h, context], -1)), self.slope)
        pooled = masked_view_pool(h, present)
        rel = jnp.where(has[..., None] > 0, xyz - anchor[..., None, :], 0.0)
        batch = features.shape[:-3]
        g = jnp.concatenate(
            [pooled, jnp.concatenate([has[..., None], rel], -1).reshape(batch + (-1,))], -1
        )
        for layer in self.decode:
            g = jax.nn.leaky_relu(layer(g), self.slope)
        offsets = self.out(g).reshape(batch + (self.num_keypoints, 3))
        out = offsets + initial_estimate(features, per_keypoint=True)
        return out @ q  # back to the world frame


def masked_view_pool(h: jax.Array, present: jax.Array) -> jax.Array:
    """Mean and max of (..., C, W) over the present views (..., C): (..., 2W); zeros without any."""
    m = present[..., None].astype(h.dtype)
    mean = jnp.sum(h * m, axis=-2) / jnp.maximum(m.sum(-2), 1.0)
    top = jnp.max(jnp.where(present[..., None], h, -jnp.inf), axis=-2)
    return jnp.concatenate([mean, jnp.where(present.any(-1)[..., None], top, 0.0)], axis=-1)


def estimator_model(
    num_cameras: int, num_keypoints: int, config: MLPConfig, *, rngs: nnx.Rngs
) -> nnx.Module:
    """The 3D estimator ``config.views`` names: `PoseMLP` (per-camera slots, the paper's) or
    `ViewPooledMLP` (any rig; ``num_cameras`` is then only the features' slot count)."""
    if config.views == "pooled":
        return ViewPooledMLP(num_keypoints, config, rngs=rngs)
    return PoseMLP(num_cameras, num_keypoints, config, rngs=rngs)


def initialised(make: Callable[[], nnx.Module]) -> nnx.Module:
    """``make()``'s model with its initial parameters drawn in one jitted program: drawn eagerly,
    every weight shape compiles random-number programs of its own (about ten a network, a
    second or more before training starts). The numbers are the same (threefry's bits and the
    same arithmetic, in or out of one program)."""
    graphdef, _ = nnx.split(nnx.eval_shape(make))
    return nnx.merge(graphdef, jax.jit(lambda: nnx.split(make())[1])())


def unfilled(make: Callable[[], nnx.Module]) -> tuple[Any, Any, Any]:
    """``make()``'s model split as (graphdef, params, rest) to load into: its parameters abstract
    (shapes and dtypes, what a checkpoint restores into), its other state (a rig-agnostic model's
    frame) as ``make`` sets it. Unlike `initialised`, the initial parameters are never drawn: a
    loader replaces them, and the jitted ``rest`` alone leaves them out of its program (drawn
    eagerly, the shipped models compiled 17 random-number programs, 3 s of a cold ``infer``)."""
    graphdef, params, _ = nnx.split(nnx.eval_shape(make), nnx.Param, ...)
    rest = jax.jit(lambda: nnx.split(make(), nnx.Param, ...)[2])()
    return graphdef, params, rest


def to_world(xyz_normalised: jax.Array, centre: jax.Array, radius: jax.Array) -> jax.Array:
    """Rig-normalised coordinates to metres. xyz: (..., 3); centre: (3,); radius: ()."""
    return xyz_normalised * radius + centre.reshape((1,) * (xyz_normalised.ndim - 1) + (3,))


def count_params(params) -> int:
    """Number of scalars in a parameter pytree."""
    return int(sum(math.prod(x.shape) for x in jax.tree_util.tree_leaves(params)))


# =========================================================================== skeleton matching GAT
# (DESIGN.md §1.2; graphs come from `mvpose_jax.graphs`.)


PAPER_GAT_WIDTHS = (40, 40, 40, 30, 1)
PAPER_GAT_HEADS = (10, 10, 8, 5, 1)


@dataclasses.dataclass(frozen=True)
class GATConfig:
    """The skeleton-matching GAT's architecture (the paper's by default).

    Attributes:
      widths: output width of each attention layer, heads concatenated; the last must be 1 (the
        match score). Paper: [40, 40, 40, 30] hidden and 1 output.
      heads: attention heads of each layer (each width must divide by its heads). Paper:
        [10, 10, 8, 5] and 1.
      inner_slope: LeakyReLU slope inside each layer's projection ``W2·LeakyReLU(W1·h)`` and in the
        attention logits (paper/original code 0.15).
      between_slope: LeakyReLU slope between layers (0.01).
      views: how the cameras enter. "slots" (the paper): each detection node's features sit in
        its camera's slot, so the network is tied to its cameras' number and order. "pooled":
        `RigAgnosticGAT`, one network for any rig.
      encoder_widths: "pooled" only: the layers that encode a detection node's skeleton and a
        match node's pair geometry before the attention layers.
    """

    widths: tuple[int, ...] = PAPER_GAT_WIDTHS
    heads: tuple[int, ...] = PAPER_GAT_HEADS
    inner_slope: float = 0.15
    between_slope: float = 0.01
    views: str = "slots"
    encoder_widths: tuple[int, ...] = (128, 64)

    def __post_init__(self):
        if self.views not in ("slots", "pooled"):
            raise ValueError(f"GATConfig.views must be slots or pooled, not {self.views!r}")
        if len(self.widths) != len(self.heads) or not self.widths:
            raise ValueError("GATConfig: widths and heads need the same, non-zero length")
        if self.widths[-1] != 1 or self.heads[-1] != 1:
            raise ValueError("GATConfig: the last layer must have width 1 and 1 head")
        for w, h in zip(self.widths, self.heads, strict=True):
            if w % h:
                raise ValueError(f"GATConfig: width {w} is not a multiple of {h} heads")

    @classmethod
    def quick(cls) -> GATConfig:
        """Three attention layers instead of five, for fast runs and tests."""
        return cls(widths=(24, 24, 1), heads=(4, 4, 1))

    @classmethod
    def pooled(cls) -> GATConfig:
        """The rig-agnostic matcher's sizes (`RigAgnosticGAT`)."""
        return cls(widths=(64, 64, 32, 1), heads=(8, 8, 4, 1), views="pooled")


class GATLayer(nnx.Module):
    """One graph-attention layer: (N, in) node features -> (N, heads * width/heads).

    ``z = W2·LeakyReLU(W1·h)`` (W1 square; both with bias), split into heads; per edge
    ``e = LeakyReLU(a_l·z_src + a_r·z_dst)``; softmax of ``e`` over the edges entering each node;
    the node's new feature is the attention-weighted sum of ``z_src``; heads are concatenated.

    ``feature_major``: W1 is stored (out, in) (`FeatureMajorLinear`, as ``fc1_out_in``), for the
    first layer, whose wide W1 multiplies a few detection rows (see `MatchingGAT`). Same function
    and initial values; the other name makes a checkpoint of the other layout fail to load
    instead of loading transposed.
    """

    def __init__(
        self,
        in_dim: int,
        width: int,
        heads: int,
        slope: float,
        *,
        feature_major: bool = False,
        rngs: nnx.Rngs,
    ):
        self.heads, self.head_dim, self.slope = heads, width // heads, slope
        self.feature_major = feature_major
        if feature_major:
            self.fc1_out_in = FeatureMajorLinear(in_dim, in_dim, rngs=rngs)
            rngs.params()  # nnx.Linear draws a bias key too: the layers after it start as before
        else:
            self.fc1 = nnx.Linear(in_dim, in_dim, rngs=rngs)
        self.fc2 = nnx.Linear(in_dim, width, rngs=rngs)
        init = nnx.initializers.xavier_normal()
        self.attn_src = nnx.Param(init(rngs.params(), (heads, self.head_dim)))
        self.attn_dst = nnx.Param(init(rngs.params(), (heads, self.head_dim)))

    def project(self, h: jax.Array) -> jax.Array:
        """(N, in) -> z (N, heads, head_dim)."""
        pre = self.fc1_out_in(h.T).T if self.feature_major else self.fc1(h)
        z = self.fc2(jax.nn.leaky_relu(pre, self.slope))
        return z.reshape(z.shape[:-1] + (self.heads, self.head_dim))

    def attend(self, z: jax.Array, graphs: jraph.GraphsTuple) -> jax.Array:
        """Attention over incoming edges. z: (N, heads, head_dim) -> (N, heads * head_dim).

        As jraph.segment_softmax, but the logits' two halves are per-node scalars gathered per
        edge, not per-edge dot products of gathered (E, heads, head_dim) features: a third less
        time per layer on CPU, the same numbers.
        """
        num_nodes = z.shape[0]
        src = (z * self.attn_src[...][None]).sum(-1)  # (N, heads): a_l . z of each node
        dst = (z * self.attn_dst[...][None]).sum(-1)
        logits = jax.nn.leaky_relu(
            src[graphs.senders] + dst[graphs.receivers], self.slope
        )  # (E, heads)
        alpha = jraph.segment_softmax(logits, graphs.receivers, num_nodes)[
            ..., None
        ]  # (E, heads, 1)
        out = jax.ops.segment_sum(
            alpha * z[graphs.senders], graphs.receivers, num_nodes
        )  # (N, heads, head_dim)
        return out.reshape(num_nodes, self.heads * self.head_dim)

    def __call__(self, h: jax.Array, graphs: jraph.GraphsTuple) -> jax.Array:
        return self.attend(self.project(h), graphs)


class MatchingGAT(nnx.Module):
    """The skeleton-matching GAT: a `GraphBatch` -> (N,) scores in [0, 1] (match nodes matter).

    The first layer's input is the paper's (N, 2 + C·K·10) matrix, which is zero outside the
    one-hot and the node's own camera slot. Its projection is computed exactly but cheaply: match
    and padding nodes carry only a one-hot, so their ``z`` is one of two rows computed once; the
    square ``W1`` multiplies detection rows only (`graphs.GraphBatch.det_features`), stored
    (out, in) so that the product of the wide matrix with a few rows streams it once
    (benchmarks/README.md).
    """

    def __init__(self, num_cameras: int, num_keypoints: int, config: GATConfig, *, rngs: nnx.Rngs):
        if config.views != "slots":
            raise ValueError("MatchingGAT needs GATConfig(views='slots'); see matcher_model")
        self.num_keypoints = num_keypoints
        self.in_dim = 2 + num_cameras * num_keypoints * NUM_KEYPOINT_FEATURES
        self.between_slope = config.between_slope
        dims = (self.in_dim,) + tuple(config.widths[:-1])
        self.layers = nnx.List(
            [
                GATLayer(d, w, h, config.inner_slope, feature_major=i == 0, rngs=rngs)
                for i, (d, w, h) in enumerate(zip(dims, config.widths, config.heads, strict=True))
            ]
        )

    def slot_products(self, rows: jax.Array) -> jax.Array:
        """W1 times keypoint rows held per camera: (C, R, K*10) -> (C, R, in), row r of camera c
        multiplied by camera c's slot of W1 alone (no one-hot, no bias).

        Inference holds its detections per camera (F, C, P slots), so each camera's rows meet
        only their own slot of the square W1: a C-th of the dense product's work (5 views: 180
        of 902 columns), for `first_projection`'s ``det_pre``."""
        w1 = self.layers[0].fc1_out_in.kernel[...]  # (out, in)
        C = rows.shape[0]
        slots = w1[:, 2:].reshape(w1.shape[0], C, -1)  # (out, C, K*10)
        return jnp.einsum("crk,ock->cro", rows, slots)

    def first_projection(self, batch: GraphBatch, det_pre: jax.Array | None = None) -> jax.Array:
        """z of the first layer, (N, heads, head_dim), without densifying the node features.

        ``det_pre``: (D, in) W1 times each detection row's camera slot (`slot_products`,
        gathered per row); None: computed from ``batch.det_features``."""
        layer = self.layers[0]
        w1, b1 = layer.fc1_out_in.kernel[...], layer.fc1_out_in.bias[...]  # (out, in), (out,)
        project = lambda pre: layer.fc2(jax.nn.leaky_relu(pre, layer.slope))  # noqa: E731
        # Match and padding nodes carry only their one-hot (or nothing): their z is one of two rows.
        kind = batch.graphs.nodes  # (N, 2)
        table = project(jnp.stack([w1[:, MATCH] + b1, b1]))  # (2, width): match, padding
        is_match = kind[:, MATCH : MATCH + 1]
        z = is_match * table[0][None] + (1.0 - is_match) * table[1][None]  # (N, width)
        if det_pre is not None:
            z_det = project(det_pre + (w1[:, DETECTION] + b1)[None])  # (D, width)
        else:
            # Detection rows: the full product of their dense rows [one-hot, camera slots], as
            # columns. Prepending the one-hot to the rows (not slicing W1's one-hot columns off)
            # keeps W1 in place: a slice would copy the whole matrix on every call.
            det = batch.det_features
            one_hot = jnp.zeros((det.shape[0], 2), det.dtype).at[:, DETECTION].set(1.0)
            pre = w1 @ jnp.concatenate([one_hot, det], axis=1).T + b1[:, None]  # (in, D)
            z_det = project(pre.T)  # (D, width)
        # Padding rows point at a padding node: whatever they write there stays in padding.
        z = z.at[batch.det_node].set(jnp.where(batch.det_mask[:, None], z_det, table[1][None]))
        return z.reshape(z.shape[:-1] + (layer.heads, layer.head_dim))

    def __call__(self, batch: GraphBatch, det_pre: jax.Array | None = None) -> jax.Array:
        """(N,) scores; ``det_pre`` as `first_projection`'s."""
        graphs = batch.graphs
        h = self.layers[0].attend(self.first_projection(batch, det_pre), graphs)
        for layer in self.layers[1:]:
            h = layer(jax.nn.leaky_relu(h, self.between_slope), graphs)
        return jax.nn.sigmoid(h[:, 0])

    def dense_forward(self, node_features: jax.Array, graphs: jraph.GraphsTuple) -> jax.Array:
        """The same network on the paper's dense (N, 2 + C·K·10) features (reference, tests)."""
        h = node_features
        for i, layer in enumerate(self.layers):
            if i:
                h = jax.nn.leaky_relu(h, self.between_slope)
            h = layer(h, graphs)
        return jax.nn.sigmoid(h[:, 0])


class FrameScale(nnx.Variable):
    """Metres per unit of a model's inputs' world coordinates (not trained): the rig's radius
    for features in the rig-normalised frame (`features.keypoint_features`), 1 for features
    already in metres; set when a rig-agnostic matcher is loaded for a rig."""


# Per keypoint of a cross-view skeleton pair (`pair_geometry`).
NUM_PAIR_FEATURES = 9


def closest_ray_points(
    c1: jax.Array, d1: jax.Array, c2: jax.Array, d2: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Depths along two rays (centres ``c``, unit directions ``d``, (..., 3)) of their points of
    closest approach, and the gap between those points: (s (...), t (...), gap (...)), in the
    units of the centres. Near-parallel rays take the foot of ``c1``'s perpendicular."""
    w0 = c1 - c2
    b = jnp.sum(d1 * d2, -1)
    d = jnp.sum(d1 * w0, -1)
    e = jnp.sum(d2 * w0, -1)
    denom = 1.0 - b * b
    parallel = denom < 1e-6
    safe = jnp.where(parallel, 1.0, denom)
    s = jnp.where(parallel, 0.0, (b * e - d) / safe)
    t = jnp.where(parallel, e, (e - b * d) / safe)
    gap = jnp.linalg.norm(w0 + s[..., None] * d1 - t[..., None] * d2, axis=-1)
    return s, t, gap


def pair_geometry(a: jax.Array, b: jax.Array, q: jax.Array, scale: jax.Array) -> jax.Array:
    """What two skeletons of different views say about being one person, per keypoint, the
    same whichever is first; rig-agnostic (metres and angles in a z-up frame).

    Args:
      a, b: (..., K, 10) the two skeletons' keypoint features (`features.keypoint_features`).
      q: (3, 3) rotation into the model's z-up frame; scale: metres per input unit.
    Returns:
      (..., K, `NUM_PAIR_FEATURES`): both seen; the rays' gap as an angle (gap over the nearer
      depth; two soft scales, 1 and 5 degrees) and in metres (10 and 50 cm); the height of
      their meeting point above the rig's centre; the nearer and the farther depth (negative:
      behind a camera); the product of the scores. All zero where either view misses the
      keypoint.
    """
    both = a[..., 0] * b[..., 0]
    ca, cb = (a[..., 4:7] @ q.T) * scale, (b[..., 4:7] @ q.T) * scale
    da, db = a[..., 7:10] @ q.T, b[..., 7:10] @ q.T
    s, t, gap = closest_ray_points(ca, da, cb, db)
    near, far = jnp.minimum(s, t), jnp.maximum(s, t)
    angle = gap / jnp.maximum(near, 0.1)
    height = 0.5 * (ca[..., 2] + s * da[..., 2] + cb[..., 2] + t * db[..., 2])
    feats = jnp.stack(
        [
            both,
            jnp.tanh(angle / 0.0175),
            jnp.tanh(angle / 0.0873),
            jnp.tanh(gap / 0.1),
            jnp.tanh(gap / 0.5),
            jnp.clip(height, -6.0, 6.0) / 2.0,
            jnp.clip(near, -3.0, 30.0) / 5.0,
            jnp.clip(far, -3.0, 30.0) / 5.0,
            a[..., 3] * b[..., 3],
        ],
        axis=-1,
    )
    return jnp.where(both[..., None] > 0, feats, 0.0)


class RigAgnosticGAT(nnx.Module):
    """A skeleton matcher for any rig: a `GraphBatch` -> (N,) scores in [0, 1], any number and
    order of cameras.

    The paper's GAT reads a detection's features in its camera's slot, so it learns each camera
    pair's geometry separately and is tied to its rig. Here nothing depends on which slot a
    detection sits in (the slots are summed; only the node's own is non-zero):

    * a detection node is its skeleton (visible, x, y, score and ray of each keypoint) and its
      camera's centre, in metres from the rig's centre, through an encoder shared by all views;
    * a match node, empty in the paper, carries its pair's geometry (`pair_geometry`: how far
      the two views' rays through each keypoint pass from each other, where they meet), through
      a second encoder;
    * the paper's attention layers (`GATLayer`) then pass messages over the same graph, so that
      a pair's score can depend on the detections' other candidate pairs.

    World vectors are read after `FrameRotation` and `FrameScale` (set per rig when loaded,
    `trained.rig_agnostic_matcher`): the model works in metres in a z-up world, as it was
    trained.
    """

    def __init__(self, num_keypoints: int, config: GATConfig, *, rngs: nnx.Rngs):
        if config.views != "pooled":
            raise ValueError("RigAgnosticGAT needs GATConfig(views='pooled')")
        K = self.num_keypoints = num_keypoints
        self.between_slope = config.between_slope
        self.slope = config.inner_slope
        enc = tuple(config.encoder_widths)
        det = (K * 7 + 3,) + enc
        self.encode_detection = nnx.List(
            [nnx.Linear(a, b, rngs=rngs) for a, b in zip(det[:-1], det[1:], strict=True)]
        )
        pair = (K * NUM_PAIR_FEATURES + 1,) + enc
        self.encode_pair = nnx.List(
            [nnx.Linear(a, b, rngs=rngs) for a, b in zip(pair[:-1], pair[1:], strict=True)]
        )
        dims = (enc[-1] + 2,) + tuple(config.widths[:-1])
        self.layers = nnx.List(
            [
                GATLayer(d, w, h, config.inner_slope, rngs=rngs)
                for d, w, h in zip(dims, config.widths, config.heads, strict=True)
            ]
        )
        self.rotation = FrameRotation(jnp.eye(3, dtype=jnp.float32))
        self.scale = FrameScale(jnp.ones((), jnp.float32))

    def _mlp(self, layers, h: jax.Array) -> jax.Array:
        for layer in layers:
            h = jax.nn.leaky_relu(layer(h), self.slope)
        return h

    def __call__(self, batch: GraphBatch) -> jax.Array:
        q, scale = self.rotation[...], self.scale[...]
        K = self.num_keypoints
        D = batch.det_features.shape[0]
        # Only the detection's own camera slot is non-zero: the sum is that slot.
        rows = batch.det_features.reshape(D, -1, K, NUM_KEYPOINT_FEATURES).sum(1)  # (D, K, 10)
        seen = rows[..., 0]
        camera = (
            jnp.sum(rows[..., 4:7] * seen[..., None], -2)
            / jnp.maximum(seen.sum(-1), 1.0)[..., None]
        )
        per_view = jnp.concatenate(
            [
                rows[..., :4].reshape(D, -1),
                (rows[..., 7:10] @ q.T).reshape(D, -1),
                (camera @ q.T) * scale,
            ],
            -1,
        )
        h_det = self._mlp(self.encode_detection, per_view)  # (D, E)
        # Each match node's two detection rows (padding rows point at a padding node).
        N = batch.node_mask.shape[0]
        row_of_node = jnp.zeros(N, jnp.int32).at[batch.det_node].set(jnp.arange(D, dtype=jnp.int32))
        ends = row_of_node[jnp.maximum(batch.pair, 0)]  # (N, 2)
        geometry = pair_geometry(rows[ends[:, 0]], rows[ends[:, 1]], q, scale)  # (N, K, 9)
        shared = geometry[..., 0].mean(-1, keepdims=True)
        h_pair = self._mlp(
            self.encode_pair, jnp.concatenate([geometry.reshape(N, -1), shared], -1)
        )  # (N, E)
        is_match = (batch.is_match & batch.node_mask)[:, None]
        h = jnp.where(is_match, h_pair, 0.0)
        h = h.at[batch.det_node].set(jnp.where(batch.det_mask[:, None], h_det, h[batch.det_node]))
        h = jnp.concatenate([h, batch.graphs.nodes], -1)  # with the [detection, match] one-hot
        graphs = batch.graphs
        for i, layer in enumerate(self.layers):
            if i:
                h = jax.nn.leaky_relu(h, self.between_slope)
            h = layer(h, graphs)
        return jax.nn.sigmoid(h[:, 0])


def matcher_model(
    num_cameras: int, num_keypoints: int, config: GATConfig, *, rngs: nnx.Rngs
) -> nnx.Module:
    """The matcher ``config.views`` names: `MatchingGAT` (per-camera slots, the paper's) or
    `RigAgnosticGAT` (any rig; ``num_cameras`` is then unused)."""
    if config.views == "pooled":
        return RigAgnosticGAT(num_keypoints, config, rngs=rngs)
    return MatchingGAT(num_cameras, num_keypoints, config, rngs=rngs)


@functools.partial(jax.jit, static_argnums=0)
def stacked_match_scores(graphdef, rest, params, batch: GraphBatch) -> jax.Array:
    """The matcher's node scores for S graph batches stacked on a leading axis (one per device).

    Args:
      batch: a `GraphBatch` whose every leaf has a leading (S,) axis (`split_graph_batch`),
        split over the devices along it (`parallel.shard_batch`).
    Returns:
      (S, N) scores, split like ``batch``.
    """
    return jax.vmap(lambda b: nnx.merge(graphdef, params, rest)(b))(batch)
