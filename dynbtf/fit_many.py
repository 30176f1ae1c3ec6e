"""Fit a library of BTFs as Ray tasks: ``dynbtf fit-many MANIFEST -o DIR``.

A manifest (TOML) lists the sources and their options; every option of ``dynbtf fit`` is allowed,
in ``[defaults]`` for every source or in a source's own table::

    [defaults]
    minutes = 60            # dynbtf fit --minutes: the auto recipe fitted to an hour per material
    repr = "auto"           # the default: a trial of each kind, the better one's fit continued

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

Untrusted manifests: everything is checked before Ray starts or anything is written, and every
problem of every source is reported together (one line each, nothing runs; fix them and run
again), rather than running the good sources and skipping the bad. A manifest is UTF-8 TOML of at
most :data:`MAX_MANIFEST_BYTES`; a ``name`` is :data:`NAME_RULE` (so a model is always written
inside the output directory: ``"../x"``, ``"/tmp/x"``, ``"a/b"`` are refused, not resolved); a
``btf`` is opened as ``dynbtf fit`` opens it (a ``sim:`` spec with its options, an existing file by its
content: any other file is refused; a missing one is left to its task, which then fails alone);
numbers are finite and fit in 64 bits. The output directory must be writable, ``--cpus``,
``--cpus-per-task`` and ``--max-retries`` in range, a task must fit on one machine
(``--cpus-per-task`` <= ``--cpus``, or the CPUs of the cluster's largest node), and an
``--address`` must answer within :data:`CONNECT_TIMEOUT` seconds. ``check=True``
(``dynbtf fit-many --check``) stops after these checks.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import re
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any, Callable

from .errors import DynBTFError, InputError, optional_module
from .io import atomic_path, check_writable

__all__ = ["fit_many", "fit_one", "read_manifest", "check_name", "FitTask", "MANIFEST_OPTIONS", "RESULT_COLUMNS",
           "NAME_RULE", "MAX_NAME_LENGTH", "MAX_MANIFEST_BYTES", "CONNECT_TIMEOUT"]

#: Manifest keys: ``dynbtf fit`` options (command-line names with ``_`` for ``-``) and their types.
MANIFEST_OPTIONS: dict[str, type | tuple[type, ...]] = {
    "repr": str, "recipe": str, "minutes": (int, float), "epochs": int, "max_minutes": (int, float),
    "seed": int, "held_out_fraction": (int, float), "images_per_step": int, "lr_scale": (int, float),
    "lr_decay": (int, float), "texels_per_image": int, "texel_groups": int, "memory_mb": (int, float),
    "precision": str, "device": str, "stereo_max_height": (int, float), "texels": str,
}
#: Keys of a ``[[source]]`` table besides the options.
SOURCE_KEYS = {"btf": str, "name": str}
#: Columns of ``results.csv`` (and keys of each ``results.json`` row).
RESULT_COLUMNS = ("name", "btf", "status", "psnr", "psnr_fixed1", "dssim", "flip", "epochs", "finished",
                  "training_minutes", "model_bytes", "attempts", "model", "error")

#: ``dynbtf fit`` option names that are :class:`~dynbtf.training.fit.TrainConfig` fields under another name.
_TRAIN_FIELD = {"memory_mb": "memory_budget_mb"}
#: Longest source name (the files written for it add up to ~40 characters to it; file names stop at 255).
MAX_NAME_LENGTH = 100
#: What a source name may be (its files are ``DIR/<name>.dbtfm``, ``DIR/<name>_eval/``).
NAME_RULE = (f"1 to {MAX_NAME_LENGTH} characters of A-Z, a-z, 0-9, '_', '-' and '.', starting with a letter, "
             "a digit or '_'")
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*\Z")
#: Largest manifest file read (bytes).
MAX_MANIFEST_BYTES = 4 * 2**20
#: Seconds an ``address`` has to answer (a TCP connection, then a Ray driver connecting to it).
CONNECT_TIMEOUT = 60.0
#: Most problems of a manifest listed in one error (the count says how many more).
MAX_LISTED = 50
#: Largest ``max_retries`` (Ray's -1, retry for ever, is not offered).
MAX_RETRIES = 100


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
            raise InputError(f"{path}:{line}: {where} key {key!r} = {_short(value)}: expected {names}")
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError(f"{path}:{line}: {where} key {key!r} = {value!r}: expected a finite number")
        if isinstance(value, int) and not -2**63 <= value < 2**63:
            raise InputError(f"{path}:{line}: {where} key {key!r} = {_short(value)}: out of range (a 64-bit integer)")
        if isinstance(value, str) and key != "name" and ("\x00" in value or len(value) > 4096):
            raise InputError(f"{path}:{line}: {where} key {key!r} = {_short(value)}: expected text without NUL "
                             "characters, at most 4096 characters")


def _default_name(btf: str) -> str:
    base = btf.split("?")[0].removeprefix("sim:")
    stem = Path(base).name
    for suffix in (".btf", ".zip", ".dbtf"):
        stem = stem.removesuffix(suffix)
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", stem).lstrip(".-")[:MAX_NAME_LENGTH]
    return name or "btf"


def check_name(name) -> str | None:
    """Why ``name`` is not a valid source name (:data:`NAME_RULE`), or ``None`` if it is.

    >>> check_name("leather_01")
    >>> check_name("../../x")
    "'../../x' is a path"
    """
    if not isinstance(name, str):
        return f"{_short(name)} is not a string"
    if "/" in name or "\\" in name or name in (".", "..") or os.path.isabs(name):
        return f"{_short(name)} is a path"
    if len(name) > MAX_NAME_LENGTH:
        return f"{_short(name)} has {len(name)} characters; at most {MAX_NAME_LENGTH}"
    if not _NAME.match(name):
        bad = sorted({c for c in name if not (c.isascii() and (c.isalnum() or c in "_.-"))})
        if bad:
            return f"{_short(name)} contains {', '.join(repr(c) for c in bad[:5])}"
        return f"{_short(name)} starts with {name[:1]!r}" if name else "the name is empty"
    return None


def _short(value, limit: int = 60) -> str:
    """``repr(value)``, cut to ``limit`` characters for a message (a value may be megabytes)."""
    try:
        text = repr(value)
    except RecursionError:
        text = f"<a deeply nested {type(value).__name__}>"
    return text if len(text) <= limit else text[:limit - 5] + "...'" + f" ({len(text)} characters)"


def _check_options(path: Path, options: dict[str, Any], lines: dict[str, int]) -> None:
    """Values a fit would refuse, found before any task starts (the line of the offending key)."""
    from .training.exemplar_texels import parse_texels
    from .training.fit import TrainConfig
    from .training.fitters import get_fitter
    from .training.model_choice import DEFAULT_KIND
    from .training.recipe import RECIPES

    def fail(key: str, message: str):
        raise InputError(f"{path}:{lines.get(key, lines.get('', 0))}: {key!r}: {message}")

    if options.get("recipe", "auto") not in RECIPES:
        fail("recipe", f"expected one of {list(RECIPES)}, got {options['recipe']!r}")
    try:
        get_fitter(options.get("repr", DEFAULT_KIND))
    except InputError as e:
        fail("repr", str(e))
    if "minutes" in options and not options["minutes"] > 0:
        fail("minutes", f"expected a positive time budget, got {options['minutes']!r}")
    if "stereo_max_height" in options and options.get("repr", DEFAULT_KIND) not in ("triple-parallax", "auto"):
        fail("stereo_max_height", "applies to repr = 'triple-parallax' (or 'auto') only")
    if "texels" in options:
        try:
            parse_texels(options["texels"])
        except InputError as e:
            fail("texels", str(e).removeprefix("--texels: "))
    fields = {_TRAIN_FIELD.get(k, k): v for k, v in options.items() if _TRAIN_FIELD.get(k, k) in
              {f.name for f in dataclasses.fields(TrainConfig)}}
    try:
        TrainConfig(**fields).validate()
    except InputError as e:
        flag = str(e).split(" ")[0].removeprefix("--").replace("-", "_")
        key = next((k for k in options if k == flag or _TRAIN_FIELD.get(k) == flag), "")
        fail(key, str(e))


def _read_text(path: Path) -> str:
    """The manifest's text: a file of at most :data:`MAX_MANIFEST_BYTES`, UTF-8 (a BOM is skipped)."""
    try:
        if not path.is_file():
            raise InputError(f"{path}: manifest not found" if not path.exists() else
                             f"{path}: not a file (expected a TOML manifest)")
        size = path.stat().st_size
        if size > MAX_MANIFEST_BYTES:
            raise InputError(f"{path}: {size} bytes; a manifest is at most {MAX_MANIFEST_BYTES} bytes")
        data = path.read_bytes()[:MAX_MANIFEST_BYTES + 1]
    except OSError as e:
        from .io import os_error_message

        raise InputError(f"{path}: cannot read the manifest: {os_error_message(e)}") from None
    if len(data) > MAX_MANIFEST_BYTES:
        raise InputError(f"{path}: more than {MAX_MANIFEST_BYTES} bytes; a manifest is at most {MAX_MANIFEST_BYTES}")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        column = e.start - (data.rfind(b"\n", 0, e.start) + 1) + 1
        raise InputError(f"{path}:{line}: byte 0x{data[e.start]:02x} (column {column}) is not UTF-8; a manifest is "
                         "TOML, which is UTF-8 text (comments too)") from None
    return text.removeprefix("\ufeff")


def _parse(path: Path, text: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: not valid TOML ({e})") from None
    except RecursionError:
        raise InputError(f"{path}: arrays or inline tables nested too deeply to read; a manifest's values are "
                         "numbers and strings") from None


def _problems_error(path: Path, problems: list[str]) -> InputError:
    if len(problems) == 1:
        return InputError(problems[0])
    listed = problems[:MAX_LISTED]
    more = f"\n  ... and {len(problems) - MAX_LISTED} more" if len(problems) > MAX_LISTED else ""
    return InputError(f"{path}: {len(problems)} problems, nothing was run (each is fixed in the manifest):\n  "
                      + "\n  ".join(listed) + more)


def read_manifest(manifest, output_dir, *, cpus_per_task: int = 1) -> list[FitTask]:
    """The tasks of a manifest file, every key and option checked.

    Raises :class:`InputError` naming the file, line and key for an unknown key, a value of the wrong
    type or range, a ``[[source]]`` without ``btf``, a ``name`` that is not :data:`NAME_RULE`, or two
    sources with one name; every problem of every source is listed in one error (one line each), and
    nothing runs before. Also for a file that is not UTF-8 TOML of at most :data:`MAX_MANIFEST_BYTES`.
    """
    path = Path(manifest)
    text = _read_text(path)
    data = _parse(path, text)
    default_lines, source_lines = _key_lines(text)
    unknown = set(data) - {"defaults", "source"}
    if unknown:
        key = sorted(unknown)[0]
        line = next((n for n, s in enumerate(text.splitlines(), 1) if re.match(rf"\s*\[*\s*{re.escape(key)}\b", s)), 0)
        raise InputError(f"{path}:{line}: unknown key {_short(key)}; a manifest has [defaults] and [[source]] tables")
    defaults = data.get("defaults", {})
    if not isinstance(defaults, dict):
        raise InputError(f"{path}: 'defaults' must be a table ([defaults])")
    problems: list[str] = []
    try:
        _check_table(path, defaults, default_lines, "[defaults]", MANIFEST_OPTIONS)
    except InputError as e:
        problems.append(str(e))
    sources = data.get("source", [])
    if isinstance(sources, list) and not sources:
        raise _problems_error(path, problems + [f"{path}: no [[source]] tables: nothing to fit"])
    if not isinstance(sources, list) or any(not isinstance(table, dict) for table in sources):
        raise _problems_error(path, problems + [f"{path}: 'source' must be an array of tables ([[source]])"])
    defaults_ok = not problems
    tasks: list[FitTask] = []
    seen: dict[str, int] = {}
    for index, table in enumerate(sources):
        lines = source_lines[index] if index < len(source_lines) else {}
        where = lines.get("", 0)
        try:
            _check_table(path, table, lines, f"[[source]] #{index + 1}", MANIFEST_OPTIONS | SOURCE_KEYS)
            if "btf" not in table:
                raise InputError(f"{path}:{where}: [[source]] #{index + 1} has no 'btf' key (a BTF file "
                                 "or a spec such as 'sim:leather?size=128')")
            if not table["btf"].strip():
                raise InputError(f"{path}:{lines.get('btf', where)}: [[source]] #{index + 1} key 'btf' is empty; "
                                 "expected a BTF file or a spec such as 'sim:leather?size=128'")
            name = table.get("name")
            if name is not None:
                why = check_name(name)
                if why is not None:
                    raise InputError(f"{path}:{lines.get('name', where)}: [[source]] #{index + 1} name {why}; a name "
                                     f"is {NAME_RULE}, so that its model is written inside the output directory")
            name = name or _default_name(table["btf"])
            options = {**defaults, **{k: v for k, v in table.items() if k not in SOURCE_KEYS}}
            if defaults_ok:
                _check_options(path, options, {**default_lines, **lines})
        except InputError as e:
            problems.append(str(e))
            continue
        btf = table["btf"]
        if not btf.startswith("sim:") and not Path(btf).is_absolute():
            btf = os.path.abspath(path.parent / btf)
        problem = _source_problem(btf)
        if problem is not None:
            problems.append(f"{path}:{lines.get('btf', where)}: [[source]] #{index + 1} btf {table['btf']!r}: {problem}")
            continue
        if name in seen:
            problems.append(f"{path}:{lines.get('name', where)}: two sources are named {name!r} (also line "
                            f"{seen[name]}); give one a 'name'")
            continue
        seen[name] = where
        tasks.append(FitTask(name, btf, options, str(output_dir), int(cpus_per_task), where))
    if problems:
        raise _problems_error(path, problems)
    return tasks


def _source_problem(btf: str) -> str | None:
    """Why ``btf`` cannot be opened as ``dynbtf fit`` would open it, or None: a ``sim:`` spec is opened (its
    options checked), an existing path must be a BTF (its format recognized from the content). A missing
    file is left to the run, where its task fails and the others go on."""
    from .data.open import open_btf, sniff_format
    from .errors import FormatError

    try:
        if btf.startswith("sim:"):
            open_btf(btf)
        elif os.path.exists(btf):
            sniff_format(btf)
    except (InputError, FormatError) as e:
        return str(e)
    return None


# ---------------------------------------------------------------------------- one task
def fit_one(task: FitTask, callback: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Fit and evaluate one source as ``dynbtf fit`` would, using ``task.cpus`` threads; a result row.

    Resumes from the model's checkpoint if one exists. Errors of the source or its options are
    returned as ``status = "failed"`` with the message (not raised: the other tasks go on).
    """
    import torch

    from .data.open import open_btf
    from .training.evaluate import evaluate_model, resolve_eval_pairs
    from .training.exemplar_texels import resample_for_fit
    from .training.fitters import get_fitter
    from .training.model_choice import DEFAULT_KIND, stereo_fitter_options
    from .training.recipe import choose_config

    torch.set_num_threads(max(1, task.cpus))
    row: dict[str, Any] = {"name": task.name, "btf": task.btf, "status": "failed", "model": str(task.model_path)}
    started = time.perf_counter()
    try:
        options = dict(task.options)
        repr_kind = options.pop("repr", DEFAULT_KIND)
        recipe = options.pop("recipe", "auto")
        minutes = options.pop("minutes", None)
        stereo = options.pop("stereo_max_height", None)
        texels = options.pop("texels", None)
        train = {_TRAIN_FIELD.get(k, k): v for k, v in options.items()}
        train.setdefault("workers", max(1, task.cpus))
        source, _ = resample_for_fit(open_btf(task.btf), texels)
        Path(task.output_dir).mkdir(parents=True, exist_ok=True)
        config, summary = choose_config(source, task.model_path, recipe=recipe, minutes=minutes, **train)
        extra = stereo_fitter_options(repr_kind, stereo, "stereo_max_height")
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


def _first_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0][:300]}" if text else type(e).__name__


def _check_fits(node_cpus: list[float], cpus_per_task: int, where: str) -> None:
    """A task of ``cpus_per_task`` CPUs must fit on one node, or Ray waits for ever."""
    largest = max(node_cpus, default=0.0)
    if cpus_per_task > largest:
        raise InputError(f"--cpus-per-task {cpus_per_task}: no task could ever be scheduled: {where} has at most "
                         f"{largest:g} CPUs on one node; expected --cpus-per-task {max(1, int(largest))} or less"
                         + (" (or a larger --cpus)" if where.startswith("the local") else ""))


def _node_cpus(ray) -> list[float]:
    return [float(n.get("Resources", {}).get("CPU", 0.0)) for n in ray.nodes() if n.get("Alive")]


_ADDRESS = re.compile(r"(?:(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://)?(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+)"
                      r":(?P<port>[0-9]{1,5})\Z")


def check_address(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a Ray ``address`` (``host:port`` or ``ray://host:port``); ``None`` for ``"auto"``.

    Raises :class:`InputError` for anything else (the forms Ray accepts are named).

    >>> check_address("ray://head:10001")
    ('head', 10001)
    """
    if address in ("auto",):
        return None
    match = _ADDRESS.match(address or "")
    port = int(match.group("port")) if match else 0
    scheme = match.group("scheme") if match else None
    if match is None or not 1 <= port <= 65535 or scheme not in (None, "ray"):
        raise InputError(f"--address {_short(address)}: expected 'auto', HOST:PORT (the head's GCS, e.g. "
                         "10.0.0.5:6379) or ray://HOST:PORT (Ray Client, e.g. ray://head:10001)")
    return match.group("host").strip("[]"), port


_PROBE = """
import json, sys
import ray
ray.init(address=sys.argv[1], include_dashboard=False, log_to_driver=False, configure_logging=False)
print(json.dumps([float(n.get("Resources", {}).get("CPU", 0.0)) for n in ray.nodes() if n.get("Alive")]))
ray.shutdown()
"""


def _probe_cluster(address: str, cpus_per_task: int) -> None:
    """Check that ``address`` answers (within :data:`CONNECT_TIMEOUT` s) and has a node large enough.

    A Ray driver that connects to an address where no Ray head answers waits for minutes and then
    exits the process; the probe runs in a child process with a deadline instead.
    """
    hostport = check_address(address)
    if hostport is not None:
        try:
            with socket.create_connection(hostport, timeout=min(10.0, CONNECT_TIMEOUT)):
                pass
        except OSError as e:
            reason = e.strerror or str(e) or type(e).__name__
            raise InputError(f"--address {address!r}: cannot reach {hostport[0]}:{hostport[1]} ({reason}); is the "
                             "Ray head running there (ray start --head) and the port open?") from None
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE, address], capture_output=True, text=True,
                              timeout=CONNECT_TIMEOUT)
    except subprocess.TimeoutExpired:
        raise InputError(f"--address {address!r}: no Ray cluster answered within {CONNECT_TIMEOUT:g} s (the port is "
                         "open, but is it a Ray head's GCS port, 6379 by default, or a Ray Client port?)") from None
    lines = done.stdout.strip().splitlines()
    try:
        node_cpus = [float(x) for x in json.loads(lines[-1])] if done.returncode == 0 and lines else None
    except (ValueError, TypeError):
        node_cpus = None
    if node_cpus is None:
        errors = [line for line in done.stderr.strip().splitlines() if "Error" in line] or done.stderr.strip().splitlines()
        reason = errors[-1][:300] if errors else f"exit status {done.returncode}"
        raise InputError(f"--address {address!r}: cannot connect to a Ray cluster: {reason}")
    _check_fits(node_cpus, cpus_per_task, f"the cluster at {address}")


def check_run(manifest, output_dir, *, address: str | None = None, cpus: int | None = None, cpus_per_task: int = 1,
              max_retries: int = 3) -> list[FitTask]:
    """Everything :func:`fit_many` checks before it starts Ray; the tasks it would run.

    The arguments' ranges, the output directory (writable, not a file), the manifest
    (:func:`read_manifest`), the address's form, and that a task fits on the local instance
    (``cpus_per_task <= cpus``). Raises :class:`InputError`; writes nothing, starts nothing.
    """
    from .limits import check_count

    check_count(cpus_per_task, "--cpus-per-task", high=4096, unit="CPUs per task")
    if cpus is not None:
        check_count(cpus, "--cpus", high=65536, unit="CPUs for the local Ray instance")
    check_count(max_retries, "--max-retries", low=0, high=MAX_RETRIES, unit="retries of a task whose worker died")
    check_writable(output_dir, "-o/--output", directory=True)
    tasks = read_manifest(manifest, output_dir, cpus_per_task=cpus_per_task)
    if address:
        check_address(address)
    else:
        local = cpus or os.cpu_count() or 1
        if cpus_per_task > local:
            raise InputError(f"--cpus-per-task {cpus_per_task}: no task could ever be scheduled: the local Ray "
                             f"instance has {local} CPU(s) ({'--cpus' if cpus else 'all of this machine'}); expected "
                             f"--cpus-per-task {local} or less, or a larger --cpus")
    return tasks


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
        An existing Ray cluster (``"auto"``, ``"HOST:PORT"`` or ``"ray://HOST:PORT"``), which must
        answer within :data:`CONNECT_TIMEOUT` seconds and have a node with ``cpus_per_task`` CPUs;
        default: a local Ray instance with ``cpus`` CPUs (default: all), started and stopped here.
    cpus_per_task : int
        CPUs (torch threads) per fit, at most ``cpus`` (a task never runs otherwise: refused).
    max_retries : int
        Retries of a task whose worker process died (a retry resumes from the checkpoint), 0..100.
    task_fn : callable
        What a task runs (default :func:`fit_one`).

    Returns
    -------
    list of dict
        One result row per source, in manifest order (:data:`RESULT_COLUMNS`).
    """
    output_dir = Path(output_dir)
    tasks = check_run(manifest, output_dir, address=address, cpus=cpus, cpus_per_task=cpus_per_task,
                      max_retries=max_retries)
    ray = optional_module("ray", "cluster", "dynbtf fit-many")
    if address and not ray.is_initialized():
        _probe_cluster(address, cpus_per_task)
    output_dir.mkdir(parents=True, exist_ok=True)
    for task in tasks:
        (output_dir / f".{task.name}.attempts").unlink(missing_ok=True)
    started_here = not ray.is_initialized()
    if started_here:
        init = {"address": address} if address else {"num_cpus": cpus or os.cpu_count() or 1}
        try:
            ray.init(**init, include_dashboard=False, log_to_driver=False, configure_logging=False)
        except Exception as e:  # a cluster that went away since the probe, a local instance that cannot start
            where = f"--address {address!r}" if address else "the local Ray instance"
            raise InputError(f"{where}: Ray could not start or connect: {_first_line(e)}") from None
    else:
        _check_fits(_node_cpus(ray), cpus_per_task, "the running Ray instance")
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
