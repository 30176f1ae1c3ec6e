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
        assert (tables.RESULTS / f"{name}.json").is_file(), f"table {name!r} has no data file"


def test_docs_tables_agree_with_their_data():
    stale = _tables().update(check=True)
    assert not stale, "tables re-typed or data changed; run python benchmarks/tables.py: " + ", ".join(stale)
