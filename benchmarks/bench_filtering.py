"""Footprint-filtered queries vs point queries on an endless plane at a grazing view (issue: filtering).

One run renders the same plane (preview renderer, :func:`dynbtf.render.preview.render_preview`;
synthesis ``--method`` at ``--scale`` repeats per uv unit) for each synthesis seed of ``--seeds`` (three by default)
several times:

* **reference** -- ``--ref-spp`` (256) point samples per pixel on a stratified grid (the supersampled
  synthesized BTF: what a filtered query must approach);
* **unfiltered** -- 1 point sample per pixel (today's query);
* **filtered** -- 1 footprint query per pixel (``footprint`` from the camera's ray differentials),
  with the per-level decoders (default) and with the plain decoder (``level_decoders=False``);
* **stochastic** -- 1 point query at a random position in each pixel (stochastic texture
  filtering's one sample of the pixel's box filter, the baseline),

and prints FLIP (LDR, sRGB) of each 1-spp image against the reference, the relative error of the far
field's mean colour (the plane's rows nearest the horizon, ``--far`` of the plane's rows), each per seed and
their mean; then, with the first seed, the cost
per query of ``SynthesizedBTF.eval`` filtered / point on the same queries (best of ``--repeats``
calls each, interleaved), and what the filtering adds to memory and to the model file. With
``--images DIR`` it writes ``plane_filtering.png`` (reference | unfiltered | filtered).

Then the Mitsuba plugin (unless ``--no-mitsuba``): its cost per query filtered / point on the same
queries (the evaluator the BSDF runs, fastest of ``--repeats`` interleaved calls after compiling),
the largest difference to ``SynthesizedBTF.eval`` with the same footprints, and a render of
:func:`dynbtf.render.mitsuba.scenes.scene_dict`'s ``plane`` scene (a 40 x 40 plane seen at a grazing
angle; the point light alone, direct light; ``--mitsuba-size`` px, the material at ``--scale``
repeats per mesh uv unit): 1 spp with footprints from the camera's ray cone, 1 spp without, and a
``--ref-spp`` reference without, FLIP of each against the reference (``plane_filtering_mitsuba.png``
with ``--images``).

The quality rows (per seed, their mean, min and max) are written as JSON (``--json``, default
``benchmarks/results/filtering.json``) with the command, the commit and the machine; docs/results.md's table is
generated from it (``python benchmarks/tables.py``).

Run: ``python benchmarks/bench_filtering.py MODEL.dbtfm [--method hist --scale 45 --size 256 --seeds 0 1 2]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("--method", default="hist", choices=["tile", "linear", "hist", "hex"])
    parser.add_argument("--scale", type=float, default=45.0, help="exemplar repeats per uv unit")
    parser.add_argument("--size", type=int, default=256, help="image side, pixels")
    parser.add_argument("--ref-spp", type=int, default=256)
    parser.add_argument("--far", type=float, default=0.25, help="share of the plane's rows (from the horizon) "
                                                                "that make the far field")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="synthesis seeds (quality: each)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--images", default=None, help="directory for plane_filtering.png")
    parser.add_argument("--no-mitsuba", action="store_true", help="skip the plugin's cost and render")
    parser.add_argument("--mitsuba-size", type=int, default=192, help="width of the Mitsuba render, pixels")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "filtering.json")
    args = parser.parse_args()
    quality = [measure_seed(args, seed) for seed in args.seeds]
    args.seed = args.seeds[0]
    write_json(args, quality, costs(args, quality[0]))


#: The kinds of 1-sample-per-pixel query compared, as the table names them.
QUERIES = {"unfiltered (point query)": "point query (no footprint)",
           "stochastic (1 random point in the pixel)": "stochastic (one random point in the pixel)",
           "filtered, plain decoder": "mip-mapped features, the plain decoder",
           "filtered (default)": "mip-mapped features, per-level decoders, mean appearance at the top level "
                                 "(the default)"}


def write_json(args, quality: list[dict], cost: dict) -> None:
    """The quality rows over the seeds (each seed's value, the mean, min and max) and the first seed's costs
    (:func:`costs`) as JSON (``args.json``)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, write_result

    rows = []
    for name, label in QUERIES.items():
        flips = [q["scores"][name] for q in quality]
        errors = [100 * q["far_error"][name] for q in quality]
        rows.append({"query": label, "flip": float(np.mean(flips)), "flip_per_seed": flips,
                     "flip_range": [min(flips), max(flips)], "far_field_error_percent": float(np.mean(errors)),
                     "far_field_error_percent_per_seed": errors, "far_field_error_range": [min(errors), max(errors)]})
    rows[-1]["bold"] = ["query", "flip", "far_field_error_percent"]
    write_result(args.json, header("filtering", "bench_filtering.py") | {
        "model": os.path.basename(args.model), "seeds": list(args.seeds),
        "conditions": f"an endless plane at a grazing view, {args.scale:g}x, {args.method}, {args.size} x {args.size} "
                      f"pixels, 1 sample per pixel against a {args.ref_spp}-samples-per-pixel reference with the same "
                      f"seed; the mean over {len(args.seeds)} synthesis seeds (per seed: flip_per_seed)",
        "rows": rows, "cost": cost})


def measure_seed(args, seed: int) -> dict:
    """One seed's renders: FLIP and far-field error of each kind of query (printed; returned with what
    :func:`costs` needs)."""
    from dynbtf.metrics import flip
    from dynbtf.render.preview import DirectionalLight, grazing_camera, render_preview
    from dynbtf.synthesized import synthesized_btf

    synthesized_btf(args.model, args.method, scale=args.scale, seed=seed)  # the tables, before the timed fit
    t0 = time.perf_counter()
    btf = synthesized_btf(args.model, args.method, scale=args.scale, seed=seed, footprints=True)
    t_fit = time.perf_counter() - t0
    camera = grazing_camera(distance=6.0, height=0.6, fov=40.0)
    light = DirectionalLight((0.3, 0.5, 0.8), 1.0)
    res = (args.size, args.size)
    t0 = time.perf_counter()
    reference = render_preview(btf, camera, light, resolution=res, spp=args.ref_spp, progress=True)
    t_ref = time.perf_counter() - t0
    unfiltered = render_preview(btf, camera, light, resolution=res, spp=1)
    filtered = render_preview(btf, camera, light, resolution=res, spp=1, filtered=True)
    plain = synthesized_btf(args.model, args.method, scale=args.scale, seed=seed, level_decoders=False)
    images = {"unfiltered (point query)": unfiltered,
              "stochastic (1 random point in the pixel)": render_preview(
                  btf, camera, light, resolution=res, spp=1, filtered=False, jitter_seed=seed),
              "filtered, plain decoder": render_preview(plain, camera, light, resolution=res, spp=1, filtered=True),
              "filtered (default)": filtered}

    _, d_top = camera.rays(*res, np.array([0.0, -0.5]))  # rows whose pixels lie wholly on the plane
    hit_rows = np.nonzero((d_top[..., 2] < -1e-12).all(axis=1))[0]
    far_rows = hit_rows[: max(1, int(round(args.far * len(hit_rows))))]
    exposure = 0.8 / float(np.percentile(reference[hit_rows], 99.0))
    scores = {name: flip(reference * exposure, img * exposure) for name, img in images.items()}
    ref_far = reference[far_rows].reshape(-1, 3).mean(0)
    far_error = {name: float(np.abs(img[far_rows].reshape(-1, 3).mean(0) / ref_far - 1.0).max())
                 for name, img in images.items()}
    print(f"plane: {args.method}, scale {args.scale:g}x, {args.size} x {args.size} px, seed {seed}; "
          f"reference {args.ref_spp} spp ({t_ref:.0f} s); per-level decoders fitted in {t_fit:.0f} s")
    print(f"| {'1 sample per pixel':42s} | FLIP vs reference | far-field mean colour error |")
    print(f"|{'-' * 44}|------------------:|----------------------------:|")
    for name in images:
        print(f"| {name:42s} | {scores[name]:17.4f} | {100 * far_error[name]:26.2f}% |")
    ratio = scores["filtered (default)"] / scores["unfiltered (point query)"]
    print(f"FLIP filtered / unfiltered = {ratio:.3f} (target <= 0.5; filtered target <= 0.05; far field: the "
          f"{len(far_rows)} plane rows nearest the horizon, worst channel, target 2%)")
    return {"btf": btf, "camera": camera, "light": light, "res": res, "reference": reference,
            "unfiltered": unfiltered, "filtered": filtered, "exposure": exposure, "hit_rows": hit_rows,
            "scores": scores, "far_error": far_error}


def costs(args, q: dict) -> dict:
    """With one seed's renders ``q``: the cost per query filtered / point, the memory, the images and the plugin
    (printed, and returned for the JSON)."""
    from dynbtf.render.preview import plane_footprint
    from dynbtf.synthesis.mip import pyramid_storage_bytes

    btf, camera, light, res = q["btf"], q["camera"], q["light"], q["res"]
    # cost per query: the 1-spp frame's queries, filtered vs point, interleaved calls
    o, d = camera.rays(*res)
    hit = d[..., 2] < -1e-12
    t_hit = -o[2] / d[hit][:, 2]
    uv = (o + t_hit[:, None] * d[hit])[:, :2]
    w_view = -d[hit]
    w_light = np.broadcast_to(np.asarray(light.direction) / np.linalg.norm(light.direction), w_view.shape)
    footprint = plane_footprint(camera, d[hit], *res)
    n = len(uv)
    reps = max(1, 1_000_000 // n)  # time ~1e6 queries per call
    uv_t, wv_t, wl_t, fp_t = (np.concatenate([x] * reps) for x in (uv, w_view, w_light, footprint))
    btf.eval(uv_t[:4096], wv_t[:4096], wl_t[:4096])
    btf.eval(uv_t[:4096], wv_t[:4096], wl_t[:4096], footprint=fp_t[:4096])
    best = {"point": float("inf"), "filtered": float("inf")}
    for _ in range(args.repeats):
        for name, extra in (("point", {}), ("filtered", {"footprint": fp_t})):
            t0 = time.perf_counter()
            btf.eval(uv_t, wv_t, wl_t, **extra)
            best[name] = min(best[name], time.perf_counter() - t0)
    pyramid = btf.synthesizer.pyramid() if hasattr(btf.synthesizer, "pyramid") else None
    memory = 0
    if pyramid is not None:
        memory = pyramid_storage_bytes(pyramid["levels"]) + pyramid_storage_bytes(pyramid.get("luminances", []))
        if "luts" in pyramid:
            memory += pyramid["luts"][1:].numel() * pyramid["luts"].element_size()
    per_query = {k: v / len(uv_t) * 1e9 for k, v in best.items()}
    print(f"eval cost per query ({len(uv_t)} queries, best of {args.repeats}): point {per_query['point']:.0f} ns, "
          f"filtered {per_query['filtered']:.0f} ns, ratio {best['filtered'] / best['point']:.2f}x (target <= 1.5x)")
    size = os.path.getsize(args.model)
    print(f"storage: model file {size} bytes, added to the file 0 bytes (pyramid and tables are derived at load); "
          f"in memory {memory} bytes ({100 * memory / size:.0f}% of the file)")
    if args.images:
        from dynbtf.io import save_image

        reference, unfiltered, filtered, exposure = q["reference"], q["unfiltered"], q["filtered"], q["exposure"]
        hit_rows = q["hit_rows"]
        gap = np.ones((args.size, 4, 3), dtype=np.float32)
        out = Path(args.images)
        out.mkdir(parents=True, exist_ok=True)
        save_image(out / "plane_filtering.png", np.concatenate([reference, gap, unfiltered, gap, filtered], axis=1),
                   exposure=exposure)
        crop = slice(hit_rows[0], hit_rows[0] + max(8, len(hit_rows) // 3))  # the far field, enlarged 2x
        zoom = [np.repeat(np.repeat(img[crop], 2, 0), 2, 1) for img in (reference, unfiltered, filtered)]
        gap2 = np.ones((zoom[0].shape[0], 4, 3), dtype=np.float32)
        save_image(out / "plane_filtering_far.png", np.concatenate([zoom[0], gap2, zoom[1], gap2, zoom[2]], axis=1),
                   exposure=exposure)
        print(f"wrote {out / 'plane_filtering.png'}")
    out = {"seed": args.seed, "queries": len(uv_t), "repeats": args.repeats, "eval_ns_per_query": per_query,
           "model_file_bytes": size, "memory_bytes": memory}
    if not args.no_mitsuba:
        out["plugin"] = bench_plugin(args, btf, uv_t, wv_t, wl_t, fp_t)
    return out


def bench_plugin(args, btf, uv, w_view, w_light, footprint) -> dict:
    """The plugin's footprint queries: cost and agreement on the frame's queries, and a Mitsuba render (printed, and
    returned for the JSON)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_render import plugin_seconds

    from dynbtf.metrics import flip
    from dynbtf.jit import mi_module
    from dynbtf.render.mitsuba.bsdf import register_plugin
    from dynbtf.render.mitsuba.evaluator import DynBTFEvaluator
    from dynbtf.render.mitsuba.scenes import bsdf_dict, scene_dict
    from dynbtf.synthesized import synthesized_btf

    register_plugin("llvm_ad_rgb")
    mi = mi_module()
    evaluator = DynBTFEvaluator(synthesized_btf(btf.model, args.method, seed=args.seed))
    evaluator.prepare_footprints()
    # the evaluator works in exemplar repeats: uv and footprints times the scale
    uv32 = (uv * args.scale).astype(np.float32)
    fp32 = (footprint * args.scale).astype(np.float32)
    wv32, wl32 = w_view.astype(np.float32), w_light.astype(np.float32)
    plugin_seconds(evaluator, uv32, wv32, wl32, 2)  # warm-up, point and footprint queries
    plugin_seconds(evaluator, uv32, wv32, wl32, 2, fp32)
    best = {"point": float("inf"), "filtered": float("inf")}
    got = None
    for _ in range(args.repeats):
        best["point"] = min(best["point"], min(plugin_seconds(evaluator, uv32, wv32, wl32, 1)[0]))
        times, got = plugin_seconds(evaluator, uv32, wv32, wl32, 1, fp32)
        best["filtered"] = min(best["filtered"], min(times))
    sub = slice(0, 200_000)
    library = synthesized_btf(btf.model, args.method, scale=1.0, seed=args.seed, footprints=True)
    ref = library.eval(uv32[sub].astype(np.float64), wv32[sub], wl32[sub], footprint=fp32[sub].astype(np.float64))
    per_query = {k: v / len(uv32) * 1e9 for k, v in best.items()}
    print(f"plugin cost per query ({len(uv32)} queries, best of {args.repeats}): point {per_query['point']:.0f} ns, "
          f"filtered {per_query['filtered']:.0f} ns, ratio {best['filtered'] / best['point']:.2f}x (target <= 1.5x); "
          f"largest difference to SynthesizedBTF.eval {np.abs(got[sub] - ref).max():.1e} "
          f"(values up to {np.abs(ref).max():.2f})")

    width = args.mitsuba_size
    res = (width * 3 // 4, width)

    def render(filtered: bool, spp: int, seed: int) -> np.ndarray:
        material = {**bsdf_dict(args.model, method=args.method, scale=args.scale, seed=args.seed),
                    "filtered": filtered}
        scene = scene_dict("plane", material, lighting="point", resolution=res, spp=spp, max_depth=2)
        del scene["ambient"]  # the point light alone: the texture is the only source of noise
        return np.asarray(mi.render(mi.load_dict(scene), spp=spp, seed=seed), dtype=np.float64)

    t0 = time.perf_counter()
    reference = sum(render(False, 64, 1000 + k) for k in range(args.ref_spp // 64)) / (args.ref_spp // 64)
    t_ref = time.perf_counter() - t0
    images = {"unfiltered (point query)": render(False, 1, 1), "filtered (ray cone)": render(True, 1, 1)}
    exposure = 0.8 / float(np.percentile(reference, 99.0))
    print(f"Mitsuba plane scene, {res[1]} x {res[0]} px, point light, direct; reference {args.ref_spp} spp "
          f"({t_ref:.0f} s)")
    scores = {name: flip(reference * exposure, img * exposure) for name, img in images.items()}
    for name, score in scores.items():
        print(f"| {name:42s} | {score:17.4f} |")
    print(f"Mitsuba FLIP filtered / unfiltered = {scores['filtered (ray cone)'] / scores['unfiltered (point query)']:.3f}")
    if args.images:
        from dynbtf.io import save_image

        gap = np.ones((res[0], 4, 3), dtype=np.float32)
        out = Path(args.images) / "plane_filtering_mitsuba.png"
        save_image(out, np.concatenate([reference, gap, images["unfiltered (point query)"], gap,
                                        images["filtered (ray cone)"]], axis=1), exposure=exposure)
        print(f"wrote {out}")
    return {"ns_per_query": per_query, "max_abs_difference": float(np.abs(got[sub] - ref).max()),
            "max_abs_value": float(np.abs(ref).max()), "scene_pixels": [res[1], res[0]],
            "scene_reference_spp": args.ref_spp, "scene_flip": scores}


if __name__ == "__main__":
    main()
