"""The BTF source interface: how a BTF gets into dynbtf.

A source is a read-only, lazily decoded 6-D table: ``height x width`` texels,
``n_views`` view directions and ``n_lights`` light directions. Nothing ever
materializes a whole BTF in memory: images are decoded one (view, light) pair at
a time, and random-access sampling decodes only what it needs.

Conventions (see :mod:`dynbtf.conventions`): directions are unit vectors in the
local frame, float64 ``(N, 3)``; images are ``(H, W, 3)`` linear RGB float32
whose values exclude ``cos(theta_light)``.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, Iterator

import numpy as np

from ..errors import InputError

__all__ = ["BTFSource", "BTFSamples"]


@dataclass
class BTFSamples:
    """A batch of BTF samples, all arrays of length ``N``.

    Attributes
    ----------
    uv : float64 ``(N, 2)``: texel-centre coordinates in ``[0, 1)^2``.
    view_index, light_index : int64 ``(N,)``: indices into the source's direction lists.
    w_view, w_light : float64 ``(N, 3)``: the corresponding unit vectors.
    rgb : float32 ``(N, 3)``: linear RGB values.
    """

    uv: np.ndarray
    view_index: np.ndarray
    light_index: np.ndarray
    w_view: np.ndarray
    w_light: np.ndarray
    rgb: np.ndarray


class BTFSource(abc.ABC):
    """Abstract BTF source. Subclasses implement ``_read_image`` and the metadata.

    Attributes
    ----------
    height, width : int
        Spatial size in texels (image rows, columns).
    views : float64 ``(n_views, 3)``
        View directions (towards the camera), unit vectors.
    lights : float64 ``(n_lights, 3)``
        Light directions (towards the light), unit vectors.
    name : str
        Human-readable name (file name or material).
    metadata : dict
        Provenance and format-specific facts (JSON-serializable).
    """

    height: int
    width: int
    views: np.ndarray
    lights: np.ndarray
    name: str = "btf"
    metadata: dict[str, Any]

    def __init__(self) -> None:
        self.metadata = {}

    # ---------------------------------------------------------------- interface
    @abc.abstractmethod
    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        """Decode one image ``(H, W, 3)`` float32; indices are already validated."""

    def close(self) -> None:
        """Release files or memory maps (optional)."""

    # ---------------------------------------------------------------- derived
    @property
    def n_views(self) -> int:
        return int(len(self.views))

    @property
    def n_lights(self) -> int:
        return int(len(self.lights))

    @property
    def n_pairs(self) -> int:
        return self.n_views * self.n_lights

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """``(n_views, n_lights, height, width)``."""
        return (self.n_views, self.n_lights, self.height, self.width)

    @property
    def nbytes_float32(self) -> int:
        """Size of the full BTF as raw float32 RGB (what we never materialize)."""
        return self.n_views * self.n_lights * self.height * self.width * 3 * 4

    def _check_pair(self, view_index, light_index) -> tuple[int, int]:
        try:
            v, l = int(view_index), int(light_index)
        except (TypeError, ValueError):
            raise InputError(f"view/light index must be integers, got {view_index!r}, {light_index!r}") from None
        if not 0 <= v < self.n_views:
            raise InputError(f"view index {v} out of range: {self.name} has {self.n_views} views (0..{self.n_views - 1})")
        if not 0 <= l < self.n_lights:
            raise InputError(f"light index {l} out of range: {self.name} has {self.n_lights} lights (0..{self.n_lights - 1})")
        return v, l

    def image(self, view_index: int, light_index: int) -> np.ndarray:
        """Linear RGB image ``(H, W, 3)`` float32 for one (view, light) pair."""
        v, l = self._check_pair(view_index, light_index)
        img = self._read_image(v, l)
        return img

    def pairs(self) -> Iterator[tuple[int, int]]:
        """All (view index, light index) pairs, view-major (row = view * n_lights + light)."""
        for v in range(self.n_views):
            for l in range(self.n_lights):
                yield v, l

    def nearest_view(self, w) -> int:
        """Index of the view direction closest to unit vector ``w`` (3,)."""
        return int(np.argmax(self.views @ np.asarray(w, dtype=np.float64)))

    def nearest_light(self, w) -> int:
        """Index of the light direction closest to unit vector ``w`` (3,)."""
        return int(np.argmax(self.lights @ np.asarray(w, dtype=np.float64)))

    def sample(self, n: int, rng: np.random.Generator, *, pairs: np.ndarray | None = None,
               images_per_batch: int = 64) -> BTFSamples:
        """Random-access samples of ``(uv, view, light) -> RGB``.

        Draws ``n`` samples uniformly over texels and over ``pairs`` (an ``(P, 2)``
        int array of allowed (view, light) index pairs; all pairs by default).
        Only ``images_per_batch`` distinct images are decoded per call, so the cost
        is bounded by ``images_per_batch`` image decodes however large ``n`` is.
        """
        if n <= 0:
            raise InputError(f"n: expected a positive number of samples, got {n}")
        if pairs is None:
            k = rng.integers(0, self.n_pairs, size=min(images_per_batch, n))
            chosen = np.stack([k // self.n_lights, k % self.n_lights], axis=1)
        else:
            pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
            chosen = pairs[rng.integers(0, len(pairs), size=min(images_per_batch, n))]
        which = rng.integers(0, len(chosen), size=n)
        rows = rng.integers(0, self.height, size=n)
        cols = rng.integers(0, self.width, size=n)
        rgb = np.empty((n, 3), dtype=np.float32)
        for k, (v, l) in enumerate(chosen):
            sel = which == k
            if sel.any():
                rgb[sel] = self.image(int(v), int(l))[rows[sel], cols[sel]]
        vi, li = chosen[which, 0], chosen[which, 1]
        uv = np.stack([(cols + 0.5) / self.width, (rows + 0.5) / self.height], axis=1)
        return BTFSamples(uv=uv, view_index=vi, light_index=li, w_view=self.views[vi],
                          w_light=self.lights[li], rgb=rgb)

    def describe(self) -> dict[str, Any]:
        """A JSON-serializable summary (used by ``dynbtf info``)."""
        return {
            "name": self.name,
            "kind": type(self).__name__,
            "height": self.height,
            "width": self.width,
            "n_views": self.n_views,
            "n_lights": self.n_lights,
            "raw_float32_bytes": self.nbytes_float32,
            **{k: v for k, v in self.metadata.items() if isinstance(v, (str, int, float, bool))},
        }

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.name!r}, {self.height}x{self.width} texels, "
                f"{self.n_views} views x {self.n_lights} lights)")
