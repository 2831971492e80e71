"""Attitude at a frame's exposure time, from timestamped AHRS and gyro samples.

Only the rotation *between* a cycle's base snapshot and the current frame moves the template; an error ``e`` in it
shifts the nadir point by ``focal_px * e`` pixels whatever the altitude.  Two independent noisy AHRS samples make
that relative rotation as noisy as the AHRS; the gyro integrated over the short interval is far better.  So:

* :meth:`AttitudeBuffer.attitude_at` interpolates the AHRS attitude (``q_nb``) to any time (slerp);
* :meth:`AttitudeBuffer.relative_rotation` gives ``R_b0b1`` between two times from the integrated gyro (a running
  product of ``exp(omega dt)`` stored with its timestamps and interpolated), after removing a gyro bias estimate;
* the bias estimate is a slow complementary filter: over each interval, the AHRS relative rotation minus the gyro
  one, divided by the interval, low-passed with time constant ``gyro_bias_tau_s`` (the AHRS noise averages out,
  its bias cancels in a relative rotation);
* :attr:`AttitudeBuffer.ahrs_latency_s` estimates the AHRS latency (a sample stamped ``t`` describes the body at
  ``t - L``; the gyro is taken as stamped on time): every ``LATENCY_UPDATE_S`` the AHRS relative rotation over the
  last ``LATENCY_WINDOW_S`` is compared with the gyro's over the same window shifted back by each candidate ``L``
  of ``LATENCY_GRID_S``; the squared residuals are summed with forgetting time ``LATENCY_FORGET_S`` and the
  minimum, refined by a parabola, is the estimate.  Only rotation-rate *changes* (rolling into and out of turns)
  discriminate the candidates; noise and a gyro bias add about the same to all of them;
* :meth:`AttitudeBuffer.compensated_at` is the attitude at a time with that latency removed and the AHRS noise
  averaged, by a complementary filter: with exact data ``q_nb(t) = C * q_g(t)`` for a constant ``C`` (``q_g`` the
  integrated gyro); each AHRS sample ``a_i`` (stamp ``s_i``) gives ``C_i = a_i * q_g(s_i - L)^-1`` and ``C`` is
  their exponential average with time constant ``SMOOTH_TAU_S``, so ``q_nb(t) = C * q_g(t)`` at any ``t`` the
  gyro covers.  An AHRS latency of 0.1 s is a 2 deg
  heading error in a 20 deg/s turn, and a 0.5 deg noisy AHRS sample labels one TM cycle's stabilised frame with a
  0.5 deg heading error: the optical course carries both (see ``fusion.measurements.OpticalDisplacement``).

Rotations are scalar quaternions of :mod:`gsoe.quat` (a per-sample hot path; scipy's ``Rotation`` is the reference
in the tests).
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from numpy.typing import NDArray

from common.samples import AttitudeSample, ImuSample
from gsoe import quat
from gsoe.quat import Quat

US_PER_S = 1_000_000
# A frame may be stamped slightly after the newest attitude sample; beyond this the attitude is unknown.
MAX_EXTRAPOLATION_US = 50_000
# AHRS latency estimation (see the module docstring).  Candidates 0-0.25 s in 10 ms steps (a parabola refines the
# minimum); the relative rotations compared span 1 s (a roll-in changes the roll rate by ~0.5 rad/s within that);
# evaluated every 0.5 s (windows overlapping by half: more overlap gives correlated residuals that add little);
# forgotten over 120 s (the latency is a property of the installation, fixed within a flight).  The estimate is used
# only after LATENCY_MIN_RATE_CHANGE_RAD of accumulated absolute rate change (a few roll-ins), before that it is 0.
LATENCY_GRID_S = tuple(0.01 * i for i in range(26))
LATENCY_WINDOW_S = 1.0
LATENCY_UPDATE_S = 0.5
LATENCY_FORGET_S = 120.0
LATENCY_MIN_RATE_CHANGE_RAD = 2.0
# Time constant of the complementary filter of compensated_at (s): about 2 tau * rate = 30 samples of a 50 Hz AHRS
# are averaged (its white noise divided by ~5.5); a residual gyro bias b lags it by tau * b (0.03 deg at 0.1 deg/s).
SMOOTH_TAU_S = 0.3


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

    def __init__(self, horizon_s: float = 5.0, gyro_bias_tau_s: float = 20.0,
                 latency_s: float | None = None) -> None:
        """``latency_s``: the AHRS latency if known (s, >= 0); None estimates it from the data."""
        if latency_s is not None and not (math.isfinite(latency_s) and latency_s >= 0.0):
            raise ValueError(f"latency_s must be finite and >= 0 or None, got {latency_s!r}")
        horizon_us = int(horizon_s * US_PER_S)
        self._att = _Track(horizon_us)
        self._gyro = _Track(horizon_us)  # cumulative q_g(t): the integrated gyro since start
        self._cum: Quat = quat.IDENTITY
        self._last_t_us: int | None = None
        self._last_w = (0.0, 0.0, 0.0)
        self._bias = [0.0, 0.0, 0.0]
        self._bias_tau_s = gyro_bias_tau_s
        self._bias_time_s = 0.0
        self._fixed_latency_s = latency_s
        self._lat_sse = [0.0] * len(LATENCY_GRID_S)
        self._lat_next_us: int | None = None
        self._lat_rate_change_rad = 0.0
        self._lat_prev_rate: tuple[float, float, float] | None = None
        self._latency_s = 0.0 if latency_s is None else latency_s
        self._c_mean: Quat | None = None  # the complementary filter's q_nb * q_g^-1
        self._c_last_us: int | None = None
        # the integrated gyro at the last start time relative_rotation was asked for (a cycle's base time, asked
        # every frame): final once the gyro track has samples on both sides of it (they are only appended later)
        self._g0_memo: tuple[int, Quat] | None = None

    # ---------------------------------------------------------------------------------------------- input
    def push_attitude(self, s: AttitudeSample) -> bool:
        """Add an AHRS sample; returns False (and ignores it) when non-finite or out of time order."""
        vals = (s.roll_rad, s.pitch_rad, s.yaw_rad)
        if not all(math.isfinite(v) for v in vals) or (self._att.t and s.t_us <= self._att.t[-1]):
            return False
        self._att.append(s.t_us, quat.from_euler321(s.roll_rad, s.pitch_rad, s.yaw_rad))
        if self._fixed_latency_s is None:
            if self._lat_next_us is None:
                self._lat_next_us = s.t_us + int((LATENCY_WINDOW_S + LATENCY_GRID_S[-1]) * US_PER_S)
            elif s.t_us >= self._lat_next_us:
                self._lat_next_us = s.t_us + int(LATENCY_UPDATE_S * US_PER_S)
                self._update_latency(s.t_us)
        self._update_smoother(s.t_us)
        return True

    def _update_smoother(self, t_us: int) -> None:
        """Feed the newest AHRS sample (stamped ``t_us``) to the complementary filter of :meth:`compensated_at`."""
        g = self._gyro.at(t_us - int(round(self._latency_s * US_PER_S)))
        if g is None:
            return
        c = quat.mul(self._att.q[-1], quat.conj(g))
        if self._c_mean is None or self._c_last_us is None:
            self._c_mean = c
        else:
            k = min(1.0, (t_us - self._c_last_us) / US_PER_S / SMOOTH_TAU_S)
            rx, ry, rz = quat.to_rotvec(quat.mul(quat.conj(self._c_mean), c))
            self._c_mean = quat.normalize(quat.mul(self._c_mean, quat.from_rotvec(k * rx, k * ry, k * rz)))
        self._c_last_us = t_us

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

    @property
    def ahrs_latency_s(self) -> float:
        """The AHRS latency in use (s): the configured one, else the estimate (0 until it is trustworthy)."""
        return self._latency_s

    def _update_latency(self, t_us: int) -> None:
        """One step of the latency estimator at the AHRS sample stamped ``t_us`` (see the module docstring)."""
        w_us = int(LATENCY_WINDOW_S * US_PER_S)
        a0, a1 = self._att.at(t_us - w_us), self._att.at(t_us)
        if a0 is None or a1 is None:
            return
        rel_a = quat.mul(quat.conj(a0), a1)
        res = []
        rate = (0.0, 0.0, 0.0)
        for lat in LATENCY_GRID_S:
            l_us = int(round(lat * US_PER_S))
            g0, g1 = self._gyro.at(t_us - w_us - l_us), self._gyro.at(t_us - l_us)
            if g0 is None or g1 is None:
                return
            rel_g = quat.mul(quat.conj(g0), g1)
            if l_us == 0:
                rate = quat.to_rotvec(rel_g)  # the window's rotation: its changes are what discriminates
            rx, ry, rz = quat.to_rotvec(quat.mul(quat.conj(rel_g), rel_a))
            res.append(rx * rx + ry * ry + rz * rz)
        if self._lat_prev_rate is not None:
            self._lat_rate_change_rad += math.dist(rate, self._lat_prev_rate)
        self._lat_prev_rate = rate
        k = math.exp(-LATENCY_UPDATE_S / LATENCY_FORGET_S)
        sse = self._lat_sse
        for i, r in enumerate(res):
            sse[i] = k * sse[i] + r
        if self._lat_rate_change_rad < LATENCY_MIN_RATE_CHANGE_RAD:
            return
        i = min(range(len(sse)), key=sse.__getitem__)
        lat = LATENCY_GRID_S[i]
        if 0 < i < len(sse) - 1:
            den = sse[i - 1] - 2.0 * sse[i] + sse[i + 1]
            if den > 0.0:
                lat += 0.5 * (sse[i - 1] - sse[i + 1]) / den * (LATENCY_GRID_S[1] - LATENCY_GRID_S[0])
        self._latency_s = lat

    def compensated_at(self, t_us: int, smooth: bool = True) -> Quat | None:
        """``q_nb`` at ``t_us`` with the AHRS latency removed (and, with ``smooth``, its noise averaged).

        Each AHRS sample stamped ``s`` describes the body at ``s - L``; carried to ``t_us`` by the gyro rotation
        from ``s - L`` to ``t_us``.  Without ``smooth`` only the sample (interpolated) at ``min(t + L, newest)`` is
        used; with it, the complementary filter's ``C * q_g(t)`` (module docstring; O(1)).  Falls back to
        :meth:`attitude_at` (the raw AHRS) when the gyro does not cover the times needed; None when the AHRS does
        not cover ``t_us``.
        """
        ts = self._att.t
        if not ts or t_us < ts[0] or t_us > ts[-1] + MAX_EXTRAPOLATION_US:
            return None                      # the AHRS does not cover t_us (the same test as _Track.at)
        g_t = self._gyro.at(t_us)
        if smooth and g_t is not None and self._c_mean is not None:
            return quat.normalize(quat.mul(self._c_mean, g_t))       # the per-IMU-sample path
        raw = self._att.at(t_us)
        if raw is None:
            return None
        l_us = int(round(self._latency_s * US_PER_S))
        if g_t is None or (l_us == 0 and not smooth):
            return raw
        centre = min(t_us + l_us, ts[-1])
        if not smooth:
            a = self._att.at(centre)
            g0 = self._gyro.at(centre - l_us)
            if a is None or g0 is None:
                return raw
            return quat.normalize(quat.mul(a, quat.mul(quat.conj(g0), g_t)))
        return self.compensated_at(t_us, smooth=False)          # smooth, but no AHRS sample averaged yet

    def attitude_at(self, t_us: int) -> Quat | None:
        """AHRS ``q_nb`` interpolated to ``t_us`` (None when outside the buffer)."""
        return self._att.at(t_us)

    def relative_rotation(self, t0_us: int, t1_us: int, use_gyro: bool = True) -> Quat | None:
        """``q_b0b1``: the body at ``t1_us`` relative to the body at ``t0_us``.

        From the bias-corrected integrated gyro when ``use_gyro`` and both times are covered, else from two AHRS
        samples.
        """
        if use_gyro:
            ts = self._gyro.t
            memo = self._g0_memo
            if memo is not None and memo[0] == t0_us and ts and ts[0] <= t0_us:
                g0: Quat | None = memo[1]
            else:
                g0 = self._gyro.at(t0_us)
                if g0 is not None and t0_us < ts[-1]:     # interpolated: its neighbours are final
                    self._g0_memo = (t0_us, g0)
            g1 = self._gyro.at(t1_us)
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
        # AHRS samples stamped t describe the body at t - latency: compare with the gyro over that interval
        l_us = int(round(self._latency_s * US_PER_S))
        g0, g1 = self._gyro.at(t0_us - l_us), self._gyro.at(t1_us - l_us)
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
