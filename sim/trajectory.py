"""A scripted kinematic flight: straight legs and coordinated turns in a steady wind, with exact truth.

For tests and benchmarks that need a known crab angle, ground speed and turn rate without flight dynamics: the
aircraft flies at constant true airspeed with zero sideslip, its heading follows a turn-rate schedule (ramped
between segments), roll is the coordinated-turn value ``atan(V omega / g)``, and the ground velocity is the air
velocity plus the wind.  Body rates come from the attitude history itself, so gyro samples are consistent with
the attitude to integration accuracy.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import cumulative_trapezoid
from scipy.spatial.transform import Rotation

from sim.truth import TruthState

G_M_S2 = 9.80665
_TABLE_RATE_HZ = 1000.0


@dataclass(frozen=True)
class Segment:
    """``duration_s`` at turn rate ``turn_rate_rad_s`` (positive: clockwise seen from above)."""

    duration_s: float
    turn_rate_rad_s: float = 0.0


class ScriptedFlight:
    """Truth of a scripted flight, tabulated at 1 kHz and interpolated."""

    def __init__(self, segments: Sequence[Segment], *, tas_m_s: float = 20.0, height_m: float = 100.0,
                 yaw0_rad: float = 0.0, pitch_rad: float = 0.03, wind_ned_m_s: Sequence[float] = (0.0, 0.0, 0.0),
                 ramp_s: float = 1.0) -> None:
        self.duration_s = float(sum(s.duration_s for s in segments))
        t = np.arange(0.0, self.duration_s + 1e-9, 1.0 / _TABLE_RATE_HZ)
        edges = np.cumsum([0.0] + [s.duration_s for s in segments])
        rates = np.array([s.turn_rate_rad_s for s in segments])
        idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, len(segments) - 1)
        omega = rates[idx]
        if ramp_s > 0:  # moving average over the ramp: smooth roll-in/roll-out
            k = max(1, int(ramp_s * _TABLE_RATE_HZ))
            pad = np.concatenate([np.full(k // 2, omega[0]), omega, np.full(k - k // 2 - 1, omega[-1])])
            omega = np.convolve(pad, np.ones(k) / k, mode="valid")
        yaw = yaw0_rad + cumulative_trapezoid(omega, t, initial=0.0)
        wind = np.asarray(wind_ned_m_s, dtype=float)
        vel = np.column_stack([tas_m_s * np.cos(yaw) + wind[0], tas_m_s * np.sin(yaw) + wind[1],
                               np.full_like(t, wind[2])])
        pos = np.column_stack([cumulative_trapezoid(vel[:, 0], t, initial=0.0),
                               cumulative_trapezoid(vel[:, 1], t, initial=0.0),
                               -height_m + cumulative_trapezoid(vel[:, 2], t, initial=0.0)])
        roll = np.arctan(tas_m_s * omega / G_M_S2)
        self._t = t
        self._pos = pos
        self._vel = vel
        self._att = np.column_stack([roll, np.full_like(t, pitch_rad), yaw])
        self._omega = omega
        self.tas_m_s = tas_m_s
        self.wind_ned_m_s = wind
        rot = Rotation.from_euler("ZYX", self._att[:, ::-1])
        rel = rot[:-1].inv() * rot[1:]
        rates = rel.as_rotvec() * _TABLE_RATE_HZ
        self._rates = np.vstack([rates, rates[-1:]])
        # specific force: d(vel)/dt - gravity, in body axes
        acc_n = np.gradient(vel, t, axis=0) - np.array([0.0, 0.0, G_M_S2])
        self._accel_b = rot.inv().apply(acc_n)

    def _lerp(self, arr: NDArray[np.float64], t_s: float) -> NDArray[np.float64]:
        i = int(np.clip(np.searchsorted(self._t, t_s) - 1, 0, len(self._t) - 2))
        w = (t_s - self._t[i]) * _TABLE_RATE_HZ
        return (1 - w) * arr[i] + w * arr[i + 1]

    def truth(self, t_s: float) -> TruthState:
        att = self._lerp(self._att, t_s)
        pos = self._lerp(self._pos, t_s)
        return TruthState(
            t_s=t_s, pos_ned_m=pos, vel_ned_m_s=self._lerp(self._vel, t_s),
            roll_rad=float(att[0]), pitch_rad=float(att[1]), yaw_rad=float(att[2]),
            rates_b_rad_s=self._lerp(self._rates, t_s), accel_b_m_s2=self._lerp(self._accel_b, t_s),
            tas_m_s=self.tas_m_s, alpha_rad=float(att[1]), beta_rad=0.0,
            wind_ned_m_s=self.wind_ned_m_s.copy(), wind_steady_ned_m_s=self.wind_ned_m_s.copy(),
            height_agl_m=float(-pos[2]),
        )

    def turn_rate_rad_s(self, t_s: float) -> float:
        return float(np.interp(t_s, self._t, self._omega))
