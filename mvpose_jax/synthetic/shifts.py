"""Domain shifts: recordings made with detectors, people and rigs the models never saw in training.

Models are trained on the default simulator (`SyntheticConfig()`); a `Shift` turns that into the
settings of a test recording (and, for calibration errors, the rig the detections are made
with, while reconstruction keeps the nominal rig). `SHIFTS` names the presets that
``python -m experiments.run --experiment domain-shift`` measures; `docs/synthetic.md` gives each
one's sources.

* ``coco-sigmas``: per-keypoint error scales from COCO's published keypoint sigmas (OKS), with
  heavy (Student-t, 3 degrees of freedom) tails.
* ``part-mixing``: a bottom-up detector's grouping errors: lower limbs of the nearest other person,
  duplicate skeletons, fragments.
* ``occluders``: static boxes (furniture) hiding body parts in some views, and people cut at the
  image border.
* ``scores``: another score calibration (a Beta distribution up to 1.04, blind to size and
  occlusion).
* ``world``: children, deep squats and sitting, deep bends, arms straight up, fewer walkers.
* ``floor+0.3``, ``floor-0.3``, ``floor+0.6``, ``floor-0.6``: the scenes' floor that far above or
  below the one the models were trained on (metres, along up).
* ``calibration``: each camera of the recording rotated by 0.5-1 px (at the focal length) and
  moved by 1 cm; the models and triangulation use the nominal calibration.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from mvpose_jax.cameras import Rig, make_rig, up_vector
from mvpose_jax.synthetic.config import SyntheticConfig
from mvpose_jax.synthetic.scene import scene_geometry

# COCO's per-keypoint OKS sigmas (cocodataset.org/#keypoints-eval; pycocotools
# COCOeval.computeOks / Params.kpt_oks_sigmas): nose, eyes, ears, shoulders, elbows, wrists,
# hips, knees, ankles; in coco18 order, the neck (OpenPose's midpoint of the shoulders) last,
# given the shoulders' sigma.
COCO_SIGMAS = np.array(
    [
        0.026,
        0.025,
        0.025,
        0.035,
        0.035,
        0.079,
        0.079,
        0.072,
        0.072,
        0.062,
        0.062,
        0.107,
        0.107,
        0.087,
        0.087,
        0.089,
        0.089,
        0.079,
    ]
)


@dataclasses.dataclass(frozen=True)
class Shift:
    """A domain shift of test recordings.

    Attributes:
      name: the preset's key in `SHIFTS`.
      description: one line, for tables.
      config: the training recordings' settings -> the shifted recordings' settings.
      rotation_px: (min, max) calibration error of each camera's rotation, pixels at the focal
        length (a rotation by px / fx radians about a random axis); None: the nominal rig.
      translation_m: calibration error of each camera's position, metres (a random direction).
    """

    name: str
    description: str
    config: Callable[[SyntheticConfig], SyntheticConfig] = lambda c: c
    rotation_px: tuple[float, float] | None = None
    translation_m: float = 0.0

    def apply(
        self,
        rig: Rig,
        config: SyntheticConfig = SyntheticConfig(),
        seed: int | Sequence[int] = 0,
    ) -> tuple[Rig, SyntheticConfig]:
        """The rig to generate a shifted recording with, and its settings.

        Args:
          rig: the nominal rig (the one the models know and reconstruction uses).
          config: the training recordings' settings.
          seed: draws the calibration error (per recording).
        Returns:
          (rig to simulate the detections with, settings).
        """
        shifted = self.config(config)
        if self.rotation_px is None and self.translation_m == 0:
            return rig, shifted
        # The scene stays where the nominal rig puts it: up and floor from the nominal rig.
        floor = scene_geometry(rig, config.scene).floor_height
        shifted = shifted.with_scene(up=tuple(float(x) for x in up_vector(rig)), floor_height=floor)
        perturbed = perturb_rig(
            rig,
            rotation_px=self.rotation_px or (0.0, 0.0),
            translation_m=self.translation_m,
            seed=seed,
        )
        return perturbed, shifted


def perturb_rig(
    rig: Rig,
    *,
    rotation_px: tuple[float, float],
    translation_m: float,
    seed: int | Sequence[int] = 0,
) -> Rig:
    """The rig with each camera's pose slightly wrong (a calibration error).

    Each camera turns by ``U(*rotation_px) / fx`` radians about a uniformly random axis (so a
    rotation perpendicular to the optical axis moves the image centre by that many pixels) and
    its centre moves ``translation_m`` metres in a uniformly random direction.

    Returns:
      A `Rig` with the same intrinsics, names and up.
    """
    rng = np.random.default_rng(seed)
    K = np.asarray(rig.K, np.float64)
    R = np.asarray(rig.R, np.float64)
    t = np.asarray(rig.t, np.float64)
    C = len(rig.names)
    angle = rng.uniform(*rotation_px, C) / K[:, 0, 0]
    axis = _unit(rng.standard_normal((C, 3)))
    centre = -np.einsum("cji,cj->ci", R, t)
    moved = centre + translation_m * _unit(rng.standard_normal((C, 3)))
    R_new = np.einsum("cij,cjk->cik", rotation_matrix(axis * angle[:, None]), R)
    t_new = -np.einsum("cij,cj->ci", R_new, moved)
    return make_rig(K, np.asarray(rig.dist), R_new, t_new, np.asarray(rig.size), rig.names, rig.up)


def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (..., 3) (axis times angle, radians) -> (..., 3, 3)."""
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = rotvec / np.maximum(theta[..., 0], 1e-300)
    z = np.zeros_like(k[..., 0])
    cross = np.stack(
        [
            np.stack([z, -k[..., 2], k[..., 1]], -1),
            np.stack([k[..., 2], z, -k[..., 0]], -1),
            np.stack([-k[..., 1], k[..., 0], z], -1),
        ],
        -2,
    )
    eye = np.broadcast_to(np.eye(3), cross.shape)
    return eye + np.sin(theta) * cross + (1 - np.cos(theta)) * cross @ cross


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _coco_sigmas(c: SyntheticConfig) -> SyntheticConfig:
    # The sigmas' shape (faces 0.4x, hips 1.6x the mean), their mean at the default's noise, and
    # Student-t tails with 3 degrees of freedom (standard deviation sqrt(3) times the scale).
    scale = COCO_SIGMAS / COCO_SIGMAS.mean()
    return c.with_detector(keypoint_noise_scale=tuple(float(s) for s in scale), noise_tail_dof=3.0)


def _part_mixing(c: SyntheticConfig) -> SyntheticConfig:
    return c.with_detector(
        limb_mix_rate=0.15, mix_distance=0.6, duplicate_rate=0.03, fragment_rate=0.05
    )


def _occluders(c: SyntheticConfig) -> SyntheticConfig:
    return c.with_detector(num_occluders=3, border_margin=0.05)


def _scores(c: SyntheticConfig) -> SyntheticConfig:
    return c.with_detector(score_beta=(4.0, 1.5), score_max=1.04, occluded_score_factor=1.0)


def _world(c: SyntheticConfig) -> SyntheticConfig:
    # Outside the training ranges: children (training heights are 1.50-1.95 m); crouches deeper
    # and upright (sitting on an unseen stool: hips and knees flexed 86-114 and 106-142 deg,
    # training 57-95 and 71-118 with the trunk 18-30 deg forward); bends of 80-110 deg
    # (training 50-85); arms straight up (165-180 deg, training 140-170); and more of these
    # activities, fewer walkers.
    return c.with_body(child_fraction=0.5).with_motion(
        crouch_depth=(0.9, 1.2),
        crouch_trunk_deg=5.0,
        bend_deg=(80.0, 110.0),
        reach_up_deg=(165.0, 180.0),
        activity_weights=(1.0, 0.5, 2.0, 1.0, 2.0, 2.0),
        walk_probability=0.3,
    )


def _floor(offset: float) -> Callable[[SyntheticConfig], SyntheticConfig]:
    return lambda c: c.with_scene(floor_offset_m=offset)


SHIFTS: dict[str, Shift] = {
    s.name: s
    for s in (
        Shift("none", "the training simulator (reference)"),
        Shift(
            "coco-sigmas",
            "per-keypoint noise from COCO's OKS sigmas, Student-t tails",
            _coco_sigmas,
        ),
        Shift("part-mixing", "limbs of the nearest person, duplicates, fragments", _part_mixing),
        Shift("occluders", "3 static boxes per scene, 5 % image border lost", _occluders),
        Shift("scores", "scores 1.04 Beta(4, 1.5), blind to size and occlusion", _scores),
        Shift("world", "children, deep squats and sitting, deep bends, arms up", _world),
        Shift("floor+0.3", "the floor 0.3 m above the training floor", _floor(0.3)),
        Shift("floor-0.3", "the floor 0.3 m below the training floor", _floor(-0.3)),
        Shift(
            "floor+0.6", "the floor 0.6 m above the training floor (issue 19's rig)", _floor(0.6)
        ),
        Shift("floor-0.6", "the floor 0.6 m below the training floor", _floor(-0.6)),
        Shift(
            "calibration",
            "cameras rotated 0.5-1 px and moved 1 cm; nominal rig used",
            rotation_px=(0.5, 1.0),
            translation_m=0.01,
        ),
    )
}
