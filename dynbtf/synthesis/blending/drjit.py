"""Lattice blending in Dr.Jit: :func:`dynbtf.synthesis.blending.kernel.lattice_blend` (``linear``, ``hist``,
``hex``, the guided blends) traced into the renderer's kernel.
"""

from __future__ import annotations

import numpy as np

from ...device import to_host
from ...errors import InputError
from ...jit import drjit_module, flat_array, gather_channels, mi_module
from .. import hash as synthesis_hash
from ..drjit_blocks import (DrLevelOfDetail, accumulate, filtering_tables, gather_one, hash_vertex, level_shares,
                            lut_lookup, mix32, positive_mod, split_repeats, triangle_lattice)
from .kernel import MODE_HEX, MODE_HIST, MODE_LINEAR

class DrLatticeBlending:
    """Lattice blending of three hashed exemplar samples: :func:`dynbtf.synthesis.blending.kernel.lattice_blend` in Dr.Jit.

    The same computation, step for step: the triangle lattice in float64, the
    vertices' integer hash, whole-texel offsets wrapped on the (preprocessed)
    plane, one shared sub-texel bilinear footprint, then per mode

    * ``MODE_LINEAR``: weights = barycentrics;
    * ``MODE_HIST``: ``w_i = b_i^gamma / sum``, variance-preserving scale
      ``1 / sqrt(sum w_i^2)`` (Gaussian space, mean 0), then the inverse
      transform per channel through the :class:`~dynbtf.synthesis.histogram.InverseLUT`;
    * ``MODE_HEX``: ``w_i = (1 - beta + beta lum_i) b_i^7`` normalized, contrast gain
      ``g(x)`` with exponent ``gain_k``, renormalized;

    and finally the output map ``features = latent @ matrix + offset`` (the PCA
    un-projection of decorrelated methods), if any.

    Parameters
    ----------
    plane : float32 ``(H', W', C)``
        The plane the method blends (Gaussian-transformed coefficients for hist).
    density : (int, int)
        Texels per repeat along ``u`` and ``v``.
    seed : int
    mode : int
        The numba kernel's mode (:data:`~dynbtf.synthesis.blending.kernel.MODE_LINEAR`, ``MODE_HIST``, ``MODE_HEX``): the
        method's ``mode`` attribute.
    gamma, beta, gain_k : float
    luminance : float32 ``(H', W')``, for hex
    lut : float32 ``(C, L)``, ``g_min``, ``step``: for hist
    matrix : ``(C, C)``, ``offset`` ``(C,)``, optional: the output map
    pyramid_source : callable, optional
        Returns the synthesizer's pyramid (:meth:`dynbtf.synthesis.blending.LatticeBlending.pyramid`:
        ``levels``, ``lod``, and ``luts_numpy`` for hist, ``luminances`` for hex); called on the first
        footprint query (:meth:`filtered_latent`).
    guidance : DrGuidance, optional
        Exemplar guidance (:mod:`dynbtf.synthesis.guided_blending`): each sample takes the first candidate
        offset whose four texels (the point query's) carry the query's target label; footprint queries read the
        pyramid at those samples.
    """

    def __init__(self, plane, density, seed: int, mode: int, *, gamma: float = 1.0, beta: float = 0.0,
                 gain_k: float = 1.0, luminance=None, lut=None, g_min: float = 0.0, step: float = 1.0,
                 matrix=None, offset=None, pyramid_source=None, guidance=None) -> None:
        mi = mi_module()
        self.pyramid_source = pyramid_source
        self._filtering = None
        if mode not in (MODE_LINEAR, MODE_HIST, MODE_HEX):
            raise InputError(f"lattice blending mode: expected one of the kernel's modes {MODE_LINEAR}, {MODE_HIST}, "
                             f"{MODE_HEX}, got {mode!r}")
        plane = np.asarray(plane, dtype=np.float32)
        self.ph, self.pw, self.channels = (int(x) for x in plane.shape)
        self.plane = flat_array(mi, plane)
        self.density = (int(density[0]), int(density[1]))
        self.seed = int(seed) & 0xFFFFFFFF
        self.mode = mode
        self.gamma, self.beta, self.gain_k = float(gamma), float(beta), float(gain_k)
        self.luminance = flat_array(mi, luminance) if luminance is not None else None
        if mode == MODE_HEX and luminance is None:
            raise InputError("hex blending needs the luminance plane")
        if mode == MODE_HIST:
            if lut is None:
                raise InputError("hist blending needs the inverse-transform LUT")
            lut = np.asarray(lut, dtype=np.float32)
            self.lut_size = int(lut.shape[1])
            self.lut = flat_array(mi, lut)
            self.g_min, self.step = float(g_min), float(step)
        self.matrix = None if matrix is None else np.asarray(matrix, dtype=np.float32)
        self.offset = None if offset is None else np.asarray(offset, dtype=np.float32)
        self.guidance = guidance

    def _gain(self, x):
        dr = drjit_module()
        k = self.gain_k
        lo = 0.5 * dr.power(2.0 * x, k)
        hi = 1.0 - 0.5 * dr.power(dr.maximum(2.0 - 2.0 * x, 0.0), k)
        return dr.select(x < 0.5, lo, hi)

    def _weights(self, bary, lum=None):
        """The three samples' blend weights (``mi.Float``) from barycentrics and, for hex, their luminances ``lum``."""
        mi, dr = mi_module(), drjit_module()
        if self.mode == MODE_LINEAR:
            return [mi.Float(b) for b in bary]
        if self.mode == MODE_HIST:
            if self.gamma == 1.0:
                s = list(bary)
            else:  # (b / max b)^gamma: the largest term is 1, no underflow to 0/0 (blend_weights)
                top = dr.maximum(dr.maximum(bary[0], bary[1]), bary[2])
                s = [dr.power(dr.maximum(b, 0.0) / top, self.gamma) for b in bary]
            total = s[0] + s[1] + s[2]
            s = [x / total for x in s]
            scale = 1.0 / dr.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
            return [mi.Float(x * scale) for x in s]
        s = [(1.0 - self.beta + self.beta * l) * dr.power(dr.maximum(b, 0.0), 7) for l, b in zip(lum, bary)]
        total = s[0] + s[1] + s[2]
        s = [x / total for x in s]
        if self.gain_k != 1.0:
            s = [self._gain(x) for x in s]
            total = s[0] + s[1] + s[2]
            s = [x / total for x in s]
        return [mi.Float(x) for x in s]

    def _lattice(self, u, v):
        """The three samples of each query: barycentrics, their whole-texel offsets and the query's texel position.

        Returns ``bary`` (3 ``mi.Float64``), ``offsets`` (3 pairs ``(ox, oy)`` of ``mi.Int32``), the
        position in the read plane before the offsets: whole texels ``(mu, mv)`` (``mi.Int32``,
        ``(repeat x density) mod plane size``) plus ``(fu x W, fv x H)`` (``mi.Float64``), and the three
        vertices (pairs of ``mi.Int32``).
        """
        mi = mi_module()
        u, v = mi.Float64(u), mi.Float64(v)
        verts, bary = triangle_lattice(u, v)
        (wu, fu), (wv, fv) = split_repeats(u), split_repeats(v)
        dw, dh = self.density
        pw, ph = self.pw, self.ph
        # (iu * density) mod plane size, reduced before multiplying so nothing overflows
        mu = positive_mod(positive_mod(mi.Int32(wu), pw) * (dw % pw), pw)
        mv = positive_mod(positive_mod(mi.Int32(wv), ph) * (dh % ph), ph)
        offsets = [self._offsets(vx, vy, self.seed) for vx, vy in verts]
        return bary, offsets, (mu, mv), (fu * dw, fv * dh), verts

    def _samples(self, u, v, active=True):
        """:meth:`_lattice`, with the point query's shared bilinear footprint ``(xi, yi)`` (``mi.Int32``, the texel
        left of and below the position) and fractions ``(tx, ty)`` (``mi.Float``), and under guidance the chosen
        offsets and steered barycentrics: ``(bary, offsets, ((mu, mv), (fx, fy)), (xi, yi, tx, ty))``."""
        mi, dr = mi_module(), drjit_module()
        bary, offsets, (mu, mv), (fx, fy), verts = self._lattice(u, v)
        px = mi.Float64(mu) + fx - 0.5
        py = mi.Float64(mv) + fy - 0.5
        x0, y0 = dr.floor(px), dr.floor(py)
        tx, ty = mi.Float(px - x0), mi.Float(py - y0)
        xi, yi = mi.Int32(x0), mi.Int32(y0)
        if self.guidance is not None:
            offsets, bary = self.guidance.steer(self, u, v, verts, bary, offsets, xi, yi, active)
        return bary, offsets, ((mu, mv), (fx, fy)), (xi, yi, tx, ty)

    def _offsets(self, vx, vy, seed: int):
        """Whole-texel offsets ``(ox, oy)`` (``mi.Int32``) of vertices ``(vx, vy)`` hashed with ``seed``."""
        mi = mi_module()
        h = hash_vertex(vx, vy, seed)
        return mi.Int32(h % self.pw), mi.Int32(mix32(h ^ synthesis_hash.SECOND_STREAM) % self.ph)

    def latent(self, u, v, active=True, which=None):
        """Blended values before the output map: list of ``C`` mi.Float (only channels ``which``, if given)."""
        mi = mi_module()
        bary, offsets, _, (xi, yi, tx, ty) = self._samples(u, v, active)
        pw, ph = self.pw, self.ph
        wts = ((1.0 - tx) * (1.0 - ty), tx * (1.0 - ty), (1.0 - tx) * ty, tx * ty)
        taps_of_sample = []
        for ox, oy in offsets:
            ca, cb = positive_mod(xi + ox, pw), positive_mod(xi + ox + 1, pw)
            ra, rb = positive_mod(yi + oy, ph), positive_mod(yi + oy + 1, ph)
            idx = (mi.UInt32(ra * pw + ca), mi.UInt32(ra * pw + cb), mi.UInt32(rb * pw + ca), mi.UInt32(rb * pw + cb))
            taps_of_sample.append(list(zip(idx, wts)))
        lum = ([mi.Float64(gather_one(self.luminance, taps)) for taps in taps_of_sample] if self.mode == MODE_HEX
               else None)
        weights = self._weights(bary, lum)
        which = list(range(self.channels)) if which is None else list(which)
        out = []
        fetched = [gather_channels(self.plane, self.channels, taps, active, which) for taps in taps_of_sample]
        for k, c in enumerate(which):
            acc = weights[0] * fetched[0][k] + weights[1] * fetched[1][k] + weights[2] * fetched[2][k]
            if self.mode == MODE_HIST:
                acc = lut_lookup(self.lut, self.lut_size, c, self.g_min, self.step, acc)
            out.append(acc)
        return out

    def level_of_detail(self) -> DrLevelOfDetail:
        """The pyramid's :class:`DrLevelOfDetail` (builds the pyramid on first use)."""
        return self._pyramid()[1]

    def filtered_latent(self, u, v, lower, t=None, active=True):
        """:meth:`latent` over a footprint: list of ``C`` mi.Float.

        ``lower, t``: the footprint's lower pyramid level (``mi.UInt32``, or an ``int`` for all lanes)
        and the next level's weight (:meth:`level_of_detail` of the footprint in level-0 texels);
        ``t=None``: level ``lower`` alone (lanes whose weight is 0). As
        :meth:`dynbtf.synthesis.blending.LatticeBlending.filtered_latent` (the numba kernel
        ``filtered_lattice_blend``): every sample read from the footprint's two pyramid levels,
        blended per level (hex: the level's luminance; hist: the level's inverse table) and mixed.
        """
        mi = mi_module()
        pyramid, lod, luts = self._pyramid()
        bary, offsets, ((mu, mv), (fx, fy)), _ = self._samples(u, v, active)
        pw, ph, c = self.pw, self.ph, self.channels
        positions = [(mi.Float64(positive_mod(mu + ox, pw)) + fx, mi.Float64(positive_mod(mv + oy, ph)) + fy) for ox, oy in offsets]
        out = None
        for level, share, mask in level_shares(lower, t, lod.top, active):
            taps_of_sample = [pyramid.taps(level, x, y) for x, y in positions]
            lum = ([mi.Float64(gather_one(pyramid.luminances, taps, mask)) for taps in taps_of_sample]
                   if self.mode == MODE_HEX else None)
            weights = self._weights(bary, lum)
            fetched = [gather_channels(pyramid.flat, c, taps, mask) for taps in taps_of_sample]
            row = [weights[0] * fetched[0][k] + weights[1] * fetched[1][k] + weights[2] * fetched[2][k]
                   for k in range(c)]
            if self.mode == MODE_HIST:
                base = level * (c * self.lut_size)
                row = [lut_lookup(luts, self.lut_size, k, self.g_min, self.step, row[k], base) for k in range(c)]
            out = accumulate(out, row, share)
        return out

    def _pyramid(self):
        """``(DrPyramid, DrLevelOfDetail, per-level inverse tables or None)``, built on first use from ``pyramid_source``."""
        if self._filtering is None:
            self._filtering = filtering_tables(self.pyramid_source, luminances=self.mode == MODE_HEX,
                                                inverse_tables=self.mode == MODE_HIST)
        return self._filtering

    def features(self, u, v, active=True):
        """Synthesized positional features at ``(u, v)``: list of ``C`` mi.Float."""
        dr = drjit_module()
        latent = self.latent(u, v, active)
        if self.matrix is None:
            return latent
        out = []
        for j in range(self.matrix.shape[1]):
            acc = latent[0] * float(self.matrix[0, j]) + float(self.offset[j])
            for i in range(1, self.matrix.shape[0]):
                acc = dr.fma(latent[i], float(self.matrix[i, j]), acc)
            out.append(acc)
        return out


    def channel(self, u, v, index: int, active=True):
        """One synthesized feature channel (``mi.Float``) at ``(u, v)``: e.g. a parallax model's height.

        Only the latent channels the output map mixes into it are blended (as
        :meth:`dynbtf.synthesis.base.Synthesizer.channel`): that channel alone without an
        output map, or for a channel kept out of the decorrelation (hist's ``separate``: one
        channel's three bilinear reads and one inverse table); else every latent channel.
        """
        dr = drjit_module()
        if self.matrix is None:
            return self.latent(u, v, active, which=[index])[0]
        rows = [int(i) for i in np.nonzero(self.matrix[:, index])[0]]
        latent = self.latent(u, v, active, which=rows)
        acc = latent[0] * float(self.matrix[rows[0], index]) + float(self.offset[index])
        for x, i in zip(latent[1:], rows[1:]):
            acc = dr.fma(x, float(self.matrix[i, index]), acc)
        return acc


def form(synthesizer, guidance=None) -> DrLatticeBlending:
    """The Dr.Jit kernel of a :class:`~dynbtf.synthesis.blending.LatticeBlending` (its read plane, kernel arguments,
    output map and pyramid; ``guidance``: a :class:`~dynbtf.synthesis.guided_blending.drjit.DrGuidance`)."""
    kwargs = {k: to_host(v) for k, v in synthesizer.kernel_arguments().items()}
    matrix, offset = synthesizer.output_map()
    return DrLatticeBlending(to_host(synthesizer.prepared.plane), synthesizer.density, synthesizer.seed, synthesizer.mode,
                             matrix=None if matrix is None else to_host(matrix),
                             offset=None if offset is None else to_host(offset),
                             pyramid_source=synthesizer.pyramid, guidance=guidance, **kwargs)
