"""UBO2003 zip reader/writer: round trips (PNG exact after 8-bit sRGB quantization, JPEG within
tolerance), naming and grid conventions, and every error case."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from PIL import Image

from dynbtf.conventions import direction_to_spherical
from dynbtf.data import ArrayBTF, UBO2003BTF, open_btf, write_ubo2003
from dynbtf.data.directions import ubo2003_directions, ubo2014_directions
from dynbtf.errors import FormatError, InputError
from dynbtf.io import srgb_to_linear, to_uint8_srgb


def small_source(seed=0, n_views=3, n_lights=4, size=(6, 5)) -> ArrayBTF:
    rng = np.random.default_rng(seed)
    dirs, _ = ubo2003_directions()
    views = dirs[np.sort(rng.choice(81, n_views, replace=False))]
    lights = dirs[np.sort(rng.choice(81, n_lights, replace=False))]
    # smooth images (JPEG-friendly) plus a texel-level pattern
    yy, xx = np.mgrid[0:size[0], 0:size[1]] / max(size)
    base = np.stack([0.2 + 0.5 * xx, 0.3 + 0.4 * yy, 0.25 + 0.2 * xx * yy], axis=-1)
    values = base * rng.uniform(0.5, 1.0, (n_views, n_lights, 1, 1, 3))
    return ArrayBTF(values, views, lights, name="small")


def test_png_round_trip_is_exact_up_to_8bit_srgb(tmp_path):
    src = small_source()
    path = write_ubo2003(tmp_path / "a.zip", src, image_format="png")
    with UBO2003BTF(path) as btf:
        assert btf.shape == src.shape
        # views/lights come back sorted by (theta, phi): find each source direction
        for v in range(src.n_views):
            for l in range(src.n_lights):
                vv, ll = btf.nearest_view(src.views[v]), btf.nearest_light(src.lights[l])
                np.testing.assert_allclose(btf.views[vv], src.views[v], atol=1e-12)
                np.testing.assert_allclose(btf.lights[ll], src.lights[l], atol=1e-12)
                expected = srgb_to_linear(to_uint8_srgb(src.image(v, l)) / 255.0)
                np.testing.assert_array_equal(btf.image(vv, ll), expected)


def test_jpeg_round_trip_within_tolerance(tmp_path):
    src = small_source(1)
    path = write_ubo2003(tmp_path / "a.zip", src, quality=95)
    with open_btf(path) as btf:
        assert type(btf) is UBO2003BTF
        for v, l in src.pairs():
            got = btf.image(btf.nearest_view(src.views[v]), btf.nearest_light(src.lights[l]))
            assert np.abs(got - src.image(v, l)).max() < 0.03
            assert got.dtype == np.float32


def test_names_and_order_follow_the_database(tmp_path):
    src = small_source(2)
    path = write_ubo2003(tmp_path / "a.zip", src, image_format="png")
    with zipfile.ZipFile(path) as zf:
        names = sorted(zf.namelist())
    theta_v, phi_v = direction_to_spherical(src.views[0])
    theta_l, phi_l = direction_to_spherical(src.lights[0])
    first = f"tl{round(float(theta_l)):03d} pl{round(float(phi_l)):03d} tv{round(float(theta_v)):03d} " \
            f"pv{round(float(phi_v)):03d}.png"
    assert first in names and len(names) == src.n_pairs
    with UBO2003BTF(path) as btf:
        theta, phi = direction_to_spherical(btf.views)
        assert list(zip(theta.round(6), phi.round(6))) == sorted(zip(theta.round(6), phi.round(6)))
        # image row 0 is the top row of the file
        name = btf.entry_names()[0]
        with zipfile.ZipFile(path) as zf:
            top = np.asarray(Image.open(io.BytesIO(zf.read(name))))[0]
        np.testing.assert_allclose(btf.image(0, 0)[0], srgb_to_linear(top / 255.0), atol=1e-7)


def _zip_of(path, entries: dict[str, np.ndarray | bytes]):
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in entries.items():
            if isinstance(data, np.ndarray):
                buf = io.BytesIO()
                Image.fromarray(data).save(buf, format="PNG")
                data = buf.getvalue()
            zf.writestr(name, data)
    return path


GREY = np.full((4, 4, 3), 128, np.uint8)


def test_folders_and_hidden_entries_are_ignored(tmp_path):
    path = _zip_of(tmp_path / "a.zip", {"wool/tl000 pl000 tv000 pv000.png": GREY, "wool/": b"",
                                        "__MACOSX/wool/._tl000 pl000 tv000 pv000.png": b"junk", ".DS_Store": b"x"})
    with UBO2003BTF(path) as btf:
        assert btf.shape == (1, 1, 4, 4)


@pytest.mark.parametrize("entries, message", [
    ({"tl000 pl000 tv000 pv000.png": GREY, "readme.txt": b"hello"}, "malformed entry name 'readme.txt'"),
    ({"tl0 pl000 tv000 pv000.png": GREY}, "malformed entry name"),
    ({"tl000 pl000 tv095 pv000.png": GREY}, "below the horizon"),
    ({"tl000 pl360 tv000 pv000.png": GREY}, "phi = 360"),
    ({"tl000 pl000 tv000 pv000.png": GREY, "tl015 pl000 tv000 pv000.png": GREY,
      "tl000 pl000 tv015 pv090.png": GREY}, r"1 images missing: 2 views x 2 lights .* 'tl015 pl000 tv015 pv090"),
    ({"a/tl000 pl000 tv000 pv000.png": GREY, "b/tl000 pl000 tv000 pv000.png": GREY}, "same angles"),
    ({"tl000 pl000 tv000 pv000.png": GREY, "tl015 pl000 tv000 pv000.png": np.zeros((5, 4, 3), np.uint8)},
     "all images must have the same size"),
    ({"tl000 pl000 tv000 pv000.jpg": b"not a jpeg"}, "not a readable image"),
    ({}, "contains no images"),
])
def test_malformed_zips(tmp_path, entries, message):
    path = _zip_of(tmp_path / "bad.zip", entries)
    with pytest.raises(FormatError, match=message) as e:
        UBO2003BTF(path)
    assert str(e.value).startswith(str(path))


def test_not_a_zip_and_missing(tmp_path):
    bad = tmp_path / "x.zip"
    bad.write_bytes(b"this is not a zip file")
    with pytest.raises(FormatError, match="not a zip file"):
        UBO2003BTF(bad)
    with pytest.raises(FormatError, match="not found"):
        UBO2003BTF(tmp_path / "missing.zip")


def test_truncated_image_data_is_a_format_error(tmp_path):
    buf = io.BytesIO()
    Image.fromarray(np.full((16, 16, 3), 90, np.uint8)).save(buf, format="JPEG")
    path = _zip_of(tmp_path / "t.zip", {"tl000 pl000 tv000 pv000.jpg": buf.getvalue()[:200]})
    with pytest.raises(FormatError, match="tl000 pl000 tv000 pv000.jpg"):
        with UBO2003BTF(path) as btf:
            btf.image(0, 0)


def test_writer_rejects_non_integer_angles_and_bad_options(tmp_path):
    dirs, _ = ubo2014_directions()  # has theta = 23.5 deg
    src = ArrayBTF(np.zeros((1, 13, 2, 2, 3)), dirs[:1], dirs[7:20])
    with pytest.raises(InputError, match="integer"):
        write_ubo2003(tmp_path / "x.zip", src)
    with pytest.raises(InputError, match="image_format"):
        write_ubo2003(tmp_path / "x.zip", small_source(), image_format="gif")
    with pytest.raises(InputError, match="quality"):
        write_ubo2003(tmp_path / "x.zip", small_source(), quality=0)
    assert not list(tmp_path.iterdir())


def test_fuzz_damaged_zips_raise_only_format_error(tmp_path):
    """Truncated zips and random byte flips (names, headers, deflate streams, JPEG/PNG data)."""
    rng = np.random.default_rng(7)
    src = small_source(3, 2, 2, (8, 8))
    bases = [write_ubo2003(tmp_path / "j.zip", src).read_bytes(),
             write_ubo2003(tmp_path / "p.zip", src, image_format="png").read_bytes()]
    path = tmp_path / "mutant.zip"
    outcomes = {"ok": 0, "format_error": 0}
    for k in range(300):
        b = bytearray(bases[k % 2])
        if k % 3 == 0:
            b = b[:int(rng.integers(0, len(b)))]
        else:
            for _ in range(int(rng.integers(1, 6))):
                b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
        path.write_bytes(bytes(b))
        try:
            with UBO2003BTF(path) as btf:
                for v, l in btf.pairs():
                    assert np.isfinite(btf.image(v, l)).all()
            outcomes["ok"] += 1
        except FormatError as e:
            assert str(e).startswith(str(path))
            outcomes["format_error"] += 1
        except Exception as e:  # pragma: no cover - the failure this test exists to catch
            pytest.fail(f"mutant {k} raised {type(e).__name__}: {e}")
    assert outcomes["format_error"] > 100 and outcomes["ok"] > 0


def test_an_entry_declaring_far_more_than_an_image_is_refused_before_reading(tmp_path):
    """A small zip can declare a huge entry (2 MiB of zeros deflate to ~2 KB): refused from the declared
    size, instead of read whole into memory."""
    buf = io.BytesIO()
    Image.fromarray(np.full((4, 4, 3), 90, np.uint8)).save(buf, format="PNG")
    path = tmp_path / "bomb.zip"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("tl000 pl000 tv000 pv000.png", buf.getvalue())
        z.writestr("tl015 pl000 tv000 pv000.png", buf.getvalue() + bytes(2 ** 21))  # valid header, huge tail
    assert path.stat().st_size < 20_000
    with pytest.raises(FormatError, match=r"entry 'tl015 pl000 tv000 pv000.png' declares 2,097,\d+ bytes, far "
                                          r"more than an image of 4x4 pixels needs"):
        UBO2003BTF(path)
