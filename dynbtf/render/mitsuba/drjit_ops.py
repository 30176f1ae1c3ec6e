"""Dr.Jit translations of dynbtf's evaluation primitives, for use inside a Mitsuba kernel.

Everything here mirrors a torch function of the package operation by operation, so
that a renderer evaluates exactly what :class:`dynbtf.infinite_btf.SynthesizedBTF`
evaluates:

==========================================  ============================================
Dr.Jit (this module)                        torch / NumPy reference
==========================================  ============================================
:func:`half_diff`                           :func:`dynbtf.conventions.half_diff_from_view_light`
:func:`angular_coords`                      :func:`dynbtf.conventions.angular_plane_coords`
:func:`fetch_angular`                       :func:`dynbtf.texture.fetch_angular`
:class:`DrDecoder`                          :class:`dynbtf.representations.triple_plane.Decoder`
:class:`DrTriplePlane`                      :class:`dynbtf.representations.triple_plane.TriplePlane`
:class:`DrNeuMIP`                           :class:`dynbtf.representations.neumip.NeuMIP`
:func:`march_visible_uv`                    :func:`dynbtf.representations.parallax.march_visible_uv`
:class:`DrParallaxTriplePlane`              :class:`dynbtf.representations.parallax.ParallaxTriplePlane`
==========================================  ============================================

The array operations they are written with (flat buffers, bilinear gathers, the periodic fetch of
:func:`dynbtf.texture.fetch_wrap`) are the Dr.Jit substrate, :mod:`dynbtf.jit`; each synthesis method's kernel
is in its own package (``dynbtf/synthesis/<method>/drjit.py``).

Conventions
-----------
* Dr.Jit types come from the active Mitsuba variant (``mi.Float``, ``mi.UInt32``...);
  a variant must be set before calling anything here. Nothing is specific to the
  LLVM backend: the same code traces into CUDA kernels.
* A vector of ``C`` feature channels is a Python ``list`` of ``C`` ``mi.Float``
  arrays (one per channel, structure-of-arrays) so that the decoder unrolls into
  scalar fused multiply-adds with the weights baked in as literals.
* Planes are stored as flat, channels-last ``mi.Float`` buffers (texel ``[i, j]``,
  channel ``c`` at ``(i * W + j) * C + c``) and fetched with ``dr.gather``: a
  manual bilinear fetch is bit-for-bit the same arithmetic on every backend,
  whereas hardware texture units interpolate with reduced precision.
"""

from __future__ import annotations

import math

import numpy as np

from ...jit import bilinear_taps, drjit_module, flat_array, gather_channels, mi_module, wrap01

__all__ = [
    "half_diff",
    "angular_coords",
    "fetch_angular",
    "DrDecoder",
    "DrTriplePlane",
    "DrNeuMIP",
    "march_visible_uv",
    "DrParallaxTriplePlane",
    "DR_REPRESENTATIONS",
    "check_renderable",
    "dr_representation",
]


def half_diff(wv, wl):
    """Rusinkiewicz ``(h, d)`` of local directions ``wv, wl`` (``mi.Vector3f``).

    Same arithmetic as :func:`dynbtf.conventions.half_diff_from_view_light`,
    including the fall-back to the normal for exactly opposite directions and the
    pole handling of ``phi_h``.
    """
    mi, dr = mi_module(), drjit_module()
    s = wv + wl
    n2 = dr.squared_norm(s)
    s = dr.select(n2 < 1e-24, mi.Vector3f(0.0, 0.0, 1.0), s)
    h = s / dr.maximum(dr.norm(s), 1e-30)
    cos_t = dr.clip(h.z, -1.0, 1.0)
    sin_t = dr.sqrt(dr.maximum(1.0 - cos_t * cos_t, 0.0))
    rxy = dr.sqrt(h.x * h.x + h.y * h.y)
    pole = rxy < 1e-12
    safe = dr.select(pole, 1.0, rxy)
    cos_p = dr.select(pole, 1.0, h.x / safe)
    sin_p = dr.select(pole, 0.0, h.y / safe)
    # d = R_y(-theta_h) R_z(-phi_h) w_light
    x1 = cos_p * wl.x + sin_p * wl.y
    y1 = -sin_p * wl.x + cos_p * wl.y
    z1 = wl.z
    d = mi.Vector3f(cos_t * x1 - sin_t * z1, y1, sin_t * x1 + cos_t * z1)
    return h, d


def angular_coords(w):
    """``(s, t)`` angular-plane coordinates of unit vectors ``w``: ``theta/90deg`` clamped, ``phi/360deg`` wrapped."""
    dr = drjit_module()
    theta = dr.acos(dr.clip(w.z, -1.0, 1.0)) * (180.0 / math.pi)
    from ...conventions import POLE_RADIUS

    # phi = 0 at the poles, as dynbtf.conventions.direction_to_spherical
    pole = w.x * w.x + w.y * w.y < POLE_RADIUS ** 2
    phi = dr.select(pole, 0.0, dr.atan2(w.y, w.x) * (180.0 / math.pi))
    phi = dr.select(phi < 0.0, phi + 360.0, phi)
    phi = dr.select(phi >= 360.0, phi - 360.0, phi)
    return dr.clip(theta / 90.0, 0.0, 1.0), phi / 360.0


def fetch_angular(buffer, resolution: tuple[int, int], channels: int, s, t, active=True):
    """Bilinear fetch of an angular plane ``(R_s, R_t, C)`` at ``(s, t)``: rows clamp, columns wrap."""
    rs, rt = resolution
    dr = drjit_module()
    s = dr.clip(s, 0.0, 1.0)
    t = wrap01(t)
    taps = bilinear_taps(t * rt - 0.5, s * rs - 0.5, rt, rs, wrap_x=True, wrap_y=False)
    return gather_channels(buffer, channels, taps, active)


class DrDecoder:
    """The representations' MLP (:class:`dynbtf.representations.triple_plane.Decoder`) in Dr.Jit.

    Unrolled into scalar fused multiply-adds with the weights as float32 kernel literals (NumPy
    arrays here). Built from layers (:meth:`from_layers`): a decoder's own (:meth:`of`) or a
    compiled material's folded ones (:meth:`of_folded`: the synthesizer's output map is folded
    into layer 1, :class:`~dynbtf.decoder.folded.FoldedDecoder`; :meth:`__call__` then takes the
    synthesizer's latent values).
    """

    @classmethod
    def of(cls, decoder) -> "DrDecoder":
        """A fitted decoder's own layers: layer 1 on ``concat(positional (C_U), angular (C_A))``, LeakyReLU after
        every layer but the last, 3 outputs (RGB)."""
        return cls.from_layers([(layer.weight, layer.bias) for layer in [decoder.first, *decoder.rest]],
                               decoder.positional_channels, decoder.negative_slope)

    @classmethod
    def of_folded(cls, folded, level: int = 0) -> "DrDecoder":
        """Level ``level``'s decoder of a :class:`~dynbtf.decoder.folded.FoldedDecoder` (0: the point query's)."""
        return cls.from_layers([folded.first_layer(level), *folded.levels[level].rest], folded.positional_channels,
                               folded.slope)

    @classmethod
    def from_layers(cls, layers, positional_channels: int, negative_slope: float) -> "DrDecoder":
        """A decoder from its layers ``[(weight (out, in), bias (out,)), ...]`` (NumPy or torch; layer 1's inputs:
        ``positional_channels`` positional values, then the angular ones), e.g. a pyramid level's decoder."""
        decoder = cls.__new__(cls)
        decoder.positional_channels = int(positional_channels)
        decoder.negative_slope = float(negative_slope)
        host = [(w.detach().float().cpu().numpy() if hasattr(w, "detach") else w,
                 b.detach().float().cpu().numpy() if hasattr(b, "detach") else b) for w, b in layers]
        decoder.layers = [(np.asarray(w, dtype=np.float32), np.asarray(b, dtype=np.float32)) for w, b in host]
        return decoder

    def _leaky(self, x):
        dr = drjit_module()
        return dr.select(x >= 0.0, x, x * self.negative_slope)

    def __call__(self, features, angular):
        """RGB (``mi.Color3f``) from positional ``features`` (list of C_U mi.Float) and ``angular`` (list of C_A)."""
        mi, dr = mi_module(), drjit_module()
        x = list(features) + list(angular)
        for k, (weight, bias) in enumerate(self.layers):
            out = []
            for o in range(weight.shape[0]):
                acc = mi.Float(float(bias[o]))
                for i in range(weight.shape[1]):
                    acc = dr.fma(x[i], float(weight[o, i]), acc)
                out.append(acc)
            x = out if k == len(self.layers) - 1 else [self._leaky(a) for a in out]
        return mi.Color3f(x[0], x[1], x[2])


class DrTriplePlane:
    """A :class:`~dynbtf.representations.triple_plane.TriplePlane` evaluated with Dr.Jit.

    Holds the angular planes as flat ``mi.Float`` buffers and the decoder as a
    :class:`DrDecoder`.

    Parameters
    ----------
    model : TriplePlane
        A fitted model (any device; its tensors are copied to the host once).
    folded : FoldedDecoder, optional
        The compiled material's decoder, the synthesizer's output map folded into layer 1
        (:meth:`DrDecoder.of_folded`); then :meth:`decode` takes the synthesizer's latent values.

    Examples
    --------
    ``DrTriplePlane(model).decode(features, wv, wl)`` with ``features`` a list of
    ``C_U`` ``mi.Float`` and ``wv, wl`` ``mi.Vector3f`` gives an ``mi.Color3f``
    equal (to float32 rounding) to ``model.decode(features, w_view, w_light)``.
    """

    def __init__(self, model, folded=None) -> None:
        mi = mi_module()
        half = model.f_h.detach().float().cpu().numpy()
        diff = model.f_d.detach().float().cpu().numpy()
        self.angular_resolution = tuple(half.shape[:2])
        self.angular_channels = int(half.shape[2])
        self.positional_channels = int(model.positional_plane().shape[-1])
        self.half = flat_array(mi, half)
        self.diff = flat_array(mi, diff)
        self.decoder = DrDecoder.of(model.decoder) if folded is None else DrDecoder.of_folded(folded)

    def angular_features(self, wv, wl, active=True):
        """``concat(f_H(h), f_D(d))`` as a list of ``2 C_A`` mi.Float."""
        h, d = half_diff(wv, wl)
        sh, th = angular_coords(h)
        sd, td = angular_coords(d)
        c = self.angular_channels
        return (fetch_angular(self.half, self.angular_resolution, c, sh, th, active)
                + fetch_angular(self.diff, self.angular_resolution, c, sd, td, active))

    def decode(self, features, wv, wl, active=True):
        """RGB (``mi.Color3f``, values exclude cos(theta_light)) from positional features and directions."""
        return self.decoder(features, self.angular_features(wv, wl, active))


class DrNeuMIP:
    """The paper's modified :class:`~dynbtf.representations.neumip.NeuMIP` evaluated with Dr.Jit.

    Its decoder input is ``concat(T(uv), light_xy, view_xy)``: the neural texture's
    features (synthesized like the Triple Plane's ``f_U``) and the ``(x, y)``
    components of the local directions, as
    :meth:`~dynbtf.representations.neumip.NeuMIP.direction_inputs`.

    Parameters
    ----------
    model : NeuMIP
        A fitted model.
    folded : FoldedDecoder, optional
        The compiled material's folded decoder (see :class:`DrTriplePlane`).
    """

    def __init__(self, model, folded=None) -> None:
        self.positional_channels = int(model.positional_plane().shape[-1])
        self.decoder = DrDecoder.of(model.decoder) if folded is None else DrDecoder.of_folded(folded)

    @staticmethod
    def angular_features(wv, wl, active=True):
        """``[light_x, light_y, view_x, view_y]`` as a list of 4 mi.Float."""
        return [wl.x, wl.y, wv.x, wv.y]

    def decode(self, features, wv, wl, active=True):
        """RGB (``mi.Color3f``, values exclude cos(theta_light)) from texture features and directions."""
        return self.decoder(features, self.angular_features(wv, wl, active))


def march_visible_uv(u, v, w_view, height_at, *, h_min: float, h_max: float, step: float,
                     max_step: float | None = None, surface_slope: float = 0.5, aspect: float = 1.0, active=True):
    """:func:`dynbtf.representations.parallax.march_visible_uv` in Dr.Jit: where the camera rays through
    the reference-plane points ``(u, v)`` first meet a height field.

    The same march, sample for sample, in float64: search steps from ``z = h_max`` down to
    ``h_min`` scaled by the gap under the ray (between ``step`` and ``max_step``), the first
    sample at or below the surface and the one before it bracketing the hit, the bracket
    halved while longer than ``step``, the hit placed by linear interpolation of
    ``height - z`` between its ends.

    Parameters
    ----------
    u, v : mi.Float or mi.Float64
        Reference-plane points (exemplar repeats).
    w_view : mi.Vector3f
        Unit directions towards the viewer; ``z <= 0`` is treated as vertical.
    height_at : callable
        ``height_at(u, v, active) -> mi.Float`` (uv units) at ``mi.Float64`` points.
    h_min, h_max, step, max_step, surface_slope, aspect : float
        As the torch function.
    active : mi.Bool
        Lanes to march (the others return ``(u, v)`` unchanged).

    Returns
    -------
    ``(u, v)`` as ``mi.Float64``: the visible points (not wrapped).

    Notes
    -----
    One symbolic loop per lane inside the kernel (whatever Dr.Jit's ``SymbolicLoops`` flag),
    searching and halving in the same loop: a lane takes as many samples as its own ray needs
    and stops (its fetches masked) once its bracket is short enough; the loop ends when every
    lane of a SIMD vector has (coherent camera rays, which see similar elevations, wait least).
    """
    mi, dr = mi_module(), drjit_module()
    F64 = mi.Float64
    u, v = F64(u), F64(v)
    wx, wy, wz = F64(w_view.x), F64(w_view.y), F64(w_view.z)
    up = wz > 0.0
    wx, wy, wz = dr.select(up, wx, 0.0), dr.select(up, wy, 0.0), dr.select(up, wz, 1.0)
    inv = 1.0 / dr.maximum(wz, 1e-6)
    sx, sy = wx * inv, wy * inv * float(aspect)
    length = dr.maximum(dr.sqrt(sx * sx + sy * sy), 1e-12)  # horizontal uv per unit of z
    max_step = float(step if max_step is None else max_step)
    shortest, longest, fine = float(step) / length, max_step / length, float(step) * (1.0 + 1e-6) / length  # in z
    climb = 1.0 + float(surface_slope) * length
    active = mi.Bool(active)
    f_hi = F64(height_at(u + h_max * sx, v + h_max * sy, active)) - h_max  # height - z at the bracket's ends
    z_hi, z_lo, f_lo = F64(h_max), F64(h_max), F64(f_hi)
    bracketed = f_hi >= 0.0  # the field reaches h_max here: hit at once
    marching = active & ~bracketed

    def cond(z_hi, f_hi, z_lo, f_lo, bracketed, marching):
        return marching

    def body(z_hi, f_hi, z_lo, f_lo, bracketed, marching):
        inside = bracketed  # halving the bracket, else searching
        search = dr.maximum(z_hi - dr.minimum(dr.maximum(-f_hi / climb, shortest), longest), h_min)
        z = dr.select(inside, 0.5 * (z_lo + z_hi), search)
        f = F64(height_at(u + z * sx, v + z * sy, marching)) - z
        below = (f >= 0.0) | (~inside & (search <= h_min))
        z_lo, f_lo = dr.select(below, z, z_lo), dr.select(below, f, f_lo)
        z_hi, f_hi = dr.select(below, z_hi, z), dr.select(below, f_hi, f)
        bracketed = inside | below
        return z_hi, f_hi, z_lo, f_lo, bracketed, marching & ~(bracketed & (z_hi - z_lo <= fine))

    z_hi, f_hi, z_lo, f_lo, _, _ = dr.while_loop(
        state=(z_hi, f_hi, z_lo, f_lo, bracketed, marching), cond=cond, body=body,
        labels=("z_hi", "f_hi", "z_lo", "f_lo", "bracketed", "marching"), label="dynbtf_parallax_march",
        mode="symbolic")
    denominator = f_lo - f_hi
    t = dr.select(denominator != 0.0, f_lo / denominator, 0.0)  # fraction of the bracket back up
    t = dr.clip(dr.select(dr.isnan(t), 0.0, t), 0.0, 1.0)
    z_hit = dr.select(active, z_lo + t * (z_hi - z_lo), 0.0)
    return u + z_hit * sx, v + z_hit * sy


class DrParallaxTriplePlane(DrTriplePlane):
    """A :class:`~dynbtf.representations.parallax.ParallaxTriplePlane` evaluated with Dr.Jit.

    The Triple Plane's decode (the height is the decoder's last positional input)
    plus :meth:`visible_uv`, the march through the synthesized height field that
    :meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` runs before fetching features.
    """

    def __init__(self, model, folded=None) -> None:
        super().__init__(model, folded)
        config = model.config()
        self.height_scale = float(config["height_scale"])
        self.h_min, self.h_max = model.height_range()
        self.march = model.march_parameters()  # step, resolution, aspect

    def visible_uv(self, u, v, w_view, height_channel, active=True):
        """The surface point (``mi.Float64`` pair) seen through ``(u, v)`` from ``w_view``.

        ``height_channel(u, v, active) -> mi.Float`` is the synthesized positional
        plane's last channel (the height in channel units) at ``mi.Float64`` points.
        """
        scale = self.height_scale

        def height_at(pu, pv, mask):
            return mi_module().Float64(height_channel(pu, pv, mask)) * scale

        return march_visible_uv(u, v, w_view, height_at, h_min=self.h_min, h_max=self.h_max, **self.march,
                                active=active)


#: Representation kind (model files' ``kind``) -> its Dr.Jit evaluator; what the Mitsuba plugin renders.
DR_REPRESENTATIONS = {"triple": DrTriplePlane, "triple-parallax": DrParallaxTriplePlane, "neumip": DrNeuMIP}


def check_renderable(model, what="model") -> None:
    """:class:`~dynbtf.errors.InputError` unless ``model`` is of a kind in :data:`DR_REPRESENTATIONS`.

    ``what`` names the model in the message (e.g. its file). PCA and SH models
    have no decoder to trace into a kernel (their value is a sum over measured
    directions), so they cannot be rendered by the plugin.
    """
    from ...errors import InputError

    kind = getattr(model, "kind", type(model).__name__)
    if kind not in DR_REPRESENTATIONS:
        raise InputError(f"{what}: the Mitsuba plugin renders Triple Plane (kind 'triple', `dynbtf fit`; "
                         f"'triple-parallax', `dynbtf fit --repr triple-parallax`) and NeuMIP (kind 'neumip', "
                         f"`dynbtf fit --repr neumip`) models, got a model of kind {kind!r}")


def dr_representation(model, folded=None):
    """The Dr.Jit evaluator of ``model`` (:data:`DR_REPRESENTATIONS`): ``.decode(features, wv, wl, active)``;
    with ``folded`` (a compiled material's :class:`~dynbtf.decoder.folded.FoldedDecoder`) it decodes latents."""
    check_renderable(model)
    return DR_REPRESENTATIONS[model.kind](model, folded)
