"""The Dr.Jit substrate: Mitsuba and Dr.Jit imported on first use, and the few array operations every kernel builds on.

The synthesis methods' Dr.Jit kernels (``dynbtf/synthesis/<method>/drjit.py``) and the renderer's
(:mod:`dynbtf.render.mitsuba`) are written with these; nothing here knows a method or a representation.

Conventions
-----------
* Dr.Jit types come from the active Mitsuba variant (``mi.Float``, ``mi.UInt32``...); :func:`mi_module`
  sets ``llvm_ad_rgb`` if none was chosen. Nothing is specific to the LLVM backend: the same code traces
  into CUDA kernels.
* Planes are flat, channels-last ``mi.Float`` buffers (texel ``[i, j]``, channel ``c`` at
  ``(i * W + j) * C + c``) fetched with ``dr.gather``: a manual bilinear fetch is the same arithmetic on
  every backend, whereas hardware texture units interpolate with reduced precision.
* A vector of ``C`` channels is a Python ``list`` of ``C`` ``mi.Float`` arrays (structure of arrays).
"""

from __future__ import annotations

import numpy as np

from ..errors import optional_module

__all__ = ["mitsuba_module", "mi_module", "drjit_module", "wrap01", "bilinear_taps", "gather_channels", "fetch_wrap",
           "flat_array"]


def mitsuba_module():
    """The ``mitsuba`` module, imported on first use (Mitsuba is the optional extra ``dynbtf[render]``;
    :class:`dynbtf.errors.MissingDependencyError` says how to install it)."""
    return optional_module("mitsuba", "render", "rendering with Mitsuba 3")


def mi_module():
    """The ``mitsuba`` module with a variant set (``llvm_ad_rgb`` if none was chosen; a missing or too old LLVM is
    refused first, :func:`~dynbtf.jit.llvm.check_llvm`)."""
    mi = mitsuba_module()
    if mi.variant() is None:
        from .llvm import check_llvm

        check_llvm("llvm_ad_rgb")  # an old LLVM aborts the process while compiling: refused before
        mi.set_variant("llvm_ad_rgb")
    return mi


def drjit_module():
    """The ``drjit`` module (installed with Mitsuba), imported on first use."""
    return optional_module("drjit", "render", "rendering with Mitsuba 3")


def wrap01(x):
    """``x - floor(x)`` in ``[0, 1)`` (the exact 1.0 of tiny negative inputs maps to 0)."""
    dr = drjit_module()
    f = x - dr.floor(x)
    return dr.select(f >= 1.0, f - 1.0, f)


def bilinear_taps(x, y, width: int, height: int, *, wrap_x: bool, wrap_y: bool):
    """Texel indices and weights of a bilinear fetch at continuous texel coordinates.

    Parameters
    ----------
    x, y : mi.Float
        Coordinates in texels with texel ``[i, j]`` centred at ``(j, i)``
        (i.e. ``u * W - 0.5``).
    width, height : int
        Plane size.
    wrap_x, wrap_y : bool
        Periodic addressing along that axis; otherwise clamp to the edge texels.

    Returns
    -------
    list of 4 ``(flat_index: mi.UInt32, weight: mi.Float)``
    """
    mi, dr = mi_module(), drjit_module()
    x0f, y0f = dr.floor(x), dr.floor(y)
    fx, fy = x - x0f, y - y0f
    x0, y0 = mi.Int32(x0f), mi.Int32(y0f)

    def addr(k, n, wrap):
        if wrap:
            k = k % n
            return dr.select(k < 0, k + n, k)
        return dr.clip(k, 0, n - 1)

    xs = (addr(x0, width, wrap_x), addr(x0 + 1, width, wrap_x))
    ys = (addr(y0, height, wrap_y), addr(y0 + 1, height, wrap_y))
    wx = (1.0 - fx, fx)
    wy = (1.0 - fy, fy)
    return [(mi.UInt32(ys[b] * width + xs[a]), wy[b] * wx[a]) for b in (0, 1) for a in (0, 1)]


def gather_channels(buffer, channels: int, taps, active=True, which=None):
    """Bilinear combination of ``channels`` values per tap from a flat channels-last buffer -> list of mi.Float.

    ``which`` (a sequence of channel indices) fetches only those channels, in that order.
    """
    mi, dr = mi_module(), drjit_module()
    which = range(channels) if which is None else list(which)
    out = [mi.Float(0.0) for _ in which]
    for index, weight in taps:
        base = index * channels
        for k, c in enumerate(which):
            out[k] = dr.fma(dr.gather(mi.Float, buffer, base + c, active), weight, out[k])
    return out


def fetch_wrap(buffer, size: tuple[int, int], channels: int, u, v, active=True, which=None):
    """Bilinear periodic fetch of a positional plane ``(H, W, C)`` at ``(u, v)`` (units of one repeat).

    ``u, v`` are ``mi.Float``, or ``mi.Float64`` whose whole repeats are removed in float64
    before the float32 interpolation (as :func:`dynbtf.texture.fetch_wrap`). ``which``: as
    :func:`gather_channels`.
    """
    mi = mi_module()
    h, w = size
    u, v = mi.Float(wrap01(u)), mi.Float(wrap01(v))
    taps = bilinear_taps(wrap01(u) * w - 0.5, wrap01(v) * h - 0.5, w, h, wrap_x=True, wrap_y=True)
    return gather_channels(buffer, channels, taps, active, which)


def flat_array(mi, array) -> "object":
    """A numpy array of any shape as a flat ``mi.Float`` (float32, row-major)."""
    return mi.Float(np.ascontiguousarray(np.asarray(array, dtype=np.float32)).ravel())
