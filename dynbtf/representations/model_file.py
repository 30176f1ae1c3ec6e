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
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..errors import FormatError
from ..io import atomic_path
from .base import Representation
from .registry import get_representation_class

__all__ = ["save_model", "load_model", "read_model_metadata", "model_size_report", "FORMAT_NAME",
           "FORMAT_VERSION", "CONVENTIONS"]

FORMAT_NAME = "dynbtf-model"
FORMAT_VERSION = 1

#: What every model file's tensors assume (see :mod:`dynbtf.conventions`).
CONVENTIONS = {
    "directions": "unit vectors in the local frame (x=+u, y=+v, z=normal), w_view and w_light point away",
    "values": "linear RGB, pi * f_r, excluding cos(theta_light)",
    "uv": "units of one exemplar repeat; texel [i, j] centre at ((j + 0.5) / W, (i + 0.5) / H)",
    "angular_planes": "rows theta/90deg (clamped), columns phi/360deg (wrapped), Rusinkiewicz h and d",
}


def _tensor_digest(tensors: dict[str, torch.Tensor]) -> str:
    digest = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        digest.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        digest.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return digest.hexdigest()


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
        "tensor_sha256": _tensor_digest(tensors),
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
    except json.JSONDecodeError as e:
        raise FormatError(path, f"damaged metadata (invalid JSON: {e})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise FormatError(path, f"metadata field 'format' is {meta.get('format') if isinstance(meta, dict) else None!r}, "
                                f"expected {FORMAT_NAME!r}")
    version = meta.get("format_version")
    if not isinstance(version, int):
        raise FormatError(path, f"metadata field 'format_version' must be an integer, got {version!r}")
    if version > FORMAT_VERSION:
        raise FormatError(path, f"format version {version} is newer than this dynbtf supports "
                                f"({FORMAT_VERSION}); upgrade dynbtf to read it")
    for field in ("kind", "config"):
        if field not in meta:
            raise FormatError(path, f"metadata lacks the field {field!r}")
    return meta


def _check_tensors(path: Path, kind: str, expected: dict[str, torch.Tensor], found: dict[str, torch.Tensor]) -> None:
    """:class:`FormatError` naming the first tensor that is missing, extra, of the wrong shape or not finite."""
    missing = [name for name in expected if name not in found]
    if missing:
        raise FormatError(path, f"tensor {missing[0]!r} of the {kind!r} model is missing"
                                + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    extra = [name for name in found if name not in expected]
    if extra:
        raise FormatError(path, f"tensor {extra[0]!r} is not part of a {kind!r} model")
    for name, want in expected.items():
        got = found[name]
        if tuple(got.shape) != tuple(want.shape):
            raise FormatError(path, f"tensor {name!r} has shape {tuple(got.shape)}; the model's config needs "
                                    f"{tuple(want.shape)}")
        if got.is_floating_point() and not bool(torch.isfinite(got).all()):
            bad = int((~torch.isfinite(got)).sum())
            raise FormatError(path, f"tensor {name!r} holds {bad} non-finite value(s) (NaN or Inf): the model is "
                                    "damaged; refit it")


def load_model(path, device=None) -> tuple[Representation, dict[str, Any]]:
    """Load a model file: ``(representation, metadata)``.

    Parameters
    ----------
    path : str or Path
    device : str or torch.device, optional
        Where to put the representation (default: the CPU).

    Raises
    ------
    FormatError
        Missing, truncated or damaged file, newer format version, unknown kind,
        or tensors that do not match the stored architecture.
    """
    from safetensors.torch import load_file

    from ..device import resolve_device
    from ..errors import InputError

    path = Path(path)
    meta = read_model_metadata(path)
    try:
        cls = get_representation_class(meta["kind"])
    except InputError as e:
        raise FormatError(path, str(e)) from None
    try:
        tensors = load_file(str(path))
    except Exception as e:
        raise FormatError(path, f"damaged or truncated tensor data ({e})") from None
    if meta.get("tensor_sha256") != _tensor_digest(tensors):
        raise FormatError(path, "tensor data does not match its checksum: the file is damaged")
    try:
        rep = cls(**meta["config"])
    except (TypeError, InputError) as e:
        raise FormatError(path, f"metadata 'config' {meta['config']} does not describe a {meta['kind']!r} model ({e})") \
            from None
    _check_tensors(path, meta["kind"], rep.state_dict(), tensors)
    rep.load_state_dict(tensors, strict=True)
    rep.eval()
    if device is not None:
        rep.to(resolve_device(device))
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
