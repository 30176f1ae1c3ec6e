"""Native CPU kernels: C++ sources shipped with the package, compiled on first use, loaded with ctypes.

A kernel ``NAME`` is the file ``dynbtf/decoder/native/NAME.cpp``. :func:`load_library` compiles it with
the system C++ compiler (``$CXX`` or ``g++``/``c++``/``clang++``) for the machine it runs on
(``-O3 -march=native``), caches the shared library and returns a :class:`ctypes.CDLL`.

* **Cache**: ``$DYNBTF_NATIVE_CACHE``, else ``$XDG_CACHE_HOME/dynbtf/decoder/native``, else
  ``~/.cache/dynbtf/decoder/native``. The file name carries a hash of the source, the compiler's version,
  the flags and the CPU's feature flags, so an edited source, another compiler or another CPU
  (a shared home directory) gets its own build. Builds are written to a temporary file and
  renamed, so concurrent processes never load a half-written library.
* **No compiler, or a failed build**: :func:`load_library` returns ``None`` and
  :func:`status` says why; callers fall back to their PyTorch code path, which computes the same
  values (slower). ``DYNBTF_NATIVE=0`` disables native kernels.

The kernels themselves are plain C ABI functions taking pointers to contiguous float32 CPU
buffers (see each source's header comment); their Python wrappers live next to the code that
uses them (:mod:`dynbtf.decoder.fused_mlp`).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

__all__ = ["load_library", "status", "cache_dir"]

_SOURCE_DIR = Path(__file__).resolve().parent
_FLAGS = ["-O3", "-std=c++17", "-shared", "-fPIC", "-fno-math-errno"]
_LOCK = threading.Lock()
_LOADED: dict[str, ctypes.CDLL | None] = {}
_STATUS: dict[str, str] = {}


def cache_dir() -> Path:
    """Directory holding compiled kernels (see the module docstring)."""
    if os.environ.get("DYNBTF_NATIVE_CACHE"):
        return Path(os.environ["DYNBTF_NATIVE_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "dynbtf" / "native"


def _compiler() -> str | None:
    for candidate in filter(None, [os.environ.get("CXX"), "g++", "c++", "clang++"]):
        path = shutil.which(candidate)
        if path:
            return path
    return None


def _cpu_signature() -> str:
    """The CPU's feature flags (Linux), or the platform's processor string."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return f"{platform.machine()} {platform.processor()}"


def _compile(compiler: str, source: Path, target: Path) -> str | None:
    """Compile ``source`` into ``target`` (atomically); returns an error message or None."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=target.name + ".", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        errors = []
        for arch in (["-march=native"], ["-mcpu=native"], []):
            result = subprocess.run([compiler, *_FLAGS, *arch, str(source), "-o", tmp],
                                    capture_output=True, text=True, timeout=300)
            if result.returncode == 0:
                os.chmod(tmp, 0o755)
                os.replace(tmp, target)
                return None
            errors.append(result.stderr.strip().splitlines()[-1:] or ["(no message)"])
        return f"{compiler} failed: {errors[-1][0]}"
    except (OSError, subprocess.SubprocessError) as e:
        return f"{compiler} could not run: {e}"
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def load_library(name: str) -> ctypes.CDLL | None:
    """The compiled kernel ``dynbtf/decoder/native/<name>.cpp`` as a :class:`ctypes.CDLL`, or None if unavailable.

    Compiles on the first call in a machine's lifetime (a few seconds), then loads from the cache.
    Thread-safe; the result is remembered for the process.
    """
    with _LOCK:
        if name in _LOADED:
            return _LOADED[name]
        library = None
        source = _SOURCE_DIR / f"{name}.cpp"
        compiler = _compiler()
        if os.environ.get("DYNBTF_NATIVE", "1") == "0":
            _STATUS[name] = "disabled by DYNBTF_NATIVE=0"
        elif not source.is_file():
            _STATUS[name] = f"source {source} is missing"
        elif compiler is None:
            _STATUS[name] = "no C++ compiler found (set CXX, or install g++)"
        else:
            try:
                version = subprocess.run([compiler, "--version"], capture_output=True, text=True,
                                         timeout=60).stdout
            except (OSError, subprocess.SubprocessError):
                version = ""
            key = hashlib.sha256("\0".join([source.read_text(), compiler, version, " ".join(_FLAGS),
                                            _cpu_signature()]).encode()).hexdigest()[:20]
            target = cache_dir() / f"{name}-{key}.so"
            error = None if target.is_file() else _compile(compiler, source, target)
            if error is None:
                try:
                    library = ctypes.CDLL(str(target))
                    _STATUS[name] = f"loaded {target}"
                except OSError as e:
                    _STATUS[name] = f"could not load {target}: {e}"
            else:
                _STATUS[name] = error
        _LOADED[name] = library
        return library


def status(name: str) -> str:
    """Why ``name`` is (not) available: ``"loaded <path>"`` or the reason it is not."""
    load_library(name)
    return _STATUS.get(name, "not loaded")
