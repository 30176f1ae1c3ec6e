"""The compiled material: one saved artifact from which every backend answers queries.

A synthesized BTF is a fitted model, a synthesis method and a seed. Answering a query needs more
than the model file: the method's off-line tables (inverse histogram tables, hex luminance, cut
tables, a quilted plane), the feature pyramid and its per-level tables, the decoder with the
method's output map folded into layer 1, the per-level decoders and the mean appearance of
footprint queries (fitted once per model, method and seed), and the renderer's importance-sampling
table. A :class:`CompiledMaterial` holds all of it; :func:`dynbtf.material.compiler.compile_material`
builds it once, and the library's evaluation (:class:`dynbtf.infinite_btf.SynthesizedBTF`), the
Mitsuba plugin and the web export read it.

File format (``.dbtfc``)
------------------------
A safetensors file. Tensors: ``model.*`` (the representation's state dict), ``synthesis.*``
(:meth:`~dynbtf.synthesis.base.Synthesizer.prepared_arrays`), ``decoder.*``
(:meth:`~dynbtf.decoder.folded.FoldedDecoder.to_tensors`) and, once a renderer built it,
``sampling.*``. The metadata entry ``dynbtf`` is a JSON header: ``format``
(``"dynbtf-compiled-material"``), ``format_version`` (:data:`FORMAT_VERSION`; a reader refuses
newer versions), the model's ``kind`` and ``config``, ``model_sha256`` (the digest of the model's
tensors, as in the model file), ``method``, ``seed``, ``arguments`` (the method's parameters that
rebuild it from the tables), ``choice`` (what ``auto`` chose: method, line, strength; or null), ``key`` (the cache
key), ``tensor_sha256``, a checksum of every tensor, and ``header_sha256``, a checksum of every other header
field: a damaged file is detected, never used.

Opening a file from anyone
--------------------------
A checksum anyone can recompute proves that a file was not damaged, not that it is sound. Before any
kernel reads a table, :func:`load_compiled` holds the file to what its writer would have produced: the
model's tensors to the model file's checks and to ``model_sha256``; every ``synthesis.*`` table to its
method's declared rules (:meth:`~dynbtf.synthesis.base.Synthesizer.stored_tables`: dtype, shape, value
bounds, monotone inverse tables, indices in range); the ``decoder.*`` tables to the shapes of the model's
own decoder (:meth:`~dynbtf.decoder.folded.FoldedDecoder.stored_tables`), finite and bounded; the
``sampling.*`` table to its shape and ranges. A file that breaks any of them is refused with a
:class:`~dynbtf.errors.FormatError` naming the file and the table.

Conventions as everywhere in dynbtf: directions in the local frame, linear RGB without
``cos(theta_light)``, ``uv`` in exemplar repeats.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from ..decoder.folded import MAX_MEAN_NODES, FoldedDecoder, stored_levels
from ..errors import FormatError, InputError
from ..io import atomic_path
from ..representations.model_file import read_checked_tensors, representation_from_state, tensor_digest
from ..tables import Table, TableError, check_tables

__all__ = ["CompiledMaterial", "save_compiled", "load_compiled", "is_compiled_material", "open_model_file", "material_key",
           "FORMAT_NAME", "FORMAT_VERSION", "SUFFIX"]

FORMAT_NAME = "dynbtf-compiled-material"
#: Bumped whenever a stored table changes meaning: older readers refuse newer files, old cache entries miss.
FORMAT_VERSION = 3  # 2: a relief model's hist tables keep the height out of the PCA (separate); 3: header_sha256
SUFFIX = ".dbtfc"


@dataclass
class CompiledMaterial:
    """Everything a backend needs to answer queries of one model, synthesis method and seed.

    Attributes
    ----------
    model : Representation
        The fitted representation (its decoder, angular planes and positional plane ``f_U``).
    method : str
        The synthesis method, resolved (``auto`` is stored as the method it chose).
    seed : int
    arguments : dict
        The method's parameters (JSON) that, with :attr:`synthesis`, rebuild the synthesizer.
    synthesis : dict of str to tensor
        The method's off-line tables and pyramid (:meth:`~dynbtf.synthesis.base.Synthesizer.prepared_arrays`).
    decoder : FoldedDecoder or None
        Layer 1 folded with the method's output map, per-level decoders, mean appearance. None for
        representations without a foldable decoder (they decode with their own ``decode``).
    choice : dict or None
        What ``auto`` chose and why (:meth:`~dynbtf.synthesis.auto.MethodChoice.record`: ``method``,
        ``line``, ``strength``), or None for a method asked by name.
    sampling : dict of str to tensor or None
        The importance-sampling table (:mod:`dynbtf.render.mitsuba.sampling`), once built.
    key : str
        The cache key: model contents, method, arguments, seed and format version.
    model_sha256 : str
        Digest of the model's tensors.
    """

    model: Any
    method: str
    seed: int
    arguments: dict[str, Any]
    synthesis: dict[str, torch.Tensor]
    decoder: FoldedDecoder | None
    choice: dict[str, Any] | None = None
    sampling: dict[str, torch.Tensor] | None = None
    key: str = ""
    model_sha256: str = ""
    _synthesizers: dict = field(default_factory=dict, repr=False, compare=False)

    def synthesizer(self, device: torch.device | str | None = None):
        """The synthesizer rebuilt from the stored tables on ``device`` (default: the model's), built once."""
        from ..synthesis.registry import make_synthesizer, synthesizer_class

        device = torch.device(device) if device is not None else self.model.positional_plane().device
        if str(device) not in self._synthesizers:
            plane = self.model.positional_plane().detach().to(device)
            prepared = synthesizer_class(self.method).prepared_from_arrays(self.synthesis, device)
            extra = {} if prepared is None else {"prepared": prepared}
            if device.type != "cpu" and "fast" in _accepted_arguments(self.method):
                extra["fast"] = False
            try:
                synth = make_synthesizer(self.method, plane, seed=self.seed, **self.arguments, **extra)
            except (TypeError, ValueError, OverflowError) as e:  # arguments read from a file, of the wrong kind
                raise InputError(f"the material's arguments {self.arguments} do not build method {self.method!r}: "
                                 f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
            if synth.choice is None and self.choice is not None:
                from ..synthesis.auto import RecordedChoice

                synth.choice = RecordedChoice(str(self.choice["method"]), str(self.choice["line"]),
                                              float(self.choice["strength"]))
            self._synthesizers[str(device)] = synth
        return self._synthesizers[str(device)]

    def to(self, device: torch.device | str) -> "CompiledMaterial":
        """The same material with its model and decoder on ``device`` (copies; this one is unchanged)."""
        import copy

        decoder = None if self.decoder is None else FoldedDecoder.from_tensors(self.decoder.to_tensors(), device)
        return replace(self, model=copy.deepcopy(self.model).to(torch.device(device)), decoder=decoder,
                       _synthesizers={})

    def exemplar(self) -> "CompiledMaterial":
        """The material of the exemplar itself: the same model, periodic (the registry's
        :data:`~dynbtf.synthesis.registry.EXEMPLAR_METHOD`, which has no tables), its decoder folded with no output
        map. Derived, not compiled: nothing is fitted or cached."""
        from ..synthesis.registry import EXEMPLAR_METHOD

        fast = self.model.fast_decoder()
        decoder = None if fast is None else FoldedDecoder.fold(fast.decoder, None, None)
        return CompiledMaterial(model=self.model, method=EXEMPLAR_METHOD, seed=0, arguments={}, synthesis={},
                                decoder=decoder, model_sha256=self.model_sha256)

    def with_sampling(self, table: dict[str, torch.Tensor]) -> "CompiledMaterial":
        """The same material with an importance-sampling table."""
        return replace(self, sampling={k: v.detach().cpu().contiguous() for k, v in table.items()},
                       _synthesizers=self._synthesizers)

    def storage_bytes(self) -> int:
        """Bytes of the stored tables beyond the model (synthesis, decoders, sampling)."""
        tensors = list(self.synthesis.values()) + list((self.decoder.to_tensors() if self.decoder else {}).values())
        tensors += list((self.sampling or {}).values())
        return sum(t.numel() * t.element_size() for t in tensors)

    def describe(self) -> dict[str, Any]:
        """Method, seed, arguments, choice, levels and sizes (JSON-serializable)."""
        return {"method": self.method, "seed": self.seed, "arguments": self.arguments, "choice": self.choice,
                "footprint_levels": 0 if self.decoder is None else len(self.decoder.levels),
                "mean_appearance": self.decoder is not None and self.decoder.mean is not None,
                "sampling_table": self.sampling is not None, "table_bytes": self.storage_bytes(), "key": self.key}


def _accepted_arguments(method: str) -> list[str]:
    import inspect

    from ..synthesis.registry import synthesizer_class

    return list(inspect.signature(synthesizer_class(method).__init__).parameters)


def material_key(model_sha256: str, method: str, seed: int, arguments: dict[str, Any], footprints) -> str:
    """The cache key of a compiled material: SHA-256 of the format version, the model's digest, the method as
    asked for (``auto`` included), the version of the method's table construction
    (:attr:`~dynbtf.synthesis.base.Synthesizer.tables_version`; for ``auto``, its candidates'), its arguments
    (JSON), the seed and the footprint fits' settings (or False)."""
    from ..synthesis.registry import AUTO_CANDIDATES, SYNTHESIZERS

    versions = {name: SYNTHESIZERS[name].tables_version for name in (AUTO_CANDIDATES if method == "auto" else (method,))
                if name in SYNTHESIZERS}
    text = json.dumps({"format_version": FORMAT_VERSION, "model": model_sha256, "method": method, "seed": int(seed),
                       "tables_versions": versions, "arguments": arguments, "footprints": footprints},
                      sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def save_compiled(material: CompiledMaterial, path) -> Path:
    """Write ``material`` to ``path`` atomically (temporary file, then rename). Returns the path."""
    from safetensors.torch import save_file

    path = Path(path)
    tensors = {f"model.{k}": v for k, v in material.model.state_dict().items()}
    tensors.update({f"synthesis.{k}": v for k, v in material.synthesis.items()})
    if material.decoder is not None:
        tensors.update({f"decoder.{k}": v for k, v in material.decoder.to_tensors().items()})
    tensors.update({f"sampling.{k}": v for k, v in (material.sampling or {}).items()})
    tensors = {k: v.detach().cpu().clone() for k, v in tensors.items()}  # clones: tables may share storage
    header = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, "kind": material.model.kind,
              "config": material.model.config(), "model_sha256": material.model_sha256, "method": material.method,
              "seed": material.seed, "arguments": material.arguments, "choice": material.choice,
              "key": material.key}
    header = json.loads(json.dumps(header, default=str))  # as a reader will see it
    header.update(header_sha256=header_digest(header), tensor_sha256=tensor_digest(tensors))
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={"dynbtf": json.dumps(header, default=str)})
    return path


def header_digest(header: dict[str, Any]) -> str:
    """SHA-256 of a header's fields other than its checksums (canonical JSON): its ``header_sha256``."""
    fields = {k: v for k, v in header.items() if k not in ("header_sha256", "tensor_sha256")}
    return hashlib.sha256(json.dumps(fields, sort_keys=True, default=str).encode()).hexdigest()


def _header(path: Path) -> dict[str, Any]:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            text = (f.metadata() or {}).get("dynbtf")
    except Exception as e:  # SafetensorError, OSError
        raise FormatError(path, f"not a compiled material (unreadable safetensors data: {e})") from None
    try:
        header = json.loads(text) if text is not None else None
    except ValueError as e:
        raise FormatError(path, f"damaged header ({e})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise FormatError(path, f"not a compiled material (expected format {FORMAT_NAME!r} in the header)")
    version = header.get("format_version")
    if not isinstance(version, int) or version != FORMAT_VERSION:
        raise FormatError(path, f"compiled-material format version {version!r}; this dynbtf reads version "
                                f"{FORMAT_VERSION} (compile the model again with this version: dynbtf compile)")
    if header.get("header_sha256") != header_digest(header):
        raise FormatError(path, "header fields do not match their checksum: the file is damaged")
    return header


def is_compiled_material(path) -> bool:
    """Whether ``path`` is a compiled material file (its header says so)."""
    try:
        _header(Path(path))
        return True
    except FormatError:
        return False


def open_model_file(path, device: torch.device | str | None = None) -> tuple[Any, CompiledMaterial | None]:
    """``(representation, material)`` of a file that is either a model file (``dynbtf fit``'s ``.dbtfm``:
    ``material`` is None) or a compiled material (``dynbtf compile``'s ``.dbtfc``: its model and itself), each
    read under its format's checks (:class:`~dynbtf.errors.FormatError` names the file)."""
    from ..representations.model_file import load_model

    if is_compiled_material(path):
        material = load_compiled(path, device=device)
        return material.model, material
    return load_model(path, device=device)[0], None


def _section(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}


def load_compiled(path, device: torch.device | str | None = None) -> CompiledMaterial:
    """Read a compiled material; :class:`~dynbtf.errors.FormatError` names the file and what is wrong
    (not a compiled material, another version, a checksum mismatch, a missing table, a table that breaks
    its rule: see "Opening a file from anyone" in the module docstring). Nothing but regular files is read."""
    path = Path(path)
    if path.exists() and not path.is_file():
        raise FormatError(path, "not a regular file (a compiled material is a file)")
    header = _header(path)
    tensors = read_checked_tensors(path, header.get("tensor_sha256"))
    try:
        model_tensors = _section(tensors, "model.")
        if header["model_sha256"] != tensor_digest(model_tensors):
            raise FormatError(path, "model_sha256 does not match the model stored in the file")
        model = representation_from_state(path, header["kind"], header["config"], model_tensors)
        method, seed = header["method"], header["seed"]
        if not isinstance(method, str) or isinstance(seed, bool) or not isinstance(seed, int) or \
                not 0 <= seed < 2 ** 63 or not isinstance(header["arguments"], dict):
            raise FormatError(path, "damaged header: method, seed or arguments of the wrong type")
        choice = header.get("choice")
        if choice is not None and not (isinstance(choice, dict) and isinstance(choice.get("method"), str)
                                       and isinstance(choice.get("line"), str)
                                       and isinstance(choice.get("strength"), (int, float))
                                       and not isinstance(choice.get("strength"), bool)
                                       and math.isfinite(choice["strength"])):
            raise FormatError(path, "damaged header: choice is not null or {method, line, strength}")
        synthesis, decoder_tensors = _section(tensors, "synthesis."), _section(tensors, "decoder.")
        sampling = _section(tensors, "sampling.")
        unknown = sorted(k for k in tensors if not k.startswith(("model.", "synthesis.", "decoder.", "sampling.")))
        if unknown:
            raise FormatError(path, f"unexpected tensor {unknown[0]!r} (expected model.*, synthesis.*, decoder.*, "
                                    "sampling.*)")
        _check_tables(path, model, method, synthesis, decoder_tensors, sampling)
        material = CompiledMaterial(
            model=model, method=method, seed=seed, arguments=dict(header["arguments"]), synthesis=synthesis,
            decoder=FoldedDecoder.from_tensors(decoder_tensors) if decoder_tensors else None,
            choice=header.get("choice"), sampling=sampling or None,
            key=str(header.get("key", "")), model_sha256=str(header["model_sha256"]))
    except KeyError as e:
        raise FormatError(path, f"missing entry {e} of a compiled material") from None
    except (TypeError, ValueError) as e:
        raise FormatError(path, f"damaged header ({e})") from None
    return material if device is None else material.to(device)


def _check_tables(path: Path, model, method: str, synthesis: dict[str, torch.Tensor],
                  decoder: dict[str, torch.Tensor], sampling: dict[str, torch.Tensor]) -> None:
    """Hold the stored tables to their rules (module docstring); FormatError names the table."""
    from ..synthesis.mip import level_shapes
    from ..synthesis.registry import synthesizer_class

    try:
        synthesizer = synthesizer_class(method)
    except InputError:
        raise FormatError(path, f"unknown synthesis method {method!r} in the header") from None
    plane = model.positional_plane().detach().cpu()
    section = "synthesis"
    try:
        synthesizer.check_stored(synthesis, plane)
        section = "decoder"
        fast = model.fast_decoder()
        if fast is None:
            check_tables(decoder, [])
        else:
            reference = FoldedDecoder.fold(fast.decoder, None, None)
            check_tables(decoder, FoldedDecoder.stored_tables(decoder, reference))
            count = stored_levels(decoder)
            levels = len(level_shapes(*synthesizer.pyramid_size(synthesis, plane)))
            if count not in (1, levels):
                raise TableError(f"{count} level decoders, expected 1 (the point decoder) or one per pyramid level "
                                 f"({levels})")
            if "mean.weights" in decoder:
                weights = decoder["mean.weights"].double()
                if not 1 <= len(weights) <= MAX_MEAN_NODES or abs(float(weights.sum()) - 1.0) > 1e-3:
                    raise TableError(f"table 'mean.weights': {len(weights)} weights summing to "
                                     f"{float(weights.sum()):.6g}, expected 1 to {MAX_MEAN_NODES} summing to 1")
        section = "sampling"
        if sampling:
            check_tables(sampling, _sampling_rules(sampling))
    except TableError as e:
        raise FormatError(path, f"{section} tables of method {method!r}: {e}") from None


def _sampling_rules(sampling: dict[str, torch.Tensor]) -> list[Table]:
    """The importance-sampling table (:mod:`dynbtf.render.mitsuba.sampling`): non-negative densities on an
    ``R x R`` grid per view node, azimuth nodes in ``[0, 2 pi]``, polar nodes in ``[0, pi / 2]``."""
    density = sampling.get("density")
    p, t, r = (density.shape[0], density.shape[1], density.shape[2]) if isinstance(density, torch.Tensor) and \
        density.ndim == 4 else (None, None, None)
    return [Table("density", torch.float32, (p, t, r, r), 0.0, 1e30),
            Table("phi_nodes", torch.float64, (p,), 0.0, 2 * math.pi + 1e-9, monotone=True),
            Table("theta_nodes", torch.float64, (t,), 0.0, 0.5 * math.pi + 1e-9, monotone=True)]
