"""The ``dynbtf_layered`` BSDF plugin for Mitsuba 3: two synthesized BTFs on one surface, chosen per point by a mask.

It is :class:`dynbtf.layered.LayeredBTF` at every shading point. Its two layers are ``dynbtf`` BSDFs
(:mod:`dynbtf.render.mitsuba.bsdf`, each with its model file, method, scale and seed) and its mask is any
Mitsuba texture over the mesh's uv (a ``bitmap`` for a painted mask, ``dynbtf_noise`` for
:class:`~dynbtf.layered.NoiseMask`'s value noise)::

    mi.load_dict({"type": "dynbtf_layered",
                  "layer0": {"type": "dynbtf", "filename": "worn.dbtfm", "scale": 8},
                  "layer1": {"type": "dynbtf", "filename": "new.dbtfm", "scale": 8},
                  "mask": {"type": "bitmap", "filename": "mask.png", "raw": True, "filter_type": "bilinear"},
                  "width": 0.05})

:func:`dynbtf.render.mitsuba.bsdf.register_plugin` registers it and the ``dynbtf_noise`` texture with ``dynbtf``. The class docstring
(:data:`LAYERED_DOC`) is its reference page; its parameters are one table, :data:`LAYERED_PARAMETERS`.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ... import jit
from ...errors import InputError
from .bsdf import PluginParameter, number_check, plugin_class, rst_parameter_rows

__all__ = ["LAYERED_PARAMETERS", "LAYERED_DOC", "build_layered_class", "build_noise_class",
           "layered_parameter_table_markdown", "mask_texture_dict"]


_width = number_check(lambda v: math.isfinite(v) and v > 0.0, "a positive width in uv units", "dynbtf_layered")
_softness = number_check(lambda v: math.isfinite(v) and v >= 0.0, "a height difference >= 0", "dynbtf_layered")


#: The plugin's scalar parameters (the two layers and the mask are nested objects, documented in :data:`LAYERED_DOC`).
LAYERED_PARAMETERS: tuple[PluginParameter, ...] = (
    PluginParameter(
        "width", "float", 0.05, check=_width, plugin="dynbtf_layered",
        doc="""Half-width (mesh uv units) of the band around the mask's 0.5 contour
where the two materials' heights decide which one shows.""",
        summary="half-width (mesh uv units) of the band around the mask's 0.5 contour where the heights decide"),
    PluginParameter(
        "softness", "float", 0.0, check=_softness, shown_default="0", plugin="dynbtf_layered",
        doc="""Height difference over which the two layers blend inside the band
(0: each point from one layer, a hard edge that follows the materials' structure).""",
        summary="height difference over which the layers blend inside the band (0: each point from one layer)"),
)

_DOC_HEAD = """Layered synthesized BTF (``dynbtf_layered``)

Two ``dynbtf`` BSDFs on one surface: ``layer0`` where the ``mask`` texture is below
one half, ``layer1`` where it is above, with the boundary synthesized, not
cross-faded: within ``width`` of the mask's 0.5 contour a point shows the layer that
stands higher there once a bias growing with the distance ``d`` to the contour is added,
``score = (h_1 - h_0) + d / width`` (``h``: each layer's height in [0, 1], the rank among the
exemplar's texels of its relief where the model has one, else of the luminance of its synthesized
features, :class:`dynbtf.layered.LayerHeight`; ``d``:
``(m - 0.5) / |grad m|`` from the mask's value and gradient). It evaluates what
:class:`dynbtf.layered.LayeredBTF` evaluates, with the mask a Mitsuba texture:
``bitmap`` with ``raw = true``, ``filter_type = "bilinear"`` and ``to_uv`` scaled by
``1 / size`` is :class:`~dynbtf.layered.ImageMask` over ``size`` uv units
(``wrap_mode`` ``repeat`` or ``clamp``; :func:`mask_texture_dict` writes it). The
texture must give its gradient (``eval_1_grad``: Mitsuba's ``bitmap`` does).

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Description
     - Default
   * - ``layer0``, ``layer1``
     - bsdf
     - the two materials: ``dynbtf`` BSDFs, each with its own model file, method,
       scale, seed, sampling and footprint settings
     - (required)
   * - ``mask``
     - texture
     - over the mesh's uv, in [0, 1]: below 0.5 ``layer0``, above ``layer1``
     - (required)
"""

_DOC_TAIL = """``eval`` is ``(1 - w) eval_0 + w eval_1`` with ``w`` layer 1's weight at the point (0
or 1 away from the band, and inside it with ``softness = 0``). Sampling accounts for
the mix: a direction is drawn from layer 1 with probability ``w``, else from layer 0
(each with its own sampling), ``pdf`` is the mixture ``(1 - w) pdf_0 + w pdf_1`` and
``sample``'s weight is ``eval / pdf``. Each layer is evaluated on the lanes where it shows
and the heights inside the band only (the plugin's query hands over active lanes alone), so away
from the boundary a shading point costs one ``dynbtf`` evaluation plus the mask.
"""


#: The plugin's reference page (the class docstring of the BSDF).
LAYERED_DOC = _DOC_HEAD + rst_parameter_rows(LAYERED_PARAMETERS) + "\n" + _DOC_TAIL


def layered_parameter_table_markdown() -> str:
    """The plugin's parameter table in Markdown, as docs/rendering.md shows it (a test keeps the two equal)."""
    lines = ["| Parameter | Type | Description | Default |", "|---|---|---|---|",
             "| `layer0`, `layer1` | bsdf | the two materials: `dynbtf` BSDFs (each its own model file, method, scale, "
             "seed, sampling) | required |",
             "| `mask` | texture | over the mesh's uv, in [0, 1]: below 0.5 `layer0`, above `layer1` (a `bitmap` with "
             "`raw`, bilinear filtering and its gradient) | required |"]
    lines += [f"| `{p.name}` | {p.type} | {p.summary} | {p.default_text(markdown=True)} |" for p in LAYERED_PARAMETERS]
    return "\n".join(lines) + "\n"


def mask_texture_dict(mask) -> dict:
    """The Mitsuba texture that is ``mask`` over the mesh's uv: a ``bitmap`` for an
    :class:`~dynbtf.layered.ImageMask`, a ``dynbtf_noise`` for a :class:`~dynbtf.layered.NoiseMask`."""
    from ...layered import ImageMask, NoiseMask

    if isinstance(mask, NoiseMask):
        return {"type": "dynbtf_noise", "scale": float(mask.scale), "contrast": float(mask.contrast),
                "seed": int(mask.seed)}
    if not isinstance(mask, ImageMask):
        raise InputError(f"mask: Mitsuba renders an ImageMask or a NoiseMask, got {type(mask).__name__}")
    mi = jit.mitsuba_module()
    image = np.ascontiguousarray(np.asarray(mask.image, dtype=np.float32)[..., None])
    return {"type": "bitmap", "data": mi.TensorXf(image), "raw": True, "filter_type": "bilinear",
            "wrap_mode": "repeat" if mask.wrap == "repeat" else "clamp",
            "to_uv": mi.ScalarTransform4f().scale([1.0 / mask.size, 1.0 / mask.size, 1.0])}


def _mi():
    return jit.mitsuba_module()


def _dr():
    return jit.drjit_module()


def _nested(props, name: str, kind: str, check):
    """The nested object ``name`` of ``props`` (a BSDF or a texture), or a one-line error naming it."""
    if not props.has_property(name):
        raise InputError(f"dynbtf_layered BSDF: {kind} '{name}' is required")
    value = props[name]
    if not check(value):
        raise InputError(f"dynbtf_layered BSDF: '{name}' must be a {kind}, got {type(value).__name__}")
    return value


class _LayeredBSDFBody:
    """The body of the ``dynbtf_layered`` BSDF class (copied onto a subclass of the variant's ``mi.BSDF``, as the
    ``dynbtf`` plugin's body is)."""

    def __init__(self, props):
        self._base.__init__(self, props)
        from ...layered import layer_height_map

        mi = _mi()
        for parameter in LAYERED_PARAMETERS:
            setattr(self, parameter.name, parameter.read(props, {}))
        self.layers = [_nested(props, name, "dynbtf BSDF", lambda v: hasattr(v, "evaluator"))
                       for name in ("layer0", "layer1")]
        self.mask = _nested(props, "mask", "texture", lambda v: isinstance(v, mi.Texture))
        # each layer's height from its synthesized features, as LayeredBTF reads it (a rank, by its table)
        self.heights = [layer_height_map(layer.evaluator.btf) for layer in self.layers]
        self.m_flags = int(self.layers[0].m_flags) | int(self.layers[1].m_flags)  # footprints if either layer
        self.m_components = [int(mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide)]

    # ------------------------------------------------------------ layer 1's weight
    def _height(self, k, si, active):
        """Layer ``k``'s height in [0, 1] at the shading point: :func:`dynbtf.layered.layer_height`, the library's."""
        from ...layered import layer_height
        from .evaluator import library_call

        mi, dr = _mi(), _dr()
        layer = self.layers[k]
        btf, height_of = layer.evaluator.btf, self.heights[k]
        u = si.uv.x * dr.opaque(mi.Float, layer.scale)
        v = si.uv.y * dr.opaque(mi.Float, layer.scale_v)

        def query(u, v):
            height, _ = layer_height(btf, height_of, torch.stack([u, v], -1).to(torch.float64).cpu())
            return (torch.from_numpy(height),)

        return library_call(query, [u, v], 1, active)[0]

    def _footprint(self, si):
        """Each lane's footprint (side of a square, uv units) as the first filtered layer sees it, or None."""
        mi, dr = _mi(), _dr()
        for layer in self.layers:
            if layer.filtered:
                return layer._footprint(si, dr.opaque(mi.Float, 1.0), dr.opaque(mi.Float, 1.0))
        return None

    def _weight(self, si, active):
        """Layer 1's weight at the shading point, in [0, 1]: the library's rule (:func:`dynbtf.layered.layer_weight`)
        on the mask texture's contour distance."""
        from ...layered import layer_weight
        from .evaluator import library_call

        mi, dr = _mi(), _dr()
        m = self.mask.eval_1(si, active)
        gradient = self.mask.eval_1_grad(si, active)
        slope = dr.norm(mi.Vector2f(gradient.x, gradient.y))
        distance = dr.select(m == 0.5, 0.0, (m - 0.5) / dr.maximum(slope, 1e-30))
        band = active & (dr.abs(distance) < self.width)
        difference = self._height(1, si, band) - self._height(0, si, band)
        footprint = self._footprint(si)
        # texels per uv unit of the coarser layer (the layers' own scales: their BTFs are at scale 1)
        texels = min(layer.evaluator.btf.texels_per_uv() * math.sqrt(layer.scale * layer.scale_v)
                     for layer in self.layers)
        width, softness = self.width, self.softness

        def query(distance, difference, *footprint):
            side = footprint[0].double().numpy() if footprint else None
            return (torch.from_numpy(layer_weight(distance.double().numpy(), difference.double().numpy(), width,
                                                  softness, side, None if side is None else side * texels)),)

        inputs = [distance, difference] + ([] if footprint is None else [footprint])
        return library_call(query, inputs, 1, active)[0]

    # ------------------------------------------------------------ BSDF API
    def _eval_pdf(self, ctx, si, wo, weight, active):
        dr = _dr()
        value_0, pdf_0 = self.layers[0].eval_pdf(ctx, si, wo, active & (weight < 1.0))
        value_1, pdf_1 = self.layers[1].eval_pdf(ctx, si, wo, active & (weight > 0.0))
        value = dr.select(weight > 0.0, value_1, 0.0) * weight + dr.select(weight < 1.0, value_0, 0.0) * (1.0 - weight)
        pdf = dr.select(weight > 0.0, pdf_1, 0.0) * weight + dr.select(weight < 1.0, pdf_0, 0.0) * (1.0 - weight)
        return value, pdf

    def eval(self, ctx, si, wo, active=True):
        return self._eval_pdf(ctx, si, wo, self._weight(si, active), active)[0]

    def pdf(self, ctx, si, wo, active=True):
        return self._eval_pdf(ctx, si, wo, self._weight(si, active), active)[1]

    def eval_pdf(self, ctx, si, wo, active=True):
        return self._eval_pdf(ctx, si, wo, self._weight(si, active), active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        mi, dr = _mi(), _dr()
        weight = self._weight(si, active)
        pick_1 = active & (sample1 < weight)
        # the part of sample1 that picked a layer is uniform again in [0, 1) for that layer's own choice
        reused = dr.select(pick_1, sample1 / dr.maximum(weight, 1e-30),
                           (sample1 - weight) / dr.maximum(1.0 - weight, 1e-30))
        reused = dr.clip(reused, 0.0, 0.99999994)
        bs_0, _ = self.layers[0].sample(ctx, si, reused, sample2, active & ~pick_1)
        bs_1, _ = self.layers[1].sample(ctx, si, reused, sample2, pick_1)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = dr.select(pick_1, bs_1.wo, bs_0.wo)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        bs.sampled_component = mi.UInt32(0)
        value, pdf = self._eval_pdf(ctx, si, bs.wo, weight, active)
        ok = active & (pdf > 0.0)
        bs.pdf = dr.select(ok, pdf, 0.0)
        return bs, dr.select(ok, value / dr.select(ok, pdf, 1.0), 0.0)

    def traverse(self, callback):
        pass  # nothing differentiable is exposed

    def to_string(self):
        return (f"DynBTFLayeredBSDF[layer0={self.layers[0].to_string()}, layer1={self.layers[1].to_string()}, "
                f"width={self.width}, softness={self.softness}]")


def build_layered_class(mi):
    """The ``dynbtf_layered`` BSDF class of the active variant: :class:`_LayeredBSDFBody`'s methods on ``mi.BSDF``."""
    return plugin_class(_LayeredBSDFBody, mi.BSDF, "DynBTFLayeredBSDF", LAYERED_DOC)


# ------------------------------------------------------------------------------------------------ noise mask texture
class _NoiseTextureBody:
    """The body of the ``dynbtf_noise`` texture: :class:`dynbtf.layered.NoiseMask` at the shading points (value noise over
    integer lattice vertices hashed with ``seed``, smoothstep-interpolated over cells of ``scale`` uv units, then
    ``0.5 + contrast (n - 0.5)`` clipped to [0, 1]), with its gradient (``eval_1_grad``)."""

    def __init__(self, props):
        self._base.__init__(self, props)
        from ...layered import NoiseMask

        read = {name: props[name] for name in ("scale", "contrast", "seed") if props.has_property(name)}
        # NoiseMask checks the parameters (one-line errors naming them)
        self.noise = NoiseMask(float(read.get("scale", 1.0)), float(read.get("contrast", 2.0)),
                               int(read.get("seed", 0)))

    def _noise(self, si, active):
        """The mask's value and gradient at the shading points: :meth:`dynbtf.layered.NoiseMask.value_and_gradient`
        (float64 cell coordinates: exact far from the origin), the library's."""
        from .evaluator import library_call

        mi = _mi()
        noise = self.noise

        def query(u, v):
            value, gradient = noise.value_and_gradient(torch.stack([u, v], -1).to(torch.float64).cpu().numpy())
            return tuple(torch.from_numpy(np.ascontiguousarray(x)) for x in (value, gradient[:, 0], gradient[:, 1]))

        value, gx, gy = library_call(query, [si.uv.x, si.uv.y], 3, active)
        return value, mi.Vector2f(gx, gy)

    def eval_1(self, si, active=True):
        return self._noise(si, active)[0]

    def eval_1_grad(self, si, active=True):
        return self._noise(si, active)[1]

    def eval(self, si, active=True):
        return _mi().Color3f(self.eval_1(si, active))

    def mean(self):
        return 0.5

    def traverse(self, callback):
        pass

    def to_string(self):
        n = self.noise
        return f"DynBTFNoise[scale={n.scale}, contrast={n.contrast}, seed={n.seed}]"


def build_noise_class(mi):
    """The ``dynbtf_noise`` texture class of the active variant."""
    return plugin_class(_NoiseTextureBody, mi.Texture, "DynBTFNoise", _NoiseTextureBody.__doc__)
