"""``dynbtf compare``: the paper's representation (and synthesis) comparisons in one command."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app


@app.command()
def compare(
    btf: str = typer.Argument(..., help="BTF to compare on: a file path or a spec such as 'sim:leather?size=64'."),
    output: Path = typer.Option(..., "-o", "--output", help="Output directory: model files <kind>.dbtfm (reused "
                                "when run again; unfinished fits continue), representations.csv/.json, "
                                "representations.png, eval_<kind>/ and index.html."),
    repr: str = typer.Option("triple,neumip,pca,sh", "--repr", help="Comma-separated representation kinds."),
    budget_minutes: Optional[float] = typer.Option(None, "--budget-minutes", help="Training-time limit (minutes) "
                                                   "of each gradient-trained fit in this run (triple, neumip); "
                                                   "a stopped fit continues when the command is run again. "
                                                   "Default: no limit."),
    epochs: int = typer.Option(12, help="Epochs of the gradient-trained fits (the paper: 50)."),
    seed: int = typer.Option(0, help="Seed of the shared held-out split, batch order and initializations."),
    held_out_fraction: float = typer.Option(0.05, "--held-out-fraction", help="Fraction of (view, light) pairs "
                                            "held out of every fit and used for the comparison."),
    images_per_step: int = typer.Option(16, "--images-per-step", help="Whole images per optimizer step of the "
                                        "gradient-trained fits (as in `dynbtf fit`)."),
    lr_scale: float = typer.Option(1.0, "--lr-scale", help="Multiplier of the gradient-trained fits' learning "
                                   "rates (as in `dynbtf fit`; 1: the paper's)."),
    texel_groups: int = typer.Option(1, "--texel-groups", help="Texel groups per step of the gradient-trained fits "
                                     "(as in `dynbtf fit`; 64 with --lr-scale 6 is the fast Triple Plane recipe; docs/baselines.md used 3; 1: the "
                                     "paper's whole images)."),
    precision: str = typer.Option("auto", help="Arithmetic of the gradient-trained fits' training kernel: fp32, "
                                  "bf16 or auto (as in `dynbtf fit`)."),
    examples: int = typer.Option(3, help="Held-out pairs shown in the figure (rows)."),
    synthesis: Optional[str] = typer.Option(None, "--synthesis", help="Also compare synthesis methods on the "
                                            "fitted model of this kind (e.g. triple): quality numbers, storage "
                                            "and one image per method, in synthesis.csv/.json."),
    methods: str = typer.Option("tile,hist,hex,quilt", "--methods", help="Synthesis methods (with --synthesis)."),
    scale: float = typer.Option(15.0, help="Synthesized area in exemplar repeats per side (with --synthesis; "
                                "quilting pre-generates a plane of this size)."),
    workers: Optional[int] = typer.Option(None, help="Threads of the fused training kernel (default: torch's)."),
    device: str = typer.Option("auto", help="auto (CUDA if available), cpu, cuda:0, ..."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bars."),
) -> None:
    """Fit (or load) each representation, evaluate all on the same held-out pairs, write table and figures.

    Columns: PSNR (dB, linear values), DSSIM and FLIP (clamped sRGB), storage (bytes; all of the model and
    its positional plane alone) and fit time (seconds), as in the paper's Figs. 4 and 8.
    """
    from ..compare import compare_representations
    from ..data.open import open_btf
    from ..errors import InputError
    from ..report.html import HtmlReport
    from ..training import TrainConfig

    kinds = [k.strip() for k in repr.split(",") if k.strip()]
    if not kinds:
        raise InputError("--repr: expected a comma-separated list of representation kinds, e.g. triple,pca")
    if synthesis is not None and synthesis not in kinds:
        raise InputError(f"--synthesis {synthesis!r}: expected one of the compared kinds {kinds}")
    config = TrainConfig(epochs=epochs, max_minutes=budget_minutes, seed=seed, held_out_fraction=held_out_fraction,
                         images_per_step=images_per_step, lr_scale=lr_scale, texel_groups=texel_groups,
                         workers=workers, device=device, precision=precision)
    source = open_btf(btf)
    report = HtmlReport(f"dynbtf compare: {source.name}",
                        f"{source.height} x {source.width} texels, {source.n_views} views x {source.n_lights} lights")
    scores = compare_representations(source, output, kinds, config, examples=examples, progress=not quiet,
                                     report=report)
    if synthesis:
        from ..compare import compare_synthesis

        compare_synthesis(Path(output) / f"{synthesis}.dbtfm", output,
                          [m.strip() for m in methods.split(",") if m.strip()], scale=scale, seed=seed,
                          report=report, progress=not quiet)
    report.write(Path(output) / "index.html")
    width = max(len(s.kind) for s in scores)
    lines = [f"{'kind':<{width}}  PSNR dB  grazing   others  fixed-1   DSSIM    FLIP    storage B   fit s"]
    lines += [f"{s.kind:<{width}}  {s.psnr:7.2f}  {s.psnr_grazing:7.2f}  {s.psnr_others:7.2f}  {s.psnr_fixed1:7.2f}  "
              f"{s.dssim:6.4f}  {s.flip:6.4f}  {s.storage_bytes:10d}  "
              f"{s.fit_seconds:6.0f}" + ("" if s.finished else "  (unfinished)") for s in scores]
    lines.append("PSNR: per-image peak (grazing: view or light beyond 60 deg); fixed-1: against a fixed peak of 1")
    typer.echo("\n".join(lines) + f"\nwrote {Path(output) / 'index.html'}")
