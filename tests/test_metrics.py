"""Image metrics against closed forms and an independent SSIM implementation."""

import math

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from dynbtf.errors import InputError
from dynbtf.io import linear_to_srgb
from dynbtf.metrics import dssim, flip, flip_map, psnr, psnr_fixed_range


def by_hand_mse(a, b):
    total, count = 0.0, 0
    for x, y in zip(np.asarray(a, np.float64).ravel().tolist(), np.asarray(b, np.float64).ravel().tolist()):
        total += (x - y) ** 2
        count += 1
    return total / count


def test_psnr_fixed_range_closed_form_and_by_hand():
    rng = np.random.default_rng(0)
    a = rng.random((16, 12, 3)).astype(np.float32)
    # constant error c everywhere: MSE = c^2 -> PSNR = -20 log10(c)
    assert psnr_fixed_range(a, a + 0.05) == pytest.approx(-20 * math.log10(0.05), abs=1e-4)
    # half the values off by 0.2: MSE = 0.02
    b = a.copy()
    b[:8] += 0.2
    assert psnr_fixed_range(a, b) == pytest.approx(10 * math.log10(1 / 0.02), abs=1e-4)
    assert psnr_fixed_range(a, a + 0.1, data_range=2.0) == pytest.approx(20 * math.log10(2 / 0.1), abs=1e-4)
    assert psnr_fixed_range(a, a) == math.inf
    c = a + rng.normal(0, 0.03, a.shape).astype(np.float32)
    assert psnr_fixed_range(a, c) == pytest.approx(10 * math.log10(1.0 / by_hand_mse(a, c)), abs=1e-6)
    with pytest.raises(InputError, match="data_range"):
        psnr_fixed_range(a, c, data_range=0)


def test_psnr_per_image_peak_by_hand():
    """Peak = the reference's maximum over texels and channels (not the test image's, not 1)."""
    rng = np.random.default_rng(1)
    ref = (0.2 * rng.random((9, 7, 3))).astype(np.float32)  # a dark material: max ~0.2
    ref[4, 3, 1] = 0.31
    test = ref + rng.normal(0, 0.01, ref.shape).astype(np.float32)
    test[0, 0, 0] = 0.9  # the test's own peak does not matter
    expected = 10 * math.log10(0.31 ** 2 / by_hand_mse(ref, test))
    assert psnr(ref, test) == pytest.approx(expected, abs=1e-5)
    # the fixed form reads ~10 dB higher on this dark image: 20 log10(1 / 0.31)
    assert psnr_fixed_range(ref, test) - psnr(ref, test) == pytest.approx(-20 * math.log10(0.31), abs=1e-5)
    assert psnr(ref, ref) == math.inf
    assert math.isnan(psnr(np.zeros((2, 2, 3)), np.full((2, 2, 3), 0.1)))  # an all-black reference has no peak


@pytest.mark.parametrize("k", [0.01, 0.25, 7.0, 40.0])
def test_psnr_is_unchanged_when_a_pair_is_scaled(k):
    rng = np.random.default_rng(2)
    ref = rng.random((8, 8, 3)).astype(np.float64)
    test = ref + rng.normal(0, 0.05, ref.shape)
    assert psnr(k * ref, k * test) == pytest.approx(psnr(ref, test), abs=1e-4)  # float32 inputs
    assert psnr_fixed_range(k * ref, k * test) == pytest.approx(psnr_fixed_range(ref, test) - 20 * math.log10(k),
                                                                abs=1e-4)


def independent_ssim(x, y):
    """SSIM with a 7x7 uniform window and sample covariance (Wang et al. 2004 constants), per channel mean."""
    c1, c2, n = 0.01 ** 2, 0.03 ** 2, 49
    values = []
    for c in range(3):
        a, b = x[..., c].astype(np.float64), y[..., c].astype(np.float64)
        mu_a, mu_b = uniform_filter(a, 7), uniform_filter(b, 7)
        va = (uniform_filter(a * a, 7) - mu_a ** 2) * n / (n - 1)
        vb = (uniform_filter(b * b, 7) - mu_b ** 2) * n / (n - 1)
        cov = (uniform_filter(a * b, 7) - mu_a * mu_b) * n / (n - 1)
        s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (va + vb + c2))
        values.append(s[3:-3, 3:-3].mean())
    return float(np.mean(values))


def test_dssim_matches_independent_formula_on_srgb():
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:32, 0:40] / 32.0
    ref = np.stack([0.2 + 0.5 * xx / 1.25, 0.3 + 0.2 * np.sin(6 * yy), 0.1 + 0.3 * yy], -1).astype(np.float32)
    test = np.clip(ref + rng.normal(0, 0.05, ref.shape), 0, 1.5).astype(np.float32)
    expected = (1 - independent_ssim(linear_to_srgb(ref), linear_to_srgb(test))) / 2
    assert dssim(ref, test) == pytest.approx(expected, abs=1e-5)
    assert dssim(ref, ref) == pytest.approx(0.0, abs=1e-7)
    assert 0 < dssim(ref, test) <= 1


def test_flip_identical_is_zero_and_differences_are_bounded_and_ordered():
    rng = np.random.default_rng(2)
    ref = rng.random((24, 24, 3)).astype(np.float32) * 0.8
    assert flip(ref, ref) == pytest.approx(0.0, abs=1e-7)
    small = flip(ref, ref * 0.95)
    large = flip(ref, np.clip(ref + rng.normal(0, 0.3, ref.shape), 0, 1).astype(np.float32))
    assert 0 < small < large <= 1
    error_map, mean = flip_map(ref, ref * 0.95)
    assert error_map.shape == (24, 24) and error_map.min() >= 0 and error_map.max() <= 1
    assert mean == pytest.approx(float(error_map.mean()), rel=1e-4)
    # values above 1 are clamped before encoding: an HDR difference above white is invisible
    assert flip(np.full((8, 8, 3), 2.0, np.float32), np.full((8, 8, 3), 3.0, np.float32)) == pytest.approx(0, abs=1e-7)


@pytest.mark.parametrize("metric", [psnr, dssim, flip])
def test_metrics_reject_bad_input(metric):
    a = np.zeros((8, 8, 3), np.float32)
    with pytest.raises(InputError, match="shape"):
        metric(a, np.zeros((8, 9, 3), np.float32))
    with pytest.raises(InputError, match=r"\(H, W, 3\)"):
        metric(np.zeros((3, 8, 8), np.float32), np.zeros((3, 8, 8), np.float32))
    with pytest.raises(InputError, match="uint8"):
        metric(a, np.zeros((8, 8, 3), np.uint8))
    bad = a.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        metric(bad, a)


def test_flip_magma_is_flips_colour_map_of_its_error():
    """FLIP's display: no error is magma's black end, a larger error a brighter colour, pixel by pixel."""
    from dynbtf.metrics import flip_magma

    rng = np.random.default_rng(4)
    ref = rng.random((16, 16, 3)).astype(np.float32) * 0.8
    test = ref.copy()
    test[:, :8] = np.clip(ref[:, :8] + 0.4, 0, 1)  # error in the left half only
    display = flip_magma(ref, test)
    error_map, _ = flip_map(ref, test)
    assert display.shape == (16, 16, 3) and display.dtype == np.float32
    assert 0.0 <= display.min() and display.max() <= 1.0
    same = flip_magma(ref, ref).reshape(-1, 3)
    assert np.allclose(same, same[0]) and same[0].sum() < 0.1  # no error anywhere: magma's black end
    brightness = display.sum(-1)
    order = np.argsort(error_map.ravel())
    assert np.all(np.diff(brightness.ravel()[order]) >= -1e-6)  # brighter with the error, as magma is
    assert brightness[:, :8].mean() > brightness[:, 8:].mean() + 0.5
