"""Measure why hist's decoded colours drift and what the blending exponent does (docs/synthesis.md).

Usage::

    python benchmarks/measure_blend_exponent.py MODEL.dbtfm [MODEL2.dbtfm ...] [--seeds 3] [--diagnose]

Per model, for tile, hex, hist with ``gamma`` in :data:`GAMMAS` (and without decorrelation at
gamma 1 and 7) and a *dithered selection* prototype (defined here, not in the library), and for
each synthesis seed of ``--seeds`` (three by default; tile draws nothing random and is measured
once): the quality report's numbers (feature W1/std, RGB W1/std, RGB std ratio, repetition,
verbatim fraction; 8 x 8 repeats at 8x), the **area blended** (the share of texel centres, over
4 x 4 repeats, whose largest blending weight is below 0.9) plus a **speckle** score: the variance
of the 4-neighbour Laplacian of the decoded luminance over 4 x 4 repeats at texel centres, divided
by plain tiling's (1 = the exemplar's own fine detail; blended features that decode to noise raise
it), mean over two (view, light) pairs. Each number is kept per seed with the mean over the seeds
and their min-max range; the models are described from their files (kind, source, training,
held-out PSNR). It writes ``--json`` (default ``benchmarks/results/blend_exponent.json``, the data
of docs/results.md's table, rendered by ``benchmarks/tables.py``). ``--diagnose`` adds the point-wise analysis behind the cause (first model only):
decoded RGB std of blends of random texels per range of the variance-preserving factor,
of the exemplar's features plus Gaussian noise, and of fresh samples with the exemplar's
marginals and covariance, and of the remedies that did not work (partial variance
normalization, blending whitened coefficients without the transforms, a Gaussianized joint
distribution) or are not dynamic (snapping to the nearest exemplar vector). ``--figure PNG`` draws the comparison image of docs/synthesis.md
(rows: the models; columns: :data:`FIGURE_COLUMNS`). About 1 min per model (one core) plus 1 min
for ``--diagnose``, times the seeds.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from dynbtf.conventions import spherical_to_direction
from dynbtf.representations.model_file import load_model
from dynbtf.synthesis.base import register_synthesizer
from dynbtf.synthesis.blending import LatticeBlending
from dynbtf.synthesis.histogram import Decorrelation, GaussianTransform, blend_weights
from dynbtf.synthesis.quality import DEFAULT_PAIRS, quality_report, w1_over_std
from dynbtf.infinite_btf import SynthesizedBTF
from dynbtf.synthesized import synthesized_btf
from dynbtf.texture import fetch_wrap

from results_io import spread  # benchmarks/ is on the path of a script run from it

GAMMAS = (1.0, 3.0, 5.0, 7.0, 10.0)
SPECKLE_PAIRS = (((0.0, 0.0), (40.0, 30.0)), ((30.0, 0.0), (45.0, 180.0)))


def _texel_uniform(uv: np.ndarray, w: int, h: int, seed: int = 12345) -> np.ndarray:
    """A uniform number in [0, 1) per output texel (splitmix-style hash of the integer texel coordinates)."""
    x = np.floor(uv[:, 0] * w).astype(np.int64).astype(np.uint64)
    y = np.floor(uv[:, 1] * h).astype(np.int64).astype(np.uint64)
    z = (x * np.uint64(0x9E3779B97F4A7C15)) ^ (y * np.uint64(0xC2B2AE3D27D4EB4F)) ^ np.uint64(seed)
    for shift, mult in ((33, 0xFF51AFD7ED558CCD), (33, 0xC4CEB9FE1A85EC53)):
        z ^= z >> np.uint64(shift)
        z *= np.uint64(mult)
    z ^= z >> np.uint64(33)
    return (z >> np.uint64(11)).astype(np.float64) / 2.0 ** 53


@register_synthesizer("dither_prototype")
class DitheredSelection(LatticeBlending):
    """Prototype: each output texel copies ONE of the three samples, sample i with probability w_i = b_i^gamma / sum.

    No new feature vectors at all (every texel verbatim); transitions become ragged per-texel mixtures.
    Torch reference path only (hash per output texel, not per bilinear tap: exact at texel centres only).
    """

    mode = 0

    def __init__(self, exemplar, seed: int = 0, *, gamma: float = 7.0, tileable="auto", band: int | None = None,
                 fast: bool | None = None, prepared=None) -> None:
        self.gamma = float(gamma)
        super().__init__(exemplar, seed, tileable=tileable, band=band, fast=False, prepared=prepared)

    def reference_latent(self, uv):
        uv_samples, bary = self.sample_positions(uv)
        samples = fetch_wrap(self.prepared.plane, uv_samples)
        w = blend_weights(bary, self.gamma).numpy()
        pick = (_texel_uniform(uv.numpy(), *self.density)[:, None] > np.cumsum(w, 1)[:, :2]).sum(1)
        return samples[torch.arange(len(pick)), torch.from_numpy(pick)].float()

    def parameters(self):
        return {"gamma": self.gamma, **super().parameters()}


def variants(table_only: bool = False):
    """(name, method, parameters) of each variant measured; ``table_only``: those of the docs' table (tile, hex,
    hist at each exponent of :data:`GAMMAS`)."""
    out = [("tile", "tile", {}), ("hex", "hex", {})]
    out += [(f"hist gamma={g:g}", "hist", {"gamma": g}) for g in GAMMAS]
    if table_only:
        return out
    out += [(f"hist gamma={g:g}, no decorrelation", "hist", {"gamma": g, "decorrelate": False}) for g in (1.0, 7.0)]
    out += [(f"dithered selection gamma={g:g} (prototype)", "dither_prototype", {"gamma": g}) for g in (7.0, 15.0)]
    return out


def laplacian_variance(image: np.ndarray) -> float:
    lum = image @ np.array([0.2126, 0.7152, 0.0722])
    lap = 4 * lum - np.roll(lum, 1, 0) - np.roll(lum, -1, 0) - np.roll(lum, 1, 1) - np.roll(lum, -1, 1)
    return float(lap[1:-1, 1:-1].var())


def speckle_energy(btf: SynthesizedBTF, texels: tuple[int, int]) -> list[float]:
    h, w = texels
    return [laplacian_variance(btf.image(view=v, light=l, uv_rect=(0.0, 0.0, 4.0, 4.0), resolution=(4 * h, 4 * w)))
            for v, l in SPECKLE_PAIRS]


def blended_area(synth, texels: tuple[int, int], side: int = 4, threshold: float = 0.9) -> float:
    """The share of texel centres over ``side x side`` repeats whose largest blending weight is below
    ``threshold`` (0 for a synthesizer that does not blend three samples)."""
    if not isinstance(synth, LatticeBlending):
        return 0.0
    h, w = texels
    v, u = (np.arange(side * h) + 0.5) / h, (np.arange(side * w) + 0.5) / w
    uu, vv = np.meshgrid(u, v)
    uv = torch.from_numpy(np.stack([uu.ravel(), vv.ravel()], -1))
    uv_samples, bary = synth.sample_positions(uv)
    if hasattr(synth, "gamma"):  # hist (its blend is not linear in the samples) and the dithered prototype
        weights = blend_weights(bary, synth.gamma)
    else:  # a linear blend: blending the unit vectors gives the weights
        weights = synth.blend(torch.eye(3, dtype=torch.float64).expand(len(bary), 3, 3), bary, uv_samples)
    return float((weights.max(-1).values < threshold).double().mean())



def measure(path: str, seeds: list[int], label: str | None = None, table_only: bool = False) -> list[dict]:
    """A row per variant: the quality report's numbers, the area blended and the speckle, each per seed."""
    rep, _ = load_model(path)
    texels = tuple(rep.positional_plane().shape[:2])
    rows, tile_speckle = [], None
    for name, method, params in variants(table_only):
        per_seed = []
        for seed in (seeds[:1] if method == "tile" else seeds):
            btf = synthesized_btf(rep, method, scale=8.0, seed=seed, **params)
            r = quality_report(btf, repeats=8, seed=seed)
            speckle = speckle_energy(synthesized_btf(rep, btf.synthesizer, scale=1.0), texels)
            tile_speckle = speckle if method == "tile" else tile_speckle
            per_seed.append({
                "feature_w1_mean": r["feature_w1_over_std_mean"], "feature_w1_max": r["feature_w1_over_std_max"],
                "sliced": r["feature_sliced_w1_over_std"], "rgb_w1_max": r["rgb_w1_over_std_max"],
                "rgb_std_ratio": float(np.mean([np.mean(p["std_ratio"]) for p in r["rgb"]])),
                "repetition": r["repetition"]["score"], "verbatim": r["verbatim_fraction"],
                "area_blended": blended_area(btf.synthesizer, texels),
                "speckle": float(np.mean([s / t for s, t in zip(speckle, tile_speckle)]))})
        row = {"model": label or Path(path).stem.replace("_", " "), "variant": name, "method": method,
               "gamma": params.get("gamma"), "decorrelate": params.get("decorrelate", True),
               "seeds": list(seeds[:1] if method == "tile" else seeds),
               **{key: spread([s[key] for s in per_seed]) for key in per_seed[0]}}
        rows.append(row)
        m = {key: value["mean"] for key, value in row.items() if isinstance(value, dict)}
        print(f"{row['model']:<24} {name:<44} feat {m['feature_w1_mean']:.4f}/{m['feature_w1_max']:.4f} "
              f"RGB {m['rgb_w1_max']:.4f} ({row['rgb_w1_max']['range'][0]:.4f}-{row['rgb_w1_max']['range'][1]:.4f}) "
              f"std x{m['rgb_std_ratio']:.2f} rep {m['repetition']:.3f} verbatim {m['verbatim']:.2f} "
              f"blended {100 * m['area_blended']:.0f}% speckle {m['speckle']:.2f}", flush=True)
    return rows


@torch.no_grad()
def diagnose(path: str, n: int = 200_000, seed: int = 0) -> dict:
    """Point-wise: what the decoder makes of feature vectors that are not the exemplar's own."""
    rep, _ = load_model(path)
    x = rep.positional_plane().detach().double().reshape(-1, rep.positional_plane().shape[-1])
    xn = x.numpy()
    rng = np.random.default_rng(seed)
    pairs = [(torch.from_numpy(spherical_to_direction(np.array(v[0]), np.array(v[1]))).float(),
              torch.from_numpy(spherical_to_direction(np.array(l[0]), np.array(l[1]))).float()) for v, l in DEFAULT_PAIRS]

    def decode(features: np.ndarray) -> list[np.ndarray]:
        f = torch.from_numpy(np.ascontiguousarray(features)).float()
        return [rep.decode(f, wv.expand(len(f), 3), wl.expand(len(f), 3)).double().numpy() for wv, wl in pairs]

    reference = decode(xn)

    def stats(features: np.ndarray) -> dict:
        rgb = decode(features)
        return {"rgb_std_ratio": float(np.mean([(a.std(0) / e.std(0)).mean() for a, e in zip(rgb, reference)])),
                "rgb_w1_max": float(max(w1_over_std(a, e).max() for a, e in zip(rgb, reference))),
                "feature_w1_max": float(w1_over_std(features, xn).max())}

    # hist's blend of three random texels with barycentrics uniform on a triangle (what texel centres see)
    r = rng.random((n, 2))
    s = np.sqrt(r[:, 0])
    bary = np.stack([1 - s, s * (1 - r[:, 1]), s * r[:, 1]], 1)
    pca = Decorrelation.fit(x)
    transform, gaussian = GaussianTransform.fit(pca.project(x))
    idx = rng.integers(0, len(xn), (n, 3))
    out: dict = {"model": Path(path).name}
    for gamma in (1.0, 7.0):
        w = blend_weights(torch.from_numpy(bary), gamma).numpy()
        norm = np.sqrt((w * w).sum(1))
        g = (w[..., None] * gaussian.numpy()[idx]).sum(1) / norm[:, None]
        blended = pca.unproject(transform.inverse(torch.from_numpy(g))).numpy()
        out[f"hist gamma={gamma:g}"] = stats(blended)
        if gamma == 1.0:  # by the variance-preserving factor 1/sqrt(sum w^2): 1 at vertices, sqrt(3) at centres
            rgb = decode(blended)[0]
            for lo, hi in ((0.9, 1.01), (0.75, 0.9), (0.65, 0.75), (0.57, 0.65)):
                m = (norm >= lo) & (norm < hi)
                out[f"hist gamma=1, sqrt(sum w^2) in [{lo}, {hi})"] = {
                    "fraction": float(m.mean()), "rgb_std_ratio": float((rgb[m].std(0) / reference[0].std(0)).mean())}
    # partial variance normalization: sum w G / (sum w^2)^(alpha/2) (alpha = 1: hist, 0: linear in Gaussian space)
    w = blend_weights(torch.from_numpy(bary), 1.0).numpy()
    norm = np.sqrt((w * w).sum(1))
    mixed = (w[..., None] * gaussian.numpy()[idx]).sum(1)
    for alpha in (0.5, 0.75):
        out[f"hist gamma=1, normalization exponent {alpha}"] = stats(
            pca.unproject(transform.inverse(torch.from_numpy(mixed / norm[:, None] ** alpha))).numpy())
    hist1 = pca.unproject(transform.inverse(torch.from_numpy(mixed / norm[:, None]))).numpy()
    # what the decoder's first layer sees: the 32 positional pre-activations, marginally
    weight = rep.decoder.first.weight[:, : xn.shape[1]].detach().double().numpy()
    pre = w1_over_std(hist1 @ weight.T, xn @ weight.T)
    ratio = (hist1 @ weight.T).std(0) / (xn @ weight.T).std(0)
    out["hist gamma=1, layer-1 positional pre-activations"] = {
        "w1_mean": float(pre.mean()), "w1_max": float(pre.max()), "std_ratio_min_max": [float(ratio.min()),
                                                                                      float(ratio.max())]}
    plane = rep.positional_plane().detach().double().numpy()
    a, b = plane - plane.mean((0, 1)), np.roll(plane, -1, 1) - plane.mean((0, 1))
    out["correlation of horizontally adjacent texels (mean over channels)"] = float(
        ((a * b).mean((0, 1)) / (a * a).mean((0, 1))).mean())
    # blending whitened PCA coefficients, variance-preserving, without the per-channel transforms
    coef = pca.project(x).numpy()
    sd = coef.std(0)
    vp = (w[..., None] * (coef / sd)[idx]).sum(1) / norm[:, None] * sd
    out["whitened PCA, variance-preserving, no T"] = stats(pca.unproject(torch.from_numpy(vp)).numpy())
    # a Gaussianization of the JOINT distribution (RBIG: random rotation + marginal Gaussianization, 16 layers)
    from scipy.stats import special_ortho_group

    layers, z = [], pca.project(x) / torch.from_numpy(sd)
    for k in range(16):
        rot = torch.from_numpy(special_ortho_group.rvs(xn.shape[1], random_state=k)) if k else None
        t, z = GaussianTransform.fit(z @ rot if rot is not None else z)
        layers.append((rot, t))
    g = torch.from_numpy((w[..., None] * z.numpy()[idx]).sum(1) / norm[:, None])
    for rot, t in reversed(layers):
        g = t.inverse(g)
        g = g @ rot.T if rot is not None else g
    out["RBIG (16 layers) Gaussianized joint, gamma=1"] = stats(pca.unproject(g * torch.from_numpy(sd)).numpy())
    # each blend replaced by its nearest exemplar vector (standardized L2): verbatim again
    from scipy.spatial import cKDTree

    std = xn.std(0)
    tree = cKDTree(xn / std)
    dist, nearest = tree.query(hist1[:50_000] / std)
    own, _ = tree.query(xn[:5000] / std, k=2)
    out["hist gamma=1 snapped to the nearest exemplar vector"] = stats(xn[nearest]) | {
        "median_distance": float(np.median(dist)), "exemplar_median_distance_to_neighbour": float(np.median(own[:, 1]))}
    for sigma in (0.1, 0.2, 0.4):
        out[f"exemplar + N(0, ({sigma} std)^2)"] = stats(xn[idx[:, 0]] + rng.normal(size=(n, xn.shape[1])) * sigma * std)
    # fresh vectors with the exemplar's marginals and covariance (Gaussian copula of the PCA coefficients)
    fresh = rng.multivariate_normal(np.zeros(xn.shape[1]), np.cov(gaussian.numpy().T), n)
    out["fresh samples, exemplar marginals + covariance"] = stats(
        pca.unproject(transform.inverse(torch.from_numpy(fresh))).numpy())
    for k, v in out.items():
        print(f"  {k:<52} {v}")
    return out


FIGURE_COLUMNS = (("tile", "tile", {}), ("hist gamma=1", "hist", {"gamma": 1.0}), ("hist gamma=7", "hist", {}),
                  ("hex", "hex", {}), ("dithered gamma=15", "dither_prototype", {"gamma": 15.0}))


def figure(paths: list[str], out: Path, side: int = 96, zoom: int = 2) -> None:
    """Rows: models; columns: :data:`FIGURE_COLUMNS`; each panel ``side`` x ``side`` texels around uv (0.6, 0.6)
    repeats, one sample per texel centre (no magnification filter), shown ``zoom`` x enlarged (nearest)."""
    from dynbtf.io import save_image

    cos_light = float(spherical_to_direction(np.array(40.0), np.array(30.0))[2])
    rows = []
    for path in paths:
        rep, _ = load_model(path)
        h, w = rep.positional_plane().shape[:2]
        u0, v0 = round(0.6 * w) / w, round(0.6 * h) / h  # on texel boundaries: pixels at texel centres
        rect = (u0, v0, u0 + side / w, v0 + side / h)
        images = [synthesized_btf(rep, method, scale=1.0, **params).image((0.0, 0.0), (40.0, 30.0), rect, side)
                  * cos_light for _, method, params in FIGURE_COLUMNS]
        exposure = 0.8 / float(np.percentile(images[0], 99.5))  # per row, from the exemplar (tiling)
        rows.append([np.repeat(np.repeat(img * exposure, zoom, 0), zoom, 1) for img in images])
    gap_v = np.ones((side * zoom, 6, 3), np.float32)
    lines = [np.concatenate([x for p in r for x in (p, gap_v)][:-1], 1) for r in rows]
    gap_h = np.ones((6, lines[0].shape[1], 3), np.float32)
    save_image(out, np.concatenate([x for r in lines for x in (r, gap_h)][:-1], 0))
    print(f"wrote {out} (columns: {', '.join(c[0] for c in FIGURE_COLUMNS)})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+")
    parser.add_argument("--labels", default=None, help="comma-separated model names for the table (default: the "
                                                       "file names, underscores as spaces)")
    parser.add_argument("--seeds", type=int, default=3, help="synthesis seeds 0..N-1 (each number per seed)")
    parser.add_argument("--json", type=Path,
                        default=Path(__file__).resolve().parent / "results" / "blend_exponent.json",
                        help="where to write every number (the docs' table data)")
    parser.add_argument("--table-only", action="store_true",
                        help="only the docs' table's variants (no undecorrelated hist, no dithered prototype)")
    parser.add_argument("--diagnose", action="store_true")
    parser.add_argument("--figure", default=None, help="also write a comparison PNG (rows: models) here")
    parser.add_argument("--no-sweep", action="store_true", help="skip the per-model table (e.g. only --figure)")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, model_record, write_result

    from dynbtf.synthesis.histogram_blending import DEFAULT_GAMMA

    labels = args.labels.split(",") if args.labels else [None] * len(args.models)
    if len(labels) != len(args.models):
        parser.error(f"--labels: {len(labels)} names for {len(args.models)} models")
    if args.figure:
        figure(args.models, Path(args.figure))
    seeds = list(range(args.seeds))
    rows = [] if args.no_sweep else [row for path, label in zip(args.models, labels)
                                     for row in measure(path, seeds, label, args.table_only)]
    if not rows and not args.diagnose:
        return
    result = header("blend_exponent", "measure_blend_exponent.py") | {
        "conditions": f"hist, hex and tile at 8x, {len(seeds)} synthesis seeds (tile: one, it draws nothing random); "
                      "RGB W1/std: the quality report's, max over three (view, light) pairs, 8 x 8 repeats; each "
                      "number the mean over the seeds (min-max); area blended: texel centres over 4 x 4 repeats "
                      "whose largest blending weight is below 0.9",
        "gammas": list(GAMMAS), "default_gamma": DEFAULT_GAMMA, "seeds": seeds,
        "models": [dict(model_record(path), label=row_label)
                   for path, row_label in zip(args.models, [l or Path(p).stem.replace("_", " ")
                                                            for l, p in zip(labels, args.models)])],
        "rows": rows}
    if args.diagnose:
        result["diagnosis"] = diagnose(args.models[0])
    write_result(args.json, result)


if __name__ == "__main__":
    main()
