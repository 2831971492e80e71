"""The companion's link to the autopilot through MAVSDK 4 (native binding, asyncio API).

Inputs (MAVSDK streams unless noted), each validated (finite, physically plausible, time not going backwards)
before it becomes a timestamped sample; rejected samples are counted per kind and per reason, never raised:

==================  ==============================================  =======================================
sample              source                                          becomes
==================  ==============================================  =======================================
attitude            ``telemetry.subscribe_attitude_euler``           :class:`common.samples.AttitudeSample`
IMU                 ``telemetry.subscribe_scaled_imu`` (SCALED_IMU)  :class:`common.samples.ImuSample`
airspeed            ``telemetry.subscribe_fixedwing_metrics``        :class:`common.samples.AirspeedSample` (VFR_HUD)
baro                ``telemetry.subscribe_scaled_pressure``          :class:`common.samples.BaroSample` (ISA)
GNSS                ``MavlinkDirect`` GPS_RAW_INT (one message with  :class:`common.samples.GnssSample`
                    fix type, satellites, accuracy and velocity;
                    MAVSDK's telemetry splits them over two streams)
home elevation      ``telemetry.subscribe_position``                 :class:`HomeReading`
external tracker    ``MavlinkDirect`` CAMERA_TRACKING_IMAGE_STATUS   :class:`TrackReading` (an image tracker's
                    (a video tracker's target point, normalised)     point, for :class:`nav.tracker.ExternalTracker`)
==================  ==============================================  =======================================

Time: every sample is stamped on the companion's monotonic clock (``t_us``).  Messages that carry the vehicle's
boot time are mapped through :class:`ClockSync` (offset = the smallest observed receive-minus-send difference, i.e.
the least-delayed packet), so that attitude can be matched to a camera frame's exposure time.

Outputs (only while the estimate passes :func:`check_estimate`; otherwise nothing of the estimate is sent and the
reason is returned and logged): drift and ATA as NAMED_VALUE_FLOAT (``GSOE_DRIFT``, ``GSOE_ATA`` in degrees) or one
DEBUG_VECT ``GSOE`` (x drift deg, y ATA deg, z quality), through ``MavlinkDirect``; ground velocity as
VISION_SPEED_ESTIMATE with its 3x3 covariance through MAVSDK ``mocap`` (what ArduPilot EKF3 takes as
external-navigation velocity); wind as WIND_COV (MAVSDK's own telemetry reads wind from it) and ArduPilot's WIND
(Mission Planner's HUD), both through ``MavlinkDirect``; STATUSTEXT.  The status named values ``GSOE_Q`` (optical
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
from common.config import In, Validated
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
from nav.gnss_monitor import GPS_FIX_TYPE_3D

log = logging.getLogger(__name__)

# Physical plausibility limits for telemetry (documented constants, not tuning knobs)
MAX_GYRO_RAD_S = 35.0          # 2000 deg/s, the largest common MEMS gyro range
MAX_ACCEL_M_S2 = 16.0 * 9.80665  # 16 g accelerometer range
MAX_AIRSPEED_M_S = 150.0
ALT_RANGE_M = (-500.0, 20000.0)
MAX_PITCH_RAD = math.pi / 2
ISA_P0_HPA = 1013.25
ISA_T0_K = 288.15
ISA_LAPSE_K_M = 0.0065
ISA_EXP = 5.25588
EARTH_RADIUS_M = 6371008.8
MAV_COMP_ID_ONBOARD_COMPUTER = 191
TRACKING_STATUS_ACTIVE = 1  # CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
TRACKING_MODE_POINT = 1     # CAMERA_TRACKING_MODE_POINT
MAV_SEVERITY = {"emergency": 0, "alert": 1, "critical": 2, "error": 3, "warning": 4, "notice": 5, "info": 6}
NAMED_VALUE_MAX_CHARS = 10
LATENCY_HISTORY = 100_000  # capture-to-sent latencies kept per output kind

_OutputRateHz = Annotated[float, In(0.01, 100.0)]
_MavlinkId = Annotated[int, In(1, 255)]


@dataclass(frozen=True)
class LinkConfig(Validated):
    """``[companion.link]``: connection, output switches and rates, output gates (units in the names).

    ``system_id``/``component_id``: the companion's MAVLink identity (the vehicle's system id; component 191,
    MAV_COMP_ID_ONBOARD_COMPUTER).  ``status_values``: send ``GSOE_Q``/``GSOE_GNSS``/``GSOE_VALID`` even while the
    estimate is withheld.  ``unknown_vertical_sigma_m_s``: the one-sigma WIND_COV states for the vertical wind it
    does not estimate.
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
    ``quality`` in [0, 1]; ``gnss_state`` an integer :class:`nav.gnss_monitor.GnssState`.
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


def encode_outputs(est: OutputEstimate, cfg: LinkConfig, kinds: set[str]) -> dict[str, tuple[str, dict[str, Any]]]:
    """MAVLink message names and fields for the requested output ``kinds`` (``named``, ``vision``, ``wind``).

    The estimate must have passed :func:`check_estimate`.  VISION_SPEED_ESTIMATE is returned with its fields as
    plain numbers; the link turns it into a MAVSDK ``VisionSpeedEstimate``.
    """
    out: dict[str, tuple[str, dict[str, Any]]] = {}
    t_ms = int(est.t_us // 1000) & 0xFFFFFFFF
    if "named" in kinds and cfg.named_values == "named_value_float":
        vals = {"GSOE_DRIFT": math.degrees(est.drift_rad), "GSOE_ATA": float(wrap_360(math.degrees(est.ata_rad)))}
        for name, v in vals.items():
            out[f"named:{name}"] = ("NAMED_VALUE_FLOAT", {"time_boot_ms": t_ms, "name": name, "value": float(v)})
    elif "named" in kinds and cfg.named_values == "debug_vect":
        out["named:GSOE"] = ("DEBUG_VECT", {"name": "GSOE", "time_usec": int(est.t_us),
                                            "x": math.degrees(est.drift_rad),
                                            "y": float(wrap_360(math.degrees(est.ata_rad))), "z": est.quality})
    if "vision" in kinds and cfg.vision_speed:
        vd, vd_var = est.vel_d_m_s, est.vel_d_var
        if not (math.isfinite(vd) and math.isfinite(vd_var)):
            vd, vd_var = 0.0, cfg.unknown_vertical_var_m2_s2
        c = est.vel_cov_ne
        cov = [float(c[0, 0]), float(c[0, 1]), 0.0, float(c[1, 0]), float(c[1, 1]), 0.0, 0.0, 0.0, float(vd_var)]
        out["vision"] = ("VISION_SPEED_ESTIMATE", {"usec": int(est.t_us), "x": float(est.vel_ne_m_s[0]),
                                                   "y": float(est.vel_ne_m_s[1]), "z": float(vd),
                                                   "covariance": cov})
    if "wind" in kinds:
        speed = float(np.hypot(*est.wind_ne_m_s))
        if cfg.wind_cov:
            speed_sigma, rms_sigma = wind_sigmas(est.wind_ne_m_s, est.wind_cov_ne)
            alt = est.height_agl_m + (est.home_amsl_m if math.isfinite(est.home_amsl_m) else 0.0)
            out["wind_cov"] = ("WIND_COV", {"time_usec": int(est.t_us), "wind_x": float(est.wind_ne_m_s[0]),
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
        self._samples: list[tuple[int, int]] = []  # (receive_us, receive - send)
        self.offset_us: int | None = None

    def observe(self, vehicle_us: int, receive_us: int) -> int:
        d = receive_us - vehicle_us
        self._samples.append((receive_us, d))
        cutoff = receive_us - self._window_us
        while self._samples and self._samples[0][0] < cutoff:
            self._samples.pop(0)
        self.offset_us = min(s[1] for s in self._samples)
        return vehicle_us + self.offset_us

    def reset(self) -> None:
        self._samples.clear()
        self.offset_us = None


def now_us() -> int:
    """The companion's clock: monotonic microseconds."""
    return time.monotonic_ns() // 1000


def pressure_altitude_m(pressure_hpa: float) -> float:
    return ISA_T0_K / ISA_LAPSE_K_M * (1.0 - (pressure_hpa / ISA_P0_HPA) ** (1.0 / ISA_EXP))


class TelemetryGuard:
    """Validates raw telemetry into samples; counts what it rejects (``rejected[kind:reason]``)."""

    def __init__(self, cfg: LinkConfig, clock: Callable[[], int] = now_us) -> None:
        self.cfg = cfg
        self.clock = clock
        self.rejected: dict[str, int] = {}
        self.accepted: dict[str, int] = {}
        self._sync: dict[str, ClockSync] = {}
        self._last_vehicle_us: dict[str, int] = {}
        self.ref_lat_lon: tuple[float, float] | None = None

    def _reject(self, kind: str, reason: str) -> None:
        key = f"{kind}:{reason}"
        n = self.rejected.get(key, 0) + 1
        self.rejected[key] = n
        if n == 1 or n % 100 == 0:
            log.warning("rejected %s telemetry (%s), %d so far", kind, reason, n)

    def _stamp(self, kind: str, vehicle_us: int) -> int | None:
        """Companion time of a vehicle-stamped sample, or None (rejected) when its time went backwards."""
        recv = self.clock()
        if vehicle_us <= 0:
            return recv
        last = self._last_vehicle_us.get(kind)
        sync = self._sync.setdefault(kind, ClockSync(self.cfg.clock_window_s))
        if last is not None and vehicle_us <= last:
            if last - vehicle_us > self.cfg.max_clock_backwards_s * 1e6:
                log.warning("%s: vehicle clock jumped back %.1f s (reboot?): clock re-synchronised", kind,
                            (last - vehicle_us) / 1e6)
                sync.reset()
            else:
                self._reject(kind, "time not increasing")
                return None
        self._last_vehicle_us[kind] = vehicle_us
        return sync.observe(vehicle_us, recv)

    def _ok(self, kind: str) -> None:
        self.accepted[kind] = self.accepted.get(kind, 0) + 1

    def attitude(self, roll_deg: float, pitch_deg: float, yaw_deg: float, vehicle_us: int) -> AttitudeSample | None:
        vals = (roll_deg, pitch_deg, yaw_deg)
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in vals):
            self._reject("attitude", "not finite")
            return None
        roll, pitch, yaw = (math.radians(v) for v in vals)
        if abs(roll) > math.pi or abs(pitch) > MAX_PITCH_RAD or abs(yaw) > 2 * math.pi:
            self._reject("attitude", "out of range")
            return None
        t = self._stamp("attitude", vehicle_us)
        if t is None:
            return None
        self._ok("attitude")
        return AttitudeSample(t, roll, pitch, yaw)

    def imu(self, gyro: tuple[float, float, float], accel: tuple[float, float, float],
            vehicle_us: int) -> ImuSample | None:
        g = np.asarray(gyro, dtype=np.float64)
        a = np.asarray(accel, dtype=np.float64)
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
            self._reject("imu", "not finite")
            return None
        if np.max(np.abs(g)) > MAX_GYRO_RAD_S or np.max(np.abs(a)) > MAX_ACCEL_M_S2:
            self._reject("imu", "out of range")
            return None
        t = self._stamp("imu", vehicle_us)
        if t is None:
            return None
        self._ok("imu")
        return ImuSample(t, g, a)

    def airspeed(self, tas_m_s: float) -> AirspeedSample | None:
        if not (isinstance(tas_m_s, int | float) and math.isfinite(tas_m_s)):
            self._reject("airspeed", "not finite")
            return None
        if not 0.0 <= tas_m_s <= MAX_AIRSPEED_M_S:
            self._reject("airspeed", "out of range")
            return None
        self._ok("airspeed")
        return AirspeedSample(self.clock(), float(tas_m_s))

    def baro(self, pressure_hpa: float, vehicle_us: int) -> BaroSample | None:
        if not (isinstance(pressure_hpa, int | float) and math.isfinite(pressure_hpa)) or pressure_hpa <= 0.0:
            self._reject("baro", "not finite or not positive")
            return None
        alt = pressure_altitude_m(pressure_hpa)
        if not ALT_RANGE_M[0] <= alt <= ALT_RANGE_M[1]:
            self._reject("baro", "out of range")
            return None
        t = self._stamp("baro", vehicle_us)
        if t is None:
            return None
        self._ok("baro")
        return BaroSample(t, alt, pressure_pa=float(pressure_hpa) * 100.0)

    def home(self, alt_amsl_m: float, rel_alt_m: float) -> HomeReading | None:
        vals = (alt_amsl_m, rel_alt_m)
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in vals):
            self._reject("position", "not finite")
            return None
        if not (ALT_RANGE_M[0] <= alt_amsl_m <= ALT_RANGE_M[1] and abs(rel_alt_m) <= ALT_RANGE_M[1]):
            self._reject("position", "out of range")
            return None
        self._ok("position")
        return HomeReading(self.clock(), float(alt_amsl_m), float(rel_alt_m))

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
        return TrackReading(self.clock(), x, y, active)

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
        t = self._stamp("gnss", vehicle_us)
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
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

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
        tel = TelemetryAsync(system)
        self._direct = MavlinkDirectAsync(system)
        self._mocap = MocapAsync(system)
        g = self.guard
        self._tasks = [
            asyncio.ensure_future(self._pump(tel.subscribe_attitude_euler(), lambda a: g.attitude(
                a.roll_deg, a.pitch_deg, a.yaw_deg, a.timestamp_us))),
            asyncio.ensure_future(self._pump(tel.subscribe_scaled_imu(), lambda m: g.imu(
                (m.angular_velocity_frd.forward_rad_s, m.angular_velocity_frd.right_rad_s,
                 m.angular_velocity_frd.down_rad_s),
                (m.acceleration_frd.forward_m_s2, m.acceleration_frd.right_m_s2, m.acceleration_frd.down_m_s2),
                m.timestamp_us))),
            asyncio.ensure_future(self._pump(tel.subscribe_fixedwing_metrics(), lambda m: g.airspeed(
                m.airspeed_m_s))),
            asyncio.ensure_future(self._pump(tel.subscribe_scaled_pressure(), lambda m: g.baro(
                m.absolute_pressure_hpa, m.timestamp_us))),
            asyncio.ensure_future(self._pump(self._direct.subscribe_message("GPS_RAW_INT"), lambda m: g.gps_raw_int(
                json.loads(m.fields_json)))),
            asyncio.ensure_future(self._pump(tel.subscribe_position(), lambda m: g.home(
                m.absolute_altitude_m, m.relative_altitude_m))),
            asyncio.ensure_future(self._pump(self._direct.subscribe_message("CAMERA_TRACKING_IMAGE_STATUS"),
                                             lambda m: g.tracking(json.loads(m.fields_json)))),
            asyncio.ensure_future(self._watch(system)),
        ]
        self.stats.connected = True
        log.info("connected to autopilot (system %d) on %s", self.target_system, self.url)
        return True

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

    async def _watch(self, system: Any) -> None:
        async for connected in system.is_connected_state():
            if connected != self.stats.connected:
                log.warning("autopilot link %s", "restored" if connected else "lost")
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
        if self.cfg.vision_speed and self._due("vision", est.t_us, self.cfg.vision_speed_hz):
            kinds.add("vision")
        if (self.cfg.wind_cov or self.cfg.wind_ardupilot) and self._due("wind", est.t_us, self.cfg.wind_hz):
            kinds.add("wind")
        for key, (name, fields) in encode_outputs(est, self.cfg, kinds).items():
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
                             target_component_id=self.target_component, fields_json=json.dumps(fields))
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
