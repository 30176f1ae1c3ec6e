"""Limits on what a command may ask for: scales and uv ranges, image sizes, samples, memory.

One place decides them for every command (``dynbtf synth``, ``render``, ``export``) and the
library functions behind them, so that an extreme value is refused up front with one clear
line (naming the option, the value, the limit and what to change) instead of a NaN image, a
process killed for memory, or a run that never ends.

Scales and uv
-------------
The library's rule (:func:`dynbtf.synthesis.base.check_uv`): a position is answered exactly
while ``|uv| * scale < 2**52`` exemplar repeats (:data:`MAX_REPEATS`), beyond which float64
resolves no fraction of a repeat. Backends that compute ``uv * scale`` in float32 (Mitsuba's
mesh uv in the ``dynbtf`` plugin, the WebGL shader's local uv) resolve no fraction of a repeat
beyond ``2**24`` repeats (:data:`FLOAT32_MAX_REPEATS`); their texels are resolved only below
``2**23 / W`` repeats for a ``W``-texel exemplar (65,536 for 128 texels), so renders at more
repeats than that per mesh are coarser than a texel, not wrong. :func:`check_scale` refuses a
scale that is not finite and positive, or whose uv range reaches the backend's limit.

Memory and work
---------------
:func:`memory_limit_mb` is the default budget of a command's working memory (half the
machine's physical memory, :data:`FALLBACK_MEMORY_MB` where unknown; ``--memory-mb`` raises
it); :func:`check_memory` refuses an estimate above it, stating both.
"""

from __future__ import annotations

import math
import os

from .errors import InputError

__all__ = ["MAX_REPEATS", "FLOAT32_MAX_REPEATS", "FALLBACK_MEMORY_MB", "check_scale", "check_count",
           "memory_limit_mb", "check_memory", "format_bytes"]

#: Exemplar repeats below which float64 resolves a fraction of a repeat: the library's uv rule, the bound of the
#: synthesis lattice's exactness (:data:`dynbtf.synthesis.lattice.MAX_REPEATS` is this value).
MAX_REPEATS = 2.0**52
#: The same for float32 arithmetic (Mitsuba's uv, a shader's local uv): integers are exact up to 2**24.
FLOAT32_MAX_REPEATS = 2.0**24
#: Working-memory budget (MB) where the machine's physical memory cannot be read.
FALLBACK_MEMORY_MB = 4096.0


def format_bytes(n: float) -> str:
    """``n`` bytes for a message: ``"1.5 GB"``, ``"931 TB"`` (decimal units).

    >>> format_bytes(1.5e9)
    '1.5 GB'
    """
    n = float(n)
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(n) >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n:.0f} bytes"


def check_scale(scale, name: str = "--scale", *, extent: float = 1.0, float32: bool = False,
                where: str = "", limit: float | None = None) -> float:
    """``float(scale)`` if it is finite, positive and ``extent * scale`` stays below the backend's limit.

    Parameters
    ----------
    scale : number
        Exemplar repeats per unit of uv.
    name : str
        The option or parameter named in the error.
    extent : float
        The largest ``|uv|`` the scale multiplies (1 for a mesh whose uv span ``[0, 1]``).
    float32 : bool
        The backend computes ``uv * scale`` in float32: the limit is :data:`FLOAT32_MAX_REPEATS`
        (else :data:`MAX_REPEATS`).
    where : str
        What computes it, for the message (e.g. ``"Mitsuba's float32 uv"``).
    limit : float, optional
        A lower limit of the backend's own (e.g. the repeats a shader's local uv may span).

    >>> check_scale("25")
    25.0
    >>> check_scale(1e17, float32=True, where="Mitsuba's float32 uv")
    Traceback (most recent call last):
    ...
    dynbtf.errors.InputError: --scale: 1e+17 exemplar repeats across the uv range exceed the 16777216 (2**24) that Mitsuba's float32 uv resolves (beyond, no fraction of a repeat is resolved); expected a positive scale below 16777216
    """
    try:
        value = float(scale)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name}: expected a positive, finite number of exemplar repeats, got {scale!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{name}: expected a positive, finite number of exemplar repeats, got {scale!r}")
    bound = FLOAT32_MAX_REPEATS if float32 else MAX_REPEATS
    power = 24 if float32 else 52
    what = where or ("float32 arithmetic" if float32 else "float64 arithmetic")
    reason = f"the {int(bound)} (2**{power}) that {what} resolves (beyond, no fraction of a repeat is resolved)"
    if limit is not None and limit < bound:
        bound, reason = float(limit), f"the {limit:g} that {what} spans"
    repeats = value * float(extent)
    if not repeats < bound:
        largest = bound / float(extent)
        span = "across the uv range" if extent == 1.0 else f"across the uv range (|uv| up to {extent:g})"
        raise InputError(f"{name}: {repeats:g} exemplar repeats {span} exceed {reason}; expected a positive "
                         f"scale below {largest:.10g}")
    return value


def check_count(value, name: str, *, low: int = 1, high: int | None = None, unit: str = "", why: str = "") -> int:
    """``int(value)`` if it is an integer in ``low..high``, else :class:`InputError` naming ``name``, the
    range and ``why`` (what the upper bound protects).

    >>> check_count(3000, "--spp", high=64, unit="samples per pixel axis")
    Traceback (most recent call last):
    ...
    dynbtf.errors.InputError: --spp: expected 1..64 samples per pixel axis, got 3000
    """
    ok = isinstance(value, int) and not isinstance(value, bool)
    if not ok and isinstance(value, float) and math.isfinite(value) and value == int(value):
        value, ok = int(value), True
    span = f"{low}..{high}" if high is not None else f"an integer >= {low}"
    text = f"{name}: expected {span}{' ' + unit if unit else ''}, got {value!r}{'; ' + why if why else ''}"
    if not ok or value < low or (high is not None and value > high):
        raise InputError(text)
    return int(value)


def memory_limit_mb(requested: float | None = None, name: str = "--memory-mb") -> tuple[float, str]:
    """The working-memory budget in MB and how it was chosen (for messages).

    ``requested`` (a ``--memory-mb`` value) if given (positive, finite); else half the machine's
    physical memory, or :data:`FALLBACK_MEMORY_MB` where that is unknown.
    """
    if requested is not None:
        try:
            value = float(requested)
        except (TypeError, ValueError):
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"{name}: expected a positive number of MB, got {requested!r}")
        return value, f"{name} {value:g}"
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 0
    if total > 0:
        return total / 2 / 1e6, f"the default, half of this machine's {format_bytes(total)} of memory; {name} changes it"
    return FALLBACK_MEMORY_MB, f"the default; {name} changes it"


def check_memory(needed_bytes: float, what: str, requested_mb: float | None = None, *, name: str = "--memory-mb",
                 fix: str = "") -> float:
    """Refuse work whose estimated memory ``needed_bytes`` exceeds the budget (:func:`memory_limit_mb`).

    ``what`` names the work and its size (e.g. ``"--resolution 100000 (1e10 pixels)"``), ``fix``
    says what else to change. Returns the budget in MB.
    """
    limit_mb, how = memory_limit_mb(requested_mb, name)
    if not needed_bytes <= limit_mb * 1e6:
        raise InputError(f"{what} needs about {format_bytes(needed_bytes)} of memory, above the limit of "
                         f"{format_bytes(limit_mb * 1e6)} ({how}){'; ' + fix if fix else ''}")
    return limit_mb
