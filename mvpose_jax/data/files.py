"""File edges shared by every format: atomic output and checked JSON/TOML input.

Output is atomic: written to a temporary file in the same folder, then renamed over the target, so
a reader never sees a half-written file and a crash leaves the old file (or none) in place.
Input raises `InputError` naming the file (and line/column) for missing, empty or malformed files.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from mvpose_jax.errors import InputError


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """Opens a temporary file beside ``path``; on success renames it to ``path``.

    Args:
      path: the final file.
      mode: ``"w"`` (text, UTF-8 unless ``encoding`` is given) or ``"wb"``.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open writes only, mode 'w' or 'wb', not {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if mode == "w":
        kwargs.setdefault("encoding", "utf-8")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp makes the file private (0600); give it the permissions open() would have.
        os.chmod(tmp, 0o666 & ~_umask())
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Writes ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_open(path, "w") as f:
        f.write(text)


def _read_text(path: str | os.PathLike) -> str:
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("no such file", file=path) from None
    except IsADirectoryError:
        raise InputError("is a folder, expected a file", file=path) from None
    except OSError as e:
        raise InputError(f"cannot read ({e.strerror})", file=path) from None
    if not data.strip():
        raise InputError("file is empty", file=path)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"not UTF-8 text (byte {e.start})", file=path) from None


def read_json(path: str | os.PathLike) -> Any:
    """Parses a JSON file; raises InputError (with line and column) when it cannot."""
    import json

    text = _read_text(path)
    try:
        # NaN/Infinity are not JSON; refuse them here rather than let them reach the arrays.
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as e:
        raise InputError(
            f"malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}", file=path
        ) from None
    except _NonFinite as e:
        raise InputError(f"non-finite number {e.args[0]} in JSON", file=path) from None
    except RecursionError:
        raise InputError("JSON nested too deeply", file=path) from None
    except ValueError as e:  # e.g. an integer beyond Python's digit limit for str -> int
        raise InputError(f"unreadable JSON ({e})", file=path) from None


def read_toml(path: str | os.PathLike) -> dict[str, Any]:
    """Parses a TOML file; raises InputError when it cannot."""
    import tomllib

    text = _read_text(path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"malformed TOML: {e}", file=path) from None
    except RecursionError:
        raise InputError("TOML nested too deeply", file=path) from None
    except ValueError as e:  # e.g. an integer beyond Python's digit limit for str -> int
        raise InputError(f"unreadable TOML ({e})", file=path) from None


class _NonFinite(ValueError):
    pass


def _reject_constant(name: str):
    raise _NonFinite(name)


def to_jsonable(value: Any) -> Any:
    """``value`` with tuples as lists, dict keys as strings and numpy scalars and arrays as Python
    numbers and lists, as JSON holds it (so a config compares equal to its saved form)."""
    import numpy as np

    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


def check_writable(path: str | os.PathLike, *, folder: bool, field: str = "--out") -> Path:
    """Refuses, before any work, an output that could not be written: a file where a folder
    must go (or a folder where a file must go), or a place whose nearest existing folder is not
    writable. Creates nothing.

    Raises:
      InputError naming the path and the option.
    """
    path = Path(path)
    if path.exists():
        if folder and not path.is_dir():
            raise InputError("is a file, but an output folder must go here", file=path, field=field)
        if not folder and path.is_dir():
            raise InputError("is a folder, but an output file must go here", file=path, field=field)
    parent = path if (folder and path.is_dir()) else path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(
            f"{parent} is a file, so nothing can be written below it", file=path, field=field
        )
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot write in {parent} (permission denied)", file=path, field=field)
    if path.exists() and not os.access(path, os.W_OK):
        raise InputError("cannot be overwritten (permission denied)", file=path, field=field)
    return path
