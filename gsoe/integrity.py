"""The paper's data filter (eq. 6, section 2.5) and heuristic data-integrity filter (section 2.7).

Both are kept as the baseline that the EKF of :mod:`fusion` replaces and is compared against.  Angles in radians
inside, compared only through :mod:`common.angles`.

Data filter (eq. 6)
    ``|a_x - b_x| >= zeta  and  |a_y - b_y| >= zeta``: both components of two consecutive quantities differ by at
    least ``zeta`` px.  The paper applies it to consecutive template locations ``L(n-1), L(n)``; the project's
    cycle (:mod:`gsoe.cycle`, ``cycle.data_filter_zeta_px``) applies it to consecutive per-frame template *steps*,
    so that steady motion never fires and a jump (a wrong match) does.

Integrity filter (2.7)
    The paper describes it only in words: it compares each cycle's result with the last cycles' and erases the
    inconsistent ones, and its efficiency depends on how many past cycles it compares.  Here a finished cycle's
    drift is *released* when

    * its timestamp is later than the previous cycle's, its drift is finite,
    * it had at least ``min_steps`` valid matches and its template travelled at least ``min_travel_px``
      (a short baseline gives a coarse angle), and
    * it lies within ``max_jump_deg`` of the circular median of the last ``history_cycles`` released drifts.

    Recovery: a real change of drift (a turn that changes the wind's angle to the heading, a new wind) would be
    rejected for ever by the median test alone.  So cycles rejected for a jump are kept as candidates; when the
    last ``recovery_cycles`` consecutive candidates (default :data:`RECOVERY_CYCLES`) agree among themselves (all
    within ``max_jump_deg`` of their own circular median), the new level is accepted: the history is replaced
    by the candidates and the current cycle is released.  A released cycle clears the candidates; cycles
    rejected for too few steps or too short a travel neither add to nor clear them.  At start-up (no history)
    every usable cycle is a candidate, so the first release needs ``recovery_cycles`` agreeing cycles.

    Circular median: the angles' circular mean plus the median of their signed differences from it, a robust
    centre for angles spread over less than a half turn (which a drift history always is).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from common.angles import angle_diff, circular_mean, wrap_pi
from gsoe.config import IntegrityConfig

# Consecutive jump-rejected cycles that must agree among themselves before their drift is accepted as the new
# level (and, at start-up, before the first release).  Three: two could be one outlier and its twin.
RECOVERY_CYCLES = 3


def data_filter_fires(prev_step_xy: Sequence[float], step_xy: Sequence[float], zeta_px: float) -> bool:
    """Paper eq. 6: True when both components of ``step_xy`` differ from ``prev_step_xy`` by at least ``zeta_px``.

    ``prev_step_xy``/``step_xy`` are (x, y) pixel pairs: consecutive per-frame template steps (the project's use)
    or consecutive template locations (the paper's).  A non-finite component fires (an anomaly ends the cycle).
    ``zeta_px`` must be finite and non-negative (``ValueError`` otherwise); zero fires on every step.
    """
    if not (math.isfinite(zeta_px) and zeta_px >= 0.0):
        raise ValueError(f"zeta_px: must be finite and >= 0, got {zeta_px!r}")
    if len(prev_step_xy) != 2 or len(step_xy) != 2:
        raise ValueError(f"expected (x, y) pairs, got {prev_step_xy!r} and {step_xy!r}")
    ddx = abs(float(step_xy[0]) - float(prev_step_xy[0]))
    ddy = abs(float(step_xy[1]) - float(prev_step_xy[1]))
    if not (math.isfinite(ddx) and math.isfinite(ddy)):
        return True
    return ddx >= zeta_px and ddy >= zeta_px


def circular_median(angles_rad: Sequence[float]) -> float:
    """Robust centre of angles (rad) spread over less than a half turn, in [-pi, pi); nan for no angles."""
    a = np.asarray(angles_rad, dtype=float)
    if a.size == 0:
        return math.nan
    centre = circular_mean(a)
    return float(wrap_pi(centre + float(np.median(angle_diff(a, centre)))))


@dataclass(frozen=True, slots=True)
class IntegrityVerdict:
    """What the integrity filter says about one cycle: ``released`` with its drift (rad, [-pi, pi)), or not, with
    ``drift_rad = nan`` (the paper's filter erases inconsistent data); ``reason`` says why, for logs."""

    released: bool
    drift_rad: float
    reason: str


class IntegrityFilter:
    """The paper's heuristic data-integrity filter (2.7); see the module docstring for the rules.

    Parameters
    ----------
    cfg
        ``history_cycles``, ``max_jump_deg``, ``min_steps``, ``min_travel_px``.
    recovery_cycles
        Consecutive agreeing jump-rejected cycles that establish a new level (>= 1).
    """

    def __init__(self, cfg: IntegrityConfig, *, recovery_cycles: int = RECOVERY_CYCLES) -> None:
        if recovery_cycles < 1:
            raise ValueError(f"recovery_cycles: must be >= 1, got {recovery_cycles}")
        self.cfg = cfg
        self.recovery_cycles = recovery_cycles
        self._max_jump_rad = math.radians(cfg.max_jump_deg)
        self._history: deque[float] = deque(maxlen=cfg.history_cycles)
        self._candidates: deque[float] = deque(maxlen=recovery_cycles)
        self._last_t_us: int | None = None

    @property
    def reference_rad(self) -> float:
        """Circular median of the released history (nan before the first release)."""
        return circular_median(list(self._history))

    def _agree(self, angles: Sequence[float]) -> bool:
        centre = circular_median(angles)
        return bool(np.all(np.abs(angle_diff(np.asarray(angles), centre)) <= self._max_jump_rad))

    def update(self, t_us: int, drift_rad: float, n_steps: int, travel_px: float) -> IntegrityVerdict:
        """Judge one finished cycle: its end time ``t_us``, drift (rad), valid matches and template travel (px)."""
        if self._last_t_us is not None and t_us <= self._last_t_us:
            return IntegrityVerdict(False, math.nan, f"t_us {t_us} not after the previous cycle's {self._last_t_us}")
        self._last_t_us = t_us
        if not math.isfinite(drift_rad):
            return IntegrityVerdict(False, math.nan, "drift not finite")
        if n_steps < self.cfg.min_steps:
            return IntegrityVerdict(False, math.nan, f"{n_steps} valid steps < min_steps {self.cfg.min_steps}")
        if not (math.isfinite(travel_px) and travel_px >= self.cfg.min_travel_px):
            return IntegrityVerdict(False, math.nan,
                                    f"travel {travel_px:.1f} px < min_travel_px {self.cfg.min_travel_px:.1f}")
        drift = float(wrap_pi(drift_rad))
        if self._history:
            ref = self.reference_rad
            jump = abs(float(angle_diff(drift, ref)))
            if jump <= self._max_jump_rad:
                self._history.append(drift)
                self._candidates.clear()
                return IntegrityVerdict(True, drift, "consistent with history")
            why = f"jump {math.degrees(jump):.1f} deg from median {math.degrees(ref):.1f} deg"
        else:
            why = "no history yet"
        self._candidates.append(drift)
        if len(self._candidates) == self.recovery_cycles and self._agree(list(self._candidates)):
            self._history.clear()
            self._history.extend(self._candidates)
            self._candidates.clear()
            return IntegrityVerdict(True, drift, f"new level: {self.recovery_cycles} consecutive cycles agree")
        return IntegrityVerdict(False, math.nan,
                                f"{why}; {len(self._candidates)}/{self.recovery_cycles} agreeing candidates")
