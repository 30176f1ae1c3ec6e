"""Stored BTF format: round trips, metadata, streaming, atomic + resumable writes, and validation errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dynbtf.conventions import direction_to_spherical
from dynbtf.data import ArrayBTF, BTFSource, StoredBTF, open_btf, write_stored
from dynbtf.data.directions import ubo2003_directions
from dynbtf.data.file_array import FileArray
from dynbtf.data.stored import DATA_FILE, META_FILE, STORED_FORMAT, STORED_VERSION
from dynbtf.errors import FormatError, InputError


def small_source(seed=0, n_views=3, n_lights=5, h=4, w=6, scale=1.0) -> ArrayBTF:
    rng = np.random.default_rng(seed)
    dirs, _ = ubo2003_directions()
    return ArrayBTF(rng.random((n_views, n_lights, h, w, 3)) * scale, dirs[:n_views], dirs[10:10 + n_lights],
                    name=f"small{seed}", metadata={"origin": "test", "seed": seed})


class CountingSource(BTFSource):
    """Wraps a source, counting image reads (and offering no view_images, so reads are per image)."""

    def __init__(self, inner: BTFSource):
        super().__init__()
        self.inner = inner
        self.height, self.width, self.views, self.lights = inner.height, inner.width, inner.views, inner.lights
        self.name, self.metadata = inner.name, dict(inner.metadata)
        self.reads: list[tuple[int, int]] = []

    def _read_image(self, v, l):
        self.reads.append((v, l))
        return self.inner.image(v, l)


@pytest.mark.parametrize("dtype, tol", [("float32", 0.0), ("float16", 1e-3)])
def test_round_trip_and_metadata(tmp_path, dtype, tol):
    src = small_source()
    path = write_stored(tmp_path / "a.dbtf", src, dtype=dtype, progress=False)
    btf = StoredBTF(path)
    assert btf.shape == src.shape and btf.name == src.name
    np.testing.assert_array_equal(btf.views, src.views)
    np.testing.assert_array_equal(btf.lights, src.lights)
    for v, l in src.pairs():
        np.testing.assert_allclose(btf.image(v, l), src.image(v, l), rtol=tol, atol=tol * 1e-2)
        assert btf.image(v, l).dtype == np.float32
    np.testing.assert_array_equal(btf.view_images(2, [4, 0]), np.stack([btf.image(2, 4), btf.image(2, 0)]))
    meta = json.loads((path / META_FILE).read_text())
    assert meta["format"] == STORED_FORMAT and meta["version"] == STORED_VERSION and meta["dtype"] == dtype
    theta, phi = direction_to_spherical(np.array(meta["views"]))
    np.testing.assert_allclose(np.array(meta["views_deg"]), np.stack([theta, phi], 1), atol=1e-8)
    assert "excluding cos(theta_light)" in meta["values"] and "linear RGB" in meta["values"]
    assert meta["provenance"]["origin"] == "test" and meta["provenance"]["source_kind"] == "ArrayBTF"
    assert (path / DATA_FILE).stat().st_size == src.n_pairs * 4 * 6 * 3 * np.dtype(dtype).itemsize
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.dbtf"]  # no temporary left over
    assert isinstance(btf._values, FileArray)  # read on demand, never loaded whole


def test_streams_each_image_once_in_view_major_order(tmp_path):
    src = CountingSource(small_source())
    write_stored(tmp_path / "a.dbtf", src, progress=False, lights_per_batch=2)
    assert src.reads == list(small_source().pairs())


def test_interrupted_write_resumes_where_it_stopped(tmp_path):
    target = tmp_path / "r.dbtf"

    class Interrupt(Exception):
        pass

    def stop_after_six(done):
        if done >= 6:
            raise Interrupt

    first = CountingSource(small_source())
    with pytest.raises(Interrupt):
        write_stored(target, first, dtype="float32", progress=False, lights_per_batch=3, callback=stop_after_six)
    assert not target.exists()
    partial = tmp_path / ".r.dbtf.partial"
    # batches never straddle views (5 lights in batches of 3 and 2): the marker says 3 + 2 + 3 images
    assert json.loads((partial / "progress.json").read_text())["images_done"] == 8
    assert first.reads == list(small_source().pairs())[:8]
    second = CountingSource(small_source())
    write_stored(target, second, dtype="float32", progress=False, lights_per_batch=3)
    assert second.reads == list(small_source().pairs())[8:]  # only the remaining images
    assert not partial.exists()
    src, btf = small_source(), StoredBTF(target)
    for v, l in src.pairs():
        np.testing.assert_array_equal(btf.image(v, l), src.image(v, l).astype(np.float32))


def test_partial_directory_of_another_source_is_discarded(tmp_path):
    target = tmp_path / "r.dbtf"

    def stop(done):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_stored(target, small_source(0), progress=False, callback=stop)
    other = CountingSource(small_source(1))
    write_stored(target, other, progress=False)
    assert len(other.reads) == other.n_pairs  # restarted from scratch
    np.testing.assert_allclose(StoredBTF(target).image(2, 4), small_source(1).image(2, 4), rtol=1e-3)
    # a damaged partial directory (missing progress marker) is also restarted, not trusted
    with pytest.raises(KeyboardInterrupt):
        write_stored(tmp_path / "s.dbtf", small_source(0), progress=False, callback=stop)
    (tmp_path / ".s.dbtf.partial" / "progress.json").unlink()
    again = CountingSource(small_source(0))
    write_stored(tmp_path / "s.dbtf", again, progress=False)
    assert len(again.reads) == again.n_pairs


def test_overwrite_rules(tmp_path):
    target = write_stored(tmp_path / "o.dbtf", small_source(0), progress=False)
    with pytest.raises(InputError, match="already exists"):
        write_stored(target, small_source(1), progress=False)
    write_stored(target, small_source(1), progress=False, overwrite=True, dtype="float32")
    np.testing.assert_array_equal(StoredBTF(target).image(0, 0), small_source(1).image(0, 0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.dbtf"]


def test_writer_rejects_bad_values_and_options(tmp_path):
    with pytest.raises(InputError, match="dtype"):
        write_stored(tmp_path / "a.dbtf", small_source(), dtype="int8")
    with pytest.raises(InputError, match="out-of-range"):
        write_stored(tmp_path / "b.dbtf", small_source(scale=1e6), dtype="float16", progress=False)
    with pytest.raises(InputError, match="BTFSource"):
        write_stored(tmp_path / "c.dbtf", np.zeros((1, 1, 2, 2, 3)))


def _stored(tmp_path) -> tuple:
    path = write_stored(tmp_path / "m.dbtf", small_source(), progress=False)
    return path, json.loads((path / META_FILE).read_text())


@pytest.mark.parametrize("edit, message", [
    (lambda m: m.update(version=STORED_VERSION + 1), "newer dynbtf"),
    (lambda m: m.update(version="1"), "must be an integer"),
    (lambda m: m.update(format="something-else"), "format is 'something-else'"),
    (lambda m: m.update(dtype="float64"), "dtype 'float64' is not supported"),
    (lambda m: m.update(height=5), "truncated or mismatched"),
    (lambda m: m.pop("width"), "missing field 'width'"),
    (lambda m: m.update(n_views=0), "must be positive"),
    (lambda m: m.update(views=[[0, 0, 1.0]]), r"shape \(1, 3\); expected \(3, 3\)"),
    (lambda m: m.update(lights=[[0, 0.6, -0.8]] * 5), "below the horizon"),
    (lambda m: m.update(data_file="../values.bin"), "plain file name"),
])
def test_meta_validation(tmp_path, edit, message):
    path, meta = _stored(tmp_path)
    edit(meta)
    (path / META_FILE).write_text(json.dumps(meta))
    with pytest.raises(FormatError, match=message) as e:
        StoredBTF(path)
    assert str(path) in str(e.value)


def test_damaged_files(tmp_path):
    path, _ = _stored(tmp_path)
    data = path / DATA_FILE
    data.write_bytes(data.read_bytes()[:-2])
    with pytest.raises(FormatError, match="truncated or mismatched"):
        StoredBTF(path)
    (path / META_FILE).write_text("{not json")
    with pytest.raises(FormatError, match="not valid JSON"):
        StoredBTF(path)
    (path / META_FILE).unlink()
    with pytest.raises(FormatError, match="not found"):
        StoredBTF(path)
    with pytest.raises(FormatError, match="without meta.json"):
        open_btf(path)


def test_nan_in_data_is_reported_on_read(tmp_path):
    path = write_stored(tmp_path / "n.dbtf", small_source(), progress=False, dtype="float32")
    values = np.memmap(path / DATA_FILE, dtype="<f4", mode="r+")
    values[5] = np.nan
    values.flush()
    del values
    btf = StoredBTF(path / META_FILE)  # the meta.json path works too
    with pytest.raises(FormatError, match=r"view 0, light 0"):
        btf.image(0, 0)


def test_view_images_reports_the_bad_light(tmp_path):
    path = write_stored(tmp_path / "n.dbtf", small_source(), progress=False, dtype="float32")
    values = np.memmap(path / DATA_FILE, dtype="<f4", mode="r+", shape=(3, 5, 4, 6, 3))
    values[1, 3, 2, 2, 1] = np.inf
    values.flush()
    del values
    btf = StoredBTF(path)
    np.testing.assert_array_equal(btf.view_images(1, [0, 1, 2]), np.stack([btf.image(1, l) for l in range(3)]))
    with pytest.raises(FormatError, match=r"view 1, light 3"):
        btf.view_images(1)
