"""BTFSource.read_texels: texels of images without decoding whole images, for every source kind.

Each native implementation (DFMF factors, stored memory map, simulator) and the default
whole-image fallback is checked against ``image(v, l)[texels]``; the DFMF one also
against the independent brute-force decoder of ``dfmf_reference``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dfmf_reference import dfmf_bytes, reference_decode
from dynbtf.data import ArrayBTF, UBO2014BTF, open_btf, write_ubo2014
from dynbtf.data.stored import StoredBTF, write_stored
from dynbtf.errors import InputError
from dynbtf.training import ImageStore

VIEWS = np.array([[0, 0, 1.0], [0.6, 0, 0.8], [0, 0.6, 0.8]])


def by_images(btf, pairs, texels):
    """The definition: whole images, then the texels."""
    return np.stack([np.stack([btf.image(*p).reshape(-1, 3)[t] for p in group]) for group, t in zip(pairs, texels)])


# a block, a block wrapping round the image's end, and scattered texels (shape (G, N) with G = 3)
PAIRS = np.array([[[0, 1], [2, 2]], [[1, 0], [0, 1]], [[2, 1], [2, 0]]])
TEXELS = np.array([[3, 4, 5, 6], [33, 34, 0, 1], [17, 2, 30, 9]])


@pytest.fixture(scope="module")
def array_btf():
    rng = np.random.default_rng(3)
    return ArrayBTF(rng.random((3, 3, 5, 7, 3)).astype(np.float32), VIEWS, VIEWS)


@pytest.mark.parametrize("colour_model", [0, 11])
@pytest.mark.parametrize("scalar", ["half", "float", "double"])
@pytest.mark.parametrize("factor_cache_bytes", [1 << 30, 0])
def test_dfmf_texels_from_factors(tmp_path, array_btf, colour_model, scalar, factor_cache_bytes):
    path = write_ubo2014(tmp_path / "a.btf", array_btf, components=4, scalar=scalar, colour_model=colour_model)
    with UBO2014BTF(path, factor_cache_bytes=factor_cache_bytes) as btf:
        out = btf.read_texels(PAIRS, TEXELS)
        assert out.shape == (3, 2, 4, 3) and out.dtype == np.float32
        np.testing.assert_allclose(out, by_images(btf, PAIRS, TEXELS), atol=2e-7)
        single = btf.read_texels(PAIRS[2], TEXELS[2])  # no group axis
        np.testing.assert_array_equal(single, out[2])
        on_device = btf.read_texels(PAIRS, TEXELS, device="cpu")
        assert isinstance(on_device, torch.Tensor) and torch.equal(on_device, torch.from_numpy(out))


def test_dfmf_texels_match_brute_force_decoder_with_cosine_flag(tmp_path):
    """Factors written byte by byte (cosine flag set, float scalars): read_texels == the reference decoder."""
    rng = np.random.default_rng(5)
    w, h, c = 4, 3, 2
    angles = [(0.0, 0.0), (np.radians(40), np.radians(120))]
    u = [rng.normal(size=(4, c)) for _ in range(3)]
    sxv = [rng.normal(size=(w * h, c)) for _ in range(3)]
    path = tmp_path / "cos.btf"
    path.write_bytes(dfmf_bytes(angles, angles, w, h, u, sxv, scalar_size=4, version=2, cosine_flag=1))
    with UBO2014BTF(path) as btf:
        texels = np.array([[11, 0, 5], [6, 7, 8]])
        pairs = np.array([[[1, 1], [0, 1]], [[1, 0], [0, 0]]])
        out = btf.read_texels(pairs, texels)
        for g in range(2):
            for b, (v, l) in enumerate(pairs[g]):
                ref = np.asarray(reference_decode(path, v, l)[0])  # divided by cos(theta_light) there
                np.testing.assert_allclose(out[g, b], ref.reshape(-1, 3)[texels[g]], rtol=1e-5, atol=1e-6)


def test_stored_and_simulated_answer_natively(tmp_path):
    sim = open_btf("sim:leather?size=8")
    write_stored(tmp_path / "s.dbtf", sim, dtype="float32", progress=False)
    pairs = np.array([[[0, 1], [5, 7], [5, 3]], [[80, 80], [0, 1], [40, 2]]])
    texels = np.array([[3, 4, 5, 6, 7], [63, 62, 0, 1, 40]])
    with StoredBTF(tmp_path / "s.dbtf") as stored:
        for btf in (sim, stored):
            np.testing.assert_array_equal(btf.read_texels(pairs, texels), by_images(btf, pairs, texels))


def test_default_fallback_decodes_each_image_once(array_btf, monkeypatch):
    decoded = []
    original = ArrayBTF._read_image
    monkeypatch.setattr(ArrayBTF, "_read_image", lambda self, v, l: decoded.append((v, l)) or original(self, v, l))
    pairs = np.array([[[0, 1], [2, 2]], [[2, 2], [0, 1]]])
    out = array_btf.read_texels(pairs, TEXELS[:2])
    assert sorted(decoded) == [(0, 1), (2, 2)]
    np.testing.assert_array_equal(out, by_images(array_btf, pairs, TEXELS[:2]))


@pytest.mark.parametrize("pairs, texels, message", [
    (np.zeros((2, 3), int), np.zeros(2, int), "pairs must be"),
    (np.zeros((2, 2), int), np.zeros((2, 2), int), r"texels must be \(N,\)"),
    (np.zeros((1, 2, 2), int), np.zeros(3, int), r"texels must be \(1, N\)"),
    (np.zeros((2, 2), int), np.array([0, 35]), r"texel indices must lie in \[0, 35\)"),
    (np.array([[3, 0]]), np.array([0]), r"view indices must lie in \[0, 3\)"),
    (np.array([[0, -1]]), np.array([0]), r"light indices must lie in \[0, 3\)"),
    (np.zeros((1, 2), int), np.array([0.5]), "texels must hold integers"),
])
def test_bad_requests_are_named(array_btf, pairs, texels, message):
    with pytest.raises(InputError, match=message):
        array_btf.read_texels(pairs, texels)


def test_uncached_store_serves_the_same_batches_as_the_cache(tmp_path, array_btf):
    path = write_ubo2014(tmp_path / "a.btf", array_btf, components=6, scalar="float")
    with UBO2014BTF(path) as btf:
        cached, streamed = ImageStore(btf), ImageStore(btf, memory_budget=0)
        assert cached.cached and not streamed.cached
        pairs = np.array([[[0, 1], [2, 2]], [[1, 0], [0, 1]]])
        starts = np.array([30, 2])
        blocks = streamed.get_blocks(pairs, starts, 8, device="cpu")
        assert isinstance(blocks, torch.Tensor) and blocks.shape == (2, 16, 3)
        # the cache holds float16: equal to its precision
        np.testing.assert_allclose(blocks.numpy(), cached.get_blocks(pairs, starts, 8), rtol=1e-3, atol=1e-4)
        texels = np.array([1, 5, 20])
        np.testing.assert_allclose(streamed.get(pairs[0], texels), cached.get(pairs[0], texels), rtol=1e-3,
                                   atol=1e-4)
        np.testing.assert_allclose(streamed.get(pairs[0], texels), by_images(btf, pairs[:1], texels[None])[0],
                                   atol=2e-7)
