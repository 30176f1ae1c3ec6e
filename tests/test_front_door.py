"""The package's front door (``import dynbtf``) and what importing it costs."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest

import dynbtf


def _loaded_after(code: str) -> set[str]:
    """Heavy modules in ``sys.modules`` after running ``code`` in a fresh interpreter."""
    script = textwrap.dedent(code) + textwrap.dedent("""
        import sys
        print(" ".join(m for m in ("torch", "numba", "mitsuba", "drjit", "matplotlib") if m in sys.modules))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_import_dynbtf_loads_no_heavy_dependency():
    assert _loaded_after("import dynbtf; dynbtf.__version__") == set()


def test_reading_a_stored_btf_needs_neither_numba_nor_mitsuba(tmp_path):
    from dynbtf.data import ArrayBTF, write_stored
    from dynbtf.data.directions import ubo2003_directions

    views = lights = ubo2003_directions()[0][:3]
    images = np.random.default_rng(0).random((3, 3, 4, 4, 3)).astype(np.float32)
    path = write_stored(tmp_path / "tiny.dbtf", ArrayBTF(images, views, lights, name="tiny"), progress=False)
    loaded = _loaded_after(f"""
        import dynbtf
        btf = dynbtf.open_btf({str(path)!r})
        assert btf.image(2, 1).shape == (4, 4, 3)
    """)
    assert "numba" not in loaded and "mitsuba" not in loaded and "drjit" not in loaded


def test_every_front_door_name_is_the_defining_modules_object():
    import importlib

    for name, module in dynbtf._FRONT_DOOR.items():
        assert getattr(dynbtf, name) is getattr(importlib.import_module(module), name), name
    assert set(dynbtf.__all__) == {"__version__", *dynbtf._FRONT_DOOR}
    with pytest.raises(AttributeError, match="no attribute 'fitt'"):
        dynbtf.fitt


def test_version_is_the_packages():
    from importlib.metadata import version

    assert dynbtf.__version__ == version("dynbtf")


def test_rendering_without_mitsuba_says_how_to_install_it(monkeypatch):
    """Mitsuba is the extra dynbtf[render]: without it, rendering fails with one line that says so."""
    from dynbtf.errors import MissingDependencyError
    from dynbtf.render.mitsuba.bsdf import register_plugin

    monkeypatch.setitem(sys.modules, "mitsuba", None)  # what an absent package looks like to import
    monkeypatch.setitem(sys.modules, "drjit", None)
    with pytest.raises(MissingDependencyError, match=r"pip install 'dynbtf\[render\]'"):
        register_plugin()
