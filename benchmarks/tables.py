"""The measured tables of docs/, generated from the benchmarks' JSON results (``benchmarks/results/*.json``).

A table in a document is the text between ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->``; this module
renders table ``NAME`` from ``benchmarks/results/NAME.json`` (written by the benchmark that measured it) and
writes it there. Run: ``python benchmarks/tables.py`` (after a benchmark run) to rewrite every table,
``python benchmarks/tables.py --check`` to list the tables that disagree with their data (exit status 1);
``tests/test_docs_tables.py`` runs the check, so a table is never re-typed by hand.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _machine(data: dict) -> str:
    return f"{data['cpu']} ({data['cores']} cores, best level {data['cpu_isa']})"


def training(data: dict) -> str:
    """bench_training.py: a row per (level, BTF, variant)."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({data['seconds_per_variant']:g} s of training "
             "per row).", "",
             "| level | BTF | recipe | M samples/s | x naive | GFLOP/s | share of the level's FMA peak |",
             "|---|---|---|---|---|---|---|"]
    for r in data["rows"]:
        share = r.get("share_of_fma_peak")
        lines.append(
            f"| {r['isa']} | `{r['btf']}` | {r['variant']} | {r['samples_per_second'] / 1e6:.2f} | "
            + (f"**{r['ratio_to_naive']:.1f}x**" if "ratio_to_naive" in r else "1x") + " | "
            + (f"{r['gflops']:.0f}" if "gflops" in r else "") + " | "
            + (f"{100 * share:.0f}% of {r['fma_peak_gflops']:.0f} GFLOP/s" if share is not None else "") + " |")
    return "\n".join(lines)


def budget(data: dict) -> str:
    """bench_budget.py: ``dynbtf fit --minutes M`` wall times per representation choice."""
    lines = [f"Measured on {_machine(data)}, level {data['isa']}, by `{data['command']}` on `{data['btf']}`.", "",
             "| --repr | --minutes | wall (min) | of the budget | model written | chosen | held-out PSNR (dB) |",
             "|---|---|---|---|---|---|---|"]
    for r in data["rows"]:
        lines.append(f"| {r['repr']} | {r['minutes']:g} | {r['wall_seconds'] / 60:.2f} | "
                     f"{100 * r['wall_seconds'] / (60 * r['minutes']):.0f}% | {'yes' if r['written'] else 'no'} | "
                     f"{r.get('kind', '')} | "
                     + (f"{r['held_out_psnr']:.2f}" if r.get("held_out_psnr") is not None else "") + " |")
    return "\n".join(lines)


def evaluation(data: dict) -> str:
    """bench_synthesis_eval.py: queries/s per level and method, share of the FMA bound."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({data['queries']:,} queries, a 1080p frame).",
             "", "| level | method | naive M queries/s | ours M queries/s | x naive | share of the FMA bound |",
             "|---|---|---|---|---|---|"]
    for r in data["rows"]:
        lines.append(f"| {r['isa']} | {r['method']} | {r['naive_qps'] / 1e6:.2f} | {r['ours_qps'] / 1e6:.2f} | "
                     f"{r['ours_qps'] / r['naive_qps']:.1f}x | {100 * r['share_of_fma_bound']:.1f}% of "
                     f"{r['fma_peak_gflops']:.0f} GFLOP/s |")
    return "\n".join(lines)


def gpu(data: dict) -> str:
    """gpu_check.py on a GPU machine."""
    rows = [f"Measured on {data['device_name']} (torch {data['torch']}) by `{data['command']}`.", "",
            "| what | result |", "|---|---|"]
    if "training" in data:
        t = data["training"]
        rows.append(f"| training, fast recipe, `{t['btf']}` | {t['samples_per_second'] / 1e6:.1f} M samples/s "
                    f"({t['ms_per_step']:.2f} ms per step) |")
    if "full_size_fit" in data:
        f = data["full_size_fit"]
        rows.append(f"| full-size fit, `{f['btf']}`, `--minutes {f['minutes_budget']:g}` | within 0.5 dB of its best "
                    f"({f['best_held_out_psnr']:.2f} dB) after {f['seconds_to_within_half_db'] / 60:.1f} min; "
                    f"{f['steps']} steps ({f['stopped']}) |")
    if "evaluation" in data:
        e = data["evaluation"]
        rows.append(f"| 1080p evaluation, hist | {1e3 * e['seconds']:.0f} ms ({e['queries_per_second'] / 1e6:.1f} M "
                    "queries/s) |")
    return "\n".join(rows)


def guided(data: dict) -> str:
    """bench_guided.py: a layered material's region statistics, band width and cost per query, per seed."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}`: `{data['layers'][0]}` | `{data['layers'][1]}`, "
             f"hist at {data['scale']:g} repeats per uv unit, a half-plane mask; cost over {data['queries']:,} "
             "queries.", "",
             "| seed | W1/std left / right, whole halves | W1/std left / right, outside the band | band half-width "
             "left / right (of `width`) | cost away from the band | cost in the band |", "|---|---|---|---|---|---|"]
    for r in data["rows"]:
        lines.append(f"| {r['seed']} | {r['w1_left']:.3f} / {r['w1_right']:.3f} | {r['w1_left_outside_band']:.3f} / "
                     f"{r['w1_right_outside_band']:.3f} | {r['band_left'] / r['width']:.2f} / "
                     f"{r['band_right'] / r['width']:.2f} | {r['cost_away']:.2f}x | {r['cost_band']:.2f}x |")
    return "\n".join(lines)


RENDERERS = {"training": training, "budget": budget, "evaluation": evaluation, "gpu": gpu, "guided": guided}
_BLOCK = re.compile(r"<!-- table:(?P<name>[a-z_]+) -->\n(?P<body>.*?)\n?<!-- /table:(?P=name) -->", re.S)


def render(name: str) -> str:
    return RENDERERS[name](json.loads((RESULTS / f"{name}.json").read_text()))


def update(check: bool) -> list[str]:
    """Rewrite (or, with ``check``, compare) every table block in the docs; the ``path: name`` of each that
    differs from its data."""
    stale = []
    for path in DOCS:
        text = path.read_text()

        def replace(match):
            body = render(match["name"])
            if body != match["body"]:
                stale.append(f"{path.relative_to(ROOT)}: {match['name']}")
            return f"<!-- table:{match['name']} -->\n{body}\n<!-- /table:{match['name']} -->"

        new = _BLOCK.sub(replace, text)
        if not check and new != text:
            path.write_text(new)
    return stale


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="only list the tables that disagree with their data")
    args = parser.parse_args()
    stale = update(args.check)
    for line in stale:
        print(("out of date: " if args.check else "rewrote: ") + line)
    sys.exit(1 if args.check and stale else 0)


if __name__ == "__main__":
    main()
