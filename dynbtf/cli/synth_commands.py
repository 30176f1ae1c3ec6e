"""``dynbtf synth``: a flat sample of the synthesized BTF (Figs. 5-6 style) and the synthesis quality report."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .app import app


def _pair(text: str, name: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        raise InputError(f"--{name}: expected two comma-separated numbers like '30,90', got {text!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise InputError(f"--{name}: expected finite numbers, got {text!r}")
    return a, b


@app.command()
def synth(
    model: Path = typer.Argument(..., help="dynbtf model file (a fitted representation with a positional plane)."),
    output: Optional[Path] = typer.Option(None, "-o", "--output",
                                          help="Output image: .png (sRGB) or .exr (linear HDR)."),
    method: str = typer.Option("hist", help="Synthesis method: tile, linear, hist, hex or quilt."),
    scale: float = typer.Option(8.0, help="Exemplar repeats across the image (the paper's 8x, 25x, 45x)."),
    view: str = typer.Option("0,0", help="View direction THETA,PHI in degrees."),
    light: str = typer.Option("30,0", help="Light direction THETA,PHI in degrees."),
    resolution: int = typer.Option(1024, help="Image width and height in pixels."),
    seed: int = typer.Option(0, help="Synthesis seed."),
    spp: int = typer.Option(1, help="Supersampling: spp x spp samples per pixel (box filter) against aliasing "
                                    "when a pixel covers many texels."),
    center: str = typer.Option("0.5,0.5", help="uv of the image centre (the image spans one uv unit), "
                                               "e.g. 1e6,1e6 to look far from the origin."),
    exposure: float = typer.Option(1.0, help="Multiplier applied before sRGB encoding (PNG only)."),
    report: bool = typer.Option(False, "--report", help="Also measure synthesis quality (W1/std of features and "
                                                        "RGB, repetition, verbatim copies) and print a table."),
    report_methods: str = typer.Option("tile,linear,hist,hex", help="Methods compared by --report."),
    report_json: Optional[Path] = typer.Option(None, help="Where --report saves its JSON "
                                                          "(default: next to -o, or synthesis-quality.json)."),
    repeats: int = typer.Option(8, help="Side of the area measured by --report, in exemplar repeats."),
) -> None:
    """Synthesize a flat sample of the BTF at any scale and position; optionally report quality.

    The image shows the uv square of side 1 centred at --center under one view
    and one directional light; pixel values are the BTF value times
    cos(theta_light) (unit irradiance at normal incidence), linear RGB.
    """
    from ..conventions import spherical_to_direction
    from ..io import save_image
    from ..representations.model_file import load_model
    from ..synthesized import SynthesizedBTF

    if output is None and not report:
        raise InputError("nothing to do: give -o/--output for an image and/or --report")
    if resolution < 1:
        raise InputError(f"--resolution: expected a positive number of pixels, got {resolution}")
    view_dir, light_dir = _pair(view, "view"), _pair(light, "light")
    cu, cv = _pair(center, "center")
    rep, _ = load_model(model)
    if output is not None:
        btf = SynthesizedBTF(rep, method, scale=scale, seed=seed)
        img = btf.image(view=view_dir, light=light_dir, uv_rect=(cu - 0.5, cv - 0.5, cu + 0.5, cv + 0.5),
                        resolution=resolution, spp=spp)
        cos_light = max(float(spherical_to_direction(light_dir[0], light_dir[1])[2]), 0.0)
        save_image(output, img * cos_light, exposure=exposure)
        typer.echo(f"wrote {output} ({resolution}x{resolution}, {method}, {scale:g}x, centre {cu:g},{cv:g})")
    if report:
        from ..synthesis.quality import format_report, quality_report, save_report

        reports = []
        for name in [m.strip() for m in report_methods.split(",") if m.strip()]:
            reports.append(quality_report(SynthesizedBTF(rep, name, scale=scale, seed=seed), repeats=repeats))
        typer.echo(format_report(reports))
        path = report_json or (output.with_suffix(".quality.json") if output is not None
                               else Path("synthesis-quality.json"))
        save_report(reports, path)
        typer.echo(f"wrote {path}")
