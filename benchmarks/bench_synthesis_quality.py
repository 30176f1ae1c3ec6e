"""The synthesis quality table of docs/synthesis.md: the quality report of each method on one fitted model.

For each method -- tile, linear, hist (the default exponent), hist with gamma 1, hex and quilt (``--quilt-repeats``
repeats quilted up front) -- and each synthesis seed of ``--seeds`` (three by default; tile draws nothing random and
is measured once) it builds the synthesized BTF at ``--scale`` and measures it with the library's quality report
(:func:`dynbtf.synthesis.quality.quality_report`, ``--repeats`` x ``--repeats`` exemplar repeats at texel centres,
the report's sub-sampling seeded with the synthesis seed): feature W1/std (mean and max over the channels), sliced
W1/std, the smallest std ratio, RGB W1/std (max over three (view, light) pairs), repetition and verbatim texels.
Each number is kept per seed, with the mean over the seeds and their min-max range; the extra storage is the
synthesizer's tables (seed 0).

It writes ``--json`` (default ``benchmarks/results/synthesis_quality.json``, the data of docs/synthesis.md's table
and results.md's summary, rendered by ``benchmarks/tables.py``) and prints the table.

Run: ``python benchmarks/bench_synthesis_quality.py stone.dbtfm [--fit-minutes 3]`` (e.g. a 128 x 128 Triple Plane
of ``sim:stone?size=128``; ``--fit-minutes`` or ``--fitted-by COMMAND`` only records how it was fitted). The
baselines' structured comparison (docs/baselines.md) is the same measurement of a lacquered-wood model at 15x:
``--scale 15 --quilt-repeats 8 --fitted-by '...' --json benchmarks/results/synthesis_quality_wood.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from results_io import spread  # benchmarks/ is on the path of a script run from it

#: (label, method, parameters, note): the table's rows.
ROWS = (("tile", "tile", {}, None), ("linear", "linear", {}, None), ("hist", "hist", {}, "default"),
        ("hist, gamma 1", "hist", {"gamma": 1.0}, None), ("hex", "hex", {}, None), ("quilt", "quilt", {}, None))
#: The quality numbers of a row, each from one report.
NUMBERS = {"feature_w1_mean": lambda r: r["feature_w1_over_std_mean"],
           "feature_w1_max": lambda r: r["feature_w1_over_std_max"],
           "sliced_w1": lambda r: r["feature_sliced_w1_over_std"],
           "std_ratio_min": lambda r: min(r["feature_std_ratio"]),
           "rgb_w1_max": lambda r: r["rgb_w1_over_std_max"],
           "repetition": lambda r: r["repetition"]["score"],
           "verbatim": lambda r: r["verbatim_fraction"]}



def measure(model: Path, scale: float, seeds: list[int], repeats: int, quilt_repeats: float) -> list[dict]:
    """A row per method: each quality number per seed (mean, min-max), the extra storage and the seconds taken."""
    from dynbtf.synthesis.quality import quality_report
    from dynbtf.synthesized import synthesized_btf

    rows = []
    for label, method, params, note in ROWS:
        params = dict(params)
        if method == "quilt":
            params |= {"repeats": quilt_repeats, "progress": False}
        method_seeds = seeds[:1] if method == "tile" else seeds  # tiling draws nothing random
        reports, storage, parameters = [], None, None
        start = time.perf_counter()
        for seed in method_seeds:
            btf = synthesized_btf(model, method, scale=scale, seed=seed, **params)
            report = quality_report(btf, repeats=repeats, seed=seed)
            if storage is None:
                storage, parameters = report["synthesizer_storage_bytes"], report.get("parameters") or {}
            reports.append(report)
            del btf
        row = {"method": label, "synthesizer": method, "seeds": list(method_seeds),
               **{key: spread([get(r) for r in reports]) for key, get in NUMBERS.items()},
               "extra_storage_mb": storage / 1e6, "seconds": time.perf_counter() - start}
        if method == "hist" and not params:
            row["gamma"] = parameters.get("gamma")
            row["note"] = f"gamma {row['gamma']:g}" if row.get("gamma") is not None else None
            row["default"] = True
        if method == "quilt":
            row["note"] = f"{quilt_repeats:g}x"
        rows.append(row)
        print(f"   measured {label} ({row['seconds']:.0f} s)", flush=True)
    _bold(rows)
    return rows


def _bold(rows: list[dict]) -> None:
    """Tiling's repetition (what the others remove), and the default method's name and every number in which it is
    the best of the non-tiling rows (lowest; highest for the std ratio; verbatim is neither)."""
    rows[0]["bold"] = ["repetition"]
    default = next(r for r in rows if r.get("default"))
    others = [r for r in rows if r["synthesizer"] != "tile"]
    bold = ["method"]
    for key in ("feature_w1_mean", "sliced_w1", "std_ratio_min", "rgb_w1_max", "repetition"):
        pick = max if key == "std_ratio_min" else min
        best = pick(round(r[key]["mean"], 3 if key in ("std_ratio_min", "rgb_w1_max", "repetition") else 4)
                    for r in others)
        mine = round(default[key]["mean"], 3 if key in ("std_ratio_min", "rgb_w1_max", "repetition") else 4)
        if mine == best:
            bold.append(key)
    default["bold"] = bold


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path, help="a fitted model file (.dbtfm)")
    parser.add_argument("--scale", type=float, default=8.0, help="exemplar repeats per unit uv")
    parser.add_argument("--seeds", type=int, default=3, help="synthesis seeds 0..N-1 (each quality number per seed)")
    parser.add_argument("--repeats", type=int, default=8, help="side of the measured area, exemplar repeats")
    parser.add_argument("--quilt-repeats", type=float, default=4.0, help="repeats quilted up front (quilt's row)")
    parser.add_argument("--fit-minutes", type=float, default=None,
                        help="for the record: the model was fitted by `dynbtf fit SOURCE --repr KIND --minutes M`")
    parser.add_argument("--fitted-by", default=None,
                        help="for the record: the command that fitted the model (instead of --fit-minutes)")
    parser.add_argument("--json", type=Path,
                        default=Path(__file__).resolve().parent / "results" / "synthesis_quality.json",
                        help="where to write every number (the docs' table data)")
    args = parser.parse_args()

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import header, model_record, write_result

    seeds = list(range(args.seeds))
    record = model_record(args.model)
    rows = measure(args.model, args.scale, seeds, args.repeats, args.quilt_repeats)

    def cell(spread: dict, spec: str) -> str:
        return f"{format(spread['mean'], spec)} ({format(spread['range'][0], spec)}-{format(spread['range'][1], spec)})"

    print(f"{'method':<14} {'W1/std feat mean':>26} {'max':>26} {'sliced':>26} {'std ratio min':>23} "
          f"{'W1/std RGB max':>23} {'repetition':>23} {'verbatim':>23} {'storage':>9}")
    for r in rows:
        print(f"{r['method']:<14} {cell(r['feature_w1_mean'], '.4f'):>26} {cell(r['feature_w1_max'], '.4f'):>26} "
              f"{cell(r['sliced_w1'], '.4f'):>26} {cell(r['std_ratio_min'], '.3f'):>23} "
              f"{cell(r['rgb_w1_max'], '.3f'):>23} {cell(r['repetition'], '.3f'):>23} "
              f"{cell(r['verbatim'], '.3f'):>23} {r['extra_storage_mb']:>7.2f}MB")
    fitted = f"fitted by `{args.fitted_by}`: " if args.fitted_by else ""
    if args.fit_minutes is not None and not args.fitted_by:
        source = record["source"] + (f"?size={record['size'][0]}" if record.get("size") else "")
        fitted = f"fitted by `dynbtf fit '{source}' --repr {record['kind']} --minutes {args.fit_minutes:g}`: "
    size = f"{record['size'][0]} x {record['size'][1]} " if record.get("size") else ""
    conditions = (f"model: a {size}`{record['kind']}` of `{record['source']}` {fitted}"
                  f"{record['epochs']:.1f} epochs in {record['training_minutes']:.1f} min, held-out "
                  f"{record['held_out_psnr']:.1f} dB; synthesized at {args.scale:g}x, {len(seeds)} synthesis seeds "
                  "(tile: one, it draws nothing random), each number the mean over the seeds (min-max); "
                  f"the quality report over {args.repeats} x {args.repeats} exemplar repeats; quilt quilts "
                  f"{args.quilt_repeats:g} x {args.quilt_repeats:g} repeats up front; extra storage: seed 0's tables")
    result = {**header("synthesis_quality", "bench_synthesis_quality.py"), "conditions": conditions,
              "model": record, "scale": args.scale, "seeds": seeds, "repeats": args.repeats,
              "quilt_repeats": args.quilt_repeats, "rows": rows}
    write_result(args.json, result)


if __name__ == "__main__":
    main()
