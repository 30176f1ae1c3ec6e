"""Guided histogram-preserving blending (``guided``) in the web shader: hist's three samples, each re-chosen by the
candidate search of :mod:`dynbtf.synthesis.guided_blending`, their barycentrics steered by ``softness``, then hist's
weights, blend and inverse tables (:mod:`dynbtf.synthesis.web_form`).

Per query the shader

* reads the target's label at the query from the target field (the constant ``field``: the target image laid over
  the plane, ``size`` exemplar repeats per image, tiled or clamped; the repeat origin carries where the query's
  repeat starts on it, :func:`dynbtf.export.web.shader.field_origin`);
* for each of the three samples tries candidate 0 (hist's own offset), then candidate ``j`` (the vertex hashed
  from the candidate's hash state, the constant ``states``), and keeps the first whose four bilinear texels on
  the read plane all carry the target label (the table ``guidance``: the read plane's labels, then the target
  image's); if none does, candidate 0, unmatched;
* multiplies the unmatched samples' barycentrics by ``softness`` unless none matched.

This is the fused kernel's ``_guided_texels`` / ``_steered_barycentrics`` and
:meth:`~dynbtf.synthesis.guided_blending._Guidance.sample_positions`. Labels are stored renumbered (the read
plane's distinct labels in increasing order, a target label the plane lacks as -1, which no texel carries), so any
non-negative labels fit the exact ``R16I`` table. At most :data:`MAX_CANDIDATES` candidates per sample.
"""

from __future__ import annotations

import numpy as np
import torch

from ...errors import InputError
from ..hash import SECOND_STREAM
from ..histogram_blending import web as hist_web
from ..web_form import WebForm, WebTable

MODE = 5
ORIGIN = "lattice"
SAMPLES = 3
#: Candidate offsets per sample the shader holds (its ``dynbtf_guide_states`` array).
MAX_CANDIDATES = 64
#: Candidates per sample the shader's cost is counted for (the library's default).
COUNTED_CANDIDATES = 16
HASHES = 3 * COUNTED_CANDIDATES  # at most: every candidate of every sample hashed
GLSL_UNIFORMS = f"""uniform highp isampler2D dynbtf_guide;        // guided: labels of the read plane, then of the target (int16), entry k at (k % row, k / row)
uniform int dynbtf_guide_row;                // guided: table entries per texture row
uniform int dynbtf_guide_target_start;       // guided: first entry of the target's labels (its rows of dynbtf_field_size.x)
uniform int dynbtf_guide_candidates;         // guided: offsets tried per sample
uniform uvec4 dynbtf_guide_states[{MAX_CANDIDATES // 4}];    // guided: candidate j's hash state at [j / 4][j % 4]
uniform float dynbtf_guide_softness;         // guided: barycentric factor of unmatched samples
"""
GLSL_FUNCTIONS = """// ---- guided synthesis (dynbtf.synthesis.guided_blending): each sample's first candidate whose content carries the
// target label, and the steered barycentrics
int dynbtf_guide_entry(int k) { return texelFetch(dynbtf_guide, ivec2(k % dynbtf_guide_row, k / dynbtf_guide_row), 0).r; }

// whether the four texels of the bilinear footprint at c (wrapped on the read plane) all carry label `target`
bool dynbtf_guide_covers(ivec2 c, int target) {
    ivec2 size = dynbtf_plane_size;
    int c1 = c.x + 1 == size.x ? 0 : c.x + 1;
    int r1 = c.y + 1 == size.y ? 0 : c.y + 1;
    return dynbtf_guide_entry(c.y * size.x + c.x) == target && dynbtf_guide_entry(c.y * size.x + c1) == target
        && dynbtf_guide_entry(r1 * size.x + c.x) == target && dynbtf_guide_entry(r1 * size.x + c1) == target;
}

// the three samples' texels after the candidate search; tri.b becomes the steered barycentrics
void dynbtf_guided_texels(DynbtfOrigin o, vec2 local, inout DynbtfTriangle tri, out ivec2 c[3]) {
    ivec2 t = dynbtf_field_texel(o, local);
    int target = dynbtf_guide_entry(dynbtf_guide_target_start + t.y * dynbtf_field_size.x + t.x);
    dynbtf_sample_texels(tri, c);   // candidate 0: the method's own offsets
    ivec2 size = dynbtf_plane_size;
    uint pw = uint(size.x), ph = uint(size.y);
    bool matched[3];
    for (int i = 0; i < 3; ++i) {
        matched[i] = dynbtf_guide_covers(c[i], target);
        for (int j = 1; j < dynbtf_guide_candidates && !matched[i]; ++j) {
            uint h = dynbtf_fold(dynbtf_fold(dynbtf_guide_states[j / 4][j % 4], tri.vx[i]), tri.vy[i]);
            ivec2 off = ivec2(int(h % pw), int(dynbtf_mix32(h ^ SECOND_STREAMu) % ph));
            ivec2 cj = ivec2((tri.texel.x + off.x) % size.x, (tri.texel.y + off.y) % size.y);
            if (dynbtf_guide_covers(cj, target)) { c[i] = cj; matched[i] = true; }
        }
    }
    if (matched[0] || matched[1] || matched[2]) {
        for (int i = 0; i < 3; ++i) tri.b[i] = matched[i] ? tri.b[i] : tri.b[i] * dynbtf_guide_softness;
    }
}

""".replace("SECOND_STREAM", f"{SECOND_STREAM:#010x}")
_OWN = "dynbtf_sample_texels(tri, c);"
_GUIDED = "dynbtf_guided_texels(o, local, tri, c);"


def guided_sample(method_sample: str) -> str:
    """A lattice method's ``GLSL_SAMPLE`` with its samples' texels chosen by the guided search (and its barycentrics
    steered) in place of its own."""
    if method_sample.count(_OWN) != 1:
        raise AssertionError("the method's branch does not choose its texels with dynbtf_sample_texels once")
    return method_sample.replace(_OWN, _GUIDED)


GLSL_SAMPLE = guided_sample(hist_web.GLSL_SAMPLE)
GLSL_AFTER = hist_web.GLSL_AFTER


def search_cost() -> tuple[int, int]:
    """The target's label and, at most, four labels per candidate of each sample (:data:`COUNTED_CANDIDATES`)."""
    return 1 + SAMPLES * COUNTED_CANDIDATES * 4, 0


def cost(groups: int) -> tuple[int, int]:
    """hist's tables and the candidate search (:func:`search_cost`)."""
    fetches, macs = hist_web.cost(groups)
    search_fetches, search_macs = search_cost()
    return fetches + search_fetches, macs + search_macs


def guidance(synthesizer) -> tuple[dict[str, WebTable], dict]:
    """The guidance of a guided lattice synthesizer as a table (``guidance``: ``labels`` of the read plane and the
    target image's ``target``, renumbered) and constants (``candidates``, ``states``, ``softness``, ``field``)."""
    if synthesizer.candidates > MAX_CANDIDATES:
        raise InputError(f"export: the web shader tries at most {MAX_CANDIDATES} candidates per sample, got "
                         f"candidates={synthesizer.candidates}")
    # the fused kernel's own arguments: the candidates' hash states, the read plane's labels, the softness
    states, labels, _, softness = synthesizer.kernel_guidance(torch.zeros((0, 2), dtype=torch.float64))
    dense_labels, dense_target = renumbered(labels, synthesizer.target.image)
    table = WebTable("int16", {"labels": dense_labels, "target": dense_target})
    return {"guidance": table}, {"candidates": int(len(states)), "states": [int(s) & 0xFFFFFFFF for s in states],
                                 "softness": float(softness), "field": target_field(synthesizer.target)}


def renumbered(labels, target) -> tuple[np.ndarray, np.ndarray]:
    """``labels`` (what the read content carries) and a ``target`` image as small integers that compare as they do:
    the distinct labels in increasing order ``0, 1, ...``, a target label no content carries ``-1`` (what the
    ``R16I`` table holds, whatever the labels' range)."""
    labels = np.asarray(labels, dtype=np.int64)
    target = np.asarray(target.cpu().numpy() if isinstance(target, torch.Tensor) else target).astype(np.int64)
    present = np.unique(labels)
    index = np.searchsorted(present, target).clip(0, max(len(present) - 1, 0))
    dense_target = np.where(present[index] == target, index, -1) if len(present) else np.full_like(target, -1)
    return np.searchsorted(present, labels), dense_target


def target_field(target) -> dict:
    """A :class:`~dynbtf.synthesis.guided_blending.LabelField` as the shader's label ``field`` constant
    (:mod:`dynbtf.synthesis.web_form`)."""
    return {"width": int(target.image.shape[1]), "height": int(target.image.shape[0]), "size": float(target.size),
            "wrap": target.wrap}


def form(synthesizer) -> WebForm:
    """hist's form (:func:`dynbtf.synthesis.histogram_blending.web.form`) with the guidance (:func:`guidance`)."""
    base = hist_web.form(synthesizer)
    tables, constants = guidance(synthesizer)
    return WebForm(base.plane, base.tables | tables, base.constants | constants)
