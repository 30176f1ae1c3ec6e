"""The numba building blocks of the synthesis methods' CPU kernels: the lattice, the hash, addressing, fetches.

Compiled twins of :mod:`dynbtf.synthesis.hash` (``jit_hash_vertex`` and its parts: the same functions compiled as
they are, bit for bit) and of :mod:`dynbtf.synthesis.lattice` (float64/int64, exact at any coordinate), the
periodic bilinear fetch, a cache-line prefetch and the cache-aligned plane the kernels read. Each method's kernel is
in its package, written with these: ``blending/kernel.py`` (the fused lattice blend of ``linear``, ``hist``,
``hex`` and the guided blends), ``tiling/kernel.py``, ``cell_quilting/kernel.py``.
"""

from __future__ import annotations

import math
import types

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils
from numba.extending import intrinsic

from .hash import SECOND_STREAM, MASK32, fold_coordinate, hash_vertex, mix32, seed_state
from .lattice import LATTICE_SCALE_HI, LATTICE_SCALE_LO, LATTICE_SCALE, large_scaled_integer
from .sample_transform import displacement, inverse_scales, quarter_turns, turn_cos_sin

__all__ = ["jit_with", "mulmod32_native", "jit_mix32", "jit_seed_state", "jit_fold_coordinate", "jit_hash_vertex",
           "jit_large_scaled_integer", "prefetch", "SMALL_REPEAT", "small_scaled_integer", "scaled_integer", "wrap",
           "modulo", "sample_texels", "POWER_BITS", "int_power", "gain", "split_repeat", "lattice_cell_of",
           "lattice_cell", "vertex_hashes", "barycentrics", "lattice_hashes", "vertex", "CACHE_LINE", "cache_aligned",
           "bilinear_periodic", "jit_quarter_turns", "jit_inverse_scales", "sample_displacement"]


def jit_with(fn, **globals_):
    """numba-compile the pure-Python function ``fn`` with some of its globals replaced (by compiled twins)."""
    return numba.njit(inline="always")(types.FunctionType(fn.__code__, {**fn.__globals__, **globals_}, fn.__name__))


@numba.njit(inline="always")
def mulmod32_native(x, c):
    """``(x * c) mod 2**32`` for ``0 <= x, c < 2**32``: one unsigned 64-bit multiply (wraps, exact)."""
    return np.int64((np.uint64(x) * np.uint64(c)) & np.uint64(MASK32))


jit_mix32 = jit_with(mix32, _mulmod32=mulmod32_native)
jit_seed_state = jit_with(seed_state, mix32=jit_mix32)
jit_fold_coordinate = jit_with(fold_coordinate, mix32=jit_mix32)
jit_hash_vertex = jit_with(hash_vertex, fold_coordinate=jit_fold_coordinate, seed_state=jit_seed_state)
jit_large_scaled_integer = jit_with(large_scaled_integer, _floor=math.floor, _to_float64=np.float64, _to_int64=np.int64)
jit_quarter_turns = jit_with(quarter_turns, mix32=jit_mix32)
jit_turn_cos_sin = jit_with(turn_cos_sin)
jit_inverse_scales = jit_with(inverse_scales, mix32=jit_mix32, _exp=math.exp, _to_float64=np.float64)
jit_displacement = jit_with(displacement, _floor=math.floor)


@intrinsic
def prefetch(typingctx, array, index):
    """Hint the CPU to load ``array[index]`` (1-D) into cache (``llvm.prefetch``, read, high locality)."""
    sig = numba.types.void(array, index)

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        pointer = cgutils.get_item_pointer(context, builder, array_type, view, [args[1]], wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                            "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(pointer, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


#: Below this repeat index the lattice's ``2 sqrt(3) i`` is exact in two float64 products (:func:`scaled_integer`).
SMALL_REPEAT = 1 << 27


@numba.njit(inline="always")
def small_scaled_integer(i):
    """2 sqrt(3) * i as (int64 floor, float64 fraction) for ``|i| < SMALL_REPEAT`` (branch-free)."""
    p_hi = np.float64(i) * LATTICE_SCALE_HI
    whole = math.floor(p_hi)
    frac = (p_hi - whole) + np.float64(i) * LATTICE_SCALE_LO
    carry = math.floor(frac)
    return np.int64(whole) + np.int64(carry), frac - carry


@numba.njit(inline="always")
def scaled_integer(i):
    """2 sqrt(3) * i as (int64 floor, float64 fraction): scalar twin of lattice._scaled_integer."""
    if abs(i) >= SMALL_REPEAT:  # beyond 1.3e8 repeats: integer fixed point (lattice.large_scaled_integer)
        return jit_large_scaled_integer(i)
    return small_scaled_integer(i)


@numba.njit(inline="always")
def wrap(i, period):
    """``i mod period`` for ``-period <= i < 2 period`` without a division."""
    if i >= period:
        return i - period
    if i < 0:
        return i + period
    return i


@numba.njit(inline="always")
def modulo(i, period, inverse):
    """``i mod period`` in ``[0, period)`` (Python's ``%``) for int64 ``|i| < 2**52``, ``inverse = 1 / period``.

    A float64 quotient, off by at most one and corrected: exact, and unlike a 64-bit integer division it
    runs in SIMD lanes, so the block loops below vectorize across queries."""
    r = i - np.int64(math.floor(np.float64(i) * inverse)) * period
    if r < 0:
        r += period
    if r >= period:
        r -= period
    return r


@numba.njit(inline="always")
def sample_texels(h, xi, yi, pw, ph):
    """Columns/rows of the 2x2 bilinear footprint of a sample offset by hash ``h`` (wrapped)."""
    ox = modulo(h, pw, 1.0 / pw)
    oy = modulo(jit_mix32(h ^ SECOND_STREAM), ph, 1.0 / ph)
    c0 = wrap(xi + ox, pw)
    r0 = wrap(yi + oy, ph)
    return c0, wrap(c0 + 1, pw), r0, wrap(r0 + 1, ph)


#: Bits of the largest integral histogram-blending exponent (64) taken by :func:`int_power`.
POWER_BITS = 7


@numba.njit(inline="always")
def int_power(x, n):
    """``max(x, 0) ** n`` for an integer ``1 <= n < 2**POWER_BITS`` by repeated squaring (no ``pow`` call).

    A fixed number of steps, each multiply taken or not by a select, so that a loop over queries vectorizes."""
    base = max(x, 0.0)
    result = 1.0
    for bit in range(POWER_BITS):
        if (n >> bit) & 1:
            result *= base
        base *= base
    return result


@numba.njit(inline="always")
def gain(x, k):
    if x < 0.5:
        return 0.5 * (2.0 * x) ** k
    return 1.0 - 0.5 * (2.0 - 2.0 * x) ** k


@numba.njit(inline="always")
def split_repeat(u):
    """Repeat index (int64) and fraction in ``[0, 1)`` of one coordinate: scalar twin of ``lattice.split_uv``."""
    whole = math.floor(u)
    frac = u - whole
    if frac >= 1.0:  # never for exact arithmetic; guards -tiny inputs
        frac -= 1.0
        whole += 1.0
    return np.int64(whole), frac


@numba.njit(inline="always")
def lattice_cell_of(iu, iv, fu, fv, iu_whole, iu_frac):
    """:func:`lattice_cell` from the repeat's split and ``2 sqrt(3) iu`` (:func:`scaled_integer`)."""
    kx = iu_frac + LATTICE_SCALE * fu - 2.0 * fv
    ky = 4.0 * fv
    bx = math.floor(kx)
    by = math.floor(ky)
    fx = kx - bx
    fy = ky - by
    return np.int64(bx) + iu_whole - 2 * iv, np.int64(by) + 4 * iv, fx, fy, 1.0 - fx - fy


@numba.njit(inline="always")
def lattice_cell(u, v):
    """Lattice triangle of a query (:func:`dynbtf.synthesis.lattice.triangle_lattice`).

    Returns the repeat index ``iu, iv`` (int64), the fraction ``fu, fv`` in ``[0, 1)``, the cell's base vertex
    ``base_x, base_y`` (int64), its fractions ``fx, fy`` and ``z = 1 - fx - fy`` (the lower triangle where
    ``z > 0``).
    """
    iu, fu = split_repeat(u)
    iv, fv = split_repeat(v)
    iu_whole, iu_frac = scaled_integer(iu)
    base_x, base_y, fx, fy, z = lattice_cell_of(iu, iv, fu, fv, iu_whole, iu_frac)
    return iu, iv, fu, fv, base_x, base_y, fx, fy, z


@numba.njit(inline="always")
def vertex_hashes(state, base_x, base_y, lower):
    """Hashes (:func:`dynbtf.synthesis.hash.hash_vertex`) of the triangle's vertices, in the order
    b, b + (0, 1), b + (1, 0) for the lower triangle and b + (1, 1), b + (1, 0), b + (0, 1) for the upper
    (``b`` the base vertex); the two vertices with the same x share its fold. Selects, not branches."""
    h_a = jit_fold_coordinate(state, base_x)
    h_b = jit_fold_coordinate(state, base_x + 1)
    first = h_a if lower else h_b
    second = h_b if lower else h_a
    y_near = base_y if lower else base_y + 1
    y_far = base_y + 1 if lower else base_y
    return jit_fold_coordinate(first, y_near), jit_fold_coordinate(first, y_far), jit_fold_coordinate(second, y_near)


@numba.njit(inline="always")
def barycentrics(fx, fy, z, lower):
    """Barycentrics of the three vertices of :func:`vertex_hashes` (same order)."""
    if lower:
        return z, fy, fx
    return -z, 1.0 - fy, 1.0 - fx


@numba.njit(inline="always")
def lattice_hashes(u, v, state):
    """Lattice triangle of a query, its vertex hashes and barycentrics.

    Returns ``iu, iv, fu, fv`` (:func:`lattice_cell`), the three vertices' hashes ``h0, h1, h2`` and their
    barycentrics ``b0, b1, b2``, the base vertex and whether the triangle is the lower one.
    """
    iu, iv, fu, fv, base_x, base_y, fx, fy, z = lattice_cell(u, v)
    lower = z > 0
    h0, h1, h2 = vertex_hashes(state, base_x, base_y, lower)
    b0, b1, b2 = barycentrics(fx, fy, z, lower)
    return iu, iv, fu, fv, h0, h1, h2, b0, b1, b2, base_x, base_y, lower


@numba.njit(inline="always")
def vertex(k, base_x, base_y, lower):
    """Coordinates of sample ``k``'s lattice vertex (the order of :func:`vertex_hashes`)."""
    if lower:  # b, b + (0, 1), b + (1, 0)
        return base_x + (1 if k == 2 else 0), base_y + (1 if k == 1 else 0)
    return base_x + (0 if k == 2 else 1), base_y + (0 if k == 1 else 1)  # b + (1, 1), b + (1, 0), b + (0, 1)


@numba.njit(inline="always")
def sample_displacement(k, b0, b1, b2, lower, h, density_w, density_h, t_x, t_y, rotation, log_range):
    """How far (texels, ``(ex, ey)`` float64) sample ``k`` (order of :func:`vertex_hashes`, hash ``h``) of a query with
    barycentrics ``b0, b1, b2`` and fractions ``t_x, t_y`` from its texel centre moves when turned (``rotation``)
    and scaled (``log_range = log(1 + scale_jitter)``, 0: not) about the texel centre next to its vertex (its pivot):
    the scalar twin of :func:`dynbtf.synthesis.sample_transform.lattice_displacements` and ``displacement``."""
    kx, ky = vertex(k, 0, 0, lower)
    x0, y0 = vertex(0, 0, 0, lower)
    x1, y1 = vertex(1, 0, 0, lower)
    x2, y2 = vertex(2, 0, 0, lower)
    lx = b0 * np.float64(x0 - kx) + b1 * np.float64(x1 - kx) + b2 * np.float64(x2 - kx)
    ly = b0 * np.float64(y0 - ky) + b1 * np.float64(y1 - ky) + b2 * np.float64(y2 - ky)
    dx = (lx + 0.5 * ly) / LATTICE_SCALE * density_w
    dy = 0.25 * ly * density_h
    cos_a, sin_a = 1.0, 0.0
    if rotation:
        c, s = jit_turn_cos_sin(jit_quarter_turns(h))
        cos_a, sin_a = np.float64(c), np.float64(s)
    if log_range != 0.0:
        inverse = jit_inverse_scales(h, log_range)
        cos_a, sin_a = cos_a * inverse, sin_a * inverse
    return jit_displacement(t_x, t_y, dx, dy, cos_a, sin_a)


#: Bytes of a cache line (x86-64 and ARM64 alike).
CACHE_LINE = 64


def cache_aligned(array: np.ndarray) -> np.ndarray:
    """``array`` as a C-contiguous float32 array whose first byte starts a cache line (itself if it already is).

    The lattice kernel reads whole texels at random: with 16 channels a texel of an aligned plane is one cache
    line, of an unaligned one two."""
    array = np.asarray(array, dtype=np.float32)
    if array.flags.c_contiguous and array.ctypes.data % CACHE_LINE == 0:
        return array
    buffer = np.empty(array.size + CACHE_LINE // 4, dtype=np.float32)
    start = (-buffer.ctypes.data % CACHE_LINE) // 4
    aligned = buffer[start:start + array.size].reshape(array.shape)
    aligned[...] = array
    return aligned

@numba.njit(inline="always")
def bilinear_periodic(plane, x, y, out, n):
    """``out[n] =`` bilinear periodic fetch of ``plane (H, W, C)`` at texel position ``(x, y)`` (float64, texel
    ``[i, j]`` centred at ``(j + 0.5, i + 0.5)``, any value: wrapped); weights in float32."""
    ph, pw, nc = plane.shape
    px = x - 0.5
    py = y - 0.5
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
