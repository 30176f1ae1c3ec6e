"""The registry behind ``dynbtf fit --repr KIND``: one fitter per representation kind.

A fitter turns a BTF into a model file. Gradient-trained kinds build a fresh
representation of the BTF's size and call :func:`dynbtf.training.fit.fit`;
closed-form kinds (PCA, SH) compute theirs directly from the training pairs of
:func:`dynbtf.training.images.held_out_split` and write it with
:func:`dynbtf.representations.model_file.save_model` and
:func:`dynbtf.training.fit.training_provenance`. Fitters register with
:func:`register_fitter`; modules that define them are imported by
:func:`get_fitter` (the same built-in list as the representation registry).

Signature: ``fitter(source, output, config: TrainConfig, *, progress=True, **options) -> FitResult``.
"""

from __future__ import annotations

from typing import Any, Callable

from ..data.base import BTFSource
from ..errors import InputError
from .fit import FitResult, TrainConfig, fit

__all__ = ["FITTERS", "register_fitter", "get_fitter", "fit_triple_plane", "fit_parallax_triple_plane"]

#: kind -> fitter
FITTERS: dict[str, Callable[..., FitResult]] = {}


def register_fitter(kind: str):
    """Decorator: make ``fitter`` the one ``dynbtf fit --repr kind`` runs."""

    def deco(fn):
        FITTERS[kind] = fn
        return fn

    return deco


def get_fitter(kind: str) -> Callable[..., FitResult]:
    """The fitter registered for ``kind``; a clear error lists the known kinds."""
    from ..representations import _load_builtin  # noqa: F401  (kinds may register fitters at import)

    try:
        return FITTERS[kind]
    except KeyError:
        raise InputError(f"--repr: no fitter for {kind!r}; expected one of {sorted(FITTERS)}") from None


@register_fitter("triple")
def fit_triple_plane(source: BTFSource, output, config: TrainConfig | None = None, *, progress: bool = True,
                     **options: Any) -> FitResult:
    """Fit the paper's Triple Plane to ``source``.

    ``options`` are :class:`~dynbtf.representations.triple_plane.TriplePlane`
    constructor arguments (``positional_channels``, ``angular_resolution``, ...);
    the initialization seed is ``config.seed``.
    """
    from ..representations.triple_plane import TriplePlane

    config = config or TrainConfig()
    rep = TriplePlane(source.height, source.width, seed=config.seed, **options)
    return fit(rep, source, config, output, progress=progress)


@register_fitter("triple-parallax")
def fit_parallax_triple_plane(source: BTFSource, output, config: TrainConfig | None = None, *,
                              progress: bool = True, **options: Any) -> FitResult:
    """Fit the Triple Plane with parallax: estimate the height field by stereo, then train as the paper.

    ``options`` are :class:`~dynbtf.representations.parallax.ParallaxTriplePlane`
    constructor arguments, plus ``stereo`` (a dict of
    :func:`~dynbtf.training.stereo_height.stereo_height` options). The height is
    estimated from the BTF's images before training and kept fixed; a resumed run
    takes it from its checkpoint.
    """
    from ..representations.parallax import ParallaxTriplePlane
    from .fit import checkpoint_path
    from .stereo_height import stereo_height

    config = config or TrainConfig()
    stereo_options = dict(options.pop("stereo", None) or {})
    rep = ParallaxTriplePlane(source.height, source.width, seed=config.seed, **options)
    if not checkpoint_path(output).exists():  # a resumed run reads the height from the checkpoint
        rep.set_height(stereo_height(source, progress=progress, **stereo_options))
    provenance = {"height_field": {"method": "plane-sweep stereo (dynbtf.training.stereo_height)",
                                   "options": stereo_options}}
    return fit(rep, source, config, output, progress=progress, extra_provenance=provenance)
