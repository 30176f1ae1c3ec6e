"""Micro-scale reflectance: a clear-coated GGX microfacet BRDF with a Lambertian base.

All functions are elementwise torch code on broadcastable tensors of cosines
(measured against the *local* shading normal ``n`` of the meso-scale surface,
not the macro normal).

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

__all__ = ["ggx_ndf", "smith_g1", "smith_g1_over_cos", "schlick_fresnel", "ggx_specular", "layered_brdf", "dot3"]


def dot3(a, b) -> torch.Tensor:
    """``sum_k a[..., k] * b[..., k]`` written out (batch-independent rounding)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def ggx_ndf(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution ``D`` (per steradian of micro-normal) at ``cos(n, h)``."""
    a2 = alpha * alpha
    d = (cos_h * cos_h * (a2 - 1.0)).add_(1.0)
    return a2 / d.square_().mul_(math.pi)


def smith_g1(cos_w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Smith masking of GGX for a direction at ``cos(n, w) > 0``."""
    return smith_g1_over_cos(cos_w, alpha).mul_(cos_w)


def smith_g1_over_cos(cos_w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """``G1(w) / cos(n, w) = 2 / (x + sqrt(a^2 + (1 - a^2) x^2))`` (what the specular lobe needs)."""
    a2 = alpha * alpha
    root = (cos_w * cos_w * (1.0 - a2)).add_(a2).sqrt_()
    return root.add_(cos_w).reciprocal_().mul_(2.0)


def schlick_fresnel(f0, cos_d: torch.Tensor) -> torch.Tensor:
    """Schlick's Fresnel approximation with normal-incidence reflectance ``f0``."""
    m = (1.0 - cos_d).clamp(0.0, 1.0)
    m2 = m * m
    return f0 + (1.0 - f0) * (m2 * m2 * m)


def ggx_specular(cos_l, cos_v, cos_h, cos_d, alpha, f0) -> torch.Tensor:
    """Microfacet specular lobe ``f_spec`` (1/sr) for positive ``cos_l, cos_v``.

    Arguments broadcast; pass per-light and per-texel factors with singleton
    axes (e.g. ``cos_d`` as ``(L, 1)``, ``cos_v`` as ``(1, N)``) so each factor is
    computed at its own size before the product.
    """
    g1_over_cos_l = smith_g1_over_cos(cos_l, alpha)
    g1_over_cos_v = smith_g1_over_cos(cos_v, alpha)
    spec = ggx_ndf(cos_h, alpha).mul_(g1_over_cos_l).mul_(g1_over_cos_v * 0.25)
    return spec * schlick_fresnel(f0, cos_d)


def layered_brdf(cos_l, cos_v, cos_h, cos_d, *, albedo, alpha, f0, coat=None, coat_alpha=0.05,
                 coat_f0=0.04) -> torch.Tensor:
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
    alpha, f0 : tensors ``(...)``
        Base GGX roughness and base specular reflectance at normal incidence.
    coat : tensor ``(...)`` or None
        Clear-coat weight in ``[0, 1]``; ``None`` means no coat anywhere.
    coat_alpha, coat_f0 : float
        Clear-coat GGX roughness and reflectance at normal incidence.

    All arguments broadcast against each other (``albedo`` with an extra RGB axis).

    Returns
    -------
    tensor ``(..., 3)``: ``pi * f_r``.
    """
    base = albedo + ggx_specular(cos_l, cos_v, cos_h, cos_d, alpha, f0).mul_(math.pi)[..., None]
    if coat is None:
        return base
    ca = torch.as_tensor(coat_alpha, dtype=cos_l.dtype, device=cos_l.device)
    coat_spec = ggx_specular(cos_l, cos_v, cos_h, cos_d, ca, coat_f0)
    transmit = (1.0 - schlick_fresnel(coat_f0, cos_l)) * (1.0 - schlick_fresnel(coat_f0, cos_v))
    # coat * [spec_c + T base] + (1 - coat) base  =  base (1 - coat + coat T) + coat spec_c
    through = 1.0 - coat + coat * transmit
    return base * through[..., None] + (math.pi * coat * coat_spec)[..., None]
