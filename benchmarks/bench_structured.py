"""Structured materials: every synthesis method side by side on structured and stochastic materials.

For each material (``--materials``: the structured woven_fabric, ceramic_tiles and brick_wall, the stochastic
leather and stone; 128 x 128 simulated BTFs), a fitted Triple Plane is read from ``--models DIR/<material>.dbtfm``
or, when missing, fitted there (``dynbtf fit 'sim:<material>?size=128' --repr triple``, with ``--fit-minutes`` as
the whole command's time budget; the default recipe, until converged, when not given). Then, for each method (tile,
hist, hex, quilt, struct, and what ``auto`` picks, printed with its measurement) and each synthesis seed of
``--seeds`` (three by default; tile draws nothing random and is measured once) it measures:

* **coherence p90 / identity** (:mod:`dynbtf.synthesis.coherence`): the synthesized area at one pixel per
  texel, decoded at view (0, 0) and light (40, 30), ``scale`` repeats on a side (``--scales``, 8 and 25)
  far from the origin (1e6 repeats) -- its central window of at most 1024 x 1024 texels (8 x 8 repeats of
  a 128-texel exemplar; the synthesis is stationary, so a window's patches are distributed as the whole
  area's) -- 256 random 16 x 16 patches against every periodic position of the exemplar decoded the same
  way. Quilting is measured at the first scale only (its plane is generated up front: 25 x 25 repeats of a
  128-texel plane are 655 MB);
* **broken elements** (struct): the share of the elements of an 8 x 8-repeat window whose inner texels read more
  than one of the exemplar's elements (:func:`dynbtf.synthesis.elements.broken_elements`, from struct's joints);
* **repetition** and **RGB W1/std** (max over three (view, light) pairs) from the quality report
  (:func:`dynbtf.synthesis.quality.quality_report`, 8 x 8 repeats, the synthesis at the first scale);
* **cost**: ``SynthesizedBTF.eval`` per query on the same 2^20 random far-away queries, best of
  ``--repeats`` interleaved calls, as a ratio to hist's (seed 0);
* **storage**: the synthesizer's tables over the positional plane's bytes; **build**: the off-line
  construction's seconds (struct's cut tables, cache off).

Each quality number is kept per seed, with the mean over the seeds and their min-max range.
Finally struct's off-line construction on a 400 x 400 x 16 plane (the first structured model's plane
and appearance resampled to 400 x 400).

It writes ``--json`` (default ``benchmarks/results/structured.json``, the data of docs/results.md's table, rendered
by ``benchmarks/tables.py``). With ``--images DIR`` it writes ``structured_<material>.png`` for each structured
material: rows 8x and 25x (the unit uv square far from the origin, 512 px, 3 x 3 samples per pixel), columns
tile | hist | auto.

Run: ``python benchmarks/bench_structured.py --models bench-models [--fit-minutes 5] [--images docs/images]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from results_io import spread  # benchmarks/ is on the path of a script run from it

STRUCTURED = ("woven_fabric", "ceramic_tiles", "brick_wall")
STOCHASTIC = ("leather", "stone")
METHODS = ("tile", "hist", "hex", "quilt", "struct")
FAR = 1e6
#: Largest side of the measured window, texels.
WINDOW = 1024


def ensure_model(folder: Path, material: str, minutes: float | None) -> Path:
    """``folder/<material>.dbtfm``, a Triple Plane of ``sim:<material>?size=128`` fitted (by the dynbtf command,
    ``minutes`` its whole time budget) when missing."""
    model = folder / f"{material}.dbtfm"
    if model.exists():
        return model
    folder.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "dynbtf", "fit", f"sim:{material}?size=128", "-o", str(model), "--repr", "triple"]
    if minutes is not None:
        command += ["--minutes", str(minutes)]
    subprocess.run(command, check=True)
    return model


def coherence(btf, scale: float, seed: int) -> dict:
    """Coherence of the ``scale x scale``-repeat area far from the origin: its central window of at most
    ``WINDOW`` texels (the synthesis is stationary: a window's patches are distributed as the area's)."""
    from dynbtf.synthesis.coherence import synthesized_coherence

    w = int(btf.synthesizer.exemplar.shape[1])
    side = min(WINDOW, int(round(scale * w)))
    corner = FAR + (scale - side / w) / 2  # the window's lower corner, exemplar repeats
    return synthesized_coherence(btf, side=side, origin=(corner + 0.25, corner + 0.5), seed=seed)


def cost_per_query(btfs: dict, repeats: int) -> dict[str, float]:
    """Seconds per query of each SynthesizedBTF's eval on the same far-away queries (best of interleaved calls)."""
    rng = np.random.default_rng(0)
    n = 1 << 20
    uv = FAR + rng.random((n, 2)) * 64.0
    wv = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, 3))
    wl = np.broadcast_to(np.array([0.5, 0.0, np.sqrt(0.75)]), (n, 3))
    best = {name: np.inf for name in btfs}
    for name, btf in btfs.items():
        btf.eval(uv[:4096], wv[:4096], wl[:4096])  # compile / warm up
    for _ in range(repeats):
        for name, btf in btfs.items():
            start = time.perf_counter()
            btf.eval(uv, wv, wl)
            best[name] = min(best[name], (time.perf_counter() - start) / n)
    return best


def far_panel(model: Path, method: str, scale: float, size: int) -> np.ndarray:
    """``(size, size, 3)``: ``model`` synthesized with ``method`` (seed 0) at ``scale``, the unit uv square far from
    the origin (view (0, 0), light (40, 30), 3 x 3 samples per pixel)."""
    from dynbtf.synthesized import synthesized_btf

    btf = synthesized_btf(model, method, scale=scale, seed=0)
    c = FAR / scale
    return btf.image(view=(0.0, 0.0), light=(40.0, 30.0), uv_rect=(c, c, c + 1.0, c + 1.0), resolution=size, spp=3)


def comparison_image(model: Path, material: str, folder: Path, size: int = 512) -> Path:
    """``structured_<material>.png``: rows 8x and 25x, columns tile | hist | auto (:func:`far_panel`)."""
    from dynbtf.io import save_image

    rows = []
    gap = 6
    for scale in (8.0, 25.0):
        panels = []
        for method in ("tile", "hist", "auto"):
            panels += [far_panel(model, method, scale, size), np.ones((size, gap, 3), np.float32)]
        rows += [np.concatenate(panels[:-1], 1), np.ones((gap, 3 * size + 2 * gap, 3), np.float32)]
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"structured_{material}.png"
    save_image(path, np.concatenate(rows[:-1], 0))
    return path



def measure_material(model: Path, material: str, scales: list[float], seeds: list[int], repeats: int
                     ) -> tuple[list[dict], dict]:
    """A row per method: coherence and identity per scale, repetition and RGB W1/std, each per seed (mean, range),
    cost per query against hist's, storage and build time (printed as a table); and auto's choice."""
    from dynbtf.synthesis.elements import broken_elements
    from dynbtf.synthesis.quality import quality_report
    from dynbtf.synthesized import synthesized_btf

    auto = synthesized_btf(model, "auto", scale=scales[0], seed=0)
    choice = auto.synthesizer.choice
    print(f"\n== {material} ({model}): {choice.line}", flush=True)
    plane_bytes = auto.synthesizer.exemplar.numel() * 4
    rows, first = [], {}
    for method in METHODS:
        params = {"repeats": scales[0], "progress": False} if method == "quilt" else {}
        method_seeds = seeds[:1] if method == "tile" else seeds  # tiling draws nothing random
        per_scale: dict[float, list[dict]] = {}
        quality, broken = [], []
        for seed in method_seeds:
            start = time.perf_counter()
            btf = synthesized_btf(model, method, scale=scales[0], seed=seed, **params)
            built = time.perf_counter() - start
            if seed == method_seeds[0]:
                first[method] = (btf, built)
            for scale in scales:
                if method == "quilt" and scale != scales[0]:
                    continue
                b = btf if scale == scales[0] else synthesized_btf(model, method, scale=scale, seed=seed, **params)
                per_scale.setdefault(scale, []).append(coherence(b, scale, seed))
            quality.append(quality_report(btf, repeats=8, seed=seed))
            if method == "struct":
                synth = btf.synthesizer
                broken.append(broken_elements(lambda uv: synth.read_positions(uv)[0], synth.prepared.joints.numpy(),
                                              repeats=scales[0], far=FAR)[0])
        btf, built = first[method]
        measured = sorted(per_scale)
        row = {"material": material, "method": method, "chosen": choice.method == method,
               "seeds": list(method_seeds), "scales": measured,
               "coherence_p90": [spread([r["p90"] for r in per_scale[s]]) for s in measured],
               "identity": [spread([r["identity"] for r in per_scale[s]]) for s in measured],
               "repetition": spread([q["repetition"]["score"] for q in quality]),
               "rgb_w1": spread([q["rgb_w1_over_std_max"] for q in quality]),
               "broken_elements": spread(broken) if broken else None,
               "storage_vs_plane": btf.synthesizer.storage_bytes() / plane_bytes,
               "build_seconds": btf.synthesizer.prepared.build_seconds if method == "struct" else built}
        if measured != sorted(scales):
            row["note"] = " and ".join(f"{s:g}x" for s in measured) + " only"
        if row["chosen"]:
            row["bold"] = ["method", "coherence_p90", "identity"] if method == "struct" else ["method"]
        rows.append(row)
        print(f"   measured {method}", flush=True)
    costs = cost_per_query({m: b for m, (b, _) in first.items() if m != "quilt"}, repeats)
    for row in rows:
        cost = costs.get(row["method"])
        row["cost_vs_hist"] = None if cost is None else cost / costs["hist"]
        row["ns_per_query"] = None if cost is None else cost * 1e9

    def cell(spread: dict) -> str:
        return f"{spread['mean']:.3f} ({spread['range'][0]:.3f}-{spread['range'][1]:.3f})"

    print(f"{'method':<8} " + " ".join(f"{'coh p90 @' + format(s, 'g'):>21} {'ident @' + format(s, 'g'):>21}"
                                       for s in scales)
          + f" {'repetition':>21} {'W1/std RGB':>21} {'cost/hist':>9} {'ns/query':>8} {'storage':>8} {'build s':>8}")
    for row in rows:
        cells = []
        for s in scales:
            if s in row["scales"]:
                k = row["scales"].index(s)
                cells.append(f"{cell(row['coherence_p90'][k]):>21} {cell(row['identity'][k]):>21}")
            else:
                cells.append(f"{'-':>21} {'-':>21}")
        cost = (f"{row['cost_vs_hist']:>9.2f} {row['ns_per_query']:>8.0f}" if row["cost_vs_hist"] is not None
                else f"{'-':>9} {'-':>8}")
        name = row["method"] + ("*" if row["chosen"] else "")
        print(f"{name:<8} " + " ".join(cells) + f" {cell(row['repetition']):>21} {cell(row['rgb_w1']):>21} {cost} "
              f"{row['storage_vs_plane']:>7.2f}x {row['build_seconds']:>8.2f}")
    print("(* = auto's choice; each cell: mean over the seeds (min-max))")
    return rows, {"method": choice.method, "strength": choice.strength, "line": choice.line}


def large_build(model: Path, material: str) -> dict:
    """struct's off-line construction on the model's plane and appearance resampled to 400 x 400 x C."""
    import torch

    from dynbtf.material.compiler import decoded_appearance
    from dynbtf.representations.model_file import load_model
    from dynbtf.synthesis.cell_quilting import build_cell_tables

    rep, _ = load_model(model)
    exemplar = rep.positional_plane().detach()
    plane = exemplar.permute(2, 0, 1)[None]
    guide = decoded_appearance(rep, exemplar).permute(2, 0, 1)[None]  # what struct cuts along (its model input)
    big = torch.nn.functional.interpolate(plane, size=(400, 400), mode="bilinear")[0].permute(1, 2, 0)
    big_guide = torch.nn.functional.interpolate(guide, size=(400, 400), mode="bilinear")[0].permute(1, 2, 0)
    start = time.perf_counter()
    tables = build_cell_tables(big.contiguous(), guide=big_guide.contiguous())
    seconds = time.perf_counter() - start
    channels = int(big.shape[-1])
    ratio = tables.storage_bytes() / (400 * 400 * channels * 4)
    print(f"\nstruct tables at 400 x 400 x {channels}: {seconds:.1f} s, {tables.storage_bytes() / 1e6:.2f} MB "
          f"({ratio:.2f}x the plane)")
    return {"material": material, "method": "struct", "size": [400, 400, channels], "build_seconds": seconds,
            "storage_vs_plane": ratio}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="bench-models", help="folder of <material>.dbtfm (fitted when missing)")
    parser.add_argument("--materials", default=",".join(STRUCTURED + STOCHASTIC))
    parser.add_argument("--fit-minutes", type=float, default=None,
                        help="time budget of each missing fit (the whole dynbtf fit command)")
    parser.add_argument("--scales", default="8,25")
    parser.add_argument("--seeds", type=int, default=3, help="synthesis seeds 0..N-1 (each quality number per seed)")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per method (the best is kept)")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "structured.json",
                        help="where to write every number (the docs' table data)")
    parser.add_argument("--images", default=None, help="folder for structured_<material>.png (tile | hist | auto)")
    args = parser.parse_args()

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, model_record, write_result

    from dynbtf.synthesis.structure import STRUCTURE_THRESHOLD

    scales = [float(s) for s in args.scales.split(",")]
    seeds = list(range(args.seeds))
    materials = [m.strip() for m in args.materials.split(",") if m.strip()]
    rows, choices, models = [], {}, {}
    for material in materials:
        model = ensure_model(Path(args.models), material, args.fit_minutes)
        models[material] = model_record(model)
        material_rows, choices[material] = measure_material(model, material, scales, seeds, args.repeats)
        rows += material_rows
        if args.images and material in STRUCTURED:
            print(f"   wrote {comparison_image(model, material, Path(args.images))}")
    first = next((m for m in materials if m in STRUCTURED), None)
    large = large_build(Path(args.models) / f"{first}.dbtfm", first) if first is not None else None

    fits = (f"a Triple Plane fitted by `dynbtf fit 'sim:<material>?size=128' --repr triple --minutes "
            f"{args.fit_minutes:g}`" if args.fit_minutes is not None else "a Triple Plane fitted by `dynbtf fit "
            "'sim:<material>?size=128' --repr triple` (until converged)")
    psnr = [m["held_out_psnr"] for m in models.values() if m.get("held_out_psnr") is not None]
    fits += f" (held-out PSNR {min(psnr):.1f}-{max(psnr):.1f} dB)" if psnr else ""
    write_result(args.json, header("structured", "bench_structured.py") | {
        "conditions": f"128 x 128 simulated BTFs, each {fits}; synthesized far from the origin at "
                      f"{' and '.join(f'{s:g}x' for s in scales)}, {len(seeds)} synthesis seeds (tile: one, it draws "
                      "nothing random); each quality number the mean over the seeds (min-max); coherence and "
                      "identity at view (0, 0), light (40, 30), repetition and RGB W1/std from the quality report "
                      f"(8 x 8 repeats at {scales[0]:g}x); cost per query in `SynthesizedBTF.eval` relative to "
                      "hist's in the same run (seed 0); storage relative to the positional plane",
        "scales": scales, "seeds": seeds, "structured": [m for m in materials if m in STRUCTURED],
        "structure_threshold": STRUCTURE_THRESHOLD, "models": models, "choices": choices, "rows": rows,
        "large_build": large})


if __name__ == "__main__":
    main()
