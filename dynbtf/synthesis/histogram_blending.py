"""Histogram-preserving blending (Heitz & Neyret 2018): the paper's main synthesis method.

Per query: the triangle lattice gives three vertices with barycentrics ``b_i``;
each vertex owns a hashed whole-texel offset; the exemplar's **Gaussianized**
values ``G = T(f)`` are read at the three offset positions and blended with the
variance-preserving formula

    G* = sum_i w_i G_i / sqrt(sum_i w_i^2),   w_i = b_i^gamma / sum_j b_j^gamma

(the Gaussian transform has mean 0), then mapped back with the inverse
transform: ``f* = T^-1(G*)``. Because a variance-preserving blend of Gaussians
is Gaussian with the same mean and variance, ``f*`` has the exemplar's
histogram, where plain linear blending loses contrast.

With ``decorrelate=True`` (default) the ``C`` channels are first projected on
their principal components (:class:`~dynbtf.synthesis.histogram.Decorrelation`)
and the 1-D transforms act on the coefficients; the output map un-projects
(and a decoder can fold it into its first layer). Decorrelation keeps the joint
distribution of correlated latent channels better: the measured numbers are in
``docs/synthesis.md``.

The fused kernel inverts with an :class:`~dynbtf.synthesis.histogram.InverseLUT`
of ``lut_size`` entries; the torch reference path inverts exactly.
"""

from __future__ import annotations

from typing import Any

import torch

from ..errors import InputError
from .blending import LatticeBlending, LatticePlane
from .base import register_synthesizer
from .histogram import Decorrelation, GaussianTransform, blend_weights, variance_preserving_blend
from .kernels import MODE_HIST

__all__ = ["HistogramBlending"]


@register_synthesizer("hist")
class HistogramBlending(LatticeBlending):
    """Histogram-preserving blending of an exemplar plane.

    Parameters
    ----------
    exemplar : ``(H, W, C)``
    seed : int, default 0
    gamma : float, default 1.0
        Barycentric exponent of the weights (1 in Heitz & Neyret; Burley's ports use 3).
    decorrelate : bool, default True
        PCA over the channels before the per-channel transforms.
    lut_size : int, default 4096
        Entries of the inverse-transform table of the fused kernel.
    tileable, band, fast, prepared
        See :class:`~dynbtf.synthesis.blending.LatticeBlending`.

    Attributes
    ----------
    prepared.extras : dict
        ``transform`` (GaussianTransform), ``decorrelation`` (Decorrelation or None),
        ``lut`` (InverseLUT), ``lut_table`` float32 ``(C, lut_size)``.

    Examples
    --------
    >>> import torch
    >>> exemplar = torch.randn(32, 32, 4).exp()
    >>> synth = HistogramBlending(exemplar, seed=1)
    >>> synth(torch.tensor([[0.25, 0.5], [1e6 + 0.25, 0.5]], dtype=torch.float64)).shape
    torch.Size([2, 4])
    """

    mode = MODE_HIST

    def __init__(self, exemplar, seed: int = 0, *, gamma: float = 1.0, decorrelate: bool = True,
                 lut_size: int = 4096, tileable="auto", band: int | None = None, fast: bool | None = None,
                 prepared: LatticePlane | None = None) -> None:
        if not gamma > 0:
            raise InputError(f"gamma: expected a positive exponent, got {gamma!r}")
        if int(lut_size) < 2:
            raise InputError(f"lut_size: expected at least 2 entries, got {lut_size!r}")
        self.gamma = float(gamma)
        self.decorrelate = bool(decorrelate)
        self.lut_size = int(lut_size)
        super().__init__(exemplar, seed, tileable=tileable, band=band, fast=fast, prepared=prepared)

    def prepare(self, source: torch.Tensor) -> LatticePlane:
        h, w, c = source.shape
        values = source.reshape(-1, c).to(torch.float64)
        decorrelation = Decorrelation.fit(values) if self.decorrelate else None
        coefficients = decorrelation.project(values) if decorrelation is not None else values
        transform, gaussian = GaussianTransform.fit(coefficients)
        lut = transform.lut(self.lut_size)
        plane = gaussian.reshape(h, w, c).to(torch.float32).contiguous()
        return LatticePlane(plane, False, 0.0, 0.0, {
            "transform": transform, "decorrelation": decorrelation, "lut": lut,
            "lut_table": lut.table.to(torch.float32)})

    def blend(self, samples, barycentrics, uv_samples):
        g = variance_preserving_blend(samples.to(torch.float64), blend_weights(barycentrics, self.gamma))
        return self.prepared.extras["transform"].inverse(g).to(torch.float32)

    def kernel_arguments(self) -> dict[str, Any]:
        lut = self.prepared.extras["lut"]
        return {"gamma": self.gamma, "lut": self.prepared.extras["lut_table"], "g_min": lut.g_min, "step": lut.step}

    def output_map(self):
        decorrelation = self.prepared.extras["decorrelation"]
        if decorrelation is None:
            return None, None
        return decorrelation.basis.T.to(torch.float32), decorrelation.mean.to(torch.float32)

    def parameters(self) -> dict[str, Any]:
        return {"gamma": self.gamma, "decorrelate": self.decorrelate, "lut_size": self.lut_size,
                **super().parameters()}
