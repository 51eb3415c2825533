"""The main job runs end to end (in its seconds-long smoke mode) and writes what it promises."""

from __future__ import annotations

import json

import pytest

from experiments.run import main

pytestmark = pytest.mark.slow  # the main job end to end, twice (minutes)


def test_default_experiment_smoke(tmp_path):
    """Run as a user would, its progress and tables written to a log file (not a terminal): the
    log stays readable (no carriage-return updates, under 200 lines)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    out, log = tmp_path / "run", tmp_path / "run.log"
    root = Path(__file__).resolve().parents[1]
    with log.open("w") as f:
        subprocess.run(
            [sys.executable, "-m", "experiments.run", "--smoke", "--out", str(out)],
            cwd=root,
            env={**os.environ, "PYTHONPATH": str(root)},
            stdout=f,
            stderr=subprocess.STDOUT,
            check=True,
            timeout=1200,
        )
    text = log.read_text()
    assert "\r" not in text and len(text.splitlines()) < 200, len(text.splitlines())
    assert "matcher:" in text and "left" in text  # progress, a line every few seconds
    assert "Table 3" in text and "Table 6" in text and "paper" in text.lower()
    assert "## Validation scenes" in (out / "tables.md").read_text()
    m = json.loads((out / "metrics.json").read_text())
    assert m["experiment"] == "paper-panoptic" and m["scale"] == "smoke" and m["seeds"] == [0]
    (res,) = m["runs"]
    assert set(res["matching"]) == {"validation", "test"}
    for split, rows in res["matching"].items():
        assert set(rows) == {"2", "3", "5"}
        for n, row in rows.items():
            for method in ("gat", "gat_chosen", "geometric"):
                scores = {
                    "ari",
                    "homogeneity",
                    "completeness",
                    "v_measure",
                    "pooled_ari",
                    "pooled_v_measure",
                }
                assert scores | {"t_pp_ms"} <= set(row[method])
            # Both matchers' settings are the ones chosen on dev frames (never on the scenes).
            fit = res["training"][f"matcher-{n}"]
            assert row["gat_chosen"]["threshold"] == fit["threshold"]
            assert row["geometric"]["cutoff_px"] == fit["geometric_cutoff_px"]
            # Threshold diagnostics are computed on validation scenes only.
            assert ("ari_by_threshold" in row["gat"]) == (split == "validation")
    for n in ("2", "3", "5"):
        fit = res["training"][f"matcher-{n}"]
        assert 0 < fit["threshold"] < 1
        assert fit["dev_ari_by_threshold"][str(fit["threshold"])] == max(
            fit["dev_ari_by_threshold"].values()
        )
        assert fit["dev_ari_by_cutoff_px"][str(fit["geometric_cutoff_px"])] == max(
            fit["dev_ari_by_cutoff_px"].values()
        )
    # The geometric baseline needs no training: even here it groups nearly perfectly.
    assert res["matching"]["test"]["5"]["geometric"]["ari"] > 0.9
    for split in ("validation", "test"):
        assert set(res["pose"][split]) == {"detected", "projected", "average"}
        for rows in res["pose"][split].values():
            assert set(rows) == {
                "pipeline",
                "true_groups",
                "geometric_proposals",
                "gat_proposals_at_half",
            }
            assert {"ours", "centroid", "dlt", "ours_on_dlt_keypoints"} <= set(rows["true_groups"])
            assert set(rows["true_groups"]["ours"]["pcp_by_limb"]) == {
                "head",
                "torso",
                "upper_arm",
                "lower_arm",
                "upper_leg",
                "lower_leg",
            }
    text = (out / "tables.md").read_text()
    assert text.index("## Test scenes") < text.index("## Validation scenes")
    assert (out / "tables.md").read_text().startswith("# paper-panoptic")
    figures = sorted(p.name for p in (out / "figures").iterdir())
    assert "training_curves.png" in figures and any(f.startswith("frame_") for f in figures)


def test_synthetic_summary_smoke(tmp_path):
    out = tmp_path / "summary"
    assert main(["--only", "synthetic-summary", "--smoke", "--out", str(out), "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["runs"][0]["variants"]) == {"detected", "projected", "average"}
    assert (out / "recording.json").exists()


def test_arp_experiment_smoke_and_tables_from_saved_runs(tmp_path, capsys):
    out = tmp_path / "arp"
    # --experiment: the deprecated spelling of --only, still working.
    with pytest.warns(FutureWarning, match="--experiment is deprecated; use --only paper-arp"):
        assert (
            main(["--experiment", "paper-arp", "--smoke", "--out", str(out), "--no-progress"]) == 0
        )
    text = capsys.readouterr().out
    assert "Table 4" in text and "Table 7" in text
    (res,) = json.loads((out / "metrics.json").read_text())["runs"]
    for key in ("camera_subsets", "camera_subsets_proposals"):
        assert set(res[key]) == {"M_1/6", "M_2/6", "M_6/6", "M_2/2"}
        for model in res[key].values():
            assert {"people", "reprojection", "mpjpe_mm", "pcp"} <= set(model)
    assert set(res["matching"]) == {"validation", "test"}
    # The tables again, from the saved seeds (a stopped multi-seed run keeps what it finished).
    again = tmp_path / "again"
    argv = [
        "--only",
        "paper-arp",
        "--out",
        str(again),
        "--tables-from",
        str(out / "runs_partial.json"),
    ]
    assert main(argv) == 0
    first = (out / "tables.md").read_text().split("\n", 3)[3]
    assert (again / "tables.md").read_text().split("\n", 3)[3] == first
    # A second part of the same table (as `--seed 1 --scenes-seed 0` writes it: the same scenes),
    # joined with the first; a part measured on other scenes is refused.
    (run,) = json.loads((out / "runs_partial.json").read_text())
    assert run["scenes_seed"] == 0
    part, other = tmp_path / "part2.json", tmp_path / "other.json"
    part.write_text(json.dumps([run | {"seed": 1}]))
    other.write_text(json.dumps([run | {"seed": 1, "scenes_seed": 1}]))
    joined = tmp_path / "joined"
    argv = ["--only", "paper-arp", "--out", str(joined), "--tables-from"]
    assert main([*argv, str(out / "runs_partial.json"), str(part)]) == 0
    text = (joined / "tables.md").read_text()
    assert "over 2 training seeds (0, 1)" in text and "both from seed 0" in text
    with pytest.raises(SystemExit):
        main([*argv, str(out / "runs_partial.json"), str(other)])
    assert "differ in scenes_seed ([0, 1])" in capsys.readouterr().err
    # So is a part trained on another floor; the joined tables say which floor they trained on.
    assert run["train_floor_offset_m"] == 0.0 and run["train_floor_jitter_m"] == 0.0
    other.write_text(json.dumps([run | {"seed": 1, "train_floor_offset_m": -0.6}]))
    with pytest.raises(SystemExit):
        main([*argv, str(out / "runs_partial.json"), str(other)])
    assert "differ in train_floor_offset_m ([-0.6, 0.0])" in capsys.readouterr().err
    both = [run | {"train_floor_offset_m": -0.6}, run | {"seed": 1, "train_floor_offset_m": -0.6}]
    other.write_text(json.dumps(both))
    assert main([*argv, str(other)]) == 0
    assert "on a floor -0.6 m from the rig's" in (joined / "tables.md").read_text()
    # A record older than the floor fields needs them said (they were not recorded).
    old = {k: v for k, v in run.items() if not k.startswith("train_floor")}
    other.write_text(json.dumps([old]))
    with pytest.raises(SystemExit):
        main([*argv, str(other)])
    assert "say it with --train-floor-jitter" in capsys.readouterr().err
    argv += [str(other), "--train-floor-jitter", "0", "--train-floor-offset", "0"]
    assert main(argv) == 0


def test_training_recordings_take_the_given_detector():
    """`make_data(detector=...)` (what `real_models.synthetic_models` trains on with a fitted detector): the same
    people and motion, seen by the given detector instead of the default one."""
    import dataclasses

    import numpy as np

    from experiments.config import SCALES
    from experiments.data import make_data
    from mvpose_jax.data.calibration import load_preset
    from mvpose_jax.synthetic import DetectorConfig

    rig = load_preset("panoptic5")
    blind = dataclasses.replace(DetectorConfig(), miss_rate=1.0, false_positive_rate=0.0)
    default = make_data(rig, {}, SCALES["smoke"], 0, False)
    given = make_data(rig, {}, SCALES["smoke"], 0, False, detector=blind)
    for a, b in zip(default.train + default.dev, given.train + given.dev, strict=True):
        np.testing.assert_array_equal(a.ground_truth.xyz, b.ground_truth.xyz)
        assert int(np.asarray(b.detections.count).sum()) == 0
    assert sum(int(np.asarray(r.detections.count).sum()) for r in default.train) > 0


def test_score_separation_auc_is_scikit_learns():
    import numpy as np
    from sklearn.metrics import roc_auc_score

    from experiments.detector_like import score_separation

    rng = np.random.default_rng(3)
    same = rng.random(400) < 0.3
    scores = np.round(rng.random(400) * 0.7 + 0.3 * same, 2)  # rounded: ties across kinds
    got = score_separation(scores, same, 0.5)
    assert got["auc"] == pytest.approx(roc_auc_score(same, scores), abs=1e-12)
    assert got["same_person_pairs"] == same.sum() and got["pairs"] == 400
    assert got["same_below_threshold"] == pytest.approx((scores[same] < 0.5).mean())
    assert got["other_above_threshold"] == pytest.approx((scores[~same] >= 0.5).mean())


def test_seed_table_gives_each_seed_and_the_mean_and_range():
    from experiments.real_adapted import seed_lines

    records = {"0": {"a": 1.0, "b": 0.5}, "1": {"a": 4.0, "b": 0.25}, "2": {"a": 2.5, "b": 0.75}}
    columns = (("A", lambda r: r["a"], ".1f"), ("B", lambda r: r["b"], ".3f"))
    lines = seed_lines(records, columns)
    assert lines[0] == "| seed | A | B |"
    assert lines[2:5] == ["| 0 | 1.0 | 0.500 |", "| 1 | 4.0 | 0.250 |", "| 2 | 2.5 | 0.750 |"]
    assert lines[5] == "| mean (min-max) | 2.5 (1.0-4.0) | 0.500 (0.250-0.750) |"
    assert len(seed_lines({"0": records["0"]}, columns)) == 3  # one seed: no summary row
