"""Evaluating a representation against the measured BTF (``dynbtf eval``).

For each requested (view, light) pair the model's image at the texel centres is
compared with the BTF's: PSNR on linear values against the reference image's peak
(``psnr``) and against a fixed peak of 1 (``psnr_fixed1``, the older form), DSSIM and
FLIP on clamped sRGB-encoded images (:mod:`dynbtf.metrics`). The means are given over
all pairs and split by angle: **grazing** pairs (view or light more than
:data:`GRAZING_THETA_DEG` from the normal), where relief materials concentrate their
error, and the **others**. Results: one row per pair plus the means, written as
``metrics.csv`` and ``metrics.json``, and side-by-side PNGs
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
from ..metrics import PSNR_FIXED_LABEL, PSNR_LABEL, dssim, flip, flip_magma, psnr, psnr_fixed_range
from ..representations.base import Representation
from .fit import predict_images
from ..decoder.fused_mlp import single_intra_op_thread

__all__ = ["Evaluation", "evaluate_model", "resolve_eval_pairs", "side_by_side", "write_evaluation",
           "GRAZING_THETA_DEG", "METRIC_DESCRIPTIONS"]

METRICS = ("psnr", "psnr_fixed1", "dssim", "flip")
#: A pair is grazing when its view or its light is further than this from the normal (degrees).
GRAZING_THETA_DEG = 60.0
#: What each metric column is (written into metrics.json).
METRIC_DESCRIPTIONS = {
    "psnr": f"{PSNR_LABEL}: 10 log10(max(reference)^2 / MSE) on linear values, per pair, then averaged",
    "psnr_fixed1": f"{PSNR_FIXED_LABEL}: 10 log10(1 / MSE) on linear values (depends on the material's brightness)",
    "dssim": "(1 - SSIM)/2 on clamped sRGB",
    "flip": "mean NVIDIA FLIP (LDR) on clamped sRGB",
}


@dataclass
class Evaluation:
    """Per-pair metrics and their means.

    Attributes
    ----------
    rows : list of dict
        One per pair: view/light indices and angles (degrees), ``grazing``, ``psnr`` (per-image peak),
        ``psnr_fixed1``, ``dssim``, ``flip``.
    mean : dict
        Means over all pairs (``nan`` entries, e.g. the PSNR of an all-black reference, are skipped).
    images : list of Path
    by_angle : dict
        ``{"grazing": {...}, "others": {...}}``: the count ``n`` and the means of the grazing pairs (view or
        light beyond :data:`GRAZING_THETA_DEG`) and of the rest (empty groups have ``n = 0`` and no means).
    """

    rows: list[dict[str, Any]]
    mean: dict[str, float]
    images: list[Path]
    by_angle: dict[str, dict[str, float]] | None = None

    def summary(self) -> str:
        text = (f"{len(self.rows)} pairs: {PSNR_LABEL.replace('(dB, ', '(')} {self.mean['psnr']:.2f} dB")
        parts = [f"{name} {g['psnr']:.2f} dB over {g['n']}" for name, g in (self.by_angle or {}).items()
                 if g.get("n")]
        if parts:
            text += f" ({'; '.join(parts)}; grazing: view or light > {GRAZING_THETA_DEG:g} deg)"
        return (text + f"; {PSNR_FIXED_LABEL.replace('(dB, ', '(')} {self.mean['psnr_fixed1']:.2f} dB; "
                f"DSSIM {self.mean['dssim']:.4f}, FLIP {self.mean['flip']:.4f}")


def _means(rows: list[dict[str, Any]]) -> dict[str, float]:
    with np.errstate(all="ignore"):
        return {m: float(np.nanmean([r[m] for r in rows])) if rows else float("nan") for m in METRICS}


def angle_groups(rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Counts and means of the grazing pairs and of the others (see :class:`Evaluation`)."""
    out = {}
    for name, want in (("grazing", True), ("others", False)):
        group = [r for r in rows if bool(r["grazing"]) == want]
        out[name] = {"n": len(group), **(_means(group) if group else {})}
    return out


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


def side_by_side(reference: np.ndarray, test: np.ndarray, *, min_height: int = 256, gap: int = 4) -> np.ndarray:
    """Display image ``ground truth | model | FLIP map`` (sRGB values in ``[0, 1]``), upscaled (nearest)
    to at least ``min_height`` rows, white gaps of ``gap`` pixels."""
    panels = [linear_to_srgb(reference), linear_to_srgb(test), flip_magma(reference, test)]
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
    from ..progress import progress_bar
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
        for k0 in progress_bar(range(0, len(pairs), batch), disable=not progress, desc="evaluating",
                                 unit="batch"):
            chunk = pairs[k0:k0 + batch]
            wv = torch.as_tensor(source.views[chunk[:, 0]], dtype=torch.float32, device=device)
            wl = torch.as_tensor(source.lights[chunk[:, 1]], dtype=torch.float32, device=device)
            pred = predict_images(rep, wv, wl, (source.height, source.width)).float().cpu().numpy()
            for j, (v, l) in enumerate(chunk):
                gt = np.asarray(source.image(int(v), int(l)), dtype=np.float32)
                img = pred[j].reshape(gt.shape)
                fmean = flip(gt, img)
                tv, pv = direction_to_spherical(source.views[v])
                tl, pl = direction_to_spherical(source.lights[l])
                rows.append({"view_index": int(v), "light_index": int(l), "theta_view": round(float(tv), 4),
                             "phi_view": round(float(pv), 4), "theta_light": round(float(tl), 4),
                             "phi_light": round(float(pl), 4),
                             "grazing": bool(max(tv, tl) > GRAZING_THETA_DEG + 1e-6), "psnr": psnr(gt, img),
                             "psnr_fixed1": psnr_fixed_range(gt, img), "dssim": dssim(gt, img), "flip": fmean})
                if k0 + j in show:
                    shown.append((int(v), int(l), side_by_side(gt, img)))
    rep.train(was_training)
    evaluation = Evaluation(rows, _means(rows), [], angle_groups(rows))
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
        for name, group in (evaluation.by_angle or {}).items():
            if group.get("n"):
                writer.writerow({fields[0]: f"mean ({name}, {group['n']} pairs)",
                                 **{m: group[m] for m in METRICS}})
    for v, l, img in side_by_sides:
        evaluation.images.append(save_image(out_dir / f"pair_v{v:03d}_l{l:03d}.png", srgb_to_linear(img)))
    payload = {"mean": evaluation.mean, "by_angle": evaluation.by_angle, "n_pairs": len(evaluation.rows),
               "grazing_theta_deg": GRAZING_THETA_DEG, "pairs": evaluation.rows,
               "images": [p.name for p in evaluation.images], "metrics": METRIC_DESCRIPTIONS, **(extra or {})}
    with atomic_path(out_dir / "metrics.json") as tmp:
        tmp.write_text(json.dumps(payload, indent=1, allow_nan=True))
