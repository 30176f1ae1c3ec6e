"""Training benchmark: the paper's recipe run naively vs dynbtf's whole-image path, side by side.

Both train the same Triple Plane (same initialization, same held-out pairs,
same AdamW groups and learning rates) on the same simulated BTF:

* **naive** -- per-sample random batches (``--naive-batch`` samples drawn over random
  (texel, view, light) of the training pairs), the model's plain forward (three
  ``grid_sample`` fetches per sample, standard autograd MLP), L1, AdamW. Its torch
  thread count is the faster of 1 and all threads (measured first).
* **ours (paper batches)** -- :func:`dynbtf.training.fit` with the paper's recipe
  (16 whole images per step, angular features once per image, layer 1's positional
  product once per texel, layers 2-4 with their loss and backward in the native fused
  kernel of :mod:`dynbtf.decoder.fused_mlp`), at ``precision="auto"`` (bf16 products
  with float32 accumulation on CPUs with AVX512-BF16, else fp32).
* **ours (fast)** -- the same code with ``texel_groups`` (default 64: each step's
  texels in 64 blocks, each under its own 16 pairs, so 1024 distinct pairs
  per step for the cost of 16 images) and ``lr_scale`` (default 3). Both are
  departures from the paper's recipe; the naive path keeps the paper's rates.
* **ours (fast, fp32)** -- the fast variant in float32 arithmetic, when ``auto`` chose
  bf16: what the reduced precision buys, measured in the same run.

Both decay the learning rate by 0.9 per epoch of ``pairs x texels`` samples. The
held-out PSNR (linear, peak 1, pooled over a fixed subset of held-out pairs) is
measured every ``--eval-every`` seconds of training time (evaluation excluded from
the clock). Printed: samples/s of each and their ratio, naive's final PSNR, and
the training time each needs to first reach it, and that ratio.

Targets: ours >= 10x naive samples/s; ours reaches naive's final
PSNR in <= 1/10 of naive's time.

The default BTF is the demo's scale, ``sim:leather?size=128`` (the naive path's rate does
not depend on the size; ours amortizes its per-step overhead over 16 x 128^2 samples).

Run: ``python benchmarks/bench_training.py`` (about 10 minutes; ``--help`` for options).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from dynbtf.conventions import texel_centers_uv
from dynbtf.data.open import open_btf
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.training import ImageStore, TrainConfig, fit, held_out_split, predict_images
from dynbtf.decoder import native
from dynbtf.decoder.fused_mlp import resolve_precision, single_intra_op_thread


def matmul_peak(dtype=torch.float32, size: int = 2048, repeats: int = 3) -> float:
    """FLOP/s of a ``size^2`` matmul in ``dtype`` on all torch threads (best of ``repeats``)."""
    a, b = torch.randn(size, size, dtype=dtype), torch.randn(size, size, dtype=dtype)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t)
    return 2 * size ** 3 / best


def fused_flops_per_sample(model: TriplePlane) -> int:
    """Multiply-adds x 2 per sample of the fused step: layers 2.. forward, input gradients and weight gradients."""
    layers = model.decoder.rest
    return 3 * sum(2 * layer.in_features * layer.out_features for layer in layers)


class Stop(Exception):
    """Raised from the training callback to end a timed run."""


def held_out_psnr(rep, source, store, pairs) -> float:
    se, count = 0.0, 0
    with torch.no_grad(), single_intra_op_thread():
        for k in range(0, len(pairs), 8):
            chunk = pairs[k:k + 8]
            target = torch.from_numpy(store.get(chunk))
            wv = torch.as_tensor(source.views[chunk[:, 0]], dtype=torch.float32)
            wl = torch.as_tensor(source.lights[chunk[:, 1]], dtype=torch.float32)
            pred = predict_images(rep, wv, wl, (source.height, source.width))
            se += float(((pred - target) ** 2).sum(dtype=torch.float64))
            count += target.numel()
    return -10.0 * math.log10(se / count)


class Curve:
    """Training-time clock with periodic held-out PSNR measurements (evaluation excluded)."""

    def __init__(self, rep, source, store, pairs, every: float):
        self.rep, self.source, self.store, self.pairs, self.every = rep, source, store, pairs, every
        self.train_seconds, self.samples, self.points, self._next = 0.0, 0, [], every

    def step(self, seconds: float, samples: int) -> None:
        self.train_seconds += seconds
        self.samples += samples
        if self.train_seconds >= self._next:
            self.measure()
            self._next = self.train_seconds + self.every

    def measure(self) -> float:
        psnr = held_out_psnr(self.rep, self.source, self.store, self.pairs)
        self.points.append((self.train_seconds, psnr))
        return psnr

    def time_to_reach(self, psnr: float) -> float | None:
        for t, p in self.points:
            if p >= psnr:
                return t
        return None


def naive_training(source, store, train_pairs, eval_pairs, budget, batch, eval_every, seed):
    rep = TriplePlane(source.height, source.width, seed=seed)
    optimizer = torch.optim.AdamW(rep.param_groups())
    initial = [g["lr"] for g in optimizer.param_groups]
    n = source.height * source.width
    uv_all = torch.from_numpy(texel_centers_uv(source.height, source.width)).reshape(-1, 2).float()
    views = torch.as_tensor(source.views, dtype=torch.float32)
    lights = torch.as_tensor(source.lights, dtype=torch.float32)
    images = torch.from_numpy(store.get(train_pairs)).to(torch.float16)  # (P, N, 3), already decoded
    rng = np.random.default_rng(seed)
    samples_per_epoch = len(train_pairs) * n

    def step():
        p = torch.from_numpy(rng.integers(0, len(train_pairs), batch))
        t = torch.from_numpy(rng.integers(0, n, batch))
        pairs = torch.from_numpy(train_pairs)[p]
        target = images[p, t].float()
        pred = rep(uv_all[t], views[pairs[:, 0]], lights[pairs[:, 1]])
        loss = (pred - target).abs().mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    # pick the faster thread setting for the naive path (OpenMP can stall on a shared machine)
    threads = torch.get_num_threads()
    speeds = {}
    for setting in sorted({1, threads}):
        torch.set_num_threads(setting)
        step()
        t0 = time.perf_counter()
        for _ in range(3):
            step()
        speeds[setting] = 3 * batch / (time.perf_counter() - t0)
    best = max(speeds, key=speeds.get)
    torch.set_num_threads(best)
    # restart from the same initialization for the timed run
    rep = TriplePlane(source.height, source.width, seed=seed)
    optimizer = torch.optim.AdamW(rep.param_groups())
    curve = Curve(rep, source, store, eval_pairs, eval_every)
    curve.measure()
    try:
        while curve.train_seconds < budget:
            epoch = curve.samples // samples_per_epoch
            for g, lr in zip(optimizer.param_groups, initial):
                g["lr"] = lr * 0.9 ** epoch
            t0 = time.perf_counter()
            step()
            curve.step(time.perf_counter() - t0, batch)
    finally:
        torch.set_num_threads(threads)
    curve.measure()
    return curve, best, speeds


def our_training(source, store, eval_pairs, budget, stop_psnr, eval_every, seed, workdir, texel_groups=1,
                 lr_scale=1.0, precision="auto"):
    rep = TriplePlane(source.height, source.width, seed=seed)
    curve = Curve(rep, source, store, eval_pairs, eval_every)
    curve.measure()

    def callback(info):
        curve.step(info["step_seconds"], info["samples"])
        if curve.train_seconds >= budget or (stop_psnr is not None and curve.points[-1][1] >= stop_psnr):
            raise Stop

    config = TrainConfig(epochs=1000, seed=seed, held_out_fraction=0.05, monitor_pairs=0, checkpoint_every=10 ** 9,
                         texel_groups=texel_groups, lr_scale=lr_scale, precision=precision)
    try:
        fit(rep, source, config, Path(workdir) / "ours.dbtfm", progress=False, callback=callback)
    except Stop:
        pass
    curve.measure()
    return curve


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--btf", default="sim:leather?size=128", help="BTF path or spec (default %(default)s)")
    parser.add_argument("--naive-seconds", type=float, default=150.0, help="naive path's training time budget")
    parser.add_argument("--ours-seconds", type=float, default=None,
                        help="our path's budget (default: naive's; stops early once it reaches naive's final PSNR)")
    parser.add_argument("--naive-batch", type=int, default=65536, help="samples per naive step")
    parser.add_argument("--eval-pairs", type=int, default=32, help="held-out pairs in the PSNR measurement")
    parser.add_argument("--eval-every", type=float, default=5.0, help="seconds of training between PSNR measurements")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--groups", type=int, default=64, help="texel groups of the fast variant")
    parser.add_argument("--lr-scale", type=float, default=6.0, help="learning-rate multiplier of the fast variant")
    args = parser.parse_args()

    source = open_btf(args.btf)
    train_pairs, held_out = held_out_split(source.n_views, source.n_lights, 0.05, args.seed)
    eval_pairs = held_out[np.linspace(0, len(held_out) - 1, min(args.eval_pairs, len(held_out))).astype(int)]
    store = ImageStore(source)
    t0 = time.perf_counter()
    store.fill(progress=True)
    print(f"BTF {source!r}: decoded in {time.perf_counter() - t0:.1f} s; {len(train_pairs)} training pairs, "
          f"PSNR on {len(eval_pairs)} held-out pairs (pooled MSE, fixed peak 1: the convergence criterion of this "
          f"benchmark); torch threads {torch.get_num_threads()}")
    precision = resolve_precision("auto")  # builds the native kernel now, outside the timed runs
    print(f"native kernel: {native.status('fused_mlp')}; our precision: {precision}")

    naive, naive_threads, speeds = naive_training(source, store, train_pairs, eval_pairs, args.naive_seconds,
                                                  args.naive_batch, args.eval_every, args.seed)
    naive_rate = naive.samples / naive.train_seconds
    target = naive.points[-1][1]
    print(f"naive: {naive_rate / 1e6:.3f} M samples/s (threads {naive_threads}; warm-up "
          + ", ".join(f"{k} thread(s) {v / 1e6:.3f} M/s" for k, v in speeds.items())
          + f"), final held-out PSNR {target:.2f} dB after {naive.train_seconds:.1f} s")
    fast = dict(texel_groups=args.groups, lr_scale=args.lr_scale)
    variants = {f"ours (paper batches, {precision})": dict(texel_groups=1, lr_scale=1.0),
                f"ours (fast: {args.groups} groups, lr x{args.lr_scale:g}, {precision})": fast}
    if precision != "fp32":
        variants[f"ours (fast: {args.groups} groups, lr x{args.lr_scale:g}, fp32)"] = fast | dict(precision="fp32")
    runs = {}
    for name, options in variants.items():
        with tempfile.TemporaryDirectory() as workdir:
            curve = our_training(source, store, eval_pairs, args.ours_seconds or args.naive_seconds, target,
                                 args.eval_every / 5, args.seed, workdir, **options)
        runs[name] = curve
        print(f"{name}: {curve.samples / curve.train_seconds / 1e6:.3f} M samples/s, held-out PSNR "
              f"{curve.points[-1][1]:.2f} dB after {curve.train_seconds:.1f} s")
    t_naive = naive.time_to_reach(target)
    peaks = {"fp32": matmul_peak(torch.float32), "bf16": matmul_peak(torch.bfloat16)}
    flops = fused_flops_per_sample(TriplePlane(source.height, source.width))
    print(f"\nmatmul peaks (2048^2, all threads): fp32 {peaks['fp32'] / 1e9:.0f} GFLOP/s, bf16 "
          f"{peaks['bf16'] / 1e9:.0f} GFLOP/s; fused step {flops} FLOP/sample; 10x naive = "
          f"{10 * naive_rate / 1e6:.2f} M samples/s = {10 * naive_rate * flops / 1e9:.0f} GFLOP/s")
    print("\nRESULTS (targets: >= 10x samples/s; naive's final PSNR in <= 1/10 of its time)")
    for name, curve in runs.items():
        rate = curve.samples / curve.train_seconds
        t_ours = curve.time_to_reach(target)
        arithmetic = "fp32" if name.endswith("fp32)") else precision
        print(f"  {name}")
        print(f"    samples/s ratio (ours / naive):   {rate / naive_rate:.1f}x   ({rate * flops / 1e9:.0f} GFLOP/s, "
              f"{100 * rate * flops / peaks[arithmetic]:.0f} % of the {arithmetic} matmul peak)")
        if t_ours is None:
            print(f"    did not reach naive's final PSNR ({target:.2f} dB) within its budget")
        else:
            print(f"    time to reach {target:.2f} dB: naive {t_naive:.1f} s, ours {t_ours:.1f} s -> "
                  f"{t_naive / max(t_ours, 1e-9):.1f}x faster")
        print("    curve (s, dB): " + ", ".join(f"({t:.1f}, {p:.1f})"
                                                for t, p in curve.points[::max(1, len(curve.points) // 8)]))
    print("  naive curve (s, dB): " + ", ".join(f"({t:.0f}, {p:.1f})" for t, p in naive.points[::max(1, len(naive.points) // 8)]))


if __name__ == "__main__":
    main()
