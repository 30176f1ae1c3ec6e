"""Fitting a representation to a BTF by gradient descent on whole-image batches (the paper's recipe).

Recipe (paper, supplementary): L1 loss; AdamW with the representation's
parameter groups (Triple Plane: lr 1e-3 for the planes, 3e-4 for the decoder,
PyTorch's default weight decay 0.01); the learning rate is multiplied by 0.9
after every epoch; each step uses 16 whole images, each under one (view, light)
pair. An **epoch** is one pass over the training pairs in a random order.

Option ``texel_groups = G > 1`` (not the paper's) splits each step's texels into
``G`` disjoint groups of ``n = N // G`` texels (``N mod G`` texels sit the step
out), each seen under its own 16 pairs: a step then covers ``16 G`` distinct
(view, light) pairs for the cost of 16 whole images, and an epoch (still
``pairs x texels`` samples) visits every pair ``G`` times, on a different ``1/G``
of its texels each time. Group ``g`` is the ``g``-th block of ``n`` consecutive
texels (row-major, wrapping) after a random start drawn per step, so a step's
batch is gathered with contiguous reads; scattered random groups learned the same
per step (held-out PSNR equal to float noise) but cost a random memory read
per texel. The angular planes and the
decoder see many more directions per step, which makes each sample count more
(``benchmarks/bench_training.py`` measures both).

**View-coherent batches.** A representation whose positional fetch depends on the
view (``view_coherent_batches = True``, e.g. the parallax Triple Plane) gets every
group's ``B`` pairs from **one view**: per epoch (and per pass ``k`` of the groups),
each view's training pairs in a random order are cut into blocks of ``B`` (the last
block wrapped round to ``B``), and the blocks are visited in a random order; an
epoch then has ``sum over views of ceil(pairs of the view / B)`` steps.

Any :class:`~dynbtf.representations.base.Representation` with parameters trains
with :func:`fit` through the abilities the base class declares with defaults:
``param_groups()`` (optimizer groups), ``texel_image_l1_loss(...)`` (the batch's loss;
fused for the Triple Plane and NeuMIP, :func:`dynbtf.decoder.fused_mlp.split_mlp_l1_loss`,
``has_fused_loss``), ``predict_texel_images(...)`` (images at texel centres) and
``view_coherent_batches``.

Held-out pairs (``held_out_fraction`` of all pairs, drawn from ``seed``) are never
used for training; they are stored in the checkpoint and in the model file.

Determinism and resuming
------------------------
All randomness is counter-based: the pair order of epoch ``e`` comes from
``numpy.random.default_rng([seed, 1, e])`` (pass ``k > 0`` of ``texel_groups``:
``[seed, 1, e, k]``) and the texel subset or the groups' start of step ``s``
(options ``texels_per_image``, ``texel_groups``) from ``default_rng([seed, 2, e, s])``; the model is
initialized from ``seed``. A checkpoint (``<output>.ckpt``, written atomically
with ``torch.save`` and read back with ``weights_only=True``) holds the model,
the optimizer state and the position (epoch, step); it is written every
``checkpoint_every`` steps, at the end of each epoch, when the time budget runs
out and when the run is interrupted (Ctrl-C, or an exception raised by a
``callback`` between steps). Running :func:`fit` again with the same output
continues from the checkpoint and ends with the same parameters as an
uninterrupted run (same ``workers``, same machine).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import json
import math
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..data.base import BTFSource
from ..device import resolve_device
from ..errors import InputError
from ..representations.base import Representation
from ..representations.model_file import load_model, model_size_report, save_model
from ..decoder.fused_mlp import resolve_precision, single_intra_op_thread
from .batches import BatchSampler, between_texel_count, between_texel_points
from .checkpoint import Checkpointer, checkpoint_path
from .distributed import from_environment
from .images import ImageStore, held_out_split
from .monitor import HeldOutMonitor
from .schedule import ANNEAL_FLOOR, SCHEDULES, make_schedule
from .step_loss import COMPILE_MODES, StepLoss, resolve_compile

__all__ = ["TrainConfig", "FitResult", "fit", "check_options", "TrainingDiverged", "StopTraining", "budget_left",
           "WRITE_RESERVE_SECONDS", "shared_image_cache", "steps_after_this_fit", "implausible_targets",
           "OPTION_RULES", "MAX_REFLECTANCE", "CommandLineOption", "command_line_options", "option_flag",
           "checkpoint_path", "texel_image_loss", "predict_images", "training_provenance", "finished_fit"]

#: Default largest |value| of a training target (reflectance ``pi f_r``): measured materials stay
#: below ~1e2 (specular peaks included); values beyond are decoding garbage.
MAX_REFLECTANCE = 1e4
#: A fit stops when its loss exceeds its first loss by this factor (diverged).
DIVERGENCE_FACTOR = 1e6
#: Under a time budget, the converge schedule's ceiling is re-planned at each held-out check to the steps this
#: fraction of the budget's rest affords (the rest: the last checks, the checkpoint and the model file).
BUDGET_PLAN_FRACTION = 0.95
#: Seconds of a time budget kept for writing the checkpoint and the model file after the last step.
WRITE_RESERVE_SECONDS = 1.0


def budget_left(config: "TrainConfig", started: float) -> "TrainConfig":
    """``config`` with ``max_minutes`` less the time since ``started`` (a ``time.perf_counter()`` time): what a step of
    a command passes on to the next, so that the command's budget covers all of them. At least a millisecond is
    left (the next step then stops at its first chance, its model written)."""
    if config.max_minutes is None:
        return config
    left = config.max_minutes - (time.perf_counter() - started) / 60.0
    return dataclasses.replace(config, max_minutes=max(left, 1e-5))


@dataclass(frozen=True)
class _Rule:
    """The valid values of one :class:`TrainConfig` option: ``kind`` ``"int"``, ``"number"`` (finite) or
    ``"choice"``; ``low``/``high`` bounds (``low_open``, ``high_open``: excluded); ``optional``: None allowed."""

    kind: str
    low: float = 0
    high: float = 0
    low_open: bool = False
    high_open: bool = False
    optional: bool = False
    choices: tuple = ()

    def expectation(self) -> str:
        """``"an integer in [1, 1000000]"``, ``"a finite number in (0, 1]"``, ``"'auto', 'fp32' or 'bf16'"``."""
        if self.kind == "choice":
            return ", ".join(repr(c) for c in self.choices[:-1]) + f" or {self.choices[-1]!r}"
        what = "an integer" if self.kind == "int" else "a finite number"
        low, high = (f"{int(v)}" if float(v).is_integer() else f"{v:g}" for v in (self.low, self.high))
        return f"{what} in {'(' if self.low_open else '['}{low}, {high}{')' if self.high_open else ']'}"

    def accepts(self, value) -> bool:
        if value is None:
            return self.optional
        if self.kind == "choice":
            return isinstance(value, str) and value in self.choices
        if isinstance(value, bool) or not isinstance(value, (int, float) if self.kind == "number" else int):
            return False
        if not math.isfinite(value):
            return False
        return (value > self.low if self.low_open else value >= self.low) and \
            (value < self.high if self.high_open else value <= self.high)


#: The valid values of every :class:`TrainConfig` option (one truth for :meth:`TrainConfig.validate`,
#: :func:`check_options` and the command line).
OPTION_RULES: dict[str, _Rule] = {
    "epochs": _Rule("int", 1, 10 ** 6),
    "images_per_step": _Rule("int", 1, 10 ** 6),
    "lr_decay": _Rule("number", 0, 1, low_open=True),
    "lr_scale": _Rule("number", 0, 1e6, low_open=True),
    "held_out_fraction": _Rule("number", 0, 1, high_open=True),
    "seed": _Rule("int", 0, 2 ** 63 - 1),
    "texels_per_image": _Rule("int", 1, 2 ** 40, optional=True),
    "texel_groups": _Rule("int", 1, 2 ** 20),
    "max_minutes": _Rule("number", 0, 1e9, low_open=True, optional=True),
    "checkpoint_every": _Rule("int", 1, 2 ** 40),
    "memory_budget_mb": _Rule("number", 0, 2 ** 30, low_open=True),
    "workers": _Rule("int", 1, 4096, optional=True),
    "chunk_texels": _Rule("int", 1, 2 ** 24),
    "monitor_pairs": _Rule("int", 0, 10 ** 6),
    "device": _Rule("choice", choices=()),  # any string; resolved (and checked) by dynbtf.device
    "precision": _Rule("choice", choices=("auto", "fp32", "bf16")),
    "compile": _Rule("choice", choices=COMPILE_MODES),
    "max_reflectance": _Rule("number", 0, 1e30, low_open=True),
    "schedule": _Rule("choice", choices=SCHEDULES),
    "monitor_every": _Rule("int", 0, 2 ** 40),
    "min_steps": _Rule("int", 0, 2 ** 40),
    "subtexel": _Rule("number", 0, 1e3, optional=True),
}


def check_options(**options) -> None:
    """Check the given :class:`TrainConfig` options (by field name) before anything uses them.

    :class:`InputError` ``"--flag (TrainConfig.name): expected ..., got ..."`` for the first one of the
    wrong type or out of range (e.g. ``epochs=0``, ``memory_budget_mb=inf``); unknown names too.

    >>> check_options(epochs=0)
    Traceback (most recent call last):
    ...
    dynbtf.errors.InputError: --epochs (TrainConfig.epochs): expected an integer in [1, 1000000], got 0
    """
    for name, value in options.items():
        rule = OPTION_RULES.get(name)
        if rule is None:
            raise InputError(f"unknown training option {name!r}; expected one of {sorted(OPTION_RULES)}")
        if name == "device":
            if not isinstance(value, str):
                raise InputError(f"--device (TrainConfig.device): expected a device name such as 'cpu', got {value!r}")
            continue
        if not rule.accepts(value):
            flag = option_flag(name)
            raise InputError(f"{flag} (TrainConfig.{name}): expected {rule.expectation()}"
                             + (" (or unset)" if rule.optional else "") + f", got {value!r}")


@dataclass(frozen=True)
class CommandLineOption:
    """How a :class:`TrainConfig` field appears on ``dynbtf fit``'s command line (the field's metadata
    ``"cli"``): its ``flag`` (empty: ``--`` and the name with dashes), its ``help`` text and the command's
    ``default`` (None: the recipe chooses)."""

    flag: str
    help: str
    default: Any


def _option(default, cli_default, help: str, *, flag: str = ""):
    """A :class:`TrainConfig` field (library ``default``) that is also a ``dynbtf fit`` option."""
    return field(default=default, metadata={"cli": CommandLineOption(flag, help, cli_default)})


def option_flag(name: str) -> str:
    """The command-line flag of :class:`TrainConfig` field ``name`` (``--memory-mb``, ``--epochs``, ...); error
    messages name fields without an option the same way."""
    spec = TrainConfig.__dataclass_fields__.get(name)
    cli = spec.metadata.get("cli") if spec is not None else None
    return cli.flag if cli is not None and cli.flag else "--" + name.replace("_", "-")


def command_line_options() -> dict[str, tuple[Any, CommandLineOption]]:
    """``{field name: (type, CommandLineOption)}`` of the :class:`TrainConfig` fields that are ``dynbtf fit``
    options, in field order; ``type`` is the field's annotation, resolved (``int``, ``float | None``, ...)."""
    import typing

    hints = typing.get_type_hints(TrainConfig)
    return {f.name: (hints[f.name], f.metadata["cli"]) for f in dataclasses.fields(TrainConfig) if "cli" in f.metadata}


@dataclass
class TrainConfig:
    """Options of :func:`fit` (defaults: the paper's recipe at the demo scale).

    Attributes
    ----------
    epochs : int
        Passes over the training pairs (the paper: 50 at 400^2 x 151^2). The
        default 12 converges on the 128 x 128 x 81 x 81 demo BTF.
    images_per_step : int
        Whole images per optimizer step (16 as in the paper).
    lr_decay : float
        Learning-rate factor applied after every epoch (0.9).
    lr_scale : float
        Multiplies every parameter group's learning rate (1: the paper's rates).
    held_out_fraction : float
        Fraction of (view, light) pairs never trained on (0.05).
    seed : int
        Seed of the split, the pair order, texel subsets and the initialization.
    texels_per_image : int or None
        Train on a random subset of this many texels per step (shared by the
        step's images) instead of whole images: for very large BTFs.
    texel_groups : int
        Split each step's texels into this many groups (blocks of consecutive
        texels after a random start), each under its own ``images_per_step``
        pairs (1: whole images, the paper's recipe). A BTF too large for the
        cache is read block by block from the source (the texels of the step only).
    max_minutes : float or None
        Stop (checkpointed, model written) after this much training time in this
        run; run again to continue. Under ``"converge"`` each held-out check also
        re-plans the ceiling to the steps the rest affords, so the fit ends annealed
        inside the budget even if the machine slows down (:mod:`dynbtf.training.schedule`).
    checkpoint_every : int
        Steps between checkpoints (also at every epoch end).
    memory_budget_mb : float
        RAM the float16 image cache may use; larger BTFs are read per step,
        only the step's texels (:meth:`dynbtf.data.base.BTFSource.read_texels`).
    workers : int or None
        Threads of the fused loss (default: torch's thread count).
    chunk_texels : int
        Texels per chunk of the fused loss.
    monitor_pairs : int
        Held-out pairs evaluated (PSNR) after each epoch for the progress display.
    device : str
        ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda:0"``, ...
    precision : str
        Arithmetic of the fused loss (decoder layers 2.., the bulk of the work): ``"fp32"``;
        ``"bf16"`` (bfloat16 products accumulated in float32, parameters, optimizer and
        gradients in float32: mixed precision; needs a CPU with AVX512-BF16); ``"auto"``
        (default: ``"fp32"``; see :func:`dynbtf.decoder.fused_mlp.resolve_precision`). The precision
        used is recorded in the model file.
    compile : str
        How a step's loss runs (:mod:`dynbtf.training.step_loss`): ``"off"`` (eager: the fused kernels),
        ``"kernels"`` (``torch.compile``: generated fused kernels), ``"graphs"`` (the same replayed as CUDA graphs;
        CUDA only) or ``"auto"`` (default: :func:`~dynbtf.training.step_loss.resolve_compile`). The
        model is the same to float32 rounding.
    max_reflectance : float
        Largest |value| (``pi f_r``, linear RGB) a training target may have (default
        :data:`MAX_REFLECTANCE`): a BTF beyond it decodes to garbage (e.g. flipped exponent bits)
        and the fit stops naming the first such image. Raise it for data that really is that bright.
    schedule : str
        ``"epochs"`` (default: ``epochs`` epochs, ``lr_decay`` per epoch) or ``"converge"`` (until
        the held-out monitor stops improving: the learning rate is halved at every stall and decays
        to 1/32 over the last third of the ceiling ``epochs``, the fit stops at a stall once it is 1/16;
        :mod:`dynbtf.training.schedule`).
    monitor_every : int
        Steps between held-out checks of ``"converge"`` (0: once per epoch).
    min_steps : int
        Fewest steps before ``"converge"`` may stop.
    """

    epochs: int = _option(12, None, "Passes over the training (view, light) pairs (auto: none, the fit runs until "
                          "the held-out monitor stops improving, at most the reference's steps; paper: 50, the "
                          "paper's).")
    images_per_step: int = _option(16, 16, "Whole images per optimizer step.")
    lr_decay: float = _option(0.9, None, "Learning-rate factor per epoch (paper: 0.9; auto: the reference's total "
                              "decay 0.9^30 spread over its epochs).")
    lr_scale: float = _option(1.0, None, "Multiplier of the learning rates (paper: 1, i.e. 1e-3 for planes, 3e-4 "
                              "for the decoder; auto: 6).")
    held_out_fraction: float = _option(0.05, 0.05, "Fraction of (view, light) pairs never trained on, for "
                                       "evaluation.")
    seed: int = _option(0, 0, "Seed of the held-out split, batch order and initialization.")
    texels_per_image: int | None = _option(None, None, "Train on a random subset of this many texels per step "
                                           "(auto: all up to 262,144).")
    texel_groups: int = _option(1, None, "Split each step's texels into this many groups, each under its own "
                                "--images-per-step pairs: more (view, light) pairs per step at the same cost (paper: "
                                "1, whole images; auto: 64).")
    max_minutes: float | None = _option(None, None, "Stop after this many minutes of training (checkpointed; run "
                                        "again to continue); the converge schedule re-plans its ceiling at each "
                                        "check to end annealed inside it. Default: no limit.")
    checkpoint_every: int = 100
    memory_budget_mb: float = _option(2048.0, None, "RAM (MB) for the float16 image cache; larger BTFs are read "
                                      "texel block by texel block from the source (paper: 2048; auto: 40% of RAM, at "
                                      "most 8 GiB).", flag="--memory-mb")
    workers: int | None = _option(None, None, "Threads of the fused training kernel (default: torch's).")
    chunk_texels: int = 256
    monitor_pairs: int = 16
    device: str = _option("auto", "auto", "auto (CUDA if available), cpu, cuda:0, ...")
    precision: str = _option("auto", "auto", "Arithmetic of the decoder's training kernel: fp32, bf16 (bfloat16 "
                             "products, float32 accumulation and parameters; CPUs with AVX512-BF16), or auto "
                             "(fp32: the same model on every CPU to float32 rounding; bf16 may train faster "
                             "where it runs, docs/results.md).")
    compile: str = _option("auto", "auto", "How a step's loss runs: off (eager, the fused kernels), kernels "
                           "(torch.compile's generated kernels), graphs (the same replayed as CUDA graphs; CUDA "
                           "only), or auto (off on the CPU; graphs on a GPU with Triton for the Triple Plane: "
                           "docs/results.md 'On a GPU'). The model is the same to float32 rounding.")
    max_reflectance: float = _option(MAX_REFLECTANCE, None, "Largest |value| a training image may hold "
                                     "(reflectance pi f_r, linear RGB; default 1e4): beyond it the BTF decodes to "
                                     "garbage and the fit stops naming the image. Raise it for data that really is "
                                     "that bright.")
    schedule: str = _option("epochs", None, "epochs: --epochs passes, lr x--lr-decay per epoch (paper); converge: "
                            "train until the held-out monitor stops improving (lr halved at every stall and "
                            "decaying to 1/32 over the last third of the ceiling --epochs; stop at a stall once lr is "
                            "1/16). auto: converge unless --epochs or --lr-decay is given.")
    monitor_every: int = 0
    min_steps: int = 0
    subtexel: float | None = _option(0.0, None, "Weight of a second L1 term at random points between texel centres "
                                     "(an eighth of a step's texels, under the step's first --images-per-step "
                                     "pairs), against the bilinear mix of the measured texels around each, so that "
                                     "the colours a renderer reads between centres are the measured ones' mix (0: "
                                     "off, the paper's recipe; auto: 0.25 for the Triple Plane, 0 for the kinds "
                                     "without the term; docs/triple_plane.md, 'Between texel centres').")

    def validate(self) -> "TrainConfig":
        """Check every option's type and range; :class:`InputError` names the option (and its command-line flag)
        and the valid range."""
        check_options(**dataclasses.asdict(self))
        return self

    # options that change the result: a checkpoint must agree on them to be resumed
    RESULT_FIELDS = ("images_per_step", "lr_decay", "lr_scale", "held_out_fraction", "seed", "texels_per_image",
                     "texel_groups", "chunk_texels", "precision", "schedule", "monitor_every", "min_steps")


@dataclass
class FitResult:
    """What :func:`fit` returns."""

    model_path: Path
    representation: Representation
    metadata: dict[str, Any]
    history: list[dict[str, float]] = field(default_factory=list)
    finished: bool = True


# ---------------------------------------------------------------------------- predictions and loss
def predict_images(rep: Representation, w_view: torch.Tensor, w_light: torch.Tensor, size: tuple[int, int] = None,
                   texels: torch.Tensor | None = None) -> torch.Tensor:
    """Model images at texel centres, ``(B, N, 3)``, for ``w_view, w_light (B, 3)``:
    :meth:`Representation.predict_texel_images <dynbtf.representations.base.Representation.predict_texel_images>`
    (``size``, the image's ``(H, W)``, is the representation's own and kept for callers that pass it)."""
    return rep.predict_texel_images(w_view, w_light, texels)


def texel_image_loss(rep: Representation, w_view: torch.Tensor, w_light: torch.Tensor, target: torch.Tensor,
                     size: tuple[int, int] = None, texels: torch.Tensor | None = None, *, chunk_texels: int = 256,
                     workers: int = 1, texel_groups: int = 1, precision: str = "fp32",
                     angular_taps: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
    """Mean L1 loss of a whole-image batch:
    :meth:`Representation.texel_image_l1_loss <dynbtf.representations.base.Representation.texel_image_l1_loss>`
    (fused for the Triple Plane and NeuMIP; shapes, ``texel_groups`` and ``angular_taps`` there)."""
    kwargs = {} if angular_taps is None else {"angular_taps": angular_taps}
    return rep.texel_image_l1_loss(w_view, w_light, target, texels, chunk_texels=chunk_texels, workers=workers,
                                   texel_groups=texel_groups, precision=precision, **kwargs)


def _param_groups(rep: Representation, lr_scale: float = 1.0) -> list[dict[str, Any]]:
    groups = [dict(g) for g in rep.param_groups()]
    for g in groups:
        g["lr"] = g["initial_lr"] = g["lr"] * lr_scale
    if not any(len(g["params"]) for g in groups):
        raise InputError(f"representation {rep.kind!r} has no trainable parameters: it cannot be fitted by "
                         "gradient descent (use its closed-form fitter)")
    return groups


# ---------------------------------------------------------------------------- provenance
def training_provenance(source: BTFSource, held_out: np.ndarray, **extra) -> dict[str, Any]:
    """The provenance block every fitter stores in a model file (source, held-out pairs, extras).

    ``source`` records the BTF's name, size, directions and content fingerprint
    (:func:`dynbtf.provenance.source_fingerprint`), which ``dynbtf eval`` checks
    (:func:`dynbtf.provenance.check_model_source`), and for a BTF resampled before the fit
    (:class:`~dynbtf.data.resampled.ResampledBTF`) its size before (``resampled_from``: rows, columns), so that
    the BTF given to ``dynbtf eval`` is resampled the same way (:func:`dynbtf.provenance.source_as_fitted`).
    """
    from ..provenance import source_fingerprint

    return {
        "source": {"name": source.name, "height": source.height, "width": source.width,
                   "n_views": source.n_views, "n_lights": source.n_lights,
                   "views": np.asarray(source.views).tolist(), "lights": np.asarray(source.lights).tolist(),
                   "raw_float32_bytes": source.nbytes_float32, "fingerprint": source_fingerprint(source),
                   **({"resampled_from": [source.metadata["resampled_from_height"],
                                          source.metadata["resampled_from_width"]]}
                      if "resampled_from_height" in source.metadata else {})},
        "held_out_pairs": np.asarray(held_out, dtype=np.int64).tolist(),
        **extra,
    }


#: The sub-texel term's weight where ``TrainConfig.subtexel`` is None (the auto recipe's), for a representation that
#: has the term (``bench_subtexel.py``: the weight that brought the colours between centres near their floor for
#: the least held-out PSNR).
AUTO_SUBTEXEL = 0.25


def subtexel_weight(rep: Representation, config: TrainConfig) -> float:
    """The sub-texel term's weight in a fit of ``rep``: ``config.subtexel``, or where it is None (auto)
    :data:`AUTO_SUBTEXEL` for a representation with the term and 0 for one without. An explicit weight on a
    representation without the term raises :class:`InputError`."""
    has_term = bool(getattr(rep, "has_subtexel_term", False))
    if config.subtexel is None:
        return AUTO_SUBTEXEL if has_term else 0.0
    if config.subtexel and not has_term:
        raise InputError(f"--subtexel (TrainConfig.subtexel): the {rep.kind!r} representation has no sub-texel "
                         "term; it applies to the Triple Plane ('triple')")
    return float(config.subtexel)


def _fingerprint(rep: Representation, source: BTFSource, config: TrainConfig) -> dict[str, Any]:
    # the sub-texel weight only where used: runs and model files from before it match as they did
    weight = subtexel_weight(rep, config)
    return {"kind": rep.kind, "config": rep.config(), "source": [source.name, *source.shape],
            **{name: getattr(config, name) for name in TrainConfig.RESULT_FIELDS},
            **({"subtexel": weight} if weight else {})}


def _jsonable(value: Any) -> Any:
    """``value`` as it reads back from a model file's JSON metadata (tuples become lists)."""
    return json.loads(json.dumps(value))


def _already_fitted(output: Path, rep: Representation, source: BTFSource, config: TrainConfig):
    """The metadata of ``output`` if it is a finished fit of this very run (same representation, BTF and
    result-changing options), else None: a rerun of a finished fit then returns at once. A model file of
    another run is refused (:class:`InputError` naming the differing options), as its checkpoint would be."""
    from ..errors import DynBTFError
    from ..representations.model_file import read_model_metadata

    if not output.is_file() or checkpoint_path(output).exists():
        return None
    try:
        meta = read_model_metadata(output)
    except DynBTFError:
        return None
    provenance = meta.get("provenance") or {}
    recorded = provenance.get("run")
    if not isinstance(recorded, dict):  # written before runs were recorded: overwritten as before
        return None
    current = _jsonable(_fingerprint(rep, source, config) | {"epochs": config.epochs})
    if recorded != current:
        differ = [k for k in {**recorded, **current} if recorded.get(k) != current.get(k)]
        raise InputError(f"{output}: holds a fit of a different training run (differs in {differ}); delete it or "
                         "choose another output to start over")
    return meta if provenance.get("finished") else None


def finished_fit(representation: Representation, source: BTFSource, config: TrainConfig, output) -> bool:
    """Whether ``output`` already holds the finished fit of this run (the same representation, BTF and result-changing
    options), which :func:`fit` returns at once: a fitter can skip its own preparation (e.g. the parallax fitter's
    stereo sweep). A model file of another run raises :class:`InputError`, as :func:`fit` would."""
    return _already_fitted(Path(output), representation, source, (config or TrainConfig()).validate()) is not None


class _InterruptFlag:
    """Turns SIGINT into a flag checked between steps (main thread only)."""

    def __init__(self) -> None:
        self.raised = False
        self._previous = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handler)
        return self

    def _handler(self, signum, frame):
        if self.raised:  # second Ctrl-C: give up at once
            raise KeyboardInterrupt
        self.raised = True

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def _saved_options(config: TrainConfig) -> dict[str, Any]:
    """The options a checkpoint records so that a resumed run (``dynbtf fit`` with a recipe) uses the same ones."""
    # where and how long this run computes is the run's own business, not the recipe's
    return {k: v for k, v in dataclasses.asdict(config).items()
            if k not in ("device", "workers", "max_minutes", "compile")}


def _check_memory(config: TrainConfig, sampler: BatchSampler, store: ImageStore) -> None:
    """A streamed BTF needs two steps' targets (the one trained on and the one prefetched) in the budget."""
    if store.cached:
        return
    step_bytes = 2 * sampler.b * sampler.texels_per_step * 3 * 4
    if step_bytes > config.memory_budget_mb * 1024 ** 2:
        raise InputError(f"--memory-mb {config.memory_budget_mb:g} is too small for one training step of this BTF: "
                         f"{sampler.b} images x {sampler.texels_per_step} texels need at least "
                         f"{math.ceil(step_bytes / 1024 ** 2)} MB (or use --texels-per-image)")


# ---------------------------------------------------------------------------- implausible data
class StopTraining(Exception):
    """Raised by a :func:`fit` callback to end training after the current step: the fit is checkpointed, its model
    file written (unfinished) and its :class:`FitResult` returned, as when a time budget runs out."""


class TrainingDiverged(InputError):
    """The loss became non-finite or grew by :data:`DIVERGENCE_FACTOR`: the fit stops before the update."""


def _btf_label(source: BTFSource) -> str:
    """The BTF's file path when it has one, else its name."""
    return str(source.metadata.get("path", source.name)) if isinstance(source.metadata, dict) else source.name


def implausible_targets(batch, limit: float) -> tuple[int, int, float] | None:
    """``(view, light, largest |value|)`` of the first image of ``batch`` (in pair order) holding a value that
    is non-finite or beyond ``limit``, else None.

    ``batch.target (B, G * n, 3)``: texel block ``g`` under pair ``batch.pairs[g * B + b]``
    (:class:`~dynbtf.training.batches.Batch`).
    """
    target = batch.target
    if target.numel() == 0:
        return None
    b, groups = target.shape[0], max(int(batch.groups), 1)
    largest = target.detach().abs().reshape(b, groups, -1).amax(-1)  # (B, G)
    largest = torch.where(torch.isnan(largest), math.inf, largest)
    bad = largest > limit
    if not bool(bad.any()):
        return None
    b_bad, g_bad = torch.nonzero(bad, as_tuple=True)
    order = g_bad * b + b_bad  # index into batch.pairs
    first = int(order.argmin())
    view, light = (int(x) for x in batch.pairs[int(order[first])])
    return view, light, float(largest[b_bad[first], g_bad[first]])


def _garbage_message(source: BTFSource, problem: tuple[int, int, float], limit: float) -> str:
    view, light, value = problem
    return (f"{_btf_label(source)}: image (view {view}, light {light}) holds values up to {value:.3g}, beyond any "
            f"plausible reflectance (--max-reflectance {limit:g}): the BTF decodes to garbage (a damaged file?); "
            f"check it with `dynbtf info`, or if the data really is this bright, rerun with --max-reflectance above "
            f"{value:.3g}")


def _image_problem(image: np.ndarray, limit: float) -> float | None:
    """The largest |value| of ``image`` (inf if any is NaN) when beyond ``limit``, else None."""
    image = np.asarray(image)
    largest = float(np.abs(image).max()) if image.size and np.isfinite(image).all() else \
        (math.inf if image.size else 0.0)
    return largest if largest > limit else None


class _PlausibleImages(BTFSource):
    """``source`` whose whole images are checked against ``limit`` as they are decoded (what the trainer's
    image cache reads: a value beyond float16 would otherwise be cached as inf, naming nothing); texels
    read straight from the source are checked per batch (:func:`implausible_targets`)."""

    #: Largest value of the trainer's float16 image cache.
    FLOAT16_MAX = 65504.0

    def __init__(self, source: BTFSource, limit: float) -> None:
        super().__init__()
        self.source, self.limit = source, limit
        self.cached = False  # set by the trainer: images are then stored as float16
        self.height, self.width, self.views, self.lights = source.height, source.width, source.views, source.lights
        self.name, self.metadata = source.name, source.metadata

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        image = self.source.image(view_index, light_index)
        largest = _image_problem(image, self.limit)
        if largest is not None:
            raise InputError(_garbage_message(self.source, (view_index, light_index, largest), self.limit))
        largest = _image_problem(image, self.FLOAT16_MAX) if self.cached else None
        if largest is not None:
            raise InputError(f"{_btf_label(self.source)}: image (view {view_index}, light {light_index}) holds values "
                             f"up to {largest:.3g}, beyond the float16 image cache ({self.FLOAT16_MAX:g}); to train "
                             "on data this bright, read it straight from the BTF: --memory-mb below the cache's "
                             "size")
        return image

    def _read_texels(self, pairs: np.ndarray, texels: np.ndarray, device=None):
        return self.source.read_texels(pairs, texels, device=device)


# ---------------------------------------------------------------------------- the command's plan
_STEPS_AFTER: contextvars.ContextVar[tuple[int, int | None]] = contextvars.ContextVar("steps_after_this_fit",
                                                                                       default=(0, None))


@contextlib.contextmanager
def steps_after_this_fit(steps: int, stop_at: int | None = None):
    """Within this block, a fit's progress shows the whole command's ETA (``command_eta``) as its own steps (up to
    its ceiling, or ``stop_at`` when the caller stops it there) plus ``steps`` more at its step time: what a command
    that runs several fits (``--repr auto``'s trials, then the winner's fit) has left after this one."""
    token = _STEPS_AFTER.set((max(int(steps), 0), stop_at))
    try:
        yield
    finally:
        _STEPS_AFTER.reset(token)


# ---------------------------------------------------------------------------- the image cache
_SHARED: list[dict] | None = None  # the stores of the innermost shared_image_cache(), else None


@contextlib.contextmanager
def shared_image_cache():
    """Within this block, the fits of one BTF share its decoded images: ``dynbtf fit --repr auto`` decodes the BTF
    once for its trials and the winner's fit, not once per fit. Outside, each fit decodes its own (and frees
    them when it returns)."""
    global _SHARED
    previous, _SHARED = _SHARED, []
    try:
        yield
    finally:
        _SHARED = previous


def _image_store(source: BTFSource, config: TrainConfig) -> ImageStore:
    """The training run's image cache of ``source``: whole images checked against ``config.max_reflectance`` as they
    are decoded; inside :func:`shared_image_cache`, the one an earlier fit of the same source and options made."""
    budget = int(config.memory_budget_mb * 1024 ** 2)
    if _SHARED is not None:
        for entry in _SHARED:
            if entry["source"] is source and entry["key"] == (config.max_reflectance, budget):
                return entry["store"]
    checked = _PlausibleImages(source, config.max_reflectance)
    store = ImageStore(checked, budget)
    checked.cached = store.cached
    if _SHARED is not None:
        _SHARED.append({"source": source, "key": (config.max_reflectance, budget), "store": store})
    return store


# ---------------------------------------------------------------------------- the loop
class _TrainingRun:
    """One run of :func:`fit`: its parts (sampler, optimizer, monitor, checkpointer) and its position.

    ``epoch, step`` is the next step to train; :meth:`train_steps` advances it, :meth:`checkpoint`
    records it, and a new run on the same output starts where the checkpoint left off.
    """

    def __init__(self, representation: Representation, source: BTFSource, config: TrainConfig, output: Path):
        if (representation.positional_plane().shape[0], representation.positional_plane().shape[1]) != \
                (source.height, source.width):
            raise InputError(f"representation's positional plane is "
                             f"{tuple(representation.positional_plane().shape[:2])} but the BTF {source.name!r} is "
                             f"{source.height} x {source.width} texels")
        self.subtexel = subtexel_weight(representation, config)
        self.source, self.config, self.output = source, config, output
        self.parallel, device = from_environment(resolve_device(config.device))
        self.device = device
        self.rep = rep = representation.to(device)
        rep.train()
        # CPU: cache-sized chunks over worker threads; GPU: one chunk, one launch sequence
        self.workers = int(config.workers or torch.get_num_threads()) if device.type == "cpu" else 1
        self.train_pairs, self.held_out = held_out_split(source.n_views, source.n_lights, config.held_out_fraction,
                                                         config.seed)
        self.store = _image_store(source, config)
        # cached images were checked whole as they were decoded (_PlausibleImages); texels read straight from the BTF
        # are checked per batch (the same decision in every process of a data-parallel fit)
        self.check_batches = self.parallel.any(not self.store.cached)
        self.sampler = BatchSampler(self.store, self.train_pairs, images_per_step=config.images_per_step,
                                    texel_groups=config.texel_groups, texels_per_image=config.texels_per_image,
                                    seed=config.seed, view_coherent=rep.view_coherent_batches, device=device,
                                    part=(self.parallel.rank, self.parallel.world))
        _check_memory(config, self.sampler, self.store)
        self.chunk_texels = config.chunk_texels if device.type == "cpu" else self.sampler.texels_per_image
        self.precision = resolve_precision(
            config.precision if rep.has_fused_loss or config.precision == "bf16" else "fp32", device)
        # what the model reads per (view, light) pair that depends on the directions alone, once for all pairs
        views = torch.as_tensor(source.views, dtype=torch.float32, device=device)
        lights = torch.as_tensor(source.lights, dtype=torch.float32, device=device)
        with torch.no_grad():
            self.angular_taps = rep.direction_taps(views.repeat_interleave(len(lights), 0), lights.repeat(len(views), 1))
        self.loss = StepLoss(rep, compile=resolve_compile(config.compile, device, rep),
                             chunk_texels=self.chunk_texels, workers=self.workers, precision=self.precision)
        # fused: one kernel per step for all parameters (same update, less time per step on the CPU)
        self.optimizer = torch.optim.AdamW(_param_groups(rep, config.lr_scale), fused=True)
        self.monitor = HeldOutMonitor(self.store, self.held_out, config.monitor_pairs, config.seed, device)
        self.schedule = make_schedule(config, self.sampler.steps_per_epoch)
        if self.schedule.kind == "converge" and len(self.monitor.pairs) == 0:
            raise InputError("--schedule converge stops when the held-out monitor stops improving: it needs held-out "
                             "pairs (--held-out-fraction > 0, TrainConfig.monitor_pairs > 0)")
        self.checkpointer = Checkpointer(checkpoint_path(output), _fingerprint(rep, source, config))
        self.epoch, self.step, self.elapsed, self.history = 0, 0, 0.0, []
        self.record: list[dict[str, float]] = []  # every held-out check: step, score, lr multiplier, time[, ceiling]
        self.budget_clock: dict[str, float] | None = None  # the budget's end, and this run's last check's time, step
        self.first_loss: float | None = None  # of this run (a resumed run: its first step)
        self.step_seconds: float | None = None  # recent seconds per step (a running mean), for the command's ETA
        if self.checkpointer.exists():
            state = self.checkpointer.restore(rep, self.optimizer, epochs=config.epochs,
                                              steps_per_epoch=self.sampler.steps_per_epoch)
            self.epoch, self.step = state["epoch"], state["step"]
            self.elapsed, self.history = state["elapsed_seconds"], state["history"]
            self.record = state["monitor"]
        self.total_steps = config.epochs * self.sampler.steps_per_epoch
        self.done_steps = min(self.epoch * self.sampler.steps_per_epoch + self.step, self.total_steps)
        self.last_checkpoint_step = self.done_steps
        self.finished = self._schedule_ended()
        self.size_info = model_size_report(rep, source.nbytes_float32)

    # ------------------------------------------------------------------ parts of a step
    def checkpoint(self) -> None:
        if not self.parallel.is_main:  # one writer; every process has the same state
            self.last_checkpoint_step = self.done_steps
            return
        self.checkpointer.save({"config": _saved_options(self.config), "model": self.rep.state_dict(),
                                "optimizer": self.optimizer.state_dict(), "epoch": self.epoch, "step": self.step,
                                "elapsed_seconds": self.elapsed, "history": self.history, "monitor": self.record,
                                "held_out_pairs": torch.from_numpy(self.held_out)})
        self.last_checkpoint_step = self.done_steps

    def _next_position(self) -> tuple[int, int]:
        return (self.epoch, self.step + 1) if self.step + 1 < self.sampler.steps_per_epoch else (self.epoch + 1, 0)

    def _step_inputs(self, epoch: int, step: int):
        """``(batch, (w_view, w_light, texels, taps, between))``: step ``(epoch, step)``'s batch and the tensors the
        loss reads besides its targets (directions, texel indices, the pairs' rows of the angular taps, and the
        sub-texel term's data or None: :meth:`_between_texels`). Prepared by the prefetch thread while the previous
        step trains."""
        batch = self.sampler.batch(epoch, step)
        wv, wl, taps = self._pair_inputs(batch.pairs)
        texels = None if batch.texels is None else torch.from_numpy(batch.texels).to(self.device)
        # the sub-texel term: one process computes it for the whole step (see _optimizer_step)
        between = self._between_texels(epoch, step) if self.subtexel and self.parallel.is_main else None
        return batch, (wv, wl, texels, taps, between)

    def _pair_inputs(self, pairs: np.ndarray):
        """``(w_view, w_light, taps)`` of (view, light) index pairs ``(P, 2)``: their directions ``(P, 3)`` and their
        rows of the angular taps (None without taps, or for no pairs)."""
        source, device = self.source, self.device
        wv = torch.as_tensor(source.views[pairs[:, 0]], dtype=torch.float32, device=device)
        wl = torch.as_tensor(source.lights[pairs[:, 1]], dtype=torch.float32, device=device)
        taps = None
        if self.angular_taps is not None and len(pairs):
            rows = torch.as_tensor(pairs[:, 0] * source.n_lights + pairs[:, 1], device=device)
            taps = tuple(t.index_select(0, rows) for t in self.angular_taps)
        return wv, wl, taps

    def _between_texels(self, epoch: int, step: int) -> dict[str, Any]:
        """The sub-texel term's data of step ``(epoch, step)`` (:func:`subtexel_weight`): random points between
        texel centres (:func:`~dynbtf.training.batches.between_texel_count` of them), each with its four
        surrounding texels (``neighbours``, int64 ``(4, n)``, flat, periodic) and their bilinear ``weights``
        (float32 ``(4, n)``; :func:`~dynbtf.training.batches.between_texel_points`), under the whole step's first
        ``B`` pairs (whatever this process's share of the step: ``w_view``, ``w_light``, ``angular_taps``), and the
        ``target``: the bilinear mix of those texels' measured values (float32 ``(B, n, 3)``). Seeded by the run's
        seed and the step."""
        device = self.device
        n = between_texel_count(self.sampler.texels_per_step)
        neighbours, weights, _ = between_texel_points(self.source.height, self.source.width, n,
                                                      np.random.default_rng([self.config.seed, 3, epoch, step]))
        pairs = self.sampler.pairs(epoch, step)[:self.sampler.b]
        texels = np.asarray(self.store.get(pairs, neighbours.reshape(-1)), dtype=np.float32).reshape(len(pairs), 4,
                                                                                                      n, 3)
        wv, wl, taps = self._pair_inputs(pairs)
        return {"neighbours": torch.from_numpy(neighbours).to(device), "weights": torch.from_numpy(weights).to(device),
                "w_view": wv, "w_light": wl, "angular_taps": taps,
                "target": torch.from_numpy(np.einsum("kn,bknc->bnc", weights, texels).astype(np.float32)).to(device)}

    def _optimizer_step(self, batch, inputs) -> float:
        """One step of the optimizer on ``batch`` (``inputs``: :meth:`_step_inputs`); returns the loss."""
        multiplier = self.schedule.lr_multiplier(self.epoch, self.done_steps, self.record)
        for g in self.optimizer.param_groups:
            g["lr"] = g["initial_lr"] * multiplier
        wv, wl, texels, taps, between = inputs
        self.optimizer.zero_grad(set_to_none=True)
        self.loss.begin_step()
        parallel = self.parallel
        loss = None
        if len(batch.pairs):  # (a data-parallel share of an epoch's short last step can be empty)
            loss = self.loss.batch(wv, wl, batch.target, texels, texel_groups=batch.groups, angular_taps=taps)
            if parallel.world > 1:  # weighted by the share: the mean over processes is the whole step's loss
                loss = loss * (batch.fraction * parallel.world)
        if between is not None:  # the whole step's sub-texel term, in one process: x world in the mean
            term = self.loss.between_texels(between["neighbours"], between["weights"], between["w_view"],
                                            between["w_light"], between["target"], between["angular_taps"])
            term = term * (self.subtexel * parallel.world)
            loss = term if loss is None else loss + term
        if loss is None:
            loss_value = 0.0
        else:
            loss.backward()
            loss_value = float(loss.detach())
        parallel.average_gradients(self.rep.parameters())
        loss_value = parallel.mean(loss_value)
        self._check_loss(loss_value)  # before the update: the model keeps its last good state
        self.optimizer.step()
        return loss_value

    def _check_held_out(self) -> None:
        """Score the held-out monitor now and add it to the record (in every process of a data-parallel fit: the
        schedule's decisions depend on it). Under a time budget, the check also re-plans the ceiling
        (:meth:`~dynbtf.training.schedule.Schedule.replan`): the steps :data:`BUDGET_PLAN_FRACTION` of the
        budget's rest affords at the rate since this run's previous check (wall time, this check included; the
        run's first check only starts the clock, its interval holding the run's start-up)."""
        score = self.monitor.score(self.rep, predict_images)
        self.record.append({"step": self.done_steps, "held_out_psnr": score, "elapsed_seconds": self.elapsed,
                            "lr_multiplier": self.schedule.lr_multiplier(self.epoch, self.done_steps - 1,
                                                                         self.record)})
        clock = self.budget_clock
        if clock is not None:
            now = time.perf_counter()
            steps, seconds = self.done_steps - clock["step"], now - clock.get("time", now)
            if steps > 0 and seconds > 0:  # the same plan in every process of a data-parallel fit
                affordable = self.parallel.mean(BUDGET_PLAN_FRACTION * (clock["end"] - now) * steps / seconds)
                ceiling = self.schedule.replan(self.done_steps, affordable, self.record)
                if ceiling is not None:
                    self.record[-1]["ceiling"] = ceiling
            clock.update(time=now, step=self.done_steps)

    def _command_eta(self) -> str:
        """The whole command's time left, ``h:mm:ss``: this fit's steps up to its ceiling and the steps that follow it
        (:func:`steps_after_this_fit`, e.g. the other trial and the winner's fit of ``--repr auto``) at the recent
        step time; at most the time budget's rest."""
        after, stop_at = _STEPS_AFTER.get()
        end = self.schedule.ceiling(self.record) if stop_at is None else min(stop_at, self.schedule.ceiling(self.record))
        left = (max(end - self.done_steps, 0) + after) * self.step_seconds
        if self.budget_clock is not None:
            left = min(left, max(self.budget_clock["end"] - time.perf_counter(), 0.0))
        left = int(round(left))
        return f"{left // 3600}:{left // 60 % 60:02d}:{left % 60:02d}"

    def _schedule_ended(self) -> bool:
        """All epochs done, the monitor converged, or a time budget's lowered ceiling reached."""
        return (self.epoch >= self.config.epochs or self.schedule.converged(self.done_steps, self.record)
                or self.done_steps >= self.schedule.ceiling(self.record))

    def _check_targets(self, batch) -> None:
        """:class:`InputError` naming the BTF and the first image of ``batch`` beyond ``max_reflectance`` (a batch read
        straight from the BTF; the image cache's images were checked as they were decoded)."""
        if not self.check_batches:
            return
        problem = implausible_targets(batch, self.config.max_reflectance)
        if self.parallel.any(problem is not None):
            raise InputError(_garbage_message(self.source, problem, self.config.max_reflectance) if problem else
                             f"{_btf_label(self.source)}: another process of this data-parallel fit read "
                             "implausible values (its message names the image)")

    def _check_loss(self, loss: float) -> None:
        """:class:`TrainingDiverged` when ``loss`` is not finite or :data:`DIVERGENCE_FACTOR` x the run's first."""
        if self.first_loss is None and math.isfinite(loss):
            self.first_loss = loss
        if math.isfinite(loss) and loss <= DIVERGENCE_FACTOR * max(self.first_loss, 1e-12):
            return
        raise TrainingDiverged(
            f"{_btf_label(self.source)}: the fit diverged at epoch {self.epoch}, step {self.step}: loss {loss:.3g} "
            f"(this run started at {self.first_loss if self.first_loss is not None else float('nan'):.3g}); "
            f"nothing was written beyond the last checkpoint ({self.checkpointer.path}). Check the BTF's values "
            f"(dynbtf info), or lower --lr-scale and delete the checkpoint to start over")

    def _after_step(self, loss: float, samples: int, seconds: float, bar) -> bool:
        """The bookkeeping after a step: time, progress, held-out check, epoch history, convergence, checkpoint.
        Returns whether the held-out monitor was checked."""
        self.elapsed += seconds
        self.done_steps += 1
        bar.update(1)
        checked = self.schedule.monitor_due(self.done_steps, self.step == 0)
        if checked:
            self._check_held_out()
        self.step_seconds = seconds if self.step_seconds is None else 0.95 * self.step_seconds + 0.05 * seconds
        bar.set_postfix(loss=f"{loss:.4f}", samples_s=f"{samples / seconds:.3g}",
                        **({"heldout_psnr": f"{self.record[-1]['held_out_psnr']:.2f}"} if self.record else {}),
                        command_eta=self._command_eta(), refresh=False)  # shown at the bar's own pace
        if self.step == 0:  # an epoch ended
            self.history.append({"epoch": self.epoch, "loss": loss, "held_out_psnr":
                                 self.record[-1]["held_out_psnr"] if self.record else float("nan"),
                                 "elapsed_seconds": self.elapsed})
        self.finished = self._schedule_ended()
        if self.finished and self.stop_reason() == "converged":
            bar.write(f"converged at step {self.done_steps}: the held-out monitor stopped improving (best "
                      f"{max(r['held_out_psnr'] for r in self.record):.2f} dB; {self.schedule.rule.describe()})")
        elif self.finished and self.epoch < self.config.epochs:
            best = max(r["held_out_psnr"] for r in self.record)
            bar.write(f"reached step {self.done_steps}, the ceiling the time budget left room for (the rate decayed "
                      f"to at most x{ANNEAL_FLOOR:g} by then; best held-out {best:.2f} dB)")
        if self.step == 0 or self.finished or \
                self.done_steps - self.last_checkpoint_step >= self.config.checkpoint_every:
            self.checkpoint()
        return checked

    # ------------------------------------------------------------------ the loop
    def train_steps(self, bar, callback, deadline: float | None = None) -> None:
        """Train until the schedule ends, the time budget runs out (``deadline``, a ``time.perf_counter()`` time),
        the ``callback`` raises :class:`StopTraining`, or an interrupt (checkpointed either way).

        A background thread prepares the next step's batch while this one trains.
        """
        config, steps_per_epoch = self.config, self.sampler.steps_per_epoch
        self.budget_clock = None if deadline is None else {"end": deadline, "step": self.done_steps}
        consistent = True  # model/optimizer state matches (epoch, step)
        prefetch = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dynbtf-prefetch")
        # On the CPU the loop runs torch kernels on one intra-op thread and parallelizes the fused loss over
        # ``workers`` Python threads instead: OpenMP barriers stall badly on a shared, oversubscribed machine.
        try:
            with _InterruptFlag() as interrupt, single_intra_op_thread(self.device.type == "cpu"):
                pending = prefetch.submit(self._step_inputs, self.epoch, self.step) if not self.finished else None
                while not self.finished:
                    t0 = time.perf_counter()
                    batch, inputs = pending.result()
                    nxt = self._next_position()
                    pending = prefetch.submit(self._step_inputs, *nxt) if nxt[0] < config.epochs else None
                    self._check_targets(batch)
                    consistent = False
                    try:
                        loss = self._optimizer_step(batch, inputs)
                    except TrainingDiverged:
                        consistent = True  # raised before the update: the state is still that of (epoch, step)
                        raise
                    self.epoch, self.step = nxt
                    consistent = True
                    dt = time.perf_counter() - t0
                    checked = self._after_step(loss, batch.samples, dt, bar)
                    if callback is not None:
                        try:
                            callback({"epoch": self.epoch if self.step else self.epoch - 1,
                                      "step": self.step or steps_per_epoch, "global_step": self.done_steps,
                                      "loss": loss, "step_seconds": dt, "samples": batch.samples,
                                      **({"held_out_psnr": self.record[-1]["held_out_psnr"]} if checked else {})})
                        except StopTraining as stop:
                            if not self.finished:
                                bar.write(f"stopped at step {self.done_steps}: {stop}")
                            break
                    over_budget = deadline is not None and time.perf_counter() >= deadline
                    if self.parallel.world > 1:  # every process stops at the same step
                        stop = self.parallel.any(interrupt.raised or over_budget)
                        interrupted, over_budget = stop and interrupt.raised, stop and not interrupt.raised
                    else:
                        interrupted = interrupt.raised
                    if interrupted:
                        raise KeyboardInterrupt
                    if over_budget and not self.finished:
                        bar.write(f"time budget of {config.max_minutes:.3g} min reached at step {self.done_steps} "
                                  f"(epoch {self.epoch}, step {self.step}): the model so far is written; run again "
                                  "to continue")
                        break
        except BaseException:
            if consistent and self.done_steps > self.last_checkpoint_step:
                self.checkpoint()
            raise
        finally:
            prefetch.shutdown(wait=True, cancel_futures=True)
        if self.done_steps > self.last_checkpoint_step:
            self.checkpoint()

    def stop_reason(self) -> str:
        """Why training ended: ``"converged"``, ``"ceiling"`` (all its epochs, or the ceiling a time budget
        lowered it to) or ``"unfinished"`` (time budget, interrupt)."""
        if not self.finished:
            return "unfinished"
        return "ceiling" if self.done_steps >= self.schedule.ceiling(self.record) else "converged"

    def write_model(self, extra_provenance: dict[str, Any] | None) -> float:
        """Write the model file with its provenance (process 0); returns the epochs completed."""
        config, rep = self.config, self.rep
        rep.eval()
        completed_epochs = self.epoch + self.step / self.sampler.steps_per_epoch
        if not self.parallel.is_main:
            self.parallel.barrier()  # until process 0 has written it
            return completed_epochs
        provenance = training_provenance(
            self.source, self.held_out, seed=config.seed,
            training=dataclasses.asdict(config) | {"workers": self.workers, "precision_used": self.precision},
            epochs_completed=completed_epochs, finished=self.finished, training_seconds=self.elapsed,
            history=self.history, samples_per_epoch=self.sampler.samples_per_epoch, size=self.size_info,
            run=_jsonable(_fingerprint(rep, self.source, config) | {"epochs": config.epochs}),
            schedule={"rule": self.schedule.describe(), "steps": self.done_steps,
                      "stopped": self.stop_reason(), "monitor": self.record},
            **(extra_provenance or {}))
        if self.record:
            provenance["held_out_psnr_monitor"] = self.record[-1]["held_out_psnr"]
            provenance["held_out_psnr_monitor_metric"] = "per-image peak"
        if self.parallel.world > 1:
            provenance["data_parallel_processes"] = self.parallel.world
        save_model(self.output, rep, provenance)
        self.parallel.barrier()
        return completed_epochs


def fit(representation: Representation, source: BTFSource, config: TrainConfig | None = None,
        output=None, *, progress: bool = True, callback: Callable[[dict[str, Any]], None] | None = None,
        extra_provenance: dict[str, Any] | None = None) -> FitResult:
    """Train ``representation`` on ``source``; write the model file ``output`` (and its checkpoint).

    The loop composes a :class:`~dynbtf.training.batches.BatchSampler` (which pairs and
    texels each step sees, prefetched on a background thread), a
    :class:`~dynbtf.training.checkpoint.Checkpointer` and a
    :class:`~dynbtf.training.monitor.HeldOutMonitor`.

    Parameters
    ----------
    representation : Representation
        A freshly constructed model of the BTF's size (its initial values are
        replaced by the checkpoint's when resuming).
    source : BTFSource
        The BTF. Cached in RAM as float16 when it fits ``memory_budget_mb``; otherwise every step's
        texels are read straight from the source (:meth:`~dynbtf.data.base.BTFSource.read_texels`).
    config : TrainConfig
        Options; see :class:`TrainConfig`.
    output : str or Path
        Model file to write (``.dbtfm``); the checkpoint is ``<output>.ckpt``.
        If that checkpoint exists, training continues from it.
    progress : bool
        Show a tqdm progress bar (loss, samples/s, held-out PSNR, ETA).
    callback : callable, optional
        Called after every optimizer step with a dict (epoch, step, global_step,
        loss, step_seconds, samples); :class:`StopTraining` from it ends training as a time budget does (model
        written, unfinished); another exception stops training after a checkpoint and propagates.
    extra_provenance : dict, optional
        Added to the model file's provenance.

    Returns
    -------
    FitResult
        ``finished`` is False when the time budget stopped training early.
    """
    from ..progress import progress_bar
    from ..representations.model_file import read_model_metadata

    started = time.perf_counter()  # a time budget counts from here: the image cache's decoding is part of it
    config = (config or TrainConfig()).validate()
    if output is None:
        raise InputError("output: a model file path is required")
    output = Path(output)
    if _already_fitted(output, representation, source, config) is not None:
        rep, meta = load_model(output, device=resolve_device(config.device))
        if progress:
            print(f"{output} is already a finished fit with these options: nothing to do (delete it to fit again)")
        provenance = meta["provenance"]
        return FitResult(output, rep, meta, list(provenance.get("history", [])), True)
    run = _TrainingRun(representation, source, config, output)
    sampler, store = run.sampler, run.store
    progress = progress and run.parallel.is_main  # one progress display for a data-parallel run
    bar = progress_bar(total=run.total_steps, initial=run.done_steps, unit="step", disable=not progress,
               desc=f"fit {run.rep.kind} on {source.name}")
    if progress:
        bar.write(f"{run.size_info['summary']}; {len(run.train_pairs)} training pairs, {len(run.held_out)} held out; "
                  f"{sampler.steps_per_epoch} steps/epoch x {config.epochs} epochs, {run.workers} worker thread(s), "
                  f"{run.precision} arithmetic" +
                  ("" if store.cached else "; texels read straight from the BTF (larger than the image cache)") +
                  (f" (resuming at epoch {run.epoch}, step {run.step})" if run.done_steps else ""))
    if not run.finished and store.cached:
        store.fill(np.concatenate([run.train_pairs, run.monitor.pairs]), progress=progress)
    deadline = None if config.max_minutes is None else started + config.max_minutes * 60.0 - WRITE_RESERVE_SECONDS
    try:
        run.train_steps(bar, callback, deadline)
    finally:
        bar.close()
    completed_epochs = run.write_model(extra_provenance)
    if run.finished and run.parallel.is_main:  # the model file has everything; a rerun returns at once
        run.checkpointer.remove()
    if progress:
        record = run.record
        print(f"wrote {output} ({run.size_info['summary']}; {completed_epochs:.2f} epochs ({run.done_steps} steps) in "
              f"{run.elapsed / 60:.1f} min" + (f", held-out PSNR {record[-1]['held_out_psnr']:.2f} dB (per-image peak, "
                                                f"{len(run.monitor.pairs)} pairs)" if record else "") + ")")
    return FitResult(output, run.rep, read_model_metadata(output), run.history, run.finished)
