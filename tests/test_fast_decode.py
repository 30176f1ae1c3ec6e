"""The synthesized BTF's fused first-layer kernel (dynbtf.decoder.fast_decode) vs float64 references.

The kernel computes the Rusinkiewicz h/d vectors in float64 and their plane angles with a
branch-free polynomial atan2 (vectorized across queries). References: ``np.arctan2``; the
conventions' half/difference vectors and plane coordinates plus ``texture.fetch_angular``, all in
float64; ``torch.nn.functional.leaky_relu``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from dynbtf.conventions import angular_plane_coords, half_diff_from_view_light, spherical_to_direction
from dynbtf.errors import InputError
from dynbtf.decoder.fast_decode import _atan2, all_unit_vectors, first_layer_preactivation
from dynbtf.texture import fetch_angular


def test_polynomial_atan2_matches_numpy_everywhere():
    rng = np.random.default_rng(0)
    y = np.concatenate([rng.normal(size=20000), rng.normal(size=2000) * 1e-9, [0.0, 0.0, 1.0, -1.0, 1e-300, 0.0, -0.0]])
    x = np.concatenate([rng.normal(size=20000), rng.normal(size=2000), [1.0, -1.0, 0.0, 0.0, 1.0, 0.0, 1.0]])
    # octant boundaries and the tan(pi/8) switch of the range reduction
    a = np.linspace(-math.pi, math.pi, 4001)
    y, x = np.concatenate([y, np.sin(a), np.full(3, math.tan(math.pi / 8))]), np.concatenate([x, np.cos(a), np.ones(3)])
    got = np.array([_atan2(b, c) for b, c in zip(y, x)])
    expected = np.arctan2(y, x)
    expected[(y == 0) & (x == 0)] = 0.0
    wrapped = np.abs(np.angle(np.exp(1j * (got - expected))))  # -pi and pi are the same angle
    assert float(wrapped.max()) < 2e-15


def reference_first_layer(latent, w_pos, bias, w_view, w_light, plane_h, plane_d):
    """bias + latent @ w_pos + fetch(plane_h, h) + fetch(plane_d, d), everything in float64."""
    h, d = half_diff_from_view_light(torch.from_numpy(w_view).double(), torch.from_numpy(w_light).double())
    angular = (fetch_angular(torch.from_numpy(plane_h).double(), angular_plane_coords(h))
               + fetch_angular(torch.from_numpy(plane_d).double(), angular_plane_coords(d)))
    return torch.from_numpy(latent).double() @ torch.from_numpy(w_pos).double() + torch.from_numpy(bias).double() \
        + angular


def direction_set(rng, n):
    """Random hemisphere pairs plus the hard cases: h at or near the pole, grazing, the phi seam."""
    wv = spherical_to_direction(rng.random(n) * 89.0, rng.random(n) * 360.0)
    wl = spherical_to_direction(rng.random(n) * 89.0, rng.random(n) * 360.0)
    k = n // 5
    wl[:k] = wv[:k] * np.array([-1.0, -1.0, 1.0])  # mirror pairs: h exactly at the normal
    wl[k:2 * k] = spherical_to_direction(*direction_angles(wv[k:2 * k], rng, 1e-3))  # h within ~1e-3 deg
    wv[2 * k:3 * k] = spherical_to_direction(np.full(k, 90.0), rng.random(k) * 360.0)  # grazing view
    wv[3 * k:3 * k + 50] = spherical_to_direction(np.full(50, 40.0), np.full(50, 180.0))  # phi = 180: seam of t
    return wv.astype(np.float32), wl.astype(np.float32)


def direction_angles(w, rng, jitter):
    """(theta, phi) of the mirror of ``w`` about the normal, jittered by up to ``jitter`` degrees."""
    theta = np.degrees(np.arccos(np.clip(w[:, 2], -1, 1))) + rng.uniform(-jitter, jitter, len(w))
    phi = np.degrees(np.arctan2(w[:, 1], w[:, 0])) + 180.0 + rng.uniform(-jitter, jitter, len(w))
    return np.abs(theta), phi


@pytest.mark.parametrize("resolution", [20, 7])
def test_first_layer_matches_float64_reference(resolution):
    rng = np.random.default_rng(resolution)
    n, c, hidden = 5000, 16, 32
    latent = rng.normal(size=(n, c)).astype(np.float32)
    w_pos = (rng.normal(size=(c, hidden)) / 4).astype(np.float32)
    bias = rng.normal(size=hidden).astype(np.float32)
    plane_h = rng.normal(size=(resolution, resolution, hidden)).astype(np.float32)
    plane_d = rng.normal(size=(resolution, resolution, hidden)).astype(np.float32)
    wv, wl = direction_set(rng, n)
    expected = reference_first_layer(latent, w_pos, bias, wv, wl, plane_h, plane_d)
    pre = first_layer_preactivation(latent, w_pos, bias, wv, wl, plane_h, plane_d)
    err = np.abs(pre - expected.numpy())
    # float32 storage and sums of ~O(1) terms: a few float32 ulps (measured 3e-6 relative, near the pole
    # of h; the same fetches at float32-computed angles are off by 6e-5 relative)
    assert float(err.max()) < 1e-5 * float(np.abs(expected.numpy()).max())
    act = first_layer_preactivation(latent, w_pos, bias, wv, wl, plane_h, plane_d, negative_slope=0.01)
    np.testing.assert_allclose(act, F.leaky_relu(torch.from_numpy(pre), 0.01).numpy(), rtol=1e-6, atol=1e-6)


def test_all_unit_vectors():
    w = spherical_to_direction(np.array([0.0, 45.0, 90.0, 120.0]), np.array([0.0, 10.0, 200.0, 300.0]))
    assert all_unit_vectors(w) and all_unit_vectors(w.astype(np.float32))  # below the horizon is fine here
    assert all_unit_vectors(np.zeros((0, 3)))
    for bad in (np.nan, np.inf):
        v = w.copy()
        v[2, 1] = bad
        assert not all_unit_vectors(v)
    assert not all_unit_vectors(w * 1.01) and all_unit_vectors(w * 1.0005)


def test_threaded_evaluation_equals_serial():
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesized import synthesized_btf

    rng = np.random.default_rng(5)
    model = TriplePlane(24, 24, seed=1)
    uv = rng.random((5000, 2)) * 7 + 1e6
    wv = spherical_to_direction(rng.random(5000) * 100, rng.random(5000) * 360)  # some below the horizon: 0
    wl = spherical_to_direction(rng.random(5000) * 80, rng.random(5000) * 360)
    serial = synthesized_btf(model, "hist", scale=3.0, chunk_size=700, workers=1).eval(uv, wv, wl)
    threaded = synthesized_btf(model, "hist", scale=3.0, chunk_size=700, workers=3).eval(uv, wv, wl)
    np.testing.assert_array_equal(threaded, serial)
    assert (serial[wv[:, 2] < 0] == 0).all() and (serial[wv[:, 2] >= 0] != 0).any()
    with pytest.raises(InputError, match="workers"):
        synthesized_btf(model, "hist", workers=0)
