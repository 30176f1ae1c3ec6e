"""Fast preview: an infinite flat surface with a (synthesized) BTF, one light, a pinhole camera.

No Mitsuba, no path tracing: every pixel's camera ray is intersected with the
plane ``z = 0`` analytically, and the BTF is queried once per pixel sample with
the exact view and light directions. This is for quick looks and for the report;
:mod:`dynbtf.render.mitsuba.bsdf` is the renderer for real scenes.

Geometry and units
------------------
* World space = the surface's local frame: the plane is ``z = 0`` with normal
  ``+z``; world ``x`` and ``y`` **are** the BTF's ``u`` and ``v`` (one world
  unit = one exemplar repeat), so a camera 3 units above the plane sees a few
  repeats, one 50 units away at a grazing angle sees hundreds.
* Pixel values are ``value * cos(theta_light) * E``: the BTF value (which
  excludes the cosine, :mod:`dynbtf.conventions`) times the cosine times the
  normal irradiance ``E`` of the light at the point (``E = irradiance`` for a
  :class:`DirectionalLight`, ``intensity / r^2`` for a :class:`PointLight`).
  A white Lambertian surface lit head-on by ``E = 1`` shows 1, like the
  measured BTF images; multiply by ``1 / pi`` for radiance.
* Pixels whose ray misses the plane (above the horizon) get ``background``.
* Image row 0 is the top of the picture; ``up`` points towards row 0.

Examples
--------
>>> import numpy as np
>>> class White:                                   # a white Lambertian "BTF"
...     def eval(self, uv, w_view, w_light):
...         return np.ones(uv.shape[:-1] + (3,), dtype=np.float32)
>>> cam = PinholeCamera(origin=(0, 0, 2), target=(0, 0, 0), up=(0, 1, 0), fov=30)
>>> img = render_preview(White(), cam, DirectionalLight((0, 0, 1), 1.0), resolution=(4, 4))
>>> float(img.min()), float(img.max())
(1.0, 1.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ["PinholeCamera", "DirectionalLight", "PointLight", "render_preview", "plane_footprint", "grazing_camera", "top_camera"]


def _unit(v, name):
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(v).all() or n == 0.0:
        raise InputError(f"{name}: expected a finite non-zero 3-vector, got {v.tolist()}")
    return v / n


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera.

    Parameters
    ----------
    origin, target : 3-vectors
        Eye position and the point it looks at (world = surface frame, uv units).
    up : 3-vector
        Approximate up direction of the image.
    fov : float
        Vertical field of view in degrees (0 < fov < 180).
    """

    origin: tuple = (0.0, -4.0, 2.0)
    target: tuple = (0.0, 0.0, 0.0)
    up: tuple = (0.0, 0.0, 1.0)
    fov: float = 40.0

    def frame(self):
        """The camera's origin ``(3,)``, unit ``forward``, ``right`` and ``up`` 3-vectors, and
        ``tan(fov / 2)``: a ray's unnormalized direction is ``forward + x right + y up``."""
        if not 0.0 < float(self.fov) < 180.0:
            raise InputError(f"camera fov: expected degrees in (0, 180), got {self.fov}")
        o = np.asarray(self.origin, dtype=np.float64).reshape(3)
        forward = _unit(np.asarray(self.target, dtype=np.float64) - o, "camera target - origin")
        right = np.cross(forward, _unit(self.up, "camera up"))
        if np.linalg.norm(right) < 1e-9:
            raise InputError("camera up: must not be parallel to the viewing direction")
        right /= np.linalg.norm(right)
        return o, forward, right, np.cross(right, forward), math.tan(math.radians(self.fov) / 2.0)

    def rays(self, height: int, width: int, jitter: np.ndarray | None = None):
        """Ray origins ``(3,)`` and unit directions ``(height, width, 3)`` through pixel centres (+ jitter).

        ``jitter`` ``(2,)`` in pixels, in ``[-0.5, 0.5)``, shifts every ray (for supersampling); ``(height,
        width, 2)`` shifts each pixel's ray on its own.
        """
        o, forward, right, true_up, half_h = self.frame()
        half_w = half_h * width / height
        jitter = np.zeros(2) if jitter is None else np.asarray(jitter, dtype=np.float64)
        jx, jy = (jitter[0], jitter[1]) if jitter.ndim == 1 else (jitter[..., 0], jitter[..., 1])
        xs = ((np.arange(width)[None, :] + 0.5 + jx) / width * 2.0 - 1.0) * half_w
        ys = (1.0 - (np.arange(height)[:, None] + 0.5 + jy) / height * 2.0) * half_h
        xs, ys = np.broadcast_to(xs, (height, width)), np.broadcast_to(ys, (height, width))
        d = forward + xs[..., None] * right + ys[..., None] * true_up
        return o, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def pixel_steps(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """How the (unnormalized) ray direction ``forward + x right + y up`` of :meth:`rays` changes
        per pixel along the image's columns and rows: two 3-vectors (ray differentials)."""
        _, _, right, true_up, half_h = self.frame()
        return right * (2.0 * half_h / height), -true_up * (2.0 * half_h / height)


@dataclass(frozen=True)
class DirectionalLight:
    """A distant light: ``direction`` points **towards** the light; ``irradiance`` is its normal irradiance E."""

    direction: tuple = (0.3, -0.5, 0.8)
    irradiance: float = 1.0

    def at(self, points: np.ndarray):
        w = _unit(self.direction, "light direction")
        return np.broadcast_to(w, points.shape).copy(), np.full(points.shape[:-1], float(self.irradiance))


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light at ``position``: normal irradiance ``intensity / r^2``."""

    position: tuple = (1.0, -1.0, 2.0)
    intensity: float = 5.0

    def at(self, points: np.ndarray):
        p = np.asarray(self.position, dtype=np.float64).reshape(3)
        if p[2] <= 0.0:
            raise InputError(f"point light position: must be above the plane (z > 0), got {p.tolist()}")
        to_light = p - points
        r2 = (to_light ** 2).sum(-1)
        return to_light / np.sqrt(r2)[..., None], float(self.intensity) / r2


def _stratified_jitter(spp: int) -> np.ndarray:
    """``spp`` sub-pixel offsets in ``[-0.5, 0.5)^2`` on a deterministic ``n x m`` grid."""
    n = int(math.ceil(math.sqrt(spp)))
    m = int(math.ceil(spp / n))
    g = [((i + 0.5) / n - 0.5, (j + 0.5) / m - 0.5) for j in range(m) for i in range(n)]
    return np.asarray(g[:spp], dtype=np.float64)


def plane_footprint(camera: PinholeCamera, directions: np.ndarray, height: int, width: int, spp: int = 1
                    ) -> np.ndarray:
    """Footprint (uv units, :func:`dynbtf.infinite_btf.footprint_width`: the longer pixel axis) of pixel
    samples on the plane ``z = 0``.

    ``directions (..., 3)`` are unit rays of :meth:`PinholeCamera.rays` that hit the plane. The
    hit point ``p = o - o_z d / d_z`` moves per pixel by ``t (dD - d dD_z / d_z)`` (ray differentials
    transferred to the plane, ``t`` the hit distance, ``dD`` the per-pixel change of the ray direction
    over its length); with ``spp`` samples per pixel each covers ``1 / sqrt(spp)`` of the pixel's side.
    """
    from ..infinite_btf import footprint_width

    origin, forward, _, _, _ = camera.frame()
    o_z = float(origin[2])
    step_x, step_y = camera.pixel_steps(height, width)
    # |D| of the unnormalized direction: D = d |D| and D . forward = 1
    length = 1.0 / (directions @ forward)
    t = -o_z / directions[..., 2]
    derivatives = []
    for step in (step_x, step_y):
        dd = step[None, :] / length[..., None]
        dp = t[..., None] * (dd - directions * (dd[..., 2:3] / directions[..., 2:3]))
        derivatives.append(dp[..., :2])
    return footprint_width(*derivatives) / math.sqrt(spp)


def render_preview(btf, camera: PinholeCamera, light, *, resolution=(256, 256), spp: int = 1,
                   background=(0.0, 0.0, 0.0), progress: bool = False, filtered: bool = False,
                   jitter_seed: int | None = None) -> np.ndarray:
    """Render the infinite plane ``z = 0`` covered by ``btf``.

    Parameters
    ----------
    btf : object with ``eval(uv, w_view, w_light)``
        E.g. a :class:`dynbtf.infinite_btf.SynthesizedBTF`, or any object whose
        ``eval`` takes float64 NumPy arrays ``uv (N, 2)``, ``w_view, w_light (N, 3)``
        (or torch tensors: NumPy inputs are converted when the call needs tensors)
        and returns ``(N, 3)`` linear RGB values excluding cos(theta_light).
    camera : PinholeCamera
    light : DirectionalLight or PointLight
    resolution : (height, width)
    spp : int
        Samples per pixel on a stratified sub-pixel grid (box filter), >= 1.
    background : RGB
        Colour of pixels whose ray misses the plane.
    progress : bool
        Show a tqdm bar over the ``spp`` passes.
    filtered : bool, default False
        Footprint queries: each sample passes ``footprint=`` (its share of the pixel on the
        plane, :func:`plane_footprint`) to ``btf.eval``, so that one sample per pixel shows the
        filtered appearance instead of aliased texels (far away and at grazing angles).
    jitter_seed : int, optional
        Each pixel's samples at independent random positions in the pixel (seeded) instead of
        the stratified grid shared by all pixels: a stochastic box filter.

    Returns
    -------
    float32 ``(height, width, 3)`` linear RGB (see the module docstring for units).
    """
    try:
        height, width = (int(resolution[0]), int(resolution[1]))
    except (TypeError, ValueError, IndexError):
        raise InputError(f"resolution: expected (height, width), got {resolution!r}") from None
    if height < 1 or width < 1:
        raise InputError(f"resolution: expected positive (height, width), got {resolution!r}")
    if int(spp) < 1:
        raise InputError(f"spp: expected a positive number of samples per pixel, got {spp}")
    if not (hasattr(light, "at")):
        raise InputError(f"light: expected a DirectionalLight or PointLight, got {type(light).__name__}")
    if float(np.asarray(camera.origin, dtype=np.float64).reshape(3)[2]) <= 0.0:
        raise InputError(f"camera origin: must be above the plane (z > 0), got {list(camera.origin)}")
    background = np.asarray(background, dtype=np.float32).reshape(3)
    acc = np.zeros((height, width, 3), dtype=np.float64)
    from ..progress import progress_bar
    rng = None if jitter_seed is None else np.random.default_rng(jitter_seed)
    for jitter in progress_bar(_stratified_jitter(int(spp)), desc="preview", unit="pass", disable=not progress):
        if rng is None:
            o, d = camera.rays(height, width, jitter)
        else:
            o, d = camera.rays(height, width, rng.random((height, width, 2)) - 0.5)
        hit = d[..., 2] < -1e-12
        t = np.where(hit, -o[2] / np.where(hit, d[..., 2], -1.0), 0.0)
        points = (o + t[..., None] * d)[hit]
        w_light, irradiance = light.at(points)
        w_view = -d[hit]
        cos_l = w_light[:, 2]
        lit = cos_l > 0.0
        rgb = np.zeros((int(hit.sum()), 3), dtype=np.float64)
        if lit.any():
            uv = points[lit][:, :2]
            footprint = plane_footprint(camera, d[hit][lit], height, width, int(spp)) if filtered else None
            value = _eval(btf, uv, w_view[lit], w_light[lit], footprint)
            rgb[lit] = value * (cos_l[lit] * irradiance[lit])[:, None]
        img = np.empty((height, width, 3), dtype=np.float64)
        img[:] = background
        img[hit] = rgb
        acc += img
    return (acc / int(spp)).astype(np.float32)


def _eval(btf, uv, w_view, w_light, footprint=None) -> np.ndarray:
    """Call ``btf.eval`` with NumPy or (on TypeError/AttributeError) torch inputs; return float64 ``(N, 3)``.

    ``footprint`` (N,) is passed only when given (BTFs without footprint queries work unfiltered).
    """
    extra = {} if footprint is None else {"footprint": footprint}
    try:
        out = btf.eval(uv, w_view, w_light, **extra)
    except (TypeError, AttributeError):
        import torch

        extra = {k: torch.from_numpy(v) for k, v in extra.items()}
        out = btf.eval(torch.from_numpy(uv), torch.from_numpy(w_view).float(), torch.from_numpy(w_light).float(),
                       **extra)
    if hasattr(out, "detach"):
        out = out.detach().cpu().numpy()
    return np.asarray(out, dtype=np.float64).reshape(-1, 3)


def grazing_camera(distance: float = 6.0, height: float = 0.6, fov: float = 40.0, center=(0.0, 0.0)) -> PinholeCamera:
    """A camera low over the plane looking at ``center`` (uv) from ``distance`` away: repetition shows here."""
    cx, cy = float(center[0]), float(center[1])
    return PinholeCamera(origin=(cx, cy - distance, height), target=(cx, cy, 0.0), up=(0.0, 0.0, 1.0), fov=fov)


def top_camera(extent: float = 1.0, center=(0.5, 0.5), distance: float = 10.0) -> PinholeCamera:
    """A camera straight above ``center`` whose vertical field of view spans ``extent`` uv units.

    Seen from above, ``+u`` runs to the right and ``+v`` upwards in the image
    (a physical view; texture arrays of :mod:`dynbtf.conventions` store row 0 = ``v = 0`` at the top,
    so they appear flipped vertically relative to it).
    """
    cx, cy = float(center[0]), float(center[1])
    fov = math.degrees(2.0 * math.atan(extent / 2.0 / distance))
    return PinholeCamera(origin=(cx, cy, distance), target=(cx, cy, 0.0), up=(0.0, 1.0, 0.0), fov=fov)
