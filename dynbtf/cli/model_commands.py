"""``dynbtf fit``, ``dynbtf eval`` and ``dynbtf inspect``: make, measure and look at model files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from ..errors import InputError
from .app import app


def _open_source(spec: str):
    """A BTF source from a path or spec (``sim:leather?size=64``, a .btf file, ...)."""
    from ..data.open import open_btf

    return open_btf(spec)


@app.command()
def fit(
    btf: str = typer.Argument(..., help="BTF to fit: a file path or a spec such as 'sim:leather?size=128'."),
    output: Path = typer.Option(..., "-o", "--output", help="Model file to write (.dbtfm). Its checkpoint "
                                "<output>.ckpt makes a re-run continue where an interrupted one stopped."),
    repr: str = typer.Option("triple", "--repr", help="Representation kind: triple (the paper's Triple Plane), "
                             "triple-parallax (Triple Plane fetched at the visible point of a height field "
                             "estimated by stereo: materials with relief), or another registered kind "
                             "(neumip, pca, sh)."),
    recipe: str = typer.Option("auto", help="auto: options chosen from the BTF's size (and --minutes), stated in "
                               "one line (docs/triple_plane.md); paper: the paper's batches and learning rates "
                               "(16 whole images per step, x0.9 per epoch). Options below override either."),
    minutes: Optional[float] = typer.Option(None, "--minutes", help="Time budget in minutes: the auto recipe "
                                            "times a few steps and shortens its schedule to fit, and training stops "
                                            "(checkpointed) if it still overruns."),
    epochs: Optional[int] = typer.Option(None, help="Passes over the training (view, light) pairs (auto: from the "
                                         "BTF's size; paper: 50, the paper's)."),
    max_minutes: Optional[float] = typer.Option(None, "--max-minutes", help="Stop after this many minutes of "
                                                "training (checkpointed; run again to continue). Default: no limit."),
    seed: int = typer.Option(0, help="Seed of the held-out split, batch order and initialization."),
    held_out_fraction: float = typer.Option(0.05, "--held-out-fraction", help="Fraction of (view, light) pairs "
                                            "never trained on, for evaluation."),
    images_per_step: int = typer.Option(16, "--images-per-step", help="Whole images per optimizer step."),
    lr_scale: Optional[float] = typer.Option(None, "--lr-scale", help="Multiplier of the learning rates (paper: 1, "
                                             "i.e. 1e-3 for planes, 3e-4 for the decoder; auto: 6)."),
    lr_decay: Optional[float] = typer.Option(None, "--lr-decay", help="Learning-rate factor per epoch (paper: 0.9; "
                                             "auto: the reference's total decay 0.9^30 spread over its epochs)."),
    texels_per_image: Optional[int] = typer.Option(None, "--texels-per-image", help="Train on a random subset of "
                                                   "this many texels per step (auto: all up to 262,144)."),
    texel_groups: Optional[int] = typer.Option(None, "--texel-groups", help="Split each step's texels into this "
                                               "many groups, each under its own --images-per-step pairs: more "
                                               "(view, light) pairs per step at the same cost (paper: 1, whole "
                                               "images; auto: 64)."),
    memory_mb: Optional[float] = typer.Option(None, "--memory-mb", help="RAM (MB) for the float16 image cache; "
                                              "larger BTFs are read texel block by texel block from the source "
                                              "(paper: 2048; auto: 40% of RAM, at most 8 GiB)."),
    workers: Optional[int] = typer.Option(None, help="Threads of the fused training kernel (default: torch's)."),
    device: str = typer.Option("auto", help="auto (CUDA if available), cpu, cuda:0, ..."),
    precision: str = typer.Option("auto", help="Arithmetic of the decoder's training kernel: fp32, bf16 "
                                  "(bfloat16 products, float32 accumulation and parameters; CPUs with "
                                  "AVX512-BF16), or auto (bf16 where available, else fp32)."),
    max_reflectance: Optional[float] = typer.Option(None, "--max-reflectance", help="Largest |value| a training "
                                                    "image may hold (reflectance pi f_r, linear RGB; default 1e4): "
                                                    "beyond it the BTF decodes to garbage and the fit stops naming "
                                                    "the image. Raise it for data that really is that bright."),
    stereo_max_height: Optional[float] = typer.Option(None, "--stereo-max-height", help="triple-parallax only: "
                                                      "largest relief height the stereo estimate searches, in uv "
                                                      "units (default 0.08: +-10 texels at 128 texels)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Fit a representation to a BTF (L1, AdamW; the recipe chosen from its size, or the paper's).

    Example: dynbtf fit leather.btf -o leather.dbtfm --minutes 60
    """
    from ..errors import positive_number
    from ..training import get_fitter
    from ..training.fit import check_options
    from ..training.recipe import choose_config

    given = {name: value for name, value in (
        ("epochs", epochs), ("max_minutes", max_minutes), ("lr_scale", lr_scale), ("lr_decay", lr_decay),
        ("texels_per_image", texels_per_image), ("texel_groups", texel_groups), ("memory_budget_mb", memory_mb),
        ("workers", workers), ("max_reflectance", max_reflectance)) if value is not None}
    common = dict(seed=seed, held_out_fraction=held_out_fraction, images_per_step=images_per_step, device=device,
                  precision=precision)
    check_options(**given, **common)  # every number finite and in range before the recipe computes with it
    if minutes is not None:
        positive_number("--minutes", minutes, "number of minutes")
    if stereo_max_height is not None:
        positive_number("--stereo-max-height", stereo_max_height, "height in uv units")
    fitter = get_fitter(repr)
    source = _open_source(btf)
    config, summary = choose_config(source, output, recipe=recipe, minutes=minutes, **common, **given)
    if not quiet:
        typer.echo(summary)
    options = {}
    if stereo_max_height is not None:
        if repr != "triple-parallax":
            raise InputError(f"--stereo-max-height applies to --repr triple-parallax, not {repr!r}")
        options["stereo"] = {"max_height": stereo_max_height}
    result = fitter(source, output, config, progress=not quiet, **options)
    if quiet:
        size = result.metadata.get("provenance", {}).get("size", {})
        typer.echo(f"wrote {result.model_path}" + (f" ({size['summary']})" if "summary" in size else ""))


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
    from ..provenance import check_model_source
    from ..representations.model_file import load_model
    from ..training.evaluate import evaluate_model, resolve_eval_pairs

    rep, meta = load_model(model, device=device)
    source = _open_source(btf)
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
