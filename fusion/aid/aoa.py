"""Lift-model angle of attack: the pseudo-measurement fused with every airspeed sample, and its aid source.

With the airspeed and the sideslip it fixes the body-frame air velocity's third component, so the vertical air
velocity, and with the ground's vertical velocity the vertical wind, which in a bank is sideslip and so
cross-heading wind (:mod:`fusion.state`, ``wind_d``).  Not fused beyond ``aoa.max_deg`` (stall, or a pull beyond
the linear lift curve).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from fusion.aid.air import MIN_AIR_SPEED_M_S, AirAngle, air_angle_row, body_air_velocity
from fusion.aid.base import Vec
from fusion.aid.sideslip import AirDataAid
from fusion.config import EkfConfig
from fusion.core import Linearised
from fusion.state import S

REASON_AOA_RANGE = "lift-model angle of attack outside aoa_max_deg (lift curve not linear there)"

_BAZ, _AOF = S.accel_bias_b.start + 2, S.aoa_ofs.start


@dataclass(slots=True)
class LiftAngleOfAttack(AirAngle):
    """Angle-of-attack pseudo-measurement from the lift (rad, ``atan(v_air_b_z / v_air_b_x)``), noise ``var_rad2``.

    The wing's lift is what the accelerometer's normal channel reads: ``-m f_z = q S (C_L0 + C_Lalpha alpha)``
    (FRD, ``f_z`` about ``-g`` in level flight), so ``alpha = -2 m f_z / (rho S C_Lalpha V^2) - C_L0 / C_Lalpha``,
    with ``f_z`` low-passed like the sideslip's lateral force and ``V`` the pitot airspeed corrected by the scale
    state.  The predicted angle uses the AHRS attitude corrected by the heading error, as the sideslip does.  The
    measured value holds the accelerometer's z bias and whatever offsets the lift model and the AHRS pitch have,
    so the prediction is ``alpha(x) - accel_gain_rad_per_m_s2 * accel_bias_z + aoa_ofs`` (``accel_gain_rad_per_m_s2``
    is :attr:`~fusion.config.EkfConfig.airframe.aoa_accel_gain_m` over ``V^2``, one model per sample).
    """

    def linearise(self, x: Vec) -> Linearised:
        xl = x.tolist()
        (vbx, _, vbz), r, w, cs = body_air_velocity(xl, self.R_nb_ahrs)
        vbx = max(vbx, MIN_AIR_SPEED_M_S)
        q = 1.0 / (vbx * vbx + vbz * vbz)
        # d atan(vb_z / vb_x) / d(vb_x, vb_z), so d alpha / d w along body x and body z (columns 0 and 2 of R_nb)
        h = air_angle_row(-vbz * q, vbx * q, 2, r, w, cs)
        k = self.accel_gain_rad_per_m_s2
        h[_BAZ] = -k
        h[_AOF] = 1.0
        return Linearised((math.atan2(vbz, vbx) - k * xl[_BAZ] + xl[_AOF],), h, None, (self.var_rad2,))

    @staticmethod
    def measured(cfg: EkfConfig, normal_force_m_s2: float, airspeed_m_s: float) -> float:
        """The lift-model angle of attack (rad) from the low-passed normal specific force (FRD z, m/s^2) and the
        corrected airspeed (m/s)."""
        a = cfg.airframe
        return -a.aoa_accel_gain_m * normal_force_m_s2 / (airspeed_m_s * airspeed_m_s) - a.aoa_zero_lift_rad

    @staticmethod
    def variance(cfg: EkfConfig, turb_var_m2_s2: float = 0.0, airspeed_m_s: float = math.inf) -> float:
        """Measurement variance (rad^2): ``aoa.sigma_rad^2`` plus the vertical turbulence the wind state does not
        follow, seen as an angle at the airspeed:
        ``(aoa.turb_noise_factor * wind.vertical_sigma_ratio * sigma_turb / V)^2``."""
        return (cfg.aoa.sigma_rad**2
                + (cfg.aoa.turb_noise_factor * cfg.wind.vertical_sigma_ratio)**2 * turb_var_m2_s2 / airspeed_m_s**2)


class AoaAid(AirDataAid):
    """Fuses the lift-model angle of attack with each airspeed sample above ``airspeed.min_m_s`` (``aoa.enabled``; gate
    ``gates.aoa_nis``), within ``aoa.max_deg``."""

    name = "aoa"

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        c = self.cfg
        self._gain_m = c.airframe.aoa_accel_gain_m if c.aoa.enabled else 0.0
        self._max_rad = math.radians(c.aoa.max_deg)
        # the configuration's derived numbers, once (this runs with every airspeed sample): those of
        # LiftAngleOfAttack.measured and LiftAngleOfAttack.variance
        self._gate = c.gates.aoa_nis
        self._lift = (c.airframe.aoa_accel_gain_m, c.airframe.aoa_zero_lift_rad)
        self._var_terms = (c.aoa.sigma_rad**2, (c.aoa.turb_noise_factor * c.wind.vertical_sigma_ratio)**2)

    def control(self, t_us: int, tas: float) -> bool:
        if tas >= self._min_m_s and not self._gain_m:
            return True
        air = self.air_sample(t_us, tas, need_normal=True)
        if air is None:
            return True
        R_nb, v_air = air
        gain, zero_lift = self._lift
        z_alpha = -gain * self.ctx.imu.nrm_f / (v_air * v_air) - zero_lift
        if abs(z_alpha) > self._max_rad:                  # stall, or a pull beyond the linear lift curve
            self.row.set(t_us, reason=REASON_AOA_RANGE)
            return True
        var0, k_turb = self._var_terms
        var = var0 + k_turb * self.ctx.process.turb_var / v_air**2
        model = LiftAngleOfAttack(R_nb, self._gain_m / (v_air * v_air), var)
        self.fuse(t_us, (z_alpha,), model, self._gate)
        return True
