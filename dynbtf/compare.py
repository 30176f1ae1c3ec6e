"""The paper's comparisons in one call: representations (Figs. 4 and 8) and synthesis methods.

:func:`compare_representations` fits (or loads) each representation kind on one
BTF with the **same** held-out split, evaluates every model on the **same**
held-out (view, light) pairs and writes, into one output directory:

* ``<kind>.dbtfm`` -- the model files (kept: running again reuses them, and an
  unfinished gradient fit -- stopped by ``max_minutes`` -- continues from its
  checkpoint), and ``source_fingerprint.json`` (:func:`dynbtf.provenance.source_fingerprint`:
  models fitted to other content of a BTF of the same name are refused, not reused);
* ``representations.csv`` / ``.json`` -- one row per kind: mean PSNR (linear),
  DSSIM and FLIP (clamped sRGB) over the held-out pairs, storage in bytes (all
  parameters and buffers; and the positional plane alone, the part a non-dynamic
  synthesis must pre-generate at the output size), fit time; the JSON also
  holds every pair's numbers;
* ``eval_<kind>/`` -- each model's ``dynbtf eval`` output on the held-out pairs
  (:func:`dynbtf.training.evaluate.evaluate_model`: per-pair metrics, side-by-side PNGs);
* ``representations.png`` and ``images/`` -- the figure in the layout of the
  paper's Figs. 4 and 8: one row per held-out example, columns
  ``GT | each representation | FLIP error map of each`` (FLIP maps in the
  magma colour map, black = no error);
* ``index.html`` -- the table and the figure on one page.

:func:`compare_synthesis` (the second part, the paper's Fig. 7 and its
storage argument) renders one representation's positional plane synthesized
by each method at ``scale`` x the exemplar and reports the synthesis quality
numbers of :mod:`dynbtf.synthesis.quality` next to each method's storage: the
dynamic methods need only the exemplar (the representation), quilting must
store its pre-generated planes.
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from .data.base import BTFSource
from .errors import InputError
from .io import atomic_path, save_image, to_uint8_srgb
from .metrics import flip, flip_magma
from .provenance import source_fingerprint
from .report.html import HtmlReport
from .representations.base import Representation
from .representations.model_file import load_model, read_model_metadata
from .training.fit import TrainConfig, checkpoint_path, predict_images
from .training.fitters import get_fitter
from .training.evaluate import METRIC_DESCRIPTIONS, evaluate_model
from .training.images import held_out_split

__all__ = ["DEFAULT_KINDS", "RepresentationScore", "fit_or_load", "example_images", "CachedPairs", "source_fingerprint", "compare_representations"]

#: The paper's four representations, in the order of its figures.
DEFAULT_KINDS = ("triple", "neumip", "pca", "sh")

@dataclass
class RepresentationScore:
    """One row of the representation table (means over the held-out pairs)."""

    kind: str
    psnr: float  # per-image peak (dynbtf.metrics.psnr)
    psnr_fixed1: float  # fixed peak 1 (the older form)
    psnr_grazing: float  # per-image peak, pairs with view or light beyond 60 degrees
    psnr_others: float  # per-image peak, the other pairs
    dssim: float
    flip: float
    storage_bytes: int
    positional_bytes: int
    fit_seconds: float
    finished: bool
    model_path: str
    per_pair: list[dict[str, Any]] = field(default_factory=list, repr=False)

    def row(self) -> dict[str, Any]:
        """The table columns (without per-pair numbers)."""
        return {k: v for k, v in asdict(self).items() if k != "per_pair"}


# ---------------------------------------------------------------------- fitting
def _provenance_matches(meta: dict[str, Any], source: BTFSource, held_out: np.ndarray) -> str | None:
    """Why a stored model does not belong to this comparison (``None`` if it does)."""
    prov = meta.get("provenance", {})
    src = prov.get("source", {})
    expected = {"name": source.name, "height": source.height, "width": source.width,
                "n_views": source.n_views, "n_lights": source.n_lights}
    for key, value in expected.items():
        if src.get(key) != value:
            return f"it was fitted to {src.get('name')!r} ({key}={src.get(key)!r}, expected {value!r})"
    if prov.get("held_out_pairs") != np.asarray(held_out).tolist():
        return "its held-out pairs differ from this comparison's (other --held-out or --seed)"
    return None


#: Training options a finished gradient fit must share with the comparison's config to be reused.
REUSED_TRAINING_FIELDS = ("epochs", "images_per_step", "lr_decay", "lr_scale", "texels_per_image", "texel_groups",
                          "precision")


def _training_matches(meta: dict[str, Any], config: TrainConfig) -> str | None:
    """Why a finished gradient fit was trained with other options than ``config`` (``None`` if it was not).

    Closed-form fits (no ``epochs`` in their training record) have no such options; an option
    the record lacks (a file older than the option) is not compared.
    """
    training = meta.get("provenance", {}).get("training", {})
    if "epochs" not in training:
        return None
    differ = [f"{name}={training.get(name)!r} (this comparison: {getattr(config, name)!r})"
              for name in REUSED_TRAINING_FIELDS if name in training and training[name] != getattr(config, name)]
    return ("it was trained with other options: " + ", ".join(differ)) if differ else None


def fit_or_load(kind: str, source: BTFSource, path, config: TrainConfig, *, progress: bool = True
                ) -> tuple[Representation, dict[str, Any]]:
    """The model of ``kind`` at ``path``: loaded if it is a finished fit of this source and split, else fitted.

    An unfinished gradient fit (its checkpoint exists) continues. A model file
    that belongs to another BTF or split, or a finished gradient fit trained
    with other options (:data:`REUSED_TRAINING_FIELDS`: e.g. fewer epochs or
    another learning-rate scale), raises :class:`InputError` (nothing is
    overwritten): a table must not silently mix models of other settings.
    """
    path = Path(path)
    _, held_out = held_out_split(source.n_views, source.n_lights, config.held_out_fraction, config.seed)
    if path.exists():
        meta = read_model_metadata(path)
        problem = (f"it is a {meta.get('kind')!r} model" if meta.get("kind") != kind
                   else _provenance_matches(meta, source, held_out))
        if problem:
            raise InputError(f"{path}: cannot reuse this model file: {problem}; remove it or choose another "
                             "output directory")
        if meta["provenance"].get("finished", True) or not checkpoint_path(path).exists():
            problem = _training_matches(meta, config)
            if problem:
                raise InputError(f"{path}: cannot reuse this model file: {problem}; remove it (and its .ckpt) or "
                                 "choose another output directory")
            rep, meta = load_model(path)
            return rep, meta
    result = get_fitter(kind)(source, path, config, progress=progress)
    return result.representation, result.metadata


def _check_fingerprint(output_dir: Path, source: BTFSource) -> None:
    """Refuse to reuse models in ``output_dir`` fitted to different BTF content; record the fingerprint."""
    path = output_dir / "source_fingerprint.json"
    current = source_fingerprint(source)
    if path.exists():
        stored = json.loads(path.read_text()).get("sha256")
        if stored != current:
            raise InputError(f"{output_dir}: the models there were fitted to different content of {source.name!r} "
                             f"(fingerprint {str(stored)[:12]}, now {current[:12]}): the BTF changed; remove the "
                             "model files or choose another output directory")
        return
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"source": source.name, "sha256": current}))


# ---------------------------------------------------------------------- evaluation
class CachedPairs(BTFSource):
    """A view of ``source`` that decodes the images of ``pairs`` once and keeps them in memory.

    Every representation is evaluated on the same held-out pairs: without the
    cache a procedural or compressed source would decode each ground-truth image
    once per representation. Other pairs pass through to ``source``. Memory:
    ``len(pairs) x H x W x 3`` float32.
    """

    def __init__(self, source: BTFSource, pairs: np.ndarray) -> None:
        super().__init__()
        self.source = source
        self.height, self.width = source.height, source.width
        self.views, self.lights = source.views, source.lights
        self.name, self.metadata = source.name, source.metadata
        self._images = {(int(v), int(l)): source.image(int(v), int(l)) for v, l in np.asarray(pairs)}

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        image = self._images.get((view_index, light_index))
        return self.source.image(view_index, light_index) if image is None else image

    def describe(self) -> dict[str, Any]:
        return self.source.describe()


def example_images(rep: Representation, source: BTFSource, pairs: np.ndarray
                   ) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Model image ``(H, W, 3)``, FLIP display map ``(H, W, 3)`` (:func:`dynbtf.metrics.flip_magma`) and mean FLIP
    at each (view, light) pair (for figures)."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs) == 0:
        return []
    device = rep.positional_plane().device
    with torch.no_grad():
        wv = torch.as_tensor(source.views[pairs[:, 0]], dtype=torch.float32, device=device)
        wl = torch.as_tensor(source.lights[pairs[:, 1]], dtype=torch.float32, device=device)
        pred = predict_images(rep, wv, wl, (source.height, source.width)).float().cpu().numpy()
    out = []
    for j, (v, l) in enumerate(pairs):
        image = pred[j].reshape(source.height, source.width, 3)
        truth = source.image(int(v), int(l))
        out.append((image, flip_magma(truth, image), flip(truth, image)))
    return out


def _example_positions(n_pairs: int, examples: int) -> list[int]:
    """``examples`` positions spread evenly over the held-out list (deterministic)."""
    if n_pairs == 0 or examples <= 0:
        return []
    return sorted(set(np.linspace(0, n_pairs - 1, min(examples, n_pairs)).round().astype(int).tolist()))


def _upscale(image: np.ndarray, factor: int) -> np.ndarray:
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)


def _labelled_grid(cells: list[list[np.ndarray]], column_labels: list[str], row_labels: list[str],
                   scale: int) -> np.ndarray:
    """Compose display sRGB cells ``[row][col] (h, w, 3)`` with text labels into one uint8 image."""
    from PIL import Image, ImageDraw

    h, w = cells[0][0].shape[:2]
    h, w, pad, top, left = h * scale, w * scale, 4, 18, 110
    canvas = Image.new("RGB", (left + len(column_labels) * (w + pad), top + len(cells) * (h + pad)), "white")
    draw = ImageDraw.Draw(canvas)
    for c, label in enumerate(column_labels):
        draw.text((left + c * (w + pad) + 2, 3), label, fill="black")
    for r, row in enumerate(cells):
        draw.text((3, top + r * (h + pad) + h // 2 - 5), row_labels[r], fill="black")
        for c, cell in enumerate(row):
            tile = np.round(_upscale(np.clip(cell, 0, 1), scale) * 255).astype(np.uint8)
            canvas.paste(Image.fromarray(tile), (left + c * (w + pad), top + r * (h + pad)))
    return np.asarray(canvas)


def _write_png(path: Path, srgb_uint8: np.ndarray) -> None:
    import imageio.v3 as iio

    with atomic_path(path) as tmp:
        iio.imwrite(tmp, srgb_uint8, extension=".png")


def _write_table(output_dir: Path, stem: str, rows: list[dict[str, Any]], extra: dict[str, Any]) -> None:
    """``<stem>.csv`` (the rows) and ``<stem>.json`` (rows + ``extra``), atomically."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    with atomic_path(output_dir / f"{stem}.csv") as tmp:
        tmp.write_text(buffer.getvalue())
    with atomic_path(output_dir / f"{stem}.json") as tmp:
        tmp.write_text(json.dumps({"rows": rows, **extra}, indent=1, default=float))


def compare_representations(source: BTFSource, output_dir, kinds: Sequence[str] = DEFAULT_KINDS,
                            config: TrainConfig | None = None, *, examples: int = 3, progress: bool = True,
                            report: HtmlReport | None = None, cache_mb: float = 1024.0) -> list[RepresentationScore]:
    """Fit or load each kind, evaluate all on the same held-out pairs, write table and figure.

    Parameters
    ----------
    source : BTFSource
        The measured (or simulated) BTF.
    output_dir : str or Path
        Where models, tables, images and ``index.html`` go (created).
    kinds : sequence of str
        Registered fitter kinds (``triple``, ``neumip``, ``pca``, ``sh``).
    config : TrainConfig
        Shared by all fits: the held-out split (``held_out_fraction``, ``seed``)
        and, for gradient-trained kinds, the training options (``max_minutes``
        is the budget of each gradient fit in this run).
    examples : int
        Held-out pairs shown in the figure (rows).
    progress : bool
        Progress bars and summary lines.
    report : HtmlReport, optional
        Append to this report instead of writing ``index.html`` (used by the CLI
        to put both comparisons on one page).
    cache_mb : float
        The held-out ground-truth images are decoded once and kept in memory
        when they fit in this many MB (:class:`CachedPairs`).

    Returns
    -------
    list of RepresentationScore, in the order of ``kinds``.
    """
    config = (config or TrainConfig()).validate()
    kinds = _checked_kinds(kinds)
    output_dir = Path(output_dir)
    (output_dir / "images").mkdir(parents=True, exist_ok=True)
    _, held_out = held_out_split(source.n_views, source.n_lights, config.held_out_fraction, config.seed)
    if len(held_out) == 0:
        raise InputError("held-out fraction is 0: there are no held-out pairs to compare on")
    shown = _example_positions(len(held_out), examples)
    ground_truth = source
    if len(held_out) * source.height * source.width * 12 <= cache_mb * 1024 ** 2:
        ground_truth = CachedPairs(source, held_out)
    truths = {p: ground_truth.image(*map(int, held_out[p])) for p in shown}
    _check_fingerprint(output_dir, source)

    scores, kept = [], {}
    for kind in kinds:
        score, kept[kind] = _score_kind(kind, source, ground_truth, held_out, held_out[shown], output_dir, config,
                                        examples=examples, progress=progress)
        scores.append(score)
        if progress:
            _print_score(score)

    table = _write_representation_table(output_dir, source, held_out, scores)
    labels, figure_items = _write_representation_figure(output_dir, source, held_out, shown, truths, scores, kept)
    own_report = report is None
    report = report or HtmlReport(f"dynbtf compare: {source.name}",
                                  f"{source.height} x {source.width} texels, {source.n_views} views x "
                                  f"{source.n_lights} lights; {len(held_out)} held-out pairs")
    _report_representations(report, output_dir, table, labels, figure_items)
    if own_report:
        report.write(output_dir / "index.html")
    return scores


def _checked_kinds(kinds: Sequence[str]) -> list[str]:
    """``kinds`` without repeats, in order; an empty list or an unknown kind raises :class:`InputError` (before
    any fit)."""
    kinds = list(dict.fromkeys(kinds))
    if not kinds:
        raise InputError("--repr: expected at least one representation kind")
    for kind in kinds:
        get_fitter(kind)  # fail early on an unknown kind
    return kinds


def _score_kind(kind: str, source: BTFSource, ground_truth: BTFSource, held_out: np.ndarray, shown_pairs: np.ndarray,
                output_dir: Path, config: TrainConfig, *, examples: int, progress: bool
                ) -> tuple[RepresentationScore, list[tuple[np.ndarray, np.ndarray, float]]]:
    """Fit or load ``kind`` (``<kind>.dbtfm``), evaluate it on the ``held_out (P, 2)`` pairs (``eval_<kind>/``).

    Returns its score (fit time: the model's recorded training seconds, else this call's wall time) and
    :func:`example_images` at ``shown_pairs (E, 2)`` for the figure.
    """
    start = time.perf_counter()
    rep, meta = fit_or_load(kind, source, output_dir / f"{kind}.dbtfm", config, progress=progress)
    wall = time.perf_counter() - start
    prov = meta.get("provenance", {})
    evaluation = evaluate_model(rep, ground_truth, held_out, out_dir=output_dir / f"eval_{kind}", images=examples,
                                progress=progress)
    examples_kept = example_images(rep, ground_truth, shown_pairs)
    plane = rep.positional_plane()
    score = RepresentationScore(
        kind=kind, psnr=evaluation.mean["psnr"], psnr_fixed1=evaluation.mean["psnr_fixed1"],
        psnr_grazing=evaluation.by_angle["grazing"].get("psnr", float("nan")),
        psnr_others=evaluation.by_angle["others"].get("psnr", float("nan")),
        dssim=evaluation.mean["dssim"], flip=evaluation.mean["flip"],
        storage_bytes=int(rep.storage_bytes()), positional_bytes=int(plane.numel() * plane.element_size()),
        fit_seconds=float(prov.get("training_seconds", wall)), finished=bool(prov.get("finished", True)),
        model_path=str(output_dir / f"{kind}.dbtfm"), per_pair=evaluation.rows)
    return score, examples_kept


def _print_score(score: RepresentationScore) -> None:
    """One summary line: PSNR (dB), DSSIM, FLIP, storage (MB) and fit time (s) of a kind."""
    print(f"{score.kind}: PSNR (per-image peak) {score.psnr:.2f} dB (grazing {score.psnr_grazing:.2f}, others "
          f"{score.psnr_others:.2f}), PSNR (fixed peak 1) {score.psnr_fixed1:.2f} dB, "
          f"DSSIM {score.dssim:.4f}, FLIP {score.flip:.4f}, "
          f"{score.storage_bytes / 1e6:.3g} MB, fit {score.fit_seconds:.0f} s")


def _write_representation_table(output_dir: Path, source: BTFSource, held_out: np.ndarray,
                                scores: list[RepresentationScore]) -> list[dict[str, Any]]:
    """``representations.csv`` / ``.json`` (with the source, the held-out pairs, every pair's numbers and what
    the metrics mean); returns the table rows."""
    table = [s.row() for s in scores]
    _write_table(output_dir, "representations", table, {
        "source": source.describe(), "held_out_pairs": held_out.tolist(),
        "per_pair": {s.kind: s.per_pair for s in scores},
        "metrics": METRIC_DESCRIPTIONS | {
            "psnr_grazing": "psnr over the pairs with view or light beyond 60 degrees",
            "psnr_others": "psnr over the other pairs"}})
    return table


def _write_representation_figure(output_dir: Path, source: BTFSource, held_out: np.ndarray, shown: list[int],
                                 truths: dict[int, np.ndarray], scores: list[RepresentationScore],
                                 kept: dict[str, list[tuple[np.ndarray, np.ndarray, float]]]
                                 ) -> tuple[list[str], list[list[tuple[Path, str]]]]:
    """The figure ``representations.png`` (GT | each kind | FLIP map of each, one row per example) and its
    images in ``images/``.

    ``shown``: positions in ``held_out (P, 2)`` of the examples; ``truths``: their ground truth ``(H, W, 3)``
    by position; ``kept``: :func:`example_images` per kind. Returns the column labels and, per example, the
    ``(path, caption)`` of its images (for the report).
    """
    cells, row_labels, figure_items = [], [], []
    for row_index, p in enumerate(shown):
        v, l = map(int, held_out[p])
        gt_path = output_dir / "images" / f"v{v:03d}_l{l:03d}_gt.png"
        save_image(gt_path, truths[p])
        row = [to_uint8_srgb(truths[p]) / 255.0]
        items = [(gt_path, f"GT (view {v}, light {l})")]
        maps = []
        for s in scores:
            image, flip_display, pair_flip = kept[s.kind][row_index]
            img_path = output_dir / "images" / f"v{v:03d}_l{l:03d}_{s.kind}.png"
            map_path = output_dir / "images" / f"v{v:03d}_l{l:03d}_{s.kind}_flip.png"
            save_image(img_path, image)
            _write_png(map_path, np.round(flip_display * 255).astype(np.uint8))
            row.append(to_uint8_srgb(image) / 255.0)
            maps.append(flip_display)
            items.append((img_path, f"{s.kind}"))
            items.append((map_path, f"{s.kind} FLIP {pair_flip:.3f}"))
        cells.append(row + maps)
        row_labels.append(f"v{v} l{l}")
        figure_items.append(items)
    labels = ["GT", *[s.kind for s in scores], *[f"FLIP {s.kind}" for s in scores]]
    scale = max(1, 128 // max(source.height, source.width))
    _write_png(output_dir / "representations.png", _labelled_grid(cells, labels, row_labels, scale))
    return labels, figure_items


def _report_representations(report: HtmlReport, output_dir: Path, table: list[dict[str, Any]], labels: list[str],
                            figure_items: list[list[tuple[Path, str]]]) -> None:
    """The "Representations" section of ``report``: what the numbers mean, the table, the figure and each
    example's images."""
    report.section("Representations", "Means over the same held-out (view, light) pairs, never used in any fit. "
                   "PSNR on linear values against each reference image's peak (psnr; split into grazing pairs, "
                   "view or light beyond 60 degrees, and the others) and against a fixed peak of 1 (psnr_fixed1, the "
                   "older form); DSSIM and FLIP on clamped sRGB. Storage: all parameters and buffers; "
                   "positional: the positional plane alone.")
    report.table(table, columns=["kind", "psnr", "psnr_grazing", "psnr_others", "psnr_fixed1", "dssim", "flip",
                                 "storage_bytes", "positional_bytes",
                                 "fit_seconds", "finished"], caption="Held-out error, storage and fit time")
    report.images([(output_dir / "representations.png", "GT | representations | FLIP error maps (magma)")],
                  width=min(1400, 160 * len(labels)))
    for items in figure_items:
        report.images(items, width=128, pixelated=True)


# ---------------------------------------------------------------------- synthesis
#: The synthesis methods of the paper's Fig. 7.
DEFAULT_SYNTHESIS_METHODS = ("tile", "hist", "hex", "quilt")


def compare_synthesis(model, output_dir, methods: Sequence[str] = DEFAULT_SYNTHESIS_METHODS, *,
                      scale: float = 15.0, seed: int = 0, view=(0.0, 0.0), light=(45.0, 0.0),
                      resolution: int | None = None, progress: bool = True,
                      report: HtmlReport | None = None) -> list[dict[str, Any]]:
    """Synthesize one representation's positional plane with each method and compare quality and storage.

    Parameters
    ----------
    model : Representation or path
        A fitted representation or its model file.
    output_dir : str or Path
        Receives ``synthesis.csv`` / ``.json``, ``images/synthesis_<method>.png``
        and (unless ``report`` is given) ``synthesis.html``.
    methods : sequence of str
        Synthesis methods (:func:`dynbtf.synthesis.registry.make_synthesizer` names).
    scale : float, default 15
        Exemplar repeats per side of the synthesized area (the paper's 15x);
        quilting pre-generates a plane of this size.
    seed : int
        Synthesis seed.
    view, light : (theta, phi) in degrees
        Directions of the rendered images.
    resolution : int, optional
        Pixels per side of the images (default: ``scale`` x the exemplar's
        width, capped at 1024).
    progress : bool
        Print one line per method.
    report : HtmlReport, optional
        Append to this report instead of writing ``synthesis.html``.

    Returns
    -------
    list of dict
        Per method: ``dynamic``, the quality numbers of
        :func:`dynbtf.synthesis.quality.quality_report` (feature W1/std mean,
        smallest std ratio, RGB W1/std max, repetition score, verbatim fraction),
        ``representation_bytes`` (the exemplar: what a dynamic method needs),
        ``synthesis_storage_bytes`` (what the method stores beyond it -- for
        quilting the pre-generated plane), their sum ``total_bytes``, and the
        set-up time.
    """
    from .synthesis.quality import quality_report
    from .synthesized import synthesized_btf

    if isinstance(model, (str, Path)):
        model, _ = load_model(model)
    methods = list(dict.fromkeys(methods))
    if not methods:
        raise InputError("methods: expected at least one synthesis method, e.g. tile,hist,hex,quilt")
    if not (isinstance(scale, (int, float)) and scale >= 2):
        raise InputError(f"scale: expected at least 2 exemplar repeats per side, got {scale!r}")
    output_dir = Path(output_dir)
    (output_dir / "images").mkdir(parents=True, exist_ok=True)
    plane = model.positional_plane()
    height, width = int(plane.shape[0]), int(plane.shape[1])
    side = int(resolution or min(1024, round(scale * width)))
    representation_bytes = int(model.storage_bytes())
    rows, items = [], []
    for method in methods:
        params = {"repeats": float(scale)} if method == "quilt" else {}
        start = time.perf_counter()
        btf = synthesized_btf(model, method, scale=float(scale), seed=seed, **params)
        setup = time.perf_counter() - start
        quality = quality_report(btf, repeats=int(math.ceil(scale)), max_side=max(1024, side), seed=seed)
        image_path = output_dir / "images" / f"synthesis_{method}.png"
        save_image(image_path, btf.image(view=view, light=light, resolution=side))
        extra = int(btf.synthesizer.storage_bytes())
        row = {"method": method, "dynamic": bool(btf.synthesizer.dynamic),
               "feature_w1_over_std": quality["feature_w1_over_std_mean"],
               "feature_std_ratio_min": float(min(quality["feature_std_ratio"])),
               "rgb_w1_over_std_max": quality["rgb_w1_over_std_max"],
               "repetition": quality["repetition"]["score"], "verbatim_fraction": quality["verbatim_fraction"],
               "representation_bytes": representation_bytes, "synthesis_storage_bytes": extra,
               "total_bytes": representation_bytes + extra, "setup_seconds": setup}
        rows.append(row)
        items.append((image_path, f"{method}: W1/std {row['feature_w1_over_std']:.3f}, repetition "
                                  f"{row['repetition']:.2f}, +{extra / 1e6:.3g} MB"))
        if progress:
            print(f"synthesis {method}: feature W1/std {row['feature_w1_over_std']:.4f}, repetition "
                  f"{row['repetition']:.3f}, verbatim {row['verbatim_fraction']:.3f}, storage "
                  f"{representation_bytes / 1e6:.3g} MB + {extra / 1e6:.3g} MB")
    _write_table(output_dir, "synthesis", rows, {
        "representation": model.kind, "exemplar_texels": [height, width], "scale": scale, "seed": seed,
        "view_deg": list(view), "light_deg": list(light)})
    own_report = report is None
    report = report or HtmlReport(f"dynbtf synthesis comparison ({model.kind})")
    report.section(f"Synthesis methods on the {model.kind} positional plane, {scale:g}x",
                   "Quality without ground truth (dynbtf.synthesis.quality): feature W1/std (0 = the exemplar's "
                   "histogram), smallest std ratio, RGB W1/std, repetition (autocorrelation at the exemplar "
                   "period: ~1 for tiling), verbatim copies. Storage: the representation (all a dynamic method "
                   "needs) plus what the method stores; quilting must pre-generate and store its plane.")
    report.table(rows, caption=f"Synthesis at {scale:g}x, seed {seed}")
    report.images(items, width=320)
    if own_report:
        report.write(output_dir / "synthesis.html")
    return rows
