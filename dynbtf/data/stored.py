"""dynbtf's own on-disk format for full BTFs: a directory with JSON metadata and one raw array.

Layout of ``name.dbtf/``
------------------------
``meta.json``
    ``format`` (``"dynbtf-stored-btf"``), ``version`` (int), ``height``,
    ``width``, ``n_views``, ``n_lights``, ``dtype`` (``"float16"`` or
    ``"float32"``), ``layout``, ``data_file``, the directions both as unit vectors
    (``views``, ``lights``: ``[[x, y, z], ...]``) and in degrees (``views_deg``,
    ``lights_deg``: ``[[theta, phi], ...]``), ``values`` (units and conventions:
    linear RGB, ``pi * f_r``, excluding ``cos(theta_light)``), ``name`` and a
    ``provenance`` dict (where the BTF came from).
``values.bin``
    The values, little endian, C order, shape ``(n_views, n_lights, H, W, 3)``:
    image ``(v, l)`` is one contiguous block, rows top-down as dynbtf images.

Writing streams image by image from any :class:`~dynbtf.data.base.BTFSource`
into a temporary directory ``.name.dbtf.partial`` next to the target (never
holding the whole BTF), with a progress marker ``progress.json`` committed after
each batch; the directory is renamed onto the target when complete. An
interrupted write continues from the images already written when run again
with the same source and options.

Examples
--------
>>> import numpy as np, tempfile, os
>>> from dynbtf.data.array import ArrayBTF
>>> src = ArrayBTF(np.full((1, 2, 3, 4, 3), 0.5), [[0, 0, 1.0]], [[0, 0, 1.0], [1.0, 0, 0]])
>>> path = write_stored(os.path.join(tempfile.mkdtemp(), "grey.dbtf"), src, progress=False)
>>> btf = StoredBTF(path)
>>> btf.shape, float(btf.image(0, 1)[2, 3, 0])
((1, 2, 3, 4), 0.5)
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..conventions import check_directions, direction_to_spherical
from ..errors import FormatError, InputError
from .base import BTFSource
from .file_array import FileArray, OpenFile

__all__ = ["StoredBTF", "write_stored", "read_stored", "STORED_FORMAT", "STORED_VERSION", "STORED_DTYPES",
           "META_FILE", "DATA_FILE"]

#: Value of ``meta.json``'s ``format`` field.
STORED_FORMAT = "dynbtf-stored-btf"
#: Newest format version this dynbtf writes and reads.
STORED_VERSION = 1
#: Value types a stored BTF may hold.
STORED_DTYPES = ("float16", "float32")
META_FILE = "meta.json"
DATA_FILE = "values.bin"
_PROGRESS_FILE = "progress.json"
_VALUES_NOTE = ("linear RGB reflectance factor pi * f_r, excluding cos(theta_light); directions are unit vectors "
                "in the local frame (x = +u, y = +v, z = normal), both pointing away from the surface; "
                "(theta, phi) in degrees with phi from +x towards +y")
_LAYOUT = "values[view, light, row, col, rgb], C order, little endian; row 0 is v = 0 (top of an image)"


def _json_safe(d: dict) -> dict[str, Any]:
    """Keep the JSON-serializable entries of a metadata dict."""
    out = {}
    for k, v in d.items():
        try:
            json.dumps(v)
        except (TypeError, ValueError):
            continue
        out[str(k)] = v
    return out


def _meta_for(source: BTFSource, dtype: str) -> dict[str, Any]:
    def degrees(w):
        theta, phi = direction_to_spherical(w)
        return np.stack([theta, phi], axis=1).round(9).tolist()

    from .._version import __version__

    return {
        "format": STORED_FORMAT,
        "version": STORED_VERSION,
        "name": source.name,
        "height": int(source.height),
        "width": int(source.width),
        "n_views": source.n_views,
        "n_lights": source.n_lights,
        "dtype": dtype,
        "layout": _LAYOUT,
        "data_file": DATA_FILE,
        "values": _VALUES_NOTE,
        "views": np.asarray(source.views, dtype=np.float64).tolist(),
        "lights": np.asarray(source.lights, dtype=np.float64).tolist(),
        "views_deg": degrees(source.views),
        "lights_deg": degrees(source.lights),
        "provenance": {"source_kind": type(source).__name__, "source_name": source.name,
                       "written_by": f"dynbtf {__version__}", **_json_safe(source.metadata)},
    }


def _write_json_atomic(path: Path, obj) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _read_json(path: Path):
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except (OSError, ValueError) as e:
        raise FormatError(path, f"not valid JSON ({e})") from None


def _partial_dir(path: Path) -> Path:
    return path.with_name(f".{path.name}.partial")


def write_stored(path, source: BTFSource, *, dtype: str = "float16", progress: bool = True,
                 overwrite: bool = False, lights_per_batch: int | None = None,
                 callback: Callable[[int], None] | None = None) -> Path:
    """Stream ``source`` into a stored BTF directory at ``path``, atomically and resumably.

    Parameters
    ----------
    path : str or Path
        Target directory (conventionally named ``*.dbtf``).
    source : BTFSource
        Any BTF source; read image by image (or one view's lights at a time when
        the source offers ``view_images``), never whole.
    dtype : ``"float16"`` or ``"float32"``
        Stored value type (default ``float16``: half the size, relative error
        below 1e-3; values above 65504 are refused).
    progress : bool
        Show a tqdm progress bar (images, rate, ETA).
    overwrite : bool
        Replace an existing ``path`` (default: refuse).
    lights_per_batch : int, optional
        Images decoded together per batch (default: as many as fit in ~64 MB).
    callback : callable, optional
        Called with the number of images written after each committed batch
        (e.g. to report progress elsewhere, or to interrupt in tests).

    Returns
    -------
    Path : ``path``.

    Notes
    -----
    The temporary directory ``.<name>.partial`` next to ``path`` holds
    ``meta.json``, the preallocated ``values.bin`` and ``progress.json`` (images
    done). A later call with a source of identical metadata resumes there; a
    partial directory of another source is discarded.
    """
    path = Path(path)
    _check_write_arguments(path, source, dtype, overwrite)
    meta = _meta_for(source, dtype)
    image_shape = (source.height, source.width, 3)
    total_bytes = source.n_pairs * int(np.prod(image_shape)) * np.dtype(dtype).itemsize
    partial = _partial_dir(path)
    done = _prepare_partial(partial, meta, source.n_pairs, total_bytes)
    if lights_per_batch is None:
        lights_per_batch = max(1, min(source.n_lights, (64 << 20) // max(1, int(np.prod(image_shape)) * 4)))
    _write_images(partial, source, dtype, done, lights_per_batch, desc=f"writing {path.name}", progress=progress,
                  callback=callback)
    os.remove(partial / _PROGRESS_FILE)
    _move_into_place(partial, path)
    return path


def _check_write_arguments(path: Path, source: BTFSource, dtype: str, overwrite: bool) -> None:
    """:class:`InputError` for an unknown ``dtype``, a ``source`` that is no BTFSource, or an existing ``path``
    without ``overwrite``."""
    if dtype not in STORED_DTYPES:
        raise InputError(f"dtype: expected one of {STORED_DTYPES}, got {dtype!r}")
    if not isinstance(source, BTFSource):
        raise InputError(f"source: expected a BTFSource, got {type(source).__name__}")
    if path.exists() and not overwrite:
        raise InputError(f"{path}: already exists (pass overwrite=True, or --overwrite on the command line)")


def _prepare_partial(partial: Path, meta: dict[str, Any], n_images: int, total_bytes: int) -> int:
    """Resume or start the partial directory; returns the images already written there.

    A partial directory is resumed when its ``meta.json`` equals ``meta``, its ``values.bin`` has
    ``total_bytes`` bytes and its ``progress.json`` counts ``0 <= done <= n_images`` images; otherwise it is
    discarded and a new one made: ``meta.json``, ``values.bin`` preallocated (sparse) and a progress of 0.
    """
    done = 0
    if partial.exists():
        try:
            same = _read_json(partial / META_FILE) == json.loads(json.dumps(meta))
            marker = _read_json(partial / _PROGRESS_FILE)
            same = same and (partial / DATA_FILE).stat().st_size == total_bytes
            done = int(marker["images_done"]) if same else 0
        except (FormatError, OSError, KeyError, TypeError, ValueError):
            same = False
        if not same or not 0 <= done <= n_images:
            shutil.rmtree(partial)
            done = 0
    if not partial.exists():
        partial.mkdir(parents=True)
        _write_json_atomic(partial / META_FILE, meta)
        with open(partial / DATA_FILE, "wb") as f:
            f.truncate(total_bytes)
        _write_json_atomic(partial / _PROGRESS_FILE, {"images_done": 0, "images_total": n_images})
    return done


def _write_images(partial: Path, source: BTFSource, dtype: str, done: int, lights_per_batch: int, *, desc: str,
                  progress: bool, callback: Callable[[int], None] | None) -> None:
    """Write images ``done..n_pairs`` (view-major) into ``partial/values.bin``, ``lights_per_batch`` of one view
    at a time, committing ``progress.json`` (and calling ``callback(images done)``) after each batch."""
    from ..progress import progress_bar

    n_lights, n_images = source.n_lights, source.n_pairs
    image_shape = (source.height, source.width, 3)
    values = np.memmap(partial / DATA_FILE, dtype=np.dtype(dtype).newbyteorder("<"), mode="r+",
                       shape=(source.n_views, n_lights) + image_shape)
    with progress_bar(total=n_images, initial=done, unit="img", desc=desc, disable=not progress) as bar:
        while done < n_images:
            v, l0 = divmod(done, n_lights)
            lights = np.arange(l0, min(n_lights, l0 + lights_per_batch))
            values[v, lights] = _read_batch(source, v, lights, dtype)
            values.flush()
            done += len(lights)
            _write_json_atomic(partial / _PROGRESS_FILE, {"images_done": done, "images_total": n_images})
            bar.update(len(lights))
            if callback is not None:
                callback(done)
    del values


def _read_batch(source: BTFSource, view: int, lights: np.ndarray, dtype: str) -> np.ndarray:
    """Images ``(len(lights), H, W, 3)`` of one ``view`` (through ``source.view_images`` when it has it);
    :class:`InputError` for a wrong shape, NaN, infinite values or values ``dtype`` cannot hold."""
    image_shape = (source.height, source.width, 3)
    view_images = getattr(source, "view_images", None)
    if view_images is not None:
        batch = np.asarray(view_images(view, lights), dtype=np.float32)
    else:
        batch = np.stack([source.image(view, int(l)) for l in lights])
    if batch.shape != (len(lights),) + image_shape:
        raise InputError(f"{source.name}: view {view} returned images of shape {batch.shape[1:]}, "
                         f"expected {image_shape}")
    limit = np.finfo(np.float16).max if dtype == "float16" else np.inf
    if not np.isfinite(batch).all() or np.abs(batch).max() > limit:
        raise InputError(f"{source.name}: view {view} has NaN, infinite or out-of-range values "
                         f"(|value| must stay below {limit:g} for {dtype})")
    return batch


def _move_into_place(partial: Path, path: Path) -> None:
    """Rename the finished ``partial`` directory onto ``path``; an existing ``path`` (overwrite) is moved aside
    first and removed after the swap."""
    if path.exists():  # overwrite: move the old one aside, then swap in the new one
        trash = path.with_name(f".{path.name}.old")
        if trash.exists():
            shutil.rmtree(trash)
        os.replace(path, trash)
        os.replace(partial, path)
        if trash.is_dir():
            shutil.rmtree(trash)
        else:
            os.remove(trash)
    else:
        os.replace(partial, path)


def _field(meta: dict, key: str, kind, where: Path):
    if key not in meta:
        raise FormatError(where, f"missing field {key!r}")
    value = meta[key]
    if kind is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise FormatError(where, f"field {key!r} must be an integer, got {value!r}")
    if kind is str and not isinstance(value, str):
        raise FormatError(where, f"field {key!r} must be a string, got {value!r}")
    return value


def _directions(meta: dict, key: str, n: int, where: Path) -> np.ndarray:
    try:
        w = np.asarray(_field(meta, key, list, where), dtype=np.float64)
    except (TypeError, ValueError):
        raise FormatError(where, f"field {key!r} must be a list of [x, y, z] unit vectors") from None
    if w.shape != (n, 3):
        raise FormatError(where, f"field {key!r} has shape {w.shape}; expected ({n}, 3)")
    try:
        check_directions(w, key)
    except ValueError as e:
        raise FormatError(where, str(e)) from None
    return w


class StoredBTF(BTFSource):
    """A stored BTF directory (see the module docstring), its values read on demand.

    Parameters
    ----------
    path : str or Path
        The ``*.dbtf`` directory (or its ``meta.json``).

    Raises
    ------
    FormatError
        Missing or malformed ``meta.json``, a format version newer than
        :data:`STORED_VERSION`, an unknown dtype, bad directions, or a data file
        whose size does not match the shape.
    """

    def __init__(self, path):
        super().__init__()
        path = Path(path)
        if path.name == META_FILE and path.is_file():
            path = path.parent
        if not path.exists():
            raise FormatError(path, "not found")
        if not path.is_dir():
            raise FormatError(path, "not a stored BTF directory (expected a directory with meta.json)")
        self.path = path
        meta_path = path / META_FILE
        meta = _read_json(meta_path)
        if not isinstance(meta, dict):
            raise FormatError(meta_path, "expected a JSON object")
        fmt = _field(meta, "format", str, meta_path)
        if fmt != STORED_FORMAT:
            raise FormatError(meta_path, f"format is {fmt!r}; expected {STORED_FORMAT!r}")
        version = _field(meta, "version", int, meta_path)
        if version > STORED_VERSION:
            raise FormatError(meta_path, f"format version {version} was written by a newer dynbtf; this dynbtf "
                                         f"reads versions up to {STORED_VERSION} (upgrade dynbtf)")
        if version < 1:
            raise FormatError(meta_path, f"format version {version} is invalid (expected 1..{STORED_VERSION})")
        dims = {}
        for key in ("height", "width", "n_views", "n_lights"):
            dims[key] = _field(meta, key, int, meta_path)
            if dims[key] < 1:
                raise FormatError(meta_path, f"field {key!r} must be positive, got {dims[key]}")
        dtype = _field(meta, "dtype", str, meta_path)
        if dtype not in STORED_DTYPES:
            raise FormatError(meta_path, f"dtype {dtype!r} is not supported; expected one of {STORED_DTYPES}")
        data_name = _field(meta, "data_file", str, meta_path)
        if Path(data_name).name != data_name:
            raise FormatError(meta_path, f"data_file {data_name!r} must be a plain file name inside {path}")
        self.views = _directions(meta, "views", dims["n_views"], meta_path)
        self.lights = _directions(meta, "lights", dims["n_lights"], meta_path)
        self.height, self.width = dims["height"], dims["width"]
        self.dtype = np.dtype(dtype).newbyteorder("<")
        shape = (dims["n_views"], dims["n_lights"], self.height, self.width, 3)
        expected = math.prod(shape) * self.dtype.itemsize
        data_path = path / data_name
        if not data_path.is_file():
            raise FormatError(data_path, "data file not found")
        actual = data_path.stat().st_size
        if actual != expected:
            raise FormatError(data_path, f"has {actual} bytes but meta.json's shape {shape} of {dtype} needs "
                                         f"{expected} bytes (truncated or mismatched file)")
        self._file = OpenFile(data_path, expected_bytes=expected)
        # one row per texel of image (v, l): rows (v * n_lights + l) * H * W ...; read on demand (file_array)
        self._values: FileArray | None = self._file.array(0, (math.prod(shape[:4]), 3), self.dtype)
        self.name = str(meta.get("name", path.name))
        provenance = meta.get("provenance", {})
        self.metadata = {"format": "dynbtf-stored", "version": version, "dtype": dtype, "path": str(path),
                         "provenance": provenance if isinstance(provenance, dict) else {}}

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        if self._values is None:
            raise InputError(f"{self.path}: the stored BTF was closed")
        first = self._image_row(view_index, light_index)
        img = self._values[first:first + self.height * self.width].astype(np.float32).reshape(self.height,
                                                                                             self.width, 3)
        if not np.isfinite(img).all():
            raise FormatError(self.path, f"image (view {view_index}, light {light_index}) contains NaN or "
                                         f"infinite values")
        return img

    def view_images(self, view_index: int, light_indices=None) -> np.ndarray:
        """Images of one view for several lights, ``(L, H, W, 3)`` float32 (default all lights)."""
        v, _ = self._check_pair(view_index, 0)
        lights = np.arange(self.n_lights) if light_indices is None else np.asarray(light_indices, np.int64).reshape(-1)
        for l in lights:
            self._check_pair(v, l)
        if self._values is None:
            raise InputError(f"{self.path}: the stored BTF was closed")
        texels = self.height * self.width
        images = np.empty((len(lights), self.height, self.width, 3), dtype=np.float32)
        for i, first in enumerate(self._image_row(v, lights)):  # one read per image
            images[i] = self._values[first:first + texels].reshape(self.height, self.width, 3)
        if not np.isfinite(images).all():
            bad = int(lights[np.flatnonzero(~np.isfinite(images).reshape(len(lights), -1).all(axis=1))[0]])
            raise FormatError(self.path, f"image (view {v}, light {bad}) contains NaN or infinite values")
        return images

    def _read_texels(self, pairs: np.ndarray, texels: np.ndarray, device=None) -> np.ndarray:
        """Only the requested texels are read from the file (rows close together: one read)."""
        if self._values is None:
            raise InputError(f"{self.path}: the stored BTF was closed")
        out = np.empty(pairs.shape[:2] + (texels.shape[1], 3), dtype=np.float32)
        first = self._image_row(pairs[..., 0], pairs[..., 1])  # (G, B)
        for g in range(pairs.shape[0]):
            lo, hi = (int(texels[g].min()), int(texels[g].max()) + 1) if texels.shape[1] else (0, 0)
            dense = hi - lo <= 2 * texels.shape[1]  # a block (or nearly): read the span, then select
            for b, start in enumerate(first[g]):
                out[g, b] = (self._values[start + lo:start + hi][texels[g] - lo] if dense
                             else self._values.take(start + texels[g]))
        if not np.isfinite(out).all():
            g, b = np.argwhere(~np.isfinite(out).reshape(*out.shape[:2], -1).all(axis=2))[0]
            raise FormatError(self.path, f"image (view {pairs[g, b, 0]}, light {pairs[g, b, 1]}) contains NaN or "
                                         f"infinite values")
        return out

    def _image_row(self, view_index, light_index):
        """The first row (texel) of image ``(view, light)`` in the values file (ints or arrays)."""
        return (np.asarray(view_index, np.int64) * self.n_lights + light_index) * (self.height * self.width)

    def close(self) -> None:
        self._values = None
        self._file.close()


def read_stored(path) -> StoredBTF:
    """Open a stored BTF directory (see :class:`StoredBTF`)."""
    return StoredBTF(path)
