"""Shared fixtures (builders live in `tests/helpers.py`). Rank promotion raises, so shape bugs fail loudly instead of broadcasting."""

from __future__ import annotations

import os
import shutil
import tempfile

# One compilation cache for the whole run, shared by the parallel workers and the CLI
# subprocesses (they inherit the environment): the experiments' smoke runs, the benchmarks' smoke
# run and many tests compile the same programs, and XLA's compiles are most of the suite's time.
# A fresh folder per run (made by the first process, removed by it at the end), so no test ever
# sees another version's programs; jax keys its entries by program, options and version anyway.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="mvpose-jax-tests-")
    _OWN_CACHE = os.environ["JAX_COMPILATION_CACHE_DIR"]
else:
    _OWN_CACHE = None
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
# XLA's optimisation passes are most of a compile and buy nothing on the tests' tiny arrays:
# off, the suite's CPU time about halves (the default smoke experiment: 115 -> 61 s). Results
# are the same programs' (tolerances unchanged); speed is measured in benchmarks/, optimised.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")

import jax
import pytest

jax.config.update("jax_numpy_rank_promotion", "raise")

from mvpose_jax.data.calibration import PRESETS, load_preset  # noqa: E402
from tests.helpers import random_rig  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drops every compiled program after each test module. A worker process runs many modules,
    and each XLA:CPU executable it keeps holds its own memory maps: after ~15 modules a worker
    held 65,000 maps, Linux's default `vm.max_map_count` (65,530), and the next compile
    segfaulted (in XLA, while serialising the program for the cache). The persistent cache
    (above) makes the programs a later module needs again cheap to get back."""
    yield
    jax.clear_caches()


def pytest_unconfigure(config):
    if _OWN_CACHE is not None:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


@pytest.fixture(scope="session", params=PRESETS)
def preset_rig(request):
    """Each rig preset in turn."""
    return load_preset(request.param)


@pytest.fixture(scope="session")
def ring_rig():
    return random_rig()
