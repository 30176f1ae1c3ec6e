"""The web export in a browser: frame time, per-pixel cost, agreement with the library, quantization.

One command, four measurements of ``dynbtf export --format web`` (docs/realtime.md):

1. **Frame time** at 1280 x 720 in headless Chromium: every pixel runs ``dynbtf_eval`` once
   (a full-screen pass, synchronized by a one-pixel read-back), the median of ``--frames``
   frames per method after a warm-up frame, with the GL renderer string Chromium reports.
   ``--gl gpu`` (default) uses the machine's GPU when Chromium finds one and falls back to
   its software GL (SwiftShader) otherwise; ``--gl swiftshader`` forces software GL.
2. **Per-pixel cost**: texel fetches and multiply-adds of the shader (:func:`shader_cost`), next
   to the paper's 2.0 ms per 1920 x 1080 frame (RTX 4090, Falcor).
3. **Agreement**: the shader's values on random queries (uv within 40 repeats and near 1e6,
   random view and light) vs ``SynthesizedBTF.eval``: PSNR per method and precision.
4. **Quantization** (with ``--btf``, the BTF the model was fitted to): held-out PSNR of the model
   with fp16 and u8 planes vs the float32 model, and the export's size vs the model file.

Run: ``python benchmarks/bench_web.py MODEL [--btf BTF]`` (default model: a random Triple Plane
of the paper's size, 128 x 128 texels; frame time and cost do not depend on the weights). ``--weave`` replaces
the model's plane by a weave (an element of 1/8 of its side tiled 8 x 8, plus noise: ``auto`` chooses ``struct``),
the structured stand-in of the struct rows.

Written as JSON (``--json``, default ``benchmarks/results/web.json``) with the command, the commit and the
machine: the parts ``frame_time``, ``agreement`` and ``size`` (with ``--btf``), or with ``--weave`` the part
``struct``; the file's other parts are kept. docs/realtime.md's and docs/results.md's tables are generated from it
(``python benchmarks/tables.py``).
"""

from __future__ import annotations

import argparse
import json
import sys
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

PAPER_MS_1080P = 2.0  # the paper's Table: 1920 x 1080, 1 spp, RTX 4090 (texture fetches + MLP)


def _queries(n, seed=0):
    rng = np.random.default_rng(seed)
    points = (rng.random((n, 2)) - 0.5) * 80.0
    points[n // 2:] += 1e6
    w = rng.normal(size=(2, n, 3))
    w[..., 2] = np.abs(w[..., 2]) + 0.05
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    return points, w[0].astype(np.float32), w[1].astype(np.float32)


def _psnr(got, ref):
    return 10.0 * np.log10(np.abs(ref).max() ** 2 / np.mean((got - ref) ** 2))


def structured_model(model):
    """``model`` if ``auto`` chooses struct for its positional plane, else a copy whose plane is a weave
    (an element of 1/8 of the plane's side, from the plane itself, tiled 8 x 8, plus 10% noise)."""
    import copy

    from dynbtf.synthesis.auto import choose_method

    plane = model.positional_plane().detach()
    if choose_method(plane).method == "struct":
        return model
    h, w, c = plane.shape
    weave = copy.deepcopy(model)
    element = plane[: h // 8, : w // 8]
    generator = torch.Generator().manual_seed(0)
    noise = torch.randn(h // 8 * 8, w // 8 * 8, c, generator=generator)
    with torch.no_grad():
        weave.positional_plane().zero_()
        weave.positional_plane()[: h // 8 * 8, : w // 8 * 8] = element.repeat(8, 8, 1) + 0.1 * float(element.std()) * noise
    return weave


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", nargs="?", default=None, help="model file (default: a random 128 x 128 Triple Plane)")
    parser.add_argument("--btf", default=None, help="the BTF the model was fitted to: adds the held-out quantization loss")
    parser.add_argument("--methods", nargs="+", default=["hist", "hex", "tile"])
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--frames", type=int, default=3, help="timed frames per method (after one warm-up frame)")
    parser.add_argument("--gl", default="gpu", choices=["gpu", "swiftshader"])
    parser.add_argument("--queries", type=int, default=4096, help="queries of the agreement check")
    parser.add_argument("--weave", action="store_true", help="the model with its plane replaced by a weave (the struct "
                                                              "part of the JSON)")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "web.json")
    parser.add_argument("--chromium-flag", action="append", default=[],
                        help="extra Chromium flag for the frame-time run (repeatable), e.g. --use-angle=vulkan "
                             "when the GL renderer printed is still SwiftShader on a machine with a GPU")
    args = parser.parse_args()

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the headless-Chromium driver
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from chromium import eval_in_browser, time_frames
    from results_io import header, write_result
    from dynbtf.export.web.exporter import export_web, quantized_model
    from dynbtf.export.web.shader import shader_cost
    from dynbtf.representations.model_file import load_model, save_model
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesized import synthesized_btf

    work = Path(tempfile.mkdtemp(prefix="dynbtf-bench-web-"))
    if args.model:
        model_path = Path(args.model)
        model, meta = load_model(model_path)
    else:
        model, meta = TriplePlane(128, 128, seed=0), {}
        model_path = save_model(work / "random.dbtfm", model)
    if args.weave:
        model = structured_model(model)
        model_path = save_model(work / "weave.dbtfm", model)
    print(f"model: {model_path.name} ({model.kind}, {model_path.stat().st_size / 1e6:.2f} MB)")
    exports = {p: export_web(model, work / p, precision=p, methods=args.methods) for p in ("fp16", "u8")}

    # 1 + 2: frame time and per-pixel cost
    t0 = time.perf_counter()
    frames = time_frames(exports["fp16"].directory, args.methods, width=args.width, height=args.height,
                         frames=args.frames, gl=args.gl, extra_flags=tuple(args.chromium_flag))
    print(f"\nframe time at {frames.width} x {frames.height} in headless Chromium ({time.perf_counter() - t0:.0f} s)")
    print(f"GL renderer: {frames.renderer}  ->  {'software GL (no GPU used)' if frames.software else 'GPU'}")
    print(f"shader program compile + link: {frames.compile_ms:.0f} ms")
    pixels = frames.width * frames.height
    cfg = model.config()
    paper_ns = PAPER_MS_1080P * 1e6 / (1920 * 1080)
    print(f"{'method':<8}{'ms/frame':>12}{'Mpixel/s':>10}{'ns/pixel':>10}{'x paper':>10}{'fetches':>9}{'MACs':>7}")
    rows = {}
    for m, ms in frames.frame_ms.items():
        med = statistics.median(ms)
        cost = shader_cost(m, channels=cfg["positional_channels"] + getattr(model, "extra_positional_channels", 0),
                           angular_channels=cfg["angular_channels"], hidden=cfg["hidden"], layers=cfg["layers"])
        ns = med * 1e6 / pixels
        print(f"{m:<8}{med:>12.1f}{pixels / med / 1e3:>10.2f}{ns:>10.1f}{ns / paper_ns:>10.0f}"
              f"{cost['texel_fetches']:>9}{cost['macs']:>7}")
        rows[m] = {"method": m, "ms_per_frame": [round(med)], "ns_per_pixel": [round(ns)],
                   "vs_paper": [int(round(ns / paper_ns, -2))], "texel_fetches": cost["texel_fetches"],
                   "multiply_adds": cost["macs"]}
    paper = shader_cost("hist")
    print(f"{'paper':<8}{PAPER_MS_1080P * pixels / (1920 * 1080):>12.2f}{1920 * 1080 / PAPER_MS_1080P / 1e3:>10.0f}"
          f"{paper_ns:>10.2f}{1:>10}{'-':>9}{paper['decoder_macs']:>7}"
          "   (RTX 4090, 2.0 ms per 1920x1080 frame scaled to this size; decoder MACs of its 32-32-32-3 MLP)")

    # 3: agreement with the library
    points, wv, wl = _queries(args.queries)
    print(f"\nshader vs SynthesizedBTF.eval on {args.queries} random queries (half near 1e6 repeats): PSNR dB")
    print(f"{'method':<8}" + "".join(f"{p:>10}" for p in exports))
    agreement = []
    for m in args.methods:
        ref = synthesized_btf(model, m, seed=0).eval(points, wv.astype(np.float64), wl.astype(np.float64))
        row = [_psnr(eval_in_browser(ex.directory, m, points, wv, wl, gl=args.gl).rgb, ref) for ex in exports.values()]
        print(f"{m:<8}" + "".join(f"{x:>10.1f}" for x in row))
        agreement.append({"method": m, "psnr_fp16_db": round(float(row[0]), 1), "psnr_u8_db": round(float(row[1]), 1)})

    # 4: sizes and quantization loss
    size = model_path.stat().st_size
    print(f"\nexport size (binary files; the hist method's plane, tables, angular planes and decoder) vs the model "
          f"file ({size / 1e6:.2f} MB, float32)")
    for p, ex in exports.items():
        print(f"  {p:<5} hist {ex.method_bytes('hist') / 1e6:.2f} MB ({ex.method_bytes('hist') / size:.2f}x the model "
              f"file), all methods {ex.total_bytes() / 1e6:.2f} MB")
    conditions = (f"{model_path.name}, {model.positional_plane().shape[0]} x {model.positional_plane().shape[1]}; "
                  f"{frames.width} x {frames.height}, every pixel one dynbtf_eval, median of {args.frames} frames after "
                  f"a warm-up; GL: {frames.renderer}")
    record = header("web", "bench_web.py")
    record.pop("benchmark")
    if args.weave:
        fp16, u8 = exports["fp16"], exports["u8"]

        def only(export, method):  # the method's own files: its tables (the plane is tile's too)
            files = set(export.manifest["methods"][method]["files"]) - set(export.manifest["methods"]["tile"]["files"])
            return sum(export.manifest["files"][f]["bytes"] for f in files) if "tile" in args.methods else 0

        struct_rows = []
        for r in agreement:
            m = r["method"]
            struct_rows.append({"method": m, "ms_per_frame": rows[m]["ms_per_frame"],
                                "texel_fetches": rows[m]["texel_fetches"], "multiply_adds": rows[m]["multiply_adds"],
                                "psnr_fp16_db": [r["psnr_fp16_db"]], "psnr_u8_db": [r["psnr_u8_db"]],
                                "fp16_mb": round(fp16.method_bytes(m) / 1e6, 2), "u8_mb": round(u8.method_bytes(m) / 1e6, 2),
                                **({"tables_mb": round(only(fp16, m) / 1e6, 2),
                                    "note": "one bilinear footprint, the offset, at most two cut entries"}
                                   if m == "struct" and only(fp16, m) else {})})
        parts = {"struct": record | {"conditions": "a random paper-size Triple Plane whose plane repeats an element of "
                                                   "1/8 of its side plus noise; " + conditions, "rows": struct_rows}}
    else:
        paper_cost = shader_cost("hist")
        parts = {"frame_time": record | {"conditions": conditions, "rows": list(rows.values()),
                                         "paper": {"gpu": "RTX 4090, Falcor",
                                                   "ms_per_frame": round(PAPER_MS_1080P * pixels / (1920 * 1080), 2),
                                                   "ms_per_frame_1080p": PAPER_MS_1080P,
                                                   "ns_per_pixel": round(paper_ns, 2),
                                                   "multiply_adds": paper_cost["decoder_macs"]}},
                 "agreement": record | {"conditions": f"{args.queries} random queries (half of them near 1e6 repeats), "
                                                      "PSNR in dB", "rows": agreement}}
    if args.btf and not args.weave:
        from dynbtf.data.open import open_btf
        from dynbtf.training.evaluate import evaluate_model, resolve_eval_pairs

        source = open_btf(args.btf)
        pairs = resolve_eval_pairs("held-out", source, meta)
        torch.set_num_threads(max(1, torch.get_num_threads()))
        print(f"\nheld-out PSNR ({len(pairs)} pairs, per-image peak) of the model with quantized planes")
        base = evaluate_model(model, source, pairs, images=0, progress=False).mean["psnr"]
        print(f"  fp32  {base:.3f} dB")
        psnr, fp16_loss = {"fp32": round(float(base), 3)}, 0.0
        for p in ("fp16", "u8"):
            q = evaluate_model(quantized_model(model, p), source, pairs, images=0, progress=False).mean["psnr"]
            loss = base - q
            psnr[p] = round(float(q), 3)
            fp16_loss = float(loss) if p == "fp16" else fp16_loss
            print(f"  {p:<5} {q:.3f} dB (loss {'< 0.001' if abs(loss) < 5e-4 else f'{loss:.3f}'} dB)")
        hist = {p: round(ex.method_bytes("hist") / 1e6, 2) for p, ex in exports.items()}
        parts["size"] = record | {
            "conditions": f"held-out PSNR of the model with its feature planes stored as the export stores them "
                          f"(quantized_model); {len(pairs)} held-out pairs of {args.btf}, per-image peak",
            "model_mb": round(size / 1e6, 2), "hist_mb": hist, "u8_of_model": round(hist["u8"] * 1e6 / size, 2),
            "all_methods_mb": {p: round(ex.total_bytes() / 1e6, 2) for p, ex in exports.items()},
            "held_out_psnr_db": psnr, "fp16_loss_below_db": 0.001 if abs(fp16_loss) < 5e-4
            else round(abs(fp16_loss) + 0.001, 3)}
    data = json.loads(args.json.read_text()) if args.json.is_file() else {"benchmark": "web"}
    data.pop("recorded_from", None)
    write_result(args.json, data | parts)


if __name__ == "__main__":
    main()
