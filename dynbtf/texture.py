"""Bilinear fetches from feature planes: the one texture-sampling primitive.

Planes are torch tensors ``(H, W, C)`` (channels last, like images). Two
addressing modes exist:

* :func:`fetch_wrap` -- positional planes: ``uv`` in units of one plane repeat,
  wrapped (periodic) in both axes, texel ``[i, j]`` centred at
  ``((j + 0.5) / W, (i + 0.5) / H)``. ``uv`` may be float64 and arbitrarily
  large: the integer part is removed in the input's precision before the
  (float32) interpolation, so ``uv = 1e6 + x`` fetches the same value as ``x``
  (exactly, when ``x`` is representable).
* :func:`fetch_angular` -- angular planes indexed by
  :func:`dynbtf.conventions.angular_plane_coords` ``(s, t)``: rows follow
  ``s`` (theta, clamped at the edges), columns follow ``t`` (phi, wrapped).

Both are differentiable with respect to the plane (training) and run on any
device (implemented with ``torch.nn.functional.grid_sample`` on a padded plane).

A fetch whose coordinates repeat (training reads the angular planes at the BTF's fixed
(view, light) pairs, step after step) can be split in two: :func:`angular_taps` computes
once where and with which weights it reads (four texels per point), and
:func:`fetch_taps` reads them: a gather and a weighted sum, whose backward is a
scatter-add, cheaper than a fresh ``grid_sample`` for a few thousand points.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["fetch_wrap", "fetch_wrap_stack", "fetch_angular", "wrap_uv", "angular_taps", "fetch_taps"]


def wrap_uv(uv: torch.Tensor) -> torch.Tensor:
    """``uv - floor(uv)`` computed in ``uv``'s own dtype: the fraction in ``[0, 1)``."""
    frac = uv - torch.floor(uv)
    # float rounding can give exactly 1.0 for tiny negative inputs
    return torch.where(frac >= 1.0, frac - 1.0, frac)


def _grid_sample_hwc(padded: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Sample ``B`` padded planes ``(B, C, Hp, Wp)`` at padded-texel coordinates ``x, y (B, N)`` -> ``(B, N, C)``."""
    hp, wp = padded.shape[-2:]
    grid = torch.stack([x * (2.0 / (wp - 1)) - 1.0, y * (2.0 / (hp - 1)) - 1.0], dim=-1).to(padded.dtype)[:, None]
    out = F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[:, :, 0, :].transpose(1, 2)


def fetch_wrap(plane: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear, periodic fetch of ``plane`` ``(H, W, C)`` at ``uv`` ``(..., 2)`` -> ``(..., C)``.

    Examples
    --------
    >>> import torch
    >>> plane = torch.arange(4.0).view(2, 2, 1)          # [[0, 1], [2, 3]]
    >>> fetch_wrap(plane, torch.tensor([[0.25, 0.25], [0.5, 0.25], [1e6 + 0.25, 0.75]], dtype=torch.float64))
    tensor([[0.0000],
            [0.5000],
            [2.0000]])
    """
    batch = uv.shape[:-1]
    return fetch_wrap_stack(plane[None], uv.reshape(1, -1, 2))[0].reshape(*batch, plane.shape[-1])


def fetch_wrap_stack(planes: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """:func:`fetch_wrap` of ``B`` planes ``(B, H, W, C)`` at their own points ``uv (B, N, 2)`` -> ``(B, N, C)``.

    One ``grid_sample`` call for the whole stack (e.g. all views' images of a BTF).

    Examples
    --------
    >>> import torch
    >>> planes = torch.arange(8.0).view(2, 2, 2, 1)       # [[0, 1], [2, 3]] and [[4, 5], [6, 7]]
    >>> fetch_wrap_stack(planes, torch.tensor([[[0.5, 0.25]], [[0.25, 0.5]]]))
    tensor([[[0.5000]],
    <BLANKLINE>
            [[5.0000]]])
    """
    b, h, w, c = planes.shape
    frac = wrap_uv(uv)
    x = (frac[..., 0] * w + 0.5).to(planes.dtype)  # padded coordinate: texel j centre at j + 1
    y = (frac[..., 1] * h + 0.5).to(planes.dtype)
    padded = F.pad(planes.permute(0, 3, 1, 2), (1, 1, 1, 1), mode="circular")  # (B, C, H + 2, W + 2)
    return _grid_sample_hwc(padded, x, y)


def fetch_angular(plane: torch.Tensor, st: torch.Tensor) -> torch.Tensor:
    """Bilinear fetch of an angular plane ``(R_s, R_t, C)`` at ``st`` ``(..., 2)`` -> ``(..., C)``.

    ``s`` (rows, theta) clamps to the edge texels; ``t`` (columns, phi) wraps.
    """
    rs, rt, c = plane.shape
    batch = st.shape[:-1]
    st = st.reshape(-1, 2)
    s = st[:, 0].clamp(0.0, 1.0)
    t = wrap_uv(st[:, 1])
    y = (s * rs + 0.5).to(plane.dtype)  # rows padded by one replicated texel each side
    x = (t * rt + 0.5).to(plane.dtype)
    chw = plane.permute(2, 0, 1)[None]
    padded = F.pad(chw, (1, 1, 0, 0), mode="circular")
    padded = F.pad(padded, (0, 0, 1, 1), mode="replicate")[0]
    return _grid_sample_hwc(padded[None], x[None], y[None])[0].reshape(*batch, c)


def angular_taps(st: torch.Tensor, rows: int, columns: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Where :func:`fetch_angular` reads a ``rows x columns`` plane at ``st`` ``(..., 2)``: the four texels
    (flat indices ``row * columns + column``, int64 ``(..., 4)``) and their bilinear weights (``(..., 4)``,
    ``st``'s dtype, summing to 1), with the same addressing (rows clamp to the edge texels, columns wrap).

    ``fetch_taps(plane.reshape(-1, C), *angular_taps(st, R_s, R_t))`` equals ``fetch_angular(plane, st)``
    to float rounding.

    >>> index, weight = angular_taps(torch.tensor([[0.0, 0.0]]), 20, 20)  # theta 0, phi 0: a corner
    >>> index.tolist(), weight.tolist()
    ([[19, 0, 19, 0]], [[0.25, 0.25, 0.25, 0.25]])
    """
    s = st[..., 0].clamp(0.0, 1.0) * rows - 0.5      # continuous row: texel k is centred at k + 0.5
    t = wrap_uv(st[..., 1]) * columns - 0.5
    r0, c0 = torch.floor(s), torch.floor(t)
    fr, fc = s - r0, t - c0
    r0, c0 = r0.long(), c0.long()
    top, bottom = r0.clamp(0, rows - 1) * columns, (r0 + 1).clamp(0, rows - 1) * columns
    left, right = c0 % columns, (c0 + 1) % columns
    index = torch.stack([top + left, top + right, bottom + left, bottom + right], dim=-1)
    weight = torch.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc], dim=-1)
    return index, weight


class _FetchTaps(torch.autograd.Function):
    """:func:`fetch_taps` with its backward written as one ``index_add_`` (advanced indexing's backward is a slower
    ``index_put_`` with accumulation)."""

    @staticmethod
    def forward(ctx, flat_plane, index, weight):
        rows = flat_plane.index_select(0, index.reshape(-1)).view(*index.shape, flat_plane.shape[-1])
        ctx.save_for_backward(index, weight)
        ctx.texels = flat_plane.shape[0]
        return (rows * weight[..., None]).sum(-2)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        index, weight = ctx.saved_tensors
        rows = (grad[..., None, :] * weight[..., None]).reshape(-1, grad.shape[-1])
        flat = grad.new_zeros(ctx.texels, grad.shape[-1]).index_add_(0, index.reshape(-1), rows)
        return flat, None, None


def fetch_taps(flat_plane: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``sum_k weight[..., k] * flat_plane[index[..., k]]``: ``(T, C)`` texels, ``(..., K)`` taps -> ``(..., C)``.

    Differentiable with respect to ``flat_plane`` (its gradient is a scatter-add).
    """
    return _FetchTaps.apply(flat_plane, index, weight.to(flat_plane.dtype))
