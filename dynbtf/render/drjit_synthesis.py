"""Dynamic synthesis of the positional plane, re-expressed in Dr.Jit for the rendering kernel.

Each class here mirrors one synthesizer of :mod:`dynbtf.synthesis` and reads its
precomputed tables (the exemplar plane after its preprocessing, transforms,
look-up tables) from the torch object, so that the kernel evaluates the same
function as :meth:`dynbtf.synthesized.SynthesizedBTF.features`.

Inputs are ``u, v`` (``mi.Float``, units of one exemplar repeat); outputs are
lists of ``C`` ``mi.Float`` (one per feature channel).
"""

from __future__ import annotations

import math

from ..errors import InputError
from ..synthesis import hash as _hash
from ..synthesis import lattice as _lattice
from .drjit_ops import _dr, _flat, fetch_wrap, mi_module

__all__ = ["mix32", "hash_vertex", "vertex_offsets", "triangle_lattice", "lut_lookup", "DrTiling",
           "make_dr_synthesizer"]


# ---------------------------------------------------------------- integer hash (dynbtf.synthesis.hash)
def mix32(x):
    """lowbias32 finalizer on ``mi.UInt32`` (arithmetic is modulo 2**32 natively)."""
    x = x ^ (x >> 16)
    x = x * _hash._M1
    x = x ^ (x >> 15)
    x = x * _hash._M2
    return x ^ (x >> 16)


def _words(k):
    """Low and high 32-bit words of an ``mi.Int32`` sign-extended to 64 bits, as ``mi.UInt32``."""
    mi, dr = mi_module(), _dr()
    return mi.UInt32(k), dr.select(k < 0, mi.UInt32(0xFFFFFFFF), mi.UInt32(0))


def hash_vertex(vx, vy, seed: int):
    """:func:`dynbtf.synthesis.hash.hash_vertex` for ``mi.Int32`` vertices: identical 32-bit values."""
    mi = mi_module()
    h = mi.UInt32(int(_hash.mix32((int(seed) ^ _hash._SEED_SALT) & _hash.MASK32)))
    lo, hi = _words(vx)
    h = mix32(mix32(h ^ lo) ^ hi)
    lo, hi = _words(vy)
    return mix32(mix32(h ^ lo) ^ hi)


def vertex_offsets(vx, vy, seed: int, width: int, height: int):
    """Whole-texel offsets ``(ox, oy)`` (``mi.UInt32``) of lattice vertices, as :func:`dynbtf.synthesis.hash.vertex_offsets`."""
    h = hash_vertex(vx, vy, seed)
    return h % width, mix32(h ^ _hash._SECOND_STREAM) % height


# ---------------------------------------------------------------- triangle lattice (dynbtf.synthesis.lattice)
def triangle_lattice(u, v):
    """:func:`dynbtf.synthesis.lattice.triangle_lattice` in Dr.Jit.

    ``u, v`` (``mi.Float``) are widened to float64 and split into whole repeats and
    fractions exactly as the torch code does (``|u|, |v| < 2**27``), so the
    vertices are identical and the barycentrics agree to float64 rounding.

    Returns ``([(vx, vy)] * 3 as mi.Int32, [b0, b1, b2] as mi.Float64)``.
    """
    mi, dr = mi_module(), _dr()
    u, v = mi.Float64(u), mi.Float64(v)
    wu, wv = dr.floor(u), dr.floor(v)
    fu, fv = u - wu, v - wv
    cu, cv = fu >= 1.0, fv >= 1.0
    wu, fu = dr.select(cu, wu + 1.0, wu), dr.select(cu, fu - 1.0, fu)
    wv, fv = dr.select(cv, wv + 1.0, wv), dr.select(cv, fv - 1.0, fv)
    # 2 sqrt(3) * whole_u as integer + fraction (hi/lo split of the constant, as in torch)
    p_hi = wu * _lattice._C_HI
    p_whole = dr.floor(p_hi)
    p_frac = (p_hi - p_whole) + wu * _lattice._C_LO
    carry = dr.floor(p_frac)
    iu_whole, iu_frac = p_whole + carry, p_frac - carry
    kx = iu_frac + _lattice.LATTICE_SCALE * fu - 2.0 * fv
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
    return (x + 0.5 * y) / _lattice.LATTICE_SCALE, y / 4.0


# ---------------------------------------------------------------- inverse transform LUT (dynbtf.synthesis.histogram)
def lut_lookup(table, size: int, channel: int, g_min: float, step: float, g):
    """:class:`dynbtf.synthesis.histogram.InverseLUT` lookup of one channel: linear interpolation, clamped.

    ``table`` is the flat ``(C, size)`` float32 table as ``mi.Float``; ``g`` an ``mi.Float``.
    """
    mi, dr = mi_module(), _dr()
    pos = dr.clip((g - g_min) / step, 0.0, size - 1.0)
    lo = dr.minimum(mi.UInt32(dr.floor(pos)), size - 2)
    t = pos - mi.Float(lo)
    base = channel * size
    x0 = dr.gather(mi.Float, table, base + lo)
    x1 = dr.gather(mi.Float, table, base + lo + 1)
    return x0 + t * (x1 - x0)


class DrTiling:
    """Plain periodic tiling: a bilinear, wrapped fetch of the exemplar plane ``(H, W, C)``."""

    def __init__(self, plane) -> None:
        mi = mi_module()
        plane = plane.detach().float().cpu().numpy() if hasattr(plane, "detach") else plane
        self.size = (int(plane.shape[0]), int(plane.shape[1]))
        self.channels = int(plane.shape[2])
        self.plane = _flat(mi, plane)

    def features(self, u, v, active=True):
        return fetch_wrap(self.plane, self.size, self.channels, u, v, active)


def make_dr_synthesizer(model, method: str, seed: int):
    """The Dr.Jit synthesizer for ``method`` on ``model``'s positional plane (same tables as torch's)."""
    if method == "tile":
        return DrTiling(model.positional_plane())
    raise InputError(f"method: expected one of ['tile', 'hist', 'hex'], got {method!r}")

