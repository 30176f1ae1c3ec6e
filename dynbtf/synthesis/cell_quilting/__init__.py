"""Lattice-aligned cell quilting: dynamic synthesis that keeps weaves, tiles and bricks intact.

Blending methods (``hist``, ``hex``) mix three copies of the exemplar at unrelated offsets,
so a structured exemplar's yarns and joints ghost into each other. This method never blends.
The plane is cut into a grid of **cells**, ``cells = (nx, ny)`` per exemplar repeat (so a
cell is ``T_x = W / nx`` by ``T_y = H / ny`` texels and the grid is fixed to the repeats);
every cell shows the exemplar shifted by one of ``K`` **lattice offsets**, chosen per cell
by the integer hash of the cell's index and the seed (:mod:`.hash`)::

    features(p) = E(p + o[k(cell(p))])        (texels, E read with wrap addressing)

The offsets are the exemplar's own translational lattice: ``o[0] = (0, 0)`` and the
strongest peaks of its autocorrelation (:mod:`.structure`), measured on a ``guide`` when one is
given: what the plane looks like, e.g. a fitted model's colours decoded under a few lights
(:class:`dynbtf.infinite_btf.SynthesizedBTF` passes them). A fitted feature plane spreads its
variance over many channels, fine detail included, so its own autocorrelation peaks are weaker
(0.31 at the simulated woven fabric's lattice against 0.96 for its decoded colours). A copy shifted by a lattice
vector puts every yarn, joint and tile edge where the unshifted copy has one, so neighbouring
cells continue each other's structure and differ only in the elements' own variation
(each tile's tint, each brick's colour, each thread's twist).

Where two cells meet, the border is a **minimum-error seam** (Efros & Freeman 2001's cut, here
free to run along a row as well: :func:`~dynbtf.synthesis.quilting.min_error_seam`) through a band of
``margin`` texels on either side of the straight cell edge, found off-line for every pair of offsets and
every position of the edge within the repeat, so the seam runs where the two copies agree: along a grout
line, between yarns, and down a running bond's staggered head joints and along its bed joints, so that every
brick comes whole from one copy. Agreement alone would let a seam cut through two bricks of one colour (a two-tone
brick under another light), so a seam also pays for every texel it runs through off the exemplar's joints
(:func:`joint_crossing`), and crosses an element only where its band holds no path along the joints. A query needs its own cell's hash, and near an edge the neighbour's hash and
one table entry; it reads one bilinear sample. Where the two cuts of a corner both claim
a point, it takes the diagonal cell.

Tables (built once per exemplar, guide and parameters, ``prepared``; a compiled material stores them, and the
material stage's one cache shares them between seeds): the offsets ``(K, 2)``,
the vertical edges' cuts ``(nx, ny, K, K, T_y)`` and the horizontal edges' ``(nx, ny, K, K, T_x)``
(int16, texels relative to the straight edge). Texel density is the exemplar's; any
``uv`` below ``2**52`` repeats is exact (the cell index is an int64 computed from the repeat
index and the fraction, as the lattice methods do).

Footprint queries read the exemplar's area pyramid at the point query's read position
(:meth:`read_uv`), as :class:`~dynbtf.synthesis.tiling.Tiling`'s do (this class extends it).

Examples
--------
>>> import torch
>>> element = torch.rand(8, 8, 3)
>>> weave = element.repeat(4, 4, 1) + 0.05 * torch.rand(32, 32, 3)
>>> synth = CellQuilting(weave, seed=1)
>>> synth.prepared.offsets.shape[1], synth(torch.tensor([[0.3, 0.6], [1e9 + 0.3, 0.6]], dtype=torch.float64)).shape
(2, torch.Size([2, 3]))
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ...errors import InputError
from ...tables import Table, TableError, check_tables
from ...texture import fetch_wrap
from ..base import register_synthesizer
from ..hash import hash_vertex
from ..lattice import split_uv
from ..quilting import min_error_seam
from ..elements import check_element_grid, check_variation, element_gain, element_grid, whole_element_size
from ..structure import StructureAnalysis, analyze_structure
from ..tiling import Tiling

__all__ = ["CellQuilting", "CellTables", "build_cell_tables", "check_guide", "copy_spread", "elements_of",
           "joint_crossing", "DEFAULT_OFFSETS", "MIN_CELL_TEXELS", "SPREAD_WEIGHT", "CROSSING_WEIGHT"]

#: Default number of lattice offsets a cell chooses from (``K``).
DEFAULT_OFFSETS = 16
#: Smallest cell side in texels: the cut bands (a quarter of the cell on each side of an edge) need room.
MIN_CELL_TEXELS = 8
#: Peaks at least this share of the strongest one are lattice offsets (the rest are the variation's).
PEAK_SHARE = 0.5
#: Most offsets a stored table may have (the cut tables grow as ``K^2``).
MAX_OFFSETS = 256


@dataclass
class CellTables:
    """What a cell-quilting query reads besides the exemplar (see the module docstring).

    Attributes
    ----------
    offsets : int64 ``(K, 2)``
        ``(dx, dy)`` texel offsets of the copies, ``offsets[0] = (0, 0)``; ``dx in [0, W)``, ``dy in [0, H)``.
    cells : (nx, ny)
        Cells per exemplar repeat along ``u`` and ``v``.
    margin : (mx, my)
        Half-width in texels of the cut bands of vertical and horizontal edges.
    vertical_cuts : int16 ``(nx, ny, K, K, T_y)``
        ``[i, j, a, b, r]``: on the edge at the start of cell column ``i`` (between a cell with offset
        ``a`` on its left and ``b`` on its right) in cell row ``j``, texel row ``r`` of the cell, the first
        texel that belongs to the right cell, relative to the straight edge (``-mx <= c < mx``).
    horizontal_cuts : int16 ``(nx, ny, K, K, T_x)``
        ``[i, j, a, b, s]``: the same for the edge at the start of cell row ``j`` (lower cell ``a``,
        upper ``b``) in cell column ``i``, texel column ``s``.
    strength : float
        The exemplar's structure strength (:func:`~dynbtf.synthesis.structure.analyze_structure`).
    peak_values : float64 ``(K,)``
        The autocorrelation at each offset (1 for ``(0, 0)``).
    build_seconds : float
        Wall time of the construction.
    element_grid : float64 ``(6,)`` or None
        The elements' rows, columns, row shift and placement, and ``joints``, int8 ``(H, W)``, 1 on the joints
        (:func:`~dynbtf.synthesis.elements.element_grid` of the offsets and the exemplar's appearance): what the
        per-element variation reads. None in materials compiled before elements were tabulated.
    """

    offsets: torch.Tensor
    cells: tuple[int, int]
    margin: tuple[int, int]
    vertical_cuts: torch.Tensor
    horizontal_cuts: torch.Tensor
    strength: float
    peak_values: np.ndarray
    build_seconds: float = 0.0
    element_grid: torch.Tensor | None = None
    joints: torch.Tensor | None = None

    #: How these tables were obtained: "built" (here) or "compiled" (read from a compiled material, which the
    #: material stage's one cache also shares between seeds: :mod:`dynbtf.material.cache`).
    source: str = "built"

    ARRAYS = ("offsets", "cells", "margin", "vertical_cuts", "horizontal_cuts", "strength", "peak_values",
              "build_seconds", "element_grid", "joints")

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The tables as named numpy arrays (what a compiled material stores)."""
        return {"offsets": self.offsets.numpy(), "cells": np.array(self.cells, dtype=np.int64),
                "margin": np.array(self.margin, dtype=np.int64), "vertical_cuts": self.vertical_cuts.numpy(),
                "horizontal_cuts": self.horizontal_cuts.numpy(), "strength": np.array(self.strength),
                "peak_values": np.asarray(self.peak_values, dtype=np.float64), "build_seconds": np.array(self.build_seconds)} \
            | ({} if self.element_grid is None else {"element_grid": self.element_grid.numpy(),
                                                      "joints": self.joints.numpy()})

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], source: str) -> "CellTables":
        return cls(offsets=torch.from_numpy(arrays["offsets"].astype(np.int64)),
                   cells=tuple(int(n) for n in arrays["cells"]), margin=tuple(int(m) for m in arrays["margin"]),
                   vertical_cuts=torch.from_numpy(arrays["vertical_cuts"].astype(np.int16)),
                   horizontal_cuts=torch.from_numpy(arrays["horizontal_cuts"].astype(np.int16)),
                   strength=float(arrays["strength"]), peak_values=arrays["peak_values"],
                   build_seconds=float(arrays["build_seconds"]), source=source,
                   element_grid=None if "element_grid" not in arrays
                   else torch.from_numpy(arrays["element_grid"].astype(np.float64)),
                   joints=None if "joints" not in arrays else torch.from_numpy(arrays["joints"].astype(np.int8)))

    @classmethod
    def rules(cls, arrays: dict[str, torch.Tensor], height: int, width: int) -> list[Table]:
        """The rules of :meth:`to_arrays` (as tensors) for an ``height x width`` exemplar: ``K`` from the stored
        offsets (at most :data:`MAX_OFFSETS`, a relation), the cut tables' sizes from the stored cells and margins."""
        def values(name, n):  # n stored integers, or None where the table is not that yet
            a = arrays.get(name)
            ok = isinstance(a, torch.Tensor) and a.dtype == torch.int64 and tuple(a.shape) == (n,)
            return [int(v) for v in a] if ok else None

        offsets = arrays.get("offsets")
        k = offsets.shape[0] if isinstance(offsets, torch.Tensor) and offsets.ndim == 2 else None
        side = max(height, width)
        cells, margin = values("cells", 2), values("margin", 2)
        tx, ty = ((width // cells[0], height // cells[1]) if cells and min(cells) >= 1 else (None, None))
        nx, ny = cells if cells else (None, None)
        mx, my = margin if margin else (0, 0)
        return [Table("offsets", torch.int64, (k, 2), 0, side - 1),
                Table("cells", torch.int64, (2,), 1, side), Table("margin", torch.int64, (2,), 1, side),
                Table("vertical_cuts", torch.int16, (nx, ny, k, k, ty), -mx, mx - 1),
                Table("horizontal_cuts", torch.int16, (nx, ny, k, k, tx), -my, my - 1),
                Table("strength", torch.float64, ()), Table("peak_values", torch.float64, (k,)),
                Table("build_seconds", torch.float64, (), 0.0)] + \
            ([] if "element_grid" not in arrays and "joints" not in arrays else  # (materials before them lack both)
             [Table("element_grid", torch.float64, (6,), 0.0, float(max(height, width))),
              Table("joints", torch.int8, (height, width), 0, 1)])

    @classmethod
    def relations(cls, arrays: dict[str, torch.Tensor], height: int, width: int) -> str | None:
        """What is wrong between tables that each follow :meth:`rules` (cells that do not divide the exemplar,
        margins wider than a cell, an offset outside it, a first offset other than ``(0, 0)``), or None."""
        if arrays["offsets"].shape[0] > MAX_OFFSETS:
            return f"table 'offsets': {arrays['offsets'].shape[0]} offsets, expected at most {MAX_OFFSETS}"
        nx, ny = (int(v) for v in arrays["cells"])
        mx, my = (int(v) for v in arrays["margin"])
        if width % nx or height % ny:
            return f"table 'cells': {nx} x {ny} cells do not divide the {width} x {height} exemplar"
        if mx > width // nx // 2 or my > height // ny // 2:
            return f"table 'margin': ({mx}, {my}) texels, expected at most half a cell ({width // nx // 2}, {height // ny // 2})"
        offsets = arrays["offsets"]
        if bool((offsets[:, 0] >= width).any()) or bool((offsets[:, 1] >= height).any()):
            return f"table 'offsets': an offset outside the {width} x {height} exemplar"
        if offsets[0].tolist() != [0, 0]:
            return f"table 'offsets': the first offset is {offsets[0].tolist()}, expected [0, 0]"
        if "element_grid" in arrays:
            return check_element_grid(arrays["element_grid"], height, width)
        return None

    @classmethod
    def check_arrays(cls, arrays: dict, height: int, width: int) -> None:
        """Hold stored tables (NumPy arrays or tensors) to :meth:`rules` and :meth:`relations`; raises
        :class:`~dynbtf.tables.TableError` naming the table."""
        arrays = {k: torch.from_numpy(np.array(v)) if isinstance(v, np.ndarray) else v for k, v in arrays.items()}
        check_tables(arrays, cls.rules(arrays, height, width))
        problem = cls.relations(arrays, height, width)
        if problem is not None:
            raise TableError(problem)

    @property
    def count(self) -> int:
        """``K``, the number of offsets."""
        return int(self.offsets.shape[0])

    def storage_bytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.offsets, self.vertical_cuts, self.horizontal_cuts))


def _cells_per_repeat(side: int, cells, axis: str) -> int:
    """Validate/choose the cells per repeat along one axis (``side`` texels)."""
    if cells == "auto":
        for n in (2, 1):  # two cells per repeat where the side allows it: more variety, cuts far apart
            if side % n == 0 and side // n >= max(MIN_CELL_TEXELS, 16 if n > 1 else 0):
                return n
        return 1
    if isinstance(cells, bool) or not isinstance(cells, (int, np.integer)) or int(cells) < 1:
        raise InputError(f"cells: expected a positive integer or 'auto', got {cells!r}")
    n = int(cells)
    if side % n:
        raise InputError(f"cells: {n} cells per repeat do not divide the exemplar's {side} texels along {axis}; "
                         f"expected a divisor of {side}")
    if side // n < MIN_CELL_TEXELS:
        raise InputError(f"cells: {n} cells per repeat make {side // n}-texel cells along {axis}; cells need at least "
                         f"{MIN_CELL_TEXELS} texels (an exemplar of at least {MIN_CELL_TEXELS * n} texels, or fewer cells)")
    return n


def _bands_reach_joints(grid: np.ndarray, side: int, n: int, margin: float, axis: str) -> bool:
    """Whether ``n`` cells per repeat along ``axis`` (``side`` texels) let every seam follow a joint: each cell
    edge's band (``margin`` of the cell on either side, one texel spare) holds, in every row of the element
    ``grid`` (:func:`~dynbtf.synthesis.elements.element_grid`), a head joint (``u``: the rows' own shifts) or a
    bed joint (``v``). An axis without elements (one per repeat) passes: there are no joints to follow.

    A running bond of 16-texel bricks has head joints 8 texels apart in alternate rows: two 32-texel cells (8-texel
    bands) leave the seams one texel short of half the rows' joints, where they must cross a brick; one cell
    (16-texel bands) does not."""
    columns, rows, p, q, phase_x, phase_y = (float(v) for v in grid)
    count = columns if axis == "u" else rows
    if count <= 1:
        return True
    period = side / count  # an element's width (u) or a row's height (v)
    shifts = [(r * p / q) % 1.0 for r in range(int(rows))] if axis == "u" else [0.0]
    phase = phase_x if axis == "u" else phase_y
    reach = max(1, int(margin * side / n)) - 1
    for edge in np.arange(n) * side / n:
        for shift in shifts:  # this row's joints: phase + (shift + k) period
            offset = (edge - phase - shift * period) % period
            if min(offset, period - offset) > reach:
                return False
    return True


def lattice_offsets(analysis: StructureAnalysis, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``(K, 2)`` int64 offsets ``(dx, dy)``: ``(0, 0)`` and up to ``count - 1`` strongest peaks, and their values.

    Only peaks of at least :data:`PEAK_SHARE` times the strongest are lattice vectors; an exemplar
    with none (or a constant one) has the single offset ``(0, 0)`` (the method then tiles).
    """
    chosen = [(0, 0)]
    values = [1.0]
    for dx, dy, value in analysis.peaks:
        if len(chosen) >= count or value < PEAK_SHARE * analysis.strength or value <= 0.0:
            break
        chosen.append((dx, dy))
        values.append(value)
    return np.array(chosen, dtype=np.int64), np.array(values)


def _standardized(plane: np.ndarray) -> np.ndarray:
    """Channels minus their mean over their standard deviation, all divided by ``sqrt(channels)``."""
    z = (plane - plane.mean((0, 1))) / np.maximum(plane.std((0, 1)), 1e-12)
    return z / np.sqrt(plane.shape[-1])


def elements_of(appearance: np.ndarray, offsets: int = DEFAULT_OFFSETS) -> tuple[np.ndarray, float]:
    """The element grid (:func:`~dynbtf.synthesis.elements.element_grid`) that ``struct`` finds in an exemplar of
    appearance ``appearance (H, W, C)`` (its feature plane, or images of a BTF as channels), and the exemplar's
    structure strength (:func:`~dynbtf.synthesis.structure.analyze_structure`): the same lattice, from the same
    ``offsets`` strongest peaks, as :func:`build_cell_tables`."""
    appearance = np.asarray(appearance, dtype=np.float64)
    analysis = analyze_structure(appearance)
    chosen, _ = lattice_offsets(analysis, int(offsets))
    grid, _ = element_grid(chosen, _standardized(appearance))
    return grid, float(analysis.strength)


#: Weight of the copies' spread (:func:`copy_spread`) in a seam's cost: two random copies differ by twice the
#: spread on average, so a seam weighs what all copies do there as much as what its own two copies do.
SPREAD_WEIGHT = 2.0


def copy_spread(z: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``(H, W)``: at each texel, the variance of ``z (H, W, C)`` over its copies shifted by every offset
    ``(K, 2)`` (whole texels; summed over channels): low where every copy agrees (the joints the lattice shares:
    mortar, grout, the gaps between yarns), high inside the elements, which vary from copy to copy.

    Two copies that happen to agree inside an element (two bricks of one colour) still differ from the rest
    there: a seam that also pays this spread crosses an element only where no joint is near.

    >>> z = np.zeros((4, 4, 1)); z[1:3, 1:3] = 1.0  # one element on a plain ground
    >>> copy_spread(z, np.array([[0, 0], [2, 0]]))[1].tolist()
    [0.25, 0.25, 0.25, 0.25]
    """
    total = np.zeros(z.shape, dtype=np.float64)
    squares = np.zeros(z.shape[:2], dtype=np.float64)
    for dx, dy in offsets:
        copy = np.roll(z, (-int(dy), -int(dx)), axis=(0, 1))  # copy[r, c] = z[r + dy, c + dx]
        total += copy
        squares += (copy * copy).sum(-1)
    k = len(offsets)
    return np.maximum(squares / k - ((total / k) ** 2).sum(-1), 0.0)


#: What a seam pays for each texel it runs through off the joints, in units of the mean difference of two unrelated
#: texels (:func:`joint_crossing`): so much that a seam runs along the joints wherever its band holds a path
#: along them, however alike two copies' elements happen to be.
CROSSING_WEIGHT = 4.0


def joint_crossing(joints: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``(H, W)``: what a seam pays at each texel for crossing an element there: 0 on the ``joints (H, W)`` (bool,
    :func:`~dynbtf.synthesis.elements.element_grid`'s), elsewhere :data:`CROSSING_WEIGHT` times the mean squared
    difference of two unrelated texels of ``z (H, W, C)`` (twice its total variance); all 0 when the exemplar has no
    joints (or nothing but joints).

    The copies' difference and spread alone let a seam cut through two bricks of one colour, where it is hardly
    visible in one image but makes a two-tone brick or a sliver under other lights and for the per-element
    variation; this cost keeps every element whole from one copy wherever the band reaches a joint.

    >>> joints = np.zeros((2, 3), bool); joints[:, 1] = True
    >>> joint_crossing(joints, np.array([[[0.0], [1.0], [2.0]]] * 2)).tolist()
    [[5.333333333333333, 0.0, 5.333333333333333], [5.333333333333333, 0.0, 5.333333333333333]]
    """
    joints = np.asarray(joints, dtype=bool)
    if joints.all() or not joints.any():
        return np.zeros(joints.shape)
    unrelated = 2.0 * float(z.reshape(-1, z.shape[-1]).var(0).sum())
    return np.where(joints, 0.0, CROSSING_WEIGHT * unrelated)


def check_guide(guide, exemplar: torch.Tensor) -> np.ndarray | None:
    """Validate a guide plane: None, or a finite ``(H, W, G)`` array/tensor of the exemplar's size -> float64."""
    if guide is None:
        return None
    g = guide.detach().cpu().numpy() if isinstance(guide, torch.Tensor) else np.asarray(guide)
    h, w = exemplar.shape[:2]
    if g.ndim == 2:
        g = g[..., None]
    if g.ndim != 3 or g.shape[:2] != (h, w) or not g.shape[2]:
        raise InputError(f"guide: expected a plane of shape ({h}, {w}, G) like the exemplar's, got shape {g.shape}")
    g = g.astype(np.float64)
    if not np.isfinite(g).all():
        raise InputError("guide: contains NaN or infinite values")
    return g


def build_cell_tables(exemplar: torch.Tensor, *, offsets: int = DEFAULT_OFFSETS, cells="auto",
                      margin: float = 0.25, guide=None) -> CellTables:
    """The offsets and cut tables of cell quilting for ``exemplar (H, W, C)`` (see the module docstring).

    ``offsets``: most copies ``K`` (2..64); ``cells``: cells per repeat, an int or ``(nx, ny)`` or
    ``"auto"`` (2 per axis where the side is even and at least 32 texels and the bands then reach every row's
    joints, else 1); ``margin``: half-width of the cut bands as a fraction of the cell side (0 < margin <= 0.5);
    ``guide``: optional ``(H, W, G)`` appearance of the exemplar: the lattice is found on it, and the seams weigh
    its differences equally with the exemplar's. A seam between two copies costs their difference plus the spread
    of all copies (:func:`copy_spread`) plus the crossing of elements (:func:`joint_crossing`), so that it runs
    along the joints every copy shares.
    """
    start = time.perf_counter()
    if isinstance(offsets, bool) or not isinstance(offsets, (int, np.integer)) or not 1 <= int(offsets) <= 64:
        raise InputError(f"offsets: expected an integer number of lattice offsets in [1, 64], got {offsets!r}")
    try:
        margin = float(margin)
    except (TypeError, ValueError):
        raise InputError(f"margin: expected a fraction of the cell side in (0, 0.5], got {margin!r}") from None
    if not 0.0 < margin <= 0.5:
        raise InputError(f"margin: expected a fraction of the cell side in (0, 0.5], got {margin!r}")
    h, w, _ = exemplar.shape
    cx, cy = cells if isinstance(cells, (tuple, list)) else (cells, cells)
    nx, ny = _cells_per_repeat(w, cx, "u"), _cells_per_repeat(h, cy, "v")
    guide = check_guide(guide, exemplar)
    analysis = analyze_structure(exemplar if guide is None else guide)
    chosen, values = lattice_offsets(analysis, int(offsets))
    k = chosen.shape[0]
    z = _standardized(exemplar.detach().cpu().numpy().astype(np.float64))
    if guide is not None:
        z = np.concatenate([z, _standardized(guide)], -1)

    grid, joints = element_grid(chosen, z)
    texel_cost = SPREAD_WEIGHT * copy_spread(z, chosen) + joint_crossing(joints, z)  # (H, W), what any seam pays
    if cx == "auto" and nx > 1 and not _bands_reach_joints(grid, w, nx, margin, "u"):
        nx = 1
    if cy == "auto" and ny > 1 and not _bands_reach_joints(grid, h, ny, margin, "v"):
        ny = 1
    tx, ty = w // nx, h // ny
    mx, my = max(1, int(margin * tx)), max(1, int(margin * ty))

    def band_errors(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Seam costs ``(K, K, len(rows), len(cols))`` of every two copies over a band: their squared difference
        plus :data:`SPREAD_WEIGHT` times the spread of all copies there (:func:`copy_spread`) plus the cost of
        crossing an element there (:func:`joint_crossing`)."""
        copies = np.stack([z[(rows[:, None] + dy) % h, (cols[None, :] + dx) % w] for dx, dy in chosen])
        norms = (copies * copies).sum(-1)
        cross = np.einsum("arsc,brsc->abrs", copies, copies, optimize=True)
        return (np.maximum(norms[:, None] + norms[None, :] - 2.0 * cross, 0.0)
                + texel_cost[rows[:, None] % h, cols[None, :] % w])

    vertical = np.zeros((nx, ny, k, k, ty), dtype=np.int16)
    horizontal = np.zeros((nx, ny, k, k, tx), dtype=np.int16)
    for i in range(nx):
        for j in range(ny):
            # vertical edge at x = i T_x, rows of cell row j; band columns i T_x - mx ... i T_x + mx - 1
            err = band_errors(np.arange(j * ty, (j + 1) * ty), np.arange(i * tx - mx, i * tx + mx))
            vertical[i, j] = min_error_seam(err) - mx
            # horizontal edge at y = j T_y, columns of cell column i: the transposed problem
            err = band_errors(np.arange(j * ty - my, j * ty + my), np.arange(i * tx, (i + 1) * tx))
            horizontal[i, j] = min_error_seam(np.swapaxes(err, -1, -2)) - my
    return CellTables(offsets=torch.from_numpy(chosen), cells=(nx, ny), margin=(mx, my),
                      vertical_cuts=torch.from_numpy(vertical), horizontal_cuts=torch.from_numpy(horizontal),
                      strength=analysis.strength, peak_values=values, build_seconds=time.perf_counter() - start,
                      element_grid=torch.from_numpy(grid), joints=torch.from_numpy(joints.astype(np.int8)))


def cell_choice(cell_x, cell_y, seed: int, count: int):
    """Offset index ``hash(cell_x, cell_y, seed) mod K`` of int64 cells (numpy, torch or numba scalars)."""
    return hash_vertex(cell_x, cell_y, seed) % count


@register_synthesizer("struct")
class CellQuilting(Tiling):
    """Lattice-aligned cell quilting of an exemplar plane (see the module docstring).

    Parameters
    ----------
    exemplar : ``(H, W, C)``
    seed : int, default 0
    offsets : int, default 16
        Most lattice offsets a cell chooses from (fewer when the exemplar has fewer strong peaks).
    cells : int, (int, int) or "auto", default "auto"
        Cells per exemplar repeat along u and v (must divide the exemplar's sides); "auto": 2 where
        the side is even and at least 32 texels and the seams' bands then reach a joint of every row of the
        elements (:func:`_bands_reach_joints`), else 1.
    margin : float, default 0.25
        Half-width of the cut bands, as a fraction of the cell side.
    guide : array ``(H, W, G)``, optional
        The exemplar's appearance (e.g. decoded colours): finds the lattice and guides the cuts.
    brightness, tint : float, default 0
        Per-element variation (:mod:`dynbtf.synthesis.elements`): the standard deviation of each element's
        log-brightness, and of its channels' log gains against each other (0: off). Drawn from the seed; every
        texel of one element (one brick, one tile) on the surface gets the same factor; joints none.
    fast : bool, optional
        Use the fused numba kernel (default: when the exemplar is on the CPU).
    prepared : CellTables, optional
        The ``prepared`` attribute of an earlier synthesizer of the same exemplar and parameters.
    """

    backends = {"web": f"{__name__}.web"}

    model_inputs = {"guide": "appearance"}

    #: 2: seams that may run along a row or column (:func:`~dynbtf.synthesis.quilting.min_error_seam`) and pay the
    #: copies' spread (:func:`copy_spread`), so that they follow a running bond's staggered joints. 3: the row shift
    #: fitted to every lattice offset, and ``cells="auto"`` one cell along an axis where two would leave the seams'
    #: bands short of some row's joints (:func:`_bands_reach_joints`). 4: seams pay for every texel off the joints
    #: (:func:`joint_crossing`), so that two bricks of one colour no longer make a cut through them cheap.
    tables_version = 4

    def __init__(self, exemplar, seed: int = 0, *, offsets: int = DEFAULT_OFFSETS, cells="auto", margin: float = 0.25,
                 guide=None, brightness: float = 0.0, tint: float = 0.0, fast: bool | None = None,
                 prepared: CellTables | None = None) -> None:
        super().__init__(exemplar, seed, fast=fast)
        self.brightness, self.tint = check_variation("brightness", brightness), check_variation("tint", tint)
        if fast and self.device.type != "cpu":
            raise InputError(f"fast: the fused kernel runs on the CPU; the exemplar is on {self.device}")
        if prepared is None:
            prepared = build_cell_tables(self.exemplar, offsets=offsets, cells=cells, margin=margin, guide=guide)
        elif not isinstance(prepared, CellTables):
            raise InputError(f"prepared: expected the CellTables of a 'struct' synthesizer, got {type(prepared).__name__}")
        h, w, _ = self.exemplar.shape
        nx, ny = prepared.cells
        if w % nx or h % ny or prepared.vertical_cuts.shape[-1] != h // ny or prepared.horizontal_cuts.shape[-1] != w // nx:
            raise InputError(f"prepared: its cut tables do not fit this {h}x{w} exemplar")
        if (self.brightness or self.tint) and prepared.element_grid is None:
            raise InputError("brightness, tint: these struct tables have no element map (a material compiled by an "
                             "earlier dynbtf); compile the material again")
        self.prepared = prepared
        self._numpy: tuple | None = None

    def advice(self) -> list[str]:
        """A line when the elements are not whole texels (:func:`~dynbtf.synthesis.elements.whole_element_size`):
        lattice copies shifted by whole texels then cannot line their joints up, and a model fitted with
        ``dynbtf fit --texels whole`` can."""
        grid = self.prepared.element_grid
        if grid is None:
            return []
        h, w, _ = self.exemplar.shape
        size = whole_element_size(grid, h, w)
        if size == (h, w):
            return []
        columns, rows = int(grid[0]), int(grid[1])
        return [f"struct: the elements are {w / columns:.4g} x {h / rows:.4g} texels, not whole texels, so the seams "
                f"cannot follow every joint; a model fitted with `dynbtf fit ... --texels whole` ({size[0]} x "
                f"{size[1]} texels) keeps the elements whole"]

    # ------------------------------------------------------------ evaluation
    @property
    def density(self) -> tuple[int, int]:
        """Texels per repeat ``(W, H)``."""
        return int(self.exemplar.shape[1]), int(self.exemplar.shape[0])

    def read_positions(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Where each query reads: ``(x, y)`` texels on the exemplar, float64 ``(N, 2)`` in ``[0, W) x [0, H)``,
        and the chosen offset index ``(N,)`` int64 (the torch reference path, any device)."""
        t = self.prepared
        w, h = self.density
        nx, ny = t.cells
        tx, ty = w // nx, h // ny
        mx, my = t.margin
        whole, frac = split_uv(uv)
        pos_x, pos_y = frac[:, 0] * w, frac[:, 1] * h
        texel_x = torch.clamp(torch.floor(pos_x).to(torch.int64), max=w - 1)
        texel_y = torch.clamp(torch.floor(pos_y).to(torch.int64), max=h - 1)
        col, row = texel_x // tx, texel_y // ty
        local_x, local_y = texel_x - col * tx, texel_y - row * ty
        cell_x, cell_y = whole[:, 0] * nx + col, whole[:, 1] * ny + row
        own = self.cell_choices(cell_x, cell_y)
        vertical = t.vertical_cuts.to(uv.device).to(torch.int64)
        horizontal = t.horizontal_cuts.to(uv.device).to(torch.int64)
        # vertical edges: the left one (point in the right cell) and the right one (point in the left cell)
        left = self.cell_choices(cell_x - 1, cell_y)
        right = self.cell_choices(cell_x + 1, cell_y)
        cut_left = vertical[col, row, left, own, local_y]
        cut_right = vertical[(col + 1) % nx, row, own, right, local_y]
        side_x = torch.where((local_x < mx) & (local_x < cut_left), -1,
                             torch.where((local_x >= tx - mx) & (local_x - tx >= cut_right), 1, 0))
        lower = self.cell_choices(cell_x, cell_y - 1)
        upper = self.cell_choices(cell_x, cell_y + 1)
        cut_lower = horizontal[col, row, lower, own, local_x]
        cut_upper = horizontal[col, (row + 1) % ny, own, upper, local_x]
        side_y = torch.where((local_y < my) & (local_y < cut_lower), -1,
                             torch.where((local_y >= ty - my) & (local_y - ty >= cut_upper), 1, 0))
        chosen = self.cell_choices(cell_x + side_x, cell_y + side_y)
        offsets = t.offsets.to(uv.device)
        read_x = torch.remainder(pos_x + offsets[chosen, 0].to(torch.float64), float(w))
        read_y = torch.remainder(pos_y + offsets[chosen, 1].to(torch.float64), float(h))
        return torch.stack([read_x, read_y], -1), chosen

    def variation_gain(self, points: torch.Tensor, footprint_texels: torch.Tensor | None = None) -> torch.Tensor | None:
        """The per-element RGB factors ``(N, 3)`` at ``points (N, 2)`` (exemplar repeats), or None when
        ``brightness`` and ``tint`` are 0 (:func:`~dynbtf.synthesis.elements.element_gain`)."""
        if not (self.brightness or self.tint):
            return None
        t = self.prepared
        return element_gain(points, t.element_grid.tolist(), t.joints, self.seed, self.brightness, self.tint,
                            footprint_texels)

    def cell_choices(self, cell_x: torch.Tensor, cell_y: torch.Tensor) -> torch.Tensor:
        """Offset index ``(N,)`` int64 of int64 cells (:func:`cell_choice` with this synthesizer's seed)."""
        return cell_choice(cell_x, cell_y, self.seed, self.prepared.count)

    def reference_latent(self, uv: torch.Tensor) -> torch.Tensor:
        """The torch reference path of :meth:`latent` (any device)."""
        return fetch_wrap(self.exemplar, self.read_uv(uv))

    def _tables_numpy(self) -> tuple:
        if self._numpy is None:
            t = self.prepared
            self._numpy = (self._plane_numpy, np.ascontiguousarray(t.offsets.numpy(), dtype=np.int64),
                           np.ascontiguousarray(t.vertical_cuts.numpy()), np.ascontiguousarray(t.horizontal_cuts.numpy()))
        return self._numpy

    def latent(self, uv: torch.Tensor) -> torch.Tensor:
        if not self.fast:
            return self.reference_latent(uv)
        from .kernel import cell_quilt

        plane, offsets, vertical, horizontal = self._tables_numpy()
        return torch.from_numpy(cell_quilt(uv.detach().cpu().numpy(), plane, offsets, vertical, horizontal,
                                           self.prepared.cells, self.prepared.margin, self.seed,
                                           guidance=self.kernel_guidance()))

    def kernel_guidance(self) -> tuple | None:
        """What the fused kernel's cell choice needs besides the hash (None: the hash alone)."""
        return None

    # ------------------------------------------------------------ footprint queries (Tiling's, at read_uv)
    def read_uv(self, uv: torch.Tensor) -> torch.Tensor:
        positions, _ = self.read_positions(uv)
        w, h = self.density
        return positions / positions.new_tensor([w, h])

    # ------------------------------------------------------------ reports
    def prepared_arrays(self) -> dict[str, torch.Tensor]:
        """The cut tables (:meth:`CellTables.to_arrays`) as tensors."""
        return {k: torch.from_numpy(np.array(v)) for k, v in self.prepared.to_arrays().items()}  # np.array: 0-d stays 0-d

    @classmethod
    def stored_tables(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> list[Table]:
        return CellTables.rules(arrays, plane.shape[0], plane.shape[1])

    @classmethod
    def table_relations(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> str | None:
        return CellTables.relations(arrays, plane.shape[0], plane.shape[1])

    @classmethod
    def prepared_from_arrays(cls, arrays: dict[str, torch.Tensor], device: torch.device | str = "cpu") -> CellTables:
        return CellTables.from_arrays({k: arrays[k].cpu().numpy() for k in CellTables.ARRAYS if k in arrays},
                                      source="compiled")

    def parameters(self) -> dict[str, Any]:
        t = self.prepared
        return {"offsets": t.count, "cells": list(t.cells), "margin": list(t.margin), "fast": self.fast,
                "brightness": self.brightness, "tint": self.tint,
                "structure_strength": round(t.strength, 4), "build_seconds": round(t.build_seconds, 3),
                "tables": t.source}

    def storage_bytes(self) -> int:
        return self.prepared.storage_bytes()
