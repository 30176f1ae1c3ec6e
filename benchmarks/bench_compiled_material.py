"""What a compiled material saves: a second process renders without fitting again, a demo rerun compiles nothing.

Two measurements, each command run as a user runs it (a fresh process, its wall time), with a compiled-material
cache of their own (an empty ``DYNBTF_COMPILED_CACHE``):

1. **A render in a second process.** A 64 x 64 Triple Plane (``dynbtf fit 'sim:leather?size=64' --repr triple
   --minutes 1``) is compiled with footprints (``dynbtf compile m.dbtfm``), then ``dynbtf render m.dbtfm -o a.png
   --size 64 --spp 1`` runs in another process: its wall time and the render's own seconds (what the command
   prints), next to the compile's wall time.
2. **A demo rerun with the model unchanged** (unless ``--no-demo``): ``dynbtf demo -o DIR`` from scratch, then
   again after removing ``DIR/stages/synthesis.json`` (the synthesis stage and the later ones are redone, the fit
   is kept): the synthesis and render stages' seconds of both runs (``DIR/stages/*.json``).

Run: ``python benchmarks/bench_compiled_material.py [--no-demo]``. Written as JSON (``--json``, default
``benchmarks/results/compiled_material.json``) with the command, the commit and the machine;
docs/compiled_material.md's table and a row of docs/results.md's Speed summary are generated from it
(``python benchmarks/tables.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run(command: list[str], env: dict, cwd: Path) -> tuple[float, str]:
    """Wall seconds and standard output + error of ``command`` (raises with its output if it fails)."""
    t0 = time.perf_counter()
    done = subprocess.run(command, env=env, cwd=cwd, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
    return seconds, done.stdout + done.stderr


def stage_seconds(demo: Path) -> dict:
    """Each demo stage's seconds (``DIR/stages/<stage>.json``)."""
    return {p.stem: json.loads(p.read_text()).get("seconds") for p in sorted((demo / "stages").glob("*.json"))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-demo", dest="demo", action="store_false", help="skip the demo rerun")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" /
                        "compiled_material.json")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result

    work = Path(tempfile.mkdtemp(prefix="dynbtf-bench-compiled-"))
    env = dict(os.environ, DYNBTF_COMPILED_CACHE=str(work / "cache"))
    dynbtf = [sys.executable, "-m", "dynbtf"]
    run(dynbtf + ["fit", "sim:leather?size=64", "--repr", "triple", "-o", "m.dbtfm", "--minutes", "1"], env, work)
    compile_seconds, _ = run(dynbtf + ["compile", "m.dbtfm"], env, work)
    render_wall, out = run(dynbtf + ["render", "m.dbtfm", "-o", "a.png", "--size", "64", "--spp", "1"], env, work)
    render_seconds = float(re.search(r"spp, [a-z0-9_]+, ([0-9.]+) s", out).group(1))
    print(f"compile {compile_seconds:.1f} s; render in a second process {render_wall:.1f} s wall, "
          f"{render_seconds:.1f} s of it the render")
    rows = [{"what": "render of a 64 x 64 texel model, footprints on, in a second process",
             "how": "`dynbtf compile m.dbtfm`, then `dynbtf render m.dbtfm -o a.png --size 64 --spp 1`",
             "result": "{wall_seconds:.1f} s wall time, {render_seconds:.1f} s of it the render (the compile: "
                       "{compile_seconds:.0f} s)",
             "values": {"wall_seconds": render_wall, "render_seconds": render_seconds,
                        "compile_seconds": compile_seconds}}]
    if args.demo:
        demo = work / "demo"
        run(dynbtf + ["demo", "-o", str(demo)], env, work)
        first = stage_seconds(demo)
        (demo / "stages" / "synthesis.json").unlink()
        run(dynbtf + ["demo", "-o", str(demo)], env, work)
        again = stage_seconds(demo)
        print(f"demo: synthesis {first['synthesis']:.1f} s then {again['synthesis']:.1f} s, render "
              f"{first['render']:.1f} s then {again['render']:.1f} s")
        rows.append({"what": "`dynbtf demo` rerun with the model unchanged (synthesis and later stages redone)",
                     "how": "`dynbtf demo -o DIR`, then `rm DIR/stages/synthesis.json; dynbtf demo -o DIR`",
                     "result": "synthesis stage {synthesis_seconds:.1f} s, render stage {render_seconds:.1f} s "
                               "({synthesis_seconds_compiled:.0f} s and {render_seconds_compiled:.0f} s in the first "
                               "run, which compiled everything)",
                     "values": {"synthesis_seconds": again["synthesis"], "render_seconds": again["render"],
                                "synthesis_seconds_compiled": first["synthesis"],
                                "render_seconds_compiled": first["render"]}})
    write_result(args.json, header("compiled_material", "bench_compiled_material.py") | {
        "conditions": "each command in a fresh process with an empty compiled-material cache of its own; one run",
        "rows": rows})


if __name__ == "__main__":
    main()
