"""The measured tables in README.md and docs/ are generated from the benchmarks' JSON data (benchmarks/tables.py):
each ``<!-- table:NAME -->`` block must be what its data renders, and every block must name data that exists."""

import importlib.util
import re
from pathlib import Path

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
            assert row["from"] in tables._SPEED_FROM, row
            assert (tables.RESULTS / f"{row['from']}.json").is_file(), row
        else:
            r = row["recorded"]
            assert {"what", "command", "cpu", "cpu_isa", "cores", "values", "result", "target"} <= r.keys(), r
            assert all(isinstance(v, (int, float)) for v in r["values"].values()), r
            assert re.search(r"\{[a-z0-9_]+(:[^}]*)?\}", r["result"]), r["result"]  # the numbers come from values
            r["result"].format(**r["values"]), r["target"].format(**r["values"])


def test_rendering_table_renders_what_bench_render_writes():
    """The rendering table's renderer reads the fields bench_render.py writes (a run's parts: no ``recorded_from``)."""
    tables = _tables()
    head = {"command": "python benchmarks/bench_render.py", "commit": "abc1234", "cpu": "CPU", "cpu_isa": "avx2",
            "cores": 2}
    data = {"benchmark": "rendering",
            "eval": head | {"model": "a random Triple Plane", "model_shape": [128, 128, 16], "method": "hist",
                            "queries": 1000, "repeats": 2, "eval_queries_per_second": {"fp32": 1e6, "bf16": 2e6},
                            "plugin_queries_per_second": 4e6, "plugin_first_call_seconds": 0.5,
                            "max_abs_difference": 1e-4, "max_abs_value": 2.0},
            "relief": head | {"model": "a random triple-parallax model", "model_shape": [128, 128, 17],
                              "relief_texels": 5.0, "method": "hist", "queries": 1000, "repeats": 2,
                              "ns_per_query": {o: {"flat": 100.0, "parallax": 150.0, "dense": 300.0}
                                               for o in ("random order", "sorted by view elevation")},
                              "max_abs_difference_to_dense": 0.1, "dense_value_range": 3.0,
                              "max_abs_difference_to_eval": 1e-4, "eval_value_range": 3.0,
                              "eval_queries_compared": 1000}}
    text = tables.rendering(data)
    assert "Measured on CPU (2 cores, best level avx2)" in text and "4.0 M" in text and "| 1.5x |" in text
    what, result, target = tables._speed_rendering({"part": "relief", "max_difference_of_range": 1e-3}, data)
    assert "1.5x in random order" in result and "(met; tested)" in target
