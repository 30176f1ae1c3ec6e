"""The material stage: build a compiled material once, open it anywhere.

A *compiled material* is what every backend answers queries from: a fitted model, a synthesis method
and a seed, with every table derived from them (the method's tables and pyramid, the folded decoder,
the footprint decoders, the renderer's sampling table). This package owns it:

* :mod:`~dynbtf.material.format` -- the ``.dbtfc`` file: :class:`CompiledMaterial`, :func:`save_compiled`,
  :func:`load_compiled` (opening only reads and validates: every table against its declared rules);
* :mod:`~dynbtf.material.compiler` -- :func:`compile_material`, off-line: it resolves ``auto`` and may fit
  the footprint decoders (:mod:`~dynbtf.material.footprint_decoders`);
* :mod:`~dynbtf.material.cache` -- the one on-disk cache and :func:`open_or_compile`.

The stage imports no training code, and the query object (:class:`dynbtf.infinite_btf.SynthesizedBTF`),
the renderers and the exporters reach materials only through it (``pyproject.toml``'s import contracts).

Example
-------
>>> import os, tempfile
>>> from dynbtf.material import load_compiled, open_or_compile, save_compiled
>>> from dynbtf.representations.triple_plane import TriplePlane
>>> os.environ["DYNBTF_COMPILED_CACHE"] = "off"
>>> material, how = open_or_compile(TriplePlane(16, 16), "tile", footprints=False)
>>> path = save_compiled(material, os.path.join(tempfile.mkdtemp(), "m.dbtfc"))
>>> how, load_compiled(path).method
('uncached', 'tile')
"""

from .cache import compiled_cache_dir, open_or_compile, store_cached
from .compiler import APPEARANCE_PAIRS, compile_material, decoded_appearance, decoded_luminance, model_digest
from .format import (FORMAT_VERSION, SUFFIX, CompiledMaterial, is_compiled_material, load_compiled, open_model_file,
                     save_compiled)

__all__ = ["CompiledMaterial", "load_compiled", "save_compiled", "open_model_file", "is_compiled_material",
           "compile_material", "open_or_compile", "store_cached", "compiled_cache_dir", "decoded_appearance",
           "decoded_luminance", "model_digest", "APPEARANCE_PAIRS", "FORMAT_VERSION", "SUFFIX"]
