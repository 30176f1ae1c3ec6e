"""dynbtf: dynamic, infinitely large BTF synthesis from a small measured BTF.

The pipeline has three stages, each in its own subpackage:

1. **Represent** -- :mod:`dynbtf.representations` (Triple Plane and baselines),
   fitted by :mod:`dynbtf.training` on a BTF from :mod:`dynbtf.data`.
2. **Synthesize** -- :mod:`dynbtf.synthesis` (tiling, histogram-preserving
   blending, hex-tiling, quilting) of the positional feature plane.
3. **Recover** -- :mod:`dynbtf.synthesized` decodes synthesized features into
   reflectance at any uv; :mod:`dynbtf.render` renders it.

Conventions are defined once, in :mod:`dynbtf.conventions`.
"""

__version__ = "0.1.0"
