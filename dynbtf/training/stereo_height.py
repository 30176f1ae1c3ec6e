"""A BTF's height field from its own images: multi-view plane-sweep stereo.

A BTF is a stack of photographs of one surface, rectified to a reference plane
``z = 0``, from many views. A surface point ``x`` at height ``z`` (uv units, see
:mod:`dynbtf.representations.parallax`) appears in the image of view ``w`` at
the reference-plane position

    x - z * (w_x, w_y) / w_z

(v component times ``W / H`` for non-square planes). For each candidate height of
a sweep every view's image is sampled there: at the true height all views see
the same point and (under the same light, away from strong view dependence)
agree. The photo-consistency cost of a height is the L1 spread of the views'
samples around their median -- the median keeps views in which the point is
hidden or glossy from dominating -- summed over the colour channels, over
near-vertical lights (little cast shadow, so the images are comparable across
views) and over a small window of texels. Each texel takes the height of least
cost, refined by a parabola through the neighbouring candidates -- where that cost
is clearly below the reference plane's; elsewhere (flat or glossy regions, whose
cost curve is flat) the height is filled in from trusted neighbours, or 0.

Its accuracy against the simulator's true height (RMSE, correlation) and its time are
measured in ``docs/triple_plane.md``.

**Scale.** The sweep runs over blocks of texels (``chunk_texels``; every texel's cost is
its own, so the blocks change nothing numerically) with each light's images padded
once: memory is the images read at a time (:data:`READ_BYTES`, or one light's images if more) plus a
bounded block, whatever the BTF's size.
Time grows with views x texels x lights x levels; ``max_views`` sweeps a subset of
views spread over the hemisphere (:func:`spread_views`) and ``max_lights`` the lights
nearest the normal, which the parallax fitter chooses for large BTFs
(:func:`auto_stereo_options`: a 400 x 400, 151-view file sweeps 32
views and 3 lights).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
import torch.nn.functional as F

from ..conventions import texel_centers_uv
from ..data.base import BTFSource
from ..errors import InputError
from ..representations.parallax import view_offsets
from ..texture import _grid_sample_hwc, wrap_uv

__all__ = ["stereo_height", "spread_views", "auto_stereo_options", "STEREO_VIEW_TEXELS", "BLOCK_VIEW_TEXELS",
           "READ_BYTES", "CHUNK_ALIGN"]

#: Views x texels of one light's sweep above which the parallax fitter sweeps a spread subset of views
#: and the lights nearest the normal (:func:`auto_stereo_options`); a 128 x 128 BTF of 81 views (1.3 M)
#: sweeps them all.
STEREO_VIEW_TEXELS = 5_120_000
#: Lights the parallax fitter sweeps on a large BTF (the normal one and two at the next elevation on
#: the UBO grids).
LARGE_BTF_LIGHTS = 3
#: Views x texels of one block of the sweep when ``chunk_texels`` is not given (~100 bytes each at the peak).
BLOCK_VIEW_TEXELS = 2_097_152
#: Bytes of images (float32) the sweep reads at a time: the lights whose images under the swept views fit are read
#: together, view-major (at least one light): 7 lights x 151 views of 64 x 64 texels (52 MB), or the 3 lights x 32
#: views of a 400 x 400 file's auto subset (184 MB).
READ_BYTES = 256 * 1024 ** 2
#: Blocks are multiples of this many texels: CPU sums over the views then take the same vectorized
#: path for every texel as in one block of all texels (measured: blocks of 100 texels do not).
CHUNK_ALIGN = 256


def spread_views(views: np.ndarray, count: int) -> np.ndarray:
    """Indices (sorted, int64) of ``count`` of ``views (V, 3)`` (unit directions) spread over the hemisphere.

    Farthest-point order: the view nearest the normal first, then repeatedly the view
    whose angle to the nearest chosen one is largest (ties: the lowest index).
    ``count >= V`` returns every index.
    """
    views = np.asarray(views, dtype=np.float64)
    if count >= len(views):
        return np.arange(len(views))
    chosen = [int(np.argmax(views[:, 2]))]
    nearest = views @ views[chosen[0]]  # cosine to the nearest chosen view
    while len(chosen) < count:
        pick = int(np.argmin(nearest))
        chosen.append(pick)
        nearest = np.maximum(nearest, views @ views[pick])
    return np.sort(np.asarray(chosen, dtype=np.int64))


def auto_stereo_options(source: BTFSource) -> dict:
    """The :func:`stereo_height` options the parallax fitter adds for ``source``: none when
    ``views x texels <= STEREO_VIEW_TEXELS`` (every view and light), else ``max_views`` (the views
    that fit that budget, at least 16) and ``max_lights = LARGE_BTF_LIGHTS``. A 400 x 400 BTF of 151
    views: 32 views, 3 lights."""
    texels = source.height * source.width
    if source.n_views * texels <= STEREO_VIEW_TEXELS:
        return {}
    return {"max_views": int(min(source.n_views, max(16, STEREO_VIEW_TEXELS // texels))),
            "max_lights": LARGE_BTF_LIGHTS}


def _check_options(source: BTFSource, levels, max_height, window, min_contrast, fill_window, max_views,
                   max_lights, chunk_texels) -> None:
    if int(levels) < 3:
        raise InputError(f"stereo levels: expected at least 3 candidate heights, got {levels}")
    if not max_height > 0:
        raise InputError(f"stereo max_height: expected a positive height in uv units, got {max_height}")
    for name, value in (("window", window), ("fill_window", fill_window)):
        if int(value) < 1 or int(value) % 2 == 0:
            raise InputError(f"stereo {name}: expected an odd number of texels, got {value}")
    if not 0 <= min_contrast < 1:
        raise InputError(f"stereo min_contrast: expected a fraction in [0, 1), got {min_contrast}")
    if source.n_views < 2:
        raise InputError(f"{source.name}: stereo needs at least two views, the BTF has {source.n_views}")
    if max_views is not None and int(max_views) < 2:
        raise InputError(f"stereo max_views: expected at least 2 views (or None: all), got {max_views}")
    if max_lights is not None and int(max_lights) < 1:
        raise InputError(f"stereo max_lights: expected at least 1 light (or None: all), got {max_lights}")
    if chunk_texels is not None and int(chunk_texels) < 1:
        raise InputError(f"stereo chunk_texels: expected a positive number of texels (or None), got {chunk_texels}")


def _read_lights(source: BTFSource, view_set: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """The images ``(len(lights), V', H, W, 3)`` of ``lights`` under the views ``view_set``, read **view-major**:
    sources that render or decode a view's lights together (simulated BTFs, DFMF files) then do it once per
    view, not once per view and light."""
    stack = None
    for i, v in enumerate(view_set):
        for j, light in enumerate(lights):
            image = np.asarray(source.image(int(v), int(light)))
            if stack is None:
                stack = np.empty((len(lights), len(view_set)) + image.shape, dtype=image.dtype)
            stack[j, i] = image
    return stack


def _median_views(seen: torch.Tensor) -> torch.Tensor:
    """The median over the views of ``seen (V', n, C)`` -> ``(n, C)``: for an even ``V'`` the lower of the two
    middle values (as ``torch.median``), found by a selection (``numpy.partition``, in place), chosen over
    ``torch.median`` for its speed on the CPU. The views are brought last by :func:`_views_last` (a blocked
    copy on every core, in place of numpy's slower strided copy)."""
    k = (seen.shape[0] - 1) // 2
    by_view = seen.detach().cpu().permute(0, 2, 1).contiguous().numpy()  # (V', C, n): grid_sample's own layout
    by_texel = np.empty((by_view.shape[2], by_view.shape[1], by_view.shape[0]), dtype=by_view.dtype)
    _views_last(by_view, by_texel)
    by_texel.partition(k, axis=-1)
    return torch.from_numpy(np.ascontiguousarray(by_texel[..., k])).to(seen.device)


#: Side of the square tiles :func:`_views_last` copies (views x texels).
_TILE = 32


@numba.njit(parallel=True, cache=True, nogil=True)
def _views_last(values, out):  # pragma: no cover - compiled
    """``out[t, c, v] = values[v, c, t]`` for ``values (V, C, n)``, tile by tile."""
    views, channels, n = values.shape
    blocks = (n + _TILE - 1) // _TILE
    for task in numba.prange(blocks * channels):
        c, b = task // blocks, task % blocks
        for v0 in range(0, views, _TILE):
            for t in range(b * _TILE, min(b * _TILE + _TILE, n)):
                for v in range(v0, min(v0 + _TILE, views)):
                    out[t, c, v] = values[v, c, t]


def _sweep_cost(source: BTFSource, view_set: np.ndarray, light_set: np.ndarray, heights: torch.Tensor,
                chunk_texels: int, bar) -> torch.Tensor:
    """Photo-consistency cost ``(levels, H * W)`` float64 of every candidate height at every texel.

    The swept views' images are read once, view-major, as many lights together as fit in :data:`READ_BYTES`
    (``(L'', V', H, W, 3)``), and padded once; the texels are swept in blocks of ``chunk_texels``: per level the
    block's sample points ``(V', n, 2)`` float64 (as :func:`~dynbtf.texture.fetch_wrap_stack`) are computed once
    for those lights, and each light's samples ``(V', n, 3)`` float32 taken there.
    """
    h, w = source.height, source.width
    views = torch.as_tensor(np.asarray(source.views)[view_set], dtype=torch.float64)
    offsets = view_offsets(views, w / h)  # (V', 2)
    centres = torch.from_numpy(texel_centers_uv(h, w).reshape(-1, 2))  # (N, 2) float64
    cost = torch.zeros(len(heights), h * w, dtype=torch.float64)
    per_read = max(1, READ_BYTES // (len(view_set) * h * w * 3 * 4))  # lights read together
    for j in range(0, len(light_set), per_read):
        images = _read_lights(source, view_set, light_set[j: j + per_read])
        padded = [F.pad(torch.from_numpy(stack).permute(0, 3, 1, 2), (1, 1, 1, 1), mode="circular")
                  for stack in images]  # per light (V', 3, H + 2, W + 2)
        del images
        for k, z in enumerate(heights):
            for a in range(0, h * w, chunk_texels):
                points = centres[None, a:a + chunk_texels] - float(z) * offsets[:, None]  # (V', n, 2)
                frac = wrap_uv(points)
                x = (frac[..., 0] * w + 0.5).to(padded[0].dtype)  # padded coordinate: texel j centre at j + 1
                y = (frac[..., 1] * h + 0.5).to(padded[0].dtype)
                for light_images in padded:  # (the lights' costs added in order, as one light at a time would)
                    seen = _grid_sample_hwc(light_images, x, y)  # (V', n, 3)
                    cost[k, a:a + chunk_texels] += (seen - _median_views(seen)).abs().sum((0, 2)).double()
            bar.update(len(padded))
    return cost


def stereo_height(source: BTFSource, *, max_light_theta: float = 15.0, levels: int = 65, max_height: float = 0.08,
                  window: int = 3, min_contrast: float = 0.1, fill_window: int = 7, max_views: int | None = None,
                  max_lights: int | None = None, chunk_texels: int | None = None,
                  progress: bool = False, return_trusted: bool = False):
    """Height field ``(H, W)`` float64, uv units, of ``source`` by plane-sweep stereo.

    Parameters
    ----------
    source : BTFSource
        The BTF (every swept view's images under the selected lights are read once).
    max_light_theta : float
        Lights with ``theta <= max_light_theta`` degrees are used (at least the one
        nearest the normal).
    levels : int
        Candidate heights, evenly spaced in ``[-max_height, max_height]`` (>= 3).
    max_height : float
        Largest height searched, uv units (0.08: +-10 texels at 128 texels).
    window : int
        Odd side of the square window the cost is summed over.
    min_contrast : float
        A texel's estimate is trusted only where its least cost is inside the search range and
        at least this fraction below the cost of the reference plane (``cost(z) <= (1 - min_contrast) cost(0)``); elsewhere the
        views agree about as well at ``z = 0`` (a flat or glossy surface: its cost curve is flat
        and the minimum is noise), and the height is the mean of the trusted estimates within
        ``fill_window`` texels, or 0 where there are none. 0 trusts every texel.
    fill_window : int
        Odd side of that window.
    max_views : int or None
        Sweep at most this many views, spread over the hemisphere (:func:`spread_views`);
        None: every view. Time and the images held are proportional to it.
    max_lights : int or None
        Of the lights within ``max_light_theta``, sweep the ``max_lights`` nearest the normal
        (ties: the lowest index); None: all of them. Time is proportional to it.
    chunk_texels : int or None
        Texels per block of the sweep, rounded up to a multiple of ``CHUNK_ALIGN`` (None:
        ``BLOCK_VIEW_TEXELS // views``, so a block's arrays stay near 200 MB); the result
        does not depend on it (bit for bit).
    progress : bool
        Show a progress bar.
    return_trusted : bool
        Also return where the estimate is trusted (see ``min_contrast``).

    Returns
    -------
    float64 ``(H, W)``: height of each texel centre relative to the reference plane; with
    ``return_trusted``, ``(height, trusted)`` where ``trusted (H, W)`` bool marks the texels whose
    own estimate was kept (the others are filled in). Its mean separates a surface with relief
    the views agree on from a flat or glossy one whose "relief" is noise (simulated at 128 x 128:
    stone, woven fabric and leather vs lacquered wood; docs/choosing.md).
    """
    from ..progress import progress_bar
    _check_options(source, levels, max_height, window, min_contrast, fill_window, max_views, max_lights,
                   chunk_texels)
    h, w = source.height, source.width
    lights = np.asarray(source.lights, dtype=np.float64)
    light_set = np.nonzero(lights[:, 2] >= math.cos(math.radians(max_light_theta)) - 1e-9)[0]
    if len(light_set) == 0:
        light_set = np.array([int(np.argmax(lights[:, 2]))])
    if max_lights is not None and len(light_set) > int(max_lights):
        nearest = np.argsort(-lights[light_set, 2], kind="stable")[: int(max_lights)]
        light_set = np.sort(light_set[nearest])
    view_set = np.arange(source.n_views) if max_views is None else spread_views(source.views, int(max_views))
    chunk = int(chunk_texels) if chunk_texels is not None else BLOCK_VIEW_TEXELS // len(view_set)
    chunk = -(-chunk // CHUNK_ALIGN) * CHUNK_ALIGN  # blocks aligned so that the sums round as one block's would
    heights = torch.linspace(-max_height, max_height, int(levels), dtype=torch.float64)
    bar = progress_bar(total=len(light_set) * int(levels), unit="level", disable=not progress, desc="stereo height")
    try:
        cost = _sweep_cost(source, view_set, light_set, heights, chunk, bar)
    finally:
        bar.close()
    height, trusted = _pick_heights(cost, heights, h, w, window, min_contrast, fill_window)
    return (height, trusted) if return_trusted else height


def _pick_heights(cost: torch.Tensor, heights: torch.Tensor, h: int, w: int, window: int, min_contrast: float,
                  fill_window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The height ``(H, W)`` float64 (uv units) of least ``cost (levels, H * W)`` (window-summed,
    parabola-refined), filled in from trusted neighbours where untrusted (see :func:`stereo_height`),
    and the trusted texels ``(H, W)`` bool."""
    levels = len(heights)
    if window > 1:
        pad = int(window) // 2
        padded = F.pad(cost.view(levels, 1, h, w), (pad, pad, pad, pad), mode="circular")
        cost = F.avg_pool2d(padded, int(window), stride=1).view(levels, h * w)
    best = cost.argmin(0)
    k = best.clamp(1, levels - 2)
    below, at, above = (cost.gather(0, (k + d)[None])[0] for d in (-1, 0, 1))
    shift = (0.5 * (below - above) / (below - 2 * at + above).clamp_min(1e-12)).clamp(-0.5, 0.5)
    estimate = (heights[k] + shift * (heights[1] - heights[0])).view(h, w)
    plane = int(heights.abs().argmin())  # the level nearest z = 0
    trusted = (cost.gather(0, best[None])[0] <= (1 - min_contrast) * cost[plane]) & (best > 0) & (best < levels - 1)
    trusted = trusted.view(h, w)  # (a minimum on the search's bound is no minimum)
    if bool(trusted.all()):
        return estimate, trusted
    pad = int(fill_window) // 2
    weights = trusted.double()[None, None]
    sums = F.avg_pool2d(F.pad(estimate[None, None] * weights, (pad,) * 4, mode="circular"), int(fill_window), stride=1)
    counts = F.avg_pool2d(F.pad(weights, (pad,) * 4, mode="circular"), int(fill_window), stride=1)
    filled = torch.where(counts > 0, sums / counts.clamp_min(1e-12), torch.zeros_like(sums))[0, 0]
    return torch.where(trusted, estimate, filled), trusted
