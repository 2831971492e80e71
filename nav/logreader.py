"""Reading real flight logs into one time-ordered stream of typed samples (for ``gsoe replay``).

Formats
    ``.tlog``  MAVLink telemetry log (8-byte big-endian receive time in microseconds, then the frame), read with
               ``pymavlink.mavutil.mavlogfile``, the streaming tlog reader behind ``mavutil.mavlink_connection``
               (``mavlink_connection`` returns the memory-mapped variant for plain reading, which in pymavlink
               2.4.50 raises ``AttributeError`` on corrupt files and cannot say where a torn log ends).
    ``.bin``   ArduPilot DataFlash log, read with ``pymavlink.DFReader.DFReader_binary``.
    ``.ulg``   PX4 ULog, read with ``pyulog.ULog``.

Samples (frames and units as in :mod:`gsoe`; every sample has ``t_us``, integer microseconds since the log's
first sample on one common clock)
    :class:`common.samples.ImuSample`       body rates (rad/s) and specific force (m/s^2), FRD.
    :class:`common.samples.AttitudeSample`  autopilot AHRS roll, pitch, yaw (rad; yaw in [-pi, pi), from north).
    :class:`AirspeedSample`             true airspeed (m/s) and the equivalent airspeed it came from.
    :class:`BaroSample`                 ISA pressure altitude (m, up) from the static pressure (Pa).
    :class:`GnssSample`                 position in local NED (m) from the first 3-D fix, ground velocity NED.
    :class:`AutopilotWind`              the autopilot's own wind estimate (direction it blows FROM, speed).

Sources per format (first one present wins)
    =========== ========================================== ========================== ================================
    sample      tlog (MAVLink)                             DataFlash                  ULog
    =========== ========================================== ========================== ================================
    IMU         HIGHRES_IMU (SI), SCALED_IMU, RAW_IMU      IMU (instance 0)           sensor_combined
                (ArduPilot only: milli-g, milli-rad/s),
                SCALED_IMU2, SCALED_IMU3
    attitude    ATTITUDE (rad)                             ATT (deg)                  vehicle_attitude (quaternion)
    airspeed    VFR_HUD.airspeed (EAS, m/s)                ARSP.Airspeed (EAS, m/s)   airspeed_validated, airspeed
    baro        SCALED_PRESSURE.press_abs (hPa)            BARO.Press (Pa)            vehicle_air_data
    GNSS        GPS_RAW_INT (1e-7 deg, mm, cm/s, cdeg)     GPS (deg, m, m/s, deg)     vehicle_gps_position,
                                                                                      sensor_gps
    wind        WIND (deg FROM, m/s)                       NKF2 / XKF2 VWN, VWE (m/s, wind, wind_estimate
                                                           the air's velocity)        (windspeed_north/east)
    =========== ========================================== ========================== ================================

Clock
    DataFlash and ULog stamp every record with the autopilot's boot clock.  In a tlog every sample is placed by
    the autopilot's own timestamp, never by when the ground station received it (a telemetry link delivers in
    bursts: messages held for seconds arrive together):

    * messages with ``time_boot_ms`` or a boot ``time_usec`` (ATTITUDE, SCALED_PRESSURE, the IMUs, GPS_RAW_INT,
      whose ``time_usec`` is the fix's own time) are on the boot clock as they are;
    * a ``time_usec`` in UNIX time (after 2001) is a second clock, mapped onto the boot clock by the difference of
      the two clocks' offsets from the receive time;
    * each clock's offset is a robust fit against the receive time: the *lower envelope* of ``receive - stamp``
      (the minimum over each ``CLOCK_WINDOW_S`` of receive time: the transport delay is never negative and a burst
      only adds to it; a burst ends with a message that waited least), a Theil-Sen line through those minima
      (clock drift; a constant when the log is shorter than three windows);
    * a message without a timestamp (VFR_HUD, WIND) takes the boot time of the newest stamped message the vehicle
      sent before it (any type, in the order of the log: the autopilot sends a scheduler slot's messages together,
      so this is within one slot, 20-100 ms; a burst keeps the order); with none within ``MAX_TRANSPORT_DELAY_US``
      of receive time before it, the receive time less the fitted offset;
    * a stamp that arrives earlier than the fit allows (by ``CLOCK_EARLY_TOL_US``) or later than
      ``MAX_TRANSPORT_DELAY_US`` after it (autopilot reboot, corrupt frame) is not trusted: the message is placed
      as one without a timestamp, with a warning.
Airspeed
    ArduPilot logs equivalent airspeed (EAS); ``tas_m_s = eas_m_s * sqrt(rho0 / rho)`` with the density at the
    logged static pressure and the air temperature ArduPilot's EKF assumes for the same conversion: the baro's own
    temperature, at most the firmware's clamp (a board's baro reads high, self-heated; the version the log names,
    in a DataFlash ``MSG`` or ``VER``, a tlog's ``STATUSTEXT`` or an ArduPilot's ``AUTOPILOT_VERSION``, else
    ``baro_temp_clamp_c``), at the log's lowest
    altitude, less the ISA lapse rate above it (:mod:`common.atmosphere`, the live link's policy too;
    ``ReadReport.air_temp_c``; 10 K is 1.7 % of TAS; docs/real-data.md).
    Without a baro temperature the ISA atmosphere's; without a logged pressure ``tas_m_s = eas_m_s`` and the report
    says so.
Bad input
    Truncated or corrupt logs give what was readable and a :class:`ReadReport` whose ``warnings`` say what was
    lost; a file with nothing readable gives no samples and a warning.  An unknown extension raises
    :class:`LogFormatError`; a missing file ``FileNotFoundError``.  No parser exception escapes
    :func:`read_log`.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import mmap
import os
import struct
import sys
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import theilslopes

from common.angles import wrap_2pi, wrap_pi
from common.atmosphere import (
    ARDUPILOT_BARO_TEMP_CLAMP_C,
    KELVIN_AT_0_C,
    ardupilot_baro_temp_clamp_c,
    baro_air_temperature_k,
    eas_to_tas_ratio,
    pressure_altitude_m,
)
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
from nav.hygiene import MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_INVALID, flight_sw_version

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------------------------
# Constants (units in the names)

G0_M_S2 = 9.80665  #: standard gravity; ArduPilot's milli-g scale factor (GRAVITY_MSS)
WGS84_A_M = 6378137.0  #: WGS-84 semi-major axis
WGS84_E2 = 6.69437999014e-3  #: WGS-84 first eccentricity squared
#: A MAVLink ``time_usec`` above this is UNIX time (after 2001-09-09), not time since boot.
UNIX_TIME_MIN_US = 10**15
#: A tlog stamp received more than this after the clock fit allows (its lower envelope) is not trusted (a reboot,
#: a corrupt frame); a burst of a telemetry link holds messages back for seconds, not this long.
MAX_TRANSPORT_DELAY_US = 10_000_000
#: ... nor one received earlier than the fit allows by more than this (nothing arrives before it is sent).
CLOCK_EARLY_TOL_US = 200_000
#: Window of receive time over which the minimum of ``receive - stamp`` is taken (longer than a link's bursts).
CLOCK_WINDOW_S = 10.0
#: Undecodable tlog frames above this fraction of all frames earn a warning (the ALFA logs have about 1 %).
BAD_FRAME_WARN_FRACTION = 0.05
GPS_FIX_TYPE_3D = 3  #: MAVLink GPS_FIX_TYPE_3D_FIX; DataFlash GPS.Status and ULog fix_type use the same numbers
_MAV_UNKNOWN_U16 = 65535  # GPS_RAW_INT vel/cog: unknown
_MAV_UNKNOWN_U8 = 255  # GPS_RAW_INT satellites_visible: unknown
_MAV_TYPE_GCS = 6

SUFFIXES = {".tlog": "tlog", ".bin": "dataflash", ".ulg": "ulog"}


# --------------------------------------------------------------------------------------------------------------
# Samples (AirspeedSample, BaroSample, GnssSample, ImuSample, AttitudeSample are common.samples')


@dataclass(frozen=True, slots=True)
class AutopilotWind:
    """The autopilot's own wind estimate at ``t_us``: the direction the wind blows FROM (clockwise from north,
    radians in [0, 2 pi), as MAVLink WIND) and the horizontal speed."""

    t_us: int
    wind_from_rad: float
    speed_m_s: float

    @property
    def wind_ned_m_s(self) -> NDArray[np.float64]:
        """Horizontal velocity of the air (the direction it blows TO), north and east, m/s."""
        return -self.speed_m_s * np.array([math.cos(self.wind_from_rad), math.sin(self.wind_from_rad)])


Sample = ImuSample | AttitudeSample | AirspeedSample | BaroSample | GnssSample | AutopilotWind
S = TypeVar("S", ImuSample, AttitudeSample, AirspeedSample, BaroSample, GnssSample, AutopilotWind)


class LogFormatError(ValueError):
    """The file is not a log this module reads (unknown extension, not a regular file)."""


@dataclass(frozen=True)
class ReadReport:
    """What was read and what was lost.

    ``warnings`` is empty for a clean log.  ``counts`` and ``sources`` are keyed by sample class name
    (``"ImuSample"``): how many samples and from which message or topic.  ``t0_boot_us`` is the autopilot boot
    clock at ``t_us == 0`` (``None`` when only receive times were available).  ``origin_*`` is the GNSS origin of
    the local NED frame (``None`` without a 3-D fix).  ``frames``/``bad_frames``: MAVLink frames read and frames
    that failed to decode (tlog only).  ``air_temp_c``: the air temperature at the log's lowest altitude behind its
    EAS -> TAS conversion (``None``: the ISA atmosphere's).  ``firmware``: the autopilot firmware the log names
    (``""``: none); ``baro_temp_clamp_c``: the baro temperature clamp taken (degC), the firmware's when it is an
    ArduPilot version, else the caller's.
    """

    path: str
    log_format: str
    warnings: tuple[str, ...]
    counts: dict[str, int]
    sources: dict[str, str]
    t0_boot_us: int | None = None
    origin_lat_deg: float | None = None
    origin_lon_deg: float | None = None
    origin_alt_m: float | None = None
    frames: int = 0
    bad_frames: int = 0
    air_temp_c: float | None = None
    firmware: str = ""
    baro_temp_clamp_c: float = ARDUPILOT_BARO_TEMP_CLAMP_C

    @property
    def ok(self) -> bool:
        return not self.warnings


@dataclass(frozen=True)
class FlightLog:
    """Samples of one log in time order (ties keep the order of :data:`Sample`'s types), plus the report."""

    samples: tuple[Sample, ...]
    report: ReadReport

    def of_type(self, cls: type[S]) -> list[S]:
        return [s for s in self.samples if type(s) is cls]

    def __iter__(self) -> Iterator[Sample]:
        return iter(self.samples)

    def __len__(self) -> int:
        return len(self.samples)

    @property
    def duration_s(self) -> float:
        return (self.samples[-1].t_us - self.samples[0].t_us) * 1e-6 if self.samples else 0.0


# --------------------------------------------------------------------------------------------------------------
# Physics helpers


def local_ned_m(lat_deg: NDArray[np.float64], lon_deg: NDArray[np.float64], alt_m: NDArray[np.float64],
                origin: tuple[float, float, float]) -> NDArray[np.float64]:
    """Flat-earth local NED (m), shape (N, 3), of geodetic points relative to ``origin = (lat, lon, alt)``.

    Uses the meridian and prime-vertical radii of curvature of WGS-84 at the origin; the error grows with the
    square of the distance (well under 1 m within 10 km).
    """
    lat0, lon0, alt0 = origin
    phi = math.radians(lat0)
    s2 = math.sin(phi) ** 2
    r_meridian = WGS84_A_M * (1 - WGS84_E2) / (1 - WGS84_E2 * s2) ** 1.5
    r_normal = WGS84_A_M / math.sqrt(1 - WGS84_E2 * s2)
    north = np.radians(np.asarray(lat_deg, dtype=float) - lat0) * (r_meridian + alt0)
    dlon = np.asarray(wrap_pi(np.radians(np.asarray(lon_deg, dtype=float) - lon0)))
    east = dlon * (r_normal + alt0) * math.cos(phi)
    down = -(np.asarray(alt_m, dtype=float) - alt0)
    return np.column_stack([north, east, down])


# --------------------------------------------------------------------------------------------------------------
# Raw records (boot-clock microseconds) shared by the three readers


@dataclass
class _Raw:
    """Records in autopilot units already converted to SI; times in microseconds on the reader's clock."""

    imu: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)  # gyro xyz, accel xyz
    att: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)  # roll, pitch, yaw (rad)
    air: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)  # eas or tas, is_tas (1/0)
    baro: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)  # pressure Pa[, baro temperature C]
    gnss: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)  # lat, lon, alt, vn, ve, vd, fix, sats
    wind: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)  # from rad, speed
    sources: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    frames: int = 0
    bad_frames: int = 0
    t0_boot_known: bool = True
    firmware: str = ""          # the autopilot firmware the log names ("ArduPlane V3.8.2-dev (8178ab40)")


def _finite_split(records: list[tuple[int, tuple[float, ...]]], what: str,
                  warnings: list[str]) -> list[tuple[int, tuple[float, ...]]]:
    good = [r for r in records if all(math.isfinite(v) for v in r[1])]
    if len(good) < len(records):
        warnings.append(f"{len(records) - len(good)} {what} records with non-finite values dropped")
    return good


def _assemble(path: Path, fmt: str, raw: _Raw, baro_temp_clamp_c: float) -> FlightLog:
    warnings = list(raw.warnings)
    named = ardupilot_baro_temp_clamp_c(raw.firmware)    # the log's own firmware decides when it names itself
    if named is not None:
        baro_temp_clamp_c = named
    imu = _finite_split(raw.imu, "IMU", warnings)
    att = _finite_split(raw.att, "attitude", warnings)
    air = _finite_split(raw.air, "airspeed", warnings)
    baro = _finite_split(raw.baro, "baro", warnings)
    if any(v[0] <= 0.0 for _, v in baro):
        warnings.append(f"{sum(v[0] <= 0.0 for _, v in baro)} baro records with a non-positive pressure dropped")
        baro = [r for r in baro if r[1][0] > 0.0]
    wind = _finite_split(raw.wind, "wind", warnings)
    gnss = raw.gnss
    all_t = [r[0] for group in (imu, att, air, baro, gnss, wind) for r in group]
    counts: dict[str, int] = {}
    origin: tuple[float, float, float] | None = None
    if not all_t:
        warnings.append("no samples could be read from this log")
        report = ReadReport(path=str(path), log_format=fmt, warnings=tuple(warnings), counts={}, sources={},
                            frames=raw.frames, bad_frames=raw.bad_frames)
        return FlightLog(samples=(), report=report)
    t0 = min(all_t)
    samples: list[tuple[int, int, Sample]] = []

    def add(order: int, s: Sample) -> None:
        samples.append((s.t_us, order, s))

    for t, v in imu:
        add(0, ImuSample(t_us=t - t0, gyro_b_rad_s=np.array(v[:3]), accel_b_m_s2=np.array(v[3:6])))
    for t, v in att:
        add(1, AttitudeSample(t_us=t - t0, roll_rad=v[0], pitch_rad=v[1], yaw_rad=float(wrap_pi(v[2]))))
    air_temp_c: float | None = None
    if air:
        p_t = np.array([t for t, _ in baro], dtype=float)
        p_v = np.array([v[0] for _, v in baro], dtype=float)
        baro_temp_c = [v[1] for _, v in baro if len(v) > 1]
        needs_eas2tas = any(v[1] == 0.0 for _, v in air)
        if needs_eas2tas and len(p_t) == 0:
            warnings.append("no static pressure in the log: true airspeed taken equal to the logged (equivalent) "
                            "airspeed")
        ground: tuple[float, float] | None = None
        if needs_eas2tas and len(p_t) and baro_temp_c:
            ground = (float(np.max(p_v)), baro_air_temperature_k(float(np.median(baro_temp_c)), baro_temp_clamp_c))
            air_temp_c = ground[1] - KELVIN_AT_0_C
        for t, v in air:
            if v[1]:
                add(2, AirspeedSample(t_us=t - t0, tas_m_s=v[0], eas_m_s=math.nan))
            else:
                ratio = float(eas_to_tas_ratio(np.interp(t, p_t, p_v), ground)) if len(p_t) else 1.0
                add(2, AirspeedSample(t_us=t - t0, tas_m_s=v[0] * ratio, eas_m_s=v[0]))
    for t, v in baro:
        add(3, BaroSample(t_us=t - t0, alt_m=float(pressure_altitude_m(v[0])), pressure_pa=v[0]))
    if gnss:
        arr = np.array([v for _, v in gnss], dtype=float)
        fix = (arr[:, 6] >= GPS_FIX_TYPE_3D) & np.all(np.isfinite(arr[:, :3]), axis=1) & (
            (arr[:, 0] != 0.0) | (arr[:, 1] != 0.0))
        if np.any(fix):
            i0 = int(np.argmax(fix))
            origin = (float(arr[i0, 0]), float(arr[i0, 1]), float(arr[i0, 2]))
            ned = local_ned_m(arr[:, 0], arr[:, 1], arr[:, 2], origin)
        else:
            warnings.append("no 3-D GNSS fix in the log: GNSS positions are nan")
            ned = np.full((len(arr), 3), np.nan)
        nan3 = np.full(3, np.nan)
        for k, (t, _) in enumerate(gnss):
            ok = bool(fix[k])
            add(4, GnssSample(t_us=t - t0, pos_ned_m=ned[k].copy() if ok else nan3.copy(),
                              vel_ned_m_s=arr[k, 3:6].copy() if ok else nan3.copy(), fix_ok=ok,
                              n_sats=int(arr[k, 7]) if math.isfinite(arr[k, 7]) else -1,
                              lat_deg=float(arr[k, 0]), lon_deg=float(arr[k, 1]),
                              alt_msl_m=float(arr[k, 2])))
    for t, v in wind:
        add(5, AutopilotWind(t_us=t - t0, wind_from_rad=float(wrap_2pi(v[0])), speed_m_s=v[1]))
    samples.sort(key=lambda x: (x[0], x[1]))
    ordered = tuple(s for _, _, s in samples)
    for s in ordered:
        counts[type(s).__name__] = counts.get(type(s).__name__, 0) + 1
    report = ReadReport(
        path=str(path), log_format=fmt, warnings=tuple(warnings), counts=counts,
        sources={k: v for k, v in raw.sources.items() if k in counts},
        t0_boot_us=int(t0) if raw.t0_boot_known else None,
        origin_lat_deg=origin[0] if origin else None, origin_lon_deg=origin[1] if origin else None,
        origin_alt_m=origin[2] if origin else None, frames=raw.frames, bad_frames=raw.bad_frames,
        air_temp_c=air_temp_c, firmware=raw.firmware, baro_temp_clamp_c=baro_temp_clamp_c)
    return FlightLog(samples=ordered, report=report)


# --------------------------------------------------------------------------------------------------------------
# MAVLink telemetry log

_TLOG_TIME_HEADER_BYTES = 8
# (type, (src system, src component), receive us, stamp (clock, us) or None, values, index in the log)
_TlogRecord = tuple[str, tuple[int, int], int, tuple[str, int] | None, tuple[float, ...], int]
# a stamped message of any type: (index in the log, source, receive us, (clock, us))
_TlogAnchor = tuple[int, tuple[int, int], int, tuple[str, int]]
_BOOT, _UNIX = "boot", "unix"
_TLOG_IMU_PREFERENCE = ("HIGHRES_IMU", "SCALED_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")
_TLOG_TYPES = {*_TLOG_IMU_PREFERENCE, "ATTITUDE", "VFR_HUD", "GPS_RAW_INT", "WIND", "SCALED_PRESSURE"}


def _tlog_firmware(msg: Any) -> str:
    """The ArduPilot firmware a STATUSTEXT names ("ArduPlane V4.5.1 (...)", sent at boot and to a new ground
    station); ``""`` for any other text."""
    try:
        text = str(msg.text)
    except (AttributeError, TypeError, ValueError):
        return ""
    return text if ardupilot_baro_temp_clamp_c(text) is not None else ""


def _tlog_version(msg: Any) -> str:
    """An AUTOPILOT_VERSION's flight software version as an ArduPilot banner names it ("ArduPilot V4.5.1"; the
    caller takes it only from an ArduPilot vehicle); ``""`` when the field is damaged."""
    version = flight_sw_version(getattr(msg, "flight_sw_version", None))
    return "" if version is None else "ArduPilot V{}.{}.{}".format(*version)


def _stamp(msg: Any) -> tuple[str, int] | None:
    """The message's own timestamp: ``("boot", us)``, ``("unix", us)`` or None."""
    if hasattr(msg, "time_boot_ms"):
        return _BOOT, int(msg.time_boot_ms) * 1000
    if hasattr(msg, "time_usec"):
        t = int(msg.time_usec)
        if t <= 0:
            return None
        return (_BOOT, t) if t < UNIX_TIME_MIN_US else (_UNIX, t)
    return None


def _tlog_values(mtype: str, m: Any) -> tuple[float, ...] | None:
    """SI values of one message (see :class:`_Raw`), or None to skip it."""
    if mtype == "HIGHRES_IMU":
        return (m.xgyro, m.ygyro, m.zgyro, m.xacc, m.yacc, m.zacc)
    if mtype in ("SCALED_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3"):
        mg = G0_M_S2 * 1e-3
        return (m.xgyro * 1e-3, m.ygyro * 1e-3, m.zgyro * 1e-3, m.xacc * mg, m.yacc * mg, m.zacc * mg)
    if mtype == "ATTITUDE":
        return (m.roll, m.pitch, m.yaw)
    if mtype == "VFR_HUD":
        return (m.airspeed, 0.0)
    if mtype == "SCALED_PRESSURE":
        return (m.press_abs * 100.0, m.temperature * 0.01)
    if mtype == "WIND":
        return (math.radians(m.direction), m.speed)
    if mtype == "GPS_RAW_INT":
        vel = math.nan if m.vel == _MAV_UNKNOWN_U16 else m.vel * 0.01
        cog = math.nan if m.cog == _MAV_UNKNOWN_U16 else math.radians(m.cog * 0.01)
        sats = -1 if m.satellites_visible == _MAV_UNKNOWN_U8 else m.satellites_visible
        return (m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3, vel * math.cos(cog), vel * math.sin(cog), math.nan,
                float(m.fix_type), float(sats))
    return None


def read_tlog(path: Path, baro_temp_clamp_c: float = ARDUPILOT_BARO_TEMP_CLAMP_C) -> FlightLog:
    from pymavlink import mavutil

    raw = _Raw()
    size = path.stat().st_size
    recs: list[_TlogRecord] = []
    anchors: list[_TlogAnchor] = []
    vehicle: tuple[int, int, int] | None = None  # (sysid, compid, autopilot)
    banners: dict[tuple[int, int], str] = {}      # the firmware each sender names in a STATUSTEXT
    versions: dict[tuple[int, int], str] = {}     # ... or in an AUTOPILOT_VERSION (an ArduPilot's, as its banner)
    last_end = skipped = 0
    try:
        conn = mavutil.mavlogfile(str(path), robust_parsing=True)
    except Exception as e:  # noqa: BLE001 - any failure of the third-party parser becomes a warning
        raw.warnings.append(f"cannot open as a MAVLink log: {e}")
        return _assemble(path, "tlog", raw, baro_temp_clamp_c)
    try:
        while True:
            try:
                msg = conn.recv_msg()
            except Exception as e:  # noqa: BLE001
                raw.warnings.append(f"MAVLink parser stopped at byte {conn.f.tell()} of {size}: {e}")
                break
            if msg is None:
                break
            end = conn.f.tell()
            # bytes consumed beyond this frame and its 8-byte time header were skipped by the parser's resync
            skipped += max(0, end - last_end - len(msg.get_msgbuf()) - _TLOG_TIME_HEADER_BYTES)
            last_end = end
            raw.frames += 1
            mtype = msg.get_type()
            if mtype == "BAD_DATA":
                raw.bad_frames += 1
                continue
            if mtype == "HEARTBEAT":
                if vehicle is None and msg.type != _MAV_TYPE_GCS and msg.autopilot != MAV_AUTOPILOT_INVALID:
                    vehicle = (msg.get_srcSystem(), msg.get_srcComponent(), msg.autopilot)
                continue
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            recv_us = int(round(msg._timestamp * 1e6))
            try:
                stamp = _stamp(msg)
            except (TypeError, ValueError):
                stamp = None
            if stamp is not None:
                anchors.append((raw.frames, src, recv_us, stamp))
            if mtype == "STATUSTEXT" and src not in banners:
                text = _tlog_firmware(msg)
                if text:
                    banners[src] = text
            elif mtype == "AUTOPILOT_VERSION" and src not in versions:
                text = _tlog_version(msg)
                if text:
                    versions[src] = text
            if mtype not in _TLOG_TYPES:
                continue
            try:
                values = _tlog_values(mtype, msg)
            except (AttributeError, TypeError, ValueError) as e:
                raw.warnings.append(f"{mtype} message not decodable: {e}")
                continue
            if values is not None:
                recs.append((mtype, src, recv_us, stamp, values, raw.frames))
    finally:
        conn.close()
    if size - last_end > 0 and raw.frames:
        raw.warnings.append(f"log ends with {size - last_end} bytes that are not a complete MAVLink frame "
                            f"(truncated or corrupt tail)")
    if skipped:
        raw.warnings.append(f"{skipped} bytes inside the log were skipped as undecodable (corrupt data)")
    if raw.frames and raw.bad_frames > BAD_FRAME_WARN_FRACTION * raw.frames:
        raw.warnings.append(f"{raw.bad_frames} of {raw.frames} frames could not be decoded "
                            f"({100.0 * raw.bad_frames / raw.frames:.0f} %)")
    if vehicle is None:
        if recs:
            raw.warnings.append("no vehicle HEARTBEAT: messages of every system are used")
        raw.firmware = next(iter(banners.values()), "")
    else:
        recs = [r for r in recs if r[1] == vehicle[:2]]
        anchors = [a for a in anchors if a[1] == vehicle[:2]]
        raw.firmware = banners.get(vehicle[:2], "") or (
            versions.get(vehicle[:2], "") if vehicle[2] == MAV_AUTOPILOT_ARDUPILOTMEGA else "")
    present = {r[0] for r in recs}
    imu_type = None
    for cand in _TLOG_IMU_PREFERENCE:
        if cand in present:
            if cand == "RAW_IMU" and (vehicle is None or vehicle[2] != MAV_AUTOPILOT_ARDUPILOTMEGA):
                raw.warnings.append("RAW_IMU ignored: its units are only known for ArduPilot (milli-g, milli-rad/s)")
                continue
            imu_type = cand
            break
    placed = _tlog_clock(recs, anchors, raw)
    targets: dict[str, tuple[list[tuple[int, tuple[float, ...]]], str]] = {
        "ATTITUDE": (raw.att, "AttitudeSample"), "VFR_HUD": (raw.air, "AirspeedSample"),
        "SCALED_PRESSURE": (raw.baro, "BaroSample"), "GPS_RAW_INT": (raw.gnss, "GnssSample"),
        "WIND": (raw.wind, "AutopilotWind")}
    if imu_type is not None:
        targets[imu_type] = (raw.imu, "ImuSample")
    for mtype, t, values in placed:
        if mtype in targets:
            targets[mtype][0].append((t, values))
    for mtype, (_, name) in targets.items():
        if mtype in present:
            raw.sources[name] = mtype
    return _assemble(path, "tlog", raw, baro_temp_clamp_c)


class _ClockFit:
    """``receive - stamp`` of one clock as a line in receive time, fitted to its lower envelope (module docstring)."""

    def __init__(self, recv_us: NDArray[np.int64], stamp_us: NDArray[np.int64]) -> None:
        off = (recv_us - stamp_us).astype(np.float64)
        x = (recv_us - recv_us.min()).astype(np.float64)
        win = np.floor(x / (CLOCK_WINDOW_S * 1e6)).astype(np.int64)
        xs, ys = [], []
        for w in np.unique(win):
            sel = np.flatnonzero(win == w)
            i = sel[np.argmin(off[sel])]
            xs.append(x[i])
            ys.append(off[i])
        self.x0 = int(recv_us.min())
        self.slope = 0.0
        self.intercept = float(min(ys))
        if len(xs) >= 3:
            slope, intercept, _, _ = theilslopes(ys, xs)
            self.slope, self.intercept = float(slope), float(intercept)

    def offset_us(self, recv_us: int) -> float:
        """The fitted ``receive - stamp`` at a receive time (the least transport delay plus the clocks' offset)."""
        return self.intercept + self.slope * (recv_us - self.x0)


def _tlog_clock(recs: list[_TlogRecord], anchors: list[_TlogAnchor],
                raw: _Raw) -> list[tuple[str, int, tuple[float, ...]]]:
    """Each record's time on the autopilot's boot clock (module docstring): ``(type, t_us, values)``."""
    fits: dict[str, _ClockFit] = {}
    for clock in (_BOOT, _UNIX):
        pts = [(a[2], a[3][1]) for a in anchors if a[3][0] == clock]
        if pts:
            arr = np.array(pts, dtype=np.int64)
            fits[clock] = _ClockFit(arr[:, 0], arr[:, 1])
    ref = _BOOT if _BOOT in fits else (_UNIX if _UNIX in fits else None)
    if ref is None:
        if recs:
            raw.warnings.append("no autopilot timestamps in the log: the tlog receive times are the clock")
        raw.t0_boot_known = False
        return [(r[0], r[2], r[4]) for r in recs]
    if ref != _BOOT:
        raw.t0_boot_known = False
    ref_fit = fits[ref]

    def on_ref(recv_us: int, stamp: tuple[str, int] | None) -> int | None:
        """The stamp on the reference clock, or None when there is none or it is not trusted."""
        if stamp is None:
            return None
        fit = fits[stamp[0]]
        resid = recv_us - stamp[1] - fit.offset_us(recv_us)
        if not -CLOCK_EARLY_TOL_US <= resid <= MAX_TRANSPORT_DELAY_US:
            return None
        if stamp[0] == ref:
            return stamp[1]
        return int(round(stamp[1] + fit.offset_us(recv_us) - ref_fit.offset_us(recv_us)))

    # the newest trusted stamped message of the same source before each record, in the order of the log
    newest: dict[tuple[int, int], tuple[int, int]] = {}     # source -> (receive us, time on the reference clock)
    before: list[tuple[int, int] | None] = []
    ai = 0
    for r in recs:                                          # recs and anchors are both in the log's order
        while ai < len(anchors) and anchors[ai][0] < r[5]:
            _, src, a_recv, a_stamp = anchors[ai]
            a_t = on_ref(a_recv, a_stamp)
            if a_t is not None:
                newest[src] = (a_recv, a_t)
            ai += 1
        before.append(newest.get(r[1]))
    times = [on_ref(r[2], r[3]) for r in recs]
    good = [t for t in times if t is not None]
    lo, hi = min(good, default=None), max(good, default=None)
    untrusted = dropped = 0
    out = []
    for r, t, prev in zip(recs, times, before, strict=True):
        mtype, _, recv, stamp, values, _ = r
        if t is None:
            untrusted += stamp is not None
            if prev is not None and 0 <= recv - prev[0] <= MAX_TRANSPORT_DELAY_US:
                t = prev[1]
            else:
                t = int(round(recv - ref_fit.offset_us(recv)))
            if lo is not None and hi is not None and not (
                    lo - MAX_TRANSPORT_DELAY_US <= t <= hi + MAX_TRANSPORT_DELAY_US):
                dropped += 1
                continue
        out.append((mtype, t, values))
    if untrusted:
        raw.warnings.append(f"{untrusted} messages whose autopilot timestamp disagrees with the receive time "
                            f"(reboot or corruption) were placed by the messages sent before them")
    if dropped:
        raw.warnings.append(f"{dropped} messages with a time outside the log's span were dropped")
    return out


# --------------------------------------------------------------------------------------------------------------
# ArduPilot DataFlash


@contextlib.contextmanager
def _captured_output() -> Iterator[io.StringIO]:
    """Collect what a parser prints instead of letting it reach the terminal: Python-level stdout/stderr, and
    file descriptor 2, where pymavlink's compiled DataFlash indexer ``fprintf``s one "bad header" line per byte
    it skips.  The text is in the yielded buffer after the block.  (Process-wide while active: fd 2 is shared by
    all threads.)"""
    buf = io.StringIO()
    sys.stderr.flush()
    saved_fd = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
                yield buf
        finally:
            sys.stderr.flush()
            os.dup2(saved_fd, 2)
            os.close(saved_fd)
            tmp.seek(0)
            buf.write(tmp.read().decode("utf-8", errors="replace"))

_DF_TYPES = ["IMU", "ATT", "BARO", "GPS", "ARSP", "NKF2", "XKF2", "PARM", "MSG", "VER"]


def _df_time_us(m: Any) -> int | None:
    if hasattr(m, "TimeUS"):
        return int(m.TimeUS)
    if hasattr(m, "TimeMS"):
        return int(m.TimeMS) * 1000
    return None


def read_dataflash(path: Path, baro_temp_clamp_c: float = ARDUPILOT_BARO_TEMP_CLAMP_C) -> FlightLog:
    from pymavlink import DFReader

    raw = _Raw()
    winds: dict[str, list[tuple[int, tuple[float, ...]]]] = {"NKF2": [], "XKF2": []}
    reader = None
    untimed = 0
    with _captured_output() as noise:
        try:
            reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
            while True:
                m = reader.recv_match(type=_DF_TYPES)
                if m is None:
                    break
                untimed += not _df_record(m, raw, winds)
        except Exception as e:  # noqa: BLE001 - any failure of the third-party parser becomes a warning
            raw.warnings.append(f"DataFlash parser stopped: {e}")
    if untimed:
        raw.warnings.append(f"{untimed} messages without TimeUS/TimeMS were skipped")
    skipped = sum(1 for line in noise.getvalue().splitlines() if line.startswith("bad header"))
    if skipped:
        raw.warnings.append(f"{skipped} bytes are not DataFlash messages (corrupt or not a DataFlash log)")
    if reader is not None:
        _df_tail_check(reader, raw)
        ekf_type = reader.params.get("AHRS_EKF_TYPE")
        order = ["XKF2", "NKF2"] if ekf_type == 3 else ["NKF2", "XKF2"]
        for name in order:
            if winds[name]:
                raw.wind.extend(winds[name])
                raw.sources["AutopilotWind"] = f"{name}.VWN/VWE"
                break
    return _assemble(path, "dataflash", raw, baro_temp_clamp_c)


def _df_record(m: Any, raw: _Raw, winds: dict[str, list[tuple[int, tuple[float, ...]]]]) -> bool:
    """Store one message; False when it has no timestamp (and was not stored)."""
    mtype = m.get_type()
    if mtype == "PARM":
        return True
    if mtype in ("MSG", "VER"):          # the firmware: MSG's text, or VER's numbers (ArduPilot 4.1 on)
        if not raw.firmware:
            try:
                text = (str(m.Message) if mtype == "MSG" else f"ArduPilot V{int(m.Major)}.{int(m.Minor)}")
            except (AttributeError, TypeError, ValueError, OverflowError):
                text = ""                # a damaged record names nothing
            if ardupilot_baro_temp_clamp_c(text) is not None and not text.startswith("ArduPilot V0."):
                raw.firmware = text
        return True
    t = _df_time_us(m)
    if t is None:
        return False
    instance = getattr(m, "I", 0)
    if mtype == "IMU" and instance == 0:
        raw.imu.append((t, (m.GyrX, m.GyrY, m.GyrZ, m.AccX, m.AccY, m.AccZ)))
        raw.sources["ImuSample"] = "IMU"
    elif mtype == "ATT":
        raw.att.append((t, (math.radians(m.Roll), math.radians(m.Pitch), math.radians(m.Yaw))))
        raw.sources["AttitudeSample"] = "ATT"
    elif mtype == "BARO" and instance == 0:
        temp_c = getattr(m, "Temp", None)
        raw.baro.append((t, (float(m.Press),) if temp_c is None else (float(m.Press), float(temp_c))))
        raw.sources["BaroSample"] = "BARO"
    elif mtype == "ARSP" and instance == 0:
        raw.air.append((t, (float(m.Airspeed), 0.0)))
        raw.sources["AirspeedSample"] = "ARSP"
    elif mtype == "GPS" and instance == 0:
        crs = math.radians(m.GCrs)
        vz = float(getattr(m, "VZ", math.nan))
        raw.gnss.append((t, (m.Lat, m.Lng, m.Alt, m.Spd * math.cos(crs), m.Spd * math.sin(crs), vz,
                             float(m.Status), float(m.NSats))))
        raw.sources["GnssSample"] = "GPS"
    elif mtype in winds and getattr(m, "C", 0) == 0:
        vn, ve = float(m.VWN), float(m.VWE)
        # VWN/VWE is the air's velocity; the wind blows FROM the opposite direction
        winds[mtype].append((t, (math.atan2(-ve, -vn), math.hypot(vn, ve))))
    return True


def _df_tail_check(reader: Any, raw: _Raw) -> None:
    """Warn when the last indexed message does not end exactly at the end of the file (torn or padded log)."""
    offsets = getattr(reader, "offsets", None)
    formats = getattr(reader, "formats", None)
    data_len = getattr(reader, "data_len", None)
    if not offsets or not formats or data_len is None:
        return
    end = 0
    for mtype, offs in enumerate(offsets):
        if offs and mtype in formats:
            end = max(end, offs[-1] + formats[mtype].len)
    if end > data_len:
        raw.warnings.append("the last DataFlash message is cut off (truncated log)")
    elif 0 < end < data_len:
        raw.warnings.append(f"log ends with {data_len - end} bytes that are not a complete DataFlash message "
                            f"(truncated or corrupt tail)")


# --------------------------------------------------------------------------------------------------------------
# PX4 ULog

_ULOG_TOPICS = ["sensor_combined", "vehicle_attitude", "vehicle_air_data", "airspeed_validated", "airspeed",
                "vehicle_gps_position", "sensor_gps", "wind", "wind_estimate"]


def read_ulog(path: Path, baro_temp_clamp_c: float = ARDUPILOT_BARO_TEMP_CLAMP_C) -> FlightLog:
    from pyulog import ULog

    raw = _Raw()
    with _captured_output():
        try:
            ulog = ULog(str(path), message_name_filter_list=_ULOG_TOPICS)
        except Exception as e:  # noqa: BLE001 - any failure of the third-party parser becomes a warning
            raw.warnings.append(f"not a readable ULog file: {e}")
            return _assemble(path, "ulog", raw, baro_temp_clamp_c)
    if ulog.file_corruption:
        raw.warnings.append("ULog file corruption detected (truncated or damaged): the readable part is used")
    tail = _ulog_tail_bytes(path)
    if tail:
        raw.warnings.append(f"log ends with {tail} bytes that are not a complete ULog message (truncated log)")
    if ulog.dropouts:
        lost_ms = sum(d.duration for d in ulog.dropouts)
        raw.warnings.append(f"{len(ulog.dropouts)} logging dropouts ({lost_ms} ms of data lost)")
    data = {(d.name, d.multi_id): d.data for d in ulog.data_list}

    def topic(*names: str) -> tuple[str, dict[str, NDArray[Any]]] | None:
        for n in names:
            if (n, 0) in data and len(data[(n, 0)].get("timestamp", ())) > 0:
                return n, data[(n, 0)]
        return None

    def fill(names: tuple[str, ...], kind: str, target: list[tuple[int, tuple[float, ...]]],
             convert: Callable[[dict[str, NDArray[Any]]], NDArray[np.float64]]) -> None:
        found = topic(*names)
        if found is None:
            return
        name, d = found
        try:
            values = convert(d)
        except KeyError as e:
            raw.warnings.append(f"ULog topic {name} lacks field {e}: {kind} not read")
            return
        ts = np.asarray(d["timestamp"], dtype=np.int64)
        target.extend((int(t), tuple(float(x) for x in row)) for t, row in zip(ts, values, strict=True))
        raw.sources[kind] = name

    def vec(d: dict[str, NDArray[Any]], base: str, n: int = 3) -> NDArray[np.float64]:
        return np.column_stack([np.asarray(d[f"{base}[{i}]"], dtype=float) for i in range(n)])

    fill(("sensor_combined",), "ImuSample", raw.imu,
         lambda d: np.hstack([vec(d, "gyro_rad"), vec(d, "accelerometer_m_s2")]))
    fill(("vehicle_attitude",), "AttitudeSample", raw.att, _ulog_euler)
    fill(("vehicle_air_data",), "BaroSample", raw.baro,
         lambda d: np.asarray(d["baro_pressure_pa"], dtype=float)[:, None])
    fill(("airspeed_validated", "airspeed"), "AirspeedSample", raw.air,
         lambda d: np.column_stack([np.asarray(d["true_airspeed_m_s"], dtype=float),
                                    np.ones(len(d["true_airspeed_m_s"]))]))
    fill(("vehicle_gps_position", "sensor_gps"), "GnssSample", raw.gnss, _ulog_gnss)
    fill(("wind", "wind_estimate"), "AutopilotWind", raw.wind,
         lambda d: np.column_stack([
             np.arctan2(-np.asarray(d["windspeed_east"], dtype=float), -np.asarray(d["windspeed_north"], dtype=float)),
             np.hypot(np.asarray(d["windspeed_north"], dtype=float), np.asarray(d["windspeed_east"], dtype=float))]))
    return _assemble(path, "ulog", raw, baro_temp_clamp_c)


_ULOG_HEADER_BYTES = 16  # magic (7), version (1), start timestamp (8)
_ULOG_MSG_HEADER = struct.Struct("<HB")  # message size (excluding this header), message type


def _ulog_tail_bytes(path: Path) -> int:
    """Bytes after the last complete ULog message: walks the message framing (size, type) of the file, which
    pyulog does not report; a log cut inside a message has a non-zero tail."""
    with path.open("rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
        size = len(data)
        ofs = _ULOG_HEADER_BYTES
        while ofs + _ULOG_MSG_HEADER.size <= size:
            msg_size, _ = _ULOG_MSG_HEADER.unpack_from(data, ofs)
            end = ofs + _ULOG_MSG_HEADER.size + msg_size
            if end > size:
                break
            ofs = end
        return max(0, size - ofs)


def _ulog_euler(d: dict[str, NDArray[Any]]) -> NDArray[np.float64]:
    """(roll, pitch, yaw) rows from ``vehicle_attitude.q`` (w, x, y, z; body to NED, Hamilton), with the 3-2-1
    sequence of :func:`gsoe.rotation.euler_from_R_nb` (vectorised here)."""
    q = np.column_stack([np.asarray(d[f"q[{i}]"], dtype=float) for i in range(4)])
    out = np.full((len(q), 3), np.nan)
    good = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0)
    if np.any(good):
        yaw_pitch_roll = Rotation.from_quat(q[good][:, [1, 2, 3, 0]]).as_euler("ZYX")
        out[good] = yaw_pitch_roll[:, ::-1]
    return out


def _ulog_gnss(d: dict[str, NDArray[Any]]) -> NDArray[np.float64]:
    if "latitude_deg" in d:  # PX4 >= 1.14
        lat, lon = np.asarray(d["latitude_deg"], float), np.asarray(d["longitude_deg"], float)
        alt = np.asarray(d["altitude_msl_m"], float)
    else:
        lat, lon = np.asarray(d["lat"], float) * 1e-7, np.asarray(d["lon"], float) * 1e-7
        alt = np.asarray(d["alt"], float) * 1e-3
    vel = np.column_stack([np.asarray(d[k], float) for k in ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s")])
    if "vel_ned_valid" in d:
        vel[np.asarray(d["vel_ned_valid"]) == 0] = np.nan
    sats = np.asarray(d["satellites_used"], float) if "satellites_used" in d else np.full(len(lat), -1.0)
    return np.column_stack([lat, lon, alt, vel, np.asarray(d["fix_type"], float), sats])


# --------------------------------------------------------------------------------------------------------------
# Entry point

_READERS: dict[str, Callable[[Path, float], FlightLog]] = {"tlog": read_tlog, "dataflash": read_dataflash,
                                                            "ulog": read_ulog}


def read_log(path: str | Path, baro_temp_clamp_c: float = ARDUPILOT_BARO_TEMP_CLAMP_C) -> FlightLog:
    """Read a ``.tlog``, ``.bin`` or ``.ulg`` flight log (see the module docstring).

    Raises ``FileNotFoundError`` for a missing file and :class:`LogFormatError` for an unknown extension or a
    path that is not a regular file; everything wrong inside the file ends up in ``report.warnings``.
    """
    p = Path(path)
    fmt = SUFFIXES.get(p.suffix.lower())
    if fmt is None:
        raise LogFormatError(f"{p}: unknown log type {p.suffix!r} (known: {', '.join(sorted(SUFFIXES))})")
    if not p.exists():
        raise FileNotFoundError(2, "No such file or directory", str(p))
    if not p.is_file():
        raise LogFormatError(f"{p}: not a regular file")
    if p.stat().st_size == 0:
        raw = _Raw(warnings=["the file is empty"])
        return _assemble(p, fmt, raw, baro_temp_clamp_c)
    result = _READERS[fmt](p, baro_temp_clamp_c)
    for w in result.report.warnings:
        log.warning("%s: %s", p.name, w)
    return result
