"""The measured tables in README.md and docs/ are generated from the benchmarks' JSON data (benchmarks/tables.py):
each ``<!-- table:NAME -->`` block must be what its data renders, every block must name data that exists, and every
other table must be one of the tables below that report no measurement."""

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _tables():
    spec = importlib.util.spec_from_file_location("tables", ROOT / "benchmarks" / "tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_table_block_names_data_that_exists():
    tables = _tables()
    names = {m for path in tables.DOCS for m in re.findall(r"<!-- table:([a-z_]+) -->", path.read_text())}
    assert names, "no generated tables found in the docs"
    for name in names:
        assert name in tables.RENDERERS, f"no renderer for table {name!r}"
        source = tables.SOURCES.get(name, name)
        assert (tables.RESULTS / f"{source}.json").is_file(), f"table {name!r} has no data file ({source}.json)"


def test_docs_tables_agree_with_their_data():
    stale = _tables().update(check=True)
    assert not stale, "tables re-typed or data changed; run python benchmarks/tables.py: " + ", ".join(stale)


def test_speed_rows_come_from_data_or_record_their_measurement():
    """Each row of docs/results.md's Speed summary (benchmarks/results/speed.json) is rendered from a benchmark's
    JSON that exists, or is a recorded measurement with its numbers as values and its command and machine (null where
    the text that first stated it did not say)."""
    import json

    tables = _tables()
    rows = json.loads((tables.RESULTS / "speed.json").read_text())["rows"]
    assert rows
    for row in rows:
        if "from" in row:
            assert row.get("view", row["from"]) in tables._SPEED_FROM, row
            assert (tables.RESULTS / f"{row['from']}.json").is_file(), row
        else:
            r = row["recorded"]
            assert {"what", "command", "cpu", "cpu_isa", "cores", "values", "result", "target"} <= r.keys(), r
            assert all(isinstance(v, (int, float)) for v in r["values"].values()), r
            assert re.search(r"\{[a-z0-9_]+(:[^}]*)?\}", r["result"]), r["result"]  # the numbers come from values
            r["result"].format(**r["values"]), r["target"].format(**r["values"])


def test_rendering_table_renders_what_bench_render_writes():
    """The rendering table's renderer reads the fields bench_render.py writes."""
    tables = _tables()
    head = {"command": "python benchmarks/bench_render.py", "commit": "abc1234", "cpu": "CPU", "cpu_isa": "avx2",
            "cores": 2}
    data = {"benchmark": "rendering",
            "eval": head | {"model": "a random Triple Plane", "model_shape": [128, 128, 16], "method": "hist",
                            "queries": 1000, "repeats": 2, "eval_queries_per_second": {"fp32": 1e6, "bf16": 2e6},
                            "plugin_queries_per_second": 0.9e6, "plugin_first_call_seconds": 0.5,
                            "max_abs_difference": 0.0, "max_abs_value": 2.0}}
    text = tables.rendering(data)
    assert "Measured on CPU (2 cores, best level avx2)" in text and "| 0.9 M |" in text
    assert "0.90x (fp32), 0.45x (bf16) | max difference 0 on values up to 2.0" in text
    what, result, target = tables._speed_rendering({"part": "eval", "target": "match (met; tested)"}, data)
    assert "0.9 vs 1.0 M queries/s (0.90x), max difference 0" in result and target == "match (met; tested)"


def test_evaluation_breakdown_states_what_30_percent_of_the_fma_bound_leaves_the_synthesis():
    """One level's breakdown: 1 M queries/s on one thread is 1,000 ns per query; at 30% of a 10 GFLOP/s peak a
    6,000-FLOP query may take 2,000 ns, and with the other stages at 400 ns the synthesis is left 1,600 ns; layers 2..
    at 2,000 FLOP in 200 ns run at 10 GFLOP/s, all of the peak."""
    tables = _tables()
    head = {"command": "python benchmarks/bench_synthesis_eval.py", "commit": "abc1234", "cpu": "CPU",
            "cpu_isa": "avx2", "cores": 2, "queries": 100, "rows": []}
    stages = {"synthesis kernel": 0.6, "layer 1 (BLAS + angular kernel)": 0.15, "layers 2.. (native forward)": 0.2,
              "eval's own work (validation, chunks)": 0.05}
    breakdown = {"isa": "avx2", "queries_per_second_one_thread": 1e6, "stages": stages,
                 "fma_peak_gflops_one_thread": 10.0, "decoder_flop_per_query": 6000, "layers_2_on_flop_per_query": 2000}
    text = tables.evaluation(head | {"breakdowns": [breakdown]})
    assert "| avx2 | 1.00 | 600 | 150 | 200 | 50 | 1000 | 100% | 2000 | 1600 |" in text, text


def test_baselines_small_renders_a_measured_part_with_its_spread():
    """A part bench_baselines.py writes: each quality number as its mean and min-max over the seeds, the best mean
    bold, the storage as counted; a recorded part keeps its plain numbers."""
    tables = _tables()

    def spread(*values):
        return {"mean": sum(values) / len(values), "range": [min(values), max(values)], "per_seed": list(values)}

    row = {"kind": "triple", "psnr": spread(30.0, 31.0), "psnr_fixed1": spread(40.0, 41.0, 42.0),
           "dssim": spread(0.03), "flip": spread(0.04, 0.05), "model_bytes": 300812, "positional_bytes": 262144,
           "fit_seconds": spread(100.0, 110.0), "bold": ["psnr_fixed1"]}
    part = {"command": "python benchmarks/bench_baselines.py", "commit": "abc1234", "cpu": "CPU", "cpu_isa": "avx2",
            "cores": 2, "btf": "sim:leather?size=64", "seeds": [0, 1, 2], "conditions": "30 epochs", "rows": [row]}
    text = tables.baselines_small({"small": part})
    assert "by `python benchmarks/bench_baselines.py` (`sim:leather?size=64`, 3 seeds; 30 epochs)" in text, text
    assert ("| triple | **41.00 (40.00-42.00)** | 0.0300 | 0.0450 (0.0400-0.0500) | 300,812 | 262,144 | "
            "105 (100-110) |") in text, text
    recorded = {"recorded_from": "the hand-typed docs/results.md", "rows": [
        {"kind": "pca", "psnr_fixed1": 38.97, "dssim": 0.0513, "flip": 0.0768, "model_bytes": 1, "positional_bytes": 1,
         "fit_seconds": 3}]}
    assert "| pca | 38.97 | 0.0513 | 0.0768 | 1 | 1 | 3 |" in tables.baselines_small({"small": recorded})


def test_stone_tables_render_measured_parts_and_the_quality_rows_they_name():
    """measure_stone_limits.py's parts: each number as its mean and min-max over the seeds, the oracle's nearest light
    beside it; a fetch row ``"from": "quality"`` shows the stone row of its ``"part"`` of quality.json."""
    import json

    tables = _tables()

    def spread(*values):
        return {"mean": sum(values) / len(values), "range": [min(values), max(values)], "per_seed": list(values)}

    run = {"command": "python benchmarks/measure_stone_limits.py limits S", "commit": "abc1234", "cpu": "CPU",
           "cpu_isa": "avx2", "cores": 2, "seeds": [0, 1, 2], "conditions": "fixed peak 1"}
    limits = run | {"rows": [
        {"measurement": "oracle", "psnr_training": None, "psnr_held_out": spread(30.0, 31.0),
         "nearest_light_psnr_held_out": spread(25.0, 26.0)},
        {"measurement": "all views", "psnr_training": spread(20.0, 21.0, 22.0), "psnr_held_out": spread(21.5)}]}
    text = tables.stone_limits({"limits": limits})
    assert "by `python benchmarks/measure_stone_limits.py limits S` (3 seeds; fixed peak 1)" in text, text
    assert "| oracle | | 30.50 (30.00-31.00) (nearest light alone: 25.50 (25.00-26.00)) |" in text, text
    assert "| all views | 21.00 (20.00-22.00) | 21.50 |" in text, text
    fetch = run | {"rows": [{"fetch": "`uv`", "from": "quality", "part": "triple"},
                            {"fetch": "oracle", "psnr_fixed1": spread(31.0, 32.0), "dssim": spread(0.02),
                             "flip": spread(0.1)}]}
    text = tables.stone_fetch({"fetch": fetch})
    stone = next(r for r in json.loads((tables.RESULTS / "quality.json").read_text())["triple"]["rows"]
                 if r["material"] == "stone")
    assert f"| `uv` | {tables._spread(stone['psnr_fixed1'], '.2f')} |" in text, text
    assert "| oracle | 31.50 (31.00-32.00) | 0.020 | 0.100 |" in text, text


def test_stone_limits_sentence_reads_the_means_and_says_whether_the_fit_over_fits():
    """The stone's limits in one sentence, from the measured part: the oracle's and the fits' means, and "does not
    over-fit" only while training and held-out PSNR are within 1 dB."""
    tables = _tables()

    def spread(*values):
        return {"mean": sum(values) / len(values), "range": [min(values), max(values)], "per_seed": list(values)}

    def part(training, held_out):
        return {"limits": {"seeds": [0, 1, 2], "rows": [
            {"measurement": "oracle: the 3 nearest measured lights", "psnr_training": None,
             "psnr_held_out": spread(30.0, 31.0), "nearest_light_psnr_held_out": spread(25.0, 26.0)},
            {"measurement": "the fit of all 81 views (lr x3)", "psnr_training": training, "psnr_held_out": held_out},
            {"measurement": "views with theta <= 30 deg only (19 x 81)", "psnr_training": spread(25.0),
             "psnr_held_out": spread(24.0)},
            {"measurement": "the normal view only (1 x 81)", "psnr_training": spread(31.0, 32.0),
             "psnr_held_out": spread(19.0)}]}}

    text = tables.stone_limits_summary(part(spread(20.0, 22.0), spread(21.5)))
    assert text.startswith("Means of 3 seeds, fixed peak 1: an oracle interpolating the 3 nearest measured lights at "
                           "the same view reaches 30.50 dB on held-out pairs (the nearest light alone 25.50), so the "
                           "grid supports 30.5 dB; the fit does not over-fit (training 21.00 dB, held-out 21.50);"), text
    assert text.endswith("the normal view alone is fitted to 31.50 dB, all 81 views to 21.00."), text
    text = tables.stone_limits_summary(part(spread(24.0), spread(21.5)))
    assert "the fit over-fits by 2.5 dB (training 24.00 dB, held-out 21.50)" in text, text


def test_fit_default_renders_a_measured_file_per_seed_against_the_best_fixed_epoch_fit():
    """fit_materials.py --default --json: the chosen kind counted over the seeds, the trials' means (and on how many
    seeds they ran), the default's PSNR / FLIP as spreads, the better of quality.json's 30-epoch fits of that BTF."""
    import json

    tables = _tables()

    def spread(*values):
        return {"mean": sum(values) / len(values), "range": [min(values), max(values)], "per_seed": list(values)}

    row = {"spec": "sim:stone?size=128", "chosen": ["triple-parallax", "triple-parallax", "triple"],
           "trials": [{"triple": 24.0, "triple-parallax": 30.0}, {}, {"triple": 25.0, "triple-parallax": 28.0}],
           "stereo_trusted": [0.86, 0.88, 0.9], "stopped": ["converged", "ceiling", "converged"],
           "steps": [12000, 12210, 11000], "psnr": spread(34.0, 33.0, 35.0), "flip": spread(0.1),
           "wall_minutes": spread(9.0, 11.0), "vs_earlier": None}
    data = {"command": "python benchmarks/fit_materials.py --default", "commit": "abc1234", "cpu": "CPU",
            "cpu_isa": "avx2", "cores": 2, "seeds": [0, 1, 2], "conditions": "seeded", "rows": [row]}
    quality = json.loads((tables.RESULTS / "quality.json").read_text())
    fits = {short: tables._means(next(r for r in quality[part]["rows"] if r["material"] == "stone"))
            for part, short in (("triple", "triple"), ("triple_parallax", "parallax"))}
    kind, best = max(fits.items(), key=lambda item: item[1]["psnr"])
    text = tables.fit_default(data)
    assert "(3 seeds; seeded; best: the better of quality.json's 30-epoch fits)" in text, text
    assert (f"| `sim:stone?size=128` | triple-parallax 2, triple 1 | 24.50 / 29.00 (2 of 3 seeds) | 88 % | "
            f"**34.00 (33.00-35.00)** / 0.100 | {kind}: {best['psnr']:.2f} / {best['flip']:.3f} | "
            "11,737 (converged 2, ceiling 1) | 10.0 (9.0-11.0) | - |") in text, text


def _recorded_parts(data: dict):
    """The parts of a recorded data file that state a measurement: every dict holding rows or points."""
    if "rows" in data or "points" in data:
        yield data
    for value in data.values():
        if isinstance(value, dict):
            yield from _recorded_parts(value)


def _recorded(data: dict):
    """The recorded measurements in a data file: the whole file, or each of its parts, that says ``"recorded_from"``
    (a file whose benchmark now writes some of its parts keeps the others recorded)."""
    if "recorded_from" in data:
        yield data
        return
    for value in data.values():
        if isinstance(value, dict):
            yield from _recorded(value)


def test_recorded_measurements_name_their_command_and_machine():
    """Each recorded data file or part (``"recorded_from"``, other than speed.json, checked above) states for each
    part, or for each of its rows, the command and machine (null where the hand-typed text did not say); a recorded
    prose cell takes its numbers from the row's ``"values"``, numbers all."""
    import json

    tables = _tables()
    files = {path.stem: json.loads(path.read_text()) for path in sorted(tables.RESULTS.glob("*.json"))
             if path.stem != "speed"}
    recorded = [(name, data) for name, whole in files.items() for data in _recorded(whole)]
    assert "baselines" in {name for name, _ in recorded}  # a file whose parts are recorded one by one is read too
    machine = {"command", "cpu", "cpu_isa", "cores"}
    for name, data in recorded:
        assert data["recorded_from"].startswith("the hand-typed "), name
        for part in _recorded_parts(data):
            for row in part.get("rows", []):
                if "from" in row:  # rendered from a benchmark's data, which names its own command and machine
                    continue
                assert machine <= part.keys() or machine <= row.keys(), (name, row)
                values = row.get("values", {})
                assert all(isinstance(v, (int, float)) or isinstance(v, list) and all(
                    isinstance(x, (int, float)) for x in v) for v in values.values()), (name, values)
            assert "rows" in part or machine <= part.keys(), name



def test_a_benchmark_part_is_written_beside_the_others_with_its_command_and_machine(tmp_path, monkeypatch):
    """results_io.write_part: the file's other parts are kept, the new part starts with the run's command (shell
    quoted), commit and machine, and no temporary file is left."""
    import json
    import sys

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import results_io

    monkeypatch.setattr(sys, "argv", ["x.py", "limits", "sim:stone?size=16", "--note", "two words"])
    path = tmp_path / "stone.json"
    results_io.write_part(path, "limits", "measure_stone_limits.py", {"seeds": [0, 1]})
    path.write_text(json.dumps(json.loads(path.read_text()) | {"fetch": {"rows": [1]}}))
    results_io.write_part(path, "limits", "measure_stone_limits.py", {"seeds": [0, 1, 2]})
    data = json.loads(path.read_text())
    assert data["benchmark"] == "stone" and data["fetch"] == {"rows": [1]}
    part = data["limits"]
    assert part["command"] == ("python benchmarks/measure_stone_limits.py limits 'sim:stone?size=16' --note "
                               "'two words'"), part["command"]
    assert part["seeds"] == [0, 1, 2] and part["cores"] >= 1 and part["cpu_isa"]
    assert list(part)[:5] == ["command", "commit", "cpu", "cpu_isa", "cores"]
    assert [p.name for p in tmp_path.iterdir()] == ["stone.json"]


def _gpu_tables(monkeypatch):
    """tables.py with the CPU's figures the GPU table compares with: 2 M samples/s of training, 4 M hist queries/s,
    a measured curve within 0.5 dB of its final PSNR from step 6,000."""
    tables = _tables()
    cpu = {"training": {"rows": [{"btf": "sim:leather?size=128", "variant": "fast", "isa": "avx2",
                                  "samples_per_second": 2e6}]},
           "evaluation": {"rows": [{"method": "hist", "isa": "avx2", "ours_qps": 4e6}]},
           "fullsize": {"curve": {"steps_to_within_0_5_db": 6000}}}
    monkeypatch.setattr(tables, "_load", lambda name: cpu[name])
    return tables


def test_gpu_table_projects_the_full_size_fit_from_its_measured_step_and_the_cpu_curve(monkeypatch):
    """gpu_check.py's runs: the projection is the CPU curve's steps to within 0.5 dB times the GPU fit's measured
    seconds per step (its last monitor time over its steps); the default chunk size is the one set in bold."""
    tables = _gpu_tables(monkeypatch)
    run = {"command": "python benchmarks/gpu_check.py", "training": {"btf": "sim:leather?size=128",
                                                                     "samples_per_second": 5e7, "ms_per_step": 4.0},
           "evaluation": {"queries": 2_000_000, "seconds": 0.04, "queries_per_second": 5.2e7, "chunk_sizes": [
               {"chunk_size": 1 << 20, "default": True, "seconds": 0.04, "queries_per_second": 5.2e7,
                "peak_memory_bytes": 2 ** 30},
               {"chunk_size": 32768, "default": False, "seconds": 0.5, "queries_per_second": 4.1e6,
                "peak_memory_bytes": 2 ** 28}]},
           "evaluation_agreement": {"queries": 1000, "relative_l2_difference": 1e-4, "max_abs_difference": 1e-3},
           "full_size_fit": {"btf": "big.btf", "file_components": 96, "minutes_budget": 3, "steps": 1000,
                             "stopped": "ceiling", "best_held_out_psnr": 21.0, "curve": [[10.0, 20.0], [50.0, 21.0]]}}
    text = tables.gpu({"machine": "a GPU", "torch": "2.x", "runs": [run]})
    assert "**50.0 M samples/s**" in text and "2.0 M (fast)" in text
    assert "**40.0 ms, 52.0 M queries/s, 1.00 GiB** | 500 ms, 4.0 M |" in text, text  # the CPU: 2e6 / 4e6 q/s
    assert "**40.0 ms, 52.0 M queries/s, 1.00 GiB**" in text and "| 500.0 ms, 4.1 M queries/s, 0.25 GiB |" in text
    assert "50 ms per step" in text
    assert "**5.0 min**" in text  # 6000 steps x 0.05 s


def test_gpu_table_has_a_row_per_compile_mode_and_the_summary_takes_the_fastest(monkeypatch):
    """A run that measured the compile modes: a row each, the fastest in bold with the planner's figure beside it, a
    failed mode says so; a run without evaluation adds no evaluation rows, and the agreement row names the run that
    measured it; the README line reads the last run's fastest mode."""
    tables = _gpu_tables(monkeypatch)
    first = {"command": "one", "training": {"btf": "sim:leather?size=128", "samples_per_second": 5e7,
                                             "ms_per_step": 4.0},
             "evaluation": {"queries": 2_000_000, "seconds": 0.04, "queries_per_second": 5.2e7},
             "evaluation_agreement": {"queries": 1000, "relative_l2_difference": 1e-4, "max_abs_difference": 1e-3},
             "full_size_fit": {"btf": "big.btf", "file_components": 96, "minutes_budget": 3, "steps": 1000,
                               "stopped": "ceiling", "best_held_out_psnr": 21.0, "curve": [[10.0, 20.0], [50.0, 21.0]]}}
    modes = {"off": {"samples_per_second": 6e7, "ms_per_step": 4.0},
             "graphs": {"samples_per_second": 1.2e8, "ms_per_step": 2.0},
             "kernels": {"compile": "kernels", "error": "Traceback ..."}}
    second = {"command": "two", "training": {"btf": "sim:leather?size=128", **modes["off"], "compile_modes": modes,
                                              "fastest_compile": "graphs", "planned_ms_per_step": 1.5}}
    text = tables.gpu({"machine": "a GPU", "torch": "2.x", "runs": [first, second]})
    assert "`--compile graphs` | **120.0 M samples/s** (2.00 ms per step; the budget planner measures 1.50 ms) |" \
        in text
    assert "`--compile off` | 60.0 M samples/s (4.00 ms per step) | 2.0 M (fast) | 2 |" in text
    assert "`--compile kernels` | failed | | 2 |" in text
    assert text.count("1080p evaluation") == 1 and "largest 1.0e-03 | | 1 |" in text
    summary = tables.gpu_summary({"machine": "a GPU (80 GB)", "runs": [first, second]})
    assert summary.startswith("a GPU: training 120 M samples/s (`--compile graphs`); a 1080p `hist` frame in 40 ms")


def test_stone_fetch_sentence_reads_the_means_and_the_refined_row_from_quality(monkeypatch):
    """The fetch part's sentence: the means of its measured rows, the refined (`--repr triple-parallax`) row from
    quality.json's stone row, the gap to the exact height, and which conclusion the numbers support."""
    tables = _tables()

    def spread(*values):
        return {"mean": sum(values) / len(values), "range": [min(values), max(values)], "per_seed": list(values)}

    quality = {"triple": {"rows": [{"material": "stone", "psnr_fixed1": spread(22.0, 23.0)}]},
               "triple_parallax": {"rows": [{"material": "stone", "psnr_fixed1": spread(30.0, 31.0)}]}}
    monkeypatch.setattr(tables, "_load", lambda name: quality)

    def part(wide: float) -> dict:
        return {"fetch": {"seeds": [0, 1, 2], "rows": [
            {"fetch": "`uv` (the paper's Triple Plane)", "from": "quality", "part": "triple"},
            {"fetch": "`uv`, 2x wider model", "psnr_fixed1": spread(wide, wide)},
            {"fetch": "visible point of the stereo height, kept fixed", "psnr_fixed1": spread(26.0, 27.0)},
            {"fetch": "visible point of the stereo height, refined by the fit", "from": "quality",
             "part": "triple_parallax"},
            {"fetch": "visible point the simulator traced", "psnr_fixed1": spread(32.0, 33.0)}]}}

    text = tables.stone_fetch_summary(part(24.0))
    assert text.startswith("The stone (means of 3 seeds, fixed peak 1)"), text
    assert "exact height the fit reaches 32.50 dB, at that of the stereo height kept fixed 26.50 dB, and refined by " \
           "the fit (`--repr triple-parallax`) 30.50 dB, 2.0 dB from the exact height" in text, text
    assert "at `uv` reaches 22.50 dB, and a model twice as wide there 24.00 dB" in text, text
    assert text.endswith("Parallax and masking, not the model's size, are the stone's limit."), text
    assert "Doubling the model" in tables.stone_fetch_summary(part(29.0))  # the wide model gains more than half


def test_relief_cost_line_reads_the_hist_rows_of_bench_parallax_eval():
    """README's relief line: the hist rows' cost ratios (one coherent view, random views), not hex's."""
    tables = _tables()
    rows = [{"method": m, "views": v, "flat_mqps": 6.0, "relief_mqps": 6.0 / ratio, "cost_ratio": ratio}
            for m, base in (("hist", 1.0), ("hex", 10.0))
            for v, ratio in (("all views", base * 5.0), ("one view at 45 deg", base * 3.0), ("normal view", 1.5))]
    text = tables.parallax_eval_summary({"rows": rows, "max_theta": 75.0, "btf": "sim:stone?size=64",
                                         "relief_depth_texels": 3.2})
    assert "costs 3.0x a flat one with one 45-degree view" in text, text
    assert "5.0x with views random up to 75 degrees (`sim:stone?size=64`, relief 3 texels deep)" in text, text


def test_fullsize_rows_come_from_bench_training_large_and_say_whether_the_target_holds(monkeypatch):
    """The full-size table's throughput row: both recipes' ratios without the sub-texel term, the largest peak RSS,
    and "met" only when every ratio is at least 0.8 and the memory at most 4 GB; the file row from the run that
    wrote it; README's line takes the minutes after which the measured curve stays within 0.5 dB of its end."""
    tables = _tables()
    machine = {"command": "python benchmarks/bench_training_large.py", "cpu": "CPU", "cpu_isa": "avx2", "cores": 2}

    def data(paper_ratio: float) -> dict:
        return machine | {"file_written": {"command": "dynbtf simulate ...", "seconds": 250.0, "bytes": 105e6,
                                           "peak_rss_gb": 2.21},
                          "rows": [{"recipe": "paper batches", "subtexel": 0.0, "ratio": paper_ratio,
                                    "large_msps": 9.0, "cached_msps": 10.0, "peak_rss_gb": 0.9},
                                   {"recipe": "fast", "subtexel": 0.0, "ratio": 0.9, "large_msps": 9.9,
                                    "cached_msps": 11.0, "peak_rss_gb": 1.1},
                                   {"recipe": "fast", "subtexel": 0.25, "ratio": 0.5, "large_msps": 5.0,
                                    "cached_msps": 10.0, "peak_rss_gb": 9.0}]}

    what, result, target = tables.fullsize_throughput(data(0.85))
    assert result == "0.90x (fast recipe, 9.9 vs 11.0 M samples/s), 0.85x (paper batches); peak memory 1.10 GB"
    assert target.endswith("(met)") and tables.fullsize_throughput(data(0.7))[2].endswith("(not met)")
    assert tables.fullsize_file(data(0.85))[1] == "4.2 min, 105 MB, 2.2 GB peak memory"
    curve = {"curve": {"minutes_to_within_0_5_db": 9.0, "isa": "avx2"}}
    monkeypatch.setattr(tables, "_load", lambda name: curve)
    assert tables.fullsize_summary(data(0.85)).endswith(
        "0.90x the cached speed; within 0.5 dB of the final PSNR in 9 min of training (avx2)")


def test_fullsize_parallax_row_comes_from_a_triple_parallax_run_of_bench_training_large():
    """The parallax row: the fast recipe's rates without the sub-texel term, its step, peak memory against 4 GB and
    the stereo's seconds at both sizes; a Triple Plane run is refused (its numbers would pass for the parallax's)."""
    tables = _tables()
    run = {"command": "python benchmarks/bench_training_large.py --repr triple-parallax", "cpu": "CPU",
           "cpu_isa": "avx512bf16", "cores": 2, "isa": "avx512bf16", "representation": "triple-parallax",
           "rows": [{"recipe": "fast", "subtexel": 0.0, "cached_msps": 6.06, "large_msps": 3.434, "ratio": 0.567,
                     "step_seconds": 0.751, "peak_rss_gb": 1.96, "stereo_seconds_cached": 12.6,
                     "stereo_seconds_large": 37.2}]}
    _check_row(tables.fullsize_parallax_throughput, run,
               "`triple-parallax`: training throughput and peak memory, stereo height included "
               "(`python benchmarks/bench_training_large.py --repr triple-parallax`",
               "3.43 M samples/s on the 400 x 400 file vs 6.06 on the cached 128 x 128 (0.57x; 0.75 s per step); "
               "peak memory **1.96 GB**; the stereo height 37 s at 400 x 400, 13 s at 128 x 128",
               "at most 4 GB", lambda d: d["rows"][0].update(peak_rss_gb=4.5))
    with pytest.raises(ValueError, match="a run of --repr triple-parallax expected, got 'triple'"):
        tables.fullsize_parallax_throughput(run | {"representation": "triple"})


def _finished_curve(minutes_psnr, isa="avx2"):
    """A curve file as measure_fit_curves.py writes it: scores every 3 min (``minutes_psnr``), 10 steps a minute."""
    curve = [{"seconds": 0.0, "psnr": 1.0, "step": 0}] + [{"seconds": 60.0 * m, "psnr": p, "step": 10 * m}
                                                          for m, p in minutes_psnr]
    final = curve[-1]["psnr"]
    within = next(q["seconds"] for q in curve if all(r["psnr"] >= final - 0.5 for r in curve[curve.index(q):]))
    return {"benchmark": "fit_curves", "command": "python benchmarks/measure_fit_curves.py --btf big.btf",
            "commit": "abc1234", "cpu": "Some CPU", "cpu_isa": "avx512bf16", "cores": 2, "isa": isa, "name": "big",
            "btf": "/data/big.btf", "repr": "triple", "size": [400, 400], "directions": [151, 151],
            "recipe": "recipe for 400 x 400 texels", "stereo_seconds": 0.0, "curve": curve, "finished": True,
            "final_psnr": final, "seconds_to_within_0_5_db": within, "training_seconds": curve[-1]["seconds"],
            "steps": curve[-1]["step"]}


def test_a_recorded_fit_curve_renders_its_scores_and_its_time_to_within_half_a_db(tmp_path, monkeypatch):
    """measure_fit_curves.py --record: the finished curve becomes a part of the results file (the others kept);
    the table shows at most 10 evenly spaced scores and the last, and the minutes after which the curve stays within
    0.5 dB of its final PSNR (not the first time it got there); the full-size row states the 2-hour AVX2 target."""
    import json

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import measure_fit_curves

    tables = _tables()
    scores = [(3 * k, 20.0 + min(k, 10) * 0.7) for k in range(1, 25)]  # 27.0 from 30 min on
    scores[5] = (18, 26.8)  # within 0.5 dB once at 18 min, then below again
    path = tmp_path / "fullsize.json"
    path.write_text(json.dumps({"benchmark": "fullsize", "parallax_curve": {"points": []}}))
    measure_fit_curves.record(_finished_curve(scores), path, "curve", note="other work shared the cores")
    data = json.loads(path.read_text())
    assert "parallax_curve" in data and data["curve"]["minutes_to_within_0_5_db"] == 30.0
    assert data["curve"]["points"][0] == {"minutes": 3.0, "step": 30, "psnr": pytest.approx(20.7)}
    assert data["curve"]["steps_to_within_0_5_db"] == 300
    text = tables.fullsize_curve(data)
    header = text.splitlines()[2]
    assert header.startswith("| training time (min) | 9 | 18 | 27 | 36 |") and header.endswith("| 72 |"), header
    assert "level avx2 (forced)" in text and "(`big.btf`, the recipe for 400 x 400 texels;" in text
    assert "16 pairs; other work shared the cores):" in text
    assert "Within 0.5 dB of the final 27.00 dB after **30 min** of training; 720 steps in 72 min" in text
    what, result, target = tables.fullsize_curve_row(data)
    assert result.startswith("**30 min** (27.0 dB at the end") and target == "at most 2 h on AVX2 (met)"
    slow = json.loads(path.read_text())
    slow["curve"]["minutes_to_within_0_5_db"] = 130.0
    assert tables.fullsize_curve_row(slow)[2] == "at most 2 h on AVX2 (not met)"
    unfinished = _finished_curve(scores) | {"finished": False}
    with pytest.raises(SystemExit, match="is not finished"):
        measure_fit_curves.record(unfinished, path, "curve")


def test_a_measured_parallax_curve_renders_like_the_flat_one_and_its_row_states_the_90_minute_target(tmp_path,
                                                                                                   monkeypatch):
    """measure_fit_curves.py --repr triple-parallax --part parallax_curve: the same table as the flat curve's (its
    stereo seconds stated), and the full-size row with the step it stays within 0.5 dB from, beside the flat curve's
    end, against 90 minutes."""
    import json

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import measure_fit_curves

    tables = _tables()
    path = tmp_path / "fullsize.json"
    path.write_text(json.dumps({"benchmark": "fullsize"}))
    measure_fit_curves.record(_finished_curve([(3 * k, 20.0 + min(k, 10) * 0.7) for k in range(1, 25)]), path,
                              "curve")
    relief = _finished_curve([(5 * k, 22.0 + min(k, 12) * 0.75) for k in range(1, 15)], isa="avx512bf16")
    measure_fit_curves.record(relief | {"repr": "triple-parallax", "stereo_seconds": 31.4}, path, "parallax_curve")
    data = json.loads(path.read_text())
    text = tables.fullsize_parallax_curve(data)
    assert text.startswith("Measured on Some CPU (2 cores, best level avx512bf16), level avx512bf16, by "), text[:120]
    assert text.rstrip().endswith("Within 0.5 dB of the final 31.00 dB after **60 min** of training; 700 steps in "
                                  "70 min in all, 6.00 s per step (the stereo height before it: 31 s).")
    _check_row(tables.fullsize_parallax_curve_row, data,
               "`triple-parallax`: time to within 0.5 dB of the final held-out PSNR "
               "(`python benchmarks/measure_fit_curves.py --btf big.btf`",
               "**60 min** of training (step 600 of 700, 6.00 s per step; the stereo height before it 31 s), "
               "31.00 dB at the end; the Triple Plane's curve above ends at 27.00 dB",
               "at most 90 min", lambda d: d["parallax_curve"].update(minutes_to_within_0_5_db=95.0))


def _check_row(render, data: dict, what: str, result: str, target: str, spoil) -> None:
    """A summary row ``render(data)``: its first cell starts with ``what``, its result is ``result``, its target
    ``target`` is met; after ``spoil(data)`` it is not."""
    cells = render(data)
    assert cells[0].startswith(what), cells[0]
    assert cells[1:] == (result, f"{target} (met)")
    spoil(data)
    assert render(data)[2] == f"{target} (not met)"
