"""The UBO2014 (151) and UBO2003 (81) direction sets."""

from __future__ import annotations

import numpy as np
import pytest

from dynbtf.conventions import direction_to_spherical
from dynbtf.data.directions import (UBO2003_RINGS, UBO2014_RINGS, direction_set, direction_set_degrees,
                                    ubo2003_directions, ubo2014_directions)
from dynbtf.errors import InputError


@pytest.mark.parametrize("make, thetas, counts", [
    (ubo2014_directions, [0, 11, 23.5, 30, 37.5, 45, 52.5, 60, 67.5, 75], [1, 6, 12, 12, 12, 18, 18, 24, 24, 24]),
    (ubo2003_directions, [0, 15, 30, 45, 60, 75], [1, 6, 12, 18, 20, 24]),
])
def test_rings(make, thetas, counts):
    vectors, degrees = make()
    assert len(vectors) == sum(counts) and vectors.shape[1] == 3 and degrees.shape == (len(vectors), 2)
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-12)
    theta, phi = direction_to_spherical(vectors)
    np.testing.assert_allclose(theta, degrees[:, 0], atol=1e-9)
    phi_expected = np.where(theta < 1e-9, 0.0, degrees[:, 1])
    np.testing.assert_allclose(np.minimum(np.abs(phi - phi_expected), 360 - np.abs(phi - phi_expected)), 0,
                               atol=1e-9)
    start = 0
    for t, c in zip(thetas, counts):
        ring = degrees[start:start + c]
        assert (ring[:, 0] == t).all()
        np.testing.assert_allclose(ring[:, 1], np.arange(c) * 360.0 / c)
        start += c
    assert theta.max() == pytest.approx(75.0) and (vectors[:, 2] > 0.25).all()


def test_named_sets_and_errors():
    assert len(direction_set("ubo2014")) == 151 and len(direction_set("UBO2003")) == 81
    np.testing.assert_array_equal(direction_set_degrees("ubo2003"), ubo2003_directions()[1])
    assert sum(c for _, c in UBO2014_RINGS) == 151 and sum(c for _, c in UBO2003_RINGS) == 81
    with pytest.raises(InputError, match="ubo2003"):
        direction_set("ubo1999")


def test_ubo2003_angles_are_integer_degrees():
    """UBO2003 file names hold integer degrees: every direction must be nameable."""
    _, degrees = ubo2003_directions()
    np.testing.assert_array_equal(degrees, np.round(degrees))
