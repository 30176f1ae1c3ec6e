"""Fused CPU kernel of a Triple Plane decoder's first layer, for the synthesized BTF's fast path.

Layer 1 of the Triple Plane decoder is ``W_U f_U + W_H f_H(h) + W_D f_D(d) + b``.
Its angular part is folded into the angular planes once: bilinear interpolation
is linear, so ``W_H fetch(f_H, st) = fetch(f_H W_H^T, st)`` -- a ``(R, R, hidden)``
plane read gives layer 1's angular contribution directly (no 16 -> 32 product
per query). The positional part arrives as synthesized (decorrelated) latent
features with the synthesizer's output map already folded into ``W_U``.

Per query the kernel computes the Rusinkiewicz half and difference vectors,
their angular-plane coordinates and the two clamped/wrapped bilinear fetches
exactly as :func:`dynbtf.conventions.half_diff_from_view_light`,
:func:`dynbtf.conventions.angular_plane_coords` and
:func:`dynbtf.texture.fetch_angular` do (tested against them), adds the
positional product and the bias, and writes the pre-activation ``(N, hidden)``.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

__all__ = ["fold_angular_planes", "first_layer_preactivation"]

_RAD_TO_TURN_S = 180.0 / math.pi / 90.0  # radians -> theta / 90deg
_RAD_TO_TURN_T = 180.0 / math.pi / 360.0  # radians -> phi / 360deg


def fold_angular_planes(f_h: torch.Tensor, f_d: torch.Tensor, weight_angular: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(f_H W_H^T, f_D W_D^T)`` as float32 ``(R, R, hidden)`` arrays; ``weight_angular`` is ``(hidden, C_H + C_D)``."""
    ch = f_h.shape[-1]
    ph = f_h.detach().float() @ weight_angular[:, :ch].detach().float().T
    pd = f_d.detach().float() @ weight_angular[:, ch:].detach().float().T
    return (np.ascontiguousarray(ph.cpu().numpy(), dtype=np.float32),
            np.ascontiguousarray(pd.cpu().numpy(), dtype=np.float32))


@numba.njit(inline="always")
def _plane_coords(x, y, z):
    """(s, t) of a unit vector: theta / 90deg clamped to [0, 1], phi / 360deg in [0, 1)."""
    zc = min(max(z, -1.0), 1.0)
    s = math.acos(zc) * _RAD_TO_TURN_S
    s = min(max(s, 0.0), 1.0)
    t = math.atan2(y, x) * _RAD_TO_TURN_T
    t = t - math.floor(t)
    if t >= 1.0:
        t -= 1.0
    return s, t


@numba.njit(inline="always")
def _accumulate_fetch(plane, s, t, acc):
    """acc += bilinear fetch of ``plane (R_s, R_t, K)`` at (s, t): rows clamp, columns wrap."""
    rs, rt, k = plane.shape
    y = min(max(s * rs - 0.5, 0.0), rs - 1.0)
    x = t * rt - 0.5
    y0 = min(int(math.floor(y)), rs - 2) if rs > 1 else 0
    ty = y - y0 if rs > 1 else 0.0
    x0f = math.floor(x)
    tx = x - x0f
    x0 = int(x0f) % rt
    x1 = (x0 + 1) % rt
    y1 = min(y0 + 1, rs - 1)
    w00 = (1 - tx) * (1 - ty)
    w01 = tx * (1 - ty)
    w10 = (1 - tx) * ty
    w11 = tx * ty
    for j in range(k):
        acc[j] += w00 * plane[y0, x0, j] + w01 * plane[y0, x1, j] + w10 * plane[y1, x0, j] + w11 * plane[y1, x1, j]


@numba.njit(parallel=True, cache=True)
def _kernel(latent, w_pos, bias, w_view, w_light, plane_h, plane_d, out):
    n, c = latent.shape
    hidden = w_pos.shape[1]
    for q in numba.prange(n):
        acc = out[q]
        for j in range(hidden):
            acc[j] = bias[j]
        for i in range(c):
            f = latent[q, i]
            for j in range(hidden):
                acc[j] += f * w_pos[i, j]
        vx, vy, vz = np.float64(w_view[q, 0]), np.float64(w_view[q, 1]), np.float64(w_view[q, 2])
        lx, ly, lz = np.float64(w_light[q, 0]), np.float64(w_light[q, 1]), np.float64(w_light[q, 2])
        sx, sy, sz = vx + lx, vy + ly, vz + lz
        n2 = sx * sx + sy * sy + sz * sz
        if n2 < 1e-24:
            sx, sy, sz = 0.0, 0.0, 1.0
            n2 = 1.0
        inv = 1.0 / max(math.sqrt(n2), 1e-30)
        hx, hy, hz = sx * inv, sy * inv, sz * inv
        cos_t = min(max(hz, -1.0), 1.0)
        sin_t = math.sqrt(max(1.0 - cos_t * cos_t, 0.0))
        rxy = math.sqrt(hx * hx + hy * hy)
        if rxy < 1e-12:
            cos_p, sin_p = 1.0, 0.0
        else:
            cos_p, sin_p = hx / rxy, hy / rxy
        # d = R_y(-theta_h) R_z(-phi_h) w_light
        ax = cos_p * lx + sin_p * ly
        ay = -sin_p * lx + cos_p * ly
        dx = cos_t * ax - sin_t * lz
        dz = sin_t * ax + cos_t * lz
        s, t = _plane_coords(hx, hy, hz)
        _accumulate_fetch(plane_h, s, t, acc)
        s, t = _plane_coords(dx, ay, dz)
        _accumulate_fetch(plane_d, s, t, acc)


def first_layer_preactivation(latent: np.ndarray, w_pos: np.ndarray, bias: np.ndarray, w_view: np.ndarray,
                              w_light: np.ndarray, plane_h: np.ndarray, plane_d: np.ndarray,
                              out: np.ndarray | None = None) -> np.ndarray:
    """Layer-1 pre-activation ``(N, hidden)`` float32 of a Triple Plane decoder.

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
    """
    n = latent.shape[0]
    if out is None:
        out = np.empty((n, w_pos.shape[1]), dtype=np.float32)
    _kernel(np.ascontiguousarray(latent, dtype=np.float32), np.ascontiguousarray(w_pos, dtype=np.float32),
            np.ascontiguousarray(bias, dtype=np.float32), np.ascontiguousarray(w_view, dtype=np.float32),
            np.ascontiguousarray(w_light, dtype=np.float32), plane_h, plane_d, out)
    return out
