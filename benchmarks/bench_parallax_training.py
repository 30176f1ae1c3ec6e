"""Training step cost of the parallax Triple Plane vs the Triple Plane, side by side in one run.

A ``triple-parallax`` step does what a Triple Plane step does, plus the visible points of the
step's texels: a table lookup, a ray march of the rows the table does not hold (after every
refresh of the learned height), a Newton step and a bilinear fetch with its backward. This
benchmark trains, on the same BTF, with the fast recipe (64 texel groups, view-coherent batches
for the parallax model):

* **triple** -- the Triple Plane;
* **parallax** -- ``triple-parallax`` as ``dynbtf fit`` trains it on the CPU: the visible-point table
  read and its missing rows marched in one compiled loop
  (:func:`~dynbtf.representations.parallax_kernels.visible_texel_points`), the Newton step and the fetch
  there with their backward in compiled loops (:func:`~dynbtf.representations.visible_fetch.fetch_visible`);
* **parallax, torch ops** -- the same model with ``use_compiled_kernels = False``: the table, the Newton
  step and the fetch in torch operations (the same values to float32 rounding), the marches still compiled
  (:func:`~dynbtf.representations.parallax_kernels.march_plane`);
* **parallax, torch ops and march** -- also the march run by the torch loop of
  :func:`~dynbtf.representations.parallax.march_visible_uv`: what any other device runs.

Each variant trains ``--steps`` optimizer steps after ``--warmup`` (the height estimated once
by stereo, as ``dynbtf fit`` does, and given to every parallax variant). Printed: mean ms per
step and each variant's ratio to the Triple Plane.

Run: ``python benchmarks/bench_parallax_training.py`` (about 2 minutes on 2 cores; ``--btf``
any BTF path or spec, e.g. ``'sim:stone?size=64&grid=ubo2014&seed=7'`` for the 64 x 64 default-fit row of
docs/choosing.md).

``--quality`` measures instead what the two forms of the Newton step and fetch do to a fit: the compiled
loops and the torch operations agree to float32 rounding, not bit for bit, and a fit is chaotic, so their
trajectories part as two seeds' do. For each of ``--seeds`` it fits ``parallax`` and ``parallax, torch ops``
for ``--quality-steps`` steps from the same start and prints their held-out PSNR (32 held-out images); the
rows are written to ``benchmarks/results/parallax_quality.json`` (the table in docs/parallax.md).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def step_times(rep, source, steps: int, warmup: int) -> list[float]:
    """Seconds of each of ``steps`` optimizer steps after ``warmup`` of :func:`dynbtf.training.fit`."""
    from dynbtf.training import TrainConfig, fit

    times = []

    class Enough(Exception):
        pass

    def callback(info):
        if info["global_step"] > warmup:
            times.append(info["step_seconds"])
        if len(times) >= steps:
            raise Enough

    config = TrainConfig(epochs=1000, monitor_pairs=0, texel_groups=64, lr_scale=6.0)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            fit(rep, source, config, Path(tmp) / "m.dbtfm", progress=False, callback=callback)
        except Enough:
            pass
    return times


def quality(args, source, parallax_model) -> None:
    """Held-out PSNR after ``args.quality_steps`` steps of the two forms of the fetch, per seed (``--quality``)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_training import held_out_psnr
    from results_io import header, write_result

    from dynbtf.training import ImageStore, TrainConfig, fit, held_out_split
    from dynbtf.training.fit import StopTraining

    store = ImageStore(source)
    store.fill()
    rows = []
    for seed in args.seeds:
        _, held_out = held_out_split(source.n_views, source.n_lights, 0.05, seed)
        eval_pairs = held_out[np.linspace(0, len(held_out) - 1, min(32, len(held_out))).astype(int)]
        row = {"seed": seed, "steps": args.quality_steps}
        for name, compiled in (("compiled", True), ("torch_ops", False)):
            rep = parallax_model(seed)
            rep.use_compiled_kernels = compiled

            def callback(info):
                if info["global_step"] >= args.quality_steps:
                    raise StopTraining("steps")

            config = TrainConfig(epochs=1000, seed=seed, held_out_fraction=0.05, monitor_pairs=0,
                                 checkpoint_every=10 ** 9, texel_groups=64, lr_scale=6.0)
            with tempfile.TemporaryDirectory() as tmp:
                fit(rep, source, config, Path(tmp) / "m.dbtfm", progress=False, callback=callback)
            row[f"{name}_psnr_db"] = held_out_psnr(rep, source, store, eval_pairs)
        rows.append(row)
        print(f"seed {seed}: compiled {row['compiled_psnr_db']:.2f} dB, torch ops {row['torch_ops_psnr_db']:.2f} dB "
              f"after {args.quality_steps} steps", flush=True)
    difference = [r["compiled_psnr_db"] - r["torch_ops_psnr_db"] for r in rows]
    spread = [max(r[f"{k}_psnr_db"] for r in rows) - min(r[f"{k}_psnr_db"] for r in rows)
              for k in ("compiled", "torch_ops")]
    print(f"compiled - torch ops: mean {np.mean(difference):+.2f} dB over {len(rows)} seeds; spread across seeds "
          f"{spread[0]:.2f} dB (compiled), {spread[1]:.2f} dB (torch ops)")
    write_result(Path(__file__).resolve().parent / "results" / "parallax_quality.json",
                 header("parallax_quality", "bench_parallax_training.py") | {"btf": args.btf, "rows": rows})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--btf", default="sim:stone?size=128", help="BTF path or spec (default %(default)s)")
    parser.add_argument("--steps", type=int, default=400, help="timed steps per variant")
    parser.add_argument("--warmup", type=int, default=20, help="untimed steps first")
    parser.add_argument("--quality", action="store_true", help="fit with each form of the fetch over --seeds and "
                                                              "compare held-out PSNR (no timing)")
    parser.add_argument("--quality-steps", type=int, default=600, help="steps per fit of --quality")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds of --quality")
    args = parser.parse_args()

    from dynbtf.data.open import open_btf
    from dynbtf.representations import parallax
    from dynbtf.representations.parallax import ParallaxTriplePlane
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.training.fitters import parallax_size_options
    from dynbtf.training.stereo_height import auto_stereo_options, stereo_height

    source = open_btf(args.btf)
    start = time.perf_counter()
    height = stereo_height(source, **auto_stereo_options(source))
    print(f"{args.btf}: stereo height in {time.perf_counter() - start:.0f} s; {args.steps} steps per variant "
          f"after {args.warmup}, {torch.get_num_threads()} threads")

    def parallax_model(seed=0):
        rep = ParallaxTriplePlane(source.height, source.width, seed=seed, **parallax_size_options(source))
        rep.set_height(height)
        return rep

    if args.quality:
        quality(args, source, parallax_model)
        return

    compiled = parallax.march_plane

    def torch_ops_model():  # the visible-point table and the fetch in torch ops, as any other device runs them
        rep = parallax_model()
        rep.use_compiled_kernels = False
        return rep

    def torch_loop(uv, slope, plane, **march):  # the march of any other device: the torch loop, same rays
        w = torch.nn.functional.normalize(torch.cat([slope, torch.ones_like(slope[:, :1])], dim=-1), dim=-1)
        return parallax.march_visible_uv(uv, w, lambda p: parallax.fetch_wrap(plane[..., None], p)[:, 0], **march)

    rows = []
    for name, make, march in [("triple", lambda: TriplePlane(source.height, source.width), compiled),
                              ("parallax", parallax_model, compiled),
                              ("parallax, torch ops", torch_ops_model, compiled),
                              ("parallax, torch ops and march", torch_ops_model, torch_loop)]:
        parallax.march_plane = march
        try:
            times = step_times(make(), source, args.steps, args.warmup)
        finally:
            parallax.march_plane = compiled
        rows.append((name, 1e3 * float(np.mean(times))))
    print("| variant | ms per step (mean) | vs triple |")
    print("|---|---|---|")
    for name, ms in rows:
        print(f"| {name} | {ms:.1f} | {ms / rows[0][1]:.2f}x |")


if __name__ == "__main__":
    main()
