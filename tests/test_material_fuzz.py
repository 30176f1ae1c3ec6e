"""Compiled materials from strangers: crafted files with valid checksums never crash, hang, trace back, answer
NaN or answer with another model (dynbtf.material's checks, the caches of dynbtf.material
and dynbtf.synthesis.table_cache).

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
def test_a_fifo_in_the_caches_is_never_opened(models, tmp_path, monkeypatch):
    """A FIFO where a cache entry belongs would block every reader: it is skipped (warning) and replaced."""
    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path / "compiled"))
    monkeypatch.setenv("DYNBTF_SYNTHESIS_CACHE", str(tmp_path / "synthesis"))
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
    from dynbtf.synthesis.cell_quilting import cached_cell_tables

    for old in (tmp_path / "synthesis").glob("*.npz"):
        old.unlink()
    assert cached_cell_tables(a.positional_plane().detach()).source == "stored"
    tables = next((tmp_path / "synthesis").glob("struct-*.npz"))
    tables.unlink()
    os.mkfifo(tables)
    with pytest.warns(UserWarning, match="not a regular file"):
        rebuilt = cached_cell_tables(a.positional_plane().detach())
    assert rebuilt.source == "rebuilt" and tables.is_file()


def test_an_edited_table_cache_entry_with_a_recomputed_checksum_is_rebuilt(models, tmp_path, monkeypatch):
    """struct's cut tables edited (an offset past the exemplar, 100,000 offsets against cut tables for 16) and the
    public checksum recomputed: the entry is rebuilt with a warning, the query answers from sound tables."""
    from dynbtf.synthesis import table_cache
    from dynbtf.synthesis.cell_quilting import cached_cell_tables

    monkeypatch.setenv("DYNBTF_SYNTHESIS_CACHE", str(tmp_path))
    plane = models[0].positional_plane().detach()
    sound = cached_cell_tables(plane)
    entry = next(tmp_path.glob("struct-*.npz"))
    for edit in ({"offsets": np.full((3, 2), 10 ** 6, dtype=np.int64)},
                 {"offsets": np.zeros((100000, 2), dtype=np.int64)},
                 {"vertical_cuts": np.full_like(sound.vertical_cuts.numpy(), 30000)},
                 {"cells": np.array([3, 1], dtype=np.int64)}):
        arrays = {**sound.to_arrays(), **edit}
        with open(entry, "wb") as f:
            np.savez(f, checksum=np.array(table_cache._checksum(arrays)), **arrays)
        with pytest.warns(UserWarning, match="damaged"):
            tables = cached_cell_tables(plane)
        assert tables.source == "rebuilt"
        assert torch.equal(tables.offsets, sound.offsets) and torch.equal(tables.vertical_cuts, sound.vertical_cuts)


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
