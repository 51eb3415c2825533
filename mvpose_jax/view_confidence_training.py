"""Training the view-confidence network (`view_confidence`) without a real label.

Examples come from synthetic recordings (`synthetic.simulate`, best with the detector fitted to
the user's recording: `detector_fit.fit_detector`); the generator knows each detection's true
person and noise-free projection, so a view's keypoint is labelled an outlier where it lies
farther than `INLIER_FRACTION` of the person's image size from its true projection (a swap, an
inversion, a mixed limb, heavy jitter). People are grouped by their true identities. The
features are `view_confidence.view_features`, the loss binary cross-entropy, the step
`train.make_train_step`'s. The drop threshold is chosen on validation scenes
(`choose_threshold`) by the error of `view_confidence.triangulate_confident` against their 3D
truth.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx

from mvpose_jax.cameras import Rig
from mvpose_jax.data.recording import Recording
from mvpose_jax.graphs import next_power_of_two
from mvpose_jax.lifting import group_people, members_from_identity
from mvpose_jax.train import init_train_state, make_optimizer, make_train_step
from mvpose_jax.trained import TrainConfig
from mvpose_jax.triangulate import triangulate_points, triangulate_skeletons_robust
from mvpose_jax.view_confidence import (
    ConfidenceConfig,
    ConfidenceNet,
    ViewConfidence,
    inlier_probability,
    layout_tables,
    triangulate_confident,
    view_features,
)

# A view's keypoint is an inlier within this fraction of the person's image size (the diagonal of
# its true keypoints' box) of its true projection, and never needs to be closer than
# `MIN_INLIER_PX`: on a 1.7 m person 700 px tall (diagonal ~750 px) that is 38 px, above the
# simulator's jitter (8-12 px mean) and below a swapped wrist's error.
INLIER_FRACTION = 0.05
MIN_INLIER_PX = 8.0
THRESHOLDS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)


@dataclasses.dataclass(frozen=True)
class Examples:
    """Grouped people of synthetic recordings, with what the generator knows.

    xy (N, C, K, 2), score (N, C, K), projected (N, C, K, 2): noise-free projections of the truth;
    truth (N, K, 3) metres and truth_valid (N, K); inlier (N, C, K) labels (valid where score > 0).
    """

    xy: np.ndarray
    score: np.ndarray
    projected: np.ndarray
    truth: np.ndarray
    truth_valid: np.ndarray
    inlier: np.ndarray

    def __len__(self) -> int:
        return len(self.score)


def outlier_labels(
    xy: np.ndarray, projected: np.ndarray, score: np.ndarray, fraction: float = INLIER_FRACTION
) -> np.ndarray:
    """(N, C, K) bool inlier labels of detections against their true projections: within
    ``fraction`` of the person's image size, or `MIN_INLIER_PX` (module doc)."""
    seen = score > 0
    lo = np.min(np.where(seen[..., None], projected, np.inf), axis=-2)
    hi = np.max(np.where(seen[..., None], projected, -np.inf), axis=-2)
    diag = np.where(np.isfinite(hi - lo).all(-1), np.linalg.norm(hi - lo, axis=-1), 0.0)
    tol = np.maximum(fraction * diag, MIN_INLIER_PX)[..., None]  # (N, C, 1)
    return seen & (np.linalg.norm(xy - projected, axis=-1) <= tol)


def examples_from_recordings(
    recordings: Sequence[Recording], fraction: float = INLIER_FRACTION
) -> Examples:
    """Every true person seen by two or more views of the recordings (true groupings), labelled
    by `outlier_labels` with ``fraction``."""
    parts = []
    for rec in recordings:
        if rec.identity is None or rec.projected is None or rec.ground_truth is None:
            raise ValueError("needs synthetic recordings (identity, projections, 3D truth)")
        gt = rec.ground_truth
        G = np.shape(gt.valid)[1]
        members = members_from_identity(rec.identity, G)  # (F, G, C)
        xy, score = group_people(rec.detections.xy, rec.detections.score, members)
        proj, _ = group_people(rec.projected, rec.detections.score, members)
        views = (score > 0).any(-1).sum(-1)  # (F, G)
        keep = (views >= 2) & np.asarray(gt.valid, bool)
        parts.append(
            (
                xy[keep],
                score[keep],
                proj[keep],
                np.asarray(gt.xyz)[keep],
                np.asarray(gt.keypoint_valid, bool)[keep],
            )
        )
    xy, score, proj, truth, tv = (np.concatenate(a) for a in zip(*parts, strict=True))
    return Examples(xy, score, proj, truth, tv, outlier_labels(xy, proj, score, fraction))


def features_of(rig: Rig, ex: Examples, layout: str = "coco18", chunk: int = 256):
    """`view_features` of every example, in chunks of padded shape. Returns features
    (M, NUM_FEATURES) and labels (M,) float of the seen views, and their (N, C, K) mask."""
    flip, bones = layout_tables(layout)
    feats, seen = [], []
    for lo in range(0, len(ex), chunk):
        xy, score = ex.xy[lo : lo + chunk], ex.score[lo : lo + chunk]
        n = len(xy)
        pad = next_power_of_two(n) - n
        xy = np.pad(xy, ((0, pad), (0, 0), (0, 0), (0, 0)))
        score = np.pad(score, ((0, pad), (0, 0), (0, 0)))
        f, s = view_features(rig, jnp.asarray(xy, jnp.float32), jnp.asarray(score), flip, bones)
        feats.append(np.asarray(f)[:n])
        seen.append(np.asarray(s)[:n])
    feats, seen = np.concatenate(feats), np.concatenate(seen)
    return feats[seen], ex.inlier[seen].astype(np.float32), seen


def fit_view_confidence(
    train: tuple[np.ndarray, np.ndarray],
    dev: tuple[np.ndarray, np.ndarray],
    config: ConfidenceConfig = ConfidenceConfig(),
    *,
    steps: int = 2000,
    batch_size: int = 1024,
    learning_rate: float = 1e-3,
    seed: int = 0,
) -> tuple[ViewConfidence, dict]:
    """Binary cross-entropy on (features (M, F), labels (M,)); the parameters with the lowest
    dev loss (checked every 200 steps) are kept. Returns (model, record: losses and accuracy)."""
    model = ConfidenceNet(config, rngs=nnx.Rngs(seed))
    tx = make_optimizer(TrainConfig(learning_rate=learning_rate, max_steps=steps))
    graphdef, rest, state = init_train_state(model, tx)
    step_fn = make_train_step(graphdef, rest, tx, _bce_loss)
    x, y = train
    rng = np.random.default_rng(seed)
    key = jax.random.key(seed)
    dev_x, dev_y = jnp.asarray(dev[0]), jnp.asarray(dev[1])
    best = (np.inf, state.params, 0)
    history = []
    for step in range(steps):
        idx = rng.integers(0, len(y), batch_size)
        state, metrics = step_fn(state, (jnp.asarray(x[idx]), jnp.asarray(y[idx])), key)
        if (step + 1) % 200 == 0 or step + 1 == steps:
            vm = ViewConfidence(graphdef, rest, state.params, config)
            val = float(_dev_loss(vm, dev_x, dev_y))
            history.append(
                {"step": step + 1, "train_loss": float(metrics["loss"]), "dev_loss": val}
            )
            if val < best[0]:
                best = (val, jax.tree.map(jnp.copy, state.params), step + 1)
    trained = ViewConfidence(graphdef, rest, best[1], config)
    logits = _logits(trained, dev_x)
    pred = np.asarray(logits) > 0
    truth = np.asarray(dev_y) > 0.5
    record = {
        "dev_loss": best[0],
        "best_step": best[2],
        "history": history,
        "dev_accuracy": float((pred == truth).mean()),
        "dev_outlier_recall": float((~pred & ~truth).sum() / max((~truth).sum(), 1)),
        "dev_inlier_recall": float((pred & truth).sum() / max(truth.sum(), 1)),
        "dev_outlier_share": float((~truth).mean()),
    }
    return trained, record


def _bce_loss(model, batch, key):
    del key
    x, y = batch
    per_item = optax.sigmoid_binary_cross_entropy(model(x), y)
    return per_item, jnp.ones_like(per_item, bool), {}


def _logits(model: ViewConfidence, x) -> jax.Array:
    return _apply(model.graphdef, model.rest, model.params, x)


@functools.partial(jax.jit, static_argnums=0)
def _apply(graphdef, rest, params, x):
    return nnx.merge(graphdef, params, rest)(x)


def _dev_loss(model: ViewConfidence, x, y) -> jax.Array:
    return jnp.mean(optax.sigmoid_binary_cross_entropy(_logits(model, x), y))


def triangulation_errors(
    model: ViewConfidence | None,
    rig: Rig,
    ex: Examples,
    thresholds: Sequence[float] = THRESHOLDS,
    layout: str = "coco18",
) -> dict:
    """Mean 3D error (mm) against the truth of robust triangulation, DLT, and the confident
    triangulation at each threshold (``then`` robust and DLT), on the keypoints each reconstructs;
    with ``model`` None only the geometric rows. Keypoints: those robust triangulation
    reconstructs and the truth has (the same set for every row)."""
    px, w = np.moveaxis(ex.xy, 1, 0), np.moveaxis(ex.score, 1, 0)
    rob, rob_ok, _ = (np.asarray(a) for a in triangulate_skeletons_robust(rig, px, w))
    common = rob_ok & ex.truth_valid

    def mm(xyz, ok):
        use = common & ok
        return float(1000 * np.linalg.norm(xyz - ex.truth, axis=-1)[use].mean()), int(use.sum())

    out = {"robust": mm(rob, rob_ok)}
    dlt, dlt_ok = (np.asarray(a) for a in triangulate_points(rig, px, w))
    out["dlt"] = mm(dlt, dlt_ok)
    if model is None:
        return out
    p = np.moveaxis(inlier_probability(model, rig, ex.xy, ex.score, layout), 1, 0)
    for then in ("robust", "dlt"):
        for t in thresholds:
            xyz, ok = triangulate_confident(rig, px, w, p, threshold=t, then=then)
            out[f"confident {then} {t:g}"] = mm(np.asarray(xyz), np.asarray(ok))
    return out


def choose_threshold(errors: dict, then: str = "robust") -> float:
    """The threshold of the lowest error among `triangulation_errors`' confident rows."""
    rows = {k: v for k, v in errors.items() if k.startswith(f"confident {then} ")}
    best = min(rows, key=lambda k: rows[k][0])
    return float(best.rsplit(" ", 1)[1])
