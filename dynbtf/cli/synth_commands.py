"""``dynbtf synth``: a flat sample of the synthesized BTF (Figs. 5-6 style) and the synthesis quality report.

Quilting is not dynamic: its plane is generated and held in memory before the
first query. Its size (``--quilt-repeats``, default ``ceil(--scale)`` so that the
image shows no wrap-around) is bounded by :data:`QUILT_MAX_BYTES` of stored
float32 plane; generating it takes several times that memory at its peak (float64
work arrays), and its time grows with the square of the repeats.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from . import guidance_options
from ..errors import InputError
from .app import app

#: Largest quilted plane ``dynbtf synth`` generates, bytes of stored float32 (512 MiB: 22 x 22
#: repeats of a 128^2 x 16 plane, 7 x 7 of a 400^2 x 16 one; peak memory while quilting ~9x that).
QUILT_MAX_BYTES = 512 * 2**20
#: Working memory of ``SynthesizedBTF.image`` per pixel, bytes (float64 sums, uv grids, the decoded
#: chunk; measured ~92 bytes per pixel at 1024^2 to 2048^2, hist, 128^2 x 16 plane).
BYTES_PER_PIXEL = 100
#: Most samples per pixel axis (--spp; spp x spp samples per pixel).
MAX_SPP = 64
#: Most queries of one image (pixels x spp^2): 2**32, a bound on one command's run time (the query rate is
#: measured by ``benchmarks/bench_synthesis_eval.py``).
MAX_QUERIES = 2**32


def check_image_request(resolution: int, spp: int, memory_mb: float | None) -> None:
    """--resolution, --spp and the estimated memory of ``SynthesizedBTF.image`` within limits, else InputError."""
    from ..limits import check_count, check_memory

    if resolution < 1:
        raise InputError(f"--resolution: expected a positive number of pixels, got {resolution}")
    if spp < 1:
        raise InputError(f"--spp: expected a positive number of samples per pixel axis, got {spp}")
    check_count(spp, "--spp", high=MAX_SPP, unit="samples per pixel axis",
                why=f"--spp N takes N x N samples per pixel; {MAX_SPP} x {MAX_SPP} already averages 4096")
    check_memory(float(resolution) ** 2 * BYTES_PER_PIXEL,
                 f"--resolution {resolution} ({float(resolution) ** 2:.3g} pixels, ~{BYTES_PER_PIXEL} bytes each)",
                 memory_mb, fix="expected a smaller --resolution")
    queries = float(resolution) ** 2 * spp * spp
    if queries > MAX_QUERIES:
        raise InputError(f"--resolution {resolution} with --spp {spp} is {queries:.3g} queries ({spp} x {spp} per "
                         f"pixel), above the limit of {MAX_QUERIES:.3g} (2**32, about an hour); expected a smaller "
                         "--resolution or --spp")


def _pair(text: str, name: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        raise InputError(f"--{name}: expected two comma-separated numbers like '30,90', got {text!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise InputError(f"--{name}: expected finite numbers, got {text!r}")
    return a, b


def _quilt_repeats(quilt_repeats: int | None, scale: float, plane_shape) -> int:
    """The quilt's size in exemplar repeats per axis: ``quilt_repeats`` or ``ceil(scale)``, within the memory limit."""
    from ..synthesis.quilting import quilted_storage_bytes

    h, w, c = (int(x) for x in plane_shape)
    repeats = math.ceil(scale) if quilt_repeats is None else int(quilt_repeats)
    if repeats < 1:
        raise InputError(f"--quilt-repeats: expected a positive number of exemplar repeats, got {repeats}")
    needed = quilted_storage_bytes(h, w, c, repeats)
    if needed > QUILT_MAX_BYTES:
        largest = math.isqrt(QUILT_MAX_BYTES // (h * w * c * 4))
        source = "--quilt-repeats" if quilt_repeats is not None else f"--quilt-repeats (default ceil(--scale) = {repeats})"
        raise InputError(f"{source}: a {repeats} x {repeats}-repeat quilt of the {h}x{w}x{c} plane needs "
                         f"{needed / 1e6:.4g} MB (float32; ~9x that while quilting), above the limit of "
                         f"{QUILT_MAX_BYTES / 1e6:.4g} MB; expected --quilt-repeats {largest} or less (the image then "
                         f"repeats with the quilt's period)")
    return repeats


@app.command()
def synth(
    model: Path = typer.Argument(..., help="dynbtf model file (a fitted representation with a positional plane), or "
                                           "a compiled material (`dynbtf compile`: its method and seed, nothing "
                                           "fitted or built again)."),
    output: Optional[Path] = typer.Option(None, "-o", "--output",
                                          help="Output image: .png (sRGB) or .exr (linear HDR)."),
    method: str = typer.Option("auto", help="Synthesis method: tile, linear, hist, hex, quilt, struct, or auto (struct "
                                            "for structured exemplars, hist otherwise; the choice is printed)."),
    scale: float = typer.Option(8.0, help="Exemplar repeats across the image (the paper's 8x, 25x, 45x)."),
    view: str = typer.Option("0,0", help="View direction THETA,PHI in degrees (theta 0..90)."),
    light: str = typer.Option("30,0", help="Light direction THETA,PHI in degrees (theta 0..90)."),
    resolution: int = typer.Option(1024, help="Image width and height in pixels."),
    seed: Optional[int] = typer.Option(None, help="Synthesis seed (default 0; a compiled material's own)."),
    device: str = typer.Option("auto", help="auto (CUDA if available), cpu, cuda:0, ...: where the model is "
                                            "decoded and synthesized (the numba fast paths are the CPU's)."),
    spp: int = typer.Option(1, help="Supersampling: spp x spp samples per pixel (box filter) against aliasing "
                                    "when a pixel covers many texels."),
    filtered: bool = typer.Option(False, "--filtered", help="Footprint queries: each sample answers for its share "
                                                            "of the pixel (the material's filtered look from afar "
                                                            "at one sample per pixel, instead of aliased texels)."),
    center: str = typer.Option("0.5,0.5", help="uv of the image centre (the image spans one uv unit), "
                                               "e.g. 1e6,1e6 to look far from the origin; |uv| * scale must stay "
                                               "below 2**52 (~4.5e15) exemplar repeats."),
    exposure: float = typer.Option(1.0, help="Multiplier (positive) applied before sRGB encoding (PNG only)."),
    cosine: bool = typer.Option(False, "--cosine", help="Multiply by cos(theta_light): the radiance under a "
                                                        "directional light of unit irradiance at normal incidence "
                                                        "(default: the BTF value itself, which excludes it)."),
    quilt_repeats: Optional[int] = typer.Option(None, "--quilt-repeats",
                                                help="Size of the quilted plane (--method quilt, or quilt in "
                                                     "--report-methods), exemplar repeats per axis; default "
                                                     "ceil(--scale), so the image does not wrap. The plane is "
                                                     f"generated up front and limited to {QUILT_MAX_BYTES // 2**20} "
                                                     "MiB (float32); its storage is printed."),
    gamma: Optional[float] = typer.Option(None, "--gamma", help="Blending exponent of hist (weights b^gamma; default "
                                                                 "7; 1 = Heitz & Neyret's smooth blending, whose decoded "
                                                                 "colours are over-contrasted on fitted models; see "
                                                                 "docs/synthesis.md). Applies to hist only (and to auto when it chooses hist)."),
    report: bool = typer.Option(False, "--report", help="Also measure synthesis quality (W1/std of features and "
                                                        "RGB, repetition, verbatim copies, patch coherence and "
                                                        "identity with tiling) and print a table."),
    report_methods: str = typer.Option("tile,hist,hex,struct", help="Methods compared by --report."),
    report_json: Optional[Path] = typer.Option(None, help="Where --report saves its JSON "
                                                          "(default: next to -o, or synthesis-quality.json)."),
    repeats: int = typer.Option(8, help="Side of the area measured by --report, in exemplar repeats; reduced to "
                                        "fit 1024 texels per side (8 repeats of a 128-texel exemplar; the report "
                                        "prints the measured area)."),
    layer: Optional[Path] = typer.Option(None, "--layer", help="A second material (model file or .dbtfc) layered "
                                         "with MODEL: MODEL where --mask is below one half, this one above "
                                         "(same method and scale; the boundary follows both materials' heights)."),
    mask: str = typer.Option("noise", "--mask", help="With --layer: an image file (PNG/JPEG grey levels or EXR "
                             "values in [0, 1]) or noise:SCALE[,CONTRAST[,SEED]] (value noise, cells of SCALE uv "
                             "units)."),
    mask_size: float = typer.Option(1.0, "--mask-size", help="uv units a mask image covers."),
    mask_wrap: str = typer.Option("repeat", "--mask-wrap", help="A mask image repeats (repeat) or extends its "
                                  "edges (clamp)."),
    width: float = typer.Option(0.05, "--width", help="With --layer: half-width (uv units) of the band around "
                                "the mask's contour where the materials' heights decide."),
    target: Optional[Path] = typer.Option(None, "--target", help="Guided synthesis (hist, hex or struct steered by "
                                          "labels): an image painted over the surface (PNG/JPEG grey levels, or EXR values in [0, 1]), "
                                          "cut into --classes equal bins; a point in bin k shows the material's "
                                          "class k (k-means on its decoded appearance, 0 the darkest)."),
    classes: int = guidance_options.CLASSES,
    target_size: float = typer.Option(1.0, "--target-size", help="uv units the --target image covers."),
    target_wrap: str = guidance_options.TARGET_WRAP,
    softness: float = guidance_options.SOFTNESS,
    cells: Optional[int] = guidance_options.CELLS,
    brightness: float = guidance_options.BRIGHTNESS,
    tint: float = guidance_options.TINT,
    rotation: bool = guidance_options.ROTATION,
    scale_jitter: float = guidance_options.SCALE_JITTER,
    memory_mb: Optional[float] = typer.Option(None, "--memory-mb", help="Limit (MB) of the image's estimated "
                                                                        f"working memory (~{BYTES_PER_PIXEL} bytes "
                                                                        "per pixel); default half of this machine's "
                                                                        "memory. Larger images are refused up front."),
) -> None:
    """Synthesize a flat sample of the BTF at any scale and position; optionally report quality.

    The image shows the uv square of side 1 centred at --center under one view
    and one directional light; pixel values are BTF values (linear RGB, excluding
    cos(theta_light), as everywhere in dynbtf; --cosine multiplies it in).

    Limits, checked before the model loads: |uv| * --scale below 2**52 repeats, --spp at most 64
    per axis, --resolution^2 x --spp^2 at most 2**32 queries, the estimated memory within --memory-mb.
    """
    from ..device import resolve_device
    from ..limits import check_scale
    from ..material import open_model_file
    from ..synthesis.base import check_uv
    from ..synthesis.registry import variation_flag
    from .arguments import check_exposure, parse_theta_phi

    _check_outputs(output, report, report_json)
    where = resolve_device(device)
    if output is not None:
        check_image_request(resolution, spp, memory_mb)
    scale = check_scale(scale, "--scale", where="the library's float64 uv")
    view_dir, light_dir = parse_theta_phi(view, "view"), parse_theta_phi(light, "light")
    check_exposure(exposure)
    cu, cv = _pair(center, "center")
    check_uv([[cu - 0.5, cv - 0.5], [cu + 0.5, cv + 0.5]], "--center", scale=scale)  # before any work
    the_mask = _layer_mask(layer, mask, mask_size, mask_wrap, width, report, output)  # before any work
    guidance = _guidance(target, method, layer, report, output, target_size, target_wrap, classes, softness, cells)
    if cells is not None and method != "struct":
        raise InputError(f"--cells: sets struct's cells; give it with --method struct, not {method!r}")
    variation = _variation({"brightness": brightness, "tint": tint, "rotation": rotation,
                            "scale_jitter": scale_jitter}, method, guidance, layer)
    if variation.get("scale_jitter"):
        from ..synthesized import warn_without_subtexel_term

        warn_without_subtexel_term(model)
    rep, material = open_model_file(model, device=where)
    if variation and material is not None:
        raise InputError(f"{', '.join(variation_flag(name) for name in variation)}: {model} is a compiled "
                         "material, which fixes its method's parameters; compile it with them, or give the model "
                         "file (.dbtfm)")
    if guidance is not None:
        if material is not None:
            raise InputError(f"--target: {model} is a compiled material, which fixes its method; guide the model "
                             "file (.dbtfm) it was compiled from")
        btf = guidance.build(rep, scale=scale, seed=0 if seed is None else seed,
                             **({"gamma": gamma} if gamma is not None and guidance.method == "hist" else {}))
        _write_image(btf, output, view_dir, light_dir, (cu, cv), resolution=resolution, spp=spp, filtered=False,
                     cosine=cosine, exposure=exposure)
        typer.echo(f"wrote {output} ({resolution}x{resolution}, guided by {target}, {classes} classes, {scale:g}x, "
                   f"centre {cu:g},{cv:g})")
        return
    methods = [m.strip() for m in report_methods.split(",") if m.strip()] if report else []
    quilt_size = _quilt_repeats(quilt_repeats, scale, tuple(rep.positional_plane().shape)) \
        if (output is not None and method == "quilt") or "quilt" in methods else None

    def build(name: str):
        if material is not None and name in ("auto", material.method):  # the material as compiled
            return _build(material, material.method, scale=scale, seed=seed, quilt_size=None, gamma=gamma,
                          footprints=filtered)
        return _build(rep, name, scale=scale, seed=0 if seed is None else seed, quilt_size=quilt_size, gamma=gamma,
                      cells=cells, footprints=filtered, variation=variation if name == method else {})

    if layer is not None:
        btf = _layered(build(method), layer, method, where, scale=scale, seed=seed, gamma=gamma, mask=the_mask,
                       width=width, footprints=filtered)
        _write_image(btf, output, view_dir, light_dir, (cu, cv), resolution=resolution, spp=spp, filtered=filtered,
                     cosine=cosine, exposure=exposure)
        typer.echo(f"wrote {output} ({resolution}x{resolution}, {model} | {layer}, {scale:g}x, centre {cu:g},{cv:g})")
        return
    if output is not None:
        btf = build(method)
        _write_image(btf, output, view_dir, light_dir, (cu, cv), resolution=resolution, spp=spp, filtered=filtered,
                     cosine=cosine, exposure=exposure)
        typer.echo(f"wrote {output} ({resolution}x{resolution}, {btf.synthesizer.name}, {scale:g}x, centre {cu:g},{cv:g})")
    if report:
        _write_report(build, methods, repeats, _report_path(output, report_json))



def _layer_mask(layer: Path | None, mask: str, mask_size: float, mask_wrap: str, width: float, report: bool, output):
    """``--layer``'s mask (None without ``--layer``), its options checked."""
    from ..errors import positive_number
    from ..layered import mask_from_spec

    if layer is None:
        return None
    if report or output is None:
        raise InputError("--layer: writes an image (-o); --report measures one material at a time")
    positive_number("--width", width, "uv units")
    return mask_from_spec(mask, size=mask_size, wrap=mask_wrap)


def _guidance(target: Path | None, method: str, layer, report: bool, output, size: float, wrap: str, classes: int,
              softness: float, cells: int | None):
    """``--target`` and its companions checked and the image read (None without ``--target``), before the model
    loads (:func:`dynbtf.guided.guidance_options`)."""
    if target is None:
        return None
    if report or output is None or layer is not None:
        raise InputError("--target: writes one guided image (-o), without --report or --layer")
    from ..guided import guidance_options

    return guidance_options(target, method=method, classes=classes, target_size=size, target_wrap=wrap,
                            softness=softness, cells=cells)


def _layered(first, layer: Path, method: str, where, *, scale: float, seed, gamma, mask, width: float,
             footprints: bool = False):
    """``--layer``: the layered material of ``first`` and the material in ``layer`` under ``mask``."""
    from ..layered import LayeredBTF
    from ..material import open_model_file

    rep, material = open_model_file(layer, device=where)
    source = material if material is not None and method in ("auto", material.method) else rep
    second = _build(source, material.method if source is material else method, scale=scale,
                    seed=seed if source is not material else None, quilt_size=None, gamma=gamma, footprints=footprints)
    return LayeredBTF([first, second], mask, width=width)


def _report_path(output: Path | None, report_json: Path | None) -> Path:
    """Where --report saves its JSON: --report-json, else next to -o, else synthesis-quality.json."""
    return report_json or (output.with_suffix(".quality.json") if output is not None
                           else Path("synthesis-quality.json"))


def _check_outputs(output: Path | None, report: bool, report_json: Path | None) -> None:
    """Something to do, and every output (the image, the report's JSON) writable, before any work."""
    from ..io import check_image_path, check_writable

    if output is None and not report:
        raise InputError("nothing to do: give -o/--output for an image and/or --report")
    if output is not None:
        check_image_path(output)
        check_writable(output, "-o/--output")
    if report:
        check_writable(_report_path(output, report_json), "--report-json")


def _variation(values: dict[str, float], method: str, guidance, layer) -> dict[str, float]:
    """The variation parameters that were given (``{}``: none; struct's ``brightness``, ``tint``; lattice
    blending's ``rotation``, ``scale_jitter``), checked: one-line errors, naming the methods that take each."""
    from ..synthesis.registry import VARIATIONS, given_variations, methods_taking, takes_parameter, variation_flag

    given = given_variations(values, "--")
    for name in given:
        if not takes_parameter(method, name) or guidance is not None or layer is not None:
            having = methods_taking(name)
            whose = f"{having[0]}'s" if len(having) == 1 else f"for {', '.join(having)}"
            raise InputError(f"{variation_flag(name)}: {VARIATIONS[name]} is {whose}; give it with --method "
                             f"{having[0]} (without --target or --layer), not {method!r}")
    return given


def _build(rep, name: str, *, scale: float, seed: int | None, quilt_size: int | None, gamma: float | None,
           cells: int | None = None, footprints: bool = False, variation: dict | None = None):
    """The :class:`~dynbtf.infinite_btf.SynthesizedBTF` of method ``name`` of ``rep`` (a representation, or a
    compiled material of method ``name``, whose seed ``seed`` must be or None), with the footprint decoders if
    ``footprints`` (``--filtered``); prints auto's choice and the quilt's size."""
    from ..material import CompiledMaterial
    from ..synthesized import synthesized_btf

    compiled = isinstance(rep, CompiledMaterial)
    params = {"repeats": float(quilt_size), "progress": True} if name == "quilt" and not compiled else {}
    if name in ("hist", "auto") and gamma is not None:
        params["gamma"] = gamma  # auto: used if it chooses hist
    if name == "struct" and cells is not None and not compiled:
        params["cells"] = int(cells)
    if not compiled:
        params.update(variation or {})
    btf = synthesized_btf(rep, name, scale=scale, seed=(rep.seed if compiled else 0) if seed is None else seed,
                          footprints=footprints, **params)
    rep = btf.model
    if btf.synthesizer.choice is not None:
        typer.echo(btf.synthesizer.choice.line)
    for line in btf.synthesizer.advice():
        typer.echo(line)
    if name == "quilt" and quilt_size is not None:
        size = btf.synthesizer.size
        typer.echo(f"quilt: {quilt_size} x {quilt_size} exemplar repeats = {size[0]} x {size[1]} texels, "
                   f"storage {rep.storage_bytes() / 1e6:.3g} MB (model) + "
                   f"{btf.synthesizer.storage_bytes() / 1e6:.3g} MB (quilted plane, float32)")
    return btf


def _write_image(btf, output: Path, view_dir, light_dir, center: tuple[float, float], *, resolution: int, spp: int,
                 filtered: bool, cosine: bool, exposure: float) -> None:
    """Render the uv square of side 1 centred at ``center`` under one view and light, and save it."""
    from ..conventions import spherical_to_direction
    from ..io import save_image

    cu, cv = center
    img = btf.image(view=view_dir, light=light_dir, uv_rect=(cu - 0.5, cv - 0.5, cu + 0.5, cv + 0.5),
                    resolution=resolution, spp=spp, filtered=filtered)
    if cosine:
        img = img * max(float(spherical_to_direction(light_dir[0], light_dir[1])[2]), 0.0)
    save_image(output, img, exposure=exposure)


def _write_report(build, methods: list[str], repeats: int, path: Path) -> None:
    """Build and measure each method in turn (one at a time in memory), print the table and save its JSON to ``path``."""
    from ..synthesis.quality import format_report, quality_report, save_report

    reports = [quality_report(build(name), repeats=repeats) for name in methods]
    typer.echo(format_report(reports))
    save_report(reports, path)
    typer.echo(f"wrote {path}")
