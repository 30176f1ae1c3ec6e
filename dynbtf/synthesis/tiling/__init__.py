"""Repetitive tiling: the exemplar repeated with period one (the reference point).

``features(uv) = fetch_wrap(exemplar, uv)``: exact for any ``uv`` (the integer
part is removed in float64 before the float32 interpolation). Every repeat is
identical, so the repetition score of a tiled area is ~1.
"""

from __future__ import annotations

import torch

from ...texture import fetch_wrap
from ..base import Synthesizer, register_synthesizer
from ..mip import LevelOfDetail, PlanePyramid

__all__ = ["Tiling"]


@register_synthesizer("tile")
class Tiling(Synthesizer):
    """Plain periodic tiling of an exemplar ``(H, W, C)`` (``seed`` is unused; no precomputation).

    ``fast`` (default: on the CPU) uses the fused numba fetch instead of ``grid_sample``.

    >>> import torch
    >>> t = Tiling(torch.arange(64.0).reshape(8, 8, 1))
    >>> float(t(torch.tensor([[0.5 / 8, 0.5 / 8]]))), float(t(torch.tensor([[1e6 + 0.5 / 8, 0.5 / 8]], dtype=torch.float64)))
    (0.0, 0.0)
    """

    backends = {"web": f"{__name__}.web"}

    def __init__(self, exemplar, seed: int = 0, *, fast: bool | None = None) -> None:
        super().__init__(exemplar, seed)
        self.prepared = None
        self.fast = self.device.type == "cpu" if fast is None else bool(fast) and self.device.type == "cpu"
        self._plane_numpy = None
        if self.fast:  # aligned to cache lines: a 16-channel texel is one line (the kernel's prefetches)
            from ..kernels import cache_aligned

            self._plane_numpy = cache_aligned(self.exemplar.cpu().numpy())
        self._pyramid = PlanePyramid(self.exemplar)

    def latent(self, uv: torch.Tensor) -> torch.Tensor:
        if self.fast:  # the fused numba twin of fetch_wrap
            from .kernel import tile_fetch

            return torch.from_numpy(tile_fetch(uv.detach().cpu().numpy(), self._plane_numpy))
        return fetch_wrap(self.exemplar, uv)

    def level_of_detail(self) -> LevelOfDetail:
        return self._pyramid.level_of_detail

    def pyramid(self) -> dict:
        """The exemplar's pyramid: ``levels`` (:func:`~dynbtf.synthesis.mip.area_pyramid`) and ``lod``, built once."""
        return {"levels": self._pyramid.levels, "lod": self._pyramid.level_of_detail}

    def read_uv(self, uv: torch.Tensor) -> torch.Tensor:
        """Where the point query at ``uv (N, 2)`` reads the exemplar, in repeats ``(N, 2)`` float64 (tiling: ``uv``).

        Methods that read one shifted copy of the exemplar per query (``struct``) override it; the
        footprint query reads the pyramid there.
        """
        return uv

    def filtered_latent(self, uv: torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
        if not bool((footprint > 1.0).any()):
            return self.latent(uv)
        return self._pyramid.fetch(self.read_uv(uv), footprint)
