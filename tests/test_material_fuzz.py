"""Compiled materials from strangers: crafted files with valid checksums never crash, hang, trace back, answer
NaN or answer with another model (dynbtf.material's checks and its one cache, whose entries include the tables
shared between seeds).

The seeded campaign runs in a child process (``tests/material_fuzz.py``): a crash or a hang there fails this test
with the case that caused it instead of killing the runner. Against the reader before these checks, the same
campaign crashed with SIGSEGV at its second case (a footprint decoder's bias emptied) and, on another seed, ended
40 of 200 cases in a traceback or NaN answers.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from dynbtf.material import FORMAT_VERSION, load_compiled, save_compiled
from dynbtf.errors import FormatError
from dynbtf.synthesized import synthesized_btf
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.material import open_or_compile

HERE = Path(__file__).resolve().parent
#: Crafted materials per run of the suite (the campaign behind the release notes ran more: ``DYNBTF_FUZZ_CASES``).
CASES = int(os.environ.get("DYNBTF_FUZZ_CASES", "300"))


def test_crafted_materials_end_in_a_one_line_error_or_finite_answers(tmp_path):
    env = {**os.environ, "DYNBTF_COMPILED_CACHE": "off", "PYTHONPATH": os.pathsep.join(
        [str(HERE.parent), os.environ.get("PYTHONPATH", "")])}
    try:
        run = subprocess.run([sys.executable, str(HERE / "material_fuzz.py"), str(CASES), "20261128", str(tmp_path)],
                             capture_output=True, text=True, timeout=900, env=env)
    except subprocess.TimeoutExpired:
        pytest.fail(f"hung at {(tmp_path / 'current.txt').read_text()}")
    current = tmp_path / "current.txt"
    assert run.returncode == 0, (f"the reader process ended with code {run.returncode} at "
                                 f"{current.read_text() if current.exists() else '?'}:\n{run.stderr[-3000:]}")
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["violations"] == []
    outcomes = result["outcomes"]
    assert sum(outcomes.values()) == CASES
    # the campaign is not vacuous: most crafted files are refused, and some (benign changes) are read
    assert outcomes.get("refused", 0) > CASES // 2 and outcomes.get("accepted, finite", 0) > 0, outcomes


@pytest.fixture(scope="module")
def models():
    return TriplePlane(32, 32, seed=0), TriplePlane(32, 32, seed=5)


def _uv_directions(n=64):
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * 50
    w = torch.nn.functional.normalize(torch.rand(n, 3, generator=g) + torch.tensor([0, 0, 1.0]), dim=-1)
    return uv, w


def test_another_models_entry_under_this_key_is_rebuilt_not_used(models, tmp_path, monkeypatch):
    """The cache holds B's material under A's key (checksums valid): A's query warns, compiles A and answers as A."""
    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path))
    a, b = models
    material_a, how = open_or_compile(a, "linear", 0, footprints=False, progress=False)
    assert how == "compiled"
    material_b, _ = open_or_compile(b, "linear", 0, footprints=False, progress=False)
    entry_a, entry_b = tmp_path / f"{material_a.key}.dbtfc", tmp_path / f"{material_b.key}.dbtfc"
    entry_a.write_bytes(entry_b.read_bytes())  # B's file, intact, under A's key
    uv, w = _uv_directions()
    with pytest.warns(UserWarning, match="another model"):
        again, how = open_or_compile(a, "linear", 0, footprints=False, progress=False)
    assert how == "compiled" and again.model_sha256 == material_a.model_sha256
    assert load_compiled(entry_a).model_sha256 == material_a.model_sha256  # the entry was replaced
    answer_a = synthesized_btf(entry_a, level_decoders=False).eval(uv, w, w)
    answer_b = synthesized_btf(entry_b, level_decoders=False).eval(uv, w, w)
    assert not torch.equal(answer_a, answer_b)
    np.testing.assert_array_equal(answer_a, synthesized_btf(material_a, level_decoders=False).eval(uv, w, w))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
def test_a_fifo_in_the_cache_is_never_opened(models, tmp_path, monkeypatch):
    """A FIFO where a cache entry belongs (a material's, or the tables every seed shares) would block every reader:
    it is skipped (warning) and replaced."""
    from dynbtf.material.cache import tables_key
    from dynbtf.material.compiler import model_digest

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path / "compiled"))
    a, _ = models
    material, _ = open_or_compile(a, "struct", 0, footprints=False, progress=False)
    entry = tmp_path / "compiled" / f"{material.key}.dbtfc"
    entry.unlink()
    os.mkfifo(entry)
    with pytest.warns(UserWarning, match="not a regular file"):
        again, how = open_or_compile(a, "struct", 0, footprints=False, progress=False)
    assert how == "compiled" and entry.is_file()
    entry.unlink()
    os.mkfifo(entry)
    with pytest.raises(FormatError, match="not a regular file"):
        load_compiled(entry)
    tables = tmp_path / "compiled" / f"{tables_key(model_digest(a), 'struct', {})}.dbtfc"
    assert tables.is_file()  # kept by the first compile
    tables.unlink()
    os.mkfifo(tables)
    with pytest.warns(UserWarning, match="not a regular file"):
        other, how = open_or_compile(a, "struct", 1, footprints=False, progress=False)
    assert how == "compiled" and other.seed == 1


def test_an_edited_tables_entry_with_a_valid_checksum_is_compiled_again(models, tmp_path, monkeypatch):
    """The tables every seed shares, edited and saved through the public API (so with a valid checksum: an offset
    past the exemplar, 100,000 offsets against cut tables for 16, cuts past their band): the next seed's material is
    compiled from scratch with a warning, and answers as a fresh compile does."""
    from dataclasses import replace

    from dynbtf.material.cache import tables_key
    from dynbtf.material.compiler import compile_material, model_digest

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path))
    a = models[0]
    sound, _ = open_or_compile(a, "struct", 0, footprints=False, progress=False)
    entry = tmp_path / f"{tables_key(model_digest(a), 'struct', {})}.dbtfc"
    kept = load_compiled(entry)
    fresh = compile_material(a, "struct", 5, footprints=False, progress=False)
    uv = np.random.default_rng(3).random((500, 2)) * 40.0
    w = np.tile([[0.0, 0.0, 1.0]], (500, 1))
    want = synthesized_btf(fresh, level_decoders=False).eval(uv, w, w)
    for seed, edit in enumerate(({"offsets": torch.full((3, 2), 10 ** 6, dtype=torch.int64)},
                                 {"offsets": torch.zeros((100000, 2), dtype=torch.int64)},
                                 {"vertical_cuts": torch.full_like(kept.synthesis["vertical_cuts"], 30000)}), start=5):
        save_compiled(replace(kept, synthesis={**kept.synthesis, **edit}), entry)
        with pytest.warns(UserWarning, match="compiling again"):
            material, how = open_or_compile(a, "struct", seed, footprints=False, progress=False)
        assert how == "compiled" and material.seed == seed
        assert torch.equal(load_compiled(entry).synthesis["offsets"], kept.synthesis["offsets"])  # replaced, sound
        if seed == 5:
            np.testing.assert_array_equal(synthesized_btf(material, level_decoders=False).eval(uv, w, w), want)
    assert sound.seed == 0


def test_another_seed_is_made_from_the_kept_tables_and_answers_as_a_fresh_compile(models, tmp_path, monkeypatch):
    """The tables of the first seed serve the next (nothing rebuilt): the material equals a compile from scratch,
    while quilt, whose texture is drawn with the seed, keeps no shared tables."""
    from dynbtf.material.cache import tables_key
    from dynbtf.material.compiler import compile_material, model_digest

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path))
    a = models[0]
    open_or_compile(a, "struct", 0, footprints=False, progress=False)
    built = []
    import dynbtf.synthesis.cell_quilting as cq

    original = cq.build_cell_tables
    monkeypatch.setattr(cq, "build_cell_tables", lambda *args, **kw: built.append(1) or original(*args, **kw))
    material, how = open_or_compile(a, "struct", 9, footprints=False, progress=False)
    assert how == "compiled" and not built  # the cut tables were not built again
    fresh = compile_material(a, "struct", 9, footprints=False, progress=False)
    assert built  # (a compile from scratch builds them)
    assert material.key == fresh.key and material.seed == 9
    for name, table in fresh.synthesis.items():
        if name != "build_seconds":
            assert torch.equal(material.synthesis[name], table), name
    uv = np.random.default_rng(4).random((500, 2)) * 40.0
    w = np.tile([[0.0, 0.0, 1.0]], (500, 1))
    np.testing.assert_array_equal(synthesized_btf(material, level_decoders=False).eval(uv, w, w),
                                  synthesized_btf(fresh, level_decoders=False).eval(uv, w, w))
    open_or_compile(a, "quilt", 0, footprints=False, progress=False, repeats=2)
    assert not (tmp_path / f"{tables_key(model_digest(a), 'quilt', {'repeats': 2})}.dbtfc").exists()


def test_header_fields_are_under_the_checksum(models, tmp_path):
    """Editing the method, seed or arguments in the header (tensors untouched) makes the file refused, not obeyed."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    from dynbtf.material import compile_material

    material = compile_material(models[0], "hist", 0, footprints=False, progress=False)
    path = save_compiled(material, tmp_path / "m.dbtfc")
    with safe_open(str(path), framework="pt") as f:
        header = json.loads(f.metadata()["dynbtf"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    assert header["format_version"] == FORMAT_VERSION
    for field, value in (("seed", 9), ("arguments", {"gamma": 1.0}), ("method", "linear")):
        edited = {**header, field: value}
        save_file(tensors, str(tmp_path / "e.dbtfc"), metadata={"dynbtf": json.dumps(edited)})
        with pytest.raises(FormatError, match="header fields do not match their checksum"):
            load_compiled(tmp_path / "e.dbtfc")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_compiled(path).seed == 0


@pytest.mark.parametrize("config", [{"height_scale": 1e6}, {"march_step_texels": 1e-9}])
def test_a_relief_whose_march_would_not_end_is_refused_when_read(tmp_path, config):
    """A relief's configuration within its own bounds (height scale up to 1e6 uv, march steps down to any positive
    size) can make every query march for seconds or forever: the model file and a compiled material of it are refused
    before they answer anything, in a fraction of a second."""
    import time

    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.parallax import ParallaxTriplePlane
    from dynbtf.material import compile_material

    sound = ParallaxTriplePlane(16, 16, seed=0)
    sound.set_height(0.01 * torch.rand(16, 16, generator=torch.Generator().manual_seed(0)))
    assert sound.state_problem() is None
    bad = ParallaxTriplePlane(16, 16, seed=0, **config)
    bad.load_state_dict(sound.state_dict())
    save_model(tmp_path / "bad.dbtfm", bad)
    material = compile_material(sound, "hist", 0, footprints=False, progress=False)
    material.model = bad
    save_compiled(material, tmp_path / "bad.dbtfc")
    for path in (tmp_path / "bad.dbtfm", tmp_path / "bad.dbtfc"):
        start = time.perf_counter()
        with pytest.raises(FormatError, match="march steps"):
            synthesized_btf(path, "hist") if path.suffix == ".dbtfm" else synthesized_btf(path)
        assert time.perf_counter() - start < 30
