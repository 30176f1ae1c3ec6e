"""Make the figures of docs/baselines.md that ``dynbtf compare`` does not write itself.

Usage::

    python benchmarks/make_baseline_images.py --row "woven fabric" 'sim:woven_fabric?size=128' CMP_DIR \\
        [--row LABEL BTF CMP_DIR ...] [--out docs/images/baselines_fig9.png] [--panel 192] [--gamma G] \\
        [--strip SYN_DIR --strip-out docs/images/baselines_synthesis_wood128.png]

**The paper's Fig. 9 on our data** (``--row``, ``--out``): NeuMIP vs Triple Plane, each with tiling
and with histogram-preserving blending.

Each ``CMP_DIR`` is a ``dynbtf compare`` output directory holding ``triple.dbtfm`` and
``neumip.dbtfm`` fitted to ``BTF`` (same held-out split). One row per material, columns as in the
paper's Fig. 9 -- NeuMIP w/ tiling | Triple Plane w/ tiling | NeuMIP w/ hist. preserving | Triple
Plane w/ hist. preserving -- preceded by the reference: the measured exemplar itself, tiled. Every
panel shows the same 3 x 3 exemplar repeats (uv ``[0, 3)^2`` at scale 1), rendered at one texel per
sample and box-filtered to ``--panel`` pixels, under one held-out (view, light) pair (never used in
either fit: the pair nearest view (0, 0) and light (45 deg, 30 deg)); below each, a detail of the
centre (64 x 64 texels at 3 pixels per texel). The tiling panels carry their mean FLIP against the
reference over the 3 x 3 repeats (the same number as ``dynbtf eval`` on that pair, up to the
directions' round trip through degrees); the synthesized panels have no ground truth. Prints those
numbers. ``--gamma`` sets hist's blending exponent (default: the library's).

**The synthesis strip** (``--strip``, ``--strip-out``): the centre 384 x 384 pixels of the
``images/synthesis_<method>.png`` that ``dynbtf compare --synthesis KIND --scale 15`` wrote into
``SYN_DIR`` (tile | hist | hex | quilt), box-filtered to 288 pixels each, side by side; quilting's
label carries its extra storage from ``SYN_DIR/synthesis.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dynbtf.conventions import direction_to_spherical, spherical_to_direction
from dynbtf.data.open import open_btf
from dynbtf.io import to_uint8_srgb
from dynbtf.metrics import flip
from dynbtf.representations.model_file import load_model
from dynbtf.synthesized import synthesized_btf

REPEATS = 3  # exemplar repeats per panel side (tiling shows 3 x 3 copies)
DETAIL_TEXELS = 64  # side of the centre detail, texels
DETAIL_ZOOM = 3  # pixels per texel of the detail
#: The figure's (view, light) is the held-out pair nearest these (theta, phi) in degrees.
TARGET_VIEW, TARGET_LIGHT = (0.0, 0.0), (45.0, 30.0)


def pick_pair(held_out: np.ndarray, views: np.ndarray, lights: np.ndarray) -> tuple[int, int]:
    """The held-out (view, light) pair nearest ``TARGET_VIEW``, ``TARGET_LIGHT`` (sum of squared chord distances)."""
    target_view, target_light = (spherical_to_direction(np.array(t), np.array(p)) for t, p in (TARGET_VIEW, TARGET_LIGHT))
    cost = (np.sum((views[held_out[:, 0]] - target_view) ** 2, axis=1)
            + np.sum((lights[held_out[:, 1]] - target_light) ** 2, axis=1))
    v, l = held_out[int(np.argmin(cost))]
    return int(v), int(l)


def box_down(image: np.ndarray, side: int) -> np.ndarray:
    """Box-filter a square ``(n, n, 3)`` image to ``(side, side, 3)`` (``n`` a multiple of ``side``)."""
    n = image.shape[0]
    f = n // side
    return image[:side * f, :side * f].reshape(side, f, side, f, 3).mean(axis=(1, 3))


def detail(image: np.ndarray) -> np.ndarray:
    """The centre ``DETAIL_TEXELS`` x ``DETAIL_TEXELS`` texels at ``DETAIL_ZOOM`` pixels per texel."""
    c, h = image.shape[0] // 2, DETAIL_TEXELS // 2
    crop = image[c - h:c + h, c - h:c + h]
    return np.repeat(np.repeat(crop, DETAIL_ZOOM, axis=0), DETAIL_ZOOM, axis=1)


def material_row(label: str, spec: str, cmp_dir: Path, hist_params: dict) -> tuple[list[np.ndarray], list[str], float, str]:
    """Panels (linear, full texel resolution), captions, exposure (from the reference) and title of one material."""
    source = open_btf(spec)
    models = {kind: load_model(cmp_dir / f"{kind}.dbtfm") for kind in ("neumip", "triple")}
    held = {kind: np.asarray(meta["provenance"]["held_out_pairs"]) for kind, (_, meta) in models.items()}
    if not np.array_equal(held["neumip"], held["triple"]):
        raise SystemExit(f"{cmp_dir}: the two models have different held-out pairs")
    v, l = pick_pair(held["triple"], source.views, source.lights)
    view = [float(x) for x in direction_to_spherical(source.views[v])]
    light = [float(x) for x in direction_to_spherical(source.lights[l])]
    height, width = source.height, source.width
    reference = np.tile(source.image(v, l), (REPEATS, REPEATS, 1))
    images, captions = [reference], ["reference (measured, tiled)"]
    for method in ("tile", "hist"):
        for kind in ("neumip", "triple"):
            btf = synthesized_btf(models[kind][0], method, scale=1.0, seed=0, device="cpu",
                                 **(hist_params if method == "hist" else {}))
            image = btf.image(view, light, (0.0, 0.0, float(REPEATS), float(REPEATS)),
                              (REPEATS * height, REPEATS * width))
            name = {"neumip": "NeuMIP", "triple": "Triple Plane"}[kind]
            caption = f"{name} w/ {'tiling' if method == 'tile' else 'hist. preserving'}"
            if method == "hist" and hist_params:
                caption += f" (gamma {hist_params['gamma']:g})"
            if method == "tile":
                error = flip(reference, image)
                caption += f"  FLIP {error:.3f}"
                print(f"{label}: {name} tiling, held-out pair (view {v}, light {l}): FLIP {error:.4f}")
            images.append(image)
            captions.append(caption)
    exposure = 0.8 / float(np.percentile(reference, 99.5))
    title = (f"{label}: view {view[0]:.0f}/{view[1]:.0f} deg, light {light[0]:.0f}/{light[1]:.0f} deg "
             f"(held-out pair {v}, {l}); {REPEATS} x {REPEATS} repeats of {height} x {width} texels")
    return images, captions, exposure, title


def synthesis_strip(syn_dir: Path, out: Path, side: int = 288, crop: int = 384) -> None:
    """The strip of ``compare --synthesis`` images (see the module docstring)."""
    import json

    from PIL import Image, ImageDraw

    rows = {r["method"]: r for r in json.loads((syn_dir / "synthesis.json").read_text())["rows"]}
    pad, top = 6, 16
    canvas = Image.new("RGB", (pad + len(rows) * (side + pad), top + side + pad), "white")
    draw = ImageDraw.Draw(canvas)
    for i, (method, row) in enumerate(rows.items()):
        image = Image.open(syn_dir / "images" / f"synthesis_{method}.png").convert("RGB")
        w, h = image.size
        box = (w // 2 - crop // 2, h // 2 - crop // 2, w // 2 + crop // 2, h // 2 + crop // 2)
        x = pad + i * (side + pad)
        if not row["dynamic"]:
            label = f"{method} (pre-generated, +{row['synthesis_storage_bytes'] / 1e6:.0f} MB)"
        else:
            label = method if method == "tile" else f"{method} (dynamic)"
        draw.text((x, 2), label, fill="black")
        canvas.paste(image.crop(box).resize((side, side), Image.BOX), (x, top))
    out.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--row", nargs=3, action="append", metavar=("LABEL", "BTF", "CMP_DIR"), default=[])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "images" / "baselines_fig9.png"))
    parser.add_argument("--panel", type=int, default=192, help="side of the full panels, pixels")
    parser.add_argument("--gamma", type=float, default=None, help="hist's blending exponent (default: the library's, "
                        "7; 1 = Heitz & Neyret's, the paper's)")
    parser.add_argument("--strip", type=Path, help="a `dynbtf compare --synthesis` output directory")
    parser.add_argument("--strip-out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "images" / "baselines_synthesis_wood128.png")
    args = parser.parse_args()
    if args.strip:
        synthesis_strip(args.strip, args.strip_out)
    if not args.row:
        return
    hist_params = {} if args.gamma is None else {"gamma": args.gamma}

    from PIL import Image, ImageDraw

    pad, title_h, caption_h = 6, 16, 14
    rows = [material_row(label, spec, Path(d), hist_params) for label, spec, d in args.row]
    n_cols = len(rows[0][0])
    detail_side = DETAIL_ZOOM * DETAIL_TEXELS
    row_h = title_h + caption_h + args.panel + pad + detail_side + 2 * pad
    canvas = Image.new("RGB", (n_cols * (args.panel + pad) + pad, len(rows) * row_h), "white")
    draw = ImageDraw.Draw(canvas)
    for r, (images, captions, exposure, title) in enumerate(rows):
        top = r * row_h
        draw.text((pad, top + 2), title, fill="black")
        for c, (image, caption) in enumerate(zip(images, captions)):
            x = pad + c * (args.panel + pad)
            draw.text((x, top + title_h), caption, fill="black")
            y = top + title_h + caption_h
            canvas.paste(Image.fromarray(to_uint8_srgb(box_down(image, args.panel), exposure)), (x, y))
            canvas.paste(Image.fromarray(to_uint8_srgb(detail(image), exposure)),
                         (x + (args.panel - detail_side) // 2, y + args.panel + pad))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
