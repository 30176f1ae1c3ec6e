"""Fused CPU kernel of a Triple Plane decoder's first layer, for the synthesized BTF's fast path.

Layer 1 of the Triple Plane decoder is ``W_U f_U + W_H f_H(h) + W_D f_D(d) + b``.
Its angular part is folded into the angular planes once: bilinear interpolation
is linear, so ``W_H fetch(f_H, st) = fetch(f_H W_H^T, st)`` -- a ``(R, R, hidden)``
plane read gives layer 1's angular contribution directly (no 16 -> 32 product
per query). The positional part arrives as synthesized (decorrelated) latent
features with the synthesizer's output map already folded into ``W_U``.

:func:`first_layer_preactivation` applies the positional product and the bias
as one BLAS matmul (a 16 -> 32 product per query is what BLAS does best), then
the angular kernel adds, per query, the two clamped/wrapped bilinear fetches at
the Rusinkiewicz half and difference vectors' angular-plane coordinates, as
:func:`dynbtf.conventions.half_diff_from_view_light`,
:func:`dynbtf.conventions.angular_plane_coords` and
:func:`dynbtf.texture.fetch_angular` define them (tested against them in
float64), and optionally the LeakyReLU. The kernel works on blocks of queries
in structure-of-arrays form with branch-free float64 arithmetic and a
polynomial ``atan2`` (:func:`_atan2`, error ~1e-15 rad) instead of libm's
``acos``/``atan2`` calls, so the direction math vectorizes across queries.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from ..conventions import POLE_RADIUS
from .fused_mlp import native_affine_rows

__all__ = ["fold_angular_planes", "first_layer_preactivation", "all_unit_vectors"]

_RAD_TO_TURN_S = 180.0 / math.pi / 90.0  # radians -> theta / 90deg
_RAD_TO_TURN_T = 180.0 / math.pi / 360.0  # radians -> phi / 360deg


def fold_angular_planes(f_h: torch.Tensor, f_d: torch.Tensor, weight_angular: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(f_H W_H^T, f_D W_D^T)`` as float32 ``(R, R, hidden)`` arrays; ``weight_angular`` is ``(hidden, C_H + C_D)``."""
    ch = f_h.shape[-1]
    ph = f_h.detach().float() @ weight_angular[:, :ch].detach().float().T
    pd = f_d.detach().float() @ weight_angular[:, ch:].detach().float().T
    return (np.ascontiguousarray(ph.cpu().numpy(), dtype=np.float32),
            np.ascontiguousarray(pd.cpu().numpy(), dtype=np.float32))


def _fit_atan_polynomial(degree: int = 9) -> tuple[float, ...]:
    """Coefficients ``c_0..c_degree`` of ``atan(r) / r ~ sum_i c_i r^(2i)`` for ``|r| <= tan(pi/8)``.

    A Chebyshev least-squares fit in ``z = r^2`` (deterministic, done at import), converted to
    monomials for Horner's rule: max error of ``r * poly(r^2)`` vs ``atan`` ~1e-15 rad.
    """
    z_max = math.tan(math.pi / 8) ** 2
    z = z_max * (1.0 - np.cos(np.linspace(0.0, math.pi, 2001))) / 2.0
    r = np.sqrt(z)
    target = np.ones_like(z)
    target[1:] = np.arctan(r[1:]) / r[1:]
    fit = np.polynomial.Chebyshev.fit(z, target, degree, domain=[0.0, z_max])
    return tuple(float(c) for c in fit.convert(kind=np.polynomial.Polynomial, domain=[0.0, z_max],
                                               window=[0.0, z_max]).coef)


#: Highest coefficient first (Horner).
_ATAN_POLY = _fit_atan_polynomial()[::-1]
_TAN_PI_8 = math.tan(math.pi / 8)


@numba.njit(inline="always")
def _atan2(y, x):
    """``atan2(y, x)`` in radians, ``(-pi, pi]``, float64, branch-free (so loops over it vectorize).

    Octant reduction to ``a = min(|x|, |y|) / max(|x|, |y|)`` in ``[0, 1]``, above ``tan(pi/8)``
    ``atan(a) = pi/4 + atan((a - 1) / (a + 1))``, then the polynomial :data:`_ATAN_POLY`; error
    ~1e-15 rad (tested against ``np.arctan2``). ``atan2(0, 0) = 0``. It vectorizes, where libm's
    ``atan2`` and ``acos`` are calls per value.
    """
    ax = abs(x)
    ay = abs(y)
    lo = min(ax, ay)
    hi = max(max(ax, ay), 1e-300)
    big = lo > _TAN_PI_8 * hi  # a = lo / hi > tan(pi/8): r = (a - 1) / (a + 1), one division either way
    r = (lo - hi if big else lo) / (lo + hi if big else hi)
    z = r * r
    p = 0.0
    for c in _ATAN_POLY:
        p = p * z + c
    angle = r * p + (0.25 * math.pi if big else 0.0)
    angle = 0.5 * math.pi - angle if ay > ax else angle
    angle = math.pi - angle if x < 0.0 else angle
    return -angle if y < 0.0 else angle


@numba.njit(inline="always")
def _plane_taps(x, y, z, rs, rt, k):
    """Bilinear taps of a ``(rs, rt, k)`` angular plane at the direction ``(x, y, z)`` (float64 unit vector).

    ``s = theta / 90deg = atan2(|(x, y)|, z) / (pi / 2)`` clamped to [0, 1] (equal to ``acos(z)``
    for a unit vector, and well conditioned at the pole); ``t = phi / 360deg = atan2(y, x) / 2 pi``
    wrapped to [0, 1). Rows clamp, columns wrap. Returns the flat start index ``(row * rt + col) * k``
    of the four texels and their weights (float64).
    """
    r = math.sqrt(x * x + y * y)
    s = _atan2(r, z) * _RAD_TO_TURN_S
    s = min(max(s, 0.0), 1.0)
    t = 0.0 if r < POLE_RADIUS else _atan2(y, x) * _RAD_TO_TURN_T  # as direction_to_spherical
    t = t - math.floor(t)
    t = t - 1.0 if t >= 1.0 else t
    row = min(max(s * rs - 0.5, 0.0), rs - 1.0)
    row0 = min(math.floor(row), max(rs - 2.0, 0.0))
    ty = row - row0
    row1 = min(row0 + 1.0, rs - 1.0)
    col = t * rt - 0.5
    col0 = math.floor(col)
    tx = col - col0
    col0 = rt - 1.0 if col0 < 0.0 else col0
    col1 = 0.0 if col0 + 1.0 >= rt else col0 + 1.0
    i00 = np.int32((row0 * rt + col0) * k)
    i01 = np.int32((row0 * rt + col1) * k)
    i10 = np.int32((row1 * rt + col0) * k)
    i11 = np.int32((row1 * rt + col1) * k)
    return i00, i01, i10, i11, (1.0 - tx) * (1.0 - ty), tx * (1.0 - ty), (1.0 - tx) * ty, tx * ty


@numba.njit(inline="always")
def _add_taps_and_activate(row, flat_h, flat_d, taps, weights, q, slope):
    """``row += sum`` of the 8 weighted plane rows of query ``q``, then ``max(v, 0) + slope min(v, 0)``.

    Unsigned indices: numba then skips the negative-index wraparound and the loop vectorizes (~2x).
    """
    i0, i1, i2, i3 = np.uint64(taps[0, q]), np.uint64(taps[1, q]), np.uint64(taps[2, q]), np.uint64(taps[3, q])
    i4, i5, i6, i7 = np.uint64(taps[4, q]), np.uint64(taps[5, q]), np.uint64(taps[6, q]), np.uint64(taps[7, q])
    w0, w1, w2, w3 = weights[0, q], weights[1, q], weights[2, q], weights[3, q]
    w4, w5, w6, w7 = weights[4, q], weights[5, q], weights[6, q], weights[7, q]
    for j in range(np.uint64(row.shape[0])):
        v = (row[j] + w0 * flat_h[i0 + j] + w1 * flat_h[i1 + j] + w2 * flat_h[i2 + j] + w3 * flat_h[i3 + j]
             + w4 * flat_d[i4 + j] + w5 * flat_d[i5 + j] + w6 * flat_d[i6 + j] + w7 * flat_d[i7 + j])
        row[j] = max(v, np.float32(0.0)) + slope * min(v, np.float32(0.0))


#: Queries per block of the angular kernel (its per-query arithmetic runs as one loop over the block).
_BLOCK = 256


# error_model="numpy": no zero-division checks (branches that stop loops from vectorizing)
@numba.njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def _angular_kernel(w_view, w_light, plane_h, plane_d, slope, out):
    """``out[q] += fetch(plane_h, h_q) + fetch(plane_d, d_q)``, then LeakyReLU with ``slope`` (1: none)."""
    n, hidden = out.shape
    rs_h, rt_h, k_h = plane_h.shape
    rs_d, rt_d, k_d = plane_d.shape
    flat_h = plane_h.reshape(rs_h * rt_h * k_h)
    flat_d = plane_d.reshape(rs_d * rt_d * k_d)
    for block in numba.prange((n + _BLOCK - 1) // _BLOCK):
        first = block * _BLOCK
        count = min(_BLOCK, n - first)
        taps = np.empty((8, _BLOCK), dtype=np.int32)
        weights = np.empty((8, _BLOCK), dtype=np.float32)
        view = np.empty((3, _BLOCK), dtype=np.float64)  # structure of arrays: the loop below vectorizes
        light = np.empty((3, _BLOCK), dtype=np.float64)
        for c in range(3):
            for i in range(count):
                view[c, i] = w_view[first + i, c]
                light[c, i] = w_light[first + i, c]
        for i in range(count):  # straight-line float64 arithmetic: vectorizes across queries
            vx, vy, vz = view[0, i], view[1, i], view[2, i]
            lx, ly, lz = light[0, i], light[1, i], light[2, i]
            sx, sy, sz = vx + lx, vy + ly, vz + lz
            n2 = sx * sx + sy * sy + sz * sz
            degenerate = n2 < 1e-24  # opposite directions: h is undefined, use the normal
            sx = 0.0 if degenerate else sx
            sy = 0.0 if degenerate else sy
            sz = 1.0 if degenerate else sz
            inv = 1.0 / math.sqrt(1.0 if degenerate else n2)
            hx, hy, hz = sx * inv, sy * inv, sz * inv
            cos_t = min(max(hz, -1.0), 1.0)
            sin_t = math.sqrt(max(1.0 - cos_t * cos_t, 0.0))
            rxy = math.sqrt(hx * hx + hy * hy)
            pole = rxy < 1e-12
            inv_rxy = 1.0 / (1.0 if pole else rxy)
            cos_p = 1.0 if pole else hx * inv_rxy
            sin_p = 0.0 if pole else hy * inv_rxy
            # d = R_y(-theta_h) R_z(-phi_h) w_light
            ax = cos_p * lx + sin_p * ly
            ay = -sin_p * lx + cos_p * ly
            dx = cos_t * ax - sin_t * lz
            dz = sin_t * ax + cos_t * lz
            t0, t1, t2, t3, a0, a1, a2, a3 = _plane_taps(hx, hy, hz, rs_h, rt_h, k_h)
            t4, t5, t6, t7, a4, a5, a6, a7 = _plane_taps(dx, ay, dz, rs_d, rt_d, k_d)
            taps[0, i], taps[1, i], taps[2, i], taps[3, i] = t0, t1, t2, t3
            taps[4, i], taps[5, i], taps[6, i], taps[7, i] = t4, t5, t6, t7
            weights[0, i], weights[1, i], weights[2, i], weights[3, i] = a0, a1, a2, a3
            weights[4, i], weights[5, i], weights[6, i], weights[7, i] = a4, a5, a6, a7
        for i in range(count):
            _add_taps_and_activate(out[first + i], flat_h, flat_d, taps, weights, i, slope)


def first_layer_preactivation(latent: np.ndarray, w_pos: np.ndarray, bias: np.ndarray, w_view: np.ndarray,
                              w_light: np.ndarray, plane_h: np.ndarray, plane_d: np.ndarray,
                              out: np.ndarray | None = None, negative_slope: float | None = None,
                              positional: np.ndarray | None = None) -> np.ndarray:
    """Layer-1 pre-activation ``(N, hidden)`` float32 of a Triple Plane decoder (or its LeakyReLU).

    Parameters
    ----------
    latent : float32 ``(N, C)``
        Positional inputs (e.g. synthesized decorrelated features).
    w_pos : float32 ``(C, hidden)``
        Positional weights (transposed), with any output map folded in.
    bias : float32 ``(hidden,)``
        Layer-1 bias plus the folded output-map offset.
    w_view, w_light : float32 ``(N, 3)``
        Unit directions in the local frame.
    plane_h, plane_d : float32 ``(R, R, hidden)``
        Angular planes folded with their layer-1 weights (:func:`fold_angular_planes`).
    out : float32 ``(N, hidden)``, optional
        Output buffer.
    negative_slope : float, optional
        If given, return ``LeakyReLU(pre-activation)`` with this slope (fused: one pass less).
    positional : float32 ``(N, hidden)``, optional
        The positional part and bias already computed (e.g. with per-query weights): used
        instead of ``latent @ w_pos + bias`` (then ``latent``, ``w_pos`` and ``bias`` are unused).
    """
    if positional is not None:
        out = np.ascontiguousarray(positional, dtype=np.float32)
        _angular_kernel(np.ascontiguousarray(w_view, dtype=np.float32),
                        np.ascontiguousarray(w_light, dtype=np.float32),
                        np.ascontiguousarray(plane_h, dtype=np.float32), np.ascontiguousarray(plane_d, dtype=np.float32),
                        np.float32(1.0 if negative_slope is None else negative_slope), out)
        return out
    n = latent.shape[0]
    if out is None:
        out = np.empty((n, w_pos.shape[1]), dtype=np.float32)
    # the positional product, a small dense matmul: the native kernel's row-by-row products (what BLAS does at
    # this size, but each row's sum the same whatever the chunk or thread it is computed in), else BLAS
    latent = np.ascontiguousarray(latent, dtype=np.float32)
    w_pos = np.ascontiguousarray(w_pos, dtype=np.float32)
    bias = np.ascontiguousarray(bias, dtype=np.float32)
    if not native_affine_rows(latent, w_pos, bias, out):
        torch.addmm(torch.from_numpy(bias), torch.from_numpy(latent), torch.from_numpy(w_pos), out=torch.from_numpy(out))
    _angular_kernel(np.ascontiguousarray(w_view, dtype=np.float32), np.ascontiguousarray(w_light, dtype=np.float32),
                    np.ascontiguousarray(plane_h, dtype=np.float32), np.ascontiguousarray(plane_d, dtype=np.float32),
                    np.float32(1.0 if negative_slope is None else negative_slope), out)
    return out


@numba.njit(cache=True, error_model="numpy")
def _all_unit_vectors(w, atol):
    # |norm - 1| <= atol as bounds on the squared norm, counted without an early exit: the loop vectorizes
    low, high = max(1.0 - atol, 0.0) ** 2, (1.0 + atol) ** 2
    bad = 0
    for q in range(w.shape[0]):
        x, y, z = np.float64(w[q, 0]), np.float64(w[q, 1]), np.float64(w[q, 2])
        squared = x * x + y * y + z * z
        bad += np.int64(not ((squared >= low) & (squared <= high)))  # NaN and inf fail too
    return bad == 0


def all_unit_vectors(w: np.ndarray, atol: float = 1e-3) -> bool:
    """Whether every row of ``w (N, 3)`` (float32/64) is finite with ``|norm - 1| <= atol``: one pass.

    The fast twin of the checks of :func:`dynbtf.conventions.check_directions` with
    ``allow_below_horizon=True`` (callers run that function for the error message when this is False).
    """
    return bool(_all_unit_vectors(np.ascontiguousarray(w), float(atol)))
