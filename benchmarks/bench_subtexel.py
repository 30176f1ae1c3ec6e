"""The sub-texel term (``dynbtf fit --subtexel W``): what it buys between texel centres and costs at them.

For each BTF of ``--specs`` and each seed, a Triple Plane is fitted without the term and with each weight of
``--weights`` (the fast recipe: ``--epochs`` epochs, learning rates x3, 64 texel groups, the CPU's fastest training
precision), and measured:

* **held-out PSNR** against a fixed peak of 1, and FLIP, at texel centres (:func:`dynbtf.training.evaluate.
  evaluate_model` on the held-out pairs: what every quality table reports);
* between texel centres, half a texel off in both directions (the worst place): the **RGB W1/std** against the
  centres' colours and the **mean ratio** (:mod:`measure_between_texels`), beside the W1/std of the centres'
  own bilinear mix, the floor a model whose colours between centres were that mix would reach;
* the **training minutes** (the model file's; fits of one run side by side: the ratio is what to read; a model
  already finished in ``--out`` is read, not fitted again).

Run: ``python benchmarks/bench_subtexel.py [--specs 'sim:leather?size=64'] [--weights 0.5] [--seeds 3]
[--epochs 15] [--out DIR] [--images docs/images]`` (about a minute per fit of a 64 x 64 BTF on 2 cores). Writes
``benchmarks/results/subtexel.json`` (docs/triple_plane.md's table) and, with ``--images``,
``subtexel_closeup.png``: the seed-0 fits of the BTF whose fits without the term drift most, one per weight (0
first), each over 12 x 12 texels at 32 pixels per texel.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))

#: Where the between-texel numbers are read: half a texel off in both directions.
OFFSET = (0.5, 0.5)


def fit_and_measure(spec: str, weight: float, seed: int, epochs: int, folder: Path) -> dict:
    """One fit of ``spec`` with sub-texel weight ``weight`` (0: off) and seed ``seed``, and its measurements."""
    from measure_between_texels import measure
    from results_io import model_record

    from dynbtf.data.open import open_btf
    from dynbtf.representations.model_file import load_model
    from dynbtf.training import TrainConfig, get_fitter
    from dynbtf.training.evaluate import evaluate_model, resolve_eval_pairs
    from dynbtf.cpu import active_isa

    source = open_btf(spec)
    name = "".join(c if c.isalnum() else "_" for c in spec)
    model = folder / f"{name}_w{weight:g}_s{seed}.dbtfm"
    precision = "bf16" if active_isa() == "avx512bf16" else "fp32"  # the CPU's fastest training kernel
    config = TrainConfig(epochs=epochs, lr_scale=3.0, lr_decay=0.9 ** (30 / epochs), texel_groups=64, seed=seed,
                         precision=precision, subtexel=weight)
    get_fitter("triple")(source, model, config, progress=sys.stderr.isatty())  # a finished fit in --out: read
    rep, meta = load_model(model)
    minutes = meta["provenance"]["training_seconds"] / 60
    evaluation = evaluate_model(rep, source, resolve_eval_pairs("held-out", source, meta), images=0, progress=False)
    between = measure(model, [OFFSET])[0]
    row = {"spec": spec, "weight": weight, "seed": seed, "precision": precision, "model": model_record(model),
           "psnr_fixed1": evaluation.mean["psnr_fixed1"], "flip": evaluation.mean["flip"],
           "between_rgb_w1": between["rgb_w1"], "between_mean_ratio": between["mean_ratio"],
           "centres_mix_rgb_w1": between["centres_mix_rgb_w1"], "training_minutes": minutes, "model_path": model}
    print(f"{spec} weight {weight:g} seed {seed}: {row['psnr_fixed1']:.2f} dB, between W1/std "
          f"{row['between_rgb_w1']:.3f} (mix {row['centres_mix_rgb_w1']:.3f}), mean ratio "
          f"{row['between_mean_ratio']:.3f}, {minutes:.1f} min", file=sys.stderr, flush=True)
    return row


def closeups(models: list[Path], folder: Path) -> Path:
    """``subtexel_closeup.png``: :func:`measure_between_texels.closeup` of each model side by side (one BTF's fits
    of seed 0, one per weight, 0 first)."""
    from measure_between_texels import closeup
    from results_io import panel_strip

    from dynbtf.io import load_image, save_image

    with tempfile.TemporaryDirectory() as scratch:
        panels = [load_image(closeup(model, Path(scratch) / str(k))) for k, model in enumerate(models)]
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "subtexel_closeup.png"
    save_image(path, panel_strip(panels, gap=8))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--specs", default="sim:leather?size=64", help="BTFs, comma-separated")
    parser.add_argument("--weights", default="0.5", help="sub-texel weights to compare with 0, comma-separated")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--epochs", type=int, default=15)
    parser.add_argument("--out", type=Path, default=None, help="folder for the models (default: a temporary one)")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "subtexel.json")
    parser.add_argument("--images", type=Path, default=None, help="folder for subtexel_closeup.png")
    args = parser.parse_args()
    try:
        weights = [0.0] + [float(w) for w in args.weights.split(",") if w.strip()]
    except ValueError:
        parser.error(f"--weights: expected numbers separated by commas, got {args.weights!r}")
    from results_io import header, spread, write_result

    with tempfile.TemporaryDirectory() as scratch:
        folder = args.out or Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        runs = [fit_and_measure(spec.strip(), weight, seed, args.epochs, folder)
                for spec in args.specs.split(",") if spec.strip() for seed in range(args.seeds) for weight in weights]
        if args.images is not None and runs:  # the BTF whose fits without the term drift most between centres
            plain = [r for r in runs if r["weight"] == 0]
            shown = max(dict.fromkeys(r["spec"] for r in plain),
                        key=lambda spec: sum(r["between_rgb_w1"] for r in plain if r["spec"] == spec))
            models = [r["model_path"] for r in runs if r["seed"] == 0 and r["spec"] == shown]
            print(f"wrote {closeups(models, args.images)} ({shown})", file=sys.stderr)
    for run in runs:
        del run["model_path"]
    keys = ("psnr_fixed1", "flip", "between_rgb_w1", "between_mean_ratio", "centres_mix_rgb_w1", "training_minutes")
    rows = []
    for spec in dict.fromkeys(r["spec"] for r in runs):
        for weight in weights:
            mine = [r for r in runs if r["spec"] == spec and r["weight"] == weight]
            rows.append({"spec": spec, "weight": weight, **{k: spread([r[k] for r in mine]) for k in keys}})
    result = header("subtexel", "bench_subtexel.py") | {
        "epochs": args.epochs, "seeds": list(range(args.seeds)), "offset_texels": list(OFFSET),
        "precision": runs[0]["precision"] if runs else None, "rows": rows, "runs": runs}
    from tables import subtexel

    print("\n" + subtexel(result))
    write_result(args.json, result)


if __name__ == "__main__":
    main()
