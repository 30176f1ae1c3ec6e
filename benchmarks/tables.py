"""The measured tables of docs/, generated from the benchmarks' JSON results (``benchmarks/results/*.json``).

A table in a document is the text between ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->``; this module
renders table ``NAME`` from ``benchmarks/results/NAME.json`` (written by the benchmark that measured it) and
writes it there. ``speed.json`` (docs/results.md's Speed summary) is not a benchmark's output: it lists the
summary's rows, each rendered from its benchmark's JSON or, where that benchmark writes none yet, from a
measurement recorded in the file (its numbers, command and machine as the hand-typed table stated them). A part
of a benchmark's file may be such a recorded measurement too (``"recorded_from"``) until the benchmark is re-run,
and so may a whole file: the tables whose benchmark writes no JSON
yet (quality.json, baselines.json, ... below "Recorded measurements"). Several tables of one benchmark share a file
(``SOURCES``).

Run: ``python benchmarks/tables.py`` (after a benchmark run) to rewrite every table,
``python benchmarks/tables.py --check`` to list the tables that disagree with their data (exit status 1);
``tests/test_docs_tables.py`` runs the check, so a table is never re-typed by hand, and fails on any table outside
a block that is not on its list of tables that report no measurement.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _machine(data: dict) -> str:
    return f"{data['cpu']} ({data['cores']} cores, best level {data['cpu_isa']})"


def _level(isa: str, cpu_isa: str) -> str:
    """An instruction-set level a measurement ran on, ``" (forced)"`` after it when below the CPU's best."""
    return isa + (" (forced)" if isa != cpu_isa else "")


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
    breakdowns = data.get("breakdowns", [])
    if breakdowns:
        stages = list(breakdowns[0]["stages"])
        lines += ["", "Where one hist query's time goes on one thread, in nanoseconds per query; then what a query may "
                      "take at 30% of that thread's FMA peak (the decoder's FLOP per query over 30% of the peak), and "
                      "what that leaves the synthesis kernel when the other stages keep their time:", "",
                  "| level | M queries/s | " + " | ".join(stages) + " | all | layers 2..: share of the thread's FMA "
                  "peak | at 30%: the query | at 30%: left for the synthesis |",
                  "|---|---|" + "---|" * (len(stages) + 4)]
        for b in breakdowns:
            ns = 1e9 / b["queries_per_second_one_thread"]
            target = b["decoder_flop_per_query"] / (0.3 * b["fma_peak_gflops_one_thread"])
            synthesis = ns * b["stages"][stages[0]]
            rest = b["layers_2_on_flop_per_query"] / (ns * b["stages"]["layers 2.. (native forward)"])
            lines.append(f"| {b['isa']} | {b['queries_per_second_one_thread'] / 1e6:.2f} | "
                         + " | ".join(f"{ns * b['stages'][name]:.0f}" for name in stages)
                         + f" | {ns:.0f} | {100 * rest / b['fma_peak_gflops_one_thread']:.0f}% | {target:.0f} | "
                         f"{target - (ns - synthesis):.0f} |")
    return "\n".join(lines)


def gpu(data: dict) -> str:
    """gpu_check.py on a GPU machine: its runs side by side, with the CPU's figures for the same measurement (the
    best level of training.json and evaluation.json, 2 cores) and the full-size fit's projected time
    (:func:`_projected_minutes`)."""
    runs = data["runs"]
    cpu_train = max((r for r in _load("training")["rows"] if r["btf"].endswith("size=128") and r["variant"] != "naive"),
                    key=lambda r: r["samples_per_second"])
    cpu_eval = max((r for r in _load("evaluation")["rows"] if r["method"] == "hist"), key=lambda r: r["ours_qps"])
    lines = [f"Measured on {data['machine']} (torch {data['torch']}), in {len(runs)} runs: "
             + "; ".join(f"({i + 1}) `{r['command']}`" + (f" ({r['code']})" if r.get("code") else "")
                         for i, r in enumerate(runs))
             + f". The CPU columns: 2 cores of the CPU in the tables above, its best level ({cpu_train['isa']} "
             f"training, {cpu_eval['isa']} evaluation).", "",
             "| what | GPU | CPU (2 cores) | run |", "|---|---|---|---|"]
    for i, r in enumerate(runs, 1):
        t = r.get("training")
        if t is None:
            continue
        # runs before --compile measured the eager step alone
        modes = t.get("compile_modes") or {"off": t}
        for mode, m in modes.items():
            if "error" in m:
                lines.append(f"| training, fast recipe, `{t['btf']}`, `--compile {mode}` | failed | | {i} |")
                continue
            planned = (f"; the budget planner measures {t['planned_ms_per_step']:.2f} ms"
                       if "planned_ms_per_step" in t and mode == t.get("fastest_compile", "off") else "")
            bold = "**" if mode == t.get("fastest_compile", "off") else ""
            lines.append(f"| training, fast recipe, `{t['btf']}`, `--compile {mode}` | {bold}"
                         f"{m['samples_per_second'] / 1e6:.1f} M samples/s{bold} ({m['ms_per_step']:.2f} ms per "
                         f"step{planned}) | {cpu_train['samples_per_second'] / 1e6:.1f} M ({cpu_train['variant']}) "
                         f"| {i} |")
    for i, r in enumerate(runs, 1):
        if "evaluation" not in r:
            continue
        for c in r["evaluation"].get("chunk_sizes", [{"chunk_size": 32768, "default": True,
                                                       **{k: r["evaluation"][k] for k in ("seconds",
                                                                                          "queries_per_second")}}]):
            memory = f", {c['peak_memory_bytes'] / 2**30:.2f} GiB" if c.get("peak_memory_bytes") else ""
            default = " (the default then)" if c["default"] and "chunk_sizes" not in r["evaluation"] else \
                (" (the default)" if c["default"] else "")
            value = f"{1e3 * c['seconds']:.1f} ms, {c['queries_per_second'] / 1e6:.1f} M queries/s{memory}"
            lines.append(f"| 1080p evaluation, hist, chunks of {c['chunk_size']:,} queries{default} | "
                         + (f"**{value}**" if c["default"] and "chunk_sizes" in r["evaluation"] else value)
                         + f" | {r['evaluation']['queries'] / cpu_eval['ours_qps'] * 1e3:.0f} ms, "
                         f"{cpu_eval['ours_qps'] / 1e6:.1f} M "
                         f"| {i} |")
    i, a = next((i, r["evaluation_agreement"]) for i, r in reversed(list(enumerate(runs, 1)))
                if "evaluation_agreement" in r)
    lines.append(f"| the GPU's hist answers against the CPU's compiled kernels ({a['queries']:,} queries) | relative "
                 f"L2 difference {a['relative_l2_difference']:.1e}, largest {a['max_abs_difference']:.1e} | | "
                 f"{i} |")
    fits = [(i, r["full_size_fit"]) for i, r in enumerate(runs, 1) if "full_size_fit" in r]
    converge = _steps_to_half_db()
    for i, f in fits:
        seconds_per_step = _seconds_per_step(f)
        lines.append(f"| full-size fit, `{f['btf']}` ({f['file_components']}-component DFMF file), "
                     f"`--minutes {f['minutes_budget']:g} --compile {f.get('compile', 'off')}` | {f['steps']:,} "
                     f"steps ({f['stopped']}) in "
                     f"{f['curve'][-1][0] / 60:.1f} min, {f['best_held_out_psnr']:.2f} dB held-out; "
                     f"{1e3 * seconds_per_step:.0f} ms per step, texels read from the file's factors | | {i} |")
        lines.append(f"| full-size fit to within 0.5 dB of converged (projected: {converge:,} steps of the CPU's "
                     f"measured curve x the step above) | **{_projected_minutes(f):.1f} min** | see above | {i} |")
    return "\n".join(lines)


def _seconds_per_step(fit: dict) -> float:
    """A gpu_check.py full-size fit's measured seconds per step: its last monitor time over its steps."""
    return fit["curve"][-1][0] / fit["steps"]


def _steps_to_half_db() -> int:
    """The steps after which the CPU's measured full-size convergence curve stays within 0.5 dB of its final PSNR
    (fullsize.json, :func:`fullsize_curve`)."""
    return _load("fullsize")["curve"]["steps_to_within_0_5_db"]


def _projected_minutes(fit: dict) -> float:
    """A full-size fit's projected minutes to within 0.5 dB: :func:`_steps_to_half_db` times the fit's measured step
    (:func:`_seconds_per_step`)."""
    return _steps_to_half_db() * _seconds_per_step(fit) / 60


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


def _guidance_caption(data: dict, g: dict) -> str:
    """The start of a guidance table's caption: machine, command, material, classes and the half-and-half target."""
    return (f"Measured on {_machine(data)} by `{data['command']}`: `{g['model']}` in {g['classes']} classes, a target "
            f"asking for class 0 on the left half and class 1 on the right half of {g['repeats']} x {g['repeats']} "
            "exemplar repeats")


def guidance_struct(data: dict) -> str:
    """bench_guided.py's guided struct: cells and texels on target, repetition against struct's, cost, per seed."""
    g = data["guidance_struct"]
    lines = [_guidance_caption(data, g) + f"; struct's cells per repeat as it chooses them "
             f"({g['rows'][0]['cells'][0]} x {g['rows'][0]['cells'][1]}).", "",
             "| seed | cells whose content is the target's (unguided struct) | texels on target (left / right) | "
             "repetition, guided over struct | synthesis cost per query, guided over struct |", "|---|---|---|---|---|"]
    for r in g["rows"]:
        lines.append(f"| {r['seed']} | {100 * r['cells_on_target']:.1f}% ({100 * r['cells_on_target_unguided']:.1f}%) | "
                     f"{100 * r['on_target']:.1f}% ({100 * r['on_target_left']:.1f}% / {100 * r['on_target_right']:.1f}%) "
                     f"| {r['repetition_ratio']:.2f}x | {r['cost_vs_hist']:.1f}x |")
    return "\n".join(lines)


def web_layered(data: dict) -> str:
    """bench_web_layered.py: the layered viewer's frame time against each layer alone, per mask."""
    w, h = data["size"]
    lines = [f"Measured on {_machine(data)} by `{data['command']}`: `{data['layers'][0]}` | `{data['layers'][1]}`, hist "
             f"at {data['scale']:g} repeats per uv unit, band half-width {data['width']:g}, {data['span']:g} uv units "
             f"across a {w} x {h} frame; median of {data['frames']} frames; GL: {data['renderer']}.", "",
             "| mask | layer 0 alone | layer 1 alone | layered | layered over the sum of the two |",
             "|---|---|---|---|---|"]
    for r in data["rows"]:
        lines.append(f"| {r['mask']} | {r['ms_layer0']:.0f} ms | {r['ms_layer1']:.0f} ms | {r['ms_layered']:.0f} ms | "
                     f"{r['ms_layered'] / (r['ms_layer0'] + r['ms_layer1']):.2f} |")
    return "\n".join(lines)


def guidance(data: dict) -> str:
    """bench_guided.py's guidance part: content on target, repetition against hist's, cost, per seed."""
    g = data["guidance"]
    lines = [_guidance_caption(data, g) + ", one query per texel.", "",
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
    """``6.2e-4`` (``decimals`` decimals, no zero-padded exponent); ``0`` for zero."""
    if x == 0:
        return "0"
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


def _speed_convergence(row: dict, data: dict) -> tuple[str, str, str]:
    """training.json's ``convergence`` (``bench_training.py --convergence``): the training time to naive's final
    held-out PSNR, ours (each precision) vs naive."""
    parts, misses = [], []
    for c in data["convergence"]:
        ours = []
        for precision, o in c["ours"].items():
            if o["speedup"] is None:
                ours.append(f"{precision}: not reached in as long")
                misses.append(f"`{c['btf']}` {precision}")
                continue
            ours.append(f"{precision} **{o['speedup']:.1f}x** sooner ({o['seconds_to_reach']:.1f} s)")
            if o["speedup"] < row["target_ratio"]:
                misses.append(f"`{c['btf']}` {precision} ({o['speedup']:.1f}x)")
        parts.append(f"`{c['btf']}` ({c['isa']}): naive {c['naive_final_psnr']:.2f} dB after "
                     f"{c['naive_seconds']:g} s; ours " + ", ".join(ours))
    what = (f"training to naive's final held-out PSNR, ours (fast recipe) vs the paper's recipe run naively "
            f"(`{data['command']}`)")
    target = (f"naive's PSNR in at most 1/{row['target_ratio']:g} of its time: "
              + ("met" if not misses else "missed for " + ", ".join(misses)))
    return what, "; ".join(parts), target


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
    plugin, fp32 = part["plugin_queries_per_second"], part["eval_queries_per_second"]["fp32"]
    what = (f"Mitsuba plugin's query vs `SynthesizedBTF.eval`, the same {part['queries']:,} queries "
            f"(`{part['command']}`)")
    result = (f"{plugin / 1e6:.1f} vs {fp32 / 1e6:.1f} M queries/s ({plugin / fp32:.2f}x), max difference "
              f"{_sci(part['max_abs_difference'])} on values up to "
              f"{part['max_abs_value']:.1f}")
    return what, result, row["target"]


def _speed_web(row: dict, data: dict) -> tuple[str, str, str]:
    frames, agreement, size = data["frame_time"], data["agreement"], data["size"]
    fp16 = [r["psnr_fp16_db"] for r in agreement["rows"]]
    u8 = [r["psnr_u8_db"] for r in agreement["rows"]]
    seconds = [ms / 1e3 for r in frames["rows"] for ms in r["ms_per_frame"]]
    psnr = size["held_out_psnr_db"]
    what = (f"web export: the GLSL ES 3.00 shader in headless Chromium vs `SynthesizedBTF.eval`, leather "
            f"(`{agreement['command']}`)")
    result = (f"PSNR {min(fp16):.1f}-{max(fp16):.1f} dB (fp16 textures), {min(u8):.1f}-{max(u8):.1f} dB (u8) on random "
              f"queries up to 1e6 repeats; u8 export {size['hist_mb']['u8']:.2f} MB vs the {size['model_mb']:.2f} MB "
              f"model file, held-out loss {psnr['fp32'] - psnr['u8']:.3f} dB (fp16: < {size['fp16_loss_below_db']:g} "
              f"dB); a 1280 x 720 frame takes {min(seconds):.1f}-"
              f"{max(seconds):.1f} s in software GL (SwiftShader) on the 2 shared cores (the paper: "
              f"{frames['paper']['ms_per_frame']:g} ms on an RTX 4090; [realtime.md](realtime.md))")
    met = min(fp16) >= 40
    return what, result, f"{row['target']} ({'met' if met else 'missed'})"


def _speed_compiled_material(row: dict, data: dict) -> tuple[str, str, str]:
    v = data["rows"][0]["values"]
    what = ("`dynbtf render` in a second process, a compiled 64 x 64 Triple Plane (`dynbtf compile m.dbtfm`, then "
            f"`dynbtf render m.dbtfm -o a.png --size 64 --spp 1`, footprints on; `{data['command']}`)")
    result = (f"**{v['wall_seconds']:.1f} s** wall time, {v['render_seconds']:.1f} s of it the render; nothing fitted "
              "again ([compiled_material.md](compiled_material.md#measured))")
    return what, result, f"at most {row['target_seconds']:g} s ({'met' if v['wall_seconds'] <= row['target_seconds'] else 'missed'})"


def _speed_demo(row: dict, data: dict) -> tuple[str, str, str]:
    what = f"`dynbtf demo` with defaults (`{data['command']}`: {data['conditions']})"
    parts, met = [], True
    for r in data["rows"]:
        minutes = r["total_seconds"] / 60
        met = met and minutes <= row["target_minutes"]
        stages = ", ".join(f"{name} {r['stages'][name] / 60:.1f}" for name in ("fit", "synthesis", "structured",
                                                                              "render"))
        parts.append(f"{r['isa']}{' (forced)' if r['forced'] else ''}: **{minutes:.1f} min** ({stages}); held-out "
                     f"PSNR {r['held_out_psnr']:.2f} dB")
    return what, "; ".join(parts), f"at most {row['target_minutes']:g} min ({'met' if met else 'missed'})"


def _speed_simulator(row: dict, data: dict) -> tuple[str, str, str]:
    seconds = [r["seconds"] for r in data["rows"]]
    what = (f"simulating a {data['size']} x {data['size']} material, {data['grid'].upper()} grid "
            f"(`{data['command']}`, {len(seconds)} materials)")
    met = max(seconds) <= row["target_seconds"]
    return what, f"{_span(seconds, '.1f')} s", f"well under a minute ({'met' if met else 'missed'})"


def _speed_sampling(row: dict, data: dict) -> tuple[str, str, str]:
    what = f"importance sampling vs cosine sampling (`{data['command']}`: {data['conditions']})"
    glossy = [r for r in data["rows"] if r["auto"] == "mixture"]
    rough = [r for r in data["rows"] if r["auto"] != "mixture"]
    parts = [f"{r['model']}, {r['lighting']}: **{r['equal_spp_ratio']:.1f}x** lower MSE at equal spp "
             f"({r['equal_time_ratio']:.1f}x at equal time)" for r in glossy]
    if rough:
        names = ", ".join(dict.fromkeys(r["model"] for r in rough))
        parts.append(f"{names}: {_span([r['equal_spp_ratio'] for r in rough], '.2f')}x at equal spp, "
                     f"{_span([r['equal_time_ratio'] for r in rough], '.2f')}x at equal time")
    # what the plugin's default picks is cosine where auto says so (ratio 1 by definition), else the mixture
    picked = [r["equal_time_ratio"] if r["auto"] == "mixture" else 1.0 for r in data["rows"]]
    glossy_met = bool(glossy) and all(r["equal_spp_ratio"] >= row["target_equal_spp"] for r in glossy)
    target = (f"{row['target_equal_spp']:g}x at equal spp on the glossy material ({'met' if glossy_met else 'missed'}); "
              f"the default `auto` never more than 5% worse than cosine at equal time "
              f"({'met' if min(picked) >= 0.95 else 'missed'})")
    return what, "; ".join(parts), target


_SPEED_FROM = {"training": _speed_training, "training_convergence": _speed_convergence,
               "evaluation": _speed_evaluation, "rendering": _speed_rendering,
               "web": _speed_web, "compiled_material": _speed_compiled_material, "demo": _speed_demo,
               "simulator": _speed_simulator, "sampling": _speed_sampling,
               "fit_many": lambda row, data: _speed_fit_many(row, data)}  # (defined beside fit_many below)


def speed(data: dict) -> str:
    """docs/results.md's Speed summary: a row per command, rendered from its benchmark's JSON (``"from"``; ``"view"``:
    which of that file's summaries, default the one named like it) or, where the benchmark writes none yet, from the
    measurement recorded in speed.json (``"recorded"``: the numbers, the command and the machine as the hand-typed
    table stated them)."""
    recorded = any("recorded" in row for row in data["rows"])
    lines = ["Rows whose data column names a JSON file are generated from the benchmark's data; rows marked "
             "*recorded* are earlier measurements kept as data in `benchmarks/results/speed.json` (numbers, command "
             "and machine as the hand-typed table stated them), until their benchmark writes JSON." if recorded else
             "Every row is generated from its benchmark's data (the JSON file its data column names; "
             "`benchmarks/results/speed.json` lists the rows and their targets).", "",
             "| what (command) | result | target | data |", "|---|---|---|---|"]
    for row in data["rows"]:
        if "from" in row:
            source = _load(row["from"])
            what, result, target = _SPEED_FROM[row.get("view", row["from"])](row, source)
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
    """bench_render.py: ``SynthesizedBTF.eval``'s queries/s and the Mitsuba plugin's (the same query, handed over)."""
    e = data["eval"]
    fp32, bf16 = e["eval_queries_per_second"]["fp32"], e["eval_queries_per_second"]["bf16"]
    plugin = e["plugin_queries_per_second"]
    workers = f", {e['workers']} workers" if e.get("workers") else ""
    difference = _sci(e["max_abs_difference"])
    return "\n".join([
        f"Measured on {_machine(e)} by `{e['command']}`: {e['queries']:,} random queries within 25 repeats, "
        f"{e['model']}, {e['method']}; warmed up, fastest of {e['repeats']} ([rendering.md](rendering.md)):", "",
        "| path | queries/s | notes |", "|---|---|---|",
        f"| `SynthesizedBTF.eval`, fp32 decoder (default) | {fp32 / 1e6:.1f} M | numba synthesis + BLAS/native "
        f"decoder{workers} |",
        f"| `SynthesizedBTF.eval`, `precision=\"bf16\"` | {bf16 / 1e6:.1f} M | |",
        f"| the plugin's query (`DynBTFEvaluator.eval`: the wavefront handed to `SynthesizedBTF.eval` and back) | "
        f"{plugin / 1e6:.1f} M | first call {e['plugin_first_call_seconds']:.2f} s |",
        f"| ratio plugin / eval | {plugin / fp32:.2f}x (fp32), {plugin / bf16:.2f}x (bf16) | max difference "
        f"{difference} on values up to {e['max_abs_value']:.1f} |"])


def render_scenes(data: dict) -> str:
    """bench_render.py's scenes part: ``dynbtf render``'s wall time at its defaults, first and second run."""
    p = data["scenes"]
    w, h = p["resolution"]
    lines = [f"Measured on {_machine(p)} by `{p['command']}`: {p['model']}, {w} x {h} pixels, {p['spp']} spp in "
             f"passes of {p['spp_per_pass']}, each scene rendered twice in one process:", "",
             "| scene / lighting / method | run | wall time | first pass | of it compiling |", "|---|---|---|---|---|"]
    for r in p["rows"]:
        lines.append(f"| {r['scene']} / {r['lighting']} / {r['method']} | {r['run']} | {r['seconds']:.1f} s | "
                     f"{r['first_pass_seconds']:.1f} s | {r['compile_seconds']:.1f} s |")
    return "\n".join(lines)


def runtimes(data: dict) -> str:
    """The measurement behind the choice of runtimes (docs/architecture.md): the plugin's former Dr.Jit kernel beside
    the library's CPU path, per level and method."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({data['queries']:,} queries, a 1080p frame), the "
             f"last run with the Dr.Jit kernel (its commit is in `benchmarks/results/runtimes.json`):", "",
             "| level | method | library (numba + native decoder) M queries/s | Dr.Jit kernel M queries/s | "
             "Dr.Jit / library |", "|---|---|---|---|---|"]
    for r in data["rows"]:
        lines.append(f"| {r['isa']} | {r['method']} | {r['library_qps'] / 1e6:.2f} | {r['drjit_qps'] / 1e6:.2f} | "
                     f"{r['drjit_qps'] / r['library_qps']:.2f}x |")
    return "\n".join(lines)


# --- Recorded measurements -------------------------------------------------------------------------------------
# The tables below come from data files that no benchmark writes yet: each (``"recorded_from"``) holds the numbers
# as the hand-typed table showed them, with the command and machine its text stated (null where it did not), until
# a benchmark run replaces it. A row's ``"bold"`` lists the numbers the table emphasises (a cell of several numbers
# by its first); a recorded cell of prose is a ``str.format`` template filled from the row's ``"values"``.


def _line(*cells: str) -> str:
    """A markdown table row; an empty cell is written ``| |``."""
    return "|" + "|".join(f" {c} " if c else " " for c in cells) + "|"


def _head(*headers: str, spaced: bool = False) -> list[str]:
    """A table's header row and its rule (``| --- |`` when ``spaced``, else ``|---|``)."""
    return [_line(*headers), _line(*["---"] * len(headers)) if spaced else "|" + "---|" * len(headers)]


def _cells(row: dict):
    """``c(key, spec)``: ``row[key]`` formatted (empty where it is null), written **bold** where the row's
    ``"bold"`` lists ``key``; ``c(key, text=...)`` writes ``text`` (a cell of several numbers) the same way."""
    marked = set(row.get("bold", ()))

    def c(key: str, spec: str = "", text: str | None = None) -> str:
        if text is None:
            text = "" if row.get(key) is None else format(row[key], spec)
        return f"**{text}**" if key in marked else text

    return c


def _numbers(row: dict):
    """``n(key, spec)``: :func:`_cells`' cell of ``row[key]``, a number measured per seed (``{"mean", "range",
    "per_seed"}``) written as its mean and min-max (:func:`_spread`)."""
    c = _cells(row)

    def n(key: str, spec: str) -> str:
        return c(key, text=_spread(row[key], spec)) if isinstance(row[key], dict) else c(key, spec)

    return n


def _note(text: str | None) -> str:
    """`` (text)``, or nothing."""
    return f" ({text})" if text else ""


def _named(row: dict, key: str) -> str:
    """``row[key]``, followed by the row's ``"note"`` in parentheses if it has one."""
    return row[key] + _note(row.get("note"))


def _grouped(rows: list[dict], label):
    """(``label(row)``, row) per row, the label left blank where it repeats the previous row's."""
    previous = None
    for r in rows:
        yield ("" if label(r) == previous else label(r)), r
        previous = label(r)


def _filled(row: dict, key: str) -> str:
    """A recorded cell: the template ``row[key]`` filled from ``row["values"]``."""
    return row[key].format(**row.get("values", {}))


def _prose(part: dict, *columns: tuple[str, str], spaced: bool = False) -> str:
    """A table of recorded prose rows; ``columns``: (header, the key of the rows' template for that column)."""
    lines = _head(*(header for header, _ in columns), spaced=spaced)
    return "\n".join(lines + [_line(*(_filled(r, key) for _, key in columns)) for r in part["rows"]])


def _range(values: list, spec: str) -> str:
    """``3,070 - 3,120``: the lowest and highest of several runs, or the one value."""
    return " - ".join(format(v, spec) for v in values)


def _storage(row: dict) -> str:
    """A synthesis method's extra storage: ``0``, or megabytes with the row's ``"storage_note"``."""
    mb = row["extra_storage_mb"]
    text = _cells(row)("extra_storage_mb", text=f"{mb:g} MB" if mb else "0")
    return text + _note(row.get("storage_note"))


def _transposed(points: list[dict], *rows: tuple) -> str:
    """A column per point: ``rows`` are (label, the cell of a point), the first of them the header row."""
    (label, cell), *rest = rows
    return "\n".join(_head(label, *map(cell, points)) + [_line(label, *map(cell, points)) for label, cell in rest])


#: Measured rows whose result comes from a benchmark's data (``"from"``: the data file, rendered by the function of
#: the row's ``"view"``, or where it has none of ``"from"``).
_MEASURED_FROM = {"structured": "structured_summary", "demo": "demo_summary", "sampling": "sampling_summary",
                  "rendering": "rendering_summary", "compiled_material": "compiled_material_summary",
                  "web": "web_summary", "filtering": "filtering_summary", "training": "training_summary",
                  "evaluation": "evaluation_summary", "quality": "quality_summary",
                  "quality_parallax": "quality_parallax_summary", "baselines_storage": "storage_summary",
                  "gpu": "gpu_summary", "parallax_eval": "parallax_eval_summary",
                  "fullsize_data_path": "fullsize_summary"}


def parallax_eval(data: dict) -> str:
    """bench_parallax_eval.py: queries/s of the Triple Plane and of ``triple-parallax`` per method and set of views,
    and their ratio (what the march costs)."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` (`{data['btf']}`'s height, "
             f"{data['relief_depth_texels']:.1f} texels deep; {data['queries']:,} queries at 45 repeats, lights random; "
             f"all views: uniform in solid angle up to {data['max_theta']:g} deg; best of {data['repeats']} after a "
             "warm-up):", ""]
    lines += _head("method", "views", "Triple Plane (M queries/s)", "triple-parallax (M queries/s)", "cost ratio")
    lines += [_line(r["method"], r["views"], f"{r['flat_mqps']:.2f}", f"{r['relief_mqps']:.2f}",
                    f"**{r['cost_ratio']:.1f}x**") for r in data["rows"]]
    return "\n".join(lines)


def parallax_eval_summary(data: dict) -> str:
    """README.md's Measured line of bench_parallax_eval.py: what the relief march costs a ``hist`` query against the
    flat Triple Plane's, with random views and with one view for every query (a camera's coherent rays)."""
    rows = {r["views"]: r for r in data["rows"] if r["method"] == "hist"}
    return (f"matches `SynthesizedBTF.eval` (tested); a `hist` query with the march costs "
            f"{rows['one view at 45 deg']['cost_ratio']:.1f}x a flat one with one 45-degree view for every query "
            f"(a camera's rays), {rows['all views']['cost_ratio']:.1f}x with views random up to "
            f"{data['max_theta']:g} degrees (`{data['btf']}`, relief {data['relief_depth_texels']:.0f} texels deep)")


def fullsize_summary(data: dict) -> str:
    """README.md's Measured line of the full-size BTF: the fast recipe's rate on the DFMF file over its rate on a
    cached BTF (bench_training_large.py), and the training time after which fullsize.json's convergence curve stays
    within 0.5 dB of its final PSNR (:func:`fullsize_curve`)."""
    fast = next(r for r in data["rows"] if r["recipe"] == "fast" and not r["subtexel"])
    curve = _load("fullsize")["curve"]
    return (f"streamed from its factors at {fast['ratio']:.2f}x the cached speed; within 0.5 dB of the final PSNR "
            f"in {curve['minutes_to_within_0_5_db']:.0f} min of training ({curve['isa']})")


def storage_summary(data: dict) -> str:
    """README.md's Measured line of bench_baselines.py's storage part: the Triple Plane's model file against the raw
    BTF it was fitted to (float32 RGB of every (view, light) pair and texel)."""
    part = data["storage"]
    triple = next(r for r in part["rows"] if r["kind"] == "triple")
    raw = part["n_pairs"] * part["height"] * part["width"] * 3 * 4
    return f"{triple['model_bytes'] / 1e6:.2f} MB vs {raw / 1e9:.2f} GB raw (float32)"


def gpu_summary(data: dict) -> str:
    """README.md's Measured line of gpu_check.py: the last run's training and 1080p evaluation, and the projected
    full-size fit (:func:`gpu`)."""
    def last(key: str) -> dict:
        return next(r[key] for r in reversed(data["runs"]) if key in r)

    training, fit = last("training"), last("full_size_fit")
    fastest = training.get("fastest_compile", "off")
    rate = (training.get("compile_modes") or {"off": training})[fastest]["samples_per_second"]
    return (f"{data['machine'].split(' (')[0]}: training {rate / 1e6:.0f} M samples/s (`--compile {fastest}`); "
            f"a 1080p `hist` frame in {1e3 * last('evaluation')['seconds']:.0f} ms; a full-size fit to within "
            f"0.5 dB in {_projected_minutes(fit):.1f} min (projected from its measured step)")


def quality_summary(data: dict, part: str = "triple") -> str:
    """README.md's Measured line of a part of fit_materials.py's data (``triple``, the Triple Plane, or
    ``triple_parallax``): held-out PSNR / FLIP per material (the mean over the seeds)."""
    part = data[part]
    seeds = f" (mean of {len(part['seeds'])} seeds)" if part.get("seeds") else ""
    return ", ".join(f"{r['material']} {r['psnr']:.1f} dB / {r['flip']:.3f}" for r in map(_means, part["rows"])) + seeds


def quality_parallax_summary(data: dict) -> str:
    """README.md's Measured line of fit_materials.py's ``triple_parallax`` part (:func:`quality_summary`)."""
    return quality_summary(data, "triple_parallax")


def training_summary(data: dict) -> str:
    """README.md's Measured line of bench_training.py: the fast recipe's samples/s over the naive recipe's, per
    level and BTF (with bf16 products where the level has them)."""
    btfs = list(dict.fromkeys(r["btf"] for r in data["rows"]))
    per_level = []
    for isa in dict.fromkeys(r["isa"] for r in data["rows"]):
        for variant, label in (("fast", ""), ("fast, bf16", ", bf16 products")):
            ratios = {r["btf"]: r["ratio_to_naive"] for r in data["rows"]
                      if r["isa"] == isa and r["variant"] == variant}
            if ratios:
                per_level.append(f"{_level(isa, data['cpu_isa'])}{label} "
                                 + " / ".join(f"{ratios[b]:.1f}x" for b in btfs if b in ratios))
    return (f"ours over the naive recipe's samples/s ({' / '.join(f'`{b}`' for b in btfs)}): " + "; ".join(per_level)
            + "; [per level](docs/results.md#training-speed)")


def evaluation_summary(data: dict) -> str:
    """README.md's Measured line of bench_synthesis_eval.py: hist's queries/s over naive PyTorch's, per level, and
    the share of the FMA bound."""
    rows = [r for r in data["rows"] if r["method"] == "hist"]
    return ("ours over naive PyTorch: " + "; ".join(
        f"{_level(r['isa'], data['cpu_isa'])} {r['ours_qps'] / r['naive_qps']:.1f}x "
        f"({r['ours_qps'] / 1e6:.2f} M queries/s, "
        f"{r['share_of_fma_bound']:.0%} of the FMA bound)" for r in rows)
        + "; [per level](docs/results.md#synthesis-evaluation-speed)")


def rendering_summary(data: dict) -> str:
    """README.md's Measured line of bench_render.py: the plugin's queries/s against ``SynthesizedBTF.eval``'s."""
    e = data["eval"]
    difference = _sci(e["max_abs_difference"])
    return (f"{e['plugin_queries_per_second'] / e['eval_queries_per_second']['fp32']:.2f}x the queries/s (the plugin "
            f"hands each wavefront to it), max difference {difference}")


def compiled_material_summary(data: dict) -> str:
    """README.md's Measured line of bench_compiled_material.py: a second process's render of a compiled model."""
    v = data["rows"][0]["values"]
    return (f"{v['wall_seconds']:.1f} s, {v['render_seconds']:.1f} s of it the render (compiled materials cached: "
            f"nothing fitted again; the compile before it {v['compile_seconds']:.0f} s)")


def web_summary(data: dict) -> str:
    """README.md's Measured line of bench_web.py: the shader's agreement with the library per precision."""
    rows = data["agreement"]["rows"]
    fp16, u8 = _span([r["psnr_fp16_db"] for r in rows], ".0f"), _span([r["psnr_u8_db"] for r in rows], ".0f")
    return (f"{fp16} dB (fp16), {u8} dB (u8) over {', '.join(r['method'] for r in rows)}; same texels at every "
            "lattice vertex up to 2^45 repeats")


def filtering_summary(data: dict) -> str:
    """README.md's Measured line of bench_filtering.py: the default footprint query against the point query."""
    point, default = data["rows"][0], data["rows"][-1]
    ns, plugin = data["cost"]["eval_ns_per_query"], data["cost"]["plugin"]["ns_per_query"]
    return (f"FLIP {default['flip']:.3f} vs point queries' {point['flip']:.3f}; far-field colour within "
            f"{default['far_field_error_percent']:.1f}%; {ns['filtered'] / ns['point']:.1f}x the cost of a point query "
            f"({plugin['filtered'] / plugin['point']:.1f}x in the Mitsuba plugin)")


def demo_summary(data: dict) -> str:
    """README.md's Measured line of bench_demo.py: the demo's minutes per level and its report's held-out PSNR."""
    parts = [f"{r['total_seconds'] / 60:.1f} min on the {r['isa']} path{' (forced)' if r['forced'] else ''}"
             for r in data["rows"]]
    psnr = _span([r["held_out_psnr"] for r in data["rows"]], ".2f")
    return f"{', '.join(parts)}, {data['conditions'].split(';')[0]}; the report's model at {psnr} dB held-out PSNR"


def sampling_summary(data: dict) -> str:
    """README.md's Measured line of bench_sampling.py: the glossy model's MSE ratios, and what auto does elsewhere."""
    glossy = [r for r in data["rows"] if r["auto"] == "mixture"]
    parts = [f"{r['model']} {r['equal_spp_ratio']:.1f}x lower MSE under the {r['lighting']} light" for r in glossy]
    return ("; ".join(parts) + "; the default (`auto`) samples rough materials cosine-weighted, where the table gains "
            "nothing")


def measured(data: dict) -> str:
    """README.md's Measured: a line per result, each pointing at its table in docs/results.md; a row with
    ``"from"`` takes its result from that benchmark's data (rendered by :data:`_MEASURED_FROM` of its ``"view"``, if
    it names one, else of ``"from"``), the others are recorded."""
    lines = _head("what", "result", spaced=True)
    for r in data["rows"]:
        result = (globals()[_MEASURED_FROM[r.get("view", r["from"])]](_load(r["from"])) if "from" in r
                  else _filled(r, "result"))
        lines.append(_line(_filled(r, "what"), result))
    return "\n".join(lines)


def _quality(part: dict) -> str:
    """A quality table: a row per material. A measured part (fit_materials.py ``--json``) holds each number per seed
    (the mean, with the min-max of PSNR); a recorded part, the hand-typed numbers."""
    if part.get("recorded_from"):
        lines = []
    else:
        lines = [f"Measured on {_machine(part)} by `{part['command']}` ({len(part['seeds'])} seeds; "
                 f"{part['conditions']}).", ""]
    lines += _head("material", "PSNR (dB)", "grazing / others", "PSNR, fixed peak 1", "DSSIM", "FLIP", "fit (min)")
    for r in part["rows"]:
        m = _means(r)
        c = _cells(m)
        psnr = _spread(r["psnr"], ".2f") if isinstance(r["psnr"], dict) else c("psnr", ".2f")
        lines.append(_line(_named(r, "material"), psnr, f"{m['psnr_grazing']:.2f} / {m['psnr_others']:.2f}",
                           c("psnr_fixed1", ".2f"), c("dssim", ".3f"), c("flip", ".3f"), c("fit_minutes", ".1f")))
    return "\n".join(lines)


def _means(row: dict) -> dict:
    """``row`` with each number measured per seed (``{"mean", "range", "per_seed"}``) replaced by its mean."""
    return {k: v["mean"] if isinstance(v, dict) and "mean" in v else v for k, v in row.items()}


def quality_triple(data: dict) -> str:
    """fit_materials.py: held-out quality of the Triple Plane per simulated material."""
    return _quality(data["triple"])


def quality_parallax(data: dict) -> str:
    """fit_materials.py --repr triple-parallax: the same with parallax."""
    return _quality(data["triple_parallax"])


def quality_compared(data: dict) -> str:
    """parallax.md: quality.json's two kinds side by side, the better PSNR bold, the materials parallax improves
    first."""
    flat = {r["material"]: _means(r) for r in data["triple"]["rows"]}

    def scores(r: dict, other: dict) -> str:
        psnr = f"**{r['psnr']:.2f}**" if r["psnr"] > other["psnr"] else f"{r['psnr']:.2f}"
        return f"{psnr} ({r['psnr_grazing']:.2f} / {r['psnr_others']:.2f}) / {r['dssim']:.3f} / {r['flip']:.3f}"

    lines = _head("material", "Triple Plane: PSNR (grazing / others) / DSSIM / FLIP",
                  "triple-parallax: PSNR (grazing / others) / DSSIM / FLIP", "PSNR fixed peak 1: flat -> parallax")
    parallax = map(_means, data["triple_parallax"]["rows"])
    for p in sorted(parallax, key=lambda p: p["psnr"] < flat[p["material"]]["psnr"]):
        t = flat[p["material"]]
        lines.append(_line(p["material"], scores(t, p), scores(p, t),
                           f"{t['psnr_fixed1']:.2f} -> {p['psnr_fixed1']:.2f}"))
    return "\n".join(lines)


def baselines(data: dict) -> str:
    """dynbtf compare on the simulated materials: each representation's held-out quality."""
    lines = _head("material", "kind", "PSNR dB", "grazing / others", "PSNR (fixed peak 1)", "DSSIM", "FLIP")
    for material, r in _grouped(data["representations"]["rows"], lambda r: _named(r, "material")):
        c = _cells(r)
        lines.append(_line(material, r["kind"], c("psnr", ".2f"),
                           c("psnr_grazing", text=f"{r['psnr_grazing']:.2f} / {r['psnr_others']:.2f}"),
                           c("psnr_fixed1", ".2f"), c("dssim", ".4f"), c("flip", ".4f")))
    return "\n".join(lines)


def baselines_summary(data: dict) -> str:
    """results.md: PSNR / FLIP per material and kind from the same runs, the best kind (its PSNR bold) bold, the
    materials the Triple Plane wins first."""
    rows = data["representations"]["rows"]
    storage = {r["kind"]: r["positional_bytes"] for r in data["storage"]["rows"]}
    best = {r["material"]: r["kind"] for r in rows if "psnr" in r.get("bold", ())}
    kinds = ("triple", "neumip", "pca", "sh")
    lines = _head("material", "Triple Plane", "NeuMIP", "PCA",
                  f"SH ({storage['sh'] / storage['triple']:.0f}x the positional storage)")
    for material in sorted(dict.fromkeys(r["material"] for r in rows), key=lambda m: best[m] != "triple"):
        of = {r["kind"]: r for r in rows if r["material"] == material}
        cells = (f"{of[k]['psnr']:.2f} / {of[k]['flip']:.3f}" for k in kinds)
        lines.append(_line(material, *(f"**{text}**" if k == best[material] else text
                                       for k, text in zip(kinds, cells))))
    return "\n".join(lines)


def baselines_storage(data: dict) -> str:
    """The storage of each kind (float32): its positional plane (with its values per texel and its size against the
    Triple Plane's) and the whole model."""
    part = data["storage"]
    texels = part["height"] * part["width"]
    triple = next(r["positional_bytes"] for r in part["rows"] if r["kind"] == "triple")
    lines = [f"Measured by `{part['command']}` ({part['height']} x {part['width']} texels, {part['n_pairs']:,} "
             f"(view, light) pairs; {part['conditions']}):", ""]
    lines += _head("kind", "values per texel", "positional plane", "x the Triple Plane's", "whole model")
    lines += [_line(r["kind"], f"{r['positional_bytes'] / 4 / texels:g}", f"{r['positional_bytes']:,} B",
                    f"{r['positional_bytes'] / triple:.2f}x", f"{r['model_bytes']:,} B") for r in part["rows"]]
    return "\n".join(lines)


def baselines_small(data: dict) -> str:
    """dynbtf compare on sim:leather?size=64: quality, storage and fit time per kind. A measured part
    (bench_baselines.py) holds each number per seed (the mean and its min-max); a recorded one, the hand-typed
    numbers."""
    part = data["small"]
    lines = [] if part.get("recorded_from") else [
        f"Measured on {_machine(part)} by `{part['command']}` (`{part['btf']}`, {len(part['seeds'])} seeds; "
        f"{part['conditions']}):", ""]
    lines += _head("kind", "PSNR (fixed peak 1) dB", "DSSIM", "FLIP", "storage B", "positional B", "fit s")
    for r in part["rows"]:
        c, number = _cells(r), _numbers(r)
        lines.append(_line(r["kind"], number("psnr_fixed1", ".2f"), number("dssim", ".4f"), number("flip", ".4f"),
                           c("model_bytes", ","), c("positional_bytes", ","), number("fit_seconds", ".0f")))
    return "\n".join(lines)


def neumip_variants(data: dict) -> str:
    """NeuMIP's channels and learning rate against the Triple Plane: PSNR (fixed peak 1) / DSSIM / FLIP."""
    part = data["neumip_variants"]
    lines = _head("NeuMIP variant", *part["materials"])
    for r in part["rows"]:
        scores = (_cells(r["scores"][m]) for m in part["materials"])
        lines.append(_line(_filled(r, "variant"),
                           *(f"{c('psnr_fixed1', '.2f')} / {c('dssim', '.4f')} / {c('flip', '.4f')}" for c in scores)))
    return "\n".join(lines)


def baselines_synthesis(data: dict) -> str:
    """dynbtf compare --synthesis on the same models (the paper's Fig. 9): synthesis quality per material and kind."""
    lines = _head("material", "kind", "hist feature W1/std", "hist RGB W1/std (gamma 7)",
                  "hist RGB W1/std (gamma 1, the paper's)", "hex RGB W1/std", "tile FLIP on the figure's pair")
    for material, r in _grouped(data["synthesis"]["rows"], lambda r: r["material"]):
        c = _cells(r)
        lines.append(_line(material, r["kind"], c("hist_feature_w1", ".4f"), c("hist_rgb_w1", ".3f"),
                           c("hist_rgb_w1_gamma1", ".3f"), c("hex_rgb_w1", ".3f"), c("tile_flip", ".3f")))
    return "\n".join(lines)


def synthesis_quality(data: dict) -> str:
    """bench_synthesis_quality.py: the quality report per method on one fitted model (each number the mean over the
    synthesis seeds, min-max)."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({data['conditions']}):", ""]
    lines += _head("method", "W1/std feat mean / max", "sliced W1/std", "std ratio (min)", "W1/std RGB (max)",
                   "repetition", "verbatim", "extra storage")
    for r in data["rows"]:
        c = _cells(r)
        lines.append(_line(c("method", text=r["method"]) + _note(r.get("note")),
                           c("feature_w1_mean", text=f"{_spread(r['feature_w1_mean'], '.4f')} / "
                                                     f"{_spread(r['feature_w1_max'], '.4f')}"),
                           c("sliced_w1", text=_spread(r["sliced_w1"], ".4f")),
                           c("std_ratio_min", text=_spread(r["std_ratio_min"], ".3f")),
                           c("rgb_w1_max", text=_spread(r["rgb_w1_max"], ".3f")),
                           c("repetition", text=_spread(r["repetition"], ".3f")),
                           c("verbatim", text=_spread(r["verbatim"], ".3f")),
                           c("extra_storage_mb", text=f"{r['extra_storage_mb']:.3g} MB" if r["extra_storage_mb"]
                             else "0")))
    return "\n".join(lines)


def synthesis_quality_summary(data: dict) -> str:
    """results.md's sentence on synthesis quality, from bench_synthesis_quality.py's data (means over the seeds)."""
    rows = {r["method"]: r for r in data["rows"]}
    default = next(r for r in data["rows"] if r.get("default"))
    tile, linear, hex_ = rows["tile"], rows["linear"], rows["hex"]

    def m(row: dict, key: str) -> float:
        return row[key]["mean"]

    w1_met = max(m(default, "feature_w1_mean"), m(default, "rgb_w1_max")) < 0.05
    rep_met = m(default, "repetition") <= m(tile, "repetition") / 5
    targets = "met" if w1_met and rep_met else ("missed" if not (w1_met or rep_met) else
                                                 "W1/std " + ("met" if w1_met else "missed") + ", repetition "
                                                 + ("met" if rep_met else "missed"))
    model = data["model"]
    return (f"`python benchmarks/bench_synthesis_quality.py` (the quality report of `dynbtf synth MODEL --report`) on "
            f"the stone ({model['size'][0]} x {model['size'][1]} `{model['kind']}`, {model['held_out_psnr']:.1f} dB "
            f"held-out), {default['method']} (gamma {default['gamma']:g}), mean of {len(default['seeds'])} seeds: "
            f"feature W1/std {m(default, 'feature_w1_mean'):.4f} (max {m(default, 'feature_w1_max'):.4f}), RGB "
            f"W1/std {m(default, 'rgb_w1_max'):.3f}, repetition score {m(default, 'repetition'):.3f} (tiling: "
            f"{m(tile, 'repetition'):.1f}); linear blending {m(linear, 'feature_w1_mean'):.2f} / "
            f"{m(linear, 'rgb_w1_max'):.2f}, hex-tiling {m(hex_, 'feature_w1_mean'):.3f} / "
            f"{m(hex_, 'rgb_w1_max'):.3f} (targets feature and RGB W1/std < 0.05 and repetition at most 1/5 of "
            f"tiling's: {targets}).")


def _fixed_peak(first: str, rows: list[dict], label, digits: int) -> str:
    """Held-out PSNR (fixed peak 1), DSSIM and FLIP, a row per fit; a number measured per seed as its mean and
    min-max."""
    lines = _head(first, "held-out PSNR, fixed peak 1 (dB)", "DSSIM", "FLIP")
    for r in rows:
        number = _numbers(r)
        lines.append(_line(label(r), number("psnr_fixed1", ".2f"), number("dssim", f".{digits}f"),
                           number("flip", f".{digits}f")))
    return "\n".join(lines)


def stone_fetch(data: dict) -> str:
    """parallax.md: the stone's quality by where the positional features are fetched. A measured part
    (``measure_stone_limits.py fetch --json``) holds each number per seed; its rows with ``"from": "quality"`` show
    the stone row of quality.json's ``"part"`` (fit_materials.py, the same recipe)."""
    part = data["fetch"]
    if part.get("recorded_from"):
        return _fixed_peak("positional fetch at", part["rows"], lambda r: r["fetch"], 3)
    quality = _load("quality")

    def shown(row: dict) -> dict:
        if "from" not in row:
            return row
        fitted = next(r for r in quality[row["part"]]["rows"] if r["material"] == "stone")
        return {"fetch": row["fetch"]} | {key: fitted[key] for key in ("psnr_fixed1", "dssim", "flip")}

    return "\n".join([f"Measured on {_machine(part)} by `{part['command']}` ({len(part['seeds'])} seeds; "
                      f"{part['conditions']}; the `--repr` rows: the stone of quality.json).", "",
                      _fixed_peak("positional fetch at", [shown(r) for r in part["rows"]], lambda r: r["fetch"], 3)])


def stone_fetch_summary(data: dict) -> str:
    """The sentence that reads the ``fetch`` part (parallax.md, triple_plane.md): the stone's fixed-peak PSNR with the
    positional fetch at the exact visible point (the oracle), at that of the stereo height kept fixed, and at that of
    the height refined by ``--repr triple-parallax`` (quality.json's stone row, for a measured part), against the
    Triple Plane at ``uv``. Means over the seeds of a measured part; a recorded part's single fits as typed."""
    part = data["fetch"]
    quality = None if part.get("recorded_from") else _load("quality")

    def psnr(start: str) -> float:
        row = next(r for r in part["rows"] if r["fetch"].startswith(start))
        if "from" in row:
            row = next(r for r in quality[row["part"]]["rows"] if r["material"] == "stone")
        value = row["psnr_fixed1"]
        return value["mean"] if isinstance(value, dict) else value

    uv, wide = psnr("`uv` (the paper's"), psnr("`uv`, 2x wider")
    fixed, refined, exact = psnr("visible point of the stereo height, kept"), psnr(
        "visible point of the stereo height, refined"), psnr("visible point the simulator")
    over = ("one fit each" if part.get("recorded_from") else f"means of {len(part['seeds'])} seeds") + ", fixed peak 1"
    return (f"The stone ({over}): with the positional fetch at the visible point of the exact height the fit reaches "
            f"{exact:.2f} dB, at that of the stereo height kept fixed {fixed:.2f} dB, and refined by the fit "
            f"(`--repr triple-parallax`) {refined:.2f} dB, {exact - refined:.1f} dB from the exact height; the "
            f"Triple Plane at `uv` reaches {uv:.2f} dB, and a model twice as wide there {wide:.2f} dB. "
            + ("Parallax and masking, not the model's size, are the stone's limit." if exact - uv > 2 * (wide - uv)
               else "Doubling the model gains at least half of what the exact visible point gains."))


#: What the relief scales of the stone table are (the simulator's ``relief`` option).
_RELIEF_NOTES = {0.0: "flat: spatially varying BRDF only", 1.0: "the material as designed"}


def _relief(row: dict) -> float:
    """The relief scale of a stone table's row: recorded as ``relief``, or the ``relief=`` of a measured row's spec
    (the simulator's default, 1, where the spec gives none)."""
    if "relief" in row:
        return float(row["relief"])
    found = re.search(r"[?&]relief=([0-9.]+)", row["spec"])
    return float(found.group(1)) if found else 1.0


def stone_relief(data: dict) -> str:
    """triple_plane.md: the Triple Plane's quality against the simulator's relief scale. A measured part
    (fit_materials.py ``--json``) holds each number per seed, the best mean PSNR marked."""
    part = data["relief"]
    rows = part["rows"]
    lines = []
    if not part.get("recorded_from"):
        rows = [r | {"bold": ["psnr_fixed1"]} if r is max(rows, key=lambda r: r["psnr_fixed1"]["mean"]) else r
                for r in rows]
        lines = [f"Measured on {_machine(part)} by `{part['command']}` ({len(part['seeds'])} seeds; "
                 f"{part['conditions']}).", ""]
    return "\n".join(lines + [_fixed_peak("`sim:stone?size=128&relief=...`", rows,
                                           lambda r: f"{_relief(r):g}" + _note(r.get("note") if "relief" in r else
                                                                            _RELIEF_NOTES.get(_relief(r))), 4)])


def stone_limits(data: dict) -> str:
    """measure_stone_limits.py: data (an oracle), fit (training vs held-out) and model (view subsets) on the stone.
    A measured part (``limits --json``) holds each number per seed (its mean and min-max)."""
    part = data["limits"]
    lines = [] if part.get("recorded_from") else [
        f"Measured on {_machine(part)} by `{part['command']}` ({len(part['seeds'])} seeds; {part['conditions']}).", ""]
    lines += _head("measurement (stone, relief 1, 128^2)" if part.get("recorded_from") else "measurement",
                   "PSNR on training pairs", "PSNR on held-out pairs")
    for r in part["rows"]:
        number = _numbers(r)
        alone = r.get("nearest_light_psnr_held_out")
        if isinstance(alone, dict):
            alone = _spread(alone, ".2f")
        elif alone is not None:
            alone = f"{alone:.2f}"
        lines.append(_line(r["measurement"], number("psnr_training", ".2f"), number("psnr_held_out", ".2f")
                           + (f" (nearest light alone: {alone})" if alone is not None else "")))
    return "\n".join(lines)


def stone_limits_summary(data: dict) -> str:
    """The sentence that reads measure_stone_limits.py's measured ``limits`` part (means over the seeds): what the
    data supports (the oracle), whether the fit over-fits (training against held-out) and where capacity goes (the
    normal view alone against all views)."""
    part = data["limits"]
    rows = part["rows"]
    oracle = next(r for r in rows if r["measurement"].startswith("oracle"))
    every = next(r for r in rows if r["measurement"].startswith("the fit of all"))
    normal = next(r for r in rows if r["measurement"].startswith("the normal view only"))
    views = re.search(r"all (\d+) views", every["measurement"])[1]
    training, held_out = every["psnr_training"]["mean"], every["psnr_held_out"]["mean"]
    gap = training - held_out
    fit = (f"the fit does not over-fit (training {training:.2f} dB, held-out {held_out:.2f})" if gap < 1.0 else
           f"the fit over-fits by {gap:.1f} dB (training {training:.2f} dB, held-out {held_out:.2f})")
    return (f"Means of {len(part['seeds'])} seeds, fixed peak 1: an oracle interpolating the 3 nearest measured "
            f"lights at the same view reaches {oracle['psnr_held_out']['mean']:.2f} dB on held-out pairs (the "
            f"nearest light alone {oracle['nearest_light_psnr_held_out']['mean']:.2f}), so the grid supports "
            f"{oracle['psnr_held_out']['mean']:.1f} dB; {fit}; and capacity goes to the view dependence: the normal "
            f"view alone is fitted to {normal['psnr_training']['mean']:.2f} dB, all {views} views to "
            f"{training:.2f}.")


def fullsize(data: dict) -> str:
    """results.md's full-size table: a line per measurement, its command in the first column. A row with ``"from"``
    is rendered from that benchmark's data by :data:`_FULLSIZE_FROM` of its ``"view"``; the others are recorded."""
    lines = _head("what", "result", "target")
    for r in data["summary"]["rows"]:
        cells = globals()[_FULLSIZE_FROM[r["view"]]](_load(r["from"])) if "from" in r else \
            tuple(_filled(r, key) for key in ("what", "result", "target"))
        lines.append(_line(*cells))
    return "\n".join(lines)


#: The full-size table's rows rendered from data: ``"view"`` -> the function of the data file that gives the row's
#: (what, result, target).
_FULLSIZE_FROM = {"throughput": "fullsize_throughput", "file": "fullsize_file", "curve": "fullsize_curve_row",
                  "parallax_throughput": "fullsize_parallax_throughput",
                  "parallax_curve": "fullsize_parallax_curve_row"}


def fullsize_throughput(data: dict) -> tuple[str, str, str]:
    """The full-size table's throughput row from bench_training_large.py's data: each recipe's rate on the DFMF file
    over its rate on the cached BTF (without the sub-texel term), and the largest peak RSS."""
    rows = {r["recipe"]: r for r in data["rows"] if not r["subtexel"]}
    fast, paper = rows["fast"], rows["paper batches"]
    peak = max(r["peak_rss_gb"] for r in rows.values())
    met = all(r["ratio"] >= 0.8 for r in rows.values()) and peak <= 4.0
    return (f"training throughput, 400 x 400 DFMF file vs a cached 128 x 128 BTF (`{data['command']}`, "
            f"{_machine(data)})",
            f"{fast['ratio']:.2f}x (fast recipe, {fast['large_msps']:.1f} vs {fast['cached_msps']:.1f} M samples/s), "
            f"{paper['ratio']:.2f}x (paper batches); peak memory {peak:.2f} GB",
            f"at least 0.8x, at most 4 GB ({'met' if met else 'not met'})")


def fullsize_parallax_throughput(data: dict) -> tuple[str, str, str]:
    """The full-size table's ``triple-parallax`` row from bench_training_large.py ``--repr triple-parallax``: the
    fast recipe's rate on the DFMF file and on the cached BTF, its step time and peak RSS (the stereo height's
    memory included), and the stereo's seconds at both sizes."""
    if data.get("representation") != "triple-parallax":
        raise ValueError(f"fullsize_parallax_throughput: a run of --repr triple-parallax expected, got "
                         f"{data.get('representation')!r}")
    row = next(r for r in data["rows"] if r["recipe"] == "fast" and not r["subtexel"])
    peak = row["peak_rss_gb"]
    return (f"`triple-parallax`: training throughput and peak memory, stereo height included (`{data['command']}`, "
            f"{_machine(data)}, level {data['isa']})",
            f"{row['large_msps']:.2f} M samples/s on the 400 x 400 file vs {row['cached_msps']:.2f} on the cached "
            f"128 x 128 ({row['ratio']:.2f}x; {row['step_seconds']:.2f} s per step); peak memory **{peak:.2f} GB**; "
            f"the stereo height {row['stereo_seconds_large']:.0f} s at 400 x 400, "
            f"{row['stereo_seconds_cached']:.0f} s at 128 x 128",
            f"at most 4 GB ({'met' if peak <= 4.0 else 'not met'})")


def fullsize_file(data: dict) -> tuple[str, str, str]:
    """The full-size table's row of writing the DFMF file, from the run of bench_training_large.py that wrote it."""
    written = data["file_written"]
    return (f"writing the file (`{written['command']}`, {_machine(data)})",
            f"{written['seconds'] / 60:.1f} min, {written['bytes'] / 1e6:.0f} MB, {written['peak_rss_gb']:.1f} GB "
            "peak memory", "")


def training_large(data: dict) -> str:
    """bench_training_large.py --json: samples/s on the full-size DFMF file and a cached 128 x 128 BTF per recipe
    and sub-texel weight on one level, and the projected time of a full-size fit to within 0.5 dB."""
    lines = [f"Measured on {_machine(data)}, level {data['isa_description']}, by `{data['command']}` "
             f"({data['steps']} timed steps after {data['warmup']}, data waits included; projected: "
             f"{data['steps_to_converge']:,} steps to within 0.5 dB of converged, times the median step):", ""]
    lines += _head("recipe", "sub-texel term", "cached 128 x 128 (M samples/s)", "400 x 400 DFMF (M samples/s)",
                   "ratio", "s per step at 400 x 400", "peak RSS", "to within 0.5 dB (projected)")
    lines += [_line(r["recipe"], f"x{r['subtexel']:g}" if r["subtexel"] else "off", f"{r['cached_msps']:.2f}",
                    f"{r['large_msps']:.2f}", f"{r['ratio']:.2f}", f"{r['step_seconds']:.3f}",
                    f"{r['peak_rss_gb']:.2f} GB", f"**{r['projected_minutes']:.0f} min**") for r in data["rows"]]
    return "\n".join(lines)


#: What each recipe of bench_training_large.py is, for the data-path table.
_RECIPE_NOTES = {"paper batches": "16 whole images per step", "fast": "64 texel groups, what `dynbtf fit` picks"}


def fullsize_data_path(data: dict) -> str:
    """bench_training_large.py: samples/s from the 400 x 400 DFMF file against a cached 128 x 128 BTF, per recipe
    (without the sub-texel term), on the CPU's own level."""
    lines = [f"Measured on {_machine(data)}, level {data['isa_description']}, by `{data['command']}` "
             f"({data['steps']} timed steps after {data['warmup']} warm-up steps, data waits included):", ""]
    lines += _head("recipe", "cached 128 x 128 (M samples/s)", "400 x 400 DFMF (M samples/s)", "ratio",
                   "peak RSS at 400 x 400")
    lines += [_line(f"{r['recipe']} ({_RECIPE_NOTES[r['recipe']]})", f"{r['cached_msps']:.2f}",
                    f"{r['large_msps']:.2f}", f"**{r['ratio']:.2f}**", f"{r['peak_rss_gb']:.2f} GB")
              for r in data["rows"] if not r["subtexel"]]
    return "\n".join(lines)


def _minutes(p: dict) -> str:
    return f"{p['minutes']:g}" + (" (end)" if p.get("end") else "")


def fullsize_curve(data: dict) -> str:
    """measure_fit_curves.py on the full-size file (``--json ... --part curve``): held-out PSNR against training
    time, at most :data:`_CURVE_COLUMNS` of its scores (evenly spaced, the last always), and the time after which it
    stays within 0.5 dB of its final PSNR."""
    return _curve_table(data["curve"])


def _curve_table(c: dict) -> str:
    """A measured convergence curve (a part measure_fit_curves.py ``--json`` wrote) as :func:`fullsize_curve` shows
    it."""
    level = _level(c["isa"], c["cpu_isa"])
    every = -(-len(c["points"]) // _CURVE_COLUMNS)
    points = c["points"][every - 1::every]
    points += [] if points[-1] is c["points"][-1] else [c["points"][-1]]
    lines = [f"Measured on {_machine(c)}, level {level}, by `{c['command']}` (`{c['btf'].rsplit('/', 1)[-1]}`, the "
             f"{c['recipe']}; held-out PSNR with the per-image peak, 16 pairs"
             + (f"; {c['note']}" if c.get("note") else "") + "):", ""]
    lines += _transposed(points, ("training time (min)", lambda p: f"{p['minutes']:.0f}"),
                         ("step", lambda p: f"{p['step']:,}"),
                         ("held-out PSNR (dB)", lambda p: f"{p['psnr']:.2f}")).split("\n")
    stereo = f" (the stereo height before it: {c['stereo_seconds']:.0f} s)" if c.get("stereo_seconds") else ""
    lines += ["", f"Within 0.5 dB of the final {c['final_psnr']:.2f} dB after **{c['minutes_to_within_0_5_db']:.0f} "
              f"min** of training; {c['steps']:,} steps in {c['training_minutes']:.0f} min in all, "
              f"{c['seconds_per_step']:.2f} s per step{stereo}."]
    return "\n".join(lines)


#: The most scores :func:`fullsize_curve` shows.
_CURVE_COLUMNS = 10


def fullsize_curve_row(data: dict) -> tuple[str, str, str]:
    """The full-size table's row of the convergence curve (:func:`fullsize_curve`), against the 2-hour target of a
    full-size fit on AVX2."""
    c = data["curve"]
    level = _level(c["isa"], c["cpu_isa"])
    met = c["minutes_to_within_0_5_db"] <= 120
    return (f"time to within 0.5 dB of the final held-out PSNR (`{c['command']}`, {_machine(c)}, level {level})",
            f"**{c['minutes_to_within_0_5_db']:.0f} min** ({c['final_psnr']:.1f} dB at the end; the whole fit "
            f"{c['training_minutes']:.0f} min)",
            f"at most 2 h on AVX2 ({'met' if met else 'not met'})" if c["isa"] == "avx2" else "")


def fullsize_parallax_curve(data: dict) -> str:
    """The same with --repr triple-parallax (``--part parallax_curve``; a part recorded from the hand-typed table:
    its scores alone)."""
    c = data["parallax_curve"]
    if "recorded_from" not in c:
        return _curve_table(c)
    return _transposed(c["points"], ("training (min)", _minutes),
                       ("step", lambda p: f"{p['step']:,}"), ("held-out PSNR (dB)", lambda p: f"{p['psnr']:.2f}"))


def fullsize_parallax_curve_row(data: dict) -> tuple[str, str, str]:
    """The full-size table's ``triple-parallax`` convergence row from the measured ``parallax_curve`` part, beside
    the Triple Plane's measured curve, against the 90-minute target of a full-size parallax fit."""
    c, flat = data["parallax_curve"], data["curve"]
    met = c["minutes_to_within_0_5_db"] <= 90
    return (f"`triple-parallax`: time to within 0.5 dB of the final held-out PSNR (`{c['command']}`, "
            f"{_machine(c)}, level {_level(c['isa'], c['cpu_isa'])})",
            f"**{c['minutes_to_within_0_5_db']:.0f} min** of training (step {c['steps_to_within_0_5_db']:,} of "
            f"{c['steps']:,}, {c['seconds_per_step']:.2f} s per step; the stereo height before it "
            f"{c['stereo_seconds']:.0f} s), {c['final_psnr']:.2f} dB at the end; the Triple Plane's curve above ends "
            f"at {flat['final_psnr']:.2f} dB",
            f"at most 90 min ({'met' if met else 'not met'})")


def sampling(data: dict) -> str:
    """bench_sampling.py: MSE of cosine and mixture (importance) sampling, at equal spp and equal time."""
    lines = _head("model", "lighting", "MSE cosine", "MSE mixture", "equal spp: cosine / mixture",
                  "s per render cosine / mixture", "equal time: cosine / mixture", "`auto` picks")
    lines += [_line(_named(r, "model"), r["lighting"], f"{r['mse_cosine']:.3e}", f"{r['mse_mixture']:.3e}",
                    f"**{r['equal_spp_ratio']:.2f}x**", f"{r['seconds_cosine']:.3f} / {r['seconds_mixture']:.3f}",
                    f"**{r['equal_time_ratio']:.2f}x**", r["auto"]) for r in data["rows"]]
    return "\n".join(lines)


def web_struct(data: dict) -> str:
    """bench_web.py on a structured stand-in model: frame time, cost, agreement and size per method."""
    lines = _head("method", "ms / frame (1280 x 720, SwiftShader)", "texel fetches / pixel",
                  "multiply-adds / pixel", "fp16 PSNR vs library", "u8 PSNR", "bytes for the method, fp16 / u8",
                  spaced=True)
    for r in data["struct"]["rows"]:
        tables = f" (of which the int16 tables {r['tables_mb']:.2f} MB)" if r.get("tables_mb") else ""
        lines.append(_line(r["method"], _range(r["ms_per_frame"], ","),
                           f"{r['texel_fetches']}{_note(r.get('note'))}",
                           f"{r['multiply_adds']:,}", _range(r["psnr_fp16_db"], ".1f") + " dB",
                           _range(r["psnr_u8_db"], ".1f") + " dB", f"{r['fp16_mb']:.2f} / {r['u8_mb']:.2f} MB{tables}"))
    return "\n".join(lines)


def web_frame_time(data: dict) -> str:
    """bench_web.py: frame time and cost per pixel per method, and the paper's."""
    part = data["frame_time"]
    lines = _head("method", "ms / frame", "ns / pixel", "vs the paper's ns / pixel", "texel fetches / pixel",
                  "multiply-adds / pixel", spaced=True)
    lines += [_line(r["method"], _range(r["ms_per_frame"], ","), _range(r["ns_per_pixel"], ","),
                    _range(r["vs_paper"], ",") + "x", f"{r['texel_fetches']}", f"{r['multiply_adds']:,}")
              for r in part["rows"]]
    p = part["paper"]
    lines.append(_line(f"the paper ({p['gpu']})",
                       f"{p['ms_per_frame']:g} ({p['ms_per_frame_1080p']:.1f} ms at 1920 x 1080)",
                       f"{p['ns_per_pixel']:g}", "1", "not given", f"{p['multiply_adds']:,} in its decoder"))
    return "\n".join(lines)


def web_agreement(data: dict) -> str:
    """bench_web.py: PSNR of the shader against the library per method and texture precision."""
    lines = _head("method", "fp16", "u8", spaced=True)
    lines += [_line(r["method"], f"{r['psnr_fp16_db']:.1f}", f"{r['psnr_u8_db']:.1f}")
              for r in data["agreement"]["rows"]]
    return "\n".join(lines)


def web_size(data: dict) -> str:
    """bench_web.py: the export's bytes and its held-out PSNR per texture precision."""
    s = data["size"]
    mb, every, psnr = s["hist_mb"], s["all_methods_mb"], s["held_out_psnr_db"]
    return "\n".join(_head("", "fp32 model", "fp16 export", "u8 export", spaced=True) + [
        _line("bytes for `hist` (plane, tables, angular planes, decoder)", f"{s['model_mb']:.2f} MB (model file)",
              f"{mb['fp16']:.2f} MB", f"**{mb['u8']:.2f} MB** ({s['u8_of_model']:.2f}x)"),
        _line("all three methods", "", f"{every['fp16']:.2f} MB", f"{every['u8']:.2f} MB"),
        _line("held-out PSNR", f"{psnr['fp32']:.3f} dB",
              f"{psnr['fp16']:.3f} dB (loss < {s['fp16_loss_below_db']:g} dB)",
              f"{psnr['u8']:.3f} dB (loss **{psnr['fp32'] - psnr['u8']:.3f} dB**)")])


def web_checks(data: dict) -> str:
    """realtime.md: what tests/test_web_export.py checks in the browser, and what it measured."""
    return _prose(data["checks"], ("check", "check"), ("result", "result"), spaced=True)


def filtering(data: dict) -> str:
    """bench_filtering.py: FLIP and far-field colour error of each kind of query, 1 sample per pixel."""
    seeds = data.get("seeds")
    spread = f" (mean of {len(seeds)} seeds; min-max)" if seeds else ""
    lines = _head("1 sample per pixel", "FLIP vs reference" + spread, "far-field mean colour error" + spread)
    for r in data["rows"]:
        c = _cells(r)
        flip_range = f" ({r['flip_range'][0]:.4f}-{r['flip_range'][1]:.4f})" if "flip_range" in r else ""
        error_range = (f" ({r['far_field_error_range'][0]:.2f}-{r['far_field_error_range'][1]:.2f}%)"
                       if "far_field_error_range" in r else "")
        lines.append(_line(c("query"), c("flip", ".4f") + flip_range,
                           c("far_field_error_percent", text=f"{r['far_field_error_percent']:.2f}%") + error_range))
    cost = data.get("cost")
    if cost:
        point, default = data["rows"][0], data["rows"][-1]
        ratio = default["flip"] / point["flip"]
        ns = cost["eval_ns_per_query"]
        text = (f"Measured on {_machine(data)} by `{data['command']}`. The default's FLIP is {ratio:.3f} of the point "
                f"query's (target at most 0.5: {'met' if ratio <= 0.5 else 'missed'}; at most 0.05: "
                f"{'met' if default['flip'] <= 0.05 else 'missed'}), its far-field error "
                f"{default['far_field_error_percent']:.2f}% (target 2%: "
                f"{'met' if default['far_field_error_percent'] <= 2 else 'missed'}). Cost per query (seed "
                f"{cost['seed']}, {cost['queries']:,} queries, best of {cost['repeats']}): "
                f"{ns['filtered']:.0f} vs {ns['point']:.0f} ns in `SynthesizedBTF.eval` "
                f"({ns['filtered'] / ns['point']:.2f}x; target at most 1.5x: "
                f"{'met' if ns['filtered'] <= 1.5 * ns['point'] else 'missed'})")
        plugin = cost.get("plugin")
        if plugin:
            pns, scene = plugin["ns_per_query"], plugin["scene_flip"]
            text += (f", {pns['filtered']:.0f} vs {pns['point']:.0f} ns in the Mitsuba plugin "
                     f"({pns['filtered'] / pns['point']:.2f}x), which matches `SynthesizedBTF.eval` with the same "
                     f"footprints to {_sci(plugin['max_abs_difference'])}; "
                     f"in Mitsuba's own grazing `plane` scene ({plugin['scene_pixels'][0]} x "
                     f"{plugin['scene_pixels'][1]} pixels, 1 spp vs {plugin['scene_reference_spp']} spp, point light) "
                     f"FLIP falls from {scene['unfiltered (point query)']:.3f} to {scene['filtered (ray cone)']:.3f}")
        text += (f". Nothing is added to the model file ({cost['model_file_bytes'] / 1e6:.2f} MB); the pyramid and "
                 f"per-level tables take {cost['memory_bytes'] / 1e6:.2f} MB in memory.")
        lines += ["", text]
    return "\n".join(lines)


def _spread(spread: dict, spec: str, unit: str = "", scale: float = 1.0) -> str:
    """A number measured per seed: ``0.049 (0.047-0.051)``, the mean and the min-max (the mean alone where the
    range rounds to one value)."""
    mean, (lo, hi) = (format(scale * spread["mean"], spec), [format(scale * v, spec) for v in spread["range"]])
    return f"{mean}{unit}" if lo == hi else f"{mean}{unit} ({lo}-{hi}{unit})"


def _exponent_table(data: dict) -> dict:
    """measure_blend_exponent.py's rows by model: ``{label: {"tile": spread, "hex": spread, gamma: spread, ...}}``
    (RGB W1/std; hist with decorrelation), with ``"area"`` and ``"verbatim"`` the same per column."""
    table: dict = {}
    for r in data["rows"]:
        if r["method"] in ("tile", "hex") or (r["method"] == "hist" and r["decorrelate"]):
            column = r["gamma"] if r["method"] == "hist" else r["method"]
            table.setdefault(r["model"], {})[column] = r
    return table


def _pooled(rows: list[dict], key: str) -> dict:
    """The mean of the rows' means of ``key``, and the min-max of every row's per-seed values."""
    values = [v for r in rows for v in r[key]["per_seed"]]
    return {"mean": sum(r[key]["mean"] for r in rows) / len(rows), "range": [min(values), max(values)]}


def _exponent_findings(data: dict) -> dict:
    """What the exponent table shows: gamma 1 over the default per model, the default against hex and the largest
    exponent, the area blended."""
    table, gammas, default = _exponent_table(data), data["gammas"], data["default_gamma"]
    w1 = {m: {c: r["rgb_w1_max"]["mean"] for c, r in cols.items()} for m, cols in table.items()}
    top = max(gammas)
    area = {c: _pooled([cols[c] for cols in table.values()], "area_blended")["mean"] for c in (*gammas, "hex")}
    return {"models": len(w1), "gain": [min(v[1.0] / v[default] for v in w1.values()),
                                        max(v[1.0] / v[default] for v in w1.values())],
            "below_hex": [m for m, v in w1.items() if v[default] < v["hex"]],
            "top": top, "top_lower": [m for m, v in w1.items() if v[top] < v[default]],
            "best": {m: min(gammas, key=lambda g: v[g]) for m, v in w1.items()}, "area": area}


def _count(names: list, total: int) -> str:
    """``all seven``, or ``4 of 7 (leather, stone, ...)``."""
    words = {2: "both", 3: "all three", 4: "all four", 5: "all five", 6: "all six", 7: "all seven", 8: "all eight"}
    if len(names) == total:
        return words.get(total, f"all {total}")
    return f"{len(names)} of {total}" + (f" ({', '.join(names)})" if names else "")


def blend_exponent(data: dict) -> str:
    """measure_blend_exponent.py: RGB W1/std per model and blending exponent (mean over the seeds, min-max), the
    default's column bold; then what the table shows."""
    gammas, default = data["gammas"], data["default_gamma"]
    table = _exponent_table(data)
    models = {m["label"]: m for m in data["models"]}

    def row(label: str, cells: dict, fmt) -> str:
        return _line(label, fmt(cells["tile"]) if "tile" in cells else "",
                     *(f"**{fmt(cells[g])}**" if g == default else fmt(cells[g]) for g in gammas), fmt(cells["hex"]))

    def fitted(label: str) -> str:
        m = models.get(label)
        if not m:
            return label
        size = f"{m['size'][0]} x {m['size'][1]}, " if m.get("size") else ""
        return (f"{label} ({size}{m['epochs']:.1f} epochs in {m['training_minutes']:.1f} min, "
                f"{m['held_out_psnr']:.1f} dB)")

    heads = (("hist " if i == 0 else "") + f"g{g:g}" for i, g in enumerate(gammas))
    kinds = ", ".join(f"`{k}`" for k in sorted({m["kind"] for m in data["models"]}))
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({data['conditions']}). The models ({kinds}): "
             "their size, training and held-out PSNR after their names.", ""]
    lines += _head("model", "tile",
                   *(f"**{h} (default)**" if g == default else h for g, h in zip(gammas, heads)), "hex")
    lines += [row(fitted(m), {c: r["rgb_w1_max"] for c, r in cols.items()}, lambda v: _spread(v, ".3f"))
              for m, cols in table.items()]
    columns = {c: [cols[c] for cols in table.values()] for c in (*gammas, "hex")}
    lines.append(row("area blended (largest weight < 0.9), mean over the models",
                     {c: _pooled(rs, "area_blended") for c, rs in columns.items()},
                     lambda v: _spread(v, ".0f", "%", 100)))
    lines.append(row("verbatim texels (report), mean over the models",
                     {c: _pooled(rs, "verbatim") for c, rs in columns.items()}, lambda v: _spread(v, ".2f")))
    f = _exponent_findings(data)
    n = f["models"]
    best = sorted(set(f["best"].values()))
    lines += ["", f"gamma {default:g} is {f['gain'][0]:.1f}-{f['gain'][1]:.1f}x below gamma 1 and below hex on "
                  f"{_count(f['below_hex'], n)} models, with {100 * f['area'][default]:.0f}% of the surface still "
                  f"blended; `--gamma {f['top']:g}` is lower still on {_count(f['top_lower'], n)} "
                  f"({100 * f['area'][f['top']]:.0f}% blended, hex {100 * f['area']['hex']:.0f}%: hex-like "
                  "transitions). The lowest of the exponents measured: "
                  + "; ".join(f"gamma {g:g} on {_count([m for m, b in f['best'].items() if b == g], n)}"
                              for g in best) + "."]
    return "\n".join(lines)


def blend_exponent_summary(data: dict) -> str:
    """synthesis.md's sentence on the blending exponent, from measure_blend_exponent.py's data."""
    default, f = data["default_gamma"], _exponent_findings(data)
    n = f["models"]
    words = dict(enumerate(("no", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")))
    return (f"On {words.get(n, n)} fitted models (`python benchmarks/measure_blend_exponent.py MODEL...`; table in "
            f"[results.md](results.md#blending-exponent-per-model)) gamma {default:g} gives "
            f"{f['gain'][0]:.1f}-{f['gain'][1]:.1f}x lower RGB W1/std than gamma 1 and is below hex on "
            f"{_count(f['below_hex'], n)}, with {100 * f['area'][default]:.0f}% of the surface still blended (gamma 1: "
            f"{100 * f['area'][1.0]:.0f}%); `--gamma {f['top']:g}` is lower still on {_count(f['top_lower'], n)}, "
            "with hex-like transitions.")


def _structured_ranges(data: dict, materials, method: str, key: str) -> list[float]:
    """The lowest and highest per-seed value of ``key`` (every scale) over ``method``'s rows of ``materials``."""
    values = []
    for r in data["rows"]:
        if r["material"] in materials and r["method"] == method:
            spreads = r[key] if isinstance(r[key], list) else [r[key]]
            values += [v for s in spreads for v in s["per_seed"]]
    return [min(values), max(values)]


def _rows_of(data: dict, materials, method: str, key: str) -> list:
    """``key`` of ``method``'s rows of ``materials``."""
    return [r[key] for r in data["rows"] if r["material"] in materials and r["method"] == method]


def _times(x: float) -> str:
    """A ratio: two decimals below 10 (``0.25``, ``1.06``), else whole (``64``)."""
    return f"{x:.2f}" if x < 10 else f"{x:.0f}"


def _span(values: list[float], spec: str) -> str:
    """``0.92-0.97``: the lowest and highest of ``values``, or one number where they format alike."""
    lo, hi = format(min(values), spec), format(max(values), spec)
    return lo if lo == hi else f"{lo}-{hi}"


def whole_elements(data: dict) -> str:
    """bench_whole_elements.py: broken bricks, coherence p90 and identity per held-out wall and method (mean over the
    seeds, min-max); then the targets, met or missed per wall (struct, and struct on the wall fitted with
    ``--texels whole`` where that resampled it)."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({len(data['seeds'])} seeds, {data['scale']:g} "
             f"repeats, {data['size']} x {data['size']} walls).", ""]
    lines += _head("wall", "method", "broken bricks", "coherence p90", "identity")
    for row in data["rows"]:
        bricks = row["broken_bricks"]
        lines.append(_line(row["material"], row["method"], "-" if bricks is None else _spread(bricks, ".1%"),
                           _spread(row["coherence_p90"], ".3f"), _spread(row["identity"], ".3f")))
    verdicts = []
    for row in data["rows"]:
        if row["method"] in ("struct", "struct, --texels whole"):
            p90, identity = row["coherence_p90"]["range"][1], row["identity"]["range"][1]
            how = " with --texels whole" if row["method"] != "struct" else ""
            verdicts.append(f"{row['material']}{how} {'met' if p90 <= 0.10 and identity <= 0.35 else 'missed'} "
                            f"(p90 at most {p90:.3f}, identity at most {identity:.3f}; broken bricks at most "
                            f"{row['broken_bricks']['range'][1]:.1%})")
    lines += ["", "Targets (struct: coherence p90 at most 0.10 with identity at most 0.35, every seed): "
              + "; ".join(verdicts) + "."]
    return "\n".join(lines)


def rotation(data: dict) -> str:
    """bench_rotation.py: repetition, colour, orientation coherence under a grazing light and cost per model and
    setting (the mean over the seeds, min-max)."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({len(data['seeds'])} seeds, {data['repeats']} "
             f"repeats; light at theta {data['light'][0]:g} deg for the orientation; cost: "
             f"{data['queries']:,} random queries side by side):", ""]
    lines += _head("material", "setting", "repetition", "RGB W1/std", "orientation coherence", "cost / hist")
    for row in data["rows"]:
        lines.append(_line(row["material"].replace("_", " "), row["setting"], _spread(row["repetition"], ".4f"),
                           _spread(row["rgb_w1"], ".3f"),
                           f"{_spread(row['orientation_coherence'], '.3f')}; exemplar "
                           f"{row['exemplar_orientation_coherence']:.3f}", f"{row['cost_vs_hist']:.2f}x"))
    return "\n".join(lines)


def scale_jitter(data: dict) -> str:
    """bench_scale_jitter.py: repetition, colour, mean colour and cost per material, model (without or with the
    sub-texel term) and setting (the mean over the seeds, min-max)."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({len(data['seeds'])} seeds, {data['repeats']} "
             "repeats; mean colour: the one farthest from hist's over the quality report's pairs; cost: random "
             "queries side by side, on the model with the term):", ""]
    lines += _head("material", "sub-texel term", "setting", "repetition", "RGB W1/std", "mean colour / hist's",
                   "cost / hist")
    for row in data["rows"]:
        cost = row.get("cost_vs_hist")
        lines.append(_line(row["material"].replace("_", " "), row["subtexel_term"], row["setting"],
                           _spread(row["repetition"], ".4f"), _spread(row["rgb_w1"], ".3f"),
                           _spread(row["mean_ratio"], ".3f"), "-" if cost is None else f"{cost:.2f}x"))
    return "\n".join(lines)


def between_texels(data: dict) -> str:
    """measure_between_texels.py: a model's colours between texel centres against its colours at the centres, a
    row per model and offset."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` (`tile`, every texel of one repeat, the quality "
             f"report's {len(data['pairs'])} view/light pairs; W1/std: the largest over channels and pairs; mean colour "
             "over the centres': the smallest over the pairs). The models: their size, training and held-out PSNR.", ""]
    lines += _head("model", "offset from the texel centres (texels)", "RGB W1/std", "mean colour / the centres'",
                   "RGB W1/std of the centres' bilinear mix")
    for row in data["rows"]:
        m = row["model"]
        psnr = "" if m.get("held_out_psnr") is None else f", {m['held_out_psnr']:.1f} dB"
        epochs = "" if m.get("epochs") is None else f", {m['epochs']:.3g} epochs"
        name = f"{Path(m['file']).stem.replace('_', ' ')} ({m['size'][0]}^2{epochs}{psnr})"
        dx, dy = row["offset_texels"]
        floor = row.get("centres_mix_rgb_w1")
        lines.append(_line(name, f"({dx:g}, {dy:g})", f"{row['rgb_w1']:.3f}", f"{row['mean_ratio']:.3f}",
                           "-" if floor is None else f"{floor:.3f}"))
    return "\n".join(lines)


def subtexel(data: dict) -> str:
    """bench_subtexel.py: held-out quality at texel centres and the colours between them, per BTF and sub-texel
    weight (the mean over the seeds, min-max), and the training time against the fit without the term."""
    dx, dy = data["offset_texels"]
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({len(data['seeds'])} seeds, {data['epochs']} "
             f"epochs of the fast recipe, {data['precision']} training; between centres: ({dx:g}, {dy:g}) texels off, "
             "the largest W1/std and smallest mean ratio over the quality report's pairs).", ""]
    lines += _head("BTF", "--subtexel", "held-out PSNR, fixed peak 1 (dB)", "FLIP", "between centres: RGB W1/std",
                   "the centres' mix (floor)", "between centres: mean / the centres'", "training time")
    base = {r["spec"]: r for r in data["rows"] if r["weight"] == 0}
    for row in data["rows"]:
        time_ratio = row["training_minutes"]["mean"] / base[row["spec"]]["training_minutes"]["mean"]
        lines.append(_line(f"`{row['spec']}`", f"{row['weight']:g}", _spread(row["psnr_fixed1"], ".2f"),
                           _spread(row["flip"], ".4f"), _spread(row["between_rgb_w1"], ".3f"),
                           f"{row['centres_mix_rgb_w1']['mean']:.3f}", _spread(row["between_mean_ratio"], ".3f"),
                           f"{time_ratio:.2f}x"))
    return "\n".join(lines)


def structured(data: dict) -> str:
    """bench_structured.py: coherence and identity per scale, repetition, colour (each the mean over the seeds,
    min-max), cost and storage per method; ``*`` marks auto's choice; then the targets, met or missed."""
    scales = " / ".join(f"{s:g}x" for s in data["scales"])
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({data['conditions']}). `*` marks `auto`'s "
             "choice.", ""]
    lines += _head("material", "method", f"coherence p90 {scales}", f"identity {scales}", "repetition",
                   "RGB W1/std", "cost / hist", "storage")
    for material, r in _grouped(data["rows"], lambda r: r["material"]):
        c = _cells(r)

        def scaled(key: str) -> str:
            return c(key, text=" / ".join(_spread(v, ".3f") for v in r[key]))

        cost, storage = r["cost_vs_hist"], r["storage_vs_plane"]
        lines.append(_line(material, c("method", text=_named(r, "method") + ("*" if r.get("chosen") else "")),
                           scaled("coherence_p90"), scaled("identity"), _spread(r["repetition"], ".3f"),
                           _spread(r["rgb_w1"], ".3f"), "-" if cost is None else f"{cost:.2f}",
                           f"{_times(storage)}x" if storage else "0"))
    structured_ = data["structured"]
    stochastic = [m for m in data["choices"] if m not in structured_]
    coh = _structured_ranges(data, structured_, "struct", "coherence_p90")
    ident = _structured_ranges(data, structured_, "struct", "identity")
    choices, threshold = data["choices"], data["structure_threshold"]
    picks_struct = all(choices[m]["method"] == "struct" for m in structured_)
    picks_hist = all(choices[m]["method"] == "hist" for m in stochastic)
    cost = [r["cost_vs_hist"] for r in data["rows"] if r["method"] == "struct" and r["cost_vs_hist"] is not None]
    storage = _rows_of(data, structured_, "struct", "storage_vs_plane")
    build = _rows_of(data, data["choices"], "struct", "build_seconds")
    large = data.get("large_build")
    rep_struct = _structured_ranges(data, structured_, "struct", "repetition")
    rep_stoch = _structured_ranges(data, stochastic, "struct", "repetition")
    rep_hist = _structured_ranges(data, stochastic, "hist", "repetition")

    def met(ok: bool) -> str:
        return "met" if ok else "missed"

    text = (f"Targets: on the structured materials coherence p90 at most 0.10 and identity at most 0.35 (struct: "
            f"{_span(coh, '.3f')} and {_span(ident, '.2f')} over every scale and seed: "
            f"{met(coh[1] <= 0.10 and ident[1] <= 0.35)}; `auto` picks struct there: {met(picks_struct)}); on "
            f"{' and '.join(stochastic)} `auto` picks hist ({met(picks_hist)}; structure strength "
            f"{' and '.join(format(choices[m]['strength'], '.2f') for m in stochastic)} against the threshold "
            f"{threshold:.2f}, the structured materials "
            f"{_span([choices[m]['strength'] for m in structured_], '.2f')}); struct's cost per query "
            f"{_span(cost, '.2f')}x hist's in `SynthesizedBTF.eval` (at most 1.5x: {met(max(cost) <= 1.5)}; "
            "the Mitsuba plugin's kernel: `python benchmarks/bench_render.py --method struct`); storage "
            f"{_span(storage, '.2f')}x the positional plane on the structured materials (at most 4x: "
            f"{met(max(storage) <= 4)}); off-line construction {_span(build, '.2f')} s at 128 x 128")
    if large:
        text += (f" and {large['build_seconds']:.1f} s at {' x '.join(map(str, large['size']))} (at most 1 and 10 "
                 f"minutes: {met(max(build) <= 60 and large['build_seconds'] <= 600)})")
    else:
        text += f" (at most 1 minute: {met(max(build) <= 60)})"
    broken = [(m, r["broken_elements"]) for m, r in ((r["material"], r) for r in data["rows"])
              if r["method"] == "struct" and m in structured_ and r.get("broken_elements")]
    if broken:
        text += (". struct's broken elements (an element of the 8 x 8-repeat window whose inner texels read more "
                 "than one of the exemplar's elements, found from its joints: `elements.broken_elements`): "
                 + ", ".join(f"{m} {_spread(b, '.1%')}" for m, b in broken))
    text += (f". A structured material repeats its own lattice, so struct's repetition score there "
             f"({_span(rep_struct, '.2f')}) measures the structure kept, not a repeated exemplar; on the "
             f"stochastic materials it reshuffles coarse cells and scores {_span(rep_stoch, '.2f')} "
             f"against hist's {_span(rep_hist, '.3f')}"
             + (", which is why `auto` does not choose it there." if rep_stoch[0] > rep_hist[1] else "."))
    return "\n".join(lines + ["", text])


def structured_construction(data: dict) -> str:
    """synthesis.md's sentences on auto's structure strengths and struct's cut tables, from bench_structured.py."""
    choices, structured_ = data["choices"], data["structured"]
    size = next((m["size"] for m in data["models"].values() if m.get("size")), None)
    fits = f" ({size[0]}^2 fits)" if size and size[0] == size[1] else " (the benchmark's fits)"
    strengths = "; ".join(", ".join(f"{m} {choices[m]['strength']:.2f}" for m in group) for group in
                          (structured_, [m for m in choices if m not in structured_]) if group)
    build = _rows_of(data, choices, "struct", "build_seconds")
    storage = _rows_of(data, structured_, "struct", "storage_vs_plane")
    large = data.get("large_build")
    at = f" at {size[0]}^2 x {large['size'][2]}" if size and large else " on those fits"
    text = (f"Strengths{fits}: {strengths}. Cut tables: {_span(build, '.2g')} s to build{at}"
            + (f", {large['build_seconds']:.1f} s at {large['size'][0]}^2 x {large['size'][2]}" if large else "")
            + f"; {_span(storage, '.2f')}x the positional "
              "plane on the structured materials" + (f" and {large['storage_vs_plane']:.2g}x at "
                                                      f"{large['size'][0]}^2" if large else "") + ".")
    return text


def structured_summary(data: dict) -> str:
    """README.md's Measured row on structured materials (the cell after its description), from bench_structured.py."""
    structured_ = data["structured"]

    def span(method: str, key: str, spec: str) -> str:
        return _span(_structured_ranges(data, structured_, method, key), spec)

    chosen = {data["choices"][m]["method"] for m in structured_}
    cost = [r["cost_vs_hist"] for r in data["rows"]
            if r["material"] in structured_ and r["method"] == "struct" and r["cost_vs_hist"] is not None]
    storage = _rows_of(data, structured_, "struct", "storage_vs_plane")
    return (f"`auto` ({', '.join(sorted(chosen))}) {span('struct', 'coherence_p90', '.2f')} / "
            f"{span('struct', 'identity', '.2f')}; hist {span('hist', 'coherence_p90', '.2f')} / "
            f"{span('hist', 'identity', '.2g')}; quilt {span('quilt', 'coherence_p90', '.2f')} / "
            f"{span('quilt', 'identity', '.2g')}; at {_span(cost, '.2f')}x hist's cost per query, "
            f"{_span(storage, '.2f')}x the plane's storage")


def decode_speed(data: dict) -> str:
    """btf_decode_speed.py: milliseconds per image of each reader."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}`: {data['conditions']}.", ""]
    lines += _head("", "per image", spaced=True)
    return "\n".join(lines + [_line(_filled(r, "reader"), f"{r['ms_per_image']:g} ms") for r in data["rows"]])


def fit_default(data: dict) -> str:
    """choosing.md: what dynbtf fit chooses with no options, against the best of the two kinds, and its time. A
    measured file (``fit_materials.py --default --json``) holds each run per seed: :func:`_fit_default_measured`."""
    if not data.get("recorded_from"):
        return _fit_default_measured(data)
    lines = _head("material", "chosen (trial PSNR: triple / parallax)", "default: PSNR / FLIP", "best: PSNR / FLIP",
                  "steps (stopped)", "wall min (vs earlier)", "march cost")
    for r in data["rows"]:
        trial = f"{r['trial_psnr'][0]:.2f} / {r['trial_psnr'][1]:.2f}" if r.get("trial_psnr") else None
        stereo = (f"stereo trusted on {r['stereo_trusted_percent']:g} %"
                  if r.get("stereo_trusted_percent") is not None else None)
        why = "; ".join(filter(None, (trial, stereo))) if trial else f"{stereo}: no trial"
        best, other = r["best"], r.get("other")
        versus = f" ({other['kind']} {other['psnr']:.2f} / {other['flip']:.3f})" if other else ""
        if r.get("earlier_run_minutes") is not None:
            wall = (f"{r['wall_minutes']:.2f} ({r['vs_earlier']:.2f}x the earlier default run itself, "
                    f"{r['earlier_run_minutes']:.2f} min)")
        else:
            shared = f"; {r['conditions']}" if r.get("conditions") else ""
            wall = f"{r['wall_minutes']:.1f} ({r['vs_earlier']:.2f}x{shared})"
        lines.append(_line(r["material"], f"{r['chosen']} ({why})", f"**{r['psnr']:.2f}** / {r['flip']:.3f}",
                           f"{best['kind']}: {best['psnr']:.2f} / {best['flip']:.3f}{versus}",
                           f"{r['steps']:,} ({r['stopped']})", wall,
                           f"{r['march_cost']:.1f}x flat" if r.get("march_cost") else "none (flat)"))
    return "\n".join(lines)


def _counted(values: list) -> str:
    """The one value of a per-seed list, or each value with its count (``triple-parallax 2, triple 1``)."""
    counts = Counter(values)
    return str(values[0]) if len(counts) == 1 else ", ".join(f"{v} {n}" for v, n in counts.most_common())


def _best_fixed_epochs(spec: str) -> str:
    """The better of quality.json's two 30-epoch fits of the simulated material ``spec`` names (its PSNR / FLIP,
    means over the seeds), or ``-`` where quality.json has no such row."""
    quality = _load("quality")
    found = {}
    for part, short in (("triple", "triple"), ("triple_parallax", "parallax")):
        for r in quality[part]["rows"]:  # (a recorded row names its material: 128 x 128)
            if r.get("spec", f"sim:{r['material'].replace(' ', '_')}?size=128") == spec:
                found[short] = _means(r)
    if not found:
        return "-"
    kind, best = max(found.items(), key=lambda item: item[1]["psnr"])
    return f"{kind}: {best['psnr']:.2f} / {best['flip']:.3f}"


def _fit_default_measured(data: dict) -> str:
    """fit_materials.py --default --json: per BTF, the kind dynbtf fit chose under each seed, the trials' mean scores
    (where the stereo did not decide alone), the stereo's trusted fraction, the default's quality against the better
    30-epoch fit of quality.json, its steps, stop and time."""
    lines = [f"Measured on {_machine(data)} by `{data['command']}` ({len(data['seeds'])} seeds; "
             f"{data['conditions']}; best: the better of quality.json's 30-epoch fits).", ""]
    lines += _head("BTF", "chosen", "trial PSNR: triple / parallax", "stereo trusted", "default: PSNR / FLIP",
                   "best: PSNR / FLIP", "steps (stopped)", "wall min", "vs earlier")
    for r in data["rows"]:
        trials = [t for t in r["trials"] if t]
        trial = (" / ".join(f"{sum(t[k] for t in trials) / len(trials):.2f}" for k in ("triple", "triple-parallax"))
                 + ("" if len(trials) == len(r["trials"]) else f" ({len(trials)} of {len(r['trials'])} seeds)")
                 if trials else "none: the stereo decided")
        trusted = [t for t in r["stereo_trusted"] if t is not None]
        lines.append(_line(f"`{r['spec']}`", _counted(r["chosen"]), trial,
                           f"{100 * sum(trusted) / len(trusted):.0f} %" if trusted else "-",
                           f"**{_spread(r['psnr'], '.2f')}** / {_spread(r['flip'], '.3f')}",
                           _best_fixed_epochs(r["spec"]),
                           f"{round(sum(r['steps']) / len(r['steps'])):,} ({_counted(r['stopped'])})",
                           _spread(r["wall_minutes"], ".1f"),
                           _spread(r["vs_earlier"], ".2f", "x") if r.get("vs_earlier") else "-"))
    return "\n".join(lines)


def fit_many(data: dict) -> str:
    """bench_fit_many.py: the same fits one after another and on Ray; the ratio of materials per minute; then each
    material's held-out PSNR in both runs."""
    runs = {r["run"]: r for r in data["rows"]}
    lines = [] if data.get("recorded_from") else [f"Measured on {_machine(data)} by `{data['command']}` "
                                                  f"({data['conditions']}):", ""]
    lines += _head("run", "wall time", "materials per minute")
    lines += [_line(r["label"], f"{r['wall_seconds']:.1f} s", f"{r['materials_per_minute']:.1f}") for r in data["rows"]]
    ratio = runs["ray"]["materials_per_minute"] / runs["sequential"]["materials_per_minute"]
    lines.append(_line("**ratio Ray / sequential**", "", f"**{ratio:.2f}x**"))
    if data.get("held_out_psnr"):
        pairs = [(r["material"].replace("_", " "), r["sequential"], r["ray"]) for r in data["held_out_psnr"]]
        gap = max(abs(a - b) for _, a, b in pairs)
        lines += ["", "Held-out PSNR (per-image peak), sequential / Ray: "
                  + ", ".join(f"{m} {a:.2f} / {b:.2f}" for m, a, b in pairs) + f" dB (at most {gap:.2f} dB apart)."]
    return "\n".join(lines)


def _speed_fit_many(row: dict, data: dict) -> tuple[str, str, str]:
    runs = {r["run"]: r for r in data["rows"]}
    ratio = runs["ray"]["materials_per_minute"] / runs["sequential"]["materials_per_minute"]
    what = f"many materials on Ray vs one after another (`{data['command']}`, {data['conditions']})"
    return (what, f"**{ratio:.2f}x** the materials per minute ([cluster.md](cluster.md#measured))",
            f"about 1-2x on {data['cores']} cores ({'met' if ratio >= 0.9 else 'missed'})")


def compiled_material(data: dict) -> str:
    """compiled_material.md: what a compiled material saves, a line per command."""
    table = _prose(data, ("what", "what"), ("command", "how"), ("result", "result"), spaced=True)
    if data.get("recorded_from"):
        return table
    return f"Measured on {_machine(data)} by `{data['command']}` ({data['conditions']}):\n\n" + table


RENDERERS = {"stone_fetch_summary": stone_fetch_summary, "parallax_eval": parallax_eval,
             "parallax_quality": parallax_quality, "training": training, "budget": budget, "evaluation": evaluation,
             "gpu": gpu, "guided": guided, "guidance": guidance, "guidance_struct": guidance_struct, "web_layered": web_layered, "speed": speed, "rendering": rendering, "runtimes": runtimes,
             "render_scenes": render_scenes,
             "measured": measured, "quality_triple": quality_triple, "quality_parallax": quality_parallax,
             "quality_compared": quality_compared, "baselines": baselines, "baselines_summary": baselines_summary,
             "baselines_storage": baselines_storage, "baselines_small": baselines_small,
             "neumip_variants": neumip_variants, "baselines_synthesis": baselines_synthesis,
             "synthesis_quality": synthesis_quality, "synthesis_quality_wood": synthesis_quality,
             "synthesis_quality_summary": synthesis_quality_summary,
             "stone_fetch": stone_fetch, "stone_relief": stone_relief, "stone_limits": stone_limits,
             "stone_limits_summary": stone_limits_summary,
             "fullsize": fullsize, "training_large": training_large, "fullsize_data_path": fullsize_data_path, "fullsize_curve": fullsize_curve,
             "fullsize_parallax_curve": fullsize_parallax_curve, "sampling": sampling, "web_struct": web_struct,
             "web_frame_time": web_frame_time, "web_agreement": web_agreement, "web_size": web_size,
             "web_checks": web_checks, "filtering": filtering, "blend_exponent": blend_exponent,
             "blend_exponent_summary": blend_exponent_summary, "structured_construction": structured_construction,
             "structured": structured, "decode_speed": decode_speed, "fit_default": fit_default,
             "fit_many": fit_many, "compiled_material": compiled_material, "whole_elements": whole_elements,
             "rotation": rotation, "scale_jitter": scale_jitter, "between_texels": between_texels, "subtexel": subtexel}
#: Tables rendered from another table's data file (default: ``<name>.json``).
SOURCES = {"guidance": "guided", "guidance_struct": "guided", "render_scenes": "rendering",
           "blend_exponent_summary": "blend_exponent",
           "synthesis_quality_summary": "synthesis_quality", "structured_construction": "structured",
           **dict.fromkeys(("quality_triple", "quality_parallax", "quality_compared"), "quality"),
           **dict.fromkeys(("baselines_summary", "baselines_storage", "baselines_small", "neumip_variants",
                            "baselines_synthesis"), "baselines"),
           **dict.fromkeys(("stone_fetch", "stone_fetch_summary", "stone_relief", "stone_limits",
                            "stone_limits_summary"), "stone"),
           **dict.fromkeys(("fullsize_curve", "fullsize_parallax_curve"), "fullsize"),
           **dict.fromkeys(("web_struct", "web_frame_time", "web_agreement", "web_size", "web_checks"), "web")}
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
