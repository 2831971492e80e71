"""GNSS outage, jamming and spoofing detection: the ``GNSS_OK`` / ``GNSS_DEGRADED`` / ``GNSS_DENIED`` state machine.

Each GNSS report is graded on its own (the *instant* level):

* ``DENIED``: no 3-D fix, fewer than ``min_sats_denied`` satellites, horizontal accuracy worse than
  ``hacc_denied_m``, non-finite numbers, or a **position jump**: a step in the receiver's own track, the fix
  farther than ``max(track_gate_m, track_sigma * sigma)`` from the previous fix advanced by the mean of the two
  fixes' velocities (the air-data velocity where the receiver gives none; no check after a gap of
  ``track_max_gap_s``).  After a jump the fixes stay ``DENIED`` while they are farther from the EKF's prediction
  than ``max(jump_min_m, jump_sigma * sigma)`` (a spoofer that jumped the solution and now moves it smoothly), at
  most ``jump_max_hold_s``: the receiver is judged again on its own when the estimate and the new track agree
  (the EKF's position sigma grows while GNSS is withheld, so the gate widens) or that time has passed;
* ``DEGRADED``: fewer than ``min_sats_ok`` satellites, accuracy worse than ``hacc_ok_m``, or a **velocity
  disagreement**: the GNSS ground velocity differs from the air-data velocity (true airspeed along the heading
  plus the EKF's wind) by more than ``max(vel_min_m_s, vel_sigma * sigma)``, checked only while the true airspeed
  is at least ``vel_check_min_tas_m_s`` (on the ground and in the take-off roll the pitot says nothing of the
  ground speed);
* ``OK`` otherwise.

An estimate that drifted away from a receiver whose track is consistent (the EKF on the runway, ArduPlane's
take-off roll) is never a jump: only the receiver's own track can jump, so the fixes keep reaching the EKF, which
resets to them after ``gnss_reset_after_s`` of rejection.  A spoofer walking the solution off slowly is the
velocity check's to catch.

No report for ``timeout_s`` is ``DENIED`` (jamming usually just silences the receiver).

Hysteresis: the state worsens once the instant level has been worse for ``worsen_after_s`` (0: at once) and
improves only after it has been better for ``recover_after_s`` without interruption, so a flickering receiver
does not toggle the EKF's GNSS fusion.  Every transition is logged and returned as an :class:`Announcement` whose
``text`` fits a MAVLink STATUSTEXT (50 characters).
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from numpy.typing import NDArray

from common.config import In, Validated, require
from common.samples import GnssSample

log = logging.getLogger(__name__)

STATUSTEXT_MAX_CHARS = 50
GPS_FIX_TYPE_3D = 3  # MAVLink GPS_FIX_TYPE_3D_FIX; higher values (DGPS, RTK) are better 3-D fixes


class GnssState(enum.IntEnum):
    """Ordered from best to worst (the integer is also what the companion logs and sends as a named value)."""

    GNSS_OK = 0
    GNSS_DEGRADED = 1
    GNSS_DENIED = 2


@dataclass(frozen=True)
class GnssMonitorConfig(Validated):
    """``[companion.gnss]`` thresholds (units in the names)."""

    min_sats_ok: Annotated[int, In(0, 100)] = 6
    min_sats_denied: Annotated[int, In(0, 100)] = 4
    hacc_ok_m: Annotated[float, In(0.0, 1e4, lo_open=True)] = 5.0
    hacc_denied_m: Annotated[float, In(0.0, 1e5, lo_open=True)] = 20.0
    jump_min_m: Annotated[float, In(0.0, 1e5)] = 50.0
    jump_sigma: Annotated[float, In(0.0, 1e3)] = 5.0
    track_gate_m: Annotated[float, In(0.0, 1e5)] = 20.0
    track_sigma: Annotated[float, In(0.0, 1e3)] = 5.0
    track_max_gap_s: Annotated[float, In(0.0, 600.0, lo_open=True)] = 5.0
    jump_max_hold_s: Annotated[float, In(0.0, 86400.0)] = 300.0
    vel_check_min_tas_m_s: Annotated[float, In(0.0, 1e3)] = 8.0
    vel_min_m_s: Annotated[float, In(0.0, 1e3)] = 5.0
    vel_sigma: Annotated[float, In(0.0, 1e3)] = 4.0
    timeout_s: Annotated[float, In(0.01, 600.0)] = 1.5
    worsen_after_s: Annotated[float, In(0.0, 600.0)] = 0.0
    recover_after_s: Annotated[float, In(0.0, 3600.0)] = 5.0

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.min_sats_denied <= self.min_sats_ok, "min_sats_denied", "must be <= min_sats_ok")
        require(self.hacc_denied_m >= self.hacc_ok_m, "hacc_denied_m", "must be >= hacc_ok_m")


@dataclass(frozen=True, slots=True)
class Consistency:
    """What the EKF and air data expect at the report's time (any part may be ``None``: that check is skipped).

    ``pred_pos_ne_m`` with one-sigma ``pred_pos_sigma_m``; ``air_vel_ne_m_s`` (TAS along the heading + wind) with
    one-sigma ``air_vel_sigma_m_s``, from the true airspeed ``tas_m_s`` (NaN: not known, the velocity check then
    runs at any airspeed)."""

    pred_pos_ne_m: NDArray[np.float64] | None = None
    pred_pos_sigma_m: float = 0.0
    air_vel_ne_m_s: NDArray[np.float64] | None = None
    air_vel_sigma_m_s: float = 0.0
    tas_m_s: float = math.nan


@dataclass(frozen=True, slots=True)
class Announcement:
    """A state transition: ``text`` is the STATUSTEXT to send, ``reason`` the full explanation for the log."""

    t_us: int
    old: GnssState
    new: GnssState
    reason: str
    text: str


def _finite(a: NDArray[np.float64] | None, n: int = 2) -> bool:
    return a is not None and np.shape(a) == (n,) and bool(np.all(np.isfinite(a)))


def _ne(v: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The north/east part of a NED vector, None unless both are finite."""
    ne = np.asarray(v, dtype=float)[:2]
    return ne if ne.shape == (2,) and bool(np.all(np.isfinite(ne))) else None


class GnssMonitor:
    """The state machine.  Feed every report with :meth:`update` and call :meth:`tick` regularly (timeouts)."""

    def __init__(self, config: GnssMonitorConfig, initial: GnssState = GnssState.GNSS_DENIED) -> None:
        self.config = config
        self.state = initial
        self.reason = "no GNSS report yet"
        self.last_level = initial
        self.last_reason = self.reason
        self._last_report_t_us: int | None = None
        self._cand: GnssState | None = None
        self._cand_since_us = 0
        self.counts = {s.name: 0 for s in GnssState}
        self._track: tuple[int, NDArray[np.float64], NDArray[np.float64] | None, float] | None = None
        self._jump_since_us: int | None = None
        self.jumps = 0

    def _held(self, s: GnssSample, pos: NDArray[np.float64], expect: Consistency | None) -> float | None:
        """The fix's distance from the estimate while a jump holds it off (module docstring), else None."""
        c = self.config
        if (self._jump_since_us is None or (s.t_us - self._jump_since_us) / 1e6 >= c.jump_max_hold_s
                or expect is None or not _finite(expect.pred_pos_ne_m) or not math.isfinite(expect.pred_pos_sigma_m)):
            return None
        off = float(np.hypot(*(pos - expect.pred_pos_ne_m)))  # type: ignore[operator]
        return off if off > max(c.jump_min_m, c.jump_sigma * expect.pred_pos_sigma_m) else None

    def _track_step_m(self, s: GnssSample, pos: NDArray[np.float64], vel: NDArray[np.float64] | None,
                      expect: Consistency | None) -> tuple[float, float] | None:
        """(distance of the fix from the previous fix advanced by the mean velocity, its gate), or None when the
        track cannot tell (no previous fix, a gap, no velocity)."""
        c = self.config
        if self._track is None:
            return None
        t0, p0, v0, hacc0 = self._track
        dt = (s.t_us - t0) / 1e6
        if not 0.0 < dt <= c.track_max_gap_s:
            return None
        air = expect.air_vel_ne_m_s if expect is not None and _finite(expect.air_vel_ne_m_s) else None
        vels = [v for v in (v0, vel) if v is not None] or ([air] if air is not None else [])
        if not vels:
            return None
        pred = p0 + np.mean(vels, axis=0) * dt
        sig = math.hypot(*(h if math.isfinite(h) else 0.0 for h in (hacc0, s.h_acc_m)))
        return float(np.hypot(*(pos - pred))), max(c.track_gate_m, c.track_sigma * sig)

    def grade(self, s: GnssSample, expect: Consistency | None = None) -> tuple[GnssState, str]:
        """The instant level of one fix and why (no state change).  A component the receiver did not report is
        NaN in the sample and not checked; the fix type is ``fix_type`` or, where the source gives none, 3-D
        for ``fix_ok``."""
        c = self.config
        fix_type = s.fix_type if s.fix_type >= 0 else (GPS_FIX_TYPE_3D if s.fix_ok else 0)
        if fix_type < GPS_FIX_TYPE_3D:
            return GnssState.GNSS_DENIED, f"no 3D fix (fix type {fix_type})"
        if s.n_sats < c.min_sats_denied:
            return GnssState.GNSS_DENIED, f"{s.n_sats} satellites < {c.min_sats_denied}"
        if math.isfinite(s.h_acc_m) and s.h_acc_m > c.hacc_denied_m:
            return GnssState.GNSS_DENIED, f"accuracy {s.h_acc_m:.1f} m > {c.hacc_denied_m} m"
        pos, vel = _ne(s.pos_ned_m), _ne(s.vel_ned_m_s)
        if pos is None:
            return GnssState.GNSS_DENIED, "non-finite position"
        step = self._track_step_m(s, pos, vel, expect)
        if step is not None and step[0] > step[1]:
            return GnssState.GNSS_DENIED, f"position jump {step[0]:.0f} m > {step[1]:.0f} m in the track (spoofing?)"
        held = self._held(s, pos, expect)
        if held is not None:
            return GnssState.GNSS_DENIED, f"{held:.0f} m from the estimate since a position jump"
        level, why = GnssState.GNSS_OK, "3D fix"
        if s.n_sats < c.min_sats_ok:
            level, why = GnssState.GNSS_DEGRADED, f"{s.n_sats} satellites < {c.min_sats_ok}"
        elif math.isfinite(s.h_acc_m) and s.h_acc_m > c.hacc_ok_m:
            level, why = GnssState.GNSS_DEGRADED, f"accuracy {s.h_acc_m:.1f} m > {c.hacc_ok_m} m"
        if (expect is not None and vel is not None and _finite(expect.air_vel_ne_m_s)
                and math.isfinite(expect.air_vel_sigma_m_s)
                and not expect.tas_m_s < c.vel_check_min_tas_m_s):  # NaN: unknown airspeed, checked
            dv = float(np.hypot(*(vel - expect.air_vel_ne_m_s)))  # type: ignore[operator]
            gate = max(c.vel_min_m_s, c.vel_sigma * expect.air_vel_sigma_m_s)
            if dv > gate:
                level, why = GnssState.GNSS_DEGRADED, f"velocity disagrees with air data by {dv:.1f} m/s"
        return level, why

    def update(self, report: GnssSample, expect: Consistency | None = None) -> list[Announcement]:
        """Grade a fix and advance the state machine; returns the transitions (0 or 1)."""
        if self._last_report_t_us is not None and report.t_us < self._last_report_t_us:
            log.warning("GNSS report time went backwards (%d < %d us): ignored", report.t_us, self._last_report_t_us)
            return []
        self._last_report_t_us = report.t_us
        level, why = self.grade(report, expect)
        self.last_level, self.last_reason = level, why
        self.counts[level.name] += 1
        self._follow_track(report, why, expect)
        return self._advance(report.t_us, level, why)

    def _follow_track(self, s: GnssSample, why: str, expect: Consistency | None) -> None:
        """The track the next fix is judged against, and the jump hold (module docstring)."""
        pos, vel = _ne(s.pos_ned_m), _ne(s.vel_ned_m_s)
        if pos is None or not s.fix_ok:
            return
        if why.startswith("position jump"):
            self.jumps += 1
            self._jump_since_us = s.t_us
        elif self._jump_since_us is not None and self._held(s, pos, expect) is None:
            self._jump_since_us = None  # the estimate and the track agree again (or the hold is over)
        self._track = (s.t_us, pos, vel, s.h_acc_m)

    def tick(self, t_us: int) -> list[Announcement]:
        """Check the report timeout at ``t_us`` (call at the companion's loop rate)."""
        timeout_us = self.config.timeout_s * 1e6
        if self._last_report_t_us is None:
            if self.state != GnssState.GNSS_DENIED:
                return self._advance(t_us, GnssState.GNSS_DENIED, "no GNSS report")
            return []
        if t_us - self._last_report_t_us > timeout_us:
            silent = (t_us - self._last_report_t_us) / 1e6
            return self._advance(t_us, GnssState.GNSS_DENIED, f"no GNSS report for {silent:.1f} s")
        return []

    def _advance(self, t_us: int, level: GnssState, why: str) -> list[Announcement]:
        if level == self.state:
            self._cand = None
            return []
        better = level < self.state
        if self._cand is None or (self._cand < self.state) != better:
            self._cand, self._cand_since_us = level, t_us  # direction changed: restart the clock
        else:
            # while improving, go only as far as the worst level seen in the window; while worsening, at least
            # to the mildest worse level seen (both keep the window's start)
            self._cand = max(self._cand, level) if better else min(self._cand, level)
        wait_s = self.config.recover_after_s if better else self.config.worsen_after_s
        if (t_us - self._cand_since_us) / 1e6 < wait_s:
            return []
        old, new = self.state, self._cand
        self.state, self.reason, self._cand = new, why, None
        text = f"GSOE {new.name}: {why}"[:STATUSTEXT_MAX_CHARS]
        log.warning("GNSS state %s -> %s: %s", old.name, new.name, why)
        return [Announcement(t_us, old, new, why, text)]
