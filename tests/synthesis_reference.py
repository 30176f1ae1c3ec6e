"""Independent references for the synthesis tests (pure Python / NumPy / high precision)."""

from __future__ import annotations

import math
from decimal import Decimal, getcontext
from fractions import Fraction

import numpy as np
import torch
import torch.nn.functional as F
from scipy.special import ndtr


def smooth_lognormal(h=48, w=48, c=4, seed=0, periodic=False):
    """Correlated, smooth, non-Gaussian exemplar ``(h, w, c)``."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(1, c, h, w, generator=g)
    mix = torch.eye(c) + 0.6 * torch.ones(c, c) / c
    x = torch.einsum("ij,bjhw->bihw", mix, x)
    x = F.avg_pool2d(F.pad(x, (2, 2, 2, 2), mode="circular" if periodic else "reflect"), 5, 1)
    return (x[0].permute(1, 2, 0) * 2.0).exp().contiguous()


def lowbias32(x: int) -> int:
    m = 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & m
    x ^= x >> 15
    x = (x * 0x846CA68B) & m
    return x ^ (x >> 16)


def reference_hash(vx: int, vy: int, seed: int) -> int:
    m = 0xFFFFFFFF
    h = lowbias32((seed ^ 0x85EBCA6B) & m)
    for word in (vx & m, (vx >> 32) & m, vy & m, (vy >> 32) & m):
        h = lowbias32(h ^ word)
    return h


def exact_lattice(u: float, v: float):
    """(base vertex, fractional k) with sqrt(3) to 40 digits: the independent reference."""
    getcontext().prec = 60
    s3 = Fraction(Decimal(3).sqrt())
    kx = 2 * s3 * Fraction(u) - 2 * Fraction(v)
    ky = 4 * Fraction(v)
    bx, by = math.floor(kx), math.floor(ky)
    return (bx, by), (float(kx - bx), float(ky - by))



def brute_force_lattice_blend(synth, uv: np.ndarray, mode: str) -> np.ndarray:
    """Features of a lattice-blending synthesizer, one query at a time, from its prepared tables.

    Lattice from :func:`exact_lattice` (40-digit sqrt(3)), hash from :func:`reference_hash`,
    texel addressing in exact fractions, bilinear fetch in float64, blend per the
    method's formula; histogram blending inverts with ``np.interp`` exactly.
    """
    plane = synth.prepared.plane.double().numpy()
    ph, pw, c = plane.shape
    dw, dh = synth.density
    out = np.zeros((uv.shape[0], c))
    for n, (u, v) in enumerate(uv):
        (bx, by), (fx, fy) = exact_lattice(u, v)
        if 1 - fx - fy > 0:
            verts, bary = [(bx, by), (bx, by + 1), (bx + 1, by)], [1 - fx - fy, fy, fx]
        else:
            verts, bary = [(bx + 1, by + 1), (bx + 1, by), (bx, by + 1)], [fx + fy - 1, 1 - fy, 1 - fx]
        px = Fraction(u) * dw - Fraction(1, 2)
        py = Fraction(v) * dh - Fraction(1, 2)
        x0, y0 = math.floor(px), math.floor(py)
        tx, ty = float(px - x0), float(py - y0)
        samples, lums = [], []
        for vx, vy in verts:
            h = reference_hash(vx, vy, synth.seed)
            ox, oy = h % pw, lowbias32(h ^ 0x9E3779B9) % ph
            c0, c1 = (x0 + ox) % pw, (x0 + ox + 1) % pw
            r0, r1 = (y0 + oy) % ph, (y0 + oy + 1) % ph

            def bilerp(p):
                return ((1 - tx) * (1 - ty) * p[r0, c0] + tx * (1 - ty) * p[r0, c1]
                        + (1 - tx) * ty * p[r1, c0] + tx * ty * p[r1, c1])

            samples.append(bilerp(plane))
            if mode == "hex":
                lums.append(bilerp(synth.prepared.extras["luminance"].double().numpy()))
        b = np.array(bary)
        s = np.array(samples)
        if mode == "linear":
            out[n] = b @ s
        elif mode == "hist":
            w = b ** synth.gamma / (b ** synth.gamma).sum()
            g = (w @ s) / math.sqrt((w * w).sum())
            sorted_values = synth.prepared.extras["transform"].sorted_values.numpy()
            m = sorted_values.shape[1]
            out[n] = [np.interp(ndtr(g[k]), (np.arange(m) + 0.5) / m, sorted_values[k]) for k in range(c)]
        else:
            w = (1 - synth.beta + synth.beta * np.array(lums)) * b ** 7
            w /= w.sum()
            k = math.log(1 - synth.contrast) / math.log(0.5)
            w = np.where(w < 0.5, 0.5 * (2 * w) ** k, 1 - 0.5 * (2 - 2 * w) ** k)
            out[n] = (w / w.sum()) @ s
    matrix, offset = synth.output_map()
    if matrix is not None:
        out = out @ matrix.double().numpy() + offset.double().numpy()
    return out


def reference_lattice_reads(synth, u: float, v: float):
    """Where a lattice-blending synthesizer's point query at ``(u, v)`` reads its plane: the three vertices'
    barycentrics (floats) and read positions ``(X, Y)`` in level-0 texels of the read plane, exact fractions in
    ``[0, W) x [0, H)`` (texel ``[i, j]`` covers ``[j, j + 1) x [i, i + 1)``): ``X = u W_density + offset_x mod W``.

    Lattice from :func:`exact_lattice`, offsets from :func:`reference_hash` (as :func:`brute_force_lattice_blend`)."""
    ph, pw = synth.prepared.plane.shape[:2]
    dw, dh = synth.density
    (bx, by), (fx, fy) = exact_lattice(u, v)
    if 1 - fx - fy > 0:
        verts, bary = [(bx, by), (bx, by + 1), (bx + 1, by)], [1 - fx - fy, fy, fx]
    else:
        verts, bary = [(bx + 1, by + 1), (bx + 1, by), (bx, by + 1)], [fx + fy - 1, 1 - fy, 1 - fx]
    positions = []
    for vx, vy in verts:
        h = reference_hash(vx, vy, synth.seed)
        ox, oy = h % pw, lowbias32(h ^ 0x9E3779B9) % ph
        positions.append(((Fraction(u) * dw + ox) % pw, (Fraction(v) * dh + oy) % ph))
    return bary, positions
