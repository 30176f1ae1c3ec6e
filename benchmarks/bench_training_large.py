"""Training at full size: samples/s on a 400 x 400, 151 x 151 DFMF file vs a cached 128 x 128 BTF, and peak RSS.

The data our users own are UBO2014 files (400 x 400 texels, 151 x 151 directions:
22,801 images, 41 GiB as float32); a 128 x 128 BTF of the UBO2003 grid fits the
float16 image cache (0.65 GB) and trains at the fused kernel's speed. This
benchmark runs :func:`dynbtf.training.fit` on both, in one run, for two recipes:

* **paper batches** -- 16 whole images per step (``texel_groups=1``);
* **fast** -- 64 texel groups per step (1,024 pairs; what ``dynbtf fit`` chooses).

On the full-size file every step's texels come straight from the DFMF factors
(:meth:`dynbtf.data.base.BTFSource.read_texels`, prefetched on a background thread
while the kernel runs). Each measurement runs in its own process (so peak RSS is
that run's), for ``--steps`` optimizer steps after ``--warmup`` steps; samples/s is
samples over the steps' wall time, data waits included. Printed: both rates,
their ratio (target: at least 0.8), and the full-size runs' peak RSS (target: at
most 4 GB).

The full-size file is written once by ``dynbtf simulate leather --grid ubo2014
--size 400 -o FILE`` (``--components``, default 96: 105 MB; about 4 minutes on 2
cores) unless ``--btf`` names one.

A run that writes the file records its wall time, size and peak memory under ``file_written`` of ``--json``.

``--subtexel W[,W ...]`` measures each sub-texel weight (``TrainConfig.subtexel``; the default recipe trains the
Triple Plane with 0.25), ``--isa LEVEL`` runs the workers on that level of :mod:`dynbtf.cpu` (e.g. ``avx2`` on a CPU
with more), and ``--json PATH`` writes the rows, each with the projected time of a full-size fit to within 0.5 dB of
its converged PSNR: ``--steps-to-converge`` (default 5,370: measured by ``measure_fit_curves.py`` on this file with
the fast recipe, without the term) times the step's median time.

``--repr triple-parallax`` measures the parallax Triple Plane instead: each run first
estimates the height by stereo as ``dynbtf fit`` does
(:func:`dynbtf.training.stereo_height.auto_stereo_options`; its time is printed, its
memory is in the peak RSS), then trains with view-coherent batches.

Run: ``python benchmarks/bench_training_large.py`` (about 10 minutes with the file present;
``--repr triple-parallax --recipes fast``: the parallax model, the fast recipe only).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RECIPES = {"paper batches": dict(texel_groups=1, lr_scale=1.0), "fast": dict(texel_groups=64, lr_scale=6.0)}


def build(kind: str, source, seed: int = 0):
    """``(representation, stereo seconds)``: a fresh model of ``kind`` for ``source``, as ``dynbtf fit`` builds it
    (``triple-parallax``: with its stereo height, :func:`~dynbtf.training.fitters.parallax_stereo_options`,
    and :func:`~dynbtf.training.fitters.parallax_size_options`)."""
    if kind == "triple":
        from dynbtf.representations.triple_plane import TriplePlane
        return TriplePlane(source.height, source.width, seed=seed), 0.0
    if kind != "triple-parallax":
        raise SystemExit(f"--repr: expected triple or triple-parallax, got {kind!r}")
    from dynbtf.representations.parallax import ParallaxTriplePlane
    from dynbtf.training.fitters import parallax_size_options, parallax_stereo_options
    from dynbtf.training.stereo_height import stereo_height

    rep = ParallaxTriplePlane(source.height, source.width, seed=seed, **parallax_size_options(source))
    start = time.perf_counter()
    rep.set_height(stereo_height(source, **parallax_stereo_options(source)))
    return rep, time.perf_counter() - start


def worker(spec: str, recipe: str, steps: int, warmup: int, memory_mb: float, kind: str = "triple",
           subtexel: float = 0.0) -> dict:
    """One measurement in this process: rate over ``steps`` steps after ``warmup``, and peak RSS."""
    import numpy as np

    from dynbtf.data.open import open_btf
    from dynbtf.training import TrainConfig, fit

    source = open_btf(spec)
    rep, stereo_seconds = build(kind, source)
    times, samples = [], []

    class Enough(Exception):
        pass

    def callback(info):
        if info["global_step"] > warmup:
            times.append(info["step_seconds"])
            samples.append(info["samples"])
        if len(times) >= steps:
            raise Enough

    config = TrainConfig(epochs=1, monitor_pairs=0, memory_budget_mb=memory_mb, subtexel=subtexel,
                         **RECIPES[recipe])
    with tempfile.TemporaryDirectory() as tmp:
        try:
            fit(rep, source, config, Path(tmp) / "m.dbtfm", progress=False, callback=callback)
        except Enough:
            pass
    return {"samples_per_second": float(np.sum(samples) / np.sum(times)), "steps": len(times),
            "step_seconds": float(np.median(times)), "stereo_seconds": stereo_seconds,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9}


def measure(spec: str, recipe: str, args, subtexel: float = 0.0) -> dict:
    from dynbtf.cpu import isa_environment

    cmd = [sys.executable, __file__, "--worker", spec, "--recipe", recipe, "--steps", str(args.steps),
           "--warmup", str(args.warmup), "--memory-mb", str(args.memory_mb), "--repr", args.repr,
           "--subtexel", f"{subtexel:g}"]
    env = dict(os.environ)
    if args.isa:
        env = {k: v for k, v in env.items() if k not in isa_environment(args.isa)} | isa_environment(args.isa)
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--btf", default=None, help="a 400 x 400, 151 x 151 .btf file (default: simulate one)")
    parser.add_argument("--cache-dir", default=os.path.join(tempfile.gettempdir(), "dynbtf-bench"),
                        help="where the simulated file is kept (default %(default)s)")
    parser.add_argument("--components", type=int, default=96, help="SVD components of the simulated file")
    parser.add_argument("--reference", default="sim:leather?size=128", help="the cached BTF (default %(default)s)")
    parser.add_argument("--steps", type=int, default=40, help="timed steps per measurement")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps first")
    parser.add_argument("--memory-mb", type=float, default=2048.0, help="image cache budget (as dynbtf fit)")
    parser.add_argument("--repr", default="triple", choices=["triple", "triple-parallax"],
                        help="the representation (default %(default)s)")
    parser.add_argument("--recipes", default=",".join(RECIPES), help="comma-separated recipes (default %(default)s)")
    parser.add_argument("--subtexel", default="0", help="comma-separated sub-texel weights (default %(default)s)")
    parser.add_argument("--isa", default=None, help="a level of dynbtf.cpu to run the workers on (default: the "
                                                    "CPU's own)")
    parser.add_argument("--steps-to-converge", type=int, default=5370,
                        help="steps of a full-size fit to within 0.5 dB of converged, for the projection")
    parser.add_argument("--json", type=Path, default=None, help="write the rows here (benchmark JSON)")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--recipe", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.recipe, args.steps, args.warmup, args.memory_mb, args.repr,
                                float(args.subtexel))))
        return
    big = args.btf
    written = None  # the file's writing, when this run wrote it: wall seconds and the process's peak RSS
    if big is None:
        big = str(Path(args.cache_dir) / f"leather400_c{args.components}.btf")
        if not Path(big).exists():
            Path(args.cache_dir).mkdir(parents=True, exist_ok=True)
            print(f"writing {big} (once) ...", flush=True)
            command = ["dynbtf", "simulate", "leather", "--grid", "ubo2014", "--size", "400", "--components",
                       str(args.components), "-o", big, "--quiet"]
            started = time.perf_counter()
            subprocess.run([sys.executable, "-m", *command], check=True)
            written = {"command": " ".join(command), "seconds": time.perf_counter() - started,
                       "bytes": Path(big).stat().st_size,  # ru_maxrss: kB on Linux; the largest child so far
                       "peak_rss_gb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 1e9}
            print(f"wrote it in {written['seconds'] / 60:.1f} min, peak RSS {written['peak_rss_gb']:.2f} GB")
    print(f"full size: {big} ({Path(big).stat().st_size / 1e6:.0f} MB); cached reference: {args.reference}; "
          f"representation: {args.repr}")
    print(f"{'recipe':<14} {'sub-texel':>9} {'cached 128^2 (M samples/s)':>27} {'400^2 DFMF (M samples/s)':>25} "
          f"{'ratio':>6} {'RSS 400^2 (GB)':>15} {'step 400^2 (s)':>15} {'stereo 128^2 / 400^2 (s)':>25}")
    rows = []
    for recipe in args.recipes.split(","):
        for weight in (float(w) for w in args.subtexel.split(",")):
            small = measure(args.reference, recipe, args, weight)
            large = measure(big, recipe, args, weight)
            ratio = large["samples_per_second"] / small["samples_per_second"]
            print(f"{recipe:<14} {weight:>9g} {small['samples_per_second'] / 1e6:>27.2f} "
                  f"{large['samples_per_second'] / 1e6:>25.2f} {ratio:>6.2f} {large['peak_rss_gb']:>15.2f} "
                  f"{large['step_seconds']:>15.3f} {small['stereo_seconds']:>11.0f} / {large['stereo_seconds']:>11.0f}",
                  flush=True)
            rows.append({"recipe": recipe, "subtexel": weight, "cached_msps": small["samples_per_second"] / 1e6,
                         "large_msps": large["samples_per_second"] / 1e6, "ratio": ratio,
                         "peak_rss_gb": large["peak_rss_gb"], "step_seconds": large["step_seconds"],
                         "projected_minutes": args.steps_to_converge * large["step_seconds"] / 60.0,
                         "stereo_seconds_cached": small["stereo_seconds"],
                         "stereo_seconds_large": large["stereo_seconds"]})
    print("targets: ratio >= 0.8, RSS <= 4 GB")
    if args.json is not None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from results_io import header, write_result

        from dynbtf.cpu import hardware_isa, isa_description

        write_result(args.json, header("training_large", "bench_training_large.py") | {
            "isa": args.isa or hardware_isa(), "isa_description": isa_description(args.isa),
            "representation": args.repr, "steps": args.steps, "warmup": args.warmup,
            "steps_to_converge": args.steps_to_converge, "reference": args.reference, "file_written": written,
            "rows": rows})


if __name__ == "__main__":
    main()
