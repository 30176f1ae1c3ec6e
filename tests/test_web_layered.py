"""The web export of a layered material (dynbtf.export.web.layered) in headless Chromium, against the library.

The reference is :meth:`dynbtf.layered.LayeredBTF.eval` on the same points: the two passes of the shader (layer 0's
value and height, then layer 1's decision and mix) read back from float32 targets (tests/chromium.py). The viewer's
mask painting is driven through the page's own controls and mouse events, and judged on screenshots.
"""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest
import torch

from chromium import eval_layered_in_browser, find_chromium, run_page
from dynbtf.conventions import spherical_to_direction
from dynbtf.errors import InputError
from dynbtf.export.web.layered import MaskOrigin, export_layered_web, mask_origin
from dynbtf.layered import ImageMask, LayeredBTF, NoiseMask, contour_distance
from dynbtf.synthesized import synthesized_btf

browser = pytest.mark.skipif(find_chromium() is None, reason="needs headless Chromium (scripts/test.sh installs it)")


@pytest.fixture(scope="module")
def layers():
    """Layer 0: a random Triple Plane under hist; layer 1: a random relief model (its height channel decides) under
    tile, at another scale. Untrained: every weight matters; biased to positive values, like materials."""
    from test_web_export import random_relief_model

    from dynbtf.representations.triple_plane import TriplePlane

    flat = TriplePlane(24, 20, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    relief = random_relief_model(20, 16, 5, seed=6, bias=0.3)
    with torch.no_grad():
        flat.decoder.rest[-1].bias.add_(0.6)
    return [synthesized_btf(flat, "hist", scale=4.0), synthesized_btf(relief, "tile", scale=3.0)]


def _points(n, seed):
    rng = np.random.default_rng(seed)
    uv = rng.random((n, 2)) * 4.0
    uv[n // 4: n // 2] += 1e5  # far from the origin: the mask's and the layers' origins split in float64
    # away from the normal: at the Rusinkiewicz pole phi_h is ill-conditioned in float32 (the single export's
    # tests hold the pole; here the layering is under test)
    wv = spherical_to_direction(5 + rng.random(n) * 55, rng.random(n) * 360)
    wl = spherical_to_direction(5 + rng.random(n) * 65, rng.random(n) * 360)
    return uv, wv, wl


MASKS = {
    "image-repeat": lambda: ImageMask(np.random.default_rng(3).random((5, 7)), size=1.5, wrap="repeat"),
    "image-clamp": lambda: ImageMask(np.random.default_rng(4).random((6, 4)), size=3.0, wrap="clamp"),
    "noise": lambda: NoiseMask(0.6, 3.0, 7),
}


@browser
@pytest.mark.browser
@pytest.mark.parametrize("mask_name", list(MASKS))
def test_layered_shader_matches_layered_btf(layers, tmp_path, mask_name):
    """fp32 textures: every point equal to LayeredBTF.eval to float32 rounding, except points within float32
    rounding of a decision (none expected among these); in the band, heights decide against the side."""
    layered = LayeredBTF(layers, MASKS[mask_name](), width=0.2)
    export = export_layered_web(layered, tmp_path / "web", precision="fp32")
    uv, wv, wl = _points(1536, seed=len(mask_name))
    ref = layered.eval(uv, wv, wl)
    got = eval_layered_in_browser(export.directory, uv, wv, wl)
    mask = layered.mask
    distance = contour_distance(*mask.value_and_gradient(uv))
    heights = layered.heights(torch.from_numpy(uv)).numpy()
    score = heights[:, 1] - heights[:, 0] + distance / layered.width
    band = np.abs(distance) < layered.width
    decided = ~(band & (np.abs(score) < 1e-4)) & (np.abs(np.abs(distance) - layered.width) > 1e-5)
    assert decided.mean() > 0.99
    peak = np.abs(ref).max()
    assert peak > 0.3 and ref.std() > 0.05
    # float32 rounding; a relief march (layer 1) may take another step at a rare point, as in the single export's test
    close = np.abs(got.rgb - ref).max(-1) <= 2e-4 * peak
    assert close[decided].mean() > 0.995, np.flatnonzero(~close & decided)
    psnr = 10 * np.log10(peak ** 2 / np.mean((got.rgb[decided] - ref[decided]) ** 2))
    assert psnr > 90.0, psnr
    weight = layered.weight(uv)
    assert close[decided & (weight == 0)].all()  # layer 0 alone (no march): every point
    np.testing.assert_array_equal(got.weight[decided & band], weight[decided & band])
    # the band is exercised both ways: each layer wins somewhere in it, and the heights overrule the side
    assert 0.05 < weight[band].mean() < 0.95 and band.sum() > 100
    assert ((weight[band] > 0.5) != (distance[band] > 0)).sum() > 10
    # layer 0's pass wrote layer 0's height (in [0, 1]) where it was in the band, as the library reads it
    np.testing.assert_allclose(got.first[band & decided, 3], heights[band & decided, 0], atol=1e-4)


def test_mask_origin_reassembles_the_position():
    """The float64 split: noise cell + offset = uv / scale; a repeated image's offset = uv mod size."""
    uv = np.array([[0.3, -2.7], [1e9 + 0.25, -3e12 - 0.5]])
    noise = {"kind": "noise", "scale": 0.6}
    split = mask_origin(noise, uv)
    assert isinstance(split, MaskOrigin) and split.cell.dtype == np.int64
    np.testing.assert_allclose(split.cell + split.offset, uv / 0.6, rtol=1e-15)
    assert ((split.offset >= 0) & (split.offset < 1)).all()
    words = split.words()
    assert words.dtype == np.uint32 and int(words[1, 2]) + (int(words[1, 3]) << 32) == int(split.cell[1, 1]) % 2**64
    image = mask_origin({"kind": "image", "size": 1.5, "wrap": "repeat"}, uv)
    np.testing.assert_array_equal(image.offset, np.mod(uv, 1.5))
    clamp = mask_origin({"kind": "image", "size": 1.5, "wrap": "clamp"}, uv)
    np.testing.assert_array_equal(clamp.offset, uv)


def test_export_writes_both_layers_the_mask_and_the_viewer(layers, tmp_path):
    layered = LayeredBTF(layers, MASKS["image-repeat"](), width=0.05, softness=0.1)
    export = export_layered_web(layered, tmp_path / "web", precision="u8")
    manifest = json.loads((export.directory / "layered.json").read_text())
    assert manifest == export.manifest and manifest["format"] == "dynbtf-web-layered"
    assert [layer["method"] for layer in manifest["layers"]] == ["hist", "tile"]
    assert [layer["kind"] for layer in manifest["layers"]] == ["triple", "triple-parallax"]
    assert manifest["width"] == 0.05 and manifest["softness"] == 0.1 and manifest["mask"]["wrap"] == "repeat"
    stored = np.frombuffer((export.directory / "mask.bin").read_bytes(), np.float32).reshape(5, 7)
    np.testing.assert_array_equal(stored, layered.mask.image.astype(np.float32))
    for k in (0, 1):
        assert (export.directory / f"layer{k}" / "manifest.js").is_file()
        assert not (export.directory / f"layer{k}" / "index.html").exists()  # one page, at the top
    page = (export.directory / "index.html").read_text()
    assert 'data-viewer="layered"' in page
    assert "clamp(0.5 + score * 5.0, 0.0, 1.0)" in (export.directory / "layered.glsl").read_text()  # the softness


def test_export_refuses_what_it_cannot_show_before_writing(layers, tmp_path):
    class Stripes:
        def value(self, uv):
            return (uv[:, 0] % 1 > 0.5).astype(float)

        def gradient(self, uv):
            return np.zeros_like(uv)

    with pytest.raises(InputError, match="ImageMask or a NoiseMask, not a Stripes"):
        export_layered_web(LayeredBTF(layers, Stripes()), tmp_path / "a")
    with pytest.raises(InputError, match="layered: expected a LayeredBTF, got SynthesizedBTF"):
        export_layered_web(layers[0], tmp_path / "b")
    with pytest.raises(InputError, match="precision: expected one of"):
        export_layered_web(LayeredBTF(layers, NoiseMask()), tmp_path / "c", precision="fp8")
    with pytest.raises(InputError, match="span x scale of layer 0"):
        export_layered_web(LayeredBTF(layers, NoiseMask()), tmp_path / "d", span=5000.0)
    assert not any((tmp_path / name).exists() for name in ("b", "c", "d"))


# ---------------------------------------------------------------- the viewer, as a person uses it
_PAINT = """<script>
window.addEventListener('load', function () {
  var job = __JOB__;
  function note(text) { var p = document.createElement('pre'); p.id = 'probe-paint'; p.hidden = true; p.textContent = text;
                        document.body.appendChild(p); }
  function when(test, then) { if (test()) then(); else window.setTimeout(function () { when(test, then); }, 20); }
  when(function () { return DynBTF.viewer && +(document.body.getAttribute('data-frames') || 0) >= 1; }, function () {
    try {
      var canvas = document.getElementById('view'), rect = canvas.getBoundingClientRect();
      var box = document.getElementById('paint');
      if (job.paint) {
        box.click();  // the checkbox, as a person ticks it
        var cx = rect.left + rect.width / 2, cy = rect.top + rect.height / 2;
        canvas.dispatchEvent(new MouseEvent('mousedown', {bubbles: true, clientX: cx, clientY: cy}));
        window.dispatchEvent(new MouseEvent('mousemove', {clientX: cx + 4, clientY: cy}));
        window.dispatchEvent(new MouseEvent('mouseup', {clientX: cx + 4, clientY: cy}));
      }
      var v = DynBTF.viewer, k = v.scene.renderer.mask, ones = 0;
      for (var i = 0; i < k.values.length; ++i) ones += k.values[i] === 1 ? 1 : 0;
      var save = document.getElementById('mask-save');
      save.click();
      var centre = DynBTF.pick('plane', v.camera(), 0, 0);
      note(JSON.stringify({painting: box.checked, ones: ones, size: [k.width, k.height], centre: centre, png: save.href}));
    } catch (e) { note('error: ' + e.message); }
  });
});
</script>"""


def _viewer_run(directory, tmp_path, name, paint, query):
    page = directory / f"{name}.html"
    job = json.dumps({"paint": paint})
    page.write_text((directory / "index.html").read_text().replace("</body>", _PAINT.replace("__JOB__", job) +
                                                                    "</body>", 1))
    try:
        return run_page(page, screenshot=tmp_path / f"{name}.png", window=(900, 600), budget_ms=5000, query=query)
    finally:
        page.unlink()


@browser
@pytest.mark.browser
def test_viewer_paints_the_mask_and_shows_the_other_layer_there(layers, tmp_path):
    """Tick "Paint", press the mouse at the centre of the plane seen from above: the mask texels within the brush
    become 1; there the viewer shows what it shows with a mask of ones, elsewhere what it showed before; the saved
    PNG is the painted mask, read back by ``dynbtf synth --mask`` as the same values."""
    from dynbtf.io import load_image
    from dynbtf.layered import mask_from_spec

    n = 64
    query = "shape=plane&view-theta=0&distance=2.6&brush=0.2&width=0.02&light-theta=0&resolution=0.5"
    shots = {}
    for name, values, paint in (("zeros", 0.0, False), ("painted", 0.0, True), ("ones", 1.0, False)):
        layered = LayeredBTF(layers, ImageMask(np.full((n, n), values), size=1.0, wrap="repeat"), width=0.02)
        export = export_layered_web(layered, tmp_path / name, precision="fp16")
        run = _viewer_run(export.directory, tmp_path, name, paint, query)
        assert not (run.element("dynbtf-error") or "").strip() and run.console == [], (run.console, run.dom[-800:])
        result = run.element("probe-paint")
        assert result is not None and not result.startswith("error"), result
        shots[name] = (json.loads(result), load_image(run.screenshot))
    painted = shots["painted"][0]
    assert painted["painting"] is True and painted["size"] == [n, n]
    np.testing.assert_allclose(painted["centre"], [0.5, 0.5], atol=1e-6)  # the canvas centre is the plane's centre
    disc = np.pi * (0.2 * n) ** 2
    assert abs(painted["ones"] - disc) < 0.15 * disc, (painted["ones"], disc)  # a disc of the brush's radius
    # the saved PNG holds the painted mask; the command line reads it back as these values
    png = tmp_path / "mask.png"
    png.write_bytes(base64.b64decode(re.sub("^data:image/png;base64,", "", painted["png"])))
    read = mask_from_spec(str(png), size=1.0)
    assert read.image.shape == (n, n) and set(np.unique(read.image)) == {0.0, 1.0}
    assert int(read.image.sum()) == painted["ones"] and read.image[n // 2, n // 2] == 1.0
    # on screen: inside the brush the painted view is the all-ones view, far from it the all-zeros view
    canvas = 900 - 332  # the panel: 300 px and its padding
    zeros, after, ones = (shots[k][1][:, :canvas] for k in ("zeros", "painted", "ones"))
    cy, cx = after.shape[0] // 2, canvas // 2
    inner = (slice(cy - 25, cy + 25), slice(cx - 25, cx + 25))
    outer = (slice(cy - 160, cy - 120), slice(cx - 160, cx - 120))
    assert np.abs(zeros[inner] - ones[inner]).mean() > 0.02  # the two materials differ there
    np.testing.assert_allclose(after[inner], ones[inner], atol=2 / 255)
    np.testing.assert_allclose(after[outer], zeros[outer], atol=2 / 255)


def test_cli_export_with_a_layer_writes_a_layered_viewer(layers, tmp_path):
    from test_web_export import _cli

    from dynbtf.representations.model_file import save_model

    first = save_model(tmp_path / "a.dbtfm", layers[0].model)
    second = save_model(tmp_path / "b.dbtfm", layers[1].model)
    result = _cli("export", first, "--layer", second, "--mask", "noise:0.5,3,2", "--method", "hist", "--width", "0.1",
                  "--scale", "4", "-o", tmp_path / "out")
    assert result.exit_code == 0, result.text
    assert "a layered material, layer 0 a.dbtfm (hist), layer 1 b.dbtfm (hist)" in result.output
    manifest = json.loads((tmp_path / "out" / "layered.json").read_text())
    assert manifest["mask"] == {"kind": "noise", "scale": 0.5, "contrast": 3.0, "seed": 2,
                                "seed_state": manifest["mask"]["seed_state"]}
    assert manifest["width"] == 0.1 and [layer["scale"] for layer in manifest["layers"]] == [4.0, 4.0]
    assert (tmp_path / "out" / "index.html").is_file()
    # the export is the library's layered material: the same layers, mask and band
    cli_layers = [synthesized_btf(path, "hist", scale=4.0) for path in (first, second)]
    expected = export_layered_web(LayeredBTF(cli_layers, NoiseMask(0.5, 3.0, 2), width=0.1), tmp_path / "api")
    for ours, theirs in zip(expected.manifest["layers"], manifest["layers"]):
        heights = ours.pop("height"), theirs.pop("height")
        assert ours == theirs
        for key in ("map", "offset", "low", "high", "table"):  # a least-squares fit: equal to float64 rounding
            np.testing.assert_allclose(heights[0][key], heights[1][key], rtol=1e-9, atol=1e-12)
    for args, message in (((), "give at most one --method"), (("--width", "0"), "--width"),
                          (("--mask", "noise:a"), "expected noise:SCALE[,CONTRAST[,SEED]] with numbers")):
        extra = ("--method", "hist", "--method", "tile") if not args else args
        refused = _cli("export", first, "--layer", second, *extra, "-o", tmp_path / "bad")
        assert refused.exit_code != 0 and message in refused.text, refused.text
    missing = _cli("export", first, "--layer", tmp_path / "nothere.dbtfm", "-o", tmp_path / "bad")
    assert missing.exit_code != 0 and "nothere.dbtfm: model file not found" in missing.text
    assert not (tmp_path / "bad").exists()


@browser
@pytest.mark.browser
def test_layered_frame_timing_page_times_both_layers_and_the_mix(layers, tmp_path):
    """The page bench_web_layered.py uses draws each layer alone and the layered material, and times each frame."""
    from chromium import time_layered_frames

    export = export_layered_web(LayeredBTF(layers, NoiseMask(0.3, 3.0, 1), width=0.05), tmp_path / "web")
    frames = time_layered_frames(export.directory, width=64, height=36, frames=2, gl="swiftshader")
    assert set(frames.frame_ms) == {"layer 0 alone", "layer 1 alone", "layered"} and frames.software
    assert all(len(times) == 2 and min(times) > 0 for times in frames.frame_ms.values())
    with pytest.raises(InputError, match="not a layered web export"):
        time_layered_frames(tmp_path)
