"""Native CPU kernels: C++ sources shipped with the package, compiled on first use, loaded with ctypes.

A kernel ``NAME`` is the file ``dynbtf/decoder/native/NAME.cpp``. :func:`load_library` compiles it with
the system C++ compiler (``$CXX`` or ``g++``/``c++``/``clang++``) for one instruction-set level of
:mod:`dynbtf.cpu` (by default the active one: the CPU's best, or the one ``$DYNBTF_CPU_ISA`` forces),
caches the shared library and returns a :class:`ctypes.CDLL`. The level's flags (:data:`ISA_FLAGS`) are
explicit, never ``-march=native``: a build is the same on every machine of its level, and each level
can be built and run on any CPU that has it (``load_library("fused_mlp", "avx2")`` on an AVX-512 CPU).

* **Cache**: ``$DYNBTF_NATIVE_CACHE``, else ``$XDG_CACHE_HOME/dynbtf/native``, else
  ``~/.cache/dynbtf/native``. The file name carries the level and a hash of the source, the compiler's
  version and the flags, so an edited source or another compiler gets its own build. Builds are
  written to a temporary file and renamed, so concurrent processes never load a half-written library.
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

__all__ = ["load_library", "status", "cache_dir", "ISA_FLAGS", "isa_flags", "fma_peak_flops"]

_SOURCE_DIR = Path(__file__).resolve().parent
_FLAGS = ["-O3", "-std=c++17", "-ffp-contract=fast", "-shared", "-fPIC", "-fno-math-errno"]
_LOCK = threading.Lock()
_LOADED: dict[tuple[str, str], ctypes.CDLL | None] = {}
_STATUS: dict[tuple[str, str], str] = {}

#: Compiler flags of each instruction-set level of :mod:`dynbtf.cpu` on x86-64 (explicit features rather than
#: ``-march=x86-64-v3`` etc., which older compilers lack; ``-mtune=generic``: no one CPU model's scheduling).
ISA_FLAGS = {
    "portable": ["-mtune=generic"],
    "avx2": ["-mavx2", "-mfma", "-mf16c", "-mbmi2", "-mtune=generic"],
    "avx512": ["-mavx2", "-mfma", "-mf16c", "-mbmi2", "-mavx512f", "-mavx512bw", "-mavx512dq", "-mavx512vl",
               "-mavx512cd", "-mprefer-vector-width=512", "-mtune=generic"],
    "avx512bf16": ["-mavx2", "-mfma", "-mf16c", "-mbmi2", "-mavx512f", "-mavx512bw", "-mavx512dq", "-mavx512vl",
                   "-mavx512cd", "-mavx512bf16", "-mprefer-vector-width=512", "-mtune=generic"],
}


def isa_flags(isa: str) -> list[str]:
    """The compiler flags of level ``isa`` on this machine's architecture (ARM64: ``-march=armv8-a``, whose
    128-bit NEON is the portable level; other architectures: none)."""
    machine = platform.machine().lower()
    if machine in ("x86_64", "amd64"):
        return list(ISA_FLAGS[isa])
    if isa != "portable":
        raise ValueError(f"instruction-set level {isa!r} exists on x86-64 only")
    return ["-march=armv8-a"] if machine in ("aarch64", "arm64") else []


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


def _compile(compiler: str, flags: list[str], source: Path, target: Path) -> str | None:
    """Compile ``source`` into ``target`` (atomically) with ``flags``; returns an error message or None."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=target.name + ".", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        result = subprocess.run([compiler, *flags, str(source), "-o", tmp], capture_output=True, text=True,
                                timeout=300)
        if result.returncode == 0:
            os.chmod(tmp, 0o755)
            os.replace(tmp, target)
            return None
        return f"{compiler} failed: {(result.stderr.strip().splitlines() or ['(no message)'])[-1]}"
    except (OSError, subprocess.SubprocessError) as e:
        return f"{compiler} could not run: {e}"
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


_NOT_LOADED = object()


def load_library(name: str, isa: str | None = None) -> ctypes.CDLL | None:
    """The compiled kernel ``dynbtf/decoder/native/<name>.cpp`` for instruction-set level ``isa`` (default: the
    active one, :func:`dynbtf.cpu.active_isa`) as a :class:`ctypes.CDLL`, or None if unavailable.

    Compiles on the first call in a machine's lifetime (a few seconds), then loads from the cache.
    Thread-safe; the result is remembered for the process. A level the CPU lacks raises
    :class:`~dynbtf.errors.InputError` (its code would stop the process with an illegal instruction).
    """
    from ...cpu import ISAS, active_isa, hardware_isa
    from ...errors import InputError

    isa = isa or active_isa()
    if isa not in ISAS:
        raise InputError(f"isa: expected one of {', '.join(ISAS)}, got {isa!r}")
    if ISAS.index(isa) > ISAS.index(hardware_isa()):
        raise InputError(f"isa={isa!r}: this CPU runs at most {hardware_isa()!r}")
    loaded = _LOADED.get((name, isa), _NOT_LOADED)  # a library loaded before: no lock
    if loaded is not _NOT_LOADED:
        return loaded
    key_name = (name, isa)
    with _LOCK:
        if key_name in _LOADED:
            return _LOADED[key_name]
        library = None
        source = _SOURCE_DIR / f"{name}.cpp"
        compiler = _compiler()
        if os.environ.get("DYNBTF_NATIVE", "1") == "0":
            _STATUS[key_name] = "disabled by DYNBTF_NATIVE=0"
        elif not source.is_file():
            _STATUS[key_name] = f"source {source} is missing"
        elif compiler is None:
            _STATUS[key_name] = "no C++ compiler found (set CXX, or install g++)"
        else:
            try:
                version = subprocess.run([compiler, "--version"], capture_output=True, text=True,
                                         timeout=60).stdout
            except (OSError, subprocess.SubprocessError):
                version = ""
            flags = _FLAGS + isa_flags(isa)
            key = hashlib.sha256("\0".join([source.read_text(), compiler, version, " ".join(flags)]).encode()
                                 ).hexdigest()[:20]
            target = cache_dir() / f"{name}-{isa}-{key}.so"
            error = None if target.is_file() else _compile(compiler, flags, source, target)
            if error is None:
                try:
                    library = ctypes.CDLL(str(target))
                    _STATUS[key_name] = f"loaded {target} ({isa})"
                except OSError as e:
                    _STATUS[key_name] = f"could not load {target}: {e}"
            else:
                _STATUS[key_name] = error
        _LOADED[key_name] = library
        return library


def status(name: str, isa: str | None = None) -> str:
    """Why ``name`` is (not) available at level ``isa`` (default: the active one): ``"loaded <path> (<isa>)"``
    or the reason it is not."""
    from ...cpu import active_isa

    isa = isa or active_isa()
    load_library(name, isa)
    return _STATUS.get((name, isa), "not loaded")


def fma_peak_flops(isa: str | None = None, threads: int = 1, seconds: float = 0.5) -> float | None:
    """Measured fused multiply-add throughput (FLOP/s, 2 per lane per FMA) of ``threads`` threads at level ``isa``
    (default: the active one): independent FMAs on the level's vectors held in registers
    (``dynbtf/decoder/native/fma_peak.cpp``), the best of three runs about ``seconds`` long each (a run that
    another process interrupts measures less than the peak). The peak a kernel's "share" is measured against;
    None without a compiler."""
    from concurrent.futures import ThreadPoolExecutor
    import time

    library = load_library("fma_peak", isa)
    if library is None:
        return None
    library.dynbtf_fma_loop.restype = ctypes.c_float
    library.dynbtf_fma_loop.argtypes = [ctypes.c_int64]
    library.dynbtf_fma_lanes.restype = ctypes.c_int
    library.dynbtf_fma_chains.restype = ctypes.c_int
    lanes, chains = library.dynbtf_fma_lanes(), library.dynbtf_fma_chains()
    iterations = 1 << 16
    while True:  # calibrate on one thread: a run of about seconds / 4
        t0 = time.perf_counter()
        library.dynbtf_fma_loop(iterations)
        if time.perf_counter() - t0 > seconds / 4 or iterations > 1 << 34:
            break
        iterations *= 4
    elapsed = float("inf")
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for _ in range(3):
            t0 = time.perf_counter()
            list(pool.map(library.dynbtf_fma_loop, [iterations] * threads))
            elapsed = min(elapsed, time.perf_counter() - t0)
    return 2.0 * lanes * chains * iterations * threads / elapsed
