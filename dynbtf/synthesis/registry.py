"""The synthesis registry: every built-in method, looked up and built by its registry name.

This module sits above the methods (it imports them, so that their
:func:`~dynbtf.synthesis.base.register_synthesizer` decorators have run, and
:mod:`.auto`, which chooses between two of them), and the methods sit above
:mod:`~dynbtf.synthesis.base`, which only defines the interface, the decorator and
:data:`~dynbtf.synthesis.base.SYNTHESIZERS`: no module of the package imports one
above it (the import-linter contract in ``pyproject.toml`` checks this).
"""

from __future__ import annotations

import inspect
from typing import Any

from ..errors import InputError
from . import blending, cell_quilting, guided_blending, hex_tiling, histogram_blending, quilting, tiling  # noqa: F401
from .auto import choose_method
from .base import SYNTHESIZERS, Synthesizer
from .elements import check_variation
from .sample_transform import check_rotation, check_scale_jitter

__all__ = ["SYNTHESIZERS", "synthesizer_class", "make_synthesizer", "model_inputs", "AUTO_CANDIDATES",
           "EXEMPLAR_METHOD", "PAPER_METHOD", "VARIATIONS", "takes_parameter", "methods_taking", "methods_with",
           "given_variations", "variation_flag"]

#: The methods ``auto`` chooses between (:func:`dynbtf.synthesis.auto.choose_method`).
AUTO_CANDIDATES = ("struct", "hist")
#: The method that answers the exemplar itself, periodic and without tables: what synthesis is measured against.
EXEMPLAR_METHOD = "tile"
#: The paper's method (histogram-preserving blending): the one other methods and the automatic choice are shown next to.
PAPER_METHOD = "hist"
#: The variation controls a method may take, each off by default and drawn from the seed: parameter -> what it does
#: (for messages). ``struct``'s per-element ``brightness`` and ``tint`` (:mod:`.elements`), lattice blending's
#: ``rotation`` and ``scale_jitter`` (:mod:`.sample_transform`).
VARIATIONS = {"brightness": "per-element variation", "tint": "per-element variation",
              "rotation": "turning the samples", "scale_jitter": "scaling the samples"}


def synthesizer_class(name: str) -> type[Synthesizer]:
    """The class registered as ``name``; unknown names raise :class:`InputError` listing the known ones."""
    try:
        return SYNTHESIZERS[name]
    except KeyError:
        raise InputError(f"synthesis method {name!r} is unknown; expected one of {sorted(SYNTHESIZERS) + ['auto']}") from None


def model_inputs(name: str) -> dict[str, str]:
    """What method ``name`` takes from a fitted model (:attr:`~dynbtf.synthesis.base.Synthesizer.model_inputs`);
    for ``auto``, what either candidate takes (the choice itself measures ``guide``)."""
    if name == "auto":
        merged: dict[str, str] = {}
        for candidate in AUTO_CANDIDATES:
            merged.update(synthesizer_class(candidate).model_inputs)
        return merged
    return dict(synthesizer_class(name).model_inputs)


def _accepted(cls) -> list[str]:
    """The method parameters of a synthesizer class (its constructor's keywords besides exemplar and seed; a
    constructor that passes ``**params`` on takes those of the synthesizer class it builds on, e.g. guided struct
    struct's)."""
    names: list[str] = []
    for p in inspect.signature(cls.__init__).parameters.values():
        if p.name in ("self", "exemplar", "seed") or p.kind == inspect.Parameter.VAR_POSITIONAL:
            continue
        if p.kind == inspect.Parameter.VAR_KEYWORD:
            base = next((b for b in cls.__mro__[1:] if issubclass(b, Synthesizer) and "__init__" in vars(b)), None)
            names += [n for n in (_accepted(base) if base is not None else []) if n not in names]
        elif p.name not in names:
            names.append(p.name)
    return names


def _required(cls) -> list[str]:
    """The method parameters of a synthesizer class without a default (e.g. the guided methods' labels and target)."""
    return [p.name for p in inspect.signature(cls.__init__).parameters.values()
            if p.name not in ("self", "exemplar", "seed") and p.default is inspect.Parameter.empty
            and p.kind not in (inspect.Parameter.VAR_KEYWORD, inspect.Parameter.VAR_POSITIONAL)]


def takes_parameter(name: str, parameter: str) -> bool:
    """Whether method ``name`` takes ``parameter`` (a keyword of its constructor); ``auto`` takes none itself (its
    parameters go to the method it chooses), and an unknown name takes nothing.

    >>> takes_parameter("struct", "cells"), takes_parameter("hist", "cells"), takes_parameter("hist", "gamma")
    (True, False, True)
    """
    cls = SYNTHESIZERS.get(name)
    return cls is not None and parameter in _accepted(cls)


def given_variations(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """The variation controls (:data:`VARIATIONS`) among ``values`` that are on, each checked: an
    :class:`InputError` naming ``prefix + name`` (``prefix="--"``: the command-line flag) for a bad value.

    >>> given_variations({"brightness": 0.1, "tint": 0.0, "rotation": False, "scale_jitter": 0.0})
    {'brightness': 0.1}
    """
    checks = {"brightness": check_variation, "tint": check_variation, "rotation": check_rotation,
              "scale_jitter": check_scale_jitter}
    given = {name: checks[name](variation_flag(name, prefix), value) for name, value in values.items()}
    return {name: value for name, value in given.items() if value}


def variation_flag(name: str, prefix: str = "--") -> str:
    """How a message names variation ``name``: the command-line flag for ``prefix="--"``, else ``prefix + name``.

    >>> variation_flag("scale_jitter"), variation_flag("scale_jitter", "")
    ('--scale-jitter', 'scale_jitter')
    """
    return prefix + (name.replace("_", "-") if prefix == "--" else name)


def methods_taking(parameter: str) -> list[str]:
    """The methods built from an exemplar alone (:func:`methods_with`) that take ``parameter``, sorted: what a
    message names when a method that does not take it was given.

    >>> methods_taking("rotation"), methods_taking("scale_jitter"), methods_taking("brightness")
    (['hex', 'hist', 'linear'], ['hex', 'hist', 'linear'], ['struct'])
    """
    return [m for m in methods_with() if takes_parameter(m, parameter)]


def methods_with(backend: str | None = None, *, with_required: bool = False) -> list[str]:
    """The methods that run on ``backend`` (:attr:`~dynbtf.synthesis.base.Synthesizer.backends`; ``None``: every
    method, on the CPU and torch) and build from an exemplar alone (no required parameter, unlike the guided methods,
    which need labels and a target), sorted; ``with_required``: also those that need parameters besides the exemplar
    (what a backend implements, e.g. the web shader's branches).

    >>> methods_with("web")
    ['hex', 'hist', 'linear', 'struct', 'tile']
    >>> methods_with()
    ['hex', 'hist', 'linear', 'quilt', 'struct', 'tile']
    >>> methods_with("web", with_required=True)
    ['guided', 'guided-hex', 'guided-struct', 'hex', 'hist', 'linear', 'struct', 'tile']
    """
    return sorted(name for name, cls in SYNTHESIZERS.items()
                  if (backend is None or backend in cls.backends) and (with_required or not _required(cls)))


def make_synthesizer(name: str, exemplar, seed: int = 0, **params) -> Synthesizer:
    """Build the synthesizer ``name`` on ``exemplar (H, W, C)`` with ``seed`` and method ``params``.

    ``name = "auto"`` chooses ``struct`` or ``hist`` from the exemplar's structure
    (:func:`dynbtf.synthesis.auto.choose_method`); the built synthesizer's ``choice`` attribute
    then holds the :class:`~dynbtf.synthesis.auto.MethodChoice` (else None); ``auto`` passes each
    parameter to the chosen method if it takes it (``guide`` is also measured by the choice; ``gamma``
    applies if ``hist`` is chosen). Unknown parameter names raise :class:`InputError` listing the
    accepted ones.
    """
    choice = None
    if name == "auto":
        choice = choose_method(Synthesizer.check_exemplar(exemplar), params.get("guide"))
        candidates = {m: _accepted(synthesizer_class(m)) for m in AUTO_CANDIDATES}
        unknown = sorted(set(params) - set().union(*candidates.values()))
        if unknown:
            raise InputError(f"synthesis method 'auto': unknown parameter(s) {unknown}; accepted: "
                             f"{sorted(set().union(*candidates.values()))} (each passed to the method that takes it)")
        name = choice.method
        params = {k: v for k, v in params.items() if k in candidates[name]}
    cls = synthesizer_class(name)
    accepted = _accepted(cls)
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise InputError(f"synthesis method {name!r}: unknown parameter(s) {unknown}; accepted: {accepted}")
    missing = [p for p in _required(cls) if p not in params]
    if missing:
        raise InputError(f"synthesis method {name!r} needs parameter(s) {missing}; give them (e.g. as method "
                         "parameters), or build the synthesizer and pass it")
    synth = cls(exemplar, seed=seed, **params)
    synth.choice = choice
    return synth
