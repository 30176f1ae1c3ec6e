"""The measured tables in README.md and docs/ are generated from the benchmarks' JSON data (benchmarks/tables.py):
each ``<!-- table:NAME -->`` block must be what its data renders, every block must name data that exists, and every
other table must be one of the tables below that report no measurement."""

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


#: The tables outside generated blocks, each by its file and header row: none reports a measurement (conventions,
#: image grids, module and option lists, formats; rendering.md's two parameter tables are checked against the
#: plugin's parameters by tests/test_render_mitsuba.py and tests/test_render_layered.py). A table that reports a
#: measurement belongs in a generated block (benchmarks/tables.py), never on this list.
NOT_MEASUREMENTS = {
    ("README.md", "| what | convention |"),
    ("README.md", "| stone | leather | lacquered wood | woven fabric |"),
    ("README.md", "| ceramic tiles | brick wall |"),
    ("README.md", "| topic | document |"),
    ("docs/architecture.md", "| stage | where | what it produces |"),
    ("docs/architecture.md", "| layer | package(s) | one line |"),
    ("docs/architecture.md", "| world | runtime | runs on |"),
    ("docs/baselines.md", "| kind | module | positional plane (per texel) | angular part | fitted by |"),
    ("docs/cluster.md", "| you have | use | what runs |"),
    ("docs/compiled_material.md", "| backend | reads |"),
    ("docs/compiled_material.md", "| field | meaning |"),
    ("docs/data.md", "| source | class | read / write |"),
    ("docs/layered.md", "| mask | `--mask` | Python |"),
    ("docs/realtime.md", "| file | content |"),
    ("docs/rendering.md", "| what | module / command | renderer |"),
    ("docs/rendering.md", "| Parameter | Type | Description | Default |"),
    ("docs/results.md", "| name | definition |"),
    ("docs/simulator.md", "| name | kind | what it is |"),
    ("docs/simulator.md", "| stone | leather |"),
    ("docs/synthesis.md", "| name | method | dynamic | parameters (defaults) |"),
    ("docs/triple_plane.md", "| parameter | default | meaning |"),
}
_RULE = re.compile(r"^\s*\|(\s*:?-+:?\s*\|)+\s*$")


def hand_typed_tables(text: str) -> list[tuple[int, str]]:
    """(line number, header row) of each markdown table in ``text`` outside generated blocks and code fences."""
    found, block, fence = [], None, False
    lines = text.split("\n")
    for i, line in enumerate(lines):
        if line.lstrip().startswith(("```", "~~~")):
            fence = not fence
        elif opened := re.match(r"<!-- table:([a-z_]+) -->", line):
            block = opened[1]
        elif line.startswith(f"<!-- /table:{block} -->"):
            block = None
        elif (not fence and block is None and line.lstrip().startswith("|") and i + 1 < len(lines)
              and _RULE.match(lines[i + 1]) and not (i and lines[i - 1].lstrip().startswith("|"))):
            found.append((i + 1, line.strip()))
    return found


def test_every_table_is_generated_or_reports_no_measurement():
    """A table in README.md or docs/*.md is inside a generated block, or is on NOT_MEASUREMENTS: a table of measured
    numbers typed by hand fails here, naming its file and line."""
    tables = _tables()
    hand = [f"{path.relative_to(ROOT).as_posix()}:{line}: {header}" for path in tables.DOCS
            for line, header in hand_typed_tables(path.read_text())
            if (path.relative_to(ROOT).as_posix(), header) not in NOT_MEASUREMENTS]
    assert not hand, ("tables typed by hand; generate each from benchmarks/results/*.json (benchmarks/tables.py) "
                      "or, if it reports no measurement, add it to NOT_MEASUREMENTS:\n" + "\n".join(hand))


def test_hand_typed_table_is_found():
    """The check above sees a table typed between blocks, and not one inside a block or a code fence."""
    text = ("intro\n\n<!-- table:speed -->\n| a | b |\n|---|---|\n| 1 | 2 |\n<!-- /table:speed -->\n\n"
            "```\n| c | d |\n| --- | --- |\n```\n\n| what | ms |\n| --- | ---: |\n| eval | 3.2 |\n")
    assert hand_typed_tables(text) == [(14, "| what | ms |")]


def _recorded_parts(data: dict):
    """The parts of a recorded data file that state a measurement: every dict holding rows or points."""
    if "rows" in data or "points" in data:
        yield data
    for value in data.values():
        if isinstance(value, dict):
            yield from _recorded_parts(value)


def test_recorded_measurements_name_their_command_and_machine():
    """Each recorded data file (``"recorded_from"``, other than speed.json, checked above) states for each part, or
    for each of its rows, the command and machine (null where the hand-typed text did not say); a recorded prose
    cell takes its numbers from the row's ``"values"``, numbers all."""
    import json

    tables = _tables()
    recorded = {path.stem: json.loads(path.read_text()) for path in sorted(tables.RESULTS.glob("*.json"))
                if path.stem != "speed"}
    recorded = {name: data for name, data in recorded.items() if "recorded_from" in data}
    assert recorded
    machine = {"command", "cpu", "cpu_isa", "cores"}
    for name, data in recorded.items():
        assert data["recorded_from"].startswith("the hand-typed "), name
        for part in _recorded_parts(data):
            for row in part.get("rows", []):
                assert machine <= part.keys() or machine <= row.keys(), (name, row)
                values = row.get("values", {})
                assert all(isinstance(v, (int, float)) or isinstance(v, list) and all(
                    isinstance(x, (int, float)) for x in v) for v in values.values()), (name, values)
            assert "rows" in part or machine <= part.keys(), name

