"""``dynbtf compile``: a model's compiled material for one synthesis method and seed (:mod:`dynbtf.material`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from . import guidance_options
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
    rotation: bool = guidance_options.ROTATION,
    scale_jitter: float = guidance_options.SCALE_JITTER,
    brightness: float = guidance_options.BRIGHTNESS,
    tint: float = guidance_options.TINT,
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
    from ..synthesis.registry import VARIATIONS, given_variations, methods_taking, takes_parameter, variation_flag

    params = {} if gamma is None else {"gamma": gamma}
    given = given_variations({"rotation": rotation, "scale_jitter": scale_jitter, "brightness": brightness,
                              "tint": tint}, "--")
    for name, value in given.items():
        if not takes_parameter(method, name):
            having = methods_taking(name)
            raise InputError(f"{variation_flag(name)}: {VARIATIONS[name]} is for {', '.join(having)}; give it with "
                             f"--method {having[0]}, not {method!r}")
        params[name] = value
    if params.get("scale_jitter"):
        from ..synthesized import warn_without_subtexel_term

        warn_without_subtexel_term(model)
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
