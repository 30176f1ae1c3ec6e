"""A BTF seen through a box filter: what a footprint of ``factor x factor`` texels sees.

Each image of the source is averaged over blocks of ``factor x factor`` texels (block ``(i, j)``
covers rows ``i * factor ...`` and columns ``j * factor ...``), the ground truth of a filtered query
at that footprint on the exemplar, and the training target of a representation's coarser levels
(the mip of its positional plane with ``torch.nn.functional.avg_pool2d`` has the same blocks).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .base import BTFSource

__all__ = ["BoxFilteredBTF"]


class BoxFilteredBTF(BTFSource):
    """``source`` with every image block-averaged by ``factor`` (an integer dividing its height and width).

    Examples
    --------
    >>> from dynbtf.data.array import ArrayBTF
    >>> values = np.arange(16.0).reshape(1, 1, 4, 4, 1).repeat(3, -1)
    >>> coarse = BoxFilteredBTF(ArrayBTF(values, [[0, 0, 1.0]], [[0, 0, 1.0]]), 2)
    >>> coarse.shape, coarse.image(0, 0)[..., 0].tolist()
    ((1, 1, 2, 2), [[2.5, 4.5], [10.5, 12.5]])
    """

    def __init__(self, source: BTFSource, factor: int) -> None:
        super().__init__()
        if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
            raise InputError(f"factor: expected a positive integer number of texels, got {factor!r}")
        if source.height % factor or source.width % factor:
            raise InputError(f"factor {factor} does not divide the BTF {source.name!r} of {source.height} x "
                             f"{source.width} texels")
        self.source, self.factor = source, int(factor)
        self.height, self.width = source.height // self.factor, source.width // self.factor
        self.views, self.lights = source.views, source.lights
        self.name = f"{source.name} (box {self.factor}x{self.factor})"
        self.metadata = {"box_filter": self.factor, "source": source.describe()}

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        image = np.asarray(self.source.image(view_index, light_index), dtype=np.float64)
        f = self.factor
        blocks = image.reshape(self.height, f, self.width, f, 3)
        return blocks.mean(axis=(1, 3)).astype(np.float32)
