"""Run-time device choice: CUDA when present, else the CPU; waiting for a device; values brought back to the host."""

from __future__ import annotations

import torch

__all__ = ["resolve_device", "synchronize", "to_host"]


def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """Return ``device`` as a ``torch.device``; ``None`` or ``"auto"`` picks CUDA if available.

    >>> resolve_device("cpu")
    device(type='cpu')
    """
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    from .errors import InputError

    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise InputError(f"device: {device!r} is not a valid torch device ({e})") from None
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device: {device!r} requested but CUDA is not available here; use 'cpu' or 'auto'")
    return resolved


def synchronize(device: str | torch.device) -> None:
    """Wait until ``device`` has run everything launched on it (a GPU runs its work after the launches return, so a
    clock read without this measures the launches); nothing to wait for on the CPU.

    >>> synchronize("cpu")
    """
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def to_host(x):
    """A tensor on any device as a NumPy array (detached, on the CPU); any other value as it is.

    >>> to_host(torch.ones(2)), to_host(1.5)
    (array([1., 1.], dtype=float32), 1.5)
    """
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x
