"""The shader side of the web export: ``dynbtf.glsl`` (GLSL ES 3.00) and what the CPU passes it.

:func:`glsl_source` generates the shader functions that evaluate
:class:`dynbtf.infinite_btf.SynthesizedBTF` per pixel: the triangle lattice
(:mod:`dynbtf.synthesis.lattice`), the integer vertex hash (:mod:`dynbtf.synthesis.hash`, bit for
bit, in ``uint`` arithmetic), the blends of ``tile``, ``linear``, ``hist`` and ``hex``, the inverse
histogram tables, the cells, cuts and lattice offsets of ``struct``
(:mod:`dynbtf.synthesis.cell_quilting`), the Rusinkiewicz angular fetches (:mod:`dynbtf.conventions`),
the relief march of ``triple-parallax`` models and the decoder. :func:`repeat_origin` is the CPU half of its large-uv
contract (``viewer.js``'s ``DynBTF.origin`` is the same function in JavaScript; with :func:`field_origin` for a
method that reads a label field laid over the plane, e.g. guided synthesis's target; the repeat's first element
for a method whose elements vary, e.g. ``struct`` with ``brightness`` or ``tint``), and
:func:`shader_cost` counts what a pixel costs. The files and formats the shader reads are
:mod:`dynbtf.export.web.exporter`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ...errors import InputError
from ...synthesis.hash import MASK32, MIX_MULTIPLIER_1, MIX_MULTIPLIER_2, SECOND_STREAM
from ...synthesis.lattice import (_C3, _N1, _N2, LATTICE_SCALE, LATTICE_SCALE_HI, LATTICE_SCALE_LO, MAX_REPEATS,
                                 _scaled_integer, split_uv)
from ...synthesis.registry import methods_with, synthesizer_class
from ...synthesis.sample_transform import PIVOT_SHIFT, ROTATION_STREAM, SCALE_STREAM

__all__ = ["glsl_source", "shader_cost", "repeat_origin", "RepeatOrigin", "field_origin", "lattice_constants",
           "web_methods", "web_module", "LOCAL_REPEATS", "MAX_MARCH_STEPS"]



def web_methods() -> dict[str, Any]:
    """The synthesis methods the shader implements (:func:`~dynbtf.synthesis.registry.methods_with` ``"web"``, those
    that need parameters besides the exemplar included): registry name -> the method's ``web`` module
    (:mod:`dynbtf.synthesis.web_form`), in the order of their ``MODE`` numbers."""
    found = {name: synthesizer_class(name).backend_module("web")
             for name in methods_with("web", with_required=True)}
    return dict(sorted(found.items(), key=lambda item: item[1].MODE))


def web_module(method: str):
    """The ``web`` module of ``method`` (a registry name); a method without one raises :class:`InputError`."""
    methods = web_methods()
    if method not in methods:
        raise InputError(f"method: expected one of {list(methods)}, got {method!r}")
    return methods[method]
#: Repeats the shader's float32 local uv may span (beyond: the caller moves the origin).
LOCAL_REPEATS = 2 ** 12
#: Most samples of the relief ray march per pixel after the first (a march that needs more stops short of the library's).
MAX_MARCH_STEPS = 1024


def lattice_constants() -> dict[str, Any]:
    """What ``DynBTF.origin`` (viewer.js) needs to split uv as :func:`repeat_origin` does (JSON-serializable)."""
    return {"scale_hi": LATTICE_SCALE_HI, "scale_lo": LATTICE_SCALE_LO, "n1": _N1, "n2": _N2, "c3": _C3,
            "local_repeats": LOCAL_REPEATS, "max_repeats": MAX_REPEATS}


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
    cell_x, cell_y : int64
        ``I_u n_x`` and ``I_v n_y``: the ``struct`` cell index of the repeat's first cell
        (:class:`~dynbtf.synthesis.cell_quilting.CellQuilting`, ``cells = (n_x, n_y)`` per repeat;
        ``I`` itself when no cells were given).
    field : float64 ``(..., 2)``
        Where the repeat ``I`` starts on the method's label field (:func:`field_origin`), in the field's texels;
        zeros when no field was given.
    element_x, element_y : int64
        The repeat's first element instance, ``I_u columns - I_v shift`` and ``I_v rows``
        (:func:`~dynbtf.synthesis.elements.repeat_elements`; ``I`` itself when no elements were given).
    """

    lattice_x: np.ndarray
    lattice_y: np.ndarray
    phase: np.ndarray
    texel_x: np.ndarray
    texel_y: np.ndarray
    fraction: np.ndarray
    cell_x: np.ndarray
    cell_y: np.ndarray
    field: np.ndarray
    element_x: np.ndarray
    element_y: np.ndarray

    @staticmethod
    def _words(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.asarray(x).astype(np.int64).view(np.uint64)
        y = np.asarray(y).astype(np.int64).view(np.uint64)
        return np.stack([x & MASK32, x >> np.uint64(32), y & MASK32, y >> np.uint64(32)], -1).astype(np.uint32)

    def words(self) -> np.ndarray:
        """``(..., 4)`` uint32: low and high words of ``lattice_x`` and ``lattice_y`` (two's complement)."""
        return self._words(self.lattice_x, self.lattice_y)

    def cell_words(self) -> np.ndarray:
        """``(..., 4)`` uint32: low and high words of ``cell_x`` and ``cell_y`` (two's complement)."""
        return self._words(self.cell_x, self.cell_y)

    def element_words(self) -> np.ndarray:
        """``(..., 4)`` uint32: low and high words of ``element_x`` and ``element_y`` (two's complement)."""
        return self._words(self.element_x, self.element_y)

    def shader_words(self, method: str) -> np.ndarray:
        """What the shader's ``DynbtfOrigin.lattice`` holds for ``method``: :meth:`cell_words` for a method whose
        ``web`` module's ``ORIGIN`` is ``"cells"``, else :meth:`words`."""
        return self.cell_words() if web_module(method).ORIGIN == "cells" else self.words()


def field_origin(whole, field: dict[str, Any]) -> np.ndarray:
    """Where whole repeats ``whole (..., 2)`` (float64 integers) lie on a label field laid over the plane, in the
    field's texels ``(..., 2)`` float64: the CPU half of the shader's ``dynbtf_field_texel``.

    ``field`` (a method's manifest entry ``"field"``, :mod:`dynbtf.synthesis.web_form`): ``width`` x ``height``
    texels over ``size`` x ``size`` exemplar repeats from the origin, ``wrap`` ``"repeat"`` (tiled: the repeat is
    first reduced modulo ``size`` as :class:`~dynbtf.synthesis.guided_blending.LabelField` reduces a position, so
    the result lies in ``[0, width) x [0, height)``) or ``"clamp"`` (the position itself, bounded to a range the
    local uv cannot leave the field's edge texels from). The shader adds the local uv times ``(width, height) /
    size`` in float32 and takes the texel, wrapped or clamped.
    """
    whole = np.asarray(whole, dtype=np.float64)
    size = float(field["size"])
    dims = np.array([field["width"], field["height"]], dtype=np.float64)
    if field["wrap"] == "repeat":
        return (whole - np.floor(whole / size) * size) / size * dims
    bound = (LOCAL_REPEATS + 1) / size * dims + dims + 1.0
    return np.clip(whole / size * dims, -bound, bound)


def repeat_origin(points, plane_size: tuple[int, int], density: tuple[int, int],
                  cells: tuple[int, int] = (1, 1), field: dict[str, Any] | None = None,
                  elements: tuple[int, int, int] = (1, 1, 0)) -> RepeatOrigin:
    """Split positions ``points (..., 2)`` (exemplar repeats, float64) for the shader.

    ``plane_size = (W', H')`` of the plane read, ``density = (W, H)`` texels per repeat, ``cells =
    (n_x, n_y)`` the ``struct`` cells per repeat, ``field`` the method's label field if it has one
    (:func:`field_origin`), ``elements = (columns, rows, shift)`` its element grid if its elements vary
    (:func:`~dynbtf.synthesis.elements.repeat_elements`). The arithmetic is
    :func:`dynbtf.synthesis.lattice.triangle_lattice`'s (same float64 and int64 operations), so the
    shader's vertices are the library's; the cell index ``I n`` is
    :meth:`~dynbtf.synthesis.cell_quilting.CellQuilting.read_positions`'s (int64). ``|points| < 2**52``
    is required.
    """
    points = torch.as_tensor(np.asarray(points, dtype=np.float64))
    if points.numel() and float(points.abs().max()) >= MAX_REPEATS:
        raise InputError(f"uv: |uv * scale| must be below 2**52 = {int(MAX_REPEATS)} exemplar repeats")
    whole, frac = split_uv(points)
    iu_whole, iu_frac = _scaled_integer(whole[..., 0])
    pw, ph = plane_size
    dw, dh = density
    nx, ny = (int(c) for c in cells)
    columns, rows, shift = (int(e) for e in elements)
    return RepeatOrigin(
        lattice_x=(iu_whole - 2 * whole[..., 1]).numpy(), lattice_y=(4 * whole[..., 1]).numpy(),
        phase=iu_frac.numpy(),
        texel_x=torch.remainder(torch.remainder(whole[..., 0], pw) * (dw % pw), pw).numpy(),
        texel_y=torch.remainder(torch.remainder(whole[..., 1], ph) * (dh % ph), ph).numpy(),
        fraction=frac.numpy(), cell_x=(whole[..., 0] * nx).numpy(), cell_y=(whole[..., 1] * ny).numpy(),
        field=np.zeros(frac.shape) if field is None else field_origin(whole.numpy(), field),
        element_x=(whole[..., 0] * columns - whole[..., 1] * shift).numpy(), element_y=(whole[..., 1] * rows).numpy())


# ---------------------------------------------------------------- the shader
def _float(x: float) -> str:
    """A GLSL float literal that rounds to the float32 nearest ``x``."""
    return repr(float(np.float32(x))) if math.isfinite(x) else "0.0"


def _constant_array(name: str, kind: str, values: np.ndarray) -> str:
    """``const mat4/vec4 name[n] = ...;`` from a flat float32 array of column-major mat4s or vec4s."""
    size = 16 if kind == "mat4" else 4
    rows = np.asarray(values, dtype=np.float32).reshape(-1, size)
    items = ",\n    ".join(f"{kind}(" + ", ".join(repr(float(v)) for v in row) + ")" for row in rows)
    return f"const {kind} {name}[{len(rows)}] = {kind}[{len(rows)}](\n    {items});"


def glsl_source(*, channels: int, angular_channels: int, hidden: int, layers: int, negative_slope: float,
                angular_resolution: int, angular_weights: np.ndarray, rest_weights: list[tuple[np.ndarray, np.ndarray]],
                relief: dict[str, float] | None = None) -> str:
    """The shader functions of ``dynbtf.glsl`` for a decoder of these sizes (GLSL ES 3.00, no ``#version``).

    Sizes are compile-time constants, and so are the decoder weights every method shares:
    ``angular_weights`` (layer 1's angular part) and ``rest_weights`` (layers 2.., each
    ``(mat4 blocks, vec4 biases)``), all flat float32 arrays in the order of
    :func:`dynbtf.export.web.exporter` 's ``decoder.bin`` (literals that parse to the same float32
    values; as constants they run faster in software GL than read from uniform blocks).
    The method's quantities (tables, parameters, layer 1's positional part with its output map
    folded in) are uniforms, a uniform block and textures, so one program serves every method.
    ``relief`` (models with a height field: ``h_min``, ``h_max``, ``step``, ``max_step``, ``surface_slope``, ``aspect``,
    ``height_scale``) adds the ray march of
    :func:`dynbtf.representations.parallax.march_visible_uv` through the synthesized height.

    The source is the concatenation, in this order, of: the header (sizes, the uniforms shared and each
    method's, decoder constants), the integer part of a position and the hash, the triangle lattice, the
    texel fetches and the lattice samples' blend, each method's functions, ``dynbtf_latent`` (a branch per
    method, :func:`web_methods`), ``dynbtf_gain`` (the factor of a method whose elements vary), the angular
    features, then the decoder (with the relief march, if any)
    and ``dynbtf_eval``.
    """
    if len(rest_weights) != layers - 1:
        raise InputError(f"glsl_source: expected weights of {layers - 1} layers after the first, got {len(rest_weights)}")
    sizes = dict(channels=channels, angular_channels=angular_channels, hidden=hidden, layers=layers)
    methods = web_methods()
    return "".join([
        _glsl_header(**sizes, angular_resolution=angular_resolution,
                     constants=_glsl_decoder_constants(angular_weights, rest_weights), methods=methods),
        _glsl_integers(),
        _glsl_triangle(),
        _glsl_fetches(),
        *_once(web.GLSL_FUNCTIONS for web in methods.values()),
        _glsl_latent(methods),
        _glsl_gain(methods),
        _glsl_angular(angular_resolution),
        _glsl_decoder_and_eval(**sizes, negative_slope=negative_slope, relief=relief),
    ])


def _once(blocks) -> list[str]:
    """``blocks`` of GLSL with repeats left out (methods that share uniforms or functions declare them once); a
    method's blocks may be a tuple of blocks (e.g. another method's and its own), each kept once."""
    flat = [b for block in blocks for b in ((block,) if isinstance(block, str) else block)]
    return list(dict.fromkeys(flat))


def _groups(n: int) -> int:
    """RGBA layers (vec4) holding ``n`` channels: ``ceil(n / 4)``."""
    return (n + 3) // 4


def _glsl_decoder_constants(angular_weights: np.ndarray, rest_weights: list[tuple[np.ndarray, np.ndarray]]
                            ) -> list[str]:
    """``const`` arrays of the decoder weights every method shares: ``dynbtf_w1a`` (layer 1's angular part,
    mat4 blocks), then ``dynbtf_wK`` (mat4 blocks) and ``dynbtf_bK`` (vec4 biases) of each layer ``K >= 2``."""
    constants = [_constant_array("dynbtf_w1a", "mat4", angular_weights)]
    for k, (weights, biases) in enumerate(rest_weights, start=2):
        constants += [_constant_array(f"dynbtf_w{k}", "mat4", weights), _constant_array(f"dynbtf_b{k}", "vec4", biases)]
    return constants


def _glsl_header(*, channels: int, angular_channels: int, hidden: int, layers: int, angular_resolution: int,
                 constants: list[str], methods: dict[str, Any]) -> str:
    """The header: what the shader evaluates, its sizes (``DYNBTF_G``, ``DYNBTF_AG``, ``DYNBTF_HG``: RGBA
    layers of the positional, angular and hidden channels), the uniforms and textures every method reads, those of
    each of ``methods`` (:func:`web_methods`), the ``DynbtfLayer1`` uniform block (``hg * g`` mat4 and ``hg``
    vec4) and the decoder ``constants``."""
    g, ag, hg = _groups(channels), _groups(angular_channels), _groups(hidden)
    names = ", ".join(methods)
    modes = ", ".join(f"{web.MODE} {name}" for name, web in methods.items())
    method_uniforms = "".join(_once(web.GLSL_UNIFORMS for web in methods.values()))
    return f"""// dynbtf real-time shader functions (GLSL ES 3.00), generated by dynbtf.export.web.shader.
// Evaluates dynbtf.infinite_btf.SynthesizedBTF: synthesized positional features ({names}),
// Rusinkiewicz angular features and the decoder. Conventions (dynbtf README):
// directions are unit vectors in the local frame (x along +u, y along +v, z = normal), both
// pointing away from the surface; the value excludes cos(theta_light) (pi f_r), linear RGB.
// Sizes: {channels} positional channels ({g} RGBA layers), {angular_channels} angular channels per plane
// ({angular_resolution}x{angular_resolution}), decoder {layers} layers of {hidden} hidden units.

#define DYNBTF_G {g}
#define DYNBTF_AG {ag}
#define DYNBTF_HG {hg}

// ---- per-method state (set by the host for the method in use)
uniform highp sampler2DArray dynbtf_plane;   // the plane the method reads, RGBA layers
uniform highp sampler2DArray dynbtf_fh;      // angular planes: x = phi column, y = theta row
uniform highp sampler2DArray dynbtf_fd;
uniform int dynbtf_mode;                     // {modes}
uniform ivec2 dynbtf_plane_size;             // (W', H') of the plane read
uniform ivec2 dynbtf_density;                // (W, H): texels per repeat
uniform uint dynbtf_seed_state;              // mix32((seed ^ 0x85EBCA6B)) (dynbtf.synthesis.hash.seed_state)
uniform vec4 dynbtf_plane_scale[DYNBTF_G];   // value = stored * scale + bias, per channel
uniform vec4 dynbtf_plane_bias[DYNBTF_G];
uniform ivec2 dynbtf_field_size;             // the method's label field, if any ("field"): (width, height) texels
uniform vec2 dynbtf_field_scale;             // its texels per exemplar repeat: (width, height) / size
uniform int dynbtf_field_wrap;               // 1: it repeats every size repeats, 0: its edge texels extend it
uniform int dynbtf_rotation;                 // lattice methods: 1: samples turned by quarter turns (sample_transform)
uniform float dynbtf_frame_exponent;         // ... and the frame's lattice weights b^p (hist: gamma, hex: 7, linear: 1)
uniform float dynbtf_scale_log;              // lattice methods: log(1 + scale_jitter), 0: samples not scaled
{method_uniforms}uniform vec4 dynbtf_fh_scale[DYNBTF_AG];
uniform vec4 dynbtf_fh_bias[DYNBTF_AG];
uniform vec4 dynbtf_fd_scale[DYNBTF_AG];
uniform vec4 dynbtf_fd_bias[DYNBTF_AG];

// decoder: layer 1 = positional part (the method's output map folded in) + bias, per method ...
layout(std140) uniform DynbtfLayer1 {{ mat4 dynbtf_w1p[{hg * g}]; vec4 dynbtf_b1[{hg}]; }};
// ... + angular part, and layers 2.. (the same for every method): constants
{chr(10).join(constants)}

"""


def _glsl_integers() -> str:
    """``DynbtfOrigin`` (a position's integer part, from :func:`repeat_origin`), the uint hash
    (:mod:`dynbtf.synthesis.hash`), 64-bit (low, high) word addition, a non-negative ``mod`` and the texel of a
    method's label field under a query (``dynbtf_field_texel``, :func:`field_origin`)."""
    return f"""// ---- the integer part of a position (computed on the CPU in float64: dynbtf.export.web.shader.repeat_origin)
struct DynbtfOrigin {{
    uvec4 lattice;   // (low, high) words of the int64 lattice x, then of lattice y; struct: of the cell I_u n_x, I_v n_y
    float phase;     // 2 sqrt(3) I_u mod 1
    ivec2 texel;     // (I_u W mod W', I_v H mod H')
    vec2 field;      // where the repeat starts on the method's label field, in its texels (methods with a field only)
    uvec4 element;   // (low, high) words of the repeat's first element instance (column, row) (methods whose elements vary)
}};

// ---- integer hash (dynbtf.synthesis.hash): lowbias32, uint arithmetic wraps modulo 2^32
uint dynbtf_mix32(uint x) {{
    x ^= x >> 16u; x *= {MIX_MULTIPLIER_1:#010x}u; x ^= x >> 15u; x *= {MIX_MULTIPLIER_2:#010x}u; return x ^ (x >> 16u);
}}
uint dynbtf_fold(uint h, uvec2 k) {{ return dynbtf_mix32(dynbtf_mix32(h ^ k.x) ^ k.y); }}
// 64-bit two's complement (low, high) + a small signed int
uvec2 dynbtf_add(uvec2 a, int d) {{
    uint lo = a.x + (d < 0 ? ~uint(-1 - d) : uint(d));   // two's complement of d without converting a negative int
    return uvec2(lo, a.y + (d < 0 ? 0xFFFFFFFFu : 0u) + (lo < a.x ? 1u : 0u));
}}
int dynbtf_mod(int a, int n) {{ return a >= 0 ? a % n : (n - 1) - ((-a - 1) % n); }}

// the label field's texel under a query (dynbtf.export.web.shader.field_origin): the repeat's position on the
// field plus the local uv's, wrapped or clamped
ivec2 dynbtf_field_texel(DynbtfOrigin o, vec2 local) {{
    ivec2 n = dynbtf_field_size;
    vec2 p = floor(o.field + local * dynbtf_field_scale);
    if (dynbtf_field_wrap == 1) return ivec2(dynbtf_mod(int(p.x), n.x), dynbtf_mod(int(p.y), n.y));
    return ivec2(clamp(p, vec2(0.0), vec2(n - 1)));
}}

"""


def _glsl_triangle() -> str:
    """The lattice methods' triangle (:mod:`dynbtf.synthesis.lattice`): ``dynbtf_split``, ``dynbtf_triangle``
    (int64 vertices, barycentrics, hashed whole-texel offsets, the bilinear footprint on the read plane).

    ``2 sqrt(3)`` enters as a 12-bit high part (exact products for ``|w_u| < 2**12`` repeats) plus the rest.
    """
    hi_scale = math.ldexp(math.floor(math.ldexp(LATTICE_SCALE, 10)), -10)  # 12 significant bits
    lo_scale = LATTICE_SCALE - hi_scale
    return f"""// ---- the triangle lattice (dynbtf.synthesis.lattice) and the vertices' hashed whole-texel offsets
struct DynbtfTriangle {{
    uvec2 vx[3]; uvec2 vy[3];  // int64 vertex coordinates as (low, high) words
    float b[3];                // barycentrics
    ivec2 offset[3];           // (ox, oy) of each vertex
    ivec2 texel;               // texel of the bilinear footprint's corner (before offsets), on the read plane
    vec2 t;                    // bilinear weights inside the footprint
    ivec2 shift[3];            // turned samples: each one's whole texels moved (0 unturned) ...
    vec2 ts[3];                // ... and its own bilinear weights (t unturned)
}};

// the frame (cos, sin) of the content the last dynbtf_latent synthesized: its turned samples' circular mean
// (dynbtf.synthesis.sample_transform.frame_direction); dynbtf_decode turns the view and the light into it
vec2 dynbtf_frame = vec2(1.0, 0.0);

// whole repeats and fraction in [0, 1) of the local uv (dynbtf.synthesis.lattice.split_uv)
void dynbtf_split(vec2 local, out vec2 whole, out vec2 f) {{
    whole = floor(local);
    f = local - whole;
    if (f.x >= 1.0) {{ f.x -= 1.0; whole.x += 1.0; }}
    if (f.y >= 1.0) {{ f.y -= 1.0; whole.y += 1.0; }}
}}

DynbtfTriangle dynbtf_triangle(DynbtfOrigin o, vec2 local) {{
    DynbtfTriangle tri;
    vec2 wf, f;
    dynbtf_split(local, wf, f);
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
    uint hashes[3];
    for (int i = 0; i < 3; ++i) {{
        uint h = dynbtf_fold(dynbtf_fold(dynbtf_seed_state, tri.vx[i]), tri.vy[i]);
        hashes[i] = h;
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
    for (int i = 0; i < 3; ++i) {{ tri.shift[i] = ivec2(0); tri.ts[i] = tri.t; }}
    if (dynbtf_rotation == 1 || dynbtf_scale_log != 0.0) {{   // turns and scales about each vertex's pivot
                                                             // (dynbtf.synthesis.sample_transform)
        vec2 steps[3];   // the vertices, from the triangle's base vertex
        if (z > 0.0) {{ steps[0] = vec2(0.0); steps[1] = vec2(0.0, 1.0); steps[2] = vec2(1.0, 0.0); }}
        else {{ steps[0] = vec2(1.0); steps[1] = vec2(1.0, 0.0); steps[2] = vec2(0.0, 1.0); }}
        vec3 b = vec3(tri.b[0], tri.b[1], tri.b[2]);
        vec3 s = dynbtf_frame_exponent == 1.0 ? b
                 : pow(max(b, 0.0) / max(max(b.x, b.y), b.z), vec3(dynbtf_frame_exponent));
        s /= s.x + s.y + s.z;
        vec2 frame = vec2(0.0);
        for (int i = 0; i < 3; ++i) {{
            uint turns = dynbtf_rotation == 1 ? dynbtf_mix32(hashes[i] ^ {ROTATION_STREAM:#010x}u) & 3u : 0u;
            vec2 cs = turns == 0u ? vec2(1.0, 0.0) : turns == 1u ? vec2(0.0, 1.0) : turns == 2u ? vec2(-1.0, 0.0)
                                                                                             : vec2(0.0, -1.0);
            frame += s[i] * cs;
            if (dynbtf_scale_log != 0.0) {{   // 1 / f, f = exp((2 r - 1) log(1 + j)), r: 24 bits of the hash
                float r = float(dynbtf_mix32(hashes[i] ^ {SCALE_STREAM:#010x}u) >> 8u) * {_float(1.0 / 16777216.0)};
                cs *= exp((1.0 - 2.0 * r) * dynbtf_scale_log);
            }}
            vec2 l = b.x * (steps[0] - steps[i]) + b.y * (steps[1] - steps[i]) + b.z * (steps[2] - steps[i]);
            vec2 d = vec2((l.x + 0.5 * l.y) * {_float(1.0 / LATTICE_SCALE)} * float(dynbtf_density.x),
                          0.25 * l.y * float(dynbtf_density.y));
            vec2 m = tri.t - floor(tri.t - d + {_float(0.5 + PIVOT_SHIFT)});
            vec2 q = tri.t + vec2((cs.x - 1.0) * m.x - cs.y * m.y, cs.y * m.x + (cs.x - 1.0) * m.y);
            vec2 whole = floor(q);
            tri.shift[i] = ivec2(whole);
            tri.ts[i] = q - whole;
        }}
        float len = length(frame);
        if (dynbtf_rotation == 1) dynbtf_frame = len > 0.0 ? frame / len : vec2(1.0, 0.0);
    }}
    return tri;
}}

"""


def _glsl_fetches() -> str:
    """Texel fetches: the bilinear footprint of the plane (every method), and the lattice methods' three samples:
    their texels on the read plane (``dynbtf_sample_texels``) and their weighted blend (``dynbtf_blend3``)."""
    return """// ---- fetches
void dynbtf_bilinear(ivec2 c, vec2 t, float weight, int g0, int g1, inout vec4 acc[DYNBTF_G]) {
    ivec2 size = dynbtf_plane_size;
    int c1 = c.x + 1 == size.x ? 0 : c.x + 1;
    int r1 = c.y + 1 == size.y ? 0 : c.y + 1;
    float w00 = weight * (1.0 - t.x) * (1.0 - t.y), w01 = weight * t.x * (1.0 - t.y);
    float w10 = weight * (1.0 - t.x) * t.y, w11 = weight * t.x * t.y;
    for (int g = g0; g < g1; ++g) {
        acc[g] += w00 * texelFetch(dynbtf_plane, ivec3(c.x, c.y, g), 0) + w01 * texelFetch(dynbtf_plane, ivec3(c1, c.y, g), 0)
                + w10 * texelFetch(dynbtf_plane, ivec3(c.x, r1, g), 0) + w11 * texelFetch(dynbtf_plane, ivec3(c1, r1, g), 0);
    }
}

// the three samples of a lattice triangle: each vertex's hashed offset (and a turned sample's shift) added to the
// shared footprint's texel
void dynbtf_sample_texels(DynbtfTriangle tri, out ivec2 c[3]) {
    ivec2 size = dynbtf_plane_size;
    for (int i = 0; i < 3; ++i) c[i] = ivec2(dynbtf_mod(tri.texel.x + tri.offset[i].x + tri.shift[i].x, size.x),
                                             dynbtf_mod(tri.texel.y + tri.offset[i].y + tri.shift[i].y, size.y));
}

// the samples blended with weights s; returns the sum of the weights
float dynbtf_blend3(DynbtfTriangle tri, ivec2 c[3], vec3 s, int g0, int g1, inout vec4 acc[DYNBTF_G]) {
    for (int i = 0; i < 3; ++i) dynbtf_bilinear(c[i], tri.ts[i], s[i], g0, g1, acc);
    return s.x + s.y + s.z;
}

"""


def _indented(code: str, spaces: int) -> str:
    """``code``'s lines indented by ``spaces``."""
    return "".join(" " * spaces + line + "\n" for line in code.splitlines())


def _glsl_latent(methods: dict[str, Any]) -> str:
    """``dynbtf_latent``: the synthesized positional features before the output map, a branch per method
    (``dynbtf_mode``: each ``web`` module's ``GLSL_SAMPLE``, then the plane's dequantization and its ``GLSL_AFTER``);
    only the channel groups ``[g0, g1)`` (the others are 0: a relief march reads the height's group alone)."""
    branches = " else ".join(f"if (dynbtf_mode == {web.MODE}) {{\n{_indented(web.GLSL_SAMPLE, 8)}    }}"
                             for web in methods.values())
    after = "".join(f"    if (dynbtf_mode == {web.MODE}) {{\n{_indented(web.GLSL_AFTER, 8)}    }}\n"
                    for web in methods.values() if web.GLSL_AFTER)
    return f"""// ---- synthesized positional features before the output map (the "latent", DYNBTF_G vec4)
void dynbtf_latent(DynbtfOrigin o, vec2 local, int g0, int g1, out vec4 latent[DYNBTF_G]) {{
    vec4 acc[DYNBTF_G];
    for (int g = 0; g < DYNBTF_G; ++g) acc[g] = vec4(0.0);
    float total = 1.0;
    dynbtf_frame = vec2(1.0, 0.0);   // (a turned lattice method's dynbtf_triangle sets it)
    {branches}
    for (int g = g0; g < g1; ++g) acc[g] = acc[g] * dynbtf_plane_scale[g] + total * dynbtf_plane_bias[g];
{after}    for (int g = 0; g < DYNBTF_G; ++g) latent[g] = acc[g];
}}

"""


def _glsl_gain(methods: dict[str, Any]) -> str:
    """``dynbtf_gain``: the RGB factor a method applies to the decoded value at a point (its ``web`` module's
    ``GLSL_GAIN``, e.g. ``struct``'s per-element variation), 1 for the others."""
    branches = "".join(f"    if (dynbtf_mode == {web.MODE}) {{\n{_indented(web.GLSL_GAIN, 8)}    }}\n"
                       for web in methods.values() if getattr(web, "GLSL_GAIN", ""))
    return f"""// ---- the method's factor on the decoded value (1 unless its elements vary)
vec3 dynbtf_gain(DynbtfOrigin o, vec2 local) {{
{branches}    return vec3(1.0);
}}

"""


def _glsl_angular(angular_resolution: int) -> str:
    """The angular features: Rusinkiewicz difference vector and the bilinear fetch of an
    ``R x R`` angular plane (``R = angular_resolution``) at ``(theta / 90 deg, phi / 360 deg)``."""
    return f"""// ---- angular features (dynbtf.conventions: Rusinkiewicz h and d, plane coords (theta/90, phi/360))
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
"""


def _glsl_relief(relief: dict[str, float] | None) -> str:
    """The relief ray march (``dynbtf_height``, ``dynbtf_visible``) when ``relief`` is given, else ``""``.

    ``relief``: ``h_min``, ``h_max`` (height range, repeats), ``step``, ``max_step`` (shortest and longest search
    step, repeats), ``surface_slope``, ``aspect`` (the plane's rows over columns) and ``height_scale``, as
    :func:`dynbtf.representations.parallax.march_visible_uv` uses them.
    """
    if not relief:
        return ""
    return f"""
#define DYNBTF_RELIEF 1
// ---- relief (dynbtf.representations.parallax): features are read where the camera ray meets the
// synthesized height field, searched from h_max down to h_min in steps of {_float(relief["step"])} to
// {_float(relief["max_step"])} repeats, the hit's bracket halved down to {_float(relief["step"])}
uniform vec4 dynbtf_height_map[DYNBTF_G];   // height channel = latent . map + offset (the method's output map)
uniform float dynbtf_height_offset;
#define DYNBTF_MAX_MARCH {MAX_MARCH_STEPS}
float dynbtf_height(DynbtfOrigin o, vec2 p) {{
    // only the latent groups the height map mixes (one where the height is synthesized as a channel of its own)
    int g0 = DYNBTF_G, g1 = 0;
    for (int g = 0; g < DYNBTF_G; ++g) {{
        if (dynbtf_height_map[g] != vec4(0.0)) {{ g0 = min(g0, g); g1 = g + 1; }}
    }}
    vec4 x[DYNBTF_G];
    dynbtf_latent(o, p, g0, max(g1, g0), x);
    float h = dynbtf_height_offset;
    for (int g = 0; g < DYNBTF_G; ++g) h += dot(x[g], dynbtf_height_map[g]);
    return h * {_float(relief["height_scale"])};
}}
vec2 dynbtf_visible(DynbtfOrigin o, vec2 local, vec3 w) {{
    const float h_min = {_float(relief["h_min"])}, h_max = {_float(relief["h_max"])};
    if (w.z <= 0.0) w = vec3(0.0, 0.0, 1.0);
    vec2 slope = w.xy / max(w.z, 1e-6) * vec2(1.0, {_float(relief["aspect"])});
    float len = max(length(slope), 1e-12);
    float shortest = {_float(relief["step"])} / len, longest = {_float(relief["max_step"])} / len;
    float fine = {_float(relief["step"] * (1.0 + 1e-6))} / len, climb = 1.0 + {_float(relief["surface_slope"])} * len;
    float z_hi = h_max, f_hi = dynbtf_height(o, local + h_max * slope) - h_max;
    float z_lo = h_max, f_lo = f_hi;
    bool bracketed = f_hi >= 0.0;
    for (int k = 0; k < DYNBTF_MAX_MARCH && !(bracketed && z_hi - z_lo <= fine); ++k) {{
        float search = max(z_hi - min(max(-f_hi / climb, shortest), longest), h_min);
        float z = bracketed ? 0.5 * (z_lo + z_hi) : search;
        float f = dynbtf_height(o, local + z * slope) - z;
        if (f >= 0.0 || (!bracketed && search <= h_min)) {{
            z_lo = z; f_lo = f; bracketed = true;
        }} else {{
            z_hi = z; f_hi = f;
        }}
    }}
    float t = f_lo - f_hi != 0.0 ? clamp(f_lo / (f_lo - f_hi), 0.0, 1.0) : 0.0;
    return local + (z_lo + t * (z_hi - z_lo)) * slope;
}}
"""


def _glsl_decoder_statements(*, channels: int, angular_channels: int, hidden: int, layers: int) -> list[str]:
    """The decoder unrolled into ``mat4 x vec4`` statements on named vec4 variables ``yK_q`` (layer ``K``,
    RGBA group ``q``; the last layer has one group, its ``.rgb`` is the value)."""
    g, ag, hg = _groups(channels), _groups(angular_channels), _groups(hidden)
    # no local arrays: software GL keeps named variables in registers; GPU compilers unroll constant loops anyway
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
    return decoder_code


def _glsl_decoder_and_eval(*, channels: int, angular_channels: int, hidden: int, layers: int,
                           negative_slope: float, relief: dict[str, float] | None) -> str:
    """The LeakyReLU, the relief march (:func:`_glsl_relief`) and ``dynbtf_eval``: latent at the visible
    point, angular features, the unrolled decoder; linear RGB, zero below either horizon."""
    relief_code = _glsl_relief(relief)
    decoder_code = _glsl_decoder_statements(channels=channels, angular_channels=angular_channels, hidden=hidden,
                                            layers=layers)
    return f"""
vec4 dynbtf_leaky(vec4 x) {{ return max(x, 0.0) + {_float(negative_slope)} * min(x, 0.0); }}

{relief_code}
// ---- the decoder on synthesized features x (dynbtf_latent's): linear RGB, excluding cos(theta_light)
vec3 dynbtf_decode(vec4 x[DYNBTF_G], vec3 w_view, vec3 w_light) {{
    vec2 f = dynbtf_frame;   // the frame of the features x (dynbtf_latent's): view and light turned into it
    w_view = vec3(f.x * w_view.x - f.y * w_view.y, f.y * w_view.x + f.x * w_view.y, w_view.z);
    w_light = vec3(f.x * w_light.x - f.y * w_light.y, f.y * w_light.x + f.x * w_light.y, w_light.z);
    vec3 sum = w_view + w_light;
    vec3 h = dot(sum, sum) < 1e-24 ? vec3(0.0, 0.0, 1.0) : normalize(sum);
    vec4 fh[DYNBTF_AG], fd[DYNBTF_AG];
    dynbtf_angular_fetch(dynbtf_fh, h, dynbtf_fh_scale, dynbtf_fh_bias, fh);
    dynbtf_angular_fetch(dynbtf_fd, dynbtf_difference(h, w_light), dynbtf_fd_scale, dynbtf_fd_bias, fd);
{chr(10).join(decoder_code)}
    return y{layers}_0.rgb;
}}

// ---- the BTF value: linear RGB, excluding cos(theta_light); zero below either horizon
vec3 dynbtf_eval(DynbtfOrigin o, vec2 local, vec3 w_view, vec3 w_light) {{
    if (w_view.z < 0.0 || w_light.z < 0.0) return vec3(0.0);
    vec4 x[DYNBTF_G];
    vec2 p = {"dynbtf_visible(o, local, w_view)" if relief else "local"};
    dynbtf_latent(o, p, 0, DYNBTF_G, x);
    return dynbtf_decode(x, w_view, w_light) * dynbtf_gain(o, p);
}}
"""


def shader_cost(method: str, *, channels: int = 16, angular_channels: int = 8, hidden: int = 32, layers: int = 4
                ) -> dict[str, int]:
    """Work per pixel of ``dynbtf_eval`` as ``dynbtf.glsl`` does it: texel fetches, multiply-adds, hashes.

    Fetches are ``texelFetch`` calls of RGBA (or single-channel) texels: each of the method's ``SAMPLES`` reads a
    2 x 2 bilinear footprint of ``ceil(C / 4)`` RGBA layers, each angular plane a 2 x 2 footprint of
    ``ceil(C_A / 4)`` layers, and the method's own tables what its ``web`` module's ``cost`` says (e.g. the
    inverse histogram tables, the cut tables; counted: the most a pixel reads). Multiply-adds count the bilinear
    and blend weights applied to every channel, the per-channel dequantization, the method's table
    interpolation, and the decoder's layers as the shader runs them (``mat4 x vec4`` blocks: widths padded to
    multiples of 4), not the integer hash or the lattice's few scalar operations. ``hashes`` counts
    :func:`~dynbtf.synthesis.hash.hash_vertex` evaluations (four 32-bit ``mix32`` each), the method's ``HASHES``.
    ``method``: a registry name with a ``web`` form (:func:`web_methods`).
    """
    web = web_module(method)
    g, ag, hg = (channels + 3) // 4, (angular_channels + 3) // 4, (hidden + 3) // 4
    samples = web.SAMPLES
    fetches = samples * 4 * g + 2 * 4 * ag
    macs = samples * 4 * 4 * g + 4 * g + 2 * (4 * 4 * ag + 4 * ag)  # bilinear+blend weights, dequantization
    table_fetches, table_macs = web.cost(g)  # the method's own tables
    decoder = 16 * hg * (g + 2 * ag) + 16 * hg * hg * (layers - 2) + 16 * hg
    return {"texel_fetches": fetches + table_fetches, "macs": macs + table_macs + decoder, "decoder_macs": decoder,
            "hashes": web.HASHES}
