"""Compiled CPU kernels of the parallax model (numba): the march through a height plane, and training's
table of visible points.

They live in one module because they share the march and its bilinear, periodic fetch, and numba's on-disk
cache of a kernel is keyed on its own source file only (a helper edited in another file would leave it stale).

**The march.** :func:`dynbtf.representations.parallax.march_visible_uv` is the definition: a torch loop over
shrinking sets of rays that calls a height function once per sample, which serves any height
(a plane, a synthesizer) on any device. Marching the rays through one stored height plane
on the CPU -- what training does for every step's texels, and what a model evaluated on its
own plane does -- is cheaper as one compiled loop per ray: :func:`march_plane` runs the same
search, bisection and interpolation, fetching the plane bilinearly and periodically as
:func:`dynbtf.texture.fetch_wrap` does, in float64.

The two agree to float64 rounding (the bilinear weights are computed in a different order
than ``grid_sample``'s), which ``tests/test_parallax.py`` checks on random fields against the
torch march given the same bilinear height function.

**Training's visible points** (:func:`visible_texel_points`): the table of every view's visible texel points
read, and its missing rows marched (the same rays as :func:`march_plane`), in one loop.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

__all__ = ["march_plane", "visible_texel_points"]


@numba.njit(inline="always")
def _wrapped_fraction(x):
    frac = x - np.floor(x)
    return frac - 1.0 if frac >= 1.0 else frac


@numba.njit(inline="always")
def _bilinear_corners(rows, cols, x, y):
    """The four texels and weights of a bilinear, periodic fetch of a ``(rows, cols)`` plane at uv ``(x, y)``:
    ``(i0, i1, j0, j1, wx, wy)``, the value being ``(1 - wy) ((1 - wx) p[i0, j0] + wx p[i0, j1]) + wy ((1 - wx)
    p[i1, j0] + wx p[i1, j1])``. Texel ``[i, j]`` is centred at ``((j + 0.5) / cols, (i + 0.5) / rows)`` (the
    convention of :func:`dynbtf.texture.fetch_wrap`)."""
    px = _wrapped_fraction(x) * cols + 0.5  # texel j's centre at j + 1 (one wrapped texel before column 0)
    py = _wrapped_fraction(y) * rows + 0.5
    x0, y0 = np.floor(px), np.floor(py)  # in [0, cols] and [0, rows]: texels x0 - 1 and x0, wrapped
    j1, i1 = _wrapped_index(x0, cols), _wrapped_index(y0, rows)
    j0 = j1 - 1 if j1 > 0 else cols - 1
    i0 = i1 - 1 if i1 > 0 else rows - 1
    return i0, i1, j0, j1, px - x0, py - y0


@numba.njit(inline="always")
def _wrapped_index(floor, count):
    """``floor % count`` for ``floor`` in ``[0, count]`` (a branch, not a division); 0 for anything else (NaN)."""
    index = int(floor) if 0.0 <= floor < count else 0
    return index


@numba.njit(inline="always")
def _height_at(plane, x, y):
    """Bilinear, periodic fetch of ``plane (H, W)`` at uv ``(x, y)`` (see :func:`_bilinear_corners`)."""
    i0, i1, j0, j1, wx, wy = _bilinear_corners(plane.shape[0], plane.shape[1], x, y)
    top = (1.0 - wx) * plane[i0, j0] + wx * plane[i0, j1]
    bottom = (1.0 - wx) * plane[i1, j0] + wx * plane[i1, j1]
    return (1.0 - wy) * top + wy * bottom


#: Rays below which :func:`march_plane` marches on the calling thread: waking the parallel workers costs more
#: than it saves there (measured in training, while the decoder's threads hold both cores).
PARALLEL_MARCH_RAYS = 1024


@numba.njit(inline="always")
def _march_ray(u, v, sx, sy, plane, h_min, h_max, step, max_step, surface_slope):
    """The visible point ``(x, y)`` of the ray through ``(u, v)`` with slope ``(sx, sy)`` (see :func:`march_plane`)."""
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
    return u + z * sx, v + z * sy


@numba.njit(parallel=True, cache=True, nogil=True, error_model="numpy")
def _march_parallel(uv, slope, plane, h_min, h_max, step, max_step, surface_slope, out):  # pragma: no cover
    for i in numba.prange(uv.shape[0]):
        out[i, 0], out[i, 1] = _march_ray(uv[i, 0], uv[i, 1], slope[i, 0], slope[i, 1], plane, h_min, h_max, step,
                                          max_step, surface_slope)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _march_serial(uv, slope, plane, h_min, h_max, step, max_step, surface_slope, out):  # pragma: no cover
    for i in range(uv.shape[0]):
        out[i, 0], out[i, 1] = _march_ray(uv[i, 0], uv[i, 1], slope[i, 0], slope[i, 1], plane, h_min, h_max, step,
                                          max_step, surface_slope)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def visible_texel_points(slots, texels, centres, slope, plane, h_min, h_max, step, max_step, surface_slope,
                         table_points, table_heights, marched, points, heights):  # pragma: no cover - compiled
    """Training's visible-point table (:class:`~dynbtf.representations.parallax.VisibleTexelCache`) read, and the
    rows it does not hold yet marched, in one loop.

    ``texels (G, n)`` int64 under the views of slots ``slots (G,)`` whose ray slopes are ``slope (G, 2)``;
    ``centres (T, 2)`` float64 the texel centres; ``plane (H, W)`` float64 the height field (uv units) the rows
    are marched through, between ``h_min`` and ``h_max``, with the march parameters of :func:`march_plane`.
    The table is ``table_points (V * T, 2)`` and ``table_heights (V * T,)`` (float32) with ``marched (V * T,)``;
    a row ``slot * T + texel`` not marched yet gets its visible point (wrapped to ``[0, 1)``) and the height there.
    Writes ``points (G, n, 2)`` and ``heights (G, n)`` (float32).
    """
    n_texels = centres.shape[0]
    for g in range(texels.shape[0]):
        sx, sy = slope[g, 0], slope[g, 1]
        base = slots[g] * n_texels
        for k in range(texels.shape[1]):
            texel = texels[g, k]
            row = base + texel
            if not marched[row]:
                x, y = _march_ray(centres[texel, 0], centres[texel, 1], sx, sy, plane, h_min, h_max, step,
                                  max_step, surface_slope)
                table_heights[row] = _height_at(plane, x, y)
                table_points[row, 0] = _wrapped_fraction(x)
                table_points[row, 1] = _wrapped_fraction(y)
                marched[row] = True
            points[g, k, 0] = table_points[row, 0]
            points[g, k, 1] = table_points[row, 1]
            heights[g, k] = table_heights[row]


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
    march = _march_parallel if len(uv_np) >= PARALLEL_MARCH_RAYS else _march_serial  # same rays, same values
    march(uv_np, slope_np, plane_np, float(h_min), float(h_max), float(step), float(max_step), float(surface_slope),
          out)
    return torch.from_numpy(out)
