"""What the benchmark harness measures on: rigs, synthetic recordings, untrained models, and the
paper's OpenCV triangulation written out as the comparison row.

Models get random weights: timings do not depend on the values of the weights (the one place where
they matter, how many pairs the proposal step accepts, is measured separately with oracle scores).
They are built exactly as `trained.load_estimator` / `trained.load_matcher` build them, so the timed
calls see the same pytrees as after loading a checkpoint.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import cv2
import jax
import numpy as np
from flax import nnx

from mvpose_jax.cameras import Rig, make_rig, rig_centre_and_radius
from mvpose_jax.data import Recording, select_cameras
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.models import GATConfig, MatchingGAT, MLPConfig, PoseMLP
from mvpose_jax.synthetic import generate_recording
from mvpose_jax.trained import Estimator, EstimatorConfig, Matcher, MatcherConfig

# Camera subsets of the five Panoptic cameras for 2 and 3 views (the paper's Table 3 uses subsets
# of these too); 8 views come from a ring rig with Panoptic's lenses.
PANOPTIC = "panoptic5"


def ring_rig(num_cameras: int = 8) -> Rig:
    """``num_cameras`` cameras on a 3.5 m ring around a capture area, Panoptic lenses and images.

    World frame as Panoptic's: y points down (up = -y), the floor at y = 0. Heights alternate
    between 1.7 and 2.5 m; every camera looks at the point 1 m above the centre of the floor.
    """
    base = load_rig(PANOPTIC)
    K0, dist0 = np.asarray(base.K)[0], np.asarray(base.dist)[0]
    K, dist, R, t = [], [], [], []
    target = np.array([0.0, -1.0, 0.0])
    for c in range(num_cameras):
        angle = 2 * np.pi * c / num_cameras
        centre = np.array([3.5 * np.cos(angle), -(1.7 if c % 2 else 2.5), 3.5 * np.sin(angle)])
        forward = (target - centre) / np.linalg.norm(target - centre)
        right = np.cross(forward, [0.0, -1.0, 0.0])  # level cameras: x axis perpendicular to up
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rot = np.stack([right, down, forward])  # cam_from_world rows
        K.append(K0)
        dist.append(dist0)
        R.append(rot)
        t.append(-rot @ centre)
    size = [np.asarray(base.size)[0]] * num_cameras
    return make_rig(
        K, dist, R, t, size, [f"ring{c}" for c in range(num_cameras)], up=(0.0, -1.0, 0.0)
    )


def scene_rig(num_views: int) -> tuple[Rig, tuple[str, ...] | None]:
    """The rig to generate on for ``num_views`` views, and the cameras to keep (None: all).

    2, 3 and 5 views are subsets of panoptic5 (generated once on all five, then selected); more
    than five come from `ring_rig`.
    """
    if num_views <= 5:
        rig = load_rig(PANOPTIC)
        return rig, tuple(rig.names[:num_views])
    return ring_rig(num_views), None


def recording(
    num_views: int, num_people: int, num_frames: int, seed: int = 0
) -> tuple[Rig, Recording]:
    """A synthetic multi-person recording seen by ``num_views`` cameras, and their rig."""
    rig, keep = scene_rig(num_views)
    rec = generate_recording(rig, num_people=num_people, num_frames=num_frames, seed=seed)
    if keep is not None and len(keep) < rig.num_cameras:
        rec = select_cameras(rec, keep)
        rig = rig.select(list(keep))
    return rig, rec


def estimator_for(rig: Rig, num_keypoints: int, mlp: MLPConfig) -> Estimator:
    """An untrained `Estimator` for ``rig``'s cameras, built as `trained.load_estimator` builds it."""
    config = EstimatorConfig(train_cameras=rig.names, infer_cameras=rig.names, mlp=mlp)
    graphdef, rest, params = _split(
        lambda: PoseMLP(rig.num_cameras, num_keypoints, config.mlp, rngs=nnx.Rngs(0))
    )
    # The normalised frame as trained estimators carry it (computed once, not on every call).
    return Estimator(graphdef, rest, params, rig, config, rig_centre_and_radius(rig))


def matcher_for(rig: Rig, num_keypoints: int, gat: GATConfig) -> Matcher:
    """An untrained `Matcher` for ``rig``'s cameras, built as `trained.load_matcher` builds it."""
    config = MatcherConfig(cameras=rig.names, gat=gat)
    graphdef, rest, params = _split(
        lambda: MatchingGAT(rig.num_cameras, num_keypoints, config.gat, rngs=nnx.Rngs(0))
    )
    return Matcher(graphdef, rest, params, rig, config)


def _split(make):
    """(graphdef, rest, params) of the model ``make()`` builds, split as `train.init_train_state`
    splits it (``nnx.split(model, nnx.Param, ...)``; the optimizer state, which inference never
    reads, is left out). The initialisation runs as one jit call: eagerly, every parameter shape
    compiles its own random-number program (seconds for the paper MLP). Same values either way."""
    graphdef, _, _ = nnx.split(nnx.eval_shape(make), nnx.Param, ...)
    params, rest = jax.jit(lambda: nnx.split(make(), nnx.Param, ...)[1:])()
    return graphdef, rest, params


MODEL_SIZES = {
    "paper": (MLPConfig(), GATConfig()),
    "quick": (MLPConfig.quick(), GATConfig.quick()),
}


# --------------------------------------------------------------------------- OpenCV reference


class OpenCVCameras(NamedTuple):
    """Per-camera numpy calibration for the OpenCV reference (float64, as OpenCV works)."""

    K: np.ndarray  # (C, 3, 3)
    dist: np.ndarray  # (C, 5)
    Rt: np.ndarray  # (C, 3, 4) cam_from_world [R | t]


def opencv_cameras(rig: Rig) -> OpenCVCameras:
    R = np.asarray(rig.R, np.float64)
    t = np.asarray(rig.t, np.float64)
    return OpenCVCameras(
        np.asarray(rig.K, np.float64),
        np.asarray(rig.dist, np.float64),
        np.concatenate([R, t[..., None]], axis=-1),
    )


def opencv_pairwise_centroid(
    cams: OpenCVCameras, xy: np.ndarray, score: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's triangulation, the way its original code runs it: OpenCV, person by person.

    For each person: undistort every view's keypoints (``cv2.undistortPoints`` to normalised
    coordinates), triangulate every camera pair on the keypoints both views see
    (``cv2.triangulatePoints`` with the pair's ``[R | t]``), dehomogenise, and average each
    keypoint's pair points.

    Args:
      cams: `opencv_cameras` of the C views.
      xy: (N, C, K, 2) distorted pixels; score: (N, C, K), 0 = missing.
    Returns:
      xyz (N, K, 3) metres (0 where fewer than two views see the keypoint) and valid (N, K).
    """
    N, C, K = score.shape
    out = np.zeros((N, K, 3))
    count = np.zeros((N, K))
    pairs = list(itertools.combinations(range(C), 2))
    for n in range(N):
        seen = score[n] > 0  # (C, K)
        views = [c for c in range(C) if seen[c].any()]
        und = {
            c: cv2.undistortPoints(
                xy[n, c].reshape(-1, 1, 2).astype(np.float64), cams.K[c], cams.dist[c]
            ).reshape(-1, 2)
            for c in views
        }
        for i, j in pairs:
            if i not in und or j not in und:
                continue
            both = seen[i] & seen[j]
            if not both.any():
                continue
            hom = cv2.triangulatePoints(
                cams.Rt[i], cams.Rt[j], und[i][both].T, und[j][both].T
            )  # (4, k)
            out[n, both] += (hom[:3] / hom[3]).T
            count[n, both] += 1
    valid = count > 0
    return np.where(valid[..., None], out / np.maximum(count, 1)[..., None], 0.0), valid
