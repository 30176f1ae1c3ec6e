"""The LLVM library behind Mitsuba's ``llvm_*`` variants: found, and recent enough, before any kernel compiles.

Dr.Jit's CPU back end compiles every kernel with the system's LLVM shared library, which it
loads at run time (``DRJIT_LIBLLVM_PATH`` names it; otherwise Dr.Jit searches the usual
names, ``libLLVM.so`` and ``libLLVM-NN.so``). Dr.Jit itself refuses LLVM 14 and older; LLVM 15
loads, but the kernels of Mitsuba 3.9 (``fminimum``/``fmaximum`` instructions) make LLVM 15 abort
the whole process while compiling ("LLVM ERROR: Cannot select: f32 = fminimum"). So
:func:`check_llvm` asks Dr.Jit which LLVM it loaded (loading it is all that asking does: no
kernel is compiled) and raises a clear :class:`~dynbtf.errors.MissingDependencyError` naming
the version and path found and the fix, before any ``llvm_*`` variant is set.

``dynbtf system`` prints :func:`llvm_status` with the other versions.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile

from ..errors import MissingDependencyError, optional_module

__all__ = ["MIN_LLVM", "llvm_status", "check_llvm", "LLVM_FIX", "apply_isa_target", "LLVM_TARGETS"]

#: Oldest LLVM major version that compiles Mitsuba 3.9's kernels (15 aborts on ``fminimum``).
MIN_LLVM = 16
#: What to do about a missing or old LLVM.
LLVM_FIX = ("install LLVM 16 or newer (e.g. apt-get install libllvm19) or point DRJIT_LIBLLVM_PATH at its "
            "libLLVM shared library (e.g. DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1); "
            "`dynbtf system` shows what Dr.Jit found")

_STATUS: dict | None = None


def _flush_c_stdio() -> None:
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL(None).fflush(None)


@contextlib.contextmanager
def _captured_output():
    """Collect what C code writes to file descriptors 1 and 2 (Dr.Jit's loader messages) in ``lines``."""
    lines: list[str] = []
    saved: list[tuple[int, int]] = []
    with tempfile.TemporaryFile() as sink:
        try:
            for stream, fd in ((sys.stdout, 1), (sys.stderr, 2)):
                with contextlib.suppress(Exception):
                    stream.flush()
                try:
                    saved.append((fd, os.dup(fd)))
                    os.dup2(sink.fileno(), fd)
                except OSError:  # no such descriptor (an embedding host): nothing to capture there
                    pass
            yield lines
        finally:
            _flush_c_stdio()
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            lines.extend(sink.read().decode("utf-8", "replace").splitlines())


def _loaded_library() -> str | None:
    """Path of the libLLVM mapped into this process (Linux), else ``None``."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            for line in maps:
                name = line.rstrip("\n").split(" ")[-1]
                if "libLLVM" in os.path.basename(name):
                    return name
    except OSError:
        pass
    return None


def _named_major(path: str | None) -> int | None:
    """The LLVM major version in the file name of an existing library ``path`` (``libLLVM-14.so``,
    ``libLLVM.so.19.1``; a symbolic link's target's name), else None."""
    if not path or not os.path.isfile(path):
        return None
    named = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(os.path.realpath(path)))
    return int(named.group(1)) if named else None


def llvm_status(refresh: bool = False) -> dict:
    """What Dr.Jit's LLVM back end found: ``{"version": (major, minor, patch) or None, "path": str or None,
    "requested": DRJIT_LIBLLVM_PATH or None, "messages": [Dr.Jit's loader lines], "problem": str or None}``.

    ``problem`` is ``None`` when the LLVM back end is usable for the plugin (LLVM >= :data:`MIN_LLVM`),
    else the one-line reason. Loads the library (once per process; not at all when ``DRJIT_LIBLLVM_PATH`` names an
    LLVM older than :data:`MIN_LLVM` in its file name, which is refused as it is); compiles nothing.
    """
    global _STATUS
    if _STATUS is not None and not refresh:
        return _STATUS
    requested = os.environ.get("DRJIT_LIBLLVM_PATH") or None
    named = _named_major(requested)
    if named is not None and named < MIN_LLVM:  # refused from its name: not loaded into this process at all
        _STATUS = {"version": None, "path": None, "requested": requested,
                   "messages": [f"the LLVM version ({named}) named by DRJIT_LIBLLVM_PATH is too old (from the file "
                                "name; not loaded)"],
                   "problem": (f"DRJIT_LIBLLVM_PATH names LLVM {named} ({requested}), which is too old (the dynbtf "
                               f"plugin needs LLVM {MIN_LLVM} or newer)")}
        return _STATUS
    # Dr.Jit loads LLVM when it is imported, and says why it fails on standard output/error (C code):
    # collected here when this is the first import (a library named older than MIN_LLVM was refused above)
    with _captured_output() as messages:
        dr = optional_module("drjit", "render", "rendering with Mitsuba 3")
        try:
            version = tuple(int(x) for x in dr.detail.llvm_version())
        except Exception:  # an older Dr.Jit without llvm_version, or a loader failure
            version = (-1, -1, -1)
    found = version if version and version[0] >= 0 else None
    path = _loaded_library() if found else None
    old = next((m for m in messages if "too old" in m), None)
    problem = None
    if found is None:
        major = re.search(r"LLVM version \((\d+)\)", old or "")
        if major:
            problem = (f"Dr.Jit found LLVM {major.group(1)}{' at ' + requested if requested else ''}, which is too old "
                       f"(the dynbtf plugin needs LLVM {MIN_LLVM} or newer)")
        elif requested:
            why = next((m.split(": ")[-1].rstrip("!. ") for m in messages if "Unable to load" in m), "")
            problem = f"Dr.Jit could not load the LLVM library DRJIT_LIBLLVM_PATH={requested}" + (f" ({why})" if why else "")
        else:
            problem = "Dr.Jit found no LLVM library on this machine"
    elif found[0] < MIN_LLVM:
        problem = (f"Dr.Jit loaded LLVM {'.'.join(map(str, found))} ({path or requested or 'path unknown'}), "
                   f"which aborts while compiling Mitsuba's kernels (LLVM ERROR: Cannot select: fminimum); the dynbtf "
                   f"plugin needs LLVM {MIN_LLVM} or newer")
    _STATUS = {"version": found, "path": path, "requested": requested, "messages": messages, "problem": problem}
    return _STATUS


def check_llvm(variant: str | None = "llvm_ad_rgb") -> None:
    """Raise :class:`~dynbtf.errors.MissingDependencyError` if ``variant`` is an ``llvm_*`` variant and Dr.Jit's
    LLVM is missing or older than :data:`MIN_LLVM`; call it before ``mi.set_variant`` (no kernel compiled yet).

    Other variants (``cuda_*``, ``scalar_*``) pass without looking.
    """
    if variant is not None and not str(variant).startswith("llvm"):
        return
    status = llvm_status()
    if status["problem"]:
        error = MissingDependencyError(f"Mitsuba variant {variant or 'llvm_ad_rgb'}: {status['problem']}; {LLVM_FIX}")
        # an LLVM Dr.Jit cannot use is mapped into the process: its shutdown at exit may hang, so the command
        # line leaves without finalizing (dynbtf.cli.main)
        error.leave_without_finalizing = status["version"] is not None or any("too old" in m
                                                                             for m in status["messages"])
        raise error
    apply_isa_target()


#: Dr.Jit's LLVM target (CPU name, features, vector width) per forced level of :mod:`dynbtf.cpu` (x86-64).
LLVM_TARGETS = {
    "portable": ("x86-64", "+sse2,-avx,-avx2,-fma,-avx512f", 4),
    "avx2": ("haswell", "+avx,+avx2,+fma,+f16c,+bmi,+bmi2,+popcnt,+sse4.2,-avx512f", 8),
    "avx512": ("skylake-avx512", "+avx2,+fma,+avx512f,+avx512bw,+avx512dq,+avx512vl,+avx512cd", 16),
}
_TARGET_SET: str | None = None


def apply_isa_target() -> str | None:
    """Where ``DYNBTF_CPU_ISA`` forces a level below the CPU's (:mod:`dynbtf.cpu`), make Dr.Jit compile its LLVM
    kernels for it too (its C function ``jit_llvm_set_target``, before a kernel is compiled), so that the plugin's
    speed on an AVX2 machine can be measured on one with AVX-512. Returns the target set (``"haswell"``, ...),
    or None when nothing is forced (or this Dr.Jit has no such function: the kernels then use the CPU's own)."""
    global _TARGET_SET
    from ..cpu import ISA_ENV, active_isa, hardware_isa

    if _TARGET_SET is not None or not os.environ.get(ISA_ENV):
        return _TARGET_SET
    isa = active_isa()
    if isa == hardware_isa() or isa not in LLVM_TARGETS:
        return None
    import ctypes

    dr = optional_module("drjit", "render", "rendering with Mitsuba 3")
    try:
        core = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))
        set_target = core._Z19jit_llvm_set_targetPKcS0_j  # jit_llvm_set_target(const char*, const char*, uint32_t)
    except (OSError, AttributeError):
        return None
    set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    set_target.restype = None
    cpu, features, width = LLVM_TARGETS[isa]
    set_target(cpu.encode(), features.encode(), width)
    _TARGET_SET = cpu
    return cpu
