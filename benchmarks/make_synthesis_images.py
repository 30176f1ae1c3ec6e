"""Make the synthesis figures and numbers of docs/synthesis.md from a fitted model.

Usage::

    python benchmarks/make_synthesis_images.py MODEL.dbtfm [--out docs/images] [--panel 192]

Writes ``synthesis_crops.png`` (3 x 3 repeats at one texel per pixel, at uv 0 and 1e6),
``synthesis_scales.png`` (rows: tile, linear, hist, hex, quilt; columns: 1x, 8x,
25x, 45x of the unit uv square and 45x of the unit square at uv = 1e6; each full view
supersampled to about one sample per texel, at most 8 x 8 per pixel; where a full-view
pixel averages more than :data:`MAX_TEXELS_PER_PIXEL` texels -- 8x, 25x and 45x of a 128-texel
exemplar in 192 px; 25x and 45x box-filter a stochastic material to flat grey -- a detail panel
follows: the centre :data:`DETAIL_REPEATS` x :data:`DETAIL_REPEATS` repeats of the same
view at :data:`DETAIL_TEXELS_PER_PIXEL` texels per pixel, outlined in the full view),
``synthesis_filtering.png`` (hist at 25x and 45x: point query | footprint query | 8 x 8
supersampled, one query per pixel for the first two), ``synthesis_quality.json`` (the quality report of every method) and prints the report
table plus the blending-exponent, decorrelation and tileable ablations (feature and RGB W1/std).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dynbtf.conventions import spherical_to_direction
from dynbtf.io import save_image
from dynbtf.representations.model_file import load_model
from dynbtf.synthesis.quality import format_report, quality_report, save_report
from dynbtf.infinite_btf import SynthesizedBTF
from dynbtf.synthesized import synthesized_btf

SCALES = (1.0, 8.0, 25.0, 45.0)
VIEW, LIGHT = (0.0, 0.0), (40.0, 30.0)
#: Full views whose pixels average more texels than this get a detail panel.
MAX_TEXELS_PER_PIXEL = 4.0
#: Side of the detail panel's area, exemplar repeats (tiling shows 3 x 3 copies).
DETAIL_REPEATS = 3.0
#: Texels per pixel of the detail panel (2: the structure at full size, a 2 x 2 box filter).
DETAIL_TEXELS_PER_PIXEL = 2


def crops(rep, out: Path, cos_light: float) -> None:
    """``synthesis_crops.png``: 3 x 3 exemplar repeats at one texel per pixel, around uv 0 and 1e6 (columns),
    one row per method (tile, linear, hist, hex, quilt)."""
    texels = rep.positional_plane().shape[1]
    side = 3 * texels
    rows = []
    for method in ("tile", "linear", "hist", "hex", "quilt"):
        btf = synthesized_btf(rep, method, scale=1.0, **({"repeats": 4.0} if method == "quilt" else {}))
        panels = [btf.image(VIEW, LIGHT, (c, c, c + 3.0, c + 3.0), side) * cos_light for c in (0.0, 1e6)]
        rows.append(np.concatenate([panels[0], np.ones((side, 4, 3), np.float32), panels[1]], axis=1))
    gap = np.ones((4, rows[0].shape[1], 3), dtype=np.float32)
    grid = np.concatenate([x for r in rows for x in (r, gap)][:-1], axis=0)
    save_image(out / "synthesis_crops.png", grid, exposure=0.8 / float(np.percentile(rows[0], 99.5)))


def outline(image: np.ndarray, box: tuple[int, int, int, int], value: float) -> np.ndarray:
    """``image (H, W, 3)`` with a one-pixel frame of ``value`` around rows ``y0:y1``, columns ``x0:x1``."""
    y0, x0, y1, x1 = box
    framed = image.copy()
    framed[y0:y1, [x0, x1 - 1]] = value
    framed[[y0, y1 - 1], x0:x1] = value
    return framed


def scale_panels(btf: SynthesizedBTF, corner: float, panel: int, texels: int, bright: float) -> list[np.ndarray]:
    """The unit uv square at ``corner`` seen through ``btf`` (its scale), ``panel`` px per side, and,
    when a pixel would average more than :data:`MAX_TEXELS_PER_PIXEL` texels, a detail panel of its
    centre (``DETAIL_REPEATS`` repeats at ``DETAIL_TEXELS_PER_PIXEL`` texels per pixel), outlined in
    the full view with ``bright``. Values are BTF values (multiply by cos(theta_light) to show)."""
    texels_per_pixel = btf.scale * texels / panel
    full = btf.image(VIEW, LIGHT, (corner, corner, corner + 1.0, corner + 1.0), panel,
                     spp=max(1, min(8, round(texels_per_pixel))))
    if texels_per_pixel <= MAX_TEXELS_PER_PIXEL:
        return [full]
    half = DETAIL_REPEATS / btf.scale / 2  # user uv
    centre = corner + 0.5
    side = round(DETAIL_REPEATS * texels / DETAIL_TEXELS_PER_PIXEL)
    detail = btf.image(VIEW, LIGHT, (centre - half, centre - half, centre + half, centre + half), side,
                       spp=DETAIL_TEXELS_PER_PIXEL)
    lo, hi = round((0.5 - half) * panel), round((0.5 + half) * panel)
    return [outline(full, (lo, lo, hi, hi), bright), detail]


def filtering(rep, out: Path, cos_light: float, panel: int) -> None:
    """``synthesis_filtering.png``: hist at 25x and 45x of the unit square (rows), one point query per
    pixel | one footprint query per pixel (``filtered=True``) | 8 x 8 point queries per pixel (the
    supersampled reference), ``panel`` px per side."""
    rows = []
    for scale in (25.0, 45.0):
        btf = synthesized_btf(rep, "hist", scale=scale)
        panels = [btf.image(VIEW, LIGHT, (0.0, 0.0, 1.0, 1.0), panel, **kw) * cos_light
                  for kw in ({}, {"filtered": True}, {"spp": 8})]
        gap = np.ones((panel, 4, 3), dtype=np.float32)
        rows.append(np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1))
    grid = np.concatenate([rows[0], np.ones((4, rows[0].shape[1], 3), np.float32), rows[1]], axis=0)
    save_image(out / "synthesis_filtering.png", grid, exposure=0.8 / float(np.percentile(rows[1], 99.5)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "images"))
    parser.add_argument("--panel", type=int, default=192, help="side of the full-view panels, pixels")
    parser.add_argument("--crops-only", action="store_true", help="only synthesis_crops.png")
    parser.add_argument("--filtering-only", action="store_true", help="only synthesis_filtering.png")
    args = parser.parse_args()
    out = Path(args.out)
    rep, _ = load_model(args.model)
    cos_light = float(spherical_to_direction(np.array(LIGHT[0]), np.array(LIGHT[1]))[2])
    if args.filtering_only:
        filtering(rep, out, cos_light, args.panel)
        return
    crops(rep, out, cos_light)
    if args.crops_only:
        return
    filtering(rep, out, cos_light, args.panel)
    rows = []
    synthesizers = {}
    bright = 1e3  # the outline: clamps to white after any exposure
    for method in ("tile", "linear", "hist", "hex", "quilt"):
        synth = synthesized_btf(rep, method, **({"repeats": 4.0} if method == "quilt" else {})).synthesizer
        synthesizers[method] = synth
        texels = synth.exemplar.shape[1]
        groups = [scale_panels(synthesized_btf(rep, synth, scale=scale), 0.0, args.panel, texels, bright)
                  for scale in SCALES]
        groups.append(scale_panels(synthesized_btf(rep, synth, scale=45.0), 1e6, args.panel, texels, bright))
        height = max(p.shape[0] for g in groups for p in g)
        pieces = []
        for group in groups:  # 4 px between a full view and its detail, 12 px between scales
            for k, p in enumerate(group):
                p = np.pad(p * cos_light, ((0, height - p.shape[0]), (0, 0), (0, 0)), constant_values=1.0)
                pieces += [np.ones((height, 4 if k else 12, 3), np.float32), p]
        rows.append(np.concatenate(pieces[1:], axis=1))
        print(f"{method}: done", flush=True)
        if method == "tile":  # exposure from the exemplar itself (tiling at 1x)
            exposure = 0.8 / float(np.percentile(groups[0][0] * cos_light, 99.5))
    gap = np.ones((4, rows[0].shape[1], 3), dtype=np.float32)
    grid = np.concatenate([x for r in rows for x in (r, gap)][:-1], axis=0)
    save_image(out / "synthesis_scales.png", grid, exposure=exposure)
    reports = [quality_report(synthesized_btf(rep, synthesizers[m], scale=8.0))
               for m in ("tile", "linear", "hist", "hex", "quilt")]
    print(format_report(reports))
    save_report(reports, out / "synthesis_quality.json")
    ablation = {}
    for name, params in (("hist", {}), ("hist, gamma=1 (Heitz-Neyret)", {"gamma": 1.0}),
                         ("hist, gamma=3 (Burley)", {"gamma": 3.0}), ("hist, gamma=10", {"gamma": 10.0}),
                         ("hist, no decorrelation", {"decorrelate": False}),
                         ("hist, gamma=1, no decorrelation", {"gamma": 1.0, "decorrelate": False}),
                         ("hist, tileable off", {"tileable": False}), ("hist, tileable on", {"tileable": True}),
                         ("hex, tileable off", {"tileable": False}), ("hex, tileable on", {"tileable": True})):
        method = name.split(",")[0]
        r = quality_report(synthesized_btf(rep, method, scale=8.0, **params))
        ablation[name] = {k: r[k] for k in ("feature_w1_over_std_mean", "feature_w1_over_std_max",
                                            "feature_sliced_w1_over_std", "rgb_w1_over_std_max")} \
            | {"seam": r["parameters"].get("seam_after")}
        print(f"{name:<32} W1/std feat mean {ablation[name]['feature_w1_over_std_mean']:.4f} "
              f"max {ablation[name]['feature_w1_over_std_max']:.4f} "
              f"sliced {ablation[name]['feature_sliced_w1_over_std']:.4f}  RGB max {ablation[name]['rgb_w1_over_std_max']:.4f}"
              f"  seam {ablation[name]['seam']}")
    (out / "synthesis_ablation.json").write_text(json.dumps(ablation, indent=2))


if __name__ == "__main__":
    main()
