"""Fitting closed-form representations (PCA, SH) behind the same ``dynbtf fit`` interface.

A closed-form kind has no gradient training: a function computes it from the
training (view, light) pairs. :func:`fit_closed_form` wraps such a function so
that its result is indistinguishable, for evaluation and comparison, from a
gradient-trained model: the same held-out split
(:func:`dynbtf.training.images.held_out_split` with ``config.held_out_fraction``
and ``config.seed``), the same provenance block
(:func:`dynbtf.training.fit.training_provenance`, with ``training_seconds`` =
wall time of the fit) and the same model file (:func:`save_model`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from ..data.base import BTFSource
from ..errors import InputError
from ..representations.base import Representation
from ..representations.model_file import model_size_report, read_model_metadata, save_model
from .fit import FitResult, TrainConfig, training_provenance
from .images import held_out_split

__all__ = ["fit_closed_form"]


def fit_closed_form(compute: Callable[..., Representation], source: BTFSource, output, config: TrainConfig | None,
                    *, progress: bool = True, extra_provenance: dict[str, Any] | None = None,
                    **options: Any) -> FitResult:
    """Run ``compute(source, pairs=train_pairs, progress=progress, **options)`` and write the model file.

    Parameters
    ----------
    compute : callable
        E.g. :func:`dynbtf.representations.pca.fit_pca`; returns the fitted representation.
    source : BTFSource
    output : str or Path
        Model file to write (atomically).
    config : TrainConfig, optional
        Only ``held_out_fraction`` and ``seed`` (the split) matter here.
    progress : bool
        Passed to ``compute`` (its tqdm bar) and prints a summary line.
    extra_provenance : dict, optional
        Added to the model file's provenance.
    **options
        Keyword arguments of ``compute`` (e.g. ``components=5``).

    Returns
    -------
    FitResult
        ``history`` is empty; ``finished`` is True.
    """
    if output is None:
        raise InputError("output: a model file path is required")
    config = (config or TrainConfig()).validate()
    if config.subtexel:
        raise InputError("--subtexel (TrainConfig.subtexel): a representation fitted in closed form has no training "
                         "loss to add it to; it applies to the Triple Plane ('triple')")
    output = Path(output)
    train_pairs, held_out = held_out_split(source.n_views, source.n_lights, config.held_out_fraction, config.seed)
    start = time.perf_counter()
    rep = compute(source, pairs=train_pairs, progress=progress, **options)
    elapsed = time.perf_counter() - start
    size_info = model_size_report(rep, source.nbytes_float32)
    provenance = training_provenance(
        source, held_out, seed=config.seed, training={"method": f"closed form ({compute.__name__})",
                                                      "held_out_fraction": config.held_out_fraction,
                                                      "seed": config.seed, "options": options},
        finished=True, training_seconds=elapsed, size=size_info, n_training_pairs=int(len(train_pairs)),
        **(extra_provenance or {}))
    save_model(output, rep, provenance)
    if progress:
        print(f"wrote {output} ({size_info['summary']}; fitted in {elapsed:.1f} s from "
              f"{len(train_pairs)} pairs, {len(held_out)} held out)")
    return FitResult(output, rep, read_model_metadata(output), [], True)
