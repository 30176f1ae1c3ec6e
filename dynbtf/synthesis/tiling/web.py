"""Plain tiling in the web shader: one bilinear, periodic sample of the exemplar (:mod:`dynbtf.synthesis.web_form`)."""

from __future__ import annotations

from ...device import to_host
from ..web_form import WebForm

MODE = 0
ORIGIN = "lattice"
SAMPLES = 1
HASHES = 3  # the triangle's three vertices are hashed, their offsets unused
GLSL_UNIFORMS = ""
GLSL_FUNCTIONS = ""
GLSL_SAMPLE = """DynbtfTriangle tri = dynbtf_triangle(o, local);
dynbtf_bilinear(tri.texel, tri.t, 1.0, g0, g1, acc);"""
GLSL_AFTER = ""


def cost(groups: int) -> tuple[int, int]:
    """No tables besides the plane."""
    return 0, 0


def form(synthesizer) -> WebForm:
    """The exemplar itself."""
    return WebForm(to_host(synthesizer.exemplar))
