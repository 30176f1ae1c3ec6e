"""The Triple Plane: the paper's decomposition of a 6-D BTF into three 2-D feature planes.

A BTF value at texel position ``uv`` seen from ``w_view`` and lit from ``w_light`` is

    rgb = MLP( concat( f_U(uv), f_H(h), f_D(d) ) )

where ``h, d`` are the Rusinkiewicz half and difference vectors
(:func:`dynbtf.conventions.half_diff_from_view_light`):

* ``f_U`` -- the **positional plane**, ``(H, W, 16)`` at the BTF's spatial
  resolution, fetched bilinearly and periodically (:func:`dynbtf.texture.fetch_wrap`).
  This is the texture that synthesis replaces.
* ``f_H``, ``f_D`` -- the **angular planes**, ``(20, 20, 8)`` each, indexed by
  :func:`dynbtf.conventions.angular_plane_coords` of ``h`` and ``d``: rows follow
  ``theta / 90deg`` (clamped), columns follow ``phi / 360deg`` (circularly padded),
  fetched bilinearly (:func:`dynbtf.texture.fetch_angular`).
* the decoder -- 4 linear layers ``32 -> 32 -> 32 -> 32 -> 3`` with LeakyReLU after
  each hidden layer.

Choices not fixed by the paper (documented here, every size a parameter):

* **Output activation: none.** The last layer is linear. Stored BTF values are
  ``pi * f_r`` and exceed 1 on specular highlights, so a sigmoid (Biplane) would
  clip them; a final LeakyReLU would only distort the small negative errors that
  the L1 loss already drives to zero. Consumers clamp at display time.
* **Initialization** ("He et al."): each feature plane ``(..., C)`` is drawn from
  ``N(0, 2 / C)`` (Kaiming-normal with fan-in = channels); decoder weights are
  Kaiming-uniform for LeakyReLU, biases zero. All from the constructor's ``seed``.
* The first decoder layer is applied as ``W_U f_U + W_A [f_H, f_D] + b``
  (mathematically the same as one linear layer on the concatenation). This lets
  callers broadcast: a single angular vector per image against all texels
  (training, :meth:`TriplePlane.predict_texel_images`) or positional features
  against many directions (synthesis, :meth:`TriplePlane.decode_with_angular`).
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from ..conventions import angular_plane_coords, half_diff_from_view_light
from ..errors import InputError
from ..texture import angular_taps, fetch_angular, fetch_taps
from ..decoder.fused_mlp import decoder_l1_loss, triple_plane_l1_loss
from .base import (MAX_CHANNELS, MAX_LAYERS, MAX_SEED, MAX_SIDE, FoldableDecoder, Representation, config_int,
                   config_number, register)

__all__ = ["TriplePlane", "Decoder"]


class Decoder(nn.Module):
    """The Triple Plane's MLP, with the first layer split into positional and angular parts.

    Parameters
    ----------
    positional_channels, angular_channels : int
        Input widths: ``C_U`` and ``C_H + C_D``.
    hidden : int
        Hidden units per layer (32 in the paper).
    layers : int
        Number of linear layers (4 in the paper, 2 .. :data:`~dynbtf.representations.base.MAX_LAYERS`).
    negative_slope : float
        LeakyReLU slope (PyTorch's default 0.01), in [0, 1].
    out_channels : int
        3 (linear RGB).
    owner : str
        Names the model in the :class:`InputError` raised for an argument of the wrong type or range.

    Attributes
    ----------
    first : nn.Linear
        Layer 1 acting on ``concat(positional, angular)``; its weight's first
        ``positional_channels`` columns multiply the positional features.
    rest : nn.ModuleList
        Layers 2 .. ``layers``; the last one outputs RGB without activation.
    """

    def __init__(self, positional_channels: int = 16, angular_channels: int = 16, hidden: int = 32,
                 layers: int = 4, negative_slope: float = 0.01, out_channels: int = 3, *,
                 owner: str = "Decoder") -> None:
        super().__init__()
        positional_channels = config_int(owner, "positional_channels", positional_channels, 1, MAX_CHANNELS + 1)
        angular_channels = config_int(owner, "angular_channels", angular_channels, 1, 2 * MAX_CHANNELS)
        hidden = config_int(owner, "hidden", hidden, 1, MAX_CHANNELS)
        layers = config_int(owner, "layers", layers, 2, MAX_LAYERS)
        negative_slope = config_number(owner, "negative_slope", negative_slope, 0.0, 1.0)
        out_channels = config_int(owner, "out_channels", out_channels, 1, MAX_CHANNELS)
        self.positional_channels = positional_channels
        self.negative_slope = negative_slope
        self.first = nn.Linear(positional_channels + angular_channels, hidden)
        widths = [hidden] * (layers - 1) + [out_channels]
        self.rest = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))

    def reset_parameters(self, generator: torch.Generator) -> None:
        """Kaiming-uniform weights for LeakyReLU, zero biases, drawn from ``generator``."""
        for layer in [self.first, *self.rest]:
            gain = math.sqrt(2.0 / (1.0 + self.negative_slope ** 2))
            bound = gain * math.sqrt(3.0 / layer.in_features)
            with torch.no_grad():
                layer.weight.copy_(torch.rand(layer.weight.shape, generator=generator) * (2 * bound) - bound)
                layer.bias.zero_()

    def first_layer_positional(self, positional: torch.Tensor) -> torch.Tensor:
        """``W_U @ positional``: layer 1's positional part, ``(..., C_U) -> (..., hidden)`` (no bias)."""
        return F.linear(positional, self.first.weight[:, : self.positional_channels])

    def first_layer_angular(self, angular: torch.Tensor) -> torch.Tensor:
        """``W_A @ angular + b``: layer 1's angular part and bias, ``(..., C_A) -> (..., hidden)``."""
        return F.linear(angular, self.first.weight[:, self.positional_channels:], self.first.bias)

    def from_first_layer(self, pre_activation: torch.Tensor) -> torch.Tensor:
        """Layers 2.. on layer 1's pre-activation ``(..., hidden)`` -> RGB ``(..., 3)``."""
        x = F.leaky_relu(pre_activation, self.negative_slope)
        for k, layer in enumerate(self.rest):
            x = layer(x)
            if k < len(self.rest) - 1:
                x = F.leaky_relu(x, self.negative_slope)
        return x

    def texel_image_l1_loss(self, positional: torch.Tensor, angular: torch.Tensor, target: torch.Tensor, *,
                            chunk_texels: int = 256, workers: int = 1, texel_groups: int = 1,
                            precision: str = "fp32") -> torch.Tensor:
        """Fused mean L1 loss of ``self(positional[None], angular[:, None])`` against ``target (B, N, 3)``.

        ``positional (N, C_U)`` is shared by the ``B`` images, ``angular (B, C_A)`` is one
        vector per image: layer 1's positional product is computed once per texel, its
        angular part once per image, layers 2.. by
        :func:`dynbtf.decoder.fused_mlp.split_mlp_l1_loss` in cache-sized chunks.
        With ``texel_groups = G``, the texels form ``G`` equal consecutive groups, group
        ``g`` seen under its own ``B`` images: ``angular`` is ``(G * B, C_A)`` (group-major).
        ``precision``: arithmetic of layers 2.. (see :func:`~dynbtf.decoder.fused_mlp.split_mlp_l1_loss`).
        """
        if texel_groups < 1 or angular.shape[0] % texel_groups or angular.shape[0] // texel_groups != target.shape[0]:
            raise InputError(f"texel_groups={texel_groups}: expected {texel_groups} x {target.shape[0]} images, got "
                             f"{angular.shape[0]}")
        return decoder_l1_loss(positional, angular, self.first, self.rest, self.negative_slope, target,
                               chunk_texels=chunk_texels, workers=workers, precision=precision)

    def forward(self, positional: torch.Tensor, angular: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from broadcastable ``positional (..., C_U)`` and ``angular (..., C_A)``."""
        return self.from_first_layer(self.first_layer_positional(positional) + self.first_layer_angular(angular))


@register("triple")
class TriplePlane(Representation):
    """The paper's Triple Plane representation (positional plane + two angular planes + MLP).

    Parameters
    ----------
    height, width : int
        Spatial resolution of the positional plane ``f_U`` (the BTF's texels).
    positional_channels : int, default 16
        Channels of ``f_U``.
    angular_resolution : int, default 20
        ``f_H`` and ``f_D`` are ``angular_resolution x angular_resolution`` (theta rows x phi columns).
    angular_channels : int, default 8
        Channels of ``f_H`` and of ``f_D`` each.
    hidden : int, default 32
        Hidden units of the decoder.
    layers : int, default 4
        Linear layers of the decoder.
    negative_slope : float, default 0.01
        LeakyReLU slope.
    seed : int, default 0
        Seed of the initialization (a model file stores it; loading overwrites the values).

    Examples
    --------
    >>> import torch
    >>> model = TriplePlane(8, 8)
    >>> uv = torch.rand(5, 7, 2)
    >>> w = torch.nn.functional.normalize(torch.rand(5, 7, 3) + torch.tensor([0, 0, 1.0]), dim=-1)
    >>> model(uv, w, w).shape
    torch.Size([5, 7, 3])
    >>> model.positional_plane().shape, model.storage_bytes()
    (torch.Size([8, 8, 16]), 42764)
    """

    #: Positional-plane channels beyond ``f_U`` that the decoder also reads (subclasses: e.g. a height).
    extra_positional_channels: int = 0

    def __init__(self, height: int, width: int, positional_channels: int = 16, angular_resolution: int = 20,
                 angular_channels: int = 8, hidden: int = 32, layers: int = 4, negative_slope: float = 0.01,
                 seed: int = 0) -> None:
        super().__init__()
        owner = type(self).__name__
        height, width = (config_int(owner, name, value, 1, MAX_SIDE) for name, value in
                         (("height", height), ("width", width)))
        positional_channels, angular_channels = (config_int(owner, name, value, 1, MAX_CHANNELS) for name, value in
                                                 (("positional_channels", positional_channels),
                                                  ("angular_channels", angular_channels)))
        angular_resolution = config_int(owner, "angular_resolution", angular_resolution, 1, MAX_SIDE)
        seed = config_int(owner, "seed", seed, 0, MAX_SEED)
        # built first: it checks its own arguments before the planes are allocated
        decoder = Decoder(positional_channels + self.extra_positional_channels, 2 * angular_channels, hidden,
                          layers, negative_slope, owner=owner)
        self._config = dict(height=height, width=width, positional_channels=positional_channels,
                            angular_resolution=angular_resolution, angular_channels=angular_channels,
                            hidden=int(hidden), layers=int(layers), negative_slope=decoder.negative_slope, seed=seed)
        generator = torch.Generator().manual_seed(seed)

        def he_plane(*shape: int) -> nn.Parameter:
            return nn.Parameter(torch.randn(shape, generator=generator) * math.sqrt(2.0 / shape[-1]))

        self.f_u = he_plane(height, width, positional_channels)
        self.f_h = he_plane(angular_resolution, angular_resolution, angular_channels)
        self.f_d = he_plane(angular_resolution, angular_resolution, angular_channels)
        self.decoder = decoder
        self.decoder.reset_parameters(generator)

    # ------------------------------------------------------------ Representation API
    def config(self) -> dict[str, Any]:
        return dict(self._config)

    def positional_plane(self) -> torch.Tensor:
        """``f_U``, ``(H, W, C_U)``: the texture synthesis consumes."""
        return self.f_u

    def angular_features(self, w_view: torch.Tensor, w_light: torch.Tensor,
                         taps: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """``concat(f_H(h), f_D(d))``, ``(..., 2 C_A)``, for unit directions ``(..., 3)``.

        Depends only on the directions: callers that decode many positions under
        one (view, light) pair compute it once and pass it to
        :meth:`decode_with_angular`. ``taps``: these pairs' rows of :meth:`direction_taps`
        (then the directions are not read again; equal to float rounding).
        """
        if taps is not None:
            index, weight = taps  # (P, 2, 4) into [f_H; f_D] flattened, (P, 2, 4)
            planes = torch.cat([self.f_h.reshape(-1, self.f_h.shape[-1]), self.f_d.reshape(-1, self.f_d.shape[-1])])
            return fetch_taps(planes, index, weight).reshape(index.shape[0], -1)
        h, d = half_diff_from_view_light(w_view, w_light)
        return torch.cat([fetch_angular(self.f_h, angular_plane_coords(h)),
                          fetch_angular(self.f_d, angular_plane_coords(d))], dim=-1)

    def direction_taps(self, w_view: torch.Tensor, w_light: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The texels and bilinear weights :meth:`angular_features` reads for pairs ``(P, 3)``:
        ``(index, weight)``, each ``(P, 2, 4)`` (``[:, 0]`` the half-vector plane, ``[:, 1]`` the
        difference-vector plane, as flat rows of ``[f_H; f_D]``; :func:`dynbtf.texture.angular_taps`)."""
        rows, columns = self.f_h.shape[:2]
        h, d = half_diff_from_view_light(w_view, w_light)
        index_h, weight_h = angular_taps(angular_plane_coords(h), rows, columns)
        index_d, weight_d = angular_taps(angular_plane_coords(d), rows, columns)
        return torch.stack([index_h, index_d + rows * columns], 1), torch.stack([weight_h, weight_d], 1)

    def decode_with_angular(self, features: torch.Tensor, angular: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from positional ``features (..., C_U)`` and ``angular (..., 2 C_A)``.

        The two inputs broadcast against each other (e.g. ``(N, C_U)`` with
        ``(B, 1, 2 C_A)`` gives ``(B, N, 3)``) and layer 1's positional product is
        computed once per feature vector, not once per broadcast copy.
        """
        features = features.to(self.decoder.first.weight.dtype)
        angular = angular.to(self.decoder.first.weight.dtype)
        return self.decoder(features, angular)

    def decode(self, features: torch.Tensor, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from positional ``features (..., C_U)`` and directions ``(..., 3)``."""
        return self.decode_with_angular(features, self.angular_features(w_view, w_light))

    # ------------------------------------------------------------ training fast path
    def predict_texel_images(self, w_view: torch.Tensor, w_light: torch.Tensor,
                             texels: torch.Tensor | None = None) -> torch.Tensor:
        """Whole images at texel centres: ``(B, N, 3)`` for ``B`` (view, light) pairs.

        Parameters
        ----------
        w_view, w_light : ``(B, 3)``
            One direction pair per image.
        texels : int64 ``(N,)``, optional
            Flat texel indices ``row * W + col`` (default: all ``H * W`` texels in order).

        At texel centres the bilinear positional fetch is exactly the plane's
        texel value, so the positional plane is read directly; the angular
        features are fetched once per image and layer 1's positional product once
        for all ``B`` images. Equal (to float rounding) to ``self(uv, w_view, w_light)``
        at the texel centres.
        """
        plane = self.f_u.reshape(-1, self.f_u.shape[-1])
        features = plane if texels is None else plane.index_select(0, texels)
        angular = self.angular_features(w_view, w_light)  # (B, 2 C_A)
        return self.decode_with_angular(features[None], angular[:, None])

    def texel_image_l1_loss(self, w_view: torch.Tensor, w_light: torch.Tensor, target: torch.Tensor,
                            texels: torch.Tensor | None = None, *, chunk_texels: int = 256,
                            workers: int = 1, texel_groups: int = 1, precision: str = "fp32",
                            angular_taps: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Mean L1 loss of :meth:`predict_texel_images` against ``target (B, N, 3)``, fused.

        Same value and gradients as ``(self.predict_texel_images(w_view, w_light, texels)
        - target).abs().mean()`` (to float rounding), computed by
        :func:`dynbtf.decoder.fused_mlp.split_mlp_l1_loss`: layer 1's positional
        product once per texel, its angular part once per image, layers 2.. in
        cache-sized chunks with a hand-written backward pass.

        With ``texel_groups = G``, the texels form ``G`` equal consecutive groups,
        ``w_view, w_light`` are ``(G * B, 3)``, group-major, and ``target[b, t]`` is
        texel ``t`` under image ``b`` of its group (see :func:`dynbtf.training.fit.texel_image_loss`).
        ``angular_taps``: these pairs' rows of :meth:`direction_taps` (the fit passes them).
        """
        plane = self.f_u.reshape(-1, self.f_u.shape[-1])
        if angular_taps is not None and type(self).extra_positional_channels == 0:
            # the fetches and layer 1 in native kernels too (None where they do not run: torch below)
            loss = triple_plane_l1_loss(plane, texels, self._stacked_angular_planes(), angular_taps, self.decoder.first,
                                        self.decoder.rest, self.decoder.negative_slope, target,
                                        chunk_texels=chunk_texels, workers=workers, precision=precision)
            if loss is not None:
                return loss
        features = plane if texels is None else plane.index_select(0, texels)
        return self.decoder.texel_image_l1_loss(features, self.angular_features(w_view, w_light, angular_taps),
                                                target, chunk_texels=chunk_texels, workers=workers,
                                                texel_groups=texel_groups, precision=precision)

    def _stacked_angular_planes(self) -> torch.Tensor:
        """``f_H`` and ``f_D`` flattened and stacked, ``(2 * rows * columns, C_A)``: the rows :meth:`direction_taps`
        indexes."""
        return torch.cat([self.f_h.reshape(-1, self.f_h.shape[-1]), self.f_d.reshape(-1, self.f_d.shape[-1])])

    @property
    def has_subtexel_term(self) -> bool:
        """Whether :meth:`subtexel_l1_loss` applies: the plane alone is read between texels (not the parallax
        model's, whose fetch moves with the view)."""
        return type(self).extra_positional_channels == 0

    def subtexel_l1_loss(self, neighbours: torch.Tensor, weights: torch.Tensor, w_view: torch.Tensor,
                         w_light: torch.Tensor, target: torch.Tensor, *, chunk_texels: int = 256, workers: int = 1,
                         precision: str = "fp32",
                         angular_taps: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Mean L1 loss at ``n`` points between texel centres, under ``B`` (view, light) pairs.

        ``neighbours``: int64 ``(4, n)``, each point's four surrounding texels (flat ``row * W + col``);
        ``weights``: float32 ``(4, n)``, their bilinear weights (what :func:`dynbtf.texture.fetch_wrap` reads at
        the point); ``w_view, w_light``: ``(B, 3)``; ``target``: ``(B, n, 3)``. The points' features are the
        weighted sums of the texels' (the bilinear fetch), decoded by the fused loss: with ``angular_taps`` (the
        fit passes them) the weighted fetch and layer 1 run in the native kernels too
        (:func:`~dynbtf.decoder.fused_mlp.triple_plane_l1_loss` with ``texel_weights``), else
        :meth:`texel_image_l1_loss`'s generic path. The trainer's sub-texel term (``TrainConfig.subtexel``)
        passes the same weights' mix of the measured texels as ``target``, so that the model's colours between
        centres become the mix of its measured ones."""
        if not self.has_subtexel_term:
            raise InputError(f"subtexel: the {self.kind!r} representation reads more than its plane between "
                             "texels; the sub-texel term applies to the Triple Plane ('triple')")
        plane = self.f_u.reshape(-1, self.f_u.shape[-1])
        if angular_taps is not None:  # the weighted fetch and layer 1 in native kernels (None where they do not run)
            # a few chunks per thread: the term's points are one group, and a chunk each would leave a thread
            # waiting on the other one wherever the prefetch thread shares its core
            chunk = min(chunk_texels, max(8, neighbours.shape[1] // (4 * workers)))
            loss = triple_plane_l1_loss(plane, neighbours, self._stacked_angular_planes(), angular_taps,
                                        self.decoder.first, self.decoder.rest, self.decoder.negative_slope, target,
                                        chunk_texels=chunk, workers=workers, precision=precision,
                                        texel_weights=weights)
            if loss is not None:
                return loss
        features = sum(weights[k, :, None] * plane.index_select(0, neighbours[k]) for k in range(4))
        return self.decoder.texel_image_l1_loss(features, self.angular_features(w_view, w_light, angular_taps),
                                                target, chunk_texels=chunk_texels, workers=workers, texel_groups=1,
                                                precision=precision)

    def param_groups(self) -> list[dict[str, Any]]:
        """Optimizer parameter groups, the paper's recipe: AdamW (PyTorch's default weight
        decay 0.01, "AdamW with the default setting"), lr 1e-3 for the planes, 3e-4 for the decoder."""
        return [{"params": [self.f_u, self.f_h, self.f_d], "lr": 1e-3, "weight_decay": 0.01, "name": "planes"},
                {"params": list(self.decoder.parameters()), "lr": 3e-4, "weight_decay": 0.01, "name": "decoder"}]

    has_fused_loss = True
    compiled_on_gpu = True

    def fast_decoder(self) -> FoldableDecoder:
        """The decoder, the angular fetch and the ``(f_H, f_D)`` planes, for fast synthesis."""
        return FoldableDecoder(self.decoder, self.angular_features, (self.f_h, self.f_d))

    def angular_planes(self) -> dict[str, torch.Tensor]:
        """The angular feature planes by name (``f_H``, ``f_D``), for visualization."""
        return {"f_H": self.f_h, "f_D": self.f_d}
