"""The ``dynbtf`` BSDF plugin for Mitsuba 3: a synthesized BTF evaluated inside the rendering kernel.

Call :func:`register_plugin` once and Mitsuba knows a BSDF of type ``"dynbtf"``::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")          # or a cuda_* variant
    from dynbtf.render.mitsuba_bsdf import register_plugin
    register_plugin()
    bsdf = mi.load_dict({"type": "dynbtf", "filename": "leather.dynbtf", "method": "hist", "scale": 25})

The class docstring of :class:`DynBTFBSDF` (available as :data:`PLUGIN_DOC`) is the
plugin's reference page.
"""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import InputError
from . import drjit_ops

__all__ = ["register_plugin", "PLUGIN_DOC", "METHODS", "configure_jit"]

#: Synthesis methods the plugin evaluates in Dr.Jit.
METHODS = ("tile", "hist", "hex")

PLUGIN_DOC = """Synthesized BTF material (``dynbtf``)

Evaluates an infinite, non-repeating BTF -- a fitted Triple Plane model whose
positional feature plane is synthesized on the fly -- at every shading point.
The whole chain (lattice, integer hash, histogram-preserving blend, inverse
transform, decoder MLP) is traced into the rendering kernel; nothing is
pre-generated, so any ``scale`` costs the same.

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Description
     - Default
   * - ``filename``
     - string
     - Path of a dynbtf model file (``dynbtf fit``), a Triple Plane.
     - (required)
   * - ``method``
     - string
     - Synthesis of the positional plane: ``tile`` (plain repetition, the
       reference point), ``hist`` (histogram-preserving blending on a triangle
       lattice, the paper's method) or ``hex`` (hex-tiling).
     - ``hist``
   * - ``scale``
     - float
     - Exemplar repeats per unit of mesh ``u`` (how many times the measured
       patch would fit across the mesh's uv range).
     - 1.0
   * - ``scale_v``
     - float
     - Repeats per unit of mesh ``v``; set it to ``scale / 2`` on Mitsuba's
       ``sphere`` (whose ``u`` spans the circumference, ``v`` half of it).
     - ``scale``
   * - ``seed``
     - integer
     - Seed of the synthesis' integer hash (another seed, another material instance).
     - 0

Conventions: ``si.wi`` (towards the camera / previous path vertex) is the BTF's
``w_view``, ``wo`` (towards the light / next vertex) its ``w_light``, both in the
local shading frame (``x`` along ``dp/du``, so it follows increasing ``u``).
``eval`` returns ``value / pi * cos(theta_light)`` where ``value`` is what
:meth:`dynbtf.synthesized.SynthesizedBTF.eval` returns at
``uv = (scale * u, scale_v * v)``; directions below either horizon give 0
(one-sided reflection: wrap it in Mitsuba's ``twosided`` for cloth).
Sampling is cosine-weighted over the upper hemisphere (pdf ``cos(theta) / pi``),
as in the paper, so a sample's weight is the BTF value itself. A BTF is not
reciprocal: use radiance-mode integrators (``path``, ``direct``), not light
tracing.

Precision: Mitsuba's mesh uv and the product ``scale * u`` are float32; from
there on the lattice runs in float64 exactly as dynbtf does, so the plugin agrees
with :class:`~dynbtf.synthesized.SynthesizedBTF` at the same float32 ``uv``. Repeat
counts beyond ~1e4 per mesh make float32 uv coarser than a texel (a mesh
limitation, not a synthesis one).
"""


def configure_jit() -> None:
    """Dr.Jit flags under which the unrolled decoder compiles into one fast kernel.

    Symbolic loops and calls trace the integrator's loop body once and dispatch
    BSDF calls indirectly; with them off (wavefront mode), the plugin's code is
    fused into straight-line kernels -- ~15x faster on the CPU for this BSDF.
    """
    import drjit as dr

    dr.set_flag(dr.JitFlag.SymbolicLoops, False)
    dr.set_flag(dr.JitFlag.SymbolicCalls, False)


def _build_class(mi):
    import drjit as dr

    from ..representations.model_file import load_model

    class DynBTFBSDF(mi.BSDF):
        __doc__ = PLUGIN_DOC

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            if not props.has_property("filename"):
                raise InputError("dynbtf BSDF: parameter 'filename' (a dynbtf model file) is required")
            self.filename = str(props["filename"])
            self.method = str(props["method"]) if props.has_property("method") else "hist"
            if self.method not in METHODS:
                raise InputError(f"dynbtf BSDF: parameter 'method' must be one of {list(METHODS)}, "
                                 f"got {self.method!r}")
            self.scale = float(props["scale"]) if props.has_property("scale") else 1.0
            self.scale_v = float(props["scale_v"]) if props.has_property("scale_v") else self.scale
            self.seed = int(props["seed"]) if props.has_property("seed") else 0
            for name, value in (("scale", self.scale), ("scale_v", self.scale_v)):
                if not (math.isfinite(value) and value > 0):
                    raise InputError(f"dynbtf BSDF: parameter '{name}' must be a positive number of repeats, "
                                     f"got {value}")
            if not Path(self.filename).exists():
                raise InputError(f"dynbtf BSDF: parameter 'filename': model file {self.filename!r} not found")
            model, _ = load_model(self.filename, device="cpu")
            self.evaluator = DynBTFEvaluator(model, self.method, self.seed)
            self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [self.m_flags]

        # ------------------------------------------------------------ BTF value
        def _value(self, si, wo, active):
            # opaque: the scale is a kernel parameter, not a literal, so scenes that differ
            # only in scale share one compiled kernel
            u = si.uv.x * dr.opaque(mi.Float, self.scale)
            v = si.uv.y * dr.opaque(mi.Float, self.scale_v)
            return self.evaluator.eval(u, v, si.wi, wo, active)

        def _valid(self, si, wo, active):
            return active & (mi.Frame3f.cos_theta(si.wi) > 0.0) & (mi.Frame3f.cos_theta(wo) > 0.0)

        # ------------------------------------------------------------ BSDF API
        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(bs.wo)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            bs.sampled_component = mi.UInt32(0)
            ok = self._valid(si, bs.wo, active) & (bs.pdf > 0.0)
            bs.pdf = dr.select(ok, bs.pdf, 0.0)
            # weight = eval / pdf = (value / pi * cos) / (cos / pi) = value
            return bs, dr.select(ok, self._value(si, bs.wo, ok), 0.0)

        def eval(self, ctx, si, wo, active=True):
            ok = self._valid(si, wo, active)
            value = self._value(si, wo, ok)
            return dr.select(ok, value * (dr.inv_pi * mi.Frame3f.cos_theta(wo)), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            ok = self._valid(si, wo, active)
            return dr.select(ok, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            ok = self._valid(si, wo, active)
            value = self._value(si, wo, ok) * (dr.inv_pi * mi.Frame3f.cos_theta(wo))
            return (dr.select(ok, value, 0.0),
                    dr.select(ok, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0))

        def traverse(self, callback):
            pass  # nothing differentiable is exposed

        def to_string(self):
            return (f"DynBTFBSDF[filename={self.filename!r}, method={self.method!r}, "
                    f"scale={self.scale}, scale_v={self.scale_v}, seed={self.seed}]")

    return DynBTFBSDF


class DynBTFEvaluator:
    """``SynthesizedBTF.eval`` re-expressed in Dr.Jit: the body of the plugin's ``eval``.

    Parameters
    ----------
    model : TriplePlane
        The fitted representation.
    method : {"tile", "hist", "hex"}
        Synthesis method (the same synthesizer :class:`~dynbtf.synthesized.SynthesizedBTF` builds).
    seed : int
        Synthesis seed.

    :meth:`eval` takes Dr.Jit arrays of the active Mitsuba variant: ``u, v``
    (``mi.Float``, in exemplar repeats), ``w_view, w_light`` (``mi.Vector3f``,
    local frame) and returns ``mi.Color3f`` values (excluding cos(theta_light)).
    """

    def __init__(self, model, method: str, seed: int) -> None:
        from ..synthesized import SynthesizedBTF
        from .drjit_synthesis import make_dr_synthesizer

        self.btf = SynthesizedBTF(model, method, scale=1.0, seed=seed)
        self.synthesizer = make_dr_synthesizer(self.btf.synthesizer)
        # fold the synthesizer's output map (PCA un-projection) into the decoder's first layer,
        # as SynthesizedBTF's fast path does: 16 x 16 fewer multiply-adds per shading point
        matrix, offset = getattr(self.synthesizer, "matrix", None), getattr(self.synthesizer, "offset", None)
        self.model = drjit_ops.DrTriplePlane(model, output_map=(matrix, offset))
        self._latent = matrix is not None

    def features(self, u, v, active=True):
        """Synthesized positional features at ``(u, v)``: list of ``C_U`` mi.Float."""
        return self.synthesizer.features(u, v, active)

    def eval(self, u, v, w_view, w_light, active=True):
        """RGB value (``mi.Color3f``) of the synthesized BTF, excluding cos(theta_light)."""
        if self._latent:  # the output map is folded into the decoder
            return self.model.decode(self.synthesizer.latent(u, v, active), w_view, w_light, active)
        return self.model.decode(self.features(u, v, active), w_view, w_light, active)


_REGISTERED: set[str] = set()


def register_plugin(variant: str | None = None) -> str:
    """Register the ``dynbtf`` BSDF with Mitsuba (idempotent per variant).

    Parameters
    ----------
    variant : str, optional
        Mitsuba variant to activate first (e.g. ``"llvm_ad_rgb"``, ``"cuda_ad_rgb"``).
        ``None`` keeps the active one, or picks ``llvm_ad_rgb`` when none is set.
        Scalar variants work but evaluate per sample (~100x slower).

    Returns
    -------
    str: the active variant.
    """
    import mitsuba as mi

    if variant is not None:
        if variant not in mi.variants():
            raise InputError(f"Mitsuba variant {variant!r} is not available; expected one of {mi.variants()}")
        mi.set_variant(variant)
    mi = drjit_ops.mi_module()
    configure_jit()
    active = mi.variant()
    if active not in _REGISTERED:
        cls = _build_class(mi)
        mi.register_bsdf("dynbtf", lambda props: cls(props))
        _REGISTERED.add(active)
    return active
