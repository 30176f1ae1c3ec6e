"""The benchmark scripts' imports resolve: every ``from M import name`` in ``benchmarks/*.py`` (at the top or inside a
function) names something module ``M`` has, where ``M`` is another benchmark script or part of dynbtf.

The suite does not run the benchmarks (they take minutes to hours), so a helper renamed in one script or in the
library would otherwise break another script only when someone next measures with it."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
SCRIPTS = sorted(BENCHMARKS.glob("*.py"))


def imported_names(script: Path) -> list[tuple[str, str, int]]:
    """``(module, name, line)`` of every ``from module import name`` in ``script`` whose module is a benchmark script
    or dynbtf's (absolute imports only)."""
    siblings = {p.stem for p in SCRIPTS}
    found = []
    for node in ast.walk(ast.parse(script.read_text(), filename=str(script))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            root = node.module.split(".")[0]
            if root in siblings or root == "dynbtf":
                found += [(node.module, alias.name, node.lineno) for alias in node.names if alias.name != "*"]
    return found


def test_the_walk_finds_the_scripts_imports():
    """The walk sees imports inside functions too (the scripts import lazily)."""
    found = imported_names(BENCHMARKS / "bench_whole_elements.py")
    assert ("bench_structured", "coherence") in {(m, n) for m, n, _ in found}
    assert any(m == "results_io" and n == "spread" for m, n, _ in found)


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_imports_resolve(script, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    missing = []
    for module, name, line in imported_names(script):
        try:
            target = importlib.import_module(module)
        except ImportError as error:
            missing.append(f"{script.name}:{line}: module {module} ({error})")
            continue
        if not hasattr(target, name):
            try:
                importlib.import_module(f"{module}.{name}")  # a submodule
            except ImportError:
                missing.append(f"{script.name}:{line}: {module} has no {name}")
    assert not missing, "\n".join(missing)
