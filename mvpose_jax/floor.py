"""The floor from the people: its height measured from a recording's own detections.

The simulator (`synthetic.scene.estimate_floor_height`) can only guess the floor from where the
cameras hang, and on a real rig that guess can be half a metre off; models trained on recordings
generated with a wrong floor fail on the real one. When a user has detections of people walking
on their floor, the floor is measured instead: geometric proposals group the skeletons, robust
triangulation (`triangulate.triangulate_skeletons_robust`) reconstructs the feet of people seen
by three or more cameras, and the floor is the densest half (`shortest_half`) of the lowest foot
keypoint's height per person and frame, less that keypoint's height above the floor.

Why the lowest foot: while standing, walking, crouching or sitting, one foot is on the floor in
nearly every frame (walking alternates which), so its height above the floor is the keypoint's
own height (the ankle's malleolus, the heel, the toe). The densest half of the person-frames
ignores frames with both feet up (a jump, a foot on furniture) and the feet of a false skeleton
or of a person grouped wrongly, even where they are a third of the samples (a median is pulled).

Where the feet are hidden (an operating room: tables and equipment; a desk; a tight frame), the
floor comes from the upper body instead: the mid-shoulder height of upright people (torso within
`UPRIGHT_DEG` of up) less a standing adult's shoulder height, `STANDING_SHOULDER_HEIGHT_M` (a
standing-height prior; the median over person-frames, the people's own heights scattering it).
It assumes most of the people stand; people sitting put their shoulders
about 0.3 m lower, so a recording of seated people gives a floor that much too low, and the
spread says how far single person-frames disagree. ``basis="auto"`` (the default) measures the
feet and falls back to the upper body when too few feet are confident.

Up: the calibration's; without one, the cameras' guess (`cameras.up_vector`, which assumes
cameras mounted without roll) unless the people's torsos disagree with it by more than
`PEOPLE_UP_MIN_DEG`: then their mean direction (rolled or portrait cameras put the guess 10
degrees off and more).
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
# The standing-height prior: the shoulder joints of a standing adult are 0.818 of the standing
# height above the floor (Drillis & Contini), for the mean adult height of 1.70 m (and of the
# simulator's standing people, 1.50-1.95 m: 1.725 m, shoulders 0.806 H after their drop below the
# neck); detectors' shoulder keypoints sit on the joint. Heights vary by 7 cm (one standard
# deviation): one person-frame says the floor within about 6 cm, the median of many better, for
# a team of average height. People in motion carry their shoulders lower (the simulator's walk,
# crouch and bend: 1.33 m on median), so on them the floor comes out 5-10 cm low.
STANDING_SHOULDER_HEIGHT_M = 0.818 * 1.70
# A torso (mid-hip to mid-shoulder) within this angle of up is upright; others (people lying,
# bending over a table) say nothing of their shoulder height.
UPRIGHT_DEG = 25.0
# A shoulder or hip keypoint counts when robust triangulation kept this many views of it.
MIN_UPPER_BODY_VIEWS = 2
BASES = ("auto", "feet", "upper_body")
# Without an up in the calibration, up is the mean direction of the people's torsos (mid-hip to
# mid-shoulder) within this angle of it: people stand and walk upright, while the cameras' guess
# (`cameras.up_vector`) assumes cameras mounted without roll, which portrait or rolled cameras
# break (Pose2Sim's demo rig: 12 degrees off; its walking people's torsos: 2 degrees). Forward lean
# averages out over people facing several ways, not over one person facing one way.
PEOPLE_UP_DEG = 30.0
# The people's up replaces the cameras' guess only when they disagree by more than this: the
# guess is within 2.5 degrees on rigs of level cameras, the torsos' mean within 2-7 (people lean:
# 5.8 degrees between the two on the simulated presets, 10.7 on Pose2Sim's demo rig, where the
# people are 2 degrees from the calibration's true vertical and the guess 12).
PEOPLE_UP_MIN_DEG = 8.0


@dataclasses.dataclass(frozen=True)
class FloorEstimate:
    """The floor measured from detections.

    Attributes:
      height: floor height along ``up`` (the floor is ``{x : x . up = height}``), metres.
      spread: a robust standard deviation of the per-person-frame floor heights, metres (the
        feet: the shortest half's length / 1.349; the upper body: 1.4826 x the median absolute
        deviation): how much they scatter.
      num_samples: person-frames with a confident foot keypoint (or upright torso).
      num_frames: frames looked at.
      up: (3,) the unit up vector used (`cameras.up_vector`).
      basis: what was measured: "feet" (the lowest confident foot keypoint) or "upper_body"
        (upright people's shoulders and the standing-height prior).
      up_source: where ``up`` comes from: "calibration" (its ``up``), "people" (the mean torso
        direction of the upright people, the calibration having none and the cameras' guess
        being more than `PEOPLE_UP_MIN_DEG` off it) or "cameras" (`cameras.up_vector`'s guess).
      camera_up_deg: without an up in the calibration, degrees between the people's up and the
        cameras' guess (None: too few upright people, or the calibration's up).
    """

    height: float
    spread: float
    num_samples: int
    num_frames: int
    up: tuple[float, float, float]
    basis: str = "feet"
    up_source: str = "calibration"
    camera_up_deg: float | None = None

    @property
    def measured_up(self) -> tuple[float, float, float] | None:
        """``up`` where it was measured from the people (the one to simulate along), else None:
        the calibration's or the cameras' guess, which the rig already gives."""
        return self.up if self.up_source == "people" else None

    def describe(self) -> str:
        """One line: height, spread, samples and basis."""
        basis = (
            "the feet"
            if self.basis == "feet"
            else "upright people's shoulders with a standing-height prior (the feet too rarely seen)"
        )
        text = (
            f"{self.height:.3f} m along up (spread {self.spread:.3f} m over {self.num_samples} "
            f"person-frames of {self.num_frames} frames; from {basis})"
        )
        if self.up_source == "people":
            text += (
                f"; up {np.round(self.up, 3).tolist()} measured from the people's torsos (the "
                f"calibration has none; the cameras' guess is {self.camera_up_deg:.1f} deg off)"
            )
        return text


def estimate_floor_from_detections(
    rig: Rig,
    detections: Detections,
    *,
    layout: str | Layout = "coco18",
    max_frames: int = 2000,
    min_samples: int = MIN_SAMPLES,
    max_error_px: float = MAX_FOOT_ERROR_PX,
    basis: str = "auto",
) -> FloorEstimate:
    """The floor height along the rig's up from the triangulated people (module docstring).

    Args:
      rig: the C cameras of the detections, in their order.
      detections: xy (F, C, P, K, 2) pixels, score (F, C, P, K), count (F, C).
      layout: the detections' keypoint layout (its ankles, and heels and big toes if it has them;
        its shoulders and hips for the upper body).
      max_frames: at most this many frames, evenly spaced, are used (the floor does not move).
      min_samples: fewest person-frames with a confident foot (or upright torso).
      max_error_px: largest reprojection error of a kept view of a confident keypoint.
      basis: "feet", "upper_body", or "auto": the feet, else the upper body when fewer than
        ``min_samples`` person-frames show a confident foot.
    Returns:
      A `FloorEstimate`.
    Raises:
      InputError when the layout lacks the keypoints or too few confident people are found.
    """
    if basis not in BASES:
        raise InputError(f"must be one of {', '.join(BASES)}, not {basis!r}", field="basis")
    lay = get_layout(layout)
    feet = [
        (lay.index(f"{side}_{name}"), offset)
        for name, offset in FOOT_KEYPOINT_HEIGHTS_M.items()
        for side in ("l", "r")
        if f"{side}_{name}" in lay.keypoints
    ]
    torso = ("l_shoulder", "r_shoulder", "l_hip", "r_hip")
    has_torso = all(k in lay.keypoints for k in torso)
    if basis == "feet" and not feet or basis != "feet" and not feet and not has_torso:
        raise InputError(
            f"layout {lay.name!r} has no ankle keypoints to find the floor from"
            + ("" if basis == "feet" else " (nor shoulders and hips)"),
            field="layout",
        )
    if basis == "upper_body" and not has_torso:
        raise InputError(
            f"layout {lay.name!r} has no shoulders and hips to find the floor from", field="layout"
        )
    F = int(np.shape(detections.count)[0])
    frames = np.unique(np.linspace(0, max(F - 1, 0), min(F, max_frames)).round().astype(int))
    det = Detections(*(np.asarray(a)[frames] for a in detections))
    people = _grouped_people(rig, det)
    torsos = None
    if has_torso and people is not None:
        torsos = _torsos(rig, *people, [lay.index(k) for k in torso])
    up, up_source, off_deg = _up(rig, torsos, min_samples)
    meta = dict(num_frames=len(frames), up=up, up_source=up_source, camera_up_deg=off_deg)
    feet_heights = np.zeros((0,))
    if basis != "upper_body" and feet and people is not None:
        xy, score = people
        seen = (score > 0).any(-1).sum(-1) >= MIN_FOOT_VIEWS
        feet_heights = _lowest_foot_heights(rig, xy[seen], score[seen], feet, up, max_error_px)
    if basis == "feet" or (basis == "auto" and len(feet_heights) >= min_samples):
        return _estimate(feet_heights, "feet", min_samples, basis, **meta)
    torso_heights = np.zeros((0,))
    if torsos is not None:
        shoulders, hips = torsos
        upright = _upright(shoulders - hips, up)
        torso_heights = shoulders[upright] @ up - STANDING_SHOULDER_HEIGHT_M
    return _estimate(
        torso_heights, "upper_body", min_samples, basis, feet=len(feet_heights), **meta
    )


def _grouped_people(rig: Rig, det: Detections) -> tuple[np.ndarray, np.ndarray] | None:
    """The geometric default's people: xy (N, C, K, 2), score (N, C, K); None without any."""
    if int(np.shape(det.count)[0]) == 0 or rig.num_cameras < MIN_UPPER_BODY_VIEWS:
        return None
    res = run_pipeline(rig, det, method="robust")
    xy, score = group_people(det.xy, det.score, res.members)  # (F, G, C, K, ...)
    valid = np.asarray(res.poses.valid)
    return np.asarray(xy)[valid], np.asarray(score)[valid]


def _estimate(
    heights: np.ndarray,
    basis: str,
    min_samples: int,
    asked: str,
    *,
    num_frames: int,
    up: np.ndarray,
    up_source: str,
    camera_up_deg: float | None,
    feet: int | None = None,
) -> FloorEstimate:
    if len(heights) < min_samples:
        if basis == "feet":
            what = f"have a foot keypoint seen consistently by {MIN_FOOT_VIEWS}+ cameras"
        else:
            what = (
                f"show an upright torso (shoulders and hips seen consistently by "
                f"{MIN_UPPER_BODY_VIEWS}+ cameras)"
            )
            if asked == "auto":
                what += f", and {feet} a foot seen by {MIN_FOOT_VIEWS}+ cameras"
        raise InputError(
            f"cannot measure the floor: only {len(heights)} person-frames (of {num_frames} "
            f"frames) {what} (need {min_samples}); give the floor height instead",
            field="floor",
        )
    if basis == "feet":
        height, spread = shortest_half(heights)
    else:
        # Shoulder heights scatter with the people's own heights, a continuous spread whose
        # densest half would be the tallest or the shortest people: the median.
        height = float(np.median(heights))
        spread = float(1.4826 * np.median(np.abs(heights - height)))
    return FloorEstimate(
        height,
        spread,
        len(heights),
        num_frames,
        tuple(float(u) for u in up),
        basis,
        up_source,
        camera_up_deg,
    )


def shortest_half(values: np.ndarray) -> tuple[float, float]:
    """(location, spread) of the densest half of ``values`` (N,): the median of the shortest
    interval that holds half of them, and that interval's length / 1.349 (a normal
    distribution's standard deviation). Unlike the median, a second cluster (a raised foot, a
    false skeleton's feet on a table, 0.75 m up in Pose2Sim's demo) of under half the values does
    not pull it."""
    v = np.sort(np.asarray(values, np.float64))
    k = (len(v) + 1) // 2
    i = int(np.argmin(v[k - 1 :] - v[: len(v) - k + 1]))
    window = v[i : i + k]
    return float(np.median(window)), float((window[-1] - window[0]) / 1.349)


def _torsos(
    rig: Rig, xy: np.ndarray, score: np.ndarray, torso: list[int]
) -> tuple[np.ndarray, np.ndarray]:
    """Mid-shoulders and mid-hips (M, 3) of the people whose four torso keypoints robust
    triangulation keeps in `MIN_UPPER_BODY_VIEWS`+ views.

    xy: (N, C, K, 2), score: (N, C, K); torso: the indices of l/r shoulder, l/r hip. No pixel
    limit beyond robust triangulation's own outlier test: detectors place hips loosely (tens of
    pixels in large images), and the median over many people absorbs it.
    """
    if len(xy) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    idx = np.array(torso)
    px, w = np.moveaxis(xy[:, :, idx], 1, 0), np.moveaxis(score[:, :, idx], 1, 0)
    xyz, valid, kept = (np.asarray(a) for a in triangulate_skeletons_robust(rig, px, w))
    ok = (valid & (kept.sum(0) >= MIN_UPPER_BODY_VIEWS)).all(-1)
    return xyz[ok, :2].mean(1), xyz[ok, 2:].mean(1)


def _upright(axis: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Whether torso vectors (M, 3) (mid-hip to mid-shoulder) are within `UPRIGHT_DEG` of up."""
    length = np.linalg.norm(axis, axis=-1)
    return (length > 0) & (axis @ up >= np.cos(np.radians(UPRIGHT_DEG)) * length)


def _up(
    rig: Rig, torsos: tuple[np.ndarray, np.ndarray] | None, min_samples: int
) -> tuple[np.ndarray, str, float | None]:
    """(up, its source, degrees between the people's up and the cameras' guess): the
    calibration's up; else the mean torso direction of the upright people (trimmed at
    `PEOPLE_UP_DEG`) where it is more than `PEOPLE_UP_MIN_DEG` from `cameras.up_vector`'s guess
    from the cameras; else that guess (also with fewer than ``min_samples`` upright people)."""
    cameras = np.asarray(up_vector(rig), np.float64)
    if rig.up is not None:
        return cameras, "calibration", None
    if torsos is None:
        return cameras, "cameras", None
    axis = torsos[0] - torsos[1]
    axis = axis[np.linalg.norm(axis, axis=-1) > 0]
    unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    if len(unit) < min_samples:
        return cameras, "cameras", None
    up = unit.mean(0) / np.linalg.norm(unit.mean(0))
    for _ in range(4):  # from the mean of all torsos: the mean of those near the current mean
        keep = unit @ up >= np.cos(np.radians(PEOPLE_UP_DEG))
        if keep.sum() < min_samples:
            return cameras, "cameras", None
        up = unit[keep].mean(0)
        up /= np.linalg.norm(up)
    deg = float(np.degrees(np.arccos(np.clip(up @ cameras, -1.0, 1.0))))
    if deg <= PEOPLE_UP_MIN_DEG:
        return cameras, "cameras", deg
    return up, "people", deg


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
