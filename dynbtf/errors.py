"""User-facing errors.

Every mistake a user can make (a bad file, a wrong argument) raises a subclass of
:class:`DynBTFError` whose message names the file, field or argument and what was
expected. The command line prints these messages without a traceback.
"""

from __future__ import annotations

import math

__all__ = ["DynBTFError", "FormatError", "InputError", "MissingDependencyError", "optional_module",
           "require_positive_ints", "positive_number"]


class DynBTFError(ValueError):
    """Base class of errors caused by user input (files, arguments)."""


class FormatError(DynBTFError):
    """A file is missing, truncated, corrupt or of an unsupported version.

    The message always starts with the file's path.
    """

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class InputError(DynBTFError):
    """An argument has the wrong shape, type or value; the message names it."""


class MissingDependencyError(DynBTFError, ImportError):
    """An optional dependency (an extra such as ``dynbtf[render]``) is not installed; the message says
    which package and how to install it."""


def optional_module(name: str, extra: str, purpose: str):
    """Import module ``name`` of the optional extra ``dynbtf[extra]``, or raise :class:`MissingDependencyError`.

    >>> optional_module("math", "render", "rendering").sqrt(4.0)
    2.0
    >>> optional_module("no_such_module_xyz", "render", "rendering")
    Traceback (most recent call last):
    ...
    dynbtf.errors.MissingDependencyError: rendering needs the Python package 'no_such_module_xyz', which is not installed: pip install 'dynbtf[render]' (or run bash scripts/install.sh)
    """
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError as e:
        raise MissingDependencyError(
            f"{purpose} needs the Python package {name!r}, which is not installed: pip install 'dynbtf[{extra}]' "
            "(or run bash scripts/install.sh)") from e


def require_positive_ints(owner: str, **values) -> None:
    """Check that every keyword value is an ``int`` >= 1.

    Raises :class:`InputError` ``"{owner} {name}: expected a positive integer, got {value!r}"`` for
    the first one that is not.

    >>> require_positive_ints("TriplePlane", height=128, width=0)
    Traceback (most recent call last):
    ...
    dynbtf.errors.InputError: TriplePlane width: expected a positive integer, got 0
    """
    for name, value in values.items():
        if not isinstance(value, int) or value < 1:
            raise InputError(f"{owner} {name}: expected a positive integer, got {value!r}")


def number_in_range(name: str, value, low: float, high: float, expected: str) -> float:
    """``float(value)`` if it is a number (not a bool) in ``[low, high]``; otherwise :class:`InputError`
    ``"{name}: expected {expected}, got ..."``.

    >>> number_in_range("tint", "0.25", 0.0, 1.0, "a value in [0, 1]")
    0.25
    """
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, bool) or not low <= number <= high:
        raise InputError(f"{name}: expected {expected}, got {value!r}")
    return number


def positive_number(name: str, value, meaning: str = "number") -> float:
    """``float(value)`` if it is a finite number > 0.

    Otherwise raises :class:`InputError` ``"{name}: expected a positive, finite {meaning}, got ..."``
    (``meaning`` says what the number is, e.g. ``"exponent"``).

    >>> positive_number("gamma", "7", "exponent")
    7.0
    """
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a positive, finite {meaning}, got {value!r}") from None
    if not (math.isfinite(number) and number > 0):
        raise InputError(f"{name}: expected a positive, finite {meaning}, got {value!r}")
    return number
