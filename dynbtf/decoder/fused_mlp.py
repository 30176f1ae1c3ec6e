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
  (mixed precision). Speed per level: ``benchmarks/bench_training.py`` (docs/results.md).
* the **PyTorch path** (:func:`_chunk_range`): chunks of 256 texels x 16 images through
  ordinary torch ops with a hand-written backward -- for other dtypes, GPUs, machines
  without a C++ compiler, and as the reference the native kernel is tested against.

For a Triple Plane, :func:`triple_plane_l1_loss` also moves the plane fetches and layer 1 into native code
(``dynbtf_first_layer_forward`` / ``_backward``): the whole decoder and its planes are one autograd node.

Chunks are split across ``workers`` Python threads (torch and the native kernel release the
GIL) with torch's own intra-op threading disabled for the duration: on a small shared CPU
this avoids OpenMP barriers stalling on a descheduled thread. Gradients are summed over
workers in a fixed order, so the result is deterministic for a given ``workers`` and
``chunk_texels`` on a given machine.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
from concurrent.futures import ThreadPoolExecutor
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from . import native
from ..errors import InputError

__all__ = ["split_mlp_l1_loss", "decoder_l1_loss", "triple_plane_l1_loss", "native_mlp_forward", "native_affine_rows", "single_intra_op_thread", "native_precisions", "resolve_precision"]

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
                ("item_stride", ctypes.c_int64), ("item_grads", ctypes.c_void_p), ("item_loss", ctypes.c_void_p),
                ("next_item", ctypes.c_void_p)]


class _FirstLayerArgs(ctypes.Structure):
    """``FirstLayerArgs`` of ``dynbtf/decoder/native/fused_mlp.cpp`` (same field order)."""

    _fields_ = [("hidden", ctypes.c_int32), ("positional", ctypes.c_int32), ("angular", ctypes.c_int32),
                ("plane_channels", ctypes.c_int32), ("taps", ctypes.c_int32), ("texel_taps", ctypes.c_int32),
                ("rows", ctypes.c_int64),
                ("images", ctypes.c_int64), ("plane_rows", ctypes.c_int64), ("angular_rows", ctypes.c_int64),
                ("positional_scale", ctypes.c_float), ("weight", ctypes.c_void_p), ("bias", ctypes.c_void_p),
                ("plane", ctypes.c_void_p),
                ("texels", ctypes.c_void_p), ("texel_weight", ctypes.c_void_p), ("angular_planes", ctypes.c_void_p),
                ("tap_index", ctypes.c_void_p),
                ("tap_weight", ctypes.c_void_p), ("positional_pre", ctypes.c_void_p),
                ("angular_features", ctypes.c_void_p), ("image_pre", ctypes.c_void_p)]


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
        library.dynbtf_fused_l1_item_floats.restype = ctypes.c_int64
        library.dynbtf_fused_l1_item_floats.argtypes = [ctypes.c_int32] * 4
        library.dynbtf_fused_l1_reduce.argtypes = [ctypes.POINTER(_NativeArgs), ctypes.c_float] + [ctypes.c_void_p] * 3
        library.dynbtf_fused_l1_reduce.restype = ctypes.c_int
        library.dynbtf_mlp_forward_fp32.argtypes = [ctypes.POINTER(_MlpArgs)]
        library.dynbtf_mlp_forward_fp32.restype = ctypes.c_int
        library.dynbtf_affine_rows_fp32.argtypes = [ctypes.c_int64, ctypes.c_int32, ctypes.c_int32] + \
            [ctypes.c_void_p] * 4
        library.dynbtf_affine_rows_fp32.restype = ctypes.c_int
        library.dynbtf_first_layer_forward.argtypes = [ctypes.POINTER(_FirstLayerArgs)]
        library.dynbtf_first_layer_forward.restype = ctypes.c_int
        library.dynbtf_first_layer_backward.argtypes = [ctypes.POINTER(_FirstLayerArgs)] + [ctypes.c_void_p] * 6
        library.dynbtf_first_layer_backward.restype = ctypes.c_int
        library.dynbtf_first_layer_supports.argtypes = [ctypes.c_int32] * 3
        library.dynbtf_first_layer_supports.restype = ctypes.c_int
        library.dynbtf_first_layer_args_size.restype = ctypes.c_int
        for name, native_size, mirror in (("FusedL1Args", library.dynbtf_fused_l1_args_size(), _NativeArgs),
                                          ("FirstLayerArgs", library.dynbtf_first_layer_args_size(), _FirstLayerArgs)):
            if native_size != ctypes.sizeof(mirror):  # a field added on one side only: never call with a wrong layout
                raise RuntimeError(f"dynbtf/decoder/native/fused_mlp.cpp: {name} is {native_size} bytes but its "
                                   f"ctypes mirror in {__name__} is {ctypes.sizeof(mirror)}; update both field lists "
                                   "together")
        library._dynbtf_ready = True
    return library


class _MlpArgs(ctypes.Structure):
    """``MlpArgs`` of ``dynbtf/decoder/native/fused_mlp.cpp`` (same field order)."""

    _fields_ = [("hidden", ctypes.c_int32), ("out_channels", ctypes.c_int32), ("n_layers", ctypes.c_int32),
                ("slope", ctypes.c_float), ("activate_input", ctypes.c_int32), ("rows", ctypes.c_int64),
                ("x", ctypes.c_void_p),
                ("weights", ctypes.c_void_p), ("biases", ctypes.c_void_p), ("out", ctypes.c_void_p)]


def native_mlp_forward(x: torch.Tensor, layers: Sequence[tuple[torch.Tensor, torch.Tensor]], slope: float, *,
                       activate_input: bool = False) -> torch.Tensor | None:
    """Inference with the training kernel's products: layers ``[(weight (out, in), bias (out,)), ...]`` with
    LeakyReLU between them on rows ``x (N, H)`` (layer 1's activations; ``activate_input``: its pre-activation,
    the LeakyReLU applied first) -> float32 ``(N, C)``; tiles of rows stay in the L1 cache. None where the native
    kernel does not take the call (another device or dtype, a shape without a template instance, gradients to
    carry, no compiler): the caller uses torch."""
    if not (x.device.type == "cpu" and x.dtype == torch.float32 and x.ndim == 2 and layers):
        return None
    if torch.is_grad_enabled() and (x.requires_grad or any(t.requires_grad for layer in layers for t in layer)):
        return None  # training these layers (e.g. the per-level decoders' fit): torch's ops carry the gradients
    hidden = x.shape[1]
    weights = [w.detach().contiguous() for w, _ in layers]
    biases = [b.detach().contiguous() for _, b in layers]
    if not all(w.dtype == torch.float32 and w.device.type == "cpu" for w in weights + biases):
        return None
    if not (all(tuple(w.shape) == (hidden, hidden) for w in weights[:-1]) and weights[-1].shape[1] == hidden):
        return None
    library = _native_library()
    if library is None or not library.dynbtf_fused_l1_supports(hidden, weights[-1].shape[0], len(weights)):
        return None
    x = x.detach().contiguous()
    out = torch.empty((x.shape[0], weights[-1].shape[0]), dtype=torch.float32)
    keep = [_pointer_array(weights), _pointer_array(biases)]
    args = _MlpArgs(hidden=hidden, out_channels=weights[-1].shape[0], n_layers=len(weights), slope=float(slope),
                    activate_input=int(activate_input), rows=x.shape[0], x=x.data_ptr(), weights=ctypes.addressof(keep[0]),
                    biases=ctypes.addressof(keep[1]), out=out.data_ptr())
    if library.dynbtf_mlp_forward_fp32(ctypes.byref(args)) != 0:
        return None
    return out


def native_affine_rows(x: np.ndarray, weight: np.ndarray, bias: np.ndarray, out: np.ndarray) -> bool:
    """``out = x @ weight + bias`` row by row (float32 ``(N, in)``, ``(in, hidden)``, ``(hidden,)``, ``(N, hidden)``,
    C-contiguous) in the native kernel: each row's sum in input order whatever the rows around it or the calling
    thread (BLAS's depend on both). False when the kernel does not take it (no compiler, ``hidden`` not a whole
    number of vectors): the caller computes it another way."""
    library = _native_library()
    if library is None:
        return False
    rows, inputs = x.shape
    code = library.dynbtf_affine_rows_fp32(rows, inputs, weight.shape[1], x.ctypes.data, weight.ctypes.data,
                                           bias.ctypes.data, out.ctypes.data)
    return code == 0


def native_precisions(library=None) -> tuple[str, ...]:
    """Precisions the native CPU kernel offers on this machine: ``("fp32", "bf16")``, ``("fp32",)`` or ``()``.

    ``bf16`` needs a CPU with AVX512-BF16 (bfloat16 dot products); without a C++ compiler there is no
    native kernel and training uses the PyTorch path (fp32). :func:`dynbtf.decoder.native.status` says why.
    """
    library = library or _native_library()
    if library is None:
        return ()
    return ("fp32", "bf16") if library.dynbtf_fused_l1_has_bf16() else ("fp32",)


def resolve_precision(precision: str, device: torch.device | str = "cpu") -> str:
    """The arithmetic of the fused loss: ``"fp32"`` or ``"bf16"``.

    ``"auto"`` is ``"fp32"`` on every machine: the float32 kernel, register-blocked for each level's vectors, gives
    results that agree across levels to float32 rounding (a seed fits the same model on every CPU, to rounding).
    ``"bf16"`` (bfloat16 products, float32 accumulation) is there to ask for on CPUs with AVX512-BF16, where it
    may train faster (docs/results.md's training table measures both, ``benchmarks/bench_training.py``); on a
    machine without it, an error.
    """
    device = torch.device(device)
    if precision not in ("auto", "fp32", "bf16"):
        raise InputError(f"precision: expected 'auto', 'fp32' or 'bf16', got {precision!r}")
    if precision in ("auto", "fp32"):
        return "fp32"
    available = native_precisions() if device.type == "cpu" else ()
    if precision == "bf16" and "bf16" not in available:
        where = "on the GPU" if device.type != "cpu" else f"on this CPU ({native.status('fused_mlp')})"
        raise InputError(f"precision='bf16': the bfloat16 training kernel is not available {where}; "
                         "use 'fp32' or 'auto'")
    return precision


def _pointer_array(tensors: Sequence[torch.Tensor]):
    return (ctypes.c_void_p * len(tensors))(*[t.data_ptr() for t in tensors])


@functools.lru_cache(maxsize=16)
def _work_items(groups: int, n: int, chunk: int) -> torch.Tensor:
    """The native kernel's work items, int64 ``(k, 3)``: (group, first texel, end texel) in chunks of ``chunk``
    texels, group by group (the same for every step of a fit: computed once)."""
    return torch.tensor([(g, a, min(a + chunk, n)) for g in range(groups) for a in range(0, n, chunk)],
                        dtype=torch.int64)


def _native_loss(precision, positional_pre, image_pre, weights, biases, slope, target, chunk, workers, scale,
                 scale_positional=True, library=None):
    """The native kernel over every ``(group, chunk of texels)`` item, on ``workers`` threads that take items
    from a shared counter. Returns the same sums as :func:`_chunk_range` over all items: ``(loss, g_positional,
    g_image, g_weights, g_biases)``, the gradients times ``scale``, each item's summed in item order
    (deterministic)."""
    groups, b, hidden = image_pre.shape
    n = positional_pre.shape[0] // groups
    items = _work_items(groups, n, chunk)
    library = library or _native_library()
    out = weights[-1].shape[0]
    stride = library.dynbtf_fused_l1_item_floats(hidden, out, len(weights), b)
    item_grads = torch.empty((len(items), stride), dtype=torch.float32)
    item_loss = torch.empty(len(items), dtype=torch.float64)
    next_item = torch.zeros(1, dtype=torch.int32)
    g_positional = torch.empty_like(positional_pre)
    keep = [_pointer_array(weights), _pointer_array(biases)]
    args = _NativeArgs(hidden=hidden, out_channels=out, n_layers=len(weights), groups=groups, images=b,
                       texels_per_group=n, slope=slope, n_items=len(items), items=items.data_ptr(),
                       positional_pre=positional_pre.data_ptr(), image_pre=image_pre.data_ptr(),
                       target=target.data_ptr(), weights=ctypes.addressof(keep[0]), biases=ctypes.addressof(keep[1]),
                       grad_positional=g_positional.data_ptr(), item_stride=stride, item_grads=item_grads.data_ptr(),
                       item_loss=item_loss.data_ptr(), next_item=next_item.data_ptr())
    fn = library.dynbtf_fused_l1_bf16 if precision == "bf16" else library.dynbtf_fused_l1_fp32
    workers = max(1, min(workers, len(items)))
    if workers == 1:
        codes = [fn(ctypes.byref(args))]
    else:
        # the calling thread is one of the workers (ctypes releases the GIL during the call)
        futures = [_pool(workers - 1).submit(fn, ctypes.byref(args)) for _ in range(workers - 1)]
        codes = [fn(ctypes.byref(args))] + [f.result() for f in futures]
    if any(codes):
        raise RuntimeError(f"native fused_mlp kernel refused its arguments (codes {codes})")
    # the slots summed in item order, scaled by `scale` (the weights' over all items, dQ per group)
    weight_grads = torch.empty(stride - b * hidden, dtype=torch.float32)
    g_image = torch.empty((groups, b, hidden), dtype=torch.float32)
    loss = torch.empty((), dtype=torch.float64)
    if library.dynbtf_fused_l1_reduce(ctypes.byref(args), scale, weight_grads.data_ptr(), g_image.data_ptr(),
                                      loss.data_ptr()):
        raise RuntimeError(f"native fused_mlp kernel: {len(items)} work items are not {groups} equal groups")
    if scale_positional:
        g_positional.mul_(scale)
    parts = torch.split_with_sizes(weight_grads, [w.numel() for w in weights] + [x.numel() for x in biases])
    g_weights = [p.view_as(w) for p, w in zip(parts[:len(weights)], weights)]
    g_biases = [p.view_as(x) for p, x in zip(parts[len(weights):], biases)]
    return loss, g_positional, g_image, g_weights, g_biases


def _native_supports(positional_pre, weights, precision, library=None) -> bool:
    """Whether the native kernel (``library``, default :func:`_native_library`) handles this call: CPU float32,
    the precision available, square hidden layers, and a layer shape the kernel reports it has a path for
    (``dynbtf_fused_l1_supports``)."""
    hidden = positional_pre.shape[1]
    library = library or _native_library()
    if precision not in native_precisions(library):
        return False
    if not (positional_pre.device.type == "cpu" and positional_pre.dtype == torch.float32
            and all(tuple(w.shape) == (hidden, hidden) for w in weights[:-1]) and weights[-1].shape[1] == hidden):
        return False
    return bool(library.dynbtf_fused_l1_supports(hidden, weights[-1].shape[0], len(weights)))


def _fused_sums(positional_pre, image_pre, target, slope, chunk, workers, precision, weights, biases):
    """Sum of ``|residual|`` over the batch and the gradients of its mean ``(loss_sum, g_positional, g_image,
    g_weights, g_biases)``, by the native kernel where it runs, else the PyTorch path."""
    scale = 1.0 / target.numel()
    groups = image_pre.shape[0]
    n = positional_pre.shape[0] // groups
    args = (positional_pre.detach().contiguous(), image_pre.detach().contiguous(),
            [w.detach().contiguous() for w in weights], [x.detach().contiguous() for x in biases], slope,
            target.contiguous())
    library = _native_library()
    if _native_supports(positional_pre, weights, precision, library):
        with single_intra_op_thread():
            return _native_loss(precision, *args, chunk, workers, scale, library=library)
    if precision != "fp32":
        raise InputError(f"precision={precision!r} needs the native CPU kernel; it is not available here")
    items = _chunks(groups, n, chunk)
    workers = max(1, min(workers, len(items)))
    split = [round(len(items) * k / workers) for k in range(workers + 1)]
    if workers == 1:
        parts = [_chunk_range(*args, items)]
    else:
        with single_intra_op_thread():
            futures = [_pool(workers).submit(_chunk_range, *args, items[split[k]:split[k + 1]])
                       for k in range(workers)]
            parts = [f.result() for f in futures]
    g_positional = torch.cat([p[1][r0] for p in parts for r0 in sorted(p[1])])
    loss = sum(p[0] for p in parts)
    g_image = parts[0][2].clone()
    g_weights = [g.clone() for g in parts[0][3]]
    g_biases = [g.clone() for g in parts[0][4]]
    for p in parts[1:]:
        g_image += p[2]
        for acc, g in zip(g_weights + g_biases, p[3] + p[4]):
            acc += g
    for g in [g_positional, g_image, *g_weights, *g_biases]:
        g.mul_(scale)
    return loss, g_positional, g_image, g_weights, g_biases


class _SplitMLPL1(torch.autograd.Function):
    """The mean L1 loss from layer 1's two parts ``P``, ``Q`` (:func:`split_mlp_l1_loss`)."""

    @staticmethod
    def forward(ctx, positional_pre, image_pre, target, slope, chunk, workers, precision, *weights_and_biases):
        n_layers = len(weights_and_biases) // 2
        loss, g_positional, g_image, g_weights, g_biases = _fused_sums(
            positional_pre, image_pre, target, slope, chunk, workers, precision, weights_and_biases[:n_layers],
            weights_and_biases[n_layers:])
        ctx.save_for_backward(g_positional, g_image, *g_weights, *g_biases)  # of the mean
        return (loss / target.numel()).to(positional_pre.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_loss):
        g_positional, g_image, *g_params = _times(ctx.saved_tensors, grad_loss)
        return (g_positional, g_image, None, None, None, None, None, *g_params)


class _DecoderL1(torch.autograd.Function):
    """The mean L1 loss from the decoder's inputs, layer 1 included (:func:`decoder_l1_loss`): one autograd
    node for the whole decoder, layer 1's products and their gradients written out."""

    @staticmethod
    def forward(ctx, positional, angular, first_weight, first_bias, target, slope, chunk, workers, precision,
                *weights_and_biases):
        n_layers = len(weights_and_biases) // 2
        c_u, images = positional.shape[1], target.shape[0]
        w_u, w_a = first_weight[:, :c_u], first_weight[:, c_u:]
        positional_pre = positional @ w_u.t()                        # (N, hidden): once per texel
        image_pre = torch.addmm(first_bias, angular, w_a.t())         # (G * B, hidden): once per image
        loss, g_positional, g_image, g_weights, g_biases = _fused_sums(
            positional_pre, image_pre.reshape(-1, images, image_pre.shape[-1]), target, slope, chunk, workers,
            precision, weights_and_biases[:n_layers], weights_and_biases[n_layers:])
        ctx.save_for_backward(positional, angular, w_u, w_a, g_positional, g_image.reshape(image_pre.shape),
                              *g_weights, *g_biases)
        return (loss / target.numel()).to(positional.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_loss):
        positional, angular, w_u, w_a = ctx.saved_tensors[:4]
        g_positional, g_image, *g_params = _times(ctx.saved_tensors[4:], grad_loss)  # d loss / d P, d Q, ...
        g_first = torch.cat([g_positional.t() @ positional, g_image.t() @ angular], dim=1)
        return (g_positional @ w_u if ctx.needs_input_grad[0] else None,
                g_image @ w_a if ctx.needs_input_grad[1] else None,
                g_first, g_image.sum(0), None, None, None, None, None, *g_params)


class _TriplePlaneL1(torch.autograd.Function):
    """The mean L1 loss from the planes themselves (:func:`triple_plane_l1_loss`): the plane fetches and layer 1
    in ``dynbtf_first_layer_forward`` / ``_backward``, layers 2.. in the fused kernel; one autograd node, every
    gradient computed in the forward pass (the kernels produce them together)."""

    @staticmethod
    def forward(ctx, plane, angular_planes, first_weight, first_bias, texels, texel_weights, tap_index, tap_weight,
                target, slope, chunk, workers, precision, *weights_and_biases):
        n_layers = len(weights_and_biases) // 2
        weights = [w.detach().contiguous() for w in weights_and_biases[:n_layers]]
        biases = [b.detach().contiguous() for b in weights_and_biases[n_layers:]]
        plane, angular_planes = plane.detach().contiguous(), angular_planes.detach().contiguous()
        first_weight, first_bias = first_weight.detach().contiguous(), first_bias.detach().contiguous()
        hidden, positional = first_weight.shape[0], plane.shape[1]
        images, planes, taps = tap_index.shape
        rows = plane.shape[0] if texels is None else texels.shape[-1]
        positional_pre = torch.empty((rows, hidden), dtype=torch.float32)
        angular = torch.empty((images, planes * angular_planes.shape[1]), dtype=torch.float32)
        image_pre = torch.empty((images, hidden), dtype=torch.float32)
        args = _FirstLayerArgs(
            hidden=hidden, positional=positional, angular=angular.shape[1], plane_channels=angular_planes.shape[1],
            taps=taps, texel_taps=1 if texel_weights is None else texel_weights.shape[0], rows=rows, images=images,
            plane_rows=plane.shape[0], angular_rows=angular_planes.shape[0],
            positional_scale=1.0 / target.numel(), weight=first_weight.data_ptr(), bias=first_bias.data_ptr(),
            plane=plane.data_ptr(),
            texels=None if texels is None else texels.data_ptr(),
            texel_weight=None if texel_weights is None else texel_weights.data_ptr(),
            angular_planes=angular_planes.data_ptr(),
            tap_index=tap_index.data_ptr(), tap_weight=tap_weight.data_ptr(), positional_pre=positional_pre.data_ptr(),
            angular_features=angular.data_ptr(), image_pre=image_pre.data_ptr())
        library = _native_library()
        code = library.dynbtf_first_layer_forward(ctypes.byref(args))
        if code:
            raise InputError("triple_plane_l1_loss: a texel or angular tap index outside its plane" if code == 2
                             else f"triple_plane_l1_loss: sizes the first-layer kernel does not take (code {code})")
        groups = images // target.shape[0]
        with single_intra_op_thread():
            loss, g_positional, g_image, g_weights, g_biases = _native_loss(
                precision, positional_pre, image_pre.view(groups, -1, hidden), weights, biases, slope,
                target.contiguous(), chunk, workers, 1.0 / target.numel(), scale_positional=False, library=library)
        g_image = g_image.reshape(images, hidden).contiguous()
        g_first_weight, g_first_bias = torch.empty_like(first_weight), torch.empty_like(first_bias)
        g_plane, g_angular_planes = torch.zeros_like(plane), torch.zeros_like(angular_planes)
        library.dynbtf_first_layer_backward(ctypes.byref(args), g_positional.data_ptr(), g_image.data_ptr(),
                                            g_first_weight.data_ptr(), g_first_bias.data_ptr(), g_plane.data_ptr(),
                                            g_angular_planes.data_ptr())
        ctx.save_for_backward(g_plane, g_angular_planes, g_first_weight, g_first_bias, *g_weights, *g_biases)
        return (loss / target.numel()).to(torch.float32)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_loss):
        g_plane, g_angular_planes, g_first_weight, g_first_bias, *g_params = _times(ctx.saved_tensors, grad_loss)
        return (g_plane, g_angular_planes, g_first_weight, g_first_bias, None, None, None, None, None, None, None,
                None, None, *g_params)


def triple_plane_l1_loss(plane: torch.Tensor, texels: torch.Tensor | None, angular_planes: torch.Tensor,
                         taps: tuple[torch.Tensor, torch.Tensor], first: nn.Linear, layers: Sequence[nn.Linear],
                         negative_slope: float, target: torch.Tensor, *, chunk_texels: int = 256, workers: int = 1,
                         precision: str = "fp32", texel_weights: torch.Tensor | None = None) -> torch.Tensor | None:
    """:func:`decoder_l1_loss` with the plane fetches included, all in native kernels: the mean L1 loss of a
    Triple Plane decoder on ``plane[texels]`` (``plane (T, C_U)``, the positional plane flattened; ``texels``
    int64 ``(N,)`` or None for all ``T``; with ``texel_weights`` float32 ``(J, N)``, ``texels`` is ``(J, N)`` and
    row ``r`` reads ``sum_j texel_weights[j, r] * plane[texels[j, r]]``, e.g. the bilinear mix of 4 texels at a
    point between centres) and, per image, the angular features fetched from ``angular_planes``
    (``(A, C)``: ``f_H`` and ``f_D`` flattened and stacked) at ``taps = (index, weight)``, each
    ``(G * B, planes, K)`` (:meth:`dynbtf.representations.triple_plane.TriplePlane.direction_taps`); ``target``
    ``(B, N, 3)``. Gradients flow to ``plane``, ``angular_planes`` and every layer; repeated texels and taps add
    up. Equal to :func:`decoder_l1_loss` on the fetched features to float rounding.

    Returns None where the native kernels do not take the call (another device or dtype, no compiler, a
    precision or layer shape the fused kernel has no path for): the caller uses :func:`decoder_l1_loss`.
    """
    if torch.compiler.is_compiling():  # torch.compile traces the ordinary ops instead (decoder_l1_loss)
        return None
    index, weight = taps
    tensors = [plane, angular_planes, first.weight, first.bias, target, weight] + \
        [t for layer in layers for t in (layer.weight, layer.bias)]
    if not all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors):
        return None
    if index.dtype != torch.int64 or index.ndim != 3 or weight.shape != index.shape or (
            texel_weights is None and texels is not None and (texels.dtype != torch.int64 or texels.ndim != 1)):
        return None
    if texel_weights is not None:
        if texels is None or texels.dtype != torch.int64 or texels.ndim != 2 or texel_weights.shape != texels.shape \
                or not 1 <= texels.shape[0] <= 16:
            raise InputError(f"texel_weights: expected (J, N) with texels int64 of the same shape and 1 <= J <= 16, "
                             f"got {tuple(texel_weights.shape)} and "
                             f"{None if texels is None else (tuple(texels.shape), texels.dtype)}")
        if texel_weights.device.type != "cpu" or texel_weights.dtype != torch.float32:
            return None
    try:
        precision = resolve_precision(precision, "cpu")
    except InputError:
        return None
    hidden = first.weight.shape[0]
    images, planes, _ = index.shape
    if first.weight.shape[1] != plane.shape[1] + planes * angular_planes.shape[1]:
        raise InputError(f"first layer takes {first.weight.shape[1]} inputs, but the positional plane "
                         f"({plane.shape[1]}) and {planes} angular planes of {angular_planes.shape[1]} give "
                         f"{plane.shape[1] + planes * angular_planes.shape[1]}")
    library = _native_library()
    weights = [layer.weight for layer in layers]
    if library is None or not _native_supports(torch.empty((0, hidden)), weights, precision, library) \
            or not library.dynbtf_first_layer_supports(hidden, plane.shape[1], planes * angular_planes.shape[1]):
        return None
    rows = plane.shape[0] if texels is None else texels.shape[-1]
    b = target.shape[0]
    if images % b or rows % (images // b):
        raise InputError(f"taps: expected (G * {b}, planes, K) with G dividing the {rows} texels, "
                         f"got {tuple(index.shape)}")
    _check_split_shapes(rows, hidden, (images // b, b), target, chunk_texels, workers)
    return _TriplePlaneL1.apply(plane, angular_planes, first.weight, first.bias,
                                None if texels is None else texels.contiguous(),
                                None if texel_weights is None else texel_weights.detach().contiguous(),
                                index.contiguous(),
                                weight.contiguous(), target, float(negative_slope), int(chunk_texels), int(workers),
                                precision, *weights, *[layer.bias for layer in layers])


def _times(gradients, grad_loss):
    """The saved gradients of the mean times the incoming ``grad_loss`` (skipped when it is 1, as in training)."""
    if grad_loss.numel() == 1 and float(grad_loss) == 1.0:
        return list(gradients)
    return [g * grad_loss for g in gradients]


def decoder_l1_loss(positional: torch.Tensor, angular: torch.Tensor, first: nn.Linear, layers: Sequence[nn.Linear],
                    negative_slope: float, target: torch.Tensor, *, chunk_texels: int = 256, workers: int = 1,
                    precision: str = "fp32") -> torch.Tensor:
    """:func:`split_mlp_l1_loss` with layer 1 included: the mean L1 loss of a decoder whose first layer ``first``
    acts on ``concat(positional, angular)``, given ``positional (N, C_U)`` (the texels, shared by a group's
    images) and ``angular (G * B, C_A)`` (one vector per image, group-major). Layer 1 is split as
    ``P = W_U positional``, ``Q = W_A angular + b`` and its gradients are written out, so the whole decoder is
    one autograd node (measured cheaper per step than layer 1 as ordinary ops). Equal to float rounding.

    Under ``torch.compile`` (:mod:`dynbtf.training.step_loss`) the loss is written as ordinary ops instead
    (:func:`_decoder_l1_loss_ops`), float32 only: autograd derives the backward pass and Inductor fuses both."""
    c_u = positional.shape[-1]
    if first.weight.shape[1] != c_u + angular.shape[-1]:
        raise InputError(f"first layer takes {first.weight.shape[1]} inputs, but positional ({c_u}) + angular "
                         f"({angular.shape[-1]}) give {c_u + angular.shape[-1]}")
    images = target.shape[0]
    if angular.ndim != 2 or angular.shape[0] % images or positional.shape[0] % (angular.shape[0] // images):
        raise InputError(f"angular: expected (G * {images}, C_A) with G dividing the {positional.shape[0]} texels, "
                         f"got {tuple(angular.shape)}")
    groups = angular.shape[0] // images
    _check_split_shapes(positional.shape[0], first.weight.shape[0], (groups, images), target, chunk_texels, workers)
    if torch.compiler.is_compiling():
        if precision != "fp32":
            raise InputError(f"precision={precision!r}: a compiled loss computes in float32 (use fp32)")
        return _decoder_l1_loss_ops(positional, angular, first, layers, float(negative_slope), target, groups)
    weights = [layer.weight for layer in layers]
    biases = [layer.bias for layer in layers]
    dtype = first.weight.dtype
    precision = resolve_precision(precision, first.weight.device)
    return _DecoderL1.apply(positional.to(dtype), angular.to(dtype), first.weight, first.bias, target.to(dtype),
                            float(negative_slope), int(chunk_texels), int(workers), precision, *weights, *biases)


def _decoder_l1_loss_ops(positional, angular, first, layers, slope, target, groups):
    """:func:`decoder_l1_loss` as ordinary differentiable ops (what ``torch.compile`` traces): layer 1 split into
    its per-texel and per-image products, added by broadcasting over the ``(G, B, n)`` samples."""
    images, hidden, c_u = target.shape[0], first.weight.shape[0], positional.shape[-1]
    n = positional.shape[0] // groups
    x = F.linear(positional, first.weight[:, :c_u]).view(groups, 1, n, hidden) + \
        F.linear(angular, first.weight[:, c_u:], first.bias).view(groups, images, 1, hidden)
    x = F.leaky_relu(x, slope)
    for k, layer in enumerate(layers):
        x = F.linear(x, layer.weight, layer.bias)
        if k < len(layers) - 1:
            x = F.leaky_relu(x, slope)
    return (x - target.view(images, groups, n, -1).transpose(0, 1)).abs().mean()


def _check_split_shapes(n: int, hidden: int, groups_images: tuple[int, int], target, chunk_texels, workers) -> None:
    groups, images = groups_images
    if n % groups:
        raise InputError(f"image_pre: {groups} texel groups do not divide the {n} texels evenly")
    if tuple(target.shape[:2]) != (images, n):
        raise InputError(f"target: expected shape ({images}, {n}, C), got {tuple(target.shape)}")
    if chunk_texels < 1 or workers < 1:
        raise InputError(f"chunk_texels and workers must be >= 1, got {chunk_texels}, {workers}")


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
    _check_split_shapes(n, hidden, image_pre.shape[:2], target, chunk_texels, workers)
    weights = [layer.weight for layer in layers]
    biases = [layer.bias for layer in layers]
    target = target.to(positional_pre.dtype)
    precision = resolve_precision(precision, positional_pre.device)
    return _SplitMLPL1.apply(positional_pre, image_pre, target, float(negative_slope), int(chunk_texels),
                             int(workers), precision, *weights, *biases)
