"""Exemplar guidance: synthesis (hist, hex, struct) that draws each point from exemplar content of a target label.

The user gives a **label map over the exemplar** (``(H, W)`` integers, or derived by
:func:`exemplar_labels`: k-means on a feature or appearance plane into ``classes`` classes) and a
**target label field over the surface** (:class:`LabelField`: a label image laid over the plane, in
exemplar repeats). Histogram-preserving blending (:class:`~dynbtf.synthesis.histogram_blending.HistogramBlending`)
(and hex-tiling, :class:`~dynbtf.synthesis.hex_tiling.HexTiling`) reads three samples per query, each at the
query's texel position plus a whole-texel offset hashed from a lattice vertex. Guided (:class:`GuidedBlending`,
registry name ``guided``; :class:`GuidedHexTiling`, ``guided-hex``), each sample tries ``candidates`` offsets
for its vertex in turn:

* candidate 0 is hist's own offset, candidate ``j`` hashes the vertex with the seed's ``j``-th stream
  (:func:`candidate_seed`);
* the sample takes the first candidate whose bilinear footprint under the query (its four texels) carries
  the target label at the query, so that what it reads is content of that label alone;
* if no candidate does, it keeps candidate 0 and counts as unmatched.

Samples that match keep their blend weight. Unmatched samples have their barycentric weight multiplied by
``softness`` (0: dropped, unless none of the three match; 1: kept as they are). Queries that share a
vertex and a target label take the same candidate, so content stays coherent within a label's region;
where the target changes, the samples change offset. Every choice is a function of the query's position
and the integer hash, so the field is defined, and exact, at any ``uv``, as hist's is.

Cell quilting (``struct``) is guided per cell instead (:class:`GuidedCellQuilting`, ``guided-struct``): a whole
cell takes the first lattice offset, from its hashed one on, under which its content is of the target's label.

On the CPU the fused numba kernel of lattice blending runs the search (:func:`dynbtf.synthesis.blending.kernel.lattice_blend`
with ``guidance``); :meth:`GuidedBlending.reference_latent` is the torch path (any device), against which the tests
hold it; footprint queries read the pyramid at the guided samples, with their steered weights (the same
:meth:`sample_positions` in every path). The guided methods also run in the Mitsuba plugin (its ``target``
parameter: the plugin calls this query). The web export runs all three in the shader (the package's ``web``,
``web_hex`` and ``web_struct`` modules: the read plane's labels, or the cells' majority labels per offset, and the
target image as an integer table, the target laid over the plane as a label field of the repeat origin, the
candidates' hash states and the softness as uniforms).
"""

from __future__ import annotations

import numpy as np
import torch

from ...errors import InputError
from ..base import check_uv, register_synthesizer, wrapped_texel_position
from ..cell_quilting import CellQuilting
from ..hash import MASK32, mix32, vertex_offsets
from ..hex_tiling import HexTiling
from ..histogram_blending import HistogramBlending
from ..lattice import split_uv, triangle_lattice

__all__ = ["GuidedBlending", "GuidedHexTiling", "GuidedCellQuilting", "LabelField", "exemplar_labels",
           "candidate_seed", "source_labels"]

#: Golden-ratio constant that separates the candidates' seed streams.
_CANDIDATE_STREAM = 0x9E3779B9


def candidate_seed(seed: int, j: int) -> int:
    """The seed of candidate ``j`` of a guided sample: ``seed`` itself for ``j = 0`` (hist's offset), else the
    lowbias32 mix of ``seed`` xor ``j`` times a golden-ratio constant (32 bits)."""
    if j == 0:
        return int(seed) & MASK32
    return int(mix32((int(seed) ^ ((j * _CANDIDATE_STREAM) & MASK32)) & MASK32))


def exemplar_labels(features, classes: int, seed: int = 0, order_by=None) -> np.ndarray:
    """Labels ``(H, W)`` int64 in ``[0, classes)`` of a plane ``features (H, W, C)``: k-means clustering of its texels
    (:func:`scipy.cluster.vq.kmeans2`, k-means++ initialisation seeded by ``seed``; Euclidean distance in the
    plane's own units, so a channel weighs by its spread).

    ``order_by`` (optional ``(H, W)``, e.g. the decoded luminance) numbers the classes by their mean of it,
    increasing (class 0 the darkest); without it, by their mean of the first channel.

    Examples
    --------
    >>> import numpy as np
    >>> plane = np.concatenate([np.zeros((4, 2, 1)), np.ones((4, 2, 1))], axis=1)
    >>> exemplar_labels(plane, 2).tolist()[0]
    [0, 0, 1, 1]
    """
    from scipy.cluster.vq import kmeans2

    x = features.detach().cpu().numpy() if isinstance(features, torch.Tensor) else features
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 2:
        x = x[..., None]
    if x.ndim != 3 or x.shape[0] * x.shape[1] == 0:
        raise InputError(f"features: expected a plane (H, W, C), got shape {x.shape}")
    if not np.isfinite(x).all():
        raise InputError("features: contains NaN or infinite values")
    classes = int(classes)
    h, w, c = x.shape
    if not 2 <= classes <= min(h * w, 255):
        raise InputError(f"classes: expected 2 to {min(h * w, 255)} classes for a {h} x {w} plane, got {classes}")
    rows = x.reshape(-1, c)
    rows = rows - rows.mean(0)
    _, labels = kmeans2(rows, classes, minit="++", seed=np.random.default_rng(int(seed)))
    key = (rows[:, 0] if order_by is None else np.asarray(
        order_by.detach().cpu().numpy() if isinstance(order_by, torch.Tensor) else order_by, dtype=np.float64
    ).reshape(-1))
    if key.shape[0] != h * w:
        raise InputError(f"order_by: expected ({h}, {w}) values, got {np.shape(order_by)}")
    means = np.array([key[labels == k].mean() if np.any(labels == k) else np.inf for k in range(classes)])
    rank = np.empty(classes, dtype=np.int64)
    rank[np.argsort(means, kind="stable")] = np.arange(classes)
    return rank[labels].reshape(h, w)


class LabelField:
    """A label image ``(H, W)`` of non-negative integers laid over the plane: ``size`` x ``size`` exemplar repeats
    (row 0 at ``v = 0``, column 0 at ``u = 0``), each point taking its nearest texel's label; ``wrap``:
    ``"repeat"`` (the image tiles the plane, addressed by an exact remainder: the same labels at any distance)
    or ``"clamp"`` (its edge texels extend it)."""

    def __init__(self, labels, size: float = 1.0, wrap: str = "repeat") -> None:
        from ...errors import positive_number

        try:
            labels = np.array(labels)
        except (TypeError, ValueError) as e:
            raise InputError(f"target: expected a label image (H, W) of integers ({e})") from None
        if labels.ndim != 2 or labels.size == 0:
            raise InputError(f"target: expected a label image of shape (H, W), got shape {labels.shape}")
        if not (np.issubdtype(labels.dtype, np.integer) or (np.issubdtype(labels.dtype, np.floating)
                                                             and np.isfinite(labels).all()
                                                             and np.all(labels == np.round(labels)))):
            raise InputError(f"target: expected integer labels, got dtype {labels.dtype}")
        if labels.min() < 0:
            raise InputError(f"target: expected labels >= 0, got {labels.min()}")
        if wrap not in ("repeat", "clamp"):
            raise InputError(f"target wrap: expected 'repeat' or 'clamp', got {wrap!r}")
        self.image = torch.from_numpy(labels.astype(np.int64))
        self.size, self.wrap = positive_number("target size", size, "exemplar repeats"), wrap

    def labels(self, points: torch.Tensor) -> torch.Tensor:
        """The target label ``(N,)`` int64 at ``points (N, 2)`` float64 exemplar repeats."""
        h, w = self.image.shape
        p = points.to(torch.float64).cpu()
        if self.wrap == "repeat":  # written out as the fused kernels compute it
            p = p - torch.floor(p / self.size) * self.size
        col = torch.floor(p[:, 0] / self.size * w).to(torch.int64)
        row = torch.floor(p[:, 1] / self.size * h).to(torch.int64)
        if self.wrap == "repeat":
            col, row = torch.remainder(col, w), torch.remainder(row, h)
        else:
            col, row = col.clamp(0, w - 1), row.clamp(0, h - 1)
        return self.image[row, col].to(points.device)


def _checked_labels(labels, target, shape: tuple[int, int]) -> torch.Tensor:
    """An exemplar label map ``shape`` of non-negative integers as int64, and ``target`` a :class:`LabelField`
    (an :class:`InputError` naming what is wrong otherwise)."""
    labels = torch.as_tensor(np.asarray(labels.cpu() if isinstance(labels, torch.Tensor) else labels))
    if tuple(labels.shape) != shape:
        raise InputError(f"labels: expected the exemplar's shape {shape}, got {tuple(labels.shape)}")
    if labels.is_floating_point() or labels.dtype == torch.bool or (labels.numel() and labels.min() < 0):
        raise InputError("labels: expected non-negative integer labels")
    if not isinstance(target, LabelField):
        raise InputError(f"target: expected a LabelField, got {type(target).__name__}")
    return labels.to(torch.int64)


class _Guidance:
    """What guidance adds to a lattice-blending method (hist, hex): the offset search, the steered weights, the
    fused kernel's guidance arguments. Mixed in before the method's class. Its GLSL form is the package's ``web``
    module (hist) and ``web_hex`` (hex)."""

    def __init__(self, exemplar, seed: int = 0, *, labels, target: LabelField, candidates: int = 16,
                 softness: float = 0.0, **params) -> None:
        super().__init__(exemplar, seed, **params)  # the method's own (hist, hex)
        if self.rotation or self.scale_jitter:
            name = "rotation" if self.rotation else "scale_jitter"
            raise InputError(f"{name}: the guided methods read their candidates' content unturned and unscaled; "
                             f"leave it off for {self.base_method!r} with guidance")
        labels = _checked_labels(labels, target, tuple(self.exemplar.shape[:2]))
        if int(candidates) < 1:
            raise InputError(f"candidates: expected at least 1 offset per sample, got {candidates}")
        softness = float(softness)
        if not 0.0 <= softness <= 1.0:
            raise InputError(f"softness: expected a weight factor in [0, 1], got {softness}")
        ph, pw = self.prepared.plane.shape[:2]
        self.labels = labels[:ph, :pw].contiguous()  # the read plane (tileable crops)
        self.target, self.candidates, self.softness = target, int(candidates), softness

    def guided_positions(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Read positions ``(N, 3, 2)`` in ``[0, 1)``, barycentrics ``(N, 3)`` and whether each sample's content
        carries the target label ``(N, 3)`` bool, for ``uv (N, 2)`` float64 exemplar repeats."""
        plane = self.prepared.plane
        ph, pw = plane.shape[:2]
        whole, frac = split_uv(uv)
        vertices, bary = triangle_lattice(uv)
        dw, dh = self.density
        x = wrapped_texel_position(whole[:, 0], frac[:, 0], dw, pw)[:, None]
        y = wrapped_texel_position(whole[:, 1], frac[:, 1], dh, ph)[:, None]
        target = self.target.labels(uv).to(uv.device)[:, None]
        labels = self.labels.to(uv.device)
        chosen_x = chosen_y = None
        matched = torch.zeros(bary.shape, dtype=torch.bool, device=uv.device)
        for j in range(self.candidates):
            ox, oy = vertex_offsets(vertices[..., 0], vertices[..., 1], candidate_seed(self.seed, j), pw, ph)
            cx, cy = torch.remainder(x + ox, pw), torch.remainder(y + oy, ph)
            if chosen_x is None:
                chosen_x, chosen_y = cx, cy
            # the sample's bilinear footprint: texels floor(c - 1/2) and the next one, wrapped, along each axis
            c0 = torch.remainder(torch.floor(cx - 0.5).long(), pw)
            r0 = torch.remainder(torch.floor(cy - 0.5).long(), ph)
            c1, r1 = torch.remainder(c0 + 1, pw), torch.remainder(r0 + 1, ph)
            inside = ((labels[r0, c0] == target) & (labels[r0, c1] == target) & (labels[r1, c0] == target)
                      & (labels[r1, c1] == target))
            hit = inside & ~matched
            chosen_x, chosen_y = torch.where(hit, cx, chosen_x), torch.where(hit, cy, chosen_y)
            matched |= hit
            if bool(matched.all()):
                break
        return torch.stack([chosen_x / pw, chosen_y / ph], dim=-1), bary, matched

    def steered_barycentrics(self, bary: torch.Tensor, matched: torch.Tensor) -> torch.Tensor:
        """Barycentrics with unmatched samples' weight times ``softness`` (unchanged where none matches)."""
        steered = torch.where(matched, bary, bary * self.softness)
        return torch.where(matched.any(-1, keepdim=True), steered, bary)

    def sample_positions(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The guided samples' read positions ``(N, 3, 2)`` and their steered barycentrics ``(N, 3)``: what the
        method's own reference paths (:meth:`reference_latent`, footprint queries) read and blend."""
        uv_samples, bary, matched = self.guided_positions(uv)
        return uv_samples, self.steered_barycentrics(bary, matched)

    def kernel_guidance(self, uv: torch.Tensor) -> tuple:
        """The fused kernels' guidance arguments for queries ``uv (N, 2)``: the candidates' hash states, the read
        plane's labels, the target label per query and the softness."""
        from ..hash import seed_state

        if "states" not in self._numpy_cache:
            self._numpy_cache["states"] = np.array([int(seed_state(candidate_seed(self.seed, j)))
                                                    for j in range(self.candidates)], dtype=np.int64)
            self._numpy_cache["labels"] = np.ascontiguousarray(self.labels.cpu().numpy(), dtype=np.int32)
        target = self.target.labels(uv.cpu()).numpy().astype(np.int32)
        return self._numpy_cache["states"], self._numpy_cache["labels"], target, self.softness

    def parameters(self):
        return super().parameters() | {"base": self.base_method, "candidates": self.candidates,
                                       "softness": self.softness,
                                       "label_classes": int(self.labels.max()) + 1 if self.labels.numel() else 0}




@register_synthesizer("guided")
class GuidedBlending(_Guidance, HistogramBlending):
    """Histogram-preserving blending steered by labels (see the module docstring).

    Parameters
    ----------
    exemplar : ``(H, W, C)``
    seed : int
    labels : ``(H, W)`` integers
        The exemplar's label per texel (:func:`exemplar_labels` derives one).
    target : LabelField
        The label each point of the plane should show (in exemplar repeats).
    candidates : int, default 16
        Offsets tried per sample (the first is hist's).
    softness : float in [0, 1], default 0
        Barycentric-weight factor of samples whose content does not carry the target label.
    **params
        :class:`~dynbtf.synthesis.histogram_blending.HistogramBlending`'s parameters (``gamma``, ...).

    Examples
    --------
    >>> import torch
    >>> plane = torch.cat([torch.zeros(8, 4, 2), torch.ones(8, 4, 2)], 1) + 0.1 * torch.randn(8, 8, 2)
    >>> labels = (torch.arange(8) >= 4).long().expand(8, 8)
    >>> synth = GuidedBlending(plane, labels=labels, target=LabelField([[1]]), tileable=False)
    >>> uv = torch.rand(500, 2, dtype=torch.float64) * 10
    >>> bool((source_labels(synth, uv) == 1).float().mean() > 0.95)
    True
    """

    backends = {"web": f"{__name__}.web"}

    base_method = "hist"


@register_synthesizer("guided-hex")
class GuidedHexTiling(_Guidance, HexTiling):
    """Hex-tiling steered by labels: :class:`GuidedBlending`'s search with
    :class:`~dynbtf.synthesis.hex_tiling.HexTiling`'s blend (its parameters in ``**params``, e.g. ``luminance``)."""

    backends = {"web": f"{__name__}.web_hex"}

    base_method = "hex"


@register_synthesizer("guided-struct")
class GuidedCellQuilting(CellQuilting):
    """Cell quilting whose cells choose their lattice offset by label.

    :class:`~dynbtf.synthesis.cell_quilting.CellQuilting` gives every cell one of ``K`` lattice offsets, by the
    cell's hash. Guided, a cell takes, from the hashed offset on (``k, k + 1, ...`` mod ``K``), the first offset
    whose content in the cell (the majority label of the cell's texels under that offset, :attr:`cell_labels`)
    is the target's label at the cell's centre; if none is, the hashed one. Whole cells change, so the
    elements stay whole and the cuts between cells are struct's own.

    Parameters: ``labels`` ``(H, W)`` and ``target`` (:class:`LabelField`) as :class:`GuidedBlending`'s, and
    :class:`~dynbtf.synthesis.cell_quilting.CellQuilting`'s in ``**struct``.
    """

    backends = {"web": f"{__name__}.web_struct"}

    base_method = "struct"

    def __init__(self, exemplar, seed: int = 0, *, labels, target: LabelField, **struct) -> None:
        super().__init__(exemplar, seed, **struct)
        self.labels = _checked_labels(labels, target, tuple(self.exemplar.shape[:2]))
        self.target = target
        self.cell_labels = torch.from_numpy(_cell_majorities(self.labels.numpy(), self.prepared))

    def cell_target(self, cell_x: torch.Tensor, cell_y: torch.Tensor) -> torch.Tensor:
        """The target's label ``(N,)`` int64 at the centres of int64 cells (the fused kernel's arithmetic)."""
        nx, ny = self.prepared.cells
        centres = torch.stack([(cell_x.to(torch.float64) + 0.5) / nx, (cell_y.to(torch.float64) + 0.5) / ny], -1)
        return self.target.labels(centres)

    def cell_choices(self, cell_x: torch.Tensor, cell_y: torch.Tensor) -> torch.Tensor:
        own = super().cell_choices(cell_x, cell_y)
        nx, ny = self.prepared.cells
        count = self.prepared.count
        candidates = torch.remainder(own[:, None] + torch.arange(count, device=own.device), count)  # (N, K)
        i = torch.remainder(cell_x, nx)[:, None]
        j = torch.remainder(cell_y, ny)[:, None]
        hit = self.cell_labels.to(own.device)[i, j, candidates] == self.cell_target(cell_x, cell_y)[:, None]
        first = candidates.gather(1, torch.argmax(hit.to(torch.int8), 1, keepdim=True))[:, 0]
        return torch.where(hit.any(1), first, own)

    def kernel_guidance(self) -> tuple:
        return (self.cell_labels.numpy().astype(np.int32), self.target.image.numpy().astype(np.int32),
                float(self.target.size), self.target.wrap == "repeat")

    def parameters(self):
        return super().parameters() | {"base": self.base_method,
                                       "label_classes": int(self.labels.max()) + 1 if self.labels.numel() else 0}


def _cell_majorities(labels: np.ndarray, tables) -> np.ndarray:
    """``(nx, ny, K)`` int64: the majority label of each cell's texels under each lattice offset (ties: the
    smallest label)."""
    h, w = labels.shape
    nx, ny = tables.cells
    tx, ty = w // nx, h // ny
    classes = int(labels.max()) + 1
    out = np.zeros((nx, ny, tables.count), dtype=np.int64)
    for k, (dx, dy) in enumerate(tables.offsets.numpy().astype(np.int64)):
        shifted = np.roll(labels, (-int(dy), -int(dx)), axis=(0, 1))  # shifted[r, c] = labels[r + dy, c + dx]
        blocks = shifted.reshape(ny, ty, nx, tx)
        counts = np.stack([(blocks == c).sum((1, 3)) for c in range(classes)], -1)  # (ny, nx, classes)
        out[:, :, k] = np.argmax(counts, -1).T
    return out


def source_labels(synth, uv) -> torch.Tensor:
    """The exemplar label of the content each query shows ``(N,)`` int64 -- what the guidance target counts: a point
    comes from content of its target label when this equals the target. Guided hist and hex: the label under the
    sample of largest steered barycentric weight (the largest blend weight for hist, whose weights grow with it);
    guided struct: the label of the texel the point reads (after its cell's offset and the cuts)."""
    uv = check_uv(uv).reshape(-1, 2).to(torch.float64)
    if isinstance(synth, GuidedCellQuilting):
        read, _ = synth.read_positions(uv)
        h, w = synth.labels.shape
        col = torch.floor(read[:, 0]).long().clamp(0, w - 1)
        row = torch.floor(read[:, 1]).long().clamp(0, h - 1)
        return synth.labels.to(uv.device)[row, col]
    uv_samples, bary, matched = synth.guided_positions(uv)
    k = torch.argmax(synth.steered_barycentrics(bary, matched), dim=-1)
    ph, pw = synth.prepared.plane.shape[:2]
    pos = uv_samples[torch.arange(len(uv)), k]
    col = torch.floor(pos[:, 0] * pw).long().clamp(0, pw - 1)
    row = torch.floor(pos[:, 1] * ph).long().clamp(0, ph - 1)
    return synth.labels.to(uv.device)[row, col]
