"""Real-time export: a synthesized BTF as GPU textures, decoder weights and a GLSL ES 3.00 shader.

:func:`export_web` writes, into one directory, everything a renderer needs to evaluate
:class:`dynbtf.synthesized.SynthesizedBTF` per pixel on a GPU, plus a self-contained WebGL2
viewer page (``index.html``, no build step, no network):

* ``manifest.json`` -- what every file holds (formats, sizes, per-channel scale and bias, the
  synthesis parameters of every exported method, the decoder's layout, conventions).
* ``*.bin`` -- textures and weights, little-endian, tightly packed:
  the positional plane each method reads (the exemplar for ``tile``, the tileable exemplar for
  ``linear``/``hex``, its Gaussianized PCA coefficients for ``hist``) as ``ceil(C / 4)`` RGBA
  layers; the per-channel inverse transform tables of ``hist``; the luminance plane of ``hex``;
  the angular planes ``f_H``, ``f_D`` (RGBA layers, rows = theta, columns = phi); and the
  decoder's weights (float32, already in std140 uniform-block order).
* ``dynbtf.glsl`` -- the shader functions (GLSL ES 3.00): the triangle lattice, the integer
  vertex hash (bit for bit :func:`dynbtf.synthesis.hash.hash_vertex`), the three blends, the
  inverse tables, the Rusinkiewicz angular fetches and the decoder. A renderer calls
  ``dynbtf_eval(origin, local_uv, w_view, w_light)``.
* ``index.html``, ``viewer.js`` and ``*.js`` copies of the binary files (browsers do not let a
  page opened from disk read binary files; a ``<script>`` can be read).

Texture precision (``precision``): ``fp32`` (exact; for checking), ``fp16`` (half floats), or
``u8`` (8 bits per channel; each channel stores ``value = stored * scale + bias`` with
``stored`` in ``[0, 1]`` and its own scale and bias). Decoder weights stay float32 (a few KB).

Large uv
--------
A shader has 32-bit floats, which cannot hold ``uv = 1e6 + 0.3`` to a texel. The caller splits
``uv * scale`` (in float64, on the CPU) into an integer repeat index and a fraction; the
repeat index enters the shader as a :class:`RepeatOrigin`: the lattice's 64-bit integer
offset, its fractional phase ``2 sqrt(3) I_u mod 1`` and the texel offset of the repeat
(:func:`repeat_origin`; ``viewer.js`` has the same function). The shader adds a local uv
(the fraction plus up to ``2**12`` further repeats, e.g. a mesh's uv times the scale) in
float32. Exact range: any ``|uv * scale| < 2**52`` repeats, the library's own limit; the
vertex hashes and texel choices are those of the library bit for bit at every repeat index,
and positions within a repeat have float32 resolution (``2**-24`` of the local uv's size).
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import InputError
from ..io import atomic_path
from ..synthesis.hash import MASK32, SECOND_STREAM, MIX_MULTIPLIER_1, MIX_MULTIPLIER_2, seed_state
from ..synthesis.lattice import _C3, _N1, _N2, LATTICE_SCALE, MAX_REPEATS, _scaled_integer, split_uv
from ..synthesized import SynthesizedBTF

__all__ = ["export_web", "WebExport", "RepeatOrigin", "repeat_origin", "quantize", "dequantize",
           "quantized_model", "glsl_source", "SUPPORTED_KINDS", "WEB_METHODS", "WEB_PRECISIONS",
           "LOCAL_REPEATS", "FORMAT_VERSION", "shader_cost"]

#: Model kinds the shader evaluates.
SUPPORTED_KINDS = ("triple", "triple-parallax")
#: Kinds refused, and why.
_REFUSED = {
    "pca": "it has no positional feature plane to synthesize (a per-texel PCA basis)",
    "sh": "it has no positional feature plane to synthesize (per-texel spherical-harmonics coefficients)",
    "neumip": "its neural offset texture and per-texel MLP inputs have no shader form",
}
#: Synthesis methods the shader implements, with their mode numbers in ``dynbtf.glsl``.
WEB_METHODS = {"tile": 0, "linear": 1, "hist": 2, "hex": 3}
#: Texture precisions: GL internal formats of RGBA and single-channel textures, bytes per value.
WEB_PRECISIONS = {"fp32": ("RGBA32F", "R32F", 4), "fp16": ("RGBA16F", "R16F", 2), "u8": ("RGBA8", "R8", 1)}
#: Repeats the shader's float32 local uv may span (beyond: the caller moves the origin).
LOCAL_REPEATS = 2 ** 12
#: Version of the manifest's layout.
FORMAT_VERSION = 1
#: Largest uniform block WebGL2 guarantees (bytes).
_MAX_UNIFORM_BLOCK = 16384
#: Most steps of the relief ray march per pixel (views closer to grazing than ~89 deg march coarser than the library).
MAX_MARCH_STEPS = 1024
#: Width of the texture rows that hold the inverse tables (WebGL2 guarantees 2048).
_LUT_ROW = 1024
_VIEWER_FILES = ("index.html", "viewer.js")


# ---------------------------------------------------------------- quantization
def quantize(values: np.ndarray, precision: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Store ``values (..., C)`` in ``precision``: ``(stored, scale (C,), bias (C,))``.

    ``values ~ stored * scale + bias`` per channel: ``fp32``/``fp16`` store the values
    (``scale = 1, bias = 0``); ``u8`` stores ``round((v - min) / (max - min) * 255)`` as uint8,
    read by the GPU as ``stored / 255`` (``scale = max - min``, ``bias = min``).
    """
    if precision not in WEB_PRECISIONS:
        raise InputError(f"precision: expected one of {sorted(WEB_PRECISIONS)}, got {precision!r}")
    values = np.asarray(values, dtype=np.float32)
    c = values.shape[-1]
    if precision == "fp32":
        return values.copy(), np.ones(c, np.float32), np.zeros(c, np.float32)
    if precision == "fp16":
        return values.astype(np.float16), np.ones(c, np.float32), np.zeros(c, np.float32)
    flat = values.reshape(-1, c).astype(np.float64)
    lo, hi = flat.min(0), flat.max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    stored = np.clip(np.rint((values - lo) / span * 255.0), 0, 255).astype(np.uint8)
    return stored, span.astype(np.float32), lo.astype(np.float32)


def dequantize(stored: np.ndarray, scale: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """What the GPU reads back from :func:`quantize`'s output, float32 (``u8``: ``stored / 255 * scale + bias``)."""
    x = stored.astype(np.float32) / np.float32(255.0) if stored.dtype == np.uint8 else stored.astype(np.float32)
    return (x * scale.astype(np.float32) + bias.astype(np.float32)).astype(np.float32)


def _round_trip(values: torch.Tensor, precision: str) -> torch.Tensor:
    return torch.from_numpy(dequantize(*quantize(values.detach().cpu().numpy(), precision)))


def quantized_model(model, precision: str):
    """A copy of a Triple Plane (or its relief variant) whose feature planes hold what an export of ``precision`` stores.

    The decoder is unchanged (exported as float32). Evaluating it (e.g. on held-out pairs)
    measures what the quantization of the planes costs.
    """
    import copy

    _check_kind(model)
    out = copy.deepcopy(model).cpu()
    with torch.no_grad():
        for name in ("f_u", "f_h", "f_d"):
            getattr(out, name).copy_(_round_trip(getattr(out, name), precision))
        if hasattr(out, "height_channel"):  # the plane's last channel (relief models), quantized on its own
            out.height_channel.copy_(_round_trip(out.height_channel[..., None], precision)[..., 0])
    return out


# ---------------------------------------------------------------- the repeat origin (CPU side of large uv)
@dataclass
class RepeatOrigin:
    """The integer part of a position, as the shader takes it (see the module docstring).

    Attributes (arrays of the positions' batch shape)
    ----------
    lattice_x, lattice_y : int64
        The lattice vertex the repeat ``I`` maps to: ``floor(2 sqrt(3) I_u) - 2 I_v`` and ``4 I_v``.
    phase : float64
        ``2 sqrt(3) I_u - floor(2 sqrt(3) I_u)`` in ``[0, 1)``.
    texel_x, texel_y : int64
        ``(I_u W) mod W'`` and ``(I_v H) mod H'``: where the repeat starts on the read plane
        (``W, H`` the exemplar's size, ``W', H'`` the plane's; they differ after tileable
        preprocessing).
    fraction : float64 ``(..., 2)``
        ``uv - I`` in ``[0, 1)``.
    """

    lattice_x: np.ndarray
    lattice_y: np.ndarray
    phase: np.ndarray
    texel_x: np.ndarray
    texel_y: np.ndarray
    fraction: np.ndarray

    def words(self) -> np.ndarray:
        """``(..., 4)`` uint32: low and high words of ``lattice_x`` and ``lattice_y`` (two's complement)."""
        x = self.lattice_x.astype(np.int64).view(np.uint64)
        y = self.lattice_y.astype(np.int64).view(np.uint64)
        return np.stack([x & MASK32, x >> np.uint64(32), y & MASK32, y >> np.uint64(32)], -1).astype(np.uint32)


def repeat_origin(points, plane_size: tuple[int, int], density: tuple[int, int]) -> RepeatOrigin:
    """Split positions ``points (..., 2)`` (exemplar repeats, float64) for the shader.

    ``plane_size = (W', H')`` of the plane read, ``density = (W, H)`` texels per repeat. The
    arithmetic is :func:`dynbtf.synthesis.lattice.triangle_lattice`'s (same float64 and int64
    operations), so the shader's vertices are the library's. ``|points| < 2**52`` is required.
    """
    points = torch.as_tensor(np.asarray(points, dtype=np.float64))
    if points.numel() and float(points.abs().max()) >= MAX_REPEATS:
        raise InputError(f"uv: |uv * scale| must be below 2**52 = {int(MAX_REPEATS)} exemplar repeats")
    whole, frac = split_uv(points)
    iu_whole, iu_frac = _scaled_integer(whole[..., 0])
    pw, ph = plane_size
    dw, dh = density
    return RepeatOrigin(
        lattice_x=(iu_whole - 2 * whole[..., 1]).numpy(), lattice_y=(4 * whole[..., 1]).numpy(),
        phase=iu_frac.numpy(),
        texel_x=torch.remainder(torch.remainder(whole[..., 0], pw) * (dw % pw), pw).numpy(),
        texel_y=torch.remainder(torch.remainder(whole[..., 1], ph) * (dh % ph), ph).numpy(),
        fraction=frac.numpy())


# ---------------------------------------------------------------- the shader
def _float(x: float) -> str:
    """A GLSL float literal that rounds to the float32 nearest ``x``."""
    return repr(float(np.float32(x))) if math.isfinite(x) else "0.0"


def glsl_source(*, channels: int, angular_channels: int, hidden: int, layers: int, negative_slope: float,
                angular_resolution: int, relief: dict[str, float] | None = None) -> str:
    """The shader functions of ``dynbtf.glsl`` for a decoder of these sizes (GLSL ES 3.00, no ``#version``).

    Sizes are compile-time constants; every other quantity (method, tables, weights) is a
    uniform, a uniform block or a texture, so one program serves every exported method.
    ``relief`` (models with a height field: ``h_min``, ``h_max``, ``step``, ``aspect``,
    ``height_scale``) adds the ray march of
    :func:`dynbtf.representations.parallax.march_visible_uv` through the synthesized height.
    """
    g = (channels + 3) // 4
    ag = (angular_channels + 3) // 4
    hg = (hidden + 3) // 4
    hi_scale = math.ldexp(math.floor(math.ldexp(LATTICE_SCALE, 10)), -10)  # 12 significant bits
    lo_scale = LATTICE_SCALE - hi_scale
    rest = []
    for k in range(2, layers + 1):
        og = 1 if k == layers else hg
        rest.append(f"layout(std140) uniform DynbtfLayer{k} {{ mat4 dynbtf_w{k}[{og * hg}]; vec4 dynbtf_b{k}[{og}]; }};")
    # the decoder unrolled into mat4 x vec4 statements on named vec4 variables (no local arrays: software
    # GL keeps them in registers; GPU compilers unroll constant loops anyway)
    decoder_code = []
    for q in range(hg):
        terms = [f"dynbtf_b1[{q}]"] + [f"dynbtf_w1p[{q * g + i}] * x[{i}]" for i in range(g)]
        terms += [f"dynbtf_w1a[{q * 2 * ag + i}] * fh[{i}]" for i in range(ag)]
        terms += [f"dynbtf_w1a[{q * 2 * ag + ag + i}] * fd[{i}]" for i in range(ag)]
        decoder_code.append(f"    vec4 y1_{q} = dynbtf_leaky({' + '.join(terms)});")
    for k in range(2, layers + 1):
        og = 1 if k == layers else hg
        for q in range(og):
            terms = [f"dynbtf_b{k}[{q}]"] + [f"dynbtf_w{k}[{q * hg + i}] * y{k - 1}_{i}" for i in range(hg)]
            value = " + ".join(terms)
            decoder_code.append(f"    vec4 y{k}_{q} = {value if k == layers else f'dynbtf_leaky({value})'};")
    relief_code = ""
    if relief:
        relief_code = f"""
// ---- relief (dynbtf.representations.parallax): features are read where the camera ray meets the
// synthesized height field, marched from h_max down to h_min in steps of at most {_float(relief["step"])} repeats
uniform vec4 dynbtf_height_map[DYNBTF_G];   // height channel = latent . map + offset (the method's output map)
uniform float dynbtf_height_offset;
#define DYNBTF_MAX_MARCH {MAX_MARCH_STEPS}
float dynbtf_height(DynbtfOrigin o, vec2 p) {{
    vec4 x[DYNBTF_G];
    dynbtf_latent(o, p, x);
    float h = dynbtf_height_offset;
    for (int g = 0; g < DYNBTF_G; ++g) h += dot(x[g], dynbtf_height_map[g]);
    return h * {_float(relief["height_scale"])};
}}
vec2 dynbtf_visible(DynbtfOrigin o, vec2 local, vec3 w) {{
    const float h_min = {_float(relief["h_min"])}, h_max = {_float(relief["h_max"])};
    if (w.z <= 0.0) w = vec3(0.0, 0.0, 1.0);
    vec2 slope = w.xy / max(w.z, 1e-6) * vec2(1.0, {_float(relief["aspect"])});
    float depth = h_max - h_min;
    int n = min(max(int(ceil(depth * length(slope) / {_float(relief["step"])})), 1), DYNBTF_MAX_MARCH);
    float dz = depth / float(n);
    float f_prev = dynbtf_height(o, local + h_max * slope) - h_max;
    if (f_prev >= 0.0) return local + h_max * slope;
    float z_hit = h_min;
    for (int k = 1; k <= DYNBTF_MAX_MARCH; ++k) {{
        bool last = k >= n;
        float z_above = h_max - float(k - 1) * dz;
        float z = last ? h_min : h_max - float(k) * dz;
        float f = dynbtf_height(o, local + z * slope) - z;
        if (f >= 0.0 || last) {{
            float t = f - f_prev != 0.0 ? clamp(f / (f - f_prev), 0.0, 1.0) : 0.0;
            z_hit = z + t * (z_above - z);
            break;
        }}
        f_prev = f;
    }}
    return local + z_hit * slope;
}}
"""
    return f"""// dynbtf real-time shader functions (GLSL ES 3.00), generated by dynbtf.render.web_export.
// Evaluates dynbtf.synthesized.SynthesizedBTF: synthesized positional features (tile, linear,
// hist, hex), Rusinkiewicz angular features and the decoder. Conventions (dynbtf README):
// directions are unit vectors in the local frame (x along +u, y along +v, z = normal), both
// pointing away from the surface; the value excludes cos(theta_light) (pi f_r), linear RGB.
// Sizes: {channels} positional channels ({g} RGBA layers), {angular_channels} angular channels per plane
// ({angular_resolution}x{angular_resolution}), decoder {layers} layers of {hidden} hidden units.

#define DYNBTF_G {g}
#define DYNBTF_AG {ag}
#define DYNBTF_HG {hg}

// ---- per-method state (set by the host for the method in use)
uniform highp sampler2DArray dynbtf_plane;   // the plane the method reads, RGBA layers
uniform highp sampler2D dynbtf_lut;          // hist: inverse tables, channel c entry k at (k % row, c * rows + k / row)
uniform highp sampler2D dynbtf_lum;          // hex: luminance in [0, 1]
uniform highp sampler2DArray dynbtf_fh;      // angular planes: x = phi column, y = theta row
uniform highp sampler2DArray dynbtf_fd;
uniform int dynbtf_mode;                     // 0 tile, 1 linear, 2 hist, 3 hex
uniform ivec2 dynbtf_plane_size;             // (W', H') of the plane read
uniform ivec2 dynbtf_density;                // (W, H): texels per repeat
uniform uint dynbtf_seed_state;              // mix32((seed ^ 0x85EBCA6B)) (dynbtf.synthesis.hash.seed_state)
uniform float dynbtf_gamma;                  // hist: barycentric exponent
uniform float dynbtf_beta;                   // hex: luminance fall-off
uniform float dynbtf_gain_k;                 // hex: contrast-gain exponent (1: none)
uniform float dynbtf_g_min;                  // hist: Gaussian value of table entry 0
uniform float dynbtf_inv_step;               // hist: table entries per Gaussian unit
uniform int dynbtf_lut_size;                 // hist: entries per channel
uniform int dynbtf_lut_row;                  // hist: entries per texture row
uniform vec4 dynbtf_plane_scale[DYNBTF_G];   // value = stored * scale + bias, per channel
uniform vec4 dynbtf_plane_bias[DYNBTF_G];
uniform vec4 dynbtf_lut_scale[DYNBTF_G];
uniform vec4 dynbtf_lut_bias[DYNBTF_G];
uniform vec4 dynbtf_lum_scale_bias;          // (scale, bias, 0, 0)
uniform vec4 dynbtf_fh_scale[DYNBTF_AG];
uniform vec4 dynbtf_fh_bias[DYNBTF_AG];
uniform vec4 dynbtf_fd_scale[DYNBTF_AG];
uniform vec4 dynbtf_fd_bias[DYNBTF_AG];

// decoder: layer 1 = positional part (the method's output map folded in) + angular part + bias
layout(std140) uniform DynbtfLayer1 {{ mat4 dynbtf_w1p[{hg * g}]; mat4 dynbtf_w1a[{hg * 2 * ag}]; vec4 dynbtf_b1[{hg}]; }};
{chr(10).join(rest)}

// ---- the integer part of a position (computed on the CPU in float64: dynbtf.render.web_export.repeat_origin)
struct DynbtfOrigin {{
    uvec4 lattice;   // (low, high) words of the int64 lattice x, then of lattice y
    float phase;     // 2 sqrt(3) I_u mod 1
    ivec2 texel;     // (I_u W mod W', I_v H mod H')
}};

// ---- integer hash (dynbtf.synthesis.hash): lowbias32, uint arithmetic wraps modulo 2^32
uint dynbtf_mix32(uint x) {{
    x ^= x >> 16u; x *= {MIX_MULTIPLIER_1:#010x}u; x ^= x >> 15u; x *= {MIX_MULTIPLIER_2:#010x}u; return x ^ (x >> 16u);
}}
uint dynbtf_fold(uint h, uvec2 k) {{ return dynbtf_mix32(dynbtf_mix32(h ^ k.x) ^ k.y); }}
// 64-bit two's complement (low, high) + a small signed int
uvec2 dynbtf_add(uvec2 a, int d) {{
    uint lo = a.x + uint(d);
    return uvec2(lo, a.y + (d < 0 ? 0xFFFFFFFFu : 0u) + (lo < a.x ? 1u : 0u));
}}
int dynbtf_mod(int a, int n) {{ return a >= 0 ? a % n : (n - 1) - ((-a - 1) % n); }}

// ---- the triangle lattice (dynbtf.synthesis.lattice) and the vertices' hashed whole-texel offsets
struct DynbtfTriangle {{
    uvec2 vx[3]; uvec2 vy[3];  // int64 vertex coordinates as (low, high) words
    float b[3];                // barycentrics
    ivec2 offset[3];           // (ox, oy) of each vertex
    ivec2 texel;               // texel of the bilinear footprint's corner (before offsets), on the read plane
    vec2 t;                    // bilinear weights inside the footprint
}};

DynbtfTriangle dynbtf_triangle(DynbtfOrigin o, vec2 local) {{
    DynbtfTriangle tri;
    vec2 wf = floor(local);
    vec2 f = local - wf;
    if (f.x >= 1.0) {{ f.x -= 1.0; wf.x += 1.0; }}
    if (f.y >= 1.0) {{ f.y -= 1.0; wf.y += 1.0; }}
    ivec2 w = ivec2(wf);
    // 2 sqrt(3) w_u as an integer plus a fraction (the high part has 12 bits: exact for |w_u| < 2^12)
    float p_hi = wf.x * {_float(hi_scale)};
    float p_whole = floor(p_hi);
    float frac = (p_hi - p_whole) + wf.x * {_float(lo_scale)} + o.phase;
    float carry = floor(frac);
    frac -= carry;
    float kx = frac + {_float(LATTICE_SCALE)} * f.x - 2.0 * f.y;
    float ky = 4.0 * f.y;
    float bx = floor(kx), by = floor(ky);
    float fx = kx - bx, fy = ky - by;
    int dx = int(bx) + int(p_whole) + int(carry) - 2 * w.y;
    int dy = int(by) + 4 * w.y;
    uvec2 base_x = dynbtf_add(o.lattice.xy, dx);
    uvec2 base_y = dynbtf_add(o.lattice.zw, dy);
    uvec2 base_x1 = dynbtf_add(base_x, 1), base_y1 = dynbtf_add(base_y, 1);
    float z = 1.0 - fx - fy;
    if (z > 0.0) {{   // b, b + (0, 1), b + (1, 0)
        tri.vx[0] = base_x;  tri.vy[0] = base_y;  tri.b[0] = z;
        tri.vx[1] = base_x;  tri.vy[1] = base_y1; tri.b[1] = fy;
        tri.vx[2] = base_x1; tri.vy[2] = base_y;  tri.b[2] = fx;
    }} else {{         // b + (1, 1), b + (1, 0), b + (0, 1)
        tri.vx[0] = base_x1; tri.vy[0] = base_y1; tri.b[0] = -z;
        tri.vx[1] = base_x1; tri.vy[1] = base_y;  tri.b[1] = 1.0 - fy;
        tri.vx[2] = base_x;  tri.vy[2] = base_y1; tri.b[2] = 1.0 - fx;
    }}
    uint pw = uint(dynbtf_plane_size.x), ph = uint(dynbtf_plane_size.y);
    for (int i = 0; i < 3; ++i) {{
        uint h = dynbtf_fold(dynbtf_fold(dynbtf_seed_state, tri.vx[i]), tri.vy[i]);
        tri.offset[i] = ivec2(int(h % pw), int(dynbtf_mix32(h ^ {SECOND_STREAM:#010x}u) % ph));
    }}
    // texel addressing shared by the three samples: (I W) mod W' + the fraction's texel
    vec2 p = f * vec2(dynbtf_density) - 0.5;
    vec2 p0 = floor(p);
    tri.t = p - p0;
    ivec2 size = dynbtf_plane_size;
    tri.texel = ivec2(
        dynbtf_mod(o.texel.x + dynbtf_mod(w.x, size.x) * (dynbtf_density.x % size.x) + int(p0.x), size.x),
        dynbtf_mod(o.texel.y + dynbtf_mod(w.y, size.y) * (dynbtf_density.y % size.y) + int(p0.y), size.y));
    return tri;
}}

// ---- fetches
void dynbtf_bilinear(ivec2 c, vec2 t, float weight, inout vec4 acc[DYNBTF_G]) {{
    ivec2 size = dynbtf_plane_size;
    int c1 = c.x + 1 == size.x ? 0 : c.x + 1;
    int r1 = c.y + 1 == size.y ? 0 : c.y + 1;
    float w00 = weight * (1.0 - t.x) * (1.0 - t.y), w01 = weight * t.x * (1.0 - t.y);
    float w10 = weight * (1.0 - t.x) * t.y, w11 = weight * t.x * t.y;
    for (int g = 0; g < DYNBTF_G; ++g) {{
        acc[g] += w00 * texelFetch(dynbtf_plane, ivec3(c.x, c.y, g), 0) + w01 * texelFetch(dynbtf_plane, ivec3(c1, c.y, g), 0)
                + w10 * texelFetch(dynbtf_plane, ivec3(c.x, r1, g), 0) + w11 * texelFetch(dynbtf_plane, ivec3(c1, r1, g), 0);
    }}
}}

float dynbtf_luminance(ivec2 c, vec2 t) {{
    ivec2 size = dynbtf_plane_size;
    int c1 = c.x + 1 == size.x ? 0 : c.x + 1;
    int r1 = c.y + 1 == size.y ? 0 : c.y + 1;
    float v = (1.0 - t.x) * (1.0 - t.y) * texelFetch(dynbtf_lum, c, 0).r + t.x * (1.0 - t.y) * texelFetch(dynbtf_lum, ivec2(c1, c.y), 0).r
            + (1.0 - t.x) * t.y * texelFetch(dynbtf_lum, ivec2(c.x, r1), 0).r + t.x * t.y * texelFetch(dynbtf_lum, ivec2(c1, r1), 0).r;
    return v * dynbtf_lum_scale_bias.x + dynbtf_lum_scale_bias.y;
}}

float dynbtf_inverse_table(int c, float g) {{
    float top = float(dynbtf_lut_size - 1);
    float pos = clamp((g - dynbtf_g_min) * dynbtf_inv_step, 0.0, top);
    int lo = min(int(pos), dynbtf_lut_size - 2);
    float t = pos - float(lo);
    int rows = (dynbtf_lut_size + dynbtf_lut_row - 1) / dynbtf_lut_row;
    int hi = lo + 1;
    float x0 = texelFetch(dynbtf_lut, ivec2(lo % dynbtf_lut_row, c * rows + lo / dynbtf_lut_row), 0).r;
    float x1 = texelFetch(dynbtf_lut, ivec2(hi % dynbtf_lut_row, c * rows + hi / dynbtf_lut_row), 0).r;
    return x0 + t * (x1 - x0);
}}

float dynbtf_gain(float x) {{
    return x < 0.5 ? 0.5 * pow(2.0 * x, dynbtf_gain_k) : 1.0 - 0.5 * pow(max(2.0 - 2.0 * x, 0.0), dynbtf_gain_k);
}}

// ---- synthesized positional features before the output map (the "latent", DYNBTF_G vec4)
void dynbtf_latent(DynbtfOrigin o, vec2 local, out vec4 latent[DYNBTF_G]) {{
    vec4 acc[DYNBTF_G];
    for (int g = 0; g < DYNBTF_G; ++g) acc[g] = vec4(0.0);
    float total = 1.0;
    DynbtfTriangle tri = dynbtf_triangle(o, local);
    if (dynbtf_mode == 0) {{
        dynbtf_bilinear(tri.texel, tri.t, 1.0, acc);
    }} else {{
        vec3 s = vec3(tri.b[0], tri.b[1], tri.b[2]);
        ivec2 size = dynbtf_plane_size;
        ivec2 c[3];
        for (int i = 0; i < 3; ++i) c[i] = ivec2((tri.texel.x + tri.offset[i].x) % size.x, (tri.texel.y + tri.offset[i].y) % size.y);
        if (dynbtf_mode == 2) {{
            s = dynbtf_gamma == 1.0 ? s : pow(max(s, 0.0), vec3(dynbtf_gamma));
            s /= s.x + s.y + s.z;
            s *= inversesqrt(dot(s, s));
        }} else if (dynbtf_mode == 3) {{
            vec3 lum = vec3(dynbtf_luminance(c[0], tri.t), dynbtf_luminance(c[1], tri.t), dynbtf_luminance(c[2], tri.t));
            vec3 b = max(s, 0.0), b2 = b * b, b4 = b2 * b2;
            s = (1.0 - dynbtf_beta + dynbtf_beta * lum) * (b4 * b2 * b);
            s /= s.x + s.y + s.z;
            if (dynbtf_gain_k != 1.0) {{
                s = vec3(dynbtf_gain(s.x), dynbtf_gain(s.y), dynbtf_gain(s.z));
                s /= s.x + s.y + s.z;
            }}
        }}
        for (int i = 0; i < 3; ++i) dynbtf_bilinear(c[i], tri.t, s[i], acc);
        total = s.x + s.y + s.z;
    }}
    for (int g = 0; g < DYNBTF_G; ++g) acc[g] = acc[g] * dynbtf_plane_scale[g] + total * dynbtf_plane_bias[g];
    if (dynbtf_mode == 2) {{
        for (int g = 0; g < DYNBTF_G; ++g) {{
            vec4 v;
            for (int k = 0; k < 4; ++k) v[k] = dynbtf_inverse_table(4 * g + k, acc[g][k]);
            acc[g] = v * dynbtf_lut_scale[g] + dynbtf_lut_bias[g];
        }}
    }}
    for (int g = 0; g < DYNBTF_G; ++g) latent[g] = acc[g];
}}

// ---- angular features (dynbtf.conventions: Rusinkiewicz h and d, plane coords (theta/90, phi/360))
vec3 dynbtf_difference(vec3 h, vec3 wl) {{
    float cos_t = clamp(h.z, -1.0, 1.0);
    float sin_t = sqrt(max(1.0 - cos_t * cos_t, 0.0));
    float rxy = length(h.xy);
    float cos_p = rxy < 1e-12 ? 1.0 : h.x / rxy;
    float sin_p = rxy < 1e-12 ? 0.0 : h.y / rxy;
    vec3 d = vec3(cos_p * wl.x + sin_p * wl.y, -sin_p * wl.x + cos_p * wl.y, wl.z);   // R_z(-phi_h)
    return vec3(cos_t * d.x - sin_t * d.z, d.y, sin_t * d.x + cos_t * d.z);           // R_y(-theta_h)
}}

void dynbtf_angular_fetch(highp sampler2DArray plane, vec3 w, vec4 scale[DYNBTF_AG], vec4 bias[DYNBTF_AG],
                          out vec4 result[DYNBTF_AG]) {{
    const float R = {float(angular_resolution)};
    float r = length(w.xy);
    float s = clamp(atan(r, w.z) * {_float(2.0 / math.pi)}, 0.0, 1.0);
    float t = r < 1e-5 ? 0.0 : atan(w.y, w.x) * {_float(0.5 / math.pi)};
    t -= floor(t);
    if (t >= 1.0) t -= 1.0;
    float row = clamp(s * R - 0.5, 0.0, R - 1.0);
    float row0 = min(floor(row), max(R - 2.0, 0.0));
    float ty = row - row0;
    float row1 = min(row0 + 1.0, R - 1.0);
    float col = t * R - 0.5;
    float col0 = floor(col);
    float tx = col - col0;
    col0 = col0 < 0.0 ? R - 1.0 : col0;
    float col1 = col0 + 1.0 >= R ? 0.0 : col0 + 1.0;
    ivec2 a = ivec2(int(col0), int(row0)), b = ivec2(int(col1), int(row1));
    for (int g = 0; g < DYNBTF_AG; ++g) {{
        vec4 v = (1.0 - tx) * (1.0 - ty) * texelFetch(plane, ivec3(a.x, a.y, g), 0) + tx * (1.0 - ty) * texelFetch(plane, ivec3(b.x, a.y, g), 0)
               + (1.0 - tx) * ty * texelFetch(plane, ivec3(a.x, b.y, g), 0) + tx * ty * texelFetch(plane, ivec3(b.x, b.y, g), 0);
        result[g] = v * scale[g] + bias[g];
    }}
}}

vec4 dynbtf_leaky(vec4 x) {{ return max(x, 0.0) + {_float(negative_slope)} * min(x, 0.0); }}

{relief_code}
// ---- the BTF value: linear RGB, excluding cos(theta_light); zero below either horizon
vec3 dynbtf_eval(DynbtfOrigin o, vec2 local, vec3 w_view, vec3 w_light) {{
    if (w_view.z < 0.0 || w_light.z < 0.0) return vec3(0.0);
    vec4 x[DYNBTF_G];
    dynbtf_latent(o, {"dynbtf_visible(o, local, w_view)" if relief else "local"}, x);
    vec3 sum = w_view + w_light;
    vec3 h = dot(sum, sum) < 1e-24 ? vec3(0.0, 0.0, 1.0) : normalize(sum);
    vec4 fh[DYNBTF_AG], fd[DYNBTF_AG];
    dynbtf_angular_fetch(dynbtf_fh, h, dynbtf_fh_scale, dynbtf_fh_bias, fh);
    dynbtf_angular_fetch(dynbtf_fd, dynbtf_difference(h, w_light), dynbtf_fd_scale, dynbtf_fd_bias, fd);
{chr(10).join(decoder_code)}
    return y{layers}_0.rgb;
}}
"""


def shader_cost(method: str, *, channels: int = 16, angular_channels: int = 8, hidden: int = 32, layers: int = 4
                ) -> dict[str, int]:
    """Work per pixel of ``dynbtf_eval`` as ``dynbtf.glsl`` does it: texel fetches and multiply-adds.

    Fetches are ``texelFetch`` calls of RGBA (or single-channel) texels: the three samples of a
    blend read a 2 x 2 bilinear footprint of ``ceil(C / 4)`` RGBA layers each (tile: one sample),
    ``hist`` reads two table entries per channel, ``hex`` a 2 x 2 luminance footprint per sample, and
    each angular plane a 2 x 2 footprint of ``ceil(C_A / 4)`` layers. Multiply-adds count the
    bilinear and blend weights applied to every channel, the per-channel dequantization and table
    interpolation, and the decoder's layers as the shader runs them (``mat4 x vec4`` blocks: widths
    padded to multiples of 4), not the integer hash or the lattice's few scalar operations.
    """
    if method not in WEB_METHODS:
        raise InputError(f"method: expected one of {list(WEB_METHODS)}, got {method!r}")
    g, ag, hg = (channels + 3) // 4, (angular_channels + 3) // 4, (hidden + 3) // 4
    samples = 1 if method == "tile" else 3
    fetches = samples * 4 * g + 2 * 4 * ag
    macs = samples * 4 * 4 * g + 4 * g + 2 * (4 * 4 * ag + 4 * ag)  # bilinear+blend weights, dequantization
    if method == "hist":
        fetches += 2 * 4 * g
        macs += 2 * 4 * g  # interpolation and dequantization of the table values
    if method == "hex":
        fetches += samples * 4
        macs += samples * 4
    decoder = 16 * hg * (g + 2 * ag) + 16 * hg * hg * (layers - 2) + 16 * hg
    return {"texel_fetches": fetches, "macs": macs + decoder, "decoder_macs": decoder}


# ---------------------------------------------------------------- packing
def _layers_rgba(plane: np.ndarray) -> np.ndarray:
    """``(H, W, C)`` -> ``(ceil(C / 4), H, W, 4)`` (zero-padded channels): the RGBA layers of a texture array."""
    h, w, c = plane.shape
    g = (c + 3) // 4
    out = np.zeros((h, w, 4 * g), dtype=plane.dtype)
    out[..., :c] = plane
    return np.ascontiguousarray(out.reshape(h, w, g, 4).transpose(2, 0, 1, 3))


def _pad4(x: np.ndarray, fill: float) -> list[float]:
    n = (len(x) + 3) // 4 * 4
    return [float(v) for v in x] + [fill] * (n - len(x))


def _mat4_blocks(weight: np.ndarray) -> np.ndarray:
    """``(out, in)`` weights -> std140 ``mat4`` blocks ``[o * ceil(in / 4) + i]`` (column-major) as float32.

    Block ``(o, i)`` multiplies input group ``i`` into output group ``o``: ``y[o] += M * x[i]``.
    """
    n_out, n_in = weight.shape
    og, ig = (n_out + 3) // 4, (n_in + 3) // 4
    padded = np.zeros((4 * og, 4 * ig), dtype=np.float64)
    padded[:n_out, :n_in] = weight
    blocks = padded.reshape(og, 4, ig, 4).transpose(0, 2, 3, 1)  # [o, i, column c, row r] = W[4o + r, 4i + c]
    return np.ascontiguousarray(blocks, dtype=np.float32).reshape(-1)


def _vec4s(bias: np.ndarray) -> np.ndarray:
    return np.asarray(_pad4(np.asarray(bias, dtype=np.float64), 0.0), dtype=np.float32)


def _check_kind(model) -> str:
    """The model's kind if the shader evaluates it, else an :class:`InputError` saying why not."""
    from ..representations.parallax import ParallaxTriplePlane
    from ..representations.triple_plane import TriplePlane

    kind = getattr(model, "kind", None) or type(model).__name__
    if type(model) not in (TriplePlane, ParallaxTriplePlane):
        why = _REFUSED.get(kind, "the shader implements only the Triple Plane's decoder")
        raise InputError(f"export: model kind {kind!r} is not supported by the web export ({why}); "
                         f"supported kinds: {', '.join(SUPPORTED_KINDS)}")
    return kind


@dataclass
class WebExport:
    """What :func:`export_web` wrote.

    Attributes
    ----------
    directory : Path
    manifest : dict
        The content of ``manifest.json``.
    """

    directory: Path
    manifest: dict[str, Any]

    @property
    def index(self) -> Path:
        """The viewer page."""
        return self.directory / "index.html"

    def method_bytes(self, method: str) -> int:
        """Bytes of the binary files one method needs (its plane and tables, angular planes, decoder)."""
        files = set(self.manifest["methods"][method]["files"]) | set(self.manifest["shared_files"])
        return sum(self.manifest["files"][f]["bytes"] for f in files)

    def total_bytes(self) -> int:
        """Bytes of all binary files."""
        return sum(f["bytes"] for f in self.manifest["files"].values())


class _Writer:
    """Collects binary files (deduplicated by content) and writes them with their ``.js`` twins."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.files: dict[str, dict[str, Any]] = {}
        self._by_digest: dict[str, str] = {}

    def add(self, name: str, data: np.ndarray) -> str:
        raw = np.ascontiguousarray(data).tobytes()
        digest = hashlib.sha256(raw).hexdigest()
        if digest in self._by_digest:
            return self._by_digest[digest]
        self._by_digest[digest] = name
        self.files[name] = {"bytes": len(raw), "sha256": digest}
        with atomic_path(self.directory / name) as tmp:
            tmp.write_bytes(raw)
        payload = base64.b64encode(raw).decode("ascii")
        with atomic_path(self.directory / f"{name}.js") as tmp:
            tmp.write_text(f"DynBTF.file({json.dumps(name)}, {len(raw)}, \"{payload}\");\n", encoding="ascii")
        return name


def _texture(writer: _Writer, name: str, values: np.ndarray, precision: str, *, layered: bool) -> dict[str, Any]:
    """Quantize ``values`` (``(H, W, C)`` if ``layered`` else ``(H, W)``) and write it: its manifest entry."""
    rgba, single, _ = WEB_PRECISIONS[precision]
    if layered:
        stored, scale, bias = quantize(values, precision)
        c = values.shape[-1]
        data = _layers_rgba(stored)
        return {"file": writer.add(name, data), "format": rgba, "layers": int(data.shape[0]),
                "height": int(values.shape[0]), "width": int(values.shape[1]), "channels": int(c),
                "scale": _pad4(scale, 0.0), "bias": _pad4(bias, 0.0)}
    stored, scale, bias = quantize(values[..., None], precision)
    return {"file": writer.add(name, stored[..., 0]), "format": single, "height": int(values.shape[0]),
            "width": int(values.shape[1]), "scale": float(scale[0]), "bias": float(bias[0])}


def _lut_texture(writer: _Writer, name: str, table: np.ndarray, precision: str) -> dict[str, Any]:
    """Inverse tables ``(C, L)``: each channel quantized on its own, ``ceil(L / row)`` rows of ``row`` entries."""
    c, size = table.shape
    row = min(size, _LUT_ROW)
    rows = (size + row - 1) // row
    padded = np.zeros((c, rows * row), dtype=np.float32)
    padded[:, :size] = table
    padded[:, size:] = table[:, -1:]
    stored, scale, bias = quantize(padded.T, precision)  # (entries, C): per-channel scale/bias
    data = np.ascontiguousarray(stored.T.reshape(c * rows, row))
    return {"file": writer.add(name, data), "format": WEB_PRECISIONS[precision][1], "height": int(c * rows),
            "width": int(row), "size": int(size), "row": int(row), "scale": _pad4(scale, 0.0), "bias": _pad4(bias, 0.0)}


def export_web(model, out_dir, *, precision: str = "fp16", methods=("hist", "hex", "tile"), seed: int = 0,
               scale: float = 8.0, viewer: bool = True, method_params: dict[str, dict[str, Any]] | None = None
               ) -> WebExport:
    """Export a Triple Plane model for real-time evaluation in a GLSL ES 3.00 shader (and a WebGL2 viewer).

    Parameters
    ----------
    model : Representation, str or Path
        A fitted Triple Plane (kind ``triple``, or ``triple-parallax``: the shader then marches
        the synthesized height field) or its model file. Other kinds raise
        :class:`~dynbtf.errors.InputError` naming the supported ones.
    out_dir : path
        Directory to write (created; files of an earlier export are replaced).
    precision : {"fp16", "u8", "fp32"}
        Storage of the textures (see the module docstring).
    methods : sequence of {"tile", "linear", "hist", "hex"}
        Synthesis methods to export (each with its own plane and tables); the first is the
        viewer's default.
    seed : int
        Synthesis seed (the same choices as ``SynthesizedBTF(model, method, seed=seed)``).
    scale : float
        The viewer's initial exemplar repeats per unit of the surface's uv.
    viewer : bool
        Also write ``index.html``, ``viewer.js`` and the ``.js`` twins of the binary files.
    method_params : dict, optional
        Per-method synthesizer parameters (e.g. ``{"hist": {"gamma": 3.0}}``).

    Returns
    -------
    WebExport
    """
    source = None
    if isinstance(model, (str, bytes)) or hasattr(model, "__fspath__"):
        from ..representations.model_file import load_model

        source = Path(model)
        model, _ = load_model(model)
    kind = _check_kind(model)
    if precision not in WEB_PRECISIONS:
        raise InputError(f"precision: expected one of {sorted(WEB_PRECISIONS)} (fp16: half floats, u8: 8 bits per "
                         f"channel with per-channel scale and bias, fp32: exact), got {precision!r}")
    methods = list(methods)
    if not methods:
        raise InputError(f"methods: expected at least one of {list(WEB_METHODS)}")
    for m in methods:
        if m not in WEB_METHODS:
            raise InputError(f"method: {m!r} has no shader form; expected one of {list(WEB_METHODS)} "
                             "(quilting is not dynamic)")
    method_params = dict(method_params or {})
    model = model.cpu().eval()
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"-o/--output: {out_dir} exists and is not a directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    writer = _Writer(out_dir)
    cfg = model.config()
    decoder = model.decoder
    hidden, layers = int(cfg["hidden"]), int(cfg["layers"])
    # positional channels as the decoder reads them (a relief model's plane adds its height channel)
    c_u, c_a, res = int(decoder.positional_channels), int(cfg["angular_channels"]), int(cfg["angular_resolution"])
    relief = None
    if kind == "triple-parallax":
        h_min, h_max = model.height_range()
        rows, cols = model.height_channel.shape
        relief = {"h_min": h_min, "h_max": h_max, "step": cfg["march_step_texels"] / max(rows, cols),
                  "aspect": cols / rows, "height_scale": model.height_scale}
    g, ag, hg = (c_u + 3) // 4, (c_a + 3) // 4, (hidden + 3) // 4
    first_w = decoder.first.weight.detach().double().numpy()
    first_b = decoder.first.bias.detach().double().numpy()
    w_pos, w_ang = first_w[:, :c_u], first_w[:, c_u:]
    # the angular part of layer 1: f_H's channels then f_D's, each padded to whole vec4 groups
    w_ang_padded = np.zeros((hidden, 8 * ag))
    w_ang_padded[:, :c_a] = w_ang[:, :c_a]
    w_ang_padded[:, 4 * ag:4 * ag + c_a] = w_ang[:, c_a:]
    angular_blocks = _mat4_blocks(w_ang_padded)

    with torch.no_grad():
        angular = {"f_H": _texture(writer, "f_H.bin", model.f_h.detach().numpy(), precision, layered=True),
                   "f_D": _texture(writer, "f_D.bin", model.f_d.detach().numpy(), precision, layered=True)}
    # decoder layers 2..: one float32 file in std140 block order
    rest_blocks, rest_entries, offset = [], [], 0
    for k, layer in enumerate(decoder.rest, start=2):
        block = np.concatenate([_mat4_blocks(layer.weight.detach().double().numpy()),
                                _vec4s(layer.bias.detach().double().numpy())])
        rest_entries.append({"block": f"DynbtfLayer{k}", "offset": offset, "floats": int(block.size)})
        rest_blocks.append(block)
        offset += int(block.size)
    decoder_file = writer.add("decoder.bin", np.concatenate(rest_blocks) if rest_blocks else np.zeros(0, np.float32))
    layer1_floats = 16 * (hg * g + hg * 2 * ag) + 4 * hg
    for entry in [{"block": "DynbtfLayer1", "floats": layer1_floats}, *rest_entries]:
        if entry["floats"] * 4 > _MAX_UNIFORM_BLOCK:
            raise InputError(f"export: decoder block {entry['block']} needs {entry['floats'] * 4} bytes, more than "
                             f"the {_MAX_UNIFORM_BLOCK} bytes WebGL2 guarantees per uniform block "
                             f"(hidden = {hidden}); export a model with a smaller decoder")

    method_entries: dict[str, Any] = {}
    for m in methods:
        params = dict(method_params.get(m, {}))
        btf = SynthesizedBTF(model, m, seed=seed, **params)
        synth = btf.synthesizer
        files = []
        entry: dict[str, Any] = {"mode": WEB_METHODS[m], "density": [int(synth.exemplar.shape[1]),
                                                                     int(synth.exemplar.shape[0])],
                                 "seed": int(seed), "seed_state": int(seed_state(int(seed) & MASK32)),
                                 "parameters": synth.parameters()}
        plane = (synth.exemplar if m == "tile" else synth.prepared.plane).detach().cpu().numpy()
        entry["plane"] = _texture(writer, f"plane_{m}.bin", plane, precision, layered=True)
        files.append(entry["plane"]["file"])
        matrix, out_offset = synth.output_map()
        if m == "hist":
            lut = synth.prepared.extras["lut"]
            entry["lut"] = _lut_texture(writer, f"lut_{m}.bin", synth.prepared.extras["lut_table"].cpu().numpy(),
                                        precision)
            entry.update(gamma=float(synth.gamma), g_min=float(lut.g_min), inv_step=float(1.0 / lut.step))
            files.append(entry["lut"]["file"])
        if m == "hex":
            entry["luminance"] = _texture(writer, f"luminance_{m}.bin",
                                          synth.prepared.extras["luminance"].cpu().numpy(), precision, layered=False)
            entry.update(beta=float(synth.beta), gain_k=float(math.log(1.0 - synth.contrast) / math.log(0.5)))
            files.append(entry["luminance"]["file"])
        # layer 1 with the method's output map folded in: W_U (M x + o) + b = (W_U M) x + (W_U o + b)
        m_mat = np.eye(c_u) if matrix is None else matrix.double().cpu().numpy()   # features = latent @ M + o
        m_off = np.zeros(c_u) if out_offset is None else out_offset.double().cpu().numpy()
        w_fold = w_pos @ m_mat.T                                                   # (hidden, C)
        b_fold = w_pos @ m_off + first_b
        block = np.concatenate([_mat4_blocks(w_fold), angular_blocks, _vec4s(b_fold)])
        entry["layer1"] = {"file": writer.add(f"layer1_{m}.bin", block), "floats": int(block.size)}
        if relief is not None:  # the height channel (the plane's last) in terms of the latent
            entry["height"] = {"map": _pad4(m_mat[:, -1], 0.0), "offset": float(m_off[-1])}
        files.append(entry["layer1"]["file"])
        entry["files"] = files
        method_entries[m] = entry

    shader = glsl_source(channels=c_u, angular_channels=c_a, hidden=hidden, layers=layers,
                         negative_slope=float(decoder.negative_slope), angular_resolution=res, relief=relief)
    with atomic_path(out_dir / "dynbtf.glsl") as tmp:
        tmp.write_text(shader, encoding="utf-8")
    manifest = {
        "format": "dynbtf-web", "version": FORMAT_VERSION, "kind": kind, "config": cfg,
        "source": None if source is None else source.name, "precision": precision,
        "channels": c_u, "relief": relief, "angular_channels": c_a, "angular_resolution": res, "hidden": hidden, "layers": layers,
        "negative_slope": float(decoder.negative_slope), "scale": float(scale), "default_method": methods[0],
        "lattice": {"scale_hi": float(math.ldexp(math.floor(math.ldexp(LATTICE_SCALE, 24)), -24)),
                    "scale_lo": float(LATTICE_SCALE - math.ldexp(math.floor(math.ldexp(LATTICE_SCALE, 24)), -24)),
                    "n1": _N1, "n2": _N2, "c3": _C3, "local_repeats": LOCAL_REPEATS,
                    "max_repeats": MAX_REPEATS},
        "angular": angular, "decoder": {"file": decoder_file, "layers": rest_entries},
        "methods": method_entries, "shared_files": sorted({angular["f_H"]["file"], angular["f_D"]["file"],
                                                           decoder_file}),
        "files": writer.files, "shader": "dynbtf.glsl",
        "conventions": ("directions: unit vectors in the local frame (x along +u, y along +v, z = normal), w_view "
                        "towards the camera, w_light towards the light; (theta, phi) in degrees: theta from the "
                        "normal, phi from +u towards +v. Values: linear RGB, excluding cos(theta_light) (pi f_r). "
                        "uv: exemplar repeats = surface uv x scale; exact for |uv x scale| < 2**52 (split on the "
                        "CPU into a repeat origin and a local uv of at most 2**12 repeats)."),
    }
    with atomic_path(out_dir / "manifest.json") as tmp:
        tmp.write_text(json.dumps(manifest, indent=1), encoding="utf-8")
    if viewer:
        with atomic_path(out_dir / "manifest.js") as tmp:
            tmp.write_text(f"DynBTF.manifest({json.dumps(manifest)}, {json.dumps(shader)});\n", encoding="utf-8")
        here = Path(__file__).parent / "web"
        for name in _VIEWER_FILES:
            with atomic_path(out_dir / name) as tmp:
                shutil.copyfile(here / name, tmp)
    return WebExport(out_dir, manifest)
