"""The GPU check: training and evaluation on an NVIDIA GPU, in at most about 5 minutes of GPU time.

Run on a machine with a CUDA build of PyTorch: ``python benchmarks/gpu_check.py`` (``--device cpu`` runs the same
steps on the CPU, smaller, as a smoke test). Three measurements, each printed as it ends and written as JSON
(``--json``, default ``benchmarks/results/gpu.json``):

1. **training throughput**: samples/s of :func:`dynbtf.training.fit` on the GPU (``--device cuda``: the whole
   step's texels in one chunk, every op on the device) with the fast recipe (64 texel groups of 16 pairs, lr x6)
   on a 128 x 128 simulated BTF, ``--train-seconds`` of optimizer steps after a warm-up, once per
   ``--compile-modes`` (``TrainConfig.compile``: eager, Inductor's kernels, CUDA graphs) one after the other in
   this process, and the budget planner's own measurement of the fastest;
2. **a 1080p evaluation**: 1920 x 1080 queries of :meth:`dynbtf.SynthesizedBTF.eval` (hist, random uv in
   ``[0, 45)^2``, random directions) on the GPU, best of 3 after a warm-up; and the same synthesized BTF's
   answers on the GPU against the CPU's compiled kernels (largest and relative L2 difference);
3. **a full-size fit**: a 400 x 400 BTF on the UBO2014 grid (151 x 151 directions; rendered on the GPU and
   written as a 96-component DFMF file first, as ``dynbtf simulate leather --grid ubo2014 --size 400 -o X.btf``
   does, not counted) fitted with ``dynbtf fit``'s auto recipe under ``--fit-minutes``, in the fastest mode of
   (1); the held-out monitor's curve gives the time at which the fit came within 0.5 dB of the best it reached (the
   converged PSNR when it converged).

A measurement that fails is printed with its traceback and recorded under ``errors``; the others still run.

The CPU's figures for the same steps are in docs/results.md (``benchmarks/bench_training.py``,
``benchmarks/bench_synthesis_eval.py``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import traceback
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "gpu.json"


def training_throughput(spec: str, device: str, seconds: float, compile: str = "off") -> dict:
    """Samples/s of the fast recipe on ``device`` (:func:`bench_training.our_rate`) with the step's loss run as
    ``compile`` says (``TrainConfig.compile``); ``wall_seconds`` includes the warm-up (and compiling)."""
    import tempfile

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_training import our_rate

    from dynbtf.data.open import open_btf

    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as workdir:
        rate, steps, seconds_per_step = our_rate(open_btf(spec), seconds, 0, Path(workdir), texel_groups=64,
                                                 lr_scale=6.0, device=device, compile=compile, details=True)
    return {"btf": spec, "device": device, "compile": compile, "samples_per_second": rate, "steps": steps,
            "ms_per_step": 1e3 * seconds_per_step, "wall_seconds": time.perf_counter() - started}


def full_size_fit(spec: str, device: str, minutes: float, compile: str = "auto") -> dict:
    from dynbtf.data.open import open_btf
    from dynbtf.training import get_fitter
    from dynbtf.training.recipe import choose_config

    source = open_btf(spec)
    with tempfile.TemporaryDirectory() as workdir:
        output = Path(workdir) / "full.dbtfm"
        started = time.perf_counter()
        config, summary = choose_config(source, output, minutes=minutes, device=device, compile=compile)
        result = get_fitter("triple")(source, output, config, progress=True)
        wall = time.perf_counter() - started
    schedule = result.metadata["provenance"]["schedule"]
    curve = [(r["elapsed_seconds"], r["held_out_psnr"]) for r in schedule["monitor"]]
    best = max(p for _, p in curve)
    within = next(t for t, p in curve if p >= best - 0.5)
    return {"btf": spec, "device": device, "compile": compile, "recipe": summary, "minutes_budget": minutes,
            "wall_seconds": wall, "steps": schedule["steps"], "stopped": schedule["stopped"], "best_held_out_psnr": best,
            "seconds_to_within_half_db": within, "curve": curve}


def evaluation_1080p(device: str, repeats: int = 3, chunk_sizes=(None, 32768, 1 << 21)) -> dict:
    """1080p hist queries on ``device``: best of ``repeats`` after a warm-up, for each of ``chunk_sizes`` (None: the
    default of :class:`dynbtf.SynthesizedBTF` there), with the peak device memory of each."""
    import numpy as np
    import torch

    import dynbtf
    from dynbtf.device import synchronize
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(400, 400, seed=0).eval()
    n = 1920 * 1080
    rng = np.random.default_rng(0)
    uv = torch.from_numpy(rng.random((n, 2)) * 45.0)
    w_view = torch.from_numpy(dynbtf.spherical_to_direction(rng.random(n) * 80, rng.random(n) * 360)).float()
    w_light = torch.from_numpy(dynbtf.spherical_to_direction(rng.random(n) * 80, rng.random(n) * 360)).float()
    uv, w_view, w_light = uv.to(device), w_view.to(device), w_light.to(device)
    cuda = torch.device(device).type == "cuda"
    rows = []
    for chunk_size in chunk_sizes:
        synth = dynbtf.synthesized_btf(model, "hist", scale=1.0, seed=0, device=device, chunk_size=chunk_size)
        synth.eval(uv[:50000], w_view[:50000], w_light[:50000])
        if cuda:
            torch.cuda.reset_peak_memory_stats(device)
        best = float("inf")
        for _ in range(repeats):
            synchronize(device)
            t0 = time.perf_counter()
            synth.eval(uv, w_view, w_light)
            synchronize(device)
            best = min(best, time.perf_counter() - t0)
        rows.append({"chunk_size": synth.chunk_size, "default": chunk_size is None, "seconds": best,
                     "queries_per_second": n / best,
                     "peak_memory_bytes": torch.cuda.max_memory_allocated(device) if cuda else None})
        print(f"  chunk {synth.chunk_size:>9,}{' (default)' if chunk_size is None else ''}: {1e3 * best:.1f} ms"
              + (f", peak {rows[-1]['peak_memory_bytes'] / 2**30:.2f} GiB" if cuda else ""), flush=True)
    return {"device": device, "queries": n, **{k: rows[0][k] for k in ("seconds", "queries_per_second")},
            "chunk_sizes": rows}


def profile(device: str, train_btf: str) -> dict:
    """Where a GPU's time goes: torch's profiler over one 1080p hist evaluation and over a few seconds of training
    steps, the operations with the most device time (printed as tables, kept as text)."""
    import numpy as np
    import torch
    from torch.profiler import ProfilerActivity

    import dynbtf
    from dynbtf.device import synchronize
    from dynbtf.representations.triple_plane import TriplePlane

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.device(device).type == "cuda" else [])
    sort = "cuda_time_total" if len(activities) > 1 else "cpu_time_total"
    n = 1920 * 1080
    rng = np.random.default_rng(0)
    uv = torch.from_numpy(rng.random((n, 2)) * 45.0).to(device)
    w = torch.from_numpy(dynbtf.spherical_to_direction(rng.random(n) * 80, rng.random(n) * 360)).float().to(device)
    synth = dynbtf.synthesized_btf(TriplePlane(400, 400, seed=0).eval(), "hist", device=device)
    synth.eval(uv[:50000], w[:50000], w[:50000])
    synchronize(device)
    with torch.profiler.profile(activities=activities) as prof:
        synth.eval(uv, w, w)
        synchronize(device)
    tables = {"evaluation": prof.key_averages().table(sort_by=sort, row_limit=15)}
    print("profile of one 1080p hist evaluation:\n" + tables["evaluation"], flush=True)
    with torch.profiler.profile(activities=activities) as prof:
        training_throughput(train_btf, device, 2.0)
    tables["training"] = prof.key_averages().table(sort_by=sort, row_limit=20)
    print("profile of 2 s of training steps (with the fit's set-up):\n" + tables["training"], flush=True)
    return tables


def full_size_file(spec: str, device: str, workdir: Path, components: int = 96) -> tuple[str, dict]:
    """A DFMF file of the simulated BTF ``spec`` (``dynbtf simulate ... -o X.btf``: rendered on ``device``,
    ``components`` per channel, randomized SVD), so that the fit reads texels from factors as it would from a
    UBO2014 file; a file's path is returned as it is. Not counted in the fit's time."""
    from dynbtf.data.open import open_btf
    from dynbtf.data.simulated import SimulatedBTF, simulated_btf
    from dynbtf.data.ubo2014 import write_ubo2014

    source = open_btf(spec)
    if not isinstance(source, SimulatedBTF):
        return spec, {"btf": spec}
    started = time.perf_counter()
    path = workdir / "full.btf"
    rendered = simulated_btf(source.material, size=source.height, grid=source.grid, seed=source.seed,
                             relief=source.relief, device=device)
    write_ubo2014(path, rendered, components=components, scalar="half", method="randomized", seed=source.seed,
                  progress=True)
    return str(path), {"btf": spec, "file_components": components, "file_seconds": time.perf_counter() - started,
                       "file_bytes": path.stat().st_size}


def evaluation_agreement(device: str, n: int = 200_000) -> dict:
    """The same synthesized BTF evaluated on ``device`` and on the CPU (the CPU's compiled kernels): the largest
    absolute difference and the relative L2 difference of ``n`` queries' RGB, the 99.9th percentile of the
    per-query difference, how many queries differ by more than 1e-3, and the 5 that differ most. The model's
    weights are exaggerated (values of a few units), so that the differences are not lost under the values."""
    import numpy as np
    import torch

    import dynbtf
    from dynbtf.representations.triple_plane import TriplePlane

    torch.manual_seed(1)
    model = TriplePlane(64, 64, seed=1).eval()
    with torch.no_grad():  # a model with structure (a fresh one's planes are near zero)
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
    rng = np.random.default_rng(1)
    uv = torch.from_numpy(rng.random((n, 2)) * 45.0)
    w_view = torch.from_numpy(dynbtf.spherical_to_direction(rng.random(n) * 80, rng.random(n) * 360)).float()
    w_light = torch.from_numpy(dynbtf.spherical_to_direction(rng.random(n) * 80, rng.random(n) * 360)).float()
    out = {}
    for where in ("cpu", device):
        synth = dynbtf.synthesized_btf(model, "hist", scale=1.0, seed=0, device=where)
        out[where] = synth.eval(uv.to(where), w_view.to(where), w_light.to(where)).double().cpu()
    diff = (out[device] - out["cpu"]).abs().amax(dim=-1)
    worst = torch.argsort(diff, descending=True)[:5]
    return {"queries": n, "max_abs_difference": float(diff.max()),
            "relative_l2_difference": float((out[device] - out["cpu"]).norm() / out["cpu"].norm()),
            "p999_abs_difference": float(torch.quantile(diff[:100_000], 0.999)),
            "queries_over_1e-3": int((diff > 1e-3).sum()),
            "worst": [{"uv": uv[i].tolist(), "cpu": out["cpu"][i].tolist(), device: out[device][i].tolist()}
                      for i in worst.tolist()]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda", help="cuda (default), cuda:N, or cpu for a smoke test")
    parser.add_argument("--train-btf", default="sim:leather?size=128")
    parser.add_argument("--train-seconds", type=float, default=20.0)
    parser.add_argument("--full-btf", default="sim:leather?size=400&grid=ubo2014",
                        help="the full-size BTF: a file, or a simulated BTF (written to a 96-component DFMF file "
                             "first, as `dynbtf simulate ... -o X.btf` would, not counted)")
    parser.add_argument("--full-components", type=int, default=96)
    parser.add_argument("--fit-minutes", type=float, default=3.0)
    parser.add_argument("--compile-modes", nargs="*", default=["off", "kernels", "graphs"],
                        help="TrainConfig.compile modes whose training throughput is measured side by side; "
                             "the full-size fit uses the fastest")
    parser.add_argument("--skip", nargs="*", default=[], choices=["train", "fit", "eval", "profile"])
    parser.add_argument("--json", type=Path, default=RESULTS)
    args = parser.parse_args()

    import torch

    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("gpu_check: CUDA is not available here (torch " + torch.__version__ + "); run it on a GPU "
                         "machine with a CUDA build of PyTorch, or pass --device cpu for a smoke test")
    name = torch.cuda.get_device_name(args.device) if args.device.startswith("cuda") else "CPU"
    result = {"benchmark": "gpu_check", "device": args.device, "device_name": name, "torch": torch.__version__,
              "command": " ".join(["python", "benchmarks/gpu_check.py", *sys.argv[1:]]), "errors": {}}
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import write_result

    def stage(key: str, run) -> None:
        """Run one measurement; a failure is recorded (and printed) and the next one still runs."""
        t0 = time.perf_counter()
        try:
            result[key] = run()
        except Exception:  # noqa: BLE001 (a benchmark on a borrowed machine: keep what the other stages measure)
            result["errors"][key] = traceback.format_exc()
            print(f"{key}: FAILED after {time.perf_counter() - t0:.0f} s\n{result['errors'][key]}", flush=True)
        write_result(args.json, result)

    fastest = {"compile": "auto"}  # the training stage's fastest compile mode, for the full-size fit

    def train():
        from dynbtf.data.open import open_btf
        from dynbtf.training import TrainConfig
        from dynbtf.training.recipe import measure_step_seconds

        modes = {}
        for mode in args.compile_modes:  # each on its own: a mode that fails is recorded, the others still run
            try:
                modes[mode] = training_throughput(args.train_btf, args.device, args.train_seconds, mode)
            except Exception:  # noqa: BLE001
                modes[mode] = {"compile": mode, "error": traceback.format_exc()}
                print(f"training with compile={mode}: FAILED\n{modes[mode]['error']}", flush=True)
                continue
            print(f"training ({args.train_btf}, fast recipe, compile={mode}): "
                  f"{modes[mode]['samples_per_second'] / 1e6:.1f} M samples/s, {modes[mode]['ms_per_step']:.2f} "
                  f"ms/step ({modes[mode]['wall_seconds']:.0f} s with the warm-up)", flush=True)
        ran = {m: r for m, r in modes.items() if "error" not in r}
        if not ran:
            raise RuntimeError("no compile mode ran: " + ", ".join(modes))
        best = max(ran, key=lambda m: ran[m]["samples_per_second"])
        fastest["compile"] = best
        row = {"btf": args.train_btf, "device": args.device, "compile_modes": modes, "fastest_compile": best}
        # what `dynbtf fit --minutes` plans with: its own measurement of the same recipe's step
        row["planned_ms_per_step"] = 1e3 * measure_step_seconds(
            open_btf(args.train_btf), TrainConfig(device=args.device, texel_groups=64, lr_scale=6.0, subtexel=0.0,
                                                  compile=best))
        print(f"fastest: compile={best}, {ran[best]['ms_per_step']:.2f} ms/step (the budget planner measures "
              f"{row['planned_ms_per_step']:.2f} with it)", flush=True)
        return row

    def evaluate():
        row = evaluation_1080p(args.device)
        print(f"1080p evaluation (hist): {1e3 * row['seconds']:.1f} ms, {row['queries_per_second'] / 1e6:.1f} M "
              f"queries/s", flush=True)
        return row

    def agree():
        row = evaluation_agreement(args.device)
        print(f"{args.device} against the CPU, {row['queries']} hist queries: max |difference| "
              f"{row['max_abs_difference']:.2e} (99.9th percentile {row['p999_abs_difference']:.2e}, "
              f"{row['queries_over_1e-3']} over 1e-3), relative L2 {row['relative_l2_difference']:.2e}; worst: "
              f"{row['worst'][:2]}", flush=True)
        return row

    def full_fit():
        with tempfile.TemporaryDirectory() as workdir:
            path, data = full_size_file(args.full_btf, args.device, Path(workdir), args.full_components)
            if "file_seconds" in data:
                print(f"full-size file: {data['file_bytes'] / 1e6:.0f} MB in {data['file_seconds']:.0f} s "
                      f"(not counted)", flush=True)
            fit = {**full_size_fit(path, args.device, args.fit_minutes, fastest["compile"]), **data}
        print(f"full-size fit ({args.full_btf}): best held-out {fit['best_held_out_psnr']:.2f} dB, within 0.5 dB of "
              f"it after {fit['seconds_to_within_half_db'] / 60:.1f} min of training ({fit['steps']} steps, "
              f"{fit['stopped']}); {fit['wall_seconds']:.0f} s in all", flush=True)
        return fit

    if "train" not in args.skip:
        stage("training", train)
    if "eval" not in args.skip:
        stage("evaluation", evaluate)
        if args.device != "cpu":
            stage("evaluation_agreement", agree)
    if "profile" not in args.skip:
        stage("profile", lambda: profile(args.device, args.train_btf))
    if "fit" not in args.skip:
        stage("full_size_fit", full_fit)
    if result["errors"]:
        raise SystemExit(f"gpu_check: {len(result['errors'])} measurement(s) failed: {', '.join(result['errors'])}")


if __name__ == "__main__":
    main()
