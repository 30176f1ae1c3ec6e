"""One package per synthesis method: backends find each method's forms in the registry and name no method.

A method package holds its synthesizer and a module per backend it runs on besides the CPU (``web.py``), declared in
the class's ``backends``; the web export, the query object and the material stage look them up
(:meth:`dynbtf.synthesis.base.Synthesizer.backend_form`), and the Mitsuba plugin calls the query object. These tests
hold that contract: no backend's code names a method, and a method written as one new package (outside the
repository) is exported and evaluated by the web shader, and rendered by the plugin, like the built-in ones, with no
backend changed.
"""

from __future__ import annotations

import ast
import importlib
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from dynbtf.synthesis.base import SYNTHESIZERS
from dynbtf.synthesis.registry import methods_with, synthesizer_class

REPO = Path(__file__).resolve().parents[1]
#: What the issue calls the backends: the renderer, the web export, the query object and the material stage.
BACKENDS = ("dynbtf/render", "dynbtf/export", "dynbtf/infinite_btf.py", "dynbtf/material")


def method_names_in_code(source: str, names) -> list[tuple[int, str]]:
    """``(line, name)`` of every string constant of ``source`` that is a method name, docstrings left out (their
    examples are for readers)."""
    tree = ast.parse(source)
    docstrings = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                docstrings.add(id(first.value))
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names
            and id(node) not in docstrings]


def test_the_scan_finds_a_method_name_in_code_but_not_in_a_docstring():
    source = 'def f(m):\n    """e.g. "hist"."""\n    return m == "hist"\n'
    assert method_names_in_code(source, {"hist"}) == [(3, "hist")]


def test_backend_code_names_no_method():
    names = set(SYNTHESIZERS)
    found = []
    for root in BACKENDS:
        path = REPO / root
        for file in [path] if path.is_file() else sorted(path.rglob("*.py")):
            found += [f"{file.relative_to(REPO)}:{line}: {name!r}"
                      for line, name in method_names_in_code(file.read_text(), names)]
    assert not found, "backends name methods (look them up in dynbtf.synthesis.registry):\n" + "\n".join(found)


def test_every_method_declares_backends_that_exist_and_build():
    exemplar = torch.rand(16, 16, 3)
    for name in methods_with("web"):
        cls = synthesizer_class(name)
        for backend in cls.backends:
            module = cls.backend_module(backend)
            assert callable(module.form), f"{name}: {module.__name__} has no form()"
        form = cls(exemplar, seed=1).backend_form("web")
        assert form.plane.ndim == 3 and form.plane.shape[-1] == 3
    with pytest.raises(InputError, match=r"synthesis method 'quilt' has no web form; methods with one: \[.*'struct'"):
        synthesizer_class("quilt")(exemplar, seed=0).backend_form("web")


SHIFTED_PACKAGE = '''
"""A test method: the exemplar tiled with a shift of half its width (one package: synthesizer, web form)."""

import torch

from dynbtf.synthesis.base import register_synthesizer
from dynbtf.synthesis.tiling import Tiling


@register_synthesizer("test-shifted")
class ShiftedTiling(Tiling):
    """Tiling of the exemplar rolled by half its width."""

    backends = {"web": f"{__name__}.web"}

    def __init__(self, exemplar, seed: int = 0) -> None:
        exemplar = torch.as_tensor(exemplar)
        super().__init__(torch.roll(exemplar, exemplar.shape[1] // 2, dims=1), seed)
'''

SHIFTED_WEB = '''
"""The test method in the web shader: tiling's branch under a mode of its own."""

from dynbtf.synthesis.tiling import web as tiling_web

MODE = 9
ORIGIN = "lattice"
SAMPLES = 1
HASHES = 3
GLSL_UNIFORMS = ""
GLSL_FUNCTIONS = ""
GLSL_SAMPLE = tiling_web.GLSL_SAMPLE
GLSL_AFTER = ""
cost = tiling_web.cost
form = tiling_web.form
'''


@pytest.fixture
def shifted_method(tmp_path, monkeypatch):
    """The package of a new method, ``test-shifted``, imported from outside the repository (registered for the
    test, unregistered after)."""
    package = tmp_path / "shifted_tiling"
    package.mkdir()
    (package / "__init__.py").write_text(textwrap.dedent(SHIFTED_PACKAGE))
    (package / "web.py").write_text(textwrap.dedent(SHIFTED_WEB))
    monkeypatch.syspath_prepend(str(tmp_path))
    registered = dict(SYNTHESIZERS)
    importlib.import_module("shifted_tiling")
    yield "test-shifted"
    SYNTHESIZERS.clear()
    SYNTHESIZERS.update(registered)
    for name in [m for m in sys.modules if m == "shifted_tiling" or m.startswith("shifted_tiling.")]:
        del sys.modules[name]


def test_a_new_method_package_reaches_the_shader_without_a_backend_change(shifted_method, tmp_path):
    from dynbtf.export.web.shader import glsl_source, shader_cost, web_methods

    assert list(web_methods())[-1] == shifted_method  # ordered by MODE
    source = glsl_source(channels=4, angular_channels=4, hidden=8, layers=3, negative_slope=0.01, angular_resolution=4,
                         angular_weights=np.zeros(2 * 4 * 16, np.float32),
                         rest_weights=[(np.zeros(4 * 16, np.float32), np.zeros(8, np.float32)),
                                       (np.zeros(2 * 16, np.float32), np.zeros(4, np.float32))])
    assert "if (dynbtf_mode == 9) {" in source and f"9 {shifted_method}" in source
    assert shader_cost(shifted_method) == shader_cost("tile")


@pytest.mark.browser
def test_a_new_method_package_renders_in_the_browser_as_the_library_evaluates_it(shifted_method, tmp_path):
    from chromium import eval_in_browser, find_chromium

    from dynbtf.export.web.exporter import export_web
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesized import synthesized_btf

    if find_chromium() is None:
        pytest.skip("needs headless Chromium (scripts/test.sh installs it)")
    model = TriplePlane(24, 20, positional_channels=4, angular_channels=3, hidden=12, seed=5)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
    export = export_web(model, tmp_path / "web", precision="fp32", methods=(shifted_method, "tile"))
    rng = np.random.default_rng(0)
    points = (rng.random((256, 2)) - 0.5) * 20.0
    w = rng.normal(size=(256, 3))
    w[:, 2] = np.abs(w[:, 2]) + 0.2
    w = (w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)
    ref = synthesized_btf(model, shifted_method, seed=0).eval(points, w.astype(np.float64), w.astype(np.float64))
    tile = synthesized_btf(model, "tile", seed=0).eval(points, w.astype(np.float64), w.astype(np.float64))
    got = eval_in_browser(export.directory, shifted_method, points, w, w).rgb
    peak = np.abs(ref).max()
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-4 * peak)
    assert np.abs(ref - tile).max() > 0.05 * peak  # the shift shows: not tiling's answer
    assert export.manifest["methods"][shifted_method]["mode"] == 9


def test_a_new_method_package_renders_in_the_plugin_as_the_library_evaluates_it(shifted_method):
    """The Mitsuba plugin renders the new method with no form of its own (it calls the query object): its evaluator
    answers as ``SynthesizedBTF.eval``, and the method is one of the plugin's."""
    pytest.importorskip("mitsuba")
    from dynbtf.jit import mi_module
    from dynbtf.render.mitsuba.bsdf import plugin_variants
    from dynbtf.render.mitsuba.evaluator import DynBTFEvaluator
    from dynbtf.synthesis.registry import methods_with
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesized import synthesized_btf

    if "llvm_ad_rgb" not in plugin_variants():  # pragma: no cover - no LLVM on this machine
        pytest.skip("Mitsuba variant llvm_ad_rgb not usable here")
    mi = mi_module()
    model = TriplePlane(24, 20, positional_channels=4, angular_channels=3, hidden=12, seed=5)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
    btf = synthesized_btf(model, shifted_method, seed=0)
    evaluator = DynBTFEvaluator(btf)
    assert evaluator.method == shifted_method
    rng = np.random.default_rng(1)
    uv = (rng.random((512, 2)) - 0.5) * 20.0
    w = rng.normal(size=(512, 3))
    w[:, 2] = np.abs(w[:, 2]) + 0.2
    w = (w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)
    want = btf.eval(uv, w.astype(np.float64), w.astype(np.float64))
    rgb = evaluator.eval(mi.Float64(uv[:, 0]), mi.Float64(uv[:, 1]), mi.Vector3f(*w.T), mi.Vector3f(*w.T))
    got = np.stack([np.asarray(rgb.x), np.asarray(rgb.y), np.asarray(rgb.z)], axis=-1)
    peak = np.abs(want).max()
    np.testing.assert_array_equal(got, want)
    assert shifted_method in methods_with()
    tile = synthesized_btf(model, "tile", seed=0).eval(uv, w.astype(np.float64), w.astype(np.float64))
    assert np.abs(want - tile).max() > 0.05 * peak  # the shifted exemplar was read, not tiling's
