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

Blending exponent: ``gamma = 7`` by default (Heitz & Neyret use 1, Burley's
ports 3, hex-tiling 7). On a fitted Triple Plane the decoder is co-adapted to
the exemplar's own feature vectors: a *new* vector -- a blend of three
unrelated texels' codes -- decodes to over-contrasted, speckled colours even
when its marginals and covariance are right (decoded RGB std up to 2x the
exemplar's with ``gamma = 1``). Sharper weights keep each point closer to one
sample, so less of the surface is a blend: RGB W1/std several times lower than
with ``gamma = 1`` on every fitted model measured, feature W1/std lower too, no
repetition. Measurements (``benchmarks/measure_blend_exponent.py``, 3 seeds) and
images: ``docs/synthesis.md`` ("Why decoded colours drift: the blending exponent").
"""

from __future__ import annotations

from typing import Any

import torch

from ...errors import InputError, positive_number
from ...tables import Table
from ..blending import LatticeBlending, LatticePlane
from ..base import GAUSSIAN_BOUND, coefficient_bound, feature_bound, register_synthesizer
from ..histogram import Decorrelation, GaussianTransform, InverseLUT, blend_weights, variance_preserving_blend
from ..mip import level_shapes, prefiltered_inverse_tables
from ..blending.kernel import MODE_HIST

__all__ = ["HistogramBlending", "DEFAULT_GAMMA"]

#: Default barycentric exponent of the blending weights (Heitz & Neyret: 1; see the module docstring).
DEFAULT_GAMMA = 7.0


@register_synthesizer("hist")
class HistogramBlending(LatticeBlending):
    """Histogram-preserving blending of an exemplar plane.

    Parameters
    ----------
    exemplar : ``(H, W, C)``
    seed : int, default 0
    gamma : float, default 7.0
        Barycentric exponent of the weights ``b^gamma`` (1 in Heitz & Neyret, the smoothest
        transitions; Burley's ports use 3; larger values blend over less of the surface).
        The default 7 keeps decoded colours close to the exemplar's (see the module
        docstring); integral values are as fast as 1 in the fused kernel.
    decorrelate : bool, default True
        PCA over the channels before the per-channel transforms.
    separate : int, default 0
        The last ``separate`` channels stay out of the PCA: each gets its own 1-D transform of the
        channel itself (:meth:`~dynbtf.synthesis.histogram.Decorrelation.fit`), blended with the same
        lattice, offsets and weights as the others. A relief model's height (its plane's last
        channel) is synthesized so: a march reads it alone (:meth:`channel`: one channel's three
        bilinear reads and one inverse table instead of all ``C``). 0: every channel in the PCA.
    lut_size : int, default 4096
        Entries of the inverse-transform table of the fused kernel.
    tileable, band, fast, prepared, rotation, scale_jitter
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

    backends = {**LatticeBlending.backends, "web": f"{__name__}.web"}

    mode = MODE_HIST
    model_inputs = {"separate": "separate_channels"}

    def __init__(self, exemplar, seed: int = 0, *, gamma: float = DEFAULT_GAMMA, decorrelate: bool = True,
                 separate: int = 0, lut_size: int = 4096, tileable="auto", band: int | None = None, fast: bool | None = None,
                 prepared: LatticePlane | None = None, rotation: bool = False,
                 scale_jitter: float = 0.0) -> None:
        gamma = positive_number("gamma", gamma, "exponent")
        if int(lut_size) < 2:
            raise InputError(f"lut_size: expected at least 2 entries, got {lut_size!r}")
        self.gamma = gamma
        self.decorrelate = bool(decorrelate)
        self.separate = int(separate)
        self.lut_size = int(lut_size)
        super().__init__(exemplar, seed, tileable=tileable, band=band, fast=fast, prepared=prepared, rotation=rotation,
                         scale_jitter=scale_jitter)

    def prepare(self, source: torch.Tensor) -> LatticePlane:
        h, w, c = source.shape
        values = source.reshape(-1, c).to(torch.float64)
        decorrelation = Decorrelation.fit(values, self.separate) if self.decorrelate else None
        coefficients = decorrelation.project(values) if decorrelation is not None else values
        transform, gaussian = GaussianTransform.fit(coefficients)
        lut = transform.lut(self.lut_size)
        plane = gaussian.reshape(h, w, c).to(torch.float32).contiguous()
        return LatticePlane(plane, False, 0.0, 0.0, {
            "transform": transform, "decorrelation": decorrelation, "lut": lut,
            "lut_table": lut.table.to(torch.float32)})

    def blend(self, samples, barycentrics, uv_samples, level: int = 0):
        g = variance_preserving_blend(samples.to(torch.float64), blend_weights(barycentrics, self.gamma))
        if level == 0:
            return self.prepared.extras["transform"].inverse(g).to(torch.float32)
        lut = self.prepared.extras["lut"]
        table = self.pyramid()["luts"][level].to(torch.float64)
        return InverseLUT(table, lut.g_min, lut.step)(g).to(torch.float32)

    @property
    def frame_exponent(self) -> float:
        """The blend's own weights ``b^gamma``."""
        return self.gamma

    def filter_tables(self, levels):
        """Per-level inverse tables (:func:`~dynbtf.synthesis.mip.prefiltered_inverse_tables`), level 0 the point table."""
        lut = self.prepared.extras["lut"]
        luts = prefiltered_inverse_tables(self.prepared.extras["transform"], levels, lut.g_min, lut.step,
                                          self.lut_size)
        luts[0] = self.prepared.extras["lut_table"]
        return {"luts": luts, "luts_numpy": luts.cpu().numpy()}

    def extras_arrays(self) -> dict[str, torch.Tensor]:
        extras = self.prepared.extras
        lut, decorrelation = extras["lut"], extras["decorrelation"]
        arrays = {"transform.sorted_values": extras["transform"].sorted_values, "lut.table": lut.table,
                  "lut.g_min": torch.tensor(lut.g_min, dtype=torch.float64),
                  "lut.step": torch.tensor(lut.step, dtype=torch.float64), "lut_table": extras["lut_table"]}
        if decorrelation is not None:
            arrays.update({"decorrelation.mean": decorrelation.mean, "decorrelation.basis": decorrelation.basis,
                           "decorrelation.variances": decorrelation.variances})
        return arrays

    @classmethod
    def extras_from_arrays(cls, arrays: dict[str, torch.Tensor]) -> dict[str, Any]:
        decorrelation = None
        if "decorrelation.mean" in arrays:
            decorrelation = Decorrelation(arrays["decorrelation.mean"], arrays["decorrelation.basis"],
                                          arrays["decorrelation.variances"])
        lut = InverseLUT(arrays["lut.table"].to(torch.float64), float(arrays["lut.g_min"]), float(arrays["lut.step"]))
        return {"transform": GaussianTransform(arrays["transform.sorted_values"].to(torch.float64)),
                "decorrelation": decorrelation, "lut": lut, "lut_table": arrays["lut_table"].to(torch.float32)}

    @classmethod
    def plane_bound(cls, plane: torch.Tensor) -> float:
        return GAUSSIAN_BOUND  # the read plane holds Gaussianized values

    @classmethod
    def extra_tables(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor, read: tuple[int, int]) -> list[Table]:
        """The Gaussian transform's sorted values and inverse tables (non-decreasing rows of decorrelated
        coefficients), the tables' grid, the PCA (when decorrelated) and one inverse table per pyramid level."""
        c = plane.shape[-1]
        table = arrays.get("lut.table")
        size = table.shape[1] if isinstance(table, torch.Tensor) and table.ndim == 2 else None
        levels = len(level_shapes(*read))
        coefficient = coefficient_bound(plane)
        rules = [Table("transform.sorted_values", torch.float64, (c, None), -coefficient, coefficient, monotone=True),
                 Table("lut.table", torch.float64, (c, size), -coefficient, coefficient, monotone=True),
                 Table("lut_table", torch.float32, (c, size), -coefficient, coefficient, monotone=True),
                 Table("luts", torch.float32, (levels, c, size), -coefficient, coefficient, monotone=True),
                 Table("lut.g_min", torch.float64, (), -GAUSSIAN_BOUND, 0.0),
                 Table("lut.step", torch.float64, (), 1e-9, 2 * GAUSSIAN_BOUND)]
        if any(name.startswith("decorrelation.") for name in arrays):
            feature = feature_bound(plane)
            rules += [Table("decorrelation.mean", torch.float64, (c,), -feature, feature),
                      Table("decorrelation.basis", torch.float64, (c, c), -1.0 - 1e-6, 1.0 + 1e-6),
                      Table("decorrelation.variances", torch.float64, (c,), 0.0, coefficient ** 2)]
        return rules

    @classmethod
    def table_relations(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> str | None:
        if arrays["lut.table"].shape[1] < 2:
            return f"table 'lut.table': {arrays['lut.table'].shape[1]} entries per row, expected at least 2"
        return super().table_relations(arrays, plane)

    def filter_arrays(self, pyramid: dict[str, Any]) -> dict[str, torch.Tensor]:
        return {"luts": pyramid["luts"]}

    @classmethod
    def filter_from_arrays(cls, arrays: dict[str, torch.Tensor]) -> dict[str, Any]:
        luts = arrays["luts"].to(torch.float32).contiguous()
        return {"luts": luts, "luts_numpy": luts.cpu().numpy()}

    def kernel_arguments(self) -> dict[str, Any]:
        lut = self.prepared.extras["lut"]
        return {"gamma": self.gamma, "lut": self.prepared.extras["lut_table"], "g_min": lut.g_min, "step": lut.step}

    def output_map(self):
        decorrelation = self.prepared.extras["decorrelation"]
        if decorrelation is None:
            return None, None
        return decorrelation.basis.T.to(torch.float32), decorrelation.mean.to(torch.float32)

    def parameters(self) -> dict[str, Any]:
        return {"gamma": self.gamma, "decorrelate": self.decorrelate, "separate": self.separate, "lut_size": self.lut_size,
                **super().parameters()}
