"""Patch coherence and identity with tiling (dynbtf.synthesis.coherence) and the quality report's structure entry.

The reference is brute force: every wrapped exemplar position of every patch by explicit loops.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from dynbtf.errors import InputError
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.synthesis.coherence import (best_matches, default_patch_size, patch_coherence, synthesized_coherence,
                                        synthesized_images)
from dynbtf.synthesis.quality import format_report, quality_report
from dynbtf.synthesized import synthesized_btf

pytestmark = pytest.mark.usefixtures("single_thread")


def brute_force_msd(patch: np.ndarray, exemplar: np.ndarray) -> np.ndarray:
    """``(H, W)`` mean squared difference of ``patch (P, P, C)`` to the exemplar at every wrapped top-left."""
    h, w, _ = exemplar.shape
    p = patch.shape[0]
    out = np.empty((h, w))
    for y in range(h):
        for x in range(w):
            window = exemplar[[(y + a) % h for a in range(p)]][:, [(x + b) % w for b in range(p)]]
            out[y, x] = ((patch - window) ** 2).mean()
    return out


def tiled(exemplar: np.ndarray, origin, shape) -> np.ndarray:
    """Plain tiling: image texel [i, j] = exemplar texel ((row0 + i) % H, (col0 + j) % W)."""
    h, w, _ = exemplar.shape
    rows = (origin[0] + np.arange(shape[0])) % h
    cols = (origin[1] + np.arange(shape[1])) % w
    return exemplar[rows[:, None], cols[None, :]]


@pytest.fixture(scope="module")
def exemplar():
    return np.random.default_rng(5).random((16, 16, 3))


def test_patch_size_rule():
    assert default_patch_size((128, 128)) == 16 and default_patch_size((400, 300, 3)) == 16
    assert default_patch_size((16, 16, 3)) == 4 and default_patch_size((32, 48, 3)) == 8
    assert default_patch_size((3, 3, 1)) == 1


@pytest.mark.parametrize("patch", [None, 8])
def test_matches_brute_force(exemplar, patch):
    rng = np.random.default_rng(1)
    image = rng.random((23, 19, 3))
    origin = (7, 3)
    image[:12, :12] = tiled(exemplar, (3, 6), (12, 12))  # patches found in the exemplar, elsewhere ...
    image[12:, 6:] = tiled(exemplar, (7 + 12, 3 + 6), (11, 13))  # ... and where tiling reads
    r = patch_coherence(image, exemplar, tiling_origin=origin, patch=patch, patches=40, seed=3, details=True)
    p = 4 if patch is None else 8  # a quarter of the 16-texel exemplar side
    assert r["patch"] == p and r["patches"] == 40 and r["tiling_origin"] == [7, 3]
    corners = r["corners"]
    assert corners.shape == (40, 2) and corners.min() >= 0
    assert (corners[:, 0] <= 23 - p).all() and (corners[:, 1] <= 19 - p).all()
    # the normalization: the median of random pairs is near the median over all pairs of positions
    every = np.stack([brute_force_msd(exemplar[[(y + a) % 16 for a in range(p)]][:, [(x + b) % 16 for b in range(p)]],
                                      exemplar).ravel() for y in range(16) for x in range(16)])
    off_diagonal = every[~np.eye(256, dtype=bool)]
    assert abs(r["reference_msd"] / np.median(off_diagonal) - 1) < 0.06
    best_msd = []
    for (i, j), best, score, at_tiling in zip(corners, r["best"], r["scores"], r["at_tiling"]):
        msd = brute_force_msd(image[i:i + p, j:j + p], exemplar)
        best_msd.append(msd.min())
        np.testing.assert_allclose(score * r["reference_msd"], msd.min(), rtol=1e-9, atol=1e-15)
        assert msd[tuple(best)] == pytest.approx(msd.min(), rel=1e-9, abs=1e-15)
        place = ((7 + i) % 16, (3 + j) % 16)
        assert at_tiling == (msd[place] <= msd.min() * (1 + 1e-9) + 1e-15)
    scores = np.array(best_msd) / r["reference_msd"]
    assert r["median"] == pytest.approx(np.median(scores), rel=1e-9, abs=1e-15)
    assert r["p90"] == pytest.approx(np.percentile(scores, 90), rel=1e-9, abs=1e-15)
    assert r["mean"] == pytest.approx(scores.mean(), rel=1e-9)
    assert r["identity"] == pytest.approx(np.mean(r["at_tiling"]))
    # every kind of patch was drawn
    assert (scores == 0).any() and (scores > 0.1).any() and r["at_tiling"].any() and (scores[~r["at_tiling"]] == 0).any()


def test_best_matches_on_given_corners(exemplar):
    image = np.random.default_rng(2).random((12, 12, 3))
    corners = np.array([[0, 0], [5, 7], [8, 8]])
    ssd, best = best_matches(image, exemplar, corners, 4)
    for (i, j), s, b in zip(corners, ssd, best):
        msd = brute_force_msd(image[i:i + 4, j:j + 4], exemplar)
        assert tuple(b) == np.unravel_index(msd.argmin(), msd.shape)
        assert s == pytest.approx(msd.min() * 48, rel=1e-9)


def test_tiling_scores_zero_and_identity_one(exemplar):
    image = tiled(exemplar, (5, 11), (40, 36))
    r = patch_coherence(image, exemplar, tiling_origin=(5, 11), patches=100)
    assert r["median"] == 0.0 and r["p90"] == 0.0 and r["identity"] == 1.0
    # origins are taken modulo the exemplar; another origin: still copies (coherence 0), not tiling's place
    assert patch_coherence(image, exemplar, tiling_origin=(5 + 32, 11 - 16), patches=100)["identity"] == 1.0
    other = patch_coherence(image, exemplar, tiling_origin=(6, 11), patches=100)
    assert other["median"] == 0.0 and other["p90"] == 0.0 and other["identity"] == 0.0
    assert patch_coherence(image, exemplar, tiling_origin=None, patches=10)["identity"] is None


def test_blocks_copied_from_other_positions_score_zero_and_identity_zero():
    rng = np.random.default_rng(3)
    exemplar = rng.random((32, 32, 3))
    block = 32
    offsets = {(0, 0): (3, 17), (0, 1): (20, 9), (1, 0): (30, 30), (1, 1): (11, 2)}  # none is tiling's (0, 0)
    image = np.empty((64, 64, 3))
    for (bi, bj), (dy, dx) in offsets.items():
        # the block at texel (bi, bj) * block copies the exemplar from (dy, dx) on, wrapped
        image[bi * block:(bi + 1) * block, bj * block:(bj + 1) * block] = tiled(exemplar, (dy, dx), (block, block))
    r = patch_coherence(image, exemplar, tiling_origin=(0, 0), patch=4, patches=200, seed=1, details=True)
    inside = (r["corners"] % block <= block - 4).all(1)  # patches within one block
    assert inside.mean() > 0.7
    assert (r["scores"][inside] == 0).all() and r["median"] == 0.0 and r["p90"] > 0.1  # straddling ones: not copies
    for (i, j), best in zip(r["corners"][inside], r["best"][inside]):
        dy, dx = offsets[(i // block, j // block)]
        assert tuple(best) == ((dy + i % block) % 32, (dx + j % block) % 32)
    assert r["identity"] == 0.0


def test_noise_scores_near_one():
    rng = np.random.default_rng(4)
    exemplar, image = rng.normal(size=(32, 32, 3)), rng.normal(size=(64, 64, 3))
    r = patch_coherence(image, exemplar, tiling_origin=(0, 0), seed=2)
    assert r["patch"] == 8
    # independent plausible range: an 8 x 8 x 3 patch's MSD to an unrelated Gaussian patch is 2 chi2_n / n
    # (n = 192); the best of the 1024 positions, were they independent, has the median below (overlapping
    # positions are correlated: fewer independent chances, so the real minimum is larger); the
    # normalization is the median of 2 chi2_n / n
    n, m = 192, 32 * 32
    independent = chi2.ppf(1 - 0.5 ** (1 / m), n) / chi2.median(n)
    assert independent == pytest.approx(0.707, abs=0.005)
    assert independent - 0.03 < r["median"] < 1.0 and r["median"] < r["p90"] < 1.0
    assert r["reference_msd"] == pytest.approx(2 * chi2.median(n) / n, rel=0.05)
    assert r["identity"] < 0.05


def test_deterministic_per_seed(exemplar):
    image = np.random.default_rng(6).random((30, 30, 3))
    a = patch_coherence(image, exemplar, seed=7, details=True)
    b = patch_coherence(image, exemplar, seed=7, details=True)
    c = patch_coherence(image, exemplar, seed=8, details=True)
    assert np.array_equal(a["corners"], b["corners"]) and a["median"] == b["median"] and a["p90"] == b["p90"]
    assert not np.array_equal(a["corners"], c["corners"])


@pytest.mark.parametrize("kwargs, message", [
    ({"image": np.zeros((8, 8))}, r"image: expected a non-empty image of shape \(H, W, C\), got shape \(8, 8\)"),
    ({"exemplar": np.zeros((16, 16, 3, 1))}, r"exemplar: expected a non-empty image of shape"),
    ({"image": np.full((8, 8, 3), np.nan)}, "image: expected finite values, got 192 NaN or infinite"),
    ({"exemplar": np.full((16, 16, 3), np.inf)}, "exemplar: expected finite values"),
    ({"image": np.zeros((8, 8, 4))}, "image: 4 channels, but the exemplar has 3; expected the same channels"),
    ({"image": np.zeros((3, 20, 3))}, r"image: 3x20 is smaller than a 4x4 patch; expected at least 4 texels"),
    ({"patch": 17}, "patch: 17 texels is larger than the 16x16 exemplar; expected at most 16"),
    ({"patch": 0}, "patch: expected an integer >= 1, got 0"),
    ({"patch": 2.5}, "patch: expected an integer >= 1, got 2.5"),
    ({"patches": 0}, "patches: expected an integer >= 1, got 0"),
    ({"seed": -1}, "seed: expected an integer >= 0, got -1"),
    ({"tiling_origin": (1.5, 0)}, r"tiling_origin: expected \(row0, col0\) integers or None, got \(1.5, 0\)"),
    ({"tiling_origin": 3}, r"tiling_origin: expected \(row0, col0\) integers or None, got 3"),
    ({"image": "abc"}, r"image: expected a float array of shape \(H, W, C\)"),
])
def test_bad_input_names_the_argument(exemplar, kwargs, message):
    args = {"image": np.zeros((8, 8, 3)), "exemplar": exemplar, **kwargs}
    with pytest.raises(InputError, match=message):
        patch_coherence(args.pop("image"), args.pop("exemplar"), **args)


# ---------------------------------------------------------------- from a synthesized BTF
@pytest.fixture(scope="module")
def model():
    return TriplePlane(32, 32, seed=3)


@pytest.mark.parametrize("scale", [4.0, 3.0])
def test_synthesized_images_place_the_area_at_the_origin_in_exemplar_repeats(model, scale):
    btf = synthesized_btf(model, "tile", scale=scale)
    im = synthesized_images(btf, side=40, origin=(1e6 + 0.25, 2e5 + 0.5 + 0.4 / 32))  # v rounds to row 16
    assert im["tiling_origin"] == (16, 8) and im["origin"] == [1e6 + 0.25, 2e5 + 0.5] and im["side"] == 40
    assert im["image"].shape == (40, 40, 3) and im["exemplar"].shape == (32, 32, 3)
    np.testing.assert_allclose(im["image"], tiled(im["exemplar"], (16, 8), (40, 40)), rtol=0, atol=1e-6)
    # the synthesizer sees uv * scale: texel [i, j] is the synthesized BTF at (origin + centre) / scale
    w = np.array([[0.0, 0.0, 1.0]])
    light = np.array([[np.sin(np.radians(40)) * np.cos(np.radians(30)), np.sin(np.radians(40)) * np.sin(np.radians(30)),
                       np.cos(np.radians(40))]])
    uv = np.array([[(1e6 + 0.25 + 3.5 / 32) / scale, (2e5 + 0.5 + 7.5 / 32) / scale]])
    np.testing.assert_allclose(im["image"][7, 3], btf.eval(uv, w, light)[0], rtol=0, atol=1e-6)
    assert synthesized_images(btf, origin=(0.99, 0.0))["tiling_origin"] == (0, 0)  # 31.68 texels: the next repeat
    assert synthesized_images(btf)["side"] == 128  # 4 repeats of the 32-texel exemplar


def test_synthesized_coherence_of_tile_and_hist(model):
    tile = synthesized_coherence(synthesized_btf(model, "tile", scale=4.0), patches=64)
    assert tile["p90"] < 1e-9 and tile["identity"] == 1.0
    assert tile["view"] == [0.0, 0.0] and tile["light"] == [40.0, 30.0] and tile["side"] == 128
    hist = synthesized_coherence(synthesized_btf(model, "hist", scale=4.0), patches=64)
    assert hist["identity"] < 0.2 and hist["p90"] > 0.1
    with pytest.raises(InputError, match="side: expected an integer >= 1"):
        synthesized_images(synthesized_btf(model, "tile"), side=0)
    with pytest.raises(InputError, match="light: expected two numbers"):
        synthesized_images(synthesized_btf(model, "tile"), light=(40.0,))


def test_quality_report_has_the_structure_entry(model):
    reports = [quality_report(synthesized_btf(model, method, scale=4.0), repeats=2, rgb_side=64,
                              pairs=(((0.0, 0.0), (40.0, 30.0)),)) for method in ("tile", "hist")]
    tile, hist = (r["structure"] for r in reports)
    assert set(tile) >= {"coherence_median", "coherence_p90", "identity"}
    assert tile["coherence_p90"] < 1e-9  # the decoded copies agree to float rounding
    assert tile["identity"] == 1.0 and hist["identity"] < 0.2 and hist["coherence_p90"] > 0.1
    table = format_report(reports)
    head, _, tile_row, hist_row = table.splitlines()[:4]
    assert "coh p90" in head and "identity" in head
    assert f"{hist['coherence_p90']:.3f} {hist['identity']:>8.3f}" in hist_row and " 1.000 " in tile_row
    del reports[0]["structure"]  # a report saved before the structure measures still prints
    assert "-" in format_report(reports).splitlines()[2]
