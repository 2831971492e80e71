"""Attitude at a frame's exposure time, from timestamped AHRS and gyro samples.

Only the rotation *between* a cycle's base snapshot and the current frame moves the template; an error ``e`` in it
shifts the nadir point by ``focal_px * e`` pixels whatever the altitude.  Two independent noisy AHRS samples make
that relative rotation as noisy as the AHRS; the gyro integrated over the short interval is far better.  So:

* :meth:`AttitudeBuffer.attitude_at` interpolates the AHRS attitude (``R_nb``) to any time (scipy ``Slerp``);
* :meth:`AttitudeBuffer.relative_rotation` gives ``R_b0b1`` between two times from the integrated gyro (a running
  product of ``exp(omega dt)`` stored with its timestamps and interpolated), after removing a gyro bias estimate;
* the bias estimate is a slow complementary filter: over each interval, the AHRS relative rotation minus the gyro
  one, divided by the interval, low-passed with time constant ``gyro_bias_tau_s`` (the AHRS noise averages out,
  its bias cancels in a relative rotation).
"""

from __future__ import annotations

import bisect
import math
from collections import deque

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from gsoe.types import AttitudeSample, ImuSample

US_PER_S = 1_000_000
# A frame may be stamped slightly after the newest attitude sample; beyond this the attitude is unknown.
MAX_EXTRAPOLATION_US = 50_000


class AttitudeBuffer:
    """Time-ordered AHRS attitudes and gyro-integrated rotations (frames as in :mod:`gsoe`)."""

    def __init__(self, horizon_s: float = 5.0, gyro_bias_tau_s: float = 20.0) -> None:
        self._horizon_us = int(horizon_s * US_PER_S)
        self._att_t: deque[int] = deque()
        self._att_q: deque[NDArray[np.float64]] = deque()
        self._gyro_t: deque[int] = deque()
        self._gyro_q: deque[NDArray[np.float64]] = deque()  # cumulative R_g(t) as quaternions (x, y, z, w)
        self._cum = Rotation.identity()
        self._last_gyro: ImuSample | None = None
        self._bias_b_rad_s = np.zeros(3)
        self._bias_tau_s = gyro_bias_tau_s
        self._bias_t_us: int | None = None

    # ---------------------------------------------------------------------------------------------- input
    def push_attitude(self, s: AttitudeSample) -> bool:
        """Add an AHRS sample; returns False (and ignores it) when non-finite or out of time order."""
        vals = (s.roll_rad, s.pitch_rad, s.yaw_rad)
        if not all(math.isfinite(v) for v in vals) or (self._att_t and s.t_us <= self._att_t[-1]):
            return False
        q = Rotation.from_euler("ZYX", [s.yaw_rad, s.pitch_rad, s.roll_rad]).as_quat()
        self._att_t.append(s.t_us)
        self._att_q.append(q)
        self._trim(self._att_t, self._att_q)
        return True

    def push_imu(self, s: ImuSample) -> bool:
        """Integrate one gyro sample (rectangular rule with the previous rate); False when rejected."""
        w = np.asarray(s.gyro_b_rad_s, dtype=float)
        if w.shape != (3,) or not np.all(np.isfinite(w)) or (self._gyro_t and s.t_us <= self._gyro_t[-1]):
            return False
        if self._last_gyro is not None:
            dt_s = (s.t_us - self._last_gyro.t_us) / US_PER_S
            w_mid = 0.5 * (w + self._last_gyro.gyro_b_rad_s) - self._bias_b_rad_s
            self._cum = self._cum * Rotation.from_rotvec(w_mid * dt_s)
        self._last_gyro = ImuSample(s.t_us, w, np.asarray(s.accel_b_m_s2, dtype=float))
        self._gyro_t.append(s.t_us)
        self._gyro_q.append(self._cum.as_quat())
        self._trim(self._gyro_t, self._gyro_q)
        return True

    def _trim(self, ts: deque[int], qs: deque[NDArray[np.float64]]) -> None:
        while len(ts) > 2 and ts[-1] - ts[0] > self._horizon_us:
            ts.popleft()
            qs.popleft()

    # ---------------------------------------------------------------------------------------------- queries
    @property
    def gyro_bias_b_rad_s(self) -> NDArray[np.float64]:
        return self._bias_b_rad_s.copy()

    @property
    def has_gyro(self) -> bool:
        return len(self._gyro_t) >= 2

    def attitude_at(self, t_us: int) -> Rotation | None:
        """AHRS ``R_nb`` interpolated to ``t_us`` (None when outside the buffer)."""
        return self._interp(self._att_t, self._att_q, t_us)

    def _interp(self, ts: deque[int], qs: deque[NDArray[np.float64]], t_us: int) -> Rotation | None:
        n = len(ts)
        if n == 0 or t_us < ts[0] or t_us > ts[-1] + MAX_EXTRAPOLATION_US:
            return None
        if n == 1 or t_us >= ts[-1]:
            if n >= 2 and t_us > ts[-1]:
                # short extrapolation at the last rate
                r0, r1 = Rotation.from_quat(qs[-2]), Rotation.from_quat(qs[-1])
                rate = (r0.inv() * r1).as_rotvec() / max(ts[-1] - ts[-2], 1)
                return r1 * Rotation.from_rotvec(rate * (t_us - ts[-1]))
            return Rotation.from_quat(qs[-1])
        i = bisect.bisect_right(ts, t_us)  # ts[i-1] <= t < ts[i]
        t0, t1 = ts[i - 1], ts[i]
        slerp = Slerp([0.0, 1.0], Rotation.from_quat(np.stack([qs[i - 1], qs[i]])))
        return slerp([(t_us - t0) / (t1 - t0)])[0]

    def relative_rotation(self, t0_us: int, t1_us: int, use_gyro: bool = True) -> Rotation | None:
        """``R_b0b1``: rotation of the body at ``t1_us`` relative to the body at ``t0_us``.

        From the bias-corrected integrated gyro when ``use_gyro`` and both times are covered, else from two AHRS
        samples.
        """
        if use_gyro:
            g0 = self._interp(self._gyro_t, self._gyro_q, t0_us)
            g1 = self._interp(self._gyro_t, self._gyro_q, t1_us)
            if g0 is not None and g1 is not None:
                return g0.inv() * g1
        a0, a1 = self.attitude_at(t0_us), self.attitude_at(t1_us)
        if a0 is None or a1 is None:
            return None
        return a0.inv() * a1

    def update_bias(self, t0_us: int, t1_us: int) -> None:
        """Feed the gyro-bias complementary filter with the interval [t0, t1] (called once per TM cycle)."""
        if self._bias_tau_s <= 0.0:
            return
        dt_s = (t1_us - t0_us) / US_PER_S
        if dt_s <= 0.0:
            return
        g0 = self._interp(self._gyro_t, self._gyro_q, t0_us)
        g1 = self._interp(self._gyro_t, self._gyro_q, t1_us)
        a0, a1 = self.attitude_at(t0_us), self.attitude_at(t1_us)
        if g0 is None or g1 is None or a0 is None or a1 is None:
            return
        # residual rotation (body frame) the gyro missed over the interval, as a rate
        resid = ((g0.inv() * g1).inv() * (a0.inv() * a1)).as_rotvec()
        sample = -resid / dt_s  # remaining bias = gyro rate - true rate
        k = min(1.0, dt_s / self._bias_tau_s)
        self._bias_b_rad_s = self._bias_b_rad_s + k * sample
