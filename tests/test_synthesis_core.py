"""Synthesis building blocks: hash, lattice, histogram transforms, tileable preprocessing, quilting.

References: a pure-Python (arbitrary-precision int) lowbias32 hash; the lattice
recomputed with ``fractions.Fraction`` and a 40-digit sqrt(3) (``decimal``);
``np.interp`` + ``scipy.special.ndtr`` for the inverse transform; brute-force
SSD and path enumeration for quilting.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy.special import ndtr

from dynbtf.errors import InputError
from dynbtf.synthesis import hash as H
from dynbtf.synthesis.histogram import (Decorrelation, GaussianTransform, blend_weights,
                                        variance_preserving_blend)
from dynbtf.synthesis.lattice import LATTICE_SCALE, TRIANGLE_EDGE, triangle_lattice, vertex_uv
from dynbtf.synthesis.quilting import Quilting, min_error_cut, min_error_seam, overlap_errors, quilt, quilted_storage_bytes
from dynbtf.synthesis.tileable import make_tileable, seam_discontinuity
from synthesis_reference import exact_lattice, reference_hash, smooth_lognormal


# ---------------------------------------------------------------- hash
def test_hash_fixed_values_and_reference():
    # pinned: any change breaks reproducibility of every synthesized material
    assert int(H.hash_vertex(np.int64(0), np.int64(0), 0)) == 4125828455
    assert int(H.hash_vertex(np.int64(1), np.int64(0), 0)) == reference_hash(1, 0, 0)
    assert reference_hash(0, 0, 0) == 4125828455
    assert [int(x) for x in H.hash_vertex(np.array([3, -7, 1 << 40]), np.array([5, 1 << 40, -1]), 7)] == \
        [reference_hash(3, 5, 7), reference_hash(-7, 1 << 40, 7), reference_hash(1 << 40, -1, 7)]


def test_hash_numpy_torch_numba_agree():
    rng = np.random.default_rng(1)
    vx = np.concatenate([rng.integers(-2**40, 2**40, 500), rng.integers(-50, 50, 500)]).astype(np.int64)
    vy = np.concatenate([rng.integers(-2**40, 2**40, 500), rng.integers(-50, 50, 500)]).astype(np.int64)
    seed = 123456789
    expected = np.array([reference_hash(int(a), int(b), seed) for a, b in zip(vx, vy)], dtype=np.int64)
    np.testing.assert_array_equal(H.hash_vertex(vx, vy, seed), expected)
    np.testing.assert_array_equal(H.hash_vertex(torch.from_numpy(vx), torch.from_numpy(vy), seed).numpy(), expected)
    from dynbtf.synthesis.kernels import jit_hash_vertex as _hash_vertex

    assert [_hash_vertex(np.int64(a), np.int64(b), np.int64(seed)) for a, b in zip(vx[:20], vy[:20])] == \
        expected[:20].tolist()
    ox, oy = H.vertex_offsets(vx, vy, seed, 37, 29)
    assert ox.min() >= 0 and ox.max() < 37 and oy.min() >= 0 and oy.max() < 29


def test_hash_offsets_are_uniform_and_seed_dependent():
    v = np.arange(40000, dtype=np.int64)
    ox, _ = H.vertex_offsets(v % 200, v // 200, 0, 16, 16)
    counts = np.bincount(ox, minlength=16)
    chi2 = ((counts - 2500) ** 2 / 2500).sum()
    assert chi2 < 45  # 15 dof: p ~ 1e-4
    ox1, _ = H.vertex_offsets(v % 200, v // 200, 1, 16, 16)
    assert (ox1 != ox).mean() > 0.9


# ---------------------------------------------------------------- lattice
def test_lattice_barycentrics_and_equilateral_triangles():
    uv = torch.rand(5000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 6 - 3
    vertices, bary = triangle_lattice(uv)
    assert bool((bary >= 0).all())
    torch.testing.assert_close(bary.sum(-1), torch.ones(5000, dtype=torch.float64), rtol=0, atol=1e-12)
    pos = vertex_uv(vertices)
    torch.testing.assert_close((pos * bary[..., None]).sum(-2), uv, rtol=0, atol=1e-12)
    for i, j in ((0, 1), (1, 2), (0, 2)):
        d = (pos[:, i] - pos[:, j]).norm(dim=-1)
        torch.testing.assert_close(d, torch.full_like(d, TRIANGLE_EDGE), rtol=0, atol=1e-12)
    assert TRIANGLE_EDGE == pytest.approx(0.2887, abs=1e-4)


@pytest.mark.parametrize("offset", [0.0, 1e6, -3e7, 1e9, 2.0**40, -(2.0**51), 2.0**52 - 2])
def test_lattice_exact_at_large_coordinates(offset):
    rng = np.random.default_rng(2)
    uv = rng.random((200, 2)) + offset
    vertices, bary = triangle_lattice(torch.from_numpy(uv))
    for n in range(200):
        (bx, by), (fx, fy) = exact_lattice(uv[n, 0], uv[n, 1])
        lower = 1 - fx - fy > 0
        expected_b = [1 - fx - fy, fy, fx] if lower else [fx + fy - 1, 1 - fy, 1 - fx]
        first = [bx, by] if lower else [bx + 1, by + 1]
        assert vertices[n, 0].tolist() == first
        # below 2**27 repeats the float64 constant 2 sqrt(3) (error ~2e-16 |u|); beyond, integer fixed point
        np.testing.assert_allclose(bary[n].numpy(), expected_b, atol=1e-8 if abs(offset) < 2**27 else 1e-12)


def test_large_scaled_integer_is_exact_up_to_the_uv_limit():
    from fractions import Fraction

    from dynbtf.synthesis.lattice import MAX_REPEATS, large_scaled_integer
    from synthesis_reference import exact_lattice

    rng = np.random.default_rng(4)
    i = np.concatenate([[2**27, -(2**27), 2**52 - 1, -(2**52) + 1, 2**53, -(2**53)],
                        rng.integers(-(2**52), 2**52, 500)])
    whole, frac = large_scaled_integer(torch.from_numpy(i))
    assert whole.dtype == torch.int64 and frac.dtype == torch.float64 and MAX_REPEATS == 2.0**52
    for k, n in enumerate(i.tolist()):
        (bx, _), (fx, _) = exact_lattice(float(n), 0.0)  # k_x = 2 sqrt(3) n
        assert abs(Fraction(int(whole[k])) + Fraction(float(frac[k])) - (bx + Fraction(fx))) < 1e-14


def test_lattice_whole_v_shift_is_an_exact_lattice_translation():
    uv = torch.from_numpy(np.random.default_rng(3).integers(0, 2**20, (300, 2)) / 2**20)  # dyadic: uv + N exact
    v0, b0 = triangle_lattice(uv)
    for n in (1, 12345, 10**6, -(10**9)):
        v1, b1 = triangle_lattice(uv + torch.tensor([0.0, float(n)], dtype=torch.float64))
        assert torch.equal(b1, b0)
        assert torch.equal(v1 - v0, torch.tensor([-2 * n, 4 * n]).expand_as(v0))


def test_lattice_scale_constant():
    # the shaders' 0.57735027 / 1.15470054 are 1/sqrt(3) and 2/sqrt(3)
    assert LATTICE_SCALE == pytest.approx(2 * math.sqrt(3))
    s = LATTICE_SCALE * np.array([0.3, 0.7])
    k = (s[0] - 0.57735027 * s[1], 1.15470054 * s[1])
    (bx, by), (fx, fy) = exact_lattice(0.3, 0.7)
    assert (bx + fx, by + fy) == pytest.approx(k, abs=1e-7)


# ---------------------------------------------------------------- histogram transforms
def test_gaussian_transform_round_trip_and_reference_inverse():
    x = smooth_lognormal(16, 16, 3).reshape(-1, 3).double()
    x[:40, 0] = x[0, 0]  # ties
    transform, g = GaussianTransform.fit(x)
    torch.testing.assert_close(transform.inverse(g), x, rtol=0, atol=1e-9 * float(x.abs().max()))
    # forward on distinct exemplar values is the rank transform
    torch.testing.assert_close(transform.forward(x)[:, 1:], g[:, 1:], rtol=0, atol=1e-9)
    # marginals of T(x) are the standard normal quantiles
    assert abs(float(g.mean())) < 1e-12 and float(g.std()) == pytest.approx(1.0, abs=0.02)
    # exact inverse == np.interp(Phi(g), (arange(N) + .5) / N, sorted)
    q = np.random.default_rng(0).normal(0, 1.3, (1000, 3))
    ours = transform.inverse(torch.from_numpy(q)).numpy()
    n = x.shape[0]
    for c in range(3):
        ref = np.interp(ndtr(q[:, c]), (np.arange(n) + 0.5) / n, np.sort(x[:, c].numpy()))
        np.testing.assert_allclose(ours[:, c], ref, rtol=1e-10, atol=1e-12)


def test_inverse_lut_error_bound_and_clamp():
    x = smooth_lognormal(32, 32, 2, seed=4).reshape(-1, 2).double()
    transform, g = GaussianTransform.fit(x)
    lut = transform.lut(4096)
    bulk = torch.linspace(-3, 3, 20001, dtype=torch.float64)[:, None].expand(-1, 2)
    err = (lut(bulk) - transform.inverse(bulk)).abs().max(0).values / x.std(0)
    assert float(err.max()) < 0.01
    far = torch.tensor([[-50.0, 50.0]], dtype=torch.float64)
    np.testing.assert_allclose(lut(far).numpy()[0], [float(x[:, 0].min()), float(x[:, 1].max())], rtol=1e-12)
    with pytest.raises(InputError, match="lut_size"):
        transform.lut(1)


def test_variance_preserving_blend_keeps_mean_and_variance():
    g = torch.randn(400000, 3, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    b = torch.rand(400000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    w = blend_weights(b / b.sum(-1, keepdim=True))
    out = variance_preserving_blend(g, w)
    assert abs(float(out.mean())) < 0.01 and float(out.std()) == pytest.approx(1.0, abs=0.01)
    plain = (w[..., None] * g).sum(-2)
    assert float(plain.std()) < 0.8  # what the correction fixes
    torch.testing.assert_close(blend_weights(torch.tensor([[1.0, 1.0, 2.0]]), 2.0),
                               torch.tensor([[1 / 6, 1 / 6, 4 / 6]]))


def test_decorrelation_diagonalizes_and_round_trips():
    x = smooth_lognormal(24, 24, 4).reshape(-1, 4).double()
    pca = Decorrelation.fit(x)
    c = pca.project(x)
    cov = torch.cov(c.T)
    assert float((cov - torch.diag(torch.diag(cov))).abs().max()) < 1e-10
    assert bool((pca.variances[:-1] >= pca.variances[1:]).all())
    torch.testing.assert_close(pca.unproject(c), x)


# ---------------------------------------------------------------- tileable
def test_tileable_is_periodic_and_keeps_interior_and_histogram():
    x = smooth_lognormal(48, 48, 4)
    band = 8
    t = make_tileable(x, band)
    assert t.shape == (40, 40, 4)
    assert seam_discontinuity(x) > 3.0
    assert seam_discontinuity(t) < 1.3
    # the interior (outside the bands) is untouched
    torch.testing.assert_close(t[band:, band:], x[band:40, band:40], rtol=1e-6, atol=1e-6)
    from scipy.stats import wasserstein_distance

    # the histogram changes no more than cropping a 48^2 patch to 40^2 does (~0.04-0.15 here)
    for c in range(4):
        assert wasserstein_distance(t[..., c].flatten(), x[..., c].flatten()) / float(x[..., c].std()) < 0.1
        assert float(t[..., c].std() / x[..., c].std()) == pytest.approx(1.0, abs=0.08)
    with pytest.raises(InputError, match="band"):
        make_tileable(x, 20)


# ---------------------------------------------------------------- quilting
def test_min_error_cut_matches_brute_force():
    rng = np.random.default_rng(5)
    for _ in range(5):
        e = rng.random((5, 4))
        best = math.inf
        for start in range(4):
            for steps in itertools.product((-1, 0, 1), repeat=4):
                path = [start]
                for s in steps:
                    path.append(path[-1] + s)
                if min(path) < 0 or max(path) > 3:
                    continue
                best = min(best, sum(e[i, p] for i, p in enumerate(path)))
        cut = min_error_cut(e)
        assert np.all(np.abs(np.diff(cut)) <= 1)
        assert sum(e[i, p] for i, p in enumerate(cut)) == pytest.approx(best)


def test_min_error_seam_matches_brute_force_over_every_path():
    """Every column sequence is a seam; its cost: each row's cut texel, plus min of the two rows' errors at every
    column strictly between consecutive cuts. Batched problems equal the same problems solved one by one."""
    rng = np.random.default_rng(7)
    for _ in range(40):
        rows, cols = int(rng.integers(1, 5)), int(rng.integers(1, 6))
        e = rng.random((rows, cols)) ** 3

        def cost(path):
            total = sum(e[r, c] for r, c in enumerate(path))
            for r in range(1, rows):
                low, high = sorted((path[r - 1], path[r]))
                total += sum(min(e[r - 1, k], e[r, k]) for k in range(low + 1, high))
            return total

        best = min(cost(path) for path in itertools.product(range(cols), repeat=rows))
        cut = min_error_seam(e)
        assert cut.shape == (rows,) and cost(list(cut)) == pytest.approx(best, rel=1e-12, abs=1e-12)
    batch = rng.random((3, 2, 6, 7))
    cuts = min_error_seam(batch)
    for i, j in itertools.product(range(3), range(2)):
        assert (cuts[i, j] == min_error_seam(batch[i, j])).all()


def test_overlap_errors_match_direct_ssd():
    rng = np.random.default_rng(6)
    ex = rng.random((20, 18, 3))
    target = rng.random((6, 6, 3))
    mask = np.zeros((6, 6))
    mask[:, :2] = 1
    mask[:2, :] = 1
    from dynbtf.synthesis.quilting import _exemplar_spectra

    err = overlap_errors(_exemplar_spectra(ex), target, mask)
    assert err.shape == (15, 13)
    for y, x in [(0, 0), (3, 7), (14, 12)]:
        direct = (((ex[y:y + 6, x:x + 6] - target) ** 2).sum(-1) * mask).sum()
        assert err[y, x] == pytest.approx(direct, abs=1e-9)


def test_quilting_copies_blocks_and_reports_storage():
    x = smooth_lognormal(32, 32, 3, periodic=True)
    q = Quilting(x, seed=3, repeats=2, block=12, overlap=3)
    assert q.prepared.shape == (64, 64, 3) and not q.dynamic
    assert q.storage_bytes() == 64 * 64 * 3 * 4 == quilted_storage_bytes(32, 32, 3, 2)
    from dynbtf.synthesis.quality import verbatim_fraction

    assert verbatim_fraction(q.prepared.reshape(-1, 3).double().numpy(), x.reshape(-1, 3).double().numpy(),
                             tolerance=1e-4) > 0.999
    again = Quilting(x, seed=3, repeats=2, block=12, overlap=3)
    assert torch.equal(again.prepared, q.prepared)
    # queries wrap with the quilt's period (2 repeats), exactly at large coordinates: uv + 2e6 and uv
    # land on the same texel position up to float64 rounding (~1e-10 texel), which the float32
    # bilinear fetch may round to neighbouring float32 positions (one ulp at 64 texels = 7.6e-6
    # texel), so values agree to float32 resolution; a wrong period would differ by O(std).
    uv = torch.rand(50, 2, dtype=torch.float64)
    torch.testing.assert_close(q(uv + 2e6), q(uv), rtol=0, atol=1e-4 * float(x.std()))
    # a left-overlap cut: the seam follows the DP path through the squared differences
    rng = np.random.default_rng(0)
    plane = quilt(rng.random((16, 16, 1)), 16, 28, 8, 2, np.random.default_rng(1))
    assert plane.shape == (16, 28, 1)
    with pytest.raises(InputError, match="block"):
        Quilting(x, block=40)
