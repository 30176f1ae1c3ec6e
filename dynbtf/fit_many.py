"""Fit a library of BTFs as Ray tasks: ``dynbtf fit-many MANIFEST -o DIR``.

A manifest (TOML) lists the sources and their options; every option of ``dynbtf fit`` is allowed,
in ``[defaults]`` for every source or in a source's own table::

    [defaults]
    minutes = 60            # dynbtf fit --minutes: the auto recipe fitted to an hour per material
    repr = "triple"

    [[source]]
    btf = "leather.btf"     # required: a path (relative to the manifest) or a spec such as 'sim:leather?size=128'
    name = "leather"        # optional: DIR/leather.dbtfm (default: from the file or spec)

    [[source]]
    btf = "stone.btf"
    repr = "triple-parallax"
    epochs = 20

Each source is fitted by one Ray task (:func:`fit_one`): on a local Ray instance that the call
starts and stops (``address=None``), or on an existing cluster (``address="ray://..."`` or
``"auto"``). A task uses the CPUs Ray gives it (``cpus_per_task``: its torch threads and the fused
kernel's workers), continues from its own checkpoint, and is retried (``max_retries``) when its
worker process dies; the retry resumes where the checkpoint left off and ends with the same model
as an uninterrupted fit. A source that fails (a missing file, a bad BTF) is reported as failed and
the others go on. Results: one model per source, ``results.csv`` / ``results.json`` (held-out PSNR,
DSSIM, FLIP, training time, model size, status) and ``index.html`` with each model's evaluation
images. Ray is the optional extra ``dynbtf[cluster]``.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
import re
import time
import tomllib
from pathlib import Path
from typing import Any, Callable

from .errors import DynBTFError, InputError, optional_module
from .io import atomic_path

__all__ = ["fit_many", "fit_one", "read_manifest", "FitTask", "MANIFEST_OPTIONS", "RESULT_COLUMNS"]

#: Manifest keys: ``dynbtf fit`` options (command-line names with ``_`` for ``-``) and their types.
MANIFEST_OPTIONS: dict[str, type | tuple[type, ...]] = {
    "repr": str, "recipe": str, "minutes": (int, float), "epochs": int, "max_minutes": (int, float),
    "seed": int, "held_out_fraction": (int, float), "images_per_step": int, "lr_scale": (int, float),
    "lr_decay": (int, float), "texels_per_image": int, "texel_groups": int, "memory_mb": (int, float),
    "precision": str, "device": str, "stereo_max_height": (int, float),
}
#: Keys of a ``[[source]]`` table besides the options.
SOURCE_KEYS = {"btf": str, "name": str}
#: Columns of ``results.csv`` (and keys of each ``results.json`` row).
RESULT_COLUMNS = ("name", "btf", "status", "psnr", "psnr_fixed1", "dssim", "flip", "epochs", "finished",
                  "training_minutes", "model_bytes", "attempts", "model", "error")

#: ``dynbtf fit`` option names that are :class:`~dynbtf.training.fit.TrainConfig` fields under another name.
_TRAIN_FIELD = {"memory_mb": "memory_budget_mb"}


@dataclasses.dataclass
class FitTask:
    """One source of a manifest, resolved: what :func:`fit_one` fits."""

    name: str
    btf: str
    options: dict[str, Any]
    output_dir: str
    cpus: int = 1
    line: int = 0

    @property
    def model_path(self) -> Path:
        return Path(self.output_dir) / f"{self.name}.dbtfm"


# ---------------------------------------------------------------------------- manifest
def _key_lines(text: str) -> tuple[dict[str, int], list[dict[str, int]]]:
    """Line numbers (1-based) of the keys of ``[defaults]`` and of each ``[[source]]`` table."""
    defaults: dict[str, int] = {}
    sources: list[dict[str, int]] = []
    current: dict[str, int] | None = None
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped.startswith("[[") and stripped.rstrip().endswith("]]"):
            current = {"": number} if stripped[2:-2].strip() == "source" else None
            if current is not None:
                sources.append(current)
        elif stripped.startswith("["):
            current = defaults if stripped[1:-1].strip() == "defaults" else None
            if current is defaults:
                defaults.setdefault("", number)
        else:
            match = re.match(r'\s*"?([A-Za-z0-9_\-]+)"?\s*=', line)
            if match and current is not None:
                current.setdefault(match.group(1), number)
    return defaults, sources


def _check_table(path: Path, table: dict[str, Any], lines: dict[str, int], where: str, allowed: dict) -> None:
    for key, value in table.items():
        line = lines.get(key, lines.get("", 0))
        if key not in allowed:
            raise InputError(f"{path}:{line}: unknown key {key!r} in {where}; expected one of "
                             f"{sorted(allowed)}")
        kind = allowed[key]
        if isinstance(value, bool) or not isinstance(value, kind):
            names = " or ".join(t.__name__ for t in (kind if isinstance(kind, tuple) else (kind,)))
            raise InputError(f"{path}:{line}: {where} key {key!r} = {value!r}: expected {names}")


def _default_name(btf: str) -> str:
    base = btf.split("?")[0].removeprefix("sim:")
    stem = Path(base).name
    for suffix in (".btf", ".zip", ".dbtf"):
        stem = stem.removesuffix(suffix)
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", stem) or "btf"


def _check_options(path: Path, options: dict[str, Any], lines: dict[str, int]) -> None:
    """Values a fit would refuse, found before any task starts (the line of the offending key)."""
    from .training.fit import TrainConfig
    from .training.fitters import get_fitter
    from .training.recipe import RECIPES

    def fail(key: str, message: str):
        raise InputError(f"{path}:{lines.get(key, lines.get('', 0))}: {key!r}: {message}")

    if options.get("recipe", "auto") not in RECIPES:
        fail("recipe", f"expected one of {list(RECIPES)}, got {options['recipe']!r}")
    try:
        get_fitter(options.get("repr", "triple"))
    except InputError as e:
        fail("repr", str(e))
    if "minutes" in options and not options["minutes"] > 0:
        fail("minutes", f"expected a positive time budget, got {options['minutes']!r}")
    if "stereo_max_height" in options and options.get("repr") != "triple-parallax":
        fail("stereo_max_height", "applies to repr = 'triple-parallax' only")
    fields = {_TRAIN_FIELD.get(k, k): v for k, v in options.items() if _TRAIN_FIELD.get(k, k) in
              {f.name for f in dataclasses.fields(TrainConfig)}}
    try:
        TrainConfig(**fields).validate()
    except InputError as e:
        flag = str(e).split(" ")[0].removeprefix("--").replace("-", "_")
        key = next((k for k in options if k == flag or _TRAIN_FIELD.get(k) == flag), "")
        fail(key, str(e))


def read_manifest(manifest, output_dir, *, cpus_per_task: int = 1) -> list[FitTask]:
    """The tasks of a manifest file, every key and option checked.

    Raises :class:`InputError` naming the file, line and key for an unknown key, a value of the wrong
    type or range, a ``[[source]]`` without ``btf``, or two sources with one name; nothing runs before.
    """
    path = Path(manifest)
    if not path.is_file():
        raise InputError(f"{path}: manifest not found")
    text = path.read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: not valid TOML ({e})") from None
    default_lines, source_lines = _key_lines(text)
    unknown = set(data) - {"defaults", "source"}
    if unknown:
        key = sorted(unknown)[0]
        line = next((n for n, s in enumerate(text.splitlines(), 1) if re.match(rf"\s*\[*\s*{re.escape(key)}\b", s)), 0)
        raise InputError(f"{path}:{line}: unknown key {key!r}; a manifest has [defaults] and [[source]] tables")
    defaults = data.get("defaults", {})
    if not isinstance(defaults, dict):
        raise InputError(f"{path}: 'defaults' must be a table ([defaults])")
    _check_table(path, defaults, default_lines, "[defaults]", MANIFEST_OPTIONS)
    sources = data.get("source", [])
    if not isinstance(sources, list) or not sources:
        raise InputError(f"{path}: no [[source]] tables: nothing to fit")
    tasks: list[FitTask] = []
    seen: dict[str, int] = {}
    for index, table in enumerate(sources):
        lines = source_lines[index] if index < len(source_lines) else {}
        _check_table(path, table, lines, f"[[source]] #{index + 1}", MANIFEST_OPTIONS | SOURCE_KEYS)
        if "btf" not in table:
            raise InputError(f"{path}:{lines.get('', 0)}: [[source]] #{index + 1} has no 'btf' key (a BTF file "
                             "or a spec such as 'sim:leather?size=128')")
        options = {**defaults, **{k: v for k, v in table.items() if k not in SOURCE_KEYS}}
        _check_options(path, options, {**default_lines, **lines})
        btf = table["btf"]
        if not btf.startswith("sim:") and not Path(btf).is_absolute():
            btf = str((path.parent / btf).resolve())
        name = table.get("name") or _default_name(table["btf"])
        if name in seen:
            raise InputError(f"{path}:{lines.get('name', lines.get('', 0))}: two sources are named {name!r} "
                             f"(also line {seen[name]}); give one a 'name'")
        seen[name] = lines.get("", 0)
        tasks.append(FitTask(name, btf, options, str(output_dir), int(cpus_per_task), lines.get("", 0)))
    return tasks


# ---------------------------------------------------------------------------- one task
def fit_one(task: FitTask, callback: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Fit and evaluate one source as ``dynbtf fit`` would, using ``task.cpus`` threads; a result row.

    Resumes from the model's checkpoint if one exists. Errors of the source or its options are
    returned as ``status = "failed"`` with the message (not raised: the other tasks go on).
    """
    import torch

    from .data.open import open_btf
    from .training.evaluate import evaluate_model, resolve_eval_pairs
    from .training.fitters import get_fitter
    from .training.recipe import choose_config

    torch.set_num_threads(max(1, task.cpus))
    row: dict[str, Any] = {"name": task.name, "btf": task.btf, "status": "failed", "model": str(task.model_path)}
    started = time.perf_counter()
    try:
        options = dict(task.options)
        repr_kind = options.pop("repr", "triple")
        recipe = options.pop("recipe", "auto")
        minutes = options.pop("minutes", None)
        stereo = options.pop("stereo_max_height", None)
        train = {_TRAIN_FIELD.get(k, k): v for k, v in options.items()}
        train.setdefault("workers", max(1, task.cpus))
        source = open_btf(task.btf)
        Path(task.output_dir).mkdir(parents=True, exist_ok=True)
        config, summary = choose_config(source, task.model_path, recipe=recipe, minutes=minutes, **train)
        extra = {"stereo": {"max_height": stereo}} if stereo is not None else {}
        fitter = get_fitter(repr_kind)
        if callback is not None:
            extra["callback"] = callback
        result = fitter(source, task.model_path, config, progress=False, **extra)
        provenance = result.metadata.get("provenance", {})
        pairs = resolve_eval_pairs("held-out", source, result.metadata)
        evaluation = evaluate_model(result.representation, source, pairs, out_dir=Path(task.output_dir) /
                                    f"{task.name}_eval", images=4, progress=False)
        row.update(status="done", recipe=summary, epochs=provenance.get("epochs_completed"),
                   finished=provenance.get("finished"),
                   training_minutes=float(provenance.get("training_seconds", 0.0)) / 60.0,
                   model_bytes=(provenance.get("size") or {}).get("model_bytes"),
                   images=[str(p) for p in evaluation.images],
                   **{k: evaluation.mean.get(k) for k in ("psnr", "psnr_fixed1", "dssim", "flip")})
    except DynBTFError as e:
        row["error"] = str(e)
    except Exception as e:  # a bug or an environment failure: reported with its type, the others go on
        row["error"] = f"{type(e).__name__}: {e}"
    row["seconds"] = time.perf_counter() - started
    return row


# ---------------------------------------------------------------------------- many tasks
def _write_results(output_dir: Path, rows: list[dict[str, Any]]) -> None:
    with atomic_path(output_dir / "results.json") as tmp:
        tmp.write_text(json.dumps({"results": rows}, indent=2, default=str))
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=RESULT_COLUMNS, extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: row.get(k, "") for k in RESULT_COLUMNS})
    with atomic_path(output_dir / "results.csv") as tmp:
        tmp.write_text(buffer.getvalue())
    _write_index(output_dir, rows)


def _write_index(output_dir: Path, rows: list[dict[str, Any]]) -> None:
    from .report.html import HtmlReport

    report = HtmlReport("dynbtf fit-many", f"{sum(r['status'] == 'done' for r in rows)} of {len(rows)} sources "
                                          "fitted; metrics on each model's held-out pairs.")
    report.table([{"source": r["name"], "BTF": r["btf"], "status": r["status"],
                   "PSNR (dB, per-image peak)": r.get("psnr"), "DSSIM": r.get("dssim"), "FLIP": r.get("flip"),
                   "epochs": r.get("epochs"), "training (min)": r.get("training_minutes"),
                   "model size (bytes)": r.get("model_bytes"), "attempts": r.get("attempts"),
                   "error": r.get("error", "")} for r in rows], caption="Results (also results.csv, results.json)")
    for r in rows:
        if r.get("images"):
            report.section(r["name"], f"{r['btf']}: ground truth | model | FLIP error, held-out pairs")
            report.images([(p, Path(p).stem.replace("_", " ")) for p in r["images"]], width=420)
    report.write(output_dir / "index.html")


def _attempts(task_name: str, output_dir: Path) -> int:
    marker = output_dir / f".{task_name}.attempts"
    return int(marker.read_text()) if marker.exists() else 1


def _counted(task_fn: Callable[..., dict[str, Any]]):
    """``task_fn`` that first counts its attempts in a file next to the outputs (retries show as > 1)."""
    def run(task: FitTask) -> dict[str, Any]:
        marker = Path(task.output_dir) / f".{task.name}.attempts"
        Path(task.output_dir).mkdir(parents=True, exist_ok=True)
        count = (int(marker.read_text()) if marker.exists() else 0) + 1
        with atomic_path(marker) as tmp:
            tmp.write_text(str(count))
        return task_fn(task)

    return run


def fit_many(manifest, output_dir, *, address: str | None = None, cpus: int | None = None, cpus_per_task: int = 1,
             max_retries: int = 3, progress: bool = True, task_fn: Callable[[FitTask], dict[str, Any]] = fit_one
             ) -> list[dict[str, Any]]:
    """Fit every source of ``manifest`` as a Ray task; write the models and the results to ``output_dir``.

    Parameters
    ----------
    manifest : path
        The TOML manifest (see the module docstring); checked completely before any task starts.
    output_dir : path
        Models (``<name>.dbtfm``), evaluations (``<name>_eval/``), ``results.csv``, ``results.json``,
        ``index.html``.
    address : str, optional
        An existing Ray cluster; default: a local Ray instance with ``cpus`` CPUs (default: all),
        started and stopped here.
    cpus_per_task : int
        CPUs (torch threads) per fit.
    max_retries : int
        Retries of a task whose worker process died (a retry resumes from the checkpoint).
    task_fn : callable
        What a task runs (default :func:`fit_one`).

    Returns
    -------
    list of dict
        One result row per source, in manifest order (:data:`RESULT_COLUMNS`).
    """
    output_dir = Path(output_dir)
    if cpus_per_task < 1:
        raise InputError(f"--cpus-per-task: expected an integer >= 1, got {cpus_per_task}")
    tasks = read_manifest(manifest, output_dir, cpus_per_task=cpus_per_task)
    ray = optional_module("ray", "cluster", "dynbtf fit-many")
    output_dir.mkdir(parents=True, exist_ok=True)
    for task in tasks:
        (output_dir / f".{task.name}.attempts").unlink(missing_ok=True)
    started_here = not ray.is_initialized()
    if started_here:
        init = {"address": address} if address else {"num_cpus": cpus or os.cpu_count() or 1}
        ray.init(**init, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        remote = ray.remote(_counted(task_fn)).options(num_cpus=cpus_per_task, max_retries=max_retries,
                                                        retry_exceptions=False)
        pending = {remote.remote(task): index for index, task in enumerate(tasks)}
        rows: list[dict[str, Any] | None] = [None] * len(tasks)
        from .progress import progress_bar

        bar = progress_bar(total=len(tasks), desc="fit-many", unit="fit", disable=not progress)
        failed = 0
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=5.0)
            for ref in done:
                index = pending.pop(ref)
                try:
                    row = ray.get(ref)
                except Exception as e:  # the worker died more often than max_retries
                    row = {"name": tasks[index].name, "btf": tasks[index].btf, "status": "failed",
                           "model": str(tasks[index].model_path), "error": f"task lost: {type(e).__name__}: {e}"}
                row["attempts"] = _attempts(tasks[index].name, output_dir)
                rows[index] = row
                failed += row["status"] != "done"
                bar.update(1)
            bar.set_postfix(running=len(pending), failed=failed, refresh=False)
            bar.refresh()  # at most every 5 s (ray.wait's timeout), whatever the bar's interval
        bar.close()
    finally:
        if started_here:
            ray.shutdown()
    for task in tasks:
        (output_dir / f".{task.name}.attempts").unlink(missing_ok=True)
    results = [r for r in rows if r is not None]
    _write_results(output_dir, results)
    return results
