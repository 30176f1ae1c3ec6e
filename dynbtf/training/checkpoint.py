"""Checkpoints of a training run: written atomically, read back safely, tied to the run's options.

A checkpoint (``<model file>.ckpt``, :func:`checkpoint_path`) is a ``torch.save`` dict
holding the model and optimizer states and the position (epoch, step), plus a
*fingerprint* of everything that changes the result (representation kind and
configuration, the BTF's name and shape, the result-changing training options).
Resuming refuses a checkpoint whose fingerprint differs, naming the fields.
"""

from __future__ import annotations

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
            diff = [k for k in self.fingerprint if saved.get(k) != self.fingerprint[k]]
            raise InputError(f"{self.path}: checkpoint belongs to a different training run (differs in {diff}); "
                             "delete it or choose another output to start over")
        return state

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
        return dict(config) if isinstance(config, dict) else None

    def remove(self) -> None:
        """Delete the checkpoint (after a finished run wrote its model file)."""
        self.path.unlink(missing_ok=True)
