"""Quarter turns and scales of the lattice's samples: orientation and size variation, exact far from the origin.

Lattice blending (``linear``, ``hist``, ``hex``) reads, for each of a query's three lattice vertices, the
exemplar shifted by the vertex's hashed whole-texel offset: every copy keeps the exemplar's orientation, and on an
isotropic material (stone, sand, leather) the eye still finds the one direction of its grain and of its shading.
With ``rotation`` each vertex's sample is also turned by ``t`` quarter turns, ``t`` in ``{0, 1, 2, 3}`` drawn from
the vertex's hash (in a stream of its own), about a texel centre next to the vertex (its pivot).

**Why quarter turns.** A quarter turn about a texel centre maps the texel grid onto itself: a query at a texel
centre reads one exemplar texel, as the unturned sample does, and between centres the bilinear read is the turned
exemplar's own. Any other angle reads between texels everywhere, and a fitted feature plane read between texels is
not a feature vector the decoder has seen: measured on a 128 x 128 stone with free angles, the decoded colours'
W1/std against the exemplar's rose from 0.02 to 0.61 (``benchmarks/bench_rotation.py``, docs/synthesis.md).

**The pivot.** Sample ``k`` is ``E(v + A (x - v) + o)`` with ``v = floor(V_k + s) + 1/2`` the texel centre
that :data:`PIVOT_SHIFT` ``s`` picks next to vertex ``V_k``, ``A`` the turn and ``o`` the vertex's offset. (Not
the nearest centre: vertices often sit exactly on texel boundaries -- every vertex row does where the exemplar's
height is a multiple of 4 -- and the nearest centre would then be a tie that rounding breaks differently from one
query to the next; ``s`` moves the tie to ``frac(V) = 1 - s``, where no vertex sits.) The query ``q`` (texels)
is ``c + t`` with ``c`` its texel centre below-left and ``t`` in ``[0, 1)^2``; its offset from the vertex,
``d = q - V_k``, comes from the lattice cell's barycentrics and small vertex steps
(:func:`lattice_displacements`). Then ``q - v = t - floor(t - d + 1/2 + s)``: small numbers only, so the turn is
exact far from the origin, as the lattice is; the read point moves by ``(A - I)(q - v)`` (:func:`displacement`),
a whole number of texels at a texel centre.

**Directions.** Turning a BTF's surface turns its directions too: the exemplar point under directions ``A w`` is
the synthesized point under ``w`` (a ridge turned with its lighting). One decode per query needs one frame, so
the view and the light are turned by the query's **frame angle**: the circular mean of its samples' angles weighted
by the method's lattice weights (:func:`frame_direction`; ``hist``: ``b^gamma`` normalized), so that wherever one sample
shows, its own frame is used, and between samples the frame turns continuously.

**Scale jitter.** With ``scale_jitter`` ``j`` each vertex's sample is also magnified by a factor
``f = (1 + j)^(2 r - 1)``, log-uniform in ``[1 / (1 + j), 1 + j]``, ``r`` drawn from the vertex's hash (a stream
of its own, 24 bits): sample ``k`` is ``E(v + A (x - v) / f + o)``, so the read point moves by ``(A / f - I) m``
with the same pivot and the same small ``m``. The directions are not changed (a uniform scale keeps every slope's
orientation). Unlike a quarter turn, a scale reads between texel centres everywhere, so it needs a feature plane
that decodes well there: a model fitted with the sub-texel term (``dynbtf fit``'s default for the Triple Plane;
docs/triple_plane.md, "Between texel centres").

The functions below use only arithmetic, ``mix32`` and the replaceable ``_floor``, ``_exp`` and ``_to_float64``,
so the same code runs on torch tensors and, compiled by numba (:mod:`dynbtf.synthesis.kernels`), on scalars.

Examples
--------
>>> import torch
>>> quarter_turns(torch.tensor([0, 1, 2, 12345], dtype=torch.int64)).tolist()
[0, 2, 1, 2]
>>> f = 1.0 / inverse_scales(torch.arange(100000, dtype=torch.int64), scale_log(0.25))
>>> round(float(f.min()), 4), round(float(f.max()), 4), abs(float(f.log().mean())) < 1e-3
(0.8, 1.25, True)
"""

from __future__ import annotations

import math

import torch

from ..errors import InputError, number_in_range
from .hash import mix32
from .lattice import LATTICE_SCALE

__all__ = ["ROTATION_STREAM", "SCALE_STREAM", "PIVOT_SHIFT", "MAX_SCALE_JITTER", "check_rotation",
           "check_scale_jitter", "scale_log", "quarter_turns", "turn_cos_sin", "inverse_scales", "displacement",
           "lattice_displacements", "frame_direction"]

#: Constant xor-ed into a vertex's hash for its turn (a stream apart from its offset's).
ROTATION_STREAM = 0x27D4EB2F
#: Constant xor-ed into a vertex's hash for its scale (a stream apart from its offset's and its turn's).
SCALE_STREAM = 0x165667B1
#: Largest ``scale_jitter``: samples magnified between half and twice the exemplar's size.
MAX_SCALE_JITTER = 1.0
#: The pivot of a vertex's turn is the texel centre ``floor(V + PIVOT_SHIFT) + 1/2`` (texels, each axis).
PIVOT_SHIFT = 0.2345

_floor = torch.floor
_exp = torch.exp


def _to_float64(x):
    return x.to(torch.float64)


def check_rotation(name: str, value) -> bool:
    """``value`` as a bool (True, False, 1, 0), else :class:`InputError` naming ``name``."""
    if isinstance(value, bool) or (isinstance(value, (int, float)) and value in (0, 1)):
        return bool(value)
    raise InputError(f"{name}: expected true or false (each sample turned by a random quarter turn), got {value!r}")


def check_scale_jitter(name: str, value) -> float:
    """``value`` as a float in ``[0, MAX_SCALE_JITTER]``, else :class:`InputError` naming ``name``."""
    return number_in_range(name, value, 0.0, MAX_SCALE_JITTER, f"a scale jitter in [0, {MAX_SCALE_JITTER:g}] (each "
                           "sample magnified by a factor between 1/(1 + j) and 1 + j; 0: off)")


def scale_log(jitter: float) -> float:
    """``log(1 + jitter)``: the half-range of the samples' log scale factors, what the kernels take."""
    return math.log1p(float(jitter))


def inverse_scales(h, log_range):
    """``1 / f`` (float64) of the samples owned by vertices of hash ``h``: ``f = exp((2 r - 1) log_range)``,
    ``r = (mix32(h ^ SCALE_STREAM) >> 8) / 2**24`` (exactly 1 where ``log_range`` is 0)."""
    r = _to_float64(mix32(h ^ SCALE_STREAM) >> 8) * (1.0 / 16777216.0)
    return _exp((1.0 - 2.0 * r) * log_range)


def quarter_turns(h):
    """Quarter turns ``t`` in ``{0, 1, 2, 3}`` (int64) of the sample owned by a vertex of hash ``h``."""
    return mix32(h ^ ROTATION_STREAM) & 3


def turn_cos_sin(t):
    """``(cos, sin)`` of ``t`` quarter turns, exact: ``(1, 0), (0, 1), (-1, 0), (0, -1)``."""
    odd = t & 1
    sign = 1 - (t & 2)  # +1 for t = 0, 1; -1 for t = 2, 3
    return (1 - odd) * sign, odd * sign


def displacement(t_x, t_y, d_x, d_y, cos_a, sin_a):
    """How far a turned (and scaled) sample's read point moves, in texels: ``(A - I) m`` with ``A = [[c, -s], [s, c]]``
    (a quarter turn, times ``1 / f`` for a scaled sample) and
    ``m = t - floor(t - d + 1/2 + PIVOT_SHIFT)`` the query's offset from the vertex's pivot (``t``: the query's
    fraction from its texel centre below-left, in ``[0, 1)``; ``d``: its offset from the vertex)."""
    m_x = t_x - _floor(t_x - d_x + (0.5 + PIVOT_SHIFT))
    m_y = t_y - _floor(t_y - d_y + (0.5 + PIVOT_SHIFT))
    return (cos_a - 1.0) * m_x - sin_a * m_y, sin_a * m_x + (cos_a - 1.0) * m_y


def lattice_displacements(vertices: torch.Tensor, barycentrics: torch.Tensor, density: tuple[int, int]):
    """Texel offsets ``(dx, dy)``, each float64 ``(N, 3)``, of each query from its three vertices' positions.

    ``vertices (N, 3, 2)`` int64 and ``barycentrics (N, 3)`` float64 as :func:`~dynbtf.synthesis.lattice.triangle_lattice`
    returns them; ``density``: texels per repeat ``(W, H)``. In lattice units the query is
    ``sum_k b_k V_k``, so its offset from ``V_j`` is ``sum_k b_k (V_k - V_j)``: small integers times
    barycentrics, exact far from the origin; to repeats by the inverse of the lattice's matrix
    (``u = (x + y / 2) / (2 sqrt 3)``, ``v = y / 4``), then to texels.
    """
    steps = (vertices[:, None, :, :] - vertices[:, :, None, :]).to(torch.float64)  # [n, j, k] = V_k - V_j
    lattice = (barycentrics[:, None, :, None] * steps).sum(2)  # (N, 3, 2)
    du = (lattice[..., 0] + 0.5 * lattice[..., 1]) / LATTICE_SCALE
    dv = 0.25 * lattice[..., 1]
    return du * density[0], dv * density[1]


def frame_direction(turns: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``(cos, sin)`` ``(N, 2)`` float64 of the frame angle of queries whose samples have ``turns (N, 3)`` quarter
    turns and lattice weights ``weights (N, 3)``: the weighted circular mean, ``sum_k w_k (cos, sin)(turn_k)``
    normalized (``(1, 0)`` where it vanishes: two opposite turns of equal weight)."""
    cos_a, sin_a = turn_cos_sin(turns)
    x, y = (weights * cos_a).sum(-1), (weights * sin_a).sum(-1)
    length = torch.sqrt(x * x + y * y)
    zero = length == 0.0
    length = torch.where(zero, torch.ones_like(length), length)
    return torch.stack([torch.where(zero, torch.ones_like(x), x / length), y / length], -1)
