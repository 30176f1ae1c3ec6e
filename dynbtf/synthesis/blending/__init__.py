"""Blending on the triangle lattice: the shared machinery of ``linear``, ``hist`` and ``hex``.

Every query ``uv`` lies in one triangle of the lattice (:mod:`~dynbtf.synthesis.lattice`);
each of its three vertices owns a random whole-texel offset (:mod:`~dynbtf.synthesis.hash`);
the exemplar is read at ``uv`` shifted by each offset (bilinear, wrapped) and the
three samples are blended with weights from the barycentrics. Methods differ only
in what plane they read and how they blend:

* ``linear`` -- plain linear blending of the raw features, weights ``b_i``
  (for comparison: loses contrast and creates ghosts).
* ``hist``  -- :class:`~dynbtf.synthesis.histogram_blending.HistogramBlending`.
* ``hex``   -- :class:`~dynbtf.synthesis.hex_tiling.HexTiling`.

Two implementations compute the same thing: a torch reference path (any device;
three :func:`dynbtf.texture.fetch_wrap` reads) and the fused numba kernel
(:func:`dynbtf.synthesis.blending.kernel.lattice_blend`, CPU), used on the CPU unless
``fast=False``.

Preprocessing ``tileable``: ``"auto"`` (default) makes the exemplar periodic with
:func:`~dynbtf.synthesis.tileable.make_tileable` when its wrap seams are visible,
i.e. when :func:`~dynbtf.synthesis.tileable.seam_discontinuity` exceeds
:data:`SEAM_THRESHOLD`; ``True``/``False`` force it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch

from ...errors import InputError
from ...tables import Table
from ...texture import fetch_wrap
from ..base import Synthesizer, feature_bound, register_synthesizer, wrapped_texel_position
from ..hash import hash_vertex, vertex_offsets
from ..histogram import blend_weights
from ..lattice import split_uv, triangle_lattice
from ..mip import LevelOfDetail, area_pyramid, level_shapes
from ..sample_transform import (check_rotation, check_scale_jitter, displacement, frame_direction, inverse_scales,
                                lattice_displacements, quarter_turns, scale_log, turn_cos_sin)
from ..tileable import make_tileable, seam_discontinuity

__all__ = ["LatticeBlending", "LinearBlending", "LatticePlane", "SEAM_THRESHOLD"]

#: ``tileable="auto"`` preprocesses exemplars whose wrap seams differ more than
#: this factor from interior neighbour differences (see :func:`seam_discontinuity`).
#: Measured on 64^2 x 4 smooth noise: periodic planes score 0.6-1.3, 48^2 crops 7-12.
SEAM_THRESHOLD = 2.0


@dataclass
class LatticePlane:
    """Precomputed plane that the lattice blend reads.

    Attributes
    ----------
    plane : float32 ``(H', W', C)``
        What the three samples fetch (raw features, or their Gaussian transform).
    tileable : bool
        Whether the exemplar was made periodic (then ``H' < H``, ``W' < W``).
    seam_before, seam_after : float
        :func:`seam_discontinuity` of the exemplar and of the plane actually read.
    extras : dict
        Method-specific tables (histogram transform, PCA, LUT, luminance).
    """

    plane: torch.Tensor
    tileable: bool
    seam_before: float
    seam_after: float
    extras: dict[str, Any] = field(default_factory=dict)

    def storage_bytes(self) -> int:
        tensors = [self.plane] + [v for v in self.extras.values() if isinstance(v, torch.Tensor)]
        return sum(t.numel() * t.element_size() for t in tensors)


def _resolve_tileable(exemplar: torch.Tensor, tileable, band: int | None) -> tuple[torch.Tensor, bool, float]:
    if tileable not in ("auto", True, False):
        raise InputError(f"tileable: expected 'auto', True or False, got {tileable!r}")
    seam = seam_discontinuity(exemplar)
    apply = seam > SEAM_THRESHOLD if tileable == "auto" else bool(tileable)
    return (make_tileable(exemplar, band) if apply else exemplar), apply, seam


class LatticeBlending(Synthesizer):
    """Base of the lattice-blending synthesizers (see the module docstring).

    Parameters
    ----------
    exemplar : ``(H, W, C)``
    seed : int, default 0
    tileable : {"auto", True, False}, default "auto"
        Make the exemplar periodic first ("Avoiding Cuts").
    band : int, optional
        Cross-fade band of the tileable preprocessing, texels (default ``0.165 min(H, W)``).
    fast : bool, optional
        Use the fused numba kernel (default: when the exemplar is on the CPU).
    prepared : LatticePlane, optional
        The ``prepared`` attribute of an earlier synthesizer of the same method
        and exemplar: skips the precomputation.
    rotation : bool, default False
        Turn each vertex's sample by a random number of quarter turns (from its hash) about a texel centre next
        to the vertex, and the view and the light into the query's frame
        (:mod:`~dynbtf.synthesis.sample_transform`). For isotropic materials.
    scale_jitter : float, default 0
        Magnify each vertex's sample by a factor between ``1 / (1 + scale_jitter)`` and ``1 + scale_jitter``
        (log-uniform, from its hash) about the same pivot; in ``[0, 1]``, 0: off. Reads between texel centres:
        for models fitted with the sub-texel term (:mod:`~dynbtf.synthesis.sample_transform`).
    """

    backends = {"web": f"{__name__}.web"}

    mode: ClassVar[int]

    def __init__(self, exemplar, seed: int = 0, *, tileable="auto", band: int | None = None, fast: bool | None = None,
                 prepared: LatticePlane | None = None, rotation: bool = False, scale_jitter: float = 0.0) -> None:
        super().__init__(exemplar, seed)
        self.rotation = check_rotation("rotation", rotation)
        self.scale_jitter = check_scale_jitter("scale_jitter", scale_jitter)
        self.tileable_option = tileable
        self.band = band
        self.fast = self.device.type == "cpu" if fast is None else bool(fast)
        if self.fast and self.device.type != "cpu":
            raise InputError(f"fast: the fused kernel runs on the CPU; the exemplar is on {self.device}")
        if prepared is None:
            source, applied, seam = _resolve_tileable(self.exemplar, tileable, band)
            prepared = self.prepare(source)
            prepared.tileable, prepared.seam_before = applied, seam
            prepared.seam_after = seam_discontinuity(source) if applied else seam
        elif not isinstance(prepared, LatticePlane) or prepared.plane.shape[-1] != self.plane_channels():
            raise InputError(f"prepared: expected the LatticePlane of a {self.name!r} synthesizer "
                             f"of a {self.channels}-channel exemplar")
        self.prepared = prepared
        self._numpy_cache: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------ method hooks
    def prepare(self, source: torch.Tensor) -> LatticePlane:
        """Precompute the plane that is read (``source`` is the possibly tileable exemplar)."""
        return LatticePlane(source, False, 0.0, 0.0)

    def plane_channels(self) -> int:
        return self.channels

    def blend(self, samples: torch.Tensor, barycentrics: torch.Tensor, uv_samples: torch.Tensor,
              level: int = 0) -> torch.Tensor:
        """Reference blend of ``samples (N, 3, C')`` with ``barycentrics (N, 3)`` float64 -> ``(N, C)`` float32.

        ``uv_samples (N, 3, 2)`` are the wrapped read positions (for extra fetches); ``level`` is
        the pyramid level the samples were read from (0: the point query; see :meth:`filtered_latent`).
        """
        return (barycentrics.to(samples.dtype)[..., None] * samples).sum(-2)

    def kernel_arguments(self) -> dict[str, Any]:
        """Keyword arguments of :func:`dynbtf.synthesis.blending.kernel.lattice_blend` besides uv/plane/density/seed
        and the turns."""
        return {}

    #: The exponent ``p`` of the lattice weights ``b^p`` (normalized) that set a query's frame angle
    #: (:func:`~dynbtf.synthesis.sample_transform.frame_direction`): 1, the barycentrics, here; a method with sharper
    #: weights gives its own.
    frame_exponent: float = 1.0

    def filter_tables(self, levels: list[torch.Tensor]) -> dict[str, Any]:
        """Method-specific per-level tables of the footprint query, built once from the read plane's pyramid."""
        return {}

    # ------------------------------------------------------------ evaluation
    @property
    def density(self) -> tuple[int, int]:
        """Texels per repeat ``(W, H)`` of the original exemplar."""
        return int(self.exemplar.shape[1]), int(self.exemplar.shape[0])

    def _turns(self, vertices: torch.Tensor) -> torch.Tensor:
        """Quarter turns ``(N, 3)`` int64 of the samples of lattice ``vertices (N, 3, 2)``."""
        return quarter_turns(hash_vertex(vertices[..., 0], vertices[..., 1], self.seed))

    @property
    def transformed(self) -> bool:
        """Whether the samples are turned or scaled (each then has its own read position's fraction)."""
        return self.rotation or self.scale_jitter > 0.0

    def _sample_matrices(self, vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(c, s)`` float64 ``(N, 3)`` of each sample's map ``[[c, -s], [s, c]]``: its quarter turn (identity
        without ``rotation``) over its scale factor (1 without ``scale_jitter``)."""
        hashes = hash_vertex(vertices[..., 0], vertices[..., 1], self.seed)
        if self.rotation:
            cos_a, sin_a = (t.to(torch.float64) for t in turn_cos_sin(quarter_turns(hashes)))
        else:
            cos_a, sin_a = torch.ones_like(hashes, dtype=torch.float64), torch.zeros_like(hashes, dtype=torch.float64)
        if self.scale_jitter > 0.0:
            inverse = inverse_scales(hashes, scale_log(self.scale_jitter))
            cos_a, sin_a = cos_a * inverse, sin_a * inverse
        return cos_a, sin_a

    def frame_rotation(self, points: torch.Tensor) -> torch.Tensor | None:
        if not self.rotation:
            return None
        if self.fast:
            from .kernel import lattice_frames

            return torch.from_numpy(lattice_frames(points.detach().cpu().numpy(), self.seed, self.frame_exponent))
        vertices, bary = triangle_lattice(points)
        return frame_direction(self._turns(vertices), blend_weights(bary, self.frame_exponent))

    def sample_positions(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Read positions and barycentrics of the three samples of each query.

        Returns ``uv_samples (N, 3, 2)`` float64 in ``[0, 1)`` (fractions of the read
        plane, wrapped) and ``barycentrics (N, 3)`` float64, for ``uv (N, 2)`` float64.
        """
        ph, pw = self.prepared.plane.shape[:2]
        whole, frac = split_uv(uv)
        vertices, bary = triangle_lattice(uv)
        ox, oy = vertex_offsets(vertices[..., 0], vertices[..., 1], self.seed, pw, ph)
        dw, dh = self.density
        x = wrapped_texel_position(whole[:, 0], frac[:, 0], dw, pw)[:, None] + ox
        y = wrapped_texel_position(whole[:, 1], frac[:, 1], dh, ph)[:, None] + oy
        if self.transformed:  # each sample turned and/or scaled about its vertex's pivot, a texel centre next to it
            cos_a, sin_a = self._sample_matrices(vertices)
            dx, dy = lattice_displacements(vertices, bary, (dw, dh))
            tx, ty = x - 0.5 - torch.floor(x - 0.5), y - 0.5 - torch.floor(y - 0.5)  # fractions from the texel centre
            ex, ey = displacement(tx, ty, dx, dy, cos_a, sin_a)
            x, y = x + ex, y + ey
        return torch.stack([torch.remainder(x, pw) / pw, torch.remainder(y, ph) / ph], dim=-1), bary

    def reference_latent(self, uv: torch.Tensor) -> torch.Tensor:
        """The torch reference path of :meth:`latent` (any device)."""
        uv_samples, bary = self.sample_positions(uv)
        samples = fetch_wrap(self.prepared.plane, uv_samples)
        return self.blend(samples, bary, uv_samples).to(torch.float32)

    def _numpy(self, name: str, tensor: torch.Tensor) -> np.ndarray:
        if name not in self._numpy_cache:
            from ..kernels import cache_aligned

            self._numpy_cache[name] = cache_aligned(tensor.detach().cpu().numpy())
        return self._numpy_cache[name]

    def latent(self, uv: torch.Tensor, out: np.ndarray | None = None) -> torch.Tensor:
        """Blended values ``(N, C)`` float32 for ``uv (N, 2)`` float64 (fused kernel when ``fast``)."""
        if not self.fast:
            return self.reference_latent(uv)
        from .kernel import lattice_blend

        kwargs = {k: (self._numpy(k, v) if isinstance(v, torch.Tensor) else v)
                  for k, v in self.kernel_arguments().items()}
        result = lattice_blend(uv.detach().cpu().numpy(), self._numpy("plane", self.prepared.plane), self.density,
                               self.seed, self.mode, out=out, guidance=self.kernel_guidance(uv),
                               rotation=self.rotation, scale_log=scale_log(self.scale_jitter), **kwargs)
        return torch.from_numpy(result)

    def kernel_guidance(self, uv: torch.Tensor) -> tuple | None:
        """Exemplar guidance for the fused kernels at queries ``uv (N, 2)`` (None: none; see
        :mod:`dynbtf.synthesis.guided_blending`)."""
        return None

    def latent_channels(self, uv: torch.Tensor, rows: list[int]) -> torch.Tensor:
        """:meth:`latent`'s channels ``rows`` ``(N, len(rows))`` float32 for ``uv (N, 2)`` float64: the fused kernel
        reads only those channels of the plane (and of the inverse tables): every channel is blended with the
        same weights on its own, so the values are those of :meth:`latent`."""
        if not self.fast or len(rows) == self.plane_channels():
            return self.latent(uv)[:, rows]
        from .kernel import lattice_blend

        key = ",".join(map(str, rows))
        kwargs = {k: (self._numpy(f"{k}[{key}]", v[rows]) if k == "lut" else
                      self._numpy(k, v) if isinstance(v, torch.Tensor) else v)
                  for k, v in self.kernel_arguments().items()}
        plane = self._numpy(f"plane[{key}]", self.prepared.plane[..., rows])
        return torch.from_numpy(lattice_blend(uv.detach().cpu().numpy(), plane, self.density, self.seed, self.mode,
                                              guidance=self.kernel_guidance(uv), rotation=self.rotation,
                                              scale_log=scale_log(self.scale_jitter), **kwargs))

    # ------------------------------------------------------------ footprint queries
    def pyramid(self) -> dict[str, Any]:
        """The read plane's pyramid, its level of detail and the method's per-level tables (built once).

        Cached in ``prepared.extras["pyramid"]`` (shared by synthesizers built with the same ``prepared``).
        """
        cached = self.prepared.extras.get("pyramid")
        if cached is None:
            levels = area_pyramid(self.prepared.plane)
            cached = {"levels": levels, "lod": LevelOfDetail.of(levels), **self.filter_tables(levels)}
            self.prepared.extras["pyramid"] = cached
        return cached

    def level_of_detail(self) -> LevelOfDetail:
        return self.pyramid()["lod"]

    def filtered_latent(self, uv: torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
        """Latent values ``(N, C)`` float32 averaged over a footprint of ``footprint (N,)`` texels per query.

        Every sample of the point query is read from the pyramid level of that footprint
        (trilinear; :mod:`dynbtf.synthesis.mip`); footprints of at most one texel give the point
        query (to float rounding). Fused kernel when ``fast``.
        """
        pyr = self.pyramid()
        level, upper = pyr["lod"](footprint.detach().cpu().numpy())
        if not self.fast:
            return self._reference_filtered_latent(uv, pyr, level, upper)
        from .kernel import PackedPyramid, filtered_lattice_blend

        if "packed" not in pyr:
            lums = pyr.get("luminances")
            pyr["packed"] = PackedPyramid.pack([t.cpu().numpy() for t in pyr["levels"]],
                                               None if lums is None else [t.cpu().numpy() for t in lums])
        kwargs = {k: v for k, v in self.kernel_arguments().items() if k not in ("lut", "luminance")}
        if "luts" in pyr:
            kwargs["luts"] = pyr["luts_numpy"]
        result = filtered_lattice_blend(uv.detach().cpu().numpy(), level, upper, pyr["packed"], self.density,
                                        self.seed, self.mode, guidance=self.kernel_guidance(uv),
                                        rotation=self.rotation, scale_log=scale_log(self.scale_jitter), **kwargs)
        return torch.from_numpy(result)

    def _reference_filtered_latent(self, uv, pyr, level, upper) -> torch.Tensor:
        uv_samples, bary = self.sample_positions(uv)
        level = torch.from_numpy(level.astype(np.int64)).to(uv.device)
        upper = torch.from_numpy(upper).to(uv.device)
        out = torch.zeros(uv.shape[0], self.plane_channels(), dtype=torch.float32, device=uv.device)
        for lv in range(len(pyr["levels"])):
            for step, share in ((0, 1.0 - upper), (1, upper)):
                mask = (level + step == lv) & (share > 0)
                if not bool(mask.any()):
                    continue
                samples = fetch_wrap(pyr["levels"][lv], uv_samples[mask])
                out[mask] += share[mask, None] * self.blend(samples, bary[mask], uv_samples[mask], lv).float()
        return out

    # ------------------------------------------------------------ compiled state
    def prepared_arrays(self) -> dict[str, torch.Tensor]:
        """The read plane, its seam numbers, the method's tables (:meth:`extras_arrays`) and the pyramid."""
        pyr = self.pyramid()
        arrays = {"plane": self.prepared.plane, "tileable": torch.tensor(bool(self.prepared.tileable)),
                  "seam_before": torch.tensor(float(self.prepared.seam_before), dtype=torch.float64),
                  "seam_after": torch.tensor(float(self.prepared.seam_after), dtype=torch.float64),
                  **self.extras_arrays(), **self.filter_arrays(pyr)}
        arrays.update({f"pyramid.{i}": level for i, level in enumerate(pyr["levels"])})
        return {k: v.detach().cpu().contiguous() for k, v in arrays.items()}

    @classmethod
    def prepared_from_arrays(cls, arrays: dict[str, torch.Tensor], device: torch.device | str = "cpu") -> LatticePlane:
        arrays = {k: v.to(device) for k, v in arrays.items()}
        prepared = LatticePlane(arrays["plane"].to(torch.float32).contiguous(), bool(arrays["tileable"]),
                                float(arrays["seam_before"]), float(arrays["seam_after"]), cls.extras_from_arrays(arrays))
        count = sum(1 for k in arrays if k.startswith("pyramid."))
        levels = [arrays[f"pyramid.{i}"].to(torch.float32).contiguous() for i in range(count)]
        prepared.extras["pyramid"] = {"levels": levels, "lod": LevelOfDetail.of(levels),
                                      **cls.filter_from_arrays(arrays)}
        return prepared

    @classmethod
    def stored_tables(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> list[Table]:
        """The read plane ``(H', W', C)`` (``H' <= H``, ``W' <= W``: tileable preprocessing crops), its seam
        numbers, the pyramid of the read plane and the method's tables (:meth:`extra_tables`)."""
        h, w, c = plane.shape
        read = arrays.get("plane")
        hp, wp = (tuple(read.shape[:2]) if isinstance(read, torch.Tensor) and read.ndim == 3
                  and 1 <= read.shape[0] <= h and 1 <= read.shape[1] <= w else (h, w))
        bound = cls.plane_bound(plane)
        rules = [Table("plane", torch.float32, (hp, wp, c), -bound, bound), Table("tileable", torch.bool, ()),
                 Table("seam_before", torch.float64, (), 0.0), Table("seam_after", torch.float64, (), 0.0)]
        rules += [Table(f"pyramid.{i}", torch.float32, (lh, lw, c), -bound, bound)
                  for i, (lh, lw) in enumerate(level_shapes(hp, wp))]
        return rules + cls.extra_tables(arrays, plane, (hp, wp))

    @classmethod
    def pyramid_size(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> tuple[int, int]:
        return int(arrays["plane"].shape[0]), int(arrays["plane"].shape[1])  # the read plane's pyramid

    @classmethod
    def plane_bound(cls, plane: torch.Tensor) -> float:
        """Largest magnitude of the read plane's values (raw features: the exemplar's own)."""
        return feature_bound(plane)

    @classmethod
    def extra_tables(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor, read: tuple[int, int]) -> list[Table]:
        """Rules of the method's tables (:meth:`extras_arrays`, :meth:`filter_arrays`) for a read plane of
        ``read = (H', W')`` texels."""
        return []

    @classmethod
    def table_relations(cls, arrays: dict[str, torch.Tensor], plane: torch.Tensor) -> str | None:
        if not bool(arrays["tileable"]) and tuple(arrays["plane"].shape[:2]) != tuple(plane.shape[:2]):
            return (f"table 'plane': {tuple(arrays['plane'].shape[:2])} texels, but a plane that was not made "
                    f"tileable is the exemplar's {tuple(plane.shape[:2])}")
        return None

    def extras_arrays(self) -> dict[str, torch.Tensor]:
        """The method's tables in ``prepared.extras`` as named tensors (see :meth:`prepared_arrays`)."""
        return {}

    @classmethod
    def extras_from_arrays(cls, arrays: dict[str, torch.Tensor]) -> dict[str, Any]:
        """``prepared.extras`` rebuilt from :meth:`extras_arrays`."""
        return {}

    def filter_arrays(self, pyramid: dict[str, Any]) -> dict[str, torch.Tensor]:
        """The per-level tables of :meth:`filter_tables` as named tensors."""
        return {}

    @classmethod
    def filter_from_arrays(cls, arrays: dict[str, torch.Tensor]) -> dict[str, Any]:
        """The per-level tables rebuilt from :meth:`filter_arrays`."""
        return {}

    def parameters(self) -> dict[str, Any]:
        return {"tileable": self.prepared.tileable, "band": self.band, "fast": self.fast, "rotation": self.rotation,
                "scale_jitter": self.scale_jitter, "seam_before": round(self.prepared.seam_before, 4),
                "seam_after": round(self.prepared.seam_after, 4)}

    def storage_bytes(self) -> int:
        return self.prepared.storage_bytes()


@register_synthesizer("linear")
class LinearBlending(LatticeBlending):
    """Plain linear blending on the lattice (weights = barycentrics), for comparison.

    Same lattice, offsets and preprocessing as ``hist``, no histogram transform
    and no variance correction: contrast drops towards triangle centres (the
    variance of a blend of independent samples is ``sum b_i^2 <= 1`` times the
    exemplar's, down to 1/3) and new, averaged features appear.
    """

    from .kernel import MODE_LINEAR as mode  # noqa: E402
