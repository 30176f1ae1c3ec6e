"""Make the synthesis figures and numbers of docs/synthesis.md from a fitted model.

Usage::

    python docs/make_synthesis_images.py MODEL.dbtfm [--out docs/images] [--panel 256]

Writes ``synthesis_crops.png`` (3 x 3 repeats at one texel per pixel, at uv 0 and 1e6),
``synthesis_scales.png`` (rows: tile, linear, hist, hex, quilt; columns: 1x, 8x,
25x, 45x of the unit uv square and 45x of the unit square at uv = 1e6; supersampled to about
one sample per texel, at most 8 x 8 per pixel), ``synthesis_quality.json`` (the
quality report of every method) and prints the report table plus the decorrelation
and tileable ablations (feature W1/std with and without).
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
from dynbtf.synthesized import SynthesizedBTF

SCALES = (1.0, 8.0, 25.0, 45.0)
VIEW, LIGHT = (0.0, 0.0), (40.0, 30.0)


def crops(rep, out: Path, cos_light: float) -> None:
    """``synthesis_crops.png``: 3 x 3 exemplar repeats at one texel per pixel, around uv 0 and 1e6 (columns),
    one row per method (tile, linear, hist, hex, quilt)."""
    texels = rep.positional_plane().shape[1]
    side = 3 * texels
    rows = []
    for method in ("tile", "linear", "hist", "hex", "quilt"):
        btf = SynthesizedBTF(rep, method, scale=1.0, **({"repeats": 4.0} if method == "quilt" else {}))
        panels = [btf.image(VIEW, LIGHT, (c, c, c + 3.0, c + 3.0), side) * cos_light for c in (0.0, 1e6)]
        rows.append(np.concatenate([panels[0], np.ones((side, 4, 3), np.float32), panels[1]], axis=1))
    gap = np.ones((4, rows[0].shape[1], 3), dtype=np.float32)
    grid = np.concatenate([x for r in rows for x in (r, gap)][:-1], axis=0)
    save_image(out / "synthesis_crops.png", grid, exposure=0.8 / float(np.percentile(rows[0], 99.5)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--out", default="docs/images")
    parser.add_argument("--panel", type=int, default=256)
    parser.add_argument("--crops-only", action="store_true", help="only synthesis_crops.png")
    args = parser.parse_args()
    out = Path(args.out)
    rep, _ = load_model(args.model)
    cos_light = float(spherical_to_direction(np.array(LIGHT[0]), np.array(LIGHT[1]))[2])
    crops(rep, out, cos_light)
    if args.crops_only:
        return
    rows = []
    synthesizers = {}
    for method in ("tile", "linear", "hist", "hex", "quilt"):
        synth = SynthesizedBTF(rep, method, **({"repeats": 4.0} if method == "quilt" else {})).synthesizer
        synthesizers[method] = synth
        texels = synth.exemplar.shape[1]

        def spp(scale):  # about one sample per texel (at most 8 x 8)
            return max(1, min(8, round(scale * texels / args.panel)))

        panels = [SynthesizedBTF(rep, synth, scale=scale).image(VIEW, LIGHT, (0.0, 0.0, 1.0, 1.0), args.panel,
                                                                spp=spp(scale))
                  for scale in SCALES]
        panels.append(SynthesizedBTF(rep, synth, scale=45.0).image(VIEW, LIGHT, (1e6, 1e6, 1e6 + 1.0, 1e6 + 1.0),
                                                                    args.panel, spp=spp(45.0)))
        gap = np.ones((args.panel, 4, 3), dtype=np.float32)
        rows.append(np.concatenate([x for p in panels for x in (p * cos_light, gap)][:-1], axis=1))
        print(f"{method}: done", flush=True)
    gap = np.ones((4, rows[0].shape[1], 3), dtype=np.float32)
    grid = np.concatenate([x for r in rows for x in (r, gap)][:-1], axis=0)
    exposure = 0.8 / float(np.percentile(rows[0], 99.5))
    save_image(out / "synthesis_scales.png", grid, exposure=exposure)
    reports = [quality_report(SynthesizedBTF(rep, synthesizers[m], scale=8.0))
               for m in ("tile", "linear", "hist", "hex", "quilt")]
    print(format_report(reports))
    save_report(reports, out / "synthesis_quality.json")
    ablation = {}
    for name, params in (("hist", {}), ("hist, no decorrelation", {"decorrelate": False}),
                         ("hist, tileable off", {"tileable": False}), ("hist, tileable on", {"tileable": True}),
                         ("hex, tileable off", {"tileable": False}), ("hex, tileable on", {"tileable": True})):
        method = name.split(",")[0]
        r = quality_report(SynthesizedBTF(rep, method, scale=8.0, **params))
        ablation[name] = {k: r[k] for k in ("feature_w1_over_std_mean", "feature_w1_over_std_max",
                                            "feature_sliced_w1_over_std", "rgb_w1_over_std_max")} \
            | {"seam": r["parameters"].get("seam_after")}
        print(f"{name:<24} W1/std feat mean {ablation[name]['feature_w1_over_std_mean']:.4f} "
              f"max {ablation[name]['feature_w1_over_std_max']:.4f} "
              f"sliced {ablation[name]['feature_sliced_w1_over_std']:.4f}  RGB max {ablation[name]['rgb_w1_over_std_max']:.4f}"
              f"  seam {ablation[name]['seam']}")
    (out / "synthesis_ablation.json").write_text(json.dumps(ablation, indent=2))


if __name__ == "__main__":
    main()
