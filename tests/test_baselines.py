"""The comparison baselines (NeuMIP, PCA, SH) against independent computations.

References: numpy's dense SVD (PCA), scipy's complex spherical harmonics
``scipy.special.sph_harm_y`` and Gauss-Legendre quadrature (SH), direct
evaluation of the analytic test BTF (NeuMIP training).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dynbtf.conventions import spherical_to_direction, texel_centers_uv
from dynbtf.data.array import ArrayBTF
from dynbtf.errors import InputError
from dynbtf.representations import get_representation_class
from dynbtf.representations.measured_directions import nearest_direction_weights
from dynbtf.representations.neumip import NeuMIP
from dynbtf.representations.pca import PCA, fit_pca, streamed_randomized_svd
from dynbtf.representations.sh import SH_NORMALIZATION, SphericalHarmonics, fit_sh, real_sh_basis


def ring_directions(thetas, counts):
    """Directions in rings of constant theta (degrees), phi evenly spaced (like the UBO grids)."""
    th = np.concatenate([np.full(n, t, dtype=np.float64) for t, n in zip(thetas, counts)])
    ph = np.concatenate([np.arange(n) * 360.0 / n for n in counts])
    return spherical_to_direction(th, ph)


def analytic_btf(height=8, width=10, seed=0):
    """A small BTF: albedo x Lambert + a Blinn-Phong lobe of per-texel strength + weaker separable terms.

    The weaker terms (texture_i x angular_i, weights 0.3 * 2^-i) give every channel's
    texel x pair matrix a decaying spectrum with clear gaps (a well-defined top subspace).
    """
    rng = np.random.default_rng(seed)
    views = ring_directions([0, 30, 60], [1, 4, 6])
    lights = ring_directions([0, 25, 50, 75], [1, 5, 8, 10])
    albedo = 0.2 + 0.6 * rng.random((height, width, 3))
    gloss = rng.random((height, width, 1))
    h = views[:, None, :] + lights[None, :, :]
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    lobe = h[..., 2] ** 20  # (V, L)
    values = albedo[None, None] + 2.0 * gloss[None, None] * lobe[:, :, None, None, None]
    for i in range(6):
        texture = rng.random((height, width, 3))
        angular = rng.random((len(views), len(lights), 1, 1, 3))
        values = values + 0.3 * 2.0 ** -i * texture[None, None] * angular
    return ArrayBTF(values, views, lights, name="analytic")


def btf_matrix(btf):
    """The dense texel x pair matrix per channel, ``(3, T, P)``, columns view-major."""
    cols = [btf.image(v, l).reshape(-1, 3) for v, l in btf.pairs()]
    return np.stack(cols, axis=-1).transpose(1, 0, 2).astype(np.float64)


def pair_directions(btf, pairs):
    pairs = np.asarray(pairs)
    return (torch.tensor(btf.views[pairs[:, 0]], dtype=torch.float32),
            torch.tensor(btf.lights[pairs[:, 1]], dtype=torch.float32))


pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture(scope="module")
def btf():
    return analytic_btf()


# ---------------------------------------------------------------------- measured directions
def test_nearest_direction_weights_exact_at_measured_and_convex():
    dirs = torch.tensor(ring_directions([0, 30, 60], [1, 6, 12]), dtype=torch.float32)
    idx, wt = nearest_direction_weights(dirs, dirs, k=3)
    assert torch.equal(idx[:, 0], torch.arange(len(dirs)))
    assert torch.equal(wt, torch.tensor([1.0, 0.0, 0.0]).expand_as(wt))
    q = torch.nn.functional.normalize(torch.randn(50, 3, generator=torch.Generator().manual_seed(1)).abs(), dim=-1)
    idx, wt = nearest_direction_weights(q, dirs, k=3)
    assert (wt >= 0).all() and torch.allclose(wt.sum(-1), torch.ones(50))
    brute = torch.argsort(torch.cdist(q, dirs), dim=-1)[:, :3]
    assert torch.equal(torch.sort(idx, -1).values, torch.sort(brute, -1).values)
    assert (wt[:, 0] >= wt[:, 1]).all() and (wt[:, 1] >= wt[:, 2]).all()


# ---------------------------------------------------------------------- PCA
@pytest.mark.parametrize("centered", [False, True])
def test_streamed_randomized_svd_matches_numpy_svd(btf, centered):
    a = btf_matrix(btf)
    if centered:
        a = a - a.mean(axis=1, keepdims=True)
    u_ref, s_ref, vt_ref = np.linalg.svd(a, full_matrices=False)
    u, s, vt, means = streamed_randomized_svd(btf, None, 4, centered=centered, block=7, progress=False)
    np.testing.assert_allclose(s, s_ref[:, :4], rtol=1e-6, atol=1e-9 * s_ref.max())
    for c in range(3):  # same right subspace: projections agree
        np.testing.assert_allclose(vt[c].T @ vt[c], vt_ref[c, :4].T @ vt_ref[c, :4], atol=1e-6)
        np.testing.assert_allclose(np.abs(u[c].T @ u_ref[c, :, :4]), np.eye(4), atol=1e-6)
    assert np.allclose(means, btf_matrix(btf).mean(axis=1).T) if centered else not means.any()
    # streaming every pass from the source (no in-memory cache) gives the same result
    streamed = streamed_randomized_svd(btf, None, 4, centered=centered, block=7, progress=False, cache_mb=0)
    for x, y in zip(streamed, (u, s, vt, means)):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("centered", [False, True])
def test_pca_reconstructs_the_rank_k_approximation(btf, centered):
    k = 3
    a = btf_matrix(btf)
    mean = a.mean(axis=1, keepdims=True) if centered else 0.0
    u, s, vt = np.linalg.svd(a - mean, full_matrices=False)
    rank_k = (u[:, :, :k] * s[:, None, :k]) @ vt[:, :k] + mean  # (3, T, P)
    model = fit_pca(btf, components=k, centered=centered, progress=False)
    pairs = np.array(list(btf.pairs()))
    pred = model.predict_texel_images(*pair_directions(btf, pairs))  # (P, T, 3)
    np.testing.assert_allclose(pred.numpy().transpose(2, 1, 0), rank_k, atol=2e-5)
    assert model.positional_plane().shape == (btf.height, btf.width, 3 * k)
    assert model.storage_bytes() >= 4 * (btf.height * btf.width * 3 * k + btf.n_pairs * 3 * (k + 1))


def test_pca_held_out_pairs_are_not_used_and_are_interpolated(btf):
    pairs = np.array(list(btf.pairs()))
    held = pairs[[5, 17, 40]]
    train = np.array([p for p in pairs if not (p == held).all(1).any()])
    changed = ArrayBTF(btf.values.copy(), btf.views, btf.lights)
    for v, l in held:  # garbage in held-out images must not influence the fit
        changed.values[v, l] = 100.0
    m1 = fit_pca(btf, pairs=train, components=3, progress=False)
    m2 = fit_pca(changed, pairs=train, components=3, progress=False)
    torch.testing.assert_close(m1.coefficients, m2.coefficients)
    # the held-out pairs' angular basis is a convex blend of fitted neighbours: finite, close to the truth
    pred = m1.predict_texel_images(*pair_directions(btf, held))
    truth = np.stack([btf.image(v, l).reshape(-1, 3) for v, l in held])
    assert torch.isfinite(pred).all()
    assert np.abs(pred.numpy() - truth).mean() < 0.5 * np.abs(truth).mean()


def test_pca_bad_arguments_raise_clear_errors(btf):
    with pytest.raises(InputError, match="rank 500 exceeds"):
        streamed_randomized_svd(btf, None, 500, progress=False)
    with pytest.raises(InputError, match="pairs: 1 pair"):
        fit_pca(btf, pairs=[[0, 0], [99, 0]], progress=False)
    with pytest.raises(InputError, match="components"):
        PCA(4, 4, 2, 2, components=0)


# ---------------------------------------------------------------------- SH
def scipy_real_sh(w, bands=3):
    """Real SH from scipy's complex ``sph_harm_y`` (Condon-Shortley phase): the independent reference."""
    from scipy.special import sph_harm_y

    theta = np.arccos(np.clip(w[..., 2], -1, 1))
    phi = np.arctan2(w[..., 1], w[..., 0])
    cols = []
    for l in range(bands):
        for m in range(-l, l + 1):
            y = sph_harm_y(l, abs(m), theta, phi)
            if m > 0:
                cols.append(np.sqrt(2) * (-1) ** m * y.real)
            elif m < 0:
                cols.append(np.sqrt(2) * (-1) ** m * y.imag)
            else:
                cols.append(y.real)
    return np.stack(cols, axis=-1)


def test_real_sh_basis_matches_scipy_and_closed_form_constants():
    rng = np.random.default_rng(2)
    w = rng.standard_normal((200, 3))
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    np.testing.assert_allclose(real_sh_basis(w), scipy_real_sh(w), atol=1e-12)
    torch.testing.assert_close(real_sh_basis(torch.tensor(w)), torch.tensor(scipy_real_sh(w)))
    # the textbook constants (e.g. Sloan, "Stupid SH tricks")
    expected = {"l0": 0.282095, "l1": 0.488603, "l2_xy": 1.092548, "l2_z2": 0.315392, "l2_x2y2": 0.546274}
    for key, value in expected.items():
        assert SH_NORMALIZATION[key] == pytest.approx(value, abs=1e-6)


def test_real_sh_basis_is_orthonormal_by_quadrature():
    z, wz = np.polynomial.legendre.leggauss(8)  # exact for the degree-4 products in z
    phi = np.arange(16) * (2 * np.pi / 16)  # exact for trigonometric degree < 16
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - zz ** 2)
    w = np.stack([r * np.cos(pp), r * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    weight = (wz[:, None] * np.full(len(phi), 2 * np.pi / len(phi))[None]).reshape(-1)
    y = real_sh_basis(w)
    np.testing.assert_allclose(y.T @ (y * weight[:, None]), np.eye(9), atol=1e-12)


def test_sh_fit_recovers_an_exact_sh_function():
    rng = np.random.default_rng(3)
    views = ring_directions([0, 40], [1, 3])
    lights = ring_directions([0, 20, 40, 60, 75], [1, 4, 6, 8, 8])
    truth = rng.standard_normal((3, 4, len(views), 3, 9))
    values = np.einsum("hwvcj,lj->vlhwc", truth, real_sh_basis(lights))
    btf = ArrayBTF(values, views, lights)
    model = fit_sh(btf, progress=False)
    np.testing.assert_allclose(model.coefficients.numpy().reshape(truth.shape), truth, atol=2e-5)
    # any light direction (not only the measured ones) at a measured view
    wl = torch.tensor(spherical_to_direction(np.array([33.0, 80.0]), np.array([100.0, 271.0])), dtype=torch.float32)
    wv = torch.tensor(views[[2, 3]], dtype=torch.float32)
    pred = model.predict_texel_images(wv, wl)
    ref = np.einsum("hwvcj,vj->vhwc", truth[:, :, [2, 3]], real_sh_basis(wl.double().numpy()))
    np.testing.assert_allclose(pred.numpy().reshape(ref.shape), ref, atol=2e-5)


def test_sh_view_without_fitted_lights_is_filled_from_neighbours(btf):
    train = np.array([p for p in btf.pairs() if p[0] != 3])
    model = fit_sh(btf, pairs=train, progress=False)
    coef = model.coefficients.reshape(btf.height, btf.width, btf.n_views, 27)
    assert coef[:, :, 3].abs().sum() > 0 and torch.isfinite(coef).all()
    assert model.positional_plane().shape == (btf.height, btf.width, btf.n_views * 27)


# ---------------------------------------------------------------------- NeuMIP
def test_neumip_shapes_and_inputs():
    model = NeuMIP(6, 7)
    assert model.positional_plane().shape == (6, 7, 8)
    assert model.decoder.first.in_features == 12 and model.decoder.first.out_features == 32
    assert len(model.decoder.rest) == 3 and model.decoder.rest[-1].out_features == 3
    wv = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, 1.0]]), dim=-1)
    wl = torch.nn.functional.normalize(torch.tensor([[-0.5, 0.1, 1.0]]), dim=-1)
    torch.testing.assert_close(model.direction_inputs(wv, wl), torch.cat([wl[:, :2], wv[:, :2]], -1))
    out = model(torch.rand(4, 5, 2), wv.expand(4, 5, 3), wl.expand(4, 5, 3))
    assert out.shape == (4, 5, 3)
    groups = model.param_groups()
    assert {id(p) for g in groups for p in g["params"]} == {id(p) for p in model.parameters()}
    assert all(g["lr"] == 1e-3 for g in groups)


def test_neumip_training_decreases_the_l1_loss(btf):
    model = NeuMIP(btf.height, btf.width, seed=1)
    optimizer = torch.optim.Adam(model.param_groups())
    pairs = np.array(list(btf.pairs()))
    wv, wl = pair_directions(btf, pairs)
    target = torch.tensor(np.stack([btf.image(v, l).reshape(-1, 3) for v, l in pairs]))

    def full_loss():
        with torch.no_grad():
            return float((model.predict_texel_images(wv, wl) - target).abs().mean())

    before = full_loss()
    rng = np.random.default_rng(0)
    for _step in range(100):
        batch = torch.from_numpy(rng.choice(len(pairs), 16, replace=False))
        loss = (model.predict_texel_images(wv[batch], wl[batch]) - target[batch]).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert full_loss() < 0.5 * before
    assert all(p.grad is not None for p in model.parameters())


# ---------------------------------------------------------------------- the synthesis interface
def fitted_baselines(btf):
    return {"neumip": NeuMIP(btf.height, btf.width, seed=4),
            "pca": fit_pca(btf, components=3, progress=False),
            "sh": fit_sh(btf, progress=False)}


@pytest.mark.parametrize("kind", ["neumip", "pca", "sh"])
def test_plane_fetch_then_decode_equals_forward_and_texel_images(btf, kind):
    model = fitted_baselines(btf)[kind]
    assert get_representation_class(kind) is type(model)
    uv = torch.tensor(texel_centers_uv(btf.height, btf.width).reshape(-1, 2))
    pairs = np.array([[0, 0], [4, 13], [10, 23]])
    wv, wl = pair_directions(btf, pairs)
    images = model.predict_texel_images(wv, wl)
    for b in range(len(pairs)):
        v, l = wv[b].expand(len(uv), 3), wl[b].expand(len(uv), 3)
        forward = model(uv, v, l)
        synthesized = model.decode(model.positional_features(uv), v, l)  # what synthesis does
        torch.testing.assert_close(forward, images[b], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(synthesized, forward)
    # off-grid query: directions between measured ones still decode to finite values
    q = torch.nn.functional.normalize(torch.tensor([[0.2, 0.1, 0.9]]), dim=-1).expand(len(uv), 3)
    assert torch.isfinite(model(uv, q, q.flip(-1).abs())).all()


def test_config_rebuilds_each_baseline(btf):
    for kind, model in fitted_baselines(btf).items():
        rebuilt = get_representation_class(kind)(**model.config())
        rebuilt.load_state_dict(model.state_dict())
        wv, wl = pair_directions(btf, [[2, 7]])
        torch.testing.assert_close(rebuilt.predict_texel_images(wv, wl), model.predict_texel_images(wv, wl))
    with pytest.raises(InputError, match="bands"):
        SphericalHarmonics(4, 4, 2, bands=4)


# ---------------------------------------------------------------------- fitters and model files
def test_neumip_fused_loss_equals_plain_loss_and_gradients(btf):
    model = NeuMIP(btf.height, btf.width, seed=2)
    wv, wl = pair_directions(btf, [[1, 3], [6, 20], [9, 9]])
    target = torch.rand(3, btf.height * btf.width, 3, generator=torch.Generator().manual_seed(0))
    fused = model.texel_image_l1_loss(wv, wl, target, chunk_texels=16)
    fused.backward()
    grads = [p.grad.clone() for p in model.parameters()]
    model.zero_grad()
    plain = (model.predict_texel_images(wv, wl) - target).abs().mean()
    plain.backward()
    torch.testing.assert_close(fused, plain)
    for g, p in zip(grads, model.parameters()):
        torch.testing.assert_close(g, p.grad, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("kind", ["pca", "sh"])
def test_closed_form_fitters_hold_out_pairs_and_round_trip_model_files(btf, kind, tmp_path):
    from dynbtf.representations.model_file import load_model
    from dynbtf.training import TrainConfig, get_fitter, held_out_split

    config = TrainConfig(held_out_fraction=0.1, seed=5)
    result = get_fitter(kind)(btf, tmp_path / f"{kind}.dbtfm", config, progress=False)
    train, held = held_out_split(btf.n_views, btf.n_lights, 0.1, 5)
    provenance = result.metadata["provenance"]
    assert provenance["held_out_pairs"] == held.tolist() and provenance["training_seconds"] >= 0
    loaded, meta = load_model(tmp_path / f"{kind}.dbtfm")
    assert meta["kind"] == kind and type(loaded) is type(result.representation)
    for name, tensor in result.representation.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor), name
    # the direct fit on the same training pairs is the same model
    direct = fit_pca(btf, pairs=train, seed=5, progress=False) if kind == "pca" else fit_sh(btf, pairs=train,
                                                                                              progress=False)
    torch.testing.assert_close(loaded.positional_plane(), direct.positional_plane())


def test_neumip_trains_with_the_shared_trainer_and_round_trips(btf, tmp_path):
    from dynbtf.representations.model_file import load_model
    from dynbtf.training import TrainConfig, get_fitter

    config = TrainConfig(epochs=4, images_per_step=8, held_out_fraction=0.1, seed=3, device="cpu", workers=1)
    result = get_fitter("neumip")(btf, tmp_path / "neumip.dbtfm", config, progress=False)
    psnr = [h["held_out_psnr"] for h in result.history]
    assert len(psnr) == 4 and psnr[-1] > psnr[0]
    loaded, _ = load_model(tmp_path / "neumip.dbtfm")
    for name, tensor in result.representation.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor.cpu()), name


@pytest.mark.parametrize("kind", ["neumip", "pca", "sh"])
def test_each_baseline_through_the_synthesized_btf(btf, kind):
    from dynbtf.synthesized import synthesized_btf

    model = fitted_baselines(btf)[kind]
    uv = torch.tensor(texel_centers_uv(btf.height, btf.width).reshape(-1, 2))
    wv, wl = (w.expand(len(uv), 3) for w in pair_directions(btf, [[4, 13]]))
    reference = model(uv, wv, wl)
    tiled = synthesized_btf(model, "tile", scale=1.0).eval(uv + 7.0, wv, wl)  # plain repetition: the model itself
    torch.testing.assert_close(tiled, reference, atol=1e-5, rtol=1e-5)
    blended = synthesized_btf(model, "hist", scale=1.0, seed=3).eval(uv + 1e5, wv, wl)
    assert blended.shape == reference.shape and torch.isfinite(blended).all()
    assert not torch.allclose(blended, reference)  # the plane was really synthesized
