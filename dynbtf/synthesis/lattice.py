"""The triangle grid of dynamic by-example synthesis, exact at any coordinate.

``uv`` is in units of one exemplar repeat. Heitz & Neyret (2018) scale it by
``2 sqrt(3)`` and skew it onto an equilateral triangle lattice:

    s = 2 sqrt(3) uv ;  k = (s_x - s_y / sqrt(3), 2 s_y / sqrt(3)) = M uv,  M = [[2 sqrt(3), -2], [0, 4]]

(the shaders' constants 0.57735027 and 1.15470054 are 1/sqrt(3) and 2/sqrt(3)
rounded). With ``b = floor(k)``, ``f = k - b``, ``z = 1 - f_x - f_y``, the point
lies in the triangle with vertices ``b, b + (0, 1), b + (1, 0)`` and barycentrics
``(z, f_y, f_x)`` when ``z > 0``, else in ``b + (1, 1), b + (1, 0), b + (0, 1)`` with
``(-z, 1 - f_y, 1 - f_x)``. Triangle edges are ``1 / (2 sqrt(3)) ~ 0.289`` repeats
long; vertex ``(i, j)`` sits at ``uv = ((i + j / 2) / (2 sqrt(3)), j / 4)``, which
is also the centre of hex-tile ``(i, j)`` (Mikkelsen 2022).

Exactness for any uv
--------------------
``uv`` is split in float64 into an integer repeat index ``I`` (int64) and a
fraction ``F`` in ``[0, 1)``. Because ``M``'s second column is integer, ``I_v``
moves the lattice by whole vertex steps ``(-2, 4)``; ``2 sqrt(3) I_u`` is split into
an integer and a fraction: for ``|I_u| < 2**27`` with a two-term (hi + lo) float64
product, beyond in integer fixed point (``2 sqrt(3)`` as ``N1 / 2**24 + N2 / 2**50 + c3``
from its exact digits; :func:`large_scaled_integer`), so the fraction is within ~1e-15
lattice units of the true ``2 sqrt(3) I_u mod 1`` for every ``|I_u| <`` :data:`MAX_REPEATS`
(= ``2**52``, the limit :func:`dynbtf.synthesis.base.check_uv` enforces). So ``k``'s integer
part is exact int64 and its fraction is computed from numbers below ~4 in size:
a query at ``uv = 1e6 + x`` sees exactly the lattice phase (barycentrics) it
would see at a base point with the same phase, and any shift by whole repeats
in ``v`` maps the lattice onto itself (bitwise identical barycentrics).
"""

from __future__ import annotations

import math

import torch

__all__ = ["split_uv", "triangle_lattice", "vertex_uv", "large_scaled_integer", "LATTICE_SCALE", "TRIANGLE_EDGE",
           "MAX_REPEATS", "LATTICE_SCALE_HI", "LATTICE_SCALE_LO"]

#: Largest ``|uv|`` (exemplar repeats, i.e. after a synthesized BTF's ``scale``) the lattice and
#: every synthesizer accept (exclusive). Below it the lattice is exact (see the module docstring)
#: and every int64 quantity derived from ``uv`` (repeat index, vertices up to ~3.5 * 2**52,
#: texel addresses) fits; from it on float64 holds no fraction of a repeat at all (its spacing is
#: >= 1 repeat), so a query can only land on whole repeats. Texel resolution ends earlier, where the
#: float64 spacing ``2**(e - 52)`` exceeds ``1 / W`` repeats: ``|uv| >= 2**52 / W`` (~1e13 for W = 400).
#: Defined in :mod:`dynbtf.limits` (the commands check scales against the same value).
from ..limits import MAX_REPEATS  # noqa: E402

#: ``2 sqrt(3)``: lattice units per exemplar repeat along ``u``.
LATTICE_SCALE = 2.0 * math.sqrt(3.0)
#: Edge length of a lattice triangle, in exemplar repeats.
TRIANGLE_EDGE = 1.0 / LATTICE_SCALE
#: ``2 sqrt(3) = LATTICE_SCALE_HI + LATTICE_SCALE_LO``; the high part holds 26 significant bits, so
#: ``I * LATTICE_SCALE_HI`` is exact for ``|I| < 2**27`` (the split every backend uses for large uv).
LATTICE_SCALE_HI = math.ldexp(math.floor(math.ldexp(LATTICE_SCALE, 24)), -24)
LATTICE_SCALE_LO = LATTICE_SCALE - LATTICE_SCALE_HI
# The exact 2 sqrt(3) = sqrt(12) in fixed point: _N1 / 2**24 + _N2 / 2**50 + _C3, with _N1 < 2**26 and
# _N2 < 2**26 integers and 0 <= _C3 < 2**-50 (all from integer square roots, no rounded constant).
_N1 = math.isqrt(12 << 48)
_N2 = math.isqrt(12 << 100) - (_N1 << 26)
_C3 = (math.isqrt(12 << 228) - (math.isqrt(12 << 100) << 64)) / 2.0**114
_MASK24, _MASK50 = (1 << 24) - 1, (1 << 50) - 1


def split_uv(uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Integer repeat index (int64) and fraction in ``[0, 1)`` (float64) of ``uv``.

    ``uv`` is first converted to float64 (exact for float32 input); the split is
    exact in float64.
    """
    uv = uv.to(torch.float64)
    whole = torch.floor(uv)
    frac = uv - whole
    carry = frac >= 1.0  # never for exact arithmetic; guards -tiny inputs
    return (whole + carry).to(torch.int64), torch.where(carry, frac - 1.0, frac)


def _to_float64(x: torch.Tensor) -> torch.Tensor:
    return x.to(torch.float64)


def _to_int64(x: torch.Tensor) -> torch.Tensor:
    return x.to(torch.int64)


_floor = torch.floor


def large_scaled_integer(i):
    """``2 sqrt(3) * i`` for int64 ``|i| <= 2**53`` as (int64 floor, float64 fraction in ``[0, 1)``).

    Integer fixed point: with ``i = a 2**26 + b`` (``0 <= b < 2**26``) every product of ``a`` or ``b``
    with ``_N1`` or ``_N2`` is an exact int64 (< 2**54) whose bits below the binary point give an
    exact fraction; only ``i * _C3`` (< 8) is rounded, so the fraction is within ~1e-15 of
    ``2 sqrt(3) i mod 1``. Written once for int64 tensors and, compiled with ``_floor``,
    ``_to_float64`` and ``_to_int64`` replaced by scalar twins, for the numba kernel.
    """
    a = i >> 26
    b = i & ((1 << 26) - 1)
    p_b1, p_a2, p_b2 = b * _N1, a * _N2, b * _N2
    whole = 4 * a * _N1 + (p_b1 >> 24) + (p_a2 >> 24) + (p_b2 >> 50)  # a 2**26 _N1 / 2**24 = 4 a _N1
    frac = (_to_float64((p_b1 & _MASK24) + (p_a2 & _MASK24)) * 2.0**-24 + _to_float64(p_b2 & _MASK50) * 2.0**-50
            + _to_float64(i) * _C3)
    carry = _floor(frac)
    return whole + _to_int64(carry), frac - carry


def _scaled_integer(i: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``2 sqrt(3) * i`` for int64 ``|i| <= 2**53`` as (int64 floor, float64 fraction)."""
    i_lo = torch.where(i.abs() < (1 << 27), i, torch.zeros_like(i)).to(torch.float64)
    p_hi = i_lo * LATTICE_SCALE_HI  # exact: |i_lo| < 2**27, LATTICE_SCALE_HI has 26 bits
    whole = torch.floor(p_hi)
    frac = (p_hi - whole) + i_lo * LATTICE_SCALE_LO
    carry = torch.floor(frac)
    small_whole, small_frac = whole.to(torch.int64) + carry.to(torch.int64), frac - carry
    large = i.abs() >= (1 << 27)  # beyond 1.3e8 repeats: integer fixed point
    if not bool(large.any()):
        return small_whole, small_frac
    big_whole, big_frac = large_scaled_integer(i)
    return torch.where(large, big_whole, small_whole), torch.where(large, big_frac, small_frac)


def triangle_lattice(uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertices and barycentric coordinates of the lattice triangle containing each ``uv``.

    Parameters
    ----------
    uv : tensor ``(..., 2)``, float32 or float64
        Positions in exemplar repeats (any real value).

    Returns
    -------
    vertices : int64 tensor ``(..., 3, 2)``
        Integer lattice coordinates of the triangle's three vertices.
    barycentrics : float64 tensor ``(..., 3)``
        Non-negative, summing to 1 (vertex ``i`` has weight ``barycentrics[..., i]``).

    Examples
    --------
    >>> import torch
    >>> v, b = triangle_lattice(torch.tensor([[0.05, 0.05], [1e6 + 0.05, 0.05]], dtype=torch.float64))
    >>> v[0].tolist(), [round(x, 4) for x in b[0].tolist()]
    ([[0, 0], [0, 1], [1, 0]], [0.7268, 0.2, 0.0732])
    """
    whole, frac = split_uv(uv)
    iu_whole, iu_frac = _scaled_integer(whole[..., 0])
    # k = M uv, integer part from the whole repeats, fraction from small numbers only
    kx = iu_frac + LATTICE_SCALE * frac[..., 0] - 2.0 * frac[..., 1]
    ky = 4.0 * frac[..., 1]
    bx, by = torch.floor(kx), torch.floor(ky)
    fx, fy = kx - bx, ky - by
    base_x = bx.to(torch.int64) + iu_whole - 2 * whole[..., 1]
    base_y = by.to(torch.int64) + 4 * whole[..., 1]
    z = 1.0 - fx - fy
    lower = z > 0
    one = torch.ones_like(base_x)
    zero = torch.zeros_like(base_x)
    # lower triangle: b, b+(0,1), b+(1,0); upper: b+(1,1), b+(1,0), b+(0,1)
    dx = torch.stack([torch.where(lower, zero, one), torch.where(lower, zero, one), torch.where(lower, one, zero)], -1)
    dy = torch.stack([torch.where(lower, zero, one), torch.where(lower, one, zero), torch.where(lower, zero, one)], -1)
    vertices = torch.stack([base_x[..., None] + dx, base_y[..., None] + dy], dim=-1)
    bary = torch.stack([torch.where(lower, z, -z), torch.where(lower, fy, 1.0 - fy),
                        torch.where(lower, fx, 1.0 - fx)], dim=-1)
    return vertices, bary


def vertex_uv(vertices: torch.Tensor) -> torch.Tensor:
    """Position ``(..., 2)`` float64 (exemplar repeats) of integer lattice vertices ``(..., 2)``.

    Also the centre of the hex tile of that vertex (Mikkelsen 2022).
    """
    v = vertices.to(torch.float64)
    return torch.stack([(v[..., 0] + 0.5 * v[..., 1]) / LATTICE_SCALE, v[..., 1] / 4.0], dim=-1)
