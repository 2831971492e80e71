"""Angle helpers: the one place where angles are wrapped and compared (see :mod:`gsoe` conventions)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

TWO_PI = 2.0 * math.pi


def wrap_pi(angle_rad: ArrayLike) -> NDArray[np.float64] | float:
    """Wrap to [-pi, pi)."""
    if isinstance(angle_rad, float | int):  # fast path for scalars in hot loops
        return (float(angle_rad) + math.pi) % TWO_PI - math.pi
    a = (np.asarray(angle_rad, dtype=float) + np.pi) % TWO_PI - np.pi
    return float(a) if a.ndim == 0 else a


def wrap_2pi(angle_rad: ArrayLike) -> NDArray[np.float64] | float:
    """Wrap to [0, 2 pi)."""
    if isinstance(angle_rad, float | int):  # fast path for scalars in hot loops (the same floating-point modulo)
        return float(angle_rad) % TWO_PI
    a = np.asarray(angle_rad, dtype=float) % TWO_PI
    return float(a) if a.ndim == 0 else a


def angle_diff(a_rad: ArrayLike, b_rad: ArrayLike) -> NDArray[np.float64] | float:
    """Signed smallest difference ``a - b`` in [-pi, pi)."""
    if isinstance(a_rad, float | int) and isinstance(b_rad, float | int):
        return (float(a_rad) - float(b_rad) + math.pi) % TWO_PI - math.pi
    return wrap_pi(np.asarray(a_rad, dtype=float) - np.asarray(b_rad, dtype=float))


def wrap_360(angle_deg: ArrayLike) -> NDArray[np.float64] | float:
    """Wrap degrees to [0, 360) (for edges that speak degrees)."""
    a = np.asarray(angle_deg, dtype=float) % 360.0
    return float(a) if a.ndim == 0 else a


def angle_diff_deg(a_deg: ArrayLike, b_deg: ArrayLike) -> NDArray[np.float64] | float:
    """Signed smallest difference ``a - b`` in degrees, in [-180, 180)."""
    d = (np.asarray(a_deg, dtype=float) - np.asarray(b_deg, dtype=float) + 180.0) % 360.0 - 180.0
    return float(d) if d.ndim == 0 else d


def circular_mean(angles_rad: ArrayLike, weights: ArrayLike | None = None) -> float:
    """Mean direction of angles (radians), in [-pi, pi)."""
    a = np.asarray(angles_rad, dtype=float)
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=float)
    return float(np.arctan2(np.sum(w * np.sin(a)), np.sum(w * np.cos(a))))
