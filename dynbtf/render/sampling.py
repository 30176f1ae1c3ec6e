"""Importance sampling of a synthesized BTF's outgoing directions, for the Mitsuba plugin.

The plugin's cosine sampling ignores where a glossy material reflects; this module
builds, once per model, a **sampling table**: for a grid of view directions, a 2-D
density over the **half vector** ``h = normalize(w_view + w_light)``, proportional to
the BTF's luminance times ``cos(theta_light)`` times the Jacobian of ``h -> w_light``,
averaged over the exemplar's positional features. Parametrized by the half vector,
a glossy lobe sits near the normal for every view, so tables of neighbouring views
are alike and interpolating between them keeps the lobe sharp (as microfacet
sampling does).

Sampling follows Mitsuba's own ``measured`` BSDF (Dupuy and Jakob's luminance
warps): the table is a ``MarginalContinuous2D2`` warp (bilinear density on
``[0, 1]^2``, linearly interpolated between the view nodes ``(phi_view,
theta_view)``); the square maps to the half-vector hemisphere by Mitsuba's
area-preserving concentric map (``mi.warp.square_to_uniform_hemisphere``, Jacobian
``2 pi``), and ``w_light`` is ``w_view`` reflected about ``h`` (Jacobian
``4 (w_light . h)``):

    pdf(w_light) = p_square(s(h)) / (2 pi * 4 (w_light . h))

The plugin mixes it with cosine sampling (one-sample multiple importance sampling
with the balance heuristic, i.e. a mixture: ``pdf = a pdf_table + (1 - a)
pdf_cosine``), so that no lobe the averaged table misses goes unsampled.

Conventions: directions in the BTF's local frame (z = normal, x = +u, y = +v);
``w_view`` is Mitsuba's ``si.wi``, ``w_light`` its ``wo``; angles in radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..conventions import spherical_to_direction
from ..errors import InputError

__all__ = ["SAMPLING_MODES", "DEFAULT_TABLE_WEIGHT", "SamplingTable", "build_sampling_table", "table_problem",
           "DrTableSampler"]

#: Values of the plugin's ``sampling`` parameter.
SAMPLING_MODES = ("cosine", "mixture")
#: Probability of drawing from the table in ``mixture`` mode (the rest: cosine).
DEFAULT_TABLE_WEIGHT = 0.75
#: Rec. 709 luminance of linear RGB.
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


@dataclass
class SamplingTable:
    """Unnormalized half-vector densities of one model.

    Attributes
    ----------
    density : float32 ``(P, T, R, R)``
        Density at the vertices of an ``R x R`` grid on the unit square (row = square y),
        for view azimuth node ``p`` and view elevation node ``t``.
    phi_nodes : float ``(P,)``
        View azimuths (radians, ``0 .. 2 pi``; the last node repeats the first).
    theta_nodes : float ``(T,)``
        View polar angles (radians, ``0 .. pi / 2``).
    """

    density: np.ndarray
    phi_nodes: np.ndarray
    theta_nodes: np.ndarray


def _square_to_hemisphere(points: np.ndarray) -> np.ndarray:
    """``mi.warp.square_to_uniform_hemisphere`` (concentric, area-preserving) in NumPy, float64 ``(N, 3)``."""
    mi = _mi()
    out = mi.warp.square_to_uniform_hemisphere(mi.Point2f(mi.Float(points[:, 0]), mi.Float(points[:, 1])))
    return np.stack([np.asarray(out.x), np.asarray(out.y), np.asarray(out.z)], axis=-1).astype(np.float64)


def _mi():
    from .drjit_ops import mi_module

    return mi_module()


def build_sampling_table(model, *, phi_bins: int = 8, theta_bins: int = 8, resolution: int = 48,
                         positions: int = 16, seed: int = 0, chunk: int = 262_144) -> SamplingTable:
    """Tabulate a model's half-vector sampling density (see the module docstring).

    Parameters
    ----------
    model : Representation
        A fitted model with ``positional_plane()`` and ``decode(features, w_view, w_light)``.
    phi_bins, theta_bins : int
        View nodes: ``phi_bins`` azimuths over ``[0, 2 pi)`` (plus the closing ``2 pi``) and
        ``theta_bins`` polar angles over ``[0, pi / 2]`` (the last evaluated at 88 degrees).
    resolution : int
        Vertices per side of the half-vector square.
    positions : int
        Positional features averaged over: texels of the exemplar plane drawn with ``seed``.
    chunk : int
        Queries per decoder call.

    Returns
    -------
    SamplingTable
        ``density = luminance(mean_k f(x_k, w_view, w_light)) * cos(theta_light) * 4 (w_light . h)``,
        clamped at 0, zero where ``w_light`` is below the horizon, floored at ``1e-4`` of each
        table's peak where it is above (so that every direction the table may produce has a density).
    """
    import torch

    if phi_bins < 1 or theta_bins < 2 or resolution < 2 or positions < 1:
        raise InputError(f"sampling table: expected phi_bins >= 1, theta_bins >= 2, resolution >= 2, positions >= 1, "
                         f"got {phi_bins}, {theta_bins}, {resolution}, {positions}")
    plane = model.positional_plane().detach().float().cpu()
    h, w, c = plane.shape
    rng = np.random.default_rng(seed)
    picks = rng.choice(h * w, size=min(positions, h * w), replace=False)
    features = plane.reshape(h * w, c)[torch.from_numpy(picks)]
    k = features.shape[0]

    grid = np.linspace(0.0, 1.0, resolution)
    sy, sx = np.meshgrid(grid, grid, indexing="ij")
    half = _square_to_hemisphere(np.stack([sx.ravel(), sy.ravel()], axis=-1))  # (R*R, 3)
    phi_nodes = np.linspace(0.0, 2.0 * math.pi, phi_bins + 1)
    theta_nodes = np.linspace(0.0, 0.5 * math.pi, theta_bins)
    theta_eval = np.minimum(theta_nodes, math.radians(88.0))
    theta_grid, phi_grid = np.meshgrid(np.degrees(theta_eval), np.degrees(phi_nodes[:phi_bins]))
    views = spherical_to_direction(theta_grid, phi_grid).reshape(-1, 3)  # (P*T, 3), row p * T + t

    wv = np.repeat(views, len(half), axis=0)  # (P*T*R*R, 3)
    hh = np.tile(half, (len(views), 1))
    cos_vh = (wv * hh).sum(-1, keepdims=True)
    wl = 2.0 * cos_vh * hh - wv
    wl /= np.linalg.norm(wl, axis=-1, keepdims=True)
    valid = (wl[:, 2] > 1e-4) & (cos_vh[:, 0] > 0)
    lum = np.zeros(len(wv))
    index = np.nonzero(valid)[0]
    model_dtype = next(iter(model.parameters())).dtype if hasattr(model, "parameters") else torch.float32
    with torch.no_grad():
        per_call = max(1, chunk // k)
        for start in range(0, len(index), per_call):
            rows = index[start:start + per_call]
            n = len(rows)
            v = torch.from_numpy(wv[rows]).to(model_dtype)
            l = torch.from_numpy(wl[rows]).to(model_dtype)
            if hasattr(model, "angular_features") and hasattr(model, "decode_with_angular"):
                # angular features once per direction pair, broadcast against the k feature vectors
                rgb = model.decode_with_angular(features.to(model_dtype)[None], model.angular_features(v, l)[:, None])
            else:
                f = features.to(model_dtype).repeat(n, 1)
                rgb = model.decode(f, v.repeat_interleave(k, 0), l.repeat_interleave(k, 0)).reshape(n, k, 3)
            rgb = rgb.double().mean(1).numpy()
            lum[rows] = rgb @ _LUMINANCE
    jacobian = 4.0 * (wl * hh).sum(-1)
    density = np.where(valid, np.maximum(lum, 0.0) * wl[:, 2] * jacobian, 0.0)
    density = density.reshape(phi_bins, theta_bins, resolution, resolution)
    valid = valid.reshape(density.shape)
    peak = density.max(axis=(2, 3), keepdims=True)
    floor = np.where(peak > 0, 1e-4 * peak, 1.0)
    density = np.where(valid, np.maximum(density, floor), 0.0)
    density = np.concatenate([density, density[:1]], axis=0)  # phi = 2 pi closes the circle
    return SamplingTable(density.astype(np.float32), phi_nodes, theta_nodes)


def table_problem(table) -> str | None:
    """Why ``table`` cannot be sampled (``None`` if it can): wrong shape, non-finite, negative or empty slices."""
    density = getattr(table, "density", None)
    if density is None or np.ndim(density) != 4:
        return "the sampling table is missing or not a 4-D density"
    density = np.asarray(density)
    p, t = len(table.phi_nodes), len(table.theta_nodes)
    if density.shape[:2] != (p, t) or min(density.shape[2:]) < 2:
        return f"the sampling table's shape {density.shape} does not match its {p} x {t} view nodes"
    if not np.isfinite(density).all():
        return "the sampling table has non-finite values (the decoder returned NaN or inf)"
    if (density < 0).any():
        return "the sampling table has negative densities"
    if not (density.sum(axis=(2, 3)) > 0).all():
        return "the sampling table has a view with zero density everywhere"
    return None


class DrTableSampler:
    """A :class:`SamplingTable` as Dr.Jit code: :meth:`sample` and :meth:`pdf` of ``w_light`` given ``w_view``.

    Both take ``mi.Vector3f`` directions in the BTF's frame; they agree: the pdf
    :meth:`sample` implies is the one :meth:`pdf` returns for its direction.
    """

    def __init__(self, table: SamplingTable) -> None:
        mi = _mi()
        self.warp = mi.MarginalContinuous2D2(np.ascontiguousarray(table.density, dtype=np.float32),
                                             [table.phi_nodes.tolist(), table.theta_nodes.tolist()], normalize=True)

    @staticmethod
    def _param(w_view):
        mi = _mi()
        import drjit as dr

        phi = dr.atan2(w_view.y, w_view.x)
        phi = dr.select(phi < 0.0, phi + 2.0 * math.pi, phi)
        theta = dr.acos(dr.clip(w_view.z, -1.0, 1.0))
        return mi.Vector2f(phi, theta)

    def sample(self, w_view, sample2, active=True):
        """A light direction (``mi.Vector3f``, may fall below the horizon) drawn from the table."""
        mi = _mi()
        import drjit as dr

        s, _ = self.warp.sample(sample2, self._param(w_view), active)
        h = mi.warp.square_to_uniform_hemisphere(s)
        return 2.0 * dr.dot(w_view, h) * h - w_view

    def pdf(self, w_view, w_light, active=True):
        """Solid-angle density (``mi.Float``) of drawing ``w_light`` for ``w_view``; 0 below either horizon."""
        mi = _mi()
        import drjit as dr

        s = w_view + w_light
        n2 = dr.squared_norm(s)
        h = s / dr.sqrt(dr.maximum(n2, 1e-30))
        cos_lh = dr.dot(w_light, h)
        ok = mi.Bool(active) & (n2 > 1e-12) & (h.z > 0.0) & (cos_lh > 1e-7) & (w_light.z > 0.0) & (w_view.z > 0.0)
        p_square = self.warp.eval(mi.warp.uniform_hemisphere_to_square(h), self._param(w_view), ok)
        return dr.select(ok, p_square / (8.0 * math.pi * dr.maximum(cos_lh, 1e-7)), 0.0)
