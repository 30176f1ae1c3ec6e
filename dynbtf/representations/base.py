"""The representation interface (stage 1 of the pipeline: Represent).

A representation is a ``torch.nn.Module`` that answers BTF queries and, for
synthesis, exposes a **positional plane**: a texture ``(H, W, C)`` whose
bilinear, periodic fetch at ``uv`` followed by :meth:`Representation.decode`
gives the BTF value. Synthesis replaces the fetch by a synthesized fetch and
keeps the decode: this is what makes NeuMIP, PCA or a new representation plug
into the same synthesis code ("our scheme is general to any representation with
a positional plane").

Shapes: ``uv (..., 2)`` (float32 or float64, units of one exemplar repeat, any
real value), ``w_view, w_light (..., 3)`` unit vectors in the local frame,
``features (..., C)``; outputs ``(..., 3)`` linear RGB (excluding cos(theta_light)).
All leading (batch) shapes must be equal.

New kinds register with :func:`register` so that model files can name them.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import torch
from torch import nn

from ..errors import InputError
from ..texture import fetch_wrap

__all__ = ["Representation", "register", "REPRESENTATIONS", "get_representation_class"]

#: kind name -> class, filled by :func:`register`.
REPRESENTATIONS: dict[str, type["Representation"]] = {}


def register(kind: str):
    """Class decorator: make a representation loadable by its ``kind`` name."""

    def deco(cls):
        cls.kind = kind
        REPRESENTATIONS[kind] = cls
        return cls

    return deco


def get_representation_class(kind: str) -> type["Representation"]:
    """The class registered as ``kind``; a clear error lists the known kinds."""
    from . import _load_builtin  # noqa: F401  (imports the built-in kinds)

    try:
        return REPRESENTATIONS[kind]
    except KeyError:
        raise InputError(f"unknown representation {kind!r}; expected one of {sorted(REPRESENTATIONS)}") from None


class Representation(nn.Module, abc.ABC):
    """Base class of BTF representations with a positional feature plane."""

    kind: ClassVar[str] = "abstract"

    #: True when the training loop must give every texel group images of one view
    #: (representations whose positional fetch depends on the view, e.g. parallax).
    view_coherent_batches: ClassVar[bool] = False

    # ------------------------------------------------------------ to implement
    @abc.abstractmethod
    def positional_plane(self) -> torch.Tensor:
        """The positional feature texture ``(H, W, C)`` that synthesis consumes."""

    @abc.abstractmethod
    def decode(self, features: torch.Tensor, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from positional ``features (..., C)`` and directions ``(..., 3)``."""

    @abc.abstractmethod
    def config(self) -> dict[str, Any]:
        """JSON-serializable constructor arguments: ``type(self)(**config())`` rebuilds it."""

    # ------------------------------------------------------------ provided
    @property
    def feature_channels(self) -> int:
        return int(self.positional_plane().shape[-1])

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device if any(True for _ in self.parameters()) else torch.device("cpu")

    def positional_features(self, uv: torch.Tensor) -> torch.Tensor:
        """Bilinear periodic fetch of the positional plane at ``uv (..., 2)`` -> ``(..., C)``."""
        return fetch_wrap(self.positional_plane(), uv)

    def visible_uv(self, uv: torch.Tensor, w_view: torch.Tensor, fetch=None) -> torch.Tensor:
        """Where the positional plane is fetched for a query at ``uv (..., 2)`` seen from ``w_view (..., 3)``.

        The identity here: the paper's representations fetch at ``uv`` whatever the
        view. A representation with relief (:class:`~dynbtf.representations.parallax.ParallaxTriplePlane`)
        returns the visible surface point, found through ``fetch(points (M, 2)) -> (M, C)``
        (default: its own plane; a synthesized BTF passes the synthesized fetch).
        """
        return uv

    def forward(self, uv: torch.Tensor, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """BTF value ``(..., 3)`` at ``uv (..., 2)`` for directions ``(..., 3)``."""
        check_query_shapes(uv, w_view, w_light)
        return self.decode(self.positional_features(self.visible_uv(uv, w_view)), w_view, w_light)

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def storage_bytes(self) -> int:
        """Bytes needed to store the representation's parameters and buffers."""
        return sum(t.numel() * t.element_size() for t in list(self.parameters()) + list(self.buffers()))


def check_query_shapes(uv, w_view, w_light) -> None:
    """Raise :class:`InputError` unless ``uv (..., 2)`` and ``w_* (..., 3)`` share batch shapes."""
    if uv.shape[-1:] != (2,):
        raise InputError(f"uv: expected shape (..., 2), got {tuple(uv.shape)}")
    for name, w in (("w_view", w_view), ("w_light", w_light)):
        if w.shape[-1:] != (3,):
            raise InputError(f"{name}: expected shape (..., 3), got {tuple(w.shape)}")
        if w.shape[:-1] != uv.shape[:-1]:
            raise InputError(
                f"{name}: batch shape {tuple(w.shape[:-1])} does not match uv's {tuple(uv.shape[:-1])}")
