"""Mitsuba and Dr.Jit, imported on first use (they are the optional extra ``dynbtf[render]``).

Dr.Jit types come from the active Mitsuba variant (``mi.Float``, ``mi.UInt32``...); :func:`mi_module` sets
``llvm_ad_rgb`` if none was chosen. :mod:`.llvm` checks the LLVM library Dr.Jit's CPU back end compiles with.
"""

from __future__ import annotations

from ..errors import optional_module

__all__ = ["mitsuba_module", "mi_module", "drjit_module"]


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
