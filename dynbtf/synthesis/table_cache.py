"""An on-disk cache of synthesis tables, keyed by the exemplar's contents and the method's parameters.

Off-line work that a synthesis method does once per exemplar (the cut tables of ``struct``:
a quarter of a second at 128 x 128 texels, several seconds at 400 x 400) is stored here so that
every later process -- another ``dynbtf synth``, a Mitsuba scene loading the same model --
reads it instead of building it again.

* **Where**: ``$DYNBTF_SYNTHESIS_CACHE`` if set (``off`` disables the cache), else
  ``$XDG_CACHE_HOME/dynbtf/synthesis`` (``~/.cache/dynbtf/synthesis``).
* **Key**: SHA-256 of the format version, the method, the parameters (JSON) and the bytes and
  shapes of every input array (the exemplar, the guide): an entry can only be found by the
  inputs it was built from.
* **Entry**: one ``.npz`` file (no pickles) of the table arrays plus ``checksum``, the SHA-256 of
  those arrays' names, dtypes, shapes and bytes. It is written to a temporary file and renamed,
  so a reader never sees half an entry; a damaged entry (unreadable, missing arrays, wrong
  checksum) is never used: :func:`cached_tables` warns, builds the tables again and replaces it.
"""

from __future__ import annotations

import hashlib
import json
import stat
import warnings
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np

from ..io import atomic_path, user_cache_dir

__all__ = ["cache_dir", "cache_key", "cached_tables", "FORMAT_VERSION"]

#: Bumped whenever a method's tables change meaning: old entries are then never found.
FORMAT_VERSION = 1


def cache_dir() -> Path | None:
    """The cache directory, or None when ``DYNBTF_SYNTHESIS_CACHE=off``."""
    return user_cache_dir("DYNBTF_SYNTHESIS_CACHE", "synthesis")


def cache_key(method: str, parameters: dict, arrays: dict[str, np.ndarray | None]) -> str:
    """Hex SHA-256 of the version, ``method``, ``parameters`` (JSON) and the named input ``arrays``."""
    digest = hashlib.sha256()
    digest.update(json.dumps({"version": FORMAT_VERSION, "method": method, "parameters": parameters},
                             sort_keys=True).encode())
    for name in sorted(arrays):
        array = arrays[name]
        digest.update(name.encode())
        if array is None:
            digest.update(b"none")
            continue
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    digest = hashlib.sha256()
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _read(path: Path, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The entry's arrays; raises ValueError (or an OS/zip error) for anything but an intact entry."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    stored = arrays.pop("checksum", None)
    if stored is None or set(arrays) != set(names):
        raise ValueError(f"expected the arrays {sorted(names)}, found {sorted(arrays)}")
    if str(stored) != _checksum(arrays):
        raise ValueError("checksum mismatch")
    return arrays


def cached_tables(method: str, parameters: dict, inputs: dict[str, np.ndarray | None], names: tuple[str, ...],
                  build: Callable[[], dict[str, np.ndarray]],
                  check: Callable[[dict[str, np.ndarray]], None] | None = None) -> tuple[dict[str, np.ndarray], str]:
    """The tables ``build()`` returns for these inputs, from the cache when an intact entry exists.

    ``names``: the arrays ``build()`` returns (an entry holding others is damaged). ``check``: raises
    ``ValueError`` for tables a kernel must not read (shapes, bounds, indices): such an entry is rebuilt too,
    since a checksum anyone can recompute proves nothing about the contents. Only regular files are read.

    Returns ``(arrays, how)`` with ``how`` one of ``"built"`` (no cache), ``"cached"`` (read),
    ``"stored"`` (built and written) or ``"rebuilt"`` (a damaged entry was replaced). A cache
    directory that cannot be written only costs the rebuild, with a warning.
    """
    folder = cache_dir()
    if folder is None:
        return build(), "built"
    path = folder / f"{method}-{cache_key(method, parameters, inputs)}.npz"
    how = "stored"
    if path.exists() or path.is_symlink():
        try:
            if not stat.S_ISREG(path.stat().st_mode):  # a FIFO or device would block or never end
                raise ValueError("not a regular file")
            arrays = _read(path, names)
            if check is not None:
                check(arrays)
            return arrays, "cached"
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as e:
            warnings.warn(f"synthesis table cache: {path} is damaged ({e}); building the tables again", stacklevel=3)
            how = "rebuilt"
    arrays = build()
    try:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, checksum=np.array(_checksum(arrays)), **arrays)
    except OSError as e:
        warnings.warn(f"synthesis table cache: could not write {path} ({e}); the tables were built and are used",
                      stacklevel=3)
    return arrays, how

