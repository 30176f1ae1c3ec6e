"""One truth per formula: each formula of a query (uv -> RGB) has one float64 reference, written here
from its definition, and every backend that computes it is held to that reference.

Formulas and backends:

* triangle lattice (vertices and barycentrics) -- torch (``synthesis.lattice``), through the methods' kernels;
* Rusinkiewicz half/difference vectors and angular-plane coordinates -- numpy and torch
  (``conventions``), numba (``fast_decode``, inside layer 1);
* bilinear taps (periodic positional fetch, clamped/wrapped angular fetch) -- torch (``texture``),
  numba (``synthesis.tiling.kernel.tile_fetch``, ``fast_decode``);
* the decoder MLP -- torch, numba layer 1 + torch (the synthesized BTF's fast path), and the
  C++ training kernel (its loss);
* every dynamic synthesis method (tile, linear, hist, hex, struct, the guided ones) -- torch reference path, numba
  kernel;
* the relief march (``ParallaxTriplePlane.visible_uv``) -- torch synthesis path, numba kernel, GLSL (through its
  values) -- against the documented march in float64 through a float64 reference of the synthesized height;
* the footprint pyramid -- its levels (``mip.area_pyramid``) against brute-force box averages, the level of detail
  against its documented rule, the filtered read (torch path, numba ``filtered_lattice_blend``) against a float64
  read of the reference levels;
* the mean appearance (``DecodePath.mean_appearance``, ``eval`` and the Mitsuba plugin at a wide footprint) against
  its quadrature in float64, and the quadrature against the brute-force mean of point queries;
* a compiled material's point query -- numba, torch, the Mitsuba plugin, GLSL -- against a float64 reference from
  its tensors.

The integer hash's reference tests are in ``test_synthesis_core.py``. The Mitsuba plugin calls the library's query
(:mod:`dynbtf.render.mitsuba.evaluator`), so its tests here check that it hands the query over and back intact.

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


# ---------------------------------------------------------------------------- Mitsuba
def plugin_mitsuba():
    """Mitsuba with the plugin's variant ``llvm_ad_rgb`` and flags set (skips where it cannot run here)."""
    mitsuba = pytest.importorskip("mitsuba")
    pytest.importorskip("drjit")
    from dynbtf.render.mitsuba.bsdf import configure_jit, plugin_variants

    if "llvm_ad_rgb" not in plugin_variants():  # pragma: no cover - no LLVM on this machine
        pytest.skip("Mitsuba variant llvm_ad_rgb not usable here")
    mitsuba.set_variant("llvm_ad_rgb")
    configure_jit()
    return mitsuba


@pytest.fixture(scope="module")
def mi():
    return plugin_mitsuba()


def as_numpy(values) -> np.ndarray:
    """A Dr.Jit array, or a list of them, as float64 ``(N,)`` or ``(N, k)``."""
    if isinstance(values, (list, tuple)):
        return np.stack([np.array(v, dtype=np.float64) for v in values], axis=-1)
    return np.array(values, dtype=np.float64)


def vector3(mi, w: np.ndarray):
    return mi.Vector3f(*(mi.Float(np.ascontiguousarray(w[:, k], dtype=np.float32)) for k in range(3)))


# ---------------------------------------------------------------------------- lattice
@pytest.mark.parametrize("offset", [0.0, -37.25, 1e6 + 0.5])
def test_lattice_in_torch_is_the_exact_lattice(offset):
    from dynbtf.synthesis.lattice import triangle_lattice

    uv = RNG.random((200, 2)) * 3.0 + offset
    torch_vertices, torch_bary = triangle_lattice(torch.from_numpy(uv))
    for q, (u, v) in enumerate(uv):
        want = exact_triangle(float(u), float(v))
        # the three vertices are the same set; each carries its own barycentric
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


# ---------------------------------------------------------------------------- bilinear taps
def float32_fetch_tolerance(plane: np.ndarray) -> float:
    """What float32 rounding allows a bilinear fetch of ``plane (H, W, C)`` at a float32 coordinate: the texel
    coordinate is rounded a few times (the wrap, the scale by the side, ``grid_sample``'s normalization and back:
    at most 4 ulps of the padded side), which moves the value by that times the largest step between neighbours,
    plus the rounding of the 4-tap sum. Independent of the CPU's vector unit (the kernels' order of operations
    differs between AVX2 and AVX-512; each stays inside this)."""
    eps = float(np.finfo(np.float32).eps)
    side = max(plane.shape[:2]) + 2
    steps = max(np.abs(np.diff(plane, axis=0, append=plane[:1])).max(), np.abs(np.diff(plane, axis=1, append=plane[:, :1])).max())
    return 4 * side * eps * float(steps) + 4 * eps * float(np.abs(plane).max())


def test_positional_fetch_torch_numba_are_the_bilinear_reference():
    from dynbtf.synthesis.tiling.kernel import tile_fetch
    from dynbtf.texture import fetch_wrap

    plane = RNG.normal(size=(7, 5, 3)).astype(np.float32)
    uv = (RNG.random((300, 2)) - 0.5) * 6.0
    uv[:4] = [[0.0, 0.0], [1.0 - 1e-9, 0.5], [-1e-9, 0.999], [0.1, 0.9]]  # seams and corners
    want = reference_fetch_wrap(plane, uv)
    tolerance = float32_fetch_tolerance(plane)
    np.testing.assert_allclose(fetch_wrap(torch.from_numpy(plane), torch.from_numpy(uv)).numpy(), want, atol=tolerance)
    np.testing.assert_allclose(tile_fetch(uv, plane), want, atol=tolerance)


def test_angular_fetch_torch_is_the_bilinear_reference():
    from dynbtf.texture import fetch_angular

    plane = RNG.normal(size=(6, 9, 4)).astype(np.float32)
    st = np.column_stack([RNG.random(300) * 1.2 - 0.1, RNG.random(300) * 3.0 - 1.0])  # s beyond [0, 1] clamps
    st[:3] = [[0.0, 0.0], [1.0, 0.999999], [0.5, -1e-9]]
    want = reference_fetch_angular(plane, st)
    np.testing.assert_allclose(fetch_angular(torch.from_numpy(plane), torch.from_numpy(st)).numpy(), want, atol=5e-6)


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
    # float32 inputs and sums: 2e-5 of the value, plus the float32 directions' rounding of phi near a pole of h or d,
    # which grows as 1 / sin(theta) (measured: at most 2.9e-6 / sin(theta) over 90,000 queries)
    h, d = reference_half_diff(wv, wl)
    sin_theta = np.sqrt(np.minimum((h[:, :2] ** 2).sum(1), (d[:, :2] ** 2).sum(1)))[keep, None]

    def check(got):
        error = np.abs(got[keep] - want[keep])
        assert np.all(error <= 2e-5 * np.abs(want[keep]) + 2e-5 + 4e-6 / sin_theta), error.max()

    check(model.decode(torch.from_numpy(features).float(), torch.from_numpy(wv).float(),
                       torch.from_numpy(wl).float()).detach().numpy())
    # numba: layer 1 with the angular planes folded into it, then layers 2.. in torch
    decoder = model.decoder
    w_first = decoder.first.weight.detach()
    plane_h, plane_d = fold_angular_planes(model.f_h.detach(), model.f_d.detach(), w_first[:, 6:])
    pre = first_layer_preactivation(features.astype(np.float32), w_first[:, :6].T.contiguous().numpy(),
                                    decoder.first.bias.detach().numpy(), wv.astype(np.float32),
                                    wl.astype(np.float32), plane_h, plane_d)
    check(decoder.from_first_layer(torch.from_numpy(pre)).detach().numpy())


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
def test_every_synthesis_method_in_numba_is_the_torch_reference(method):
    """Torch path (float64 positions) = numba kernel, for every dynamic method.

    Histogram blending's kernels invert the Gaussian transform through its lookup table (the method's
    definition for rendering); the reference then uses the same table, and the exact inverse is
    checked to be within the table's error bound (1% of a channel's spread).
    """
    from dynbtf.synthesis.registry import make_synthesizer
    from dynbtf.synthesis.histogram import blend_weights, variance_preserving_blend

    exemplar = smooth_lognormal(24, 20, 4, seed=4)
    reference = make_synthesizer(method, exemplar, seed=9, fast=False)  # the torch path, float64 positions
    fast = make_synthesizer(method, exemplar, seed=9, fast=True)  # the numba kernel
    uv = (RNG.random((400, 2)) - 0.5) * 50.0
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


@pytest.mark.parametrize("kind", ["guided", "guided-hex"])
def test_guided_lattice_blending_in_numba_is_the_torch_reference(kind):
    """Exemplar guidance: the numba kernel's candidate search (the first offset whose four texels carry the target
    label) and steered weights give the torch reference's features, with most points steered off hist's own
    offsets."""
    from dynbtf.synthesis.guided_blending import GuidedBlending, GuidedHexTiling, LabelField, source_labels

    exemplar = smooth_lognormal(24, 20, 4, seed=4)
    labels = (exemplar[..., 0] > exemplar[..., 0].median()).long()
    target = LabelField(np.array([[0, 1, 1], [1, 0, 0]]), size=3.0, wrap="repeat")
    kind_class = GuidedBlending if kind == "guided" else GuidedHexTiling
    extra = {} if kind == "guided" else {"luminance": torch.rand(24, 20, generator=torch.Generator().manual_seed(1))}
    synth = kind_class(exemplar, 9, labels=labels, target=target, softness=0.25, tileable=False, **extra)
    uv = (RNG.random((600, 2)) - 0.5) * 60.0
    points = torch.from_numpy(uv)
    assert float((source_labels(synth, points) == target.labels(points)).float().mean()) > 0.9
    want = synth.reference_latent(points).double().numpy()
    matrix, offset = synth.output_map()
    if matrix is not None:
        want = want @ matrix.double().numpy() + offset.double().numpy()
    scale = np.abs(want).max()
    got = synth.features_from_latent(synth.latent(points)).double().numpy()
    tolerance = 0.01 * np.abs(want).std() if kind == "guided" else 5e-5 * scale  # hist: the LUT's error bound
    np.testing.assert_allclose(got, want, atol=tolerance)


@pytest.mark.parametrize("gamma", [1000.0, 1e10, 1e300])
def test_hist_with_extreme_exponents_is_finite_and_one_sample_in_every_backend(gamma):
    """``b^gamma`` underflows to 0 for all three barycentrics once gamma is large (0/0: NaN weights, and a NaN
    index into the inverse table crashed the numba kernel). The weights are ``(b / max b)^gamma``: finite for
    any gamma, and for gamma -> inf one-hot on the dominant vertex, whose sample passes through unblended."""
    from dynbtf.synthesis.registry import make_synthesizer

    exemplar = smooth_lognormal(24, 20, 4, seed=4)
    reference = make_synthesizer("hist", exemplar, seed=9, fast=False, gamma=gamma)
    fast = make_synthesizer("hist", exemplar, seed=9, fast=True, gamma=gamma, prepared=reference.prepared)
    uv = (RNG.random((400, 2)) - 0.5) * 50.0
    want = reference(torch.from_numpy(uv)).double().numpy()
    assert np.isfinite(want).all()
    scale = np.abs(want).max()
    np.testing.assert_allclose(fast(torch.from_numpy(uv)).double().numpy(), want, atol=0.01 * scale)
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
def test_guided_cell_quilting_in_numba_is_the_torch_reference():
    """Guided struct: the numba kernel's values (cells choosing, from the hashed offset on, the first whose content
    carries the target's label at the cell's centre) are the torch path's to float rounding, near the origin and
    2**45 repeats away; guidance moves many cells off their hashed offset."""
    from dynbtf.synthesis.cell_quilting import cell_choice
    from dynbtf.synthesis.guided_blending import GuidedCellQuilting, LabelField

    rng = np.random.default_rng(46)
    element = rng.random((8, 8, 4))
    exemplar = torch.from_numpy(np.tile(element, (4, 4, 1)) + 0.1 * rng.random((32, 32, 4))).float()
    labels = (exemplar[..., 0] > exemplar[..., 0].median()).long()
    target = LabelField(np.array([[0, 1], [1, 0]]), size=3.0)
    synth = GuidedCellQuilting(exemplar, 9, labels=labels, target=target, cells=(4, 4), fast=False)
    fast = GuidedCellQuilting(exemplar, 9, labels=labels, target=target, cells=(4, 4), fast=True)
    k = synth.prepared.count
    assert k > 4
    for origin in (0.0, 2.0 ** 45):
        uv = origin + (rng.random((3000, 2)) - 0.5) * (40.0 if origin == 0.0 else 6.0)
        want = synth(torch.from_numpy(uv)).double().numpy()
        got = fast(torch.from_numpy(uv)).double().numpy()
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-5 * np.abs(want).max())
    whole = np.floor(uv).astype(np.int64)
    texel = np.minimum(np.floor((uv - np.floor(uv)) * 32).astype(np.int64), 31)
    cx, cy = whole[:, 0] * 4 + texel[:, 0] // 8, whole[:, 1] * 4 + texel[:, 1] // 8
    hashed = cell_choice(torch.from_numpy(cx), torch.from_numpy(cy), 9, k).numpy()
    guided = synth.cell_choices(torch.from_numpy(cx), torch.from_numpy(cy)).numpy()
    assert np.mean(hashed != guided) > 0.2


@pytest.mark.parametrize("seed", [9, 2 ** 32 + 5])
def test_cell_quilting_in_numba_is_the_torch_reference(seed):
    """struct: torch path = numba kernel (values to float rounding), near the origin and 2**45 repeats from it (int64
    cell indices beyond any int32), on both sides; the torch path's chosen offsets are the hashed cells' (near cell
    edges neighbours' and diagonal cells' offsets are taken)."""
    from dynbtf.synthesis.registry import make_synthesizer
    from dynbtf.synthesis.cell_quilting import cell_choice

    rng = np.random.default_rng(45)
    exemplar = torch.from_numpy(np.tile(rng.random((8, 8, 4)), (4, 4, 1)) + 0.1 * rng.random((32, 32, 4))).float()
    # the torch path, float64 positions; two cells per repeat
    reference = make_synthesizer("struct", exemplar, seed=seed, fast=False, cells=2)
    fast = make_synthesizer("struct", exemplar, seed=seed, fast=True, prepared=reference.prepared)  # numba
    tables = reference.prepared
    assert tables.count > 4 and tables.cells == (2, 2)  # a lattice to choose from, two cells per repeat
    n = 4000
    for origin in (0.0, 2.0 ** 45, -(2.0 ** 45)):
        uv = origin + (rng.random((n, 2)) - 0.5) * (60.0 if origin == 0.0 else 6.0)
        _, chosen = reference.read_positions(torch.from_numpy(uv))
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


# ---------------------------------------------------------------------------- the relief march
def reference_march(uv: np.ndarray, w: np.ndarray, height_at, *, h_min: float, h_max: float, step: float,
                    max_step: float | None = None, surface_slope: float = 0.0, aspect: float = 1.0) -> np.ndarray:
    """The visible points of ``march_visible_uv``'s documented definition, one ray at a time in float64.

    Ray ``uv + z s``, ``s = (w_x, w_y aspect) / max(w_z, 1e-6)`` (``w_z <= 0``: vertical), ``L = max(|s|, 1e-12)``;
    a field at or above ``h_max`` at ``z = h_max`` is hit there; else from each sample ``z`` (gap ``g = z - height``)
    the next is ``max(h_min, z - clamp(g / (1 + surface_slope L), step / L, max_step / L))`` until one is at or
    below the surface or at ``h_min``: it and the one before bracket the hit. The bracket is halved (midpoint
    sampled, the half that still brackets kept) while longer than ``step (1 + 1e-6) / L`` in z; the hit is the
    linear interpolation of ``height - z`` between its ends (clamped to the bracket; no change: the lower end)."""
    out = np.array(uv, dtype=np.float64)
    max_step = step if max_step is None else max_step
    for q, (point, direction) in enumerate(zip(out, np.asarray(w, np.float64))):
        wx, wy, wz = direction if direction[2] > 0 else (0.0, 0.0, 1.0)
        s = np.array([wx, wy * aspect]) / max(wz, 1e-6)
        length = max(math.hypot(*s), 1e-12)

        def f(z):
            return height_at(point + z * s) - z

        z_hi = z_lo = h_max
        f_hi = f_lo = f(h_max)
        if f_hi < 0:
            while True:  # the search
                z = max(h_min, z_hi - min(max(-f_hi / (1 + surface_slope * length), step / length), max_step / length))
                fz = f(z)
                if fz >= 0 or z <= h_min:
                    z_lo, f_lo = z, fz
                    break
                z_hi, f_hi = z, fz
            while z_hi - z_lo > step * (1 + 1e-6) / length:  # the bracket halved
                z = 0.5 * (z_lo + z_hi)
                fz = f(z)
                if fz >= 0:
                    z_lo, f_lo = z, fz
                else:
                    z_hi, f_hi = z, fz
        t = f_lo / (f_lo - f_hi) if f_lo != f_hi else 0.0
        out[q] = point + (z_lo + min(1.0, max(0.0, t)) * (z_hi - z_lo)) * s
    return out


@pytest.fixture(scope="module")
def relief_model():
    """A small triple-parallax model: waves plus noise, a relief of ~2.5 texels."""
    from dynbtf.representations.parallax import ParallaxTriplePlane

    model = ParallaxTriplePlane(24, 20, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    generator = torch.Generator().manual_seed(4)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
        model.f_h.normal_(generator=generator)
        model.f_d.normal_(generator=generator)
        yy, xx = torch.meshgrid(torch.arange(24.0), torch.arange(20.0), indexing="ij")
        waves = torch.sin(2 * np.pi * xx / 10) * torch.cos(2 * np.pi * yy / 8)
        model.set_height(0.05 * (waves + 0.3 * torch.rand(24, 20, generator=generator)))
    return model.eval()


def relief_queries(n: int, seed: int):
    """Points over +-20 repeats; float32 views from the normal to 75 degrees (the last ones steep: long marches)."""
    from dynbtf.conventions import spherical_to_direction

    rng = np.random.default_rng(seed)
    uv = (rng.random((n, 2)) - 0.5) * 40.0
    theta, phi = rng.random((2, n)) * [[75.0], [360.0]]
    theta[0], theta[-n // 8:] = 0.0, 70.0 + 5.0 * rng.random(n // 8)
    w = spherical_to_direction(np.stack([theta, rng.random(n) * 70.0]), np.stack([phi, rng.random(n) * 360.0]))
    return uv, w[0].astype(np.float32).astype(np.float64), w[1].astype(np.float32).astype(np.float64)


def reference_relief_field(model, synth, method: str):
    """The synthesized height (uv units) at one point, float64: tile -- the bilinear reference of the height channel;
    linear -- the brute-force lattice blend of the synthesizer's tables."""
    from synthesis_reference import brute_force_lattice_blend

    scale = model.height_scale
    if method == "tile":
        plane = model.positional_plane().detach().double().numpy()[..., -1:]
        return lambda p: float(reference_fetch_wrap(plane, p[None])[0, 0]) * scale
    return lambda p: float(brute_force_lattice_blend(synth, p[None], "linear")[0, -1]) * scale


def reference_hist_height(model, seed: int, table: bool, gamma: float = 7.0):
    """hist's separately synthesized height (``separate=1``, no tileable preprocessing) at one point, uv units,
    float64, from the model's height channel alone: its texels ranked (stable) to ``G = ndtri((rank + 0.5) / N)``,
    the exact lattice, each vertex's hashed whole-texel offset, bilinear reads of ``G`` at the three offset
    positions, the blend ``sum w_i G_i / sqrt(sum w_i^2)`` with ``w_i = b_i^gamma / sum_j b_j^gamma``, then the
    inverse ``np.interp(ndtr(g), (arange(N) + 0.5) / N, sorted heights)`` -- or (``table``, the kernels' inverse)
    that inverse tabulated at 4096 points evenly from ``G_min = ndtri(0.5 / N)`` to ``-G_min``, interpolated
    linearly, clamped at both ends."""
    from fractions import Fraction

    from scipy.special import ndtr, ndtri
    from synthesis_reference import lowbias32

    height = model.height_channel.detach().double().numpy()
    rows, cols = height.shape
    flat = height.reshape(-1)
    order = np.argsort(flat, kind="stable")
    ranks = (np.arange(flat.size) + 0.5) / flat.size
    gaussian = np.empty(flat.size)
    gaussian[order] = ndtri(ranks)
    gaussian = gaussian.reshape(rows, cols)

    def inverse(g):
        return np.interp(ndtr(g), ranks, flat[order])

    g_min = float(ndtri(0.5 / flat.size))
    grid = np.linspace(g_min, -g_min, 4096)
    tabulated = inverse(grid)

    def inverse_table(g):
        pos = min(max((g - g_min) / (grid[1] - grid[0]), 0.0), 4095.0)
        lo = min(int(pos), 4094)
        return tabulated[lo] + (pos - lo) * (tabulated[lo + 1] - tabulated[lo])

    def field(p):
        u, v = float(p[0]), float(p[1])
        (bx, by), (fx, fy) = exact_lattice(u, v)
        if 1 - fx - fy > 0:
            verts, bary = [(bx, by), (bx, by + 1), (bx + 1, by)], [1 - fx - fy, fy, fx]
        else:
            verts, bary = [(bx + 1, by + 1), (bx + 1, by), (bx, by + 1)], [fx + fy - 1, 1 - fy, 1 - fx]
        px, py = Fraction(u) * cols - Fraction(1, 2), Fraction(v) * rows - Fraction(1, 2)
        x0, y0 = math.floor(px), math.floor(py)
        tx, ty = float(px - x0), float(py - y0)
        samples = []
        for vx, vy in verts:
            h = reference_hash(vx, vy, seed)
            ox, oy = h % cols, lowbias32(h ^ 0x9E3779B9) % rows
            c0, c1, r0, r1 = (x0 + ox) % cols, (x0 + ox + 1) % cols, (y0 + oy) % rows, (y0 + oy + 1) % rows
            samples.append((1 - tx) * (1 - ty) * gaussian[r0, c0] + tx * (1 - ty) * gaussian[r0, c1]
                           + (1 - tx) * ty * gaussian[r1, c0] + tx * ty * gaussian[r1, c1])
        w = np.array(bary) ** gamma
        w /= w.sum()
        g = float(w @ np.array(samples)) / math.sqrt(float(w @ w))
        return float(inverse_table(g) if table else inverse(g)) * model.height_scale

    return field


def march_parameters(model) -> dict:
    """``h_min, h_max`` (the exemplar's height range, float64), ``step``, ``max_step``, ``surface_slope`` and
    ``aspect`` from the model's config and the march's documented constants."""
    from dynbtf.representations.parallax import MARCH_SEARCH_FACTOR, MARCH_SURFACE_SLOPE

    rows, cols = model.height_channel.shape
    height = model.height_channel.detach().double() * model.height_scale
    step = model.config()["march_step_texels"] / max(rows, cols)
    return {"h_min": float(height.min()), "h_max": float(height.max()), "step": step,
            "max_step": MARCH_SEARCH_FACTOR * step, "surface_slope": MARCH_SURFACE_SLOPE, "aspect": cols / rows}


@pytest.mark.parametrize("method", ["tile", "linear", "hist"])
def test_relief_march_in_torch_and_numba_is_the_reference(relief_model, method):
    """The visible point through the synthesized height: the library's march (through the torch synthesis path
    and through the numba kernel) = :func:`reference_march` of the float64 reference field.

    Every backend reads a float32 height (~1e-9 uv from the reference), which moves a hit by about that over
    ``1 - grad h . s``: within 1e-5 texels. Where a ray grazes a ridge (a sample within that of the surface,
    then below it again) the rounding may decide between the ridge and a surface further on: a jump by up to the
    march's reach. Such queries are rare (measured: none in these 240): at most 2% of them may jump."""
    from dynbtf.synthesis.registry import make_synthesizer

    model = relief_model
    plane = model.positional_plane().detach()
    options = {"separate": 1, "tileable": False} if method == "hist" else {}  # hist: the height on its own
    reference = make_synthesizer(method, plane, seed=3, fast=False, **options)
    fast = make_synthesizer(method, plane, seed=3, fast=True, **({} if method == "tile" else
                                                                {"prepared": reference.prepared, **options}))
    uv, wv, _ = relief_queries(240, seed=31)
    if method == "hist":  # the torch path inverts exactly, the kernels through the table
        wants = {table: reference_march(uv, wv, reference_hist_height(model, 3, table), **march_parameters(model))
                 for table in (False, True)}
    else:
        field = reference_relief_field(model, reference, method)
        wants = dict.fromkeys((False, True), reference_march(uv, wv, field, **march_parameters(model)))
    want = wants[True]
    texels = np.array(model.height_channel.shape[::-1], np.float64)  # uv -> texels per axis

    def check(got, what):
        want = wants[what != "torch"]
        error = np.abs(np.asarray(got, np.float64) - want).max(1) * texels.max()
        assert np.mean(error < 1e-5) >= 0.98, (what, np.sort(error)[-8:])

    for name, synth in (("torch", reference), ("numba", fast)):
        check(model.visible_uv(torch.from_numpy(uv), torch.from_numpy(wv).float(), synth).numpy(), name)
    # the march matters here: the visible points move by up to ~3 texels (not a comparison of uv with itself)
    assert (np.abs(want - uv).max(1) * texels.max()).max() > 1.0


def dense_march(uv: np.ndarray, w: np.ndarray, plane: np.ndarray, *, h_min: float, h_max: float, texels: float,
                aspect: float = 1.0, **_) -> np.ndarray:
    """Brute force: every ray sampled from ``h_max`` to ``h_min`` every 1/50 texel (horizontally) of the height
    plane ``(H, W, 1)`` (uv units, bilinear, periodic); the first sample at or below the surface and the one
    before it bracket the hit, placed by linear interpolation (no sample below: ``h_min``)."""
    slope = np.where(w[:, 2:3] > 0, w[:, :2], 0.0) / np.maximum(w[:, 2:3], 1e-6) * [1.0, aspect]
    count = int(np.ceil((h_max - h_min) * np.hypot(*slope.T).max() * texels * 50)) + 1
    z = np.linspace(h_max, h_min, count)
    f = np.stack([reference_fetch_wrap(plane, uv + zk * slope)[:, 0] - zk for zk in z], 1)  # (N, count)
    first = np.where((f >= 0).any(1), np.argmax(f >= 0, 1), count - 1)
    above = np.maximum(first - 1, 0)
    rows = np.arange(len(uv))
    fa, fb = f[rows, above], f[rows, first]
    t = np.where(fb != fa, np.clip(fb / np.where(fb != fa, fb - fa, 1.0), 0.0, 1.0), 0.0)
    return uv + (z[first] + t * (z[above] - z[first]))[:, None] * slope


def test_relief_march_is_the_dense_march_but_where_rays_graze_a_ridge(relief_model):
    """The march's variable search steps and bisected bracket lose nothing against a brute-force march 25x finer
    than its resolution: 97% of the hits within 0.05 texels (measured: 98.5% for 2000 queries, as a fixed
    half-texel march), the others where a ray grazes a ridge either march may miss."""
    model = relief_model
    uv, wv, _ = relief_queries(400, seed=33)
    plane = model.height_channel.detach().double().numpy()[..., None] * model.height_scale
    texels = max(model.height_channel.shape)
    want = dense_march(uv, wv, plane, texels=texels, **march_parameters(model))
    got = model.visible_uv(torch.from_numpy(uv), torch.from_numpy(wv), model.height_channel.detach()[..., None])
    error = np.abs(got.numpy() - want).max(1) * texels
    assert np.mean(error < 0.05) >= 0.97, np.sort(error)[-12:]


# ---------------------------------------------------------------------------- every backend reads a compiled material
def material_model():
    """The Triple Plane of the compiled-material tests: a plane with structure (a 16-texel period) and visible
    angular variation (also ``test_compiled_material.py``'s model)."""
    from dynbtf.representations.triple_plane import TriplePlane

    rep = TriplePlane(32, 32, seed=5)
    with torch.no_grad():
        grid = torch.arange(32.0)
        rep.f_u.add_(0.5 * torch.sin(grid * np.pi / 8)[:, None, None] * torch.cos(grid * np.pi / 8)[None, :, None])
        rep.f_h.normal_(generator=torch.Generator().manual_seed(1))
        rep.f_d.normal_(generator=torch.Generator().manual_seed(2))
    return rep.eval()


def material_queries(n: int, spread: float = 40.0, seed: int | None = None):
    """``n`` points over ``+-spread / 2`` repeats and (view, light) pairs up to 70 degrees from the normal."""
    from dynbtf.conventions import spherical_to_direction

    rng = RNG if seed is None else np.random.default_rng(seed)
    uv = (rng.random((n, 2)) - 0.5) * spread
    theta = rng.random((2, n)) * 70.0
    phi = rng.random((2, n)) * 360.0
    w = spherical_to_direction(theta, phi)
    return uv, w[0], w[1]


def reference_eval(material, uv: np.ndarray, wv: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """float64 reference of a compiled material's point query: the stored synthesizer's torch path (float64
    positions), the stored folded layer 1, the model's angular planes fetched at the reference angular coordinates,
    the stored layers 2.. in float64."""
    synth = material.synthesizer()
    fast = synth.fast
    synth.fast = False
    if material.method == "hist":  # rendering's definition inverts the Gaussian transform through the stored table
        from dynbtf.synthesis.histogram import blend_weights, variance_preserving_blend

        lut = synth.prepared.extras["lut"]
        synth.blend = lambda samples, bary, uv_samples: lut(variance_preserving_blend(
            samples.double(), blend_weights(bary, synth.gamma))).float()
    try:
        latent = synth.latent(torch.from_numpy(uv)).double().numpy()
    finally:
        synth.fast = fast
        synth.__dict__.pop("blend", None)
    d = material.decoder
    point = d.levels[0]
    h, dd = reference_half_diff(wv, wl)
    model = material.model
    angular = np.concatenate([reference_fetch_angular(model.f_h.detach().numpy(), reference_angular_coords(h)),
                              reference_fetch_angular(model.f_d.detach().numpy(), reference_angular_coords(dd))], 1)
    first = latent @ point.weight.double().numpy() + point.bias.double().numpy() \
        + angular @ d.angular_weight.double().numpy().T + d.first_bias.double().numpy()
    x = np.where(first >= 0, first, first * d.slope)
    layers = [(w.double().numpy(), b.double().numpy()) for w, b in point.rest]
    return reference_mlp(x, layers, d.slope)


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    """One saved compiled material per method, read back (the backends below read these files' contents)."""
    from dynbtf.material import load_compiled, save_compiled
    from dynbtf.material import compile_material

    model = material_model()
    folder = tmp_path_factory.mktemp("compiled")
    out = {}
    for method in ("tile", "hist", "hex", "struct"):
        save_compiled(compile_material(model, method, seed=9, footprints=False), folder / f"{method}.dbtfc")
        out[method] = load_compiled(folder / f"{method}.dbtfc")
    return out


def glsl_eval(model, method: str, seed: int, folder, uv, wv, wl) -> np.ndarray:
    """The exported fp32 shader's values in headless Chromium (skips without Chromium)."""
    from chromium import eval_in_browser, find_chromium

    if find_chromium() is None:
        pytest.skip("needs headless Chromium (scripts/test.sh installs it)")
    from dynbtf.export.web.exporter import export_web

    export_web(model, folder, precision="fp32", methods=(method,), seed=seed)
    return eval_in_browser(folder, method, uv, wv, wl).rgb


@pytest.mark.parametrize("method", ["tile", "hist", "hex", "struct"])
@pytest.mark.parametrize("backend", ["numba", "torch", "plugin", "glsl"])
def test_every_backend_reads_the_compiled_material_as_the_float64_reference(compiled, method, backend, tmp_path):
    from dynbtf.infinite_btf import SynthesizedBTF

    material = compiled[method]
    uv, wv, wl = material_queries(300, spread=1e3, seed=17)  # the same queries for every backend and method
    # float32 directions for every backend (the plugin and the shader take float32 vectors), the reference
    # computed from those same values in float64
    wv, wl = wv.astype(np.float32).astype(np.float64), wl.astype(np.float32).astype(np.float64)
    keep = _away_from_phi_seam(wv, wl)
    want = reference_eval(material, uv, wv, wl)
    scale = np.abs(want).max()
    if backend in ("numba", "torch"):
        btf = SynthesizedBTF(material)
        if backend == "torch":  # the torch synthesis path and the torch decoder's first layer (put back after: the
            fused = btf.decode_path._fused  # material's synthesizer and decode path serve every query object of it)
            btf.synthesizer.fast = False
            btf.decode_path._fused = None
            try:
                got = btf.eval(uv, wv, wl)
            finally:
                btf.synthesizer.fast = True
                btf.decode_path._fused = fused
        else:
            got = btf.eval(uv, wv, wl)
    elif backend == "plugin":  # the Mitsuba plugin's query: the library's, handed a wavefront and back
        mi = plugin_mitsuba()
        from dynbtf.render.mitsuba.evaluator import DynBTFEvaluator

        evaluator = DynBTFEvaluator(SynthesizedBTF(material))  # the file's material itself
        rgb = evaluator.eval(mi.Float64(uv[:, 0]), mi.Float64(uv[:, 1]), mi.Vector3f(*wv.T.astype(np.float32)),
                             mi.Vector3f(*wl.T.astype(np.float32)))
        got = np.stack([np.asarray(rgb.x), np.asarray(rgb.y), np.asarray(rgb.z)], axis=-1)
        np.testing.assert_array_equal(got, SynthesizedBTF(material).eval(uv, wv.astype(np.float32),
                                                                         wl.astype(np.float32)))
    else:
        got = glsl_eval(material.model, method, material.seed, tmp_path / "web", uv, wv, wl)
    # the torch path computes the angular coordinates from float32 directions (the others in float64 or with
    # their own float32 care): near the poles of h and d that moves the fetch by ~1e-4 of the value range
    tolerance = {"numba": 2e-5, "torch": 5e-4, "plugin": 2e-5, "glsl": 2e-3}[backend]
    error = np.abs(got[keep] - want[keep]).max(1)
    if backend == "glsl":
        # float32 kernels: a few queries at a lattice edge or an angular seam may round to the other side (a jump
        # of a few 1e-3 of the range); every query stays within 1%, and 99% within the tolerance
        assert error.max() < 1e-2 * scale
        assert np.mean(error < tolerance * scale) > 0.99
    else:
        assert error.max() < tolerance * scale


def test_relief_march_in_glsl_is_the_reference(relief_model, tmp_path):
    """The shader's march (tiling: the reference field is the bilinear height channel) = the float64 reference
    decode (:func:`reference_eval`) at :func:`reference_march`'s visible points. Tolerances as the compiled
    material's GLSL backend above (float32 shader: 99% within 2e-3 of the range, every query within 1%); the
    march moves the answer by far more than that (checked)."""
    from dynbtf.material import compile_material

    model = relief_model
    material = compile_material(model, "tile", seed=0, footprints=False)
    uv, wv, wl = relief_queries(200, seed=32)
    keep = _away_from_phi_seam(wv, wl)
    visible = reference_march(uv, wv, reference_relief_field(model, None, "tile"), **march_parameters(model))
    want = reference_eval(material, visible, wv, wl)
    got = glsl_eval(model, "tile", 0, tmp_path / "web", uv, wv, wl)
    scale = np.abs(want).max()
    error = np.abs(got[keep] - want[keep]).max(1)
    assert error.max() < 1e-2 * scale
    assert np.mean(error < 2e-3 * scale) > 0.99
    unmarched = np.abs(reference_eval(material, uv, wv, wl) - want).max(1)
    assert unmarched.max() > 0.1 * scale


# ---------------------------------------------------------------------------- the footprint pyramid
def reference_box_levels(plane: np.ndarray) -> list[np.ndarray]:
    """Levels of a plane ``(H, W, C)`` by brute force: level ``l`` has ``max(1, ceil(H / 2**l)) x max(1, ceil(W / 2**l))``
    texels, texel ``[i, j]`` the float64 mean of the plane (piecewise constant: texel ``[r, c]`` on ``[c, c + 1) x
    [r, r + 1)``) over ``[j W / W_l, (j + 1) W / W_l) x [i H / H_l, (i + 1) H / H_l)``. Every level-0 texel is cut
    into ``H_l x W_l`` equal sub-texels: the box of ``[i, j]`` is then exactly sub-rows ``[i H, (i + 1) H)`` and
    sub-columns ``[j W, (j + 1) W)``, whose plain mean it is."""
    plane = np.asarray(plane, np.float64)
    h, w, c = plane.shape
    levels, l = [plane], 1
    while levels[-1].shape[:2] != (1, 1):
        hl, wl = max(1, math.ceil(h / 2 ** l)), max(1, math.ceil(w / 2 ** l))
        fine = np.repeat(np.repeat(plane, hl, axis=0), wl, axis=1)
        levels.append(fine.reshape(hl, h, wl, w, c).mean(axis=(1, 3)))
        l += 1
    return levels


def reference_level_of_detail(shapes, blend_band: float, footprint: float) -> tuple[int, float]:
    """``LevelOfDetail``'s documented rule for one footprint (level-0 texels): level widths ``sqrt(H / H_l W / W_l)``;
    the last level whose width is at most the footprint (at most one texel: level 0; beyond the top: the top) and
    the next level's weight, linear in ``log2`` between the two widths; with ``blend_band < 1`` the weight is
    ``(t - 0.5) / band + 0.5``, a weight reaching 1 reads the next level alone; clamped to ``[0, 1]``."""
    (h, w), top = shapes[0], len(shapes) - 1
    log_w = [math.log2(math.sqrt(h / hl * (w / wl))) for hl, wl in shapes]
    log_f = math.log2(max(footprint, 1.0))
    lower = max([k for k in range(top + 1) if log_w[k] <= log_f] or [0])
    upper = min(lower + 1, top)
    span = log_w[upper] - log_w[lower]
    t = (log_f - log_w[lower]) / span if span > 0 else 0.0
    if blend_band < 1.0:
        t = (t - 0.5) / blend_band + 0.5
        if t >= 1.0:
            lower, t = upper, 0.0
    return lower, min(1.0, max(0.0, t))


def reference_filtered(synth, method: str, uv: np.ndarray, footprint: np.ndarray, levels, luminances=None):
    """The footprint read of ``tile``/``linear``/``hex`` in float64 (latent values, before the output map): each
    sample where the point query reads it (tile: ``frac(uv)``; lattice methods: :func:`reference_lattice_reads`),
    bilinear in the reference ``levels`` at that position, blended per level (hex: weights from the level's
    luminance), the two levels of :func:`reference_level_of_detail` mixed."""
    from synthesis_reference import reference_lattice_reads

    ph, pw = levels[0].shape[:2]
    shapes = [t.shape[:2] for t in levels]
    band = synth.level_of_detail().blend_band
    out = np.zeros((len(uv), levels[0].shape[2]))
    for q, ((u, v), f) in enumerate(zip(uv, footprint)):
        lower, t = reference_level_of_detail(shapes, band, float(f))
        if method == "tile":
            bary, positions = [1.0], [((u - math.floor(u)) * pw, (v - math.floor(v)) * ph)]
        else:
            bary, positions = reference_lattice_reads(synth, float(u), float(v))
        for level, share in ((lower, 1.0 - t), (min(lower + 1, len(levels) - 1), t)):
            if share == 0.0:
                continue
            hl, wl = shapes[level]

            def read(plane):  # bilinear reads of the three samples at level-l texel coordinates
                return np.concatenate([reference_bilinear(plane, np.array([float(x) * wl / pw - 0.5]),
                                                          np.array([float(y) * hl / ph - 0.5]), wrap_x=True,
                                                          wrap_y=True) for x, y in positions])

            samples, b = read(levels[level]), np.array(bary)
            if method == "hex":
                lum = read(luminances[level][..., None])[:, 0]
                weights = (1 - synth.beta + synth.beta * lum) * np.maximum(b, 0.0) ** 7
                weights /= weights.sum()
                k = math.log(1 - synth.contrast) / math.log(0.5)
                weights = np.where(weights < 0.5, 0.5 * (2 * weights) ** k, 1 - 0.5 * (2 - 2 * weights) ** k)
                b = weights / weights.sum()
            out[q] += share * (b @ samples)
    return out


def footprint_queries(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points over +-25 repeats and footprints from half a texel to 300 texels (beyond the 24 x 20 exemplar),
    a few at exactly the levels' widths."""
    rng = np.random.default_rng(seed)
    uv = (rng.random((n, 2)) - 0.5) * 50.0
    texels = np.exp(rng.uniform(math.log(0.5), math.log(300.0), n))
    texels[:6] = [1.0, 2.0, math.sqrt(8 * 7), 1.5, 2 ** 0.65, 2 ** 0.35]
    return uv, texels


@pytest.mark.parametrize("method", ["tile", "linear", "hist", "hex"])
def test_pyramid_levels_and_level_of_detail_are_the_brute_force_box_average(method):
    """Every level every backend reads (the read plane's pyramid; hex's luminance pyramid) = the brute-force box
    average (float32 storage of a float64 mean: 1e-6 of the plane's range); the level of detail = the documented
    rule (same level; weights to float32)."""
    from dynbtf.synthesis.registry import make_synthesizer

    synth = make_synthesizer(method, smooth_lognormal(24, 20, 4, seed=4), seed=9)
    pyr = synth.pyramid()
    plane = synth.exemplar if method == "tile" else synth.prepared.plane
    pairs = [(pyr["levels"], reference_box_levels(plane.double().numpy()))]
    if method == "hex":
        pairs.append(([t[..., None] for t in pyr["luminances"]],
                      reference_box_levels(synth.prepared.extras["luminance"].double().numpy()[..., None])))
    for got, want in pairs:
        assert [tuple(t.shape) for t in got] == [t.shape for t in want]
        for level, (a, b) in enumerate(zip(got, want)):
            np.testing.assert_allclose(a.double().numpy(), b, rtol=0, atol=1e-6 * np.ptp(want[0]), err_msg=level)
    shapes = [t.shape[:2] for t in pyr["levels"]]
    _, texels = footprint_queries(300, seed=40)
    lod = synth.level_of_detail()
    for band in (lod.blend_band, 1.0):  # rendering's band ("brilinear"), and trilinear
        lod.blend_band = band
        want = np.array([reference_level_of_detail(shapes, band, f) for f in texels])
        assert 0 < np.mean(want[:, 1] > 0) < 1 and len(set(want[:, 0])) == len(shapes)  # mixed and single reads
        level, upper = lod(texels)
        np.testing.assert_array_equal(level, want[:, 0])
        np.testing.assert_allclose(upper, want[:, 1], rtol=0, atol=1e-6)


@pytest.mark.parametrize("method", ["tile", "linear", "hist", "hex"])
def test_filtered_read_in_torch_and_numba_is_the_reference(method):
    """The footprint query's latent values: torch reference path and numba kernel (the lattice methods; tile's
    footprint read is the torch trilinear fetch) = the float64 reference from the brute-force levels
    (:func:`reference_filtered`). hist's per-level inverse tables have no float64 form here: its torch path
    (float64 positions, Gaussian-space blend; level 0 through the point query's table, as rendering defines it)
    is the reference, and its levels are the ones checked above.

    Tolerance 5e-6 of the values' range: float32 levels, float32 bilinear weights (the torch fetch also at
    float32 texel positions); measured at most 1.2e-6 (torch path), 1.4e-7 (numba)."""
    from dynbtf.synthesis.registry import make_synthesizer

    exemplar = smooth_lognormal(24, 20, 4, seed=4)
    reference = make_synthesizer(method, exemplar, seed=9, fast=False)
    uv, texels = footprint_queries(200, seed=41)
    footprint = torch.from_numpy(texels)
    if method == "hist":
        lut, blend = reference.prepared.extras["lut"], reference.blend
        from dynbtf.synthesis.histogram import blend_weights, variance_preserving_blend

        reference.blend = lambda samples, bary, uv_samples, level=0: (lut(variance_preserving_blend(
            samples.double(), blend_weights(bary, reference.gamma))).float() if level == 0
            else blend(samples, bary, uv_samples, level))
        want = reference.filtered_latent(torch.from_numpy(uv), footprint).double().numpy()
    else:
        plane = reference.exemplar if method == "tile" else reference.prepared.plane
        luminances = (reference_box_levels(reference.prepared.extras["luminance"].double().numpy()[..., None])
                      if method == "hex" else None)
        want = reference_filtered(reference, method, uv, texels, reference_box_levels(plane.double().numpy()),
                                  None if luminances is None else [t[..., 0] for t in luminances])
    scale = np.ptp(want)
    got = {"torch": reference.filtered_latent(torch.from_numpy(uv), footprint).double().numpy()}
    if method != "tile":
        fast = make_synthesizer(method, exemplar, seed=9, fast=True, prepared=reference.prepared)
        got["numba"] = fast.filtered_latent(torch.from_numpy(uv), footprint).double().numpy()
    for backend, values in got.items():
        np.testing.assert_allclose(values, want, rtol=0, atol=5e-6 * scale, err_msg=backend)
    # the footprint matters: the point query differs (not a comparison of the point query with itself)
    point = reference.latent(torch.from_numpy(uv)).double().numpy()
    assert np.abs(point - want).max() > 0.1 * scale


# ---------------------------------------------------------------------------- the mean appearance
def reference_mean_appearance(decoder, model, wv: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """``MeanAppearance``'s definition in float64: ``sum_k weights[k] decode(nodes[k])``, where ``decode(node)`` is
    layer 1 (``node`` as its positional pre-activation, plus the angular part and layer 1's bias), LeakyReLU, then
    the mean's own layers 2..; angular inputs as :func:`reference_decode`'s."""
    mean = decoder.mean
    h, d = reference_half_diff(wv, wl)
    angular = np.concatenate([reference_fetch_angular(model.f_h.detach().numpy(), reference_angular_coords(h)),
                              reference_fetch_angular(model.f_d.detach().numpy(), reference_angular_coords(d))], 1)
    pre = angular @ decoder.angular_weight.double().numpy().T + decoder.first_bias.double().numpy()
    layers = [(w.double().numpy(), b.double().numpy()) for w, b in mean.rest]
    out = 0.0
    for weight, node in zip(mean.weights.double().tolist(), mean.nodes.double().numpy()):
        x = pre + node
        out = out + weight * reference_mlp(np.where(x >= 0, x, decoder.slope * x), layers, decoder.slope)
    return out


def test_mean_appearance_in_every_backend_is_its_quadrature_and_answers_the_brute_force_mean(mi):
    """Footprints that read only the 1 x 1 top level answer the material's mean appearance.

    Its formula (the fitted quadrature, :func:`reference_mean_appearance`): the library's fused and torch paths,
    ``eval`` at a footprint beyond the exemplar and the Mitsuba plugin at one are held to
    it (float32: 2e-5 of the range; the torch path computes angular coordinates from float32 directions, 5e-4 as
    for point queries). Its accuracy: against the brute-force mean of point queries over 4096 random positions per
    (view, light) pair, in units of their spread around it -- the fitted quadrature far closer than the plain
    decoder on the mean features (measured: 0.07 vs 0.41 of the spread)."""
    from dynbtf.decoder.folded import DecodePath
    from dynbtf.synthesized import synthesized_btf
    from dynbtf.render.mitsuba.evaluator import DynBTFEvaluator
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.conventions import spherical_to_direction

    btf = synthesized_btf(TriplePlane(16, 16, seed=3), "hist", scale=4.0, seed=1, footprints=True)  # 5 levels: 4 fits
    plain = synthesized_btf(btf.model, "hist", scale=btf.scale, seed=btf.seed, level_decoders=False)
    rng = np.random.default_rng(14)
    w = spherical_to_direction(rng.random((2, 24)) * 70.0, rng.random((2, 24)) * 360.0)
    wv, wl = (x.astype(np.float32).astype(np.float64) for x in w)
    keep = _away_from_phi_seam(wv, wl)
    folded = btf.footprint_decoder()
    assert folded.mean is not None
    want = reference_mean_appearance(folded, btf.model, wv, wl)
    scale = np.abs(want).max()
    uv = np.random.default_rng(16).random((24, 2)) * 1e4
    torch_path = DecodePath(folded, btf.model.fast_decoder().angular_features)  # no angular planes: torch layer 1
    evaluator = DynBTFEvaluator(synthesized_btf(btf.model, "hist", seed=btf.seed, footprints=True))
    rgb = evaluator.eval(mi.Float64(uv[:, 0]), mi.Float64(uv[:, 1]), vector3(mi, wv), vector3(mi, wl),
                         footprint=mi.Float(np.full(24, 1e4, np.float32)))
    got = {"fused": btf.mean_appearance(torch.from_numpy(wv).float(), torch.from_numpy(wl).float()).numpy(),
           "torch": torch_path.mean_appearance(torch.from_numpy(wv).float(), torch.from_numpy(wl).float()).detach().numpy(),
           "eval": btf.eval(uv, wv, wl, footprint=1e4), "plugin": as_numpy([rgb.x, rgb.y, rgb.z])}
    for backend, values in got.items():
        tolerance = 5e-4 if backend == "torch" else 2e-5
        np.testing.assert_allclose(values[keep], want[keep], rtol=0, atol=tolerance * scale, err_msg=backend)
    # the quadrature's accuracy against the brute-force mean
    positions = np.random.default_rng(15).random((4096, 2)) * 50
    points = np.stack([btf.eval(positions, np.repeat(wv[i:i + 1], 4096, 0), np.repeat(wl[i:i + 1], 4096, 0))
                       for i in range(24)])
    brute, spread = points.mean(1), float(points.std(1).mean())  # the mean, and the spread around it
    ours = float(np.abs(want - brute).mean()) / spread
    theirs = float(np.abs(plain.eval(uv, wv, wl, footprint=1e4) - brute).mean()) / spread
    assert ours < 0.2 and ours < 0.5 * theirs, (ours, theirs)
