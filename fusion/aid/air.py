"""What the air-data models share: the body-frame air velocity and the Jacobian row of an angle of it.

Scalar arithmetic: this runs with every airspeed sample, and nine multiplications are cheaper than four 3x3 NumPy
products.  The air velocity is ``[v_ne - wind_ne, v_d - wind_d]`` (m/s); the AHRS attitude is corrected by the
heading error: ``R_nb = R_z(-yaw_bias) @ R_nb_ahrs`` (the state's ``yaw_bias`` is ``yaw_ahrs - yaw_true``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fusion.aid.base import Mat, ModelBase, Vec
from fusion.state import S

#: Air-relative speed (m/s) below which the airspeed and sideslip models are not evaluated (their Jacobians divide
#: by it); the EKF never fuses airspeed below ``EkfConfig.airspeed.min_m_s``, which must be larger.
MIN_AIR_SPEED_M_S = 0.5

# Scalar indices derived from the layout (the models run at sample rate; scalar indexing is the cheap path).
VN, VE, VD = S.vel_ne.start, S.vel_ne.start + 1, S.vel_d.start
WN, WE, WD = S.wind_ne.start, S.wind_ne.start + 1, S.wind_d.start
YB, TS = S.yaw_bias.start, S.tas_scale.start

#: The body-to-NED rotation as a 3 x 3 matrix or its nine entries row by row (what the IMU integrator keeps).
Rotation = Mat | tuple[float, ...]


def body_air_velocity(x: Vec | list[float], R_nb_ahrs: Rotation) -> tuple[
        tuple[float, float, float], tuple[float, ...], tuple[float, float], tuple[float, float]]:
    """The body-frame air velocity ``vb = R_nb_ahrs^T [w, v_air_d]`` (m/s, FRD) with ``w = R_z(yaw_bias) v_air``
    (N, E; the AHRS attitude corrected by the heading error), ``R_nb_ahrs`` row by row (its columns are the body
    axes in NED), ``w`` and ``(cos, sin)`` of ``yaw_bias``.  ``x``: the state, or its ``tolist()``."""
    xl = x if isinstance(x, list) else x.tolist()
    an, ae, ad = xl[VN] - xl[WN], xl[VE] - xl[WE], xl[VD] - xl[WD]
    c, s = math.cos(xl[YB]), math.sin(xl[YB])
    wn, we = c * an - s * ae, s * an + c * ae                # R_z(yaw_bias) = R_z(-yaw_bias)^T
    r = R_nb_ahrs if isinstance(R_nb_ahrs, tuple) else tuple(R_nb_ahrs.ravel().tolist())
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    vb = (r00 * wn + r10 * we + r20 * ad, r01 * wn + r11 * we + r21 * ad, r02 * wn + r12 * we + r22 * ad)
    return vb, r, (wn, we), (c, s)


def air_angle_row(gx: float, g2: float, col: int, r: tuple[float, ...], w: tuple[float, float],
                  cs: tuple[float, float]) -> Vec:
    """Jacobian row (n,) of an angle of the body-frame air velocity whose derivative w.r.t. it is ``gx`` along the
    body x axis and ``g2`` along the body axis ``col`` (1: y, 2: z): ``d angle / d [w, v_air_d] = gx body_x + g2
    body_col`` (columns of ``R_nb``, ``r`` row by row; ``w``, ``cs`` from :func:`body_air_velocity`), through
    ``R_z(yaw_bias)`` to the air velocity ``v - wind`` and to ``yaw_bias``."""
    dw0, dw1, dw2 = gx * r[0] + g2 * r[col], gx * r[3] + g2 * r[3 + col], gx * r[6] + g2 * r[6 + col]
    c, s = cs
    dn, de = c * dw0 + s * dw1, -s * dw0 + c * dw1
    h = np.zeros(S.dim)
    h[VN], h[VE], h[VD], h[WN], h[WE], h[WD] = dn, de, dw2, -dn, -de, -dw2
    h[YB] = dw0 * -w[1] + dw1 * w[0]                       # d w / d yaw_bias = (-w_E, w_N, 0)
    return h


@dataclass(slots=True)
class AirAngle(ModelBase):
    """What the air-data angle pseudo-measurements (sideslip, lift-model angle of attack) are built from: the AHRS
    attitude ``R_nb_ahrs`` (:data:`Rotation`), the gain of the accelerometer reading in the measured angle
    (rad per m/s^2; 0: none) and the noise variance (rad^2).  The sources build one model per sample."""

    R_nb_ahrs: Rotation
    accel_gain_rad_per_m_s2: float
    var_rad2: float
