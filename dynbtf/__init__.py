"""dynbtf: dynamic, infinitely large BTF synthesis from a small measured BTF.

The pipeline has three stages, each in its own subpackage:

1. **Represent** -- :mod:`dynbtf.representations` (Triple Plane and baselines),
   fitted by :mod:`dynbtf.training` on a BTF from :mod:`dynbtf.data`.
2. **Synthesize** -- :mod:`dynbtf.synthesis` (tiling, histogram-preserving
   blending, hex-tiling, quilting) of the positional feature plane.
3. **Recover** -- :mod:`dynbtf.infinite_btf` decodes synthesized features into
   reflectance at any uv; :mod:`dynbtf.render` renders it.

Conventions are defined once, in :mod:`dynbtf.conventions`.

The names a user needs are here, imported on first use (``import dynbtf`` itself loads
neither PyTorch nor Mitsuba nor numba):

>>> import dynbtf
>>> btf = dynbtf.open_btf("sim:leather?size=16")
>>> btf.shape  # views, lights, height, width (RGB images)
(81, 81, 16, 16)
>>> w = dynbtf.spherical_to_direction(0.0, 0.0)  # (theta, phi) in degrees -> unit vector, z = normal
>>> [round(float(x), 6) for x in w]
[0.0, 0.0, 1.0]

Fit, save and synthesize::

    result = dynbtf.fit(dynbtf.TriplePlane(btf.height, btf.width), btf, dynbtf.TrainConfig(epochs=30), "m.dbtfm")
    synth = dynbtf.synthesized_btf("m.dbtfm", "hist", scale=25, seed=0)
    rgb = synth.eval(uv, w_view, w_light)    # (..., 3) linear RGB at any real uv

Mitsuba 3 (optional, ``pip install dynbtf[render]``): ``dynbtf.register_plugin()`` after
``mitsuba.set_variant(...)`` makes the ``dynbtf`` BSDF available. ``dynbtf.export_web(model,
out_dir)`` writes a GLSL ES 3.00 shader, its textures and a WebGL2 viewer page.
"""

from __future__ import annotations

import importlib

from ._version import __version__
from .cpu import apply_isa_environment

# DYNBTF_CPU_ISA (dynbtf.cpu) forces an instruction-set level on PyTorch, MKL, oneDNN and numba too: their
# variables must be set before they load, which is now (dynbtf loads none of them at import)
apply_isa_environment()

#: The front door: public name -> module that defines it (imported when the name is first used).
_FRONT_DOOR = {
    # data
    "open_btf": "dynbtf.data.open",
    "simulated_btf": "dynbtf.data.simulated",
    "BTFSource": "dynbtf.data.base",
    "spherical_to_direction": "dynbtf.conventions",
    "direction_to_spherical": "dynbtf.conventions",
    # representations and training
    "TriplePlane": "dynbtf.representations.triple_plane",
    "fit": "dynbtf.training.fit",
    "TrainConfig": "dynbtf.training.fit",
    "auto_recipe": "dynbtf.training.recipe",
    "save_model": "dynbtf.representations.model_file",
    "load_model": "dynbtf.representations.model_file",
    "evaluate_model": "dynbtf.training.evaluate",
    # synthesis and recovery
    "synthesized_btf": "dynbtf.synthesized",
    "SynthesizedBTF": "dynbtf.infinite_btf",
    "make_synthesizer": "dynbtf.synthesis.registry",
    "LayeredBTF": "dynbtf.layered",
    "ImageMask": "dynbtf.layered",
    "NoiseMask": "dynbtf.layered",
    "guided_btf": "dynbtf.guided",
    # the material stage
    "open_or_compile": "dynbtf.material",
    "load_compiled": "dynbtf.material",
    # rendering (Mitsuba 3, optional) and real time (GLSL shader + WebGL2 viewer)
    "register_plugin": "dynbtf.render.mitsuba.bsdf",
    "export_web": "dynbtf.export.web.exporter",
    # errors
    "DynBTFError": "dynbtf.errors",
    "InputError": "dynbtf.errors",
    "FormatError": "dynbtf.errors",
}

__all__ = ["__version__", *_FRONT_DOOR]


def __getattr__(name: str):
    module = _FRONT_DOOR.get(name)
    if module is None:
        raise AttributeError(f"module 'dynbtf' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_FRONT_DOOR))
