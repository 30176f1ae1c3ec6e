"""Compiled materials: the saved artifact every backend reads (dynbtf.material, dynbtf.material).

Round trips (every synthesis method's tables, the folded decoder, per-level decoders and mean appearance read back
bit for bit), damaged and foreign files (clear errors naming the file), the cache keyed by model contents (a second
object of the same model reads what the first compiled; a damaged entry is rebuilt) and the command line. Every
backend reading a compiled material is held to the float64 reference in ``test_one_truth.py``.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import torch

from dynbtf.material import FORMAT_VERSION, load_compiled, save_compiled
from dynbtf.errors import FormatError, InputError
from dynbtf.synthesized import synthesized_btf
from dynbtf.material import open_or_compile, compile_material
from test_one_truth import material_model, material_queries as queries

METHODS = ["tile", "linear", "hist", "hex", "struct", "quilt"]
RNG = np.random.default_rng(20261125)


@pytest.fixture(scope="module")
def model():
    return material_model()


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
    btf = synthesized_btf(model, "hist", scale=3.0, seed=2, footprints=True)
    uv, wv, wl = queries(2000)
    footprint = np.geomspace(1e-3, 30.0, 2000)
    point, filtered = btf.eval(uv, wv, wl), btf.eval(uv, wv, wl, footprint=footprint)
    save_compiled(btf.material, tmp_path / "hist.dbtfc")  # with its footprint decoders
    loaded = load_compiled(tmp_path / "hist.dbtfc")
    assert len(loaded.decoder.levels) == len(btf.material.decoder.levels) > 1 and loaded.decoder.mean is not None
    again = synthesized_btf(tmp_path / "hist.dbtfc", scale=3.0)
    np.testing.assert_array_equal(again.eval(uv, wv, wl), point)
    np.testing.assert_array_equal(again.eval(uv, wv, wl, footprint=footprint), filtered)
    with pytest.raises(InputError, match="compiled material fixes method 'hist' and seed 2"):
        synthesized_btf(tmp_path / "hist.dbtfc", "hex")


def test_footprint_decoders_fit_inside_torch_no_grad(model):
    """Compiling with footprints fits per-level decoders with gradients whatever the caller's autograd mode: inside
    ``torch.no_grad()`` (an inference caller, a benchmark) it fits the same decoders as outside."""
    outside = compile_material(model, "hex", seed=5, footprints=True)
    with torch.no_grad():
        inside = compile_material(model, "hex", seed=5, footprints=True)
    assert len(inside.decoder.levels) == len(outside.decoder.levels) > 1
    for a, b in zip(inside.decoder.levels, outside.decoder.levels):
        assert torch.equal(a.weight, b.weight) and all(torch.equal(x, y) for pair in zip(a.rest, b.rest)
                                                       for x, y in zip(*pair))


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

    import dynbtf.material.cache as compile_module

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path / "cache"))
    built = []
    real = compile_module.compile_material
    monkeypatch.setattr(compile_module, "compile_material", lambda *a, **k: built.append(a[1]) or real(*a, **k))
    first, how = open_or_compile(model, "hex", 3, footprints=False)
    assert how == "compiled" and built == ["hex"]
    second, how = open_or_compile(copy.deepcopy(model), "hex", 3, footprints=False)
    assert how == "cached" and built == ["hex"]
    for name, tensor in first.synthesis.items():
        assert torch.equal(second.synthesis[name], tensor)
    assert open_or_compile(model, "hex", 4, footprints=False)[1] == "compiled"  # another seed: another entry
    entry = tmp_path / "cache" / f"{first.key}.dbtfc"
    entry.write_bytes(entry.read_bytes()[:-64])
    with pytest.warns(UserWarning, match="compiled-material cache: .* compiling again"):
        third, how = open_or_compile(model, "hex", 3, footprints=False)
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


def test_synth_export_and_render_take_a_compiled_material(model, tmp_path, monkeypatch, capsys):
    """The artifact `dynbtf compile -o` writes is used as compiled (its method and seed) by synth, export and render;
    another seed is refused in one line; another method is built from the model inside it."""
    from dynbtf.cli.main import main
    from dynbtf.io import load_image

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", "off")
    material = compile_material(model, "hist", seed=3, footprints=False)
    path = save_compiled(material, tmp_path / "m.dbtfc")
    assert main(["synth", str(path), "-o", str(tmp_path / "a.exr"), "--resolution", "48"]) == 0
    assert "hist" in capsys.readouterr().out
    expected = synthesized_btf(material, scale=8.0).image(view=(0.0, 0.0), light=(30.0, 0.0), uv_rect=(0, 0, 1, 1),
                                                         resolution=48)
    np.testing.assert_allclose(load_image(tmp_path / "a.exr"), expected, rtol=1e-3, atol=1e-6)  # (EXR: half floats)
    assert main(["synth", str(path), "-o", str(tmp_path / "b.png"), "--resolution", "48", "--seed", "4"]) == 2
    err = capsys.readouterr().err.strip()
    assert "fixes method 'hist' and seed 3" in err and len(err.splitlines()) == 1
    assert main(["synth", str(path), "-o", str(tmp_path / "c.png"), "--resolution", "48", "--method", "tile"]) == 0
    assert main(["export", str(path), "-o", str(tmp_path / "web"), "--no-viewer"]) == 0
    manifest = json.loads((tmp_path / "web" / "manifest.json").read_text())
    assert manifest["default_method"] == "hist" and manifest["methods"]["hist"]["seed"] == 3
    pytest.importorskip("mitsuba")
    assert main(["render", str(path), "-o", str(tmp_path / "r.png"), "--size", "16", "--spp", "1", "--point"]) == 0
    assert "compiled material: method hist, seed 3" in capsys.readouterr().out
    assert main(["render", str(path), "-o", str(tmp_path / "r.png"), "--size", "16", "--method", "tile"]) == 2
    assert "fixes method 'hist' and seed 3" in capsys.readouterr().err
