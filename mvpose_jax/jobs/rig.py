"""A rig described: its cameras, centre and up, and the floor measured from people on it."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, NamedTuple

from mvpose_jax.jobs.common import DetectionsSource, RigSource, measure_floor

if TYPE_CHECKING:
    import numpy as np

    from mvpose_jax.cameras import Rig
    from mvpose_jax.floor import FloorEstimate


@dataclasses.dataclass(frozen=True)
class RigConfig:
    """A rig, and optionally detections of people on it to measure the floor from."""

    rig: RigSource
    detections: DetectionsSource | None = None


class RigDescription(NamedTuple):
    """A rig's geometry (metres, world frame).

    Attributes:
      rig: the loaded rig (C cameras).
      centres: (C, 3) camera centres.
      centre: (3,) the rig's centre; radius: its radius.
      up: (3,) the up vector as `cameras.up_vector` gives it (``rig.up``, or inferred from the
        cameras when None).
      floor: the floor measured from the detections (None without them).
      floor_guess: the floor height guessed from the cameras (None without detections).
    """

    rig: Rig
    centres: np.ndarray
    centre: np.ndarray
    radius: float
    up: object
    floor: FloorEstimate | None
    floor_guess: float | None


def describe_rig(config: RigConfig) -> RigDescription:
    """Loads the rig and measures what `RigDescription` holds."""
    import numpy as np

    from mvpose_jax.cameras import camera_centres, rig_centre_and_radius, up_vector

    rig = config.rig.load()
    centres = np.asarray(camera_centres(rig), np.float64)
    centre, radius = rig_centre_and_radius(rig)
    up = up_vector(rig)
    floor = guess = None
    if config.detections:
        from mvpose_jax.synthetic import estimate_floor_height

        floor = measure_floor(rig, config.detections)
        guess = float(estimate_floor_height(rig))
    return RigDescription(
        rig, centres, np.asarray(centre, np.float64), float(radius), up, floor, guess
    )
