"""BoxFilteredBTF: the block average of every image, against loops written here."""

import numpy as np
import pytest

from dynbtf.data.filtered import BoxFilteredBTF
from dynbtf.errors import InputError
from synthetic_btf import synthetic_btf


def test_block_averages_match_loops_and_read_texels():
    btf = synthetic_btf(size=8)
    coarse = BoxFilteredBTF(btf, 4)
    assert coarse.shape == (btf.n_views, btf.n_lights, 2, 2)
    image = btf.image(3, 5).astype(np.float64)
    want = np.zeros((2, 2, 3))
    for i in range(2):
        for j in range(2):
            for r in range(4):
                for c in range(4):
                    want[i, j] += image[4 * i + r, 4 * j + c] / 16.0
    np.testing.assert_allclose(coarse.image(3, 5), want, rtol=1e-6)
    texels = coarse.read_texels(np.array([[3, 5], [0, 0]]), np.array([3, 1]))
    np.testing.assert_allclose(texels[0], coarse.image(3, 5).reshape(-1, 3)[[3, 1]], rtol=1e-6)
    np.testing.assert_array_equal(BoxFilteredBTF(btf, 1).image(2, 2), btf.image(2, 2))
    assert np.allclose(BoxFilteredBTF(btf, 8).image(1, 1)[0, 0], btf.image(1, 1).mean((0, 1)), rtol=1e-6)


@pytest.mark.parametrize("factor, message", [(3, "does not divide"), (0, "positive integer"), (2.0, "positive integer")])
def test_bad_factors_are_named(factor, message):
    with pytest.raises(InputError, match=message):
        BoxFilteredBTF(synthetic_btf(size=8), factor)
