"""Meso-scale geometry of a periodic height field: normals, parallax/masking, cast shadows.

The sample is a height field ``z = h(u, v)`` over the unit torus (period 1 in
``u`` and ``v``), tabulated on a ``(G, G)`` grid (point ``[i, j]`` at
``uv = ((j + 0.5) / G, (i + 0.5) / G)``) and interpolated bilinearly with
periodic wrap. Heights are in **uv units**
(the same unit as the exemplar's side length), so a height of ``0.01`` seen at
``theta = 45 deg`` shifts by ``0.01`` in uv. The **reference plane** -- the plane a
measurement rectifies its images to -- is ``z = 0`` (the materials' mean height).

Three operations make the BTF effects a per-texel BRDF cannot produce:

* :func:`trace_view` -- **parallax and masking**: the camera ray through a point
  of the reference plane is marched down into the height field; the first
  intersection is what that texel shows (higher points shift towards the
  camera, points hidden behind bumps disappear).
* :func:`light_visibility` -- **cast shadows**: per light direction, the horizon
  elevation of every grid point along the light's azimuth; a point is lit when
  the light is above its horizon (with a soft edge of the light's angular size).
* :func:`sky_view_factor` -- the cosine-weighted fraction of the sky a point sees
  (used for the one-bounce interreflection fill-in of the renderer).

All functions take torch tensors and run on their device: whole-field torch
shifts in general, the equivalent per-point numba kernels of :mod:`.kernels`
on the CPU (several times faster there).
"""

from __future__ import annotations

import math

import numpy as np
import torch


__all__ = [
    "normals_from_height",
    "shift_periodic",
    "bilinear_taps",
    "interpolate_taps",
    "trace_view",
    "horizon_tangent",
    "light_visibility",
    "sky_view_factor",
]

#: March step of the view and shadow rays, in grid cells (horizontal distance).
STEP_CELLS = 0.5

#: Force the whole-field torch marching on the CPU too (tests compare it with the numba kernels).
_TORCH_MARCHING = False


def bilinear_taps(uv: torch.Tensor, grid: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Periodic bilinear interpolation of ``(grid, grid)`` fields at ``uv`` ``(N, 2)``: flat indices and weights.

    Returns ``taps`` int64 ``(N, 4)`` into a row-major flattened field and
    ``weights`` float32 ``(N, 4)`` (summing to 1): ``sum_k weights[:, k] * field.reshape(-1)[taps[:, k]]``
    is the bilinear, wrapped value, with grid point ``[i, j]`` at
    ``((j + .5) / grid, (i + .5) / grid)`` (the convention of
    :func:`dynbtf.texture.fetch_wrap`). Computed once per view, it serves every
    field and every light's shadow map.

    >>> import torch
    >>> taps, w = bilinear_taps(torch.tensor([[0.25, 0.0]], dtype=torch.float64), 2)
    >>> taps.tolist(), w.tolist()                  # halfway between rows 1 (wrapped) and 0
    ([[2, 3, 0, 1]], [[0.5, 0.0, 0.5, 0.0]])
    """
    x = uv[:, 0] * grid - 0.5
    y = uv[:, 1] * grid - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    j0 = torch.remainder(x0.to(torch.int64), grid)
    i0 = torch.remainder(y0.to(torch.int64), grid)
    j1, i1 = (j0 + 1) % grid, (i0 + 1) % grid
    taps = torch.stack([i0 * grid + j0, i0 * grid + j1, i1 * grid + j0, i1 * grid + j1], dim=-1)
    weights = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], dim=-1)
    return taps, weights.to(torch.float32)


def interpolate_taps(values: torch.Tensor, taps: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Apply :func:`bilinear_taps`: ``values`` ``(..., G * G)`` -> ``(..., N)``.

    (On the CPU the gather runs in NumPy, which is several times faster than
    torch's advanced indexing there; elsewhere in torch.)
    """
    if values.device.type == "cpu":
        v, t, w = values.numpy(), taps.numpy(), weights.numpy()
        out = v[..., t[:, 0]] * w[:, 0]
        for k in range(1, 4):
            out += v[..., t[:, k]] * w[:, k]
        return torch.from_numpy(out)
    out = values[..., taps[:, 0]] * weights[:, 0]
    for k in range(1, 4):
        out = out + values[..., taps[:, k]] * weights[:, k]
    return out


def normals_from_height(height: torch.Tensor) -> torch.Tensor:
    """Unit surface normals ``(G, G, 3)`` of a periodic height field ``(G, G)`` (uv units).

    Central differences with wrap: ``n = normalize(-dh/du, -dh/dv, 1)``, ``u`` along
    columns (x), ``v`` along rows (y).

    >>> import math, torch
    >>> g = 64; u = (torch.arange(g, dtype=torch.float64) + 0.5) / g
    >>> n = normals_from_height(0.01 * torch.sin(2 * math.pi * u)[None, :].expand(g, g))
    >>> slope = -n[0, 0, 0] / n[0, 0, 2]        # dh/du at u ~ 0: 0.02 pi
    >>> round(float(slope), 3), round(0.02 * math.pi, 3)
    (0.063, 0.063)
    """
    g_rows, g_cols = height.shape
    dhdu = (torch.roll(height, -1, dims=1) - torch.roll(height, 1, dims=1)) * (g_cols / 2.0)
    dhdv = (torch.roll(height, -1, dims=0) - torch.roll(height, 1, dims=0)) * (g_rows / 2.0)
    n = torch.stack([-dhdu, -dhdv, torch.ones_like(height)], dim=-1)
    return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)


def shift_periodic(field: torch.Tensor, offset_cells) -> torch.Tensor:
    """``field(x + offset)`` at every grid point ``x``: a bilinear, periodic shift of a ``(G, G)`` field.

    ``offset_cells = (dx, dy)`` in grid cells (``x`` along columns, ``y`` along
    rows). Equal to a bilinear periodic fetch at the shifted grid points, but
    costs four rolls (no per-point gather), which is what makes marching cheap.

    >>> import torch
    >>> f = torch.arange(4.0).view(1, 4).expand(2, 4)
    >>> shift_periodic(f, (0.5, 0.0))[0].tolist()
    [0.5, 1.5, 2.5, 1.5]
    """
    dx, dy = float(offset_cells[0]), float(offset_cells[1])
    ix, iy = math.floor(dx), math.floor(dy)
    fx, fy = dx - ix, dy - iy
    a = torch.roll(field, shifts=(-iy, -ix), dims=(0, 1))
    b = torch.roll(a, shifts=-1, dims=1)
    top = a + (b - a) * fx if fx else a
    if not fy:
        return top
    c = torch.roll(a, shifts=-1, dims=0)
    d = torch.roll(b, shifts=-1, dims=0)
    bottom = c + (d - c) * fx if fx else c
    return top + (bottom - top) * fy


def trace_view(height: torch.Tensor, w_view, stride: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the camera rays through the output texels first hit the height field.

    Parameters
    ----------
    height : ``(G, G)`` tensor
        Periodic height field in uv units.
    w_view : sequence of 3 floats
        View direction (towards the camera), unit vector with ``z > 0``.
    stride : int
        Odd number of grid cells per output texel: the output has ``S = G / stride``
        texels per side, and texel ``[i, j]`` (centre ``((j + .5) / S, (i + .5) / S)``)
        is grid point ``[stride * i + stride // 2, stride * j + stride // 2]``.

    Returns
    -------
    hit_uv : float64 ``(S * S, 2)``
        uv of the visible surface point of each texel, row-major (not wrapped).
    hit_z : float64 ``(S * S,)``
        Its height.

    Notes
    -----
    The ray through reference-plane point ``p`` is at ``p + z * (w_x, w_y) / w_z``
    at height ``z``. It is marched from the field's maximum down to its minimum
    in steps of at most :data:`STEP_CELLS` grid cells horizontally (every step is
    the same offset for all texels: one :func:`shift_periodic`); the first sample
    at or below the surface and the one before bracket the intersection, which
    is then placed by linear interpolation of ``h - z`` between them. A vertical
    ray hits ``h(p)`` directly. Features narrower than a step can be missed.
    """
    g = height.shape[0]
    stride = int(stride)
    if stride < 1 or stride % 2 == 0 or g % stride:
        raise ValueError(f"stride must be an odd divisor of the grid size {g}, got {stride}")
    first = stride // 2
    s = g // stride
    texels = height[first::stride, first::stride].reshape(-1)
    c = (torch.arange(s, dtype=torch.float64, device=height.device) + 0.5) / s
    vv, uu = torch.meshgrid(c, c, indexing="ij")
    uv = torch.stack([uu.reshape(-1), vv.reshape(-1)], dim=-1)
    wx, wy, wz = (float(x) for x in w_view)
    slope = (wx / wz, wy / wz)
    h_max, h_min = float(height.max()), float(height.min())
    reach = (h_max - h_min) * math.hypot(wx, wy) / wz * g  # horizontal ray length, in grid cells
    if reach < 1e-6:
        return uv, texels.to(torch.float64)
    n_steps = max(2, int(math.ceil(reach / STEP_CELLS)))
    dz = (h_max - h_min) / n_steps
    z_top = h_max + 1e-9 * max(1.0, abs(h_max))
    if height.device.type == "cpu" and not _TORCH_MARCHING:
        from .kernels import trace_view_kernel

        z_np = np.empty(s * s, dtype=np.float64)
        trace_view_kernel(height.numpy().astype(np.float64), slope[0], slope[1], stride, z_top, dz, h_min,
                          n_steps, z_np)
        z_hit = torch.from_numpy(z_np)
        return uv + z_hit[:, None] * torch.tensor(slope, dtype=torch.float64), z_hit
    f_prev = texels.new_full(texels.shape, -1e-9)            # h - z at the previous sample (< 0)
    z_hit = torch.full(texels.shape, h_min, dtype=torch.float64, device=height.device)
    found = torch.zeros(texels.shape, dtype=torch.bool, device=height.device)
    for k in range(1, n_steps + 1):
        z = z_top - k * dz if k < n_steps else h_min
        shifted = shift_periodic(height, (z * slope[0] * g, z * slope[1] * g))
        f = shifted[first::stride, first::stride].reshape(-1) - z
        new = (f >= 0.0) & ~found
        if bool(new.any()):
            t = (f / (f - f_prev)).clamp(0.0, 1.0)            # fraction of the step back up
            z_k = z + t * (z_top - (k - 1) * dz - z)
            z_hit = torch.where(new, z_k.to(torch.float64), z_hit)
            found |= new
            if bool(found.all()):
                break
        f_prev = f
    hit = uv + z_hit[:, None] * torch.tensor(slope, dtype=torch.float64, device=height.device)
    return hit, z_hit


def horizon_tangent(height: torch.Tensor, azimuth_xy, max_distance: float) -> torch.Tensor:
    """Tangent of the horizon elevation of every grid point towards one azimuth.

    ``tan(beta)(x) = max_{0 < r <= max_distance} (h(x + r a) - h(x)) / r`` with ``a``
    the unit horizontal direction ``azimuth_xy`` and ``r`` sampled every
    :data:`STEP_CELLS` grid cells (the first sample gives the local slope, so a
    facet turned away from the light is in its own shadow). Returns ``(G, G)``;
    ``-inf`` where ``max_distance`` is shorter than one step.
    """
    g = height.shape[0]
    ax, ay = float(azimuth_xy[0]), float(azimuth_xy[1])
    step = STEP_CELLS / g
    n = int(math.floor(max_distance / step + 1e-9))
    if height.device.type == "cpu" and not _TORCH_MARCHING:
        from .kernels import horizon_tangent_kernel

        out = np.empty((g, g), dtype=np.float64)
        horizon_tangent_kernel(height.numpy().astype(np.float64), ax, ay, STEP_CELLS, n, out)
        return torch.from_numpy(out).to(height.dtype)
    best = torch.full_like(height, -math.inf)
    for k in range(1, n + 1):
        r = k * step
        best = torch.maximum(best, (shift_periodic(height, (r * ax * g, r * ay * g)) - height) * (1.0 / r))
    return best


def light_visibility(height: torch.Tensor, w_light, *, spread_deg: float = 2.0) -> torch.Tensor:
    """Cast-shadow visibility in ``[0, 1]`` of every grid point for one light direction, ``(G, G)``.

    The light (unit vector ``w_light``, towards the light) has elevation
    ``alpha = 90 deg - theta_light``; a point whose horizon elevation ``beta``
    towards the light's azimuth (:func:`horizon_tangent`, searched as far as the
    field's height range can cast a shadow) is below ``alpha`` is lit. The edge
    is a smoothstep of width ``spread_deg`` (the angular size of the lamp), which
    also anti-aliases shadow boundaries. A light at the zenith lights everything.
    """
    wx, wy, wz = (float(c) for c in w_light)
    rxy = math.hypot(wx, wy)
    g = height.shape[0]
    if rxy < 1e-9:
        return torch.ones((g, g), dtype=torch.float32, device=height.device)
    relief = float(height.max() - height.min())
    alpha = math.degrees(math.atan2(wz, rxy))
    # below elevation alpha - spread/2 nothing can shade; search that far
    tan_lo = math.tan(math.radians(max(alpha - 0.5 * spread_deg, 0.5)))
    max_distance = relief / tan_lo + STEP_CELLS / g
    beta = torch.rad2deg(torch.atan(horizon_tangent(height, (wx / rxy, wy / rxy), max_distance)))
    x = ((alpha - beta) / spread_deg + 0.5).clamp(0.0, 1.0)
    return (x * x * (3.0 - 2.0 * x)).to(torch.float32)


def sky_view_factor(height: torch.Tensor, *, n_azimuths: int = 8, max_elevation_deg: float = 80.0) -> torch.Tensor:
    """Cosine-weighted fraction of the sky each grid point sees, ``(G, G)`` in ``[0, 1]``.

    Averages ``cos^2(max(beta, 0))`` over ``n_azimuths`` evenly spaced azimuths,
    ``beta`` being the horizon elevation (:func:`horizon_tangent`, searched as far
    as the field's relief can raise a horizon above 5 deg, and clamped to
    ``max_elevation_deg``). 1 for a flat field.
    """
    g = height.shape[0]
    relief = float(height.max() - height.min())
    # horizons lower than 5 deg hardly matter for cos^2; search the distance that could raise one to 5 deg
    max_distance = min(relief / math.tan(math.radians(5.0)), 0.5)
    total = torch.zeros((g, g), dtype=torch.float64, device=height.device)
    for k in range(n_azimuths):
        phi = 2.0 * math.pi * k / n_azimuths
        tb = horizon_tangent(height, (math.cos(phi), math.sin(phi)), max_distance).clamp_min(0.0)
        tb = tb.clamp_max(math.tan(math.radians(max_elevation_deg)))
        total += 1.0 / (1.0 + tb * tb)  # cos^2(beta) = 1 / (1 + tan^2)
    return (total / n_azimuths).to(torch.float32)
