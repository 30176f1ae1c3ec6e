"""What every benchmark records with its numbers: the machine, the commit, the command; and writing them as JSON.

The JSON files in ``benchmarks/results/`` are the data behind the docs' measured tables (``benchmarks/tables.py``).
"""

from __future__ import annotations

import json
import os
import platform
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
    """The record's common fields: the benchmark, the command that ran it, the commit and the machine."""
    from dynbtf.cpu import hardware_isa

    return {"benchmark": benchmark, "command": " ".join(["python", f"benchmarks/{script}", *sys.argv[1:]]),
            "commit": commit(), "cpu": cpu_model(), "cpu_isa": hardware_isa(), "cores": os.cpu_count()}


def write_result(path: Path, result: dict) -> None:
    """Write ``result`` as JSON to ``path`` (atomically: a temporary file renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n")
    os.replace(tmp, path)
    print(f"wrote {path}")
