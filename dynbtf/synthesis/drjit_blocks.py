"""The building blocks of the synthesis methods' Dr.Jit kernels: hash, triangle lattice, inverse table, pyramid.

Each mirrors a function of :mod:`dynbtf.synthesis` operation by operation (the integer hash of
:mod:`~dynbtf.synthesis.hash` bit for bit, the float64 lattice of :mod:`~dynbtf.synthesis.lattice`,
the :class:`~dynbtf.synthesis.histogram.InverseLUT`, the area pyramid of :mod:`~dynbtf.synthesis.mip`),
so that a method's kernel (``dynbtf/synthesis/<method>/drjit.py``) evaluates what its numba kernel
evaluates. Inputs are Dr.Jit arrays of the active Mitsuba variant (:mod:`dynbtf.jit`); a vector of
``C`` channels is a list of ``C`` ``mi.Float``.
"""

from __future__ import annotations

import numpy as np

from ..device import to_host
from ..errors import InputError
from ..jit import drjit_module, flat_array, gather_channels, mi_module
from . import hash as synthesis_hash
from . import lattice as synthesis_lattice

__all__ = ["mix32", "int_words", "fold_coordinate", "seed_literal", "hash_vertex", "vertex_offsets", "split_repeats",
           "triangle_lattice", "vertex_uv", "lut_lookup", "positive_mod", "DrLevelOfDetail", "level_shares",
           "accumulate", "wrap_small", "DrPyramid", "periodic_taps", "filtering_tables", "gather_one", "DrLabelField"]


# ---------------------------------------------------------------- integer hash (dynbtf.synthesis.hash)
def mix32(x):
    """lowbias32 finalizer on ``mi.UInt32`` (arithmetic is modulo 2**32 natively)."""
    x = x ^ (x >> 16)
    x = x * synthesis_hash.MIX_MULTIPLIER_1
    x = x ^ (x >> 15)
    x = x * synthesis_hash.MIX_MULTIPLIER_2
    return x ^ (x >> 16)


def int_words(k):
    """Low and high 32-bit words (``mi.UInt32``) of an ``mi.Int32`` sign-extended to 64 bits, or of an ``mi.Int64``."""
    mi, dr = mi_module(), drjit_module()
    if dr.type_v(k) == dr.VarType.Int64:  # the casts truncate; >> is arithmetic: Python's (k >> 32) & MASK32
        return mi.UInt32(k), mi.UInt32(k >> 32)
    return mi.UInt32(k), dr.select(k < 0, mi.UInt32(0xFFFFFFFF), mi.UInt32(0))


def fold_coordinate(h, k):
    """:func:`dynbtf.synthesis.hash.fold_coordinate`: the low then the high word of ``k`` (``mi.Int32`` or
    ``mi.Int64``) folded into the hash state ``h`` (``mi.UInt32`` or a Python int)."""
    lo, hi = int_words(k)
    return mix32(mix32(h ^ lo) ^ hi)


def seed_literal(seed: int) -> int:
    """:func:`dynbtf.synthesis.hash.seed_state` of ``seed`` (a Python int: a literal of the kernel)."""
    return int(synthesis_hash.seed_state(int(seed)))


def hash_vertex(vx, vy, seed: int):
    """:func:`dynbtf.synthesis.hash.hash_vertex` for ``mi.Int32`` (or ``mi.Int64``) vertices: identical 32-bit values."""
    mi = mi_module()
    return fold_coordinate(fold_coordinate(mi.UInt32(seed_literal(seed)), vx), vy)


def vertex_offsets(vx, vy, seed: int, width: int, height: int):
    """Whole-texel offsets ``(ox, oy)`` (``mi.UInt32``) of lattice vertices, as :func:`dynbtf.synthesis.hash.vertex_offsets`."""
    h = hash_vertex(vx, vy, seed)
    return h % width, mix32(h ^ synthesis_hash.SECOND_STREAM) % height


def split_repeats(x):
    """:func:`dynbtf.synthesis.lattice.split_uv` of one coordinate: ``x`` (``mi.Float`` or ``mi.Float64``)
    widened to float64 -> whole repeats (``mi.Float64``, an integer) and the fraction in ``[0, 1)``; exact."""
    mi, dr = mi_module(), drjit_module()
    x = mi.Float64(x)
    whole = dr.floor(x)
    frac = x - whole
    carry = frac >= 1.0  # never for exact arithmetic; guards -tiny inputs
    return dr.select(carry, whole + 1.0, whole), dr.select(carry, frac - 1.0, frac)


def triangle_lattice(u, v):
    """:func:`dynbtf.synthesis.lattice.triangle_lattice` in Dr.Jit.

    ``u, v`` (``mi.Float``) are widened to float64 and split into whole repeats and
    fractions exactly as the torch code does (``|u|, |v| < 2**27``), so the
    vertices are identical and the barycentrics agree to float64 rounding.

    Returns ``([(vx, vy)] * 3 as mi.Int32, [b0, b1, b2] as mi.Float64)``.
    """
    mi, dr = mi_module(), drjit_module()
    (wu, fu), (wv, fv) = split_repeats(u), split_repeats(v)
    # 2 sqrt(3) * whole_u as integer + fraction (hi/lo split of the constant, as in torch)
    p_hi = wu * synthesis_lattice.LATTICE_SCALE_HI
    p_whole = dr.floor(p_hi)
    p_frac = (p_hi - p_whole) + wu * synthesis_lattice.LATTICE_SCALE_LO
    carry = dr.floor(p_frac)
    iu_whole, iu_frac = p_whole + carry, p_frac - carry
    kx = iu_frac + synthesis_lattice.LATTICE_SCALE * fu - 2.0 * fv
    ky = 4.0 * fv
    bx, by = dr.floor(kx), dr.floor(ky)
    fx, fy = kx - bx, ky - by
    base_x = mi.Int32(bx) + mi.Int32(iu_whole) - 2 * mi.Int32(wv)
    base_y = mi.Int32(by) + 4 * mi.Int32(wv)
    z = 1.0 - fx - fy
    lower = z > 0.0
    one = dr.select(lower, mi.Int32(0), mi.Int32(1))
    verts = [(base_x + one, base_y + one),
             (base_x + one, base_y + (1 - one)),
             (base_x + (1 - one), base_y + one)]
    bary = [dr.select(lower, z, -z), dr.select(lower, fy, 1.0 - fy), dr.select(lower, fx, 1.0 - fx)]
    return verts, bary


def vertex_uv(vx, vy):
    """Position (``mi.Float64`` pair, exemplar repeats) of lattice vertices: hex-tile centres."""
    mi = mi_module()
    x, y = mi.Float64(vx), mi.Float64(vy)
    return (x + 0.5 * y) / synthesis_lattice.LATTICE_SCALE, y / 4.0


def lut_lookup(table, size: int, channel: int, g_min: float, step: float, g, base=0):
    """:class:`dynbtf.synthesis.histogram.InverseLUT` lookup of one channel: linear interpolation, clamped.

    ``table`` is the flat ``(C, size)`` float32 table as ``mi.Float`` (or several such tables one after
    another, ``base`` (int or per-lane ``mi.UInt32``) the offset of the one to read); ``g`` an ``mi.Float``.
    """
    mi, dr = mi_module(), drjit_module()
    pos = dr.clip((g - g_min) / step, 0.0, size - 1.0)
    lo = dr.minimum(mi.UInt32(dr.floor(pos)), size - 2)
    t = pos - mi.Float(lo)
    base = base + channel * size
    x0 = dr.gather(mi.Float, table, base + lo)
    x1 = dr.gather(mi.Float, table, base + lo + 1)
    return x0 + t * (x1 - x0)


def positive_mod(k, n: int):
    """Non-negative ``k mod n`` for ``mi.Int32`` ``k`` (Python semantics, as numba's and torch's)."""
    dr = drjit_module()
    r = k % n
    return dr.select(r < 0, r + n, r)


class DrLevelOfDetail:
    """:class:`dynbtf.synthesis.mip.LevelOfDetail` per lane: footprint (texels) -> lower level, next level's weight.

    Parameters
    ----------
    lod : LevelOfDetail
        The synthesizer's level of detail (level widths and blend band).
    """

    def __init__(self, lod) -> None:
        self.log_widths = [float(x) for x in np.log2(np.asarray(lod.widths, dtype=np.float64))]
        self.blend_band = float(lod.blend_band)
        self.top = len(self.log_widths) - 1

    def __call__(self, texels):
        """``texels`` (``mi.Float``/``mi.Float64``, level-0 texels) -> lower level (``mi.UInt32``), weight of the next (``mi.Float``)."""
        mi, dr = mi_module(), drjit_module()
        log_w, top = self.log_widths, self.top
        log_f = dr.log2(dr.maximum(mi.Float64(texels), 1.0))
        lower = mi.UInt32(0)
        lw_lower, lw_upper = mi.Float64(log_w[0]), mi.Float64(log_w[min(1, top)])
        for k in range(1, top + 1):  # the widths grow with the level: the last level at or below the footprint
            above = log_f >= log_w[k]
            lower = dr.select(above, k, lower)
            lw_lower = dr.select(above, log_w[k], lw_lower)
            lw_upper = dr.select(above, log_w[min(k + 1, top)], lw_upper)
        span = lw_upper - lw_lower
        t = dr.select(span > 0.0, (log_f - lw_lower) / dr.select(span > 0.0, span, 1.0), 0.0)
        if self.blend_band < 1.0:  # the two levels are mixed only in a band around the octave's middle
            t = (t - 0.5) / self.blend_band + 0.5
            up = t >= 1.0
            lower = dr.select(up, dr.minimum(lower + 1, top), lower)
            t = dr.select(up, 0.0, t)
        return lower, mi.Float(dr.clip(t, 0.0, 1.0))

    def nearest(self, lower, weight):
        """The level nearest the footprint (``mi.UInt32``): :meth:`dynbtf.infinite_btf.SynthesizedBTF.nearest_level`."""
        dr = drjit_module()
        return lower + dr.select(weight >= 0.5, 1, 0)


def level_shares(lower, t, top: int, active):
    """``(level, share, mask)`` of each pyramid level a footprint reads: ``lower`` alone (``t=None``), or
    ``lower`` with ``1 - t`` and the next level with ``t`` (its reads masked where ``t`` is 0)."""
    dr = drjit_module()
    if t is None:
        return [(lower, None, active)]
    upper = min(lower + 1, top) if isinstance(lower, int) else dr.minimum(lower + 1, top)
    return [(lower, 1.0 - t, active), (upper, t, active & (t > 0.0))]


def accumulate(out, row, share):
    """``out + share * row`` per channel (``out=None``: nothing yet; ``share=None``: 1)."""
    if share is not None:
        row = [share * x for x in row]
    return row if out is None else [o + x for o, x in zip(out, row)]


def wrap_small(k, n):
    """``k mod n`` (``mi.UInt32``) for ``mi.Int32`` ``k`` in ``[-n, 3 n)`` and per-lane ``n``, without a division.

    (An integer division by a per-lane ``n`` traps on lanes that hold no data, e.g. a SIMD packet's tail.)
    """
    mi, dr = mi_module(), drjit_module()
    for _ in range(2):
        k = dr.select(k >= n, k - n, k)
    return mi.UInt32(dr.select(k < 0, k + n, k))


class DrPyramid:
    """An area pyramid (:func:`dynbtf.synthesis.mip.area_pyramid`) in one flat buffer, read at a level per lane.

    Parameters
    ----------
    levels : list of float32 ``(H_l, W_l, C)``
        Level 0 (the read plane) first.
    luminances : list of float32 ``(H_l, W_l)``, optional
        A one-channel pyramid of the same sizes (hex's luminance).
    """

    def __init__(self, levels, luminances=None) -> None:
        mi = mi_module()
        arrays = [np.asarray(t, dtype=np.float32) for t in levels]
        self.height, self.width, self.channels = (int(x) for x in arrays[0].shape)
        #: (first texel, width, height) of each level, as Python ints (literals) and as per-lane gather sources
        self.level_sizes = []
        start = 0
        for t in arrays:
            self.level_sizes.append((start, int(t.shape[1]), int(t.shape[0])))
            start += int(t.shape[0] * t.shape[1])
        starts, widths, heights = (np.array(column, dtype=np.uint32) for column in zip(*self.level_sizes))
        self.flat = flat_array(mi, np.concatenate([t.reshape(-1) for t in arrays]))
        self.starts, self.widths, self.heights = mi.UInt32(starts), mi.UInt32(widths), mi.UInt32(heights)
        self.luminances = None if luminances is None else flat_array(
            mi, np.concatenate([np.asarray(t, dtype=np.float32).reshape(-1) for t in luminances]))

    def taps(self, level, x, y):
        """Bilinear taps of ``level`` (``mi.UInt32``, or an ``int``) at level-0 texel positions ``x, y`` (``mi.Float64``).

        Level-0 texel ``[i, j]`` covers ``[j, j + 1) x [i, i + 1)``; positions in ``[0, 3 W)``; the
        level wraps. Returns 4 ``(texel index into the flat buffer, weight)`` as
        :func:`~dynbtf.jit.bilinear_taps` (the numba kernel's ``_level_tap``).
        """
        mi, dr = mi_module(), drjit_module()
        if isinstance(level, int):  # one level for all lanes: its sizes are literals
            start, mw, mh = self.level_sizes[level]
            px = x * (mw / self.width) - 0.5
            py = y * (mh / self.height) - 0.5
        else:
            start = dr.gather(mi.UInt32, self.starts, level)
            mw = dr.gather(mi.UInt32, self.widths, level)
            mh = dr.gather(mi.UInt32, self.heights, level)
            px = x * (mi.Float64(mw) / self.width) - 0.5
            py = y * (mi.Float64(mh) / self.height) - 0.5
        return periodic_taps(px, py, mw, mh, start)


def periodic_taps(px, py, width, height, start=0):
    """Bilinear taps of a periodic ``height x width`` plane at texel coordinates ``px, py`` (``mi.Float64``, texel
    ``[i, j]`` centred at ``(j, i)``, within ``[-W, 3 W)``); ``width, height``: ints, or ``mi.UInt32`` per lane.

    Returns 4 ``(texel index + start, weight: mi.Float)`` as :func:`~dynbtf.jit.bilinear_taps`
    (the numba kernels' fetches: float64 positions, float32 weights).
    """
    mi, dr = mi_module(), drjit_module()
    cols, rows = (width, height) if isinstance(width, int) else (mi.Int32(width), mi.Int32(height))
    fx, fy = dr.floor(px), dr.floor(py)
    tx, ty = mi.Float(px - fx), mi.Float(py - fy)
    c0, r0 = wrap_small(mi.Int32(fx), cols), wrap_small(mi.Int32(fy), rows)
    c1 = dr.select(c0 + 1 == width, 0, c0 + 1)
    r1 = dr.select(r0 + 1 == height, 0, r0 + 1)
    return [(start + r0 * width + c0, (1.0 - tx) * (1.0 - ty)), (start + r0 * width + c1, tx * (1.0 - ty)),
            (start + r1 * width + c0, (1.0 - tx) * ty), (start + r1 * width + c1, tx * ty)]


def filtering_tables(pyramid_source, *, luminances: bool = False, inverse_tables: bool = False):
    """What a Dr.Jit synthesizer's footprint queries read, from its torch twin's ``pyramid()`` (``pyramid_source``).

    Returns ``(DrPyramid, DrLevelOfDetail, the per-level inverse tables as one flat mi.Float or None)``;
    ``luminances``: with the luminance pyramid (hex); ``inverse_tables``: with the tables (hist).
    """
    if pyramid_source is None:
        raise InputError("footprint queries need the synthesizer's pyramid (pyramid_source)")
    pyr = pyramid_source()
    pyramid = DrPyramid([to_host(t) for t in pyr["levels"]],
                        [to_host(t) for t in pyr["luminances"]] if luminances else None)
    tables = flat_array(mi_module(), pyr["luts_numpy"]) if inverse_tables else None
    return pyramid, DrLevelOfDetail(pyr["lod"]), tables


def gather_one(buffer, taps, active=True):
    """Bilinear combination of a one-channel buffer over ``taps`` (as :func:`~dynbtf.jit.gather_channels`)."""
    return gather_channels(buffer, 1, taps, active)[0]


class DrLabelField:
    """:class:`dynbtf.synthesis.guided_blending.LabelField` in Dr.Jit: a label image over exemplar repeats, nearest
    texel, repeated (an exact remainder: the same labels at any distance) or clamped."""

    def __init__(self, field) -> None:
        mi = mi_module()
        image = np.asarray(field.image, dtype=np.int32)
        self.h, self.w = (int(x) for x in image.shape)
        self.image = mi.Int32(image.reshape(-1))
        self.size, self.repeat = float(field.size), field.wrap == "repeat"

    def __call__(self, u, v, active=True):
        """The label (``mi.Int32``) at ``(u, v)`` exemplar repeats (``mi.Float64``)."""
        mi, dr = mi_module(), drjit_module()
        size, h, w = self.size, self.h, self.w
        pu, pv = mi.Float64(u), mi.Float64(v)
        if self.repeat:
            pu, pv = pu - dr.floor(pu / size) * size, pv - dr.floor(pv / size) * size
        col, row = mi.Int32(dr.floor(pu / size * w)), mi.Int32(dr.floor(pv / size * h))
        if self.repeat:
            col, row = positive_mod(col, w), positive_mod(row, h)
        else:
            col, row = dr.clip(col, 0, w - 1), dr.clip(row, 0, h - 1)
        return dr.gather(mi.Int32, self.image, mi.UInt32(row * w + col), active)
