"""docs/images/layered.png: a layered material next to its mask and its two materials.

Run: ``python benchmarks/make_layered_images.py LAYER0.dbtfm LAYER1.dbtfm`` (the picture in docs/layered.md:
``dynbtf fit 'sim:leather?size=64&grid=ubo2014' -o leather.dbtfm`` and ``dynbtf fit 'sim:stone?size=64' -o
stone.dbtfm --minutes 3``). Panels, left to right: the mask (value noise), the layered material, layer 0 alone,
layer 1 alone, and which layer each pixel shows (grey: layer 1). hist synthesis at 6 repeats per uv unit, view
normal, light at 35 degrees; 2 x 2 samples per pixel.

With ``--render`` (Mitsuba installed) it also writes docs/images/layered_render.png: the same two materials
path-traced on the grazing plane under the sky by the ``dynbtf_layered`` BSDF (``dynbtf render LAYER0 --layer
LAYER1 --mask noise:0.08,3,7 --width 0.01 --method hist --scale 12 --size 384 --spp 16``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent.parent / "docs" / "images" / "layered.png"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("layers", nargs=2, help="two model files (or .dbtfc)")
    parser.add_argument("--resolution", type=int, default=320)
    parser.add_argument("--width", type=float, default=0.04, help="the boundary band's half-width (uv units)")
    parser.add_argument("-o", "--output", type=Path, default=OUT)
    parser.add_argument("--render", action="store_true", help="also the Mitsuba render (docs/images/layered_render.png)")
    args = parser.parse_args()

    import dynbtf
    from dynbtf.io import save_image

    a, b = (dynbtf.synthesized_btf(path, "hist", scale=6.0) for path in args.layers)
    mask = dynbtf.NoiseMask(scale=0.35, contrast=3.0, seed=3)
    layered = dynbtf.LayeredBTF([a, b], mask, width=args.width)
    res = args.resolution
    view = dict(view=(0, 0), light=(35, 60), uv_rect=(0, 0, 1, 1), resolution=res, spp=2)
    u = (np.arange(res) + 0.5) / res
    uv = np.stack(np.meshgrid(u, u, indexing="xy"), -1).reshape(-1, 2)
    grey = [np.repeat(x.reshape(res, res, 1), 3, -1) * 0.5 for x in (mask.value(uv), layered.weight(uv))]
    panels = [grey[0], layered.image(**view), a.image(**view), b.image(**view), grey[1]]
    gap = np.full((res, 6, 3), 0.5, np.float32)
    row = np.concatenate([x for panel in panels for x in (panel, gap)][:-1], 1)
    save_image(args.output, row)
    print(f"wrote {args.output}")
    if args.render:
        from dynbtf.render.mitsuba.scene_render import render_scene

        result = render_scene(args.layers[0], layer=args.layers[1], mask=dynbtf.NoiseMask(0.08, 3.0, 7), width=0.01,
                              method="hist", scene="plane", lighting="sky", scale=12.0, resolution=(384, 384), spp=16)
        target = args.output.with_name("layered_render.png")
        save_image(target, result.image)
        print(f"wrote {target}")


if __name__ == "__main__":
    main()
