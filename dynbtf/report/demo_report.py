"""The demo's ``report.html``: every image and table of :func:`dynbtf.demo.run_demo`, at a glance first."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Any

from .html import HtmlReport

__all__ = ["write_demo_report"]


def _human_bytes(n: float | None) -> str:
    if n is None:
        return ""
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.3g} {unit}"
        n /= 1000.0
    return str(n)


def _angles(pair) -> str:
    """``(theta, phi)`` in degrees as text."""
    try:
        theta, phi = pair
        return f"(theta {float(theta):g}, phi {float(phi):g}) deg"
    except (TypeError, ValueError):
        return str(pair)


def _feature_caption(stem: str) -> str:
    """Caption of a feature-plane picture from its file name (dynbtf.representations.visualize)."""
    if stem == "height":
        return "height field (light = high)"
    name, _, what = stem.rpartition("_")
    plane = {"positional": "f_U (positional)", "f_h": "f_H (half vector)", "f_d": "f_D (difference vector)"}.get(
        name.lower(), name)
    if what == "pca":
        return f"{plane}: first three principal components as RGB"
    if what == "channels":
        return f"{plane}: each channel (rows theta 0-90 deg, columns phi 0-360 deg)"
    return stem.replace("_", " ")


def _training_state(fit: dict[str, Any], config) -> str:
    """Whether the fit finished, and if not, what stopped it and how to finish it."""
    if fit.get("finished", True):
        return f"finished ({fit.get('epochs_configured', '?')} epochs)"
    done = fit.get("epochs_completed")
    done = f"{done:.1f}" if isinstance(done, (int, float)) else "some"
    return (f"not finished: the time budget stopped it after {done} of {fit.get('epochs_configured', '?')} epochs; "
            f"run the same demo command again to continue the fit from its checkpoint")


#: Captions of the synthesis methods the demo shows (the demo's results list which ones ran, in order).
METHOD_TITLES = {"tile": "tiling (repetition)", "hist": "histogram-preserving blending", "hex": "hex-tiling",
                 "quilt": "image quilting (off-line)", "struct": "lattice-aligned cell quilting",
                 "auto": "auto (the method dynbtf chooses)"}


def write_demo_report(out: Path, config, results: dict[str, Any]) -> Path:
    """Write ``<out>/report.html`` from the stage results of the demo; return its path.

    Sections, each present when its stage produced something: at a glance, the measured BTF, the
    representation on held-out pairs, the feature planes, dynamic synthesis, the structured material,
    the renders, the real-time viewer; then the timings and the command that reproduces the run.
    Image paths in ``results`` are relative to ``out``.
    """
    out = Path(out)
    name = config.btf or f"simulated '{config.material}' ({config.size} x {config.size} texels, UBO2003 81 x 81 directions)"
    r = HtmlReport("dynbtf: an infinite BTF from a small exemplar",
                   f"Material: {name}. Pipeline: fit a Triple Plane (positional plane + half/difference-vector planes "
                   f"+ MLP), synthesize its positional plane dynamically, decode on demand.")
    syn = results.get("synthesis", {})
    ren = results.get("render", {}).get("renders", [])
    _at_a_glance(r, out, syn, ren)
    _data_section(r, out, results.get("data", {}))
    ev = results.get("evaluate", {})
    if ev:
        _evaluation_section(r, out, ev, results.get("fit", {}), config)
    _features_section(r, out, results.get("features", {}).get("images", []))
    if syn.get("grid"):
        _synthesis_section(r, out, syn)
    _structured_section(r, out, results.get("structured", {}))
    _renders_section(r, out, ren)
    _viewer_section(r, out, results.get("viewer"))
    _timings_section(r, out, config, results)
    return r.write(out / "report.html")


def _at_a_glance(r: HtmlReport, out: Path, syn: dict[str, Any], ren: list[dict[str, Any]]) -> None:
    """The synthesis previews side by side, and the path-traced renders of histogram-preserving blending."""
    r.section("At a glance", "The same fitted material on an endless plane seen at a grazing angle. Tiling repeats "
              "the exemplar (a visible grid towards the horizon); histogram-preserving blending and hex-tiling "
              "synthesize a non-repeating material on the fly.")
    if syn.get("previews"):
        r.images([(out / syn["previews"][m], METHOD_TITLES.get(m, m)) for m in syn["previews"]], width=420)
    teaser = [x for x in ren if x["method"] == "hist"]
    if teaser:
        r.paragraph("Path-traced in Mitsuba 3 with the dynbtf BSDF plugin (the library's query at every shading point), "
                    "histogram-preserving blending, two lighting conditions:")
        r.images([(out / x["path"], f"{x['scene']}, {x['lighting']} light, {x['scale']:g} repeats")
                  for x in teaser], width=300)


def _data_section(r: HtmlReport, out: Path, data: dict[str, Any]) -> None:
    """A few images of the measured BTF and its size (nothing without a data stage)."""
    if not data:
        return
    r.section("The measured BTF", "Images of the exemplar for a few (view, light) pairs (values exclude "
              "cos(theta_light)).")
    r.images([(out / x["path"], f"view {_angles(x['view'])}, light {_angles(x['light'])}")
              for x in data.get("images", [])], width=256, pixelated=True)
    d = data.get("describe", {})
    r.table([{"name": d.get("name", ""), "texels": f"{d.get('height')} x {d.get('width')}",
              "views x lights": f"{d.get('n_views')} x {d.get('n_lights')}",
              "raw size (float32 RGB)": _human_bytes(data.get("raw_bytes"))}], caption="BTF")


def _evaluation_section(r: HtmlReport, out: Path, ev: dict[str, Any], fit: dict[str, Any], config) -> None:
    """Held-out metrics (all, grazing, others), the training state, the GT | model | FLIP images, the first
    pairs' numbers and the model's size against the raw BTF."""
    r.section("Representation: ground truth vs model on held-out pairs",
              "Pairs the training never saw (up to 48, evenly spaced over the held-out set; `dynbtf eval` "
              "scores all of them). Each image: ground truth | Triple Plane | FLIP error map.")
    mean = ev.get("mean", {})
    groups = ev.get("by_angle") or {}
    r.table([{"pairs": name, "count": g.get("n"), "PSNR (dB, per-image peak)": g.get("psnr"),
              "PSNR (dB, fixed peak 1)": g.get("psnr_fixed1"), "DSSIM": g.get("dssim"), "FLIP": g.get("flip")}
             for name, g in [("all", {"n": ev.get("n_pairs"), **mean}),
                             ("grazing (view or light > 60 deg)", groups.get("grazing", {})),
                             ("others", groups.get("others", {}))] if g.get("n")],
            caption="Held-out metrics (means). PSNR per-image peak: against each reference image's maximum, "
                    "comparable across materials; fixed peak 1: the older form, higher on dark materials")
    r.table([{"training": _training_state(fit, config),
              "training time (s)": fit.get("seconds_training", fit.get("seconds")),
              "recipe": fit.get("recipe", "")}],
            caption=f"Training. The fit's own progress line shows the held-out PSNR on "
                    f"{fit.get('monitor_pairs', 16)} of the held-out pairs (a quick monitor); the tables above "
                    f"score {ev.get('n_pairs')} held-out pairs, so the two numbers differ slightly.")
    r.images([(out / x["path"], _pair_caption(x.get("row") or {})) for x in ev.get("images", [])], width=460)
    rows = ev.get("rows", [])
    if rows:
        r.table(rows[:12], columns=["view_index", "light_index", "theta_view", "phi_view", "theta_light",
                                    "phi_light", "grazing", "psnr", "psnr_fixed1", "dssim", "flip"],
                caption=f"Per pair (first {min(12, len(rows))} of {len(rows)})")
    size = ev.get("size", {})
    if size:
        r.table([{"model": _human_bytes(size.get("model_bytes")),
                  "parameters": f"{size.get('n_parameters', 0):,}",
                  "raw BTF (float32 RGB)": _human_bytes(size.get("raw_btf_bytes")),
                  "compression": f"{size['compression_ratio']:.3g} : 1" if "compression_ratio" in size else ""}],
                caption="Model size vs raw BTF size")


def _pair_caption(row: dict[str, Any]) -> str:
    """Caption of a held-out example: its directions (degrees), PSNR (dB) and FLIP; ``""`` without a row."""
    if not row:
        return ""
    return (f"view ({row.get('theta_view', 0):.0f}, {row.get('phi_view', 0):.0f}) deg, light "
            f"({row.get('theta_light', 0):.0f}, {row.get('phi_light', 0):.0f}) deg: "
            f"PSNR {row.get('psnr', float('nan')):.1f} dB, FLIP {row.get('flip', float('nan')):.3f}")


def _features_section(r: HtmlReport, out: Path, feats: list[str]) -> None:
    """The feature-plane pictures (nothing when there are none)."""
    if not feats:
        return
    r.section("Feature planes", "Positional plane f_U (first three principal components as RGB), and the "
              "half-vector / difference-vector planes f_H, f_D (rows: theta from 0 at the top; columns: phi).")
    r.images([(out / p, _feature_caption(Path(p).stem)) for p in feats], width=256, pixelated=True)


def _synthesis_section(r: HtmlReport, out: Path, syn: dict[str, Any]) -> None:
    """Dynamic synthesis: per method (in the order the demo ran them) its panels at each scale, point and
    footprint queries; then the quality and timing tables."""
    methods = list(syn.get("grid") or syn.get("previews") or {})  # in the order the demo ran them
    r.section("Dynamic synthesis at 1x, 8x, 25x and 45x the exemplar's area",
              f"BTF values (excluding cos(theta_light)), top view, light at theta {syn['light'][0]:g} deg, "
              f"phi {syn['light'][1]:g} deg; "
              f"each image spans N x N exemplar repeats at {syn.get('resolution')} x {syn.get('resolution')} pixels, one query per pixel "
              "(at 25x and 45x several texels fall in a pixel and the one query shows one of them: the "
              "fine noise there is aliasing of point samples, not the material's look from afar; large-scale "
              "repetition -- or its absence -- is what these panels show). At 25x and 45x the same views follow "
              "as footprint queries (SynthesizedBTF.eval(..., footprint=pixel size)), unfiltered | filtered: the "
              "filtered panel shows the material's appearance from afar at the same one query per pixel. "
              "Every texel is computed on demand from its uv: nothing is pre-generated.")
    for m in methods:
        row = syn["grid"].get(m, {})
        r.section(METHOD_TITLES.get(m, m), level=3)
        r.images([(out / row[str(s)], f"{s}x") for s in syn.get("scales", []) if str(s) in row], width=300)
        filtered = syn.get("filtered", {}).get(m, {})
        if filtered:
            pairs = [(out / p, f"{s}x, {kind}") for s in syn.get("scales", []) if str(s) in filtered
                     for p, kind in ((row[str(s)], "unfiltered (point query)"),
                                     (filtered[str(s)], "filtered (footprint query)"))]
            r.images(pairs, width=300)
    g = syn.get("guided")
    if g:
        scale = str(g["scale"])
        r.section("Guided by a painted target", level=3)
        r.paragraph(f"The same material, its texels in {g['classes']} classes by k-means on their decoded "
                    "appearance (class 0 the darker), and a target painted over the surface: each point draws only "
                    "from content of the class its target asks for (dark where the target is dark). "
                    f"{scale}x the exemplar's area; hist beside it for comparison (dynbtf.guided_btf, dynbtf synth "
                    "--target).")
        panels = [(out / g["target"], "target"), (out / g["image"], f"guided, {scale}x")]
        hist = syn.get("grid", {}).get("hist", {}).get(scale)
        if hist:
            panels.insert(1, (out / hist, f"hist, {scale}x"))
        r.images(panels, width=300)
    _synthesis_tables(r, syn, methods)


def _synthesis_tables(r: HtmlReport, syn: dict[str, Any], methods: list[str]) -> None:
    """The synthesis quality measures and the seconds per synthesized image (and first, compiling, call)."""
    q = syn.get("quality", [])
    if q:
        r.table(q, caption="Synthesis quality (dynbtf.synthesis.quality), measured on an area of N x N "
                "exemplar repeats: W1/std, the Wasserstein distance between the synthesized and the exemplar's "
                "histograms over the exemplar's spread (lower is better); std ratio, synthesized over exemplar "
                "spread (1: contrast kept); repetition score, the autocorrelation peak at the exemplar's period "
                "(tiling ~1); verbatim fraction, the share of synthesized texels within 1% of the channel spread "
                "of some exemplar texel (copies: tiling ~1; blending creates new values except near lattice "
                "vertices)")
    t = syn.get("timings", {})
    if t:
        scales = syn.get("scales", [])
        compiled = syn.get("compile_seconds", {})
        r.table([{"method": m, **{f"{sc}x": t.get(f"{m}@{sc}x") for sc in scales},
                  "first call (compiles kernels)": compiled.get(m)} for m in methods],
                columns=["method", *[f"{sc}x" for sc in scales], "first call (compiles kernels)"],
                caption=f"Seconds per {syn.get('resolution')} x {syn.get('resolution')} px synthesized image "
                        "(kernels already compiled), and the first call of each method, which compiles its "
                        "kernels once per machine (cached on disk)")


def _structured_section(r: HtmlReport, out: Path, st: dict[str, Any]) -> None:
    """The structured material synthesized by tile, hist and auto at 8x and 25x, and its structure measures."""
    if not st.get("images"):
        return
    r.section("A structured material: tile | hist | auto",
              f"Simulated {st['material']} ({st['size']} x {st['size']} texels, a brief fit), synthesized far from "
              f"the origin (uv 1e6) at 8x and 25x the exemplar's area, top view, light at theta "
              f"{st['light'][0]:g} deg, phi {st['light'][1]:g} deg. Tiling keeps the structure but repeats; "
              "histogram-preserving blending never repeats but blends unrelated copies into ghosted joints; "
              "auto measures the exemplar's structure and picks lattice-aligned cell quilting, which copies "
              "whole cells at offsets along the material's own lattice and joins them along minimum-error cuts. "
              + (f"Its choice: \"{st['choice']}\"." if st.get("choice") else ""))
    columns = [m for m in ("tile", "hist", "auto") if m in st["images"]]
    for scale in ("8", "25"):
        r.images([(out / st["images"][m][scale], f"{scale}x, {METHOD_TITLES.get(m, m)}") for m in columns
                  if scale in st["images"][m]], width=300)
    if st.get("quality"):
        r.table(st["quality"], caption="Structure measures (dynbtf.synthesis.coherence), one pixel per texel at "
                "view (0, 0) and light (40, 30): coherence, the best match of a 16 x 16 patch anywhere in the "
                "exemplar over the typical difference of two exemplar patches (0: every patch exists in the "
                "exemplar); identity with tiling, the share of patches whose best match is where tiling would "
                "copy from (1 for tiling)")
    lay = st.get("layered")
    if lay:
        r.section("Two materials on one surface: a layered material", level=3)
        r.paragraph(f"The demo's material ({lay['methods'][0]}) and the structured one ({lay['methods'][1]}) under a "
                    f"mask of value noise ({lay['noise'][0]:g} uv units per cell, contrast {lay['noise'][1]:g}), at 8 "
                    "repeats per uv unit. Within "
                    f"{lay['width']:g} uv units of the mask's contour the material that stands higher there shows, "
                    "so the boundary follows the materials' own structure instead of cross-fading them "
                    "(dynbtf.LayeredBTF, dynbtf synth --layer; docs/layered.md).")
        r.images([(out / lay["mask"], "mask"), (out / lay["image"], "layered, 8x"),
                  (out / lay["shown"], "which material shows (light: the structured one)")], width=300)


def _renders_section(r: HtmlReport, out: Path, ren: list[dict[str, Any]]) -> None:
    """The Mitsuba renders and their settings and timings (nothing without renders)."""
    if not ren:
        return
    r.section("Renders (Mitsuba 3, dynbtf BSDF plugin)",
              "Every shading point is answered by dynbtf's own query (lattice, hash, blending, inverse transform "
              "and decoder MLP), the same code as the synthesized images above. Each camera "
              "sample answers for its footprint on the surface (the camera's ray cone; the plugin's "
              "'filtered' parameter): distant ground shows the material's filtered look, not sparkling "
              "point samples.")
    r.images([(out / x["path"], f"{x['scene']} / {x['lighting']} / {x['method']}") for x in ren], width=300)
    r.table([{"scene": x["scene"], "lighting": x["lighting"], "method": x["method"],
              "scale (repeats)": x["scale"], "size (px)": x["size"], "spp": x["spp"], "seconds": x["seconds"],
              "compile seconds": x["compile_seconds"], "variant": x["variant"]} for x in ren],
            caption="Render settings and timings")


def _viewer_section(r: HtmlReport, out: Path, viewer: dict[str, Any] | None) -> None:
    """The link to the WebGL2 viewer and the size of what it loads (nothing without a viewer)."""
    if not viewer:
        return
    r.section("Real-time viewer (WebGL2)")
    r.link("The same synthesized material, evaluated per pixel on the GPU in your browser (no server, no "
           "download): ", out / viewer["index"], "open the viewer",
           f". Plane or sphere, orbit camera, light direction and intensity, synthesis method and scale. "
           f"Its {viewer['precision']} textures, tables and decoder weights for histogram-preserving blending take "
           f"{_human_bytes(viewer['hist_bytes'])} (the model file: {_human_bytes(viewer['model_bytes'])}); "
           "`dynbtf export` writes the same for your own engine (docs/realtime.md).")
    if viewer.get("layered_index"):
        r.link("The layered material in the same way: ", out / viewer["layered_index"], "open the layered viewer",
               ". Tick \"Paint the mask\" and drag on the shape to move the boundary; save the mask as a PNG for "
               "dynbtf synth --layer ... --mask (dynbtf export --layer).")


def _timings_section(r: HtmlReport, out: Path, config, results: dict[str, Any]) -> None:
    """Wall time per stage, and the command that reproduces the run (reruns skip finished stages)."""
    r.section("Timings")
    r.table([{"stage": k, "seconds": v.get("seconds")} for k, v in results.items()],
            caption="Wall time per stage (of the run that computed it)")
    command = [sys.executable, "-m", "dynbtf", "demo", "-o", str(out)]  # works wherever dynbtf is installed
    command += ["--btf", str(config.btf)] if config.btf else ["--material", config.material, "--size", str(config.size)]
    command += ["--quick"] if config.quick else []
    r.paragraph(f"Reproduce (reruns skip finished stages): {shlex.join(command)}", note=True)
