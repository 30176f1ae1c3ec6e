"""Parsing and validation of command-line values shared by several commands.

Each function takes the option's text or value and the option's name (without
``--``) and raises :class:`dynbtf.errors.InputError` naming ``--name`` and the
expected value, so every command rejects the same mistakes with the same words.
"""

from __future__ import annotations

import math

from ..errors import InputError

__all__ = ["parse_theta_phi", "check_exposure"]

#: The ``expected`` wording of :func:`parse_theta_phi`.
THETA_PHI = "THETA,PHI in degrees (e.g. 30,90)"


def parse_theta_phi(text: str, what: str, expected: str = THETA_PHI) -> tuple[float, float]:
    """``"THETA,PHI"`` (degrees) -> ``(theta, phi)`` of a direction in the upper hemisphere.

    ``theta`` must lie in ``0..90`` degrees (a direction below the horizon sees or
    lights nothing); both must be finite. ``expected`` words the error for text that
    is not two numbers (e.g. a command that also accepts an index says so).

    >>> parse_theta_phi("30, 90", "view")
    (30.0, 90.0)
    """
    parts = [p.strip() for p in str(text).split(",")]
    try:
        numbers = [float(p) for p in parts]
    except ValueError:
        numbers = []
    if len(numbers) != 2 or not all(math.isfinite(x) for x in numbers):
        raise InputError(f"--{what}: expected {expected}, got {text!r}")
    theta, phi = numbers
    if not 0.0 <= theta <= 90.0:
        raise InputError(f"--{what}: theta must be 0..90 degrees, got {parts[0]}")
    return theta, phi


def check_exposure(exposure: float, what: str = "exposure") -> float:
    """An exposure multiplier: a positive, finite number (0 or less would write a black image)."""
    if not (math.isfinite(exposure) and exposure > 0):
        raise InputError(f"--{what}: expected a positive number, got {exposure}")
    return float(exposure)
