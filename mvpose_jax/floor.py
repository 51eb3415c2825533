"""The floor from the people: its height measured from a recording's own detections.

The simulator (`synthetic.scene.estimate_floor_height`) can only guess the floor from where the
cameras hang, and on a real rig that guess can be half a metre off; models trained on recordings
generated with a wrong floor fail on the real one. When a user has detections of people walking
on their floor, the floor is measured instead: geometric proposals group the skeletons, robust
triangulation (`triangulate.triangulate_skeletons_robust`) reconstructs the feet of people seen
by three or more cameras, and the floor is a robust statistic of the lowest foot keypoint's
height per person and frame, less that keypoint's height above the floor.

Why the lowest foot: while standing, walking, crouching or sitting, one foot is on the floor in
nearly every frame (walking alternates which), so its height above the floor is the keypoint's
own height (the ankle's malleolus, the heel, the toe). The median over person-frames ignores the
rare frame with both feet up (a jump, a foot on furniture) and any leftover wrong triangulation.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mvpose_jax.cameras import Rig, project_points, up_vector
from mvpose_jax.errors import InputError
from mvpose_jax.inference import run_pipeline
from mvpose_jax.lifting import group_people
from mvpose_jax.skeletons import Detections, Layout, get_layout
from mvpose_jax.triangulate import triangulate_skeletons_robust

# Height above the floor of each foot keypoint of a standing adult, metres (the layout's left and
# right keypoints of these names are used where it has them). Ankle: the malleolus is 0.039 of the
# standing height above the sole (Drillis & Contini; 0.065-0.075 m for adults of 1.65-1.90 m; the
# simulator's ankle keypoint sits there), plus 1-2 cm of shoe sole, and detectors mark the ankle a
# little above the joint. Heel and big toe (BODY_25(B), HALPE, COCO-WholeBody): a few cm above the
# sole.
FOOT_KEYPOINT_HEIGHTS_M = {"ankle": 0.08, "heel": 0.03, "big_toe": 0.02}
# A foot keypoint counts when robust triangulation kept three or more views of it, each within
# this many pixels of the reprojected point: a confidently matched, consistent person.
MAX_FOOT_ERROR_PX = 20.0
MIN_FOOT_VIEWS = 3
# Fewer person-frames than this cannot tell a floor from a few wrong triangulations.
MIN_SAMPLES = 30


@dataclasses.dataclass(frozen=True)
class FloorEstimate:
    """The floor measured from detections.

    Attributes:
      height: floor height along ``up`` (the floor is ``{x : x . up = height}``), metres.
      spread: robust standard deviation (1.4826 x the median absolute deviation) of the
        per-person-frame floor heights, metres: how much single measurements scatter.
      num_samples: person-frames with a confident foot keypoint.
      num_frames: frames looked at.
      up: (3,) the unit up vector used (`cameras.up_vector`).
    """

    height: float
    spread: float
    num_samples: int
    num_frames: int
    up: tuple[float, float, float]


def estimate_floor_from_detections(
    rig: Rig,
    detections: Detections,
    *,
    layout: str | Layout = "coco18",
    max_frames: int = 2000,
    min_samples: int = MIN_SAMPLES,
    max_error_px: float = MAX_FOOT_ERROR_PX,
) -> FloorEstimate:
    """The floor height along the rig's up from the triangulated feet of its people.

    Args:
      rig: the C cameras of the detections, in their order.
      detections: xy (F, C, P, K, 2) pixels, score (F, C, P, K), count (F, C).
      layout: the detections' keypoint layout (its ankles, and heels and big toes if it has them).
      max_frames: at most this many frames, evenly spaced, are used (the floor does not move).
      min_samples: fewest person-frames with a confident foot keypoint.
      max_error_px: largest reprojection error of a kept view of a confident foot keypoint.
    Returns:
      A `FloorEstimate`.
    Raises:
      InputError when the layout has no ankles or too few confident feet are found.
    """
    lay = get_layout(layout)
    feet = [
        (lay.index(f"{side}_{name}"), offset)
        for name, offset in FOOT_KEYPOINT_HEIGHTS_M.items()
        for side in ("l", "r")
        if f"{side}_{name}" in lay.keypoints
    ]
    if not feet:
        raise InputError(
            f"layout {lay.name!r} has no ankle keypoints to find the floor from", field="layout"
        )
    up = np.asarray(up_vector(rig), np.float64)
    F = int(np.shape(detections.count)[0])
    frames = np.unique(np.linspace(0, max(F - 1, 0), min(F, max_frames)).round().astype(int))
    det = Detections(*(np.asarray(a)[frames] for a in detections))
    heights = np.zeros((0,))
    if F > 0 and rig.num_cameras >= MIN_FOOT_VIEWS:
        res = run_pipeline(rig, det, method="robust")
        xy, score = group_people(det.xy, det.score, res.members)  # (F, G, C, K, ...)
        person = res.poses.valid & ((score > 0).any(-1).sum(-1) >= MIN_FOOT_VIEWS)  # (F, G)
        heights = _lowest_foot_heights(rig, xy[person], score[person], feet, up, max_error_px)
    if len(heights) < min_samples:
        raise InputError(
            f"cannot measure the floor: only {len(heights)} person-frames (of {len(frames)} "
            f"frames) have a foot keypoint seen consistently by {MIN_FOOT_VIEWS}+ cameras (need "
            f"{min_samples}); give the floor height instead",
            field="floor",
        )
    height = float(np.median(heights))
    spread = float(1.4826 * np.median(np.abs(heights - height)))
    return FloorEstimate(height, spread, len(heights), len(frames), tuple(float(u) for u in up))


def _lowest_foot_heights(
    rig: Rig,
    xy: np.ndarray,
    score: np.ndarray,
    feet: list[tuple[int, float]],
    up: np.ndarray,
    max_error_px: float,
) -> np.ndarray:
    """Per person, the floor height its lowest confident foot keypoint says.

    xy: (N, C, K, 2), score: (N, C, K). Returns (M,) metres, one per person with a confident
    foot keypoint.
    """
    if len(xy) == 0:
        return np.zeros((0,))
    px, w = np.moveaxis(xy, 1, 0), np.moveaxis(score, 1, 0)  # (C, N, K, ...)
    xyz, valid, kept = (np.asarray(a) for a in triangulate_skeletons_robust(rig, px, w))
    idx = np.array([k for k, _ in feet])
    offset = np.array([o for _, o in feet])
    foot = xyz[:, idx]  # (N, J, 3)
    err = np.linalg.norm(np.asarray(project_points(rig, foot)) - px[:, :, idx], axis=-1)
    keep = kept[:, :, idx]  # (C, N, J)
    worst = np.where(keep, err, 0.0).max(0)  # (N, J) px, over the kept views
    ok = valid[:, idx] & (keep.sum(0) >= MIN_FOOT_VIEWS) & (worst <= max_error_px)
    floor = np.where(ok, foot @ up - offset, np.inf).min(-1)  # (N,)
    return floor[np.isfinite(floor)]
