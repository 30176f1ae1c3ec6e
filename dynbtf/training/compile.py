"""Compile a fitted model for one synthesis method and seed: derive every table once, save, reuse.

:func:`compile_material` builds a :class:`~dynbtf.compiled_material.CompiledMaterial`: the synthesizer
on the model's positional plane (``auto`` resolved, its off-line tables and pyramid), the decoder
with the method's output map folded into layer 1 and, with ``footprints=True``, the per-level
decoders and mean appearance of footprint queries (:mod:`dynbtf.training.footprint_decoders`, the
expensive part: a fit per pyramid level, timed in ``docs/compiled_material.md``). :func:`cached_material` does the same through
an on-disk cache keyed by the model's contents, so a second process (another ``dynbtf render`` of
the same model, a Mitsuba scene load, a second ``dynbtf demo``) reads what the first one built.

Cache: ``$DYNBTF_COMPILED_CACHE`` (``off`` disables it), else ``~/.cache/dynbtf/compiled``; entries
are written atomically and a damaged entry (checksum, truncation) is warned about and rebuilt.

Example
-------
>>> from dynbtf.representations.triple_plane import TriplePlane
>>> material = compile_material(TriplePlane(16, 16), "hist", seed=3, footprints=False)
>>> material.method, material.seed, sorted(material.synthesis)[:3]
('hist', 3, ['decorrelation.basis', 'decorrelation.mean', 'decorrelation.variances'])
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..compiled_material import SUFFIX, CompiledMaterial, compiled_cache_dir, load_compiled, material_key, save_compiled
from ..conventions import spherical_to_direction
from ..decoder.folded import DecodePath, FoldedDecoder
from ..errors import FormatError, InputError
from ..synthesis.registry import make_synthesizer, synthesizer_class
from ..representations.model_file import tensor_digest
from .footprint_decoders import fit_footprint_decoders

__all__ = ["compile_material", "cached_material", "decoded_appearance", "decoded_luminance", "APPEARANCE_PAIRS",
           "model_digest"]

#: (view, light) pairs, (theta, phi) in degrees, under which ``struct`` and ``auto`` see the exemplar's
#: structure (normal view and light, a slanted pair, a grazing-ish pair from other azimuths).
APPEARANCE_PAIRS = (((0.0, 0.0), (0.0, 0.0)), ((30.0, 0.0), (45.0, 180.0)), ((60.0, 90.0), (30.0, 270.0)))

#: Method parameters that are inputs of the tables, not settings: they are not stored (the tables are).
_TABLE_INPUTS = ("guide", "luminance", "prepared", "progress")


def decoded_appearance(model, plane: torch.Tensor | None = None, chunk_size: int = 32768,
                       pairs=APPEARANCE_PAIRS) -> torch.Tensor:
    """A model's positional plane decoded under ``pairs`` of (view, light) ``(theta, phi)`` in degrees (default
    :data:`APPEARANCE_PAIRS`): ``(H, W, 3 * pairs)`` float32.

    What ``struct`` and ``auto`` see of a fitted model (their ``guide``): a feature plane spreads its
    variance over many channels, fine detail included, while its decoded colours show the material's
    structure. ``plane`` defaults to ``model.positional_plane()``.
    """
    with torch.no_grad():
        plane = model.positional_plane().detach() if plane is None else plane
        h, w, _ = plane.shape
        rows = plane.reshape(h * w, -1)
        images = []
        for view, light in pairs:
            wv = spherical_to_direction(np.array(view[0]), np.array(view[1]))
            wl = spherical_to_direction(np.array(light[0]), np.array(light[1]))
            wv = torch.as_tensor(wv, dtype=plane.dtype, device=plane.device).expand(h * w, 3)
            wl = torch.as_tensor(wl, dtype=plane.dtype, device=plane.device).expand(h * w, 3)
            images.append(torch.cat([model.decode(chunk, a, b) for chunk, a, b in
                                     zip(rows.split(chunk_size), wv.split(chunk_size), wl.split(chunk_size))]))
        return torch.cat(images, -1).float().reshape(h, w, -1)


def decoded_luminance(model, chunk_size: int = 32768) -> torch.Tensor:
    """Rec. 709 luminance ``(H, W)`` of the positional plane decoded at normal view and light (``hex``'s default)."""
    rgb = decoded_appearance(model, chunk_size=chunk_size, pairs=APPEARANCE_PAIRS[:1])  # normal view and light
    return rgb @ torch.tensor([0.2126, 0.7152, 0.0722], device=rgb.device)


def model_digest(model) -> str:
    """SHA-256 of a model's state dict (names, dtypes, shapes, bytes): the model file's ``tensor_sha256``."""
    return tensor_digest(model.state_dict())


def _argument_key(arguments: dict[str, Any]) -> dict[str, Any]:
    """JSON-able form of ``arguments`` for the cache key: arrays by their digest."""
    out = {}
    for name, value in arguments.items():
        if isinstance(value, (torch.Tensor, np.ndarray)):
            value = torch.as_tensor(value)
            out[name] = "sha256:" + tensor_digest({name: value})
        else:
            out[name] = value
    return out


def _build_synthesizer(model, method: str, seed: int, arguments: dict[str, Any]):
    plane = model.positional_plane().detach()
    arguments = dict(arguments)
    if method in ("auto", "struct") and "guide" not in arguments:
        arguments["guide"] = decoded_appearance(model, plane)
    if method == "hex" and "luminance" not in arguments:
        arguments["luminance"] = decoded_luminance(model)
    if getattr(model, "separate_channels", 0) and "separate" not in arguments and method in ("auto", "hist"):
        arguments["separate"] = int(model.separate_channels)  # a relief model's height: its own transform
    return make_synthesizer(method, plane, seed=seed, **arguments)


def _stored_arguments(synthesizer, arguments: dict[str, Any]) -> dict[str, Any]:
    """The arguments the resolved method takes, without the tables' inputs (JSON)."""
    import inspect

    accepted = set(inspect.signature(synthesizer_class(synthesizer.name).__init__).parameters)
    return {k: v for k, v in arguments.items() if k in accepted and k not in _TABLE_INPUTS}


def point_query(model, synthesizer, path: DecodePath):
    """The synthesized BTF's point query in exemplar repeats ``(points (N, 2) float64, w_view, w_light) -> (N, 3)``,
    relief included (the fit targets of the footprint decoders)."""
    from ..representations.base import Representation

    relief = type(model).visible_uv is not Representation.visible_uv

    def query(points, wv, wl):
        if relief:
            points = model.visible_uv(points, wv, synthesizer)
        return path.decode(synthesizer.latent(points).to(path.decoder.first_bias.device), wv, wl)

    return query


def _fit_footprints(material: CompiledMaterial, progress: bool) -> CompiledMaterial:
    synth = material.synthesizer()
    if material.decoder is None or synth.level_of_detail() is None:
        return material
    fast = material.model.fast_decoder()
    path = DecodePath(material.decoder, fast.angular_features, angular_planes=fast.angular_planes)
    h, w = synth.exemplar.shape[:2]
    decoder = fit_footprint_decoders(material.decoder, synth, point_query(material.model, synth, path),
                                     fast.angular_features, float(np.sqrt(h * w)), progress=progress)
    return replace(material, decoder=decoder, _synthesizers=material._synthesizers)


def compile_material(model, method: str = "auto", seed: int = 0, *, footprints: bool = True, progress: bool = True,
                     base: CompiledMaterial | None = None, synthesizer=None, **arguments) -> CompiledMaterial:
    """Compile ``model`` for synthesis ``method`` and ``seed`` (see the module docstring).

    Parameters
    ----------
    model : Representation
        A fitted representation with a positional plane.
    method : str
        ``auto`` (``struct`` for structured materials, else ``hist``), or a method name.
    seed : int
    footprints : bool
        Also fit the per-level decoders and mean appearance (footprint queries need them).
    progress : bool
        A progress bar over the per-level decoders (on a terminal; a line every few seconds in a log).
    base : CompiledMaterial, optional
        A material of the same model, method, seed and arguments compiled without footprints: its
        tables are reused and only the footprint decoders are fitted.
    synthesizer : Synthesizer, optional
        A ready synthesizer of the model's positional plane (``method``, ``seed`` and ``arguments`` are
        then its own; such a material has no cache key).
    **arguments
        The method's parameters (e.g. ``gamma`` for ``hist``).
    """
    if not hasattr(model, "positional_plane"):
        raise InputError(f"model: expected a Representation with a positional plane, got {type(model).__name__}")
    digest = model_digest(model)
    cacheable = synthesizer is None and (base is None or bool(base.key))  # a ready synthesizer has no key
    key = material_key(digest, method, seed, _argument_key(arguments), footprint_settings(footprints)) \
        if cacheable else ""
    if base is None:
        with torch.no_grad():
            synth = synthesizer if synthesizer is not None else _build_synthesizer(model, method, seed, arguments)
            fast = model.fast_decoder()
            decoder = None if fast is None else FoldedDecoder.fold(fast.decoder, *synth.output_map())
        choice = synth.choice.record() if synth.choice is not None else None
        base = CompiledMaterial(model=model, method=synth.name, seed=synth.seed,
                                arguments=_stored_arguments(synth, arguments),
                                synthesis=synth.prepared_arrays(),  # the tables and the pyramid
                                decoder=decoder, choice=choice, model_sha256=digest)
        base._synthesizers[str(model.positional_plane().device)] = synth
    material = _fit_footprints(base, progress) if footprints else base
    return replace(material, key=key, _synthesizers=material._synthesizers)


def footprint_settings(footprints: bool) -> dict[str, Any] | bool:
    """What the footprint decoders depend on besides the model and method (part of the cache key): the fits'
    sizes, or False without footprint decoders."""
    if not footprints:
        return False
    from . import footprint_decoders as f

    return {"queries": f.LEVEL_FIT_QUERIES, "grid": f.LEVEL_FIT_GRID, "steps": f.LEVEL_FIT_STEPS,
            "batch": f.LEVEL_FIT_BATCH, "lr": f.LEVEL_FIT_LR, "seed": f.LEVEL_FIT_SEED, "mean_nodes": f.MEAN_NODES,
            "mean_positions": f.MEAN_FIT_POSITIONS, "mean_pairs": f.MEAN_FIT_PAIRS, "mean_steps": f.MEAN_FIT_STEPS}


def _cache_path(key: str) -> Path | None:
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


def store_cached(material: CompiledMaterial) -> None:
    """Write ``material`` to the cache under its key (a cache that cannot be written costs only a warning)."""
    path = _cache_path(material.key)
    if path is None:
        return
    try:
        save_compiled(material, path)
    except OSError as e:
        warnings.warn(f"compiled-material cache: could not write {path} ({e}); the material is used unsaved",
                      stacklevel=3)


def cached_material(model, method: str = "auto", seed: int = 0, *, footprints: bool = True, progress: bool = True,
                    **arguments) -> tuple[CompiledMaterial, str]:
    """:func:`compile_material` through the cache: ``(material, how)``, ``how`` one of ``"cached"`` (read),
    ``"compiled"`` (built and stored) or ``"uncached"`` (the cache is off).

    Without ``footprints`` a cached material with footprint decoders is used as well (it holds the same
    tables); with ``footprints``, a cached material without them is completed (tables reused) and stored.
    ``auto`` with ``footprints`` is the material of the method it chooses (one fit per resolved method).
    """
    if method == "auto" and footprints:  # the footprint decoders are keyed by the method auto resolves to
        chosen, _ = cached_material(model, "auto", seed, footprints=False, progress=progress, **arguments)
        full, how = cached_material(model, chosen.method, seed, footprints=True, progress=progress, **chosen.arguments)
        return replace(full, choice=chosen.choice, _synthesizers=full._synthesizers), how
    device = model.positional_plane().device
    digest = model_digest(model)
    keys = {flag: material_key(digest, method, seed, _argument_key(arguments), footprint_settings(flag))
            for flag in (True, False)}
    for flag in ((True, False) if not footprints else (True,)):
        found = _read_cached(_cache_path(keys[flag]), device, digest)
        if found is not None:
            found.model = model  # the caller's module (equal contents): no second copy
            return found, "cached"
    base = None if not footprints else _read_cached(_cache_path(keys[False]), device, digest)
    if base is not None:
        base.model = model
    material = compile_material(model, method, seed, footprints=footprints, progress=progress, base=base, **arguments)
    if compiled_cache_dir() is None:
        return material, "uncached"
    store_cached(material)
    return material, "compiled"
