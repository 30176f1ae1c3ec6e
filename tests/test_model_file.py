"""Model files: bit-exact round trips, metadata, and clear errors for damaged or newer files."""

import json

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from dynbtf.errors import FormatError
from dynbtf.representations.model_file import (FORMAT_VERSION, load_model, model_size_report,
                                               read_model_metadata, save_model)
from dynbtf.representations.triple_plane import TriplePlane


@pytest.fixture
def model():
    m = TriplePlane(6, 5, angular_resolution=10, seed=3)
    with torch.no_grad():  # values that are not the initialization
        for p in m.parameters():
            p.add_(torch.linspace(-1, 1, p.numel()).reshape(p.shape))
    return m


def test_round_trip_is_bit_exact(tmp_path, model):
    path = save_model(tmp_path / "m.dbtfm", model, {"seed": 3, "held_out_pairs": np.array([[1, 2], [3, 4]]),
                                                    "psnr": np.float32(31.5)})
    loaded, meta = load_model(path)
    assert type(loaded) is TriplePlane and loaded.config() == model.config()
    for (name, a), b in zip(model.state_dict().items(), loaded.state_dict().values()):
        assert a.dtype == b.dtype and torch.equal(a, b), name
    assert meta["kind"] == "triple" and meta["format_version"] == FORMAT_VERSION
    assert meta["provenance"] == {"seed": 3, "held_out_pairs": [[1, 2], [3, 4]], "psnr": 31.5}
    assert "cos(theta_light)" in meta["conventions"]["values"]
    uv = torch.rand(4, 2)
    w = torch.nn.functional.normalize(torch.rand(4, 3) + torch.tensor([0, 0, 1.0]), dim=-1)
    assert torch.equal(model(uv, w, w), loaded(uv, w, w))
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write left no temporary file


def test_truncated_file_fails_clearly(tmp_path, model):
    path = save_model(tmp_path / "m.dbtfm", model)
    data = path.read_bytes()
    for cut in (4, len(data) // 2, len(data) - 10):
        bad = tmp_path / f"cut{cut}.dbtfm"
        bad.write_bytes(data[:cut])
        with pytest.raises(FormatError, match=str(bad.name)):
            load_model(bad)


def test_damaged_tensor_data_is_detected(tmp_path, model):
    path = save_model(tmp_path / "m.dbtfm", model)
    data = bytearray(path.read_bytes())
    data[-7] ^= 0x40
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="damaged"):
        load_model(path)


def write_raw(path, meta):
    save_file({"x": torch.zeros(2)}, str(path), metadata={"dynbtf": json.dumps(meta)} if meta is not None else None)


def test_newer_version_and_foreign_files_fail_clearly(tmp_path, model):
    newer = tmp_path / "newer.dbtfm"
    write_raw(newer, {"format": "dynbtf-model", "format_version": FORMAT_VERSION + 1, "kind": "triple", "config": {}})
    with pytest.raises(FormatError, match="newer"):
        load_model(newer)
    foreign = tmp_path / "foreign.safetensors"
    write_raw(foreign, None)
    with pytest.raises(FormatError, match="not a dynbtf model"):
        read_model_metadata(foreign)
    other = tmp_path / "other.dbtfm"
    write_raw(other, {"format": "something-else", "format_version": 1})
    with pytest.raises(FormatError, match="format"):
        load_model(other)
    unknown = tmp_path / "unknown.dbtfm"
    write_raw(unknown, {"format": "dynbtf-model", "format_version": 1, "kind": "nope", "config": {}})
    with pytest.raises(FormatError, match="unknown representation"):
        load_model(unknown)
    text = tmp_path / "text.dbtfm"
    text.write_text("hello, I am not a model")
    with pytest.raises(FormatError, match="text.dbtfm"):
        load_model(text)
    with pytest.raises(FormatError, match="not found"):
        load_model(tmp_path / "missing.dbtfm")


def _rewrite(tmp_path, path, change_meta=None, change_tensors=None):
    """A copy of a model file with its metadata and tensors edited and the checksum recomputed
    (what a hand-edited file or a buggy writer produces)."""
    from safetensors.torch import load_file

    from dynbtf.representations.model_file import tensor_digest

    meta = read_model_metadata(path)
    tensors = load_file(str(path))
    if change_meta:
        change_meta(meta)
    if change_tensors:
        change_tensors(tensors)
    meta["tensor_sha256"] = tensor_digest(tensors)
    out = tmp_path / "edited.dbtfm"
    save_file(tensors, str(out), metadata={"dynbtf": json.dumps(meta)})
    return out


def test_tensors_not_matching_config_fail_naming_the_tensor(tmp_path, model):
    path = save_model(tmp_path / "m.dbtfm", model)
    lie = _rewrite(tmp_path, path, change_meta=lambda m: m["config"].update(positional_channels=8))
    with pytest.raises(FormatError, match=r"tensor 'f_u' has shape \(6, 5, 16\); the model's config needs "
                                          r"\(6, 5, 8\)"):
        load_model(lie)


def test_missing_extra_and_non_finite_tensors_are_named(tmp_path, model):
    path = save_model(tmp_path / "m.dbtfm", model)
    with pytest.raises(FormatError, match="tensor 'f_h' of the 'triple' model is missing"):
        load_model(_rewrite(tmp_path, path, change_tensors=lambda t: t.pop("f_h")))
    with pytest.raises(FormatError, match="tensor 'bonus' is not part of a 'triple' model"):
        load_model(_rewrite(tmp_path, path, change_tensors=lambda t: t.update(bonus=torch.zeros(2))))

    def poison(t):
        t["f_u"] = t["f_u"].clone()
        t["f_u"][0, 0, 0] = float("inf")

    with pytest.raises(FormatError, match=r"tensor 'f_u' holds 1 non-finite value\(s\)"):
        load_model(_rewrite(tmp_path, path, change_tensors=poison))
    with pytest.raises(FormatError, match="does not describe a 'triple' model"):
        load_model(_rewrite(tmp_path, path, change_meta=lambda m: m["config"].update(no_such_option=1)))


def test_size_report_counts_parameters():
    m = TriplePlane(400, 400)
    report = model_size_report(m, raw_btf_bytes=400 * 400 * 151 * 151 * 3 * 4)
    expected_params = 400 * 400 * 16 + 2 * 20 * 20 * 8 + (32 * 32 + 32) * 3 + 32 * 3 + 3
    assert report["n_parameters"] == expected_params
    assert report["model_bytes"] == 4 * expected_params  # ~10 MB, the paper's "10 MB"
    assert report["compression_ratio"] == pytest.approx(400 * 400 * 151 * 151 * 12 / (4 * expected_params))
    assert "10.3 MB" in report["summary"] and "43.8 GB" in report["summary"]


@pytest.mark.parametrize("kind", ["triple", "neumip", "pca", "sh"])
def test_model_files_of_an_earlier_version_load_and_give_their_values(kind):
    """Files written by dynbtf before the architecture rework (commit 3d18bab, tests/data/round1_models)
    load unchanged and evaluate to the values that version recorded."""
    from pathlib import Path

    data = Path(__file__).parent / "data" / "round1_models"
    record = json.loads((data / "values.json").read_text())
    rep, meta = load_model(data / f"{kind}.dbtfm")
    assert rep.kind == kind
    with torch.no_grad():
        values = rep(torch.tensor(record["uv"], dtype=torch.float64), torch.tensor(record["w_view"]).float(),
                     torch.tensor(record["w_light"]).float())
    np.testing.assert_allclose(values.double().numpy(), np.array(record["values"][kind]), rtol=1e-5, atol=1e-6)  # float32: the sums' order depends on the CPU's kernels


def test_a_btf_given_as_a_model_says_so(tmp_path):
    from dynbtf.data import ArrayBTF, write_stored
    from dynbtf.data.directions import ubo2003_directions

    dirs = ubo2003_directions()[0][:2]
    btf = ArrayBTF(np.full((2, 2, 4, 4, 3), 0.5, np.float32), dirs, dirs)
    stored = write_stored(tmp_path / "leather.dbtf", btf, progress=False)
    with pytest.raises(FormatError, match=r"leather\.dbtf: is a BTF \(stored\), not a model file"):
        load_model(stored)
    (tmp_path / "notes.dbtfm").write_text("hello")
    with pytest.raises(FormatError, match="not a readable dynbtf model file"):
        load_model(tmp_path / "notes.dbtfm")
    with pytest.raises(FormatError, match="model file not found"):
        load_model(tmp_path / "absent.dbtfm")
