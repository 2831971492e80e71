"""What a ground station shows of the companion: the wind with its sigma, drift, ATA, GSOE quality, GNSS state.

Without any plugin a ground station already gets (the autopilot routes the companion's messages to it):

=====================================  ==========================================================================
message                                shown by
=====================================  ==========================================================================
WIND (ArduPilot dialect)               Mission Planner's HUD wind arrow and speed; MAVProxy's ``wind`` status
WIND_COV                               QGroundControl's and MAVSDK's wind telemetry (velocity, 1-sigma accuracy)
NAMED_VALUE_FLOAT ``GSOE_DRIFT``,      Mission Planner's "Quick" tab and graphs, QGroundControl's MAVLink
``GSOE_ATA`` (degrees), ``GSOE_Q``     inspector, MAVProxy's ``graph`` (any named value)
(0..1), ``GSOE_GNSS`` (0 OK, 1
DEGRADED, 2 DENIED), ``GSOE_VALID``
STATUSTEXT ``GSOE ...``                every ground station's message list: GNSS state changes, estimate
                                       invalid (with the reason) and valid again
=====================================  ==========================================================================

:class:`GsoeGroundState` turns those messages into one display state (pure: no MAVProxy, no I/O) with the
warnings a ground station should raise: the estimate going invalid (``GSOE_VALID`` 1 -> 0 or the companion's
STATUSTEXT), GNSS state changes, and the companion going silent (no ``GSOE_VALID`` for ``stale_s``).
:mod:`nav.gcs_mavproxy` shows it in MAVProxy.

Only messages from the companion's component (``source_component``, MAV_COMP_ID_ONBOARD_COMPUTER = 191 by default;
0 accepts any) are used, so the autopilot's own WIND (ArduPilot sends its EKF's wind too) does not overwrite
ours.  Units: speeds m/s, angles degrees (a display edge); the wind direction is where it blows *from*.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from common.angles import wrap_360

MAV_COMP_ID_ONBOARD_COMPUTER = 191
GNSS_STATE_NAMES = {0: "GNSS_OK", 1: "GNSS_DEGRADED", 2: "GNSS_DENIED"}
STATUSTEXT_PREFIX = "GSOE"


@dataclass
class GsoeGroundState:
    """The companion's outputs as a ground station sees them (NaN / empty until received).

    ``wind_speed_m_s``, ``wind_from_deg`` (WIND); ``wind_n_m_s``, ``wind_e_m_s`` (WIND_COV, the air's velocity),
    ``wind_speed_sigma_m_s`` (WIND_COV ``horiz_accuracy``), ``wind_from_sigma_deg`` (the RMS axis sigma
    ``var_horiz`` across the wind over its speed); ``drift_deg``, ``ata_deg``, ``quality`` (0..1), ``gnss_state``
    (name), ``valid`` (None: not known yet); ``last_statustext``; ``t_*_s``: when each part was last received
    (the caller's clock, seconds); ``counts`` per message kind; ``warnings`` every warning raised so far.
    """

    source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER
    stale_s: float = 3.0
    wind_speed_m_s: float = math.nan
    wind_from_deg: float = math.nan
    wind_n_m_s: float = math.nan
    wind_e_m_s: float = math.nan
    wind_speed_sigma_m_s: float = math.nan
    wind_from_sigma_deg: float = math.nan
    drift_deg: float = math.nan
    ata_deg: float = math.nan
    quality: float = math.nan
    gnss_state: str = ""
    valid: bool | None = None
    last_statustext: str = ""
    t_wind_s: float = math.nan
    t_drift_s: float = math.nan
    t_status_s: float = math.nan
    stale: bool = False
    counts: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def _from_companion(self, msg: Any) -> bool:
        if self.source_component == 0:
            return True
        try:
            return int(msg.get_srcComponent()) == self.source_component
        except (AttributeError, TypeError, ValueError):
            return False

    def update(self, msg: Any, now_s: float) -> list[str]:
        """Take one pymavlink message; returns the warnings/announcements it causes (for the operator)."""
        kind = msg.get_type()
        if kind not in ("WIND", "WIND_COV", "NAMED_VALUE_FLOAT", "STATUSTEXT") or not self._from_companion(msg):
            return []
        self.counts[kind] = self.counts.get(kind, 0) + 1
        out: list[str] = []
        if kind == "WIND":
            speed, direction = float(msg.speed), float(msg.direction)
            if math.isfinite(speed) and math.isfinite(direction):
                self.wind_speed_m_s, self.wind_from_deg = speed, float(wrap_360(direction))
                self.t_wind_s = now_s
        elif kind == "WIND_COV":
            wn, we, acc, rms = float(msg.wind_x), float(msg.wind_y), float(msg.horiz_accuracy), float(msg.var_horiz)
            if all(math.isfinite(v) for v in (wn, we, acc, rms)):
                self.wind_n_m_s, self.wind_e_m_s, self.wind_speed_sigma_m_s = wn, we, acc
                speed = math.hypot(wn, we)
                self.wind_from_sigma_deg = math.degrees(min(math.pi, rms / speed)) if speed > 0 else 180.0
        elif kind == "NAMED_VALUE_FLOAT":
            out += self._named(str(msg.name), float(msg.value), now_s)
        elif kind == "STATUSTEXT":
            text = str(msg.text)
            if text.startswith(STATUSTEXT_PREFIX):
                self.last_statustext = text
                out.append(text)
        self.warnings += out
        return out

    def _named(self, name: str, value: float, now_s: float) -> list[str]:
        if not math.isfinite(value):
            return []
        out: list[str] = []
        if name == "GSOE_DRIFT":
            self.drift_deg, self.t_drift_s = value, now_s
        elif name == "GSOE_ATA":
            self.ata_deg = value
        elif name == "GSOE_Q":
            self.quality = value
        elif name == "GSOE_GNSS":
            new = GNSS_STATE_NAMES.get(int(round(value)), f"unknown {value:g}")
            if self.gnss_state and new != self.gnss_state:
                out.append(f"GSOE GNSS state {self.gnss_state} -> {new}")
            self.gnss_state = new
        elif name == "GSOE_VALID":
            valid = value >= 0.5
            if self.valid is True and not valid:
                out.append("GSOE estimate INVALID: wind and drift no longer sent")
            elif self.valid is False and valid:
                out.append("GSOE estimate valid again")
            self.valid = valid
            self.t_status_s = now_s
            self.stale = False
        return out

    def check(self, now_s: float) -> list[str]:
        """Warnings due to time alone: the companion's status stopped arriving for ``stale_s``."""
        if self.stale or not math.isfinite(self.t_status_s) or now_s - self.t_status_s <= self.stale_s:
            return []
        self.stale = True
        out = [f"GSOE silent for {now_s - self.t_status_s:.0f} s: estimate unknown"]
        self.warnings += out
        return out

    def lines(self) -> dict[str, str]:
        """Display lines (status-bar name -> text)."""
        def f(v: float, fmt: str) -> str:
            return format(v, fmt) if math.isfinite(v) else "--"

        validity = "STALE" if self.stale else {True: "valid", False: "INVALID", None: "unknown"}[self.valid]
        return {
            "GSOEWind": f"Wind {f(self.wind_speed_m_s, '.1f')}+-{f(self.wind_speed_sigma_m_s, '.1f')} m/s from "
                        f"{f(self.wind_from_deg, '.0f')}+-{f(self.wind_from_sigma_deg, '.0f')} deg",
            "GSOEDrift": f"Drift {f(self.drift_deg, '+.1f')} deg  ATA {f(self.ata_deg, '.1f')} deg",
            "GSOEState": f"GSOE {validity}  Q {f(self.quality, '.2f')}  {self.gnss_state or 'GNSS ?'}",
        }

    def as_dict(self) -> dict[str, Any]:
        """Plain form (NaN as None) for JSON."""
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(self).items()}
