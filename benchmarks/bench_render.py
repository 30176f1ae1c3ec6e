"""Shading-point throughput of the Mitsuba plugin's Dr.Jit evaluation vs ``SynthesizedBTF.eval``.

Evaluates the same 1920 x 1080 random queries (uv within 25 repeats, upper-hemisphere
view and light) through

(a) ``SynthesizedBTF.eval`` (dynbtf's CPU fast path: numba synthesis kernel + torch decoder), in
    float32 (its default) and in bfloat16 (``precision="bf16"``), each after a warm-up call and the
    fastest of the same number of calls as (b), and
(b) ``DynBTFEvaluator.eval`` (what the ``dynbtf`` BSDF runs per shading point: the whole chain
    traced by Dr.Jit into one kernel), the fastest of several calls on fresh inputs (the first
    ones compile),

and prints queries/s of each, their ratio, the one-off compile time and the largest difference.

Then relief (kind ``triple-parallax``): the plugin's kernel with the ray march through the
synthesized height next to the same kernel without it (the flat model: same decoder, features
fetched at ``uv``) and with a dense march (fixed half-texel search steps), on the same queries
sorted by view elevation (what a camera's coherent lanes see: a SIMD vector of the kernel waits
for its longest march) and in random order: the ratios parallax/flat, the largest value difference
between the march and the dense one, and the largest difference to ``SynthesizedBTF.eval`` on a
subset. The parallax model is MODEL if it is
one, else a random one of the same size with a relief of ``--relief-texels`` (default 5, the
simulated stone's).

Then struct vs hist: the plugin's kernel cost per query of cell quilting (``struct``: the cell's
hashes, one cut-table entry per edge band, one fetch) next to histogram-preserving blending (``hist``:
the triangle lattice, three hashed fetches, the inverse transform), timed side by side (the two
methods' calls interleaved, fresh inputs each, fastest of ``--repeats``): the synthesis alone (what
the kernel computes before the decoder) and the whole evaluation (with the decoder, the same for
both), and their ratios struct / hist. On a structured exemplar: MODEL's positional plane if
``auto`` chooses struct for it, else the model with its plane replaced by a weave (a
``1/8``-repeat element tiled 8 x 8, plus 10% noise), so that cells choose among a lattice of offsets.
``--struct-only`` runs this part alone, ``--relief-only`` the relief part.

Run: ``python benchmarks/bench_render.py [MODEL] [--method hist] [--struct-only | --relief-only]`` (default: a random
model of the paper's size, 128 x 128 texels).

The throughput (``eval``) and relief (``relief``) parts are also written as JSON (``--json``, default
``benchmarks/results/rendering.json``), each with the command, the commit and the CPU that measured it (a
``--relief-only`` run replaces the relief part and keeps the other), from which docs/results.md's rendering tables
and Speed rows are generated (``python benchmarks/tables.py``).
"""

from __future__ import annotations

import argparse
import json
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
    parser.add_argument("--relief-texels", type=float, default=5.0,
                        help="peak-to-peak height of the random parallax model, in texels")
    parser.add_argument("--struct-only", action="store_true", help="only the struct vs hist comparison")
    parser.add_argument("--relief-only", action="store_true", help="only the relief (parallax vs flat) comparison")
    parser.add_argument("--json", type=Path, default=RESULTS, help="where the eval and relief parts are written")
    args = parser.parse_args()

    from dynbtf.jit import mi_module
    from dynbtf.render.mitsuba.bsdf import DynBTFEvaluator, configure_jit
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
    if args.struct_only:
        bench_struct(model, args, uv, wv, wl)
        return
    if args.relief_only:
        write_json(args, relief=bench_relief(model, args, uv, wv, wl))
        return
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
    # the first call compiles (inputs in Dr.Jit's own memory, jit_array: NumPy buffers' varying alignment used to
    # compile a new kernel on some calls); time several calls on fresh inputs and report the first and the fastest
    times, got = plugin_seconds(ev, uv, wv, wl, args.repeats)
    t_first, t_drjit = times[0], min(times)
    shifted = shifted_uv(uv, args.repeats - 1)
    ref = btf.eval(shifted, wv, wl)
    print(f"{n} queries, method {args.method}, model {tuple(model.positional_plane().shape)}")
    for precision, t in t_eval.items():
        print(f"{'(a) SynthesizedBTF.eval ' + precision:<28}: {n / t / 1e6:7.2f} M queries/s ({t:.3f} s; fastest of "
              f"{args.repeats} after a warm-up)")
    print(f"(b) plugin Dr.Jit kernel    : {n / t_drjit / 1e6:7.2f} M queries/s ({t_drjit:.3f} s; "
          f"fastest of {len(times)}; first call incl. compile {t_first:.1f} s)")
    for precision, t in t_eval.items():
        print(f"{'ratio (b)/(a ' + precision + ')':<28}: {t / t_drjit:7.2f}x")
    print(f"max |difference|            : {np.abs(got - ref).max():.2e} (values up to {np.abs(ref).max():.2f})")
    evaluation = {"model": args.model or "a random Triple Plane", "model_shape": list(model.positional_plane().shape),
                  "method": args.method, "queries": n, "repeats": args.repeats,
                  "eval_queries_per_second": {p: n / t for p, t in t_eval.items()},
                  "plugin_queries_per_second": n / t_drjit, "plugin_first_call_seconds": t_first,
                  "max_abs_difference": float(np.abs(got - ref).max()), "max_abs_value": float(np.abs(ref).max())}
    relief = bench_relief(model, args, uv, wv, wl)
    write_json(args, eval=evaluation, relief=relief)
    bench_struct(model, args, uv, wv, wl)


def write_json(args, **parts) -> None:
    """Write the measured ``parts`` (``eval``, ``relief``) to ``args.json``, each with the run's command, commit and
    machine; the parts this run did not measure are kept from the file."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result

    data = json.loads(args.json.read_text()) if args.json.is_file() else {}
    data["benchmark"] = "rendering"
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


def parallax_model(model, relief_texels: float):
    """``model`` if it has relief, else a random triple-parallax model of its size with smooth random relief."""
    from dynbtf.representations.parallax import ParallaxTriplePlane

    if getattr(model, "kind", None) == "triple-parallax":
        return model
    h, w, c = model.positional_plane().shape
    relief = ParallaxTriplePlane(h, w, positional_channels=c, seed=0)
    generator = torch.Generator().manual_seed(0)
    noise = torch.rand(1, 1, h // 8, w // 8, generator=generator)
    smooth = torch.nn.functional.interpolate(noise, size=(h, w), mode="bicubic", align_corners=False)[0, 0]
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min())
    relief.set_height(smooth * relief_texels / max(h, w))
    return relief


def bench_relief(model, args, uv, wv, wl) -> None:
    """The parallax kernel vs the flat one (sorted by view elevation and in random order), and vs the same kernel
    with a dense march (fixed half-texel search steps: ``max_step = step``, the sampling of the march before its
    variable steps), timed in the same run; the largest value difference between the two marches. Returns the
    measured values (for the JSON)."""
    from dynbtf.render.mitsuba.bsdf import DynBTFEvaluator
    from dynbtf.synthesized import synthesized_btf

    relief = parallax_model(model, args.relief_texels)
    lo, hi = relief.height_range()
    texels = (hi - lo) * max(relief.height_channel.shape)
    ev = DynBTFEvaluator(synthesized_btf(relief, args.method, seed=0))
    march = dict(ev.model.march)
    dense = {**march, "max_step": march["step"]}
    n = len(uv)
    order = np.argsort(wv[:, 2], kind="stable")
    results = {}
    for name, idx in (("random order", np.arange(n)), ("sorted by view elevation", order)):
        for kind, on, params in (("flat", False, march), ("parallax", True, march), ("dense", True, dense)):
            ev.relief, ev.model.march = on, params
            results[name, kind] = plugin_seconds(ev, uv[idx], wv[idx], wl[idx], args.repeats)
    ev.relief, ev.model.march = True, march
    print(f"\nrelief: triple-parallax {tuple(relief.positional_plane().shape)}, height range {texels:.1f} texels, "
          f"method {args.method}, {n} queries")
    for name in ("sorted by view elevation", "random order"):
        flat, marched, slow = (min(results[name, kind][0]) for kind in ("flat", "parallax", "dense"))
        print(f"  {name:<25}: flat {flat / n * 1e9:6.0f} ns/query, parallax {marched / n * 1e9:6.0f} ns/query, "
              f"ratio parallax/flat {marched / flat:5.2f}x (dense march {slow / flat:5.2f}x)")
    got, slow = results["random order", "parallax"][1], results["random order", "dense"][1]
    span = slow.max() - slow.min()
    gap = np.abs(got - slow).max(-1)
    print(f"  vs the dense march: max |difference| {gap.max():.2e} (value range {span:.2f}); "
          f"{np.mean(gap > 1e-3 * span):.3%} of queries beyond 1e-3 of the range")
    m = min(n, 100_000)
    shifted = shifted_uv(uv[:m], args.repeats - 1)
    ref = synthesized_btf(relief, args.method).eval(shifted, wv[:m], wl[:m])
    print(f"  max |difference| to SynthesizedBTF.eval: {np.abs(got[:m] - ref).max():.2e} "
          f"(value range {ref.max() - ref.min():.2f}; {m} queries)")
    return {"model": args.model if relief is model else f"a random triple-parallax model of {args.relief_texels:g} "
                                                           "texels of relief",
            "model_shape": list(relief.positional_plane().shape), "relief_texels": float(texels),
            "method": args.method, "queries": n, "repeats": args.repeats,
            "ns_per_query": {name: {kind: min(results[name, kind][0]) / n * 1e9
                                    for kind in ("flat", "parallax", "dense")}
                             for name in ("random order", "sorted by view elevation")},
            "max_abs_difference_to_dense": float(gap.max()), "dense_value_range": float(span),
            "max_abs_difference_to_eval": float(np.abs(got[:m] - ref).max()),
            "eval_value_range": float(ref.max() - ref.min()), "eval_queries_compared": m}


def synthesis_seconds(evaluator, uv, shift):
    """Seconds of the evaluator's synthesis alone (what its kernel computes before the decoder) on ``uv`` shifted by
    ``shift`` whole repeats."""
    import drjit as dr

    U, V = jit_array(uv[:, 0] + np.float32(shift)), jit_array(uv[:, 1])
    synth = evaluator.synthesizer
    t0 = time.perf_counter()
    out = synth.latent(U, V) if evaluator._latent else synth.features(U, V)
    dr.eval(out)
    dr.sync_thread()
    return time.perf_counter() - t0


def structured_model(model):
    """``model`` if ``auto`` chooses struct for its positional plane, else a copy whose plane is a weave
    (an element of 1/8 of the plane's side, from the plane itself, tiled 8 x 8, plus 10% noise)."""
    import copy

    from dynbtf.synthesis.auto import choose_method

    plane = model.positional_plane().detach()
    if choose_method(plane).method == "struct":
        return model
    h, w, c = plane.shape
    weave = copy.deepcopy(model)
    element = plane[: h // 8, : w // 8]
    generator = torch.Generator().manual_seed(0)
    noise = torch.randn(h // 8 * 8, w // 8 * 8, c, generator=generator)
    with torch.no_grad():
        weave.positional_plane().zero_()
        weave.positional_plane()[: h // 8 * 8, : w // 8 * 8] = element.repeat(8, 8, 1) + 0.1 * float(element.std()) * noise
    return weave


def bench_struct(model, args, uv, wv, wl) -> None:
    """struct vs hist: the plugin's synthesis and whole evaluation per query, side by side (see the module docstring)."""
    from dynbtf.render.mitsuba.bsdf import DynBTFEvaluator
    from dynbtf.synthesis.auto import choose_method
    from dynbtf.synthesized import synthesized_btf

    weave = structured_model(model)
    line = choose_method(weave.positional_plane().detach()).line
    methods = ("hist", "struct")
    evaluators = {m: DynBTFEvaluator(synthesized_btf(weave, m, seed=0)) for m in methods}
    n = len(uv)
    compile_seconds = {}
    for m, ev in evaluators.items():  # the first calls compile (or load the kernels from Dr.Jit's cache)
        t0 = time.perf_counter()
        plugin_seconds(ev, uv, wv, wl, 2, start=1000)
        synthesis_seconds(ev, uv, 1000)
        synthesis_seconds(ev, uv, 1001)
        compile_seconds[m] = time.perf_counter() - t0
    synthesis = {m: [] for m in methods}
    whole = {m: [] for m in methods}
    got = {}
    for k in range(args.repeats):  # interleaved: both methods see the same machine load
        for m, ev in evaluators.items():
            synthesis[m].append(synthesis_seconds(ev, uv, k))
            times, got[m] = plugin_seconds(ev, uv, wv, wl, 1, start=k)
            whole[m] += times
    params = evaluators["struct"].btf.synthesizer.parameters()
    print(f"\nstruct vs hist: {n} queries, model {tuple(weave.positional_plane().shape)} "
          f"({'MODEL' if weave is model else 'plane replaced by a weave'}); {line}")
    print(f"  struct: {params['offsets']} offsets, cells {params['cells']}, margins {params['margin']} texels")
    for what, runs in (("synthesis alone", synthesis), ("whole evaluation", whole)):
        best = {m: min(t) for m, t in runs.items()}
        print(f"  {what:<17}: hist {best['hist'] / n * 1e9:6.1f} ns/query, struct {best['struct'] / n * 1e9:6.1f} "
              f"ns/query, ratio struct/hist {best['struct'] / best['hist']:5.2f}x (fastest of {args.repeats})")
    print(f"  first calls incl. compile: hist {compile_seconds['hist']:.1f} s, struct {compile_seconds['struct']:.1f} s")
    m = min(n, 100_000)
    shifted = shifted_uv(uv[:m], args.repeats - 1)
    ref = synthesized_btf(weave, "struct").eval(shifted, wv[:m], wl[:m])
    print(f"  struct: max |difference| to SynthesizedBTF.eval: {np.abs(got['struct'][:m] - ref).max():.2e} "
          f"(values up to {np.abs(ref).max():.2f}; {m} queries)")


if __name__ == "__main__":
    with torch.no_grad():
        main()
