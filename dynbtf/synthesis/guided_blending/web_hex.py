"""Guided hex-tiling (``guided-hex``) in the web shader: hex-tiling's three samples chosen by the guided search and
steered as :mod:`dynbtf.synthesis.guided_blending.web` chooses and steers hist's, then hex's luminance weights and
contrast gain (:mod:`dynbtf.synthesis.web_form`)."""

from __future__ import annotations

from ..hex_tiling import web as hex_web
from ..web_form import WebForm
from . import web as guided_web

MODE = 6
ORIGIN = "lattice"
SAMPLES = 3
HASHES = guided_web.HASHES
GLSL_UNIFORMS = guided_web.GLSL_UNIFORMS     # the same declarations as guided hist's (the shader emits them once)
GLSL_FUNCTIONS = guided_web.GLSL_FUNCTIONS
GLSL_SAMPLE = guided_web.guided_sample(hex_web.GLSL_SAMPLE)
GLSL_AFTER = hex_web.GLSL_AFTER


def cost(groups: int) -> tuple[int, int]:
    """hex's luminance footprints and the candidate search (:func:`~dynbtf.synthesis.guided_blending.web.search_cost`)."""
    fetches, macs = hex_web.cost(groups)
    search_fetches, search_macs = guided_web.search_cost()
    return fetches + search_fetches, macs + search_macs


def form(synthesizer) -> WebForm:
    """hex's form (:func:`dynbtf.synthesis.hex_tiling.web.form`) with the guidance
    (:func:`~dynbtf.synthesis.guided_blending.web.guidance`)."""
    base = hex_web.form(synthesizer)
    tables, constants = guided_web.guidance(synthesizer)
    return WebForm(base.plane, base.tables | tables, base.constants | constants)
