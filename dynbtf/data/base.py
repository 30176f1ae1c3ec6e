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
from dataclasses import dataclass
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
        """Release open files (optional)."""

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

    def read_texels(self, pairs, texels, *, device=None):
        """Some texels of some images, decoding no more than the format needs.

        Parameters
        ----------
        pairs : int ``(B, 2)`` or ``(G, B, 2)``
            (view index, light index) of each image; with a leading group axis,
            group ``g``'s ``B`` images are read at group ``g``'s texels.
        texels : int ``(N,)`` or ``(G, N)``
            Flat texel indices ``row * width + col`` (row 0 at the top, as
            :meth:`image`), per group when ``pairs`` has a group axis.
        device : torch device or str, optional
            Return a ``torch.Tensor`` on this device (sources that decode with a
            matrix product, such as DFMF files, compute it there); by default a
            NumPy array.

        Returns
        -------
        float32 ``(B, N, 3)`` or ``(G, B, N, 3)``: ``out[g, b, j]`` is texel
        ``texels[g, j]`` of image ``pairs[g, b]``, equal to
        ``image(*pairs[g, b]).reshape(-1, 3)[texels[g, j]]``.

        Formats that can answer without decoding whole images (DFMF factors,
        stored values files, the simulator) override :meth:`_read_texels`; the
        default decodes each distinct image once per call.

        Examples
        --------
        >>> import numpy as np
        >>> from dynbtf.data.array import ArrayBTF
        >>> btf = ArrayBTF(np.arange(2 * 1 * 2 * 3 * 3, dtype=np.float32).reshape(2, 1, 2, 3, 3),
        ...                [[0, 0, 1.0], [0.6, 0, 0.8]], [[0, 0, 1.0]])
        >>> btf.read_texels([[1, 0]], [0, 5])[0, :, 0]
        array([18., 33.], dtype=float32)
        """
        pairs, texels, grouped = self._check_texel_request(pairs, texels)
        out = self._read_texels(pairs, texels, device)
        if device is not None:
            import torch

            out = (out if isinstance(out, torch.Tensor) else torch.from_numpy(out)).to(device)
        elif not isinstance(out, np.ndarray):
            out = out.cpu().numpy()
        return out if grouped else out[0]

    def _check_texel_request(self, pairs, texels) -> tuple[np.ndarray, np.ndarray, bool]:
        """Validated ``pairs (G, B, 2)``, ``texels (G, N)`` int64 and whether a group axis was given."""
        try:
            pairs = np.asarray(pairs)
            texels = np.asarray(texels)
        except (TypeError, ValueError):
            raise InputError("read_texels: pairs and texels must be integer arrays") from None
        for what, a in (("pairs", pairs), ("texels", texels)):
            if a.size and not np.issubdtype(a.dtype, np.integer):
                raise InputError(f"read_texels: {what} must hold integers, got dtype {a.dtype}")
        grouped = pairs.ndim == 3
        if pairs.ndim not in (2, 3) or pairs.shape[-1] != 2:
            raise InputError(f"read_texels: pairs must be (B, 2) or (G, B, 2) (view, light) indices, got shape "
                             f"{pairs.shape}")
        if texels.ndim != (2 if grouped else 1) or (grouped and texels.shape[0] != pairs.shape[0]):
            raise InputError("read_texels: texels must be " + (f"({pairs.shape[0]}, N) to match pairs {pairs.shape}"
                             if grouped else "(N,) flat indices") + f", got shape {texels.shape}")
        pairs = pairs.astype(np.int64).reshape(-1, pairs.shape[-2], 2)
        texels = texels.astype(np.int64).reshape(pairs.shape[0], -1)
        n_texels = self.height * self.width
        if texels.size and (texels.min() < 0 or texels.max() >= n_texels):
            raise InputError(f"read_texels: texel indices must lie in [0, {n_texels}) for {self.name} "
                             f"({self.height} x {self.width}), got {texels.min()}..{texels.max()}")
        if pairs.size:
            for axis, what, n in ((0, "view", self.n_views), (1, "light", self.n_lights)):
                col = pairs[..., axis]
                if col.min() < 0 or col.max() >= n:
                    raise InputError(f"read_texels: {what} indices must lie in [0, {n}) for {self.name}, got "
                                     f"{col.min()}..{col.max()}")
        return pairs, texels, grouped

    def _read_texels(self, pairs: np.ndarray, texels: np.ndarray, device=None):
        """Answer a validated request: ``pairs (G, B, 2)``, ``texels (G, N)`` -> ``(G, B, N, 3)`` float32.

        Default: decode each distinct image once and gather its texels (memory: one
        image at a time). May return a NumPy array or a torch tensor (on ``device``,
        where the source computes; the caller moves it there otherwise).
        """
        out = np.empty(pairs.shape[:2] + (texels.shape[1], 3), dtype=np.float32)
        rows = pairs[..., 0] * self.n_lights + pairs[..., 1]
        order = np.argsort(rows, axis=None, kind="stable")  # view-major: sources decoding per view stay warm
        flat_rows = rows.reshape(-1)[order]
        starts = np.flatnonzero(np.r_[True, flat_rows[1:] != flat_rows[:-1]])
        for a, z in zip(starts, np.r_[starts[1:], len(order)]):
            row = int(flat_rows[a])
            image = np.asarray(self._read_image(row // self.n_lights, row % self.n_lights),
                               dtype=np.float32).reshape(-1, 3)
            for k in order[a:z]:
                g, b = divmod(int(k), pairs.shape[1])
                out[g, b] = image[texels[g]]
        return out

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
