"""Render the example scenes with the ``dynbtf`` Mitsuba plugin (what ``dynbtf render`` runs)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .mitsuba_bsdf import METHODS, register_plugin
from .scenes import LIGHTINGS, SCENES, bsdf_dict, scene_dict

__all__ = ["render_scene", "RenderResult"]


@dataclass
class RenderResult:
    """A rendered image ``(H, W, 3)`` linear RGB float32 (radiance) and how long it took."""

    image: np.ndarray
    seconds: float
    compile_seconds: float
    variant: str


def render_scene(model_path, *, scene: str = "plane", method: str = "hist", scale: float = 25.0, seed: int = 0,
                 lighting: str = "sky", resolution=(512, 512), spp: int = 16, spp_per_pass: int = 4,
                 variant: str | None = None, progress: bool = True) -> RenderResult:
    """Path-trace ``scene`` covered by the synthesized BTF of ``model_path``.

    Parameters
    ----------
    model_path : path
        A dynbtf Triple Plane model file.
    scene : {"plane", "sphere", "cloth"}
        See :mod:`dynbtf.render.scenes`.
    method : {"tile", "hist", "hex"}
        Synthesis method of the plugin.
    scale : float
        Exemplar repeats across the mesh's uv range.
    seed : int
        Synthesis seed (the sampler uses the pass index).
    lighting : {"point", "sky"}
    resolution : (height, width)
    spp : int
        Samples per pixel in total.
    spp_per_pass : int
        Samples per ``mi.render`` call; the passes are averaged and drive the progress bar.
    variant : str, optional
        Mitsuba variant (default: the active one, or ``llvm_ad_rgb``).
    progress : bool
        Show a tqdm bar over the passes.

    Returns
    -------
    RenderResult
        ``seconds`` is the total wall time, ``compile_seconds`` the first pass's
        extra time (kernel tracing and compilation, cached across runs by Dr.Jit).
    """
    if scene not in SCENES:
        raise InputError(f"--scene: expected one of {list(SCENES)}, got {scene!r}")
    if lighting not in LIGHTINGS:
        raise InputError(f"--lighting: expected one of {list(LIGHTINGS)}, got {lighting!r}")
    if method not in METHODS:
        raise InputError(f"--method: expected one of {list(METHODS)}, got {method!r}")
    if not Path(model_path).is_file():
        raise InputError(f"{model_path}: model file not found")
    if int(spp) < 1 or int(spp_per_pass) < 1:
        raise InputError(f"--spp: expected a positive number of samples per pixel, got {spp}")
    if not (math.isfinite(scale) and scale > 0):
        raise InputError(f"--scale: expected a positive number of repeats, got {scale}")
    active = register_plugin(variant)
    from .drjit_ops import mi_module

    mi = mi_module()
    import drjit as dr
    from tqdm.auto import tqdm

    t0 = time.perf_counter()
    material = bsdf_dict(model_path, method=method, scale=scale, seed=seed)
    scene_obj = mi.load_dict(scene_dict(scene, material, lighting=lighting, resolution=resolution,
                                        spp=min(int(spp), int(spp_per_pass))))
    n_passes = int(math.ceil(int(spp) / int(spp_per_pass)))
    acc = None
    total = 0
    first = None
    with tqdm(total=int(spp), desc=f"render {scene}/{lighting}/{method}", unit="spp", disable=not progress) as bar:
        for k in range(n_passes):
            n = min(int(spp_per_pass), int(spp) - total)
            tp = time.perf_counter()
            img = mi.render(scene_obj, spp=n, seed=k)
            dr.eval(img)
            img = np.asarray(img, dtype=np.float64)
            if first is None:
                first = time.perf_counter() - tp
            acc = img * n if acc is None else acc + img * n
            total += n
            bar.update(n)
    seconds = time.perf_counter() - t0
    per_pass = (seconds - first) / max(n_passes - 1, 1) if n_passes > 1 else 0.0
    compile_seconds = max(first - per_pass, 0.0) if n_passes > 1 else 0.0
    return RenderResult(image=(acc / total).astype(np.float32), seconds=seconds,
                        compile_seconds=compile_seconds, variant=active)
