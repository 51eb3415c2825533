"""floor.py: the floor measured from the people against the synthetic recordings' true floor."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_jax.data.calibration import load_rig
from mvpose_jax.errors import InputError
from mvpose_jax.floor import estimate_floor_from_detections
from mvpose_jax.skeletons import Detections, Layout
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
