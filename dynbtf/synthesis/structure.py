"""How structured an exemplar is: its translational lattice from autocorrelation peaks.

A stochastic exemplar (leather, stone) is correlated with a shifted copy of itself only
over short distances: away from zero lag its autocorrelation is small everywhere. A
structured one (a weave, tiles, bricks, parquet) repeats an element: its autocorrelation
has strong secondary peaks at the element lattice's vectors. :func:`analyze_structure`
finds those peaks and condenses them into one number, the **structure strength**: the
normalized autocorrelation at the strongest peak away from zero lag (0: no shifted copy
of the exemplar resembles it; 1: it is exactly periodic with that shift).

The autocorrelation is that of the standardized channels (each channel minus its mean,
divided by its standard deviation), summed over channels, periodic (the exemplar is read
with wrap addressing everywhere), computed with one FFT per channel and normalized to 1
at zero lag. A peak is a lag whose value is at least that of its 8 neighbours (wrapped).

Lags are whole texels ``(dx, dy)``: ``dx`` along ``u`` (columns), ``dy`` along ``v`` (rows),
each in ``[0, W)`` and ``[0, H)`` (a lag and its negative are the same peak of a real
signal's autocorrelation; both are listed).

Examples
--------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> element = rng.normal(size=(8, 8, 3))
>>> weave = np.tile(element, (4, 4, 1)) + 0.1 * rng.normal(size=(32, 32, 3))
>>> a = analyze_structure(weave)
>>> a.strength > 0.9, a.peaks[0][:2] in [(8, 0), (0, 8), (24, 0), (0, 24)]
(True, True)
>>> analyze_structure(rng.normal(size=(32, 32, 3))).strength < 0.3
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError

__all__ = ["StructureAnalysis", "analyze_structure", "autocorrelation", "STRUCTURE_THRESHOLD"]

#: ``--method auto`` treats exemplars whose structure strength is at least this as structured
#: (the measured strengths of the simulated materials' fitted planes are in docs/synthesis.md).
STRUCTURE_THRESHOLD = 0.5


def autocorrelation(plane) -> np.ndarray:
    """Periodic autocorrelation ``(H, W)`` float64 of the standardized channels of ``plane (H, W, C)``, 1 at lag 0.

    Entry ``[dy, dx]`` is ``mean_p sum_c z_c(p) z_c(p + (dx, dy)) / C`` (wrapped), ``z_c`` the
    standardized channel ``c``. Constant channels contribute nothing; an all-constant plane
    gives 1 everywhere (every shift is an exact copy).
    """
    x = plane.detach().cpu().numpy() if isinstance(plane, torch.Tensor) else np.asarray(plane)
    if x.ndim != 3:
        raise InputError(f"exemplar: expected a plane of shape (H, W, C), got shape {x.shape}")
    x = x.astype(np.float64)
    x = x - x.mean((0, 1))
    std = x.std((0, 1))
    live = std > 1e-12 * max(1.0, float(np.abs(x).max()))
    if not live.any():
        return np.ones(x.shape[:2])
    z = x[..., live] / std[live]
    power = (np.abs(np.fft.rfft2(z, axes=(0, 1))) ** 2).sum(-1)
    corr = np.fft.irfft2(power, s=z.shape[:2])
    return corr / corr[0, 0]


@dataclass
class StructureAnalysis:
    """The autocorrelation peaks of an exemplar.

    Attributes
    ----------
    peaks : list of (dx, dy, value)
        Local maxima of the autocorrelation other than lag ``(0, 0)``, strongest first;
        ``dx in [0, W)`` texels along ``u``, ``dy in [0, H)`` along ``v``, ``value`` in ``[-1, 1]``.
    strength : float
        The strongest peak's value (0 if there is none): how structured the exemplar is.
    size : (H, W)
        The exemplar's size in texels.
    """

    peaks: list[tuple[int, int, float]]
    strength: float
    size: tuple[int, int]

    @property
    def structured(self) -> bool:
        """Whether ``strength >=`` :data:`STRUCTURE_THRESHOLD`."""
        return self.strength >= STRUCTURE_THRESHOLD

    def shortest_period(self) -> float:
        """Length in texels of the shortest lag among the peaks within 10% of the strongest (inf if none)."""
        h, w = self.size
        best = [(dx, dy) for dx, dy, value in self.peaks if value >= 0.9 * self.strength]
        if not best:
            return float("inf")
        return float(min(np.hypot(min(dx, w - dx), min(dy, h - dy)) for dx, dy in best))

    def describe(self) -> str:
        """One line: the strength and the strongest peak's lag."""
        if not self.peaks:
            return "structure strength 0.00 (no autocorrelation peak)"
        dx, dy, _ = self.peaks[0]
        h, w = self.size
        sx, sy = (dx if dx <= w // 2 else dx - w), (dy if dy <= h // 2 else dy - h)
        return f"structure strength {self.strength:.2f} (autocorrelation peak at lag ({sx}, {sy}) texels)"


def analyze_structure(plane) -> StructureAnalysis:
    """Autocorrelation peaks and structure strength of ``plane (H, W, C)`` (array or tensor).

    See the module docstring.
    """
    corr = autocorrelation(plane)
    h, w = corr.shape
    neighbours = np.stack([np.roll(corr, (i, j), axis=(0, 1)) for i in (-1, 0, 1) for j in (-1, 0, 1)
                           if (i, j) != (0, 0)])
    is_peak = corr >= neighbours.max(0)
    is_peak[0, 0] = False
    rows, cols = np.nonzero(is_peak)
    values = corr[rows, cols]
    order = np.lexsort((cols, rows, -values))  # strongest first; ties by position (deterministic)
    peaks = [(int(cols[i]), int(rows[i]), float(values[i])) for i in order]
    strength = max(0.0, peaks[0][2]) if peaks else 0.0
    return StructureAnalysis(peaks=peaks, strength=strength, size=(h, w))
