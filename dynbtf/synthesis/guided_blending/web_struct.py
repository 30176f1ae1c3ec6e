"""Guided cell quilting (``guided-struct``) in the web shader: struct's cells, cuts and read texel
(:mod:`dynbtf.synthesis.cell_quilting.web`) with every cell's offset chosen by label
(:mod:`dynbtf.synthesis.web_form`).

A cell's offset is, from its hashed one on (``k, k + 1, ...`` mod ``K``), the first whose content in the cell (its
majority label under that offset, the table ``guidance``'s ``cell_labels``, ``(n_x, n_y, K)``) is the target's label
at the cell's centre; if none is, the hashed one. This is the fused kernel's ``_guided_cell_choice``
(:class:`~dynbtf.synthesis.guided_blending.GuidedCellQuilting`), for the query's own cell and for each neighbour
whose cut it consults, so the cuts are struct's own between the chosen offsets. The target's label at a cell's
centre is read from the target field (the constant ``field``, as guided hist reads it at a query,
:func:`dynbtf.export.web.shader.field_origin`): the cell relative to the repeat's first cell is the difference of
their int64 cell words (small), its centre that difference plus one half over the cells per repeat, in the local uv.
Labels are stored renumbered (:func:`~dynbtf.synthesis.guided_blending.web.renumbered`).
"""

from __future__ import annotations

from ..cell_quilting import web as struct_web
from ..web_form import WebForm, WebTable
from . import web as guided_web

MODE = 7
ORIGIN = "cells"
SAMPLES = 1
HASHES = struct_web.HASHES  # struct's choices; the label search hashes nothing more
#: Offsets per cell the shader's cost is counted for (the library's default ``K``).
COUNTED_OFFSETS = 16
# struct's uniforms and guidance's (the label table, the field) once each, whichever methods are exported with it
GLSL_UNIFORMS = (struct_web.GLSL_UNIFORMS, guided_web.GLSL_UNIFORMS)
_GLSL_CHOICE = """// ---- guided cell quilting (dynbtf.synthesis.guided_blending.GuidedCellQuilting): a cell's offset by label
int dynbtf_guided_cell_choice(DynbtfOrigin o, uvec2 cx, uvec2 cy) {
    int own = dynbtf_cell_choice(cx, cy);
    ivec2 n = dynbtf_cell_grid;
    ivec2 r = ivec2(int(cx.x - o.lattice.x), int(cy.x - o.lattice.z));   // the cell from the repeat's first one
    ivec2 t = dynbtf_field_texel(o, (vec2(r) + 0.5) / vec2(n));          // the target's texel at its centre
    int wanted = dynbtf_guide_entry(dynbtf_guide_target_start + t.y * dynbtf_field_size.x + t.x);
    int k = dynbtf_cell_count;
    int first = (dynbtf_mod(r.x, n.x) * n.y + dynbtf_mod(r.y, n.y)) * k;   // its cell_labels (i, j, .)
    for (int step = 0; step < k; ++step) {
        int c = own + step >= k ? own + step - k : own + step;
        if (dynbtf_guide_entry(first + c) == wanted) return c;
    }
    return own;
}

"""
_OWN_CHOICE = "dynbtf_cell_choice("
_OWN_CELL = "DynbtfCell dynbtf_cell("
if struct_web.GLSL_CELL.count(_OWN_CELL) != 1 or struct_web.GLSL_CELL.count(_OWN_CHOICE) != 6:
    raise AssertionError("struct's dynbtf_cell is not one function that chooses with dynbtf_cell_choice")
_GLSL_CELL = struct_web.GLSL_CELL.replace(_OWN_CELL, "DynbtfCell dynbtf_guided_cell(").replace(
    _OWN_CHOICE, "dynbtf_guided_cell_choice(o, ")
GLSL_FUNCTIONS = (struct_web.GLSL_CELL_TYPES, guided_web.GLSL_FUNCTIONS, _GLSL_CHOICE + _GLSL_CELL)
if struct_web.GLSL_SAMPLE.count("dynbtf_cell(o, local)") != 1:
    raise AssertionError("struct's branch does not answer with dynbtf_cell(o, local) once")
GLSL_SAMPLE = struct_web.GLSL_SAMPLE.replace("dynbtf_cell(o, local)", "dynbtf_guided_cell(o, local)")
GLSL_AFTER = struct_web.GLSL_AFTER


def cost(groups: int) -> tuple[int, int]:
    """struct's tables and, for each of the (at most four) cells chosen, the target's label and at most
    :data:`COUNTED_OFFSETS` cell labels."""
    fetches, macs = struct_web.cost(groups)
    return fetches + struct_web.HASHES * (1 + COUNTED_OFFSETS), macs


def form(synthesizer) -> WebForm:
    """struct's form (:func:`dynbtf.synthesis.cell_quilting.web.form`) with the guidance: the table ``guidance``
    (``cell_labels`` ``(n_x, n_y, K)`` and the ``target`` image, renumbered) and the target as the label ``field``."""
    base = struct_web.form(synthesizer)
    cell_labels, target = guided_web.renumbered(synthesizer.cell_labels.cpu().numpy(), synthesizer.target.image)
    table = WebTable("int16", {"cell_labels": cell_labels, "target": target})
    return WebForm(base.plane, base.tables | {"guidance": table},
                   base.constants | {"field": guided_web.target_field(synthesizer.target)})
