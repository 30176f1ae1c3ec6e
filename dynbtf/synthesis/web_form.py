"""What a synthesis method gives the web export: its plane, its tables and its constants (:class:`WebForm`).

A method that runs in the web shader has a ``web`` module in its package (its
:attr:`~dynbtf.synthesis.base.Synthesizer.backends` entry ``"web"``) that declares

* ``MODE`` (int): its branch of ``dynbtf_latent`` in ``dynbtf.glsl`` (``dynbtf_mode``);
* ``ORIGIN``: what the shader's ``DynbtfOrigin.lattice`` holds for it, ``"lattice"`` (the triangle lattice's
  int64 vertex of the repeat) or ``"cells"`` (the int64 index of the repeat's first cell);
* ``SAMPLES`` and ``HASHES``: bilinear samples of the plane and vertex hashes per pixel;
* ``GLSL_UNIFORMS``, ``GLSL_FUNCTIONS``: its uniforms and functions (GLSL ES 3.00), added to the shader, each a
  block of text or a tuple of blocks (a method built on others lists theirs and its own); a block two methods
  share is emitted once;
* ``GLSL_SAMPLE``: the body of its branch, which adds its weighted samples to ``acc`` (and sets ``total``, the sum
  of their weights) with the shader's building blocks (``dynbtf_triangle``, ``dynbtf_bilinear``,
  ``dynbtf_sample_texels``, ``dynbtf_blend3``); ``GLSL_AFTER``: what it does to ``acc`` after the plane's
  dequantization (e.g. the inverse histogram tables), or ``""``;
* ``GLSL_GAIN`` (optional): the body of its branch of ``dynbtf_gain(o, local)``, which returns the RGB factor it
  applies to the decoded value (``struct``'s per-element variation), or ``""``;
* ``cost(groups) -> (texel fetches, multiply-adds)``: what its own tables add per pixel, ``groups`` RGBA layers of
  the plane (:func:`dynbtf.export.web.shader.shader_cost` counts the rest);
* ``form(synthesizer) -> WebForm``: the synthesizer's plane, tables and constants.

The exporter (:mod:`dynbtf.export.web`) writes every table by its kind and names no method.

A method that reads a **label field laid over the plane** per query (e.g. guided synthesis's target labels) gives
it as the constant ``"field"``: ``{"width", "height", "size", "wrap"}``, a grid of ``width`` x ``height`` texels over
``size`` x ``size`` exemplar repeats from the origin, ``"repeat"`` (tiled) or ``"clamp"``. The repeat origin then
holds where the repeat starts on it (:func:`dynbtf.export.web.shader.field_origin`, ``DynbtfOrigin.field``; the
viewer's ``DynBTF.origin`` too), and the shader's ``dynbtf_field_texel(o, local)`` gives the field's texel under a
query, wrapped or clamped; the method's own tables hold what the texels mean.

A method whose **elements vary** (``struct`` with ``brightness`` or ``tint``) gives the constant ``"elements"``
with ``columns``, ``rows`` and ``shift`` (:func:`dynbtf.synthesis.elements.repeat_elements`): the repeat origin
then holds the repeat's first element instance, ``(I_u columns - I_v shift, I_v rows)`` as int64 words
(``DynbtfOrigin.element``; :meth:`dynbtf.export.web.shader.RepeatOrigin.element_words`, the viewer's
``DynBTF.origin`` too).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["WebTable", "WebForm", "TABLE_KINDS"]

#: How a table is stored: ``"single"``, an ``(H, W)`` one-channel float texture (quantized like the plane);
#: ``"lut"``, ``(C, L)`` float rows of a table per channel; ``"int16"``, named integer arrays packed one after
#: another into one exact ``R16I`` texture.
TABLE_KINDS = ("single", "lut", "int16")


@dataclass
class WebTable:
    """One table of a method's shader: ``kind`` (one of :data:`TABLE_KINDS`) and its ``values`` (an array; for
    ``"int16"`` a dict of named integer arrays)."""

    kind: str
    values: np.ndarray | dict[str, np.ndarray]


@dataclass
class WebForm:
    """A synthesizer as the web shader reads it.

    ``plane``: float32 ``(H', W', C)``, the plane the method samples; ``tables``: the name of its manifest entry
    -> :class:`WebTable`; ``constants``: JSON values of the method's manifest entry (the shader's uniforms).
    """

    plane: np.ndarray
    tables: dict[str, WebTable] = field(default_factory=dict)
    constants: dict[str, Any] = field(default_factory=dict)
