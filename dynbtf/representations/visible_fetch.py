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

The compiled loops do **torch's float32 arithmetic operation for operation**, so that a fit takes the same
trajectory whichever form runs (a fit is chaotic: loops that summed in another order led the default 64 x 64
fit 0.26 dB lower). That means reproducing what the torch form computes, not just what it means:

* the coordinate chain of :func:`~dynbtf.texture.fetch_wrap` (wrap, scale to padded texels, normalize to
  ``[-1, 1]``) and ``grid_sample``'s un-normalization, each rounded to float32 where torch rounds it;
* ``grid_sample``'s CPU kernel: its bilinear sum is a chain of fused multiply-adds
  ``fma(se_v, se, fma(sw_v, sw, fma(ne_v, ne, nw_v * nw)))`` (the compiler contracts the kernel's expression),
  its coordinate gradient likewise, and its backward adds into the plane's gradient vector by vector of
  :data:`TORCH_GRID_SAMPLE_LANES` points, corner by corner within a vector;
* the gradient of the circular padding: the wrapped rows are added before the wrapped columns.

``tests/test_visible_fetch.py`` checks the features and both gradients bit for bit against the torch form
where torch runs that kernel (x86 CPUs), and to float32 rounding everywhere.

Conventions: uv units (one plane repeat = 1) for ``points`` and ``z``; ``slope`` in uv per unit of height
(``v`` scaled by the plane's aspect, as :func:`~dynbtf.representations.parallax.view_offsets` does).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from ..texture import fetch_wrap

__all__ = ["fetch_visible", "TORCH_GRID_SAMPLE_LANES"]

#: Points per vector of torch's CPU ``grid_sample`` kernel (float32, the AVX2 build x86 CPUs run): its backward
#: adds a vector's gradient into the plane corner by corner, which orders the sums of points that share a texel.
TORCH_GRID_SAMPLE_LANES = 8

_ONE, _HALF, _ZERO = np.float32(1.0), np.float32(0.5), np.float32(0.0)


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
        constants = _constants(rows, cols, height_scale)
        n = len(points_np)
        out = np.empty((n, channels + 1), dtype=np.float32)
        denominator = np.empty(n, dtype=np.float32)
        footprints = (np.empty((n, 2), dtype=np.int64), np.empty((n, 4), dtype=np.int64),
                      np.empty((n, 8), dtype=np.float32), np.empty((n, 4), dtype=np.float32))
        _forward(plane, rows, cols, points_np, _contiguous(z), slope_np, *constants, out, denominator, *footprints)
        ctx.shape = (rows, cols, channels)
        ctx.arrays = (plane, slope_np, denominator, footprints, constants)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        plane, slope, denominator, footprints, constants = ctx.arrays
        rows, cols, channels = ctx.shape
        grad_f_u = np.empty((rows, cols, channels), dtype=np.float32)
        grad_height = np.empty((rows, cols), dtype=np.float32)
        _backward(plane, rows, cols, slope, denominator, *footprints, *constants, _contiguous(grad_out),
                  grad_f_u, grad_height)
        return torch.from_numpy(grad_f_u), torch.from_numpy(grad_height), None, None, None, None


def _contiguous(tensor: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().numpy(), dtype=np.float32)


def _constants(rows: int, cols: int, height_scale: float) -> tuple:
    """The float32 constants torch rounds: per axis (u, then v) the scale from ``[0, 1)`` to padded texels,
    ``fetch_wrap``'s normalization ``2 / (padded - 1)`` and ``grid_sample``'s ``(padded - 1) / 2``; then
    ``eps``, ``2 eps`` and ``height_scale``."""
    eps = _half_texel(rows, cols)
    return (np.float32(cols), np.float32(2.0 / (cols + 1)), np.float32(cols + 1) / np.float32(2),
            np.float32(rows), np.float32(2.0 / (rows + 1)), np.float32(rows + 1) / np.float32(2),
            np.float32(eps), np.float32(2 * eps), np.float32(height_scale))


# ---------------------------------------------------------------------------- compiled loops
@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (float32), as the contracted ``grid_sample`` kernel computes it."""
    signature = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, sig, args):
        function = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.FloatType(), [ir.FloatType()] * 3),
                                                  "llvm.fma.f32")
        return builder.call(function, args)

    return signature, codegen


@numba.njit(inline="always")
def _axis(p, size, to_grid, half_span):
    """One axis of ``fetch_wrap`` at ``p`` (float32) through ``grid_sample``: the padded texel ``index`` left of
    the point (texel ``j`` of the plane is padded texel ``j + 1``), the fraction ``t`` past it, and the
    gradient multiplier of ``grid_sample``'s clipped, un-normalized coordinate."""
    wrapped = p - np.floor(p)  # wrap_uv
    if wrapped >= _ONE:
        wrapped = wrapped - _ONE
    grid = (wrapped * size + _HALF) * to_grid - _ONE  # padded texels, then [-1, 1] (each op rounded)
    x = (grid + _ONE) * half_span  # grid_sample's un-normalization (align_corners), clipped to the border
    low = max(x, _ZERO)
    top = (half_span + half_span)
    x = min(low, top)
    multiplier = half_span if (low != _ZERO and x != top) else _ZERO
    index = np.floor(x)
    return int(index), x - index, multiplier


@numba.njit(inline="always")
def _bilinear(rows, cols, x, y, constants):
    """``grid_sample``'s bilinear footprint at uv ``(x, y)``: the plane's four texels (flat indices
    ``north_west, north_east, south_west, south_east``), their weights, the padded texel of the north-west
    corner ``(iy, jx)``, the fractions ``(ty, tx)`` and the coordinate-gradient multipliers ``(my, mx)``."""
    jx, tx, mx = _axis(x, constants[0], constants[1], constants[2])
    iy, ty, my = _axis(y, constants[3], constants[4], constants[5])
    j0, j1, i0, i1 = _texel(jx, cols), _texel(jx + 1, cols), _texel(iy, rows), _texel(iy + 1, rows)
    east, south = _ONE - tx, _ONE - ty
    texels = (i0 * cols + j0, i0 * cols + j1, i1 * cols + j0, i1 * cols + j1)
    weights = (south * east, south * tx, ty * east, ty * tx)
    return texels, weights, iy, jx, ty, tx, my, mx


@numba.njit(inline="always")
def _texel(padded, count):
    """The plane's texel of padded texel ``padded`` (``0 .. count + 1``, wrapped)."""
    index = padded - 1
    if index < 0:
        return count - 1
    if index >= count:
        return 0
    return index


@numba.njit(inline="always")
def _interpolate(plane, texels, weights, channel):
    """``grid_sample``'s bilinear sum of one channel (its fused multiply-adds, in its order)."""
    return _fma(plane[texels[3], channel], weights[3],
                _fma(plane[texels[2], channel], weights[2],
                     _fma(plane[texels[1], channel], weights[1], plane[texels[0], channel] * weights[0])))


@numba.njit(inline="always")
def _height(height, rows, cols, x, y, constants):
    texels, weights, _, _, _, _, _, _ = _bilinear(rows, cols, x, y, constants)
    return _interpolate(height, texels, weights, 0)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _forward(plane, rows, cols, points, z, slope, size_u, to_grid_u, half_u, size_v, to_grid_v, half_v, eps, two_eps,
             height_scale, out, denominator, cells, texels, weights, terms):  # pragma: no cover - compiled
    """The features ``out (N, C)`` at the points after the Newton step, from ``plane (rows * cols, C)`` float32
    (the height channel last). Writes for the backward the denominators and the footprints (:func:`_bilinear`) of
    the fetch at ``q`` and of the height's at ``p``: ``cells (N, 2)`` their padded north-west cells (``q``, ``p``),
    ``texels (N, 4)`` and ``weights[:, :4]`` ``q``'s, ``weights[:, 4:]`` ``p``'s, ``terms (N, 4)`` ``q``'s
    ``(ty, tx, my, mx)``."""
    constants = (size_u, to_grid_u, half_u, size_v, to_grid_v, half_v)
    last = plane.shape[1] - 1
    height = np.empty((plane.shape[0], 1), dtype=np.float32)  # uv units: height_channel * height_scale
    for r in range(plane.shape[0]):
        height[r, 0] = plane[r, last] * height_scale
    for n in range(points.shape[0]):
        px, py, sx, sy = points[n, 0], points[n, 1], slope[n, 0], slope[n, 1]
        ex, ey = sx * eps, sy * eps
        along = (_height(height, rows, cols, px + ex, py + ey, constants)
                 - _height(height, rows, cols, px - ex, py - ey, constants))
        d = max(_ONE - along / two_eps, np.float32(0.25))
        at_p, p_weights, iy, jx, _, _, _, _ = _bilinear(rows, cols, px, py, constants)
        dz = (_interpolate(height, at_p, p_weights, 0) - z[n]) / d
        qx, qy = px + dz * sx, py + dz * sy
        at_q, q_weights, qiy, qjx, ty, tx, my, mx = _bilinear(rows, cols, qx, qy, constants)
        for k in range(last + 1):
            out[n, k] = _interpolate(plane, at_q, q_weights, k)
        denominator[n] = d
        cells[n, 0], cells[n, 1] = qiy * (cols + 2) + qjx, iy * (cols + 2) + jx
        for c in range(4):
            texels[n, c], weights[n, c], weights[n, 4 + c] = at_q[c], q_weights[c], p_weights[c]
        terms[n, 0], terms[n, 1], terms[n, 2], terms[n, 3] = ty, tx, my, mx


@numba.njit(inline="always")
def _scatter(grad, cols, cells, weights, grad_out):
    """Add ``weights[n, c] * grad_out[n, k]`` into the padded gradient ``grad`` at each point's four corners, as
    ``grid_sample``'s backward does: vector by vector of points, corner by corner within a vector."""
    offsets = (0, 1, cols + 2, cols + 3)  # north-west, north-east, south-west, south-east
    lanes = TORCH_GRID_SAMPLE_LANES
    for start in range(0, cells.shape[0], lanes):
        for c in range(4):
            for n in range(start, min(start + lanes, cells.shape[0])):
                cell, weight = cells[n] + offsets[c], weights[n, c]
                for k in range(grad.shape[1]):
                    grad[cell, k] += weight * grad_out[n, k]


@numba.njit(inline="always")
def _unpad(grad, rows, cols, k):
    """The circular padding's gradient (channel ``k`` of ``grad ((rows + 2) * (cols + 2), C)``), in place: the
    wrapped rows added first, then the wrapped columns; the plane's gradient is the interior."""
    padded_cols = cols + 2
    for j in range(padded_cols):
        grad[padded_cols + j, k] += grad[(rows + 1) * padded_cols + j, k]
        grad[rows * padded_cols + j, k] += grad[j, k]
    for i in range(1, rows + 1):
        grad[i * padded_cols + 1, k] += grad[i * padded_cols + cols + 1, k]
        grad[i * padded_cols + cols, k] += grad[i * padded_cols, k]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _backward(plane, rows, cols, slope, denominator, cells, texels, weights, terms, size_u, to_grid_u, half_u, size_v,
              to_grid_v, half_v, eps, two_eps, height_scale, grad_out, grad_f_u, grad_height):  # pragma: no cover
    """The gradients of ``sum(grad_out * out)``: ``grad_f_u (rows, cols, C - 1)`` and ``grad_height (rows, cols)``
    (channel units: through the fetch and through ``dz``), from :func:`_forward`'s footprints."""
    channels = plane.shape[1]
    n_points = slope.shape[0]
    padded = (rows + 2) * (cols + 2)
    grad_plane = np.zeros((padded, channels), dtype=np.float32)
    grad_along_height = np.zeros((padded, 1), dtype=np.float32)
    grad_h = np.empty((n_points, 1), dtype=np.float32)  # d loss / d h(p)
    _scatter(grad_plane, cols, cells[:, 0], weights[:, :4], grad_out)
    for n in range(n_points):  # grid_sample's coordinate gradient, then back through fetch_wrap and q = p + dz s
        ty, tx, my, mx = terms[n, 0], terms[n, 1], terms[n, 2], terms[n, 3]
        east, south = _ONE - tx, _ONE - ty
        gx, gy = _ZERO, _ZERO
        for k in range(channels):
            nw, ne = plane[texels[n, 0], k], plane[texels[n, 1], k]
            sw, se = plane[texels[n, 2], k], plane[texels[n, 3], k]
            g = grad_out[n, k]
            gx = _fma(_fma(se - sw, ty, (ne - nw) * south), g, gx)
            gy = _fma(_fma(se - ne, tx, (sw - nw) * east), g, gy)
        grad_u = ((gx * mx) * to_grid_u) * size_u
        grad_v = ((gy * my) * to_grid_v) * size_v
        grad_h[n, 0] = (grad_u * slope[n, 0] + grad_v * slope[n, 1]) / denominator[n]
    _scatter(grad_along_height, cols, cells[:, 1], weights[:, 4:], grad_h)
    for k in range(channels):
        _unpad(grad_plane, rows, cols, k)
    _unpad(grad_along_height, rows, cols, 0)
    last = channels - 1
    for i in range(rows):
        for j in range(cols):
            cell = (i + 1) * (cols + 2) + j + 1
            for k in range(last):
                grad_f_u[i, j, k] = grad_plane[cell, k]
            grad_height[i, j] = grad_plane[cell, last] + grad_along_height[cell, 0] * height_scale
