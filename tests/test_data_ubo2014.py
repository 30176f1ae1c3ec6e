"""UBO2014 DFMF reader/writer: round trips, an independent brute-force decoder,
btf-extractor's conventions (and the package itself when installed), and fuzzing."""

from __future__ import annotations

import os
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from dfmf_reference import dfmf_bytes, reference_decode
from dynbtf.conventions import direction_to_spherical
from dynbtf.data import ArrayBTF, UBO2014BTF, btf_extractor_angles, open_btf, write_ubo2014
from dynbtf.data.directions import ubo2003_directions, ubo2014_directions
from dynbtf.data.file_array import FileArray
from dynbtf.errors import FormatError, InputError

REPO = Path(__file__).resolve().parents[1]


def small_source(n_views=3, n_lights=4, height=5, width=6, seed=0, low_rank=None) -> ArrayBTF:
    """A small random BTF on UBO2014 directions (values in [0, 1])."""
    rng = np.random.default_rng(seed)
    dirs, _ = ubo2014_directions()
    views = dirs[rng.choice(len(dirs), n_views, replace=False)]
    lights = dirs[rng.choice(len(dirs), n_lights, replace=False)]
    if low_rank is None:
        values = rng.random((n_views, n_lights, height, width, 3))
    else:  # exactly rank low_rank per channel
        a = rng.random((n_views * n_lights, low_rank, 3))
        b = rng.random((low_rank, height * width, 3)) / low_rank
        values = np.einsum("rkc,ktc->rtc", a, b).reshape(n_views, n_lights, height, width, 3)
    return ArrayBTF(values, views, lights, name="small")


@pytest.mark.parametrize("scalar, tol", [("half", 3e-3), ("float", 2e-6), ("double", 1e-12)])
@pytest.mark.parametrize("colour_model", [0, 11])
def test_round_trip_full_rank(tmp_path, scalar, tol, colour_model):
    src = small_source()
    path = write_ubo2014(tmp_path / "a.btf", src, components=100, scalar=scalar, colour_model=colour_model)
    with UBO2014BTF(path) as btf:
        assert btf.shape == src.shape
        np.testing.assert_allclose(btf.views, src.views, atol=1e-6)
        np.testing.assert_allclose(btf.lights, src.lights, atol=1e-6)
        tol = max(tol, 2e-6) if colour_model == 11 else tol  # the log-YUV model decodes in float32
        for v, l in src.pairs():
            np.testing.assert_allclose(btf.image(v, l), src.image(v, l), atol=tol * (3 if colour_model else 1))
        assert btf.metadata["colour_model"] == colour_model
        assert btf.metadata["scalar_bytes"] == {"half": 2, "float": 4, "double": 8}[scalar]


def test_truncation_is_exact_for_low_rank_and_monotone(tmp_path):
    exact = small_source(4, 4, 6, 7, low_rank=2)
    path = write_ubo2014(tmp_path / "r2.btf", exact, components=2, scalar="double")
    with UBO2014BTF(path) as btf:
        err = max(np.abs(btf.image(v, l) - exact.image(v, l)).max() for v, l in exact.pairs())
    assert err < 1e-6
    src = small_source(4, 4, 6, 7)
    errors = []
    for k in (1, 4, 12):  # 16 rows: rank <= 16
        path = write_ubo2014(tmp_path / f"k{k}.btf", src, components=k, scalar="double")
        with UBO2014BTF(path) as btf:
            errors.append(sum(float(((btf.image(v, l) - src.image(v, l)) ** 2).sum()) for v, l in src.pairs()))
    assert errors[0] > errors[1] > errors[2] > 0


@pytest.mark.parametrize("scalar_size", [2, 4, 8])
@pytest.mark.parametrize("colour_model", [0, 11])
def test_reader_matches_brute_force_reference(tmp_path, scalar_size, colour_model):
    """Hand-built files with every header option, decoded by the struct-based reference."""
    rng = np.random.default_rng(scalar_size + colour_model)
    w, h, c = 4, 3, 5
    views = [(0.0, 0.0), (0.6, 1.0), (1.2, 4.0)]
    lights = [(0.3, 0.5), (1.0, 6.0)]
    u = [rng.standard_normal((6, c)) * 0.3 for _ in range(3)]
    sxv = [rng.standard_normal((w * h, c)) * 0.3 for _ in range(3)]
    if colour_model == 11:
        u[0] = np.abs(u[0]) * -1  # log Y <= 0
    for version, rotations, cosine in ((1, None, 0), (2, None, 1), (3, [np.eye(3)], 0), (4, [np.eye(3)] * 2, 1)):
        data = dfmf_bytes(views, lights, w, h, u, sxv, scalar_size=scalar_size, colour_model=colour_model,
                          version=version, rotations=rotations, cosine_flag=cosine, xml=b"<x/>")
        path = tmp_path / f"v{version}.btf"
        path.write_bytes(data)
        with UBO2014BTF(path) as btf:
            assert (btf.height, btf.width, btf.n_views, btf.n_lights) == (h, w, 3, 2)
            assert btf.header.version == version and btf.header.cosine_flag == cosine
            assert btf.header.rotations_included == (rotations is not None)
            for v in range(3):
                for l in range(2):
                    ref, ref_views, ref_lights = reference_decode(path, v, l)
                    tol = 1e-12 if scalar_size == 8 and colour_model == 0 else 2e-5
                    np.testing.assert_allclose(btf.image(v, l), ref, atol=tol, rtol=1e-5)
            theta, phi = direction_to_spherical(btf.views)
            np.testing.assert_allclose(np.radians(theta), [a[0] for a in ref_views], atol=1e-6)
            np.testing.assert_allclose(np.radians(phi), [a[1] % (2 * np.pi) for a in ref_views], atol=1e-6)
            # all lights of a view at once equal the single-image decodes
            np.testing.assert_allclose(btf.view_images(1), np.stack([btf.image(1, 0), btf.image(1, 1)]), atol=1e-6)


def test_btf_extractor_conventions(tmp_path):
    """The documented relation: our RGB image == btf-extractor's BGR image[..., ::-1], same vertical orientation,
    i.e. our row i is file texel row H - 1 - i; angle tuples are (theta_l, phi_l, theta_v, phi_v) degrees."""
    rng = np.random.default_rng(3)
    w, h = 3, 4
    sxv = [np.eye(w * h) for _ in range(3)]  # SxV = identity: U's row holds the file's texels directly
    u = [rng.standard_normal((4, w * h)) for _ in range(3)]
    path = tmp_path / "id.btf"
    path.write_bytes(dfmf_bytes([(0.0, 0.0), (np.radians(30), np.radians(90))], [(np.radians(45), np.radians(300)),
                                (0.2, 0.1)], w, h, u, sxv, scalar_size=8))
    with UBO2014BTF(path) as btf:
        img = btf.image(1, 0)  # row = 1 * 2 + 0
        file_texels = np.stack([u[c][2] for c in range(3)], axis=-1).reshape(h, w, 3)  # file row-major, R G B
        np.testing.assert_allclose(img, file_texels[::-1], atol=1e-6)
        tl, pl, tv, pv = btf_extractor_angles(btf, 1, 0)
        assert (round(tl, 1), round(pl, 1), round(tv, 1), round(pv, 1)) == (45.0, 300.0, 30.0, 90.0)


def test_real_size_file_is_read_on_demand_not_materialized(tmp_path):
    """A 400 x 400 texel, 151 x 151 direction file (44 GB as float32) with one component per channel."""
    dirs, deg = ubo2014_directions()
    angles = np.radians(deg)
    rows, cols = 151 * 151, 400 * 400
    u = [np.full((rows, 1), 0.5 + 0.1 * c) for c in range(3)]
    sxv = [np.linspace(0, 1, cols).reshape(cols, 1) for _ in range(3)]
    path = tmp_path / "big.btf"
    path.write_bytes(dfmf_bytes(angles, angles, 400, 400, u, sxv, scalar_size=2))
    with UBO2014BTF(path) as btf:
        assert btf.shape == (151, 151, 400, 400) and btf.nbytes_float32 > 40e9
        np.testing.assert_allclose(btf.views, dirs, atol=1e-6)
        assert all(isinstance(m, FileArray) for m in btf._sxv + btf._u)
        img = btf.image(150, 77)
        assert img.shape == (400, 400, 3)
        ramp = np.linspace(0, 1, cols).astype(np.float16).astype(np.float32).reshape(400, 400)[::-1]
        np.testing.assert_allclose(img[..., 1], np.float32(np.float16(0.6)) * ramp, rtol=1e-6, atol=1e-7)


def test_writer_argument_errors(tmp_path):
    src = small_source()
    with pytest.raises(InputError, match="scalar"):
        write_ubo2014(tmp_path / "x.btf", src, scalar="quad")
    with pytest.raises(InputError, match="colour_model"):
        write_ubo2014(tmp_path / "x.btf", src, colour_model=3)
    with pytest.raises(InputError, match="views= and lights="):
        write_ubo2014(tmp_path / "x.btf", np.zeros((1, 1, 2, 2, 3)))
    with pytest.raises(InputError, match="max_bytes"):
        write_ubo2014(tmp_path / "x.btf", src, max_bytes=100, method="exact")
    with pytest.raises(InputError, match="method"):
        write_ubo2014(tmp_path / "x.btf", src, method="lanczos")
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_randomized_writer_recovers_a_low_rank_btf_exactly(tmp_path):
    """A BTF of exact rank 3 per channel (sums of angular x spatial products): the streamed randomized SVD
    (two passes, oversampled) recovers it to float precision, like the exact SVD."""
    rng = np.random.default_rng(4)
    views, lights = ubo2003_directions()[0][:5], ubo2003_directions()[0][10:16]
    angular = rng.random((3, 5 * 6, 3))     # (component, pair, channel)
    spatial = rng.random((3, 6 * 7, 3))     # (component, texel, channel)
    values = np.einsum("kpc,ktc->ptc", angular, spatial).reshape(5, 6, 6, 7, 3)
    src = ArrayBTF(values, views, lights)
    path = write_ubo2014(tmp_path / "r.btf", src, components=3, scalar="double", method="randomized")
    with UBO2014BTF(path) as btf:
        assert btf.metadata["components"] == [3, 3, 3]
        for v, l in [(0, 0), (4, 5), (2, 3)]:
            np.testing.assert_allclose(btf.image(v, l), values[v, l], atol=1e-6)
    # more components than the rank: still exact; a bad rank request is clipped to the matrix
    path = write_ubo2014(tmp_path / "r8.btf", src, components=50, scalar="double", method="randomized", seed=3)
    with UBO2014BTF(path) as btf:
        np.testing.assert_allclose(btf.image(3, 1), values[3, 1], atol=1e-6)


def test_writer_accepts_arrays_and_is_atomic(tmp_path):
    src = small_source(2, 2, 3, 3)
    path = write_ubo2014(tmp_path / "arr.btf", src.values, views=src.views, lights=src.lights, scalar="float",
                         components=50)
    with open_btf(path) as btf:
        np.testing.assert_allclose(btf.image(1, 1), src.values[1, 1], atol=1e-5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arr.btf"]


# ------------------------------------------------------------------ errors and fuzzing
def valid_file(tmp_path) -> bytes:
    path = write_ubo2014(tmp_path / "valid.btf", small_source(2, 3, 3, 4), components=3, scalar="float",
                         version=4)
    return path.read_bytes()


def _opens(path, **options) -> None:
    """Open and decode every image; FormatError is the only acceptable failure."""
    with UBO2014BTF(path, **options) as btf:
        for v in range(btf.n_views):
            assert np.isfinite(btf.view_images(v)).all()


@pytest.mark.parametrize("mutate, message", [
    (lambda b: b"PK" + b[2:], "bad magic"),
    (lambda b: b"!FMF12FCE" + b[9:], "unsupported BTF variant 'FMF1'"),
    (lambda b: b[:-10], "truncated"),
    (lambda b: b + b"\0" * 7, "unexpected bytes"),
    (lambda b: b[:9], "truncated: common header"),
    (lambda b: b"", "empty file"),
])
def test_corrupt_files_name_the_problem(tmp_path, mutate, message):
    data = valid_file(tmp_path)
    path = tmp_path / "bad.btf"
    path.write_bytes(mutate(data))
    with pytest.raises(FormatError, match=message) as e:
        _opens(path)
    assert str(e.value).startswith(str(path))


def _offsets(data: bytes) -> dict:
    """Byte offsets of a few fields of a file written by write_ubo2014(version=4)."""
    pos = 9
    size = struct.unpack_from("<I", data, pos)[0]
    pos += size
    n_views = struct.unpack_from("<I", data, pos)[0]
    views_at = pos
    pos += 4
    n_lights = struct.unpack_from("<I", data, pos + 8)[0]
    view_record = 12 + 8 * n_lights
    wh = pos + n_views * view_record
    colour = wh + 8
    channel0 = colour + 8 + 48
    return {"size": 9, "version": 13, "n_views": views_at, "theta_v0": views_at + 4, "n_lights_v1":
            views_at + 4 + view_record + 8, "light0_theta": views_at + 16, "width": wh, "colour_model": colour + 4,
            "scalar": channel0, "components": channel0 + 1, "rows": channel0 + 5, "cols": channel0 + 9,
            "payload": channel0 + 13}


@pytest.mark.parametrize("field, value, message", [
    ("size", struct.pack("<I", 999), "header size field"),
    ("n_views", struct.pack("<I", 0), "view count is 0"),
    ("n_views", struct.pack("<I", 0xFFFFFFFF), "view count"),
    ("n_lights_v1", struct.pack("<I", 2), "sizes disagree"),
    ("width", struct.pack("<I", 5), "column count of channel 0"),
    ("colour_model", struct.pack("<I", 7), "unsupported colour model 7"),
    ("scalar", bytes([3]), "scalar size of channel 0 is 3"),
    ("components", struct.pack("<I", 0), "component count of channel 0 is 0"),
    ("components", struct.pack("<I", 10**6), "bytes remain"),
    ("rows", struct.pack("<I", 7), "row count of channel 0"),
    ("theta_v0", struct.pack("<f", np.radians(95.0)), "below the horizon"),
    ("light0_theta", struct.pack("<f", -0.5), "upper hemisphere"),
    ("theta_v0", struct.pack("<f", np.nan), "NaN"),
])
def test_inconsistent_fields(tmp_path, field, value, message):
    data = bytearray(valid_file(tmp_path))
    at = _offsets(bytes(data))[field]
    data[at:at + len(value)] = value
    path = tmp_path / "bad.btf"
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match=message):
        _opens(path)


@pytest.mark.parametrize("poison", [np.nan, np.inf, -np.inf])
def test_non_finite_payload(tmp_path, poison):
    data = bytearray(valid_file(tmp_path))
    at = _offsets(bytes(data))["payload"] + 3 * 4 + 4 * 5  # inside channel 0's U
    data[at:at + 4] = struct.pack("<f", poison)
    path = tmp_path / "nan.btf"
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="NaN or infinite"):
        UBO2014BTF(path)
    # without the scan on opening, the decoded image is checked
    with UBO2014BTF(path, check_payload=False) as btf, pytest.raises(FormatError, match="not finite"):
        for v, l in btf.pairs():
            btf.image(v, l)


def test_missing_or_directory(tmp_path):
    with pytest.raises(FormatError, match="not found"):
        UBO2014BTF(tmp_path / "missing.btf")
    with pytest.raises(FormatError, match="not a file"):
        UBO2014BTF(tmp_path)


def test_fuzz_mutated_files_raise_only_format_error(tmp_path):
    """Truncations at random offsets, random byte flips (header-heavy), corrupted counts, NaN payloads."""
    data = valid_file(tmp_path)
    offsets = _offsets(data)
    rng = np.random.default_rng(2024)
    header_end = offsets["payload"]
    mutants = []
    for cut in np.concatenate([np.arange(0, header_end, 3), rng.integers(0, len(data), 60)]):
        mutants.append(data[:int(cut)])
    for _ in range(300):
        b = bytearray(data)
        for _ in range(int(rng.integers(1, 4))):
            at = int(rng.integers(0, header_end if rng.random() < 0.8 else len(b)))
            b[at] = int(rng.integers(0, 256))
        mutants.append(bytes(b))
    for field in ("size", "version", "n_views", "n_lights_v1", "width", "components", "rows", "cols"):
        for value in (0, 1, 2, 3, 255, 65535, 2**31 - 1, 2**32 - 1):
            b = bytearray(data)
            b[offsets[field]:offsets[field] + 4] = struct.pack("<I", value)
            mutants.append(bytes(b))
    for _ in range(40):
        b = bytearray(data)
        at = int(rng.integers(header_end, len(b) - 4))
        b[at:at + 4] = struct.pack("<f", [np.nan, np.inf, -np.inf, 3e38][int(rng.integers(0, 4))])
        mutants.append(bytes(b))
    outcomes = {"ok": 0, "format_error": 0}
    path = tmp_path / "mutant.btf"
    for k, m in enumerate(mutants):
        path.write_bytes(m)
        try:  # every other mutant skips the NaN scan at open: decoding must still catch everything
            _opens(path, check_payload=k % 2 == 0, factor_cache_bytes=(k // 2) % 2 << 30)
            outcomes["ok"] += 1
        except FormatError as e:
            assert str(e).startswith(str(path)), e
            outcomes["format_error"] += 1
        except Exception as e:  # pragma: no cover - the failure this test exists to catch
            pytest.fail(f"mutant {k} raised {type(e).__name__}: {e}")
    assert outcomes["format_error"] > len(mutants) // 2
    assert outcomes["ok"] > 0  # payload byte flips are still valid files


# ------------------------------------------------------------------ btf-extractor itself (optional)
def _btf_extractor_python() -> str | None:
    candidates = [os.environ.get("DYNBTF_BTFX_PYTHON"), str(REPO / ".venv-btfx" / "bin" / "python")]
    for c in candidates:
        if c and Path(c).is_file():
            return c
    return None


_BTFX_SCRIPT = r"""
import json, sys
import numpy as np
from btf_extractor import Ubo2014
btf = Ubo2014(sys.argv[1])
out = {}
keys = sorted(btf.angles_vs_index_dict.items(), key=lambda kv: kv[1])
angles = np.array([k for k, _ in keys], dtype=np.float64)
index = np.array([i for _, i in keys], dtype=np.int64)  # (light, view)
images = np.stack([btf.angles_to_image(*k) for k, _ in keys])
np.savez(sys.argv[2], angles=angles, index=index, images=images, shape=np.array(btf.img_shape))
"""


@pytest.mark.skipif(_btf_extractor_python() is None,
                    reason="btf-extractor not installed (bash scripts/install_btf_extractor.sh creates .venv-btfx; "
                           "or set DYNBTF_BTFX_PYTHON to a python that can import btf_extractor)")
@pytest.mark.parametrize("scalar, colour_model", [("half", 0), ("float", 11), ("double", 0)])
def test_against_btf_extractor(tmp_path, scalar, colour_model):
    """Write with our writer, read with btf-extractor in its own venv, compare images and angles."""
    dirs, _ = ubo2003_directions()
    rng = np.random.default_rng(11)
    sel_v, sel_l = rng.choice(81, 4, replace=False), rng.choice(81, 4, replace=False)
    values = rng.random((4, 4, 5, 7, 3))  # non-square: 5 rows, 7 columns
    src = ArrayBTF(values, dirs[sel_v], dirs[sel_l])
    path = write_ubo2014(tmp_path / "x.btf", src, components=8, scalar=scalar, colour_model=colour_model)
    out = tmp_path / "btfx.npz"
    subprocess.run([_btf_extractor_python(), "-c", _BTFX_SCRIPT, str(path), str(out)], check=True, timeout=120,
                   capture_output=True)
    ref = np.load(out)
    with UBO2014BTF(path) as btf:
        assert ref["images"].shape[1:] == (btf.height, btf.width, 3)
        for angles, (l, v), image in zip(ref["angles"], ref["index"], ref["images"]):
            ours = btf.image(v, l)
            np.testing.assert_allclose(image[..., ::-1], ours, atol=2e-6, rtol=1e-5)
            np.testing.assert_allclose(angles, np.round(btf_extractor_angles(btf, v, l), 1), atol=0.051)


@pytest.mark.skipif(_btf_extractor_python() is None, reason="btf-extractor not installed")
def test_simulated_full_grid_dfmf_file_against_btf_extractor(tmp_path):
    """`dynbtf simulate --grid ubo2014 -o x.btf` (the full-size benchmark file's writer, here at 8 x 8 texels):
    a true DFMF file that btf-extractor reads as we do, and close to the simulated BTF it compresses."""
    from typer.testing import CliRunner

    from dynbtf.cli.main import app

    path = tmp_path / "sim.btf"
    result = CliRunner().invoke(app, ["simulate", "leather", "--grid", "ubo2014", "--size", "8", "--components",
                                      "24", "-o", str(path), "--quiet"])
    assert result.exit_code == 0, result.output
    out = tmp_path / "btfx.npz"
    subprocess.run([_btf_extractor_python(), "-c", _BTFX_SCRIPT, str(path), str(out)], check=True, timeout=300,
                   capture_output=True)
    ref = np.load(out)
    sim = open_btf("sim:leather?size=8&grid=ubo2014")
    with UBO2014BTF(path) as btf:
        assert (btf.n_views, btf.n_lights, btf.height, btf.width) == (151, 151, 8, 8)
        assert len(ref["images"]) == 151 * 151
        rng = np.random.default_rng(0)
        for k in rng.choice(len(ref["images"]), 40, replace=False):
            l, v = ref["index"][k]
            ours = btf.image(v, l)
            np.testing.assert_allclose(ref["images"][k][..., ::-1], ours, atol=2e-3, rtol=2e-3)  # half factors
        # rank 24 of a 22,801 x 64 matrix: a close approximation of the simulated material
        pairs = np.stack([rng.integers(0, 151, 64), rng.integers(0, 151, 64)], 1)
        approx = btf.read_texels(pairs, np.arange(64))
        exact = np.stack([sim.image(v, l).reshape(-1, 3) for v, l in pairs])
        assert np.abs(approx - exact).mean() < 0.05 * np.abs(exact).mean()


def test_streamed_factors_equal_cached_factors(tmp_path, monkeypatch):
    """Without the float32 SxV cache, decoding converts the factors chunk by chunk: same images."""
    import dynbtf.data.ubo2014 as ubo2014

    src = small_source(3, 4, 9, 10)
    path = write_ubo2014(tmp_path / "s.btf", src, components=5, scalar="half")
    cached = UBO2014BTF(path)
    monkeypatch.setattr(ubo2014, "_CHUNK_BYTES", 5 * 4 * 7)  # 7 texels per chunk: many chunks
    streamed = UBO2014BTF(path, factor_cache_bytes=0)
    for v, l in src.pairs():
        np.testing.assert_allclose(streamed.image(v, l), cached.image(v, l), rtol=1e-6, atol=1e-7)
    assert cached._sxv_cached is not None and streamed._sxv_cached is None


@pytest.mark.parametrize("shape", [(530, 620), (620, 530)])
def test_gram_path_of_the_truncated_svd_equals_lapack(shape):
    """Matrices above 512 on both sides use the Gram eigen-decomposition: compare with a full SVD."""
    from dynbtf.data.ubo2014 import _truncated_svd

    rng = np.random.default_rng(5)
    m = rng.standard_normal((shape[0], 6)) @ rng.standard_normal((6, shape[1])) + 0.01 * rng.standard_normal(shape)
    u, s, sxv = _truncated_svd(m, 8)
    u_ref, s_ref, vt_ref = np.linalg.svd(m, full_matrices=False)
    np.testing.assert_allclose(s, s_ref[:8], rtol=1e-9)
    best = (u_ref[:, :8] * s_ref[:8]) @ vt_ref[:8]
    np.testing.assert_allclose(u @ sxv.T, best, atol=1e-9)
    np.testing.assert_allclose(u.T @ u, np.eye(8), atol=1e-9)


def test_writer_reports_bad_directions_as_input_errors(tmp_path):
    with pytest.raises(InputError, match="below the horizon"):
        write_ubo2014(tmp_path / "x.btf", np.zeros((1, 1, 2, 2, 3)), views=[[0, 0.6, -0.8]], lights=[[0, 0, 1.0]])
