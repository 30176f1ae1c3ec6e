"""Wall time of ``dynbtf demo`` with its default settings (the README's main command), per instruction-set level.

Run: ``python benchmarks/bench_demo.py [--isa avx2 avx512bf16] [--minutes 10]``. For each level (default: AVX2,
forced where the CPU has more, and the CPU's own level), the demo runs in a process of its own started with that
level's environment (:func:`dynbtf.cpu.isa_environment`), into a fresh output folder, with empty numba,
native-kernel and compiled-material caches (what a first run on a new machine meets), and its stages' wall times,
the total and the report's held-out PSNR are recorded. Writes ``--json`` (default
``benchmarks/results/demo.json``; docs/results.md's Speed row is generated from it). The demo's target: its
budget, 10 minutes, on 2 cores of an AVX2 CPU. Timings on shared machines move by 10-50%.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def run_one(args) -> dict:
    """The demo in this process: its stages' seconds, the total and the report's numbers."""
    from dynbtf.cpu import active_isa
    from dynbtf.demo import STAGES, DemoConfig, run_demo

    with tempfile.TemporaryDirectory(prefix="dynbtf-bench-demo-") as out:
        t0 = time.perf_counter()
        results = run_demo(DemoConfig(output=str(Path(out) / "demo"), minutes=args.minutes, material=args.material,
                                      size=args.size))
        total = time.perf_counter() - t0
    mean = results["evaluate"]["mean"]
    return {"isa": active_isa(), "total_seconds": total, "stages": {s: results[s]["seconds"] for s in STAGES},
            "held_out_psnr": mean["psnr"], "flip": mean["flip"], "fit_finished": bool(results["fit"]["finished"])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--isa", nargs="+", default=None, help="levels to run (default: avx2 and the CPU's own)")
    parser.add_argument("--minutes", type=float, default=10.0, help="the demo's time budget (default 10)")
    parser.add_argument("--material", default="leather")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "demo.json")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(run_one(args)))
        return
    from results_io import header, write_result

    from dynbtf.cpu import ISAS, hardware_isa, isa_environment

    levels = args.isa or sorted({"avx2", hardware_isa()} & set(ISAS), key=ISAS.index)
    rows = []
    for isa in levels:
        with tempfile.TemporaryDirectory(prefix="dynbtf-bench-demo-caches-") as caches:
            env = {k: v for k, v in os.environ.items() if k not in isa_environment(isa)} | isa_environment(isa) | {
                "NUMBA_CACHE_DIR": str(Path(caches) / "numba"), "DYNBTF_NATIVE_CACHE": str(Path(caches) / "native"),
                "DYNBTF_COMPILED_CACHE": str(Path(caches) / "compiled")}
            command = [sys.executable, __file__, "--worker", "--minutes", str(args.minutes), "--material",
                       args.material, "--size", str(args.size)]
            done = subprocess.run(command, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            sys.stderr.write(done.stderr[-4000:])
            raise SystemExit(f"level {isa}: the demo failed")
        row = json.loads(done.stdout.strip().splitlines()[-1]) | {"forced": isa != hardware_isa()}
        rows.append(row)
        stages = ", ".join(f"{s} {t:.0f} s" for s, t in row["stages"].items())
        print(f"[{isa}{' forced' if row['forced'] else ''}] {row['total_seconds'] / 60:.2f} min ({stages}); held-out "
              f"PSNR {row['held_out_psnr']:.2f} dB", file=sys.stderr, flush=True)
    result = header("demo", "bench_demo.py") | {"minutes": args.minutes, "material": args.material,
                                                "size": args.size, "conditions": "empty numba, native-kernel and "
                                                "compiled-material caches; a fresh output folder", "rows": rows}
    write_result(args.json, result)


if __name__ == "__main__":
    main()
