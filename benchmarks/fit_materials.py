"""Fit a Triple Plane (or another kind) to every simulated material and report held-out PSNR / DSSIM / FLIP.

Run: ``python benchmarks/fit_materials.py [--repr triple] [--size 128] [--epochs 30] [--lr-scale 6]
[--texel-groups 64] [--out DIR]`` (about 3-4 minutes per material on 2 cores with the native bf16
kernel; ~7 with ``--repr triple-parallax``), or on any BTFs:
``--specs 'sim:stone?relief=0.25,sim:stone?relief=0.5'``.

``--converge`` fits ``--repr`` as ``dynbtf fit BTF --repr KIND -o MODEL`` does (the auto recipe's
converge schedule). ``--default`` fits as ``dynbtf fit BTF -o MODEL`` with no options does (``--repr auto``: the
stereo estimate, then unless it decides a trial of each kind, the winner's fit continued; the auto recipe: until the
held-out monitor stops improving), and adds the chosen kind, the stereo's trusted fraction, the trial scores and the
whole command's wall time (stereo and trials included) to each row ("vs earlier default" needs the Triple Plane's
trial: "-" where the stereo decided alone).
With ``--seeds N`` each material is fitted with seeds 0..N-1; ``--json FILE`` writes the rows (each number's mean
and min-max over the seeds) as one part of FILE: ``python benchmarks/fit_materials.py --materials
stone,leather,lacquered_wood,woven_fabric --seeds 3 --precision bf16 --json benchmarks/results/quality.json`` makes
docs/results.md's Triple Plane quality table; ``--default --seeds 3 --specs ... --json
benchmarks/results/fit_default.json`` writes docs/choosing.md's table of what ``dynbtf fit`` chooses (a row per BTF,
each run kept per seed).
Each material is fitted with :func:`dynbtf.training.fit` (resumable: re-running
with the same ``--out`` continues unfinished fits), evaluated on its held-out
pairs with :func:`dynbtf.training.evaluate.evaluate_model` (tables and
side-by-side PNGs in ``DIR/<material>_eval``), and one table row is printed per
material with the training time and epochs reached.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import time
from pathlib import Path

from dynbtf.data.open import open_btf
from dynbtf.data.simulator import MATERIALS
from dynbtf.representations.model_file import load_model
from dynbtf.training import TrainConfig, get_fitter
from dynbtf.training.evaluate import evaluate_model, resolve_eval_pairs
from dynbtf.training.images import held_out_split
from dynbtf.training.recipe import auto_recipe, choose_config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repr", default="triple", help="representation kind (triple, triple-parallax, neumip, ...)")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--minutes", type=float, default=None, help="training time budget per material")
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--lr-scale", type=float, default=6.0)
    parser.add_argument("--texel-groups", type=int, default=64, help="1: the paper's whole-image batches")
    parser.add_argument("--materials", default=",".join(MATERIALS))
    parser.add_argument("--specs", default=None, help="comma-separated BTF specs or files (instead of --materials)")
    parser.add_argument("--out", default="materials_out")
    parser.add_argument("--default", action="store_true", help="fit as `dynbtf fit BTF -o M` with no options "
                        "(--repr auto, the auto recipe); --repr, --epochs, --lr-scale, --texel-groups are ignored")
    parser.add_argument("--converge", action="store_true", help="fit --repr as `dynbtf fit BTF --repr KIND -o M` "
                        "does (the auto recipe: until the held-out monitor stops improving); --epochs, --lr-scale, "
                        "--texel-groups are ignored")
    parser.add_argument("--seeds", type=int, default=1, help="fit each material with seeds 0..N-1 (the training "
                        "seed: initialization, batches and the held-out split)")
    parser.add_argument("--precision", default=None, help="training precision (fp32, bf16; default: the recipe's)")
    parser.add_argument("--json", type=Path, default=None, help="write the rows (each number's mean and min-max "
                        "over the seeds) as part --part of this JSON file (e.g. benchmarks/results/quality.json, "
                        "docs/results.md's quality tables); its other parts are kept. With --default: the whole file "
                        "(benchmarks/results/fit_default.json)")
    parser.add_argument("--part", default=None, help="the part of --json (default: the kind, '-' written '_')")
    parser.add_argument("--note", default=None, help="a condition of the run that --json's part states after the "
                        "others (e.g. that other work shared the machine, so the fit minutes are longer)")
    args = parser.parse_args()
    out = Path(args.out)
    rows = []
    specs = args.specs.split(",") if args.specs else [f"sim:{m}?size={args.size}" for m in args.materials.split(",")]
    for spec, seed in ((spec, seed) for spec in specs for seed in range(args.seeds)):
        source = open_btf(spec)
        material = re.sub(r"[^A-Za-z0-9_.-]+", "_", spec.replace("sim:", "")).strip("_")
        model = out / (f"{material}.dbtfm" if seed == 0 else f"{material}_seed{seed}.dbtfm")
        start = time.perf_counter()
        precision = {} if args.precision is None else {"precision": args.precision}
        if args.default or args.converge:
            out.mkdir(parents=True, exist_ok=True)
            config, summary = choose_config(source, model, recipe="auto", minutes=args.minutes, seed=seed,
                                            **precision)
            print(summary)
            get_fitter("auto" if args.default else args.repr)(source, model, config)
        else:
            config = TrainConfig(epochs=args.epochs, max_minutes=args.minutes, lr_scale=args.lr_scale,
                                 texel_groups=args.texel_groups, seed=seed, **precision)
            get_fitter(args.repr)(source, model, config)
        wall = time.perf_counter() - start
        rep, meta = load_model(model)
        ev = evaluate_model(rep, source, resolve_eval_pairs("held-out", source, meta), out_dir=out / f"{material}_eval",
                            images=4)
        prov = meta["provenance"]
        by_angle = ev.by_angle or {}
        rows.append({"material": material, "seed": seed, "spec": spec, **ev.mean,
                     "psnr_grazing": by_angle.get("grazing", {}).get("psnr", float("nan")),
                     "psnr_others": by_angle.get("others", {}).get("psnr", float("nan")),
                     "n_grazing": by_angle.get("grazing", {}).get("n", 0), "epochs": prov["epochs_completed"],
                     "minutes": prov["training_seconds"] / 60, "model_bytes": prov["size"]["model_bytes"],
                     "kind": meta["kind"], "steps": prov.get("schedule", {}).get("steps"),
                     "stopped": prov.get("schedule", {}).get("stopped"), "wall_minutes": wall / 60,
                     "trials": {k: t["held_out_psnr"] for k, t in
                                prov.get("representation_choice", {}).get("trials", {}).items()},
                     "stereo_trusted": prov.get("representation_choice", {}).get("stereo_trusted"),
                     "today_minutes": earlier_default_minutes(source, prov) if args.default else None})
        print(json.dumps(rows[-1]))
    print(f"\n{'dynbtf fit with no options' if args.default else args.repr}: held-out pairs; PSNR against each "
          "reference image's peak (psnr), and against a fixed peak of 1.0 (psnr_fixed1, the earlier definition); "
          "grazing = view or light beyond 60 degrees; wall = the whole fit call (trials, stereo, training)")
    print("| material | kind | PSNR (dB) | grazing / other pairs | PSNR fixed peak 1 | DSSIM | FLIP | epochs | "
          "training min | wall min | vs earlier default |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        today = f"{r['wall_minutes'] / r['today_minutes']:.2f}x" if r.get("today_minutes") else "-"
        print(f"| {r['material']} | {r['kind']} | {r['psnr']:.2f} | {r['psnr_grazing']:.2f} / {r['psnr_others']:.2f} | "
              f"{r['psnr_fixed1']:.2f} | {r['dssim']:.4f} | {r['flip']:.4f} | {r['epochs']:.2f} | {r['minutes']:.1f} | "
              f"{r['wall_minutes']:.1f} | {today} |")
    if args.json is not None and args.default:
        write_default(args.json, rows, args)
    elif args.json is not None:
        write_part(args.json, args.part or args.repr.replace("-", "_"), rows, args)


#: The kind of each simulated material, as the quality tables name it.
MATERIAL_NOTES = {"stone": "stochastic, deep relief", "leather": "stochastic", "lacquered_wood": "glossy",
                  "woven_fabric": "structured", "ceramic_tiles": "structured", "brick_wall": "structured"}
#: The numbers of a quality row, each kept per seed with its mean and min-max.
QUALITY_KEYS = ("psnr", "psnr_grazing", "psnr_others", "psnr_fixed1", "dssim", "flip")


def write_part(path: Path, part: str, rows: list[dict], args) -> None:
    """Part ``part`` of the JSON file ``path`` (created, or its other parts kept): the command and machine, and a row
    per material with each number of :data:`QUALITY_KEYS` and the fit's minutes as ``{"mean", "range",
    "per_seed"}`` over the seeds."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import spread
    from results_io import write_part as write_json_part

    seeds = sorted({r["seed"] for r in rows})
    table = []
    for material in dict.fromkeys(r["material"] for r in rows):
        mine = [r for r in rows if r["material"] == material]
        name = material.split("_size")[0] if material.startswith(tuple(MATERIAL_NOTES)) else material
        entry = {"material": name.replace("_", " "), "note": MATERIAL_NOTES.get(name), "spec": mine[0]["spec"]}
        for key, values in [(k, [r[k] for r in mine]) for k in QUALITY_KEYS] + [("fit_minutes",
                                                                                  [r["minutes"] for r in mine])]:
            entry[key] = spread(values)
        table.append(entry)
    write_json_part(path, part, "fit_materials.py", {
        "seeds": seeds, "conditions": f"{args.size} x {args.size} simulated BTFs; "
        + (f"{args.epochs} epochs, learning rates x{args.lr_scale:g}, {args.texel_groups} texel groups"
           if not (args.default or args.converge) else "the auto recipe")
        + (f", precision {args.precision}" if args.precision else "") + "; each number the mean over the seeds "
        "(min-max); the held-out split is the seed's" + (f"; {args.note}" if args.note else ""), "rows": table})


def write_default(path: Path, rows: list[dict], args) -> None:
    """``--default --json``: the whole file ``path`` (benchmarks/results/fit_default.json, docs/choosing.md's table):
    the command and machine, and a row per BTF with what ``dynbtf fit`` chose and did under each seed. Per seed
    (``per_seed`` lists, in seed order): the chosen kind, the trial scores (``trials``: kind -> held-out PSNR, empty
    where the stereo decided alone), the stereo's trusted fraction, the stop (``stopped``) and the steps; held-out
    PSNR, FLIP, wall minutes and their ratio to the earlier default's (``vs_earlier``, where a Triple Plane trial
    gives it) as ``{"mean", "range", "per_seed"}``."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, spread, write_result

    table = []
    for spec in dict.fromkeys(r["spec"] for r in rows):
        mine = [r for r in rows if r["spec"] == spec]
        ratios = [r["wall_minutes"] / r["today_minutes"] for r in mine if r.get("today_minutes")]
        table.append({"spec": spec, "chosen": [r["kind"] for r in mine], "trials": [r["trials"] for r in mine],
                      "stereo_trusted": [r["stereo_trusted"] for r in mine], "stopped": [r["stopped"] for r in mine],
                      "steps": [r["steps"] for r in mine], "psnr": spread([r["psnr"] for r in mine]),
                      "flip": spread([r["flip"] for r in mine]),
                      "wall_minutes": spread([r["wall_minutes"] for r in mine]),
                      "vs_earlier": spread(ratios) if ratios else None})
    write_result(path, header(path.stem, "fit_materials.py") | {
        "seeds": sorted({r["seed"] for r in rows}),
        "conditions": "dynbtf fit with no options (--repr auto, the auto recipe), seeded; held-out PSNR (per-image "
        "peak) and FLIP over all held-out pairs; wall minutes of the whole fit call (stereo and trials included); "
        "vs_earlier: divided by the earlier default's time (--repr triple, the reference's step count) at the "
        "Triple Plane trial's speed" + (f"; {args.note}" if args.note else ""), "rows": table})


def earlier_default_minutes(source, provenance: dict) -> float | None:
    """The earlier default's wall minutes (``--repr triple``, a fixed schedule of the reference's step count) at this
    run's speed: the Triple Plane trial's seconds (its set-up, image decoding included, and first steps) plus the
    rest of that schedule's steps at the trial's seconds per step. None without a Triple Plane trial."""
    trial = provenance.get("representation_choice", {}).get("trials", {}).get("triple")
    if not trial or "seconds_per_step" not in trial:
        return None
    earlier = auto_recipe(source, schedule="epochs").config
    steps_per_epoch = math.ceil(len(held_out_split(source.n_views, source.n_lights, earlier.held_out_fraction,
                                                   earlier.seed)[0]) / earlier.images_per_step)
    steps = earlier.epochs * steps_per_epoch
    return (trial["seconds"] + max(steps - trial["steps"], 0) * trial["seconds_per_step"]) / 60


if __name__ == "__main__":
    main()
