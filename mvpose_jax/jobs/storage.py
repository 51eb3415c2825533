"""Where a batch's results go: a local path, or an fsspec URL (``s3://bucket/run``,
``gs://...``, ``abfs://...``, ``file:///shared/run``) that every machine of a cluster reaches.

A local output is written in place, atomically, as every job writes. A URL output is written by
its worker into a local staging folder first (`staging`), as a local run would write it, and
then published (`publish`): each file is uploaded under a temporary name and moved onto its own
name, so a reader never sees a half-written file; the recording counts as done only once the run
manifest (written the same way, by the driver) says so. Object stores have no atomic rename of
a folder: a recording whose worker died mid-upload may leave some of its files, which its retry
overwrites.

fsspec is imported only for a URL (``pip install "mvpose-jax[cluster]"`` adds it; a store's own
filesystem too: ``s3fs``, ``gcsfs``, ``adlfs``).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

from mvpose_jax.data.files import atomic_write_text, read_json
from mvpose_jax.errors import InputError, MvposeError

INSTALL_HINT = (
    'outputs at a URL are written with fsspec: pip install "mvpose-jax[cluster]" (and the '
    "store's filesystem: s3fs, gcsfs or adlfs)"
)


def is_url(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an fsspec URL (``protocol://...``), not a local path."""
    return "://" in str(path)


def join(base: str | os.PathLike, *parts: str) -> str:
    """``base``/``parts``: '/'-separated for a URL, the system's separator for a path."""
    if is_url(base):
        return "/".join([str(base).rstrip("/"), *(p.strip("/") for p in parts)])
    return os.path.join(base, *parts)


def _filesystem(url: str):
    """(fsspec filesystem, path within it) of ``url``."""
    try:
        import fsspec
    except ImportError:
        raise MvposeError(INSTALL_HINT) from None
    try:
        return fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as e:  # an unknown protocol, or its package missing
        raise InputError(f"cannot open this URL ({e})", file=url, field="--out") from None


def exists(path: str | os.PathLike) -> bool:
    if not is_url(path):
        return os.path.exists(path)
    fs, where = _filesystem(str(path))
    return fs.exists(where)


def make_folder(path: str | os.PathLike) -> None:
    """Creates the folder ``path`` (and its parents) where there is none; object stores have no
    folders, and need none."""
    if not is_url(path):
        Path(path).mkdir(parents=True, exist_ok=True)
        return
    fs, where = _filesystem(str(path))
    with contextlib.suppress(FileExistsError):
        fs.makedirs(where, exist_ok=True)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Writes ``text`` (UTF-8) to ``path`` atomically: a reader sees the old file or the new."""
    if not is_url(path):
        atomic_write_text(path, text)
        return
    fs, where = _filesystem(str(path))
    partial = f"{where}.partial-{uuid.uuid4().hex[:12]}"
    with fs.open(partial, "wb") as f:
        f.write(text.encode("utf-8"))
    fs.mv(partial, where)


def read_json_at(path: str | os.PathLike):
    """`data.files.read_json` of a path or a URL (fetched to a temporary file, so that a bad
    document is reported as for a local one, naming the URL)."""
    if not is_url(path):
        return read_json(path)
    fs, where = _filesystem(str(path))
    with tempfile.TemporaryDirectory(prefix="mvpose-jax-") as tmp:
        local = Path(tmp) / Path(where).name
        try:
            fs.get(where, str(local))
        except FileNotFoundError:
            raise InputError("no such file", file=path) from None
        try:
            return read_json(local)
        except InputError as e:
            raise InputError(e.reason, file=path, field=e.field) from None


@contextlib.contextmanager
def staging(out: str) -> Iterator[Path | None]:
    """For a URL ``out``: a local temporary folder to write the results into before
    `publish` (removed at the end, whatever happens); for a path: None (write in place)."""
    if not is_url(out):
        yield None
        return
    _filesystem(out)  # an unusable URL fails before the work
    folder = Path(tempfile.mkdtemp(prefix="mvpose-jax-batch-"))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def publish(local: str | os.PathLike, url: str) -> int:
    """Uploads the file or folder ``local`` to ``url`` (a folder: every file below it, at the
    same relative path, in sorted order), each file under a temporary name first and then moved
    onto its own (`write_text`'s promise, per file). Returns the files uploaded."""
    fs, where = _filesystem(url)
    local = Path(local)
    if local.is_file():
        files = [(local, where)]
    else:
        files = [
            (f, f"{where.rstrip('/')}/{f.relative_to(local).as_posix()}")
            for f in sorted(local.rglob("*"))
            if f.is_file()
        ]
    token = uuid.uuid4().hex[:12]
    for source, target in files:
        parent = target.rsplit("/", 1)[0]
        with contextlib.suppress(FileExistsError):
            fs.makedirs(parent, exist_ok=True)
        partial = f"{target}.partial-{token}"
        fs.put_file(str(source), partial)
        fs.mv(partial, target)
    return len(files)
