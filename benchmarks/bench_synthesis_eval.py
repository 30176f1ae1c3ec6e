"""Evaluation speed of the synthesized BTF per instruction-set level: a 1080p frame of queries, naive PyTorch vs ours.

Usage::

    python benchmarks/bench_synthesis_eval.py [--model MODEL.dbtfm] [--queries 2073600] [--methods tile,linear,hist,hex]
                                              [--isa avx2 avx512 ...] [--json benchmarks/results/evaluation.json]

For each level of :mod:`dynbtf.cpu` this CPU runs from AVX2 up (each in a process of its own with the level
forced: dynbtf's kernels, PyTorch's, MKL's and numba's), and each method, 1920 x 1080 queries with random uv
inside a frame's range (``[0, 45)^2`` exemplar repeats, the paper's 45x) and random view/light directions are
evaluated by

(a) a **naive PyTorch path**: lattice + hash in torch, the three exemplar
    samples fetched with ``grid_sample`` (:func:`dynbtf.texture.fetch_wrap`),
    the blend, the inverse-transform LUT and the PCA un-projection in torch,
    then ``model.decode`` on one big float32 batch;
(b) **ours**: :meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` (fused numba
    synthesis kernel, first layer as a BLAS positional product plus a numba
    angular kernel vectorized across queries with the LeakyReLU fused, decoder
    layers 2.. in the training kernel's float32 forward on tiles of rows;
    chunks spread over one Python thread per core, each running numba and torch single-threaded).

Both paths are timed alike: one warm-up run on the first 50,000 queries (kernel
compilation/loading, allocator, caches), then the best of ``--repeats`` full runs.

Printed per level and method: queries/s of each and the speed-up, and our share of the **FMA bound**: the
decoder's FLOP per query times queries/s over the level's FMA peak on all threads
(:func:`dynbtf.decoder.native.fma_peak_flops`, measured in the same process), and, on every level, a
per-stage breakdown of our hist path on one thread, in nanoseconds per query, beside the time per query one
thread would take at a given share of its FMA peak. The rows are written as JSON (docs/results.md's table is
generated from it). Timings on shared machines move 10-50% between runs: compare the ratios of one run.
"""

from __future__ import annotations

import argparse
import sys
import time

import numba
import numpy as np
import torch

from dynbtf.conventions import spherical_to_direction
from dynbtf.decoder.fast_decode import first_layer_preactivation
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.synthesis.blending import LatticeBlending
from dynbtf.synthesis.histogram import variance_preserving_blend, blend_weights
from dynbtf.synthesis.histogram_blending import HistogramBlending
from dynbtf.decoder.folded import MLP_ROWS, mlp
from dynbtf.synthesized import synthesized_btf
from dynbtf.texture import fetch_wrap


def best_time(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


#: Queries of the warm-up run before each path is timed.
WARM_UP_QUERIES = 50_000


def warm_then_best(run, n: int, repeats: int) -> float:
    """Seconds of ``run(slice)`` over all ``n`` queries: one warm-up on the first
    :data:`WARM_UP_QUERIES`, then the best of ``repeats`` full runs (the same for every path)."""
    run(slice(0, min(n, WARM_UP_QUERIES)))
    return best_time(lambda: run(slice(0, n)), repeats)


def decoder_flops(model) -> int:
    """Multiply-adds x 2 of the decoder's linear layers per query."""
    layers = [model.decoder.first, *model.decoder.rest]
    return sum(2 * layer.in_features * layer.out_features for layer in layers)


@torch.no_grad()
def naive_eval(model, synth, uv, w_view, w_light):
    """The straightforward PyTorch evaluation (one big batch, float32 decoder)."""
    if isinstance(synth, LatticeBlending):
        uv_samples, bary = synth.sample_positions(uv)
        samples = fetch_wrap(synth.prepared.plane, uv_samples)  # the three grid_sample fetches
        if isinstance(synth, HistogramBlending):
            g = variance_preserving_blend(samples, blend_weights(bary.float(), synth.gamma))
            latent = synth.prepared.extras["lut"](g)  # the inverse-transform LUT
        else:
            latent = synth.blend(samples, bary, uv_samples)
        matrix, offset = synth.output_map()
        features = latent if matrix is None else latent @ matrix + offset
    else:
        features = synth(uv)
    return model.decode_with_angular(features.float(), model.angular_features(w_view, w_light).float())


def measure(args) -> dict:
    """This process's level: ``{"rows": a row per method, "breakdown": the per-stage breakdown of hist on one thread
    (None without hist)}``."""
    from dynbtf.cpu import active_isa
    from dynbtf.decoder.native import fma_peak_flops

    torch.manual_seed(0)
    if args.model:
        from dynbtf.representations.model_file import load_model

        model, _ = load_model(args.model)
    else:
        model = TriplePlane(400, 400, seed=0)
    model.eval()
    n = args.queries
    rng = np.random.default_rng(0)
    uv = torch.from_numpy(rng.random((n, 2)) * 45.0)
    w_view = torch.from_numpy(spherical_to_direction(rng.random(n) * 80, rng.random(n) * 360)).float()
    w_light = torch.from_numpy(spherical_to_direction(rng.random(n) * 80, rng.random(n) * 360)).float()
    isa = active_isa()
    peak = fma_peak_flops(isa, threads=torch.get_num_threads(), seconds=1.0)
    flops = decoder_flops(model) * n
    bound = flops / peak
    print(f"[{isa}] torch {torch.__version__}, {torch.get_num_threads()} threads, CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}; FMA peak {peak / 1e9:.0f} GFLOP/s; {n} queries, decoder "
          f"{decoder_flops(model)} FLOP/query: bound {bound * 1e3:.1f} ms", file=sys.stderr)
    rows = []
    for method in args.methods.split(","):
        ours = synthesized_btf(model, method, scale=1.0)
        t_naive = warm_then_best(lambda sl: naive_eval(model, ours.synthesizer, uv[sl], w_view[sl], w_light[sl]),
                                 n, args.repeats)
        t_ours = warm_then_best(lambda sl: ours.eval(uv[sl], w_view[sl], w_light[sl]), n, args.repeats)
        sub = slice(0, 200000)
        # error vs the naive path with float64 directions (float32 directions make phi_h ill-conditioned
        # near the pole of h, where the naive float32 path itself is off by up to ~0.1)
        err = float((ours.eval(uv[sub], w_view[sub], w_light[sub])
                     - naive_eval(model, ours.synthesizer, uv[sub], w_view[sub].double(),
                                  w_light[sub].double())).abs().max())
        rows.append({"isa": isa, "method": method, "queries": n, "naive_qps": n / t_naive, "ours_qps": n / t_ours,
                     "share_of_fma_bound": bound / t_ours, "fma_peak_gflops": peak / 1e9, "workers": ours.workers,
                     "max_abs_difference": err, "decoder_flop_per_query": decoder_flops(model)})
        print(f"[{isa}] {method:<7} naive {n / t_naive:.3g} q/s, ours {n / t_ours:.3g} q/s ({t_naive / t_ours:.1f}x), "
              f"{bound / t_ours:.1%} of the FMA bound, max |ours - naive| {err:.2g}", file=sys.stderr, flush=True)
    breakdown = None
    if "hist" in args.methods.split(","):
        breakdown = stage_breakdown(model, uv, w_view, w_light, n) | {
            "isa": isa, "fma_peak_gflops_one_thread": fma_peak_flops(isa, threads=1, seconds=1.0) / 1e9,
            "decoder_flop_per_query": decoder_flops(model),
            "layers_2_on_flop_per_query": sum(2 * layer.in_features * layer.out_features
                                              for layer in model.decoder.rest)}
    return {"rows": rows, "breakdown": breakdown}


def stage_breakdown(model, uv, w_view, w_light, n) -> dict:
    """Where our hist path's time goes: per-stage timings over the same chunks, on one thread as each worker runs
    (printed, and returned as ``{"queries_per_second_one_thread", "stages": {name: share}}``)."""
    btf = synthesized_btf(model, "hist", scale=1.0, workers=1)
    chunk = btf.chunk_size
    stages = {"synthesis kernel": 0.0, "layer 1 (BLAS + angular kernel)": 0.0, "layers 2.. (native forward)": 0.0}
    path = btf.decode_path
    planes, weight, bias = path._fused
    threads = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    try:
        with torch.no_grad():
            btf.eval(uv[:chunk], w_view[:chunk], w_light[:chunk])  # warm-up: kernels loaded, buffers allocated
            for start in range(0, n, chunk):
                sl = slice(start, start + chunk)
                t0 = time.perf_counter()
                latent = btf.synthesizer.latent(uv[sl])
                t1 = time.perf_counter()
                x = torch.from_numpy(first_layer_preactivation(latent.numpy(), weight, bias, w_view[sl].numpy(),
                                                               w_light[sl].numpy(), *planes,
                                                               negative_slope=path.decoder.slope)).to(path.dtype)
                t2 = time.perf_counter()
                for block in x.split(MLP_ROWS):
                    mlp(block, path._rest[0], path.decoder.slope)
                t3 = time.perf_counter()
                stages["synthesis kernel"] += t1 - t0
                stages["layer 1 (BLAS + angular kernel)"] += t2 - t1
                stages["layers 2.. (native forward)"] += t3 - t2
        t_one = best_time(lambda: btf.eval(uv, w_view, w_light), 1)
    finally:
        torch.set_num_threads(threads[0])
        numba.set_num_threads(threads[1])
    stages["eval's own work (validation, chunks)"] = max(t_one - sum(stages.values()), 0.0)
    total = sum(stages.values())
    print(f"\nour hist path on ONE thread, per stage ({n / t_one:.3g} q/s on one thread):", file=sys.stderr)
    for name, t in stages.items():
        print(f"  {name:<38} {t * 1e3:8.1f} ms  {t / total:6.1%}", file=sys.stderr)
    return {"queries_per_second_one_thread": n / t_one, "stages": {name: t / total for name, t in stages.items()}}


def main() -> None:
    import json
    import os
    import subprocess
    from pathlib import Path

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", help="model file (default: a random 400x400x16 Triple Plane; speed does not "
                                        "depend on training)")
    parser.add_argument("--methods", default="tile,linear,hist,hex")
    parser.add_argument("--queries", type=int, default=1920 * 1080, help="queries per frame (default 1080p)")
    parser.add_argument("--repeats", type=int, default=2, help="timed full runs per path after one warm-up run "
                                                               f"on {WARM_UP_QUERIES} queries (best is kept)")
    parser.add_argument("--isa", nargs="+", default=None, help="levels to measure (default: avx2 and up)")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "evaluation.json")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(measure(args)))
        return
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_training import levels_to_measure
    from results_io import header, write_result

    from dynbtf.cpu import isa_environment

    rows, breakdowns = [], []
    for isa in levels_to_measure(args.isa):
        env = {k: v for k, v in os.environ.items() if k not in isa_environment(isa)} | isa_environment(isa)
        command = [sys.executable, __file__, "--worker", "--methods", args.methods, "--queries", str(args.queries),
                   "--repeats", str(args.repeats)] + (["--model", args.model] if args.model else [])
        done = subprocess.run(command, env=env, capture_output=True, text=True)
        sys.stderr.write(done.stderr)
        if done.returncode != 0:
            raise SystemExit(f"level {isa}: the measuring process failed")
        measured = json.loads(done.stdout.strip().splitlines()[-1])
        rows += measured["rows"]
        breakdowns += [measured["breakdown"]] if measured["breakdown"] else []
    result = header("evaluation", "bench_synthesis_eval.py") | {"queries": args.queries, "rows": rows,
                                                                  "breakdowns": breakdowns}
    from tables import evaluation

    print("\n" + evaluation(result))
    write_result(args.json, result)


if __name__ == "__main__":
    main()
