"""Keypoint layouts and the array contracts for 2D detections and 3D poses.

Letter legend used across the package: F frames, C cameras, P people (padded), K keypoints,
G ground-truth people (padded).

Layouts:
  * ``coco18`` (default): COCO's 17 keypoints plus the neck as index 17, the original repository's.
  * ``coco17``: COCO's 17 keypoints.
  * ``body25``: OpenPose's BODY_25.
  * ``halpe26``: HALPE_26 (RTMPose / AlphaPose body, Pose2Sim's default): COCO's 17, then head,
    neck, mid_hip, big toes, small toes and heels (left before right).
  * ``openpose_coco18``: OpenPose's COCO model: the same 18 keypoints as ``coco18`` in OpenPose's
    order (0 nose, 1 neck, 2-4 right arm, 5-7 left arm, 8-10 right leg, 11-13 left leg, 14 r_eye,
    15 l_eye, 16 r_ear, 17 l_ear). OpenPose JSON files hold this order; `convert_keypoints` maps it
    to ``coco18`` by name.

The number of keypoints is always read from a layout (``layout.num_keypoints``), never assumed.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import numpy as np

from mvpose_jax.errors import InputError


class Detections(NamedTuple):
    """2D skeletons of F frames seen by C cameras, padded to P people per view.

    A keypoint with score 0 is missing (its xy is meaningless, conventionally 0). Rows
    ``p >= count[f, c]`` are padding and have score 0 everywhere.
    """

    xy: jax.Array  # (F, C, P, K, 2) pixels, distorted (as the detector saw them)
    score: jax.Array  # (F, C, P, K) detector confidence in [0, 1]; 0 = missing
    count: jax.Array  # (F, C) int32, number of valid skeletons in each view


class Poses3D(NamedTuple):
    """3D poses of F frames, padded to P people.

    ``keypoint_valid`` extends the design's (xyz, valid) pair: ground truth and triangulation can
    lack single keypoints, and metrics must know which ones.
    """

    xyz: jax.Array  # (F, P, K, 3) metres, world frame
    valid: jax.Array  # (F, P) bool, the person exists
    keypoint_valid: jax.Array  # (F, P, K) bool, the keypoint exists (False where not valid)


@dataclasses.dataclass(frozen=True)
class Layout:
    """A keypoint layout: names, bones and the left/right mirror permutation.

    Attributes:
      name: layout name (``"coco18"`` …).
      keypoints: keypoint names, in index order.
      bones: pairs of keypoint indices joined by a limb (for drawing and bone-length checks).
      flip: ``flip[k]`` is the index of the mirror keypoint of ``k`` (``k`` itself on the midline).
    """

    name: str
    keypoints: tuple[str, ...]
    bones: tuple[tuple[int, int], ...]
    flip: tuple[int, ...]

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoints)

    def index(self, name: str) -> int:
        """Index of a keypoint by name."""
        try:
            return self.keypoints.index(name)
        except ValueError:
            raise KeyError(f"layout {self.name!r} has no keypoint {name!r}") from None


def _layout(name: str, keypoints: tuple[str, ...], bones: tuple[tuple[str, str], ...]) -> Layout:
    index = {k: i for i, k in enumerate(keypoints)}

    def mirror(k: str) -> str:
        for a, b in (("l_", "r_"), ("r_", "l_")):
            if k.startswith(a):
                return b + k[len(a) :]
        return k

    flip = tuple(index[mirror(k)] for k in keypoints)
    return Layout(name, keypoints, tuple((index[a], index[b]) for a, b in bones), flip)


_COCO17 = (
    "nose",
    "l_eye",
    "r_eye",
    "l_ear",
    "r_ear",
    "l_shoulder",
    "r_shoulder",
    "l_elbow",
    "r_elbow",
    "l_wrist",
    "r_wrist",
    "l_hip",
    "r_hip",
    "l_knee",
    "r_knee",
    "l_ankle",
    "r_ankle",
)
_LIMBS = (
    ("l_shoulder", "l_elbow"),
    ("l_elbow", "l_wrist"),
    ("r_shoulder", "r_elbow"),
    ("r_elbow", "r_wrist"),
    ("l_hip", "l_knee"),
    ("l_knee", "l_ankle"),
    ("r_hip", "r_knee"),
    ("r_knee", "r_ankle"),
    ("nose", "l_eye"),
    ("nose", "r_eye"),
    ("l_eye", "l_ear"),
    ("r_eye", "r_ear"),
)
_BODY25 = (
    "nose",
    "neck",
    "r_shoulder",
    "r_elbow",
    "r_wrist",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
    "mid_hip",
    "r_hip",
    "r_knee",
    "r_ankle",
    "l_hip",
    "l_knee",
    "l_ankle",
    "r_eye",
    "l_eye",
    "r_ear",
    "l_ear",
    "l_big_toe",
    "l_small_toe",
    "l_heel",
    "r_big_toe",
    "r_small_toe",
    "r_heel",
)

COCO17 = _layout(
    "coco17",
    _COCO17,
    _LIMBS
    + (
        ("l_shoulder", "r_shoulder"),
        ("l_hip", "r_hip"),
        ("l_shoulder", "l_hip"),
        ("r_shoulder", "r_hip"),
        ("l_ear", "l_shoulder"),
        ("r_ear", "r_shoulder"),
    ),
)
_COCO18_BONES = _LIMBS + (
    ("neck", "nose"),
    ("neck", "l_shoulder"),
    ("neck", "r_shoulder"),
    ("neck", "l_hip"),
    ("neck", "r_hip"),
    ("l_hip", "r_hip"),
)
COCO18 = _layout("coco18", _COCO17 + ("neck",), _COCO18_BONES)
# OpenPose's COCO model: coco18's keypoints in another order (see the module docstring).
OPENPOSE_COCO18 = _layout(
    "openpose_coco18",
    (
        "nose",
        "neck",
        "r_shoulder",
        "r_elbow",
        "r_wrist",
        "l_shoulder",
        "l_elbow",
        "l_wrist",
        "r_hip",
        "r_knee",
        "r_ankle",
        "l_hip",
        "l_knee",
        "l_ankle",
        "r_eye",
        "l_eye",
        "r_ear",
        "l_ear",
    ),
    _COCO18_BONES,
)
# The trunk (neck, mid hip) and feet of the layouts that have them (BODY_25, HALPE_26).
_TRUNK_AND_FEET_BONES = (
    ("neck", "nose"),
    ("neck", "l_shoulder"),
    ("neck", "r_shoulder"),
    ("neck", "mid_hip"),
    ("mid_hip", "l_hip"),
    ("mid_hip", "r_hip"),
    ("l_ankle", "l_heel"),
    ("l_ankle", "l_big_toe"),
    ("l_big_toe", "l_small_toe"),
    ("r_ankle", "r_heel"),
    ("r_ankle", "r_big_toe"),
    ("r_big_toe", "r_small_toe"),
)
BODY25 = _layout("body25", _BODY25, _LIMBS + _TRUNK_AND_FEET_BONES)

# HALPE_26 (Halpe-FullBody's body keypoints; Pose2Sim's default with RTMPose/AlphaPose): COCO's 17,
# then head top, neck, mid hip and the six foot keypoints.
HALPE26 = _layout(
    "halpe26",
    _COCO17
    + (
        "head",
        "neck",
        "mid_hip",
        "l_big_toe",
        "r_big_toe",
        "l_small_toe",
        "r_small_toe",
        "l_heel",
        "r_heel",
    ),
    _LIMBS + (("neck", "head"),) + _TRUNK_AND_FEET_BONES,
)

LAYOUTS: dict[str, Layout] = {
    lay.name: lay for lay in (COCO18, COCO17, BODY25, OPENPOSE_COCO18, HALPE26)
}
DEFAULT_LAYOUT = "coco18"

# Keypoints of one layout that other layouts lack, as the mean of keypoints they share.
_DERIVED: dict[str, tuple[str, ...]] = {
    "neck": ("l_shoulder", "r_shoulder"),
    "mid_hip": ("l_hip", "r_hip"),
}

# The paper evaluates on every keypoint but the eyes and ears.
_NOT_EVALUATED = frozenset({"l_eye", "r_eye", "l_ear", "r_ear"})


def get_layout(layout: str | Layout) -> Layout:
    """Returns a layout by name (or passes a Layout through)."""
    if isinstance(layout, Layout):
        return layout
    try:
        return LAYOUTS[layout]
    except KeyError:
        raise InputError(
            f"unknown keypoint layout {layout!r}; known: {sorted(LAYOUTS)}", field="layout"
        ) from None


def evaluation_keypoints(layout: str | Layout) -> np.ndarray:
    """Indices of the keypoints the paper's 3D metrics use (all but eyes and ears): (K_eval,)."""
    lay = get_layout(layout)
    names = [k for k in lay.keypoints if k not in _NOT_EVALUATED and k in COCO18.keypoints]
    return np.array([lay.index(k) for k in names], dtype=np.int32)


def conversion_matrix(src: str | Layout, dst: str | Layout) -> np.ndarray:
    """Weights that build each ``dst`` keypoint as a mean of ``src`` keypoints.

    Returns:
      (K_dst, K_src) float32; row k has weights summing to 1 over its sources, or is all zero
      when ``src`` cannot provide keypoint k (it is then missing after conversion).
    """
    src, dst = get_layout(src), get_layout(dst)
    weights = np.zeros((dst.num_keypoints, src.num_keypoints), np.float32)
    for k, name in enumerate(dst.keypoints):
        if name in src.keypoints:
            sources = (name,)
        elif name in _DERIVED and all(s in src.keypoints for s in _DERIVED[name]):
            sources = _DERIVED[name]
        else:
            continue
        for s in sources:
            weights[k, src.index(s)] = 1.0 / len(sources)
    return weights


def convert_keypoints(
    values: np.ndarray, present: np.ndarray, src: str | Layout, dst: str | Layout
) -> tuple[np.ndarray, np.ndarray]:
    """Converts keypoint values between layouts.

    A derived keypoint (e.g. the neck from the shoulders) exists only where all its sources exist;
    a keypoint ``src`` cannot provide is missing.

    Args:
      values: (..., K_src, D) coordinates (pixels or metres).
      present: (..., K_src) bool, or float scores (> 0 means present).
    Returns:
      values (..., K_dst, D) and, matching the type of ``present``, (..., K_dst): bools, or scores
      where a derived keypoint gets the minimum of its sources' scores.
    """
    w = conversion_matrix(src, dst)
    values = np.asarray(values)
    present = np.asarray(present)
    is_bool = present.dtype == bool
    score = present.astype(np.float32)
    has = score > 0
    uses = w > 0  # (K_dst, K_src)
    # A destination keypoint exists when every one of its sources exists.
    all_there = np.all(has[..., None, :] | ~uses, axis=-1) & uses.any(axis=-1)
    out_values = np.einsum("ds,...sj->...dj", w, np.where(has[..., None], values, 0.0))
    out_values = np.where(all_there[..., None], out_values, 0.0).astype(values.dtype)
    if is_bool:
        return out_values, all_there
    big = np.where(uses, score[..., None, :], np.inf).min(axis=-1)
    out_score = np.where(all_there, big, 0.0).astype(present.dtype)
    return out_values, out_score


def convert_detections(det: Detections, src: str | Layout, dst: str | Layout) -> Detections:
    """Converts ``Detections`` between layouts (host-side numpy)."""
    xy, score = convert_keypoints(np.asarray(det.xy), np.asarray(det.score), src, dst)
    return Detections(xy, score, np.asarray(det.count))


def flip_keypoints(values: np.ndarray, layout: str | Layout, axis: int = -2) -> np.ndarray:
    """Swaps left and right keypoints along ``axis`` (a mirror relabelling)."""
    return np.take(values, np.array(get_layout(layout).flip), axis=axis)


def empty_detections(
    num_frames: int, num_cameras: int, max_people: int, num_keypoints: int
) -> Detections:
    """All-padding ``Detections`` (numpy) of the given shape."""
    return Detections(
        np.zeros((num_frames, num_cameras, max_people, num_keypoints, 2), np.float32),
        np.zeros((num_frames, num_cameras, max_people, num_keypoints), np.float32),
        np.zeros((num_frames, num_cameras), np.int32),
    )
