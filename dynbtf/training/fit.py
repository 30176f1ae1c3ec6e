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
per step (measured: held-out PSNR equal to 0.01 dB over 800 steps) but cost
~20 ms per step of random memory reads at 128 x 128. The angular planes and the
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
from .batches import BatchSampler
from .checkpoint import Checkpointer, checkpoint_path
from .distributed import from_environment
from .images import ImageStore, held_out_split
from .monitor import HeldOutMonitor

__all__ = ["TrainConfig", "FitResult", "fit", "checkpoint_path", "texel_image_loss", "predict_images",
           "training_provenance"]

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
        run; run again to continue.
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
        (default: ``"bf16"`` where available, else ``"fp32"``; see
        :func:`dynbtf.decoder.fused_mlp.resolve_precision`). The precision used is recorded in
        the model file.
    """

    epochs: int = 12
    images_per_step: int = 16
    lr_decay: float = 0.9
    lr_scale: float = 1.0
    held_out_fraction: float = 0.05
    seed: int = 0
    texels_per_image: int | None = None
    texel_groups: int = 1
    max_minutes: float | None = None
    checkpoint_every: int = 100
    memory_budget_mb: float = 2048.0
    workers: int | None = None
    chunk_texels: int = 256
    monitor_pairs: int = 16
    device: str = "auto"
    precision: str = "auto"

    def validate(self) -> "TrainConfig":
        """Check every option; :class:`InputError` names the option (and its command-line flag) and the
        valid range."""
        checks = [("epochs", self.epochs >= 1, "an integer >= 1"),
                  ("images_per_step", self.images_per_step >= 1, "an integer >= 1"),
                  ("lr_decay", 0 < self.lr_decay <= 1, "a factor in (0, 1]"),
                  ("lr_scale", self.lr_scale > 0, "a number > 0"),
                  ("held_out_fraction", 0 <= self.held_out_fraction < 1, "a fraction in [0, 1)"),
                  ("texels_per_image", self.texels_per_image is None or self.texels_per_image >= 1,
                   "an integer >= 1"),
                  ("texel_groups", self.texel_groups >= 1, "an integer >= 1"),
                  ("max_minutes", self.max_minutes is None or self.max_minutes > 0, "a number of minutes > 0"),
                  ("checkpoint_every", self.checkpoint_every >= 1, "an integer >= 1"),
                  ("chunk_texels", self.chunk_texels >= 1, "an integer >= 1"),
                  ("workers", self.workers is None or self.workers >= 1, "an integer >= 1"),
                  ("monitor_pairs", self.monitor_pairs >= 0, "an integer >= 0"),
                  ("memory_budget_mb", self.memory_budget_mb > 0, "a number of MB > 0"),
                  ("precision", self.precision in ("auto", "fp32", "bf16"), "'auto', 'fp32' or 'bf16'")]
        for name, ok, valid in checks:
            if not ok:
                flag = "--" + name.replace("_", "-").replace("memory-budget-mb", "memory-mb")
                raise InputError(f"{flag} (TrainConfig.{name}): expected {valid}, got {getattr(self, name)!r}")
        return self

    # options that change the result: a checkpoint must agree on them to be resumed
    RESULT_FIELDS = ("images_per_step", "lr_decay", "lr_scale", "held_out_fraction", "seed", "texels_per_image",
                     "texel_groups", "chunk_texels", "precision")


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
                     workers: int = 1, texel_groups: int = 1, precision: str = "fp32") -> torch.Tensor:
    """Mean L1 loss of a whole-image batch:
    :meth:`Representation.texel_image_l1_loss <dynbtf.representations.base.Representation.texel_image_l1_loss>`
    (fused for the Triple Plane and NeuMIP; shapes and ``texel_groups`` there)."""
    return rep.texel_image_l1_loss(w_view, w_light, target, texels, chunk_texels=chunk_texels, workers=workers,
                                   texel_groups=texel_groups, precision=precision)


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
    (:func:`dynbtf.provenance.check_model_source`).
    """
    from ..provenance import source_fingerprint

    return {
        "source": {"name": source.name, "height": source.height, "width": source.width,
                   "n_views": source.n_views, "n_lights": source.n_lights,
                   "views": np.asarray(source.views).tolist(), "lights": np.asarray(source.lights).tolist(),
                   "raw_float32_bytes": source.nbytes_float32, "fingerprint": source_fingerprint(source)},
        "held_out_pairs": np.asarray(held_out, dtype=np.int64).tolist(),
        **extra,
    }


def _fingerprint(rep: Representation, source: BTFSource, config: TrainConfig) -> dict[str, Any]:
    return {"kind": rep.kind, "config": rep.config(), "source": [source.name, *source.shape],
            **{name: getattr(config, name) for name in TrainConfig.RESULT_FIELDS}}


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
        differ = [k for k in current if recorded.get(k) != current[k]]
        raise InputError(f"{output}: holds a fit of a different training run (differs in {differ}); delete it or "
                         "choose another output to start over")
    return meta if provenance.get("finished") else None


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
    return {k: v for k, v in dataclasses.asdict(config).items() if k not in ("device", "workers", "max_minutes")}


def _check_memory(config: TrainConfig, sampler: BatchSampler, store: ImageStore) -> None:
    """A streamed BTF needs two steps' targets (the one trained on and the one prefetched) in the budget."""
    if store.cached:
        return
    step_bytes = 2 * sampler.b * sampler.texels_per_step * 3 * 4
    if step_bytes > config.memory_budget_mb * 1024 ** 2:
        raise InputError(f"--memory-mb {config.memory_budget_mb:g} is too small for one training step of this BTF: "
                         f"{sampler.b} images x {sampler.texels_per_step} texels need at least "
                         f"{math.ceil(step_bytes / 1024 ** 2)} MB (or use --texels-per-image)")


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
        self.source, self.config, self.output = source, config, output
        self.parallel, device = from_environment(resolve_device(config.device))
        self.device = device
        self.rep = rep = representation.to(device)
        rep.train()
        # CPU: cache-sized chunks over worker threads; GPU: one chunk, one launch sequence
        self.workers = int(config.workers or torch.get_num_threads()) if device.type == "cpu" else 1
        self.train_pairs, self.held_out = held_out_split(source.n_views, source.n_lights, config.held_out_fraction,
                                                         config.seed)
        self.store = ImageStore(source, int(config.memory_budget_mb * 1024 ** 2))
        self.sampler = BatchSampler(self.store, self.train_pairs, images_per_step=config.images_per_step,
                                    texel_groups=config.texel_groups, texels_per_image=config.texels_per_image,
                                    seed=config.seed, view_coherent=rep.view_coherent_batches, device=device,
                                    part=(self.parallel.rank, self.parallel.world))
        _check_memory(config, self.sampler, self.store)
        self.chunk_texels = config.chunk_texels if device.type == "cpu" else self.sampler.texels_per_image
        self.precision = resolve_precision(
            config.precision if rep.has_fused_loss or config.precision == "bf16" else "fp32", device)
        # fused: one kernel per step for all parameters (same update; ~0.2 ms less per step on the CPU)
        self.optimizer = torch.optim.AdamW(_param_groups(rep, config.lr_scale), fused=True)
        self.monitor = HeldOutMonitor(self.store, self.held_out, config.monitor_pairs, config.seed, device)
        self.checkpointer = Checkpointer(checkpoint_path(output), _fingerprint(rep, source, config))
        self.epoch, self.step, self.elapsed, self.history = 0, 0, 0.0, []
        if self.checkpointer.exists():
            state = self.checkpointer.load()
            rep.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.epoch, self.step = int(state["epoch"]), int(state["step"])
            self.elapsed, self.history = float(state["elapsed_seconds"]), list(state["history"])
        self.total_steps = config.epochs * self.sampler.steps_per_epoch
        self.done_steps = min(self.epoch * self.sampler.steps_per_epoch + self.step, self.total_steps)
        self.last_checkpoint_step = self.done_steps
        self.finished = self.epoch >= config.epochs
        self.size_info = model_size_report(rep, source.nbytes_float32)

    # ------------------------------------------------------------------ parts of a step
    def checkpoint(self) -> None:
        if not self.parallel.is_main:  # one writer; every process has the same state
            self.last_checkpoint_step = self.done_steps
            return
        self.checkpointer.save({"config": _saved_options(self.config), "model": self.rep.state_dict(),
                                "optimizer": self.optimizer.state_dict(), "epoch": self.epoch, "step": self.step,
                                "elapsed_seconds": self.elapsed, "history": self.history,
                                "held_out_pairs": torch.from_numpy(self.held_out)})
        self.last_checkpoint_step = self.done_steps

    def _next_position(self) -> tuple[int, int]:
        return (self.epoch, self.step + 1) if self.step + 1 < self.sampler.steps_per_epoch else (self.epoch + 1, 0)

    def _optimizer_step(self, batch) -> float:
        """One step of the optimizer on ``batch``; returns the loss."""
        for g in self.optimizer.param_groups:
            g["lr"] = g["initial_lr"] * self.config.lr_decay ** self.epoch
        source, device = self.source, self.device
        wv = torch.as_tensor(source.views[batch.pairs[:, 0]], dtype=torch.float32, device=device)
        wl = torch.as_tensor(source.lights[batch.pairs[:, 1]], dtype=torch.float32, device=device)
        texels = None if batch.texels is None else torch.from_numpy(batch.texels).to(device)
        self.optimizer.zero_grad(set_to_none=True)
        parallel = self.parallel
        if len(batch.pairs) == 0:  # a data-parallel share of an epoch's short last step can be empty
            loss_value = 0.0
        else:
            loss = texel_image_loss(self.rep, wv, wl, batch.target, (source.height, source.width), texels,
                                    chunk_texels=self.chunk_texels, workers=self.workers,
                                    texel_groups=batch.groups, precision=self.precision)
            if parallel.world > 1:  # weighted by the share: the mean over processes is the whole step's loss
                loss = loss * (batch.fraction * parallel.world)
            loss.backward()
            loss_value = float(loss.detach())
        parallel.average_gradients(self.rep.parameters())
        self.optimizer.step()
        return parallel.mean(loss_value)

    # ------------------------------------------------------------------ the loop
    def train_steps(self, bar, callback) -> None:
        """Train until the schedule ends, the time budget runs out, or an interrupt (checkpointed either way).

        A background thread prepares the next step's batch while this one trains.
        """
        config, steps_per_epoch = self.config, self.sampler.steps_per_epoch
        run_start = time.perf_counter()
        budget = None if config.max_minutes is None else config.max_minutes * 60.0
        consistent = True  # model/optimizer state matches (epoch, step)
        prefetch = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dynbtf-prefetch")
        # On the CPU the loop runs torch kernels on one intra-op thread and parallelizes the fused loss over
        # ``workers`` Python threads instead: OpenMP barriers stall badly on a shared, oversubscribed machine.
        try:
            with _InterruptFlag() as interrupt, single_intra_op_thread(self.device.type == "cpu"):
                pending = prefetch.submit(self.sampler.batch, self.epoch, self.step) if not self.finished else None
                while not self.finished:
                    t0 = time.perf_counter()
                    batch = pending.result()
                    nxt = self._next_position()
                    pending = prefetch.submit(self.sampler.batch, *nxt) if nxt[0] < config.epochs else None
                    consistent = False
                    loss = self._optimizer_step(batch)
                    self.epoch, self.step = nxt
                    consistent = True
                    dt = time.perf_counter() - t0
                    self.elapsed += dt
                    self.done_steps += 1
                    bar.update(1)
                    bar.set_postfix(loss=f"{loss:.4f}", samples_s=f"{batch.samples / dt:.3g}",
                                    **({"heldout_psnr": f"{self.history[-1]['held_out_psnr']:.2f}"}
                                       if self.history else {}), refresh=False)  # shown at the bar's own pace
                    if self.step == 0:  # an epoch ended
                        score = self.monitor.score(self.rep, predict_images) if self.parallel.is_main else \
                            float("nan")
                        self.history.append({"epoch": self.epoch, "loss": loss, "held_out_psnr": score,
                                             "elapsed_seconds": self.elapsed})
                        self.finished = self.epoch >= config.epochs
                    if self.step == 0 or self.done_steps - self.last_checkpoint_step >= config.checkpoint_every:
                        self.checkpoint()
                    if callback is not None:
                        callback({"epoch": self.epoch if self.step else self.epoch - 1,
                                  "step": self.step or steps_per_epoch, "global_step": self.done_steps,
                                  "loss": loss, "step_seconds": dt, "samples": batch.samples})
                    over_budget = budget is not None and time.perf_counter() - run_start >= budget
                    if self.parallel.world > 1:  # every process stops at the same step
                        stop = self.parallel.any(interrupt.raised or over_budget)
                        interrupted, over_budget = stop and interrupt.raised, stop and not interrupt.raised
                    else:
                        interrupted = interrupt.raised
                    if interrupted:
                        raise KeyboardInterrupt
                    if over_budget and not self.finished:
                        bar.write(f"time budget of {config.max_minutes} min reached at epoch {self.epoch}, "
                                  f"step {self.step}; run again to continue")
                        break
        except BaseException:
            if consistent and self.done_steps > self.last_checkpoint_step:
                self.checkpoint()
            raise
        finally:
            prefetch.shutdown(wait=True, cancel_futures=True)
        if self.done_steps > self.last_checkpoint_step:
            self.checkpoint()

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
            **(extra_provenance or {}))
        if self.history:
            provenance["held_out_psnr_monitor"] = self.history[-1]["held_out_psnr"]
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
        loss, step_seconds, samples); an exception it raises stops training after a checkpoint.
    extra_provenance : dict, optional
        Added to the model file's provenance.

    Returns
    -------
    FitResult
        ``finished`` is False when the time budget stopped training early.
    """
    from ..progress import progress_bar
    from ..representations.model_file import read_model_metadata

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
    try:
        run.train_steps(bar, callback)
    finally:
        bar.close()
    completed_epochs = run.write_model(extra_provenance)
    if run.finished and run.parallel.is_main:  # the model file has everything; a rerun returns at once
        run.checkpointer.remove()
    if progress:
        history = run.history
        print(f"wrote {output} ({run.size_info['summary']}; {completed_epochs:.2f} epochs in {run.elapsed / 60:.1f} "
              "min" + (f", held-out PSNR {history[-1]['held_out_psnr']:.2f} dB (per-image peak, "
                       f"{len(run.monitor.pairs)} pairs)" if history else "") + ")")
    return FitResult(output, run.rep, read_model_metadata(output), run.history, run.finished)
