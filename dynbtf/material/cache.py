"""The one on-disk cache of compiled materials, and "open or compile" on top of it.

An entry is a ``.dbtfc`` file (:mod:`dynbtf.material.format`) named by its cache key: the digest of the
model's tensors, the method (and the version of its table construction), the seed, the method's arguments and
the footprint-fit settings
(:func:`~dynbtf.material.format.material_key`). A second process (another ``dynbtf render`` of the same
model, a Mitsuba scene load, a second ``dynbtf demo``) reads what the first one compiled.

Most methods' tables depend on the exemplar alone, not on the seed (the seed picks hashes at query time): the
first material compiled for a model, method and arguments also keeps its tables under a key without the seed
(:func:`tables_key`), and every other seed's material is made from them (only footprint decoders, where asked
for, are fitted again). This is the one cache: the synthesis package keeps none of its own.

Folder: ``$DYNBTF_COMPILED_CACHE`` (``off`` disables the cache), else ``~/.cache/dynbtf/compiled``.
Entries are written atomically. An entry is read through :func:`~dynbtf.material.format.load_compiled`
(every check of a file from anyone, regular files only) and must hold the material of the model asked
for under its own key; anything else -- damaged, edited, a FIFO, another model's material copied under
this key -- costs a warning and is compiled again, the new entry replacing it.

Example
-------
>>> import os, tempfile
>>> from dynbtf.representations.triple_plane import TriplePlane
>>> os.environ["DYNBTF_COMPILED_CACHE"] = tempfile.mkdtemp()
>>> model = TriplePlane(16, 16)
>>> open_or_compile(model, "hist", seed=3, footprints=False)[1]
'compiled'
>>> material, how = open_or_compile(model, "hist", seed=3, footprints=False)
>>> how, material.method, material.seed
('cached', 'hist', 3)
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

from ..errors import FormatError
from ..io import user_cache_dir
from ..synthesis.registry import synthesizer_class
from .compiler import argument_key, compile_material, footprint_settings, model_digest
from .format import SUFFIX, CompiledMaterial, load_compiled, material_key, save_compiled

__all__ = ["open_or_compile", "store_cached", "compiled_cache_dir", "cache_path", "tables_key"]


def compiled_cache_dir() -> Path | None:
    """The folder of the compiled-material cache, or None when ``$DYNBTF_COMPILED_CACHE`` is ``off``."""
    return user_cache_dir("DYNBTF_COMPILED_CACHE", "compiled")


def cache_path(key: str) -> Path | None:
    """Where the entry of cache key ``key`` lives (None: the cache is off)."""
    folder = compiled_cache_dir()
    return None if folder is None else folder / f"{key}{SUFFIX}"


def _read_cached(path: Path | None, device, digest: str) -> CompiledMaterial | None:
    """The cache entry at ``path`` if it is a sound material of the model with ``digest`` stored under its own
    key; anything else (damaged, not a regular file, another model's material copied under this key) costs a
    warning and is compiled again (the new entry replaces it)."""
    if path is None or not (path.exists() or path.is_symlink()):
        return None
    try:
        found = load_compiled(path, device=device)  # (refuses anything but a regular file)
        if found.model_sha256 != digest or found.key != path.stem:
            raise FormatError(path, "holds the material of another model or key")
        return found
    except (FormatError, OSError) as e:
        warnings.warn(f"compiled-material cache: {e}; compiling again", stacklevel=3)
        return None


def store_cached(material: CompiledMaterial) -> Path | None:
    """Write ``material`` to the cache under its key; returns the entry's path (None when the cache is off or
    cannot be written: that costs only a warning, the material is used unsaved)."""
    path = cache_path(material.key) if material.key else None
    if path is None:
        return None
    try:
        return save_compiled(material, path)
    except OSError as e:
        warnings.warn(f"compiled-material cache: could not write {path} ({e}); the material is used unsaved",
                      stacklevel=3)
        return None


def open_or_compile(model, method: str = "auto", seed: int = 0, *, footprints: bool = True, progress: bool = True,
                    **arguments) -> tuple[CompiledMaterial, str]:
    """The compiled material of ``model`` for ``method`` and ``seed``: read from the cache, or compiled
    (:func:`~dynbtf.material.compiler.compile_material`) and stored. Returns ``(material, how)``, ``how`` one of
    ``"cached"`` (read), ``"compiled"`` (built and stored) or ``"uncached"`` (the cache is off).

    Without ``footprints`` a cached material with footprint decoders is used as well (it holds the same
    tables); with ``footprints``, a cached material without them is completed (tables reused) and stored.
    ``auto`` is compiled once and also stored under the key of the method it chose (same tables), so that
    asking for that method by name later reads it; with ``footprints`` the footprint decoders
    are those of the chosen method (one fit per resolved method).
    """
    if method == "auto":
        chosen, how = _open_or_compile(model, "auto", seed, footprints=False, progress=progress, **arguments)
        _alias(model, chosen, seed)
        if not footprints:
            return chosen, how
        full, how = _open_or_compile(model, chosen.method, seed, footprints=True, progress=progress,
                                     **chosen.arguments)
        return replace(full, choice=chosen.choice, _synthesizers=full._synthesizers), how
    return _open_or_compile(model, method, seed, footprints=footprints, progress=progress, **arguments)


def _alias(model, material: CompiledMaterial, seed: int) -> None:
    """Store ``material`` (compiled for ``auto``) under the key of the method it chose, unless that entry
    exists."""
    if not material.key or compiled_cache_dir() is None:
        return
    key = material_key(model_digest(model), material.method, seed, argument_key(material.arguments),
                       footprint_settings(False))
    if not cache_path(key).exists():
        store_cached(replace(material, key=key, choice=None, _synthesizers=material._synthesizers))


def _open_or_compile(model, method: str, seed: int, *, footprints: bool, progress: bool,
                     **arguments) -> tuple[CompiledMaterial, str]:
    device = model.positional_plane().device
    digest = model_digest(model)
    keys = {flag: material_key(digest, method, seed, argument_key(arguments), footprint_settings(flag))
            for flag in (True, False)}
    for flag in ((True, False) if not footprints else (True,)):
        found = _read_cached(cache_path(keys[flag]), device, digest)
        if found is not None:
            found.model = model  # the caller's module (equal contents): no second copy
            return found, "cached"
    base = None if not footprints else _read_cached(cache_path(keys[False]), device, digest)
    refused = False
    if base is None:  # another seed's tables, where they do not depend on the seed
        base, refused = _tables_of_another_seed(method, seed, arguments, digest, device, keys[False])
    if base is not None:
        base.model = model
    material = compile_material(model, method, seed, footprints=footprints, progress=progress, base=base, **arguments)
    if compiled_cache_dir() is None:
        return material, "uncached"
    store_cached(material)
    _store_tables(material, method, arguments, digest, replace_entry=refused)
    return material, "compiled"


def tables_key(digest: str, method: str, arguments: dict) -> str:
    """The cache key of the tables every seed of ``method`` shares on a model (its entry holds a material without
    footprint decoders; :attr:`~dynbtf.synthesis.base.Synthesizer.seeded_tables` methods have none)."""
    return material_key(digest, method, -1, argument_key(arguments), "tables of any seed")


def _store_tables(material: CompiledMaterial, method: str, arguments: dict, digest: str, *,
                  replace_entry: bool = False) -> None:
    """Keep ``material``'s seed-independent tables (and point decoder) under :func:`tables_key`, unless kept
    already; ``replace_entry``: the entry there was refused (damaged, edited, not a regular file) and is replaced."""
    if not material.key or synthesizer_class(material.method).seeded_tables:
        return
    key = tables_key(digest, method, arguments)
    path = cache_path(key)
    if path.exists() and not replace_entry:
        return
    decoder = material.decoder
    if decoder is not None and (len(decoder.levels) > 1 or decoder.mean is not None):  # another seed fits its own
        decoder = replace(decoder, levels=decoder.levels[:1], mean=None)
    store_cached(replace(material, key=key, decoder=decoder, sampling=None, _synthesizers={}))


def _tables_of_another_seed(method: str, seed: int, arguments: dict, digest: str, device,
                            key: str) -> tuple[CompiledMaterial | None, bool]:
    """``(material, refused)``: the material of ``seed`` without footprint decoders, made from another seed's tables
    (:func:`_store_tables`) under its own ``key``, or None where none are kept or the entry was refused (then
    ``refused``: a warning was given, and the entry is to be replaced). The synthesizer is rebuilt from the
    tables with ``seed``."""
    path = cache_path(tables_key(digest, method, arguments))
    if path is None or not (path.exists() or path.is_symlink()):
        return None, False
    found = _read_cached(path, device, digest)
    if found is None:
        return None, True
    if synthesizer_class(found.method).seeded_tables:
        return None, False
    return replace(found, seed=int(seed), key=key, _synthesizers={}), False
