"""Dynamic synthesis of the positional plane, re-expressed in Dr.Jit for the rendering kernel.

Each class here mirrors one synthesizer of :mod:`dynbtf.synthesis` and reads its
precomputed tables (the exemplar plane after its preprocessing, transforms,
look-up tables) from the torch object, so that the kernel evaluates the same
function as :meth:`dynbtf.infinite_btf.SynthesizedBTF.features`.

Inputs are ``u, v`` (``mi.Float``, units of one exemplar repeat); outputs are
lists of ``C`` ``mi.Float`` (one per feature channel).
"""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from ...synthesis import hash as synthesis_hash
from ...synthesis import lattice as synthesis_lattice
from .drjit_ops import drjit_module, fetch_wrap, flat_array, gather_channels, mi_module, wrap01

__all__ = ["mix32", "fold_coordinate", "hash_vertex", "vertex_offsets", "triangle_lattice", "split_repeats",
           "lut_lookup", "DrTiling", "DrCellQuilting", "DrLatticeBlending", "DrGuidance", "DrLabelField",
           "DrLevelOfDetail", "DrPyramid",
           "make_dr_synthesizer"]


# ---------------------------------------------------------------- integer hash (dynbtf.synthesis.hash)
def mix32(x):
    """lowbias32 finalizer on ``mi.UInt32`` (arithmetic is modulo 2**32 natively)."""
    x = x ^ (x >> 16)
    x = x * synthesis_hash.MIX_MULTIPLIER_1
    x = x ^ (x >> 15)
    x = x * synthesis_hash.MIX_MULTIPLIER_2
    return x ^ (x >> 16)


def _words(k):
    """Low and high 32-bit words (``mi.UInt32``) of an ``mi.Int32`` sign-extended to 64 bits, or of an ``mi.Int64``."""
    mi, dr = mi_module(), drjit_module()
    if dr.type_v(k) == dr.VarType.Int64:  # the casts truncate; >> is arithmetic: Python's (k >> 32) & MASK32
        return mi.UInt32(k), mi.UInt32(k >> 32)
    return mi.UInt32(k), dr.select(k < 0, mi.UInt32(0xFFFFFFFF), mi.UInt32(0))


def fold_coordinate(h, k):
    """:func:`dynbtf.synthesis.hash.fold_coordinate`: the low then the high word of ``k`` (``mi.Int32`` or
    ``mi.Int64``) folded into the hash state ``h`` (``mi.UInt32`` or a Python int)."""
    lo, hi = _words(k)
    return mix32(mix32(h ^ lo) ^ hi)


def _seed_state(seed: int) -> int:
    """:func:`dynbtf.synthesis.hash.seed_state` of ``seed`` (a Python int: a literal of the kernel)."""
    return int(synthesis_hash.seed_state(int(seed)))


def hash_vertex(vx, vy, seed: int):
    """:func:`dynbtf.synthesis.hash.hash_vertex` for ``mi.Int32`` (or ``mi.Int64``) vertices: identical 32-bit values."""
    mi = mi_module()
    return fold_coordinate(fold_coordinate(mi.UInt32(_seed_state(seed)), vx), vy)


def vertex_offsets(vx, vy, seed: int, width: int, height: int):
    """Whole-texel offsets ``(ox, oy)`` (``mi.UInt32``) of lattice vertices, as :func:`dynbtf.synthesis.hash.vertex_offsets`."""
    h = hash_vertex(vx, vy, seed)
    return h % width, mix32(h ^ synthesis_hash.SECOND_STREAM) % height


# ---------------------------------------------------------------- triangle lattice (dynbtf.synthesis.lattice)
def split_repeats(x):
    """:func:`dynbtf.synthesis.lattice.split_uv` of one coordinate: ``x`` (``mi.Float`` or ``mi.Float64``)
    widened to float64 -> whole repeats (``mi.Float64``, an integer) and the fraction in ``[0, 1)``; exact."""
    mi, dr = mi_module(), drjit_module()
    x = mi.Float64(x)
    whole = dr.floor(x)
    frac = x - whole
    carry = frac >= 1.0  # never for exact arithmetic; guards -tiny inputs
    return dr.select(carry, whole + 1.0, whole), dr.select(carry, frac - 1.0, frac)


def triangle_lattice(u, v):
    """:func:`dynbtf.synthesis.lattice.triangle_lattice` in Dr.Jit.

    ``u, v`` (``mi.Float``) are widened to float64 and split into whole repeats and
    fractions exactly as the torch code does (``|u|, |v| < 2**27``), so the
    vertices are identical and the barycentrics agree to float64 rounding.

    Returns ``([(vx, vy)] * 3 as mi.Int32, [b0, b1, b2] as mi.Float64)``.
    """
    mi, dr = mi_module(), drjit_module()
    (wu, fu), (wv, fv) = split_repeats(u), split_repeats(v)
    # 2 sqrt(3) * whole_u as integer + fraction (hi/lo split of the constant, as in torch)
    p_hi = wu * synthesis_lattice.LATTICE_SCALE_HI
    p_whole = dr.floor(p_hi)
    p_frac = (p_hi - p_whole) + wu * synthesis_lattice.LATTICE_SCALE_LO
    carry = dr.floor(p_frac)
    iu_whole, iu_frac = p_whole + carry, p_frac - carry
    kx = iu_frac + synthesis_lattice.LATTICE_SCALE * fu - 2.0 * fv
    ky = 4.0 * fv
    bx, by = dr.floor(kx), dr.floor(ky)
    fx, fy = kx - bx, ky - by
    base_x = mi.Int32(bx) + mi.Int32(iu_whole) - 2 * mi.Int32(wv)
    base_y = mi.Int32(by) + 4 * mi.Int32(wv)
    z = 1.0 - fx - fy
    lower = z > 0.0
    one = dr.select(lower, mi.Int32(0), mi.Int32(1))
    verts = [(base_x + one, base_y + one),
             (base_x + one, base_y + (1 - one)),
             (base_x + (1 - one), base_y + one)]
    bary = [dr.select(lower, z, -z), dr.select(lower, fy, 1.0 - fy), dr.select(lower, fx, 1.0 - fx)]
    return verts, bary


def vertex_uv(vx, vy):
    """Position (``mi.Float64`` pair, exemplar repeats) of lattice vertices: hex-tile centres."""
    mi = mi_module()
    x, y = mi.Float64(vx), mi.Float64(vy)
    return (x + 0.5 * y) / synthesis_lattice.LATTICE_SCALE, y / 4.0


# ---------------------------------------------------------------- inverse transform LUT (dynbtf.synthesis.histogram)
def lut_lookup(table, size: int, channel: int, g_min: float, step: float, g, base=0):
    """:class:`dynbtf.synthesis.histogram.InverseLUT` lookup of one channel: linear interpolation, clamped.

    ``table`` is the flat ``(C, size)`` float32 table as ``mi.Float`` (or several such tables one after
    another, ``base`` (int or per-lane ``mi.UInt32``) the offset of the one to read); ``g`` an ``mi.Float``.
    """
    mi, dr = mi_module(), drjit_module()
    pos = dr.clip((g - g_min) / step, 0.0, size - 1.0)
    lo = dr.minimum(mi.UInt32(dr.floor(pos)), size - 2)
    t = pos - mi.Float(lo)
    base = base + channel * size
    x0 = dr.gather(mi.Float, table, base + lo)
    x1 = dr.gather(mi.Float, table, base + lo + 1)
    return x0 + t * (x1 - x0)


def _mod(k, n: int):
    """Non-negative ``k mod n`` for ``mi.Int32`` ``k`` (Python semantics, as numba's and torch's)."""
    dr = drjit_module()
    r = k % n
    return dr.select(r < 0, r + n, r)


# ---------------------------------------------------------------- footprint queries (dynbtf.synthesis.mip)
class DrLevelOfDetail:
    """:class:`dynbtf.synthesis.mip.LevelOfDetail` per lane: footprint (texels) -> lower level, next level's weight.

    Parameters
    ----------
    lod : LevelOfDetail
        The synthesizer's level of detail (level widths and blend band).
    """

    def __init__(self, lod) -> None:
        import numpy as np

        self.log_widths = [float(x) for x in np.log2(np.asarray(lod.widths, dtype=np.float64))]
        self.blend_band = float(lod.blend_band)
        self.top = len(self.log_widths) - 1

    def __call__(self, texels):
        """``texels`` (``mi.Float``/``mi.Float64``, level-0 texels) -> lower level (``mi.UInt32``), weight of the next (``mi.Float``)."""
        mi, dr = mi_module(), drjit_module()
        log_w, top = self.log_widths, self.top
        log_f = dr.log2(dr.maximum(mi.Float64(texels), 1.0))
        lower = mi.UInt32(0)
        lw_lower, lw_upper = mi.Float64(log_w[0]), mi.Float64(log_w[min(1, top)])
        for k in range(1, top + 1):  # the widths grow with the level: the last level at or below the footprint
            above = log_f >= log_w[k]
            lower = dr.select(above, k, lower)
            lw_lower = dr.select(above, log_w[k], lw_lower)
            lw_upper = dr.select(above, log_w[min(k + 1, top)], lw_upper)
        span = lw_upper - lw_lower
        t = dr.select(span > 0.0, (log_f - lw_lower) / dr.select(span > 0.0, span, 1.0), 0.0)
        if self.blend_band < 1.0:  # the two levels are mixed only in a band around the octave's middle
            t = (t - 0.5) / self.blend_band + 0.5
            up = t >= 1.0
            lower = dr.select(up, dr.minimum(lower + 1, top), lower)
            t = dr.select(up, 0.0, t)
        return lower, mi.Float(dr.clip(t, 0.0, 1.0))

    def nearest(self, lower, weight):
        """The level nearest the footprint (``mi.UInt32``): :meth:`dynbtf.infinite_btf.SynthesizedBTF.nearest_level`."""
        dr = drjit_module()
        return lower + dr.select(weight >= 0.5, 1, 0)


def _level_shares(lower, t, top: int, active):
    """``(level, share, mask)`` of each pyramid level a footprint reads: ``lower`` alone (``t=None``), or
    ``lower`` with ``1 - t`` and the next level with ``t`` (its reads masked where ``t`` is 0)."""
    dr = drjit_module()
    if t is None:
        return [(lower, None, active)]
    upper = min(lower + 1, top) if isinstance(lower, int) else dr.minimum(lower + 1, top)
    return [(lower, 1.0 - t, active), (upper, t, active & (t > 0.0))]


def _accumulate(out, row, share):
    """``out + share * row`` per channel (``out=None``: nothing yet; ``share=None``: 1)."""
    if share is not None:
        row = [share * x for x in row]
    return row if out is None else [o + x for o, x in zip(out, row)]


def _wrap_small(k, n):
    """``k mod n`` (``mi.UInt32``) for ``mi.Int32`` ``k`` in ``[-n, 3 n)`` and per-lane ``n``, without a division.

    (An integer division by a per-lane ``n`` traps on lanes that hold no data, e.g. a SIMD packet's tail.)
    """
    mi, dr = mi_module(), drjit_module()
    for _ in range(2):
        k = dr.select(k >= n, k - n, k)
    return mi.UInt32(dr.select(k < 0, k + n, k))


class DrPyramid:
    """An area pyramid (:func:`dynbtf.synthesis.mip.area_pyramid`) in one flat buffer, read at a level per lane.

    Parameters
    ----------
    levels : list of float32 ``(H_l, W_l, C)``
        Level 0 (the read plane) first.
    luminances : list of float32 ``(H_l, W_l)``, optional
        A one-channel pyramid of the same sizes (hex's luminance).
    """

    def __init__(self, levels, luminances=None) -> None:
        import numpy as np

        mi = mi_module()
        arrays = [np.asarray(t, dtype=np.float32) for t in levels]
        self.height, self.width, self.channels = (int(x) for x in arrays[0].shape)
        #: (first texel, width, height) of each level, as Python ints (literals) and as per-lane gather sources
        self.level_sizes = []
        start = 0
        for t in arrays:
            self.level_sizes.append((start, int(t.shape[1]), int(t.shape[0])))
            start += int(t.shape[0] * t.shape[1])
        starts, widths, heights = (np.array(column, dtype=np.uint32) for column in zip(*self.level_sizes))
        self.flat = flat_array(mi, np.concatenate([t.reshape(-1) for t in arrays]))
        self.starts, self.widths, self.heights = mi.UInt32(starts), mi.UInt32(widths), mi.UInt32(heights)
        self.luminances = None if luminances is None else flat_array(
            mi, np.concatenate([np.asarray(t, dtype=np.float32).reshape(-1) for t in luminances]))

    def taps(self, level, x, y):
        """Bilinear taps of ``level`` (``mi.UInt32``, or an ``int``) at level-0 texel positions ``x, y`` (``mi.Float64``).

        Level-0 texel ``[i, j]`` covers ``[j, j + 1) x [i, i + 1)``; positions in ``[0, 3 W)``; the
        level wraps. Returns 4 ``(texel index into the flat buffer, weight)`` as
        :func:`~dynbtf.render.mitsuba.drjit_ops.bilinear_taps` (the numba kernel's ``_level_tap``).
        """
        mi, dr = mi_module(), drjit_module()
        if isinstance(level, int):  # one level for all lanes: its sizes are literals
            start, mw, mh = self.level_sizes[level]
            px = x * (mw / self.width) - 0.5
            py = y * (mh / self.height) - 0.5
        else:
            start = dr.gather(mi.UInt32, self.starts, level)
            mw = dr.gather(mi.UInt32, self.widths, level)
            mh = dr.gather(mi.UInt32, self.heights, level)
            px = x * (mi.Float64(mw) / self.width) - 0.5
            py = y * (mi.Float64(mh) / self.height) - 0.5
        return periodic_taps(px, py, mw, mh, start)


def periodic_taps(px, py, width, height, start=0):
    """Bilinear taps of a periodic ``height x width`` plane at texel coordinates ``px, py`` (``mi.Float64``, texel
    ``[i, j]`` centred at ``(j, i)``, within ``[-W, 3 W)``); ``width, height``: ints, or ``mi.UInt32`` per lane.

    Returns 4 ``(texel index + start, weight: mi.Float)`` as :func:`~dynbtf.render.mitsuba.drjit_ops.bilinear_taps`
    (the numba kernels' fetches: float64 positions, float32 weights).
    """
    mi, dr = mi_module(), drjit_module()
    cols, rows = (width, height) if isinstance(width, int) else (mi.Int32(width), mi.Int32(height))
    fx, fy = dr.floor(px), dr.floor(py)
    tx, ty = mi.Float(px - fx), mi.Float(py - fy)
    c0, r0 = _wrap_small(mi.Int32(fx), cols), _wrap_small(mi.Int32(fy), rows)
    c1 = dr.select(c0 + 1 == width, 0, c0 + 1)
    r1 = dr.select(r0 + 1 == height, 0, r0 + 1)
    return [(start + r0 * width + c0, (1.0 - tx) * (1.0 - ty)), (start + r0 * width + c1, tx * (1.0 - ty)),
            (start + r1 * width + c0, (1.0 - tx) * ty), (start + r1 * width + c1, tx * ty)]


def _filtering_tables(pyramid_source, *, luminances: bool = False, inverse_tables: bool = False):
    """What a Dr.Jit synthesizer's footprint queries read, from its torch twin's ``pyramid()`` (``pyramid_source``).

    Returns ``(DrPyramid, DrLevelOfDetail, the per-level inverse tables as one flat mi.Float or None)``;
    ``luminances``: with the luminance pyramid (hex); ``inverse_tables``: with the tables (hist).
    """
    if pyramid_source is None:
        raise InputError("footprint queries need the synthesizer's pyramid (pyramid_source)")
    pyr = pyramid_source()

    def host(tensors):
        return [t.detach().cpu().numpy() for t in tensors]

    pyramid = DrPyramid(host(pyr["levels"]), host(pyr["luminances"]) if luminances else None)
    tables = flat_array(mi_module(), pyr["luts_numpy"]) if inverse_tables else None
    return pyramid, DrLevelOfDetail(pyr["lod"]), tables


class DrLatticeBlending:
    """Lattice blending of three hashed exemplar samples: :func:`dynbtf.synthesis.kernels.lattice_blend` in Dr.Jit.

    The same computation, step for step: the triangle lattice in float64, the
    vertices' integer hash, whole-texel offsets wrapped on the (preprocessed)
    plane, one shared sub-texel bilinear footprint, then per mode

    * ``"linear"``: weights = barycentrics;
    * ``"hist"``: ``w_i = b_i^gamma / sum``, variance-preserving scale
      ``1 / sqrt(sum w_i^2)`` (Gaussian space, mean 0), then the inverse
      transform per channel through the :class:`~dynbtf.synthesis.histogram.InverseLUT`;
    * ``"hex"``: ``w_i = (1 - beta + beta lum_i) b_i^7`` normalized, contrast gain
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
    mode : {"linear", "hist", "hex"}
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

    def __init__(self, plane, density, seed: int, mode: str, *, gamma: float = 1.0, beta: float = 0.0,
                 gain_k: float = 1.0, luminance=None, lut=None, g_min: float = 0.0, step: float = 1.0,
                 matrix=None, offset=None, pyramid_source=None, guidance=None) -> None:
        import numpy as np

        mi = mi_module()
        self.pyramid_source = pyramid_source
        self._filtering = None
        if mode not in ("linear", "hist", "hex"):
            raise InputError(f"lattice blending mode: expected linear, hist or hex, got {mode!r}")
        plane = np.asarray(plane, dtype=np.float32)
        self.ph, self.pw, self.channels = (int(x) for x in plane.shape)
        self.plane = flat_array(mi, plane)
        self.density = (int(density[0]), int(density[1]))
        self.seed = int(seed) & 0xFFFFFFFF
        self.mode = mode
        self.gamma, self.beta, self.gain_k = float(gamma), float(beta), float(gain_k)
        self.luminance = flat_array(mi, luminance) if luminance is not None else None
        if mode == "hex" and luminance is None:
            raise InputError("hex blending needs the luminance plane")
        if mode == "hist":
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
        if self.mode == "linear":
            return [mi.Float(b) for b in bary]
        if self.mode == "hist":
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
        mu = _mod(_mod(mi.Int32(wu), pw) * (dw % pw), pw)
        mv = _mod(_mod(mi.Int32(wv), ph) * (dh % ph), ph)
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
            ca, cb = _mod(xi + ox, pw), _mod(xi + ox + 1, pw)
            ra, rb = _mod(yi + oy, ph), _mod(yi + oy + 1, ph)
            idx = (mi.UInt32(ra * pw + ca), mi.UInt32(ra * pw + cb), mi.UInt32(rb * pw + ca), mi.UInt32(rb * pw + cb))
            taps_of_sample.append(list(zip(idx, wts)))
        lum = ([mi.Float64(gather_one(self.luminance, taps)) for taps in taps_of_sample] if self.mode == "hex"
               else None)
        weights = self._weights(bary, lum)
        which = list(range(self.channels)) if which is None else list(which)
        out = []
        fetched = [gather_channels(self.plane, self.channels, taps, active, which) for taps in taps_of_sample]
        for k, c in enumerate(which):
            acc = weights[0] * fetched[0][k] + weights[1] * fetched[1][k] + weights[2] * fetched[2][k]
            if self.mode == "hist":
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
        positions = [(mi.Float64(_mod(mu + ox, pw)) + fx, mi.Float64(_mod(mv + oy, ph)) + fy) for ox, oy in offsets]
        out = None
        for level, share, mask in _level_shares(lower, t, lod.top, active):
            taps_of_sample = [pyramid.taps(level, x, y) for x, y in positions]
            lum = ([mi.Float64(gather_one(pyramid.luminances, taps, mask)) for taps in taps_of_sample]
                   if self.mode == "hex" else None)
            weights = self._weights(bary, lum)
            fetched = [gather_channels(pyramid.flat, c, taps, mask) for taps in taps_of_sample]
            row = [weights[0] * fetched[0][k] + weights[1] * fetched[1][k] + weights[2] * fetched[2][k]
                   for k in range(c)]
            if self.mode == "hist":
                base = level * (c * self.lut_size)
                row = [lut_lookup(luts, self.lut_size, k, self.g_min, self.step, row[k], base) for k in range(c)]
            out = _accumulate(out, row, share)
        return out

    def _pyramid(self):
        """``(DrPyramid, DrLevelOfDetail, per-level inverse tables or None)``, built on first use from ``pyramid_source``."""
        if self._filtering is None:
            self._filtering = _filtering_tables(self.pyramid_source, luminances=self.mode == "hex",
                                                inverse_tables=self.mode == "hist")
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


class DrLabelField:
    """:class:`dynbtf.synthesis.guided_blending.LabelField` in Dr.Jit: a label image over exemplar repeats, nearest
    texel, repeated (an exact remainder: the same labels at any distance) or clamped."""

    def __init__(self, field) -> None:
        mi = mi_module()
        image = np.asarray(field.image, dtype=np.int32)
        self.h, self.w = (int(x) for x in image.shape)
        self.image = mi.Int32(image.reshape(-1))
        self.size, self.repeat = float(field.size), field.wrap == "repeat"

    def __call__(self, u, v, active=True):
        """The label (``mi.Int32``) at ``(u, v)`` exemplar repeats (``mi.Float64``)."""
        mi, dr = mi_module(), drjit_module()
        size, h, w = self.size, self.h, self.w
        pu, pv = mi.Float64(u), mi.Float64(v)
        if self.repeat:
            pu, pv = pu - dr.floor(pu / size) * size, pv - dr.floor(pv / size) * size
        col, row = mi.Int32(dr.floor(pu / size * w)), mi.Int32(dr.floor(pv / size * h))
        if self.repeat:
            col, row = _mod(col, w), _mod(row, h)
        else:
            col, row = dr.clip(col, 0, w - 1), dr.clip(row, 0, h - 1)
        return dr.gather(mi.Int32, self.image, mi.UInt32(row * w + col), active)


class DrGuidance:
    """Exemplar guidance of a lattice blend in Dr.Jit: :meth:`dynbtf.synthesis.guided_blending._Guidance` (and the
    numba kernel's search), the candidates tried in the same order.

    Parameters
    ----------
    seeds : list of int
        The candidates' seeds (:func:`~dynbtf.synthesis.guided_blending.candidate_seed`; candidate 0 the synthesis
        seed).
    labels : int ``(H', W')``
        The read plane's labels.
    target : :class:`~dynbtf.synthesis.guided_blending.LabelField`
        The label each point should show, over exemplar repeats.
    softness : float
        Barycentric-weight factor of samples that found no candidate of the target's label.
    """

    def __init__(self, seeds, labels, target, softness: float) -> None:
        mi = mi_module()
        labels = np.asarray(labels, dtype=np.int32)
        self.seeds = [int(x) for x in seeds]
        self.labels = mi.Int32(labels.reshape(-1))
        self.target = DrLabelField(target)
        self.softness = float(softness)

    def steer(self, blend, u, v, verts, bary, offsets, xi, yi, active):
        """Each sample's offset (the first candidate whose bilinear footprint carries the target label, else
        candidate 0's) and the barycentrics with unmatched samples' weight times ``softness``."""
        mi, dr = mi_module(), drjit_module()
        pw, ph = blend.pw, blend.ph
        target = self.target(u, v, active)
        chosen, matched = [], []
        for (vx, vy), first in zip(verts, offsets):
            ox, oy = first
            found = dr.zeros(mi.Bool, dr.width(xi))
            for j, seed in enumerate(self.seeds):
                cx, cy = first if j == 0 else blend._offsets(vx, vy, seed)
                ca, cb = _mod(xi + cx, pw), _mod(xi + cx + 1, pw)
                ra, rb = _mod(yi + cy, ph), _mod(yi + cy + 1, ph)
                inside = mi.Bool(active)  # a new mask: the in-place updates below must not touch the caller's
                for r, c in ((ra, ca), (ra, cb), (rb, ca), (rb, cb)):
                    inside = inside & (dr.gather(mi.Int32, self.labels, mi.UInt32(r * pw + c), active) == target)
                hit = inside & ~found
                ox, oy = dr.select(hit, cx, ox), dr.select(hit, cy, oy)
                found = found | hit
            chosen.append((ox, oy))
            matched.append(found)
        any_match = matched[0] | matched[1] | matched[2]
        steered = [dr.select(m | ~any_match, b, b * self.softness) for b, m in zip(bary, matched)]
        return chosen, steered


def gather_one(buffer, taps, active=True):
    """Bilinear combination of a one-channel buffer over ``taps`` (as :func:`~dynbtf.render.mitsuba.drjit_ops.gather_channels`)."""
    return gather_channels(buffer, 1, taps, active)[0]


class DrTiling:
    """Plain periodic tiling: a bilinear, wrapped fetch of the exemplar plane ``(H, W, C)``.

    ``pyramid_source`` (optional) returns the plane's pyramid (``levels``, ``lod``) for
    :meth:`filtered_latent`, on its first call.
    """

    def __init__(self, plane, pyramid_source=None) -> None:
        mi = mi_module()
        self.pyramid_source = pyramid_source
        self._filtering = None
        plane = plane.detach().float().cpu().numpy() if hasattr(plane, "detach") else plane
        self.size = (int(plane.shape[0]), int(plane.shape[1]))
        self.channels = int(plane.shape[2])
        self.plane = flat_array(mi, plane)

    def features(self, u, v, active=True):
        """The plane's features at ``(u, v)`` (``mi.Float`` or ``mi.Float64``): list of ``C`` mi.Float."""
        return fetch_wrap(self.plane, self.size, self.channels, u, v, active)

    def channel(self, u, v, index: int, active=True):
        """One feature channel (``mi.Float``) at ``(u, v)``."""
        return fetch_wrap(self.plane, self.size, self.channels, u, v, active, which=[index])[0]

    def _pyramid(self):
        """``(DrPyramid, DrLevelOfDetail, None)``, built on first use from ``pyramid_source``."""
        if self._filtering is None:
            self._filtering = _filtering_tables(self.pyramid_source)
        return self._filtering

    def level_of_detail(self) -> DrLevelOfDetail:
        """The exemplar pyramid's :class:`DrLevelOfDetail` (builds the pyramid on first use)."""
        return self._pyramid()[1]

    def texel_positions(self, u, v, active=True):
        """Where the point query at ``(u, v)`` reads the plane: level-0 texel positions ``x, y`` (``mi.Float64``,
        in ``[0, W) x [0, H)``); footprint queries read the pyramid there (:meth:`filtered_latent`)."""
        mi = mi_module()
        h, w = self.size
        return mi.Float64(wrap01(mi.Float64(u))) * w, mi.Float64(wrap01(mi.Float64(v))) * h

    def filtered_latent(self, u, v, lower, t=None, active=True):
        """The plane averaged over a footprint (``lower`` level, next level's weight ``t``: :meth:`level_of_detail`;
        as :meth:`DrLatticeBlending.filtered_latent`).

        :func:`dynbtf.synthesis.mip.trilinear_fetch` at :meth:`texel_positions`: list of ``C`` mi.Float.
        """
        pyramid, lod, _ = self._pyramid()
        x, y = self.texel_positions(u, v, active)
        out = None
        for level, share, mask in _level_shares(lower, t, lod.top, active):
            out = _accumulate(out, gather_channels(pyramid.flat, pyramid.channels, pyramid.taps(level, x, y), mask),
                              share)
        return out


class DrCellQuilting(DrTiling):
    """Lattice-aligned cell quilting: :class:`dynbtf.synthesis.cell_quilting.CellQuilting` (its numba kernel
    :func:`~dynbtf.synthesis.kernels.cell_quilt`) in Dr.Jit.

    The same computation, step for step: ``u, v`` widened to float64 and split into whole repeats and
    fractions (:func:`split_repeats`), the texel and its cell within the repeat, the cell's index as an
    ``mi.Int64`` (``whole * n + column``: exact for any ``uv`` below ``2**52`` repeats), the offset index
    ``hash(cell) mod K`` (:func:`fold_coordinate` on the index's two 32-bit words: the library's bits); near
    a cell edge (within the margin) the neighbour's index and one cut-table entry decide whether the point
    belongs to the neighbour (or, past both cuts of a corner, to the diagonal cell); then one bilinear,
    periodic fetch of the exemplar at the shifted position. Footprint queries read the exemplar's pyramid
    at that position (:meth:`DrTiling.filtered_latent` at :meth:`texel_positions`).

    Per query: four hashes (the own cell, the nearer neighbour along ``u``, along ``v``, and the diagonal
    between them; each lane needs at most the band's neighbours, so the two columns share their first
    fold), two cut-table gathers and one fetch.

    Parameters
    ----------
    plane : ``(H, W, C)``
        The exemplar.
    offsets : int ``(K, 2)``
        The copies' texel offsets ``(dx, dy)``; ``cells``: ``(nx, ny)`` per repeat; ``margin``: ``(mx, my)`` texels;
    vertical_cuts, horizontal_cuts : int ``(nx, ny, K, K, T_y)``, ``(nx, ny, K, K, T_x)``
        As :class:`~dynbtf.synthesis.cell_quilting.CellTables`.
    seed : int
    pyramid_source : callable, optional
        As :class:`DrTiling`.
    guidance : (cell_labels, target), optional
        Guided struct (:class:`~dynbtf.synthesis.guided_blending.GuidedCellQuilting`): each cell's content label
        under each offset ``(nx, ny, K)`` and the target :class:`~dynbtf.synthesis.guided_blending.LabelField`;
        a cell takes, from its hashed offset on, the first whose content carries the target's label at the
        cell's centre (footprint queries read the pyramid at the chosen cells' positions, as unguided).
    """

    def __init__(self, plane, offsets, cells, margin, vertical_cuts, horizontal_cuts, seed: int,
                 pyramid_source=None, guidance=None) -> None:
        import numpy as np

        super().__init__(plane, pyramid_source)
        mi = mi_module()
        h, w = self.size
        self.cells = (int(cells[0]), int(cells[1]))
        self.margin = (int(margin[0]), int(margin[1]))
        nx, ny = self.cells
        self.cell_size = (w // nx, h // ny)
        offsets = np.asarray(offsets.detach().cpu() if hasattr(offsets, "detach") else offsets, dtype=np.int64)
        self.count = int(offsets.shape[0])

        def table(t, last):
            t = np.asarray(t.detach().cpu() if hasattr(t, "detach") else t, dtype=np.int32)
            if t.shape != (nx, ny, self.count, self.count, last):
                raise InputError(f"cell quilting: a cut table of shape {t.shape}, expected "
                                 f"{(nx, ny, self.count, self.count, last)}")
            return mi.Int32(np.ascontiguousarray(t).ravel())

        tx, ty = self.cell_size
        if w % nx or h % ny or not (0 < 2 * self.margin[0] <= tx and 0 < 2 * self.margin[1] <= ty):
            raise InputError(f"cell quilting: cells {self.cells} with margins {self.margin} do not fit the {h}x{w} plane")
        self.vertical = table(vertical_cuts, ty)
        self.horizontal = table(horizontal_cuts, tx)
        self.offset_x = mi.Float64(offsets[:, 0].astype(np.float64))
        self.offset_y = mi.Float64(offsets[:, 1].astype(np.float64))
        self.state = _seed_state(int(seed) & 0xFFFFFFFF)
        self.guidance = None
        if guidance is not None:
            cell_labels, target = guidance
            cell_labels = np.asarray(cell_labels, dtype=np.int32)
            if cell_labels.shape != (nx, ny, self.count):
                raise InputError(f"cell quilting: cell labels of shape {cell_labels.shape}, expected "
                                 f"{(nx, ny, self.count)}")
            self.guidance = (mi.Int32(np.ascontiguousarray(cell_labels).ravel()), DrLabelField(target))

    @classmethod
    def of(cls, synthesizer) -> "DrCellQuilting":
        """The twin of a :class:`~dynbtf.synthesis.cell_quilting.CellQuilting` (its exemplar and tables; guided
        struct's cell labels and target)."""
        t = synthesizer.prepared
        guidance = None
        if getattr(synthesizer, "target", None) is not None:
            guidance = (synthesizer.cell_labels.cpu().numpy(), synthesizer.target)
        return cls(synthesizer.exemplar, t.offsets, t.cells, t.margin, t.vertical_cuts, t.horizontal_cuts,
                   synthesizer.seed, pyramid_source=synthesizer.pyramid, guidance=guidance)

    def _guided(self, cell_x, cell_y, hashed, active):
        """A cell's offset index under guidance: from the hashed one (``mi.UInt32``) on, the first whose content in
        the cell carries the target's label at the cell's centre, else the hashed one (the numba kernel's
        ``_guided_cell_choice``)."""
        if self.guidance is None:
            return hashed
        mi, dr = mi_module(), drjit_module()
        labels, target = self.guidance
        nx, ny = self.cells
        k = self.count
        wanted = target((mi.Float64(cell_x) + 0.5) / nx, (mi.Float64(cell_y) + 0.5) / ny, active)
        i, j = cell_x % nx, cell_y % ny
        i, j = mi.UInt32(dr.select(i < 0, i + nx, i)), mi.UInt32(dr.select(j < 0, j + ny, j))
        chosen, found = mi.UInt32(hashed), dr.zeros(mi.Bool, dr.width(hashed))
        for step in range(k):
            candidate = (hashed + step) % k
            hit = (dr.gather(mi.Int32, labels, (i * ny + j) * k + candidate, active) == wanted) & ~found
            chosen = dr.select(hit, candidate, chosen)
            found = found | hit
        return chosen

    def read_positions(self, u, v, active=True):
        """:meth:`dynbtf.synthesis.cell_quilting.CellQuilting.read_positions`: texel positions ``x, y``
        (``mi.Float64`` in ``[0, W) x [0, H)``) on the exemplar and the chosen offset index (``mi.UInt32``)."""
        mi, dr = mi_module(), drjit_module()
        h, w = self.size
        nx, ny = self.cells
        tx, ty = self.cell_size
        mx, my = self.margin
        k = self.count
        (whole_u, frac_u), (whole_v, frac_v) = split_repeats(u), split_repeats(v)
        pos_x, pos_y = frac_u * w, frac_v * h
        texel_x = dr.minimum(mi.Int32(dr.floor(pos_x)), w - 1)
        texel_y = dr.minimum(mi.Int32(dr.floor(pos_y)), h - 1)
        if k == 1:  # one copy: the exemplar itself everywhere
            return pos_x, pos_y, mi.UInt32(0)
        col, row = texel_x // tx, texel_y // ty
        local_x, local_y = texel_x - col * tx, texel_y - row * ty
        cell_x = mi.Int64(whole_u) * nx + mi.Int64(col)
        cell_y = mi.Int64(whole_v) * ny + mi.Int64(row)
        # the band a lane is in (at most one per axis: 2 margin <= cell side) names its neighbour's index
        left, right = local_x < mx, local_x >= tx - mx
        lower, upper = local_y < my, local_y >= ty - my
        near_x = cell_x + dr.select(left, mi.Int64(-1), mi.Int64(1))
        near_y = cell_y + dr.select(lower, mi.Int64(-1), mi.Int64(1))
        column, column_near = fold_coordinate(self.state, cell_x), fold_coordinate(self.state, near_x)
        own = self._guided(cell_x, cell_y, fold_coordinate(column, cell_y) % k, active)
        across_x = self._guided(near_x, cell_y, fold_coordinate(column_near, cell_y) % k, active)
        across_y = self._guided(cell_x, near_y, fold_coordinate(column, near_y) % k, active)
        diagonal = self._guided(near_x, near_y, fold_coordinate(column_near, near_y) % k, active)
        # the cut of the edge between the lane's cell and that neighbour: [edge, row/column, first, second, texel]
        edge = dr.select(left, col, dr.select(col + 1 == nx, 0, col + 1))
        first, second = dr.select(left, across_x, own), dr.select(left, own, across_x)
        index = (((mi.UInt32(edge) * ny + mi.UInt32(row)) * k + first) * k + second) * ty + mi.UInt32(local_y)
        cut = dr.gather(mi.Int32, self.vertical, index, active & (left | right))
        crossed_x = (left & (local_x < cut)) | (right & (local_x - tx >= cut))
        edge = dr.select(lower, row, dr.select(row + 1 == ny, 0, row + 1))
        first, second = dr.select(lower, across_y, own), dr.select(lower, own, across_y)
        index = (((mi.UInt32(col) * ny + mi.UInt32(edge)) * k + first) * k + second) * tx + mi.UInt32(local_x)
        cut = dr.gather(mi.Int32, self.horizontal, index, active & (lower | upper))
        crossed_y = (lower & (local_y < cut)) | (upper & (local_y - ty >= cut))
        chosen = dr.select(crossed_x, dr.select(crossed_y, diagonal, across_x), dr.select(crossed_y, across_y, own))
        x = pos_x + dr.gather(mi.Float64, self.offset_x, chosen, active)
        y = pos_y + dr.gather(mi.Float64, self.offset_y, chosen, active)
        return dr.select(x >= w, x - w, x), dr.select(y >= h, y - h, y), chosen

    def texel_positions(self, u, v, active=True):
        """Where the point query at ``(u, v)`` reads the exemplar (:meth:`read_positions` without the index)."""
        x, y, _ = self.read_positions(u, v, active)
        return x, y

    def _fetch(self, u, v, active, which=None):
        h, w = self.size
        x, y = self.texel_positions(u, v, active)
        return gather_channels(self.plane, self.channels, periodic_taps(x - 0.5, y - 0.5, w, h), active, which)

    def features(self, u, v, active=True):
        """The synthesized features at ``(u, v)`` (``mi.Float`` or ``mi.Float64``): list of ``C`` mi.Float."""
        return self._fetch(u, v, active)

    def channel(self, u, v, index: int, active=True):
        """One feature channel (``mi.Float``) at ``(u, v)``."""
        return self._fetch(u, v, active, which=[index])[0]


def make_dr_synthesizer(synthesizer):
    """The Dr.Jit twin of a :class:`dynbtf.synthesis.base.Synthesizer` (same tables, same function).

    Supported: plain tiling, every lattice-blending method (``linear``, ``hist``, ``hex``) and cell
    quilting (``struct``); quilting is not dynamic and has no kernel form.
    """
    from ...synthesis.blending import LatticeBlending
    from ...synthesis.cell_quilting import CellQuilting
    from ...synthesis.kernels import MODE_HEX, MODE_HIST, MODE_LINEAR

    def host(x):
        return x.detach().cpu().numpy() if hasattr(x, "detach") else x

    if not getattr(synthesizer, "portable", True):
        raise InputError(f"synthesis method {synthesizer.name!r} has no Dr.Jit form yet; render it with "
                         "SynthesizedBTF (dynbtf synth) or choose another method")
    if isinstance(synthesizer, LatticeBlending):
        mode = {MODE_LINEAR: "linear", MODE_HIST: "hist", MODE_HEX: "hex"}[synthesizer.mode]
        kwargs = {k: host(v) for k, v in synthesizer.kernel_arguments().items()}
        matrix, offset = synthesizer.output_map()
        guidance = None
        if getattr(synthesizer, "target", None) is not None:  # exemplar guidance (guided_blending)
            from ...synthesis.guided_blending import candidate_seed

            guidance = DrGuidance([candidate_seed(synthesizer.seed, j) for j in range(synthesizer.candidates)],
                                  host(synthesizer.labels), synthesizer.target, synthesizer.softness)
        return DrLatticeBlending(host(synthesizer.prepared.plane), synthesizer.density, synthesizer.seed, mode,
                                 matrix=None if matrix is None else host(matrix),
                                 offset=None if offset is None else host(offset),
                                 pyramid_source=synthesizer.pyramid, guidance=guidance, **kwargs)
    if isinstance(synthesizer, CellQuilting):
        return DrCellQuilting.of(synthesizer)
    if getattr(synthesizer, "name", None) == "tile":
        return DrTiling(tiling_plane(synthesizer), pyramid_source=synthesizer.pyramid)
    raise InputError(f"synthesis method {getattr(synthesizer, 'name', synthesizer)!r} has no Dr.Jit form; "
                     f"expected one of ['tile', 'linear', 'hist', 'hex', 'struct']")


def tiling_plane(synthesizer):
    """The plane a tiling synthesizer repeats (its exemplar)."""
    return synthesizer.exemplar
