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
    assert "6 kept, 0 broken" in result.stdout


def copy_package(tmp_path: Path) -> Path:
    """A copy of the package and its contracts in ``tmp_path`` (to break them without touching the repo)."""
    shutil.copytree(REPO / "dynbtf", tmp_path / "dynbtf", ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    shutil.copy(REPO / "pyproject.toml", tmp_path)
    return tmp_path / "dynbtf"


def test_an_upward_import_breaks_the_contract(tmp_path):
    base = copy_package(tmp_path) / "data" / "base.py"
    base.write_text(base.read_text() + "\n\ndef _up():\n    from ..training import fit  # stage 1 data reaching up\n")
    result = lint(tmp_path)
    assert result.returncode != 0
    assert "dynbtf.data is not allowed to import dynbtf.training" in result.stdout
    assert "dynbtf.data.base -> dynbtf.training" in result.stdout


def test_a_deferred_import_from_the_interface_to_a_kind_breaks_the_contract(tmp_path):
    # the cycle the registry used to close: base -> (deferred) kinds -> base
    base = copy_package(tmp_path) / "representations" / "base.py"
    base.write_text(base.read_text() + "\n\ndef _kinds():\n    from . import triple_plane  # noqa: F401\n")
    result = lint(tmp_path)
    assert result.returncode != 0
    report = " ".join(result.stdout.split())  # the report wraps long lines
    assert "dynbtf.representations.base is not allowed to import dynbtf.representations.triple_plane" in report
    assert "dynbtf.representations.base -> dynbtf.representations.triple_plane" in report


def test_a_deferred_import_from_the_synthesis_interface_to_a_method_breaks_the_contract(tmp_path):
    # the cycle synthesizer_class used to close: base -> (deferred) methods -> base
    base = copy_package(tmp_path) / "synthesis" / "base.py"
    base.write_text(base.read_text() + "\n\ndef _methods():\n    from . import histogram_blending  # noqa: F401\n")
    result = lint(tmp_path)
    assert result.returncode != 0
    report = " ".join(result.stdout.split())
    assert "dynbtf.synthesis.base is not allowed to import dynbtf.synthesis.histogram_blending" in report
    assert "dynbtf.synthesis.base -> dynbtf.synthesis.histogram_blending" in report


def test_a_new_synthesis_module_must_be_placed_in_a_layer(tmp_path):
    (copy_package(tmp_path) / "synthesis" / "unplaced.py").write_text("from .base import Synthesizer\n")
    result = lint(tmp_path)
    assert result.returncode != 0
    assert "dynbtf.synthesis.unplaced" in result.stdout


def test_a_new_representations_module_must_be_placed_in_a_layer(tmp_path):
    (copy_package(tmp_path) / "representations" / "unplaced.py").write_text("from .base import Representation\n")
    result = lint(tmp_path)
    assert result.returncode != 0
    assert "dynbtf.representations.unplaced" in result.stdout


def test_a_renderer_that_imports_training_breaks_the_material_contract(tmp_path):
    # a backend reaching into training (the compiler used to live there): even a deferred import is refused
    bsdf = copy_package(tmp_path) / "render" / "mitsuba" / "bsdf.py"
    bsdf.write_text(bsdf.read_text() + "\n\ndef _fit():\n    from ...training import fit  # noqa: F401\n")
    result = lint(tmp_path)
    assert result.returncode != 0
    report = " ".join(result.stdout.split())
    assert "dynbtf.render is not allowed to import dynbtf.training" in report
    assert "dynbtf.render.mitsuba.bsdf -> dynbtf.training" in report


def test_the_material_format_cannot_reach_up_to_its_compiler(tmp_path):
    fmt = copy_package(tmp_path) / "material" / "format.py"
    fmt.write_text(fmt.read_text() + "\n\ndef _build():\n    from .compiler import compile_material  # noqa: F401\n")
    result = lint(tmp_path)
    assert result.returncode != 0
    assert "dynbtf.material.format is not allowed to import dynbtf.material.compiler" in " ".join(result.stdout.split())
