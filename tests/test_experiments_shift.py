"""The domain-shift experiment end to end (smoke scale), apart from the other experiments so
that a parallel run (`pytest -n auto`, one file per worker) runs it beside them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.run import main

pytestmark = pytest.mark.slow  # trains both models, then four shifts on both splits (minutes)

# The unshifted reference, a detector shift, a world shift and a rig shift: every kind of row the
# tables have (each shift's generator is tested in test_synthetic).
SMOKE_SHIFTS = ("none", "part-mixing", "floor+0.6", "calibration")


def test_domain_shift_smoke_and_tables_from_saved_runs(tmp_path, capsys):
    from experiments.config import SCALES
    from experiments.data import make_scenes, make_shifted_scenes
    from experiments.domain_shift import ADAPT_PIPELINES, SHIFT_PIPELINES
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.synthetic import SHIFTS

    out = tmp_path / "shift"
    argv = ["--only", "domain-shift", "--smoke", "--out", str(out), "--no-progress"]
    assert main([*argv, "--shifts", ",".join(SMOKE_SHIFTS)]) == 0
    text = capsys.readouterr().out
    assert "Δ ARI" in text and "floor+0.6" in text and "calibration" in text
    assert "combined + blend PCP" in text and "Δ true robust" in text
    assert "Matcher adapted to each shift's own test detections" in text
    (res,) = json.loads((out / "metrics.json").read_text())["runs"]
    # The combined matcher's settings, chosen on composed dev frames, are recorded with the GAT's.
    combined = res["training"]["matcher-5"]["combined"]
    assert combined["epipolar_cutoff_px"] == res["training"]["matcher-5"]["geometric_cutoff_px"]
    ari = res["training"]["matcher-5"]["dev_ari_by_combined_threshold"]
    assert ari[str(combined["threshold"])] == max(ari.values())
    assert list(res["shifts"]) == [s for s in SHIFTS if s in SMOKE_SHIFTS]
    for splits in res["shifts"].values():
        assert set(splits) == {"validation", "test"}
        for row in splits.values():
            # The matcher adapted to the split (pseudo-labels: the combined proposals).
            assert set(row["matching"]) == {
                "combined",
                "gat",
                "epipolar",
                "combined_adapted",
                "gat_adapted",
            }
            assert row["matcher_adapt"]["steps"] == SCALES["smoke"].matcher_adapt.max_steps
            assert set(row["pose"]) == set(SHIFT_PIPELINES) | set(ADAPT_PIPELINES)
            for metrics in row["pose"].values():
                assert 0 <= metrics["pcp"] <= 100 and 0 <= metrics["completeness"] <= 100
            for key in ("combined_mlp", "combined_blend", "combined_blend_adapted"):
                assert "mpjpe_on_epipolar_robust_keypoints_mm" in row["pose"][key]
            # On robust triangulation's keypoints the blend IS robust triangulation.
            for g in ("combined", "gat", "epipolar", "true"):
                blend, robust = row["pose"][f"{g}_blend"], row["pose"][f"{g}_robust"]
                if robust["completeness"] > 0:
                    assert blend["mpjpe_on_robust_keypoints_mm"] == pytest.approx(
                        robust["mpjpe_mm"], abs=2e-3
                    )
    # The unshifted reference is exactly paper-panoptic's scenes.
    rig = load_rig("panoptic5")
    plain = make_scenes(rig, SCALES["smoke"], 0)
    none = make_shifted_scenes(rig, SCALES["smoke"], 0, SHIFTS["none"])
    for split in plain:
        for a, b in zip(plain[split], none[split], strict=True):
            np.testing.assert_array_equal(a.detections.xy, b.detections.xy)
            np.testing.assert_array_equal(a.detections.score, b.detections.score)
    # Tables again from the saved seed.
    again = tmp_path / "again"
    argv = ["--only", "domain-shift", "--out", str(again)]
    assert main([*argv, "--tables-from", str(out / "runs_partial.json")]) == 0
    first = (out / "tables.md").read_text().split("\n", 3)[3]
    assert (again / "tables.md").read_text().split("\n", 3)[3] == first
    # experiments.combined_matching prints the same tables from the same runs.
    from experiments import combined_matching

    capsys.readouterr()
    assert combined_matching.main(["--tables-from", str(out / "runs_partial.json")]) == 0
    printed = capsys.readouterr().out.strip().splitlines()
    assert "Δ ARI" in "\n".join(printed)
    assert all(line in first for line in printed if line.startswith("|"))
    with pytest.raises(SystemExit):
        main(["--only", "domain-shift", "--smoke", "--shifts", "floor+0.7"])
    assert "no shift named ['floor+0.7']" in capsys.readouterr().err
