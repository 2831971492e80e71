"""Attitude at a frame's exposure time, from timestamped AHRS and gyro samples.

Only the rotation *between* a cycle's base snapshot and the current frame moves the template; an error ``e`` in it
shifts the nadir point by ``focal_px * e`` pixels whatever the altitude.  Two independent noisy AHRS samples make
that relative rotation as noisy as the AHRS; the gyro integrated over the short interval is far better.  So:

* :meth:`AttitudeBuffer.attitude_at` interpolates the AHRS attitude (``q_nb``) to any time (slerp);
* :meth:`AttitudeBuffer.relative_rotation` gives ``R_b0b1`` between two times from the integrated gyro (a running
  product of ``exp(omega dt)`` stored with its timestamps and interpolated), after removing a gyro bias estimate;
* the bias estimate is a slow complementary filter: over each interval, the AHRS relative rotation minus the gyro
  one, divided by the interval, low-passed with time constant ``gyro_bias_tau_s`` (the AHRS noise averages out,
  its bias cancels in a relative rotation).

Rotations are scalar quaternions of :mod:`gsoe.quat` (a per-sample hot path; scipy's ``Rotation`` is the reference
in the tests).
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from numpy.typing import NDArray

from gsoe import quat
from gsoe.quat import Quat
from gsoe.types import AttitudeSample, ImuSample

US_PER_S = 1_000_000
# A frame may be stamped slightly after the newest attitude sample; beyond this the attitude is unknown.
MAX_EXTRAPOLATION_US = 50_000


class _Track:
    """Time-stamped quaternions with a bounded horizon, interpolated by slerp."""

    def __init__(self, horizon_us: int) -> None:
        self.t: list[int] = []
        self.q: list[Quat] = []
        self._horizon_us = horizon_us

    def append(self, t_us: int, q: Quat) -> None:
        self.t.append(t_us)
        self.q.append(q)
        if len(self.t) > 64 and self.t[-1] - self.t[0] > 2 * self._horizon_us:
            cut = bisect.bisect_left(self.t, self.t[-1] - self._horizon_us)
            del self.t[:cut]
            del self.q[:cut]

    def at(self, t_us: int) -> Quat | None:
        ts, qs = self.t, self.q
        n = len(ts)
        if n == 0 or t_us < ts[0] or t_us > ts[-1] + MAX_EXTRAPOLATION_US:
            return None
        if t_us >= ts[-1]:
            if n >= 2 and t_us > ts[-1]:  # short extrapolation at the last rate
                rx, ry, rz = quat.to_rotvec(quat.mul(quat.conj(qs[-2]), qs[-1]))
                f = (t_us - ts[-1]) / max(ts[-1] - ts[-2], 1)
                return quat.normalize(quat.mul(qs[-1], quat.from_rotvec(rx * f, ry * f, rz * f)))
            return qs[-1]
        i = bisect.bisect_right(ts, t_us)  # ts[i-1] <= t < ts[i]
        t0, t1 = ts[i - 1], ts[i]
        return quat.slerp(qs[i - 1], qs[i], (t_us - t0) / (t1 - t0))


class AttitudeBuffer:
    """Time-ordered AHRS attitudes and gyro-integrated rotations (frames as in :mod:`gsoe`)."""

    def __init__(self, horizon_s: float = 5.0, gyro_bias_tau_s: float = 20.0) -> None:
        horizon_us = int(horizon_s * US_PER_S)
        self._att = _Track(horizon_us)
        self._gyro = _Track(horizon_us)  # cumulative q_g(t): the integrated gyro since start
        self._cum: Quat = quat.IDENTITY
        self._last_t_us: int | None = None
        self._last_w = (0.0, 0.0, 0.0)
        self._bias = [0.0, 0.0, 0.0]
        self._bias_tau_s = gyro_bias_tau_s
        self._bias_time_s = 0.0

    # ---------------------------------------------------------------------------------------------- input
    def push_attitude(self, s: AttitudeSample) -> bool:
        """Add an AHRS sample; returns False (and ignores it) when non-finite or out of time order."""
        vals = (s.roll_rad, s.pitch_rad, s.yaw_rad)
        if not all(math.isfinite(v) for v in vals) or (self._att.t and s.t_us <= self._att.t[-1]):
            return False
        self._att.append(s.t_us, quat.from_euler321(s.roll_rad, s.pitch_rad, s.yaw_rad))
        return True

    def push_imu(self, s: ImuSample) -> bool:
        """Integrate one gyro sample (trapezoidal rate, bias removed); False when rejected."""
        g = s.gyro_b_rad_s
        if len(g) != 3:
            return False
        wx, wy, wz = float(g[0]), float(g[1]), float(g[2])
        if not (math.isfinite(wx) and math.isfinite(wy) and math.isfinite(wz)):
            return False
        if self._last_t_us is not None:
            if s.t_us <= self._last_t_us:
                return False
            dt_s = (s.t_us - self._last_t_us) / US_PER_S
            lw = self._last_w
            b = self._bias
            self._cum = quat.mul(self._cum, quat.from_rotvec((0.5 * (wx + lw[0]) - b[0]) * dt_s,
                                                             (0.5 * (wy + lw[1]) - b[1]) * dt_s,
                                                             (0.5 * (wz + lw[2]) - b[2]) * dt_s))
        self._last_t_us = s.t_us
        self._last_w = (wx, wy, wz)
        self._gyro.append(s.t_us, self._cum)
        return True

    # ---------------------------------------------------------------------------------------------- queries
    @property
    def gyro_bias_b_rad_s(self) -> NDArray[np.float64]:
        return np.array(self._bias)

    @property
    def has_gyro(self) -> bool:
        return len(self._gyro.t) >= 2

    @property
    def newest_attitude_t_us(self) -> int | None:
        return self._att.t[-1] if self._att.t else None

    def attitude_at(self, t_us: int) -> Quat | None:
        """AHRS ``q_nb`` interpolated to ``t_us`` (None when outside the buffer)."""
        return self._att.at(t_us)

    def relative_rotation(self, t0_us: int, t1_us: int, use_gyro: bool = True) -> Quat | None:
        """``q_b0b1``: the body at ``t1_us`` relative to the body at ``t0_us``.

        From the bias-corrected integrated gyro when ``use_gyro`` and both times are covered, else from two AHRS
        samples.
        """
        if use_gyro:
            g0, g1 = self._gyro.at(t0_us), self._gyro.at(t1_us)
            if g0 is not None and g1 is not None:
                return quat.mul(quat.conj(g0), g1)
        a0, a1 = self._att.at(t0_us), self._att.at(t1_us)
        if a0 is None or a1 is None:
            return None
        return quat.mul(quat.conj(a0), a1)

    def update_bias(self, t0_us: int, t1_us: int) -> None:
        """Feed the gyro-bias complementary filter with the interval [t0, t1] (called once per TM cycle).

        The gain is ``dt / max(tau, time averaged so far)``: a running mean at first, then a low-pass with time
        constant ``gyro_bias_tau_s``.
        """
        if self._bias_tau_s <= 0.0:
            return
        dt_s = (t1_us - t0_us) / US_PER_S
        if dt_s <= 0.0:
            return
        g0, g1 = self._gyro.at(t0_us), self._gyro.at(t1_us)
        a0, a1 = self._att.at(t0_us), self._att.at(t1_us)
        if g0 is None or g1 is None or a0 is None or a1 is None:
            return
        # residual rotation (body frame) the gyro missed over the interval, as a rate: remaining bias = -resid/dt
        rel_g = quat.mul(quat.conj(g0), g1)
        rel_a = quat.mul(quat.conj(a0), a1)
        resid = quat.to_rotvec(quat.mul(quat.conj(rel_g), rel_a))
        self._bias_time_s += dt_s
        k = min(1.0, dt_s / max(self._bias_tau_s, self._bias_time_s))
        for i in range(3):
            self._bias[i] -= k * resid[i] / dt_s
