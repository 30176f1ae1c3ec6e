"""Arrays stored in a file, read with ``pread`` so that a file truncated while it is read is an error, not a crash.

A memory map of a file that another process truncates kills the reader with ``SIGBUS`` (no message, no
``finally``) as soon as it touches a page past the new end, and no check before the access closes that
window: the file can shrink between the check and the read. :class:`OpenFile` reads with ``os.pread``
instead, which returns fewer bytes at the end of the file; a short read becomes a
:class:`~dynbtf.errors.FormatError` naming the file and both sizes. The descriptor is held open, so a file
replaced (renamed over) or deleted while open keeps being read as it was, as a memory map would.

:class:`FileArray` is a read-only C-order array in a region of an open file: slices and integer arrays
along its first axis are read on demand (rows close together are read in one call), and ``np.asarray``
reads all of it. ``pread`` does not move a file position, so readers in several threads share one file.

Examples
--------
>>> import numpy as np, tempfile, os
>>> path = os.path.join(tempfile.mkdtemp(), "rows.bin")
>>> np.arange(12, dtype="<f4").tofile(path)
>>> with OpenFile(path) as f:
...     a = f.array(offset=8, shape=(2, 5), dtype="<f4")
...     a[1:2].tolist(), a[np.array([1, 0, 1])][:, 0].tolist()
([[7.0, 8.0, 9.0, 10.0, 11.0]], [7.0, 2.0, 7.0])
>>> with OpenFile(path) as f:
...     a = f.array(offset=8, shape=(2, 5), dtype="<f4")
...     os.truncate(path, 20)
...     a[1:]  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
dynbtf.errors.FormatError: ...rows.bin: the file shrank from 48 to 20 bytes while it was being read ...
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError

__all__ = ["OpenFile", "FileArray"]

#: Rows of a gather closer than this many bytes are read in one call (the gap is read and dropped).
GATHER_GAP_BYTES = 1 << 16


class OpenFile:
    """A file opened for positioned reads; ``file[a:b]`` is ``bytes``, as from a ``bytes`` object.

    ``expected_bytes`` (default: the size when opened) is what the reader relies on; a read that ends
    short of it raises :class:`FormatError` saying the file shrank.
    """

    def __init__(self, path, *, expected_bytes: int | None = None):
        self.path = Path(path)
        try:
            self._fd: int | None = os.open(self.path, os.O_RDONLY | getattr(os, "O_BINARY", 0))
        except OSError as e:
            raise FormatError(self.path, f"cannot open ({e.strerror or e})") from None
        self.size = os.fstat(self._fd).st_size
        self.expected_bytes = self.size if expected_bytes is None else int(expected_bytes)

    def read(self, offset: int, nbytes: int) -> bytes:
        """Exactly ``nbytes`` bytes from ``offset``; :class:`FormatError` when the file now ends before."""
        if self._fd is None:
            raise InputError(f"{self.path}: the file was closed")
        parts, done = [], 0
        while done < nbytes:
            part = os.pread(self._fd, nbytes - done, offset + done)
            if not part:
                now = os.fstat(self._fd).st_size
                if now >= self.expected_bytes:
                    raise FormatError(self.path, f"truncated: {nbytes} bytes at offset {offset} are needed but the "
                                                 f"file has {now} bytes")
                raise FormatError(self.path, f"the file shrank from {self.expected_bytes} to {now} bytes while it "
                                             "was being read (truncated, or being rewritten?). Restore the file and "
                                             "run again (a fit continues from its checkpoint)")
            parts.append(part)
            done += len(part)
        return parts[0] if len(parts) == 1 else b"".join(parts)

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, key: slice) -> bytes:
        if not isinstance(key, slice) or key.step not in (None, 1):
            raise TypeError("an OpenFile is sliced with [start:stop] only")
        start, stop, _ = key.indices(self.size)
        return self.read(start, max(0, stop - start))

    def array(self, offset: int, shape: tuple[int, ...], dtype) -> FileArray:
        """The C-order array of ``shape`` and ``dtype`` stored from byte ``offset``."""
        return FileArray(self, offset, shape, dtype)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except OSError:
            pass


class FileArray:
    """A read-only C-order array in a file region; indexing along the first axis reads the file.

    ``a[i]``, ``a[start:stop]`` and ``a[int_array]`` return NumPy arrays (the first drops the axis);
    ``np.asarray(a)`` reads everything. Shapes are as for the same index into an ``np.ndarray``.
    """

    def __init__(self, file: OpenFile, offset: int, shape: tuple[int, ...], dtype):
        self.file, self.offset = file, int(offset)
        self.shape = tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)
        self.itemsize = self.dtype.itemsize
        self.size = math.prod(self.shape)
        self.row_bytes = math.prod(self.shape[1:]) * self.itemsize

    def __len__(self) -> int:
        return self.shape[0]

    def _rows(self, start: int, stop: int) -> np.ndarray:
        data = self.file.read(self.offset + start * self.row_bytes, (stop - start) * self.row_bytes)
        return np.frombuffer(data, dtype=self.dtype).reshape((stop - start,) + self.shape[1:])

    def __getitem__(self, key):
        if isinstance(key, (int, np.integer)):
            i = int(key) + (self.shape[0] if key < 0 else 0)
            if not 0 <= i < self.shape[0]:
                raise IndexError(f"row {int(key)} of {self.shape[0]}")
            return self._rows(i, i + 1)[0]
        if isinstance(key, slice):
            start, stop, step = key.indices(self.shape[0])
            if step != 1:
                raise TypeError("a FileArray is sliced with step 1 only")
            return self._rows(start, max(start, stop))
        return self.take(key)

    def take(self, rows) -> np.ndarray:
        """Rows ``rows`` (an integer array, any order, repeats allowed) -> ``rows.shape + shape[1:]``.

        Rows nearer than :data:`GATHER_GAP_BYTES` to each other are read together.
        """
        rows = np.asarray(rows)
        if rows.dtype.kind not in "iu":
            raise TypeError(f"rows must be integers, not {rows.dtype}")
        flat = rows.reshape(-1).astype(np.int64)
        flat = np.where(flat < 0, flat + self.shape[0], flat)
        if flat.size and (flat.min() < 0 or flat.max() >= self.shape[0]):
            raise IndexError(f"rows outside 0..{self.shape[0] - 1}")
        unique, inverse = np.unique(flat, return_inverse=True)
        out = np.empty((len(unique),) + self.shape[1:], dtype=self.dtype)
        gap_rows = max(1, GATHER_GAP_BYTES // max(1, self.row_bytes))
        cuts = np.flatnonzero(np.diff(unique) > gap_rows) + 1
        for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, len(unique)]) if len(unique) else ():
            first, last = int(unique[lo]), int(unique[hi - 1])
            out[lo:hi] = self._rows(first, last + 1)[unique[lo:hi] - first]
        return out[inverse].reshape(rows.shape + self.shape[1:])

    def __array__(self, dtype=None, copy=None):
        values = self._rows(0, self.shape[0])
        return values if dtype is None else values.astype(dtype)
