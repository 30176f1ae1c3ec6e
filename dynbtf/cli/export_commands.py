"""``dynbtf export``: a fitted model for real-time renderers (``--format web``: GLSL ES 3.00 + a WebGL2 viewer)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from . import guidance_options
from ..errors import InputError
from .app import app

#: Export formats (``web`` is the only one so far).
FORMATS = ("web",)


@app.command("export")
def export_command(
    model: Path = typer.Argument(..., help="dynbtf model file of kind triple or triple-parallax (`dynbtf fit`), "
                                           "or a compiled material of one (`dynbtf compile`)."),
    output: Path = typer.Option(..., "-o", "--output", help="Directory to write (created; an earlier export's "
                                                              "files are replaced)."),
    export_format: str = typer.Option("web", "--format", help="web: textures, decoder weights, a GLSL ES 3.00 "
                                                                "shader and a WebGL2 viewer page (index.html)."),
    precision: str = typer.Option("fp16", help="Texture storage: fp16 (half floats), u8 (8 bits per channel with a "
                                               "per-channel scale and bias) or fp32 (exact)."),
    method: Optional[List[str]] = typer.Option(
        None, "--method", metavar="METHOD",
        help="Synthesis method(s) to export: auto, struct, tile, linear, hist, hex (repeat the option; default: auto, "
             "hist, tile; the first is the viewer's default). auto is the model's choice (struct for a structured "
             "positional plane, else hist), printed and exported under the chosen name."),
    seed: int = typer.Option(0, help="Synthesis seed (the choices of SynthesizedBTF with this seed)."),
    scale: float = typer.Option(8.0, help="The viewer's initial exemplar repeats per unit of the surface's uv "
                                          "(positive, below 4096: the shader's float32 local uv spans at most "
                                          "2**12 repeats)."),
    viewer: bool = typer.Option(True, "--viewer/--no-viewer", help="Also write the viewer page (index.html, viewer.js "
                                                                   "and .js copies of the binary files)."),
    layer: Optional[Path] = typer.Option(None, "--layer", help="A second material (model file or .dbtfc) layered "
                                         "with MODEL: MODEL where --mask is below one half, this one above (a "
                                         "layered export: the viewer paints the mask; docs/layered.md)."),
    mask: str = typer.Option("noise", "--mask", help="With --layer: an image file (PNG/JPEG grey levels or EXR "
                             "values in [0, 1]) or noise:SCALE[,CONTRAST[,SEED]] (value noise)."),
    mask_size: float = typer.Option(1.0, "--mask-size", help="uv units a mask image covers."),
    mask_wrap: str = typer.Option("repeat", "--mask-wrap", help="A mask image repeats (repeat) or extends its "
                                  "edges (clamp)."),
    width: float = typer.Option(0.05, "--width", help="With --layer: half-width (uv units) of the band around the "
                                "mask's contour where the materials' heights decide."),
    target: Optional[Path] = typer.Option(None, "--target", help="Guided synthesis (hist, hex or struct steered by "
                                          "labels; auto: hist): an image painted over the surface's uv (PNG/JPEG grey "
                                          "levels, or EXR values in [0, 1]), cut into --classes equal bins; a point "
                                          "in bin k shows the material's class k (k-means on its decoded "
                                          "appearance, 0 the darkest). The shader runs the guided method."),
    classes: int = guidance_options.CLASSES,
    target_size: float = typer.Option(1.0, "--target-size", help="uv units the --target image covers (at --scale "
                                      "repeats per uv unit: the target is laid over the exemplar repeats)."),
    target_wrap: str = guidance_options.TARGET_WRAP,
    softness: float = guidance_options.SOFTNESS,
    cells: Optional[int] = guidance_options.CELLS,
    rotation: bool = typer.Option(False, "--rotation", help="Turn the exported hist, hex and linear materials' "
                                  "samples by random quarter turns (drawn from --seed), the view and light with "
                                  "them (auto and the other methods as they are)."),
    scale_jitter: float = typer.Option(0.0, "--scale-jitter", help="Magnify the exported hist, hex and linear "
                                       "materials' samples by random factors between 1/(1 + J) and 1 + J (drawn from "
                                       "--seed), in [0, 1]; 0: off."),
    brightness: float = typer.Option(0.0, "--brightness", help="struct (give it with --method struct): per-element "
                                     "variation, the standard deviation of each element's log-brightness (drawn "
                                     "from --seed; joints none), in [0, 1]; 0: off."),
    tint: float = typer.Option(0.0, "--tint", help="struct (give it with --method struct): the standard deviation "
                               "of each element's colour tint, in [0, 1]; 0: off."),
) -> None:
    """Export a synthesized BTF for real-time rendering: GPU textures, decoder weights and a shader (docs/realtime.md).

    Example: dynbtf export leather.dbtfm -o leather-web --precision u8, then open leather-web/index.html
    (methods auto, hist, tile: auto prints its choice, struct for a structured material, else hist).
    With --layer: both materials, their mask and the boundary rule in one viewer (each layer's --method, default
    auto; --scale is each layer's repeats per uv unit), e.g. dynbtf export new.dbtfm --layer worn.dbtfm --mask
    noise:0.5,3 -o floor-web
    With --target: one guided method whose content follows a painted image, e.g. dynbtf export leather.dbtfm
    --target worn.png --target-size 2 -o leather-worn-web (or --method struct --cells 8 for bricks)
    """
    from ..export.web.exporter import DEFAULT_METHODS, WEB_PRECISIONS, export_web
    from ..export.web.shader import LOCAL_REPEATS
    from ..io import check_writable
    from ..limits import check_scale
    from ..material import is_compiled_material
    from ..representations.model_file import read_model_metadata

    check_writable(output, "-o/--output", directory=True)
    # the viewer's meshes have uv in [0, 1]: uv x scale is the shader's float32 local uv
    check_scale(scale, "--scale", float32=True, limit=LOCAL_REPEATS,
                where="the shader's float32 local uv (dynbtf.export.web.shader.LOCAL_REPEATS)")
    if export_format not in FORMATS:
        raise InputError(f"--format: expected one of {list(FORMATS)}, got {export_format!r}")
    if precision not in WEB_PRECISIONS:
        raise InputError(f"--precision: expected one of {sorted(WEB_PRECISIONS)}, got {precision!r}")
    for path in (model, layer):
        if path is not None and not is_compiled_material(path):  # (a compiled material is read, and checked, later)
            read_model_metadata(path)  # a missing or damaged file is named before anything is written
    if cells is not None and ("struct" not in (method or []) or layer is not None):
        raise InputError("--cells: sets struct's cells; give it with --method struct (without --layer), not "
                         f"{list(method or ['auto'])}" + (" with --layer" if layer is not None else ""))
    params = {} if cells is None else {"struct": {"cells": int(cells)}}
    from ..synthesis.registry import VARIATIONS, given_variations, methods_taking, takes_parameter, variation_flag

    exported = list(method or DEFAULT_METHODS)
    given = given_variations({"rotation": rotation, "scale_jitter": scale_jitter, "brightness": brightness,
                              "tint": tint}, "--")
    for name, value in given.items():
        # each exported method that takes it draws it; auto and the others are exported as they are
        varied = [m for m in exported if takes_parameter(m, name)]
        if not varied or layer is not None or target is not None:
            having = methods_taking(name)
            raise InputError(f"{variation_flag(name)}: {VARIATIONS[name]} is for {', '.join(having)}; export "
                             f"{'it' if len(having) == 1 else 'one of them'} with --method (without --layer or "
                             f"--target), not {exported}")
        for m in varied:
            params.setdefault(m, {})[name] = value
    if "scale_jitter" in given:
        from ..synthesized import warn_without_subtexel_term

        warn_without_subtexel_term(model)
    if target is not None:
        if layer is not None:
            raise InputError("--target: guides one material; it does not combine with a layered export (--layer)")
        _export_guided(model, output, method=method, seed=seed, scale=scale, precision=precision, viewer=viewer,
                       target=target, classes=classes, target_size=target_size, target_wrap=target_wrap,
                       softness=softness, cells=cells)
        return
    if layer is not None:
        _export_layered(model, layer, output, method=method, seed=seed, scale=scale, precision=precision,
                        viewer=viewer, mask=mask, mask_size=mask_size, mask_wrap=mask_wrap, width=width)
        return
    result = export_web(model, output, precision=precision, methods=tuple(method or DEFAULT_METHODS),
                        seed=seed, scale=scale, viewer=viewer,
                        method_params=params or None)
    m = result.manifest
    if m.get("auto"):
        typer.echo(m["auto"]["line"])
    _echo_written(result, model, output, precision, viewer)


def _echo_written(result, model: Path, output: Path, precision: str, viewer: bool, what: str = "") -> None:
    """The line that says what was written (``what``: said after the sizes, e.g. the guidance)."""
    m = result.manifest
    first = m["default_method"]
    typer.echo(f"wrote {output}: {len(m['files'])} binary files ({result.total_bytes() / 1e6:.2f} MB, {precision}; "
               f"the {first} method alone needs {result.method_bytes(first) / 1e6:.2f} MB vs the model file's "
               f"{model.stat().st_size / 1e6:.2f} MB){what}, the shader dynbtf.glsl"
               + (f" and the viewer {result.index} (open it in a browser with WebGL2)" if viewer else ""))


def _export_guided(model: Path, output: Path, *, method, seed: int, scale: float, precision: str, viewer: bool,
                   target: Path, classes: int, target_size: float, target_wrap: str, softness: float,
                   cells: int | None) -> None:
    """``--target``: the guided material of ``model`` (:func:`dynbtf.guided.guidance_options`, as ``dynbtf synth``
    and ``dynbtf render`` build theirs), exported as its guided method."""
    from ..export.web.exporter import export_web
    from ..export.web.shader import web_methods
    from ..guided import GUIDED_METHODS, guidance_options, guided_synthesizer
    from ..material import is_compiled_material

    methods = list(method or ["auto"])
    if len(methods) != 1:
        raise InputError(f"--target: exports one guided method; give at most one --method, got {methods}")
    asked = "hist" if methods[0] == "auto" else methods[0]
    if asked in GUIDED_METHODS and guided_synthesizer(asked) not in web_methods():
        guided = [guided_synthesizer(m) for m in GUIDED_METHODS if guided_synthesizer(m) in web_methods()]
        raise InputError(f"--target: the web shader has no form of guided {asked} ({guided_synthesizer(asked)!r}); "
                         f"it runs {guided}")
    guidance = guidance_options(target, method=methods[0], classes=classes, target_size=target_size,
                                target_wrap=target_wrap, softness=softness, cells=cells)
    name = guided_synthesizer(guidance.method)
    if is_compiled_material(model):
        raise InputError(f"--target: {model} is a compiled material, which fixes its method; guide the model file "
                         "(.dbtfm) it was compiled from")
    btf = guidance.build(model, scale=scale, seed=seed)
    result = export_web(btf.material, output, precision=precision, methods=(btf.material.method,), seed=seed,
                        scale=scale, viewer=viewer)
    _echo_written(result, model, output, precision, viewer,
                  f"; {name}, guided by {target}, {guidance.classes} classes over {guidance.target_size:g} uv units")


def _export_layered(model: Path, layer: Path, output: Path, *, method, seed: int, scale: float, precision: str,
                    viewer: bool, mask: str, mask_size: float, mask_wrap: str, width: float) -> None:
    """``--layer``: the layered material of ``model`` and ``layer`` under ``mask``, exported."""
    from ..errors import positive_number
    from ..export.web.layered import export_layered_web
    from ..layered import LayeredBTF, mask_from_spec
    from ..synthesized import synthesized_btf

    methods = list(method or ["auto"])
    if len(methods) != 1:
        raise InputError(f"--layer: each layer is exported with one method; give at most one --method, got {methods}")
    positive_number("--width", width, "uv units")
    the_mask = mask_from_spec(mask, size=mask_size, wrap=mask_wrap)
    layers = [synthesized_btf(path, methods[0], scale=scale, seed=seed) for path in (model, layer)]
    for path, btf in zip((model, layer), layers):
        choice = btf.synthesizer.choice
        if choice is not None:
            typer.echo(f"{path.name}: {choice.line}")
    result = export_layered_web(LayeredBTF(layers, the_mask, width=width), output, precision=precision, viewer=viewer)
    names = ", ".join(f"layer {k} {path.name} ({entry['method']})"
                      for k, (path, entry) in enumerate(zip((model, layer), result.manifest["layers"])))
    typer.echo(f"wrote {output}: a layered material, {names}, mask {mask}"
               + (f"; the viewer {result.index} (open it in a browser with WebGL2; paint the mask there)"
                  if viewer else ""))
