"""Training data: the held-out split of (view, light) pairs and whole images served per step.

The paper trains on batches of whole BTF images, each under one (view, light)
pair. :class:`ImageStore` serves such images as flat ``(N, 3)`` float32 arrays;
when the whole BTF fits in a memory budget it keeps every image it decoded in a
float16 cache (the 128 x 128 x 81 x 81 demo BTF is 0.65 GB as float16), otherwise
it decodes on demand and memory stays bounded by a few images (the paper's
400 x 400 x 151 x 151 would be 22 GB as float16). Float16 keeps ~3.3 significant
digits, far below the representation's error.
"""

from __future__ import annotations

import ctypes
import functools
import threading

import numpy as np

from ..data.base import BTFSource
from ..errors import InputError

__all__ = ["held_out_split", "ImageStore"]


def held_out_split(n_views: int, n_lights: int, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Split all (view, light) index pairs into ``(train, held_out)``, each int64 ``(P, 2)``.

    ``round(fraction * n_pairs)`` pairs (at least one when ``fraction > 0``, and at
    least one pair stays for training) are drawn without replacement from a
    NumPy generator seeded with ``seed``; both lists are sorted view-major. The
    same arguments always give the same split.

    >>> train, held = held_out_split(3, 4, 0.25, seed=0)
    >>> len(train), len(held)
    (9, 3)
    """
    n_pairs = n_views * n_lights
    if not 0.0 <= fraction < 1.0:
        raise InputError(f"held_out_fraction: expected a value in [0, 1), got {fraction}")
    if n_pairs < 1:
        raise InputError("the BTF has no (view, light) pairs")
    k = int(round(fraction * n_pairs))
    if fraction > 0:
        k = max(k, 1)
    k = min(k, n_pairs - 1)
    rng = np.random.default_rng([int(seed), 0x4E1D])
    held_rows = np.sort(rng.choice(n_pairs, size=k, replace=False)) if k else np.zeros(0, dtype=np.int64)
    mask = np.zeros(n_pairs, dtype=bool)
    mask[held_rows] = True
    rows = np.arange(n_pairs)
    to_pairs = lambda r: np.stack([r // n_lights, r % n_lights], axis=1).astype(np.int64)  # noqa: E731
    return to_pairs(rows[~mask]), to_pairs(rows[mask])


class ImageStore:
    """Whole images of a :class:`BTFSource` as flat ``(H * W, 3)`` arrays, cached when they fit.

    Parameters
    ----------
    source : BTFSource
    memory_budget : int
        Bytes the float16 cache may use. If the whole BTF (``n_pairs * H * W * 3 * 2``
        bytes) fits, every decoded image is kept; otherwise nothing is cached
        and every request decodes (bounded memory).

    Thread-safe: a prefetch thread may call :meth:`get` while the trainer runs.
    """

    def __init__(self, source: BTFSource, memory_budget: int = 2 * 1024 ** 3) -> None:
        self.source = source
        self.n_texels = source.height * source.width
        cache_bytes = source.n_pairs * self.n_texels * 3 * 2
        self.cached = cache_bytes <= memory_budget
        self._lock = threading.Lock()
        if self.cached:
            # np.empty reserves address space only; pages are touched as images arrive
            self._cache = np.empty((source.n_pairs, self.n_texels, 3), dtype=np.float16)
            self._filled = np.zeros(source.n_pairs, dtype=bool)

    def _decode(self, v: int, l: int) -> np.ndarray:
        img = np.asarray(self.source.image(v, l), dtype=np.float32)
        if img.shape != (self.source.height, self.source.width, 3):
            raise InputError(f"{self.source.name}: image ({v}, {l}) has shape {img.shape}, expected "
                             f"{(self.source.height, self.source.width, 3)}")
        return img.reshape(self.n_texels, 3)

    def image(self, view_index: int, light_index: int) -> np.ndarray:
        """Flat float32 image ``(H * W, 3)`` of one pair."""
        if not self.cached:
            return self._decode(view_index, light_index)
        row = view_index * self.source.n_lights + light_index
        if not self._filled[row]:
            img = self._decode(view_index, light_index)
            with self._lock:
                self._cache[row] = img
                self._filled[row] = True
            return img
        return self._cache[row].astype(np.float32)

    def fill(self, pairs: np.ndarray | None = None, progress: bool = False) -> None:
        """Decode ``pairs`` (default: all) into the cache in view-major order (no-op when not cached).

        Sources that render or decode a view's lights together (simulated BTFs,
        DFMF files) are fastest when read view-major; training then reads the
        cache in any order.
        """
        if not self.cached:
            return
        from ..progress import progress_bar
        if pairs is None:
            rows = np.arange(self.source.n_pairs)
        else:
            pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
            rows = np.sort(pairs[:, 0] * self.source.n_lights + pairs[:, 1])
        rows = rows[~self._filled[rows]]
        for row in progress_bar(rows, disable=not progress or len(rows) == 0, unit="image", desc="decoding BTF",
                        leave=False):
            self.image(int(row) // self.source.n_lights, int(row) % self.source.n_lights)

    def get_blocks(self, pairs: np.ndarray, starts: np.ndarray, length: int, *, device=None):
        """Blocks of consecutive texels of different images, side by side: float32 ``(B, G * length, 3)``.

        Block ``g`` holds the flat texels ``starts[g], starts[g] + 1, ..., starts[g] + length - 1``
        (modulo ``H * W``) of the ``B`` images ``pairs[g]`` (int ``(G, B, 2)``): ``out[b, g * length + j]``
        is texel ``(starts[g] + j) mod (H * W)`` of image ``pairs[g, b]``. Contiguous reads from the
        cache; an uncached BTF answers with :meth:`~dynbtf.data.base.BTFSource.read_texels` (a DFMF file
        computes just these texels from its factors). A NumPy array, or a tensor on ``device`` if given.
        """
        pairs = np.asarray(pairs, dtype=np.int64)
        starts = np.asarray(starts, dtype=np.int64)
        if pairs.ndim != 3 or pairs.shape[2] != 2 or starts.shape != (pairs.shape[0],):
            raise InputError(f"get_blocks: expected pairs (G, B, 2) and starts (G,), got {pairs.shape} and "
                             f"{starts.shape}")
        if not 1 <= length <= self.n_texels:
            raise InputError(f"get_blocks: length {length} must be in [1, {self.n_texels}]")
        groups, b = pairs.shape[:2]
        if not self._all_cached(pairs):
            texels = (starts[:, None] + np.arange(length)[None, :]) % self.n_texels
            out = self.source.read_texels(pairs, texels, device=device)  # (G, B, n, 3)
            return out.transpose(0, 1).reshape(b, groups * length, 3) if device is not None else \
                np.ascontiguousarray(out.transpose(1, 0, 2, 3)).reshape(b, groups * length, 3)
        rows = pairs[..., 0] * self.source.n_lights + pairs[..., 1]                       # (G, B)
        out = np.empty((b, groups * length, 3), dtype=np.float32)
        gather = _native_gather()
        if gather is not None:  # one pass that converts while it copies (no index arrays)
            rows = np.ascontiguousarray(rows, dtype=np.int64)
            starts = np.ascontiguousarray(starts, dtype=np.int64)
            code = gather(self._cache.ctypes.data, self._cache.shape[0], self.n_texels, 3, rows.ctypes.data, groups,
                          b, starts.ctypes.data, length, out.ctypes.data)
            if code:
                raise InputError(f"get_blocks: image rows outside the cache's {self._cache.shape[0]} images")
        else:  # one gather of flat (image, texel) rows, converted after selecting
            texels = (starts[:, None] + np.arange(length)[None, :]) % self.n_texels          # (G, length)
            flat = rows.T[:, :, None] * self.n_texels + texels[None, :, :]                    # (B, G, length)
            out[:] = np.take(self._cache.reshape(-1, 3), flat.reshape(-1), axis=0).reshape(out.shape)
        return _on(out, device)

    def _all_cached(self, pairs: np.ndarray) -> bool:
        if not self.cached:
            return False
        rows = (pairs[..., 0] * self.source.n_lights + pairs[..., 1]).reshape(-1)
        if not self._filled[rows].all():
            self.fill(pairs.reshape(-1, 2))
        return True

    def get(self, pairs: np.ndarray, texels: np.ndarray | None = None, *, device=None):
        """Images of ``pairs`` (int ``(B, 2)``) as float32 ``(B, N, 3)``, optionally at flat ``texels`` only.

        A NumPy array, or a tensor on ``device`` if given. Uncached BTFs answer with
        :meth:`~dynbtf.data.base.BTFSource.read_texels` (whole images when ``texels`` is None).
        """
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if self._all_cached(pairs):
            rows = pairs[:, 0] * self.source.n_lights + pairs[:, 1]
            if texels is None:
                return _on(self._cache[rows].astype(np.float32), device)
            # one gather of flat (image, texel) rows, converted after selecting (torch's float16 conversion is
            # vectorized; NumPy's fancy indexing and conversion took 5x as long)
            import torch

            texels = np.asarray(texels, dtype=np.int64)
            if texels.size and (texels.min() < 0 or texels.max() >= self.n_texels):
                raise InputError(f"get: texel indices must be in [0, {self.n_texels}), got {texels.min()} .. "
                                 f"{texels.max()}")
            flat = torch.from_numpy((rows[:, None] * self.n_texels + texels[None, :]).reshape(-1))
            out = torch.from_numpy(self._cache).view(-1, 3).index_select(0, flat).float()
            out = out.view(len(rows), len(texels), 3)
            return out.numpy() if device is None else out.to(device)
        texels = np.arange(self.n_texels) if texels is None else np.asarray(texels, dtype=np.int64)
        return self.source.read_texels(pairs, texels, device=device)


@functools.lru_cache(maxsize=1)
def _native_gather():
    """``dynbtf_gather_blocks_f16`` of the native ``texel_blocks`` kernel (see its source), or None where no
    kernel builds (then NumPy gathers)."""
    from ..decoder.native import load_library

    library = load_library("texel_blocks")
    if library is None:
        return None
    fn = library.dynbtf_gather_blocks_f16
    fn.restype = ctypes.c_int
    fn.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int32, ctypes.c_void_p, ctypes.c_int64,
                   ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p]
    return fn


def _on(array: np.ndarray, device):
    """``array`` itself, or as a tensor on ``device``."""
    if device is None:
        return array
    import torch

    return torch.from_numpy(array).to(device)
