"""The synthesized BTF: representation o synthesizer, queryable at any uv (the one evaluation path).

``SynthesizedBTF(model, "hist", scale=8, seed=0).eval(uv, w_view, w_light)`` is the
paper's pipeline end to end: the positional feature plane ``f_U`` of a fitted
representation is synthesized at ``uv * scale`` (stage 2, :mod:`dynbtf.synthesis`)
and decoded with the representation's angular features (stage 3). Every
consumer -- the ``dynbtf synth`` command, the quality report, the preview
renderer and the Mitsuba plugin's tests -- evaluates through this class.

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
  the synthesized plane, per-level inverse tables and per-level decoders fitted on first use;
  :mod:`dynbtf.synthesis.mip`, "Footprint queries" in ``docs/synthesis.md``). ``None``: the point query.
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
16384 rows in ``precision`` (``"bf16"`` is ~2x faster on CPUs with bf16 matrix
units and emulated, i.e. much slower, elsewhere; it differs from float32 by
< 0.01, bounded in the tests). Representations without a split first layer are
decoded with their own ``decode``. Measured numbers: ``docs/synthesis.md``.

Devices
-------
Everything runs where the model is (``device=`` moves it: ``"auto"`` picks CUDA when
present, :func:`dynbtf.device.resolve_device`). The numba kernels above are the CPU's;
on CUDA the synthesizers use their torch paths and the decoder its torch layers.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from .conventions import check_directions, spherical_to_direction
from .errors import InputError, positive_number
from .synthesis.base import Synthesizer, check_footprint, check_uv, make_synthesizer

__all__ = ["SynthesizedBTF", "PRECISIONS", "footprint_width"]

#: Accepted ``precision`` values: dtype of decoder layers 2.. on the fast path.
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16}
#: (view, light) pairs, (theta, phi) in degrees, under which ``struct`` and ``auto`` see the exemplar's
#: structure (normal view and light, a slanted pair, a grazing-ish pair from other azimuths).
APPEARANCE_PAIRS = (((0.0, 0.0), (0.0, 0.0)), ((30.0, 0.0), (45.0, 180.0)), ((60.0, 90.0), (30.0, 270.0)))
_POOLS: dict[int, ThreadPoolExecutor] = {}


def footprint_width(duv_dx, duv_dy):
    """Isotropic footprint (side of a square, uv units) of a pixel from its uv derivatives ``(..., 2)`` each.

    The **longer** of the two screen-space derivative vectors (OpenGL's isotropic level of detail):
    no texel the pixel covers is left out, at the price of some blur across the view at grazing
    angles. On the grazing plane of ``benchmarks/bench_filtering.py`` (anisotropy up to ~50) FLIP
    against the 256-spp reference (per-level decoders of a smaller fit) was 0.030 with the longer
    axis, 0.032 with the geometric mean of both, 0.037 with the shorter one; 1.25-1.8x the geometric
    mean gave 0.030 too. Returns ``(...)`` float64 NumPy or torch, as the input.
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


def _single_numba_thread(fn, *args):
    """``fn(*args)`` with numba kernels on one thread (numba's thread count is per calling thread)."""
    import numba

    numba.set_num_threads(1)
    return fn(*args)


#: The per-level decoders' fit (:meth:`SynthesizedBTF.level_decoder_parameters`): positions and (view, light)
#: pairs per level, jittered point queries averaged per footprint (a grid x grid), Adam steps, minibatch
#: rows and rate, seed.
LEVEL_FIT_QUERIES = 65536
LEVEL_FIT_GRID = 8
LEVEL_FIT_STEPS = 1000
LEVEL_FIT_BATCH = 2048
LEVEL_FIT_LR = 3e-3
LEVEL_FIT_SEED = 0

#: The mean appearance of footprints that read only the pyramid's 1 x 1 top level
#: (:meth:`SynthesizedBTF.level_decoder_parameters`): quadrature nodes, random synthesized positions whose
#: mean is the fit's target (the same positions for every pair), (view, light) pairs, Adam steps.
MEAN_NODES = 3
MEAN_FIT_POSITIONS = 512
MEAN_FIT_PAIRS = 65536
MEAN_FIT_STEPS = 2000

#: Fitted per-level decoders by (model contents, method, seed, parameters, precision, device): SynthesizedBTFs
#: of one model (the same parameters, e.g. loaded twice from one file), method and seed fit once per process.
#: Other scales share the fit (it is in exemplar repeats); the seed is part of the key because the fit's
#: targets are that seed's synthesized BTF, so results never depend on which seed was evaluated first.
_LEVEL_DECODERS: dict[tuple, list[dict[str, Any]]] = {}


def _fingerprint(model) -> str:
    """SHA-1 of a model's parameters and buffers (names, shapes, dtypes, bytes): equal for equal models."""
    import hashlib

    digest = hashlib.sha1()
    for name, tensor in sorted(model.state_dict().items()):
        data = tensor.detach().cpu().contiguous()
        digest.update(f"{name}:{tuple(data.shape)}:{data.dtype}".encode())
        digest.update(data.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


#: Rows per call of decoder layers 2..: torch's small (32-wide) linear layers ran ~3x faster per row
#: at <= 16384 rows than at 32768+ (activations stay in cache; measured on a 2-core EPYC).
_MLP_ROWS = 16384


def _hidden(x: torch.Tensor, layers, slope: float) -> torch.Tensor:
    """Linear layers ``[(weight, bias), ...]`` each followed by LeakyReLU on ``x (N, in)`` (none: ``x``)."""
    for weight, bias in layers:
        x = F.leaky_relu(F.linear(x, weight, bias), slope)
    return x


def _mlp(x: torch.Tensor, layers, slope: float) -> torch.Tensor:
    """Linear layers ``[(weight, bias), ...]`` with LeakyReLU between them on ``x (N, in)`` -> float32."""
    weight, bias = layers[-1]
    return F.linear(_hidden(x, layers[:-1], slope), weight, bias).float()


def _random_direction_pairs(rng: np.random.Generator, n: int) -> np.ndarray:
    """``(2, n, 3)`` float64 (view, light) unit directions of the per-level fits: cosines uniform in [0.01, 1]
    (grazing views included: where filtering matters most), azimuths uniform."""
    cos_t = rng.uniform(0.01, 1.0, (2, n))
    phi = rng.uniform(0.0, 2 * np.pi, (2, n))
    sin_t = np.sqrt(1.0 - cos_t ** 2)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def _adam_steps(loss_of, optimizer, schedule, batches) -> None:
    """One optimizer and schedule step of ``loss_of(rows)`` per row-index batch, on one torch thread: the small
    layers' backward passes ran ~10x slower on two threads of a loaded 2-core machine (OpenMP spin-waiting), as
    the evaluation does (:func:`dynbtf.decoder.fused_mlp.single_intra_op_thread`)."""
    from .decoder.fused_mlp import single_intra_op_thread

    with single_intra_op_thread():
        for rows in batches:
            loss = loss_of(rows)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            schedule.step()


def decoded_appearance(model, plane: torch.Tensor | None = None, chunk_size: int = 32768) -> torch.Tensor:
    """A model's positional plane decoded under :data:`APPEARANCE_PAIRS`: ``(H, W, 3 * pairs)`` float32.

    What ``struct`` and ``auto`` see of a fitted model (their ``guide``): a feature plane spreads its
    variance over many channels, fine detail included, while its decoded colours show the material's
    structure. ``plane`` defaults to ``model.positional_plane()``.
    """
    with torch.no_grad():
        plane = model.positional_plane().detach() if plane is None else plane
        h, w, _ = plane.shape
        rows = plane.reshape(h * w, -1)
        images = []
        for view, light in APPEARANCE_PAIRS:
            wv = spherical_to_direction(np.array(view[0]), np.array(view[1]))
            wl = spherical_to_direction(np.array(light[0]), np.array(light[1]))
            wv = torch.as_tensor(wv, dtype=plane.dtype, device=plane.device).expand(h * w, 3)
            wl = torch.as_tensor(wl, dtype=plane.dtype, device=plane.device).expand(h * w, 3)
            images.append(torch.cat([model.decode(chunk, a, b) for chunk, a, b in
                                     zip(rows.split(chunk_size), wv.split(chunk_size), wl.split(chunk_size))]))
        return torch.cat(images, -1).float().reshape(h, w, -1)


def auto_method(model):
    """What ``synthesizer="auto"`` chooses for a fitted ``model``: a :class:`~dynbtf.synthesis.auto.MethodChoice`
    measured on its :func:`decoded_appearance` (the same choice :class:`SynthesizedBTF` makes)."""
    from .synthesis.auto import choose_method

    return choose_method(model.positional_plane().detach(), decoded_appearance(model))


def _same_device(a: torch.device, b: torch.device) -> bool:
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


class SynthesizedBTF:
    """An infinite, non-repeating BTF: a fitted representation with a synthesized positional plane.

    Parameters
    ----------
    model : Representation or str or Path
        A fitted representation with a positional plane (or a model file path,
        loaded with :func:`dynbtf.representations.model_file.load_model`).
    synthesizer : str or Synthesizer, default "auto"
        A method name (``tile``, ``linear``, ``hist``, ``hex``, ``quilt``, ``struct``) built on
        the model's positional plane with ``seed`` and ``**params``, or ``auto``: ``struct`` for
        structured materials, ``hist`` otherwise, chosen from the model's decoded appearance
        (:func:`dynbtf.synthesis.auto.choose_method`; ``self.synthesizer.choice.line`` says why),
        or a ready synthesizer (then ``seed`` and ``params`` must be left out).
    scale : float, default 1.0
        Exemplar repeats per unit of the user's ``uv`` (positive).
    seed : int, default 0
        Synthesis seed.
    chunk_size : int, default 32768
        Queries per chunk (bounds memory).
    workers : int, optional
        Threads of the CPU fast path (default: torch's intra-op thread count). Chunks are spread
        over a pool of this many Python threads, each running numba and torch single-threaded
        (torch's intra-op thread count is 1 while :meth:`eval` runs, restored afterwards).
    precision : {"fp32", "bf16"}, default "fp32"
        Dtype of decoder layers 2.. on the fast path.
    device : str or torch.device, optional
        Where the model, the synthesizer and the outputs live: ``"auto"`` (CUDA when present),
        ``"cpu"``, ``"cuda:0"``, ... (:func:`dynbtf.device.resolve_device`; CUDA requested
        but absent raises :class:`InputError`). Default: where ``model`` is (a model file:
        the CPU). A representation on another device is copied there; the caller's stays
        where it is. The numba fast paths run on the CPU only: elsewhere all is torch.
    level_decoders : bool, default True
        Footprint queries decode each pyramid level with its own decoder (layers 2.. and layer 1's
        positional weights),
        fitted on first use so that decoding a level's filtered features matches the mean of
        the point queries over its footprint (:meth:`level_decoder_parameters`; the decoder is
        nonlinear: the plain decoder on filtered features is biased). Models without a
        foldable decoder decode every level with their own decoder.
    **params
        Method parameters (see each synthesizer). For ``hex`` the default
        luminance is the model's decoded brightness at normal view and light.

    Examples
    --------
    >>> import torch
    >>> from dynbtf.representations.triple_plane import TriplePlane
    >>> btf = SynthesizedBTF(TriplePlane(16, 16), "hist", scale=8.0)
    >>> w = torch.tensor([[0.0, 0.0, 1.0]] * 2)
    >>> btf.eval(torch.tensor([[0.1, 0.2], [1e6 + 0.1, 0.2]], dtype=torch.float64), w, w).shape
    torch.Size([2, 3])
    """

    def __init__(self, model, synthesizer: str | Synthesizer = "auto", scale: float = 1.0, seed: int = 0, *,
                 chunk_size: int = 32768, precision: str = "fp32", workers: int | None = None,
                 device: str | torch.device | None = None, level_decoders: bool = True, **params) -> None:
        if device is not None:
            from .device import resolve_device

            device = resolve_device(device)
        if isinstance(model, (str, bytes)) or hasattr(model, "__fspath__"):
            from .representations.model_file import load_model

            model, _ = load_model(model, device=device)
        if not hasattr(model, "positional_plane") or not hasattr(model, "decode"):
            raise InputError(f"model: expected a Representation with a positional plane, got {type(model).__name__}")
        if device is not None and not _same_device(model.positional_plane().device, device):
            import copy

            model = copy.deepcopy(model).to(device)  # the caller's model stays on its device
        scale = positive_number("scale", scale, "number of exemplar repeats per uv unit")
        if precision not in PRECISIONS:
            raise InputError(f"precision: expected one of {sorted(PRECISIONS)}, got {precision!r}")
        if int(chunk_size) < 1:
            raise InputError(f"chunk_size: expected a positive number of queries, got {chunk_size}")
        if workers is not None and int(workers) < 1:
            raise InputError(f"workers: expected a positive number of threads, got {workers}")
        self.workers = torch.get_num_threads() if workers is None else int(workers)
        self.model = model.eval()
        self.scale = scale
        self.chunk_size = int(chunk_size)
        self.precision = precision
        with torch.no_grad():
            plane = model.positional_plane().detach()
            if isinstance(synthesizer, Synthesizer):
                if params:
                    raise InputError(f"parameters {sorted(params)} given with a ready synthesizer; "
                                     "pass them to the synthesizer instead")
                if not _same_device(synthesizer.device, plane.device):
                    raise InputError(f"synthesizer: its exemplar is on {synthesizer.device}, the model on "
                                     f"{plane.device}; build it on the model's device")
                self.synthesizer = synthesizer
            elif isinstance(synthesizer, str):
                if synthesizer == "hex" and "luminance" not in params:
                    params["luminance"] = self._decoded_luminance(plane)
                if synthesizer in ("auto", "struct") and "guide" not in params:
                    params["guide"] = self._decoded_appearance(plane)
                self.synthesizer = make_synthesizer(synthesizer, plane, seed=seed, **params)
            else:
                raise InputError(f"synthesizer: expected a method name or a Synthesizer, got {type(synthesizer).__name__}")
        if self.synthesizer.channels != plane.shape[-1]:
            raise InputError(f"synthesizer: synthesizes {self.synthesizer.channels} channels, the model's positional "
                             f"plane has {plane.shape[-1]}")
        self.seed = self.synthesizer.seed
        self._fold = self._fold_first_layer()
        from .representations.base import Representation

        # representations with relief answer at the visible point, marched through the synthesized height
        self._relief = type(model).visible_uv is not Representation.visible_uv
        self._level_layers: list[dict[str, Any]] | None = None
        self.level_decoders = bool(level_decoders) and self._fold is not None

    # ------------------------------------------------------------ set-up
    def _decoded_luminance(self, plane: torch.Tensor) -> torch.Tensor:
        """Rec. 709 luminance of the exemplar decoded at normal view and light, ``(H, W)``."""
        h, w, _ = plane.shape
        up = torch.zeros(h * w, 3, dtype=plane.dtype, device=plane.device)
        up[:, 2] = 1.0
        rgb = torch.cat([self.model.decode(chunk, n, n) for chunk, n in
                         zip(plane.reshape(h * w, -1).split(self.chunk_size), up.split(self.chunk_size))])
        return (rgb.float() @ torch.tensor([0.2126, 0.7152, 0.0722], device=rgb.device)).reshape(h, w)

    def _decoded_appearance(self, plane: torch.Tensor) -> torch.Tensor:
        return decoded_appearance(self.model, plane, self.chunk_size)

    def _fold_first_layer(self) -> dict[str, Any] | None:
        """Layer-1 positional weights with the synthesizer's output map folded in (fast path), or None."""
        fast = self.model.fast_decoder()
        if fast is None:
            return None
        decoder = fast.decoder
        with torch.no_grad():
            w_pos = decoder.first.weight[:, : decoder.positional_channels].detach().float()  # (hidden, C)
            matrix, offset = self.synthesizer.output_map()
            c = w_pos.shape[1]
            matrix = torch.eye(c, device=w_pos.device) if matrix is None else matrix.to(w_pos.device).float()
            offset = torch.zeros(c, device=w_pos.device) if offset is None else offset.to(w_pos.device).float()
            dtype = PRECISIONS[self.precision]
            rest = [(layer.weight.detach().to(dtype), layer.bias.detach().to(dtype)) for layer in decoder.rest]
            fold = {"weight": (matrix @ w_pos.T).contiguous(), "bias": offset @ w_pos.T, "rest": rest,
                    "first_bias": decoder.first.bias.detach().float(),
                    "slope": float(decoder.negative_slope), "dtype": dtype, "planes": None, "fast": fast}
            if fast.angular_planes is not None and self.device.type == "cpu":
                from .decoder.fast_decode import fold_angular_planes

                fold["planes"] = fold_angular_planes(*fast.angular_planes,
                                                     decoder.first.weight[:, decoder.positional_channels:])
                fold["numpy"] = (np.ascontiguousarray(fold["weight"].cpu().numpy()),
                                 np.ascontiguousarray((fold["bias"] + decoder.first.bias.detach().float()).cpu().numpy()))
            return fold

    # ------------------------------------------------------------ queries
    @property
    def device(self) -> torch.device:
        return self.synthesizer.device

    def features(self, uv) -> torch.Tensor:
        """Synthesized positional features ``(..., C)`` float32 at the user's ``uv (..., 2)``."""
        uv = check_uv(uv, scale=self.scale)
        flat = uv.reshape(-1, 2).to(torch.float64)
        out = [self.synthesizer(chunk.to(self.device) * self.scale) for chunk in flat.split(self.chunk_size)]
        c = self.synthesizer.channels
        result = torch.cat(out) if out else torch.zeros(0, c, device=self.device)
        return result.reshape(*uv.shape[:-1], c)

    def _check_directions(self, w, name: str, batch) -> tuple[torch.Tensor, torch.Tensor]:
        w = _as_tensor(w, name, 3)
        if tuple(w.shape[:-1]) != tuple(batch):
            raise InputError(f"{name}: batch shape {tuple(w.shape[:-1])} does not match uv's {tuple(batch)}")
        flat = w.reshape(-1, 3)
        if flat.device.type == "cpu" and flat.dtype in (torch.float32, torch.float64):
            from .decoder.fast_decode import all_unit_vectors

            valid = all_unit_vectors(flat.numpy())  # one pass; check_directions below words the error
        else:
            valid = False
        if not valid:
            try:
                check_directions(w, name, allow_below_horizon=True)
            except ValueError as e:
                raise InputError(str(e)) from None
        return flat, flat[:, 2] >= 0

    def texels_per_uv(self) -> float:
        """Texels of the exemplar per unit of the user's ``uv`` (``scale`` x the exemplar's side;
        the geometric mean of both sides for a non-square exemplar): converts a footprint to texels."""
        h, w = self.synthesizer.exemplar.shape[:2]
        return self.scale * float(np.sqrt(h * w))

    def _decode_chunk(self, uv: torch.Tensor, wv: torch.Tensor, wl: torch.Tensor,
                      footprint: torch.Tensor | None = None) -> torch.Tensor:
        fold = self._fold
        points = uv * self.scale  # exemplar repeats
        if self._relief:  # fetch at the visible point of the synthesized height field
            points = self.model.visible_uv(points, wv, self.synthesizer)
        texels = None if footprint is None else footprint * self.texels_per_uv()
        if texels is not None and fold is not None and self.level_decoders:
            # queries sorted by their level decoder: every per-level step below works on contiguous runs
            params = self.level_decoder_parameters()
            lower, upper = self.synthesizer.level_of_detail()(texels.cpu().numpy())
            levels = lower + (upper >= 0.5)
            top = len(params) - 1
            if params[top].get("mean") is not None:  # reading the top level alone: the mean appearance (last run)
                levels = np.where((lower == top) & (upper == 0.0), top + 1, levels)
            order = np.argsort(levels.astype(np.int8), kind="stable")  # int8: numpy radix-sorts it (~5x faster)
            runs = np.flatnonzero(np.diff(levels[order])) + 1
            bounds = [(int(a), int(b), int(levels[order[a]])) for a, b in
                      zip(np.concatenate([[0], runs]), np.concatenate([runs, [len(levels)]]))]
            perm = torch.from_numpy(order).to(points.device)
            wv_sorted, wl_sorted = wv[perm.to(wv.device)], wl[perm.to(wl.device)]
            rgb = torch.empty(len(levels), 3, dtype=torch.float32, device=self.device)
            split = bounds[-1][0] if bounds[-1][2] == top + 1 else len(levels)
            if split > 0:
                rgb[:split] = self._decode_sorted(points[perm[:split]], wv_sorted[:split], wl_sorted[:split],
                                                  texels[torch.from_numpy(order[:split])],
                                                  [b for b in bounds if b[2] <= top])
            if split < len(levels):
                rgb[split:] = self.mean_appearance(wv_sorted[split:], wl_sorted[split:])
            return torch.empty_like(rgb).index_copy_(0, perm.to(rgb.device), rgb)
        if fold is None:
            features = self.synthesizer(points, texels)
            return self.model.decode(features, wv, wl).float()
        latent = (self.synthesizer.latent(points) if texels is None
                  else self.synthesizer.filtered_latent(points, texels)).to(self.device)
        return self._decode_latent(latent, wv, wl)

    def _decode_latent(self, latent: torch.Tensor, wv: torch.Tensor, wl: torch.Tensor,
                       positional: torch.Tensor | None = None, bounds=None) -> torch.Tensor:
        """Decode latents ``(N, C)``: the decoder's layers, or with ``bounds`` (runs ``(start, stop, level)``
        of queries sorted by level) and their layer-1 ``positional`` pre-activation (with layer 1's bias on the fused
        CPU path, without it on the torch path), each run's level decoder."""
        fold = self._fold
        if fold["planes"] is not None:  # fused CPU kernel: angular planes pre-multiplied by layer 1, LeakyReLU
            from .decoder.fast_decode import first_layer_preactivation

            x = torch.from_numpy(first_layer_preactivation(
                latent.numpy(), *fold["numpy"], wv.float().numpy(), wl.float().numpy(), *fold["planes"],
                negative_slope=fold["slope"],
                positional=None if positional is None else positional.numpy()))
        else:
            fast = fold["fast"]
            pre = torch.addmm(fold["bias"], latent, fold["weight"]) if positional is None else positional
            pre += fast.decoder.first_layer_angular(fast.angular_features(wv, wl).float())
            x = F.leaky_relu(pre, fold["slope"])
        x = x.to(fold["dtype"])
        if bounds is not None:
            params = self.level_decoder_parameters()
            out = torch.empty(x.shape[0], 3, dtype=torch.float32, device=x.device)
            for a, b, level in bounds:
                for start in range(a, b, _MLP_ROWS):
                    stop = min(b, start + _MLP_ROWS)
                    out[start:stop] = _mlp(x[start:stop], params[level]["rest"], fold["slope"])
            return out
        return torch.cat([self._decode_rest(block) for block in x.split(_MLP_ROWS)]) if len(x) > _MLP_ROWS \
            else self._decode_rest(x)

    # ------------------------------------------------------------ footprint queries: per-level decoders
    def level_decoder_parameters(self) -> list[dict[str, Any]]:
        """Per-level decoder parameters (fitted once, on the first footprint query), level 0 the decoder's own.

        Entry ``l``: ``weight (C, hidden)`` and ``bias (hidden,)`` of layer 1's positional part (with
        the synthesizer's output map folded in, without the decoder's layer-1 bias) and ``rest``,
        the ``(weight, bias)`` of layers 2.. (float32). Level ``l >= 1`` decodes the footprints whose
        nearest pyramid level is ``l`` (:meth:`nearest_level`) and is fine-tuned from the decoder
        (mean squared error, Adam, seeded; layer 1's angular part kept) so that, on the filtered
        latent of such footprints, it matches the mean of ``LEVEL_FIT_GRID**2`` jittered point
        queries over each footprint, at ``LEVEL_FIT_QUERIES`` random positions and (view, light)
        pairs. Why: the decoder is nonlinear -- decoding mean features is not the mean decoded
        colour (on a fitted leather ~6% darker, and the error varies with the directions;
        ``docs/synthesis.md``).

        Footprints that read only the top level (``1 x 1``: the same latent at every position) answer
        the material's mean appearance, a function of the directions alone. The top entry's ``mean``
        holds it as a quadrature of ``MEAN_NODES`` decodes, :meth:`mean_appearance`: ``nodes
        (MEAN_NODES, hidden)`` (layer 1's positional pre-activation, without layer 1's bias;
        ``nodes_total`` with it), ``weights (MEAN_NODES,)`` (summing to one) and ``rest``, fitted
        (relative squared error) to the mean of the decoder over ``MEAN_FIT_POSITIONS`` synthesized
        positions. ``None`` where the top level is not constant (e.g. a one-level pyramid).
        """
        if self._level_layers is None:
            import json

            key = (_fingerprint(self.model), self.synthesizer.name, self.seed,
                   json.dumps(self.synthesizer.parameters(), sort_keys=True, default=str), self.precision,
                   str(self.device))
            if key not in _LEVEL_DECODERS:
                _LEVEL_DECODERS[key] = self._fit_level_decoders()
            first_bias = self._fold["first_bias"]
            self._level_layers = [{**p, "bias_total": p["bias"] + first_bias} for p in _LEVEL_DECODERS[key]]
            mean = self._level_layers[-1].get("mean")
            if mean is not None:
                self._level_layers[-1]["mean"] = {**mean, "nodes_total": mean["nodes"] + first_bias}
        return self._level_layers

    def nearest_level(self, texels: torch.Tensor) -> np.ndarray:
        """Pyramid level ``(N,)`` int whose texel width is nearest (in log scale) to each footprint (texels)."""
        lower, upper = self.synthesizer.level_of_detail()(texels.cpu().numpy())
        return (lower + (upper >= 0.5)).astype(np.int64)

    def _decode_sorted(self, points: torch.Tensor, wv: torch.Tensor, wl: torch.Tensor, texels: torch.Tensor,
                       bounds) -> torch.Tensor:
        """Footprint queries sorted by level decoder (runs ``bounds``): filtered latent, each run's decoder."""
        params = self.level_decoder_parameters()
        latent = self.synthesizer.filtered_latent(points, texels).to(self.device)
        key = "bias" if self._fold["planes"] is None else "bias_total"  # the fused kernel: with layer 1's bias
        positional = torch.empty(latent.shape[0], params[0]["weight"].shape[1], dtype=torch.float32,
                                 device=latent.device)
        for a, b, level in bounds:
            torch.addmm(params[level][key], latent[a:b], params[level]["weight"], out=positional[a:b])
        return self._decode_latent(latent, wv, wl, positional, bounds)

    def _fit_level_decoders(self) -> list[dict[str, Any]]:
        fold = self._fold
        widths = self.synthesizer.level_of_detail().widths
        fast = fold["fast"]
        decoder = fast.decoder
        dtype = fold["dtype"]
        rng = np.random.default_rng(LEVEL_FIT_SEED)
        n, grid = LEVEL_FIT_QUERIES, LEVEL_FIT_GRID
        density = self.texels_per_uv() / self.scale  # texels per repeat
        rest0 = [(layer.weight.detach().float(), layer.bias.detach().float()) for layer in decoder.rest]
        params = [{"weight": fold["weight"].float(), "bias": fold["bias"].float(),
                   "rest": [(w.to(dtype), b.to(dtype)) for w, b in rest0]}]
        from .progress import progress_bar

        for level in progress_bar(range(1, len(widths)), desc="per-level decoders", unit="level",
                                  disable=len(widths) < 6):
            with torch.no_grad():
                # footprints whose nearest level is this one (the top level: up to 4x its width)
                hi = 4.0 * widths[level] if level == len(widths) - 1 else np.sqrt(widths[level] * widths[level + 1])
                texels = np.exp(rng.uniform(np.log(np.sqrt(widths[level - 1] * widths[level])), np.log(hi), n))
                centres = rng.random((n, 2)) * 64.0
                w = _random_direction_pairs(rng, n)
                wv = torch.from_numpy(w[0]).to(self.device, torch.float32)
                wl = torch.from_numpy(w[1]).to(self.device, torch.float32)
                target = torch.zeros(n, 3, dtype=torch.float32, device=self.device)
                side = (texels / density)[:, None]  # repeats
                for i in range(grid):  # the footprint's mean: one jittered point query per cell of a grid x grid
                    for j in range(grid):
                        jitter = (np.array([j, i]) + rng.random((n, 2))) / grid - 0.5
                        points = torch.from_numpy((centres + side * jitter) / self.scale).to(self.device)
                        target += self._decode_chunk(points, wv, wl)
                target /= grid * grid
                latent = self.synthesizer.filtered_latent(torch.from_numpy(centres).to(self.device),
                                                          torch.from_numpy(texels)).to(self.device)
                angular = decoder.first_layer_angular(fast.angular_features(wv, wl).float())
            weight = fold["weight"].float().clone().requires_grad_()
            bias = fold["bias"].float().clone().requires_grad_()
            rest = [(w_.clone().requires_grad_(), b_.clone().requires_grad_()) for w_, b_ in rest0]
            # eps well above float noise: where the plain decoder is already exact (e.g. a constant plane) the
            # gradients are rounding noise, which Adam's normalization would otherwise turn into full-size steps
            optimizer = torch.optim.Adam([weight, bias, *[p for pair in rest for p in pair]], lr=LEVEL_FIT_LR,
                                         eps=1e-6)
            schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, LEVEL_FIT_STEPS)

            def loss_of(rows):
                x = F.leaky_relu(torch.addmm(bias, latent[rows], weight) + angular[rows], decoder.negative_slope)
                return ((_mlp(x, rest, decoder.negative_slope) - target[rows]) ** 2).mean()

            every = slice(None)
            with torch.no_grad():
                plain_loss = float(loss_of(every))
            _adam_steps(loss_of, optimizer, schedule,
                        torch.from_numpy(rng.integers(0, n, (LEVEL_FIT_STEPS, min(n, LEVEL_FIT_BATCH)))))
            with torch.no_grad():
                fitted_loss = float(loss_of(every))
            if fitted_loss < plain_loss:
                params.append({"weight": weight.detach(), "bias": bias.detach(),
                               "rest": [(w_.detach().to(dtype), b_.detach().to(dtype)) for w_, b_ in rest]})
            else:  # the plain decoder is as good (e.g. a constant plane): keep it
                params.append(params[0])
        if len(params) > 1:
            params[-1] = {**params[-1], "mean": self._fit_mean_appearance(rng)}
        return params

    def _fit_mean_appearance(self, rng: np.random.Generator) -> dict[str, Any] | None:
        """The top level's quadrature (:meth:`level_decoder_parameters`), or None if that level is not constant."""
        fold = self._fold
        fast = fold["fast"]
        decoder = fast.decoder
        slope = decoder.negative_slope
        top = len(self.synthesizer.level_of_detail().widths) - 1
        texel = float(self.synthesizer.level_of_detail().widths[top]) * 4.0
        with torch.no_grad():
            probe = torch.from_numpy(rng.random((16, 2)) * 64.0).to(self.device)
            latent = self.synthesizer.filtered_latent(probe, torch.full((16,), texel, dtype=torch.float64)).float()
            if float((latent - latent[:1]).abs().max()) > 1e-6:
                return None
            n = MEAN_FIT_PAIRS
            w = torch.from_numpy(_random_direction_pairs(rng, n)).float()
            angular = decoder.first_layer_angular(fast.angular_features(w[0].to(self.device), w[1].to(self.device))
                                                  .float())  # with layer 1's bias
            rest0 = [(layer.weight.detach().float(), layer.bias.detach().float()) for layer in decoder.rest]

            # layer 1's positional pre-activation (without its bias) at random synthesized positions
            where = torch.from_numpy(rng.random((MEAN_FIT_POSITIONS, 2)) * 64.0).to(self.device)
            points = torch.addmm(fold["bias"].float(), self.synthesizer.latent(where).to(self.device).float(),
                                 fold["weight"].float())
            # the same positions for every (view, light) pair: the targets are a smooth function of the directions
            # (independent positions per pair gave noisy targets whose fit, though closer on average, left
            # larger blotches on the benchmark's plane)
            target = torch.zeros(n, 3, dtype=torch.float32, device=self.device)
            for start in range(0, n, 64):
                pre = points[None] + angular[start:start + 64, None]
                target[start:start + 64] = _mlp(F.leaky_relu(pre, slope), rest0, slope).mean(1)
        nodes = points[torch.from_numpy(rng.choice(len(points), MEAN_NODES, replace=False)).to(self.device)]
        nodes = nodes.clone().requires_grad_()
        logits = torch.zeros(MEAN_NODES, device=self.device, requires_grad=True)
        rest = [(w_.clone().requires_grad_(), b_.clone().requires_grad_()) for w_, b_ in rest0]
        optimizer = torch.optim.Adam([nodes, logits, *[p for pair in rest for p in pair]], lr=LEVEL_FIT_LR, eps=1e-6)
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, MEAN_FIT_STEPS)

        # the nodes' weighted mean is taken before the last (linear) layer: the same as the mean of the decoded
        # values, with one last-layer product instead of MEAN_NODES
        split = len(rest) - 1

        def loss_of(rows):
            x = F.leaky_relu(nodes[None] + angular[rows, None], slope)
            value = _mlp((_hidden(x, rest[:split], slope) * torch.softmax(logits, 0)[None, :, None]).sum(1),
                         rest[split:], slope)
            # relative error: the mean appearance spans orders of magnitude over the directions
            return (((value - target[rows]) / (target[rows].abs() + 0.02)) ** 2).mean()

        def snapshot():
            return {"nodes": nodes.detach().clone(), "weights": torch.softmax(logits.detach(), 0),
                    "rest": [(w_.detach().clone().to(fold["dtype"]), b_.detach().clone().to(fold["dtype"]))
                             for w_, b_ in rest]}

        every = slice(None)
        with torch.no_grad():
            start_loss, start = float(loss_of(every)), snapshot()
        _adam_steps(loss_of, optimizer, schedule,
                    torch.from_numpy(rng.integers(0, n, (MEAN_FIT_STEPS, min(n, LEVEL_FIT_BATCH)))))
        with torch.no_grad():
            fitted_loss = float(loss_of(every))
        # the starting point (the decoder at MEAN_NODES of the positions) is kept where it is as good, e.g. a
        # constant plane, whose mean appearance it is exactly
        return snapshot() if fitted_loss < start_loss else start

    def mean_appearance(self, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """The material's mean appearance ``(N, 3)`` float32 at unit directions ``(N, 3)`` (model device/dtype).

        What a footprint that reads only the top pyramid level answers: ``sum_k weights[k] decode(nodes[k],
        w_view, w_light)`` with the top level's quadrature (:meth:`level_decoder_parameters`; requires it).
        """
        fold = self._fold
        mean = self.level_decoder_parameters()[-1]["mean"]
        if fold["planes"] is not None:  # the fused kernel's angular plane fetches (no bias), no activation
            from .decoder.fast_decode import first_layer_preactivation

            hidden = fold["planes"][0].shape[-1]
            angular = torch.from_numpy(first_layer_preactivation(
                None, None, None, w_view.float().numpy(), w_light.float().numpy(), *fold["planes"],
                positional=np.zeros((len(w_view), hidden), dtype=np.float32)))
            nodes = mean["nodes_total"]
        else:  # layer 1's angular part with its bias
            fast = fold["fast"]
            angular = fast.decoder.first_layer_angular(fast.angular_features(w_view, w_light).float())
            nodes = mean["nodes"]
        out = torch.empty(len(w_view), 3, dtype=torch.float32, device=angular.device)
        split, slope, weights = len(mean["rest"]) - 1, fold["slope"], mean["weights"].to(fold["dtype"])
        rows = max(1, _MLP_ROWS // len(nodes))
        for start in range(0, len(angular), rows):
            block = angular[start:start + rows]
            # every node's activations as one batch of rows, their weighted mean, then the remaining layers
            x = F.leaky_relu(block[None] + nodes[:, None], slope).to(fold["dtype"]).reshape(-1, block.shape[1])
            x = _hidden(x, mean["rest"][:split], slope).reshape(len(nodes), len(block), -1)
            out[start:start + rows] = _mlp(torch.tensordot(weights, x, dims=1), mean["rest"][split:], slope)
        return out

    def _decode_rest(self, x: torch.Tensor) -> torch.Tensor:
        """Decoder layers 2.. on first-layer activations ``(N, hidden)`` -> RGB float32."""
        return _mlp(x, self._fold["rest"], self._fold["slope"])

    def eval(self, uv, w_view, w_light, footprint=None):
        """BTF value (linear RGB ``(..., 3)`` float32, excluding cos(theta_light)).

        Parameters
        ----------
        uv : ``(..., 2)`` float32/float64
            User's surface coordinates, any finite value with ``|uv| * scale < 2**52``.
        w_view, w_light : ``(..., 3)``
            Unit directions in the local frame, same batch shape as ``uv``. Rows
            with either direction below the horizon (``z < 0``) return zero.
        footprint : float or ``(...)`` array, optional
            The surface area each query stands for, as the side of a square in the user's ``uv``
            units (a pixel's footprint; from uv derivatives with :func:`footprint_width`). The
            answer approximates the BTF averaged over that square (the supersampled value):
            every synthesized sample is read from the mip level of the footprint (trilinear),
            see :mod:`dynbtf.synthesis.mip`. Finite and non-negative, any size (beyond the
            exemplar: the material's mean appearance). Up to one texel (``1 / texels_per_uv()``)
            it is the point query to float rounding. ``None`` (default): the point query.

        Returns
        -------
        ``(..., 3)`` float32: a NumPy array for NumPy ``uv``, else a tensor on the model's device.
        """
        as_numpy = not isinstance(uv, torch.Tensor)
        uv = check_uv(uv, scale=self.scale)
        batch = uv.shape[:-1]
        wv, up_v = self._check_directions(w_view, "w_view", batch)
        wl, up_l = self._check_directions(w_light, "w_light", batch)
        flat = uv.reshape(-1, 2).to(torch.float64)
        fp = None if footprint is None else check_footprint(footprint, batch).reshape(-1)
        if fp is not None and self.level_decoders:
            self.level_decoder_parameters()  # fitted once, before the worker threads need it
        n = flat.shape[0]
        out = torch.zeros(n, 3, dtype=torch.float32, device=self.device)
        visible = up_v & up_l
        dtype = self.model.positional_plane().dtype
        chunks = [slice(start, min(start + self.chunk_size, n)) for start in range(0, n, self.chunk_size)]

        def run(sl: slice) -> None:
            vis = visible[sl]
            if not bool(vis.any()):
                return
            with torch.no_grad():
                rgb = self._decode_chunk(flat[sl].to(self.device), wv[sl].to(self.device, dtype),
                                         wl[sl].to(self.device, dtype), None if fp is None else fp[sl])
            out[sl] = rgb if bool(vis.all()) else torch.where(vis.to(self.device)[:, None], rgb, torch.zeros_like(rgb))

        workers = self.workers if self._fold is not None and self._fold["planes"] is not None else 1
        if workers > 1 and len(chunks) > 1:
            # one chunk per Python thread, each with single-threaded torch and numba: no OpenMP pools
            # handing over between numba kernels and torch matmuls (on a loaded 2-core machine
            # their spin-waiting made two-thread evaluation ~8x slower than one thread)
            from .decoder.fused_mlp import single_intra_op_thread

            with single_intra_op_thread():
                list(_eval_pool(workers).map(lambda sl: _single_numba_thread(run, sl), chunks))
        else:
            for sl in chunks:
                run(sl)
        out = out.reshape(*batch, 3)
        return out.cpu().numpy() if as_numpy else out

    __call__ = eval

    def image(self, view=(0.0, 0.0), light=(0.0, 0.0), uv_rect=(0.0, 0.0, 1.0, 1.0), resolution=512,
              spp: int = 1, filtered: bool = False) -> np.ndarray:
        """A flat sample under one directional (view, light) pair, like the paper's Figs. 5-6.

        Parameters
        ----------
        view, light : (theta, phi) in degrees
            Directions of the camera and of the light (the same for every pixel).
        uv_rect : (u0, v0, u1, v1)
            The user-uv rectangle shown; with ``scale = 45`` the default unit
            square shows 45 x 45 exemplar repeats. May lie anywhere (e.g. around 1e6) with
            ``|u|, |v| * scale < 2**52``.
        resolution : int or (height, width)
            Pixels; pixel ``[i, j]`` shows ``uv = (u0 + (j + .5) (u1 - u0) / W, v0 + (i + .5) (v1 - v0) / H)``.
        spp : int, default 1
            Supersampling: the mean of ``spp x spp`` samples on a regular sub-pixel grid
            (a box filter; use it when a pixel covers many texels, e.g. 45x at 512 px).
        filtered : bool, default False
            Footprint queries: each sample answers for its share of the pixel
            (``footprint`` = the longer side of a pixel / ``spp``, :meth:`eval`): one sample
            per pixel then shows the filtered appearance instead of aliased texels.

        Returns
        -------
        float32 ``(height, width, 3)``: BTF values (linear RGB, excluding cos(theta_light);
        multiply by ``cos(theta_light)`` for the irradiance-weighted image).
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
        check_uv(np.array([[u0, v0], [u1, v1]]), "uv_rect", scale=self.scale)
        directions = []
        for name, pair in (("view", view), ("light", light)):
            try:
                theta, phi = (float(x) for x in pair)
            except (TypeError, ValueError):
                raise InputError(f"{name}: expected (theta, phi) in degrees, got {pair!r}") from None
            if not (np.isfinite(theta) and np.isfinite(phi)):
                raise InputError(f"{name}: (theta, phi) must be finite, got {pair!r}")
            directions.append(spherical_to_direction(np.array(theta), np.array(phi)))
        if int(spp) < 1:
            raise InputError(f"spp: expected a positive number of samples per pixel axis, got {spp}")
        spp = int(spp)
        wv = np.broadcast_to(directions[0], (height, width, 3))
        wl = np.broadcast_to(directions[1], (height, width, 3))
        total = np.zeros((height, width, 3), dtype=np.float64)
        footprint = max(abs(u1 - u0) / width, abs(v1 - v0) / height) / spp if filtered else None
        for sy in range(spp):
            for sx in range(spp):
                u = u0 + (np.arange(width, dtype=np.float64) + (sx + 0.5) / spp) * ((u1 - u0) / width)
                v = v0 + (np.arange(height, dtype=np.float64) + (sy + 0.5) / spp) * ((v1 - v0) / height)
                uu, vv = np.meshgrid(u, v)
                total += self.eval(np.stack([uu, vv], axis=-1), wv, wl, footprint=footprint)
        return (total / (spp * spp)).astype(np.float32)

    def tiled(self) -> "SynthesizedBTF":
        """The same model and precision with plain tiling at scale 1: the exemplar itself, repeated.

        What synthesis is measured against (:func:`dynbtf.synthesis.quality.quality_report`).
        """
        return SynthesizedBTF(self.model, "tile", scale=1.0, precision=self.precision)

    def describe(self) -> dict[str, Any]:
        """Method, seed, scale and parameters (JSON-serializable)."""
        return {"method": self.synthesizer.name, "seed": self.seed, "scale": self.scale, "precision": self.precision,
                "dynamic": self.synthesizer.dynamic, "parameters": self.synthesizer.parameters(),
                "synthesizer_storage_bytes": self.synthesizer.storage_bytes()}
