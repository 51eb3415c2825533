"""Compiled programs: trained models' jitted functions, built once per model structure (matching
and lifting share them), the compiler options of the geometry's and the matcher's programs, and
the on-disk cache that keeps compiled programs between processes."""

from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

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


# ------------------------------------------------------------------------- XLA's own CPU kernels

# XLA:CPU hands dots, and the elementwise work around them, to YNNPACK fusions. On the small
# arrays of geometry (3x3 matrices, a frame's few skeletons) a fusion costs more to launch than
# its arithmetic: XLA's own kernels run the epipolar distances of a live frame in 131 against
# 228 us, and of a 32-frame chunk in 1.4 against 3.6 ms; the matcher's GAT on a chunk in 14.3
# against 18.5 ms; robust triangulation is equal live and 16 against 19 ms on a chunk of 1,024
# people (2-core AMD EPYC, min of 300 interleaved calls; docs/performance.md). The estimator's
# MLP is the exception: on a live frame's few people YNNPACK's matrix-vector kernels are faster
# (0.34 against 0.50 ms), so its programs keep the default. Training is the other way round:
# the matcher's and the estimator's train steps (`train.make_train_step`'s ``xla_kernels``) run
# 13 and 17 % faster with XLA's kernels (the quick scale's 5-view GAT and its MLP). The numbers
# are the same arithmetic in another order: groupings and tracks identical, keypoints within
# float32 rounding; a training run departs from the default kernels' at rounding and ends in
# other weights of the same quality (the main job's tables, docs/performance.md).
XLA_CPU_KERNELS = {"xla_cpu_experimental_ynn_fusion_type": ""}


@functools.cache
def xla_kernel_options() -> dict[str, str]:
    """`XLA_CPU_KERNELS` where the default backend is the CPU and its XLA knows the option, else
    none (a GPU, or a jax whose CPU compiler dropped the experimental flag)."""
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1, compiler_options=XLA_CPU_KERNELS).lower(1.0).compile()
    except Exception:  # an unknown option: the defaults
        return {}
    return dict(XLA_CPU_KERNELS)


def jit(fun: Callable | None = None, /, **jit_kwargs) -> Callable:
    """``jax.jit(fun, **jit_kwargs)`` compiled with `xla_kernel_options` (a decorator too).

    The jitted functions are made at the first call (the options need the backend, which the
    import must not start). Called on tracers, inside another program, it is traced into that
    program without options of its own (jax takes them only at the top level): the caller's
    options apply.
    """
    if fun is None:
        return functools.partial(jit, **jit_kwargs)
    jitted: list[Callable] = []  # [top level, nested]

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if not jitted:
            options = xla_kernel_options()
            jitted.append(jax.jit(fun, compiler_options=options or None, **jit_kwargs))
            jitted.append(jax.jit(fun, **jit_kwargs) if options else jitted[0])
        nested = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((args, kwargs)))
        return jitted[nested](*args, **kwargs)

    # Traced shapes of both, as jax.jit's own counts them (what the no-recompilation tests read).
    call._cache_size = lambda: sum(f._cache_size() for f in {id(f): f for f in jitted}.values())
    return call


# ------------------------------------------------------------------- host values kept per object


def kept_per_object(table: dict, obj: Any, make: Callable[[], Any], max_entries: int) -> Any:
    """``make()``, computed once per object ``obj`` (by identity) and kept in ``table``.

    For values read off immutable objects (a rig's arrays fetched to the host, a model's static
    attributes) on a hot path, where hashing the object, or recomputing, costs more than a
    lookup. Each entry keeps its object, so an id is never reused while the entry is there; the
    table is emptied when it holds ``max_entries``.
    """
    hit = table.get(id(obj))
    if hit is None or hit[0] is not obj:
        if len(table) >= max_entries:
            table.clear()
        hit = table[id(obj)] = (obj, make())
    return hit[1]


# ------------------------------------------------------------------------ models' jitted functions

# Models are called through jit-compiled functions with their NNX GraphDef closed over, one per
# GraphDef: passed as a static argument, a GraphDef is hashed on every call, and hashing one
# costs about 70 µs (a twentieth of a frame's 3D stage). Equal GraphDefs share one function (and
# its compiled programs); the id cache keeps a strong reference, so an id is never reused.
_BOUND_BY_ID: dict[tuple, tuple] = {}
_BOUND_BY_VALUE: dict[tuple, Callable] = {}
_MAX_BOUND = 256


def bound_model_fn(fn: Callable, graphdef, *, xla_kernels: bool = False) -> Callable:
    """``jax.jit(functools.partial(fn, graphdef))``, built once per (fn, GraphDef).

    ``fn(graphdef, *args)`` must be a pure function of arrays besides its GraphDef.
    ``xla_kernels``: compiled with `xla_kernel_options` (the matcher's programs; the
    estimator's keep the defaults, faster on a live frame's few people).
    """
    key = (fn, xla_kernels)
    hit = _BOUND_BY_ID.get((key, id(graphdef)))
    if hit is not None and hit[0] is graphdef:
        return hit[1]
    if len(_BOUND_BY_ID) >= _MAX_BOUND:
        _BOUND_BY_ID.clear()
        _BOUND_BY_VALUE.clear()
    jitted = _BOUND_BY_VALUE.get((key, graphdef))
    if jitted is None:
        options = xla_kernel_options() if xla_kernels else None
        jitted = jax.jit(functools.partial(fn, graphdef), compiler_options=options)
        _BOUND_BY_VALUE[(key, graphdef)] = jitted
    _BOUND_BY_ID[(key, id(graphdef))] = (graphdef, jitted)
    return jitted
