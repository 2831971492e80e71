"""nav.replay_checks: the log measurements behind the replay profile, against synthetic flights with known values
and on the ALFA log (``../shared/data/flightlogs``; skipped when absent)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.atmosphere import ARDUPILOT_3_BARO_TEMP_CLAMP_C, eas_to_tas_ratio, pressure_altitude_m
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample
from nav.logreader import read_log
from nav.replay import ReplayConfig
from nav.replay_checks import along_cross_heading, autopilot_position_lag_s, gnss_velocity_drift_m_s, wind_triangle_fit
from tests.conftest import shared_data

LONG = "alfa_carbonZ_2018-07-30-17-36-35_engine_failure.tlog"


def _circuit(rng: np.random.Generator, tas_scale: float, wind_ne: tuple[float, float], offset_rad: float,
             pos_drift_ne_m_s: tuple[float, float] = (0.0, 0.0)):
    """120 s of a 16 m/s airspeed circuit (heading turning 3 deg/s with straight legs), GNSS at 5 Hz, airspeed and
    attitude at 2.5 Hz; the measured airspeed ``(1 + tas_scale)`` times the air-relative speed plus 0.3 m/s noise,
    the air moving along heading + ``offset_rad``; the GNSS position drifting ``pos_drift_ne_m_s`` from the velocity's
    integral."""
    t = np.arange(0.0, 120.0, 0.01)
    rate = np.where(np.sin(2 * np.pi * t / 40.0) > 0, math.radians(9.0), 0.0)
    psi = np.cumsum(rate) * 0.01
    air = 16.0 * np.column_stack([np.cos(psi + offset_rad), np.sin(psi + offset_rad)])
    v = air + np.array(wind_ne)
    p = np.cumsum(v, axis=0) * 0.01 + np.outer(t, pos_drift_ne_m_s)
    gnss = [GnssSample(t_us=round(t[i] * 1e6), pos_ned_m=np.array([p[i, 0], p[i, 1], 0.0]),
                       vel_ned_m_s=np.array([v[i, 0], v[i, 1], math.nan]), fix_ok=True, n_sats=10)
            for i in range(0, t.size, 20)]
    k = range(0, t.size, 40)
    airs = [AirspeedSample(t_us=round(t[i] * 1e6), tas_m_s=(1 + tas_scale) * 16.0 + float(rng.normal(0, 0.3)))
            for i in k]
    att = [AttitudeSample(t_us=round(t[i] * 1e6), roll_rad=0.0, pitch_rad=0.0, yaw_rad=float(psi[i])) for i in k]
    return airs, gnss, att


def test_wind_triangle_fit_recovers_a_known_scale_wind_and_heading_offset():
    air, gnss, att = _circuit(np.random.default_rng(4), tas_scale=0.05, wind_ne=(2.0, -1.0),
                              offset_rad=math.radians(2.0))
    f = wind_triangle_fit(air, gnss, att, (0.0, 120.0))
    assert f is not None
    assert f.tas_scale == pytest.approx(0.05, abs=0.005)
    assert f.tas_scale_sigma < 0.005
    assert f.wind_ne_m_s == pytest.approx((2.0, -1.0), abs=0.1)
    assert math.degrees(f.heading_offset_rad) == pytest.approx(2.0, abs=0.3)
    assert f.residual_rms_m_s < 0.4


def test_gnss_velocity_drift_is_the_positions_departure_from_the_velocity():
    _, gnss, _ = _circuit(np.random.default_rng(5), 0.0, (1.0, 1.0), 0.0, pos_drift_ne_m_s=(0.04, -0.01))
    assert gnss_velocity_drift_m_s(gnss) == pytest.approx([0.04, -0.01], abs=0.005)


def test_along_and_across_the_heading():
    d = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 2.0]])
    along, cross = along_cross_heading(d, np.radians([0.0, 90.0, 90.0]))
    assert along == pytest.approx([1.0, 0.0, 2.0])
    assert cross == pytest.approx([0.0, -1.0, 0.0])       # positive to the right of the heading


def test_replay_gnss_delay_is_the_lag_of_the_autopilots_own_track():
    """ArduPilot fuses each fix at its stamp less the receiver's lag: its GLOBAL_POSITION_INT track, shifted by that
    lag, lies on the GPS_RAW_INT fixes.  The replay's default ``gnss_delay_s`` is within 0.05 s of it."""
    path = shared_data("flightlogs", LONG)
    flight = read_log(path)
    lag = autopilot_position_lag_s(str(path), flight, np.round(np.arange(0.0, 0.5001, 0.01), 2))
    assert lag is not None
    lag_s, rms_m = lag
    assert 0.2 <= lag_s <= 0.28 and rms_m < 0.7                # measured: 0.24 s, 0.53 m
    assert abs(ReplayConfig().gnss_delay_s - lag_s) <= 0.05
    # unshifted, the same track is metres away: the lag is resolved
    unshifted = autopilot_position_lag_s(str(path), flight, np.array([0.0]))
    assert unshifted is not None and unshifted[1] > 3 * rms_m


def test_eas_to_tas_with_a_ground_temperature_is_the_ideal_gas_density():
    p_pa, t_k = 97150.0, 298.15
    rho = p_pa / (287.053 * t_k)
    assert float(eas_to_tas_ratio(p_pa, (p_pa, t_k))) == pytest.approx(math.sqrt(1.225 / rho), rel=1e-3)
    # 500 m higher (ISA pressure altitude): the ISA lapse rate, 3.25 K colder
    p_up = 101325.0 * (1.0 - 0.0065 * (float(pressure_altitude_m(p_pa)) + 500.0) / 288.15) ** 5.25588
    rho_up = p_up / (287.053 * (t_k - 3.25))
    assert float(eas_to_tas_ratio(p_up, (p_pa, t_k))) == pytest.approx(math.sqrt(1.225 / rho_up), rel=1e-3)


def test_alfa_true_airspeed_is_the_autopilots():
    """The logged EAS becomes the TAS ArduPilot's EKF fused (AP_Baro::get_EAS2TAS: the baro temperature capped at
    25 C at the ground, the ISA lapse above it, its own gas constant 287.26), not the ISA atmosphere's 2.2 % less."""
    flight = read_log(shared_data("flightlogs", LONG), ARDUPILOT_3_BARO_TEMP_CLAMP_C)
    assert flight.report.air_temp_c == 25.0                   # the baro reads 54-56 C
    air = flight.of_type(AirspeedSample)
    baro = flight.of_type(BaroSample)
    tb = np.array([b.t_us for b in baro], dtype=float)
    pb = np.array([b.pressure_pa for b in baro])
    ta = np.array([a.t_us for a in air], dtype=float)
    p = np.interp(ta, tb, pb)
    height_m = 44330.0 * (1.0 - (p / pb.max()) ** 0.190263)   # above the lowest point (ISA, within 1 m here)
    ardupilot = np.sqrt(1.225 / (p / (287.26 * (25.0 + 273.15 - 0.0065 * height_m))))
    ours = np.array([a.tas_m_s / a.eas_m_s for a in air])
    assert np.max(np.abs(ours / ardupilot - 1.0)) < 0.002
    assert np.median(ours / eas_to_tas_ratio(p)) == pytest.approx(1.022, abs=0.003)   # vs the ISA temperature
