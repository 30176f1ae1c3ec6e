"""The CPU's instruction set: which vector unit dynbtf's kernels are built for, and how to force a lower one.

dynbtf's CPU work runs in four kinds of code: its native C++ kernels (:mod:`dynbtf.decoder.native`),
numba kernels, PyTorch's own kernels (ATen, oneDNN) and Intel MKL's matrix products. Each picks its
code path from the CPU at run time. This module names the **instruction-set levels** dynbtf builds
its native kernels for and can force on all four at once:

==============  ======================================================  ==============================
level           what the CPU needs                                      native build flags (x86-64)
==============  ======================================================  ==============================
``portable``    nothing (x86-64 SSE2; 128-bit NEON on ARM64)            ``-march=x86-64`` / ``armv8-a``
``avx2``        AVX2 + FMA (x86-64-v3: most laptops and desktops)       ``-march=x86-64-v3``
``avx512``      AVX-512 F/BW/DQ/VL (x86-64-v4)                          ``-march=x86-64-v4``
``avx512bf16``  AVX-512 with AVX512-BF16 (bfloat16 dot products)        ``-march=x86-64-v4 -mavx512bf16``
==============  ======================================================  ==============================

The **active level** is the best one the CPU has (:func:`hardware_isa`), unless the environment
variable ``DYNBTF_CPU_ISA`` names a lower one: ``DYNBTF_CPU_ISA=avx2`` on an AVX-512 machine runs
every dynbtf kernel as an AVX2 machine would, so the AVX2 path can be measured and tested anywhere.
Forcing works only before PyTorch, MKL and numba start: ``import dynbtf`` applies
:func:`isa_environment` to ``os.environ`` when ``DYNBTF_CPU_ISA`` is set (``ATEN_CPU_CAPABILITY``,
``MKL_ENABLE_INSTRUCTIONS``, ``MKL_CBWR``, ``ONEDNN_MAX_CPU_ISA``, ``NUMBA_CPU_NAME``, and a cache of
``torch.compile``'s kernels of the level's own, :func:`inductor_cache_dir`; variables the user set already are
kept), and :func:`check_forced_environment` says when a library was loaded before that. It also
asks MKL for reproducible results whatever the level (``MKL_CBWR``, :data:`MKL_REPRODUCIBLE`).
A level above the CPU's is an error, not a silent fallback.

>>> ISAS
('portable', 'avx2', 'avx512', 'avx512bf16')
>>> isa_environment("avx2")["ATEN_CPU_CAPABILITY"]
'avx2'
"""

from __future__ import annotations

import os
import platform
import sys
from functools import lru_cache

from .errors import InputError

__all__ = ["ISAS", "ISA_ENV", "cpu_features", "hardware_isa", "active_isa", "isa_environment", "inductor_cache_dir",
           "apply_isa_environment", "check_forced_environment", "isa_description", "vector_width"]

#: The levels, lowest first.
ISAS = ("portable", "avx2", "avx512", "avx512bf16")
#: The environment variable that forces a level.
ISA_ENV = "DYNBTF_CPU_ISA"

#: x86 CPU flags (Linux ``/proc/cpuinfo`` names) each level needs, on top of the level below it.
_NEEDS = {"avx2": {"avx2", "fma", "f16c", "bmi2"},
          "avx512": {"avx512f", "avx512bw", "avx512dq", "avx512vl", "avx512cd"},
          "avx512bf16": {"avx512_bf16"}}

#: What each level tells the other libraries (PyTorch's ATen, Intel MKL, oneDNN, numba/LLVM).
_LIBRARY_SETTINGS = {
    "portable": {"ATEN_CPU_CAPABILITY": "default", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2", "MKL_CBWR": "SSE4_2,STRICT",
                 "ONEDNN_MAX_CPU_ISA": "SSE41", "NUMBA_CPU_NAME": "x86-64"},
    "avx2": {"ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2", "MKL_CBWR": "AVX2,STRICT",
             "ONEDNN_MAX_CPU_ISA": "AVX2", "NUMBA_CPU_NAME": "haswell"},
    "avx512": {"ATEN_CPU_CAPABILITY": "avx512", "MKL_ENABLE_INSTRUCTIONS": "AVX512", "MKL_CBWR": "AVX512,STRICT",
               "ONEDNN_MAX_CPU_ISA": "AVX512_CORE", "NUMBA_CPU_NAME": "skylake-avx512"},
    "avx512bf16": {"ATEN_CPU_CAPABILITY": "avx512", "MKL_ENABLE_INSTRUCTIONS": "AVX512", "MKL_CBWR": "AVX512,STRICT",
                   "ONEDNN_MAX_CPU_ISA": "AVX512_CORE_BF16", "NUMBA_CPU_NAME": "cooperlake"},
}
#: MKL's conditional numerical reproducibility, set unless the user set it: with MKL's AVX2 kernels a product's
#: rounding otherwise depends on its operands' memory alignment and on the calling thread (measured: one ulp
#: between two calls on the same data), which would make two runs of a fit differ. The price is some of a large
#: matmul's speed: MKL forgoes the optimizations whose rounding depends on alignment and threads.
MKL_REPRODUCIBLE = "AUTO,STRICT"


def _is_x86() -> bool:
    return platform.machine().lower() in ("x86_64", "amd64", "i686", "i386", "x86")


@lru_cache(maxsize=1)
def cpu_features() -> frozenset[str]:
    """The CPU's feature flags as Linux names them (``/proc/cpuinfo``: ``avx2``, ``avx512_bf16``, ``asimd``, ...).

    Elsewhere (macOS, Windows) LLVM's view of the host CPU (llvmlite, which numba brings) answers, its names
    mapped to Linux's; without it the set is empty and the level is ``portable``.
    """
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    try:
        from llvmlite import binding

        host = binding.get_host_cpu_features()
    except Exception:  # no llvmlite, or it cannot tell
        return frozenset()
    return frozenset(name.replace("avx512bf16", "avx512_bf16") for name, on in host.items() if on)


def hardware_isa(features: frozenset[str] | None = None) -> str:
    """The best level of :data:`ISAS` the CPU (its ``features``, default :func:`cpu_features`) runs.

    >>> hardware_isa(frozenset({"avx2", "fma", "f16c", "bmi2"}))
    'avx2'
    >>> hardware_isa(frozenset({"sse2"}))
    'portable'
    """
    if features is None:
        if not _is_x86():
            return "portable"
        features = cpu_features()
    best = "portable"
    for isa in ISAS[1:]:
        if not _NEEDS[isa] <= features:
            break
        best = isa
    return best


def _requested() -> str | None:
    value = os.environ.get(ISA_ENV, "").strip().lower()
    if value in ("", "auto", "native"):
        return None
    if value not in ISAS:
        raise InputError(f"{ISA_ENV}={os.environ[ISA_ENV]!r}: expected one of {', '.join(ISAS)} or 'auto'")
    return value


def active_isa() -> str:
    """The level dynbtf's kernels run at: ``$DYNBTF_CPU_ISA`` if set, else :func:`hardware_isa`.

    :class:`~dynbtf.errors.InputError` when ``$DYNBTF_CPU_ISA`` is not a level, or is one the CPU lacks.
    """
    hardware = hardware_isa()
    requested = _requested()
    if requested is None:
        return hardware
    if ISAS.index(requested) > ISAS.index(hardware):
        raise InputError(f"{ISA_ENV}={requested}: this CPU ({platform.machine()}) runs at most '{hardware}'; "
                         f"choose one of {', '.join(ISAS[:ISAS.index(hardware) + 1])}")
    return requested


def vector_width(isa: str) -> int:
    """float32 lanes of the level's vectors: 16 (AVX-512), 8 (AVX2), 4 (portable: SSE2 / NEON).

    >>> vector_width("avx2")
    8
    """
    return {"portable": 4, "avx2": 8, "avx512": 16, "avx512bf16": 16}[isa]


def isa_environment(isa: str) -> dict[str, str]:
    """The environment variables that make a process run at level ``isa``: ``DYNBTF_CPU_ISA`` and the
    settings of PyTorch (``ATEN_CPU_CAPABILITY``, and :func:`inductor_cache_dir` for ``torch.compile``), MKL, oneDNN
    and numba that match it (x86-64 only; on other machines only ``DYNBTF_CPU_ISA``). Give them to a new process
    (``subprocess``'s ``env``)."""
    if isa not in ISAS:
        raise InputError(f"isa: expected one of {', '.join(ISAS)}, got {isa!r}")
    env = {ISA_ENV: isa}
    if _is_x86():
        env |= _LIBRARY_SETTINGS[isa] | {"TORCHINDUCTOR_CACHE_DIR": inductor_cache_dir(isa)}
    return env


def inductor_cache_dir(isa: str) -> str:
    """The directory of PyTorch Inductor's compiled kernels (``torch.compile``, ``--compile kernels``) at a forced
    level: one per level, beside Inductor's own default. Inductor generates each level's vector code (it reads
    ``ATEN_CPU_CAPABILITY``) but its cache does not tell the levels apart: a kernel compiled at the CPU's level and
    loaded at a forced AVX2 fails (``RuntimeError: tuple args required``).

    >>> inductor_cache_dir("avx2").endswith("-dynbtf-avx2")
    True
    """
    import getpass
    import re
    import tempfile

    try:
        user = getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (some containers)
        user = str(os.getuid()) if hasattr(os, "getuid") else "user"
    return os.path.join(tempfile.gettempdir(), f"torchinductor_{re.sub(r'[^A-Za-z0-9_.-]', '_', user)}-dynbtf-{isa}")


def apply_isa_environment() -> None:
    """When ``$DYNBTF_CPU_ISA`` forces a level, set the other libraries' variables of :func:`isa_environment`
    in ``os.environ`` (keeping any the user set); in any case MKL's reproducible mode (:data:`MKL_REPRODUCIBLE`).
    Called by ``import dynbtf``, before PyTorch or numba load."""
    try:
        requested = _requested()
    except InputError:
        return  # reported by active_isa() where a kernel is chosen, not at import
    if requested is None:
        if _is_x86():
            os.environ.setdefault("MKL_CBWR", MKL_REPRODUCIBLE)
        return
    for key, value in isa_environment(requested).items():
        os.environ.setdefault(key, value)


def check_forced_environment() -> str | None:
    """Why the forced level does not hold in this process, or None: PyTorch (or numba) loaded before
    ``import dynbtf`` could set their variables, so they run at another level than ``$DYNBTF_CPU_ISA``."""
    requested = _requested()
    if requested is None or not _is_x86():
        return None
    if "torch" in sys.modules:
        capability = sys.modules["torch"].backends.cpu.get_cpu_capability().lower()
        want = _LIBRARY_SETTINGS[requested]["ATEN_CPU_CAPABILITY"]
        if capability != want:
            return (f"{ISA_ENV}={requested}, but PyTorch was loaded before dynbtf and runs its {capability!r} kernels; "
                    f"set ATEN_CPU_CAPABILITY={want} too, or import dynbtf first")
    return None


def isa_description(isa: str | None = None) -> str:
    """One line: the active level, whether it was forced, and the hardware's.

    e.g. ``"avx2 (forced by DYNBTF_CPU_ISA; the CPU has avx512bf16), 8 float32 lanes"``."""
    isa = isa or active_isa()
    hardware = hardware_isa()
    how = f"forced by {ISA_ENV}; the CPU has {hardware}" if isa != hardware else "the CPU's best"
    return f"{isa} ({how}), {vector_width(isa)} float32 lanes"
