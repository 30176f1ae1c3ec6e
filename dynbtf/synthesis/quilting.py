"""Image quilting (Efros & Freeman 2001): the non-dynamic comparison.

Quilting grows a finite plane block by block in raster order: each new block
(``block x block`` texels, overlapping its left and top neighbours by
``overlap``) is chosen at random among the exemplar blocks whose overlap error
is within ``tolerance`` (1.1) times the smallest, and is pasted along a
minimum-error boundary cut found by dynamic programming (vertical cut in the
left overlap, horizontal in the top one, combined at the corner).

For a 16-channel latent plane the overlap error is the sum of squared
differences in PCA-whitened space (each principal component scaled to unit
variance), computed for every candidate position at once with FFT correlation.

Quilting is **not dynamic**: the whole plane must be generated and stored
before the first query (:meth:`Quilting.storage_bytes`; the paper reports
2.15 GB for 15x a 400x400x16 plane in float32). Queries read the stored plane
with wrap addressing, so the result repeats with the quilt's period.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from ..progress import progress_bar
from ..errors import InputError
from ..tables import Table
from ..texture import fetch_wrap
from .base import Synthesizer, feature_bound, register_synthesizer, wrapped_texel_position
from .histogram import Decorrelation
from .lattice import split_uv
from .mip import LevelOfDetail, PlanePyramid

__all__ = ["Quilting", "min_error_cut", "min_error_seam", "quilt", "overlap_errors", "quilted_storage_bytes", "MAX_QUILT_SIDE"]

#: Largest side of a stored quilted plane, texels (the paper's 15 repeats of 400 texels are 6,000).
MAX_QUILT_SIDE = 1 << 16


def quilted_storage_bytes(height: int, width: int, channels: int, repeats: float, bytes_per_value: int = 4) -> int:
    """Bytes of a quilted plane covering ``repeats x repeats`` repeats of an ``H x W x C`` exemplar.

    >>> round(quilted_storage_bytes(400, 400, 16, 15) / 2**30, 2)  # the paper's 15x: 2.15 GB
    2.15
    """
    return round(repeats * height) * round(repeats * width) * channels * bytes_per_value


def min_error_cut(errors: np.ndarray) -> np.ndarray:
    """Minimum-error vertical path through ``errors (..., rows, cols)`` by dynamic programming.

    Returns ``cut (..., rows)`` int64: the column of the path in each row; moving down one
    row the path shifts by at most one column. Texels left of the cut keep the
    old content, the cut texel and those right of it take the new block. Leading axes are
    independent problems solved at once (ties go to the leftmost column).

    >>> min_error_cut(np.array([[5, 0, 5], [5, 5, 0], [5, 5, 0]], dtype=float)).tolist()
    [1, 2, 2]
    """
    errors = np.asarray(errors, dtype=np.float64)
    rows, cols = errors.shape[-2:]
    cost = errors.copy()
    pad = np.full(errors.shape[:-2] + (1,), np.inf)
    for i in range(1, rows):
        prev = cost[..., i - 1, :]
        left = np.concatenate([pad, prev[..., :-1]], -1)
        right = np.concatenate([prev[..., 1:], pad], -1)
        cost[..., i, :] += np.minimum(np.minimum(left, prev), right)
    cut = np.empty(errors.shape[:-1], dtype=np.int64)
    cut[..., -1] = np.argmin(cost[..., -1, :], -1)
    padded = np.concatenate([pad[..., None, :].repeat(rows, -2), cost, pad[..., None, :].repeat(rows, -2)], -1)
    for i in range(rows - 2, -1, -1):
        j = cut[..., i + 1]  # candidates j-1, j, j+1 are padded columns j, j+1, j+2
        window = np.stack([np.take_along_axis(padded[..., i, :], (j + k)[..., None], -1)[..., 0] for k in range(3)], -1)
        cut[..., i] = j - 1 + np.argmin(window, -1)
    return cut


def min_error_seam(errors: np.ndarray) -> np.ndarray:
    """Minimum-error seam through ``errors (..., rows, cols)`` that may also run along a row: a cut that follows joints.

    Returns ``cut (..., rows)`` int64 with :func:`min_error_cut`'s meaning (texels left of ``cut[r]`` keep the old
    content, the others take the new), but between two rows the cut may move by any number of columns. A move
    from column ``a`` to ``b`` lays the seam along the boundary between the two rows, so it costs what the seam
    meets there: ``min(errors[r - 1, c], errors[r, c])`` for every column ``c`` strictly between ``a`` and ``b``
    (a seam between two texels is invisible where either of them agrees in both copies; a move by one column
    costs nothing extra, as in :func:`min_error_cut`). So the seam can follow a
    running bond's staggered joints (down a head joint, along the bed joint, down the next head joint), where
    :func:`min_error_cut`, one column per row at most, crosses the bricks diagonally.

    Minimized exactly by dynamic programming with running minima over the columns (prefix sums of the move
    costs), ``O(rows x cols)`` per problem; leading axes are independent problems solved at once (ties go to
    the leftmost column).

    >>> joints = np.array([[0, 9, 9, 9, 9], [0, 9, 9, 9, 9], [0, 0, 0, 0, 0], [9, 9, 9, 9, 0], [9, 9, 9, 9, 0]])
    >>> min_error_seam(joints).tolist(), min_error_cut(joints).tolist()
    ([0, 0, 0, 4, 4], [0, 0, 0, 0, 0])
    """
    errors = np.asarray(errors, dtype=np.float64)
    rows, cols = errors.shape[-2:]
    lead = errors.shape[:-2]
    inf = np.full(lead + (1,), np.inf)
    cost = np.empty_like(errors)
    cost[..., 0, :] = errors[..., 0, :]
    zero = np.zeros(lead + (1,))

    def move_costs(i):
        """``Q (..., cols + 1)``: ``Q[k]`` the cost of the row boundary above row ``i`` over columns ``< k``."""
        return np.concatenate([zero, np.cumsum(np.minimum(errors[..., i - 1, :], errors[..., i, :]), -1)], -1)

    for i in range(1, rows):
        prev = cost[..., i - 1, :]
        q = move_costs(i)
        # from a < b: prev[a] - Q[a + 1] + Q[b]; from a > b: prev[a] + Q[a] - Q[b + 1]
        from_left = np.concatenate([inf, np.minimum.accumulate(prev - q[..., 1:], -1)[..., :-1]], -1) + q[..., :-1]
        right_min = np.flip(np.minimum.accumulate(np.flip(prev + q[..., :-1], -1), -1), -1)
        from_right = np.concatenate([right_min[..., 1:], inf], -1) - q[..., 1:]
        cost[..., i, :] = errors[..., i, :] + np.minimum(prev, np.minimum(from_left, from_right))
    cut = np.empty(lead + (rows,), dtype=np.int64)
    cut[..., -1] = np.argmin(cost[..., -1, :], -1)
    columns = np.arange(cols)
    for i in range(rows - 1, 0, -1):
        b = cut[..., i][..., None]
        q = move_costs(i)
        low, high = np.minimum(columns, b), np.maximum(columns, b)
        # the move a -> b costs Q[max] - Q[min + 1] (nothing for |a - b| <= 1)
        move = np.where(high - low >= 2, np.take_along_axis(q, high, -1) - np.take_along_axis(q, low + 1, -1), 0.0)
        cut[..., i - 1] = np.argmin(cost[..., i - 1, :] + move, -1)
    return cut


def overlap_errors(exemplar_fft: tuple, target: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """SSD between ``target * mask`` and every ``block x block`` window of the exemplar.

    Parameters
    ----------
    exemplar_fft : tuple
        ``(F[E], F[sum_c E_c^2], shape)`` from :func:`_exemplar_spectra`.
    target : ``(B, B, C)``; mask : ``(B, B)`` of 0/1.

    Returns
    -------
    ``(H - B + 1, W - B + 1)``: error of the window whose top-left texel is ``(y, x)``.
    """
    spec_e, spec_e2, (h, w) = exemplar_fft
    b = target.shape[0]
    pad = np.zeros((h, w, target.shape[2]))
    pad[:b, :b] = target * mask[..., None]
    mpad = np.zeros((h, w))
    mpad[:b, :b] = mask
    # correlation via FFT: corr(E, T)[y, x] = sum_q E[y + q] T[q]
    cross = np.fft.irfft2((spec_e * np.conj(np.fft.rfft2(pad, axes=(0, 1)))).sum(-1), s=(h, w), axes=(0, 1))
    energy = np.fft.irfft2(spec_e2 * np.conj(np.fft.rfft2(mpad)), s=(h, w))
    total = float((target * target * mask[..., None]).sum())
    err = energy - 2.0 * cross + total
    return np.maximum(err[: h - b + 1, : w - b + 1], 0.0)


def _exemplar_spectra(e: np.ndarray):
    return np.fft.rfft2(e, axes=(0, 1)), np.fft.rfft2((e * e).sum(-1)), e.shape[:2]


def quilt(exemplar: np.ndarray, out_height: int, out_width: int, block: int, overlap: int,
          rng: np.random.Generator, tolerance: float = 1.1, progress: bool = False) -> np.ndarray:
    """Quilt ``exemplar (H, W, C)`` (whitened values) into an ``(out_height, out_width, C)`` plane.

    Returns the quilted plane ``(rows*(B-O)+O, cols*(B-O)+O, C)`` cropped to the
    requested size, and is deterministic given ``rng``.
    """
    h, w, c = exemplar.shape
    step = block - overlap
    rows = max(1, math.ceil((out_height - overlap) / step))
    cols = max(1, math.ceil((out_width - overlap) / step))
    out = np.zeros((rows * step + overlap, cols * step + overlap, c))
    spectra = _exemplar_spectra(exemplar)
    bar = progress_bar(total=rows * cols, desc="quilting", unit="block", disable=not progress)
    for i in range(rows):
        for j in range(cols):
            y, x = i * step, j * step
            if i == 0 and j == 0:
                sy, sx = int(rng.integers(h - block + 1)), int(rng.integers(w - block + 1))
                out[:block, :block] = exemplar[sy: sy + block, sx: sx + block]
                bar.update()
                continue
            mask = np.zeros((block, block))
            if j > 0:
                mask[:, :overlap] = 1
            if i > 0:
                mask[:overlap, :] = 1
            target = out[y: y + block, x: x + block]
            err = overlap_errors(spectra, target, mask)
            best = err.min()
            ys, xs = np.nonzero(err <= tolerance * best + 1e-12 * max(1.0, abs(best)))
            k = int(rng.integers(len(ys)))
            patch = exemplar[ys[k]: ys[k] + block, xs[k]: xs[k] + block]
            diff = ((patch - target) ** 2).sum(-1)
            take = np.ones((block, block), dtype=bool)
            if j > 0:
                cut = min_error_cut(diff[:, :overlap])
                take &= np.arange(block)[None, :] >= cut[:, None]
            if i > 0:
                cut = min_error_cut(diff[:overlap, :].T)
                take &= np.arange(block)[:, None] >= cut[None, :]
            region = out[y: y + block, x: x + block]
            region[take] = patch[take]
            bar.update()
    bar.close()
    return out[:out_height, :out_width]


@register_synthesizer("quilt")
class Quilting(Synthesizer):
    """Image quilting of an exemplar plane into a finite, stored plane (not dynamic).

    Parameters
    ----------
    exemplar : ``(H, W, C)``
    seed : int, default 0
        Seed of the random block choices (numpy Generator).
    repeats : float, default 4
        Size of the generated plane in exemplar repeats per axis (``round(repeats * H) x
        round(repeats * W)`` texels); queries wrap with this period.
    block : int, optional
        Block side in texels; default ``max(8, min(H, W) // 4)``.
    overlap : int, optional
        Overlap in texels; default ``max(2, block // 6)``.
    tolerance : float, default 1.1
        Candidates within ``tolerance x`` the minimum overlap error.
    progress : bool, default False
        Show a progress bar while quilting.
    prepared : tensor ``(H_q, W_q, C)``, optional
        A plane quilted earlier with the same parameters.
    """

    seeded_tables = True  # the quilted texture is drawn with the seed

    dynamic = False

    def __init__(self, exemplar, seed: int = 0, *, repeats: float = 4.0, block: int | None = None,
                 overlap: int | None = None, tolerance: float = 1.1, progress: bool = False,
                 prepared: torch.Tensor | None = None) -> None:
        super().__init__(exemplar, seed)
        h, w, c = self.exemplar.shape
        self.block = max(8, min(h, w) // 4) if block is None else int(block)
        self.overlap = max(2, self.block // 6) if overlap is None else int(overlap)
        if not 2 <= self.block <= min(h, w):
            raise InputError(f"block: expected 2 <= block <= min(H, W) = {min(h, w)} texels, got {self.block}")
        if not 1 <= self.overlap < self.block:
            raise InputError(f"overlap: expected 1 <= overlap < block = {self.block}, got {self.overlap}")
        if isinstance(repeats, bool) or not isinstance(repeats, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(repeats) and repeats > 0):
            raise InputError(f"repeats: expected a positive number of exemplar repeats, got {repeats!r}")
        if not tolerance >= 1.0:
            raise InputError(f"tolerance: expected >= 1, got {tolerance!r}")
        self.repeats, self.tolerance = float(repeats), float(tolerance)
        self.size = (max(self.block, round(self.repeats * h)), max(self.block, round(self.repeats * w)))
        if prepared is None:
            prepared = self._generate(progress)
        elif tuple(prepared.shape) != (*self.size, c):
            raise InputError(f"prepared: expected a quilted plane of shape {(*self.size, c)}, got {tuple(prepared.shape)}")
        self.prepared = prepared
        self._pyramid = PlanePyramid(prepared)

    def _generate(self, progress: bool) -> torch.Tensor:
        h, w, c = self.exemplar.shape
        values = self.exemplar.reshape(-1, c).to(torch.float64).cpu()
        pca = Decorrelation.fit(values)
        scale = 1.0 / torch.sqrt(pca.variances.clamp_min(1e-12 * float(pca.variances.max().clamp_min(1e-300))))
        whitened = (pca.project(values) * scale).reshape(h, w, c).numpy()
        rng = np.random.default_rng(self.seed)
        plane = quilt(whitened, self.size[0], self.size[1], self.block, self.overlap, rng, self.tolerance, progress)
        restored = pca.unproject(torch.from_numpy(plane) / scale)
        return restored.to(torch.float32).to(self.device).contiguous()

    def _positions(self, uv: torch.Tensor) -> torch.Tensor:
        """Read positions ``(N, 2)`` in fractions of the quilted plane (exact for any ``uv``)."""
        qh, qw = self.size
        whole, frac = split_uv(uv)
        h, w = self.exemplar.shape[:2]
        x = wrapped_texel_position(whole[:, 0], frac[:, 0], w, qw) / qw
        y = wrapped_texel_position(whole[:, 1], frac[:, 1], h, qh) / qh
        return torch.stack([x, y], dim=-1)

    def latent(self, uv: torch.Tensor) -> torch.Tensor:
        return fetch_wrap(self.prepared, self._positions(uv))

    def level_of_detail(self) -> LevelOfDetail:
        return self._pyramid.level_of_detail

    def filtered_latent(self, uv: torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
        return self._pyramid.fetch(self._positions(uv), footprint)

    def prepared_arrays(self) -> dict[str, torch.Tensor]:
        """The quilted plane."""
        return {"plane": self.prepared.detach().cpu().contiguous()}

    @classmethod
    def prepared_from_arrays(cls, arrays: dict[str, torch.Tensor], device: torch.device | str = "cpu") -> torch.Tensor:
        return arrays["plane"].to(device, torch.float32).contiguous()

    @classmethod
    def stored_tables(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> list[Table]:
        """The quilted plane: the exemplar's texels, ``(H_q, W_q, C)``."""
        bound = feature_bound(plane)
        return [Table("plane", torch.float32, (None, None, plane.shape[-1]), -bound, bound)]

    @classmethod
    def pyramid_size(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> tuple[int, int]:
        return int(arrays["plane"].shape[0]), int(arrays["plane"].shape[1])  # the quilted plane's pyramid

    @classmethod
    def table_relations(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> str | None:
        h, w = arrays["plane"].shape[:2]
        if max(h, w) > MAX_QUILT_SIDE:
            return f"table 'plane': {h} x {w} texels, expected at most {MAX_QUILT_SIDE} on a side"
        return None

    def storage_bytes(self) -> int:
        return self.prepared.numel() * self.prepared.element_size()

    def parameters(self) -> dict[str, Any]:
        return {"repeats": self.repeats, "block": self.block, "overlap": self.overlap, "tolerance": self.tolerance,
                "size": list(self.size)}
