"""Layered materials measured: region statistics, the width of the boundary band, cost per query.

Run: ``python benchmarks/bench_guided.py`` (about 8 minutes, most of it fitting the three default materials once;
``--layers A.dbtfm B.dbtfm`` takes fitted models instead). Two materials (default: ``sim:leather?size=64`` and
``sim:stone?size=64``, fitted with ``dynbtf fit --minutes 2`` into ``~/.cache/dynbtf/bench_guided``), each
synthesized with hist at ``--scale`` repeats per uv unit, are layered by a half-plane mask (layer 0 left of
``u = 0.5``, layer 1 right of it; a linear ramp, so the signed distance to the contour is exactly ``u - 0.5``)
with boundary half-width ``--width``. For each synthesis seed (``--seeds``, 3 by default), over the uv square
``[0, 1]^2`` at ``--resolution`` pixels (view normal, light at 30 degrees):

* **region statistics** -- per channel, W1 / std of the layered image's left (right) half against the same half
  of layer 0's (layer 1's) own hist image; the largest channel's; over the whole half, and over the half without
  the band's columns. Target (issue "synthesis the artist steers"): within 0.02;
* **band width** -- the fraction of each pixel column that shows layer 1, against the column's distance to the
  contour; the measured half-width of the band is the largest distance of a column where both layers show
  (more than 0.5% and less than 99.5% of the column), per side, over ``--width``. Target: within 20% of it;
* **cost per query** -- ``LayeredBTF.eval`` over ``--queries`` random queries away from the band and inside it,
  against layer 0's own ``SynthesizedBTF.eval`` of the same queries, timed side by side (best of 3). Targets: at
  most 1.1x away from boundaries, at most 2.2x inside them.

Guidance (:func:`guidance_row`) is measured with hist on the first material and with struct on a structured one
(``--struct-model``, default the simulated brick wall), where whole cells are guided: there the share of cells
whose content is the target's label counts, besides the texels'.

The rows are written as JSON (``--json``, default ``benchmarks/results/guided.json``), from which the table in
docs/layered.md is generated (``python benchmarks/tables.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results" / "guided.json"
DEFAULT_LAYERS = ("sim:leather?size=64", "sim:stone?size=64")


def fitted(spec: str) -> Path:
    """A model of ``spec`` fitted once with ``dynbtf fit --minutes 2`` (kept in the user's cache)."""
    from dynbtf.io import user_cache_dir

    folder = (user_cache_dir("DYNBTF_BENCH_CACHE", "bench_guided") or Path(".")).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / (spec.replace(":", "_").replace("?", "_").replace("=", "").replace("&", "_") + ".dbtfm")
    if not path.exists():
        subprocess.run([sys.executable, "-m", "dynbtf", "fit", spec, "-o", str(path), "--minutes", "2"], check=True)
    return path


def region_w1(image: np.ndarray, own: np.ndarray) -> float:
    """The largest channel's W1 / std of ``image``'s pixels against ``own``'s (both ``(H, W, 3)``)."""
    from dynbtf.synthesis.quality import w1_over_std

    return float(w1_over_std(image.reshape(-1, 3), own.reshape(-1, 3)).max())


def band_half_widths(layered, resolution: int) -> tuple[float, float]:
    """The measured half-width of the boundary band on each side (uv units): the largest ``|u - 0.5|`` of a pixel
    column where both layers show."""
    u = (np.arange(resolution) + 0.5) / resolution
    v = (np.arange(resolution * 4) + 0.5) / (resolution * 4)
    uv = np.stack(np.meshgrid(u, v, indexing="xy"), -1).reshape(-1, 2)
    share = layered.weight(uv).reshape(len(v), len(u)).mean(0)  # of layer 1, per column
    both = (share > 0.005) & (share < 0.995)
    distance = u - 0.5
    left = distance[both & (distance < 0)]
    right = distance[both & (distance > 0)]
    return (float(-left.min()) if left.size else 0.0), (float(right.max()) if right.size else 0.0)


def cost_ratios(layered, own, width: float, queries: int, seed: int) -> tuple[float, float]:
    """Seconds of ``layered.eval`` over those of ``own.eval`` on the same queries: away from the band, inside it."""
    rng = np.random.default_rng(seed)

    def directions():
        w = rng.normal(size=(queries, 3))
        w[:, 2] = np.abs(w[:, 2]) + 0.3
        return w / np.linalg.norm(w, axis=1, keepdims=True)

    wv, wl = directions(), directions()
    away = np.stack([rng.uniform(0.0, 0.5 - 2 * width, queries), rng.uniform(0, 50, queries)], 1)
    band = np.stack([rng.uniform(0.5 - width, 0.5 + width, queries), rng.uniform(0, 50, queries)], 1)

    def best(fn) -> float:
        fn()
        times = []
        for _ in range(3):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times)

    t_own_away = best(lambda: own.eval(away, wv, wl))
    t_away = best(lambda: layered.eval(away, wv, wl))
    t_own_band = best(lambda: own.eval(band, wv, wl))
    t_band = best(lambda: layered.eval(band, wv, wl))
    return t_away / t_own_away, t_band / t_own_band


def guidance_row(path: Path, seed: int, classes: int, repeats: int, method: str = "hist") -> dict:
    """Exemplar guidance on one material: a target whose left half asks for class 0 and right half for class 1 over
    ``repeats`` x ``repeats`` exemplar repeats, sampled at one query per texel. Measured: the share of points whose
    content (:func:`~dynbtf.synthesis.guided_blending.source_labels`: the label under their sample of largest weight,
    or for struct the label of the texel read) is their target's, per half and overall; the repetition score
    (:func:`dynbtf.synthesis.quality.repetition_score` of the synthesized features) of each half, guided over the
    unguided ``method`` (hist or struct, with its automatic cells) with the same seed; the synthesis cost of a
    query (no decoder), guided over unguided, both on the fused CPU kernel."""
    import torch

    import dynbtf
    from dynbtf.guided import exemplar_classes
    from dynbtf.synthesis.guided_blending import GuidedBlending, GuidedCellQuilting, LabelField, source_labels
    from dynbtf.synthesis.quality import repetition_score

    model, _ = dynbtf.load_model(str(path))
    labels = exemplar_classes(model, classes, 0)  # the material's classes (fixed); the seed varies the synthesis
    target = LabelField(np.array([[0, 1]]), size=float(repeats), wrap="clamp")
    plane = model.positional_plane().detach()
    separate = {"separate": int(model.separate_channels)} if getattr(model, "separate_channels", 0) else {}
    if method == "struct":
        hist = dynbtf.make_synthesizer("struct", plane, seed=seed)  # (the unguided method, under hist's name)
        guided = GuidedCellQuilting(plane, seed, labels=labels, target=target, prepared=hist.prepared)
    else:
        guided = GuidedBlending(plane, seed, labels=labels, target=target, **separate)
        hist = dynbtf.make_synthesizer("hist", plane, seed=seed, **separate)
    h, w = plane.shape[:2]
    side_u, side_v = repeats * w, repeats * h
    u, v = np.meshgrid((np.arange(side_u) + 0.5) / w, (np.arange(side_v) + 0.5) / h)
    uv = torch.from_numpy(np.stack([u.ravel(), v.ravel()], -1))
    wanted = target.labels(uv)
    got = source_labels(guided, uv)
    left = wanted == 0
    f_guided = guided(uv).numpy().reshape(side_v, side_u, -1)
    f_hist = hist(uv).numpy().reshape(side_v, side_u, -1)
    half = side_u // 2
    repetition = [repetition_score(f[:, cols], (h, w))["score"] for f in (f_guided, f_hist)
                  for cols in (slice(0, half), slice(half, None))]
    sub = uv[: 50_000]
    t_guided = min(_seconds(lambda: guided(sub)) for _ in range(3))
    t_hist = min(_seconds(lambda: hist(sub)) for _ in range(3))
    cells = {}
    if method == "struct":  # struct guides whole cells: each cell's content (its majority label) against the target
        nx, ny = guided.prepared.cells
        cx, cy = np.meshgrid(np.arange(repeats * nx), np.arange(repeats * ny))
        cx, cy = torch.from_numpy(cx.ravel()), torch.from_numpy(cy.ravel())
        i, j = torch.remainder(cx, nx), torch.remainder(cy, ny)
        content = guided.cell_labels[i, j, guided.cell_choices(cx, cy)]
        asked = guided.cell_target(cx, cy)
        cells = {"cells": [int(nx), int(ny)], "cells_on_target": float((content == asked).float().mean()),
                 "cells_possible": float((guided.cell_labels[i, j] == asked[:, None]).any(1).float().mean()),
                 "cells_on_target_unguided": float((guided.cell_labels[i, j, hist.cell_choices(cx, cy)] == asked)
                                                   .float().mean())}
    row = {"seed": seed, **cells, "on_target": float((got == wanted).float().mean()),
           "on_target_left": float((got[left] == 0).float().mean()),
           "on_target_right": float((got[~left] == 1).float().mean()),
           "repetition_guided": repetition[:2], "repetition_hist": repetition[2:],
           "repetition_ratio": max(repetition[0] / repetition[2], repetition[1] / repetition[3]),
           "cost_vs_hist": t_guided / t_hist}
    print(f"guidance ({method}) seed {seed}: on target {row['on_target']:.3f} (left {row['on_target_left']:.3f}, "
          f"right {row['on_target_right']:.3f}); repetition guided / {method} {row['repetition_ratio']:.2f}x; cost "
          f"{row['cost_vs_hist']:.1f}x {method}", file=sys.stderr, flush=True)
    return row


def _seconds(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--layers", nargs=2, default=None, help="two fitted models (default: fit the two "
                                                                "simulated materials once)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--scale", type=float, default=6.0)
    parser.add_argument("--width", type=float, default=0.05)
    parser.add_argument("--resolution", type=int, default=384)
    parser.add_argument("--queries", type=int, default=200_000)
    parser.add_argument("--json", type=Path, default=RESULTS)
    parser.add_argument("--classes", type=int, default=2, help="guidance: classes of the first material")
    parser.add_argument("--repeats", type=int, default=8, help="guidance: side of the measured area, exemplar repeats")
    parser.add_argument("--struct-model", default="sim:brick_wall?size=64",
                        help="guided struct: a structured material (a spec fitted once, or a model file)")
    parser.add_argument("--struct-classes", type=int, default=3,
                        help="guided struct: classes of its texels (the brick wall's 3: dark bricks, light bricks, "
                             "mortar; the target asks for classes 0 and 1)")
    args = parser.parse_args()

    import dynbtf
    from dynbtf.cpu import active_isa

    paths = [Path(p) for p in args.layers] if args.layers else [fitted(spec) for spec in DEFAULT_LAYERS]
    names = list(args.layers) if args.layers else list(DEFAULT_LAYERS)
    mask = dynbtf.ImageMask(np.array([[0.0, 1.0]]), size=1.0, wrap="clamp")  # ramp over u in [0.25, 0.75]
    view = dict(view=(0, 0), light=(30, 0), uv_rect=(0, 0, 1, 1), resolution=args.resolution)
    half = args.resolution // 2
    rows = []
    for seed in args.seeds:
        a = dynbtf.synthesized_btf(str(paths[0]), "hist", scale=args.scale, seed=seed)
        b = dynbtf.synthesized_btf(str(paths[1]), "hist", scale=args.scale, seed=seed + 1000)
        layered = dynbtf.LayeredBTF([a, b], mask, width=args.width)
        image, own_a, own_b = layered.image(**view), a.image(**view), b.image(**view)
        left, right = band_half_widths(layered, args.resolution)
        away, band = cost_ratios(layered, a, args.width, args.queries, seed)
        outside = int(np.ceil(args.width * args.resolution))  # pixel columns within the band on each side
        row = {"seed": seed, "w1_left": region_w1(image[:, :half], own_a[:, :half]),
               "w1_right": region_w1(image[:, half:], own_b[:, half:]),
               "w1_left_outside_band": region_w1(image[:, :half - outside], own_a[:, :half - outside]),
               "w1_right_outside_band": region_w1(image[:, half + outside:], own_b[:, half + outside:]),
               "band_left": left, "band_right": right,
               "width": args.width, "cost_away": away, "cost_band": band}
        rows.append(row)
        print(f"seed {seed}: W1/std left {row['w1_left']:.4f}, right {row['w1_right']:.4f}; band half-width "
              f"{left:.4f} | {right:.4f} uv ({left / args.width:.2f}x | {right / args.width:.2f}x of {args.width:g}); "
              f"cost {away:.2f}x away, {band:.2f}x in the band", file=sys.stderr, flush=True)
    guidance = [guidance_row(paths[0], seed, args.classes, args.repeats) for seed in args.seeds]
    struct_path = Path(args.struct_model) if Path(args.struct_model).is_file() else fitted(args.struct_model)
    guidance_struct = [guidance_row(struct_path, seed, args.struct_classes, args.repeats, "struct")
                       for seed in args.seeds]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip()
    command = "python benchmarks/bench_guided.py" + ("" if args.layers is None else " --layers A B")
    data = {"benchmark": "guided", "command": command, "commit": commit, "cpu": _cpu_name(),
            "cores": os.cpu_count(), "cpu_isa": active_isa(), "layers": names, "scale": args.scale,
            "resolution": args.resolution, "queries": args.queries, "rows": rows,
            "guidance": {"model": names[0], "classes": args.classes, "repeats": args.repeats, "rows": guidance},
            "guidance_struct": {"model": args.struct_model, "classes": args.struct_classes, "repeats": args.repeats,
                                "rows": guidance_struct}}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(data, indent=1) + "\n")
    print(f"wrote {args.json}", file=sys.stderr)


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


if __name__ == "__main__":
    main()
