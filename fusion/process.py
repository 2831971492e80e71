"""The process model: IMU-driven mean propagation, its Jacobian ``F``, the process noise ``Q`` and the wind model.

Prediction
    ``v' = R_z(-yaw_bias) R_nb_ahrs (I + [omega_b x] att_delay) (f_b - accel_bias_b) + g_n`` and ``p' = v``: the
    AHRS attitude stamped ``t`` describes the body at ``t - att_delay``, and the gyro's body rates ``omega_b``
    carry it forward (first order; the ``att_delay omega_b x accel_bias_b`` term is dropped); ``f_b`` is already
    turned to the middle of its sample's interval (:mod:`fusion.imu`).  The IMU samples of
    one prediction arrive summed as an :class:`ImuIncrement` (:mod:`fusion.imu` builds it); with its first moments
    the mean of one prediction over many samples equals the sample-by-sample integration of a piecewise constant
    specific force (velocity and position, bias, heading and delay Jacobians included; tests check it).

Wind
    A walking mean ``wind_mean_ne`` plus first-order Gauss-Markov turbulence: over a prediction of ``dt`` the total
    wind relaxes as ``wind' = e wind + (1 - e) wind_mean`` (``e = exp(-dt / wind.turb_corr_time_s)``) with the
    turbulence's noise ``sigma^2 (1 - e^2)``; ``sigma^2`` is estimated in flight (``wind.turb_adapt_time_s``) from
    the estimated turbulence ``wind - wind_mean`` and its variance, so the wind's covariance follows the day's
    turbulence level.  The vertical wind relaxes to 0 with ``wind.vertical_sigma_ratio`` times that sigma.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from filterpy.common import Q_continuous_white_noise
from numpy.typing import NDArray
from scipy.constants import g as STANDARD_GRAVITY_M_S2

from common.samples import AttitudeSample
from fusion.config import EkfConfig
from fusion.state import S

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

US_PER_S = 1_000_000
S_PER_US = 1e-6
#: Process-noise matrices kept per prediction length (µs); the cache is emptied when it grows beyond this (the
#: lengths are few when samples come on a clock grid, arbitrary in replays of jittery logs).
Q_CACHE_MAX = 256
#: ``|cos(pitch)|`` below which the 3-2-1 yaw rate is undefined (pitch within 0.06 deg of +-90 deg) and taken as 0.
MIN_COS_PITCH = 1e-3

_I_POS = S.idx("pos_ned")
_I_VEL = S.idx("vel_ned")
_I_YAW = S.yaw_bias.start
_I_WIND = S.idx("wind_ne")
_I_WMEAN = S.idx("wind_mean_ne")
_I_WD = S.wind_d.start
_I_CLONE = S.idx("base_pos_ned")
_I_BA = S.idx("accel_bias_b")
_I_DELAY = S.att_delay.start
_POS, _VEL, _BA = S.pos_ned, S.vel_ned, S.accel_bias_b
_POS0, _VEL0, _BA0 = _POS.start, _VEL.start, _BA.start      # (plain ints for the per-prediction arithmetic)


def _flat(rows: Any, cols: Any) -> NDArray[np.intp]:
    return np.ravel_multi_index((rows, cols), (S.dim, S.dim))


# flat indices of the wind's Gauss-Markov entries of F: d wind / d wind (N, E), then d wind / d wind_mean (N, E)
_F_WIND = np.concatenate([_flat(_I_WIND, _I_WIND), _flat(_I_WIND, _I_WMEAN)])
_F_WD = _I_WD * S.dim + _I_WD                             # flat index of d wind_d / d wind_d in F
# flat indices of the wind's process-noise entries: (wind, wind), (wind, mean), (mean, wind)
_Q_WW, _Q_WM, _Q_MW = _flat(_I_WIND, _I_WIND), _flat(_I_WIND, _I_WMEAN), _flat(_I_WMEAN, _I_WIND)
# what the turbulence adaptation reads: wind (N, E) and its mean (N, E) in x; in P the variance of wind - mean per
# axis, (wind, wind) - 2 (wind, mean) + (mean, mean), N then E
_P_TURB = _flat([_I_WIND[0], _I_WIND[0], _I_WMEAN[0], _I_WIND[1], _I_WIND[1], _I_WMEAN[1]],
                [_I_WIND[0], _I_WMEAN[0], _I_WMEAN[0], _I_WIND[1], _I_WMEAN[1], _I_WMEAN[1]])
_X_TURB = np.array([_I_WIND[0], _I_WIND[1], _I_WMEAN[0], _I_WMEAN[1]])
_WN, _WE, _MN, _ME = (int(i) for i in _X_TURB)
# flat indices of the IMU-dependent entries of F, in the order _propagate_into lists them: d pos / d vel (N, E, D),
# d pos / d accel_bias_b (3 x 3, row by row), d vel / d accel_bias_b, d(pos_n, pos_e, vel_n, vel_e) / d yaw_bias,
# d pos / d att_delay, d vel / d att_delay
_F_IMU = np.concatenate([
    _flat(_I_POS, _I_VEL),
    _flat(np.repeat(_I_POS, 3), np.tile(_I_BA, 3)),
    _flat(np.repeat(_I_VEL, 3), np.tile(_I_BA, 3)),
    _flat([S.pos_ne.start, S.pos_ne.start + 1, S.vel_ne.start, S.vel_ne.start + 1], [_I_YAW] * 4),
    _flat(_I_POS, [_I_DELAY] * 3),
    _flat(_I_VEL, [_I_DELAY] * 3),
])
_N_F_IMU = len(_F_IMU)
# flat indices of the position/velocity blocks of Q (north, east, down in turn)
_Q_PP, _Q_PV, _Q_VP, _Q_VV = _flat(_I_POS, _I_POS), _flat(_I_POS, _I_VEL), _flat(_I_VEL, _I_POS), _flat(_I_VEL, _I_VEL)
_HALF_G = 0.5 * STANDARD_GRAVITY_M_S2
_EYE = np.eye(S.dim)
_EYE.flags.writeable = False


def rot_rows(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, ...]:
    """The nine entries (row by row) of the body-to-NED rotation from 3-2-1 Euler angles."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
            sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
            -sp, cp * sr, cp * cr)


def R_nb_321(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Mat:
    """Body-to-NED rotation from 3-2-1 Euler angles; the same as :func:`gsoe.rotation.R_nb_from_euler` (a test
    checks it) written out, because building a scipy ``Rotation`` per IMU sample costs more than the EKF step."""
    return np.array(rot_rows(roll_rad, pitch_rad, yaw_rad)).reshape(3, 3)


def yaw_rate(att: AttitudeSample, rates_b: tuple[float, float, float]) -> float:
    """Rate of the 3-2-1 yaw angle (rad/s) from body rates ``(p, q, r)``: ``(q sin(roll) + r cos(roll)) / cos(pitch)``
    (0 at the 3-2-1 singularity, ``|cos(pitch)| < MIN_COS_PITCH``)."""
    cp = math.cos(att.pitch_rad)
    if abs(cp) < MIN_COS_PITCH:
        return 0.0
    return (rates_b[1] * math.sin(att.roll_rad) + rates_b[2] * math.cos(att.roll_rad)) / cp


@dataclass(slots=True)
class ImuIncrement:
    """IMU input of one prediction over ``dt_s`` (AHRS-NED, no gravity, no bias correction).

    ``dv_ahrs_n = sum(R_nb f_b dt)`` (m/s) and ``int_R_nb = sum(R_nb dt)`` (s), and their first moments
    ``dv_moment_n = sum(R_nb f_b dt t_mid)`` (m) and ``int_R_nb_moment = sum(R_nb dt t_mid)`` (s^2), ``t_mid`` being
    each sample interval's midpoint measured from the start of the increment.  The moments make the position change
    of a piecewise constant specific force exact: ``sum(R f dt (T - t_mid)) = T dv - moment``.  ``None`` (the
    default): the increment is spread evenly over ``dt_s`` (moment = value * dt_s / 2, e.g. one sample held).
    Arrays, or (the filter's own per-sample path) nested sequences of floats of the same shapes.

    ``dv_delay_n = sum(R_nb (omega_b x f_b) dt)`` (m/s^2; ``omega_b`` the gyro's body rates) and its first moment
    ``dv_delay_moment_n`` (m/s): the velocity (position) change per second of AHRS delay ``att_delay``, since the
    true attitude is ``R_nb (I + [omega x] att_delay)``.  ``None``: no rates (the delay has no effect).
    """

    dt_s: float = 0.0
    dv_ahrs_n: Vec | Sequence[float] = field(default_factory=lambda: np.zeros(3))
    int_R_nb: Mat | Sequence[Sequence[float]] = field(default_factory=lambda: np.zeros((3, 3)))
    dv_moment_n: Vec | Sequence[float] | None = None
    int_R_nb_moment: Mat | Sequence[Sequence[float]] | None = None
    dv_delay_n: Vec | Sequence[float] | None = None
    dv_delay_moment_n: Vec | Sequence[float] | None = None


def _floats(a: Any) -> Any:
    """Python floats (nested lists) of an array; sequences pass unchanged."""
    return a.tolist() if isinstance(a, np.ndarray) else a


def _moments(inc: ImuIncrement) -> tuple[Any, ...]:
    """The increment's sums as floats: ``sum R dt`` (rows), ``sum R dt (T - t_mid)`` (rows), ``sum R f dt``,
    ``sum R f dt (T - t_mid)``, the delay's ``sum R (w x f) dt`` and ``sum R (w x f) dt (T - t_mid)`` (or None)."""
    T = inc.dt_s
    M = inc.int_R_nb if type(inc.int_R_nb) is list else _floats(inc.int_R_nb)     # sum R dt
    (u0, u1, u2), (w0, w1, w2), (z0, z1, z2) = M
    dv0, dv1, dv2 = _floats(inc.dv_ahrs_n)                                    # sum R f dt
    if inc.dv_moment_n is None or inc.int_R_nb_moment is None:
        h = 0.5 * T
        Mq = [[h * v for v in r] for r in M]
        dq = (h * dv0, h * dv1, h * dv2)
    else:                                                 # sum R dt (T - t_mid), sum R f dt (T - t_mid)
        (a0, a1, a2), (e0, e1, e2), (d0, d1, d2) = _floats(inc.int_R_nb_moment)
        Mq = [[T * u0 - a0, T * u1 - a1, T * u2 - a2], [T * w0 - e0, T * w1 - e1, T * w2 - e2],
              [T * z0 - d0, T * z1 - d1, T * z2 - d2]]
        n0, n1, n2 = _floats(inc.dv_moment_n)
        dq = (T * dv0 - n0, T * dv1 - n1, T * dv2 - n2)
    if inc.dv_delay_n is None:
        return M, Mq, (dv0, dv1, dv2), dq, None, None
    k0, k1, k2 = _floats(inc.dv_delay_n)
    if inc.dv_delay_moment_n is None:
        j = (0.5 * T * k0, 0.5 * T * k1, 0.5 * T * k2)
    else:
        n0, n1, n2 = _floats(inc.dv_delay_moment_n)
        j = (T * k0 - n0, T * k1 - n1, T * k2 - n2)
    return M, Mq, (dv0, dv1, dv2), dq, (k0, k1, k2), j


def moments_of_sums(T: float, a: Sequence[float]) -> tuple[Any, ...]:
    """:func:`_moments` of the integrator's flat sums ``a`` over ``T`` seconds (:class:`fusion.imu.ImuIntegrator`:
    ``sum R f dt`` (3), ``sum R f dt t_mid`` (3), ``sum R dt`` (9, row by row), ``sum R dt t_mid`` (9),
    ``sum R (w x f) dt`` (3), ``sum R (w x f) dt t_mid`` (3)) without building an :class:`ImuIncrement`; the same
    arithmetic."""
    (dv0, dv1, dv2, n0, n1, n2, u0, u1, u2, w0, w1, w2, z0, z1, z2, a0, a1, a2, e0, e1, e2, d0, d1, d2,
     k0, k1, k2, j0, j1, j2) = a
    Mq = [[T * u0 - a0, T * u1 - a1, T * u2 - a2], [T * w0 - e0, T * w1 - e1, T * w2 - e2],
          [T * z0 - d0, T * z1 - d1, T * z2 - d2]]
    return ([[u0, u1, u2], [w0, w1, w2], [z0, z1, z2]], Mq, (dv0, dv1, dv2), (T * dv0 - n0, T * dv1 - n1, T * dv2 - n2),
            (k0, k1, k2), (T * k0 - j0, T * k1 - j1, T * k2 - j2))


def _propagate_into(x: Vec, T: float, moments: tuple[Any, ...], F: Mat, wind_decay: float = 1.0,
                    xl: list[float] | None = None, wind_d_decay: float = 1.0) -> Vec:
    """Mean propagation over ``T`` seconds of an increment's :func:`_moments`; returns the new state and writes the
    IMU-dependent entries of the Jacobian ``F = d x_new / d x`` into ``F`` (its other entries must be those of the
    identity).  ``xl``: ``x.tolist()`` when already at hand.  ``wind_decay``/``wind_d_decay``: the horizontal
    turbulence's and the vertical wind's decay over ``T`` (:class:`ProcessModel`).

    Scalar arithmetic on Python floats: the 3-vectors and 3 x 3 blocks here cost ~1-2 µs per NumPy call, and the
    floats go to NumPy with ``np.fromiter`` (a third of ``np.array``'s cost: no type discovery)."""
    ((u0, u1, u2), (w0, w1, w2), (z0, z1, z2)), ((a0, a1, a2), (e0, e1, e2), (d0, d1, d2)), dv, dq, k, j = moments
    xl = x.tolist() if xl is None else list(xl)
    b0, b1, b2 = xl[_BA0], xl[_BA0 + 1], xl[_BA0 + 2]
    m0 = dv[0] - (u0 * b0 + u1 * b1 + u2 * b2)            # sum R (f - b) dt
    m1 = dv[1] - (w0 * b0 + w1 * b1 + w2 * b2)
    m2 = dv[2] - (z0 * b0 + z1 * b1 + z2 * b2)
    q0 = dq[0] - (a0 * b0 + a1 * b1 + a2 * b2)            # sum R (f - b) dt (T - t_mid)
    q1 = dq[1] - (e0 * b0 + e1 * b1 + e2 * b2)
    q2 = dq[2] - (d0 * b0 + d1 * b1 + d2 * b2)
    # the AHRS delay: + tau sum R (omega x f) dt (and its position moment); the tau omega x b term is negligible
    if k is None or j is None:
        k = j = (0.0, 0.0, 0.0)
    else:
        tau = xl[_I_DELAY]
        m0, m1, m2 = m0 + tau * k[0], m1 + tau * k[1], m2 + tau * k[2]
        q0, q1, q2 = q0 + tau * j[0], q1 + tau * j[1], q2 + tau * j[2]
    yb = xl[_I_YAW]
    c, s = math.cos(yb), math.sin(yb)                     # R_z(-yaw_bias) = [[c, s], [-s, c]]
    mn, me = c * m0 + s * m1, -s * m0 + c * m1            # velocity change without gravity, N/E
    qn, qe = c * q0 + s * q1, -s * q0 + c * q1            # position change beyond v T, without gravity, N/E
    ip, iv = _POS0, _VEL0
    vn, ve, vd = xl[iv], xl[iv + 1], xl[iv + 2]
    xl[ip] += vn * T + qn
    xl[ip + 1] += ve * T + qe
    xl[ip + 2] += vd * T + q2 + _HALF_G * T * T
    xl[iv] = vn + mn
    xl[iv + 1] = ve + me
    xl[iv + 2] = vd + m2 + STANDARD_GRAVITY_M_S2 * T
    # -R_z(-yaw_bias) @ Mq (position rows; Mq = [a; e; d]) and -R_z(-yaw_bias) @ M (velocity rows; M = [u; w; z])
    F.reshape(-1)[_F_IMU] = np.fromiter((
        T, T, T,
        -(c * a0 + s * e0), -(c * a1 + s * e1), -(c * a2 + s * e2),
        s * a0 - c * e0, s * a1 - c * e1, s * a2 - c * e2,
        -d0, -d1, -d2,
        -(c * u0 + s * w0), -(c * u1 + s * w1), -(c * u2 + s * w2),
        s * u0 - c * w0, s * u1 - c * w1, s * u2 - c * w2,
        -z0, -z1, -z2,
        qe, -qn, me, -mn,                                 # d R_z(-b) u / d b = (u_E', -u_N') of the rotated u
        c * j[0] + s * j[1], -s * j[0] + c * j[1], j[2],  # d pos / d att_delay = R_z(-b) sum R (w x f) dt (T - t)
        c * k[0] + s * k[1], -s * k[0] + c * k[1], k[2],  # d vel / d att_delay = R_z(-b) sum R (w x f) dt
    ), float, _N_F_IMU)
    if wind_decay != 1.0:                                 # turbulence relaxing to the mean (see ProcessModel)
        iw, im = _WN, _MN
        xl[iw] = wind_decay * xl[iw] + (1.0 - wind_decay) * xl[im]
        xl[iw + 1] = wind_decay * xl[iw + 1] + (1.0 - wind_decay) * xl[im + 1]
    if wind_d_decay != 1.0:
        xl[_I_WD] *= wind_d_decay
    return np.fromiter(xl, float, S.dim)


def propagate(x: Vec, inc: ImuIncrement) -> tuple[Vec, Mat]:
    """Mean propagation over one increment and its Jacobian ``F = d x_new / d x`` (n x n)."""
    F = _EYE.copy()
    return _propagate_into(x, inc.dt_s, _moments(inc), F), F


_NoiseTerms = tuple[Mat, float, float, float, float, float, float]


class ProcessModel:
    """``x' = f(x, increment)``, ``F`` and ``Q`` for one prediction, with the in-flight turbulence level.

    :meth:`step` gives the new mean, ``Q`` and the per-prediction diagonal noise of the turbulence (added after the
    core's symmetrised ``F P F' + Q``); ``F`` is one preallocated matrix whose IMU-dependent and wind entries are
    written in place (the rest stays the identity)."""

    def __init__(self, cfg: EkfConfig) -> None:
        self._cfg = cfg
        self.F = np.eye(S.dim)
        self._q_cache: dict[int, _NoiseTerms] = {}
        self._decay = 1.0                  # the wind turbulence's decay over the current prediction
        self._decay_wd = 1.0               # the vertical wind's decay over the current prediction
        self._wd_ratio2 = cfg.wind.vertical_sigma_ratio**2    # vertical / horizontal turbulence variance
        #: the turbulence variance in use (m^2/s^2 per axis): ``wind.turb_sigma_m_s^2``, adapted (see step)
        self.turb_var = cfg.wind.turb_sigma_m_s**2
        self._turb_var_lo = cfg.wind.turb_sigma_min_m_s**2
        self._turb_var_hi = cfg.wind.turb_sigma_max_m_s**2
        self._adapting = cfg.wind.turb_adapt_time_s > 0.0          # (read once: this runs at every prediction)
        self._adapt_var_weight = cfg.wind.turb_adapt_var_weight
        rw = np.zeros(S.dim)               # random-walk variance rates of the slow states (per second)
        p = cfg.process
        for name, q in (("wind_mean_ne", cfg.wind.mean_rw_m_s_per_rt_s), ("wind_ne", cfg.wind.mean_rw_m_s_per_rt_s),
                        ("accel_bias_b", p.accel_bias_rw_m_s2_per_rt_s), ("yaw_bias", p.yaw_bias_rw_rad_per_rt_s),
                        ("opt_rot", p.opt_rot_rw_rad_per_rt_s), ("baro_bias", p.baro_bias_rw_m_per_rt_s),
                        ("terrain_h", p.terrain_rw_m_per_rt_s), ("tas_scale", p.tas_scale_rw_per_rt_s),
                        ("att_delay", p.att_delay_rw_s_per_rt_s), ("side_force_ofs", p.side_force_ofs_rw_m_s2_per_rt_s),
                        ("aoa_ofs", p.aoa_ofs_rw_rad_per_rt_s)):
            rw[getattr(S, name)] = q * q
        self._rw_var_rate = rw

    def process_noise(self, dt_s: float) -> Mat:
        """``Q`` over a prediction of ``dt_s`` with the turbulence variance now in use."""
        Q, _, g, _, _, _, g_w = self._noise_and_decay(dt_s)
        Q = Q.copy()
        Q.flat[_Q_WW] += self.turb_var * g
        Q[_I_WD, _I_WD] += self._wd_ratio2 * self.turb_var * g_w
        return Q

    def _noise_and_decay(self, dt_s: float) -> _NoiseTerms:
        """``Q`` without the turbulence's own term, the turbulence decay ``e = exp(-dt / tau)``, ``1 - e^2``, the
        adaptation's decay ``a = exp(-dt / A)`` (``A = wind.turb_adapt_time_s``; 1 when not adapting),
        ``c = (2 / tau) / (2 / tau - 1 / A) (a - e^2)``, the vertical wind's decay ``e_w = exp(-dt / tau_w)`` and
        ``1 - e_w^2`` over a prediction of ``dt_s`` (cached per length).

        Wind: ``wind = mean + turb``, the mean a random walk (rate ``q``), the turbulence first-order Gauss-Markov
        (``sigma``, ``tau``), so over ``dt`` ``Q_mean = q dt``, ``Q_wind = q dt + sigma^2 (1 - e^2)`` and
        ``Q_wind,mean = q dt`` (the mean's walk moves the total wind as well).  The ``sigma^2 (1 - e^2)`` term is
        added after the covariance prediction (``sigma`` may adapt)."""
        key = round(dt_s * US_PER_S)
        hit = self._q_cache.get(key)
        if hit is not None:
            return hit
        cfg = self._cfg
        Q = np.diag(self._rw_var_rate * dt_s)
        qpv = Q_continuous_white_noise(dim=2, dt=dt_s, spectral_density=cfg.process.accel_noise_m_s2_per_rt_hz**2)
        Q.flat[_Q_PP], Q.flat[_Q_PV], Q.flat[_Q_VP], Q.flat[_Q_VV] = qpv[0, 0], qpv[0, 1], qpv[1, 0], qpv[1, 1]
        decay = math.exp(-dt_s / cfg.wind.turb_corr_time_s)
        q_mean = cfg.wind.mean_rw_m_s_per_rt_s**2 * dt_s
        Q.flat[_Q_WW] = Q.flat[_Q_WM] = Q.flat[_Q_MW] = q_mean
        tau, adapt = cfg.wind.turb_corr_time_s, cfg.wind.turb_adapt_time_s
        e2 = math.exp(-2.0 * dt_s / tau)
        if adapt > 0.0:
            a = math.exp(-dt_s / adapt)
            k = 2.0 / tau - 1.0 / adapt
            # int_0^dt exp(-t / A) (2 / tau) exp(-2 (dt - t) / tau) dt (its limit where 2 / tau = 1 / A)
            c = (2.0 / tau) * (a - e2) / k if abs(k * dt_s) > 1e-9 else (2.0 * dt_s / tau) * e2
        else:
            a, c = 1.0, 0.0
        if len(self._q_cache) >= Q_CACHE_MAX:
            self._q_cache.clear()
        Q.flags.writeable = False
        tau_w = cfg.wind.vertical_corr_time_s
        hit = self._q_cache[key] = (Q, decay, -math.expm1(-2.0 * dt_s / tau), a, c, math.exp(-dt_s / tau_w),
                                    -math.expm1(-2.0 * dt_s / tau_w))
        return hit

    def _adapt_turbulence(self, x: Vec, P: Mat, g: float, a: float, c: float, xl: list[float] | None = None) -> float:
        """Move the turbulence variance in use over one prediction; returns the turbulence's noise over it.

        Turbulence intensity: E[d^2] of the estimated turbulence d = wind - mean (its square plus
        ``wind.turb_adapt_var_weight`` of its variance from P), per axis, averaged over the adaptation time A
        (exponentially), within [sigma_min, sigma_max]^2; the measurements behind the weight are in
        docs/ekf-tuning.md.  Over the prediction the variance moves as v(t) = d2 + (v0 - d2) exp(-t / A), and the
        noise is the exact integral of v(t) (2 / tau) exp(-2 (dt - t) / tau): d2 (1 - e^2) + (v0 - d2) c, so the
        result does not depend on the prediction rate."""
        v0 = self.turb_var
        if not self._adapting:
            return v0 * g
        if xl is None:
            wn, we, mn, me = x.take(_X_TURB).tolist()
        else:
            wn, we, mn, me = xl[_WN], xl[_WE], xl[_MN], xl[_ME]
        ann, anm, amm, aee, aem, bmm = P.take(_P_TURB).tolist()
        dn, de = wn - mn, we - me
        d2 = 0.5 * (dn * dn + de * de + self._adapt_var_weight * (ann - 2.0 * anm + amm + aee - 2.0 * aem + bmm))
        self.turb_var = min(self._turb_var_hi, max(self._turb_var_lo, d2 + (v0 - d2) * a))
        return d2 * g + (v0 - d2) * c

    def step(self, x: Vec, P: Mat, inc: ImuIncrement) -> tuple[Vec, Mat, tuple[tuple[int, float], ...]]:
        """One prediction's mean, ``Q`` and the diagonal noise added after ``F P F' + Q`` (index, variance);
        :attr:`F` is left at the prior state's Jacobian."""
        return self._step(x, P, inc.dt_s, _moments(inc))

    def step_sums(self, x: Vec, P: Mat, dt_s: float, sums: Sequence[float]
                  ) -> tuple[Vec, Mat, tuple[tuple[int, float], ...]]:
        """:meth:`step` over ``dt_s`` from the integrator's flat sums (:func:`moments_of_sums`)."""
        return self._step(x, P, dt_s, moments_of_sums(dt_s, sums))

    def _step(self, x: Vec, P: Mat, dt_s: float, moments: tuple[Any, ...]
              ) -> tuple[Vec, Mat, tuple[tuple[int, float], ...]]:
        Q, e, g, a, c, e_w, g_w = self._noise_and_decay(dt_s)
        xl = x.tolist()
        q_turb = self._adapt_turbulence(x, P, g, a, c, xl)
        # the vertical wind's turbulence (sigma a fixed ratio of the horizontal one's in use)
        q_wd = self._wd_ratio2 * self.turb_var * g_w
        # the turbulence relaxes towards the mean: wind' = e wind + (1 - e) mean; the vertical wind towards 0
        x_new = _propagate_into(x, dt_s, moments, self.F, e, xl, e_w)
        if e != self._decay:
            self.F.flat[_F_WIND] = (e, e, 1.0 - e, 1.0 - e)
            self._decay = e
        if e_w != self._decay_wd:
            self.F.flat[_F_WD] = e_w
            self._decay_wd = e_w
        iw = _I_WIND[0]
        return x_new, Q, ((iw, q_turb), (iw + 1, q_turb), (_I_WD, q_wd))


def initial_variances(cfg: EkfConfig) -> Vec:
    """Diagonal of the initial covariance (also what a covariance reset restores)."""
    c = cfg.init
    var = np.zeros(S.dim)
    for fields, sigma in (
            (("pos_ne", "base_pos_ne"), c.pos_ne_sigma_m), (("pos_d", "base_pos_d"), c.pos_d_sigma_m),
            (("vel_ne",), c.vel_ne_sigma_m_s), (("vel_d",), c.vel_d_sigma_m_s),
            (("wind_ne", "wind_mean_ne"), c.wind_sigma_m_s),
            (("wind_d",), cfg.wind.vertical_sigma_ratio * cfg.wind.turb_sigma_m_s),  # stationary turbulence
            (("accel_bias_b",), c.accel_bias_sigma_m_s2), (("yaw_bias",), c.yaw_bias_sigma_rad),
            (("opt_rot",), c.opt_rot_sigma_rad), (("baro_bias",), c.baro_bias_sigma_m),
            (("terrain_h",), c.terrain_sigma_m), (("tas_scale",), c.tas_scale_sigma),
            (("att_delay",), c.att_delay_sigma_s), (("side_force_ofs",), c.side_force_ofs_sigma_m_s2),
            (("aoa_ofs",), c.aoa_ofs_sigma_rad)):
        for name in fields:
            var[getattr(S, name)] = sigma**2
    return var


def initial_covariance(cfg: EkfConfig, init_var: Vec) -> Mat:
    """The initial ``P``: independent states, except the total wind (mean plus independent turbulence, so
    ``cov(wind, mean) = var(mean)``) and the clone (a copy of the position)."""
    P0 = np.diag(init_var)
    P0[_I_WIND, _I_WMEAN] = P0[_I_WMEAN, _I_WIND] = init_var[_I_WMEAN]
    P0[_I_WIND, _I_WIND] += cfg.wind.turb_sigma_m_s**2
    P0[np.ix_(_I_CLONE, _I_POS)] = P0[np.ix_(_I_POS, _I_POS)]
    P0[np.ix_(_I_POS, _I_CLONE)] = P0[np.ix_(_I_POS, _I_POS)]
    return P0
