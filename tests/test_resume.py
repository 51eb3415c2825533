"""Resumable training: a run killed with SIGKILL and resumed ends exactly where an uninterrupted
run ends; damaged or mismatched checkpoints are refused with `InputError`, never restarted.

The interrupted run is a real process (`_train_main` in a subprocess), killed as soon as a
periodic checkpoint after the first validation exists, in the middle of an epoch.
"""

from __future__ import annotations

import dataclasses
import gc
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from mvpose_jax.checkpoints import Checkpoints
from mvpose_jax.errors import InputError
from mvpose_jax.estimator_training import train_estimator
from mvpose_jax.models import MLPConfig
from mvpose_jax.trained import EstimatorConfig, TrainConfig

pytestmark = pytest.mark.slow  # trains, kills and resumes runs

ROOT = Path(__file__).resolve().parents[1]
# 64 people, 8 per step: 8 steps per epoch, validation every 2 epochs (steps 16, 32, 48, 60),
# a periodic checkpoint every 3 steps (kept: the 2 newest).
CONFIG = EstimatorConfig(
    mlp=MLPConfig(widths=(32,), output="residual"),
    num_augment=2,
    train=TrainConfig(
        learning_rate=1e-3,
        batch_size=8,
        max_steps=60,
        eval_every=2,
        patience=100,
        final_lr_fraction=0.1,
        checkpoint_every_steps=3,
        max_to_keep=2,
    ),
)
KILL_AT = 18  # a checkpoint at or after this step: after the first validation (16), mid-epoch


def _samples():
    from mvpose_jax.data.calibration import load_preset
    from mvpose_jax.features import single_person_samples
    from mvpose_jax.synthetic import generate_single_person_recordings

    rig = load_preset("panoptic5").select(["trackera", "trackerb", "trackerc"])
    recs = generate_single_person_recordings(rig, num_recordings=4, num_frames=16, seed=0)
    return (rig, *single_person_samples(recs))


def _train(folder, config=CONFIG, resume=False, data=None):
    rig, xy, score = data or _samples()
    return train_estimator(
        rig,
        xy,
        score,
        xy[:8],
        score[:8],
        config,
        checkpoint_dir=folder,
        progress=False,
        resume=resume,
    )


def _train_main(folder: str) -> None:
    """The interrupted run's process: trains until killed (or done)."""
    _train(folder)


def _latest_steps(folder: Path) -> list[int]:
    latest = folder / "latest"
    # Finished checkpoints only: orbax writes into a temporary folder and renames it to the step.
    return (
        sorted(int(p.name) for p in latest.iterdir() if p.name.isdigit()) if latest.exists() else []
    )


def _leaves(tree):
    return [np.asarray(a) for a in jax.tree.leaves(tree)]


@pytest.fixture(scope="module")
def data():
    return _samples()


@pytest.fixture(scope="module")
def reference(data, tmp_path_factory):
    """The uninterrupted run (its folder and result). It saves at validations only: how often a
    run checkpoints changes nothing it computes (and saves time here)."""
    folder = tmp_path_factory.mktemp("reference")
    quiet = dataclasses.replace(
        CONFIG, train=dataclasses.replace(CONFIG.train, checkpoint_every_steps=0)
    )
    return folder, _train(folder, config=quiet, data=data)


def test_killed_run_resumes_exactly(data, reference, tmp_path):
    folder = tmp_path / "killed"
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"from tests.test_resume import _train_main; _train_main({str(folder)!r})",
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 240
        while not any(s >= KILL_AT for s in _latest_steps(folder)):
            assert proc.poll() is None, proc.stderr.read().decode()[-3000:]
            assert time.monotonic() < deadline, "no periodic checkpoint in time"
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()
    steps = _latest_steps(folder)
    assert KILL_AT <= steps[-1] < CONFIG.train.max_steps  # killed mid-training ...
    # ... with a bounded number of checkpoints (orbax deletes the oldest after writing the newest,
    # so a kill in between leaves one more).
    assert len(steps) <= CONFIG.train.max_to_keep + 1
    ck = Checkpoints(folder)
    try:
        progress = ck.read_progress()
    finally:
        ck.close()
    # The checkpoint resumed from carries the loop's state: position, history, best so far.
    assert progress["step"] == steps[-1] and progress["index"] > 0 and len(progress["history"]) >= 1
    assert progress["best_step"] is not None and progress["seed"] == CONFIG.train.seed

    resumed, fit = _train(folder, resume=True, data=data)
    ref_folder, (whole, ref_fit) = reference
    assert fit.steps == ref_fit.steps == CONFIG.train.max_steps
    drop = lambda h: {k: v for k, v in h.items() if k != "seconds"}  # noqa: E731
    assert [drop(h) for h in fit.history] == [drop(h) for h in ref_fit.history]
    assert fit.best_val_loss == ref_fit.best_val_loss
    for a, b in zip(_leaves(resumed.params), _leaves(whole.params), strict=True):  # the best state
        np.testing.assert_array_equal(a, b)
    latest = []
    for f in (folder, ref_folder):  # the final state, optimiser state included
        ck = Checkpoints(f)
        try:
            state, _ = _restore_latest(ck)
        finally:
            ck.close()
        latest.append(state)
    assert int(latest[0].step) == int(latest[1].step) == CONFIG.train.max_steps
    for a, b in zip(_leaves(latest[0]), _leaves(latest[1]), strict=True):
        np.testing.assert_array_equal(a, b)


def _restore_latest(ck: Checkpoints, config: EstimatorConfig = CONFIG):
    from flax import nnx

    from mvpose_jax.models import PoseMLP
    from mvpose_jax.train import init_train_state, make_optimizer

    model = PoseMLP(3, 18, config.mlp, rngs=nnx.Rngs(0))
    _, _, state = init_train_state(model, make_optimizer(config.train, 8))
    return ck.restore(jax.eval_shape(lambda: state), "latest")


def _damage_data(step_dir: Path) -> None:
    # The array bytes (tensorstore/OCDBT data files): garbage over the start of each.
    files = [p for p in (step_dir / "state").rglob("*") if p.is_file() and p.parent.name == "d"]
    assert files
    for f in files:
        with open(f, "r+b") as fh:
            fh.write(b"\xff" * 64)


def _truncate_fit(step_dir: Path) -> None:
    files = [
        p for p in (step_dir / "fit").iterdir() if p.is_file() and p.name != "commit_success.txt"
    ]
    assert files
    for f in files:
        os.truncate(f, max(0, f.stat().st_size // 2))


def _garble_config(step_dir: Path) -> None:
    for f in (step_dir / "config").iterdir():
        if f.name != "commit_success.txt":
            f.write_text("{not json")


# A failed read leaves orbax's other pending array reads to the garbage collector, which reports
# them as unraisable exceptions (harmless; collected in the test, under this filter).
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.parametrize(
    "damage", [_damage_data, _truncate_fit, _garble_config], ids=lambda f: f.__name__[1:]
)
def test_damaged_checkpoint_is_refused(data, reference, tmp_path, damage):
    folder = tmp_path / "damaged"
    shutil.copytree(reference[0], folder)
    steps = _latest_steps(folder)
    damage(folder / "latest" / str(steps[-1]))
    with pytest.raises(InputError, match="damaged or unreadable|malformed") as err:
        _train(folder, resume=True, data=data)
    assert str(steps[-1]) in str(err.value)  # names the checkpoint
    gc.collect()


def test_checkpoint_of_another_model_is_refused(data, reference, tmp_path):
    folder = tmp_path / "other"
    shutil.copytree(reference[0], folder)
    wider = dataclasses.replace(CONFIG, mlp=MLPConfig(widths=(64,), output="residual"))
    with pytest.raises(InputError, match=r"another config \(differs in \['mlp'\]\)"):
        _train(folder, config=wider, resume=True, data=data)
    # Below the config check too: restoring into another width names the shape mismatch.
    ck = Checkpoints(folder)
    try:
        with pytest.raises(
            InputError,
            match=r"another model \(params\.hidden\.0\.bias\.value: checkpoint \(32,\), model \(64,\)",
        ):
            _restore_latest(ck, wider)
    finally:
        ck.close()


def test_changing_only_length_or_execution_is_accepted(data, reference, tmp_path):
    folder = tmp_path / "longer"
    shutil.copytree(reference[0], folder)
    longer = dataclasses.replace(
        CONFIG,
        train=dataclasses.replace(
            CONFIG.train, max_steps=64, checkpoint_every_steps=0, max_to_keep=1
        ),
    )
    _, fit = _train(folder, config=longer, resume=True, data=data)
    assert fit.steps == 64 and len(fit.history) == len(reference[1][1].history) + 1
    other_seed = dataclasses.replace(CONFIG, train=dataclasses.replace(CONFIG.train, seed=1))
    with pytest.raises(InputError, match=r"train\.seed"):
        _train(folder, config=other_seed, resume=True, data=data)
