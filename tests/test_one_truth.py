"""One truth per formula: each formula of a query (uv -> RGB) has one float64 reference, written here
from its definition, and every backend that computes it is held to that reference.

Formulas and backends:

* integer hash of lattice vertices -- numpy/torch (``synthesis.hash``), numba (``synthesis.kernels``),
  Dr.Jit (``render.drjit_synthesis``);
* triangle lattice (vertices and barycentrics) -- torch (``synthesis.lattice``), numba, Dr.Jit;
* Rusinkiewicz half/difference vectors and angular-plane coordinates -- numpy and torch
  (``conventions``), numba (``fast_decode``, inside layer 1), Dr.Jit (``render.drjit_ops``);
* bilinear taps (periodic positional fetch, clamped/wrapped angular fetch) -- torch (``texture``),
  numba (``synthesis.kernels.tile_fetch``, ``fast_decode``), Dr.Jit;
* the decoder MLP -- torch, numba layer 1 + torch (the synthesized BTF's fast path), Dr.Jit, and the
  C++ training kernel (its loss);
* every dynamic synthesis method (tile, linear, hist, hex) -- torch reference path, numba kernel, Dr.Jit.

The hash and lattice references are the exact-integer / exact-rational ones of
``synthesis_reference.py``; the others are below, in float64 NumPy, from the definitions in
``dynbtf.conventions`` and ``dynbtf.texture`` (rotation matrices, explicit 2 x 2 texel loops).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dynbtf.conventions import POLE_RADIUS
from synthesis_reference import exact_lattice, reference_hash, smooth_lognormal

RNG = np.random.default_rng(20261124)


# ---------------------------------------------------------------------------- float64 references
def exact_triangle(u: float, v: float) -> dict[tuple[int, int], float]:
    """The lattice triangle containing ``(u, v)``: ``{vertex: barycentric}`` from the exact lattice
    coordinates (``k = (2 sqrt(3) u - 2 v, 4 v)``, 40-digit sqrt(3)); lower triangle when ``1 - fx - fy > 0``."""
    (bx, by), (fx, fy) = exact_lattice(u, v)
    if 1.0 - fx - fy > 0.0:
        return {(bx, by): 1.0 - fx - fy, (bx, by + 1): fy, (bx + 1, by): fx}
    return {(bx + 1, by + 1): fx + fy - 1.0, (bx + 1, by): 1.0 - fy, (bx, by + 1): 1.0 - fx}


def reference_half_diff(w_view: np.ndarray, w_light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``h = normalize(w_view + w_light)``; ``d = R_y(-theta_h) R_z(-phi_h) w_light`` with explicit matrices."""
    h_all, d_all = [], []
    for wv, wl in zip(w_view.astype(np.float64), w_light.astype(np.float64)):
        h = wv + wl
        h = h / np.linalg.norm(h)
        theta, phi = math.acos(min(1.0, max(-1.0, h[2]))), math.atan2(h[1], h[0])
        if math.hypot(h[0], h[1]) < 1e-12:
            phi = 0.0
        c, s = math.cos(-phi), math.sin(-phi)
        rot_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        c, s = math.cos(-theta), math.sin(-theta)
        rot_y = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        h_all.append(h)
        d_all.append(rot_y @ rot_z @ wl)
    return np.array(h_all), np.array(d_all)


def reference_angular_coords(w: np.ndarray) -> np.ndarray:
    """``(s, t) = (theta / 90 deg clamped to [0, 1], phi / 360 deg in [0, 1))``, phi = 0 at the pole."""
    out = []
    for x, y, z in w.astype(np.float64):
        theta = math.degrees(math.acos(min(1.0, max(-1.0, z))))
        phi = 0.0 if x * x + y * y < POLE_RADIUS ** 2 else math.degrees(math.atan2(y, x)) % 360.0
        out.append((min(1.0, max(0.0, theta / 90.0)), phi / 360.0))
    return np.array(out)


def reference_bilinear(plane: np.ndarray, x: np.ndarray, y: np.ndarray, *, wrap_x: bool, wrap_y: bool) -> np.ndarray:
    """Bilinear value at continuous texel coordinates (texel ``[i, j]`` centred at ``(x, y) = (j, i)``):
    periodic or clamped addressing per axis; one explicit 2 x 2 loop per query."""
    h, w = plane.shape[:2]
    out = np.zeros((len(x), plane.shape[2]))
    for q, (xq, yq) in enumerate(zip(x.astype(np.float64), y.astype(np.float64))):
        x0, y0 = math.floor(xq), math.floor(yq)
        for dy in (0, 1):
            for dx in (0, 1):
                weight = (xq - x0 if dx else 1.0 - (xq - x0)) * (yq - y0 if dy else 1.0 - (yq - y0))
                col = (x0 + dx) % w if wrap_x else min(max(x0 + dx, 0), w - 1)
                row = (y0 + dy) % h if wrap_y else min(max(y0 + dy, 0), h - 1)
                out[q] += weight * plane[row, col].astype(np.float64)
    return out


def reference_fetch_wrap(plane: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = plane.shape[:2]
    frac = uv - np.floor(uv)
    return reference_bilinear(plane, frac[:, 0] * w - 0.5, frac[:, 1] * h - 0.5, wrap_x=True, wrap_y=True)


def reference_fetch_angular(plane: np.ndarray, st: np.ndarray) -> np.ndarray:
    rs, rt = plane.shape[:2]
    s = np.clip(st[:, 0], 0.0, 1.0)
    t = st[:, 1] - np.floor(st[:, 1])
    return reference_bilinear(plane, t * rt - 0.5, s * rs - 0.5, wrap_x=True, wrap_y=False)


def reference_mlp(x: np.ndarray, layers, slope: float) -> np.ndarray:
    """LeakyReLU MLP in float64: ``layers`` is a list of ``(weight (out, in), bias (out,))``."""
    x = x.astype(np.float64)
    for k, (weight, bias) in enumerate(layers):
        x = x @ np.asarray(weight, np.float64).T + np.asarray(bias, np.float64)
        if k < len(layers) - 1:
            x = np.where(x >= 0, x, slope * x)
    return x


def hemisphere(n: int, rng=RNG) -> np.ndarray:
    """Unit directions of the upper hemisphere, the first one the normal (a pole case)."""
    w = rng.normal(size=(n, 3))
    w[:, 2] = np.abs(w[:, 2]) + 0.05
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    w[0] = (0.0, 0.0, 1.0)
    return w


def circular_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``|a - b|`` on the unit circle of ``t = phi / 360 deg``."""
    d = np.abs(a - b) % 1.0
    return np.minimum(d, 1.0 - d)


# ---------------------------------------------------------------------------- Dr.Jit helpers
@pytest.fixture(scope="module")
def mi():
    mitsuba = pytest.importorskip("mitsuba")
    pytest.importorskip("drjit")
    from dynbtf.render.mitsuba.bsdf import plugin_variants

    if "llvm_ad_rgb" not in plugin_variants():  # pragma: no cover - no LLVM on this machine
        pytest.skip("Mitsuba variant llvm_ad_rgb not usable here")
    mitsuba.set_variant("llvm_ad_rgb")
    return mitsuba


def as_numpy(values) -> np.ndarray:
    """A Dr.Jit array, or a list of them, as float64 ``(N,)`` or ``(N, k)``."""
    if isinstance(values, (list, tuple)):
        return np.stack([np.array(v, dtype=np.float64) for v in values], axis=-1)
    return np.array(values, dtype=np.float64)


def vector3(mi, w: np.ndarray):
    return mi.Vector3f(*(mi.Float(np.ascontiguousarray(w[:, k], dtype=np.float32)) for k in range(3)))


# ---------------------------------------------------------------------------- hash
def test_hash_in_drjit_is_the_reference_hash(mi):
    from dynbtf.render.mitsuba import drjit_synthesis
    from dynbtf.synthesis.hash import vertex_offsets

    vx = RNG.integers(-2 ** 31, 2 ** 31, 300)
    vy = RNG.integers(-2 ** 31, 2 ** 31, 300)
    vx[:4], vy[:4] = [0, -1, 2 ** 31 - 1, -2 ** 31], [0, 1, -2 ** 31, 7]
    for seed in (0, 12345, 2 ** 32 - 1):
        got = np.array(drjit_synthesis.hash_vertex(mi.Int32(vx), mi.Int32(vy), seed), dtype=np.int64)
        want = np.array([reference_hash(int(a), int(b), seed) for a, b in zip(vx, vy)], dtype=np.int64)
        np.testing.assert_array_equal(got, want)
        ox, oy = drjit_synthesis.vertex_offsets(mi.Int32(vx), mi.Int32(vy), seed, 37, 29)
        want_x, want_y = vertex_offsets(torch.from_numpy(vx), torch.from_numpy(vy), seed, 37, 29)
        np.testing.assert_array_equal(np.array(ox, dtype=np.int64), want_x.numpy())
        np.testing.assert_array_equal(np.array(oy, dtype=np.int64), want_y.numpy())


# ---------------------------------------------------------------------------- lattice
@pytest.mark.parametrize("offset", [0.0, -37.25, 1e6 + 0.5])
def test_lattice_in_drjit_is_the_exact_lattice(mi, offset):
    from dynbtf.render.mitsuba import drjit_synthesis
    from dynbtf.synthesis.lattice import triangle_lattice

    uv = RNG.random((200, 2)) * 3.0 + offset
    verts, bary = drjit_synthesis.triangle_lattice(mi.Float64(uv[:, 0]), mi.Float64(uv[:, 1]))
    got_vertices = np.stack([np.stack([np.array(x, np.int64), np.array(y, np.int64)], -1) for x, y in verts], 1)
    got_bary = as_numpy(bary)
    torch_vertices, torch_bary = triangle_lattice(torch.from_numpy(uv))
    for q, (u, v) in enumerate(uv):
        want = exact_triangle(float(u), float(v))
        # the three vertices are the same set; each carries its own barycentric
        got = {tuple(vtx): b for vtx, b in zip(got_vertices[q].tolist(), got_bary[q])}
        assert got.keys() == want.keys(), (u, v)
        assert max(abs(got[k] - want[k]) for k in want) < 1e-9
        via_torch = {tuple(vtx): float(b) for vtx, b in zip(torch_vertices[q].tolist(), torch_bary[q].tolist())}
        assert via_torch.keys() == want.keys() and max(abs(via_torch[k] - want[k]) for k in want) < 1e-9


# ---------------------------------------------------------------------------- Rusinkiewicz angles
def test_half_diff_numpy_and_torch_are_the_rotation_matrices():
    from dynbtf.conventions import angular_plane_coords, half_diff_from_view_light

    wv, wl = hemisphere(400), hemisphere(400)
    wl[1] = wv[1]  # h = w_view = w_light
    h_ref, d_ref = reference_half_diff(wv, wl)
    h, d = half_diff_from_view_light(wv, wl)
    np.testing.assert_allclose(h, h_ref, atol=1e-12)
    np.testing.assert_allclose(d, d_ref, atol=1e-12)
    h32, d32 = half_diff_from_view_light(torch.from_numpy(wv).float(), torch.from_numpy(wl).float())
    np.testing.assert_allclose(h32.numpy(), h_ref, atol=2e-6)
    np.testing.assert_allclose(d32.numpy(), d_ref, atol=2e-6)
    for w in (h_ref, d_ref):
        st_ref, st = reference_angular_coords(w), angular_plane_coords(w)
        np.testing.assert_allclose(st[:, 0], st_ref[:, 0], atol=1e-12)
        assert circular_difference(st[:, 1], st_ref[:, 1]).max() < 1e-12


def test_half_diff_in_drjit_is_the_rotation_matrices(mi):
    from dynbtf.render.mitsuba.drjit_ops import angular_coords, half_diff

    wv, wl = hemisphere(400), hemisphere(400)
    h_ref, d_ref = reference_half_diff(wv, wl)
    h, d = half_diff(vector3(mi, wv), vector3(mi, wl))
    np.testing.assert_allclose(as_numpy([h.x, h.y, h.z]), h_ref, atol=3e-6)
    np.testing.assert_allclose(as_numpy([d.x, d.y, d.z]), d_ref, atol=3e-6)
    for w in (h_ref, d_ref):
        s, t = angular_coords(vector3(mi, w))
        st_ref = reference_angular_coords(w)
        away_from_pole = w[:, 0] ** 2 + w[:, 1] ** 2 > 1e-6  # float32 input: phi is defined only away from it
        np.testing.assert_allclose(np.array(s), st_ref[:, 0], atol=2e-6)
        assert circular_difference(np.array(t, np.float64), st_ref[:, 1])[away_from_pole].max() < 2e-5


# ---------------------------------------------------------------------------- bilinear taps
def test_positional_fetch_torch_numba_drjit_are_the_bilinear_reference(mi):
    from dynbtf.render.mitsuba.drjit_ops import fetch_wrap as drjit_fetch_wrap
    from dynbtf.synthesis.kernels import tile_fetch
    from dynbtf.texture import fetch_wrap

    plane = RNG.normal(size=(7, 5, 3)).astype(np.float32)
    uv = (RNG.random((300, 2)) - 0.5) * 6.0
    uv[:4] = [[0.0, 0.0], [1.0 - 1e-9, 0.5], [-1e-9, 0.999], [0.1, 0.9]]  # seams and corners
    want = reference_fetch_wrap(plane, uv)
    np.testing.assert_allclose(fetch_wrap(torch.from_numpy(plane), torch.from_numpy(uv)).numpy(), want, atol=2e-6)
    np.testing.assert_allclose(tile_fetch(uv, plane), want, atol=2e-6)
    uv32 = uv.astype(np.float32)  # Dr.Jit fetches at float32 uv
    got = as_numpy(drjit_fetch_wrap(mi.Float(plane.ravel()), (7, 5), 3, mi.Float(uv32[:, 0]), mi.Float(uv32[:, 1])))
    np.testing.assert_allclose(got, reference_fetch_wrap(plane, uv32.astype(np.float64)), atol=2e-5)


def test_angular_fetch_torch_and_drjit_are_the_bilinear_reference(mi):
    from dynbtf.render.mitsuba.drjit_ops import fetch_angular as drjit_fetch_angular
    from dynbtf.texture import fetch_angular

    plane = RNG.normal(size=(6, 9, 4)).astype(np.float32)
    st = np.column_stack([RNG.random(300) * 1.2 - 0.1, RNG.random(300) * 3.0 - 1.0])  # s beyond [0, 1] clamps
    st[:3] = [[0.0, 0.0], [1.0, 0.999999], [0.5, -1e-9]]
    want = reference_fetch_angular(plane, st)
    np.testing.assert_allclose(fetch_angular(torch.from_numpy(plane), torch.from_numpy(st)).numpy(), want, atol=5e-6)
    st32 = st.astype(np.float32)
    got = as_numpy(drjit_fetch_angular(mi.Float(plane.ravel()), (6, 9), 4, mi.Float(st32[:, 0]),
                                       mi.Float(st32[:, 1])))
    np.testing.assert_allclose(got, reference_fetch_angular(plane, st32.astype(np.float64)), atol=2e-5)


# ---------------------------------------------------------------------------- decoder
@pytest.fixture(scope="module")
def triple_plane():
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(12, 10, positional_channels=6, angular_channels=4, hidden=16, seed=11)
    with torch.no_grad():  # angular planes with structure in every texel (initial planes may be near zero)
        model.f_h.copy_(torch.randn(model.f_h.shape, generator=torch.Generator().manual_seed(1)))
        model.f_d.copy_(torch.randn(model.f_d.shape, generator=torch.Generator().manual_seed(2)))
    return model.eval()


def _layers(decoder):
    return [(layer.weight.detach().double().numpy(), layer.bias.detach().double().numpy())
            for layer in [decoder.first, *decoder.rest]]


def reference_decode(model, features: np.ndarray, wv: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """The Triple Plane's RGB from its definition: angular inputs are bilinear fetches at the angular
    coordinates of the reference half/difference vectors, then the float64 MLP."""
    h, d = reference_half_diff(wv, wl)
    f_h = reference_fetch_angular(model.f_h.detach().numpy(), reference_angular_coords(h))
    f_d = reference_fetch_angular(model.f_d.detach().numpy(), reference_angular_coords(d))
    return reference_mlp(np.concatenate([features, f_h, f_d], axis=1), _layers(model.decoder),
                         model.decoder.negative_slope)


def _away_from_phi_seam(wv, wl, margin=1e-4):
    """Queries whose h and d are not at the pole, where float32 inputs leave phi undefined."""
    h, d = reference_half_diff(wv, wl)
    return ((h[:, :2] ** 2).sum(1) > margin) & ((d[:, :2] ** 2).sum(1) > margin)


def test_decoder_torch_and_numba_first_layer_are_the_reference(triple_plane):
    from dynbtf.decoder.fast_decode import first_layer_preactivation, fold_angular_planes

    model = triple_plane
    n = 300
    features = RNG.normal(size=(n, 6))
    wv, wl = hemisphere(n), hemisphere(n)
    keep = _away_from_phi_seam(wv, wl)
    want = reference_decode(model, features, wv, wl)
    got = model.decode(torch.from_numpy(features).float(), torch.from_numpy(wv).float(),
                       torch.from_numpy(wl).float()).detach().numpy()
    np.testing.assert_allclose(got[keep], want[keep], rtol=2e-5, atol=2e-5)  # float32 inputs and sums
    # numba: layer 1 with the angular planes folded into it, then layers 2.. in torch
    decoder = model.decoder
    w_first = decoder.first.weight.detach()
    plane_h, plane_d = fold_angular_planes(model.f_h.detach(), model.f_d.detach(), w_first[:, 6:])
    pre = first_layer_preactivation(features.astype(np.float32), w_first[:, :6].T.contiguous().numpy(),
                                    decoder.first.bias.detach().numpy(), wv.astype(np.float32),
                                    wl.astype(np.float32), plane_h, plane_d)
    got = decoder.from_first_layer(torch.from_numpy(pre)).detach().numpy()
    np.testing.assert_allclose(got[keep], want[keep], rtol=2e-5, atol=2e-5)  # float32 inputs and sums


def test_decoder_in_drjit_is_the_reference(mi, triple_plane):
    from dynbtf.render.mitsuba.drjit_ops import DrDecoder

    model = triple_plane
    n = 200
    features, angular = RNG.normal(size=(n, 6)), RNG.normal(size=(n, 8))
    want = reference_mlp(np.concatenate([features, angular], 1), _layers(model.decoder), model.decoder.negative_slope)
    rgb = DrDecoder.of(model.decoder)([mi.Float(c.astype(np.float32)) for c in features.T],
                                   [mi.Float(c.astype(np.float32)) for c in angular.T])
    np.testing.assert_allclose(as_numpy([rgb.x, rgb.y, rgb.z]), want, atol=2e-5)


def test_native_training_kernel_loss_is_the_reference_l1():
    from dynbtf.decoder.fused_mlp import native_precisions, split_mlp_l1_loss

    if "fp32" not in native_precisions():
        pytest.skip("no native kernel on this machine")
    torch.manual_seed(3)
    hidden, groups, images, texels = 32, 2, 3, 40
    layers = [torch.nn.Linear(hidden, hidden), torch.nn.Linear(hidden, hidden), torch.nn.Linear(hidden, 3)]
    positional = torch.randn(groups * texels, hidden)
    image = torch.randn(groups, images, hidden)
    target = torch.rand(images, groups * texels, 3)
    with torch.no_grad():
        got = float(split_mlp_l1_loss(positional, image, layers, 0.01, target))
    # reference: every (image b of group g, texel t of group g) through the float64 MLP
    first = (positional.double().numpy().reshape(groups, 1, texels, hidden) + image.double().numpy()[:, :, None])
    first = np.where(first >= 0, first, 0.01 * first)
    ref_layers = [(layer.weight.detach().double().numpy(), layer.bias.detach().double().numpy()) for layer in layers]
    out = reference_mlp(first.reshape(-1, hidden), ref_layers, 0.01).reshape(groups, images, texels, 3)
    want = np.abs(out.transpose(1, 0, 2, 3).reshape(images, groups * texels, 3) - target.double().numpy()).mean()
    assert got == pytest.approx(want, rel=1e-5)


# ---------------------------------------------------------------------------- every synthesis method
@pytest.mark.parametrize("method", ["tile", "linear", "hist", "hex"])
def test_every_synthesis_method_in_numba_and_drjit_is_the_torch_reference(mi, method):
    """Torch path (float64 positions) = numba kernel = Dr.Jit twin, for every dynamic method.

    Histogram blending's kernels invert the Gaussian transform through its lookup table (the method's
    definition for rendering); the reference then uses the same table, and the exact inverse is
    checked to be within the table's error bound (1% of a channel's spread).
    """
    from dynbtf.render.mitsuba.drjit_synthesis import make_dr_synthesizer
    from dynbtf.synthesis.registry import make_synthesizer
    from dynbtf.synthesis.histogram import blend_weights, variance_preserving_blend

    exemplar = smooth_lognormal(24, 20, 4, seed=4)
    reference = make_synthesizer(method, exemplar, seed=9, fast=False)  # the torch path, float64 positions
    fast = make_synthesizer(method, exemplar, seed=9, fast=True)  # the numba kernel
    uv = (RNG.random((400, 2)) - 0.5) * 50.0
    if method == "tile":  # Dr.Jit's tiling fetch takes float32 uv: every backend queries those positions
        uv = uv.astype(np.float32).astype(np.float64)
    exact = reference(torch.from_numpy(uv)).double().numpy()
    if method == "hist":
        lut = reference.prepared.extras["lut"]
        reference.blend = lambda samples, bary, uv_samples: lut(variance_preserving_blend(
            samples.double(), blend_weights(bary, reference.gamma))).float()
    want = reference(torch.from_numpy(uv)).double().numpy()
    scale = np.abs(want).max()
    if method == "hist":
        spread = exact.std(0)
        assert np.all(np.abs(want - exact).max(0) < 0.01 * spread)
    np.testing.assert_allclose(fast(torch.from_numpy(uv)).double().numpy(), want, atol=2e-5 * scale)
    twin = make_dr_synthesizer(reference)
    precise = method != "tile"
    u = mi.Float64(uv[:, 0]) if precise else mi.Float(uv[:, 0].astype(np.float32))
    v = mi.Float64(uv[:, 1]) if precise else mi.Float(uv[:, 1].astype(np.float32))
    np.testing.assert_allclose(as_numpy(twin.features(u, v)), want, atol=5e-5 * scale)


@pytest.mark.parametrize("gamma", [1000.0, 1e10, 1e300])
def test_hist_with_extreme_exponents_is_finite_and_one_sample_in_every_backend(mi, gamma):
    """``b^gamma`` underflows to 0 for all three barycentrics once gamma is large (0/0: NaN weights, and a NaN
    index into the inverse table crashed the numba kernel). The weights are ``(b / max b)^gamma``: finite for
    any gamma, and for gamma -> inf one-hot on the dominant vertex, whose sample passes through unblended."""
    from dynbtf.render.mitsuba.drjit_synthesis import make_dr_synthesizer
    from dynbtf.synthesis.registry import make_synthesizer

    exemplar = smooth_lognormal(24, 20, 4, seed=4)
    reference = make_synthesizer("hist", exemplar, seed=9, fast=False, gamma=gamma)
    fast = make_synthesizer("hist", exemplar, seed=9, fast=True, gamma=gamma, prepared=reference.prepared)
    uv = (RNG.random((400, 2)) - 0.5) * 50.0
    want = reference(torch.from_numpy(uv)).double().numpy()
    assert np.isfinite(want).all()
    scale = np.abs(want).max()
    np.testing.assert_allclose(fast(torch.from_numpy(uv)).double().numpy(), want, atol=0.01 * scale)
    twin = make_dr_synthesizer(reference)
    got = as_numpy(twin.features(mi.Float64(uv[:, 0]), mi.Float64(uv[:, 1])))
    np.testing.assert_allclose(got, want, atol=0.01 * scale)
    if gamma == 1e300:  # closed form: the dominant sample's own value (transform and inverse cancel)
        uv_samples, bary = reference.sample_positions(torch.from_numpy(uv))
        dominant = bary.argmax(-1)
        reads = uv_samples[torch.arange(len(uv)), dominant]
        from dynbtf.texture import fetch_wrap

        gaussian = fetch_wrap(reference.prepared.plane.double(), reads)
        latent = reference.prepared.extras["transform"].inverse(gaussian)
        matrix, offset = reference.output_map()
        closed = (latent.float() @ matrix + offset).double().numpy()
        np.testing.assert_allclose(want, closed, atol=1e-4 * scale)


# ---------------------------------------------------------------------------- cell quilting (struct)
@pytest.mark.parametrize("seed", [9, 2 ** 32 + 5])
def test_cell_quilting_in_numba_and_drjit_is_the_torch_reference(mi, seed):
    """struct: torch path = numba kernel = Dr.Jit twin (values to float rounding); the twin's read positions and
    chosen offset indices are the torch path's bit for bit, near the origin and 2**45 repeats from it (int64
    cell indices beyond any int32), on both sides; near cell edges neighbours' and diagonal cells' offsets are taken."""
    from dynbtf.render.mitsuba.drjit_synthesis import make_dr_synthesizer
    from dynbtf.synthesis.registry import make_synthesizer
    from dynbtf.synthesis.cell_quilting import cell_choice

    rng = np.random.default_rng(45)
    exemplar = torch.from_numpy(np.tile(rng.random((8, 8, 4)), (4, 4, 1)) + 0.1 * rng.random((32, 32, 4))).float()
    reference = make_synthesizer("struct", exemplar, seed=seed, fast=False)  # the torch path, float64 positions
    fast = make_synthesizer("struct", exemplar, seed=seed, fast=True, prepared=reference.prepared)  # numba
    tables = reference.prepared
    assert tables.count > 4 and tables.cells == (2, 2)  # a lattice to choose from, two cells per repeat
    twin = make_dr_synthesizer(reference)
    n = 4000
    for origin in (0.0, 2.0 ** 45, -(2.0 ** 45)):
        uv = origin + (rng.random((n, 2)) - 0.5) * (60.0 if origin == 0.0 else 6.0)
        u, v = mi.Float64(uv[:, 0]), mi.Float64(uv[:, 1])
        positions, chosen = reference.read_positions(torch.from_numpy(uv))
        x, y, got = twin.read_positions(u, v)
        np.testing.assert_array_equal(np.array(got, dtype=np.int64), chosen.numpy())
        np.testing.assert_allclose(np.stack([np.array(x), np.array(y)], -1), positions.numpy(), rtol=0, atol=1e-9)
        # the cells (int64 from the repeat index and the fraction) and how often a neighbour's offset is read
        whole = np.floor(uv).astype(np.int64)
        texel = np.minimum(np.floor((uv - np.floor(uv)) * 32).astype(np.int64), 31)
        cx, cy = whole[:, 0] * 2 + texel[:, 0] // 16, whole[:, 1] * 2 + texel[:, 1] // 16
        if origin != 0.0:
            assert np.abs(cx).min() > 2 ** 45 or np.abs(cy).min() > 2 ** 45
        k = tables.count

        def choice(dx, dy):
            return cell_choice(torch.from_numpy(cx + dx), torch.from_numpy(cy + dy), seed, k).numpy()

        own = choice(0, 0)
        moved = chosen.numpy() != own
        assert 0.05 < moved.mean() < 0.5, moved.mean()
        axis = np.zeros(n, bool)
        for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            axis |= chosen.numpy() == choice(dx, dy)
        assert (moved & ~axis).sum() > 20  # lanes past both cuts of a corner: the diagonal cell's offset
        want = reference(torch.from_numpy(uv)).double().numpy()
        scale = np.abs(want).max()
        np.testing.assert_allclose(fast(torch.from_numpy(uv)).double().numpy(), want, rtol=0, atol=2e-5 * scale)
        features = as_numpy(twin.features(u, v))
        np.testing.assert_allclose(features, want, rtol=0, atol=5e-5 * scale)
        np.testing.assert_array_equal(np.array(twin.channel(u, v, 2), dtype=np.float64), features[:, 2])
