"""Exemplar guidance in Dr.Jit: the guided lattice blends and guided cell quilting of
:mod:`dynbtf.synthesis.guided_blending`.
"""

from __future__ import annotations

import numpy as np

from ...jit import drjit_module, mi_module
from ..blending import drjit as blending_drjit
from ..cell_quilting.drjit import DrCellQuilting
from ..drjit_blocks import DrLabelField, positive_mod

class DrGuidance:
    """Exemplar guidance of a lattice blend in Dr.Jit: :meth:`dynbtf.synthesis.guided_blending._Guidance` (and the
    numba kernel's search), the candidates tried in the same order.

    Parameters
    ----------
    seeds : list of int
        The candidates' seeds (:func:`~dynbtf.synthesis.guided_blending.candidate_seed`; candidate 0 the synthesis
        seed).
    labels : int ``(H', W')``
        The read plane's labels.
    target : :class:`~dynbtf.synthesis.guided_blending.LabelField`
        The label each point should show, over exemplar repeats.
    softness : float
        Barycentric-weight factor of samples that found no candidate of the target's label.
    """

    def __init__(self, seeds, labels, target, softness: float) -> None:
        mi = mi_module()
        labels = np.asarray(labels, dtype=np.int32)
        self.seeds = [int(x) for x in seeds]
        self.labels = mi.Int32(labels.reshape(-1))
        self.target = DrLabelField(target)
        self.softness = float(softness)

    def steer(self, blend, u, v, verts, bary, offsets, xi, yi, active):
        """Each sample's offset (the first candidate whose bilinear footprint carries the target label, else
        candidate 0's) and the barycentrics with unmatched samples' weight times ``softness``."""
        mi, dr = mi_module(), drjit_module()
        pw, ph = blend.pw, blend.ph
        target = self.target(u, v, active)
        chosen, matched = [], []
        for (vx, vy), first in zip(verts, offsets):
            ox, oy = first
            found = dr.zeros(mi.Bool, dr.width(xi))
            for j, seed in enumerate(self.seeds):
                cx, cy = first if j == 0 else blend._offsets(vx, vy, seed)
                ca, cb = positive_mod(xi + cx, pw), positive_mod(xi + cx + 1, pw)
                ra, rb = positive_mod(yi + cy, ph), positive_mod(yi + cy + 1, ph)
                inside = mi.Bool(active)  # a new mask: the in-place updates below must not touch the caller's
                for r, c in ((ra, ca), (ra, cb), (rb, ca), (rb, cb)):
                    inside = inside & (dr.gather(mi.Int32, self.labels, mi.UInt32(r * pw + c), active) == target)
                hit = inside & ~found
                ox, oy = dr.select(hit, cx, ox), dr.select(hit, cy, oy)
                found = found | hit
            chosen.append((ox, oy))
            matched.append(found)
        any_match = matched[0] | matched[1] | matched[2]
        steered = [dr.select(m | ~any_match, b, b * self.softness) for b, m in zip(bary, matched)]
        return chosen, steered




def form(synthesizer):
    """The Dr.Jit kernel of a guided method: guided struct's cell quilting with its cell labels, or a guided lattice
    blend with its candidates' seeds."""
    from . import CellQuilting, candidate_seed

    if isinstance(synthesizer, CellQuilting):
        return DrCellQuilting.of(synthesizer)
    guidance = DrGuidance([candidate_seed(synthesizer.seed, j) for j in range(synthesizer.candidates)],
                          synthesizer.labels.detach().cpu().numpy(), synthesizer.target, synthesizer.softness)
    return blending_drjit.form(synthesizer, guidance=guidance)
