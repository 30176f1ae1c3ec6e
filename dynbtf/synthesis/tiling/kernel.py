"""The CPU kernel of plain tiling (numba): the periodic bilinear fetch of the exemplar at any uv."""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from ..base import check_uv
from ..kernels import bilinear_periodic

__all__ = ["tile_fetch"]


@numba.njit(parallel=True, cache=True, nogil=True)
def _tile_kernel(uv, plane, out):
    n_queries = uv.shape[0]
    ph, pw, nc = plane.shape
    for n in numba.prange(n_queries):
        u = uv[n, 0]
        v = uv[n, 1]
        bilinear_periodic(plane, (u - math.floor(u)) * pw, (v - math.floor(v)) * ph, out, n)


def tile_fetch(uv: np.ndarray, plane: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Bilinear periodic fetch of ``plane (H, W, C)`` float32 at ``uv (N, 2)`` float64 -> ``(N, C)`` float32.

    The fused twin of :func:`dynbtf.texture.fetch_wrap` (the fraction of ``uv`` is
    taken in float64, so any ``uv`` is exact); ``uv`` is checked like :func:`lattice_blend`'s.
    """
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    check_uv(torch.from_numpy(uv))
    if out is None:
        out = np.empty((uv.shape[0], plane.shape[2]), dtype=np.float32)
    _tile_kernel(uv, np.ascontiguousarray(plane, dtype=np.float32), out)
    return out
