"""Timestamped samples in and estimates out of the optical estimator (frames and units as in :mod:`gsoe`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, slots=True)
class AttitudeSample:
    """AHRS attitude (3-2-1 Euler, body FRD relative to NED) at ``t_us``."""

    t_us: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class ImuSample:
    """IMU sample at ``t_us``: body rates and specific force, both in the body frame (FRD)."""

    t_us: int
    gyro_b_rad_s: NDArray[np.float64]
    accel_b_m_s2: NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class MatchQuality:
    """Quality of one template match: peak-to-sidelobe ratio, template texture (intensity std, 0-255), SSD at the
    best match per pixel, and the verdict.

    ``match_sigma_px``: the match position's one-sigma error (px, per axis, the root of half the covariance's
    trace) implied by the SSD surface itself, ``C = 2 s^2 H^-1`` with ``H`` the surface's Hessian at the minimum
    and ``s^2`` the residual SSD per pixel (:func:`gsoe.matching.ssd_precision_px`); nan where the surface is not
    a bowl there or no match was made."""

    psr: float
    texture_std: float
    ssd_per_px: float
    valid: bool
    match_sigma_px: float = math.nan


@dataclass(frozen=True, slots=True)
class GsoeStep:
    """One optical measurement: the template's accumulated migration since the cycle's base snapshot.

    ``dx_px`` cross track (right of ``base_yaw_rad``), ``dy_px`` along track (forward), both in the stabilised
    frame ``s`` of the cycle, whose ground sample distance at the base snapshot was ``gsd_m_px`` (with the height
    ``height_agl_m`` used for it).  ``yaw_rad`` is the heading at the current frame.  ``t_us`` is the current
    frame's exposure time, ``base_t_us`` the base
    snapshot's.  ``rel_rot_rad`` is the size of the rotation between the base and current camera poses (what the
    attitude-induced pixel error scales with).
    """

    t_us: int
    base_t_us: int
    cycle_id: int
    step: int
    dx_px: float
    dy_px: float
    base_yaw_rad: float
    yaw_rad: float
    gsd_m_px: float
    height_agl_m: float
    focal_px: float
    rel_rot_rad: float
    quality: MatchQuality
    valid: bool
    new_cycle: bool


@dataclass(frozen=True, slots=True)
class AirspeedSample:
    """Airspeed at ``t_us``: true airspeed ``tas_m_s`` (what the EKF fuses) and, where a log gives it, the
    equivalent airspeed ``eas_m_s`` it was derived from (``nan`` otherwise)."""

    t_us: int
    tas_m_s: float
    eas_m_s: float = math.nan


@dataclass(frozen=True, slots=True)
class BaroSample:
    """Barometric altitude at ``t_us`` (m, up).  In the simulator it is the height above the mission's reference
    point plus the baro's errors; from a flight log it is the ISA pressure altitude of ``pressure_pa`` (the datum
    is not the ground: only its changes matter and the EKF estimates the offset)."""

    t_us: int
    alt_m: float
    pressure_pa: float = math.nan


@dataclass(frozen=True, slots=True)
class GnssSample:
    """GNSS fix at ``t_us``: NED position relative to the local origin (the reference point, or a log's first
    3-D fix) and NED ground velocity.

    Without a fix (``fix_ok`` false, e.g. in an outage) the position and velocity are NaN.  ``h_acc_m`` /
    ``v_acc_m_s`` are the receiver's 1-sigma accuracies of one horizontal position axis and one velocity axis,
    ``alt_acc_m`` of the vertical position (``nan`` when unknown, ``inf`` without a fix); ``n_sats`` is -1 when
    unknown.  ``lat_deg``, ``lon_deg``, ``alt_msl_m`` are the fix as logged (``nan`` in the simulator).
    ``fix_type`` is MAVLink's GPS_FIX_TYPE where the source gives it (-1 otherwise).  Components a source does not
    give are NaN.
    """

    t_us: int
    pos_ned_m: NDArray[np.float64]
    vel_ned_m_s: NDArray[np.float64]
    fix_ok: bool
    n_sats: int
    h_acc_m: float = math.nan
    v_acc_m_s: float = math.nan
    lat_deg: float = math.nan
    lon_deg: float = math.nan
    alt_msl_m: float = math.nan
    alt_acc_m: float = math.nan
    fix_type: int = -1
