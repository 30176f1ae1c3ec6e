"""Wall time of ``dynbtf demo`` with its default settings (the README's main command).

Run: ``python benchmarks/bench_demo.py [--output DIR] [--minutes 10]``. A fresh
output directory is used so no stage is skipped; the script prints each
stage's wall time, the total, and whether it met the budget. Not a test:
timings on shared machines move by 10-50%.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

from dynbtf.demo import STAGES, DemoConfig, run_demo


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=None, help="output directory (default: a fresh temporary one)")
    parser.add_argument("--minutes", type=float, default=10.0, help="the demo's time budget")
    parser.add_argument("--material", default="leather")
    parser.add_argument("--size", type=int, default=128)
    args = parser.parse_args()
    out = Path(args.output or tempfile.mkdtemp(prefix="dynbtf-bench-demo-"))
    if out.exists():
        shutil.rmtree(out)
    import torch

    print(f"cpu threads: torch {torch.get_num_threads()}, os {os.cpu_count()}; output {out}")
    t0 = time.perf_counter()
    results = run_demo(DemoConfig(output=str(out), minutes=args.minutes, material=args.material, size=args.size))
    total = time.perf_counter() - t0
    print("\nstage           seconds")
    for stage in STAGES:
        print(f"{stage:<14} {results[stage]['seconds']:8.1f}")
    print(f"{'total':<14} {total:8.1f}  ({total / 60:.2f} min; budget {args.minutes:g} min: "
          f"{'met' if total <= args.minutes * 60 else 'EXCEEDED'})")
    ev = results["evaluate"]["mean"]
    print(f"held-out PSNR {ev['psnr']:.2f} dB, DSSIM {ev['dssim']:.4f}, FLIP {ev['flip']:.4f}; "
          f"training finished: {results['fit']['finished']}")
    for row in results["render"]["renders"]:
        print(f"render {row['scene']:<6} {row['lighting']:<5} {row['method']:<4} {row['size']}^2 {row['spp']} spp: "
              f"{row['seconds']:.1f} s (compile {row['compile_seconds']:.1f} s)")
    (out / "bench_demo.json").write_text(json.dumps({"total_seconds": total, "stages": {
        s: results[s]["seconds"] for s in STAGES}}, indent=1))


if __name__ == "__main__":
    main()
