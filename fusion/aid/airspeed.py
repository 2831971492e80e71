"""True airspeed: the model ``(1 + tas_scale) |v_ground - wind|`` and its aid source.

The source resets the wind from the wind triangle at the first usable sample when the filter was started without a
wind (PX4 EKF2's ``resetWindUsingAirspeed``), which avoids a wind far outside its initial sigma (strong winds) being
explained away by the airspeed scale state.

Partial-update (Schmidt) airspeed scale: every update multiplies the scale's row of the gain by
``airspeed.scale_update_fraction`` (:mod:`fusion.core`).  In turbulence the scale and the along-heading wind are nearly
degenerate and a fully updated scale walks away; a near-fixed scale prior instead made the wind sigma ignore a
2-4 % pitot error.  With the calibration's prior and a small fraction the pitot error is in the wind sigma and the
airspeed innovation variance, and a constant scale is still learnt over a few minutes of turns in smooth air.  The
fraction follows the turbulence level: ``airspeed.scale_calm_fraction`` once the adapted turbulence sigma is known
(after ``wind.turb_adapt_time_s``) to be at most ``airspeed.scale_calm_turb_sigma_max_m_s`` (docs/ekf-tuning.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from fusion.aid.air import MIN_AIR_SPEED_M_S, TS, VD, VE, VN, WD, WE, WN, YB
from fusion.aid.base import AidSource, Mat, ModelBase, Vec
from fusion.config import EkfConfig
from fusion.core import Linearised
from fusion.process import US_PER_S
from fusion.state import S

REASON_LOW_AIRSPEED = "airspeed below tas_min_m_s"
REASON_WIND_RESET = "wind reset from the wind triangle (first airspeed sample)"

_I_WIND, _I_WMEAN = S.idx("wind_ne"), S.idx("wind_mean_ne")


@dataclass(slots=True)
class TrueAirspeed(ModelBase):
    """Measured true airspeed (m/s): ``(1 + tas_scale) * |v_ground - wind|``, both 3-D (``[wind_ne, wind_d]``; PX4
    EKF2 and ArduPilot fuse it the same way with a horizontal wind); ``var_m2_s2`` its noise variance."""

    var_m2_s2: float

    @classmethod
    def from_config(cls, cfg: EkfConfig, turb_var_m2_s2: float) -> TrueAirspeed:
        return cls(cls.variance(cfg, turb_var_m2_s2))

    def linearise(self, x: Vec) -> Linearised:
        xl = x.tolist()
        an, ae, ad = xl[VN] - xl[WN], xl[VE] - xl[WE], xl[VD] - xl[WD]
        speed = max(math.sqrt(an * an + ae * ae + ad * ad), MIN_AIR_SPEED_M_S)
        scale = 1.0 + xl[TS]
        k = scale / speed
        h = np.zeros(S.dim)
        h[VN], h[VE], h[VD], h[WN], h[WE], h[WD] = k * an, k * ae, k * ad, -k * an, -k * ae, -k * ad
        h[TS] = speed
        return Linearised((scale * speed,), h, None, (self.var_m2_s2,))

    @staticmethod
    def variance(cfg: EkfConfig, turb_var_m2_s2: float = 0.0) -> float:
        """Measurement variance (m^2/s^2): the pitot's white noise plus the share of the turbulence (variance in use
        ``turb_var_m2_s2``, per axis) that the wind state does not follow, time-correlated and so weighted down:
        ``airspeed.sigma_m_s^2 + airspeed.turb_noise_factor^2 turb_var``."""
        white, k_turb = TrueAirspeed.variance_terms(cfg)
        return white + k_turb * turb_var_m2_s2

    @staticmethod
    def variance_terms(cfg: EkfConfig) -> tuple[float, float]:
        """:meth:`variance`'s two configuration numbers (m^2/s^2 and its factor of the turbulence variance), which
        the source reads once."""
        return cfg.airspeed.sigma_m_s**2, cfg.airspeed.turb_noise_factor**2

    @staticmethod
    def wind_from_airspeed(x: Vec, tas_m_s: float, yaw_ahrs_rad: float) -> tuple[Vec, Mat, Vec, Vec]:
        """The wind triangle for a wind reset: with zero sideslip the air moves along the true heading
        ``psi = yaw_ahrs - yaw_bias`` at the horizontal true airspeed, so ``wind_ne = vel_ne - tas_h [cos psi,
        sin psi]`` with ``tas_h = sqrt((tas / (1 + tas_scale))^2 - v_air_d^2)`` and ``v_air_d = vel_d - wind_d``.

        Returns the wind (m/s, N/E) and its Jacobians w.r.t. the state (2 x n), the measured airspeed (2,) and the
        sideslip angle (2,; for the sideslip's uncertainty)."""
        k = 1.0 + x[TS]
        tas = tas_m_s / k
        vd = x[VD] - x[WD]                                  # vertical air velocity
        tas_h = math.sqrt(max(tas * tas - vd * vd, MIN_AIR_SPEED_M_S**2))
        psi = yaw_ahrs_rad - x[YB]
        c, s = math.cos(psi), math.sin(psi)
        wind = np.array([x[VN] - tas_h * c, x[VE] - tas_h * s])
        dh_dtas = tas / tas_h                               # d tas_h / d tas (true airspeed)
        J = np.zeros((2, S.dim))
        J[0, VN] = J[1, VE] = 1.0
        J[0, YB], J[1, YB] = -tas_h * s, tas_h * c          # d psi / d yaw_bias = -1
        J[0, VD], J[1, VD] = c * vd / tas_h, s * vd / tas_h
        J[0, WD], J[1, WD] = -J[0, VD], -J[1, VD]
        J[0, TS], J[1, TS] = c * dh_dtas * tas / k, s * dh_dtas * tas / k      # d tas / d tas_scale = -tas / k
        d_tas = np.array([-c, -s]) * dh_dtas / k
        d_beta = np.array([s, -c]) * tas_h                  # air direction psi + beta
        return wind, J, d_tas, d_beta


class AirspeedAid(AidSource):
    """Fuses every airspeed sample above ``airspeed.min_m_s`` (gate ``gates.airspeed_nis``); the sideslip and the angle
    of attack ride on the same sample (:mod:`fusion.aid.sideslip`, :mod:`fusion.aid.aoa`)."""

    name = "airspeed"
    events: ClassVar[dict[str, int]] = {"airspeed": 4}

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self._wind_reset_pending = not self.ctx.wind_given
        # the turbulence sigma is a measurement only after one adaptation time: before, calm air is not known
        self._calm_known_us = self.ctx.t0_us + round(self.cfg.wind.turb_adapt_time_s * US_PER_S)
        self.core.set_partial_update(TS, self.cfg.airspeed.scale_update_fraction)
        # the configuration's derived numbers, once (this runs with every airspeed sample)
        a = self.cfg.airspeed
        self._min_m_s, self._gate = a.min_m_s, self.cfg.gates.airspeed_nis
        self._calm_turb_var_max = a.scale_calm_turb_sigma_max_m_s**2
        self._fractions = (a.scale_calm_fraction, a.scale_update_fraction)
        self._var_terms = TrueAirspeed.variance_terms(self.cfg)

    def push(self, t_us: int, payload: Any) -> None:
        self.ctx.timeline.push(t_us, self.name, float(payload))

    def control(self, t_us: int, tas: float) -> bool:
        if tas < self._min_m_s:
            self.row.set(t_us, reason=REASON_LOW_AIRSPEED)
            return True
        if self._wind_reset_pending and self.ctx.imu.att is not None:
            self.reset(t_us, tas)
            return False                                  # the wind is the measurement: nothing else to learn
        turb_var = self.ctx.process.turb_var
        # the scale's fraction follows the turbulence level (full update in calm air)
        calm = t_us >= self._calm_known_us and turb_var <= self._calm_turb_var_max
        g = self._fractions[0] if calm else self._fractions[1]
        if g != self.core.partial_update_fraction(TS):
            self.core.set_partial_update(TS, g)
        var0, k_turb = self._var_terms
        self.fuse(t_us, (tas,), TrueAirspeed(var0 + k_turb * turb_var), self._gate)
        return True

    def reset(self, t_us: int, sample: float) -> None:
        """Wind from the wind triangle (:meth:`TrueAirspeed.wind_from_airspeed`) with its covariance
        ``J P J' + sigma_tas^2 a a' + sigma_beta^2 b b'`` and cross covariance ``J P``."""
        att = self.ctx.imu.att
        assert att is not None
        core = self.core
        x, P = core.x, core.P
        wind, J, d_tas, d_beta = TrueAirspeed.wind_from_airspeed(x, sample, att.yaw_rad)
        A = J @ P
        iw, im = _I_WIND, _I_WMEAN
        x_new = x.copy()
        x_new[iw] = wind
        x_new[im] = wind                           # the mean: the same wind, less the turbulence (unknown, zero mean)
        P_new = P.copy()
        P_new[iw, :] = A
        P_new[:, iw] = A.T
        P_new[im, :] = A
        P_new[:, im] = A.T
        Pww = (A @ J.T + self.cfg.airspeed.sigma_m_s**2 * np.outer(d_tas, d_tas)
               + self.cfg.sideslip.sigma_rad**2 * np.outer(d_beta, d_beta))
        P_new[np.ix_(iw, iw)] = Pww
        P_new[np.ix_(iw, im)] = Pww
        P_new[np.ix_(im, iw)] = Pww
        P_new[np.ix_(im, im)] = Pww + self.ctx.process.turb_var * np.eye(2)
        core.store(x_new, 0.5 * (P_new + P_new.T))
        self._wind_reset_pending = False
        self.row.set(t_us, reason=REASON_WIND_RESET)
