"""The physics of the simulated measured BTF: materials, height fields, shading, rendering.

* :mod:`.noise` -- periodic, resolution-independent procedural noise (seeded).
* :mod:`.materials` -- the four materials as tabulated height + reflectance maps.
* :mod:`.geometry` -- parallax/masking (view ray marching), cast shadows, sky view.
* :mod:`.shading` -- the clear-coated GGX microfacet BRDF (``pi * f_r``).
* :mod:`.renderer` -- combines them into ``(view, lights) -> images``.

The BTF source built on it is :class:`dynbtf.data.simulated.SimulatedBTF`.
"""

from .materials import MATERIALS, MaterialMaps, build_material
from .renderer import HeightFieldRenderer

__all__ = ["MATERIALS", "MaterialMaps", "build_material", "HeightFieldRenderer"]
