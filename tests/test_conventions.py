"""Direction conventions (dynbtf.conventions) and texture fetches (dynbtf.texture).

References: closed-form geometry (mirror configurations, the Rusinkiewicz
definition written out with explicit rotation matrices) and a brute-force
bilinear interpolation written with plain index arithmetic.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dynbtf.conventions import (angular_plane_coords, angular_plane_coords_to_direction, check_directions,
                                direction_to_spherical, half_diff_from_view_light, spherical_to_direction,
                                view_light_from_half_diff)
from dynbtf.texture import fetch_angular, fetch_wrap


def random_hemisphere(rng, n, max_theta=90.0):
    theta = np.degrees(np.arccos(rng.uniform(np.cos(np.radians(max_theta)), 1.0, n)))
    phi = rng.uniform(0.0, 360.0, n)
    return spherical_to_direction(theta, phi)


def direction_pairs():
    """Random, grazing (89.9 deg) and normal-incidence pairs used below."""
    rng = np.random.default_rng(1)
    w = random_hemisphere(rng, 2000, 89.9)
    grazing = spherical_to_direction(np.full(50, 89.9), rng.uniform(0, 360, 50))
    normal = np.tile([0.0, 0.0, 1.0], (50, 1))
    views = np.concatenate([w[:1000], grazing, normal, grazing, normal])
    lights = np.concatenate([w[1000:], normal, grazing, grazing[::-1], normal])
    assert views.shape == lights.shape == (1200, 3)
    return views, lights


@pytest.mark.parametrize("kind", ["numpy", "torch"])
def test_half_diff_round_trip(kind):
    views, lights = direction_pairs()
    if kind == "torch":
        views, lights = torch.from_numpy(views), torch.from_numpy(lights)
    h, d = half_diff_from_view_light(views, lights)
    v2, l2 = view_light_from_half_diff(h, d)
    to_np = (lambda x: x.numpy()) if kind == "torch" else np.asarray
    np.testing.assert_allclose(to_np(v2), to_np(views), atol=1e-6)
    np.testing.assert_allclose(to_np(l2), to_np(lights), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(to_np(h), axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(to_np(d), axis=-1), 1.0, atol=1e-12)


def test_half_diff_matches_explicit_rotation_matrices():
    """d = R_y(-theta_h) R_z(-phi_h) w_light, written with explicit matrices."""
    rng = np.random.default_rng(2)
    views, lights = random_hemisphere(rng, 200), random_hemisphere(rng, 200)
    h, d = half_diff_from_view_light(views, lights)
    for k in range(200):
        s = views[k] + lights[k]
        hk = s / np.linalg.norm(s)
        th, ph = math.acos(hk[2]), math.atan2(hk[1], hk[0])
        rz = np.array([[math.cos(-ph), -math.sin(-ph), 0], [math.sin(-ph), math.cos(-ph), 0], [0, 0, 1]])
        ry = np.array([[math.cos(-th), 0, math.sin(-th)], [0, 1, 0], [-math.sin(-th), 0, math.cos(-th)]])
        np.testing.assert_allclose(h[k], hk, atol=1e-12)
        np.testing.assert_allclose(d[k], ry @ rz @ lights[k], atol=1e-12)
    # theta_d is the angle between h and either direction
    np.testing.assert_allclose(d[:, 2], (h * lights).sum(-1), atol=1e-12)
    np.testing.assert_allclose(d[:, 2], (h * views).sum(-1), atol=1e-12)


def test_reciprocity():
    views, lights = direction_pairs()
    h1, d1 = half_diff_from_view_light(views, lights)
    h2, d2 = half_diff_from_view_light(lights, views)
    np.testing.assert_allclose(h2, h1, atol=1e-12)
    np.testing.assert_allclose(d2, d1 * np.array([-1.0, -1.0, 1.0]), atol=1e-9)


def test_closed_form_cases():
    rng = np.random.default_rng(3)
    w = np.concatenate([random_hemisphere(rng, 100), [[0.0, 0.0, 1.0]]])
    # view == light: h is that direction, d is the pole
    h, d = half_diff_from_view_light(w, w)
    np.testing.assert_allclose(h, w, atol=1e-12)
    np.testing.assert_allclose(d, np.tile([0.0, 0.0, 1.0], (len(w), 1)), atol=1e-9)
    # mirror configuration about the normal: h is the normal, d is the light itself
    mirror = w * np.array([-1.0, -1.0, 1.0])
    h, d = half_diff_from_view_light(mirror, w)
    np.testing.assert_allclose(h, np.tile([0.0, 0.0, 1.0], (len(w), 1)), atol=1e-12)
    np.testing.assert_allclose(d, w, atol=1e-12)
    # view along the normal, light at 60 deg in the x-z plane: theta_h = 30 deg, theta_d = 30 deg
    h, d = half_diff_from_view_light(np.array([0, 0, 1.0]), spherical_to_direction(np.array(60.0), np.array(0.0)))
    np.testing.assert_allclose(direction_to_spherical(h), (30.0, 0.0), atol=1e-9)
    np.testing.assert_allclose(d, [0.5, 0.0, math.sqrt(3) / 2], atol=1e-12)


def test_spherical_round_trip_and_conventions():
    rng = np.random.default_rng(4)
    theta, phi = rng.uniform(0.01, 179.99, 500), rng.uniform(0, 360, 500)
    t2, p2 = direction_to_spherical(spherical_to_direction(theta, phi))
    np.testing.assert_allclose(t2, theta, atol=1e-9)
    np.testing.assert_allclose(p2, phi, atol=1e-9)
    # phi from +x towards +y, in [0, 360)
    np.testing.assert_allclose(spherical_to_direction(np.array(90.0), np.array(90.0)), [0, 1, 0], atol=1e-12)
    _, p = direction_to_spherical(np.array([[0.0, -1e-20, 1.0], [1.0, -1e-9, 0.0], [0.0, -1.0, 0.0]]))
    assert ((p >= 0) & (p < 360)).all() and p[2] == pytest.approx(270.0)
    # torch float32 gives the same in single precision and never returns 360
    tt, pt = direction_to_spherical(torch.tensor([[1.0, -1e-8, 0.0]]))
    assert float(pt) < 360.0


def test_angular_plane_coords_wrap_clamp_continuity():
    rng = np.random.default_rng(5)
    w = random_hemisphere(rng, 1000)
    st = angular_plane_coords(w)
    theta, phi = direction_to_spherical(w)
    np.testing.assert_allclose(st[:, 0], theta / 90.0, atol=1e-12)
    np.testing.assert_allclose(st[:, 1], phi / 360.0, atol=1e-12)
    np.testing.assert_allclose(angular_plane_coords_to_direction(st), w, atol=1e-9)
    # theta clamps (d may go below its pole's horizon), phi wraps
    below = spherical_to_direction(np.array([95.0, 120.0]), np.array([10.0, 20.0]))
    np.testing.assert_allclose(angular_plane_coords(below)[:, 0], 1.0)
    seam = spherical_to_direction(np.array([45.0, 45.0]), np.array([359.9999, 0.0001]))
    st = angular_plane_coords(seam)
    assert st[0, 1] > 0.999 and st[1, 1] < 0.001
    # continuity: a small step on the sphere moves (s, t) by a small circular distance (away from the pole)
    step = w + 1e-5 * rng.standard_normal(w.shape)
    step /= np.linalg.norm(step, axis=1, keepdims=True)
    a, b = angular_plane_coords(w), angular_plane_coords(step)
    away = direction_to_spherical(w)[0] > 5.0
    dt = np.abs((a[:, 1] - b[:, 1] + 0.5) % 1.0 - 0.5)
    assert np.abs(a[away, 0] - b[away, 0]).max() < 1e-3 and dt[away].max() < 1e-3
    # torch input gives torch output with the same values
    np.testing.assert_allclose(angular_plane_coords(torch.from_numpy(w)).numpy(), a, atol=1e-12)


@pytest.mark.parametrize("bad, message", [
    (np.zeros((3, 2)), "shape"),
    (np.array([[0.0, np.nan, 1.0]]), "NaN"),
    (np.array([[0.0, 0.0, 2.0]]), "unit"),
    (np.array([[0.0, 0.6, -0.8]]), "below the horizon"),
])
def test_check_directions_errors(bad, message):
    with pytest.raises(ValueError, match=message) as e:
        check_directions(bad, "views")
    assert "views" in str(e.value)


def test_check_directions_accepts_valid_and_opt_in_lower_hemisphere():
    w = np.array([[0.0, 0.6, -0.8], [0, 0, 1.0]])
    assert check_directions(w, "d", allow_below_horizon=True) is w
    assert check_directions(torch.tensor([[0.0, 0.0, 1.0]]), "w").shape == (1, 3)


# ------------------------------------------------------------------ texture fetches
def bilinear_reference(plane: np.ndarray, x: float, y: float, wrap_rows: bool) -> np.ndarray:
    """Brute-force bilinear value at continuous texel coordinates (x along columns, y along rows).

    Texel centres are at integer coordinates; columns always wrap; rows wrap
    (``wrap_rows``) or clamp to the edge texels.
    """
    h, w, _ = plane.shape
    j0, i0 = math.floor(x), math.floor(y)
    fx, fy = x - j0, y - i0
    total = np.zeros(plane.shape[-1])
    for di, wy in ((0, 1 - fy), (1, fy)):
        for dj, wx in ((0, 1 - fx), (1, fx)):
            i = (i0 + di) % h if wrap_rows else min(max(i0 + di, 0), h - 1)
            total += wy * wx * plane[i, (j0 + dj) % w]
    return total


def test_fetch_wrap_matches_brute_force_bilinear():
    rng = np.random.default_rng(6)
    plane = rng.standard_normal((5, 7, 3))
    uv = np.concatenate([rng.uniform(-3, 3, (300, 2)), [[0.0, 0.0], [0.999999, 0.5], [1 / 14, 1 / 10]]])
    got = fetch_wrap(torch.from_numpy(plane), torch.from_numpy(uv)).numpy()
    for k, (u, v) in enumerate(uv):
        frac_u, frac_v = u - math.floor(u), v - math.floor(v)
        ref = bilinear_reference(plane, frac_u * 7 - 0.5, frac_v * 5 - 0.5, wrap_rows=True)
        np.testing.assert_allclose(got[k], ref, atol=1e-5)
    # texel centres return the texel exactly
    centre = torch.tensor([[(3 + 0.5) / 7, (2 + 0.5) / 5]], dtype=torch.float64)
    np.testing.assert_allclose(fetch_wrap(torch.from_numpy(plane), centre).numpy()[0], plane[2, 3], atol=1e-6)


def test_fetch_wrap_huge_uv_is_exact():
    rng = np.random.default_rng(7)
    plane = torch.from_numpy(rng.standard_normal((8, 8, 4)).astype(np.float32))
    x = torch.from_numpy(rng.integers(0, 2**20, (100, 2)) / 2**20)  # exactly representable fractions
    near = fetch_wrap(plane, x)
    far = fetch_wrap(plane, x + 1e6)
    assert torch.equal(near, far)
    assert torch.equal(fetch_wrap(plane, x - 1e6), near)


def test_fetch_angular_matches_brute_force_clamp_and_wrap():
    rng = np.random.default_rng(8)
    plane = rng.standard_normal((6, 9, 2))
    st = np.concatenate([rng.uniform(-0.2, 1.2, (300, 1)), rng.uniform(-2, 2, (300, 1))], axis=1)
    got = fetch_angular(torch.from_numpy(plane), torch.from_numpy(st)).numpy()
    for k, (s, t) in enumerate(st):
        s_c = min(max(s, 0.0), 1.0)
        frac_t = t - math.floor(t)
        ref = bilinear_reference(plane, frac_t * 9 - 0.5, s_c * 6 - 0.5, wrap_rows=False)
        np.testing.assert_allclose(got[k], ref, atol=1e-5)
    # phi seam: t just below 1 and just above 0 give (nearly) the same value
    a = fetch_angular(torch.from_numpy(plane), torch.tensor([[0.4, 1 - 1e-7], [0.4, 1e-7]], dtype=torch.float64))
    np.testing.assert_allclose(a[0].numpy(), a[1].numpy(), atol=1e-5)


def test_fetches_are_differentiable_and_follow_the_plane_device():
    plane = torch.zeros(4, 4, 2, requires_grad=True)
    out = fetch_wrap(plane, torch.tensor([[0.3, 0.6]])).sum() + fetch_angular(plane, torch.tensor([[0.3, 0.6]])).sum()
    out.backward()
    assert plane.grad is not None and float(plane.grad.sum()) == pytest.approx(4.0)
    assert fetch_wrap(plane.detach(), torch.tensor([[0.1, 0.2]])).device == plane.device


def test_angular_taps_read_what_fetch_angular_reads():
    """Training reads the angular planes through taps computed once per (view, light) pair: the same values as the
    grid_sample fetch (float64: to rounding), seams, poles and clamped rows included, and the same gradient."""
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.texture import angular_taps, fetch_angular, fetch_taps

    g = torch.Generator().manual_seed(7)
    plane = torch.randn(20, 20, 8, generator=g, dtype=torch.float64)
    st = torch.rand(500, 2, generator=g, dtype=torch.float64) * torch.tensor([1.2, 3.0], dtype=torch.float64) \
        - torch.tensor([0.1, 1.0], dtype=torch.float64)
    st[:6] = torch.tensor([[0, 0], [1, 0.999999], [0.5, 1.0], [0.025, 0.025], [1, 1], [0.0, 0.5]])
    index, weight = angular_taps(st, 20, 20)
    torch.testing.assert_close(fetch_taps(plane.reshape(-1, 8), index, weight), fetch_angular(plane, st),
                               rtol=0, atol=1e-13)
    flat = plane.reshape(-1, 8).clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: fetch_taps(x, index, weight), (flat,))
    # the model's angular features through its taps, as the fit reads them, and its gradients
    model = TriplePlane(4, 4, seed=3)
    w = torch.nn.functional.normalize(torch.rand(64, 3, generator=g) + torch.tensor([0.0, 0.0, 0.2]), dim=-1)
    v = torch.nn.functional.normalize(torch.rand(64, 3, generator=g) + torch.tensor([0.0, 0.0, 0.2]), dim=-1)
    direct = model.angular_features(v, w)
    direct.square().sum().backward()
    grads = [model.f_h.grad.clone(), model.f_d.grad.clone()]
    model.zero_grad()
    with torch.no_grad():
        taps = model.direction_taps(v, w)
    tapped = model.angular_features(None, None, taps)
    tapped.square().sum().backward()
    # float32: the two compute the texel coordinate with different roundings (a few ulps of the padded side, 22),
    # which moves a value by that times the largest step between neighbouring texels
    eps = torch.finfo(torch.float32).eps
    planes = torch.stack([model.f_h, model.f_d]).detach()
    step = max(planes.diff(dim=1).abs().max(), planes.diff(dim=2).abs().max())
    torch.testing.assert_close(tapped, direct, rtol=0, atol=float(4 * 22 * eps * step + 8 * eps * planes.abs().max()))
    # the gradients: the same bilinear weights (to the coordinate's rounding) times 2 x the feature, summed
    torch.testing.assert_close([model.f_h.grad, model.f_d.grad], grads, rtol=0,
                               atol=float(4 * 22 * eps * 2 * direct.detach().abs().max() * 64))
