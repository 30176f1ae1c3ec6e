"""Histogram transforms of histogram-preserving blending (Heitz & Neyret 2018).

* :class:`Decorrelation` -- PCA over the ``C`` channels of an exemplar: the
  synthesis runs on decorrelated coefficients, whose 1-D marginals capture more
  of the joint distribution than the raw (correlated) latent channels.
* :class:`GaussianTransform` -- per-channel forward transform ``T`` (the value of
  rank ``i`` of ``N`` maps to ``G = Phi^-1((i + 0.5) / N)``, a standard normal) and
  its exact inverse ``T^-1(G) = interp(Phi(G), (arange(N) + 0.5) / N, sorted)``
  (``np.interp`` semantics: clamped to the extreme values). Because the ``U``
  grid is uniform, the inverse is a direct index, no search.
* :class:`InverseLUT` -- the inverse tabulated on ``size`` uniformly spaced
  Gaussian values in ``[G_min, G_max]`` (the extreme ranks) with linear
  interpolation and the clamp at both ends: the fast path's inverse.
* :func:`variance_preserving_blend` -- ``G = (sum w_i G_i - mu) / sqrt(sum w_i^2) + mu``.

All tables are float64 tensors on the exemplar's device.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["Decorrelation", "GaussianTransform", "InverseLUT", "variance_preserving_blend", "blend_weights"]


@dataclass
class Decorrelation:
    """PCA of ``C`` channels: ``coefficients = (x - mean) @ basis``; ``x = coefficients @ basis.T + mean``.

    Attributes
    ----------
    mean : ``(C,)`` float64
    basis : ``(C, C)`` float64, orthonormal columns sorted by decreasing variance
        (each column's sign chosen so that its largest-magnitude entry is positive).
    variances : ``(C,)`` float64, the eigenvalues.
    """

    mean: torch.Tensor
    basis: torch.Tensor
    variances: torch.Tensor

    @classmethod
    def fit(cls, values: torch.Tensor, separate: int = 0) -> "Decorrelation":
        """Fit to ``values (N, C)``; the last ``separate`` channels stay out of the PCA.

        With ``separate = s > 0`` the PCA runs on the first ``C - s`` channels and each of the last ``s``
        is its own coefficient, only centred: ``basis`` is block-diagonal (the PCA's columns, then an
        identity block), so a coefficient of the last ``s`` depends on that channel alone and the
        channel on that coefficient alone (a relief model's height, synthesized on its own).

        >>> import torch
        >>> x = torch.randn(1000, 2, dtype=torch.float64) @ torch.tensor([[1.0, 0.9], [0.0, 0.3]], dtype=torch.float64)
        >>> pca = Decorrelation.fit(x)
        >>> c = pca.project(x)
        >>> bool(abs(torch.cov(c.T)[0, 1]) < 1e-10), bool(torch.allclose(pca.unproject(c), x))
        (True, True)
        """
        values = values.to(torch.float64)
        c = values.shape[1]
        if separate:
            if not 0 < separate < c:
                from ..errors import InputError

                raise InputError(f"separate: expected fewer than the {c} channels, got {separate}")
            head = cls.fit(values[:, : c - separate])
            basis = torch.zeros(c, c, dtype=torch.float64, device=values.device)
            basis[: c - separate, : c - separate] = head.basis
            basis[c - separate:, c - separate:] = torch.eye(separate, dtype=torch.float64, device=values.device)
            tail = values[:, c - separate:]
            variances = tail.var(0) if values.shape[0] > 1 else torch.zeros(separate, dtype=torch.float64)
            return cls(torch.cat([head.mean, tail.mean(0)]), basis, torch.cat([head.variances, variances]))
        mean = values.mean(0)
        centred = values - mean
        cov = centred.T @ centred / max(values.shape[0] - 1, 1)
        variances, basis = torch.linalg.eigh(cov)
        order = torch.argsort(variances, descending=True)
        variances, basis = variances[order].clamp_min(0.0), basis[:, order]
        signs = torch.sign(basis.gather(0, basis.abs().argmax(0, keepdim=True)))
        return cls(mean, basis * signs, variances)

    def project(self, x: torch.Tensor) -> torch.Tensor:
        """``(..., C)`` values -> ``(..., C)`` coefficients (float64)."""
        return (x.to(torch.float64) - self.mean) @ self.basis

    def unproject(self, c: torch.Tensor) -> torch.Tensor:
        """``(..., C)`` coefficients -> values, in ``c``'s dtype."""
        return c @ self.basis.T.to(c.dtype) + self.mean.to(c.dtype)


@dataclass
class GaussianTransform:
    """Per-channel rank transform to a standard normal and its exact inverse.

    Attributes
    ----------
    sorted_values : ``(C, N)`` float64, each channel's exemplar values in increasing order.
    """

    sorted_values: torch.Tensor

    @classmethod
    def fit(cls, values: torch.Tensor) -> tuple["GaussianTransform", torch.Tensor]:
        """Fit to exemplar ``values (N, C)``; also return ``T(values)`` ``(N, C)`` float64 by rank.

        Ties get distinct consecutive ranks (stable order), so ``T^-1(T(x)) == x``.
        """
        values = values.to(torch.float64)
        n = values.shape[0]
        sorted_values, order = torch.sort(values, dim=0, stable=True)
        ranks_g = torch.special.ndtri((torch.arange(n, dtype=torch.float64, device=values.device) + 0.5) / n)
        gaussian = torch.empty_like(values)
        gaussian.scatter_(0, order, ranks_g[:, None].expand_as(values).contiguous())
        return cls(sorted_values.T.contiguous()), gaussian

    @property
    def n(self) -> int:
        return int(self.sorted_values.shape[1])

    @property
    def gaussian_range(self) -> tuple[float, float]:
        """``(G_min, G_max)``: the Gaussian values of the lowest and highest rank."""
        g = float(torch.special.ndtri(torch.tensor(0.5 / self.n, dtype=torch.float64)))
        return g, -g

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``T(x)`` for arbitrary values ``x (..., C)``: piecewise-linear CDF, then ``Phi^-1`` (float64)."""
        x = x.to(torch.float64)
        flat = x.reshape(-1, x.shape[-1]).T.contiguous()  # (C, M)
        n = self.n
        hi = torch.searchsorted(self.sorted_values, flat).clamp(1, n - 1)
        lo = hi - 1
        x0, x1 = self.sorted_values.gather(1, lo), self.sorted_values.gather(1, hi)
        t = ((flat - x0) / torch.where(x1 > x0, x1 - x0, torch.ones_like(x0))).clamp(0.0, 1.0)
        u = (lo.to(torch.float64) + t + 0.5) / n
        return torch.special.ndtri(u).T.reshape(x.shape)

    def inverse(self, g: torch.Tensor) -> torch.Tensor:
        """Exact ``T^-1(g)`` for ``g (..., C)``: ``np.interp(Phi(g), (arange(N) + .5) / N, sorted)`` (float64)."""
        g = g.to(torch.float64)
        n = self.n
        flat = g.reshape(-1, g.shape[-1]).T.contiguous()  # (C, M), each channel's values together for the gathers
        pos = (torch.special.ndtr(flat) * n - 0.5).clamp(0.0, n - 1.0)
        lo = torch.floor(pos).to(torch.int64).clamp_max(n - 2) if n > 1 else torch.zeros_like(pos, dtype=torch.int64)
        t = pos - lo
        x0 = self.sorted_values.gather(1, lo)
        x1 = self.sorted_values.gather(1, (lo + 1).clamp_max(n - 1))
        return (x0 + t * (x1 - x0)).T.reshape(g.shape)

    def lut(self, size: int = 4096) -> "InverseLUT":
        """Tabulate the inverse on ``size`` uniformly spaced Gaussian values (see :class:`InverseLUT`)."""
        return InverseLUT.build(self, size)


@dataclass
class InverseLUT:
    """``T^-1`` tabulated per channel on a uniform grid over ``[g_min, g_max]``.

    Entry ``k`` of channel ``c`` is ``T^-1(g_min + k * step)``; lookups interpolate
    linearly and clamp to the first/last entry outside the range (the clamp
    matters: without it the index overflows).

    Attributes
    ----------
    table : ``(C, size)`` float64
    g_min, step : float
    """

    table: torch.Tensor
    g_min: float
    step: float

    @classmethod
    def build(cls, transform: GaussianTransform, size: int) -> "InverseLUT":
        if size < 2:
            from ..errors import InputError

            raise InputError(f"lut_size: expected at least 2 entries, got {size}")
        g_min, g_max = transform.gaussian_range
        grid = torch.linspace(g_min, g_max, size, dtype=torch.float64, device=transform.sorted_values.device)
        table = transform.inverse(grid[:, None].expand(size, transform.sorted_values.shape[0]))
        return cls(table.T.contiguous(), g_min, (g_max - g_min) / (size - 1))

    def __call__(self, g: torch.Tensor) -> torch.Tensor:
        """``T^-1(g)`` for ``g (..., C)``, in ``g``'s floating dtype."""
        size = self.table.shape[1]
        flat = g.reshape(-1, g.shape[-1]).T  # (C, M)
        pos = ((flat - self.g_min) / self.step).clamp(0.0, size - 1.0)
        lo = torch.floor(pos).to(torch.int64).clamp_max(size - 2)
        t = (pos - lo).to(g.dtype)
        table = self.table.to(g.dtype)
        x0, x1 = table.gather(1, lo), table.gather(1, lo + 1)
        return (x0 + t * (x1 - x0)).T.reshape(g.shape)


def blend_weights(barycentrics: torch.Tensor, gamma: float = 1.0) -> torch.Tensor:
    """Normalized blending weights ``w_i = b_i^gamma / sum_j b_j^gamma`` of ``(..., K)`` barycentrics.

    Computed as ``(b_i / max_j b_j)^gamma`` normalized (the same weights): the largest term is 1, so no
    exponent, however large, underflows every term to 0 (which would make the weights 0/0 = NaN).
    """
    if gamma == 1.0:
        w = barycentrics
    else:
        b = barycentrics.clamp_min(0.0)
        w = (b / b.amax(-1, keepdim=True)) ** gamma
    return w / w.sum(-1, keepdim=True)


def variance_preserving_blend(samples: torch.Tensor, weights: torch.Tensor, mean: float | torch.Tensor = 0.0
                              ) -> torch.Tensor:
    """``(sum_i w_i G_i - mu) / sqrt(sum_i w_i^2) + mu`` for ``samples (..., K, C)``, ``weights (..., K)``.

    With normalized weights and independent Gaussian samples of mean ``mu`` and
    variance ``s^2`` the result has the same mean and variance (the plain
    weighted mean has variance ``s^2 sum w_i^2``, as low as ``s^2 / 3``).

    >>> import torch
    >>> g = torch.randn(200000, 3, 1, dtype=torch.float64)
    >>> w = torch.tensor([0.2, 0.3, 0.5], dtype=torch.float64).expand(200000, 3)
    >>> round(float(variance_preserving_blend(g, w).std()), 2), round(float((g[..., 0] * w).sum(-1).std()), 2)
    (1.0, 0.62)
    """
    weights = weights.to(samples.dtype)
    blended = (weights[..., None] * samples).sum(-2)
    norm = torch.sqrt((weights * weights).sum(-1, keepdim=True))
    return (blended - mean) / norm + mean
