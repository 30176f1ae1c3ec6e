"""Tests of the simulated measured BTF (dynbtf.data.simulated, dynbtf.data.simulator).

References used here are independent of the simulator's code: a closed-form GGX
evaluation written with Walter et al.'s Lambda form of Smith masking (the
simulator uses the equivalent G1 = 2x / (x + sqrt(a^2 + (1 - a^2) x^2))), and the
elementary geometry of shadows and parallax of a raised plateau
(shadow length = H tan(theta_light), parallax shift = H tan(theta_view)).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dynbtf.conventions import spherical_to_direction
from dynbtf.data.simulated import MATERIALS, SimulatedBTF, simulated_btf, tabulation_size
from dynbtf.data.simulator.geometry import light_visibility, trace_view
from dynbtf.data.simulator.materials import MaterialMaps, build_material
from dynbtf.data.simulator.noise import derive_rng, fourier_noise, worley
from dynbtf.data.simulator.renderer import HeightFieldRenderer
from dynbtf.errors import DynBTFError, InputError


# ----------------------------------------------------------------------------- helpers
def _maps(height, albedo=(0.5, 0.4, 0.3), alpha=0.3, f0=0.04, coat=0.0, coat_alpha=0.05, coat_f0=0.04):
    g = height.shape[0]
    albedo = np.broadcast_to(np.asarray(albedo, dtype=np.float64), (g, g, 3)).copy()
    return MaterialMaps(height=np.asarray(height, dtype=np.float64), albedo=albedo,
                        alpha=np.full((g, g), alpha), f0=np.full((g, g), f0), coat=np.full((g, g), coat),
                        coat_alpha=coat_alpha, coat_f0=coat_f0)


def _plateau(g, x0, x1, y0, y1, h):
    """Height field (G, G) with a raised rectangle [x0, x1) x [y0, y1) (uv) of height h on a flat floor."""
    c = (np.arange(g) + 0.5) / g
    u, v = np.meshgrid(c, c)
    return np.where((u >= x0) & (u < x1) & (v >= y0) & (v < y1), h, 0.0)


def _ggx_reference(w_view, w_light, albedo, alpha, f0, coat=0.0, coat_alpha=0.05, coat_f0=0.04):
    """pi * f_r of a flat GGX + Lambert (+ clear coat) surface, float64 closed form."""
    v, l = np.asarray(w_view, float), np.asarray(w_light, float)
    h = (v + l) / np.linalg.norm(v + l)
    cv, cl, ch, cd = v[2], l[2], h[2], float(v @ h)

    def lam(c, a):  # Smith Lambda of GGX: (-1 + sqrt(1 + a^2 tan^2)) / 2
        tan2 = (1.0 - c * c) / (c * c)
        return 0.5 * (-1.0 + math.sqrt(1.0 + a * a * tan2))

    def spec(a, F0):
        d = a * a / (math.pi * (ch * ch * (a * a - 1.0) + 1.0) ** 2)
        g = 1.0 / (1.0 + lam(cl, a)) / (1.0 + lam(cv, a))
        f = F0 + (1.0 - F0) * (1.0 - cd) ** 5
        return d * g * f / (4.0 * cl * cv)

    base = np.asarray(albedo, float) / math.pi + spec(alpha, f0)
    fc = lambda c: coat_f0 + (1.0 - coat_f0) * (1.0 - c) ** 5  # noqa: E731
    coated = spec(coat_alpha, coat_f0) + (1.0 - fc(cl)) * (1.0 - fc(cv)) * base
    return math.pi * (coat * coated + (1.0 - coat) * base)


# ----------------------------------------------------------------------------- flat case = analytic BRDF
@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("coat", [0.0, 0.7])
def test_flat_height_field_reduces_to_closed_form_ggx(coat, backend):
    g = 16
    albedo, alpha, f0 = (0.6, 0.3, 0.1), 0.25, 0.05
    maps = _maps(np.zeros((g, g)), albedo, alpha, f0, coat=coat, coat_alpha=0.08, coat_f0=0.045)
    r = HeightFieldRenderer(maps, g, backend=backend)
    rng = np.random.default_rng(1)
    views = spherical_to_direction(rng.uniform(0, 80, 6), rng.uniform(0, 360, 6))
    lights = spherical_to_direction(np.r_[rng.uniform(0, 80, 7), 0.0, 75.0], np.r_[rng.uniform(0, 360, 7), 0, 10])
    for v in views:
        imgs = r.render(v, lights).numpy()
        # a flat surface is uniform
        assert np.ptp(imgs.reshape(len(lights), -1, 3), axis=1).max() < 1e-5
        for k, l in enumerate(lights):
            ref = _ggx_reference(v, l, albedo, alpha, f0, coat, 0.08, 0.045)
            np.testing.assert_allclose(imgs[k, 3, 5], ref, rtol=2e-4, atol=1e-6)


def test_flat_case_is_reciprocal():
    """Swapping view and light leaves a flat GGX/Lambert/coat surface's value unchanged."""
    g = 8
    r = HeightFieldRenderer(_maps(np.zeros((g, g)), coat=0.5), g)
    rng = np.random.default_rng(2)
    dirs = spherical_to_direction(rng.uniform(0, 75, 8), rng.uniform(0, 360, 8))
    table = np.stack([r.render(v, dirs).numpy()[:, 0, 0] for v in dirs])  # [view, light, rgb]
    np.testing.assert_allclose(table, table.transpose(1, 0, 2), rtol=1e-5)


@pytest.mark.parametrize("name", ["stone", "woven_fabric"])
def test_tile_averaged_values_are_nearly_reciprocal(name):
    """With relief, single texels are not reciprocal (shadowing and masking differ), but the
    macro BRDF -- the tile average -- is, typically up to a few percent: shadows and masking are modelled
    alike and the macro cos(theta_light) is divided out. (Without that division the asymmetry is
    cos(theta_view) / cos(theta_light), tens of percent.)"""
    btf = simulated_btf(name, size=32)
    rng = np.random.default_rng(0)
    asym = []
    for _ in range(16):
        v, l = (int(i) for i in rng.integers(0, btf.n_views, 2))
        a, b = btf.image(v, l).mean((0, 1)), btf.image(l, v).mean((0, 1))
        asym.append(np.abs(a - b).max() / max(a.max(), b.max()))
    assert np.median(asym) < 0.05 and max(asym) < 0.35   # worst pairs: both grazing, 32 point samples
    # single texels are not reciprocal with relief
    v, l = btf.nearest_view([0.5, 0, 0.866]), btf.nearest_light([-0.9, 0.0, 0.26])
    assert np.abs(btf.image(v, l) - btf.image(l, v)).max() > 0.05


@pytest.mark.parametrize("name", ["stone", "lacquered_wood"])
def test_numba_kernel_matches_torch_reference(name):
    """The fused CPU kernel computes the same values as the whole-array torch path (any device)."""
    maps = build_material(name, 32 * 3, seed=0)
    ref = HeightFieldRenderer(maps, 32, backend="torch")
    fast = HeightFieldRenderer(maps, 32, backend="numba")
    btf = simulated_btf(name, size=32)
    for v in (0, 37, 80):
        a = ref.render(btf.views[v], btf.lights).numpy()
        b = fast.render(btf.views[v], btf.lights).numpy()
        np.testing.assert_allclose(b, a, rtol=2e-4, atol=1e-5 * float(a.max()))


def test_bilinear_taps_agree_with_fetch_wrap():
    from dynbtf.data.simulator.geometry import bilinear_taps, interpolate_taps
    from dynbtf.texture import fetch_wrap

    g = 12
    field = torch.rand(g, g, 2, generator=torch.Generator().manual_seed(0))
    uv = torch.rand(500, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 3.0 - 1.0
    taps, w = bilinear_taps(uv, g)
    ours = interpolate_taps(field.reshape(-1, 2).T.contiguous(), taps, w).T
    torch.testing.assert_close(ours, fetch_wrap(field, uv), rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------- cast shadows
def test_shadow_of_a_plateau_has_the_closed_form_length():
    g, h, theta = 128, 0.05, 60.0
    height = torch.as_tensor(_plateau(g, 0.45, 0.55, 0.0, 1.0, h))  # a ridge along v
    light = spherical_to_direction(np.array(theta), np.array(0.0))   # from +u: shadow falls towards -u
    vis = light_visibility(height, light, spread_deg=1.0).numpy()
    length = h * math.tan(math.radians(theta))                         # 0.0866 uv = 11 texels
    u = (np.arange(g) + 0.5) / g
    row = vis[g // 2]
    shadowed = (u > 0.45 - length + 1.5 / g) & (u < 0.45 - 1.0 / g)
    lit = (u < 0.45 - length - 1.5 / g) | (u > 0.56)
    assert row[shadowed].max() < 0.05
    assert row[lit].min() > 0.95
    # a light from the other side casts the shadow on the other side
    vis_other = light_visibility(height, spherical_to_direction(np.array(theta), np.array(180.0))).numpy()[g // 2]
    assert vis_other[shadowed].min() > 0.95


def test_grazing_light_darkens_texels_compared_to_no_shadows():
    maps = build_material("stone", 64, seed=0)
    with_shadows = HeightFieldRenderer(maps, 64)
    without = HeightFieldRenderer(maps, 64, shadows=False)
    view = [0.0, 0.0, 1.0]
    lights = spherical_to_direction(np.array([0.0, 75.0]), np.array([0.0, 30.0]))
    a, b = with_shadows.render(view, lights).numpy(), without.render(view, lights).numpy()
    lum_a, lum_b = a.mean(-1), b.mean(-1)
    darker = lum_a < 0.5 * lum_b
    assert darker[1].mean() > 0.10            # a grazing light casts shadows over many texels
    assert darker[0].mean() == 0.0            # a light at the zenith casts none
    assert (lum_a <= lum_b + 1e-6).all()      # shadows never brighten


# ----------------------------------------------------------------------------- parallax and masking
def test_parallax_shift_and_masking_of_a_plateau():
    g, h, theta = 64, 0.05, 60.0
    height = _plateau(g, 0.4, 0.6, 0.3, 0.7, h)
    c = (np.arange(g) + 0.5) / g
    u, v = np.meshgrid(c, c)
    albedo = np.where((height > 0)[..., None], [0.8, 0.05, 0.05], [0.05, 0.05, 0.8])
    marker = (u >= 0.34) & (u < 0.38) & (v >= 0.3) & (v < 0.7)       # green strip just before the plateau
    albedo[marker] = [0.05, 0.8, 0.05]
    maps = _maps(height)
    maps.albedo = albedo
    r = HeightFieldRenderer(maps, g, interreflection=False)
    zenith = np.array([[0.0, 0.0, 1.0]])
    top_view = r.render([0.0, 0.0, 1.0], zenith).numpy()[0]
    w_view = spherical_to_direction(np.array(theta), np.array(0.0))    # camera towards +u
    side_view = r.render(w_view, zenith).numpy()[0]

    def red_columns(img):
        red = (img[..., 0] > 2 * img[..., 2]) & (img[..., 0] > 2 * img[..., 1])
        cols = np.nonzero(red[g // 2])[0]
        return cols.min(), cols.max()

    shift = h * math.tan(math.radians(theta)) * g                       # 5.5 texels towards -u
    # the plateau's far edge (whose wall faces away from the camera) moves by -h tan(theta);
    # at the near edge the wall facing the camera becomes visible, so only the far edge is sharp
    (a0, _), (b0, _) = red_columns(top_view), red_columns(side_view)
    assert abs((b0 - a0) + shift) <= 1.0
    # the green strip behind the plateau (seen from the camera) is hidden at grazing view
    def green(img):
        return ((img[..., 1] > 2 * img[..., 0]) & (img[..., 1] > 2 * img[..., 2]))[20:44].sum()
    assert green(top_view) > 20 and green(side_view) == 0
    # the traced hit points on the plateau top are displaced by exactly h tan(theta)
    hit_uv, hit_z = trace_view(torch.as_tensor(height, dtype=torch.float32), w_view)
    on_top = hit_z.numpy() > 0.99 * h
    texel_u = np.tile(c, g)
    np.testing.assert_allclose(hit_uv.numpy()[on_top, 0] - texel_u[on_top], shift / g, atol=1e-3)


# ----------------------------------------------------------------------------- determinism, tiling, resolution
def test_same_seed_identical_bytes_other_seed_different():
    a = simulated_btf("leather", size=16, seed=3)
    b = simulated_btf("leather", size=16, seed=3)
    c = simulated_btf("leather", size=16, seed=4)
    for v, l in [(0, 0), (40, 7), (80, 80)]:
        assert a.image(v, l).tobytes() == b.image(v, l).tobytes()
        assert a.image(v, l).tobytes() != c.image(v, l).tobytes()


def test_derive_rng_streams_are_fixed():
    # PCG64 streams are specified bit for bit; these numbers must never change
    x = derive_rng(7, "stone/pebbles").random(3)
    y = derive_rng(7, "stone/pebbles").random(3)
    z = derive_rng(7, "stone/grain").random(3)
    assert np.array_equal(x, y) and not np.array_equal(x, z)


@pytest.mark.parametrize("name", list(MATERIALS))
def test_material_height_field_tiles_seamlessly(name):
    maps = build_material(name, 128, seed=1)
    h = maps.height
    neighbour = np.abs(np.diff(h, axis=1)).mean()
    seam = np.abs(h[:, 0] - h[:, -1]).mean()
    assert seam < 2.0 * neighbour
    neighbour_v = np.abs(np.diff(h, axis=0)).mean()
    seam_v = np.abs(h[0, :] - h[-1, :]).mean()
    assert seam_v < 2.0 * neighbour_v
    for field in (maps.albedo[..., 1], maps.alpha):
        assert np.abs(field[:, 0] - field[:, -1]).mean() < 2.0 * np.abs(np.diff(field, axis=1)).mean() + 1e-12


@pytest.mark.parametrize("name", list(MATERIALS))
def test_material_is_resolution_independent(name):
    """The same continuous material sampled on a 3x finer grid (up to the mean height)."""
    coarse, fine = build_material(name, 32, seed=2), build_material(name, 96, seed=2)
    sub = fine.height[1::3, 1::3]
    np.testing.assert_allclose(coarse.height - coarse.height.mean(), sub - sub.mean(), atol=1e-9)
    np.testing.assert_allclose(coarse.albedo, fine.albedo[1::3, 1::3], atol=1e-9)


# ----------------------------------------------------------------------------- structured: lattice + variation
#: Element lattice of the structured materials: two basis vectors (du, dv) in uv. Tiles: 4 x 4 per repeat;
#: bricks: 1/4 x 1/8 repeat in running bond, odd courses shifted half a brick, so (1/8, 1/8) is a lattice
#: vector and (0, 1/8) -- one course straight up -- is not.
LATTICES = {
    "ceramic_tiles": ((0.25, 0.0), (0.0, 0.25)),
    "brick_wall": ((0.25, 0.0), (0.125, 0.125)),
}


def _autocorrelation(x):
    """Circular autocorrelation of a (G, G) field, normalized to 1 at lag 0; [dy, dx] = lag (rows = v)."""
    x = x - x.mean()
    f = np.fft.fft2(x)
    return np.real(np.fft.ifft2(f * np.conj(f))) / (x.var() * x.size)


@pytest.mark.parametrize("grid", [64, 128])
@pytest.mark.parametrize("name", list(LATTICES))
def test_structured_material_has_its_element_lattice_with_per_element_variation(name, grid):
    """The albedo's and height's strongest autocorrelation peaks (local maxima off the origin) lie on the
    element lattice, and its basis vectors correlate clearly better than any off-lattice peak and than
    half a basis vector; yet the maps are not periodic at the element period (every element differs)."""
    maps = build_material(name, grid, seed=1)
    basis = [(round(du * grid), round(dv * grid)) for du, dv in LATTICES[name]]   # (dx, dy) texels
    assert all(abs(du * grid - dx) < 1e-9 and abs(dv * grid - dy) < 1e-9
               for (du, dv), (dx, dy) in zip(LATTICES[name], basis))             # whole texels at this grid
    lattice = {((i * basis[0][0] + j * basis[1][0]) % grid, (i * basis[0][1] + j * basis[1][1]) % grid)
               for i in range(grid) for j in range(grid)}
    assert len(lattice) == (16 if name == "ceramic_tiles" else 32)                # elements per repeat
    luminance = maps.albedo.mean(-1)
    for field in (luminance, maps.height):
        c = _autocorrelation(field)
        neighbours = [np.roll(c, (a, b), (0, 1)) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
        peak = np.all([c > n for n in neighbours], axis=0)
        peak[0, 0] = False
        iy, ix = np.nonzero(peak)
        on = np.array([(x, y) in lattice for x, y in zip(ix, iy)])
        strongest = int(np.argmax(c[iy, ix]))
        assert on[strongest], (ix[strongest], iy[strongest])
        at_basis = min(c[dy % grid, dx % grid] for dx, dy in basis)
        assert all(peak[dy % grid, dx % grid] for dx, dy in basis)                # peaks at the basis vectors
        off = c[iy[~on], ix[~on]].max() if (~on).any() else -1.0
        assert at_basis > off + 0.05
        half = max(c[(dy // 2) % grid, (dx // 2) % grid] for dx, dy in basis)
        assert at_basis > half + 0.15
        # per-element variation: shifting by one element changes the maps (only the full repeat is a period)
        assert at_basis < 0.995
        for dx, dy in basis:
            moved = np.roll(field, (-dy, -dx), (0, 1))
            assert np.abs(field - moved).mean() > 0.1 * np.abs(field - field.mean()).mean()
    # element by element: the colour around each element's centre varies (moderately: one material)
    box = sum(np.roll(luminance, (a, b), (0, 1)) for a in range(-2, 3) for b in range(-2, 3)) / 25.0
    x0, y0 = grid // 8, (grid // 8 if name == "ceramic_tiles" else grid // 16)    # centre of element (0, 0)
    centres = np.array([box[(y0 + y) % grid, (x0 + x) % grid] for x, y in lattice])
    spread = centres.std() / centres.mean()
    assert 0.04 < spread < 0.25, spread


@pytest.mark.parametrize("name", list(LATTICES))
def test_structured_material_is_deterministic_per_seed(name):
    a, b, c = build_material(name, 64, seed=3), build_material(name, 64, seed=3), build_material(name, 64, seed=4)
    for field in ("height", "albedo", "alpha", "f0", "coat"):
        assert np.array_equal(getattr(a, field), getattr(b, field))
    assert (a.coat_alpha, a.coat_f0) == (b.coat_alpha, b.coat_f0)
    assert not np.array_equal(a.albedo, c.albedo) and not np.array_equal(a.height, c.height)
    # another seed varies the elements, not the lattice: the joints stay where they are
    joints = lambda m: m.height < m.height.min() + 0.5 * np.ptp(m.height)      # noqa: E731
    assert (joints(a) == joints(c)).mean() > 0.97


def test_noise_is_periodic_and_normalized():
    n = fourier_noise(64, derive_rng(0, "t"), k_max=8)
    assert abs(n.mean()) < 1e-9 and abs(n.std() - 1.0) < 1e-9
    cells = worley(48, derive_rng(0, "w"), cells=4)
    assert cells.f1.min() >= 0 and (cells.f2 >= cells.f1).all()
    # wrap: the distance field is continuous across the seam
    assert np.abs(cells.f1[:, 0] - cells.f1[:, -1]).max() < 4 * np.abs(np.diff(cells.f1, axis=1)).max()


# ----------------------------------------------------------------------------- the BTF source
def test_source_shape_dtype_range_and_metadata():
    btf = SimulatedBTF("woven_fabric", size=16, grid="ubo2014", seed=0)
    assert btf.shape == (151, 151, 16, 16)
    assert tabulation_size(16) == 80
    img = btf.image(150, 3)
    assert img.shape == (16, 16, 3) and img.dtype == np.float32
    imgs = btf.view_images(60)
    assert imgs.shape == (151, 16, 16, 3) and np.isfinite(imgs).all() and imgs.min() >= 0.0
    np.testing.assert_allclose(imgs[3], btf.image(60, 3), rtol=1e-5, atol=1e-7)
    assert 0.02 < float(imgs.mean()) < 2.0
    assert btf.metadata["material"] == "woven_fabric" and btf.metadata["grid"] == "ubo2014"
    samples = btf.sample(50, np.random.default_rng(0))
    assert samples.rgb.shape == (50, 3) and np.isfinite(samples.rgb).all()


def test_images_show_view_dependent_structure():
    """Not a per-texel BRDF: at a fixed light, the spatial pattern changes with the view (parallax)."""
    btf = simulated_btf("stone", size=32)
    normal = btf.image(0, 0).mean(-1)
    grazing = btf.image(btf.nearest_view(spherical_to_direction(np.array(75.0), np.array(0.0))), 0).mean(-1)
    corr = np.corrcoef(normal.ravel(), grazing.ravel())[0, 1]
    assert corr < 0.8


@pytest.mark.parametrize("kwargs, words", [
    (dict(material="velvet"), ["velvet", "stone", "leather", "lacquered_wood", "woven_fabric", "ceramic_tiles",
                               "brick_wall"]),
    (dict(material="stone", grid="ubo1999"), ["ubo1999", "ubo2003", "ubo2014"]),
    (dict(material="stone", size=0), ["size", "0"]),
    (dict(material="stone", size=2.5), ["size"]),
    (dict(material="stone", size="big"), ["size", "big"]),
    (dict(material="stone", seed=-1), ["seed"]),
])
def test_bad_arguments_raise_input_error(kwargs, words):
    with pytest.raises(InputError) as e:
        simulated_btf(**kwargs)
    for w in words:
        assert w in str(e.value)


def test_bad_indices_raise():
    btf = simulated_btf("stone", size=8)
    with pytest.raises(DynBTFError, match="view index 81"):
        btf.image(81, 0)
    with pytest.raises(DynBTFError, match="light index"):
        btf.view_images(0, [0, 99])


# ----------------------------------------------------------------------------- stored BTF and command line
def test_simulate_command_writes_a_stored_btf_that_reads_back(tmp_path, capsys):
    from dynbtf.cli.main import main
    from dynbtf.data.open import open_btf

    out = tmp_path / "fabric.dbtf"
    assert main(["simulate", "woven_fabric", "-o", str(out), "--size", "8", "--seed", "5",
                 "--dtype", "float32", "--quiet"]) == 0
    assert "wrote" in capsys.readouterr().out
    stored = open_btf(str(out))
    source = simulated_btf("woven_fabric", size=8, seed=5)
    assert stored.shape == source.shape == (81, 81, 8, 8)
    np.testing.assert_allclose(stored.views, source.views, atol=1e-7)
    for v, l in [(0, 0), (33, 80), (80, 12)]:
        np.testing.assert_allclose(stored.image(v, l), source.image(v, l), rtol=1e-6, atol=1e-7)
    # the spec form opens the same simulated BTF
    spec = open_btf("sim:woven_fabric?size=8&seed=5")
    assert spec.image(33, 80).tobytes() == source.image(33, 80).tobytes()


def test_simulate_command_lists_materials_and_reports_bad_input(tmp_path, capsys):
    from dynbtf.cli.main import main

    assert main(["simulate", "--list"]) == 0
    listing = capsys.readouterr().out
    for name in MATERIALS:
        assert name in listing
    assert main(["simulate", "velvet", "-o", str(tmp_path / "x.dbtf")]) == 2
    err = capsys.readouterr().err
    assert "velvet" in err and "stone" in err and "Traceback" not in err
    assert main(["simulate", "stone", "-o", str(tmp_path / "x.dbtf"), "--size", "0"]) == 2
    assert "size" in capsys.readouterr().err
    assert main(["simulate", "stone"]) == 2
    assert "--output" in capsys.readouterr().err
    assert not (tmp_path / "x.dbtf").exists()


def test_numba_marching_matches_torch_shifts(monkeypatch):
    """Traces and horizons of the numba kernels (CPU) equal the whole-field torch versions (other devices)."""
    from dynbtf.data.simulator import geometry

    height = torch.as_tensor(build_material("stone", 96, seed=0).height, dtype=torch.float32)
    views = spherical_to_direction(np.array([0.0, 30.0, 75.0]), np.array([0.0, 200.0, 33.0]))
    fast = [geometry.trace_view(height, w, 3) for w in views]
    fast_h = geometry.light_visibility(height, views[2])
    monkeypatch.setattr(geometry, "_TORCH_MARCHING", True)
    ref = [geometry.trace_view(height, w, 3) for w in views]
    ref_h = geometry.light_visibility(height, views[2])
    for (uv_a, z_a), (uv_b, z_b) in zip(fast, ref):
        torch.testing.assert_close(z_a, z_b, rtol=0, atol=1e-6)
        torch.testing.assert_close(uv_a, uv_b, rtol=0, atol=1e-5)
    torch.testing.assert_close(fast_h, ref_h, rtol=0, atol=1e-3)
    assert float(ref_h.min()) < 0.5 < float(ref_h.max())      # the case has shadows


def test_interrupted_write_of_a_simulated_btf_resumes(tmp_path):
    """The simulated source's metadata is stable, so write_stored resumes where it stopped."""
    from dynbtf.data.stored import read_stored, write_stored

    out = tmp_path / "leather.dbtf"

    class Stop(Exception):
        pass

    def stop_after_some(done):
        if done >= 81 * 10:
            raise Stop

    with pytest.raises(Stop):
        write_stored(out, simulated_btf("leather", size=8, seed=1), dtype="float32", progress=False,
                     callback=stop_after_some)
    assert not out.exists()
    seen = []
    write_stored(out, simulated_btf("leather", size=8, seed=1), dtype="float32", progress=False,
                 callback=seen.append)
    assert seen[0] > 81 * 10 - 1            # resumed, not restarted
    stored, fresh = read_stored(out), simulated_btf("leather", size=8, seed=1)
    for v, l in [(2, 3), (50, 60)]:
        np.testing.assert_array_equal(stored.image(v, l), fresh.image(v, l))


def test_relief_scales_the_height_field_and_its_shadows():
    """relief multiplies the height field: 0 is flat (no cast shadows: a grazing light darkens no texel
    beyond the flat-surface shading), 1 is the default material byte for byte, and the spec form parses it."""
    from dynbtf.data.open import open_btf

    default = simulated_btf("stone", size=16)
    same = open_btf("sim:stone?size=16&relief=1")
    half = open_btf("sim:stone?size=16&relief=0.5")
    flat = simulated_btf("stone", size=16, relief=0.0)
    assert default.name == same.name == "sim:stone" and half.name == "sim:stone?relief=0.5"
    np.testing.assert_array_equal(half.renderer.maps.height, 0.5 * default.renderer.maps.height)
    assert not flat.renderer.maps.height.any() and half.metadata["relief"] == 0.5
    np.testing.assert_array_equal(default.image(3, 40), same.image(3, 40))
    # light at theta 75: with relief, shadowed texels fall far below the flat surface's values
    grazing = int(np.argmax(np.arccos(np.clip(default.lights[:, 2], -1, 1))))
    ratio_flat = flat.image(0, grazing).mean(-1) / flat.image(0, 0).mean(-1)
    ratio_deep = default.image(0, grazing).mean(-1) / default.image(0, 0).mean(-1)
    assert (ratio_deep < 0.5 * ratio_flat.min()).mean() > 0.1  # >10% of texels in cast shadow
    with pytest.raises(InputError, match="relief"):
        simulated_btf("stone", size=16, relief=-1)
    with pytest.raises(InputError, match="relief"):
        open_btf("sim:stone?relief=deep")
