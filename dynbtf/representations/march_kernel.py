"""Fused CPU kernel of the parallax march through a height plane (numba).

:func:`dynbtf.representations.parallax.march_visible_uv` is the definition: a torch loop over
shrinking sets of rays that calls a height function once per sample, which serves any height
(a plane, a synthesizer) on any device. Marching the rays through one stored height plane
on the CPU -- what training does for every step's texels, and what a model evaluated on its
own plane does -- is cheaper as one compiled loop per ray: :func:`march_plane` runs the same
search, bisection and interpolation, fetching the plane bilinearly and periodically as
:func:`dynbtf.texture.fetch_wrap` does, in float64.

The two agree to float64 rounding (the bilinear weights are computed in a different order
than ``grid_sample``'s), which ``tests/test_parallax.py`` checks on random fields against the
torch march given the same bilinear height function.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

__all__ = ["march_plane"]


@numba.njit(inline="always")
def _wrapped_fraction(x):
    frac = x - math.floor(x)
    return frac - 1.0 if frac >= 1.0 else frac


@numba.njit(inline="always")
def _height_at(plane, x, y):
    """Bilinear, periodic fetch of ``plane (H, W)`` at uv ``(x, y)``: texel ``[i, j]`` centred at
    ``((j + 0.5) / W, (i + 0.5) / H)`` (the convention of :func:`dynbtf.texture.fetch_wrap`)."""
    rows, cols = plane.shape
    px = _wrapped_fraction(x) * cols + 0.5  # texel j's centre at j + 1 (one wrapped texel before column 0)
    py = _wrapped_fraction(y) * rows + 0.5
    x0, y0 = math.floor(px), math.floor(py)
    wx, wy = px - x0, py - y0
    j0, j1 = (int(x0) - 1) % cols, int(x0) % cols
    i0, i1 = (int(y0) - 1) % rows, int(y0) % rows
    top = (1.0 - wx) * plane[i0, j0] + wx * plane[i0, j1]
    bottom = (1.0 - wx) * plane[i1, j0] + wx * plane[i1, j1]
    return (1.0 - wy) * top + wy * bottom


@numba.njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def _march_kernel(uv, slope, plane, h_min, h_max, step, max_step, surface_slope, out):  # pragma: no cover - compiled
    for i in numba.prange(uv.shape[0]):
        u, v, sx, sy = uv[i, 0], uv[i, 1], slope[i, 0], slope[i, 1]
        length = max(math.sqrt(sx * sx + sy * sy), 1e-12)  # horizontal uv per unit of z
        shortest, longest, fine = step / length, max_step / length, step * (1.0 + 1e-6) / length
        f_hi = _height_at(plane, u + h_max * sx, v + h_max * sy) - h_max
        z_hi, z_lo, f_lo = h_max, h_max, f_hi
        bracketed = f_hi >= 0.0
        done = bracketed
        while not done:
            inside = bracketed
            gap = min(max(-f_hi / (1.0 + surface_slope * length), shortest), longest)
            search = max(z_hi - gap, h_min)
            z = 0.5 * (z_lo + z_hi) if inside else search
            f = _height_at(plane, u + z * sx, v + z * sy) - z
            below = (f >= 0.0) or (not inside and search <= h_min)
            if below:
                z_lo, f_lo = z, f
            else:
                z_hi, f_hi = z, f
            bracketed = inside or below
            done = bracketed and z_hi - z_lo <= fine
        t = f_lo / (f_lo - f_hi)  # fraction of the bracket back up
        t = 0.0 if math.isnan(t) else min(max(t, 0.0), 1.0)
        z = z_lo + t * (z_hi - z_lo)
        out[i, 0] = u + z * sx
        out[i, 1] = v + z * sy


def march_plane(uv: torch.Tensor, slope: torch.Tensor, plane: torch.Tensor, *, h_min: float, h_max: float,
                step: float, max_step: float, surface_slope: float) -> torch.Tensor:
    """:func:`~dynbtf.representations.parallax.march_visible_uv` through a height plane, on the CPU.

    Parameters
    ----------
    uv : ``(N, 2)`` float64
        Reference-plane points, uv units.
    slope : ``(N, 2)`` float64
        Each ray's uv displacement per unit of height (:func:`~dynbtf.representations.parallax.view_offsets`).
    plane : ``(H, W)``
        The height field at the texel centres, uv units (read as float64, periodic).
    h_min, h_max, step, max_step, surface_slope : float
        As :func:`~dynbtf.representations.parallax.march_visible_uv` (validated there).

    Returns
    -------
    ``(N, 2)`` float64 CPU tensor: the visible points (not wrapped).
    """
    uv_np = np.ascontiguousarray(uv.detach().cpu().numpy(), dtype=np.float64)
    slope_np = np.ascontiguousarray(slope.detach().cpu().numpy(), dtype=np.float64)
    plane_np = np.ascontiguousarray(plane.detach().cpu().numpy(), dtype=np.float64)
    out = np.empty_like(uv_np)
    _march_kernel(uv_np, slope_np, plane_np, float(h_min), float(h_max), float(step), float(max_step),
                  float(surface_slope), out)
    return torch.from_numpy(out)
