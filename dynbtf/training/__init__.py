"""Fitting representations to BTFs, evaluating them, and the fast whole-image training path.

* :func:`fit` / :class:`TrainConfig` -- gradient training (the paper's recipe), resumable.
* :func:`get_fitter` / :func:`register_fitter` -- ``dynbtf fit --repr KIND``; ``auto`` (the default,
  :mod:`~dynbtf.training.model_choice`) races the kinds on held-out pairs.
* :func:`evaluate_model` -- PSNR / DSSIM / FLIP on held-out pairs, tables and images.
"""

from .fit import FitResult, TrainConfig, checkpoint_path, fit, predict_images, texel_image_loss, training_provenance
from .evaluate import Evaluation, evaluate_model, resolve_eval_pairs
from .fitters import FITTERS, get_fitter, register_fitter
from . import model_choice  # noqa: F401  (registers --repr auto)
from .images import ImageStore, held_out_split

__all__ = ["fit", "TrainConfig", "FitResult", "checkpoint_path", "predict_images", "texel_image_loss",
           "training_provenance", "evaluate_model", "Evaluation", "resolve_eval_pairs", "get_fitter", "register_fitter", "FITTERS", "held_out_split", "ImageStore"]
