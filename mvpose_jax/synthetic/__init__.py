"""Synthetic multi-camera recordings: people, motion and 2D-detector behaviour on any rig.

Pure numpy, vectorised over frames, people and cameras. See `docs/synthetic.md` for every
parameter and why its default is realistic. A figure of one frame:
`mvpose_jax.render.render_frame_figure` (``mvpose-jax synthetic-figure``).
"""

from __future__ import annotations

from mvpose_jax.synthetic.config import (
    BodyConfig,
    DetectorConfig,
    MotionConfig,
    SceneConfig,
    SyntheticConfig,
)
from mvpose_jax.synthetic.generate import (
    SyntheticScene,
    detection_variants,
    generate_recording,
    generate_single_person_recordings,
    simulate,
)
from mvpose_jax.synthetic.scene import (
    SceneGeometry,
    estimate_floor_height,
    scene_geometry,
)
from mvpose_jax.synthetic.shifts import SHIFTS, Shift, perturb_rig

__all__ = [
    "BodyConfig",
    "DetectorConfig",
    "MotionConfig",
    "SceneConfig",
    "SyntheticConfig",
    "SyntheticScene",
    "SceneGeometry",
    "SHIFTS",
    "Shift",
    "detection_variants",
    "estimate_floor_height",
    "generate_recording",
    "generate_single_person_recordings",
    "perturb_rig",
    "scene_geometry",
    "simulate",
]
