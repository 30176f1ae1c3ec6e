"""The CPU kernel of cell quilting (numba): the cell, its hashed offset, the cuts, one bilinear fetch."""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from ..base import check_uv
from ..hash import MASK32, seed_state
from ..kernels import jit_fold_coordinate, split_repeat, bilinear_periodic

__all__ = ["cell_quilt"]


# ---------------------------------------------------------------- cell quilting (dynbtf.synthesis.cell_quilting)
@numba.njit(inline="always")
def _cell_choice(cell_x, cell_y, state, count):
    """Offset index of a cell: ``hash_vertex(cell_x, cell_y, seed) mod K`` (``state = seed_state(seed)``)."""
    return jit_fold_coordinate(jit_fold_coordinate(state, cell_x), cell_y) % count


@numba.njit(inline="always")
def _guided_cell_choice(cell_x, cell_y, state, count, guide):
    """A cell's offset index; guided (:class:`~dynbtf.synthesis.guided_blending.GuidedCellQuilting`; ``guide =
    (nx, ny, cell_labels, target, target_size, repeat)``; without labels, the hash alone), from the hashed one
    on, the first offset whose content in the cell has the target's label at the cell's centre."""
    nx, ny, cell_labels, target, target_size, repeat = guide
    own = _cell_choice(cell_x, cell_y, state, count)
    if cell_labels.shape[2] == 0:
        return own
    th, tw = target.shape
    u = (np.float64(cell_x) + 0.5) / nx
    v = (np.float64(cell_y) + 0.5) / ny
    if repeat:
        u = u - math.floor(u / target_size) * target_size
        v = v - math.floor(v / target_size) * target_size
    col = np.int64(math.floor(u / target_size * tw))
    row = np.int64(math.floor(v / target_size * th))
    if repeat:
        col, row = col % tw, row % th
    else:
        col, row = min(max(col, 0), tw - 1), min(max(row, 0), th - 1)
    wanted = target[row, col]
    i, j = cell_x % nx, cell_y % ny
    for step in range(count):
        k = (own + step) % count
        if cell_labels[i, j, k] == wanted:
            return k
    return own


@numba.njit(parallel=True, cache=True, nogil=True)
def _cell_quilt_kernel(uv, plane, offsets, vertical, horizontal, nx, ny, mx, my, state, out, cell_labels, target,
                       target_size, repeat):
    n_queries = uv.shape[0]
    ph, pw, nc = plane.shape
    count = offsets.shape[0]
    tx = pw // nx
    ty = ph // ny
    guide = (nx, ny, cell_labels, target, target_size, repeat)
    for n in numba.prange(n_queries):
        wu, fu = split_repeat(uv[n, 0])
        wv, fv = split_repeat(uv[n, 1])
        pos_x = fu * pw
        pos_y = fv * ph
        texel_x = min(np.int64(math.floor(pos_x)), pw - 1)
        texel_y = min(np.int64(math.floor(pos_y)), ph - 1)
        col = texel_x // tx
        row = texel_y // ty
        local_x = texel_x - col * tx
        local_y = texel_y - row * ty
        cell_x = wu * nx + col
        cell_y = wv * ny + row
        own = _guided_cell_choice(cell_x, cell_y, state, count, guide)
        side_x = 0
        if local_x < mx:
            if local_x < vertical[col, row, _guided_cell_choice(cell_x - 1, cell_y, state, count, guide), own, local_y]:
                side_x = -1
        elif local_x >= tx - mx:
            right = _guided_cell_choice(cell_x + 1, cell_y, state, count, guide)
            if local_x - tx >= vertical[(col + 1) % nx, row, own, right, local_y]:
                side_x = 1
        side_y = 0
        if local_y < my:
            lower = _guided_cell_choice(cell_x, cell_y - 1, state, count, guide)
            if local_y < horizontal[col, row, lower, own, local_x]:
                side_y = -1
        elif local_y >= ty - my:
            upper = _guided_cell_choice(cell_x, cell_y + 1, state, count, guide)
            if local_y - ty >= horizontal[col, (row + 1) % ny, own, upper, local_x]:
                side_y = 1
        chosen = own if side_x == 0 and side_y == 0 else \
            _guided_cell_choice(cell_x + side_x, cell_y + side_y, state, count, guide)
        bilinear_periodic(plane, pos_x + offsets[chosen, 0], pos_y + offsets[chosen, 1], out, n)


def cell_quilt(uv: np.ndarray, plane: np.ndarray, offsets: np.ndarray, vertical: np.ndarray, horizontal: np.ndarray,
               cells: tuple[int, int], margin: tuple[int, int], seed: int, out: np.ndarray | None = None,
               guidance: tuple | None = None) -> np.ndarray:
    """Fused cell quilting (:class:`dynbtf.synthesis.cell_quilting.CellQuilting`): ``uv (N, 2)`` float64 -> ``(N, C)`` float32.

    ``plane (H, W, C)`` float32, ``offsets (K, 2)`` int64, the cut tables int16 as in
    :class:`~dynbtf.synthesis.cell_quilting.CellTables`; same cells, hashes and read positions as the
    torch reference path, the bilinear fetch as :func:`tile_fetch`'s. ``guidance`` (optional): ``(cell_labels
    (nx, ny, K) int32, target (Ht, Wt) int32, target_size, repeat)`` of a guided struct
    (:class:`~dynbtf.synthesis.guided_blending.GuidedCellQuilting`).
    """
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    check_uv(torch.from_numpy(uv))
    if out is None:
        out = np.empty((uv.shape[0], plane.shape[2]), dtype=np.float32)
    if guidance is None:
        guidance = (np.zeros((1, 1, 0), np.int32), np.zeros((1, 1), np.int32), 1.0, True)
    cell_labels, target, target_size, repeat = guidance
    _cell_quilt_kernel(uv, np.ascontiguousarray(plane, dtype=np.float32), offsets, vertical, horizontal,
                       int(cells[0]), int(cells[1]), int(margin[0]), int(margin[1]),
                       np.int64(seed_state(np.int64(int(seed) & MASK32))), out,
                       np.ascontiguousarray(cell_labels, dtype=np.int32), np.ascontiguousarray(target, dtype=np.int32),
                       float(target_size), bool(repeat))
    return out
