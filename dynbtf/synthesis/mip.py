"""Footprint filtering of synthesized planes: a periodic area pyramid and its level of detail.

A query that stands for a footprint of ``F`` texels (``F`` = the side of the box it covers,
in texels of the original exemplar) should answer the average of the synthesized plane over
that box, not one point. The synthesizers answer it like a GPU's trilinear mip fetch: every
sample they read (the three lattice samples of ``linear``/``hist``/``hex``, the one fetch of
``tile``/``quilt``) is read from the pyramid level whose texels are ``F`` texels wide,
interpolated between the two nearest levels. The synthesis stays dynamic: only the exemplar
(the read plane) is filtered, the lattice, hashes and blend run per query as in the point
query.

* :func:`area_pyramid` -- level ``l`` has ``ceil(H / 2**l) x ceil(W / 2**l)`` texels, each the
  exact area average of the texels of level 0 it covers (a periodic plane, fractional texel
  boundaries where ``2**l`` does not divide the side), down to ``1 x 1`` (the mean).
* :class:`LevelOfDetail` -- footprint (texels) -> lower level index and the weight of the
  next one. Footprints of at most one texel read level 0 only (the point query). Two levels are
  mixed only in a band around the middle of each octave (:data:`BLEND_BAND`, "brilinear").

Histogram-preserving blending also needs the inverse transform of each level
(:func:`prefiltered_inverse_tables`): a filtered Gaussian value ``g`` stands for a footprint
whose Gaussian values spread around ``g`` with the variance the filter removed, ``1 - var_l``;
its answer is the mean of ``T^-1`` over that spread (Heitz & Neyret 2018, Sec. 5; Deliot &
Heitz 2019's per-level lookup table).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["trilinear_fetch", "PlanePyramid", "area_pyramid", "level_shapes", "area_matrix", "LevelOfDetail", "prefiltered_inverse_tables", "pyramid_storage_bytes", "BLEND_BAND"]

#: Default :attr:`LevelOfDetail.blend_band`: two levels are mixed in the middle 30% of each octave only.
#: On the grazing plane of ``benchmarks/bench_filtering.py`` FLIP against the 256-spp reference was the same
#: (0.0347 at 1 and 0.5, 0.0348 at 0.3), and a narrower band makes more filtered queries single-level ones, which
#: need half the texel reads and one inverse table (the filtered / point cost per query: the same benchmark).
BLEND_BAND = 0.3

#: Gauss-Hermite nodes of the per-level inverse tables (the mean of ``T^-1(g + s z)`` over ``z ~ N(0, 1)``).
QUADRATURE_NODES = 48


def area_matrix(n: int, m: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """``(m, n)`` averaging matrix: row ``j`` averages source texels over ``[j n / m, (j + 1) n / m)``.

    Rows sum to one; source texel ``i`` covers ``[i, i + 1)``.

    >>> area_matrix(4, 2).tolist()
    [[0.5, 0.5, 0.0, 0.0], [0.0, 0.0, 0.5, 0.5]]
    """
    lo = torch.arange(m, dtype=torch.float64)[:, None] * (n / m)
    hi = lo + n / m
    i = torch.arange(n, dtype=torch.float64)[None, :]
    overlap = (torch.minimum(hi, i + 1) - torch.maximum(lo, i)).clamp_min(0.0)
    return (overlap / (n / m)).to(dtype=dtype, device=device)


def level_shapes(height: int, width: int) -> list[tuple[int, int]]:
    """``(rows, columns)`` of every level of the area pyramid of a ``height x width`` plane
    (:func:`area_pyramid`): level ``l`` is ``ceil(H / 2**l) x ceil(W / 2**l)`` (at least 1), down to ``1 x 1``.

    >>> level_shapes(4, 3)
    [(4, 3), (2, 2), (1, 1)]
    """
    shapes = [(int(height), int(width))]
    level = 1
    while shapes[-1] != (1, 1):
        shapes.append((max(1, math.ceil(height / 2 ** level)), max(1, math.ceil(width / 2 ** level))))
        level += 1
    return shapes


def area_pyramid(plane: torch.Tensor) -> list[torch.Tensor]:
    """Levels ``[plane, ..., 1 x 1 mean]`` of a periodic plane ``(H, W, C)`` (float32, plane's device).

    Level ``l`` is ``ceil(H / 2**l) x ceil(W / 2**l)`` (at least 1), each texel the exact area average
    of the level-0 texels under it. Texel ``[i, j]`` of every level is centred at
    ``((j + 0.5) / W_l, (i + 0.5) / H_l)`` in fractions of one repeat, like level 0
    (:func:`dynbtf.texture.fetch_wrap`).
    """
    h, w, _ = plane.shape
    levels = [plane.to(torch.float32).contiguous()]
    source = plane.to(torch.float64)
    for mh, mw in level_shapes(h, w)[1:]:
        rows = area_matrix(h, mh, device=plane.device)
        cols = area_matrix(w, mw, device=plane.device)
        level = torch.einsum("ih,hwc,jw->ijc", rows, source, cols)
        levels.append(level.to(torch.float32).contiguous())
    return levels


def pyramid_storage_bytes(levels: list[torch.Tensor]) -> int:
    """Bytes of the levels above level 0 (what filtering adds to the read plane; 0 for no levels)."""
    return sum(t.numel() * t.element_size() for t in levels[1:])


@dataclass
class LevelOfDetail:
    """Which pyramid levels a footprint reads.

    Attributes
    ----------
    widths : float64 ``(L,)``
        Texel width of each level in level-0 texels (geometric mean of both axes): 1 for level 0,
        about ``2**l`` above.
    blend_band : float in (0, 1]
        Share of each octave (in ``log2`` of the footprint, centred between two levels) where the two
        levels are mixed; outside it one level is read ("brilinear" filtering: 1 is trilinear).
    """

    widths: np.ndarray
    blend_band: float = 1.0

    @classmethod
    def of(cls, levels: list[torch.Tensor], blend_band: float | None = None) -> "LevelOfDetail":
        h, w = levels[0].shape[:2]
        band = BLEND_BAND if blend_band is None else float(blend_band)
        return cls(np.array([math.sqrt((h / t.shape[0]) * (w / t.shape[1])) for t in levels]), band)

    def __call__(self, footprint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Footprints ``(N,)`` in level-0 texels -> lower level ``(N,)`` int32 and next-level weight ``(N,)`` float32.

        Linear in ``log2(footprint)`` between the two levels whose widths bracket it; at most one
        texel -> level 0 with weight 0 (the point query); beyond the top level -> the top level.
        """
        log_w = np.log2(self.widths)
        with np.errstate(divide="ignore"):
            log_f = np.log2(np.maximum(np.asarray(footprint, dtype=np.float64), 1.0))
        top = len(log_w) - 1
        lower = np.clip(np.searchsorted(log_w, log_f, side="right") - 1, 0, top)
        upper = np.minimum(lower + 1, top)
        span = log_w[upper] - log_w[lower]
        t = np.where(span > 0, (log_f - log_w[lower]) / np.where(span > 0, span, 1.0), 0.0)
        if self.blend_band < 1.0:  # mix the two levels only in a band around the midpoint ("brilinear")
            t = (t - 0.5) / self.blend_band + 0.5
            up = t >= 1.0
            lower = np.where(up, upper, lower)
            t = np.where(up, 0.0, t)
        return lower.astype(np.int32), np.clip(t, 0.0, 1.0).astype(np.float32)


def prefiltered_inverse_tables(transform, levels: list[torch.Tensor], g_min: float, step: float,
                               size: int) -> torch.Tensor:
    """Per-level inverse Gaussian transforms ``(L, C, size)`` float32 on the grid ``g_min + k step``.

    Level ``l`` maps a filtered Gaussian value ``g`` to ``E[T^-1(g + s_l z)]``, ``z ~ N(0, 1)``, with
    ``s_l^2 = max(0, 1 - var_l)`` the variance that filtering to level ``l`` removed from each channel
    of the Gaussianized plane (level 0: ``s = 0``, the plain inverse). ``transform`` is the
    :class:`~dynbtf.synthesis.histogram.GaussianTransform` of the plane whose pyramid ``levels`` are.
    """
    device = transform.sorted_values.device
    c = transform.sorted_values.shape[0]
    grid = (g_min + step * torch.arange(size, dtype=torch.float64, device=device))[:, None].expand(size, c)
    nodes, weights = np.polynomial.hermite_e.hermegauss(QUADRATURE_NODES)
    nodes = torch.as_tensor(nodes, dtype=torch.float64, device=device)
    weights = torch.as_tensor(weights / weights.sum(), dtype=torch.float64, device=device)
    tables = []
    for level in levels:
        var = level.reshape(-1, c).to(torch.float64).var(0, unbiased=False) if level.shape[0] * level.shape[1] > 1 \
            else torch.zeros(c, dtype=torch.float64, device=device)
        spread = (1.0 - var).clamp_min(0.0).sqrt()
        if not bool((spread > 0).any()):
            tables.append(transform.inverse(grid).T)
            continue
        # node by node: (size, C) at a time, not (K, size, C) at once -- with many channels (a spherical-harmonics
        # plane has hundreds) the whole stack is gigabytes of fresh temporaries, each page faulted in
        expected = torch.zeros_like(grid)
        for node, weight in zip(nodes, weights):
            expected += weight * transform.inverse(grid + node * spread[None, :])
        tables.append(expected.T)
    tables[0] = transform.inverse(grid).T  # level 0 is the point query's table
    return torch.stack(tables).to(torch.float32).contiguous()


def trilinear_fetch(levels: list[torch.Tensor], lod: LevelOfDetail, uv: torch.Tensor,
                    footprint: torch.Tensor) -> torch.Tensor:
    """Periodic trilinear fetch of a pyramid at ``uv (N, 2)`` (repeats of the plane) for ``footprint (N,)`` texels.

    The footprint twin of :func:`dynbtf.texture.fetch_wrap` (its bilinear fetch of each level, mixed
    between the two levels :class:`LevelOfDetail` picks) -> ``(N, C)`` float32.
    """
    from ..texture import fetch_wrap

    level, upper = lod(footprint.detach().cpu().numpy())
    level = torch.from_numpy(level.astype(np.int64)).to(uv.device)
    upper = torch.from_numpy(upper).to(uv.device)
    out = torch.zeros(uv.shape[0], levels[0].shape[-1], dtype=torch.float32, device=uv.device)
    for lv in range(len(levels)):
        for step, share in ((0, 1.0 - upper), (1, upper)):
            mask = (level + step == lv) & (share > 0)
            if bool(mask.any()):
                out[mask] += share[mask, None] * fetch_wrap(levels[lv], uv[mask]).float()
    return out


class PlanePyramid:
    """The area pyramid of one plane ``(H, W, C)`` and its :class:`LevelOfDetail`, built on first use.

    For synthesizers that read a single plane at periodic positions (tiling, quilting): their
    footprint query is :meth:`fetch` at the positions their point query reads.
    """

    def __init__(self, plane: torch.Tensor) -> None:
        self.plane = plane
        self._built: tuple[list[torch.Tensor], LevelOfDetail] | None = None

    def _levels(self) -> tuple[list[torch.Tensor], LevelOfDetail]:
        if self._built is None:
            levels = area_pyramid(self.plane)
            self._built = (levels, LevelOfDetail.of(levels))
        return self._built

    @property
    def levels(self) -> list[torch.Tensor]:
        """The pyramid's levels ``[plane, ..., 1 x 1 mean]`` (:func:`area_pyramid`)."""
        return self._levels()[0]

    @property
    def level_of_detail(self) -> LevelOfDetail:
        return self._levels()[1]

    def fetch(self, positions: torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
        """:func:`trilinear_fetch` of the pyramid at ``positions (N, 2)`` (repeats of the plane) -> ``(N, C)``."""
        return trilinear_fetch(*self._levels(), positions, footprint)
