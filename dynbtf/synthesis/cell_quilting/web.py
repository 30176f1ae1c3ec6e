"""Cell quilting (``struct``) in the web shader: the query's cell, the cuts that may give the point to a neighbour,
that cell's hashed lattice offset and one bilinear sample of the exemplar (:mod:`dynbtf.synthesis.web_form`); with
``brightness`` or ``tint``, each element's factor on the decoded value (``GLSL_GAIN``)."""

from __future__ import annotations

import numpy as np

from ...device import to_host
from ..elements import VARIATION_SALT, repeat_elements
from ..hash import MASK32, SECOND_STREAM, seed_state
from ..web_form import WebForm, WebTable

MODE = 4
ORIGIN = "cells"
SAMPLES = 1
HASHES = 4  # its own cell and at most three more (the neighbours across the edges within the cut bands, the diagonal)
GLSL_UNIFORMS = """uniform highp isampler2D dynbtf_cells;       // struct: offsets, vertical cuts, horizontal cuts (int16), entry k at (k % row, k / row)
uniform ivec2 dynbtf_cell_grid;              // struct: cells per repeat (n_x, n_y)
uniform ivec2 dynbtf_cell_margin;            // struct: half-widths of the cut bands (m_x, m_y), texels
uniform int dynbtf_cell_count;               // struct: K, the number of lattice offsets
uniform int dynbtf_cell_row;                 // struct: table entries per texture row
uniform ivec2 dynbtf_cut_start;              // struct: first entry of the vertical and of the horizontal cuts
uniform ivec4 dynbtf_element_grid;           // struct's elements: columns, rows per repeat, row shift p / q of an element
uniform vec2 dynbtf_element_phase;           // ... their placement on the exemplar (phase_x, phase_y), texels
uniform vec2 dynbtf_variation;               // ... per-element variation (brightness, tint); (0, 0): off
uniform uint dynbtf_variation_state;         // ... its hash state: seed_state((seed ^ VARIATION_SALT) mod 2^32)
uniform int dynbtf_joint_start;              // ... first entry of the joints (H x W, 1 on a joint) in dynbtf_cells
"""
GLSL_CELL_TYPES = """// ---- lattice-aligned cell quilting (dynbtf.synthesis.cell_quilting): the cell, its hashed offset, the cuts
struct DynbtfCell {
    uvec2 cx; uvec2 cy;   // the query's own cell, int64 (low, high) words: I n + w n + column (row)
    ivec2 side;           // -1, 0 or 1 per axis: the point belongs to this neighbour of its cell (both: the diagonal one)
    int chosen;           // offset index (hash of that cell mod K)
    ivec2 offset;         // its lattice offset (dx, dy), texels
    ivec2 texel;          // texel of the bilinear footprint's corner on the exemplar, offset applied
    vec2 t;               // bilinear weights inside the footprint
};

int dynbtf_cell_entry(int k) { return texelFetch(dynbtf_cells, ivec2(k % dynbtf_cell_row, k / dynbtf_cell_row), 0).r; }
int dynbtf_cell_choice(uvec2 cx, uvec2 cy) {
    return int(dynbtf_fold(dynbtf_fold(dynbtf_seed_state, cx), cy) % uint(dynbtf_cell_count));
}

"""
#: The function that answers a query's cell (its choice, the cuts, the read texel); every choice it makes is a call
#: ``dynbtf_cell_choice(cx, cy)`` of a cell's int64 words (a variant replaces the calls: guided struct).
GLSL_CELL = """DynbtfCell dynbtf_cell(DynbtfOrigin o, vec2 local) {
    DynbtfCell c;
    vec2 wf, f;
    dynbtf_split(local, wf, f);
    ivec2 w = ivec2(wf);
    ivec2 size = dynbtf_plane_size;   // the exemplar: W' = W, H' = H
    ivec2 n = dynbtf_cell_grid;
    ivec2 span = size / n;            // cell side (T_x, T_y)
    ivec2 texel = min(ivec2(floor(f * vec2(size))), size - 1);
    ivec2 cell = texel / span;        // column and row within the repeat
    ivec2 l = texel - cell * span;    // texel within the cell
    c.cx = dynbtf_add(o.lattice.xy, w.x * n.x + cell.x);
    c.cy = dynbtf_add(o.lattice.zw, w.y * n.y + cell.y);
    int k = dynbtf_cell_count;
    int own = dynbtf_cell_choice(c.cx, c.cy);
    ivec2 m = dynbtf_cell_margin;
    c.side = ivec2(0);
    if (l.x < m.x) {   // the cut of the edge at the cell's start: left cell a, this cell b, texel row l.y
        int a = dynbtf_cell_choice(dynbtf_add(c.cx, -1), c.cy);
        int cut = dynbtf_cell_entry(dynbtf_cut_start.x + (((cell.x * n.y + cell.y) * k + a) * k + own) * span.y + l.y);
        if (l.x < cut) c.side.x = -1;
    } else if (l.x >= span.x - m.x) {   // the edge at the cell's end: this cell a, right cell b
        int b = dynbtf_cell_choice(dynbtf_add(c.cx, 1), c.cy);
        int i = cell.x + 1 == n.x ? 0 : cell.x + 1;
        int cut = dynbtf_cell_entry(dynbtf_cut_start.x + (((i * n.y + cell.y) * k + own) * k + b) * span.y + l.y);
        if (l.x - span.x >= cut) c.side.x = 1;
    }
    if (l.y < m.y) {
        int a = dynbtf_cell_choice(c.cx, dynbtf_add(c.cy, -1));
        int cut = dynbtf_cell_entry(dynbtf_cut_start.y + (((cell.x * n.y + cell.y) * k + a) * k + own) * span.x + l.x);
        if (l.y < cut) c.side.y = -1;
    } else if (l.y >= span.y - m.y) {
        int b = dynbtf_cell_choice(c.cx, dynbtf_add(c.cy, 1));
        int j = cell.y + 1 == n.y ? 0 : cell.y + 1;
        int cut = dynbtf_cell_entry(dynbtf_cut_start.y + (((cell.x * n.y + j) * k + own) * k + b) * span.x + l.x);
        if (l.y - span.y >= cut) c.side.y = 1;
    }
    c.chosen = c.side == ivec2(0) ? own : dynbtf_cell_choice(dynbtf_add(c.cx, c.side.x), dynbtf_add(c.cy, c.side.y));
    c.offset = ivec2(dynbtf_cell_entry(2 * c.chosen), dynbtf_cell_entry(2 * c.chosen + 1));
    // one bilinear sample at the shifted position (texel centres at whole + 0.5), wrapped
    vec2 p = f * vec2(size) - 0.5;
    vec2 p0 = floor(p);
    c.t = p - p0;
    c.texel = ivec2(dynbtf_mod(int(p0.x) + c.offset.x, size.x), dynbtf_mod(int(p0.y) + c.offset.y, size.y));
    return c;
}

"""
GLSL_ELEMENT_GAIN = f"""// ---- per-element variation (dynbtf.synthesis.elements.element_gain): the element instance under a point as int64
// words (the repeat's first, DynbtfOrigin.element, plus the point's place in its repeat), its hashed RGB factor
// exp(brightness a_0 + tint (a_c - mean a)); 1 on the joints
vec3 dynbtf_element_gain(DynbtfOrigin o, vec2 local) {{
    if (dynbtf_variation == vec2(0.0)) return vec3(1.0);
    vec2 wf, f;
    dynbtf_split(local, wf, f);
    ivec2 w = ivec2(wf);
    ivec2 size = dynbtf_plane_size;
    ivec2 texel = min(ivec2(floor(f * vec2(size))), size - 1);
    if (dynbtf_cell_entry(dynbtf_joint_start + texel.y * size.x + texel.x) != 0) return vec3(1.0);
    ivec4 e = dynbtf_element_grid;                                       // columns, rows, p, q
    vec2 span = vec2(size) / vec2(e.xy);                                 // an element's width and row height, texels
    int r = int(floor((f.y * float(size.y) - dynbtf_element_phase.y) / span.y));   // the row in the repeat (from -1)
    int shifted = r * e.z;
    int carry = shifted >= 0 ? shifted / e.w : -((e.w - 1 - shifted) / e.w);      // floor(r p / q)
    float along = (f.x * float(size.x) - dynbtf_element_phase.x) / span.x * float(e.w) - float(shifted - carry * e.w);
    int column = int(floor(along / float(e.w)));
    uvec2 cx = dynbtf_add(o.element.xy, w.x * e.x - w.y * (e.y * e.z / e.w) - carry + column);
    uvec2 cy = dynbtf_add(o.element.zw, w.y * e.y + r);
    uint key = dynbtf_fold(dynbtf_fold(dynbtf_variation_state, cx), cy);
    vec4 a;   // four uniforms of unit variance, one stream each
    for (int k = 0; k < 4; ++k) {{
        a[k] = (float(dynbtf_mix32(key ^ (uint(k) * {SECOND_STREAM:#010x}u))) * {2.0 ** -32!r} - 0.5) * {12 ** 0.5!r};
    }}
    return exp(dynbtf_variation.x * a.x + dynbtf_variation.y * (a.yzw - (a.y + a.z + a.w) / 3.0));
}}

"""
# the types apart: guided struct shares them, not the cell's choices
GLSL_FUNCTIONS = (GLSL_CELL_TYPES, GLSL_CELL, GLSL_ELEMENT_GAIN)
GLSL_SAMPLE = """DynbtfCell cell = dynbtf_cell(o, local);
dynbtf_bilinear(cell.texel, cell.t, 1.0, g0, g1, acc);"""
GLSL_AFTER = ""
GLSL_GAIN = "return dynbtf_element_gain(o, local);"


def cost(groups: int) -> tuple[int, int]:
    """The chosen offset's two table entries and, near a cell's edges, one entry of the vertical and one of the
    horizontal cut table (the most a pixel reads)."""
    return 2 + 2, 0


def form(synthesizer) -> WebForm:
    """The exemplar, the offsets and cut tables (``tables``) and ``cells``, ``margin``, ``count``; with per-element
    variation, also the joints (in ``tables``) and ``elements``: the element grid (``grid``, ``columns``, ``rows``,
    ``shift``: :func:`~dynbtf.synthesis.elements.repeat_elements`), ``brightness``, ``tint`` and the hash
    ``state``."""
    t = synthesizer.prepared
    tables = {"offsets": to_host(t.offsets), "vertical_cuts": to_host(t.vertical_cuts),
              "horizontal_cuts": to_host(t.horizontal_cuts)}
    constants = {"cells": [int(c) for c in t.cells], "margin": [int(c) for c in t.margin], "count": int(t.count)}
    if synthesizer.brightness or synthesizer.tint:
        grid = [float(v) for v in to_host(t.element_grid).tolist()]
        columns, rows, shift = repeat_elements(grid)
        tables["joints"] = np.asarray(to_host(t.joints), dtype=np.int16)
        constants["elements"] = {
            "grid": grid, "columns": columns, "rows": rows, "shift": shift,
            "brightness": float(synthesizer.brightness), "tint": float(synthesizer.tint),
            "state": int(seed_state((int(synthesizer.seed) ^ VARIATION_SALT) & MASK32))}
    return WebForm(to_host(synthesizer.exemplar), {"tables": WebTable("int16", tables)}, constants)
