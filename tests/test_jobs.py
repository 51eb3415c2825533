"""The jobs layer called directly, without the command line (what experiments and benchmarks
do): each job's result against the library functions it stands for."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_jax.data import load_recording, save_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.recording import recording_fps
from mvpose_jax.errors import InputError
from mvpose_jax.jobs.common import DetectionsSource, RigSource, load_detections
from mvpose_jax.synthetic import generate_recording


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    rec = generate_recording(load_rig("panoptic5"), num_people=2, num_frames=5, seed=3)
    path = tmp_path_factory.mktemp("jobs") / "scene.npz"
    save_recording(rec, path)
    return rec, path


def test_convert_job_writes_what_the_reader_reads_back(scene, tmp_path):
    from mvpose_jax.jobs.convert import ConvertConfig, convert

    rec, path = scene
    cameras = tuple(reversed(rec.cameras[:2]))
    done = convert(ConvertConfig(str(path), str(tmp_path / "two.json"), cameras=cameras))
    back = load_recording(tmp_path / "two.json")
    assert done == (rec.num_frames, cameras, rec.layout)
    assert tuple(back.cameras) == cameras
    index = [list(rec.cameras).index(c) for c in cameras]
    np.testing.assert_allclose(
        back.detections.xy, np.asarray(rec.detections.xy)[:, index], atol=1e-3
    )


def test_detections_source_selects_cameras_while_reading(scene):
    rec, path = scene
    source = DetectionsSource(str(path), cameras=(rec.cameras[3], rec.cameras[1]))
    got, rig = load_detections(source, RigSource("panoptic5").load())
    assert tuple(got.cameras) == tuple(rig.names) == (rec.cameras[3], rec.cameras[1])


def test_generate_job_refuses_a_negative_floor_jitter(tmp_path):
    from mvpose_jax.jobs.generate import GenerateConfig, floor_jitter

    config = GenerateConfig(RigSource("panoptic5"), str(tmp_path / "x.npz"), floor_jitter=-0.1)
    with pytest.raises(InputError, match="--floor-jitter"):
        floor_jitter(config)
    singles = GenerateConfig(RigSource("panoptic5"), str(tmp_path), single_person_recordings=2)
    assert floor_jitter(singles) == 0.3 and floor_jitter(GenerateConfig(singles.rig, "a")) == 0


def test_recording_fps_is_the_median_step():
    assert recording_fps(np.arange(10) / 25.0) == pytest.approx(25.0)
    assert recording_fps(None) == 30.0 and recording_fps([1.0, 1.0]) == 30.0


def test_matcher_adapt_steps_is_the_adaptations_default():
    from mvpose_jax.adapt import MatcherAdaptConfig
    from mvpose_jax.jobs.adapt import MATCHER_ADAPT_STEPS

    assert MatcherAdaptConfig().max_steps == MATCHER_ADAPT_STEPS
