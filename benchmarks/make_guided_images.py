"""docs/images/guided.png: exemplar guidance next to its target, plain tiling and hist.

Run: ``python benchmarks/make_guided_images.py MODEL.dbtfm`` (the picture in docs/layered.md: the leather of
``dynbtf fit 'sim:leather?size=64&grid=ubo2014' -o leather.dbtfm``). Panels, left to right: the target (a painted
grey image: a dark band and a dark disc on a light ground, cut into two classes), tile, hist, and hist guided by the
target (``dynbtf.guided_btf``, the material's texels in two classes by k-means on their decoded appearance: class 0,
the darker, where the target is dark). 6 repeats per uv unit, view normal, light at 35 degrees; 2 x 2 samples per
pixel.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent.parent / "docs" / "images" / "guided.png"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", help="a model file")
    parser.add_argument("--resolution", type=int, default=320)
    parser.add_argument("-o", "--output", type=Path, default=OUT)
    args = parser.parse_args()

    import dynbtf
    from dynbtf.io import save_image

    from dynbtf.guided import example_target

    target = example_target()
    tile, hist = (dynbtf.synthesized_btf(args.model, m, scale=6.0) for m in ("tile", "hist"))
    guided = dynbtf.guided_btf(args.model, target, classes=2, target_size=1.0, target_wrap="clamp", scale=6.0)
    res = args.resolution
    view = dict(view=(0, 0), light=(35, 60), uv_rect=(0, 0, 1, 1), resolution=res, spp=2)
    rows = (np.arange(res) * target.shape[0] // res)
    shown = np.repeat(target[rows][:, rows][..., None], 3, -1).astype(np.float32) * 0.5
    panels = [shown, tile.image(**view), hist.image(**view), guided.image(**view)]
    gap = np.full((res, 6, 3), 0.5, np.float32)
    save_image(args.output, np.concatenate([x for panel in panels for x in (panel, gap)][:-1], 1))
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
