"""The paper's estimator output chain, kept as the baseline the EKF is compared against.

Per finished TM cycle (paper 2.4-2.7): the last valid step's migration gives the drift (eq. 9, as the chord drift
of :func:`gsoe.cycle.chord_drift_rad`), the ground speed (migration times the ground sample distance over the
cycle's duration, eq. 10-11 with the camera-model GSD), the ATA (eq. 12; the sideslip is unknown in flight and
taken as zero) and the wind (eq. 13-17 with the pitot TAS); the heuristic integrity filter (2.7) then releases
or erases the cycle.  Everything is stamped at the middle of the cycle, where the chord's course applies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from common.angles import circular_mean
from common.samples import GsoeStep
from gsoe.attitude import US_PER_S
from gsoe.config import IntegrityConfig
from gsoe.cycle import chord_drift_rad
from gsoe.equations import ata_rad, wind_triangle
from gsoe.integrity import IntegrityFilter


@dataclass(frozen=True, slots=True)
class BaselineEstimate:
    """One cycle's output (released or erased by the integrity filter, with the reason)."""

    t_us: int
    drift_rad: float
    heading_rad: float
    ground_speed_m_s: float
    ata_rad: float
    wind_speed_m_s: float
    wind_from_rad: float
    released: bool
    reason: str


class PaperBaseline:
    """Cycle-level drift, ground speed, ATA and wind with the paper's integrity filter."""

    def __init__(self, cfg: IntegrityConfig) -> None:
        self.filter = IntegrityFilter(cfg)
        self._last_valid: GsoeStep | None = None
        self._n_valid = 0
        self._cycle_id = -1
        self._tas_m_s = math.nan

    def set_airspeed(self, tas_m_s: float) -> None:
        if math.isfinite(tas_m_s) and tas_m_s >= 0.0:
            self._tas_m_s = tas_m_s

    def update(self, step: GsoeStep) -> BaselineEstimate | None:
        """Feed every optical step; returns the previous cycle's estimate when a new cycle starts."""
        out = None
        if step.cycle_id != self._cycle_id:
            out = self._finish()
            self._cycle_id = step.cycle_id
            self._last_valid = None
            self._n_valid = 0
        if step.valid and not step.new_cycle:
            self._last_valid = step
            self._n_valid += 1
        return out

    def _finish(self) -> BaselineEstimate | None:
        s = self._last_valid
        if s is None:
            return None
        dt_s = (s.t_us - s.base_t_us) / US_PER_S
        travel_px = math.hypot(s.dx_px, s.dy_px)
        drift = chord_drift_rad(s)
        heading = circular_mean([s.base_yaw_rad, s.yaw_rad])
        gs = travel_px * s.gsd_m_px / dt_s if dt_s > 0 else math.nan
        ata = float(ata_rad(0.0, heading, drift))
        if math.isfinite(gs) and math.isfinite(self._tas_m_s):
            ws, wd = wind_triangle(self._tas_m_s, 0.0, heading, gs, ata)
        else:
            ws, wd = math.nan, math.nan
        t_mid = (s.t_us + s.base_t_us) // 2
        verdict = self.filter.update(t_mid, drift, self._n_valid, travel_px)
        return BaselineEstimate(t_us=t_mid, drift_rad=verdict.drift_rad if verdict.released else drift,
                                heading_rad=heading, ground_speed_m_s=gs, ata_rad=ata, wind_speed_m_s=float(ws),
                                wind_from_rad=float(wd), released=verdict.released, reason=verdict.reason)
