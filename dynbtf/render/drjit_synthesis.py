"""Dynamic synthesis of the positional plane, re-expressed in Dr.Jit for the rendering kernel.

Each class here mirrors one synthesizer of :mod:`dynbtf.synthesis` and reads its
precomputed tables (the exemplar plane after its preprocessing, transforms,
look-up tables) from the torch object, so that the kernel evaluates the same
function as :meth:`dynbtf.synthesized.SynthesizedBTF.features`.

Inputs are ``u, v`` (``mi.Float``, units of one exemplar repeat); outputs are
lists of ``C`` ``mi.Float`` (one per feature channel).
"""

from __future__ import annotations

from ..errors import InputError
from . import drjit_ops
from .drjit_ops import _flat, fetch_wrap, mi_module

__all__ = ["DrTiling", "make_dr_synthesizer"]


class DrTiling:
    """Plain periodic tiling: a bilinear, wrapped fetch of the exemplar plane ``(H, W, C)``."""

    def __init__(self, plane) -> None:
        mi = mi_module()
        plane = plane.detach().float().cpu().numpy() if hasattr(plane, "detach") else plane
        self.size = (int(plane.shape[0]), int(plane.shape[1]))
        self.channels = int(plane.shape[2])
        self.plane = _flat(mi, plane)

    def features(self, u, v, active=True):
        return fetch_wrap(self.plane, self.size, self.channels, u, v, active)


def make_dr_synthesizer(model, method: str, seed: int):
    """The Dr.Jit synthesizer for ``method`` on ``model``'s positional plane (same tables as torch's)."""
    if method == "tile":
        return DrTiling(model.positional_plane())
    raise InputError(f"method: expected one of ['tile', 'hist', 'hex'], got {method!r}")


del drjit_ops
