"""The web export of a layered material: both materials, their mask and the boundary rule, in one viewer.

:func:`export_layered_web` writes a :class:`~dynbtf.layered.LayeredBTF` for a GPU: each layer as a web
export of its own (``layer0/``, ``layer1/``: the material as compiled, its method, seed and tables;
:func:`~dynbtf.export.web.exporter.export_web`), and next to them

* ``layered.json`` -- the layers (directory, method, scale, how the height is read from the synthesized
  features), the mask, the band's ``width`` and ``softness``;
* ``layered.glsl`` -- the mask (image or value noise, its value and gradient, the signed distance to its
  0.5 contour) and ``dynbtf_layer_pass``, appended to each layer's ``dynbtf.glsl``
  (:func:`layered_glsl`);
* ``mask.bin`` -- an image mask's values (``R32F``, row 0 at ``v = 0``);
* the viewer (``index.html``, ``viewer.js``), which renders the two layers in two passes, lets the user
  paint the mask, load one from an image and save it as a PNG for ``dynbtf synth --mask``.

A pixel is evaluated as :meth:`LayeredBTF.eval <dynbtf.layered.LayeredBTF.eval>` evaluates a point: the
first pass evaluates layer 0 where it can show (its side of the contour, and the band) and writes its
value and height; the second evaluates layer 1 where it can show, reads the first pass's result at the
same pixel, decides inside the band by ``h_1 - h_0 + d / width`` (or blends over ``softness``) and writes
the mix. Outside the band a pixel evaluates one material. The mask is computed in float32 from an origin
split on the CPU in float64 (:func:`mask_origin`; ``DynBTF.maskOrigin`` in ``viewer.js`` is the same), so a
noise mask's lattice hashes are the library's at any distance; points within float32 rounding of a
decision (the contour, the band's edge, equal scores) may fall on the other side.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import InputError
from ...io import atomic_path
from ...limits import check_scale
from ...layered import HEIGHT_TABLE
from ...synthesis.hash import MASK32, seed_state
from .exporter import WebExport, _export_web, _output_directory, _pad4, _Writer, check_precision, write_viewer_page
from .shader import LOCAL_REPEATS, RepeatOrigin, _float, lattice_constants

__all__ = ["export_layered_web", "LayeredWebExport", "layered_glsl", "mask_origin", "MaskOrigin", "LAYERED_FORMAT",
           "LAYERED_VERSION", "MASK_KINDS"]

#: ``format`` of ``layered.json``.
LAYERED_FORMAT = "dynbtf-web-layered"
#: Version of its layout.
LAYERED_VERSION = 1
#: The masks the shader evaluates, by ``dynbtf_mask_kind``.
MASK_KINDS = {"image": 0, "noise": 1}


@dataclass
class LayeredWebExport:
    """What :func:`export_layered_web` wrote: the directory, ``layered.json``'s content and each layer's export."""

    directory: Path
    manifest: dict[str, Any]
    layers: list[WebExport]

    @property
    def index(self) -> Path:
        """The viewer page."""
        return self.directory / "index.html"


# ---------------------------------------------------------------- the mask's origin (CPU side of large uv)
@dataclass
class MaskOrigin:
    """The part of a surface position the CPU computes in float64 for the shader's mask.

    ``cell`` (int64 ``(..., 2)``): a noise mask's lattice cell ``floor(uv_origin / scale)`` (0 for an image);
    ``offset`` (float64 ``(..., 2)``): the origin within it -- a noise mask's ``uv_origin / scale - cell``, a
    repeated image's ``uv_origin mod size``, a clamped image's ``uv_origin``. The shader adds a float32 local uv.
    """

    cell: np.ndarray
    offset: np.ndarray

    def words(self) -> np.ndarray:
        """``(..., 4)`` uint32: low and high words of ``cell``'s x, then of its y (two's complement)."""
        return RepeatOrigin._words(self.cell[..., 0], self.cell[..., 1])


def mask_origin(mask: dict[str, Any], uv) -> MaskOrigin:
    """Split surface positions ``uv (..., 2)`` (float64, uv units) for the shader's mask ``mask`` (the ``mask``
    entry of ``layered.json``)."""
    uv = np.asarray(uv, dtype=np.float64)
    if mask["kind"] == "noise":
        p = uv / float(mask["scale"])
        cell = np.floor(p)
        return MaskOrigin(cell.astype(np.int64), p - cell)
    if mask["wrap"] == "repeat":
        return MaskOrigin(np.zeros(uv.shape, np.int64), np.mod(uv, float(mask["size"])))
    return MaskOrigin(np.zeros(uv.shape, np.int64), uv.copy())


# ---------------------------------------------------------------- the shader
def layered_glsl(*, softness: float = 0.0) -> str:
    """``layered.glsl``: appended to a layer's ``dynbtf.glsl`` (GLSL ES 3.00, no ``#version``).

    ``dynbtf_mask_distance(mask_origin, mask_local)`` is the signed distance (uv units, positive on layer 1's
    side) to the mask's 0.5 contour, ``(m - 0.5) / |grad m|`` as :func:`dynbtf.layered.contour_distance`;
    ``dynbtf_layer_pass(origin, local, mask_origin, mask_local, w_view, w_light, previous)`` is one layer's pass
    (see the module docstring): layer 0 returns ``(value, height)``, layer 1 ``(mixed value, layer 1's
    weight)`` from layer 0's ``previous``. ``softness`` > 0 blends over that height difference
    (:class:`dynbtf.layered.LayeredBTF`'s parameter; a constant of the program).
    """
    blend = (f"clamp(0.5 + score * {_float(0.5 / softness)}, 0.0, 1.0)" if softness > 0 else
             "(score > 0.0 ? 1.0 : 0.0)")
    return f"""
// ---- layered material (dynbtf.layered.LayeredBTF), generated by dynbtf.export.web.layered
uniform int dynbtf_mask_kind;               // 0: an image over dynbtf_mask_size uv units, 1: value noise
uniform highp sampler2D dynbtf_mask;        // the image, R32F, row 0 at v = 0
uniform float dynbtf_mask_size;
uniform bool dynbtf_mask_repeat;            // the image repeats (else its edge texels extend it)
uniform float dynbtf_mask_scale;            // noise: uv units per cell
uniform float dynbtf_mask_contrast;
uniform uint dynbtf_mask_seed_state;        // noise: seed_state(seed)
uniform int dynbtf_layer_index;             // 0 or 1: which layer this program evaluates
uniform float dynbtf_layer_width;           // half-width of the band around the contour (uv units)
uniform vec4 dynbtf_layer_height_map[DYNBTF_G];   // raw height = latent . map + offset
uniform float dynbtf_layer_height_offset;
uniform vec2 dynbtf_layer_height_range;     // the exemplar's lowest and highest raw height
uniform vec4 dynbtf_layer_height_table[{HEIGHT_TABLE // 4}];   // the raw height's rank at evenly spaced raw heights

struct DynbtfMaskOrigin {{
    uvec4 cell;      // noise: (low, high) words of the int64 cell of the origin, x then y
    vec2 offset;     // noise: origin / scale - cell; image: origin mod size (repeat) or origin (clamp)
}};

// the mask's value (.x) and gradient (.yz, per uv unit) at the origin plus mask_local (uv units)
vec3 dynbtf_mask_value(DynbtfMaskOrigin mo, vec2 mask_local) {{
    if (dynbtf_mask_kind == 1) {{   // value noise (dynbtf.layered.NoiseMask)
        vec2 p = mo.offset + mask_local / dynbtf_mask_scale;
        vec2 i = floor(p), f = p - i;
        uvec2 x0 = dynbtf_add(mo.cell.xy, int(i.x)), y0 = dynbtf_add(mo.cell.zw, int(i.y));
        uvec2 x1 = dynbtf_add(x0, 1), y1 = dynbtf_add(y0, 1);
        uint s = dynbtf_mask_seed_state;
        float a = float(dynbtf_fold(dynbtf_fold(s, x0), y0)) * {_float(1.0 / MASK32)};
        float b = float(dynbtf_fold(dynbtf_fold(s, x1), y0)) * {_float(1.0 / MASK32)};
        float c = float(dynbtf_fold(dynbtf_fold(s, x0), y1)) * {_float(1.0 / MASK32)};
        float d = float(dynbtf_fold(dynbtf_fold(s, x1), y1)) * {_float(1.0 / MASK32)};
        vec2 t = f * f * (3.0 - 2.0 * f), dt = 6.0 * f * (1.0 - f) / dynbtf_mask_scale;
        float n = (a * (1.0 - t.x) + b * t.x) * (1.0 - t.y) + (c * (1.0 - t.x) + d * t.x) * t.y;
        vec2 g = vec2(((b - a) * (1.0 - t.y) + (d - c) * t.y) * dt.x, ((c - a) * (1.0 - t.x) + (d - b) * t.x) * dt.y);
        float k = dynbtf_mask_contrast;
        bool inside = abs(k * (n - 0.5)) < 0.5;   // where the clip is flat, so is the mask
        return vec3(clamp(0.5 + k * (n - 0.5), 0.0, 1.0), inside ? g * k : vec2(0.0));
    }}
    ivec2 size = textureSize(dynbtf_mask, 0);       // (W, H)
    float extent = dynbtf_mask_size;
    vec2 uv = mo.offset + mask_local;
    if (dynbtf_mask_repeat) uv = mod(uv, extent);
    vec2 p = uv / extent * vec2(size) - 0.5;
    vec2 p0 = floor(p), f = p - p0;
    ivec2 q = ivec2(p0);
    ivec2 c0, c1;
    if (dynbtf_mask_repeat) {{
        c0 = ivec2(dynbtf_mod(q.x, size.x), dynbtf_mod(q.y, size.y));
        c1 = ivec2(dynbtf_mod(q.x + 1, size.x), dynbtf_mod(q.y + 1, size.y));
    }} else {{
        c0 = clamp(q, ivec2(0), size - 1);
        c1 = clamp(q + 1, ivec2(0), size - 1);
    }}
    float a = texelFetch(dynbtf_mask, ivec2(c0.x, c0.y), 0).x, b = texelFetch(dynbtf_mask, ivec2(c1.x, c0.y), 0).x;
    float c = texelFetch(dynbtf_mask, ivec2(c0.x, c1.y), 0).x, d = texelFetch(dynbtf_mask, ivec2(c1.x, c1.y), 0).x;
    float value = (a * (1.0 - f.x) + b * f.x) * (1.0 - f.y) + (c * (1.0 - f.x) + d * f.x) * f.y;
    vec2 g = vec2(((b - a) * (1.0 - f.y) + (d - c) * f.y), ((c - a) * (1.0 - f.x) + (d - b) * f.x)) * vec2(size) / extent;
    return vec3(value, g);
}}

// signed distance (uv units) to the mask's 0.5 contour, positive on layer 1's side
float dynbtf_mask_distance(DynbtfMaskOrigin mo, vec2 mask_local) {{
    vec3 m = dynbtf_mask_value(mo, mask_local);
    float s = m.x - 0.5;
    return s == 0.0 ? 0.0 : s / max(length(m.yz), 1e-30);
}}

// one layer's pass: layer 0 -> (value, height); layer 1 -> (mix of previous.rgb and its value, its weight)
vec4 dynbtf_layer_pass(DynbtfOrigin o, vec2 local, DynbtfMaskOrigin mo, vec2 mask_local, vec3 w_view, vec3 w_light,
                       vec4 previous) {{
    float distance = dynbtf_mask_distance(mo, mask_local);
    bool band = abs(distance) < dynbtf_layer_width;
    bool own_side = dynbtf_layer_index == 1 ? distance > 0.0 : distance <= 0.0;
    if (!band && !own_side) return dynbtf_layer_index == 1 ? vec4(previous.rgb, 0.0) : vec4(0.0);
    vec4 x[DYNBTF_G];
#ifdef DYNBTF_RELIEF
    if (band) dynbtf_latent(o, local, 0, DYNBTF_G, x);   // for the height only: the colour marches on its own
#else
    dynbtf_latent(o, local, 0, DYNBTF_G, x);             // for the height and the colour
#endif
    float height = 0.0;
    if (band) {{   // the raw height's rank (dynbtf.layered.LayerHeight), read linearly from the table
        float raw = dynbtf_layer_height_offset;
        for (int g = 0; g < DYNBTF_G; ++g) raw += dot(x[g], dynbtf_layer_height_map[g]);
        vec2 range = dynbtf_layer_height_range;
        float pos = clamp((raw - range.x) * ({float(HEIGHT_TABLE - 1)} / (range.y - range.x)), 0.0, {float(HEIGHT_TABLE - 1)});
        int i = min(int(pos), {HEIGHT_TABLE - 2});
        float lo = dynbtf_layer_height_table[i / 4][i % 4], hi = dynbtf_layer_height_table[(i + 1) / 4][(i + 1) % 4];
        height = lo + (pos - float(i)) * (hi - lo);
    }}
    float weight = 1.0;
    if (dynbtf_layer_index == 1 && band) {{
        float score = height - previous.a + distance / dynbtf_layer_width;
        weight = {blend};
    }}
    vec3 value = vec3(0.0);
    if (weight > 0.0 && w_view.z >= 0.0 && w_light.z >= 0.0) {{
#ifdef DYNBTF_RELIEF
        value = dynbtf_eval(o, local, w_view, w_light);   // the colour where the view ray meets the relief
#else
        value = dynbtf_decode(x, w_view, w_light) * dynbtf_gain(o, local);   // the features the height was read from
#endif
    }}
    if (dynbtf_layer_index == 0) return vec4(value, height);
    return vec4(previous.rgb * (1.0 - weight) + value * weight, weight);
}}
"""


# ---------------------------------------------------------------- the export
def _mask_entry(mask, writer: _Writer) -> dict[str, Any]:
    """The mask's ``layered.json`` entry (an image's values written as ``mask.bin``)."""
    from ...layered import ImageMask, NoiseMask

    if isinstance(mask, ImageMask):
        image = np.ascontiguousarray(mask.image, dtype=np.float32)
        return {"kind": "image", "size": float(mask.size), "wrap": mask.wrap,
                "texture": {"file": writer.add("mask.bin", image), "format": "R32F", "height": int(image.shape[0]),
                            "width": int(image.shape[1])}}
    if isinstance(mask, NoiseMask):
        return {"kind": "noise", "scale": float(mask.scale), "contrast": float(mask.contrast), "seed": int(mask.seed),
                "seed_state": int(seed_state(int(mask.seed) & MASK32))}
    raise InputError(f"export: the shader evaluates an ImageMask or a NoiseMask, not a {type(mask).__name__}")


def _height_entry(btf, height) -> dict[str, Any]:
    """How the shader reads a layer's height from its latent values: the layer's :class:`~dynbtf.layered.LayerHeight`
    weights with the method's output map folded in (``features = latent @ M + o``), and its rank table."""
    matrix, offset = btf.synthesizer.output_map()
    weights = np.asarray(height.weights, dtype=np.float64)
    mapped = weights if matrix is None else matrix.double().cpu().numpy() @ weights
    shift = 0.0 if offset is None else float(offset.double().cpu().numpy() @ weights)
    return {"map": _pad4(mapped, 0.0), "offset": shift, "low": float(height.low), "high": float(height.high),
            "table": [float(v) for v in height.table]}


def export_layered_web(layered, out_dir, *, precision: str = "fp16", viewer: bool = True, span: float = 1.0
                       ) -> LayeredWebExport:
    """Export a :class:`~dynbtf.layered.LayeredBTF` for a GPU shader and the WebGL2 viewer (module docstring).

    Parameters
    ----------
    layered : LayeredBTF
        Two synthesized BTFs and an :class:`~dynbtf.layered.ImageMask` or :class:`~dynbtf.layered.NoiseMask`
        (another mask object is an :class:`~dynbtf.errors.InputError`); each layer is exported as compiled (its
        method, seed and tables), with its scale.
    out_dir : path
        Directory to write (created; files of an earlier export are replaced).
    precision : {"fp16", "u8", "fp32"}
        The layers' texture storage (:func:`~dynbtf.export.web.exporter.export_web`); the mask is float32.
    viewer : bool
        Also write the viewer page and the ``.js`` twins of the files.
    span : float
        The viewer's initial uv units across its meshes (each layer then shows ``span x scale`` repeats; at most
        :data:`~dynbtf.export.web.shader.LOCAL_REPEATS` for either layer).
    """
    from ...layered import LayeredBTF

    if not isinstance(layered, LayeredBTF):
        raise InputError(f"layered: expected a LayeredBTF, got {type(layered).__name__}")
    check_precision(precision)
    for k, btf in enumerate(layered.layers):
        check_scale(float(span) * btf.scale, f"span x scale of layer {k}", float32=True, limit=LOCAL_REPEATS,
                    where="the shader's float32 local uv")
    out_dir = _output_directory(out_dir)
    writer = _Writer(out_dir, scripts=viewer)
    mask = _mask_entry(layered.mask, writer)  # (refuses a mask the shader has no form of before anything is big)
    exports, entries = [], []
    for k, (btf, height) in enumerate(zip(layered.layers, layered.height_maps)):
        directory = f"layer{k}"
        method = btf.material.method
        export = _export_web(btf.material, out_dir / directory, precision=precision, methods=(method,), seed=btf.seed,
                             scale=btf.scale, scripts=viewer, page=False, method_params=None)
        exports.append(export)
        entries.append({"directory": directory + "/", "method": method, "scale": float(btf.scale),
                        "kind": export.manifest["kind"], "height": _height_entry(btf, height)})
    manifest = {
        "format": LAYERED_FORMAT, "version": LAYERED_VERSION, "layers": entries, "mask": mask,
        "width": float(layered.width), "softness": float(layered.softness), "span": float(span),
        "precision": precision, "lattice": lattice_constants(), "files": writer.files, "shader": "layered.glsl",
        "conventions": ("Layer 0 shows where the mask is below one half, layer 1 where it is above; within `width` "
                        "uv units of the contour the layer with the higher score h_1 - h_0 + d / width shows "
                        "(dynbtf.layered.LayeredBTF). uv in the surface's units; each layer's exemplar repeats are "
                        "uv x its scale. Values as in each layer's manifest: linear RGB, excluding cos(theta_light)."),
    }
    shader = layered_glsl(softness=layered.softness)
    with atomic_path(out_dir / "layered.glsl") as tmp:
        tmp.write_text(shader, encoding="utf-8")
    with atomic_path(out_dir / "layered.json") as tmp:
        tmp.write_text(json.dumps(manifest, indent=1), encoding="utf-8")
    if viewer:
        with atomic_path(out_dir / "layered.js") as tmp:
            tmp.write_text(f"DynBTF.layered({json.dumps(manifest)}, {json.dumps(shader)});\n", encoding="utf-8")
        write_viewer_page(out_dir, layered=True)
    return LayeredWebExport(out_dir, manifest, exports)
