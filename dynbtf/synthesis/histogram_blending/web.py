"""Histogram-preserving blending in the web shader: three samples of the Gaussianized plane with
``(b / max b)^gamma`` weights and the variance-preserving scale, then each channel's inverse table
(:mod:`dynbtf.synthesis.web_form`)."""

from __future__ import annotations

from ...device import to_host
from ..blending.web import turn_constants
from ..web_form import WebForm, WebTable

MODE = 2
ORIGIN = "lattice"
SAMPLES = 3
HASHES = 3
GLSL_UNIFORMS = """uniform highp sampler2D dynbtf_lut;          // hist: inverse tables, channel c entry k at (k % row, c * rows + k / row)
uniform float dynbtf_gamma;                  // hist: barycentric exponent
uniform float dynbtf_g_min;                  // hist: Gaussian value of table entry 0
uniform float dynbtf_inv_step;               // hist: table entries per Gaussian unit
uniform int dynbtf_lut_size;                 // hist: entries per channel
uniform int dynbtf_lut_row;                  // hist: entries per texture row
uniform vec4 dynbtf_lut_scale[DYNBTF_G];     // hist: table value = stored * scale + bias, per channel
uniform vec4 dynbtf_lut_bias[DYNBTF_G];
"""
GLSL_FUNCTIONS = """// ---- hist: the inverse histogram tables (dynbtf.synthesis.histogram.InverseLUT)
float dynbtf_inverse_table(int c, float g) {
    float top = float(dynbtf_lut_size - 1);
    float pos = clamp((g - dynbtf_g_min) * dynbtf_inv_step, 0.0, top);
    int lo = min(int(pos), dynbtf_lut_size - 2);
    float t = pos - float(lo);
    int rows = (dynbtf_lut_size + dynbtf_lut_row - 1) / dynbtf_lut_row;
    int hi = lo + 1;
    float x0 = texelFetch(dynbtf_lut, ivec2(lo % dynbtf_lut_row, c * rows + lo / dynbtf_lut_row), 0).r;
    float x1 = texelFetch(dynbtf_lut, ivec2(hi % dynbtf_lut_row, c * rows + hi / dynbtf_lut_row), 0).r;
    return x0 + t * (x1 - x0);
}

"""
GLSL_SAMPLE = """DynbtfTriangle tri = dynbtf_triangle(o, local);
ivec2 c[3];
dynbtf_sample_texels(tri, c);
vec3 s = vec3(tri.b[0], tri.b[1], tri.b[2]);
// (b / max b)^gamma: the largest term is 1, no underflow to 0/0 (dynbtf.synthesis.histogram.blend_weights)
s = dynbtf_gamma == 1.0 ? s : pow(max(s, 0.0) / max(max(s.x, s.y), s.z), vec3(dynbtf_gamma));
s /= s.x + s.y + s.z;
s *= inversesqrt(dot(s, s));
total = dynbtf_blend3(tri, c, s, g0, g1, acc);"""
GLSL_AFTER = """for (int g = g0; g < g1; ++g) {
    vec4 v;
    for (int k = 0; k < 4; ++k) v[k] = dynbtf_inverse_table(4 * g + k, acc[g][k]);
    acc[g] = v * dynbtf_lut_scale[g] + dynbtf_lut_bias[g];
}"""


def cost(groups: int) -> tuple[int, int]:
    """Two table entries per channel, interpolated and dequantized."""
    return 2 * 4 * groups, 2 * 4 * groups


def form(synthesizer) -> WebForm:
    """The Gaussianized plane, the inverse tables (``lut``) and ``gamma``, ``g_min``, ``inv_step``."""
    kernel = synthesizer.kernel_arguments()
    return WebForm(to_host(synthesizer.prepared.plane), {"lut": WebTable("lut", to_host(kernel["lut"]))},
                   {**turn_constants(synthesizer), "gamma": float(kernel["gamma"]), "g_min": float(kernel["g_min"]),
                    "inv_step": float(1.0 / kernel["step"])})
