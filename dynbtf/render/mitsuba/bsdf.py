"""The ``dynbtf`` BSDF plugin for Mitsuba 3: a synthesized BTF evaluated at every shading point.

Call :func:`register_plugin` once and Mitsuba knows a BSDF of type ``"dynbtf"``::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")          # or a cuda_* variant
    from dynbtf.render.mitsuba.bsdf import register_plugin
    register_plugin()
    bsdf = mi.load_dict({"type": "dynbtf", "filename": "leather.dynbtf", "method": "hist", "scale": 25})

The class docstring of :class:`DynBTFBSDF` (available as :data:`PLUGIN_DOC`) is the
plugin's reference page. Its parameters are one table, :data:`PARAMETERS`: the constructor reads and
checks them from it, and :data:`PLUGIN_DOC`'s and docs/rendering.md's parameter tables are generated
from it (:func:`parameter_table_markdown`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

from ... import jit
from ...errors import InputError
from ...synthesis.auto import AUTO
from ...synthesis.elements import MAX_VARIATION
from ...synthesis.sample_transform import MAX_SCALE_JITTER
from ...synthesis.registry import VARIATIONS, methods_taking, methods_with, takes_parameter
from .evaluator import DynBTFEvaluator, check_renderable
from .sampling import AUTO_MIN_COSINE_VARIANCE, DEFAULT_TABLE_WEIGHT, SAMPLING_MODES

__all__ = ["register_plugin", "plugin_variants", "load_plugin_model", "plugin_sampler", "PLUGIN_DOC", "METHODS",
           "DEFAULT_METHOD", "number_check", "configure_jit", "DynBTFEvaluator", "ray_cone_angle", "announce_choice", "PARAMETERS",
           "PluginParameter", "read_parameters", "parameter_table_markdown"]

#: Mitsuba's ``BSDFFlags::NeedsDifferentials`` (not exported to Python): with it, integrators that trace ray
#: differentials compute ``si.duv_dx`` / ``si.duv_dy`` before calling the BSDF.
NEEDS_DIFFERENTIALS = 0x20000


def ray_cone_angle(fov: float, width: int, spp: int = 1) -> float:
    """The plugin's ``ray_cone_angle`` for a perspective camera: radians per pixel at the image centre / sqrt(spp).

    ``fov`` in degrees along the image's ``width`` pixels; ``spp`` samples per pixel (each sample
    stands for ``1 / spp`` of the pixel, as Mitsuba scales ray differentials by ``1 / sqrt(spp)``).

    >>> round(ray_cone_angle(90.0, 512, 4), 6)
    0.001953
    """
    for name, value in (("fov", fov), ("width", width), ("spp", spp)):
        if not (math.isfinite(float(value)) and float(value) > 0):
            raise InputError(f"ray_cone_angle: {name} must be positive, got {value}")
    if not float(fov) < 180.0:
        raise InputError(f"ray_cone_angle: fov must be below 180 degrees, got {fov}")
    return 2.0 * math.tan(math.radians(float(fov)) / 2.0) / float(width) / math.sqrt(float(spp))

#: Synthesis methods the plugin evaluates (every method that builds from the exemplar alone:
#: :func:`~dynbtf.synthesis.registry.methods_with`; the guided ones come through ``target``), and ``auto``.
METHODS = (*methods_with(), AUTO)
#: The plugin's (and ``dynbtf render``'s) default method.
DEFAULT_METHOD = AUTO


def check_variation_method(method: str, what: str, parameter: str = "brightness") -> None:
    """A variation parameter (:data:`~dynbtf.synthesis.registry.VARIATIONS`: struct's ``brightness``, ``tint``,
    lattice blending's ``rotation``, ``scale_jitter``) is only for a method that takes it: else a one-line error
    naming ``what``."""
    if not takes_parameter(method, parameter):
        having = methods_taking(parameter)
        raise InputError(f"{what}: {VARIATIONS[parameter]} is for {', '.join(having)}; "
                         f"method is {method!r}")


def check_cells(cells: int, method: str, what: str) -> None:
    """``cells`` (0: none) is only for a method that takes cells (:func:`~dynbtf.synthesis.registry.takes_parameter`):
    an :class:`InputError` from ``what`` otherwise."""
    if cells and not takes_parameter(method, "cells"):
        having = methods_taking("cells")
        raise InputError(f"{what}: sets the cells per repeat of {', '.join(having)}; method is {method!r}")

@dataclass(frozen=True)
class PluginParameter:
    """One parameter of the ``dynbtf`` BSDF: how the constructor reads it and how the references document it.

    The plugin's constructor, :data:`PLUGIN_DOC`'s parameter table and the table in docs/rendering.md
    (:func:`parameter_table_markdown`) all come from :data:`PARAMETERS`.

    Attributes
    ----------
    name : str
        The property's name in a scene (``filename``, ``scale``, ...).
    type : {"string", "float", "integer", "boolean"}
        What the constructor converts the property to (``str``, ``float``, ``int``, ``bool``).
    default : object
        The value where the scene does not set it; a callable takes the parameters read so far (by
        name) and returns it (``scale_v`` defaults to ``scale``); unused for a ``required`` parameter.
    doc : str
        The reference text (reStructuredText) of :data:`PLUGIN_DOC`.
    summary : str
        One line (Markdown) for the table in docs/rendering.md.
    check : callable, optional
        ``check(name, value)`` returns the value to keep or raises :class:`InputError` (``dynbtf BSDF:
        parameter 'name' ...``).
    attribute : str
        The BSDF's attribute holding the value (default: ``name``).
    required : str
        What a required parameter is, for the error naming it (empty: optional).
    shown_default : str
        The default as documented, where it is not the value itself (e.g. ``scale``, or ``0`` for ``0.0``).
    plugin : str
        The plugin the parameter belongs to, as its errors name it (``dynbtf``, ``dynbtf_layered``).
    """

    name: str
    type: str
    default: Any
    doc: str
    summary: str
    check: Callable[[str, Any], Any] | None = None
    attribute: str = ""
    required: str = ""
    shown_default: str = ""
    plugin: str = "dynbtf"

    def read(self, props, parsed: dict[str, Any]) -> Any:
        """The parameter's value in Mitsuba ``props`` (converted, checked), given the parameters ``parsed`` so far."""
        if props.has_property(self.name):
            value = _CONVERTERS[self.type](props[self.name])
        elif self.required:
            raise InputError(f"{self.plugin} BSDF: parameter '{self.name}' ({self.required}) is required")
        else:
            value = self.default(parsed) if callable(self.default) else self.default
        return self.check(self.name, value) if self.check is not None else value

    def default_text(self, markdown: bool = False) -> str:
        """The documented default: ``(required)``, a literal (``auto``, ``true``, ``scale``) or a number."""
        if self.required:
            return "required" if markdown else "(required)"
        quote = "`" if markdown else "``"
        if self.shown_default:
            text = self.shown_default
            return f"{quote}{text}{quote}" if not _is_number(text) else text
        if isinstance(self.default, bool):
            return f"{quote}{str(self.default).lower()}{quote}"
        if isinstance(self.default, str):
            return f"{quote}{self.default}{quote}"
        return str(self.default)


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


_CONVERTERS: dict[str, Callable[[Any], Any]] = {"string": str, "float": float, "integer": int, "boolean": bool}


def _one_of(choices):
    def check(name, value):
        if value not in choices:
            raise InputError(f"dynbtf BSDF: parameter '{name}' must be one of {list(choices)}, got {value!r}")
        return value

    return check


def _repeats(name, value):
    """A scale: finite, positive, below the 2**24 repeats Mitsuba's float32 uv resolves."""
    from ...limits import check_scale

    return check_scale(value, f"dynbtf BSDF: parameter '{name}'", float32=True, where="Mitsuba's float32 uv")


def number_check(valid: Callable[[float], bool], expected: str, plugin: str = "dynbtf"):
    """A :class:`PluginParameter` ``check``: keeps a value ``valid`` accepts, else raises ``{plugin} BSDF: parameter
    'name' must be {expected}, got value``."""

    def check(name, value):
        if not valid(value):
            raise InputError(f"{plugin} BSDF: parameter '{name}' must be {expected}, got {value}")
        return value

    return check


_probability = number_check(lambda v: math.isfinite(v) and 0.0 < v <= 1.0, "a probability in (0, 1]")
_unit_interval = number_check(lambda v: math.isfinite(v) and 0.0 <= v <= 1.0, "in [0, 1]")
_angle = number_check(lambda v: math.isfinite(v) and v >= 0.0, "a non-negative angle in radians")


def _at_least(low: int):
    return number_check(lambda v: v >= low, f"at least {low}")


_variation = number_check(lambda v: math.isfinite(v) and 0.0 <= v <= MAX_VARIATION,
                          f"the standard deviation of a log gain in [0, {MAX_VARIATION:g}] (0: off)")
_scale_jitter = number_check(lambda v: math.isfinite(v) and 0.0 <= v <= MAX_SCALE_JITTER,
                             f"a scale jitter in [0, {MAX_SCALE_JITTER:g}] (0: off)")



#: The plugin's parameters, in the order the constructor reads them and the references list them.
PARAMETERS: tuple[PluginParameter, ...] = (
    PluginParameter(
        "filename", "string", None, required="a dynbtf model file",
        doc="""Path of a dynbtf model file: a Triple Plane (``dynbtf fit``), one
with relief (``--repr triple-parallax``: the query marches the view
ray through the synthesized height first) or a NeuMIP (``dynbtf fit
--repr neumip``); PCA and SH models have no positional plane to
synthesize and are refused.""",
        summary="model file: Triple Plane (also `triple-parallax`) or NeuMIP; PCA and SH are refused (no positional "
                "plane to synthesize)"),
    PluginParameter(
        "method", "string", DEFAULT_METHOD, check=_one_of(METHODS),
        doc="""Synthesis of the positional plane: ``tile`` (plain repetition, the
reference point), ``linear`` (the triangle lattice's three samples blended
by their barycentrics), ``hist`` (histogram-preserving blending on a triangle
lattice, the paper's method), ``hex`` (hex-tiling), ``struct``
(lattice-aligned cell quilting: cells of the exemplar shifted by its own
lattice vectors, cut along minimum-error seams; keeps weaves, tiles and
bricks intact), ``quilt`` (off-line image quilting: a pre-generated texture,
for comparison) or ``auto``: ``struct`` for a structured exemplar (the
model's positional plane), else ``hist``
(:func:`~dynbtf.synthesis.auto.choose_method`). With ``auto`` the
plugin prints its choice and the evidence (one line, on standard error)
once per model file and process.""",
        summary="`tile`, `linear`, `hist` (the paper's), `hex`, `struct` (cell quilting for structured materials), "
                "`quilt` (off-line, pre-generated: for comparison) or `auto` "
                "(`struct` for a structured exemplar, else `hist`; the choice is printed once per model file)"),
    PluginParameter(
        "scale", "float", 1.0, check=_repeats,
        doc="""Exemplar repeats per unit of mesh ``u`` (how many times the measured
patch would fit across the mesh's uv range).""",
        summary="exemplar repeats per unit of mesh `u` (positive, below 2**24: Mitsuba's uv is float32)"),
    PluginParameter(
        "scale_v", "float", lambda parsed: parsed["scale"], check=_repeats, shown_default="scale",
        doc="""Repeats per unit of mesh ``v``; set it to ``scale / 2`` on Mitsuba's
``sphere`` (whose ``u`` spans the circumference, ``v`` half of it).""",
        summary="repeats per unit of mesh `v` (use `scale / 2` on Mitsuba's `sphere`)"),
    PluginParameter(
        "seed", "integer", 0,
        doc="Seed of the synthesis' integer hash (another seed, another material instance).",
        summary="synthesis seed"),
    PluginParameter(
        "sampling", "string", "auto", check=_one_of(SAMPLING_MODES),
        doc="""How ``sample`` draws directions: ``mixture`` (importance sampling: the
model's sampling table, built once when the plugin loads the model --
a half-vector density per view direction from the decoder, averaged over
positional features -- mixed with cosine sampling by one-sample multiple
importance sampling), ``cosine`` (cosine-weighted only, the paper's), or
``auto``: ``mixture`` where the table's lobe is one cosine sampling misses
(:func:`~dynbtf.render.mitsuba.sampling.cosine_relative_variance` of the table at
least 4: glossy materials), else ``cosine`` (rough materials, where the
table gains nothing per sample and its lookups only add to a sample's cost;
``benchmarks/bench_sampling.py`` measures both).
Any other value is an error naming the allowed ones.""",
        summary="`mixture` (the model's sampling table mixed with cosine sampling), `cosine` (the paper's), `auto` "
                "(`mixture` for glossy models, `cosine` for rough ones)"),
    PluginParameter(
        "sampling_weight", "float", DEFAULT_TABLE_WEIGHT, check=_probability, attribute="table_weight",
        doc="""In ``mixture`` mode, the probability of drawing from the table (the
rest draws cosine-weighted directions), in ``(0, 1]``.""",
        summary="in `mixture`, the probability of drawing from the table, in (0, 1]"),
    PluginParameter(
        "cells", "integer", 0, check=_at_least(0),
        doc="""``struct``'s cells per exemplar repeat along each side (0: its own
choice, 2 x 2 for most exemplars); with ``target``, give about one cell per
element so that a cell's content is of one class.""",
        summary="`struct`'s cells per repeat along each side (0: its own choice); with `target`, about one per "
                "element"),
    PluginParameter(
        "brightness", "float", 0.0, check=_variation,
        doc="""``struct``'s per-element variation (:mod:`dynbtf.synthesis.elements`):
the standard deviation of each element's log-brightness (each brick, tile or
weave element of the surface its own factor, drawn from ``seed``; joints
none), in [0, 1]. 0: off.""",
        summary="`struct`: standard deviation of each element's log-brightness, in [0, 1] (0: off)"),
    PluginParameter(
        "tint", "float", 0.0, check=_variation,
        doc="""``struct``'s per-element variation: the standard deviation of the
element's channels' log gains against each other, in [0, 1]. 0: off.""",
        summary="`struct`: standard deviation of each element's colour tint (log gains of the channels against "
                "each other), in [0, 1] (0: off)"),
    PluginParameter(
        "rotation", "boolean", False,
        doc="""Lattice blending's (``hist``, ``hex``, ``linear``) sample rotation
(:mod:`dynbtf.synthesis.sample_transform`): each lattice vertex's sample
turned by random quarter turns (drawn from ``seed``) about a texel
centre next to the vertex, the view and the light turned into the
query's frame. For isotropic materials.""",
        summary="`hist`, `hex`, `linear`: turn each sample by random quarter turns (for isotropic materials)"),
    PluginParameter(
        "scale_jitter", "float", 0.0, check=_scale_jitter,
        doc="""Lattice blending's (``hist``, ``hex``, ``linear``) sample scales
(:mod:`dynbtf.synthesis.sample_transform`): each lattice vertex's sample
magnified by a random factor between ``1 / (1 + scale_jitter)`` and
``1 + scale_jitter`` (log-uniform, drawn from ``seed``), in [0, 1]. 0: off.
Reads between texel centres: for models fitted with the sub-texel term.""",
        summary="`hist`, `hex`, `linear`: magnify each sample by a random factor in [1/(1 + j), 1 + j], j in "
                "[0, 1] (0: off)"),
    PluginParameter(
        "target", "string", "", shown_default='""',
        doc="""Guided synthesis (:func:`dynbtf.guided.guided_btf`): an image painted
over the mesh's uv (PNG/JPEG grey levels, or EXR values in [0, 1]), cut
into ``classes`` equal bins; a point in bin ``k`` shows the material's
class ``k`` (k-means on its decoded appearance, 0 the darkest). Steers
``hist`` (also what ``auto`` becomes), ``hex`` or ``struct`` (with ``cells``),
with footprint queries as unguided (``filtered``). Empty: no guidance.""",
        summary="guided synthesis: an image painted over the mesh's uv, cut into `classes` bins (class 0 the "
                "darkest content); steers `hist`, `hex` or `struct` (with `cells`); empty: none"),
    PluginParameter(
        "classes", "integer", 2, check=_at_least(2),
        doc="With ``target``: classes of the material's texels (k-means), at least 2.",
        summary="with `target`: classes of the material's texels (k-means), at least 2"),
    PluginParameter(
        "target_size", "float", 1.0, check=_repeats,
        doc="""With ``target``: mesh uv units the target image covers (along ``u``;
laid out in exemplar repeats through ``scale``).""",
        summary="with `target`: mesh uv units the target image covers"),
    PluginParameter(
        "target_wrap", "string", "repeat", check=_one_of(("repeat", "clamp")),
        doc="With ``target``: the image repeats (``repeat``) or extends its edges (``clamp``).",
        summary="with `target`: the image repeats (`repeat`) or extends its edges (`clamp`)"),
    PluginParameter(
        "softness", "float", 0.0, check=_unit_interval, shown_default="0",
        doc="""With ``target``: weight factor in [0, 1] of the samples that found no
content of the target's class (0: dropped where another sample found some).""",
        summary="with `target`: weight factor in [0, 1] of samples that found no content of the target's class"),
    PluginParameter(
        "filtered", "boolean", True,
        doc="""Footprint queries: a shading point that stands for a footprint
(below) answers the synthesized BTF averaged over it, as
:meth:`~dynbtf.infinite_btf.SynthesizedBTF.eval` with ``footprint``
does (pyramid levels of the synthesized samples, a decoder per level),
so distant surfaces do not alias. Where no footprint is known it is
the point query. ``false``: always the point query.""",
        summary="footprint queries where a footprint is known (below); `false`: always the point query"),
    PluginParameter(
        "ray_cone_angle", "float", 0.0, check=_angle, attribute="cone", shown_default="0",
        doc="""Spread (radians) of one camera sample's ray cone: the angle one pixel
subtends divided by ``sqrt(spp)``
(:func:`~dynbtf.render.mitsuba.bsdf.ray_cone_angle`;
:func:`dynbtf.render.mitsuba.scenes.scene_dict` sets it from its camera).
Mitsuba's own integrators do not pass ray differentials to BSDFs, so
the footprint is estimated from the cone: the side
``t ray_cone_angle / cos(theta_view)`` at hit distance ``t``, in uv
through ``|dp/du|`` and ``|dp/dv|`` (the longer side). Where the
integrator computed uv partials (``si.duv_dx``, ``si.duv_dy``, e.g. a
custom integrator calling ``si.compute_uv_partials(ray)``), those are
used instead (:func:`~dynbtf.infinite_btf.footprint_width`). 0: partials only.""",
        summary="radians: one camera sample's spread (`dynbtf.render.mitsuba.bsdf.ray_cone_angle(fov, width, "
                "spp)`; `scene_dict` sets it), used where the integrator gives no uv partials; 0: partials only"),
)


def read_parameters(props) -> dict[str, Any]:
    """The plugin's parameters from Mitsuba ``props``, converted and checked (:data:`PARAMETERS`), by name."""
    parsed: dict[str, Any] = {}
    for parameter in PARAMETERS:
        parsed[parameter.name] = parameter.read(props, parsed)
    return parsed


def rst_parameter_rows(parameters) -> str:
    """The rows of a plugin reference's parameter table (reStructuredText ``list-table``) for ``parameters``."""
    rows = []
    for p in parameters:
        description = "\n       ".join(p.doc.splitlines())
        rows.append(f"   * - ``{p.name}``\n     - {p.type}\n     - {description}\n     - {p.default_text()}\n")
    return "".join(rows)


def parameter_table_markdown() -> str:
    """The plugin's parameter table in Markdown, as docs/rendering.md shows it (a test keeps the two equal)."""
    lines = ["| Parameter | Type | Description | Default |", "|---|---|---|---|"]
    lines += [f"| `{p.name}` | {p.type} | {p.summary} | {p.default_text(markdown=True)} |" for p in PARAMETERS]
    return "\n".join(lines) + "\n"


_DOC_HEAD = """Synthesized BTF material (``dynbtf``)

Evaluates an infinite, non-repeating BTF -- a fitted Triple Plane (or NeuMIP)
model whose positional feature plane is synthesized on the fly -- at every
shading point.
Each wavefront's shading points are answered by the library's own query,
:meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` (lattice, integer hash,
histogram-preserving blend, inverse transform -- or for ``struct`` the cell's
hash, its cut and one fetch --, decoder MLP), handed the points and back
(:mod:`dynbtf.render.mitsuba.evaluator`); nothing is pre-generated, so any
``scale`` costs the same.

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Description
     - Default
"""

_DOC_TAIL = """Conventions: ``si.wi`` (towards the camera / previous path vertex) is the BTF's
``w_view``, ``wo`` (towards the light / next vertex) its ``w_light``, both in the
local shading frame with ``x`` along ``dp/du`` and ``y`` along ``dp/dv`` (the
BTF's frame: x along +u, y along +v). Mitsuba's frame has ``y = n x dp/du``;
where that points along ``-dp/dv`` (a left-handed parametrization, e.g. Mitsuba's
``sphere``) the plugin mirrors the ``y`` of both directions, so shading agrees
with the texture's orientation on every mesh (on the ``rectangle`` and on
meshes whose uv runs like their x, y no mirroring happens).
``eval`` returns ``value / pi * cos(theta_light)`` where ``value`` is what
:meth:`dynbtf.infinite_btf.SynthesizedBTF.eval` returns at
``uv = (scale * u, scale_v * v)``; directions below either horizon give 0
(one-sided reflection: wrap it in Mitsuba's ``twosided`` for cloth).
Sampling: with ``sampling = "cosine"``, cosine-weighted over the upper hemisphere
(pdf ``cos(theta) / pi``), as in the paper, so a sample's weight is the BTF value
itself. With ``"mixture"`` (what ``"auto"``, the default, picks for glossy models),
a direction comes from the sampling table with probability ``sampling_weight`` and from the cosine distribution
otherwise; ``pdf`` returns the mixture's density
``a pdf_table + (1 - a) cos(theta) / pi`` whichever way the direction was drawn,
and ``sample``'s weight is ``eval / pdf`` (see :mod:`dynbtf.render.mitsuba.sampling`).
The table costs a few seconds when a model is first loaded; so do the per-level
decoders of ``filtered`` (fitted at load). Both are stored in the model's compiled
material (:mod:`dynbtf.material`, in the cache shared with
:class:`~dynbtf.infinite_btf.SynthesizedBTF`), so later loads, in this process or
another, read them.
If the table cannot be built (the decoder returns NaN or inf, or a view has
no density), the plugin falls back to cosine sampling and says so once per
model file with a warning (``UserWarning``).
A BTF is not reciprocal: use radiance-mode integrators (``path``, ``direct``), not
light tracing.

Dr.Jit flags: :func:`register_plugin` turns Dr.Jit's ``SymbolicLoops`` and
``SymbolicCalls`` off (:func:`configure_jit`). Dr.Jit keeps these flags per
thread, so the change holds for the rest of the calling thread's life and for
everything Dr.Jit runs in it, not only this BSDF: every later loop (e.g. any
integrator's path loop) and virtual call is evaluated in wavefront mode. Why:
the plugin hands each wavefront to the library, which a symbolic loop (its
body traced once) cannot call out to. Code that needs symbolic mode afterwards
(without this plugin) sets the flags back with ``drjit.set_flag``; another
thread that renders with the plugin calls :func:`configure_jit` itself.

Precision: Mitsuba's mesh uv and the product ``scale * u`` are float32; from
there on the query is dynbtf's (the lattice in float64), so the plugin agrees
with :class:`~dynbtf.infinite_btf.SynthesizedBTF` at the same float32 ``uv``. Repeat
counts beyond ~1e4 per mesh make float32 uv coarser than a texel (a mesh
limitation, not a synthesis one).
"""

#: The plugin's reference page (the class docstring of the BSDF); its parameter table comes from :data:`PARAMETERS`.
PLUGIN_DOC = _DOC_HEAD + rst_parameter_rows(PARAMETERS) + "\n" + _DOC_TAIL


def configure_jit() -> None:
    """Dr.Jit flags under which the plugin can hand a wavefront to the library.

    Symbolic loops and calls trace the integrator's loop body once and dispatch
    BSDF calls indirectly, inside one kernel; with them off (wavefront mode), each
    BSDF call sees its wavefront as evaluated arrays, which
    :mod:`~dynbtf.render.mitsuba.evaluator` hands to ``SynthesizedBTF.eval``.

    The flags are Dr.Jit's per-thread state: this changes them for everything
    the calling thread runs afterwards (see "Dr.Jit flags" in :data:`PLUGIN_DOC`).
    """
    dr = jit.drjit_module()

    dr.set_flag(dr.JitFlag.SymbolicLoops, False)
    dr.set_flag(dr.JitFlag.SymbolicCalls, False)


def _mi():
    return jit.mitsuba_module()


def _dr():
    return jit.drjit_module()


class _DynBTFBSDFBody:
    """The body of the ``dynbtf`` BSDF class: :func:`plugin_class` copies it onto a subclass of the active
    variant's ``mi.BSDF``."""

    # ------------------------------------------------------------ construction
    def __init__(self, props):
        self._base.__init__(self, props)
        mi = _mi()
        parsed = read_parameters(props)  # every parameter converted and checked, before the model loads
        for parameter in PARAMETERS:
            setattr(self, parameter.attribute or parameter.name, parsed[parameter.name])
        model = load_plugin_model(self.filename)  # a representation or a compiled material
        if self.scale_jitter:
            from ...synthesized import warn_without_subtexel_term

            warn_without_subtexel_term(self.filename)
        check_cells(self.cells, self.method, "dynbtf BSDF: parameter 'cells'")
        params = {"cells": self.cells} if self.cells else {}
        for name in VARIATIONS:
            if getattr(self, name):
                check_variation_method(self.method, f"dynbtf BSDF: parameter '{name}'", name)
                value = getattr(self, name)
                params[name] = value if isinstance(value, bool) else float(value)
        # the app-level step: the material opened from the cache or compiled (with the footprint decoders if asked),
        # or the guided one the target asks for; the evaluator only translates it
        btf = self._guided_btf(model, params)
        if btf is None:
            from ...synthesized import synthesized_btf

            btf = synthesized_btf(model, self.method, scale=1.0, seed=self.seed, footprints=self.filtered, **params)
        self.evaluator = DynBTFEvaluator(btf)
        model = self.evaluator.btf.model
        #: the method the query runs (``auto``'s choice, else ``method``)
        self.synthesis = self.evaluator.method
        if self.evaluator.choice is not None:
            announce_choice(self.filename, self.evaluator.choice)
        if self.filtered:  # the pyramid and per-level decoders, before the first shading point
            self.evaluator.prepare_footprints()
        self.sampler = self._choose_sampler(model)
        self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        self.m_components = [self.m_flags]
        if self.filtered:
            self.m_flags = int(self.m_flags) | NEEDS_DIFFERENTIALS

    def _guided_btf(self, model, params):
        """The guided synthesized BTF of ``target`` (None without one), its request checked (one-line errors);
        ``params``: the method's parameters (struct's ``cells``)."""
        if not self.target:
            return None
        from ...guided import guided_btf
        from ...layered import mask_from_spec

        from ...guided import guided_method

        method = guided_method(self.method, self.cells, where="dynbtf BSDF: parameter 'target'")
        painted = mask_from_spec(self.target, size=1.0, wrap=self.target_wrap)
        if not hasattr(painted, "image"):
            raise InputError(f"dynbtf BSDF: parameter 'target': expected an image file, got {self.target!r}")
        image = painted.image
        # the target over target_size mesh uv units = target_size * scale exemplar repeats (guided_btf's scale 1)
        return guided_btf(model, image, classes=self.classes, target_size=self.target_size * self.scale,
                          target_wrap=self.target_wrap, seed=self.seed, softness=self.softness,
                          method=method, footprints=self.filtered, **params)

    def _choose_sampler(self, model):
        """The table sampler of ``sampling`` ``auto``/``mixture`` (None: cosine); resolves :attr:`sampling`."""
        if self.sampling not in ("auto", "mixture"):
            return None
        sampler = plugin_sampler(self.filename, model, btf=self.evaluator.btf)
        if sampler is None:
            self.sampling = "cosine"  # the fall-back, announced once by plugin_sampler
        elif self.sampling == "auto":
            # the table where cosine sampling misses the model's lobe (glossy), else cosine
            glossy = sampler.cosine_relative_variance >= AUTO_MIN_COSINE_VARIANCE
            self.sampling = "mixture" if glossy else "cosine"
            sampler = sampler if glossy else None
        return sampler

    # ------------------------------------------------------------ BTF value
    @staticmethod
    def _mirror(si):
        """+1, or -1 where the BTF's y (+v) is the frame's -t (a left-handed parametrization)."""
        # Mitsuba's frame t = n x s runs along -dp/dv where the parametrization is left-handed
        # (its sphere): the BTF sees both directions mirrored in y there
        return _dr().select(_dr().dot(si.sh_frame.t, si.dp_dv) < 0.0, -1.0, 1.0)

    @staticmethod
    def _flip_y(w, y):
        """``w`` with its y multiplied by ``y`` (:meth:`_mirror`): the frame's and the BTF's directions."""
        return _mi().Vector3f(w.x, w.y * y, w.z)

    def _value(self, si, wo, active):
        mi, dr = _mi(), _dr()
        # opaque: the scale is a kernel parameter, not a literal, so scenes that differ
        # only in scale share Mitsuba's compiled kernels
        scale_u, scale_v = dr.opaque(mi.Float, self.scale), dr.opaque(mi.Float, self.scale_v)
        u = si.uv.x * scale_u
        v = si.uv.y * scale_v
        y = self._mirror(si)
        return self.evaluator.eval(u, v, self._flip_y(si.wi, y), self._flip_y(wo, y), active,
                                   footprint=self._footprint(si, scale_u, scale_v))

    def _footprint(self, si, scale_u, scale_v):
        """Each lane's footprint (side of a square, exemplar repeats) or None: the point query everywhere."""
        if not self.filtered:
            return None
        mi, dr = _mi(), _dr()
        partials = (si.duv_dx.x != 0.0) | (si.duv_dx.y != 0.0) | (si.duv_dy.x != 0.0) | (si.duv_dy.y != 0.0)
        if self.cone == 0.0 and not dr.flag(dr.JitFlag.SymbolicScope) and not dr.any(partials):
            return None  # nothing has a footprint: the point query, bit for bit
        width = dr.maximum(dr.norm(mi.Vector2f(si.duv_dx.x * scale_u, si.duv_dx.y * scale_v)),
                           dr.norm(mi.Vector2f(si.duv_dy.x * scale_u, si.duv_dy.y * scale_v)))
        if self.cone > 0.0:  # the camera ray's cone at the hit, stretched along the view, in uv
            side = si.t * self.cone / dr.maximum(dr.abs(mi.Frame3f.cos_theta(si.wi)), 1e-6)
            cone = side * dr.maximum(scale_u / dr.norm(si.dp_du), scale_v / dr.norm(si.dp_dv))
            width = dr.select(partials, width, dr.select(dr.isfinite(cone), cone, 0.0))
        return width

    @staticmethod
    def _valid(si, wo, active):
        mi = _mi()
        return active & (mi.Frame3f.cos_theta(si.wi) > 0.0) & (mi.Frame3f.cos_theta(wo) > 0.0)

    def _pdf(self, si, wo, active):
        """The density ``sample`` draws ``wo`` with (solid angle), for valid ``wo``."""
        cosine = _mi().warp.square_to_cosine_hemisphere_pdf(wo)
        if self.sampler is None:
            return cosine
        y = self._mirror(si)
        table = self.sampler.pdf(self._flip_y(si.wi, y), self._flip_y(wo, y), active)
        a = self.table_weight
        return a * table + (1.0 - a) * cosine

    # ------------------------------------------------------------ BSDF API
    def sample(self, ctx, si, sample1, sample2, active=True):
        mi, dr = _mi(), _dr()
        bs = dr.zeros(mi.BSDFSample3f)
        wo = mi.warp.square_to_cosine_hemisphere(sample2)
        if self.sampler is not None:
            y = self._mirror(si)
            from_table = active & (sample1 < self.table_weight)
            # sample1 < a chose the table; sample1 / a is uniform again and picks the view node
            drawn = self.sampler.sample(self._flip_y(si.wi, y),
                                        sample1 * (1.0 / self.table_weight), sample2, from_table)
            wo = dr.select(from_table, self._flip_y(drawn, y), wo)
        bs.wo = wo
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        bs.sampled_component = mi.UInt32(0)
        ok = self._valid(si, bs.wo, active)
        bs.pdf = dr.select(ok, self._pdf(si, bs.wo, ok), 0.0)
        ok &= bs.pdf > 0.0
        value = self._value(si, bs.wo, ok)
        if self.sampler is None:
            # weight = eval / pdf = (value / pi * cos) / (cos / pi) = value
            return bs, dr.select(ok, value, 0.0)
        weight = value * (dr.inv_pi * mi.Frame3f.cos_theta(bs.wo) / dr.select(ok, bs.pdf, 1.0))
        return bs, dr.select(ok, weight, 0.0)

    def eval(self, ctx, si, wo, active=True):
        mi, dr = _mi(), _dr()
        ok = self._valid(si, wo, active)
        value = self._value(si, wo, ok)
        return dr.select(ok, value * (dr.inv_pi * mi.Frame3f.cos_theta(wo)), 0.0)

    def pdf(self, ctx, si, wo, active=True):
        ok = self._valid(si, wo, active)
        return _dr().select(ok, self._pdf(si, wo, ok), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        mi, dr = _mi(), _dr()
        ok = self._valid(si, wo, active)
        value = self._value(si, wo, ok) * (dr.inv_pi * mi.Frame3f.cos_theta(wo))
        return dr.select(ok, value, 0.0), dr.select(ok, self._pdf(si, wo, ok), 0.0)

    def traverse(self, callback):
        pass  # nothing differentiable is exposed

    def to_string(self):
        method = self.method if self.synthesis == self.method else f"{self.method} -> {self.synthesis}"
        return (f"DynBTFBSDF[filename={self.filename!r}, method={method!r}, "
                f"scale={self.scale}, scale_v={self.scale_v}, seed={self.seed}, sampling={self.sampling!r}, "
                f"filtered={self.filtered}, ray_cone_angle={self.cone}]")


def plugin_class(body: type, base: type, name: str, doc: str) -> type:
    """A plugin class of the active variant: ``body``'s methods on ``base`` (``mi.BSDF``, ``mi.Texture``).

    nanobind classes take one base, so a body cannot be a mix-in; its ``__init__`` calls ``self._base.__init__``."""
    namespace = {key: value for key, value in vars(body).items()
                 if key not in ("__dict__", "__weakref__", "__doc__", "__module__", "__qualname__")}
    namespace.update(__doc__=doc, __module__=body.__module__, __qualname__=name, _base=base)
    return type(name, (base,), namespace)

_SAMPLERS: dict = {}
_TABLES: dict = {}  # the tables of _SAMPLERS' samplers (None: not sampleable)
_ANNOUNCED: set = set()
_CHOICES_ANNOUNCED: set = set()


def announce_choice(filename, choice) -> bool:
    """Print what ``method = "auto"`` chose for model file ``filename`` (``choice.line``) on standard error,
    once per file version (path, size, modification time) and process; True if it printed."""
    import os
    import sys

    stat = os.stat(filename)
    key = (os.path.abspath(str(filename)), stat.st_size, stat.st_mtime_ns)
    if key in _CHOICES_ANNOUNCED:
        return False
    _CHOICES_ANNOUNCED.add(key)
    print(f"dynbtf BSDF ({filename}): {choice.line}", file=sys.stderr, flush=True)
    return True


def plugin_sampler(filename, model, *, build=None, btf=None):
    """The :class:`~dynbtf.render.mitsuba.sampling.DrTableSampler` of model file ``filename``, or ``None``.

    Made once per file version (path, size, modification time) and process. The table comes from the
    compiled material of ``btf`` (a :class:`~dynbtf.infinite_btf.SynthesizedBTF` of ``model``: the
    plugin's evaluator's) when it holds one (``material.sampling``); else it is built by
    :func:`~dynbtf.render.mitsuba.sampling.build_sampling_table` and stored into the material, which is
    written back to the compiled-material cache (when it has a cache key), so that the next process
    reads it (a material of the same file that comes later in the process, e.g. another method or seed,
    gets the process's table). ``build(model)`` replaces both (tests): the table is built by it, neither
    read nor stored.
    A table that cannot be sampled (:func:`~dynbtf.render.mitsuba.sampling.table_problem`)
    gives ``None`` -- the plugin then samples cosine-weighted -- and a
    ``UserWarning`` naming the file and the problem, once per file; it is not stored.
    """
    import os
    import warnings

    from .sampling import DrTableSampler, build_sampling_table, table_problem

    mi = jit.mitsuba_module()
    stat = os.stat(filename)
    key = (os.path.abspath(str(filename)), stat.st_size, stat.st_mtime_ns, mi.variant(), build)
    if key not in _SAMPLERS:
        table = build(model) if build is not None else _material_table(btf) or build_sampling_table(model)
        problem = table_problem(table)
        _SAMPLERS[key] = None if problem else DrTableSampler(table)
        _TABLES[key] = None if problem else table
        if problem and key[0] not in _ANNOUNCED:
            _ANNOUNCED.add(key[0])
            warnings.warn(f"{filename}: {problem}; the dynbtf plugin samples this model cosine-weighted "
                          f"(sampling='cosine')", UserWarning, stacklevel=2)
    if build is None and _TABLES.get(key) is not None:
        _store_table(btf, _TABLES[key])  # this material's first table (another method or seed of the same file)
    return _SAMPLERS[key]


def _material_table(btf):
    """The sampling table stored in ``btf``'s compiled material, or None (none, or one that cannot be sampled)."""
    from .sampling import SamplingTable, table_problem

    table = SamplingTable.from_tensors(getattr(getattr(btf, "material", None), "sampling", None))
    return table if table is not None and table_problem(table) is None else None


def _store_table(btf, table) -> None:
    """Put ``table`` into ``btf``'s compiled material unless it holds one, and write the material to the
    compiled-material cache (when it has a cache key: a material of a ready synthesizer has none)."""
    material = getattr(btf, "material", None)
    if material is None or _material_table(btf) is not None:
        return
    btf.material = material = material.with_sampling(table.to_tensors())
    if material.key:
        from ...material import store_cached

        store_cached(material)


def load_plugin_model(filename):
    """The representation in model file ``filename`` -- or the compiled material in it (``dynbtf compile``'s
    ``.dbtfc``: a :class:`~dynbtf.material.format.CompiledMaterial`, whose method and seed the plugin then
    uses) -- checked for the plugin.

    What the plugin's constructor loads; :func:`dynbtf.render.mitsuba.scene_render.render_scene`
    calls it before Mitsuba loads a scene, so that a mistake is a clear error and
    not one wrapped by Mitsuba.

    Raises
    ------
    FormatError
        The file is missing, damaged or not a dynbtf model file.
    InputError
        The model's kind is not one the plugin evaluates (PCA, SH).
    """
    from ...material import open_model_file

    model, material = open_model_file(filename, device="cpu")
    check_renderable(model, str(filename))
    return model if material is None else material


def plugin_variants() -> list[str]:
    """Mitsuba variants the plugin runs on here, best first (e.g. ``["llvm_ad_rgb"]`` on a CPU).

    The plugin needs an RGB variant (it returns RGB colours) of a JIT back end (it hands
    whole wavefronts to the library): ``llvm_*_rgb`` when Dr.Jit finds the LLVM library,
    ``cuda_*_rgb`` when it finds a CUDA device. Only variants built into the
    installed Mitsuba count.
    """
    dr = jit.drjit_module()
    mi = jit.mitsuba_module()

    backends = {"llvm": dr.JitBackend.LLVM, "cuda": dr.JitBackend.CUDA}
    usable = {name: bool(dr.has_backend(b)) for name, b in backends.items()}
    ok = [v for v in mi.variants() if v.endswith("_rgb") and usable.get(v.split("_")[0], False)]
    return sorted(ok, key=lambda v: (v != "llvm_ad_rgb", v))


def _check_variant(variant: str, available: list[str]) -> None:
    """:class:`InputError` saying why ``variant`` cannot run the plugin, unless it is in ``available``."""
    mi = jit.mitsuba_module()

    if variant in available:
        return
    backend = variant.split("_")[0]
    if variant not in mi.variants():
        why = f"not built into the installed Mitsuba {mi.__version__}"
    elif backend not in ("llvm", "cuda") or not variant.endswith("_rgb"):
        why = "the dynbtf plugin needs an RGB variant of the LLVM or CUDA back end (llvm_*_rgb, cuda_*_rgb)"
    elif backend == "cuda":
        why = "no CUDA device or driver found on this machine"
    else:
        why = "Dr.Jit found no LLVM library on this machine (install it, e.g. apt-get install libllvm19)"
    listed = ", ".join(available) if available else "none"
    raise InputError(f"--variant: Mitsuba variant {variant!r} is not available: {why}; "
                     f"available for the dynbtf plugin here: {listed}")


_REGISTERED: set[str] = set()


def register_plugin(variant: str | None = None) -> str:
    """Register the ``dynbtf`` BSDF and the ``dynbtf_layered`` one (:mod:`.layered_bsdf`) with Mitsuba
    (idempotent per variant).

    Also calls :func:`configure_jit`, which changes Dr.Jit's flags for the
    calling thread (see "Dr.Jit flags" in :data:`PLUGIN_DOC`).

    Parameters
    ----------
    variant : str, optional
        Mitsuba variant to activate first (one of :func:`plugin_variants`, e.g.
        ``"llvm_ad_rgb"``, ``"cuda_ad_rgb"``). ``None`` keeps the active one, or
        picks ``llvm_ad_rgb`` when none is set.

    Returns
    -------
    str: the active variant.

    Raises
    ------
    InputError
        The variant is not built, not usable on this machine (no CUDA device, no
        LLVM library) or not one the plugin runs on (scalar, mono, spectral); the
        message lists the variants that are available.
    """
    mi = jit.mitsuba_module()

    wanted = variant if variant is not None else (mi.variant() or "llvm_ad_rgb")
    from ...jit.llvm import check_llvm

    check_llvm(wanted)  # an old LLVM aborts the process while compiling: refused before the variant is set
    _check_variant(wanted, plugin_variants())
    if mi.variant() != wanted:
        mi.set_variant(wanted)
    configure_jit()
    active = mi.variant()
    if active not in _REGISTERED:
        cls = plugin_class(_DynBTFBSDFBody, mi.BSDF, "DynBTFBSDF", PLUGIN_DOC)
        mi.register_bsdf("dynbtf", lambda props: cls(props))
        from .layered_bsdf import build_layered_class, build_noise_class

        layered, noise = build_layered_class(mi), build_noise_class(mi)
        mi.register_bsdf("dynbtf_layered", lambda props: layered(props))
        mi.register_texture("dynbtf_noise", lambda props: noise(props))
        _REGISTERED.add(active)
    return active
