"""Hex-tiling (Mikkelsen 2022, "Practical Real-Time Hex-Tiling").

Same lattice, hash and whole-texel offsets as histogram blending (each lattice
vertex is the centre of a hexagonal tile, :func:`~dynbtf.synthesis.lattice.vertex_uv`),
but the raw features are blended with sharp, content-aware weights and no
histogram transform:

    W_i = delta_i b_i^7,  delta_i = (1 - beta) + beta lum_i,  normalized, then the contrast gain
    g(x) = 0.5 (2x)^k (x < 0.5),  1 - 0.5 (2 - 2x)^k (x >= 0.5),  k = ln(1 - r) / ln(1/2),  renormalized

where ``lum_i`` is a luminance-like value in ``[0, 1]`` of sample ``i`` (brighter
content wins the transition) and ``r`` the contrast (``r = 0.5`` leaves the
weights unchanged; larger values sharpen the transitions). For a 16-channel
latent plane "luminance" is the first principal component of the exemplar
(min-max normalized) unless a per-texel ``luminance`` plane is given (e.g. the
decoded brightness, as :class:`dynbtf.infinite_btf.SynthesizedBTF` does).

Per-tile rotation (Mikkelsen's variation) is off by default: ``rotation`` turns each tile's
sample by random quarter turns about a texel centre next to the tile's centre, and the view and light into the
query's frame (:mod:`~dynbtf.synthesis.sample_transform`; free angles would read between texels
everywhere). No variance correction: some contrast is lost in the (narrow) transition zones.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from ...errors import InputError
from ...tables import Table
from ...texture import fetch_wrap
from ..base import register_synthesizer
from ..blending import LatticeBlending, LatticePlane
from ..histogram import Decorrelation
from ..blending.kernel import MODE_HEX
from ..mip import area_pyramid, level_shapes
from ..tileable import make_tileable

__all__ = ["HexTiling", "contrast_gain"]


def contrast_gain(weights: torch.Tensor, r: float) -> torch.Tensor:
    """Mikkelsen's gain of normalized weights ``(..., 3)``, renormalized (identity for ``r = 0.5``)."""
    k = math.log(1.0 - r) / math.log(0.5)
    if k == 1.0:
        return weights
    low = 0.5 * (2.0 * weights).clamp_min(0.0) ** k
    high = 1.0 - 0.5 * (2.0 - 2.0 * weights).clamp_min(0.0) ** k
    g = torch.where(weights < 0.5, low, high)
    return g / g.sum(-1, keepdim=True)


def _normalized(x: torch.Tensor) -> torch.Tensor:
    lo, hi = x.min(), x.max()
    return ((x - lo) / (hi - lo)) if float(hi - lo) > 0 else torch.full_like(x, 0.5)


@register_synthesizer("hex")
class HexTiling(LatticeBlending):
    """Hex-tiling of an exemplar plane (Mikkelsen's rotation variation, in quarter turns: ``rotation``).

    Parameters
    ----------
    exemplar : ``(H, W, C)``
    seed : int, default 0
    contrast : float in (0, 1), default 0.7
        Mikkelsen's ``r`` (the demo's colour default); 0.5 = no gain.
    beta : float in [0, 1], default 0.6
        Luminance fall-off strength.
    luminance : tensor ``(H, W)``, optional
        Per-texel luminance-like values (any range; min-max normalized). Default:
        the first principal component of the exemplar's channels.
    tileable, band, fast, prepared, rotation, scale_jitter
        See :class:`~dynbtf.synthesis.blending.LatticeBlending`.
    """

    backends = {**LatticeBlending.backends, "web": f"{__name__}.web"}

    mode = MODE_HEX
    model_inputs = {"luminance": "luminance"}

    def __init__(self, exemplar, seed: int = 0, *, contrast: float = 0.7, beta: float = 0.6, luminance=None,
                 tileable="auto", band: int | None = None, fast: bool | None = None,
                 prepared: LatticePlane | None = None, rotation: bool = False,
                 scale_jitter: float = 0.0) -> None:
        if not 0.0 < contrast < 1.0:
            raise InputError(f"contrast: expected r in (0, 1) (0.5 = no gain), got {contrast!r}")
        if not 0.0 <= beta <= 1.0:
            raise InputError(f"beta: expected a value in [0, 1], got {beta!r}")
        self.contrast = float(contrast)
        self.beta = float(beta)
        self.luminance_input = None
        if luminance is not None:
            luminance = torch.as_tensor(luminance, dtype=torch.float32)
            shape = tuple(torch.as_tensor(exemplar).shape[:2])
            if tuple(luminance.shape) != shape or not bool(torch.isfinite(luminance).all()):
                raise InputError(f"luminance: expected a finite (H, W) = {shape} plane, got shape "
                                 f"{tuple(luminance.shape)}")
            self.luminance_input = luminance
        super().__init__(exemplar, seed, tileable=tileable, band=band, fast=fast, prepared=prepared, rotation=rotation,
                         scale_jitter=scale_jitter)

    #: The blend's lattice part ``b^7`` (its luminance factor depends on the content read).
    frame_exponent = 7.0

    def prepare(self, source: torch.Tensor) -> LatticePlane:
        h, w, c = source.shape
        if self.luminance_input is None:
            pca = Decorrelation.fit(source.reshape(-1, c))
            lum = pca.project(source.reshape(-1, c))[:, 0].reshape(h, w)
        else:
            lum = self.luminance_input.to(source.device)
            if lum.shape != (h, w):  # the exemplar was made tileable: crop/blend the luminance alike
                lum = make_tileable(lum[..., None], self.exemplar.shape[0] - h)[..., 0]
        lum = _normalized(lum.to(torch.float32)).contiguous()
        return LatticePlane(source.contiguous(), False, 0.0, 0.0, {"luminance": lum})

    def blend(self, samples, barycentrics, uv_samples, level: int = 0):
        lum_plane = self.prepared.extras["luminance"] if level == 0 else self.pyramid()["luminances"][level]
        lum = fetch_wrap(lum_plane[..., None], uv_samples)[..., 0].to(torch.float64)
        w = (1.0 - self.beta + self.beta * lum) * barycentrics.clamp_min(0.0) ** 7
        w = contrast_gain(w / w.sum(-1, keepdim=True), self.contrast)
        return (w.to(samples.dtype)[..., None] * samples).sum(-2).to(torch.float32)

    def filter_tables(self, levels):
        """The luminance's pyramid (the weights of a level's samples come from its luminance)."""
        return {"luminances": [t[..., 0] for t in area_pyramid(self.prepared.extras["luminance"][..., None])]}

    def extras_arrays(self) -> dict[str, torch.Tensor]:
        return {"luminance": self.prepared.extras["luminance"]}

    @classmethod
    def extras_from_arrays(cls, arrays: dict[str, torch.Tensor]) -> dict[str, Any]:
        return {"luminance": arrays["luminance"].to(torch.float32).contiguous()}

    @classmethod
    def extra_tables(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor, read: tuple[int, int]) -> list[Table]:
        """The per-texel luminance gain in ``[0, 1]`` and its pyramid."""
        return [Table("luminance", torch.float32, read, 0.0, 1.0)] + [
            Table(f"luminances.{i}", torch.float32, shape, 0.0, 1.0) for i, shape in enumerate(level_shapes(*read))]

    def filter_arrays(self, pyramid: dict[str, Any]) -> dict[str, torch.Tensor]:
        return {f"luminances.{i}": plane for i, plane in enumerate(pyramid["luminances"])}

    @classmethod
    def filter_from_arrays(cls, arrays: dict[str, torch.Tensor]) -> dict[str, Any]:
        count = sum(1 for k in arrays if k.startswith("luminances."))
        return {"luminances": [arrays[f"luminances.{i}"].to(torch.float32).contiguous() for i in range(count)]}

    def kernel_arguments(self) -> dict[str, Any]:
        return {"luminance": self.prepared.extras["luminance"], "beta": self.beta,
                "gain_k": math.log(1.0 - self.contrast) / math.log(0.5)}

    def parameters(self) -> dict[str, Any]:
        return {"contrast": self.contrast, "beta": self.beta,
                "luminance": "given" if self.luminance_input is not None else "first principal component",
                **super().parameters()}
