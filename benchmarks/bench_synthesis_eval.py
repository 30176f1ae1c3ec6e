"""Evaluation speed of the synthesized BTF: a 1080p frame of queries, naive PyTorch vs our path.

Usage::

    python benchmarks/bench_synthesis_eval.py [--model MODEL.dbtfm] [--queries 2073600] [--methods tile,linear,hist,hex]

For each method, 1920 x 1080 queries with random uv inside a frame's range
(``[0, 45)^2`` exemplar repeats, the paper's 45x) and random view/light
directions are evaluated by

(a) a **naive PyTorch path**: lattice + hash in torch, the three exemplar
    samples fetched with ``grid_sample`` (:func:`dynbtf.texture.fetch_wrap`),
    the blend, the inverse-transform LUT and the PCA un-projection in torch,
    then ``model.decode`` on one big float32 batch;
(b) **ours**: :meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` (fused numba
    synthesis kernel, first layer as a BLAS positional product plus a numba
    angular kernel vectorized across queries with the LeakyReLU fused, decoder
    layers 2.. in torch on 16k-row blocks -- bf16 where the CPU has native bf16
    matmul, i.e. where bf16 measures faster than fp32, else fp32; chunks spread
    over one Python thread per core, each running numba and torch single-threaded).

Both paths are timed alike: one warm-up run on the first 50,000 queries (kernel
compilation/loading, allocator, caches), then the best of ``--repeats`` full runs.

It prints queries/s, the speed-up, a per-stage breakdown of our path (on one
thread, as each worker runs it), and our throughput as a fraction of the
decoder-FLOP bound at the machine's matmul peak
(a 4096^2 matmul measured in the same run, bf16 where native, else fp32). Timings on shared
machines move 10-50% between runs: compare the ratios of one run.
"""

from __future__ import annotations

import argparse
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
from dynbtf.infinite_btf import SynthesizedBTF
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


def matmul_peak_flops(dtype, size: int, repeats: int = 2) -> float:
    """FLOP/s of a ``size^2`` matmul in ``dtype`` (best of ``repeats``)."""
    a = torch.randn(size, size).to(dtype)
    b = torch.randn(size, size).to(dtype)
    a @ b
    return 2 * size ** 3 / best_time(lambda: a @ b, repeats)


def peaks() -> dict[str, tuple[float, int]]:
    """Matmul peaks: fp32 at 4096^2; bf16 at 4096^2 when it is native, else at 512^2 (emulated bf16 on
    CPUs without AVX-512-BF16/AMX takes minutes at 4096^2)."""
    fp32 = matmul_peak_flops(torch.float32, 4096)
    probe = matmul_peak_flops(torch.bfloat16, 512, repeats=1)
    if probe > 0.25 * fp32:
        return {"fp32": (fp32, 4096), "bf16": (matmul_peak_flops(torch.bfloat16, 4096), 4096)}
    return {"fp32": (fp32, 4096), "bf16": (probe, 512)}


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", help="model file (default: a random 400x400x16 Triple Plane; speed does not "
                                        "depend on training)")
    parser.add_argument("--methods", default="tile,linear,hist,hex")
    parser.add_argument("--queries", type=int, default=1920 * 1080, help="queries per frame (default 1080p)")
    parser.add_argument("--repeats", type=int, default=2, help="timed full runs per path after one warm-up run "
                                                               f"on {WARM_UP_QUERIES} queries (best is kept)")
    args = parser.parse_args()
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
    measured = peaks()
    # the bound uses the faster matmul precision (bf16 where it is native, as the issue intends)
    precision = max(measured, key=lambda k: measured[k][0])
    peak = measured[precision][0]
    flops = decoder_flops(model) * n
    bound = flops / peak
    print(f"machine: torch {torch.__version__}, {torch.get_num_threads()} threads, CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}; matmul peaks: "
          + ", ".join(f"{k} {v[0] / 1e9:.0f} GFLOP/s ({v[1]}^2)" for k, v in measured.items()))
    print(f"frame: {n} queries; decoder {decoder_flops(model)} FLOP/query = {flops / 1e9:.1f} GFLOP; "
          f"bound at the {precision} peak {bound * 1e3:.1f} ms; our decoder runs in {precision}\n")
    header = f"{'method':<7} {'naive q/s':>11} {'ours q/s':>11} {'speed-up':>9} {'of peak bound':>14} " \
             f"{'max |ours-naive|':>17}"
    print(header)
    print("-" * len(header))
    ours_hist = None  # (queries/s, workers) of the hist row
    for method in args.methods.split(","):
        ours = SynthesizedBTF(model, method, scale=1.0, precision=precision)
        t_naive = warm_then_best(lambda sl: naive_eval(model, ours.synthesizer, uv[sl], w_view[sl], w_light[sl]),
                                 n, args.repeats)
        t_ours = warm_then_best(lambda sl: ours.eval(uv[sl], w_view[sl], w_light[sl]), n, args.repeats)
        if method == "hist":
            ours_hist = (n / t_ours, ours.workers)
        sub = slice(0, 200000)
        # error vs the naive path with float64 directions (float32 directions make phi_h ill-conditioned
        # near the pole of h, where the naive float32 path itself is off by up to ~0.1)
        err = float((ours.eval(uv[sub], w_view[sub], w_light[sub])
                     - naive_eval(model, ours.synthesizer, uv[sub], w_view[sub].double(),
                                  w_light[sub].double())).abs().max())
        print(f"{method:<7} {n / t_naive:>11.3g} {n / t_ours:>11.3g} {t_naive / t_ours:>8.1f}x {bound / t_ours:>13.1%} "
              f"{err:>17.2g}", flush=True)
    # where our time goes (hist): per-stage timings over the same chunks, on one thread as each worker runs them
    btf = SynthesizedBTF(model, "hist", scale=1.0, precision=precision, workers=1)
    chunk = btf.chunk_size
    rest = f"layers 2-4 ({precision}, torch)"
    stages = {"synthesis kernel": 0.0, "layer 1 (BLAS + angular kernel)": 0.0, rest: 0.0}
    path = btf.decode_path
    planes, weight, bias = path._fused
    threads = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    try:
        with torch.no_grad():
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
                stages[rest] += t3 - t2
        t_one = best_time(lambda: btf.eval(uv, w_view, w_light), 1)
    finally:
        torch.set_num_threads(threads[0])
        numba.set_num_threads(threads[1])
    stages["eval's own work (validation, chunks)"] = max(t_one - sum(stages.values()), 0.0)
    total = sum(stages.values())
    print(f"\nour hist path on ONE thread, per stage ({precision}; {n / t_one:.3g} q/s on one thread"
          + (f", {ours_hist[0]:.3g} q/s with {ours_hist[1]} workers above" if ours_hist else "") + "):")
    for name, t in stages.items():
        print(f"  {name:<38} {t * 1e3:8.1f} ms  {t / total:6.1%}")
    print(f"  {'bound at ' + precision + ' peak (all threads)':<38} {bound * 1e3:8.1f} ms")


if __name__ == "__main__":
    main()
