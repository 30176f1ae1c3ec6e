"""Parallax: answering a query at the surface point the viewer actually sees.

A measured BTF is rectified to a **reference plane** ``z = 0``: the pixel at ``uv``
of the image seen from ``w_view`` shows whatever surface point the camera ray
through ``(uv, 0)`` meets first. On a material with relief that point is *not*
above ``uv``: the ray through ``uv`` meets height ``z`` at

    uv + z * (w_x, w_y) / w_z                      (uv units, z in uv units)

so a bump seen at grazing angles slides towards the viewer and hides what lies
behind it (parallax and masking). A positional plane fetched at ``uv`` for every
view cannot represent that: each texel would have to learn every view's
displacement (the paper's Triple Plane loses ~10 dB on a rough stone for this
reason, measured in ``docs/triple_plane.md``).

:class:`ParallaxTriplePlane` (kind ``"triple-parallax"``) adds a **height field** to
the Triple Plane, stored as one more channel of the positional plane (so
synthesis synthesizes it with the features), and fetches the features at the
visible point found by :func:`march_visible_uv`. Given the height, everything
else is the paper's Triple Plane. The height is estimated from the BTF's own
images before training (:func:`dynbtf.training.stereo_height.stereo_height`) and
then refined with the other parameters by the same L1 loss (gradients reach it
through the visible point, by the implicit-function rule, and through the
decoder, which reads it as a 17th positional channel).

Conventions: heights are in uv units (one exemplar repeat = 1), positive
towards the viewer side (``+z``); the reference plane is ``z = 0``. ``uv`` may be
float64 and any real value (the height is periodic).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from ..conventions import texel_centers_uv
from ..errors import InputError
from ..texture import fetch_wrap, wrap_uv
from .base import config_flag, config_number, register
from .parallax_kernels import march_plane, visible_texel_points
from .triple_plane import TriplePlane
from .visible_fetch import fetch_visible

__all__ = ["view_offsets", "march_visible_uv", "VisibleTexelCache", "ParallaxTriplePlane"]

#: Default resolution of a march: the largest horizontal length of the bracket its hit is interpolated in, in
#: texels of the height field (``march_step_texels``).
MARCH_STEP_TEXELS = 0.5
#: The longest search step of a model's march in units of its resolution (``march_step_texels``).
MARCH_SEARCH_FACTOR = 16
#: Most march steps a model's height range may span (its plane's largest magnitude, both signs, in uv, over its
#: march step): a fitted relief spans tens to a few thousand (a 4096-texel side); a file beyond it is refused
#: before it answers (each query would march for seconds or never return).
MAX_MARCH_SPAN = 1 << 15
#: The slope the march's search step assumes the surface may rise at (height per horizontal distance): a step
#: covers the gap under the ray as if the surface rose towards the ray at this slope (see :func:`march_visible_uv`).
MARCH_SURFACE_SLOPE = 0.5


def view_offsets(w_view: torch.Tensor, aspect: float = 1.0) -> torch.Tensor:
    """Where a view sees a point, per unit of its height: ``(..., 2)`` uv displacement ``(w_x, w_y) / w_z``.

    ``w_view (..., 3)`` unit directions (``z > 0``; ``z`` is clamped at 1e-6); heights are in u
    units, so the v component is multiplied by ``aspect = W / H``. A point at height ``z`` is
    seen through the reference-plane point ``x - z * view_offsets(w)``.
    """
    offsets = w_view[..., :2] / w_view[..., 2:3].clamp_min(1e-6)
    return offsets * torch.tensor([1.0, aspect], dtype=offsets.dtype, device=offsets.device)


def _marchable(w_view: torch.Tensor) -> torch.Tensor:
    """``w_view (N, 3)`` as float64 with directions ``z <= 0`` replaced by the vertical (they evaluate to zero anyway)."""
    w = w_view.to(torch.float64)
    return torch.where(w[:, 2:3] > 0, w, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=w.device))


def march_visible_uv(uv: torch.Tensor, w_view: torch.Tensor,
                     height_at: Callable[[torch.Tensor], torch.Tensor] | torch.Tensor, *,
                     h_min: float, h_max: float, step: float, max_step: float | None = None,
                     surface_slope: float = MARCH_SURFACE_SLOPE, aspect: float = 1.0) -> torch.Tensor:
    """Where the camera rays through the reference-plane points ``uv`` first meet a height field.

    Parameters
    ----------
    uv : ``(N, 2)`` float64
        Reference-plane points, uv units (any real values).
    w_view : ``(N, 3)``
        Unit directions towards the viewer, ``z > 0``.
    height_at : callable or tensor
        ``height_at(points (M, 2) float64) -> (M,)`` the height field (uv units) at
        any points; called once per sample of a ray, on shrinking subsets. Or a
        height plane ``(H, W)`` (uv units, at the texel centres, fetched bilinearly and
        periodically as :func:`~dynbtf.texture.fetch_wrap` does): on the CPU its rays are
        marched by a compiled kernel (:func:`~dynbtf.representations.parallax_kernels.march_plane`),
        the same march in one loop per ray.
    h_min, h_max : float
        Bounds of the field (a point where the field exceeds ``h_max`` is hit at ``h_max``).
    step : float
        Resolution (uv units): the shortest horizontal search step and the longest
        bracket the hit is interpolated in.
    max_step : float, optional
        Longest horizontal search step (uv units; default ``step``: every step is ``step``).
    surface_slope : float
        The slope (height per horizontal distance) the search step assumes the surface may rise at.
    aspect : float
        ``W / H`` of the plane: heights are in u units, so a v displacement is
        scaled by it (1 for square planes).

    Returns
    -------
    ``(N, 2)`` float64: the visible points (not wrapped).

    Notes
    -----
    Each ray ``uv + z s`` (``s = (w_x, w_y) / w_z``) is searched from ``z = h_max``
    down to ``h_min``. From a sample at ``z`` with a gap ``g = z - height > 0`` the
    next sample is a horizontal distance ``clamp(g |s| / (1 + surface_slope |s|), step,
    max_step)`` further (where the ray would meet a surface rising towards it at
    ``surface_slope`` from the point below it), never below ``h_min``. The first
    sample at or below the surface (or the one at ``h_min``) and the one before it
    bracket the intersection. The bracket is halved (its midpoint sampled, the half
    that still brackets kept) while its horizontal length exceeds ``step (1 + 1e-6)``,
    and the hit is placed by linear interpolation of ``height - z`` between its ends
    (clamped to the bracket). A vertical ray therefore lands exactly on ``height(uv)``
    and a planar field is hit exactly. Features narrower than ``step`` can be missed,
    as in any height-field ray march; so can features steeper than ``surface_slope``
    and narrower than the longer steps taken in the gap above them.

    Examples
    --------
    A flat field at height 0.1 seen at 45 degrees along +x: the visible point is 0.1 further along x.

    >>> import math, torch
    >>> w = torch.tensor([[math.sqrt(0.5), 0.0, math.sqrt(0.5)]], dtype=torch.float64)
    >>> march_visible_uv(torch.tensor([[0.2, 0.3]], dtype=torch.float64), w,
    ...                  lambda p: torch.full(p.shape[:1], 0.1, dtype=torch.float64), h_min=0.0, h_max=0.2,
    ...                  step=0.01, max_step=0.08)
    tensor([[0.3000, 0.3000]], dtype=torch.float64)
    """
    uv = uv.to(torch.float64)
    w = w_view.to(device=uv.device, dtype=torch.float64)
    if uv.ndim != 2 or uv.shape[-1] != 2 or w.shape != (uv.shape[0], 3):
        raise InputError(f"march_visible_uv: expected uv (N, 2) and w_view (N, 3), got {tuple(uv.shape)} and "
                         f"{tuple(w_view.shape)}")
    max_step = step if max_step is None else max_step
    if not h_max >= h_min or not 0 < step <= max_step or not surface_slope >= 0:
        raise InputError(f"march_visible_uv: expected h_min <= h_max, 0 < step <= max_step and surface_slope >= 0, "
                         f"got {h_min}, {h_max}, {step}, {max_step}, {surface_slope}")
    if uv.shape[0] == 0:
        return uv.clone()
    slope = view_offsets(w, aspect)
    if isinstance(height_at, torch.Tensor):
        plane = height_at.to(torch.float64)
        if plane.ndim != 2:
            raise InputError(f"march_visible_uv: expected a height plane (H, W), got {tuple(height_at.shape)}")
        if plane.device.type == "cpu" and uv.device.type == "cpu":
            return march_plane(uv, slope, plane, h_min=h_min, h_max=h_max, step=step, max_step=max_step,
                               surface_slope=surface_slope)
        height_at = lambda points: fetch_wrap(plane[..., None], points)[:, 0]  # noqa: E731
    length = slope.norm(dim=-1).clamp_min(1e-12)  # horizontal uv per unit of z
    shortest, longest, fine = step / length, max_step / length, step * (1.0 + 1e-6) / length  # in z
    f_hi = height_at(uv + h_max * slope).to(torch.float64) - h_max  # height - z at the bracket's ends
    z_hi, z_lo, f_lo = torch.full_like(f_hi, h_max), torch.full_like(f_hi, h_max), f_hi.clone()
    bracketed = f_hi >= 0  # the field reaches h_max here: hit at once
    active = torch.nonzero(~bracketed).reshape(-1)
    while active.numel():
        inside = bracketed[active]  # halving the bracket, else searching
        zh, fh = z_hi[active], f_hi[active]
        gap = torch.minimum(torch.maximum(-fh / (1.0 + surface_slope * length[active]), shortest[active]),
                            longest[active])
        search = (zh - gap).clamp_min(h_min)
        z = torch.where(inside, 0.5 * (z_lo[active] + zh), search)
        f = height_at(uv[active] + z[:, None] * slope[active]).to(torch.float64) - z
        below = (f >= 0) | (~inside & (search <= h_min))
        z_lo[active] = torch.where(below, z, z_lo[active])
        f_lo[active] = torch.where(below, f, f_lo[active])
        z_hi[active] = torch.where(below, zh, z)
        f_hi[active] = torch.where(below, fh, f)
        bracketed[active] = inside | below
        done = bracketed[active] & (z_hi[active] - z_lo[active] <= fine[active])
        active = active[~done]
    t = (f_lo / (f_lo - f_hi)).clamp(0.0, 1.0).nan_to_num(0.0)  # fraction of the bracket back up
    return uv + (z_lo + t * (z_hi - z_lo))[:, None] * slope


class VisibleTexelCache:
    """Training's table of visible points: for each view seen so far, each texel centre's visible point
    (float32, wrapped) and its height (uv units), filled row by row as steps ask for them.

    ``views (V, 3)`` float64, ``points (V, T, 2)``, ``heights (V, T)``, ``marched (V, T)`` bool for
    ``T = n_texels``; rows not marched hold zeros. A view is matched by exact equality of its direction.
    Each view's :func:`view_offsets` for a plane of aspect ``aspect`` are kept with it (numpy): ``march_slopes
    (V, 2)`` float64 (of the view as marched, :func:`_marchable`) and ``fetch_slopes (V, 2)`` float32 (computed
    in the dtype the view was first given in, then rounded to float32: the Newton step's).
    Capacity grows in blocks of ``GROW_VIEWS`` views (13 bytes per texel and view: 0.3 GB for 400 x 400
    texels under 151 views); past ``MAX_VIEWS`` views the cache starts over.
    """

    GROW_VIEWS = 32
    MAX_VIEWS = 512

    def __init__(self, n_texels: int, aspect: float = 1.0) -> None:
        self.n_texels = int(n_texels)
        self.aspect = float(aspect)
        self.clear()

    def clear(self, device: torch.device | str = "cpu") -> None:
        """Forget every view."""
        self.count = 0
        self.slots_of: dict[tuple[float, float, float], int] = {}  # view direction -> its slot
        self.field = None  # (height plane, h_min, h_max) the rows are marched through, as the compiled path keeps it
        self.views = torch.zeros(0, 3, dtype=torch.float64, device=device)
        self.points = torch.zeros(0, self.n_texels, 2, device=device)
        self.heights = torch.zeros(0, self.n_texels, device=device)
        self.marched = torch.zeros(0, self.n_texels, dtype=torch.bool, device=device)
        self.march_slopes = np.zeros((0, 2))
        self.fetch_slopes = np.zeros((0, 2), dtype=np.float32)

    def forget_rows(self) -> None:
        """Keep the views, mark every row as to be marched again (the height has moved)."""
        self.marched.zero_()
        self.field = None

    def _reserve(self, count: int) -> None:
        capacity = self.views.shape[0]
        if count <= capacity:
            return
        extra = -(-(count - capacity) // self.GROW_VIEWS) * self.GROW_VIEWS
        self.views, self.points, self.heights, self.marched = (
            torch.cat([t, t.new_zeros(extra, *t.shape[1:])]) for t in (self.views, self.points, self.heights,
                                                                          self.marched))
        self.march_slopes, self.fetch_slopes = (np.concatenate([a, np.zeros((extra, 2), a.dtype)])
                                                for a in (self.march_slopes, self.fetch_slopes))

    def slots(self, w_views: torch.Tensor) -> np.ndarray:
        """The slots ``(G,)`` int64 (numpy) of the views ``w_views (G, 3)``; views not seen yet are added (past
        ``MAX_VIEWS`` the cache starts over first)."""
        device = w_views.device
        if self.views.device != torch.device(device):
            self.clear(device)
        given = w_views.detach()
        # exact values: a view is matched by equality of its direction
        keys = [tuple(v) for v in given.cpu().numpy().astype(np.float64).tolist()]
        first = {}  # new direction -> the index of its first row in w_views
        for i, key in enumerate(keys):
            if key not in self.slots_of and key not in first:
                first[key] = i
        if first:
            if self.count + len(first) > self.MAX_VIEWS and self.count:
                self.clear(device)
                return self.slots(w_views)
            start, stop = self.count, self.count + len(first)
            self._reserve(stop)
            new = torch.tensor(list(first), dtype=torch.float64, device=device)
            self.views[start:stop] = new
            self.march_slopes[start:stop] = view_offsets(_marchable(new), self.aspect).cpu().numpy()
            rows = torch.tensor(list(first.values()), device=device)
            self.fetch_slopes[start:stop] = view_offsets(given[rows], self.aspect).to(torch.float32).cpu().numpy()
            self.slots_of.update((key, start + i) for i, key in enumerate(first))
            self.count = stop
        return np.array([self.slots_of[key] for key in keys], dtype=np.int64)

    def lookup(self, w_views: torch.Tensor, texels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows ``(G, n)`` int64 (flat indices ``slot * n_texels + texel``) of ``texels (G, n)`` under the views
        ``w_views (G, 3)`` (new views are added) and the rows to march: those not marched yet (in row order; a row
        asked for twice is marched twice, to the same value)."""
        return self.rows(self.slots(w_views.to(texels.device)), texels)

    def rows(self, slots: np.ndarray, texels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`lookup` for views already given their ``slots (G,)`` by :meth:`slots`."""
        rows = torch.from_numpy(slots).to(texels.device)[:, None] * self.n_texels + texels
        return rows, rows[~self.marched.view(-1)[rows]]

    def store(self, rows: torch.Tensor, points: torch.Tensor, heights: torch.Tensor) -> None:
        """Rows ``rows (K,)`` (flat indices, as :meth:`lookup`'s) now hold ``points (K, 2)`` and ``heights (K,)``."""
        self.points.view(-1, 2)[rows] = points
        self.heights.view(-1)[rows] = heights
        self.marched.view(-1)[rows] = True

    def read(self, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The points ``(..., 2)`` and heights ``(...)`` of ``rows (...)`` (flat indices, as :meth:`lookup`'s)."""
        flat = rows.reshape(-1)
        return (self.points.view(-1, 2).index_select(0, flat).view(*rows.shape, 2),
                self.heights.view(-1).index_select(0, flat).view(rows.shape))


@register("triple-parallax")
class ParallaxTriplePlane(TriplePlane):
    """The Triple Plane with a height field: features are fetched at the visible surface point.

    Parameters
    ----------
    height, width, positional_channels, angular_resolution, angular_channels, hidden, layers, negative_slope, seed
        As :class:`~dynbtf.representations.triple_plane.TriplePlane`.
    height_scale : float, default 0.02
        uv units per unit of the stored height channel: the positional plane's last
        channel is ``height / height_scale`` (of the order of the learned features,
        which matters to synthesis and to the decoder, which reads it too).
    march_step_texels : float, default 0.5
        Resolution of the ray march, in texels of the plane: the largest horizontal length of the
        bracket its hit is interpolated in and the shortest search step (the longest is ``MARCH_SEARCH_FACTOR``
        times this).
    learn_height : bool, default True
        Train the height with the other parameters (a parameter) or keep it as set (a buffer).
    height_refresh_texels : float, default 0.05
        Training caches every view's visible points; they are marched again once the
        learned height has moved by this much on average (or by a texel anywhere).

    Set the height with :meth:`set_height` before fitting (``dynbtf fit --repr
    triple-parallax`` estimates it by plane-sweep stereo). A zero height field makes
    the model the Triple Plane with one constant extra decoder input.

    Examples
    --------
    >>> import torch
    >>> model = ParallaxTriplePlane(8, 8)
    >>> model.set_height(0.01 * torch.rand(8, 8))
    >>> w = torch.nn.functional.normalize(torch.rand(5, 3) + torch.tensor([0, 0, 1.0]), dim=-1)
    >>> model(torch.rand(5, 2), w, w).shape, model.positional_plane().shape
    (torch.Size([5, 3]), torch.Size([8, 8, 17]))
    """

    extra_positional_channels = 1
    #: Training on the CPU reads the visible-point table and marches its missing rows in one compiled loop
    #: (:func:`~dynbtf.representations.parallax_kernels.visible_texel_points`), and fetches the features there and
    #: their gradients in compiled loops (:func:`~dynbtf.representations.visible_fetch.fetch_visible`); ``False``
    #: runs the torch operations every other device runs (the same rays and points, and on x86 the same bits).
    use_compiled_kernels = True
    #: The fit loop gives every texel group images of one view (see :mod:`dynbtf.training.fit`).
    view_coherent_batches = True
    #: Compiling its loss traces the march step by step and takes longer than a short fit: not by default.
    compiled_on_gpu = False
    separate_channels = 1  # the height: synthesized on its own (its own histogram transform, outside the PCA)

    def __init__(self, height: int, width: int, positional_channels: int = 16, angular_resolution: int = 20,
                 angular_channels: int = 8, hidden: int = 32, layers: int = 4, negative_slope: float = 0.01,
                 seed: int = 0, height_scale: float = 0.02, march_step_texels: float = MARCH_STEP_TEXELS,
                 learn_height: bool = True, height_refresh_texels: float = 0.05) -> None:
        owner = "ParallaxTriplePlane"
        # checked before the Triple Plane allocates its planes
        height_scale = config_number(owner, "height_scale", height_scale, 0.0, 1e6, low_open=True)  # uv units
        march_step_texels = config_number(owner, "march_step_texels", march_step_texels, 0.0, 4.0, low_open=True)
        learn_height = config_flag(owner, "learn_height", learn_height)
        height_refresh_texels = config_number(owner, "height_refresh_texels", height_refresh_texels, 0.0, 1e6,
                                              low_open=True)
        super().__init__(height, width, positional_channels, angular_resolution, angular_channels, hidden, layers,
                         negative_slope, seed)
        height, width = self._config["height"], self._config["width"]
        self._config.update(height_scale=height_scale, march_step_texels=march_step_texels,
                            learn_height=learn_height, height_refresh_texels=height_refresh_texels)
        if learn_height:
            self.height_channel = nn.Parameter(torch.zeros(height, width))
        else:
            self.register_buffer("height_channel", torch.zeros(height, width))
        # the height (channel units) training's visible-point tables are marched through: a buffer, so that a
        # resumed run marches through the same field as an uninterrupted one (see _check_visible_cache)
        self.register_buffer("marched_height_channel", torch.zeros(height, width))
        self._visible_cache = VisibleTexelCache(height * width, aspect=width / height)

    # ------------------------------------------------------------ the height field
    @property
    def height_scale(self) -> float:
        return self._config["height_scale"]

    def height_field(self) -> torch.Tensor:
        """The height field ``(H, W)`` in uv units at the texel centres."""
        return self.height_channel * self.height_scale

    def set_height(self, height: torch.Tensor) -> None:
        """Set the height field from ``height (H, W)`` in uv units (e.g. :func:`~dynbtf.training.stereo_height.stereo_height`)."""
        height = torch.as_tensor(height)
        if tuple(height.shape) != tuple(self.height_channel.shape) or not bool(torch.isfinite(height).all()):
            raise InputError(f"height: expected finite values of shape {tuple(self.height_channel.shape)}, "
                             f"got shape {tuple(height.shape)}")
        with torch.no_grad():
            self.height_channel.copy_(height.to(self.height_channel) / self.height_scale)
            self.marched_height_channel.copy_(self.height_channel)
        self._visible_cache.clear()

    def _load_from_state_dict(self, *args, **kwargs):
        self._visible_cache.clear()
        return super()._load_from_state_dict(*args, **kwargs)

    def height_range(self) -> tuple[float, float]:
        """``(min, max)`` of the height field, uv units."""
        height = self.height_field().detach()
        return float(height.min()), float(height.max())

    # ------------------------------------------------------------ Representation API
    def positional_plane(self) -> torch.Tensor:
        """``concat(f_U, height / height_scale)``, ``(H, W, C_U + 1)``: the texture synthesis consumes."""
        return torch.cat([self.f_u, self.height_channel[..., None].to(self.f_u.dtype)], dim=-1)

    def visible_uv(self, uv: torch.Tensor, w_view: torch.Tensor,
                   fetch: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
        """The surface point seen through reference-plane point ``uv (..., 2)`` from ``w_view (..., 3)``.

        ``fetch(points (M, 2)) -> (M, C_U + 1)`` is the positional fetch whose last
        channel is the height (default: this model's plane; a synthesized BTF passes
        its synthesizer, so the march follows the synthesized relief, read through its
        ``channel(points, -1)``: the height channel alone), or a height
        plane ``(H, W, 1)`` in channel units. Directions
        with ``z <= 0`` are treated as vertical (they evaluate to zero anyway).
        Returns float64 ``(..., 2)``.
        """
        batch = uv.shape[:-1]
        flat = uv.reshape(-1, 2).to(torch.float64)
        w = _marchable(w_view.reshape(-1, 3).to(device=flat.device))
        # the exemplar's range: a synthesized field (blends of the exemplar's) may leave it a little, where
        # the march lands on its bounds (a ray meeting heights above h_max is stopped at h_max)
        if fetch is None:
            fetch = self.height_channel.detach()[..., None]
        if isinstance(fetch, torch.Tensor):  # a height plane (H, W, 1), channel units
            height_at, h_min, h_max = self._height_plane(fetch[..., 0])
        else:
            h_min, h_max = self.height_range()
            # a synthesizer synthesizes the height channel alone (Synthesizer.channel), not every channel
            read = getattr(fetch, "channel", None) or (lambda points, index: fetch(points)[..., index])

            def height_at(points):
                return read(points, -1).to(torch.float64) * self.height_scale
        return march_visible_uv(flat, w, height_at, h_min=h_min, h_max=h_max,
                                **self.march_parameters()).reshape(*batch, 2)

    def _height_plane(self, channel: torch.Tensor) -> tuple[torch.Tensor, float, float]:
        """A height plane in channel units ``(H, W)`` as :meth:`visible_uv` marches through it: float64 uv units,
        with its ``h_min`` and ``h_max``."""
        plane = channel.to(torch.float64) * self.height_scale
        return plane, float(plane.min()), float(plane.max())

    def state_problem(self) -> str | None:
        """A height range (the plane's largest magnitude, either sign, times ``height_scale``: what a synthesized
        height may reach) spanning more than :data:`MAX_MARCH_SPAN` march steps, or None."""
        plane = self.positional_plane().detach()
        reach = 2.0 * float(plane.abs().max()) * self.height_scale if plane.numel() else 0.0
        span = reach / self.march_parameters()["step"]
        if not span <= MAX_MARCH_SPAN:
            return (f"its height field spans {span:.3g} march steps ({reach:.3g} uv of height over steps of "
                    f"{self.march_parameters()['step']:.3g} uv; a fitted relief spans at most {MAX_MARCH_SPAN})")
        return None

    def march_parameters(self) -> dict[str, float]:
        """``step``, ``max_step`` (uv units), ``surface_slope`` and ``aspect`` of this model's march (:func:`march_visible_uv`):
        every backend marches with these."""
        rows, cols = self.height_channel.shape
        resolution = self._config["march_step_texels"] / max(rows, cols)
        return {"step": resolution, "max_step": MARCH_SEARCH_FACTOR * resolution,
                "surface_slope": MARCH_SURFACE_SLOPE, "aspect": cols / rows}

    # ------------------------------------------------------------ training fast path
    def _visible_texel_points(self, w_views: torch.Tensor,
                              texels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        """Visible points ``(G, n, 2)`` (float32, wrapped) and their heights ``(G, n)`` (uv units) of the
        texel centres ``texels[g] (G, n)`` (int64 texel indices) under view ``w_views[g] (G, 3)``, and the
        views' slots ``(G,)`` in the table (numpy int64).

        Answered from :class:`VisibleTexelCache` (see :meth:`_check_visible_cache`); the rows it does
        not hold yet are marched first, through ``marched_height_channel`` as :meth:`visible_uv` marches
        (a training step reads ``n = N / G`` texels per view, so a refresh costs one march of the step's
        ``N`` texels). Each ray is marched on its own, so a row is the same whichever rays are marched
        with it. On the CPU (:attr:`use_compiled_kernels`) the table is read and its missing rows marched
        in one compiled loop (:func:`~dynbtf.representations.parallax_kernels.visible_texel_points`); elsewhere
        by torch operations and :meth:`visible_uv`. Both march the same rays.
        """
        cache = self._visible_cache
        rows, cols = self.height_channel.shape
        if getattr(self, "_texel_centres", None) is None or self._texel_centres.device != texels.device:
            self._texel_centres = torch.from_numpy(texel_centers_uv(rows, cols).reshape(-1, 2)).to(texels.device)
        if self.use_compiled_kernels and texels.device.type == "cpu":
            slots = cache.slots(w_views.cpu())
            if cache.field is None:
                plane, h_min, h_max = self._height_plane(self.marched_height_channel.detach())
                cache.field = (plane.numpy(), h_min, h_max)
            plane, h_min, h_max = cache.field
            march = self.march_parameters()
            points = np.empty((*texels.shape, 2), dtype=np.float32)
            heights = np.empty(texels.shape, dtype=np.float32)
            visible_texel_points(slots, texels.numpy(), self._texel_centres.numpy(), cache.march_slopes[slots],
                                 plane, h_min, h_max, march["step"], march["max_step"], march["surface_slope"],
                                 cache.points.view(-1, 2).numpy(), cache.heights.view(-1).numpy(),
                                 cache.marched.view(-1).numpy(), points, heights)
            return torch.from_numpy(points), torch.from_numpy(heights), slots
        slots = cache.slots(w_views.to(texels.device))
        cached, todo = cache.rows(slots, texels)
        if todo.numel():
            plane = self.marched_height_channel[..., None]
            slot, texel = todo // (rows * cols), todo % (rows * cols)
            with torch.no_grad():
                hit = self.visible_uv(self._texel_centres[texel], cache.views[slot], plane)
                at_hit = fetch_wrap(plane.double() * self.height_scale, hit)[:, 0]
            cache.store(todo, wrap_uv(hit).to(torch.float32), at_hit.to(torch.float32))
        return (*cache.read(cached), slots)

    def _check_visible_cache(self) -> None:
        """Empty the visible-point cache once the height has moved since it was filled by
        ``height_refresh_texels`` on average or by a texel anywhere (a learned height changes every
        optimizer step; between two marches :meth:`_visible_features` follows it by a Newton step)."""
        current = self.height_channel.detach()
        if current.device.type == "cpu":  # (numpy: cheap; torch's small reductions cost more than the work here)
            moved = np.abs(current.numpy() - self.marched_height_channel.numpy())
            mean, largest = float(moved.mean()), float(moved.max())
        else:
            moved = (current - self.marched_height_channel).abs()
            mean, largest = torch.stack([moved.mean(), moved.max()]).tolist()  # (one synchronization)
        texels = self.height_scale * max(current.shape)  # texels per channel unit
        if mean * texels < self._config["height_refresh_texels"] and largest * texels < 1.0:
            return
        self._visible_cache.forget_rows()  # the tables are kept, their rows marched again
        with torch.no_grad():
            self.marched_height_channel.copy_(current)

    def _visible_features(self, w_views: torch.Tensor, texels: torch.Tensor) -> torch.Tensor:
        """Positional features ``(G * n, C_U + 1)`` at the visible points of ``texels (G, n)``, row ``g``
        under view ``w_views[g]`` (one fetch of the plane for all of them).

        With a learned height the visible point is differentiable in it: from the
        cached hit ``p`` at height ``z`` (where ``height(p) = z`` when it was
        marched), one Newton step of ``height(p + dz s) = z + dz`` gives
        ``dz = (height(p) - z) / (1 - grad height . s)``; its value follows the height
        between two marches and its gradient is the implicit-function one
        (:func:`~dynbtf.representations.visible_fetch.fetch_visible`).
        """
        points, z, slots = self._visible_texel_points(w_views, texels)
        points, z = points.reshape(-1, 2), z.reshape(-1)
        if self.height_channel.requires_grad and torch.is_grad_enabled():
            # view_offsets of each group's view (float32), one row per point
            slope = np.repeat(self._visible_cache.fetch_slopes[slots], texels.shape[1], axis=0)
            slope = torch.from_numpy(slope).to(points.device)
            # the height learns both as geometry (the visible point) and as a decoder input; learning it as
            # geometry alone (detached here) measured worse on the stone: 30.14 vs 30.23 dB, height RMSE 0.25 vs 0.16
            return fetch_visible(self.f_u, self.height_channel, points, z, slope, self.height_scale,
                                 compiled=None if self.use_compiled_kernels else False)
        return fetch_wrap(self.positional_plane(), points)

    def predict_texel_images(self, w_view: torch.Tensor, w_light: torch.Tensor,
                             texels: torch.Tensor | None = None) -> torch.Tensor:
        """Whole images ``(B, N, 3)``: every texel centre's visible point, one (view, light) pair per image."""
        self._check_visible_cache()
        if texels is None:
            texels = torch.arange(self.height_channel.numel(), device=w_view.device)
        features = self._visible_features(w_view, texels.expand(w_view.shape[0], -1))
        angular = self.angular_features(w_view, w_light)
        return self.decode_with_angular(features.reshape(w_view.shape[0], texels.shape[0], -1), angular[:, None])

    def texel_image_l1_loss(self, w_view: torch.Tensor, w_light: torch.Tensor, target: torch.Tensor,
                            texels: torch.Tensor | None = None, *, chunk_texels: int = 256,
                            workers: int = 1, texel_groups: int = 1, precision: str = "fp32",
                            angular_taps: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
        """Fused mean L1 loss, as :meth:`TriplePlane.texel_image_l1_loss`, fetching at the visible points.

        Every texel group's images must share **one view** (the fit loop's
        view-coherent batches, :attr:`view_coherent_batches`): the group's
        positional features are then fetched once, at that view's visible points.
        """
        n_images = w_view.shape[0]
        if texel_groups < 1 or n_images % texel_groups:
            raise InputError(f"texel_groups={texel_groups} does not divide the {n_images} images")
        per_group = n_images // texel_groups
        group_views = w_view.reshape(texel_groups, per_group, 3)
        if not bool((group_views == group_views[:, :1]).all()):
            raise InputError("triple-parallax: every texel group's images must share one view "
                             "(view-coherent batches; see dynbtf.training.fit)")
        self._check_visible_cache()
        if texels is None:
            texels = torch.arange(self.height_channel.numel(), device=w_view.device)
        n = texels.shape[0] // texel_groups
        features = self._visible_features(group_views[:, 0], texels[: n * texel_groups].reshape(texel_groups, n))
        return self.decoder.texel_image_l1_loss(features, self.angular_features(w_view, w_light, angular_taps),
                                                target, chunk_texels=chunk_texels, workers=workers,
                                                texel_groups=texel_groups, precision=precision)

    def storage_bytes(self) -> int:
        """Bytes of what evaluation needs (the training-only ``marched_height_channel`` excluded)."""
        return super().storage_bytes() - self.marched_height_channel.numel() * self.marched_height_channel.element_size()

    def param_groups(self) -> list[dict[str, Any]]:
        """The Triple Plane's groups, plus the learned height (lr 1e-3 in channel units, no weight
        decay: decay would pull the relief towards the reference plane)."""
        groups = super().param_groups()
        if isinstance(self.height_channel, nn.Parameter):
            groups.append({"params": [self.height_channel], "lr": 1e-3, "weight_decay": 0.0, "name": "height"})
        return groups

