"""The filter's output: :class:`NavEstimate`, derived from the state with first-order uncertainties."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.angles import angle_diff, wrap_2pi
from common.samples import AttitudeSample
from fusion.config import EkfConfig
from fusion.process import S_PER_US, US_PER_S, yaw_rate
from fusion.state import S
from fusion.status import REASON_NO_ATTITUDE

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

_I_YAW, _I_DELAY, _I_WD = S.yaw_bias.start, S.att_delay.start, S.wind_d.start
_IX_PVW = np.ix_(S.idx("pos_ne", "vel_ne", "wind_ne"), S.idx("pos_ne", "vel_ne", "wind_ne"))
# flat indices of the covariance entries the output reads, in order: velocity N/E (nn, ne, ee), yaw bias (yy,
# vel_n-yaw, vel_e-yaw), wind (nn, ne, ee), down position, terrain, down position-terrain, AHRS delay (dd, yaw-delay,
# vel_n-delay, vel_e-delay)
_EST_FLAT = np.ravel_multi_index(tuple(np.array([
    (S.vel_ne.start, S.vel_ne.start), (S.vel_ne.start, S.vel_ne.start + 1), (S.vel_ne.start + 1, S.vel_ne.start + 1),
    (_I_YAW, _I_YAW), (S.vel_ne.start, _I_YAW), (S.vel_ne.start + 1, _I_YAW),
    (S.wind_ne.start, S.wind_ne.start), (S.wind_ne.start, S.wind_ne.start + 1),
    (S.wind_ne.start + 1, S.wind_ne.start + 1),
    (S.pos_d.start, S.pos_d.start), (S.terrain_h.start, S.terrain_h.start), (S.pos_d.start, S.terrain_h.start),
    (_I_DELAY, _I_DELAY), (_I_YAW, _I_DELAY), (S.vel_ne.start, _I_DELAY), (S.vel_ne.start + 1, _I_DELAY),
]).T), (S.dim, S.dim))


@dataclass(frozen=True, slots=True)
class NavEstimate:
    """The filter's output at ``t_us`` (the fusion horizon), with one-sigma uncertainties.

    Positions in the local NED frame (m); ``height_m`` above the reference ground, ``height_agl_m`` above the ground
    under the aircraft.  Velocities are ground velocities (m/s).  Angles in radians, clockwise from north:
    ``course_rad`` (of the ground velocity, [0, 2 pi)), ``heading_rad`` (AHRS yaw corrected by the estimated
    heading error and, with the yaw rate, by the estimated AHRS delay), ``drift_rad`` = course - heading in
    [-pi, pi) (positive: track to the right of the heading), ``ata_rad`` = the paper's eq. 12 actual tracking angle
    ``beta + psi + drift``, i.e. the EKF's course over ground.  ``wind_ne_m_s`` is the velocity of the air (blowing
    *to*); ``wind_from_rad`` the direction it blows *from* (MAVLink WIND); ``wind_d_m_s`` the vertical wind (down
    positive, turbulence: :mod:`fusion.state`).  Angle sigmas are capped at pi where the angle is undefined (speed
    near zero).
    ``yaw_bias_rad``, ``opt_rot_rad``, ``baro_bias_m``, ``terrain_h_m``, ``tas_scale``, ``accel_bias_b_m_s2``,
    ``side_force_ofs_m_s2``, ``aoa_ofs_rad``: the calibration states (:mod:`fusion.state`).
    ``wind_turb_sigma_m_s``: the
    turbulence level the wind model uses now (per axis, adapted in flight).  ``cov_pvw`` is the 6x6 covariance of
    ``[pos_ne, vel_ne, wind_ne]`` (for NEES).  ``valid`` is false with ``invalid_reason`` when the output should not
    be used (see :class:`~fusion.config.EkfConfig`).
    """

    t_us: int
    pos_ne_m: Vec
    pos_ne_sigma_m: Vec
    height_m: float
    height_sigma_m: float
    height_agl_m: float
    height_agl_sigma_m: float
    vel_ned_m_s: Vec
    vel_ned_sigma_m_s: Vec
    ground_speed_m_s: float
    ground_speed_sigma_m_s: float
    course_rad: float
    course_sigma_rad: float
    wind_ne_m_s: Vec
    wind_ne_sigma_m_s: Vec
    wind_speed_m_s: float
    wind_speed_sigma_m_s: float
    wind_from_rad: float
    wind_from_sigma_rad: float
    wind_d_m_s: float
    wind_d_sigma_m_s: float
    heading_rad: float
    heading_sigma_rad: float
    drift_rad: float
    drift_sigma_rad: float
    ata_rad: float
    ata_sigma_rad: float
    accel_bias_b_m_s2: Vec
    yaw_bias_rad: float
    opt_rot_rad: float
    baro_bias_m: float
    terrain_h_m: float
    tas_scale: float
    side_force_ofs_m_s2: float
    aoa_ofs_rad: float
    wind_turb_sigma_m_s: float
    cov_pvw: Mat
    valid: bool
    invalid_reason: str = ""
    opt_rot_sigma_rad: float = math.nan     #: one-sigma of ``opt_rot_rad`` (what a camera-mount calibration reads)

    def as_record(self) -> dict[str, Any]:
        """Flat record for ``ekf.csv`` (unit suffixes in the column names)."""
        r: dict[str, Any] = {"t_us": self.t_us}
        for i, ax in enumerate("ne"):
            r[f"pos_{ax}_m"] = float(self.pos_ne_m[i])
            r[f"pos_{ax}_sigma_m"] = float(self.pos_ne_sigma_m[i])
        r.update(height_m=self.height_m, height_sigma_m=self.height_sigma_m, height_agl_m=self.height_agl_m,
                 height_agl_sigma_m=self.height_agl_sigma_m)
        for i, ax in enumerate("ned"):
            r[f"vel_{ax}_m_s"] = float(self.vel_ned_m_s[i])
            r[f"vel_{ax}_sigma_m_s"] = float(self.vel_ned_sigma_m_s[i])
        for i, ax in enumerate("ne"):
            r[f"wind_{ax}_m_s"] = float(self.wind_ne_m_s[i])
            r[f"wind_{ax}_sigma_m_s"] = float(self.wind_ne_sigma_m_s[i])
        r.update(
            ground_speed_m_s=self.ground_speed_m_s, ground_speed_sigma_m_s=self.ground_speed_sigma_m_s,
            course_rad=self.course_rad, course_sigma_rad=self.course_sigma_rad,
            wind_speed_m_s=self.wind_speed_m_s, wind_speed_sigma_m_s=self.wind_speed_sigma_m_s,
            wind_from_rad=self.wind_from_rad, wind_from_sigma_rad=self.wind_from_sigma_rad,
            wind_d_m_s=self.wind_d_m_s, wind_d_sigma_m_s=self.wind_d_sigma_m_s,
            heading_rad=self.heading_rad, heading_sigma_rad=self.heading_sigma_rad,
            drift_rad=self.drift_rad, drift_sigma_rad=self.drift_sigma_rad,
            ata_rad=self.ata_rad, ata_sigma_rad=self.ata_sigma_rad,
            accel_bias_x_m_s2=float(self.accel_bias_b_m_s2[0]), accel_bias_y_m_s2=float(self.accel_bias_b_m_s2[1]),
            accel_bias_z_m_s2=float(self.accel_bias_b_m_s2[2]), yaw_bias_rad=self.yaw_bias_rad,
            opt_rot_rad=self.opt_rot_rad, opt_rot_sigma_rad=self.opt_rot_sigma_rad,
            baro_bias_m=self.baro_bias_m, terrain_h_m=self.terrain_h_m, tas_scale=self.tas_scale,
            side_force_ofs_m_s2=self.side_force_ofs_m_s2, aoa_ofs_rad=self.aoa_ofs_rad,
            wind_turb_sigma_m_s=self.wind_turb_sigma_m_s,
            valid=self.valid, invalid_reason=self.invalid_reason,
        )
        return r


def _read_only(a: Vec) -> Vec:
    a.flags.writeable = False
    return a


def _polar(n: float, e: float, pnn: float, pne: float, pee: float) -> tuple[float, float, float, float, float]:
    """Speed and its sigma, the angle ``atan2(e, n)`` and its variance, from a N/E vector and its covariance; also
    the angle's gradient w.r.t. ``(n, e)``, ``(-e, n) / speed^2`` (zero, and the variance inf, at zero speed)."""
    sp = math.hypot(n, e)
    if sp > 0.0:
        gn, ge = -e / (sp * sp), n / (sp * sp)
        var_a = gn * gn * pnn + 2.0 * gn * ge * pne + ge * ge * pee
        return sp, math.sqrt(max((n * n * pnn + 2.0 * n * e * pne + e * e * pee) / (sp * sp), 0.0)), var_a, gn, ge
    return sp, math.sqrt(max((pnn + pee) / 2.0, 0.0)), math.inf, 0.0, 0.0


def _heading(att: AttitudeSample | None, rates_b: tuple[float, float, float], yb: float, tau: float, course: float,
             gs: float, gn: float, ge: float, var_c: float, p: tuple[float, ...], t_us: int
             ) -> tuple[float, float, float, float]:
    """Heading at ``t_us`` ``yaw_ahrs - yaw_bias + yaw_rate * (att_delay + t_us - t_att)`` (the AHRS heading lags
    the turn by the delay; the attitude is the last IMU sample's, stamped ``t_att``, which may be ahead of the
    state's time), the drift ``course - heading`` and their sigmas; ``p`` = (yy, vel_n-yaw, vel_e-yaw, dd,
    yaw-delay, vel_n-delay, vel_e-delay) of ``P``."""
    if att is None:
        return math.nan, math.pi, math.nan, math.pi
    pyy, pny, pey, pdd_t, pyd, pnd, ped = p
    rate = yaw_rate(att, rates_b)
    heading = float(wrap_2pi(att.yaw_rad - yb + rate * (tau + (t_us - att.t_us) * S_PER_US)))
    drift = float(angle_diff(course, heading))
    var_h = pyy - 2.0 * rate * pyd + rate * rate * pdd_t
    # d drift / d (vel_n, vel_e, yaw_bias, att_delay) = (gn, ge, 1, -rate)
    var_d = var_c + var_h + 2.0 * (gn * pny + ge * pey) - 2.0 * rate * (gn * pnd + ge * ped)
    drift_sd = min(math.pi, math.sqrt(max(var_d, 0.0))) if gs > 0.0 else math.pi
    return heading, math.sqrt(max(var_h, 0.0)), drift, drift_sd


def validity(cfg: EkfConfig, has_att: bool, vel_sd_max: float, gs: float, drift_sd: float, t_us: int,
             last_aid_fuse_us: int) -> tuple[bool, str]:
    """Whether the output may be used, and why not (:class:`~fusion.config.EkfConfig`, validity)."""
    c = cfg
    if not has_att:
        return False, REASON_NO_ATTITUDE
    if vel_sd_max > c.validity.vel_sigma_max_m_s:
        return False, "velocity sigma above valid_vel_sigma_max_m_s"
    if gs < c.validity.min_ground_speed_m_s:
        return False, "ground speed below valid_min_ground_speed_m_s"
    if drift_sd > c.validity.drift_sigma_max_rad:
        return False, "drift sigma above valid_drift_sigma_max_deg"
    if last_aid_fuse_us < 0 or t_us - last_aid_fuse_us > c.validity.aid_timeout_s * US_PER_S:
        return False, "no optical or GNSS fused within valid_aid_timeout_s"
    return True, ""


def make_estimate(cfg: EkfConfig, x: Vec, P: Mat, t_us: int, att: AttitudeSample | None,
                  rates_b: tuple[float, float, float], turb_var: float, *, has_att: bool,
                  last_aid_fuse_us: int) -> NavEstimate:
    """The output at ``t_us`` from the state ``x``, ``P``, the attitude for the heading ``att`` with the body rates,
    and the turbulence variance in use; validity from the config, the processed attitude and the last aid fused."""
    xl = x.tolist()
    xr = _read_only(x.copy())                  # the output's vectors are read-only views of this copy
    sd = _read_only(np.sqrt(np.maximum(P.diagonal(), 0.0)))
    (pnn, pne, pee, pyy, pny, pey, qnn, qne, qee, pdd, ptt, pdt, pdd_t, pyd, pnd, ped) = P.take(_EST_FLAT).tolist()
    iv, iw = S.vel_ne.start, S.wind_ne.start
    gs, gs_sd, var_c, gn, ge = _polar(xl[iv], xl[iv + 1], pnn, pne, pee)
    course = float(wrap_2pi(math.atan2(xl[iv + 1], xl[iv])))
    course_sd = min(math.pi, math.sqrt(max(var_c, 0.0)))
    yb, tau = xl[_I_YAW], xl[_I_DELAY]
    heading, heading_sd, drift, drift_sd = _heading(att, rates_b, yb, tau, course, gs, gn, ge, var_c,
                                                    (pyy, pny, pey, pdd_t, pyd, pnd, ped), t_us)
    # wind speed and the direction it blows from: atan2(-we, -wn) (the gradient's sign does not change the variance)
    ws, ws_sd, var_w, _, _ = _polar(xl[iw], xl[iw + 1], qnn, qne, qee)
    wd_sd = min(math.pi, math.sqrt(max(var_w, 0.0))) if ws > 0.0 else math.pi
    ipd, ith = S.pos_d.start, S.terrain_h.start
    ok, why = validity(cfg, has_att, math.sqrt(max(pnn, pee, 0.0)), gs, drift_sd, t_us, last_aid_fuse_us)
    return NavEstimate(
        t_us=t_us,
        pos_ne_m=xr[S.pos_ne], pos_ne_sigma_m=sd[S.pos_ne],
        height_m=-xl[ipd], height_sigma_m=math.sqrt(max(pdd, 0.0)),
        height_agl_m=-xl[ipd] - xl[ith], height_agl_sigma_m=math.sqrt(max(pdd + ptt + 2.0 * pdt, 0.0)),
        vel_ned_m_s=xr[S.vel_ned], vel_ned_sigma_m_s=sd[S.vel_ned],
        ground_speed_m_s=gs, ground_speed_sigma_m_s=gs_sd,
        course_rad=course, course_sigma_rad=course_sd,
        wind_ne_m_s=xr[S.wind_ne], wind_ne_sigma_m_s=sd[S.wind_ne],
        wind_speed_m_s=ws, wind_speed_sigma_m_s=ws_sd,
        wind_from_rad=float(wrap_2pi(math.atan2(-xl[iw + 1], -xl[iw]))), wind_from_sigma_rad=wd_sd,
        wind_d_m_s=xl[_I_WD], wind_d_sigma_m_s=float(sd[_I_WD]),
        heading_rad=heading, heading_sigma_rad=heading_sd,
        drift_rad=drift, drift_sigma_rad=drift_sd,
        ata_rad=course, ata_sigma_rad=course_sd,
        accel_bias_b_m_s2=xr[S.accel_bias_b], yaw_bias_rad=yb, opt_rot_rad=xl[S.opt_rot.start],
        baro_bias_m=xl[S.baro_bias.start],
        terrain_h_m=xl[ith], tas_scale=xl[S.tas_scale.start], side_force_ofs_m_s2=xl[S.side_force_ofs.start],
        aoa_ofs_rad=xl[S.aoa_ofs.start], wind_turb_sigma_m_s=math.sqrt(turb_var),
        cov_pvw=_read_only(P[_IX_PVW]),
        valid=ok, invalid_reason=why, opt_rot_sigma_rad=float(sd[S.opt_rot.start]),
    )
