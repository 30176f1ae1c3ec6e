"""Open any BTF: one entry point that recognizes every source dynbtf reads.

``open_btf(spec)`` accepts

* a UBO2014 DFMF ``.btf`` file (recognized by its magic bytes ``!DFMF08FC``),
* a UBO2003 zip of angle-named images (recognized as a zip file),
* a stored BTF directory (containing ``meta.json``) or its ``meta.json``,
* a simulated BTF spec ``sim:<material>[?size=128&grid=ubo2003&seed=0&relief=1]``
  (see :mod:`dynbtf.data.simulated`; e.g. ``sim:leather?size=64``).

Examples
--------
>>> parse_sim_spec("sim:stone?size=64&seed=3")
('stone', {'size': 64, 'grid': 'ubo2003', 'seed': 3, 'relief': 1.0})
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from urllib.parse import parse_qsl

from ..errors import FormatError, InputError
from .base import BTFSource

__all__ = ["open_btf", "sniff_format", "parse_sim_spec", "SIM_PREFIX", "SIM_DEFAULTS"]

#: Prefix of simulated-BTF specs.
SIM_PREFIX = "sim:"
#: Defaults of a ``sim:`` spec's options.
SIM_DEFAULTS = {"size": 128, "grid": "ubo2003", "seed": 0, "relief": 1.0}


def parse_sim_spec(spec: str) -> tuple[str, dict]:
    """Split ``sim:<material>[?size=..&grid=..&seed=..&relief=..]`` into ``(material, options)``."""
    body = spec[len(SIM_PREFIX):]
    material, _, query = body.partition("?")
    if not material:
        raise InputError(f"{spec!r}: expected 'sim:<material>[?size=128&grid=ubo2003&seed=0]'")
    options = dict(SIM_DEFAULTS)
    given: set[str] = set()
    for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=False):
        if key not in SIM_DEFAULTS:
            raise InputError(f"{spec!r}: unknown option {key!r}; expected {sorted(SIM_DEFAULTS)}")
        if key in given:
            raise InputError(f"{spec!r}: option {key!r} is given twice; give each option once")
        given.add(key)
        if key in ("size", "seed"):
            try:
                options[key] = int(value)
            except ValueError:
                raise InputError(f"{spec!r}: option {key!r} must be an integer, got {value!r}") from None
        elif key == "relief":
            try:
                options[key] = float(value)
            except ValueError:
                raise InputError(f"{spec!r}: option 'relief' must be a number, got {value!r}") from None
        else:
            options[key] = value
    return material, options


def sniff_format(path) -> str:
    """``"ubo2014"``, ``"ubo2003"`` or ``"stored"`` from a file's content (not its name).

    Raises :class:`FormatError` for a missing or unrecognized file.
    """
    from .ubo2014 import DFMF_MAGIC
    from .stored import META_FILE

    path = Path(path)
    if not path.exists():
        raise FormatError(path, "not found")
    if path.is_dir():
        if (path / META_FILE).is_file():
            return "stored"
        raise FormatError(path, f"is a directory without {META_FILE} (not a stored BTF)")
    if path.name == META_FILE:
        return "stored"
    try:
        with open(path, "rb") as f:
            head = f.read(len(DFMF_MAGIC))
    except OSError as e:
        raise FormatError(path, f"cannot read ({e.strerror or e})") from None
    if head.startswith(b"!"):
        return "ubo2014"  # the DFMF reader names what is wrong with other '!' variants
    if zipfile.is_zipfile(path):
        return "ubo2003"
    raise FormatError(path, "unrecognized format: expected a UBO2014 .btf (DFMF), a UBO2003 .zip, "
                            "a stored BTF directory (*.dbtf with meta.json) or a 'sim:<material>' spec")


def open_btf(path_or_spec, **options) -> BTFSource:
    """Open a BTF source from a path or a ``sim:`` spec (see the module docstring).

    ``options`` are passed to the reader (e.g. ``check_payload=False`` for a
    ``.btf``, ``device=`` for a simulated BTF).
    """
    if isinstance(path_or_spec, BTFSource):
        return path_or_spec
    spec = str(path_or_spec)
    if spec.startswith(SIM_PREFIX):
        material, sim = parse_sim_spec(spec)
        from . import simulated  # imported lazily: it needs torch and the simulator

        return simulated.simulated_btf(material, size=sim["size"], grid=sim["grid"], seed=sim["seed"],
                                       relief=sim["relief"], **options)
    kind = sniff_format(spec)
    if kind == "ubo2014":
        from .ubo2014 import UBO2014BTF

        return UBO2014BTF(spec, **options)
    if kind == "ubo2003":
        from .ubo2003 import UBO2003BTF

        return UBO2003BTF(spec, **options)
    from .stored import StoredBTF

    return StoredBTF(spec, **options)
