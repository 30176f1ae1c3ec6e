"""NeuMIP as modified in the paper: one neural texture and an MLP conditioned on the directions.

Kuznetsov et al. 2021 (NeuMIP) learn a pyramid of neural textures plus a
neural offset module. The paper compares against a reduced version, "without
the offset module and only the finest layer of the feature pyramid":

    rgb = MLP( concat( light_xy, view_xy, T(uv) ) )

* ``T`` -- the **positional neural texture**, ``(H, W, 8)`` at the BTF's spatial
  resolution, fetched bilinearly and periodically. It is the positional plane
  that synthesis replaces (the paper's Fig. 9 synthesizes it like the Triple
  Plane's ``f_U``).
* ``light_xy``, ``view_xy`` -- the directions' orthographic projections onto
  the unit disk, i.e. the ``(x, y)`` components of the unit vectors (NeuMIP's
  "light/camera xy" inputs).
* the MLP -- 4 linear layers ``12 -> 32 -> 32 -> 32 -> 3`` with LeakyReLU after
  each hidden layer, no output activation: the same decoder as the Triple Plane
  (:class:`dynbtf.representations.triple_plane.Decoder`), here with 8 positional
  and 4 angular inputs. Its first layer is written as ``W_T T + W_A [l_xy, v_xy] + b``;
  the order of the concatenation does not matter for a linear layer.

Training recipe (NeuMIP's): L1 loss, Adam with lr 1e-3 for every parameter and
no weight decay (AdamW with weight decay 0 is Adam) -- see :meth:`NeuMIP.param_groups`,
which the shared trainer (:func:`dynbtf.training.fit.fit`) uses; whole-image
batches take the same fused loss as the Triple Plane (:meth:`NeuMIP.texel_image_l1_loss`). Initialization as the Triple
Plane's: texture ~ ``N(0, 2 / C)``, Kaiming-uniform decoder, from ``seed``.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from .base import MAX_CHANNELS, MAX_SEED, MAX_SIDE, FoldableDecoder, Representation, config_int, register
from .triple_plane import Decoder

__all__ = ["NeuMIP"]


@register("neumip")
class NeuMIP(Representation):
    """The paper's modified NeuMIP (finest level only, no offset module).

    Parameters
    ----------
    height, width : int
        Spatial resolution of the neural texture (the BTF's texels).
    channels : int, default 8
        Channels of the neural texture.
    hidden : int, default 32
        Hidden units of the MLP.
    layers : int, default 4
        Linear layers of the MLP.
    negative_slope : float, default 0.01
        LeakyReLU slope.
    seed : int, default 0
        Seed of the initialization.

    Examples
    --------
    >>> import torch
    >>> model = NeuMIP(8, 8)
    >>> w = torch.nn.functional.normalize(torch.rand(5, 3) + torch.tensor([0, 0, 1.0]), dim=-1)
    >>> model(torch.rand(5, 2), w, w).shape, model.positional_plane().shape
    (torch.Size([5, 3]), torch.Size([8, 8, 8]))
    """

    def __init__(self, height: int, width: int, channels: int = 8, hidden: int = 32, layers: int = 4,
                 negative_slope: float = 0.01, seed: int = 0) -> None:
        super().__init__()
        height, width = (config_int("NeuMIP", name, value, 1, MAX_SIDE) for name, value in
                         (("height", height), ("width", width)))
        channels = config_int("NeuMIP", "channels", channels, 1, MAX_CHANNELS)
        seed = config_int("NeuMIP", "seed", seed, 0, MAX_SEED)
        # built first: it checks its own arguments before the texture is allocated
        decoder = Decoder(channels, 4, hidden, layers, negative_slope, owner="NeuMIP")
        self._config = dict(height=height, width=width, channels=channels, hidden=int(hidden), layers=int(layers),
                            negative_slope=decoder.negative_slope, seed=seed)
        generator = torch.Generator().manual_seed(seed)
        self.texture = nn.Parameter(torch.randn((height, width, channels), generator=generator)
                                    * math.sqrt(2.0 / channels))
        self.decoder = decoder
        self.decoder.reset_parameters(generator)

    # ------------------------------------------------------------ Representation API
    def config(self) -> dict[str, Any]:
        return dict(self._config)

    def positional_plane(self) -> torch.Tensor:
        """The neural texture ``(H, W, C)``."""
        return self.texture

    @staticmethod
    def direction_inputs(w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """NeuMIP's angular input ``[light_x, light_y, view_x, view_y]``, ``(..., 4)``."""
        return torch.cat([w_light[..., :2], w_view[..., :2]], dim=-1)

    def angular_features(self, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """The decoder's angular input, ``(..., 4)`` (:meth:`direction_inputs`).

        Same role as the Triple Plane's ``angular_features``: with it the
        synthesized BTF (:class:`dynbtf.infinite_btf.SynthesizedBTF`) takes its fast
        path (layer 1's angular part once per chunk).
        """
        return self.direction_inputs(w_view, w_light)

    def decode(self, features: torch.Tensor, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from texture features ``(..., C)`` and directions ``(..., 3)``.

        ``features`` and the directions broadcast against each other.
        """
        dtype = self.decoder.first.weight.dtype
        return self.decoder(features.to(dtype), self.direction_inputs(w_view, w_light).to(dtype))

    # ------------------------------------------------------------ training
    has_fused_loss = True

    def fast_decoder(self) -> FoldableDecoder:
        """The Triple Plane's decoder on NeuMIP's direction inputs, for fast synthesis."""
        return FoldableDecoder(self.decoder, self.angular_features)

    def param_groups(self) -> list[dict[str, Any]]:
        """Optimizer parameter groups: NeuMIP trains everything with Adam, lr 1e-3, no weight decay."""
        return [{"params": [self.texture], "lr": 1e-3, "weight_decay": 0.0, "name": "texture"},
                {"params": list(self.decoder.parameters()), "lr": 1e-3, "weight_decay": 0.0, "name": "decoder"}]

    def predict_texel_images(self, w_view: torch.Tensor, w_light: torch.Tensor,
                             texels: torch.Tensor | None = None) -> torch.Tensor:
        """Whole images at texel centres, ``(B, N, 3)``, for ``B`` pairs ``w_view, w_light (B, 3)``.

        ``texels`` are flat indices ``row * W + col`` (default all, in order). At
        texel centres the bilinear fetch is the texel value itself, so the texture
        is read directly; equal (to rounding) to ``self(uv, w_view, w_light)``.
        """
        plane = self.texture.reshape(-1, self.texture.shape[-1])
        features = plane if texels is None else plane.index_select(0, texels)
        return self.decode(features[None], w_view[:, None], w_light[:, None])

    def texel_image_l1_loss(self, w_view: torch.Tensor, w_light: torch.Tensor, target: torch.Tensor,
                            texels: torch.Tensor | None = None, *, chunk_texels: int = 256,
                            workers: int = 1, texel_groups: int = 1, precision: str = "fp32",
                            angular_taps: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
        """Mean L1 loss of :meth:`predict_texel_images` against ``target (B, N, 3)``, fused (NeuMIP's direction
        inputs are the directions themselves: it has no ``angular_taps``).

        The same fast path as the Triple Plane's (same decoder structure): layer 1's
        texture product once per texel, its direction part once per image, layers 2..
        by :func:`dynbtf.decoder.fused_mlp.split_mlp_l1_loss`. Equal (to rounding)
        to ``(self.predict_texel_images(...) - target).abs().mean()``; ``texel_groups``
        and ``precision`` as in :meth:`dynbtf.representations.triple_plane.TriplePlane.texel_image_l1_loss`.
        """
        plane = self.texture.reshape(-1, self.texture.shape[-1])
        features = plane if texels is None else plane.index_select(0, texels)
        return self.decoder.texel_image_l1_loss(features, self.direction_inputs(w_view, w_light), target,
                                                chunk_texels=chunk_texels, workers=workers, texel_groups=texel_groups,
                                                precision=precision)
