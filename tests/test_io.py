"""Atomic writes and image files (dynbtf.io)."""

import os
import stat

import numpy as np
import pytest

from dynbtf.errors import FormatError, InputError
from dynbtf.io import atomic_path, linear_to_srgb, load_image, save_image, srgb_to_linear


def test_atomic_path_leaves_old_content_and_no_temp_file_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half-written")
            raise RuntimeError("interrupted")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_path_gives_umask_mode(tmp_path):
    umask = os.umask(0o022)
    try:
        with atomic_path(tmp_path / "a.bin") as tmp:
            tmp.write_bytes(b"x")
    finally:
        os.umask(umask)
    assert stat.S_IMODE(os.stat(tmp_path / "a.bin").st_mode) == 0o644


def test_srgb_transfer_matches_the_standard_and_inverts():
    # IEC 61966-2-1 reference points: 0.0031308 -> 0.04045, 0.5 -> 0.735357, 1 -> 1
    np.testing.assert_allclose(linear_to_srgb([0.0031308, 0.5, 1.0]), [0.04045, 0.735357, 1.0], atol=2e-6)
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-6)


def test_exr_round_trip_is_exact_and_png_is_8_bit_srgb(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.random((7, 9, 3)) * 3).astype(np.float32)
    save_image(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(load_image(tmp_path / "a.exr"), img)
    save_image(tmp_path / "a.png", img)
    back = load_image(tmp_path / "a.png")
    clipped = np.clip(img, 0, 1)
    # one 8-bit step of the sRGB encoding, expressed in linear units
    assert np.all(np.abs(linear_to_srgb(back) - linear_to_srgb(clipped)) <= 0.5 / 255 + 1e-6)


def test_image_errors_name_the_problem(tmp_path):
    with pytest.raises(InputError, match="unsupported image extension"):
        save_image(tmp_path / "a.bmp", np.zeros((2, 2, 3)))
    with pytest.raises(InputError, match=r"\(H, W, 3\)"):
        save_image(tmp_path / "a.png", np.zeros((2, 2, 2, 3)))
    with pytest.raises(FormatError, match="file not found"):
        load_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(FormatError, match="bad.png"):
        load_image(tmp_path / "bad.png")


def test_check_image_path_is_the_rule_save_image_applies(tmp_path):
    from dynbtf.io import IMAGE_EXTENSIONS, check_image_path

    for ext in IMAGE_EXTENSIONS:
        assert check_image_path(tmp_path / f"a{ext.upper()}") == ext
        save_image(tmp_path / f"a{ext}", np.full((2, 2, 3), 0.5))  # every accepted extension is written
    for bad in ("a.tiff", "a", "a.png.txt"):
        with pytest.raises(InputError, match=r"unsupported image extension .*expected \.png, \.jpg or \.exr"):
            check_image_path(tmp_path / bad)
    assert not (tmp_path / "a.tiff").exists()


def test_a_painted_image_read_again_unchanged_is_not_decoded_again(tmp_path, monkeypatch):
    """``render --target`` checks the image, then the plugin reads it: one decode. A changed file is read anew, and the
    caller's copy is its own."""
    import dynbtf.io as io

    path = tmp_path / "target.png"
    levels = np.array([[0, 128, 255]], dtype=np.float64) / 255.0
    save_image(path, srgb_to_linear(np.repeat(levels[..., None], 3, axis=-1)).astype(np.float32))
    decoded = []
    monkeypatch.setattr(io, "load_image", lambda p: decoded.append(p) or load_image(p))
    first = io.load_painted_image(path, "--target")
    np.testing.assert_array_equal(first, levels)  # the stored grey levels over 255
    first[:] = 7.0  # the caller's copy
    np.testing.assert_array_equal(io.load_painted_image(str(path), "--target"), levels)
    assert len(decoded) == 1
    save_image(path, np.zeros((1, 3, 3), dtype=np.float32))
    os.utime(path, ns=(os.stat(path).st_atime_ns, os.stat(path).st_mtime_ns + 10 ** 9))  # a later modification
    np.testing.assert_array_equal(io.load_painted_image(path, "--target"), np.zeros((1, 3)))
    assert len(decoded) == 2
    bad = tmp_path / "bad.exr"
    save_image(bad, np.full((2, 2, 3), 2.0, dtype=np.float32))
    for _ in range(2):  # an image that fails its check is not kept: the error comes each time
        with pytest.raises(InputError, match="--target .*bad.exr: expected grey values in"):
            io.load_painted_image(bad, "--target")
