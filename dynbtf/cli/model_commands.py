"""``dynbtf fit``, ``dynbtf eval`` and ``dynbtf inspect``: make, measure and look at model files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from ..training.model_choice import DEFAULT_KIND, stereo_fitter_options
from .app import app


def _open_source(spec: str):
    """A BTF source from a path or spec (``sim:leather?size=64``, a .btf file, ...)."""
    from ..data.open import open_btf

    return open_btf(spec)


# The order in which fit's help lists the training options (each one's flag, type, default and help are those of its
# TrainConfig field: dynbtf.training.fit.command_line_options).
_FIT_TRAINING_OPTIONS = ("epochs", "schedule", "max_minutes", "seed", "held_out_fraction", "images_per_step", "lr_scale",
                         "lr_decay", "texels_per_image", "texel_groups", "memory_budget_mb", "workers", "device",
                         "precision", "compile", "max_reflectance", "subtexel")


def fit(
    btf: str = typer.Argument(..., help="BTF to fit: a file path or a spec such as 'sim:leather?size=128'."),
    output: Path = typer.Option(..., "-o", "--output", help="Model file to write (.dbtfm). Its checkpoint "
                                "<output>.ckpt makes a re-run continue where an interrupted one stopped."),
    repr: str = typer.Option(DEFAULT_KIND, "--repr", help="Representation kind: auto (a short trial fit of triple and "
                             "triple-parallax on the same held-out pairs; the better one's fit continues: the "
                             "choice is printed and recorded in the model), triple (the paper's Triple Plane), "
                             "triple-parallax (Triple Plane fetched at the visible point of a height field "
                             "estimated by stereo: materials with relief), or another registered kind "
                             "(neumip, pca, sh)."),
    recipe: str = typer.Option("auto", help="auto: options chosen from the BTF's size (and --minutes), stated in "
                               "one line (docs/triple_plane.md); paper: the paper's batches and learning rates "
                               "(16 whole images per step, x0.9 per epoch). Options below override either."),
    minutes: Optional[float] = typer.Option(None, "--minutes", help="Time budget of the whole command in minutes "
                                            "(decoding, stereo, the representation's trials, training, writing): the "
                                            "auto recipe times a few steps and shortens its schedule to fit, the "
                                            "trials are sized to it, and the model trained so far is written when "
                                            "it runs out (checkpointed: the same command again continues)."),
    texels: Optional[str] = typer.Option(None, "--texels", help="Fit the BTF resampled to this many texels over "
                                         "the same repeat: HxW (rows x columns) or N; 'whole': the nearest size at "
                                         "which a structured material's elements (bricks, tiles) are whole texels, "
                                         "so that `synth --method struct` can keep each one whole (stated in one "
                                         "line; a BTF without elements keeps its size). `dynbtf eval` resamples the "
                                         "BTF the same way."),
    stereo_max_height: Optional[float] = typer.Option(None, "--stereo-max-height", help="triple-parallax only: "
                                                      "largest relief height the stereo estimate searches, in uv "
                                                      "units (default 0.08: +-10 texels at 128 texels)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
    **training,
) -> None:
    """Fit a representation to a BTF (L1, AdamW; the recipe chosen from its size, or the paper's).

    Example: dynbtf fit leather.btf -o leather.dbtfm --minutes 60
    """
    from ..errors import positive_number
    from ..io import check_writable
    from ..training import get_fitter
    from ..training.exemplar_texels import parse_texels, resample_for_fit
    from ..training.fit import budget_left, check_options
    from ..training.recipe import choose_config

    from .app import command_started

    started = command_started()  # --minutes counts from the command's start

    check_writable(output, "-o/--output")  # an unwritable model file fails before any training
    given = {name: value for name, value in training.items() if value is not None}  # None: the recipe chooses
    check_options(**given)  # every number finite and in range before the recipe computes with it
    if "compile" in given:  # a mode this device cannot run fails before any work
        from ..device import resolve_device
        from ..training.step_loss import resolve_compile

        resolve_compile(given["compile"], resolve_device(given.get("device", "auto")))
    if minutes is not None:
        positive_number("--minutes", minutes, "number of minutes")
    if stereo_max_height is not None:
        positive_number("--stereo-max-height", stereo_max_height, "height in uv units")
    fitter = get_fitter(repr)
    if texels is not None:
        parse_texels(texels)  # a malformed value fails before the BTF is opened
    source, resampled = resample_for_fit(_open_source(btf), texels)
    if resampled and not quiet:
        typer.echo(resampled)
    config, summary = choose_config(source, output, recipe=recipe, minutes=minutes, **given)
    if not quiet:
        typer.echo(summary)
    options = stereo_fitter_options(repr, stereo_max_height)
    result = fitter(source, output, budget_left(config, started), progress=not quiet, **options)
    if quiet:
        size = result.metadata.get("provenance", {}).get("size", {})
        typer.echo(f"wrote {result.model_path}" + (f" ({size['summary']})" if "summary" in size else ""))


def _with_training_options(command):
    """``command``'s signature with the :class:`~dynbtf.training.TrainConfig` options inserted after
    ``minutes`` (as ``typer.Option`` parameters built from the fields), so that typer parses them into
    ``**training``."""
    import inspect
    import types
    import typing

    from ..training.fit import command_line_options

    fields = command_line_options()
    made = []
    for name in _FIT_TRAINING_OPTIONS:
        annotation, cli = fields[name]
        base = next(a for a in typing.get_args(annotation) if a is not type(None)) \
            if isinstance(annotation, types.UnionType) else annotation
        flags = (cli.flag,) if cli.flag else ()
        made.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=Optional[base]
                                      if cli.default is None else base,
                                      default=typer.Option(cli.default, *flags, help=cli.help)))
    own = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in inspect.signature(command).parameters.values()
           if p.kind is not inspect.Parameter.VAR_KEYWORD]
    cut = [p.name for p in own].index("minutes") + 1
    command.__signature__ = inspect.Signature(own[:cut] + made + own[cut:], return_annotation=None)
    return command


app.command()(_with_training_options(fit))


@app.command("eval")
def eval_command(
    model: Path = typer.Argument(..., help="Model file (.dbtfm)."),
    btf: str = typer.Argument(..., help="The BTF it was fitted to: a file path or spec (as given to `dynbtf fit`)."),
    output: Path = typer.Option(..., "-o", "--output", help="Directory for metrics.csv, metrics.json and "
                                "side-by-side PNGs (ground truth | model | FLIP error map)."),
    pairs: str = typer.Option("held-out", help="Pairs to evaluate: held-out (never trained on), all, or a file "
                              "of 'view_index,light_index' lines."),
    images: int = typer.Option(8, help="Number of side-by-side PNGs."),
    device: str = typer.Option("auto", help="auto, cpu, cuda:0, ..."),
    force: bool = typer.Option(False, "--force", help="Skip the check that the BTF is the one the model was fitted "
                               "to (size, directions, name and content, as recorded in the model file)."),
) -> None:
    """Evaluate a model against its BTF: PSNR (linear), DSSIM and FLIP (clamped sRGB), per pair and mean.

    The BTF is checked against the one recorded in the model file: another size or other
    directions is an error; another name with the same size and directions (e.g. a converted
    copy), or other content under the same name (the BTF changed since the fit, or a lossy
    copy), is a warning. --force skips the check.
    """
    from ..provenance import check_model_source, source_as_fitted
    from ..representations.model_file import load_model
    from ..training.evaluate import evaluate_model, resolve_eval_pairs

    rep, meta = load_model(model, device=device)
    source = source_as_fitted(meta, _open_source(btf))
    if not force:
        for warning in check_model_source(meta, source, model=str(model)):
            typer.echo(f"dynbtf: warning: {warning}", err=True)
    chosen = resolve_eval_pairs(pairs, source, meta)
    result = evaluate_model(rep, source, chosen, out_dir=output, images=images)
    typer.echo(f"{model.name} on {source.name}: {result.summary()}; wrote {output}")


@app.command()
def inspect(
    model: Path = typer.Argument(..., help="Model file (.dbtfm)."),
    output: Optional[Path] = typer.Option(None, "-o", "--output", help="Directory for feature-plane PNGs "
                                          "(positional plane's first 3 principal components as RGB, angular planes)."),
    as_json: bool = typer.Option(False, "--json", help="Print the full metadata as JSON."),
) -> None:
    """Show a model file's metadata and size (vs the raw BTF); optionally write feature-plane pictures."""
    from ..representations.model_file import load_model, model_size_report

    rep, meta = load_model(model)
    prov = meta.get("provenance", {})
    src = prov.get("source", {})
    if as_json:
        typer.echo(json.dumps(meta, indent=1))
    else:
        size = model_size_report(rep, src.get("raw_float32_bytes"))
        lines = [f"{model}: {meta['kind']} (format {meta['format']} v{meta['format_version']})",
                 f"  config: {json.dumps(meta['config'])}",
                 f"  size: {size['summary']}; {size['n_parameters']} parameters"]
        if src:
            lines.append(f"  fitted to: {src.get('name')} ({src.get('height')}x{src.get('width')} texels, "
                         f"{src.get('n_views')} views x {src.get('n_lights')} lights)")
        if "epochs_completed" in prov:
            lines.append(f"  training: {prov['epochs_completed']:.2f} epochs, {prov.get('training_seconds', 0) / 60:.1f} "
                         f"min, seed {prov.get('seed')}, finished={prov.get('finished')}")
        if "held_out_pairs" in prov:
            lines.append(f"  held-out pairs: {len(prov['held_out_pairs'])}"
                         + (f" (monitor PSNR {prov['held_out_psnr_monitor']:.2f} dB, "
                            f"{prov.get('held_out_psnr_monitor_metric', 'fixed peak 1')})"
                            if "held_out_psnr_monitor" in prov else ""))
        typer.echo("\n".join(lines))
    if output is not None:
        from ..representations.visualize import write_feature_plane_pngs

        paths = write_feature_plane_pngs(rep, output)
        typer.echo(f"wrote {len(paths)} feature-plane images to {output}")
