"""Micro-scale reflectance: a clear-coated GGX microfacet BRDF with a Lambertian base.

All functions are elementwise torch code on broadcastable tensors of cosines
(measured against the *local* shading normal ``n`` of the meso-scale surface,
not the macro normal). Dot products are written out component by component so
the result of one (view, light) pair never depends on how many pairs are
evaluated together (bitwise reproducible under any batching).

Model (``x = n . w`` cosines, ``h = normalize(v + l)``)::

    D(h)      = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)             GGX / Trowbridge-Reitz
    G1(x)     = 2 x / (x + sqrt(a^2 + (1 - a^2) x^2))             Smith, uncorrelated
    F(c)      = F0 + (1 - F0) (1 - c)^5                           Schlick
    spec      = D G1(n.l) G1(n.v) F(v.h) / (4 (n.l) (n.v))
    base      = albedo / pi + spec(alpha, F0)
    f_r       = coat * [spec(coat_alpha, coat_F0) + (1 - Fc(n.l)) (1 - Fc(n.v)) base]
                + (1 - coat) * base

:func:`layered_brdf` returns ``pi * f_r`` (the reflectance factor convention of
:mod:`dynbtf.conventions`). ``a`` is the GGX roughness (``alpha = roughness^2`` of
the Disney convention is *not* applied: parameters are alphas).
"""

from __future__ import annotations

import math

import torch

__all__ = ["ggx_ndf", "smith_g1", "schlick_fresnel", "ggx_specular", "layered_brdf", "dot3"]


def dot3(a, b) -> torch.Tensor:
    """``sum_k a[..., k] * b[..., k]`` written out (batch-independent rounding)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def ggx_ndf(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution ``D`` (per steradian of micro-normal) at ``cos(n, h)``."""
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    d = c2 * (a2 - 1.0) + 1.0
    return a2 / (math.pi * d * d)


def smith_g1(cos_w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Smith masking of GGX for a direction at ``cos(n, w) > 0``."""
    a2 = alpha * alpha
    return 2.0 * cos_w / (cos_w + torch.sqrt(a2 + (1.0 - a2) * cos_w * cos_w))


def schlick_fresnel(f0, cos_d: torch.Tensor) -> torch.Tensor:
    """Schlick's Fresnel approximation with normal-incidence reflectance ``f0``."""
    m = (1.0 - cos_d).clamp(0.0, 1.0)
    m2 = m * m
    return f0 + (1.0 - f0) * (m2 * m2 * m)


def ggx_specular(cos_l, cos_v, cos_h, cos_d, alpha, f0) -> torch.Tensor:
    """Microfacet specular lobe ``f_spec`` (1/sr) for positive ``cos_l, cos_v``."""
    num = ggx_ndf(cos_h, alpha) * smith_g1(cos_l, alpha) * smith_g1(cos_v, alpha) * schlick_fresnel(f0, cos_d)
    return num / (4.0 * cos_l * cos_v)


def layered_brdf(cos_l, cos_v, cos_h, cos_d, *, albedo, alpha, f0, coat, coat_alpha, coat_f0) -> torch.Tensor:
    """``pi * f_r`` of the clear-coated microfacet model (see module docstring).

    Parameters
    ----------
    cos_l, cos_v : tensors ``(...)``
        Cosines of light and view with the local normal; must be > 0 (callers
        mask the rest).
    cos_h, cos_d : tensors ``(...)``
        ``n . h`` and ``v . h`` with ``h = normalize(v + l)``.
    albedo : tensor ``(..., 3)``
        Lambertian base albedo (linear RGB).
    alpha, f0, coat : tensors ``(...)``
        Base GGX roughness, base specular reflectance at normal incidence, and
        clear-coat weight in ``[0, 1]``.
    coat_alpha, coat_f0 : float
        Clear-coat GGX roughness and reflectance at normal incidence.

    Returns
    -------
    tensor ``(..., 3)``: ``pi * f_r``.
    """
    spec = ggx_specular(cos_l, cos_v, cos_h, cos_d, alpha, f0)
    base = albedo * (1.0 / math.pi) + spec[..., None]
    ca = torch.as_tensor(coat_alpha, dtype=cos_l.dtype, device=cos_l.device)
    coat_spec = ggx_specular(cos_l, cos_v, cos_h, cos_d, ca, coat_f0)
    transmit = (1.0 - schlick_fresnel(coat_f0, cos_l)) * (1.0 - schlick_fresnel(coat_f0, cos_v))
    coated = coat_spec[..., None] + transmit[..., None] * base
    c = coat[..., None]
    return math.pi * (c * coated + (1.0 - c) * base)
