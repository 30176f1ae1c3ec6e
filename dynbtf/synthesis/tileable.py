"""Making an exemplar tileable before synthesis (the supplementary's "Avoiding Cuts").

Synthesis reads the exemplar with wrap addressing, so a measured (non-periodic)
patch shows its border as a straight seam inside every synthesized patch. The
fix cross-fades a band of ``b`` texels across each border, horizontally then
vertically, in Gaussian space (:class:`~dynbtf.synthesis.histogram.GaussianTransform`
per channel) with the variance-preserving correction:

    out[x] = (a G[x] + (1 - a) G[x + W - b]) / sqrt(a^2 + (1 - a)^2),  a = (x + 0.5) / b,  x < b
    out[x] = G[x]                                                           b <= x < W - b

The result is ``(H - b) x (W - b)`` and periodic: column ``W - b - 1`` is followed
(with wrap) by column 0, which is mostly ``G[W - b]``, its original neighbour.
Values are mapped back with the exact inverse transform, so the marginal
distribution is preserved up to the crop.
"""

from __future__ import annotations

import math

import torch

from ..errors import InputError
from .histogram import GaussianTransform

__all__ = ["make_tileable", "seam_discontinuity", "default_band", "DEFAULT_BAND_FRACTION"]

#: Band width as a fraction of ``min(H, W)``: the reference demo's ``0.33 * min(W, H) / 2``.
DEFAULT_BAND_FRACTION = 0.165


def default_band(height: int, width: int, fraction: float = DEFAULT_BAND_FRACTION) -> int:
    """Band width in texels for an exemplar of ``height x width`` (at least 1)."""
    return max(1, int(round(fraction * min(height, width))))


def _crossfade_columns(g: torch.Tensor, band: int) -> torch.Tensor:
    """Cross-fade the first ``band`` columns of ``g (H, W, C)`` with the columns after ``W - band``."""
    w = g.shape[1]
    a = (torch.arange(band, dtype=g.dtype, device=g.device) + 0.5) / band
    norm = torch.sqrt(a * a + (1 - a) ** 2)
    left = g[:, :band]
    right = g[:, w - band:]
    blended = (a[None, :, None] * left + (1 - a)[None, :, None] * right) / norm[None, :, None]
    return torch.cat([blended, g[:, band: w - band]], dim=1)


def make_tileable(plane: torch.Tensor, band: int | None = None) -> torch.Tensor:
    """A periodic ``(H - band, W - band, C)`` version of ``plane (H, W, C)``.

    Parameters
    ----------
    plane : tensor ``(H, W, C)``
        The exemplar (e.g. a positional feature plane), any float dtype.
    band : int, optional
        Cross-fade width in texels; default :func:`default_band`. Must satisfy
        ``1 <= band <= min(H, W) / 3``.

    Returns
    -------
    tensor ``(H - band, W - band, C)`` in ``plane``'s dtype.
    """
    h, w, c = plane.shape
    band = default_band(h, w) if band is None else int(band)
    if band < 1 or 3 * band > min(h, w):
        raise InputError(f"tileable band: expected 1 <= band <= min(H, W) / 3 = {min(h, w) // 3} texels "
                         f"for a {h}x{w} exemplar, got {band}")
    transform, gaussian = GaussianTransform.fit(plane.reshape(-1, c))
    g = gaussian.reshape(h, w, c)
    g = _crossfade_columns(g, band)
    g = _crossfade_columns(g.transpose(0, 1), band).transpose(0, 1)
    return transform.inverse(g).to(plane.dtype).contiguous()


def seam_discontinuity(plane: torch.Tensor) -> float:
    """How visible the wrap-around seams of ``plane (H, W, C)`` are.

    Mean squared difference between the texels facing each other across the
    wrap (last column vs first, last row vs first), divided by the mean squared
    difference between interior neighbours. About 1 for a periodic plane of
    stationary content; well above 1 when the borders do not match.

    >>> import torch, torch.nn.functional as F
    >>> noise = torch.randn(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))
    >>> smooth = F.avg_pool2d(F.pad(noise, (4, 4, 4, 4), mode="circular"), 9, 1)[0].permute(1, 2, 0)
    >>> round(seam_discontinuity(smooth), 1), round(seam_discontinuity(smooth[:48, :48]), 1)  # periodic, cropped
    (1.5, 10.4)
    """
    p = plane.to(torch.float64)
    seam = torch.cat([((p[:, 0] - p[:, -1]) ** 2).reshape(-1), ((p[0] - p[-1]) ** 2).reshape(-1)]).mean()
    inner = torch.cat([((p[:, 1:] - p[:, :-1]) ** 2).reshape(-1), ((p[1:] - p[:-1]) ** 2).reshape(-1)]).mean()
    return float(seam / inner.clamp_min(1e-300)) if math.isfinite(float(inner)) else float("nan")
