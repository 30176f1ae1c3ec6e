"""Compiled materials: the saved artifact every backend reads (dynbtf.compiled_material, dynbtf.training.compile).

Round trips (every synthesis method's tables, the folded decoder, per-level decoders and mean appearance read back
bit for bit), damaged and foreign files (clear errors naming the file), the cache keyed by model contents (a second
object of the same model reads what the first compiled; a damaged entry is rebuilt), the command line, and every
backend -- the library's numba and torch paths, the Dr.Jit kernel, the GLSL shader -- evaluating a compiled material
held to a float64 reference computed from the material's own tensors.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import torch

from dynbtf.compiled_material import FORMAT_VERSION, load_compiled, save_compiled
from dynbtf.errors import FormatError, InputError
from dynbtf.infinite_btf import SynthesizedBTF
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.training.compile import cached_material, compile_material

METHODS = ["tile", "linear", "hist", "hex", "struct", "quilt"]
RNG = np.random.default_rng(20261125)


@pytest.fixture(scope="module")
def model():
    rep = TriplePlane(32, 32, seed=5)
    with torch.no_grad():  # a plane with structure (a 16-texel period) and visible angular variation
        grid = torch.arange(32.0)
        rep.f_u.add_(0.5 * torch.sin(grid * np.pi / 8)[:, None, None] * torch.cos(grid * np.pi / 8)[None, :, None])
        rep.f_h.normal_(generator=torch.Generator().manual_seed(1))
        rep.f_d.normal_(generator=torch.Generator().manual_seed(2))
    return rep.eval()


def queries(n: int, spread: float = 40.0, seed: int | None = None):
    rng = RNG if seed is None else np.random.default_rng(seed)
    uv = (rng.random((n, 2)) - 0.5) * spread
    theta = rng.random((2, n)) * 70.0
    phi = rng.random((2, n)) * 360.0
    from dynbtf.conventions import spherical_to_direction

    w = spherical_to_direction(theta, phi)
    return uv, w[0], w[1]


@pytest.mark.parametrize("method", METHODS)
def test_every_methods_tables_read_back_bit_for_bit(model, method, tmp_path):
    material = compile_material(model, method, seed=7, footprints=False)
    save_compiled(material, tmp_path / "m.dbtfc")
    loaded = load_compiled(tmp_path / "m.dbtfc")
    assert loaded.method == method and loaded.seed == 7 and set(loaded.synthesis) == set(material.synthesis)
    for name, tensor in material.synthesis.items():
        assert torch.equal(loaded.synthesis[name], tensor), name
    built, read = material.synthesizer(), loaded.synthesizer()
    uv = torch.from_numpy((RNG.random((500, 2)) - 0.5) * 1e4)
    assert torch.equal(read.latent(uv), built.latent(uv))
    if built.level_of_detail() is not None:
        texels = torch.from_numpy(np.geomspace(0.5, 200.0, 500))
        assert torch.equal(read.filtered_latent(uv, texels), built.filtered_latent(uv, texels))


def test_a_compiled_file_answers_as_the_model_point_and_footprint(model, tmp_path):
    btf = SynthesizedBTF(model, "hist", scale=3.0, seed=2)
    uv, wv, wl = queries(2000)
    footprint = np.geomspace(1e-3, 30.0, 2000)
    point, filtered = btf.eval(uv, wv, wl), btf.eval(uv, wv, wl, footprint=footprint)
    save_compiled(btf.material, tmp_path / "hist.dbtfc")  # with its footprint decoders (fitted by the eval above)
    loaded = load_compiled(tmp_path / "hist.dbtfc")
    assert len(loaded.decoder.levels) == len(btf.material.decoder.levels) > 1 and loaded.decoder.mean is not None
    again = SynthesizedBTF(tmp_path / "hist.dbtfc", scale=3.0)
    np.testing.assert_array_equal(again.eval(uv, wv, wl), point)
    np.testing.assert_array_equal(again.eval(uv, wv, wl, footprint=footprint), filtered)
    with pytest.raises(InputError, match="compiled material fixes method 'hist' and seed 2"):
        SynthesizedBTF(tmp_path / "hist.dbtfc", "hex")


def _rewrite_header(path, out, change):
    data = path.read_bytes()
    size = struct.unpack("<Q", data[:8])[0]
    header = json.loads(data[8:8 + size])
    meta = json.loads(header["__metadata__"]["dynbtf"])
    change(meta)
    header["__metadata__"]["dynbtf"] = json.dumps(meta)
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 8)
    out.write_bytes(struct.pack("<Q", len(text)) + text + data[8 + size:])


def test_damaged_foreign_and_newer_files_are_refused_naming_the_file(model, tmp_path):
    good = tmp_path / "good.dbtfc"
    save_compiled(compile_material(model, "tile", footprints=False), good)
    flipped = tmp_path / "flipped.dbtfc"
    data = bytearray(good.read_bytes())
    data[-5] ^= 0x40
    flipped.write_bytes(bytes(data))
    with pytest.raises(FormatError, match=r"flipped\.dbtfc: tensor data does not match its checksum"):
        load_compiled(flipped)
    cut = tmp_path / "cut.dbtfc"
    cut.write_bytes(good.read_bytes()[:-100])
    with pytest.raises(FormatError, match=r"cut\.dbtfc"):
        load_compiled(cut)
    newer = tmp_path / "newer.dbtfc"
    _rewrite_header(good, newer, lambda meta: meta.update(format_version=FORMAT_VERSION + 1))
    with pytest.raises(FormatError, match=rf"newer\.dbtfc: compiled-material format version {FORMAT_VERSION + 1}"):
        load_compiled(newer)
    foreign = tmp_path / "model.dbtfc"
    from dynbtf.representations.model_file import save_model

    save_model(foreign, model)
    with pytest.raises(FormatError, match=r"model\.dbtfc: not a compiled material"):
        load_compiled(foreign)
    huge = tmp_path / "huge.dbtfc"
    _rewrite_header(good, huge, lambda meta: meta["config"].update(hidden=200000))
    with pytest.raises(FormatError, match=r"huge\.dbtfc"):
        load_compiled(huge)


def test_the_cache_is_keyed_by_contents_and_a_damaged_entry_is_rebuilt(model, tmp_path, monkeypatch):
    import copy

    import dynbtf.training.compile as compile_module

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path / "cache"))
    built = []
    real = compile_module.compile_material
    monkeypatch.setattr(compile_module, "compile_material", lambda *a, **k: built.append(a[1]) or real(*a, **k))
    first, how = cached_material(model, "hex", 3, footprints=False)
    assert how == "compiled" and built == ["hex"]
    second, how = cached_material(copy.deepcopy(model), "hex", 3, footprints=False)
    assert how == "cached" and built == ["hex"]
    for name, tensor in first.synthesis.items():
        assert torch.equal(second.synthesis[name], tensor)
    assert cached_material(model, "hex", 4, footprints=False)[1] == "compiled"  # another seed: another entry
    entry = tmp_path / "cache" / f"{first.key}.dbtfc"
    entry.write_bytes(entry.read_bytes()[:-64])
    with pytest.warns(UserWarning, match="compiled-material cache: .* compiling again"):
        third, how = cached_material(model, "hex", 3, footprints=False)
    assert how == "compiled" and load_compiled(entry).key == first.key


def test_compile_command_writes_reads_back_and_reuses_the_cache(model, tmp_path, monkeypatch, capsys):
    from dynbtf.cli.main import main
    from dynbtf.representations.model_file import save_model

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path / "cache"))
    save_model(tmp_path / "m.dbtfm", model)
    args = ["compile", str(tmp_path / "m.dbtfm"), "--method", "struct", "--no-footprints", "-o", str(tmp_path / "m.dbtfc")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "method struct, seed 0" in out and "compiled in" in out
    assert load_compiled(tmp_path / "m.dbtfc").method == "struct"
    assert main(args) == 0
    assert "cached in" in capsys.readouterr().out
    assert main(["compile", str(tmp_path / "m.dbtfm"), "-o", str(tmp_path / "m.png")]) == 2
    assert "expected a .dbtfc file name" in capsys.readouterr().err


# ---------------------------------------------------------------- every backend reads one compiled material
def reference_eval(material, uv: np.ndarray, wv: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """float64 reference of a compiled material's point query: the stored synthesizer's torch path (float64
    positions), the stored folded layer 1, the model's angular planes fetched at the reference angular coordinates,
    the stored layers 2.. in float64."""
    from test_one_truth import reference_angular_coords, reference_fetch_angular, reference_half_diff, reference_mlp

    synth = material.synthesizer()
    fast = synth.fast
    synth.fast = False
    if material.method == "hist":  # rendering's definition inverts the Gaussian transform through the stored table
        from dynbtf.synthesis.histogram import blend_weights, variance_preserving_blend

        lut = synth.prepared.extras["lut"]
        synth.blend = lambda samples, bary, uv_samples: lut(variance_preserving_blend(
            samples.double(), blend_weights(bary, synth.gamma))).float()
    try:
        latent = synth.latent(torch.from_numpy(uv)).double().numpy()
    finally:
        synth.fast = fast
        synth.__dict__.pop("blend", None)
    d = material.decoder
    point = d.levels[0]
    h, dd = reference_half_diff(wv, wl)
    model = material.model
    angular = np.concatenate([reference_fetch_angular(model.f_h.detach().numpy(), reference_angular_coords(h)),
                              reference_fetch_angular(model.f_d.detach().numpy(), reference_angular_coords(dd))], 1)
    first = latent @ point.weight.double().numpy() + point.bias.double().numpy() \
        + angular @ d.angular_weight.double().numpy().T + d.first_bias.double().numpy()
    x = np.where(first >= 0, first, first * d.slope)
    layers = [(w.double().numpy(), b.double().numpy()) for w, b in point.rest]
    return reference_mlp(x, layers, d.slope)


@pytest.fixture(scope="module")
def compiled(model, tmp_path_factory):
    """One saved compiled material per method, read back (the backends below read these files' contents)."""
    folder = tmp_path_factory.mktemp("compiled")
    out = {}
    for method in ("tile", "hist", "hex", "struct"):
        save_compiled(compile_material(model, method, seed=9, footprints=False), folder / f"{method}.dbtfc")
        out[method] = load_compiled(folder / f"{method}.dbtfc")
    return out


def _away_from_pole(wv, wl):
    from test_one_truth import _away_from_phi_seam

    return _away_from_phi_seam(wv, wl)


@pytest.mark.parametrize("method", ["tile", "hist", "hex", "struct"])
@pytest.mark.parametrize("backend", ["numba", "torch", "drjit", "glsl"])
def test_every_backend_reads_the_compiled_material_as_the_float64_reference(compiled, method, backend, tmp_path):
    material = compiled[method]
    uv, wv, wl = queries(300, spread=1e3, seed=17)  # the same queries for every backend and method
    # float32 directions for every backend (the Dr.Jit kernel and the shader take float32 vectors), the reference
    # computed from those same values in float64
    wv, wl = wv.astype(np.float32).astype(np.float64), wl.astype(np.float32).astype(np.float64)
    keep = _away_from_pole(wv, wl)
    want = reference_eval(material, uv, wv, wl)
    scale = np.abs(want).max()
    if backend in ("numba", "torch"):
        btf = SynthesizedBTF(material)
        if backend == "torch":  # the torch synthesis path and the torch decoder's first layer
            btf.synthesizer.fast = False
            btf.decode_path._fused = None
        got = btf.eval(uv, wv, wl)
    elif backend == "drjit":
        mi = pytest.importorskip("mitsuba")
        from dynbtf.render.mitsuba.bsdf import DynBTFEvaluator
        from dynbtf.render.mitsuba.drjit_ops import mi_module

        mi = mi_module()
        evaluator = DynBTFEvaluator(material.model, method, material.seed)
        assert evaluator.btf.material.key == material.key  # the cached twin of the file's material
        rgb = evaluator.eval(mi.Float64(uv[:, 0]), mi.Float64(uv[:, 1]), mi.Vector3f(*wv.T.astype(np.float32)),
                             mi.Vector3f(*wl.T.astype(np.float32)))
        got = np.stack([np.asarray(rgb.x), np.asarray(rgb.y), np.asarray(rgb.z)], axis=-1)
    else:
        from chromium import eval_in_browser, find_chromium

        if find_chromium() is None:
            pytest.skip("needs headless Chromium (scripts/test.sh installs it)")
        from dynbtf.export.web.exporter import export_web

        export_web(material.model, tmp_path / "web", precision="fp32", methods=(method,), seed=material.seed)
        got = eval_in_browser(tmp_path / "web", method, uv, wv, wl).rgb
    # the torch path computes the angular coordinates from float32 directions (the others in float64 or with
    # their own float32 care): near the poles of h and d that moves the fetch by ~1e-4 of the value range
    tolerance = {"numba": 2e-5, "torch": 5e-4, "drjit": 1e-4, "glsl": 2e-3}[backend]
    error = np.abs(got[keep] - want[keep]).max(1)
    if backend in ("drjit", "glsl"):
        # float32 kernels: a few queries at a lattice edge or an angular seam may round to the other side (a jump
        # of a few 1e-3 of the range); every query stays within 1%, and 99% within the tolerance
        assert error.max() < 1e-2 * scale
        assert np.mean(error < tolerance * scale) > 0.99
    else:
        assert error.max() < tolerance * scale
