"""The positional features at a texel's visible point, following a learned height (training's fetch).

Training a :class:`~dynbtf.representations.parallax.ParallaxTriplePlane` reads, every step, the positional
plane at the points where the step's texel centres are seen. Those points come from a table of marched hits
(``p``, at height ``z``, where ``h(p) = z`` when it was marched); between two marches the height learns, and
one Newton step of ``h(p + dz s) = z + dz`` follows it:

    denominator = max(1 - (h(p + eps s) - h(p - eps s)) / (2 eps), 0.25)      (held constant)
    dz = (h(p) - z) / denominator
    q = p + dz s
    features = fetch_wrap(concat(f_U, height_channel), q)                     (C_U + 1 channels)

with ``h = height_scale * height_channel`` fetched bilinearly and periodically
(:func:`~dynbtf.texture.fetch_wrap`), ``s`` the view's :func:`~dynbtf.representations.parallax.view_offsets`
and ``eps`` half a texel of the longer side. Gradients reach ``f_U`` and the height channel through the fetch,
and the height channel also through ``dz`` (the implicit-function gradient of the visible point: the
denominator is not differentiated).

:func:`fetch_visible` computes it two ways:

* **torch operations** (``grid_sample`` and autograd): the definition, on any device and dtype.
* **compiled loops** (numba) for float32 CPU tensors: one loop over the points forward and one backward, in
  place of some forty small torch operations and their autograd nodes (faster per training step:
  ``benchmarks/bench_parallax_training.py`` measures both forms).

The compiled loops compute the definition directly -- a periodic bilinear fetch in texel coordinates, its
coordinate gradient in closed form, the gradients added point by point -- not ``grid_sample``'s padded
coordinate chain; so the two forms agree to float32 rounding, not bit for bit. A fit is chaotic, so the
two forms' trajectories part as two seeds' do: ``benchmarks/bench_parallax_training.py --quality`` fits
with each over three seeds and compares their held-out PSNR. ``tests/test_visible_fetch.py`` checks the
features and both gradients against the torch form, against float64 and against a closed form.

Conventions: uv units (one plane repeat = 1) for ``points`` and ``z``; ``slope`` in uv per unit of height
(``v`` scaled by the plane's aspect, as :func:`~dynbtf.representations.parallax.view_offsets` does).
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from ..texture import fetch_wrap

__all__ = ["fetch_visible"]


def fetch_visible(f_u: torch.Tensor, height_channel: torch.Tensor, points: torch.Tensor, z: torch.Tensor,
                  slope: torch.Tensor, height_scale: float, *, compiled: bool | None = None) -> torch.Tensor:
    """``concat(f_U, height_channel)`` at the visible points after the Newton step (module docstring).

    Parameters
    ----------
    f_u : ``(H, W, C)``
        Positional features.
    height_channel : ``(H, W)``
        The height in channel units (uv units / ``height_scale``).
    points : ``(N, 2)``
        Table hits ``p`` (uv units, any real values), in ``f_u``'s dtype.
    z : ``(N,)``
        Their heights when marched (uv units).
    slope : ``(N, 2)``
        Each point's view offset (uv per unit of height).
    height_scale : float
        uv units per channel unit.
    compiled : bool, optional
        Run the compiled loops (default: when every tensor is a float32 CPU tensor) or the torch operations.

    Returns
    -------
    ``(N, C + 1)`` in ``f_u``'s dtype, differentiable in ``f_u`` and ``height_channel``.

    Examples
    --------
    A flat height: the Newton step does not move the point, and the last channel is the height.

    >>> import torch
    >>> f_u, height = torch.arange(8.0).view(2, 2, 2), torch.full((2, 2), 0.5)
    >>> p = torch.tensor([[0.25, 0.25]])
    >>> fetch_visible(f_u, height, p, torch.tensor([0.01]), torch.tensor([[1.0, 0.0]]), 0.02)
    tensor([[0.0000, 1.0000, 0.5000]])
    """
    if compiled is None:
        compiled = all(t.device.type == "cpu" and t.dtype == torch.float32
                       for t in (f_u, height_channel, points, z, slope))
    if compiled:
        return _CompiledFetch.apply(f_u, height_channel, points, z, slope, float(height_scale))
    return _fetch_visible_torch(f_u, height_channel, points, z, slope, height_scale)


def _half_texel(rows: int, cols: int) -> float:
    """``eps`` of the Newton step's slope estimate: half a texel of the longer side, uv units."""
    return 0.5 / max(rows, cols)


def _fetch_visible_torch(f_u, height_channel, points, z, slope, height_scale):
    """The definition in torch operations (module docstring); autograd gives its gradients."""
    height = (height_channel * height_scale)[..., None]
    eps = _half_texel(*height_channel.shape)
    with torch.no_grad():
        along = fetch_wrap(height, torch.cat([points + eps * slope, points - eps * slope]))[:, 0]
        along = along[: len(points)] - along[len(points):]
        denominator = (1.0 - along / (2 * eps)).clamp_min(0.25)
    dz = (fetch_wrap(height, points)[:, 0] - z) / denominator
    points = points + dz[:, None] * slope
    return fetch_wrap(torch.cat([f_u, height_channel[..., None].to(f_u.dtype)], dim=-1), points)


class _CompiledFetch(torch.autograd.Function):
    """The compiled loops as an autograd function (float32 CPU tensors)."""

    @staticmethod
    def forward(ctx, f_u, height_channel, points, z, slope, height_scale):
        rows, cols, channels = f_u.shape
        plane = np.empty((rows * cols, channels + 1), dtype=np.float32)  # a texel's channels, the height last
        plane[:, :channels] = f_u.detach().reshape(rows * cols, channels).numpy()
        plane[:, channels] = height_channel.detach().reshape(-1).numpy()
        points_np, slope_np = _contiguous(points), _contiguous(slope)
        n = len(points_np)
        out = np.empty((n, channels + 1), dtype=np.float32)
        footprints = (np.empty((n, 8), dtype=np.int64), np.empty((n, 4), dtype=np.float32),
                      np.empty((n, 2), dtype=np.float32), np.empty(n, dtype=np.float32))
        _forward(plane, rows, cols, points_np, _contiguous(z), slope_np, np.float32(_half_texel(rows, cols)),
                 np.float32(height_scale), out, *footprints)
        ctx.shape = (rows, cols, channels)
        ctx.arrays = (plane, slope_np, footprints, np.float32(height_scale))
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        plane, slope, footprints, height_scale = ctx.arrays
        rows, cols, channels = ctx.shape
        grad_plane = np.zeros((rows * cols, channels + 1), dtype=np.float32)
        grad_along_height = np.zeros(rows * cols, dtype=np.float32)
        _backward(plane, rows, cols, slope, *footprints, height_scale, _contiguous(grad_out), grad_plane,
                  grad_along_height)
        grad_f_u = torch.from_numpy(grad_plane[:, :channels].reshape(rows, cols, channels).copy())
        grad_height = torch.from_numpy((grad_plane[:, channels] + grad_along_height).reshape(rows, cols))
        return grad_f_u, grad_height, None, None, None, None


def _contiguous(tensor: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().numpy(), dtype=np.float32)


# ---------------------------------------------------------------------------- compiled loops
_ONE, _HALF = np.float32(1.0), np.float32(0.5)


@numba.njit(inline="always")
def _axis(p, count):
    """One axis of the periodic bilinear fetch at ``p`` (float32, uv units; texel ``j``'s centre at
    ``(j + 0.5) / count``): the texels left and right of the point (wrapped) and the fraction past the left."""
    wrapped = p - np.floor(p)
    if wrapped >= _ONE:  # a tiny negative p rounds to 1
        wrapped = wrapped - _ONE
    x = wrapped * np.float32(count) - _HALF  # texels, in [-0.5, count - 0.5)
    left = np.floor(x)
    low = int(left)
    high = low + 1
    if low < 0:
        low += count
    if high == count:
        high = 0
    return low, high, x - left


@numba.njit(inline="always")
def _footprint(rows, cols, x, y):
    """The bilinear footprint at uv ``(x, y)``: the four texels' flat indices (north-west, north-east,
    south-west, south-east) and the fractions ``tx, ty``."""
    j0, j1, tx = _axis(x, cols)
    i0, i1, ty = _axis(y, rows)
    return (i0 * cols + j0, i0 * cols + j1, i1 * cols + j0, i1 * cols + j1), tx, ty


@numba.njit(inline="always")
def _weights(tx, ty):
    return (_ONE - tx) * (_ONE - ty), tx * (_ONE - ty), (_ONE - tx) * ty, tx * ty


@numba.njit(inline="always")
def _interpolate(plane, texels, weights, channel):
    return (weights[0] * plane[texels[0], channel] + weights[1] * plane[texels[1], channel]
            + weights[2] * plane[texels[2], channel] + weights[3] * plane[texels[3], channel])


@numba.njit(inline="always")
def _height(plane, rows, cols, x, y, channel, height_scale):
    texels, tx, ty = _footprint(rows, cols, x, y)
    return _interpolate(plane, texels, _weights(tx, ty), channel) * height_scale


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _forward(plane, rows, cols, points, z, slope, eps, height_scale, out, texels, p_weights, q_fractions,
             denominator):  # pragma: no cover - compiled
    """The features ``out (N, C)`` at the points after the Newton step, from ``plane (rows * cols, C)`` float32
    (the height channel last). Writes for the backward each point's footprints: ``texels (N, 8)`` the fetch's at
    ``q`` then the height's at ``p``, ``p_weights (N, 4)``, ``q_fractions (N, 2)`` (``tx, ty``) and the Newton
    step's ``denominator (N,)``."""
    last = plane.shape[1] - 1
    for n in range(points.shape[0]):
        px, py, sx, sy = points[n, 0], points[n, 1], slope[n, 0], slope[n, 1]
        ex, ey = sx * eps, sy * eps
        along = (_height(plane, rows, cols, px + ex, py + ey, last, height_scale)
                 - _height(plane, rows, cols, px - ex, py - ey, last, height_scale))
        d = max(_ONE - along / (eps + eps), np.float32(0.25))
        at_p, tx, ty = _footprint(rows, cols, px, py)
        weights_p = _weights(tx, ty)
        dz = (_interpolate(plane, at_p, weights_p, last) * height_scale - z[n]) / d
        at_q, tx, ty = _footprint(rows, cols, px + dz * sx, py + dz * sy)
        weights_q = _weights(tx, ty)
        for k in range(last + 1):
            out[n, k] = _interpolate(plane, at_q, weights_q, k)
        for c in range(4):
            texels[n, c], texels[n, 4 + c], p_weights[n, c] = at_q[c], at_p[c], weights_p[c]
        q_fractions[n, 0], q_fractions[n, 1] = tx, ty
        denominator[n] = d


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _backward(plane, rows, cols, slope, texels, p_weights, q_fractions, denominator, height_scale, grad_out,
              grad_plane, grad_along_height):  # pragma: no cover - compiled
    """The gradients of ``sum(grad_out * out)``: into ``grad_plane (rows * cols, C)`` through the fetch at ``q``
    and into ``grad_along_height (rows * cols,)`` (channel units) through ``dz``, from :func:`_forward`'s
    footprints. ``q = p + dz s`` with ``dz = (h(p) - z) / denominator`` (the denominator held constant)."""
    channels = plane.shape[1]
    for n in range(slope.shape[0]):
        tx, ty = q_fractions[n, 0], q_fractions[n, 1]
        weights = _weights(tx, ty)
        nw_, ne_, sw_, se_ = texels[n, 0], texels[n, 1], texels[n, 2], texels[n, 3]
        gx = np.float32(0.0)  # d loss / d (q in texels)
        gy = np.float32(0.0)
        for k in range(channels):
            g = grad_out[n, k]
            grad_plane[nw_, k] += weights[0] * g
            grad_plane[ne_, k] += weights[1] * g
            grad_plane[sw_, k] += weights[2] * g
            grad_plane[se_, k] += weights[3] * g
            nw, ne, sw, se = plane[nw_, k], plane[ne_, k], plane[sw_, k], plane[se_, k]
            gx += g * ((ne - nw) * (_ONE - ty) + (se - sw) * ty)
            gy += g * ((sw - nw) * (_ONE - tx) + (se - ne) * tx)
        grad_dz = gx * np.float32(cols) * slope[n, 0] + gy * np.float32(rows) * slope[n, 1]  # texels per uv
        grad_h = grad_dz / denominator[n] * height_scale  # d loss / d height channel at p
        for c in range(4):
            grad_along_height[texels[n, 4 + c]] += p_weights[n, c] * grad_h
