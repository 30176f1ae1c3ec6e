"""Does the plugin's importance sampling converge faster? MSE against a converged render, cosine vs mixture.

For each model (e.g. fitted lacquered wood, leather, stone) and each lighting of
:func:`dynbtf.render.mitsuba.scenes.scene_dict` (``point``: a point light plus a dim constant
environment; ``sky``: an importance-sampled HDR sky), the ``sphere`` scene (a sphere
covered by the synthesized BTF on a grey floor; Mitsuba's ``path`` integrator,
max depth 3 (``--max-depth``), which combines BSDF and emitter sampling by MIS) is rendered with

* ``sampling="cosine"`` (the paper's cosine-weighted directions) and
* ``sampling="mixture"`` (the plugin's sampling table mixed with cosine, weight ``--mix``),

and it prints what the plugin's default, ``sampling="auto"``, picks for each model (the last
column of the table), at ``--spp`` samples per pixel with ``--seeds`` different sampler seeds, and compared with a
reference of ``--ref-spp`` samples per pixel (mixture sampling, its own seeds). The MSE is
the mean over the pixels that show the sphere (found by casting the camera's pixel-centre
rays) and over RGB; the reference's own noise (its MSE is ~``spp / ref_spp`` of a
render's) is not subtracted.

Equal time: each sampling's seconds per render of ``--spp`` (kernels compiled first; the
median of ``--repeats`` renders, the two samplings interleaved so that load on the
machine affects both alike). With unbiased estimators MSE falls as 1 / samples, so
the MSE at equal time compares ``MSE x seconds`` (the inverse of the efficiency):

* equal spp: ``MSE_cosine / MSE_mixture`` (> 1: mixture better),
* equal time: ``(MSE_cosine x t_cosine) / (MSE_mixture x t_mixture)`` (> 1: mixture better).

Run (models from ``dynbtf fit``; small sizes so that it finishes in minutes on 2 cores)::

    python benchmarks/bench_sampling.py wood.dbtfm leather.dbtfm stone.dbtfm --size 64 --spp 16

The rows are written to ``--json`` (default ``benchmarks/results/sampling.json``; docs/results.md's sampling table
and its Speed row are generated from it).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def sphere_mask(mi, scene, size: int) -> np.ndarray:
    """``(size, size)`` bool: pixels whose centre ray hits the scene's sphere (the material)."""
    import drjit as dr

    sensor = scene.sensors()[0]
    i, j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    pos = mi.Point2f(mi.Float(((j + 0.5) / size).ravel()), mi.Float(((i + 0.5) / size).ravel()))
    rays, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(rays)
    sphere = [s for s in scene.shapes() if s.id() == "surface"]  # scene_dict's key of the material's shape
    hit = si.shape == mi.ShapePtr(sphere[0])
    return np.array(hit).reshape(size, size) & np.array(dr.isfinite(si.t)).reshape(size, size)


def render(mi, scene, spp: int, seed: int) -> np.ndarray:
    import drjit as dr

    img = mi.render(scene, spp=spp, seed=seed)
    dr.eval(img)
    return np.asarray(img, dtype=np.float64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", help="dynbtf model files (names: their file stems)")
    parser.add_argument("--lightings", nargs="+", default=["point", "sky"])
    parser.add_argument("--size", type=int, default=64, help="image side in pixels")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel of the compared renders")
    parser.add_argument("--seeds", type=int, default=4, help="compared renders per sampling (their MSEs averaged)")
    parser.add_argument("--ref-spp", type=int, default=2048, help="samples per pixel of the reference")
    parser.add_argument("--repeats", type=int, default=5, help="timed renders per sampling (median)")
    parser.add_argument("--mix", type=float, default=0.75, help="sampling_weight of the mixture")
    parser.add_argument("--scale", type=float, default=6.0, help="exemplar repeats around the sphere")
    parser.add_argument("--max-depth", type=int, default=3, help="path length (2: direct light only, 3: one bounce)")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "sampling.json")
    args = parser.parse_args()

    from dynbtf.jit import mi_module
    from dynbtf.render.mitsuba.bsdf import load_plugin_model, register_plugin
    from dynbtf.render.mitsuba.sampling import AUTO_MIN_COSINE_VARIANCE, build_sampling_table, cosine_relative_variance
    from dynbtf.render.mitsuba.scenes import bsdf_dict, scene_dict

    register_plugin("llvm_ad_rgb")
    mi = mi_module()
    rows = []
    auto = {}
    for model in args.models:
        # what the plugin's default, sampling="auto", picks for this model, and why
        bsdf = mi.load_dict(bsdf_dict(model, method="hist", scale=args.scale, seed=0))
        variance = (bsdf.sampler.cosine_relative_variance if bsdf.sampler is not None else
                    cosine_relative_variance(build_sampling_table(load_plugin_model(model))))
        auto[Path(model).stem] = bsdf.sampling
        print(f"{Path(model).stem}: sampling='auto' picks {bsdf.sampling!r} (cosine relative variance of its "
              f"table {variance:.3g}; threshold {AUTO_MIN_COSINE_VARIANCE:g})", flush=True)
        for lighting in args.lightings:
            scenes = {}
            for sampling in ("cosine", "mixture"):
                material = bsdf_dict(model, method="hist", scale=args.scale, seed=0, sampling=sampling)
                if sampling == "mixture":
                    material["sampling_weight"] = args.mix
                scenes[sampling] = mi.load_dict(scene_dict("sphere", material, lighting=lighting,
                                                           resolution=(args.size, args.size), spp=args.spp,
                                                           max_depth=args.max_depth))
            mask = sphere_mask(mi, scenes["cosine"], args.size)
            chunk = 256
            ref = np.zeros((args.size, args.size, 3))
            for k in range(args.ref_spp // chunk):
                ref += render(mi, scenes["mixture"], chunk, 10_000 + k)
            ref /= args.ref_spp // chunk
            mse, seconds = {}, {s: [] for s in scenes}
            for sampling, scene in scenes.items():
                render(mi, scene, args.spp, 0)  # compile
                errors = [((render(mi, scene, args.spp, 1 + s) - ref)[mask] ** 2).mean() for s in range(args.seeds)]
                mse[sampling] = float(np.mean(errors))
            for r in range(args.repeats):
                for sampling, scene in scenes.items():
                    t0 = time.perf_counter()
                    render(mi, scene, args.spp, 100 + r)
                    seconds[sampling].append(time.perf_counter() - t0)
            t = {s: float(np.median(v)) for s, v in seconds.items()}
            rows.append((Path(model).stem, lighting, mse["cosine"], mse["mixture"], t["cosine"], t["mixture"]))
            r = rows[-1]
            print(f"{r[0]:<16} {r[1]:<6} MSE cosine {r[2]:.3e} mixture {r[3]:.3e} | equal spp {r[2] / r[3]:5.2f}x | "
                  f"s/render {r[4]:.3f} vs {r[5]:.3f} | equal time {r[2] * r[4] / (r[3] * r[5]):5.2f}x", flush=True)

    print(f"\n{args.size} x {args.size} px, sphere scene (max depth {args.max_depth}), {args.spp} spp x {args.seeds} seeds vs {args.ref_spp} spp "
          f"reference, mixture weight {args.mix}; MSE over the sphere's {int(mask.sum())} pixels")
    print("| model | lighting | MSE cosine | MSE mixture | equal spp: cosine / mixture | s per render cosine / mixture "
          "| equal time: cosine / mixture | auto picks |")
    print("|---|---|---|---|---|---|---|---|")
    for name, lighting, m_c, m_m, t_c, t_m in rows:
        print(f"| {name} | {lighting} | {m_c:.3e} | {m_m:.3e} | **{m_c / m_m:.2f}x** | {t_c:.3f} / {t_m:.3f} | "
              f"**{m_c * t_c / (m_m * t_m):.2f}x** | {auto[name]} |")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result

    records = [{"model": name.replace("_", " "), **({"note": "glossy"} if auto[name] == "mixture" else {}),
                "lighting": lighting, "mse_cosine": m_c, "mse_mixture": m_m, "equal_spp_ratio": m_c / m_m,
                "seconds_cosine": t_c, "seconds_mixture": t_m, "equal_time_ratio": m_c * t_c / (m_m * t_m),
                "auto": auto[name]} for name, lighting, m_c, m_m, t_c, t_m in rows]
    conditions = (f"the sphere scene (path, depth {args.max_depth}), hist, {args.size} x {args.size} px; MSE over the "
                  f"sphere's pixels of {args.spp}-spp renders (mean of {args.seeds} seeds) against {args.ref_spp} spp; "
                  f"seconds per render the median of {args.repeats}, interleaved; equal time compares MSE x seconds")
    write_result(args.json, header("sampling", "bench_sampling.py") | {"conditions": conditions, "rows": records})


if __name__ == "__main__":
    main()
