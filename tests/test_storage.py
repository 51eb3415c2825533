"""jobs/storage.py: a batch's outputs at an fsspec URL, here fsspec's in-memory filesystem
(``memory://``, this process's), and a recording run by `jobs.batch.run_task` into it byte for
byte as a local run writes it."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from mvpose_jax.data import save_recording
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.errors import InputError
from mvpose_jax.jobs import storage
from mvpose_jax.jobs.batch import BatchTask, run_task
from mvpose_jax.jobs.common import DetectionsSource, RigSource
from mvpose_jax.jobs.generate import GenerateConfig
from mvpose_jax.jobs.infer import INFER_PIPELINE, InferConfig
from mvpose_jax.synthetic import generate_recording

fsspec = pytest.importorskip("fsspec")


@pytest.fixture
def memory():
    """A fresh folder of fsspec's in-memory filesystem, its URL; emptied at the end."""
    fs = fsspec.filesystem("memory")
    root = "/test-storage"
    fs.mkdirs(root, exist_ok=True)
    yield f"memory://{root}"
    fs.rm(root, recursive=True)


def _files(url: str) -> dict[str, bytes]:
    fs, where = fsspec.core.url_to_fs(url)
    return {p[len(where) + 1 :]: fs.cat_file(p) for p in fs.find(where)}


@pytest.mark.parametrize(
    ("base", "parts", "joined"),
    [
        ("s3://bucket/run/", ("a", "b/"), "s3://bucket/run/a/b"),
        ("file:///shared/run", ("x.json",), "file:///shared/run/x.json"),
    ],
)
def test_urls_are_told_from_paths_and_joined_with_slashes(base, parts, joined):
    assert storage.is_url(base) and storage.join(base, *parts) == joined
    assert not storage.is_url("/data/run") and not storage.is_url("C:\\data\\run")


def test_publish_uploads_every_file_of_a_folder_and_leaves_no_partial_file(memory, tmp_path):
    (tmp_path / "chunks").mkdir()
    (tmp_path / "poses.json").write_text("{}\n")
    (tmp_path / "chunks" / "chunk_0.npz").write_bytes(b"\x00\x01" * 100)
    assert storage.publish(tmp_path, memory + "/rec") == 2
    assert _files(memory + "/rec") == {
        "poses.json": b"{}\n",
        "chunks/chunk_0.npz": b"\x00\x01" * 100,
    }
    storage.write_text(memory + "/batch.json", '{"a": 1}\n')
    storage.write_text(memory + "/batch.json", '{"a": 2}\n')  # replaced whole
    assert storage.read_json_at(memory + "/batch.json") == {"a": 2}
    assert not [name for name in _files(memory) if ".partial-" in name]


def test_bad_documents_and_urls_are_named(memory):
    storage.write_text(memory + "/bad.json", "{ nope")
    with pytest.raises(InputError, match="malformed JSON") as e:
        storage.read_json_at(memory + "/bad.json")
    assert e.value.file == memory + "/bad.json"
    with pytest.raises(InputError, match="no such file") as e:
        storage.read_json_at(memory + "/none.json")
    assert e.value.file == memory + "/none.json"
    with pytest.raises(InputError, match="cannot open this URL") as e:
        storage.exists("nosuchprotocol://x/y")
    assert e.value.file == "nosuchprotocol://x/y" and e.value.field == "--out"


def test_a_recording_run_into_a_url_is_written_as_a_local_run_writes_it(memory, tmp_path):
    rig = load_rig("panoptic5")
    save_recording(generate_recording(rig, num_people=2, num_frames=4, seed=3), tmp_path / "r.json")
    pipeline = dataclasses.replace(INFER_PIPELINE, chunk_frames=2)
    job = InferConfig(
        RigSource("panoptic5"),
        DetectionsSource(str(tmp_path / "r.json")),
        str(tmp_path / "local"),
        pipeline,
        keep_chunks=True,
        progress=False,
    )
    local = run_task(BatchTask("r", job.out, job))
    remote = run_task(BatchTask("r", memory + "/r", dataclasses.replace(job, out=memory + "/r")))
    assert local["status"] == remote["status"] == "done" and local["frames"] == remote["frames"]
    written = {
        p.relative_to(tmp_path / "local").as_posix(): p.read_bytes()
        for p in sorted((tmp_path / "local").rglob("*"))
        if p.is_file()
    }
    assert "poses.npz" in written and any(name.startswith("chunks/") for name in written)
    assert _files(memory + "/r") == written  # results, chunks and the run's record alike

    generated = GenerateConfig(
        RigSource("panoptic5"), memory + "/g.json", people=1, frames=3, floor_height=0.0
    )
    assert run_task(BatchTask("g", generated.out, generated))["status"] == "done"
    run_task(
        BatchTask(
            "g",
            str(tmp_path / "g.json"),
            dataclasses.replace(generated, out=str(tmp_path / "g.json")),
        )
    )
    assert _files(memory)["g.json"] == Path(tmp_path / "g.json").read_bytes()
