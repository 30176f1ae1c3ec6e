"""``dynbtf fit-many``: fit a library of BTFs as Ray tasks (:func:`dynbtf.fit_many.fit_many`)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .app import app


@app.command("fit-many")
def fit_many_command(
    manifest: Path = typer.Argument(..., help="TOML manifest: \\[defaults] and one \\[\\[source]] table per BTF, with "
                                              "any `dynbtf fit` option (docs/cluster.md)."),
    output: Path = typer.Option(..., "-o", "--output", help="Directory for the models, results.csv, "
                                                            "results.json and index.html."),
    address: Optional[str] = typer.Option(None, "--address", help="An existing Ray cluster (e.g. 'auto' or "
                                                                  "'ray://head:10001'); default: a local Ray "
                                                                  "instance started and stopped by the command."),
    cpus: Optional[int] = typer.Option(None, "--cpus", help="CPUs of the local Ray instance (default: all)."),
    cpus_per_task: int = typer.Option(1, "--cpus-per-task", help="CPUs (torch threads) per fit."),
    max_retries: int = typer.Option(3, "--max-retries", help="Retries of a fit whose worker process died (it "
                                                             "resumes from its checkpoint)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress display."),
    check: bool = typer.Option(False, "--check", help="Check the manifest, the output directory and the resources "
                                                      "(every problem listed), print the tasks, and stop: nothing "
                                                      "is written and Ray is not started."),
) -> None:
    """Fit every BTF of a manifest as a Ray task; a results table and an index.html with the evaluations.

    Everything is checked before Ray starts: every problem of the manifest is listed together and
    nothing runs (a source's name must be a plain file name: models stay inside -o).

    Example: dynbtf fit-many library.toml -o library/ --cpus-per-task 2
    """
    from ..fit_many import check_run, fit_many

    if check:
        tasks = check_run(manifest, output, address=address, cpus=cpus, cpus_per_task=cpus_per_task,
                          max_retries=max_retries)
        for task in tasks:
            typer.echo(f"{task.name}: {task.btf} -> {task.model_path}")
        typer.echo(f"{manifest}: {len(tasks)} source(s) checked; nothing was run (--check)")
        return

    rows = fit_many(manifest, output, address=address, cpus=cpus, cpus_per_task=cpus_per_task,
                    max_retries=max_retries, progress=not quiet)
    for row in rows:
        if row["status"] == "done":
            typer.echo(f"{row['name']}: PSNR {row['psnr']:.2f} dB (per-image peak), FLIP {row['flip']:.3f}, "
                       f"{row['training_minutes']:.1f} min -> {row['model']}")
        else:
            typer.echo(f"{row['name']}: FAILED: {row.get('error', '')}")
    failed = sum(r["status"] != "done" for r in rows)
    typer.echo(f"wrote {output / 'results.csv'} and {output / 'index.html'} ({len(rows) - failed} done, "
               f"{failed} failed)")
    if failed:
        raise typer.Exit(1)
