"""The simulated materials: procedural height fields and spatially varying reflectance.

Each material is a function ``(grid, seed) -> MaterialMaps`` that samples a
*continuous*, periodic definition (see :mod:`.noise`) on a ``grid x grid`` lattice,
so it tiles seamlessly and looks the same at every resolution. Heights are in
uv units (one exemplar = 1), centred on the reference plane ``z = 0``.

==================  ==========  ===================================================
name                kind        what it looks like
==================  ==========  ===================================================
``stone``           stochastic  conglomerate: rounded pebbles of varied colour set in
                                a grainy, recessed mortar; rough, deep cast shadows
``leather``         stochastic  brown grained leather: polygonal pebble grain between
                                dark creases, pores, soft sheen
``lacquered_wood``  specular    lacquered parquet: oak-like grain in planks with
                                V-grooves, a glossy clear coat with sharp highlights
``woven_fabric``    structured  plain weave of twisted yarns (navy warp, cream
                                weft) that pass over and under each other
``ceramic_tiles``   structured  4 x 4 square glazed tiles (each with its own tint and
                                tilt) between recessed grey grout joints; glossy glaze
``brick_wall``      structured  running-bond bricks, 4 per course x 8 courses (each
                                its own red-brown colour) in recessed mortar; rough
==================  ==========  ===================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .noise import derive_rng, fourier_noise, grid_uv, smoothstep, worley

__all__ = ["MaterialMaps", "MATERIAL_BUILDERS", "MATERIALS", "build_material"]


@dataclass
class MaterialMaps:
    """Tabulated meso-structure and reflectance of one material on a ``(G, G)`` grid.

    Attributes
    ----------
    height : float64 ``(G, G)``
        Height field in uv units, mean 0 (the reference plane).
    albedo : float64 ``(G, G, 3)``
        Lambertian base albedo, linear RGB in ``[0, 1]``.
    alpha : float64 ``(G, G)``
        GGX roughness of the base layer.
    f0 : float64 ``(G, G)``
        Base specular reflectance at normal incidence.
    coat : float64 ``(G, G)``
        Clear-coat weight in ``[0, 1]`` (0: no coat).
    coat_alpha, coat_f0 : float
        Clear-coat GGX roughness and normal-incidence reflectance.
    """

    height: np.ndarray
    albedo: np.ndarray
    alpha: np.ndarray
    f0: np.ndarray
    coat: np.ndarray
    coat_alpha: float = 0.05
    coat_f0: float = 0.04

    @property
    def size(self) -> int:
        return int(self.height.shape[0])


def _lerp(a, b, t):
    t = np.asarray(t, dtype=np.float64)[..., None]
    return np.asarray(a, dtype=np.float64) * (1.0 - t) + np.asarray(b, dtype=np.float64) * t


def _finish(height, albedo, alpha, f0, coat=None, **coat_params) -> MaterialMaps:
    height = np.asarray(height, dtype=np.float64)
    height = height - height.mean()
    coat = np.zeros_like(height) if coat is None else np.broadcast_to(coat, height.shape).astype(np.float64)
    return MaterialMaps(height=height, albedo=np.clip(albedo, 0.0, 1.0), alpha=np.clip(alpha, 0.02, 1.0),
                        f0=np.broadcast_to(f0, height.shape).astype(np.float64), coat=coat, **coat_params)


# --------------------------------------------------------------------------- stone
def stone(grid: int, seed: int) -> MaterialMaps:
    """Conglomerate stone: rounded pebbles in a grainy mortar (stochastic)."""
    warp_u = 0.02 * fourier_noise(grid, derive_rng(seed, "stone/warp-u"), k_max=5)
    warp_v = 0.02 * fourier_noise(grid, derive_rng(seed, "stone/warp-v"), k_max=5)
    cells = worley(grid, derive_rng(seed, "stone/pebbles"), cells=5, jitter=0.75, warp=(warp_u, warp_v))
    rnd = cells.cell_random[cells.cell]                        # (G, G, 4) per-pebble randoms
    edge = cells.edge / 0.5                                     # ~0 at borders, ~1 at centres
    inside = smoothstep(0.06, 0.22, edge)                       # pebble mask (0 = mortar)
    dome = np.sqrt(np.clip(edge / 0.8, 0.0, 1.0))
    bumps = fourier_noise(grid, derive_rng(seed, "stone/bumps"), k_min=6, k_max=24, slope=1.5)
    grain = fourier_noise(grid, derive_rng(seed, "stone/grain"), k_min=24, k_max=60, slope=0.0)
    height = (0.03 * inside * dome * (0.7 + 0.6 * rnd[..., 1])
              + 0.0015 * bumps * inside + 0.0012 * grain * (1.0 - inside))
    palette = np.array([[0.30, 0.29, 0.27], [0.40, 0.34, 0.26], [0.16, 0.16, 0.16],
                        [0.36, 0.23, 0.16], [0.48, 0.46, 0.42], [0.26, 0.28, 0.25]])
    pick = np.minimum((rnd[..., 2] * len(palette)).astype(int), len(palette) - 1)
    pebble = palette[pick] * (0.85 + 0.3 * rnd[..., 3])[..., None]
    # granite-like mineral grains: dark and light specks
    speck = fourier_noise(grid, derive_rng(seed, "stone/speck"), k_min=30, k_max=64, slope=0.0)
    speck2 = fourier_noise(grid, derive_rng(seed, "stone/speck2"), k_min=30, k_max=64, slope=0.0)
    pebble = _lerp(pebble, pebble * 0.35, smoothstep(1.0, 1.8, speck))
    pebble = _lerp(pebble, np.minimum(pebble * 1.6 + 0.08, 0.8), smoothstep(1.2, 2.0, speck2))
    mottled = fourier_noise(grid, derive_rng(seed, "stone/mottle"), k_min=3, k_max=12)
    pebble *= (1.0 + 0.15 * np.tanh(mottled))[..., None]
    mortar = np.array([0.21, 0.19, 0.16]) * (1.0 + 0.35 * np.tanh(grain))[..., None]
    albedo = _lerp(mortar, pebble, inside)
    alpha = 0.8 - 0.45 * inside * (0.4 + 0.6 * rnd[..., 0])    # pebbles are smoother (water-polished)
    return _finish(height, albedo, alpha, 0.04)


# --------------------------------------------------------------------------- leather
def leather(grid: int, seed: int) -> MaterialMaps:
    """Brown grained leather: rounded pebble grain between creases, pores (stochastic)."""
    warp_u = 0.01 * fourier_noise(grid, derive_rng(seed, "leather/warp-u"), k_max=10)
    warp_v = 0.01 * fourier_noise(grid, derive_rng(seed, "leather/warp-v"), k_max=10)
    cells = worley(grid, derive_rng(seed, "leather/grain"), cells=14, jitter=1.0, warp=(warp_u, warp_v))
    rnd = cells.cell_random[cells.cell]
    edge = cells.edge                                          # cell units, ~0..0.5
    crease = np.exp(-(edge / 0.06) ** 2)                        # 1 in the creases
    plateau = np.sqrt(np.clip(edge / 0.35, 0.0, 1.0))          # rounded grain bumps
    fine = worley(grid, derive_rng(seed, "leather/fine-grain"), cells=36, jitter=1.0, warp=(warp_u, warp_v))
    fine_crease = np.exp(-(fine.edge / 0.08) ** 2)
    large = fourier_noise(grid, derive_rng(seed, "leather/large"), k_max=5, slope=1.5)
    pores = fourier_noise(grid, derive_rng(seed, "leather/pores"), k_min=40, k_max=64, slope=0.0)
    pore = smoothstep(2.0, 2.8, pores)
    height = (0.005 * plateau * (0.8 + 0.4 * rnd[..., 0]) - 0.002 * crease - 0.0008 * fine_crease
              + 0.002 * large - 0.0006 * pore)
    tint = fourier_noise(grid, derive_rng(seed, "leather/tint"), k_max=8, slope=1.2)
    base = np.array([0.17, 0.075, 0.032]) * (1.0 + 0.2 * np.tanh(tint))[..., None]
    base = base * (0.92 + 0.16 * rnd[..., 1])[..., None]
    albedo = _lerp(base, base * 0.55, np.clip(0.6 * crease + 0.25 * fine_crease + 0.5 * pore, 0.0, 1.0))
    alpha = 0.42 + 0.2 * crease + 0.06 * rnd[..., 2]
    return _finish(height, albedo, alpha, 0.04)


# --------------------------------------------------------------------------- lacquered wood
def lacquered_wood(grid: int, seed: int) -> MaterialMaps:
    """Lacquered parquet: wood grain in planks with grooves, glossy clear coat (specular)."""
    u, v = grid_uv(grid)
    planks = 4
    row = np.floor(v * planks).astype(int)                       # plank rows along u
    rng = derive_rng(seed, "wood/planks")
    prm = rng.random((planks, 4))
    along = np.mod(u + prm[row, 0], 1.0)                         # one end joint per row per repeat
    across = v * planks - row                                    # 0..1 across the plank
    # flat-sawn grain: growth rings cut at a shallow angle give long arches along u
    wobble = fourier_noise(grid, derive_rng(seed, "wood/wobble"), k_max=8, stretch=(4.0, 1.0))
    fine = fourier_noise(grid, derive_rng(seed, "wood/fine"), k_min=8, k_max=64, stretch=(8.0, 1.0))
    arch = (across - 0.2 - 0.6 * prm[row, 1]) ** 2 * 2.5 + 0.15 * np.cos(2 * np.pi * (along + prm[row, 2]))
    rings = 6.0 * arch + 5.0 * across + 0.5 * wobble + 0.04 * fine + 10.0 * prm[row, 3]
    phase = rings - np.floor(rings)
    late = smoothstep(0.5, 0.8, phase) * (1.0 - smoothstep(0.92, 1.0, phase))
    pores_n = fourier_noise(grid, derive_rng(seed, "wood/pores"), k_min=16, k_max=64, slope=0.0,
                            stretch=(8.0, 1.0))
    pores = smoothstep(1.4, 2.4, pores_n) * (0.3 + 0.7 * late)
    early_c = np.array([0.42, 0.24, 0.11])
    late_c = np.array([0.27, 0.135, 0.055])
    tone = (0.8 + 0.35 * prm[row, 0])[..., None]                  # planks differ slightly
    albedo = _lerp(early_c, late_c, late) * tone
    albedo = _lerp(albedo, albedo * 0.55, pores)
    albedo *= (1.0 + 0.08 * np.tanh(fine))[..., None]
    # V-grooves between planks (along u) and at each plank's end joint
    d_side = np.minimum(across, 1.0 - across) / planks           # uv distance to a long edge
    d_end = np.minimum(along, 1.0 - along)
    groove = np.maximum(1.0 - np.minimum(d_side, d_end) / 0.007, 0.0)
    peel = fourier_noise(grid, derive_rng(seed, "wood/orange-peel"), k_min=6, k_max=20, slope=1.0)
    height = -0.006 * groove ** 1.5 + 0.0003 * late - 0.0006 * pores + 0.0003 * peel
    alpha = 0.35 + 0.1 * late
    coat = 1.0 - 0.8 * groove - 0.6 * pores                      # the lacquer thins into grooves and open pores
    albedo = _lerp(albedo, albedo * 0.5, groove)
    return _finish(height, albedo, alpha, 0.04, coat, coat_alpha=0.06, coat_f0=0.045)


# --------------------------------------------------------------------------- woven fabric
def woven_fabric(grid: int, seed: int) -> MaterialMaps:
    """Plain weave of twisted yarns, warp over weft in a checkerboard (structured)."""
    u, v = grid_uv(grid)
    n = 8                                                         # threads per repeat each way
    a, b = u * n, v * n                                           # thread coordinates
    k, m = np.floor(a), np.floor(b)                               # warp index k (along v), weft index m (along u)
    fa, fb = a - k - 0.5, b - m - 0.5                             # offset from the thread axes, -0.5..0.5
    amp, radius, half_width = 0.006, 0.022, 0.46                  # undulation, yarn radius (uv), yarn half width
    # warp k runs along v, over weft m when (k + m) is even; weft the opposite
    z_warp = amp * np.cos(np.pi * (b - 0.5 - k))
    z_weft = -amp * np.cos(np.pi * (a - 0.5 - m))
    prof_warp = np.sqrt(np.clip(1.0 - (fa / half_width) ** 2, 0.0, 1.0))
    prof_weft = np.sqrt(np.clip(1.0 - (fb / half_width) ** 2, 0.0, 1.0))
    # twisted plies: diagonal ridges across each yarn
    twist_warp = np.cos(2 * np.pi * (4.0 * b + 2.0 * fa)) * prof_warp
    twist_weft = np.cos(2 * np.pi * (4.0 * a - 2.0 * fb)) * prof_weft
    rng = derive_rng(seed, "fabric/threads")
    thread_r = rng.random((2, n, 2))
    fuzz = fourier_noise(grid, derive_rng(seed, "fabric/fuzz"), k_min=30, k_max=64, slope=0.0)
    h_warp = z_warp + radius * prof_warp * (1.0 + 0.08 * twist_warp) - radius * (1 - prof_warp) * 0.6
    h_weft = z_weft + radius * prof_weft * (1.0 + 0.08 * twist_weft) - radius * (1 - prof_weft) * 0.6
    h_warp = h_warp + 0.002 * (thread_r[0, k.astype(int) % n, 0] - 0.5)
    h_weft = h_weft + 0.002 * (thread_r[1, m.astype(int) % n, 0] - 0.5)
    on_warp = h_warp >= h_weft
    top = smoothstep(-0.0015, 0.0015, h_warp - h_weft)           # soft transition between yarns
    height = np.maximum(h_warp, h_weft) + 0.0004 * fuzz
    warp_c = np.array([0.025, 0.045, 0.13]) * (0.85 + 0.3 * thread_r[0, k.astype(int) % n, 1])[..., None]
    weft_c = np.array([0.55, 0.50, 0.40]) * (0.9 + 0.2 * thread_r[1, m.astype(int) % n, 1])[..., None]
    fibre_w = 0.7 + 0.3 * (0.5 + 0.5 * twist_warp)
    fibre_f = 0.75 + 0.25 * (0.5 + 0.5 * twist_weft)
    albedo = _lerp(weft_c * fibre_f[..., None], warp_c * fibre_w[..., None], top)
    albedo *= (1.0 + 0.08 * np.tanh(fuzz))[..., None]
    alpha = np.where(on_warp, 0.55, 0.6)
    return _finish(height, albedo, alpha, 0.04)


# --------------------------------------------------------------------------- ceramic tiles
def ceramic_tiles(grid: int, seed: int) -> MaterialMaps:
    """Square glazed ceramic tiles, 4 x 4 per repeat, in recessed grout joints (structured).

    The lattice is exact (tile period 1/4 repeat in u and v); every tile has its own tint,
    mottling, lippage and tilt, so the exemplar repeats only at the full repeat.
    """
    u, v = grid_uv(grid)
    n, period = 4, 0.25                                          # tiles per repeat, tile period (uv)
    a, b = u * n, v * n                                          # tile coordinates
    k, m = np.floor(a).astype(int) % n, np.floor(b).astype(int) % n   # tile column (along u), row (along v)
    fa, fb = a - np.floor(a), b - np.floor(b)                    # 0..1 across the tile
    d = period * np.minimum(np.minimum(fa, 1.0 - fa), np.minimum(fb, 1.0 - fb))  # uv distance to the tile's border
    joint_half, bevel, depth = 0.5 * 0.07 * period, 0.007, 0.012  # 7 % joints, rounded edge width, joint depth
    e = d - joint_half                                           # < 0 in the joint, > 0 on the tile
    top = smoothstep(-0.25 * bevel, bevel, e)                    # 0: grout floor, 1: flat glaze (rounded edge between)
    prm = derive_rng(seed, "tiles/tiles").random((n, n, 7))[m, k]  # per-tile randoms
    # per tile: lippage (height offset) and a slight tilt, so highlights differ from tile to tile
    lippage = 0.0008 * (prm[..., 0] - 0.5) + 0.004 * period * ((prm[..., 1] - 0.5) * (fa - 0.5)
                                                                + (prm[..., 2] - 0.5) * (fb - 0.5))
    peel = fourier_noise(grid, derive_rng(seed, "tiles/orange-peel"), k_min=6, k_max=24, slope=1.0)
    sand = fourier_noise(grid, derive_rng(seed, "tiles/grout-sand"), k_min=16, k_max=64, slope=0.5)
    height = -depth * (1.0 - top) + top * (lippage + 0.00025 * peel) + 0.0008 * sand * (1.0 - top)
    # glaze: one colour, each tile tinted (+-12 % brightness, a small warm/cool shift), mottled
    glaze = np.array([0.34, 0.47, 0.46])                         # celadon-like blue-green
    bright = 1.0 + 0.24 * (prm[..., 3] - 0.5)
    shift = 0.10 * (prm[..., 4] - 0.5)                           # + warmer, - cooler
    tint = np.stack([1.0 + shift, np.ones_like(shift), 1.0 - shift], axis=-1) * bright[..., None]
    mottle = fourier_noise(grid, derive_rng(seed, "tiles/mottle"), k_min=8, k_max=40, slope=0.8)
    speck = fourier_noise(grid, derive_rng(seed, "tiles/speck"), k_min=40, k_max=64, slope=0.0)
    tile_c = glaze * tint * (1.0 + 0.05 * np.tanh(mottle) + 0.03 * (prm[..., 5] - 0.5))[..., None]
    tile_c = _lerp(tile_c, tile_c * 0.6, 0.6 * smoothstep(1.8, 2.6, speck))   # a few dark iron specks
    rim = smoothstep(0.0, 0.6 * bevel, e) * (1.0 - smoothstep(0.6 * bevel, 1.6 * bevel, e))
    tile_c = _lerp(tile_c, np.minimum(tile_c * 1.35 + 0.04, 0.9), 0.5 * rim)  # glaze thins (lighter) over the edge
    grout_c = np.array([0.27, 0.265, 0.25]) * (1.0 + 0.25 * np.tanh(sand))[..., None]
    albedo = _lerp(grout_c, tile_c, top)
    alpha = 0.9 - top * (0.55 + 0.1 * prm[..., 6])               # grout rough, glazed body smoother
    coat = top                                                   # the glaze: a glossy clear coat
    return _finish(height, albedo, alpha, 0.04, coat, coat_alpha=0.05, coat_f0=0.04)


# --------------------------------------------------------------------------- brick wall
def brick_wall(grid: int, seed: int) -> MaterialMaps:
    """Running-bond brick wall: 4 bricks per course, 8 courses per repeat, recessed mortar (structured).

    Bricks are 1/4 x 1/8 repeat; odd courses are offset by half a brick, so the lattice is
    spanned by (1/4, 0) and (1/8, 1/8) in uv. Every brick has its own colour, grain and
    wear, so the exemplar repeats only at the full repeat.
    """
    u, v = grid_uv(grid)
    n_u, n_v = 4, 8                                              # bricks per course, courses per repeat
    w_b, h_b = 1.0 / n_u, 1.0 / n_v                              # brick period (uv)
    b = v * n_v
    row = np.floor(b).astype(int) % n_v                          # course (along v)
    a = u * n_u + 0.5 * (row % 2)                                # running bond: odd courses shifted half a brick
    col = np.floor(a).astype(int) % n_u                          # brick within the course (along u)
    fa, fb = a - np.floor(a), b - np.floor(b)
    chip = fourier_noise(grid, derive_rng(seed, "bricks/chipped-edges"), k_min=12, k_max=48, slope=0.5)
    d = np.minimum(w_b * np.minimum(fa, 1.0 - fa), h_b * np.minimum(fb, 1.0 - fb))  # uv distance to the border
    joint_half, arris, depth = 0.5 * 0.018, 0.006, 0.014         # mortar joint 0.018 uv, worn edge width, depth
    e = d - joint_half + 0.0012 * chip                           # slightly irregular (chipped) brick edges
    face = smoothstep(-0.2 * arris, arris, e)                    # 0: mortar, 1: brick face
    prm = derive_rng(seed, "bricks/bricks").random((n_v, n_u, 6))[row, col]   # per-brick randoms
    grain = fourier_noise(grid, derive_rng(seed, "bricks/grain"), k_min=20, k_max=64, slope=0.3)
    bumps = fourier_noise(grid, derive_rng(seed, "bricks/bumps"), k_min=6, k_max=20, slope=1.0)
    sand = fourier_noise(grid, derive_rng(seed, "bricks/mortar-sand"), k_min=28, k_max=64, slope=0.0)
    pits = fourier_noise(grid, derive_rng(seed, "bricks/pits"), k_min=30, k_max=64, slope=0.0)
    pit = smoothstep(1.9, 2.6, pits)
    height = (-depth * (1.0 - face)
              + face * (0.0015 * (prm[..., 0] - 0.5) + 0.0007 * bumps + 0.0004 * grain - 0.0012 * pit)
              + (1.0 - face) * 0.0009 * sand)
    # colour: each brick between an orange-red and a darker brown, +-12 % brightness
    red, brown = np.array([0.42, 0.15, 0.085]), np.array([0.30, 0.12, 0.08])
    brick_c = _lerp(red, brown, prm[..., 1]) * (0.88 + 0.24 * prm[..., 2])[..., None]
    burnt = prm[..., 3] > 0.9                                    # an occasional darker, over-fired brick
    brick_c = np.where(burnt[..., None], brick_c * 0.75, brick_c)
    cloud = fourier_noise(grid, derive_rng(seed, "bricks/cloud"), k_min=3, k_max=14, slope=1.0)
    brick_c = brick_c * (1.0 + 0.1 * np.tanh(cloud) + 0.1 * np.tanh(grain))[..., None]
    brick_c = _lerp(brick_c, brick_c * 0.55, pit)                # dark pores
    mortar_c = np.array([0.48, 0.45, 0.40]) * (1.0 + 0.2 * np.tanh(sand))[..., None]
    albedo = _lerp(mortar_c, brick_c, face)
    alpha = 0.95 - 0.15 * face * (0.5 + 0.5 * prm[..., 4])      # rough, diffuse
    return _finish(height, albedo, alpha, 0.04)


MATERIAL_BUILDERS: dict[str, Callable[[int, int], MaterialMaps]] = {
    "stone": stone,
    "leather": leather,
    "lacquered_wood": lacquered_wood,
    "woven_fabric": woven_fabric,
    "ceramic_tiles": ceramic_tiles,
    "brick_wall": brick_wall,
}

#: Material name -> one-line description (``dynbtf simulate --list``).
MATERIALS: dict[str, str] = {
    "stone": "stochastic: rounded pebbles of varied colour in a grainy recessed mortar; rough, deep cast shadows",
    "leather": "stochastic: brown grained leather with polygonal grain, dark creases, pores and a soft sheen",
    "lacquered_wood": "glossy: parquet planks with wood grain and V-grooves under a clear coat (sharp highlights)",
    "woven_fabric": "structured: plain weave of twisted yarns, navy warp over/under cream weft",
    "ceramic_tiles": "structured: 4 x 4 glazed ceramic tiles per repeat, each tinted, in recessed grey grout; glossy",
    "brick_wall": "structured: running-bond brick wall, 4 x 8 bricks per repeat, each coloured, recessed mortar; rough",
}


def build_material(name: str, grid: int, seed: int) -> MaterialMaps:
    """Tabulate material ``name`` on a ``grid x grid`` lattice from ``seed``."""
    return MATERIAL_BUILDERS[name](int(grid), int(seed))
