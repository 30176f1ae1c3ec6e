"""Training throughput per instruction-set level: the paper's recipe run naively vs dynbtf's whole-image path.

Run: ``python benchmarks/bench_training.py`` (about 2 minutes per level and BTF; ``--help`` for options).

For every level of :mod:`dynbtf.cpu` this CPU runs from AVX2 up (``avx2``, ``avx512``, ``avx512bf16``: the AVX2
path is forced on a CPU that has more, so it is measured wherever the benchmark runs), in a process of its own
started with that level's environment (``DYNBTF_CPU_ISA``, PyTorch's ``ATEN_CPU_CAPABILITY``, MKL and oneDNN
caps, numba's CPU), and for each BTF (default: ``sim:leather?size=64`` and ``?size=128``), it measures, on the
same Triple Plane (same initialization, same training pairs):

* **naive** -- the paper's recipe written plainly: per-sample random batches (``--naive-batch`` samples over
  random texels and training pairs), the model's forward (three ``grid_sample`` fetches, autograd MLP), L1,
  AdamW; torch's thread count the faster of 1 and all (measured first);
* **ours, paper batches** -- :func:`dynbtf.training.fit` with the paper's batches (16 whole images per step);
* **ours, fast** -- the recipe ``dynbtf fit`` uses (64 texel groups of 16 pairs each per step, lr x6);
* on ``avx512bf16``, **ours, fast, bf16** -- the same with bfloat16 products (``precision="bf16"``).

Each is timed for ``--seconds`` of training after a warm-up (the optimizer steps' own time: evaluation and
set-up excluded). Printed per row: samples/s, the ratio to naive on the same level, and the share of that
level's FMA peak (FLOP of the fused layers 2.. per sample times samples/s, over
:func:`dynbtf.decoder.native.fma_peak_flops` on as many threads, measured in the same process). The rows are
also written as JSON (``--json``, default ``benchmarks/results/training.json``): the command, the commit, the
CPU and every measured value, from which docs/results.md's table is generated.

Targets (issue "fast on the machines our users have"): ours (fast) at least 8x naive on AVX2 (forced or real),
at least 14x on AVX512-BF16. ``--convergence`` also runs the older comparison on the CPU's own level: naive for
``--naive-seconds``, then ours until it reaches naive's final held-out PSNR, and the ratio of the times.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "training.json"


# ---------------------------------------------------------------------------------------------- one level
def fused_flops_per_sample(model) -> int:
    """FLOP per sample of the fused step: layers 2.. forward, input gradients and weight gradients (2 per MAC)."""
    return 3 * sum(2 * layer.in_features * layer.out_features for layer in model.decoder.rest)


def naive_recipe(source, store, train_pairs, batch: int, seed: int):
    """``(model, step)``: a fresh Triple Plane and one optimizer step of the naive recipe on it (per-sample random
    batches of ``batch`` samples over random texels and training pairs, the model's forward, L1, AdamW)."""
    import numpy as np
    import torch

    from dynbtf.conventions import texel_centers_uv
    from dynbtf.representations.triple_plane import TriplePlane

    rep = TriplePlane(source.height, source.width, seed=seed)
    optimizer = torch.optim.AdamW(rep.param_groups())
    n = source.height * source.width
    uv_all = torch.from_numpy(texel_centers_uv(source.height, source.width)).reshape(-1, 2).float()
    views = torch.as_tensor(source.views, dtype=torch.float32)
    lights = torch.as_tensor(source.lights, dtype=torch.float32)
    images = torch.from_numpy(store.get(train_pairs)).to(torch.float16)  # (P, N, 3), decoded
    rng = np.random.default_rng(seed)

    def step():
        p = torch.from_numpy(rng.integers(0, len(train_pairs), batch))
        t = torch.from_numpy(rng.integers(0, n, batch))
        pairs = torch.from_numpy(train_pairs)[p]
        pred = rep(uv_all[t], views[pairs[:, 0]], lights[pairs[:, 1]])
        loss = (pred - images[p, t].float()).abs().mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    return rep, step


def naive_rate(source, store, train_pairs, seconds: float, batch: int, seed: int) -> tuple[float, int]:
    """Samples/s of the naive recipe (and the torch thread count it ran with: the faster of 1 and all)."""
    import torch

    _, step = naive_recipe(source, store, train_pairs, batch, seed)
    threads = torch.get_num_threads()
    speeds = {}
    for setting in sorted({1, threads}):  # the faster thread setting (OpenMP can stall on a shared machine)
        torch.set_num_threads(setting)
        step()
        t0 = time.perf_counter()
        for _ in range(3):
            step()
        speeds[setting] = 3 * batch / (time.perf_counter() - t0)
    best = max(speeds, key=speeds.get)
    torch.set_num_threads(best)
    try:
        done, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            step()
            done += batch
        return done / (time.perf_counter() - t0), best
    finally:
        torch.set_num_threads(threads)


def our_rate(source, seconds: float, seed: int, workdir: Path, warmup_steps: int = 10, details: bool = False,
             **options):
    """Samples/s of :func:`dynbtf.training.fit` (the optimizer steps' own time, after ``warmup_steps``); with
    ``details``, ``(samples/s, steps timed, seconds per step)``."""
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.training import TrainConfig, fit
    from dynbtf.training.fit import StopTraining

    timed = {"steps": 0, "seconds": 0.0, "samples": 0}

    def callback(info):
        if info["global_step"] <= warmup_steps:
            return
        timed["steps"] += 1
        timed["seconds"] += info["step_seconds"]
        timed["samples"] += info["samples"]
        if timed["seconds"] >= seconds:
            raise StopTraining("timed")

    config = TrainConfig(epochs=1000, seed=seed, held_out_fraction=0.05, monitor_pairs=0, checkpoint_every=10 ** 9,
                         **options)
    fit(TriplePlane(source.height, source.width, seed=seed), source, config, workdir / "m.dbtfm", progress=False,
        callback=callback)
    rate = timed["samples"] / timed["seconds"]
    return (rate, timed["steps"], timed["seconds"] / timed["steps"]) if details else rate


def measure_level(btfs: list[str], seconds: float, naive_seconds: float, batch: int, seed: int) -> list[dict]:
    """Every row of this process's level (see the module docstring)."""
    import numpy as np
    import torch

    from dynbtf.cpu import active_isa, isa_description
    from dynbtf.data.open import open_btf
    from dynbtf.decoder.fused_mlp import native_precisions
    from dynbtf.decoder.native import fma_peak_flops
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.training import ImageStore, held_out_split

    isa = active_isa()
    workers = torch.get_num_threads()
    peak = fma_peak_flops(isa, threads=workers, seconds=1.0)
    rows = []
    for spec in btfs:
        source = open_btf(spec)
        train_pairs, _ = held_out_split(source.n_views, source.n_lights, 0.05, seed)
        store = ImageStore(source)
        store.fill(train_pairs)
        flops = fused_flops_per_sample(TriplePlane(source.height, source.width))
        naive, threads = naive_rate(source, store, train_pairs, naive_seconds, batch, seed)
        variants = {"paper batches": dict(texel_groups=1, lr_scale=1.0, precision="fp32"),
                    "fast": dict(texel_groups=64, lr_scale=6.0, precision="fp32")}
        if "bf16" in native_precisions():
            variants["fast, bf16"] = dict(texel_groups=64, lr_scale=6.0, precision="bf16")
        base = {"isa": isa, "isa_description": isa_description(isa), "btf": spec,
                "torch_capability": torch.backends.cpu.get_cpu_capability(), "workers": workers,
                "fma_peak_gflops": peak / 1e9 if peak else None, "flop_per_sample": flops}
        rows.append(base | {"variant": "naive", "samples_per_second": naive, "torch_threads": threads})
        for name, options in variants.items():
            with tempfile.TemporaryDirectory() as workdir:
                rate = our_rate(source, seconds, seed, Path(workdir), **options)
            rows.append(base | {"variant": name, "samples_per_second": rate, "ratio_to_naive": rate / naive,
                                "gflops": rate * flops / 1e9,
                                "share_of_fma_peak": rate * flops / peak if peak else None, **options})
        del store
        print(f"[{isa}] {spec}: " + ", ".join(f"{r['variant']} {r['samples_per_second'] / 1e6:.2f} M/s"
                                              for r in rows if r["btf"] == spec), file=sys.stderr, flush=True)
        np.random.default_rng(0)  # (nothing kept between BTFs)
    return rows


# ---------------------------------------------------------------------------------------------- convergence
def held_out_psnr(rep, source, store, eval_pairs) -> float:
    """PSNR (dB) of ``rep``'s images against the BTF's at the held-out ``eval_pairs (K, 2)`` (view, light) of
    ``source``, read through ``store`` (an :class:`~dynbtf.training.ImageStore`)."""
    import torch

    from dynbtf.decoder.fused_mlp import single_intra_op_thread
    from dynbtf.training import predict_images

    se, count = 0.0, 0
    with torch.no_grad(), single_intra_op_thread():
        for k in range(0, len(eval_pairs), 8):
            chunk = eval_pairs[k:k + 8]
            target = torch.from_numpy(store.get(chunk))
            wv = torch.as_tensor(source.views[chunk[:, 0]], dtype=torch.float32)
            wl = torch.as_tensor(source.lights[chunk[:, 1]], dtype=torch.float32)
            se += float(((predict_images(rep, wv, wl) - target) ** 2).sum(dtype=torch.float64))
            count += target.numel()
    return -10.0 * math.log10(se / count)


def convergence(spec: str, naive_seconds: float, batch: int, seed: int) -> dict:
    """Naive for ``naive_seconds``; ours (the fast recipe, with each precision the CPU's training kernel has) until
    naive's final held-out PSNR (checked every 20 steps on 32 held-out pairs); the training time each needed."""
    import numpy as np

    from dynbtf.cpu import active_isa
    from dynbtf.data.open import open_btf
    from dynbtf.decoder.fused_mlp import native_precisions
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.training import ImageStore, TrainConfig, fit, held_out_split
    from dynbtf.training.fit import StopTraining

    source = open_btf(spec)
    train_pairs, held_out = held_out_split(source.n_views, source.n_lights, 0.05, seed)
    eval_pairs = held_out[np.linspace(0, len(held_out) - 1, min(32, len(held_out))).astype(int)]
    store = ImageStore(source)
    store.fill()

    def psnr(rep) -> float:
        return held_out_psnr(rep, source, store, eval_pairs)

    rep, step = naive_recipe(source, store, train_pairs, batch, seed)
    trained = 0.0
    while trained < naive_seconds:
        t0 = time.perf_counter()
        step()
        trained += time.perf_counter() - t0
    target = psnr(rep)
    ours = {}
    for precision in [p for p in ("fp32", "bf16") if p in native_precisions()]:
        model = TriplePlane(source.height, source.width, seed=seed)
        clock = {"seconds": 0.0, "reached": None, "steps": 0}

        def callback(info, model=model, clock=clock):
            clock["seconds"] += info["step_seconds"]
            clock["steps"] = info["global_step"]
            if info["global_step"] % 20 == 0 and psnr(model) >= target:
                clock["reached"] = clock["seconds"]
                raise StopTraining("reached")
            if clock["seconds"] > naive_seconds:
                raise StopTraining("budget")

        with tempfile.TemporaryDirectory() as workdir:
            fit(model, source, TrainConfig(epochs=1000, seed=seed, held_out_fraction=0.05, monitor_pairs=0,
                                           checkpoint_every=10 ** 9, texel_groups=64, lr_scale=6.0,
                                           precision=precision),
                Path(workdir) / "m.dbtfm", progress=False, callback=callback)
        ours[precision] = {"seconds_to_reach": clock["reached"], "steps": clock["steps"],
                           "speedup": naive_seconds / clock["reached"] if clock["reached"] else None}
    return {"btf": spec, "isa": active_isa(), "naive_seconds": naive_seconds, "naive_final_psnr": target,
            "held_out_pairs_checked": len(eval_pairs), "ours": ours}


# ---------------------------------------------------------------------------------------------- driver
def levels_to_measure(requested: list[str] | None) -> list[str]:
    from dynbtf.cpu import ISAS, hardware_isa

    top = ISAS.index(hardware_isa())
    available = [isa for isa in ISAS[1:top + 1]] or ["portable"]
    if requested:
        unknown = [isa for isa in requested if isa not in ISAS[:top + 1]]
        if unknown:
            raise SystemExit(f"--isa {' '.join(unknown)}: this CPU runs {', '.join(ISAS[:top + 1])}")
        return requested
    return available


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--btf", nargs="+", default=["sim:leather?size=64", "sim:leather?size=128"],
                        help="BTF paths or specs (default: %(default)s)")
    parser.add_argument("--isa", nargs="+", default=None, help="levels to measure (default: avx2 and up, as the CPU runs)")
    parser.add_argument("--seconds", type=float, default=15.0, help="training seconds timed per variant")
    parser.add_argument("--naive-seconds", type=float, default=15.0, help="seconds timed for the naive recipe")
    parser.add_argument("--naive-batch", type=int, default=65536, help="samples per naive step")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--convergence", action="store_true", help="also the time-to-naive's-PSNR comparison "
                        "(on the CPU's own level: naive trains for 4 x --naive-seconds)")
    parser.add_argument("--json", type=Path, default=RESULTS, help="where the rows are written (default %(default)s)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)  # one level, in its own process
    args = parser.parse_args()

    if args.worker:
        rows = measure_level(args.btf, args.seconds, args.naive_seconds, args.naive_batch, args.seed)
        print(json.dumps(rows))
        return

    from dynbtf.cpu import isa_environment

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result

    rows = []
    for isa in levels_to_measure(args.isa):
        env = {k: v for k, v in os.environ.items() if k not in isa_environment(isa)} | isa_environment(isa)
        command = [sys.executable, __file__, "--worker", "--btf", *args.btf, "--seconds", str(args.seconds),
                   "--naive-seconds", str(args.naive_seconds), "--naive-batch", str(args.naive_batch),
                   "--seed", str(args.seed)]
        done = subprocess.run(command, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"level {isa}: the measuring process failed:\n{done.stderr[-3000:]}")
        sys.stderr.write(done.stderr)
        rows += json.loads(done.stdout.strip().splitlines()[-1])
    result = header("training", "bench_training.py") | {"seed": args.seed, "seconds_per_variant": args.seconds,
                                                          "rows": rows}
    if args.convergence:
        result["convergence"] = [convergence(spec, args.naive_seconds * 4, args.naive_batch, args.seed)
                                 for spec in args.btf]
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from tables import training  # the table docs/results.md shows, rendered from the same rows

    print("\n" + training(result))
    for c in result.get("convergence", []):
        print(f"\n{c['btf']}: naive reached {c['naive_final_psnr']:.2f} dB in {c['naive_seconds']:.0f} s; ours (fast) "
              + ", ".join(f"{p} in {o['seconds_to_reach']:.1f} s ({o['speedup']:.1f}x sooner)" if o["speedup"] else
                          f"{p} did not reach it in as long" for p, o in c["ours"].items()))
    write_result(args.json, result)


if __name__ == "__main__":
    main()
