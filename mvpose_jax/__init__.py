"""mvpose-jax: multi-person, multi-view 3D pose estimation trained without 3D labels, in JAX.

Public API (the modules hold the details):
  * cameras: `Rig`, `make_rig`, `project_points`, `undistort_points`, `pixel_rays`,
    `camera_centres`, `rig_centre_and_radius`, `up_vector`.
  * triangulate: `triangulate_points` (score-weighted DLT), `triangulate_pairwise_centroid`.
  * skeletons: `Detections`, `Poses3D`, `Layout`, `get_layout`, `convert_keypoints`.
  * data: `load_rig`, `Recording`, readers and writers.
  * synthetic: simulated recordings (`generate_recording`, `generate_single_person_recordings`).
"""

from mvpose_jax.cameras import (
    Rig,
    camera_centres,
    make_rig,
    pixel_rays,
    project_points,
    rig_centre_and_radius,
    undistort_points,
    up_vector,
)
from mvpose_jax.errors import InputError, MvposeError
from mvpose_jax.skeletons import Detections, Layout, Poses3D, convert_keypoints, get_layout
from mvpose_jax.triangulate import triangulate_pairwise_centroid, triangulate_points

__version__ = "0.1.0"

__all__ = [
    "Detections",
    "InputError",
    "Layout",
    "MvposeError",
    "Poses3D",
    "Rig",
    "camera_centres",
    "convert_keypoints",
    "get_layout",
    "make_rig",
    "pixel_rays",
    "project_points",
    "rig_centre_and_radius",
    "triangulate_pairwise_centroid",
    "triangulate_points",
    "undistort_points",
    "up_vector",
]
