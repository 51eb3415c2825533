"""The detector fitted without labels recovers a simulated detector's known parameters."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mvpose_jax.cli import main
from mvpose_jax.data import load_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.detector_fit import fit_detector
from mvpose_jax.errors import InputError
from mvpose_jax.jobs.common import RigSource
from mvpose_jax.jobs.generate import GenerateConfig, synthetic_config
from mvpose_jax.skeletons import Detections
from mvpose_jax.synthetic import DetectorConfig, SyntheticConfig, generate_recording

TRUTH = DetectorConfig(
    noise_relative=0.01,
    swap_rate=0.1,
    false_positive_rate=0.3,
    keypoint_drop_rate=0.1,
    miss_rate=0.05,
    limb_mix_rate=0.1,
    score_beta=(5.0, 2.0),
    occluded_score_factor=1.0,
)
# Stated tolerances (absolute unless relative), from what the residuals can tell: occluded
# keypoints (noisier, dropped more often) are only partly recognised, and swaps of a pair seen
# edge-on or mixed limbs of people side by side cannot be told.
TOLERANCE = {
    "noise_relative": 0.4,  # relative: 0.013 for 0.01, where 0.011 with noise alone (swaps
    # and mixes the fit cannot single out widen the residuals)
    "swap_rate": 0.04,
    "keypoint_drop_rate": 0.04,
    "miss_rate": 0.03,
    "false_positive_rate": 0.08,
    "limb_mix_rate": 0.04,
    "border_margin": 0.01,
}


@pytest.fixture(scope="module")
def fitted():
    rig = load_rig("panoptic5")
    rec = generate_recording(
        rig, num_people=4, num_frames=200, config=SyntheticConfig(detector=TRUTH), seed=3
    )
    return rec, fit_detector(rig, rec.detections)


@pytest.mark.slow  # runs the geometric pipeline
def test_fit_recovers_a_known_detector(fitted):
    _, fit = fitted
    defaults = DetectorConfig()
    for name, tol in TOLERANCE.items():
        field = fit.field(name)
        truth = getattr(TRUTH, name)
        assert field.fitted and field.samples >= 50, name
        bound = tol * truth if name == "noise_relative" else tol
        assert abs(field.value - truth) <= bound, (name, field.value, truth)
        if truth != getattr(defaults, name):  # told apart from the default
            assert abs(field.value - truth) < abs(field.value - getattr(defaults, name)), name
    assert fit.config.noise_relative == fit.field("noise_relative").value
    # Scores: a Beta whose mean is the true one's (5 / 7), scores reaching 1.
    a, b = fit.field("score_beta").value
    assert abs(a / (a + b) - 5 / 7) < 0.03
    assert abs(fit.field("score_max").value - 1.0) < 0.02
    # Per-keypoint noise: the truth has one scale for all; the fit is near 1 for each.
    scale = np.asarray(fit.field("keypoint_noise_scale").value)
    assert scale.shape == (18,) and np.all(np.abs(scale - 1) < 0.3)
    # What cannot be measured keeps the default and says so.
    for name in ("noise_tail_dof", "occluded_drop_rate"):
        field = fit.field(name)
        assert not field.fitted and field.samples == 0
        assert getattr(fit.config, name) == getattr(defaults, name)
    assert "not fitted, default kept" in "\n".join(fit.describe())
    assert fit.to_dict()["fields"]["swap_rate"]["samples"] == fit.field("swap_rate").samples


@pytest.mark.slow  # runs the geometric pipeline
def test_fit_tells_a_clean_detector_from_a_noisy_one(fitted):
    rig = load_rig("panoptic5")
    clean = dataclasses.replace(
        DetectorConfig(), noise_relative=0.002, swap_rate=0.0, false_positive_rate=0.0
    )
    rec = generate_recording(
        rig, num_people=3, num_frames=60, config=SyntheticConfig(detector=clean), seed=4
    )
    fit = fit_detector(rig, rec.detections)
    noisy = fitted[1]
    assert fit.field("noise_relative").value < 0.5 * noisy.field("noise_relative").value
    assert fit.field("swap_rate").value < 0.03
    assert fit.field("false_positive_rate").value < 0.05


def test_fit_refuses_what_it_cannot_compare():
    rig = load_rig("panoptic5")
    two = rig.select([0, 1])
    det = Detections(np.zeros((2, 2, 1, 18, 2)), np.zeros((2, 2, 1, 18)), np.zeros((2, 2), int))
    with pytest.raises(InputError, match="3\\+ cameras"):
        fit_detector(two, det)


def test_generate_takes_the_fitted_detector(fitted):
    _, fit = fitted
    config = GenerateConfig(RigSource("panoptic5"), "x.npz", rates={"miss_rate": 0.2})
    used = synthetic_config(config, None, fit).detector
    assert used == dataclasses.replace(fit.config, miss_rate=0.2)  # options still win
    assert synthetic_config(config).detector == dataclasses.replace(DetectorConfig(), miss_rate=0.2)


@pytest.mark.slow  # fits a detector through the CLI
def test_generate_detector_like_end_to_end(fitted, tmp_path, capsys):
    rec, _ = fitted
    from mvpose_jax.data import save_recording

    mine = tmp_path / "mine.npz"
    save_recording(rec, mine)
    out = tmp_path / "like.npz"
    argv = ["generate", "--rig", "panoptic5", "--people", "3", "--frames", "30"]
    assert (
        main([*argv, "--floor-height", "0", "--detector-like", str(mine), "--out", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    assert f"{mine}: detector fitted on" in printed and "swap_rate = " in printed
    assert len(load_recording(out).detections.count) == 30
    clean = ["--clean", "--detector-like", str(mine), "--out", str(tmp_path / "c.npz")]
    assert main([*argv, "--floor-height", "0", *clean]) == 2
    assert "not both" in capsys.readouterr().err


def test_experiment_tables_show_each_field_beside_the_default():
    from experiments.detector_fit import SYNTHETIC_TRUTH, TABLE_FIELDS, tables
    from mvpose_jax.detector_fit import DetectorFit, FittedField

    defaults = DetectorConfig()
    fields = tuple(
        FittedField(n, getattr(defaults, n), getattr(defaults, n), 0, False, "kept")
        for n in TABLE_FIELDS
    )
    swap = FittedField("swap_rate", 0.123, defaults.swap_rate, 77, True, "measured")
    fields = tuple(swap if f.name == "swap_rate" else f for f in fields)
    fit = DetectorFit(dataclasses.replace(defaults, swap_rate=0.123), fields, 5, 9)
    lines = tables({"mine": fit}, SYNTHETIC_TRUTH, fit)
    assert "| swap_rate | 0.02 | 0.123 (77) |" in lines
    assert "| swap_rate | 0.1 | 0.123 (77) | 0.02 |" in lines
    assert "| noise_relative | 0.004 | 0.004 (not fitted) |" in lines
