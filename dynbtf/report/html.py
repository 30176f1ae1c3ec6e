"""A small, dependency-free HTML report: sections, rows of captioned images, tables.

Images are linked by paths relative to the report file (the report and its
images live in one output directory and can be moved or zipped together). The
page is static: no script, no network access, readable offline in any browser.

Examples
--------
>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> r = HtmlReport("Demo")
>>> r.section("Numbers", "One table.")
>>> r.table([{"method": "hist", "W1/std": 0.0123}], caption="Quality")
>>> path = r.write(d / "report.html")
>>> "<table" in path.read_text() and "0.0123" in path.read_text()
True
"""

from __future__ import annotations

import html
import os
from pathlib import Path
from typing import Any, Iterable, Sequence

from ..io import atomic_path

__all__ = ["HtmlReport", "format_value"]

_CSS = """
body { font-family: system-ui, -apple-system, 'Segoe UI', sans-serif; margin: 24px auto; max-width: 1500px;
       color: #1d1d1f; background: #fafafa; line-height: 1.45; padding: 0 16px; }
h1 { font-size: 1.8em; margin-bottom: 0.2em; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: 4px; margin-top: 2em; }
h3 { margin-bottom: 0.3em; }
p.lead { color: #555; margin-top: 0; }
.row { display: flex; flex-wrap: wrap; gap: 12px; align-items: flex-start; margin: 8px 0 16px 0; }
figure { margin: 0; background: #fff; border: 1px solid #e3e3e3; border-radius: 6px; padding: 6px; }
figure img { display: block; width: var(--w, 256px); height: auto; image-rendering: auto; }
figure img.pixelated { image-rendering: pixelated; }
figcaption { font-size: 0.85em; color: #444; text-align: center; margin-top: 4px; max-width: var(--w, 256px); }
table { border-collapse: collapse; margin: 8px 0 16px 0; background: #fff; font-size: 0.92em; }
caption { caption-side: top; text-align: left; font-weight: 600; padding-bottom: 4px; }
th, td { border: 1px solid #ddd; padding: 4px 10px; text-align: right; }
th { background: #f0f0f3; }
td:first-child, th:first-child { text-align: left; }
code { background: #eee; padding: 1px 4px; border-radius: 3px; }
.note { color: #666; font-size: 0.9em; }
"""


def format_value(value: Any) -> str:
    """Table cell text: floats with 4 significant digits, others via ``str``.

    >>> format_value(0.000123456), format_value(31.234567), format_value(12), format_value(None)
    ('0.0001235', '31.23', '12', '')
    """
    if value is None:
        return ""
    if isinstance(value, float):
        if value != value:  # NaN
            return "nan"
        return f"{value:.4g}"
    return str(value)


class HtmlReport:
    """Accumulates report blocks and writes one HTML file.

    Parameters
    ----------
    title : str
        Page title and top heading.
    subtitle : str, optional
        A line under the title.
    """

    def __init__(self, title: str, subtitle: str | None = None) -> None:
        self.title = title
        self.subtitle = subtitle
        self._blocks: list[tuple[str, Any]] = []

    # ------------------------------------------------------------ blocks
    def section(self, title: str, text: str | None = None, *, level: int = 2) -> None:
        """A heading (``h2``, or ``h3`` with ``level=3``) with an optional paragraph."""
        self._blocks.append(("heading", (level, title)))
        if text:
            self.paragraph(text)

    def paragraph(self, text: str, *, note: bool = False) -> None:
        """A paragraph of plain text (escaped); ``note=True`` renders it small and grey."""
        self._blocks.append(("paragraph", (text, note)))

    def link(self, before: str, target: str | os.PathLike, label: str, after: str = "") -> None:
        """A paragraph ``before <a href=target>label</a> after`` (``target`` made relative like image paths)."""
        self._blocks.append(("link", (before, Path(target), label, after)))

    def images(self, items: Sequence[tuple[str | os.PathLike, str]], *, width: int = 256,
               pixelated: bool = False) -> None:
        """A row of images with captions: ``items`` = ``[(path, caption), ...]``.

        ``width`` is the display width in CSS pixels; ``pixelated`` shows small
        images with nearest-neighbour magnification (texel-accurate).
        """
        self._blocks.append(("images", ([(Path(p), str(c)) for p, c in items], int(width), bool(pixelated))))

    def table(self, rows: Iterable[dict[str, Any]], *, columns: Sequence[str] | None = None,
              caption: str | None = None) -> None:
        """A table from a list of dicts (one per row); ``columns`` fixes the order (default: first row's keys)."""
        rows = list(rows)
        if columns is None:
            columns = list(rows[0].keys()) if rows else []
        self._blocks.append(("table", (list(columns), rows, caption)))

    # ------------------------------------------------------------ output
    def render(self, base_dir: Path) -> str:
        """The HTML text, with image paths made relative to ``base_dir``."""
        e = html.escape
        out = ["<!DOCTYPE html>", "<html lang='en'><head><meta charset='utf-8'>",
               f"<title>{e(self.title)}</title>", f"<style>{_CSS}</style></head><body>",
               f"<h1>{e(self.title)}</h1>"]
        if self.subtitle:
            out.append(f"<p class='lead'>{e(self.subtitle)}</p>")
        for kind, payload in self._blocks:
            if kind == "heading":
                level, title = payload
                out.append(f"<h{level}>{e(title)}</h{level}>")
            elif kind == "paragraph":
                text, note = payload
                out.append(f"<p class='note'>{e(text)}</p>" if note else f"<p>{e(text)}</p>")
            elif kind == "link":
                before, target, label, after = payload
                href = Path(os.path.relpath(target.resolve(), base_dir.resolve())).as_posix()
                out.append(f"<p>{e(before)}<a href='{e(href)}'>{e(label)}</a>{e(after)}</p>")
            elif kind == "images":
                items, width, pixelated = payload
                out.append(f"<div class='row' style='--w: {width}px'>")
                cls = " class='pixelated'" if pixelated else ""
                for path, caption in items:
                    src = Path(os.path.relpath(Path(path).resolve(), base_dir.resolve())).as_posix()
                    out.append(f"<figure><img{cls} src='{e(src)}' alt='{e(caption)}' loading='eager'>"
                               f"<figcaption>{e(caption)}</figcaption></figure>")
                out.append("</div>")
            elif kind == "table":
                columns, rows, caption = payload
                out.append("<table>")
                if caption:
                    out.append(f"<caption>{e(caption)}</caption>")
                out.append("<tr>" + "".join(f"<th>{e(str(c))}</th>" for c in columns) + "</tr>")
                for row in rows:
                    out.append("<tr>" + "".join(f"<td>{e(format_value(row.get(c)))}</td>" for c in columns) + "</tr>")
                out.append("</table>")
        out.append("</body></html>")
        return "\n".join(out)

    def write(self, path: str | os.PathLike) -> Path:
        """Write the report atomically to ``path`` (image links relative to its folder)."""
        path = Path(path)
        text = self.render(path.parent)
        with atomic_path(path) as tmp:
            tmp.write_text(text, encoding="utf-8")
        return path
