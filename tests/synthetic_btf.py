"""A small analytic BTF for tests of fitting and evaluation (independent of the simulator).

Values: a spatially varying albedo (smooth periodic pattern) times a Lambertian
term plus a Blinn-Phong highlight whose strength varies over the texels --
separable enough for a Triple Plane to fit well, varied enough to need all
three planes.
"""

from __future__ import annotations

import numpy as np

from dynbtf.conventions import spherical_to_direction
from dynbtf.data.array import ArrayBTF


def ring_directions(thetas=(0.0, 30.0, 60.0), counts=(1, 6, 8)) -> np.ndarray:
    """Unit directions on rings of constant theta (degrees), like the UBO grids."""
    out = []
    for theta, count in zip(thetas, counts):
        for k in range(count):
            out.append(spherical_to_direction(np.array(theta), np.array(360.0 * k / count)))
    return np.asarray(out, dtype=np.float64)


def synthetic_btf(size: int = 8, thetas=(0.0, 30.0, 60.0), counts=(1, 6, 8), name: str = "synthetic") -> ArrayBTF:
    """An ``ArrayBTF`` of ``size x size`` texels on ring direction grids (views = lights)."""
    dirs = ring_directions(thetas, counts)
    v = (np.arange(size) + 0.5) / size
    uu, vv = np.meshgrid(v, v)
    albedo = np.stack([0.5 + 0.3 * np.sin(2 * np.pi * uu), 0.4 + 0.2 * np.cos(2 * np.pi * vv),
                       0.3 + 0.15 * np.sin(2 * np.pi * (uu + vv))], axis=-1)
    spec = 0.3 + 0.25 * np.cos(2 * np.pi * uu) * np.sin(2 * np.pi * vv)
    h = dirs[:, None, :] + dirs[None, :, :]
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    lobe = np.clip(h[..., 2], 0, 1) ** 20  # (views, lights)
    values = albedo[None, None] + spec[None, None, :, :, None] * lobe[:, :, None, None, None]
    return ArrayBTF(values.astype(np.float32), dirs, dirs, name=name)
