"""``dynbtf render``: a tiny render through the command line, and clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba")


@pytest.mark.mitsuba
def test_render_command_writes_png_and_exr(small_model, tmp_path, capsys):
    from dynbtf.cli.main import main
    from dynbtf.io import load_image

    png, exr = tmp_path / "plane.png", tmp_path / "sphere.exr"
    assert main(["render", str(small_model), "--scene", "plane", "--method", "hist", "--scale", "4",
                 "--size", "32", "--spp", "2", "-o", str(png)]) == 0
    assert main(["render", str(small_model), "--scene", "sphere", "--lighting", "point", "--method", "tile",
                 "--size", "32", "--spp", "2", "--sampling", "cosine", "-o", str(exr)]) == 0
    a, b = load_image(png), load_image(exr)
    assert a.shape == b.shape == (32, 32, 3)
    assert np.isfinite(b).all() and b.max() > 0.0 and a.std() > 0.0
    assert "kernel compilation" in capsys.readouterr().out


@pytest.fixture
def no_mitsuba_scene(monkeypatch):
    """Fail the test if Mitsuba is asked to load a scene: the mistakes below must be caught before."""
    import mitsuba as mi

    def refuse(*args, **kwargs):
        raise AssertionError("mi.load_dict was reached: the argument was not validated up front")

    monkeypatch.setattr(mi, "load_dict", refuse)


def _one_error_line(capsys, message):
    """The command printed exactly one line, ``dynbtf: error: ...`` containing ``message``, and no traceback."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("dynbtf: error: "), err
    assert message in lines[0], err
    return lines[0]


@pytest.mark.parametrize("args, message", [
    (["--scene", "teapot"], "--scene: expected one of"),
    (["--lighting", "moon"], "--lighting: expected one of"),
    (["--method", "voronoi"], "--method: expected one of"),
    (["--scale", "-1"], "--scale"),
    (["--size", "0"], "--size: expected a positive number of pixels, got 0"),
    (["--size", "-16"], "--size: expected a positive number of pixels, got -16"),
    (["--spp", "0"], "--spp: expected a positive number of samples per pixel, got 0"),
    (["--spp", "-4"], "--spp: expected a positive number of samples per pixel, got -4"),
    (["--variant", "scalar_rgb"], "the dynbtf plugin needs an RGB variant of the LLVM or CUDA back end"),
    (["--variant", "llvm_ad_spectral"], "the dynbtf plugin needs an RGB variant of the LLVM or CUDA back end"),
    (["--variant", "no_such_variant"], "not built into the installed Mitsuba"),
    (["--exposure", "-1"], "--exposure: expected a positive number, got -1.0"),
    (["--sampling", "ggx"], "--sampling: expected one of ['auto', 'mixture', 'cosine'], got 'ggx'"),
])
def test_render_command_bad_options(small_model, tmp_path, capsys, no_mitsuba_scene, args, message):
    from dynbtf.cli.main import main

    assert main(["render", str(small_model), "-o", str(tmp_path / "x.png"), *args]) == 2
    _one_error_line(capsys, message)
    assert not (tmp_path / "x.png").exists()


def test_render_command_unavailable_variant_lists_the_available_ones(small_model, tmp_path, capsys,
                                                                     no_mitsuba_scene):
    from dynbtf.cli.main import main
    from dynbtf.render.mitsuba.bsdf import plugin_variants

    available = plugin_variants()
    if "cuda_ad_rgb" in available:  # pragma: no cover - a machine with a GPU
        pytest.skip("cuda_ad_rgb is available here")
    assert main(["render", str(small_model), "-o", str(tmp_path / "x.png"), "--variant", "cuda_ad_rgb"]) == 2
    line = _one_error_line(capsys, "--variant: Mitsuba variant 'cuda_ad_rgb' is not available")
    assert line.endswith("available for the dynbtf plugin here: " + (", ".join(available) or "none"))
    assert "llvm_ad_rgb" in available  # what this machine (and the demo) renders with


def test_render_command_checks_the_output_extension_before_rendering(small_model, tmp_path, capsys, monkeypatch):
    import dynbtf.render.mitsuba.scene_render as mitsuba_render
    from dynbtf.cli.main import main

    def no_render(*args, **kwargs):
        raise AssertionError("rendered before checking -o")

    monkeypatch.setattr(mitsuba_render, "render_scene", no_render)
    assert main(["render", str(small_model), "-o", str(tmp_path / "x.tiff")]) == 2
    _one_error_line(capsys, "x.tiff: unsupported image extension '.tiff'; expected .png, .jpg or .exr")


def test_render_command_model_file_errors(tmp_path, capsys, no_mitsuba_scene, small_model):
    from dynbtf.cli.main import main
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.pca import PCA

    out = str(tmp_path / "x.png")
    assert main(["render", str(tmp_path / "none.dbtfm"), "-o", out]) == 2
    _one_error_line(capsys, "none.dbtfm: model file not found")

    damaged = tmp_path / "damaged.dbtfm"
    data = small_model.read_bytes()
    damaged.write_bytes(data[: len(data) // 2])
    assert main(["render", str(damaged), "-o", out]) == 2
    _one_error_line(capsys, "damaged.dbtfm: not a readable dynbtf model file")

    flipped = tmp_path / "flipped.dbtfm"  # header intact, one tensor byte changed
    flipped.write_bytes(data[:-10] + bytes([data[-10] ^ 0xFF]) + data[-9:])
    assert main(["render", str(flipped), "-o", out]) == 2
    _one_error_line(capsys, "flipped.dbtfm: tensor data does not match its checksum")

    pca = save_model(tmp_path / "pca.dbtfm", PCA(8, 8, 4, 4, components=2))
    assert main(["render", str(pca), "-o", out]) == 2
    _one_error_line(capsys, "pca.dbtfm: the Mitsuba plugin renders Triple Plane (kind 'triple', `dynbtf fit`; 'triple-parallax', "
                            "`dynbtf fit --repr triple-parallax`) and "
                            "NeuMIP (kind 'neumip', `dynbtf fit --repr neumip`) models, got a model of kind 'pca'")


@pytest.mark.parametrize("kwargs, error, message", [
    ({"resolution": (0, 8)}, "InputError", "resolution: expected (height, width) in pixels"),
    ({"resolution": (8, -1)}, "InputError", "resolution: expected (height, width) in pixels"),
    ({"spp": 0}, "InputError", "--spp"),
    ({"spp_per_pass": 0}, "InputError", "spp_per_pass"),
    ({"variant": "scalar_rgb"}, "InputError", "--variant"),
    ({"model": "pca"}, "InputError", "got a model of kind 'pca'"),
    ({"model": "missing"}, "FormatError", "model file not found"),
])
def test_render_scene_validates_before_mitsuba(small_model, tmp_path, no_mitsuba_scene, kwargs, error, message):
    """Library callers get the same clear errors (not Mitsuba's RuntimeError from inside the plugin)."""
    from dynbtf import errors
    from dynbtf.render.mitsuba.scene_render import render_scene
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.pca import PCA

    kwargs = dict(kwargs)
    model = {"pca": lambda: save_model(tmp_path / "pca.dbtfm", PCA(8, 8, 4, 4, components=2)),
             "missing": lambda: tmp_path / "missing.dbtfm"}.get(kwargs.pop("model", None), lambda: small_model)()
    with pytest.raises(getattr(errors, error)) as info:
        render_scene(model, **{"resolution": (8, 8), "spp": 1, "progress": False, **kwargs})
    assert message in str(info.value)


@pytest.mark.mitsuba
def test_render_progress_says_when_the_kernel_compiles(small_model, capsys):
    """A status line before the first pass (kernel compilation: no sample completes meanwhile), its time
    after it, then a bar over the remaining samples only."""
    from dynbtf.render.mitsuba.scene_render import render_scene

    result = render_scene(small_model, scene="plane", lighting="point", method="tile", scale=2.0,
                          resolution=(8, 8), spp=6, spp_per_pass=2, progress=True)
    err = capsys.readouterr().err
    before = err.index("render plane/point/tile: compiling Mitsuba's kernels and running the first pass (2 spp")
    after = err.index(f"render plane/point/tile: kernels ready, first pass done in {result.first_pass_seconds:.1f} s "
                      f"(2/6 spp)")
    bar = err.index("6/6")
    assert before < after < bar
    assert "0/6" not in err  # the bar starts after the first pass, at 2/6
    assert result.passes == 3 and 0 < result.first_pass_seconds <= result.seconds

    render_scene(small_model, scene="plane", lighting="point", method="tile", resolution=(8, 8), spp=2,
                 spp_per_pass=2, progress=True)
    err = capsys.readouterr().err
    assert "kernels ready, first pass done in" in err and "2/2 [" not in err  # one pass: no bar

    render_scene(small_model, scene="plane", lighting="point", method="tile", resolution=(8, 8), spp=2,
                 progress=False)
    assert capsys.readouterr().err == ""


@pytest.mark.mitsuba
def test_render_command_renders_a_neumip_model(tmp_path, capsys):
    from dynbtf.cli.main import main
    from dynbtf.io import load_image
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.neumip import NeuMIP

    model = NeuMIP(12, 12, channels=3, hidden=8, seed=4)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.5)
    path = save_model(tmp_path / "neumip.dbtfm", model)
    out = tmp_path / "neumip.exr"
    assert main(["render", str(path), "--scene", "plane", "--lighting", "point", "--method", "hist", "--scale", "3",
                 "--size", "16", "--spp", "2", "-o", str(out)]) == 0
    img = load_image(out)
    assert img.shape == (16, 16, 3) and np.isfinite(img).all() and img.max() > 0.0 and img.std() > 0.0
