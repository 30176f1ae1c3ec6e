"""Measuring a synthesized BTF without ground truth.

No reference exists for a synthesized BTF, so the report compares a large
synthesized area with the exemplar statistically:

* **feature W1/std** -- per channel, the 1-D Wasserstein distance
  (:func:`scipy.stats.wasserstein_distance`) between synthesized and exemplar
  feature values, divided by the exemplar's standard deviation (0 = same
  histogram; linear blending loses contrast and scores high);
* **sliced W1/std** -- the same along 64 random directions of the standardized
  channel space (mean over directions): the joint distribution, which
  per-channel marginals miss (decorrelation targets it);
* **std ratio** -- synthesized / exemplar standard deviation per channel;
* **RGB W1/std** -- the same for the decoded colours under a few (view, light) pairs;
* **repetition** -- the normalized autocorrelation (standardized channels,
  summed power spectra, zero lag = 1) of the synthesized area at the exemplar's
  period lags ``(W, 0), (0, H), (W, +-H)`` and at the lattice vectors (max over
  a +-1 texel neighbourhood): plain tiling scores ~1, a non-repeating synthesis ~0;
* **verbatim copy** -- the fraction of synthesized texels lying within 1% of
  the channel std (L2 over standardized channels) of some exemplar texel:
  tiling and quilting copy (~1), blending methods create new values except
  near lattice vertices;
* **structure** -- patch coherence and identity with tiling
  (:mod:`dynbtf.synthesis.coherence`): 256 random 16 x 16 patches (a quarter of
  the exemplar side if smaller) of a synthesized area decoded far from the origin
  (``min(512, 4 max(H, W))`` texels per side, one pixel per texel, view (0, 0),
  light (40, 30)) are matched against every wrapped position of the decoded
  exemplar. ``coherence_median`` / ``coherence_p90``: the best match's mean squared
  difference over the median of random exemplar patch pairs (0 = every patch
  exists in the exemplar, ~1 = as foreign as random patches); ``identity``: the
  share of patches whose best match is where plain tiling would read (1 for
  tiling, low for a synthesis that reshuffles).

The area is sampled at texel centres, ``repeats x repeats`` exemplar repeats,
**reduced** so that it fits ``max_side`` texels per side (default 1024: 8 repeats
of a 128-texel exemplar, 2 of a 400-texel one); the report records the requested
and the measured size and :func:`format_report` prints both.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.stats import wasserstein_distance

from ..conventions import spherical_to_direction
from ..errors import InputError
from ..io import atomic_path
from .coherence import synthesized_coherence
from .lattice import LATTICE_SCALE

__all__ = ["quality_report", "format_report", "save_report", "repetition_score", "verbatim_fraction",
           "w1_over_std", "sliced_w1_over_std", "DEFAULT_PAIRS"]

#: (view, light) pairs of the RGB statistics, (theta, phi) in degrees.
DEFAULT_PAIRS = (((0.0, 0.0), (0.0, 0.0)), ((30.0, 0.0), (45.0, 180.0)), ((60.0, 90.0), (30.0, 270.0)))


def _subsample(x: np.ndarray, limit: int, rng: np.random.Generator) -> np.ndarray:
    return x if x.shape[0] <= limit else x[rng.choice(x.shape[0], limit, replace=False)]


def w1_over_std(synthesized: np.ndarray, exemplar: np.ndarray, limit: int = 200_000, seed: int = 0) -> np.ndarray:
    """Per-channel ``W1(synthesized, exemplar) / std(exemplar)`` of ``(N, C)`` and ``(M, C)`` values."""
    rng = np.random.default_rng(seed)
    s, e = _subsample(synthesized, limit, rng), _subsample(exemplar, limit, rng)
    std = exemplar.std(0)
    return np.array([wasserstein_distance(s[:, c], e[:, c]) / max(float(std[c]), 1e-12) for c in range(s.shape[1])])


def sliced_w1_over_std(synthesized: np.ndarray, exemplar: np.ndarray, directions: int = 64, seed: int = 0,
                       limit: int = 200_000) -> float:
    """Mean over random unit directions of ``W1 / std`` of the projections of standardized ``(N, C)`` values."""
    rng = np.random.default_rng(seed)
    mean, std = exemplar.mean(0), np.maximum(exemplar.std(0), 1e-12)
    s = (_subsample(synthesized, limit, rng) - mean) / std
    e = (_subsample(exemplar, limit, rng) - mean) / std
    axes = rng.normal(size=(exemplar.shape[1], directions))
    axes /= np.linalg.norm(axes, axis=0, keepdims=True)
    return float(w1_over_std(s @ axes, e @ axes, limit=limit, seed=seed).mean())


def repetition_score(area: np.ndarray, period: tuple[int, int]) -> dict[str, float]:
    """Normalized autocorrelation of ``area (Ha, Wa, C)`` at the exemplar period and lattice vectors.

    ``period = (H, W)`` in texels. Returns ``{"period": max over the period lags,
    "lattice": max over the lattice vectors, "score": the larger}``.
    """
    a = area.astype(np.float64)
    a = (a - a.mean((0, 1))) / np.maximum(a.std((0, 1)), 1e-12)
    power = (np.abs(np.fft.rfft2(a, axes=(0, 1))) ** 2).sum(-1)
    corr = np.fft.irfft2(power, s=a.shape[:2])
    corr /= corr[0, 0]
    h, w = period

    def peak(dy: float, dx: float) -> float:
        cy, cx = int(round(dy)), int(round(dx))
        return max(float(corr[(cy + i) % a.shape[0], (cx + j) % a.shape[1]]) for i in (-1, 0, 1) for j in (-1, 0, 1))

    period_lags = [(0, w), (h, 0), (h, w), (h, -w)]
    # lattice vertex steps (1, 0), (0, 1), (1, -1) in texels (rows follow v)
    lattice_lags = [(0, w / LATTICE_SCALE), (h / 4, w / (2 * LATTICE_SCALE)), (-h / 4, w / (2 * LATTICE_SCALE))]
    p = max(peak(dy, dx) for dy, dx in period_lags)
    lat = max(peak(dy, dx) for dy, dx in lattice_lags)
    return {"period": p, "lattice": lat, "score": max(p, lat)}


def verbatim_fraction(synthesized: np.ndarray, exemplar: np.ndarray, tolerance: float = 0.01,
                      limit: int = 100_000, seed: int = 0) -> float:
    """Fraction of synthesized ``(N, C)`` values within ``tolerance`` (standardized L2) of an exemplar value."""
    std = np.maximum(exemplar.std(0), 1e-12)
    tree = cKDTree(exemplar / std)
    s = _subsample(synthesized, limit, np.random.default_rng(seed)) / std
    dist, _ = tree.query(s, k=1, distance_upper_bound=tolerance * math.sqrt(exemplar.shape[1]))
    return float(np.isfinite(dist).mean())


def quality_report(btf, *, repeats: int = 8, max_side: int = 1024, pairs=DEFAULT_PAIRS, rgb_side: int = 512,
                   seed: int = 0) -> dict[str, Any]:
    """Quality statistics of a :class:`dynbtf.infinite_btf.SynthesizedBTF` (see the module docstring).

    Parameters
    ----------
    btf : SynthesizedBTF
    repeats : int, default 8
        Side of the synthesized area in exemplar repeats, reduced to
        ``max(2, max_side // max(H, W))`` when it does not fit ``max_side``.
    max_side : int, default 1024
        Largest area side in texels (the area's features are held in float64:
        ``(side^2 C 8)`` bytes, 134 MB at 1024^2 x 16).
    pairs : sequence of ((theta, phi), (theta, phi))
        (view, light) pairs in degrees for the RGB statistics.
    rgb_side : int, default 512
        Side of the (sub-sampled) area used for the RGB statistics, texels.
    seed : int
        Seed of the sub-sampling.

    Returns
    -------
    dict (JSON-serializable).
    """
    if int(repeats) < 2:
        raise InputError(f"repeats: expected at least 2 exemplar repeats (the period must fit), got {repeats}")
    synth = btf.synthesizer
    exemplar = synth.exemplar.detach().cpu().numpy().astype(np.float64)
    h, w, c = exemplar.shape
    requested = int(repeats)
    repeats = max(2, min(requested, max_side // max(h, w)))
    side_h, side_w = repeats * h, repeats * w
    v = (np.arange(side_h) + 0.5) / h
    u = (np.arange(side_w) + 0.5) / w
    uu, vv = np.meshgrid(u, v)
    uv = torch.from_numpy(np.stack([uu, vv], -1))
    area = synth(uv).cpu().numpy().astype(np.float64)  # (side_h, side_w, C), exemplar repeats
    flat_area, flat_ex = area.reshape(-1, c), exemplar.reshape(-1, c)
    w1 = w1_over_std(flat_area, flat_ex, seed=seed)
    report: dict[str, Any] = {
        **btf.describe(),
        "exemplar_shape": [h, w, c],
        "area_repeats": repeats,
        "area_repeats_requested": requested,
        "max_side": int(max_side),
        "area_texels": [side_h, side_w],
        "feature_w1_over_std": w1.tolist(),
        "feature_w1_over_std_mean": float(w1.mean()),
        "feature_w1_over_std_max": float(w1.max()),
        "feature_sliced_w1_over_std": sliced_w1_over_std(flat_area, flat_ex, seed=seed),
        "feature_std_ratio": (flat_area.std(0) / np.maximum(flat_ex.std(0), 1e-12)).tolist(),
        "repetition": repetition_score(area, (h, w)),
        "verbatim_fraction": verbatim_fraction(flat_area, flat_ex, seed=seed),
    }
    # RGB statistics: exemplar decoded at its texel centres vs a strided sub-area, through btf.eval
    stride = max(1, max(side_h, side_w) // rgb_side)
    sub_uv = uv[::stride, ::stride].reshape(-1, 2).numpy() / btf.scale
    ex_uv = np.stack(np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h), -1).reshape(-1, 2)
    tiled = btf.tiled()  # the exemplar decoded through the same evaluation path
    rgb_rows = []
    for view, light in pairs:
        wv = spherical_to_direction(np.array(view[0]), np.array(view[1]))
        wl = spherical_to_direction(np.array(light[0]), np.array(light[1]))
        syn_rgb = btf.eval(sub_uv, np.broadcast_to(wv, sub_uv.shape[:-1] + (3,)),
                           np.broadcast_to(wl, sub_uv.shape[:-1] + (3,)))
        ex_rgb = tiled.eval(ex_uv, np.broadcast_to(wv, ex_uv.shape[:-1] + (3,)),
                            np.broadcast_to(wl, ex_uv.shape[:-1] + (3,)))
        d = w1_over_std(syn_rgb.astype(np.float64), ex_rgb.astype(np.float64), seed=seed)
        rgb_rows.append({"view": list(view), "light": list(light), "w1_over_std": d.tolist(),
                         "std_ratio": (syn_rgb.std(0) / np.maximum(ex_rgb.std(0), 1e-12)).tolist()})
    report["rgb"] = rgb_rows
    report["rgb_w1_over_std_max"] = float(max(max(r["w1_over_std"]) for r in rgb_rows))
    coherence = synthesized_coherence(btf, seed=seed)
    report["structure"] = {"coherence_median": coherence["median"], "coherence_p90": coherence["p90"],
                           "identity": coherence["identity"],
                           **{k: coherence[k] for k in ("patch", "patches", "side", "view", "light", "origin")}}
    return report


def format_report(reports: list[dict[str, Any]]) -> str:
    """A plain-text table of one row per report (method)."""
    head = f"{'method':<8} {'W1/std feat (mean/max)':>23} {'sliced':>7} {'std ratio (min)':>15} {'W1/std RGB (max)':>16} " \
           f"{'repetition':>10} {'verbatim':>8} {'coh p90':>7} {'identity':>8} {'storage':>10}"
    rows = [head, "-" * len(head)]
    for r in reports:
        structure = r.get("structure")  # absent from reports saved before the structure measures
        coherence = f"{structure['coherence_p90']:>7.3f} {structure['identity']:>8.3f}" if structure \
            else f"{'-':>7} {'-':>8}"
        rows.append(f"{r['method']:<8} {r['feature_w1_over_std_mean']:>11.4f} / {r['feature_w1_over_std_max']:<9.4f} "
                    f"{r['feature_sliced_w1_over_std']:>7.4f} "
                    f"{min(r['feature_std_ratio']):>15.3f} {r['rgb_w1_over_std_max']:>16.4f} "
                    f"{r['repetition']['score']:>10.3f} {r['verbatim_fraction']:>8.3f} {coherence} "
                    f"{r['synthesizer_storage_bytes'] / 1e6:>8.2f}MB")
    for area in dict.fromkeys((r["area_repeats"], tuple(r["area_texels"]), r.get("area_repeats_requested"),
                               r.get("max_side")) for r in reports):
        repeats, (side_h, side_w), requested, max_side = area
        line = f"measured area: {repeats} x {repeats} exemplar repeats = {side_h} x {side_w} texels"
        if requested is not None and requested != repeats:
            line += f" (requested {requested}; reduced to fit {max_side} texels per side)"
        rows.append(line)
    return "\n".join(rows)


def save_report(reports: list[dict[str, Any]], path) -> None:
    """Write the reports as JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"reports": reports}, indent=2))
