"""Metric helpers against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from common.metrics import (
    heading_coverage,
    interp_angle,
    median_per_heading_deg,
    nees_bounds,
    true_drift_rad,
    wind_from_rad,
)


def test_true_drift_and_wind_direction():
    # heading north, moving north-east at 45 deg: drift +45 deg (track right of heading)
    assert np.degrees(true_drift_rad(1.0, 1.0, 0.0)) == pytest.approx(45.0)
    # heading 350, course 10: drift +20 across north
    c = np.radians(10.0)
    assert np.degrees(true_drift_rad(np.cos(c), np.sin(c), np.radians(350.0))) == pytest.approx(20.0)
    # air moving to the south-west comes from the north-east: 45 deg
    assert np.degrees(wind_from_rad(-1.0, -1.0)) == pytest.approx(45.0)
    assert np.degrees(wind_from_rad(1.0, 0.0)) == pytest.approx(180.0)


def test_heading_coverage_counts_flown_bins_only():
    flown = np.radians(np.arange(0.0, 90.0, 0.25))
    assert heading_coverage(flown, np.radians(np.arange(0.5, 45.0, 1.0))) == pytest.approx(0.5)
    assert heading_coverage(flown, flown) == 1.0


def test_interp_angle_across_north_and_median_per_heading():
    t = np.array([0.0, 1.0])
    a = np.radians([350.0, 10.0])
    assert np.degrees(interp_angle([0.5], t, a))[0] == pytest.approx(0.0, abs=1e-9)
    centres, med = median_per_heading_deg(np.radians([10.2, 10.7, 10.9, 200.0]), np.radians([1.0, 2.0, 9.0, 4.0]))
    assert med[10] == pytest.approx(2.0) and med[200] == pytest.approx(4.0) and np.isnan(med[0])
    assert centres[10] == pytest.approx(10.5)


def test_nees_bounds_match_chi2_table():
    lo, hi = nees_bounds(2)
    assert lo == pytest.approx(0.0506, abs=1e-3) and hi == pytest.approx(7.378, abs=1e-3)
