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
  step and the fetch in torch operations (the same values, bit for bit on x86), the marches still compiled
  (:func:`~dynbtf.representations.parallax_kernels.march_plane`);
* **parallax, torch ops and march** -- also the march run by the torch loop of
  :func:`~dynbtf.representations.parallax.march_visible_uv`: what any other device runs.

Each variant trains ``--steps`` optimizer steps after ``--warmup`` (the height estimated once
by stereo, as ``dynbtf fit`` does, and given to every parallax variant). Printed: mean ms per
step and each variant's ratio to the Triple Plane.

Run: ``python benchmarks/bench_parallax_training.py`` (about 2 minutes on 2 cores; ``--btf``
any BTF path or spec, e.g. ``'sim:stone?size=64&grid=ubo2014&seed=7'`` for the 64 x 64 default-fit row of
docs/choosing.md).
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--btf", default="sim:stone?size=128", help="BTF path or spec (default %(default)s)")
    parser.add_argument("--steps", type=int, default=400, help="timed steps per variant")
    parser.add_argument("--warmup", type=int, default=20, help="untimed steps first")
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

    def parallax_model():
        rep = ParallaxTriplePlane(source.height, source.width, **parallax_size_options(source))
        rep.set_height(height)
        return rep

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
