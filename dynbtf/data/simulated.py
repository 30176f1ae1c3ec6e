"""The simulated measured BTF: dynbtf's built-in default and test data.

No measured BTF can be downloaded here, so dynbtf simulates one: a procedural,
periodic micro height field with spatially varying microfacet reflectance
(:mod:`dynbtf.data.simulator`), "measured" on the UBO2003 (81 x 81) or UBO2014
(151 x 151) direction grid. Its images contain what a per-texel BRDF cannot
represent: cast shadows, masking and parallax of the meso-structure.

Images are rendered lazily, on demand: the first request for a view traces the
texels' camera rays into the height field (cached), the first request for a
light computes its shadow map (cached), and the images of all lights of a
view (in chunks of :attr:`SimulatedBTF.chunk` lights) are then shaded together and
kept until another view or chunk is requested, so reading the BTF view-major
(as writers do) shades every image exactly once.

Examples
--------
>>> btf = simulated_btf("leather", size=32)
>>> btf.shape, btf.image(0, 5).dtype
((81, 81, 32, 32), dtype('float32'))
"""

from __future__ import annotations

import numpy as np

from ..device import resolve_device
from ..errors import InputError
from .base import BTFSource
from .directions import direction_set
from .simulator import MATERIALS, HeightFieldRenderer, build_material

__all__ = ["SimulatedBTF", "simulated_btf", "MATERIALS", "GRIDS", "SIMULATOR_VERSION", "MIN_GRID"]

#: Direction grids a simulated BTF can be "measured" on (name -> description).
GRIDS = {
    "ubo2003": "81 view x 81 light directions (theta 0-75 deg in 15 deg rings), as the UBO2003 database",
    "ubo2014": "151 view x 151 light directions (theta 0-75 deg in 10 rings), as the UBO2014 database",
}

#: Bumped whenever the simulator's output changes (recorded in the metadata).
SIMULATOR_VERSION = 1

#: Material maps are tabulated on at least this many grid points per side.
MIN_GRID = 64

#: Sizes accepted for ``size`` (texels per side).
SIZE_RANGE = (4, 4096)


class SimulatedBTF(BTFSource):
    """A BTF rendered from one of the procedural materials.

    Parameters
    ----------
    material : str
        One of :data:`MATERIALS` (``stone``, ``leather``, ``lacquered_wood``, ``woven_fabric``,
        ``ceramic_tiles``, ``brick_wall``).
    size : int
        Spatial resolution: ``size x size`` texels covering one exemplar ``[0, 1)^2``.
    grid : str
        Direction grid, ``"ubo2003"`` or ``"ubo2014"`` (the same list for views and lights).
    seed : int
        Seed of every random choice of the material (same seed: identical images).
    relief : float, default 1
        Multiplier of the material's height field (its depth; 0: flat, no shadows nor
        parallax; 0.5: half as deep). Deeper relief means longer cast shadows and more
        parallax, which no per-texel representation without a parallax model (the
        Triple Plane, PCA, SH) can reproduce; see docs/triple_plane.md.
    device : str or torch.device, optional
        Where to render (default: CUDA if available, else CPU).

    Notes
    -----
    Values are linear RGB float32 reflectance factors ``pi * f_r`` relative to the
    macro surface (excluding ``cos(theta_light)``; see :mod:`dynbtf.data.simulator.renderer`
    for the exact definition). The material is defined continuously in ``uv`` and
    tabulated on a grid of :func:`tabulation_size` points per side, so different sizes show the same
    material sampled more or less finely.
    """

    def __init__(self, material: str, size: int = 128, grid: str = "ubo2003", seed: int = 0, *,
                 relief: float = 1.0, device=None):
        super().__init__()
        material, size, grid, seed = _check_arguments(material, size, grid, seed)
        if not isinstance(relief, (int, float)) or not 0.0 <= float(relief) <= 4.0:
            raise InputError(f"relief: expected a height-field multiplier in [0, 4], got {relief!r}")
        self.material, self.grid, self.seed, self.relief = material, grid, seed, float(relief)
        self.height = self.width = size
        self.views = np.asarray(direction_set(grid), dtype=np.float64)
        self.lights = self.views.copy()
        self.name = f"sim:{material}" + ("" if self.relief == 1.0 else f"?relief={self.relief:g}")
        self.device = resolve_device(device)
        self.tabulation = tabulation_size(size)
        self._renderer: HeightFieldRenderer | None = None
        #: Lights shaded together per view (bounded so a chunk stays ~2M texels).
        self.chunk = max(1, min(self.n_lights, (1 << 21) // (size * size)))
        self._cached_key: tuple[int, int] | None = None
        self._cached_images: np.ndarray | None = None
        self.metadata = {
            "format": "simulated",
            "material": material,
            "material_description": MATERIALS[material],
            "grid": grid,
            "seed": seed,
            "relief": self.relief,
            "simulator_version": SIMULATOR_VERSION,
            "tabulation": self.tabulation,
            "values": "linear RGB, pi * f_r, excluding cos(theta_light)",
        }

    @property
    def renderer(self) -> HeightFieldRenderer:
        """The (lazily built) renderer holding the material maps and caches."""
        if self._renderer is None:
            maps = build_material(self.material, self.tabulation, self.seed)
            if self.relief != 1.0:
                maps.height = maps.height * self.relief
            self._renderer = HeightFieldRenderer(maps, self.height, device=self.device)
        return self._renderer

    def view_images(self, view_index: int, light_indices=None) -> np.ndarray:
        """Images of one view for several lights, ``(L, H, W, 3)`` float32 (default: all lights)."""
        v, _ = self._check_pair(view_index, 0)
        lights = np.arange(self.n_lights) if light_indices is None else np.asarray(light_indices, dtype=np.int64)
        for l in lights.reshape(-1):
            self._check_pair(v, int(l))
        out = self.renderer.render(self.views[v], self.lights[lights.reshape(-1)])
        return out.cpu().numpy()

    def _read_texels(self, pairs: np.ndarray, texels: np.ndarray, device=None) -> np.ndarray:
        """Shades only the requested texels: per group and view, one render of its lights at the group's texels."""
        out = np.empty(pairs.shape[:2] + (texels.shape[1], 3), dtype=np.float32)
        for g in range(pairs.shape[0]):
            for v in np.unique(pairs[g, :, 0]):
                which = np.flatnonzero(pairs[g, :, 0] == v)
                values = self.renderer.render(self.views[v], self.lights[pairs[g, which, 1]], texels[g])
                out[g, which] = values.cpu().numpy()
        return out

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        chunk_start = (light_index // self.chunk) * self.chunk
        key = (view_index, chunk_start)
        if self._cached_key != key:
            stop = min(chunk_start + self.chunk, self.n_lights)
            self._cached_images = self.view_images(view_index, np.arange(chunk_start, stop))
            self._cached_key = key
        return self._cached_images[light_index - chunk_start].copy()


def tabulation_size(size: int) -> int:
    """Grid on which the material is tabulated: the smallest odd multiple of ``size`` >= :data:`MIN_GRID`.

    An odd multiple puts every output texel centre on a grid point (see
    :func:`dynbtf.data.simulator.geometry.trace_view`).

    >>> tabulation_size(128), tabulation_size(32), tabulation_size(16)
    (128, 96, 80)
    """
    stride = max(1, -(-MIN_GRID // int(size)))
    if stride % 2 == 0:
        stride += 1
    return stride * int(size)


def _check_arguments(material, size, grid, seed):
    if not isinstance(material, str) or material not in MATERIALS:
        raise InputError(f"material: unknown simulated material {material!r}; choose one of {', '.join(MATERIALS)}")
    if not isinstance(grid, str) or grid.lower() not in GRIDS:
        raise InputError(f"grid: unknown direction grid {grid!r}; choose one of {', '.join(GRIDS)}")
    try:
        size_i = int(size)
        ok = size_i == float(size)
    except (TypeError, ValueError):
        ok = False
    if not ok or not SIZE_RANGE[0] <= size_i <= SIZE_RANGE[1]:
        raise InputError(f"size: expected an integer number of texels per side in "
                         f"[{SIZE_RANGE[0]}, {SIZE_RANGE[1]}], got {size!r}")
    try:
        seed_i = int(seed)
        ok = seed_i == float(seed) and 0 <= seed_i < 2**32
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InputError(f"seed: expected an integer in [0, 2^32), got {seed!r}")
    return material, size_i, grid.lower(), seed_i


def simulated_btf(material: str, size: int = 128, grid: str = "ubo2003", seed: int = 0, *, relief: float = 1.0,
                  device=None) -> BTFSource:
    """Open a simulated BTF (what ``open_btf("sim:MATERIAL?size=..&grid=..&seed=..&relief=..")`` returns).

    See :class:`SimulatedBTF` for the parameters; unknown materials or grids and
    bad sizes, seeds or reliefs raise :class:`dynbtf.errors.InputError` listing the choices.
    """
    return SimulatedBTF(material, size=size, grid=grid, seed=seed, relief=relief, device=device)
