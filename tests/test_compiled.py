"""The on-disk cache of compiled programs (`compiled.enable_compilation_cache`).

Each case runs in a fresh Python process: jax's cache settings are process-wide, and the suite's
own processes already use a cache (conftest.py), which the function must leave as it is.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mvpose_jax.compiled import CACHE_ENV, enable_compilation_cache, kept_per_object

# Enables the cache as the command line does, compiles one program, and reports what jax did.
SCRIPT = """
import json, sys, warnings
warnings.simplefilter("always")
import jax, jax.numpy as jnp
from mvpose_jax.compiled import enable_compilation_cache
events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
with warnings.catch_warnings(record=True) as caught:
    folder = enable_compilation_cache()
# Cache every program, however fast it compiles (the default skips the quickest ones).
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
x = jnp.linspace(0.0, 1.0, 64).reshape(8, 8)
y = jax.jit(lambda a: jnp.tanh(a @ a.T).sum(0))(x)
print(json.dumps({
    "folder": None if folder is None else str(folder),
    "jax_dir": jax.config.jax_compilation_cache_dir,
    "hits": events.count("/jax/compilation_cache/cache_hits"),
    "warnings": [str(w.message) for w in caught],
    "y": [float(v) for v in y],
}))
"""


def _run(env_changes: dict[str, str], tmp_path: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env.pop(CACHE_ENV, None)
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    env.update(env_changes)
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def _programs(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name.endswith("-cache")]


def test_a_second_process_loads_the_first_ones_programs(tmp_path):
    folder = tmp_path / "programs"
    first = _run({CACHE_ENV: str(folder)}, tmp_path)
    assert first["folder"] == str(folder) == first["jax_dir"]
    assert first["hits"] == 0 and _programs(folder)
    second = _run({CACHE_ENV: str(folder)}, tmp_path)
    assert second["hits"] >= 1
    assert second["y"] == first["y"]  # the cached program is the compiled one: same numbers
    assert not first["warnings"] and not second["warnings"]


def test_the_default_folder_is_under_the_user_cache(tmp_path):
    res = _run({}, tmp_path)
    expected = tmp_path / "xdg" / "mvpose-jax" / "xla"
    assert res["folder"] == str(expected) and _programs(expected)


@pytest.mark.parametrize("off", ["off", "0", "False", "none"])
def test_off_keeps_nothing(tmp_path, off):
    res = _run({CACHE_ENV: off}, tmp_path)
    assert res["folder"] is None and res["jax_dir"] is None
    assert not (tmp_path / "xdg").exists()


def test_a_folder_that_cannot_be_made_warns_and_runs_without(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    res = _run({CACHE_ENV: str(blocker / "programs")}, tmp_path)
    assert res["folder"] is None and res["jax_dir"] is None
    assert len(res["warnings"]) == 1 and CACHE_ENV in res["warnings"][0]
    assert str(blocker / "programs") in res["warnings"][0]
    assert len(res["y"]) == 8  # the job itself goes on


def test_a_cache_configured_for_jax_is_kept(tmp_path):
    theirs = tmp_path / "theirs"
    res = _run(
        {"JAX_COMPILATION_CACHE_DIR": str(theirs), CACHE_ENV: str(tmp_path / "ours")}, tmp_path
    )
    assert res["folder"] == str(theirs) == res["jax_dir"]
    assert not (tmp_path / "ours").exists()
    # In this process too: the suite's own cache (conftest.py) stays.
    assert enable_compilation_cache(tmp_path / "mine") == Path(
        os.environ["JAX_COMPILATION_CACHE_DIR"]
    )
    assert not (tmp_path / "mine").exists()


# ------------------------------------------------------------------------ compiled.jit's options


def test_jit_compiles_with_xla_kernels_at_the_top_and_traces_into_callers():
    import jax
    import jax.numpy as jnp
    import numpy as np

    from mvpose_jax import compiled

    @compiled.jit(static_argnames="power")
    def f(a, b, *, power):
        return jnp.einsum("ij,njk->nik", a, b) ** power

    rng = np.random.default_rng(0)
    a = rng.normal(size=(3, 3)).astype(np.float32)
    b = rng.normal(size=(7, 3, 4)).astype(np.float32)
    expected = np.einsum("ij,njk->nik", a.astype(np.float64), b) ** 2
    np.testing.assert_allclose(np.asarray(f(a, b, power=2)), expected, rtol=1e-5, atol=1e-5)
    # Inside another program it is traced without options of its own (jax refuses nested ones).
    outer = jax.jit(lambda a, b: f(a, b, power=2) + 1.0)
    np.testing.assert_allclose(np.asarray(outer(a, b)), expected + 1.0, rtol=1e-5, atol=1e-5)
    assert f._cache_size() == 1  # the top-level program; the nested trace is the caller's
    options = compiled.xla_kernel_options()
    if jax.default_backend() == "cpu":
        assert options == compiled.XLA_CPU_KERNELS  # this jax's XLA knows the option
        top = jax.jit(lambda a, b: f(a, b, power=2), compiler_options=options)
        text = top.lower(a, b).compile().as_text()
        assert "ynn" not in text.lower()
    else:
        assert options == {}


def test_kept_per_object_computes_once_per_object_and_stays_bounded():
    table: dict = {}
    calls: list[str] = []

    def make(name):
        calls.append(name)
        return name.upper()

    a, b = ["a"], ["b"]  # unhashable, as rigs' arrays are: only their identity keys the table
    for _ in range(3):
        assert kept_per_object(table, a, lambda: make("a"), max_entries=2) == "A"
        assert kept_per_object(table, b, lambda: make("b"), max_entries=2) == "B"
    assert calls == ["a", "b"]
    c = ["c"]
    assert kept_per_object(table, c, lambda: make("c"), max_entries=2) == "C"
    assert len(table) == 1  # full at two entries: emptied, then c kept
    assert kept_per_object(table, a, lambda: make("a"), max_entries=2) == "A"
    assert calls == ["a", "b", "c", "a"]
