"""Periodic (tileable), resolution-independent procedural noise.

Every function here defines a *continuous* function of ``uv`` on the unit torus
``[0, 1)^2`` (period 1 in ``u`` and ``v``) from an explicit seed, and samples it
on a ``(G, G)`` grid whose point ``[i, j]`` is at ``uv = ((j + 0.5) / G, (i + 0.5) / G)``
(the texel-centre convention of :mod:`dynbtf.conventions`). Because the
function is fixed before it is sampled, a material looks the same at every
grid resolution (only sampled more finely), and it wraps seamlessly.

Random numbers come from :class:`numpy.random.Generator` (PCG64) seeded by
:func:`derive_rng`, so results are identical across runs and platforms.

Examples
--------
>>> import numpy as np
>>> a = fourier_noise(32, derive_rng(0, "demo"), k_max=6)
>>> b = fourier_noise(96, derive_rng(0, "demo"), k_max=6)   # same function, 3x finer grid
>>> a.shape, bool(np.allclose(a, b[1::3, 1::3]))
((32, 32), True)
"""

from __future__ import annotations

import zlib

import numpy as np

__all__ = [
    "derive_rng",
    "grid_uv",
    "fourier_noise",
    "worley",
    "smoothstep",
    "WorleyResult",
]


def derive_rng(seed: int, stream: str) -> np.random.Generator:
    """An independent, deterministic generator for one named random stream.

    ``stream`` names what the numbers are for (e.g. ``"stone/pebbles"``), so
    adding a new stream never changes the numbers of another one.
    """
    key = zlib.crc32(stream.encode("utf-8"))
    return np.random.Generator(np.random.PCG64([int(seed) & 0xFFFFFFFF, key]))


def grid_uv(size: int) -> tuple[np.ndarray, np.ndarray]:
    """``(u, v)`` float64 arrays ``(size, size)`` of grid-point centres (``u`` along columns)."""
    c = (np.arange(size, dtype=np.float64) + 0.5) / size
    u, v = np.meshgrid(c, c)
    return u, v


def smoothstep(edge0, edge1, x):
    """Cubic Hermite step: 0 below ``edge0``, 1 above ``edge1``, smooth in between."""
    t = np.clip((np.asarray(x, dtype=np.float64) - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def fourier_noise(size: int, rng: np.random.Generator, *, k_max: int, k_min: float = 1.0,
                  slope: float = 1.0, stretch: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Gaussian periodic noise from random Fourier coefficients on integer frequencies.

    ``n(u, v) = Re sum_k c_k exp(2 pi i (k_u u + k_v v))`` over integer frequency
    vectors with ``k_min <= |k'| <= k_max`` where ``k' = (k_u * stretch[0], k_v * stretch[1])``
    (``stretch > 1`` along an axis keeps only lower frequencies along it, i.e.
    features elongated along that axis), amplitude
    ``|k'|^-slope`` (``slope = 1`` is 1/f "fractal" noise) and complex Gaussian
    coefficients drawn from ``rng``. Integer frequencies make it exactly periodic.
    The coefficients do not depend on ``size``, so the same continuous function
    is sampled at every resolution (evaluated exactly by separable DFT matrices,
    no aliasing of the definition).

    Returns
    -------
    float64 ``(size, size)``, zero mean and unit standard deviation over the torus.
    """
    k_max = int(k_max)
    ks = np.arange(-k_max, k_max + 1)
    ku, kv = np.meshgrid(ks, ks, indexing="ij")  # coefficient array indexed [ku, kv]
    coef = rng.standard_normal((2, len(ks), len(ks)))
    kk = np.hypot(ku * stretch[0], kv * stretch[1])
    band = (kk >= k_min) & (kk <= k_max)
    amp = np.where(band, np.maximum(kk, 1e-9) ** -float(slope), 0.0)
    c = (coef[0] + 1j * coef[1]) * amp
    c[k_max, k_max] = 0.0  # no DC term
    x = (np.arange(size, dtype=np.float64) + 0.5) / size
    e = np.exp(2j * np.pi * np.outer(x, ks))  # (size, 2K+1): e[j, k] = exp(2 pi i k x_j)
    # rows follow v, columns follow u: n[i, j] = sum c[ku, kv] e[j, ku] e[i, kv]
    n = np.real(e @ c.T @ e.T)
    # Re(c_k e_k + c_-k e_-k) = Re((c_k + conj(c_-k)) e_k): the variance over the torus is
    # 1/2 sum over the half plane of |c_k + conj(c_-k)|^2 = 1/4 of that sum over the full plane
    paired = c + np.conj(c[::-1, ::-1])
    power = 0.25 * float((np.abs(paired) ** 2).sum())
    return n / np.sqrt(max(power, 1e-30))


class WorleyResult:
    """Cellular (Voronoi) noise fields on a grid.

    Attributes
    ----------
    f1, f2 : float64 ``(G, G)``
        Distance to the nearest and second-nearest feature point, in units of
        one cell (so ``f1`` is roughly in ``[0, 1]``).
    cell : int64 ``(G, G)``
        Index ``cy * cells + cx`` of the nearest feature point's cell.
    cell_random : float64 ``(cells * cells, k)``
        Uniform random numbers per cell (for per-cell colour, height, ...).
    """

    def __init__(self, f1, f2, cell, cell_random):
        self.f1, self.f2, self.cell, self.cell_random = f1, f2, cell, cell_random

    @property
    def edge(self) -> np.ndarray:
        """Approximate distance to the nearest cell border, ``(f2 - f1) / 2`` (cell units)."""
        return 0.5 * (self.f2 - self.f1)


def worley(size: int, rng: np.random.Generator, *, cells: int, jitter: float = 0.9,
           warp: tuple[np.ndarray, np.ndarray] | None = None, n_random: int = 4) -> WorleyResult:
    """Periodic cellular noise with one jittered feature point per cell of a ``cells x cells`` lattice.

    Distances wrap around the torus, so the pattern tiles. ``warp`` optionally
    displaces the lookup positions by ``(du, dv)`` arrays ``(size, size)`` in uv
    units (domain warping; must itself be periodic to keep tiling).
    """
    cells = int(cells)
    pts = (np.stack(np.meshgrid(np.arange(cells), np.arange(cells), indexing="xy"), axis=-1)
           + 0.5 + jitter * (rng.random((cells, cells, 2)) - 0.5))  # [cy, cx] -> (x, y) cell units
    cell_random = rng.random((cells * cells, n_random))
    u, v = grid_uv(size)
    if warp is not None:
        u, v = u + warp[0], v + warp[1]
    x, y = u * cells, v * cells
    ix, iy = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    best = np.full((2,) + x.shape, np.inf)
    cell = np.zeros(x.shape, dtype=np.int64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            cx, cy = ix + dx, iy + dy
            wx, wy = np.mod(cx, cells), np.mod(cy, cells)
            px = pts[wy, wx, 0] + (cx - wx)
            py = pts[wy, wx, 1] + (cy - wy)
            d = np.hypot(px - x, py - y)
            closer = d < best[0]
            best[1] = np.where(closer, best[0], np.minimum(best[1], d))
            best[0] = np.where(closer, d, best[0])
            cell = np.where(closer, wy * cells + wx, cell)
    return WorleyResult(best[0], best[1], cell, cell_random)
