"""How long `dynbtf simulate` takes per material (128 x 128 texels, UBO2003 grid, float16).

Usage: python benchmarks/simulator_speed.py [--size 128] [--grid ubo2003] [--materials stone,leather]

Writes each material's stored BTF into a temporary directory exactly as the
command does (dynbtf.data.stored.write_stored streaming SimulatedBTF.view_images)
and prints wall-clock seconds, plus a breakdown of one material's stages
(material tabulation, shadow maps of all lights, view traces, shading). The
seconds per material are written to ``--json`` (default
``benchmarks/results/simulator.json``; docs/results.md's Speed row is generated
from it). Times on a shared machine move by tens of percent between runs:
compare within a run.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from dynbtf.data.simulated import MATERIALS, simulated_btf
from dynbtf.data.stored import write_stored


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--grid", default="ubo2003")
    ap.add_argument("--materials", default=",".join(MATERIALS))
    ap.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "simulator.json")
    args = ap.parse_args()
    print(f"torch threads: {torch.get_num_threads()}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.materials.split(","):
            source = simulated_btf(name, size=args.size, grid=args.grid)
            start = time.perf_counter()
            write_stored(Path(tmp) / f"{name}.dbtf", source, progress=False)
            total = time.perf_counter() - start
            rows.append({"material": name, "images": source.n_pairs, "seconds": total})
            print(f"{name:15s} {source.n_pairs} images of {args.size}x{args.size}: {total:6.1f} s "
                  f"({source.n_pairs / total:6.0f} images/s)")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result

    write_result(args.json, header("simulator", "simulator_speed.py") | {
        "size": args.size, "grid": args.grid, "threads": torch.get_num_threads(), "rows": rows})
    # stage breakdown for the first material
    name = args.materials.split(",")[0]
    source = simulated_btf(name, size=args.size, grid=args.grid)
    t0 = time.perf_counter()
    r = source.renderer
    t1 = time.perf_counter()
    for w in source.lights:
        r.light_maps(w)
    t2 = time.perf_counter()
    for w in source.views:
        r.view_trace(w)
    t3 = time.perf_counter()
    for w in source.views:
        r.render(w, source.lights)
    t4 = time.perf_counter()
    print(f"{name} stages: tabulate + normals + sky view {t1 - t0:.2f} s, {source.n_lights} shadow maps "
          f"{t2 - t1:.2f} s, {source.n_views} view traces {t3 - t2:.2f} s, shading (views x lights, last "
          f"{r._view_cache} traces cached) {t4 - t3:.2f} s")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
