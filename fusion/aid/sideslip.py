"""Synthetic sideslip: the pseudo-measurement fused with every airspeed sample, and its aid source.

In coordinated flight the aircraft points into the relative wind, which together with the airspeed makes the wind
observable without turns.  The measured value is either 0 (the classic zero-sideslip assumption) or the side-force
sideslip from the low-passed lateral specific force (``airframe.side_force_coef_per_rad`` not 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

from fusion.aid.air import MIN_AIR_SPEED_M_S, TS, AirAngle, air_angle_row, body_air_velocity
from fusion.aid.airspeed import REASON_LOW_AIRSPEED
from fusion.aid.base import AidSource, Vec
from fusion.config import EkfConfig
from fusion.core import Linearised
from fusion.state import S
from fusion.status import REASON_NO_ATTITUDE

_BAY, _SFO = S.accel_bias_b.start + 1, S.side_force_ofs.start


@dataclass(slots=True)
class SyntheticSideslip(AirAngle):
    """Sideslip pseudo-measurement (rad, small-angle ``v_air_b_y / v_air_b_x``) with noise variance ``var_rad2``.

    The air-relative velocity is rotated into the body frame with the AHRS attitude ``R_nb_ahrs`` corrected by the
    heading error (:mod:`fusion.aid.air`).  With the side-force model the measured value is
    ``accel_gain_rad_per_m_s2 * f_y`` of the low-passed lateral specific force ``f_y`` (the airframe's side force
    ``q S C_Ybeta beta = m f_y``: ``beta = 2 m f_y / (rho S C_Ybeta V^2)``, i.e. the gain is
    :attr:`~fusion.config.EkfConfig.airframe.sideslip_accel_gain_m` over ``V^2``).  The accelerometer's bias is in that
    reading, so with a non-zero gain the prediction is ``beta(x) + accel_gain_rad_per_m_s2 * (accel_bias_y +
    side_force_ofs)`` (the offset is the part of the reading at zero sideslip that the bias state, shared with the
    prediction's AHRS tilt error, does not hold: see :mod:`fusion.state`).  The gain changes with each sample's
    airspeed, so the source builds one model per sample.
    """

    def linearise(self, x: Vec) -> Linearised:
        xl = x.tolist()
        (vbx, vby, _), r, w, cs = body_air_velocity(xl, self.R_nb_ahrs)
        vx = max(vbx, MIN_AIR_SPEED_M_S)
        # d(vb_y / vb_x) / d(vb_x, vb_y), so d beta / d w along body x and body y (columns 0 and 1 of R_nb)
        h = air_angle_row(-vby / (vx * vx), 1.0 / vx, 1, r, w, cs)
        k = self.accel_gain_rad_per_m_s2
        if k:
            h[_BAY] = h[_SFO] = k
            return Linearised((vby / vx + k * (xl[_BAY] + xl[_SFO]),), h, None, (self.var_rad2,))
        return Linearised((vby / vx,), h, None, (self.var_rad2,))

    @staticmethod
    def variance(cfg: EkfConfig, turb_var_m2_s2: float = 0.0, airspeed_m_s: float = math.inf) -> float:
        """Measurement variance (rad^2): ``sideslip.sigma_rad^2`` plus the lateral turbulence the wind state does
        not follow, seen as an angle at the airspeed: ``(sideslip.turb_noise_factor * sigma_turb / V)^2`` (the
        sideslip's counterpart of :meth:`~fusion.aid.airspeed.TrueAirspeed.variance`)."""
        return cfg.sideslip.sigma_rad**2 + cfg.sideslip.turb_noise_factor**2 * turb_var_m2_s2 / airspeed_m_s**2


class AirDataAid(AidSource):
    """What the aid sources riding on each airspeed sample share (the sideslip here, the angle of attack): the
    airspeed and attitude conditions and the airspeed corrected by the scale state."""

    listens: ClassVar[tuple[str, ...]] = ("airspeed",)

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self._min_m_s = self.cfg.airspeed.min_m_s

    def air_sample(self, t_us: int, tas: float, need_normal: bool = False) -> tuple[tuple[float, ...], float] | None:
        """The AHRS rotation (row by row) and the corrected airspeed ``tas / (1 + tas_scale)`` (at least
        ``airspeed.min_m_s``) for a sample of ``tas``; ``None``, with the reason in the status record, when the
        airspeed is below the minimum or there is no attitude (``need_normal``: or no normal specific force) yet."""
        if tas < self._min_m_s:
            self.row.set(t_us, reason=REASON_LOW_AIRSPEED)
            return None
        imu = self.ctx.imu
        R_nb = imu.R_nb_rows()
        if R_nb is None or (need_normal and math.isnan(imu.nrm_f)):
            self.row.set(t_us, reason=REASON_NO_ATTITUDE)
            return None
        return R_nb, max(tas / (1.0 + self.core.x.item(TS)), self._min_m_s)


class SideslipAid(AirDataAid):
    """Fuses the sideslip with each airspeed sample above ``airspeed.min_m_s`` (``sideslip.enabled``; gate
    ``gates.sideslip_nis``), at the AHRS attitude of the last IMU sample at or before the stamp."""

    name = "sideslip"

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        c = self.cfg
        # the configuration's derived numbers, once (this runs with every airspeed sample)
        self._enabled, self._gain_m, self._gate = c.sideslip.enabled, c.airframe.sideslip_accel_gain_m, \
            c.gates.sideslip_nis
        self._var_terms = (c.sideslip.sigma_rad**2, c.sideslip.turb_noise_factor**2)   # SyntheticSideslip.variance

    def control(self, t_us: int, tas: float) -> bool:
        if tas >= self._min_m_s and not self._enabled:
            return True
        air = self.air_sample(t_us, tas)
        if air is None:
            return True
        R_nb, v_air = air
        # the side-force sideslip (measured value) from the lateral specific force and the corrected airspeed;
        # 0 with the model off (zero sideslip)
        k_beta, z_beta = 0.0, 0.0
        lat_f = self.ctx.imu.lat_f
        if self._gain_m and not math.isnan(lat_f):
            k_beta = self._gain_m / (v_air * v_air)
            z_beta = k_beta * lat_f
        var0, k_turb = self._var_terms
        var = var0 + k_turb * self.ctx.process.turb_var / v_air**2
        self.fuse(t_us, (z_beta,), SyntheticSideslip(R_nb, k_beta, var), self._gate)
        return True
