"""floor.py: the floor measured from the people against the synthetic recordings' true floor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mvpose_jax.cameras import camera_centres, make_rig, up_vector
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.errors import InputError
from mvpose_jax.floor import estimate_floor_from_detections, shortest_half
from mvpose_jax.skeletons import Detections, Layout, get_layout
from mvpose_jax.synthetic import SceneConfig, SyntheticConfig, estimate_floor_height, simulate


def _scene(rig, shift: float, seed: int):
    """A 4-person recording whose floor lies ``shift`` metres along up from the camera guess."""
    guess = estimate_floor_height(rig)
    config = SyntheticConfig(scene=SceneConfig(floor_height=guess + shift))
    return simulate(rig, num_people=4, num_frames=60, config=config, seed=seed)[0], guess


@pytest.mark.slow  # compiles the geometric pipeline and robust triangulation (about 10 s)
@pytest.mark.parametrize(
    ("preset", "shift"), [("panoptic5", 0.0), ("panoptic5", -0.5), ("arplab6", 0.4)]
)
def test_the_floor_of_a_synthetic_recording_is_recovered(preset, shift):
    rig = load_rig(preset)
    scene, guess = _scene(rig, shift, seed=[4, round(10 * abs(shift))])
    truth = scene.geometry.floor_height
    est = estimate_floor_from_detections(rig, scene.recording.detections)
    assert abs(truth - (guess + shift)) < 1e-6
    # Within 3 cm, whatever the camera-based guess says (0.4-0.5 m off in two of the cases).
    assert abs(est.height - truth) < 0.03, (est, truth)
    assert 0 < est.spread < 0.05 and est.num_samples >= 30 and est.num_frames == 60
    np.testing.assert_allclose(est.up, scene.geometry.up, atol=1e-9)
    # Fewer frames than people-frames needed: a clear refusal, not a guess.
    few = Detections(*(np.asarray(a)[:3] for a in scene.recording.detections))
    with pytest.raises(InputError, match="cannot measure the floor"):
        estimate_floor_from_detections(rig, few, min_samples=100)


def test_refuses_without_three_cameras_or_ankles():
    rig = load_rig("arplab6")
    two = rig.select(list(rig.names[:2]))
    det = Detections(
        np.zeros((5, 2, 1, 18, 2), np.float32),
        np.zeros((5, 2, 1, 18), np.float32),
        np.zeros((5, 2), np.int32),
    )
    with pytest.raises(InputError, match="only 0 person-frames"):
        estimate_floor_from_detections(two, det)
    upper_body = Layout(name="upper", keypoints=("nose", "neck"), bones=(), flip=(0, 1))
    with pytest.raises(InputError, match="no ankle"):
        estimate_floor_from_detections(rig, det, layout=upper_body)


@pytest.mark.slow  # compiles the geometric pipeline and robust triangulation (about 10 s)
@pytest.mark.parametrize(("preset", "shift"), [("panoptic5", 0.0), ("arplab6", -0.4)])
def test_hidden_feet_fall_back_to_the_upper_body(preset, shift):
    """Legs hidden (an operating room's tables): the shoulders and the standing-height prior."""
    rig = load_rig(preset)
    scene, guess = _scene(rig, shift, seed=[7, round(10 * abs(shift))])
    truth = scene.geometry.floor_height
    det = scene.recording.detections
    lay = get_layout("coco18")
    legs = [lay.index(f"{s}_{k}") for s in "lr" for k in ("knee", "ankle")]
    score = np.asarray(det.score).copy()
    score[..., legs] = 0.0
    hidden = Detections(det.xy, score, det.count)
    est = estimate_floor_from_detections(rig, hidden)
    assert est.basis == "upper_body" and est.num_samples >= 30
    # The prior is a standing adult's (1.39 m); the simulator's people walk, crouch and bend,
    # carrying their shoulders 1.33 m above the floor on median: the estimate is up to 10 cm low.
    assert -0.12 < est.height - truth < 0.02, (est, truth)
    assert 0 < est.spread < 0.15
    assert "standing-height prior" in est.describe()
    # Asked for the feet only: a refusal naming them, not the fallback.
    with pytest.raises(InputError, match="foot keypoint"):
        estimate_floor_from_detections(rig, hidden, basis="feet")
    # With the feet seen, auto measures the feet, and the upper body agrees with them.
    feet = estimate_floor_from_detections(rig, det)
    upper = estimate_floor_from_detections(rig, det, basis="upper_body")
    assert feet.basis == "feet" and upper.basis == "upper_body"
    assert -0.12 < upper.height - feet.height < 0.02
    with pytest.raises(InputError, match="basis"):
        estimate_floor_from_detections(rig, det, basis="head")


def test_shortest_half_ignores_a_second_cluster_the_median_follows():
    rng = np.random.default_rng(0)
    floor = rng.normal(0.0, 0.01, 60)
    table = rng.normal(0.76, 0.01, 40)  # a false skeleton's feet on a table
    heights = np.concatenate([floor, table])
    location, spread = shortest_half(heights)
    assert abs(location) < 0.01 and 0.003 < spread < 0.02
    assert abs(location) < np.median(heights)  # the median is pulled towards the table


@pytest.mark.slow  # compiles the geometric pipeline and robust triangulation (about 10 s)
def test_without_an_up_in_the_calibration_rolled_cameras_take_it_from_the_people():
    rig = load_rig("panoptic5")
    true_up = np.asarray(up_vector(rig))
    # Cameras rolled by 15-40 degrees: the cameras' guess of up (no roll assumed) is far off.
    R = np.asarray(rig.R, np.float64)
    centres = np.asarray(camera_centres(rig), np.float64)
    rolled_R = []
    for c, d in enumerate((25.0, -30.0, 40.0, 15.0, -35.0)):
        a = np.radians(d)
        roll = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        rolled_R.append(roll @ R[c])
    rolled_R = np.array(rolled_R)
    rolled_t = -np.einsum("cij,cj->ci", rolled_R, centres)
    rolled = make_rig(
        np.asarray(rig.K), np.asarray(rig.dist), rolled_R, rolled_t, np.asarray(rig.size), rig.names
    )
    assert rolled.up is None
    guess_off = np.degrees(np.arccos(np.clip(np.dot(up_vector(rolled), true_up), -1, 1)))
    assert guess_off > 10.0
    config = SyntheticConfig(scene=SceneConfig(up=tuple(true_up)))
    scene = simulate(rolled, num_people=4, num_frames=60, config=config, seed=[9])[0]
    est = estimate_floor_from_detections(rolled, scene.recording.detections)
    assert est.up_source == "people" and est.camera_up_deg > 8.0, (est, guess_off)
    angle = np.degrees(np.arccos(np.clip(np.dot(est.up, true_up), -1, 1)))
    assert angle < 8.0, angle  # the simulated people lean: their torsos' mean is a few degrees off
    assert abs(est.height - scene.geometry.floor_height) < 0.1
    assert "measured from the people's torsos" in est.describe()
    # Level cameras without an up: the cameras' guess stands (the people agree within 8 degrees).
    plain = simulate(rig, num_people=4, num_frames=60, seed=[9])[0]
    level = estimate_floor_from_detections(
        dataclasses.replace(rig, up=None), plain.recording.detections
    )
    assert level.up_source == "cameras" and level.camera_up_deg < 8.0
    assert estimate_floor_from_detections(rig, plain.recording.detections).up_source == (
        "calibration"
    )
