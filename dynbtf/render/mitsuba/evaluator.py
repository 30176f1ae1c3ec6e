"""The plugin's query: :meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` called on a Mitsuba wavefront.

The ``dynbtf`` BSDF answers a shading point by calling the library's own query object, the same code
``dynbtf synth`` and the Python API run (numba's CPU kernels, or torch on CUDA), through Dr.Jit's interop
with PyTorch (:func:`drjit.wrap`). The plugin runs Dr.Jit in wavefront mode (:func:`configure_jit`): each
BSDF call sees a whole wavefront of lanes as arrays, which this module hands to the library in one call
and takes back (zero-copy on the CPU; on CUDA the tensors stay on the device).

There is no second implementation of the query to keep equal to the first: every method, relief, guidance,
footprint and representation the library evaluates renders as it evaluates. Why the plugin calls the library
rather than a Dr.Jit translation of it (as it did): docs/architecture.md, "Runtimes".

Conventions: ``u, v`` in exemplar repeats (the plugin multiplies mesh uv by its ``scale``), directions in the
BTF's local frame, values linear RGB excluding cos(theta_light). Only the active lanes of a wavefront are handed
over (inactive ones answer zero): a layered material's layer evaluates only where it shows.
"""

from __future__ import annotations

import torch

from ... import jit
from ...errors import InputError

__all__ = ["DynBTFEvaluator", "library_call", "check_renderable", "RENDERABLE_KINDS"]

#: Representation kinds the plugin renders: those with a positional feature plane to synthesize and a decoder.
RENDERABLE_KINDS = ("triple", "triple-parallax", "neumip")


def check_renderable(model, what="model") -> None:
    """:class:`~dynbtf.errors.InputError` unless ``model`` is of a kind in :data:`RENDERABLE_KINDS`.

    ``what`` names the model in the message (e.g. its file). PCA and SH models have no positional feature plane
    to synthesize: the plugin would render the measured sample repeated, which is not what it is for.
    """
    kind = getattr(model, "kind", type(model).__name__)
    if kind not in RENDERABLE_KINDS:
        raise InputError(f"{what}: the Mitsuba plugin renders Triple Plane (kind 'triple', `dynbtf fit`; "
                         f"'triple-parallax', `dynbtf fit --repr triple-parallax`) and NeuMIP (kind 'neumip', "
                         f"`dynbtf fit --repr neumip`) models, got a model of kind {kind!r}")


def library_call(function, inputs, outputs: int, active=True):
    """``function(*tensors)`` on the active lanes of Dr.Jit arrays.

    ``inputs``: 1-D arrays of the active variant (``mi.Float``, ``mi.Float64``...) of width ``n`` or 1 (one value
    for every lane, e.g. a shading point's uv under ``n`` light directions). The
    active lanes' values are gathered (all of them without a copy where every lane is active) and handed over as
    torch tensors (detached: nothing here is differentiated); ``function`` returns ``outputs`` 1-D tensors of as
    many rows, handed back and scattered to their lanes. Returns ``outputs`` ``mi.Float`` arrays of width ``n``, zero
    on inactive lanes. Evaluates the inputs (the wavefront's kernel up to here runs first): the plugin runs in
    wavefront mode (:func:`~dynbtf.render.mitsuba.bsdf.configure_jit`).
    """
    mi, dr = jit.mi_module(), jit.drjit_module()
    n = max(dr.width(x) for x in inputs)
    active = mi.Bool(active) | dr.zeros(mi.Bool, n)
    index = None if dr.all(active) else dr.compress(active)
    if index is not None and dr.width(index) == 0:
        return tuple(dr.zeros(mi.Float, n) for _ in range(outputs))

    @dr.wrap(source="drjit", target="torch")
    def call(*tensors):
        with torch.no_grad():
            result = function(*(t.detach() for t in tensors))
        return tuple(r.to(torch.float32).contiguous() for r in result)

    if index is None and any(dr.width(x) != n for x in inputs):
        index = dr.arange(mi.UInt32, n)  # every lane active: one gather widens the width-1 inputs
    taken = [dr.detach(x) if index is None else dr.gather(type(x), dr.detach(x), index if dr.width(x) == n
                                                          else dr.zeros(mi.UInt32, dr.width(index)))
             for x in inputs]
    result = call(*taken)
    if index is None:
        return tuple(mi.Float(r) for r in result)
    out = []
    for r in result:
        full = dr.zeros(mi.Float, n)
        dr.scatter(full, mi.Float(r), index)
        out.append(full)
    return tuple(out)


class DynBTFEvaluator:
    """The body of the plugin's ``eval``: an opened material's query object, called per wavefront.

    Parameters
    ----------
    btf : SynthesizedBTF
        An opened material's query object at ``scale`` 1 (:func:`dynbtf.synthesized_btf` opens or compiles a
        model's; :func:`dynbtf.guided.guided_btf` builds a guided one). The evaluator builds nothing.

    Attributes
    ----------
    method : str
        The method the query runs (``auto`` resolved when the material was compiled).
    choice : MethodChoice or None
        What ``auto`` chose and why (``choice.line`` is the report), ``None`` for a named method.

    >>> from dynbtf import synthesized_btf
    >>> from dynbtf.representations.triple_plane import TriplePlane
    >>> evaluator = DynBTFEvaluator(synthesized_btf(TriplePlane(16, 16), "hist", seed=3))  # doctest: +SKIP
    """

    def __init__(self, btf) -> None:
        from ...infinite_btf import SynthesizedBTF

        if not isinstance(btf, SynthesizedBTF):
            raise InputError(f"DynBTFEvaluator: expected an opened material's query object (dynbtf.synthesized_btf("
                             f"model, method, seed=...)), got {type(btf).__name__}")
        if btf.scale != 1.0:
            raise InputError(f"DynBTFEvaluator: expected the query object at scale 1 (the plugin applies its own "
                             f"scale to uv), got scale {btf.scale}")
        check_renderable(btf.model)
        self.btf = btf
        self.method = btf.synthesizer.name
        self.choice = btf.synthesizer.choice

    def prepare_footprints(self) -> None:
        """Build what footprint queries read (the synthesizer's pyramid, the per-level decoders) now, not at the
        first shading point."""
        self.btf.synthesizer.level_of_detail()
        if self.btf.level_decoders:
            self.btf.footprint_decoder()

    def eval(self, u, v, w_view, w_light, active=True, footprint=None):
        """RGB value (``mi.Color3f``) of the synthesized BTF, excluding cos(theta_light); zero on inactive lanes, which
        are not evaluated.

        ``u, v`` (``mi.Float``, exemplar repeats), ``w_view, w_light`` (``mi.Vector3f``, local frame);
        ``footprint`` (optional ``mi.Float``): the side of the square each lane stands for, in exemplar repeats
        (:meth:`~dynbtf.infinite_btf.SynthesizedBTF.eval`'s ``footprint`` at scale 1); ``None``: the point query.
        """
        mi = jit.mi_module()
        btf = self.btf
        device = btf.device

        def query(u, v, vx, vy, vz, lx, ly, lz, *width):
            uv = torch.stack([u, v], -1).to(device, torch.float64)
            wv = torch.stack([vx, vy, vz], -1).to(device, torch.float32)
            wl = torch.stack([lx, ly, lz], -1).to(device, torch.float32)
            fp = width[0].to(device, torch.float64) if width else None
            rgb = btf.eval(uv, wv, wl, fp)
            return rgb[:, 0], rgb[:, 1], rgb[:, 2]

        extra = [] if footprint is None else [footprint]
        r, g, b = library_call(query, [u, v, w_view.x, w_view.y, w_view.z, w_light.x, w_light.y, w_light.z, *extra],
                               3, active)
        return mi.Color3f(r, g, b)

