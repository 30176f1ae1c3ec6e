"""The fast training kernel: L1 loss of an MLP over whole-image batches, fused and chunked.

In a whole-image batch (``B`` images, each under one (view, light) pair, all at
the same ``N`` texels) the first layer of a decoder that takes
``concat(positional, angular)`` splits into a per-texel part and a per-image
part::

    z1[b, t] = W_U f_U[t] + (W_A a[b] + b_1) = P[t] + Q[b]

so ``P`` ``(N, hidden)`` is computed once for all ``B`` images and ``Q``
``(B, hidden)`` once per image. The same holds per *texel group*: a batch may
split its ``N`` texels into ``G`` equal groups, group ``g`` seen under its own ``B``
pairs (``Q`` of shape ``(G, B, hidden)``), so one step covers ``G * B`` distinct
(view, light) pairs at the cost of ``B`` whole images. What remains per sample is layers 2.. and the
loss. Running those as ordinary autograd ops streams ``(B * N, hidden)``
tensors through memory a dozen times per step; on a CPU that is bound by
memory bandwidth, not arithmetic. :func:`split_mlp_l1_loss` instead walks the
texels in small chunks whose activations stay in cache, computes the forward
pass, the L1 loss and the whole backward pass of each chunk by hand
(LeakyReLU MLP, ``d|r|/dr = sign(r)``), and accumulates the gradients of ``P``,
``Q`` and the layer weights. It is an ``autograd.Function``: the gradients
flow on to the planes and the first layer through ordinary autograd.

Two implementations compute the same thing:

* the **native kernel** (``dynbtf/decoder/native/fused_mlp.cpp``, built on first use by
  :mod:`dynbtf.decoder.native`), used for float32 CPU tensors: tiles of one image x 64 texels whose
  activations stay in the L1 cache, register-blocked products, no per-op overhead. In
  ``precision="fp32"`` it equals the PyTorch path to float rounding; in ``"bf16"`` (CPUs
  with AVX512-BF16) the products take bfloat16 inputs and accumulate in float32, everything
  else -- parameters, residuals, LeakyReLU gains, every gradient accumulator -- stays float32
  (mixed precision). Measured at 128 x 128 (``benchmarks/bench_training.py``): 14-16x the
  naive recipe's samples/s in bf16, 11x in fp32, and the same held-out PSNR per step as fp32.
* the **PyTorch path** (:func:`_chunk_range`): chunks of 256 texels x 16 images through
  ordinary torch ops with a hand-written backward -- for other dtypes, GPUs, machines
  without a C++ compiler, and as the reference the native kernel is tested against.

Chunks are split across ``workers`` Python threads (torch and the native kernel release the
GIL) with torch's own intra-op threading disabled for the duration: on a small shared CPU
this avoids OpenMP barriers stalling on a descheduled thread. Gradients are summed over
workers in a fixed order, so the result is deterministic for a given ``workers`` and
``chunk_texels`` on a given machine.
"""

from __future__ import annotations

import contextlib
import ctypes
from concurrent.futures import ThreadPoolExecutor
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from . import native
from ..errors import InputError

__all__ = ["split_mlp_l1_loss", "single_intra_op_thread", "native_precisions", "resolve_precision"]

_POOLS: dict[int, ThreadPoolExecutor] = {}


def _pool(workers: int) -> ThreadPoolExecutor:
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="dynbtf-mlp")
    return _POOLS[workers]


@contextlib.contextmanager
def single_intra_op_thread(enabled: bool = True):
    """Temporarily run torch kernels on one intra-op thread (restored on exit)."""
    previous = torch.get_num_threads()
    if enabled and previous != 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)


def _chunks(groups: int, group_size: int, chunk: int) -> list[tuple[int, int, int, int]]:
    """Work items ``(g0, g1, a, b)``: texels ``[a, b)`` of each of the groups ``[g0, g1)``, about ``chunk`` texels.

    Groups smaller than a chunk are taken several at a time (whole); larger ones are cut into pieces.
    """
    if group_size >= chunk:
        return [(g, g + 1, a, min(a + chunk, group_size)) for g in range(groups) for a in range(0, group_size, chunk)]
    per = max(1, chunk // group_size)
    return [(g, min(g + per, groups), 0, group_size) for g in range(0, groups, per)]


def _chunk_range(positional_pre, image_pre, weights, biases, slope, target, items):
    """Forward + L1 + backward over the work items ``(g0, g1, a, b)``; returns partial sums.

    ``positional_pre`` is ``(G * n, hidden)`` (group-major), ``image_pre`` ``(G, B, hidden)``,
    ``target`` ``(B, G * n, C)``.
    """
    groups, b, hidden = image_pre.shape
    n = positional_pre.shape[0] // groups
    w_t = [w.t() for w in weights]
    g_weights = [torch.zeros_like(w) for w in weights]
    g_biases = [torch.zeros_like(x) for x in biases]
    g_positional = {}
    g_image = torch.zeros_like(image_pre)
    loss = torch.zeros((), dtype=torch.float64, device=positional_pre.device)
    last = len(weights) - 1
    for g0, g1, t0, t1 in items:
        gc, nc = g1 - g0, t1 - t0
        r0, r1 = g0 * n + t0, (g1 - 1) * n + t1  # contiguous rows: whole groups, or a piece of one
        # forward: activations[k] is the input of layer k + 2 (layer 1's output after LeakyReLU)
        first = positional_pre[r0:r1].view(gc, 1, nc, hidden) + image_pre[g0:g1].view(gc, b, 1, hidden)
        activations = [F.leaky_relu(first, slope).reshape(-1, hidden)]
        for k in range(last):
            activations.append(F.leaky_relu(torch.addmm(biases[k], activations[-1], w_t[k]), slope))
        out = torch.addmm(biases[last], activations[-1], w_t[last])
        residual = out.view(gc, b, nc, -1) - target[:, r0:r1].view(b, gc, nc, -1).transpose(0, 1)
        loss += residual.abs().sum(dtype=torch.float64)
        # backward of sum |residual|
        grad = torch.sign(residual).reshape(out.shape)
        for k in range(last, -1, -1):
            g_weights[k].addmm_(grad.t(), activations[k])
            g_biases[k] += grad.sum(0)
            grad = torch.ops.aten.leaky_relu_backward(grad @ weights[k], activations[k], slope, True)
        grad = grad.view(gc, b, nc, hidden)
        g_positional[r0] = grad.sum(1).reshape(gc * nc, hidden)
        g_image[g0:g1] += grad.sum(2)
    return loss, g_positional, g_image, g_weights, g_biases


# ---------------------------------------------------------------------------- native kernel
class _NativeArgs(ctypes.Structure):
    """``FusedL1Args`` of ``dynbtf/decoder/native/fused_mlp.cpp`` (same field order)."""

    _fields_ = [("hidden", ctypes.c_int32), ("out_channels", ctypes.c_int32), ("n_layers", ctypes.c_int32),
                ("groups", ctypes.c_int32), ("images", ctypes.c_int32), ("texels_per_group", ctypes.c_int32),
                ("slope", ctypes.c_float), ("n_items", ctypes.c_int32), ("items", ctypes.c_void_p),
                ("positional_pre", ctypes.c_void_p), ("image_pre", ctypes.c_void_p), ("target", ctypes.c_void_p),
                ("weights", ctypes.c_void_p), ("biases", ctypes.c_void_p), ("grad_positional", ctypes.c_void_p),
                ("grad_image", ctypes.c_void_p), ("grad_weights", ctypes.c_void_p), ("grad_biases", ctypes.c_void_p),
                ("loss", ctypes.c_double)]


def _native_library():
    """The kernel built for the active instruction-set level (:func:`dynbtf.cpu.active_isa`), or None."""
    library = native.load_library("fused_mlp")
    if library is not None and not hasattr(library, "_dynbtf_ready"):
        for fn in (library.dynbtf_fused_l1_fp32, library.dynbtf_fused_l1_bf16):
            fn.argtypes = [ctypes.POINTER(_NativeArgs)]
            fn.restype = ctypes.c_int
        library.dynbtf_fused_l1_has_bf16.restype = ctypes.c_int
        library.dynbtf_fused_l1_args_size.restype = ctypes.c_int
        library.dynbtf_fused_l1_supports.restype = ctypes.c_int
        library.dynbtf_fused_l1_supports.argtypes = [ctypes.c_int32] * 3
        native_size, mirror_size = library.dynbtf_fused_l1_args_size(), ctypes.sizeof(_NativeArgs)
        if native_size != mirror_size:  # a field added on one side only: never call with a wrong layout
            raise RuntimeError(f"dynbtf/decoder/native/fused_mlp.cpp: FusedL1Args is {native_size} bytes but its ctypes "
                               f"mirror in {__name__} is {mirror_size}; update both field lists together")
        library._dynbtf_ready = True
    return library


def native_precisions() -> tuple[str, ...]:
    """Precisions the native CPU kernel offers on this machine: ``("fp32", "bf16")``, ``("fp32",)`` or ``()``.

    ``bf16`` needs a CPU with AVX512-BF16 (bfloat16 dot products); without a C++ compiler there is no
    native kernel and training uses the PyTorch path (fp32). :func:`dynbtf.decoder.native.status` says why.
    """
    library = _native_library()
    if library is None:
        return ()
    return ("fp32", "bf16") if library.dynbtf_fused_l1_has_bf16() else ("fp32",)


def resolve_precision(precision: str, device: torch.device | str = "cpu") -> str:
    """The arithmetic of the fused loss: ``"fp32"`` or ``"bf16"``.

    ``"auto"`` picks ``"bf16"`` on a CPU whose native kernel has it (several times faster, see
    ``benchmarks/bench_training.py``), else ``"fp32"``. ``"bf16"`` on a machine without it is an error.
    """
    device = torch.device(device)
    if precision not in ("auto", "fp32", "bf16"):
        raise InputError(f"precision: expected 'auto', 'fp32' or 'bf16', got {precision!r}")
    available = native_precisions() if device.type == "cpu" else ()
    if precision == "auto":
        return "bf16" if "bf16" in available else "fp32"
    if precision == "bf16" and "bf16" not in available:
        where = "on the GPU" if device.type != "cpu" else f"on this CPU ({native.status('fused_mlp')})"
        raise InputError(f"precision='bf16': the bfloat16 training kernel is not available {where}; "
                         "use 'fp32' or 'auto'")
    return precision


def _pointer_array(tensors: Sequence[torch.Tensor]):
    return (ctypes.c_void_p * len(tensors))(*[t.data_ptr() for t in tensors])


def _native_range(precision, positional_pre, image_pre, weights, biases, slope, target, items, g_positional):
    """The native kernel over ``items`` (int64 ``(k, 3)``: group, texel range); same partial sums as
    :func:`_chunk_range` but ``g_positional`` rows are written in place."""
    groups, b, hidden = image_pre.shape
    g_weights = [torch.zeros_like(w) for w in weights]
    g_biases = [torch.zeros_like(x) for x in biases]
    g_image = torch.zeros_like(image_pre)
    args = _NativeArgs(hidden=hidden, out_channels=weights[-1].shape[0], n_layers=len(weights), groups=groups,
                       images=b, texels_per_group=positional_pre.shape[0] // groups, slope=slope,
                       n_items=items.shape[0], items=items.data_ptr(), positional_pre=positional_pre.data_ptr(),
                       image_pre=image_pre.data_ptr(), target=target.data_ptr(), loss=0.0)
    keep = [_pointer_array(weights), _pointer_array(biases), _pointer_array(g_weights), _pointer_array(g_biases)]
    args.weights, args.biases, args.grad_weights, args.grad_biases = [ctypes.addressof(k) for k in keep]
    args.grad_positional, args.grad_image = g_positional.data_ptr(), g_image.data_ptr()
    library = _native_library()
    fn = library.dynbtf_fused_l1_bf16 if precision == "bf16" else library.dynbtf_fused_l1_fp32
    code = fn(ctypes.byref(args))
    if code != 0:
        raise RuntimeError(f"native fused_mlp kernel refused its arguments (code {code})")
    loss = torch.tensor(args.loss, dtype=torch.float64)
    return loss, g_image, g_weights, g_biases


def _native_supports(positional_pre, weights, precision) -> bool:
    """Whether the native kernel handles this call: CPU float32, the precision available, square hidden
    layers, and a layer shape the kernel reports it has a path for (``dynbtf_fused_l1_supports``)."""
    hidden = positional_pre.shape[1]
    if not (positional_pre.device.type == "cpu" and positional_pre.dtype == torch.float32
            and precision in native_precisions()
            and all(tuple(w.shape) == (hidden, hidden) for w in weights[:-1]) and weights[-1].shape[1] == hidden):
        return False
    return bool(_native_library().dynbtf_fused_l1_supports(hidden, weights[-1].shape[0], len(weights)))


class _SplitMLPL1(torch.autograd.Function):
    @staticmethod
    def forward(ctx, positional_pre, image_pre, target, slope, chunk, workers, precision, *weights_and_biases):
        n_layers = len(weights_and_biases) // 2
        weights, biases = weights_and_biases[:n_layers], weights_and_biases[n_layers:]
        groups = image_pre.shape[0]
        n = positional_pre.shape[0] // groups
        args = (positional_pre.detach().contiguous(), image_pre.detach().contiguous(),
                [w.detach().contiguous() for w in weights], [x.detach().contiguous() for x in biases], slope,
                target.contiguous())
        native_kernel = _native_supports(positional_pre, weights, precision)
        if native_kernel:
            # work items: (group, texel range) in chunks, split evenly over the workers
            items = torch.tensor([(g, a, min(a + chunk, n)) for g in range(groups) for a in range(0, n, chunk)],
                                 dtype=torch.int64)
            g_positional = torch.empty_like(args[0])
            run = lambda part: _native_range(precision, *args, part, g_positional)  # noqa: E731
        else:
            if precision != "fp32":
                raise InputError(f"precision={precision!r} needs the native CPU kernel; it is not available here")
            items = _chunks(groups, n, chunk)
            run = lambda part: _chunk_range(*args, part)  # noqa: E731
        workers = max(1, min(workers, len(items)))
        split = [round(len(items) * k / workers) for k in range(workers + 1)]
        if workers == 1:
            parts = [run(items)]
        else:
            with single_intra_op_thread():
                futures = [_pool(workers).submit(run, items[split[k]:split[k + 1]]) for k in range(workers)]
                parts = [f.result() for f in futures]
        count = float(target.numel())
        if native_kernel:
            parts = [(p[0], None, *p[1:]) for p in parts]
        else:
            g_positional = torch.cat([p[1][r0] for p in parts for r0 in sorted(p[1])])
        loss = sum(p[0] for p in parts) / count
        g_image = parts[0][2].clone()
        g_weights = [g.clone() for g in parts[0][3]]
        g_biases = [g.clone() for g in parts[0][4]]
        for p in parts[1:]:
            g_image += p[2]
            for acc, g in zip(g_weights + g_biases, p[3] + p[4]):
                acc += g
        ctx.save_for_backward(g_positional / count, g_image / count, *[g / count for g in g_weights + g_biases])
        return loss.to(positional_pre.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_loss):
        g_positional, g_image, *g_params = ctx.saved_tensors
        return (g_positional * grad_loss, g_image * grad_loss, None, None, None, None, None,
                *[g * grad_loss for g in g_params])


def split_mlp_l1_loss(positional_pre: torch.Tensor, image_pre: torch.Tensor, layers: Sequence[nn.Linear],
                      negative_slope: float, target: torch.Tensor, *, chunk_texels: int = 256,
                      workers: int = 1, precision: str = "fp32") -> torch.Tensor:
    """Mean L1 loss of a LeakyReLU MLP whose first layer is split per texel / per image.

    Computes ``mean |MLP(P[t] + Q[g(t), b]) - target[b, t]|`` where the ``N`` texels
    form ``G`` equal consecutive groups (``g(t) = t // (N / G)``; one group: ``Q[b]``)
    and the MLP applies LeakyReLU to its input, then ``layers`` (LeakyReLU after
    each but the last). Equal (to float rounding) to the same expression written
    with ordinary torch ops, with identical gradients, at a fraction of the memory
    traffic.

    Parameters
    ----------
    positional_pre : ``(N, hidden)``
        Layer 1's per-texel part ``W_U f_U`` (requires grad for training).
    image_pre : ``(B, hidden)`` or ``(G, B, hidden)``
        Layer 1's per-image part ``W_A a + b_1``; with ``G`` texel groups (``G``
        divides ``N``), the ``B`` images of each group.
    layers : sequence of ``nn.Linear``
        Layers 2 .. L; the last outputs ``C`` channels without activation.
    negative_slope : float
        LeakyReLU slope.
    target : ``(B, N, C)``
        Ground truth (no gradient): ``target[b, t]`` is texel ``t`` under image ``b``
        of its group.
    chunk_texels : int
        Texels per chunk (the chunk holds ``B * chunk_texels`` samples); 256 keeps
        a 16-image chunk's activations in a CPU's L2 cache.
    workers : int
        Threads processing chunks in parallel.
    precision : {"fp32", "bf16", "auto"}
        Arithmetic of layers 2..: ``"fp32"`` (the native kernel where it builds, else PyTorch;
        both float32), ``"bf16"`` (native kernel on CPUs with AVX512-BF16: bfloat16 products
        accumulated in float32, float32 gradients), ``"auto"`` (see :func:`resolve_precision`).

    Returns
    -------
    Scalar tensor: the mean absolute error over ``B * N * C`` values.
    """
    n, hidden = positional_pre.shape
    if image_pre.ndim == 2:
        image_pre = image_pre[None]
    if image_pre.ndim != 3 or image_pre.shape[2] != hidden:
        raise InputError(f"image_pre: expected shape (B, {hidden}) or (G, B, {hidden}), got {tuple(image_pre.shape)}")
    if n % image_pre.shape[0]:
        raise InputError(f"image_pre: {image_pre.shape[0]} texel groups do not divide the {n} texels evenly")
    if target.shape[:2] != (image_pre.shape[1], n):
        raise InputError(f"target: expected shape ({image_pre.shape[1]}, {n}, C), got {tuple(target.shape)}")
    if chunk_texels < 1 or workers < 1:
        raise InputError(f"chunk_texels and workers must be >= 1, got {chunk_texels}, {workers}")
    weights = [layer.weight for layer in layers]
    biases = [layer.bias for layer in layers]
    target = target.to(positional_pre.dtype)
    precision = resolve_precision(precision, positional_pre.device)
    return _SplitMLPL1.apply(positional_pre, image_pre, target, float(negative_slope), int(chunk_texels),
                             int(workers), precision, *weights, *biases)
