"""The web export's shader, run in headless Chromium's WebGL2, against the library.

Queries are rendered into a float32 target and read back (tests/chromium.py);
the reference is :meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` on the same queries. The
lattice check compares the shader's triangle vertices and hashed texel offsets with
:func:`dynbtf.synthesis.lattice.triangle_lattice` and :func:`dynbtf.synthesis.hash.vertex_offsets`
bit for bit, up to ~2**45 repeats from the origin.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from chromium import eval_in_browser, find_chromium, lattice_in_browser
from dynbtf.export.web.exporter import dequantize, export_web, quantize
from dynbtf.export.web.shader import repeat_origin
from dynbtf.synthesis.hash import vertex_offsets
from dynbtf.synthesis.lattice import triangle_lattice
from dynbtf.synthesized import synthesized_btf

browser = pytest.mark.skipif(find_chromium() is None, reason="needs headless Chromium (scripts/test.sh installs it)")
METHODS = ("hist", "hex", "tile", "linear")


@pytest.fixture(scope="module")
def model():
    """A small random Triple Plane (not fitted: every weight matters) with odd channel counts (padding)."""
    from dynbtf.representations.triple_plane import TriplePlane

    m = TriplePlane(24, 20, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    with torch.no_grad():
        m.decoder.rest[-1].bias.add_(0.6)  # mostly positive values, like a material
    return m


@pytest.fixture(scope="module")
def exports(model, tmp_path_factory):
    root = tmp_path_factory.mktemp("web")
    return {p: export_web(model, root / p, precision=p, methods=METHODS) for p in ("fp32", "fp16", "u8")}


def _queries(n, seed=0):
    """Positions (repeats) around the origin, near 1e6 and far out, and directions incl. the pole and grazing."""
    rng = np.random.default_rng(seed)
    points = (rng.random((n, 2)) - 0.5) * 80.0
    points[n // 4: n // 2] += 1e6
    points[n // 2: n // 2 + n // 8] += np.array([-3.0e11, 7.0e12])
    shift = np.zeros(n, np.int32)
    shift[n // 8: n // 4] = rng.integers(-300, 300, n // 4 - n // 8)

    def hemisphere(k):
        w = rng.normal(size=(k, 3))
        w[:, 2] = np.abs(w[:, 2]) + 0.02
        return w / np.linalg.norm(w, axis=1, keepdims=True)

    wv, wl = hemisphere(n), hemisphere(n)
    wv[:4] = wl[:4] = [0.0, 0.0, 1.0]  # the Rusinkiewicz pole
    wv[4:8] = wl[4:8] = [0.6, 0.0, 0.8]  # view = light: d at its pole
    return points, shift, wv.astype(np.float32), wl.astype(np.float32)


def _psnr(got, ref):
    return 10.0 * np.log10(np.abs(ref).max() ** 2 / np.mean((got - ref) ** 2))


@browser
@pytest.mark.browser
@pytest.mark.parametrize("method", METHODS)
def test_shader_matches_synthesized_btf(exports, model, method):
    """fp32 textures: equal to float32 rounding; fp16: PSNR >= 40 dB (the issue's bar); u8: >= 30 dB."""
    points, shift, wv, wl = _queries(1024)
    ref = synthesized_btf(model, method, seed=0).eval(points, wv.astype(np.float64), wl.astype(np.float64))
    assert np.abs(ref).max() > 0.5 and ref.std() > 0.05  # the comparison is not between constants
    got = {p: eval_in_browser(exports[p].directory, method, points, wv, wl, local_shift=shift) for p in exports}
    peak = np.abs(ref).max()
    exact = shift == 0  # positions passed as origin + fraction: float32 rounding only
    np.testing.assert_allclose(got["fp32"].rgb[exact], ref[exact], rtol=0, atol=2e-4 * peak)
    # up to 300 repeats in the float32 local uv: positions within ~2e-5 repeats (4e-4 texels here)
    np.testing.assert_allclose(got["fp32"].rgb[~exact], ref[~exact], rtol=0, atol=5e-3 * peak)
    assert _psnr(got["fp16"].rgb, ref) >= 40.0
    assert _psnr(got["u8"].rgb, ref) >= 30.0
    # the export is not the identity of something trivial: another seed's synthesis differs
    if method != "tile":
        other = synthesized_btf(model, method, seed=1).eval(points, wv.astype(np.float64), wl.astype(np.float64))
        assert _psnr(got["fp32"].rgb, other) < 30.0


@browser
@pytest.mark.browser
@pytest.mark.parametrize("variation", [{"rotation": True}, {"scale_jitter": 0.4},
                                       {"rotation": True, "scale_jitter": 1.0}],
                         ids=["turned", "scaled", "turned-and-scaled"])
def test_turned_samples_in_the_shader_match_synthesized_btf(model, tmp_path, variation):
    """``rotation=True`` (quarter turns about each vertex's pivot, the directions turned into the frame) and
    ``scale_jitter`` (each sample scaled about the same pivot) in the shader = ``synthesized_btf(model, method,
    **variation)`` for linear, hist and hex, and not the plain method's values."""
    turned = ("linear", "hist", "hex")
    export = export_web(model, tmp_path / "turned", precision="fp32", methods=turned,
                        method_params={m: dict(variation) for m in turned})
    points, shift, wv, wl = _queries(1024, seed=3)
    for method in turned:
        ref = synthesized_btf(model, method, seed=0, **variation).eval(points, wv.astype(np.float64),
                                                                         wl.astype(np.float64))
        got = eval_in_browser(export.directory, method, points, wv, wl, local_shift=shift).rgb
        peak = np.abs(ref).max()
        exact = shift == 0
        np.testing.assert_allclose(got[exact], ref[exact], rtol=0, atol=2e-4 * peak)
        np.testing.assert_allclose(got[~exact], ref[~exact], rtol=0, atol=5e-3 * peak)
        plain = synthesized_btf(model, method, seed=0).eval(points, wv.astype(np.float64), wl.astype(np.float64))
        assert _psnr(got, plain) < 30.0


@browser
@pytest.mark.browser
def test_hist_with_an_extreme_exponent_is_finite_and_the_librarys(model, tmp_path):
    """gamma = 1e10: b^gamma underflows to 0 for every barycentric; the shader's (b / max b)^gamma does not
    (NaN weights would reach the inverse table's index)."""
    export = export_web(model, tmp_path / "web", precision="fp32", methods=("hist",),
                        method_params={"hist": {"gamma": 1e10}})
    points, shift, wv, wl = _queries(256)
    exact = shift == 0
    ref = synthesized_btf(model, "hist", seed=0, gamma=1e10).eval(points, wv.astype(np.float64), wl.astype(np.float64))
    got = eval_in_browser(export.directory, "hist", points[exact], wv[exact], wl[exact])
    assert np.isfinite(got.rgb).all()
    np.testing.assert_allclose(got.rgb, ref[exact], rtol=0, atol=2e-4 * np.abs(ref).max())


@browser
@pytest.mark.browser
def test_lattice_vertices_and_texel_offsets_agree_bit_for_bit(exports, model):
    """Every query's three lattice vertices and hashed whole-texel offsets equal the library's, up to 2**45 repeats."""
    rng = np.random.default_rng(7)
    n = 4096
    whole = rng.integers(-60, 60, (n, 2)).astype(np.float64)
    whole[1024:2048] += 1e6
    whole[2048:2560] += np.array([-(2.0 ** 33) - 5, 2.0 ** 31 + 3])  # beyond int32 lattice coordinates
    whole[2560:3072] += np.array([2.0 ** 45, -(2.0 ** 44)])           # the large fixed-point branch (>= 2**27)
    # fractions exact in the shader's float32 and, added to the repeat index, in float64
    bits = np.full((n, 1), 24.0)
    bits[2048:2560], bits[2560:3072] = 18.0, 6.0
    frac = np.floor(rng.random((n, 2)) * 2.0 ** bits) / 2.0 ** bits
    points = whole + frac
    assert np.array_equal(points - whole, frac)  # the points hold their fractions exactly
    shift = np.zeros(n, np.int32)
    shift[:512] = rng.integers(-2000, 2000, 512)  # these go through the shader's own lattice arithmetic
    vertices, bary = triangle_lattice(torch.from_numpy(points))
    # queries within 1e-5 of a triangle edge may fall on either side in float32: not a disagreement
    clear = (bary.min(-1).values > 1e-5).numpy()
    assert clear.mean() > 0.99
    hist = synthesized_btf(model, "hist", seed=0).synthesizer
    ph, pw = hist.prepared.plane.shape[:2]
    ox, oy = vertex_offsets(vertices[..., 0], vertices[..., 1], 0, pw, ph)
    got = lattice_in_browser(exports["fp16"].directory, "hist", points, local_shift=shift)
    np.testing.assert_array_equal(got.vertices[clear], vertices.numpy()[clear])
    np.testing.assert_array_equal(got.offsets[clear], torch.stack([ox, oy], -1).numpy()[clear])
    # texel addressing: (I W) mod W' + floor(f W - 0.5), as the fused kernel computes it
    origin = repeat_origin(points, (pw, ph), hist.density)
    corner = np.floor(origin.fraction * np.array(hist.density) - 0.5).astype(np.int64)
    expected = np.stack([(origin.texel_x + corner[:, 0]) % pw, (origin.texel_y + corner[:, 1]) % ph], -1)
    near_texel_edge = np.abs(origin.fraction * np.array(hist.density) - 0.5 - np.rint(
        origin.fraction * np.array(hist.density) - 0.5)).min(-1) < 1e-4
    np.testing.assert_array_equal(got.texel[~near_texel_edge], expected[~near_texel_edge])


def test_repeat_origin_reassembles_the_lattice(model):
    """The CPU split plus the shader's local arithmetic, redone in float64, gives triangle_lattice's vertices."""
    rng = np.random.default_rng(3)
    points = (rng.random((2000, 2)) - 0.5) * 1e3 + np.array([2.0 ** 40, -1e9])
    o = repeat_origin(points, (20, 24), (20, 24))
    kx = o.phase + 2 * np.sqrt(3.0) * o.fraction[:, 0] - 2.0 * o.fraction[:, 1]
    ky = 4.0 * o.fraction[:, 1]
    base = np.stack([o.lattice_x + np.floor(kx).astype(np.int64), o.lattice_y + np.floor(ky).astype(np.int64)], -1)
    vertices, _ = triangle_lattice(torch.from_numpy(points))
    lower = (1.0 - (kx - np.floor(kx)) - (ky - np.floor(ky))) > 0
    np.testing.assert_array_equal(base[lower], vertices[lower.tolist(), 0].numpy())
    words = o.words()
    np.testing.assert_array_equal(words[:, 0].astype(np.uint64) | (words[:, 1].astype(np.uint64) << np.uint64(32)),
                                  o.lattice_x.view(np.uint64))


def test_quantize_round_trip_and_bounds():
    rng = np.random.default_rng(0)
    x = (rng.normal(size=(30, 20, 5)) * np.array([1, 10, 0.01, 100, 0])).astype(np.float32)
    for precision, tolerance in (("fp32", 0.0), ("fp16", 1e-3), ("u8", 0.5 / 255)):
        stored, scale, bias = quantize(x, precision)
        back = dequantize(stored, scale, bias)
        span = np.maximum(x.reshape(-1, 5).max(0) - x.reshape(-1, 5).min(0), 1e-30)
        rel = np.abs(back - x).reshape(-1, 5).max(0) / (span if precision == "u8" else np.abs(x).reshape(-1, 5).max(0)
                                                      + 1e-30)
        assert (rel <= tolerance * 1.0001 + 1e-7).all(), (precision, rel)
    assert quantize(x, "u8")[0].dtype == np.uint8 and quantize(x, "fp16")[0].dtype == np.float16
    with pytest.raises(InputError, match="precision"):
        quantize(x, "int4")
    with pytest.raises(InputError, match="values up to 1e\\+05 do not fit half floats"):
        quantize(np.full((2, 2, 1), 1e5, np.float32), "fp16")


def test_export_writes_manifest_files_and_shader(exports, model, tmp_path):
    ex = exports["u8"]
    manifest = json.loads((ex.directory / "manifest.json").read_text())
    assert manifest["format"] == "dynbtf-web" and manifest["precision"] == "u8"
    for name, entry in manifest["files"].items():
        assert (ex.directory / name).stat().st_size == entry["bytes"]
        assert (ex.directory / f"{name}.js").is_file()
    for name in ("index.html", "viewer.js", "manifest.js", "dynbtf.glsl"):
        assert (ex.directory / name).is_file()
    shader = (ex.directory / "dynbtf.glsl").read_text()
    assert "0x7feb352du" in shader and "dynbtf_eval" in shader
    # u8 stores one byte per value: the hist plane is 2 RGBA layers of 24 x 20 texels
    assert manifest["files"][manifest["methods"]["hist"]["plane"]["file"]]["bytes"] == 2 * 24 * 20 * 4
    assert ex.method_bytes("hist") < ex.total_bytes()
    # without the viewer: the engine's files only
    bare = export_web(model, tmp_path / "bare", precision="u8", methods=("tile",), viewer=False)
    names = {p.name for p in bare.directory.iterdir()}
    assert names == {"manifest.json", "dynbtf.glsl", *bare.manifest["files"]}, names


def test_unsupported_kinds_are_refused_naming_the_supported_ones(tmp_path):
    from pathlib import Path

    data = Path(__file__).parent / "data" / "round1_models"
    for kind in ("pca", "sh", "neumip"):
        with pytest.raises(InputError, match=rf"kind '{kind}' is not supported.*supported kinds: triple, triple-parallax"):
            export_web(data / f"{kind}.dbtfm", tmp_path / kind)


def test_bad_arguments_are_clear_errors(model, tmp_path):
    with pytest.raises(InputError, match="precision: expected one of"):
        export_web(model, tmp_path / "a", precision="fp8")
    with pytest.raises(InputError, match="'quilt' has no shader form"):
        export_web(model, tmp_path / "b", methods=("quilt",))
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="exists and is not a directory"):
        export_web(model, tmp_path / "file")


@pytest.mark.parametrize("scale", [float("nan"), float("inf"), 0.0, -2.0, 4096.0, 1e30, "many"])
def test_export_web_refuses_a_scale_the_shader_cannot_hold_before_writing(model, tmp_path, scale):
    """The library call checks scale like the CLI: no manifest with NaN (invalid JSON), nothing written."""
    with pytest.raises(InputError, match=r"scale: .*(positive, finite number|the shader's float32 local uv)"):
        export_web(model, tmp_path / "out", methods=("tile",), scale=scale)
    assert not (tmp_path / "out").exists()


def _cli(*args):
    from typer.testing import CliRunner

    from dynbtf.cli.main import app

    result = CliRunner().invoke(app, [str(a) for a in args])
    result.text = result.output + ("" if result.exception is None else str(result.exception))
    return result


def test_cli_export_writes_the_viewer_and_refuses_bad_input(model, tmp_path):
    from pathlib import Path

    from dynbtf.representations.model_file import save_model

    path = save_model(tmp_path / "m.dbtfm", model)
    result = _cli("export", path, "-o", tmp_path / "out", "--precision", "u8", "--method", "hist", "--method", "tile")
    assert result.exit_code == 0, result.output
    assert "the hist method alone needs" in result.output and "index.html" in result.output
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert list(manifest["methods"]) == ["hist", "tile"] and manifest["precision"] == "u8"
    data = Path(__file__).parent / "data" / "round1_models"
    refused = _cli("export", data / "pca.dbtfm", "-o", tmp_path / "pca")
    assert refused.exit_code != 0 and "kind 'pca' is not supported" in refused.text
    assert "supported kinds: triple" in refused.text and not (tmp_path / "pca").exists()
    missing = _cli("export", tmp_path / "nothere.dbtfm", "-o", tmp_path / "x")
    assert missing.exit_code != 0 and "nothere.dbtfm: model file not found" in missing.text
    other = _cli("export", path, "-o", tmp_path / "x", "--format", "gltf")
    assert other.exit_code != 0 and "--format: expected one of ['web']" in other.text
    other = _cli("export", path, "-o", tmp_path / "x", "--precision", "fp8")
    assert other.exit_code != 0 and "--precision: expected one of ['fp16', 'fp32', 'u8'], got 'fp8'" in other.text
    other = _cli("export", path, "-o", tmp_path / "x", "--method", "quilt")
    assert other.exit_code != 0 and "'quilt' has no shader form" in other.text


_PROBE = """<script>
(function () {
  var seen = [];
  function note(kind, args) {
    seen.push(kind + ': ' + Array.prototype.map.call(args, String).join(' '));
    var p = document.getElementById('probe-console');
    if (!p && document.body) { p = document.createElement('pre'); p.id = 'probe-console'; document.body.appendChild(p); }
    if (p) p.textContent = JSON.stringify(seen);
  }
  ['error', 'warn'].forEach(function (k) { var f = console[k]; console[k] = function () { note(k, arguments); f.apply(console, arguments); }; });
  window.addEventListener('error', function (e) { note('exception', [e.message]); });
  window.addEventListener('unhandledrejection', function (e) { note('rejection', [e.reason]); });
})();
</script>"""


def _probe_viewer(directory, tmp_name="probe.html", **kwargs):
    """Load a copy of the viewer page with console/exception hooks; return the PageRun."""
    from chromium import run_page

    page = directory / tmp_name
    page.write_text((directory / "index.html").read_text().replace("<head>", "<head>" + _PROBE, 1))
    try:
        return run_page(page, **kwargs)
    finally:
        page.unlink()


@browser
@pytest.mark.browser
@pytest.mark.parametrize("query", ["", "shape=sphere&method=hex&origin=1e6&light-theta=60"])
def test_viewer_page_draws_without_console_errors(exports, tmp_path, query):
    """The plane with the defaults, and the sphere with hex-tiling a million uv units from the origin."""
    from dynbtf.io import load_image

    directory = exports["fp16"].directory
    run = _probe_viewer(directory, screenshot=tmp_path / "viewer.png", window=(720, 480), budget_ms=4000, query=query)
    assert 'data-state="running"' in run.dom, run.dom[-2000:]
    assert not (run.element("dynbtf-error") or "").strip()
    assert run.element("probe-console") is None and run.console == []  # nothing at all on the console
    import re

    drawn = int(re.search(r'data-frames="(\d+)"', run.dom).group(1))
    fps = re.search(r'<div id="fps">(.*?)</div>', run.dom).group(1)
    assert drawn >= 1 and ("ms per frame" in fps if drawn >= 3 else True), (drawn, fps)  # the fps counter runs
    shot = load_image(run.screenshot)
    canvas = shot[:, : shot.shape[1] - 320]  # the panel is 300 px + padding on the right
    background = np.array([0.08, 0.08, 0.09]) ** 2.2
    drawn = np.abs(canvas - background).max(-1) > 0.05
    assert drawn.mean() > 0.2  # the plane covers a good part of the view
    assert canvas[drawn].std(0).max() > 0.01  # and shows texture, not a flat colour


@browser
@pytest.mark.browser
@pytest.mark.parametrize("scale, low, high", [(1000.0, "1", "2000"), (3000.0, "1", "4096"), (0.5, "0.5", "64")])
def test_viewer_scale_slider_reaches_the_exported_scale(model, tmp_path, scale, low, high):
    """A scale beyond the slider's default range (64) or below 1 is shown as exported, not clamped."""
    export = export_web(model, tmp_path / "out", precision="fp16", methods=("tile",), scale=scale)
    run = _probe_viewer(export.directory, budget_ms=2500)
    assert 'data-state="running"' in run.dom, (run.element("dynbtf-error") or "") + run.dom[-1500:]
    assert f'<span class="value" id="scale-value">{scale:g}</span>' in run.dom
    assert f'min="{low}" max="{high}"' in run.dom


@browser
@pytest.mark.browser
def test_viewer_reports_missing_or_unreadable_files_in_the_page(exports, tmp_path):
    import shutil

    directory = tmp_path / "copy"
    shutil.copytree(exports["u8"].directory, directory)
    (directory / "plane_hist.bin.js").unlink()
    run = _probe_viewer(directory, budget_ms=3000)
    assert "plane_hist.bin.js: missing or unreadable" in (run.element("dynbtf-error") or "")
    assert 'data-state="error"' in run.dom
    shutil.copy(exports["u8"].directory / "plane_hist.bin.js", directory)
    (directory / "f_H.bin.js").write_text('DynBTF.file("f_H.bin", 12, "not base64 at all!");\n')
    run = _probe_viewer(directory, budget_ms=3000)
    assert "f_H.bin.js: unreadable" in (run.element("dynbtf-error") or "")
    (directory / "manifest.js").unlink()
    run = _probe_viewer(directory, budget_ms=3000)
    assert "manifest.js: missing or unreadable" in (run.element("dynbtf-error") or "")


@browser
@pytest.mark.browser
def test_viewer_reports_bad_page_parameters_in_the_page(exports):
    run = _probe_viewer(exports["fp16"].directory, budget_ms=3000, query="shape=cube")
    assert "page parameter shape=cube is not one of its choices" in (run.element("dynbtf-error") or "")
    run = _probe_viewer(exports["fp16"].directory, budget_ms=3000, query="colour=red")
    assert "unknown page parameter colour" in (run.element("dynbtf-error") or "")
    run = _probe_viewer(exports["fp16"].directory, budget_ms=3000, query="origin=1e20")
    assert "must be below 2^52 exemplar repeats" in (run.element("dynbtf-error") or "")
    run = _probe_viewer(exports["fp16"].directory, budget_ms=3000, query="origin=far")
    assert "uv origin: expected a number such as 0 or 1e6, got far" in (run.element("dynbtf-error") or "")


def test_shader_cost_counts_the_decoder_as_the_exported_weights_hold_it(exports, model):
    """The decoder's multiply-adds equal the float count of its exported mat4 blocks (padded widths)."""
    from dynbtf.export.web.shader import shader_cost

    manifest = exports["fp32"].manifest
    cfg = model.config()
    cost = {m: shader_cost(m, channels=cfg["positional_channels"], angular_channels=cfg["angular_channels"],
                           hidden=cfg["hidden"], layers=cfg["layers"]) for m in METHODS}
    hg = (cfg["hidden"] + 3) // 4
    weights = manifest["methods"]["hist"]["layer1"]["floats"] - 4 * hg  # mat4 floats = multiply-adds
    weights += sum(part["floats"] for name, part in manifest["decoder"]["parts"].items() if not name.startswith("b"))
    assert all(c["decoder_macs"] == weights for c in cost.values())
    # hist reads three 2 x 2 footprints of 2 RGBA layers, two table entries per (padded) channel and
    # 2 x 2 footprints of one RGBA layer in each angular plane
    assert cost["hist"]["texel_fetches"] == 3 * 4 * 2 + 2 * 8 + 2 * 4 * 1
    assert cost["tile"]["texel_fetches"] < cost["hex"]["texel_fetches"] < cost["hist"]["texel_fetches"]


def random_relief_model(height: int, width: int, positional_channels: int, seed: int, bias: float):
    """A random Triple Plane with parallax (untrained: every weight matters), a smooth random height field up to 0.03
    repeats, and ``bias`` added to its last layer (mostly positive values, like a material)."""
    from dynbtf.representations.parallax import ParallaxTriplePlane

    m = ParallaxTriplePlane(height, width, positional_channels=positional_channels, angular_channels=3, hidden=12,
                            seed=seed)
    g = torch.Generator().manual_seed(1)
    h = torch.nn.functional.avg_pool2d(torch.rand(1, 1, height, width, generator=g), 3, 1, 1, count_include_pad=False)
    m.set_height(0.03 * h[0, 0])
    with torch.no_grad():
        m.decoder.rest[-1].bias.add_(bias)
    return m


@pytest.fixture(scope="module")
def relief_model():
    """A random Triple Plane with parallax and a smooth random height field up to 0.03 repeats."""
    return random_relief_model(24, 20, 6, seed=5, bias=0.6)


@browser
@pytest.mark.browser
@pytest.mark.parametrize("method", ["hist", "hex"])
def test_relief_model_marches_the_synthesized_height_like_the_library(relief_model, tmp_path, method):
    """triple-parallax: the shader's ray march through the synthesized height agrees with SynthesizedBTF."""
    import copy

    points, shift, wv, wl = _queries(768, seed=2)
    # near 7e12 repeats float64 holds uv to 1e-3 repeats: the library's own march (uv + z slope in float64)
    # rounds there, the shader's (in the local uv) does not; compare where float64 is exact to ~1e-10
    keep = np.abs(points).max(-1) < 1e7
    points, wv, wl = points[keep], wv[keep], wl[keep]
    wv[8:40] = [0.9, 0.1, np.sqrt(1 - 0.82)]  # ~64 deg: long marches
    got = {p: eval_in_browser(export_web(relief_model, tmp_path / p, precision=p, methods=(method,)).directory, method,
                              points, wv, wl) for p in ("fp32", "fp16")}
    ref = synthesized_btf(relief_model, method, seed=0).eval(points, wv.astype(np.float64), wl.astype(np.float64))
    assert _psnr(got["fp32"].rgb, ref) > 90.0
    assert _psnr(got["fp16"].rgb, ref) >= 40.0
    # the march matters: the same model without its relief (visible point = uv) gives other values
    flat = copy.deepcopy(relief_model)
    flat.set_height(torch.full((24, 20), float(relief_model.height_field().detach().mean())))
    flat_values = synthesized_btf(flat, method, seed=0).eval(points, wv.astype(np.float64), wl.astype(np.float64))
    assert _psnr(got["fp32"].rgb, flat_values) < 40.0


# ---------------------------------------------------------------- struct (lattice-aligned cell quilting) and auto
@pytest.fixture(scope="module")
def structured_model():
    """A random Triple Plane whose positional plane repeats an 8 x 8 element (plus noise) framed by a joint (row and
    column 5 of each element, off the cell edges, so that the seams, which follow the joints, leave the straight
    edges on both sides): ``auto`` picks struct.

    24 x 48 texels: 2 x 1 cells of 24 x 24 texels, cut bands of 6 texels, 16 lattice offsets.
    """
    from dynbtf.representations.triple_plane import TriplePlane

    m = TriplePlane(24, 48, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    g = torch.Generator().manual_seed(3)
    element = torch.randn(8, 8, 6, generator=g)
    element[5, :] = element[:, 5] = -2.0  # the joint
    with torch.no_grad():
        m.f_u.copy_(element.repeat(3, 6, 1) + 0.3 * torch.randn(24, 48, 6, generator=g))
        m.decoder.rest[-1].bias.add_(0.6)
    return m


@pytest.fixture(scope="module")
def struct_exports(structured_model, tmp_path_factory):
    """The default methods (auto, hist, tile) of the structured model, at every precision."""
    root = tmp_path_factory.mktemp("web-struct")
    return {p: export_web(structured_model, root / p, precision=p) for p in ("fp32", "fp16", "u8")}


def test_export_of_auto_is_the_models_choice_exported_once(struct_exports, structured_model, model, tmp_path):
    """auto exports the method synthesized_btf(model, "auto") chooses, under its name, first; never twice."""
    manifest = struct_exports["u8"].manifest
    choice = synthesized_btf(structured_model, "auto").synthesizer.choice
    assert choice.method == "struct"
    assert manifest["auto"]["method"] == "struct" and manifest["auto"]["line"] == choice.line
    assert list(manifest["methods"]) == ["struct", "hist", "tile"] and manifest["default_method"] == "struct"
    entry = manifest["methods"]["struct"]
    tables = synthesized_btf(structured_model, "struct").synthesizer.prepared
    assert entry["mode"] == 4 and entry["cells"] == [2, 1] and entry["margin"] == [6, 6] and entry["count"] == 16
    assert entry["tables"]["format"] == "R16I"  # integer texture: the int16 tables exactly, at every precision
    stored = np.fromfile(struct_exports["u8"].directory / entry["tables"]["file"], dtype="<i2")
    for name in ("offsets", "vertical_cuts", "horizontal_cuts"):
        part = entry["tables"][name]
        values = getattr(tables, name).numpy()
        assert part["shape"] == list(values.shape)
        np.testing.assert_array_equal(stored[part["start"]:part["start"] + values.size], values.reshape(-1))
    assert entry["tables"]["file"] in entry["files"] and struct_exports["u8"].method_bytes("struct") > 0
    # a stochastic model: auto is hist, exported once (auto first, then the listed hist is the same)
    plain = export_web(model, tmp_path / "plain", precision="u8", methods=("auto", "hist", "tile"), viewer=False)
    assert plain.manifest["auto"]["method"] == "hist" and "-> hist" in plain.manifest["auto"]["line"]
    assert list(plain.manifest["methods"]) == ["hist", "tile"] and plain.manifest["default_method"] == "hist"
    assert not any("auto" in name for name in plain.manifest["files"])
    # without auto there is no choice to report
    assert export_web(model, tmp_path / "tile", methods=("tile",), viewer=False).manifest["auto"] is None


def test_cli_export_defaults_to_auto_and_prints_the_choice(structured_model, tmp_path):
    from dynbtf.representations.model_file import save_model

    path = save_model(tmp_path / "weave.dbtfm", structured_model)
    result = _cli("export", path, "-o", tmp_path / "out", "--precision", "u8", "--no-viewer")
    assert result.exit_code == 0, result.text
    assert "method auto -> struct: structured exemplar" in result.output
    assert "the struct method alone needs" in result.output
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert list(manifest["methods"]) == ["struct", "hist", "tile"]
    result = _cli("export", path, "-o", tmp_path / "two", "--method", "tile", "--method", "struct", "--no-viewer")
    assert result.exit_code == 0, result.text
    assert "method auto" not in result.output
    assert list(json.loads((tmp_path / "two" / "manifest.json").read_text())["methods"]) == ["tile", "struct"]


def test_repeat_origin_gives_structs_int64_cell_words():
    """The struct origin words are the repeat's first cell, I x cells, as (low, high) two's complement words."""
    points = np.array([[0.25, 0.5], [-3.5, 7.75], [2.0 ** 45 + 0.5, -(2.0 ** 44) - 0.25], [-(2.0 ** 51), 2.0 ** 51 - 1]])
    o = repeat_origin(points, (48, 24), (48, 24), cells=(2, 3))
    whole = np.floor(points).astype(np.int64)
    np.testing.assert_array_equal(o.cell_x, whole[:, 0] * 2)
    np.testing.assert_array_equal(o.cell_y, whole[:, 1] * 3)
    words = o.shader_words("struct").astype(np.uint64)
    np.testing.assert_array_equal((words[:, 0] | (words[:, 1] << np.uint64(32))).view(np.int64), whole[:, 0] * 2)
    np.testing.assert_array_equal((words[:, 2] | (words[:, 3] << np.uint64(32))).view(np.int64), whole[:, 1] * 3)
    np.testing.assert_array_equal(o.shader_words("hist"), o.words())


@pytest.mark.parametrize("grid", [[4, 8, 1, 2, 0.5, 1.0], [3, 6, 1, 3, 2.25, 0.0], [5, 4, 0, 1, 0.0, 3.5]])
def test_repeat_origin_and_the_shaders_local_part_give_the_element_instances(grid):
    """The element words of the repeat origin (I_u columns - I_v shift, I_v rows) plus the shader's arithmetic on the
    local uv (whole repeats w and fraction f of it, redone here in float64 and int64) are element_instances'."""
    from dynbtf.synthesis.elements import element_instances, repeat_elements

    h, w = 24, 48
    rng = np.random.default_rng(5)
    points = (rng.random((3000, 2)) - 0.5) * 200.0
    points[1000:2000] += np.array([2.0 ** 40, -(2.0 ** 41)])
    shift = rng.integers(-40, 40, 3000)  # the local uv spans a few repeats
    o = repeat_origin(points - shift[:, None], (w, h), (w, h), elements=repeat_elements(grid))
    words = o.element_words().astype(np.uint64)
    np.testing.assert_array_equal((words[:, 0] | (words[:, 1] << np.uint64(32))).view(np.int64), o.element_x)
    np.testing.assert_array_equal((words[:, 2] | (words[:, 3] << np.uint64(32))).view(np.int64), o.element_y)
    local = o.fraction + shift[:, None]
    whole = np.floor(local).astype(np.int64)
    f = local - whole
    columns, rows, p, q = (int(v) for v in grid[:4])
    r = np.floor((f[:, 1] * h - grid[5]) / (h / rows)).astype(np.int64)
    carry = (r * p) // q
    column = np.floor(((f[:, 0] * w - grid[4]) / (w / columns) * q - (r * p - carry * q)) / q).astype(np.int64)
    got_column = o.element_x + whole[:, 0] * columns - whole[:, 1] * (rows * p // q) - carry + column
    got_row = o.element_y + whole[:, 1] * rows + r
    want_column, want_row = element_instances(torch.from_numpy(points), grid, h, w)
    np.testing.assert_array_equal(got_row, want_row.numpy())
    np.testing.assert_array_equal(got_column, want_column.numpy())


def _texel_edge_distance(points, density):
    """Distance (texels) of each query's position to the nearest texel boundary (either axis), in float64."""
    pos = (points - np.floor(points)) * np.asarray(density, np.float64)
    return np.abs(pos - np.rint(pos)).min(-1)


@browser
@pytest.mark.browser
def test_struct_shader_matches_synthesized_btf(struct_exports, structured_model):
    """struct: fp32 equal to float32 rounding, fp16 >= 40 dB, u8 >= 30 dB; "auto" names it in the page too."""
    points, shift, wv, wl = _queries(1024, seed=4)
    btf = synthesized_btf(structured_model, "struct", seed=0)
    ref = btf.eval(points, wv.astype(np.float64), wl.astype(np.float64))
    assert np.abs(ref).max() > 0.5 and ref.std() > 0.05
    # a query within float32 rounding of a texel boundary may fall into the neighbouring texel, and with it
    # into another cell (a different copy): set those aside (the local-uv ones resolve ~1e-3 texels)
    keep = _texel_edge_distance(points, btf.synthesizer.density) > np.where(shift == 0, 1e-5, 2e-3)
    assert keep.mean() > 0.95
    got = {p: eval_in_browser(struct_exports[p].directory, "auto" if p == "fp32" else "struct", points, wv, wl,
                              local_shift=shift).rgb for p in struct_exports}
    peak = np.abs(ref).max()
    exact = keep & (shift == 0)
    np.testing.assert_allclose(got["fp32"][exact], ref[exact], rtol=0, atol=2e-4 * peak)
    np.testing.assert_allclose(got["fp32"][keep & ~exact], ref[keep & ~exact], rtol=0, atol=5e-3 * peak)
    assert _psnr(got["fp16"][keep], ref[keep]) >= 40.0
    assert _psnr(got["u8"][keep], ref[keep]) >= 30.0
    # not a trivial export: another seed chooses other copies, and tiling differs
    other = synthesized_btf(structured_model, "struct", seed=1).eval(points, wv.astype(np.float64), wl.astype(np.float64))
    assert _psnr(got["fp32"][keep], other[keep]) < 30.0
    tiled = synthesized_btf(structured_model, "tile").eval(points, wv.astype(np.float64), wl.astype(np.float64))
    assert _psnr(got["fp32"][keep], tiled[keep]) < 30.0


@browser
@pytest.mark.browser
def test_structs_per_element_variation_in_the_shader_matches_synthesized_btf(structured_model, tmp_path):
    """struct with brightness and tint: each element's factor (its int64 instance from the repeat origin's element
    words and the local uv, hashed; 1 on the joints) in the shader = synthesized_btf's, far from the origin too."""
    params = {"brightness": 0.5, "tint": 0.25}
    export = export_web(structured_model, tmp_path / "varied", precision="fp32", methods=("struct",),
                        method_params={"struct": params})
    entry = export.manifest["methods"]["struct"]
    assert entry["elements"]["brightness"] == 0.5 and "joints" in entry["tables"]
    points, shift, wv, wl = _queries(1024, seed=6)
    btf = synthesized_btf(structured_model, "struct", seed=0, **params)
    ref = btf.eval(points, wv.astype(np.float64), wl.astype(np.float64))
    keep = _texel_edge_distance(points, btf.synthesizer.density) > np.where(shift == 0, 1e-5, 2e-3)
    got = eval_in_browser(export.directory, "struct", points, wv, wl, local_shift=shift).rgb
    peak = np.abs(ref).max()
    exact = keep & (shift == 0)
    np.testing.assert_allclose(got[exact], ref[exact], rtol=0, atol=2e-4 * peak)
    np.testing.assert_allclose(got[keep & ~exact], ref[keep & ~exact], rtol=0, atol=5e-3 * peak)
    plain = synthesized_btf(structured_model, "struct", seed=0).eval(points, wv.astype(np.float64),
                                                                      wl.astype(np.float64))
    gain = btf.synthesizer.variation_gain(torch.from_numpy(points)).numpy()
    assert (gain == 1.0).all(-1).mean() < 0.9 and _psnr(got[keep], plain[keep]) < 30.0


_CELL_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>dynbtf struct cells</title></head><body>
<pre id="dynbtf-result"></pre><pre id="dynbtf-error" hidden></pre>
<script src="viewer.js"></script>
<script>
(function () {
  var job = __JOB__;
  function fail(e) { var p = document.getElementById('dynbtf-error'); p.textContent = String(e && e.message || e); p.hidden = false; }
  DynBTF.load('').then(function (data) {
    var n = job.points.length, w = 256, h = Math.ceil(n / w);
    var gl = document.createElement('canvas').getContext('webgl2');
    var r = new DynBTF.Renderer(gl, data), m = data.manifest;
    var words = new Uint32Array(4 * w * h), local = new Float32Array(4 * w * h), origins = [];
    for (var i = 0; i < n; ++i) {
      var k = job.shift[i], o = DynBTF.origin(m, 'auto', job.points[i][0] - k, job.points[i][1] - k);
      words.set(o.lattice, 4 * i);
      origins.push(o.lattice);
      local[4 * i] = o.fraction[0] + k; local[4 * i + 1] = o.fraction[1] + k;
    }
    var program = r.program('uniform highp usampler2D q_words; uniform highp sampler2D q_local; uniform int q_what;\\n' +
      'layout(location = 0) out uvec4 result;\\nvoid main() { ivec2 p = ivec2(gl_FragCoord.xy);\\n' +
      '  DynbtfOrigin o; o.lattice = texelFetch(q_words, p, 0); o.phase = 0.0; o.texel = ivec2(0);\\n' +
      '  DynbtfCell c = dynbtf_cell(o, texelFetch(q_local, p, 0).xy);\\n' +
      '  if (q_what == 0) result = uvec4(c.cx, c.cy);\\n' +
      '  else if (q_what == 1) result = uvec4(uint(c.chosen), uint(c.side.x + 1), uint(c.side.y + 1), 0u);\\n' +
      '  else result = uvec4(uvec2(c.texel), uvec2(c.offset)); }\\n');
    r.use(program, 'auto');
    [[5, gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, words, 'q_words'], [6, gl.RGBA32F, gl.RGBA, gl.FLOAT, local, 'q_local']]
      .forEach(function (a) {
        var t = gl.createTexture();
        gl.activeTexture(gl.TEXTURE0 + a[0]);
        gl.bindTexture(gl.TEXTURE_2D, t);
        gl.texImage2D(gl.TEXTURE_2D, 0, a[1], w, h, 0, a[2], a[3], a[4]);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
        gl.uniform1i(gl.getUniformLocation(program, a[5]), a[0]);
      });
    var rb = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, rb);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.RGBA32UI, w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, gl.createFramebuffer());
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.RENDERBUFFER, rb);
    gl.viewport(0, 0, w, h);
    var passes = [];
    for (var pass = 0; pass < 3; ++pass) {
      gl.uniform1i(gl.getUniformLocation(program, 'q_what'), pass);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      var out = new Uint32Array(4 * w * h);
      gl.readPixels(0, 0, w, h, gl.RGBA_INTEGER, gl.UNSIGNED_INT, out);
      passes.push(Array.prototype.slice.call(out, 0, 4 * n));
    }
    if (gl.getError() !== gl.NO_ERROR) throw new Error('WebGL error ' + gl.getError());
    document.getElementById('dynbtf-result').textContent = JSON.stringify({passes: passes, origins: origins});
  }).catch(fail);
})();
</script></body></html>
"""


@browser
@pytest.mark.browser
def test_struct_cells_offsets_and_texels_agree_bit_for_bit(struct_exports, structured_model):
    """Every query's cell (int64), chosen lattice offset and texel equal the library's, up to 2**45 repeats.

    The positions hold dyadic fractions that float32 and float64 represent exactly, so no query is set
    aside; they land on cell edges, in the cut bands and on texel boundaries.
    """
    from chromium import run_page

    rng = np.random.default_rng(11)
    n = 2048
    whole = rng.integers(-60, 60, (n, 2)).astype(np.float64)
    whole[512:1024] += 1e6
    whole[1024:1536] += np.array([-(2.0 ** 33) - 5, 2.0 ** 31 + 3])  # beyond int32 cell indices
    whole[1536:1792] += np.array([2.0 ** 45, -(2.0 ** 44)])
    whole[1792:] += np.array([-(2.0 ** 45) + 7, 2.0 ** 45 - 3])
    bits = np.full((n, 1), 12.0)
    bits[1536:] = 6.0  # float64 holds 2**45 + 7 bits
    frac = np.floor(rng.random((n, 2)) * 2.0 ** bits) / 2.0 ** bits
    points = whole + frac
    assert np.array_equal(points - whole, frac)
    shift = np.zeros(n, np.int64)
    shift[:384] = rng.integers(-2000, 2000, 384)  # into the float32 local uv (12-bit fractions stay exact)
    job = {"points": points.tolist(), "shift": shift.tolist()}
    directory = struct_exports["fp16"].directory
    page = directory / "cells-probe.html"
    page.write_text(_CELL_PAGE.replace("__JOB__", json.dumps(job)))
    try:
        run = run_page(page, budget_ms=600000)
    finally:
        page.unlink()
    assert not (run.element("dynbtf-error") or "").strip(), run.element("dynbtf-error")
    res = json.loads(run.element("dynbtf-result"))
    cells_words, choice, texel = (np.array(p, dtype=np.uint64).reshape(n, 4) for p in res["passes"])

    def int64(lo, hi):
        return (lo | (hi << np.uint64(32))).view(np.int64)

    synth = synthesized_btf(structured_model, "struct", seed=0).synthesizer
    w, h = synth.density
    nx, ny = synth.prepared.cells
    positions, chosen = synth.read_positions(torch.from_numpy(points))
    # the origin words viewer.js gave (for "auto") are repeat_origin's for struct
    origin = repeat_origin(points - shift[:, None], (w, h), (w, h), cells=(nx, ny))
    np.testing.assert_array_equal(np.array(res["origins"], dtype=np.uint32), origin.shader_words("struct"))
    texel_x = np.minimum(np.floor(frac[:, 0] * w).astype(np.int64), w - 1)
    texel_y = np.minimum(np.floor(frac[:, 1] * h).astype(np.int64), h - 1)
    cell = np.stack([whole[:, 0].astype(np.int64) * nx + texel_x // (w // nx),
                     whole[:, 1].astype(np.int64) * ny + texel_y // (h // ny)], -1)
    np.testing.assert_array_equal(np.stack([int64(cells_words[:, 0], cells_words[:, 1]),
                                            int64(cells_words[:, 2], cells_words[:, 3])], -1), cell)
    np.testing.assert_array_equal(choice[:, 0].astype(np.int64), chosen.numpy())
    offsets = synth.prepared.offsets.numpy()[chosen.numpy()]
    np.testing.assert_array_equal(texel[:, 2:].astype(np.int64), offsets)
    corner = np.floor(positions.numpy() - 0.5).astype(np.int64) % np.array([w, h])
    np.testing.assert_array_equal(texel[:, :2].astype(np.int64), corner)
    # the cuts were exercised: points taken by each neighbour, and by the diagonal cell
    side = choice[:, 1:3].astype(np.int64) - 1
    for axis in (0, 1):
        assert (side[:, axis] == -1).any() and (side[:, axis] == 1).any()
    assert ((side != 0).all(-1)).any() and len(np.unique(chosen.numpy())) == synth.prepared.count


@browser
@pytest.mark.browser
def test_viewer_shows_the_auto_choice_by_default(struct_exports):
    """The viewer selects struct, marked (auto), offers hist and tile, and draws it 1e6 uv units out."""
    run = _probe_viewer(struct_exports["fp16"].directory, budget_ms=4000, query="method=auto&origin=1e6")
    assert 'data-state="running"' in run.dom, (run.element("dynbtf-error") or "") + run.dom[-1500:]
    assert run.element("probe-console") is None and run.console == []
    assert '<option value="struct" title="method auto -&gt; struct' in run.dom
    assert ">struct (auto)</option>" in run.dom and ">hist</option>" in run.dom and ">tile</option>" in run.dom


def test_shader_cost_of_struct_is_one_fetch_and_the_cell_hashes(model):
    from dynbtf.export.web.shader import shader_cost

    cfg = model.config()
    sizes = dict(channels=cfg["positional_channels"], angular_channels=cfg["angular_channels"], hidden=cfg["hidden"],
                 layers=cfg["layers"])
    struct, tile, hist = (shader_cost(m, **sizes) for m in ("struct", "tile", "hist"))
    # one 2 x 2 footprint of 2 RGBA layers, the offset's two entries, one vertical and one horizontal cut
    assert struct["texel_fetches"] == 4 * 2 + 2 + 2 + 2 * 4 * 1 == tile["texel_fetches"] + 4
    assert struct["macs"] == tile["macs"] and struct["decoder_macs"] == hist["decoder_macs"]
    assert struct["hashes"] == 4 and tile["hashes"] == hist["hashes"] == 3


# ---------------------------------------------------------------- guided synthesis (dynbtf.synthesis.guided_blending)
def _guided_btf(model, method, wrap, softness=0.0):
    """Guided hist or hex on ``model`` (seed 0): the plane's labels in 5 x 6 blocks (two classes), the target a 3 x 2
    image over 3 repeats (``wrap``) that also asks for a label the plane lacks (7: never matched)."""
    from dynbtf.material.compiler import model_arguments
    from dynbtf.synthesis.guided_blending import GuidedBlending, GuidedHexTiling, LabelField

    h, w = model.positional_plane().shape[:2]
    rows, cols = np.mgrid[0:h, 0:w]
    labels = (cols // 5 + rows // 6) % 2
    target = LabelField(np.array([[0, 1, 1], [1, 0, 7]]), size=3.0, wrap=wrap)
    plane = model.positional_plane().detach()
    if method == "guided":
        synth = GuidedBlending(plane, 0, labels=labels, target=target, softness=softness)
    else:
        synth = GuidedHexTiling(plane, 0, labels=labels, target=target, softness=softness,
                                **model_arguments(model, "hex", {}))
    return synthesized_btf(model, synth)


@browser
@pytest.mark.browser
@pytest.mark.parametrize("method, wrap, softness", [("guided", "repeat", 0.3), ("guided-hex", "clamp", 0.0)])
def test_guided_shader_matches_synthesized_btf(model, tmp_path, method, wrap, softness):
    """Guided hist and hex in the shader: the target's label per query, each sample's candidate search, the steered
    barycentrics and the method's blend, as the library answers them (near the origin and up to 7e12 repeats)."""
    btf = _guided_btf(model, method, wrap, softness)
    points, shift, wv, wl = _queries(1024)
    ref = btf.eval(points, wv.astype(np.float64), wl.astype(np.float64))
    base = synthesized_btf(model, btf.synthesizer.base_method, seed=0).eval(points, wv.astype(np.float64),
                                                                             wl.astype(np.float64))
    peak = np.abs(ref).max()
    assert np.abs(ref - base).max() > 0.2 * peak  # the guidance shows: not the unguided method's answer
    got = eval_in_browser(export_web(btf.material, tmp_path / "fp32", precision="fp32", methods=(method,)).directory,
                          method, points, wv, wl, local_shift=shift).rgb
    exact = shift == 0
    np.testing.assert_allclose(got[exact], ref[exact], rtol=0, atol=2e-4 * peak)
    # up to 300 repeats in the float32 local uv (positions within ~2e-5 repeats): a query that close to a texel's
    # edge may see another footprint's labels and choose another candidate
    close = np.abs(got[~exact] - ref[~exact]).max(-1) <= 5e-3 * peak
    assert close.mean() >= 0.99, close.mean()
    if method == "guided":
        half = export_web(btf.material, tmp_path / "fp16", precision="fp16", methods=(method,))
        assert _psnr(eval_in_browser(half.directory, method, points[exact], wv[exact], wl[exact]).rgb,
                     ref[exact]) >= 40.0


def test_guided_export_carries_the_guidance(model, tmp_path):
    """The manifest entry of a guided method: its mode, the labels of the read plane and the target image (exact
    int16, renumbered; a target label the plane lacks is -1), the candidates' hash states (the fused kernel's), the
    softness and the target as a label field; a guided method without its labels is refused."""
    from dynbtf.export.web.shader import field_origin, web_module

    btf = _guided_btf(model, "guided", "repeat", 0.3)
    synth = btf.synthesizer
    export = export_web(btf.material, tmp_path / "web", precision="u8", methods=("guided",))
    entry = export.manifest["methods"]["guided"]
    assert entry["mode"] == web_module("guided").MODE and entry["lut"]["size"] == synth.parameters()["lut_size"]
    states, labels, _, softness = synth.kernel_guidance(torch.zeros((0, 2), dtype=torch.float64))
    assert entry["states"] == [int(s) for s in states] and entry["candidates"] == 16
    assert entry["softness"] == softness == 0.3
    assert entry["field"] == {"width": 3, "height": 2, "size": 3.0, "wrap": "repeat"}
    table = entry["guidance"]
    stored = np.fromfile(export.directory / table["file"], dtype="<i2")
    ph, pw = labels.shape
    assert table["labels"] == {"start": 0, "shape": [ph, pw]} and table["target"]["shape"] == [2, 3]
    np.testing.assert_array_equal(stored[:ph * pw].reshape(ph, pw), labels)  # labels 0 and 1 stay themselves
    start = table["target"]["start"]
    np.testing.assert_array_equal(stored[start:start + 6].reshape(2, 3), [[0, 1, 1], [1, 0, -1]])
    assert table["file"] in entry["files"]
    # the repeat origin's place on the field: (I mod 3) / 3 texels per repeat, as LabelField reduces a position
    np.testing.assert_allclose(field_origin(np.array([[4.0, -1.0]]), entry["field"]), [[1.0, 4.0 / 3.0]])
    with pytest.raises(InputError, match=r"'guided-struct' needs parameter\(s\) \['labels', 'target'\]"):
        export_web(model, tmp_path / "struct", methods=("guided-struct",))
    with pytest.raises(InputError, match=r"'guided' needs parameter\(s\) \['labels', 'target'\]"):
        export_web(model, tmp_path / "bare", methods=("guided",))


def test_cli_export_target_exports_the_guided_material(model, structured_model, tmp_path):
    """``dynbtf export --target``: the guided material guided_btf builds from the same options, exported as its guided
    method (hist for auto, hex when asked): the manifest carries the guidance (the target as a label field over
    --target-size x --scale repeats, the softness, the labels table), byte for byte the Python export's."""
    from dynbtf.guided import guided_btf
    from dynbtf.io import save_image
    from dynbtf.representations.model_file import save_model

    path = save_model(tmp_path / "m.dbtfm", model)
    painted = np.zeros((4, 6, 3), np.float32)
    painted[:, 3:] = 1.0  # left half class 0 (the darkest), right half class 1
    save_image(tmp_path / "target.png", painted)
    result = _cli("export", path, "-o", tmp_path / "out", "--precision", "u8", "--no-viewer", "--target",
                  tmp_path / "target.png", "--target-size", "0.5", "--target-wrap", "clamp", "--softness", "0.25",
                  "--scale", "6", "--seed", "3")
    assert result.exit_code == 0, result.text
    assert "guided, guided by" in result.output and "2 classes" in result.output
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert list(manifest["methods"]) == ["guided"] and manifest["default_method"] == "guided"
    entry = manifest["methods"]["guided"]
    assert entry["field"] == {"width": 6, "height": 4, "size": 3.0, "wrap": "clamp"}  # 0.5 uv units x 6 repeats
    assert entry["softness"] == 0.25 and entry["candidates"] == 16
    target = np.fromfile(tmp_path / "out" / entry["guidance"]["file"], dtype="<i2")
    start = entry["guidance"]["target"]["start"]
    np.testing.assert_array_equal(target[start:start + 24].reshape(4, 6), np.repeat([[0, 0, 0, 1, 1, 1]], 4, 0))
    # the same as the library's guided material, exported from Python
    btf = guided_btf(model, painted.mean(-1), classes=2, target_size=0.5, target_wrap="clamp", scale=6.0, seed=3,
                     softness=0.25)
    python = export_web(btf.material, tmp_path / "py", precision="u8", methods=("guided",), scale=6.0, viewer=False)
    reference = python.manifest["methods"]["guided"]
    assert entry["states"] == reference["states"] and entry["field"] == reference["field"]
    assert (tmp_path / "out" / entry["guidance"]["file"]).read_bytes() == \
        (python.directory / reference["guidance"]["file"]).read_bytes()
    hexed = _cli("export", path, "-o", tmp_path / "hex", "--no-viewer", "--target", tmp_path / "target.png",
                 "--method", "hex")
    assert hexed.exit_code == 0, hexed.text
    assert list(json.loads((tmp_path / "hex" / "manifest.json").read_text())["methods"]) == ["guided-hex"]
    weave = save_model(tmp_path / "weave.dbtfm", structured_model)
    struct = _cli("export", weave, "-o", tmp_path / "struct", "--no-viewer", "--target", tmp_path / "target.png",
                  "--method", "struct", "--cells", "2", "--target-size", "0.25")
    assert struct.exit_code == 0, struct.text
    entry = json.loads((tmp_path / "struct" / "manifest.json").read_text())["methods"]["guided-struct"]
    assert entry["cells"] == [2, 2] and entry["field"] == {"width": 6, "height": 4, "size": 2.0, "wrap": "repeat"}


def test_cli_export_target_refuses_bad_guidance_in_one_line(model, tmp_path, capsys):
    """Bad guidance options are one error line naming the option, before anything is written."""
    from dynbtf.cli.main import main
    from dynbtf.io import save_image
    from dynbtf.representations.model_file import save_model

    path = save_model(tmp_path / "m.dbtfm", model)
    save_image(tmp_path / "target.png", np.zeros((4, 4, 3), np.float32))
    target = ["--target", tmp_path / "target.png"]
    for extra, message in (
            (["--target", tmp_path / "nothere.png"], "--target: " + str(tmp_path / "nothere.png")
             + ": no such image file"),
            (target + ["--method", "tile"], "--target: guided synthesis steers hist, hex or struct"),
            (target + ["--method", "hist", "--method", "hex"], "--target: exports one guided method"),
            (target + ["--method", "struct"], "--target: guided struct chooses whole cells by class, so give its cells"),
            (target + ["--cells", "2"], "--cells: sets struct's cells; give it with --method struct"),
            (target + ["--classes", "1"], "--classes: expected 2 to 255 classes, got 1"),
            (target + ["--softness", "2"], "--softness: expected a weight factor in [0, 1], got 2.0"),
            (target + ["--target-size", "0"], "--target-size: expected a positive, finite uv units"),
            (target + ["--target-wrap", "mirror"], "--target-wrap: expected 'repeat' or 'clamp', got 'mirror'"),
            (target + ["--layer", path], "--target: guides one material; it does not combine with a layered export")):
        capsys.readouterr()
        assert main([str(a) for a in ["export", path, "-o", tmp_path / "bad", *extra]]) == 2
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(err) == 1 and err[0].startswith("dynbtf: error: ") and message in err[0], (extra, err)
        assert not (tmp_path / "bad").exists()


def _guided_struct_btf(structured_model, wrap):
    """Guided struct on the structured model (seed 0, struct's 2 x 1 cells): the texels labelled by the 8-texel
    columns of the element (so a cell's majority label depends on its offset), the target a 3 x 2 image over 2.4
    repeats (``wrap``: no cell centre lies on a target texel's edge) that also asks for a label no cell has (7)."""
    from dynbtf.material.compiler import model_arguments
    from dynbtf.synthesis.guided_blending import GuidedCellQuilting, LabelField

    h, w = structured_model.positional_plane().shape[:2]
    labels = (np.mgrid[0:h, 0:w][1] // 8) % 2
    target = LabelField(np.array([[0, 1, 1], [1, 0, 7]]), size=2.4, wrap=wrap)
    synth = GuidedCellQuilting(structured_model.positional_plane().detach(), 0, labels=labels, target=target,
                               **model_arguments(structured_model, "struct", {}))
    return synthesized_btf(structured_model, synth)


@browser
@pytest.mark.browser
@pytest.mark.parametrize("wrap", ["repeat", "clamp"])
def test_guided_struct_shader_matches_synthesized_btf(structured_model, tmp_path, wrap):
    """Guided struct in the shader: every cell's offset chosen by label (its own and the neighbours' whose cuts it
    consults), the cuts and the read texel, as the library answers them (near the origin and up to 7e12 repeats)."""
    btf = _guided_struct_btf(structured_model, wrap)
    points, shift, wv, wl = _queries(1024, seed=4)
    ref = btf.eval(points, wv.astype(np.float64), wl.astype(np.float64))
    base = synthesized_btf(structured_model, "struct", seed=0).eval(points, wv.astype(np.float64),
                                                                     wl.astype(np.float64))
    peak = np.abs(ref).max()
    assert np.abs(ref - base).max() > 0.2 * peak  # the guidance shows: not struct's own choices
    keep = _texel_edge_distance(points, btf.synthesizer.density) > np.where(shift == 0, 1e-5, 2e-3)
    assert keep.mean() > 0.95
    export = export_web(btf.material, tmp_path / "fp32", precision="fp32", methods=("guided-struct",))
    entry = export.manifest["methods"]["guided-struct"]
    assert entry["field"] == {"width": 3, "height": 2, "size": 2.4, "wrap": wrap} and "tables" in entry
    got = eval_in_browser(export.directory, "guided-struct", points, wv, wl, local_shift=shift).rgb
    exact = keep & (shift == 0)
    np.testing.assert_allclose(got[exact], ref[exact], rtol=0, atol=2e-4 * peak)
    np.testing.assert_allclose(got[keep & ~exact], ref[keep & ~exact], rtol=0, atol=5e-3 * peak)
    if wrap == "repeat":
        half = export_web(btf.material, tmp_path / "fp16", precision="fp16", methods=("guided-struct",))
        assert _psnr(eval_in_browser(half.directory, "guided-struct", points[exact], wv[exact], wl[exact]).rgb,
                     ref[exact]) >= 40.0


def test_guided_struct_export_carries_the_cell_labels(structured_model, tmp_path):
    """The manifest entry of guided struct: its mode, struct's tables, the cells' majority labels per offset and the
    target image (exact int16, renumbered; a label no cell has is -1) and the target as a label field; the same when
    the export builds it from the model with its labels and target as method parameters."""
    from dynbtf.export.web.shader import web_module

    btf = _guided_struct_btf(structured_model, "repeat")
    synth = btf.synthesizer
    export = export_web(btf.material, tmp_path / "web", precision="u8", methods=("guided-struct",))
    entry = export.manifest["methods"]["guided-struct"]
    assert entry["mode"] == web_module("guided-struct").MODE != web_module("struct").MODE
    assert entry["cells"] == list(synth.prepared.cells) and entry["count"] == synth.prepared.count
    assert entry["field"] == {"width": 3, "height": 2, "size": 2.4, "wrap": "repeat"}
    table = entry["guidance"]
    stored = np.fromfile(export.directory / table["file"], dtype="<i2")
    nx, ny = synth.prepared.cells
    k = synth.prepared.count
    assert table["cell_labels"] == {"start": 0, "shape": [nx, ny, k]}
    np.testing.assert_array_equal(stored[:nx * ny * k].reshape(nx, ny, k), synth.cell_labels.numpy())  # 0 and 1
    assert {0, 1} <= set(np.unique(synth.cell_labels.numpy()))  # the offsets' content differs: a choice to make
    start = table["target"]["start"]
    np.testing.assert_array_equal(stored[start:start + 6].reshape(2, 3), [[0, 1, 1], [1, 0, -1]])
    built = export_web(structured_model, tmp_path / "built", precision="u8", methods=("guided-struct",),
                       method_params={"guided-struct": {"labels": synth.labels, "target": synth.target}})
    other = built.manifest["methods"]["guided-struct"]
    assert (built.directory / other["guidance"]["file"]).read_bytes() == \
        (export.directory / table["file"]).read_bytes()
