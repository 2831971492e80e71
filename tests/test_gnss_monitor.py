"""GNSS monitor state machine on scripted receiver reports."""

from __future__ import annotations

import numpy as np
import pytest

from common.config import ConfigError, build
from common.samples import GnssSample
from nav.gnss_monitor import (
    STATUSTEXT_MAX_CHARS,
    Consistency,
    GnssMonitor,
    GnssMonitorConfig,
    GnssState,
)

CFG = GnssMonitorConfig()
DT_US = 200_000  # 5 Hz receiver


def good(t_us: int, fix_type: int = 3, satellites: int = 12, hacc_m: float = 1.5,
         pos_ne_m: tuple[float, float] = (100.0, 50.0), vel_ne_m_s: tuple[float, float] = (20.0, 0.0)) -> GnssSample:
    """A receiver's fix as the link gives it (down components unknown)."""
    return GnssSample(t_us, np.array([*pos_ne_m, np.nan]), np.array([*vel_ne_m_s, np.nan]), fix_ok=fix_type >= 3,
                      n_sats=satellites, h_acc_m=hacc_m, fix_type=fix_type)


def run(mon: GnssMonitor, reports, expect=None):
    out = []
    for r in reports:
        out += mon.update(r, expect)
    return out


def test_recovery_needs_recover_after_s_of_good_reports():
    mon = GnssMonitor(CFG)
    assert mon.state == GnssState.GNSS_DENIED
    n_needed = int(CFG.recover_after_s * 1e6 / DT_US)
    assert run(mon, [good(i * DT_US) for i in range(n_needed)]) == []
    ann = mon.update(good(n_needed * DT_US))
    assert mon.state == GnssState.GNSS_OK
    assert len(ann) == 1 and ann[0].old == GnssState.GNSS_DENIED and ann[0].new == GnssState.GNSS_OK
    assert ann[0].text.startswith("GSOE GNSS_OK") and len(ann[0].text) <= STATUSTEXT_MAX_CHARS


def ok_monitor() -> GnssMonitor:
    return GnssMonitor(CFG, initial=GnssState.GNSS_OK)


@pytest.mark.parametrize(("kw", "state", "word"), [
    ({"fix_type": 2}, GnssState.GNSS_DENIED, "fix"),
    ({"satellites": 3}, GnssState.GNSS_DENIED, "satellites"),
    ({"hacc_m": 50.0}, GnssState.GNSS_DENIED, "accuracy"),
    ({"pos_ne_m": np.array([np.nan, 0.0])}, GnssState.GNSS_DENIED, "non-finite"),
    ({"satellites": 5}, GnssState.GNSS_DEGRADED, "satellites"),
    ({"hacc_m": 8.0}, GnssState.GNSS_DEGRADED, "accuracy"),
])
def test_bad_reports_worsen_at_once_with_reason(kw, state, word):
    mon = ok_monitor()
    ann = mon.update(good(0, **kw))
    assert mon.state == state and len(ann) == 1 and word in ann[0].reason


def test_flicker_does_not_recover_and_recovers_to_worst_level_of_window():
    mon = GnssMonitor(CFG)
    reports = [good(i * DT_US, fix_type=3 if (i // 5) % 2 == 0 else 1) for i in range(100)]  # 1 s on, 1 s off
    assert run(mon, reports) == []
    assert mon.state == GnssState.GNSS_DENIED
    # 6 s alternating OK / DEGRADED reports: recovers, but only to DEGRADED
    t0 = 100 * DT_US
    alt = [good(t0 + i * DT_US, satellites=12 if i % 2 else 5) for i in range(31)]
    ann = run(mon, alt)
    assert mon.state == GnssState.GNSS_DEGRADED and [a.new for a in ann] == [GnssState.GNSS_DEGRADED]


def test_timeout_denies_and_time_going_backwards_is_ignored():
    mon = ok_monitor()
    mon.update(good(0))
    assert mon.tick(int(CFG.timeout_s * 1e6) - 1) == []
    ann = mon.tick(int(CFG.timeout_s * 1e6) + DT_US)
    assert mon.state == GnssState.GNSS_DENIED and "no GNSS report" in ann[0].reason
    assert mon.update(good(-DT_US)) == []


def test_position_jump_against_ekf_prediction_is_spoofing():
    mon = ok_monitor()
    expect = Consistency(pred_pos_ne_m=np.array([100.0, 50.0]), pred_pos_sigma_m=4.0)
    assert mon.update(good(0, pos_ne_m=np.array([130.0, 50.0])), expect) == []  # 30 m < 50 m gate
    ann = mon.update(good(DT_US, pos_ne_m=np.array([100.0, 350.0])), expect)
    assert mon.state == GnssState.GNSS_DENIED and "jump" in ann[0].reason
    # a large prediction sigma widens the gate
    wide = Consistency(pred_pos_ne_m=np.array([100.0, 50.0]), pred_pos_sigma_m=100.0)
    assert mon.grade(good(0, pos_ne_m=np.array([100.0, 350.0])), wide)[0] == GnssState.GNSS_OK


def test_velocity_disagreement_with_air_data_degrades():
    mon = ok_monitor()
    air = Consistency(air_vel_ne_m_s=np.array([20.0, 1.0]), air_vel_sigma_m_s=0.5)
    assert mon.update(good(0), air) == []
    ann = mon.update(good(DT_US, vel_ne_m_s=np.array([20.0, -12.0])), air)
    assert mon.state == GnssState.GNSS_DEGRADED and "velocity" in ann[0].reason


def test_worsen_after_s_delays_degradation():
    mon = GnssMonitor(GnssMonitorConfig(worsen_after_s=1.0), initial=GnssState.GNSS_OK)
    assert run(mon, [good(i * DT_US, fix_type=0) for i in range(5)]) == []
    assert mon.update(good(5 * DT_US, fix_type=0))[0].new == GnssState.GNSS_DENIED


def test_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="companion.gnss.min_sats_denied"):
        build(GnssMonitorConfig, {"min_sats_ok": 4, "min_sats_denied": 6}, "companion.gnss")
    with pytest.raises(ConfigError, match="hacc_ok_m"):
        build(GnssMonitorConfig, {"hacc_ok_m": -1.0}, "companion.gnss")
