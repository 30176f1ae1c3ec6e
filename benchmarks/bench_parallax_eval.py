"""What parallax costs at evaluation: the synthesized BTF with and without its ray march, side by side.

Usage::

    python benchmarks/bench_parallax_eval.py [--size 128] [--queries 500000] [--methods hist,hex] [--max-theta 75]
                                             [--json benchmarks/results/parallax_eval.json]

Two models of the same size are built: a Triple Plane and a ``triple-parallax`` model whose
height field is the simulated stone's (pebbles up to ~5 texels high at 128^2; its features are
random: speed does not depend on their values). For each synthesis method, the same queries
(uv random in ``[0, 45)^2`` exemplar repeats, the paper's 45x; view directions uniform in solid
angle up to ``--max-theta``, lights random) are evaluated with
:meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` by both; it prints queries/s of each and their
ratio, and the same ratio for views at normal incidence only (no march: the cost of the
representation itself), at ``--max-theta`` only (the longest marches) and at one 45-degree view for
every query (a camera's rays over a small patch: coherent marches). One warm-up run,
then the best of ``--repeats``. Timings on shared machines move 10-50% between runs: compare
the ratios of one run. The rows are written to ``--json`` (README.md's relief line is generated from them).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from dynbtf.data.open import open_btf
from dynbtf.representations.parallax import ParallaxTriplePlane
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.synthesized import synthesized_btf


def directions(n: int, rng: np.random.Generator, max_theta: float, fixed_theta: float | None = None) -> np.ndarray:
    """Unit vectors ``(n, 3)``: uniform in solid angle up to ``max_theta`` degrees, or all at ``fixed_theta``."""
    if fixed_theta is None:
        cos_theta = 1.0 - rng.random(n) * (1.0 - math.cos(math.radians(max_theta)))
    else:
        cos_theta = np.full(n, math.cos(math.radians(fixed_theta)))
    phi = rng.random(n) * 2 * math.pi
    sin_theta = np.sqrt(1.0 - cos_theta ** 2)
    return np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), cos_theta], axis=-1)


def best_time(fn, repeats: int) -> float:
    fn()  # warm-up: kernel compilation, allocator, caches
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--queries", type=int, default=500_000)
    parser.add_argument("--methods", default="hist,hex")
    parser.add_argument("--max-theta", type=float, default=75.0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "parallax_eval.json")
    args = parser.parse_args()

    stone = open_btf(f"sim:stone?size={args.size}")
    renderer = stone.renderer
    height = renderer.height.double()[renderer.stride // 2::renderer.stride, renderer.stride // 2::renderer.stride]
    flat = TriplePlane(args.size, args.size, seed=0)
    relief = ParallaxTriplePlane(args.size, args.size, seed=0)
    relief.set_height(height)
    depth = (float(height.max()) - float(height.min())) * args.size
    print(f"relief depth {depth:.1f} texels; {args.queries:,} queries per run; best of {args.repeats} after a warm-up")

    rng = np.random.default_rng(0)
    uv = rng.random((args.queries, 2))  # with scale 45: [0, 45) exemplar repeats
    lights = directions(args.queries, rng, 80.0)
    view_sets = {"all views": directions(args.queries, rng, args.max_theta),
                 "normal view": directions(args.queries, rng, 0.0, fixed_theta=0.0),
                 f"views at {args.max_theta:g} deg": directions(args.queries, rng, 0.0, fixed_theta=args.max_theta),
                 "one view at 45 deg": np.broadcast_to(directions(1, rng, 0.0, fixed_theta=45.0),
                                                       (args.queries, 3)).copy()}
    rows = []
    print("\n| method | views | Triple Plane (M queries/s) | triple-parallax (M queries/s) | cost ratio |")
    print("|---|---|---|---|---|")
    for method in args.methods.split(","):
        btfs = {name: synthesized_btf(model, method, scale=45.0, seed=0) for name, model in
                (("flat", flat), ("relief", relief))}
        for label, views in view_sets.items():
            rates = {}
            for name, btf in btfs.items():
                with torch.no_grad():
                    seconds = best_time(lambda: btf.eval(uv, views, lights), args.repeats)
                rates[name] = args.queries / seconds / 1e6
            print(f"| {method} | {label} | {rates['flat']:.2f} | {rates['relief']:.3f} | "
                  f"{rates['flat'] / rates['relief']:.1f}x |", flush=True)
            rows.append({"method": method, "views": label, "flat_mqps": rates["flat"],
                         "relief_mqps": rates["relief"], "cost_ratio": rates["flat"] / rates["relief"]})
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result

    write_result(args.json, header(args.json.stem, "bench_parallax_eval.py") | {
        "btf": f"sim:stone?size={args.size}", "relief_depth_texels": depth, "queries": args.queries,
        "repeats": args.repeats, "max_theta": args.max_theta, "rows": rows})


if __name__ == "__main__":
    main()
