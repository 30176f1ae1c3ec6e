"""Compose docs/rendering.md's figures from the output of one ``dynbtf demo`` run.

Run: ``python benchmarks/make_rendering_images.py DEMO_DIR [--out docs/images] [--no-screenshot]``
where ``DEMO_DIR`` is the demo's output directory (``dynbtf-demo`` by default). Writes

* ``rendering_teaser.png`` -- Mitsuba renders of hist on plane / sphere / cloth, sky (top row)
  and point light (bottom row), each shown at 240 px;
* ``rendering_plane_tile_vs_hist.png`` -- the grazing plane under the sky, tile | hist;
* ``rendering_grazing_preview_tile_hist_hex.png`` -- the fast preview, tile / hist / hex stacked;
* ``rendering_demo_synthesis_8x_tile_hist_hex.png`` -- 256 x 256 corners of the 8x synthesis;
* ``rendering_demo_report_top.png`` -- the top of ``report.html`` in headless Chromium (skipped
  with ``--no-screenshot`` or when no Chromium is installed).

The images are copied pixel for pixel (no resampling except the teaser's 240 px thumbnails), so
what the figures show is what the demo wrote.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from PIL import Image

GAP = 3  # white pixels between panels


def _open(demo: Path, relative: str) -> Image.Image:
    path = demo / relative
    if not path.is_file():
        sys.exit(f"error: {path} not found; is {demo} the output directory of a finished `dynbtf demo`?")
    return Image.open(path).convert("RGB")


def _grid(rows: list[list[Image.Image]]) -> Image.Image:
    """Panels of one size in a grid with GAP-pixel white gutters."""
    w, h = rows[0][0].size
    ncols = max(len(r) for r in rows)
    out = Image.new("RGB", (ncols * w + (ncols - 1) * GAP, len(rows) * h + (len(rows) - 1) * GAP), "white")
    for i, row in enumerate(rows):
        for j, panel in enumerate(row):
            out.paste(panel, (j * (w + GAP), i * (h + GAP)))
    return out


def _save(image: Image.Image, path: Path) -> None:
    with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".png", delete=False) as tmp:
        image.save(tmp.name)
    Path(tmp.name).replace(path)
    print(f"wrote {path} ({image.size[0]} x {image.size[1]})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demo", type=Path, help="output directory of `dynbtf demo`")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "images")
    parser.add_argument("--no-screenshot", action="store_true", help="do not run Chromium")
    args = parser.parse_args()
    demo, out = args.demo, args.out
    out.mkdir(parents=True, exist_ok=True)

    thumb = lambda im: im.resize((240, 240), Image.LANCZOS)  # noqa: E731
    teaser = [[thumb(_open(demo, f"render/{shape}_{light}_hist.png")) for shape in ("plane", "sphere", "cloth")]
              for light in ("sky", "point")]
    _save(_grid(teaser), out / "rendering_teaser.png")

    _save(_grid([[_open(demo, "render/plane_sky_tile.png"), _open(demo, "render/plane_sky_hist.png")]]),
          out / "rendering_plane_tile_vs_hist.png")

    _save(_grid([[_open(demo, f"synthesis/grazing_{m}.png")] for m in ("tile", "hist", "hex")]),
          out / "rendering_grazing_preview_tile_hist_hex.png")

    corners = [_open(demo, f"synthesis/{m}_08x.png").crop((0, 0, 256, 256)) for m in ("tile", "hist", "hex")]
    _save(_grid([corners]), out / "rendering_demo_synthesis_8x_tile_hist_hex.png")

    if not args.no_screenshot:
        import sys

        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the tests' headless browser
        from browser import check_in_browser, find_chromium

        if find_chromium() is None:
            print("no Chromium found: report screenshot skipped")
            return
        with tempfile.TemporaryDirectory() as tmp:
            shot = Path(tmp) / "report.png"
            check_in_browser(demo / "report.html", screenshot=shot, window=(1400, 1500))
            top = Image.open(shot).convert("RGB").crop((0, 0, 1400, 1500)).resize((700, 750), Image.LANCZOS)
            _save(top, out / "rendering_demo_report_top.png")


if __name__ == "__main__":
    main()
