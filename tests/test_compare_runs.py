"""`experiments.compare_runs`: two runs' quality values compared within their seed spread, on
hand-made records whose means, sds and verdicts are known in closed form."""

from __future__ import annotations

import json
import math

import pytest

from experiments import compare_runs


def _run(seed: int, ari: float, mpjpe: float, pcp_true: float = 88.5, ms: float = 1.0) -> dict:
    return {
        "seed": seed,
        "scenes_seed": 0,
        "train_floor_jitter_m": 0.0,
        "train_floor_offset_m": 0.0,
        "matching": {"test": {"5": {"gat_chosen": {"ari": ari, "t_pp_ms": ms}}}},
        "pose": {
            "test": {
                "detected": {
                    "pipeline": {"ours": {"mpjpe_mm": mpjpe, "pcp_by_limb": {"head": 1.0}}},
                    "true_groups": {"dlt": {"pcp": pcp_true}},
                }
            }
        },
        "training": {"matcher-5": {"best_val_loss": 0.01}},
    }


def _save(tmp_path, name, runs):
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps({"runs": runs}))
    return path


def test_means_sds_and_verdicts_are_the_closed_form_ones():
    reference = [_run(0, 0.990, 45.0), _run(1, 0.994, 46.0), _run(2, 0.992, 47.0)]
    candidate = [_run(0, 0.980, 46.0, ms=9.0), _run(1, 0.982, 47.0), _run(2, 0.984, 48.0)]
    rows = {r["value"]: r for r in compare_runs.compare(reference, candidate)}
    # Timings, per-limb sweeps and training records are not quality values.
    assert set(rows) == {
        "matching/test/5/gat_chosen/ari",
        "pose/test/detected/pipeline/ours/mpjpe_mm",
        "pose/test/detected/true_groups/dlt/pcp",
    }
    ari = rows["matching/test/5/gat_chosen/ari"]
    assert ari["reference"] == pytest.approx(0.992)
    assert ari["reference_sd"] == pytest.approx(0.002)
    assert ari["candidate_sd"] == pytest.approx(0.002)
    assert ari["allowed"] == pytest.approx(2 * math.sqrt(2 * 0.002**2 / 3))
    assert ari["difference"] == pytest.approx(-0.010)
    assert not ari["within"] and not ari["within_one_sd"]
    mpjpe = rows["pose/test/detected/pipeline/ours/mpjpe_mm"]
    assert mpjpe["difference"] == pytest.approx(1.0)
    assert mpjpe["allowed"] == pytest.approx(2 * math.sqrt(2 / 3))  # sd 1 on both sides
    assert mpjpe["within"] and mpjpe["within_one_sd"]
    # No seed moves it: equal is within, anything beyond rounding is not.
    assert rows["pose/test/detected/true_groups/dlt/pcp"]["within"]
    moved = compare_runs.compare(reference, [_run(s, 0.99, 46.0, pcp_true=88.7) for s in range(3)])
    assert not {r["value"]: r for r in moved}["pose/test/detected/true_groups/dlt/pcp"]["within"]


def test_command_writes_its_table_and_refuses_runs_on_other_scenes(tmp_path, capsys):
    ref = _save(tmp_path, "ref", [_run(0, 0.990, 45.0), _run(1, 0.994, 46.0)])
    cand = _save(tmp_path, "cand", [_run(0, 0.991, 45.5), _run(1, 0.993, 45.9)])
    out = tmp_path / "out"
    assert (
        compare_runs.main(["--reference", str(ref), "--candidate", str(cand), "--out", str(out)])
        == 0
    )
    md = (out / "compare.md").read_text()
    assert "| test | 3 | 3 | 0 | 3 |" in md
    assert "## Outside the spread (0)" in md
    assert "5-view GAT ARI, dev threshold" in md
    saved = json.loads((out / "compare.json").read_text())["rows"]
    assert len(saved) == 3 and all(r["within"] for r in saved)

    other = _run(2, 0.99, 45.0) | {"scenes_seed": 1}
    elsewhere = _save(tmp_path, "elsewhere", [other])
    with pytest.raises(SystemExit):
        compare_runs.main(["--reference", str(ref), "--candidate", str(elsewhere)])
    assert "settings" in capsys.readouterr().err
