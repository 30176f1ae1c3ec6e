"""The synthesizer interface: exemplar plane + query uv -> synthesized features.

A synthesizer is built from an exemplar plane ``(H, W, C)`` (e.g. the Triple
Plane's positional features ``f_U``), a ``seed`` and method parameters. Its
costly precomputation (tileable preprocessing, PCA, histogram transform tables,
or the whole quilt for non-dynamic quilting) runs once in the constructor and
is exposed as the ``prepared`` attribute; passing it back as ``prepared=`` to a
new synthesizer of the same method and exemplar (e.g. with another seed) skips
it, like nvdiffrast's ``texture_construct_mip`` -> ``mip=``.

Calling the synthesizer, ``synth(uv)``, maps ``uv (..., 2)`` -- float32 or
float64, in units of one exemplar repeat, any real value with ``|uv| <``
:data:`MAX_REPEATS` (``2**52``; :func:`check_uv`, which every entry point calls) -- to features
``(..., C)`` float32. Dynamic methods compute every query independently from
``uv`` alone (``dynamic = True``); quilting is not dynamic: it synthesizes a
finite plane up front and wraps it.

Texel density is that of the original exemplar: one unit of ``uv`` spans ``W``
texels along ``u`` and ``H`` along ``v`` even when preprocessing crops the plane.

Methods register by name (:func:`register_synthesizer`, which fills :data:`SYNTHESIZERS`) and are
built with :func:`dynbtf.synthesis.registry.make_synthesizer`: ``tile``, ``linear``, ``hist``,
``hex``, ``quilt``, ``struct``, and ``auto`` (``struct`` or ``hist``, chosen from the exemplar's
structure). This module is the bottom of the methods: it imports none of them (the registry,
above them, does; the import-linter contract in ``pyproject.toml`` checks this).
"""

from __future__ import annotations

import abc
import importlib
import math
from typing import Any, ClassVar

import numpy as np
import torch

from ..errors import InputError
from ..tables import Table, TableError, check_tables
from .lattice import MAX_REPEATS

__all__ = [
    "Synthesizer",
    "SYNTHESIZERS",
    "register_synthesizer",
    "check_uv",
    "check_footprint",
    "wrapped_texel_position",
    "MIN_EXEMPLAR_TEXELS",
    "MAX_REPEATS",
    "GAUSSIAN_BOUND",
    "feature_bound",
    "coefficient_bound",
]

#: Largest magnitude of a Gaussianized value (the inverse normal CDF of ``1 - 1e-15`` is 7.9): the bound of
#: a histogram-preserving method's stored plane.
GAUSSIAN_BOUND = 8.0


def feature_bound(plane: torch.Tensor) -> float:
    """Largest magnitude a stored table of the exemplar's own values may hold: the plane's, with room for
    float rounding (preprocessing maps values back with exact inverses, pyramids average them)."""
    return 1.001 * float(plane.detach().abs().max()) + 1e-6 if plane.numel() else 1e-6


def coefficient_bound(plane: torch.Tensor) -> float:
    """Largest magnitude of a decorrelated coefficient of the plane's values: ``|(v - mean) . b| <= sqrt(C) *
    2 max |v|`` for unit basis vectors ``b``."""
    return 2.0 * math.sqrt(plane.shape[-1]) * feature_bound(plane)


#: name -> class, filled by :func:`register_synthesizer`.
SYNTHESIZERS: dict[str, type["Synthesizer"]] = {}

#: Smallest exemplar side (texels) any method accepts: below it a lattice
#: triangle (0.289 repeats) spans fewer than ~2.3 texels and the blending
#: footprint of the three patches covers the whole exemplar.
MIN_EXEMPLAR_TEXELS = 8


def register_synthesizer(name: str):
    """Class decorator: make a synthesizer constructible by ``name``."""

    def deco(cls):
        cls.name = name
        SYNTHESIZERS[name] = cls
        return cls

    return deco


def check_uv(uv, name: str = "uv", scale: float = 1.0) -> torch.Tensor:
    """Validate query positions: a float tensor/array ``(..., 2)`` -> tensor (float64 unless a float tensor).

    The one place that decides which ``uv`` may reach the lattice and the numba kernels: every
    value must be finite and ``|uv| * scale`` (exemplar repeats: what the synthesizer sees) below
    :data:`MAX_REPEATS` = ``2**52``, where float64 stops resolving fractions of a repeat (beyond,
    int64 conversions would overflow and the kernels read out of bounds). ``name`` is the
    argument named in the :class:`InputError` (e.g. ``"uv"``, ``"uv_rect"``, ``"--center"``).
    """
    if not isinstance(uv, torch.Tensor):
        try:
            uv = torch.from_numpy(np.array(uv, dtype=np.float64))  # a writable copy
        except (TypeError, ValueError) as e:
            raise InputError(f"{name}: expected a float array of shape (..., 2) ({e})") from None
    if not uv.is_floating_point():
        uv = uv.to(torch.float64)
    if uv.ndim == 0 or uv.shape[-1] != 2:
        raise InputError(f"{name}: expected shape (..., 2), got {tuple(uv.shape)}")
    if not uv.numel():
        return uv
    scale = float(scale)
    low, high = torch.aminmax(uv)  # one pass, no copy; NaN if any value is NaN
    largest = max(-float(low), float(high))  # |uv|'s largest, exactly (float32 widens exactly)
    if largest * scale < MAX_REPEATS:  # the product rounds as uv * scale does (monotone): same decision
        return uv
    if not np.isfinite(largest):
        bad = int((~torch.isfinite(uv)).any(-1).sum())
        raise InputError(f"{name}: {bad} position(s) contain NaN or infinite values; expected finite uv")
    bad = int((uv.abs().to(torch.float64) * scale >= MAX_REPEATS).any(-1).sum())
    what, got = ("|uv|", f"{largest!r}") if scale == 1.0 else \
        (f"|uv| * scale (scale = {scale!r})", f"|uv| = {largest!r}, i.e. {largest * scale!r} repeats")
    raise InputError(f"{name}: {what} must be below 2**52 = {int(MAX_REPEATS)} exemplar repeats (float64 resolves "
                     f"no fraction of a repeat beyond), got {got} ({bad} position(s) out of range)")


def check_footprint(footprint, batch, name: str = "footprint") -> torch.Tensor:
    """Validate per-query footprints: a scalar or an array of shape ``batch`` -> float64 tensor of shape ``batch``.

    Values must be finite and non-negative (any size: beyond the exemplar is its mean appearance);
    anything else raises :class:`InputError` naming ``name``.
    """
    try:
        value = footprint if isinstance(footprint, torch.Tensor) else torch.from_numpy(np.array(footprint, dtype=np.float64))
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: expected a non-negative float or an array of shape {tuple(batch)} ({e})") from None
    value = value.detach().to(torch.float64)
    if value.ndim and tuple(value.shape) != tuple(batch):
        raise InputError(f"{name}: expected a scalar or shape {tuple(batch)} (one width per query), "
                         f"got shape {tuple(value.shape)}")
    if value.numel() and (not float(value.min()) >= 0.0 or not np.isfinite(float(value.max()))):  # NaN fails too
        bad = ~torch.isfinite(value) | (value < 0)
        first = float(value.reshape(-1)[bad.reshape(-1)][0])
        raise InputError(f"{name}: {int(bad.sum())} value(s) negative, NaN or infinite (e.g. {first!r}); "
                         "expected finite widths >= 0")
    return value.expand(tuple(batch)).cpu()


def wrapped_texel_position(whole: torch.Tensor, frac: torch.Tensor, density: int, period: int) -> torch.Tensor:
    """Exact texel coordinate ``(whole + frac) * density`` modulo ``period``, float64 in ``[0, period)``.

    ``whole`` is int64, ``frac`` float64 in ``[0, 1)``: the integer part is reduced
    in int64 (each factor first, so ``whole * density`` cannot overflow), so the result
    does not depend on the size of ``whole``.
    """
    p = torch.remainder(torch.remainder(whole, period) * (density % period), period).to(torch.float64) + frac * density
    return torch.remainder(p, float(period))


class Synthesizer(abc.ABC):
    """Base class: an exemplar plane synthesized as an infinite texture.

    Parameters
    ----------
    exemplar : tensor or array ``(H, W, C)``
        The exemplar plane (channels last), at least ``MIN_EXEMPLAR_TEXELS`` texels
        on each side, finite. Kept on its device; outputs follow it.
    seed : int
        Seed of every random choice (integer hashes of lattice vertices).

    Attributes
    ----------
    name : str
        Registry name.
    dynamic : bool
        True if any ``uv`` is computed independently without pre-generation.
    prepared : object
        Result of the costly precomputation (method-specific; pass back as ``prepared=``).
    """

    name: ClassVar[str] = "abstract"
    dynamic: ClassVar[bool] = True
    #: What the method takes from a fitted model when its caller does not give it: parameter name -> the model
    #: input that provides it (``"appearance"``: the plane decoded under a few lights; ``"luminance"``: decoded at
    #: normal view and light; ``"separate_channels"``: a relief model's height channels). The material stage
    #: derives them (:func:`dynbtf.material.compiler.model_arguments`); synthesis itself never decodes a model.
    model_inputs: ClassVar[dict[str, str]] = {}
    #: Whether the method's tables (:meth:`prepared_arrays`) depend on the seed. Most are the exemplar's alone (the
    #: seed only picks hashes at query time), and the material cache then shares them between seeds; a
    #: pre-generated texture (``quilt``) is drawn with the seed.
    seeded_tables: ClassVar[bool] = False
    #: Version of the method's off-line table construction: raised when the same exemplar and arguments build
    #: different tables, so that the material cache's entries of the older construction are compiled again.
    tables_version: ClassVar[int] = 1
    #: The backends the method runs on besides its torch reference and CPU kernel: backend name -> the module that
    #: gives its form there, ``form(synthesizer)`` (``"web"``: the GLSL export's
    #: mode, shader code and tables). A method package (``dynbtf/synthesis/<method>/``) holds its synthesizer in
    #: ``__init__.py`` and these modules beside it; a subclass inherits its base's entries unless it sets its own.
    #: Backends look methods up here (:meth:`backend_form`) and name none.
    backends: ClassVar[dict[str, str]] = {}
    #: The :class:`~dynbtf.synthesis.auto.MethodChoice` when built by ``make_synthesizer("auto", ...)``.
    choice = None

    def variation_gain(self, points: torch.Tensor, footprint_texels: torch.Tensor | None = None) -> torch.Tensor | None:
        """RGB factors ``(N, 3)`` float32 that multiply the decoded reflectance at ``points (N, 2)`` (exemplar
        repeats; ``footprint_texels (N,)``, optional: each footprint's side in texels), or None: the method's
        variation controls (``struct``'s per-element brightness and tint). None unless a method has them on."""
        return None

    def advice(self) -> list[str]:
        """Lines for the person who chose this synthesis: what would make it better for this exemplar (``struct``:
        a model fitted at a size where its elements are whole texels). None by default; the CLI prints them."""
        return []

    def frame_rotation(self, points: torch.Tensor) -> torch.Tensor | None:
        """``(cos a, sin a)`` ``(N, 2)`` float64 of the angle ``a`` (about the normal) by which the view and the light
        are turned into the frame of the content synthesized at ``points (N, 2)`` (exemplar repeats), or None: the
        method's samples keep the exemplar's orientation (lattice blending's ``rotation``,
        :mod:`~dynbtf.synthesis.sample_transform`, turns them)."""
        return None

    @classmethod
    def backend_module(cls, backend: str):
        """The module that gives this method a ``backend`` form (its :attr:`backends` entry, imported), or None.

        >>> from dynbtf.synthesis.registry import synthesizer_class
        >>> synthesizer_class("struct").backend_module("web").__name__
        'dynbtf.synthesis.cell_quilting.web'
        >>> synthesizer_class("hist").backend_module("web").__name__
        'dynbtf.synthesis.histogram_blending.web'
        >>> synthesizer_class("quilt").backend_module("web") is None
        True
        """
        module = cls.backends.get(backend)
        return None if module is None else importlib.import_module(module)

    def backend_form(self, backend: str):
        """This synthesizer in ``backend``'s terms (:meth:`backend_module`'s ``form(self)``): e.g. its tables and
        shader branch for the web export (``"web"``). A method without that backend
        raises :class:`InputError` naming the methods that have it."""
        module = self.backend_module(backend)
        if module is None:
            having = sorted(name for name, cls in SYNTHESIZERS.items() if cls.backend_module(backend) is not None)
            raise InputError(f"synthesis method {self.name!r} has no {backend} form; methods with one: {having}")
        return module.form(self)

    def __init__(self, exemplar, seed: int = 0) -> None:
        self.exemplar = self.check_exemplar(exemplar)
        if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool):
            raise InputError(f"seed: expected an integer, got {seed!r}")
        self.seed = int(seed)

    @staticmethod
    def check_exemplar(exemplar, min_texels: int = MIN_EXEMPLAR_TEXELS) -> torch.Tensor:
        """Validate an exemplar: a finite float ``(H, W, C)`` plane at least ``min_texels`` on each side."""
        if not isinstance(exemplar, torch.Tensor):
            exemplar = torch.as_tensor(np.asarray(exemplar, dtype=np.float32))
        exemplar = exemplar.detach()
        if exemplar.ndim != 3:
            raise InputError(f"exemplar: expected a plane of shape (H, W, C), got shape {tuple(exemplar.shape)}")
        h, w, c = exemplar.shape
        if min(h, w) < min_texels or c < 1:
            raise InputError(f"exemplar: {h}x{w}x{c} is smaller than the blending footprint; expected at least "
                             f"{min_texels}x{min_texels} texels and 1 channel")
        if not exemplar.is_floating_point():
            exemplar = exemplar.to(torch.float32)
        if not bool(torch.isfinite(exemplar).all()):
            raise InputError("exemplar: contains NaN or infinite values")
        return exemplar.to(torch.float32).contiguous()

    @property
    def channels(self) -> int:
        return int(self.exemplar.shape[-1])

    @property
    def device(self) -> torch.device:
        return self.exemplar.device

    def __call__(self, uv, footprint=None) -> torch.Tensor:
        """Synthesized features ``(..., C)`` float32 at ``uv (..., 2)`` (exemplar repeats, any real value).

        ``footprint`` (optional, ``(...)``: texels of the original exemplar per query, finite and
        non-negative) answers the average over a square of that side instead of the point
        (:meth:`filtered_latent`).
        """
        uv = check_uv(uv).to(self.device)
        batch = uv.shape[:-1]
        flat = uv.reshape(-1, 2).to(torch.float64)
        if footprint is None:
            latent = self.latent(flat)
        else:
            latent = self.filtered_latent(flat, check_footprint(footprint, batch).reshape(-1))
        return self.features_from_latent(latent).reshape(*batch, self.channels)

    def features_from_latent(self, latent: torch.Tensor) -> torch.Tensor:
        """Features ``(N, C)`` of latent values ``(N, C_latent)`` (:meth:`latent`'s): the :meth:`output_map` applied,
        as :meth:`__call__` applies it."""
        matrix, offset = self.output_map()
        return latent if matrix is None else latent @ matrix.to(latent.dtype) + offset.to(latent.dtype)

    def channel(self, uv, index: int) -> torch.Tensor:
        """Feature channel ``index`` ``(...)`` float32 at ``uv (..., 2)``: the values of ``self(uv)[..., index]``.

        Only the latent channels the output map mixes into it are synthesized (:meth:`latent_channels`):
        one, for a channel kept out of the decorrelation (a relief model's height, marched through), or
        without an output map.
        """
        uv = check_uv(uv).to(self.device)
        batch = uv.shape[:-1]
        flat = uv.reshape(-1, 2).to(torch.float64)
        index = int(index) % self.channels
        matrix, offset = self.output_map()
        if matrix is None:
            return self.latent_channels(flat, [index])[:, 0].reshape(batch)
        rows = torch.nonzero(matrix[:, index]).reshape(-1).tolist()
        latent = self.latent_channels(flat, rows)
        column = matrix[rows, index].to(latent.dtype)
        out = (latent @ column if len(rows) > 1 else latent[:, 0] * column[0]) + offset[index].to(latent.dtype)
        return out.reshape(batch)

    def latent_channels(self, uv: torch.Tensor, rows: list[int]) -> torch.Tensor:
        """Latent channels ``rows`` only: ``uv (N, 2)`` float64 -> ``(N, len(rows))`` float32, the values of
        ``latent(uv)[:, rows]`` (methods whose channels are synthesized independently compute only those)."""
        return self.latent(uv)[:, rows]

    # ------------------------------------------------------------ to implement
    @abc.abstractmethod
    def latent(self, uv: torch.Tensor) -> torch.Tensor:
        """Synthesized values before the output map: ``uv (N, 2)`` float64 -> ``(N, C)`` float32."""

    def filtered_latent(self, uv: torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
        """:meth:`latent` averaged over a square footprint of ``footprint (N,)`` texels (of the original
        exemplar) per query: ``uv (N, 2)`` float64 -> ``(N, C)`` float32 (:mod:`dynbtf.synthesis.mip`).

        Footprints of at most one texel give :meth:`latent` (to float rounding).
        """
        raise InputError(f"synthesis method {self.name!r} has no footprint query")

    def level_of_detail(self):
        """The :class:`~dynbtf.synthesis.mip.LevelOfDetail` of the footprint query's pyramid, or None."""
        return None

    def output_map(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """``(matrix (C, C), offset (C,))`` with ``features = latent @ matrix + offset``, or ``(None, None)``.

        Methods that synthesize decorrelated coefficients return the PCA
        un-projection here, so that a decoder can fold it into its first layer.
        """
        return None, None

    def parameters(self) -> dict[str, Any]:
        """The method's parameters (JSON-serializable), for reports."""
        return {}

    def storage_bytes(self) -> int:
        """Bytes the synthesizer stores beyond the exemplar (tables, or the pre-generated plane)."""
        return 0

    # ------------------------------------------------------------ compiled state
    def prepared_arrays(self) -> dict[str, torch.Tensor]:
        """Everything this synthesizer derived from its exemplar off-line, as named CPU tensors.

        Its ``prepared`` state (inverse tables, luminance, cut tables, a quilted plane) and the
        footprint pyramid with its per-level tables: what a compiled material stores
        (:mod:`dynbtf.material`). :meth:`prepared_from_arrays` turns them back into the
        ``prepared=`` argument, so a reader answers queries without rebuilding anything. Scalars
        are 0-d tensors. Methods without off-line work return ``{}``.
        """
        return {}

    @classmethod
    def prepared_from_arrays(cls, arrays: dict[str, torch.Tensor], device: torch.device | str = "cpu"):
        """The ``prepared=`` argument rebuilt from :meth:`prepared_arrays` (on ``device``), or None.

        Raises ``KeyError`` for a missing array (the caller names the file it came from).
        """
        return None

    @classmethod
    def stored_tables(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> list[Table]:
        """The rules of the tables :meth:`prepared_arrays` stores (:class:`~dynbtf.tables.Table`: dtype,
        shape, value bounds, monotone rows) for the exemplar ``plane (H, W, C)`` (a model's positional plane).

        ``arrays`` are the stored tables themselves, read only for the sizes a rule depends on (e.g. the
        number of offsets), so that one rule set holds every table to the others. Default: no tables.
        """
        return []

    @classmethod
    def pyramid_size(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> tuple[int, int]:
        """``(rows, columns)`` of the plane whose pyramid footprint queries read, given stored tables that
        follow their rules: the exemplar's by default (a method that reads another plane says so)."""
        return int(plane.shape[0]), int(plane.shape[1])

    @classmethod
    def table_relations(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> str | None:
        """What is wrong between stored tables that each follow their rule (e.g. a cell count that does not
        divide the exemplar), or None. Called by :meth:`check_stored` after the rules hold."""
        return None

    @classmethod
    def check_stored(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> None:
        """Hold stored tables (a compiled material's ``synthesis.*``) to :meth:`stored_tables` and
        :meth:`table_relations` before any kernel reads them: :class:`~dynbtf.tables.TableError`
        names the table and what was expected."""
        check_tables(arrays, cls.stored_tables(arrays, plane))
        problem = cls.table_relations(arrays, plane)
        if problem is not None:
            raise TableError(problem)
