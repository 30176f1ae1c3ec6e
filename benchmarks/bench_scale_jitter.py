"""Scaled samples (``scale_jitter``): what they change in quality and cost, and why they need the sub-texel term.

A scaled sample reads the feature plane between texel centres everywhere, where a model fitted without the
sub-texel term decodes drifted colours (docs/triple_plane.md, "Between texel centres"). So each material is measured
with two fits of the same BTF: without the term (``--subtexel 0``) and with it (``--subtexel 0.25``, the default
recipe's weight). Give them as pairs ``NAME=WITHOUT.dbtfm,WITH.dbtfm``.

For each model and setting (``hist``; ``hist`` with each ``--jitters`` value), three synthesis seeds, measured by
:func:`dynbtf.synthesis.quality.quality_report` (8 repeats, its area sampled on the output's texel grid):

* the **repetition** score (autocorrelation at the exemplar period and the lattice steps; lower: less repetition);
* the **RGB W1/std** of the decoded colours against the exemplar's (the largest over the report's view/light pairs;
  lower: closer);
* the **mean ratio**: the decoded area's mean colour over plain ``hist``'s at the same seed (the mean over
  channels; the one farthest from 1 over the report's pairs): how much darker or brighter the scales make it;
* the **cost per query** against plain ``hist`` (``SynthesizedBTF.eval`` of 1,048,576 random queries, best of 3,
  side by side in one run).

Writes ``benchmarks/results/scale_jitter.json`` (docs/synthesis.md's table) and, with ``--images``,
``synthesis_scale_jitter.png``: the first material at 6 x 6 repeats, view along the normal, light at 40 degrees:
hist | hist with the largest jitter (model with the term) | the same without the term.

Run: ``python benchmarks/bench_scale_jitter.py stone=A.dbtfm,B.dbtfm leather=C.dbtfm,D.dbtfm
[--jitters 0.25,0.5] [--images docs/images]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

SEEDS = (0, 1, 2)
REPEATS = 8
IMAGE_REPEATS, IMAGE_SIDE = 6.0, 384
VIEW, LIGHT = (0.0, 0.0), (40.0, 0.0)


def mean_colours(btf, pairs) -> np.ndarray:
    """``(pairs, 3)``: the mean decoded colour of 4 x 4 repeats far from the origin under each (view, light) pair."""
    u0 = 1e5
    return np.array([btf.image(view=v, light=lt, uv_rect=(u0, u0, u0 + 4.0, u0 + 4.0), resolution=256)
                     .reshape(-1, 3).mean(0) for v, lt in pairs], dtype=np.float64)


def farthest_from_one(ratios: np.ndarray) -> float:
    flat = np.asarray(ratios, dtype=np.float64).ravel()
    return float(flat[np.argmax(np.abs(flat - 1.0))])


def parse_pair(text: str) -> tuple[str, Path, Path]:
    try:
        name, paths = text.split("=", 1)
        without, with_term = paths.split(",")
    except ValueError:
        raise SystemExit(f"expected NAME=WITHOUT.dbtfm,WITH.dbtfm, got {text!r}") from None
    return name, Path(without), Path(with_term)


def main() -> None:
    from bench_rotation import query_cost
    from results_io import header, model_record, panel_strip, spread, write_result

    from dynbtf.io import save_image
    from dynbtf.representations.model_file import load_model
    from dynbtf.synthesis.quality import DEFAULT_PAIRS, quality_report
    from dynbtf.synthesized import synthesized_btf

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("materials", nargs="+", type=parse_pair)
    parser.add_argument("--jitters", default="0.25,0.5")
    parser.add_argument("--images", type=Path, help="folder for synthesis_scale_jitter.png")
    parser.add_argument("--json", type=Path, default=Path(__file__).parent / "results" / "scale_jitter.json")
    args = parser.parse_args()
    jitters = [float(j) for j in args.jitters.split(",")]
    settings = {"hist": {}} | {f"hist, scale jitter {j:g}": {"scale_jitter": j} for j in jitters}
    rows, panels, models = [], {}, []
    for index, (name, without, with_term) in enumerate(args.materials):
        for term, path in (("without", without), ("with", with_term)):
            model, _ = load_model(path)
            models.append(model_record(path))
            costs = query_cost({s: synthesized_btf(model, "hist", seed=0, **p) for s, p in settings.items()},
                               np.random.default_rng(0)) if term == "with" else {}
            plain_means = {}
            for setting, params in settings.items():
                measured = {"repetition": [], "rgb_w1": [], "mean_ratio": []}
                for seed in SEEDS:
                    btf = synthesized_btf(model, "hist", seed=seed, **params)
                    report = quality_report(btf, repeats=REPEATS)
                    measured["repetition"].append(report["repetition"]["score"])
                    measured["rgb_w1"].append(report["rgb_w1_over_std_max"])
                    means = mean_colours(btf, DEFAULT_PAIRS)
                    if not params:
                        plain_means[seed] = means
                    measured["mean_ratio"].append(farthest_from_one(means / plain_means[seed]))
                    if index == 0 and seed == 0 and args.images is not None and (
                            not params and term == "with" or params.get("scale_jitter") == max(jitters)):
                        panels[(term, setting)] = btf.image(view=VIEW, light=LIGHT, uv_rect=(
                            0.0, 0.0, IMAGE_REPEATS, IMAGE_REPEATS), resolution=IMAGE_SIDE, spp=2)
                row = {"material": name, "subtexel_term": term, "model": path.name, "setting": setting,
                       "parameters": params, **{k: spread(v) for k, v in measured.items()}}
                if costs:
                    row["cost_vs_hist"] = costs[setting]
                rows.append(row)
                print(f"{name:<14} {term:<8} {setting:<26} repetition {np.mean(measured['repetition']):.4f}  "
                      f"RGB W1/std {np.mean(measured['rgb_w1']):.3f}  mean ratio {np.mean(measured['mean_ratio']):.3f}"
                      + (f"  cost {costs[setting]:.2f}x" if costs else ""), flush=True)
    result = header("scale_jitter", "bench_scale_jitter.py") | {
        "seeds": list(SEEDS), "repeats": REPEATS, "jitters": jitters, "models": models, "rows": rows}
    write_result(args.json, result)
    if panels:
        top = f"hist, scale jitter {max(jitters):g}"
        order = [("with", "hist"), ("with", top), ("without", top)]
        images = [panels[key] for key in order if key in panels]
        strip = panel_strip(images)
        args.images.mkdir(parents=True, exist_ok=True)
        save_image(args.images / "synthesis_scale_jitter.png", strip / max(float(np.percentile(strip, 99.5)), 1e-6))
        print(f"wrote {args.images / 'synthesis_scale_jitter.png'}")


if __name__ == "__main__":
    main()
