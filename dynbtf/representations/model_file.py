"""Model files (``.dbtfm``): a fitted representation as data, never as pickled code.

Format, version 1
-----------------
A model file is a `safetensors <https://github.com/huggingface/safetensors>`_ file:

* **tensors** -- the representation's ``state_dict()`` (parameters and buffers)
  under their module names, little-endian, in their own dtype (float32 for a
  Triple Plane: ``f_u (H, W, 16)``, ``f_h (20, 20, 8)``, ``f_d (20, 20, 8)``,
  ``decoder.first.weight (32, 32)``, ``decoder.first.bias``, ``decoder.rest.K.weight``, ...);
* **metadata** -- the safetensors header's string map holds one key,
  ``"dynbtf"``, whose value is a JSON object:

  ``format``           ``"dynbtf-model"``
  ``format_version``   integer; readers refuse versions newer than they know
  ``kind``             representation name in the registry (``"triple"``, ...)
  ``config``           constructor arguments: ``REPRESENTATIONS[kind](**config)``
                       rebuilds the module before the tensors are loaded
  ``conventions``      the value/direction conventions the tensors assume
                       (:data:`CONVENTIONS`)
  ``tensor_sha256``    SHA-256 of the tensors in sorted-name order (name, dtype,
                       shape, bytes): detects damaged data
  ``provenance``       free-form JSON: source name, shape, directions and content
                       fingerprint (checked by ``dynbtf eval``), seed, epochs,
                       training time, held-out (view, light) pairs, metrics, ...

Loading a file that is missing, truncated, corrupt, of another format, of a
newer version or of an unknown kind raises :class:`dynbtf.errors.FormatError`
with the path and the problem. Files are written atomically.

Loading an untrusted file
-------------------------
A model file is what people share, so :func:`load_model` trusts nothing in it and
allocates nothing before it has checked, in this order:

1. the metadata's fields and JSON types (``kind`` a registered name, ``config`` an
   object with exactly the constructor's arguments);
2. every ``config`` value's type and range, by building the module on PyTorch's
   ``meta`` device (shapes without memory; each constructor checks its arguments,
   :func:`dynbtf.representations.base.config_int`);
3. the tensor names, shapes and dtypes of the safetensors **header** against that
   module (so a config can never make the loader allocate more than the file holds);

then reads the tensors, checks the checksum, that every value is finite and below
:data:`MAX_ABS_PARAMETER`, and decodes :data:`CHECK_QUERIES` fixed queries: a model
answering a non-finite value or one beyond ``max_output`` (:data:`MAX_ABS_OUTPUT`) is refused,
naming its largest tensor.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import FormatError
from ..io import atomic_path
from .base import Representation
from .registry import get_representation_class

__all__ = ["save_model", "load_model", "read_model_metadata", "model_size_report", "FORMAT_NAME",
           "FORMAT_VERSION", "CONVENTIONS", "MAX_ABS_PARAMETER", "MAX_ABS_OUTPUT", "CHECK_QUERIES"]

FORMAT_NAME = "dynbtf-model"
FORMAT_VERSION = 1

#: Largest magnitude a stored parameter may have. Trained planes and decoders stay within ~1e2, a PCA's
#: singular values within ~1e7 for a full-size UBO2014 BTF; beyond this a file is damaged (e.g. flipped
#: exponent bits) or hand-made.
MAX_ABS_PARAMETER = 1e8
#: Default of ``load_model(max_output=...)``: the largest |value| (reflectance ``pi f_r``, linear RGB) a
#: loaded model may answer to :data:`CHECK_QUERIES` queries. Measured materials stay below ~1e2; a
#: model fitted to data brighter than this (``dynbtf fit --max-reflectance``) is loaded with a larger one.
MAX_ABS_OUTPUT = 1e4
#: Queries (fixed uv and directions) a loaded model is decoded at to check its answers.
CHECK_QUERIES = 64

#: What every model file's tensors assume (see :mod:`dynbtf.conventions`).
CONVENTIONS = {
    "directions": "unit vectors in the local frame (x=+u, y=+v, z=normal), w_view and w_light point away",
    "values": "linear RGB, pi * f_r, excluding cos(theta_light)",
    "uv": "units of one exemplar repeat; texel [i, j] centre at ((j + 0.5) / W, (i + 0.5) / H)",
    "angular_planes": "rows theta/90deg (clamped), columns phi/360deg (wrapped), Rusinkiewicz h and d",
}


def tensor_digest(tensors: dict[str, torch.Tensor]) -> str:
    """SHA-256 of tensors' names, dtypes, shapes and bytes: a model file's (and a compiled material's)
    ``tensor_sha256``."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        digest.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        digest.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return digest.hexdigest()


def read_checked_tensors(path: Path, expected_sha256) -> dict[str, torch.Tensor]:
    """Every tensor of safetensors file ``path``, checked against its header's ``tensor_sha256``:
    :class:`FormatError` for damaged or truncated data or a checksum mismatch."""
    from safetensors.torch import load_file

    try:
        tensors = load_file(str(path))
    except Exception as e:
        raise FormatError(path, f"damaged or truncated tensor data ({e})") from None
    if expected_sha256 != tensor_digest(tensors):
        raise FormatError(path, "tensor data does not match its checksum: the file is damaged")
    return tensors


def save_model(path, representation: Representation, provenance: dict[str, Any] | None = None) -> Path:
    """Write ``representation`` and JSON-serializable ``provenance`` to ``path`` atomically.

    Returns the path written.
    """
    from safetensors.torch import save_file

    path = Path(path)
    tensors = {k: v.detach().cpu().contiguous() for k, v in representation.state_dict().items()}
    header = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "kind": representation.kind,
        "config": representation.config(),
        "conventions": CONVENTIONS,
        "tensor_sha256": tensor_digest(tensors),
        "provenance": _to_jsonable(provenance or {}),
    }
    try:
        text = json.dumps(header, allow_nan=True)
    except TypeError as e:
        raise FormatError(path, f"metadata is not JSON-serializable ({e})") from None
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={"dynbtf": text})
    return path


def _btf_format(path: Path) -> str | None:
    """The BTF format of ``path`` if it is a BTF (stored, UBO2014, UBO2003), else None."""
    from ..data.open import sniff_format

    try:
        return sniff_format(path)
    except FormatError:
        return None


def read_model_metadata(path) -> dict[str, Any]:
    """The JSON metadata of a model file, validated (format name, version), without loading tensors."""
    from safetensors import safe_open

    path = Path(path)
    if not path.exists():
        raise FormatError(path, "model file not found")
    btf_format = _btf_format(path)
    if btf_format is not None:
        raise FormatError(path, f"is a BTF ({btf_format}), not a model file (.dbtfm); fit a model to it first: "
                                f"dynbtf fit {path} -o model.dbtfm")
    if path.is_dir():
        raise FormatError(path, "is a directory, not a model file (.dbtfm)")
    try:
        with safe_open(str(path), framework="pt") as f:
            raw = (f.metadata() or {}).get("dynbtf")
    except Exception as e:  # safetensors raises its own SafetensorError / OSError variants
        raise FormatError(path, f"not a readable dynbtf model file (safetensors header: {e})") from None
    if raw is None:
        raise FormatError(path, "safetensors file without dynbtf metadata: not a dynbtf model file")
    try:
        meta = json.loads(raw)
    except (json.JSONDecodeError, RecursionError) as e:  # RecursionError: nested deeper than Python's stack
        raise FormatError(path, f"damaged metadata (invalid JSON: {str(e)[:200]})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise FormatError(path, f"metadata field 'format' is {meta.get('format') if isinstance(meta, dict) else None!r}, "
                                f"expected {FORMAT_NAME!r}")
    version = meta.get("format_version")
    if not isinstance(version, int):
        raise FormatError(path, f"metadata field 'format_version' must be an integer, got {version!r}")
    if version > FORMAT_VERSION:
        raise FormatError(path, f"format version {version} is newer than this dynbtf supports "
                                f"({FORMAT_VERSION}); upgrade dynbtf to read it")
    for field, kind, expected in (("kind", str, "a string (a representation name)"),
                                  ("config", dict, "a JSON object (the constructor's arguments)")):
        if field not in meta:
            raise FormatError(path, f"metadata lacks the field {field!r}")
        if not isinstance(meta[field], kind):
            raise FormatError(path, f"metadata field {field!r} must be {expected}, got {_short(meta[field])}")
    for field, kind, expected in (("tensor_sha256", str, "a hex string"), ("provenance", dict, "a JSON object")):
        if field in meta and not isinstance(meta[field], kind):
            raise FormatError(path, f"metadata field {field!r} must be {expected}, got {_short(meta[field])}")
    return meta


def _short(value, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters (a hand-made file may hold anything)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _tensor_header(path: Path) -> dict[str, tuple[tuple[int, ...], str]]:
    """``{name: (shape, dtype)}`` of the tensors a safetensors file declares, from its header only.

    safetensors validates the header (its size, every tensor's offsets against the file's length) without
    reading the data; dtypes are its names (``"F32"``, ...).
    """
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            return {name: (tuple(f.get_slice(name).get_shape()), str(f.get_slice(name).get_dtype()))
                    for name in f.keys()}
    except Exception as e:  # SafetensorError, OSError
        raise FormatError(path, f"damaged or truncated tensor data ({e})") from None


#: torch dtype -> safetensors dtype name.
_SAFETENSORS_DTYPES = {torch.float32: "F32", torch.float16: "F16", torch.bfloat16: "BF16", torch.float64: "F64",
                       torch.int64: "I64", torch.int32: "I32", torch.uint8: "U8", torch.bool: "BOOL"}


def _architecture(path: Path, meta: dict[str, Any]) -> Representation:
    """The module ``meta`` describes, built on the ``meta`` device (no memory): :class:`FormatError` naming the
    file and the config field that is missing, unknown, of the wrong type or out of range."""
    from ..errors import InputError

    kind, config = meta["kind"], meta["config"]
    try:
        cls = get_representation_class(kind)
    except InputError as e:
        raise FormatError(path, str(e)) from None
    parameters = list(inspect.signature(cls.__init__).parameters.values())[1:]
    names = {p.name for p in parameters}
    unknown = sorted(set(config) - names)
    if unknown:
        raise FormatError(path, f"metadata 'config' field {unknown[0]!r} is not an argument of a {kind!r} model "
                                f"(expected some of {sorted(names)}): the config does not describe a {kind!r} model")
    missing = [p.name for p in parameters if p.default is inspect.Parameter.empty and p.name not in config]
    if missing:
        raise FormatError(path, f"metadata 'config' lacks the field {missing[0]!r} of a {kind!r} model")
    try:
        with torch.device("meta"):
            return cls(**config)
    except InputError as e:
        raise FormatError(path, f"metadata 'config' does not describe a valid {kind!r} model: {e}") from None


def _check_header(path: Path, kind: str, expected: dict[str, torch.Tensor],
                  found: dict[str, tuple[tuple[int, ...], str]]) -> None:
    """:class:`FormatError` naming the first tensor that is missing, extra, or of another shape or dtype than
    the config's module ``expected`` (on the meta device) needs."""
    missing = [name for name in expected if name not in found]
    if missing:
        raise FormatError(path, f"tensor {missing[0]!r} of the {kind!r} model is missing"
                                + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    extra = [name for name in found if name not in expected]
    if extra:
        raise FormatError(path, f"tensor {extra[0]!r} is not part of a {kind!r} model")
    for name, want in expected.items():
        shape, dtype = found[name]
        if shape != tuple(want.shape):
            raise FormatError(path, f"tensor {name!r} has shape {shape}; the model's config needs "
                                    f"{tuple(want.shape)}")
        want_dtype = _SAFETENSORS_DTYPES.get(want.dtype, str(want.dtype))
        if dtype != want_dtype:
            raise FormatError(path, f"tensor {name!r} has dtype {dtype}; the model needs {want_dtype}")


def _check_values(path: Path, tensors: dict[str, torch.Tensor]) -> None:
    """:class:`FormatError` naming the first tensor holding a non-finite value or one beyond
    :data:`MAX_ABS_PARAMETER`."""
    for name in sorted(tensors):
        t = tensors[name]
        if not t.is_floating_point() or t.numel() == 0:
            continue
        finite = torch.isfinite(t)
        if not bool(finite.all()):
            bad = int((~finite).sum())
            raise FormatError(path, f"tensor {name!r} holds {bad} non-finite value(s) (NaN or Inf): the model is "
                                    "damaged; refit it")
        largest = float(t.abs().max())
        if largest > MAX_ABS_PARAMETER:
            raise FormatError(path, f"tensor {name!r} holds a value of magnitude {largest:.3g}, beyond any fitted "
                                    f"model (at most {MAX_ABS_PARAMETER:.0e}): the model is damaged; refit it")


def _check_state(path: Path, rep: Representation) -> None:
    """:class:`FormatError` where the representation says its parameters cannot be answered in bounded time
    (:meth:`~dynbtf.representations.base.Representation.state_problem`, e.g. a relief marched over millions of
    steps): checked before the test queries, which would otherwise not return."""
    problem = rep.state_problem()
    if problem is not None:
        raise FormatError(path, f"{problem}: the model is damaged; refit it")


def _check_outputs(path: Path, rep: Representation, max_output: float) -> None:
    """Decode :data:`CHECK_QUERIES` fixed queries; :class:`FormatError` if an answer is non-finite or beyond
    ``max_output``, naming the tensor of largest magnitude (the likeliest culprit)."""
    generator = torch.Generator().manual_seed(0)
    n = CHECK_QUERIES
    uv = torch.rand(n, 2, generator=generator, dtype=torch.float64)
    theta = torch.rand(2, n, generator=generator) * math.radians(80.0)
    phi = torch.rand(2, n, generator=generator) * (2 * math.pi)
    w = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()], dim=-1)  # (2, n, 3) unit
    device = rep.device
    with torch.no_grad():
        rgb = rep(uv.to(device), w[0].to(device), w[1].to(device)).double().cpu()
    worst = float(rgb.abs().max()) if bool(torch.isfinite(rgb).all()) else math.inf
    if worst <= max_output:
        return
    name, tensor = max(((k, v) for k, v in rep.state_dict().items() if v.is_floating_point() and v.numel()),
                       key=lambda item: float(item[1].abs().max()), default=("?", torch.zeros(1)))
    answer = "non-finite values" if math.isinf(worst) else f"values up to {worst:.3g}"
    raise FormatError(path, f"the model answers {answer} on {n} test queries (a reflectance model stays below "
                            f"{max_output:g}); its largest tensor is {name!r} (|value| up to "
                            f"{float(tensor.abs().max()):.3g}): the model is damaged; refit it")


def load_model(path, device=None, *,
               max_output: float = MAX_ABS_OUTPUT) -> tuple[Representation, dict[str, Any]]:
    """Load a model file: ``(representation, metadata)``, checked before anything is allocated (module docs).

    Parameters
    ----------
    path : str or Path
    device : str or torch.device, optional
        Where to put the representation (default: the CPU).
    max_output : float
        Largest |value| the model may answer on the check queries (default :data:`MAX_ABS_OUTPUT`).

    Raises
    ------
    FormatError
        Missing, truncated or damaged file, newer format version, unknown kind, a config field missing,
        unknown, of the wrong type or out of range, tensors that do not match the config, non-finite or
        absurd values or answers. The message starts with the path and names the field or tensor.
    """
    from ..device import resolve_device

    path = Path(path)
    meta = read_model_metadata(path)
    header = _tensor_header(path)
    architecture = _architecture(path, meta)  # on the meta device: shapes only
    _check_header(path, meta["kind"], architecture.state_dict(), header)
    tensors = read_checked_tensors(path, meta.get("tensor_sha256"))
    _check_values(path, tensors)
    rep = architecture
    rep.load_state_dict(tensors, strict=True, assign=True)  # the meta module takes the file's tensors
    rep.eval()
    _check_state(path, rep)
    if device is not None:
        rep.to(resolve_device(device))
    _check_outputs(path, rep, max_output)
    return rep, meta


def _human(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1000.0
    return f"{n} B"  # pragma: no cover


def model_size_report(representation: Representation, raw_btf_bytes: int | None = None) -> dict[str, Any]:
    """The model's storage next to the raw BTF's: bytes, ratio and a one-line summary.

    ``raw_btf_bytes`` is the raw float32 RGB size of the BTF
    (:attr:`dynbtf.data.base.BTFSource.nbytes_float32`).

    >>> from dynbtf.representations.triple_plane import TriplePlane
    >>> model_size_report(TriplePlane(4, 4), raw_btf_bytes=10**9)["summary"]
    'model 39.7 KB vs raw BTF 1 GB (compression 2.5e+04 : 1)'
    """
    model_bytes = int(representation.storage_bytes())
    report: dict[str, Any] = {"model_bytes": model_bytes, "n_parameters": int(representation.n_parameters())}
    if raw_btf_bytes:
        report["raw_btf_bytes"] = int(raw_btf_bytes)
        report["compression_ratio"] = float(raw_btf_bytes) / max(model_bytes, 1)
        report["summary"] = (f"model {_human(model_bytes)} vs raw BTF {_human(raw_btf_bytes)} "
                             f"(compression {report['compression_ratio']:.2g} : 1)")
    else:
        report["summary"] = f"model {_human(model_bytes)}"
    return report


def _to_jsonable(x):
    """Convert NumPy scalars/arrays inside provenance to plain JSON types."""
    if isinstance(x, dict):
        return {str(k): _to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def representation_from_state(path, kind: str, config: dict[str, Any], tensors: dict[str, torch.Tensor],
                              max_output: float = MAX_ABS_OUTPUT) -> Representation:
    """A representation of ``kind`` and ``config`` holding ``tensors`` (a state dict read from ``path``, e.g.
    the ``model.*`` section of a compiled material), under the checks of :func:`load_model`: config fields,
    tensor shapes and dtypes against the config (before anything is allocated), values and answers.
    :class:`FormatError` names ``path`` and the field or tensor."""
    path = Path(path)
    meta = {"kind": kind, "config": config}
    architecture = _architecture(path, meta)
    _check_header(path, kind, architecture.state_dict(),
                  {name: (tuple(t.shape), _SAFETENSORS_DTYPES.get(t.dtype, str(t.dtype))) for name, t in tensors.items()})
    _check_values(path, tensors)
    architecture.load_state_dict(tensors, strict=True, assign=True)
    architecture.eval()
    _check_state(path, architecture)
    _check_outputs(path, architecture, max_output)
    return architecture
