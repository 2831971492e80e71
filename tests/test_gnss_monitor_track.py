"""The GNSS monitor judges a jump against the receiver's own track, not against an estimate that may itself be wrong.

ArduPlane's take-off roll once made the companion's EKF disagree with a healthy receiver by 70 m; the monitor called
it a spoofing jump, withheld every later fix and so never let the EKF catch up: GNSS was locked out for the rest
of the flight.  Here: a smooth track that an estimate lags behind stays usable; a real jump in the track is denied
while the estimate disagrees with the new track, and never for good; the air-data velocity check waits for flying
speed.
"""

from __future__ import annotations

import math

import numpy as np

from common.samples import GnssSample
from nav.gnss_monitor import Consistency, GnssMonitor, GnssMonitorConfig, GnssState

CFG = GnssMonitorConfig()
DT_US = 200_000  # 5 Hz receiver
US = 1_000_000


def fix(t_us: int, pos_ne_m: tuple[float, float], vel_ne_m_s: tuple[float, float], hacc_m: float = 0.3
        ) -> GnssSample:
    return GnssSample(t_us, np.array([*pos_ne_m, np.nan]), np.array([*vel_ne_m_s, np.nan]), fix_ok=True, n_sats=10,
                      h_acc_m=hacc_m, fix_type=6)


def takeoff_roll(n: int, accel_m_s2: float = 3.0) -> list[GnssSample]:
    """A receiver on an accelerating take-off roll heading north (constant acceleration from rest)."""
    out = []
    for i in range(n):
        t = i * DT_US / US
        out.append(fix(i * DT_US, (0.5 * accel_m_s2 * t * t, 0.0), (accel_m_s2 * t, 0.0)))
    return out


def test_a_lagging_estimate_never_locks_out_a_consistent_track():
    """The estimate falls 70 m behind during the roll (its prediction sigma small): the receiver's track is
    consistent, so it is no jump; every fix stays usable (GNSS_OK) and reaches the EKF."""
    mon = GnssMonitor(CFG, initial=GnssState.GNSS_OK)
    states = []
    for s in takeoff_roll(75):  # 15 s
        behind = min(70.0, 0.5 * s.pos_ned_m[0])
        expect = Consistency(pred_pos_ne_m=s.pos_ned_m[:2] - np.array([behind, 0.0]), pred_pos_sigma_m=3.0,
                             air_vel_ne_m_s=np.array([0.0, 0.0]), air_vel_sigma_m_s=0.5,
                             tas_m_s=min(float(s.vel_ned_m_s[0]), 5.0))  # the pitot reads little on the roll
        mon.update(s, expect)
        states.append(mon.state)
    assert all(st == GnssState.GNSS_OK for st in states)
    assert mon.jumps == 0 and mon.counts["GNSS_DENIED"] == 0


def test_a_jump_in_the_track_is_denied_while_the_estimate_disagrees_then_recovers():
    """A spoofer moves the solution 300 m east and carries it on smoothly: the step is a jump; the following,
    self-consistent fixes stay denied while they are far from the estimate; when the solution comes back to the
    truth (another step) and stays, the receiver recovers after ``recover_after_s``."""
    mon = GnssMonitor(CFG, initial=GnssState.GNSS_OK)
    v = (20.0, 0.0)
    reasons = []
    for i in range(150):  # 30 s at 5 Hz
        t_us = i * DT_US
        truth = (20.0 * t_us / US, 0.0)
        spoofed = 50 <= i < 75  # 10-15 s
        pos = (truth[0], truth[1] + (300.0 if spoofed else 0.0))
        expect = Consistency(pred_pos_ne_m=np.array(truth), pred_pos_sigma_m=2.0 + 0.1 * max(0, i - 50),
                             air_vel_ne_m_s=np.array(v), air_vel_sigma_m_s=0.5, tas_m_s=20.0)
        ann = mon.update(fix(t_us, pos, v), expect)
        reasons += [a.reason for a in ann]
        if spoofed:
            assert mon.state == GnssState.GNSS_DENIED, (i, mon.last_reason)
        if i == 76:
            assert mon.state == GnssState.GNSS_DENIED  # back on the truth: recovery needs recover_after_s
    assert mon.jumps == 2 and "jump" in reasons[0]
    assert mon.state == GnssState.GNSS_OK
    assert mon.counts["GNSS_DENIED"] == 26  # the 25 spoofed fixes and the step back


def test_a_jump_hold_ends_after_jump_max_hold_s():
    """Never for good: a track that jumped and then stays consistent, which the estimate never agrees with, is
    judged on its own again after ``jump_max_hold_s``."""
    cfg = GnssMonitorConfig(jump_max_hold_s=20.0)
    mon = GnssMonitor(cfg, initial=GnssState.GNSS_OK)
    v = (20.0, 0.0)
    ok_since = None
    for i in range(300):  # 60 s
        t_us = i * DT_US
        truth = (20.0 * t_us / US, 0.0)
        pos = (truth[0], truth[1] + (500.0 if i >= 10 else 0.0))
        mon.update(fix(t_us, pos, v), Consistency(pred_pos_ne_m=np.array(truth), pred_pos_sigma_m=2.0))
        if mon.state == GnssState.GNSS_OK and i > 10 and ok_since is None:
            ok_since = t_us / US
    assert ok_since is not None
    assert math.isclose(ok_since, 2.0 + cfg.jump_max_hold_s + cfg.recover_after_s, abs_tol=0.5)


def test_the_track_check_needs_a_recent_fix_and_judges_with_its_velocity():
    mon = GnssMonitor(CFG, initial=GnssState.GNSS_OK)
    mon.update(fix(0, (0.0, 0.0), (25.0, 0.0)))
    # 1 s later, 25 m on at 25 m/s in a turn to the east: consistent (the mean of the two velocities)
    assert mon.grade(fix(US, (24.0, 4.0), (23.0, 8.0)))[0] == GnssState.GNSS_OK
    # 30 m off that track: a jump
    level, why = mon.grade(fix(US, (24.0, 34.0), (23.0, 8.0)))
    assert level == GnssState.GNSS_DENIED and "jump" in why
    # after a gap longer than track_max_gap_s the fix starts a new track
    far = int((CFG.track_max_gap_s + 1.0) * US)
    assert mon.grade(fix(far, (5000.0, 0.0), (25.0, 0.0)))[0] == GnssState.GNSS_OK


def test_air_data_velocity_check_waits_for_flying_speed():
    mon = GnssMonitor(CFG, initial=GnssState.GNSS_OK)
    ground = Consistency(air_vel_ne_m_s=np.array([2.0, 0.0]), air_vel_sigma_m_s=0.5, tas_m_s=2.0)
    assert mon.grade(fix(0, (0.0, 0.0), (15.0, 0.0)), ground)[0] == GnssState.GNSS_OK
    flying = Consistency(air_vel_ne_m_s=np.array([2.0, 0.0]), air_vel_sigma_m_s=0.5, tas_m_s=20.0)
    level, why = mon.grade(fix(0, (0.0, 0.0), (15.0, 0.0)), flying)
    assert level == GnssState.GNSS_DEGRADED and "velocity" in why
