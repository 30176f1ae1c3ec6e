"""Held-out PSNR vs training time of `dynbtf fit` (the auto recipe) at 128 x 128 and at full size (400 x 400).

Each run fits a Triple Plane with :func:`dynbtf.training.recipe.auto_recipe` (no time budget:
the full schedule) and scores the held-out monitor (16 held-out pairs, at most 65,536 texels
each; :class:`dynbtf.training.monitor.HeldOutMonitor`) every ``--eval-every`` seconds of
training time (scoring is not counted). It writes ``docs/images/fit_curve_<name>.json`` and
redraws ``docs/images/fit_curves.png`` from every such file present; it prints the final
PSNR and the training time after which the curve stays within 0.5 dB of it.

Run::

    python benchmarks/measure_fit_curves.py --btf 'sim:leather?size=128' --name leather128
    python benchmarks/measure_fit_curves.py --btf /tmp/dynbtf-bench/leather400_c96.btf --name leather400

(the 400 x 400 file: ``dynbtf simulate leather --grid ubo2014 --size 400 -o FILE``, ~4 min;
the fit is about an hour on 2 cores).

``--repr triple-parallax`` fits the parallax Triple Plane (its stereo height first, as
``dynbtf fit``; the stereo's seconds are recorded, not counted as training time);
``--out-dir`` writes the curve elsewhere (the figure is drawn from ``docs/images`` only); ``--model PATH``
keeps the fitted model.
The curve file is rewritten after every score (``"finished": false`` until the end).

``--json FILE --part NAME`` also keeps the finished curve as part ``NAME`` of a results file (docs/results.md's
full-size curve is ``--json benchmarks/results/fullsize.json --part curve``); ``--record CURVE_FILE`` does that for
a curve file written earlier (its own command, commit and machine are kept).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

IMAGES = Path(__file__).resolve().parents[1] / "docs" / "images"


def run(spec: str, name: str, eval_every: float, seed: int, kind: str = "triple", out_dir: Path = IMAGES,
        model: Path | None = None) -> dict:
    """Fit ``kind`` to ``spec`` with the auto recipe, scoring the held-out monitor every ``eval_every`` seconds
    of training; writes and returns the curve (``out_dir / fit_curve_<name>.json``). ``model``: where the fitted
    model goes (with its provenance: the schedule's own held-out checks); default a temporary file."""
    from bench_training_large import build

    from dynbtf.data.open import open_btf
    from dynbtf.training import ImageStore, held_out_split, predict_images
    from dynbtf.training.fit import fit
    from dynbtf.training.monitor import HeldOutMonitor
    from dynbtf.training.recipe import auto_recipe

    source = open_btf(spec)
    recipe = auto_recipe(source, seed=seed)
    print(recipe.summary, flush=True)
    config = recipe.config
    rep, stereo_seconds = build(kind, source, seed)
    print(f"{kind}: stereo height {stereo_seconds:.0f} s", flush=True)
    _, held_out = held_out_split(source.n_views, source.n_lights, config.held_out_fraction, seed)
    monitor = HeldOutMonitor(ImageStore(source, int(config.memory_budget_mb * 1024 ** 2)), held_out, 16, seed)
    curve = [{"seconds": 0.0, "psnr": monitor.score(rep, predict_images), "step": 0}]
    state = {"train_seconds": 0.0, "next": eval_every, "wall": time.perf_counter()}
    from results_io import header

    from dynbtf.cpu import active_isa

    head = {**header("fit_curves", "measure_fit_curves.py"), "isa": active_isa(),
            "name": name, "btf": spec, "repr": kind, "size": [source.height, source.width],
            "directions": [source.n_views, source.n_lights], "recipe": recipe.summary, "curve": curve,
            "stereo_seconds": stereo_seconds}
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    path = Path(out_dir) / f"fit_curve_{name}.json"

    def callback(info):
        state["train_seconds"] += info["step_seconds"]
        state["step"] = info["global_step"]
        if state["train_seconds"] >= state["next"]:
            rep.eval()
            curve.append({"seconds": state["train_seconds"], "psnr": monitor.score(rep, predict_images),
                          "step": info["global_step"]})
            rep.train()
            state["next"] += eval_every
            print(f"{state['train_seconds'] / 60:6.1f} min  step {info['global_step']:6d}  "
                  f"held-out PSNR {curve[-1]['psnr']:.2f} dB  ({info['step_seconds']:.3f} s/step)", flush=True)
            path.write_text(json.dumps(head | {"finished": False, "training_seconds": state["train_seconds"],
                                               "wall_seconds": time.perf_counter() - state["wall"]}, indent=1))

    with tempfile.TemporaryDirectory() as tmp:
        fit(rep, source, config, Path(model) if model else Path(tmp) / "m.dbtfm", progress=False, callback=callback)
    rep.eval()
    curve.append({"seconds": state["train_seconds"], "psnr": monitor.score(rep, predict_images),
                  "step": state.get("step", curve[-1]["step"])})
    final = curve[-1]["psnr"]
    within = next(p["seconds"] for p in curve if all(q["psnr"] >= final - 0.5 for q in curve[curve.index(p):]))
    out = head | {"finished": True, "final_psnr": final, "seconds_to_within_0_5_db": within,
                  "training_seconds": state["train_seconds"], "wall_seconds": time.perf_counter() - state["wall"],
                  "steps": curve[-1]["step"]}
    path.write_text(json.dumps(out, indent=1))
    print(f"{name}: final held-out PSNR {final:.2f} dB after {state['train_seconds'] / 60:.1f} min of training; "
          f"within 0.5 dB of it from {within / 60:.1f} min", flush=True)
    return out


def curve_part(curve: dict, note: str | None = None) -> dict:
    """What a results file keeps of a finished curve file: its command, commit, machine and active instruction-set
    level (``isa``), what was fitted, the scores (``points``: minutes of training, step, held-out PSNR; the start
    left out), the final PSNR, the training minutes (and steps) after which the curve stays within 0.5 dB of it, the mean
    seconds per step, and ``note`` (e.g. what else ran on the machine)."""
    if not curve.get("finished"):
        raise SystemExit(f"measure_fit_curves: the curve {curve.get('name')!r} is not finished (its fit is still "
                         "running, or was stopped): nothing to record")
    if "command" not in curve:
        raise SystemExit(f"measure_fit_curves: the curve {curve.get('name')!r} does not record its command and "
                         "machine (written by an earlier version): measure it again")
    keep = ("command", "commit", "cpu", "cpu_isa", "cores", "isa", "btf", "repr", "size", "directions", "recipe",
            "stereo_seconds")
    return {key: curve[key] for key in keep} | {
        "points": [{"minutes": p["seconds"] / 60, "step": p["step"], "psnr": p["psnr"]} for p in curve["curve"][1:]],
        "final_psnr": curve["final_psnr"], "minutes_to_within_0_5_db": curve["seconds_to_within_0_5_db"] / 60,
        "steps_to_within_0_5_db": next(p["step"] for p in curve["curve"]
                                       if p["seconds"] == curve["seconds_to_within_0_5_db"]),
        "training_minutes": curve["training_seconds"] / 60, "steps": curve["steps"],
        "seconds_per_step": curve["training_seconds"] / curve["steps"]} | ({"note": note} if note else {})


def record(curve: dict, path: Path, part: str, note: str | None = None) -> None:
    """Set part ``part`` of the results file ``path`` (its other parts kept) to :func:`curve_part` of ``curve``."""
    from results_io import write_result

    data = json.loads(path.read_text()) if path.exists() else {"benchmark": path.stem}
    data[part] = curve_part(curve, note)
    write_result(path, data)


def plot() -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [r for r in (json.loads(p.read_text()) for p in sorted(IMAGES.glob("fit_curve_*.json")))
            if r.get("finished", True)]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    for r in runs:
        t = np.array([p["seconds"] for p in r["curve"]]) / 60
        y = np.array([p["psnr"] for p in r["curve"]])
        level = f", {r['isa']}" + (" forced" if r["isa"] != r["cpu_isa"] else "") if "isa" in r else ""
        label = (f"{r.get('repr', 'triple')}, {r['size'][0]} x {r['size'][1]} texels, {r['directions'][0]} x "
                 f"{r['directions'][1]} directions{level} (final {r['final_psnr']:.1f} dB)")
        line, = ax.plot(t, y, marker="o", ms=3, label=label)
        ax.axvline(r["seconds_to_within_0_5_db"] / 60, color=line.get_color(), ls=":", lw=1)
    ax.set_xlabel("training time (minutes, 2 CPU cores)")
    ax.set_ylabel("held-out PSNR (dB, per-image peak)")
    ax.set_title("dynbtf fit, auto recipe (dotted: within 0.5 dB of the final PSNR)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    out = IMAGES / "fit_curves.png"
    fig.savefig(out)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--btf", help="BTF path or spec")
    parser.add_argument("--name", help="name of the curve (file fit_curve_<name>.json)")
    parser.add_argument("--eval-every", type=float, default=120.0, help="seconds of training between scores")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repr", default="triple", choices=["triple", "triple-parallax"],
                        help="the representation (default %(default)s)")
    parser.add_argument("--out-dir", default=str(IMAGES), help="where the curve file goes (default %(default)s)")
    parser.add_argument("--model", default=None, help="keep the fitted model here (default: not kept)")
    parser.add_argument("--plot-only", action="store_true", help="only redraw the figure")
    parser.add_argument("--json", type=Path, default=None, help="also keep the finished curve in this results file")
    parser.add_argument("--part", default="curve", help="its part in --json (default %(default)s)")
    parser.add_argument("--record", type=Path, default=None,
                        help="record this finished curve file in --json (no fit)")
    parser.add_argument("--note", default=None, help="kept with the curve in --json (e.g. what shared the machine)")
    args = parser.parse_args()
    if args.record is not None:
        if args.json is None:
            parser.error("--record needs --json (the results file to keep the curve in)")
        record(json.loads(args.record.read_text()), args.json, args.part, args.note)
        return
    if not args.plot_only:
        if not args.btf or not args.name:
            parser.error("--btf and --name are required (or --plot-only)")
        curve = run(args.btf, args.name, args.eval_every, args.seed, args.repr, Path(args.out_dir), args.model)
        if args.json is not None:
            record(curve, args.json, args.part, args.note)
        if Path(args.out_dir).resolve() != IMAGES:
            return  # the figure shows docs/images' curves
    print(f"wrote {plot()}")


if __name__ == "__main__":
    main()
