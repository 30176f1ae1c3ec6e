"""Evaluating a representation against the measured BTF (``dynbtf eval``).

For each requested (view, light) pair the model's image at the texel centres is
compared with the BTF's: PSNR on linear values, DSSIM and FLIP on clamped
sRGB-encoded images (:mod:`dynbtf.metrics`). Results: one row per pair plus the
means, written as ``metrics.csv`` and ``metrics.json``, and side-by-side PNGs
``ground truth | model | FLIP error map`` (magma colour map, as in the paper's
figures) for a few evenly spaced pairs.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..conventions import direction_to_spherical
from ..data.base import BTFSource
from ..errors import FormatError, InputError
from ..io import atomic_path, linear_to_srgb, save_image, srgb_to_linear
from ..metrics import dssim, flip_map, psnr
from ..representations.base import Representation
from .fit import predict_images
from .fused_mlp import single_intra_op_thread

__all__ = ["Evaluation", "evaluate_model", "resolve_eval_pairs", "flip_colormap", "side_by_side", "write_evaluation"]

METRICS = ("psnr", "dssim", "flip")


@dataclass
class Evaluation:
    """Per-pair metrics (``rows``: dicts with view/light indices and angles, psnr, dssim, flip) and their means."""

    rows: list[dict[str, Any]]
    mean: dict[str, float]
    images: list[Path]

    def summary(self) -> str:
        return (f"{len(self.rows)} pairs: PSNR {self.mean['psnr']:.2f} dB, DSSIM {self.mean['dssim']:.4f}, "
                f"FLIP {self.mean['flip']:.4f}")


def resolve_eval_pairs(spec: str, source: BTFSource, metadata: dict[str, Any] | None = None) -> np.ndarray:
    """The (view, light) index pairs named by ``spec``, int64 ``(P, 2)``.

    ``"held-out"`` -- the pairs the model never saw (from its metadata);
    ``"all"`` -- every pair of the BTF; otherwise a path to a text/CSV file with
    one ``view_index,light_index`` per line (``#`` comments and a header allowed).
    """
    if spec == "held-out":
        pairs = (metadata or {}).get("provenance", {}).get("held_out_pairs")
        if not pairs:
            raise InputError("--pairs held-out: the model file records no held-out pairs; use --pairs all or a file")
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    elif spec == "all":
        pairs = np.array(list(source.pairs()), dtype=np.int64).reshape(-1, 2)
    else:
        path = Path(spec)
        if not path.is_file():
            raise InputError(f"--pairs: expected 'held-out', 'all' or a file of 'view,light' lines; {spec!r} is none")
        rows = []
        for n, line in enumerate(path.read_text().splitlines(), 1):
            line = line.split("#")[0].strip()
            if not line:
                continue
            parts = line.replace(",", " ").split()
            try:
                rows.append((int(parts[0]), int(parts[1])))
            except (ValueError, IndexError):
                if not rows and n == 1:  # a header line
                    continue
                raise FormatError(path, f"line {n}: expected 'view_index,light_index', got {line!r}") from None
        if not rows:
            raise FormatError(path, "no (view, light) pairs listed")
        pairs = np.asarray(rows, dtype=np.int64)
    bad = (pairs[:, 0] < 0) | (pairs[:, 0] >= source.n_views) | (pairs[:, 1] < 0) | (pairs[:, 1] >= source.n_lights)
    if bad.any():
        v, l = pairs[np.argmax(bad)]
        raise InputError(f"pair ({v}, {l}) is outside the BTF {source.name!r} "
                         f"({source.n_views} views x {source.n_lights} lights)")
    return pairs


def flip_colormap(error_map: np.ndarray) -> np.ndarray:
    """FLIP error map ``(H, W)`` in ``[0, 1]`` -> display RGB ``(H, W, 3)`` with matplotlib's magma."""
    from matplotlib import colormaps

    return colormaps["magma"](np.clip(error_map, 0.0, 1.0))[..., :3].astype(np.float32)


def side_by_side(reference: np.ndarray, test: np.ndarray, error_map: np.ndarray, *, min_height: int = 256,
                 gap: int = 4) -> np.ndarray:
    """Display image ``ground truth | model | FLIP map`` (sRGB values in ``[0, 1]``), upscaled (nearest)
    to at least ``min_height`` rows, white gaps of ``gap`` pixels."""
    panels = [linear_to_srgb(reference), linear_to_srgb(test), flip_colormap(error_map)]
    k = max(1, math.ceil(min_height / reference.shape[0]))
    panels = [np.kron(p, np.ones((k, k, 1), dtype=np.float32)) for p in panels]
    h = panels[0].shape[0]
    sep = np.ones((h, gap, 3), dtype=np.float32)
    return np.concatenate([panels[0], sep, panels[1], sep, panels[2]], axis=1)


def evaluate_model(rep: Representation, source: BTFSource, pairs, *, out_dir=None, images: int = 8,
                   progress: bool = True, batch: int = 8) -> Evaluation:
    """Metrics of ``rep`` against ``source`` on ``pairs`` (int ``(P, 2)``); optionally write results.

    Parameters
    ----------
    rep : Representation
        Model of the BTF's spatial size, on any device.
    source : BTFSource
    pairs : array ``(P, 2)``
        (view index, light index) pairs.
    out_dir : path, optional
        If given, :func:`write_evaluation` writes the tables and ``images`` side-by-side PNGs there.
    images : int
        Number of side-by-side PNGs (evenly spaced over ``pairs``).
    batch : int
        Images predicted per model call.
    """
    from tqdm.auto import tqdm

    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs) == 0:
        raise InputError("pairs: nothing to evaluate")
    plane = rep.positional_plane()
    if tuple(plane.shape[:2]) != (source.height, source.width):
        raise InputError(f"the model's positional plane is {tuple(plane.shape[:2])} texels but the BTF "
                         f"{source.name!r} is {source.height} x {source.width}")
    device = plane.device
    show = set(np.linspace(0, len(pairs) - 1, min(images, len(pairs))).astype(int).tolist()) if out_dir else set()
    rows, shown = [], []
    was_training = rep.training
    rep.eval()
    with torch.no_grad(), single_intra_op_thread(device.type == "cpu"):
        for k0 in tqdm(range(0, len(pairs), batch), disable=not progress, desc="evaluating", unit="batch",
                       dynamic_ncols=True):
            chunk = pairs[k0:k0 + batch]
            wv = torch.as_tensor(source.views[chunk[:, 0]], dtype=torch.float32, device=device)
            wl = torch.as_tensor(source.lights[chunk[:, 1]], dtype=torch.float32, device=device)
            pred = predict_images(rep, wv, wl, (source.height, source.width)).float().cpu().numpy()
            for j, (v, l) in enumerate(chunk):
                gt = np.asarray(source.image(int(v), int(l)), dtype=np.float32)
                img = pred[j].reshape(gt.shape)
                fmap, fmean = flip_map(gt, img)
                tv, pv = direction_to_spherical(source.views[v])
                tl, pl = direction_to_spherical(source.lights[l])
                rows.append({"view_index": int(v), "light_index": int(l), "theta_view": round(float(tv), 4),
                             "phi_view": round(float(pv), 4), "theta_light": round(float(tl), 4),
                             "phi_light": round(float(pl), 4), "psnr": psnr(gt, img), "dssim": dssim(gt, img),
                             "flip": fmean})
                if k0 + j in show:
                    shown.append((int(v), int(l), side_by_side(gt, img, fmap)))
    rep.train(was_training)
    mean = {m: float(np.mean([r[m] for r in rows])) for m in METRICS}
    evaluation = Evaluation(rows, mean, [])
    if out_dir is not None:
        write_evaluation(evaluation, out_dir, shown)
    return evaluation


def write_evaluation(evaluation: Evaluation, out_dir, side_by_sides=(), extra: dict[str, Any] | None = None) -> None:
    """Write ``metrics.csv`` (one row per pair, then a ``mean`` row), ``metrics.json`` and the PNGs."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fields = list(evaluation.rows[0].keys())
    with atomic_path(out_dir / "metrics.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(evaluation.rows)
        writer.writerow({fields[0]: "mean", **evaluation.mean})
    for v, l, img in side_by_sides:
        evaluation.images.append(save_image(out_dir / f"pair_v{v:03d}_l{l:03d}.png", srgb_to_linear(img)))
    payload = {"mean": evaluation.mean, "n_pairs": len(evaluation.rows), "pairs": evaluation.rows,
               "images": [p.name for p in evaluation.images],
               "metrics": {"psnr": "dB on linear values, peak 1", "dssim": "(1 - SSIM)/2 on clamped sRGB",
                           "flip": "mean NVIDIA FLIP (LDR) on clamped sRGB"}, **(extra or {})}
    with atomic_path(out_dir / "metrics.json") as tmp:
        tmp.write_text(json.dumps(payload, indent=1, allow_nan=True))
