"""Interpolation over a measured set of directions (the tabulated baselines' angular lookup).

The PCA and SH baselines store their angular data only at the measured
directions of the BTF (PCA: one basis vector per measured (view, light) pair; SH:
one coefficient set per measured view). To answer a query at an arbitrary
direction they blend the ``k`` nearest measured directions with
**inverse squared distance** weights

    w_i = (1 / |q - d_i|^2) / sum_j (1 / |q - d_j|^2),

where ``|q - d_i|`` is the chord distance between unit vectors (monotonic in the
angle). The blend is **exact at measured directions**: a query equal to a
measured direction (chord distance below ``1e-6``) gets weight exactly 1 on it
and 0 on the others.

This is deliberately simple (no triangulation of the measurement grid); it is
continuous wherever the set of ``k`` nearest directions does not change and
reproduces the measured data exactly, which is what the comparison needs.

:func:`check_pairs` validates lists of measured (view, light) index pairs (the
columns a tabulated baseline is fitted to).
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import InputError

__all__ = ["nearest_direction_weights", "check_pairs"]


def nearest_direction_weights(w: torch.Tensor, directions: torch.Tensor, k: int = 3,
                              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices and weights of the ``k`` measured directions nearest to ``w``.

    Parameters
    ----------
    w : ``(..., 3)``
        Query unit vectors (any float dtype, any device).
    directions : ``(M, 3)``
        Measured unit vectors, same device as ``w``.
    k : int
        Neighbours to blend (clamped to ``M``).

    Returns
    -------
    index : int64 ``(..., k)``
        Indices into ``directions``, nearest first.
    weight : ``(..., k)``
        Inverse-squared-distance weights in ``w``'s dtype, summing to 1.

    Examples
    --------
    >>> import torch
    >>> dirs = torch.eye(3)
    >>> idx, wt = nearest_direction_weights(dirs[2:], dirs, k=2)
    >>> idx.tolist(), wt.tolist()
    ([[2, 0]], [[1.0, 0.0]])
    """
    k = min(int(k), int(directions.shape[0]))
    batch = w.shape[:-1]
    q = w.reshape(-1, 3)
    dirs = directions.to(q.dtype)
    index = torch.topk(q @ dirs.T, k, dim=-1).indices  # (N, k), nearest = largest cosine
    diff = q[:, None, :] - dirs[index]  # exact chord vectors (no cancellation in 1 - cos)
    dist2 = (diff * diff).sum(-1)
    inv = 1.0 / dist2.clamp_min(1e-12)
    weight = inv / inv.sum(-1, keepdim=True)
    on_measured = dist2[:, :1] < 1e-12  # the nearest one is (numerically) the query itself
    first = torch.zeros_like(weight)
    first[:, 0] = 1.0
    weight = torch.where(on_measured, first, weight)
    return index.reshape(*batch, k), weight.reshape(*batch, k)


def check_pairs(btf, pairs) -> np.ndarray:
    """Validated ``(P, 2)`` int64 (view, light) index pairs of ``btf`` (a BTFSource).

    ``None`` means all pairs, view-major. Anything else must be a non-empty
    integer array of in-range indices, else :class:`InputError` says what is wrong.
    """
    if pairs is None:
        return np.array(list(btf.pairs()), dtype=np.int64).reshape(-1, 2)
    arr = np.asarray(pairs)
    if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) == 0 or not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"pairs: expected a non-empty (P, 2) integer array of (view, light) indices, got {arr.shape}")
    bad = (arr[:, 0] < 0) | (arr[:, 0] >= btf.n_views) | (arr[:, 1] < 0) | (arr[:, 1] >= btf.n_lights)
    if bad.any():
        raise InputError(f"pairs: {int(bad.sum())} pair(s) out of range for {btf.name} "
                         f"({btf.n_views} views x {btf.n_lights} lights), e.g. {arr[bad][0].tolist()}")
    return arr.astype(np.int64)
