"""A learned temporal stage: a track's window of frames, all its views -> each frame's 3D.

Butterworth filtering smooths what triangulation found; it cannot place a wrist that fewer than
two views see. `TemporalNet` reads a window of ``T`` frames of one tracked person, every view of
every frame, and predicts each frame's keypoints:

* per frame, each present view is encoded by shared weights and the views are pooled (masked
  mean and max, one set layer between: `models.ViewPooledMLP`'s per-frame encoder), beside the
  frame's initial 3D (the centroid of the kept views' pairwise triangulations) relative to the
  window's anchor;
* dilated 1D convolutions over the window's frames (absent frames masked out) mix each frame
  with its neighbours, so that a keypoint a frame lacks is read from the frames around it and
  from the rest of the body;
* a decoder predicts each frame's offsets from its per-keypoint initial estimate (the window's
  anchor for a frame that has none). The number and order of cameras do not matter, and world
  vectors are read in the rig's z-up frame (`models.FrameRotation`, set from the rig's up).

It is trained without labels (`temporal_training`): confidence-weighted reprojection into every
view of the window's frames, while its inputs lose random views, keypoints and runs of a
keypoint (so that it learns to infer them from other views and from time), plus bone-length
constancy over the window and left/right bone symmetry.

`refine_tracks` runs it over tracked people: each track cut into overlapping windows, each
frame's prediction the tent-weighted mean of the windows that hold it, then (method "blend")
robust triangulation where it reconstructs a keypoint and the temporal model elsewhere
(`triangulate.blend_skeletons`, as the per-frame estimator's blend).
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, up_vector
from mvpose_jax.checkpoints import Checkpoints, save_params_folder
from mvpose_jax.compiled import bound_model_fn
from mvpose_jax.errors import InputError
from mvpose_jax.features import assemble_features, estimator_inputs, rig_agnostic_frame
from mvpose_jax.graphs import next_quarter_bucket
from mvpose_jax.models import (
    FrameRotation,
    initial_estimate,
    initial_estimate_parts,
    masked_view_pool,
    rotation_to_z_up,
    turned_features,
)
from mvpose_jax.skeletons import get_layout, leg_chains
from mvpose_jax.triangulate import (
    OUTLIER_PX,
    VIEW_OUTLIER_PX,
    blend_skeletons,
    triangulate_skeletons_robust,
)

CONFIG_FILE = "temporal.json"
TEMPORAL_METHODS = ("alone", "blend")


@dataclasses.dataclass(frozen=True)
class TemporalConfig:
    """The temporal network and how it is run.

    Attributes:
      window: frames per window (T); tracks are cut into windows overlapping by half.
      view_widths: the per-view encoder's hidden widths.
      width: channels of the temporal convolutions.
      kernel: their kernel size (frames).
      dilations: one residual convolution block per entry, with this dilation (frames).
      slope: LeakyReLU negative slope.
      layout: the keypoint layout the model was trained on.
    """

    window: int = 32
    view_widths: tuple[int, ...] = (128, 128)
    width: int = 256
    kernel: int = 5
    dilations: tuple[int, ...] = (1, 2, 4, 1)
    slope: float = 0.1
    layout: str = "coco18"

    def __post_init__(self):
        if self.window < 2 or self.kernel < 1 or not self.dilations or not self.view_widths:
            raise InputError(
                "window must be >= 2, kernel >= 1, with at least one dilation and one view width",
                field="temporal",
            )


class TemporalNet(nnx.Module):
    """(B, T, C, K, 14) features and (B, T) frame presence -> (B, T, K, 3), metres in the
    features' frame (`features.rig_agnostic_frame`)."""

    def __init__(self, num_keypoints: int, config: TemporalConfig, *, rngs: nnx.Rngs):
        K = num_keypoints
        self.num_keypoints = K
        self.slope = config.slope
        widths = tuple(config.view_widths)
        sizes = (K * 7 + 3,) + widths
        self.encode = nnx.List(
            [nnx.Linear(a, b, rngs=rngs) for a, b in zip(sizes[:-1], sizes[1:], strict=True)]
        )
        self.relate = nnx.Linear(widths[-1] * 3, widths[-1], rngs=rngs)
        D = config.width
        # Per frame: the pooled views, the initial 3D relative to the window's anchor (K x has,
        # xyz) and the frame's own anchor relative to the window's.
        self.frame_in = nnx.Linear(widths[-1] * 2 + K * 4 + 4, D, rngs=rngs)
        self.temporal = nnx.List(
            [
                nnx.Conv(
                    D,
                    D,
                    kernel_size=(config.kernel,),
                    kernel_dilation=(d,),
                    padding="SAME",
                    rngs=rngs,
                )
                for d in config.dilations
            ]
        )
        self.hidden = nnx.Linear(D, D, rngs=rngs)
        # Offsets start at zero: an untrained model returns the initial estimate.
        self.out = nnx.Linear(D, K * 3, kernel_init=nnx.initializers.zeros, rngs=rngs)
        self.rotation = FrameRotation(jnp.eye(3, dtype=jnp.float32))

    def __call__(self, features: jax.Array, present: jax.Array) -> jax.Array:
        q = self.rotation[...]
        features = turned_features(features, q)
        B, T, C, K, _ = features.shape
        xyz, has, anchor = initial_estimate_parts(features)  # (B,T,K,3), (B,T,K), (B,T,3)
        seen = features[..., 0]  # (B, T, C, K)
        view_present = seen.max(axis=-1) > 0  # (B, T, C)
        frame_has = (has.max(axis=-1) > 0) & present  # (B, T): some initial 3D
        # The window's anchor: the mean of its frames' anchors.
        fw = frame_has.astype(xyz.dtype)[..., None]
        window_anchor = jnp.sum(anchor * fw, axis=1) / jnp.maximum(fw.sum(1), 1.0)  # (B, 3)
        camera = (
            jnp.sum(features[..., 4:7] * seen[..., None], axis=-2)
            / jnp.maximum(seen.sum(-1), 1.0)[..., None]
        )  # (B, T, C, 3)
        frame_anchor = jnp.where(frame_has[..., None], anchor, window_anchor[:, None, :])
        per_view = jnp.concatenate(
            [
                features[..., :4].reshape(B, T, C, K * 4),
                features[..., 7:10].reshape(B, T, C, K * 3),
                jnp.where(view_present[..., None], camera - frame_anchor[:, :, None, :], 0.0),
            ],
            axis=-1,
        )
        h = per_view
        for layer in self.encode:
            h = jax.nn.leaky_relu(layer(h), self.slope)
        pooled = masked_view_pool(h, view_present)
        context = jnp.broadcast_to(pooled[..., None, :], h.shape[:-1] + pooled.shape[-1:])
        h = jax.nn.leaky_relu(self.relate(jnp.concatenate([h, context], -1)), self.slope)
        pooled = masked_view_pool(h, view_present)  # (B, T, 2W)
        rel = jnp.where(has[..., None] > 0, xyz - window_anchor[:, None, None, :], 0.0)
        moved = jnp.where(frame_has[..., None], anchor - window_anchor[:, None, :], 0.0)
        g = jnp.concatenate(
            [
                pooled,
                jnp.concatenate([has[..., None], rel], -1).reshape(B, T, K * 4),
                frame_has[..., None].astype(h.dtype),
                moved,
            ],
            axis=-1,
        )
        mask = present[..., None].astype(h.dtype)
        g = jax.nn.leaky_relu(self.frame_in(g), self.slope) * mask
        for conv in self.temporal:
            g = (g + jax.nn.leaky_relu(conv(g), self.slope)) * mask
        g = jax.nn.leaky_relu(self.hidden(g), self.slope)
        offsets = self.out(g).reshape(B, T, K, 3)
        start = initial_estimate(features, per_keypoint=True)  # (B, T, K, 3)
        start = jnp.where(frame_has[..., None, None], start, window_anchor[:, None, None, :])
        return (offsets + start) @ q  # back to the world frame


class TemporalModel(NamedTuple):
    """A temporal model: split NNX parts, its config and keypoint count."""

    graphdef: Any
    rest: Any
    params: Any
    config: TemporalConfig
    num_keypoints: int


def init_temporal(
    num_keypoints: int, config: TemporalConfig = TemporalConfig(), *, rig: Rig, seed: int = 0
) -> TemporalModel:
    """An untrained model for ``rig`` (its up turned to +z inside the model)."""
    net = TemporalNet(num_keypoints, config, rngs=nnx.Rngs(seed))
    graphdef, params, rest = nnx.split(net, nnx.Param, ...)
    return for_rig(TemporalModel(graphdef, rest, params, config, num_keypoints), rig)


def for_rig(model: TemporalModel, rig: Rig) -> TemporalModel:
    """The model with its frame rotation set for ``rig``'s up (``model`` itself unchanged: a
    cached model serves several rigs)."""
    rest = jax.tree.map(lambda a: a, model.rest)  # a copy of the state the rotation lives in
    net = nnx.merge(model.graphdef, model.params, rest)
    net.rotation[...] = jnp.asarray(rotation_to_z_up(up_vector(rig)), jnp.float32)
    graphdef, params, rest = nnx.split(net, nnx.Param, ...)
    return model._replace(graphdef=graphdef, params=params, rest=rest)


def window_features(rig: Rig, xy: jax.Array, score: jax.Array) -> jax.Array:
    """Features of windows of one person's views: xy (B, T, C, K, 2) pixels, score (B, T, C, K)
    (0 = missing) -> (B, T, C, K, 14) in the rig's metric frame (`rig_agnostic_frame`)."""
    B, T, C, K = score.shape
    frame = rig_agnostic_frame(rig)
    inputs = estimator_inputs(rig, xy.reshape(B * T, C, K, 2), score.reshape(B * T, C, K), frame)
    feats = assemble_features(inputs, (score.reshape(B * T, C, K) > 0).any(axis=-1))
    return feats.reshape(B, T, C, K, 14)


def apply_windows(net: TemporalNet, rig: Rig, xy, score, present) -> jax.Array:
    """``net`` on windows (shapes as `window_features`; present (B, T)): world metres
    (B, T, K, 3)."""
    centre, _ = rig_agnostic_frame(rig)
    return net(window_features(rig, xy, score), present) + centre[None, None, None, :]


def _predict_fn(graphdef, rest, params, rig, xy, score, present):
    return apply_windows(nnx.merge(graphdef, params, rest), rig, xy, score, present)


def _blend_fn(rig, xy, score, model_xyz, thresholds, legs, up):
    px, w = jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0)
    tri, ok, kept = triangulate_skeletons_robust(
        rig, px, w, outlier_px=thresholds[0], view_outlier_px=thresholds[1]
    )
    return blend_skeletons(
        rig, px, w, model_xyz=model_xyz, tri_xyz=tri, tri_valid=ok, kept=kept, legs=legs, up=up
    )


_blend_jit = jax.jit(_blend_fn)


class Windows(NamedTuple):
    """Tracked people cut into windows: rows (W, T) index person-frames (F * G flat, -1 none),
    weight (W, T) each row's share in its frame's mean (tent-shaped, 0 where none)."""

    rows: np.ndarray
    weight: np.ndarray


def track_windows(track: np.ndarray, valid: np.ndarray, window: int) -> Windows:
    """Each track's frames (first to last seen; frames it misses inside are empty slots) cut
    into windows of ``window`` frames overlapping by half, the last aligned with the track's end.

    Args:
      track: (F, G) track ids (-1 none); valid (F, G).
    """
    F, G = np.shape(track)
    track = np.where(np.asarray(valid, bool), np.asarray(track, np.int64), -1)
    f, g = np.nonzero(track >= 0)
    if len(f) == 0:
        return Windows(np.zeros((0, window), np.int64), np.zeros((0, window)))
    tid = track[f, g]
    uniq, inv = np.unique(tid, return_inverse=True)
    first = np.full(len(uniq), F)
    last = np.full(len(uniq), -1)
    np.minimum.at(first, inv, f)
    np.maximum.at(last, inv, f)
    # slot_of[t, frame - first[t]] = the flat person-frame, -1 in the track's gaps.
    length = last - first + 1
    span = np.full((len(uniq), int(length.max())), -1, np.int64)
    span[inv, f - first[inv]] = f * G + g
    stride = max(1, window // 2)
    starts_t, starts_s = [], []
    for t, n in enumerate(length):
        s = list(range(0, max(int(n) - window, 0) + 1, stride))
        if s[-1] + window < n:
            s.append(int(n) - window)
        starts_t += [t] * len(s)
        starts_s += s
    starts_t, starts_s = np.asarray(starts_t), np.asarray(starts_s)
    pos = starts_s[:, None] + np.arange(window)[None]  # (W, T)
    inside = pos < length[starts_t][:, None]
    rows = np.where(inside, span[starts_t[:, None], np.minimum(pos, span.shape[1] - 1)], -1)
    tent = np.minimum(np.arange(window) + 1, window - np.arange(window)).astype(np.float64)
    weight = np.where(rows >= 0, tent[None], 0.0)
    return Windows(rows, weight)


def refine_tracks(
    model: TemporalModel,
    rig: Rig,
    xy: np.ndarray,
    score: np.ndarray,
    track: np.ndarray,
    valid: np.ndarray,
    *,
    method: str = "blend",
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
) -> tuple[np.ndarray, np.ndarray]:
    """The temporal stage on tracked people.

    Args:
      model: a trained `TemporalModel` (its rotation set for ``rig``: `for_rig`).
      rig: the C cameras of the people's views.
      xy: (F, G, C, K, 2) each person's skeleton in each view (pixels); score (F, G, C, K), 0 =
        missing (`lifting.group_people`).
      track: (F, G) track ids, -1 none; valid (F, G): the people.
      method: "alone": the model's keypoints; "blend": robust triangulation where it
        reconstructs a keypoint, the model elsewhere (`triangulate.blend_skeletons`).
    Returns:
      xyz (F, G, K, 3) metres (the people's frames; others zero), and (F, G, K) bool: the
      keypoints robust triangulation gave ("blend"; all False for "alone").
    Raises:
      InputError for an unknown method or a layout mismatch.
    """
    if method not in TEMPORAL_METHODS:
        raise InputError(
            f"method must be one of {TEMPORAL_METHODS}, not {method!r}", field="method"
        )
    F, G, C, K = np.shape(score)
    if model.num_keypoints != K:
        raise InputError(
            f"the temporal model takes {model.num_keypoints} keypoints, the people have {K}",
            field="keypoints",
        )
    xy = np.asarray(xy, np.float32).reshape(F * G, C, K, 2)
    score = np.asarray(score, np.float32).reshape(F * G, C, K)
    win = track_windows(track, valid, model.config.window)
    out = np.zeros((F * G, K, 3))
    total = np.zeros(F * G)
    W, T = win.rows.shape
    predict = bound_model_fn(_predict_fn, model.graphdef)
    # Windows in a few padded batch sizes: one compilation per size.
    batch = 64
    for lo in range(0, W, batch):
        rows = win.rows[lo : lo + batch]
        n = len(rows)
        size = next_quarter_bucket(n)
        rows_p = np.full((size, T), -1, np.int64)
        rows_p[:n] = rows
        here = rows_p >= 0
        r = np.maximum(rows_p, 0)
        pred = np.asarray(
            predict(
                model.rest,
                model.params,
                rig,
                np.where(here[..., None, None, None], xy[r], 0.0),
                np.where(here[..., None, None], score[r], 0.0),
                here,
            )
        )[:n]
        w = win.weight[lo : lo + n]
        np.add.at(out, rows[here[:n]], pred[here[:n]] * w[here[:n]][:, None, None])
        np.add.at(total, rows[here[:n]], w[here[:n]])
    people = total > 0
    out[people] /= total[people][:, None, None]
    from_tri = np.zeros((F * G, K), bool)
    if method == "blend" and people.any():
        idx = np.nonzero(people)[0]
        n = len(idx)
        size = next_quarter_bucket(n)
        pad = lambda a: np.concatenate([a, np.zeros((size - n,) + a.shape[1:], a.dtype)])  # noqa: E731
        layout = get_layout(model.config.layout)
        blended, tri = _blend_jit(
            rig,
            pad(xy[idx]),
            pad(score[idx]),
            pad(out[idx].astype(np.float32)),
            np.array([outlier_px, view_outlier_px], np.float32),
            leg_chains(layout),
            np.asarray(up_vector(rig), np.float32),
        )
        out[idx] = np.asarray(blended)[:n]
        from_tri[idx] = np.asarray(tri)[:n]
    return out.reshape(F, G, K, 3), from_tri.reshape(F, G, K)


# =========================================================================== saved models


def save_temporal(folder: str | Path, model: TemporalModel, record: dict) -> Path:
    """Writes the parameters (orbax, ``folder/best``), the config and the training record
    (`checkpoints.save_params_folder`: never half written, an older model replaced whole)."""
    config = dataclasses.asdict(model.config) | {"num_keypoints": model.num_keypoints}
    text = json.dumps(config | {"record": record}, indent=1)
    return save_params_folder(
        folder, model.params, config, {CONFIG_FILE: text}, record.get("dev_loss", 0.0)
    )


def _blank(d: dict) -> TemporalModel:
    config = TemporalConfig(
        window=int(d["window"]),
        view_widths=tuple(int(v) for v in d["view_widths"]),
        width=int(d["width"]),
        kernel=int(d["kernel"]),
        dilations=tuple(int(v) for v in d["dilations"]),
        slope=float(d["slope"]),
        layout=str(d["layout"]),
    )
    net = TemporalNet(int(d["num_keypoints"]), config, rngs=nnx.Rngs(0))
    graphdef, params, rest = nnx.split(net, nnx.Param, ...)
    return TemporalModel(graphdef, rest, params, config, int(d["num_keypoints"]))


def load_temporal(folder: str | Path, rig: Rig) -> TemporalModel:
    """The model `save_temporal` wrote, its frame set for ``rig``.

    Raises:
      InputError: no such folder or config, or a checkpoint of another shape.
    """
    return for_rig(cached_temporal(str(folder)), rig)


def cached_temporal(folder: str) -> TemporalModel:
    """The model in ``folder``, read once per folder and version (a model saved again over it
    is read again); its frame is the identity until `for_rig` sets it.

    Raises:
      InputError: no such folder or config, or a checkpoint of another shape.
    """
    path = Path(folder) / CONFIG_FILE
    if not path.is_file():
        raise InputError(f"no temporal model here ({CONFIG_FILE} missing)", file=str(folder))
    return _read(str(Path(folder).absolute()), path.stat().st_mtime_ns)


@functools.lru_cache(maxsize=4)
def _read(folder: str, version: int) -> TemporalModel:
    d = json.loads((Path(folder) / CONFIG_FILE).read_text())
    blank = _blank(d)
    return blank._replace(params=Checkpoints(Path(folder)).restore_params(blank.params))
