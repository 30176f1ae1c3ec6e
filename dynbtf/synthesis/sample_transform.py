"""Random rotation and scale of the lattice's samples: orientation and size variation for isotropic materials.

Lattice blending (``linear``, ``hist``, ``hex``) reads, for each of a query's three lattice vertices, the
exemplar shifted by the vertex's hashed offset: every copy keeps the exemplar's orientation and size, and on an
isotropic material (stone, sand, leather) the eye still finds the one orientation of its grain. With
``rotation`` and ``scale_jitter`` each vertex's sample is also turned and scaled about the vertex, by an angle and
a factor drawn from the vertex's hash (the same hash as its offset, in streams of their own):

    angle = rotation * (2 u_1 - 1)            (u_1 uniform in [0, 1): angles uniform in [-rotation, rotation])
    scale = (1 + scale_jitter) ** (2 u_2 - 1)  (log-uniform in [1 / (1 + scale_jitter), 1 + scale_jitter])

A query at ``d`` texels from vertex ``k`` reads that sample at ``A_k d`` from the vertex's exemplar point
(``A_k = scale_k R(angle_k)``), i.e. ``(A_k - I) d`` away from where the untransformed sample reads.
``d`` comes from the lattice cell's fractions and small integer vertex steps (:func:`lattice_displacements`),
so it is exact far from the origin, as the lattice is.

Turning a BTF's surface also turns its directions: the exemplar point ``p = c + R(x - v)`` under directions
``R w`` looks as the synthesized point ``x`` under ``w`` (a ridge turned with its lighting). One decode per query
needs one frame, so the view and the light are turned by the query's **frame angle**: the circular mean of its
samples' angles weighted by the method's lattice weights (:func:`frame_angle`; ``hist``: ``b^gamma``
normalized), so that wherever one sample shows, its own frame is used, and between samples the frame turns
continuously. Scale does not change directions.

The functions below use only arithmetic, ``mix32`` and the replaceable ``_to_float64`` / ``_exp``, so the same
code runs on torch tensors and, compiled by numba (:mod:`dynbtf.synthesis.kernels`), on scalars.

Examples
--------
>>> import torch
>>> angle, scale = vertex_transform(torch.tensor([0, 12345], dtype=torch.int64), math.pi, math.log(1.5))
>>> [round(a, 4) for a in angle.tolist()], [round(s, 4) for s in scale.tolist()]
([1.7566, -1.2245], [0.9961, 0.9818])
"""

from __future__ import annotations

import math

import torch

from ..errors import InputError
from .hash import mix32
from .lattice import LATTICE_SCALE

__all__ = ["ROTATION_STREAM", "SCALE_STREAM", "MAX_ROTATION", "MAX_SCALE_JITTER", "check_rotation",
           "check_scale_jitter", "vertex_transform", "displacement", "lattice_displacements", "frame_angle"]

#: Constants xor-ed into a vertex's hash for its angle and its scale (streams apart from its offset's).
ROTATION_STREAM = 0x27D4EB2F
SCALE_STREAM = 0x165667B1
#: Largest ``rotation`` (degrees): 180 draws every orientation.
MAX_ROTATION = 180.0
#: Largest ``scale_jitter``: scales between 1/2 and 2.
MAX_SCALE_JITTER = 1.0

_UNIT = 2.0 ** -32
_to_float64 = torch.Tensor.double
_exp = torch.exp


def check_rotation(name: str, value) -> float:
    """``value`` as a float in ``[0, MAX_ROTATION]`` degrees, else :class:`InputError` naming ``name``."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number of degrees in [0, {MAX_ROTATION:g}], got {value!r}") from None
    if not (math.isfinite(value) and 0.0 <= value <= MAX_ROTATION):
        raise InputError(f"{name}: expected a number of degrees in [0, {MAX_ROTATION:g}] (the largest angle a "
                         f"sample is turned by; 0: off), got {value!r}")
    return value


def check_scale_jitter(name: str, value) -> float:
    """``value`` as a float in ``[0, MAX_SCALE_JITTER]``, else :class:`InputError` naming ``name``."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number in [0, {MAX_SCALE_JITTER:g}], got {value!r}") from None
    if not (math.isfinite(value) and 0.0 <= value <= MAX_SCALE_JITTER):
        raise InputError(f"{name}: expected a number in [0, {MAX_SCALE_JITTER:g}] (samples scaled between "
                         f"1 / (1 + j) and 1 + j; 0: off), got {value!r}")
    return value


def vertex_transform(h, max_angle, log_scale):
    """Angle (radians, float64) and scale factor of the sample owned by a vertex of hash ``h`` (int64 in
    ``[0, 2**32)``): uniform in ``[-max_angle, max_angle]`` and log-uniform in ``[exp(-log_scale),
    exp(log_scale)]`` (``log_scale = log(1 + scale_jitter)``)."""
    angle = max_angle * (2.0 * (_to_float64(mix32(h ^ ROTATION_STREAM)) * _UNIT) - 1.0)
    scale = _exp(log_scale * (2.0 * (_to_float64(mix32(h ^ SCALE_STREAM)) * _UNIT) - 1.0))
    return angle, scale


def displacement(dx, dy, cos_scaled, sin_scaled):
    """``(A - I) d`` for ``d = (dx, dy)`` and ``A = [[c, -s], [s, c]]`` (``c = scale cos(angle)``,
    ``s = scale sin(angle)``): how far the transformed sample's read point moves, in texels."""
    return (cos_scaled - 1.0) * dx - sin_scaled * dy, sin_scaled * dx + (cos_scaled - 1.0) * dy


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


def frame_angle(angles: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """The frame angle ``(N,)`` (radians) of queries whose samples have ``angles (N, 3)`` and lattice weights
    ``weights (N, 3)``: ``atan2(sum w sin, sum w cos)``, the weighted circular mean."""
    return torch.atan2((weights * torch.sin(angles)).sum(-1), (weights * torch.cos(angles)).sum(-1))
