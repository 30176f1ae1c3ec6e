"""Hex-tiling in the web shader: three samples weighted by luminance and ``b^7``, with the contrast gain
(:mod:`dynbtf.synthesis.web_form`)."""

from __future__ import annotations

from ...device import to_host
from ..blending.web import turn_constants
from ..web_form import WebForm, WebTable

MODE = 3
ORIGIN = "lattice"
SAMPLES = 3
HASHES = 3
GLSL_UNIFORMS = """uniform highp sampler2D dynbtf_lum;          // hex: luminance in [0, 1]
uniform float dynbtf_beta;                   // hex: luminance fall-off
uniform float dynbtf_gain_k;                 // hex: contrast-gain exponent (1: none)
uniform vec4 dynbtf_lum_scale_bias;          // hex: (scale, bias, 0, 0) of the stored luminance
"""
GLSL_FUNCTIONS = """// ---- hex: the samples' luminance and the contrast gain (dynbtf.synthesis.hex_tiling)
float dynbtf_luminance(ivec2 c, vec2 t) {
    ivec2 size = dynbtf_plane_size;
    int c1 = c.x + 1 == size.x ? 0 : c.x + 1;
    int r1 = c.y + 1 == size.y ? 0 : c.y + 1;
    float v = (1.0 - t.x) * (1.0 - t.y) * texelFetch(dynbtf_lum, c, 0).r + t.x * (1.0 - t.y) * texelFetch(dynbtf_lum, ivec2(c1, c.y), 0).r
            + (1.0 - t.x) * t.y * texelFetch(dynbtf_lum, ivec2(c.x, r1), 0).r + t.x * t.y * texelFetch(dynbtf_lum, ivec2(c1, r1), 0).r;
    return v * dynbtf_lum_scale_bias.x + dynbtf_lum_scale_bias.y;
}

float dynbtf_gain(float x) {
    return x < 0.5 ? 0.5 * pow(2.0 * x, dynbtf_gain_k) : 1.0 - 0.5 * pow(max(2.0 - 2.0 * x, 0.0), dynbtf_gain_k);
}

"""
GLSL_SAMPLE = """DynbtfTriangle tri = dynbtf_triangle(o, local);
ivec2 c[3];
dynbtf_sample_texels(tri, c);
vec3 s = vec3(tri.b[0], tri.b[1], tri.b[2]);
vec3 lum = vec3(dynbtf_luminance(c[0], tri.ts[0]), dynbtf_luminance(c[1], tri.ts[1]), dynbtf_luminance(c[2], tri.ts[2]));
vec3 b = max(s, 0.0), b2 = b * b, b4 = b2 * b2;
s = (1.0 - dynbtf_beta + dynbtf_beta * lum) * (b4 * b2 * b);
s /= s.x + s.y + s.z;
if (dynbtf_gain_k != 1.0) {
    s = vec3(dynbtf_gain(s.x), dynbtf_gain(s.y), dynbtf_gain(s.z));
    s /= s.x + s.y + s.z;
}
total = dynbtf_blend3(tri, c, s, g0, g1, acc);"""
GLSL_AFTER = ""


def cost(groups: int) -> tuple[int, int]:
    """A 2 x 2 luminance footprint per sample."""
    return SAMPLES * 4, SAMPLES * 4


def form(synthesizer) -> WebForm:
    """The read plane, the luminance plane (``luminance``) and ``beta``, ``gain_k``."""
    kernel = synthesizer.kernel_arguments()
    return WebForm(to_host(synthesizer.prepared.plane), {"luminance": WebTable("single", to_host(kernel["luminance"]))},
                   {**turn_constants(synthesizer), "beta": float(kernel["beta"]), "gain_k": float(kernel["gain_k"])})
