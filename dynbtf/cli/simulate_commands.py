"""``dynbtf simulate``: write a simulated measured BTF (the built-in default data) as a stored BTF."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from .app import app


@app.command()
def simulate(
    material: Optional[str] = typer.Argument(None, help="Material to simulate: stone, leather, lacquered_wood, "
                                             "woven_fabric, ceramic_tiles or brick_wall (see --list)."),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Where to write: a stored BTF directory "
                                          "(*.dbtf; an interrupted run resumes when run again) or, with a .btf "
                                          "suffix, a UBO2014 DFMF file (factored in bounded memory)."),
    size: int = typer.Option(128, help="Spatial resolution in texels per side (one exemplar repeat)."),
    grid: str = typer.Option("ubo2003", help="Direction grid: ubo2003 (81 views x 81 lights, 6,561 images) or "
                             "ubo2014 (151 x 151, 22,801 images)."),
    seed: int = typer.Option(0, help="Seed of the material's random structure (same seed: identical values)."),
    relief: float = typer.Option(1.0, help="Multiplier of the material's height field, in [0, 4] (0: flat, "
                                 "1: the material as designed). Deeper relief: longer shadows, more parallax."),
    dtype: str = typer.Option("float16", help="Stored value type: float16 (half the size) or float32 (for a .btf "
                              "file: its scalar type, half or float)."),
    components: int = typer.Option(96, help="For a .btf file: SVD components per colour channel (96 at 400 x 400 "
                                   "texels on the ubo2014 grid: a 210 MB file, as the UBO2014 files we met)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output."),
    device: str = typer.Option("auto", help="Where to render: auto (CUDA if available), cpu, cuda:0, ..."),
    list_materials: bool = typer.Option(False, "--list", help="List the materials and exit."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Simulate a measured BTF (height field with cast shadows, masking, parallax; GGX reflectance) and store it.

    Values are linear RGB reflectance factors pi * f_r (excluding cos(theta_light)).
    Example: dynbtf simulate leather -o leather.dbtf --size 128 --grid ubo2003
    """
    from ..data.simulated import GRIDS, MATERIALS, simulated_btf
    from ..errors import InputError

    if list_materials:
        width = max(len(m) for m in MATERIALS)
        for name, text in MATERIALS.items():
            typer.echo(f"{name:<{width}}  {text}")
        typer.echo("grids: " + "; ".join(f"{k}: {v}" for k, v in GRIDS.items()))
        return
    if material is None:
        raise InputError(f"MATERIAL: name a material to simulate ({', '.join(MATERIALS)}), or pass --list")
    if output is None:
        raise InputError("--output: give the stored BTF directory to write, e.g. -o stone.dbtf")
    from ..data.stored import write_stored

    source = simulated_btf(material, size=size, grid=grid, seed=seed, relief=relief, device=device)
    start = time.perf_counter()
    if output.suffix.lower() == ".btf":
        from ..data.ubo2014 import write_ubo2014

        scalar = {"float16": "half", "half": "half", "float32": "float", "float": "float"}.get(dtype)
        if scalar is None:
            raise InputError(f"--dtype {dtype!r}: a .btf file stores half (float16) or float (float32) values")
        if output.exists() and not overwrite:
            raise InputError(f"--output {output} exists; pass --overwrite to replace it")
        if components < 1:
            raise InputError(f"--components {components}: expected a positive number of SVD components")
        write_ubo2014(output, source, components=components, scalar=scalar, method="randomized", seed=seed,
                      progress=not quiet)
        what = f"UBO2014 DFMF, {components} components, {scalar}"
    else:
        write_stored(output, source, dtype=dtype, progress=not quiet, overwrite=overwrite)
        what = dtype
    seconds = time.perf_counter() - start
    typer.echo(f"wrote {output}: {source.name} seed {source.seed}, {source.height}x{source.width} texels, "
               f"{source.n_views} views x {source.n_lights} lights ({what}) in {seconds:.1f} s")
