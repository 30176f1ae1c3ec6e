"""Structured materials: every synthesis method side by side on structured and stochastic materials.

For each material (``--materials``: the structured woven_fabric, ceramic_tiles and brick_wall, the stochastic
leather and stone; 128 x 128 simulated BTFs), a fitted Triple Plane is read from ``--models DIR/<material>.dbtfm``
or, when missing, simulated and fitted there (``dynbtf fit`` with ``--fit-minutes`` as its time budget; the
default recipe when not given). Then, for each method (tile, hist, hex, quilt, struct, and what ``auto``
picks, printed with its measurement) it measures:

* **coherence p90 / identity** (:mod:`dynbtf.synthesis.coherence`): the synthesized area at one pixel per
  texel, decoded at view (0, 0) and light (40, 30), ``scale`` repeats on a side (``--scales``, 8 and 25)
  far from the origin (1e6 repeats) -- its central window of at most 1024 x 1024 texels (8 x 8 repeats of
  a 128-texel exemplar; the synthesis is stationary, so a window's patches are distributed as the whole
  area's) -- 256 random 16 x 16 patches against every periodic position of the exemplar decoded the same
  way; medians over ``--seeds`` synthesis seeds (the spread is printed too).
  Quilting is measured at the first scale only (its plane is generated up front: 25 x 25 repeats of a
  128-texel plane are 655 MB);
* **repetition** and **RGB W1/std** (max over three (view, light) pairs) from the quality report
  (:func:`dynbtf.synthesis.quality.quality_report`, 8 x 8 repeats, seed 0);
* **cost**: ``SynthesizedBTF.eval`` per query on the same 2^20 random far-away queries, best of
  ``--repeats`` interleaved calls, as a ratio to hist's;
* **storage**: the synthesizer's tables over the positional plane's bytes; **build**: the off-line
  construction's seconds (struct's cut tables, cache off).

Finally struct's off-line construction on a 400 x 400 x 16 plane (the first structured model's plane
and appearance resampled to 400 x 400).

With ``--images DIR`` it writes ``structured_<material>.png`` for each structured material: rows 8x and 25x
(the unit uv square far from the origin, 512 px, 3 x 3 samples per pixel), columns tile | hist | auto.

Run: ``python benchmarks/bench_structured.py --models bench-models [--fit-minutes 5] [--images docs/images]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

STRUCTURED = ("woven_fabric", "ceramic_tiles", "brick_wall")
STOCHASTIC = ("leather", "stone")
METHODS = ("tile", "hist", "hex", "quilt", "struct")
FAR = 1e6
#: Largest side of the measured window, texels.
WINDOW = 1024


def ensure_model(folder: Path, material: str, minutes: float | None) -> Path:
    """``folder/<material>.dbtfm``, simulated and fitted (by the dynbtf command) when missing."""
    model = folder / f"{material}.dbtfm"
    if model.exists():
        return model
    folder.mkdir(parents=True, exist_ok=True)
    source = folder / f"{material}.dbtf"
    if not source.exists():
        subprocess.run([sys.executable, "-m", "dynbtf", "simulate", material, "-o", str(source)], check=True)
    command = [sys.executable, "-m", "dynbtf", "fit", str(source), "-o", str(model)]
    if minutes is not None:
        command += ["--max-minutes", str(minutes)]
    subprocess.run(command, check=True)
    return model


def coherence(btf, scale: float, seed: int) -> dict:
    """Coherence of the ``scale x scale``-repeat area far from the origin: its central window of at most
    ``WINDOW`` texels (the synthesis is stationary: a window's patches are distributed as the area's)."""
    from dynbtf.synthesis.coherence import synthesized_coherence

    w = int(btf.synthesizer.exemplar.shape[1])
    side = min(WINDOW, int(round(scale * w)))
    corner = FAR + (scale - side / w) / 2  # the window's lower corner, exemplar repeats
    return synthesized_coherence(btf, side=side, origin=(corner + 0.25, corner + 0.5), seed=seed)


def cost_per_query(btfs: dict, repeats: int) -> dict[str, float]:
    """Seconds per query of each SynthesizedBTF's eval on the same far-away queries (best of interleaved calls)."""
    rng = np.random.default_rng(0)
    n = 1 << 20
    uv = FAR + rng.random((n, 2)) * 64.0
    wv = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, 3))
    wl = np.broadcast_to(np.array([0.5, 0.0, np.sqrt(0.75)]), (n, 3))
    best = {name: np.inf for name in btfs}
    for name, btf in btfs.items():
        btf.eval(uv[:4096], wv[:4096], wl[:4096])  # compile / warm up
    for _ in range(repeats):
        for name, btf in btfs.items():
            start = time.perf_counter()
            btf.eval(uv, wv, wl)
            best[name] = min(best[name], (time.perf_counter() - start) / n)
    return best


def comparison_image(model: Path, material: str, folder: Path, size: int = 512) -> Path:
    """``structured_<material>.png``: rows 8x and 25x, columns tile | hist | auto (view (0, 0), light (40, 30))."""
    from dynbtf.io import save_image
    from dynbtf.synthesized import synthesized_btf

    rows = []
    gap = 6
    for scale in (8.0, 25.0):
        panels = []
        for method in ("tile", "hist", "auto"):
            btf = synthesized_btf(model, method, scale=scale, seed=0)
            c = FAR / scale
            image = btf.image(view=(0.0, 0.0), light=(40.0, 30.0), uv_rect=(c, c, c + 1.0, c + 1.0),
                              resolution=size, spp=3)
            panels += [image, np.ones((size, gap, 3), np.float32)]
        rows += [np.concatenate(panels[:-1], 1), np.ones((gap, 3 * size + 2 * gap, 3), np.float32)]
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"structured_{material}.png"
    save_image(path, np.concatenate(rows[:-1], 0))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="bench-models", help="folder of <material>.dbtfm (fitted when missing)")
    parser.add_argument("--materials", default=",".join(STRUCTURED + STOCHASTIC))
    parser.add_argument("--fit-minutes", type=float, default=None, help="time budget of each missing fit")
    parser.add_argument("--scales", default="8,25")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per method (the best is kept)")
    parser.add_argument("--json", default=None, help="also write every number to this JSON file")
    parser.add_argument("--images", default=None, help="folder for structured_<material>.png (tile | hist | auto)")
    args = parser.parse_args()

    import torch

    from dynbtf.synthesis.cell_quilting import build_cell_tables
    from dynbtf.synthesis.quality import quality_report
    from dynbtf.synthesized import synthesized_btf

    scales = [float(s) for s in args.scales.split(",")]
    results = []
    for material in [m.strip() for m in args.materials.split(",") if m.strip()]:
        model = ensure_model(Path(args.models), material, args.fit_minutes)
        auto = synthesized_btf(model, "auto", scale=scales[0], seed=0)
        print(f"\n== {material} ({model}): {auto.synthesizer.choice.line}", flush=True)
        plane_bytes = auto.synthesizer.exemplar.numel() * 4
        btfs = {}
        for method in METHODS:
            params = {"repeats": scales[0], "progress": False} if method == "quilt" else {}
            start = time.perf_counter()
            btfs[method] = synthesized_btf(model, method, scale=scales[0], seed=0, **params)
            built = time.perf_counter() - start
            row = {"material": material, "method": method, "auto": auto.synthesizer.name == method,
                   "storage_ratio": btfs[method].synthesizer.storage_bytes() / plane_bytes,
                   "build_seconds": (btfs[method].synthesizer.prepared.build_seconds if method == "struct" else built)}
            for scale in scales:
                if method == "quilt" and scale != scales[0]:
                    continue
                runs = [coherence(btfs[method] if seed == 0 and scale == scales[0] else
                                  synthesized_btf(model, method, scale=scale, seed=seed, **params), scale, seed)
                        for seed in range(args.seeds)]
                row[f"p90@{scale:g}"] = [r["p90"] for r in runs]
                row[f"identity@{scale:g}"] = [r["identity"] for r in runs]
            q = quality_report(btfs[method], repeats=8)
            row["repetition"] = q["repetition"]["score"]
            row["rgb_w1"] = q["rgb_w1_over_std_max"]
            results.append(row)
            print(f"   measured {method}", flush=True)
        costs = cost_per_query({m: b for m, b in btfs.items() if m != "quilt"}, args.repeats)
        for row in results:
            if row["material"] == material:
                row["cost_vs_hist"] = costs[row["method"]] / costs["hist"] if row["method"] in costs else None
                row["ns_per_query"] = costs[row["method"]] * 1e9 if row["method"] in costs else None

        head = (f"{'method':<8} " + " ".join(f"{'coh p90 @' + format(s, 'g'):>13} {'ident @' + format(s, 'g'):>9}"
                                             for s in scales)
                + f" {'repetition':>10} {'W1/std RGB':>10} {'cost/hist':>9} {'ns/query':>8} {'storage':>8} {'build s':>8}")
        print(head)
        for row in results:
            if row["material"] != material:
                continue
            cells = []
            for s in scales:
                p = row.get(f"p90@{s:g}")
                i = row.get(f"identity@{s:g}")
                cells.append(f"{np.median(p):>6.3f}±{np.ptp(p) / 2:<6.3f} {np.median(i):>9.3f}" if p else f"{'-':>13} {'-':>9}")
            cost = f"{row['cost_vs_hist']:>9.2f} {row['ns_per_query']:>8.0f}" if row["cost_vs_hist"] is not None \
                else f"{'-':>9} {'-':>8}"
            name = row["method"] + ("*" if row["auto"] else "")
            print(f"{name:<8} " + " ".join(cells) + f" {row['repetition']:>10.3f} {row['rgb_w1']:>10.4f} {cost} "
                  f"{row['storage_ratio']:>7.2f}x {row['build_seconds']:>8.2f}")
        print("(* = auto's choice; coherence: median over seeds ± half the range)")
        if args.images and material in STRUCTURED:
            print(f"   wrote {comparison_image(model, material, Path(args.images))}")

    # off-line construction at full size: 400 x 400 x 16
    first = next((m for m in args.materials.split(",") if m in STRUCTURED), None)
    if first is not None:
        btf = synthesized_btf(Path(args.models) / f"{first}.dbtfm", "tile")
        plane = btf.synthesizer.exemplar.permute(2, 0, 1)[None]
        guide = btf._decoded_appearance(btf.synthesizer.exemplar).permute(2, 0, 1)[None]
        big = torch.nn.functional.interpolate(plane, size=(400, 400), mode="bilinear")[0].permute(1, 2, 0)
        big_guide = torch.nn.functional.interpolate(guide, size=(400, 400), mode="bilinear")[0].permute(1, 2, 0)
        start = time.perf_counter()
        tables = build_cell_tables(big.contiguous(), guide=big_guide.contiguous())
        seconds = time.perf_counter() - start
        print(f"\nstruct tables at 400 x 400 x 16: {seconds:.1f} s, {tables.storage_bytes() / 1e6:.2f} MB "
              f"({tables.storage_bytes() / (400 * 400 * 16 * 4):.2f}x the plane)")
        results.append({"material": first, "method": "struct", "size": 400, "build_seconds": seconds,
                        "storage_ratio": tables.storage_bytes() / (400 * 400 * 16 * 4)})
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))


if __name__ == "__main__":
    main()
