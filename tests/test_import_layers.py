"""The layer contract (pyproject.toml, [tool.importlinter]) holds, and it catches an upward import."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("importlinter")

REPO = Path(__file__).resolve().parents[1]
LINT = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"


def lint(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", LINT, "--no-cache"], cwd=root, capture_output=True, text=True,
                          env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"})


def test_the_package_keeps_its_layers():
    result = lint(REPO)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "2 kept, 0 broken" in result.stdout


def test_an_upward_import_breaks_the_contract(tmp_path):
    shutil.copytree(REPO / "dynbtf", tmp_path / "dynbtf", ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    shutil.copy(REPO / "pyproject.toml", tmp_path)
    base = tmp_path / "dynbtf" / "data" / "base.py"
    base.write_text(base.read_text() + "\n\ndef _up():\n    from ..training import fit  # stage 1 data reaching up\n")
    result = lint(tmp_path)
    assert result.returncode != 0
    assert "dynbtf.data is not allowed to import dynbtf.training" in result.stdout
    assert "dynbtf.data.base -> dynbtf.training" in result.stdout
