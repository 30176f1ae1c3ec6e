"""Guided synthesis of a fitted material: its content placed where a target painted over the surface says.

:func:`guided_btf` builds a :class:`~dynbtf.infinite_btf.SynthesizedBTF` whose synthesizer is
:class:`~dynbtf.synthesis.guided_blending.GuidedBlending` (histogram-preserving blending whose samples come
from exemplar content of the target's label):

* the exemplar's labels are the model's own classes (:func:`exemplar_classes`): k-means on its positional
  plane decoded under a few view/light pairs, numbered from the darkest class (0) to the brightest,
  by their decoded luminance at normal view and light; or labels the caller gives;
* the target is a label image over the surface, in ``uv`` units; or a grey image in ``[0, 1]``, whose
  levels are cut into ``classes`` equal bins (:func:`target_labels`), so that a painted dark region
  receives the material's darkest content.

Example: the worn, dark parts of a leather along the bottom of a panel, the rest as it comes::

    btf = guided_btf("leather.dbtfm", grey_image, classes=2, target_size=4.0, scale=8.0)
    rgb = btf.eval(uv, w_view, w_light)

Footprint queries read the pyramid at the guided samples (as hist's read it at its own). The Mitsuba plugin runs
guided hist, hex and struct (its ``target`` parameter); the web export runs them in the shader
(``export_web(btf.material, out_dir, methods=(btf.material.method,))``, or ``dynbtf export --target``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .errors import InputError
from .infinite_btf import SynthesizedBTF
from .material import open_model_file
from .material.compiler import decoded_appearance, decoded_luminance, model_arguments
from .synthesized import synthesized_btf
from .synthesis.guided_blending import (GuidedBlending, GuidedCellQuilting, GuidedHexTiling, LabelField,
                                       exemplar_labels)

__all__ = ["guided_btf", "exemplar_classes", "target_labels", "example_target", "guidance_options",
           "GuidanceOptions", "guided_synthesizer"]


def example_target(side: int = 64) -> np.ndarray:
    """A painted grey target ``(side, side)`` in ``[0, 1]`` for demonstrations: a light ground with a dark
    diagonal band and a dark disc (row 0 at ``v = 0``)."""
    y, x = (np.mgrid[0:side, 0:side] + 0.5) / side
    dark = (np.abs(x - y) < 0.12) | ((x - 0.75) ** 2 + (y - 0.25) ** 2 < 0.15 ** 2)
    return np.where(dark, 0.1, 0.9)


def exemplar_classes(model, classes: int, seed: int = 0) -> np.ndarray:
    """A fitted model's texels in ``classes`` classes ``(H, W)`` int64: k-means on its decoded appearance
    (:func:`dynbtf.material.compiler.decoded_appearance`), class 0 the darkest at normal view and light."""
    plane = model.positional_plane().detach()
    return exemplar_labels(decoded_appearance(model, plane).cpu(), classes, seed=seed,
                           order_by=decoded_luminance(model).cpu())


def target_labels(target, classes: int) -> np.ndarray:
    """A target image as labels ``(H, W)`` int64: integer images as they are; float images (grey levels in
    ``[0, 1]``, colour images by their mean) cut into ``classes`` equal bins, ``[0, 1/classes)`` -> 0."""
    image = np.asarray(target.detach().cpu().numpy() if isinstance(target, torch.Tensor) else target)
    if image.ndim == 3 and image.shape[-1] in (1, 3, 4):
        image = image[..., :3].mean(-1) if image.shape[-1] >= 3 else image[..., 0]
    if image.ndim != 2 or image.size == 0:
        raise InputError(f"target: expected an image (H, W), got shape {image.shape}")
    if np.issubdtype(image.dtype, np.integer):
        if image.min() < 0 or image.max() >= classes:
            raise InputError(f"target: labels must lie in [0, {classes}) for {classes} classes, got "
                             f"{image.min()} to {image.max()}")
        return image.astype(np.int64)
    if not np.isfinite(image).all() or image.min() < 0.0 or image.max() > 1.0:
        raise InputError("target: expected grey levels in [0, 1] (finite) or integer labels")
    return np.minimum(np.floor(image * classes), classes - 1).astype(np.int64)


#: The methods guided synthesis steers (``auto`` steers ``hist``).
GUIDED_METHODS = ("hist", "hex", "struct")


def guided_method(method: str, cells=None, *, where: str = "--target") -> str:
    """The method a guided request runs (``auto``: ``hist``), or an :class:`InputError` that starts with ``where``:
    a method guidance does not steer, or ``struct`` without ``cells`` (it chooses whole cells by class, so a cell
    must be about one element of the material)."""
    if method == "auto":
        return "hist"
    if method not in GUIDED_METHODS:
        raise InputError(f"{where}: guided synthesis steers hist, hex or struct (auto: hist), got method {method!r}")
    if method == "struct" and not cells:
        raise InputError(f"{where}: guided struct chooses whole cells by class, so give its cells (--cells), about "
                         "one cell per element of the material (e.g. 8 for eight bricks per repeat)")
    return method


def guided_synthesizer(method: str) -> str:
    """The registry name of the guided synthesizer of ``method`` (``hist`` -> ``guided``, ``hex`` -> ``guided-hex``,
    ``struct`` -> ``guided-struct``: the class whose ``base_method`` it is)."""
    from .synthesis.registry import SYNTHESIZERS

    names = [name for name, cls in SYNTHESIZERS.items() if getattr(cls, "base_method", None) == method]
    if len(names) != 1:
        raise InputError(f"method: guided synthesis steers hist, hex or struct, got {method!r}")
    return names[0]


def guided_btf(model, target, *, classes: int = 2, labels=None, target_size: float = 1.0,
               target_wrap: str = "repeat", scale: float = 1.0, seed: int = 0, candidates: int = 16,
               softness: float = 0.0, method: str = "hist", footprints: bool = False, **params) -> SynthesizedBTF:
    """A synthesized BTF of ``model`` whose content follows ``target`` (see the module docstring).

    Parameters
    ----------
    model : Representation or path of a model file
    target : ``(H, W)`` image
        Labels (integers in ``[0, classes)``) or grey levels in ``[0, 1]`` (:func:`target_labels`), laid over
        ``target_size`` x ``target_size`` uv units, repeated or clamped (``target_wrap``).
    classes : int, default 2
        Classes of the exemplar (:func:`exemplar_classes`) when ``labels`` is not given.
    labels : ``(H, W)`` integers, optional
        The exemplar's labels (the positional plane's size).
    scale, seed : as :func:`~dynbtf.synthesized.synthesized_btf`'s.
    candidates, softness : :class:`~dynbtf.synthesis.guided_blending.GuidedBlending`'s.
    method : {"hist", "hex", "struct"}, default "hist"
        The synthesis that is guided (:class:`~dynbtf.synthesis.guided_blending.GuidedBlending`,
        :class:`~dynbtf.synthesis.guided_blending.GuidedHexTiling` or
        :class:`~dynbtf.synthesis.guided_blending.GuidedCellQuilting`, with ``**params`` its parameters; hex's
        ``luminance`` and struct's ``guide`` default to the model's decoded appearance, as for ``hex`` and
        ``struct``). struct chooses whole cells by label: give it ``cells`` of about one element
        (``cells=8`` for eight elements per repeat), so that a cell's content is of one label.
    footprints : bool, default False
        Also fit the per-level decoders of footprint queries (not cached: the guidance is not in the cache's key).
    """
    method = guided_method(method, params.get("cells"), where="method")
    if isinstance(model, (str, bytes)) or hasattr(model, "__fspath__"):
        model, material = open_model_file(model)
        if material is not None:
            raise InputError("model: a compiled material fixes its method; guided synthesis needs the model file "
                             "(.dbtfm) it was compiled from")
    if not hasattr(model, "positional_plane"):
        raise InputError(f"model: expected a Representation with a positional plane, got {type(model).__name__}")
    from .errors import positive_number

    scale = positive_number("scale", scale, "exemplar repeats per uv unit")
    params = model_arguments(model, method, params)  # hex's luminance, struct's guide, a relief's height channels
    classes = int(classes)
    exemplar = labels if labels is not None else exemplar_classes(model, classes, seed)
    field = LabelField(target_labels(target, classes), size=float(target_size) * float(scale), wrap=target_wrap)
    plane = model.positional_plane().detach()
    if method == "struct":  # whole cells: no per-sample search, no softness
        synth = GuidedCellQuilting(plane, seed, labels=exemplar, target=field, **params)
    else:
        kind = GuidedBlending if method == "hist" else GuidedHexTiling
        synth = kind(plane, seed, labels=exemplar, target=field, candidates=candidates, softness=softness, **params)
    return synthesized_btf(model, synth, scale=scale, footprints=footprints)


@dataclass(frozen=True)
class GuidanceOptions:
    """A guided request as a command line gives it (``--target IMAGE`` and its companions), checked by
    :func:`guidance_options`: what ``dynbtf synth``, ``dynbtf render`` and ``dynbtf export`` build from."""

    #: the painted grey image ``(H, W)`` in ``[0, 1]`` (:func:`dynbtf.io.load_painted_image`)
    image: np.ndarray
    #: the method guided (``hist``, ``hex`` or ``struct``; ``auto`` asked for ``hist``)
    method: str
    classes: int
    #: uv units the image covers
    target_size: float
    target_wrap: str
    softness: float
    #: struct's cells per repeat (None for hist and hex)
    cells: int | None

    def build(self, model, *, scale: float, seed: int = 0, footprints: bool = False, **params) -> SynthesizedBTF:
        """The guided synthesized BTF of ``model`` (:func:`guided_btf`) at ``scale`` exemplar repeats per uv unit;
        ``params``: the method's further parameters (e.g. hist's ``gamma``)."""
        if self.method == "struct":
            params["cells"] = self.cells
        return guided_btf(model, self.image, classes=self.classes, target_size=self.target_size,
                          target_wrap=self.target_wrap, scale=scale, seed=seed, softness=self.softness,
                          method=self.method, footprints=footprints, **params)


def guidance_options(target, *, method: str = "auto", classes: int = 2, target_size: float = 1.0,
                     target_wrap: str = "repeat", softness: float = 0.0, cells=None,
                     units: str = "uv units") -> GuidanceOptions:
    """The command line's guidance (``--target`` an image file, ``--method``, ``--classes``, ``--target-size`` in
    ``units``, ``--target-wrap``, ``--softness``, ``--cells``) checked, each error one :class:`InputError` line
    naming its option, and the target image read: before any model loads."""
    from .errors import positive_number
    from .io import load_painted_image

    method = guided_method(method, cells)
    spec = str(target)
    if spec == "noise" or spec.startswith("noise:"):
        raise InputError("--target: expected an image file (a painted target), not a noise spec")
    if not Path(spec).is_file():
        raise InputError(f"--target: {spec}: no such image file")
    if isinstance(classes, bool) or int(classes) != classes or not 2 <= classes <= 255:
        raise InputError(f"--classes: expected 2 to 255 classes, got {classes}")
    target_size = positive_number("--target-size", target_size, units)
    if target_wrap not in ("repeat", "clamp"):
        raise InputError(f"--target-wrap: expected 'repeat' or 'clamp', got {target_wrap!r}")
    if not (np.isfinite(float(softness)) and 0.0 <= float(softness) <= 1.0):
        raise InputError(f"--softness: expected a weight factor in [0, 1], got {softness}")
    image = load_painted_image(spec, "--target")
    return GuidanceOptions(image=image, method=method, classes=int(classes), target_size=float(target_size),
                           target_wrap=target_wrap, softness=float(softness),
                           cells=int(cells) if method == "struct" else None)
