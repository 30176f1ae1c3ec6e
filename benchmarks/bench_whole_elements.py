"""Whole elements: does ``struct`` keep every brick of a running bond whole, on brick walls dynbtf has never seen?

The bricks (:func:`held_out_bricks`) are made here, not by the library's simulator materials: a running bond of
``4 x 8`` bricks per repeat (whole texels at 64 texels: 16 x 8) and one of ``3 x 6`` (21.33 x 10.67 texels: the
bricks' period is not whole texels), each brick of its own colour and brightness between two clays, in a
light recessed mortar, rendered by the library's height-field simulator on the UBO2003 grid at 64 x 64. Each is
fitted (a Triple Plane, ``--fit-minutes`` each, or read from ``--models DIR/<name>.dbtfm``), then synthesized far
from the origin (1e6 repeats) with, for three seeds each:

* ``struct``: cells meeting along seams that may run along a row (:func:`dynbtf.synthesis.quilting.min_error_seam`),
  pay the copies' spread (:func:`dynbtf.synthesis.cell_quilting.copy_spread`) and pay for every texel off the
  joints (:func:`dynbtf.synthesis.cell_quilting.joint_crossing`);
* ``struct, no crossing cost``: the same seams without the crossing cost;
* ``struct, straight cuts``: the same cells with the first seam rule, one column per row at most
  (:func:`~dynbtf.synthesis.quilting.min_error_cut`), no spread and no crossing cost: what ``struct`` was before
  whole elements;
* ``struct, --texels whole``: ``struct`` on the wall fitted at the size at which its bricks are whole texels
  (``dynbtf fit --texels whole``: 66 x 66 for the ``3 x 6`` bond; the ``4 x 8`` bond keeps its 64 x 64);
* ``hist``: the paper's method, for scale.

Measured: the share of **broken bricks** (bricks of an 8 x 8-repeat window, of the known geometry, whose texels
at least one texel inside the brick read more than one source brick: a two-tone brick, a sliver), the **patch
coherence p90** and **identity with tiling** (:mod:`dynbtf.synthesis.coherence`, as ``bench_structured.py``: 8
repeats, 16-texel patches). Targets (issue "synthesis the artist steers"): coherence p90 at most 0.10 with
identity at most 0.35.

Run: ``python benchmarks/bench_whole_elements.py [--models DIR] [--fit-minutes 3] [--images docs/images]`` (about
4 minutes per fit, then a minute per material; ``--images``: ``whole_elements.png``, a row per wall, tile | struct |
struct on the wall fitted with ``--texels whole``). Writes ``benchmarks/results/whole_elements.json``
(docs/synthesis.md's table).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: name -> (bricks per course, courses per repeat, joint width in uv, the two clays' colours)
BRICKS = {"bond_whole_texels": (4, 8, 0.022, ([0.22, 0.20, 0.25], [0.45, 0.30, 0.20])),
          "bond_third_texels": (3, 6, 0.024, ([0.50, 0.18, 0.10], [0.35, 0.30, 0.22]))}
SIZE = 64
SEEDS = (0, 1, 2)
#: The row of ``struct`` on the wall fitted with ``dynbtf fit --texels whole``.
WHOLE_LABEL = "struct, --texels whole"
#: The row of ``struct`` whose seams do not pay for crossing elements (what ``struct`` was before they did).
NO_CROSSING_LABEL = "struct, no crossing cost"
SCALE = 8.0
FAR = 1e6


def held_out_bricks(name: str):
    """The simulator's material builder of brick wall ``name`` of :data:`BRICKS` (registered by :func:`register`)."""
    from dynbtf.data.simulator import materials as m

    n_u, n_v, joint, (clay_a, clay_b) = BRICKS[name]

    def build(grid: int, seed: int):
        u, v = m.grid_uv(grid)
        course = np.floor(v * n_v).astype(int)
        along = u * n_u + 0.5 * (course % 2)  # running bond: odd courses shifted half a brick
        column = np.floor(along).astype(int)
        fa, fb = along - column, v * n_v - course
        chip = m.fourier_noise(grid, m.derive_rng(seed, name + "/chip"), k_min=10, k_max=40, slope=0.6)
        border = np.minimum(np.minimum(fa, 1 - fa) / n_u, np.minimum(fb, 1 - fb) / n_v)  # uv distance to the joint
        face = m.smoothstep(-0.002, 0.008, border - joint / 2 + 0.0015 * chip)  # 0: mortar, 1: brick face
        each = m.derive_rng(seed, name + "/bricks").random((n_v, n_u, 4))[course % n_v, column % n_u]
        grain = m.fourier_noise(grid, m.derive_rng(seed, name + "/grain"), k_min=16, k_max=64, slope=0.4)
        height = -0.012 * (1 - face) + face * (0.002 * (each[..., 0] - 0.5) + 0.0006 * grain)
        brick = (m._lerp(clay_a, clay_b, each[..., 1]) * (0.8 + 0.4 * each[..., 2])[..., None]
                 * (1 + 0.12 * np.tanh(grain))[..., None])
        albedo = m._lerp(np.array([0.62, 0.60, 0.55]), brick, face)
        return m._finish(height, albedo, 0.8 - 0.2 * face * each[..., 3], 0.04)

    return build


def register() -> None:
    """Make the held-out brick walls openable as ``sim:<name>`` in this process (they are not library materials)."""
    from dynbtf.data.simulator import materials as m

    for name in BRICKS:
        m.MATERIAL_BUILDERS[name] = held_out_bricks(name)
        m.MATERIALS[name] = "held-out running-bond brick wall (benchmarks/bench_whole_elements.py)"


def brick_of(name: str, x: np.ndarray, y: np.ndarray, size: int):
    """The brick ``(course, column)`` (ints, any repeat) of texel-space points ``(x, y)`` of a ``size``-texel
    repeat, and whether each lies at least one texel inside its brick's face (away from the joint and its worn
    edge)."""
    n_u, n_v, joint, _ = BRICKS[name]
    u, v = x / size, y / size
    course = np.floor(v * n_v).astype(np.int64)
    along = u * n_u + 0.5 * (course % 2)
    column = np.floor(along).astype(np.int64)
    fa, fb = along - column, v * n_v - course
    border = np.minimum(np.minimum(fa, 1 - fa) / n_u, np.minimum(fb, 1 - fb) / n_v)
    return course, column, border > joint / 2 + 0.008 + 1.0 / size


def broken_bricks(name: str, btf) -> float:
    """Share of the bricks of an ``SCALE x SCALE``-repeat window far from the origin whose inner texels read more than
    one source brick (the synthesizer's torch reference read positions)."""
    import torch

    n_u, n_v, _, _ = BRICKS[name]
    size = int(btf.synthesizer.exemplar.shape[1])  # square walls: 64, or 66 when resampled
    side = int(SCALE * size)
    gy, gx = np.mgrid[0:side, 0:side].reshape(2, -1) + 0.5
    uv = torch.from_numpy(np.stack([FAR + gx / size, FAR + gy / size], -1))
    read, _ = btf.synthesizer.read_positions(uv)
    course, column, inner = brick_of(name, gx, gy, size)
    src_course, src_column, src_inner = brick_of(name, read[:, 0].numpy(), read[:, 1].numpy(), size)
    keep = inner & src_inner
    target = course[keep] * (4 * side) + column[keep]
    source = (src_course[keep] % n_v) * n_u + src_column[keep] % n_u
    pairs = np.unique(np.stack([target, source]), axis=1)
    sources_per_brick = np.unique(pairs[0], return_counts=True)[1]
    return float((sources_per_brick > 1).mean())


def fit_model(name: str, folder: Path, minutes: float, texels: str | None = None) -> Path | None:
    """``folder/<name>.dbtfm`` (``<name>_whole.dbtfm`` with ``texels="whole"``), fitted here (a Triple Plane, the
    auto recipe within ``minutes``) when missing, to the wall resampled as ``dynbtf fit --texels`` would; None when
    ``texels`` leaves the wall's size as it is (its model is the plain one)."""
    from dynbtf.data.open import open_btf
    from dynbtf.training import get_fitter
    from dynbtf.training.exemplar_texels import resample_for_fit
    from dynbtf.training.recipe import choose_config

    path = folder / (f"{name}_{texels}.dbtfm" if texels else f"{name}.dbtfm")
    source, sentence = resample_for_fit(open_btf(f"sim:{name}?size={SIZE}"), texels)
    if sentence:
        print(sentence, file=sys.stderr)
    if texels and source.height == SIZE and source.width == SIZE:
        return None
    if not path.exists():
        folder.mkdir(parents=True, exist_ok=True)
        config, summary = choose_config(source, path, recipe="auto", minutes=minutes)
        print(summary, file=sys.stderr)
        get_fitter("triple")(source, path, config, progress=sys.stderr.isatty())
    return path


def measure(name: str, model: Path, whole: Path | None) -> list[dict]:
    """A row per method on ``model`` (and ``struct`` on ``whole``, the wall fitted with ``--texels whole``, where
    that resampled it): each measure per seed, with mean and range."""
    from bench_structured import coherence
    from results_io import model_record, spread

    from dynbtf.synthesis import cell_quilting
    from dynbtf.synthesis.quilting import min_error_cut, min_error_seam
    from dynbtf.synthesized import synthesized_btf

    rows = []
    library = cell_quilting.min_error_seam, cell_quilting.SPREAD_WEIGHT, cell_quilting.CROSSING_WEIGHT
    spread_weight = cell_quilting.SPREAD_WEIGHT
    runs = [("struct", "struct", None, model), (NO_CROSSING_LABEL, "struct", "no crossing", model),
            ("struct, straight cuts", "struct", "straight", model), ("hist", "hist", None, model)]
    if whole is not None:
        runs.insert(1, (WHOLE_LABEL, "struct", None, whole))
    for label, method, rule, fitted in runs:
        per_seed = {"broken_bricks": [], "coherence_p90": [], "identity": []}
        for seed in SEEDS:
            rules = {"straight": (min_error_cut, 0.0, 0.0), "no crossing": (min_error_seam, spread_weight, 0.0)}
            if rule is not None:  # an earlier seam rule (the material cache is off: see main)
                cell_quilting.min_error_seam, cell_quilting.SPREAD_WEIGHT, cell_quilting.CROSSING_WEIGHT = rules[rule]
            try:
                btf = synthesized_btf(fitted, method, seed=seed)
            finally:
                cell_quilting.min_error_seam, cell_quilting.SPREAD_WEIGHT, cell_quilting.CROSSING_WEIGHT = library
            if method == "struct":
                per_seed["broken_bricks"].append(broken_bricks(name, btf))
            r = coherence(btf, SCALE, seed)
            per_seed["coherence_p90"].append(float(r["p90"]))
            per_seed["identity"].append(float(r["identity"]))
        row = {"material": name, "method": label, "model": model_record(fitted)}
        row.update({key: spread(values) if values else None for key, values in per_seed.items()})
        rows.append(row)
        print(f"{name:<18} {label:<22} " + "  ".join(f"{k} {row[k]['mean']:.3f}" for k in per_seed if row[k]),
              file=sys.stderr, flush=True)
    return rows


def comparison_image(models: dict, folder: Path, size: int = 512, scale: float = 4.0) -> Path:
    """``whole_elements.png``: a row per wall, columns tile | struct | struct on the wall fitted with ``--texels
    whole`` (where it was resampled), ``scale x scale`` repeats far from the origin (view (0, 0), light (40, 30))."""
    from bench_structured import far_panel

    from dynbtf.io import save_image

    gap, rows = 6, []
    for name, (model, whole) in models.items():
        panels = []
        for fitted, method in ((model, "tile"), (model, "struct"), (whole, "struct")):
            image = np.ones((size, size, 3), np.float32) if fitted is None else far_panel(fitted, method, scale, size)
            panels += [image, np.ones((size, gap, 3), np.float32)]
        rows += [np.concatenate(panels[:-1], 1), np.ones((gap, 3 * size + 2 * gap, 3), np.float32)]
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "whole_elements.png"
    save_image(path, np.concatenate(rows[:-1], 0))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", type=Path, default=None, help="folder of the fitted walls (default: a temporary "
                                                                   "one, fitted here)")
    parser.add_argument("--fit-minutes", type=float, default=3.0, help="time budget of each fit (default 3)")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "whole_elements.json")
    parser.add_argument("--images", type=Path, default=None, help="folder for whole_elements.png (a row per wall: "
                                                                   "tile | struct | struct, --texels whole)")
    args = parser.parse_args()
    os.environ["DYNBTF_COMPILED_CACHE"] = "off"  # every material built here, with the seam rule it names
    from results_io import header, write_result

    register()
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.models or Path(scratch)
        rows, models = [], {}
        for name in BRICKS:
            models[name] = (fit_model(name, folder, args.fit_minutes),
                            fit_model(name, folder, args.fit_minutes, texels="whole"))
            rows += measure(name, *models[name])
        if args.images is not None:
            print(f"wrote {comparison_image(models, args.images)}", file=sys.stderr)
    result = header("whole_elements", "bench_whole_elements.py") | {
        "size": SIZE, "scale": SCALE, "seeds": list(SEEDS), "bricks": {k: v[:3] for k, v in BRICKS.items()},
        "rows": rows}
    from tables import whole_elements

    print("\n" + whole_elements(result))
    write_result(args.json, result)


if __name__ == "__main__":
    main()
