"""stages.py: the registries of the pipeline's stages, and a new method plugged in by one line."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mvpose_jax import stages
from mvpose_jax.cli import main
from mvpose_jax.data import save_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.data.poses import load_poses
from mvpose_jax.inference import PipelineConfig, run_pipeline
from mvpose_jax.jobs.infer import read_run_record
from mvpose_jax.lifting import LiftingConfig, lift_dlt
from mvpose_jax.synthetic import generate_recording

SHIFT_M = 0.25


def _raised_dlt(rig, xy, score, config: LiftingConfig, **kwargs):
    """A toy 3D method: DLT, every keypoint moved by SHIFT_M along each axis."""
    poses, confidence = lift_dlt(rig, xy, score, config, **kwargs)
    xyz = np.where(poses.keypoint_valid[..., None], poses.xyz + SHIFT_M, 0.0)
    return poses._replace(xyz=xyz.astype(np.float32)), confidence


@pytest.fixture
def toy_method():
    stages.register("lifting", stages.Stage("raised-dlt", _raised_dlt, "DLT, moved (a test)"))
    yield "raised-dlt"
    stages.unregister("lifting", "raised-dlt")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    rec = generate_recording(load_rig("panoptic5"), num_people=2, num_frames=6, seed=3)
    path = tmp_path_factory.mktemp("scene") / "scene.npz"
    save_recording(rec, path)
    return rec, path


def test_a_registered_method_runs_through_infer(toy_method, scene, tmp_path, capsys):
    _, path = scene
    args = ["infer", "--rig", "panoptic5", "--detections", str(path), "--no-track"]
    assert main([*args, "--method", "dlt", "--out", str(tmp_path / "dlt")]) == 0
    assert main([*args, "--method", toy_method, "--out", str(tmp_path / "toy")]) == 0
    dlt, toy = load_poses(tmp_path / "dlt"), load_poses(tmp_path / "toy")
    # The run record says which method made the results.
    _, config = read_run_record(tmp_path / "toy")
    assert config.lifting.method == toy_method and config.tracking is None
    np.testing.assert_array_equal(toy.poses.valid, dlt.poses.valid)
    assert toy.poses.keypoint_valid.any()
    kv = dlt.poses.keypoint_valid
    np.testing.assert_allclose(toy.poses.xyz[kv], dlt.poses.xyz[kv] + SHIFT_M, atol=1e-6)
    # The CLI's choices and the help read the registry.
    with pytest.raises(SystemExit):
        main(["infer", "--help"])
    assert toy_method in capsys.readouterr().out


def test_a_registered_method_runs_through_the_library(toy_method, scene):
    rec, _ = scene
    config = PipelineConfig(lifting=LiftingConfig(method=toy_method))
    toy = run_pipeline(load_rig("panoptic5"), rec.detections, config)
    dlt = run_pipeline(load_rig("panoptic5"), rec.detections, method="dlt")
    kv = dlt.poses.keypoint_valid
    np.testing.assert_allclose(toy.poses.xyz[kv], dlt.poses.xyz[kv] + SHIFT_M, atol=1e-6)


def test_unknown_names_list_the_known_ones():
    with pytest.raises(ValueError, match=r"method must be one of \('mlp', 'blend', 'dlt'"):
        stages.lookup("lifting", "nope", what="method")
    with pytest.raises(ValueError, match="registered already"):
        stages.register("lifting", stages.Stage("dlt", lift_dlt, "again"))


def test_names_filter_by_what_a_stage_needs():
    assert stages.names("lifting", needs_estimator=True) == ("mlp", "blend")
    assert stages.names("lifting", needs_estimator=False) == (
        "dlt",
        "centroid",
        "robust",
        "confident",
    )
    assert stages.names("proposals", needs_matcher=False) == ("epipolar",)
    assert stages.names("filters", streaming=True) == ("one-euro",)


@pytest.mark.parametrize("kind", ["proposals", "lifting", "filters"])
def test_every_registered_target_exists(kind):
    for name in stages.names(kind):
        assert callable(stages.lookup(kind, name).function()), name


def test_pipeline_config_round_trips_through_its_dict():
    from mvpose_jax.inference import FilterConfig
    from mvpose_jax.matching import MatchingConfig
    from mvpose_jax.proposals import CombinedConfig
    from mvpose_jax.smoothing import OneEuroConfig
    from mvpose_jax.tracking import TrackingConfig

    config = PipelineConfig(
        matching=MatchingConfig("combined", 0.3, 3, 25.0, CombinedConfig(threshold=0.25)),
        lifting=LiftingConfig("robust", outlier_px=20.0),
        tracking=TrackingConfig(max_gap_s=2.0),
        filtering=FilterConfig("one-euro", OneEuroConfig(min_cutoff_hz=0.5)),
        chunk_frames=64,
    )
    assert PipelineConfig.from_dict(config.to_dict()) == config
    assert PipelineConfig.from_dict(PipelineConfig().to_dict()) == PipelineConfig()
    # The shorthand by the stages' own names builds the same nested config.
    flat = PipelineConfig.of(method="robust", threshold=0.3, min_views=3, chunk_frames=64)
    assert flat == dataclasses.replace(
        PipelineConfig(),
        matching=MatchingConfig(threshold=0.3, min_views=3),
        lifting=LiftingConfig("robust"),
        chunk_frames=64,
    )


def test_the_architecture_page_lists_every_stage():
    from pathlib import Path

    page = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
    assert stages.markdown_table() in page.read_text(), (
        "docs/architecture.md's stage table is out of date: paste "
        "`python -c 'from mvpose_jax import stages; print(stages.markdown_table())'`"
    )
