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

New kinds register with :func:`register` so that model files can name them; the lookup by name
lives above the kinds, in :mod:`dynbtf.representations.registry` (this module imports no kind).
"""

from __future__ import annotations

import abc
import math
import numbers
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import torch
from torch import nn

from ..errors import InputError
from ..texture import fetch_wrap

__all__ = ["Representation", "register", "REPRESENTATIONS"]

#: kind name -> class, filled by :func:`register` (look kinds up with
#: :func:`dynbtf.representations.registry.get_representation_class`, which imports the built-in ones).
REPRESENTATIONS: dict[str, type["Representation"]] = {}


def register(kind: str):
    """Class decorator: make a representation loadable by its ``kind`` name."""

    def deco(cls):
        cls.kind = kind
        REPRESENTATIONS[kind] = cls
        return cls

    return deco


# ---------------------------------------------------------------------- constructor arguments
# A representation's constructor arguments are its model file's ``config`` (read from a shared, untrusted
# file): every constructor checks each one's type and range with these helpers before it allocates anything,
# so that a config can be tried on PyTorch's "meta" device (shapes without memory) and compared with the
# tensors a file holds (:func:`dynbtf.representations.model_file.load_model`). The bounds are far above any
# real model and keep the module count and the tensor ranks sane.

#: Largest side of a positional plane, texels.
MAX_SIDE = 65536
#: Largest number of channels of a plane or of hidden units of a decoder layer.
MAX_CHANNELS = 4096
#: Largest number of linear layers of a decoder.
MAX_LAYERS = 64
#: Largest number of measured view (or light) directions a tabulated representation stores.
MAX_DIRECTIONS = 65536
#: Largest number of measured directions blended by a tabulated representation.
MAX_NEIGHBOURS = 64
#: Largest initialization seed (``torch.Generator.manual_seed`` takes 64-bit integers).
MAX_SEED = 2 ** 63 - 1


def config_int(owner: str, name: str, value, low: int, high: int) -> int:
    """``value`` as an ``int`` if it is an integer (not a bool) in ``[low, high]``, else :class:`InputError`
    ``"{owner} {name}: expected an integer in [low, high], got ..."``.

    >>> config_int("TriplePlane", "layers", 1000000, 2, 64)
    Traceback (most recent call last):
    ...
    dynbtf.errors.InputError: TriplePlane layers: expected an integer in [2, 64], got 1000000
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not low <= value <= high:
        raise InputError(f"{owner} {name}: expected an integer in [{low}, {high}], got {value!r}")
    return int(value)


def config_number(owner: str, name: str, value, low: float, high: float, *, low_open: bool = False) -> float:
    """``value`` as a ``float`` if it is a finite number (not a bool) in ``[low, high]`` (``(low, high]`` with
    ``low_open``), else :class:`InputError` naming ``owner``, ``name`` and the range.

    >>> config_number("TriplePlane", "negative_slope", float("nan"), 0.0, 1.0)
    Traceback (most recent call last):
    ...
    dynbtf.errors.InputError: TriplePlane negative_slope: expected a finite number in [0.0, 1.0], got nan
    """
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value) \
        and (low < value if low_open else low <= value) and value <= high
    if not ok:
        raise InputError(f"{owner} {name}: expected a finite number in {'(' if low_open else '['}{low}, {high}], "
                         f"got {value!r}")
    return float(value)


def config_flag(owner: str, name: str, value) -> bool:
    """``value`` if it is a bool (JSON ``true``/``false``), else :class:`InputError` naming ``owner`` and ``name``."""
    if not isinstance(value, bool):
        raise InputError(f"{owner} {name}: expected true or false, got {value!r}")
    return bool(value)


@dataclass
class FoldableDecoder:
    """What the fast synthesis path needs from a representation (:meth:`Representation.fast_decoder`).

    Attributes
    ----------
    decoder : torch.nn.Module
        An MLP like :class:`dynbtf.representations.triple_plane.Decoder`: ``first`` (a Linear layer over
        ``concat(positional, angular)``), ``positional_channels``, ``rest`` (the later Linear layers),
        ``negative_slope`` (LeakyReLU) and ``first_layer_angular(angular) -> (..., hidden)``.
    angular_features : callable
        ``(w_view (N, 3), w_light (N, 3)) -> (N, A)``: the decoder's angular input.
    angular_planes : tuple of two tensors, optional
        ``(f_H, f_D)``, Rusinkiewicz feature planes ``(R, R, C)``, when the angular input is their bilinear
        fetch (the Triple Plane): the CPU kernel then folds them into layer 1
        (:func:`dynbtf.decoder.fast_decode.fold_angular_planes`).
    """

    decoder: nn.Module
    angular_features: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    angular_planes: tuple[torch.Tensor, torch.Tensor] | None = None


class Representation(nn.Module, abc.ABC):
    """Base class of BTF representations with a positional feature plane."""

    kind: ClassVar[str] = "abstract"

    #: True when the training loop must give every texel group images of one view
    #: (representations whose positional fetch depends on the view, e.g. parallax).
    view_coherent_batches: ClassVar[bool] = False

    #: How many of the positional plane's last channels synthesis keeps out of the features'
    #: decorrelation (``hist``'s ``separate``): a relief model's height, synthesized on its own so that
    #: a march reads one channel per step (same lattice, offsets and weights as the features).
    separate_channels: ClassVar[int] = 0

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

    def state_problem(self) -> str | None:
        """Why this model's parameters (as read from a file) cannot be answered in bounded time or memory, or
        None. Checked by :mod:`~dynbtf.representations.model_file` before the model answers anything; the
        paper's representations have no such limit (a relief's march does: see its override)."""
        return None

    def forward(self, uv: torch.Tensor, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """BTF value ``(..., 3)`` at ``uv (..., 2)`` for directions ``(..., 3)``."""
        check_query_shapes(uv, w_view, w_light)
        return self.decode(self.positional_features(self.visible_uv(uv, w_view)), w_view, w_light)

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    # ------------------------------------------------------------ optional abilities (defaults here)
    #: True when :meth:`texel_image_l1_loss` is a fused kernel that can run in bf16 arithmetic
    #: (:func:`dynbtf.decoder.fused_mlp.split_mlp_l1_loss`); the default loss is generic and fp32 only.
    has_fused_loss: ClassVar[bool] = False
    #: True where ``--compile auto`` compiles :meth:`texel_image_l1_loss` on a GPU (:mod:`dynbtf.training.step_loss`):
    #: only where compiling was measured to pay; the others train eagerly there unless ``--compile`` asks.
    compiled_on_gpu: ClassVar[bool] = False

    def param_groups(self) -> list[dict[str, Any]]:
        """Optimizer groups (dicts with ``params``, ``lr``, ``weight_decay``, ``name``).

        Default: every trainable parameter, lr 1e-3, weight decay 0.01 (an empty list of
        parameters means the kind has a closed-form fitter only).
        """
        return [{"params": [p for p in self.parameters() if p.requires_grad], "lr": 1e-3, "weight_decay": 0.01,
                 "name": "all"}]

    def predict_texel_images(self, w_view: torch.Tensor, w_light: torch.Tensor,
                             texels: torch.Tensor | None = None) -> torch.Tensor:
        """Images at texel centres, ``(B, N, 3)``, for ``w_view, w_light (B, 3)`` at flat ``texels (N,)``
        (default: all, row-major).

        Default: the model queried at the texel centres' uv (:func:`dynbtf.conventions.texel_centers_uv`);
        representations override it with a faster path (e.g. reading the plane directly).
        """
        from ..conventions import texel_centers_uv

        h, w = self.positional_plane().shape[:2]
        uv = torch.from_numpy(texel_centers_uv(h, w)).reshape(-1, 2).to(device=w_view.device, dtype=torch.float64)
        if texels is not None:
            uv = uv.index_select(0, texels)
        b, n = w_view.shape[0], uv.shape[0]
        return self(uv[None].expand(b, n, 2), w_view[:, None].expand(b, n, 3), w_light[:, None].expand(b, n, 3))

    def direction_taps(self, w_view: torch.Tensor, w_light: torch.Tensor) -> tuple[torch.Tensor, ...] | None:
        """What the model reads for each direction pair ``w_view, w_light (P, 3)`` that depends on the
        directions alone, computed once and passed back as ``angular_taps`` (rows of it) to
        :meth:`texel_image_l1_loss`: the fit computes it for all of a BTF's pairs before training. A tuple of
        tensors whose first dimension is ``P``, or None (default: nothing to precompute)."""
        return None

    def texel_image_l1_loss(self, w_view: torch.Tensor, w_light: torch.Tensor, target: torch.Tensor,
                            texels: torch.Tensor | None = None, *, chunk_texels: int = 256, workers: int = 1,
                            texel_groups: int = 1, precision: str = "fp32",
                            angular_taps: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
        """Mean L1 loss of a whole-image batch (the training loss).

        Parameters
        ----------
        w_view, w_light : ``(G * B, 3)``
            The ``B`` pairs of each of the ``G = texel_groups`` groups, group-major.
        target : ``(B, N, 3)``
            ``target[b, t]``: texel ``t`` under image ``b`` of its group.
        texels : int64 ``(N,)``, optional
            Flat texel indices (default all, in order); the ``N`` texels form ``G`` equal consecutive groups.
        chunk_texels, workers : int
            Chunking and threads of a fused implementation (unused by this default).
        precision : ``"fp32"`` or ``"bf16"``
            Only fused losses (:attr:`has_fused_loss`) accept ``"bf16"``.
        angular_taps : tuple of tensors, optional
            Rows of :meth:`direction_taps` for these pairs (None: computed from the directions).

        Default: :meth:`predict_texel_images` per group, then the mean absolute error (float64 sum).
        """
        if precision != "fp32":
            raise InputError(f"precision={precision!r}: representation {self.kind!r} has no fused loss; use 'fp32'")
        if texel_groups == 1:
            return (self.predict_texel_images(w_view, w_light, texels) - target).abs().mean()
        if texels is None:
            texels = torch.arange(target.shape[1], device=target.device)
        b, n = target.shape[0], target.shape[1] // texel_groups
        total = target.new_zeros((), dtype=torch.float64)
        for g in range(texel_groups):
            pred = self.predict_texel_images(w_view[g * b:(g + 1) * b], w_light[g * b:(g + 1) * b],
                                             texels[g * n:(g + 1) * n])
            total = total + (pred - target[:, g * n:(g + 1) * n]).abs().sum(dtype=torch.float64)
        return (total / target.numel()).to(target.dtype)

    def fast_decoder(self) -> FoldableDecoder | None:
        """A :class:`FoldableDecoder` when synthesis may fold layer 1 with the synthesizer's output map and
        decode in fused chunks (decoders like the Triple Plane's), else None (plain :meth:`decode`)."""
        return None

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
