"""The positional features at a texel's visible point, following a learned height (training's fetch).

Training a :class:`~dynbtf.representations.parallax.ParallaxTriplePlane` reads, every step, the positional
plane at the points where the step's texel centres are seen. Those points come from a cache of marched hits
(``p``, at height ``z``, where ``h(p) = z`` when it was marched); between two marches the height learns, and
one Newton step of ``h(p + dz s) = z + dz`` follows it:

    denominator = max(1 - (h(p + eps s) - h(p - eps s)) / (2 eps), 0.25)      (held constant)
    dz = (h(p) - z) / denominator
    q = p + dz s
    features = fetch_wrap(concat(f_U, height_channel), q)                     (C_U + 1 channels)

with ``h = height_scale * height_channel`` fetched bilinearly and periodically, ``s`` the view's
:func:`~dynbtf.representations.parallax.view_offsets` and ``eps`` half a texel. Gradients reach ``f_U`` and the
height channel through the fetch, and the height channel also through ``dz`` (the implicit-function gradient of
the visible point: the denominator is not differentiated).

:func:`fetch_visible` computes it two ways that agree to float32 rounding (``tests/test_visible_fetch.py``):

* **torch ops** (``grid_sample``, autograd): the definition; any device and dtype.
* **a compiled kernel** (numba, :mod:`~dynbtf.representations.parallax_kernels`) for float32 CPU tensors: one loop over the points forward and one backward that
  scatters the gradients straight into the plane's gradient. Same values, a fraction of the time: a training step
  at 64 x 64 texels spent ~3 ms in the torch version's dozens of small operations (padding, two ``grid_sample``
  calls and their backward, a concatenation and its backward); ``benchmarks/bench_training.py`` measures the kernel.

Conventions: uv units (one plane repeat = 1) for ``points`` and ``z``; ``slope`` in uv per unit of height
(``v`` scaled by the plane's aspect, as :func:`~dynbtf.representations.parallax.view_offsets` does).
"""

from __future__ import annotations

import numpy as np
import torch

from ..texture import fetch_wrap
from .parallax_kernels import visible_fetch_backward, visible_fetch_forward

__all__ = ["fetch_visible"]


def fetch_visible(f_u: torch.Tensor, height_channel: torch.Tensor, points: torch.Tensor, z: torch.Tensor,
                  slope: torch.Tensor, height_scale: float, *, newton: bool, kernel: bool | None = None) -> torch.Tensor:
    """``concat(f_U, height_channel)`` at the visible points, after the Newton step when ``newton``.

    Parameters
    ----------
    f_u : ``(H, W, C)``
        Positional features.
    height_channel : ``(H, W)``
        The height in channel units (uv units / ``height_scale``).
    points : ``(N, 2)``
        Cached hits (uv units, any real values).
    z : ``(N,)``
        Their heights when marched (uv units).
    slope : ``(N, 2)``
        Each point's view offset (uv per unit of height).
    height_scale : float
        uv units per channel unit.
    newton : bool
        Follow the height by the Newton step (training with a learned height); without it the plane is
        fetched at ``points`` (``z`` and ``slope`` unused).
    kernel : bool, optional
        Use the compiled kernel (default: for float32 CPU tensors) or the torch ops.

    Returns
    -------
    ``(N, C + 1)`` in ``f_u``'s dtype, differentiable in ``f_u`` and ``height_channel``.

    Examples
    --------
    A flat height: the Newton step does not move the point, the last channel is the height.

    >>> import torch
    >>> f_u, height = torch.arange(8.0).view(2, 2, 2), torch.full((2, 2), 0.5)
    >>> p = torch.tensor([[0.25, 0.25]])
    >>> fetch_visible(f_u, height, p, torch.tensor([0.01]), torch.tensor([[1.0, 0.0]]), 0.02, newton=True)
    tensor([[0.0000, 1.0000, 0.5000]])
    """
    if kernel is None:
        kernel = (f_u.device.type == "cpu" and f_u.dtype == torch.float32 and height_channel.dtype == torch.float32
                  and points.device.type == "cpu")
    if kernel:
        return _VisibleFetch.apply(f_u, height_channel, points, z, slope, float(height_scale), bool(newton))
    return _fetch_visible_torch(f_u, height_channel, points, z, slope, height_scale, newton)


def _half_texel(height_channel: torch.Tensor) -> float:
    """``eps`` of the Newton step's slope estimate: half a texel of the longer side, uv units."""
    return 0.5 / max(height_channel.shape)


def _fetch_visible_torch(f_u, height_channel, points, z, slope, height_scale, newton):
    """The definition in torch ops (module docstring); autograd gives its gradients."""
    if newton:
        height = (height_channel * height_scale)[..., None]
        eps = _half_texel(height_channel)
        with torch.no_grad():
            along = fetch_wrap(height, torch.cat([points + eps * slope, points - eps * slope]))[:, 0]
            along = along[: len(points)] - along[len(points):]
            denominator = (1.0 - along / (2 * eps)).clamp_min(0.25)
        dz = (fetch_wrap(height, points)[:, 0] - z) / denominator
        points = points + dz[:, None] * slope
    return fetch_wrap(torch.cat([f_u, height_channel[..., None].to(f_u.dtype)], dim=-1), points)


class _VisibleFetch(torch.autograd.Function):
    """The compiled kernel as an autograd function (float32 CPU)."""

    @staticmethod
    def forward(ctx, f_u, height_channel, points, z, slope, height_scale, newton):
        rows, cols, channels = f_u.shape
        height_np = _numpy(height_channel)
        # one (texels, C + 1) table: a texel's channels are contiguous, fetched and scattered in one loop
        plane = np.concatenate([_numpy(f_u).reshape(rows * cols, channels), height_np.reshape(-1, 1)], axis=1)
        points_np, slope_np = _numpy(points, np.float64), _numpy(slope, np.float64)
        z_np = _numpy(z, np.float64) if newton else np.zeros(len(points_np))
        n = points_np.shape[0]
        out = np.empty((n, channels + 1), dtype=np.float32)
        hits = np.empty((n, 2), dtype=np.float64)  # q: where the features were fetched
        gain = np.empty(n, dtype=np.float64)  # d q / d h(p) along the slope: height_scale / denominator
        visible_fetch_forward(plane, height_np, points_np, z_np, slope_np, height_scale, _half_texel(height_channel),
                        newton, out, hits, gain)
        ctx.newton, ctx.shape = newton, (rows, cols, channels)
        ctx.plane, ctx.points, ctx.slope, ctx.hits, ctx.gain = plane, points_np, slope_np, hits, gain
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        rows, cols, channels = ctx.shape
        grad = np.zeros_like(ctx.plane)
        visible_fetch_backward(ctx.plane, rows, cols, ctx.points, ctx.slope, ctx.hits, ctx.gain, ctx.newton,
                         _numpy(grad_out), grad)
        grad = torch.from_numpy(grad)
        return (grad[:, :channels].reshape(rows, cols, channels) if ctx.needs_input_grad[0] else None,
                grad[:, channels].reshape(rows, cols) if ctx.needs_input_grad[1] else None,
                None, None, None, None, None)


def _numpy(tensor: torch.Tensor, dtype=np.float32) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=dtype)
