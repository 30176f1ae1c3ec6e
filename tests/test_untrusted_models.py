"""Untrusted input: model files (.dbtfm) are checked before anything is allocated, and fail as one clear line.

Part of the issue "untrusted input never crashes, hangs or writes elsewhere". A model file is what people
share; its JSON config used to build the modules before the tensors were compared with it (a 300 KB file
asking for 57.6 GB, a million layers, a NaN slope, 1e30 weights accepted). Each test states the independent
expectation: the field or tensor the message must name, exit status 2 through the command line, and for
the fuzz test that every outcome is a clean error or a load giving the original tensors bit for bit.
"""

from __future__ import annotations

import json
import math
import random
import resource
import struct
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from dynbtf.cli.main import main
from dynbtf.errors import FormatError
from dynbtf.representations.model_file import (tensor_digest, load_model, read_model_metadata, save_model)
from dynbtf.representations.parallax import ParallaxTriplePlane
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.training.checkpoint import checkpoint_path

DATA = Path(__file__).parent / "data" / "round1_models"


@pytest.fixture
def model_path(tmp_path):
    model = TriplePlane(16, 16, positional_channels=4, angular_resolution=6, angular_channels=4, hidden=16, seed=2)
    return save_model(tmp_path / "m.dbtfm", model)


def edited(path: Path, out: Path, change_meta=None, change_tensors=None) -> Path:
    """A copy of model file ``path`` with its metadata / tensors edited and the checksum recomputed
    (a hand-made file: the checksum does not protect against a deliberate edit)."""
    meta, tensors = read_model_metadata(path), load_file(str(path))
    if change_tensors:
        change_tensors(tensors)
    meta["tensor_sha256"] = tensor_digest(tensors)
    if change_meta:
        change_meta(meta)
    save_file(tensors, str(out), metadata={"dynbtf": json.dumps(meta, allow_nan=True)})
    return out


def cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


# ---------------------------------------------------------------------------- the reported cases
@pytest.mark.parametrize("field, value, expected", [
    ("hidden", 200000, r"hidden: expected an integer in \[1, 4096\], got 200000"),
    ("layers", 1000000, r"layers: expected an integer in \[2, 64\], got 1000000"),
    ("negative_slope", float("nan"), r"negative_slope: expected a finite number in \[0.0, 1.0\], got nan"),
    ("height", "16", r"height: expected an integer in \[1, 65536\], got '16'"),
    ("seed", -1, r"seed: expected an integer in \[0, \d+\], got -1"),
    ("angular_channels", True, r"angular_channels: expected an integer in \[1, 4096\], got True"),
])
def test_config_fields_are_checked_before_anything_is_built(tmp_path, model_path, capsys, field, value, expected):
    bad = edited(model_path, tmp_path / "bad.dbtfm", change_meta=lambda m: m["config"].update({field: value}))
    before = peak_rss_mb()
    start = time.perf_counter()
    with pytest.raises(FormatError, match=expected) as error:
        load_model(bad)
    assert str(error.value).startswith(str(bad)), "the message starts with the file"
    assert time.perf_counter() - start < 2.0 and peak_rss_mb() - before < 100
    code, out, err = cli(capsys, "inspect", bad)
    assert code == 2 and out == "" and err.count("\n") == 1 and str(bad) in err and field in err


def test_a_config_asking_for_more_than_the_file_holds_allocates_nothing(tmp_path, model_path, capsys):
    """height = width = 30000 in a small file: 57.6 GB were allocated before; now the header says no."""
    bad = edited(model_path, tmp_path / "huge.dbtfm",
                 change_meta=lambda m: m["config"].update(height=30000, width=30000))
    assert bad.stat().st_size < 100_000
    before = peak_rss_mb()
    with pytest.raises(FormatError, match=r"tensor 'f_u' has shape \(16, 16, 4\); the model's config needs "
                                          r"\(30000, 30000, 4\)"):
        load_model(bad)
    assert peak_rss_mb() - before < 100
    assert cli(capsys, "inspect", bad)[0] == 2


def test_metadata_of_the_wrong_json_type_missing_or_unknown(tmp_path, model_path):
    cases = [
        (lambda m: m.update(kind=3), r"field 'kind' must be a string"),
        (lambda m: m.update(kind="bogus"), r"unknown representation 'bogus'"),
        (lambda m: m.update(config=[1, 2]), r"field 'config' must be a JSON object"),
        (lambda m: m.pop("config"), r"lacks the field 'config'"),
        (lambda m: m["config"].pop("width"), r"'config' lacks the field 'width' of a 'triple' model"),
        (lambda m: m["config"].update(colour="red"), r"'config' field 'colour' is not an argument of a 'triple'"),
        (lambda m: m.update(tensor_sha256=5), r"field 'tensor_sha256' must be a hex string"),
        (lambda m: m.update(format_version="1"), r"'format_version' must be an integer"),
    ]
    for k, (change, expected) in enumerate(cases):
        with pytest.raises(FormatError, match=expected):
            load_model(edited(model_path, tmp_path / f"c{k}.dbtfm", change_meta=change))


def test_absurd_but_finite_weights_are_refused_naming_the_tensor(tmp_path, model_path, capsys):
    def scale(factor):
        def change(t):
            t["decoder.rest.2.weight"] = t["decoder.rest.2.weight"] * factor
        return change

    huge = edited(model_path, tmp_path / "e30.dbtfm", change_tensors=scale(1e30))
    with pytest.raises(FormatError, match=r"tensor 'decoder.rest.2.weight' holds a value of magnitude [0-9.]+e\+29"):
        load_model(huge)
    # below the parameter bound but the answers are absurd: named through the decoded values
    loud = edited(model_path, tmp_path / "e7.dbtfm", change_tensors=scale(1e7))
    with pytest.raises(FormatError, match=r"answers values up to .* test queries .* largest tensor is "
                                          r"'decoder.rest.2.weight'"):
        load_model(loud)
    code, _, err = cli(capsys, "inspect", loud)
    assert code == 2 and "e7.dbtfm" in err
    # and a model answering within bounds still loads (the check is not a tautology)
    model, _ = load_model(edited(model_path, tmp_path / "ok.dbtfm", change_tensors=scale(2.0)))
    assert model.kind == "triple"


def test_a_larger_output_bound_is_a_load_option(tmp_path, model_path):
    loud = edited(model_path, tmp_path / "bright.dbtfm",
                  change_tensors=lambda t: t.update({"decoder.rest.2.bias": t["decoder.rest.2.bias"] + 3e4}))
    with pytest.raises(FormatError, match="answers values up to 3"):
        load_model(loud)
    model, _ = load_model(loud, max_output=1e5)
    assert float(model.decoder.rest[-1].bias.detach().min()) > 2.9e4


def test_truncated_non_safetensors_and_huge_header_claims(tmp_path, model_path, capsys):
    data = model_path.read_bytes()
    (tmp_path / "cut.dbtfm").write_bytes(data[: len(data) - 100])
    (tmp_path / "png.dbtfm").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    (tmp_path / "len.dbtfm").write_bytes(struct.pack("<Q", 2 ** 62) + data[8:])
    header_len = struct.unpack("<Q", data[:8])[0]
    header = json.loads(data[8:8 + header_len])
    header["f_u"]["shape"] = [100000, 100000, 4]  # claims 160 GB in the same bytes
    text = json.dumps(header).encode()
    (tmp_path / "claim.dbtfm").write_bytes(struct.pack("<Q", len(text)) + text + data[8 + header_len:])
    for name in ("cut", "png", "len", "claim"):
        path = tmp_path / f"{name}.dbtfm"
        with pytest.raises(FormatError) as error:
            load_model(path)
        assert str(error.value).startswith(str(path))
        code, out, err = cli(capsys, "inspect", path)
        assert code == 2 and err.startswith("dynbtf: error: ") and err.count("\n") == 1


def test_every_builtin_kind_still_loads_its_earlier_files():
    for kind in ("triple", "neumip", "pca", "sh"):
        model, meta = load_model(DATA / f"{kind}.dbtfm")
        assert model.kind == kind
        assert all(t.device.type == "cpu" for t in model.state_dict().values())


# ---------------------------------------------------------------------------- seeded fuzz
#: values that no config field accepts (wrong type, non-finite, negative, far beyond any bound)
INVALID_VALUES = [None, "16", [16], {"a": 1}, float("nan"), float("inf"), -float("inf"), -1, -10 ** 9, 10 ** 30,
                  2 ** 63, 1e308]
#: values some fields accept (a seed, a height scale): the file must either be refused or load with its own tensors
MAYBE_VALUES = [0, 1, 2, 3, 4, 5, 16, 0.5, 0.0, True, False, 0.01, 1e-9, 200000, 10 ** 6]


def _parallax_file(tmp_path) -> Path:
    model = ParallaxTriplePlane(8, 8, positional_channels=4, angular_resolution=6, angular_channels=4, hidden=16,
                                seed=1)
    model.set_height(0.01 * torch.rand(8, 8))
    return save_model(tmp_path / "parallax.dbtfm", model)


def _raw_parts(data: bytes) -> tuple[dict, bytes]:
    n = struct.unpack("<Q", data[:8])[0]
    return json.loads(data[8:8 + n]), data[8 + n:]


def _raw_file(header: dict, payload: bytes) -> bytes:
    text = json.dumps(header, allow_nan=True).encode()
    return struct.pack("<Q", len(text)) + text + payload


def _mutate(rng: random.Random, original: bytes) -> tuple[bytes, str, bool]:
    """One mutation of a model file's bytes: ``(bytes, description, must_fail)``."""
    header, payload = _raw_parts(original)
    meta = json.loads(header["__metadata__"]["dynbtf"])
    tensors = [k for k in header if k != "__metadata__"]
    kind = rng.randrange(9)
    must_fail = False
    if kind <= 2:  # a config value
        key = rng.choice(sorted(meta["config"]) + ["extra_field"])
        if rng.random() < 0.6:
            value, must_fail = rng.choice(INVALID_VALUES), True
        else:
            value = rng.choice(MAYBE_VALUES)
        meta["config"][key] = value
        must_fail = must_fail or key == "extra_field"
        what = f"config[{key!r}] = {value!r}"
    elif kind == 3:  # a config key removed
        key = rng.choice(sorted(meta["config"]))
        del meta["config"][key]
        what = f"config lacks {key!r}"
    elif kind == 4:  # a top-level metadata field
        key = rng.choice(["kind", "config", "format", "format_version", "tensor_sha256", "provenance"])
        value = rng.choice([None, 3, "x", [], {}, float("nan"), 10 ** 30, -1, "triple"])
        meta[key] = value
        what = f"meta[{key!r}] = {value!r}"
        if rng.random() < 0.1:  # JSON nested deeper than Python's recursion limit
            header["__metadata__"]["dynbtf"] = "[" * 100000 + "]" * 100000
            return _raw_file(header, payload), "metadata nested 100000 deep", True
    elif kind == 5:  # a tensor's declared shape or dtype
        name = rng.choice(tensors)
        before = dict(header[name])
        if rng.random() < 0.5:
            shape = list(header[name]["shape"])
            if shape:
                shape[rng.randrange(len(shape))] = rng.choice([0, 1, 3, 10 ** 5, 2 ** 40])
            header[name]["shape"] = shape
            what = f"{name} shape {shape}"
        else:
            header[name]["dtype"] = rng.choice(["F16", "F64", "I64", "U8", "BOOL", "X"])
            what = f"{name} dtype {header[name]['dtype']}"
        must_fail = header[name] != before  # sizes no longer match the offsets, or the dtype is not the model's
    elif kind == 6:  # offsets
        name = rng.choice(tensors)
        begin, end = header[name]["data_offsets"]
        header[name]["data_offsets"] = [begin, end + rng.choice([4, 2 ** 33, -4])]
        what, must_fail = f"{name} offsets", True
    elif kind == 7:  # raw bytes: a cut or flipped bits anywhere
        data = bytearray(original)
        if rng.random() < 0.5:
            cut = rng.randrange(len(data))
            return bytes(data[:cut]), f"cut at {cut}", True
        for _ in range(rng.randint(1, 4)):
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        return bytes(data), "bit flips", False  # a flip in JSON whitespace or a key's case may be harmless
    else:  # the header's length field
        value = rng.choice([0, 7, 2 ** 62, 2 ** 64 - 1, len(original)])
        return struct.pack("<Q", value) + original[8:], f"header length {value}", True
    header["__metadata__"]["dynbtf"] = json.dumps(meta, allow_nan=True)
    return _raw_file(header, payload), what, must_fail


CASES = 400


def test_fuzz_model_metadata_and_header(tmp_path, capsys):
    """CASES seeded mutations of five small model files, loaded through ``dynbtf inspect``.

    Expectation, independent of the loader: every outcome is exit status 0 or 2 (never another exception, a
    crash or a hang); a mutation that makes the file invalid (a config value of the wrong type, non-finite,
    negative or beyond any bound, an unknown field, a shape or dtype that disagrees with the bytes, a cut)
    exits with 2 and a one-line message naming the file; a file that loads gives the original's tensors bit
    for bit.
    """
    originals = [DATA / f"{k}.dbtfm" for k in ("triple", "neumip", "pca", "sh")] + [_parallax_file(tmp_path)]
    reference = {p: load_file(str(p)) for p in originals}
    rng = random.Random(20240917)
    outcomes = {"loaded": 0, "clean error": 0}
    before = peak_rss_mb()
    start = time.perf_counter()
    for case in range(CASES):
        source = rng.choice(originals)
        data, what, must_fail = _mutate(rng, source.read_bytes())
        path = tmp_path / f"case{case}.dbtfm"
        path.write_bytes(data)
        t0 = time.perf_counter()
        code, out, err = cli(capsys, "inspect", path)
        assert time.perf_counter() - t0 < 10.0, f"case {case} ({what}) took too long"
        assert code in (0, 2), f"case {case} ({what}): exit {code}, {err}"
        if code == 2:
            outcomes["clean error"] += 1
            assert err.startswith(f"dynbtf: error: {path}") and err.count("\n") == 1, (what, err)
        else:
            outcomes["loaded"] += 1
            assert not must_fail, f"case {case} ({what}) loaded but should have been refused"
            loaded, _ = load_model(path)
            for name, tensor in reference[source].items():
                assert torch.equal(loaded.state_dict()[name], tensor), (what, name)
        path.unlink()
    elapsed = time.perf_counter() - start
    growth = peak_rss_mb() - before
    print(f"\nfuzz: {CASES} cases, {outcomes['clean error']} clean errors, {outcomes['loaded']} loaded, 0 tracebacks, "
          f"{elapsed:.1f} s, peak RSS growth {growth:.0f} MB")
    assert outcomes["clean error"] > CASES // 2 and outcomes["loaded"] > 5  # the mutations reach both outcomes
    assert elapsed < 60 and growth < 300
    assert not list(tmp_path.glob("*.tmp*")) and sorted(p.name for p in tmp_path.iterdir()) == ["parallax.dbtfm"]


# ============================================================================ checkpoints
# A checkpoint that does not fit the run (tensors missing or of another shape, a position outside the schedule,
# non-finite values, another optimizer) is reported as damaged, naming its path and how to start over; the
# model file is not touched (an epoch of 1e9 used to end the run at once and write a model marked finished).

SMALL_GRID = dict(thetas=(0.0, 30.0, 60.0), counts=(1, 6, 8))  # 15 x 15 pairs


@pytest.fixture(scope="module")
def stored_btf(tmp_path_factory):
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic_btf import synthetic_btf

    from dynbtf.data import write_stored

    return write_stored(tmp_path_factory.mktemp("btf") / "small.dbtf", synthetic_btf(8, **SMALL_GRID), progress=False)


def fit_argv(btf, out, *extra) -> list[str]:
    return ["fit", str(btf), "-o", str(out), "--repr", "triple", "--epochs", "2", "--quiet", "--device", "cpu",
            "--workers", "1", *map(str, extra)]


def _damage_epoch(value):
    return lambda state: state.update(epoch=value)


def _damage_step(value):
    return lambda state: state.update(step=value)


def _reshape_f_u(state):
    state["model"]["f_u"] = torch.zeros(3, 3, 3)


def _drop_f_h(state):
    del state["model"]["f_h"]


def _nan_f_u(state):
    state["model"]["f_u"] = state["model"]["f_u"].clone()
    state["model"]["f_u"][0, 0, 0] = float("nan")


def _optimizer_of_another_model(state):
    moments = next(iter(state["optimizer"]["state"].values()))
    moments["exp_avg"] = torch.zeros(7)


@pytest.mark.parametrize("damage, expected", [
    (_reshape_f_u, r"model tensor 'f_u' is torch.float32 \(3, 3, 3\); the model needs torch.float32 \(8, 8, 16\)"),
    (_drop_f_h, r"model tensor 'f_h' is missing"),
    (_damage_epoch(-1), r"it is at epoch -1, outside this run's 0..2"),
    (_damage_epoch(10 ** 9), r"it is at epoch 1000000000, outside this run's 0..2"),
    (_damage_step(-3), r"it is at step -3 of epoch 0"),
    (_damage_step(10 ** 9), r"it is at step 1000000000 of epoch 0"),
    (_damage_epoch(1.5), r"epoch is 1.5, not an integer"),
    (_nan_f_u, r"model tensor 'f_u' holds non-finite values"),
    (_optimizer_of_another_model, r"its optimizer state does not fit this model"),
    (lambda state: state.update(history=[{}] * 5), r"its history lists 5 epoch\(s\) but its position is epoch 0"),
    (lambda state: state["config"].update(epochs="many"), r"its training options are not valid \(--epochs"),
])
def test_a_checkpoint_that_does_not_fit_the_run_is_damaged_never_a_traceback(tmp_path, stored_btf, capsys, damage,
                                                                             expected):
    out = tmp_path / "m.dbtfm"
    # a run stopped by its time budget after its first step: an unfinished model and its checkpoint
    assert cli(capsys, *fit_argv(stored_btf, out, "--max-minutes", "1e-9"))[0] == 0
    ckpt = checkpoint_path(out)
    assert ckpt.exists() and out.exists()
    state = torch.load(ckpt, weights_only=True)
    assert (state["epoch"], state["step"]) == (0, 1)
    damage(state)
    torch.save(state, ckpt)
    model_bytes, ckpt_bytes = out.read_bytes(), ckpt.read_bytes()
    code, output, err = cli(capsys, *fit_argv(stored_btf, out))
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"dynbtf: error: {ckpt}: damaged checkpoint: ")
    assert "delete it to start over" in err and f"rm '{ckpt}'" in err
    import re

    assert re.search(expected, err), err
    # nothing was written: the unfinished model and the checkpoint are as they were, no stray files
    assert out.read_bytes() == model_bytes and ckpt.read_bytes() == ckpt_bytes
    assert read_model_metadata(out)["provenance"]["finished"] is False
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.dbtfm", "m.dbtfm.ckpt"]
    # deleting it, as the message says, starts over and finishes
    ckpt.unlink()
    assert cli(capsys, *fit_argv(stored_btf, out))[0] == 0
    assert read_model_metadata(out)["provenance"]["finished"] is True and not ckpt.exists()


def test_an_intact_checkpoint_still_resumes(tmp_path, stored_btf, capsys):
    """The checks are not a tautology: the same steps with an untouched checkpoint continue and finish."""
    out = tmp_path / "m.dbtfm"
    assert cli(capsys, *fit_argv(stored_btf, out, "--max-minutes", "1e-9"))[0] == 0
    code, _, err = cli(capsys, *fit_argv(stored_btf, out))
    assert code == 0, err
    meta = read_model_metadata(out)
    assert meta["provenance"]["finished"] is True and meta["provenance"]["epochs_completed"] == 2


# ============================================================================ fit options
@pytest.mark.parametrize("option, value, expected", [
    ("--epochs", "0", "--epochs (TrainConfig.epochs): expected an integer in [1, 1000000], got 0"),
    ("--memory-mb", "inf", "--memory-mb (TrainConfig.memory_budget_mb): expected a finite number in (0, "),
    ("--memory-mb", "nan", "--memory-mb (TrainConfig.memory_budget_mb): expected a finite number"),
    ("--lr-decay", "0", "--lr-decay (TrainConfig.lr_decay): expected a finite number in (0, 1], got 0.0"),
    ("--lr-scale", "inf", "--lr-scale (TrainConfig.lr_scale): expected a finite number in (0, 1000000], got inf"),
    ("--held-out-fraction", "1", "--held-out-fraction (TrainConfig.held_out_fraction): expected a finite number "
                                 "in [0, 1), got 1.0"),
    ("--seed", "-1", "--seed (TrainConfig.seed): expected an integer in [0, "),
    ("--images-per-step", "0", "--images-per-step (TrainConfig.images_per_step)"),
    ("--texel-groups", "0", "--texel-groups (TrainConfig.texel_groups)"),
    ("--texels-per-image", "0", "--texels-per-image (TrainConfig.texels_per_image)"),
    ("--workers", "0", "--workers (TrainConfig.workers)"),
    ("--max-minutes", "-5", "--max-minutes (TrainConfig.max_minutes)"),
    ("--max-reflectance", "0", "--max-reflectance (TrainConfig.max_reflectance)"),
    ("--minutes", "inf", "--minutes: expected a positive, finite number of minutes, got inf"),
    ("--minutes", "0", "--minutes: expected a positive, finite number of minutes, got 0.0"),
    ("--stereo-max-height", "nan", "--stereo-max-height: expected a positive, finite height"),
])
def test_every_numeric_fit_option_is_checked_up_front(tmp_path, stored_btf, capsys, option, value, expected):
    out = tmp_path / "out" / "m.dbtfm"
    code, output, err = cli(capsys, *fit_argv(stored_btf, out, option, value))
    assert code == 2 and err.count("\n") == 1 and expected in err, err
    assert not (tmp_path / "out").exists()  # nothing written, not even the output's directory


# ============================================================================ BTFs that decode to garbage
def _dfmf_with_a_bright_image(tmp_path, pair) -> Path:
    """A float DFMF file whose image ``pair`` decodes to ~1e19: its U row scaled by 2^64 (what flipping one
    exponent bit of a float32 does), finite, so no NaN check catches it."""
    import sys

    import numpy as np

    sys.path.insert(0, str(Path(__file__).parent))
    from synthetic_btf import synthetic_btf

    from dynbtf.data import UBO2014BTF, write_ubo2014

    path = write_ubo2014(tmp_path / "bright.btf", synthetic_btf(8, **SMALL_GRID), components=4, scalar="float",
                         progress=False)
    with UBO2014BTF(path) as btf:
        channel, n_lights = btf.header.channels[0], btf.n_lights
    data = bytearray(path.read_bytes())
    at = channel.u_offset + (pair[0] * n_lights + pair[1]) * channel.components * 4
    row = np.frombuffer(bytes(data[at:at + 4 * channel.components]), "<f4") * np.float32(2.0 ** 64)
    data[at:at + 4 * channel.components] = row.astype("<f4").tobytes()
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("memory_mb", [None, "0.05"])  # cached images, and texels read straight from the file
def test_a_btf_decoding_to_absurd_values_stops_the_fit_naming_the_image(tmp_path, capsys, memory_mb):
    from dynbtf.training.images import held_out_split

    train, _ = held_out_split(15, 15, 0.05, 0)
    pair = tuple(int(x) for x in train[40])  # a training pair (the held-out ones are never trained on)
    btf = _dfmf_with_a_bright_image(tmp_path, pair)
    code, out, err = cli(capsys, "info", btf, "--images", "225")
    assert code == 0 and "values" in out
    assert err.startswith(f"dynbtf: warning: {btf}: sampled values reach 1.") and "e+19" in err
    if memory_mb is None:  # show refuses the image info warns about (one line), unless the limit is raised
        shown = tmp_path / "shown.exr"
        code, _, err = cli(capsys, "show", btf, "--view", str(pair[0]), "--light", str(pair[1]), "-o", shown)
        assert code == 2 and err.count("\n") == 1 and "beyond any plausible reflectance" in err and "e+19" in err
        assert not shown.exists()
        code, _, err = cli(capsys, "show", btf, "--view", str(pair[0]), "--light", str(pair[1]), "-o", shown,
                           "--max-reflectance", "1e30")
        assert code == 0 and shown.exists(), err
    out_dir = tmp_path / "fit"
    extra = ["--memory-mb", memory_mb, "--texel-groups", "4"] if memory_mb else []
    code, _, err = cli(capsys, *fit_argv(btf, out_dir / "m.dbtfm", *extra))
    assert code == 2 and err.count("\n") == 1, err
    assert f"{btf}: image (view {pair[0]}, light {pair[1]}) holds values up to 1." in err and "e+19" in err
    assert "--max-reflectance" in err
    assert not (out_dir / "m.dbtfm").exists()  # no model; a streamed fit keeps the checkpoint of its good steps
    assert sorted(p.name for p in out_dir.iterdir()) in ([], ["m.dbtfm.ckpt"]) if out_dir.exists() else True


def test_max_reflectance_lets_bright_data_through(tmp_path, capsys):
    btf = _dfmf_with_a_bright_image(tmp_path, (0, 1))
    streamed = ["--memory-mb", "0.05", "--texel-groups", "4"]
    code, _, err = cli(capsys, *fit_argv(btf, tmp_path / "m.dbtfm", "--epochs", "1", "--max-reflectance", "1e30",
                                         *streamed))
    assert code == 0, err
    assert read_model_metadata(tmp_path / "m.dbtfm")["provenance"]["finished"] is True
    # the float16 image cache cannot hold it: said so, with the way round
    code, _, err = cli(capsys, *fit_argv(btf, tmp_path / "c.dbtfm", "--epochs", "1", "--max-reflectance", "1e30"))
    assert code == 2 and "beyond the float16 image cache (65504)" in err and "--memory-mb" in err, err


def test_a_diverging_fit_stops_before_the_update_and_names_the_btf(tmp_path, stored_btf):
    from dynbtf.data import open_btf
    from dynbtf.training import TrainConfig, fit
    from dynbtf.training.fit import TrainingDiverged

    out = tmp_path / "m.dbtfm"
    losses = []
    with open_btf(stored_btf) as btf, pytest.raises(TrainingDiverged) as error:
        fit(TriplePlane(8, 8), btf, TrainConfig(epochs=50, lr_scale=1e6, device="cpu", workers=1, monitor_pairs=0),
            out, progress=False, callback=lambda info: losses.append(info["loss"]))
    message = str(error.value)
    assert message.startswith(f"{stored_btf}: the fit diverged at epoch ") and "--lr-scale" in message
    assert not out.exists()
    state = torch.load(checkpoint_path(out), weights_only=True)  # the last good state, finite
    assert all(bool(torch.isfinite(t).all()) for t in state["model"].values())
    assert state["epoch"] * 1000 + state["step"] >= 0 and losses and all(math.isfinite(x) for x in losses)


def test_an_unsupported_dfmf_version_is_named_as_such(tmp_path, capsys):
    btf = _dfmf_with_a_bright_image(tmp_path, (0, 1))
    data = bytearray(btf.read_bytes())
    data[13:17] = struct.pack("<I", 7)  # the common header's version field (after 9 magic bytes and the size)
    btf.write_bytes(bytes(data))
    code, _, err = cli(capsys, "info", btf)
    assert code == 2 and err == (f"dynbtf: error: {btf}: unsupported DFMF version 7: this reader supports versions "
                                 "1..4 (the common header's layout differs between versions)\n")


# ============================================================================ a file shortened while read
_TRUNCATE_WHILE_READING = r"""
import os, sys
import numpy as np
from dynbtf.data import UBO2014BTF
from dynbtf.errors import FormatError
path = sys.argv[1]
with UBO2014BTF(path, factor_cache_bytes=int(sys.argv[2])) as btf:
    first = btf.read_texels(np.array([[0, 0], [14, 14]]), np.arange(64))
    os.truncate(path, btf.header.channels[0].u_offset + 8)  # in place: the same inode, its factors now cut off
    try:
        btf.read_texels(np.array([[14, 14]]), np.arange(64))
    except FormatError as e:
        print("clean:", e)
"""


@pytest.mark.parametrize("cache", [0, 1 << 30])  # factors read from the file, or only U rows
def test_a_btf_truncated_between_reads_is_a_clear_error_not_sigbus(tmp_path, cache):
    import subprocess
    import sys

    btf = _dfmf_with_a_bright_image(tmp_path, (0, 1))
    size = btf.stat().st_size
    run = subprocess.run([sys.executable, "-c", _TRUNCATE_WHILE_READING, str(btf), str(cache)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, (run.returncode, run.stderr[-2000:])  # SIGBUS would be -7
    assert run.stdout.startswith(f"clean: {btf}: the file shrank from {size} to ")


_FIT_WHILE_TRUNCATED = r"""
import os, sys
from dynbtf.data import UBO2014BTF
from dynbtf.errors import DynBTFError
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.training import TrainConfig, fit
path, out = sys.argv[1], sys.argv[2]
def shorten(info):
    if info["global_step"] == 3:
        os.truncate(path, 4096)
with UBO2014BTF(path) as btf:
    config = TrainConfig(epochs=2, images_per_step=8, memory_budget_mb=0.05, texel_groups=4, workers=1,
                         monitor_pairs=0, device="cpu", max_reflectance=1e30)
    try:
        fit(TriplePlane(8, 8), btf, config, out, progress=False, callback=shorten)
    except DynBTFError as e:
        print("clean:", e)
"""


def test_a_fit_whose_btf_is_truncated_keeps_its_checkpoint(tmp_path):
    import subprocess
    import sys

    btf = _dfmf_with_a_bright_image(tmp_path, (0, 1))
    out = tmp_path / "m.dbtfm"
    run = subprocess.run([sys.executable, "-c", _FIT_WHILE_TRUNCATED, str(btf), str(out)], capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, (run.returncode, run.stderr[-2000:])
    assert run.stdout.startswith(f"clean: {btf}: the file shrank from ") and "checkpoint" in run.stdout
    state = torch.load(checkpoint_path(out), weights_only=True)
    assert state["epoch"] * 1000 + state["step"] >= 3  # the steps before the truncation are kept
    assert not out.exists()


def test_fit_options_are_the_train_config_fields(capsys):
    """One truth: every TrainConfig field marked as an option is a `dynbtf fit` flag with the field's help, and its
    range check (check_options) names that flag."""
    import re

    from dynbtf.training.fit import OPTION_RULES, command_line_options

    assert main(["fit", "--help"]) == 0
    text = re.sub(r"[\s│]+", " ", capsys.readouterr().out)
    options = command_line_options()
    assert {"epochs", "memory_budget_mb", "max_reflectance", "device"} <= set(options)
    assert set(options) <= set(OPTION_RULES)
    for name, (_, cli) in options.items():
        flag = cli.flag or "--" + name.replace("_", "-")
        assert f" {flag} " in text, flag
        assert " ".join(cli.help.split()[:6]) in text, name
