"""BTF sources: one interface (:class:`BTFSource`), every way a BTF gets into dynbtf.

* :class:`ArrayBTF` -- in memory (small BTFs, tests).
* :class:`UBO2014BTF` -- UBO2014 DFMF ``.btf`` files (SVD factors read on demand).
* :class:`UBO2003BTF` -- UBO2003 zips of angle-named sRGB images.
* :class:`StoredBTF` -- dynbtf's own ``*.dbtf`` directories (meta.json + raw array).
* ``sim:<material>`` -- simulated BTFs (:mod:`dynbtf.data.simulated`).

:func:`open_btf` opens any of them from a path or spec.
"""

from .array import ArrayBTF
from .base import BTFSamples, BTFSource
from .directions import (direction_set, direction_set_degrees, ubo2003_directions, ubo2014_directions,
                         UBO2003_RINGS, UBO2014_RINGS)
from .open import open_btf, parse_sim_spec, sniff_format
from .stored import StoredBTF, read_stored, write_stored
from .ubo2003 import UBO2003BTF, read_ubo2003, write_ubo2003
from .ubo2014 import UBO2014BTF, btf_extractor_angles, read_ubo2014, write_ubo2014

__all__ = [
    "BTFSource", "BTFSamples", "ArrayBTF", "UBO2014BTF", "UBO2003BTF", "StoredBTF",
    "open_btf", "sniff_format", "parse_sim_spec",
    "read_ubo2014", "write_ubo2014", "btf_extractor_angles", "read_ubo2003", "write_ubo2003",
    "read_stored", "write_stored",
    "direction_set", "direction_set_degrees", "ubo2014_directions", "ubo2003_directions",
    "UBO2014_RINGS", "UBO2003_RINGS",
]
