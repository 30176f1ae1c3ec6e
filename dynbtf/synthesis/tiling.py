"""Repetitive tiling: the exemplar repeated with period one (the reference point).

``features(uv) = fetch_wrap(exemplar, uv)``: exact for any ``uv`` (the integer
part is removed in float64 before the float32 interpolation). Every repeat is
identical, so the repetition score of a tiled area is ~1.
"""

from __future__ import annotations

import torch

from ..texture import fetch_wrap
from .base import Synthesizer, register_synthesizer

__all__ = ["Tiling"]


@register_synthesizer("tile")
class Tiling(Synthesizer):
    """Plain periodic tiling of an exemplar ``(H, W, C)`` (``seed`` is unused; no precomputation).

    >>> import torch
    >>> t = Tiling(torch.arange(64.0).reshape(8, 8, 1))
    >>> float(t(torch.tensor([[0.5 / 8, 0.5 / 8]]))), float(t(torch.tensor([[1e6 + 0.5 / 8, 0.5 / 8]], dtype=torch.float64)))
    (0.0, 0.0)
    """

    def __init__(self, exemplar, seed: int = 0) -> None:
        super().__init__(exemplar, seed)
        self.prepared = None

    def latent(self, uv: torch.Tensor) -> torch.Tensor:
        return fetch_wrap(self.exemplar, uv)
