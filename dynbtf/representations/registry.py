"""The representation registry: every built-in kind, looked up by its ``kind`` name.

This module sits above the kinds (it imports them, so that their
:func:`~dynbtf.representations.base.register` decorators have run), and the kinds
sit above :mod:`~dynbtf.representations.base`, which only defines the interface
and the decorator: no module of the package imports one above it (the
import-linter contract in ``pyproject.toml`` checks this).
"""

from __future__ import annotations

from ..errors import InputError
from . import neumip, parallax, pca, sh, triple_plane  # noqa: F401  (the built-in kinds register themselves)
from .base import REPRESENTATIONS, Representation

__all__ = ["REPRESENTATIONS", "get_representation_class"]


def get_representation_class(kind: str) -> type[Representation]:
    """The class registered as ``kind``; a clear error lists the known kinds."""
    try:
        return REPRESENTATIONS[kind]
    except KeyError:
        raise InputError(f"unknown representation {kind!r}; expected one of {sorted(REPRESENTATIONS)}") from None
