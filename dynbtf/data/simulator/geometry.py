"""Meso-scale geometry of a periodic height field: normals, parallax/masking, cast shadows.

The sample is a height field ``z = h(u, v)`` over the unit torus (period 1 in
``u`` and ``v``), tabulated on a ``(G, G)`` grid (point ``[i, j]`` at
``uv = ((j + 0.5) / G, (i + 0.5) / G)``) and interpolated bilinearly with
periodic wrap (:func:`dynbtf.texture.fetch_wrap`). Heights are in **uv units**
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

All functions take torch tensors and run on their device.
"""

from __future__ import annotations

import math

import torch

from ...texture import fetch_wrap

__all__ = [
    "normals_from_height",
    "grid_points_uv",
    "trace_view",
    "horizon_tangent",
    "light_visibility",
    "sky_view_factor",
]

#: March step of the view and shadow rays, in grid cells (horizontal distance).
STEP_CELLS = 0.5


def grid_points_uv(size: int, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """uv of the ``(size, size)`` grid points, shape ``(size * size, 2)``, row-major."""
    c = (torch.arange(size, dtype=dtype, device=device) + 0.5) / size
    v, u = torch.meshgrid(c, c, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def normals_from_height(height: torch.Tensor) -> torch.Tensor:
    """Unit surface normals ``(G, G, 3)`` of a periodic height field ``(G, G)`` (uv units).

    Central differences with wrap: ``n = normalize(-dh/du, -dh/dv, 1)``, ``u`` along
    columns (x), ``v`` along rows (y).

    >>> import torch
    >>> g = 8; u = (torch.arange(g, dtype=torch.float64) + 0.5) / g
    >>> n = normals_from_height(0.0 * u[None, :] + 0.0 * u[:, None])
    >>> n[3, 4].tolist()
    [0.0, 0.0, 1.0]
    """
    g_rows, g_cols = height.shape
    dhdu = (torch.roll(height, -1, dims=1) - torch.roll(height, 1, dims=1)) * (g_cols / 2.0)
    dhdv = (torch.roll(height, -1, dims=0) - torch.roll(height, 1, dims=0)) * (g_rows / 2.0)
    n = torch.stack([-dhdu, -dhdv, torch.ones_like(height)], dim=-1)
    return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)


def _fetch_height(height_plane: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    return fetch_wrap(height_plane, uv)[..., 0].to(uv.dtype)


def trace_view(height: torch.Tensor, w_view, uv: torch.Tensor, *, refine: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the camera ray through each reference-plane point first hits the height field.

    Parameters
    ----------
    height : ``(G, G)`` tensor
        Periodic height field in uv units.
    w_view : sequence of 3 floats
        View direction (towards the camera), unit vector with ``z > 0``.
    uv : float64 ``(N, 2)`` tensor
        Points of the reference plane ``z = 0`` (e.g. output texel centres).
    refine : int
        Bisection steps after the linear search (each halves the error).

    Returns
    -------
    hit_uv : float64 ``(N, 2)``
        uv of the visible surface point (not wrapped; fetches wrap).
    hit_z : float64 ``(N,)``
        Its height.

    Notes
    -----
    The ray through ``p`` at height ``z`` is at ``p + z * (w_x, w_y) / w_z``. It is
    marched from the field's maximum down to its minimum in steps of at most
    :data:`STEP_CELLS` grid cells horizontally; the first step below the surface
    brackets the intersection, which bisection then refines. A vertical ray hits
    ``h(p)`` directly. Features thinner than a step can be missed (never more
    than half a grid cell).
    """
    g = height.shape[0]
    plane = height[..., None].to(torch.float32)
    wx, wy, wz = (float(c) for c in w_view)
    slope = torch.tensor([wx / wz, wy / wz], dtype=uv.dtype, device=uv.device)
    h_max, h_min = float(height.max()), float(height.min())
    reach = (h_max - h_min) * math.hypot(wx, wy) / wz * g  # horizontal ray length, in grid cells
    if reach < 1e-6:
        z = _fetch_height(plane, uv)
        return uv.clone(), z
    n_steps = max(2, int(math.ceil(reach / STEP_CELLS)))
    dz = (h_max - h_min) / n_steps
    # a tiny margin above the maximum so the first sample is always above the surface
    z_top = h_max + 1e-9
    z_hi = torch.full(uv.shape[:1], z_top, dtype=uv.dtype, device=uv.device)   # above the surface
    z_lo = torch.full_like(z_hi, h_min)                                          # at or below it
    found = torch.zeros(uv.shape[:1], dtype=torch.bool, device=uv.device)
    z_prev = z_top
    for k in range(1, n_steps + 1):
        z = z_top - k * dz if k < n_steps else h_min
        todo = ~found
        if not bool(todo.any()):
            break
        idx = todo.nonzero(as_tuple=True)[0]
        below = _fetch_height(plane, uv[idx] + z * slope) >= z
        hit_idx = idx[below]
        z_lo[hit_idx] = z
        z_hi[hit_idx] = z_prev
        found[hit_idx] = True
        z_prev = z
    for _ in range(refine):
        z_mid = 0.5 * (z_hi + z_lo)
        below = _fetch_height(plane, uv + z_mid[:, None] * slope) >= z_mid
        z_lo = torch.where(below, z_mid, z_lo)
        z_hi = torch.where(below, z_hi, z_mid)
    # final secant step between the bracketing heights
    f_hi = _fetch_height(plane, uv + z_hi[:, None] * slope) - z_hi   # < 0 (above the surface)
    f_lo = _fetch_height(plane, uv + z_lo[:, None] * slope) - z_lo   # >= 0
    t = (f_lo / (f_lo - f_hi).clamp_min(1e-30)).clamp(0.0, 1.0)
    z = z_lo + t * (z_hi - z_lo)
    return uv + z[:, None] * slope, z


def horizon_tangent(height: torch.Tensor, azimuth_xy, max_distance: float) -> torch.Tensor:
    """Tangent of the horizon elevation of every grid point towards one azimuth.

    ``tan(beta)(x) = max_{0 < r <= max_distance} (h(x + r a) - h(x)) / r`` with ``a``
    the unit horizontal direction ``azimuth_xy`` and ``r`` sampled every
    :data:`STEP_CELLS` grid cells (the first sample gives the local slope, so a
    facet turned away from the light is in its own shadow). Returns ``(G, G)``;
    ``-inf`` where ``max_distance`` is shorter than one step.
    """
    g = height.shape[0]
    plane = height[..., None].to(torch.float32)
    pts = grid_points_uv(g, device=height.device)
    h0 = height.reshape(-1).to(torch.float64)
    a = torch.tensor([float(azimuth_xy[0]), float(azimuth_xy[1])], dtype=torch.float64, device=height.device)
    step = STEP_CELLS / g
    n = int(math.floor(max_distance / step + 1e-9))
    best = torch.full_like(h0, -math.inf)
    for k in range(1, n + 1):
        r = k * step
        best = torch.maximum(best, (_fetch_height(plane, pts + r * a) - h0) / r)
    return best.reshape(g, g)


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
