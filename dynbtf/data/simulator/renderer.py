"""Rendering BTF images of a height-field material: parallax, masking, cast shadows, shading.

For one (view, light) pair the value of output texel ``p`` (a point of the
reference plane ``z = 0``) is::

    x     = trace_view(h, w_view, p)                     visible surface point (parallax, masking)
    n     = normal of h at x
    value = pi f_r(n; w_view, w_light; material at x) * max(n.l, 0) / cos(theta_light) * V_light(x)
            + albedo(x) * albedo_mean * (1 - sky(x)) * E_mean(w_light)          (one-bounce fill)

* ``pi f_r`` is the clear-coated GGX model of :mod:`.shading` evaluated in the
  local frame of ``n`` (micro-scale masking/shadowing by Smith's ``G``).
* ``max(n.l, 0) / cos(theta_light)``: the local irradiance of a tilted facet
  relative to the macro surface's. dynbtf's stored values exclude the macro
  ``cos(theta_light)`` (:mod:`dynbtf.conventions`), exactly as a measurement
  divides it out, so this ratio -- which can exceed 1 on facets turned towards
  a grazing light -- is part of the value.
* ``V_light`` is the cast-shadow visibility (:func:`.geometry.light_visibility`),
  tabulated per light on the grid and interpolated at ``x``.
* The fill term approximates light reflected once by the surrounding relief:
  the point sees the surroundings over ``1 - sky(x)`` of its (cosine-weighted)
  hemisphere, and they have the mean albedo and, on average, the macro-relative
  irradiance ``E_mean = mean_grid(max(n.l, 0) / cos(theta_light) * V_light)``.
  It keeps shadows from being pitch black, as in photographs; it is 0 on a
  flat surface, where the model reduces exactly to the analytic BRDF.
* ``n . w_view`` is clamped to at least :data:`GRAZING_COS`: a visible point
  can only face away from the camera through the interpolation of normals.

The renderer caches the per-view trace (hit points and the material fetched
there) and the per-light visibility maps, so shading a pair is cheap
elementwise math batched over lights: on the CPU one fused numba kernel
(:mod:`.kernels`), elsewhere whole-array torch code (the reference).
"""

from __future__ import annotations

import contextlib
import functools
from collections import OrderedDict

import numpy as np
import torch

from .geometry import bilinear_taps, interpolate_taps, light_visibility, normals_from_height, sky_view_factor, trace_view
from .kernels import shade_view
from .materials import MaterialMaps
from .shading import dot3, layered_brdf

__all__ = ["HeightFieldRenderer", "GRAZING_COS"]


@contextlib.contextmanager
def _single_torch_thread():
    """Run torch ops single-threaded inside (restoring the setting afterwards).

    With the numba backend the heavy work runs in numba's own threads; the torch
    ops in between are small (one value per texel), and on a busy machine
    waking torch's intra-op thread pool for each of them costs far more than
    the operation itself.
    """
    old = torch.get_num_threads()
    if old != 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if old != 1:
            torch.set_num_threads(old)


def _cpu_bookkeeping(method):
    """Decorator: run ``method`` under :func:`_single_torch_thread` when the renderer uses numba."""
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        if self.backend != "numba":
            return method(self, *args, **kwargs)
        with _single_torch_thread():
            return method(self, *args, **kwargs)
    return wrapper

#: Smallest ``n . w_view`` used in shading (see module docstring).
GRAZING_COS = 0.02


class HeightFieldRenderer:
    """Renders ``pi f_r``-valued images of a tabulated material for given directions.

    Parameters
    ----------
    maps : MaterialMaps
        The material on a ``(G, G)`` grid.
    out_size : int
        Output images are ``(out_size, out_size, 3)``; texel ``[i, j]`` is the
        reference-plane point ``uv = ((j + .5) / S, (i + .5) / S)``.
    spread_deg : float
        Angular size of the light source (soft shadow edge), degrees.
    interreflection : bool
        Add the one-bounce fill term (see module docstring).
    shadows : bool
        Cast shadows on (``False`` gives ``V_light = 1``: for comparisons).
    device : torch device or None
        Where to compute (default CPU).
    view_cache : int
        How many views' traces to keep.
    backend : ``"auto"``, ``"torch"`` or ``"numba"``
        Shading implementation: the fused numba kernel (:mod:`.kernels`, CPU
        only, several times faster) or whole-array torch code (any device, the
        reference). ``auto`` picks numba on the CPU.
    """

    def __init__(self, maps: MaterialMaps, out_size: int, *, spread_deg: float = 2.0, interreflection: bool = True,
                 shadows: bool = True, device=None, view_cache: int = 2, backend: str = "auto"):
        self.device = torch.device("cpu") if device is None else torch.device(device)
        if backend not in ("auto", "torch", "numba"):
            raise ValueError(f"backend must be 'auto', 'torch' or 'numba', got {backend!r}")
        if backend == "numba" and self.device.type != "cpu":
            raise ValueError(f"the numba backend runs on the CPU only, not on {self.device}")
        self.backend = ("numba" if self.device.type == "cpu" else "torch") if backend == "auto" else backend
        self.maps = maps
        self.out_size = int(out_size)
        g = maps.size
        if g % self.out_size or (g // self.out_size) % 2 == 0:
            raise ValueError(f"the material grid ({g}) must be an odd multiple of the output size ({out_size})")
        self.stride = g // self.out_size
        self.spread_deg = float(spread_deg)
        self.interreflection = bool(interreflection)
        self.shadows = bool(shadows)
        f32 = dict(dtype=torch.float32, device=self.device)
        self.height = torch.as_tensor(maps.height, **f32)
        normals = normals_from_height(self.height)
        sky = sky_view_factor(self.height) if interreflection else torch.ones_like(normals[..., 0])
        self._normals = normals
        self.has_coat = bool(np.asarray(maps.coat).max() > 0.0)
        plane = torch.cat([
            normals,
            torch.as_tensor(maps.albedo, **f32),
            torch.as_tensor(maps.alpha, **f32)[..., None],
            torch.as_tensor(maps.f0, **f32)[..., None],
            torch.as_tensor(maps.coat, **f32)[..., None],
            sky[..., None],
        ], dim=-1)  # (G, G, 10)
        self._plane_channels = plane.reshape(-1, plane.shape[-1]).transpose(0, 1).contiguous()  # (10, G*G)
        self.albedo_mean = torch.as_tensor(np.asarray(maps.albedo).reshape(-1, 3).mean(0), **f32)
        self._views: OrderedDict = OrderedDict()
        self._view_cache = max(1, int(view_cache))
        self._lights: dict = {}
        self._stack_key: bytes | None = None
        self._stack = None

    # ----------------------------------------------------------- cached pieces
    @_cpu_bookkeeping
    def view_trace(self, w_view) -> dict:
        """Hit points of the texels' camera rays and the material there (cached per view).

        Returns a dict with ``uv`` (N, 2) float64 hit positions, ``z`` (N,) hit
        heights, ``taps``/``weights`` (N, 4) their bilinear interpolation
        (:func:`.geometry.bilinear_taps`), and ``n`` (N, 3), ``albedo`` (N, 3), ``alpha``, ``f0``, ``coat``,
        ``sky`` (N,) float32, ``N = out_size**2``.
        """
        key = tuple(round(float(x), 12) for x in w_view)
        if key in self._views:
            self._views.move_to_end(key)
            return self._views[key]
        hit_uv, hit_z = trace_view(self.height, w_view, self.stride)
        taps, weights = bilinear_taps(hit_uv, self.height.shape[0])
        attrs = interpolate_taps(self._plane_channels, taps, weights).transpose(0, 1)  # (N, 10)
        n = attrs[:, 0:3]
        n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)
        entry = dict(uv=hit_uv, z=hit_z, taps=taps, weights=weights, n=n, albedo=attrs[:, 3:6], alpha=attrs[:, 6], f0=attrs[:, 7],
                     coat=attrs[:, 8], sky=attrs[:, 9])
        self._views[key] = entry
        while len(self._views) > self._view_cache:
            self._views.popitem(last=False)
        return entry

    @_cpu_bookkeeping
    def light_maps(self, w_light) -> tuple[torch.Tensor, float]:
        """Visibility map ``(G, G)`` and ``E_mean`` of one light direction (cached)."""
        key = tuple(round(float(x), 12) for x in w_light)
        if key not in self._lights:
            g = self.height.shape[0]
            if self.shadows:
                vis = light_visibility(self.height, w_light, spread_deg=self.spread_deg)
            else:
                vis = torch.ones((g, g), dtype=torch.float32, device=self.device)
            l = torch.as_tensor([float(x) for x in w_light], dtype=torch.float32, device=self.device)
            irr = (dot3(self._normals, l).clamp_min(0.0) / max(float(w_light[2]), 1e-6)) * vis
            self._lights[key] = (vis, float(irr.mean()))
        return self._lights[key]

    def _light_stack(self, w_lights: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Visibility maps ``(L, G * G)`` and fill irradiances ``(L,)`` of a light list (last list cached)."""
        key = w_lights.tobytes()
        if self._stack_key != key:
            maps = [self.light_maps(wl) for wl in w_lights]
            vis = torch.stack([m[0].reshape(-1) for m in maps])
            em = torch.tensor([m[1] if self.interreflection else 0.0 for m in maps], dtype=torch.float32)
            self._stack_key, self._stack = key, (vis, em)
        return self._stack

    # ----------------------------------------------------------- rendering
    @_cpu_bookkeeping
    def render(self, w_view, w_lights, texels=None) -> torch.Tensor:
        """Images for one view and several lights: ``(L, S, S, 3)`` float32 values ``pi f_r``.

        Parameters
        ----------
        w_view : sequence of 3 floats
            View direction, unit, ``z > 0``.
        w_lights : array ``(L, 3)``
            Light directions, unit, ``z > 0``.
        texels : int array ``(N,)``, optional
            Shade only these flat texels (``row * S + col``) and return ``(L, N, 3)``: the view's
            trace is shared (cached), the shading cost is proportional to ``N``.
        """
        w_lights = np.asarray(w_lights, dtype=np.float64).reshape(-1, 3)
        t = self.view_trace(w_view)
        if texels is not None:
            index = torch.as_tensor(np.asarray(texels, dtype=np.int64), device=self.device)
            t = {k: (v.index_select(0, index) if isinstance(v, torch.Tensor) else v[index.cpu().numpy()])
                 for k, v in t.items()}
        vis_maps, e_mean = self._light_stack(w_lights)
        fill = t["albedo"] * self.albedo_mean * (1.0 - t["sky"])[:, None]                 # (N, 3)
        if self.backend == "numba":
            value = torch.from_numpy(shade_view(
                w_lights, w_view, vis_maps.numpy(), t["taps"].numpy(), t["weights"].numpy(), e_mean.numpy(),
                t["n"].numpy(),
                t["albedo"].numpy(), t["alpha"].numpy(), t["f0"].numpy(), t["coat"].numpy(), fill.numpy(),
                coat_alpha=self.maps.coat_alpha, coat_f0=self.maps.coat_f0, has_coat=self.has_coat,
                grazing_cos=GRAZING_COS))
        else:
            vis_at_hit = interpolate_taps(vis_maps, t["taps"], t["weights"])  # (L, N)
            value = self._shade_torch(t, w_view, w_lights, vis_at_hit, e_mean, fill)
        s = self.out_size
        return value if texels is not None else value.reshape(len(w_lights), s, s, 3)

    def _shade_torch(self, t: dict, w_view, w_lights: np.ndarray, vis_at_hit: torch.Tensor, e_mean,
                     fill: torch.Tensor) -> torch.Tensor:
        """Values ``(L, N, 3)`` of one traced view: the reference (any device) implementation."""
        f32 = dict(dtype=torch.float32, device=self.device)
        v = torch.as_tensor([float(x) for x in w_view], **f32)
        l = torch.as_tensor(w_lights, **f32)[:, None, :]          # (L, 1, 3)
        h = v + l
        h = h / torch.sqrt(dot3(h, h))[..., None]                 # (L, 1, 3)
        n_t = t["n"].transpose(0, 1)                              # (3, N)
        cos_l = l[:, 0, :] @ n_t                                  # (L, N)
        cos_v = dot3(t["n"], v).clamp_min(GRAZING_COS)[None]      # (1, N)
        cos_h = (h[:, 0, :] @ n_t).clamp_(0.0, 1.0)               # (L, N)
        cos_d = dot3(v, h).clamp(0.0, 1.0)                        # (L, 1)
        value = layered_brdf(cos_l.clamp_min(1e-6), cos_v, cos_h, cos_d, albedo=t["albedo"][None],
                             alpha=t["alpha"][None], f0=t["f0"][None],
                             coat=t["coat"][None] if self.has_coat else None,
                             coat_alpha=self.maps.coat_alpha, coat_f0=self.maps.coat_f0)
        cos_macro = l[..., 2].clamp_min(1e-6)                     # (L, 1)
        direct = cos_l.clamp_(min=0.0).mul_(vis_at_hit).div_(cos_macro)  # (L, N)
        value.mul_(direct[..., None])
        em = e_mean.to(**f32)[:, None, None]                      # (L, 1, 1)
        return value.addcmul_(fill[None], em)
