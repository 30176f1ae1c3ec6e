"""Patch statistics of a synthesized image against its exemplar: patch coherence and identity with tiling.

Two structure measures of a synthesized material (the quality report's
"structure" entry, :mod:`dynbtf.synthesis.quality`), on images decoded at one
view and light, one pixel per texel:

* **patch coherence** -- for ``N`` random ``P x P`` patches of the synthesized
  image, the smallest mean squared difference (MSD) to the exemplar over **every**
  periodic (wrapped) exemplar position, divided by the median MSD between two
  random exemplar patches (random periodic positions). Median and 90th
  percentile over the patches: 0 = every patch exists in the exemplar
  (tiling, quilting inside its blocks), ~1 = patches as foreign as random ones;
* **identity with tiling** -- the share of those patches whose best exemplar
  position is the one plain tiling copies at the same place: 1 for tiling, low
  for a synthesis that reshuffles the exemplar.

All wrapped SSDs of a patch come from one FFT correlation (``SSD = sum p^2 +
windowed sum e^2 - 2 corr``), in float64, vectorised over chunks of patches;
the best and the tiling position's SSDs are then recomputed directly, so that a
copied patch scores exactly 0 and ties within FFT rounding go to tiling's place.
Its time grows with the exemplar's texels (NumPy/SciPy FFTs on one core).

:func:`patch_coherence` works on any two images; :func:`synthesized_coherence`
decodes them from a :class:`~dynbtf.infinite_btf.SynthesizedBTF` far from the origin.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.fft

from ..conventions import spherical_to_direction
from ..errors import InputError

__all__ = ["patch_coherence", "best_matches", "default_patch_size", "synthesized_images", "synthesized_coherence",
           "PATCH_SIZE", "REFERENCE_PAIRS", "DEFAULT_VIEW", "DEFAULT_LIGHT", "DEFAULT_ORIGIN", "MAX_SIDE"]

#: Patch side in texels (reduced to a quarter of the exemplar's shorter side when that is smaller).
PATCH_SIZE = 16
#: Random exemplar patch pairs whose median MSD normalizes the coherence.
REFERENCE_PAIRS = 1024
#: The (view, light) of :func:`synthesized_coherence`, (theta, phi) in degrees.
DEFAULT_VIEW = (0.0, 0.0)
DEFAULT_LIGHT = (40.0, 30.0)
#: Where :func:`synthesized_coherence` decodes the synthesized area, in exemplar repeats (what the synthesizer sees).
DEFAULT_ORIGIN = (1e6 + 0.25, 1e6 + 0.5)
#: Largest default side of the synthesized area, texels (4 repeats of a 128-texel exemplar).
MAX_SIDE = 512
#: Bytes of the patches' spectra per chunk: small chunks stay in cache (2 patches against a 400^2 x 3
#: exemplar, 20 against a 128^2 one; larger chunks ran slower).
_CHUNK_BYTES = 8 * 2**20


def default_patch_size(exemplar_shape) -> int:
    """``min(PATCH_SIZE, min(H, W) // 4)``, at least 1: the patch side for an exemplar ``(H, W, ...)``.

    >>> default_patch_size((128, 128, 3)), default_patch_size((32, 48, 3))
    (16, 8)
    """
    h, w = (int(x) for x in exemplar_shape[:2])
    return max(1, min(PATCH_SIZE, min(h, w) // 4))


def _image(x, name: str) -> np.ndarray:
    try:
        a = np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: expected a float array of shape (H, W, C) ({e})") from None
    if a.ndim != 3 or min(a.shape) < 1:
        raise InputError(f"{name}: expected a non-empty image of shape (H, W, C), got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{name}: expected finite values, got {int((~np.isfinite(a)).sum())} NaN or infinite")
    return a


def _integer(value, name: str, low: int = 1) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < low:
        raise InputError(f"{name}: expected an integer >= {low}, got {value!r}")
    return int(value)


def _patches_at(image: np.ndarray, rows: np.ndarray, cols: np.ndarray, patch: int) -> np.ndarray:
    """``(N, P, P, C)`` patches of ``image`` with top-left ``(rows, cols)``, wrapped at its border."""
    h, w = image.shape[:2]
    r = (rows[:, None] + np.arange(patch)) % h
    c = (cols[:, None] + np.arange(patch)) % w
    return image[r[:, :, None], c[:, None, :]]


def _window_sums(x: np.ndarray, patch: int) -> np.ndarray:
    """Wrapped ``P x P`` box sums of ``x (H, W)``: ``out[y, x] = sum x[(y + a) % H, (x + b) % W]``."""
    for axis in (0, 1):
        n = x.shape[axis]
        idx = np.arange(n + patch - 1) % n
        c = np.cumsum(np.take(x, idx, axis=axis), axis=axis)
        c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
        x = np.take(c, np.arange(patch, n + patch), axis=axis) - np.take(c, np.arange(n), axis=axis)
    return x


def best_matches(image, exemplar, corners, patch: int) -> tuple[np.ndarray, np.ndarray]:
    """The best wrapped exemplar position of each patch: ``(ssd (N,), position (N, 2))``.

    Parameters
    ----------
    image : ``(Hs, Ws, C)`` float array
    exemplar : ``(H, W, C)`` float array
    corners : ``(N, 2)`` int
        Top-left ``(row, col)`` of each ``patch x patch`` patch of ``image`` (inside it).
    patch : int
        Patch side, texels (at most the exemplar's shorter side).

    Returns
    -------
    ``ssd`` -- float64 sum of squared differences over the patch's ``P^2 C`` values at the best
    position, recomputed directly (0 for a copied patch); ``position`` -- its ``(row, col)`` top-left
    in the exemplar (wrapped: ``0 <= row < H``, ``0 <= col < W``).
    """
    image, exemplar = np.asarray(image, dtype=np.float64), np.asarray(exemplar, dtype=np.float64)
    corners = np.asarray(corners, dtype=np.int64).reshape(-1, 2)
    h, w, c = exemplar.shape
    wf = w // 2 + 1
    spec_e = scipy.fft.rfft2(exemplar.transpose(2, 0, 1), axes=(-2, -1))  # (C, H, Wf)
    energy = _window_sums((exemplar * exemplar).sum(-1), patch)  # (H, W)
    pats = _patches_at(image, corners[:, 0], corners[:, 1], patch)  # no wrap: corners lie inside
    p2 = (pats * pats).sum((1, 2, 3))
    # the zero-padded patches' 2-D spectra: row FFTs of the P non-zero rows only, then the column FFTs
    # (faster than padded 2-D FFTs; no BLAS, whose threads spin-wait on a loaded machine)
    chunk = max(1, _CHUNK_BYTES // (c * h * wf * 16))
    flat = np.empty(len(pats), dtype=np.int64)
    for start in range(0, len(pats), chunk):
        block = pats[start:start + chunk].transpose(0, 3, 1, 2)  # (k, C, P, P)
        spec_p = scipy.fft.fft(scipy.fft.rfft(block, n=w, axis=-1), n=h, axis=-2)  # (k, C, H, Wf)
        # cross-correlation: corr[y, x] = sum_ab p[a, b] e[(y + a) % H, (x + b) % W]
        corr = scipy.fft.irfft2(np.einsum("kchw,chw->khw", spec_p.conj(), spec_e), s=(h, w), axes=(-2, -1))
        ssd = p2[start:start + chunk, None, None] + energy[None] - 2.0 * corr
        flat[start:start + chunk] = ssd.reshape(len(block), -1).argmin(1)
    position = np.stack(np.divmod(flat, w), axis=1)
    diff = pats - _patches_at(exemplar, position[:, 0], position[:, 1], patch)
    return (diff * diff).sum((1, 2, 3)), position


def patch_coherence(image, exemplar, *, tiling_origin=(0, 0), patch: int | None = None, patches: int = 256,
                    reference_pairs: int = REFERENCE_PAIRS, seed: int = 0, details: bool = False) -> dict[str, Any]:
    """Patch coherence and identity with tiling of a synthesized ``image`` against its ``exemplar``.

    Parameters
    ----------
    image : ``(Hs, Ws, C)`` float array (NumPy or torch)
        The synthesized image, one pixel per texel (e.g. linear RGB decoded at one view and light).
    exemplar : ``(H, W, C)`` float array
        The exemplar in the same units, periodic (compared at every wrapped position).
    tiling_origin : (row0, col0) ints or None, default (0, 0)
        Where plain tiling would read: it copies exemplar texel ``((row0 + i) % H, (col0 + j) % W)``
        to image texel ``[i, j]`` (for a synthesized area whose texel ``[i, j]`` lies at exemplar-repeat
        ``uv = origin + ((j + .5) / W, (i + .5) / H)``, ``(row0, col0)`` is the origin in texels).
        ``None``: identity is not measured (``None`` in the result).
    patch : int, optional
        Patch side ``P`` in texels; default :func:`default_patch_size` (16, or a quarter of the
        exemplar's shorter side if smaller). At most the exemplar's and the image's sides.
    patches : int, default 256
        Number ``N`` of random patches of the image (top-left corners uniform over the positions
        where the patch fits, with replacement).
    reference_pairs : int, default 1024
        Random exemplar patch pairs whose median MSD normalizes the coherence.
    seed : int, default 0
        Seed of all random choices (the result is deterministic per seed).
    details : bool, default False
        Also return the per-patch arrays ``corners (N, 2)``, ``best (N, 2)``, ``scores (N,)``,
        ``at_tiling (N,)`` bool (NumPy; the rest of the dict is JSON-serializable).

    Returns
    -------
    dict with ``median``, ``p90``, ``mean`` -- of the per-patch score ``min MSD / reference`` (0: every
    patch exists in the exemplar; ~1: as foreign as a random exemplar patch); ``identity`` -- share of
    patches whose best position is tiling's (ties within rounding count as tiling's); ``reference_msd``
    -- the median MSD of random exemplar pairs (per value, the images' units squared); ``patch``,
    ``patches``, ``reference_pairs``, ``seed``, ``tiling_origin``. A constant exemplar (reference 0)
    scores 0 for patches it contains and ``inf`` otherwise.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> ex = rng.random((32, 32, 3))
    >>> tiled = np.tile(ex, (3, 3, 1))[5:69, 7:71]  # plain tiling from texel (5, 7)
    >>> r = patch_coherence(tiled, ex, tiling_origin=(5, 7), patches=64)
    >>> r["patch"], r["median"], r["p90"], r["identity"]
    (8, 0.0, 0.0, 1.0)
    >>> noise = patch_coherence(rng.random((64, 64, 3)), ex, patches=64)
    >>> 0.5 < noise["median"] < 1.0, noise["identity"]
    (True, 0.0)
    """
    image, exemplar = _image(image, "image"), _image(exemplar, "exemplar")
    patch = _checked_patch(image.shape, exemplar.shape, patch)
    patches = _integer(patches, "patches")
    reference_pairs = _integer(reference_pairs, "reference_pairs")
    seed = _integer(seed, "seed", low=0)
    origin = None if tiling_origin is None else _checked_tiling_origin(tiling_origin)
    hs, ws = image.shape[:2]
    rng = np.random.default_rng(seed)
    corners = np.stack([rng.integers(0, hs - patch + 1, patches), rng.integers(0, ws - patch + 1, patches)], 1)
    reference = _reference_msd(exemplar, rng, reference_pairs, patch)

    ssd, best = best_matches(image, exemplar, corners, patch)
    at_tiling = None
    if origin is not None:
        ssd, best, at_tiling = _prefer_tiling(image, exemplar, corners, patch, origin, ssd, best)
    msd = ssd / (patch * patch * exemplar.shape[2])
    if reference > 0:
        scores = msd / reference
    else:
        scores = np.where(msd > 0, np.inf, 0.0)
    out: dict[str, Any] = {
        "median": float(np.median(scores)),
        "p90": float(np.percentile(scores, 90)),
        "mean": float(scores.mean()),
        "identity": None if at_tiling is None else float(at_tiling.mean()),
        "reference_msd": reference,
        "patch": patch,
        "patches": patches,
        "reference_pairs": reference_pairs,
        "seed": seed,
        "tiling_origin": None if origin is None else list(origin),
    }
    if details:
        out.update(corners=corners, best=best, scores=scores, at_tiling=at_tiling)
    return out


def _checked_patch(image_shape: tuple[int, int, int], exemplar_shape: tuple[int, int, int], patch: int | None
                   ) -> int:
    """The patch side ``P`` (texels; default :func:`default_patch_size`) once the image ``(Hs, Ws, C)`` and the
    exemplar ``(H, W, C)`` share their channels and hold a ``P x P`` patch (else :class:`InputError`)."""
    hs, ws, cs = image_shape
    h, w, c = exemplar_shape
    if cs != c:
        raise InputError(f"image: {cs} channels, but the exemplar has {c}; expected the same channels")
    patch = default_patch_size(exemplar_shape) if patch is None else _integer(patch, "patch")
    if patch > min(h, w):
        raise InputError(f"patch: {patch} texels is larger than the {h}x{w} exemplar; expected at most {min(h, w)}")
    if hs < patch or ws < patch:
        raise InputError(f"image: {hs}x{ws} is smaller than a {patch}x{patch} patch; expected at least "
                         f"{patch} texels per side")
    return patch


def _checked_tiling_origin(tiling_origin) -> tuple[int, int]:
    """``(row0, col0)`` as Python ints; :class:`InputError` unless two integers (not bools)."""
    try:
        row0, col0 = tiling_origin
        if not all(isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_)) for x in (row0, col0)):
            raise TypeError
    except (TypeError, ValueError):
        raise InputError(f"tiling_origin: expected (row0, col0) integers or None, got {tiling_origin!r}") from None
    return int(row0), int(col0)


def _reference_msd(exemplar: np.ndarray, rng: np.random.Generator, pairs: int, patch: int) -> float:
    """Median mean squared difference (per value: the exemplar's units squared) between the ``P x P`` patches
    of ``pairs`` random pairs of (wrapped) exemplar positions, drawn from ``rng``: the coherence's unit."""
    h, w, c = exemplar.shape
    a = rng.integers(0, (h, w), (pairs, 2))
    b = rng.integers(0, (h, w), (pairs, 2))
    diff = _patches_at(exemplar, a[:, 0], a[:, 1], patch) - _patches_at(exemplar, b[:, 0], b[:, 1], patch)
    return float(np.median((diff * diff).sum((1, 2, 3)))) / (patch * patch * c)


def _prefer_tiling(image: np.ndarray, exemplar: np.ndarray, corners: np.ndarray, patch: int,
                   origin: tuple[int, int], ssd: np.ndarray, best: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Give tiling's place the image patches it matches as well as their best match.

    ``corners (N, 2)``: the image patches' top-left texels; ``ssd (N,)``, ``best (N, 2)``: their best
    exemplar match (:func:`best_matches`); ``origin = (row0, col0)``: where plain tiling reads. A patch is
    at tiling when its best place is tiling's, or when tiling's sum of squared differences is within
    rounding (of the FFT's argmin) of the best one. Returns the updated ``ssd``, ``best`` and
    ``at_tiling (N,)`` bool.
    """
    h, w = exemplar.shape[:2]
    row0, col0 = origin
    place = np.stack([(row0 + corners[:, 0]) % h, (col0 + corners[:, 1]) % w], 1)
    pats = _patches_at(image, corners[:, 0], corners[:, 1], patch)
    d = pats - _patches_at(exemplar, place[:, 0], place[:, 1], patch)
    ssd_tiling = (d * d).sum((1, 2, 3))
    # ties within rounding (of the FFT's argmin) go to tiling's place
    scale = (pats * pats).sum((1, 2, 3)) + ssd_tiling + ssd
    at_tiling = (best == place).all(1) | (ssd_tiling <= ssd + 1e-12 * scale)
    best = np.where(at_tiling[:, None], place, best)
    ssd = np.where(at_tiling, np.minimum(ssd, ssd_tiling), ssd)
    return ssd, best, at_tiling


def _pair(value, name: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected two numbers, got {value!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise InputError(f"{name}: expected finite numbers, got {value!r}")
    return x, y


def synthesized_images(btf, *, side: int | None = None, view=DEFAULT_VIEW, light=DEFAULT_LIGHT,
                       origin=DEFAULT_ORIGIN) -> dict[str, Any]:
    """A synthesized area and the exemplar of a SynthesizedBTF, decoded at one (view, light), one pixel per texel.

    Parameters
    ----------
    btf : :class:`~dynbtf.infinite_btf.SynthesizedBTF`
    side : int, optional
        Side of the square synthesized area, texels; default ``min(MAX_SIDE, 4 max(H, W))``
        (4 exemplar repeats, at most 512 texels).
    view, light : (theta, phi) in degrees
        Default ``(0, 0)`` and ``(40, 30)``.
    origin : (u, v) in exemplar repeats (what the synthesizer sees, i.e. ``uv * btf.scale``)
        Lower corner of the area, rounded to the nearest texel corner; default ``(1e6 + .25, 1e6 + .5)``:
        far from the origin, off the repeat boundaries.

    Returns
    -------
    dict: ``image`` ``(side, side, 3)`` float64 -- synthesized texel ``[i, j]`` at exemplar-repeat
    ``uv = origin + ((j + .5) / W, (i + .5) / H)`` (``btf.eval`` at that ``uv / btf.scale``);
    ``exemplar`` ``(H, W, 3)`` float64 -- ``btf.tiled()`` at its texel centres; ``tiling_origin``
    ``(row0, col0)`` -- the origin in texels modulo the exemplar (where plain tiling reads);
    ``origin`` -- the rounded origin in exemplar repeats; ``view``, ``light``, ``side``.
    """
    h, w = (int(x) for x in btf.synthesizer.exemplar.shape[:2])
    side = min(MAX_SIDE, 4 * max(h, w)) if side is None else _integer(side, "side")
    view, light = _pair(view, "view"), _pair(light, "light")
    u0, v0 = _pair(origin, "origin")
    whole_u, whole_v = math.floor(u0), math.floor(v0)
    col0, row0 = round((u0 - whole_u) * w), round((v0 - whole_v) * h)  # may be W or H: one repeat further
    origin_u, origin_v = whole_u + col0 / w, whole_v + row0 / h
    wv = spherical_to_direction(np.array(view[0]), np.array(view[1]))
    wl = spherical_to_direction(np.array(light[0]), np.array(light[1]))

    def decode(target, uv):
        return target.eval(uv, np.broadcast_to(wv, uv.shape[:-1] + (3,)),
                           np.broadcast_to(wl, uv.shape[:-1] + (3,))).astype(np.float64)

    steps = np.arange(side, dtype=np.float64) + 0.5
    uu, vv = np.meshgrid(origin_u + steps / w, origin_v + steps / h)
    image = decode(btf, np.stack([uu, vv], -1) / btf.scale)
    eu, ev = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    exemplar = decode(btf.tiled(), np.stack([eu, ev], -1))
    return {"image": image, "exemplar": exemplar, "tiling_origin": (row0 % h, col0 % w),
            "origin": [origin_u, origin_v], "view": list(view), "light": list(light), "side": side}


def synthesized_coherence(btf, *, side: int | None = None, view=DEFAULT_VIEW, light=DEFAULT_LIGHT,
                          origin=DEFAULT_ORIGIN, patch: int | None = None, patches: int = 256,
                          seed: int = 0) -> dict[str, Any]:
    """:func:`patch_coherence` of a SynthesizedBTF's area (:func:`synthesized_images`) against its exemplar.

    Returns the dict of :func:`patch_coherence` plus ``view``, ``light``, ``origin`` (exemplar
    repeats) and ``side`` (JSON-serializable). Plain tiling scores ``median = p90 = 0`` and
    ``identity = 1``.

    >>> import torch
    >>> from dynbtf.representations.triple_plane import TriplePlane
    >>> from dynbtf.infinite_btf import SynthesizedBTF
    >>> from dynbtf.synthesized import synthesized_btf
    >>> r = synthesized_coherence(synthesized_btf(TriplePlane(32, 32, seed=1), "tile", scale=4.0), patches=32)
    >>> r["patch"], r["side"], r["p90"] < 1e-9, r["identity"]
    (8, 128, True, 1.0)
    """
    images = synthesized_images(btf, side=side, view=view, light=light, origin=origin)
    out = patch_coherence(images["image"], images["exemplar"], tiling_origin=images["tiling_origin"], patch=patch,
                          patches=patches, seed=seed)
    out.update({k: images[k] for k in ("view", "light", "origin", "side")})
    return out
