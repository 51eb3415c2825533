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
  * ``body25b``: OpenPose's experimental BODY_25B: COCO's 17, upper neck, head top, feet.
  * ``body135``: OpenPose's experimental BODY_135: BODY_25B, 2 x 20 finger points, a 70-point face.
  * ``halpe68``, ``halpe136``: HALPE_26 with both hands (68), and with the face and hands (136).
  * ``coco133``: COCO-WholeBody: COCO's 17, the feet, a 68-point face, 2 x 21 hand points.
  * ``mpii``: MPII Human Pose's 16 joints (no eyes, ears or nose: missing after conversion).
  * ``blazepose``: MediaPipe Pose's 33 landmarks.

Keypoints are matched between layouts by name; ``neck`` and ``mid_hip`` are the mean of the
shoulders or hips where a layout lacks them (`conversion_matrix`). Names: ``head`` is the top of the
head, ``upper_neck`` the neck below the chin (BODY_25B, MPII; not coco18's ``neck``), ``face_0`` ...
``face_67`` the 68-point face of the iBUG 300-W scheme, ``{l,r}_hand_root`` a hand's own wrist point
and ``{l,r}_{thumb,index,middle,ring,pinky}_{1..4}`` its finger joints from the palm out.

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
        if k in _FACE68_MIRROR:
            return _FACE68_MIRROR[k]
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

# The 68-point face of the iBUG 300-W scheme (COCO-WholeBody, HALPE_136 and OpenPose's face hold
# it in this order), 0-based: 0-16 jaw line from the person's right to left, 17-21 right brow,
# 22-26 left brow, 27-30 nose bridge, 31-35 nostrils, 36-41 right eye, 42-47 left eye, 48-59 outer
# lips, 60-67 inner lips. The points have no side prefix, so their mirror pairs are listed.
_FACE68 = tuple(f"face_{i}" for i in range(68))
_FACE68_PAIRS = (
    *((i, 16 - i) for i in range(8)),  # jaw
    *((17 + i, 26 - i) for i in range(5)),  # brows
    (31, 35),
    (32, 34),  # nostrils
    (36, 45),
    (37, 44),
    (38, 43),
    (39, 42),
    (40, 47),
    (41, 46),  # eyes
    (48, 54),
    (49, 53),
    (50, 52),
    (55, 59),
    (56, 58),  # outer lips
    (60, 64),
    (61, 63),
    (65, 67),  # inner lips
)
_FACE68_MIRROR = {f"face_{a}": f"face_{b}" for p in _FACE68_PAIRS for a, b in (p, p[::-1])}


def _chain(names: tuple[str, ...], *, closed: bool = False) -> tuple[tuple[str, str], ...]:
    pairs = tuple(zip(names[:-1], names[1:], strict=True))
    return pairs + ((names[-1], names[0]),) if closed else pairs


def _face(indices: range, *, closed: bool = False) -> tuple[tuple[str, str], ...]:
    return _chain(tuple(_FACE68[i] for i in indices), closed=closed)


# The face's contours, joined to the body at the nose tip (face_30 is the nose's tip too).
_FACE68_BONES = (
    _face(range(0, 17))
    + _face(range(17, 22))
    + _face(range(22, 27))
    + _face(range(27, 31))
    + _face(range(31, 36))
    + (("face_30", "face_33"), ("nose", "face_30"))
    + _face(range(36, 42), closed=True)
    + _face(range(42, 48), closed=True)
    + _face(range(48, 60), closed=True)
    + _face(range(60, 68), closed=True)
)
# A hand of 21 points (COCO-WholeBody, HALPE, OpenPose's hand model): 0 the wrist as the hand
# model sees it, then 4 per finger from the palm out (thumb: CMC, MCP, IP, tip; the others: MCP,
# PIP, DIP, tip). OpenPose's BODY_135 has the 20 finger points alone (its body's wrist is the root).
_FINGERS = ("thumb", "index", "middle", "ring", "pinky")


def _hand(side: str, *, root: bool = True) -> tuple[str, ...]:
    fingers = tuple(f"{side}_{f}_{j}" for f in _FINGERS for j in range(1, 5))
    return ((f"{side}_hand_root",) if root else ()) + fingers


def _hand_bones(side: str, *, root: bool = True) -> tuple[tuple[str, str], ...]:
    base = f"{side}_hand_root" if root else f"{side}_wrist"
    bones = ((f"{side}_wrist", base),) if root else ()
    for f in _FINGERS:
        bones += _chain((base,) + tuple(f"{side}_{f}_{j}" for j in range(1, 5)))
    return bones


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
# The feet of the layouts that have them, and the trunk (neck, mid hip) of BODY_25 and HALPE_26.
_FEET_BONES = (
    ("l_ankle", "l_heel"),
    ("l_ankle", "l_big_toe"),
    ("l_big_toe", "l_small_toe"),
    ("r_ankle", "r_heel"),
    ("r_ankle", "r_big_toe"),
    ("r_big_toe", "r_small_toe"),
)
_TRUNK_AND_FEET_BONES = (
    ("neck", "nose"),
    ("neck", "l_shoulder"),
    ("neck", "r_shoulder"),
    ("neck", "mid_hip"),
    ("mid_hip", "l_hip"),
    ("mid_hip", "r_hip"),
) + _FEET_BONES
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

# The six foot points of BODY_25B, BODY_135 and COCO-WholeBody, in their order.
_FEET = ("l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel")
# COCO 17's bones (coco17's, named): limbs, torso, ears to shoulders.
_COCO17_BONES = tuple((_COCO17[a], _COCO17[b]) for a, b in COCO17.bones)
# OpenPose's experimental BODY_25B (openpose_train's experimental_models README): COCO's 17, then
# the upper neck (below the chin: not coco18's neck, which is built from the shoulders) and the
# head top, then the feet. Its 25 points are BODY_25's count: files need --source-layout body25b.
_BODY25B = _COCO17 + ("upper_neck", "head") + _FEET
_BODY25B_BONES = (
    # The head hangs from the upper neck, not from the shoulders.
    tuple(b for b in _COCO17_BONES if b not in (("l_ear", "l_shoulder"), ("r_ear", "r_shoulder")))
    + (
        ("l_shoulder", "upper_neck"),
        ("r_shoulder", "upper_neck"),
        ("upper_neck", "head"),
        ("upper_neck", "nose"),
    )
    + _FEET_BONES
)
BODY25B = _layout("body25b", _BODY25B, _BODY25B_BONES)
# OpenPose's experimental BODY_135: BODY_25B, the left and right hands' 20 finger points, and the
# face's 68 points plus the right and left pupils.
BODY135 = _layout(
    "body135",
    _BODY25B + _hand("l", root=False) + _hand("r", root=False) + _FACE68 + ("r_pupil", "l_pupil"),
    _BODY25B_BONES
    + _hand_bones("l", root=False)
    + _hand_bones("r", root=False)
    + _FACE68_BONES
    + (("face_37", "r_pupil"), ("face_44", "l_pupil")),
)
# HALPE_68 (AlphaPose's Halpe-FullBody without the face) and HALPE_136 (Halpe-FullBody: the HALPE
# dataset's README): HALPE_26's body, then the face (136 only), the left hand, the right hand.
HALPE68 = _layout(
    "halpe68",
    HALPE26.keypoints + _hand("l") + _hand("r"),
    tuple((HALPE26.keypoints[a], HALPE26.keypoints[b]) for a, b in HALPE26.bones)
    + _hand_bones("l")
    + _hand_bones("r"),
)
HALPE136 = _layout(
    "halpe136",
    HALPE26.keypoints + _FACE68 + _hand("l") + _hand("r"),
    tuple((HALPE26.keypoints[a], HALPE26.keypoints[b]) for a, b in HALPE26.bones)
    + _FACE68_BONES
    + _hand_bones("l")
    + _hand_bones("r"),
)
# COCO-WholeBody (COCO_133; RTMPose's whole-body models): COCO's 17, the feet, the face, the left
# hand, the right hand.
COCO133 = _layout(
    "coco133",
    _COCO17 + _FEET + _FACE68 + _hand("l") + _hand("r"),
    _COCO17_BONES + _FEET_BONES + _FACE68_BONES + _hand_bones("l") + _hand_bones("r"),
)
# MPII Human Pose's 16 joints (its joint ids; AlphaPose's MPII output): no face but the upper neck
# and the head top, so coco18's eyes, ears and nose are missing after conversion.
MPII = _layout(
    "mpii",
    (
        "r_ankle",
        "r_knee",
        "r_hip",
        "l_hip",
        "l_knee",
        "l_ankle",
        "pelvis",
        "thorax",
        "upper_neck",
        "head",
        "r_wrist",
        "r_elbow",
        "r_shoulder",
        "l_shoulder",
        "l_elbow",
        "l_wrist",
    ),
    _LIMBS[:8]
    + (
        ("pelvis", "l_hip"),
        ("pelvis", "r_hip"),
        ("pelvis", "thorax"),
        ("thorax", "l_shoulder"),
        ("thorax", "r_shoulder"),
        ("thorax", "upper_neck"),
        ("upper_neck", "head"),
    ),
)
# MediaPipe Pose (BlazePose)'s 33 landmarks. Its "foot index" is the tip of the foot (second toe),
# not the big toe, so it keeps its own name.
BLAZEPOSE = _layout(
    "blazepose",
    (
        "nose",
        "l_eye_inner",
        "l_eye",
        "l_eye_outer",
        "r_eye_inner",
        "r_eye",
        "r_eye_outer",
        "l_ear",
        "r_ear",
        "l_mouth",
        "r_mouth",
        "l_shoulder",
        "r_shoulder",
        "l_elbow",
        "r_elbow",
        "l_wrist",
        "r_wrist",
        "l_pinky",
        "r_pinky",
        "l_index",
        "r_index",
        "l_thumb",
        "r_thumb",
        "l_hip",
        "r_hip",
        "l_knee",
        "r_knee",
        "l_ankle",
        "r_ankle",
        "l_heel",
        "r_heel",
        "l_foot_index",
        "r_foot_index",
    ),
    _COCO17_BONES
    + tuple(
        bone
        for s in ("l", "r")
        for bone in (
            (f"{s}_eye_inner", f"{s}_eye"),
            (f"{s}_eye", f"{s}_eye_outer"),
            (f"{s}_wrist", f"{s}_pinky"),
            (f"{s}_wrist", f"{s}_index"),
            (f"{s}_pinky", f"{s}_index"),
            (f"{s}_wrist", f"{s}_thumb"),
            (f"{s}_ankle", f"{s}_heel"),
            (f"{s}_heel", f"{s}_foot_index"),
            (f"{s}_ankle", f"{s}_foot_index"),
        )
    )
    + (("l_mouth", "r_mouth"),),
)

LAYOUTS: dict[str, Layout] = {
    lay.name: lay
    for lay in (
        COCO18,
        COCO17,
        BODY25,
        OPENPOSE_COCO18,
        HALPE26,
        BODY25B,
        BODY135,
        HALPE68,
        HALPE136,
        COCO133,
        MPII,
        BLAZEPOSE,
    )
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


def leg_chains(layout: str | Layout) -> np.ndarray:
    """The layout's legs as parent-child bones, for placing a keypoint by its bone's length.

    Returns:
      (J, 4) int32 rows (parent, child, mirrored parent, mirrored child): each side's thigh (hip,
      knee) before its shank (knee, ankle), so a child is placed after its parent; (0, 4) for
      a layout without hips, knees and ankles on both sides.
    """
    lay = get_layout(layout)
    names = ("hip", "knee", "ankle")
    if not all(f"{s}_{n}" in lay.keypoints for s in "lr" for n in names):
        return np.zeros((0, 4), np.int32)
    i = lay.keypoints.index
    rows = [
        (i(f"{s}_{a}"), i(f"{s}_{b}"), i(f"{m}_{a}"), i(f"{m}_{b}"))
        for s, m in (("l", "r"), ("r", "l"))
        for a, b in zip(names[:-1], names[1:], strict=True)
    ]
    return np.asarray(rows, np.int32)


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


def zero_padded(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``a`` zero-padded at the end of each axis to ``shape`` (``a`` itself when it has that
    shape): `np.pad`'s result without its cost per call (tens of microseconds, a live frame pads
    its detections several times)."""
    if a.shape == tuple(shape):
        return a
    out = np.zeros(shape, a.dtype)
    out[tuple(slice(0, n) for n in a.shape)] = a
    return out


def skeleton_slots(num_skeletons: int) -> int:
    """The skeleton slots per camera a chunk is padded to: the next multiple of 4 (at least 4).

    Every stage reads a camera's skeletons up to its count, so empty slots change no result;
    they keep the compiled programs' shapes few (recordings of 3 to 10 skeletons a camera: 3
    shapes, not 8), where each new shape costs the jitted stages seconds of compilation."""
    return 4 * max(1, -(-num_skeletons // 4))
