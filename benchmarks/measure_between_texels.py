"""Point queries between texel centres: how far a fitted model's colours there drift from its colours at the centres.

A BTF is measured at texel centres, and a model is fitted there; a renderer queries every real ``uv``. Between
two centres the Triple Plane fetches a bilinear mix of the texels' features, and the decoder, which is not
linear, need not map that mix to anything like the texels' colours. For each model this decodes every texel of
one repeat with ``tile`` (``SynthesizedBTF.eval``, what a renderer calls), at the texel centres and shifted from
them by each of ``--offsets`` (in texels), under the quality report's three view/light pairs
(:data:`dynbtf.synthesis.quality.DEFAULT_PAIRS`), and measures against the centres' colours:

* **RGB W1/std**: the per-channel Wasserstein-1 distance of the colours over the standard deviation of the
  centres' (:func:`dynbtf.synthesis.quality.w1_over_std`), the largest over the channels and pairs;
* **mean ratio**: the mean colour over the centres' mean (the mean over channels; the smallest over the pairs);
* **the centres' mix**: the RGB W1/std of the bilinear mix of the centres' colours at the same points, what a
  model whose colours between centres were the mix of its texels' would score (a mix is smoother than the texels:
  this is the floor of the first column, not 0).

At offset 0 both are exact (0 and 1). A model whose decoded colours were the bilinear mix of its texels' would
score small values and a ratio near 1; a large W1/std means that magnified renders, free rotations and free
scales show colours the measured material does not have (why ``rotation`` turns by quarter turns only:
docs/synthesis.md, "Turned samples").

Run: ``python benchmarks/measure_between_texels.py MODEL.dbtfm [MODEL.dbtfm ...] [--offsets 0.25,0 0.5,0 0.5,0.5]
[--images docs/images]``. Writes ``benchmarks/results/between_texels.json`` (docs/triple_plane.md's table) and, with
``--images``, ``between_texels_closeup.png``: the first model's ``tile`` over 12 x 12 texels, 32 pixels per texel
(view along the normal, light at 40 degrees).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def texel_grid_colours(btf, shift: tuple[float, float], view, light) -> np.ndarray:
    """``(H W, 3)``: ``btf`` (tile) at every texel centre of one repeat moved by ``shift`` texels."""
    from dynbtf.conventions import spherical_to_direction

    h, w = (int(s) for s in btf.synthesizer.exemplar.shape[:2])
    ys, xs = np.mgrid[0:h, 0:w]
    uv = np.stack([(xs.ravel() + 0.5 + shift[0]) / w, (ys.ravel() + 0.5 + shift[1]) / h], -1)
    n = uv.shape[0]
    w_view = np.repeat(spherical_to_direction(np.array([view[0]]), np.array([view[1]])), n, 0)
    w_light = np.repeat(spherical_to_direction(np.array([light[0]]), np.array([light[1]])), n, 0)
    return np.asarray(btf.eval(uv, w_view, w_light), dtype=np.float64)


def centres_mix(colours: np.ndarray, height: int, width: int, shift: tuple[float, float]) -> np.ndarray:
    """``(H W, 3)``: the bilinear mix (periodic) of the texel-centre ``colours (H W, 3)`` at every centre moved by
    ``shift`` texels (each in ``[0, 1)``)."""
    image = colours.reshape(height, width, -1)
    fx, fy = shift
    right, up = np.roll(image, -1, 1), np.roll(image, -1, 0)
    diagonal = np.roll(up, -1, 1)
    mix = (1 - fx) * (1 - fy) * image + fx * (1 - fy) * right + (1 - fx) * fy * up + fx * fy * diagonal
    return mix.reshape(height * width, -1)


def measure(model: Path, offsets: list[tuple[float, float]]) -> list[dict]:
    """A row per offset of ``model``: RGB W1/std (largest over channels and pairs), mean ratio (smallest) and the
    centres' mix's RGB W1/std (largest)."""
    from results_io import model_record

    from dynbtf.synthesis.quality import DEFAULT_PAIRS, w1_over_std
    from dynbtf.synthesized import synthesized_btf

    btf = synthesized_btf(model, "tile")
    h, w = (int(s) for s in btf.synthesizer.exemplar.shape[:2])
    centres = [texel_grid_colours(btf, (0.0, 0.0), view, light) for view, light in DEFAULT_PAIRS]
    rows = []
    for offset in offsets:
        w1, ratio, floor = [], [], []
        for (view, light), centre in zip(DEFAULT_PAIRS, centres):
            shifted = texel_grid_colours(btf, offset, view, light)
            w1.append(float(w1_over_std(shifted, centre).max()))
            ratio.append(float((shifted.mean(0) / np.maximum(centre.mean(0), 1e-12)).mean()))
            floor.append(float(w1_over_std(centres_mix(centre, h, w, offset), centre).max()))
        rows.append({"model": model_record(model), "offset_texels": list(offset), "rgb_w1": max(w1),
                     "mean_ratio": min(ratio), "centres_mix_rgb_w1": max(floor)})
        print(f"{model.name:<28} offset {offset}: RGB W1/std {max(w1):.3f}, mean ratio {min(ratio):.3f}, the "
              f"centres' mix {max(floor):.3f}", file=sys.stderr, flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", type=Path, help="fitted model files (.dbtfm)")
    parser.add_argument("--offsets", nargs="+", default=["0.25,0", "0.5,0", "0.5,0.5"],
                        help="shifts from the texel centres, 'dx,dy' in texels (default: 0.25,0 0.5,0 0.5,0.5)")
    parser.add_argument("--images", type=Path, default=None, help="folder for between_texels_closeup.png")
    parser.add_argument("--json", type=Path,
                        default=Path(__file__).resolve().parent / "results" / "between_texels.json")
    args = parser.parse_args()
    offsets = []
    for text in args.offsets:
        try:
            dx, dy = (float(v) for v in text.split(","))
        except ValueError:
            parser.error(f"--offsets: expected 'dx,dy' in texels, got {text!r}")
        offsets.append((dx, dy))
    for model in args.models:
        if not model.is_file():
            parser.error(f"{model}: no such model file")
    from results_io import header, write_result

    from dynbtf.synthesis.quality import DEFAULT_PAIRS

    rows = [row for model in args.models for row in measure(model, offsets)]
    result = header("between_texels", "measure_between_texels.py") | {
        "pairs": [list(map(list, pair)) for pair in DEFAULT_PAIRS], "rows": rows}
    from tables import between_texels

    print("\n" + between_texels(result))
    write_result(args.json, result)
    if args.images is not None:
        print(f"wrote {closeup(args.models[0], args.images)}", file=sys.stderr)


def closeup(model: Path, folder: Path, texels: int = 12, pixels_per_texel: int = 32) -> Path:
    """``between_texels_closeup.png``: ``model``'s ``tile`` over ``texels x texels`` texels of the exemplar's middle,
    ``pixels_per_texel`` pixels per texel, one sample per pixel (view (0, 0), light (40, 30))."""
    from dynbtf.io import save_image
    from dynbtf.synthesized import synthesized_btf

    btf = synthesized_btf(model, "tile")
    w = int(btf.synthesizer.exemplar.shape[1])
    corner = (w // 2) / w
    image = btf.image(view=(0.0, 0.0), light=(40.0, 30.0), uv_rect=(corner, corner, corner + texels / w,
                                                                     corner + texels / w),
                      resolution=texels * pixels_per_texel, spp=1)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "between_texels_closeup.png"
    save_image(path, image)
    return path


if __name__ == "__main__":
    main()
