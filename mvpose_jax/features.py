"""Per-keypoint input features of both networks (DESIGN.md §1.2, §1.3), batched and jit-able.

For camera c and keypoint k, the 10 numbers are: visible flag; x, y normalised to [-1, 1] by the
image size; score; the camera centre in the world (3); the unit direction, in the world, of the ray
through the UNDISTORTED pixel (3). A missing keypoint is all zeros. World quantities are expressed
in the rig's normalised frame, ``(x - centre) / radius`` (`cameras.rig_centre_and_radius`), so any
rig gives inputs of order one without constants.

The estimator adds 4 numbers, the same in every camera slot: a flag "initial 3D available" and
the initial 3D estimate, the centroid of the keypoint's two-view triangulations over the camera
pairs that both see it. Because every pair is triangulated once (`estimator_inputs`), the centroid
of any subset of views (view-subset augmentation) is a cheap masked mean (`assemble_features`),
recomputed from the views actually kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mvpose_jax import compiled
from mvpose_jax.cameras import (
    Rig,
    camera_centres,
    normalise_pixels,
    pixel_rays,
    rig_centre_and_radius,
)
from mvpose_jax.errors import InputError
from mvpose_jax.triangulate import camera_pairs, centroid_of_pairs, triangulate_pairs

if TYPE_CHECKING:
    from mvpose_jax.data.recording import Recording

NUM_KEYPOINT_FEATURES = 10
NUM_ESTIMATOR_FEATURES = 14


@compiled.jit
def keypoint_features(rig: Rig, xy: jax.Array, score: jax.Array, normalisation=None) -> jax.Array:
    """The 10 per-(camera, keypoint) numbers.

    Args:
      rig: the C cameras the detections come from.
      xy: (C, ..., K, 2) distorted pixels.
      score: (C, ..., K) detection scores; 0 = missing.
      normalisation: (centre (3,), radius ()) of the normalised space; default the rig's own
        (`cameras.rig_centre_and_radius`).
    Returns:
      (C, ..., K, 10) features, all zeros where the keypoint is missing.
    """
    centre, radius = rig_centre_and_radius(rig) if normalisation is None else normalisation
    seen = score > 0
    # Missing keypoints may carry junk coordinates: replace before any geometry touches them.
    xy = jnp.where(seen[..., None], xy, 0.5 * rig.size.reshape((-1,) + (1,) * (xy.ndim - 2) + (2,)))
    cam = (camera_centres(rig) - centre[None]) / radius  # (C, 3)
    cam = jnp.broadcast_to(cam.reshape((-1,) + (1,) * (xy.ndim - 2) + (3,)), xy.shape[:-1] + (3,))
    feats = jnp.concatenate(
        [
            jnp.ones_like(score)[..., None],
            normalise_pixels(rig, xy),
            score[..., None],
            cam,
            pixel_rays(rig, xy),
        ],
        axis=-1,
    )
    return jnp.where(seen[..., None], feats, 0.0)


def rig_agnostic_frame(rig: Rig) -> tuple[jax.Array, jax.Array]:
    """(centre (3,), unit ()) of a rig-agnostic model's inputs (`models.ViewPooledMLP`): the mean
    camera centre, in metres (unit 1), so that a body has the same size on every rig."""
    return jnp.mean(camera_centres(rig), axis=0), jnp.asarray(1.0, jnp.float32)


class EstimatorInputs(NamedTuple):
    """What the 3D estimator's features are assembled from, for N people seen by C cameras.

    Q = C (C - 1) / 2 camera pairs, in `triangulate.camera_pairs` order.
    """

    keypoint: jax.Array  # (N, C, K, 10) per-view features
    pair_xyz: jax.Array  # (N, K, Q, 3) two-view triangulations, rig-normalised frame
    pair_ok: jax.Array  # (N, K, Q) bool, the pair saw the keypoint and triangulated it


@compiled.jit
def estimator_inputs(
    rig: Rig, xy: jax.Array, score: jax.Array, normalisation=None
) -> EstimatorInputs:
    """Per-person inputs of the 3D estimator, before view selection.

    Args:
      rig: the C inference cameras (C_i).
      xy: (N, C, K, 2) each person's detections in each camera (pixels).
      score: (N, C, K) scores; 0 = missing (a whole view missing is all zeros).
      normalisation: (centre, radius) of the normalised space. An estimator uses its TRAINING rig's
        (the space people were recorded in): a compact inference rig (one camera, a stereo
        pair) spans almost nothing itself. Default: ``rig``'s own.
    Returns:
      `EstimatorInputs`.
    """
    centre, radius = rig_centre_and_radius(rig) if normalisation is None else normalisation
    keypoint = jnp.moveaxis(
        keypoint_features(rig, jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0), (centre, radius)),
        0,
        1,
    )
    pair_xyz, pair_ok = triangulate_pairs(rig, jnp.moveaxis(xy, 1, 0), jnp.moveaxis(score, 1, 0))
    pair_xyz = jnp.where(pair_ok[..., None], (pair_xyz - centre.reshape(1, 1, 1, 3)) / radius, 0.0)
    return EstimatorInputs(keypoint, pair_xyz, pair_ok)


def assemble_features(
    inputs: EstimatorInputs,
    view_mask: jax.Array,
    initial: tuple[jax.Array, jax.Array] | None = None,
) -> jax.Array:
    """The 14 numbers per (camera, keypoint), using only the views in ``view_mask``.

    Args:
      inputs: `EstimatorInputs` of N people.
      view_mask: (N, C) bool, the views given to the network (others become all zeros and take
        no part in the initial 3D estimate).
      initial: optional (xyz (N, K, 3) rig-normalised, available (N, K) bool) initial 3D
        estimate replacing the pairwise centroid (e.g. robust triangulation at inference; a
        network trained on centroids reads it as one).
    Returns:
      (N, C, K, 14) features.
    """
    N, C, K, _ = inputs.keypoint.shape
    keypoint = jnp.where(view_mask[:, :, None, None], inputs.keypoint, 0.0)
    pairs = camera_pairs(C)
    if initial is not None:
        init = jnp.where(initial[1][..., None], initial[0], 0.0).astype(keypoint.dtype)
        has_init = initial[1].astype(keypoint.dtype)
    elif len(pairs):
        pair_kept = view_mask[:, pairs[:, 0]] & view_mask[:, pairs[:, 1]]  # (N, Q)
        init, has_init = centroid_of_pairs(inputs.pair_xyz, inputs.pair_ok & pair_kept[:, None, :])
        has_init = has_init.astype(keypoint.dtype)  # init: (N, K, 3)
    else:
        init = jnp.zeros((N, K, 3), keypoint.dtype)
        has_init = jnp.zeros((N, K), keypoint.dtype)
    extra = jnp.concatenate([has_init[..., None], init], axis=-1)  # (N, K, 4)
    # The same in every slot of a present view; a slot with no view is all zeros.
    extra = jnp.where(view_mask[:, :, None, None], extra[:, None], 0.0)  # (N, C, K, 4)
    return jnp.concatenate([keypoint, extra], axis=-1)


# --------------------------------------------------------------------------- grouping people


def main_skeletons(xy: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per view, the skeleton with the most keypoints: the person of a single-person frame.

    DESIGN.md §1.2: in a one-person recording every other skeleton in a view is a false detection.

    Args:
      xy: (F, C, P, K, 2); score: (F, C, P, K) (padding rows are all zero).
    Returns:
      xy (F, C, K, 2) and score (F, C, K); a view without skeletons has score 0.
    """
    counts = (score > 0).sum(axis=-1)  # (F, C, P)
    best = counts.argmax(axis=-1)  # (F, C); ties: the first, as the detector listed them
    take = best[..., None, None]
    main_score = np.take_along_axis(score, take, axis=2)[:, :, 0]
    main_xy = np.take_along_axis(xy, take[..., None], axis=2)[:, :, 0]
    return main_xy, main_score


def single_person_samples(
    recordings: Sequence[Recording], cameras: Sequence[str] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The estimator's training people: every frame's main skeletons (`main_skeletons`) of
    single-person recordings, concatenated.

    Args:
      recordings: single-person recordings.
      cameras: the camera names to take, in this order (default: the first recording's).
    Returns:
      xy (N, C, K, 2) and score (N, C, K), N the frames of all recordings.
    Raises:
      InputError naming the recording and camera when one lacks a camera.
    """
    if not recordings:
        raise InputError("no recordings to take training people from", field="recordings")
    cameras = list(recordings[0].cameras if cameras is None else cameras)
    xy, score = [], []
    for r, rec in enumerate(recordings):
        missing = [c for c in cameras if c not in rec.cameras]
        if missing:
            raise InputError(
                f"recording {r} lacks cameras {missing}", camera=missing[0], field="cameras"
            )
        idx = [list(rec.cameras).index(c) for c in cameras]
        m_xy, m_score = main_skeletons(
            np.asarray(rec.detections.xy)[:, idx], np.asarray(rec.detections.score)[:, idx]
        )
        xy.append(m_xy)
        score.append(m_score)
    return np.concatenate(xy), np.concatenate(score)


def people_from_identity(
    xy: np.ndarray, score: np.ndarray, identity: np.ndarray, num_people: int
) -> tuple[np.ndarray, np.ndarray]:
    """Groups detections by their person (true proposals, or any per-detection assignment).

    Args:
      xy: (F, C, P, K, 2); score: (F, C, P, K).
      identity: (F, C, P) int, the person of each detection, -1 for none.
      num_people: G, the size of the person axis.
    Returns:
      xy (F, G, C, K, 2) and score (F, G, C, K): each person's skeleton in each view (score 0
      where the view has none). Two detections of one person in one view would be ambiguous:
      the one with more keypoints wins.
    """
    F, C, P, K = score.shape
    out_xy = np.zeros((F, num_people, C, K, 2), np.float32)
    out_score = np.zeros((F, num_people, C, K), np.float32)
    f, c, p = np.nonzero(identity >= 0)
    g = identity[f, c, p]
    if np.any(g >= num_people):
        raise ValueError(f"identity {g.max()} out of range for {num_people} people")
    # Write detections in increasing keypoint count: with duplicates the fullest lands last.
    order = np.argsort((score[f, c, p] > 0).sum(axis=-1), kind="stable")
    f, c, p, g = f[order], c[order], p[order], g[order]
    out_xy[f, g, c] = xy[f, c, p]
    out_score[f, g, c] = score[f, c, p]
    return out_xy, out_score
