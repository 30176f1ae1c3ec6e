"""The layered web export's frame time, against each of its layers drawn alone, in headless Chromium.

Run: ``python benchmarks/bench_web_layered.py [--layers A.dbtfm B.dbtfm]`` (default: the two materials of
``bench_guided.py``, fitted once into its cache; a few minutes in software GL). Both layers are exported with hist
at ``--scale`` repeats per uv unit (``dynbtf.export.web.layered.export_layered_web``, fp16) under two masks: value
noise (``noise:0.35,3,3``, a boundary band of ``--width`` across the frame) and an image of zeros (layer 0
everywhere: layer 1's pass has nothing to draw). Each frame is the plane seen from above, ``--span`` uv units across
its height, at ``--width-px`` x ``--height-px`` (``tests/chromium.py``'s ``time_layered_frames``: every frame waits
for its pixels; the first is a warm-up); the median of ``--frames`` frames is recorded for layer 0 alone, layer 1
alone and the layered material, with the GL renderer Chromium reports.

The rows are written as JSON (``--json``, default ``benchmarks/results/web_layered.json``), from which the table in
docs/layered.md is generated (``python benchmarks/tables.py``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))  # the headless-Chromium driver
from results_io import RESULTS, header, write_result  # noqa: E402

MASKS = {"value noise, a band across the frame": "noise:0.35,3,3", "zeros: layer 0 everywhere": None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--layers", nargs=2, default=None, help="two fitted models (default: bench_guided's)")
    parser.add_argument("--scale", type=float, default=6.0)
    parser.add_argument("--width", type=float, default=0.04, help="the band's half-width (uv units)")
    parser.add_argument("--span", type=float, default=2.0, help="uv units across the frame's height")
    parser.add_argument("--width-px", type=int, default=640)
    parser.add_argument("--height-px", type=int, default=360)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--gl", default="gpu", choices=["gpu", "swiftshader"])
    parser.add_argument("--json", type=Path, default=RESULTS / "web_layered.json")
    args = parser.parse_args()

    from bench_guided import DEFAULT_LAYERS, fitted
    from chromium import time_layered_frames
    from dynbtf.export.web.layered import export_layered_web
    from dynbtf.layered import ImageMask, LayeredBTF, mask_from_spec
    from dynbtf.synthesized import synthesized_btf

    paths = [Path(p) for p in args.layers] if args.layers else [fitted(spec) for spec in DEFAULT_LAYERS]
    names = [p.name for p in paths] if args.layers else list(DEFAULT_LAYERS)
    layers = [synthesized_btf(p, "hist", scale=args.scale) for p in paths]
    rows, renderer = [], None
    with tempfile.TemporaryDirectory(prefix="dynbtf-bench-web-layered-") as tmp:
        for what, spec in MASKS.items():
            mask = mask_from_spec(spec) if spec else ImageMask(np.zeros((8, 8)), size=1.0)
            export = export_layered_web(LayeredBTF(layers, mask, width=args.width), Path(tmp) / str(len(rows)))
            frames = time_layered_frames(export.directory, width=args.width_px, height=args.height_px,
                                         frames=args.frames, span=args.span, gl=args.gl)
            renderer = frames.renderer
            ms = {k: statistics.median(v) for k, v in frames.frame_ms.items()}
            rows.append({"mask": what, "ms_layer0": ms["layer 0 alone"], "ms_layer1": ms["layer 1 alone"],
                         "ms_layered": ms["layered"], "software": frames.software})
            print(f"{what}: layer 0 alone {ms['layer 0 alone']:.0f} ms, layer 1 alone {ms['layer 1 alone']:.0f} ms, "
                  f"layered {ms['layered']:.0f} ms per frame ({frames.renderer})", file=sys.stderr, flush=True)
    write_result(args.json, {**header("web_layered", "bench_web_layered.py"), "layers": names, "scale": args.scale,
                             "width": args.width, "span": args.span, "size": [args.width_px, args.height_px],
                             "frames": args.frames, "renderer": renderer, "rows": rows})


if __name__ == "__main__":
    main()
