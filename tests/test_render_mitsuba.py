"""The ``dynbtf`` Mitsuba plugin: same numbers as dynbtf's own evaluation, correct sampling, small renders."""

from __future__ import annotations

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

pytestmark = pytest.mark.mitsuba

#: Plugin vs SynthesizedBTF.eval with the paper-size decoder, times max(1, |value|)
#: (measured max differences 0.9e-5 to 2.3e-5 on values up to 0.5, two seeds, tile/hist/hex)
TOLERANCE_PAPER_SIZE = 1e-4


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    """A small random Triple Plane (not fitted: every weight matters, nothing is smooth) saved to disk."""
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(24, 20, positional_channels=6, angular_channels=3, hidden=12, seed=5)  # small: fast kernel compiles
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)  # mostly positive values, like a material
    path = tmp_path_factory.mktemp("model") / "random.dbtfm"
    save_model(path, model)
    return path, model


def _random_queries(n, seed, uv_range=40.0):
    rng = np.random.default_rng(seed)
    uv = ((rng.random((n, 2)) - 0.5) * uv_range).astype(np.float32)

    def hemisphere(n):
        w = rng.normal(size=(n, 3))
        w[:, 2] = np.abs(w[:, 2]) + 0.05
        return (w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)

    wv, wl = hemisphere(n), hemisphere(n)
    wv[:4] = wl[:4] = [0.0, 0.0, 1.0]  # the Rusinkiewicz pole
    return uv, wv, wl


def _plugin_eval(bsdf, uv, wv, wl, scale, dp_dv=(0.0, 1.0, 0.0), duv_dx=None, duv_dy=None, t=None,
                 dp_du=(1.0, 0.0, 0.0)):
    """``bsdf.eval`` ``(n, 3)`` at mesh uv ``uv / scale``, local directions ``wv, wl (n, 3)``.

    The shading frame is the identity (s = x, t = y, n = z) with ``dp/du = dp_du`` (x) and
    ``dp/dv = dp_dv``: ``+y`` a right-handed parametrization (Mitsuba's rectangle),
    ``-y`` a left-handed one (Mitsuba's sphere). ``duv_dx, duv_dy`` ``(n, 2)`` (mesh uv per
    pixel) and the hit distance ``t`` ``(n,)`` are set when given (zero otherwise).
    """
    n = len(uv)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.uv = mi.Point2f(mi.Float(uv[:, 0] / scale), mi.Float(uv[:, 1] / scale))
    si.wi = mi.Vector3f(*(mi.Float(wv[:, k]) for k in range(3)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.dp_du = mi.Vector3f(*dp_du)
    si.dp_dv = mi.Vector3f(*dp_dv)
    if duv_dx is not None:
        si.duv_dx = mi.Vector2f(mi.Float(duv_dx[:, 0]), mi.Float(duv_dx[:, 1]))
        si.duv_dy = mi.Vector2f(mi.Float(duv_dy[:, 0]), mi.Float(duv_dy[:, 1]))
    if t is not None:
        si.t = mi.Float(t)
    wo = mi.Vector3f(*(mi.Float(wl[:, k]) for k in range(3)))
    out = np.array(bsdf.eval(mi.BSDFContext(), si, wo), dtype=np.float64)
    return out.reshape(n, 3) if out.shape == (n, 3) else out.T


def _reference(model, method, seed, uv, wv, wl):
    """dynbtf's own evaluation: SynthesizedBTF.eval (plain model for tiling when synthesis is absent)."""
    from dynbtf.synthesized import synthesized_btf

    btf = synthesized_btf(model, method, scale=1.0, seed=seed)
    out = btf.eval(torch.from_numpy(uv.astype(np.float64)), torch.from_numpy(wv), torch.from_numpy(wl))
    return np.asarray(out.detach().cpu().numpy() if hasattr(out, "detach") else out, dtype=np.float64)


@pytest.mark.parametrize("method", ["tile", "hist", "hex"])
def test_plugin_eval_matches_synthesized_btf(variant, model_file, method):
    path, model = model_file
    _assert_plugin_matches(path, model, method)


def _assert_plugin_matches(path, model, method, *, n=4000, scale=7.0, seed=3, tolerance=2e-4):
    """The plugin's ``eval`` equals ``SynthesizedBTF.eval / pi * cos`` at ``n`` random queries over +-20 repeats.

    Returns ``(plugin, reference)`` values ``(n, 3)``.
    """
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": method, "scale": scale, "seed": seed})
    uv, wv, wl = _random_queries(n, seed=1)
    # feed the plugin mesh uv = uv / scale; what it evaluates is scale * (uv / scale) in float32
    uv = (uv / np.float32(scale)) * np.float32(scale)
    got = _plugin_eval(bsdf, uv, wv, wl, scale)
    ref = _reference(model, method, seed, uv, wv, wl) / np.pi * wl[:, 2:3]
    assert np.abs(ref).max() > 0.05  # the comparison is not between zeros
    # float32 kernels on both sides; differences come from summation order and transcendental ulps
    np.testing.assert_allclose(got, ref, rtol=0, atol=tolerance * max(1.0, np.abs(ref).max()))
    return got, ref


@pytest.fixture(scope="module")
def neumip_file(tmp_path_factory):
    """A small random NeuMIP (the paper's modified one: texture features + light/view xy into the MLP)."""
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.neumip import NeuMIP

    model = NeuMIP(20, 24, channels=5, hidden=12, seed=2)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
    path = tmp_path_factory.mktemp("neumip") / "neumip.dbtfm"
    save_model(path, model)
    return path, model


@pytest.mark.parametrize("method", ["tile", "hist"])
def test_plugin_eval_matches_synthesized_btf_for_neumip(variant, neumip_file, method):
    path, model = neumip_file
    _assert_plugin_matches(path, model, method, n=3000)


@pytest.fixture(scope="module")
def parallax_file(tmp_path_factory):
    """A small random triple-parallax model with a relief of ~3 texels (waves plus noise) saved to disk."""
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.parallax import ParallaxTriplePlane

    model = ParallaxTriplePlane(24, 20, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    generator = torch.Generator().manual_seed(4)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
        yy, xx = torch.meshgrid(torch.arange(24.0), torch.arange(20.0), indexing="ij")
        waves = torch.sin(2 * np.pi * xx / 10) * torch.cos(2 * np.pi * yy / 8)
        model.set_height(0.05 * (waves + 0.3 * torch.rand(24, 20, generator=generator)))
    path = tmp_path_factory.mktemp("parallax") / "parallax.dbtfm"
    save_model(path, model)
    return path, model


@pytest.mark.parametrize("method", ["tile", "hist", "hex"])
def test_plugin_marches_parallax_like_synthesized_btf(variant, parallax_file, method):
    """triple-parallax: the kernel's march through the synthesized height lands where dynbtf's does.

    Within 1e-3 of the value range (measured: ~2.5e-5); and the march matters: fetching the
    features at ``uv`` itself (no march) is off by far more.
    """
    from dynbtf.synthesized import synthesized_btf

    path, model = parallax_file
    got, ref = _assert_plugin_matches(path, model, method, n=3000, tolerance=1e-3 * 0.5)
    assert np.abs(got - ref).max() < 1e-3 * (ref.max() - ref.min())
    uv, wv, wl = _random_queries(3000, seed=1)
    uv = (uv / np.float32(7.0)) * np.float32(7.0)
    flat = synthesized_btf(model, method, scale=1.0, seed=3)
    flat.relief = False  # the same model answered at uv: no parallax
    no_march = flat.eval(uv.astype(np.float64), wv, wl) / np.pi * wl[:, 2:3]
    assert np.abs(no_march - ref).max() > 50 * np.abs(got - ref).max()


def test_plugin_eval_matches_synthesized_btf_with_paper_size_decoder(variant, tmp_path):
    """The paper's Triple Plane: f_U with 16 channels, 20 x 20 x 8 angular planes, 4 layers of 32 hidden units.

    Random (unfitted) weights: every one of the ~3,000 unrolled multiply-adds matters. The
    first evaluation compiles the full-size kernel (tens of seconds on a busy CPU).
    """
    from dynbtf.representations.model_file import load_model, save_model
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(32, 40, positional_channels=16, angular_resolution=20, angular_channels=8, hidden=32,
                        layers=4, seed=11)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
    path = save_model(tmp_path / "paper_size.dbtfm", model)
    loaded, _ = load_model(path)
    assert tuple(loaded.f_u.shape) == (32, 40, 16) and tuple(loaded.f_h.shape) == (20, 20, 8)
    assert [tuple(x.weight.shape) for x in [loaded.decoder.first, *loaded.decoder.rest]] == \
        [(32, 32), (32, 32), (32, 32), (3, 32)]
    _assert_plugin_matches(path, loaded, "hist", n=2000, tolerance=TOLERANCE_PAPER_SIZE)


def test_plugin_mirrors_directions_on_left_handed_uv(variant, model_file):
    """Mitsuba's sphere has ``n x dp/du = -dp/dv``: the BTF's y (+v) is then the frame's -t.

    On a left-handed parametrization the plugin evaluates the BTF at directions mirrored
    in y, so that light from +v casts the shadows the measured material casts towards -v.
    """
    path, model = model_file
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "tile", "scale": 1.0})
    uv, wv, wl = _random_queries(500, seed=6, uv_range=4.0)
    mirror = np.array([1.0, -1.0, 1.0], dtype=np.float32)
    right = _plugin_eval(bsdf, uv, wv, wl, 1.0, dp_dv=(0.0, 1.0, 0.0))
    left = _plugin_eval(bsdf, uv, wv, wl, 1.0, dp_dv=(0.0, -2.0, 0.3))
    ref = _reference(model, "tile", 0, uv, wv, wl) / np.pi * wl[:, 2:3]
    ref_mirrored = _reference(model, "tile", 0, uv, wv * mirror, wl * mirror) / np.pi * wl[:, 2:3]
    np.testing.assert_allclose(right, ref, rtol=0, atol=2e-4)
    np.testing.assert_allclose(left, ref_mirrored, rtol=0, atol=2e-4)
    assert np.abs(ref - ref_mirrored).max() > 0.01  # mirroring changes this model's values


def test_sphere_is_left_handed_and_rectangle_right_handed(variant):
    """The fact the mirroring above is for: Mitsuba's uv orientation on its built-in shapes."""
    def handedness(shape, origin, direction):
        si = shape.ray_intersect(mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(*direction)))
        return float(dr.dot(si.sh_frame.t, dr.normalize(si.dp_dv))[0])

    rect = mi.load_dict({"type": "rectangle"})
    sphere = mi.load_dict({"type": "sphere"})
    assert handedness(rect, (0.3, -0.2, 1.0), (0, 0, -1)) == pytest.approx(1.0, abs=1e-5)
    assert handedness(sphere, (0.2, -5.0, 0.3), (0, 1, 0)) == pytest.approx(-1.0, abs=1e-5)


def test_plugin_is_zero_below_either_horizon(variant, model_file):
    path, _ = model_file
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "tile"})
    uv, wv, wl = _random_queries(64, seed=2)
    below = wl * np.array([1, 1, -1], dtype=np.float32)
    assert np.all(_plugin_eval(bsdf, uv, wv, below, 1.0) == 0.0)
    assert np.all(_plugin_eval(bsdf, uv, below, wl, 1.0) == 0.0)


def test_plugin_query_hands_over_only_the_active_lanes(variant, model_file):
    """The plugin's query (``DynBTFEvaluator.eval``) is ``SynthesizedBTF.eval`` on the active lanes, bit for bit,
    point and footprint queries alike, and zero on the others; a wavefront with no active lane answers zeros."""
    from dynbtf.render.mitsuba.evaluator import DynBTFEvaluator
    from dynbtf.synthesized import synthesized_btf

    _, model = model_file
    btf = synthesized_btf(model, "hist", seed=4, footprints=True)
    evaluator = DynBTFEvaluator(btf)
    uv, wv, wl = _random_queries(500, seed=6)
    active = np.random.default_rng(7).random(500) < 0.4
    footprint = np.random.default_rng(8).random(500).astype(np.float32) * 0.3
    args = (mi.Float(uv[:, 0]), mi.Float(uv[:, 1]), mi.Vector3f(*wv.T), mi.Vector3f(*wl.T))
    for width in (None, footprint):
        got = evaluator.eval(*args, mi.Bool(active), footprint=None if width is None else mi.Float(width))
        got = np.stack([np.asarray(got[k]) for k in range(3)], -1)
        want = btf.eval(uv[active].astype(np.float64), wv[active], wl[active],
                        None if width is None else width[active].astype(np.float64))
        np.testing.assert_array_equal(got[active], want)
        assert np.all(got[~active] == 0.0) and np.abs(want).max() > 0.1
    none = evaluator.eval(*args, mi.Bool(np.zeros(500, bool)))
    assert np.all(np.stack([np.asarray(none[k]) for k in range(3)]) == 0.0)


def test_plugin_sampling_passes_chi2_and_weight_is_value(variant, model_file):
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    path, model = model_file
    spec = {"type": "dynbtf", "filename": str(path), "method": "tile", "sampling": "cosine"}
    wi = dr.normalize(mi.ScalarVector3f(0.3, -0.2, 0.9))
    sample_func, pdf_func = BSDFAdapter("dynbtf", spec, wi=wi)
    test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=200_000, res=16, ires=16)
    assert test.run(), test.messages

    # the pdf integrates to one over the sphere (midpoint rule in (cos theta, phi))
    bsdf = mi.load_dict(spec)
    pdf, cell = _pdf_on_sphere(bsdf, wi, n=256)
    integral = pdf.sum() * cell
    assert abs(integral - 1.0) < 2e-3

    # sample() returns eval / pdf = the BTF value itself
    m = 512
    si = dr.zeros(mi.SurfaceInteraction3f, m)
    si.wi = wi
    si.uv = mi.Point2f(0.3, 0.7)
    rng = np.random.default_rng(0)
    bs, weight = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(m)), mi.Point2f(mi.Float(rng.random(m)), mi.Float(rng.random(m))))
    ev = np.array(bsdf.eval(mi.BSDFContext(), si, bs.wo))
    pd = np.array(bsdf.pdf(mi.BSDFContext(), si, bs.wo))
    w = np.array(weight)
    ok = pd > 1e-3
    ok_rows = ok.reshape(-1) if ok.ndim == 1 else ok
    np.testing.assert_allclose(w.reshape(-1, 3)[ok_rows] if w.shape[-1] == 3 else w.T[ok_rows],
                               (ev.reshape(-1, 3) if ev.shape[-1] == 3 else ev.T)[ok_rows] / pd[ok_rows][:, None],
                               rtol=1e-4, atol=1e-6)


def test_bad_parameters_are_clear_errors(variant, model_file, tmp_path):
    path, _ = model_file
    with pytest.raises(Exception, match="method"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "voronoi"})
    with pytest.raises(Exception, match="scale"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "scale": -2.0})
    with pytest.raises(Exception, match="not found"):
        mi.load_dict({"type": "dynbtf", "filename": str(tmp_path / "missing.dbtfm")})
    with pytest.raises(Exception, match="ray_cone_angle"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "ray_cone_angle": -0.01})


def test_small_render_of_a_plane_matches_direct_lighting_by_hand(variant, model_file):
    """A 24x24 render of a plane under a point light, direct lighting only, against the closed form
    ``L = value / pi * cos(theta_l) * I / r^2`` evaluated with dynbtf at each pixel's hit point."""
    path, model = model_file
    from dynbtf.render.mitsuba.scenes import bsdf_dict

    res = 24
    scale = 3.0
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "plane": {"type": "rectangle", "bsdf": bsdf_dict(path, method="tile", scale=scale)},
        "light": {"type": "point", "position": [0.4, 0.3, 1.5], "intensity": {"type": "rgb", "value": [2.0] * 3}},
    })
    # deterministic pixel centres: jittered film samples would blur the texture; use many spp and compare means
    img = np.array(mi.render(scene, spp=64), dtype=np.float64)
    assert img.shape == (res, res, 3) and np.isfinite(img).all() and img.mean() > 0.01

    # reference: supersample the same pixels (64 stratified points each) with dynbtf's evaluation.
    # Mitsuba's film: columns run along the camera's right (here +x: looking down -z with up +y),
    # rows downwards (top = +y); its rectangle maps x, y in [-1, 1] to uv = ((x + 1) / 2, (y + 1) / 2)
    k = 8
    sub = (np.arange(k) + 0.5) / k
    px = (np.arange(res)[:, None] + sub[None, :]).ravel() / res  # film x (or y) in [0, 1)
    xx, yy = np.meshgrid(px, px)  # yy: film rows
    world_x = 2.0 * xx - 1.0
    world_y = 1.0 - 2.0 * yy
    pts = np.stack([world_x, world_y, np.zeros_like(world_x)], -1).reshape(-1, 3)
    uv_mesh = np.stack([(pts[:, 0] + 1) / 2, (pts[:, 1] + 1) / 2], -1)
    to_light = np.array([0.4, 0.3, 1.5]) - pts
    r2 = (to_light ** 2).sum(-1)
    wl = to_light / np.sqrt(r2)[:, None]
    wv = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    uv = (uv_mesh * scale).astype(np.float32)
    with torch.no_grad():
        value = model(torch.from_numpy(uv.astype(np.float64)), torch.from_numpy(wv).float(),
                      torch.from_numpy(wl).float()).double().numpy()
    radiance = value / np.pi * wl[:, 2:3] * 2.0 / r2[:, None]
    ref = radiance.reshape(res, k, res, k, 3).mean(axis=(1, 3))
    err = np.abs(img - ref).mean()
    assert err < 0.03 * ref.mean(), err
    # the comparison fixes the orientation: each mirror image of the reference is far off
    for mirrored in (ref[:, ::-1], ref[::-1], ref[::-1, ::-1]):
        assert np.abs(img - mirrored).mean() > 5 * err


def test_plugin_scales_u_and_v_separately(variant, model_file):
    """``scale_v`` (used on spheres) multiplies mesh v, ``scale`` mesh u."""
    path, model = model_file
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "tile", "scale": 2.0, "scale_v": 5.0})
    uv_mesh, wv, wl = _random_queries(500, seed=4, uv_range=4.0)
    n = len(uv_mesh)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.uv = mi.Point2f(mi.Float(uv_mesh[:, 0]), mi.Float(uv_mesh[:, 1]))
    si.wi = mi.Vector3f(*(mi.Float(wv[:, k]) for k in range(3)))
    got = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*(mi.Float(wl[:, k]) for k in range(3)))))
    got = got.reshape(n, 3) if got.shape == (n, 3) else got.T
    uv = uv_mesh * np.array([2.0, 5.0], dtype=np.float32)
    ref = _reference(model, "tile", 0, uv, wv, wl) / np.pi * wl[:, 2:3]
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-4 * max(1.0, np.abs(ref).max()))


# ---------------------------------------------------------------- importance sampling
def _tiny_fit(material, path):
    """A Triple Plane fitted for a few seconds to a 16 x 16 simulated BTF (deterministic)."""
    from dynbtf.data.open import open_btf
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.training.fit import TrainConfig, fit

    src = open_btf(f"sim:{material}?size=16")
    rep = TriplePlane(src.height, src.width, positional_channels=4, angular_channels=4, hidden=16, seed=0)
    config = TrainConfig(epochs=3, lr_scale=6.0, seed=0, monitor_pairs=0, device="cpu", precision="fp32",
                         workers=1, texel_groups=16)
    fit(rep, src, config, path, progress=False)
    return path


@pytest.fixture(scope="module")
def fitted_files(tmp_path_factory):
    """Small fitted models: lacquered wood (glossy clear coat) and leather (rough, diffuse-ish)."""
    folder = tmp_path_factory.mktemp("fitted")
    return {m: _tiny_fit(m, folder / f"{m}.dbtfm") for m in ("lacquered_wood", "leather")}


def _pdf_on_sphere(bsdf, wi, n=128):
    """``bsdf.pdf`` on a midpoint grid in (cos theta, phi) over the sphere, and the cell's solid angle."""
    c = (np.arange(n) + 0.5) / n * 2 - 1
    p = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    cc, pp = np.meshgrid(c, p, indexing="ij")
    s = np.sqrt(1 - cc ** 2)
    wo = mi.Vector3f(mi.Float((s * np.cos(pp)).ravel()), mi.Float((s * np.sin(pp)).ravel()), mi.Float(cc.ravel()))
    si = dr.zeros(mi.SurfaceInteraction3f, n * 2 * n)
    si.wi = wi
    return np.array(bsdf.pdf(mi.BSDFContext(), si, wo)), (2.0 / n) * (2 * np.pi / (2 * n))


@pytest.mark.parametrize("material, wi", [("lacquered_wood", (0.3, -0.2, 0.9)), ("leather", (0.3, -0.2, 0.9)),
                                         ("leather", (0.8, 0.3, 0.3))])
def test_mixture_sampling_passes_chi2(variant, fitted_files, material, wi):
    """``sample`` draws what ``pdf`` says (Mitsuba's chi-square test, as its own BSDF tests), and ``pdf``
    integrates to what the histogram holds; on the glossy model the mixture's density is far from cosine's.

    (The glossy model at the grazing view is tested on the table's own square below: there its
    piecewise-constant cells, curved on the sphere, defeat the sphere test's Simpson integration of
    the pdf -- p ~ 0.001-0.008 with the pdf's and the histogram's sums within 1e-3.)"""
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    spec = {"type": "dynbtf", "filename": str(fitted_files[material]), "method": "hist", "sampling": "mixture"}
    wi = dr.normalize(mi.ScalarVector3f(*wi))
    sample_func, pdf_func = BSDFAdapter("dynbtf", spec, wi=wi)
    test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=300_000, res=32, ires=32)
    assert test.run(), test.messages
    # the pdf integrates to at most 1 (the table's bilinear density reaches a little below the horizon,
    # where samples are lost: measured 11% at 72 degrees), as the histogram says
    pdf_sum, histogram_sum = (float(np.sum(np.array(x))) / test.sample_count for x in (test.pdf, test.histogram))
    assert 0.85 < pdf_sum < 1.002 and abs(pdf_sum - histogram_sum) < 0.005, (pdf_sum, histogram_sum)
    pdf, _ = _pdf_on_sphere(mi.load_dict(spec), wi)
    cosine, _ = _pdf_on_sphere(mi.load_dict({**spec, "sampling": "cosine"}), wi)
    if material == "lacquered_wood":  # the table follows the clear coat's highlight
        assert pdf.max() > 3 * cosine.max(), (pdf.max(), cosine.max())


@pytest.mark.parametrize("wi", [(0.3, -0.2, 0.9), (0.8, 0.3, 0.3)])
def test_table_sampler_draws_its_density_exactly(variant, fitted_files, wi):
    """On the square of the half vector in the view's azimuthal frame (``h_view = R_z(-phi_view) h``),
    where its density is constant on each of R x R cells, the table sampler's draws follow the blend of
    its four view nodes' cell densities (chi-square with exact cell integrals), and ``pdf`` of a drawn
    direction is that density over the Jacobian ``8 pi (w_light . h)``."""
    from scipy import stats

    from dynbtf.render.mitsuba.sampling import DrTableSampler, build_sampling_table
    from dynbtf.representations.model_file import load_model

    model, _ = load_model(fitted_files["lacquered_wood"])
    sampler = DrTableSampler(build_sampling_table(model))
    r, n = sampler.resolution, 1_000_000
    rng = np.random.default_rng(3)
    w = np.asarray(wi) / np.linalg.norm(wi)
    wv = mi.Vector3f(*(mi.Float(np.full(n, c, dtype=np.float32)) for c in w))
    wo = sampler.sample(wv, mi.Float(rng.random(n)), mi.Point2f(mi.Float(rng.random(n)), mi.Float(rng.random(n))))
    up = np.array(wo.z) > 0
    h = dr.normalize(wv + wo)
    c, s = w[:2] / np.hypot(w[0], w[1])  # the view's azimuth: h_view = R_z(-phi_view) h
    h_view = mi.Vector3f(c * h.x + s * h.y, -s * h.x + c * h.y, h.z)
    square = mi.warp.uniform_hemisphere_to_square(h_view)
    x, y = np.array(square.x)[up], np.array(square.y)[up]
    counts, _, _ = np.histogram2d(y, x, bins=r, range=[[0, 1], [0, 1]])
    cells = np.array(sampler.cells).reshape(-1, r, r)
    one = mi.Vector3f(*(mi.Float([c]) for c in w))
    density = sum(float(np.array(weight)[0]) * cells[int(np.array(node)[0])] for node, weight in sampler._nodes(one))
    # directions below the horizon are lost: compare where the cells' light directions are all above it
    centres = (np.arange(r) + 0.5) / r
    cy, cx = np.meshgrid(centres, centres, indexing="ij")
    hv = mi.warp.square_to_uniform_hemisphere(mi.Point2f(mi.Float(cx.ravel()), mi.Float(cy.ravel())))
    hx, hy, hz = np.array(hv.x), np.array(hv.y), np.array(hv.z)
    hc = np.stack([c * hx - s * hy, s * hx + c * hy, hz], -1)  # h = R_z(phi_view) h_view
    wl = 2 * (hc @ w)[:, None] * hc - w
    expected = density / r ** 2 * n
    use = (expected > 20) & (wl[:, 2].reshape(r, r) > 0.05)
    chi = ((counts[use] - expected[use]) ** 2 / expected[use]).sum()
    assert use.sum() > 100 and stats.chi2.sf(chi, use.sum() - 1) > 0.01, (chi, use.sum())
    pdf = np.array(sampler.pdf(wv, wo))[up]
    cos_lh = np.array(dr.dot(wo, h))[up]
    col = np.minimum((x * r).astype(int), r - 1)
    row = np.minimum((y * r).astype(int), r - 1)
    # this test's float rotation may put a point within rounding of a cell edge into the neighbouring cell
    inner = (np.abs(x * r - np.round(x * r)) > 1e-4) & (np.abs(y * r - np.round(y * r)) > 1e-4)
    assert inner.mean() > 0.99
    np.testing.assert_allclose((pdf * 8 * np.pi * cos_lh)[inner], density[row, col][inner], rtol=1e-4)


def test_mixture_sample_weight_is_eval_over_pdf(variant, fitted_files):
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(fitted_files["lacquered_wood"]), "method": "hist",
                         "scale": 3.0, "sampling_weight": 0.6})
    m = 4096
    rng = np.random.default_rng(1)
    si = dr.zeros(mi.SurfaceInteraction3f, m)
    si.wi = dr.normalize(mi.Vector3f(0.4, 0.1, 0.8))
    si.uv = mi.Point2f(mi.Float(rng.random(m)), mi.Float(rng.random(m)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.dp_dv = mi.Vector3f(0.0, -1.0, 0.0)  # left-handed: the table is sampled in the mirrored frame
    bs, weight = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(m)),
                             mi.Point2f(mi.Float(rng.random(m)), mi.Float(rng.random(m))))
    ev, pd = bsdf.eval_pdf(mi.BSDFContext(), si, bs.wo)
    ev, pd, w = np.array(ev).reshape(-1, 3) if np.array(ev).shape[-1] == 3 else np.array(ev).T, np.array(pd), None
    w = np.array(weight)
    w = w.reshape(-1, 3) if w.shape[-1] == 3 else w.T
    np.testing.assert_allclose(np.array(bs.pdf), pd, rtol=1e-5, atol=1e-7)
    ok = pd > 1e-3
    assert ok.mean() > 0.9
    np.testing.assert_allclose(w[ok], ev[ok] / pd[ok][:, None], rtol=1e-4, atol=1e-6)


def test_cosine_relative_variance_matches_monte_carlo_over_the_decoder(variant, fitted_files):
    """The table's quadrature of Var/mean^2 of f under cosine sampling vs the decoder at random cosine directions."""
    import torch

    from dynbtf.conventions import spherical_to_direction
    from dynbtf.render.mitsuba.sampling import SamplingTable, build_sampling_table, cosine_relative_variance
    from dynbtf.representations.model_file import load_model

    model, _ = load_model(fitted_files["leather"])
    plane = model.positional_plane().detach().float()
    features = plane.reshape(-1, plane.shape[-1])  # every texel: the table's average over all of them
    table = build_sampling_table(model, phi_bins=1, theta_bins=3, resolution=32, positions=len(features))
    node = SamplingTable(table.density[:, 1:2], table.phi_nodes, table.theta_nodes[1:2])  # theta 67.5 deg
    rng = np.random.default_rng(1)
    n = 4000
    u1, u2 = rng.random(n), rng.random(n)
    w_light = np.stack([np.sqrt(u1) * np.cos(2 * np.pi * u2), np.sqrt(u1) * np.sin(2 * np.pi * u2), np.sqrt(1 - u1)], -1)
    w_view = np.broadcast_to(spherical_to_direction(np.degrees(table.theta_nodes[1]), 0.0), w_light.shape)
    k = len(features)
    with torch.no_grad():
        rgb = model.decode(features.repeat(n, 1), torch.from_numpy(np.repeat(w_view, k, 0)).float(),
                           torch.from_numpy(np.repeat(w_light, k, 0)).float()).reshape(n, k, 3).double().mean(1)
    f = np.maximum(rgb.numpy() @ np.array([0.2126, 0.7152, 0.0722]), 0.0)
    monte_carlo = f.var() / f.mean() ** 2
    assert monte_carlo > 0.05  # a material with some lobe: the comparison means something
    assert cosine_relative_variance(node) == pytest.approx(monte_carlo, rel=0.15)


def test_auto_sampling_uses_the_table_for_glossy_and_cosine_for_rough(variant, fitted_files):
    """The default, sampling='auto': the glossy wood gets the table, the rough leather cosine sampling."""
    from dynbtf.render.mitsuba.sampling import AUTO_MIN_COSINE_VARIANCE

    wood = mi.load_dict({"type": "dynbtf", "filename": str(fitted_files["lacquered_wood"])})
    leather = mi.load_dict({"type": "dynbtf", "filename": str(fitted_files["leather"])})
    assert wood.sampling == "mixture" and wood.sampler.cosine_relative_variance > AUTO_MIN_COSINE_VARIANCE
    assert leather.sampling == "cosine" and leather.sampler is None
    forced = mi.load_dict({"type": "dynbtf", "filename": str(fitted_files["leather"]), "sampling": "mixture"})
    assert forced.sampling == "mixture" and forced.sampler.cosine_relative_variance < AUTO_MIN_COSINE_VARIANCE


def test_sampling_parameters_are_checked(variant, model_file):
    path, _ = model_file
    with pytest.raises(Exception, match=r"'sampling' must be one of \['auto', 'mixture', 'cosine'\], got 'ggx'"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "sampling": "ggx"})
    with pytest.raises(Exception, match=r"'sampling_weight' must be a probability in \(0, 1\]"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "sampling_weight": 1.5})


def test_damaged_sampling_table_falls_back_to_cosine_once(variant, model_file, tmp_path):
    """A table that cannot be sampled (here: NaN densities) -> cosine sampling, one warning per file."""
    import shutil
    import warnings

    from dynbtf.render.mitsuba import bsdf as mitsuba_bsdf
    from dynbtf.render.mitsuba.sampling import build_sampling_table

    path, model = model_file
    copy = shutil.copy(path, tmp_path / "damaged.dbtfm")

    def damaged(m):
        table = build_sampling_table(m, phi_bins=2, theta_bins=2, resolution=4, positions=2)
        table.density[0, 1, 2, 2] = np.nan
        return table

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert mitsuba_bsdf.plugin_sampler(copy, model, build=damaged) is None
        assert mitsuba_bsdf.plugin_sampler(copy, model, build=damaged) is None
    messages = [str(w.message) for w in caught]
    assert len(messages) == 1 and "non-finite" in messages[0] and "cosine" in messages[0], messages


def test_sampling_table_is_stored_in_the_compiled_material_and_read_back(variant, model_file, tmp_path, monkeypatch):
    """The first plugin load of a model builds its sampling table and writes it into the model's compiled material
    (cache); another load of the same model (here: a copy of the file, as a second process would see it) reads it
    from there without building, and samples the same densities."""
    import shutil

    from dynbtf.material import load_compiled
    from dynbtf.render.mitsuba import sampling

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path / "cache"))
    real, built = sampling.build_sampling_table, []

    def counting(model, **kwargs):
        built.append(model)
        return real(model, **kwargs)

    monkeypatch.setattr(sampling, "build_sampling_table", counting)
    path = shutil.copy(model_file[0], tmp_path / "first.dbtfm")  # a file this process has not sampled yet
    common = {"type": "dynbtf", "method": "hist", "sampling": "mixture", "filtered": False, "seed": 4}
    first = mi.load_dict({**common, "filename": str(path)})
    assert len(built) == 1 and first.sampling == "mixture"
    stored = [load_compiled(f) for f in (tmp_path / "cache").iterdir()]
    assert [sorted(m.sampling) for m in stored if m.sampling] == [["density", "phi_nodes", "theta_nodes"]]
    assert first.evaluator.btf.material.sampling is not None
    second = mi.load_dict({**common, "filename": str(shutil.copy(path, tmp_path / "copy.dbtfm"))})
    assert len(built) == 1 and second.sampling == "mixture"
    assert np.array_equal(np.array(first.sampler.cells), np.array(second.sampler.cells))
    mi.load_dict({**common, "filename": str(path), "sampling": "cosine"})
    assert len(built) == 1


# ---------------------------------------------------------------- footprints (filtered queries)
def _footprint_reference(model, method, seed, uv, wv, wl, footprint):
    from dynbtf.synthesized import synthesized_btf

    btf = synthesized_btf(model, method, scale=1.0, seed=seed, footprints=True)
    return np.asarray(btf.eval(uv.astype(np.float64), wv, wl, footprint=footprint), dtype=np.float64)


@pytest.mark.parametrize("method", ["tile", "hist", "hex"])
def test_plugin_footprint_from_uv_partials_matches_synthesized_btf(variant, model_file, method):
    """With ``si.duv_dx/dy`` set (an integer that traces ray differentials), the plugin answers
    ``SynthesizedBTF.eval(footprint=footprint_width(duv_dx, duv_dy))`` -- pyramid levels and per-level decoders."""
    path, model = model_file
    _assert_footprints_match(path, model, method)


def _random_uv_partials(n, scale, seed=12):
    """Random mesh-uv partials ``duv_dx, duv_dy (n, 2)`` float32 whose footprints (the third return, exemplar repeats:
    :func:`dynbtf.infinite_btf.footprint_width` of them times ``scale``) run from 1/400 of a repeat (inside a texel:
    the point query) to several repeats (the mean)."""
    from dynbtf.infinite_btf import footprint_width

    rng = np.random.default_rng(seed)
    duv_dx, duv_dy = ((rng.normal(size=(n, 2)) * np.exp(rng.uniform(-6.0, 1.0, (n, 1))) / scale).astype(np.float32)
                      for _ in range(2))
    footprint = footprint_width(duv_dx.astype(np.float64) * np.float32(scale), duv_dy.astype(np.float64) * np.float32(scale))
    return duv_dx, duv_dy, footprint


def _assert_footprints_match(path, model, method, *, n=3000):
    """The plugin with uv partials = ``SynthesizedBTF.eval`` with their footprint, at ``n`` random queries."""
    scale, seed = 7.0, 3
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": method, "scale": scale, "seed": seed})
    uv, wv, wl = _random_queries(n, seed=11)
    uv = (uv / np.float32(scale)) * np.float32(scale)
    duv_dx, duv_dy, footprint = _random_uv_partials(n, scale)
    got = _plugin_eval(bsdf, uv, wv, wl, scale, duv_dx=duv_dx, duv_dy=duv_dy)
    ref = _footprint_reference(model, method, seed, uv, wv, wl, footprint) / np.pi * wl[:, 2:3]
    point = _reference(model, method, seed, uv, wv, wl) / np.pi * wl[:, 2:3]
    assert np.abs(point - ref).max() > 0.1 * np.abs(ref).max()  # the footprint changes the answer
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-4 * max(1.0, np.abs(ref).max()))


def test_plugin_footprint_from_ray_cone(variant, model_file):
    """Without uv partials, ``ray_cone_angle`` gives the footprint ``t angle / cos(theta_view)`` in uv through
    ``|dp/du|`` and ``|dp/dv|`` (the longer side) -- checked against eval with that closed form."""
    path, model = model_file
    scale, seed, n, angle = 5.0, 2, 2000, 0.004
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "hist", "scale": scale, "seed": seed,
                         "ray_cone_angle": angle})
    uv, wv, wl = _random_queries(n, seed=21)
    uv = (uv / np.float32(scale)) * np.float32(scale)
    t = np.random.default_rng(22).uniform(1.0, 400.0, n).astype(np.float32)
    dp_du, dp_dv = (2.0, 0.0, 0.0), (0.0, 0.5, 0.0)  # uv per world unit: 1/2 along u, 2 along v
    got = _plugin_eval(bsdf, uv, wv, wl, scale, t=t, dp_du=dp_du, dp_dv=dp_dv)
    side = t.astype(np.float64) * angle / np.abs(wv[:, 2].astype(np.float64))
    footprint = side * max(scale / 2.0, scale / 0.5)
    ref = _footprint_reference(model, "hist", seed, uv, wv, wl, footprint) / np.pi * wl[:, 2:3]
    point = _reference(model, "hist", seed, uv, wv, wl) / np.pi * wl[:, 2:3]
    assert np.abs(point - ref).max() > 0.1 * np.abs(ref).max()
    # a lane whose footprint straddles a level boundary (float32 vs float64 of the same closed form) may pick
    # the other level's decoder: all but a handful of lanes agree to float rounding
    close = np.abs(got - ref).max(1) <= 2e-4 * max(1.0, np.abs(ref).max())
    assert close.mean() > 0.995, close.mean()


def test_plugin_without_a_footprint_is_the_point_query_bit_for_bit(variant, model_file):
    """No partials and no ray cone: exactly the unfiltered plugin's values (``filtered: false``)."""
    path, _ = model_file
    uv, wv, wl = _random_queries(1000, seed=31)
    common = {"type": "dynbtf", "filename": str(path), "method": "hist", "scale": 4.0}
    on = _plugin_eval(mi.load_dict({**common}), uv, wv, wl, 4.0)
    off = _plugin_eval(mi.load_dict({**common, "filtered": False}), uv, wv, wl, 4.0)
    assert np.array_equal(on, off)
    # a ray cone, but the hit at distance 0 (a footprint of 0 texels): the point query to float rounding
    cone = _plugin_eval(mi.load_dict({**common, "ray_cone_angle": 0.01}), uv, wv, wl, 4.0, t=np.zeros(len(uv)))
    np.testing.assert_allclose(cone, off, rtol=0, atol=1e-5 * np.abs(off).max())


def test_parameter_table_is_the_documented_one():
    """The plugin's parameters come from one table (bsdf.PARAMETERS): the table in docs/rendering.md is generated
    from it (regenerate: ``python -c "from dynbtf.render.mitsuba.bsdf import parameter_table_markdown as t;
    print(t())"``), and PLUGIN_DOC lists every parameter with its default."""
    from pathlib import Path

    from dynbtf.render.mitsuba.bsdf import PARAMETERS, PLUGIN_DOC, parameter_table_markdown

    lines = (Path(__file__).parents[1] / "docs" / "rendering.md").read_text(encoding="utf-8").splitlines()
    start = lines.index("| Parameter | Type | Description | Default |")
    end = next((k for k in range(start, len(lines)) if not lines[k].startswith("|")), len(lines))
    assert "\n".join(lines[start:end]) + "\n" == parameter_table_markdown()
    for parameter in PARAMETERS:
        assert f"   * - ``{parameter.name}``\n     - {parameter.type}\n" in PLUGIN_DOC
    assert [p.name for p in PARAMETERS] == ["filename", "method", "scale", "scale_v", "seed", "sampling",
                                            "sampling_weight", "cells", "brightness", "tint", "rotation",
                                            "scale_jitter", "target", "classes",
                                            "target_size",
                                            "target_wrap",
                                            "softness", "filtered", "ray_cone_angle"]


def test_parameter_errors_name_the_parameter(variant, model_file, tmp_path):
    """Every checked parameter's error: ``dynbtf BSDF: parameter 'name' ...``, before the model file is read."""
    path, _ = model_file
    from dynbtf.render.mitsuba.bsdf import METHODS

    assert {"hex", "hist", "linear", "quilt", "struct", "tile", "auto"} <= set(METHODS)
    cases = [({"method": "voronoi"}, f"parameter 'method' must be one of {list(METHODS)}, got 'voronoi'"),
             ({"scale": 0.0}, "parameter 'scale': expected a positive, finite number of exemplar repeats, got 0.0"),
             ({"scale_v": -1.0}, "parameter 'scale_v': expected a positive, finite number"),
             ({"scale": 3e7}, "parameter 'scale': 3e+07 exemplar repeats across the uv range exceed the 16777216 "
                              "(2**24) that Mitsuba's float32 uv resolves"),
             ({"sampling_weight": 0.0}, "parameter 'sampling_weight' must be a probability in (0, 1], got 0.0"),
             ({"ray_cone_angle": float("inf")}, "parameter 'ray_cone_angle' must be a non-negative angle in radians"),
             ({"brightness": 1.5}, "parameter 'brightness' must be the standard deviation of a log gain in [0, 1]"),
             ({"tint": -0.1}, "parameter 'tint' must be the standard deviation of a log gain in [0, 1]"),
             ({"filename": None}, "parameter 'filename' (a dynbtf model file) is required")]
    for extra, message in cases:
        props = {"type": "dynbtf", "filename": str(tmp_path / "never-read.dbtfm"), **extra}
        if props["filename"] is None:
            del props["filename"]
        with pytest.raises(Exception) as info:
            mi.load_dict(props)
        assert "dynbtf BSDF: " + message in str(info.value), (extra, str(info.value))


def test_register_plugin_checks_llvm_before_the_variant(variant, monkeypatch):
    """register_plugin asks jit.llvm.check_llvm about the variant it will set, before checking it."""
    from dynbtf.errors import MissingDependencyError
    from dynbtf.jit import llvm
    from dynbtf.render.mitsuba.bsdf import register_plugin

    asked = []

    def refuse(wanted):
        asked.append(wanted)
        raise MissingDependencyError(f"Mitsuba variant {wanted}: LLVM too old (test)")

    monkeypatch.setattr(llvm, "check_llvm", refuse)
    with pytest.raises(MissingDependencyError, match="LLVM too old"):
        register_plugin("llvm_ad_rgb")
    with pytest.raises(MissingDependencyError):
        register_plugin()  # the active variant
    assert asked == ["llvm_ad_rgb", mi.variant()]


def test_ray_cone_angle_of_a_camera():
    from dynbtf.errors import InputError
    from dynbtf.render.mitsuba.bsdf import ray_cone_angle

    # 90 degrees over 512 px: the image plane at distance 1 is 2 wide, a pixel 2 / 512; 4 spp: half of it
    assert ray_cone_angle(90.0, 512, 4) == pytest.approx(2.0 / 512 / 2.0, rel=1e-12)
    with pytest.raises(InputError, match="fov"):
        ray_cone_angle(200.0, 512)
    with pytest.raises(InputError, match="spp"):
        ray_cone_angle(45.0, 512, 0)


def test_rendered_distant_plane_filters_with_the_scene_camera_cone(variant, model_file):
    """A grazing plane (``scene_dict``'s plane, which sets ``ray_cone_angle`` from its camera) at 1 spp is
    closer to a 64-spp render with footprints than without: the footprints reach the plugin in a real render."""
    from dynbtf.render.mitsuba.scenes import bsdf_dict, scene_dict

    path, _ = model_file
    res = (24, 32)

    def render(filtered, spp, seed):
        material = {**bsdf_dict(path, method="hist", scale=40.0), "filtered": filtered}
        d = scene_dict("plane", material, lighting="point", resolution=res, spp=spp, max_depth=2)
        del d["ambient"]  # the point light alone: no light-sampling noise, only the texture's
        return np.array(mi.render(mi.load_dict(d), spp=spp, seed=seed), dtype=np.float64)

    reference = render(False, 64, 100)
    errors = {f: np.mean([((render(f, 1, s) - reference) ** 2).mean() for s in range(3)]) for f in (False, True)}
    assert errors[True] < 0.5 * errors[False], errors


def test_table_density_of_an_isotropic_model_does_not_depend_on_the_view_azimuth(variant, fitted_files):
    """The tables are in the view's azimuthal frame: for a model without azimuthal dependence (its ``f_H``
    constant along ``phi_h``) rotating view and light together about the normal leaves ``pdf`` unchanged --
    also at a grazing view between two azimuth nodes, where blending tables of absolute half vectors
    (the nodes' lobes 45 degrees apart) would lose the lobe."""
    import torch

    from dynbtf.render.mitsuba.sampling import DrTableSampler, build_sampling_table
    from dynbtf.representations.model_file import load_model

    model, _ = load_model(fitted_files["lacquered_wood"])
    with torch.no_grad():
        model.f_h.copy_(model.f_h.mean(dim=1, keepdim=True).expand_as(model.f_h))
    sampler = DrTableSampler(build_sampling_table(model))
    n = 20_000
    rng = np.random.default_rng(5)

    def rotated(w, phi):
        c, s = np.cos(phi), np.sin(phi)
        return np.stack([c * w[:, 0] - s * w[:, 1], s * w[:, 0] + c * w[:, 1], w[:, 2]], -1)

    def vec(w):
        return mi.Vector3f(*(mi.Float(w[:, k].astype(np.float32)) for k in range(3)))

    for theta in (40.0, 80.0):
        wv = np.tile([np.sin(np.radians(theta)), 0.0, np.cos(np.radians(theta))], (n, 1))
        wo = sampler.sample(vec(wv), mi.Float(rng.random(n)), mi.Point2f(mi.Float(rng.random(n)), mi.Float(rng.random(n))))
        wl = np.stack([np.array(wo.x), np.array(wo.y), np.array(wo.z)], -1).astype(np.float64)
        wl = wl[wl[:, 2] > 0.02]
        ref = np.array(sampler.pdf(vec(wv[:len(wl)]), vec(wl)))
        assert (ref > 0).all()
        for phi in (np.radians(22.5), np.radians(100.0)):  # between nodes, and another sector
            got = np.array(sampler.pdf(vec(rotated(wv[:len(wl)], phi)), vec(rotated(wl, phi))))
            # a direction on the edge of a table cell can land across it once rotated and rounded to float32 (seen:
            # 1 of 19,838); losing the lobe between nodes would change most of them
            apart = ~np.isclose(got, ref, rtol=2e-3, atol=0.0)
            assert apart.mean() <= 1e-3, (f"view at {theta} deg, rotated by {np.degrees(phi):g} deg: "
                                          f"{apart.sum()} of {len(ref)} densities differ, e.g. {got[apart][:5]} vs "
                                          f"{ref[apart][:5]}")


# ---------------------------------------------------------------- struct (cell quilting) and auto
@pytest.fixture(scope="module")
def structured_file(tmp_path_factory):
    """A small random Triple Plane whose positional plane is a weave: an 8 x 8 element repeated 4 x 4 plus a
    little noise (32 x 32 texels: two cells per repeat and a lattice of offsets to choose from), saved to disk."""
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(32, 32, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    generator = torch.Generator().manual_seed(6)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
        element = model.f_u[:8, :8].clone()
        noise = torch.randn(32, 32, 6, generator=generator)
        model.f_u.copy_(element.repeat(4, 4, 1) + 0.1 * float(element.std()) * noise)
    path = tmp_path_factory.mktemp("structured") / "weave.dbtfm"
    save_model(path, model)
    return path, model


def test_plugin_struct_matches_synthesized_btf(variant, structured_file):
    """struct in the plugin = ``synthesized_btf(model, "struct").eval`` to float rounding: near the origin through
    the BSDF, and 2**45 repeats away through its evaluator (float64 uv, which mesh uv cannot carry)."""
    from dynbtf.render.mitsuba.bsdf import DynBTFEvaluator
    from dynbtf.synthesized import synthesized_btf

    path, model = structured_file
    btf = synthesized_btf(model, "struct", scale=1.0, seed=3)
    assert btf.synthesizer.prepared.count > 4  # cells choose among several lattice offsets
    _assert_plugin_matches(path, model, "struct", n=3000)
    evaluator = DynBTFEvaluator(synthesized_btf(model, "struct", seed=3))
    assert evaluator.method == "struct" and evaluator.choice is None
    rng = np.random.default_rng(7)
    uv = 2.0 ** 45 + rng.random((2000, 2)) * 4.0
    uv[1000:] *= -1.0
    _, wv, wl = _random_queries(2000, seed=8)
    got = evaluator.eval(mi.Float64(uv[:, 0]), mi.Float64(uv[:, 1]), *(mi.Vector3f(*(mi.Float(w[:, k]) for k in range(3)))
                                                                      for w in (wv, wl)))
    got = np.stack([np.array(got[k], dtype=np.float64) for k in range(3)], -1)
    ref = np.asarray(btf.eval(torch.from_numpy(uv), torch.from_numpy(wv), torch.from_numpy(wl)), dtype=np.float64)
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-4 * max(1.0, np.abs(ref).max()))


def _assert_plugin_parameters_match(path, model, method, parameters):
    """The plugin with method ``parameters`` (variation controls) = ``synthesized_btf(model, method, **parameters)
    .eval`` to float rounding, and not the plain method's values (3000 random queries, scale 7, seed 3)."""
    from dynbtf.synthesized import synthesized_btf

    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": method, "scale": 7.0, "seed": 3,
                         **parameters})
    uv, wv, wl = _random_queries(3000, seed=4)
    uv = (uv / np.float32(7.0)) * np.float32(7.0)
    got = _plugin_eval(bsdf, uv, wv, wl, 7.0)
    btf = synthesized_btf(model, method, scale=1.0, seed=3, **parameters)
    ref = np.asarray(btf.eval(torch.from_numpy(uv.astype(np.float64)), torch.from_numpy(wv), torch.from_numpy(wl)),
                     dtype=np.float64) / np.pi * wl[:, 2:3]
    plain = _reference(model, method, 3, uv, wv, wl) / np.pi * wl[:, 2:3]
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-4 * max(1.0, np.abs(ref).max()))
    assert np.abs(ref - plain).max() > 0.05 * np.abs(plain).max()


def test_plugin_struct_variation_matches_synthesized_btf(variant, structured_file):
    """struct with per-element brightness and tint in the plugin = the library's, and not the plain struct's; hist
    refuses them."""
    path, model = structured_file
    _assert_plugin_parameters_match(path, model, "struct", {"brightness": 0.3, "tint": 0.2})
    with pytest.raises(Exception, match="per-element variation is for struct"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "hist", "brightness": 0.3})


def test_plugin_sample_rotation_matches_synthesized_btf(variant, model_file):
    """hist with quarter-turned samples in the plugin = the library's, and not the plain hist's; tile refuses the
    parameter."""
    path, model = model_file
    _assert_plugin_parameters_match(path, model, "hist", {"rotation": True})
    with pytest.raises(Exception, match="turning the samples is for hex, hist, linear"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "tile", "rotation": True})


def test_plugin_sample_scales_match_synthesized_btf(variant, model_file):
    """hex with scaled (and turned) samples in the plugin = the library's; struct refuses the parameter, and a
    value out of [0, 1] is refused by name."""
    path, model = model_file
    _assert_plugin_parameters_match(path, model, "hex", {"scale_jitter": 0.4, "rotation": True})
    with pytest.raises(Exception, match="scaling the samples is for hex, hist, linear"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "struct", "scale_jitter": 0.4})
    with pytest.raises(Exception, match=r"scale_jitter.*a scale jitter in \[0, 1\]"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "hist", "scale_jitter": 2.0})


def test_plugin_warns_when_scales_read_a_model_without_the_subtexel_term(variant, tmp_path):
    """``scale_jitter`` on a model file whose training record has no sub-texel term: the plugin warns, naming the
    file (scaled samples read between texel centres, where such a model's colours drift)."""
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    path = tmp_path / "old.dbtfm"
    save_model(path, TriplePlane(16, 16, seed=1), {"training": {"subtexel": 0.0}})
    with pytest.warns(UserWarning, match=r"old\.dbtfm was fitted without the sub-texel term"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "hist", "scale_jitter": 0.2})


def test_plugin_struct_footprints_match_synthesized_btf(variant, structured_file):
    """struct's footprint queries (the exemplar's pyramid at the point query's read position, per-level decoders)
    in the plugin = ``SynthesizedBTF.eval`` with the same footprints."""
    path, model = structured_file
    _assert_footprints_match(path, model, "struct", n=2000)


def test_plugin_auto_chooses_struct_for_a_structured_exemplar_and_says_so_once(variant, structured_file, model_file,
                                                                             capsys):
    """The default method, auto: struct on the weave (the same kernel, bit for bit, as method struct), hist on
    the random plane; the choice line is printed once per model file."""
    path, model = structured_file
    common = {"type": "dynbtf", "filename": str(path), "scale": 7.0, "seed": 3}
    capsys.readouterr()
    chosen = mi.load_dict(common)
    again = mi.load_dict({**common, "method": "auto"})
    err = capsys.readouterr().err
    assert chosen.method == again.method == "auto" and chosen.synthesis == again.synthesis == "struct"
    assert "auto -> struct" in chosen.to_string()
    lines = [line for line in err.splitlines() if "method auto ->" in line]
    assert len(lines) == 1 and str(path) in lines[0] and "method auto -> struct: structured exemplar" in lines[0], err
    uv, wv, wl = _random_queries(1000, seed=9)
    explicit = mi.load_dict({**common, "method": "struct"})
    assert np.array_equal(_plugin_eval(chosen, uv, wv, wl, 7.0), _plugin_eval(explicit, uv, wv, wl, 7.0))
    stochastic = mi.load_dict({"type": "dynbtf", "filename": str(model_file[0]), "filtered": False})
    assert stochastic.synthesis == "hist"
    assert "method auto -> hist: stochastic exemplar" in capsys.readouterr().err


def test_render_auto_resolves_the_method_and_echoes_the_choice(variant, structured_file, tmp_path, monkeypatch,
                                                               capsys):
    """render_scene's and ``dynbtf render``'s default, auto: resolved before Mitsuba loads the scene (the plugin
    gets struct and prints nothing), the choice line echoed (the command: on standard output)."""
    from dynbtf.cli.main import main
    from dynbtf.errors import InputError
    from dynbtf.render.mitsuba.scene_render import render_scene

    path, model = structured_file
    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", str(tmp_path / "cache"))  # nothing compiled yet
    loaded = []

    def stop(scene):  # the scene dict reaches Mitsuba: record it, render nothing
        loaded.append(scene)
        raise InputError("stopped before the render")

    monkeypatch.setattr(mi, "load_dict", stop)
    echoed = []
    with pytest.raises(InputError, match="stopped"):
        render_scene(path, scene="plane", lighting="point", resolution=(8, 8), spp=1, progress=False,
                     echo=echoed.append)
    assert loaded[0]["surface"]["bsdf"]["method"] == "struct"
    assert len(echoed) == 1 and echoed[0].startswith("method auto -> struct: structured exemplar")
    # resolved through the compiled material, which the plugin (given struct) then finds in the cache
    from dynbtf.material import open_or_compile

    found, how = open_or_compile(model, "struct", 0, footprints=False, progress=False)
    assert how == "cached" and found.method == "struct" and found.choice is None
    assert echoed[0] == open_or_compile(model, "auto", 0, footprints=False, progress=False)[0].choice["line"]
    capsys.readouterr()
    assert main(["render", str(path), "-o", str(tmp_path / "x.png"), "--size", "8", "--spp", "1"]) == 2
    captured = capsys.readouterr()
    assert echoed[0] in captured.out and "stopped before the render" in captured.err
    assert loaded[1]["surface"]["bsdf"]["method"] == "struct" and "dynbtf BSDF" not in captured.err


@pytest.fixture(scope="module")
def tinted_bricks_file(tmp_path_factory):
    """A 32 x 32 Triple Plane of 8 x 8 elements of one shape, each dark or bright (random): struct's cells of one
    element show either class depending on their offset, which guided struct chooses."""
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(32, 32, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    generator = torch.Generator().manual_seed(6)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
        element = model.f_u[:8, :8].clone()
        tint = np.kron(np.random.default_rng(2).choice([-1.0, 1.0], (4, 4)), np.ones((8, 8)))
        spread = float(element.std())
        model.f_u.copy_(element.repeat(4, 4, 1) + 0.6 * spread * torch.from_numpy(tint).float()[..., None]
                        + 0.05 * spread * torch.randn(32, 32, 6, generator=generator))
    path = tmp_path_factory.mktemp("bricks") / "bricks.dbtfm"
    save_model(path, model)
    return path, model


@pytest.mark.parametrize("method", ["hist", "hex", "struct"])
def test_plugin_guided_by_a_target_is_guided_btf(variant, model_file, tinted_bricks_file, tmp_path, method):
    """``target``: the plugin evaluates what dynbtf.guided_btf's SynthesizedBTF does (the candidate search in
    Dr.Jit), with the target laid over ``target_size`` mesh uv units; a footprint query or struct is refused."""
    from dynbtf.errors import InputError
    from dynbtf.guided import guided_btf
    from dynbtf.io import load_image, save_image
    from dynbtf.layered import mask_from_spec

    # struct: tinted bricks (a lattice of offsets to choose from), one cell per 8 x 8 element
    path, model = tinted_bricks_file if method == "struct" else model_file
    grey = np.repeat(np.repeat(np.array([[0.0, 1.0], [1.0, 0.0]], dtype=np.float32), 4, 0), 4, 1)
    target = tmp_path / "target.png"
    save_image(target, np.repeat(grey[..., None], 3, -1))
    scale, size = 7.0, 0.5
    cells = {"cells": 4} if method == "struct" else {}
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": method, "scale": scale, "seed": 3,
                         "target": str(target), "target_size": size, "softness": 0.2, "filtered": False, **cells})
    uv, wv, wl = _random_queries(3000, seed=2)
    uv = (uv / np.float32(scale)) * np.float32(scale)
    got = _plugin_eval(bsdf, uv, wv, wl, scale)
    image = mask_from_spec(str(target)).image
    btf = guided_btf(model, image, classes=2, target_size=size * scale, seed=3, softness=0.2, method=method, **cells)
    expected = np.asarray(btf.eval(torch.from_numpy(uv.astype(np.float64)), torch.from_numpy(wv),
                                   torch.from_numpy(wl)), dtype=np.float64) / np.pi * wl[:, 2:3]
    from dynbtf.synthesized import synthesized_btf

    plain = np.asarray(synthesized_btf(model, method, scale=1.0, seed=3, **cells).eval(uv.astype(np.float64), wv, wl),
                       dtype=np.float64) / np.pi * wl[:, 2:3]
    assert np.mean(np.abs(expected - plain).max(1) > 1e-3) > 0.2  # guidance changes many points
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-4 * max(1.0, np.abs(expected).max()))
    assert load_image(target).shape[:2] == (8, 8)
    for extra, message in (({"method": "struct"}, "guided struct chooses whole cells by class"), ({"method": "tile"}, "steers hist, hex or struct"),
                           ({"classes": 1}, "'classes' must be at least 2"), ({"softness": 2.0}, "'softness'")):
        spec = {"type": "dynbtf", "filename": str(path), "method": method, "target": str(target), "filtered": False,
                **extra}
        with pytest.raises((InputError, RuntimeError), match=message):
            mi.load_dict(spec)


def test_plugin_guided_footprints_are_the_librarys(variant, model_file, tmp_path):
    """``target`` with footprint queries (``filtered``, uv partials): the plugin answers what its guided
    SynthesizedBTF answers with that footprint (the pyramid read at the guided samples, per-level decoders)."""
    from dynbtf.io import save_image

    path, model = model_file
    grey = np.repeat(np.repeat(np.array([[0.0, 1.0], [1.0, 0.0]], dtype=np.float32), 4, 0), 4, 1)
    target = tmp_path / "target.png"
    save_image(target, np.repeat(grey[..., None], 3, -1))
    scale, n = 7.0, 2000
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "hist", "scale": scale, "seed": 3,
                         "target": str(target), "target_size": 0.5})
    uv, wv, wl = _random_queries(n, seed=11)
    uv = (uv / np.float32(scale)) * np.float32(scale)
    duv_dx, duv_dy, footprint = _random_uv_partials(n, scale)
    got = _plugin_eval(bsdf, uv, wv, wl, scale, duv_dx=duv_dx, duv_dy=duv_dy)
    btf = bsdf.evaluator.btf  # the guided SynthesizedBTF the plugin translated (its per-level decoders fitted once)
    assert btf.synthesizer.name == "guided"
    ref = np.asarray(btf.eval(uv.astype(np.float64), wv, wl, footprint=footprint), dtype=np.float64)
    ref = ref / np.pi * wl[:, 2:3]
    point = np.asarray(btf.eval(uv.astype(np.float64), wv, wl), dtype=np.float64) / np.pi * wl[:, 2:3]
    assert np.abs(point - ref).max() > 0.1 * np.abs(ref).max()  # the footprint changes the answer
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-4 * max(1.0, np.abs(ref).max()))
