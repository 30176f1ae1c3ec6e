"""A synthesized BTF from a fitted model: open its compiled material, or compile it, then query it.

The query object, :class:`~dynbtf.infinite_btf.SynthesizedBTF`, answers from a compiled material it is given
and never builds one: a query never starts a fit. This module is the application-level step in front of it.
:func:`synthesized_btf` takes what a user has -- a fitted representation, a model file, a compiled material or
its file -- opens the model's compiled material for the method and seed from the cache, or compiles and
stores it (:func:`dynbtf.material.open_or_compile`; ``auto`` is resolved there, once), and returns the query
object on it.

Example
-------
>>> import torch
>>> from dynbtf.representations.triple_plane import TriplePlane
>>> btf = synthesized_btf(TriplePlane(16, 16), "hist", scale=8.0)
>>> btf.material.method, btf.scale
('hist', 8.0)
>>> w = torch.tensor([[0.0, 0.0, 1.0]])
>>> btf.eval(torch.tensor([[0.1, 0.2]], dtype=torch.float64), w, w).shape
torch.Size([1, 3])
"""

from __future__ import annotations

import copy
import warnings

from .errors import InputError
from .infinite_btf import SynthesizedBTF, same_device
from .material import CompiledMaterial, compile_material, decoded_appearance, open_model_file, open_or_compile
from .synthesis.base import Synthesizer

__all__ = ["synthesized_btf", "auto_method"]


def synthesized_btf(model, synthesizer: str | Synthesizer = "auto", scale: float = 1.0, seed: int = 0, *,
                    footprints: bool = False, chunk_size: int | None = None, precision: str = "fp32",
                    workers: int | None = None, device=None, level_decoders: bool = True,
                    **params) -> SynthesizedBTF:
    """The synthesized BTF of ``model`` with ``synthesizer`` and ``seed``, queried at ``scale``.

    Parameters
    ----------
    model : Representation, CompiledMaterial or path
        A fitted representation with a positional plane, a compiled material, or a file of either (a model
        file, :func:`~dynbtf.representations.model_file.load_model`; a ``.dbtfc``). A compiled material fixes
        its method and seed: ``synthesizer``, ``seed`` and ``params`` must then be left at their defaults.
    synthesizer : str or Synthesizer, default "auto"
        A method name (``tile``, ``linear``, ``hist``, ``hex``, ``quilt``, ``struct``) built on the model's
        positional plane with ``seed`` and ``**params``, or ``auto`` (``struct`` for structured materials,
        ``hist`` otherwise; ``btf.synthesizer.choice`` says why), or a ready synthesizer of the model's plane
        (then no ``params``; its material is compiled here and not cached).
    scale : float, default 1.0
        Exemplar repeats per unit of the user's ``uv``.
    seed : int, default 0
    footprints : bool, default False
        Also open or fit the material's footprint decoders (a fit per pyramid level the first time a model
        and method are compiled with them, then cached): footprint queries decode each level with its own
        decoder. Without them a footprint query decodes every level with the point decoder.
    chunk_size, precision, workers, device, level_decoders
        The query object's (:class:`~dynbtf.infinite_btf.SynthesizedBTF`). ``device`` also moves a
        representation there before its material is compiled.
    **params
        Method parameters (see each synthesizer).
    """
    if device is not None:
        from .device import resolve_device

        device = resolve_device(device)
    if isinstance(model, (str, bytes)) or hasattr(model, "__fspath__"):
        if params.get("scale_jitter"):
            warn_without_subtexel_term(model)
        model, material = open_model_file(model, device=device)
    elif isinstance(model, CompiledMaterial):
        model, material = model.model, model
    else:
        material = None
    if material is None:
        if not hasattr(model, "positional_plane") or not hasattr(model, "decode"):
            raise InputError(f"model: expected a Representation with a positional plane, got {type(model).__name__}")
        if device is not None and not same_device(model.positional_plane().device, device):
            model = copy.deepcopy(model).to(device)  # a copy: the caller's model stays where it is
    material = _material(model, material, synthesizer, seed, footprints, params)
    return SynthesizedBTF(material, scale, chunk_size=chunk_size, precision=precision, workers=workers,
                          device=device, level_decoders=level_decoders)


def warn_without_subtexel_term(path) -> bool:
    """Warn (and return True) when the model file at ``path`` was fitted without the sub-texel term: scaled samples
    (``scale_jitter``) read its plane between texel centres, where such a model's colours drift
    (docs/synthesis.md, "Scaled samples"). Files without a training record (not written by ``dynbtf fit``) pass."""
    from .material import is_compiled_material
    from .representations.model_file import read_model_metadata

    if is_compiled_material(path):
        return False
    training = read_model_metadata(path).get("provenance", {}).get("training")
    if not isinstance(training, dict) or training.get("subtexel"):
        return False
    warnings.warn(f"scale_jitter: {path} was fitted without the sub-texel term, so its colours between texel "
                  "centres drift and scaled samples show them (darker, other colours); a Triple Plane fitted with the "
                  "default recipe or --subtexel 0.25 has it, triple-parallax none (docs/synthesis.md, 'Scaled "
                  "samples')", stacklevel=3)
    return True


def _material(model, material, synthesizer, seed: int, footprints: bool, params: dict) -> CompiledMaterial:
    """The compiled material of ``model`` for the requested synthesizer (checked against a given ``material``)."""
    if material is not None:
        if params or isinstance(synthesizer, Synthesizer) or synthesizer not in ("auto", material.method) \
                or seed not in (0, material.seed):
            raise InputError(f"a compiled material fixes method {material.method!r} and seed {material.seed}: "
                             f"leave synthesizer, seed and method parameters at their defaults or compile again")
        if footprints and (material.decoder is None or len(material.decoder.levels) < 2):
            raise InputError("footprints: this compiled material has no footprint decoders; compile it with them "
                             "(dynbtf compile MODEL -o FILE without --no-footprints)")
        return material
    if isinstance(synthesizer, Synthesizer):
        if params:
            raise InputError(f"parameters {sorted(params)} given with a ready synthesizer; "
                             "pass them to the synthesizer instead")
        if not same_device(synthesizer.device, model.positional_plane().device):
            raise InputError(f"synthesizer: its exemplar is on {synthesizer.device}, the model on "
                             f"{model.positional_plane().device}; build it on the model's device")
        return compile_material(model, synthesizer=synthesizer, footprints=footprints)
    if not isinstance(synthesizer, str):
        raise InputError(f"synthesizer: expected a method name or a Synthesizer, got {type(synthesizer).__name__}")
    # arrays among the parameters (a guide, a luminance) enter the cache's key by their digest
    return open_or_compile(model, synthesizer, seed, footprints=footprints, **params)[0]


def auto_method(model):
    """What ``synthesizer="auto"`` chooses for a fitted ``model``: a :class:`~dynbtf.synthesis.auto.MethodChoice`
    measured on its :func:`~dynbtf.material.decoded_appearance` (the same choice :func:`synthesized_btf` makes)."""
    from .synthesis.auto import choose_method

    return choose_method(model.positional_plane().detach(), decoded_appearance(model))
