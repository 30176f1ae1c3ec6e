"""Fused CPU kernel of lattice blending (numba): lattice + hash + 3 bilinear fetches + blend + inverse LUT.

Parallel over blocks of :data:`BLOCK` queries, in passes per block, each a loop
over the block's queries reading and writing rows of a scratch (one query per
column), with selects instead of branches, so that the compiler runs it in SIMD
lanes across queries: this is what a renderer pays per shading point for the
positional features. The passes: the lattice and the vertex hashes; the texel
addressing; the blend weights and the 12 taps; then the blended reads and the
inverse LUT. At random uv the reads are cache misses on a plane of megabytes, so
the blocks are software-pipelined: a block's reads are issued (prefetched) while
the block before it is blended, one query's 12 taps between two queries' blends,
and used only after the next block's arithmetic, so that their latencies overlap
that arithmetic and each other. A plane aligned to cache lines (:func:`cache_aligned`)
makes a 16-channel texel one line, not two (``benchmarks/bench_synthesis_eval.py``).
It computes what the torch reference path of :class:`~dynbtf.synthesis.blending.LatticeBlending`
computes (same lattice arithmetic in float64/int64, same hash -- the functions
of :mod:`dynbtf.synthesis.hash` compiled as they are; the blend itself in
float32), except that histogram blending inverts the Gaussian transform with an
:class:`~dynbtf.synthesis.histogram.InverseLUT` instead of the exact inverse
(error reported by the tests and the benchmark).

Blend modes: ``MODE_LINEAR`` (weights ``b``), ``MODE_HIST`` (weights
``b^gamma`` normalized -- integral ``gamma`` up to 64 by repeated multiplication, as fast as
``gamma = 1``; other values by ``pow`` -- variance-preserving, then the LUT), ``MODE_HEX``
(weights ``delta_i b_i^7`` with ``delta_i = 1 - beta + beta lum_i``, then the contrast
gain with exponent ``k``).

With ``rotation`` each sample is turned by its vertex's quarter turns about the vertex's pivot, and with a
``scale_log`` (``log(1 + scale_jitter)``) scaled about it (:mod:`~dynbtf.synthesis.sample_transform`): each
sample then has its own bilinear fractions, in rows of the scratch of their own. :func:`lattice_frames` gives
the turned queries' frames from the same lattice pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch

from ...errors import InputError
from ..base import check_uv
from ..hash import SECOND_STREAM
from ..kernels import (jit_mix32, jit_seed_state, jit_fold_coordinate, prefetch, SMALL_REPEAT, small_scaled_integer,
                       wrap, modulo, sample_texels, int_power, gain, split_repeat, lattice_cell_of, lattice_cell,
                       vertex_hashes, barycentrics, lattice_hashes, vertex, CACHE_LINE, cache_aligned,
                       sample_displacement, jit_quarter_turns, jit_turn_cos_sin)

__all__ = ["lattice_blend", "filtered_lattice_blend", "lattice_frames", "PackedPyramid", "MODE_LINEAR", "MODE_HIST",
           "MODE_HEX", "BLOCK", "TAPS"]

MODE_LINEAR, MODE_HIST, MODE_HEX = 0, 1, 2

#: Queries per block: the passes' scratch of a block (about 28 KB) stays in the L1 cache, and the block's
#: 12 texel reads per query are issued before the first is used (they overlap in memory).
BLOCK = 64
#: Bilinear taps per query: 3 samples x 2 x 2 texels.
TAPS = 12


@numba.njit(inline="always")
def _guided_texels(k, h, xi, yi, pw, ph, base_x, base_y, lower, states, labels, target):
    """Sample ``k``'s four texels under exemplar guidance (:mod:`dynbtf.synthesis.guided_blending`): the first of
    the candidate offsets (candidate 0: hash ``h``, hist's; candidate ``j``: the vertex hashed from ``states[j]``)
    whose four texels carry label ``target``; else candidate 0's. Returns the texels and whether one matched."""
    c0, c1, r0, r1 = sample_texels(h, xi, yi, pw, ph)
    if labels[r0, c0] == target and labels[r0, c1] == target and labels[r1, c0] == target and labels[r1, c1] == target:
        return c0, c1, r0, r1, True
    vx, vy = vertex(k, base_x, base_y, lower)
    for j in range(1, states.shape[0]):
        ca, cb, ra, rb = sample_texels(jit_fold_coordinate(jit_fold_coordinate(states[j], vx), vy), xi, yi, pw, ph)
        if labels[ra, ca] == target and labels[ra, cb] == target and labels[rb, ca] == target \
                and labels[rb, cb] == target:
            return ca, cb, ra, rb, True
    return c0, c1, r0, r1, False


@numba.njit(inline="always")
def _steered_barycentrics(b0, b1, b2, m0, m1, m2, softness):
    """Guided barycentrics: unmatched samples' weight times ``softness``, unless no sample matched (the torch
    path's ``steered_barycentrics``)."""
    if m0 or m1 or m2:
        return (b0 if m0 else b0 * softness), (b1 if m1 else b1 * softness), (b2 if m2 else b2 * softness)
    return b0, b1, b2


@numba.njit(inline="always")
def _sample_weights(mode, b0, b1, b2, l0, l1, l2, gamma, gamma_int, beta, gain_k):
    """Blend weights ``s0, s1, s2`` of the three samples and the blend's ``scale`` (variance correction).

    ``l0, l1, l2`` are the samples' luminances (hex-tiling only).
    """
    if mode == MODE_LINEAR:
        return b0, b1, b2, 1.0
    if mode == MODE_HIST:
        if gamma == 1.0:
            s0, s1, s2 = b0, b1, b2
        else:  # (b / max b)^gamma: the largest term is 1, so no exponent underflows all three to 0 (0/0)
            top = max(b0, b1, b2)
            b0, b1, b2 = b0 / top, b1 / top, b2 / top
            if gamma_int > 0:  # integral exponent (default 7): repeated squaring (pow: ~25% of the kernel)
                s0, s1, s2 = int_power(b0, gamma_int), int_power(b1, gamma_int), int_power(b2, gamma_int)
            else:
                s0, s1, s2 = max(b0, 0.0) ** gamma, max(b1, 0.0) ** gamma, max(b2, 0.0) ** gamma
        total = s0 + s1 + s2
        s0, s1, s2 = s0 / total, s1 / total, s2 / total
        return s0, s1, s2, 1.0 / math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    s0 = (1.0 - beta + beta * l0) * max(b0, 0.0) ** 7
    s1 = (1.0 - beta + beta * l1) * max(b1, 0.0) ** 7
    s2 = (1.0 - beta + beta * l2) * max(b2, 0.0) ** 7
    total = s0 + s1 + s2
    s0, s1, s2 = s0 / total, s1 / total, s2 / total
    if gain_k != 1.0:
        s0, s1, s2 = gain(s0, gain_k), gain(s1, gain_k), gain(s2, gain_k)
        total = s0 + s1 + s2
        s0, s1, s2 = s0 / total, s1 / total, s2 / total
    return s0, s1, s2, 1.0

@numba.njit(inline="always")
def _blend_taps(flat, taps, weights, j, row):
    """``row[c] = sum_k weights[k, j] flat[taps[k, j] + c]`` over the 12 taps of query ``j`` of a block (float32).

    Unsigned indices: numba then skips the negative-index wraparound and the loop vectorizes.
    """
    t0, t1, t2, t3 = np.uint64(taps[0, j]), np.uint64(taps[1, j]), np.uint64(taps[2, j]), np.uint64(taps[3, j])
    t4, t5, t6, t7 = np.uint64(taps[4, j]), np.uint64(taps[5, j]), np.uint64(taps[6, j]), np.uint64(taps[7, j])
    t8, t9, t10, t11 = np.uint64(taps[8, j]), np.uint64(taps[9, j]), np.uint64(taps[10, j]), np.uint64(taps[11, j])
    w0, w1, w2, w3, w4, w5 = weights[0, j], weights[1, j], weights[2, j], weights[3, j], weights[4, j], weights[5, j]
    w6, w7, w8, w9, w10, w11 = (weights[6, j], weights[7, j], weights[8, j], weights[9, j], weights[10, j],
                                weights[11, j])
    for c in range(np.uint64(row.shape[0])):
        row[c] = (w0 * flat[t0 + c] + w1 * flat[t1 + c] + w2 * flat[t2 + c] + w3 * flat[t3 + c]
                  + w4 * flat[t4 + c] + w5 * flat[t5 + c] + w6 * flat[t6 + c] + w7 * flat[t7 + c]
                  + w8 * flat[t8 + c] + w9 * flat[t9 + c] + w10 * flat[t10 + c] + w11 * flat[t11 + c])


@numba.njit(inline="always")
def _inverse_lut(row, lut, g_min, inv_step):
    """``row[c] = T_c^-1(row[c])`` by the tabulated inverse: linear interpolation, clamped at both ends.

    Positions in float32 (``row`` is float32 already; the table position's rounding, < 3e-4 of a
    table step, is far below the table's own interpolation error).
    """
    lut_size = lut.shape[1]
    top = np.float32(lut_size - 1)
    last = np.int32(lut_size - 2)
    origin = np.float32(g_min)
    scale = np.float32(inv_step)
    for c in range(np.uint64(row.shape[0])):
        pos = min(max((row[c] - origin) * scale, np.float32(0.0)), top)
        lo = min(np.int32(pos), last)
        t = pos - np.float32(lo)
        x0 = lut[c, np.uint64(lo)]  # unsigned: no negative-index wraparound
        row[c] = x0 + t * (lut[c, np.uint64(lo) + np.uint64(1)] - x0)


# Rows of a block's scratch (``(rows, BLOCK)``: one query per column). Each pass below is a loop over queries
# reading and writing whole rows (1-D views), with selects instead of branches, so that it vectorizes across
# queries (the loops that are not: the guided search and the rare large repeat index).
# Integers: the repeat index, the base vertex, the vertex hashes, the texel position shared by the samples,
# and each sample's columns and rows ``c0, c1, r0, r1``.
_IU, _IV, _BASE_X, _BASE_Y, _HASH, _XI, _YI, _TEXELS = 0, 1, 2, 3, 4, 7, 8, 9
_INT_ROWS = _TEXELS + 12
# Reals: the fraction of the repeat, the cell's fractions and z, the barycentrics, the bilinear fractions,
# the samples' luminances (hex), their blend weights and the variance correction, and each sample's own bilinear
# fractions when the samples are turned (sample_transform).
_FU, _FV, _FX, _FY, _Z, _BARY, _TX, _TY, _LUM, _WEIGHT, _SCALE, _TXK, _TYK = 0, 1, 2, 3, 4, 5, 8, 9, 10, 13, 16, 17, 20
_REAL_ROWS = 23


@numba.njit(inline="always")
def _block_lattice(uv, first, count, state, ints, reals):
    """Pass 1: the lattice cell, vertex hashes and barycentrics of queries ``first .. first + count``."""
    iu_, iv_, base_x_, base_y_ = ints[_IU], ints[_IV], ints[_BASE_X], ints[_BASE_Y]
    fu_, fv_, fx_, fy_, z_ = reals[_FU], reals[_FV], reals[_FX], reals[_FY], reals[_Z]
    for j in range(count):
        iu, fu = split_repeat(uv[first + j, 0])
        iv, fv = split_repeat(uv[first + j, 1])
        iu_whole, iu_frac = small_scaled_integer(iu)
        base_x_[j], base_y_[j], fx_[j], fy_[j], z_[j] = lattice_cell_of(iu, iv, fu, fv, iu_whole, iu_frac)
        iu_[j], iv_[j], fu_[j], fv_[j] = iu, iv, fu, fv
    for j in range(count):
        if abs(iu_[j]) >= SMALL_REPEAT:  # beyond 1.3e8 repeats (rare): the exact integer path
            _, _, _, _, base_x_[j], base_y_[j], fx_[j], fy_[j], z_[j] = lattice_cell(uv[first + j, 0],
                                                                                    uv[first + j, 1])
    h0_, h1_, h2_ = ints[_HASH], ints[_HASH + 1], ints[_HASH + 2]
    b0_, b1_, b2_ = reals[_BARY], reals[_BARY + 1], reals[_BARY + 2]
    for j in range(count):
        lower = z_[j] > 0
        h0_[j], h1_[j], h2_[j] = vertex_hashes(state, base_x_[j], base_y_[j], lower)
        b0_[j], b1_[j], b2_[j] = barycentrics(fx_[j], fy_[j], z_[j], lower)


@numba.njit(inline="always")
def _block_texels(count, pw, ph, density_w, density_h, ints, reals, rotation, log_range):
    """Pass 2: each query's bilinear texel position (whole-texel offsets shared by its samples: ``(iu * density)
    mod period`` in int64 without overflow, plus the fraction's texels), then each sample's hashed offset; with
    the samples turned (``rotation``) or scaled (``log_range``), each sample's own displacement and bilinear
    fractions (rows ``_TXK``, ``_TYK``)."""
    inv_pw = 1.0 / pw
    inv_ph = 1.0 / ph
    density_w_mod = density_w % pw
    density_h_mod = density_h % ph
    iu_, iv_, fu_, fv_, tx_, ty_ = ints[_IU], ints[_IV], reals[_FU], reals[_FV], reals[_TX], reals[_TY]
    xi_, yi_ = ints[_XI], ints[_YI]
    for j in range(count):
        px = fu_[j] * density_w - 0.5
        py = fv_[j] * density_h - 0.5
        x0 = math.floor(px)
        y0 = math.floor(py)
        tx_[j] = px - x0
        ty_[j] = py - y0
        xi_[j] = modulo(modulo(iu_[j], pw, inv_pw) * density_w_mod + np.int64(x0), pw, inv_pw)
        yi_[j] = modulo(modulo(iv_[j], ph, inv_ph) * density_h_mod + np.int64(y0), ph, inv_ph)
    z_, b0_, b1_, b2_ = reals[_Z], reals[_BARY], reals[_BARY + 1], reals[_BARY + 2]
    for k in range(3):
        h_ = ints[_HASH + k]
        c0_, c1_, r0_, r1_ = ints[_TEXELS + 4 * k], ints[_TEXELS + 4 * k + 1], ints[_TEXELS + 4 * k + 2], \
            ints[_TEXELS + 4 * k + 3]
        if not rotation and log_range == 0.0:
            for j in range(count):
                c0_[j], c1_[j], r0_[j], r1_[j] = sample_texels(h_[j], xi_[j], yi_[j], pw, ph)
            continue
        txk_, tyk_ = reals[_TXK + k], reals[_TYK + k]
        for j in range(count):
            ex, ey = sample_displacement(k, b0_[j], b1_[j], b2_[j], z_[j] > 0, h_[j], density_w, density_h, tx_[j],
                                         ty_[j], rotation, log_range)
            px = tx_[j] + ex
            py = ty_[j] + ey
            sx = math.floor(px)
            sy = math.floor(py)
            txk_[j] = px - sx
            tyk_[j] = py - sy
            xs = modulo(xi_[j] + np.int64(sx), pw, inv_pw)
            ys = modulo(yi_[j] + np.int64(sy), ph, inv_ph)
            c0_[j], c1_[j], r0_[j], r1_[j] = sample_texels(h_[j], xs, ys, pw, ph)


@numba.njit(inline="always")
def _block_guidance(first, count, pw, ph, ints, reals, states, labels, target, softness):
    """Exemplar guidance (:mod:`dynbtf.synthesis.guided_blending`): each sample re-chosen from content of the
    query's target label, and unmatched samples' barycentric weight times ``softness``."""
    matched = np.zeros(3, dtype=np.bool_)
    for j in range(count):
        t = target[first + j]
        lower = reals[_Z, j] > 0
        for k in range(3):
            row = _TEXELS + 4 * k
            ints[row, j], ints[row + 1, j], ints[row + 2, j], ints[row + 3, j], matched[k] = _guided_texels(
                k, ints[_HASH + k, j], ints[_XI, j], ints[_YI, j], pw, ph, ints[_BASE_X, j], ints[_BASE_Y, j], lower,
                states, labels, t)
        reals[_BARY, j], reals[_BARY + 1, j], reals[_BARY + 2, j] = _steered_barycentrics(
            reals[_BARY, j], reals[_BARY + 1, j], reals[_BARY + 2, j], matched[0], matched[1], matched[2], softness)


@numba.njit(inline="always")
def _block_weights(count, pw, nc, mode, lum, gamma, gamma_int, beta, gain_k, ints, reals, taps, weights, own):
    """Pass 3: the samples' blend weights, then each of the 12 taps' flat index and weight (bilinear fractions
    shared by the samples, or each sample's ``own`` when they are turned or scaled)."""
    l0_, l1_, l2_ = reals[_LUM], reals[_LUM + 1], reals[_LUM + 2]
    if mode == MODE_HEX:  # the samples' bilinear luminances
        for k in range(3):
            tx_ = reals[_TXK + k] if own else reals[_TX]
            ty_ = reals[_TYK + k] if own else reals[_TY]
            l_ = reals[_LUM + k]
            c0_, c1_, r0_, r1_ = ints[_TEXELS + 4 * k], ints[_TEXELS + 4 * k + 1], ints[_TEXELS + 4 * k + 2], \
                ints[_TEXELS + 4 * k + 3]
            for j in range(count):
                tx, ty = tx_[j], ty_[j]
                l_[j] = ((1.0 - tx) * (1.0 - ty) * lum[r0_[j], c0_[j]] + tx * (1.0 - ty) * lum[r0_[j], c1_[j]]
                         + (1.0 - tx) * ty * lum[r1_[j], c0_[j]] + tx * ty * lum[r1_[j], c1_[j]])
    b0_, b1_, b2_ = reals[_BARY], reals[_BARY + 1], reals[_BARY + 2]
    s0_, s1_, s2_, scale_ = reals[_WEIGHT], reals[_WEIGHT + 1], reals[_WEIGHT + 2], reals[_SCALE]
    for j in range(count):
        s0_[j], s1_[j], s2_[j], scale_[j] = _sample_weights(mode, b0_[j], b1_[j], b2_[j], l0_[j], l1_[j], l2_[j],
                                                            gamma, gamma_int, beta, gain_k)
    for k in range(3):
        tx_ = reals[_TXK + k] if own else reals[_TX]
        ty_ = reals[_TYK + k] if own else reals[_TY]
        s_ = reals[_WEIGHT + k]
        c0_, c1_, r0_, r1_ = ints[_TEXELS + 4 * k], ints[_TEXELS + 4 * k + 1], ints[_TEXELS + 4 * k + 2], \
            ints[_TEXELS + 4 * k + 3]
        t00_, t01_, t10_, t11_ = taps[4 * k], taps[4 * k + 1], taps[4 * k + 2], taps[4 * k + 3]
        w00_, w01_, w10_, w11_ = weights[4 * k], weights[4 * k + 1], weights[4 * k + 2], weights[4 * k + 3]
        for j in range(count):
            tx, ty = tx_[j], ty_[j]
            ws = s_[j] * scale_[j]
            t00_[j], w00_[j] = (r0_[j] * pw + c0_[j]) * nc, ws * ((1.0 - tx) * (1.0 - ty))
            t01_[j], w01_[j] = (r0_[j] * pw + c1_[j]) * nc, ws * (tx * (1.0 - ty))
            t10_[j], w10_[j] = (r1_[j] * pw + c0_[j]) * nc, ws * ((1.0 - tx) * ty)
            t11_[j], w11_[j] = (r1_[j] * pw + c1_[j]) * nc, ws * (tx * ty)


@numba.njit(parallel=True, cache=True, nogil=True)
def _kernel(uv, plane, lum, density_w, density_h, seed, mode, gamma, beta, gain_k, lut, g_min, inv_step, out,
            states, labels, target, softness, rotation, log_range, n_workers):
    n_queries = uv.shape[0]
    ph, pw, nc = plane.shape
    flat = plane.reshape(ph * pw * nc)
    state = jit_seed_state(seed)  # per-call constant part of every vertex hash
    gamma_int = np.int64(gamma) if (gamma == math.floor(gamma) and 1.0 < gamma <= 64.0) else np.int64(0)
    guided = states.shape[0] > 0
    texel_bytes = 4 * nc  # a texel crosses no cache line of an aligned plane when its size divides a line's
    one_line = (flat.ctypes.data % CACHE_LINE == 0) and (CACHE_LINE % texel_bytes == 0)
    n_blocks = (n_queries + BLOCK - 1) // BLOCK
    own = rotation or log_range != 0.0
    for worker in numba.prange(n_workers):  # each worker's scratch allocated once; blocks dealt round-robin
        ints = np.empty((_INT_ROWS, BLOCK), dtype=np.int64)
        reals = np.empty((_REAL_ROWS, BLOCK), dtype=np.float64)
        # two blocks' taps (flat index of each tap's texel) and weights: the block being read and the next one
        taps = np.empty((2, TAPS, BLOCK), dtype=np.int64)
        weights = np.empty((2, TAPS, BLOCK), dtype=np.float32)
        # software pipeline: the taps of block b are computed, then block b - 1 is read and blended while block
        # b's reads are issued (a query's 12 prefetches between two queries' blends), so that at random uv the
        # cache misses of one block overlap the arithmetic of the next, not only each other
        pending_first, pending_count = -1, 0
        for block in range(worker, n_blocks + n_workers, n_workers):
            buffer = (block // n_workers) % 2
            count = 0
            if block < n_blocks:
                first = block * BLOCK
                count = min(BLOCK, n_queries - first)
                _block_lattice(uv, first, count, state, ints, reals)
                _block_texels(count, pw, ph, density_w, density_h, ints, reals, rotation, log_range)
                if guided:
                    _block_guidance(first, count, pw, ph, ints, reals, states, labels, target, softness)
                _block_weights(count, pw, nc, mode, lum, gamma, gamma_int, beta, gain_k, ints, reals, taps[buffer],
                               weights[buffer], own)
                if pending_first < 0:  # the first block: nothing to read yet, its reads issued at once
                    for j in range(count):
                        _prefetch_query(flat, taps[buffer], j, nc, one_line)
            if pending_first >= 0:  # the block before: its reads, blended, while this block's are issued
                earlier = taps[1 - buffer]
                earlier_weights = weights[1 - buffer]
                current = taps[buffer]
                for j in range(min(pending_count, count)):
                    _prefetch_query(flat, current, j, nc, one_line)
                    _blend_taps(flat, earlier, earlier_weights, j, out[pending_first + j])
                for j in range(count, pending_count):
                    _blend_taps(flat, earlier, earlier_weights, j, out[pending_first + j])
                for j in range(pending_count, count):
                    _prefetch_query(flat, current, j, nc, one_line)
                if mode == MODE_HIST:
                    for j in range(pending_count):
                        _inverse_lut(out[pending_first + j], lut, g_min, inv_step)
            pending_first = block * BLOCK if count > 0 else -1
            pending_count = count


@numba.njit(inline="always")
def _prefetch_query(flat, taps, j, nc, one_line):
    """Issue the reads of query ``j`` of a block: its 12 taps' texels (and their last channel's cache line when a
    texel may straddle two)."""
    for m in range(TAPS):
        prefetch(flat, taps[m, j])
    if not one_line:
        for m in range(TAPS):
            prefetch(flat, taps[m, j] + nc - 1)


def _guidance_arguments(guidance: tuple | None, plane_shape: tuple[int, int], n: int) -> tuple:
    """The kernels' guidance arguments ``(states, labels, target, softness)``, checked; empty ones for None."""
    if guidance is None:
        return np.zeros(0, np.int64), np.zeros((1, 1), np.int32), np.zeros(1, np.int32), 1.0
    states, labels, target, softness = guidance
    if np.shape(labels) != tuple(plane_shape) or np.shape(target) != (n,):
        raise InputError(f"guidance: labels {np.shape(labels)} and target {np.shape(target)} do not fit a "
                         f"{tuple(plane_shape)} plane and {n} queries")
    return (np.ascontiguousarray(states, dtype=np.int64), np.ascontiguousarray(labels, dtype=np.int32),
            np.ascontiguousarray(target, dtype=np.int32), float(softness))


def lattice_blend(uv: np.ndarray, plane: np.ndarray, density: tuple[int, int], seed: int, mode: int, *,
                  gamma: float = 1.0, luminance: np.ndarray | None = None, beta: float = 0.0, gain_k: float = 1.0,
                  lut: np.ndarray | None = None, g_min: float = 0.0, step: float = 1.0,
                  out: np.ndarray | None = None, guidance: tuple | None = None, rotation: bool = False,
                  scale_log: float = 0.0) -> np.ndarray:
    """Blend three hashed, whole-texel-offset exemplar samples per query (one fused pass).

    Parameters
    ----------
    uv : float64 ``(N, 2)``
        Positions in exemplar repeats, finite, ``|uv| < 2**52`` (checked with
        :func:`~dynbtf.synthesis.base.check_uv`: beyond, the kernel's int64 arithmetic overflows).
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
    guidance : (states, labels, target, softness), optional
        Exemplar guidance (:class:`~dynbtf.synthesis.guided_blending.GuidedBlending`): the candidates' hash
        states int64 ``(K,)`` (``seed_state`` of each candidate seed, candidate 0 the synthesis seed's), the
        read plane's labels int32 ``(H', W')``, the target label per query int32 ``(N,)`` and the softness.
    rotation : bool
        Turn each sample by its vertex's quarter turns (:mod:`~dynbtf.synthesis.sample_transform`).
    scale_log : float
        ``log(1 + scale_jitter)``: scale each sample by its vertex's factor (0: not scaled).

    Returns
    -------
    float32 ``(N, C)``.
    """
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    check_uv(torch.from_numpy(uv))
    n = uv.shape[0]
    c = plane.shape[2]
    if out is None:
        out = np.empty((n, c), dtype=np.float32)
    if luminance is None:
        luminance = np.zeros((1, 1), dtype=np.float32)
    if lut is None:
        lut = np.zeros((c, 2), dtype=np.float32)
    guided = _guidance_arguments(guidance, plane.shape[:2], n)
    _kernel(uv, cache_aligned(plane),
            np.ascontiguousarray(luminance, dtype=np.float32), int(density[0]), int(density[1]), int(seed) & 0xFFFFFFFF,
            int(mode), float(gamma), float(beta), float(gain_k), np.ascontiguousarray(lut, dtype=np.float32),
            float(g_min), 1.0 / float(step), out, *guided, bool(rotation), float(scale_log),
            max(1, min(numba.get_num_threads(), -(-n // BLOCK))))
    return out


@numba.njit(parallel=True, cache=True, nogil=True)
def _frame_kernel(uv, seed, exponent, out, n_workers):
    n_queries = uv.shape[0]
    state = jit_seed_state(seed)
    exponent_int = np.int64(exponent) if (exponent == math.floor(exponent) and 1.0 < exponent <= 64.0) else np.int64(0)
    n_blocks = (n_queries + BLOCK - 1) // BLOCK
    for worker in numba.prange(n_workers):  # the lattice pass of lattice_blend, then the frame, vectorized
        ints = np.empty((_INT_ROWS, BLOCK), dtype=np.int64)
        reals = np.empty((_REAL_ROWS, BLOCK), dtype=np.float64)
        for block in range(worker, n_blocks, n_workers):
            first = block * BLOCK
            count = min(BLOCK, n_queries - first)
            _block_lattice(uv, first, count, state, ints, reals)
            h0_, h1_, h2_ = ints[_HASH], ints[_HASH + 1], ints[_HASH + 2]
            b0_, b1_, b2_ = reals[_BARY], reals[_BARY + 1], reals[_BARY + 2]
            for j in range(count):
                s0, s1, s2, _ = _sample_weights(MODE_HIST, b0_[j], b1_[j], b2_[j], 0.0, 0.0, 0.0, exponent,
                                                exponent_int, 0.0, 1.0)
                c0, n0 = jit_turn_cos_sin(jit_quarter_turns(h0_[j]))
                c1, n1 = jit_turn_cos_sin(jit_quarter_turns(h1_[j]))
                c2, n2 = jit_turn_cos_sin(jit_quarter_turns(h2_[j]))
                x = s0 * c0 + s1 * c1 + s2 * c2
                y = s0 * n0 + s1 * n1 + s2 * n2
                length = math.sqrt(x * x + y * y)
                zero = length == 0.0
                inverse = 1.0 / (1.0 if zero else length)
                out[first + j, 0] = 1.0 if zero else x * inverse
                out[first + j, 1] = y * inverse


def lattice_frames(uv: np.ndarray, seed: int, exponent: float) -> np.ndarray:
    """``(cos, sin)`` (float64 ``(N, 2)``) of the frame angle of turned lattice samples at ``uv (N, 2)`` float64:
    the circular mean of the three samples' quarter turns weighted by ``b^exponent`` normalized
    (:func:`dynbtf.synthesis.sample_transform.frame_direction`, compiled; uv checked like :func:`lattice_blend`'s)."""
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    check_uv(torch.from_numpy(uv))
    n = uv.shape[0]
    out = np.empty((n, 2), dtype=np.float64)
    _frame_kernel(uv, int(seed) & 0xFFFFFFFF, float(exponent), out,
                  max(1, min(numba.get_num_threads(), -(-n // BLOCK))))
    return out


@numba.njit(inline="always")
def _wrapped(x, period):
    """``x mod period`` in ``[0, period)`` for a float64 texel position."""
    r = x - math.floor(x / period) * period
    return r - period if r >= period else r


@numba.njit(inline="always")
def _level_tap(x, y, ratio_w, ratio_h, mw, mh):
    """Bilinear texels and weights at level-0 texel position ``(x, y)`` in a level of ``mh x mw`` texels.

    ``ratio_w = mw / W0``; returns ``c0, c1, r0, r1, tx, ty`` (wrapped columns/rows, fractions).
    """
    px = x * ratio_w - 0.5
    py = y * ratio_h - 0.5
    fx = math.floor(px)
    fy = math.floor(py)
    c0 = np.int64(fx)  # in [-1, 3 mw): wrapped without a division
    r0 = np.int64(fy)
    while c0 >= mw:
        c0 -= mw
    while r0 >= mh:
        r0 -= mh
    if c0 < 0:
        c0 += mw
    if r0 < 0:
        r0 += mh
    c1 = c0 + 1
    r1 = r0 + 1
    if c1 == mw:
        c1 = 0
    if r1 == mh:
        r1 = 0
    return c0, c1, r0, r1, np.float32(px - fx), np.float32(py - fy)


@numba.njit(inline="always")
def _level_lum(lums, start, mw, mh, x, y, ratio_w, ratio_h):
    """Bilinear luminance of a level (``lums[start:]``, ``mh x mw``) at level-0 texel position ``(x, y)``."""
    c0, c1, r0, r1, tx, ty = _level_tap(x, y, ratio_w, ratio_h, mw, mh)
    a = np.uint64(start)
    return ((1 - tx) * (1 - ty) * lums[a + np.uint64(r0 * mw + c0)] + tx * (1 - ty) * lums[a + np.uint64(r0 * mw + c1)]
            + (1 - tx) * ty * lums[a + np.uint64(r1 * mw + c0)] + tx * ty * lums[a + np.uint64(r1 * mw + c1)])


@numba.njit(inline="always")
def _add_level_sample(flat, start, mw, mh, x, y, ratio_w, ratio_h, weight, row):
    """``row += weight * bilinear(level)`` at level-0 texel position ``(x, y)`` (level at ``flat[start:]``)."""
    nc = row.shape[0]
    c0, c1, r0, r1, tx, ty = _level_tap(x, y, ratio_w, ratio_h, mw, mh)
    w = np.float32(weight)
    w00, w01 = w * (1 - tx) * (1 - ty), w * tx * (1 - ty)
    w10, w11 = w * (1 - tx) * ty, w * tx * ty
    t00 = np.uint64(start + (r0 * mw + c0) * nc)
    t01 = np.uint64(start + (r0 * mw + c1) * nc)
    t10 = np.uint64(start + (r1 * mw + c0) * nc)
    t11 = np.uint64(start + (r1 * mw + c1) * nc)
    for c in range(np.uint64(nc)):
        row[c] += w00 * flat[t00 + c] + w01 * flat[t01 + c] + w10 * flat[t10 + c] + w11 * flat[t11 + c]


@numba.njit(parallel=True, cache=True, nogil=True)
def _filtered_kernel(uv, level, upper_weight, levels, starts, heights, widths, lums, lum_starts, pw, ph,
                     density_w, density_h, seed, mode, gamma, beta, gain_k, luts, g_min, inv_step, out,
                     states, labels, target, softness, rotation, log_range):
    n_queries = uv.shape[0]
    nc = out.shape[1]
    state = jit_seed_state(seed)
    gamma_int = np.int64(gamma) if (gamma == math.floor(gamma) and 1.0 < gamma <= 64.0) else np.int64(0)
    density_w_mod = density_w % pw
    density_h_mod = density_h % ph
    n_levels = starts.shape[0]
    guided = states.shape[0] > 0
    for block in numba.prange((n_queries + BLOCK - 1) // BLOCK):
        row = np.empty(nc, dtype=np.float32)
        for n in range(block * BLOCK, min(block * BLOCK + BLOCK, n_queries)):
            iu, iv, fu, fv, h0, h1, h2, b0, b1, b2, base_x, base_y, lower = lattice_hashes(uv[n, 0], uv[n, 1], state)
            # level-0 texel positions of the three samples in the read plane (whole parts reduced exactly)
            xi = ((iu % pw) * density_w_mod) % pw
            yi = ((iv % ph) * density_h_mod) % ph
            fx = fu * density_w
            fy = fv * density_h
            ox0, oy0 = h0 % pw, jit_mix32(h0 ^ SECOND_STREAM) % ph
            ox1, oy1 = h1 % pw, jit_mix32(h1 ^ SECOND_STREAM) % ph
            ox2, oy2 = h2 % pw, jit_mix32(h2 ^ SECOND_STREAM) % ph
            if guided:  # the point query's candidate search (lattice_blend), at its level-0 bilinear footprint
                cx = modulo(xi + np.int64(math.floor(fx - 0.5)), pw, 1.0 / pw)
                cy = modulo(yi + np.int64(math.floor(fy - 0.5)), ph, 1.0 / ph)
                t = target[n]
                c0, _, r0, _, m0 = _guided_texels(0, h0, cx, cy, pw, ph, base_x, base_y, lower, states, labels, t)
                ox0, oy0 = wrap(c0 - cx, pw), wrap(r0 - cy, ph)
                c0, _, r0, _, m1 = _guided_texels(1, h1, cx, cy, pw, ph, base_x, base_y, lower, states, labels, t)
                ox1, oy1 = wrap(c0 - cx, pw), wrap(r0 - cy, ph)
                c0, _, r0, _, m2 = _guided_texels(2, h2, cx, cy, pw, ph, base_x, base_y, lower, states, labels, t)
                ox2, oy2 = wrap(c0 - cx, pw), wrap(r0 - cy, ph)
                b0, b1, b2 = _steered_barycentrics(b0, b1, b2, m0, m1, m2, softness)
            x0 = wrap(xi + ox0, pw) + fx
            y0 = wrap(yi + oy0, ph) + fy
            x1 = wrap(xi + ox1, pw) + fx
            y1 = wrap(yi + oy1, ph) + fy
            x2 = wrap(xi + ox2, pw) + fx
            y2 = wrap(yi + oy2, ph) + fy
            if rotation or log_range != 0.0:  # each sample turned/scaled about its vertex's pivot, wrapped
                t_x = (fx - 0.5) - math.floor(fx - 0.5)  # the query's fractions from its texel centre
                t_y = (fy - 0.5) - math.floor(fy - 0.5)
                ex, ey = sample_displacement(0, b0, b1, b2, lower, h0, density_w, density_h, t_x, t_y, rotation,
                                             log_range)
                x0, y0 = _wrapped(x0 + ex, pw), _wrapped(y0 + ey, ph)
                ex, ey = sample_displacement(1, b0, b1, b2, lower, h1, density_w, density_h, t_x, t_y, rotation,
                                             log_range)
                x1, y1 = _wrapped(x1 + ex, pw), _wrapped(y1 + ey, ph)
                ex, ey = sample_displacement(2, b0, b1, b2, lower, h2, density_w, density_h, t_x, t_y, rotation,
                                             log_range)
                x2, y2 = _wrapped(x2 + ex, pw), _wrapped(y2 + ey, ph)
            for c in range(nc):
                out[n, c] = 0.0
            t_up = upper_weight[n]
            for step in range(2):
                lv = level[n] + step
                if step == 1 and (t_up == 0.0 or lv >= n_levels):
                    break
                share = np.float32(1.0) - t_up if step == 0 else t_up
                mh = heights[lv]
                mw = widths[lv]
                ratio_w = mw / pw
                ratio_h = mh / ph
                start = starts[lv]
                l0 = l1 = l2 = 0.0
                if mode == MODE_HEX:
                    ls = lum_starts[lv]
                    l0 = _level_lum(lums, ls, mw, mh, x0, y0, ratio_w, ratio_h)
                    l1 = _level_lum(lums, ls, mw, mh, x1, y1, ratio_w, ratio_h)
                    l2 = _level_lum(lums, ls, mw, mh, x2, y2, ratio_w, ratio_h)
                s0, s1, s2, scale = _sample_weights(mode, b0, b1, b2, l0, l1, l2, gamma, gamma_int, beta, gain_k)
                for c in range(nc):
                    row[c] = 0.0
                _add_level_sample(levels, start, mw, mh, x0, y0, ratio_w, ratio_h, s0 * scale, row)
                _add_level_sample(levels, start, mw, mh, x1, y1, ratio_w, ratio_h, s1 * scale, row)
                _add_level_sample(levels, start, mw, mh, x2, y2, ratio_w, ratio_h, s2 * scale, row)
                if mode == MODE_HIST:
                    _inverse_lut(row, luts[lv], g_min, inv_step)
                for c in range(nc):
                    out[n, c] += share * row[c]


@dataclass
class PackedPyramid:
    """A pyramid (:func:`dynbtf.synthesis.mip.area_pyramid`) packed for :func:`filtered_lattice_blend`.

    Attributes: ``flat`` float32 (all levels' texels, level after level), ``starts`` int64 (offset of
    each level in ``flat``), ``heights, widths`` int64, ``shape`` ``(H0, W0, C)``, and the luminance
    pyramid ``lums`` float32 with ``lum_starts`` (hex; zeros otherwise).
    """

    flat: np.ndarray
    starts: np.ndarray
    heights: np.ndarray
    widths: np.ndarray
    shape: tuple[int, int, int]
    lums: np.ndarray
    lum_starts: np.ndarray

    @classmethod
    def pack(cls, levels: list, luminances: list | None = None) -> "PackedPyramid":
        levels = [np.ascontiguousarray(np.asarray(t), dtype=np.float32) for t in levels]
        c = levels[0].shape[2]
        sizes = np.array([t.size for t in levels], dtype=np.int64)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        if luminances is None:
            lums, lum_starts = np.zeros(1, dtype=np.float32), np.zeros(len(levels), dtype=np.int64)
        else:
            lums = np.concatenate([np.asarray(t, dtype=np.float32).reshape(-1) for t in luminances])
            lum_starts = starts // c
        return cls(np.concatenate([t.reshape(-1) for t in levels]), starts,
                   np.array([t.shape[0] for t in levels], dtype=np.int64),
                   np.array([t.shape[1] for t in levels], dtype=np.int64), tuple(levels[0].shape), lums, lum_starts)


def filtered_lattice_blend(uv: np.ndarray, level: np.ndarray, upper_weight: np.ndarray, pyramid: PackedPyramid,
                           density: tuple[int, int], seed: int, mode: int, *, gamma: float = 1.0, beta: float = 0.0,
                           gain_k: float = 1.0, luts: np.ndarray | None = None, g_min: float = 0.0,
                           step: float = 1.0, guidance: tuple | None = None, rotation: bool = False,
                           scale_log: float = 0.0) -> np.ndarray:
    """:func:`lattice_blend` with every sample read from a pyramid (trilinear): the footprint query.

    Parameters
    ----------
    uv : float64 ``(N, 2)``
        Positions in exemplar repeats (checked like :func:`lattice_blend`'s).
    level, upper_weight : int32 ``(N,)``, float32 ``(N,)``
        Lower pyramid level of each query and the weight of the level above
        (:class:`dynbtf.synthesis.mip.LevelOfDetail`).
    pyramid : PackedPyramid
        The read plane's pyramid (level 0 is the plane) and, for hex, its luminance's.
    luts : float32 ``(L, C, S)``
        Per-level inverse tables on the grid ``g_min + k step`` (hist;
        :func:`dynbtf.synthesis.mip.prefiltered_inverse_tables`).
    rotation, scale_log
        The samples' quarter turns and scales, as :func:`lattice_blend`'s (each sample is read at the query's
        level, not one adjusted by its scale: at most ``log2(1 + scale_jitter)`` octaves finer or coarser).

    Each of the three samples sits where the point query reads it (same lattice, hashes and
    whole-texel offsets); at level ``l`` it is a bilinear fetch of level ``l`` at that position.
    Each level is blended (and, for hist, inverted with its table) on its own; the two levels'
    results are mixed with ``upper_weight``. Returns float32 ``(N, C)``.
    """
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    check_uv(torch.from_numpy(uv))
    n_levels = len(pyramid.starts)
    ph, pw, c = pyramid.shape
    out = np.empty((uv.shape[0], c), dtype=np.float32)
    if luts is None:
        luts = np.zeros((n_levels, c, 2), dtype=np.float32)
    level = np.ascontiguousarray(np.clip(level, 0, n_levels - 1), dtype=np.int32)
    _filtered_kernel(uv, level, np.ascontiguousarray(upper_weight, dtype=np.float32), pyramid.flat, pyramid.starts,
                     pyramid.heights, pyramid.widths, pyramid.lums, pyramid.lum_starts, pw, ph, int(density[0]),
                     int(density[1]), int(seed) & 0xFFFFFFFF, int(mode), float(gamma), float(beta), float(gain_k),
                     np.ascontiguousarray(luts, dtype=np.float32), float(g_min), 1.0 / float(step), out,
                     *_guidance_arguments(guidance, (ph, pw), uv.shape[0]), bool(rotation), float(scale_log))
    return out
