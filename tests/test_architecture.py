"""The house rules, checked with the suite: the import contracts of pyproject.toml hold
(import-linter), the linter finds nothing and the formatter would change nothing (ruff)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=300, check=False)


def test_import_contracts_are_kept():
    lint_imports = Path(sys.executable).with_name("lint-imports")
    if not lint_imports.exists():
        pytest.fail(f"{lint_imports} is missing: install the test extra (pip install '.[test]')")
    out = _run([str(lint_imports), "--no-cache"])
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "0 broken" in out.stdout


def test_ruff_finds_nothing():
    out = _run([sys.executable, "-m", "ruff", "check", "."])
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]


def test_the_formatter_would_change_nothing():
    out = _run([sys.executable, "-m", "ruff", "format", "--check", "."])
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
