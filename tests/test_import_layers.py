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
    assert "8 kept, 0 broken" in result.stdout


def copy_package(tmp_path: Path) -> Path:
    """A copy of the package and its contracts in ``tmp_path`` (to break them without touching the repo)."""
    shutil.copytree(REPO / "dynbtf", tmp_path / "dynbtf", ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    shutil.copy(REPO / "pyproject.toml", tmp_path)
    return tmp_path / "dynbtf"


def lint_with_import(tmp_path: Path, module: str, function: str) -> str:
    """Lint a copy of the package in which ``module`` (a path under dynbtf/) ends with ``function`` (source of a
    function holding a deferred import); the lint must fail. Returns its report, long lines unwrapped."""
    path = copy_package(tmp_path) / module
    path.write_text(path.read_text() + "\n\n" + function)
    result = lint(tmp_path)
    assert result.returncode != 0
    return " ".join(result.stdout.split())  # the report wraps long lines


def test_an_upward_import_breaks_the_contract(tmp_path):
    report = lint_with_import(tmp_path, "data/base.py",
                              "def _up():\n    from ..training import fit  # stage 1 data reaching up\n")
    assert "dynbtf.data is not allowed to import dynbtf.training" in report
    assert "dynbtf.data.base -> dynbtf.training" in report


def test_a_deferred_import_from_the_interface_to_a_kind_breaks_the_contract(tmp_path):
    # the cycle the registry used to close: base -> (deferred) kinds -> base
    report = lint_with_import(tmp_path, "representations/base.py",
                              "def _kinds():\n    from . import triple_plane  # noqa: F401\n")
    assert "dynbtf.representations.base is not allowed to import dynbtf.representations.triple_plane" in report
    assert "dynbtf.representations.base -> dynbtf.representations.triple_plane" in report


def test_a_deferred_import_from_the_synthesis_interface_to_a_method_breaks_the_contract(tmp_path):
    # the cycle synthesizer_class used to close: base -> (deferred) methods -> base
    report = lint_with_import(tmp_path, "synthesis/base.py",
                              "def _methods():\n    from . import histogram_blending  # noqa: F401\n")
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
    report = lint_with_import(tmp_path, "render/mitsuba/bsdf.py",
                              "def _fit():\n    from ...training import fit  # noqa: F401\n")
    assert "dynbtf.render is not allowed to import dynbtf.training" in report
    assert "dynbtf.render.mitsuba.bsdf -> dynbtf.training" in report


def test_the_material_format_cannot_reach_up_to_its_compiler(tmp_path):
    report = lint_with_import(tmp_path, "material/format.py",
                              "def _build():\n    from .compiler import compile_material  # noqa: F401\n")
    assert "dynbtf.material.format is not allowed to import dynbtf.material.compiler" in report


def test_a_backend_that_imports_a_method_package_breaks_the_method_contract(tmp_path):
    # the web exporter reaching into hist's package instead of asking the registry for its web form
    report = lint_with_import(tmp_path, "export/web/exporter.py",
                              "def _lut():\n    from ...synthesis.histogram_blending import HistogramBlending  # noqa: F401\n")
    assert "dynbtf.export is not allowed to import dynbtf.synthesis.histogram_blending" in report
    assert "dynbtf.export.web.exporter -> dynbtf.synthesis.histogram_blending" in report
