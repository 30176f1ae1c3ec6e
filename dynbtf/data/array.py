"""An in-memory BTF source backed by one array (small BTFs, tests, examples)."""

from __future__ import annotations

import numpy as np

from ..conventions import check_directions
from ..errors import InputError
from .base import BTFSource

__all__ = ["ArrayBTF"]


class ArrayBTF(BTFSource):
    """A BTF held in memory as ``values[view, light, row, col, rgb]``.

    Parameters
    ----------
    values : array ``(n_views, n_lights, H, W, 3)``
        Linear RGB, excluding cos(theta_light); stored as float32.
    views, lights : arrays ``(n_views, 3)``, ``(n_lights, 3)``
        Unit direction vectors in the local frame (upper hemisphere).
    name : str
        Display name.

    Examples
    --------
    >>> import numpy as np
    >>> btf = ArrayBTF(np.ones((1, 2, 4, 5, 3)), [[0, 0, 1.0]], [[0, 0, 1.0], [1.0, 0, 0]])
    >>> btf.shape, btf.image(0, 1).shape
    ((1, 2, 4, 5), (4, 5, 3))
    """

    def __init__(self, values, views, lights, name: str = "array", metadata: dict | None = None):
        super().__init__()
        values = np.asarray(values, dtype=np.float32)
        if values.ndim != 5 or values.shape[-1] != 3:
            raise InputError(f"values: expected shape (n_views, n_lights, H, W, 3), got {values.shape}")
        self.views = np.asarray(check_directions(np.asarray(views, dtype=np.float64), "views"), dtype=np.float64)
        self.lights = np.asarray(check_directions(np.asarray(lights, dtype=np.float64), "lights"), dtype=np.float64)
        if values.shape[:2] != (len(self.views), len(self.lights)):
            raise InputError(
                f"values: first two axes {values.shape[:2]} must match (n_views, n_lights) = "
                f"({len(self.views)}, {len(self.lights)})")
        if not np.isfinite(values).all():
            raise InputError("values: contains NaN or infinite values")
        self.values = values
        self.height, self.width = values.shape[2], values.shape[3]
        self.name = name
        self.metadata = dict(metadata or {})

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        return self.values[view_index, light_index]
