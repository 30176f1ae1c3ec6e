"""The loss of one optimizer step, run eagerly or compiled by ``torch.compile``.

A step's loss is the batch's L1 loss (:meth:`Representation.texel_image_l1_loss
<dynbtf.representations.base.Representation.texel_image_l1_loss>`) plus, for the Triple Plane, the sub-texel term
(:meth:`~dynbtf.representations.triple_plane.TriplePlane.subtexel_l1_loss`). :class:`StepLoss` computes both for
:func:`dynbtf.training.fit` and for the budget planner (:func:`dynbtf.training.recipe.measure_step_seconds`), in one
of four modes (``TrainConfig.compile``, ``dynbtf fit --compile``):

* ``"off"``: eager PyTorch, the fused kernels (native on the CPU, one autograd node per loss elsewhere);
* ``"kernels"``: ``torch.compile`` of each loss: the decoder is written as ordinary ops
  (:func:`dynbtf.decoder.fused_mlp.decoder_l1_loss` under compilation) and Inductor generates fused kernels for its
  forward and backward pass (Triton on a GPU, C++ on the CPU);
* ``"graphs"``: the same, with the kernels of a step replayed as CUDA graphs (``mode="reduce-overhead"``): one
  launch per graph instead of one per kernel, for GPUs whose steps are short enough to be launch-bound; CUDA only;
* ``"auto"``: :data:`AUTO_COMPILE` of the device type for representations whose ``compiled_on_gpu`` is set (the
  Triple Plane), ``"off"`` for the others and on a GPU without Triton.

Compiling happens at a run's first step (and once more for an epoch's shorter last step, if it has one); the
values are those of the eager loss to float32 rounding (not bit-identical: the generated kernels sum in their own
order).
"""

from __future__ import annotations

import warnings
from typing import Callable

import torch

from ..errors import InputError

__all__ = ["COMPILE_MODES", "AUTO_COMPILE", "resolve_compile", "StepLoss"]

#: The values of ``TrainConfig.compile``.
COMPILE_MODES = ("auto", "off", "kernels", "graphs")

#: What ``"auto"`` is on each device type (others: ``"off"``). On the CPU the native fused kernels beat Inductor's
#: generated ones (they keep the decoder's activations in cache); on a GPU the CUDA graphs are the fastest of the
#: three (``benchmarks/gpu_check.py``; docs/results.md, "On a GPU").
AUTO_COMPILE = {"cpu": "off", "cuda": "graphs"}


def resolve_compile(mode: str, device: torch.device | str, representation=None) -> str:
    """``mode`` (:data:`COMPILE_MODES`) on ``device`` for ``representation``: ``"off"``, ``"kernels"`` or ``"graphs"``.

    ``"auto"`` compiles on a GPU only a representation whose ``compiled_on_gpu`` says it pays (the Triple Plane; the
    parallax model's march takes longer to compile than a short fit lasts).

    :class:`InputError` for an unknown mode, ``"graphs"`` off CUDA, and a compiling mode where ``torch.compile`` has
    no back end (a GPU without Triton).

    >>> resolve_compile("auto", "cpu"), resolve_compile("kernels", "cpu")
    ('off', 'kernels')
    >>> resolve_compile("graphs", "cpu")
    Traceback (most recent call last):
    ...
    dynbtf.errors.InputError: --compile graphs: CUDA graphs need a CUDA device, got 'cpu'; use kernels or off
    """
    device = torch.device(device)
    if mode not in COMPILE_MODES:
        raise InputError(f"--compile (TrainConfig.compile): expected one of {', '.join(map(repr, COMPILE_MODES))}, "
                         f"got {mode!r}")
    if mode == "auto":
        chosen = AUTO_COMPILE.get(device.type, "off")
        if representation is not None and device.type != "cpu" and not representation.compiled_on_gpu:
            return "off"
        return chosen if chosen == "off" or device.type != "cuda" or _has_triton() else "off"
    if mode == "graphs" and device.type != "cuda":
        raise InputError(f"--compile graphs: CUDA graphs need a CUDA device, got {str(device)!r}; use kernels or off")
    if mode != "off" and device.type == "cuda" and not _has_triton():
        raise InputError(f"--compile {mode}: torch.compile needs Triton on a GPU (pip install triton); use off")
    return mode


def _has_triton() -> bool:
    """Whether ``torch.compile`` can generate GPU kernels here (Triton installed, with a GPU it supports)."""
    from torch.utils._triton import has_triton

    return bool(has_triton())


class StepLoss:
    """The two losses of a step for ``representation`` on its device, eager or compiled (module docstring).

    Parameters
    ----------
    representation : Representation
        The model being fitted (on its device).
    compile : str
        ``"off"``, ``"kernels"`` or ``"graphs"`` (:func:`resolve_compile` resolves ``"auto"``).
    chunk_texels, workers, precision
        The fused kernels' options (``TrainConfig``); a compiled loss computes in float32 and takes ``"fp32"`` only.

    Examples
    --------
    >>> import torch
    >>> from dynbtf.representations.triple_plane import TriplePlane
    >>> model = TriplePlane(4, 4)
    >>> w = torch.tensor([[0.0, 0.0, 1.0]] * 2)
    >>> loss = StepLoss(model).batch(w, w, torch.zeros(2, 16, 3))
    >>> loss.shape, bool(loss > 0)
    (torch.Size([]), True)
    """

    def __init__(self, representation, *, compile: str = "off", chunk_texels: int = 256, workers: int = 1,
                 precision: str = "fp32") -> None:
        if compile not in ("off", "kernels", "graphs"):
            raise InputError(f"StepLoss: compile must be resolved to 'off', 'kernels' or 'graphs' "
                             f"(resolve_compile), got {compile!r}")
        if compile != "off" and precision != "fp32":
            raise InputError(f"--compile {compile}: a compiled loss computes in float32; use --precision fp32 or "
                             f"--compile off (got precision {precision!r})")
        self.representation, self.compile = representation, compile
        self.options = {"chunk_texels": int(chunk_texels), "workers": int(workers), "precision": precision}
        self._batch = self._compiled(representation.texel_image_l1_loss)
        self._between = (self._compiled(representation.subtexel_l1_loss)
                         if getattr(representation, "has_subtexel_term", False) else None)

    def _compiled(self, function: Callable) -> Callable:
        if self.compile == "off":
            return function
        # dynamic=False: a step's shapes are fixed (an epoch's last step is the one other shape), so each shape gets
        # kernels specialised to it rather than one symbolic-shape graph
        with warnings.catch_warnings():  # torch's own: importing Inductor touches its deprecated torch.jit API
            warnings.filterwarnings("ignore", message=r"`torch\.jit\.script_method` is deprecated",
                                    category=DeprecationWarning)
            compiled = torch.compile(function, dynamic=False,
                                     mode="reduce-overhead" if self.compile == "graphs" else None)

        def call(*args, **kwargs):
            with warnings.catch_warnings():  # float32 products are asked for: Inductor's advice to use TF32 is not
                warnings.filterwarnings("ignore", message="TensorFloat32 tensor cores", category=UserWarning)
                return compiled(*args, **kwargs)

        return call

    def begin_step(self) -> None:
        """Mark a new step (CUDA graphs: the previous step's graph outputs may be overwritten from here on)."""
        if self.compile == "graphs":
            torch.compiler.cudagraph_mark_step_begin()

    def batch(self, w_view: torch.Tensor, w_light: torch.Tensor, target: torch.Tensor,
              texels: torch.Tensor | None = None, *, texel_groups: int = 1,
              angular_taps: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
        """The batch's mean L1 loss, a 0-d tensor: :meth:`Representation.texel_image_l1_loss
        <dynbtf.representations.base.Representation.texel_image_l1_loss>` (shapes there)."""
        kwargs = {} if angular_taps is None else {"angular_taps": angular_taps}
        return self._batch(w_view, w_light, target, texels, texel_groups=texel_groups, **self.options, **kwargs)

    def between_texels(self, neighbours: torch.Tensor, weights: torch.Tensor, w_view: torch.Tensor,
                       w_light: torch.Tensor, target: torch.Tensor,
                       angular_taps: tuple[torch.Tensor, ...] | None = None) -> torch.Tensor:
        """The sub-texel term's mean L1 loss, a 0-d tensor: :meth:`TriplePlane.subtexel_l1_loss
        <dynbtf.representations.triple_plane.TriplePlane.subtexel_l1_loss>` (shapes there)."""
        if self._between is None:
            raise InputError(f"subtexel: the {self.representation.kind!r} representation has no sub-texel term")
        return self._between(neighbours, weights, w_view, w_light, target, angular_taps=angular_taps, **self.options)
