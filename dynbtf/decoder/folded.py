"""The folded decoder: a representation's MLP decoder as a synthesized BTF evaluates it.

A synthesizer answers in its own latent space (``hist``: decorrelated coefficients) with an output
map ``features = latent @ M + o`` (:meth:`dynbtf.synthesis.base.Synthesizer.output_map`). Layer 1 of
the decoder is linear in the positional features, so the map folds into it once:

    W_U (latent @ M + o)^T + b  =  latent @ (M W_U^T) + (o W_U^T) + b

and a query costs one ``(C, hidden)`` product instead of two. :meth:`FoldedDecoder.fold` is the one
place that fold is computed; the library's evaluation (:class:`DecodePath`), the Mitsuba plugin and
the web export all read its ``weight`` and ``bias``.

Footprint queries decode each pyramid level with a decoder of its own (:class:`LevelDecoder`, fitted
by :mod:`dynbtf.material.footprint_decoders`), and footprints wider than the exemplar answer the
material's mean appearance (:class:`MeanAppearance`, a quadrature of a few decodes). All of it is
stored in a compiled material (:mod:`dynbtf.material`).

Shapes: ``C`` latent channels, ``hidden`` the decoder's width, ``A`` angular input channels.
Weights are ``(out, in)`` like ``torch.nn.Linear``'s, except the folded positional weight,
``(C, hidden)`` (a right factor: ``latent @ weight``). Outputs are linear RGB float32.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from ..tables import Table

__all__ = ["FoldedDecoder", "LevelDecoder", "MeanAppearance", "DecodePath", "mlp", "hidden_layers", "stored_levels", "MLP_ROWS"]

#: Rows per call of decoder layers 2..: torch's small (32-wide) linear layers ran faster per row at
#: <= 16384 rows than at 32768+ (the activations stay in cache).
MLP_ROWS = 16384

Layers = list[tuple[torch.Tensor, torch.Tensor]]

#: Largest magnitude of a stored decoder value (:meth:`FoldedDecoder.stored_tables`): trained decoders stay
#: within a few hundred; beyond this a decode could overflow float32.
MAX_STORED_VALUE = 1e6
#: Most quadrature nodes of a stored mean appearance.
MAX_MEAN_NODES = 4096


def stored_levels(arrays: dict[str, torch.Tensor]) -> int:
    """How many level decoders :meth:`FoldedDecoder.to_tensors` tensors hold (``level.<i>.weight`` entries)."""
    return sum(1 for name in arrays if re.fullmatch(r"level\.\d+\.weight", name))


def hidden_layers(x: torch.Tensor, layers: Layers, slope: float) -> torch.Tensor:
    """Linear layers ``[(weight, bias), ...]`` each followed by LeakyReLU on ``x (N, in)`` (none: ``x``)."""
    for weight, bias in layers:
        x = F.leaky_relu(F.linear(x, weight, bias), slope)
    return x


def mlp(x: torch.Tensor, layers: Layers, slope: float) -> torch.Tensor:
    """Linear layers ``[(weight, bias), ...]`` with LeakyReLU between them on ``x (N, in)`` -> float32.

    On the CPU in float32 the training kernel's forward runs them (:func:`dynbtf.decoder.fused_mlp.native_mlp_forward`:
    register-blocked products on tiles of rows that stay in the L1 cache); elsewhere torch."""
    from .fused_mlp import native_mlp_forward

    out = native_mlp_forward(x, layers, slope)
    if out is not None:
        return out
    weight, bias = layers[-1]
    return F.linear(hidden_layers(x, layers[:-1], slope), weight, bias).float()


def _cast(layers: Layers, dtype: torch.dtype) -> Layers:
    return [(w.to(dtype), b.to(dtype)) for w, b in layers]


@dataclass
class LevelDecoder:
    """The decoder of one pyramid level: layer 1's positional part (output map folded in) and layers 2..

    ``weight (C, hidden)``, ``bias (hidden,)`` (the output map's offset through layer 1, **without**
    layer 1's own bias), ``rest``: layers 2.. ``[(weight (out, in), bias (out,)), ...]``.
    """

    weight: torch.Tensor
    bias: torch.Tensor
    rest: Layers


@dataclass
class MeanAppearance:
    """The mean appearance as a quadrature: ``sum_k weights[k] decode(nodes[k])`` over the directions.

    ``nodes (K, hidden)``: layer 1's positional pre-activation (without layer 1's bias) of ``K``
    representative positions; ``weights (K,)`` summing to one; ``rest``: layers 2.. of its own.
    """

    nodes: torch.Tensor
    weights: torch.Tensor
    rest: Layers


@dataclass
class FoldedDecoder:
    """A decoder with the synthesizer's output map folded into layer 1, per pyramid level.

    Attributes
    ----------
    levels : list of LevelDecoder
        ``levels[0]`` is the decoder itself (the point query); ``levels[l]`` decodes footprints whose
        nearest pyramid level is ``l`` (only ``levels[0]`` before footprint decoders are fitted).
    first_bias : ``(hidden,)``
        Layer 1's bias.
    angular_weight : ``(hidden, A)``
        Layer 1's angular weights.
    positional_channels : int
        ``C``, the positional inputs of layer 1.
    slope : float
        LeakyReLU's negative slope.
    mean : MeanAppearance or None
        The top level's mean appearance (footprints beyond the exemplar), if fitted.
    """

    levels: list[LevelDecoder]
    first_bias: torch.Tensor
    angular_weight: torch.Tensor
    positional_channels: int
    slope: float
    mean: MeanAppearance | None = None

    @classmethod
    def fold(cls, decoder, matrix: torch.Tensor | None, offset: torch.Tensor | None) -> "FoldedDecoder":
        """Fold ``features = latent @ matrix + offset`` into layer 1 of ``decoder`` (float32, detached).

        ``decoder``: a :class:`~dynbtf.representations.base.FoldableDecoder`'s ``decoder`` (``first``,
        ``rest``, ``positional_channels``, ``negative_slope``); ``matrix (C, C)`` and ``offset (C,)`` or
        None (identity, zero).
        """
        with torch.no_grad():
            c = int(decoder.positional_channels)
            first = decoder.first.weight.detach().float()
            w_pos = first[:, :c]  # (hidden, C)
            matrix = torch.eye(c, device=w_pos.device) if matrix is None else matrix.to(w_pos.device).float()
            offset = torch.zeros(c, device=w_pos.device) if offset is None else offset.to(w_pos.device).float()
            rest = [(layer.weight.detach().float(), layer.bias.detach().float()) for layer in decoder.rest]
            point = LevelDecoder((matrix @ w_pos.T).contiguous(), offset @ w_pos.T, rest)
            return cls([point], decoder.first.bias.detach().float(), first[:, c:].contiguous(), c,
                       float(decoder.negative_slope))

    @property
    def hidden(self) -> int:
        return int(self.first_bias.shape[0])

    def with_footprints(self, levels: list[LevelDecoder], mean: MeanAppearance | None) -> "FoldedDecoder":
        """The same decoder with fitted per-level decoders (``levels[0]`` must be the point decoder)."""
        return replace(self, levels=list(levels), mean=mean)

    def first_layer(self, level: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """Level ``level``'s whole layer 1 over ``concat(latent, angular)``: ``(hidden, C + A)``, ``(hidden,)``
        (layer 1's bias included): what a backend with a plain MLP (GLSL) loads."""
        entry = self.levels[level]
        return torch.cat([entry.weight.T, self.angular_weight], 1), entry.bias + self.first_bias

    def first_layer_angular(self, angular: torch.Tensor) -> torch.Tensor:
        """Layer 1's angular part with its bias: ``angular (N, A)`` -> ``(N, hidden)``."""
        return F.linear(angular.float(), self.angular_weight, self.first_bias)

    # ------------------------------------------------------------ storage
    def to_tensors(self) -> dict[str, torch.Tensor]:
        """Named CPU tensors (a compiled material's ``decoder.*`` entries); :meth:`from_tensors` inverts it."""
        out = {"first_bias": self.first_bias, "angular_weight": self.angular_weight,
               "positional_channels": torch.tensor(self.positional_channels),
               "slope": torch.tensor(self.slope, dtype=torch.float64)}
        for i, level in enumerate(self.levels):
            out[f"level.{i}.weight"], out[f"level.{i}.bias"] = level.weight, level.bias
            out.update(_layers_tensors(f"level.{i}.rest", level.rest))
        if self.mean is not None:
            out["mean.nodes"], out["mean.weights"] = self.mean.nodes, self.mean.weights
            out.update(_layers_tensors("mean.rest", self.mean.rest))
        return {k: v.detach().cpu().contiguous() for k, v in out.items()}

    @classmethod
    def stored_tables(cls, arrays: dict[str, torch.Tensor], reference: "FoldedDecoder") -> list[Table]:
        """The rules of :meth:`to_tensors` for a decoder folded from the same model as ``reference`` (that
        model's decoder folded with any output map): its positional channels and slope, as many levels as
        ``arrays`` store (at least one), each shaped like the reference's point decoder, and, if stored, a mean
        appearance of ``K`` nodes with weights in ``[0, 1]``. Every value finite and within
        :data:`MAX_STORED_VALUE`."""
        v, f32 = MAX_STORED_VALUE, torch.float32
        point = reference.levels[0]

        def layer_rules(prefix: str, layers: Layers) -> list[Table]:
            return [rule for k, (w, b) in enumerate(layers) for rule in
                    (Table(f"{prefix}.{k}.weight", f32, tuple(w.shape), -v, v),
                     Table(f"{prefix}.{k}.bias", f32, tuple(b.shape), -v, v))]

        rules = [Table("first_bias", f32, tuple(reference.first_bias.shape), -v, v),
                 Table("angular_weight", f32, tuple(reference.angular_weight.shape), -v, v),
                 Table("positional_channels", torch.int64, (), reference.positional_channels,
                       reference.positional_channels),
                 Table("slope", torch.float64, (), reference.slope, reference.slope)]
        for i in range(max(stored_levels(arrays), 1)):
            rules += [Table(f"level.{i}.weight", f32, tuple(point.weight.shape), -v, v),
                      Table(f"level.{i}.bias", f32, tuple(point.bias.shape), -v, v)]
            rules += layer_rules(f"level.{i}.rest", point.rest)
        if any(name.startswith("mean.") for name in arrays):
            nodes = arrays.get("mean.nodes")
            k = nodes.shape[0] if isinstance(nodes, torch.Tensor) and nodes.ndim == 2 else None
            rules += [Table("mean.nodes", f32, (k, reference.hidden), -v, v), Table("mean.weights", f32, (k,), 0.0, 1.0)]
            rules += layer_rules("mean.rest", point.rest)
        return rules

    @classmethod
    def from_tensors(cls, arrays: dict[str, torch.Tensor], device="cpu") -> "FoldedDecoder":
        """Inverse of :meth:`to_tensors` (raises ``KeyError`` naming a missing tensor)."""
        a = {k: v.to(device) for k, v in arrays.items()}
        levels = [LevelDecoder(a[f"level.{i}.weight"].float(), a[f"level.{i}.bias"].float(),
                               _tensors_layers(a, f"level.{i}.rest")) for i in range(stored_levels(a))]
        mean = None
        if "mean.nodes" in a:
            mean = MeanAppearance(a["mean.nodes"].float(), a["mean.weights"].float(), _tensors_layers(a, "mean.rest"))
        return cls(levels, a["first_bias"].float(), a["angular_weight"].float(), int(a["positional_channels"]),
                   float(a["slope"]), mean)


def _layers_tensors(prefix: str, layers: Layers) -> dict[str, torch.Tensor]:
    out = {}
    for k, (w, b) in enumerate(layers):
        out[f"{prefix}.{k}.weight"], out[f"{prefix}.{k}.bias"] = w.float(), b.float()
    return out


def _tensors_layers(arrays: dict[str, torch.Tensor], prefix: str) -> Layers:
    count = sum(1 for k in arrays if k.startswith(prefix + ".") and k.endswith(".weight"))
    if count == 0:
        raise KeyError(f"{prefix}.0.weight")
    return [(arrays[f"{prefix}.{k}.weight"].float(), arrays[f"{prefix}.{k}.bias"].float()) for k in range(count)]


@dataclass
class DecodePath:
    """Runs a :class:`FoldedDecoder` on synthesized latents: the decoding half of a query.

    Parameters
    ----------
    decoder : FoldedDecoder
    angular_features : callable
        ``(w_view (N, 3), w_light (N, 3)) -> (N, A)``, the representation's angular input.
    dtype : torch.dtype
        Of layers 2.. (``torch.bfloat16`` halves their cost on CPUs with bf16 matrix units).
    angular_planes : (f_H, f_D) or None
        The Triple Plane's angular planes ``(R, R, C_H)``, ``(R, R, C_D)``: on the CPU layer 1's
        angular part is then one numba kernel over planes pre-multiplied by layer 1's weights
        (:mod:`dynbtf.decoder.fast_decode`), fused with the positional product and the LeakyReLU.
    """

    decoder: FoldedDecoder
    angular_features: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    dtype: torch.dtype = torch.float32
    angular_planes: tuple[torch.Tensor, torch.Tensor] | None = None
    _fused: tuple | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        d = self.decoder
        self._rest = [_cast(level.rest, self.dtype) for level in d.levels]
        self._mean_rest = None if d.mean is None else _cast(d.mean.rest, self.dtype)
        if self.angular_planes is not None and d.first_bias.device.type == "cpu":
            from .fast_decode import fold_angular_planes

            planes = fold_angular_planes(*self.angular_planes, d.angular_weight)
            point = d.levels[0]
            self._fused = (planes, np.ascontiguousarray(point.weight.numpy()),
                           np.ascontiguousarray((point.bias + d.first_bias).numpy()))

    @property
    def fused(self) -> bool:
        """Whether layer 1 runs in the fused CPU kernel (the queries can then run on worker threads)."""
        return self._fused is not None

    def _activations(self, latent, wv, wl, positional=None) -> torch.Tensor:
        """Layer 1's activations ``(N, hidden)``; ``positional``: the pre-activation's positional part per
        level (with layer 1's bias on the fused path, without it on the torch path), else level 0's."""
        d = self.decoder
        if self._fused is not None:
            from .fast_decode import first_layer_preactivation

            planes, weight, bias = self._fused
            return torch.from_numpy(first_layer_preactivation(
                latent.numpy(), weight, bias, wv.float().numpy(), wl.float().numpy(), *planes,
                negative_slope=d.slope, positional=None if positional is None else positional.numpy()))
        point = d.levels[0]
        pre = torch.addmm(point.bias, latent, point.weight) if positional is None else positional
        pre = pre + d.first_layer_angular(self.angular_features(wv, wl))
        return F.leaky_relu(pre, d.slope)

    def decode(self, latent: torch.Tensor, wv: torch.Tensor, wl: torch.Tensor) -> torch.Tensor:
        """RGB ``(N, 3)`` float32 of point queries: ``latent (N, C)`` float32, unit directions ``(N, 3)``."""
        x = self._activations(latent, wv, wl).to(self.dtype)
        rest, slope = self._rest[0], self.decoder.slope
        return torch.cat([mlp(block, rest, slope) for block in x.split(MLP_ROWS)]) if len(x) else \
            torch.zeros(0, 3, device=latent.device)

    def decode_levels(self, latent: torch.Tensor, wv: torch.Tensor, wl: torch.Tensor, runs) -> torch.Tensor:
        """RGB of footprint queries sorted by level: ``runs`` are ``(start, stop, level)``, each run decoded by
        its level's decoder from the filtered ``latent (N, C)``."""
        d = self.decoder
        fused = self._fused is not None
        positional = torch.empty(latent.shape[0], d.hidden, dtype=torch.float32, device=latent.device)
        for a, b, level in runs:
            bias = d.levels[level].bias + d.first_bias if fused else d.levels[level].bias
            torch.addmm(bias, latent[a:b], d.levels[level].weight, out=positional[a:b])
        x = self._activations(latent, wv, wl, positional).to(self.dtype)
        out = torch.empty(x.shape[0], 3, dtype=torch.float32, device=x.device)
        for a, b, level in runs:
            for start in range(a, b, MLP_ROWS):
                stop = min(b, start + MLP_ROWS)
                out[start:stop] = mlp(x[start:stop], self._rest[level], d.slope)
        return out

    def mean_appearance(self, wv: torch.Tensor, wl: torch.Tensor) -> torch.Tensor:
        """The material's mean appearance ``(N, 3)`` float32 at unit directions ``(N, 3)`` (requires ``mean``):
        every node's activations as one batch of rows, their weighted mean, then the remaining layers."""
        d = self.decoder
        mean = d.mean
        nodes = mean.nodes + d.first_bias
        if self._fused is not None:  # the point query's angular fetch (the fused kernel's; no bias, no activation)
            from .fast_decode import first_layer_preactivation

            angular = torch.from_numpy(first_layer_preactivation(
                None, None, None, wv.float().numpy(), wl.float().numpy(), *self._fused[0],
                positional=np.zeros((len(wv), d.hidden), dtype=np.float32)))
        else:
            angular = F.linear(self.angular_features(wv, wl).float(), d.angular_weight)
        out = torch.empty(len(wv), 3, dtype=torch.float32, device=angular.device)
        split, weights = len(self._mean_rest) - 1, mean.weights.to(self.dtype)
        rows = max(1, MLP_ROWS // len(nodes))
        for start in range(0, len(angular), rows):
            block = angular[start:start + rows]
            x = F.leaky_relu(block[None] + nodes[:, None], d.slope).to(self.dtype).reshape(-1, block.shape[1])
            x = hidden_layers(x, self._mean_rest[:split], d.slope).reshape(len(nodes), len(block), -1)
            out[start:start + rows] = mlp(torch.tensordot(weights, x, dims=1), self._mean_rest[split:], d.slope)
        return out
