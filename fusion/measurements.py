"""Measurement models of the navigation EKF, one small class each (STYLE section 4).

Every model has ``predict(x) -> z_hat`` (shape ``(m,)``), ``jacobian(x) -> H`` (analytic, shape ``(m, n)``),
``linearise(x) -> (z_hat, H)`` (both at once, sharing the work; what the EKF calls) and ``noise(...) -> R`` (shape
``(m, m)``).  The scalar models also have ``row(x) -> (z_hat, h)`` (a float and the ``(n,)`` Jacobian row), the
EKF's per-sample path: the state is read once as Python floats (``x.tolist()``), since arithmetic on NumPy scalars
costs several times more.  ``x`` is the state vector laid out by :data:`fusion.state.S`; frames and
units as in :mod:`gsoe` (NED, FRD, SI, radians).  Per-measurement context (the camera's focal length, the AHRS
attitude, which axes a GNSS fix has) is given when the model is built, so a model is a pure function of the state.
The tests check every ``jacobian`` against finite differences of ``predict``.

Heading: the state's ``yaw_bias`` is ``yaw_ahrs - yaw_true``, so a heading reported by the AHRS (or a
:class:`GsoeStep`'s ``base_yaw_rad``, which comes from it) is corrected as ``yaw_true = yaw - yaw_bias``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from common.samples import GsoeStep
from fusion.config import EkfConfig
from fusion.state import S

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

#: Air-relative speed (m/s) below which the airspeed and sideslip models are not evaluated (their Jacobians divide
#: by it); the EKF never fuses airspeed below ``EkfConfig.tas_min_m_s``, which must be larger.
MIN_AIR_SPEED_M_S = 0.5


class MeasurementModel(Protocol):
    """What the EKF needs from a measurement model."""

    def predict(self, x: Vec) -> Vec: ...

    def jacobian(self, x: Vec) -> Mat: ...

    def linearise(self, x: Vec) -> tuple[Vec, Mat]: ...


# Scalar indices derived from the layout (the models run at IMU/camera rate; scalar indexing is the cheap path).
_N, _E = S.pos_ne.start, S.pos_ne.start + 1
_BN, _BE, _BD = S.base_pos_ne.start, S.base_pos_ne.start + 1, S.base_pos_d.start
_VN, _VE, _VD = S.vel_ne.start, S.vel_ne.start + 1, S.vel_d.start
_WN, _WE = S.wind_ne.start, S.wind_ne.start + 1
_WD = S.wind_d.start
_PD, _YB, _BB, _TH, _TS = S.pos_d.start, S.yaw_bias.start, S.baro_bias.start, S.terrain_h.start, S.tas_scale.start
_OR = S.opt_rot.start
_BAY = S.accel_bias_b.start + 1
_SFO = S.side_force_ofs.start
_BAZ = S.accel_bias_b.start + 2
_AOF = S.aoa_ofs.start
# the same indices in the second row of a flattened 2 x n Jacobian
_N2, _E2, _BN2, _BE2, _BD2, _TH2, _YB2, _OR2 = (S.dim + i for i in (_N, _E, _BN, _BE, _BD, _TH, _YB, _OR))


# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class OpticalDisplacement:
    """The template's accumulated migration ``[dx_px, dy_px]`` since the cycle's base snapshot.

    The position change since the base snapshot, ``pos_ne - base_pos_ne`` (the clone), rotated into the cycle's
    stabilised frame (cross track to the right, along track forward of ``psi = base_yaw_rad - yaw_bias + opt_rot``)
    and divided by the base image's ground sample distance ``h_base / focal_px`` with
    ``h_base = -base_pos_d - terrain_h`` (height above the ground at the base snapshot)::

        dx_px = focal_px * (-sin(psi) dN + cos(psi) dE) / h_base
        dy_px = focal_px * ( cos(psi) dN + sin(psi) dE) / h_base

    Parameters: ``focal_px`` (the virtual nadir camera's focal length, px) and ``base_yaw_rad`` (the AHRS heading
    the cycle's stabilised frame was built with, rad).  The stabilised image is de-rotated with the same attitude
    it is labelled with, so an AHRS heading error shows only in the label (``- yaw_bias``); ``opt_rot`` is what the
    optical estimator's own attitude adds (gyro bias in its relative rotation, see :mod:`fusion.state`).
    """

    focal_px: float
    base_yaw_rad: float

    def _parts(self, x: Vec) -> tuple[float, float, float, float, float, float]:
        xl = x.tolist()
        psi = self.base_yaw_rad - xl[_YB] + xl[_OR]
        c, s = math.cos(psi), math.sin(psi)
        dn, de = xl[_N] - xl[_BN], xl[_E] - xl[_BE]
        along = c * dn + s * de
        cross = -s * dn + c * de
        h = -xl[_BD] - xl[_TH]
        return c, s, along, cross, h, self.focal_px / h

    def height_base_m(self, x: Vec) -> float:
        """Height above ground at the base snapshot according to ``x`` (m)."""
        return float(-x[_BD] - x[_TH])

    def predict(self, x: Vec) -> Vec:
        _, _, along, cross, _, k = self._parts(x)
        return np.array([k * cross, k * along])

    def jacobian(self, x: Vec) -> Mat:
        return self.linearise(x)[1]

    def linearise(self, x: Vec) -> tuple[Vec, Mat]:
        c, s, along, cross, h, k = self._parts(x)
        zx_h, zy_h = k * cross / h, k * along / h        # d z / d h_base = -z / h, and d h_base / d(.) = -1
        ks, kc = k * s, k * c
        H = np.zeros(2 * S.dim)                           # row-major 2 x n, filled element by element (cheapest)
        H[_N], H[_E], H[_BN], H[_BE] = -ks, kc, ks, -kc                       # row 0 (dx_px)
        H[_BD] = H[_TH] = zx_h
        H[_YB], H[_OR] = k * along, -k * along                                # d psi / d yaw_bias = -1, opt_rot = +1
        H[_N2], H[_E2], H[_BN2], H[_BE2] = kc, ks, -kc, -ks                   # row 1 (dy_px)
        H[_BD2] = H[_TH2] = zy_h
        H[_YB2], H[_OR2] = -k * cross, k * cross
        return np.array([k * cross, k * along]), H.reshape(2, S.dim)

    def base_from_step(self, x: Vec, z_px: Vec) -> tuple[Vec, Mat, Mat]:
        """The inverse model, for a cycle whose base time was missed: the base position ``[N, E, D]`` implied by the
        current state and a step ``z_px = [dx_px, dy_px]``, ``pos_ne - (h / f) R(psi) [dy, dx]`` with the height now
        standing for the height then (``base_pos_d = pos_d``), and its Jacobians w.r.t. the state (3 x n) and
        w.r.t. ``z_px`` (3 x 2)."""
        psi = self.base_yaw_rad - x[_YB] + x[_OR]
        c, s = math.cos(psi), math.sin(psi)
        dx, dy = float(z_px[0]), float(z_px[1])
        uN, uE = c * dy - s * dx, s * dy + c * dx          # the pixel displacement rotated to north/east
        f = self.focal_px
        k = (-x[_PD] - x[_TH]) / f
        base = np.array([x[_N] - k * uN, x[_E] - k * uE, x[_PD]])
        J = np.zeros((3, S.dim))
        J[0, _N] = J[1, _E] = J[2, _PD] = 1.0
        J[0, _PD] = J[0, _TH] = uN / f                       # d(-k)/d(pos_d) = d(-k)/d(terrain_h) = 1/f
        J[1, _PD] = J[1, _TH] = uE / f
        J[0, _YB], J[1, _YB] = -k * uE, k * uN               # d psi / d yaw_bias = -1
        J[0, _OR], J[1, _OR] = k * uE, -k * uN               # d psi / d opt_rot = +1
        Kz = np.array([[k * s, -k * c], [-k * c, -k * s], [0.0, 0.0]])
        return base, J, Kz

    @staticmethod
    def noise_sigma_px(step: GsoeStep, cfg: EkfConfig) -> tuple[float, float]:
        """(matcher sigma, attitude-induced sigma) in px for one step.

        Matcher: ``optical_match_sigma_px / q`` with the quality ``q = clip(psr / optical_psr_ref,
        optical_quality_floor, 1)`` (a non-finite PSR counts as the floor), or ``optical_ssd_sigma_factor`` times the
        match's own SSD precision ``quality.match_sigma_px`` where that is larger.  Attitude: ``focal_px`` times the
        relative attitude error between base and current frame, ``optical_att_rel_sigma_rad +
        optical_att_rel_sigma_per_rad * rel_rot_rad + optical_att_rel_sigma_rad_per_s * (t - base_t)``
        (independent of altitude: an angle error moves the image by ``f * angle`` pixels at any height).
        """
        psr = step.quality.psr
        q = psr / cfg.optical_psr_ref if not math.isnan(psr) else 0.0
        q = min(1.0, max(cfg.optical_quality_floor, q))
        rel = step.rel_rot_rad if math.isfinite(step.rel_rot_rad) else cfg.optical_rel_rot_fallback_rad
        elapsed_s = max(0, step.t_us - step.base_t_us) * 1e-6
        att_rad = (cfg.optical_att_rel_sigma_rad + cfg.optical_att_rel_sigma_per_rad * abs(rel)
                   + cfg.optical_att_rel_sigma_rad_per_s * elapsed_s)
        match = cfg.optical_match_sigma_px / q
        ssd = cfg.optical_ssd_sigma_factor * step.quality.match_sigma_px
        if ssd > match:                                   # False for nan (no SSD precision: the PSR model alone)
            match = ssd
        return match, step.focal_px * att_rad

    @staticmethod
    def noise_var_px2(step: GsoeStep, cfg: EkfConfig) -> float:
        """Variance (px^2) of each of ``dx_px``, ``dy_px`` (uncorrelated): matcher plus attitude-induced error."""
        m, a = OpticalDisplacement.noise_sigma_px(step, cfg)
        return m * m + a * a

    @staticmethod
    def noise(step: GsoeStep, cfg: EkfConfig) -> Mat:
        """2x2 covariance (px^2) of ``[dx_px, dy_px]``: matcher and attitude-induced errors, equal on both axes."""
        return np.eye(2) * OpticalDisplacement.noise_var_px2(step, cfg)


# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class TrueAirspeed:
    """Measured true airspeed (m/s): ``(1 + tas_scale) * |v_ground - wind|``, both 3-D (``[wind_ne, wind_d]``; PX4
    EKF2 and ArduPilot fuse it the same way with a horizontal wind)."""

    def predict(self, x: Vec) -> Vec:
        return np.array([self.row(x)[0]])

    def jacobian(self, x: Vec) -> Mat:
        return self.linearise(x)[1]

    def linearise(self, x: Vec) -> tuple[Vec, Mat]:
        z, h = self.row(x)
        return np.array([z]), h[None, :]

    @staticmethod
    def row(x: Vec) -> tuple[float, Vec]:
        """``(z_hat, h)``: the predicted airspeed (m/s) and the Jacobian row (n,)."""
        xl = x.tolist()
        an, ae, ad = xl[_VN] - xl[_WN], xl[_VE] - xl[_WE], xl[_VD] - xl[_WD]
        speed = max(math.sqrt(an * an + ae * ae + ad * ad), MIN_AIR_SPEED_M_S)
        scale = 1.0 + xl[_TS]
        k = scale / speed
        h = np.zeros(S.dim)
        h[_VN], h[_VE], h[_VD], h[_WN], h[_WE], h[_WD] = k * an, k * ae, k * ad, -k * an, -k * ae, -k * ad
        h[_TS] = speed
        return scale * speed, h

    @staticmethod
    def variance(cfg: EkfConfig, turb_var_m2_s2: float = 0.0) -> float:
        """Measurement variance (m^2/s^2): the pitot's white noise plus the share of the turbulence (variance in use
        ``turb_var_m2_s2``, per axis) that the wind state does not follow, time-correlated and so weighted down:
        ``tas_sigma_m_s^2 + tas_turb_noise_factor^2 turb_var`` (see :class:`~fusion.config.EkfConfig`)."""
        return cfg.tas_sigma_m_s**2 + cfg.tas_turb_noise_factor**2 * turb_var_m2_s2

    @staticmethod
    def noise(cfg: EkfConfig, turb_var_m2_s2: float = 0.0) -> Mat:
        return np.array([[TrueAirspeed.variance(cfg, turb_var_m2_s2)]])

    @staticmethod
    def wind_from_airspeed(x: Vec, tas_m_s: float, yaw_ahrs_rad: float) -> tuple[Vec, Mat, Vec, Vec]:
        """The wind triangle for a wind reset (PX4 EKF2's ``resetWindUsingAirspeed``): with zero sideslip the air
        moves along the true heading ``psi = yaw_ahrs - yaw_bias`` at the horizontal true airspeed, so
        ``wind_ne = vel_ne - tas_h [cos psi, sin psi]`` with ``tas_h = sqrt((tas / (1 + tas_scale))^2 - v_air_d^2)``
        and ``v_air_d = vel_d - wind_d``.

        Returns the wind (m/s, N/E) and its Jacobians w.r.t. the state (2 x n), the measured airspeed (2,) and the
        sideslip angle (2,; for the sideslip's uncertainty)."""
        k = 1.0 + x[_TS]
        tas = tas_m_s / k
        vd = x[_VD] - x[_WD]                                # vertical air velocity
        tas_h = math.sqrt(max(tas * tas - vd * vd, MIN_AIR_SPEED_M_S**2))
        psi = yaw_ahrs_rad - x[_YB]
        c, s = math.cos(psi), math.sin(psi)
        wind = np.array([x[_VN] - tas_h * c, x[_VE] - tas_h * s])
        dh_dtas = tas / tas_h                               # d tas_h / d tas (true airspeed)
        J = np.zeros((2, S.dim))
        J[0, _VN] = J[1, _VE] = 1.0
        J[0, _YB], J[1, _YB] = -tas_h * s, tas_h * c        # d psi / d yaw_bias = -1
        J[0, _VD], J[1, _VD] = c * vd / tas_h, s * vd / tas_h
        J[0, _WD], J[1, _WD] = -J[0, _VD], -J[1, _VD]
        J[0, _TS], J[1, _TS] = c * dh_dtas * tas / k, s * dh_dtas * tas / k    # d tas / d tas_scale = -tas / k
        d_tas = np.array([-c, -s]) * dh_dtas / k
        d_beta = np.array([s, -c]) * tas_h                  # air direction psi + beta
        return wind, J, d_tas, d_beta


# --------------------------------------------------------------------------------------------------------------
def _body_air_velocity(x: Vec, R_nb_ahrs: Mat) -> tuple[tuple[float, float, float], tuple[float, ...],
                                                         tuple[float, float], tuple[float, float]]:
    """What the sideslip and the angle of attack share: the body-frame air velocity ``vb = R_nb_ahrs^T [w,
    v_air_d]`` (m/s, FRD) with ``w = R_z(yaw_bias) v_air`` (N, E; the AHRS attitude corrected by the heading error),
    ``R_nb_ahrs`` row by row (its columns are the body axes in NED), ``w`` and ``(cos, sin)`` of ``yaw_bias``.

    Scalar arithmetic: this runs with every airspeed sample, and nine multiplications are cheaper than four
    3x3 NumPy products."""
    xl = x.tolist()
    an, ae, ad = xl[_VN] - xl[_WN], xl[_VE] - xl[_WE], xl[_VD] - xl[_WD]
    c, s = math.cos(xl[_YB]), math.sin(xl[_YB])
    wn, we = c * an - s * ae, s * an + c * ae                # R_z(yaw_bias) = R_z(-yaw_bias)^T
    r = R_nb_ahrs.ravel().tolist()
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    vb = (r00 * wn + r10 * we + r20 * ad, r01 * wn + r11 * we + r21 * ad, r02 * wn + r12 * we + r22 * ad)
    return vb, tuple(r), (wn, we), (c, s)


def _air_angle_row(dw: tuple[float, float, float], w: tuple[float, float], cs: tuple[float, float]) -> Vec:
    """Jacobian row (n,) of an angle of the body-frame air velocity, from its derivative ``dw`` w.r.t. ``[w,
    v_air_d]`` (:func:`_body_air_velocity`): through ``R_z(yaw_bias)`` to the air velocity ``v - wind`` and to
    ``yaw_bias``."""
    c, s = cs
    dn, de = c * dw[0] + s * dw[1], -s * dw[0] + c * dw[1]
    h = np.zeros(S.dim)
    h[_VN], h[_VE], h[_VD], h[_WN], h[_WE], h[_WD] = dn, de, dw[2], -dn, -de, -dw[2]
    h[_YB] = dw[0] * -w[1] + dw[1] * w[0]                   # d w / d yaw_bias = (-w_E, w_N, 0)
    return h


# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class SyntheticSideslip:
    """Sideslip pseudo-measurement (rad, small-angle ``v_air_b_y / v_air_b_x``).

    The air-relative velocity ``[v_ne - wind_ne, v_d - wind_d]`` is rotated into the body frame with the AHRS attitude
    ``R_nb_ahrs`` corrected by the heading error: ``R_nb = R_z(-yaw_bias) @ R_nb_ahrs``.  In coordinated flight
    the aircraft points into the relative wind, which together with the airspeed makes the wind observable
    without turns.

    The measured value is either 0 (the classic zero-sideslip assumption) or the side-force sideslip
    ``accel_gain_rad_per_m_s2 * f_y`` from the low-passed lateral specific force ``f_y`` (the airframe's side force
    ``q S C_Ybeta beta = m f_y``: ``beta = 2 m f_y / (rho S C_Ybeta V^2)``, i.e. the gain is
    :attr:`~fusion.config.EkfConfig.sideslip_accel_gain_m` over ``V^2``).  The accelerometer's bias is in that
    reading, so with a non-zero gain the prediction is ``beta(x) + accel_gain_rad_per_m_s2 * (accel_bias_y +
    side_force_ofs)`` (measured ``f_y`` = true + bias; the offset is the part of the accelerometer's reading at zero
    sideslip that the bias state, shared with the prediction's AHRS tilt error, does not hold: see
    :mod:`fusion.state`).  The gain changes with each sample's airspeed, so the EKF builds one model
    per sample.
    """

    R_nb_ahrs: Mat
    accel_gain_rad_per_m_s2: float = 0.0

    def predict(self, x: Vec) -> Vec:
        return np.array([self.row(x)[0]])

    def jacobian(self, x: Vec) -> Mat:
        return self.linearise(x)[1]

    def linearise(self, x: Vec) -> tuple[Vec, Mat]:
        z, h = self.row(x)
        return np.array([z]), h[None, :]

    def row(self, x: Vec) -> tuple[float, Vec]:
        """``(z_hat, h)``: the predicted sideslip measurement (rad) and the Jacobian row (n,)."""
        (vbx, vby, _), (r00, r01, _, r10, r11, _, r20, r21, _), w, cs = _body_air_velocity(x, self.R_nb_ahrs)
        vx = max(vbx, MIN_AIR_SPEED_M_S)
        gx, gy = -vby / (vx * vx), 1.0 / vx                  # d(vb_y / vb_x) / d(vb_x, vb_y)
        # d beta / d w: g_x * body_x + g_y * body_y (columns 0 and 1 of R_nb)
        h = _air_angle_row((gx * r00 + gy * r01, gx * r10 + gy * r11, gx * r20 + gy * r21), w, cs)
        k = self.accel_gain_rad_per_m_s2
        if k:
            h[_BAY] = h[_SFO] = k
            return vby / vx + k * (float(x[_BAY]) + float(x[_SFO])), h
        return vby / vx, h

    @staticmethod
    def variance(cfg: EkfConfig, turb_var_m2_s2: float = 0.0, airspeed_m_s: float = math.inf) -> float:
        """Measurement variance (rad^2): ``sideslip_sigma_rad^2`` plus the lateral turbulence the wind state does
        not follow, seen as an angle at the airspeed: ``(sideslip_turb_noise_factor * sigma_turb / V)^2`` (the
        sideslip's counterpart of the airspeed's term, :meth:`TrueAirspeed.variance`)."""
        return cfg.sideslip_sigma_rad**2 + cfg.sideslip_turb_noise_factor**2 * turb_var_m2_s2 / airspeed_m_s**2

    @staticmethod
    def noise(cfg: EkfConfig, turb_var_m2_s2: float = 0.0, airspeed_m_s: float = math.inf) -> Mat:
        return np.array([[SyntheticSideslip.variance(cfg, turb_var_m2_s2, airspeed_m_s)]])


# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class LiftAngleOfAttack:
    """Angle-of-attack pseudo-measurement from the lift (rad, ``atan(v_air_b_z / v_air_b_x)``).

    The wing's lift is what the accelerometer's normal channel reads: ``-m f_z = q S (C_L0 + C_Lalpha alpha)``
    (FRD, ``f_z`` about ``-g`` in level flight), so ``alpha = -2 m f_z / (rho S C_Lalpha V^2) - C_L0 / C_Lalpha``,
    with ``f_z`` low-passed like the sideslip's lateral force and ``V`` the pitot airspeed corrected by the scale
    state.  What it adds: with the airspeed and the sideslip it fixes the body-frame air velocity's third component,
    so the vertical air velocity, and with the ground's vertical velocity the vertical wind, which in a bank is
    sideslip and so cross-heading wind (:mod:`fusion.state`, ``wind_d``).

    The predicted angle uses the AHRS attitude corrected by the heading error, as :class:`SyntheticSideslip` does.
    The measured value holds the accelerometer's z bias and whatever offsets the lift model and the AHRS pitch have,
    so the prediction is ``alpha(x) - accel_gain_rad_per_m_s2 * accel_bias_z + aoa_ofs`` (measured ``f_z`` = true +
    bias; ``accel_gain_rad_per_m_s2`` is :attr:`~fusion.config.EkfConfig.aoa_accel_gain_m` over ``V^2``, one model
    per sample).
    """

    R_nb_ahrs: Mat
    accel_gain_rad_per_m_s2: float

    def predict(self, x: Vec) -> Vec:
        return np.array([self.row(x)[0]])

    def jacobian(self, x: Vec) -> Mat:
        return self.linearise(x)[1]

    def linearise(self, x: Vec) -> tuple[Vec, Mat]:
        z, h = self.row(x)
        return np.array([z]), h[None, :]

    def row(self, x: Vec) -> tuple[float, Vec]:
        """``(z_hat, h)``: the predicted angle-of-attack measurement (rad) and the Jacobian row (n,)."""
        (vbx, _, vbz), (r00, _, r02, r10, _, r12, r20, _, r22), w, cs = _body_air_velocity(x, self.R_nb_ahrs)
        vbx = max(vbx, MIN_AIR_SPEED_M_S)
        q = 1.0 / (vbx * vbx + vbz * vbz)
        gx, gz = -vbz * q, vbx * q                           # d atan(vb_z / vb_x) / d(vb_x, vb_z)
        # d alpha / d w: g_x * body_x + g_z * body_z (columns 0 and 2 of R_nb)
        h = _air_angle_row((gx * r00 + gz * r02, gx * r10 + gz * r12, gx * r20 + gz * r22), w, cs)
        k = self.accel_gain_rad_per_m_s2
        h[_BAZ] = -k
        h[_AOF] = 1.0
        return math.atan2(vbz, vbx) - k * float(x[_BAZ]) + float(x[_AOF]), h

    @staticmethod
    def measured(cfg: EkfConfig, normal_force_m_s2: float, airspeed_m_s: float) -> float:
        """The lift-model angle of attack (rad) from the low-passed normal specific force (FRD z, m/s^2) and the
        corrected airspeed (m/s)."""
        return -cfg.aoa_accel_gain_m * normal_force_m_s2 / (airspeed_m_s * airspeed_m_s) - cfg.aoa_zero_lift_rad

    @staticmethod
    def variance(cfg: EkfConfig, turb_var_m2_s2: float = 0.0, airspeed_m_s: float = math.inf) -> float:
        """Measurement variance (rad^2): ``aoa_sigma_rad^2`` plus the vertical turbulence the wind state does not
        follow, seen as an angle at the airspeed:
        ``(aoa_turb_noise_factor * wind_d_sigma_ratio * sigma_turb / V)^2``."""
        return (cfg.aoa_sigma_rad**2
                + (cfg.aoa_turb_noise_factor * cfg.wind_d_sigma_ratio)**2 * turb_var_m2_s2 / airspeed_m_s**2)

    @staticmethod
    def noise(cfg: EkfConfig, turb_var_m2_s2: float = 0.0, airspeed_m_s: float = math.inf) -> Mat:
        return np.array([[LiftAngleOfAttack.variance(cfg, turb_var_m2_s2, airspeed_m_s)]])


_H_BARO = np.zeros(S.dim)
_H_BARO[_PD], _H_BARO[_BB] = -1.0, 1.0
_H_BARO.flags.writeable = False


# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class BaroAltitude:
    """Barometric altitude above the reference ground (m): ``-pos_d + baro_bias``."""

    def predict(self, x: Vec) -> Vec:
        return np.array([self.row(x)[0]])

    def jacobian(self, x: Vec) -> Mat:
        return _H_BARO[None, :].copy()

    def linearise(self, x: Vec) -> tuple[Vec, Mat]:
        return self.predict(x), self.jacobian(x)

    @staticmethod
    def row(x: Vec) -> tuple[float, Vec]:
        """``(z_hat, h)``: the predicted baro altitude (m) and the (constant, read-only) Jacobian row (n,)."""
        return float(x[_BB] - x[_PD]), _H_BARO

    @staticmethod
    def noise(cfg: EkfConfig) -> Mat:
        return np.array([[cfg.baro_sigma_m**2]])


# --------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class GnssPosition:
    """GNSS position in the local NED frame (m): ``pos_ne`` (``dim=2``) or ``pos_ne, pos_d`` (``dim=3``).

    A direct measurement of states: ``H`` is the rows :attr:`state_idx` of the identity, which the EKF uses as
    column selections of ``P`` instead of products."""

    dim: int = 3

    @property
    def state_idx(self) -> list[int]:
        """Indices of the measured states, in measurement order."""
        return list(range(S.pos_ned.start, S.pos_ned.start + self.dim))

    def predict(self, x: Vec) -> Vec:
        return x[S.pos_ned][: self.dim].copy()

    def jacobian(self, x: Vec) -> Mat:
        H = np.zeros((self.dim, S.dim))
        H[:, S.pos_ned][:, : self.dim] = np.eye(self.dim)
        return H

    def linearise(self, x: Vec) -> tuple[Vec, Mat]:
        return self.predict(x), self.jacobian(x)

    def variances(self, cfg: EkfConfig, sigma_ne_m: float | None = None, sigma_d_m: float | None = None) -> list[float]:
        """Diagonal of :meth:`noise` (m^2), as floats."""
        ne = cfg.gnss_pos_ne_sigma_m if sigma_ne_m is None else float(sigma_ne_m)
        d = cfg.gnss_pos_d_sigma_m if sigma_d_m is None else float(sigma_d_m)
        return [ne * ne, ne * ne, d * d][: self.dim]

    def noise(self, cfg: EkfConfig, sigma_ne_m: float | None = None, sigma_d_m: float | None = None) -> Mat:
        """Diagonal covariance (m^2); the receiver's own accuracies replace the config's when given."""
        return np.diag(self.variances(cfg, sigma_ne_m, sigma_d_m))


@dataclass(frozen=True, slots=True)
class GnssVelocity:
    """GNSS ground velocity (m/s): ``vel_ne`` (``dim=2``, e.g. from ground speed and course) or ``vel_ned``.
    Like :class:`GnssPosition`, a direct measurement of the states :attr:`state_idx`."""

    dim: int = 3

    @property
    def state_idx(self) -> list[int]:
        """Indices of the measured states, in measurement order."""
        return list(range(S.vel_ned.start, S.vel_ned.start + self.dim))

    def predict(self, x: Vec) -> Vec:
        return x[S.vel_ned][: self.dim].copy()

    def jacobian(self, x: Vec) -> Mat:
        H = np.zeros((self.dim, S.dim))
        H[:, S.vel_ned][:, : self.dim] = np.eye(self.dim)
        return H

    def linearise(self, x: Vec) -> tuple[Vec, Mat]:
        return self.predict(x), self.jacobian(x)

    def variances(self, cfg: EkfConfig, sigma_ne_m_s: float | None = None,
                  sigma_d_m_s: float | None = None) -> list[float]:
        """Diagonal of :meth:`noise` ((m/s)^2), as floats."""
        ne = cfg.gnss_vel_ne_sigma_m_s if sigma_ne_m_s is None else float(sigma_ne_m_s)
        d = cfg.gnss_vel_d_sigma_m_s if sigma_d_m_s is None else float(sigma_d_m_s)
        return [ne * ne, ne * ne, d * d][: self.dim]

    def noise(self, cfg: EkfConfig, sigma_ne_m_s: float | None = None, sigma_d_m_s: float | None = None) -> Mat:
        """Diagonal covariance ((m/s)^2); the receiver's own accuracies replace the config's when given."""
        return np.diag(self.variances(cfg, sigma_ne_m_s, sigma_d_m_s))
