"""Structure rules of the numerical core and the in-flight stages (issue 24): the in-flight estimator imports
nothing of the shell, core classes stay small, and the in-flight modules form no import cycle (counting the
imports behind TYPE_CHECKING and inside functions)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "magcomp"
#: the most methods (properties included) a class of magcomp/core may have
MAX_CORE_METHODS = 15
#: modules that must sit in no import cycle
ACYCLIC = (
    "magcomp.core.inflight",
    "magcomp.core.autopilot_params",
    "magcomp.service.inflight_stage",
    "magcomp.service.record",
    "magcomp.service.align",
    "magcomp.service.attitude",
    "magcomp.service.calibrate",
    "magcomp.service.compass",
    "magcomp.service.theta",
)


def _module_name(path: Path) -> str:
    name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
    return name.removesuffix(".__init__")


def _import_graph() -> dict[str, set[str]]:
    """Every module of the package -> the package's modules it imports anywhere in its text (top level,
    functions, TYPE_CHECKING blocks); a package's own submodules importing it are not counted."""
    paths = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in paths}
    for mod, path in paths.items():
        pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
                    base = ".".join(parts + ([node.module] if node.module else []))
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            for t in targets:
                while t and t not in paths:
                    t = t.rsplit(".", 1)[0] if "." in t else ""
                if t and t != mod and not mod.startswith(t + "."):
                    graph[mod].add(t)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[set[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = set()
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.add(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(comp)
    return out


def test_importing_the_inflight_estimator_loads_nothing_of_the_shell() -> None:
    code = (
        "import sys, magcomp.core.inflight, magcomp.core.autopilot_params\n"
        "bad = sorted(m for m in sys.modules if m.startswith(('magcomp.service', 'magcomp.adapters')))\n"
        "print(';'.join(bad))\n"
        "assert 'magcomp.core.inflight.estimator' in sys.modules\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "", out.stdout


def test_no_core_class_has_more_than_fifteen_methods() -> None:
    big = []
    n_classes = 0
    for path in sorted((PACKAGE / "core").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                n_classes += 1
                n = sum(isinstance(b, ast.FunctionDef | ast.AsyncFunctionDef) for b in node.body)
                if n > MAX_CORE_METHODS:
                    big.append(f"{path.relative_to(ROOT)} {node.name}: {n}")
    assert n_classes > 10  # the walk found the core's classes: the test can fail
    assert not big, big


def test_the_cycle_finder_finds_a_cycle() -> None:
    """The finder itself, on a graph with one cycle through TYPE_CHECKING-like edges and one chain."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _cycles(graph) == [{"a", "b", "c"}]


@pytest.mark.parametrize("module", ACYCLIC)
def test_the_inflight_modules_sit_in_no_import_cycle(module: str) -> None:
    graph = _import_graph()
    assert any(m == module or m.startswith(module + ".") for m in graph), module  # the name is right
    for comp in _cycles(graph):
        mine = sorted(m for m in comp if m == module or m.startswith(module + "."))
        assert not mine, sorted(comp)
