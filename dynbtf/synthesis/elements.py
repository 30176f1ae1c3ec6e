"""The elements of a structured exemplar (bricks, tiles, pavers) and a per-element colour variation.

A structured exemplar repeats an element on a lattice (:mod:`dynbtf.synthesis.structure`). Its elements lie in
**rows**: ``rows`` rows per repeat, each of ``columns`` elements, row ``k`` shifted by ``k p / q`` of an element
(running bond: ``p / q = 1 / 2``; stack bond and square tiles: 0). :func:`element_grid` reads that grid off the
lattice offsets -- the shortest horizontal one gives the element's width, the shortest row step the row height, and
the shift is the simple fraction that puts every offset on the lattice best -- and places it on the joints: the row
borders on the texel rows least like the typical row (joints are thin, the few rows unlike the rest), the head
borders where the exemplar looks most like those bed joints. The joints themselves are the texels that look more
like the bed joints than like the elements' middles (two means, refined).

The lattice copies of a structured synthesis (``struct``) line their elements up with the exemplar's tiled grid,
so the element a surface point shows is the grid's element at that point, whichever copy it reads: an element
instance is an integer pair ``(column, row)`` over the whole surface, computed exactly for any ``uv`` (int64 from
the repeat index, the fraction in float64). :func:`element_gain` gives each instance an RGB factor drawn from the
integer hash of the pair and the seed (:mod:`dynbtf.synthesis.hash`, a stream of its own):
``exp(brightness a_0 + tint (a_c - mean a))`` with ``a_0 .. a_3`` uniform of unit variance, so ``brightness`` is
the standard deviation of the element's log-brightness and ``tint`` moves the channels against each other (each
channel's log gain from it has standard deviation ``tint sqrt(2/3)``). Joints keep factor 1. A footprint over
many elements averages their factors: its deviation from 1 shrinks as ``sqrt(element area / footprint area)``.

Examples
--------
>>> import numpy as np
>>> h = w = 32; y, x = np.mgrid[0:h, 0:w]
>>> course = y // 8; joint = ((x + 4 * (course % 2) + 1) % 8 < 2) | ((y + 1) % 8 < 2)  # 8 x 8 bricks, half bond
>>> grid, joints = element_grid(np.array([[0, 0], [8, 0], [4, 8], [28, 8]]), np.where(joint, 1.0, 0.0)[..., None])
>>> grid.tolist(), bool((joints == joint).all())
([4.0, 4.0, 1.0, 2.0, 0.0, 0.0], True)
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import number_in_range
from .hash import MASK32, SECOND_STREAM, hash_vertex, mix32

__all__ = ["element_grid", "element_instances", "broken_elements", "element_gain", "repeat_elements", "check_variation",
           "check_element_grid", "whole_element_size", "VARIATION_SALT", "MAX_VARIATION", "MAX_SHIFT_DENOMINATOR"]

#: Xor-ed into the seed of the variation's hashes (a stream apart from the synthesis's own choices).
VARIATION_SALT = 0x5BD1E995
#: Largest ``brightness`` and ``tint`` (standard deviations of a natural-log gain).
MAX_VARIATION = 1.0
#: Row shifts are ``p / q`` of an element with ``q`` at most this (stack, half, third and quarter bonds).
MAX_SHIFT_DENOMINATOR = 4
_UNIT_UNIFORM = math.sqrt(12.0)  # (u - 1/2) sqrt(12) has unit variance for u uniform in [0, 1)
_PHASE_STEP = 0.5  # texels between the grid placements tried
_JOINT_ITERATIONS = 4  # refinements of the joints' and elements' mean appearance


def check_variation(name: str, value) -> float:
    """``value`` as a float in ``[0, MAX_VARIATION]``, else an :class:`InputError` naming ``name``."""
    return number_in_range(name, value, 0.0, MAX_VARIATION,
                           f"the standard deviation of a log gain in [0, {MAX_VARIATION:g}] (0: off)")


def _row_shift(offsets: np.ndarray, rows: int, a: float, c: float) -> tuple[int, int]:
    """``(p, q)``, ``q <= MAX_SHIFT_DENOMINATOR`` and ``rows p`` a multiple of ``q``: the row shift (in elements of
    ``a`` texels; rows ``c`` texels high) that best explains the lattice ``offsets (K, 2)`` (whole texels): an offset
    ``k`` rows up (``k = round(dy / c)``) lies ``k p / q`` elements across, up to whole elements. The sum of the
    offsets' distances from that, in texels, decides; the simplest fraction wins a tie (within half a texel).
    Every offset takes part, so that the rounding of one short step to whole texels (10 for 10.67) does not."""
    fractions = [(p, q) for q in range(1, MAX_SHIFT_DENOMINATOR + 1) for p in range(q)
                 if math.gcd(p, q) == 1 and (rows * p) % q == 0]
    best, best_error = (0, 1), math.inf
    k = np.round(offsets[:, 1] / c)  # rows up
    for p, q in fractions:
        miss = np.mod(offsets[:, 0] - k * p / q * a + a / 2, a) - a / 2
        error = float(np.abs(miss).sum())
        if error < best_error - 0.5:
            best, best_error = (p, q), error
    return best


def element_grid(offsets: np.ndarray, appearance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The element grid ``[columns, rows, p, q, phase_x, phase_y]`` (float64 ``(6,)``) of an exemplar whose lattice
    offsets are ``offsets (K, 2)`` (whole texels ``(dx, dy)``, :func:`~dynbtf.synthesis.cell_quilting.lattice_offsets`)
    and whose appearance is ``appearance (H, W, C)`` (e.g. its standardized features and decoded colours), and its
    joints ``(H, W)`` bool (see the module docstring).

    The rows' borders go on the texel rows least like the typical row (joints are thin: the few unlike the rest);
    the head borders where the exemplar, in each row's shifted coordinate, looks most like those bed joints. (A
    joint one texel wide mixes mortar with both bricks, so the lattice copies disagree there nearly as much as
    inside a brick; it still looks more like mortar than a brick does.)

    An exemplar without a horizontal offset has one element per repeat across; without an offset off the
    horizontal, one row per repeat (so an unstructured exemplar is one element per repeat).
    """
    h, w = np.shape(appearance)[:2]
    offsets = np.asarray(offsets, dtype=np.int64).reshape(-1, 2)
    # the lattice's short vectors: the offsets, their sums and differences (a running bond's strongest peaks may
    # hold the half-bond steps (8, 8) and (8, -8) but not the brick's own width (16, 0), their sum)
    offsets = np.mod(np.concatenate([offsets, (offsets[:, None] + offsets[None]).reshape(-1, 2),
                                     (offsets[:, None] - offsets[None]).reshape(-1, 2)]), [w, h])
    across = [min(int(dx), w - int(dx)) for dx, dy in offsets if dy == 0 and dx != 0]
    columns = max(1, round(w / min(across))) if across else 1
    steps = [min(int(dy), h - int(dy)) for dx, dy in offsets if dy != 0]
    rows, p, q = 1, 0, 1
    if steps:
        rows = max(1, round(h / min(steps)))
        p, q = _row_shift(offsets, rows, w / columns, h / rows)
    a, c = w / columns, h / rows
    # the placement: row borders on the rows least like the typical row, then head borders where, in every row's
    # own shifted coordinate, the exemplar looks most like those rows
    look = np.asarray(appearance, dtype=np.float64)
    centres_y = np.arange(h) + 0.5
    profile = look.mean(1)  # (H, C): each texel row's mean appearance
    unusual = ((profile - np.median(profile, 0)) ** 2).sum(-1)  # the joints' rows are the few unlike the rest
    phases_y = np.arange(0.0, c, _PHASE_STEP)
    first_rows = [np.floor(np.mod(centres_y - py, c)) == 0 for py in phases_y]
    phase_y = float(phases_y[int(np.argmax([unusual[r].mean() if r.any() else -np.inf for r in first_rows]))])
    row = np.floor((centres_y - phase_y) / c)[:, None]
    along = np.mod(np.arange(w)[None, :] + 0.5 - row * p / q * a, a)  # (H, W): position within an element
    bed = np.floor(np.mod(centres_y - phase_y, c)) == 0  # the rows holding the row borders: the bed joints
    unlike_joint = ((look - look[bed].reshape(-1, look.shape[-1]).mean(0)) ** 2).sum(-1)  # (H, W)
    phases_x = np.arange(0.0, a, _PHASE_STEP)
    cost_x = [unlike_joint[np.floor(np.mod(along - px, a)) == 0].mean() if np.any(np.floor(np.mod(along - px, a)) == 0)
              else np.inf for px in phases_x]
    phase_x = float(phases_x[int(np.argmin(cost_x))])
    # the joints: texels that look more like the bed joints than like the elements' middle rows (two means, refined)
    middle = np.floor(np.mod(centres_y - phase_y, c)) == np.floor(c / 2)
    joint_mean, element_mean = look[bed].reshape(-1, look.shape[-1]).mean(0), look[middle].reshape(-1, look.shape[-1]).mean(0)
    joints = np.zeros((h, w), dtype=bool)
    for _ in range(_JOINT_ITERATIONS):
        joints = ((look - joint_mean) ** 2).sum(-1) < ((look - element_mean) ** 2).sum(-1)
        if joints.all() or not joints.any():
            return np.array([columns, rows, p, q, phase_x, phase_y], dtype=np.float64), np.zeros((h, w), dtype=bool)
        joint_mean, element_mean = look[joints].mean(0), look[~joints].mean(0)
    return np.array([columns, rows, p, q, phase_x, phase_y], dtype=np.float64), joints


def check_element_grid(grid, height: int, width: int) -> str | None:
    """What is wrong with a stored element grid of an ``height x width`` exemplar, or None."""
    columns, rows, p, q, phase_x, phase_y = (float(v) for v in grid)
    if not all(v == int(v) for v in (columns, rows, p, q)) or not (1 <= columns <= width and 1 <= rows <= height):
        return f"table 'element_grid': columns {columns:g} and rows {rows:g} must be whole, in [1, {width}] and [1, {height}]"
    if not (1 <= q <= MAX_SHIFT_DENOMINATOR and 0 <= p < q) or (rows * p) % q:
        return (f"table 'element_grid': row shift {p:g}/{q:g}, expected p/q with 0 <= p < q <= "
                f"{MAX_SHIFT_DENOMINATOR} and rows x p a multiple of q")
    if not (0 <= phase_x < width / columns and 0 <= phase_y < height / rows):
        return "table 'element_grid': its phase lies outside one element"
    return None


def whole_element_size(grid, height: int, width: int) -> tuple[int, int]:
    """The texel size ``(height', width')`` nearest ``height x width`` at which the elements of ``grid``
    (:func:`element_grid`) are whole texels: each row ``round(height / rows)`` texels high, each element a
    multiple of ``q`` texels wide (so that the row shift ``p / q`` of an element is whole too), nearest
    ``width / columns``. Lattice copies shifted by whole texels then move whole elements onto whole elements.

    >>> whole_element_size([3.0, 6.0, 1.0, 2.0, 0.0, 0.0], 64, 64)  # 21.33 x 10.67-texel bricks, half bond
    (66, 66)
    >>> whole_element_size([4.0, 8.0, 1.0, 2.0, 0.0, 0.0], 64, 64)  # 16 x 8: whole already
    (64, 64)
    """
    columns, rows, _, q = (int(v) for v in grid[:4])
    element = q * max(1, round(width / columns / q))
    return rows * max(1, round(height / rows)), columns * element


def element_instances(points: torch.Tensor, grid, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The element instance ``(column, row)``, int64 ``(N,)`` each, of every point ``(N, 2)`` (float64, exemplar
    repeats) on an ``height x width`` exemplar's element ``grid`` (:func:`element_grid`): exact for any repeat
    index below ``2**52`` (integer arithmetic on the repeat index, float64 on the fraction)."""
    columns, rows, p, q = (int(v) for v in grid[:4])
    phase_x, phase_y = float(grid[4]), float(grid[5])
    whole = torch.floor(points)
    frac = points - whole
    whole = whole.to(torch.int64)
    a, c = width / columns, height / rows
    row = whole[:, 1] * rows + torch.floor((frac[:, 1] * height - phase_y) / c).to(torch.int64)
    shifted = row * p
    carry = torch.div(shifted, q, rounding_mode="floor")  # row * p / q = carry + rest / q
    rest = shifted - carry * q
    column = whole[:, 0] * columns - carry + torch.floor(
        ((frac[:, 0] * width - phase_x) / a * q - rest) / q).to(torch.int64)
    return column, row


def repeat_elements(grid) -> tuple[int, int, int]:
    """``(columns, rows, shift)`` of an element ``grid`` (:func:`element_grid`): the repeat ``I`` starts at element
    instance ``(I_u columns - I_v shift, I_v rows)``, with ``shift = rows p / q`` whole (a stored grid's rows
    come back to the same shift after one repeat, :func:`check_element_grid`). The integer part a renderer's CPU
    computes once per repeat (the web export's repeat origin); :func:`element_instances` adds the point's place in
    the repeat.

    >>> repeat_elements([4.0, 4.0, 1.0, 2.0, 0.0, 0.0])
    (4, 4, 2)
    """
    columns, rows, p, q = (int(v) for v in grid[:4])
    return columns, rows, rows * p // q


def element_gain(points: torch.Tensor, grid, joints: torch.Tensor, seed: int, brightness: float, tint: float,
                 footprint_texels: torch.Tensor | None = None) -> torch.Tensor:
    """RGB factors ``(N, 3)`` float32 of the element instances at ``points (N, 2)`` (float64, exemplar repeats) on
    ``grid`` (:func:`element_grid`), 1 on ``joints (H, W)``; on the points' device.

    ``footprint_texels (N,)`` (optional): each query's footprint side in texels; the log factor is scaled by
    ``min(1, sqrt(element area) / footprint)``.
    """
    h, w = joints.shape
    column, row = element_instances(points, grid, h, w)
    key = hash_vertex(column, row, (int(seed) ^ VARIATION_SALT) & MASK32)
    streams = torch.stack([mix32(key ^ ((k * SECOND_STREAM) & MASK32)) for k in range(4)], -1)
    a = (streams.to(torch.float64) / 2.0 ** 32 - 0.5) * _UNIT_UNIFORM  # (N, 4), unit variance
    log_gain = brightness * a[:, :1] + tint * (a[:, 1:] - a[:, 1:].mean(-1, keepdim=True))
    if footprint_texels is not None:
        area = (w / float(grid[0])) * (h / float(grid[1]))
        reach = torch.clamp(math.sqrt(area) / footprint_texels.to(points.device, torch.float64), max=1.0)
        log_gain = log_gain * reach[:, None]
    frac = points - torch.floor(points)
    x = torch.clamp(torch.floor(frac[:, 0] * w).to(torch.int64), 0, w - 1)
    y = torch.clamp(torch.floor(frac[:, 1] * h).to(torch.int64), 0, h - 1)
    on_joint = joints.to(points.device)[y, x].bool()
    return torch.where(on_joint[:, None], torch.ones_like(log_gain), torch.exp(log_gain)).to(torch.float32)


#: Output elements smaller than this share of the median element are not counted by :func:`broken_elements` (specks
#: of a joint map that cut a stone's chip or a mortar grain off as an element of its own).
MIN_ELEMENT_SHARE = 0.3


def _periodic_labels(elements: np.ndarray) -> np.ndarray:
    """Connected components (4-neighbours) of ``elements (H, W)`` bool on the torus: int labels, 0 off them."""
    from scipy import ndimage

    labels, count = ndimage.label(elements)
    parent = np.arange(count + 1)

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in zip(np.concatenate([labels[0], labels[:, 0]]), np.concatenate([labels[-1], labels[:, -1]])):
        if a and b:
            parent[root(int(a))] = root(int(b))
    return np.array([root(int(a)) for a in range(count + 1)])[labels]


def _inner(elements: np.ndarray, periodic: bool) -> np.ndarray:
    """``elements (H, W)`` bool eroded by one texel (4-neighbours; on the torus when ``periodic``)."""
    from scipy import ndimage

    if periodic:  # (binary_erosion has no wrap-around)
        return elements & np.roll(elements, 1, 0) & np.roll(elements, -1, 0) & np.roll(elements, 1, 1) \
            & np.roll(elements, -1, 1)
    return ndimage.binary_erosion(elements, structure=ndimage.generate_binary_structure(2, 1), border_value=0)


def broken_elements(read_positions, joints, *, repeats: float = 8.0, far: float = 1e6) -> tuple[float, int]:
    """How many elements of a structured synthesis come from more than one source element: ``(share, counted)``.

    ``read_positions``: a function from ``uv (N, 2)`` float64 tensor (exemplar repeats) to the exemplar positions each
    query reads, ``(N, 2)`` texels (as :meth:`CellQuilting.read_positions
    <dynbtf.synthesis.cell_quilting.CellQuilting.read_positions>`'s first result); ``joints (H, W)`` bool, the
    exemplar's joints (mortar, grout: ``prepared.joints`` of ``struct``).

    A window of ``repeats x repeats`` exemplar repeats, one query per texel centre, ``far`` repeats from the
    origin, is cut into its elements: the connected regions of its inner texels, those one texel in from the joints
    (4-neighbours) in the output and at the texel they read (so that a hole of a texel in a joint map does not join
    two bricks). The source elements are the exemplar's own inner regions, connected across its periodic edges. An
    output element is **broken** when it reads more than one source element: a two-tone brick, a brick with a
    sliver of another. Elements touching the window's border, and specks below :data:`MIN_ELEMENT_SHARE` of the
    median element, are not counted. An exemplar with no joints has no elements to break: ``(0.0, 0)``.

    >>> joints = np.zeros((16, 16), bool); joints[:, [0, 8]] = True; joints[[0, 8]] = True  # 7 x 7-texel tiles
    >>> tiled = lambda uv: torch.remainder(uv * 16, 16)  # tiling: every tile whole
    >>> broken_elements(tiled, joints, repeats=4)
    (0.0, 49)
    >>> def cut(uv):  # the third row of tiles takes its lower half from the next tile along
    ...     x = uv * 16
    ...     lower = (x[:, 1:] % 64 >= 20) & (x[:, 1:] % 64 < 24)
    ...     return torch.remainder(x + lower * x.new_tensor([8.0, 0.0]), 16)
    >>> broken_elements(cut, joints, repeats=4)
    (0.14285714285714285, 49)
    """
    joints = np.asarray(joints, dtype=bool)
    h, w = joints.shape
    if joints.all() or not joints.any():
        return 0.0, 0
    from scipy import ndimage

    source_inner = _inner(~joints, periodic=True)
    source = _periodic_labels(source_inner)
    side_x, side_y = int(round(repeats * w)), int(round(repeats * h))
    gy, gx = np.mgrid[0:side_y, 0:side_x].reshape(2, -1) + 0.5
    uv = np.stack([far + gx / w, far + gy / h], -1)
    positions = read_positions(torch.from_numpy(uv))
    positions = positions.cpu().numpy() if isinstance(positions, torch.Tensor) else np.asarray(positions)
    rx = np.floor(positions[:, 0]).astype(np.int64) % w
    ry = np.floor(positions[:, 1]).astype(np.int64) % h
    counted = _inner(~joints[ry, rx].reshape(side_y, side_x), periodic=False) \
        & source_inner[ry, rx].reshape(side_y, side_x)
    labels, count = ndimage.label(counted)
    border = np.unique(np.concatenate([labels[1], labels[-2], labels[:, 1], labels[:, -2]]))  # (0 and -1: eroded)
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    pairs = np.unique(np.stack([labels[counted], source[ry, rx].reshape(side_y, side_x)[counted]]), axis=1)
    ids, sources = np.unique(pairs[0], return_counts=True)
    keep = ~np.isin(ids, border) & (sizes[ids] >= MIN_ELEMENT_SHARE * np.median(sizes[ids]))
    if not keep.any():
        return 0.0, 0
    return float((sources[keep] > 1).mean()), int(keep.sum())
