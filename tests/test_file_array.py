"""Arrays read from files with pread (dynbtf.data.file_array): equal to a NumPy memory map of the same bytes, and a
file truncated while it is open is a FormatError, never a SIGBUS."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from dynbtf.data import UBO2014BTF
from dynbtf.data.file_array import GATHER_GAP_BYTES, OpenFile
from dynbtf.errors import FormatError, InputError
from dfmf_reference import dfmf_bytes


@pytest.mark.parametrize("dtype", ["<f2", "<f4", "<f8"])
def test_slices_and_gathers_equal_a_memory_map(tmp_path, dtype):
    rng = np.random.default_rng(7)
    values = rng.standard_normal((5000, 7)).astype(dtype)
    path = tmp_path / "a.bin"
    path.write_bytes(b"x" * 13 + values.tobytes())
    reference = np.memmap(path, dtype=dtype, mode="r", offset=13, shape=values.shape)
    with OpenFile(path) as f:
        a = f.array(13, values.shape, dtype)
        assert len(a) == 5000 and a.size == values.size
        np.testing.assert_array_equal(np.asarray(a), reference)
        np.testing.assert_array_equal(np.asarray(a, dtype=np.float64), reference.astype(np.float64))
        for key in (slice(0, 1), slice(4990, None), slice(100, 50), slice(-3, None), 0, -1, 4321):
            np.testing.assert_array_equal(a[key], reference[key])
        # rows far apart (separate reads), close together (one read of the span), repeated, negative, 2-D
        far = np.array([4999, 0, 2500, 0, -1])
        near = rng.integers(1000, 1000 + min(3999, GATHER_GAP_BYTES // (7 * values.itemsize)), 300)
        mixed = rng.integers(0, 5000, (6, 40))
        for rows in (far, near, mixed, np.array([], np.int64)):
            np.testing.assert_array_equal(a[rows], reference[rows])
        with pytest.raises(IndexError, match="rows outside 0..4999"):
            a.take([5000])
        with pytest.raises(TypeError, match="integers"):
            a.take([0.5])


def test_a_file_shrunk_under_an_open_reader_is_a_format_error(tmp_path):
    path = tmp_path / "a.bin"
    np.arange(1000, dtype="<f4").tofile(path)
    f = OpenFile(path)
    a = f.array(0, (100, 10), "<f4")
    assert a[99][0] == 990.0
    os.truncate(path, 2000)  # 500 values left: rows 0..49
    assert a[49][9] == 499.0
    with pytest.raises(FormatError, match=r"a\.bin: the file shrank from 4000 to 2000 bytes while it was being read"):
        a[40:60]
    with pytest.raises(FormatError, match="shrank"):
        a.take([3, 99])
    f.close()
    with pytest.raises(InputError, match="a.bin: the file was closed"):
        a[0]
    with OpenFile(path) as f:  # opened short: the region past the end is a truncated file, not a shrunk one
        with pytest.raises(FormatError, match="truncated: 40 bytes at offset 3960 are needed but the file has 2000"):
            f.array(0, (100, 10), "<f4")[99]


def test_a_file_replaced_while_open_is_read_as_it_was(tmp_path):
    """Renaming another file over an open one (how atomic writers replace files) leaves the open one readable."""
    path = tmp_path / "a.bin"
    np.arange(10, dtype="<f4").tofile(path)
    with OpenFile(path) as f:
        other = tmp_path / "b.bin"
        np.zeros(2, dtype="<f4").tofile(other)
        os.replace(other, path)
        np.testing.assert_array_equal(np.asarray(f.array(0, (10,), "<f4")), np.arange(10, dtype="<f4"))


def test_a_ubo2014_file_truncated_while_threads_decode_it_fails_cleanly(tmp_path):
    """Readers in two threads decode images while the file is truncated under them: each one ends with the
    FormatError or a correct image, and the process lives (a memory map here would have died of SIGBUS)."""
    rng = np.random.default_rng(1)
    w = h = 32
    u = [rng.random((4, 3)) for _ in range(3)]
    sxv = [rng.random((w * h, 3)) for _ in range(3)]
    angles = [(0.0, 0.0), (0.3, 1.0)]
    path = tmp_path / "t.btf"
    path.write_bytes(dfmf_bytes(angles, angles, w, h, u, sxv, scalar_size=4))
    btf = UBO2014BTF(path, factor_cache_bytes=0)  # nothing cached: every image reads the file
    expected = btf.image(1, 1)
    outcomes = []

    def decode():
        for _ in range(200):
            try:
                np.testing.assert_array_equal(btf.image(1, 1), expected)
                outcomes.append("image")
            except FormatError as e:
                assert "the file shrank from" in str(e) and str(path) in str(e)
                outcomes.append("error")
                return

    threads = [threading.Thread(target=decode) for _ in range(2)]
    for t in threads:
        t.start()
    os.truncate(path, 4096)
    for t in threads:
        t.join()
    assert outcomes.count("error") == 2
    btf.close()


def test_a_stored_btf_shrunk_under_its_reader_is_a_format_error(tmp_path):
    from dynbtf.data import ArrayBTF
    from dynbtf.data.stored import StoredBTF, write_stored

    values = np.random.default_rng(0).random((2, 2, 4, 5, 3)).astype(np.float32)
    src = ArrayBTF(values, [[0, 0, 1.0], [0.6, 0, 0.8]], [[0, 0, 1.0], [0, 0.6, 0.8]])
    path = write_stored(tmp_path / "s.dbtf", src, progress=False)
    btf = StoredBTF(path)
    np.testing.assert_allclose(btf.image(1, 1), values[1, 1], rtol=1e-3)  # float16 on disk
    data = next(p for p in path.iterdir() if p.suffix == ".bin")
    os.truncate(data, data.stat().st_size // 2)
    np.testing.assert_allclose(btf.image(0, 1), values[0, 1], rtol=1e-3)  # the first half is still there
    with pytest.raises(FormatError, match="the file shrank from"):
        btf.image(1, 1)
    with pytest.raises(FormatError, match="the file shrank from"):
        btf.view_images(1)
    btf.close()
