"""The ``dynbtf_layered`` Mitsuba plugin: LayeredBTF's numbers inside the kernel, sampling of the mix, the noise
mask texture, and ``dynbtf render --layer``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from test_render_mitsuba import _plugin_eval, _random_queries  # noqa: E402

pytestmark = pytest.mark.mitsuba

SCALE = 5.0


@pytest.fixture(scope="module")
def layer_files(tmp_path_factory):
    """Two small random Triple Planes (one brighter than the other) saved to disk."""
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    folder = tmp_path_factory.mktemp("layers")
    out = []
    for seed, lift in ((5, 0.6), (6, 0.2)):
        model = TriplePlane(24, 20, positional_channels=6, angular_channels=3, hidden=12, seed=seed)
        with torch.no_grad():
            model.decoder.rest[-1].bias.add_(lift)
        path = folder / f"layer{seed}.dbtfm"
        save_model(path, model)
        out.append((path, model))
    return out


def _layered_plugin(layer_files, mask, *, width=0.2, softness=0.0, methods=("hist", "hex"), sampling="cosine",
                    filtered=False):
    from dynbtf.render.mitsuba.layered_bsdf import mask_texture_dict

    layers = {f"layer{k}": {"type": "dynbtf", "filename": str(path), "method": method, "scale": SCALE,
                            "sampling": sampling, "filtered": filtered}
              for k, ((path, _), method) in enumerate(zip(layer_files, methods))}
    return mi.load_dict({"type": "dynbtf_layered", "width": width, "softness": softness,
                         "mask": mask_texture_dict(mask), **layers})


def _layered_reference(layer_files, mask, *, width=0.2, softness=0.0, methods=("hist", "hex"), footprints=False):
    from dynbtf.synthesized import synthesized_btf
    from dynbtf.layered import LayeredBTF

    layers = [synthesized_btf(model, method, scale=SCALE, footprints=footprints)
              for (_, model), method in zip(layer_files, methods)]
    return LayeredBTF(layers, mask, width=width, softness=softness)


@pytest.mark.parametrize("softness", [0.0, 0.3])
def test_layered_plugin_eval_is_layered_btf(variant, layer_files, softness):
    """The plugin's eval equals LayeredBTF.eval / pi * cos at random queries over a random painted mask, with many
    points inside the band (where the heights, not the mask alone, choose) and, with softness, blended ones."""
    from dynbtf.layered import ImageMask

    rng = np.random.default_rng(0)
    mask = ImageMask(rng.random((6, 9)), size=3.0, wrap="repeat")
    bsdf = _layered_plugin(layer_files, mask, softness=softness)
    reference = _layered_reference(layer_files, mask, softness=softness)
    uv, wv, wl = _random_queries(3000, seed=1, uv_range=8.0)
    got = _plugin_eval(bsdf, uv, wv, wl, 1.0)
    expected = reference.eval(uv.astype(np.float64), wv, wl) / np.pi * wl[:, 2:3]
    weight = reference.weight(uv.astype(np.float64))
    by_mask = (mask.value(uv.astype(np.float64)) > 0.5).astype(np.float64)
    assert np.mean(weight != by_mask) > 0.05  # the heights decide at many points
    if softness > 0:
        assert np.mean((weight > 0) & (weight < 1)) > 0.02  # and some points blend the two
    assert np.abs(expected).max() > 0.05
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-4 * max(1.0, np.abs(expected).max()))


def test_layered_plugin_footprints_are_layered_btf_footprints(variant, layer_files):
    """With uv partials, the plugin's layered eval equals LayeredBTF.eval with their footprint: each layer's
    footprint answer, weighed by the share of the footprint it covers (the library's rule)."""
    from dynbtf.infinite_btf import footprint_width
    from dynbtf.layered import ImageMask

    rng = np.random.default_rng(4)
    mask = ImageMask(rng.random((6, 9)), size=3.0, wrap="repeat")
    bsdf = _layered_plugin(layer_files, mask, filtered=True)
    reference = _layered_reference(layer_files, mask, footprints=True)
    uv, wv, wl = _random_queries(3000, seed=2, uv_range=8.0)
    duv_dx, duv_dy = ((rng.normal(size=(3000, 2)) * np.exp(rng.uniform(-7.0, -1.0, (3000, 1))) / SCALE)
                      .astype(np.float32) for _ in range(2))
    got = _plugin_eval(bsdf, uv, wv, wl, 1.0, duv_dx=duv_dx, duv_dy=duv_dy)
    footprint = footprint_width(duv_dx.astype(np.float64), duv_dy.astype(np.float64))
    expected = reference.eval(uv.astype(np.float64), wv, wl, footprint) / np.pi * wl[:, 2:3]
    weight = reference.weight(uv.astype(np.float64), footprint)
    assert np.mean((weight > 0) & (weight < 1)) > 0.02  # footprints that cover both layers
    # a lane whose footprint straddles a pyramid level boundary (float32 partials) may take the other level
    close = np.abs(got - expected).max(1) <= 2e-4 * max(1.0, np.abs(expected).max())
    assert close.mean() > 0.99, close.mean()


def test_layered_plugin_with_a_relief_layer_is_layered_btf(variant, layer_files, tmp_path):
    """A triple-parallax layer: its height in the band is its relief channel (read at uv, as LayeredBTF reads it)
    and its colour is marched; the plugin equals LayeredBTF with the march's tolerance."""
    from dynbtf.synthesized import synthesized_btf
    from dynbtf.layered import ImageMask, LayeredBTF
    from dynbtf.render.mitsuba.layered_bsdf import mask_texture_dict
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.parallax import ParallaxTriplePlane

    relief = ParallaxTriplePlane(24, 20, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    with torch.no_grad():
        relief.decoder.rest[-1].bias.add_(0.4)
        yy, xx = torch.meshgrid(torch.arange(24.0), torch.arange(20.0), indexing="ij")
        relief.set_height(0.05 * torch.sin(2 * np.pi * xx / 10) * torch.cos(2 * np.pi * yy / 8))
    path = tmp_path / "relief.dbtfm"
    save_model(path, relief)
    mask = ImageMask(np.random.default_rng(3).random((5, 7)), size=2.0)
    bsdf = mi.load_dict({"type": "dynbtf_layered", "width": 0.2, "mask": mask_texture_dict(mask),
                         "layer0": {"type": "dynbtf", "filename": str(layer_files[0][0]), "method": "hist",
                                    "scale": SCALE, "sampling": "cosine", "filtered": False},
                         "layer1": {"type": "dynbtf", "filename": str(path), "method": "hist", "scale": SCALE,
                                    "sampling": "cosine", "filtered": False}})
    reference = LayeredBTF([synthesized_btf(layer_files[0][1], "hist", scale=SCALE),
                            synthesized_btf(relief, "hist", scale=SCALE)], mask, width=0.2)
    uv, wv, wl = _random_queries(2000, seed=4, uv_range=6.0)
    got = _plugin_eval(bsdf, uv, wv, wl, 1.0)
    expected = reference.eval(uv.astype(np.float64), wv, wl) / np.pi * wl[:, 2:3]
    weight = reference.weight(uv.astype(np.float64))
    assert np.mean(weight != (mask.value(uv.astype(np.float64)) > 0.5)) > 0.03  # the relief's height decides
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-3 * max(0.5, np.abs(expected).max()))


def test_noise_mask_texture_is_noise_mask(variant):
    """dynbtf_noise's value and gradient equal NoiseMask's, far from the origin too."""
    from dynbtf.layered import NoiseMask
    from dynbtf.render.mitsuba.layered_bsdf import mask_texture_dict

    noise = NoiseMask(scale=0.7, contrast=2.5, seed=3)
    texture = mi.load_dict(mask_texture_dict(noise))
    rng = np.random.default_rng(2)
    uv = np.concatenate([rng.random((2000, 2)) * 6 - 3, rng.random((500, 2)) * 4 + 3000.0]).astype(np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, len(uv))
    si.uv = mi.Point2f(mi.Float(uv[:, 0]), mi.Float(uv[:, 1]))
    value, gradient = noise.value_and_gradient(uv.astype(np.float64))
    np.testing.assert_allclose(np.array(texture.eval_1(si)), value, rtol=0, atol=2e-5)
    got = np.array(texture.eval_1_grad(si))
    got = got.T if got.shape[0] == 2 else got
    np.testing.assert_allclose(got, gradient, rtol=0, atol=2e-4 * max(1.0, np.abs(gradient).max()))
    assert 0.1 < np.mean(value > 0.5) < 0.9 and np.abs(gradient).max() > 0.5


def test_layered_sampling_draws_the_mixture_and_weight_is_eval_over_pdf(variant, layer_files):
    """Inside the band the pdf is the layers' mixture (chi-square test against it), and sample's weight is
    eval / pdf."""
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain

    from dynbtf.layered import ImageMask

    mask = ImageMask(np.array([[0.0, 1.0]]), size=2.0, wrap="clamp")  # the contour at u = 1
    bsdf = _layered_plugin(layer_files, mask, width=0.5, softness=0.5)
    m = 4096
    rng = np.random.default_rng(3)
    si = dr.zeros(mi.SurfaceInteraction3f, m)
    si.wi = dr.normalize(mi.Vector3f(0.3, -0.2, 0.9))
    si.uv = mi.Point2f(mi.Float(0.9 + 0.2 * rng.random(m)), mi.Float(rng.random(m)))  # inside the band
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
    bs, weight = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(m)),
                             mi.Point2f(mi.Float(rng.random(m)), mi.Float(rng.random(m))))
    ev, pd = bsdf.eval_pdf(mi.BSDFContext(), si, bs.wo)
    ev, pd, w = np.array(ev), np.array(pd), np.array(weight)
    ev, w = (ev.T if ev.shape[0] == 3 else ev), (w.T if w.shape[0] == 3 else w)
    np.testing.assert_allclose(np.array(bs.pdf), pd, rtol=1e-5, atol=1e-7)
    ok = pd > 1e-3
    assert ok.mean() > 0.9
    np.testing.assert_allclose(w[ok], ev[ok] / pd[ok][:, None], rtol=1e-4, atol=1e-6)

    # the density sample() draws is pdf(), at a point on the contour (layer 1's weight strictly between 0 and 1)
    tiles = _layered_plugin(layer_files, mask, width=0.5, softness=0.5, methods=("tile", "tile"))
    wi = dr.normalize(mi.ScalarVector3f(0.3, -0.2, 0.9))

    def at_contour(n):
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi, si.uv = wi, mi.Point2f(1.0, 0.5)
        si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
        return si

    def sample_func(sample, *args):
        bs, weight = tiles.sample(mi.BSDFContext(), at_contour(dr.width(sample)), sample[0],
                                  mi.Vector2f(sample[1], sample[2]))
        return bs.wo, dr.select(dr.all(weight == 0), 0.0, 1.0)

    def pdf_func(wo, *args):
        return tiles.pdf(mi.BSDFContext(), at_contour(dr.width(wo)), wo)

    w_1 = float(np.array(tiles._weight(at_contour(1), True))[0])
    assert 0.0 < w_1 < 1.0  # both layers' sampling are in the mix
    test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=100_000, res=16, ires=16)
    assert test.run(), test.messages


def test_layered_plugin_errors_name_the_parameter(variant, layer_files):
    from dynbtf.errors import InputError
    from dynbtf.layered import ImageMask
    from dynbtf.render.mitsuba.layered_bsdf import mask_texture_dict

    def mask():  # a fresh texture dict per scene: Mitsuba takes over the tensor it is given
        return mask_texture_dict(ImageMask(np.array([[0.0, 1.0]]), size=2.0))

    layer = {"type": "dynbtf", "filename": str(layer_files[0][0]), "method": "tile", "filtered": False}
    cases = [({"layer0": layer, "layer1": layer}, "texture 'mask' is required"),
             ({"layer0": layer, "mask": mask()}, "'layer1' is required"),
             ({"layer0": layer, "layer1": {"type": "diffuse"}, "mask": mask()}, "'layer1' must be a dynbtf BSDF"),
             ({"layer0": layer, "layer1": layer, "mask": mask(), "width": 0.0}, "parameter 'width' must be a positive"),
             ({"layer0": layer, "layer1": layer, "mask": mask(), "softness": -1.0}, "parameter 'softness'")]
    for properties, message in cases:
        with pytest.raises((InputError, RuntimeError), match=message):
            mi.load_dict({"type": "dynbtf_layered", **properties})


def test_layered_parameter_table_is_the_documented_one():
    from pathlib import Path

    from dynbtf.render.mitsuba.layered_bsdf import layered_parameter_table_markdown

    text = (Path(__file__).resolve().parents[1] / "docs" / "rendering.md").read_text()
    assert layered_parameter_table_markdown() in text


def test_render_cli_layers_two_materials(variant, layer_files, tmp_path, capsys):
    """``dynbtf render MODEL --layer OTHER --mask IMAGE`` writes a finite, lit image; a bad band width is one error
    line naming --width, before anything loads."""
    from dynbtf.cli.main import main
    from dynbtf.io import load_image, save_image

    mask_path = tmp_path / "mask.png"
    save_image(mask_path, np.repeat(np.repeat(np.array([[0.0, 1.0]], dtype=np.float32), 8, 0), 8, 1)[..., None]
               .repeat(3, -1))
    out = tmp_path / "layered.exr"
    assert main(["render", str(layer_files[0][0]), "--layer", str(layer_files[1][0]), "--mask", str(mask_path),
                 "--mask-wrap", "clamp", "--method", "tile", "--scene", "plane", "--lighting", "point", "--size", "32",
                 "--spp", "4", "--scale", "4", "--point", "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    image = load_image(out)
    assert image.shape == (32, 32, 3) and np.isfinite(image).all() and image.max() > 0
    assert main(["render", str(layer_files[0][0]), "--layer", str(layer_files[1][0]), "--width", "0",
                 "-o", str(tmp_path / "x.png")]) != 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("dynbtf: error: ") and "--width" in err[0], err


def test_render_cli_guided_by_a_target(variant, layer_files, tmp_path, capsys):
    """``dynbtf render MODEL --target IMAGE``: a guided render (point queries) whose pixels differ from the
    unguided render's (the plugin's values against guided_btf: test_render_mitsuba.py); bad guidance options are
    one error line before anything loads."""
    from dynbtf.cli.main import main
    from dynbtf.io import load_image, save_image

    target = tmp_path / "target.png"
    save_image(target, np.zeros((4, 4, 3), np.float32))  # everywhere class 0: the darkest content
    common = ["render", str(layer_files[0][0]), "--method", "hist", "--scene", "plane", "--lighting", "point",
              "--size", "32", "--spp", "4", "--scale", "4", "--point"]
    assert main(common + ["--target", str(target), "-o", str(tmp_path / "guided.exr")]) == 0
    assert main(common + ["-o", str(tmp_path / "plain.exr")]) == 0
    guided, plain = load_image(tmp_path / "guided.exr"), load_image(tmp_path / "plain.exr")
    assert np.isfinite(guided).all() and guided.max() > 0
    assert np.abs(guided - plain).max() > 1e-3  # the target changed the content (its values: the plugin's test)
    capsys.readouterr()
    for extra, message in ((["--classes", "1"], "--classes: expected 2 to 255"),
                           (["--softness", "2"], "--softness: expected a weight factor in [0, 1]"),
                           (["--method", "struct"], "--target: guided struct chooses whole cells by class"),
                           (["--method", "tile"], "steers hist, hex or struct"),
                           (["--cells", "4"], "--cells: sets the cells per repeat of struct"),
                           (["--layer", str(layer_files[1][0])], "does not combine with a layered one")):
        assert main(common + ["--target", str(target), *extra, "-o", str(tmp_path / "x.png")]) != 0
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(err) == 1 and message in err[0], err
