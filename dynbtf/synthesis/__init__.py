"""Stage 2, Synthesize: dynamic by-example synthesis of a positional feature plane.

A synthesizer turns an exemplar plane ``(H, W, C)`` into an infinite texture
queried at any real ``uv`` (in exemplar repeats): see :mod:`.base` for the
interface. Methods (registry names):

========  ==========================================================  =======
name      method                                                      dynamic
========  ==========================================================  =======
tile      repetitive tiling (the reference point)                     yes
linear    plain linear blending on the triangle lattice (comparison)  yes
hist      histogram-preserving blending (Heitz & Neyret 2018)         yes
hex       hex-tiling (Mikkelsen 2022), rotation off                   yes
quilt     image quilting (Efros & Freeman 2001), pre-generated        no
struct    lattice-aligned cell quilting (structured materials)        yes
guided    hist steered by exemplar labels and a target label field    yes
========  ==========================================================  =======

``auto`` (:func:`~.auto.choose_method`) is not a method of its own: it measures how structured
the exemplar is (:mod:`.structure`) and builds ``struct`` or ``hist``.

Each dynamic method is a package (``tiling/``, ``blending/``, ``histogram_blending/``, ``hex_tiling/``,
``cell_quilting/``, ``guided_blending/``): its synthesizer in ``__init__.py`` and, beside it, a module per
backend it runs on besides the CPU (``web.py``: its branch of the web shader and its tables), named in the
class's ``backends``. Backends reach them through :meth:`~.base.Synthesizer.backend_form` and name no method.
(The Mitsuba plugin needs no form: it calls the library's query, :mod:`dynbtf.render.mitsuba.evaluator`.)

Building blocks: :mod:`.lattice` (triangle grid, exact at any coordinate),
:mod:`.hash` (integer vertex hash), :mod:`.histogram` (Gaussian transforms,
PCA, variance-preserving blend), :mod:`.tileable` ("Avoiding Cuts"),
:mod:`.structure` (autocorrelation peaks, structure strength), :mod:`.kernels` (the numba building
blocks of the methods' CPU kernels), :mod:`.web_form` (what a method gives the
web export), :mod:`.quality` (report) and :mod:`.coherence`
(patch coherence and identity with tiling). :mod:`.registry` (``make_synthesizer``,
``synthesizer_class``) sits above the methods, :mod:`.base` below them.
"""

from .base import SYNTHESIZERS, Synthesizer, register_synthesizer
from .cell_quilting import CellQuilting
from .blending import LatticeBlending, LinearBlending
from .guided_blending import GuidedBlending, LabelField, exemplar_labels
from .hex_tiling import HexTiling
from .histogram_blending import HistogramBlending
from .quilting import Quilting
from .tiling import Tiling
from .registry import make_synthesizer, synthesizer_class

__all__ = ["Synthesizer", "SYNTHESIZERS", "make_synthesizer", "register_synthesizer", "synthesizer_class",
           "Tiling", "CellQuilting", "LatticeBlending", "LinearBlending", "HistogramBlending", "HexTiling", "Quilting",
           "GuidedBlending", "LabelField", "exemplar_labels"]
