"""Configuration of the synthetic-data generator: frozen dataclasses with documented defaults.

Every default is chosen to be realistic; `docs/synthetic.md` says why for each one. Override with
``dataclasses.replace`` (or the ``with_*`` helpers of `SyntheticConfig`). Lengths are metres,
times seconds, angles degrees, image quantities pixels or fractions of a person's image height.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class BodyConfig:
    """Population of bodies (anthropometry). One body per person, constant over time.

    Attributes:
      height_range: (min, max) standing height (floor to top of head), metres.
      height_mean: mean height of the (female, male) sub-populations, metres.
      height_std: standard deviation of height within each sub-population, metres.
      male_fraction: probability that a body is drawn from the male sub-population.
      proportion_std: relative standard deviation of the segment-length factors (legs, trunk,
        arms, thigh/shin and upper-arm/forearm ratios); heights stay exact after them.
      width_std: relative standard deviation of shoulder and hip widths.
      head_std: relative standard deviation of head size.
      girth_std: relative standard deviation of the limb and torso radii (body mass).
      child_fraction: probability that a body is a child's instead (0: adults only, the default):
        height uniform in ``child_height_range``, head ``child_head_factor`` times larger
        relative to the height (children's heads are relatively larger).
      child_height_range: (min, max) height of children, metres.
      child_head_factor: head size of children relative to an adult of the same height.
    """

    height_range: tuple[float, float] = (1.50, 1.95)
    height_mean: tuple[float, float] = (1.63, 1.77)
    height_std: float = 0.07
    male_fraction: float = 0.5
    proportion_std: float = 0.03
    width_std: float = 0.06
    head_std: float = 0.05
    girth_std: float = 0.12
    child_fraction: float = 0.0
    child_height_range: tuple[float, float] = (1.10, 1.40)
    child_head_factor: float = 1.15


@dataclasses.dataclass(frozen=True)
class MotionConfig:
    """How people move on the floor.

    Attributes:
      fps: frame rate, frames per second (CMU Panoptic's HD cameras run at 29.97).
      speed_range: (min, max) preferred walking speed of a person, m/s.
      walk_probability: probability that a person, done with an activity, walks to a new goal
        (else it stays on the spot and does one of ``activity_weights``).
      activity_weights: relative frequencies of the on-the-spot activities
        (stand, turn, reach, wave, crouch, bend).
      activity_duration: (min, max) seconds of one on-the-spot activity.
      personal_distance: extra clearance between two people's footprints, metres; social forces
        start steering at three times this.
      face_others_probability: probability that a person turning on the spot turns to face the
        nearest other person (conversation), else to a random direction.
      max_turn_rate: fastest turn of a person's heading, degrees per second.
      acceleration: largest change of walking velocity, m/s^2.
      sim_dt: time step of the path planner, seconds (paths are then interpolated to frames).
      crouch_depth: (min, max) depth of a crouch: hips flex to 95 deg and knees to 118 deg times
        it, the trunk leans forward 30 deg times it.
      crouch_trunk_deg: forward lean of the trunk in a crouch of depth 1, degrees (0: sitting
        upright, as on a stool).
      bend_deg: (min, max) forward bend of the trunk in a bend, degrees.
      reach_up_deg: (min, max) shoulder flexion of an upward reach, degrees (180: arm straight
        up).
    """

    fps: float = 30.0
    speed_range: tuple[float, float] = (0.5, 1.8)
    walk_probability: float = 0.55
    activity_weights: tuple[float, float, float, float, float, float] = (
        3.0,
        1.5,
        1.5,
        1.0,
        1.0,
        1.0,
    )
    activity_duration: tuple[float, float] = (1.5, 5.0)
    personal_distance: float = 0.15
    face_others_probability: float = 0.5
    max_turn_rate: float = 150.0
    acceleration: float = 1.5
    sim_dt: float = 0.2
    crouch_depth: tuple[float, float] = (0.6, 1.0)
    crouch_trunk_deg: float = 30.0
    bend_deg: tuple[float, float] = (50.0, 85.0)
    reach_up_deg: tuple[float, float] = (140.0, 170.0)


@dataclasses.dataclass(frozen=True)
class DetectorConfig:
    """Behaviour of the simulated 2D skeleton detector (OpenPose-like). Rates are probabilities.

    The fields from ``keypoint_noise_scale`` on are other detectors' behaviour, all off by
    default; `synthetic.shifts` combines them into the domain shifts the models are tested on.

    Attributes:
      noise_relative: pixel noise, standard deviation per axis, as a fraction of the person's
        height in the image.
      noise_floor_px: pixel noise floor, standard deviation per axis, for a 1920x1080 image (it
        is scaled by the image diagonal); it makes the relative error grow for small people.
      occluded_noise_factor: noise multiplier for occluded keypoints (the detector guesses them).
      offset_scale: multiplier of the per-keypoint systematic offsets (the table in
        `detector.SYSTEMATIC_OFFSETS`, metres in the body frame for a 1.75 m person); 0 disables.
      offset_person_std: relative per-person variation of the systematic offsets.
      occluded_drop_rate: probability that a keypoint occluded (by the own body or by someone
        else) is missing from the detection.
      keypoint_drop_rate: probability that a visible, in-image keypoint is missing anyway.
      occluded_score_factor: factor on the score of occluded keypoints that are still reported.
      size_half_score: person image height (fraction of the image height) at which scores fall
        to half their value for large people.
      score_noise: standard deviation of the per-keypoint score noise.
      miss_rate: probability that a person in view of a camera is not detected at all.
      min_keypoints_in_view: a person is "in view" of a camera when at least this many of its
        keypoints project inside the image (in front of the camera).
      min_keypoints: detections with fewer reported keypoints are discarded (OpenPose drops
        skeletons with too few parts).
      false_positive_rate: mean number of false-positive skeletons per view and frame (Poisson).
      false_positive_near_fraction: fraction of false positives placed next to a real person
        (leftover limbs); the rest fall anywhere in the image.
      swap_rate: probability that a detection has its left and right limbs exchanged (an arm
        pair, a leg pair or the whole body).
      keypoint_noise_scale: per-keypoint multipliers (K,) of the pixel noise; None: 1 for all.
      noise_tail_dof: degrees of freedom of a Student-t pixel noise (heavy tails; its scale is
        the Gaussian's standard deviation); None: Gaussian.
      border_margin: keypoints closer than this fraction of the image height to the image border
        are not reported (detectors lose people cut by the border); 0: only keypoints outside
        the image are lost.
      num_occluders: static boxes (furniture) standing on the floor just outside the capture
        area, between a camera and the people; keypoints behind a box (the ray from the camera
        to the keypoint passes through it) are not reported. 0: none.
      occluder_size: ((min, max) width, (min, max) depth, (min, max) height) of the boxes, m.
      limb_mix_rate: bottom-up part mixing: probability, per detection and lower limb (forearm:
        elbow and wrist; shin: knee and ankle), that the limb is replaced by the same limb of
        the nearest other person detected in the view (when that person's skeleton centre lies
        within ``mix_distance`` of the person's image height).
      mix_distance: how near (in the person's image heights) another person must be to mix.
      duplicate_rate: probability that a detection is reported a second time, with its own
        noise (``duplicate_noise`` of the person's image height per axis) and lower scores.
      duplicate_noise: noise of duplicates, fraction of the person's image height.
      fragment_rate: probability that a detection comes with a fragment: a second skeleton
        holding only a limb or a few keypoints of the person.
      score_beta: (a, b): keypoint scores are ``score_max * Beta(a, b)`` draws instead of the
        default model (falling with size and occlusion); None: the default model.
      score_max: the largest score (OpenPose's peaks reach about 1.04); scores are clipped to
        [0.05, score_max].
    """

    noise_relative: float = 0.004
    noise_floor_px: float = 1.0
    occluded_noise_factor: float = 2.0
    offset_scale: float = 1.0
    offset_person_std: float = 0.3
    occluded_drop_rate: float = 0.4
    keypoint_drop_rate: float = 0.02
    occluded_score_factor: float = 0.55
    size_half_score: float = 0.08
    score_noise: float = 0.06
    miss_rate: float = 0.03
    min_keypoints_in_view: int = 6
    min_keypoints: int = 4
    false_positive_rate: float = 0.1
    false_positive_near_fraction: float = 0.5
    swap_rate: float = 0.02
    keypoint_noise_scale: tuple[float, ...] | None = None
    noise_tail_dof: float | None = None
    border_margin: float = 0.0
    num_occluders: int = 0
    occluder_size: tuple[tuple[float, float], tuple[float, float], tuple[float, float]] = (
        (0.6, 1.5),
        (0.4, 0.8),
        (0.8, 1.8),
    )
    limb_mix_rate: float = 0.0
    mix_distance: float = 1.0
    duplicate_rate: float = 0.0
    duplicate_noise: float = 0.01
    fragment_rate: float = 0.0
    score_beta: tuple[float, float] | None = None
    score_max: float = 1.0

    def clean(self) -> DetectorConfig:
        """A detector with every effect off: exact projections, all in-image keypoints."""
        return dataclasses.replace(
            self,
            noise_relative=0.0,
            noise_floor_px=0.0,
            offset_scale=0.0,
            occluded_drop_rate=0.0,
            keypoint_drop_rate=0.0,
            score_noise=0.0,
            miss_rate=0.0,
            false_positive_rate=0.0,
            swap_rate=0.0,
            min_keypoints=1,
        )


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """Where people can be: the floor and the capture area, derived from the rig.

    Attributes:
      up: world up vector; None uses the calibration's ``up`` or infers it (`cameras.up_vector`).
      floor_height: floor height along ``up`` (the floor is ``{x : x . up = floor_height}``),
        metres; None estimates it from the cameras (see `scene.estimate_floor_height`).
      min_views: a floor cell belongs to the capture area when at least this many cameras see the
        whole body of a standing 1.75 m person there (capped at the number of cameras).
      min_person_height: ... and that person is at least this fraction of the image height tall.
      cell_size: side of the floor cells of the capture-area map, metres.
      hull_margin: when the cameras surround the space, the area stays this far inside the
        horizontal convex hull of the camera centres (people do not walk into the cameras).
      camera_clearance: the area keeps this horizontal distance from every camera centre.
      floor_jitter_m: each generated recording (each scene of `simulate`) gets its own floor,
        drawn uniformly within this many metres of ``floor_height`` (or of the estimate), in 1 cm
        steps; its capture area follows (it is derived from the floor). Training recordings made
        with a jitter teach the models that the floor is not exactly where it was measured or
        guessed. 0 (the default) keeps one floor.
      floor_offset_m: added to the floor height (given or estimated), metres: scenes on a
        floor other than the one the models were trained on (a domain shift). 0: none.
    """

    up: tuple[float, float, float] | None = None
    floor_height: float | None = None
    min_views: int = 2
    min_person_height: float = 0.15
    cell_size: float = 0.1
    hull_margin: float = 0.5
    camera_clearance: float = 1.0
    floor_jitter_m: float = 0.0
    floor_offset_m: float = 0.0


@dataclasses.dataclass(frozen=True)
class SyntheticConfig:
    """Everything the generator needs besides the rig, the sizes and the seed."""

    body: BodyConfig = BodyConfig()
    motion: MotionConfig = MotionConfig()
    detector: DetectorConfig = DetectorConfig()
    scene: SceneConfig = SceneConfig()

    def replace(self, **parts) -> SyntheticConfig:
        """Returns a copy with whole parts replaced, e.g. ``cfg.replace(detector=...)``."""
        return dataclasses.replace(self, **parts)

    def with_detector(self, **fields) -> SyntheticConfig:
        """Returns a copy with some detector fields changed."""
        return dataclasses.replace(self, detector=dataclasses.replace(self.detector, **fields))

    def with_motion(self, **fields) -> SyntheticConfig:
        """Returns a copy with some motion fields changed."""
        return dataclasses.replace(self, motion=dataclasses.replace(self.motion, **fields))

    def with_body(self, **fields) -> SyntheticConfig:
        """Returns a copy with some body fields changed."""
        return dataclasses.replace(self, body=dataclasses.replace(self.body, **fields))

    def with_scene(self, **fields) -> SyntheticConfig:
        """Returns a copy with some scene fields changed."""
        return dataclasses.replace(self, scene=dataclasses.replace(self.scene, **fields))
