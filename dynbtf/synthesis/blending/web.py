"""Linear lattice blending in the web shader: three hashed samples weighted by their barycentrics
(:mod:`dynbtf.synthesis.web_form`)."""

from __future__ import annotations

from ...device import to_host
from ..sample_transform import scale_log
from ..web_form import WebForm

MODE = 1
ORIGIN = "lattice"
SAMPLES = 3
HASHES = 3
GLSL_UNIFORMS = ""
GLSL_FUNCTIONS = ""
GLSL_SAMPLE = """DynbtfTriangle tri = dynbtf_triangle(o, local);
ivec2 c[3];
dynbtf_sample_texels(tri, c);
total = dynbtf_blend3(tri, c, vec3(tri.b[0], tri.b[1], tri.b[2]), g0, g1, acc);"""
GLSL_AFTER = ""


def cost(groups: int) -> tuple[int, int]:
    """No tables besides the plane."""
    return 0, 0


def turn_constants(synthesizer) -> dict:
    """The samples' quarter turns and scales (``rotation``, ``scale_jitter``,
    :mod:`~dynbtf.synthesis.sample_transform`) as the shader's constants: whether they turn, the exponent of the
    frame's lattice weights, and ``log(1 + scale_jitter)``."""
    return {"rotation": bool(synthesizer.rotation), "frame_exponent": float(synthesizer.frame_exponent),
            "scale_log": scale_log(synthesizer.scale_jitter)}


def form(synthesizer) -> WebForm:
    """The read plane (after tileable preprocessing) and the turns."""
    return WebForm(to_host(synthesizer.prepared.plane), constants=turn_constants(synthesizer))
