"""The measured tables of docs/, generated from the benchmarks' JSON results (``benchmarks/results/*.json``).

A table in a document is the text between ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->``; this module
renders table ``NAME`` from ``benchmarks/results/NAME.json`` (written by the benchmark that measured it) and
writes it there. ``speed.json`` (docs/results.md's Speed summary) is not a benchmark's output: it lists the
summary's rows, each rendered from its benchmark's JSON or, where that benchmark writes none yet, from a
measurement recorded in the file (its numbers, command and machine as the hand-typed table stated them). A part
of a benchmark's file may be such a recorded measurement too (``"recorded_from"``) until the benchmark is re-run
(``rendering.json``, from ``bench_render.py``).

Run: ``python benchmarks/tables.py`` (after a benchmark run) to rewrite every table,
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
    drjit = any(r.get("drjit_qps") for r in data["rows"])
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({data['queries']:,} queries, a 1080p frame).",
             "", "| level | method | naive M queries/s | ours M queries/s | x naive | share of the FMA bound |"
             + (" Dr.Jit kernel M queries/s (x ours) |" if drjit else ""),
             "|---|---|---|---|---|---|" + ("---|" if drjit else "")]
    for r in data["rows"]:
        extra = ""
        if drjit:
            extra = (f" {r['drjit_qps'] / 1e6:.2f} ({r['drjit_qps'] / r['ours_qps']:.2f}x) |" if r.get("drjit_qps")
                     else " |")
        lines.append(f"| {r['isa']} | {r['method']} | {r['naive_qps'] / 1e6:.2f} | {r['ours_qps'] / 1e6:.2f} | "
                     f"{r['ours_qps'] / r['naive_qps']:.1f}x | {100 * r['share_of_fma_bound']:.1f}% of "
                     f"{r['fma_peak_gflops']:.0f} GFLOP/s |{extra}")
    b = data.get("breakdown")
    if b:
        shares = "; ".join(f"{name} {100 * share:.0f}%" for name, share in b["stages"].items())
        lines += ["", f"Where one hist query's time goes on one thread (`{b['isa']}`, "
                      f"{b['queries_per_second_one_thread'] / 1e6:.2f} M queries/s): {shares}."]
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


def guidance(data: dict) -> str:
    """bench_guided.py's guidance part: content on target, repetition against hist's, cost, per seed."""
    g = data["guidance"]
    lines = [f"Measured on {_machine(data)} by `{data['command']}`: `{g['model']}` in {g['classes']} classes, a "
             f"target asking for class 0 on the left half and class 1 on the right half of {g['repeats']} x "
             f"{g['repeats']} exemplar repeats, one query per texel.", "",
             "| seed | points on target (left / right) | repetition score guided / hist (left; right) | "
             "repetition, guided over hist | synthesis cost per query, guided over hist |", "|---|---|---|---|---|"]
    for r in g["rows"]:
        lines.append(f"| {r['seed']} | {100 * r['on_target']:.2f}% ({100 * r['on_target_left']:.2f}% / "
                     f"{100 * r['on_target_right']:.2f}%) | {r['repetition_guided'][0]:.4f} / "
                     f"{r['repetition_hist'][0]:.4f}; {r['repetition_guided'][1]:.4f} / {r['repetition_hist'][1]:.4f} | "
                     f"{r['repetition_ratio']:.2f}x | {r['cost_vs_hist']:.1f}x |")
    return "\n".join(lines)


def parallax_quality(data: dict) -> str:
    """bench_parallax_training.py --quality: held-out PSNR of the two forms of the visible-point fetch, per seed."""
    rows = data["rows"]
    lines = [f"Measured on {_machine(data)} by `{data['command']}` (`{data['btf']}`, {rows[0]['steps']} steps per fit).",
             "", "| seed | compiled loops (dB) | torch operations (dB) | difference (dB) |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['compiled_psnr_db']:.2f} | {r['torch_ops_psnr_db']:.2f} | "
                     f"{r['compiled_psnr_db'] - r['torch_ops_psnr_db']:+.2f} |")
    mean = sum(r["compiled_psnr_db"] - r["torch_ops_psnr_db"] for r in rows) / len(rows)
    lines.append(f"| mean | | | {mean:+.2f} |")
    return "\n".join(lines)


def _load(name: str) -> dict:
    return json.loads((RESULTS / f"{name}.json").read_text())


def _sci(x: float, decimals: int = 1) -> str:
    """``6.2e-4`` (``decimals`` decimals, no zero-padded exponent)."""
    return re.sub(r"e([+-])0*(\d)", lambda m: f"e{m[1].lstrip('+')}{m[2]}", f"{x:.{decimals}e}")


def _stated_machine(record: dict) -> str:
    """The machine of a recorded measurement, as far as its text stated it."""
    parts = [record["cpu"] or "CPU not recorded"] if record.get("cpu") or record.get("cores") else []
    if record.get("cores"):
        parts.append(f"{record['cores']} cores")
    if record.get("cpu_isa"):
        parts.append(f"level {record['cpu_isa']}")
    return ", ".join(parts) or "machine not recorded"


def _source(record: dict, file: str) -> str:
    """Where a part's numbers come from: a benchmark run (its machine) or a recorded measurement."""
    if record.get("recorded_from"):
        return f"*recorded*: {_stated_machine(record)} (`{file}`)"
    return f"`{file}`: {_machine(record)}"  # the commit stays in the data: docs carry no hashes


def _speed_training(row: dict, data: dict) -> tuple[str, str, str]:
    fast = [r for r in data["rows"] if r["variant"] == row["recipe"]]
    btfs = list(dict.fromkeys(r["btf"] for r in fast))
    own = data["cpu_isa"]
    naive = {(r["isa"], r["btf"]): r for r in data["rows"] if r["variant"] == "naive"}

    def ratio(r):
        text = f"{r['ratio_to_naive']:.1f}x ({r['isa']}"
        if r["isa"] == own:
            text = "**" + text.replace(" (", "** (", 1) + (f", {r['samples_per_second'] / 1e6:.2f} vs "
                                                           f"{naive[own, r['btf']]['samples_per_second'] / 1e6:.2f} "
                                                           "M samples/s")
        return text + ")"

    result = "; ".join(f"`{btf}`: " + ", ".join(ratio(r) for r in fast if r["btf"] == btf) for btf in btfs)
    bf16 = [r for r in data["rows"] if r["variant"] == f"{row['recipe']}, bf16"]
    if bf16:
        result += "; with bfloat16 products " + ", ".join(f"{r['ratio_to_naive']:.1f}x" for r in bf16)
    misses = [f"`{r['btf']}` on {r['isa']} ({r['ratio_to_naive']:.1f}x)" for r in fast
              if r["isa"] in row["targets"] and r["ratio_to_naive"] < row["targets"][r["isa"]]]
    target = (f"{row['recipe']} recipe: at least " + ", ".join(f"{x:g}x on {isa}" for isa, x in row["targets"].items())
              + f" ({row['target_source']}'s targets): " + ("met" if not misses else "met except " + ", ".join(misses)))
    what = (f"training, ours ({row['recipe']} recipe) vs the paper's recipe run naively, samples/s per level "
            f"(`{data['command']}`; [per level](#training-speed))")
    return what, result, target


def _speed_evaluation(row: dict, data: dict) -> tuple[str, str, str]:
    method, own = row["method"], data["cpu_isa"]
    rows = [r for r in data["rows"] if r["method"] == method]
    rows.sort(key=lambda r: r["isa"] != own)

    def ratio(r):
        x = r["ours_qps"] / r["naive_qps"]
        if r["isa"] == own:
            return (f"**{x:.1f}x** ({r['isa']}, ours {r['ours_qps'] / 1e6:.2f} vs {r['naive_qps'] / 1e6:.2f} "
                    "M queries/s)")
        return f"{x:.1f}x ({r['isa']})"

    others = [r for r in data["rows"] if r["method"] != method and r["isa"] == own]
    result = ", ".join(ratio(r) for r in rows) + ("; " + ", ".join(
        f"{r['method']} {r['ours_qps'] / r['naive_qps']:.1f}x" for r in others) + f" on {own}" if others else "")
    misses = [f"{r['isa']} ({r['ours_qps'] / r['naive_qps']:.1f}x)" for r in rows
              if r["ours_qps"] / r["naive_qps"] < row["target_ratio"]]
    target = f"{row['target_ratio']:g}x for `{method}` (" + (
        "met on every level" if not misses else "missed on " + ", ".join(misses)) + ")"
    frame = " (a 1080p frame)" if data["queries"] == 1920 * 1080 else ""
    what = (f"{data['queries']:,} queries{frame}, `{method}` synthesis, ours vs naive PyTorch "
            f"(`{data['command']}`; [per level](#synthesis-evaluation-speed))")
    return what, result, target


def _speed_rendering(row: dict, data: dict) -> tuple[str, str, str]:
    part = data[row["part"]]
    if row["part"] == "eval":
        plugin, fp32 = part["plugin_queries_per_second"], part["eval_queries_per_second"]["fp32"]
        what = (f"Mitsuba plugin kernel vs `SynthesizedBTF.eval`, the same {part['queries']:,} queries "
                f"(`{part['command']}`)")
        result = (f"{plugin / 1e6:.1f} vs {fp32 / 1e6:.1f} M queries/s ({plugin / fp32:.1f}x), max difference "
                  f"{_sci(part['max_abs_difference'])} on values up to {part['max_abs_value']:.1f}")
        return what, result, row["target"]
    ns = part["ns_per_query"]
    ratio = {order: v["parallax"] / v["flat"] for order, v in ns.items()}
    met = part["max_abs_difference_to_eval"] <= row["max_difference_of_range"] * part["eval_value_range"]
    what = f"the parallax march in the Mitsuba plugin (`{part['command']}`, {part['relief_texels']:g} texels of relief)"
    result = (f"{ratio['sorted by view elevation']:.1f}x the flat kernel's cost per query with queries sorted by view "
              f"elevation, {ratio['random order']:.1f}x in random order; max difference to `SynthesizedBTF.eval` "
              f"{_sci(part['max_abs_difference_to_eval'])} on a range of {part['eval_value_range']:.1f}")
    target = f"matches to {_sci(row['max_difference_of_range'], 0)} of the range ({'met' if met else 'missed'}; tested)"
    return what, result, target


_SPEED_FROM = {"training": _speed_training, "evaluation": _speed_evaluation, "rendering": _speed_rendering}


def speed(data: dict) -> str:
    """docs/results.md's Speed summary: a row per command, rendered from its benchmark's JSON (``"from"``) or, where
    the benchmark writes none yet, from the measurement recorded in speed.json (``"recorded"``: the numbers, the
    command and the machine as the hand-typed table stated them)."""
    lines = ["Rows whose data column names a JSON file are generated from the benchmark's data; rows marked "
             "*recorded* are earlier measurements kept as data in `benchmarks/results/speed.json` (numbers, command "
             "and machine as the hand-typed table stated them), until their benchmark writes JSON.", "",
             "| what (command) | result | target | data |", "|---|---|---|---|"]
    for row in data["rows"]:
        if "from" in row:
            source = _load(row["from"])
            what, result, target = _SPEED_FROM[row["from"]](row, source)
            part = source[row["part"]] if "part" in row else source
            origin = _source(part, f"{row['from']}.json")
        else:
            r = row["recorded"]
            command = "`, then `".join(r["command"].split("; "))
            what = f"{r['what']} (`{command}`" + (f", {r['conditions']}" if r.get("conditions") else "") + ")"
            result, target = r["result"].format(**r["values"]), r["target"].format(**r["values"])
            origin = f"*recorded*: {_stated_machine(r)}" + (f"; {r['note']}" if r.get("note") else "")
        lines.append(f"| {what} | {result} | {target} | {origin} |")
    return "\n".join(lines)


def rendering(data: dict) -> str:
    """bench_render.py: the plugin kernel's and ``SynthesizedBTF.eval``'s queries/s, and the parallax march's cost."""
    e, r = data["eval"], data["relief"]

    def caption(part):
        if part.get("recorded_from"):
            return (f"recorded measurement of `{part['command']}` ({_stated_machine(part)}; numbers from "
                    f"{part['recorded_from']}, kept in `benchmarks/results/rendering.json`)")
        return f"measured on {_machine(part)} by `{part['command']}`"

    fp32, bf16 = e["eval_queries_per_second"]["fp32"], e["eval_queries_per_second"]["bf16"]
    plugin = e["plugin_queries_per_second"]
    first = f"first call {e['plugin_first_call_seconds']:.1f} s " + e.get(
        "plugin_first_call_note", "(compiling, or from Dr.Jit's cache)")
    workers = f", {e['workers']} workers" if e.get("workers") else ""
    head = caption(e)
    shape = f" ({r['model_shape'][0]} x {r['model_shape'][1]} texels)" if r.get("model_shape") else ""
    lines = [f"{head[0].upper()}{head[1:]}: {e['queries']:,} random queries within 25 repeats, {e['model']}, "
             f"{e['method']}; warmed up, fastest of {e['repeats']} ([rendering.md](rendering.md)):", "",
             "| path | queries/s | notes |", "|---|---|---|",
             f"| `SynthesizedBTF.eval`, fp32 decoder (default) | {fp32 / 1e6:.1f} M | numba synthesis + BLAS/torch "
             f"decoder{workers} |",
             f"| `SynthesizedBTF.eval`, `precision=\"bf16\"` | {bf16 / 1e6:.1f} M | |",
             f"| plugin kernel (`DynBTFEvaluator.eval`, Dr.Jit LLVM) | {plugin / 1e6:.1f} M | {first} |",
             f"| ratio plugin / eval | {plugin / fp32:.1f}x (fp32), {plugin / bf16:.1f}x (bf16) | max difference "
             f"{_sci(e['max_abs_difference'])} on values up to {e['max_abs_value']:.1f} |", "",
             f"The parallax march, plugin kernel per query ({caption(r)}; {r['queries']:,} queries, "
             f"{r['model']}{shape}, {r['method']}):", "",
             "| queries | flat kernel | with parallax march | ratio |", "|---|---|---|---|"]
    for order, label in (("random order", "random order"),
                         ("sorted by view elevation", "sorted by view elevation (a camera's coherent lanes)")):
        ns = r["ns_per_query"][order]
        lines.append(f"| {label} | {ns['flat']:,.0f} ns | {ns['parallax']:,.0f} ns | "
                     f"{ns['parallax'] / ns['flat']:.1f}x |")
    lines += ["", f"Max difference to `SynthesizedBTF.eval` {_sci(r['max_abs_difference_to_eval'])} on a range of "
                  f"{r['eval_value_range']:.1f}."]
    return "\n".join(lines)


RENDERERS = {"parallax_quality": parallax_quality, "training": training, "budget": budget, "evaluation": evaluation, "gpu": gpu, "guided": guided,
             "guidance": guidance, "speed": speed, "rendering": rendering}
#: Tables rendered from another table's data file (default: ``<name>.json``).
SOURCES = {"guidance": "guided"}
_BLOCK = re.compile(r"<!-- table:(?P<name>[a-z_]+) -->\n(?P<body>.*?)\n?<!-- /table:(?P=name) -->", re.S)


def render(name: str) -> str:
    return RENDERERS[name](json.loads((RESULTS / f"{SOURCES.get(name, name)}.json").read_text()))


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
