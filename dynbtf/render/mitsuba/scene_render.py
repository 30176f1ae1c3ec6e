"""Render the example scenes with the ``dynbtf`` Mitsuba plugin (what ``dynbtf render`` runs)."""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from ...jit.llvm import check_llvm
from ...limits import check_count, check_memory, check_scale
from ...synthesis.registry import given_variations, variation_flag
from .bsdf import DEFAULT_METHOD, METHODS, check_cells, check_variation_method, load_plugin_model, register_plugin
from .sampling import SAMPLING_MODES
from .scenes import LIGHTINGS, SCENES, bsdf_dict, scene_dict

__all__ = ["render_scene", "resolve_auto", "RenderResult", "render_memory_bytes", "check_render_request", "MAX_SPP",
           "MAX_SAMPLES", "BYTES_PER_SAMPLE"]

#: Working memory of a render pass per sample in flight (Dr.Jit's wavefront buffers of the path tracer and
#: the plugin; measured: ~1.7 kB per pixel at 4 samples per pass, 512^2 to 1024^2, llvm_ad_rgb), bytes.
BYTES_PER_SAMPLE = 512
#: Most samples per pixel ``dynbtf render`` takes (a converged reference needs ~1-4k).
MAX_SPP = 65536
#: Most samples in one render (pixels x spp): 2**32, a bound on one render's run time on the CPU back end (the
#: plugin's query rate is measured by ``benchmarks/bench_render.py``).
MAX_SAMPLES = 2**32
#: What Mitsuba's uv arithmetic is, for the scale's limit (:func:`dynbtf.limits.check_scale`).
UV_ARITHMETIC = "Mitsuba's float32 uv (mesh uv x scale, in float32)"


def render_memory_bytes(resolution, spp: int, spp_per_pass: int = 4) -> float:
    """Estimated working memory of a render (its image buffers and one pass's samples in flight), bytes."""
    height, width = (int(x) for x in resolution)
    in_flight = min(int(spp), int(spp_per_pass))
    return float(height) * width * (in_flight * BYTES_PER_SAMPLE + 3 * 8 * 2)


def check_render_request(*, scale: float, resolution, spp: int, spp_per_pass: int = 4,
                         memory_mb: float | None = None, size_name: str = "resolution") -> float:
    """The limits of a render, checked before anything loads: the scale (finite, positive, below the
    2**24 repeats float32 uv resolves: the scenes' uv span [0, 1]), the samples (:data:`MAX_SPP` per
    pixel, :data:`MAX_SAMPLES` in all) and the estimated memory (:func:`render_memory_bytes` within
    ``memory_mb``, default half the machine's memory). Returns the scale as a float."""
    scale = check_scale(scale, "--scale", float32=True, where=UV_ARITHMETIC)
    if int(spp) != spp or spp < 1:
        raise InputError(f"--spp: expected a positive number of samples per pixel, got {spp}")
    check_count(int(spp), "--spp", high=MAX_SPP, unit="samples per pixel")
    height, width = (int(x) for x in resolution)
    check_memory(render_memory_bytes((height, width), spp, spp_per_pass),
                 f"--{size_name} {height if height == width else (height, width)} ({height * width:.3g} pixels, "
                 f"{min(int(spp), int(spp_per_pass))} samples per pass)", memory_mb,
                 fix="expected a smaller image")
    samples = float(height) * width * int(spp)
    if samples > MAX_SAMPLES:
        raise InputError(f"--spp {spp} at {height}x{width} pixels is {samples:.3g} samples, above the limit of "
                         f"{MAX_SAMPLES:.3g} (2**32, about an hour on the CPU); expected fewer samples per pixel or "
                         "pixels")
    return scale


@dataclass
class RenderResult:
    """A rendered image ``(H, W, 3)`` linear RGB float32 (radiance) and how long it took.

    ``seconds``: total wall time. ``first_pass_seconds``: the first ``mi.render``
    pass, which includes tracing and compiling Mitsuba's kernels (or loading them from
    Dr.Jit's cache). ``compile_seconds``: the first pass's extra time over the
    mean of the later passes, 0 when there is only one pass (nothing to compare).
    ``method``: the synthesis method the plugin ran (``auto`` resolved; a layered render's two, ``"a | b"``);
    ``choice_line``: what ``auto`` chose and why (:attr:`dynbtf.synthesis.auto.MethodChoice.line`; a line per
    material), else None.
    """

    image: np.ndarray
    seconds: float
    compile_seconds: float
    variant: str
    first_pass_seconds: float = 0.0
    passes: int = 1
    method: str = ""
    choice_line: str | None = None


def _status(progress: bool, text: str) -> None:
    """One status line on standard error (where the progress bar goes), if ``progress``."""
    if progress:
        print(text, file=sys.stderr, flush=True)


def _wanted_variant(variant: str | None) -> str:
    """The variant :func:`register_plugin` will set (the active one, else ``llvm_ad_rgb``), without importing Mitsuba."""
    if variant is not None:
        return variant
    mi = sys.modules.get("mitsuba")
    active = mi.variant() if mi is not None and hasattr(mi, "variant") else None
    return active or "llvm_ad_rgb"


def render_scene(model_path, *, scene: str = "plane", method: str = DEFAULT_METHOD, scale: float = 25.0,
                 seed: int = 0, lighting: str = "sky", resolution=(512, 512), spp: int = 16, spp_per_pass: int = 4,
                 variant: str | None = None, progress: bool = True, sampling: str = "auto",
                 filtered: bool = True, echo=None, memory_mb: float | None = None, layer=None, mask=None,
                 width: float = 0.05, softness: float = 0.0, target=None, classes: int = 2,
                 target_size: float = 1.0, target_wrap: str = "repeat", target_softness: float = 0.0,
                 cells: int = 0, brightness: float = 0.0, tint: float = 0.0,
                 rotation: bool = False, scale_jitter: float = 0.0) -> RenderResult:
    """Path-trace ``scene`` covered by the synthesized BTF of ``model_path``.

    Every argument is checked before Mitsuba loads anything, so a mistake raises
    :class:`~dynbtf.errors.InputError` or :class:`~dynbtf.errors.FormatError`
    naming it (not a ``RuntimeError`` from inside Mitsuba).

    Parameters
    ----------
    model_path : path
        A dynbtf model file: a Triple Plane or a NeuMIP
        (:func:`dynbtf.render.mitsuba.bsdf.load_plugin_model`).
    scene : {"plane", "sphere", "cloth"}
        See :mod:`dynbtf.render.mitsuba.scenes`.
    method : {"tile", "linear", "hist", "hex", "struct", "auto"}
        Synthesis method of the plugin; ``auto`` (the default) is resolved here to ``struct`` for a
        structured material, else ``hist`` (:func:`resolve_auto`: the choice of the model's compiled
        material, which the plugin then reads from the cache), and the choice line is reported (``echo``)
        before the kernel is compiled.
    scale : float
        Exemplar repeats across the mesh's uv range: positive, below 2**24 (Mitsuba's uv is float32,
        which resolves no fraction of a repeat beyond; texels of a ``W``-texel exemplar are resolved
        below ``2**23 / W`` repeats).
    seed : int
        Synthesis seed (the sampler uses the pass index).
    lighting : {"point", "sky"}
    resolution : (height, width)
        Image size in pixels, both positive.
    spp : int
        Samples per pixel in total (positive).
    spp_per_pass : int
        Samples per ``mi.render`` call (positive); the passes are averaged.
    variant : str, optional
        Mitsuba variant (default: the active one, or ``llvm_ad_rgb``); one of
        :func:`dynbtf.render.mitsuba.bsdf.plugin_variants`.
    sampling : {"auto", "mixture", "cosine"}
        The plugin's direction sampling: its importance-sampling table mixed with
        cosine sampling, cosine only, or the table for glossy models and cosine for
        rough ones (see :data:`dynbtf.render.mitsuba.bsdf.PLUGIN_DOC`).
    filtered : bool
        The plugin's footprint queries (its ``filtered``), with footprints from the camera's ray
        cone for ``spp`` samples per pixel: distant surfaces show their filtered appearance.
    progress : bool
        Report on standard error: a status line before the first pass (which
        traces and compiles Mitsuba's kernels: up to a minute the first time a model, method and
        shape are rendered, during which no sample completes), its time after it,
        then a tqdm bar over the remaining passes' samples.
    echo : callable, optional
        Receives ``auto``'s choice line (default: standard error, with the status lines, if ``progress``).
    memory_mb : float, optional
        Limit of the estimated working memory (:func:`render_memory_bytes`), MB; default half the
        machine's memory. Also: at most :data:`MAX_SPP` samples per pixel, :data:`MAX_SAMPLES` in all.
    layer : path, optional
        A second material layered with ``model_path`` (the ``dynbtf_layered`` plugin,
        :mod:`dynbtf.render.mitsuba.layered_bsdf`, which evaluates :class:`dynbtf.layered.LayeredBTF`):
        ``model_path`` where ``mask`` is below one half, ``layer`` above, both with ``method``, ``scale``
        and ``seed`` (``auto`` resolved for each).
    mask : ImageMask or NoiseMask, optional
        With ``layer``: the mask over the mesh's uv (default :class:`~dynbtf.layered.NoiseMask` ``()``).
    width, softness : float
        With ``layer``: the boundary band's half-width (mesh uv units) and the height difference over which
        the layers blend inside it (:class:`~dynbtf.layered.LayeredBTF`).
    target : path, optional
        Guided synthesis (the plugin's ``target``, :func:`dynbtf.guided.guided_btf`): an image painted over
        ``target_size`` x ``target_size`` mesh uv units (``target_wrap``), cut into ``classes`` bins, steering
        ``hist`` (also ``auto``), ``hex`` or ``struct`` (with ``cells``) with ``target_softness``.
    cells : int
        ``struct``'s cells per repeat along each side (the plugin's ``cells``; 0: its own choice).
    brightness, tint : float
        ``struct``'s per-element variation (the plugin's ``brightness`` and ``tint``; 0: off).
    rotation : bool
        Lattice blending's quarter turns of the samples (the plugin's ``rotation``;
        :mod:`dynbtf.synthesis.sample_transform`).
    scale_jitter : float
        Lattice blending's random scales of the samples, in [0, 1] (the plugin's ``scale_jitter``; 0: off).

    Returns
    -------
    RenderResult
    """
    scale, spp, spp_per_pass = _check_request(scene, lighting, method, scale, resolution, spp, spp_per_pass,
                                              sampling, memory_mb)
    if layer is not None:
        _check_layering(width, softness)
    elif mask is not None:
        raise InputError("mask: layers two materials; give the second one (layer / --layer) too")
    if target is not None:
        _check_guidance(target, classes, target_size, target_wrap, target_softness, method, layer, cells)
    if int(cells) != cells or cells < 0:
        raise InputError(f"--cells: the cells per repeat, a positive integer (0: the method's own), got {cells}")
    check_cells(int(cells), method, "--cells")
    variation = given_variations({"brightness": brightness, "tint": tint, "rotation": rotation,
                                  "scale_jitter": scale_jitter}, "--")
    for name in variation:
        if method != "auto":  # (auto's choice is checked by the plugin, once resolved)
            check_variation_method(method, variation_flag(name), name)
    from ...material import CompiledMaterial

    paths = [model_path] if layer is None else [model_path, layer]
    models = []
    for path in paths:
        model = load_plugin_model(path)  # a missing/damaged file or an unsupported kind fails here, not in Mitsuba
        if isinstance(model, CompiledMaterial):  # its method and seed, checked here rather than inside Mitsuba
            if method not in ("auto", model.method) or seed not in (0, model.seed):
                raise InputError(f"{path}: a compiled material fixes method {model.method!r} and seed {model.seed}; "
                                 "leave --method and --seed at their defaults, or render the model file")
        models.append(model)
    check_llvm(_wanted_variant(variant))  # an old LLVM aborts the process while compiling: refused before
    active = register_plugin(variant)
    methods, lines = [], []
    for model in models:
        chosen = method
        if target is not None:  # guided: the method guided_btf runs (auto: hist)
            from ...guided import guided_method

            chosen = guided_method(method, cells)
        elif method == "auto":  # resolved here (the plugin then runs the named method and reports nothing)
            chosen, line = resolve_auto(model, seed)
            lines.append(line)
            if echo is not None:
                echo(line)
            else:
                _status(progress, line)
        methods.append(chosen)
    choice_line = "\n".join(lines) if lines else None
    from ...jit import mi_module

    materials = [{**bsdf_dict(path, method=m, scale=scale, seed=seed, sampling=sampling), "filtered": bool(filtered)}
                 for path, m in zip(paths, methods)]
    if cells:
        for m in materials:
            m["cells"] = int(cells)
    for name, value in variation.items():
        for m in materials:
            m[name] = value if isinstance(value, bool) else float(value)
    material = materials[0]
    if target is not None:
        material.update({"target": str(target), "classes": int(classes), "target_size": float(target_size),
                         "target_wrap": str(target_wrap), "softness": float(target_softness)})
    if layer is not None:
        from ...layered import NoiseMask
        from .layered_bsdf import mask_texture_dict

        material = {"type": "dynbtf_layered", "layer0": materials[0], "layer1": materials[1],
                    "mask": mask_texture_dict(NoiseMask() if mask is None else mask), "width": float(width),
                    "softness": float(softness)}
    method = " | ".join(methods)
    scene_obj = mi_module().load_dict(scene_dict(scene, material, lighting=lighting, resolution=resolution,
                                                 spp=min(spp, spp_per_pass), footprint_spp=spp))
    image, timing = _render_passes(scene_obj, spp, spp_per_pass, f"render {scene}/{lighting}/{method}", progress)
    return RenderResult(image=image, variant=active, method=method, choice_line=choice_line, **timing)


def _check_request(scene, lighting, method, scale, resolution, spp, spp_per_pass, sampling,
                   memory_mb) -> tuple[float, int, int]:
    """:func:`render_scene`'s choices, sizes and limits checked (before anything loads): ``(scale, spp,
    spp_per_pass)``."""
    if scene not in SCENES:
        raise InputError(f"--scene: expected one of {list(SCENES)}, got {scene!r}")
    if lighting not in LIGHTINGS:
        raise InputError(f"--lighting: expected one of {list(LIGHTINGS)}, got {lighting!r}")
    if method not in METHODS:
        raise InputError(f"--method: expected one of {list(METHODS)}, got {method!r}")
    if len(resolution) != 2 or not all(int(x) == x and x >= 1 for x in resolution):
        raise InputError(f"resolution: expected (height, width) in pixels, both positive integers, "
                         f"got {tuple(resolution)}")
    if int(spp) != spp or spp < 1:
        raise InputError(f"--spp: expected a positive number of samples per pixel, got {spp}")
    if int(spp_per_pass) != spp_per_pass or spp_per_pass < 1:
        raise InputError(f"spp_per_pass: expected a positive number of samples per pixel, got {spp_per_pass}")
    scale = check_render_request(scale=scale, resolution=resolution, spp=spp, spp_per_pass=spp_per_pass,
                                 memory_mb=memory_mb)
    if sampling not in SAMPLING_MODES:
        raise InputError(f"--sampling: expected one of {list(SAMPLING_MODES)}, got {sampling!r}")
    return scale, int(spp), int(spp_per_pass)


def _check_layering(width, softness) -> None:
    """A layered render's band (:class:`dynbtf.layered.LayeredBTF`'s parameters), checked before anything loads."""
    from ...errors import positive_number

    positive_number("--width", width, "uv units")
    if not (math.isfinite(float(softness)) and float(softness) >= 0.0):
        raise InputError(f"softness: expected a height difference >= 0, got {softness!r}")


def _check_guidance(target, classes, target_size, target_wrap, softness, method, layer, cells) -> None:
    """A guided render's request (the plugin's ``target`` and its companions), checked before anything loads
    (:func:`dynbtf.guided.guidance_options`, as ``dynbtf synth`` and ``dynbtf export`` check theirs)."""
    if layer is not None:
        raise InputError("target: guides one material; it does not combine with a layered one (layer)")
    from ...guided import guidance_options

    guidance_options(target, method=method, classes=classes, target_size=target_size, target_wrap=target_wrap,
                     softness=softness, cells=cells, units="mesh uv units")


def resolve_auto(model, seed: int = 0) -> tuple[str, str]:
    """``(method, choice line)`` of ``auto`` for ``model`` and ``seed``: what its compiled material chose
    (:func:`dynbtf.material.open_or_compile`: read from the cache, or compiled and stored; the stage also stores
    it under the chosen method's name, so that the plugin, which then gets that name, reads it)."""
    from ...material import CompiledMaterial, open_or_compile

    if isinstance(model, CompiledMaterial):  # compiled: what it chose then, or the method it was compiled for
        line = model.choice["line"] if model.choice else f"compiled material: method {model.method}, seed {model.seed}"
        return model.method, str(line)
    material, _ = open_or_compile(model, "auto", seed, footprints=False, progress=False)
    return material.method, str(material.choice["line"])


def _render_passes(scene_obj, spp: int, spp_per_pass: int, label: str, progress: bool) -> tuple[np.ndarray, dict]:
    """Render ``spp`` samples per pixel in passes of ``spp_per_pass`` and average them: ``(image, timing)``,
    ``timing`` the :class:`RenderResult` fields ``seconds``, ``compile_seconds``, ``first_pass_seconds``, ``passes``."""
    from ...progress import progress_bar
    from ...jit import drjit_module, mi_module

    mi, dr = mi_module(), drjit_module()
    t0 = time.perf_counter()
    n_passes = int(math.ceil(spp / spp_per_pass))
    acc = None
    total = 0
    first = later = 0.0  # seconds of the first pass, of all later passes
    bar = None
    for k in range(n_passes):
        n = min(spp_per_pass, spp - total)
        if k == 0:
            _status(progress, f"{label}: compiling Mitsuba's kernels and running the first pass ({n} spp; up to "
                              f"a minute the first time this model, method and shape are rendered, then cached)...")
        tp = time.perf_counter()
        img = mi.render(scene_obj, spp=n, seed=k)
        dr.eval(img)
        img = np.asarray(img, dtype=np.float64)
        acc = img * n if acc is None else acc + img * n
        total += n
        if k == 0:
            first = time.perf_counter() - tp
            _status(progress, f"{label}: kernels ready, first pass done in {first:.1f} s ({total}/{spp} spp)")
            if n_passes > 1:
                bar = progress_bar(total=spp, initial=total, desc=label, unit="spp", disable=not progress)
        else:
            later += time.perf_counter() - tp
            bar.update(n)
    if bar is not None:
        bar.close()
    per_pass = later / (n_passes - 1) if n_passes > 1 else 0.0
    compile_seconds = max(first - per_pass, 0.0) if n_passes > 1 else 0.0
    return (acc / total).astype(np.float32), {"seconds": time.perf_counter() - t0, "compile_seconds": compile_seconds,
                                              "first_pass_seconds": first, "passes": n_passes}
