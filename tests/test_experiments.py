"""The main job runs end to end (in its seconds-long smoke mode) and writes what it promises."""

from __future__ import annotations

import json

from experiments.run import main


def test_default_experiment_smoke(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["--smoke", "--out", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "Table 3" in text and "Table 6" in text and "paper" in text.lower()
    m = json.loads((out / "metrics.json").read_text())
    assert m["experiment"] == "paper-panoptic" and m["scale"] == "smoke"
    res = m["results"]
    assert set(res["matching"]) == {"2", "3", "5"}
    for row in res["matching"].values():
        for method in ("gat", "gat_chosen", "geometric"):
            assert {"ari", "homogeneity", "completeness", "v_measure", "t_pp_ms"} <= set(row[method])
        # The threshold is chosen on dev frames, from the grid, by their best ARI.
        th = row["gat_chosen"]["threshold"]
        assert 0 < th < 1
    for n in ("2", "3", "5"):
        fit = res["training"][f"matcher-{n}"]
        assert fit["threshold"] == res["matching"][n]["gat_chosen"]["threshold"]
        assert fit["dev_ari_by_threshold"][str(fit["threshold"])] == max(fit["dev_ari_by_threshold"].values())
    # The geometric baseline needs no training: even here it groups nearly perfectly.
    assert res["matching"]["5"]["geometric"]["ari"] > 0.9
    assert set(res["pose"]) == {"detected", "projected", "average"}
    for rows in res["pose"].values():
        assert set(rows) == {"pipeline", "true_groups", "geometric_proposals", "gat_proposals_at_half"}
        assert {"ours", "centroid", "dlt", "ours_on_dlt_keypoints"} <= set(rows["true_groups"])
    assert (out / "tables.md").read_text().startswith("# paper-panoptic")
    figures = sorted(p.name for p in (out / "figures").iterdir())
    assert "training_curves.png" in figures and any(f.startswith("frame_") for f in figures)


def test_synthetic_summary_smoke(tmp_path):
    out = tmp_path / "summary"
    assert main(["--experiment", "synthetic-summary", "--smoke", "--out", str(out), "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["results"]["variants"]) == {"detected", "projected", "average"}
    assert (out / "recording.json").exists()
