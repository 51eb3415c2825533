"""Hostile input: every reader loads a mutated file correctly or raises the project's own error.

Each strategy starts from VALID files written by the project's own writers (a small synthetic
recording on the panoptic5 rig, as native JSON, original JSON, npz and an OpenPose folder, the
rig as native JSON, CMU Panoptic JSON and anipose TOML, and its ground truth as the ``poses.npz``
that ``infer`` writes) and mutates them: truncation, flipped, inserted and deleted bytes
(non-UTF-8 included), JSON values replaced by hostile ones (huge,
non-finite, negative, wrong types, nested, null, digit strings beyond Python's int limit, deep
nesting), deleted keys, lists grown far beyond their size, npz members of the wrong dtype or
shape or with headers declaring 10^9-element arrays, and OpenPose folders with files missing,
renamed or out of place. The only exceptions allowed out are `MvposeError`s (in practice
`InputError`, which must name the file); a successful load must give a valid recording or rig.
Every call runs under a time limit, so a hang fails too.

Failed saves: nothing half-written at the target (no file, or the old one), no temporary files.
No code path unpickles: an AST scan of the package source.

Hypothesis runs derandomized with a modest number of examples; set MVPOSE_HOSTILE_EXAMPLES to
search longer.
"""

from __future__ import annotations

import ast
import contextlib
import json
import os
import shutil
import signal
import tomllib
import tracemalloc
import zipfile
from collections.abc import Callable
from functools import partial
from pathlib import Path

import hypothesis.strategies as st
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

import mvpose_jax
from mvpose_jax.cameras import Rig
from mvpose_jax.data import (
    Recording,
    load_recording,
    read_native,
    read_native_rig,
    read_npz,
    read_openpose,
    read_original,
    save_openpose,
    save_recording,
    write_native,
    write_npz,
    write_original,
)
from mvpose_jax.data import files as files_module
from mvpose_jax.data.calibration import load_rig, save_rig
from mvpose_jax.data.checks import check_recording
from mvpose_jax.data.poses import PoseResults, load_poses, save_poses
from mvpose_jax.errors import InputError, MvposeError
from mvpose_jax.synthetic import generate_recording
from tests.helpers import Raw, dump_toml, json_paths, panoptic_dict, read_in_chunks, toml_text

EXAMPLES = int(os.environ.get("MVPOSE_HOSTILE_EXAMPLES", "50"))
HOSTILE = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
# Seconds one reader call may take on a mutated 3-frame file before it counts as a hang.
TIME_LIMIT = 20

PANOPTIC_CAMERAS = ["00_00", "00_01", "00_02", "00_03", "00_04"]


# --------------------------------------------------------------------------- valid files


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> dict:
    """name -> bytes of each valid file; "openpose" -> {relative path: bytes}; plus the rig."""
    rig = load_rig("panoptic5")
    rec = generate_recording(rig, num_people=2, num_frames=3, seed=0)
    d = tmp_path_factory.mktemp("valid")
    write_native(rec, d / "native.json", rig=rig)
    write_original(rec, d / "original.json")
    write_npz(rec, d / "recording.npz")
    save_openpose(rec, d / "openpose")
    save_rig(rig, d / "rig.json")
    (d / "panoptic.json").write_text(json.dumps(panoptic_dict(rig)))
    (d / "calib.toml").write_text(toml_text(rig))
    save_poses(_poses_of(rec), d)
    out = {
        name: (d / file).read_bytes()
        for name, file in (
            ("native", "native.json"),
            ("original", "original.json"),
            ("npz", "recording.npz"),
            ("calib_native", "rig.json"),
            ("calib_panoptic", "panoptic.json"),
            ("calib_toml", "calib.toml"),
            ("poses", "poses.npz"),
        )
    }
    root = d / "openpose"
    out["openpose"] = {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }
    out["rig"], out["recording"] = rig, rec
    out = _Valid(out)
    # Every valid file loads (otherwise the tests below would test nothing).
    for name in FILE_KINDS:
        path = d / f"check{SUFFIX[name]}"
        path.write_bytes(out[name])
        for reader in READERS[name]:
            assert not isinstance(_outcome(reader, path), MvposeError), (name, reader)
    assert not isinstance(_outcome(load_recording, root), MvposeError)
    return out


def _poses_of(rec: Recording) -> PoseResults:
    """The recording's ground truth as the poses ``infer`` would write for a perfect match."""
    gt, identity = rec.ground_truth, np.asarray(rec.identity)
    F, G = np.shape(gt.valid)
    members = np.full((F, G, len(rec.cameras)), -1, np.int32)
    f, c, p = np.nonzero(identity >= 0)
    members[f, identity[f, c, p], c] = p
    confidence = np.asarray(gt.valid, np.float32)
    return PoseResults(gt, confidence, members, identity, rec.cameras, rec.layout, rec.timestamps)


class _Valid(dict):
    def __repr__(self):  # hypothesis prints fixtures with a failing example: keep it short
        return "<valid files>"


# --------------------------------------------------------------------------- readers

FILE_KINDS = ("native", "original", "npz", "calib_native", "calib_panoptic", "calib_toml", "poses")
SUFFIX = {
    "native": ".json",
    "original": ".json",
    "npz": ".npz",
    "calib_native": ".json",
    "calib_panoptic": ".json",
    "calib_toml": ".toml",
    "poses": ".npz",
}
READERS: dict[str, list[Callable]] = {
    "native": [load_recording, read_native, read_native_rig],
    "original": [load_recording, read_original, partial(read_original, layout="body25")],
    "npz": [
        load_recording,
        read_npz,
        partial(load_recording, layout="body25"),
        # Read 3 frames at a time (`data.open_recording`): the same checks, range by range.
        lambda path: read_in_chunks(path, 3)[0],
    ],
    "calib_native": [load_rig],
    "calib_panoptic": [load_rig, partial(load_rig, cameras=PANOPTIC_CAMERAS[::-1])],
    "calib_toml": [load_rig, partial(load_rig, translation_scale=1e-3)],
    "poses": [load_poses],
}
OPENPOSE_READERS: list[Callable] = [
    load_recording,
    lambda path: read_in_chunks(path, 2, missing_frames="empty")[0],
    partial(read_openpose, missing_frames="empty"),
    partial(read_openpose, layout="body25", missing_frames="empty"),
]


class _Hang(BaseException):
    """A BaseException, so that a reader's broad ``except Exception`` cannot mask a hang."""


@contextlib.contextmanager
def _time_limit(seconds: float):
    def alarm(signum, frame):
        raise _Hang(f"no answer within {seconds} s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _outcome(reader: Callable, path: Path, **kwargs):
    """Calls ``reader(path)``: returns its checked result or the MvposeError it raised.

    Anything else (a TypeError deep in numpy, a MemoryError, a hang) propagates and fails the test.
    """
    with _time_limit(TIME_LIMIT):
        try:
            result = reader(path, **kwargs)
        except MvposeError as e:
            assert str(e)
            if isinstance(e, InputError):
                assert e.file is not None, f"InputError without a file: {e}"
            return e
    if isinstance(result, Recording):
        check_recording(result)  # a successful load is a valid recording
        assert result.detections.xy.dtype == np.float32
    elif isinstance(result, Rig):
        for field in ("K", "dist", "R", "t", "size"):
            assert np.isfinite(np.asarray(getattr(result, field))).all(), field
    elif isinstance(result, PoseResults):  # shapes agree: PoseResults checks them itself
        assert result.poses.xyz.dtype == np.float32 and np.isfinite(result.poses.xyz).all()
        assert np.isfinite(result.confidence).all()
    else:
        assert result is None and reader is read_native_rig, result
    return result


def _read_all(kind: str, path: Path) -> None:
    for reader in READERS[kind]:
        _outcome(reader, path)


# --------------------------------------------------------------------------- byte mutations

_NOT_UTF8 = st.sampled_from([b"\xff", b"\xc3", b"\xed\xa0\x80", b"\xf8\x88\x80\x80\x80", b"\x00"])
byte_edits = st.lists(
    st.one_of(
        st.tuples(st.just("flip"), st.integers(0, 2**32), st.integers(1, 255)),
        st.tuples(st.just("insert"), st.integers(0, 2**32), st.binary(min_size=1, max_size=8)),
        st.tuples(st.just("insert"), st.integers(0, 2**32), _NOT_UTF8),
        st.tuples(st.just("delete"), st.integers(0, 2**32), st.integers(1, 64)),
    ),
    max_size=4,
)
cuts = st.one_of(st.none(), st.integers(0, 2**32))


def _mutate_bytes(data: bytes, edits, cut) -> bytes:
    out = bytearray(data)
    for op, pos, arg in edits:
        pos = pos % (len(out) + 1)
        if op == "flip" and out:
            out[pos % len(out)] ^= arg
        elif op == "insert":
            out[pos:pos] = arg
        elif op == "delete":
            del out[pos : pos + arg]
    if cut is not None:
        out = out[: cut % (len(out) + 1)]
    return bytes(out)


@pytest.mark.parametrize("kind", FILE_KINDS)
@HOSTILE
@given(edits=byte_edits, cut=cuts)
def test_mutated_bytes(valid, tmp_path_factory, kind, edits, cut):
    path = _work(tmp_path_factory) / f"bytes{SUFFIX[kind]}"
    path.write_bytes(_mutate_bytes(valid[kind], edits, cut))
    _read_all(kind, path)


@HOSTILE
@given(pick=st.integers(0, 10**6), edits=byte_edits, cut=cuts)
def test_mutated_bytes_openpose(valid, tmp_path_factory, pick, edits, cut):
    root = _openpose_copy(valid, tmp_path_factory)
    files = sorted(valid["openpose"])
    target = root / files[pick % len(files)]
    target.write_bytes(_mutate_bytes(target.read_bytes(), edits, cut))
    for reader in OPENPOSE_READERS:
        _outcome(reader, root)


# --------------------------------------------------------------------------- JSON value mutations


_RAW = [
    Raw("[" * 5000 + "]" * 5000),  # nested beyond the recursion limit
    Raw("{" + '"a":{' * 3000 + "}" * 3001),
    Raw("1" * 5000),  # an integer beyond Python's 4300-digit str -> int limit
    Raw("-" + "9" * 400),
    Raw("1e999"),
    Raw("-Infinity"),
    Raw("NaN"),
    Raw("[" + ",".join(["0"] * 60000) + "]"),  # a list far longer than any count in the file
    Raw('"' + "x" * 100000 + '"'),
]
_SPECIAL = st.sampled_from(
    [
        None,
        True,
        False,
        0,
        -1,
        1,
        2,
        3,
        17,
        18,
        25,
        54,
        75,
        1e308,
        -1e308,
        5e-324,
        3.5e38,
        1e39,
        10**30,
        -(10**30),
        2**31,
        2**63,
        2**64,
        -(2**63) - 1,
        float("nan"),
        float("inf"),
        float("-inf"),
        "",
        "0",
        "x",
        "NaN",
        "coco18",
        "body25",
        "trackera",
        "é\u2028",
        [],
        {},
        [None],
        [[]],
        [1, 2],
        [1, 2, 3],
        [0, 0, 0],
        [[1, 2, 3]],
        {"": None},
    ]
)
json_leaves = st.one_of(
    _SPECIAL,
    st.integers(),
    st.floats(),
    st.text(max_size=8),
    st.sampled_from(_RAW),
)
hostile_json = st.recursive(
    json_leaves,
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4)
    ),
    max_leaves=12,
)
# replace: the node becomes the value; delete: the node leaves its parent; grow: a list repeats
# its last element (up to 2000 times: people, frames, keypoints far beyond their counts).
operations = st.one_of(
    st.tuples(st.just("replace"), hostile_json),
    st.tuples(st.just("delete"), st.none()),
    st.tuples(st.just("grow"), st.integers(1, 2000)),
)


# Where to mutate: (named, index). Named picks among object fields only ("identity", "t", ...),
# which the many keypoint numbers would otherwise drown.
picks = st.tuples(st.booleans(), st.integers(0, 10**6))


def _choose(paths: list, pick) -> tuple:
    named, i = pick
    fields = [p for p in paths if p and isinstance(p[-1], str)]
    pool = fields if named and fields else paths
    return pool[i % len(pool)]


def _apply(doc, path, op, arg, raws: list):
    """``doc`` with the operation applied at ``path``; Raw values go to ``raws`` as placeholders."""

    def place(value):
        if isinstance(value, Raw):
            raws.append(value)
            return f"\x00raw{len(raws) - 1}\x00"
        if isinstance(value, list):
            return [place(v) for v in value]
        if isinstance(value, dict):
            return {k: place(v) for k, v in value.items()}
        return value

    if not path:
        return place(arg) if op == "replace" else doc
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    key = path[-1]
    if op == "replace":
        parent[key] = place(arg)
    elif op == "delete":
        del parent[key]
    elif op == "grow" and isinstance(parent[key], list) and parent[key]:
        parent[key].extend([parent[key][-1]] * arg)
    return doc


def _dump_json(doc, raws: list) -> str:
    text = json.dumps(doc, ensure_ascii=False)
    for i, raw in enumerate(raws):
        text = text.replace(json.dumps(f"\x00raw{i}\x00"), raw.text)
    return text


def _mutate_json(text: str, pick: int, op: str, arg) -> str:
    doc = json.loads(text)
    paths = list(json_paths(doc))
    raws: list[Raw] = []
    doc = _apply(doc, _choose(paths, pick), op, arg, raws)
    return _dump_json(doc, raws)


@pytest.mark.parametrize("kind", ["native", "original", "calib_native", "calib_panoptic"])
@HOSTILE
@given(pick=picks, operation=operations)
def test_mutated_json_values(valid, tmp_path_factory, kind, pick, operation):
    path = _work(tmp_path_factory) / f"values{SUFFIX[kind]}"
    path.write_text(_mutate_json(valid[kind].decode(), pick, *operation), encoding="utf-8")
    _read_all(kind, path)


@HOSTILE
@given(pick=st.integers(0, 10**6), inner=picks, operation=operations)
def test_mutated_original_embedded_skeletons(valid, tmp_path_factory, pick, inner, operation):
    """The original format nests JSON in strings: mutate inside them (and break the string)."""
    doc = json.loads(valid["original"])
    entries = [(f, cam) for f, frame in enumerate(doc) for cam in frame]
    f, cam = entries[pick % len(entries)]
    raws: list[Raw] = []
    skeletons = json.loads(doc[f][cam][0])
    inner_paths = list(json_paths(skeletons))
    skeletons = _apply(skeletons, _choose(inner_paths, inner), *operation, raws)
    doc[f][cam][0] = _dump_json(skeletons, raws)
    path = _work(tmp_path_factory) / "embedded.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    _read_all("original", path)


@HOSTILE
@given(file=st.integers(0, 10**6), pick=picks, operation=operations)
def test_mutated_json_values_openpose(valid, tmp_path_factory, file, pick, operation):
    root = _openpose_copy(valid, tmp_path_factory)
    files = sorted(valid["openpose"])
    target = root / files[file % len(files)]
    target.write_text(_mutate_json(target.read_text(), pick, *operation), encoding="utf-8")
    for reader in OPENPOSE_READERS:
        _outcome(reader, root)


toml_leaves = st.one_of(
    _SPECIAL.filter(lambda v: v is not None),
    st.integers(),
    st.floats(),
    st.text(max_size=8),
    st.sampled_from([Raw("[" * 2000 + "]" * 2000), Raw("1" * 5000), Raw("1e999")]),
)
hostile_toml = st.recursive(
    toml_leaves,
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4)
    ),
    max_leaves=12,
)


@HOSTILE
@given(
    pick=picks,
    operation=st.one_of(
        st.tuples(st.just("replace"), hostile_toml),
        st.tuples(st.just("delete"), st.none()),
        st.tuples(st.just("grow"), st.integers(1, 2000)),
    ),
)
def test_mutated_toml_values(valid, tmp_path_factory, pick, operation):
    doc = tomllib.loads(valid["calib_toml"].decode())
    path = _choose(list(json_paths(doc)), pick)
    op, arg = operation
    if not path:
        doc = arg if op == "replace" else doc
    else:
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        if op == "replace":
            parent[path[-1]] = arg
        elif op == "delete":
            del parent[path[-1]]
        elif isinstance(parent[path[-1]], list) and parent[path[-1]]:
            parent[path[-1]].extend([parent[path[-1]][-1]] * arg)
    file = _work(tmp_path_factory) / "values.toml"
    file.write_text(dump_toml(doc), encoding="utf-8")
    _read_all("calib_toml", file)


# --------------------------------------------------------------------------- npz members

npz_dtypes = st.sampled_from(
    ["<f4", "<f8", ">f4", "<f2", "<i4", "<i8", "<u1", "|b1", "<U5", "|S3", "<c8", "<m8[s]", "|V4"]
)
shapes = st.lists(st.integers(0, 4), min_size=0, max_size=6).map(tuple)
fill_values = st.sampled_from([0, 1, -1, 0.5, 2.0, np.nan, np.inf, -np.inf, 1e30, 2**31 - 1])


def _npy_bytes(header: str, payload: bytes, version: tuple[int, int] = (1, 0)) -> bytes:
    """A .npy member with an arbitrary header text (numpy's writer would refuse some)."""
    head = header.encode("latin1")
    size = 2 if version == (1, 0) else 4
    pad = -(10 + size - 2 + len(head) + 1) % 64
    head = head + b" " * pad + b"\n"
    return b"\x93NUMPY" + bytes(version) + len(head).to_bytes(size, "little") + head + payload


_HEADERS = [
    # A declared 10^9-element (and larger) array holding a few bytes: must not be allocated.
    "{'descr': '<f4', 'fortran_order': False, 'shape': (1000000000,), }",
    "{'descr': '<f4', 'fortran_order': False, 'shape': (1000, 1000, 1000, 18, 2), }",
    "{'descr': '<f4', 'fortran_order': False, 'shape': (3, 5, 2, 18, 2), }",  # too few bytes
    "{'descr': '<i4', 'fortran_order': False, 'shape': (99999999999999999999,), }",
    "{'descr': '<f4', 'fortran_order': False, 'shape': (-1, 5), }",
    "{'descr': '<U1000000000', 'fortran_order': False, 'shape': (5,), }",
    "{'descr': '|O', 'fortran_order': False, 'shape': (5,), }",
    "{'descr': '<f4', 'fortran_order': True, 'shape': (3, 5, 2, 18, 2), }",
    "{'descr': 'nonsense', 'fortran_order': False, 'shape': (1,), }",
    "{'descr': '<f4', 'shape': (1,), }",
    "[1, 2, 3]",
    "{'descr': '<f4', 'fortran_order': False, 'shape': (1,), 'extra': __import__('os'), }",
    "{" * 3000,
]

# What happens to one member: a new array, one axis resized, a raw header, an object array, gone.
member_edits = st.one_of(
    st.tuples(st.just("array"), npz_dtypes, shapes),
    st.tuples(st.just("reshape"), st.integers(0, 5), st.integers(0, 10**6)),
    st.tuples(st.just("header"), st.sampled_from(_HEADERS), st.binary(max_size=64)),
    st.tuples(st.just("object"), st.none(), st.none()),
    st.tuples(st.just("delete"), st.none(), st.none()),
)


@HOSTILE
@given(
    member=st.sampled_from(
        [
            "version",
            "layout",
            "cameras",
            "xy",
            "score",
            "count",
            "identity",
            "gt_xyz",
            "gt_valid",
            "gt_keypoint_valid",
            "timestamps",
            "image_names",
            "projected",
            "extra",
        ]
    ),
    action=member_edits,
    fill=fill_values,
)
def test_mutated_npz_members(valid, tmp_path_factory, member, action, fill):
    _read_all("npz", _mutate_member(valid, tmp_path_factory, "npz", member, action, fill))


# The members poses.npz must have (timestamps is optional).
POSES_MEMBERS = (
    "xyz",
    "valid",
    "keypoint_valid",
    "confidence",
    "members",
    "identity",
    "cameras",
    "layout",
)


@HOSTILE
@given(
    member=st.sampled_from([*POSES_MEMBERS, "timestamps", "extra"]),
    action=member_edits,
    fill=fill_values,
)
def test_mutated_poses_members(valid, tmp_path_factory, member, action, fill):
    _read_all("poses", _mutate_member(valid, tmp_path_factory, "poses", member, action, fill))


def _members_of(valid, tmp_path_factory, source: str) -> dict[str, np.ndarray]:
    """The arrays of a valid archive (``source`` "npz" or "poses")."""
    src = _work(tmp_path_factory) / "valid.npz"
    src.write_bytes(valid[source])
    with np.load(src, allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


def _mutate_member(valid, tmp_path_factory, source: str, member: str, action, fill) -> Path:
    """A copy of the valid ``source`` archive with ``member`` edited (`member_edits`); its path."""
    arrays = _members_of(valid, tmp_path_factory, source)
    raw_members: dict[str, bytes] = {}
    kind, a, b = action
    if kind == "array":
        arr = np.zeros(b, dtype=a)
        with np.errstate(all="ignore"), contextlib.suppress(ValueError, TypeError, OverflowError):
            arr[...] = fill if arr.dtype.kind in "fc" else int(fill) if np.isfinite(fill) else 0
        arrays[member] = arr
    elif kind == "reshape" and member in arrays:
        # The right dtype, one axis of the wrong length.
        arr = arrays[member]
        shape = list(arr.shape) or [1]
        shape[a % len(shape)] = b % 7
        arrays[member] = np.resize(arr, shape) if arr.size else np.zeros(shape, arr.dtype)
    elif kind == "header":
        arrays.pop(member, None)
        raw_members[member] = _npy_bytes(a, b)
    elif kind == "object":
        arrays[member] = np.array([{"x": 1}, None], dtype=object)
    elif kind == "delete":
        arrays.pop(member, None)
    path = _work(tmp_path_factory) / "members.npz"
    with open(path, "wb") as f:
        np.savez(f, **arrays)  # object arrays are pickled here: the reader must refuse them
    if raw_members:
        with zipfile.ZipFile(path, "a") as z:
            for name, data in raw_members.items():
                z.writestr(f"{name}.npy", data)
    return path


def test_npz_declared_sizes_are_not_allocated(valid, tmp_path_factory):
    """A header declaring a huge array is refused from its size, before any allocation."""
    for header in _HEADERS[:4]:
        src = _work(tmp_path_factory) / "valid.npz"
        src.write_bytes(valid["npz"])
        with np.load(src, allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files if name != "xy"}
        path = _work(tmp_path_factory) / "huge.npz"
        np.savez(path, **arrays)
        with zipfile.ZipFile(path, "a") as z:
            z.writestr("xy.npy", _npy_bytes(header, b"\0" * 16))
        e = _outcome(read_npz, path)
        assert isinstance(e, InputError) and e.field == "xy", e
        assert "MemoryError" not in str(e)


def test_poses_declared_sizes_are_not_allocated(valid, tmp_path_factory):
    """poses.npz too: a header declaring a huge array (4 GB, 134 GiB, 4e20 bytes) is refused from
    its size, naming the member, and nothing near that size is allocated (numpy reports its
    buffers to tracemalloc), so no MemoryError can escape."""
    for header in _HEADERS[:4]:
        arrays = _members_of(valid, tmp_path_factory, "poses")
        del arrays["xyz"]
        path = _work(tmp_path_factory) / "poses.npz"
        np.savez(path, **arrays)
        with zipfile.ZipFile(path, "a") as z:
            z.writestr("xyz.npy", _npy_bytes(header, b"\0" * 16))
        tracemalloc.start()
        try:
            e = _outcome(load_poses, path)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert isinstance(e, InputError) and e.field == "xyz", e
        assert "MemoryError" not in str(e)
        assert peak < 2**24, f"{peak} bytes allocated reading a {path.stat().st_size}-byte file"


class _Plant:
    """Unpickling it makes a folder: evidence that a reader ran code from the file."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return os.mkdir, (self.path,)


def test_poses_pickled_members_are_refused_unread(valid, tmp_path_factory, tmp_path):
    marker = tmp_path / "unpickled"
    path = _work(tmp_path_factory) / "poses.npz"
    for member in (*POSES_MEMBERS, "timestamps", "extra"):
        arrays = _members_of(valid, tmp_path_factory, "poses")
        arrays[member] = np.array([_Plant(str(marker)), None], dtype=object)
        np.savez(path, **arrays)  # pickles the object array
        e = _outcome(load_poses, path)
        assert isinstance(e, InputError) and e.field == member, (member, e)
        assert "object arrays are refused" in str(e)
        assert not marker.exists(), f"{member}: the pickle ran"
    # The plant works: unpickling the last file's member does make the folder.
    with np.load(path, allow_pickle=True) as archive:
        archive["extra"]
    assert marker.is_dir()


def test_poses_truncated_files_are_refused(valid, tmp_path_factory):
    """Cut short (which loses the zip directory at the end, and members from mid-file on), the
    file is an InputError naming it, read directly or from its folder (more: test_mutated_bytes)."""
    data = valid["poses"]
    folder = _work(tmp_path_factory) / "cut"
    folder.mkdir(exist_ok=True)
    path = folder / "poses.npz"
    for cut in (0, 1, 4, 30, 100, len(data) // 2, len(data) - 22, len(data) - 1):
        path.write_bytes(data[:cut])
        for target in (path, folder):
            e = _outcome(load_poses, target)
            assert isinstance(e, InputError) and Path(e.file) == path, (cut, e)


@pytest.mark.parametrize("member", POSES_MEMBERS)
def test_poses_missing_members_are_named(valid, tmp_path_factory, member):
    arrays = _members_of(valid, tmp_path_factory, "poses")
    del arrays[member]
    path = _work(tmp_path_factory) / "poses.npz"
    np.savez(path, **arrays)
    e = _outcome(load_poses, path)
    assert isinstance(e, InputError) and e.field == member and "missing" in str(e), e


def test_sparse_files_cannot_ask_for_huge_arrays(tmp_path):
    """Padding is dense: a few hundred KB of JSON could ask for 161 GiB (20000 empty frames x 200
    cameras x one view of 300 people). Refused before allocating, naming the file."""
    kp = [[1.0, 2.0, 0.5]] * 18
    crowded = {"views": {"c0": [{"keypoints": kp}] * 300}}
    cameras = [f"c{i}" for i in range(200)]
    cases = {
        "people.json": {"cameras": cameras, "frames": [crowded] + [{}] * 19999},
        "frames.json": {"cameras": [f"c{i}" for i in range(2000)], "frames": [{}] * 20000},
        "gt.json": {
            "cameras": ["c0"],
            "frames": [{"ground_truth": [{"id": i} for i in range(1000)]}] + [{}] * 19999,
        },
        "original.json": [{f"c{i}": ["[]", 0.0, ""] for i in range(2000)}]
        + [{"c0": ["[]", 0.0, ""]}] * 20000,
    }
    for name, doc in cases.items():
        path = tmp_path / name
        path.write_text(json.dumps(doc))
        e = _outcome(load_recording, path)
        assert isinstance(e, InputError) and "would allocate" in str(e), (name, e)


# --------------------------------------------------------------------------- OpenPose folders

folder_edits = st.lists(
    st.one_of(
        st.tuples(st.just("remove"), st.integers(0, 10**6), st.none()),
        st.tuples(
            st.just("rename"),
            st.integers(0, 10**6),
            st.sampled_from(
                [
                    "x.json",
                    "frame.json",
                    "000000000007_keypoints.json",
                    "a_b_keypoints.json",
                    "9" * 30 + "_keypoints.json",
                    "000000000001_keypoints.json",
                    ".hidden.json",
                    "0_keypoints.JSON",
                    "notes.txt",
                ]
            ),
        ),
        st.tuples(
            st.just("stray"), st.integers(0, 10**6), st.sampled_from(["file", "dir", "root"])
        ),
        st.tuples(st.just("empty_camera"), st.integers(0, 10**6), st.none()),
        st.tuples(st.just("dir_for_file"), st.integers(0, 10**6), st.none()),
    ),
    min_size=1,
    max_size=3,
)


@HOSTILE
@given(edits=folder_edits)
def test_mutated_openpose_folders(valid, tmp_path_factory, edits):
    root = _openpose_copy(valid, tmp_path_factory)
    for op, pick, arg in edits:
        with contextlib.suppress(OSError):  # an edit the folder cannot take is skipped
            _edit_folder(root, op, pick, arg)
    rig = valid["rig"]
    for reader in OPENPOSE_READERS + [
        partial(load_recording, rig=rig),
        partial(load_recording, rig=rig.select(["trackera", "trackerb"])),
        partial(read_openpose, cameras=["trackerc", "trackera"], missing_frames="empty"),
    ]:
        _outcome(reader, root)


def _edit_folder(root: Path, op: str, pick: int, arg) -> None:
    files = sorted(p for p in root.rglob("*") if p.is_file())
    cams = sorted(p for p in root.iterdir() if p.is_dir())
    if op == "remove" and files:
        files[pick % len(files)].unlink()
    elif op == "rename" and files:
        f = files[pick % len(files)]
        f.rename(f.parent / arg)
    elif op == "stray":
        where = root if arg == "root" or not cams else cams[pick % len(cams)]
        if arg == "dir":
            (where / "sub.json").mkdir(exist_ok=True)
        else:
            (where / "stray.json").write_text('{"people": []}')
    elif op == "empty_camera" and cams:
        shutil.rmtree(cams[pick % len(cams)])
        cams[pick % len(cams)].mkdir()
    elif op == "dir_for_file" and files:
        files[pick % len(files)].unlink()
        files[pick % len(files)].mkdir()


_CONFIG = (
    "[project]\nframe_rate = 60\nframe_range = []\nexclude_from_batch = []\n\n"
    "[pose]\npose_model = 'COCO'\n"
)


def _pose2sim_copy(valid, tmp_path_factory) -> Path:
    """A fresh Pose2Sim session (session and trial Config.toml, a calibration folder, the valid
    OpenPose folder as a trial's pose/ with its camera folders renamed ``<camera>_json``)."""
    root = _work(tmp_path_factory) / "pose2sim"
    if root.exists():
        shutil.rmtree(root)
    trial = root / "P1" / "T1"
    for rel, data in valid["openpose"].items():
        camera, name = Path(rel).parts
        (trial / "pose" / f"{camera}_json").mkdir(parents=True, exist_ok=True)
        (trial / "pose" / f"{camera}_json" / name).write_bytes(data)
    (root / "Config.toml").write_text(_CONFIG)
    (trial / "Config.toml").write_text("[project]\nframe_range = [0, 3]\n")
    (root / "Calibration").mkdir()
    (root / "Calibration" / "calib.toml").write_bytes(valid["calib_toml"])
    return root


def _read_session(path: Path) -> Recording:
    """Every trial of a Pose2Sim session, read as `infer --session` would: the last one's frames."""
    from mvpose_jax.data.pose2sim import find_trials, open_trial

    recording = None
    for trial in find_trials(path).trials:
        with open_trial(trial) as stream:
            first, stop = trial.frame_span(stream.num_frames)
            recording = stream.read_frames(first, stop)
    assert recording is not None
    return recording


def test_the_valid_pose2sim_session_reads(valid, tmp_path_factory):
    rec = _outcome(_read_session, _pose2sim_copy(valid, tmp_path_factory))
    assert isinstance(rec, Recording) and rec.num_frames == 3


@pytest.mark.parametrize("config", ["Config.toml", "P1/T1/Config.toml", "Calibration/calib.toml"])
@HOSTILE
@given(edits=byte_edits, cut=cuts)
def test_mutated_pose2sim_configs(valid, tmp_path_factory, config, edits, cut):
    root = _pose2sim_copy(valid, tmp_path_factory)
    (root / config).write_bytes(_mutate_bytes((root / config).read_bytes(), edits, cut))
    _outcome(_read_session, root)


@HOSTILE
@given(
    key=st.sampled_from(["frame_rate", "frame_range", "exclude_from_batch", "pose_model"]),
    value=st.one_of(
        st.sampled_from(["nan", "inf", "-1", "0", "'auto'", "'all'", "[]", "[1]", "[2, 1]"]),
        st.sampled_from(["[0, 99999999999999999999]", "[-1, 2]", "{a = 1}", "true", "'BODY_25'"]),
        st.sampled_from(["[[1, 2]]", "['x', 1]", "'COCO_17'", "''", "1e308", "[0, 1.5]"]),
    ),
)
def test_mutated_pose2sim_settings(valid, tmp_path_factory, key, value):
    root = _pose2sim_copy(valid, tmp_path_factory)
    section = "pose" if key == "pose_model" else "project"
    (root / "P1" / "T1" / "Config.toml").write_text(f"[{section}]\n{key} = {value}\n")
    _outcome(_read_session, root)


@HOSTILE
@given(edits=folder_edits)
def test_mutated_pose2sim_trial_folders(valid, tmp_path_factory, edits):
    root = _pose2sim_copy(valid, tmp_path_factory)
    for op, pick, arg in edits:
        with contextlib.suppress(OSError):  # an edit the folder cannot take is skipped
            _edit_folder(root / "P1" / "T1" / "pose", op, pick, arg)
    _outcome(_read_session, root)


# --------------------------------------------------------------------------- failed saves


@pytest.mark.parametrize("fmt", ["native", "original", "npz", "openpose"])
@pytest.mark.parametrize("failure", ["serialise", "disk_full"])
def test_failed_save_leaves_no_partial_file(valid, tmp_path, monkeypatch, fmt, failure):
    """An exception midway through a save leaves the old file (or none) and no temporary file.

    OpenPose folders are written file by file: each file present afterwards is complete.
    """
    from mvpose_jax.data import native, npz, openpose, original

    rec = valid["recording"]
    if failure == "serialise":
        # Raised from inside the format's own serialisation, after part of the output is written.
        calls = {"n": 0}
        real_dumps = json.dumps

        def dumps(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] >= 2:
                raise RuntimeError("boom inside serialisation")
            return real_dumps(*args, **kwargs)

        def savez_half(f, **arrays):
            f.write(b"PK\x03\x04 half an archive")
            raise RuntimeError("boom inside serialisation")

        module = {"native": native, "original": original, "openpose": openpose}.get(fmt)
        if module is None:
            monkeypatch.setattr(npz.np, "savez_compressed", savez_half)
        else:
            monkeypatch.setattr(module.json, "dumps", dumps)
        expected = RuntimeError
    else:
        # The disk fills up: a file's writes fail after 50 bytes.
        real_fdopen = os.fdopen

        class Full:
            def __init__(self, f):
                self._f, self._left = f, 50

            def write(self, data):
                if len(data) > self._left:
                    self._f.write(data[: self._left])
                    raise OSError(28, "No space left on device")
                self._left -= len(data)
                return self._f.write(data)

            def __getattr__(self, name):
                return getattr(self._f, name)

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                return self._f.__exit__(*exc)

        monkeypatch.setattr(files_module.os, "fdopen", lambda *a, **k: Full(real_fdopen(*a, **k)))
        expected = OSError

    if fmt == "openpose":
        target = tmp_path / "op"
        with pytest.raises(expected):
            save_recording(rec, target, format=fmt)
        written = [p for p in target.rglob("*") if p.is_file()]
        for p in written:
            assert json.loads(p.read_text())["people"] is not None, p
        if failure == "serialise":  # the first file was written whole, the second not at all
            assert len(written) == 1
    else:
        new = tmp_path / f"new.{'npz' if fmt == 'npz' else 'json'}"
        old = tmp_path / f"old.{'npz' if fmt == 'npz' else 'json'}"
        old.write_bytes(b"old contents")
        for path in (new, old):
            with pytest.raises(expected):
                save_recording(rec, path, format=fmt)
        assert not new.exists()
        assert old.read_bytes() == b"old contents"
    leftovers = [p.name for p in tmp_path.rglob("*") if p.name.startswith(".")]
    assert not leftovers, leftovers


# --------------------------------------------------------------------------- no pickles


def test_no_code_path_unpickles():
    """An AST scan of the package: no pickle imports, no allow_pickle=True, and every np.load
    passes allow_pickle=False explicitly (numpy's default has changed before)."""
    package = Path(mvpose_jax.__file__).parent
    problems = []
    unpicklers = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "joblib", "shelve"}
    unpicklers.add("marshal")
    for file in sorted(package.rglob("*.py")):
        tree = ast.parse(file.read_text(), filename=str(file))
        where = lambda node: f"{file.relative_to(package.parent)}:{node.lineno}"  # noqa: E731
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name.split(".")[0] for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [(node.module or "").split(".")[0]]
            else:
                names = []
            problems += [f"{where(node)} imports {n}" for n in names if n in unpicklers]
            if isinstance(node, ast.Call):
                kw = {k.arg: k.value for k in node.keywords}
                allow = kw.get("allow_pickle")
                if allow is not None and not (
                    isinstance(allow, ast.Constant) and allow.value is False
                ):
                    problems.append(f"{where(node)} passes allow_pickle={ast.unparse(allow)}")
                func = ast.unparse(node.func)
                if (
                    func.split(".")[-1] == "load"
                    and func.split(".")[0] in ("np", "numpy", "jnp")
                    and allow is None
                ):
                    problems.append(f"{where(node)} calls {func} without allow_pickle=False")
                if func.split(".")[-1] in ("loads", "load") and func.split(".")[0] in unpicklers:
                    problems.append(f"{where(node)} calls {func}")
    assert not problems, "\n".join(problems)


# --------------------------------------------------------------------------- helpers


def _work(tmp_path_factory) -> Path:
    """One scratch folder for the whole module (hypothesis reruns a test body many times)."""
    global _WORK
    if _WORK is None:
        _WORK = tmp_path_factory.mktemp("hostile")
    return _WORK


_WORK: Path | None = None


def _openpose_copy(valid, tmp_path_factory) -> Path:
    """A fresh copy of the valid OpenPose folder."""
    root = _work(tmp_path_factory) / "openpose"
    if root.exists():
        shutil.rmtree(root)
    for rel, data in valid["openpose"].items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root
