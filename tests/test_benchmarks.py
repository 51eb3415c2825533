"""The benchmark harness: its smoke run writes every section with sane numbers; targets; the
OpenCV comparison row agrees with the library's pairwise centroid."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import pipeline, report, scenes
from mvpose_jax import matching
from mvpose_jax.cameras import project_points
from mvpose_jax.inference import run_pipeline
from mvpose_jax.triangulate import triangulate_pairwise_centroid

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    # One process (no per-group subprocesses) keeps the smoke run short; the CLI path is the same.
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.run", "--smoke", "--in-process", "--out", str(out)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    return json.loads((out / "run.json").read_text()), (out / "run.md").read_text()


def _check_stats(s: dict):
    assert s["n"] >= 1
    assert 0 < s["p10"] <= s["median"] <= s["p90"]


@pytest.mark.slow  # the harness smoke run (a minute)
def test_smoke_run_has_every_section(smoke_run):
    run, md = smoke_run
    for key in (
        "machine",
        "git",
        "peaks",
        "latency",
        "offline",
        "training",
        "infer_memory",
        "adapt",
        "adapt_matcher",
        "pipeline",
        "memory",
        "targets",
        "profile",
    ):
        assert key in run, key
    assert not run["errors"]
    m = run["machine"]
    assert m["cpu_count"] >= 1 and m["jax"] and m["device"]
    assert len(run["git"]["commit"]) >= 7

    assert run["peaks"]["matmul_gflops"] > 0 and run["peaks"]["bandwidth_gbs"] > 0

    lat = run["latency"]
    assert lat["rows"]
    for row in lat["rows"]:
        for key in ("t_pp", "t_3Dg", "t_3Di", "t_total"):
            _check_stats(row[key])
    methods = {r["method"] for r in lat["triangulation"]}
    assert methods == {"dlt", "centroid", "opencv_centroid"}
    for r in lat["triangulation"]:
        _check_stats(r["t_tri"])
    assert all(v["median"] > 0 for v in lat["breakdown"]["parts_ms"].values())
    assert run["profile"]

    for entry in run["offline"]["models"].values():
        assert entry["stage2"]["frames_per_s"] > 0 and entry["stage2"]["people_per_s"] > 0
        assert entry["stage3"]["frames_per_s"] > 0 and entry["stage3"]["gflops"] > 0
        _check_stats(entry["single_person"]["predict_people_ms"])

    for size, e in run["training"]["estimator"].items():
        assert e["seed_samples_per_s"] > 0 and e["compile_seconds"] >= 0
        g = run["training"]["matcher"][size]
        assert g["graphs_per_s"] > 0 and g["budgets_compiled"] >= 1

    for row in run["tracking"]["rows"]:
        _check_stats(row["per_person_ms"])
        assert row["tracks"] == row["people"] and row["status"] in ("pass", "miss")

    assert set(run["memory"]) == {
        "peaks",
        "latency",
        "offline",
        "training",
        "tracking",
        "infer_memory",
        "adapt",
        "adapt_matcher",
        "pipeline",
    }
    assert all(r["maxrss_mb"] > 0 for r in run["memory"].values())

    rows = run["infer_memory"]["rows"]
    assert [r["frames"] for r in rows] == [24, 48]
    assert all(r["infer"]["exit"] == 0 and r["infer"]["maxrss_mb"] > 100 for r in rows)
    assert rows[0]["whole"]["maxrss_mb"] > 100 and "whole" not in rows[1]

    ad = run["adapt"]
    assert ad["frames"] == 50 and ad["steps"] == 2 and ad["people_heldout"] > 0
    assert 0 < ad["grouping_seconds"] < ad["seconds"] and ad["status"] in ("pass", "miss")
    am = run["adapt_matcher"]
    assert am["frames"] == 50 and am["steps"] == 2 and am["frames_heldout"] == 10
    assert am["seconds"] > 0 and am["status"] in ("pass", "miss")

    assert len(run["targets"]) == 5
    assert all(t["status"] in ("pass", "miss", "n/a") for t in run["targets"])
    for heading in (
        "## Targets",
        "## Per-frame latency",
        "## Offline throughput",
        "## Training throughput",
        "## Peak memory",
        "## Peak memory of infer against the recording's length",
        "## Adapting the matcher to a recording",
        "## Breakdown",
        "## Tracking",
        "## Adapting the estimator",
        "## Pipelines as users run them",
    ):
        assert heading in md


@pytest.mark.slow  # the harness smoke run (a minute)
def test_smoke_run_times_every_pipeline(smoke_run):
    run, _ = smoke_run
    result = run["pipeline"]
    records = result["records"]
    scenes_run = {r["scene"] for r in records}
    assert "panoptic5-2p" in scenes_run
    real = pipeline.REAL_DATA.is_dir()
    assert ("pose2sim-demo-2p" in scenes_run) == real
    assert real or any("missing" in n for n in result["notes"])
    # Every pipeline on the synthetic scene; the smoke tier's few on the real trial.
    timed = {"panoptic5-2p": pipeline.PIPELINES}
    timed["pose2sim-demo-2p"] = pipeline.PIPELINE_TIERS["smoke"].real_pipelines
    for scene in scenes_run:
        got = {(r["pipeline"], r["mode"]) for r in records if r["scene"] == scene}
        assert got == {(p, m) for p in timed[scene] for m in pipeline.MODES}
    for r in records:
        assert r["group"] == "pipeline"
        assert r["views"] == (5 if r["scene"].startswith("panoptic5") else 4)
        assert r["people"] > 0 and r["people_found"] >= 0
        assert r["ms_per_frame"] > 0
        stages = r["stages_ms"]
        assert set(stages) == set(pipeline.STAGES)
        assert all(v >= 0 for k, v in stages.items() if k != "proposals")
        assert stages["proposals"] >= -1e-3  # its clock includes matching's (rounding only)
        assert sum(stages.values()) <= r["ms_per_frame"] * 1.001 + 1e-3
        assert stages["3d"] > 0
        assert (stages["tracking"] > 0) == r["tracked"]
        # Only the offline runs of the Butterworth-filtered pipelines filter.
        filtered = r["mode"] == "offline" and r["filter"] == "butterworth"
        assert (stages["filtering"] > 0) == filtered
        assert stages["matching"] > 0  # every pipeline matches skeletons
        assert r["jit_calls_per_frame"] > 0 and r["host_round_trips_per_frame"] > 0
        assert r["compilations"] >= 0 and r["compilations_warmup"] >= 0
        if r["pipeline"] == "geometric":
            assert r["ratio_to_geometric"] == 1.0
        geo = next(
            g
            for g in records
            if (g["scene"], g["mode"], g["pipeline"]) == (r["scene"], r["mode"], "geometric")
        )
        assert r["ratio_to_geometric"] == pytest.approx(r["ms_per_frame"] / geo["ms_per_frame"])
    tracked = ("default", "geometric", "pretrained", "shipped")
    assert {r["tracked"] for r in records if r["pipeline"] in tracked} == {True}
    assert {r["tracked"] for r in records if r["pipeline"] in ("paper", "dlt")} == {False}
    p2s = result["pose2sim"]
    assert p2s["installed"] == (importlib.util.find_spec("Pose2Sim") is not None)
    assert p2s["installed"] or "not installed" in p2s["note"]


def test_pipeline_group_stage_clock_leaves_results_unchanged():
    """The matching clock wraps library functions while the group runs: the pipeline's results
    are the same with it, and the functions are restored after it."""
    rig, rec = scenes.recording(5, 2, 4, seed=3)
    det = rec.detections
    config, _ = pipeline.pipeline_configs()["dlt"]
    before = matching.geometric_match_table
    plain = run_pipeline(rig, det, config)
    clock = {"matching": 0.0}
    with pipeline._matching_clock(clock):
        assert matching.geometric_match_table is not before
        timed = run_pipeline(rig, det, config)
    assert matching.geometric_match_table is before
    assert clock["matching"] > 0
    np.testing.assert_array_equal(plain.members, timed.members)
    np.testing.assert_array_equal(plain.poses.xyz, timed.poses.xyz)
    np.testing.assert_array_equal(plain.poses.valid, timed.poses.valid)


def _stats(ms: float) -> dict:
    return {"median": ms, "p10": ms, "p90": ms, "iqr": [ms, ms], "mean": ms, "n": 1}


def _fake_run(
    t_pp: float, t_3dg: float, t_tri: float, stage3_gflops: float, memory_growth: float = 1.05
) -> dict:
    where = dict(views=5, people=4)
    return {
        "peaks": {"matmul_gflops": 300.0, "bandwidth_gbs": 40.0},
        "latency": {
            "rows": [{**where, "model": "paper", "t_pp": _stats(t_pp), "t_3Dg": _stats(t_3dg)}],
            "triangulation": [
                {**where, "method": m, "t_tri": _stats(t_tri)} for m in ("dlt", "centroid")
            ],
            "models": {"5v-paper": {"mlp_bytes": 120_000_000}},  # bound 3 ms at 40 GB/s
        },
        "offline": {"models": {"paper": {"stage3": {"gflops": stage3_gflops}}}},
        "infer_memory": {
            "rows": [
                {"frames": n, "infer": {"maxrss_mb": mb}}
                for n, mb in ((1_000, 400.0), (10_000, 400.0 * memory_growth))
            ]
        },
    }


def test_targets_pass_and_miss():
    good = {t["name"]: t["status"] for t in report.targets(_fake_run(1.5, 3.5, 1.5, 250.0))}
    assert set(good.values()) == {"pass"}
    bad = {t["name"]: t for t in report.targets(_fake_run(2.5, 4.0, 0.5, 100.0, 1.2))}
    assert [t["status"] for t in bad.values()] == ["miss"] * 5
    assert bad["infer peak RSS within 10% across lengths"]["measured"] == pytest.approx(0.2)
    assert bad["t_3Dg <= 1.3 x weight-streaming bound"]["limit"] == pytest.approx(3.9)
    assert bad["t_pp + t_3Dg <= 2 x triangulation pipeline"]["measured"] == pytest.approx(6.5 / 3.0)
    assert all(t["status"] == "n/a" for t in report.targets({}))


def test_opencv_reference_matches_the_library_centroid():
    rig = scenes.ring_rig(4)
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(3, 18, 3)).astype(np.float32) * 0.4 + np.array(
        [0.0, -1.0, 0.0], np.float32
    )
    px = np.asarray(project_points(rig, xyz))  # (C, 3, 18, 2)
    score = (rng.random(px.shape[:-1]) < 0.8).astype(np.float32)
    ref, ok = scenes.opencv_pairwise_centroid(
        scenes.opencv_cameras(rig), np.moveaxis(px, 0, 1), np.moveaxis(score, 0, 1)
    )
    ours, ours_ok = triangulate_pairwise_centroid(rig, px, score)
    np.testing.assert_array_equal(ok, np.asarray(ours_ok))
    np.testing.assert_allclose(ref[ok], np.asarray(ours)[ok], atol=2e-3)
    np.testing.assert_allclose(ref[ok], xyz[ok], atol=2e-3)


def test_the_batch_section_reads_its_record():
    from benchmarks.batch import markdown

    record = {
        "recordings": 8, "frames_per_recording": 60, "views": 5, "people": 4,
        "pipeline": "geometric", "ray_cpus": 2, "worker_start_s": 5.2,
        "first_recording_extra_s": 6.8, "start_batch_seconds": 13.0, "repeats": 3,
        "rows": [
            {"workers": 1, "seconds": 1.0, "recordings_per_s": 8.0, "frames_per_s": 480.0},
            {"workers": 2, "seconds": 0.6, "recordings_per_s": 13.3, "frames_per_s": 800.0},
        ],
        "ratio_2_to_1": 800.0 / 480.0,
    }  # fmt: skip
    text = "\n".join(markdown(record))
    assert "| 2 | 0.60 | 13.30 | 800.0 |" in text
    assert "2 workers / 1: 1.67x" in text and "5.2 s" in text and "6.8 s" in text


def test_same_results_compares_groupings_exactly_and_keypoints_within_a_tolerance():
    from benchmarks.same_results import compare

    rng = np.random.default_rng(0)
    base = "s/p/offline"
    a = {
        f"{base}/xyz": rng.normal(size=(3, 2, 4, 3)).astype(np.float32),
        f"{base}/valid": np.array([[True, False]] * 3),
        f"{base}/keypoint_valid": np.ones((3, 2, 4), bool),
        f"{base}/members": rng.integers(-1, 3, (3, 2, 5)),
    }
    b = {k: v.copy() for k, v in a.items()}
    b[f"{base}/xyz"][:, 1] += 1.0  # an invalid person's keypoints are not compared
    b[f"{base}/xyz"][0, 0, 0, 0] += 5e-6
    compared, problems = compare(a, b)
    assert compared == 3 * 4 * 3 and problems == []
    b[f"{base}/xyz"][1, 0, 2, 1] += 1e-3
    b[f"{base}/members"][2, 0, 0] += 1
    _, problems = compare(a, b)
    assert len(problems) == 2 and any("members" in p for p in problems)


def test_ab_extracts_a_commit_under_other_names_beside_the_working_tree(tmp_path):
    """`benchmarks.ab` imports an old commit's packages under other names: every import of one
    by the other is rewritten, package data comes along, and the copy imports on its own."""
    import re

    from benchmarks import ab

    ab.extract_old("HEAD", tmp_path)
    assert {p.name for p in tmp_path.iterdir()} == {"mvpose_jax_old", "benchmarks_old"}
    sources = list(tmp_path.rglob("*.py"))
    assert len(sources) > 40
    unrenamed = re.compile(r"\b(mvpose_jax|benchmarks)\b(?!_old)")
    assert not [p for p in sources if unrenamed.search(p.read_text())]
    assert list((tmp_path / "mvpose_jax_old" / "data" / "rigs").glob("*.json"))
    code = (
        "import mvpose_jax_old.inference as i, benchmarks_old.pipeline as p; "
        "print(i.__file__); print(p.pipeline_configs.__module__)"
    )
    env = dict(os.environ, PYTHONPATH=str(tmp_path), JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    assert Path(out[0]).is_relative_to(tmp_path) and out[1] == "benchmarks_old.pipeline"
    with pytest.raises(subprocess.CalledProcessError):
        ab.extract_old("no-such-revision", tmp_path / "none")


def test_only_the_pipeline_groups_process_keeps_compiled_programs(tmp_path, monkeypatch):
    from benchmarks import measure
    from benchmarks import run as harness

    monkeypatch.setitem(measure.GROUPS, "pipeline", lambda tier: {"records": [], "notes": []})
    monkeypatch.setitem(measure.GROUPS, "tracking", lambda tier: {"records": []})
    for group in ("pipeline", "tracking"):
        assert harness._child(group, "smoke", tmp_path / f"{group}.json") == 0
    kept = json.loads((tmp_path / "pipeline.json").read_text())["result"]["notes"]
    # The tests' own cache (conftest) is the one configured, so the note names it.
    assert len(kept) == 1 and os.environ["JAX_COMPILATION_CACHE_DIR"] in kept[0]
    assert "notes" not in json.loads((tmp_path / "tracking.json").read_text())["result"]
    assert harness.CACHED_GROUPS == ("pipeline",)
