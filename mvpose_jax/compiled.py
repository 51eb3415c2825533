"""Compiled programs: trained models' jitted functions, built once per model structure (matching
and lifting share them), and the on-disk cache that keeps compiled programs between processes."""

from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Callable
from pathlib import Path

import jax

from mvpose_jax.errors import MvposeWarning

# ---------------------------------------------------------------------------- the on-disk cache

# Where the command line and the experiments keep compiled programs (a folder; "off" disables).
CACHE_ENV = "MVPOSE_JAX_COMPILATION_CACHE"
_OFF = ("0", "off", "false", "no", "none")
# A bound on the folder (jax evicts the least recently used programs past it; needs filelock).
CACHE_MAX_BYTES = 2 << 30
# Programs that compile faster than this are not worth a file (a read costs about as much).
CACHE_MIN_COMPILE_SECONDS = 0.05


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/mvpose-jax/xla`` (``~/.cache/mvpose-jax/xla`` by default)."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "mvpose-jax" / "xla"


def enable_compilation_cache(directory: str | os.PathLike | None = None) -> Path | None:
    """Keeps XLA's compiled programs on disk, so that the next process skips their compilation.

    Most of a short job's time is compilation (`mvpose-jax infer` with models on the Pose2Sim
    demo: 30 s cold, 10 s with the cache warm; docs/performance.md). jax keys each program by its
    computation, compile options, jax version and device, so a cached program is the program a
    compile would give: results do not change. Call before the first compilation that should be
    kept (the command line and `experiments.run` call it first thing). The folder is set in the
    environment too, so that processes started from this one (batch workers) share it; it is
    bounded (`CACHE_MAX_BYTES`, least recently used programs evicted) and safe to share between
    processes when ``filelock`` is installed (a dependency of the package).

    Args:
      directory: the folder; default ``$MVPOSE_JAX_COMPILATION_CACHE``, else `default_cache_dir`.
        "off" (or 0, false, no, none) disables the cache.
    Returns:
      The folder in use, or None when the cache is off. A cache already configured for jax
      (``JAX_COMPILATION_CACHE_DIR`` or ``jax_compilation_cache_dir``) is kept as it is.
    """
    configured = os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir
    if configured:
        return Path(configured)
    value = os.fspath(directory) if directory is not None else os.environ.get(CACHE_ENV, "")
    if value.strip().lower() in _OFF:
        return None
    path = Path(value).expanduser() if value.strip() else default_cache_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK):
            raise PermissionError(f"not writable: {path}")
    except OSError as e:
        warnings.warn(
            f"compiled programs are not kept between runs: cannot use {path} ({e}); set "
            f"{CACHE_ENV} to a writable folder, or to 'off'",
            MvposeWarning,
            stacklevel=2,
        )
        return None
    try:
        import filelock  # noqa: F401  (jax's eviction takes a file lock)

        max_bytes = CACHE_MAX_BYTES
    except ImportError:  # unbounded, as jax leaves it
        max_bytes = -1
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", max_bytes)
    # Inherited by the processes this one starts (jax reads these at import).
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(path)
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(CACHE_MIN_COMPILE_SECONDS)
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] = str(max_bytes)
    return path


# ------------------------------------------------------------------------ models' jitted functions

# Models are called through jit-compiled functions with their NNX GraphDef closed over, one per
# GraphDef: passed as a static argument, a GraphDef is hashed on every call, and hashing one
# costs about 70 µs (a twentieth of a frame's 3D stage). Equal GraphDefs share one function (and
# its compiled programs); the id cache keeps a strong reference, so an id is never reused.
_BOUND_BY_ID: dict[tuple, tuple] = {}
_BOUND_BY_VALUE: dict[tuple, Callable] = {}
_MAX_BOUND = 256


def bound_model_fn(fn: Callable, graphdef) -> Callable:
    """``jax.jit(functools.partial(fn, graphdef))``, built once per (fn, GraphDef).

    ``fn(graphdef, *args)`` must be a pure function of arrays besides its GraphDef.
    """
    hit = _BOUND_BY_ID.get((fn, id(graphdef)))
    if hit is not None and hit[0] is graphdef:
        return hit[1]
    if len(_BOUND_BY_ID) >= _MAX_BOUND:
        _BOUND_BY_ID.clear()
        _BOUND_BY_VALUE.clear()
    jitted = _BOUND_BY_VALUE.get((fn, graphdef))
    if jitted is None:
        jitted = _BOUND_BY_VALUE[(fn, graphdef)] = jax.jit(functools.partial(fn, graphdef))
    _BOUND_BY_ID[(fn, id(graphdef))] = (graphdef, jitted)
    return jitted
