"""Filter consistency statistics: NEES and chi-square intervals (for tests, ``gsoe sim`` and Monte Carlo reports)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.stats import chi2


def nees(error: ArrayLike, cov: ArrayLike) -> float:
    """Normalised estimation error squared ``e' P^-1 e`` (``solve``, no inverse); NaN if ``cov`` is singular."""
    e = np.asarray(error, dtype=float).reshape(-1)
    P = np.asarray(cov, dtype=float)
    if P.shape != (e.size, e.size):
        raise ValueError(f"cov: shape {P.shape} does not match an error of size {e.size}")
    try:
        return float(e @ np.linalg.solve(P, e))
    except np.linalg.LinAlgError:
        return float("nan")


def chi2_interval(dof: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval of a chi-square variable with ``dof`` degrees of freedom."""
    a = (1.0 - prob) / 2.0
    return float(chi2.ppf(a, dof)), float(chi2.ppf(1.0 - a, dof))


def fraction_in_interval(values: ArrayLike, dof: int, prob: float = 0.95) -> float:
    """Fraction of NEES ``values`` inside :func:`chi2_interval` (NaN values count as outside)."""
    v = np.asarray(values, dtype=float)
    lo, hi = chi2_interval(dof, prob)
    return float(np.mean((v >= lo) & (v <= hi))) if v.size else float("nan")
