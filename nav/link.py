"""The companion's link to the autopilot through MAVSDK 4 (native binding, asyncio API).

Inputs (MAVSDK ``MavlinkDirect`` subscriptions), each validated (finite, physically plausible, time not going
backwards) before it becomes a timestamped sample; rejected samples are counted per kind and per reason, never
raised.  Of each kind the first message of its list below that arrives is used; a later one of the list only while
none before it has arrived for ``source_timeout_s`` (ArduPlane streams RAW_IMU, SCALED_IMU2 and SCALED_IMU3
together: one IMU stream reaches the estimator, not three):

=========  ===================================================  ==============================================
kind       messages, in order of preference                     becomes
=========  ===================================================  ==============================================
attitude   ATTITUDE; ATTITUDE_QUATERNION (PX4)                  :class:`common.samples.AttitudeSample`
IMU        HIGHRES_IMU (PX4; ArduPilot when asked: float SI),   :class:`common.samples.ImuSample`
           SCALED_IMU (mG, mrad/s), RAW_IMU (ArduPilot sends
           it scaled as SCALED_IMU: ``raw_imu_accel_scale`` and
           ``raw_imu_gyro_scale``), SCALED_IMU2, SCALED_IMU3
baro       SCALED_PRESSURE (ISA pressure altitude); ALTITUDE    :class:`common.samples.BaroSample`
           (PX4, ``altitude_monotonic``)
airspeed   VFR_HUD ``airspeed``: ArduPilot's equivalent         :class:`common.samples.AirspeedSample` (true
           airspeed (PX4: calibrated), made true with the air   airspeed, with the EAS it came from)
           density of the last baro pressure and temperature
           (``air_temperature``: :mod:`common.atmosphere`)
GNSS       GPS_RAW_INT (fix type, satellites, accuracy and      :class:`common.samples.GnssSample`
           velocity in one message)
home       GLOBAL_POSITION_INT (``alt - relative_alt``)         :class:`HomeReading`
tracker    CAMERA_TRACKING_IMAGE_STATUS (a video tracker's      :class:`TrackReading` (for
           target point, normalised)                            :class:`nav.tracker.ExternalTracker`)
=========  ===================================================  ==============================================

Rates: on connecting (and again whenever the link comes back) the link asks for each kind's first message at
``rate_*_hz`` with MAV_CMD_SET_MESSAGE_INTERVAL and reads the COMMAND_ACK.  A refused rate (ArduPlane refuses more
than 0.8 x ``SCHED_LOOP_RATE``: 40 Hz at its default 50) is asked again at ``rate_fallback`` times itself, down to
``rate_min_fraction`` of the wanted rate; then the kind's next message is asked for.  What was granted is logged,
kept in ``LinkStats.rates_granted`` and told to the ground station in one STATUSTEXT (:func:`rates_text`).
ArduPlane streams every message at 1 Hz unless asked: without these requests nothing usable arrives.

Time: every sample carries the autopilot's clock (``time_boot_ms``/``time_usec``); VFR_HUD and
CAMERA_TRACKING_IMAGE_STATUS, which carry none, carry the newest autopilot stamp received (ArduPilot sends a loop's
messages together).  The samples' ``t_us`` is that clock shifted by one offset (:class:`LinkClock`), chosen at the
first stamp so that it starts at the companion's monotonic clock and constant afterwards (per kind re-chosen only
when the autopilot's clock jumps back, a reboot): the estimator runs on the autopilot's time, at its rate (a SITL
at ``--speedup 5`` runs five times faster than the companion's clock, and so must the estimator's physics).  The
companion's own clock (a camera's capture time) is mapped onto it with the offset of the least-delayed attitude
packet (:class:`ClockSync`); the outputs are stamped back on the autopilot's clock.

Outputs (only while the estimate passes :func:`check_estimate`; otherwise nothing of the estimate is sent and the
reason is returned and logged): drift and ATA as NAMED_VALUE_FLOAT (``GSOE_DRIFT``, ``GSOE_ATA`` in degrees) or one
DEBUG_VECT ``GSOE`` (x drift deg, y ATA deg, z quality), through ``MavlinkDirect``; ground velocity for the
autopilot's EKF as one of (``velocity_message``, :func:`encode_velocity`):

- ``vision_position_delta`` (the default): VISION_POSITION_DELTA, the ground velocity in the body frame (FRD) times
  the time since the last one.  The heading-aligned velocity (ground speed along the drift angle, what the optical
  migration measures) is put into the body frame with the AHRS roll and pitch only, so it carries no heading:
  ArduPilot's EKF3 fuses it as body-frame odometry with its own attitude (its heading stays the compass's and
  IMU's).  Its noise is ArduPilot's ``EK3_VIS_VERR_MIN + (EK3_VIS_VERR_MAX - EK3_VIS_VERR_MIN) (1 - confidence /
  100)``: the confidence sent makes that the estimate's sigma (``ap_vis_verr_*_m_s`` must mirror the autopilot's
  parameters).
- ``vision_speed_estimate``: VISION_SPEED_ESTIMATE, the north/east/down velocity with its 3x3 covariance (through
  MAVSDK ``mocap``); ArduPilot fuses it with ``VISO_VEL_M_NSE``, not the covariance.  North/east are made with the
  autopilot's own yaw (less the estimated yaw bias), so it returns the autopilot's heading to it.
- ``odometry``: ODOMETRY, ``frame_id`` MAV_FRAME_LOCAL_FRD, ``child_frame_id`` MAV_FRAME_BODY_FRD, the same body-frame
  velocity with its covariance, the attitude quaternion with the estimate's heading, no position (NaN).  PX4 fuses
  the body velocity with its own attitude (``EKF2_EV_CTRL`` bit 2); ArduPilot turns it to north/east with the
  quaternion sent (as VISION_SPEED_ESTIMATE) and fuses it with ``VISO_VEL_M_NSE``.

Wind as WIND_COV (MAVSDK's own telemetry reads wind from it) and ArduPilot's WIND (Mission Planner's HUD), both
through ``MavlinkDirect``; STATUSTEXT.  The status named values ``GSOE_Q`` (optical
quality 0..1), ``GSOE_GNSS`` (:class:`nav.gnss_monitor.GnssState`) and ``GSOE_VALID`` (1 while the estimate is
sent, 0 while it is withheld) are sent at the named-value rate whether the estimate is valid or not: they are
what a ground station needs to show *why* nothing else arrives.  Each output has a rate and an on/off switch in
``[companion.link]``.

WIND_COV fields: ``wind_x``/``wind_y`` the estimate (NED, blowing to), ``wind_z`` 0 with ``vert_accuracy`` and
``var_vert`` set to ``unknown_vertical_sigma_m_s`` (the vertical wind is not estimated: a large sigma, never a
claimed 0), ``horiz_accuracy`` the one-sigma of the wind speed (the covariance projected on the wind direction, or
the RMS axis sigma near calm), ``var_horiz`` the RMS of the two horizontal axis sigmas (MAVLink defines it as the
wind's variability in m/s; the EKF's wind state follows the low-passed turbulence, so its uncertainty is the honest
number we have), ``wind_alt`` the altitude AMSL (home elevation plus height; the height above home when the home
elevation is not known).

The asyncio loop runs in its own thread (:class:`CompanionLink`); the companion's frame loop is synchronous and
exchanges samples and outputs through thread-safe queues, so a slow or dead link never blocks image processing.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray

from common.angles import wrap_360
from common.atmosphere import (
    ARDUPILOT_BARO_TEMP_CLAMP_C,
    GroundAir,
    ardupilot_major_baro_temp_clamp_c,
    eas_to_tas_ratio,
    isa_pressure_pa,
    pressure_altitude_m,
)
from common.config import In, Validated, require
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
from gsoe.rotation import R_nb_from_euler
from nav.gnss_monitor import GPS_FIX_TYPE_3D
from nav.hygiene import MAV_AUTOPILOT_ARDUPILOTMEGA, AutopilotSenders, flight_sw_version

log = logging.getLogger(__name__)

# Physical plausibility limits for telemetry (documented constants, not tuning knobs)
MAX_GYRO_RAD_S = 35.0          # 2000 deg/s, the largest common MEMS gyro range
MAX_ACCEL_M_S2 = 16.0 * 9.80665  # 16 g accelerometer range
MAX_AIRSPEED_M_S = 150.0
ALT_RANGE_M = (-500.0, 20000.0)
MAX_PITCH_RAD = math.pi / 2
EARTH_RADIUS_M = 6371008.8
GRAVITY_M_S2 = 9.80665
MAV_COMP_ID_ONBOARD_COMPUTER = 191
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_UNSUPPORTED = 3
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_FRD = 20
MAV_ESTIMATOR_TYPE_VIO = 3
UINT16_UNKNOWN = 65535
INT16_UNKNOWN = 32767
#: MAVLink message ids of the messages the link asks for (rates; AUTOPILOT_VERSION once)
MESSAGE_IDS = {"ATTITUDE": 30, "ATTITUDE_QUATERNION": 31, "HIGHRES_IMU": 105, "SCALED_IMU": 26, "RAW_IMU": 27,
               "SCALED_IMU2": 116, "SCALED_IMU3": 129, "SCALED_PRESSURE": 29, "ALTITUDE": 141, "VFR_HUD": 74,
               "GPS_RAW_INT": 24, "GLOBAL_POSITION_INT": 33, "AUTOPILOT_VERSION": 148}
#: each input kind's messages, in order of preference (module docstring)
SOURCES: dict[str, tuple[str, ...]] = {
    "attitude": ("ATTITUDE", "ATTITUDE_QUATERNION"),
    "imu": ("HIGHRES_IMU", "SCALED_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3"),
    "baro": ("SCALED_PRESSURE", "ALTITUDE"),
    "airspeed": ("VFR_HUD",),
    "gnss": ("GPS_RAW_INT",),
    "home": ("GLOBAL_POSITION_INT",),
}
RATE_NAMES = {"attitude": "ATT", "imu": "IMU", "baro": "BARO", "airspeed": "AIR", "gnss": "GPS", "home": "POS"}
TRACKING_STATUS_ACTIVE = 1  # CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
TRACKING_MODE_POINT = 1     # CAMERA_TRACKING_MODE_POINT
MAV_SEVERITY = {"emergency": 0, "alert": 1, "critical": 2, "error": 3, "warning": 4, "notice": 5, "info": 6}
NAMED_VALUE_MAX_CHARS = 10
LATENCY_HISTORY = 100_000  # capture-to-sent latencies kept per output kind
CLOCK_JUMP_CONFIRM = 5  # stamps in a row beyond a jump back make it a reboot (fewer: stray stamps, rejected)

_OutputRateHz = Annotated[float, In(0.01, 100.0)]
_MavlinkId = Annotated[int, In(1, 255)]
_InputRateHz = Annotated[float, In(0.1, 1000.0)]


@dataclass(frozen=True)
class LinkConfig(Validated):
    """``[companion.link]``: connection, output switches and rates, output gates (units in the names).

    ``system_id``/``component_id``: the companion's MAVLink identity (the vehicle's system id; component 191,
    MAV_COMP_ID_ONBOARD_COMPUTER).  ``status_values``: send ``GSOE_Q``/``GSOE_GNSS``/``GSOE_VALID`` even while the
    estimate is withheld.  ``unknown_vertical_sigma_m_s``: the one-sigma WIND_COV states for the vertical wind it
    does not estimate.  ``autopilot_system_id``/``autopilot_component_id``: the only sender telemetry is taken from
    (0: learnt from the autopilot's HEARTBEAT; :mod:`nav.hygiene`).

    Inputs (module docstring): ``request_rates`` asks the autopilot for ``rate_*_hz`` on connecting, refused rates
    retried at ``rate_fallback`` times themselves down to ``rate_min_fraction`` of the wanted rate;
    ``source_timeout_s``: a kind's less preferred message is used only after its preferred one has been silent this
    long; ``raw_imu_accel_scale_m_s2``/``raw_imu_gyro_scale_rad_s``: the RAW_IMU units (ArduPilot: mG and mrad/s);
    ``air_temperature``: the temperature of the air density that makes VFR_HUD's equivalent airspeed true, the
    baro's as ArduPilot takes it (:mod:`common.atmosphere`: at the lowest altitude seen, at most
    ``baro_temp_clamp_c``, the ISA lapse above) or the ISA's at the pressure altitude; an ArduPilot that tells its
    version (AUTOPILOT_VERSION) sets that clamp itself (:meth:`TelemetryGuard.firmware_version`), so
    ``baro_temp_clamp_c`` is for autopilots that do not; ``max_clock_ahead_s``: a
    stamp mapping this far beyond the newest one is refused (a message on another time base).

    Velocity output (module docstring): ``velocity_message``; ``ap_vis_verr_min_m_s``/``ap_vis_verr_max_m_s``
    mirror ArduPilot's ``EK3_VIS_VERR_MIN``/``EK3_VIS_VERR_MAX`` (the range VISION_POSITION_DELTA's confidence
    maps onto).
    """

    connect_timeout_s: Annotated[float, In(0.1, 600.0)] = 10.0
    named_values: Literal["named_value_float", "debug_vect", "off"] = "named_value_float"
    named_values_hz: _OutputRateHz = 5.0
    vision_speed: bool = True
    vision_speed_hz: _OutputRateHz = 10.0
    wind_cov: bool = True
    wind_ardupilot: bool = True
    wind_hz: _OutputRateHz = 2.0
    statustext: bool = True
    guidance: bool = True
    max_ground_speed_m_s: Annotated[float, In(1.0, 1000.0)] = 100.0
    unknown_vertical_var_m2_s2: Annotated[float, In(0.0, 1e6, lo_open=True)] = 25.0
    max_clock_backwards_s: Annotated[float, In(0.0, 3600.0)] = 0.5
    clock_window_s: Annotated[float, In(0.1, 3600.0)] = 10.0
    queue_size: Annotated[int, In(16, 1_000_000)] = 4096
    unknown_vertical_sigma_m_s: Annotated[float, In(0.0, 1e3, lo_open=True)] = 5.0
    status_values: bool = True
    system_id: _MavlinkId = 1
    component_id: _MavlinkId = MAV_COMP_ID_ONBOARD_COMPUTER
    autopilot_system_id: Annotated[int, In(0, 255)] = 0
    autopilot_component_id: Annotated[int, In(0, 255)] = 0
    velocity_message: Literal["vision_position_delta", "vision_speed_estimate", "odometry"] = "vision_position_delta"
    ap_vis_verr_min_m_s: Annotated[float, In(0.0, 100.0, lo_open=True)] = 0.1
    ap_vis_verr_max_m_s: Annotated[float, In(0.0, 100.0, lo_open=True)] = 0.5
    request_rates: bool = True
    rate_attitude_hz: _InputRateHz = 50.0
    rate_imu_hz: _InputRateHz = 50.0
    rate_baro_hz: _InputRateHz = 10.0
    rate_airspeed_hz: _InputRateHz = 10.0
    rate_gnss_hz: _InputRateHz = 5.0
    rate_home_hz: _InputRateHz = 5.0
    rate_fallback: Annotated[float, In(0.1, 0.99)] = 0.8
    rate_min_fraction: Annotated[float, In(0.01, 1.0)] = 0.25
    source_timeout_s: Annotated[float, In(0.01, 60.0)] = 1.0
    raw_imu_accel_scale_m_s2: Annotated[float, In(0.0, 1.0, lo_open=True)] = GRAVITY_M_S2 / 1000.0
    raw_imu_gyro_scale_rad_s: Annotated[float, In(0.0, 1.0, lo_open=True)] = 1e-3
    air_temperature: Literal["baro", "isa"] = "baro"
    baro_temp_clamp_c: Annotated[float, In(-40.0, 85.0)] = ARDUPILOT_BARO_TEMP_CLAMP_C
    max_clock_ahead_s: Annotated[float, In(0.0, 3600.0, lo_open=True)] = 2.0

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.ap_vis_verr_max_m_s >= self.ap_vis_verr_min_m_s, "ap_vis_verr_max_m_s",
                "must be >= ap_vis_verr_min_m_s")

    def rate_hz(self, kind: str) -> float:
        """The rate wanted of input ``kind`` (a key of :data:`SOURCES`)."""
        return float(getattr(self, f"rate_{kind}_hz"))


# ------------------------------------------------------------------------------------------------ samples
@dataclass(frozen=True, slots=True)
class HomeReading:
    """The autopilot's altitude above its home (GLOBAL_POSITION_INT ``relative_alt``) and AMSL: their difference
    is the home (reference ground) elevation the baro and GNSS heights are referred to."""

    t_us: int
    alt_amsl_m: float
    rel_alt_m: float


@dataclass(frozen=True, slots=True)
class TrackReading:
    """An external video tracker's report (CAMERA_TRACKING_IMAGE_STATUS) received at ``t_us``: the tracked point
    ``x_norm``/``y_norm`` normalised to the image (0 left/top edge, 1 right/bottom edge), ``active`` when the
    tracker reports ACTIVE tracking with a point; otherwise the point is NaN."""

    t_us: int
    x_norm: float
    y_norm: float
    active: bool


Sample = AttitudeSample | ImuSample | AirspeedSample | BaroSample | GnssSample | HomeReading | TrackReading


@dataclass(frozen=True, slots=True)
class OutputEstimate:
    """What the companion wants the autopilot to know (frames and units as in :mod:`gsoe`).

    ``vel_ne_m_s`` ground velocity with 2x2 covariance ``vel_cov_ne``; ``vel_d_m_s``/``vel_d_var`` the vertical
    part (NaN: unknown, then ``unknown_vertical_var_m2_s2`` and 0 are sent); ``wind_ne_m_s`` the air's velocity
    (blowing to) with covariance ``wind_cov_ne``; ``drift_rad``/``ata_rad`` with ``drift_sigma_rad``;
    ``quality`` in [0, 1]; ``gnss_state`` an integer :class:`nav.gnss_monitor.GnssState`.  ``roll_rad``,
    ``pitch_rad``: the AHRS attitude at ``t_us`` and ``heading_rad`` the estimate's heading (the AHRS yaw less the
    estimated yaw bias): what puts the velocity into the body frame (NaN: unknown, then no body-frame velocity is
    sent).
    """

    t_us: int
    valid: bool
    drift_rad: float
    drift_sigma_rad: float
    ata_rad: float
    vel_ne_m_s: NDArray[np.float64]
    vel_cov_ne: NDArray[np.float64]
    wind_ne_m_s: NDArray[np.float64]
    wind_cov_ne: NDArray[np.float64]
    height_agl_m: float
    quality: float
    gnss_state: int
    vel_d_m_s: float = float("nan")
    vel_d_var: float = float("nan")
    reason: str = ""
    home_amsl_m: float = float("nan")
    roll_rad: float = float("nan")
    pitch_rad: float = float("nan")
    heading_rad: float = float("nan")


def check_estimate(est: OutputEstimate, cfg: LinkConfig) -> str:
    """Empty string when ``est`` may be sent; otherwise why not.  Whether the estimate is good enough is the
    pipeline's one validity gate (``est.valid``); here only what could not be encoded as a sane message."""
    if not est.valid:
        return f"estimate invalid ({est.reason or 'no reason given'})"
    scalars = {"drift": est.drift_rad, "drift sigma": est.drift_sigma_rad, "ATA": est.ata_rad,
               "height": est.height_agl_m, "quality": est.quality}
    for name, v in scalars.items():
        if not math.isfinite(v):
            return f"{name} not finite"
    arrays = {"velocity": est.vel_ne_m_s, "velocity covariance": est.vel_cov_ne, "wind": est.wind_ne_m_s,
              "wind covariance": est.wind_cov_ne}
    for name, a in arrays.items():
        if not np.all(np.isfinite(a)):
            return f"{name} not finite"
    if np.shape(est.vel_ne_m_s) != (2,) or np.shape(est.vel_cov_ne) != (2, 2) or np.shape(est.wind_cov_ne) != (2, 2):
        return "wrong array shapes"
    if float(np.min(np.linalg.eigvalsh(est.vel_cov_ne))) < 0 or float(np.min(np.linalg.eigvalsh(est.wind_cov_ne))) < 0:
        return "covariance not positive semi-definite"
    if abs(est.drift_rad) >= math.pi / 2:
        return f"drift {math.degrees(est.drift_rad):.0f} deg out of range"
    if float(np.hypot(*est.vel_ne_m_s)) > cfg.max_ground_speed_m_s:
        return "ground speed out of range"
    if float(np.hypot(*est.wind_ne_m_s)) > cfg.max_ground_speed_m_s:
        return "wind speed out of range"
    if math.isfinite(est.vel_d_m_s) and abs(est.vel_d_m_s) > cfg.max_ground_speed_m_s:
        return "vertical speed out of range"
    return ""


def status_values(est: OutputEstimate, valid: bool) -> dict[str, float]:
    """The status named values sent whatever the estimate's validity (all finite by construction)."""
    q = est.quality if math.isfinite(est.quality) else 0.0
    return {"GSOE_Q": min(1.0, max(0.0, float(q))), "GSOE_GNSS": float(int(est.gnss_state)),
            "GSOE_VALID": 1.0 if valid else 0.0}


def wind_sigmas(wind_ne_m_s: NDArray[np.float64], cov_ne: NDArray[np.float64]) -> tuple[float, float]:
    """(one-sigma of the wind speed, RMS of the two axis sigmas) from the 2x2 wind covariance (m/s)."""
    rms = math.sqrt(max(float(np.trace(cov_ne)) / 2.0, 0.0))
    speed = float(np.hypot(*wind_ne_m_s))
    if speed < rms:  # near calm the direction, and so the projection, is undefined
        return rms, rms
    u = np.asarray(wind_ne_m_s, dtype=float) / speed
    return math.sqrt(max(float(u @ cov_ne @ u), 0.0)), rms


def wind_from_deg(wind_ne_m_s: NDArray[np.float64]) -> float:
    """Direction the wind blows *from*, degrees clockwise from north, [0, 360) (MAVLink WIND)."""
    return float(wrap_360(math.degrees(math.atan2(-wind_ne_m_s[1], -wind_ne_m_s[0]))))


def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> list[float]:
    """The body-to-NED attitude quaternion ``[w, x, y, z]`` of 3-2-1 Euler angles (MAVLink's order)."""
    cr, sr = math.cos(roll_rad / 2), math.sin(roll_rad / 2)
    cp, sp = math.cos(pitch_rad / 2), math.sin(pitch_rad / 2)
    cy, sy = math.cos(yaw_rad / 2), math.sin(yaw_rad / 2)
    return [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy]


def vertical_velocity(est: OutputEstimate, cfg: LinkConfig) -> tuple[float, float]:
    """(down velocity, its variance) to send: the estimate's, or 0 with ``unknown_vertical_var_m2_s2``."""
    if math.isfinite(est.vel_d_m_s) and math.isfinite(est.vel_d_var):
        return float(est.vel_d_m_s), float(est.vel_d_var)
    return 0.0, cfg.unknown_vertical_var_m2_s2


def body_velocity(est: OutputEstimate, cfg: LinkConfig) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The ground velocity in the body frame (FRD, m/s) and its 3x3 covariance, or None without the attitude.

    ``v_b = R_nb^T v_n`` with ``R_nb`` of (roll, pitch, the estimate's heading): the heading cancels against the one
    that made ``v_n`` north/east, so ``v_b`` is the heading-aligned velocity (ground speed along the drift angle)
    tilted by roll and pitch alone; it holds no heading of its own.
    """
    if not all(math.isfinite(a) for a in (est.roll_rad, est.pitch_rad, est.heading_rad)):
        return None
    vd, vd_var = vertical_velocity(est, cfg)
    R = R_nb_from_euler(est.roll_rad, est.pitch_rad, est.heading_rad)
    v_n = np.array([float(est.vel_ne_m_s[0]), float(est.vel_ne_m_s[1]), vd])
    cov_n = np.zeros((3, 3))
    cov_n[:2, :2] = est.vel_cov_ne
    cov_n[2, 2] = vd_var
    return R.T @ v_n, R.T @ cov_n @ R


def vision_confidence(sigma_m_s: float, cfg: LinkConfig) -> int:
    """VISION_POSITION_DELTA ``confidence`` (0-100) whose ArduPilot noise, ``EK3_VIS_VERR_MIN + (EK3_VIS_VERR_MAX -
    EK3_VIS_VERR_MIN) (1 - confidence / 100)``, is ``sigma_m_s`` (clamped to that range)."""
    lo, hi = cfg.ap_vis_verr_min_m_s, cfg.ap_vis_verr_max_m_s
    if hi <= lo:
        return 100
    return int(round(100.0 * min(1.0, max(0.0, (hi - sigma_m_s) / (hi - lo)))))


def encode_velocity(est: OutputEstimate, cfg: LinkConfig, t_usec: int, delta_us: int
                    ) -> tuple[str, dict[str, Any]] | None:
    """The velocity output of ``cfg.velocity_message`` (module docstring) stamped ``t_usec`` (autopilot clock);
    ``delta_us``: the time since the previous one (VISION_POSITION_DELTA's interval).  None when a body-frame form
    lacks the attitude."""
    vd, vd_var = vertical_velocity(est, cfg)
    if cfg.velocity_message == "vision_speed_estimate":
        c = est.vel_cov_ne
        cov = [float(c[0, 0]), float(c[0, 1]), 0.0, float(c[1, 0]), float(c[1, 1]), 0.0, 0.0, 0.0, float(vd_var)]
        return ("VISION_SPEED_ESTIMATE", {"usec": t_usec, "x": float(est.vel_ne_m_s[0]),
                                          "y": float(est.vel_ne_m_s[1]), "z": vd, "covariance": cov})
    body = body_velocity(est, cfg)
    if body is None:
        return None
    v_b, cov_b = body
    if cfg.velocity_message == "vision_position_delta":
        dt_s = max(delta_us, 1) / 1e6
        sigma = math.sqrt(max(float(np.trace(cov_b[:2, :2])) / 2.0, 0.0))
        return ("VISION_POSITION_DELTA", {"time_usec": t_usec, "time_delta_usec": int(max(delta_us, 1)),
                                          "angle_delta": [0.0, 0.0, 0.0],
                                          "position_delta": [float(v) * dt_s for v in v_b],
                                          "confidence": float(vision_confidence(sigma, cfg))})
    nan = math.nan
    vel_cov = [nan] * 21  # upper triangle of the 6x6 (vx, vy, vz, rates): the velocity block, rates unknown
    for (i, j), k in {(0, 0): 0, (0, 1): 1, (0, 2): 2, (1, 1): 6, (1, 2): 7, (2, 2): 11}.items():
        vel_cov[k] = float(cov_b[i, j])
    return ("ODOMETRY", {"time_usec": t_usec, "frame_id": MAV_FRAME_LOCAL_FRD, "child_frame_id": MAV_FRAME_BODY_FRD,
                         "x": nan, "y": nan, "z": nan,
                         "q": quat_from_euler(est.roll_rad, est.pitch_rad, est.heading_rad),
                         "vx": float(v_b[0]), "vy": float(v_b[1]), "vz": float(v_b[2]),
                         "rollspeed": nan, "pitchspeed": nan, "yawspeed": nan, "pose_covariance": [nan] * 21,
                         "velocity_covariance": vel_cov, "reset_counter": 0,
                         "estimator_type": MAV_ESTIMATOR_TYPE_VIO, "quality": int(round(100 * est.quality))})


def encode_outputs(est: OutputEstimate, cfg: LinkConfig, kinds: set[str], *, t_offset_us: int = 0,
                   vision_delta_us: int | None = None) -> dict[str, tuple[str, dict[str, Any]]]:
    """MAVLink message names and fields for the requested output ``kinds`` (``named``, ``vision``, ``wind``).

    The estimate must have passed :func:`check_estimate`.  Stamps are ``est.t_us - t_offset_us`` (the autopilot's
    clock when ``t_offset_us`` is the link's offset, :class:`LinkClock`).  ``vision`` is the velocity output of
    :func:`encode_velocity` (``vision_delta_us``: the time since the last one, default one period of
    ``vision_speed_hz``); VISION_SPEED_ESTIMATE is returned with its fields as plain numbers, the link turns it into
    a MAVSDK ``VisionSpeedEstimate``.
    """
    out: dict[str, tuple[str, dict[str, Any]]] = {}
    t_usec = max(int(est.t_us) - int(t_offset_us), 0)
    t_ms = int(t_usec // 1000) & 0xFFFFFFFF
    if "named" in kinds and cfg.named_values == "named_value_float":
        vals = {"GSOE_DRIFT": math.degrees(est.drift_rad), "GSOE_ATA": float(wrap_360(math.degrees(est.ata_rad)))}
        for name, v in vals.items():
            out[f"named:{name}"] = ("NAMED_VALUE_FLOAT", {"time_boot_ms": t_ms, "name": name, "value": float(v)})
    elif "named" in kinds and cfg.named_values == "debug_vect":
        out["named:GSOE"] = ("DEBUG_VECT", {"name": "GSOE", "time_usec": t_usec,
                                            "x": math.degrees(est.drift_rad),
                                            "y": float(wrap_360(math.degrees(est.ata_rad))), "z": est.quality})
    if "vision" in kinds and cfg.vision_speed:
        delta = round(1e6 / cfg.vision_speed_hz) if vision_delta_us is None else vision_delta_us
        vel = encode_velocity(est, cfg, t_usec, delta)
        if vel is not None:
            out["vision"] = vel
    if "wind" in kinds:
        speed = float(np.hypot(*est.wind_ne_m_s))
        if cfg.wind_cov:
            speed_sigma, rms_sigma = wind_sigmas(est.wind_ne_m_s, est.wind_cov_ne)
            alt = est.height_agl_m + (est.home_amsl_m if math.isfinite(est.home_amsl_m) else 0.0)
            out["wind_cov"] = ("WIND_COV", {"time_usec": t_usec, "wind_x": float(est.wind_ne_m_s[0]),
                                            "wind_y": float(est.wind_ne_m_s[1]), "wind_z": 0.0,
                                            "var_horiz": rms_sigma, "var_vert": cfg.unknown_vertical_sigma_m_s,
                                            "wind_alt": float(alt), "horiz_accuracy": speed_sigma,
                                            "vert_accuracy": cfg.unknown_vertical_sigma_m_s})
        if cfg.wind_ardupilot:
            out["wind"] = ("WIND", {"direction": wind_from_deg(est.wind_ne_m_s), "speed": speed, "speed_z": 0.0})
    return out


# ------------------------------------------------------------------------------------------------ telemetry
class ClockSync:
    """Maps a vehicle timestamp (us since its boot) to the companion's clock (us): ``t = t_vehicle + offset``,
    with ``offset`` the minimum of ``receive - send`` over a sliding window (the least-delayed packet)."""

    def __init__(self, window_s: float) -> None:
        self._window_us = window_s * 1e6
        # (receive_us, receive - send) of the samples that can still be the window's minimum: receive times and
        # offsets both increasing, so the minimum is the first (a sliding-window minimum, O(1) per sample)
        self._samples: deque[tuple[int, int]] = deque()
        self.offset_us: int | None = None

    def observe(self, vehicle_us: int, receive_us: int) -> int:
        d = receive_us - vehicle_us
        s = self._samples
        while s and s[-1][1] >= d:     # never the minimum again: this sample is no larger and leaves the window later
            s.pop()
        s.append((receive_us, d))
        cutoff = receive_us - self._window_us
        while s[0][0] < cutoff:
            s.popleft()
        self.offset_us = s[0][1]
        return vehicle_us + self.offset_us

    def reset(self) -> None:
        self._samples.clear()
        self.offset_us = None


def now_us() -> int:
    """The companion's clock: monotonic microseconds."""
    return time.monotonic_ns() // 1000


@dataclass
class StreamClock:
    """One input kind's mapping of the autopilot's clock onto the samples' ``t_us``: ``t_us = vehicle_us +
    offset_us`` (the link's offset; re-chosen for the kind when its autopilot clock jumps back)."""

    offset_us: int


class LinkClock:
    """The samples' clock (module docstring): the autopilot's clock shifted by one offset, chosen at the first stamp
    as ``receive time - stamp`` so that it starts at the companion's monotonic clock ``clock``.

    :meth:`now_us` is the newest stamp plus the companion time since it arrived (the link silent: time still
    passes); :meth:`from_companion_us` maps a companion time (a camera's capture) with the least-delayed attitude
    packet's offset (:class:`ClockSync`, right when the autopilot runs in real time); :meth:`to_vehicle_us` maps a
    sample time back to the autopilot's clock (what the outputs are stamped with).
    """

    def __init__(self, window_s: float, clock: Callable[[], int] = now_us) -> None:
        self._clock = clock
        self.offset_us: int | None = None
        self.sync = ClockSync(window_s)
        self._newest_us: int | None = None
        self._newest_recv_us = 0

    def anchor(self, vehicle_us: int, receive_us: int) -> int:
        """The link's offset (chosen now if this is the first stamp)."""
        if self.offset_us is None:
            self.offset_us = receive_us - vehicle_us
            log.info("autopilot clock: samples' t_us = autopilot us %+d us", self.offset_us)
        return self.offset_us

    def observe(self, t_us: int, receive_us: int, attitude: bool = False) -> None:
        if self._newest_us is None or t_us > self._newest_us:
            self._newest_us, self._newest_recv_us = t_us, receive_us
        if attitude:
            self.sync.observe(t_us, receive_us)

    def newest_us(self) -> int:
        """The newest stamp received (the companion's clock before any)."""
        return self._newest_us if self._newest_us is not None else self._clock()

    def now_us(self) -> int:
        recv = self._clock()
        if self._newest_us is None:
            return recv
        return self._newest_us + max(recv - self._newest_recv_us, 0)

    def from_companion_us(self, companion_us: int) -> int:
        if self.sync.offset_us is not None:
            return companion_us - self.sync.offset_us
        return companion_us - self._clock() + self.now_us()

    def to_vehicle_us(self, t_us: int) -> int:
        return t_us - (self.offset_us or 0)


def _plausible_pressure(p_hpa: float) -> bool:
    """A static pressure (hPa) whose pressure altitude lies in :data:`ALT_RANGE_M` (the air density's, the ground
    reference's: one glitch must not become the ground)."""
    return (math.isfinite(p_hpa) and p_hpa > 0.0
            and ALT_RANGE_M[0] <= float(pressure_altitude_m(100.0 * p_hpa)) <= ALT_RANGE_M[1])


def _finite(*values: object) -> bool:
    """Whether every value is a finite number (telemetry fields may be anything a sender put there)."""
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


def _field(f: dict[str, Any], name: str) -> float:
    """A numeric field of a message (MAVSDK's JSON writes NaN as null)."""
    v = f[name]
    return math.nan if v is None else float(v)


def fields_json(fields: dict[str, Any]) -> str:
    """Message fields as MAVSDK's JSON: NaN (MAVLink's "unknown") as null, which MAVSDK reads back as NaN (its
    parser refuses a bare NaN, and the whole message with it)."""
    def clean(v: Any) -> Any:
        if isinstance(v, float) and math.isnan(v):
            return None
        if isinstance(v, list):
            return [clean(x) for x in v]
        return v
    return json.dumps({k: clean(v) for k, v in fields.items()}, allow_nan=False)


def rates_text(granted: dict[str, tuple[str, float]]) -> str:
    """The STATUSTEXT telling what rates the autopilot granted, e.g. ``GSOE Hz ATT 40 IMU 40 BARO 10 ...``
    (``granted``: kind -> (message, Hz); 0 Hz: none granted)."""
    parts = [f"{RATE_NAMES.get(k, k)} {hz:.3g}" for k, (_, hz) in granted.items()]
    return ("GSOE Hz " + " ".join(parts))[:50]


class TelemetryGuard:
    """Validates raw telemetry into samples; counts what it rejects (``rejected[kind:reason]``)."""

    def __init__(self, cfg: LinkConfig, clock: Callable[[], int] = now_us) -> None:
        self.cfg = cfg
        self.clock = clock
        self.rejected: dict[str, int] = {}
        self.accepted: dict[str, int] = {}
        #: the autopilot's (system, component): the only sender telemetry is taken from (nav.hygiene)
        self.senders = AutopilotSenders(cfg.autopilot_system_id, cfg.autopilot_component_id)
        self.link_clock = LinkClock(cfg.clock_window_s, clock)
        #: per kind: t_us = autopilot us + offset_us (the companion logs every new one, clock_sync.csv)
        self._sync: dict[str, StreamClock] = {}
        self._last_vehicle_us: dict[str, int] = {}
        self.ref_lat_lon: tuple[float, float] | None = None
        #: per kind, message name -> companion time it last arrived (the source preference)
        self._seen: dict[str, dict[str, int]] = {}
        self._kind_of = {name: kind for kind, names in SOURCES.items() for name in names}
        self.used: dict[str, str] = {}  # kind -> the message in use
        self._pressure_pa = math.nan
        self._ground_air = GroundAir(self.cfg.baro_temp_clamp_c)
        self._back: dict[str, list[int]] = {}
        #: the autopilot's flight software, "" until known: ``"ArduPilot 4.5.7"`` (:meth:`firmware_version`)
        self.firmware = ""
        self._autopilot_type: int | None = None          # MAV_AUTOPILOT of the autopilot's own HEARTBEAT
        self._version: tuple[int, int, int] | None = None

    def _reject(self, kind: str, reason: str) -> None:
        key = f"{kind}:{reason}"
        n = self.rejected.get(key, 0) + 1
        self.rejected[key] = n
        if n == 1 or n % 100 == 0:
            log.warning("rejected %s telemetry (%s), %d so far", kind, reason, n)

    def _stamp(self, kind: str, vehicle_us: int) -> int | None:
        """The samples' time of an autopilot-stamped sample (:class:`LinkClock`), or None (rejected) when its time
        went backwards or lies beyond ``max_clock_ahead_s`` of the newest stamp; an unstamped one (``vehicle_us``
        <= 0) gets the newest stamp."""
        recv = self.clock()
        lc = self.link_clock
        if vehicle_us <= 0:
            return lc.newest_us()
        last = self._last_vehicle_us.get(kind)
        sc = self._sync.get(kind)
        if sc is None:
            sc = self._sync[kind] = StreamClock(lc.anchor(vehicle_us, recv))
        if last is not None and vehicle_us <= last:
            if last - vehicle_us <= self.cfg.max_clock_backwards_s * 1e6:
                self._reject(kind, "time not increasing")
                return None
            # a jump back: a reboot once CLOCK_JUMP_CONFIRM stamps in a row carry on from it, else a stray stamp
            back = self._back.setdefault(kind, [])
            if back and vehicle_us <= back[-1]:
                back.clear()
            back.append(vehicle_us)
            if len(back) < CLOCK_JUMP_CONFIRM:
                self._reject(kind, "time jumped back")
                return None
            back.clear()
            sc.offset_us = lc.now_us() - vehicle_us
            log.warning("%s: vehicle clock jumped back %.1f s (reboot?): clock re-synchronised", kind,
                        (last - vehicle_us) / 1e6)
            if kind == "attitude":
                lc.sync.reset()
        self._back.pop(kind, None)
        t = vehicle_us + sc.offset_us
        if lc.offset_us is not None and t - lc.now_us() > self.cfg.max_clock_ahead_s * 1e6:
            self._reject(kind, "stamp ahead of the autopilot's clock")
            return None
        self._last_vehicle_us[kind] = vehicle_us
        lc.observe(t, recv, attitude=kind == "attitude")
        return t

    def _preferred(self, kind: str, name: str) -> bool:
        """Whether message ``name`` is the one of its kind to use now (module docstring)."""
        now = self.clock()
        seen = self._seen.setdefault(kind, {})
        seen[name] = now
        timeout_us = self.cfg.source_timeout_s * 1e6
        for better in SOURCES[kind]:
            if better == name:
                break
            t = seen.get(better)
            if t is not None and now - t <= timeout_us:
                return False
        if self.used.get(kind) != name:
            log.info("%s from %s", kind, name)
            self.used[kind] = name
        return True

    def message(self, name: str, f: dict[str, Any], sender: tuple[int, int] | None = None) -> Sample | None:
        """A sample from one message's fields (MAVSDK ``MavlinkDirect`` JSON or pymavlink ``to_dict``), or None
        (not a preferred source now, rejected, or a message that only updates the air data).  With ``sender``
        (system, component), only the autopilot's messages are taken and its HEARTBEAT tells who it is
        (:class:`nav.hygiene.AutopilotSenders`)."""
        kind = self._kind_of.get(name)
        if sender is not None:
            if name == "HEARTBEAT":
                self.senders.heartbeat(*sender, int(f.get("autopilot", 8)), int(f.get("type", 0)))
                if self._autopilot_type is None and self.senders.known and \
                        tuple(sender) == (self.senders.system_id, self.senders.component_id):
                    self._autopilot_type = int(f.get("autopilot", 8))
                    self._apply_firmware()
                return None
            why = self.senders.check(name, *sender)
            if why:
                self._reject(kind or ("version" if name == "AUTOPILOT_VERSION" else "tracking"), why)
                return None
        if kind is None:
            if name == "AUTOPILOT_VERSION":
                self._version_msg(f)
                return None
            return self.tracking(f) if name == "CAMERA_TRACKING_IMAGE_STATUS" else None
        try:
            if name == "HIGHRES_IMU":
                self._air_from_highres(f)
            elif name == "SCALED_PRESSURE":
                self._air_from_scaled_pressure(f)
            if not self._preferred(kind, name):
                return None
            if kind == "attitude":
                return self._attitude_msg(name, f)
            if kind == "imu":
                return self._imu_msg(name, f)
            if kind == "baro":
                return self._baro_msg(name, f)
            if kind == "airspeed":
                return self.airspeed_eas(_field(f, "airspeed"))
            if kind == "gnss":
                return self.gps_raw_int(f)
            return self.home(_field(f, "alt") / 1000.0, _field(f, "relative_alt") / 1000.0,
                             int(f["time_boot_ms"]) * 1000)
        except (KeyError, TypeError, ValueError, IndexError):
            self._reject(kind, f"malformed {name}")
            return None

    def _attitude_msg(self, name: str, f: dict[str, Any]) -> AttitudeSample | None:
        us = int(f["time_boot_ms"]) * 1000
        if name == "ATTITUDE":
            r, p, y = (_field(f, k) for k in ("roll", "pitch", "yaw"))
        else:  # ATTITUDE_QUATERNION: w, x, y, z
            w, x, yy, z = (_field(f, k) for k in ("q1", "q2", "q3", "q4"))
            r = math.atan2(2 * (w * x + yy * z), 1 - 2 * (x * x + yy * yy))
            p = math.asin(max(-1.0, min(1.0, 2 * (w * yy - z * x))))
            y = math.atan2(2 * (w * z + x * yy), 1 - 2 * (yy * yy + z * z))
        return self.attitude(math.degrees(r), math.degrees(p), math.degrees(y), us)

    def _imu_msg(self, name: str, f: dict[str, Any]) -> ImuSample | None:
        axes = ("x", "y", "z")
        if name == "HIGHRES_IMU":
            upd = f.get("fields_updated")
            if upd is not None and int(upd) & 0x3F != 0x3F:  # bits 0-5: accelerometer and gyro updated
                return None
            acc = tuple(_field(f, a + "acc") for a in axes)
            gyr = tuple(_field(f, a + "gyro") for a in axes)
            return self.imu(gyr, acc, int(f["time_usec"]))  # type: ignore[arg-type]
        if name == "RAW_IMU":
            ka, kg, us = self.cfg.raw_imu_accel_scale_m_s2, self.cfg.raw_imu_gyro_scale_rad_s, int(f["time_usec"])
        else:  # SCALED_IMU, SCALED_IMU2, SCALED_IMU3: mG and mrad/s
            ka, kg, us = GRAVITY_M_S2 / 1000.0, 1e-3, int(f["time_boot_ms"]) * 1000
        acc = tuple(ka * _field(f, a + "acc") for a in axes)
        gyr = tuple(kg * _field(f, a + "gyro") for a in axes)
        return self.imu(gyr, acc, us)  # type: ignore[arg-type]

    def _baro_msg(self, name: str, f: dict[str, Any]) -> BaroSample | None:
        if name == "SCALED_PRESSURE":
            return self.baro(_field(f, "press_abs"), int(f["time_boot_ms"]) * 1000)
        alt = _field(f, "altitude_monotonic")  # ALTITUDE (PX4): the baro's, never jumps
        if not math.isfinite(alt) or not ALT_RANGE_M[0] <= alt <= ALT_RANGE_M[1]:
            self._reject("baro", "altitude not finite or out of range")
            return None
        amsl = _field(f, "altitude_amsl")
        if not math.isfinite(self._pressure_pa) and math.isfinite(amsl):
            self._pressure_pa = isa_pressure_pa(amsl)
        t = self._stamp("baro", int(f["time_usec"]))
        if t is None:
            return None
        self._ok("baro")
        return BaroSample(t, alt)

    def _air_from_scaled_pressure(self, f: dict[str, Any]) -> None:
        p_hpa, t_cdeg = _field(f, "press_abs"), _field(f, "temperature")
        if not _plausible_pressure(p_hpa):
            return
        self._pressure_pa = 100.0 * p_hpa
        if math.isfinite(t_cdeg) and -8000.0 < t_cdeg < 8000.0:
            self._ground_air.update(self._pressure_pa, t_cdeg / 100.0)

    def _air_from_highres(self, f: dict[str, Any]) -> None:
        upd = int(f.get("fields_updated") or 0)
        p_hpa, t_c = (_field(f, k) if k in f else math.nan for k in ("abs_pressure", "temperature"))
        if upd & (1 << 9) and _plausible_pressure(p_hpa) and "SCALED_PRESSURE" not in self._seen.get("baro", {}):
            self._pressure_pa = 100.0 * p_hpa
            if upd & (1 << 12) and math.isfinite(t_c) and -80.0 < t_c < 80.0:
                self._ground_air.update(self._pressure_pa, t_c)

    def _version_msg(self, f: dict[str, Any]) -> None:
        """AUTOPILOT_VERSION: its ``flight_sw_version`` (:func:`nav.hygiene.flight_sw_version`)."""
        version = flight_sw_version(f.get("flight_sw_version"))
        if version is None:
            self._reject("version", "malformed AUTOPILOT_VERSION")
            return
        self.firmware_version(*version)

    @property
    def version_known(self) -> bool:
        return self._version is not None

    def firmware_version(self, major: int, minor: int, patch: int) -> None:
        """The autopilot's flight software version (its AUTOPILOT_VERSION, asked for on connecting).  An
        ArduPilot's decides the baro temperature clamp of the airspeed's air density (35 degC from 4.0 on, 25 degC
        before; :mod:`common.atmosphere`); ``baro_temp_clamp_c`` applies until then and to other autopilots."""
        if not all(isinstance(v, int) and 0 <= v < 256 for v in (major, minor, patch)):
            log.warning("autopilot version %r.%r.%r not understood: baro temperature clamp stays %.0f degC",
                        major, minor, patch, self._ground_air.baro_temp_clamp_c)
            return
        self._version = (major, minor, patch)
        self._apply_firmware()

    def _apply_firmware(self) -> None:
        if self._version is None or self._autopilot_type is None:
            return
        major, minor, patch = self._version
        before = self.firmware
        if self._autopilot_type == MAV_AUTOPILOT_ARDUPILOTMEGA:
            self.firmware = f"ArduPilot {major}.{minor}.{patch}"
            self._ground_air.set_clamp(ardupilot_major_baro_temp_clamp_c(major))
        else:
            self.firmware = f"autopilot type {self._autopilot_type} {major}.{minor}.{patch}"
        if self.firmware != before:
            log.info("autopilot firmware: %s; baro temperature clamp %.0f degC", self.firmware,
                     self._ground_air.baro_temp_clamp_c)

    @property
    def baro_temp_clamp_c(self) -> float:
        """The baro temperature clamp in use (degC)."""
        return self._ground_air.baro_temp_clamp_c

    def eas_to_tas(self) -> float:
        """``sqrt(rho0 / rho)`` at the last baro pressure (``air_temperature``; :mod:`common.atmosphere`), nan
        before the first baro report."""
        if not math.isfinite(self._pressure_pa):
            return math.nan
        if self.cfg.air_temperature == "isa" or not math.isfinite(self._ground_air.pressure_pa):
            return float(eas_to_tas_ratio(self._pressure_pa))
        return self._ground_air.ratio(self._pressure_pa)

    def airspeed_eas(self, eas_m_s: float, vehicle_us: int = 0) -> AirspeedSample | None:
        """An equivalent airspeed (VFR_HUD) made true with the air density of the last baro report."""
        if not (isinstance(eas_m_s, int | float) and math.isfinite(eas_m_s)):
            self._reject("airspeed", "not finite")
            return None
        ratio = self.eas_to_tas()
        if not math.isfinite(ratio):
            self._reject("airspeed", "no air density yet (no baro)")
            return None
        tas = float(eas_m_s) * ratio
        s = self.airspeed(tas, vehicle_us)
        return AirspeedSample(s.t_us, s.tas_m_s, float(eas_m_s)) if s is not None else None

    def _ok(self, kind: str) -> None:
        self.accepted[kind] = self.accepted.get(kind, 0) + 1

    def _accept(self, kind: str, vehicle_us: int, usable: bool, in_range: Callable[[], bool],
                unusable: str = "not finite") -> int | None:
        """The samples' time of a reading of ``kind`` (:meth:`_stamp`), counted as accepted; None, the reason
        counted, when it is not ``usable`` (``unusable`` says why), not ``in_range()`` (asked only of a usable one)
        or its stamp is refused."""
        if not usable:
            self._reject(kind, unusable)
            return None
        if not in_range():
            self._reject(kind, "out of range")
            return None
        t = self._stamp(kind, vehicle_us)
        if t is not None:
            self._ok(kind)
        return t

    def attitude(self, roll_deg: float, pitch_deg: float, yaw_deg: float, vehicle_us: int) -> AttitudeSample | None:
        usable = _finite(roll_deg, pitch_deg, yaw_deg)
        roll, pitch, yaw = (math.radians(v) if usable else math.nan for v in (roll_deg, pitch_deg, yaw_deg))
        t = self._accept("attitude", vehicle_us, usable,
                         lambda: abs(roll) <= math.pi and abs(pitch) <= MAX_PITCH_RAD and abs(yaw) <= 2 * math.pi)
        return None if t is None else AttitudeSample(t, roll, pitch, yaw)

    def imu(self, gyro: tuple[float, float, float], accel: tuple[float, float, float],
            vehicle_us: int) -> ImuSample | None:
        g = np.asarray(gyro, dtype=np.float64)
        a = np.asarray(accel, dtype=np.float64)
        t = self._accept("imu", vehicle_us, bool(np.all(np.isfinite(g)) and np.all(np.isfinite(a))),
                         lambda: np.max(np.abs(g)) <= MAX_GYRO_RAD_S and np.max(np.abs(a)) <= MAX_ACCEL_M_S2)
        return None if t is None else ImuSample(t, g, a)

    def airspeed(self, tas_m_s: float, vehicle_us: int = 0) -> AirspeedSample | None:
        """A true airspeed (stamped ``vehicle_us``, or the newest autopilot stamp when it carries none)."""
        t = self._accept("airspeed", vehicle_us, _finite(tas_m_s), lambda: 0.0 <= tas_m_s <= MAX_AIRSPEED_M_S)
        return None if t is None else AirspeedSample(t, float(tas_m_s))

    def baro(self, pressure_hpa: float, vehicle_us: int) -> BaroSample | None:
        usable = _finite(pressure_hpa) and pressure_hpa > 0.0
        alt = float(pressure_altitude_m(100.0 * pressure_hpa)) if usable else math.nan
        t = self._accept("baro", vehicle_us, usable, lambda: ALT_RANGE_M[0] <= alt <= ALT_RANGE_M[1],
                         unusable="not finite or not positive")
        return None if t is None else BaroSample(t, alt, pressure_pa=float(pressure_hpa) * 100.0)

    def home(self, alt_amsl_m: float, rel_alt_m: float, vehicle_us: int = 0) -> HomeReading | None:
        t = self._accept("position", vehicle_us, _finite(alt_amsl_m, rel_alt_m),
                         lambda: ALT_RANGE_M[0] <= alt_amsl_m <= ALT_RANGE_M[1] and abs(rel_alt_m) <= ALT_RANGE_M[1])
        return None if t is None else HomeReading(t, float(alt_amsl_m), float(rel_alt_m))

    def tracking(self, f: dict[str, Any]) -> TrackReading | None:
        """CAMERA_TRACKING_IMAGE_STATUS fields: an active point in [0, 1]^2, or an inactive report (NaN point)."""
        try:
            status, mode = int(f["tracking_status"]), int(f["tracking_mode"])
            # MAVSDK's JSON writes NaN ("unknown" in this message) as null
            x, y = (math.nan if f[k] is None else float(f[k]) for k in ("point_x", "point_y"))
        except (KeyError, TypeError, ValueError):
            self._reject("tracking", "malformed")
            return None
        active = status == TRACKING_STATUS_ACTIVE and mode == TRACKING_MODE_POINT
        if active and not (math.isfinite(x) and math.isfinite(y) and 0.0 <= x <= 1.0 and 0.0 <= y <= 1.0):
            self._reject("tracking", "point not finite or outside the image")
            return None
        self._ok("tracking")
        if not active:
            x = y = math.nan
        return TrackReading(self.link_clock.newest_us(), x, y, active)

    def gps_raw_int(self, f: dict[str, Any]) -> GnssSample | None:
        """GPS_RAW_INT fields (as MAVSDK's MavlinkDirect JSON or pymavlink's ``to_dict``)."""
        try:
            fix = int(f["fix_type"])
            sats = int(f["satellites_visible"])
            vehicle_us = int(f["time_usec"])
            lat, lon, alt = f["lat"] / 1e7, f["lon"] / 1e7, f["alt"] / 1000.0
            vel, cog = f["vel"], f["cog"]
            h_acc, v_acc, vel_acc = f.get("h_acc", 0), f.get("v_acc", 0), f.get("vel_acc", 0)
        except (KeyError, TypeError, ValueError):
            self._reject("gnss", "malformed")
            return None
        if sats == 255:  # UINT8_MAX: unknown
            sats = 0
        # without a fix ArduPlane keeps sending GPS_RAW_INT with its last fix's time_usec (frozen): such a report
        # carries the newest autopilot stamp, so that the loss reaches the GNSS monitor as what it is
        t = self._stamp("gnss", vehicle_us if fix >= GPS_FIX_TYPE_3D else 0)
        if t is None:
            return None
        nan = math.nan
        hacc = h_acc / 1000.0 if h_acc else nan
        pos = vel_ne = (nan, nan)
        if fix >= 3:
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and ALT_RANGE_M[0] <= alt <= ALT_RANGE_M[1]):
                self._reject("gnss", "position out of range")
                return None
            if self.ref_lat_lon is None:
                self.ref_lat_lon = (lat, lon)
                log.info("local NED reference set at the first 3D fix: %.7f, %.7f", lat, lon)
            rl, rn = self.ref_lat_lon
            pos = (math.radians(lat - rl) * EARTH_RADIUS_M,
                   math.radians(lon - rn) * EARTH_RADIUS_M * math.cos(math.radians(rl)))
            if vel != 65535 and cog != 65535:
                speed, course = vel / 100.0, math.radians(cog / 100.0)
                vel_ne = (speed * math.cos(course), speed * math.sin(course))
        self._ok("gnss")
        # the down components are not known here: the companion refers the height to home
        return GnssSample(t, np.array([pos[0], pos[1], nan]), np.array([vel_ne[0], vel_ne[1], nan]),
                          fix_ok=fix >= GPS_FIX_TYPE_3D, n_sats=sats, h_acc_m=hacc,
                          v_acc_m_s=vel_acc / 1000.0 if vel_acc else nan, lat_deg=lat, lon_deg=lon,
                          alt_msl_m=alt if fix >= GPS_FIX_TYPE_3D else nan,
                          alt_acc_m=v_acc / 1000.0 if v_acc else nan, fix_type=fix)


# ------------------------------------------------------------------------------------------------ the link
@dataclass
class LinkStats:
    connected: bool = False
    sent: dict[str, int] = field(default_factory=dict)
    send_errors: dict[str, int] = field(default_factory=dict)
    suppressed: dict[str, int] = field(default_factory=dict)
    dropped_samples: int = 0
    acks: list[dict[str, Any]] = field(default_factory=list)
    send_latency_us: dict[str, deque[int]] = field(default_factory=dict)
    #: kind -> (message, rate in Hz) the autopilot granted (0: refused at every rate; module docstring)
    rates_granted: dict[str, tuple[str, float]] = field(default_factory=dict)
    #: every rate request: (message, Hz asked, MAV_RESULT or -1 without an answer)
    rate_requests: list[tuple[str, float, int]] = field(default_factory=list)


class CompanionLink:
    """MAVSDK connection in a background asyncio thread.

    ``start()`` connects and subscribes (returns False on timeout, the caller may retry); samples arrive in
    :attr:`samples` (a ``queue.Queue``); ``send_estimate``, ``send_statustext``, ``send_heading_command`` return at
    once (the sends run on the link's loop).
    """

    def __init__(self, url: str, cfg: LinkConfig, clock: Callable[[], int] = now_us) -> None:
        self.url = url
        self.cfg = cfg
        self.guard = TelemetryGuard(cfg, clock)
        self.samples: queue.Queue[Sample] = queue.Queue(maxsize=cfg.queue_size)
        self.stats = LinkStats()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="mavsdk-link", daemon=True)
        self._thread.start()
        self._mavsdk: Any = None
        self._system: Any = None
        self._direct: Any = None
        self._mocap: Any = None
        self._tasks: list[asyncio.Task[Any]] = []
        self._last_sent_us: dict[str, int] = {}
        self.target_system = 1
        self.target_component = 1

    # ---------------------------------------------------------------- connection
    @property
    def started(self) -> bool:
        """An autopilot was found and the streams are subscribed (MAVSDK then reconnects by itself)."""
        return self._system is not None

    def start(self, timeout_s: float | None = None) -> bool:
        t = self.cfg.connect_timeout_s if timeout_s is None else timeout_s
        fut = asyncio.run_coroutine_threadsafe(self._connect(t), self._loop)
        try:
            return bool(fut.result(timeout=t + 5.0))
        except Exception as e:  # a link that cannot start is reported, the companion keeps running
            log.error("MAVSDK link to %s failed: %s", self.url, e)
            return False

    async def _connect(self, timeout_s: float) -> bool:
        from mavsdk import LogLevel, log_subscribe
        from mavsdk.asyncio import Configuration, Mavsdk
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
        from mavsdk.asyncio.plugins.mocap import MocapAsync

        if self._mavsdk is None:
            levels = {LogLevel.DEBUG: logging.DEBUG, LogLevel.INFO: logging.INFO, LogLevel.WARN: logging.WARNING}
            mavsdk_log = logging.getLogger("mavsdk")

            def _to_logging(level: Any, message: str, _file: str | None, _line: int) -> bool:
                mavsdk_log.log(levels.get(level, logging.ERROR), "%s", message)
                return True  # MAVSDK's own console printing off: everything goes through logging

            log_subscribe(_to_logging)
            # the vehicle's system id, component MAV_COMP_ID_ONBOARD_COMPUTER: what ground stations (and
            # nav.gcs_display) expect of a companion computer
            cfg = Configuration.create_manual(self.cfg.system_id, self.cfg.component_id, True)
            self._mavsdk = Mavsdk(cfg)
            await self._mavsdk.add_any_connection(self.url)
        system = await self._mavsdk.first_autopilot(timeout_s=timeout_s)
        if system is None:
            log.warning("no autopilot on %s within %.1f s", self.url, timeout_s)
            return False
        self._system = system
        self.target_system = await system.get_system_id()
        self.guard.senders.discovered(self.target_system, await system.component_ids())
        self._direct = MavlinkDirectAsync(system)
        self._mocap = MocapAsync(system)
        names = [n for kind_names in SOURCES.values() for n in kind_names] + ["CAMERA_TRACKING_IMAGE_STATUS",
                                                                             "HEARTBEAT", "AUTOPILOT_VERSION"]
        self._tasks = [asyncio.ensure_future(self._pump(self._direct.subscribe_message(n), self._converter(n)))
                       for n in names]
        self._tasks.append(asyncio.ensure_future(self._watch(system)))
        self._tasks.append(asyncio.ensure_future(self._request_version()))
        self.stats.connected = True
        log.info("connected to autopilot (system %d) on %s", self.target_system, self.url)
        if self.cfg.request_rates:
            self._tasks.append(asyncio.ensure_future(self._request_rates()))
        return True

    def _converter(self, name: str) -> Callable[[Any], Sample | None]:
        g = self.guard
        return lambda m: g.message(name, json.loads(m.fields_json), (int(m.system_id), int(m.component_id)))

    async def _request_rates(self) -> None:
        """Ask for each kind's rate (module docstring); log what was granted and tell the ground station."""
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkMessage

        cfg = self.cfg
        granted: dict[str, tuple[str, float]] = {}
        unsupported = False
        for kind, names in SOURCES.items():
            want = cfg.rate_hz(kind)
            granted[kind] = (names[0], 0.0)
            for name in names:
                hz = want
                while hz >= want * cfg.rate_min_fraction - 1e-9 and not unsupported:
                    fields = {"target_system": self.target_system, "target_component": self.target_component,
                              "command": MAV_CMD_SET_MESSAGE_INTERVAL, "confirmation": 0,
                              "param1": float(MESSAGE_IDS[name]), "param2": float(round(1e6 / hz)), "param3": 0.0,
                              "param4": 0.0, "param5": 0.0, "param6": 0.0, "param7": 0.0}
                    msg = MavlinkMessage(message_name="COMMAND_LONG", target_system_id=self.target_system,
                                         target_component_id=self.target_component, fields_json=json.dumps(fields))
                    try:
                        ack = await self._direct.send_command(msg)
                        result = int(json.loads(ack.fields_json).get("result", -1)) if ack.fields_json else -1
                    except Exception as e:  # no answer: the autopilot may not know the command
                        log.debug("rate request %s %.3g Hz: %s", name, hz, e)
                        result = -1
                    self.stats.rate_requests.append((name, hz, result))
                    if result == MAV_RESULT_ACCEPTED:
                        granted[kind] = (name, hz)
                        break
                    if result in (MAV_RESULT_UNSUPPORTED, -1):
                        unsupported = True
                        break
                    hz *= cfg.rate_fallback
                if granted[kind][1] > 0.0 or unsupported:
                    break
        self.stats.rates_granted = granted
        if unsupported:
            log.warning("the autopilot does not set message rates (MAV_CMD_SET_MESSAGE_INTERVAL unanswered or "
                        "unsupported): using the rates it streams")
            return
        for kind, (name, hz) in granted.items():
            if hz <= 0.0:
                log.warning("rate of %s refused for every message of %s", kind, SOURCES[kind])
            elif hz < cfg.rate_hz(kind):
                log.warning("%s: %s granted at %.3g Hz (asked %.3g Hz)", kind, name, hz, cfg.rate_hz(kind))
            else:
                log.info("%s: %s at %.3g Hz", kind, name, hz)
        self.send_statustext(rates_text(granted), "info")

    # ---------------------------------------------------------------- clock
    def now_us(self) -> int:
        """The samples' clock now (:class:`LinkClock`): what the estimator's time is compared with."""
        return self.guard.link_clock.now_us()

    def from_companion_us(self, companion_us: int) -> int:
        """A time on the companion's monotonic clock (a camera's capture) on the samples' clock."""
        return self.guard.link_clock.from_companion_us(companion_us)

    async def _pump(self, stream: Any, convert: Callable[[Any], Sample | None]) -> None:
        async for raw in stream:
            try:
                s = convert(raw)
            except Exception as e:  # a malformed sample must not end the subscription
                self.guard._reject("stream", f"conversion failed: {type(e).__name__}")
                log.debug("sample conversion failed: %s", e)
                continue
            if s is None:
                continue
            try:
                self.samples.put_nowait(s)
            except queue.Full:
                self.stats.dropped_samples += 1

    async def _request_version(self, tries: int = 5, wait_s: float = 2.0) -> None:
        """Ask for the autopilot's AUTOPILOT_VERSION (MAV_CMD_REQUEST_MESSAGE) until the guard has it: MAVSDK asks
        for it on discovery too, but that answer may come before this link subscribed."""
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkMessage

        fields = {"target_system": self.target_system, "target_component": self.target_component,
                  "command": MAV_CMD_REQUEST_MESSAGE, "confirmation": 0,
                  "param1": float(MESSAGE_IDS["AUTOPILOT_VERSION"]), "param2": 0.0, "param3": 0.0, "param4": 0.0,
                  "param5": 0.0, "param6": 0.0, "param7": 0.0}
        for _ in range(tries):
            if self.guard.version_known:
                return
            msg = MavlinkMessage(message_name="COMMAND_LONG", target_system_id=self.target_system,
                                 target_component_id=self.target_component, fields_json=json.dumps(fields))
            try:
                await self._direct.send_command(msg)
            except Exception as e:  # noqa: BLE001 - unanswered: the version may still come; asked again below
                log.debug("AUTOPILOT_VERSION request: %s", e)
            await asyncio.sleep(wait_s)
        if not self.guard.version_known:
            log.warning("the autopilot sent no AUTOPILOT_VERSION: baro temperature clamp %.0f degC "
                        "(baro_temp_clamp_c)", self.guard.baro_temp_clamp_c)

    async def _watch(self, system: Any) -> None:
        async for connected in system.is_connected_state():
            if connected != self.stats.connected:
                log.warning("autopilot link %s", "restored" if connected else "lost")
                if connected and self.cfg.request_rates:  # a rebooted autopilot forgot the rates
                    self._tasks.append(asyncio.ensure_future(self._request_rates()))
            self.stats.connected = bool(connected)

    def stop(self, destroy_native: bool = True) -> None:
        """Stop the link's tasks and its event-loop thread.  ``destroy_native=False`` leaves the native MAVSDK
        instance to the process's exit (the companion CLI leaves with ``os._exit`` after closing its logs: the
        native binding has been seen to crash when destroyed while its receive threads are busy)."""
        async def _stop() -> None:
            for t in self._tasks:
                t.cancel()
            for t in self._tasks:
                with contextlib.suppress(BaseException):
                    await t
            if self._mavsdk is not None and destroy_native:
                self._mavsdk.destroy()

        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(_stop(), self._loop).result(timeout=5.0)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5.0)

    # ---------------------------------------------------------------- outputs
    def _due(self, kind: str, t_us: int, rate_hz: float) -> bool:
        last = self._last_sent_us.get(kind)
        if last is not None and 0 <= t_us - last < 1e6 / rate_hz:
            return False
        self._last_sent_us[kind] = t_us
        return True

    def _count(self, table: dict[str, int], key: str) -> None:
        table[key] = table.get(key, 0) + 1

    def send_estimate(self, est: OutputEstimate, capture_us: int | None = None) -> str:
        """Send the outputs that are due; returns '' or the reason the estimate was not sent (the status named
        values, :func:`status_values`, go out at their rate either way).  With ``capture_us`` (when the frame the
        estimate comes from was captured, companion clock) the time from capture to each send's completion is kept
        in ``stats.send_latency_us`` (the last :data:`LATENCY_HISTORY` per output)."""
        if self._direct is None:
            self._count(self.stats.suppressed, "not connected")
            return "not connected"
        reason = check_estimate(est, self.cfg)
        if (self.cfg.status_values and self.cfg.named_values == "named_value_float"
                and self._due("status", self.guard.clock(), self.cfg.named_values_hz)):
            t_ms = int(self.guard.clock() // 1000) & 0xFFFFFFFF
            for name, v in status_values(est, not reason).items():
                self._submit(f"named:{name}", self._send_one("NAMED_VALUE_FLOAT",
                                                             {"time_boot_ms": t_ms, "name": name, "value": v}))
        if reason:
            self._count(self.stats.suppressed, reason.split(" ")[0])
            return reason
        kinds = set()
        if self.cfg.named_values != "off" and self._due("named", est.t_us, self.cfg.named_values_hz):
            kinds.add("named")
        last_vision = self._last_sent_us.get("vision")
        if self.cfg.vision_speed and self._due("vision", est.t_us, self.cfg.vision_speed_hz):
            kinds.add("vision")
        if (self.cfg.wind_cov or self.cfg.wind_ardupilot) and self._due("wind", est.t_us, self.cfg.wind_hz):
            kinds.add("wind")
        period_us = round(1e6 / self.cfg.vision_speed_hz)
        delta = est.t_us - last_vision if last_vision is not None else period_us
        delta = int(min(max(delta, 1), 2 * period_us))  # after a gap: one period's displacement, not the gap's
        outputs = encode_outputs(est, self.cfg, kinds, t_offset_us=self.guard.link_clock.offset_us or 0,
                                 vision_delta_us=delta)
        for key, (name, fields) in outputs.items():
            self._submit(key, self._send_one(name, fields), capture_us)
        return ""

    async def _send_one(self, name: str, fields: dict[str, Any]) -> None:
        if name == "VISION_SPEED_ESTIMATE":
            from mavsdk.plugins.mocap import Covariance, SpeedNed, VisionSpeedEstimate
            v = VisionSpeedEstimate(time_usec=fields["usec"],
                                    speed_ned=SpeedNed(north_m_s=fields["x"], east_m_s=fields["y"],
                                                       down_m_s=fields["z"]),
                                    speed_covariance=Covariance(fields["covariance"]))
            await self._mocap.set_vision_speed_estimate(v)
            return
        from mavsdk.asyncio.plugins.mavlink_direct import MavlinkMessage
        msg = MavlinkMessage(message_name=name, system_id=0, component_id=0, target_system_id=self.target_system,
                             target_component_id=self.target_component, fields_json=fields_json(fields))
        await self._direct.send_message(msg)

    def _submit(self, key: str, coro: Any, since_us: int | None = None) -> None:
        fut = asyncio.run_coroutine_threadsafe(coro, self._loop)

        def done(f: Any) -> None:
            e = f.exception()
            if e is None:
                self._count(self.stats.sent, key)
                if since_us is not None:
                    self.stats.send_latency_us.setdefault(key, deque(maxlen=LATENCY_HISTORY)).append(
                        self.guard.clock() - since_us)
            else:
                self._count(self.stats.send_errors, key)
                log.debug("send %s failed: %s", key, e)

        fut.add_done_callback(done)

    def send_statustext(self, text: str, severity: str = "warning") -> None:
        if not self.cfg.statustext or self._direct is None:
            return
        fields = {"severity": MAV_SEVERITY.get(severity, MAV_SEVERITY["warning"]), "text": text[:50], "id": 0,
                  "chunk_seq": 0}
        self._submit("statustext", self._send_one("STATUSTEXT", fields))

    def send_heading_command(self, fields: dict[str, float | int]) -> None:
        """COMMAND_LONG (from :func:`nav.guidance.change_heading_command_fields`), acknowledged asynchronously."""
        if not self.cfg.guidance or self._direct is None:
            return
        if not all(math.isfinite(float(v)) for v in fields.values()):
            self._count(self.stats.suppressed, "command not finite")
            return

        async def _cmd() -> None:
            from mavsdk.asyncio.plugins.mavlink_direct import MavlinkMessage
            msg = MavlinkMessage(message_name="COMMAND_LONG", target_system_id=int(fields["target_system"]),
                                 target_component_id=int(fields["target_component"]),
                                 fields_json=json.dumps(fields))
            ack = await self._direct.send_command(msg)
            result = json.loads(ack.fields_json) if ack.fields_json else {}
            self.stats.acks.append(result)
            del self.stats.acks[:-20]
            if result.get("result", 0) != 0:
                log.warning("autopilot refused the heading command: %s", result)

        self._submit("heading_command", _cmd())
