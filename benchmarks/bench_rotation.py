"""Quarter-turned samples (``rotation``): what they change in quality and cost, on fitted models.

For each model and setting, three seeds: ``hist``; ``hist`` with ``rotation=True``. Measured by
:func:`dynbtf.synthesis.quality.quality_report` (8 repeats):
the **repetition** score (autocorrelation at the exemplar period and lattice steps; lower: less repetition), the
**RGB W1/std** (decoded colours against the exemplar's, the largest over the report's view/light pairs; lower:
closer), the **orientation coherence** of the decoded luminance under a grazing light (structure-tensor
coherence over the area: 1 for one orientation everywhere, 0 for every one; the exemplar's own is listed), and the
**cost per query** against plain ``hist`` (``SynthesizedBTF.eval`` of 1,048,576 random queries, best of 3,
measured side by side in one run). Writes ``benchmarks/results/rotation.json`` (docs/synthesis.md's table) and,
with ``--images``, ``synthesis_rotation.png``: the first model at 8x under a grazing light, one panel per setting.

Run: ``python benchmarks/bench_rotation.py MODEL.dbtfm [MODEL.dbtfm ...] [--images docs/images]``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

SETTINGS = {"hist": {}, "hist, rotation": {"rotation": True}}
SEEDS = (0, 1, 2)
REPEATS = 8
VIEW, GRAZING = (0.0, 0.0), (65.0, 30.0)
QUERIES = 1 << 20


def orientation_coherence(image: np.ndarray) -> float:
    """Structure-tensor coherence ``sqrt((Jxx - Jyy)^2 + 4 Jxy^2) / (Jxx + Jyy)`` of a grey image's gradients."""
    gy, gx = np.gradient(image.astype(np.float64))
    jxx, jyy, jxy = (gx * gx).sum(), (gy * gy).sum(), (gx * gy).sum()
    return float(math.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2) / max(jxx + jyy, 1e-30))


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def grazing_image(btf, repeats: float, side: int) -> np.ndarray:
    """The decoded luminance of ``repeats`` x ``repeats`` exemplar repeats (``btf`` at scale 1) under the grazing
    light, ``side`` pixels square (far from the origin)."""
    u0 = 1e6
    return luminance(btf.image(view=VIEW, light=GRAZING, uv_rect=(u0, u0, u0 + repeats, u0 + repeats),
                               resolution=side))


def query_cost(btfs: dict, rng: np.random.Generator) -> dict:
    """Seconds per query of each setting's ``eval`` relative to the first, best of 3 each, alternating."""
    uv = torch.from_numpy(rng.random((QUERIES, 2)) * 45.0)
    from dynbtf.conventions import spherical_to_direction

    wv = torch.from_numpy(spherical_to_direction(rng.random(QUERIES) * 80, rng.random(QUERIES) * 360)).float()
    wl = torch.from_numpy(spherical_to_direction(rng.random(QUERIES) * 80, rng.random(QUERIES) * 360)).float()
    best = dict.fromkeys(btfs, float("inf"))
    for btf in btfs.values():
        btf.eval(uv[:50000], wv[:50000], wl[:50000])  # warm-up
    for _ in range(3):
        for name, btf in btfs.items():
            t = time.perf_counter()
            btf.eval(uv, wv, wl)
            best[name] = min(best[name], time.perf_counter() - t)
    first = next(iter(best.values()))
    return {name: t / first for name, t in best.items()}


def main() -> None:
    from dynbtf.io import save_image
    from dynbtf.representations.model_file import load_model
    from dynbtf.synthesis.quality import quality_report
    from dynbtf.synthesized import synthesized_btf
    from results_io import header, model_record, panel_strip, spread, write_result

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", type=Path)
    parser.add_argument("--images", type=Path, help="folder for synthesis_rotation.png")
    parser.add_argument("--json", type=Path, default=Path(__file__).parent / "results" / "rotation.json")
    args = parser.parse_args()
    rows, panels = [], []
    for index, path in enumerate(args.models):
        model, _ = load_model(path)
        name = path.stem
        exemplar_side = int(model.positional_plane().shape[0])
        tiled = synthesized_btf(model, "hist", seed=0).tiled()
        exemplar_coherence = orientation_coherence(grazing_image(tiled, 2.0, 2 * exemplar_side))
        costs = query_cost({s: synthesized_btf(model, "hist", seed=0, **p) for s, p in SETTINGS.items()},
                           np.random.default_rng(0))
        for setting, params in SETTINGS.items():
            measured = {"repetition": [], "rgb_w1": [], "orientation_coherence": []}
            for seed in SEEDS:
                btf = synthesized_btf(model, "hist", seed=seed, **params)
                report = quality_report(btf, repeats=REPEATS)
                measured["repetition"].append(report["repetition"]["score"])
                measured["rgb_w1"].append(report["rgb_w1_over_std_max"])
                measured["orientation_coherence"].append(
                    orientation_coherence(grazing_image(btf, 4.0, 4 * exemplar_side)))
                if index == 0 and seed == 0 and args.images is not None:
                    panels.append(btf.image(view=VIEW, light=GRAZING, uv_rect=(0.0, 0.0, 8.0, 8.0), resolution=384,
                                            spp=2))
            rows.append({"material": name, "setting": setting, "parameters": params,
                         "exemplar_orientation_coherence": exemplar_coherence,
                         "cost_vs_hist": costs[setting], **{k: spread(v) for k, v in measured.items()}})
            print(f"{name:<16} {setting:<40} repetition {np.mean(measured['repetition']):.3f}  RGB W1/std "
                  f"{np.mean(measured['rgb_w1']):.3f}  orientation {np.mean(measured['orientation_coherence']):.3f} "
                  f"(exemplar {exemplar_coherence:.3f})  cost {costs[setting]:.2f}x", flush=True)
    result = header("rotation", "bench_rotation.py") | {
        "seeds": list(SEEDS), "repeats": REPEATS, "light": list(GRAZING), "queries": QUERIES,
        "models": [model_record(p) for p in args.models], "rows": rows}
    write_result(args.json, result)
    if panels:
        strip = panel_strip(panels)
        args.images.mkdir(parents=True, exist_ok=True)
        save_image(args.images / "synthesis_rotation.png", strip / max(float(np.percentile(strip, 99.5)), 1e-6))
        print(f"wrote {args.images / 'synthesis_rotation.png'}")


if __name__ == "__main__":
    main()
