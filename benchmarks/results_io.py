"""What every benchmark records with its numbers: the machine, the commit, the command; and writing them as JSON.

The JSON files in ``benchmarks/results/`` are the data behind the docs' measured tables (``benchmarks/tables.py``).
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def cpu_model() -> str:
    """The CPU's model name (Linux), else the platform's processor string."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def commit() -> str | None:
    """The repository's short commit hash, if this is a git checkout."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent, timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def header(benchmark: str, script: str) -> dict:
    """The record's common fields: the benchmark, the command that ran it (quoted as a shell needs it), the commit
    and the machine."""
    from dynbtf.cpu import hardware_isa

    return {"benchmark": benchmark, "command": shlex.join(["python", f"benchmarks/{script}", *sys.argv[1:]]),
            "commit": commit(), "cpu": cpu_model(), "cpu_isa": hardware_isa(), "cores": os.cpu_count()}


def model_record(path: str | Path) -> dict:
    """What a benchmark records of a fitted model it read: its file name, kind, source, training and held-out PSNR
    (from the model file's provenance; null where it does not say)."""
    from dynbtf.representations.model_file import read_model_metadata

    meta = read_model_metadata(path)
    prov = meta.get("provenance") or {}
    history = prov.get("history") or []
    psnr = prov.get("held_out_psnr_monitor")
    if psnr is None and history:
        psnr = history[-1].get("held_out_psnr")
    seconds = prov.get("training_seconds")
    source = prov.get("source") or {}
    size = [source["height"], source["width"]] if "height" in source and "width" in source else None
    return {"file": Path(path).name, "kind": meta.get("kind"), "source": source.get("name"), "size": size,
            "epochs": prov.get("epochs_completed"), "training_minutes": None if seconds is None else seconds / 60,
            "held_out_psnr": psnr}


def spread(values: list[float]) -> dict:
    """``{"mean", "range", "per_seed"}`` of one number measured per seed (the tables write it as the mean and its
    min-max)."""
    return {"mean": float(sum(values) / len(values)), "range": [float(min(values)), float(max(values))],
            "per_seed": [float(v) for v in values]}


def panel_strip(panels, gap: int = 6):
    """``panels`` (images ``(H, W_i, 3)`` of one height) side by side, ``gap`` white columns between them."""
    import numpy as np

    white = np.ones((panels[0].shape[0], gap, 3), dtype=np.float32)
    return np.concatenate([x for panel in panels for x in (panel, white)][:-1], 1)


def write_part(path: Path, part: str, script: str, measured: dict) -> None:
    """Set part ``part`` of the JSON file ``path`` (read, or started as ``{"benchmark": stem}``; its other parts
    kept) to the command and machine of this run (:func:`header`, run by ``script``) followed by ``measured``, and
    write the file atomically."""
    data = json.loads(path.read_text()) if path.exists() else {"benchmark": path.stem}
    run = header(path.stem, script)
    data[part] = {key: run[key] for key in ("command", "commit", "cpu", "cpu_isa", "cores")} | measured
    write_result(path, data)


def write_result(path: Path, result: dict) -> None:
    """Write ``result`` as JSON to ``path`` (atomically: a temporary file renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n")
    os.replace(tmp, path)
    print(f"wrote {path}")
