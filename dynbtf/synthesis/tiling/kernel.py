"""The CPU kernel of plain tiling (numba): the periodic bilinear fetch of the exemplar at any uv."""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from ..base import check_uv
from ..kernels import CACHE_LINE, bilinear_periodic, prefetch, wrap

__all__ = ["tile_fetch"]


#: Queries per parallel chunk, and how many queries ahead of the one being fetched its texels are prefetched.
CHUNK, AHEAD = 256, 16


@numba.njit(inline="always")
def _prefetch_texels(flat, uv, n, ph, pw, nc, one_line):
    """Issue the reads of query ``n``'s four texels (and each one's last channel when a texel may straddle two
    cache lines)."""
    c0 = wrap(np.int64(math.floor((uv[n, 0] - math.floor(uv[n, 0])) * pw - 0.5)), pw)  # in [-1, pw - 1] before
    r0 = wrap(np.int64(math.floor((uv[n, 1] - math.floor(uv[n, 1])) * ph - 0.5)), ph)
    c1 = wrap(c0 + 1, pw)
    r1 = wrap(r0 + 1, ph)
    for r in (r0, r1):
        for c in (c0, c1):
            prefetch(flat, (r * pw + c) * nc)
            if not one_line:
                prefetch(flat, (r * pw + c) * nc + nc - 1)


@numba.njit(parallel=True, cache=True, nogil=True)
def _tile_kernel(uv, plane, out):
    n_queries = uv.shape[0]
    ph, pw, nc = plane.shape
    flat = plane.reshape(ph * pw * nc)
    one_line = (flat.ctypes.data % CACHE_LINE == 0) and (CACHE_LINE % (4 * nc) == 0)
    for chunk in numba.prange((n_queries + CHUNK - 1) // CHUNK):
        start = chunk * CHUNK
        stop = min(start + CHUNK, n_queries)
        # at random uv the texels are cache misses: each query's are requested AHEAD queries before they are read,
        # so that their latencies overlap the fetches in between
        for n in range(start, min(start + AHEAD, stop)):
            _prefetch_texels(flat, uv, n, ph, pw, nc, one_line)
        for n in range(start, stop):
            if n + AHEAD < stop:
                _prefetch_texels(flat, uv, n + AHEAD, ph, pw, nc, one_line)
            u = uv[n, 0]
            v = uv[n, 1]
            bilinear_periodic(plane, (u - math.floor(u)) * pw, (v - math.floor(v)) * ph, out, n)


def tile_fetch(uv: np.ndarray, plane: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Bilinear periodic fetch of ``plane (H, W, C)`` float32 at ``uv (N, 2)`` float64 -> ``(N, C)`` float32.

    The fused twin of :func:`dynbtf.texture.fetch_wrap` (the fraction of ``uv`` is
    taken in float64, so any ``uv`` is exact); ``uv`` is checked like :func:`lattice_blend`'s. A plane aligned to
    cache lines (:func:`~dynbtf.synthesis.kernels.cache_aligned`) is read with half the prefetches.
    """
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    check_uv(torch.from_numpy(uv))
    if out is None:
        out = np.empty((uv.shape[0], plane.shape[2]), dtype=np.float32)
    _tile_kernel(uv, np.ascontiguousarray(plane, dtype=np.float32), out)
    return out
