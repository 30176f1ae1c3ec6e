"""Checkpoints of a training run: written atomically, read back safely, tied to the run's options.

A checkpoint (``<model file>.ckpt``, :func:`checkpoint_path`) is a ``torch.save`` dict
holding the model and optimizer states and the position (epoch, step), plus a
*fingerprint* of everything that changes the result (representation kind and
configuration, the BTF's name and shape, the result-changing training options).
Resuming refuses a checkpoint whose fingerprint differs, naming the fields, and one that does not
fit the run (:meth:`Checkpointer.restore`: tensors missing, of another shape or not finite, a position
outside the schedule, an optimizer state of other parameters) as damaged, naming its path and how to
start over. Nothing of such a checkpoint reaches the model.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from ..errors import FormatError, InputError
from ..io import atomic_path

__all__ = ["CHECKPOINT_VERSION", "Checkpointer", "checkpoint_path"]

CHECKPOINT_VERSION = 1


def checkpoint_path(model_path) -> Path:
    """The checkpoint written next to a model file: ``<model_path>.ckpt``."""
    model_path = Path(model_path)
    return model_path.with_name(model_path.name + ".ckpt")


class Checkpointer:
    """Saves and restores one run's state at ``path``.

    Parameters
    ----------
    path : Path
        The checkpoint file.
    fingerprint : dict
        JSON-like description of the run; :meth:`load` requires an equal one.
    """

    def __init__(self, path, fingerprint: dict[str, Any]) -> None:
        self.path, self.fingerprint = Path(path), fingerprint

    def exists(self) -> bool:
        return self.path.exists()

    def save(self, state: dict[str, Any]) -> None:
        """Write ``state`` (tensors, numbers, lists) atomically: a crash leaves the previous checkpoint."""
        with atomic_path(self.path) as tmp:
            torch.save({"format": "dynbtf-checkpoint", "version": CHECKPOINT_VERSION,
                        "fingerprint": self.fingerprint, **state}, tmp)

    def load(self) -> dict[str, Any]:
        """The saved state; :class:`FormatError` if damaged, :class:`InputError` if from another run."""
        try:
            state = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception as e:  # truncated zip, unpickling refused, ...
            raise FormatError(self.path, f"damaged checkpoint ({e}); delete it to start over") from None
        if not isinstance(state, dict) or state.get("format") != "dynbtf-checkpoint":
            raise FormatError(self.path, "not a dynbtf checkpoint; delete it to start over")
        if state.get("version", 0) > CHECKPOINT_VERSION:
            raise FormatError(self.path, f"checkpoint version {state.get('version')} is newer than this dynbtf "
                                         "supports")
        saved = state.get("fingerprint", {})
        if saved != self.fingerprint:
            diff = [k for k in {**saved, **self.fingerprint} if saved.get(k) != self.fingerprint.get(k)]
            raise InputError(f"{self.path}: checkpoint belongs to a different training run (differs in {diff}); "
                             "delete it or choose another output to start over")
        return state

    def damaged(self, problem: str) -> FormatError:
        """The error for a checkpoint that does not fit this run: names it and how to start over."""
        return FormatError(self.path, f"damaged checkpoint: {problem}; delete it to start over (rm '{self.path}'; "
                                      "the training it holds is lost)")

    def restore(self, model: torch.nn.Module, optimizer: torch.optim.Optimizer, *, epochs: int,
                steps_per_epoch: int) -> dict[str, Any]:
        """Load the checkpoint into ``model`` and ``optimizer`` once it is checked to fit this run.

        Checked before anything is copied: the model tensors (names, shapes, dtypes as ``model``'s, finite),
        the position (``0 <= epoch <= epochs``, ``0 <= step < steps_per_epoch``, one history entry per
        finished epoch), the elapsed time, and the optimizer state (its parameters' shapes, finite moments).
        Anything else is :meth:`damaged` (:class:`FormatError`, never another exception).

        Returns the state (``epoch``, ``step``, ``elapsed_seconds``, ``history``, ...), its numbers as Python
        ``int`` / ``float``.
        """
        state = self.load()
        saved = state.get("model")
        if not isinstance(saved, dict):
            raise self.damaged("it holds no model state")
        for name, want in model.state_dict().items():
            got = saved.get(name)
            if not isinstance(got, torch.Tensor):
                raise self.damaged(f"model tensor {name!r} is missing")
            if tuple(got.shape) != tuple(want.shape) or got.dtype != want.dtype:
                raise self.damaged(f"model tensor {name!r} is {got.dtype} {tuple(got.shape)}; the model needs "
                                   f"{want.dtype} {tuple(want.shape)}")
            if got.is_floating_point() and not bool(torch.isfinite(got).all()):
                raise self.damaged(f"model tensor {name!r} holds non-finite values (NaN or Inf)")
        extra = sorted(set(saved) - set(model.state_dict()))
        if extra:
            raise self.damaged(f"model tensor {extra[0]!r} is not part of this model")
        position = {}
        for name in ("epoch", "step"):
            value = state.get(name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise self.damaged(f"{name} is {value!r}, not an integer")
            position[name] = value
        epoch, step = position["epoch"], position["step"]
        if not 0 <= epoch <= epochs:
            raise self.damaged(f"it is at epoch {epoch}, outside this run's 0..{epochs} (to continue a run "
                               "beyond its epochs, rerun with more --epochs)" if epoch > epochs else
                               f"it is at epoch {epoch}, outside this run's 0..{epochs}")
        if not 0 <= step < steps_per_epoch or (epoch == epochs and step != 0):
            raise self.damaged(f"it is at step {step} of epoch {epoch}; an epoch of this run has "
                               f"{steps_per_epoch} steps (0..{steps_per_epoch - 1})")
        history = state.get("history")
        if not isinstance(history, list) or len(history) != epoch or not all(isinstance(h, dict) for h in history):
            raise self.damaged(f"its history lists {len(history) if isinstance(history, list) else history!r} "
                               f"epoch(s) but its position is epoch {epoch}")
        monitor = state.get("monitor", [])  # the held-out checks (older checkpoints: none recorded)
        if not isinstance(monitor, list) or not all(
                isinstance(r, dict) and isinstance(r.get("step"), int) and isinstance(r.get("held_out_psnr"), float)
                and (type(r.get("ceiling", 0)) is int and r.get("ceiling", 0) >= 0) for r in monitor):
            raise self.damaged("its monitor record is not a list of held-out checks {step, held_out_psnr[, ceiling: a "
                               "step count >= 0]}")
        elapsed = state.get("elapsed_seconds")
        if isinstance(elapsed, bool) or not isinstance(elapsed, (int, float)) or not math.isfinite(elapsed) \
                or elapsed < 0:
            raise self.damaged(f"elapsed_seconds is {elapsed!r}, not a finite number >= 0")
        previous = optimizer.state_dict()
        try:
            optimizer.load_state_dict(state.get("optimizer"))
            for parameter, moments in optimizer.state.items():
                for key, value in moments.items():
                    if not isinstance(value, torch.Tensor) or value.numel() <= 1:
                        continue  # the step count
                    if tuple(value.shape) != tuple(parameter.shape) or not bool(torch.isfinite(value).all()):
                        raise ValueError(f"its {key!r} is {tuple(value.shape)} or not finite, for a parameter of "
                                         f"shape {tuple(parameter.shape)}")
        except Exception as e:  # ValueError, KeyError, TypeError from torch's own checks, or ours
            optimizer.load_state_dict(previous)
            raise self.damaged(f"its optimizer state does not fit this model ({e})") from None
        model.load_state_dict(saved, strict=True)
        return {**state, "epoch": epoch, "step": step, "elapsed_seconds": float(elapsed), "history": list(history),
                "monitor": list(monitor)}

    @staticmethod
    def saved_config(path) -> dict[str, Any] | None:
        """The training options a checkpoint was started with (``None``: no checkpoint, or one without them)."""
        path = Path(path)
        if not path.exists():
            return None
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:
            raise FormatError(path, f"damaged checkpoint ({e}); delete it to start over") from None
        config = state.get("config") if isinstance(state, dict) else None
        if not isinstance(config, dict):
            return None
        from .fit import check_options  # the options' rules live with TrainConfig

        try:
            check_options(**{str(k): v for k, v in config.items()})
        except InputError as e:
            raise Checkpointer(path, {}).damaged(f"its training options are not valid ({e})") from None
        return dict(config)

    def remove(self) -> None:
        """Delete the checkpoint (after a finished run wrote its model file)."""
        self.path.unlink(missing_ok=True)
