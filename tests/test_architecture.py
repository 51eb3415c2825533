"""The house rules, checked with the suite: the import contracts of pyproject.toml hold
(import-linter), no module imports itself round a circle (type-only imports included), the linter
finds nothing and the formatter would change nothing (ruff)."""

from __future__ import annotations

import ast
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


def import_graph(package_dir: Path) -> dict[str, set[str]]:
    """Which modules of the package each of its modules imports: every import statement counts,
    at module level, inside functions and under ``if TYPE_CHECKING:`` alike (import-linter leaves
    the last out; a type-only import is still a circle between the two modules).

    ``from pkg.sub import name`` counts as importing ``pkg.sub.name`` when that is a module, else
    ``pkg.sub``; a package is its ``__init__``, and importing a submodule does not count as
    importing its parent package.
    """
    root = package_dir.name
    modules = {}
    for path in package_dir.rglob("*.py"):
        parts = path.relative_to(package_dir.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = path
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                for a in node.names:
                    child = f"{base}.{a.name}"
                    targets.add(child if child in modules else base)
        graph[name] = {t for t in targets if t in modules and t != name and t.split(".")[0] == root}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The circles of an import graph: one per strongly connected group of two or more modules,
    as a path that returns to its start (Tarjan's algorithm, then a walk inside the group)."""
    index, low, on_stack, stack, groups = {}, {}, set(), [], []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.add(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(group)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    cycles = []
    for group in groups:
        start = min(group)
        path, seen = [start], {start}
        while True:  # every module of the group reaches the start inside it: walk until back
            nxt = sorted(w for w in graph[path[-1]] if w in group)
            back = [w for w in nxt if w == start]
            if back and len(path) > 1:
                cycles.append([*path, start])
                break
            fresh = [w for w in nxt if w not in seen]
            step = fresh[0] if fresh else nxt[0]
            if step in seen and step != start:
                i = path.index(step)
                cycles.append([*path[i:], step])
                break
            path.append(step)
            seen.add(step)
    return cycles


def test_the_circle_finder_sees_type_only_and_function_level_imports(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from .c import C\n")
    (pkg / "a.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.b import B\n"
    )
    (pkg / "b.py").write_text("import numpy\nfrom pkg import a\n")
    (pkg / "sub" / "c.py").write_text("def f():\n    from ..b import B\n")
    (pkg / "d.py").write_text("from pkg.sub.c import f\n")
    graph = import_graph(pkg)
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}
    assert graph["pkg.sub"] == {"pkg.sub.c"} and graph["pkg.sub.c"] == {"pkg.b"}
    assert graph["pkg.d"] == {"pkg.sub.c"}  # not its parent package
    assert import_cycles(graph) == [["pkg.a", "pkg.b", "pkg.a"]]
    (pkg / "b.py").write_text("import numpy\n")
    assert import_cycles(import_graph(pkg)) == []


def test_no_module_of_the_package_imports_itself_round_a_circle():
    cycles = import_cycles(import_graph(ROOT / "mvpose_jax"))
    assert not cycles, "import circles (type-only imports count): " + "; ".join(
        " -> ".join(c) for c in cycles
    )
