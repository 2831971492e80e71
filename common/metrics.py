"""Accuracy figures of a flight, computed from logged arrays against a reference (the simulator's truth, or a
replayed log's own GNSS and autopilot estimates).

All functions take plain arrays (SI units, radians; times in seconds) and return plain floats, so that
``gsoe sim``, ``gsoe replay``, the Monte Carlo campaign and the tests compute every figure the same way.  Degrees
appear only in the names of returned figures (``*_deg``).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from common.angles import angle_diff, wrap_2pi

HEADING_BIN_DEG = 1.0


def interp_angle(t_query_s: ArrayLike, t_s: ArrayLike, angle_rad: ArrayLike) -> NDArray[np.float64]:
    """Interpolate an angle series (unwrapped first, so that it does not jump across +-pi)."""
    t_q, t = np.asarray(t_query_s, dtype=float), np.asarray(t_s, dtype=float)
    return np.asarray(wrap_2pi(np.interp(t_q, t, np.unwrap(np.asarray(angle_rad, dtype=float)))), dtype=float)


def true_drift_rad(vel_n_m_s: ArrayLike, vel_e_m_s: ArrayLike, yaw_rad: ArrayLike) -> NDArray[np.float64]:
    """Drift = course over ground - heading, wrapped to [-pi, pi)."""
    course = np.arctan2(np.asarray(vel_e_m_s, dtype=float), np.asarray(vel_n_m_s, dtype=float))
    return np.asarray(angle_diff(course, yaw_rad))


def abs_angle_errors_deg(est_rad: ArrayLike, truth_rad: ArrayLike) -> NDArray[np.float64]:
    return np.degrees(np.abs(np.asarray(angle_diff(est_rad, truth_rad))))


def summary(errors: ArrayLike, prefix: str) -> dict[str, float]:
    """Mean, median, p95 and max of absolute errors (NaN when there are none)."""
    e = np.asarray(errors, dtype=float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {f"{prefix}_mae": math.nan, f"{prefix}_median": math.nan, f"{prefix}_p95": math.nan,
                f"{prefix}_max": math.nan}
    return {f"{prefix}_mae": float(np.mean(e)), f"{prefix}_median": float(np.median(e)),
            f"{prefix}_p95": float(np.percentile(e, 95)), f"{prefix}_max": float(np.max(e))}


def heading_coverage(yaw_flown_rad: ArrayLike, yaw_at_valid_rad: ArrayLike, bin_deg: float = HEADING_BIN_DEG
                     ) -> float:
    """Fraction of the 1-deg heading bins the aircraft flew through that hold at least one valid estimate.

    Bins never flown are not counted against the estimator (the paper's fig. 10 covers the flown headings).
    """
    n_bins = int(round(360.0 / bin_deg))
    flown = np.unique((np.degrees(np.asarray(wrap_2pi(yaw_flown_rad))) // bin_deg).astype(int) % n_bins)
    if flown.size == 0:
        return math.nan
    covered = np.unique((np.degrees(np.asarray(wrap_2pi(yaw_at_valid_rad))) // bin_deg).astype(int) % n_bins)
    return float(np.isin(flown, covered).mean())


def median_per_heading_deg(yaw_rad: ArrayLike, value_rad: ArrayLike, bin_deg: float = HEADING_BIN_DEG
                           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Median value per heading bin (paper fig. 10): (bin centres in deg, medians in deg; NaN for empty bins)."""
    n_bins = int(round(360.0 / bin_deg))
    idx = (np.degrees(np.asarray(wrap_2pi(yaw_rad))) // bin_deg).astype(int) % n_bins
    vals = np.degrees(np.asarray(value_rad, dtype=float))
    med = np.full(n_bins, np.nan, dtype=float)
    order = np.argsort(idx, kind="stable")
    idx_s, vals_s = idx[order], vals[order]
    bounds = np.searchsorted(idx_s, np.arange(n_bins + 1))
    for b in range(n_bins):
        lo, hi = bounds[b], bounds[b + 1]
        if hi > lo:
            med[b] = np.median(vals_s[lo:hi])
    centres = (np.arange(n_bins, dtype=float) + 0.5) * bin_deg
    return centres, med


def wind_from_rad(wind_n_m_s: ArrayLike, wind_e_m_s: ArrayLike) -> NDArray[np.float64]:
    """Direction the wind blows FROM (clockwise from north), for a wind velocity (air moving to) N, E."""
    return np.asarray(wrap_2pi(np.arctan2(-np.asarray(wind_e_m_s, dtype=float),
                                          -np.asarray(wind_n_m_s, dtype=float))))


def rmse(errors: ArrayLike) -> float:
    e = np.asarray(errors, dtype=float)
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e**2))) if e.size else math.nan


def nees_bounds(dof: int, n_runs: int = 1, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square interval of the (run-averaged) NEES of a ``dof``-dimensional error."""
    a = (1.0 - confidence) / 2.0
    return (float(chi2.ppf(a, dof * n_runs) / n_runs), float(chi2.ppf(1.0 - a, dof * n_runs) / n_runs))


def path_length_m(pos_n_m: ArrayLike, pos_e_m: ArrayLike) -> float:
    n, e = np.asarray(pos_n_m, dtype=float), np.asarray(pos_e_m, dtype=float)
    return float(np.sum(np.hypot(np.diff(n), np.diff(e)))) if n.size > 1 else 0.0
