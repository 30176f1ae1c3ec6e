"""Data-parallel training on several processes: ``torchrun --nproc-per-node N -m dynbtf fit ...``.

Every process builds the same model (same seed) and the same batches (counter-based seeds,
:mod:`dynbtf.training.batches`) and trains its share of each step: its texel groups, or its
range of the step's pairs. After the backward pass the gradients are averaged over the
processes (``all_reduce``), each weighted by its share of the step's samples, so every process
takes the same optimizer step as one process training the whole batch would (to float rounding:
the sums are split differently). Process 0 writes the checkpoints, the model file and the
progress; a rerun continues from the same checkpoint with any number of processes.

The process group comes from torchrun's environment (``WORLD_SIZE``, ``RANK``, ``MASTER_ADDR``,
...): gloo on CPUs, NCCL on GPUs (each process on ``cuda:LOCAL_RANK``). Without it (a plain
``dynbtf fit``) :func:`from_environment` returns the single-process :class:`DataParallel`, whose
operations do nothing.

When it pays: several GPUs, or several machines, each with its own cores and memory bandwidth.
On one 2-core machine it does not: the fused kernel already uses both cores, and two processes
only add the all-reduce and a second copy of the data path.
"""

from __future__ import annotations

import atexit
import os
from dataclasses import dataclass

import torch

__all__ = ["DataParallel", "from_environment"]


@dataclass(frozen=True)
class DataParallel:
    """This process's place in a data-parallel run (``world = 1``: not data-parallel)."""

    rank: int = 0
    world: int = 1

    @property
    def is_main(self) -> bool:
        """Process 0: the one that writes checkpoints, the model file and the progress."""
        return self.rank == 0

    def average_gradients(self, parameters) -> None:
        """Replace every gradient by its mean over the processes (a missing gradient counts as zero)."""
        if self.world == 1:
            return
        import torch.distributed as dist

        for p in parameters:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            dist.all_reduce(p.grad, op=dist.ReduceOp.SUM)
            p.grad /= self.world

    def mean(self, value: float) -> float:
        """``value`` averaged over the processes."""
        if self.world == 1:
            return value
        import torch.distributed as dist

        t = torch.tensor([value], dtype=torch.float64)
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
        return float(t) / self.world

    def any(self, flag: bool) -> bool:
        """True on every process when ``flag`` is true on any (e.g. stop: an interrupt or the time budget)."""
        if self.world == 1:
            return bool(flag)
        import torch.distributed as dist

        t = torch.tensor([1 if flag else 0], dtype=torch.int64)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return bool(t)

    def barrier(self) -> None:
        if self.world > 1:
            import torch.distributed as dist

            dist.barrier()


def _destroy_process_group() -> None:
    import torch.distributed as dist

    if dist.is_initialized():
        dist.destroy_process_group()


def from_environment(device: torch.device) -> tuple[DataParallel, torch.device]:
    """The data-parallel group torchrun set up (initialized here on first use) and this process's device."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DataParallel(), device
    import torch.distributed as dist

    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
        # torch asks for destroy_process_group() before exit: without it a gloo process was seen to abort at
        # exit now and then ("terminate called without an active exception") after a complete run
        atexit.register(_destroy_process_group)
    return DataParallel(dist.get_rank(), dist.get_world_size()), device
