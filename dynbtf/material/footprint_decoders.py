"""Per-level decoders and the mean appearance: what footprint queries decode with.

A footprint query reads the synthesized plane's pyramid at the footprint's level
(:mod:`dynbtf.synthesis.mip`). The decoder is nonlinear, so decoding the filtered features is not
the mean of the decoded colours over the footprint (on a fitted leather ~6% darker, and the error
varies with the directions). :func:`fit_footprint_decoders` fine-tunes, per pyramid level, a copy of
the decoder (layer 1's positional part and layers 2..; layer 1's angular part kept) so that on the
filtered latent of footprints whose nearest level is that one it matches the mean of
``LEVEL_FIT_GRID**2`` jittered point queries over the footprint, at ``LEVEL_FIT_QUERIES`` random
positions and (view, light) pairs (mean squared error, Adam, cosine schedule, seeded).

Footprints that read only the top ``1 x 1`` level see the same latent everywhere and answer the
material's mean appearance, a function of the directions alone: :func:`fit_mean_appearance` fits
a quadrature of ``MEAN_NODES`` decodes (relative squared error) to the decoder's mean over
``MEAN_FIT_POSITIONS`` synthesized positions.

Both fits run once per model, method and seed when a material is compiled
(:func:`dynbtf.material.compile_material`) and are stored with it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from ..decoder.folded import FoldedDecoder, LevelDecoder, MeanAppearance, hidden_layers, mlp

__all__ = ["fit_footprint_decoders", "fit_mean_appearance", "LEVEL_FIT_QUERIES", "LEVEL_FIT_STEPS", "MEAN_FIT_STEPS"]

#: The per-level decoders' fit: positions and (view, light) pairs per level, jittered point queries averaged per
#: footprint (a grid x grid), Adam steps, minibatch rows and rate, seed.
LEVEL_FIT_QUERIES = 65536
LEVEL_FIT_GRID = 8
LEVEL_FIT_STEPS = 1000
LEVEL_FIT_BATCH = 2048
LEVEL_FIT_LR = 3e-3
LEVEL_FIT_SEED = 0

#: The mean appearance's quadrature: nodes, synthesized positions whose mean is the target (the same positions
#: for every pair), (view, light) pairs, Adam steps.
MEAN_NODES = 3
MEAN_FIT_POSITIONS = 512
MEAN_FIT_PAIRS = 65536
MEAN_FIT_STEPS = 2000

#: ``(points (N, 2) float64 exemplar repeats, w_view (N, 3), w_light (N, 3)) -> RGB (N, 3) float32``.
PointQuery = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def random_direction_pairs(rng: np.random.Generator, n: int) -> np.ndarray:
    """``(2, n, 3)`` float64 (view, light) unit directions: cosines uniform in [0.01, 1] (grazing views included:
    where filtering matters most), azimuths uniform."""
    cos_t = rng.uniform(0.01, 1.0, (2, n))
    phi = rng.uniform(0.0, 2 * np.pi, (2, n))
    sin_t = np.sqrt(1.0 - cos_t ** 2)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def _adam_steps(loss_of, parameters, steps: int, batches) -> None:
    """Adam (cosine schedule) on ``loss_of(rows)``, one step per row-index batch, on one torch thread: the small
    layers' backward passes ran several times slower on two threads of a loaded machine (OpenMP spin-waiting).

    ``eps`` sits well above float noise: where a decoder is already exact (e.g. a constant plane) the gradients
    are rounding noise, which Adam's normalization would otherwise turn into full-size steps. Gradients are on
    here whatever the caller's mode (a material compiled from inside ``torch.no_grad()`` still fits)."""
    from ..decoder.fused_mlp import single_intra_op_thread

    optimizer = torch.optim.Adam(parameters, lr=LEVEL_FIT_LR, eps=1e-6)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps)
    with single_intra_op_thread(), torch.enable_grad():
        for rows in batches:
            loss = loss_of(rows)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            schedule.step()


def _footprint_targets(level: int, widths, point_query: PointQuery, density: float, rng, device):
    """Random footprints whose nearest level is ``level`` (the top level: up to 4x its width) and the mean of
    jittered point queries over each: ``(centres (n, 2) repeats, texels (n,), w_view, w_light, target (n, 3))``."""
    n, grid = LEVEL_FIT_QUERIES, LEVEL_FIT_GRID
    hi = 4.0 * widths[level] if level == len(widths) - 1 else np.sqrt(widths[level] * widths[level + 1])
    texels = np.exp(rng.uniform(np.log(np.sqrt(widths[level - 1] * widths[level])), np.log(hi), n))
    centres = rng.random((n, 2)) * 64.0
    w = random_direction_pairs(rng, n)
    wv = torch.from_numpy(w[0]).to(device, torch.float32)
    wl = torch.from_numpy(w[1]).to(device, torch.float32)
    target = torch.zeros(n, 3, dtype=torch.float32, device=device)
    side = (texels / density)[:, None]  # repeats
    for i in range(grid):  # one jittered point query per cell of a grid x grid
        for j in range(grid):
            jitter = (np.array([j, i]) + rng.random((n, 2))) / grid - 0.5
            target += point_query(torch.from_numpy(centres + side * jitter).to(device), wv, wl)
    return centres, texels, wv, wl, target / (grid * grid)


def _fit_level(decoder: FoldedDecoder, latent, angular, target, rng) -> LevelDecoder | None:
    """One level's decoder fine-tuned from the point decoder, or None where the point decoder is as good."""
    point, slope = decoder.levels[0], decoder.slope
    weight = point.weight.clone().requires_grad_()
    bias = point.bias.clone().requires_grad_()
    rest = [(w.clone().requires_grad_(), b.clone().requires_grad_()) for w, b in point.rest]

    def loss_of(rows):
        x = F.leaky_relu(torch.addmm(bias, latent[rows], weight) + angular[rows], slope)
        return ((mlp(x, rest, slope) - target[rows]) ** 2).mean()

    n = len(target)
    with torch.no_grad():
        plain_loss = float(loss_of(slice(None)))
    _adam_steps(loss_of, [weight, bias, *[p for pair in rest for p in pair]], LEVEL_FIT_STEPS,
                torch.from_numpy(rng.integers(0, n, (LEVEL_FIT_STEPS, min(n, LEVEL_FIT_BATCH)))))
    with torch.no_grad():
        fitted_loss = float(loss_of(slice(None)))
    if fitted_loss >= plain_loss:  # e.g. a constant plane: keep the point decoder
        return None
    return LevelDecoder(weight.detach(), bias.detach(), [(w.detach(), b.detach()) for w, b in rest])


def fit_footprint_decoders(decoder: FoldedDecoder, synthesizer, point_query: PointQuery,
                           angular_features, density: float, *, progress: bool = True) -> FoldedDecoder:
    """``decoder`` with per-level decoders and the top level's mean appearance fitted (see the module docstring).

    Parameters
    ----------
    decoder : FoldedDecoder
        The point decoder (``levels[0]``), folded with ``synthesizer``'s output map.
    synthesizer : Synthesizer
        Its ``filtered_latent``, ``latent`` and ``level_of_detail()`` give the footprints' latents.
    point_query : callable
        The synthesized BTF's point query in exemplar repeats (relief included): the fit's targets.
    angular_features : callable
        ``(w_view, w_light) -> (N, A)``, the representation's angular input.
    density : float
        Texels per exemplar repeat (footprints are drawn in texels).
    """
    from ..progress import progress_bar

    widths = synthesizer.level_of_detail().widths
    device = decoder.first_bias.device
    rng = np.random.default_rng(LEVEL_FIT_SEED)
    levels = [decoder.levels[0]]
    for level in progress_bar(range(1, len(widths)), desc="per-level decoders", unit="level",
                              disable=not progress or len(widths) < 6):
        with torch.no_grad():
            centres, texels, wv, wl, target = _footprint_targets(level, widths, point_query, density, rng, device)
            latent = synthesizer.filtered_latent(torch.from_numpy(centres).to(device),
                                                 torch.from_numpy(texels)).to(device)
            angular = decoder.first_layer_angular(angular_features(wv, wl))
        levels.append(_fit_level(decoder, latent, angular, target, rng) or levels[0])
    mean = fit_mean_appearance(decoder, synthesizer, angular_features, rng) if len(levels) > 1 else None
    return decoder.with_footprints(levels, mean)


def fit_mean_appearance(decoder: FoldedDecoder, synthesizer, angular_features,
                        rng: np.random.Generator) -> MeanAppearance | None:
    """The top level's quadrature (see the module docstring), or None if that level is not constant."""
    slope, point = decoder.slope, decoder.levels[0]
    device = decoder.first_bias.device
    top = len(synthesizer.level_of_detail().widths) - 1
    texel = float(synthesizer.level_of_detail().widths[top]) * 4.0
    with torch.no_grad():
        probe = torch.from_numpy(rng.random((16, 2)) * 64.0).to(device)
        latent = synthesizer.filtered_latent(probe, torch.full((16,), texel, dtype=torch.float64)).float()
        if float((latent - latent[:1]).abs().max()) > 1e-6:
            return None
        n = MEAN_FIT_PAIRS
        w = torch.from_numpy(random_direction_pairs(rng, n)).float()
        angular = decoder.first_layer_angular(angular_features(w[0].to(device), w[1].to(device)))  # with its bias
        # layer 1's positional pre-activation (without its bias) at random synthesized positions
        where = torch.from_numpy(rng.random((MEAN_FIT_POSITIONS, 2)) * 64.0).to(device)
        points = torch.addmm(point.bias, synthesizer.latent(where).to(device).float(), point.weight)
        # the same positions for every (view, light) pair: the targets are a smooth function of the directions
        target = torch.zeros(n, 3, dtype=torch.float32, device=device)
        for start in range(0, n, 64):
            pre = points[None] + angular[start:start + 64, None]
            target[start:start + 64] = mlp(F.leaky_relu(pre, slope), point.rest, slope).mean(1)
    nodes = points[torch.from_numpy(rng.choice(len(points), MEAN_NODES, replace=False)).to(device)].clone()
    nodes.requires_grad_()
    logits = torch.zeros(MEAN_NODES, device=device, requires_grad=True)
    rest = [(w_.clone().requires_grad_(), b_.clone().requires_grad_()) for w_, b_ in point.rest]
    split = len(rest) - 1  # the nodes' weighted mean is taken before the last (linear) layer

    def loss_of(rows):
        x = F.leaky_relu(nodes[None] + angular[rows, None], slope)
        value = mlp((hidden_layers(x, rest[:split], slope) * torch.softmax(logits, 0)[None, :, None]).sum(1),
                    rest[split:], slope)
        # relative error: the mean appearance spans orders of magnitude over the directions
        return (((value - target[rows]) / (target[rows].abs() + 0.02)) ** 2).mean()

    def snapshot() -> MeanAppearance:
        return MeanAppearance(nodes.detach().clone(), torch.softmax(logits.detach(), 0),
                              [(w_.detach().clone(), b_.detach().clone()) for w_, b_ in rest])

    with torch.no_grad():
        start_loss, start = float(loss_of(slice(None))), snapshot()
    _adam_steps(loss_of, [nodes, logits, *[p for pair in rest for p in pair]], MEAN_FIT_STEPS,
                torch.from_numpy(rng.integers(0, n, (MEAN_FIT_STEPS, min(n, LEVEL_FIT_BATCH)))))
    with torch.no_grad():
        fitted_loss = float(loss_of(slice(None)))
    # the starting point (the decoder at MEAN_NODES of the positions) is kept where it is as good, e.g. a
    # constant plane, whose mean appearance it is exactly
    return snapshot() if fitted_loss < start_loss else start
