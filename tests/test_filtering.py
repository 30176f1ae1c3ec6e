"""Footprint queries (prefiltered synthesis): identities, convergence to brute-force means, errors.

The references are independent of the filtering code: constant planes, the point query itself,
and the mean of many point queries over the footprint (brute force, computed here).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from dynbtf.conventions import spherical_to_direction
from dynbtf.errors import InputError
from dynbtf.render.preview import DirectionalLight, PinholeCamera, grazing_camera, plane_footprint, render_preview
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.synthesis import make_synthesizer
from dynbtf.synthesis.mip import LevelOfDetail, area_matrix, area_pyramid
from dynbtf.infinite_btf import SynthesizedBTF, footprint_width
from dynbtf.synthesized import synthesized_btf
from synthesis_reference import smooth_lognormal

METHODS = ("tile", "linear", "hist", "hex")



@pytest.fixture(scope="module")
def exemplar():
    return smooth_lognormal(40, 48, 4, seed=7)


def brute_force_mean(fn, uv, side, k, seed=0):
    """Mean of ``fn`` over the square of side ``side`` around each ``uv``: one random point in each of
    ``k x k`` sub-squares (stratified, jittered: a regular grid would alias with the exemplar's period)."""
    rng = np.random.default_rng(seed)
    total = 0.0
    for i in range(k):
        for j in range(k):
            offset = (np.array([j, i]) + rng.random((len(uv), 2))) / k - 0.5
            total = total + fn(uv + side[:, None] * offset)
    return total / (k * k)


# ---------------------------------------------------------------- the pyramid
def test_area_pyramid_levels_are_block_means_and_end_in_the_mean():
    plane = torch.rand(12, 20, 3, generator=torch.Generator().manual_seed(0))
    levels = area_pyramid(plane)
    assert [tuple(t.shape[:2]) for t in levels] == [(12, 20), (6, 10), (3, 5), (2, 3), (1, 2), (1, 1)]
    expected = plane.reshape(6, 2, 10, 2, 3).mean((1, 3))
    torch.testing.assert_close(levels[1], expected)
    torch.testing.assert_close(levels[-1][0, 0], plane.mean((0, 1)))
    a = area_matrix(3, 2)  # fractional boundaries: [0, 1.5) and [1.5, 3)
    torch.testing.assert_close(a, torch.tensor([[2 / 3, 1 / 3, 0], [0, 1 / 3, 2 / 3]], dtype=torch.float64))


def test_level_of_detail_brackets_the_footprint():
    lod = LevelOfDetail.of(area_pyramid(torch.zeros(64, 64, 1)), blend_band=1.0)  # trilinear
    level, upper = lod(np.array([0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 64.0, 1e9]))
    assert level.tolist() == [0, 0, 0, 1, 1, 2, 6, 6]
    np.testing.assert_allclose(upper, [0, 0, 0, 0, np.log2(1.5), 0, 0, 0], atol=1e-6)
    lod.blend_band = 0.5  # mixed only within a quarter octave of the midpoint between two levels
    level, upper = lod(2.0 ** np.array([1.1, 1.3, 1.5, 1.7, 1.9]))
    assert level.tolist() == [1, 1, 1, 1, 2]
    np.testing.assert_allclose(upper, [0, 0.1, 0.5, 0.9, 0], atol=1e-6)


# ---------------------------------------------------------------- synthesizers
@pytest.mark.parametrize("method", METHODS)
def test_constant_plane_filters_to_itself(method):
    value = torch.tensor([0.3, -1.2, 2.0, 0.0])
    synth = make_synthesizer(method, value.expand(24, 32, 4).clone(), seed=2)
    uv = torch.from_numpy(np.random.default_rng(0).random((500, 2)) * 7 - 3)
    for footprint in (0.0, 3.7, 40.0, 1e7):
        out = synth(uv, torch.full((500,), footprint))
        torch.testing.assert_close(out, value.expand(500, 4), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("fast", [True, False])
def test_footprint_of_at_most_one_texel_is_the_point_query(exemplar, method, fast):
    params = {} if method == "tile" else {"fast": fast}
    synth = make_synthesizer(method, exemplar, seed=5, **params)
    uv = torch.from_numpy(np.random.default_rng(1).random((2000, 2)) * 9 + np.array([1e6, -3.0]))
    point = synth(uv)
    scale = float(point.std())
    for footprint in (0.0, 0.4, 1.0):
        torch.testing.assert_close(synth(uv, torch.full((2000,), footprint)), point, atol=2e-5 * scale, rtol=0)


@pytest.mark.parametrize("method", ("linear", "hist", "hex"))
def test_fast_kernel_matches_the_reference_path(exemplar, method):
    fast = make_synthesizer(method, exemplar, seed=5)
    slow = make_synthesizer(method, exemplar, seed=5, fast=False, prepared=fast.prepared)
    rng = np.random.default_rng(2)
    uv = torch.from_numpy(rng.random((3000, 2)) * 30 - 10)
    footprint = torch.from_numpy(np.exp(rng.uniform(-1, 6, 3000)))  # 0.4 .. 400 texels
    a, b = fast(uv, footprint), slow(uv, footprint)
    # hist: level 0's reference inverts exactly, the kernel with its table (as for point queries)
    tolerance = 2e-3 if method == "hist" else 5e-4
    torch.testing.assert_close(a, b, atol=tolerance * float(b.std()), rtol=tolerance)


@pytest.mark.parametrize("method", METHODS)
def test_filtered_features_converge_to_the_brute_force_mean(exemplar, method):
    """At a footprint of many repeats the answer is the plane's mean; the error falls as the footprint grows."""
    synth = make_synthesizer(method, exemplar, seed=9)
    uv = np.random.default_rng(3).random((16, 2)) * 50
    spread = float(synth(torch.from_numpy(uv)).std())
    errors = []
    for repeats, k in ((0.5, 16), (4.0, 48), (32.0, 96)):
        side = np.full(16, repeats)
        texels = torch.full((16,), repeats * float(np.sqrt(40 * 48)))
        filtered = synth(torch.from_numpy(uv), texels).numpy()
        brute = brute_force_mean(lambda p: synth(torch.from_numpy(p)).numpy(), uv, side, k)
        errors.append(float(np.abs(filtered - brute).mean()) / spread)
    assert errors[2] < errors[0], errors
    assert errors[2] < 0.03, errors


# ---------------------------------------------------------------- the synthesized BTF
@pytest.fixture(scope="module")
def btf():
    return synthesized_btf(TriplePlane(32, 32, seed=3), "hist", scale=4.0, seed=1, footprints=True)


def directions(n, seed):
    rng = np.random.default_rng(seed)
    w = spherical_to_direction(rng.random((2, n)) * 70.0, rng.random((2, n)) * 360.0)
    return w[0], w[1]


def test_eval_without_footprint_is_the_point_query_and_one_texel_is_close(btf):
    uv = np.random.default_rng(4).random((3000, 2)) * 5 + 1e5
    wv, wl = directions(3000, 5)
    point = btf.eval(uv, wv, wl)
    np.testing.assert_array_equal(btf.eval(uv, wv, wl, footprint=None), point)
    one_texel = 1.0 / btf.texels_per_uv()
    for footprint in (0.0, one_texel, np.full(3000, 0.5 * one_texel)):
        np.testing.assert_allclose(btf.eval(uv, wv, wl, footprint=footprint), point, atol=2e-4, rtol=2e-4)


def test_constant_model_filters_to_itself():
    model = TriplePlane(16, 16, seed=0)
    with torch.no_grad():
        model.f_u[:] = torch.linspace(-1, 1, model.f_u.shape[-1])
    uv = np.random.default_rng(6).random((400, 2)) * 3
    wv, wl = directions(400, 7)
    for level_decoders in (False, True):  # the plain decoder on filtered features, and the fitted level decoders
        btf = synthesized_btf(model, "hist", scale=3.0, footprints=level_decoders, level_decoders=level_decoders)
        point = btf.eval(uv, wv, wl)
        np.testing.assert_allclose(btf.eval(uv, wv, wl, footprint=np.full(400, 2.5)), point, atol=1e-5, rtol=1e-4)


def test_filtered_btf_converges_to_the_supersampled_mean(btf):
    """Decoded: the filtered query vs the brute-force mean of point queries over its square, averaged over
    three (view, light) pairs; the per-level decoders must beat the plain decoder on filtered features."""
    plain = synthesized_btf(btf.model, "hist", scale=btf.scale, seed=btf.seed, level_decoders=False)
    uv = np.random.default_rng(8).random((12, 2)) * 20
    errors = {True: np.zeros(3), False: np.zeros(3)}
    for pair in (9, 10, 11):
        wv, wl = directions(1, pair)
        spread = float(btf.eval(np.random.default_rng(10).random((4000, 2)) * 20, np.repeat(wv, 4000, 0),
                                np.repeat(wl, 4000, 0)).std())
        wv, wl = np.repeat(wv, 12, 0), np.repeat(wl, 12, 0)
        for k, (side, grid) in enumerate(((0.02, 12), (1.0, 48), (8.0, 96))):
            sides = np.full(12, side)
            brute = brute_force_mean(lambda p: btf.eval(p, wv, wl), uv, sides, grid, seed=pair)
            for level_decoders, model in ((True, btf), (False, plain)):
                filtered = model.eval(uv, wv, wl, footprint=sides)
                errors[level_decoders][k] += float(np.abs(filtered - brute).mean()) / spread / 3
    ours = errors[True]
    assert ours[2] < ours[0] and ours[2] < 0.12, errors
    assert ours[2] < 0.6 * errors[False][2], errors  # measured: 0.09 vs 0.26


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), [0.1, -0.2, 0.3]])
def test_bad_footprints_name_the_argument(btf, bad):
    uv = np.zeros((3, 2))
    w = np.tile([0.0, 0.0, 1.0], (3, 1))
    with pytest.raises(InputError, match="footprint"):
        btf.eval(uv, w, w, footprint=bad)
    with pytest.raises(InputError, match="footprint.*shape"):
        btf.eval(uv, w, w, footprint=np.ones(4))


def test_footprint_larger_than_the_exemplar_is_the_mean_appearance(btf):
    uv = np.random.default_rng(11).random((50, 2)) * 1e3
    wv, wl = directions(1, 12)
    out = btf.eval(uv, np.repeat(wv, 50, 0), np.repeat(wl, 50, 0), footprint=1e4)
    np.testing.assert_allclose(out, np.repeat(out[:1], 50, 0), rtol=1e-5, atol=1e-6)


def test_quilting_filters_too(exemplar):
    synth = make_synthesizer("quilt", exemplar, seed=0, repeats=2.0)
    uv = torch.from_numpy(np.random.default_rng(13).random((100, 2)) * 4)
    torch.testing.assert_close(synth(uv, torch.full((100,), 0.5)), synth(uv))
    big = synth(uv, torch.full((100,), 1e6))
    torch.testing.assert_close(big, synth.prepared.mean((0, 1)).expand(100, -1), atol=1e-5, rtol=1e-5)


# ---------------------------------------------------------------- footprints from camera geometry
def test_plane_footprint_matches_finite_differences_of_hit_points():
    camera = grazing_camera(distance=6.0, height=0.6, fov=40.0)
    h, w = 40, 50

    def hits(jitter):
        o, d = camera.rays(h, w, np.array(jitter))
        return o + (-o[2] / d[..., 2])[..., None] * d, d

    p, d = hits([0.0, 0.0])
    eps = 1e-4
    dx = (hits([eps, 0.0])[0] - hits([-eps, 0.0])[0])[..., :2] / (2 * eps)
    dy = (hits([0.0, eps])[0] - hits([0.0, -eps])[0])[..., :2] / (2 * eps)
    rows = d[..., 2] < -0.02
    expected = footprint_width(dx[rows], dy[rows])
    np.testing.assert_allclose(plane_footprint(camera, d[rows], h, w), expected, rtol=1e-4)
    np.testing.assert_allclose(plane_footprint(camera, d[rows], h, w, spp=4), expected / 2, rtol=1e-4)


def test_filtered_preview_is_close_to_the_supersampled_one():
    btf = synthesized_btf(TriplePlane(32, 32, seed=3), "hist", scale=20.0, seed=1, footprints=True)
    camera = PinholeCamera(origin=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=40.0)
    light = DirectionalLight((0.2, 0.1, 0.9), 1.0)
    reference = render_preview(btf, camera, light, resolution=(24, 24), spp=64)
    point = render_preview(btf, camera, light, resolution=(24, 24), spp=1)
    filtered = render_preview(btf, camera, light, resolution=(24, 24), spp=1, filtered=True)
    err_point = float(np.abs(point - reference).mean())
    err_filtered = float(np.abs(filtered - reference).mean())
    assert err_filtered < 0.5 * err_point, (err_filtered, err_point)


def test_synth_cli_filtered_matches_the_library(tmp_path):
    """``dynbtf synth --filtered`` writes what ``SynthesizedBTF.image(..., filtered=True)`` computes."""
    from dynbtf.cli.main import main
    from dynbtf.representations.model_file import save_model

    model = TriplePlane(16, 16, seed=4)
    path = save_model(tmp_path / "m.dbtfm", model)
    out = tmp_path / "f.exr"
    assert main(["synth", str(path), "--scale", "30", "--resolution", "12", "--filtered", "-o", str(out)]) == 0
    import OpenEXR  # noqa: F401  (written as linear float32)
    from dynbtf.io import load_image

    expected = synthesized_btf(path, "hist", scale=30.0, footprints=True).image((0, 0), (30, 0), (0.0, 0.0, 1.0, 1.0), 12,
                                                               filtered=True)
    np.testing.assert_allclose(load_image(out), expected, rtol=1e-4, atol=1e-5)


def test_level_decoders_are_fitted_once_per_model_contents_and_seed(btf, tmp_path, monkeypatch):
    """Per-level decoders are fitted once per model contents, method and seed (when a material is compiled with
    footprints, not by a query), then read from the compiled-material cache: a model loaded again shares the fit; another seed fits its own (its targets are that seed's synthesized
    BTF), so a seed's answers never depend on what ran before; other parameters get their own fit."""
    import copy

    import dynbtf.material.compiler as compile_module
    from dynbtf.synthesized import synthesized_btf

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path / "cache"))
    fits = []
    real = compile_module.fit_footprint_decoders
    monkeypatch.setattr(compile_module, "fit_footprint_decoders",
                        lambda decoder, synth, *a, **k: fits.append(synth.seed) or real(decoder, synth, *a, **k))
    uv = np.array([[0.3, 0.7]])
    w = np.array([[0.0, 0.0, 1.0]])
    first = synthesized_btf(btf.model, "hist", scale=2.0, seed=5, footprints=True)
    a = first.eval(uv, w, w, footprint=0.3)
    twin = synthesized_btf(copy.deepcopy(btf.model), "hist", scale=2.0, seed=5, footprints=True)  # equal parameters, another object
    np.testing.assert_array_equal(twin.eval(uv, w, w, footprint=0.3), a)
    assert fits == [5]
    synthesized_btf(btf.model, "hist", scale=2.0, seed=6, footprints=True).eval(uv, w, w, footprint=0.3)
    assert fits == [5, 6]
    changed = copy.deepcopy(btf.model)
    with torch.no_grad():
        changed.decoder.rest[-1].bias.add_(0.1)
    synthesized_btf(changed, "hist", scale=2.0, seed=5, footprints=True).eval(uv, w, w, footprint=0.3)
    assert fits == [5, 6, 5]  # other parameters: its own fit


def test_a_query_never_fits_and_a_material_without_footprint_decoders_says_so(btf, monkeypatch):
    """The query object answers from the material it is given: footprint queries of a material compiled without
    footprint decoders decode every level with the point decoder (the same as ``level_decoders=False``), with one
    warning, and fit nothing."""
    import dynbtf.material.compiler as compile_module

    def no_fit(*args, **kwargs):
        raise AssertionError("a query fitted footprint decoders")

    monkeypatch.setattr(compile_module, "fit_footprint_decoders", no_fit)
    material = btf.material
    point_only = replace(material, decoder=material.decoder.with_footprints(material.decoder.levels[:1], None))
    bare = SynthesizedBTF(point_only, btf.scale)
    plain = SynthesizedBTF(material, btf.scale, level_decoders=False)
    uv = np.random.default_rng(14).random((200, 2)) * 9
    wv, wl = directions(200, 15)
    with pytest.warns(UserWarning, match="without footprint decoders.*point decoder"):
        got = bare.eval(uv, wv, wl, footprint=np.full(200, 0.4))
    np.testing.assert_array_equal(got, plain.eval(uv, wv, wl, footprint=np.full(200, 0.4)))
    with pytest.raises(InputError, match="mean_appearance: this material has no mean appearance"):
        bare.mean_appearance(torch.from_numpy(wv).float(), torch.from_numpy(wl).float())


def test_the_query_object_takes_a_compiled_material_only(btf, tmp_path):
    from dynbtf.representations.model_file import save_model

    with pytest.raises(InputError, match="expected a compiled material .*synthesized_btf"):
        SynthesizedBTF(btf.model, 4.0)
    path = save_model(tmp_path / "m.dbtfm", btf.model)
    with pytest.raises(InputError, match="m.dbtfm: not a compiled material"):
        SynthesizedBTF(path)
