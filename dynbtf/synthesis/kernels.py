"""Fused CPU kernel of lattice blending (numba): lattice + hash + 3 bilinear fetches + blend + inverse LUT.

One pass per query, parallel over queries, no temporaries: this is what a
renderer pays per shading point for the positional features. It computes
exactly what the torch reference path of :class:`~dynbtf.synthesis.blending.LatticeBlending`
computes (same lattice arithmetic in float64/int64, same hash -- the functions
of :mod:`dynbtf.synthesis.hash` compiled as they are), except that histogram
blending inverts the Gaussian transform with an :class:`~dynbtf.synthesis.histogram.InverseLUT`
instead of the exact inverse (error reported by the tests and the benchmark).

Blend modes: ``MODE_LINEAR`` (weights ``b``), ``MODE_HIST`` (weights
``b^gamma`` normalized, variance-preserving, then the LUT), ``MODE_HEX``
(weights ``delta_i b_i^7`` with ``delta_i = 1 - beta + beta lum_i``, then the contrast
gain with exponent ``k``).
"""

from __future__ import annotations

import math
import types

import numba
import numpy as np

from .hash import _SECOND_STREAM, _mulmod32, hash_vertex, mix32
from .lattice import _C_HI, _C_LO, LATTICE_SCALE

__all__ = ["lattice_blend", "tile_fetch", "MODE_LINEAR", "MODE_HIST", "MODE_HEX"]

MODE_LINEAR, MODE_HIST, MODE_HEX = 0, 1, 2



def _jit_with(fn, **globals_):
    """numba-compile the pure-Python function ``fn`` with some of its globals replaced (by compiled twins)."""
    return numba.njit(inline="always")(types.FunctionType(fn.__code__, {**fn.__globals__, **globals_}, fn.__name__))


_mulmod32_jit = numba.njit(inline="always")(_mulmod32)
_mix32 = _jit_with(mix32, _mulmod32=_mulmod32_jit)
_hash_vertex = _jit_with(hash_vertex, mix32=_mix32)


@numba.njit(inline="always")
def _scaled_integer(i):
    """2 sqrt(3) * i as (int64 floor, float64 fraction): scalar twin of lattice._scaled_integer."""
    if abs(i) < (1 << 27):
        p_hi = np.float64(i) * _C_HI
        whole = math.floor(p_hi)
        frac = (p_hi - whole) + np.float64(i) * _C_LO
    else:
        whole = 0.0
        frac = np.float64(i) * LATTICE_SCALE
    carry = math.floor(frac)
    return np.int64(whole) + np.int64(carry), frac - carry


@numba.njit(inline="always")
def _wrap(i, period):
    """``i mod period`` for ``-period <= i < 2 period`` without a division."""
    if i >= period:
        return i - period
    if i < 0:
        return i + period
    return i


@numba.njit(inline="always")
def _sample_texels(h, xi, yi, pw, ph):
    """Columns/rows of the 2x2 bilinear footprint of a sample offset by hash ``h`` (wrapped)."""
    ox = h % pw
    oy = _mix32(h ^ _SECOND_STREAM) % ph
    c0 = _wrap(xi + ox, pw)
    r0 = _wrap(yi + oy, ph)
    return c0, _wrap(c0 + 1, pw), r0, _wrap(r0 + 1, ph)


@numba.njit(inline="always")
def _gain(x, k):
    if x < 0.5:
        return 0.5 * (2.0 * x) ** k
    return 1.0 - 0.5 * (2.0 - 2.0 * x) ** k


@numba.njit(parallel=True, cache=True)
def _kernel(uv, plane, lum, density_w, density_h, seed, mode, gamma, beta, gain_k, lut, g_min, inv_step, out):
    n_queries = uv.shape[0]
    ph, pw, nc = plane.shape
    flat = plane.reshape(ph * pw * nc)
    lut_size = lut.shape[1]
    for n in numba.prange(n_queries):
        u = uv[n, 0]
        v = uv[n, 1]
        wu = math.floor(u)
        wv = math.floor(v)
        fu = u - wu
        fv = v - wv
        if fu >= 1.0:
            fu -= 1.0
            wu += 1.0
        if fv >= 1.0:
            fv -= 1.0
            wv += 1.0
        iu = np.int64(wu)
        iv = np.int64(wv)
        # ---- lattice (lattice.triangle_lattice)
        iu_whole, iu_frac = _scaled_integer(iu)
        kx = iu_frac + LATTICE_SCALE * fu - 2.0 * fv
        ky = 4.0 * fv
        bx = math.floor(kx)
        by = math.floor(ky)
        fx = kx - bx
        fy = ky - by
        base_x = np.int64(bx) + iu_whole - 2 * iv
        base_y = np.int64(by) + 4 * iv
        z = 1.0 - fx - fy
        if z > 0:
            v0x, v0y, b0 = base_x, base_y, z
            v1x, v1y, b1 = base_x, base_y + 1, fy
            v2x, v2y, b2 = base_x + 1, base_y, fx
        else:
            v0x, v0y, b0 = base_x + 1, base_y + 1, -z
            v1x, v1y, b1 = base_x + 1, base_y, 1.0 - fy
            v2x, v2y, b2 = base_x, base_y + 1, 1.0 - fx
        # ---- texel addressing shared by the three samples (whole-texel offsets)
        px = (iu * density_w) % pw + fu * density_w - 0.5
        py = (iv * density_h) % ph + fv * density_h - 0.5
        x0 = math.floor(px)
        y0 = math.floor(py)
        tx = np.float32(px - x0)
        ty = np.float32(py - y0)
        xi = np.int64(x0) % pw  # one division per axis; the samples then wrap by comparison
        yi = np.int64(y0) % ph
        ca0, cb0, ra0, rb0 = _sample_texels(_hash_vertex(v0x, v0y, seed), xi, yi, pw, ph)
        ca1, cb1, ra1, rb1 = _sample_texels(_hash_vertex(v1x, v1y, seed), xi, yi, pw, ph)
        ca2, cb2, ra2, rb2 = _sample_texels(_hash_vertex(v2x, v2y, seed), xi, yi, pw, ph)
        w00 = (1 - tx) * (1 - ty)
        w01 = tx * (1 - ty)
        w10 = (1 - tx) * ty
        w11 = tx * ty
        # ---- weights
        if mode == MODE_LINEAR:
            s0, s1, s2 = b0, b1, b2
            scale = 1.0
        elif mode == MODE_HIST:
            if gamma == 1.0:
                s0, s1, s2 = b0, b1, b2
            else:
                s0, s1, s2 = max(b0, 0.0) ** gamma, max(b1, 0.0) ** gamma, max(b2, 0.0) ** gamma
            total = s0 + s1 + s2
            s0, s1, s2 = s0 / total, s1 / total, s2 / total
            scale = 1.0 / math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        else:
            l0 = w00 * lum[ra0, ca0] + w01 * lum[ra0, cb0] + w10 * lum[rb0, ca0] + w11 * lum[rb0, cb0]
            l1 = w00 * lum[ra1, ca1] + w01 * lum[ra1, cb1] + w10 * lum[rb1, ca1] + w11 * lum[rb1, cb1]
            l2 = w00 * lum[ra2, ca2] + w01 * lum[ra2, cb2] + w10 * lum[rb2, ca2] + w11 * lum[rb2, cb2]
            s0 = (1.0 - beta + beta * l0) * max(b0, 0.0) ** 7
            s1 = (1.0 - beta + beta * l1) * max(b1, 0.0) ** 7
            s2 = (1.0 - beta + beta * l2) * max(b2, 0.0) ** 7
            total = s0 + s1 + s2
            s0, s1, s2 = s0 / total, s1 / total, s2 / total
            if gain_k != 1.0:
                s0, s1, s2 = _gain(s0, gain_k), _gain(s1, gain_k), _gain(s2, gain_k)
                total = s0 + s1 + s2
                s0, s1, s2 = s0 / total, s1 / total, s2 / total
            scale = 1.0
        ws0 = np.float32(s0 * scale)
        ws1 = np.float32(s1 * scale)
        ws2 = np.float32(s2 * scale)
        # ---- three bilinear fetches, blended (flat plane: texel (r, c) starts at (r * pw + c) * nc)
        o00, o01, o10, o11 = (ra0 * pw + ca0) * nc, (ra0 * pw + cb0) * nc, (rb0 * pw + ca0) * nc, (rb0 * pw + cb0) * nc
        p00, p01, p10, p11 = (ra1 * pw + ca1) * nc, (ra1 * pw + cb1) * nc, (rb1 * pw + ca1) * nc, (rb1 * pw + cb1) * nc
        q00, q01, q10, q11 = (ra2 * pw + ca2) * nc, (ra2 * pw + cb2) * nc, (rb2 * pw + ca2) * nc, (rb2 * pw + cb2) * nc
        a00, a01, a10, a11 = ws0 * w00, ws0 * w01, ws0 * w10, ws0 * w11
        b00, b01, b10, b11 = ws1 * w00, ws1 * w01, ws1 * w10, ws1 * w11
        d00, d01, d10, d11 = ws2 * w00, ws2 * w01, ws2 * w10, ws2 * w11
        row = out[n]
        for c in range(nc):
            row[c] = (a00 * flat[o00 + c] + a01 * flat[o01 + c] + a10 * flat[o10 + c] + a11 * flat[o11 + c]
                      + b00 * flat[p00 + c] + b01 * flat[p01 + c] + b10 * flat[p10 + c] + b11 * flat[p11 + c]
                      + d00 * flat[q00 + c] + d01 * flat[q01 + c] + d10 * flat[q10 + c] + d11 * flat[q11 + c])
        if mode == MODE_HIST:
            for c in range(nc):
                acc = row[c]
                pos = (acc - g_min) * inv_step
                if pos < 0.0:
                    pos = 0.0
                elif pos > lut_size - 1.0:
                    pos = lut_size - 1.0
                lo = min(np.int64(pos), lut_size - 2)
                t = np.float32(pos - lo)
                row[c] = lut[c, lo] + t * (lut[c, lo + 1] - lut[c, lo])


def lattice_blend(uv: np.ndarray, plane: np.ndarray, density: tuple[int, int], seed: int, mode: int, *,
                  gamma: float = 1.0, luminance: np.ndarray | None = None, beta: float = 0.0, gain_k: float = 1.0,
                  lut: np.ndarray | None = None, g_min: float = 0.0, step: float = 1.0,
                  out: np.ndarray | None = None) -> np.ndarray:
    """Blend three hashed, whole-texel-offset exemplar samples per query (one fused pass).

    Parameters
    ----------
    uv : float64 ``(N, 2)``
        Positions in exemplar repeats.
    plane : float32 ``(H', W', C)``, C-contiguous
        The (preprocessed) exemplar: raw features (linear, hex) or their
        Gaussian transform (hist).
    density : (int, int)
        Texels per repeat along ``u`` and ``v`` (the original exemplar's ``W, H``).
    seed : int
    mode : MODE_LINEAR, MODE_HIST or MODE_HEX
    gamma : float
        Barycentric exponent of histogram blending.
    luminance : float32 ``(H', W')``
        Per-texel gain in ``[0, 1]`` for hex-tiling.
    beta, gain_k : float
        Hex-tiling's luminance fall-off and contrast-gain exponent.
    lut, g_min, step
        Inverse histogram table ``(C, L)`` float32 and its grid (hist).
    out : float32 ``(N, C)``, optional
        Output buffer.

    Returns
    -------
    float32 ``(N, C)``.
    """
    n = uv.shape[0]
    c = plane.shape[2]
    if out is None:
        out = np.empty((n, c), dtype=np.float32)
    if luminance is None:
        luminance = np.zeros((1, 1), dtype=np.float32)
    if lut is None:
        lut = np.zeros((c, 2), dtype=np.float32)
    _kernel(np.ascontiguousarray(uv, dtype=np.float64), np.ascontiguousarray(plane, dtype=np.float32),
            np.ascontiguousarray(luminance, dtype=np.float32), int(density[0]), int(density[1]), int(seed) & 0xFFFFFFFF,
            int(mode), float(gamma), float(beta), float(gain_k), np.ascontiguousarray(lut, dtype=np.float32),
            float(g_min), 1.0 / float(step), out)
    return out


@numba.njit(parallel=True, cache=True)
def _tile_kernel(uv, plane, out):
    n_queries = uv.shape[0]
    ph, pw, nc = plane.shape
    for n in numba.prange(n_queries):
        u = uv[n, 0]
        v = uv[n, 1]
        px = (u - math.floor(u)) * pw - 0.5
        py = (v - math.floor(v)) * ph - 0.5
        x0 = math.floor(px)
        y0 = math.floor(py)
        tx = np.float32(px - x0)
        ty = np.float32(py - y0)
        c0 = np.int64(x0) % pw
        c1 = (c0 + 1) % pw
        r0 = np.int64(y0) % ph
        r1 = (r0 + 1) % ph
        for c in range(nc):
            out[n, c] = ((1 - tx) * (1 - ty) * plane[r0, c0, c] + tx * (1 - ty) * plane[r0, c1, c]
                         + (1 - tx) * ty * plane[r1, c0, c] + tx * ty * plane[r1, c1, c])


def tile_fetch(uv: np.ndarray, plane: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Bilinear periodic fetch of ``plane (H, W, C)`` float32 at ``uv (N, 2)`` float64 -> ``(N, C)`` float32.

    The fused twin of :func:`dynbtf.texture.fetch_wrap` (the fraction of ``uv`` is
    taken in float64, so any ``uv`` is exact).
    """
    if out is None:
        out = np.empty((uv.shape[0], plane.shape[2]), dtype=np.float32)
    _tile_kernel(np.ascontiguousarray(uv, dtype=np.float64), np.ascontiguousarray(plane, dtype=np.float32), out)
    return out
