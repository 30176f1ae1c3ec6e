"""How fast BTF images come out of each file source, measured side by side in one run.

Usage: python benchmarks/btf_decode_speed.py [--components 32] [--size 400] [--images 40]

Builds a UBO2014-shaped DFMF file (151 x 151 directions, size x size texels, random
half-precision factors with C components per channel: one image = one
(C,) @ (C, size^2) product per channel) and a float16 stored BTF of the same
shape truncated to one view, then prints per-image times of

* ``UBO2014BTF.image`` (one image at a time, the random access training uses),
* ``UBO2014BTF.view_images`` (all lights of a view in one product: what
  ``dynbtf convert`` streams),
* ``StoredBTF.image`` (a raw float16 read),
* btf-extractor's ``Ubo2014`` (if ``.venv-btfx`` exists; see
  ``scripts/install_btf_extractor.sh``): its load time (it reads the whole file
  into memory) and per-image decode (a C++ loop with OpenMP over rows).

Timings on a shared machine move by tens of percent: compare ratios within a run. The rows are written
as JSON (``--json``, default ``benchmarks/results/decode_speed.json``), from which the table in
docs/results.md is generated (``python benchmarks/tables.py``).
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from dynbtf.data import StoredBTF, UBO2014BTF, write_stored
from dynbtf.data.array import ArrayBTF
from dynbtf.data.directions import ubo2014_directions
from dynbtf.data.ubo2014 import write_dfmf_factors
from results_io import RESULTS, header, write_result

REPO = Path(__file__).resolve().parents[1]

_BTFX = r"""
import sys, time
from btf_extractor import Ubo2014
t = time.perf_counter(); btf = Ubo2014(sys.argv[1]); load = time.perf_counter() - t
n = int(sys.argv[2])
t = time.perf_counter()
for k in range(n):
    btf._angleindex_to_image_unsafe(k % 151, (7 * k) % 151)
print(load, (time.perf_counter() - t) / n)
"""


def per_image(fn, n: int) -> float:
    fn(0)  # warm up (page cache, first touch)
    start = time.perf_counter()
    for k in range(n):
        fn(k)
    return (time.perf_counter() - start) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--components", type=int, default=32)
    ap.add_argument("--size", type=int, default=400)
    ap.add_argument("--images", type=int, default=40)
    ap.add_argument("--json", type=Path, default=RESULTS / "decode_speed.json")
    args = ap.parse_args()
    dirs, _ = ubo2014_directions()
    rng = np.random.default_rng(0)
    rows, cols, c = 151 * 151, args.size * args.size, args.components
    u = [rng.standard_normal((rows, c)).astype(np.float32) * 0.1 for _ in range(3)]
    sxv = [rng.standard_normal((cols, c)).astype(np.float32) * 0.1 for _ in range(3)]
    with tempfile.TemporaryDirectory() as tmp:
        path = write_dfmf_factors(Path(tmp) / "bench.btf", dirs, dirs, args.size, args.size, u, sxv, scalar="half")
        print(f"DFMF file: 151 x 151 directions, {args.size}^2 texels, C = {c} half: "
              f"{path.stat().st_size / 2**20:.1f} MiB")
        start = time.perf_counter()
        btf = UBO2014BTF(path)
        print(f"UBO2014BTF open (header + NaN scan of the factors): {time.perf_counter() - start:.3f} s")
        n = args.images
        t_image = per_image(lambda k: btf.image(k % 151, (7 * k) % 151), n)
        t_view = per_image(lambda k: btf.view_images(k % 151), max(2, n // 20)) / 151
        print(f"UBO2014BTF.image        {t_image * 1e3:8.2f} ms/image")
        print(f"UBO2014BTF.view_images  {t_view * 1e3:8.2f} ms/image (151 lights per product)")
        one_view = ArrayBTF(btf.view_images(0)[None], dirs[:1], dirs)
        stored = StoredBTF(write_stored(Path(tmp) / "bench.dbtf", one_view, progress=False))
        t_stored = per_image(lambda k: stored.image(0, (7 * k) % 151), n)
        print(f"StoredBTF.image (f16)   {t_stored * 1e3:8.2f} ms/image")
        python = REPO / ".venv-btfx" / "bin" / "python"
        if python.is_file():
            out = subprocess.run([str(python), "-c", _BTFX, str(path), str(n)], check=True, capture_output=True,
                                 text=True).stdout.split()
            load, t_btfx = float(out[0]), float(out[1])
            print(f"btf-extractor load      {load:8.3f} s (reads the whole file into memory)")
            print(f"btf-extractor image     {t_btfx * 1e3:8.2f} ms/image")
            print(f"ratio image: ours / btf-extractor = {t_image / t_btfx:.2f}; "
                  f"view_images / btf-extractor = {t_view / t_btfx:.2f}")
        else:
            load = t_btfx = None
            print("btf-extractor: not installed (bash scripts/install_btf_extractor.sh)")
    rows = [{"reader": "`UBO2014BTF.image` (random access)", "ms_per_image": round(t_image * 1e3, 2)},
            {"reader": "`UBO2014BTF.view_images` (151 lights in one product)", "ms_per_image": round(t_view * 1e3, 2)}]
    if t_btfx is not None:
        rows.append({"reader": "btf-extractor `Ubo2014` image (after a {load_seconds:g} s load of the whole file "
                               "into memory)", "values": {"load_seconds": round(load, 2)},
                     "ms_per_image": round(t_btfx * 1e3, 2)})
    rows.append({"reader": "`StoredBTF.image`, float16", "ms_per_image": round(t_stored * 1e3, 2)})
    write_result(args.json, {**header("decode_speed", "btf_decode_speed.py"),
                             "conditions": f"{args.size} x {args.size} texels, 151 x 151 directions, C = {c} half "
                                           f"components per channel, {n} images per reader",
                             "rows": rows})


if __name__ == "__main__":
    main()
