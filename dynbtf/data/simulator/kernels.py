"""Fused CPU kernels of the simulator (numba): per-pair shading and height-field marching.

Computes exactly the value of :meth:`HeightFieldRenderer._shade_torch
<dynbtf.data.simulator.renderer.HeightFieldRenderer>` -- the clear-coated GGX
model of :mod:`.shading` times the local irradiance ratio and shadow
visibility, plus the interreflection fill -- in one pass per element instead of
~40 whole-array torch operations (memory bound on a CPU). It is what the
renderer uses on the CPU; the torch path serves every other device and is the
reference the tests compare this kernel to.

The marching kernels (:func:`trace_view_kernel`, :func:`horizon_tangent_kernel`)
do per grid point what :func:`.geometry.trace_view` and
:func:`.geometry.horizon_tangent` do with whole-field shifts in torch (their
implementation on other devices and their reference in the tests).

Arithmetic is float64 inside, float32 out.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["shade_view", "horizon_tangent_kernel", "trace_view_kernel"]


@numba.njit(inline="always")
def _spec(cl, cv, ch, cd, alpha, f0):
    """GGX f_spec (1/sr): D G1(l) G1(v) F / (4 cl cv); mirrors shading.ggx_specular."""
    a2 = alpha * alpha
    d = ch * ch * (a2 - 1.0) + 1.0
    ndf = a2 / (math.pi * d * d)
    g1l = 2.0 / (cl + math.sqrt(a2 + (1.0 - a2) * cl * cl))
    g1v = 2.0 / (cv + math.sqrt(a2 + (1.0 - a2) * cv * cv))
    m = min(max(1.0 - cd, 0.0), 1.0)
    fres = f0 + (1.0 - f0) * (m * m * m * m * m)
    return ndf * g1l * g1v * 0.25 * fres


@numba.njit(inline="always")
def _schlick(f0, c):
    m = min(max(1.0 - c, 0.0), 1.0)
    return f0 + (1.0 - f0) * (m * m * m * m * m)


@numba.njit(parallel=True, cache=True)
def _shade_kernel(lights, half, cos_d, view, vis_maps, taps, weights, e_mean, normals, albedo, alpha, f0, coat,
                  fill, coat_alpha, coat_f0, has_coat, grazing_cos, out):
    n_lights = lights.shape[0]
    n_texels = normals.shape[0]
    for li in numba.prange(n_lights):
        lx, ly, lz = lights[li, 0], lights[li, 1], lights[li, 2]
        hx, hy, hz = half[li, 0], half[li, 1], half[li, 2]
        cd = cos_d[li]
        inv_macro = 1.0 / max(lz, 1e-6)
        em = e_mean[li]
        for t in range(n_texels):
            nx, ny, nz = normals[t, 0], normals[t, 1], normals[t, 2]
            cl_raw = nx * lx + ny * ly + nz * lz
            vis = (weights[t, 0] * vis_maps[li, taps[t, 0]] + weights[t, 1] * vis_maps[li, taps[t, 1]]
                   + weights[t, 2] * vis_maps[li, taps[t, 2]] + weights[t, 3] * vis_maps[li, taps[t, 3]])
            direct = max(cl_raw, 0.0) * vis * inv_macro
            cl = max(cl_raw, 1e-6)
            cv = max(nx * view[0] + ny * view[1] + nz * view[2], grazing_cos)
            ch = min(max(nx * hx + ny * hy + nz * hz, 0.0), 1.0)
            pi_spec = math.pi * _spec(cl, cv, ch, cd, alpha[t], f0[t])
            through = 1.0
            pi_coat = 0.0
            if has_coat:
                c = coat[t]
                transmit = (1.0 - _schlick(coat_f0, cl)) * (1.0 - _schlick(coat_f0, cv))
                through = 1.0 - c + c * transmit
                pi_coat = math.pi * c * _spec(cl, cv, ch, cd, coat_alpha, coat_f0)
            for k in range(3):
                value = ((albedo[t, k] + pi_spec) * through + pi_coat) * direct
                out[li, t, k] = value + fill[t, k] * em


def shade_view(w_lights, w_view, vis_maps, taps, weights, e_mean, normals, albedo, alpha, f0, coat, fill, *,
               coat_alpha: float, coat_f0: float, has_coat: bool, grazing_cos: float) -> np.ndarray:
    """Values ``(L, N, 3)`` float32 of one view for ``L`` lights at ``N`` traced texels.

    Parameters
    ----------
    w_lights : float ``(L, 3)``; w_view : float ``(3,)``
        Unit directions (local frame, pointing away from the surface).
    vis_maps : float32 ``(L, G * G)``
        Cast-shadow visibility maps of the lights, flattened row-major.
    taps, weights : ``(N, 4)``
        Bilinear interpolation of the maps at the texels' hit points
        (:func:`dynbtf.data.simulator.geometry.bilinear_taps`).
    e_mean : float ``(L,)``
        Mean macro-relative irradiance per light (fill term; zeros disable it).
    normals, albedo : float32 ``(N, 3)``; alpha, f0, coat : float32 ``(N,)``
        Material at the hit points.
    fill : float32 ``(N, 3)``
        ``albedo * mean_albedo * (1 - sky)`` per texel.
    """
    lights = np.ascontiguousarray(w_lights, dtype=np.float64).reshape(-1, 3)
    view = np.ascontiguousarray(w_view, dtype=np.float64).reshape(3)
    half = view[None, :] + lights
    half /= np.sqrt((half * half).sum(-1, keepdims=True))
    cos_d = np.clip((half * view[None, :]).sum(-1), 0.0, 1.0)
    n_texels = normals.shape[0]
    out = np.empty((len(lights), n_texels, 3), dtype=np.float32)
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    _shade_kernel(lights, half, cos_d, view, f32(vis_maps), np.ascontiguousarray(taps, dtype=np.int64), f32(weights),
                  np.ascontiguousarray(e_mean, dtype=np.float64),
                  f32(normals), f32(albedo), f32(alpha), f32(f0), f32(coat), f32(fill),
                  float(coat_alpha), float(coat_f0), bool(has_coat), float(grazing_cos), out)
    return out


# --------------------------------------------------------------------------- height-field marching
@numba.njit(inline="always")
def _sample_periodic(h, x, y):
    """Bilinear, periodic sample of ``h`` (G, G) at grid coordinates ``(x, y)`` (column, row)."""
    g = h.shape[0]
    x0 = math.floor(x)
    y0 = math.floor(y)
    fx = x - x0
    fy = y - y0
    j0 = int(x0) % g
    i0 = int(y0) % g
    j1 = (j0 + 1) % g
    i1 = (i0 + 1) % g
    top = h[i0, j0] + (h[i0, j1] - h[i0, j0]) * fx
    bottom = h[i1, j0] + (h[i1, j1] - h[i1, j0]) * fx
    return top + (bottom - top) * fy


@numba.njit(parallel=True, cache=True)
def horizon_tangent_kernel(h, ax, ay, step_cells, n_steps, out):
    """``out[i, j] = max_k (h(x + r_k a) - h(x)) / r_k``, ``r_k = k step_cells`` grid cells (see geometry)."""
    g = h.shape[0]
    for i in numba.prange(g):
        for j in range(g):
            h0 = h[i, j]
            best = -math.inf
            for k in range(1, n_steps + 1):
                r = k * step_cells
                val = _sample_periodic(h, j + r * ax, i + r * ay)
                t = (val - h0) * g / r
                if t > best:
                    best = t
            out[i, j] = best


@numba.njit(parallel=True, cache=True)
def trace_view_kernel(h, slope_x, slope_y, stride, z_top, dz, h_min, n_steps, z_hit):
    """First intersection height of each output texel's camera ray (see geometry.trace_view)."""
    g = h.shape[0]
    s = g // stride
    first = stride // 2
    for i in numba.prange(s):
        for j in range(s):
            gi = stride * i + first
            gj = stride * j + first
            f_prev = -1e-9
            z_prev = z_top
            hit = h_min
            for k in range(1, n_steps + 1):
                z = z_top - k * dz if k < n_steps else h_min
                f = _sample_periodic(h, gj + z * slope_x * g, gi + z * slope_y * g) - z
                if f >= 0.0:
                    t = min(max(f / (f - f_prev), 0.0), 1.0)
                    hit = z + t * (z_prev - z)
                    break
                f_prev = f
                z_prev = z
            z_hit[i * s + j] = hit
