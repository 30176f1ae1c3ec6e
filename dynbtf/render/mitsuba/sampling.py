"""Importance sampling of a synthesized BTF's outgoing directions, for the Mitsuba plugin.

The plugin's cosine sampling ignores where a glossy material reflects; this module
builds, once per model, a **sampling table**: for a grid of view directions, a 2-D
density over the **half vector** ``h = normalize(w_view + w_light)``, proportional to
the BTF's luminance times ``cos(theta_light)`` times the Jacobian of ``h -> w_light``,
averaged over the exemplar's positional features. Parametrized by the half vector,
a glossy lobe sits near the normal for every view, so tables of neighbouring views
are alike and interpolating between them keeps the lobe sharp (as microfacet
sampling does). The half vector is taken in the **view's azimuthal frame**
(``h_view = R_z(-phi_view) h``): what depends on where the light is relative to the
view -- at grazing views the region of half vectors that reflect the view above the
horizon (a crescent towards the view), and any lobe off the normal -- then sits at the
same place in the tables of views of different azimuths, so blending the tables of
the nodes around a view (45 degrees apart in azimuth) keeps it. (In the absolute frame
the tables of two azimuth nodes of a grazing view hardly overlap, and their blend
misses the actual view's lobe.)

Sampling follows Mitsuba's own ``measured`` BSDF (Dupuy and Jakob's luminance
warps: a 2-D density on ``[0, 1]^2`` per view, sampled by its marginal and
conditional CDFs, blended between view nodes ``(phi_view, theta_view)``; see
:class:`DrTableSampler`); the square maps to the hemisphere of ``h_view`` by Mitsuba's
area-preserving concentric map (``mi.warp.square_to_uniform_hemisphere``, Jacobian
``2 pi``), ``h = R_z(phi_view) h_view`` (a rotation: Jacobian 1), and ``w_light`` is
``w_view`` reflected about ``h`` (Jacobian ``4 (w_light . h)``):

    pdf(w_light) = p_square(s(h_view)) / (2 pi * 4 (w_light . h))

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

from ...conventions import spherical_to_direction
from ...errors import InputError

__all__ = ["SAMPLING_MODES", "DEFAULT_TABLE_WEIGHT", "AUTO_MIN_COSINE_VARIANCE", "SamplingTable",
           "build_sampling_table", "table_problem", "cosine_relative_variance", "DrTableSampler"]

#: Values of the plugin's ``sampling`` parameter.
SAMPLING_MODES = ("auto", "mixture", "cosine")
#: ``auto`` samples the table (``mixture``) when :func:`cosine_relative_variance` of the model's table is
#: above this, else cosine-weighted: the glossy materials that render faster to equal error with the table
#: score far above it, the rough ones that gain nothing per sample (and lose the table's cost) far below
#: (scores and renders in docs/rendering.md, ``benchmarks/bench_sampling.py``).
AUTO_MIN_COSINE_VARIANCE = 4.0
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
        Density of each cell of an ``R x R`` grid on the unit square of ``h_view`` (the half vector in
        the view's azimuthal frame; row = square y; constant on a cell), for view azimuth node ``p``
        and view elevation node ``t``.
    phi_nodes : float ``(P,)``
        View azimuths (radians, ``0 .. 2 pi``; the last node repeats the first).
    theta_nodes : float ``(T,)``
        View polar angles (radians, ``0 .. pi / 2``), ``pi/2 (1 - (1 - x)^2)`` for ``x`` uniform in
        ``[0, 1]``: denser towards grazing views.
    """

    density: np.ndarray
    phi_nodes: np.ndarray
    theta_nodes: np.ndarray

    #: The tensors of a table as a compiled material stores it (``CompiledMaterial.sampling``).
    FIELDS = ("density", "phi_nodes", "theta_nodes")

    def to_tensors(self) -> dict:
        """``{"density", "phi_nodes", "theta_nodes"}`` as CPU tensors (what a compiled material stores)."""
        import torch

        return {name: torch.from_numpy(np.ascontiguousarray(getattr(self, name))) for name in self.FIELDS}

    @classmethod
    def from_tensors(cls, tensors) -> "SamplingTable | None":
        """The table stored as :meth:`to_tensors` gave it, or None where a tensor is missing."""
        if not tensors or any(name not in tensors for name in cls.FIELDS):
            return None
        return cls(*(np.asarray(tensors[name].detach().cpu().numpy()) for name in cls.FIELDS))


def _square_to_hemisphere(points: np.ndarray) -> np.ndarray:
    """``mi.warp.square_to_uniform_hemisphere`` (concentric, area-preserving) in NumPy, float64 ``(N, 3)``."""
    mi = _mi()
    out = mi.warp.square_to_uniform_hemisphere(mi.Point2f(mi.Float(points[:, 0]), mi.Float(points[:, 1])))
    return np.stack([np.asarray(out.x), np.asarray(out.y), np.asarray(out.z)], axis=-1).astype(np.float64)


def _mi():
    from ...jit import mi_module

    return mi_module()


def _node_views(phi_nodes: np.ndarray, theta_nodes: np.ndarray, phi_count: int) -> np.ndarray:
    """Unit view directions ``(phi_count * T, 3)`` of the table's nodes (row ``p * T + t``); the
    polar angle is evaluated at most at 88 degrees (a view at the horizon reflects nothing)."""
    theta = np.degrees(np.minimum(np.asarray(theta_nodes, dtype=np.float64), math.radians(88.0)))
    theta_grid, phi_grid = np.meshgrid(theta, np.degrees(np.asarray(phi_nodes[:phi_count], dtype=np.float64)))
    return spherical_to_direction(theta_grid, phi_grid).reshape(-1, 3)


def _cell_centres(resolution: int) -> np.ndarray:
    """Centres ``(R * R, 2)`` (x, y) of the half-vector square's cells, row-major in y (the table's layout)."""
    grid = (np.arange(resolution) + 0.5) / resolution
    sy, sx = np.meshgrid(grid, grid, indexing="ij")
    return np.stack([sx.ravel(), sy.ravel()], axis=-1)


def _view_azimuth(w_view):
    """``(cos phi_view, sin phi_view)`` of views ``(..., 3)`` (NumPy) or an ``mi.Vector3f`` (Dr.Jit); ``(1, 0)``
    at the pole, where ``atan2(0, 0) = 0``."""
    if isinstance(w_view, np.ndarray):
        r = np.hypot(w_view[..., 0], w_view[..., 1])
        pole = r < 1e-12
        safe = np.where(pole, 1.0, r)
        return np.where(pole, 1.0, w_view[..., 0] / safe), np.where(pole, 0.0, w_view[..., 1] / safe)
    import drjit as dr

    r = dr.sqrt(w_view.x * w_view.x + w_view.y * w_view.y)
    pole = r < 1e-12
    inv = 1.0 / dr.select(pole, 1.0, r)
    return dr.select(pole, 1.0, w_view.x * inv), dr.select(pole, 0.0, w_view.y * inv)


def _rotate_z(w, cos_phi, sin_phi):
    """``R_z(phi) w`` for ``(..., 3)`` NumPy arrays (``cos_phi, sin_phi`` broadcast against ``w[..., 0]``) or an
    ``mi.Vector3f``; ``R_z(-phi)`` is ``_rotate_z(w, cos_phi, -sin_phi)``."""
    numpy = isinstance(w, np.ndarray)
    x, y, z = (w[..., 0], w[..., 1], w[..., 2]) if numpy else (w.x, w.y, w.z)
    rotated = (cos_phi * x - sin_phi * y, sin_phi * x + cos_phi * y, z)
    return np.stack(rotated, axis=-1) if numpy else type(w)(*rotated)


def _reflect(w_view: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``w_light`` = ``w_view`` reflected about ``half`` (broadcast ``(..., 3)``), unit, and ``w_view . half``."""
    cos_vh = (w_view * half).sum(-1, keepdims=True)
    w_light = 2.0 * cos_vh * half - w_view
    return w_light / np.linalg.norm(w_light, axis=-1, keepdims=True), cos_vh[..., 0]


def build_sampling_table(model, *, phi_bins: int = 8, theta_bins: int = 12, resolution: int = 48,
                         positions: int = 12, seed: int = 0, chunk: int = 262_144) -> SamplingTable:
    """Tabulate a model's half-vector sampling density (see the module docstring).

    Parameters
    ----------
    model : Representation
        A fitted model with ``positional_plane()`` and ``decode(features, w_view, w_light)``.
    phi_bins, theta_bins : int
        View nodes: ``phi_bins`` azimuths over ``[0, 2 pi)`` (plus the closing ``2 pi``) and
        ``theta_bins`` polar angles over ``[0, pi / 2]``, denser towards grazing (the last
        evaluated at 88 degrees).
    resolution : int
        Cells per side of the half-vector square (the density is constant on a cell: its value
        at the cell's centre, or at its highest inner probe where the centre's light direction
        is below the horizon, times the fraction of its 5 probes above it).
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

    phi_nodes = np.linspace(0.0, 2.0 * math.pi, phi_bins + 1)
    # denser towards grazing views, where the reflected half vectors' valid region changes fastest:
    # theta = pi/2 (1 - (1 - x)^2) for x uniform in [0, 1]
    theta_nodes = 0.5 * math.pi * (1.0 - (1.0 - np.linspace(0.0, 1.0, theta_bins)) ** 2)
    views = _node_views(phi_nodes, theta_nodes, phi_bins)  # (P*T, 3), row p * T + t

    # each cell is probed at its centre and at 4 inner points; the density is evaluated at the centre or,
    # where the centre's light direction is below the horizon, at the highest valid probe (so that cells
    # straddling the horizon keep a density), times the fraction of valid probes
    offsets = np.array([[0.0, 0.0], [-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]]) / resolution
    probes = _cell_centres(resolution)[:, None, :] + offsets[None]  # (R*R, 5, 2)
    half = _square_to_hemisphere(probes.reshape(-1, 2)).reshape(-1, 5, 3)  # h_view of the cells' probes
    wv = np.repeat(views, len(half), axis=0)[:, None, :]  # (P*T*R*R, 1, 3)
    # h = R_z(phi_view) h_view: each node's cells in its view's azimuthal frame
    cos_phi, sin_phi = _view_azimuth(wv)  # (P*T*R*R, 1)
    hh = _rotate_z(np.tile(half, (len(views), 1, 1)), cos_phi, sin_phi)  # (P*T*R*R, 5, 3)
    wl, cos_vh = _reflect(wv, hh)
    ok = (wl[..., 2] > 1e-4) & (cos_vh > 0)  # (N, 5)
    fraction = ok.mean(axis=1)
    pick = np.where(ok[:, 0], 0, np.argmax(np.where(ok, wl[..., 2], -np.inf), axis=1))
    rows_all = np.arange(len(wl))
    wl, hh, wv = wl[rows_all, pick], hh[rows_all, pick], wv[:, 0]
    valid = ok.any(axis=1)
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
    density = np.where(valid, np.maximum(lum, 0.0) * wl[:, 2] * jacobian * fraction, 0.0)
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


def cosine_relative_variance(table: SamplingTable) -> float:
    """How much cosine sampling misses the table's lobe: the median over the view nodes of ``Var / mean^2``.

    With cosine-weighted light directions (density ``cos(theta_light) / pi``) a one-sample
    estimate of the reflected radiance under a uniform environment is ``pi f(w_view, w_light)``,
    so its relative variance is that of the BTF's luminance ``f`` over cosine-distributed
    ``w_light``: 0 for a Lambertian material, large for a sharp lobe. On the table (whose density
    is ``f cos(theta_light)`` times the half-vector Jacobian, in square measure) the ratio
    ``density / p_cos`` with ``p_cos = 8 cos(theta_light) (w_light . h)`` (cosine sampling's
    density on the half-vector square) is ``f / 2``; the moments are sums over the cells whose
    centre reflects above the horizon.

    Parameters
    ----------
    table : SamplingTable
        From :func:`build_sampling_table`.

    Returns
    -------
    float
        The median over the ``(P - 1) x T`` view nodes (the closing azimuth node excluded).
    """
    density = np.asarray(table.density, dtype=np.float64)[:-1]
    p, t, r, _ = density.shape
    half = _square_to_hemisphere(_cell_centres(r))  # (R*R, 3): h_view
    # the cosines below do not change under a rotation about z: every view at azimuth 0, where h = h_view
    views = _node_views(np.zeros_like(table.phi_nodes), table.theta_nodes, p)  # (P*T, 3)
    w_light, cos_vh = _reflect(views[:, None], half[None])  # (P*T, R*R, 3), (P*T, R*R)
    cos_light = w_light[..., 2]
    ok = (cos_light > 1e-4) & (cos_vh > 0)
    p_cos = np.where(ok, 8.0 * cos_light * np.einsum("nkc,kc->nk", w_light, half), 1.0)
    g = np.where(ok, density.reshape(p * t, r * r), 0.0)
    ratio = g / p_cos
    cell = 1.0 / (r * r)  # area of a cell of the unit square
    mean = (ratio * p_cos).sum(axis=1) * cell  # E[g / p_cos]
    second = (ratio * ratio * p_cos).sum(axis=1) * cell  # E[(g / p_cos)^2]
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = np.where(mean > 0, second / np.maximum(mean * mean, 1e-300) - 1.0, 0.0)
    return float(np.median(np.maximum(relative, 0.0)))


class DrTableSampler:
    """A :class:`SamplingTable` as Dr.Jit code: :meth:`sample` and :meth:`pdf` of ``w_light`` given ``w_view``.

    The density of ``w_view`` is the bilinear blend, in ``(phi_view, theta_view)``, of the
    four nearest view nodes' tables (piecewise constant on the half-vector square's
    cells). :meth:`sample` draws one of the four nodes with its blend weight (using a
    uniform number ``u_node``), a row of its table from the marginal CDF and a column
    from the row's conditional CDF (binary searches), and a uniform point inside the
    cell, whose half vector ``h_view`` it rotates to the view's azimuth, so that it draws
    exactly the density :meth:`pdf` returns: ~12 gathers per
    sample and 4 per density, about a quarter of a bilinearly interpolated warp's
    work (Mitsuba's ``MarginalContinuous2D2``).

    Both take ``mi.Vector3f`` directions in the BTF's frame.
    """

    def __init__(self, table: SamplingTable) -> None:
        mi = _mi()
        density = np.asarray(table.density, dtype=np.float64)[:-1]  # the closing phi node repeats the first
        p, t, r, _ = density.shape
        self.phi_bins, self.theta_bins, self.resolution = p, t, r
        self.theta_max = float(table.theta_nodes[-1])
        rows = density.sum(axis=3)  # (P, T, R)
        total = rows.sum(axis=2)  # (P, T)
        marginal = np.concatenate([np.zeros((p, t, 1)), np.cumsum(rows, axis=2)], axis=2) / total[..., None]
        marginal[..., -1] = 1.0
        safe_rows = np.where(rows > 0, rows, 1.0)
        conditional = np.concatenate([np.zeros((p, t, r, 1)), np.cumsum(density, axis=3)], axis=3) / safe_rows[..., None]
        conditional[..., -1] = 1.0
        # density on the unit square: each cell has area 1 / R^2
        cells = density / total[..., None, None] * (r * r)
        self.marginal = mi.Float(marginal.astype(np.float32).ravel())  # (P * T, R + 1)
        self.conditional = mi.Float(conditional.astype(np.float32).ravel())  # (P * T * R, R + 1)
        self.cells = mi.Float(cells.astype(np.float32).ravel())  # (P * T * R * R)
        #: :func:`cosine_relative_variance` of the table: what ``sampling="auto"`` decides by
        self.cosine_relative_variance = cosine_relative_variance(table)

    def _nodes(self, w_view):
        """The four nodes around ``w_view``: ``[(node index mi.UInt32, weight mi.Float)]``."""
        mi = _mi()
        import drjit as dr

        phi = dr.atan2(w_view.y, w_view.x)
        phi = dr.select(phi < 0.0, phi + 2.0 * math.pi, phi)
        theta = dr.acos(dr.clip(w_view.z, -1.0, 1.0))
        x = phi * (self.phi_bins / (2.0 * math.pi))
        p0 = dr.floor(x)
        fp = dr.clip(x - p0, 0.0, 1.0)
        p0 = mi.UInt32(p0) % self.phi_bins
        p1 = (p0 + 1) % self.phi_bins
        # the nodes are uniform in x = 1 - sqrt(1 - theta / theta_max) (see build_sampling_table)
        y = (1.0 - dr.sqrt(dr.maximum(1.0 - theta / self.theta_max, 0.0))) * (self.theta_bins - 1)
        t0 = dr.minimum(mi.UInt32(dr.floor(y)), self.theta_bins - 2)
        ft = dr.clip(y - mi.Float(t0), 0.0, 1.0)
        t = self.theta_bins
        return [(p0 * t + t0, (1.0 - fp) * (1.0 - ft)), (p1 * t + t0, fp * (1.0 - ft)),
                (p0 * t + t0 + 1, (1.0 - fp) * ft), (p1 * t + t0 + 1, fp * ft)]

    def _search(self, cdf, base, u, active):
        """Largest ``k`` in ``[0, R)`` with ``cdf[base + k] <= u``, and ``u``'s fraction of that interval."""
        mi = _mi()
        import drjit as dr

        r = self.resolution
        k = dr.binary_search(0, r, lambda i: dr.gather(mi.Float, cdf, base + i, active) <= u) - 1
        k = dr.clip(mi.UInt32(k), 0, r - 1)
        lo = dr.gather(mi.Float, cdf, base + k, active)
        hi = dr.gather(mi.Float, cdf, base + k + 1, active)
        return k, dr.clip((u - lo) / dr.maximum(hi - lo, 1e-30), 0.0, 1.0)

    def sample(self, w_view, u_node, sample2, active=True):
        """A light direction (``mi.Vector3f``; below the horizon where the drawn half vector does not
        reflect the view into the upper hemisphere) drawn from the table.

        ``u_node`` (``mi.Float`` in ``[0, 1)``) picks the view node, ``sample2`` the direction.
        """
        mi = _mi()
        import drjit as dr

        nodes = self._nodes(w_view)
        node = nodes[0][0]
        acc = nodes[0][1]
        for index, weight in nodes[1:]:
            node = dr.select(u_node >= acc, index, node)
            acc = acc + weight
        r = self.resolution
        row, fy = self._search(self.marginal, node * (r + 1), sample2.y, active)
        col, fx = self._search(self.conditional, (node * r + row) * (r + 1), sample2.x, active)
        s = mi.Point2f((mi.Float(col) + fx) / r, (mi.Float(row) + fy) / r)
        cos_phi, sin_phi = _view_azimuth(w_view)
        h = _rotate_z(mi.warp.square_to_uniform_hemisphere(s), cos_phi, sin_phi)
        cos_vh = dr.dot(w_view, h)
        # a half vector facing away from the view reflects to a direction whose half vector is -h: no
        # direction of this table's density; returned below the horizon (lost, weight 0), as pdf says
        return dr.select(cos_vh > 0.0, 2.0 * cos_vh * h - w_view, mi.Vector3f(0.0, 0.0, -1.0))

    def pdf(self, w_view, w_light, active=True):
        """Solid-angle density (``mi.Float``) of drawing ``w_light`` for ``w_view``; 0 below either horizon."""
        mi = _mi()
        import drjit as dr

        s = w_view + w_light
        n2 = dr.squared_norm(s)
        h = s / dr.sqrt(dr.maximum(n2, 1e-30))
        cos_lh = dr.dot(w_light, h)
        ok = mi.Bool(active) & (n2 > 1e-12) & (h.z > 0.0) & (cos_lh > 1e-7) & (w_light.z > 0.0) & (w_view.z > 0.0)
        cos_phi, sin_phi = _view_azimuth(w_view)
        square = mi.warp.uniform_hemisphere_to_square(_rotate_z(h, cos_phi, -sin_phi))  # of h_view
        r = self.resolution
        col = dr.clip(mi.UInt32(dr.clip(square.x, 0.0, 1.0) * r), 0, r - 1)
        row = dr.clip(mi.UInt32(dr.clip(square.y, 0.0, 1.0) * r), 0, r - 1)
        p_square = mi.Float(0.0)
        for node, weight in self._nodes(w_view):
            p_square += weight * dr.gather(mi.Float, self.cells, (node * r + row) * r + col, ok)
        return dr.select(ok, p_square / (8.0 * math.pi * dr.maximum(cos_lh, 1e-7)), 0.0)
