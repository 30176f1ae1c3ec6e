"""Cell quilting in Dr.Jit: :class:`~dynbtf.synthesis.cell_quilting.CellQuilting` (its numba kernel
:func:`~dynbtf.synthesis.cell_quilting.kernel.cell_quilt`) traced into the renderer's kernel.
"""

from __future__ import annotations

import numpy as np

from ...device import to_host
from ...errors import InputError
from ...jit import drjit_module, gather_channels, mi_module
from ..drjit_blocks import DrLabelField, fold_coordinate, periodic_taps, seed_literal, split_repeats
from ..tiling.drjit import DrTiling

class DrCellQuilting(DrTiling):
    """Lattice-aligned cell quilting: :class:`dynbtf.synthesis.cell_quilting.CellQuilting` (its numba kernel
    :func:`~dynbtf.synthesis.cell_quilting.kernel.cell_quilt`) in Dr.Jit.

    The same computation, step for step: ``u, v`` widened to float64 and split into whole repeats and
    fractions (:func:`split_repeats`), the texel and its cell within the repeat, the cell's index as an
    ``mi.Int64`` (``whole * n + column``: exact for any ``uv`` below ``2**52`` repeats), the offset index
    ``hash(cell) mod K`` (:func:`fold_coordinate` on the index's two 32-bit words: the library's bits); near
    a cell edge (within the margin) the neighbour's index and one cut-table entry decide whether the point
    belongs to the neighbour (or, past both cuts of a corner, to the diagonal cell); then one bilinear,
    periodic fetch of the exemplar at the shifted position. Footprint queries read the exemplar's pyramid
    at that position (:meth:`DrTiling.filtered_latent` at :meth:`texel_positions`).

    Per query: four hashes (the own cell, the nearer neighbour along ``u``, along ``v``, and the diagonal
    between them; each lane needs at most the band's neighbours, so the two columns share their first
    fold), two cut-table gathers and one fetch.

    Parameters
    ----------
    plane : ``(H, W, C)``
        The exemplar.
    offsets : int ``(K, 2)``
        The copies' texel offsets ``(dx, dy)``; ``cells``: ``(nx, ny)`` per repeat; ``margin``: ``(mx, my)`` texels;
    vertical_cuts, horizontal_cuts : int ``(nx, ny, K, K, T_y)``, ``(nx, ny, K, K, T_x)``
        As :class:`~dynbtf.synthesis.cell_quilting.CellTables`.
    seed : int
    pyramid_source : callable, optional
        As :class:`DrTiling`.
    guidance : (cell_labels, target), optional
        Guided struct (:class:`~dynbtf.synthesis.guided_blending.GuidedCellQuilting`): each cell's content label
        under each offset ``(nx, ny, K)`` and the target :class:`~dynbtf.synthesis.guided_blending.LabelField`;
        a cell takes, from its hashed offset on, the first whose content carries the target's label at the
        cell's centre (footprint queries read the pyramid at the chosen cells' positions, as unguided).
    """

    def __init__(self, plane, offsets, cells, margin, vertical_cuts, horizontal_cuts, seed: int,
                 pyramid_source=None, guidance=None) -> None:
        super().__init__(plane, pyramid_source)
        mi = mi_module()
        h, w = self.size
        self.cells = (int(cells[0]), int(cells[1]))
        self.margin = (int(margin[0]), int(margin[1]))
        nx, ny = self.cells
        self.cell_size = (w // nx, h // ny)
        offsets = np.asarray(to_host(offsets), dtype=np.int64)
        self.count = int(offsets.shape[0])

        def table(t, last):
            t = np.asarray(to_host(t), dtype=np.int32)
            if t.shape != (nx, ny, self.count, self.count, last):
                raise InputError(f"cell quilting: a cut table of shape {t.shape}, expected "
                                 f"{(nx, ny, self.count, self.count, last)}")
            return mi.Int32(np.ascontiguousarray(t).ravel())

        tx, ty = self.cell_size
        if w % nx or h % ny or not (0 < 2 * self.margin[0] <= tx and 0 < 2 * self.margin[1] <= ty):
            raise InputError(f"cell quilting: cells {self.cells} with margins {self.margin} do not fit the {h}x{w} plane")
        self.vertical = table(vertical_cuts, ty)
        self.horizontal = table(horizontal_cuts, tx)
        self.offset_x = mi.Float64(offsets[:, 0].astype(np.float64))
        self.offset_y = mi.Float64(offsets[:, 1].astype(np.float64))
        self.state = seed_literal(int(seed) & 0xFFFFFFFF)
        self.guidance = None
        if guidance is not None:
            cell_labels, target = guidance
            cell_labels = np.asarray(cell_labels, dtype=np.int32)
            if cell_labels.shape != (nx, ny, self.count):
                raise InputError(f"cell quilting: cell labels of shape {cell_labels.shape}, expected "
                                 f"{(nx, ny, self.count)}")
            self.guidance = (mi.Int32(np.ascontiguousarray(cell_labels).ravel()), DrLabelField(target))

    @classmethod
    def of(cls, synthesizer) -> "DrCellQuilting":
        """The twin of a :class:`~dynbtf.synthesis.cell_quilting.CellQuilting` (its exemplar and tables; guided
        struct's cell labels and target)."""
        t = synthesizer.prepared
        guidance = None
        if getattr(synthesizer, "target", None) is not None:
            guidance = (synthesizer.cell_labels.cpu().numpy(), synthesizer.target)
        return cls(synthesizer.exemplar, t.offsets, t.cells, t.margin, t.vertical_cuts, t.horizontal_cuts,
                   synthesizer.seed, pyramid_source=synthesizer.pyramid, guidance=guidance)

    def _guided(self, cell_x, cell_y, hashed, active):
        """A cell's offset index under guidance: from the hashed one (``mi.UInt32``) on, the first whose content in
        the cell carries the target's label at the cell's centre, else the hashed one (the numba kernel's
        ``_guided_cell_choice``)."""
        if self.guidance is None:
            return hashed
        mi, dr = mi_module(), drjit_module()
        labels, target = self.guidance
        nx, ny = self.cells
        k = self.count
        wanted = target((mi.Float64(cell_x) + 0.5) / nx, (mi.Float64(cell_y) + 0.5) / ny, active)
        i, j = cell_x % nx, cell_y % ny
        i, j = mi.UInt32(dr.select(i < 0, i + nx, i)), mi.UInt32(dr.select(j < 0, j + ny, j))
        chosen, found = mi.UInt32(hashed), dr.zeros(mi.Bool, dr.width(hashed))
        for step in range(k):
            candidate = (hashed + step) % k
            hit = (dr.gather(mi.Int32, labels, (i * ny + j) * k + candidate, active) == wanted) & ~found
            chosen = dr.select(hit, candidate, chosen)
            found = found | hit
        return chosen

    def read_positions(self, u, v, active=True):
        """:meth:`dynbtf.synthesis.cell_quilting.CellQuilting.read_positions`: texel positions ``x, y``
        (``mi.Float64`` in ``[0, W) x [0, H)``) on the exemplar and the chosen offset index (``mi.UInt32``)."""
        mi, dr = mi_module(), drjit_module()
        h, w = self.size
        nx, ny = self.cells
        tx, ty = self.cell_size
        mx, my = self.margin
        k = self.count
        (whole_u, frac_u), (whole_v, frac_v) = split_repeats(u), split_repeats(v)
        pos_x, pos_y = frac_u * w, frac_v * h
        texel_x = dr.minimum(mi.Int32(dr.floor(pos_x)), w - 1)
        texel_y = dr.minimum(mi.Int32(dr.floor(pos_y)), h - 1)
        if k == 1:  # one copy: the exemplar itself everywhere
            return pos_x, pos_y, mi.UInt32(0)
        col, row = texel_x // tx, texel_y // ty
        local_x, local_y = texel_x - col * tx, texel_y - row * ty
        cell_x = mi.Int64(whole_u) * nx + mi.Int64(col)
        cell_y = mi.Int64(whole_v) * ny + mi.Int64(row)
        # the band a lane is in (at most one per axis: 2 margin <= cell side) names its neighbour's index
        left, right = local_x < mx, local_x >= tx - mx
        lower, upper = local_y < my, local_y >= ty - my
        near_x = cell_x + dr.select(left, mi.Int64(-1), mi.Int64(1))
        near_y = cell_y + dr.select(lower, mi.Int64(-1), mi.Int64(1))
        column, column_near = fold_coordinate(self.state, cell_x), fold_coordinate(self.state, near_x)
        own = self._guided(cell_x, cell_y, fold_coordinate(column, cell_y) % k, active)
        across_x = self._guided(near_x, cell_y, fold_coordinate(column_near, cell_y) % k, active)
        across_y = self._guided(cell_x, near_y, fold_coordinate(column, near_y) % k, active)
        diagonal = self._guided(near_x, near_y, fold_coordinate(column_near, near_y) % k, active)
        # the cut of the edge between the lane's cell and that neighbour: [edge, row/column, first, second, texel]
        edge = dr.select(left, col, dr.select(col + 1 == nx, 0, col + 1))
        first, second = dr.select(left, across_x, own), dr.select(left, own, across_x)
        index = (((mi.UInt32(edge) * ny + mi.UInt32(row)) * k + first) * k + second) * ty + mi.UInt32(local_y)
        cut = dr.gather(mi.Int32, self.vertical, index, active & (left | right))
        crossed_x = (left & (local_x < cut)) | (right & (local_x - tx >= cut))
        edge = dr.select(lower, row, dr.select(row + 1 == ny, 0, row + 1))
        first, second = dr.select(lower, across_y, own), dr.select(lower, own, across_y)
        index = (((mi.UInt32(col) * ny + mi.UInt32(edge)) * k + first) * k + second) * tx + mi.UInt32(local_x)
        cut = dr.gather(mi.Int32, self.horizontal, index, active & (lower | upper))
        crossed_y = (lower & (local_y < cut)) | (upper & (local_y - ty >= cut))
        chosen = dr.select(crossed_x, dr.select(crossed_y, diagonal, across_x), dr.select(crossed_y, across_y, own))
        x = pos_x + dr.gather(mi.Float64, self.offset_x, chosen, active)
        y = pos_y + dr.gather(mi.Float64, self.offset_y, chosen, active)
        return dr.select(x >= w, x - w, x), dr.select(y >= h, y - h, y), chosen

    def texel_positions(self, u, v, active=True):
        """Where the point query at ``(u, v)`` reads the exemplar (:meth:`read_positions` without the index)."""
        x, y, _ = self.read_positions(u, v, active)
        return x, y

    def _fetch(self, u, v, active, which=None):
        h, w = self.size
        x, y = self.texel_positions(u, v, active)
        return gather_channels(self.plane, self.channels, periodic_taps(x - 0.5, y - 0.5, w, h), active, which)

    def features(self, u, v, active=True):
        """The synthesized features at ``(u, v)`` (``mi.Float`` or ``mi.Float64``): list of ``C`` mi.Float."""
        return self._fetch(u, v, active)

    def channel(self, u, v, index: int, active=True):
        """One feature channel (``mi.Float``) at ``(u, v)``."""
        return self._fetch(u, v, active, which=[index])[0]




def form(synthesizer) -> DrCellQuilting:
    """The Dr.Jit kernel of a :class:`~dynbtf.synthesis.cell_quilting.CellQuilting`."""
    return DrCellQuilting.of(synthesizer)
