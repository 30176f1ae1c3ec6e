"""Regenerate the simulator contact sheets in docs/images/ (used by docs/simulator.md and the README).

Usage: python benchmarks/make_simulator_images.py [--size 112] [--exposure 0.8]

For each material: a 3 x 3 sheet of stored values (linear RGB pi * f_r, times
the exposure, highlights above 0.6 compressed smoothly towards 1 (a film-like
shoulder -- see :func:`compress_highlights`), then sRGB-encoded), rows =
views, columns = lights, all directions taken from the UBO2003 grid:

* rows: view theta 0, 45, 75 deg (phi 0: the camera looks from +u, the right);
* columns: light theta 0; light theta 45, phi 180 (mirror of the middle row's
  view: the specular peak); light theta 75, phi 90 (grazing, from +v = below:
  long cast shadows towards the top).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dynbtf.conventions import spherical_to_direction
from dynbtf.data.simulated import MATERIALS, simulated_btf
from dynbtf.io import save_image

VIEWS = [(0.0, 0.0), (45.0, 0.0), (75.0, 0.0)]
LIGHTS = [(0.0, 0.0), (45.0, 180.0), (75.0, 90.0)]


def contact_sheet(source, views=VIEWS, lights=LIGHTS, gap: int = 2) -> np.ndarray:
    """Images of ``source`` for (theta, phi) views x lights, tiled with a white gap, ``(rows*H, cols*W, 3)``."""
    rows = []
    for tv, pv in views:
        v = source.nearest_view(spherical_to_direction(np.array(tv), np.array(pv)))
        row = []
        for tl, pl in lights:
            l = source.nearest_light(spherical_to_direction(np.array(tl), np.array(pl)))
            row.append(np.pad(source.image(v, l), ((gap, gap), (gap, gap), (0, 0)), constant_values=10.0))
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)


def compress_highlights(x: np.ndarray, knee: float = 0.6, reach: float = 4.0) -> np.ndarray:
    """Identity below ``knee``; above, ``knee + (1 - knee) (1 - exp(-(x - knee) / (reach (1 - knee))))``.

    Continuous, monotonic, below 1: values up to about ``knee + reach`` keep visible differences.
    """
    w = 1.0 - knee
    return np.where(x <= knee, x, knee + w * (1.0 - np.exp(-(x - knee) / (reach * w)))).astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=112)
    ap.add_argument("--exposure", type=float, default=0.8)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "images")
    args = ap.parse_args()
    for name in MATERIALS:
        sheet = compress_highlights(contact_sheet(simulated_btf(name, size=args.size)) * args.exposure)
        path = save_image(args.out / f"sim_{name}.png", sheet)
        print(f"wrote {path} ({path.stat().st_size // 1024} KB)")


if __name__ == "__main__":
    main()
