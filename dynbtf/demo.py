"""``dynbtf demo``: the whole pipeline on one material, into one ``report.html``.

Stages (each shows progress and records its results and wall time in
``<output>/stages/<stage>.json``; a rerun with the same output directory and
options skips finished stages, and the training stage resumes its checkpoint):

1. ``data``      -- open the BTF: a simulated material (default: ``leather``,
                    128 x 128 texels on the UBO2003 81 x 81 grid, no download)
                    or the user's own file; write a few of its images.
2. ``fit``       -- fit the Triple Plane (the paper's recipe; :func:`dynbtf.training.fit.fit`)
                    within a share of the time budget.
3. ``evaluate``  -- held-out (view, light) pairs: PSNR, DSSIM, FLIP; side-by-side
                    ground truth | model | FLIP map images; model size vs raw size.
4. ``features``  -- pictures of the feature planes (the paper's Fig. 2).
5. ``synthesis`` -- the synthesized BTF by tiling, histogram-preserving blending and
                    hex-tiling at 1x, 8x, 25x, 45x the exemplar's area, a grazing
                    preview of an infinite plane per method, the synthesis
                    quality numbers, and the material guided by a painted target
                    (:func:`dynbtf.guided.guided_btf`) at 8x.
6. ``structured`` -- a structured material (simulated ceramic tiles, or the demo's own material when
                    that is structured) fitted briefly at 64 x 64 texels and synthesized at 8x and
                    25x by tiling, histogram-preserving blending and ``auto`` (which picks
                    lattice-aligned cell quilting for it), with the structure measures; and the two
                    materials layered under a value-noise mask (:class:`dynbtf.layered.LayeredBTF`).
7. ``render``    -- Mitsuba 3 renders with the ``dynbtf`` plugin: plane, sphere and
                    cloth under two lighting conditions (the paper's teaser), and
                    the grazing plane per synthesis method.
8. ``viewer``    -- the real-time export (:func:`dynbtf.export.web.exporter.export_web`, fp16):
                    ``viewer/index.html``, a WebGL2 page that synthesizes and decodes the
                    material per pixel in the browser; and ``layered-viewer/index.html``, the
                    layered material, whose mask the user paints there.
9. ``report``    -- ``report.html`` with every image and table, linking the viewer.

Training gets the budget the other stages leave and stops with a checkpoint if
it has not converged; to train on, delete ``<output>/stages/fit.json`` and rerun
(training continues from ``model.dbtfm.ckpt``, the later stages are redone).

``quick=True`` shrinks every stage (a small decoder, seconds of training, tiny images, one small render):
what the tests use.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .errors import InputError
from .io import atomic_path, save_image

__all__ = ["DemoConfig", "run_demo", "STAGES", "SCALES", "METHODS"]

STAGES = ("data", "fit", "evaluate", "features", "synthesis", "structured", "render", "viewer", "report")
#: Synthesized areas shown, in multiples of the exemplar's side (the paper's Figs. 5-6 use 8x, 25x, 45x).
SCALES = (1, 8, 25, 45)
#: Synthesis methods compared.
METHODS = ("tile", "hist", "hex")
#: Methods of the structured material's comparison (``auto`` picks ``struct`` for it).
STRUCTURED_METHODS = ("tile", "hist", "auto")
#: The structured material of the ``structured`` stage when the demo's own material is not structured.
STRUCTURED_MATERIAL = "ceramic_tiles"


@dataclass
class DemoConfig:
    """Options of :func:`run_demo`.

    Attributes
    ----------
    output : str
        Output directory (created; reruns resume there).
    material : str
        Simulated material (``dynbtf.data.simulated.MATERIALS``) when ``btf`` is not given.
    size : int
        Texels per side of the simulated BTF.
    btf : str, optional
        The user's own BTF: a file or ``sim:`` spec understood by ``dynbtf.data.open_btf``.
    minutes : float
        Target wall time of the whole demo; training gets what the other stages leave.
    seed : int
        Seed of the simulation, training split/initialization and synthesis.
    quick : bool
        Tiny everything (tests, smoke runs).
    render_size : int
        Mitsuba image side in pixels.
    spp : int
        Mitsuba samples per pixel.
    device : str
        Where the model is fitted, evaluated and synthesized: ``"auto"`` (CUDA when present),
        ``"cpu"``, ``"cuda:0"``, ... (:func:`dynbtf.device.resolve_device`). Mitsuba renders with
        its own variant (``llvm_ad_rgb``). Not part of :meth:`result_key`: finished stages are
        reused on another device.
    """

    output: str = "dynbtf-demo"
    material: str = "leather"
    size: int = 128
    btf: str | None = None
    minutes: float = 10.0
    seed: int = 0
    quick: bool = False
    render_size: int = 360
    spp: int = 16
    device: str = "auto"

    def result_key(self) -> dict[str, Any]:
        """Options that change results (a finished stage is reused only if they agree)."""
        d = asdict(self)
        d.pop("output")
        d.pop("minutes")
        d.pop("device")
        return d


@dataclass
class _Context:
    config: DemoConfig
    out: Path
    progress: bool
    log: Callable[[str], None]
    results: dict[str, Any] = field(default_factory=dict)
    _source: Any = None
    _model: Any = None
    _metadata: Any = None

    def rel(self, path: Path) -> str:
        return Path(path).resolve().relative_to(self.out.resolve()).as_posix()

    # ---- lazily opened shared objects (reruns open them again)
    def source(self):
        if self._source is None:
            cfg = self.config
            if cfg.btf:
                from .data import open_btf

                self._source = open_btf(cfg.btf)
            else:
                from .data.simulated import simulated_btf

                self._source = simulated_btf(cfg.material, size=cfg.size, grid="ubo2003", seed=cfg.seed)
        return self._source

    def model(self):
        if self._model is None:
            from .representations.model_file import load_model

            self._model, self._metadata = load_model(self.out / "model.dbtfm", device=self.config.device)
        return self._model

    def metadata(self):
        self.model()
        return self._metadata


# ---------------------------------------------------------------------------------------------- stages
def _stage_data(ctx: _Context) -> dict[str, Any]:
    src = ctx.source()
    d = ctx.out / "data"
    views = [src.nearest_view([0.0, 0.0, 1.0]), src.nearest_view([0.5, 0.0, 0.866])]
    lights = [src.nearest_light([0.5, 0.3, 0.81]), src.nearest_light([-0.7, 0.2, 0.68])]
    images = []
    for v, l in zip(views, lights):
        p = save_image(d / f"btf_v{v:03d}_l{l:03d}.png", src.image(v, l))
        images.append({"path": ctx.rel(p), "view": int(v), "light": int(l)})
    return {"describe": {k: v for k, v in src.describe().items() if isinstance(v, (int, float, str))},
            "images": images, "raw_bytes": int(src.nbytes_float32)}


#: Minutes the stages after the fit take at the defaults on 2 cores of an AVX2 machine with empty kernel caches
#: (synthesis, mostly fitting the per-level footprint decoders of three methods and compiling numba kernels;
#: structured; render, mostly compiling the Mitsuba kernels; the rest), plus a margin. Each stage's time is
#: measured by ``benchmarks/bench_demo.py``.
OTHER_STAGES_MINUTES = 8.0


def _fit_minutes(cfg: DemoConfig) -> float:
    """Training's share of the time budget: what the other stages (:data:`OTHER_STAGES_MINUTES`) leave."""
    if cfg.quick:
        return min(0.15, cfg.minutes)
    return max(0.5, cfg.minutes - OTHER_STAGES_MINUTES)


def _stage_fit(ctx: _Context) -> dict[str, Any]:
    from .representations.triple_plane import TriplePlane
    from .training.fit import TrainConfig, fit

    cfg = ctx.config
    src = ctx.source()
    # the auto recipe (docs/triple_plane.md): the fast recipe (64 texel groups, 6x the paper's learning rates) with
    # the schedule that converges at 128^2 (30 epochs on the UBO2003 grid), shortened when a few timed steps show
    # that it would not fit the time budget on this machine; a rerun continues with the options it started with
    from .training import checkpoint_path
    from .training.checkpoint import Checkpointer
    from .training.recipe import auto_recipe

    if cfg.quick:  # a small decoder: quick to fit and to compile into the render kernel
        rep = TriplePlane(src.height, src.width, positional_channels=8, angular_channels=4, hidden=16, seed=cfg.seed)
    else:
        rep = TriplePlane(src.height, src.width, seed=cfg.seed)
    model_path = ctx.out / "model.dbtfm"
    saved = Checkpointer.saved_config(checkpoint_path(model_path))
    if saved is not None:
        train = TrainConfig(**{**saved, "device": cfg.device, "max_minutes": _fit_minutes(cfg)})
        summary = f"continuing the unfinished fit ({train.epochs} epochs)"
    elif cfg.quick:
        train = TrainConfig(epochs=1, monitor_pairs=2, seed=cfg.seed, max_minutes=_fit_minutes(cfg),
                            device=cfg.device, lr_scale=6.0,
                            texel_groups=max(1, min(64, int(0.9 * src.n_pairs) // 16, src.height * src.width)))
        summary = "quick: one epoch"
    else:
        chosen = auto_recipe(src, minutes=_fit_minutes(cfg), representation=rep, seed=cfg.seed, device=cfg.device)
        train, summary = chosen.config, chosen.summary
    ctx.log(summary)
    result = fit(rep, src, train, model_path, progress=ctx.progress)
    history = [{k: float(v) for k, v in h.items() if isinstance(v, (int, float))} for h in result.history]
    provenance = result.metadata.get("provenance", {})
    return {"finished": bool(result.finished), "epochs_configured": train.epochs, "recipe": summary,
            "max_minutes": train.max_minutes, "history_tail": history[-5:],
            "epochs_completed": float(provenance.get("epochs_completed", train.epochs)),
            "seconds_training": float(provenance.get("training_seconds", 0.0)),
            "monitor_pairs": int(train.monitor_pairs)}


def _stage_evaluate(ctx: _Context) -> dict[str, Any]:
    from .representations.model_file import model_size_report
    from .training.evaluate import evaluate_model, resolve_eval_pairs

    src, rep = ctx.source(), ctx.model()
    pairs = resolve_eval_pairs("held-out", src, ctx.metadata())
    limit = 6 if ctx.config.quick else 48  # evenly spaced held-out pairs (all of them: `dynbtf eval`)
    if len(pairs) > limit:
        pairs = pairs[np.linspace(0, len(pairs) - 1, limit).round().astype(int)]
    ev = evaluate_model(rep, src, pairs, out_dir=ctx.out / "evaluate", images=4 if ctx.config.quick else 6,
                        progress=ctx.progress)
    images = []
    for p in ev.images:
        row = next((r for r in ev.rows if f"v{r['view_index']:03d}_l{r['light_index']:03d}" in Path(p).name), None)
        images.append({"path": ctx.rel(p), "row": row})
    size = model_size_report(rep, src.nbytes_float32)
    return {"mean": ev.mean, "by_angle": ev.by_angle, "n_pairs": len(ev.rows), "images": images, "rows": ev.rows,
            "size": _jsonable(size)}


def _stage_features(ctx: _Context) -> dict[str, Any]:
    from .representations.visualize import write_feature_plane_pngs

    paths = write_feature_plane_pngs(ctx.model(), ctx.out / "features")
    return {"images": [ctx.rel(p) for p in paths]}


def _synth_resolution(cfg: DemoConfig) -> int:
    return 96 if cfg.quick else 512


def _stage_synthesis(ctx: _Context) -> dict[str, Any]:
    from .progress import progress_bar
    from .render.preview import DirectionalLight, grazing_camera, render_preview
    from .synthesized import synthesized_btf

    cfg = ctx.config
    rep = ctx.model()
    res = _synth_resolution(cfg)
    view, light = (0.0, 0.0), (55.0, 300.0)  # (theta, phi) in degrees: a low light shows the relief
    scales = SCALES[:2] if cfg.quick else SCALES
    out_dir = ctx.out / "synthesis"
    grid: dict[str, dict[str, Any]] = {}
    filtered: dict[str, dict[str, Any]] = {}
    timings = {}
    jobs = [(m, s) for m in METHODS for s in scales]
    compile_seconds = {}
    for method in METHODS:  # the first call compiles the method's kernels (numba, cached on disk): timed apart
        t0 = time.perf_counter()
        synthesized_btf(rep, method, scale=1.0, seed=cfg.seed).image(view, light, (0.0, 0.0, 1.0, 1.0), (8, 8))
        compile_seconds[method] = time.perf_counter() - t0
    for method, scale in progress_bar(jobs, desc="synthesis", unit="image", disable=not ctx.progress):
        # the footprint decoders where a filtered image is made (fitted once per method, then cached)
        btf = synthesized_btf(rep, method, scale=1.0, seed=cfg.seed, footprints=scale >= 25)
        t0 = time.perf_counter()  # one query per pixel, like the paper's figures (warm: kernels compiled above)
        img = btf.image(view, light, (0.0, 0.0, float(scale), float(scale)), (res, res))
        timings[f"{method}@{scale}x"] = time.perf_counter() - t0
        p = save_image(out_dir / f"{method}_{scale:02d}x.png", img)  # BTF values, like the measured images
        grid.setdefault(method, {})[str(scale)] = ctx.rel(p)
        if scale >= 25:  # many texels per pixel: the footprint query shows the filtered appearance
            t0 = time.perf_counter()
            img = btf.image(view, light, (0.0, 0.0, float(scale), float(scale)), (res, res), filtered=True)
            timings[f"{method}@{scale}x filtered"] = time.perf_counter() - t0
            p = save_image(out_dir / f"{method}_{scale:02d}x_filtered.png", img)
            filtered.setdefault(method, {})[str(scale)] = ctx.rel(p)
    # an infinite plane at a grazing angle, per method: repetition shows as a grid towards the horizon
    previews = {}
    cam = grazing_camera(distance=4.0, height=1.6, fov=55.0, center=(0.5, 2.5))
    sun = DirectionalLight((-0.55, -0.35, 0.76), irradiance=1.0)  # from behind the camera: no mirror highlight
    pres = (72, 128) if cfg.quick else (288, 512)
    for method in progress_bar(METHODS, desc="grazing previews", unit="image", disable=not ctx.progress):
        btf = synthesized_btf(rep, method, scale=1.0, seed=cfg.seed)
        img = render_preview(btf, cam, sun, resolution=pres, spp=1 if cfg.quick else 2, background=(0.55, 0.65, 0.8))
        previews[method] = ctx.rel(save_image(out_dir / f"grazing_{method}.png", img))
    quality = _synthesis_quality(ctx, rep)
    t0 = time.perf_counter()
    guided = _guided_panels(ctx, rep, view, light, res, scales[1])
    timings[f"guided@{scales[1]}x"] = time.perf_counter() - t0
    return {"grid": grid, "filtered": filtered, "scales": list(scales), "resolution": res, "view": list(view), "light": list(light),
            "timings": timings, "compile_seconds": compile_seconds, "previews": previews, "quality": quality,
            "guided": guided}


def _guided_panels(ctx: _Context, rep, view, light, res: int, scale: int) -> dict[str, Any]:
    """Exemplar guidance at ``scale`` x the exemplar's area: the painted target (:func:`dynbtf.guided.example_target`,
    over the whole image) and the material guided by it in two classes (dark where the target is dark)."""
    from .guided import example_target, guided_btf

    target = example_target()
    btf = guided_btf(rep, target, classes=2, target_size=float(scale), target_wrap="clamp", scale=1.0,
                     seed=ctx.config.seed)
    img = btf.image(view, light, (0.0, 0.0, float(scale), float(scale)), (res, res))
    rows = np.arange(res) * target.shape[0] // res
    shown = np.repeat(target[rows][:, rows][..., None], 3, -1).astype(np.float32)
    out_dir = ctx.out / "synthesis"
    return {"scale": scale, "classes": 2, "target": ctx.rel(save_image(out_dir / "guided_target.png", shown)),
            "image": ctx.rel(save_image(out_dir / f"guided_{scale:02d}x.png", img))}


def _synthesis_quality(ctx: _Context, rep) -> list[dict[str, Any]]:
    """One row of synthesis quality numbers per method (:func:`dynbtf.synthesis.quality.quality_report`)."""
    from .synthesis.quality import quality_report
    from .synthesized import synthesized_btf

    rows = []
    for method in METHODS:
        q = quality_report(synthesized_btf(rep, method, seed=ctx.config.seed), repeats=4,
                           max_side=256 if ctx.config.quick else 512, rgb_side=128 if ctx.config.quick else 256,
                           seed=ctx.config.seed)
        rows.append({"method": method,
                     "feature W1/std (mean)": q["feature_w1_over_std_mean"],
                     "feature W1/std (max)": q["feature_w1_over_std_max"],
                     "feature std ratio (min)": min(q["feature_std_ratio"]),
                     "RGB W1/std (max)": q["rgb_w1_over_std_max"],
                     "repetition score": q["repetition"]["score"],
                     "verbatim fraction": q["verbatim_fraction"],
                     "area measured (exemplar repeats per side)": q["area_repeats"]})
    return rows


def _stage_structured(ctx: _Context) -> dict[str, Any]:
    from .data.simulated import MATERIALS, simulated_btf
    from .representations.triple_plane import TriplePlane
    from .synthesis.coherence import synthesized_coherence
    from .synthesized import synthesized_btf
    from .training.fit import TrainConfig, fit

    cfg = ctx.config
    own = cfg.btf is None and MATERIALS.get(cfg.material, "").startswith("structured")
    material = cfg.material if own else STRUCTURED_MATERIAL
    size = 32 if cfg.quick else 64
    src = simulated_btf(material, size=size, grid="ubo2003", seed=cfg.seed)
    folder = ctx.out / "structured"
    model_path = folder / "model.dbtfm"
    if cfg.quick:
        rep = TriplePlane(size, size, positional_channels=8, angular_channels=4, hidden=16, seed=cfg.seed)
        train = TrainConfig(epochs=2, monitor_pairs=2, seed=cfg.seed, max_minutes=3.0, device=cfg.device,
                            lr_scale=6.0, texel_groups=16)  # one epoch leaves the tiles' joints blurred
    else:
        rep = TriplePlane(size, size, seed=cfg.seed)
        train = TrainConfig(epochs=3, monitor_pairs=8, seed=cfg.seed, max_minutes=5.0, device=cfg.device,
                            lr_scale=6.0, texel_groups=64)
    ctx.log(f"structured: fitting simulated {material} ({size} x {size} texels), {train.epochs} epochs")
    fit(rep, src, train, model_path, progress=ctx.progress)
    view, light = (0.0, 0.0), (40.0, 30.0)
    res = 96 if cfg.quick else 384
    images: dict[str, dict[str, str]] = {}
    rows = []
    choice = None
    far = 1e6
    for method in STRUCTURED_METHODS:
        for scale in (8, 25):
            btf = synthesized_btf(model_path, method, scale=float(scale), seed=cfg.seed)
            if btf.synthesizer.choice is not None:
                choice = btf.synthesizer.choice.line
            c = far / scale  # far from the origin: exact at any uv
            img = btf.image(view, light, (c, c, c + 1.0, c + 1.0), (res, res), spp=1 if cfg.quick else 2)
            images.setdefault(method, {})[str(scale)] = ctx.rel(save_image(folder / f"{method}_{scale:02d}x.png", img))
        r = synthesized_coherence(btf, side=(4 if cfg.quick else 8) * size, patches=64 if cfg.quick else 256,
                                  seed=cfg.seed)
        rows.append({"method": method if method != "auto" else f"auto ({btf.synthesizer.name})",
                     # 4 decimals: tiling's exact copies score ~1e-14 (decoding rounding), shown as 0
                     "coherence p90": round(r["p90"], 4), "coherence median": round(r["median"], 4),
                     "identity with tiling": round(r["identity"], 4),
                     "tables (KB)": btf.synthesizer.storage_bytes() / 1024})
    layered = _layered_panels(ctx, view, light, res)
    return {"material": material, "size": size, "choice": choice, "images": images, "quality": rows,
            "view": list(view), "light": list(light), "resolution": res, "layered": layered}


#: The demo's layered material: value noise of this many uv units per cell, contrast, and the band's half-width.
LAYERED_MASK = (0.35, 3.0)
LAYERED_WIDTH = 0.03


def _demo_layered(ctx: _Context, scale: float = 8.0):
    """The demo's material (hist) and the structured one (auto) on one surface under value noise
    (:class:`dynbtf.layered.LayeredBTF`), each at ``scale`` repeats per uv unit."""
    from .layered import LayeredBTF, NoiseMask
    from .synthesized import synthesized_btf

    seed = ctx.config.seed
    layers = [synthesized_btf(ctx.out / "model.dbtfm", "hist", scale=scale, seed=seed),
              synthesized_btf(ctx.out / "structured" / "model.dbtfm", "auto", scale=scale, seed=seed)]
    return LayeredBTF(layers, NoiseMask(*LAYERED_MASK, seed=seed), width=LAYERED_WIDTH)


def _layered_panels(ctx: _Context, view, light, res: int) -> dict[str, Any]:
    """The layered material over one uv unit: its mask, the image, and which layer each pixel shows."""
    layered = _demo_layered(ctx)
    folder = ctx.out / "structured"
    img = layered.image(view, light, (0.0, 0.0, 1.0, 1.0), (res, res))
    centres = (np.arange(res) + 0.5) / res
    u, v = np.meshgrid(centres, centres)
    uv = np.stack([u.ravel(), v.ravel()], -1)
    mask = layered.mask.value(uv).reshape(res, res)
    shown = layered.weight(uv).reshape(res, res)

    def grey(a):
        return np.repeat(a[..., None], 3, -1).astype(np.float32)

    return {"mask": ctx.rel(save_image(folder / "layered_mask.png", grey(mask))),
            "image": ctx.rel(save_image(folder / "layered_08x.png", img)),
            "shown": ctx.rel(save_image(folder / "layered_shown.png", grey(0.25 + 0.5 * shown))),
            "noise": list(LAYERED_MASK), "width": LAYERED_WIDTH,
            "methods": [btf.synthesizer.name for btf in layered.layers]}


def _render_jobs(cfg: DemoConfig) -> list[dict[str, Any]]:
    if cfg.quick:
        return [{"scene": "plane", "lighting": "sky", "method": "hist", "scale": 25.0}]
    jobs = [{"scene": s, "lighting": li, "method": "hist", "scale": sc}
            for s, sc in (("plane", 12.0), ("sphere", 6.0), ("cloth", 5.0)) for li in ("sky", "point")]
    # repetition at a grazing angle, in Mitsuba too (hex-tiling is shown by the preview and synthesis stages)
    jobs += [{"scene": "plane", "lighting": "sky", "method": "tile", "scale": 12.0}]
    return jobs


def _stage_render(ctx: _Context) -> dict[str, Any]:
    from .render.mitsuba.scene_render import render_scene

    cfg = ctx.config
    size = 48 if cfg.quick else cfg.render_size
    spp = 2 if cfg.quick else cfg.spp
    rows = []
    for k, job in enumerate(_render_jobs(cfg)):
        ctx.log(f"render {k + 1}/{len(_render_jobs(cfg))}: {job['scene']} / {job['lighting']} / {job['method']}")
        r = render_scene(ctx.out / "model.dbtfm", resolution=(size, size), spp=spp, seed=cfg.seed,
                         progress=ctx.progress, **job)
        name = f"{job['scene']}_{job['lighting']}_{job['method']}"
        p = save_image(ctx.out / "render" / f"{name}.png", r.image)
        save_image(ctx.out / "render" / f"{name}.exr", r.image)
        rows.append({**job, "path": ctx.rel(p), "seconds": round(r.seconds, 2),
                     "compile_seconds": round(r.compile_seconds, 2), "size": size, "spp": spp, "variant": r.variant})
    return {"renders": rows}


def _stage_viewer(ctx: _Context) -> dict[str, Any]:
    from .export.web.exporter import export_web

    result = export_web(ctx.out / "model.dbtfm", ctx.out / "viewer", precision="fp16", methods=("auto", "hist", "tile"),
                        seed=ctx.config.seed, scale=8.0)
    out = {"index": ctx.rel(result.index), "precision": "fp16", "hist_bytes": result.method_bytes("hist"),
           "total_bytes": result.total_bytes(), "model_bytes": (ctx.out / "model.dbtfm").stat().st_size}
    if (ctx.out / "structured" / "model.dbtfm").is_file():  # the layered material, its mask painted in the page
        from .export.web.layered import export_layered_web

        layered = export_layered_web(_demo_layered(ctx), ctx.out / "layered-viewer", precision="fp16")
        out["layered_index"] = ctx.rel(layered.index)
    return out


def _stage_report(ctx: _Context) -> dict[str, Any]:
    from .report.demo_report import write_demo_report

    path = write_demo_report(ctx.out, ctx.config, ctx.results)
    return {"report": ctx.rel(path)}


_STAGE_FUNCS = {"data": _stage_data, "fit": _stage_fit, "evaluate": _stage_evaluate, "features": _stage_features,
                "synthesis": _stage_synthesis, "structured": _stage_structured, "render": _stage_render, "viewer": _stage_viewer,
                "report": _stage_report}


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x)
    if isinstance(x, (np.integer, int)) and not isinstance(x, bool):
        return int(x)
    if isinstance(x, (str, bool)) or x is None:
        return x
    if hasattr(x, "item") and getattr(x, "ndim", 1) == 0:
        return x.item()
    return str(x)


def run_demo(config: DemoConfig | None = None, *, progress: bool = True, log: Callable[[str], None] | None = None,
             stages: tuple[str, ...] = STAGES) -> dict[str, Any]:
    """Run (or resume) the demo; return every stage's results (also in ``<output>/stages/*.json``).

    A stage whose record exists with the same :meth:`DemoConfig.result_key` is
    skipped; delete ``<output>/stages/<stage>.json`` to redo one stage (and the
    ones after it, whose inputs it produced).
    """
    cfg = config or DemoConfig()
    _check_config(cfg)
    out = Path(cfg.output)
    out.mkdir(parents=True, exist_ok=True)
    say = log or (lambda s: print(f"[dynbtf demo] {s}", flush=True))
    ctx = _Context(cfg, out, progress, say)
    key = _jsonable(cfg.result_key())
    redo = False
    t_start = time.perf_counter()
    for i, name in enumerate(stages):
        record = out / "stages" / f"{name}.json"
        if not redo and record.exists():
            try:
                saved = json.loads(record.read_text())
            except json.JSONDecodeError:
                saved = {}
            # an unfinished fit (time budget reached) is not done: running again continues it
            if saved.get("key") == key and name != "report" and saved.get("finished", True):
                ctx.results[name] = saved
                say(f"stage {i + 1}/{len(stages)} {name}: done earlier ({saved.get('seconds', 0):.1f} s), skipped")
                continue
        redo = True  # later stages depend on this one's outputs
        say(f"stage {i + 1}/{len(stages)} {name} ...")
        t0 = time.perf_counter()
        result = _STAGE_FUNCS[name](ctx)
        seconds = time.perf_counter() - t0
        saved = {"key": key, "seconds": seconds, **_jsonable(result)}
        ctx.results[name] = saved
        if name == "fit" and not result.get("finished", True):
            redo = True
        with atomic_path(record) as tmp:
            tmp.write_text(json.dumps(saved, indent=1))
        say(f"stage {i + 1}/{len(stages)} {name}: {seconds:.1f} s")
    total = time.perf_counter() - t_start
    say(f"report: {out / 'report.html'} (this run {total / 60:.1f} min)")
    return ctx.results


def _check_config(cfg: DemoConfig) -> None:
    from .data.simulated import MATERIALS
    from .device import resolve_device

    resolve_device(cfg.device)  # CUDA requested but absent: an InputError before any stage

    if cfg.btf is None and cfg.material not in MATERIALS:
        raise InputError(f"--material: expected one of {sorted(MATERIALS)}, got {cfg.material!r}")
    if not 8 <= int(cfg.size) <= 1024:
        raise InputError(f"--size: expected 8..1024 texels, got {cfg.size}")
    if not (math.isfinite(cfg.minutes) and cfg.minutes > 0):
        raise InputError(f"--minutes: expected a positive time budget, got {cfg.minutes}")
    if cfg.render_size < 16 or cfg.spp < 1:
        raise InputError(f"render size/spp: expected >= 16 pixels and >= 1 spp, got {cfg.render_size}, {cfg.spp}")
