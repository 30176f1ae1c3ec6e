"""``dynbtf compile``: a model's compiled material for one synthesis method and seed (:mod:`dynbtf.material`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .app import app


@app.command("compile")
def compile_command(
    model: Path = typer.Argument(..., help="dynbtf model file (`dynbtf fit`)."),
    output: Optional[Path] = typer.Option(None, "-o", "--output",
                                          help="Compiled material to write (.dbtfc); default: only the cache."),
    method: str = typer.Option("auto", help="Synthesis method: tile, linear, hist, hex, quilt, struct, or auto "
                                            "(struct for structured materials, else hist; the choice is printed)."),
    seed: int = typer.Option(0, help="Synthesis seed."),
    gamma: Optional[float] = typer.Option(None, "--gamma", help="Blending exponent of hist (when hist is used)."),
    rotation: bool = typer.Option(False, "--rotation", help="hist, hex, linear: turn each sample by random quarter "
                                  "turns, the view and light with it (for isotropic materials)."),
    footprints: bool = typer.Option(True, "--footprints/--no-footprints",
                                    help="Also fit the per-level decoders and mean appearance of footprint "
                                         "(filtered) queries: a fit per pyramid level, the slow part, done once."),
) -> None:
    """Derive once what every backend reads for MODEL, METHOD and SEED, and save it.

    The synthesis tables and pyramid, the decoder with the method's output map folded into layer 1, the
    per-level decoders and the mean appearance. The material is also stored in the cache
    ($DYNBTF_COMPILED_CACHE, default ~/.cache/dynbtf/compiled), keyed by the model's contents, where
    `dynbtf synth`, `dynbtf render`, `dynbtf export` and the Mitsuba plugin find it; a cached material is
    read, not compiled again.

    Example: dynbtf compile leather.dbtfm --method auto -o leather-auto.dbtfc
    """
    from ..material import SUFFIX, save_compiled
    from ..io import check_writable
    from ..representations.model_file import load_model
    from ..material import open_or_compile

    if output is not None:
        if output.suffix != SUFFIX:
            raise InputError(f"-o/--output: expected a {SUFFIX} file name, got {output}")
        check_writable(output, "-o/--output")
    params = {} if gamma is None else {"gamma": gamma}
    if rotation:
        from ..synthesis.registry import methods_taking, takes_parameter

        if not takes_parameter(method, "rotation"):
            having = methods_taking("rotation")
            raise InputError(f"--rotation: turning the samples is for {', '.join(having)}; give it with --method "
                             f"{having[0]}, not {method!r}")
        params["rotation"] = True
    rep, _ = load_model(model)
    start = time.perf_counter()
    material, how = open_or_compile(rep, method, seed, footprints=footprints, **params)
    if material.choice is not None:
        typer.echo(material.choice["line"])
    info = material.describe()
    typer.echo(f"{model}: method {material.method}, seed {material.seed}, {info['footprint_levels']} footprint "
               f"level(s), mean appearance {'yes' if info['mean_appearance'] else 'no'}, "
               f"{info['table_bytes'] / 1e6:.2f} MB of tables; {how} in {time.perf_counter() - start:.1f} s")
    if output is not None:
        save_compiled(material, output)
        typer.echo(f"wrote {output}")
