"""The registry behind ``dynbtf fit --repr KIND``: one fitter per representation kind.

A fitter turns a BTF into a model file. Gradient-trained kinds build a fresh
representation of the BTF's size and call :func:`dynbtf.training.fit.fit`;
closed-form kinds (PCA, SH) compute theirs directly from the training pairs of
:func:`dynbtf.training.images.held_out_split` and write it with
:func:`dynbtf.representations.model_file.save_model` and
:func:`dynbtf.training.fit.training_provenance`. The built-in fitters are all
here; a new kind registers its own with :func:`register_fitter`.

Signature: ``fitter(source, output, config: TrainConfig, *, progress=True, callback=None,
extra_provenance=None, **options) -> FitResult``; ``callback`` is :func:`~dynbtf.training.fit.fit`'s
per-step callback (closed-form fitters take no optimizer steps and never call it);
``extra_provenance`` is added to the model file's provenance. ``--repr auto``
(:mod:`dynbtf.training.model_choice`) races the gradient-trained kinds and registers here too.
"""

from __future__ import annotations

import time
from typing import Any, Callable

from ..data.base import BTFSource
from ..errors import InputError
from .fit import FitResult, TrainConfig, budget_left, fit

__all__ = ["FITTERS", "register_fitter", "get_fitter", "fit_triple_plane", "fit_parallax_triple_plane",
           "parallax_size_options", "parallax_stereo_options", "fit_neumip", "fit_pca_model", "fit_sh_model"]

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
    try:
        return FITTERS[kind]
    except KeyError:
        raise InputError(f"--repr: no fitter for {kind!r}; expected one of {sorted(FITTERS)}") from None


@register_fitter("triple")
def fit_triple_plane(source: BTFSource, output, config: TrainConfig | None = None, *, progress: bool = True,
                     callback=None, extra_provenance: dict[str, Any] | None = None, **options: Any) -> FitResult:
    """Fit the paper's Triple Plane to ``source``.

    ``options`` are :class:`~dynbtf.representations.triple_plane.TriplePlane`
    constructor arguments (``positional_channels``, ``angular_resolution``, ...);
    the initialization seed is ``config.seed``.
    """
    from ..representations.triple_plane import TriplePlane

    config = config or TrainConfig()
    rep = TriplePlane(source.height, source.width, seed=config.seed, **options)
    return fit(rep, source, config, output, progress=progress, callback=callback, extra_provenance=extra_provenance)


def parallax_size_options(source: BTFSource) -> dict[str, float]:
    """:class:`~dynbtf.representations.parallax.ParallaxTriplePlane` options the parallax fitter picks for
    ``source`` (given options win): none for BTFs that stereo sweeps whole
    (:func:`~dynbtf.training.stereo_height.auto_stereo_options` empty, e.g. 128 x 128 x 81 views); for
    larger ones ``height_refresh_texels`` = the same height change in uv units as the default 0.05 texels
    at 128 texels (the learned height moves by about as many uv units per step at any size, and every step
    reads every texel, so each refresh marches all ``H * W`` rays): 0.16 texels at 400 x 400."""
    from .stereo_height import auto_stereo_options

    if not auto_stereo_options(source):
        return {}
    return {"height_refresh_texels": 0.05 * max(source.height, source.width) / 128}


def parallax_stereo_options(source: BTFSource, given: dict[str, Any] | None = None) -> dict[str, Any]:
    """The :func:`~dynbtf.training.stereo_height.stereo_height` options the parallax fitter sweeps ``source``
    with: :func:`~dynbtf.training.stereo_height.auto_stereo_options` (a subset of views and lights on a large
    BTF), overridden by ``given`` (the fitter's ``stereo`` option). ``--repr auto`` runs its stereo evidence
    with these, so the race's estimate is the one the parallax fit starts from."""
    from .stereo_height import auto_stereo_options

    return auto_stereo_options(source) | dict(given or {})


@register_fitter("triple-parallax")
def fit_parallax_triple_plane(source: BTFSource, output, config: TrainConfig | None = None, *,
                              progress: bool = True, callback=None, extra_provenance: dict[str, Any] | None = None,
                              **options: Any) -> FitResult:
    """Fit the Triple Plane with parallax: estimate the height field by stereo, then train as the paper.

    ``options`` are :class:`~dynbtf.representations.parallax.ParallaxTriplePlane`
    constructor arguments, plus ``stereo`` (a dict of
    :func:`~dynbtf.training.stereo_height.stereo_height` options; on a large BTF
    :func:`~dynbtf.training.stereo_height.auto_stereo_options` adds a subset of views and
    lights unless given, and ``height_refresh_texels`` grows with the size), and ``stereo_estimate``: the
    ``(height, trusted)`` pair of ``stereo_height(source, return_trusted=True, **stereo)`` when the caller has
    already computed it (``--repr auto`` does). The height is estimated from the BTF's images before training
    and refined by it; a resumed run takes it from its checkpoint. The provenance records the stereo options
    and, when the height was set in this run, the fraction of texels whose estimate was trusted.
    """
    if config is not None and config.subtexel:
        raise InputError("--subtexel (TrainConfig.subtexel): the 'triple-parallax' representation has no sub-texel "
                         "term (its fetch moves with the view); it applies to the Triple Plane ('triple')")
    from ..representations.parallax import ParallaxTriplePlane
    from .fit import checkpoint_path, finished_fit
    from .stereo_height import stereo_height

    started = time.perf_counter()  # a time budget covers the stereo estimate too
    config = config or TrainConfig()
    stereo_options = parallax_stereo_options(source, options.pop("stereo", None))
    estimate = options.pop("stereo_estimate", None)
    options = parallax_size_options(source) | options
    rep = ParallaxTriplePlane(source.height, source.width, seed=config.seed, **options)
    height_field = {"method": "plane-sweep stereo (dynbtf.training.stereo_height)", "options": stereo_options}
    # a resumed run reads the height from the checkpoint; a finished one is returned as it is
    if not checkpoint_path(output).exists() and not finished_fit(rep, source, config, output):
        height, trusted = estimate or stereo_height(source, progress=progress, return_trusted=True, **stereo_options)
        rep.set_height(height)
        height_field["trusted_fraction"] = float(trusted.double().mean())
    provenance = {"height_field": height_field} | (extra_provenance or {})
    return fit(rep, source, budget_left(config, started), output, progress=progress, callback=callback,
               extra_provenance=provenance)


@register_fitter("neumip")
def fit_neumip(source: BTFSource, output, config: TrainConfig | None = None, *, progress: bool = True,
               callback=None, extra_provenance: dict[str, Any] | None = None, **options: Any) -> FitResult:
    """``dynbtf fit --repr neumip``: the shared gradient trainer (:func:`dynbtf.training.fit.fit`).

    ``options`` are :class:`~dynbtf.representations.neumip.NeuMIP` constructor arguments (``channels``,
    ``hidden``, ...); the initialization seed is ``config.seed``. The optimizer groups come from
    :meth:`NeuMIP.param_groups` (Adam, lr 1e-3).
    """
    from ..representations.neumip import NeuMIP

    config = config or TrainConfig()
    rep = NeuMIP(source.height, source.width, seed=config.seed, **options)
    return fit(rep, source, config, output, progress=progress, callback=callback, extra_provenance=extra_provenance)


@register_fitter("pca")
def fit_pca_model(source: BTFSource, output, config: TrainConfig | None = None, *, progress: bool = True,
                  callback=None, extra_provenance: dict[str, Any] | None = None, **options: Any) -> FitResult:
    """``dynbtf fit --repr pca``: :func:`~dynbtf.representations.pca.fit_pca` on the training pairs, as a model file.

    ``options`` are :func:`~dynbtf.representations.pca.fit_pca` keywords (``components``, ``centered``, ...);
    the randomized SVD's seed is ``config.seed``.
    """
    from ..representations.pca import fit_pca
    from .closed_form import fit_closed_form

    config = config or TrainConfig()
    return fit_closed_form(fit_pca, source, output, config, progress=progress, extra_provenance=extra_provenance,
                           **({"seed": config.seed} | options))


@register_fitter("sh")
def fit_sh_model(source: BTFSource, output, config: TrainConfig | None = None, *, progress: bool = True,
                 callback=None, extra_provenance: dict[str, Any] | None = None, **options: Any) -> FitResult:
    """``dynbtf fit --repr sh``: :func:`~dynbtf.representations.sh.fit_sh` on the training pairs, as a model file.

    ``options`` are :func:`~dynbtf.representations.sh.fit_sh` keywords (``bands``, ``neighbours``).
    """
    from ..representations.sh import fit_sh
    from .closed_form import fit_closed_form

    return fit_closed_form(fit_sh, source, output, config, progress=progress, extra_provenance=extra_provenance,
                           **options)
