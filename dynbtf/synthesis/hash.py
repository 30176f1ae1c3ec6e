"""Integer hash of lattice vertices: every random choice of dynamic synthesis.

The shader ports of histogram-preserving blending draw per-vertex offsets with
``frac(sin(dot(v, ...)) * 43758.5453)``, which decorrelates poorly and loses
precision at large vertex coordinates. Here a vertex ``(vx, vy)`` (int64, any
value) and a ``seed`` are mixed with the 32-bit "lowbias32" integer finalizer
(C. Wellons, *Prospecting for hash functions*, 2018):

    x ^= x >> 16; x *= 0x7feb352d; x ^= x >> 15; x *= 0x846ca68b; x ^= x >> 16   (mod 2**32)

applied to ``seed`` (xor a salt, :func:`seed_state`), then folded with the low and high 32-bit words of ``vx`` and
``vy`` in turn (:func:`fold_coordinate`). The result is exact and identical across runs, processes,
machines and devices.

The functions use only ``&``, ``^``, ``>>``, ``+`` and ``*`` on int64 values whose
products stay below 2**63, so the *same* Python code runs on NumPy arrays,
torch tensors and (compiled by numba) scalars in :mod:`dynbtf.synthesis.kernels`
(which swaps ``_mulmod32`` for a native unsigned 64-bit multiply: same values).

Examples
--------
>>> import numpy as np
>>> int(hash_vertex(np.int64(0), np.int64(0), np.int64(0)))
4125828455
>>> offsets = vertex_offsets(np.array([3, -7]), np.array([5, 1 << 40]), 0, 64, 48)
>>> offsets[0].tolist(), offsets[1].tolist()
([56, 1], [0, 26])
"""

from __future__ import annotations

__all__ = ["mix32", "seed_state", "fold_coordinate", "hash_vertex", "vertex_offsets", "MASK32", "MIX_MULTIPLIER_1",
           "MIX_MULTIPLIER_2", "SECOND_STREAM", "SEED_SALT"]

#: Low 32 bits.
MASK32 = 0xFFFFFFFF
#: The two odd multipliers of :func:`mix32` (every backend's copy of the hash uses these).
MIX_MULTIPLIER_1 = 0x7FEB352D
MIX_MULTIPLIER_2 = 0x846CA68B
#: Golden-ratio constant that separates the second offset coordinate's stream.
SECOND_STREAM = 0x9E3779B9
#: Salt xor-ed into the seed (mix32(0) == 0).
SEED_SALT = 0x85EBCA6B


def _mulmod32(x, c: int):
    """``(x * c) mod 2**32`` for ``0 <= x < 2**32`` without int64 overflow (split ``c`` in 16-bit halves)."""
    return ((((x * (c >> 16)) & 0xFFFF) << 16) + x * (c & 0xFFFF)) & MASK32


def mix32(x):
    """The lowbias32 finalizer on values in ``[0, 2**32)`` (int64 arrays, tensors or scalars)."""
    x = x ^ (x >> 16)
    x = _mulmod32(x, MIX_MULTIPLIER_1)
    x = x ^ (x >> 15)
    x = _mulmod32(x, MIX_MULTIPLIER_2)
    return x ^ (x >> 16)


def seed_state(seed):
    """The hash state before any vertex word: ``mix32`` of the salted seed (constant per synthesizer).

    Salted: vertex ``(0, 0)`` with seed 0 must not hash to 0.
    """
    return mix32((seed ^ SEED_SALT) & MASK32)


def fold_coordinate(h, k):
    """Fold the low then the high 32-bit word of the int64 coordinate ``k`` into the hash state ``h``.

    Vertices that share ``vx`` share ``fold_coordinate(seed_state(seed), vx)`` (the fused
    kernel hashes a triangle's three vertices with five folds instead of six).
    """
    return mix32(mix32(h ^ (k & MASK32)) ^ ((k >> 32) & MASK32))


def hash_vertex(vx, vy, seed):
    """32-bit hash of integer vertex coordinates and a seed, as int64 values in ``[0, 2**32)``.

    ``fold_coordinate(fold_coordinate(seed_state(seed), vx), vy)``.

    Parameters
    ----------
    vx, vy : int64 array, tensor or scalar, same shape
        Lattice vertex coordinates (any int64 value, negative included).
    seed : int or int64 array/tensor broadcastable to ``vx``
        The synthesis seed (only its low 32 bits matter).
    """
    return fold_coordinate(fold_coordinate(seed_state(seed), vx), vy)


def vertex_offsets(vx, vy, seed, width: int, height: int):
    """Random integer texel offsets ``(ox, oy)`` in ``[0, width) x [0, height)`` of lattice vertices.

    Offsets are whole texels ("snapped"): sampling the exemplar at a whole-texel
    offset adds no bilinear low-pass (which would cost a few percent of variance),
    and all samples of one query share the same sub-texel position.
    """
    h = hash_vertex(vx, vy, seed)
    return h % width, mix32(h ^ SECOND_STREAM) % height
