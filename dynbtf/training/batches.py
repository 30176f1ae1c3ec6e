"""Training batches: which (view, light) pairs and which texels each optimizer step sees.

A step's batch is ``G = texel_groups`` groups of ``B = images_per_step`` pairs; group
``g`` is read at its own texels (all texels when ``G = 1`` and no subset is asked for).
All randomness is counter-based, so any step's batch can be rebuilt from
``(seed, epoch, step)`` alone (what makes an interrupted fit resume exactly):

* the pair order of epoch ``e`` comes from ``numpy.random.default_rng([seed, 1, e])``
  (pass ``k > 0`` of the texel groups: ``[seed, 1, e, k]``);
* the texel subset, or the groups' start, of step ``s`` from ``default_rng([seed, 2, e, s])``;
* the points between texel centres of the sub-texel term (:func:`between_texel_points`), from
  ``default_rng([seed, 3, e, s])``.

Texel group ``g`` is the ``g``-th block of ``n = N // G`` consecutive flat texels
(row-major, wrapping) after a random start, so a batch is read with contiguous
reads from the image cache or straight from the BTF source
(:meth:`dynbtf.data.base.BTFSource.read_texels`).

**Data-parallel runs** (``part=(rank, world)``, :mod:`dynbtf.training.distributed`): every process
rebuilds the same full batch and keeps its share -- groups ``rank * G / world ...`` when ``G > 1``
(``G`` must be a multiple of ``world``), or a contiguous range of the ``B`` pairs when ``G = 1`` --
and reads only those targets. ``Batch.fraction`` is its share of the step's samples.

**View-coherent batches** (representations whose positional fetch depends on the view,
e.g. the parallax Triple Plane): each group's ``B`` pairs share one view. Per epoch
(and pass ``k``), each view's training pairs in a random order are cut into blocks of
``B`` (the last block wrapped round to ``B``) and the blocks visited in a random order.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError
from .images import ImageStore

__all__ = ["Batch", "BatchSampler", "between_texel_points"]


@dataclass
class Batch:
    """One optimizer step's data.

    Attributes
    ----------
    pairs : int64 ``(G * B, 2)``
        (view, light) indices, group-major.
    texels : int64 ``(G * n,)`` or None
        Flat texel indices, group-major (``None``: every texel, in order).
    target : float32 tensor ``(B, G * n, 3)``
        ``target[b, g * n + j]``: texel ``texels[g * n + j]`` under pair ``pairs[g * B + b]``.
    groups : int
        ``G`` of this batch (a process's share of the step's groups in a data-parallel run).
    fraction : float
        This batch's share of the step's samples (1 unless data-parallel).
    """

    pairs: np.ndarray
    texels: np.ndarray | None
    target: torch.Tensor
    groups: int = 1
    fraction: float = 1.0

    @property
    def samples(self) -> int:
        return int(self.target.shape[0] * self.target.shape[1])


class BatchSampler:
    """The batches of a training run (see the module docstring).

    Parameters
    ----------
    store : ImageStore
        Serves the targets (from its cache, or straight from the source).
    train_pairs : int64 ``(P, 2)``
        The training (view, light) pairs.
    images_per_step : int
        ``B``.
    texel_groups : int
        ``G``.
    texels_per_image : int or None
        Texels per step (default all); with ``G > 1`` rounded down to a multiple of ``G``.
    seed : int
    view_coherent : bool
        Every group's pairs share one view.
    device : torch.device
        Where targets are delivered.
    part : (rank, world)
        This process's share of every step in a data-parallel run (default ``(0, 1)``: all of it).
    """

    def __init__(self, store: ImageStore, train_pairs: np.ndarray, *, images_per_step: int, texel_groups: int = 1,
                 texels_per_image: int | None = None, seed: int = 0, view_coherent: bool = False,
                 device=None, part: tuple[int, int] = (0, 1)) -> None:
        self.store, self.train_pairs = store, np.asarray(train_pairs, dtype=np.int64)
        self.b, self.n_groups, self.seed = int(images_per_step), int(texel_groups), int(seed)
        self.device = torch.device("cpu") if device is None else torch.device(device)
        self.n_texels = store.n_texels
        self.texels_per_image = min(texels_per_image or self.n_texels, self.n_texels)
        b, g = self.b, self.n_groups
        if g > 1 and (b * g > len(self.train_pairs) or g > self.texels_per_image):
            raise InputError(f"texel_groups={g} x images_per_step={b} needs at least {b * g} training "
                             f"pairs and {g} texels per step; the BTF has {len(self.train_pairs)} pairs and "
                             f"{self.texels_per_image} texels per step")
        self.texels_per_step = self.texels_per_image - self.texels_per_image % g  # equal groups
        self.rank, self.world = int(part[0]), int(part[1])
        if self.world > 1 and g > 1 and g % self.world:
            raise InputError(f"--texel-groups {g}: a data-parallel run on {self.world} processes needs a multiple "
                             f"of {self.world} (each process trains its share of the groups)")
        if self.world > 1 and g == 1 and b < self.world:
            raise InputError(f"--images-per-step {b}: a data-parallel run on {self.world} processes needs at "
                             f"least {self.world} images per step")
        self.view_coherent = bool(view_coherent)
        if self.view_coherent:
            self._views_of_pairs = [np.flatnonzero(self.train_pairs[:, 0] == v)
                                    for v in np.unique(self.train_pairs[:, 0])]
            self.steps_per_epoch = sum(math.ceil(len(p) / b) for p in self._views_of_pairs)
        else:
            self.steps_per_epoch = math.ceil(len(self.train_pairs) / b)

    @property
    def samples_per_epoch(self) -> int:
        """``pairs x texels per step``: what one epoch visits (its definition)."""
        return len(self.train_pairs) * self.texels_per_step

    # ------------------------------------------------------------------ orders
    @functools.lru_cache(maxsize=2)
    def _view_blocks(self, epoch: int) -> np.ndarray:
        """Pair indices ``(G * blocks, B)``: ``G`` concatenated block orders of ``epoch``, one view per block."""
        passes = []
        for k in range(self.n_groups):
            rng = np.random.default_rng([self.seed, 1, epoch] + ([k] if k else []))
            blocks = np.concatenate([np.resize(p[rng.permutation(len(p))], (math.ceil(len(p) / self.b), self.b))
                                     for p in self._views_of_pairs])
            passes.append(blocks[rng.permutation(len(blocks))])
        return np.concatenate(passes)

    @functools.lru_cache(maxsize=2)
    def _epoch_order(self, epoch: int) -> np.ndarray:
        """Pair order of ``epoch``: ``G`` concatenated permutations of the training pairs."""
        return np.concatenate([np.random.default_rng([self.seed, 1, epoch] + ([k] if k else [])).permutation(
            len(self.train_pairs)) for k in range(self.n_groups)])

    def pairs(self, epoch: int, step: int) -> np.ndarray:
        """The (view, light) pairs of a step, ``(G * B', 2)`` group-major (``B' <= B`` at an epoch's end, G = 1)."""
        b, g = self.b, self.n_groups
        if self.view_coherent:
            return self.train_pairs[self._view_blocks(epoch)[step * g:(step + 1) * g].reshape(-1)]
        if g == 1:
            order = self._epoch_order(epoch)
            return self.train_pairs[order[step * b:(step + 1) * b]]
        order = self._epoch_order(epoch)
        return self.train_pairs[order[np.arange(step * b * g, (step + 1) * b * g) % len(order)]]

    def texels(self, epoch: int, step: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(texels, starts)``: a step's flat texels (None: all) and, with groups, each group's first texel."""
        rng = np.random.default_rng([self.seed, 2, epoch, step])
        if self.n_groups == 1:
            if self.texels_per_image < self.n_texels:
                return np.sort(rng.choice(self.n_texels, self.texels_per_image, replace=False)), None
            return None, None
        n = self.texels_per_step // self.n_groups
        starts = (int(rng.integers(self.n_texels)) + n * np.arange(self.n_groups)) % self.n_texels
        return ((starts[:, None] + np.arange(n)[None, :]) % self.n_texels).reshape(-1), starts

    def batch(self, epoch: int, step: int) -> Batch:
        """The batch of step ``step`` of epoch ``epoch`` (thread-safe: called from a prefetch thread);
        this process's share of it in a data-parallel run."""
        pairs = self.pairs(epoch, step)
        texels, starts = self.texels(epoch, step)
        if self.n_groups == 1:
            total = len(pairs)
            if self.world > 1:
                pairs = np.array_split(pairs, self.world)[self.rank]
            target = self.store.get(pairs, texels, device=self.device)
            return Batch(pairs, texels, target, 1, len(pairs) / total)
        n = self.texels_per_step // self.n_groups
        mine = slice(None)
        if self.world > 1:
            share = self.n_groups // self.world
            mine = slice(self.rank * share, (self.rank + 1) * share)
        grouped = pairs.reshape(self.n_groups, self.b, 2)[mine]
        target = self.store.get_blocks(grouped, starts[mine], n, device=self.device)
        local_texels = texels.reshape(self.n_groups, n)[mine].reshape(-1)
        return Batch(grouped.reshape(-1, 2), local_texels, target, len(grouped), len(grouped) / self.n_groups)


def between_texel_count(step_texels: int) -> int:
    """How many points between texel centres the sub-texel term reads in a step of ``step_texels`` texels: an
    eighth of them, at least 64.

    >>> between_texel_count(4096), between_texel_count(100)
    (512, 64)
    """
    return max(64, int(step_texels) // 8)


def between_texel_points(height: int, width: int, count: int, rng: np.random.Generator
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` random points of a ``height x width``-texel repeat, uniform over it, each with the four texels
    the bilinear fetch mixes there (:func:`dynbtf.texture.fetch_wrap`'s convention: texel ``(col, row)`` has its
    centre at ``uv = ((col + 1/2) / W, (row + 1/2) / H)``; periodic).

    Returns ``neighbours`` int64 ``(4, count)`` (flat ``row * W + col``: the texel, its right, upper and diagonal
    neighbours), ``weights`` float32 ``(4, count)`` (bilinear, summing to 1) and ``uv`` float64 ``(count, 2)``.

    >>> neighbours, weights, uv = between_texel_points(2, 4, 3, np.random.default_rng(0))
    >>> neighbours.shape, weights.shape, bool(np.allclose(weights.sum(0), 1)), uv.shape
    ((4, 3), (4, 3), True, (3, 2))
    """
    x, y = rng.integers(0, width, count), rng.integers(0, height, count)
    fx, fy = rng.random(count), rng.random(count)
    right, up = (x + 1) % width, (y + 1) % height
    neighbours = np.stack([y * width + x, y * width + right, up * width + x, up * width + right])
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]).astype(np.float32)
    uv = np.stack([(x + 0.5 + fx) / width, (y + 0.5 + fy) / height], -1)
    return neighbours, weights, uv
