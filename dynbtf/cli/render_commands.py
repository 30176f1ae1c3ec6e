"""``dynbtf render`` (Mitsuba 3 scenes) and ``dynbtf demo`` (the whole pipeline into one report)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from . import guidance_options
from .app import app


@app.command()
def render(
    model: Path = typer.Argument(..., help="dynbtf model file: a Triple Plane (`dynbtf fit`, also with "
                                           "`--repr triple-parallax`) or a NeuMIP (`dynbtf fit --repr neumip`)."),
    output: Path = typer.Option(..., "-o", "--output", help="Output image: .png (sRGB, exposure applied) or .exr (linear HDR)."),
    scene: str = typer.Option("plane", help="Scene: plane (grazing ground plane), sphere or cloth."),
    lighting: str = typer.Option("sky", help="Lighting: sky (procedural environment map) or point (point light + dim ambient)."),
    method: str = typer.Option("auto", help="Synthesis of the positional plane: tile, hist, hex, struct (cell "
                                            "quilting for weaves, tiles, bricks) or auto (struct for structured "
                                            "exemplars, hist otherwise; the choice is printed)."),
    scale: float = typer.Option(25.0, help="Exemplar repeats across the mesh's uv range."),
    seed: int = typer.Option(0, help="Synthesis seed."),
    spp: int = typer.Option(16, help="Samples per pixel."),
    sampling: str = typer.Option("auto", help="Direction sampling: mixture (the model's importance-sampling "
                                              "table mixed with cosine sampling; converges faster on glossy "
                                              "materials), cosine (the paper's), or auto (mixture for glossy "
                                              "models, cosine for rough ones)."),
    filtered: bool = typer.Option(True, "--filtered/--point", help="Footprint queries (the default): distant "
                                  "surfaces show their filtered appearance; --point: one point query per sample."),
    size: int = typer.Option(512, help="Image width and height in pixels."),
    exposure: float = typer.Option(1.0, help="Multiplier applied before sRGB encoding (PNG only)."),
    variant: Optional[str] = typer.Option(None, help="Mitsuba variant (default llvm_ad_rgb; cuda_ad_rgb on a GPU); "
                                                     "an unavailable one is refused with the list of available ones."),
    memory_mb: Optional[float] = typer.Option(None, "--memory-mb", help="Limit (MB) of the render's estimated working "
                                                                        "memory (~0.5 kB per sample in flight: --size "
                                                                        "squared x min(--spp, 4)); default half of "
                                                                        "this machine's memory. Larger requests are "
                                                                        "refused up front."),
    layer: Optional[Path] = typer.Option(None, "--layer", help="A second material (model file or .dbtfc) layered "
                                         "with MODEL: MODEL where --mask is below one half, this one above "
                                         "(same method and scale; the boundary follows both materials' heights)."),
    mask: str = typer.Option("noise", "--mask", help="With --layer: an image file (PNG/JPEG grey levels or EXR "
                             "values in [0, 1]) over the mesh's uv, or noise:SCALE[,CONTRAST[,SEED]] (value noise, "
                             "cells of SCALE uv units)."),
    mask_size: float = typer.Option(1.0, "--mask-size", help="Mesh uv units a mask image covers."),
    mask_wrap: str = typer.Option("repeat", "--mask-wrap", help="A mask image repeats (repeat) or extends its "
                                  "edges (clamp)."),
    width: float = typer.Option(0.05, "--width", help="With --layer: half-width (mesh uv units) of the band "
                                "around the mask's contour where the materials' heights decide."),
    target: Optional[Path] = typer.Option(None, "--target", help="Guided synthesis (hist, hex or struct; auto: hist): an "
                                          "image painted over the mesh's uv (PNG/JPEG grey levels, or EXR values in "
                                          "[0, 1]), cut into --classes bins; a point in bin k shows the material's "
                                          "class k (0 the darkest)."),
    classes: int = typer.Option(2, "--classes", help="With --target: classes of the material's texels."),
    target_size: float = typer.Option(1.0, "--target-size", help="Mesh uv units the --target image covers."),
    target_wrap: str = typer.Option("repeat", "--target-wrap", help="The --target image repeats (repeat) or "
                                    "extends its edges (clamp)."),
    softness: float = typer.Option(0.0, "--softness", help="With --target: weight factor (0 to 1) of samples "
                                   "that found no content of the target's class."),
    cells: int = typer.Option(0, "--cells", help="struct's cells per repeat along each side (0: its own choice); "
                              "with --target, about one per element of the material."),
    brightness: float = guidance_options.BRIGHTNESS,
    tint: float = guidance_options.TINT,
    rotation: bool = guidance_options.ROTATION,
    scale_jitter: float = guidance_options.SCALE_JITTER,
) -> None:
    """Path-trace a scene covered by the synthesized BTF with Mitsuba 3 (dynbtf's query at every shading point).

    With --layer, two materials share the surface (the dynbtf_layered plugin): MODEL where --mask is below one
    half, the --layer one above, the boundary following both materials' heights within --width. With --target,
    the material's content follows a painted target (guided synthesis).

    The first pass compiles Mitsuba's kernels (up to a minute the first time a scene is rendered;
    Dr.Jit caches them): a status line says so, then a bar counts samples.

    Limits, checked before anything loads: --scale below 2**24 repeats (Mitsuba's uv is float32),
    --spp at most 65536 and --size^2 x --spp at most 2**32 samples, the estimated memory within
    --memory-mb; Mitsuba's CPU back end needs LLVM 16 or newer (`dynbtf system` shows the one found).
    """
    from ..io import check_image_path, check_writable, save_image
    from ..render.mitsuba.scene_render import check_render_request, render_scene

    from .arguments import check_exposure

    check_image_path(output)  # before the render, not after it
    check_writable(output, "-o/--output")
    check_exposure(exposure)
    if size < 1:
        raise InputError(f"--size: expected a positive number of pixels, got {size}")
    check_render_request(scale=scale, resolution=(size, size), spp=spp, memory_mb=memory_mb, size_name="size")
    the_mask = None
    if layer is not None:  # (--width, with the rest, is checked by render_scene before anything loads)
        from ..layered import mask_from_spec

        the_mask = mask_from_spec(mask, size=mask_size, wrap=mask_wrap)
    result = render_scene(model, scene=scene, method=method, scale=scale, seed=seed, lighting=lighting,
                          resolution=(size, size), spp=spp, variant=variant, progress=True, sampling=sampling,
                          filtered=filtered, echo=typer.echo, memory_mb=memory_mb, layer=layer,
                          mask=the_mask, width=width, target=target, classes=classes, target_size=target_size,
                          target_wrap=target_wrap, target_softness=softness, cells=cells, brightness=brightness,
                          rotation=rotation, scale_jitter=scale_jitter,
                          tint=tint)
    save_image(output, result.image, exposure=exposure)
    timing = (f"incl. {result.compile_seconds:.1f} s kernel compilation" if result.passes > 1
              else "one pass, kernel compilation included")
    typer.echo(f"wrote {output} ({size}x{size}, {spp} spp, {result.variant}, {result.seconds:.1f} s {timing})")


@app.command()
def demo(
    output: Path = typer.Option(Path("dynbtf-demo"), "-o", "--output", help="Output directory (rerun to resume)."),
    material: str = typer.Option("leather", help="Simulated material: stone, leather, lacquered_wood, woven_fabric, "
                                                      "ceramic_tiles or brick_wall."),
    size: int = typer.Option(128, help="Texels per side of the simulated BTF."),
    btf: Optional[str] = typer.Option(None, help="Your own BTF (file or sim: spec) instead of a simulated one."),
    minutes: float = typer.Option(10.0, help="Target wall time in minutes; training gets what the other stages leave."),
    seed: int = typer.Option(0, help="Seed of simulation, training and synthesis."),
    render_size: int = typer.Option(360, help="Mitsuba render side in pixels."),
    spp: int = typer.Option(16, help="Mitsuba samples per pixel."),
    quick: bool = typer.Option(False, "--quick", help="Tiny sizes everywhere (a smoke test in about a minute)."),
    device: str = typer.Option("auto", help="auto (CUDA if available), cpu, cuda:0, ...: where the model is "
                                            "fitted, evaluated and synthesized (Mitsuba renders with llvm_ad_rgb)."),
) -> None:
    """Simulate, fit, evaluate, synthesize (tile/hist/hex at 1x-45x), render, and write report.html."""
    from ..demo import DemoConfig, run_demo

    run_demo(DemoConfig(output=str(output), material=material, size=size, btf=btf, minutes=minutes, seed=seed,
                        quick=quick, render_size=render_size, spp=spp, device=device))
