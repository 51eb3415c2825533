"""The 3D stage: poses of people grouped across views, by triangulation or the trained estimator.

People arrive grouped (by proposals, or by true identities for stage-only evaluation) as
``xy (N, C_i, K, 2)``, ``score (N, C_i, K)``. The estimator runs as one jitted, batched call over
all of them; N is padded to a power of two so a long recording compiles a handful of shapes, not
one per frame. The methods are registered by name in `stages.LIFTING`; each is a ``lift_*``
function below with the registry's contract.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from mvpose_jax import stages
from mvpose_jax.cameras import Rig, up_vector
from mvpose_jax.compiled import bound_model_fn
from mvpose_jax.errors import InputError, MvposeWarning
from mvpose_jax.features import assemble_features, estimator_inputs
from mvpose_jax.graphs import next_quarter_bucket
from mvpose_jax.models import to_world
from mvpose_jax.skeletons import Detections, Poses3D, get_layout, leg_chains, zero_padded
from mvpose_jax.trained import Estimator
from mvpose_jax.triangulate import (
    MAX_SPREAD_M,
    OUTLIER_PX,
    VIEW_OUTLIER_PX,
    blend_skeletons,
    human_sized,
    triangulate_pairwise_centroid,
    triangulate_points,
    triangulate_skeletons_robust,
)
from mvpose_jax.view_confidence import (
    cached_view_confidence,
    inlier_probability,
    triangulate_confident,
)

# The triangulation methods of the 3D stage without an estimator, and those with one: its own
# output, or robust triangulation where it reconstructs a keypoint and the estimator elsewhere
# (`triangulate.blend_skeletons`). The registry (`stages.LIFTING`) may hold more.
TRIANGULATION_METHODS = ("dlt", "centroid", "robust")
ESTIMATOR_METHODS = ("mlp", "blend")


@dataclasses.dataclass(frozen=True)
class LiftingConfig:
    """The 3D stage's settings.

    Attributes:
      method: a `stages.LIFTING` name; None: "mlp" with an estimator, else "dlt"
        (`check_method`).
      outlier_px, view_outlier_px: robust triangulation's keypoint and whole-view thresholds
        (methods "robust" and "blend"; `triangulate.triangulate_skeletons_robust`).
      max_spread_m: methods "robust" and "blend": a person whose robustly triangulated keypoints
        lie farther than this (median, metres) from their median point is not one
        (`triangulate.human_sized`); inf: no such check.
      confidence: method "confident": the folder of a trained view-confidence model
        (`view_confidence.save_view_confidence`).
    """

    method: str | None = None
    outlier_px: float = OUTLIER_PX
    view_outlier_px: float = VIEW_OUTLIER_PX
    max_spread_m: float = MAX_SPREAD_M
    confidence: str | None = None


def _predict_fn(graphdef, rest, params, rig: Rig, normalisation, xy, score):
    centre, radius = normalisation
    inputs = estimator_inputs(rig, xy, score, normalisation)
    feats = assemble_features(inputs, (score > 0).any(axis=-1))
    return to_world(nnx.merge(graphdef, params, rest)(feats), centre, radius)


def _blend_fn(graphdef, rest, params, rig: Rig, normalisation, xy, score, thresholds, legs, up):
    """Method "blend": robust triangulation once, as the estimator's initial 3D (in place of the
    pairwise centroid it was trained on: on validation scenes that helped on every shift, most
    with wrong groupings) and where it reconstructs a keypoint (`triangulate.blend_skeletons`)."""
    centre, radius = normalisation
    px, w = jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0)
    tri, ok, kept = triangulate_skeletons_robust(
        rig, px, w, outlier_px=thresholds[0], view_outlier_px=thresholds[1]
    )
    initial = ((tri - centre.reshape(1, 1, 3)) / radius, ok)
    inputs = estimator_inputs(rig, xy, score, normalisation)
    feats = assemble_features(inputs, (score > 0).any(axis=-1), initial)
    model = to_world(nnx.merge(graphdef, params, rest)(feats), centre, radius)
    return blend_skeletons(
        rig, px, w, model_xyz=model, tri_xyz=tri, tri_valid=ok, kept=kept, legs=legs, up=up
    )


def predict_people(
    estimator: Estimator,
    xy: np.ndarray,
    score: np.ndarray,
    *,
    method: str = "mlp",
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
    layout: str = "coco18",
    mesh: jax.sharding.Mesh | None = None,
) -> np.ndarray:
    """3D keypoints of N people from their views in the estimator's inference cameras.

    Args:
      estimator: a trained `Estimator`.
      xy: (N, C_i, K, 2) pixels; score: (N, C_i, K), 0 = missing.
      method: "mlp", the estimator's output; or "blend", robust triangulation
        (`triangulate.triangulate_skeletons_robust` with ``outlier_px``, ``view_outlier_px``)
        where it reconstructs a keypoint and the estimator, given it as its initial 3D,
        elsewhere (`triangulate.blend_skeletons`, legs placed by their bones' lengths).
      layout: the keypoints' layout ("blend": where the legs are).
      mesh: optional data mesh (`parallel.make_data_mesh`): people are split over its devices
        (padded to a multiple of the device count), parameters replicated.
    Returns:
      (N, K, 3) metres: every keypoint, seen or not.
    """
    return _estimate_people(
        estimator,
        xy,
        score,
        method=method,
        outlier_px=outlier_px,
        view_outlier_px=view_outlier_px,
        layout=layout,
        mesh=mesh,
    )[0]


def _estimate_people(
    estimator: Estimator,
    xy: np.ndarray,
    score: np.ndarray,
    *,
    method: str,
    outlier_px: float,
    view_outlier_px: float,
    layout: str,
    mesh: jax.sharding.Mesh | None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """`predict_people`, with (method "blend") which keypoints robust triangulation gave (N, K)
    bool; None for "mlp"."""
    if method not in ESTIMATOR_METHODS:
        raise ValueError(f"method must be one of {ESTIMATOR_METHODS}, not {method!r}")
    fn = _predict_fn if method == "mlp" else _blend_fn
    extra = ()
    if method == "blend":
        lay = get_layout(layout)
        if lay.num_keypoints != np.shape(score)[-1]:
            raise InputError(
                f"layout {lay.name!r} has {lay.num_keypoints} keypoints, the people "
                f"{np.shape(score)[-1]}",
                field="layout",
            )
        thresholds = np.array([outlier_px, view_outlier_px], np.float32)
        up = np.asarray(up_vector(estimator.rig_infer), np.float32)
        extra = (thresholds, leg_chains(lay), up)
    jitted = bound_model_fn(fn, estimator.graphdef)
    if mesh is None:

        def block(xy_b, score_b):
            out = jitted(
                estimator.rest,
                estimator.params,
                estimator.rig_infer,
                estimator.normalisation,
                xy_b,
                score_b,
                *extra,
            )
            return out if isinstance(out, tuple) else (out,)

        out = _by_blocks(block, xy, score)
        return out[0], (out[1] if len(out) > 1 else None)
    xy_p, score_p = _pad_people(xy, score)
    # Local imports: this function is the only place inference needs the mesh helpers.
    from mvpose_jax.parallel import mesh_size, pad_leading, replicate, shard_batch, to_host

    n = mesh_size(mesh)
    xy_p, score_p = shard_batch(
        mesh, (pad_leading(xy_p, n), pad_leading(score_p, n))
    )  # (B, ...) split
    out = jitted(
        estimator.rest,
        replicate(mesh, estimator.params),
        estimator.rig_infer,
        replicate(mesh, estimator.normalisation),
        xy_p,
        score_p,
        *(replicate(mesh, e) for e in extra),
    )
    return _unpadded(out, to_host, len(xy))


def _unpadded(out, to_numpy, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    """A model function's output (xyz, or "blend"'s (xyz, from triangulation)) as host arrays of
    the ``n`` real people."""
    if isinstance(out, tuple):
        return to_numpy(out[0])[:n], to_numpy(out[1])[:n]
    return to_numpy(out)[:n], None


def _pad_people(
    xy: np.ndarray, score: np.ndarray, size: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(N, C, K, 2) / (N, C, K) zero-padded to ``size`` people (default
    `graphs.next_quarter_bucket(N)`: a chunk's thousand people cost their own arithmetic, not up
    to twice it), float32 numpy.

    Host arrays: the jitted call they go to moves them to the device itself, for less than an
    explicit transfer per array costs.
    """
    n = next_quarter_bucket(len(xy)) if size is None else size
    xy, score = np.asarray(xy, np.float32), np.asarray(score, np.float32)
    return zero_padded(xy, (n,) + xy.shape[1:]), zero_padded(score, (n,) + score.shape[1:])


# The 3D stage's programs take at most this many people a call: a larger batch runs in blocks
# of this size, the last zero-padded to it. A chunk's people then compile the quarter buckets up
# to it and this one size, however many people its frames hold (a recording whose chunks hold
# 300 to 2,400 people compiled seven shapes, each a few seconds; the arithmetic per person is
# the same in every shape).
PEOPLE_PER_CALL = 512


def _people_blocks(n: int) -> list[tuple[int, int, int]]:
    """(start, stop, padded size) of the calls that take ``n`` people: one call padded to
    `graphs.next_quarter_bucket` up to `PEOPLE_PER_CALL` people, blocks of that size above."""
    if n <= PEOPLE_PER_CALL:
        return [(0, n, next_quarter_bucket(n))]
    return [(s, min(n, s + PEOPLE_PER_CALL), PEOPLE_PER_CALL) for s in range(0, n, PEOPLE_PER_CALL)]


def _by_blocks(fn, xy: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, ...]:
    """``fn(xy_block, score_block)`` (padded float32 (B, C, K, 2) / (B, C, K), a tuple of
    arrays with the people first) over `_people_blocks`, joined: each output's N real rows as
    numpy. Every block is dispatched before the first is fetched."""
    calls = []
    for start, stop, size in _people_blocks(len(xy)):
        block = _pad_people(xy[start:stop], score[start:stop], size)
        calls.append((stop - start, fn(*block)))
    parts = [tuple(np.asarray(a)[:n] for a in out) for n, out in calls]
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate(column) for column in zip(*parts, strict=True))


def triangulate_people(
    rig: Rig,
    xy: np.ndarray,
    score: np.ndarray,
    method: str = "centroid",
    *,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
) -> tuple[np.ndarray, np.ndarray]:
    """The triangulation baseline on grouped people.

    Args:
      rig: the C cameras of the views.
      xy: (N, C, K, 2); score: (N, C, K).
      method: "centroid" (the paper's pairwise centroid), "dlt" (score-weighted DLT) or "robust"
        (score-weighted DLT that rejects a person's wrong views, then each keypoint's outlier
        views: `triangulate.triangulate_skeletons_robust`).
      outlier_px, view_outlier_px: "robust" only: the keypoint and whole-view thresholds, px.
    Returns:
      xyz (N, K, 3) and keypoint_valid (N, K): which keypoints two or more views reconstructed.
    """
    if method not in TRIANGULATION_METHODS:
        raise ValueError(f"method must be one of {TRIANGULATION_METHODS}, not {method!r}")

    def block(xy_b, score_b):
        px, w = np.moveaxis(xy_b, 1, 0), np.moveaxis(score_b, 1, 0)
        if method == "robust":
            return triangulate_skeletons_robust(
                rig, px, w, outlier_px=outlier_px, view_outlier_px=view_outlier_px
            )[:2]
        fn = {"centroid": triangulate_pairwise_centroid, "dlt": triangulate_points}[method]
        return fn(rig, px, w)

    return _by_blocks(block, xy, score)


def poses_from_people(xyz: np.ndarray, keypoint_valid: np.ndarray, exists: np.ndarray) -> Poses3D:
    """Packs per-person results (F, G, K, 3) / (F, G, K) / (F, G) into `Poses3D` (numpy).

    The one gate every 3D result leaves through: a non-finite keypoint (degenerate geometry) is
    flagged invalid and zeroed, and a person left with no valid keypoint does not exist, so no
    NaN or inf ever leaves inference.
    """
    xyz = np.asarray(xyz)
    kv = keypoint_valid & exists[..., None] & np.isfinite(xyz).all(axis=-1)
    exists = exists & kv.any(axis=-1)
    return Poses3D(
        np.where(kv[..., None], xyz, 0.0).astype(np.float32), exists.astype(bool), kv.astype(bool)
    )


def estimate_grouped(
    estimator: Estimator,
    xy: np.ndarray,
    score: np.ndarray,
    min_views: int = 2,
    method: str = "mlp",
    *,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
    layout: str = "coco18",
    max_spread_m: float = MAX_SPREAD_M,
) -> tuple[Poses3D, np.ndarray]:
    """Estimator poses for people grouped per frame, (F, G, C_i, K, ...) in, `Poses3D` out.

    A person exists when at least ``min_views`` inference views (1 with a single inference
    camera) have a skeleton of them and, with method "blend", its triangulated keypoints are no
    larger than a body (`triangulate.human_sized` with ``max_spread_m``: a group of two people's
    views is not a person). ``method``, ``outlier_px``, ``view_outlier_px``, ``layout``:
    `predict_people`'s.

    Returns:
      (poses, confidence (F, G): the mean detection score of the person's keypoints).
    """
    F, G, C, K = score.shape
    exists = _present(score, min_views)
    out = np.zeros((F, G, K, 3), np.float32)
    if exists.any():
        out[exists], from_tri = _estimate_people(
            estimator,
            xy[exists],
            score[exists],
            method=method,
            outlier_px=outlier_px,
            view_outlier_px=view_outlier_px,
            layout=layout,
            mesh=None,
        )
        if from_tri is not None:
            exists[exists] = _body_sized(out[exists], from_tri, max_spread_m)
    poses = poses_from_people(out, np.ones((F, G, K), bool), exists)
    return poses, _confidence(score)


def triangulate_grouped(
    rig: Rig,
    xy: np.ndarray,
    score: np.ndarray,
    method: str = "centroid",
    min_views: int = 2,
    *,
    max_spread_m: float = MAX_SPREAD_M,
    **robust,
) -> tuple[Poses3D, np.ndarray]:
    """The triangulation baseline for grouped people (same grouping as `estimate_grouped`).

    With method "robust", a person whose triangulated keypoints are larger than a body
    (`triangulate.human_sized` with ``max_spread_m``) is not one: after its wrong views are
    rejected, what is left is the group itself. "dlt" and "centroid" keep every group: one wrong
    view among right ones stretches their skeleton too, and they are the plain baselines.
    ``robust``: `triangulate_people`'s thresholds for method "robust".
    """
    F, G, C, K = score.shape
    exists = _present(score, min_views)
    out = np.zeros((F, G, K, 3), np.float32)
    kv = np.zeros((F, G, K), bool)
    if exists.any():
        out[exists], kv[exists] = triangulate_people(
            rig, xy[exists], score[exists], method, **robust
        )
    exists = exists & kv.any(axis=-1)
    if method == "robust":
        exists[exists] = _body_sized(out[exists], kv[exists], max_spread_m)
    return poses_from_people(out, kv, exists), _confidence(score)


def _body_sized(xyz: np.ndarray, valid: np.ndarray, max_spread_m: float) -> np.ndarray:
    """`triangulate.human_sized` of N people (N, K, 3) / (N, K), with a warning when it leaves
    out most of them: then the calibration's units, not the groups, are the likely cause."""
    keep = human_sized(xyz, valid, max_spread_m)
    dropped = int((~keep).sum())
    if dropped >= 2 and dropped > keep.size / 2:
        warnings.warn(
            f"most people triangulated larger than a body (keypoints a median of more than "
            f"{max_spread_m:g} m from their middle) and were left out: check the calibration's "
            "units (a translation in mm read as metres: --translation-scale 0.001)",
            MvposeWarning,
            stacklevel=2,
        )
    return keep


def _present(score: np.ndarray, min_views: int) -> np.ndarray:
    """(F, G) people with a skeleton in at least ``min_views`` views (all, with fewer cameras)."""
    views = (score > 0).any(axis=-1).sum(axis=-1)
    return views >= min(min_views, score.shape[-2])


def _confidence(score: np.ndarray) -> np.ndarray:
    seen = score > 0
    return np.where(seen, score, 0).sum(axis=(-1, -2)) / np.maximum(seen.sum(axis=(-1, -2)), 1)


def group_people(
    xy: np.ndarray, score: np.ndarray, members: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Gathers each proposed person's skeletons: xy (F, C, P, K, 2), score (F, C, P, K) and
    members (F, G, C) -> xy (F, G, C, K, 2), score (F, G, C, K) (zeros where a person has no
    skeleton in a camera)."""
    F, C, P, K = np.shape(score)
    f = np.arange(F)[:, None, None]
    c = np.arange(C)[None, None, :]
    p = np.maximum(members, 0)
    have = members >= 0
    return (
        np.where(have[..., None, None], np.asarray(xy)[f, c, p], 0.0).astype(np.float32),
        np.where(have[..., None], np.asarray(score)[f, c, p], 0.0).astype(np.float32),
    )


def poses_of_members(
    rig: Rig,
    detections: Detections,
    members: np.ndarray,
    *,
    estimator: Estimator | None = None,
    method: str | None = None,
    min_views: int = 2,
    outlier_px: float = OUTLIER_PX,
    view_outlier_px: float = VIEW_OUTLIER_PX,
    layout: str = "coco18",
    max_spread_m: float = MAX_SPREAD_M,
    confidence: str | None = None,
) -> tuple[Poses3D, np.ndarray]:
    """The 3D stage on given person groupings (proposals, or any other).

    Args:
      rig: the C cameras of the detections and of ``members``.
      detections: xy (F, C, P, K, 2), score (F, C, P, K).
      members: (F, G, C) each person's skeleton index per camera, -1 none.
      estimator: a trained estimator, on its inference cameras (found by name in ``rig``), for
        the methods "mlp" and "blend".
      method: a `stages.LIFTING` name: "mlp" (the estimator's output) or "blend" (robust
        triangulation where it reconstructs a keypoint, the estimator elsewhere;
        `predict_people`), both with an estimator; or a triangulation of keypoints seen in 2+
        views ("dlt", "centroid" or "robust", see `triangulate_people`). Default: "mlp" with an
        estimator, else "dlt".
      min_views: a person needs skeletons in this many (inference) views.
      outlier_px, view_outlier_px: the thresholds of robust triangulation (methods "robust" and
        "blend"; `triangulate_people`).
      layout: the keypoints' layout (method "blend", `predict_people`).
      max_spread_m: methods "robust" and "blend": a person whose robustly triangulated keypoints
        lie farther than this (median, metres) from their median point is not one
        (`triangulate.human_sized`; a group of two people's views, often metres large); inf: no
        such check.
      confidence: method "confident": a view-confidence model folder.
    Returns:
      (`Poses3D` (F, G, ...), confidence (F, G)).
    Raises:
      ValueError: an unknown method, or "mlp" / "blend" without an estimator.
    """
    method = check_method(method, estimator)
    p_xy, p_score = group_people(detections.xy, detections.score, members)
    config = LiftingConfig(method, outlier_px, view_outlier_px, max_spread_m, confidence)
    lift = stages.lookup("lifting", method).function()
    return lift(rig, p_xy, p_score, config, estimator=estimator, min_views=min_views, layout=layout)


def check_method(method: str | None, estimator: Estimator | None) -> str:
    """The 3D method to run: ``method``, or the default ("mlp" with an estimator, else "dlt").

    Raises:
      ValueError: an unknown method, or an estimator method without an estimator.
    """
    if method is None:
        return "mlp" if estimator is not None else "dlt"
    if stages.lookup("lifting", method, what="method").needs_estimator and estimator is None:
        raise ValueError(f"method {method!r} needs an estimator")
    return method


def _camera_columns(names: Sequence[str], wanted: Sequence[str], what: str) -> list[int]:
    missing = [c for c in wanted if c not in names]
    if missing:
        raise InputError(
            f"{what} cameras {missing} are not among the detections' cameras {list(names)}",
            field="cameras",
        )
    return [list(names).index(c) for c in wanted]


def members_from_identity(identity: np.ndarray, num_people: int) -> np.ndarray:
    """A per-detection assignment as the pipeline's person table (e.g. true proposals).

    Args:
      identity: (F, C, P) int, the person (0..G-1) of each skeleton, -1 for none.
      num_people: G, the size of the person axis.
    Returns:
      members (F, G, C): each person's skeleton index in each camera, -1 for none (the inverse
      of `PipelineResult.identity`).
    """
    F, C, _ = np.shape(identity)
    members = np.full((F, num_people, C), -1, np.int32)
    f, c, p = np.nonzero(np.asarray(identity) >= 0)
    members[f, np.asarray(identity)[f, c, p], c] = p
    return members


# ------------------------------------------------------------------ the registered methods
# `stages.LIFTING`'s contract: grouped people on the proposal cameras in, (Poses3D, confidence)
# out; an estimator method picks its inference cameras from them.


def _triangulation(method: str):
    def lift(rig, xy, score, config: LiftingConfig, *, estimator=None, min_views=2, layout=None):
        del estimator, layout  # a triangulation uses neither
        return triangulate_grouped(
            rig,
            xy,
            score,
            method,
            min_views,
            max_spread_m=config.max_spread_m,
            outlier_px=config.outlier_px,
            view_outlier_px=config.view_outlier_px,
        )

    lift.__name__ = lift.__qualname__ = f"lift_{method}"
    lift.__doc__ = f"Registered lifting method {method!r}: `triangulate_grouped`."
    return lift


lift_dlt = _triangulation("dlt")
lift_centroid = _triangulation("centroid")
lift_robust = _triangulation("robust")


def _inference_views(rig: Rig, xy, score, estimator: Estimator):
    """Grouped people's views in the estimator's inference cameras (a subset of ``rig``'s)."""
    if tuple(rig.names) == tuple(estimator.rig_infer.names):
        return xy, score
    idx = _camera_columns(rig.names, estimator.rig_infer.names, "the estimator's inference")
    return xy[:, :, idx], score[:, :, idx]


def lift_mlp(rig, xy, score, config: LiftingConfig, *, estimator, min_views=2, layout=None):
    """Registered lifting method "mlp": the estimator's output (`estimate_grouped`)."""
    del config, layout
    xy, score = _inference_views(rig, xy, score, estimator)
    return estimate_grouped(estimator, xy, score, min_views)


def lift_blend(rig, xy, score, config: LiftingConfig, *, estimator, min_views=2, layout="coco18"):
    """Registered lifting method "blend": robust triangulation where it reconstructs a keypoint,
    the estimator elsewhere (`estimate_grouped` with method "blend")."""
    xy, score = _inference_views(rig, xy, score, estimator)
    return estimate_grouped(
        estimator,
        xy,
        score,
        min_views,
        "blend",
        outlier_px=config.outlier_px,
        view_outlier_px=config.view_outlier_px,
        layout=layout,
        max_spread_m=config.max_spread_m,
    )


def lift_confident(
    rig, xy, score, config: LiftingConfig, *, estimator=None, min_views=2, layout="coco18"
):
    """Registered lifting method "confident": triangulation weighted by a learned p(inlier) of
    each view (`view_confidence.triangulate_confident`, the model of ``config.confidence``), views
    below the model's threshold dropped, then robust triangulation; a person larger than a body
    is not one (as method "robust")."""
    del estimator
    if config.confidence is None:
        raise ValueError('method "confident" needs a view-confidence model (--confidence)')
    model = cached_view_confidence(str(config.confidence))
    F, G, C, K = score.shape
    exists = _present(score, min_views)
    out = np.zeros((F, G, K, 3), np.float32)
    kv = np.zeros((F, G, K), bool)
    if exists.any():

        def block(xy_b, score_b):
            p = inlier_probability(model, rig, xy_b, score_b, layout or "coco18")
            px, w = np.moveaxis(xy_b, 1, 0), np.moveaxis(score_b, 1, 0)
            return triangulate_confident(
                rig,
                px,
                w,
                np.moveaxis(p, 1, 0),
                threshold=model.config.threshold,
                then=model.config.then,
                outlier_px=config.outlier_px,
                view_outlier_px=config.view_outlier_px,
            )

        out[exists], kv[exists] = _by_blocks(block, xy[exists], score[exists])
    exists = exists & kv.any(axis=-1)
    exists[exists] = _body_sized(out[exists], kv[exists], config.max_spread_m)
    return poses_from_people(out, kv, exists), _confidence(score)
