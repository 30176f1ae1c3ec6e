"""Layered materials: several synthesized BTFs on one surface, the one that shows chosen per point by a mask.

``LayeredBTF([worn, new], mask, width=0.05).eval(uv, w_view, w_light)`` answers like a
:class:`~dynbtf.infinite_btf.SynthesizedBTF`, at any ``uv`` and per point, with no pre-generated texture:
layer 0 where the mask is below one half, layer 1 where it is above. Two layers, any two fitted materials
(each with its own method, seed and scale).

The boundary
------------
The boundary is not a cross-fade of the two materials. Within ``width`` (uv units) of the mask's 0.5
contour, each point shows the layer that stands **higher** there once a bias that grows with the distance
to the contour is added:

    score = (h_1 - h_0) + d / width,   d the signed distance to the contour (positive on layer 1's side)

so the raised parts of one material (a brick's face, the top of a fibre) reach into the other's side and its
hollows give way first: the boundary follows the materials' own structure. ``h`` is each layer's
**height** at the point, in ``[0, 1]``: the rank, among the exemplar's texels, of the relief height where the
model has one (``triple-parallax``), else of the luminance of its synthesized features under normal view and
light (a linear map of the features fitted to the decoded exemplar); :class:`LayerHeight`. Ranks make the band
the same for any two materials: the other layer reaches exactly ``width`` into a side. The layer whose
score sign wins is shown; ``softness`` (height units) blends the two linearly over ``|score| <
softness`` (0: a hard edge, each point from one material). Beyond ``width`` from the contour only one layer
is evaluated, so away from boundaries a query costs one material's evaluation (plus the mask).

``d`` comes from the mask: ``(m - 0.5) / |grad m|``, the distance to the contour of a mask that is locally
linear (exact for a linear ramp, and for any mask at the contour itself).

Masks
-----
A mask is any object with ``value(uv) -> (N,) float64 in [0, 1]`` and ``gradient(uv) -> (N, 2)`` for
``uv (N, 2)`` float64 (uv units):

* :class:`ImageMask` -- an image over ``size`` x ``size`` uv units, bilinear, repeated or clamped;
* :class:`NoiseMask` -- value noise with a ``scale`` (uv units per cell) and a ``contrast``, seeded, from an
  integer lattice hash (:mod:`dynbtf.synthesis.hash`): the same value at any distance from the origin.

Footprint queries (``footprint=``) evaluate each layer with its footprint and weigh them by the share of the
footprint each layer covers (:func:`footprint_weight`): the point query's choice for a footprint within one texel,
the expected share of layer 1 over a footprint of many texels (the heights of two materials are independent ranks,
so their difference follows a known law), and a mix of the two in between. A distant boundary is then a filtered
transition, not the aliased pattern of a choice made at each pixel's centre.

Conventions as everywhere in dynbtf: ``uv`` in the user's units (each layer's ``scale`` maps it to exemplar
repeats), unit directions in the local frame, linear RGB excluding ``cos(theta_light)``.

Example
-------
>>> import numpy as np
>>> from dynbtf.infinite_btf import SynthesizedBTF
>>> from dynbtf.synthesized import synthesized_btf
>>> from dynbtf.representations.triple_plane import TriplePlane
>>> a = synthesized_btf(TriplePlane(16, 16, seed=1), "hist", scale=4.0)
>>> b = synthesized_btf(TriplePlane(16, 16, seed=2), "hist", scale=4.0)
>>> half = ImageMask(np.array([[0.0, 1.0]]), size=2.0, wrap="clamp")   # left half layer 0, right half layer 1
>>> layered = LayeredBTF([a, b], half, width=0.1)
>>> uv = np.array([[0.2, 0.3], [1.8, 0.3]])
>>> w = np.array([[0.0, 0.0, 1.0]] * 2)
>>> np.allclose(layered.eval(uv, w, w), np.stack([a.eval(uv[:1], w[:1], w[:1])[0], b.eval(uv[1:], w[1:], w[1:])[0]]))
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch

from .conventions import spherical_to_direction
from .errors import InputError, positive_number
from .infinite_btf import SynthesizedBTF, flat_image
from .synthesis.base import check_footprint, check_uv
from .synthesis.hash import MASK32, hash_vertex

__all__ = ["LayeredBTF", "ImageMask", "NoiseMask", "LayerHeight", "layer_height_map", "layer_height", "mask_from_spec",
           "HEIGHT_TABLE", "point_weight", "area_weight", "footprint_weight", "layer_weight"]


# ------------------------------------------------------------------------------------------------ masks
class ImageMask:
    """A mask image ``(H, W)`` in ``[0, 1]`` over ``size`` x ``size`` uv units (row 0 at ``v = 0``, column 0 at
    ``u = 0``; texel centres at half-texel offsets), fetched bilinearly; ``wrap``: ``"repeat"`` (the image tiles
    the plane) or ``"clamp"`` (its edge texels extend it)."""

    def __init__(self, image, size: float = 1.0, wrap: str = "repeat") -> None:
        try:
            image = np.array(image, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise InputError(f"mask: expected an image of numbers (H, W), got {type(image).__name__} ({e})") from None
        if image.ndim == 3 and image.shape[-1] in (1, 3, 4):
            image = image[..., :3].mean(-1) if image.shape[-1] >= 3 else image[..., 0]
        if image.ndim != 2 or image.size == 0:
            raise InputError(f"mask: expected an image of shape (H, W) (or H x W x 1/3/4), got {image.shape}")
        if not np.isfinite(image).all() or image.min() < 0.0 or image.max() > 1.0:
            raise InputError("mask: expected values in [0, 1] (finite); scale the image first")
        if wrap not in ("repeat", "clamp"):
            raise InputError(f"mask wrap: expected 'repeat' or 'clamp', got {wrap!r}")
        self.image, self.size, self.wrap = image, positive_number("mask size", size, "uv units"), wrap
        self.cell = self.size / max(image.shape)

    def value(self, uv: np.ndarray) -> np.ndarray:
        """The mask at ``uv (N, 2)`` float64: ``(N,)`` in ``[0, 1]``."""
        return self.value_and_gradient(uv)[0]

    def gradient(self, uv: np.ndarray) -> np.ndarray:
        """``d value / d uv`` at ``uv (N, 2)``: ``(N, 2)`` per uv unit (of the bilinear interpolant)."""
        return self.value_and_gradient(uv)[1]

    def value_and_gradient(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`value` and :meth:`gradient` in one pass (one compiled loop over the points)."""
        uv = np.ascontiguousarray(uv, dtype=np.float64)
        value, gradient = np.empty(len(uv)), np.empty((len(uv), 2))
        _image_mask_kernel(uv, self.image, float(self.size), self.wrap == "repeat", value, gradient)
        return value, gradient



@numba.njit(cache=True, nogil=True, parallel=True)
def _image_mask_kernel(uv, image, size, repeat, value, gradient):
    """Bilinear value and gradient of ``image`` over ``size`` uv units at each ``uv`` (see :class:`ImageMask`).

    Repeat: ``uv mod size`` first (a remainder: exact, the same texel coordinates at any distance), texels
    wrap; clamp: edge texels extend the image."""
    h, w = image.shape
    sx, sy = w / size, h / size
    for i in numba.prange(uv.shape[0]):
        u, v = uv[i, 0], uv[i, 1]
        if repeat:
            u, v = np.mod(u, size), np.mod(v, size)
        x = u / size * w - 0.5
        y = v / size * h - 0.5
        xf, yf = math.floor(x), math.floor(y)
        fx, fy = x - xf, y - yf
        x0, y0 = np.int64(xf), np.int64(yf)
        if repeat:
            c0, c1, r0, r1 = x0 % w, (x0 + 1) % w, y0 % h, (y0 + 1) % h
        else:
            c0, c1 = min(max(x0, 0), w - 1), min(max(x0 + 1, 0), w - 1)
            r0, r1 = min(max(y0, 0), h - 1), min(max(y0 + 1, 0), h - 1)
        a, b, c, d = image[r0, c0], image[r0, c1], image[r1, c0], image[r1, c1]
        value[i] = (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy
        gradient[i, 0] = ((b - a) * (1 - fy) + (d - c) * fy) * sx
        gradient[i, 1] = ((c - a) * (1 - fx) + (d - b) * fx) * sy


def contour_distance(value: np.ndarray, gradient: np.ndarray) -> np.ndarray:
    """The signed distance ``(N,)`` (uv units) to a mask's 0.5 contour from its value ``(N,)`` and gradient ``(N, 2)``:
    ``(m - 0.5) / |grad m|`` (exact for a locally linear mask), 0 on the contour, +-inf where the mask is flat."""
    return _contour_distance_kernel(np.ascontiguousarray(value, dtype=np.float64),
                                    np.ascontiguousarray(gradient, dtype=np.float64))


@numba.njit(cache=True, nogil=True, parallel=True)
def _contour_distance_kernel(value, gradient):
    out = np.empty(value.shape[0])
    for i in numba.prange(value.shape[0]):
        m = value[i] - 0.5
        slope = math.sqrt(gradient[i, 0] * gradient[i, 0] + gradient[i, 1] * gradient[i, 1])
        out[i] = 0.0 if m == 0.0 else m / max(slope, 1e-300)
    return out


class NoiseMask:
    """Value noise in ``[0, 1]``: a random value per integer lattice vertex (hashed with ``seed``: the same at any
    distance from the origin), smoothstep-interpolated over cells of ``scale`` uv units, then
    ``0.5 + contrast * (n - 0.5)`` clipped to ``[0, 1]`` (``contrast`` > 1 sharpens the regions)."""

    def __init__(self, scale: float = 1.0, contrast: float = 2.0, seed: int = 0) -> None:
        self.scale = positive_number("mask scale", scale, "uv units per noise cell")
        self.contrast = positive_number("mask contrast", contrast, "gain around 0.5")
        if int(seed) != seed or seed < 0:
            raise InputError(f"mask seed: expected a non-negative integer, got {seed!r}")
        self.seed, self.cell = int(seed), self.scale

    def _corners(self, uv: np.ndarray):
        p = uv / self.scale
        i = np.floor(p)
        f = p - i
        i = i.astype(np.int64)
        vertex = [[hash_vertex(i[:, 0] + dx, i[:, 1] + dy, self.seed) / float(MASK32) for dx in (0, 1)]
                  for dy in (0, 1)]
        return vertex, f

    def _noise(self, uv):
        ((a, b), (c, d)), f = self._corners(uv)
        s = f * f * (3 - 2 * f)
        ds = 6 * f * (1 - f) / self.scale
        n = (a * (1 - s[:, 0]) + b * s[:, 0]) * (1 - s[:, 1]) + (c * (1 - s[:, 0]) + d * s[:, 0]) * s[:, 1]
        gx = ((b - a) * (1 - s[:, 1]) + (d - c) * s[:, 1]) * ds[:, 0]
        gy = ((c - a) * (1 - s[:, 0]) + (d - b) * s[:, 0]) * ds[:, 1]
        return n, np.stack([gx, gy], -1)

    def value(self, uv: np.ndarray) -> np.ndarray:
        """The mask at ``uv (N, 2)`` float64: ``(N,)`` in ``[0, 1]``."""
        return self.value_and_gradient(uv)[0]

    def gradient(self, uv: np.ndarray) -> np.ndarray:
        """``d value / d uv`` at ``uv (N, 2)``: ``(N, 2)`` per uv unit."""
        return self.value_and_gradient(uv)[1]

    def value_and_gradient(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`value` and :meth:`gradient` in one pass."""
        n, g = self._noise(uv)
        inside = np.abs(self.contrast * (n - 0.5)) < 0.5  # where the clip is flat, so is the mask
        return np.clip(0.5 + self.contrast * (n - 0.5), 0.0, 1.0), g * (self.contrast * inside)[:, None]


def mask_from_spec(spec: str, size: float = 1.0, wrap: str = "repeat"):
    """The mask a command line names: ``noise`` or ``noise:SCALE[,CONTRAST[,SEED]]`` (:class:`NoiseMask`), else an
    image file (:class:`ImageMask` over ``size`` uv units). A PNG or JPEG is read as painted: its stored grey
    levels over the maximum (a 50% grey is 0.5); an EXR's values as they are; colour images by their mean."""
    if spec == "noise" or spec.startswith("noise:"):
        fields = [x for x in spec[len("noise:"):].split(",") if x.strip()] if ":" in spec else []
        if len(fields) > 3:
            raise InputError(f"--mask {spec!r}: expected noise:SCALE[,CONTRAST[,SEED]]")
        try:
            scale = float(fields[0]) if fields else 1.0
            contrast = float(fields[1]) if len(fields) > 1 else 2.0
            seed = int(fields[2]) if len(fields) > 2 else 0
        except ValueError:
            raise InputError(f"--mask {spec!r}: expected noise:SCALE[,CONTRAST[,SEED]] with numbers") from None
        return NoiseMask(scale, contrast, seed)
    from .io import load_painted_image

    return ImageMask(load_painted_image(spec, "--mask"), size=size, wrap=wrap)


# ------------------------------------------------------------------------------------------------ heights
#: Entries of a layer's height table (:class:`LayerHeight`).
HEIGHT_TABLE = 256


@dataclass(frozen=True)
class LayerHeight:
    """How :class:`LayeredBTF` reads a layer's height from its synthesized features ``f (N, C)``.

    The raw height is ``f @ weights``; the height is its **rank** among the exemplar's texels, in ``[0, 1]``:
    the share of the exemplar lower than it (its empirical CDF, linear between the exemplar's distinct values),
    tabulated at :data:`HEIGHT_TABLE` raw heights evenly spaced from the exemplar's lowest (``low``) to its
    highest (``high``) and read linearly (:meth:`__call__`; every backend reads the same table the same way).
    Ranks make ``width`` mean the same for any two materials: where the two layers' heights are independent,
    the other layer shows at a distance ``d`` into one side with probability ``(1 - |d| / width)^2 / 2``,
    reaching 0 at the band's edge.
    """

    weights: np.ndarray  # (C,) float64
    low: float
    high: float
    table: np.ndarray  # (HEIGHT_TABLE,) float64, non-decreasing, in [0, 1]

    def __call__(self, raw) -> np.ndarray:
        """Heights in ``[0, 1]`` of raw heights ``f @ weights`` (any shape, float64)."""
        last = len(self.table) - 1
        pos = np.clip((np.asarray(raw, dtype=np.float64) - self.low) * (last / (self.high - self.low)), 0.0, last)
        i = np.minimum(np.floor(pos), last - 1).astype(np.int64)
        t = pos - i
        return self.table[i] + t * (self.table[i + 1] - self.table[i])


def layer_height(btf: SynthesizedBTF, height_of: LayerHeight, uv: torch.Tensor) -> tuple[np.ndarray, torch.Tensor | None]:
    """A layer's height (``(N,)`` float64 in ``[0, 1]``, :class:`LayerHeight`) at ``uv (N, 2)`` (the layer's ``uv``
    units, float64), and its latent values there where its ``eval`` takes them back (else None).

    The height is read from the layer's synthesized features: a relief's height channel alone where the model has
    one (``height_of.weights`` is one-hot on it), else ``features @ height_of.weights``."""
    weights = height_of.weights
    latent = None
    if getattr(btf.model, "extra_positional_channels", 0):  # a relief's height channel: that channel alone
        index = int(np.argmax(weights))  # (layer_height_map's weights are one-hot on it)
        points = check_uv(uv, scale=btf.scale).to(torch.float64) * btf.scale
        height = btf.synthesizer.channel(points.to(btf.device), index).double().cpu().numpy()
    else:
        if btf.takes_latent:  # kept: the colour of a band point decodes the values its height came from
            latent = btf.latent(uv)
            f = btf.synthesizer.features_from_latent(latent.to(btf.device))
        else:
            f = btf.features(uv)
        height = f.double().cpu().numpy() @ weights
    return height_of(height), latent


def layer_height_map(btf: SynthesizedBTF) -> LayerHeight:
    """How :class:`LayeredBTF` reads a layer's height (:class:`LayerHeight`).

    The raw height: a relief model's height channel where it has one (its last positional channel); else the
    luminance of the exemplar decoded under normal view and light, regressed linearly on the exemplar's features
    (least squares). The height is the raw height's rank among the exemplar's texels."""
    model = btf.model
    plane = model.positional_plane().detach().to("cpu", torch.float64)
    rows = plane.reshape(-1, plane.shape[-1])
    if getattr(model, "extra_positional_channels", 0):
        weights = torch.zeros(rows.shape[1], dtype=torch.float64)
        weights[-1] = 1.0
    else:
        with torch.no_grad():
            w = torch.as_tensor(spherical_to_direction(np.array(0.0), np.array(0.0)), dtype=model.positional_plane().dtype)
            w = w.expand(rows.shape[0], 3).to(model.positional_plane().device)
            rgb = model.decode(model.positional_plane().detach().reshape(rows.shape[0], -1), w, w)
        luminance = (rgb.double().cpu() @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64))
        design = torch.cat([rows, torch.ones(rows.shape[0], 1, dtype=torch.float64)], 1)
        solution = torch.linalg.lstsq(design, luminance[:, None]).solution[:, 0]
        weights = solution[:-1]  # (the intercept drops out: ranks do not depend on it)
    heights = (rows @ weights).numpy()
    values, counts = np.unique(heights, return_counts=True)
    low, high = float(values[0]), float(values[-1])
    if not high > low:  # a flat exemplar: every point at the middle rank
        return LayerHeight(weights.numpy(), low, low + 1.0, np.full(HEIGHT_TABLE, 0.5))
    ranks = (np.cumsum(counts) - 0.5 * counts) / len(heights)  # mid-ranks of the distinct values
    grid = np.linspace(low, high, HEIGHT_TABLE)
    return LayerHeight(weights.numpy(), low, high, np.interp(grid, values, ranks))


# ------------------------------------------------------------------------------------------------ layer 1's weight
def point_weight(score: np.ndarray, softness: float) -> np.ndarray:
    """Layer 1's weight at a point from its score ``(h_1 - h_0) + d / width`` (any shape, float64): 1 where the score
    is positive, 0 where it is negative, a linear ramp over ``|score| < softness`` if ``softness > 0``."""
    if softness > 0:
        return np.clip(0.5 + score / (2 * softness), 0.0, 1.0)
    return (score > 0).astype(np.float64)


def _difference_cdf(x: np.ndarray) -> np.ndarray:
    """``P(h_1 - h_0 <= x)`` for independent heights uniform in ``[0, 1]`` (ranks): the triangular law on [-1, 1]."""
    c = np.clip(x, -1.0, 1.0)
    return np.where(c < 0.0, 0.5 * (c + 1.0) ** 2, 1.0 - 0.5 * (1.0 - c) ** 2)


def _difference_cdf_integral(x: np.ndarray) -> np.ndarray:
    """The integral of :func:`_difference_cdf` from ``-inf`` to ``x``."""
    c = np.clip(x, -1.0, 1.0)
    return np.where(c < 0.0, (c + 1.0) ** 3 / 6.0, c + (1.0 - c) ** 3 / 6.0) + np.maximum(x - 1.0, 0.0)


#: Midpoint nodes of the average over the softness ramp in :func:`area_weight`.
SOFTNESS_NODES = 16


def area_weight(distance: np.ndarray, width: float, softness: float, footprint: np.ndarray) -> np.ndarray:
    """Layer 1's expected weight over a footprint of many texels, ``(N,)`` float64.

    The two layers' heights are independent ranks (:class:`LayerHeight`), so over many texels their difference
    ``h_1 - h_0`` follows the triangular law on [-1, 1]; the signed distance to the contour varies across the
    footprint (side ``footprint``, uv units, centred at ``distance``), taken as uniform over
    ``distance +- footprint / 2``; :func:`point_weight` averaged over both: for ``softness = 0`` the chance that
    ``h_1 - h_0 + d / width > 0``, in closed form. ``distance (N,)`` must be finite (rows near the contour)."""
    x0 = np.asarray(distance, dtype=np.float64) / width
    half = 0.5 * np.asarray(footprint, dtype=np.float64) / width
    wide = half > 1e-9  # below: the footprint is a point along the distance
    span = np.where(wide, 2.0 * half, 1.0)
    # the softness ramp is the average of hard choices over score offsets uniform in [-softness, softness]
    offsets = [0.0] if softness <= 0 else softness * ((np.arange(SOFTNESS_NODES) + 0.5) * (2.0 / SOFTNESS_NODES) - 1.0)
    total = np.zeros_like(x0)
    for offset in offsets:
        x = x0 + offset
        total += np.where(wide, (_difference_cdf_integral(x + half) - _difference_cdf_integral(x - half)) / span,
                          _difference_cdf(x))
    return total / len(offsets)


def footprint_weight(point: np.ndarray, distance: np.ndarray, width: float, softness: float, footprint: np.ndarray,
                     texels: np.ndarray) -> np.ndarray:
    """Layer 1's weight ``(N,)`` for footprint queries: the point query's weight ``point`` within one texel,
    :func:`area_weight` over many, mixed by ``a = 1 - 1 / texels^2`` (the share of the footprint's texels other than
    its centre's) between.

    ``distance``: the signed distance to the contour (uv units); ``footprint``: each query's side (uv units);
    ``texels``: the footprint in texels of the coarser layer (whose heights vary slowest). Rows farther from the
    contour than ``width`` (plus the softness' reach and half the footprint) keep ``point``.

    Examples
    --------
    >>> import numpy as np
    >>> d = np.array([-0.2, 0.0, 0.05, 0.2])
    >>> footprint_weight(np.array([0.0, 1.0, 0.0, 1.0]), d, 0.1, 0.0, np.full(4, 1e-3), np.full(4, 0.5)).tolist()
    [0.0, 1.0, 0.0, 1.0]
    >>> np.round(footprint_weight(np.array([0.0, 1.0, 0.0, 1.0]), d, 0.1, 0.0, np.full(4, 1e-3), np.full(4, 1e3)), 3).tolist()
    [0.0, 0.5, 0.875, 1.0]
    """
    point = np.asarray(point, dtype=np.float64)
    distance = np.asarray(distance, dtype=np.float64)
    footprint = np.asarray(footprint, dtype=np.float64)
    mix = np.clip(1.0 - 1.0 / np.maximum(np.asarray(texels, dtype=np.float64), 1.0) ** 2, 0.0, 1.0)
    near = np.abs(distance) < width * (1.0 + softness) + 0.5 * footprint
    rows = np.flatnonzero(near & (mix > 0))
    out = point.copy()
    if rows.size:
        area = area_weight(distance[rows], width, softness, footprint[rows])
        out[rows] = (1.0 - mix[rows]) * point[rows] + mix[rows] * area
    return out


def layer_weight(distance: np.ndarray, difference: np.ndarray, width: float, softness: float,
                 footprint: np.ndarray | None = None, texels: np.ndarray | None = None) -> np.ndarray:
    """Layer 1's weight ``(N,)`` float64 from each query's signed distance to the mask's contour ``distance (N,)``
    (uv units, positive on layer 1's side) and the layers' height difference ``h_1 - h_0`` ``difference (N,)``
    (read only where ``|distance| < width``): beyond ``width`` the side's layer, inside :func:`point_weight` of
    ``difference + distance / width``; with ``footprint`` and ``texels`` (each ``(N,)``) :func:`footprint_weight`.
    The one rule :class:`LayeredBTF` and the Mitsuba layered BSDF apply."""
    weight = (distance > 0).astype(np.float64)
    inside = np.abs(distance) < width
    weight[inside] = point_weight(difference[inside] + distance[inside] / width, softness)
    if footprint is not None:
        weight = footprint_weight(weight, distance, width, softness, footprint, texels)
    return weight


# ------------------------------------------------------------------------------------------------ layered BTF
class LayeredBTF:
    """Two synthesized BTFs on one surface, chosen per point by ``mask`` (see the module docstring).

    Parameters
    ----------
    layers : sequence of two SynthesizedBTF
        Layer 0 shows where the mask is below 0.5, layer 1 where it is above.
    mask : ImageMask, NoiseMask or any object with ``value`` and ``gradient``
        Over the user's ``uv``.
    width : float, default 0.05
        Half-width (uv units) of the band around the mask's 0.5 contour where the materials' heights decide.
    softness : float, default 0.0
        Height difference over which the two layers blend inside the band (0: each point from one layer).

    Attributes
    ----------
    height_maps : list of LayerHeight
        How each layer's height is read (:func:`layer_height_map`); the backends read the same.
    """

    def __init__(self, layers, mask, width: float = 0.05, softness: float = 0.0) -> None:
        layers = list(layers)
        if len(layers) != 2 or not all(isinstance(x, SynthesizedBTF) for x in layers):
            raise InputError(f"layers: expected two SynthesizedBTF, got {[type(x).__name__ for x in layers]}")
        if not (callable(getattr(mask, "value", None)) and callable(getattr(mask, "gradient", None))):
            raise InputError(f"mask: expected an ImageMask, a NoiseMask or an object with value(uv) and "
                             f"gradient(uv), got {type(mask).__name__}")
        self.layers, self.mask = layers, mask
        self.width = positive_number("width", width, "uv units")
        softness = float(softness)
        if not (math.isfinite(softness) and softness >= 0.0):
            raise InputError(f"softness: expected a height difference >= 0, got {softness!r}")
        self.softness = softness
        self.height_maps = [layer_height_map(layer) for layer in layers]

    @property
    def scale(self) -> float:
        """The larger of the layers' scales (exemplar repeats per uv unit): what bounds a valid ``uv``."""
        return max(btf.scale for btf in self.layers)

    def image(self, view=(0.0, 0.0), light=(0.0, 0.0), uv_rect=(0.0, 0.0, 1.0, 1.0), resolution=512,
              spp: int = 1, filtered: bool = False) -> np.ndarray:
        """A flat sample under one directional (view, light) pair (:func:`dynbtf.infinite_btf.flat_image`)."""
        return flat_image(self, view, light, uv_rect, resolution, spp, filtered)

    def heights(self, uv: torch.Tensor) -> torch.Tensor:
        """Each layer's height in ``[0, 1]`` at ``uv (N, 2)`` float64: ``(N, 2)`` float64."""
        return self._heights_and_latents(uv)[0]

    def _heights_and_latents(self, uv: torch.Tensor) -> tuple[torch.Tensor, list]:
        """:meth:`heights` and, per layer, its latent values at ``uv`` where its ``eval`` takes them back (else None):
        a layer's synthesis at a band point then serves both its height and its colour."""
        out, latents = [], []
        for btf, height_of in zip(self.layers, self.height_maps):
            height, latent = layer_height(btf, height_of, uv)
            out.append(height)
            latents.append(latent)
        return torch.from_numpy(np.stack(out, -1)), latents

    def weight(self, uv, footprint=None) -> np.ndarray:
        """Layer 1's weight in ``[0, 1]`` at ``uv (..., 2)``: ``(...)`` float64 (layer 0's is one minus it); with
        ``footprint`` (float or ``(...)``, uv units, as :meth:`eval` takes it) the share of each footprint
        (:func:`footprint_weight`)."""
        uv = check_uv(uv, scale=self.scale)
        batch = tuple(uv.shape[:-1])
        flat = uv.reshape(-1, 2).to(torch.float64).cpu()
        fp = None if footprint is None else check_footprint(footprint, batch).reshape(-1).numpy()
        return self._weight(flat, fp)[0].reshape(batch)

    def texels_per_uv(self) -> float:
        """Texels per uv unit of the coarser layer (:meth:`SynthesizedBTF.texels_per_uv`): converts a footprint to
        the texels over which the slower-varying layer's height varies."""
        return min(btf.texels_per_uv() for btf in self.layers)

    def _weight(self, flat: torch.Tensor, footprint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, list]:
        """Layer 1's weight ``(N,)`` at ``flat (N, 2)`` (with ``footprint (N,)``, uv units: :func:`footprint_weight`),
        the rows inside the band, and each layer's latent values at those rows (:meth:`_heights_and_latents`)."""
        points = flat.numpy()
        if hasattr(self.mask, "value_and_gradient"):
            distance = contour_distance(*self.mask.value_and_gradient(points))
        else:
            distance = contour_distance(self.mask.value(points), self.mask.gradient(points))
        band = np.flatnonzero(np.abs(distance) < self.width)
        difference = np.zeros_like(distance)  # h_1 - h_0, read inside the band only
        latents = [None] * len(self.layers)
        if band.size:
            h, latents = self._heights_and_latents(flat[band])
            h = h.numpy()
            difference[band] = h[:, 1] - h[:, 0]
        weight = layer_weight(distance, difference, self.width, self.softness, footprint,
                              None if footprint is None else footprint * self.texels_per_uv())
        return weight, band, latents

    def eval(self, uv, w_view, w_light, footprint=None):
        """Linear RGB ``(..., 3)`` float32 (excluding cos(theta_light)), as :meth:`SynthesizedBTF.eval`, each layer
        evaluated only where its weight is positive. NumPy in, NumPy out; torch in, torch out (on the CPU)."""
        as_numpy = not isinstance(uv, torch.Tensor)
        uv = check_uv(uv, scale=self.scale)
        batch = tuple(uv.shape[:-1])
        flat = uv.reshape(-1, 2).to(torch.float64).cpu()
        wv = w_view if isinstance(w_view, torch.Tensor) else torch.from_numpy(np.require(w_view, np.float64, "W"))
        wl = w_light if isinstance(w_light, torch.Tensor) else torch.from_numpy(np.require(w_light, np.float64, "W"))
        for name, w in (("w_view", wv), ("w_light", wl)):
            if tuple(w.shape) != batch + (3,):
                raise InputError(f"{name}: expected shape {batch + (3,)}, got {tuple(w.shape)}")
        wv, wl = wv.reshape(-1, 3), wl.reshape(-1, 3)
        fp = None if footprint is None else check_footprint(footprint, batch).reshape(-1)  # float64, on the CPU
        weight, band, latents = self._weight(flat, None if fp is None else fp.numpy())
        weight = torch.from_numpy(weight)
        band_position = torch.full((flat.shape[0],), -1, dtype=torch.int64)  # a row's index among the band's rows
        band_position[torch.from_numpy(band)] = torch.arange(len(band))
        out = torch.zeros(flat.shape[0], 3, dtype=torch.float32)
        for k, btf in enumerate(self.layers):
            share = weight if k == 1 else 1.0 - weight
            if bool((share == 1).all()) and (latents[k] is None or fp is not None):  # the whole batch, nothing kept
                out = torch.as_tensor(btf.eval(flat, wv, wl, fp)).float().cpu()
                break
            rows = torch.nonzero(share > 0)[:, 0]
            if rows.numel() == 0:
                continue
            if latents[k] is None or fp is not None:
                parts = [(rows, None)]
            else:  # band rows decode the latent values their height was read from; the others synthesize
                kept = band_position[rows] >= 0
                parts = [(rows[~kept], None), (rows[kept], latents[k][band_position[rows[kept]]])]
            for part, latent in parts:
                if part.numel() == 0:
                    continue
                rgb = btf.eval(flat[part], wv[part], wl[part], None if fp is None else fp[part], latent=latent)
                rgb = torch.as_tensor(rgb).float().cpu()
                out[part] += rgb if bool((share[part] == 1).all()) else rgb * share[part, None].float()
        out = out.reshape(*batch, 3)
        return out.numpy() if as_numpy else out
