"""Stage 1, Represent: BTF representations behind one interface.

See :mod:`dynbtf.representations.base` for the interface.
"""

from .base import REPRESENTATIONS, Representation, get_representation_class, register

__all__ = ["Representation", "register", "REPRESENTATIONS", "get_representation_class"]
