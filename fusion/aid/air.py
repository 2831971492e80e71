"""What the air-data models share: the body-frame air velocity and the Jacobian row of an angle of it.

Scalar arithmetic: this runs with every airspeed sample, and nine multiplications are cheaper than four 3x3 NumPy
products.  The air velocity is ``[v_ne - wind_ne, v_d - wind_d]`` (m/s); the AHRS attitude is corrected by the
heading error: ``R_nb = R_z(-yaw_bias) @ R_nb_ahrs`` (the state's ``yaw_bias`` is ``yaw_ahrs - yaw_true``).
"""

from __future__ import annotations

import math

import numpy as np

from fusion.aid.base import Mat, Vec
from fusion.state import S

#: Air-relative speed (m/s) below which the airspeed and sideslip models are not evaluated (their Jacobians divide
#: by it); the EKF never fuses airspeed below ``EkfConfig.airspeed.min_m_s``, which must be larger.
MIN_AIR_SPEED_M_S = 0.5

# Scalar indices derived from the layout (the models run at sample rate; scalar indexing is the cheap path).
VN, VE, VD = S.vel_ne.start, S.vel_ne.start + 1, S.vel_d.start
WN, WE, WD = S.wind_ne.start, S.wind_ne.start + 1, S.wind_d.start
YB, TS = S.yaw_bias.start, S.tas_scale.start


def body_air_velocity(x: Vec, R_nb_ahrs: Mat) -> tuple[tuple[float, float, float], tuple[float, ...],
                                                        tuple[float, float], tuple[float, float]]:
    """The body-frame air velocity ``vb = R_nb_ahrs^T [w, v_air_d]`` (m/s, FRD) with ``w = R_z(yaw_bias) v_air``
    (N, E; the AHRS attitude corrected by the heading error), ``R_nb_ahrs`` row by row (its columns are the body
    axes in NED), ``w`` and ``(cos, sin)`` of ``yaw_bias``."""
    xl = x.tolist()
    an, ae, ad = xl[VN] - xl[WN], xl[VE] - xl[WE], xl[VD] - xl[WD]
    c, s = math.cos(xl[YB]), math.sin(xl[YB])
    wn, we = c * an - s * ae, s * an + c * ae                # R_z(yaw_bias) = R_z(-yaw_bias)^T
    r = R_nb_ahrs.ravel().tolist()
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    vb = (r00 * wn + r10 * we + r20 * ad, r01 * wn + r11 * we + r21 * ad, r02 * wn + r12 * we + r22 * ad)
    return vb, tuple(r), (wn, we), (c, s)


def air_angle_row(dw: tuple[float, float, float], w: tuple[float, float], cs: tuple[float, float]) -> Vec:
    """Jacobian row (n,) of an angle of the body-frame air velocity, from its derivative ``dw`` w.r.t. ``[w,
    v_air_d]`` (:func:`body_air_velocity`): through ``R_z(yaw_bias)`` to the air velocity ``v - wind`` and to
    ``yaw_bias``."""
    c, s = cs
    dn, de = c * dw[0] + s * dw[1], -s * dw[0] + c * dw[1]
    h = np.zeros(S.dim)
    h[VN], h[VE], h[VD], h[WN], h[WE], h[WD] = dn, de, dw[2], -dn, -de, -dw[2]
    h[YB] = dw[0] * -w[1] + dw[1] * w[0]                   # d w / d yaw_bias = (-w_E, w_N, 0)
    return h
