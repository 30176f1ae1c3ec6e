"""The measurement direction sets of the Bonn BTF databases, as data.

Both sets are rings of constant ``theta`` with ``phi`` evenly spaced from 0 deg;
views and lights use the same set. Directions are unit vectors in the local
frame (see :mod:`dynbtf.conventions`), listed ring by ring, ``theta`` ascending,
``phi`` ascending within a ring.

* **UBO2014** (151 directions): theta 0, 11, 23.5, 30, 37.5, 45, 52.5, 60, 67.5,
  75 deg with 1, 6, 12, 12, 12, 18, 18, 24, 24, 24 directions.
* **UBO2003** (81 directions): theta 0, 15, 30, 45, 60, 75 deg with 1, 6, 12, 18,
  20, 24 directions (every phi is an integer number of degrees, as in the
  file names of the UBO2003 zips).

Examples
--------
>>> vectors, degrees = ubo2003_directions()
>>> vectors.shape, degrees[1].tolist()
((81, 3), [15.0, 0.0])
>>> direction_set("ubo2014").shape
(151, 3)
"""

from __future__ import annotations

import numpy as np

from ..conventions import spherical_to_direction
from ..errors import InputError

__all__ = ["UBO2014_RINGS", "UBO2003_RINGS", "DIRECTION_SETS", "ring_directions",
           "ubo2014_directions", "ubo2003_directions", "direction_set", "direction_set_degrees"]

#: ``(theta in degrees, number of directions)`` per ring of the UBO2014 set.
UBO2014_RINGS: tuple[tuple[float, int], ...] = (
    (0.0, 1), (11.0, 6), (23.5, 12), (30.0, 12), (37.5, 12),
    (45.0, 18), (52.5, 18), (60.0, 24), (67.5, 24), (75.0, 24))

#: ``(theta in degrees, number of directions)`` per ring of the UBO2003 set.
UBO2003_RINGS: tuple[tuple[float, int], ...] = (
    (0.0, 1), (15.0, 6), (30.0, 12), (45.0, 18), (60.0, 20), (75.0, 24))

#: Named direction sets (lower-case name -> rings).
DIRECTION_SETS = {"ubo2014": UBO2014_RINGS, "ubo2003": UBO2003_RINGS}


def ring_directions(rings) -> tuple[np.ndarray, np.ndarray]:
    """Directions of a ring layout.

    Parameters
    ----------
    rings : sequence of ``(theta_deg, count)``
        ``count`` directions at polar angle ``theta_deg``, azimuths ``k * 360 / count``.

    Returns
    -------
    vectors : float64 ``(N, 3)``
        Unit vectors, ring by ring.
    degrees : float64 ``(N, 2)``
        The same directions as ``(theta, phi)`` in degrees.
    """
    degrees = np.array([(theta, k * 360.0 / count) for theta, count in rings for k in range(count)],
                       dtype=np.float64).reshape(-1, 2)
    vectors = spherical_to_direction(degrees[:, 0], degrees[:, 1])
    return vectors, degrees


def ubo2014_directions() -> tuple[np.ndarray, np.ndarray]:
    """The 151 UBO2014 directions: ``(vectors (151, 3), degrees (151, 2))``."""
    return ring_directions(UBO2014_RINGS)


def ubo2003_directions() -> tuple[np.ndarray, np.ndarray]:
    """The 81 UBO2003 directions: ``(vectors (81, 3), degrees (81, 2))``."""
    return ring_directions(UBO2003_RINGS)


def _rings(name: str):
    key = str(name).lower()
    if key not in DIRECTION_SETS:
        raise InputError(f"direction set: unknown name {name!r}; expected one of {sorted(DIRECTION_SETS)}")
    return DIRECTION_SETS[key]


def direction_set(name: str) -> np.ndarray:
    """Unit vectors ``(N, 3)`` of the named set (``"ubo2014"`` or ``"ubo2003"``)."""
    return ring_directions(_rings(name))[0]


def direction_set_degrees(name: str) -> np.ndarray:
    """``(theta, phi)`` in degrees, ``(N, 2)``, of the named set."""
    return ring_directions(_rings(name))[1]
