"""Time budgets that hold: the wall time of ``dynbtf fit X -o Y --minutes M`` per representation choice.

Run: ``python benchmarks/bench_budget.py`` (the sum of the budgets, plus a little: about 45 minutes at the
defaults; ``--minutes 1`` for a quick look). For each ``--repr`` (default: ``auto``, ``triple``,
``triple-parallax``) and each budget ``M`` (default: 1, 3 and 10 minutes) it runs the command in a fresh process,
as a user would, on the same BTF (default: a 64 x 64 leather on the UBO2014 grid, 151 x 151 directions, whose
stereo estimate leaves ``auto`` to a race), and records the wall time from the process's start to its exit, whether
the model file was written, the kind chosen and the model's held-out PSNR. The target: every run writes its model
within ``M`` minutes plus 10%. ``--isa avx2`` runs the commands on the AVX2 path (``DYNBTF_CPU_ISA``).

The rows are written as JSON (``--json``, default ``benchmarks/results/budget.json``); docs/results.md's table is
generated from it (``python benchmarks/tables.py``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "budget.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--btf", default="sim:leather?size=64&grid=ubo2014")
    parser.add_argument("--repr", nargs="+", default=["auto", "triple", "triple-parallax"])
    parser.add_argument("--minutes", nargs="+", type=float, default=[1.0, 3.0, 10.0])
    parser.add_argument("--isa", default=None, help="a level of dynbtf.cpu to force (default: the CPU's own)")
    parser.add_argument("--json", type=Path, default=RESULTS)
    args = parser.parse_args()

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result  # noqa: E402

    from dynbtf.cpu import active_isa, isa_environment
    from dynbtf.representations.model_file import read_model_metadata

    env = dict(os.environ)
    if args.isa:
        env = {k: v for k, v in env.items() if k not in isa_environment(args.isa)} | isa_environment(args.isa)
    rows = []
    for minutes in args.minutes:
        for kind in args.repr:
            with tempfile.TemporaryDirectory() as workdir:
                output = Path(workdir) / "m.dbtfm"
                command = [sys.executable, "-m", "dynbtf", "fit", args.btf, "-o", str(output), "--repr", kind,
                           "--minutes", f"{minutes:g}", "--quiet"]
                t0 = time.perf_counter()
                done = subprocess.run(command, env=env, capture_output=True, text=True)
                wall = time.perf_counter() - t0
                row = {"repr": kind, "minutes": minutes, "wall_seconds": wall, "exit_status": done.returncode,
                       "written": output.is_file()}
                if output.is_file():
                    meta = read_model_metadata(output)
                    provenance = meta.get("provenance", {})
                    row |= {"kind": meta["kind"], "held_out_psnr": provenance.get("held_out_psnr_monitor"),
                            "steps": provenance.get("schedule", {}).get("steps")}
                else:
                    row["stderr"] = done.stderr[-2000:]
            rows.append(row)
            print(f"--repr {kind} --minutes {minutes:g}: {wall / 60:.2f} min ({100 * wall / (60 * minutes):.0f}%), "
                  f"exit {done.returncode}, model {'written' if row['written'] else 'NOT written'}"
                  + (f", {row['kind']} {row['held_out_psnr']:.2f} dB" if row.get("held_out_psnr") else ""),
                  flush=True)
    isa = args.isa or active_isa()
    write_result(args.json, header("budget", "bench_budget.py") | {"isa": isa, "btf": args.btf, "rows": rows})


if __name__ == "__main__":
    main()
