"""The synthesized BTF: representation o synthesizer, queryable at any uv (the one evaluation path).

``synthesized_btf(model, "hist", scale=8, seed=0).eval(uv, w_view, w_light)`` is the
paper's pipeline end to end: the positional feature plane ``f_U`` of a fitted
representation is synthesized at ``uv * scale`` (stage 2, :mod:`dynbtf.synthesis`)
and decoded with the representation's angular features (stage 3). Every
consumer -- the ``dynbtf synth`` command, the quality report, the preview
renderer and the Mitsuba plugin's tests -- evaluates through this class.

The query object answers from a **compiled material** (:mod:`dynbtf.material`) and never builds one:
``SynthesizedBTF(material, scale)`` takes an opened material (or a ``.dbtfc`` file), and
:func:`dynbtf.synthesized.synthesized_btf` is the application-level step that opens a model's material
from the cache or compiles it first.

Units and conventions
---------------------
* ``uv`` -- the user's surface coordinates, any finite value with ``|uv| * scale``
  below ``2**52`` exemplar repeats (float64 recommended beyond ~1e3; larger values
  raise :class:`~dynbtf.errors.InputError`, see :func:`dynbtf.synthesis.base.check_uv`);
  ``scale`` is the number of exemplar repeats per unit of ``uv`` (``scale = 45``
  makes the unit square show 45 x 45 exemplar repeats, the paper's "45x"). The
  synthesizer sees ``uv * scale`` in exemplar repeats.
* ``w_view, w_light`` -- unit vectors ``(..., 3)`` in the local frame
  (:mod:`dynbtf.conventions`). Directions **below the horizon** (``z < 0``)
  evaluate to **zero** (no reflection from under the surface), not an error.
* Relief -- a representation with a height field (kind ``triple-parallax``) is
  answered at the surface point visible through ``uv``: the camera ray is marched
  through the **synthesized** height channel
  (:meth:`~dynbtf.representations.base.Representation.visible_uv`), which costs
  up to ``relief depth x tan(theta_view) / step`` extra synthesized fetches per query
  (none at normal view).
* ``footprint`` (optional) -- the side of the square of surface a query stands for, in ``uv``
  units (a pixel's footprint): the answer approximates the BTF averaged over it (mip pyramid of
  the synthesized plane, per-level inverse tables and the compiled material's per-level decoders;
  :mod:`dynbtf.synthesis.mip`, :mod:`dynbtf.material.footprint_decoders`). ``None``: the point query.
* Output -- linear RGB ``(..., 3)`` float32, excluding ``cos(theta_light)``
  (``pi f_r``); NumPy in, NumPy out; torch in, torch out.

Speed (fast path, CPU, Triple-Plane-like models)
-------------------------------------------------
Queries run in chunks of ``chunk_size`` (bounded memory for any number of
queries), spread over ``workers`` Python threads that each run numba and torch
single-threaded (no hand-over between two OpenMP pools). Per chunk: the fused
numba kernel synthesizes the decorrelated latent features (lattice + hash +
three fetches + blend + inverse LUT, blocks of queries whose texel reads are
prefetched); the PCA un-projection is folded into the decoder's first-layer
positional weights, applied by one BLAS matmul; the angular features and their
first-layer product come from a second numba kernel, vectorized across queries,
that reads angular planes pre-multiplied by their layer-1 weights and applies
the LeakyReLU (:mod:`dynbtf.decoder.fast_decode`); layers 2.. run in torch on blocks of
16384 rows in ``precision`` (``"bf16"`` pays on CPUs with bf16 matrix
units and is emulated, i.e. much slower, elsewhere; it differs from float32 by
< 0.01, bounded in the tests). Representations without a split first layer are
decoded with their own ``decode``. Measured numbers: ``docs/synthesis.md``.

Compiled materials
------------------
Everything a query reads besides the model -- the method's tables, the pyramid, the folded first
layer, the per-level decoders and the mean appearance -- comes from the compiled material it is
given. Footprint queries decode each pyramid level with the material's per-level decoders where it has
them (compiled with footprints), else every level with the point decoder (a warning says so once).

Devices
-------
Everything runs where the model is (``device=`` moves it: ``"auto"`` picks CUDA when
present, :func:`dynbtf.device.resolve_device`). The numba kernels above are the CPU's;
on CUDA the synthesizers use their torch paths and the decoder its torch layers.
"""

from __future__ import annotations

import contextlib
import os
import warnings

from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch

from .conventions import check_directions, spherical_to_direction, turn_about_normal
from .decoder.folded import DecodePath, FoldedDecoder
from .errors import InputError, positive_number
from .synthesis.base import check_footprint, check_uv
from .material.format import CompiledMaterial, is_compiled_material, load_compiled

__all__ = ["SynthesizedBTF", "PRECISIONS", "footprint_width", "flat_image", "same_device"]

#: Accepted ``precision`` values: dtype of decoder layers 2.. on the fast path.
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16}
_POOLS: dict[int, ThreadPoolExecutor] = {}


def footprint_width(duv_dx, duv_dy):
    """Isotropic footprint (side of a square, uv units) of a pixel from its uv derivatives ``(..., 2)`` each.

    The **longer** of the two screen-space derivative vectors (OpenGL's isotropic level of detail):
    no texel the pixel covers is left out, at the price of some blur across the view at grazing
    angles (on the grazing plane of ``benchmarks/bench_filtering.py`` FLIP 0.030 against the 256-spp
    reference, 0.032 with the geometric mean of both axes, 0.037 with the shorter one). Returns
    ``(...)`` float64 NumPy or torch, as the input.
    """
    if isinstance(duv_dx, torch.Tensor):
        return torch.maximum(torch.linalg.vector_norm(duv_dx, dim=-1), torch.linalg.vector_norm(duv_dy, dim=-1))
    return np.maximum(np.linalg.norm(np.asarray(duv_dx, dtype=np.float64), axis=-1),
                      np.linalg.norm(np.asarray(duv_dy, dtype=np.float64), axis=-1))


def _eval_pool(workers: int) -> ThreadPoolExecutor:
    """The process-wide pool of ``workers`` evaluation threads."""
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="dynbtf-eval")
    return _POOLS[workers]


@contextlib.contextmanager
def _numba_threads(count: int | None):
    """numba kernels called from this thread use ``count`` threads inside the block (None: as they are)."""
    if count is None:
        yield
        return
    import numba

    previous = numba.get_num_threads()
    numba.set_num_threads(count)
    try:
        yield
    finally:
        numba.set_num_threads(previous)


def _single_numba_thread(fn, *args):
    """``fn(*args)`` with numba kernels on one thread (numba's thread count is per calling thread)."""
    import numba

    numba.set_num_threads(1)
    return fn(*args)


def same_device(a: torch.device, b: torch.device) -> bool:
    """Whether two devices are the same (``cuda`` without an index matches any ``cuda:N``)."""
    return a.type == b.type and (a.index is None or b.index is None or a.index == b.index)


def _as_tensor(x, name: str, last: int) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        try:
            x = torch.from_numpy(np.array(x, dtype=np.float64))  # a writable copy (inputs may be broadcast views)
        except (TypeError, ValueError) as e:
            raise InputError(f"{name}: expected a float array of shape (..., {last}) ({e})") from None
    if x.ndim == 0 or x.shape[-1] != last:
        raise InputError(f"{name}: expected shape (..., {last}), got {tuple(x.shape)}")
    return x


def _check_directions(w, name: str, batch) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit directions ``(N, 3)`` (rows below the horizon allowed) and whether each is above it."""
    w = _as_tensor(w, name, 3)
    if tuple(w.shape[:-1]) != tuple(batch):
        raise InputError(f"{name}: batch shape {tuple(w.shape[:-1])} does not match uv's {tuple(batch)}")
    flat = w.reshape(-1, 3)
    valid = False
    if flat.device.type == "cpu" and flat.dtype in (torch.float32, torch.float64):
        from .decoder.fast_decode import all_unit_vectors

        valid = all_unit_vectors(flat.numpy())  # one pass; check_directions below words the error
    if not valid:
        try:
            check_directions(w, name, allow_below_horizon=True)
        except ValueError as e:
            raise InputError(str(e)) from None
    return flat, flat[:, 2] >= 0


def _level_runs(levels: np.ndarray) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """The stable order that sorts queries by level (int8: numpy radix-sorts it) and the runs
    ``(start, stop, level)`` of the sorted queries."""
    order = np.argsort(levels.astype(np.int8), kind="stable")
    cuts = np.flatnonzero(np.diff(levels[order])) + 1
    starts, stops = np.concatenate([[0], cuts]), np.concatenate([cuts, [len(levels)]])
    return order, [(int(a), int(b), int(levels[order[a]])) for a, b in zip(starts, stops)]


def _decode_footprints(synthesizer, path: DecodePath, points, wv, wl, texels) -> torch.Tensor:
    """Footprint queries, sorted by the level decoder that answers them: the filtered latent decoded by each
    run's level decoder, and the queries reading the top level alone by the mean appearance (last run)."""
    decoder = path.decoder
    lower, upper = synthesizer.level_of_detail()(texels.cpu().numpy())
    levels = lower + (upper >= 0.5)
    top = len(decoder.levels) - 1
    if decoder.mean is not None:
        levels = np.where((lower == top) & (upper == 0.0), top + 1, levels)
    order, runs = _level_runs(levels)
    perm = torch.from_numpy(order).to(points.device)
    wv, wl = wv[perm.to(wv.device)], wl[perm.to(wl.device)]
    rgb = torch.empty(len(levels), 3, dtype=torch.float32, device=wv.device)
    split = runs[-1][0] if runs[-1][2] == top + 1 else len(levels)
    if split > 0:
        latent = synthesizer.filtered_latent(points[perm[:split]], texels[torch.from_numpy(order[:split])])
        rgb[:split] = path.decode_levels(latent.to(wv.device), wv[:split], wl[:split], [r for r in runs if r[2] <= top])
    if split < len(levels):
        rgb[split:] = path.mean_appearance(wv[split:], wl[split:])
    return torch.empty_like(rgb).index_copy_(0, perm.to(rgb.device), rgb)


CPU_CHUNK = 32768
"""Queries per chunk of :meth:`SynthesizedBTF.eval` on the CPU: each worker thread's piece, its working set near
the cache's size."""
GPU_CHUNK = 1 << 20
"""Queries per chunk on a GPU: a 1080p frame (2,073,600 queries) in two chunks, each holding about 1.5 kB of
intermediates per query (the taps' features, the decoder's hidden layers) in device memory, so that a GPU with a
few gigabytes free runs it."""


class SynthesizedBTF:
    """An infinite, non-repeating BTF: a compiled material queried at any uv.

    Parameters
    ----------
    material : CompiledMaterial or path
        An opened compiled material (:mod:`dynbtf.material`) or a ``.dbtfc`` file. A fitted model is opened or
        compiled first by :func:`dynbtf.synthesized.synthesized_btf`, which then returns this object.
    scale : float, default 1.0
        Exemplar repeats per unit of the user's ``uv`` (positive).
    chunk_size : int, optional
        Queries per chunk (bounds memory). Default: 32,768 on the CPU (cache-sized pieces for the worker
        threads), 1,048,576 on a GPU (a 1080p frame in two launch sequences: small chunks leave the GPU waiting
        on the Python loop and its per-chunk checks).
    workers : int, optional
        Threads of the CPU fast path (default: torch's intra-op thread count), each running numba and
        torch single-threaded while :meth:`eval` runs.
    precision : {"fp32", "bf16"}, default "fp32"
        Dtype of decoder layers 2.. on the fast path.
    device : str or torch.device, optional
        ``"auto"`` (CUDA when present), ``"cpu"``, ``"cuda:0"``, ... (:func:`dynbtf.device.resolve_device`).
        Default: where the material's model is (a file: the CPU); elsewhere a copy of the material is moved
        there. The numba fast paths run on the CPU only.
    level_decoders : bool, default True
        Footprint queries decode each pyramid level with the material's decoder of that level (the decoder is
        nonlinear: decoding filtered features is biased; :mod:`dynbtf.material.footprint_decoders`), where the
        material has them. False: the point decoder for every level.

    Attributes
    ----------
    material : CompiledMaterial
    model : Representation
        The material's model.
    synthesizer : Synthesizer
        Rebuilt from the material's tables.
    seed : int
        The material's synthesis seed.
    relief : bool
        Whether point queries are answered at the visible point of the synthesized height field (True for a model
        with relief; set it False to fetch at ``uv`` instead, e.g. to show what the march changes).

    Examples
    --------
    >>> import torch
    >>> from dynbtf.material import open_or_compile
    >>> from dynbtf.representations.triple_plane import TriplePlane
    >>> material, _ = open_or_compile(TriplePlane(16, 16), "hist", footprints=False)
    >>> btf = SynthesizedBTF(material, scale=8.0)
    >>> w = torch.tensor([[0.0, 0.0, 1.0]] * 2)
    >>> btf.eval(torch.tensor([[0.1, 0.2], [1e6 + 0.1, 0.2]], dtype=torch.float64), w, w).shape
    torch.Size([2, 3])
    """

    def __init__(self, material: CompiledMaterial, scale: float = 1.0, *, chunk_size: int | None = None,
                 precision: str = "fp32", workers: int | None = None, device: str | torch.device | None = None,
                 level_decoders: bool = True) -> None:
        if device is not None:
            from .device import resolve_device

            device = resolve_device(device)
        if isinstance(material, (str, bytes)) or hasattr(material, "__fspath__"):
            path = material
            if os.path.isfile(path) and not is_compiled_material(path):  # else load_compiled names what is wrong
                raise InputError(f"{path}: not a compiled material (a model file?); open or compile its material with "
                                 "dynbtf.synthesized_btf(path, method, ...) or `dynbtf compile`")
            material = load_compiled(path, device=device)
        if not isinstance(material, CompiledMaterial):
            raise InputError(f"material: expected a compiled material (CompiledMaterial or a .dbtfc file), got "
                             f"{type(material).__name__}; dynbtf.synthesized_btf(model, method, ...) opens or "
                             "compiles a fitted model's")
        if device is not None and not same_device(material.model.positional_plane().device, device):
            material = material.to(device)  # a copy: the caller's material stays on its device
        self.scale = positive_number("scale", scale, "number of exemplar repeats per uv unit")
        if precision not in PRECISIONS:
            raise InputError(f"precision: expected one of {sorted(PRECISIONS)}, got {precision!r}")
        if chunk_size is None:
            chunk_size = CPU_CHUNK if material.model.positional_plane().device.type == "cpu" else GPU_CHUNK
        if int(chunk_size) < 1:
            raise InputError(f"chunk_size: expected a positive number of queries, got {chunk_size}")
        if workers is not None and int(workers) < 1:
            raise InputError(f"workers: expected a positive number of threads, got {workers}")
        self.workers = torch.get_num_threads() if workers is None else int(workers)
        model = material.model
        self.chunk_size, self.precision, self.model = int(chunk_size), precision, model.eval()
        self.material = material
        self.synthesizer = material.synthesizer(model.positional_plane().device)
        if self.synthesizer.channels != model.positional_plane().shape[-1]:
            raise InputError(f"synthesizer: synthesizes {self.synthesizer.channels} channels, the model's positional "
                             f"plane has {model.positional_plane().shape[-1]}")
        self.seed = self.synthesizer.seed
        from .representations.base import Representation

        # representations with relief answer at the visible point, marched through the synthesized height
        self.relief = type(model).visible_uv is not Representation.visible_uv
        decoder = material.decoder
        self.level_decoders = bool(level_decoders) and decoder is not None and len(decoder.levels) > 1
        # footprint queries of a material compiled without footprint decoders: the point decoder, said once
        self._warn_point_decoder = bool(level_decoders) and decoder is not None and not self.level_decoders
        self.decode_path = self._decode_path()
        self._latent_channels: int | None = None

    def _decode_path(self) -> DecodePath | None:
        if self.material.decoder is None:
            return None
        fast = self.model.fast_decoder()
        planes = fast.angular_planes if self.device.type == "cpu" else None
        return DecodePath(self.material.decoder, fast.angular_features, PRECISIONS[self.precision], planes)

    def footprint_decoder(self) -> FoldedDecoder:
        """The material's folded decoder: its per-level decoders and mean appearance where it was compiled with
        footprints (:func:`dynbtf.synthesized.synthesized_btf` with ``footprints=True``, ``dynbtf compile``)."""
        if self.material.decoder is None:
            raise InputError("this material's representation has no foldable decoder (it decodes with its own)")
        return self.material.decoder

    @property
    def device(self) -> torch.device:
        return self.synthesizer.device

    def features(self, uv) -> torch.Tensor:
        """Synthesized positional features ``(..., C)`` float32 at the user's ``uv (..., 2)``."""
        uv = check_uv(uv, scale=self.scale)
        c = self.synthesizer.channels
        if not uv.numel():
            return torch.zeros(*uv.shape[:-1], c, device=self.device)
        latent = self.latent(uv)
        return self.synthesizer.features_from_latent(latent.reshape(-1, latent.shape[-1])).reshape(*uv.shape[:-1], c)

    def latent(self, uv) -> torch.Tensor:
        """Synthesized latent values ``(..., C_latent)`` float32 at the user's ``uv (..., 2)``: what the decoder reads
        (the synthesizer's :meth:`~dynbtf.synthesis.base.Synthesizer.output_map` is folded into it;
        ``self.synthesizer.features_from_latent`` gives :meth:`features`). :meth:`eval` takes them back as
        ``latent``, so a caller that needs both (:class:`dynbtf.layered.LayeredBTF`) synthesizes once."""
        uv = check_uv(uv, scale=self.scale)
        flat = uv.reshape(-1, 2).to(torch.float64)
        out = [self.synthesizer.latent(chunk.to(self.device) * self.scale).to(self.device)
               for chunk in flat.split(self.chunk_size)]
        latent = torch.cat(out) if out else self.synthesizer.latent(flat[:0].to(self.device) * self.scale)
        return latent.reshape(*uv.shape[:-1], latent.shape[-1])

    @property
    def takes_latent(self) -> bool:
        """Whether :meth:`eval` takes ``latent``: the point query of a model without relief (a relief model reads at
        the visible point, not at ``uv``) decoded by the compiled material's decoder."""
        return not self.relief and self.decode_path is not None

    def texels_per_uv(self) -> float:
        """Texels of the exemplar per unit of the user's ``uv`` (``scale`` x the exemplar's side; the geometric
        mean of both sides for a non-square exemplar): converts a footprint to texels."""
        h, w = self.synthesizer.exemplar.shape[:2]
        return self.scale * float(np.sqrt(h * w))

    def nearest_level(self, texels: torch.Tensor) -> np.ndarray:
        """Pyramid level ``(N,)`` int whose texel width is nearest (in log scale) to each footprint (texels)."""
        lower, upper = self.synthesizer.level_of_detail()(texels.cpu().numpy())
        return (lower + (upper >= 0.5)).astype(np.int64)

    def mean_appearance(self, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """The material's mean appearance ``(N, 3)`` float32 at unit directions ``(N, 3)``: what a footprint that
        reads only the top pyramid level answers (requires a foldable decoder and a multi-level pyramid)."""
        if self.footprint_decoder().mean is None:
            raise InputError("mean_appearance: this material has no mean appearance; compile it with footprints "
                             "(dynbtf.synthesized_btf(..., footprints=True), dynbtf compile)")
        with torch.no_grad():
            return self.decode_path.mean_appearance(w_view, w_light)

    def _decode_chunk(self, uv, wv, wl, footprint=None, latent=None) -> torch.Tensor:
        points = uv * self.scale  # exemplar repeats
        if self.relief:  # fetch at the visible point of the synthesized height field
            points = self.model.visible_uv(points, wv, self.synthesizer)
        texels = None if footprint is None else footprint * self.texels_per_uv()
        frame = self.synthesizer.frame_rotation(points)  # turned samples: the directions into their frame
        if frame is not None:
            cos_a, sin_a = frame.to(wv.device).unbind(-1)
            wv, wl = turn_about_normal(wv, cos_a, sin_a), turn_about_normal(wl, cos_a, sin_a)
        rgb = self._decoded(points, wv, wl, texels, latent)
        gain = self.synthesizer.variation_gain(points, texels)  # the method's variation controls, if on
        return rgb if gain is None else rgb * gain.to(rgb.device)

    def _decoded(self, points, wv, wl, texels, latent) -> torch.Tensor:
        """The decoded reflectance ``(N, 3)`` at ``points`` (exemplar repeats; ``texels``: footprints in texels)."""
        if latent is not None:
            return self.decode_path.decode(latent.to(self.device), wv, wl)
        path = self.decode_path
        if path is None:
            return self.model.decode(self.synthesizer(points, texels), wv, wl).float()
        if texels is not None and self.level_decoders:
            return _decode_footprints(self.synthesizer, path, points, wv, wl, texels)
        latent = self.synthesizer.latent(points) if texels is None else self.synthesizer.filtered_latent(points, texels)
        return path.decode(latent.to(self.device), wv, wl)

    def eval(self, uv, w_view, w_light, footprint=None, *, latent=None):
        """BTF value (linear RGB ``(..., 3)`` float32, excluding cos(theta_light)).

        ``uv (..., 2)``: any finite value with ``|uv| * scale < 2**52``; ``w_view, w_light (..., 3)``: unit
        directions, same batch shape (rows with either below the horizon return zero); ``footprint``
        (float or ``(...)``, optional): the side of the square of surface each query stands for, in
        ``uv`` units (:func:`footprint_width`): the answer approximates the BTF averaged over it (up to
        one texel it is the point query; beyond the exemplar the mean appearance). ``latent``
        (``(..., C_latent)``, optional): :meth:`latent` at these ``uv``, already synthesized: the point query
        decodes it instead of synthesizing again (only where :attr:`takes_latent`). Returns NumPy for
        NumPy ``uv``, else a tensor on the model's device.
        """
        as_numpy = not isinstance(uv, torch.Tensor)
        uv = check_uv(uv, scale=self.scale)
        batch = uv.shape[:-1]
        wv, up_v = _check_directions(w_view, "w_view", batch)
        wl, up_l = _check_directions(w_light, "w_light", batch)
        flat = uv.reshape(-1, 2).to(torch.float64)
        fp = None if footprint is None else check_footprint(footprint, batch).reshape(-1)
        if fp is not None and self.synthesizer.level_of_detail() is None:
            raise InputError(f"footprint: synthesis method {self.synthesizer.name!r} has no footprint query; "
                             "evaluate points (footprint=None; unfiltered images)")
        if latent is not None:
            latent = self._check_latent(latent, batch, footprint)
        if fp is not None and self._warn_point_decoder:
            self._warn_point_decoder = False
            warnings.warn("footprint queries of a material compiled without footprint decoders: every pyramid level is "
                          "decoded with the point decoder (biased for wide footprints); compile it with footprints "
                          "(dynbtf.synthesized_btf(..., footprints=True), dynbtf compile)", stacklevel=2)
        n = flat.shape[0]
        out = torch.empty(n, 3, dtype=torch.float32, device=self.device)  # every chunk writes its rows
        visible = up_v & up_l
        dtype = self.model.positional_plane().dtype

        def run(sl: slice) -> None:
            vis = visible[sl]
            if not bool(vis.any()):
                out[sl] = 0.0
                return
            with torch.no_grad():
                rgb = self._decode_chunk(flat[sl].to(self.device), wv[sl].to(self.device, dtype),
                                         wl[sl].to(self.device, dtype), None if fp is None else fp[sl],
                                         None if latent is None else latent[sl])
            out[sl] = rgb if bool(vis.all()) else torch.where(vis.to(self.device)[:, None], rgb, torch.zeros_like(rgb))

        chunks = [slice(start, min(start + self.chunk_size, n)) for start in range(0, n, self.chunk_size)]
        fused = self.decode_path is not None and self.decode_path.fused
        if self.workers > 1 and len(chunks) > 1 and fused:
            # one chunk per Python thread, each with single-threaded torch and numba: no OpenMP pools handing
            # over between numba kernels and torch matmuls (their spin-waiting made two threads many times slower)
            from .decoder.fused_mlp import single_intra_op_thread

            with single_intra_op_thread():
                list(_eval_pool(self.workers).map(lambda sl: _single_numba_thread(run, sl), chunks))
        else:
            from .decoder.fused_mlp import single_intra_op_thread

            # the fused CPU path on one thread too, as each worker above runs it: a chunk split over threads rounds
            # some rows differently (MKL's and numba's vector loops and their remainders), and the answers must not
            # depend on the number of workers
            with single_intra_op_thread(fused), _numba_threads(1 if fused else None):
                for sl in chunks:
                    run(sl)
        out = out.reshape(*batch, 3)
        return out.cpu().numpy() if as_numpy else out

    __call__ = eval

    def _check_latent(self, latent, batch, footprint) -> torch.Tensor:
        if not self.takes_latent:
            raise InputError("latent: this BTF synthesizes at the visible point of its relief (or has no compiled "
                             "decoder), so it cannot decode latent values given at uv; call eval without latent")
        if footprint is not None:
            raise InputError("latent: given for point queries only; call eval without footprint, or without latent")
        latent = torch.as_tensor(latent)
        if self._latent_channels is None:  # what the synthesizer answers (one query)
            self._latent_channels = int(self.synthesizer.latent(torch.zeros(1, 2, dtype=torch.float64,
                                                                            device=self.device)).shape[-1])
        expected = tuple(batch) + (self._latent_channels,)
        if latent.dtype != torch.float32 or tuple(latent.shape) != expected:
            raise InputError(f"latent: expected float32 values of shape {expected} (SynthesizedBTF.latent at the same "
                             f"uv), got {latent.dtype} {tuple(latent.shape)}")
        return latent.reshape(-1, latent.shape[-1])

    def image(self, view=(0.0, 0.0), light=(0.0, 0.0), uv_rect=(0.0, 0.0, 1.0, 1.0), resolution=512,
              spp: int = 1, filtered: bool = False) -> np.ndarray:
        """A flat sample under one directional (view, light) pair: :func:`flat_image` of this BTF."""
        return flat_image(self, view, light, uv_rect, resolution, spp, filtered)

    def tiled(self) -> "SynthesizedBTF":
        """The exemplar itself, periodic, through the same evaluation path and precision at scale 1 (what synthesis
        is measured against): :meth:`~dynbtf.material.CompiledMaterial.exemplar` of the material."""
        return SynthesizedBTF(self.material.exemplar(), 1.0, precision=self.precision, workers=self.workers)

    def describe(self) -> dict[str, Any]:
        """Method, seed, scale and parameters (JSON-serializable)."""
        return {"method": self.synthesizer.name, "seed": self.seed, "scale": self.scale, "precision": self.precision,
                "dynamic": self.synthesizer.dynamic, "parameters": self.synthesizer.parameters(),
                "synthesizer_storage_bytes": self.synthesizer.storage_bytes()}


#: Queries per evaluation of :func:`flat_image` (sub-pixel samples of many pixels are evaluated together).
IMAGE_BATCH = 1 << 20


def _direction(name: str, pair) -> np.ndarray:
    try:
        theta, phi = (float(x) for x in pair)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected (theta, phi) in degrees, got {pair!r}") from None
    if not (np.isfinite(theta) and np.isfinite(phi)):
        raise InputError(f"{name}: (theta, phi) must be finite, got {pair!r}")
    return spherical_to_direction(np.array(theta), np.array(phi))


def flat_image(btf: SynthesizedBTF, view=(0.0, 0.0), light=(0.0, 0.0), uv_rect=(0.0, 0.0, 1.0, 1.0),
               resolution=512, spp: int = 1, filtered: bool = False) -> np.ndarray:
    """A flat sample of ``btf`` under one directional (view, light) pair, like the paper's Figs. 5-6.

    Parameters
    ----------
    view, light : (theta, phi) in degrees
        Directions of the camera and of the light (the same for every pixel).
    uv_rect : (u0, v0, u1, v1)
        The user-uv rectangle shown (anywhere, with ``|u|, |v| * scale < 2**52``).
    resolution : int or (height, width)
        Pixel ``[i, j]`` shows ``uv = (u0 + (j + .5) (u1 - u0) / W, v0 + (i + .5) (v1 - v0) / H)``.
    spp : int, default 1
        The mean of ``spp x spp`` samples on a regular sub-pixel grid (a box filter), evaluated in batches of
        up to :data:`IMAGE_BATCH` queries.
    filtered : bool, default False
        Footprint queries: each sample answers for its share of the pixel (the longer side / ``spp``).

    Returns
    -------
    float32 ``(height, width, 3)``: BTF values (linear RGB, excluding cos(theta_light)).
    """
    try:
        height, width = (int(resolution), int(resolution)) if np.isscalar(resolution) else map(int, resolution)
    except (TypeError, ValueError):
        raise InputError(f"resolution: expected an int or (height, width), got {resolution!r}") from None
    if height < 1 or width < 1:
        raise InputError(f"resolution: expected positive sizes, got {resolution!r}")
    try:
        u0, v0, u1, v1 = (float(x) for x in uv_rect)
    except (TypeError, ValueError):
        raise InputError(f"uv_rect: expected (u0, v0, u1, v1), got {uv_rect!r}") from None
    check_uv(np.array([[u0, v0], [u1, v1]]), "uv_rect", scale=btf.scale)
    wv, wl = _direction("view", view), _direction("light", light)
    if int(spp) < 1:
        raise InputError(f"spp: expected a positive number of samples per pixel axis, got {spp}")
    spp = int(spp)
    footprint = max(abs(u1 - u0) / width, abs(v1 - v0) / height) / spp if filtered else None
    columns, rows = np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)
    total = np.zeros((height, width, 3), dtype=np.float64)
    per_batch = max(1, IMAGE_BATCH // (height * width))
    for start in range(0, spp * spp, per_batch):
        sy, sx = np.divmod(np.arange(start, min(spp * spp, start + per_batch)), spp)
        u = u0 + (columns[None, None, :] + ((sx + 0.5) / spp)[:, None, None]) * ((u1 - u0) / width)
        v = v0 + (rows[None, :, None] + ((sy + 0.5) / spp)[:, None, None]) * ((v1 - v0) / height)
        uv = np.stack(np.broadcast_arrays(u, v), axis=-1)
        shape = uv.shape[:-1] + (3,)
        total += btf.eval(uv, np.broadcast_to(wv, shape), np.broadcast_to(wl, shape), footprint=footprint).sum(0)
    return (total / (spp * spp)).astype(np.float32)
