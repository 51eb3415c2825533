"""The experiments' registry, ``--only`` and its deprecated alias, the seed streams and the model
cache, with toy experiments (seconds); the real experiments run in test_experiments*.py."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from experiments import registry
from experiments.config import SCALES, STREAMS, seed_stream
from experiments.registry import DEFAULT, EXPERIMENTS, Experiment
from experiments.run import main
from mvpose_jax.errors import InputError


def _toy(calls: list):
    """A toy experiment that records what it was asked to run and returns one record per seed."""

    def run(sc, seeds, scenes_seed, out, progress):
        calls.append((sc, seeds, scenes_seed, out, progress))
        runs = [
            {
                "seed": s,
                "scenes_seed": scenes_seed,
                "train_floor_jitter_m": sc.train_floor_jitter_m,
                "train_floor_offset_m": sc.train_floor_offset_m,
                "value": 10.0 * s,
            }
            for s in seeds
        ]
        (out / "runs_partial.json").write_text(json.dumps(runs))
        return runs, tables(runs)

    def tables(runs):
        return ["| seed | value |", *(f"| {r['seed']} | {r['value']:.1f} |" for r in runs)]

    return Experiment(run, tables, "a toy")


def test_registry_holds_every_experiment_and_the_default_is_paper_panoptic():
    assert set(EXPERIMENTS) == {"paper-panoptic", "paper-arp", "synthetic-summary", "domain-shift"}
    assert DEFAULT == "paper-panoptic"
    for name, experiment in EXPERIMENTS.items():
        assert callable(experiment.run) and experiment.summary
        # Every experiment with seeds to average rebuilds its tables from saved runs.
        assert (experiment.tables is None) == (name == "synthetic-summary")


def test_only_runs_the_named_experiment_and_no_option_runs_the_default(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setitem(EXPERIMENTS, "toy", _toy(calls))
    out = tmp_path / "toy"
    argv = ["--only", "toy", "--smoke", "--seed", "2", "--seeds", "2", "--scenes-seed", "7"]
    assert main([*argv, "--out", str(out), "--no-progress"]) == 0
    ((sc, seeds, scenes_seed, where, progress),) = calls
    assert sc.train_recordings == SCALES["smoke"].train_recordings and sc.shifts is None
    assert (seeds, scenes_seed, where, progress) == ([2, 3], 7, out, False)
    meta = json.loads((out / "metrics.json").read_text())
    assert meta["experiment"] == "toy" and meta["scale"] == "smoke" and meta["seeds"] == [2, 3]
    assert [r["value"] for r in meta["runs"]] == [20.0, 30.0]
    text = (out / "tables.md").read_text()
    assert text.startswith("# toy (smoke scale)") and "| 3 | 30.0 |" in text
    # Without --only: the default experiment, whatever the registry holds under its name.
    default_calls = []
    monkeypatch.setitem(EXPERIMENTS, DEFAULT, _toy(default_calls))
    assert main(["--smoke", "--out", str(tmp_path / "default"), "--no-progress"]) == 0
    assert len(default_calls) == 1
    assert json.loads((tmp_path / "default" / "metrics.json").read_text())["experiment"] == DEFAULT
    # The tables again from the saved runs, as for the real experiments.
    again = tmp_path / "again"
    argv = ["--only", "toy", "--out", str(again), "--tables-from", str(out / "runs_partial.json")]
    assert main(argv) == 0 and len(calls) == 1
    assert (again / "tables.md").read_text().split("\n", 3)[3] == text.split("\n", 3)[3]


def test_experiment_is_a_deprecated_alias_of_only(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setitem(EXPERIMENTS, "toy", _toy(calls))
    argv = ["--smoke", "--out", str(tmp_path), "--no-progress"]
    with pytest.warns(FutureWarning, match="--experiment is deprecated; use --only toy"):
        assert main(["--experiment", "toy", *argv]) == 0
    assert len(calls) == 1
    assert json.loads((tmp_path / "metrics.json").read_text())["experiment"] == "toy"
    # Both, naming one experiment: fine; naming two: refused.
    with pytest.warns(FutureWarning):
        assert main(["--experiment", "toy", "--only", "toy", *argv]) == 0
    with pytest.warns(FutureWarning), pytest.raises(SystemExit):
        main(["--experiment", "toy", "--only", "paper-arp", *argv])
    assert "name two experiments" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--only", "no-such-experiment", *argv])
    assert "invalid choice: 'no-such-experiment'" in capsys.readouterr().err
    # Options that belong to one experiment still say so.
    with pytest.raises(SystemExit):
        main(["--only", "toy", "--shifts", "none", *argv])
    assert "--shifts applies to --only domain-shift" in capsys.readouterr().err


def test_tables_from_needs_an_experiment_with_tables(tmp_path, capsys):
    saved = tmp_path / "runs.json"
    saved.write_text(json.dumps([{"seed": 0, "scenes_seed": 0}]))
    argv = [
        "--only",
        "synthetic-summary",
        "--out",
        str(tmp_path / "o"),
        "--tables-from",
        str(saved),
    ]
    with pytest.raises(SystemExit):
        main([*argv, "--train-floor-jitter", "0", "--train-floor-offset", "0"])
    assert "--tables-from applies to ['domain-shift', 'paper-arp', 'paper-panoptic']" in (
        capsys.readouterr().err
    )


def test_seed_streams_are_the_documented_entropy_lists_and_never_shared():
    assert seed_stream("train", 4) == [4, 1] and seed_stream("dev", 4) == [4, 2]
    assert seed_stream("validation", 0, 3) == [0, 3, 3] and seed_stream("test", 0, 3) == [0, 5, 3]
    assert seed_stream("tracking/validation", 1, 8) == [1, 4, 8]
    assert seed_stream("tracking/test", 1, 8) == [1, 6, 8]
    assert len(set(STREAMS.values())) == len(STREAMS)
    # Distinct entropy lists give distinct random numbers, also across the two seeds.
    draws = {
        (stream, seed): np.random.default_rng(
            seed_stream(stream, seed, None if stream in ("train", "dev") else 2)
        ).random()
        for stream in STREAMS
        for seed in (0, 1)
    }
    assert len(set(draws.values())) == len(draws)
    with pytest.raises(ValueError, match="no seed stream 'train2'"):
        seed_stream("train2", 0)
    with pytest.raises(ValueError, match="num_people is for scene streams only"):
        seed_stream("test", 0)


def test_model_cache_refuses_old_pickles_and_unfinished_folders(tmp_path):
    from experiments.fitting import cached_models, load_models
    from mvpose_jax.data.calibration import load_rig

    rig = load_rig("panoptic5")
    old = tmp_path / "models.pkl"
    old.write_bytes(pickle.dumps({"matcher": None}))
    with pytest.raises(InputError, match="not pickles; give a folder"):
        cached_models(rig, old)
    unfinished = tmp_path / "unfinished"
    (unfinished / "matcher").mkdir(parents=True)
    with pytest.raises(InputError, match="no fit.json in it"):
        load_models(rig, unfinished)


def test_experiment_modules_import_no_private_names_and_not_run():
    # Side studies and the registry use the shared modules' public names only.
    import ast
    import pathlib

    folder = pathlib.Path(registry.__file__).parent
    for path in folder.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("experiments"):
                assert node.module != "experiments.run", f"{path.name} imports experiments.run"
                private = [a.name for a in node.names if a.name.startswith("_")]
                assert not private, f"{path.name} imports private {private} from {node.module}"


@pytest.mark.slow  # trains a smoke-scale matcher and estimator (about a minute)
def test_model_cache_is_model_folders_that_load_to_the_same_models(tmp_path):
    from experiments.data import make_scenes
    from experiments.fitting import FIT_FILE, cached_models, combined_config, load_models
    from mvpose_jax.data.calibration import load_rig
    from mvpose_jax.inference import run_pipeline
    from mvpose_jax.trained import read_combined_config, read_proposal_threshold

    rig = load_rig("panoptic5")
    folder = tmp_path / "models"
    trained = cached_models(rig, folder, scale="smoke", progress=False)
    # The layout `mvpose-jax train-matcher/train-estimator --out` write, and the fit record.
    assert (folder / "matcher" / "best").is_dir() and (folder / "estimator" / "best").is_dir()
    assert (folder / FIT_FILE).is_file() and trained.seed == 0
    # What `infer --matcher` reads beside the checkpoints: the settings chosen with the matcher.
    assert read_proposal_threshold(folder / "matcher") == trained.fit["threshold"]
    assert read_combined_config(folder / "matcher") == combined_config(trained.fit)
    loaded = load_models(rig, folder)
    assert loaded.fit == json.loads(json.dumps(trained.fit)) and loaded.seed == 0
    again = cached_models(rig, folder, scale="smoke")  # loads, trains nothing
    assert again.fit == loaded.fit
    (scene, *_) = make_scenes(rig, SCALES["smoke"], 0)["validation"]
    kwargs = dict(proposals="combined", combined=combined_config(trained.fit), method="blend")
    a = run_pipeline(
        rig, scene.detections, matcher=trained.matcher, estimator=trained.estimator, **kwargs
    )
    b = run_pipeline(
        rig, scene.detections, matcher=loaded.matcher, estimator=loaded.estimator, **kwargs
    )
    np.testing.assert_array_equal(a.members, b.members)
    np.testing.assert_array_equal(a.poses.xyz, b.poses.xyz)
