"""A BTF resampled to another number of texels over the same repeat.

The exemplar's repeat stays the repeat: ``uv`` in ``[0, 1)^2`` covers the same surface, only the texel grid is
finer or coarser (``height x width`` texels instead of the source's). Each image is resampled on its own, periodic
(the exemplar is read with wrap addressing everywhere in dynbtf), by a cubic B-spline through the source's texel
centres (``scipy.ndimage.zoom``, ``mode="grid-wrap"``, ``grid_mode=True``): texel ``(i, j)`` of the result is the
spline at the source position ``((j + 0.5) W / width - 0.5, (i + 0.5) H / height - 0.5)``, in source texels. The
spline passes through the source's values (a resample to the same size returns them) and can ring next to sharp
edges; values below 0 (not a reflectance) are set to 0.

Why: a structured exemplar whose element period is not a whole number of texels (3 bricks across 64 texels:
21.33 texels each) cannot be re-tiled with whole elements by copies shifted by whole texels. Resampled so that
the period is whole (66 texels: 22 each), it can (``dynbtf fit --texels whole``,
:func:`dynbtf.training.exemplar_texels.whole_element_texels`).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .base import BTFSource

__all__ = ["ResampledBTF", "MAX_RESAMPLE_FACTOR"]

#: The result has at most this many times (and at least its inverse) the source's texels along each axis.
MAX_RESAMPLE_FACTOR = 4.0


def _texel_count(name: str, value, source_count: int) -> int:
    """``value`` as a texel count within :data:`MAX_RESAMPLE_FACTOR` of ``source_count``, else an InputError."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InputError(f"{name}: expected a positive integer number of texels, got {value!r}")
    if not source_count / MAX_RESAMPLE_FACTOR <= value <= source_count * MAX_RESAMPLE_FACTOR:
        raise InputError(f"{name}: {value} texels is more than {MAX_RESAMPLE_FACTOR:g}x away from the source's "
                         f"{source_count}")
    return int(value)


class ResampledBTF(BTFSource):
    """``source`` resampled to ``height x width`` texels over the same repeat (see the module docstring).

    Examples
    --------
    >>> from dynbtf.data.array import ArrayBTF
    >>> x = (np.arange(4) + 0.5) / 4
    >>> stripes = np.cos(2 * np.pi * x)[None, :].repeat(4, 0) + 1.0  # one period across the repeat
    >>> btf = ArrayBTF(stripes[None, None, :, :, None].repeat(3, -1), [[0, 0, 1.0]], [[0, 0, 1.0]])
    >>> fine = ResampledBTF(btf, 4, 6)
    >>> fine.shape, [round(float(v), 2) for v in fine.image(0, 0)[0, :, 0]]  # exact: 1.87, 1, 0.13, ...
    ((1, 1, 4, 6), [1.85, 1.0, 0.15, 0.15, 1.0, 1.85])
    """

    def __init__(self, source: BTFSource, height: int, width: int) -> None:
        super().__init__()
        self.source = source
        self.height = _texel_count("height", height, source.height)
        self.width = _texel_count("width", width, source.width)
        self.views, self.lights = source.views, source.lights
        self.name = f"{source.name} (resampled to {self.height} x {self.width} texels)"
        self.metadata = {"resampled_from_height": source.height, "resampled_from_width": source.width,
                         "source": source.describe()}

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        from scipy import ndimage

        image = np.asarray(self.source.image(view_index, light_index), dtype=np.float64)
        if (self.height, self.width) == image.shape[:2]:
            return image.astype(np.float32)
        zoom = (self.height / image.shape[0], self.width / image.shape[1], 1.0)
        out = ndimage.zoom(image, zoom, order=3, mode="grid-wrap", grid_mode=True)
        return np.maximum(out, 0.0).astype(np.float32)

    def close(self) -> None:
        self.source.close()
