"""Real-time export: a synthesized BTF as GPU textures, decoder weights and a GLSL ES 3.00 shader.

:func:`export_web` writes, into one directory, everything a renderer needs to evaluate
:class:`dynbtf.infinite_btf.SynthesizedBTF` per pixel on a GPU, plus a self-contained WebGL2
viewer page (``index.html``, no build step, no network):

* ``manifest.json`` -- what every file holds (formats, sizes, per-channel scale and bias, the
  synthesis parameters of every exported method, the decoder's layout, conventions).
* ``*.bin`` -- textures and weights, little-endian, tightly packed (the shared decoder weights are
  also constants in the shader; each method's layer 1 is a uniform block):
  the positional plane each method reads (the exemplar for ``tile`` and ``struct``, the tileable
  exemplar for ``linear``/``hex``, its Gaussianized PCA coefficients for ``hist``) as ``ceil(C / 4)``
  RGBA layers; the per-channel inverse transform tables of ``hist``; the luminance plane of ``hex``;
  the lattice offsets and cut tables of ``struct`` (one ``R16I`` integer texture, exact); the labels of the read
  plane (guided hist and hex) or the cells' majority labels per offset (guided struct, beside struct's tables) and
  of the target image (also one exact ``R16I`` texture; the target is laid over the plane as the entry's label
  ``field``, whose place the repeat origin carries); the
  angular planes ``f_H``, ``f_D`` (RGBA layers, rows = theta, columns = phi); and the decoder's
  weights (float32, already in std140 uniform-block order).
* ``dynbtf.glsl`` -- the shader functions (GLSL ES 3.00): the triangle lattice, the integer
  vertex hash (bit for bit :func:`dynbtf.synthesis.hash.hash_vertex`), the blends, the inverse
  tables, ``struct``'s cells and cuts, the Rusinkiewicz angular fetches, the relief march of
  ``triple-parallax`` models and the decoder (:mod:`dynbtf.export.web.shader`). A renderer calls
  ``dynbtf_eval(origin, local_uv, w_view, w_light)``.
* ``index.html``, ``viewer.js`` and ``*.js`` copies of the binary files (browsers do not let a
  page opened from disk read binary files; a ``<script>`` can be read).

Texture precision (``precision``): ``fp32`` (exact; for checking), ``fp16`` (half floats), or
``u8`` (8 bits per channel; each channel stores ``value = stored * scale + bias`` with
``stored`` in ``[0, 1]`` and its own scale and bias). Decoder weights stay float32 (a few KB).

Large uv
--------
A shader has 32-bit floats, which cannot hold ``uv = 1e6 + 0.3`` to a texel. The caller splits
``uv * scale`` (in float64, on the CPU) into an integer repeat index and a fraction; the
repeat index enters the shader as a :class:`~dynbtf.export.web.shader.RepeatOrigin`: the lattice's 64-bit integer
offset, its fractional phase ``2 sqrt(3) I_u mod 1`` and the texel offset of the repeat
(:func:`dynbtf.export.web.shader.repeat_origin`; ``viewer.js`` has the same function); for ``struct``
the 64-bit words hold the cell index of the repeat's first cell, ``I * cells`` (int64), instead
of the lattice vertex. The shader adds a local uv
(the fraction plus up to ``2**12`` further repeats, e.g. a mesh's uv times the scale) in
float32. Exact range: any ``|uv * scale| < 2**52`` repeats, the library's own limit; the
vertex hashes, cell hashes and texel choices are those of the library bit for bit at every
repeat index, and positions within a repeat have float32 resolution (``2**-24`` of the local uv's size).
"""

from __future__ import annotations

import base64
import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...errors import InputError
from ...io import atomic_path
from ...limits import check_scale
from ...synthesis.auto import AUTO
from ...synthesis.hash import MASK32, seed_state
from ...infinite_btf import SynthesizedBTF
from ...synthesized import synthesized_btf
from ...synthesis.registry import EXEMPLAR_METHOD, PAPER_METHOD
from ...synthesis.web_form import TABLE_KINDS, WebForm
from .shader import LOCAL_REPEATS, glsl_source, lattice_constants, web_methods

__all__ = ["export_web", "WebExport", "quantize", "dequantize", "quantized_model", "SUPPORTED_KINDS",
           "WEB_PRECISIONS", "FORMAT_VERSION", "DEFAULT_METHODS"]

#: Methods exported by default: the model's automatic choice (the viewer's default), and the paper's method and
#: plain tiling to compare.
DEFAULT_METHODS = (AUTO, PAPER_METHOD, EXEMPLAR_METHOD)

#: Model kinds the shader evaluates.
SUPPORTED_KINDS = ("triple", "triple-parallax")
#: Kinds refused, and why.
_REFUSED = {
    "pca": "it has no positional feature plane to synthesize (a per-texel PCA basis)",
    "sh": "it has no positional feature plane to synthesize (per-texel spherical-harmonics coefficients)",
    "neumip": "its neural offset texture and per-texel MLP inputs have no shader form",
}
#: Texture precisions: GL internal formats of RGBA and single-channel textures, bytes per value.
WEB_PRECISIONS = {"fp32": ("RGBA32F", "R32F", 4), "fp16": ("RGBA16F", "R16F", 2), "u8": ("RGBA8", "R8", 1)}
#: Version of the manifest's layout.
FORMAT_VERSION = 1
#: Largest uniform block WebGL2 guarantees (bytes).
_MAX_UNIFORM_BLOCK = 16384
#: Width of the texture rows that hold the inverse tables (WebGL2 guarantees 2048).
_LUT_ROW = 1024
_VIEWER_FILES = ("index.html", "viewer.js")


# ---------------------------------------------------------------- quantization
def quantize(values: np.ndarray, precision: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Store ``values (..., C)`` in ``precision``: ``(stored, scale (C,), bias (C,))``.

    ``values ~ stored * scale + bias`` per channel: ``fp32``/``fp16`` store the values
    (``scale = 1, bias = 0``); ``u8`` stores ``round((v - min) / (max - min) * 255)`` as uint8,
    read by the GPU as ``stored / 255`` (``scale = max - min``, ``bias = min``).
    """
    if precision not in WEB_PRECISIONS:
        raise InputError(f"precision: expected one of {sorted(WEB_PRECISIONS)}, got {precision!r}")
    values = np.asarray(values, dtype=np.float32)
    c = values.shape[-1]
    if precision == "fp32":
        return values.copy(), np.ones(c, np.float32), np.zeros(c, np.float32)
    if precision == "fp16":
        largest = float(np.abs(values).max()) if values.size else 0.0
        if not largest <= float(np.finfo(np.float16).max):
            raise InputError(f"precision fp16: values up to {largest:.4g} do not fit half floats (max 65504); "
                             "use --precision u8 or fp32")
        return values.astype(np.float16), np.ones(c, np.float32), np.zeros(c, np.float32)
    flat = values.reshape(-1, c).astype(np.float64)
    lo, hi = flat.min(0), flat.max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    stored = np.clip(np.rint((values - lo) / span * 255.0), 0, 255).astype(np.uint8)
    return stored, span.astype(np.float32), lo.astype(np.float32)


def dequantize(stored: np.ndarray, scale: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """What the GPU reads back from :func:`quantize`'s output, float32 (``u8``: ``stored / 255 * scale + bias``)."""
    x = stored.astype(np.float32) / np.float32(255.0) if stored.dtype == np.uint8 else stored.astype(np.float32)
    return (x * scale.astype(np.float32) + bias.astype(np.float32)).astype(np.float32)


def _round_trip(values: torch.Tensor, precision: str) -> torch.Tensor:
    return torch.from_numpy(dequantize(*quantize(values.detach().cpu().numpy(), precision)))


def quantized_model(model, precision: str):
    """A copy of a Triple Plane (or its relief variant) whose feature planes hold what an export of ``precision`` stores.

    The decoder is unchanged (exported as float32). Evaluating it (e.g. on held-out pairs)
    measures what the quantization of the planes costs.
    """
    import copy

    _check_kind(model)
    out = copy.deepcopy(model).cpu()
    with torch.no_grad():
        for name in ("f_u", "f_h", "f_d"):
            getattr(out, name).copy_(_round_trip(getattr(out, name), precision))
        if hasattr(out, "height_channel"):  # the plane's last channel (relief models), quantized on its own
            out.height_channel.copy_(_round_trip(out.height_channel[..., None], precision)[..., 0])
    return out


# ---------------------------------------------------------------- packing
def _layers_rgba(plane: np.ndarray) -> np.ndarray:
    """``(H, W, C)`` -> ``(ceil(C / 4), H, W, 4)`` (zero-padded channels): the RGBA layers of a texture array."""
    h, w, c = plane.shape
    g = (c + 3) // 4
    out = np.zeros((h, w, 4 * g), dtype=plane.dtype)
    out[..., :c] = plane
    return np.ascontiguousarray(out.reshape(h, w, g, 4).transpose(2, 0, 1, 3))


def _pad4(x: np.ndarray, fill: float) -> list[float]:
    n = (len(x) + 3) // 4 * 4
    return [float(v) for v in x] + [fill] * (n - len(x))


def _mat4_blocks(weight: np.ndarray) -> np.ndarray:
    """``(out, in)`` weights -> std140 ``mat4`` blocks ``[o * ceil(in / 4) + i]`` (column-major) as float32.

    Block ``(o, i)`` multiplies input group ``i`` into output group ``o``: ``y[o] += M * x[i]``.
    """
    n_out, n_in = weight.shape
    og, ig = (n_out + 3) // 4, (n_in + 3) // 4
    padded = np.zeros((4 * og, 4 * ig), dtype=np.float64)
    padded[:n_out, :n_in] = weight
    blocks = padded.reshape(og, 4, ig, 4).transpose(0, 2, 3, 1)  # [o, i, column c, row r] = W[4o + r, 4i + c]
    return np.ascontiguousarray(blocks, dtype=np.float32).reshape(-1)


def _vec4s(bias: np.ndarray) -> np.ndarray:
    return np.asarray(_pad4(np.asarray(bias, dtype=np.float64), 0.0), dtype=np.float32)


def _check_kind(model) -> str:
    """The model's kind if the shader evaluates it, else an :class:`InputError` saying why not."""
    from ...representations.parallax import ParallaxTriplePlane
    from ...representations.triple_plane import TriplePlane

    kind = getattr(model, "kind", None) or type(model).__name__
    if type(model) not in (TriplePlane, ParallaxTriplePlane):
        why = _REFUSED.get(kind, "the shader implements only the Triple Plane's decoder")
        raise InputError(f"export: model kind {kind!r} is not supported by the web export ({why}); "
                         f"supported kinds: {', '.join(SUPPORTED_KINDS)}")
    return kind


@dataclass
class WebExport:
    """What :func:`export_web` wrote.

    Attributes
    ----------
    directory : Path
    manifest : dict
        The content of ``manifest.json``.
    """

    directory: Path
    manifest: dict[str, Any]

    @property
    def index(self) -> Path:
        """The viewer page."""
        return self.directory / "index.html"

    def method_bytes(self, method: str) -> int:
        """Bytes of the binary files one method needs (its plane and tables, angular planes, decoder)."""
        files = set(self.manifest["methods"][method]["files"]) | set(self.manifest["shared_files"])
        return sum(self.manifest["files"][f]["bytes"] for f in files)

    def total_bytes(self) -> int:
        """Bytes of all binary files."""
        return sum(f["bytes"] for f in self.manifest["files"].values())


class _Writer:
    """Collects binary files (deduplicated by content) and writes them (with their ``.js`` twins for the viewer)."""

    def __init__(self, directory: Path, scripts: bool) -> None:
        self.directory = directory
        self.scripts = scripts
        self.files: dict[str, dict[str, Any]] = {}
        self._by_digest: dict[str, str] = {}

    def add(self, name: str, data: np.ndarray) -> str:
        raw = np.ascontiguousarray(data).tobytes()
        digest = hashlib.sha256(raw).hexdigest()
        if digest in self._by_digest:
            return self._by_digest[digest]
        self._by_digest[digest] = name
        self.files[name] = {"bytes": len(raw), "sha256": digest}
        with atomic_path(self.directory / name) as tmp:
            tmp.write_bytes(raw)
        if not self.scripts:
            return name
        payload = base64.b64encode(raw).decode("ascii")
        with atomic_path(self.directory / f"{name}.js") as tmp:
            tmp.write_text(f"DynBTF.file({json.dumps(name)}, {len(raw)}, \"{payload}\");\n", encoding="ascii")
        return name


def _texture(writer: _Writer, name: str, values: np.ndarray, precision: str, *, layered: bool) -> dict[str, Any]:
    """Quantize ``values`` (``(H, W, C)`` if ``layered`` else ``(H, W)``) and write it: its manifest entry."""
    rgba, single, _ = WEB_PRECISIONS[precision]
    if layered:
        stored, scale, bias = quantize(values, precision)
        c = values.shape[-1]
        data = _layers_rgba(stored)
        return {"file": writer.add(name, data), "format": rgba, "layers": int(data.shape[0]),
                "height": int(values.shape[0]), "width": int(values.shape[1]), "channels": int(c),
                "scale": _pad4(scale, 0.0), "bias": _pad4(bias, 0.0)}
    stored, scale, bias = quantize(values[..., None], precision)
    return {"file": writer.add(name, stored[..., 0]), "format": single, "height": int(values.shape[0]),
            "width": int(values.shape[1]), "scale": float(scale[0]), "bias": float(bias[0])}


def _lut_texture(writer: _Writer, name: str, table: np.ndarray, precision: str) -> dict[str, Any]:
    """Inverse tables ``(C, L)``: each channel quantized on its own, ``ceil(L / row)`` rows of ``row`` entries."""
    c, size = table.shape
    row = min(size, _LUT_ROW)
    rows = (size + row - 1) // row
    padded = np.zeros((c, rows * row), dtype=np.float32)
    padded[:, :size] = table
    padded[:, size:] = table[:, -1:]
    stored, scale, bias = quantize(padded.T, precision)  # (entries, C): per-channel scale/bias
    data = np.ascontiguousarray(stored.T.reshape(c * rows, row))
    return {"file": writer.add(name, data), "format": WEB_PRECISIONS[precision][1], "height": int(c * rows),
            "width": int(row), "size": int(size), "row": int(row), "scale": _pad4(scale, 0.0), "bias": _pad4(bias, 0.0)}


def _int16_texture(writer: _Writer, name: str, parts: dict[str, np.ndarray]) -> dict[str, Any]:
    """Named integer arrays flattened (C order) one after the other into one ``R16I`` texture, ``row`` entries per
    texture row: exact, so every value must fit int16 (an :class:`InputError` names the array that does not)."""
    for key, values in parts.items():
        if values.size and int(np.abs(values).max()) > np.iinfo(np.int16).max:
            raise InputError(f"export: table {key} holds {int(np.abs(values).max())}, beyond int16 (e.g. offsets of "
                             "an exemplar wider than 32767 texels)")
    flat = np.concatenate([np.asarray(v).astype(np.int16).reshape(-1) for v in parts.values()])
    row = min(len(flat), _LUT_ROW)
    rows = (len(flat) + row - 1) // row
    data = np.zeros(rows * row, np.int16)
    data[:len(flat)] = flat
    entry: dict[str, Any] = {"file": writer.add(name, data.reshape(rows, row)), "format": "R16I", "height": int(rows),
                             "width": int(row), "row": int(row)}
    start = 0
    for key, values in parts.items():
        entry[key] = {"start": start, "shape": [int(d) for d in values.shape]}
        start += int(values.size)
    return entry


def _table_entry(writer: _Writer, name: str, table, precision: str) -> dict[str, Any]:
    """One of a method's tables (:class:`~dynbtf.synthesis.web_form.WebTable`) written by its kind."""
    if table.kind == "single":
        return _texture(writer, name, np.asarray(table.values, dtype=np.float32), precision, layered=False)
    if table.kind == "lut":
        return _lut_texture(writer, name, np.asarray(table.values, dtype=np.float32), precision)
    if table.kind == "int16":
        return _int16_texture(writer, name, table.values)
    raise InputError(f"export: table {name!r} of kind {table.kind!r}; expected one of {TABLE_KINDS}")


def export_web(model, out_dir, *, precision: str = "fp16", methods=DEFAULT_METHODS, seed: int = 0,
               scale: float = 8.0, viewer: bool = True, method_params: dict[str, dict[str, Any]] | None = None
               ) -> WebExport:
    """Export a Triple Plane model for real-time evaluation in a GLSL ES 3.00 shader (and a WebGL2 viewer).

    Parameters
    ----------
    model : Representation, CompiledMaterial, str or Path
        A fitted Triple Plane (kind ``triple``, or ``triple-parallax``: the shader then marches
        the synthesized height field), its model file, or a compiled material (object or ``.dbtfc``
        file: its method, exported from its tables and seed, stands for itself and for ``auto``; other
        methods are built from its model). Other kinds raise :class:`~dynbtf.errors.InputError` naming
        the supported ones.
    out_dir : path
        Directory to write (created; files of an earlier export are replaced).
    precision : {"fp16", "u8", "fp32"}
        Storage of the textures (see the module docstring).
    methods : sequence of {"auto"} or the methods with a web form (:func:`~dynbtf.export.web.shader.web_methods`)
        Synthesis methods to export (each with its own plane and tables); the first is the
        viewer's default. A method that needs parameters besides the exemplar (the guided methods: labels and a
        target) takes them from ``method_params``, or is exported as the compiled material built with them
        (``model``). ``auto`` is the model's choice (``synthesized_btf(model, "auto")``:
        ``struct`` for a structured positional plane, else ``hist``), exported under the chosen
        method's name; the manifest's ``auto`` entry names it and holds the choice's line. A method
        named twice (or chosen by ``auto`` and also listed) is exported once, where it first appears.
    seed : int
        Synthesis seed (the same choices as ``synthesized_btf(model, method, seed=seed)``).
    scale : float
        The viewer's initial exemplar repeats per unit of the surface's uv: positive and below
        :data:`~dynbtf.export.web.shader.LOCAL_REPEATS` (``2**12``, what the shader's float32 local
        uv spans; else :class:`~dynbtf.errors.InputError`, before anything is written).
    viewer : bool
        Also write ``index.html``, ``viewer.js`` and the ``.js`` twins of the binary files.
    method_params : dict, optional
        Per-method synthesizer parameters (e.g. ``{"hist": {"gamma": 3.0}}``; ``"auto"``'s go to the
        method it chooses).

    Returns
    -------
    WebExport
    """
    return _export_web(model, out_dir, precision=precision, methods=methods, seed=seed, scale=scale, scripts=viewer,
                       page=viewer, method_params=method_params)


def _export_web(model, out_dir, *, precision: str, methods, seed: int, scale: float, scripts: bool, page: bool,
                method_params: dict[str, dict[str, Any]] | None) -> WebExport:
    """:func:`export_web`; ``scripts``: write the ``.js`` twins of the files (what a page loads), ``page``: the
    viewer page itself (a layered export's layers have the twins without a page of their own)."""
    # the viewer's meshes have uv in [0, 1]: uv x scale is the shader's float32 local uv
    scale = check_scale(scale, "scale", float32=True, limit=LOCAL_REPEATS, where="the shader's float32 local uv")
    model, source, material = _resolve_model(model)
    kind = _check_kind(model)
    methods = _check_options(precision, methods)
    method_params = dict(method_params or {})
    model = model.cpu().eval()
    out_dir = _output_directory(out_dir)
    writer = _Writer(out_dir, scripts=scripts)
    layout = _DecoderLayout.of(model, kind)
    with torch.no_grad():
        angular = {"f_H": _texture(writer, "f_H.bin", model.f_h.detach().numpy(), precision, layered=True),
                   "f_D": _texture(writer, "f_D.bin", model.f_d.detach().numpy(), precision, layered=True)}
    decoder_file, decoder_entries = _write_shared_decoder(writer, layout)
    method_entries, auto = _export_methods(writer, model, layout, methods, method_params, seed, precision, material)
    shader = glsl_source(channels=layout.c_u, angular_channels=layout.c_a, hidden=layout.hidden, layers=layout.layers,
                         negative_slope=layout.negative_slope, angular_resolution=layout.res,
                         angular_weights=layout.angular_blocks, rest_weights=layout.rest_weights, relief=layout.relief)
    with atomic_path(out_dir / "dynbtf.glsl") as tmp:
        tmp.write_text(shader, encoding="utf-8")
    manifest = _manifest(kind, source, precision, scale, layout, angular, decoder_file, decoder_entries,
                         method_entries, auto, writer.files)
    _write_manifest_and_viewer(out_dir, manifest, shader, scripts=scripts, page=page)
    return WebExport(out_dir, manifest)


def _resolve_model(model):
    """``(model, source path or None, compiled material or None)``: a model file or a compiled material file is
    read, a model or a material passes through."""
    from ...material import CompiledMaterial, open_model_file

    if isinstance(model, CompiledMaterial):
        return model.model, None, model
    if isinstance(model, (str, bytes)) or hasattr(model, "__fspath__"):
        representation, material = open_model_file(model)
        return representation, Path(model), material
    return model, None, None


def _check_options(precision: str, methods) -> list[str]:
    """Check ``precision`` and ``methods`` (an :class:`InputError` naming the accepted ones); the methods as a list."""
    check_precision(precision)
    methods = [methods] if isinstance(methods, str) else list(methods)
    accepted = [AUTO, *web_methods()]
    if not methods:
        raise InputError(f"methods: expected at least one of {accepted}")
    for m in methods:
        if m not in accepted:
            raise InputError(f"method: {m!r} has no shader form; expected one of {accepted}")
    return methods


def check_precision(precision: str) -> None:
    """An :class:`InputError` naming the texture precisions unless ``precision`` is one of them."""
    if precision not in WEB_PRECISIONS:
        raise InputError(f"precision: expected one of {sorted(WEB_PRECISIONS)} (fp16: half floats, u8: 8 bits per "
                         f"channel with per-channel scale and bias, fp32: exact), got {precision!r}")


def _output_directory(out_dir) -> Path:
    """``out_dir`` as a created directory (an existing file there is an :class:`InputError`)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"-o/--output: {out_dir} exists and is not a directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    return out_dir


@dataclass
class _DecoderLayout:
    """The model's decoder as the shader sees it: sizes, relief parameters and the weights every method shares."""

    cfg: dict[str, Any]
    hidden: int
    layers: int
    c_u: int  # positional channels as the decoder reads them (a relief model's plane adds its height channel)
    c_a: int
    res: int
    negative_slope: float
    relief: dict[str, Any] | None
    angular_blocks: np.ndarray  # layer 1's angular part (mat4 blocks)
    rest_weights: list[tuple[np.ndarray, np.ndarray]]  # layers 2..: (mat4 blocks, vec4 biases)

    @classmethod
    def of(cls, model, kind: str) -> "_DecoderLayout":
        cfg = model.config()
        decoder = model.decoder
        hidden, layers = int(cfg["hidden"]), int(cfg["layers"])
        c_u, c_a, res = int(decoder.positional_channels), int(cfg["angular_channels"]), int(cfg["angular_resolution"])
        relief = None
        if kind == "triple-parallax":
            h_min, h_max = model.height_range()
            relief = {"h_min": h_min, "h_max": h_max, **model.march_parameters(), "height_scale": model.height_scale}
        ag = (c_a + 3) // 4
        w_ang = decoder.first.weight.detach().double().numpy()[:, c_u:]
        # the angular part of layer 1: f_H's channels then f_D's, each padded to whole vec4 groups
        w_ang_padded = np.zeros((hidden, 8 * ag))
        w_ang_padded[:, :c_a] = w_ang[:, :c_a]
        w_ang_padded[:, 4 * ag:4 * ag + c_a] = w_ang[:, c_a:]
        rest_weights = [(_mat4_blocks(layer.weight.detach().double().numpy()),
                         _vec4s(layer.bias.detach().double().numpy())) for layer in decoder.rest]
        return cls(cfg, hidden, layers, c_u, c_a, res, float(decoder.negative_slope), relief,
                   _mat4_blocks(w_ang_padded), rest_weights)


def _write_shared_decoder(writer: _Writer, layout: _DecoderLayout) -> tuple[str, dict[str, Any]]:
    """Write ``decoder.bin`` (the weights every method shares: constants in the shader, and one float32 file in
    std140 order for engines that prefer uniforms); check that layer 1's uniform block fits WebGL2.

    Returns the file's name and its parts (offset and size of each, in floats).
    """
    parts = [("angular", layout.angular_blocks)]
    parts += [(f"w{k}", w) for k, (w, _) in enumerate(layout.rest_weights, start=2)]
    parts += [(f"b{k}", b) for k, (_, b) in enumerate(layout.rest_weights, start=2)]
    decoder_entries, offset = {}, 0
    for name, values in parts:
        decoder_entries[name] = {"offset": offset, "floats": int(values.size)}
        offset += int(values.size)
    decoder_file = writer.add("decoder.bin", np.concatenate([v for _, v in parts]))
    g, hg = (layout.c_u + 3) // 4, (layout.hidden + 3) // 4
    layer1_floats = 16 * hg * g + 4 * hg
    if layer1_floats * 4 > _MAX_UNIFORM_BLOCK:
        raise InputError(f"export: decoder block DynbtfLayer1 needs {layer1_floats * 4} bytes, more than the "
                         f"{_MAX_UNIFORM_BLOCK} bytes WebGL2 guarantees per uniform block (hidden = {layout.hidden}, "
                         f"{layout.c_u} positional channels); export a model with a smaller decoder")
    return decoder_file, decoder_entries


def _export_methods(writer: _Writer, model, layout: _DecoderLayout, methods: list[str],
                    method_params: dict[str, dict[str, Any]], seed: int, precision: str, material=None
                    ) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """Each method's plane, tables and folded layer 1: ``(method entries, the auto choice or None)``.

    ``auto`` is exported under the chosen method's name; a method already exported is skipped. With a
    compiled ``material``, its method (and ``auto``) is the material itself, with its seed.
    """
    method_entries: dict[str, Any] = {}
    auto = None
    for requested in methods:
        params = dict(method_params.get(requested, {}))
        if material is not None and requested in (AUTO, material.method):
            btf = SynthesizedBTF(material)  # as compiled: its tables, its seed
            choice = btf.synthesizer.choice
            if requested == AUTO and choice is not None:
                auto = {"method": choice.method, "line": choice.line, "structure_strength": choice.strength}
            m = material.method
        elif requested == AUTO:  # the model's choice, under the chosen method's name
            btf = synthesized_btf(model, AUTO, seed=seed, **params)
            choice = btf.synthesizer.choice
            auto = {"method": choice.method, "line": choice.line, "structure_strength": choice.strength}
            m = choice.method
        else:
            m = requested
            if m in method_entries:
                continue
            btf = synthesized_btf(model, m, seed=seed, **params)
        if m in method_entries:  # auto chose a method exported before it
            continue
        method_entries[m] = _method_entry(writer, m, btf, btf.seed, precision, layout)
    return method_entries, auto


def _method_entry(writer: _Writer, m: str, btf: SynthesizedBTF, seed: int, precision: str,
                  layout: _DecoderLayout) -> dict[str, Any]:
    """Write one method's files (plane, its tables, layer 1 with its output map folded in): its manifest entry.

    What the method's shader branch reads comes from its ``web`` module (:mod:`dynbtf.synthesis.web_form`)."""
    synth = btf.synthesizer
    form: WebForm = synth.backend_form("web")  # (a method without a web form: a one-line error here)
    web = synth.backend_module("web")
    files = []
    entry: dict[str, Any] = {"mode": web.MODE, "density": [int(synth.exemplar.shape[1]), int(synth.exemplar.shape[0])],
                             "seed": int(seed), "seed_state": int(seed_state(int(seed) & MASK32)),
                             "parameters": synth.parameters()}
    entry["plane"] = _texture(writer, f"plane_{m}.bin", np.asarray(form.plane, dtype=np.float32), precision,
                              layered=True)
    files.append(entry["plane"]["file"])
    for name, table in form.tables.items():
        entry[name] = _table_entry(writer, f"{name}_{m}.bin", table, precision)
        files.append(entry[name]["file"])
    entry.update(form.constants)
    matrix, out_offset = synth.output_map()
    # layer 1 with the method's output map folded in, as the compiled material holds it (FoldedDecoder.fold)
    folded = btf.material.decoder
    w_fold = folded.levels[0].weight.T.double().cpu().numpy()                 # (hidden, C)
    b_fold = (folded.levels[0].bias + folded.first_bias).double().cpu().numpy()
    block = np.concatenate([_mat4_blocks(w_fold), _vec4s(b_fold)])
    c_u = layout.c_u
    m_mat = np.eye(c_u) if matrix is None else matrix.double().cpu().numpy()   # features = latent @ M + o
    m_off = np.zeros(c_u) if out_offset is None else out_offset.double().cpu().numpy()
    entry["layer1"] = {"file": writer.add(f"layer1_{m}.bin", block), "floats": int(block.size)}
    if layout.relief is not None:  # the height channel (the plane's last) in terms of the latent
        entry["height"] = {"map": _pad4(m_mat[:, -1], 0.0), "offset": float(m_off[-1])}
    files.append(entry["layer1"]["file"])
    entry["files"] = files
    return entry


def _manifest(kind: str, source: Path | None, precision: str, scale: float, layout: _DecoderLayout,
              angular: dict[str, Any], decoder_file: str, decoder_entries: dict[str, Any],
              method_entries: dict[str, Any], auto: dict[str, Any] | None, files: dict[str, Any]) -> dict[str, Any]:
    """The content of ``manifest.json``."""
    return {
        "format": "dynbtf-web", "version": FORMAT_VERSION, "kind": kind, "config": layout.cfg,
        "source": None if source is None else source.name, "precision": precision,
        "channels": layout.c_u, "relief": layout.relief, "angular_channels": layout.c_a,
        "angular_resolution": layout.res, "hidden": layout.hidden,
        "layers": layout.layers, "negative_slope": layout.negative_slope, "scale": float(scale),
        "default_method": next(iter(method_entries)), "auto": auto, "lattice": lattice_constants(),
        "angular": angular,
        "decoder": {"file": decoder_file, "parts": decoder_entries,
                    "note": "layer 1's angular part (mat4 blocks) and layers 2.. (mat4 blocks, then each layer's "
                            "vec4 biases), also constants in dynbtf.glsl"},
        "methods": method_entries, "shared_files": sorted({angular["f_H"]["file"], angular["f_D"]["file"],
                                                           decoder_file}),
        "files": files, "shader": "dynbtf.glsl",
        "conventions": ("directions: unit vectors in the local frame (x along +u, y along +v, z = normal), w_view "
                        "towards the camera, w_light towards the light; (theta, phi) in degrees: theta from the "
                        "normal, phi from +u towards +v. Values: linear RGB, excluding cos(theta_light) (pi f_r). "
                        "uv: exemplar repeats = surface uv x scale; exact for |uv x scale| < 2**52 (split on the "
                        "CPU into a repeat origin and a local uv of at most 2**12 repeats; for a method with "
                        "cells the origin words are the int64 cell index of the repeat's first cell, I x cells)."),
    }


def _write_manifest_and_viewer(out_dir: Path, manifest: dict[str, Any], shader: str, *, scripts: bool,
                               page: bool) -> None:
    """Write ``manifest.json`` and, with ``scripts``, ``manifest.js``; with ``page``, the viewer page."""
    with atomic_path(out_dir / "manifest.json") as tmp:
        tmp.write_text(json.dumps(manifest, indent=1), encoding="utf-8")
    if scripts:
        with atomic_path(out_dir / "manifest.js") as tmp:
            tmp.write_text(f"DynBTF.manifest({json.dumps(manifest)}, {json.dumps(shader)});\n", encoding="utf-8")
    if page:
        write_viewer_page(out_dir)


def write_viewer_page(out_dir: Path, *, layered: bool = False) -> None:
    """Write the viewer's page and script (``index.html``, ``viewer.js``) into ``out_dir``; ``layered``: the page
    opens a layered export (``layered.js``, :mod:`dynbtf.export.web.layered`) instead of ``manifest.js``."""
    here = Path(__file__).parent / "assets"
    for name in _VIEWER_FILES:
        with atomic_path(out_dir / name) as tmp:
            if name == "index.html" and layered:
                page = (here / name).read_text(encoding="utf-8")
                tmp.write_text(page.replace("data-viewer>", 'data-viewer="layered">'), encoding="utf-8")
            else:
                shutil.copyfile(here / name, tmp)
