"""Render docs/rendering.md's relief figure: a triple-parallax model in Mitsuba, with and without its march.

Run: ``python benchmarks/make_relief_images.py STONE_MODEL [--out docs/images] [--size 320] [--spp 64]``
where ``STONE_MODEL`` is a ``triple-parallax`` model file, e.g. from
``dynbtf fit 'sim:stone?size=64' --repr triple-parallax -o stone.dbtfm --minutes 5``. Writes
``rendering_relief_stone.png``: the grazing plane (top) and the sphere (bottom) under the point
light, rendered by the ``dynbtf`` plugin with the features fetched at ``uv`` (left: the same model
without its ray march, what the plugin could render before) and at the visible point the kernel
marches to (right). Prints each render's time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from PIL import Image

GAP = 3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "images"))
    parser.add_argument("--size", type=int, default=320)
    parser.add_argument("--spp", type=int, default=64)
    args = parser.parse_args()

    import drjit as dr

    from dynbtf.io import to_uint8_srgb
    from dynbtf.jit import mi_module
    from dynbtf.render.mitsuba.bsdf import load_plugin_model, register_plugin
    from dynbtf.render.mitsuba.scenes import bsdf_dict, scene_dict

    model = load_plugin_model(args.model)
    if getattr(model, "kind", None) != "triple-parallax":
        raise SystemExit(f"error: {args.model} is a {getattr(model, 'kind', '?')!r} model; expected 'triple-parallax'")
    register_plugin("llvm_ad_rgb")
    mi = mi_module()
    rows = []
    for scene_name, scale in (("plane", 16.0), ("sphere", 6.0)):
        scene = mi.load_dict(scene_dict(scene_name, bsdf_dict(args.model, method="hist", scale=scale),
                                        lighting="point", resolution=(args.size, args.size), spp=args.spp))
        bsdf = next(s.bsdf() for s in scene.shapes() if s.id() == "surface")
        row = []
        for march in (False, True):
            bsdf.evaluator.btf.relief = march
            t0 = time.perf_counter()
            img = mi.render(scene, spp=args.spp, seed=0)
            dr.eval(img)
            image = np.asarray(img, dtype=np.float32)
            print(f"{scene_name}, march {'on' if march else 'off'}: {time.perf_counter() - t0:.1f} s "
                  f"({args.size}^2, {args.spp} spp, incl. Mitsuba's kernel compilation)")
            row.append(Image.fromarray(to_uint8_srgb(image)))
        rows.append(row)
    w, h = rows[0][0].size
    canvas = Image.new("RGB", (2 * w + GAP, 2 * h + GAP), "white")
    for i, row in enumerate(rows):
        for j, panel in enumerate(row):
            canvas.paste(panel, (j * (w + GAP), i * (h + GAP)))
    out = Path(args.out) / "rendering_relief_stone.png"
    canvas.save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
