"""A training recipe chosen from the BTF's size (and a time budget): ``dynbtf fit`` with no options.

The paper trains 50 epochs of 16 whole images per step (2 hours on an RTX 4090 at
400 x 400 texels, 151 x 151 directions). dynbtf's *fast recipe* (64 texel groups,
6x the paper's learning rates; docs/triple_plane.md) converges on a 128 x 128 BTF of
the UBO2003 grid (6,233 training pairs) in 30 epochs: about 11,700 optimizer steps,
in each of which every texel is trained under 16 pairs. :func:`auto_recipe` keeps
that per-texel schedule for any BTF:

* **texel groups**: 64 (fewer when the BTF has too few pairs for 64 x 16 per step);
* **texel subsets**: none up to :data:`MAX_TEXELS_PER_STEP` texels per step; larger
  BTFs train on that many texels per step (so a step stays a fraction of a second and
  progress, checkpoints and interrupts stay fine-grained);
* **schedule**: until the held-out monitor stops improving (``schedule="converge"``,
  :mod:`dynbtf.training.schedule`: checked every :data:`MONITOR_EVERY` steps, the rate halved
  at every stall and, over the last third of the ceiling, decaying steadily to 1/32 at the
  ceiling, stopped at a stall once the rate is 1/16), at least :data:`MIN_STEPS` steps. The **ceiling** is the reference's step
  count, ``30 x 6,233 / 16 = 11,700`` steps, times the **step factor**: the reference's samples
  per step over this BTF's (at least 1, at most :data:`MAX_STEP_FACTOR`). A 64 x 64 BTF, whose
  steps hold a quarter of the samples, may train twice the steps, and its checks and minimum
  scale with them (every 780 steps, at least 5,844); a 128 x 128 or 400 x 400 one keeps the reference's
  (converted to whole epochs: a 151 x 151 grid has 3.5x more pairs per epoch, so 9). With an
  explicit ``epochs`` or ``lr_decay`` the schedule is the paper's kind instead
  (``schedule="epochs"``): that many epochs, the decay per epoch set so the whole run decays as
  the reference (``0.9 ** 30`` in all);
* **memory**: the float16 image cache when the BTF fits in 40 % of the machine's RAM
  (at most 8 GiB), else texels read straight from the source each step;
* **a time budget** (``minutes``): a few steps are timed on this machine (on random
  targets of the step's shape, plus one real read of a batch when the BTF is streamed),
  and the epochs (the ceiling) are reduced, with the decay steepened to match, when they
  would not fit in 90 % of the budget. Explicit options override any choice.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..data.base import BTFSource
from ..device import resolve_device, synchronize
from ..errors import InputError
from ..representations.base import Representation
from .batches import BatchSampler, between_texel_count, between_texel_points
from .fit import AUTO_SUBTEXEL, TrainConfig, subtexel_weight
from .step_loss import StepLoss, resolve_compile
from ..decoder.fused_mlp import resolve_precision, single_intra_op_thread
from .images import ImageStore, held_out_split

__all__ = ["Recipe", "auto_recipe", "choose_config", "RECIPES", "REFERENCE_STEPS", "MAX_TEXELS_PER_STEP"]

#: The recipes of ``dynbtf fit --recipe``.
RECIPES = ("auto", "paper")
#: Epochs of the paper's recipe (``--recipe paper``; its supplementary: 50 at 400^2 x 151^2).
PAPER_EPOCHS = 50

#: Optimizer steps of the reference schedule (30 epochs of 6,233 pairs in steps of 16 pairs per group).
REFERENCE_STEPS = 30 * 6233 / 16
#: Texels per step above which the recipe trains on random texel subsets.
MAX_TEXELS_PER_STEP = 1 << 18
#: Samples per optimizer step of the reference schedule (16 pairs x 128 x 128 texels).
REFERENCE_SAMPLES_PER_STEP = 16 * 128 * 128
#: Most reference step counts a BTF with small steps may train (the converge schedule's ceiling).
MAX_STEP_FACTOR = 2.0
#: Steps between held-out checks of the converge schedule (one reference epoch), for steps of the reference's
#: size; a BTF whose steps are smaller checks every ``MONITOR_EVERY x`` its step factor (the ceiling's), so that
#: a check always follows the same number of samples and the stall threshold means the same gain per sample.
MONITOR_EVERY = round(REFERENCE_STEPS / 30)
#: Fewest steps before the converge schedule may stop (a quarter of the reference; scaled as ``MONITOR_EVERY``).
MIN_STEPS = round(REFERENCE_STEPS / 4)
_REFERENCE_EPOCHS = 30
_LR_DECAY = 0.9


@dataclass
class Recipe:
    """What :func:`auto_recipe` chose: the options and one line saying why."""

    config: TrainConfig
    summary: str
    full_epochs: int
    step_seconds: float | None = None


def _memory_for_cache_mb() -> float:
    """40 % of physical RAM, at most 8 GiB (the float16 image cache's share)."""
    try:
        ram = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        ram = 8 << 30
    return min(0.4 * ram, 8 << 30) / 1024 ** 2


def auto_recipe(source: BTFSource, *, minutes: float | None = None, representation: Representation | None = None,
                seed: int = 0, device: str = "auto", **overrides) -> Recipe:
    """Choose training options for ``source`` (see the module docstring).

    Parameters
    ----------
    source : BTFSource
    minutes : float, optional
        Time budget of the whole fit; the schedule is shortened to fit it and
        ``max_minutes`` is set to it (the run stops, checkpointed, if it still overruns).
    representation : Representation, optional
        The model to time (default: a Triple Plane of the BTF's size); only used with ``minutes``.
    seed, device :
        As :class:`TrainConfig`.
    **overrides
        :class:`TrainConfig` fields given explicitly (they win over the recipe's choices).

    Returns
    -------
    Recipe
        ``recipe.config`` to pass to :func:`~dynbtf.training.fit.fit`; ``recipe.summary`` states the choice.
    """
    if minutes is not None and not (math.isfinite(minutes) and minutes > 0):
        raise InputError(f"--minutes: expected a positive time budget, got {minutes}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(TrainConfig)}
    if unknown:
        raise InputError(f"auto_recipe: unknown training options {sorted(unknown)}")
    base = TrainConfig(seed=seed, device=device, **overrides)
    train_pairs, _ = held_out_split(source.n_views, source.n_lights, base.held_out_fraction, seed)
    b = base.images_per_step
    groups = overrides.get("texel_groups", max(1, min(64, len(train_pairs) // b)))
    n_texels = source.height * source.width
    texels = overrides.get("texels_per_image", None if n_texels <= MAX_TEXELS_PER_STEP else MAX_TEXELS_PER_STEP)
    steps_per_epoch = math.ceil(len(train_pairs) / b)
    converge = overrides.get("schedule", "converge" if not {"epochs", "lr_decay"} & set(overrides) else "epochs") \
        == "converge" and base.held_out_fraction > 0 and base.monitor_pairs > 0
    step_factor = 1.0  # reference steps per step of this BTF (converge: the ceiling's and the checks' scale)
    if converge:
        samples_per_step = b * (n_texels if texels is None else texels)
        step_factor = min(MAX_STEP_FACTOR, max(1.0, REFERENCE_SAMPLES_PER_STEP / samples_per_step))
        full_epochs = max(1, math.ceil(REFERENCE_STEPS * step_factor / steps_per_epoch - 0.05))  # (5 %: no epoch)
    else:
        full_epochs = max(1, round(REFERENCE_STEPS / steps_per_epoch))
    memory_mb = overrides.get("memory_budget_mb", max(base.memory_budget_mb, _memory_for_cache_mb()))
    config = dataclasses.replace(base, texel_groups=groups, texels_per_image=texels, memory_budget_mb=memory_mb,
                                 lr_scale=overrides.get("lr_scale", 6.0), epochs=overrides.get("epochs", full_epochs),
                                 schedule="converge" if converge else "epochs",
                                 monitor_every=overrides.get("monitor_every",
                                                             round(MONITOR_EVERY * step_factor) if converge else 0),
                                 min_steps=overrides.get("min_steps", round(MIN_STEPS * step_factor) if converge else 0),
                                 subtexel=overrides.get("subtexel", None))  # None: the representation's own
    epochs = config.epochs
    step_seconds = None
    budget_note = ""
    if minutes is not None:
        config.max_minutes = overrides.get("max_minutes", float(minutes))
        step_seconds = measure_step_seconds(source, config, representation)
        affordable = int(0.9 * minutes * 60 / (step_seconds * steps_per_epoch))
        if "epochs" not in overrides and affordable < epochs:
            epochs = max(1, affordable)
        budget_note = (f"; {step_seconds * 1e3:.3g} ms/step measured, {epochs * steps_per_epoch * step_seconds / 60:.1f} "
                       f"of {minutes:g} min" + ("" if epochs >= full_epochs else
                                                f" (the budget allows {epochs} of {full_epochs} epochs)"))
    config.epochs = epochs
    if "lr_decay" not in overrides:
        config.lr_decay = _LR_DECAY ** (_REFERENCE_EPOCHS / epochs)  # the reference's total decay, 0.9 ** 30
    config.validate()
    cached = source.n_pairs * n_texels * 3 * 2 <= config.memory_budget_mb * 1024 ** 2
    schedule = (f"until the held-out monitor stops improving (checked every {config.monitor_every} steps, lr halved "
                f"at each stall), {config.min_steps}-{config.epochs * steps_per_epoch} steps ({config.epochs} epochs "
                f"x {steps_per_epoch} at most)" if converge else
                f"{config.epochs} epochs x {steps_per_epoch} steps, lr decaying x{config.lr_decay:.3f} per epoch")
    summary = (f"recipe for {source.height} x {source.width} texels, {source.n_views} x {source.n_lights} "
               f"directions: {schedule}, {config.texel_groups} texel groups, "
               + ("all texels" if config.texels_per_image is None else f"{config.texels_per_image} texels")
               + f" per step, lr x{config.lr_scale:g}, "
               + (f"sub-texel term x{AUTO_SUBTEXEL:g} with the Triple Plane, " if config.subtexel is None else
                  f"sub-texel term x{config.subtexel:g}, " if config.subtexel else "")
               + ("images cached in RAM" if cached else "texels read from the BTF each step") + budget_note)
    return Recipe(config, summary, full_epochs, step_seconds)


def choose_config(source: BTFSource, output, *, recipe: str = "auto", minutes: float | None = None,
                  **options) -> tuple[TrainConfig, str]:
    """The training options ``dynbtf fit`` uses for ``source`` written to ``output``, and a line saying why.

    ``recipe="auto"``: :func:`auto_recipe` (with the time budget ``minutes``), unless ``output`` has
    an unfinished checkpoint, whose options are continued; ``"paper"``: :class:`TrainConfig`'s
    defaults (the paper's batches and learning rates), ``minutes`` as ``max_minutes``. ``options``
    are :class:`TrainConfig` fields given explicitly; they win over either recipe.
    """
    from .checkpoint import Checkpointer, checkpoint_path

    if recipe not in RECIPES:
        raise InputError(f"--recipe {recipe!r}: expected one of {list(RECIPES)}")
    unknown = set(options) - {f.name for f in dataclasses.fields(TrainConfig)}
    if unknown:
        raise InputError(f"unknown training options {sorted(unknown)}; expected TrainConfig fields")
    if recipe == "paper":
        options = {"epochs": PAPER_EPOCHS, **options}
        if minutes is not None and "max_minutes" not in options:
            options["max_minutes"] = minutes
        config = TrainConfig(**options).validate()
        return config, (f"the paper's recipe: {config.epochs} epochs, {config.images_per_step} whole images per "
                        f"step, lr x{config.lr_decay:g} per epoch")
    resumed = Checkpointer.saved_config(checkpoint_path(output))
    if resumed is not None:  # continue with the options the run started with
        config = TrainConfig(**{**resumed, **options}).validate()
        return config, f"continuing {checkpoint_path(output)} with its recipe ({config.epochs} epochs)"
    finished = _finished_run_options(output)
    if finished is not None:  # the same run again: its recorded options (a re-timed budget may differ)
        config = TrainConfig(**{**finished, **options}).validate()
        return config, f"{output} is a finished fit ({config.epochs} epochs); its options are kept"
    chosen = auto_recipe(source, minutes=minutes, **options)
    return chosen.config, chosen.summary


def _finished_run_options(output) -> dict | None:
    """The training options recorded in ``output`` when it is a finished fit's model file, else None."""
    from pathlib import Path

    from ..errors import DynBTFError
    from ..representations.model_file import read_model_metadata

    if not Path(output).is_file():
        return None
    try:
        provenance = read_model_metadata(output).get("provenance") or {}
    except DynBTFError:
        return None
    training = provenance.get("training")
    if not provenance.get("finished") or not isinstance(training, dict) or "run" not in provenance:
        return None
    fields = {f.name for f in dataclasses.fields(TrainConfig)} - {"device", "workers", "max_minutes"}
    return {k: v for k, v in training.items() if k in fields}


#: Seconds of warm-up steps before :func:`measure_step_seconds` times any (at least two steps).
WARM_UP_SECONDS = 0.25
#: Seconds of steps :func:`measure_step_seconds` times (at least its ``steps``), and the most steps of either phase.
TIMED_SECONDS = 0.5
MAX_TIMED_STEPS = 40


def measure_step_seconds(source: BTFSource, config: TrainConfig, representation: Representation | None = None,
                         steps: int = 5) -> float:
    """Seconds per optimizer step of ``config`` on this machine (kernel on random targets + a real batch read).

    The kernel is timed on a copy of ``representation`` (default: a Triple Plane): warm-up steps (at least two, and
    :data:`WARM_UP_SECONDS`: a process's first steps after loading a kernel run slower), then the median of at least
    ``steps`` steps and :data:`TIMED_SECONDS` (at most :data:`MAX_TIMED_STEPS`); when the BTF is too large for the
    image cache one real batch is read too and its time added (the prefetch thread shares the cores).
    """
    from ..representations.triple_plane import TriplePlane

    device = resolve_device(config.device)
    rep = copy.deepcopy(representation) if representation is not None else \
        TriplePlane(source.height, source.width, seed=config.seed)
    rep = rep.to(device).train()
    train_pairs, _ = held_out_split(source.n_views, source.n_lights, config.held_out_fraction, config.seed)
    store = ImageStore(source, int(config.memory_budget_mb * 1024 ** 2))
    sampler = BatchSampler(store, train_pairs, images_per_step=config.images_per_step,
                           texel_groups=config.texel_groups, texels_per_image=config.texels_per_image,
                           seed=config.seed, device=device)
    pairs = sampler.pairs(0, 0)
    texels, _ = sampler.texels(0, 0)
    n = sampler.texels_per_step if texels is not None or sampler.n_groups > 1 else sampler.n_texels
    texel_t = None if texels is None else torch.from_numpy(texels).to(device)
    target = torch.rand((config.images_per_step, n, 3), generator=torch.Generator().manual_seed(0)).to(device)
    wv = torch.as_tensor(source.views[pairs[:, 0]], dtype=torch.float32, device=device)
    wl = torch.as_tensor(source.lights[pairs[:, 1]], dtype=torch.float32, device=device)
    workers = int(config.workers or torch.get_num_threads()) if device.type == "cpu" else 1
    precision = resolve_precision(config.precision, device)
    chunk = config.chunk_texels if device.type == "cpu" else n
    with torch.no_grad():
        taps = rep.direction_taps(wv, wl)  # as the fit reads them (once per pair, before training)
    between = None
    if subtexel_weight(rep, config):  # the sub-texel term's points and random targets, as the fit reads them
        neighbours, weights, _ = between_texel_points(source.height, source.width, between_texel_count(n),
                                                      np.random.default_rng(0))
        b = config.images_per_step
        between = (torch.from_numpy(neighbours).to(device), torch.from_numpy(weights).to(device),
                   torch.rand((b, neighbours.shape[1], 3), generator=torch.Generator().manual_seed(1)).to(device))

    step_loss = StepLoss(rep, compile=resolve_compile(config.compile, device, rep), chunk_texels=chunk,
                         workers=workers, precision=precision)

    def step() -> float:
        t0 = time.perf_counter()
        rep.zero_grad(set_to_none=True)  # as the fit does (a CUDA graph's gradient outputs are not accumulated into)
        step_loss.begin_step()
        loss = step_loss.batch(wv, wl, target, texel_t, texel_groups=sampler.n_groups, angular_taps=taps)
        if between is not None:
            b = len(between[2])
            loss = loss + step_loss.between_texels(*between[:2], wv[:b], wl[:b], between[2],
                                                   tuple(t[:b] for t in taps))
        loss.backward()
        synchronize(device)  # a GPU runs the step after the launches return
        return time.perf_counter() - t0

    with single_intra_op_thread(device.type == "cpu"):
        warm = [step(), step()]
        while sum(warm) < WARM_UP_SECONDS and len(warm) < MAX_TIMED_STEPS:
            warm.append(step())
        times = [step() for _ in range(steps)]
        while sum(times) < TIMED_SECONDS and len(times) < MAX_TIMED_STEPS:
            times.append(step())
    seconds = float(np.median(times))
    if not store.cached:  # a step's read: the second one (the first also builds the source's factor cache)
        sampler.batch(0, 0)
        t0 = time.perf_counter()
        sampler.batch(0, min(1, sampler.steps_per_epoch - 1))
        synchronize(device)
        seconds += time.perf_counter() - t0
    return seconds * 1.05  # optimizer update and the per-epoch monitor
