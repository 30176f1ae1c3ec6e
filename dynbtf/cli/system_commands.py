"""``dynbtf system``: what dynbtf finds on this machine (versions, Mitsuba's LLVM, Chromium), for bug reports."""

from __future__ import annotations

import importlib
import os
import platform
import shutil
import subprocess
import sys

import typer

from .app import app

#: Executables the browser tests look for (tests/chromium.py), after ``$DYNBTF_CHROMIUM``.
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "chrome")


def _version(module: str) -> tuple[str, object | None]:
    """``(version text, module)``; the text says why when the module cannot be imported."""
    try:
        mod = importlib.import_module(module)
    except ImportError as e:
        return f"not installed ({e.name or module})", None
    except Exception as e:  # a broken installation: say so, go on
        return f"cannot be imported ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})", None
    return str(getattr(mod, "__version__", "unknown version")), mod


def _chromium() -> str:
    env = os.environ.get("DYNBTF_CHROMIUM")
    found = env if env and os.path.exists(env) else next(filter(None, map(shutil.which, CHROMIUM_NAMES)), None)
    if not found:
        return "not found (install Debian's 'chromium' or set DYNBTF_CHROMIUM; only the browser tests need it)"
    try:
        out = subprocess.run([found, "--version"], capture_output=True, text=True, timeout=20).stdout.strip()
    except (OSError, subprocess.SubprocessError) as e:
        out = f"--version failed: {type(e).__name__}"
    return f"{out or 'unknown version'} ({found})"


def system_report() -> list[tuple[str, str]]:
    """``(what, found)`` rows: Python, the packages, Mitsuba's LLVM (:mod:`dynbtf.jit.llvm`), Chromium."""
    from .._version import __version__

    rows = [("dynbtf", __version__), ("python", f"{platform.python_version()} ({sys.executable})"),
            ("platform", f"{platform.platform()}, {os.cpu_count()} CPUs")]
    from ..cpu import ISA_ENV, isa_description
    from ..errors import DynBTFError

    try:
        rows.append(("CPU level", isa_description()))
    except DynBTFError as e:
        rows.append(("CPU level", f"problem: {e}"))
    torch_version, torch = _version("torch")
    if torch is not None:
        cuda = torch.cuda.is_available()
        torch_version += f", CUDA {'available: ' + torch.cuda.get_device_name(0) if cuda else 'not available'}"
        torch_version += f"; CPU kernels {torch.backends.cpu.get_cpu_capability()}"
    rows.append(("torch", torch_version))
    from ..decoder import native

    rows.append(("native kernels", native.status("fused_mlp") + (f" ({ISA_ENV}={os.environ[ISA_ENV]})"
                                                                 if os.environ.get(ISA_ENV) else "")))
    for name in ("numpy", "numba", "ray"):
        rows.append((name, _version(name)[0]))
    from ..errors import DynBTFError
    from ..jit.llvm import MIN_LLVM, llvm_status

    try:
        status = llvm_status()  # first: it imports Dr.Jit, which loads LLVM and says why it cannot
    except DynBTFError:
        status = None
    except Exception as e:  # pragma: no cover - a broken installation
        status = {"version": None, "path": None, "requested": os.environ.get("DRJIT_LIBLLVM_PATH"),
                  "problem": f"cannot be checked ({type(e).__name__})"}
    drjit_version, drjit = _version("drjit")
    mitsuba_version, mitsuba = _version("mitsuba")
    rows += [("mitsuba", mitsuba_version), ("drjit", drjit_version)]
    if status is not None:
        version = ".".join(map(str, status["version"])) if status["version"] else "none loaded"
        where = status["path"] or (f"DRJIT_LIBLLVM_PATH={status['requested']}" if status["requested"] else "")
        verdict = f"problem: {status['problem']}" if status["problem"] else f"ok (>= {MIN_LLVM})"
        rows.append(("LLVM (Dr.Jit)", f"{version}{' (' + where + ')' if where else ''}; {verdict}"))
        rows.append(("DRJIT_LIBLLVM_PATH", status["requested"] or "not set"))
    if mitsuba is not None:
        try:
            rows.append(("mitsuba variants", ", ".join(mitsuba.variants())))
        except Exception as e:  # pragma: no cover - a broken installation
            rows.append(("mitsuba variants", f"cannot be listed ({type(e).__name__})"))
    rows.append(("chromium", _chromium()))
    return rows


@app.command()
def system() -> None:
    """Print what dynbtf finds here: Python, torch, numba, Mitsuba/Dr.Jit and the LLVM library Dr.Jit
    loaded (rendering needs LLVM 16+), Ray, Chromium. Paste it into a bug report.
    """
    rows = system_report()
    width = max(len(name) for name, _ in rows)
    for name, found in rows:
        typer.echo(f"{name.ljust(width)}  {found}")
