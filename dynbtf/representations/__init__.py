"""Stage 1, Represent: BTF representations behind one interface.

See :mod:`dynbtf.representations.base` for the interface and
:mod:`dynbtf.representations.registry` for the lookup by kind name.
"""

from .base import Representation, register
from .registry import REPRESENTATIONS, get_representation_class

__all__ = ["Representation", "register", "REPRESENTATIONS", "get_representation_class"]
