"""jobs/batch.py and ``mvpose-jax batch`` / ``generate --recordings`` on a local Ray of 2 CPUs
(one Ray for the module, stopped at its end): a batch equals sequential ``infer`` runs bit for
bit, also when a worker is killed mid-batch; a bad recording fails alone, named, exit status
non-zero; an interrupted batch resumed runs only what was not done."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mvpose_jax.cli import main
from mvpose_jax.data import save_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.errors import InputError
from mvpose_jax.jobs.batch import (
    KILL_ONCE_ENV,
    MANIFEST,
    BatchConfig,
    PoolConfig,
    read_manifest_file,
    release_workers,
    run_batch,
    run_generate_batch,
)
from mvpose_jax.jobs.common import DetectionsSource, RigSource
from mvpose_jax.jobs.generate import GenerateConfig, generate
from mvpose_jax.jobs.infer import INFER_PIPELINE, InferConfig, run_infer
from mvpose_jax.synthetic import generate_recording

pytestmark = pytest.mark.slow
ray = pytest.importorskip("ray")

REPO = Path(__file__).resolve().parents[1]
RIG = RigSource("panoptic5")
# infer's pipeline in chunks of 3 frames (4 chunks a recording): a worker can die mid-recording.
PIPELINE = dataclasses.replace(INFER_PIPELINE, chunk_frames=3)
NAMES = ("rec_a", "rec_b", "rec_c", "rec_d")


@pytest.fixture(scope="module")
def local_ray():
    """One Ray for the module (starting one costs seconds): its workers inherit this process's
    environment (the tests' compilation cache) and are kept warm between the batches."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Path:
    """Four small recordings of two people (native JSON, 10 frames each)."""
    rig = load_rig(RIG.rig)
    folder = tmp_path_factory.mktemp("recordings")
    for seed, name in enumerate(NAMES):
        rec = generate_recording(rig, num_people=2, num_frames=10, seed=seed)
        save_recording(rec, folder / f"{name}.json", rig=rig)
    return folder


@pytest.fixture(scope="module")
def sequential(recordings, tmp_path_factory) -> Path:
    """The recordings run one after the other in this process, as ``infer`` runs them."""
    out = tmp_path_factory.mktemp("sequential")
    for name in NAMES:
        detections = DetectionsSource(str(recordings / f"{name}.json"))
        run_infer(InferConfig(RIG, detections, str(out / name), PIPELINE, progress=False))
    return out


def _config(source: Path, out: Path, workers: int, **kwargs) -> BatchConfig:
    """A batch of this module: its workers kept warm for the next test's batch."""
    pool = PoolConfig(workers=workers, keep_workers=True, **kwargs.pop("pool", {}))
    return BatchConfig(
        str(source), str(out), rig=RIG, pipeline=PIPELINE, progress=False, pool=pool, **kwargs
    )


def _assert_same_results(out: Path, reference: Path, names=NAMES) -> None:
    for name in names:
        a, b = np.load(out / name / "poses.npz"), np.load(reference / name / "poses.npz")
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            assert a[key].dtype == b[key].dtype, (name, key)
            assert a[key].tobytes() == b[key].tobytes(), (name, key)
        same = (out / name / "poses.json").read_bytes() == (
            reference / name / "poses.json"
        ).read_bytes()
        assert same, name


def _manifest(out: Path) -> dict:
    return json.loads((out / MANIFEST).read_text())["recordings"]


def test_batch_equals_sequential_runs(local_ray, recordings, sequential, tmp_path):
    res = run_batch(_config(recordings, tmp_path, 2))
    assert [r.status for r in res.recordings] == ["done"] * 4
    assert res.workers == 2 and res.frames == 40
    assert len({r.worker for r in res.recordings}) == 2  # both workers took recordings
    _assert_same_results(tmp_path, sequential)
    recorded = _manifest(tmp_path)
    assert {n: r["status"] for n, r in recorded.items()} == dict.fromkeys(NAMES, "done")
    assert recorded["rec_c"]["out"] == str(tmp_path / "rec_c")


def test_a_worker_killed_mid_recording_is_replaced_and_its_recording_run_again(
    local_ray, recordings, sequential, tmp_path, monkeypatch
):
    # The worker of rec_b kills itself (SIGKILL) once its first chunk is written; the retry must
    # start over, not continue those chunks.
    marker = tmp_path / "killed"
    monkeypatch.setenv(KILL_ONCE_ENV, f"rec_b={marker}")
    res = run_batch(_config(recordings, tmp_path / "out", 2))
    killed_pid, when = marker.read_text().split(maxsplit=1)  # the worker did kill itself once
    assert when.strip() == "mid-recording"  # with a chunk of rec_b on disk
    assert [r.status for r in res.recordings] == ["done"] * 4
    by_name = {r.name: r for r in res.recordings}
    assert by_name["rec_b"].attempts == 2 and by_name["rec_a"].attempts == 1
    assert not by_name["rec_b"].worker.endswith(f":{killed_pid}")
    _assert_same_results(tmp_path / "out", sequential)


def test_a_recording_whose_worker_keeps_dying_fails_after_its_retries(
    local_ray, recordings, tmp_path, monkeypatch
):
    # A marker in a folder that does not exist cannot be created: the worker dies every time.
    monkeypatch.setenv(KILL_ONCE_ENV, f"rec_a={tmp_path / 'absent' / 'killed'}")
    res = run_batch(_config(recordings, tmp_path, 1, pool={"retries": 1}))
    by_name = {r.name: r for r in res.recordings}
    assert by_name["rec_a"].status == "failed" and by_name["rec_a"].attempts == 2
    assert "worker died 2 times" in by_name["rec_a"].error
    assert [by_name[n].status for n in NAMES[1:]] == ["done"] * 3


def test_an_interrupted_batch_resumed_runs_only_what_was_not_done(
    local_ray, recordings, sequential, tmp_path
):
    done_first = []

    def interrupt(status) -> None:  # Ctrl-C on the driver once one recording is done
        done_first.append(status.name)
        raise KeyboardInterrupt

    config = _config(recordings, tmp_path, 1)
    res = run_batch(config, on_done=interrupt)
    assert res.interrupted and done_first == ["rec_a"]
    recorded = _manifest(tmp_path)
    assert recorded["rec_a"]["status"] == "done"
    assert {recorded[n]["status"] for n in NAMES[1:]} == {"pending"}
    written = (tmp_path / "rec_a" / "poses.npz").stat().st_mtime_ns

    res = run_batch(BatchConfig(**{**config.__dict__, "resume": True}))
    assert [r.status for r in res.recordings] == ["skipped", "done", "done", "done"]
    assert (tmp_path / "rec_a" / "poses.npz").stat().st_mtime_ns == written  # not recomputed
    _assert_same_results(tmp_path, sequential)
    # Changed settings are not "done": the recording runs again.
    changed = BatchConfig(**{**config.__dict__, "resume": True, "fps": 25.0})
    assert {r.status for r in run_batch(changed).recordings} == {"done"}


def test_a_bad_recording_fails_alone_named_and_the_exit_status_says_so(
    local_ray, recordings, sequential, tmp_path, capsys
):
    folder = tmp_path / "in"
    folder.mkdir()
    for name in NAMES[:2]:
        (folder / f"{name}.json").write_bytes((recordings / f"{name}.json").read_bytes())
    # A recording with a camera the calibration lacks.
    doc = json.loads((recordings / "rec_c.json").read_text())
    text = json.dumps(doc).replace('"trackerc"', '"cam_x"')
    assert text != json.dumps(doc)
    (folder / "unknown_camera.json").write_text(text)
    (folder / "truncated.json").write_text((recordings / "rec_d.json").read_text()[:300])
    out = tmp_path / "out"
    command = ["batch", str(folder), "--out", str(out), "--rig", RIG.rig, "--chunk-frames", "3"]
    status = main([*command, "--workers", "2"])
    err = capsys.readouterr().err
    assert status == 1
    _assert_same_results(out, sequential, NAMES[:2])
    recorded = _manifest(out)
    assert recorded["rec_a"]["status"] == recorded["rec_b"]["status"] == "done"
    for bad in ("unknown_camera", "truncated"):
        assert recorded[bad]["status"] == "failed"
        assert f"{bad}.json" in recorded[bad]["error"]  # names the file
        assert f"failed {bad}: " in err
        assert not (out / bad / "poses.npz").exists()
    assert "cam_x" in recorded["unknown_camera"]["error"]


def test_a_killed_driver_on_the_cluster_is_resumed_without_recomputing(
    local_ray, recordings, tmp_path
):
    """``batch --address`` joins the module's Ray from another process, which is SIGKILLed once
    a recording is done; ``--resume`` then runs only the rest."""
    release_workers()  # the kept workers' CPUs, for the other driver's
    out = tmp_path / "out"
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
    }
    address = ray.get_runtime_context().gcs_address
    command = [sys.executable, "-m", "mvpose_jax.cli", "batch", str(recordings), "--out", str(out)]
    command += ["--rig", RIG.rig, "--address", address, "--workers", "1", "--chunk-frames", "3"]
    driver = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    done: list[str] = []
    deadline = time.monotonic() + 120
    while not done and driver.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
        with contextlib.suppress(OSError, ValueError, KeyError):  # not written yet / mid-rename
            done = [n for n, r in _manifest(out).items() if r["status"] == "done"]
    driver.send_signal(signal.SIGKILL)
    err = driver.communicate()[1].decode()
    assert done and len(done) < len(NAMES), err
    written = {n: (out / n / "poses.npz").stat().st_mtime_ns for n in done}

    res = run_batch(_config(recordings, out, 2, resume=True))
    status = {r.name: r.status for r in res.recordings}
    assert {n for n, s in status.items() if s == "skipped"} >= set(done)
    assert set(status.values()) <= {"skipped", "done"}
    for n in done:
        assert (out / n / "poses.npz").stat().st_mtime_ns == written[n]


def test_a_batch_written_to_a_url_equals_sequential_runs_and_resumes_from_it(
    local_ray, recordings, sequential, tmp_path
):
    # file:// goes through fsspec as s3:// or gs:// would: staged by the workers, then uploaded.
    url = tmp_path.as_uri() + "/run"
    res = run_batch(_config(recordings, url, 2))
    assert [r.status for r in res.recordings] == ["done"] * 4
    assert res.manifest == url + "/" + MANIFEST
    _assert_same_results(tmp_path / "run", sequential)
    assert not [p for p in (tmp_path / "run").rglob("*") if ".partial-" in p.name]
    assert _manifest(tmp_path / "run")["rec_b"]["out"] == url + "/rec_b"
    again = run_batch(_config(recordings, url, 2, resume=True))
    assert [r.status for r in again.recordings] == ["skipped"] * 4 and again.frames == 0


def test_generate_recordings_seeds_each_recording_whatever_the_workers(local_ray, tmp_path):
    base = GenerateConfig(RIG, str(tmp_path / "pool"), people=2, frames=6, seed=7, floor_height=0.0)
    res = run_generate_batch(base, 3, PoolConfig(workers=2), progress=False)
    assert (tmp_path / "pool" / MANIFEST).exists()
    assert [r.status for r in res.recordings] == ["done"] * 3
    for i in range(3):
        alone = tmp_path / f"alone_{i}.json"
        generate(dataclasses.replace(base, out=str(alone), seed=7 + i))
        assert (tmp_path / "pool" / f"recording_{i}.json").read_bytes() == alone.read_bytes()


def test_a_manifest_file_lists_recording_calibration_and_output(tmp_path):
    (tmp_path / "calib.toml").write_text("")
    (tmp_path / "lines.tsv").write_text(
        "# recording calibration [output]\n\n"
        "day1/a.json calib.toml\n"
        "day 2/b.npz\tpanoptic5\tsecond/b\n"
    )
    rows = read_manifest_file(tmp_path / "lines.tsv", "OUT")
    assert rows == [
        ("a", str(tmp_path / "day1/a.json"), RigSource(str(tmp_path / "calib.toml")), "OUT/a"),
        ("second/b", str(tmp_path / "day 2/b.npz"), RigSource("panoptic5"), "OUT/second/b"),
    ]
    (tmp_path / "bad.tsv").write_text("a.json\n")
    with pytest.raises(InputError, match="line 1 holds 1 fields") as e:
        read_manifest_file(tmp_path / "bad.tsv", "OUT")
    assert e.value.file == str(tmp_path / "bad.tsv")


def test_batch_without_ray_says_how_to_install_it(recordings, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    status = main(["batch", str(recordings), "--out", str(tmp_path), "--rig", RIG.rig])
    assert status == 2
    assert 'pip install "mvpose-jax[cluster]"' in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "rec_a")
