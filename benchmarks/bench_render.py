"""Shading-point throughput of the Mitsuba plugin's query vs ``SynthesizedBTF.eval``: what the hand-over costs.

Evaluates the same 1920 x 1080 random queries (uv within 25 repeats, upper-hemisphere
view and light) through

(a) ``SynthesizedBTF.eval`` (dynbtf's CPU fast path: numba synthesis kernel + BLAS/native decoder), in
    float32 (its default) and in bfloat16 (``precision="bf16"``), each after a warm-up call and the
    fastest of ``--repeats`` calls, and
(b) ``DynBTFEvaluator.eval``, what the ``dynbtf`` BSDF runs per wavefront: the same query, handed the
    wavefront's Dr.Jit arrays as torch tensors and back (:mod:`dynbtf.render.mitsuba.evaluator`), the
    fastest of several calls on fresh inputs (the first one warms up),

and prints queries/s of each, their ratio, the first call's time and the largest difference (zero: one
query). Then ``dynbtf render``'s scenes at their defaults (512 x 512, 16 spp, in passes of 4): plane / sky /
hist and sphere / sky / hex with the same model, each rendered twice in this process (the first time compiles
Mitsuba's kernels or loads them from Dr.Jit's cache): wall time, first pass, compile time. The relief march's
cost is the library's (``benchmarks/bench_parallax_eval.py``), and so is the
cost of each synthesis method (``benchmarks/bench_synthesis_eval.py``).

Run: ``python benchmarks/bench_render.py [MODEL] [--method hist]`` (default: a random model of the paper's
size, 128 x 128 texels). Written as JSON (``--json``, default ``benchmarks/results/rendering.json``) with the
command, the commit and the CPU that measured it, from which docs/results.md's rendering table and Speed row are
generated (``python benchmarks/tables.py``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

RESULTS = Path(__file__).resolve().parent / "results" / "rendering.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", nargs="?", default=None)
    parser.add_argument("--method", default="hist", choices=["tile", "hist", "hex", "struct", "auto"])
    parser.add_argument("--queries", type=int, default=1920 * 1080)
    parser.add_argument("--repeats", type=int, default=5, help="timed calls of each path (plugin: fresh inputs each)")
    parser.add_argument("--json", type=Path, default=RESULTS, help="where the measurement is written")
    parser.add_argument("--no-scenes", dest="scenes", action="store_false", help="skip the scene renders")
    args = parser.parse_args()

    from dynbtf.jit import mi_module
    from dynbtf.render.mitsuba.bsdf import configure_jit
    from dynbtf.render.mitsuba.evaluator import DynBTFEvaluator
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesized import synthesized_btf

    if args.model:
        from dynbtf.representations.model_file import load_model

        model, _ = load_model(args.model)
    else:
        model = TriplePlane(128, 128, seed=0)
    mi_module()  # the Mitsuba variant, before the plugin's evaluator is built
    configure_jit()
    rng = np.random.default_rng(0)
    n = args.queries
    uv = (rng.random((n, 2)) * 25.0).astype(np.float32)

    def hemisphere():
        w = rng.normal(size=(n, 3))
        w[:, 2] = np.abs(w[:, 2]) + 0.05
        return (w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)

    wv, wl = hemisphere(), hemisphere()
    uv64 = uv.astype(np.float64)
    t_eval = {}
    for precision in ("fp32", "bf16"):
        synth = synthesized_btf(model, args.method, precision=precision)
        synth.eval(uv64[:50_000], wv[:50_000], wl[:50_000])  # warm-up (numba, torch allocators)
        best = float("inf")
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            synth.eval(uv64, wv, wl)
            best = min(best, time.perf_counter() - t0)
        t_eval[precision] = best
    btf = synthesized_btf(model, args.method)  # float32: the reference for the difference

    ev = DynBTFEvaluator(synthesized_btf(model, args.method, seed=0))
    # several calls on fresh inputs (the first one warms up): the first and the fastest are reported
    times, got = plugin_seconds(ev, uv, wv, wl, args.repeats)
    t_first, t_plugin = times[0], min(times)
    shifted = shifted_uv(uv, args.repeats - 1)
    ref = btf.eval(shifted, wv, wl)
    print(f"{n} queries, method {args.method}, model {tuple(model.positional_plane().shape)}")
    for precision, t in t_eval.items():
        print(f"{'(a) SynthesizedBTF.eval ' + precision:<28}: {n / t / 1e6:7.2f} M queries/s ({t:.3f} s; fastest of "
              f"{args.repeats} after a warm-up)")
    print(f"(b) plugin's query          : {n / t_plugin / 1e6:7.2f} M queries/s ({t_plugin:.3f} s; "
          f"fastest of {len(times)}; first call {t_first:.1f} s)")
    for precision, t in t_eval.items():
        print(f"{'ratio (b)/(a ' + precision + ')':<28}: {t / t_plugin:7.2f}x")
    print(f"max |difference|            : {np.abs(got - ref).max():.2e} (values up to {np.abs(ref).max():.2f})")
    evaluation = {"model": args.model or "a random Triple Plane", "model_shape": list(model.positional_plane().shape),
                  "method": args.method, "queries": n, "repeats": args.repeats,
                  "eval_queries_per_second": {p: n / t for p, t in t_eval.items()},
                  "plugin_queries_per_second": n / t_plugin, "plugin_first_call_seconds": t_first,
                  "max_abs_difference": float(np.abs(got - ref).max()), "max_abs_value": float(np.abs(ref).max())}
    parts = {"eval": evaluation}
    if args.scenes:
        parts["scenes"] = bench_scenes(model, args)
    write_json(args, **parts)


def bench_scenes(model, args) -> dict:
    """``render_scene`` (what ``dynbtf render`` runs) of two scenes at its defaults, twice each: seconds."""
    import tempfile

    from dynbtf.render.mitsuba.scene_render import render_scene
    from dynbtf.representations.model_file import save_model

    path = Path(args.model) if args.model else save_model(Path(tempfile.mkdtemp()) / "model.dbtfm", model)
    rows = []
    for scene, lighting, method in (("plane", "sky", "hist"), ("sphere", "sky", "hex")):
        for run in (1, 2):
            result = render_scene(path, scene=scene, lighting=lighting, method=method, progress=False)
            rows.append({"scene": scene, "lighting": lighting, "method": method, "run": run,
                         "seconds": result.seconds, "first_pass_seconds": result.first_pass_seconds,
                         "compile_seconds": result.compile_seconds, "passes": result.passes})
            print(f"render {scene}/{lighting}/{method}, run {run}: {result.seconds:.1f} s (first pass "
                  f"{result.first_pass_seconds:.1f} s, compile {result.compile_seconds:.1f} s)")
    return {"model": args.model or "a random Triple Plane", "model_shape": list(model.positional_plane().shape),
            "resolution": [512, 512], "spp": 16, "spp_per_pass": 4, "rows": rows}


def write_json(args, **parts) -> None:
    """Write the measured ``parts`` (``eval``, ``scenes``) to ``args.json``, each with the run's command, commit and
    machine."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result

    data = {"benchmark": "rendering"}
    for name, part in parts.items():
        data[name] = header("rendering", "bench_render.py") | part
        data[name].pop("benchmark")
    write_result(args.json, data)


def shifted_uv(uv, shift):
    """The float64 uv the plugin's call with ``shift`` evaluated (:func:`plugin_seconds`): ``u + shift`` rounded to
    float32 as the plugin's input was, so that the reference queries the same points."""
    out = uv.astype(np.float64)
    out[:, 0] = (uv[:, 0] + np.float32(shift)).astype(np.float64)
    return out


def jit_array(values):
    """``values`` as an ``mi.Float`` in memory of Dr.Jit's own (computed): a buffer taken from NumPy has NumPy's
    alignment, which Dr.Jit compiles into the kernel (aligned or unaligned loads), so inputs wrapped afresh per
    call would compile a new kernel whenever their alignment changes."""
    import drjit as dr
    from dynbtf.jit import mi_module

    mi = mi_module()
    out = mi.Float(np.ascontiguousarray(values, dtype=np.float32)) * dr.opaque(mi.Float, 1.0)  # exact, a new buffer
    dr.eval(out)
    return out


def plugin_seconds(evaluator, uv, wv, wl, repeats, footprint=None, start=0):
    """Seconds of ``repeats`` plugin evaluations on fresh inputs (uv shifted by whole repeats) and the last output.

    ``footprint`` (optional, ``(N,)`` repeats): the evaluator's footprint queries; ``start``: the first shift.
    """
    import drjit as dr
    from dynbtf.jit import mi_module

    mi = mi_module()
    WV = mi.Vector3f(*(jit_array(wv[:, k]) for k in range(3)))
    WL = mi.Vector3f(*(jit_array(wl[:, k]) for k in range(3)))
    times = []
    for k in range(start, start + repeats):
        U, V = jit_array(uv[:, 0] + np.float32(k)), jit_array(uv[:, 1])
        extra = {} if footprint is None else {"footprint": jit_array(footprint)}
        dr.eval(U, V, WV, WL, *extra.values())
        t0 = time.perf_counter()
        out = evaluator.eval(U, V, WV, WL, **extra)
        dr.eval(out)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return times, np.stack([np.asarray(out[k]) for k in range(3)], -1)


if __name__ == "__main__":
    with torch.no_grad():
        main()
