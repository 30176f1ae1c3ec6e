"""fit-many throughput: a manifest of small materials on Ray (single-thread workers) vs sequential fits.

Four simulated materials (``sim:<material>?size=SIZE``, UBO2003 grid) are fitted with the same
options twice, in one run:

* **sequential** -- :func:`dynbtf.fit_many.fit_one` on each source in turn in this process, with
  all of the machine's threads (what four ``dynbtf fit`` runs one after the other do);
* **Ray** -- :func:`dynbtf.fit_many.fit_many` on a local Ray instance with ``--workers``
  single-thread workers, the four fits running side by side.

Both fit and evaluate (held-out PSNR, DSSIM, FLIP); the BTFs are written to stored files first
so that neither pays for simulation. Printed: the wall time of each and the throughput ratio
(materials per minute, Ray over sequential), plus each material's held-out PSNR in both runs
(they differ only by the thread count of the fused kernel's sums).

On a 2-core machine expect about 1-2x: the fused kernel already uses both cores, and Ray's
start-up (~5 s) and each worker's first import count against it. The point is that the same
manifest runs unchanged on a cluster (``dynbtf fit-many --address ...``).

Run: ``python benchmarks/bench_fit_many.py`` (about 5 minutes; ``--help`` for options). Writes
``benchmarks/results/fit_many.json`` (docs/cluster.md's table and docs/results.md's Speed row).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=48, help="texels per side of each material")
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2, help="single-thread Ray workers")
    parser.add_argument("--materials", default="leather,stone,lacquered_wood,woven_fabric")
    parser.add_argument("--json", type=Path, default=Path(__file__).parent / "results" / "fit_many.json")
    args = parser.parse_args()
    from results_io import header, write_result

    import torch

    from dynbtf.data import write_stored
    from dynbtf.data.open import open_btf
    from dynbtf.fit_many import FitTask, fit_many, fit_one

    materials = args.materials.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for m in materials:
            write_stored(root / f"{m}.dbtf", open_btf(f"sim:{m}?size={args.size}"), progress=False)
        options = {"epochs": args.epochs, "texel_groups": 16, "images_per_step": 16}
        manifest = root / "library.toml"
        manifest.write_text("[defaults]\n" + "".join(f"{k} = {v}\n" for k, v in options.items()) + "\n"
                            + "".join(f'[[source]]\nbtf = "{m}.dbtf"\n\n' for m in materials))

        threads = torch.get_num_threads()
        t0 = time.perf_counter()
        sequential = [fit_one(FitTask(m, str(root / f"{m}.dbtf"), dict(options), str(root / "sequential"),
                                      cpus=threads)) for m in materials]
        t_sequential = time.perf_counter() - t0
        torch.set_num_threads(threads)

        t0 = time.perf_counter()
        parallel = fit_many(manifest, root / "ray", cpus=args.workers, cpus_per_task=1, progress=False)
        t_ray = time.perf_counter() - t0

    print(f"{len(materials)} materials of {args.size} x {args.size} texels (81 x 81 directions), {args.epochs} epochs "
          f"each, 16 texel groups x 16 pairs per step")
    print(f"sequential, {threads} threads per fit:      {t_sequential:7.1f} s  "
          f"({60 * len(materials) / t_sequential:.2f} materials/min)")
    print(f"Ray, {args.workers} single-thread workers:        {t_ray:7.1f} s  "
          f"({60 * len(materials) / t_ray:.2f} materials/min)")
    print(f"throughput ratio Ray / sequential: {t_sequential / t_ray:.2f}x")
    print("held-out PSNR (dB, per-image peak), sequential | Ray:")
    for s, p in zip(sequential, parallel):
        print(f"  {s['name']:<16} {s.get('psnr', float('nan')):6.2f} | {p.get('psnr', float('nan')):6.2f}  "
              f"({s['status']} | {p['status']})")
    n = len(materials)
    write_result(args.json, header("fit_many", "bench_fit_many.py") | {
        "conditions": f"{n} simulated materials of {args.size} x {args.size} texels (81 x 81 directions), "
                      f"{args.epochs} epochs each, fitted and evaluated twice in one run",
        "rows": [{"run": "sequential", "label": f"one after the other, {threads} threads per fit",
                  "wall_seconds": t_sequential, "materials_per_minute": 60 * n / t_sequential},
                 {"run": "ray", "label": f"`fit_many` on a local Ray instance, {args.workers} single-thread workers",
                  "wall_seconds": t_ray, "materials_per_minute": 60 * n / t_ray}],
        "held_out_psnr": [{"material": s["name"], "sequential": s.get("psnr"), "ray": p.get("psnr")}
                          for s, p in zip(sequential, parallel)]})


if __name__ == "__main__":
    main()
