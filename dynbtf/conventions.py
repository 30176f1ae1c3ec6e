"""The one place that defines dynbtf's conventions.

Frames and directions
---------------------
* Directions are **unit vectors in the local surface frame**, shape ``(..., 3)``:
  ``x`` along increasing ``u``, ``y`` along increasing ``v``, ``z`` = surface normal.
* Both ``w_view`` (towards the camera) and ``w_light`` (towards the light) point
  **away** from the surface; ``z > 0`` is the upper hemisphere.
* Spherical angles appear only at file-format boundaries: ``theta`` is the polar
  angle from the normal, ``phi`` the azimuth from ``+x`` towards ``+y``, both in
  **degrees** (``theta = acos(z)``, ``phi = atan2(y, x) mod 360``), matching
  btf-extractor.

Spatial coordinates
-------------------
* ``uv`` is measured in units of one exemplar repeat: the measured BTF covers
  ``[0, 1)^2`` and the synthesized BTF is defined for every real ``uv``.
* Image arrays are ``(H, W, 3)``; texel ``[i, j]`` (row ``i``, column ``j``) has its
  centre at ``uv = ((j + 0.5) / W, (i + 0.5) / H)``: columns follow ``u``, rows
  follow ``v`` (so row 0 is ``v = 0`` and is displayed at the top of a PNG).

Values
------
* Colours are **linear RGB float32**.
* Stored BTF values **exclude** ``cos(theta_light)``: a value is the reflectance
  factor ``pi * f_r`` (1 for a white Lambertian surface), with shadowing and
  masking by the surface's own meso-structure included. An image lit by a
  directional light of unit normal irradiance is ``value * cos(theta_light)``;
  a renderer's BSDF ``eval`` returns ``value / pi * cos(theta_light)``.

Rusinkiewicz coordinates
------------------------
``h = normalize(w_view + w_light)``; ``d = R_y(-theta_h) R_z(-phi_h) w_light``: the
light direction expressed in the frame where ``h`` is the pole. Angular feature
planes are indexed by ``(theta, phi)`` of ``h`` or ``d`` mapped to ``[0, 1]^2``:
``s = theta / 90deg`` (clamped), ``t = phi / 360deg`` (wrapped). See
:func:`angular_plane_coords`.

All functions accept NumPy arrays or torch tensors and return the same kind.

Examples
--------
>>> import numpy as np
>>> w = spherical_to_direction(np.array([30.0]), np.array([90.0]))
>>> np.round(w, 6)
array([[0.      , 0.5     , 0.866025]])
>>> h, d = half_diff_from_view_light(w, w)
>>> np.allclose(h, w) and np.allclose(d, [0, 0, 1])
True
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .errors import InputError

try:  # torch is a hard dependency of the package, but keep this module light
    import torch
except ImportError:  # pragma: no cover
    torch = None

__all__ = [
    "spherical_to_direction",
    "direction_to_spherical",
    "half_diff_from_view_light",
    "view_light_from_half_diff",
    "angular_plane_coords",
    "angular_plane_coords_to_direction",
    "texel_centers_uv",
    "check_directions",
    "turn_about_normal",
    "HORIZON_EPS",
]

#: Directions with ``z < -HORIZON_EPS`` are "below the horizon".
HORIZON_EPS = 1e-6


def _is_torch(x: Any) -> bool:
    return torch is not None and isinstance(x, torch.Tensor)


def _stack(xs, like):
    if _is_torch(like):
        return torch.stack(xs, dim=-1)
    return np.stack(xs, axis=-1)


def _xp(x):
    return torch if _is_torch(x) else np


def _asarray(x):
    if _is_torch(x) or isinstance(x, np.ndarray):
        return x
    return np.asarray(x, dtype=np.float64)


def spherical_to_direction(theta_deg, phi_deg):
    """Unit vector(s) from polar angle ``theta`` and azimuth ``phi`` in degrees.

    Parameters
    ----------
    theta_deg, phi_deg : array or tensor, shape ``(...)``
        Angles in degrees (the file-format convention).

    Returns
    -------
    array or tensor, shape ``(..., 3)``: unit vectors in the local frame.
    """
    theta_deg, phi_deg = _asarray(theta_deg), _asarray(phi_deg)
    xp = _xp(theta_deg)
    t = theta_deg * (math.pi / 180.0)
    p = phi_deg * (math.pi / 180.0)
    st = xp.sin(t)
    return _stack([st * xp.cos(p), st * xp.sin(p), xp.cos(t)], theta_deg)


#: ``|(x, y)|`` of a unit vector below which it is taken to be at a pole (phi = 0): 1e-5 (~6e-4 degrees)
#: is well above float32 rounding noise of a rotated vector.
POLE_RADIUS = 1e-5


def direction_to_spherical(w):
    """``(theta, phi)`` in degrees of unit vector(s) ``w`` of shape ``(..., 3)``.

    ``theta = acos(z)`` in ``[0, 180]``; ``phi = atan2(y, x) mod 360`` in ``[0, 360)``,
    and ``phi = 0`` within :data:`POLE_RADIUS` of the poles (where ``x, y`` are rounding
    noise, e.g. the Rusinkiewicz difference vector of a view equal to the light:
    every implementation then agrees on phi).
    """
    w = _asarray(w)
    xp = _xp(w)
    z = xp.clip(w[..., 2], -1.0, 1.0)
    theta = xp.arccos(z) * (180.0 / math.pi)
    pole = w[..., 0] * w[..., 0] + w[..., 1] * w[..., 1] < POLE_RADIUS ** 2
    phi = xp.where(pole, 0.0 * w[..., 0], xp.arctan2(w[..., 1], w[..., 0]) * (180.0 / math.pi))
    phi = xp.remainder(phi, 360.0)
    # remainder can return exactly 360 for tiny negative inputs in float32
    phi = xp.where(phi >= 360.0, phi - 360.0, phi)
    return theta, phi


def _normalize(v):
    xp = _xp(v)
    n = xp.sqrt((v * v).sum(-1))[..., None]
    return v / xp.clip(n, 1e-30, None)


def _rotate_z(v, cos_a, sin_a):
    """Rotate vectors ``v`` (..., 3) about z by angle a (given as cos, sin)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return _stack([cos_a * x - sin_a * y, sin_a * x + cos_a * y, z], v)


def turn_about_normal(w, cos_a, sin_a):
    """Directions ``w (..., 3)`` turned about the normal (z) by the angle ``a`` whose cosine and sine are given
    (``(...)`` each), counter-clockwise seen from above: ``(x cos a - y sin a, x sin a + y cos a, z)``, in ``w``'s
    dtype.

    >>> import numpy as np
    >>> turn_about_normal(np.array([1.0, 0.0, 0.5]), 0.0, 1.0).tolist()
    [0.0, 1.0, 0.5]
    """
    if _is_torch(w):
        cos_a, sin_a = torch.as_tensor(cos_a).to(w), torch.as_tensor(sin_a).to(w)
    return _rotate_z(w, cos_a, sin_a)


def _rotate_y(v, cos_a, sin_a):
    """Rotate vectors ``v`` (..., 3) about y by angle a (given as cos, sin)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return _stack([cos_a * x + sin_a * z, y, -sin_a * x + cos_a * z], v)


def _half_frame(h):
    """cos/sin of theta_h and phi_h of unit half vectors, robust at the pole."""
    xp = _xp(h)
    cos_t = xp.clip(h[..., 2], -1.0, 1.0)
    sin_t = xp.sqrt(xp.clip(1.0 - cos_t * cos_t, 0.0, None))
    rxy = xp.sqrt(h[..., 0] ** 2 + h[..., 1] ** 2)
    pole = rxy < 1e-12
    safe = xp.where(pole, xp.ones_like(rxy), rxy)
    cos_p = xp.where(pole, xp.ones_like(rxy), h[..., 0] / safe)
    sin_p = xp.where(pole, xp.zeros_like(rxy), h[..., 1] / safe)
    return cos_t, sin_t, cos_p, sin_p


def half_diff_from_view_light(w_view, w_light):
    """Rusinkiewicz half and difference vectors of ``(w_view, w_light)``.

    Parameters
    ----------
    w_view, w_light : shape ``(..., 3)``
        Unit vectors in the local frame, pointing away from the surface.

    Returns
    -------
    h, d : shape ``(..., 3)``
        ``h = normalize(w_view + w_light)``; ``d`` is ``w_light`` in the frame
        whose pole is ``h`` (``d = R_y(-theta_h) R_z(-phi_h) w_light``). Swapping
        view and light keeps ``h`` and maps ``d`` to ``(-d_x, -d_y, d_z)``.
        For exactly opposite ``w_view`` and ``w_light`` (not a valid BTF
        configuration) ``h`` is undefined; the normal is used.
    """
    w_view, w_light = _asarray(w_view), _asarray(w_light)
    xp = _xp(w_view)
    s = w_view + w_light
    n2 = (s * s).sum(-1)
    degenerate = n2 < 1e-24
    if xp is np:
        s = np.where(degenerate[..., None], np.array([0.0, 0.0, 1.0], dtype=s.dtype), s)
    else:
        s = torch.where(degenerate[..., None], torch.tensor([0.0, 0.0, 1.0], dtype=s.dtype, device=s.device), s)
    h = _normalize(s)
    cos_t, sin_t, cos_p, sin_p = _half_frame(h)
    d = _rotate_z(w_light, cos_p, -sin_p)
    d = _rotate_y(d, cos_t, -sin_t)
    return h, d


def view_light_from_half_diff(h, d):
    """Inverse of :func:`half_diff_from_view_light`.

    Returns ``(w_view, w_light)``, each ``(..., 3)``: ``w_light = R_z(phi_h) R_y(theta_h) d``
    and ``w_view = 2 (w_light . h) h - w_light`` (the mirror of ``w_light`` about ``h``).
    """
    h, d = _asarray(h), _asarray(d)
    cos_t, sin_t, cos_p, sin_p = _half_frame(h)
    w_light = _rotate_y(d, cos_t, sin_t)
    w_light = _rotate_z(w_light, cos_p, sin_p)
    dot = (w_light * h).sum(-1)[..., None]
    w_view = 2.0 * dot * h - w_light
    return w_view, w_light


def angular_plane_coords(w):
    """Map unit vectors ``(..., 3)`` to angular-plane coordinates ``(..., 2)``.

    Returns ``(s, t)`` with ``s = theta / 90deg`` clamped to ``[0, 1]`` (the
    theta axis clamps; ``d`` may reach ``theta = 90deg``) and
    ``t = phi / 360deg`` in ``[0, 1)`` (the phi axis wraps around). Continuous
    everywhere except the unavoidable phi seam, which wraps. A feature plane of
    ``R x R`` texels samples ``s`` along its rows and ``t`` along its columns,
    with texel centres at ``(k + 0.5) / R``.
    """
    w = _asarray(w)
    xp = _xp(w)
    theta, phi = direction_to_spherical(w)
    s = xp.clip(theta / 90.0, 0.0, 1.0)
    t = phi / 360.0
    return _stack([s, t], w)


def angular_plane_coords_to_direction(st):
    """Inverse of :func:`angular_plane_coords` for ``s`` in ``[0, 1]``: ``(..., 2) -> (..., 3)``."""
    st = _asarray(st)
    return spherical_to_direction(st[..., 0] * 90.0, st[..., 1] * 360.0)


def texel_centers_uv(height: int, width: int, dtype=np.float64) -> np.ndarray:
    """uv of every texel centre of an ``(height, width)`` image, shape ``(H, W, 2)``.

    >>> texel_centers_uv(2, 4)[1, 3]
    array([0.875, 0.75 ])
    """
    v = (np.arange(height, dtype=dtype) + 0.5) / height
    u = (np.arange(width, dtype=dtype) + 0.5) / width
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv], axis=-1)


def check_directions(w, name: str, *, allow_below_horizon: bool = False, atol: float = 1e-3):
    """Validate a direction array; raise ``ValueError`` naming ``name`` if it is bad.

    Checks: last axis of size 3, finite values, unit length within ``atol``,
    and (unless ``allow_below_horizon``) ``z >= -HORIZON_EPS``.
    Returns the input unchanged. Raises :class:`dynbtf.errors.InputError`
    (a ``ValueError``).
    """
    w = _asarray(w)
    shape = tuple(w.shape)
    if len(shape) == 0 or shape[-1] != 3:
        raise InputError(f"{name}: expected directions of shape (..., 3), got shape {shape}")
    xp = _xp(w)
    if not bool(xp.isfinite(w).all()):
        raise InputError(f"{name}: contains NaN or infinite values")
    if w.numel() if _is_torch(w) else w.size:
        norm = xp.sqrt((w * w).sum(-1))
        bad = xp.abs(norm - 1.0) > atol
        if bool(bad.any()):
            worst = float(xp.abs(norm - 1.0).max())
            raise InputError(f"{name}: directions must be unit vectors (|norm - 1| up to {worst:.3g})")
        if not allow_below_horizon and bool((w[..., 2] < -HORIZON_EPS).any()):
            raise InputError(f"{name}: directions below the horizon (z < 0) are not allowed here")
    return w
