"""The ``dynbtf`` Mitsuba plugin: same numbers as dynbtf's own evaluation, correct sampling, small renders."""

from __future__ import annotations

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

pytestmark = pytest.mark.mitsuba

VARIANT = "llvm_ad_rgb"


@pytest.fixture(scope="module")
def variant():
    if VARIANT not in mi.variants():
        pytest.skip(f"Mitsuba variant {VARIANT} not built")
    from dynbtf.render.mitsuba_bsdf import register_plugin

    try:
        register_plugin(VARIANT)
    except ImportError as e:  # pragma: no cover - no LLVM on this machine
        pytest.skip(f"{VARIANT} unusable: {e}")
    return VARIANT


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


def _plugin_eval(bsdf, uv, wv, wl, scale):
    n = len(uv)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.uv = mi.Point2f(mi.Float(uv[:, 0] / scale), mi.Float(uv[:, 1] / scale))
    si.wi = mi.Vector3f(*(mi.Float(wv[:, k]) for k in range(3)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    wo = mi.Vector3f(*(mi.Float(wl[:, k]) for k in range(3)))
    out = bsdf.eval(mi.BSDFContext(), si, wo)
    return np.array(out, dtype=np.float64).reshape(n, 3) if np.array(out).shape == (n, 3) else np.array(out).T


def _reference(model, method, seed, uv, wv, wl):
    """dynbtf's own evaluation: SynthesizedBTF.eval (plain model for tiling when synthesis is absent)."""
    from dynbtf.synthesized import SynthesizedBTF

    btf = SynthesizedBTF(model, method, scale=1.0, seed=seed)
    out = btf.eval(torch.from_numpy(uv.astype(np.float64)), torch.from_numpy(wv), torch.from_numpy(wl))
    return np.asarray(out.detach().cpu().numpy() if hasattr(out, "detach") else out, dtype=np.float64)


@pytest.mark.parametrize("method", ["tile", "hist", "hex"])
def test_plugin_eval_matches_synthesized_btf(variant, model_file, method):
    path, model = model_file
    scale = 7.0
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": method, "scale": scale, "seed": 3})
    uv, wv, wl = _random_queries(4000, seed=1)
    # feed the plugin mesh uv = uv / scale; what it evaluates is scale * (uv / scale) in float32
    uv = (uv / np.float32(scale)) * np.float32(scale)
    got = _plugin_eval(bsdf, uv, wv, wl, scale)
    ref = _reference(model, method, 3, uv, wv, wl) / np.pi * wl[:, 2:3]
    # float32 kernels on both sides; differences come from summation order and transcendental ulps
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-4 * max(1.0, np.abs(ref).max()))
    assert np.abs(ref).max() > 0.05  # the comparison is not between zeros


def test_plugin_is_zero_below_either_horizon(variant, model_file):
    path, _ = model_file
    bsdf = mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "tile"})
    uv, wv, wl = _random_queries(64, seed=2)
    below = wl * np.array([1, 1, -1], dtype=np.float32)
    assert np.all(_plugin_eval(bsdf, uv, wv, below, 1.0) == 0.0)
    assert np.all(_plugin_eval(bsdf, uv, below, wl, 1.0) == 0.0)


def test_plugin_sampling_passes_chi2_and_weight_is_value(variant, model_file):
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    path, model = model_file
    spec = {"type": "dynbtf", "filename": str(path), "method": "tile"}
    wi = dr.normalize(mi.ScalarVector3f(0.3, -0.2, 0.9))
    sample_func, pdf_func = BSDFAdapter("dynbtf", spec, wi=wi)
    test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=200_000, res=16, ires=16)
    assert test.run(), test.messages

    # the pdf integrates to one over the sphere (midpoint rule in (cos theta, phi))
    n = 256
    c = (np.arange(n) + 0.5) / n * 2 - 1
    p = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    cc, pp = np.meshgrid(c, p, indexing="ij")
    s = np.sqrt(1 - cc ** 2)
    wo = mi.Vector3f(mi.Float((s * np.cos(pp)).ravel()), mi.Float((s * np.sin(pp)).ravel()), mi.Float(cc.ravel()))
    si = dr.zeros(mi.SurfaceInteraction3f, n * 2 * n)
    si.wi = wi
    bsdf = mi.load_dict(spec)
    pdf = np.array(bsdf.pdf(mi.BSDFContext(), si, wo))
    integral = pdf.sum() * (2.0 / n) * (2 * np.pi / (2 * n))
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
        mi.load_dict({"type": "dynbtf", "filename": str(path), "method": "quilt"})
    with pytest.raises(Exception, match="scale"):
        mi.load_dict({"type": "dynbtf", "filename": str(path), "scale": -2.0})
    with pytest.raises(Exception, match="not found"):
        mi.load_dict({"type": "dynbtf", "filename": str(tmp_path / "missing.dbtfm")})


def test_small_render_of_a_plane_matches_direct_lighting_by_hand(variant, model_file):
    """A 24x24 render of a plane under a point light, direct lighting only, against the closed form
    ``L = value / pi * cos(theta_l) * I / r^2`` evaluated with dynbtf at each pixel's hit point."""
    path, model = model_file
    from dynbtf.render.scenes import bsdf_dict

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

    # reference: supersample the same pixels (64 stratified points each) with dynbtf's evaluation
    k = 8
    sub = (np.arange(k) + 0.5) / k
    px = (np.arange(res)[:, None] + sub[None, :]).ravel() / res  # film x in [0, 1)
    xx, yy = np.meshgrid(px, px)  # yy: film rows (top = +y)
    world_x = 1.0 - 2.0 * xx   # orthographic camera looking down -z with up +y: image x runs along -x
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
    # try both uv orientations Mitsuba's rectangle may use; the right one matches closely
    err = min(np.abs(img - ref).mean(), np.abs(img - ref[:, ::-1]).mean(), np.abs(img - ref[::-1]).mean(),
              np.abs(img - ref[::-1, ::-1]).mean())
    assert err < 0.03 * ref.mean(), err


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
