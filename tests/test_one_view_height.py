"""experiments.one_view_height: the move of one-view people to a standing shoulder height,
against its closed form."""

from __future__ import annotations

import numpy as np

from experiments.one_view_height import moved_to_standing_height
from mvpose_jax.data.poses import PoseResults
from mvpose_jax.floor import STANDING_SHOULDER_HEIGHT_M
from mvpose_jax.skeletons import Poses3D, get_layout

LAYOUT = "coco18"


def _person(shoulder_z: float, torso: np.ndarray, x: float) -> np.ndarray:
    """(K, 3) keypoints: shoulders around (x, 0, shoulder_z), hips ``torso`` below them, the
    rest at the shoulders' midpoint."""
    lay = get_layout(LAYOUT)
    xyz = np.tile([x, 0.0, shoulder_z], (len(lay.keypoints), 1))
    for side, dy in (("r", -0.2), ("l", 0.2)):
        xyz[lay.index(f"{side}_shoulder")] += [0.0, dy, 0.0]
        xyz[lay.index(f"{side}_hip")] += [0.0, dy, 0.0] - torso
    return xyz


def test_upright_one_view_people_move_along_their_ray_to_the_standing_height():
    up = np.array([0.0, 0.0, 1.0])
    floor = -1.0
    centres = np.array([[0.0, 0.0, 2.0], [5.0, 0.0, 2.0]])  # metres
    upright, leaning = np.array([0.0, 0.0, 0.5]), np.array([0.5, 0.0, 0.2])
    people = np.stack(
        [
            _person(0.9, upright, 3.0),  # one view (camera 0), upright: moved
            _person(0.9, leaning, 3.0),  # one view, torso 68 deg from up: kept
            _person(0.9, upright, 2.0),  # two views: kept
            _person(0.9, upright, 2.5),  # one view (camera 1), upright: moved
        ]
    )[None]  # (1, 4, K, 3)
    K = people.shape[2]
    members = np.array([[[0, -1], [1, -1], [2, 2], [-1, 3]]])  # (1, G, C)
    poses = Poses3D(people, np.ones((1, 4), bool), np.ones((1, 4, K), bool))
    result = PoseResults(
        poses, np.ones((1, 4)), members, np.zeros((1, 2, 4), int), ("a", "b"), LAYOUT
    )
    moved, n = moved_to_standing_height(result, centres, up, floor, LAYOUT, max_tilt_deg=30.0)
    assert n == 2
    np.testing.assert_array_equal(moved[0, 1:3], people[0, 1:3])
    lay = get_layout(LAYOUT)
    shoulders = [lay.index("r_shoulder"), lay.index("l_shoulder")]
    for g, cam in ((0, 0), (3, 1)):
        before, after = people[0, g, shoulders].mean(0), moved[0, g, shoulders].mean(0)
        # At the standing height, on the camera's ray through the lifted mid-shoulder, and the
        # body translated, not scaled.
        np.testing.assert_allclose(after @ up, floor + STANDING_SHOULDER_HEIGHT_M, atol=1e-9)
        ray, moved_ray = before - centres[cam], after - centres[cam]
        np.testing.assert_allclose(np.cross(ray, moved_ray), 0.0, atol=1e-9)
        np.testing.assert_allclose(moved[0, g] - after, people[0, g] - before, atol=1e-9)
    # With every tilt allowed, the leaning person moves too.
    _, n = moved_to_standing_height(result, centres, up, floor, LAYOUT, max_tilt_deg=90.0)
    assert n == 3
