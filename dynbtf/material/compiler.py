"""Compile a fitted model for one synthesis method and seed: derive every table once, off-line.

:func:`compile_material` builds a :class:`~dynbtf.material.format.CompiledMaterial`: the synthesizer
on the model's positional plane (``auto`` resolved here, once; its off-line tables and pyramid), the
decoder with the method's output map folded into layer 1 and, with ``footprints=True``, the per-level
decoders and mean appearance of footprint queries (:mod:`dynbtf.material.footprint_decoders`, the
expensive part: a small fit per pyramid level, timed in ``docs/compiled_material.md``).
:func:`dynbtf.material.cache.open_or_compile` does the same through the on-disk cache.

Example
-------
>>> from dynbtf.representations.triple_plane import TriplePlane
>>> material = compile_material(TriplePlane(16, 16), "hist", seed=3, footprints=False)
>>> material.method, material.seed, sorted(material.synthesis)[:3]
('hist', 3, ['decorrelation.basis', 'decorrelation.mean', 'decorrelation.variances'])
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch

from ..conventions import spherical_to_direction
from ..decoder.folded import DecodePath, FoldedDecoder
from ..errors import InputError
from ..synthesis.registry import make_synthesizer, model_inputs, synthesizer_class
from ..representations.model_file import tensor_digest
from .footprint_decoders import fit_footprint_decoders
from .format import CompiledMaterial, material_key

__all__ = ["compile_material", "decoded_appearance", "decoded_luminance", "model_arguments", "MODEL_INPUTS",
           "APPEARANCE_PAIRS", "model_digest", "argument_key", "footprint_settings"]

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


def argument_key(arguments: dict[str, Any]) -> dict[str, Any]:
    """JSON-able form of a method's ``arguments`` for the cache key: arrays by their digest."""
    out = {}
    for name, value in arguments.items():
        if isinstance(value, (torch.Tensor, np.ndarray)):
            value = torch.as_tensor(value)
            out[name] = "sha256:" + tensor_digest({name: value})
        else:
            out[name] = value
    return out


#: The model inputs a method may take (:attr:`dynbtf.synthesis.base.Synthesizer.model_inputs`), each derived from a
#: fitted model (None: the model has none to give).
MODEL_INPUTS = {
    "appearance": lambda model: decoded_appearance(model, model.positional_plane().detach()),
    "luminance": lambda model: decoded_luminance(model),
    "separate_channels": lambda model: int(getattr(model, "separate_channels", 0)) or None,
}


def model_arguments(model, method: str, arguments: dict[str, Any]) -> dict[str, Any]:
    """``arguments`` completed with what ``method`` (or ``auto``'s candidates) takes from ``model`` and was not
    given: the appearance struct cuts along, hex's luminance, a relief's height channels kept out of hist's
    decorrelation (:func:`dynbtf.synthesis.registry.model_inputs`)."""
    arguments = dict(arguments)
    for name, source in model_inputs(method).items():
        if name not in arguments:
            value = MODEL_INPUTS[source](model)
            if value is not None:
                arguments[name] = value
    return arguments


def _build_synthesizer(model, method: str, seed: int, arguments: dict[str, Any]):
    return make_synthesizer(method, model.positional_plane().detach(), seed=seed,
                            **model_arguments(model, method, arguments))


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
    key = material_key(digest, method, seed, argument_key(arguments), footprint_settings(footprints)) \
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
