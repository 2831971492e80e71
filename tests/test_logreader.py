"""Flight-log readers against the logs' own reference values (ALFA tlogs, ArduPlane DataFlash) and a ULog written
here byte by byte from the format specification."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil
from scipy.spatial.transform import Rotation

from common.angles import angle_diff
from common.atmosphere import (
    ARDUPILOT_3_BARO_TEMP_CLAMP_C,
    ardupilot_baro_temp_clamp_c,
    eas_to_tas_ratio,
    pressure_altitude_m,
)
from common.samples import AttitudeSample, ImuSample
from nav.logreader import (
    AirspeedSample,
    AutopilotWind,
    BaroSample,
    GnssSample,
    LogFormatError,
    local_ned_m,
    read_log,
)
from tests.conftest import shared_data

SHORT = "alfa_carbonZ_2018-07-18-16-37-39_1.tlog"
LONG = "alfa_carbonZ_2018-07-30-17-36-35_engine_failure.tlog"
DATAFLASH = "arduplane_3.8.2_truncated.BIN"


def _pymavlink_messages(path: Path, types: set[str]) -> dict[str, list]:
    """Messages of the vehicle (system 1) straight from pymavlink's own reader, for cross-checks."""
    conn = mavutil.mavlink_connection(str(path))
    out: dict[str, list] = {t: [] for t in types}
    while (m := conn.recv_match(type=list(types))) is not None:
        if m.get_srcSystem() == 1:
            out[m.get_type()].append(m)
    conn.close()
    return out


@pytest.fixture(scope="module")
def short_log():
    return read_log(shared_data("flightlogs", SHORT), ARDUPILOT_3_BARO_TEMP_CLAMP_C)


@pytest.fixture(scope="module")
def long_log():
    return read_log(shared_data("flightlogs", LONG), ARDUPILOT_3_BARO_TEMP_CLAMP_C)


# ---------------------------------------------------------------------------------------------------------------
# physics helpers against independent references


def test_flat_earth_matches_the_standard_degree_lengths():
    # lengths of one degree from the standard series (independent of our radii-of-curvature code)
    lat = 40.59
    phi = math.radians(lat)
    m_per_deg_lat = 111132.954 - 559.822 * math.cos(2 * phi) + 1.175 * math.cos(4 * phi)
    m_per_deg_lon = 111412.84 * math.cos(phi) - 93.5 * math.cos(3 * phi) + 0.118 * math.cos(5 * phi)
    ned = local_ned_m(np.array([lat + 0.01, lat]), np.array([-79.9, -79.9 + 0.01]), np.array([400.0, 380.0]),
                      (lat, -79.9, 400.0))
    assert ned[0, 0] == pytest.approx(0.01 * m_per_deg_lat, rel=2e-4)
    assert ned[1, 1] == pytest.approx(0.01 * m_per_deg_lon, rel=2e-4)
    assert ned[1, 2] == pytest.approx(20.0)  # 20 m lower is +20 m down
    # across the antimeridian the longitude difference wraps
    e = local_ned_m(np.array([0.0]), np.array([-179.999]), np.array([0.0]), (0.0, 179.999, 0.0))[0, 1]
    assert e == pytest.approx(0.002 * 111319.49, rel=1e-3)


def test_isa_helpers_match_the_standard_atmosphere_table():
    # ICAO standard atmosphere: 1000 m -> 89874.6 Pa, density ratio 0.90748
    assert float(pressure_altitude_m(89874.6)) == pytest.approx(1000.0, abs=0.5)
    assert float(pressure_altitude_m(101325.0)) == pytest.approx(0.0, abs=1e-9)
    assert float(eas_to_tas_ratio(89874.6)) == pytest.approx(1.0 / math.sqrt(0.90748), rel=1e-4)


# ---------------------------------------------------------------------------------------------------------------
# ALFA telemetry logs


@pytest.mark.parametrize("name, span_s", [(SHORT, 30.0), (LONG, 157.0)])
def test_alfa_rates_and_counts_match_the_log(name, span_s):
    path = shared_data("flightlogs", name)
    flog = read_log(path)
    rep = flog.report
    assert rep.ok, rep.warnings
    assert rep.sources == {"ImuSample": "RAW_IMU", "AttitudeSample": "ATTITUDE", "AirspeedSample": "VFR_HUD",
                           "BaroSample": "SCALED_PRESSURE", "GnssSample": "GPS_RAW_INT", "AutopilotWind": "WIND"}
    # about 1 % of frames are undecodable (SOURCES.md)
    assert 0 < rep.bad_frames < 0.02 * rep.frames
    assert flog.duration_s == pytest.approx(span_s, abs=1.5)
    # one sample per vehicle message, as pymavlink's own reader counts them
    msgs = _pymavlink_messages(path, {"RAW_IMU", "ATTITUDE", "VFR_HUD", "SCALED_PRESSURE", "GPS_RAW_INT", "WIND"})
    assert rep.counts["ImuSample"] == len(msgs["RAW_IMU"])
    assert rep.counts["AttitudeSample"] == len(msgs["ATTITUDE"])
    assert rep.counts["AirspeedSample"] == len(msgs["VFR_HUD"])
    assert rep.counts["BaroSample"] == len(msgs["SCALED_PRESSURE"])
    assert rep.counts["GnssSample"] == len(msgs["GPS_RAW_INT"])
    assert rep.counts["AutopilotWind"] == len(msgs["WIND"])
    # rates in SOURCES.md: IMU and baro about 10 Hz, GNSS 5 Hz, attitude and airspeed 2.5 Hz, wind about 2 Hz
    dur = flog.duration_s
    for cls, hz, tol in ((ImuSample, 10.0, 0.5), (BaroSample, 10.0, 0.5), (GnssSample, 5.0, 0.3),
                         (AttitudeSample, 2.5, 0.2), (AirspeedSample, 2.5, 0.2), (AutopilotWind, 2.1, 0.3)):
        assert len(flog.of_type(cls)) / dur == pytest.approx(hz, abs=tol), cls.__name__
    # one clock: time-ordered, starting at zero, IMU stamped every 100 ms of autopilot time
    t = np.array([s.t_us for s in flog.samples])
    assert t[0] == 0 and np.all(np.diff(t) >= 0)
    t_imu = np.array([s.t_us for s in flog.of_type(ImuSample)])
    assert np.median(np.diff(t_imu)) == pytest.approx(100_000, abs=100)
    # IMU units: milli-g and milli-rad/s scaled to SI, values as logged
    imu0, raw0 = flog.of_type(ImuSample)[0], msgs["RAW_IMU"][0]
    assert imu0.accel_b_m_s2[2] == pytest.approx(raw0.zacc * 9.80665e-3)
    assert imu0.gyro_b_rad_s[0] == pytest.approx(raw0.xgyro * 1e-3)
    assert t_imu[0] + rep.t0_boot_us == raw0.time_usec


def test_alfa_imu_and_attitude_are_physically_consistent(long_log):
    # specific force magnitude averages about g in gliding/level flight
    acc = np.array([s.accel_b_m_s2 for s in long_log.of_type(ImuSample)])
    assert np.median(np.linalg.norm(acc, axis=1)) == pytest.approx(9.81, rel=0.1)
    # gyro z integrated over the flight follows the attitude's yaw (body rates ~ Euler rates at small pitch/roll
    # only on average, so compare the net heading change over 20 s windows)
    imu = long_log.of_type(ImuSample)
    att = long_log.of_type(AttitudeSample)
    t_i = np.array([s.t_us for s in imu]) * 1e-6
    t_a = np.array([s.t_us for s in att]) * 1e-6
    yaw = np.unwrap([s.yaw_rad for s in att])
    roll = np.interp(t_i, t_a, [s.roll_rad for s in att])
    pitch = np.interp(t_i, t_a, [s.pitch_rad for s in att])
    g = np.array([s.gyro_b_rad_s for s in imu])
    # Euler yaw rate from body rates: (q sin(phi) + r cos(phi)) / cos(theta)
    yaw_rate = (g[:, 1] * np.sin(roll) + g[:, 2] * np.cos(roll)) / np.cos(pitch)
    integrated = np.concatenate([[0.0], np.cumsum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * np.diff(t_i))])
    errors = []
    for start in np.arange(t_a[0] + 5, t_a[-1] - 25, 20.0):
        d_att = np.interp(start + 20, t_a, yaw) - np.interp(start, t_a, yaw)
        d_gyro = np.interp(start + 20, t_i, integrated) - np.interp(start, t_i, integrated)
        errors.append(abs(d_att - d_gyro))
    assert np.median(errors) < np.radians(10.0)


def test_alfa_gnss_track_matches_groundspeed(short_log, long_log):
    for flog, name in ((short_log, SHORT), (long_log, LONG)):
        gnss = [s for s in flog.of_type(GnssSample) if s.fix_ok]
        assert len(gnss) == flog.report.counts["GnssSample"]
        assert np.allclose(gnss[0].pos_ned_m, 0.0) and flog.report.origin_lat_deg == pytest.approx(40.59, abs=0.01)
        t = np.array([s.t_us for s in gnss]) * 1e-6
        pos = np.array([s.pos_ned_m for s in gnss])
        # speed from the local track over 1 s, against VFR_HUD groundspeed (put on the boot clock here with the
        # GPS_RAW_INT receive offset)
        msgs = _pymavlink_messages(shared_data("flightlogs", name), {"VFR_HUD", "GPS_RAW_INT"})
        offset = np.median([m._timestamp - m.time_usec * 1e-6 for m in msgs["GPS_RAW_INT"]])
        t_hud = np.array([m._timestamp - offset for m in msgs["VFR_HUD"]]) - flog.report.t0_boot_us * 1e-6
        gs = np.array([m.groundspeed for m in msgs["VFR_HUD"]])
        inside = (t_hud > t[0] + 0.5) & (t_hud < t[-1] - 0.5)
        track = np.hypot(np.interp(t_hud + 0.5, t, pos[:, 0]) - np.interp(t_hud - 0.5, t, pos[:, 0]),
                         np.interp(t_hud + 0.5, t, pos[:, 1]) - np.interp(t_hud - 0.5, t, pos[:, 1]))
        assert np.median(np.abs(track[inside] - gs[inside])) < 1.5
        vel = np.array([np.hypot(*s.vel_ned_m_s[:2]) for s in gnss])
        assert np.median(np.abs(np.interp(t_hud[inside], t, vel) - gs[inside])) < 1.0
        # GPS_RAW_INT gives no vertical velocity: nan, not a made-up zero
        assert all(np.isnan(s.vel_ned_m_s[2]) for s in gnss)
        # the length of the local track is the distance the groundspeed covers
        length = np.sum(np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1))
        assert length == pytest.approx(np.mean(gs[inside]) * (t[-1] - t[0]), rel=0.05)


def test_alfa_wind_and_air_data(long_log):
    wind = long_log.of_type(AutopilotWind)
    speeds = np.array([w.speed_m_s for w in wind])
    assert np.mean(speeds) == pytest.approx(2.5, abs=0.5)  # SOURCES.md: about 2.5 m/s
    msgs = _pymavlink_messages(shared_data("flightlogs", LONG), {"WIND"})
    raw_dir = np.radians([m.direction for m in msgs["WIND"]])
    assert np.max(np.abs(angle_diff([w.wind_from_rad for w in wind], raw_dir))) < 1e-6
    air = long_log.of_type(AirspeedSample)
    tas = np.array([a.tas_m_s for a in air])
    assert np.mean(tas) == pytest.approx(16.0, abs=1.5)  # SOURCES.md: about 16 m/s
    # at about 400 m MSL and 25 C (ArduPilot's cap of the baro's 55 C), TAS exceeds EAS by about 4 %
    assert np.median(tas / np.array([a.eas_m_s for a in air])) == pytest.approx(1.039, abs=0.01)
    baro = long_log.of_type(BaroSample)
    assert 200.0 < np.median([b.alt_m for b in baro]) < 600.0  # pressure altitude of a field at about 400 m
    # wind triangle from the log's own GNSS velocity, heading and TAS agrees with ArduPilot's wind (mean vector):
    # checks units, directions and the FROM convention of four sample types at once
    att = long_log.of_type(AttitudeSample)
    gnss = [s for s in long_log.of_type(GnssSample) if s.fix_ok]
    t_air = np.array([a.t_us for a in air])
    t_att = np.array([a.t_us for a in att])
    t_g = np.array([g.t_us for g in gnss])
    yaw = np.interp(t_air, t_att, np.unwrap([a.yaw_rad for a in att]))
    pitch = np.interp(t_air, t_att, [a.pitch_rad for a in att])
    v_n = np.interp(t_air, t_g, [g.vel_ned_m_s[0] for g in gnss])
    v_e = np.interp(t_air, t_g, [g.vel_ned_m_s[1] for g in gnss])
    tri = np.array([np.mean(v_n - tas * np.cos(pitch) * np.cos(yaw)), np.mean(v_e - tas * np.cos(pitch) * np.sin(yaw))])
    ap = np.mean([w.wind_ned_m_s for w in wind], axis=0)
    assert np.linalg.norm(tri - ap) < 1.0


# ---------------------------------------------------------------------------------------------------------------
# DataFlash (LGPL test file: read from ../shared only)


def test_truncated_dataflash_parses_imu_att_gps_and_ekf_wind():
    path = shared_data("flightlogs", DATAFLASH)
    flog = read_log(path)
    rep = flog.report
    assert rep.log_format == "dataflash"
    assert any("truncated" in w for w in rep.warnings)
    assert rep.sources["AutopilotWind"] == "NKF2.VWN/VWE" and "AirspeedSample" not in rep.counts  # no ARSP
    # its MSG names ArduPlane 3.8: 3.x's baro temperature clamp, not the caller's default (4.x)
    assert rep.firmware.startswith("ArduPlane V3.8.2") and rep.baro_temp_clamp_c == ARDUPILOT_3_BARO_TEMP_CLAMP_C
    from pymavlink import DFReader

    ref = DFReader.DFReader_binary(str(path), zero_time_base=False)
    ref_counts: dict[str, int] = {}
    first: dict[str, object] = {}
    while (m := ref.recv_match(type=["IMU", "ATT", "GPS", "NKF2", "BARO"])) is not None:
        ref_counts[m.get_type()] = ref_counts.get(m.get_type(), 0) + 1
        first.setdefault(m.get_type(), m)
    assert rep.counts["ImuSample"] == ref_counts["IMU"] == 45
    assert rep.counts["AttitudeSample"] == ref_counts["ATT"]
    assert rep.counts["GnssSample"] == ref_counts["GPS"]
    assert rep.counts["AutopilotWind"] == ref_counts["NKF2"]
    assert rep.counts["BaroSample"] == ref_counts["BARO"]
    imu = flog.of_type(ImuSample)[0]
    m = first["IMU"]
    np.testing.assert_allclose(imu.accel_b_m_s2, [m.AccX, m.AccY, m.AccZ])
    assert imu.t_us + rep.t0_boot_us == m.TimeUS
    att = flog.of_type(AttitudeSample)[0]
    m = first["ATT"]
    assert math.degrees(att.roll_rad) == pytest.approx(m.Roll)
    assert math.degrees(angle_diff(att.yaw_rad, math.radians(m.Yaw))) == pytest.approx(0.0, abs=1e-9)
    gnss = flog.of_type(GnssSample)
    assert all(g.fix_ok for g in gnss) and gnss[0].n_sats == first["GPS"].NSats
    # the aircraft sits on the ground: the local track stays within a metre, speed below 1 m/s
    assert np.max(np.abs([g.pos_ned_m for g in gnss])) < 1.0
    assert np.max(np.linalg.norm([g.vel_ned_m_s for g in gnss], axis=1)) < 1.0
    # the pressure altitude of the logged static pressure
    baro = flog.of_type(BaroSample)[0]
    assert baro.pressure_pa == pytest.approx(first["BARO"].Press)
    # EKF wind: the air's velocity VWN/VWE as logged (zero on the ground before take-off)
    wind = flog.of_type(AutopilotWind)[0]
    m = first["NKF2"]
    np.testing.assert_allclose(wind.wind_ned_m_s, [m.VWN, m.VWE], atol=1e-12)
    assert wind.t_us + rep.t0_boot_us == m.TimeUS


@pytest.mark.parametrize(("text", "clamp_c"), [
    ("ArduPlane V3.8.2-dev (8178ab40)", 25.0), ("APM:Plane V3.4.0", 25.0), ("ArduPlane V4.5.1 (deadbeef)", 35.0),
    ("ArduCopter V4.0.0", 35.0), ("PX4 v1.14.0", None), ("Initialising ArduPilot", None), ("", None)])
def test_firmware_names_give_their_baro_clamp(text, clamp_c):
    assert ardupilot_baro_temp_clamp_c(text) == clamp_c


def test_a_tlog_naming_its_firmware_takes_that_firmwares_baro_clamp(tmp_path, long_log):
    """The ALFA log names no firmware: the caller's clamp (3.x's 25 degC).  The same log with ArduPlane 4.5's boot
    banner (a STATUSTEXT) put in front takes 4.x's 35 degC whatever the caller passes: its baro reads about 55 degC,
    so the air is taken at 35 degC, and every TAS rises by the square root of the temperature ratio."""
    assert long_log.report.firmware == "" and long_log.report.baro_temp_clamp_c == ARDUPILOT_3_BARO_TEMP_CLAMP_C
    data = shared_data("flightlogs", LONG).read_bytes()
    from pymavlink.dialects.v10 import ardupilotmega as mav1

    enc = mav1.MAVLink(None, srcSystem=1, srcComponent=1)
    banner = enc.statustext_encode(6, b"ArduPlane V4.5.1 (deadbeef)").pack(enc)
    named = tmp_path / "named.tlog"
    named.write_bytes(data[:8] + banner + data)            # the first frame's time header, then the banner
    flog = read_log(named, ARDUPILOT_3_BARO_TEMP_CLAMP_C)
    rep = flog.report
    assert rep.firmware.startswith("ArduPlane V4.5.1") and rep.baro_temp_clamp_c == 35.0
    assert rep.air_temp_c == pytest.approx(35.0) and long_log.report.air_temp_c == pytest.approx(25.0)
    tas_35 = np.array([a.tas_m_s for a in flog.of_type(AirspeedSample)])
    tas_25 = np.array([a.tas_m_s for a in long_log.of_type(AirspeedSample)])
    # the same pressures, each temperature 10 K higher: sqrt(T + 10 / T) at 290-310 K
    ratio = tas_35 / tas_25
    assert np.all((ratio > math.sqrt(310.0 / 300.0) - 1e-3) & (ratio < math.sqrt(300.0 / 290.0) + 1e-3))


def test_a_tlog_with_the_vehicles_autopilot_version_takes_that_versions_baro_clamp(tmp_path, long_log):
    """A ground station that asked for AUTOPILOT_VERSION logged it: the ALFA log with ArduPlane 4.5.1's answer (from
    the vehicle, which its heartbeat names ArduPilot) in front takes 4.x's 35 degC, as the live link does; the same
    answer from another system, or a damaged one, names nothing."""
    data = shared_data("flightlogs", LONG).read_bytes()
    from pymavlink.dialects.v10 import ardupilotmega as mav1

    def with_version(name: str, src: tuple[int, int], version: int) -> Path:
        enc = mav1.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
        msg = enc.autopilot_version_encode(0, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0).pack(enc)
        path = tmp_path / name
        path.write_bytes(data[:8] + msg + data)
        return path

    v451 = (4 << 24) | (5 << 16) | (1 << 8) | 255
    rep = read_log(with_version("vehicle.tlog", (1, 1), v451), ARDUPILOT_3_BARO_TEMP_CLAMP_C).report
    assert rep.firmware == "ArduPilot V4.5.1" and rep.baro_temp_clamp_c == 35.0
    assert rep.air_temp_c == pytest.approx(35.0)
    for name, src, version in (("other.tlog", (7, 1), v451), ("damaged.tlog", (1, 1), 0)):
        rep = read_log(with_version(name, src, version), ARDUPILOT_3_BARO_TEMP_CLAMP_C).report
        assert rep.firmware == "" and rep.baro_temp_clamp_c == ARDUPILOT_3_BARO_TEMP_CLAMP_C, name


# ---------------------------------------------------------------------------------------------------------------
# Damaged and unknown files


def test_truncated_tlog_gives_the_readable_part_and_a_warning(tmp_path, short_log):
    data = shared_data("flightlogs", SHORT).read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2])
    flog = read_log(cut)
    assert flog.report.warnings and "truncated" in flog.report.warnings[0]
    imu_cut = flog.of_type(ImuSample)
    imu_full = short_log.of_type(ImuSample)
    assert 0.4 * len(imu_full) < len(imu_cut) < 0.6 * len(imu_full)
    # what was read is the beginning of the full log, sample for sample (absolute boot-clock times)
    for a, b in zip(imu_cut, imu_full, strict=False):
        assert a.t_us + flog.report.t0_boot_us == b.t_us + short_log.report.t0_boot_us
        np.testing.assert_array_equal(a.accel_b_m_s2, b.accel_b_m_s2)


def test_corrupt_block_inside_a_tlog_is_reported(tmp_path, short_log):
    data = bytearray(shared_data("flightlogs", SHORT).read_bytes())
    rng = np.random.default_rng(5)
    mid = len(data) // 2
    data[mid: mid + 2000] = rng.integers(0, 256, 2000, dtype=np.uint8).tobytes()
    bad = tmp_path / "bad.tlog"
    bad.write_bytes(bytes(data))
    flog = read_log(bad)
    assert any("skipped as undecodable" in w for w in flog.report.warnings)
    # data on both sides of the hole, almost all of it
    assert flog.report.counts["ImuSample"] > 0.95 * short_log.report.counts["ImuSample"]
    assert flog.duration_s == pytest.approx(short_log.duration_s, abs=0.5)


@pytest.mark.parametrize("suffix", [".tlog", ".bin", ".ulg", ".BIN"])
def test_garbage_and_empty_files_give_warnings_not_exceptions(tmp_path, suffix):
    rng = np.random.default_rng(12)
    junk = tmp_path / f"junk{suffix}"
    junk.write_bytes(rng.integers(0, 256, 20_000, dtype=np.uint8).tobytes())
    flog = read_log(junk)
    assert len(flog) == 0 and flog.report.warnings and "no samples" in flog.report.warnings[-1]
    empty = tmp_path / f"empty{suffix}"
    empty.write_bytes(b"")
    flog = read_log(empty)
    assert len(flog) == 0 and "empty" in flog.report.warnings[0]


def test_unknown_extension_and_missing_file(tmp_path):
    other = tmp_path / "flight.csv"
    other.write_text("t_us\n1\n")
    with pytest.raises(LogFormatError, match=r"unknown log type '.csv'"):
        read_log(other)
    with pytest.raises(FileNotFoundError):
        read_log(tmp_path / "missing.tlog")
    folder = tmp_path / "folder.ulg"
    folder.mkdir()
    with pytest.raises(LogFormatError, match="not a regular file"):
        read_log(folder)


# ---------------------------------------------------------------------------------------------------------------
# PX4 ULog, written here from the format specification (docs.px4.io "ULog File Format")

_CODES = {"uint64_t": "Q", "float": "f", "int32_t": "i", "uint8_t": "B", "bool": "?"}


def _ulog_message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _write_ulog(path: Path, topics: list[tuple[str, list[tuple[str, str]], list[tuple]]]) -> None:
    """A minimal ULog: header, flag bits, formats, subscriptions, then data messages in time order."""
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0))
    out += _ulog_message("B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
    for name, fields, _ in topics:
        out += _ulog_message("F", (name + ":" + "".join(f"{t} {n};" for t, n in fields)).encode())
    for msg_id, (name, _, _) in enumerate(topics):
        out += _ulog_message("A", struct.pack("<BH", 0, msg_id) + name.encode())
    items = []
    for msg_id, (_, fields, rows) in enumerate(topics):
        fmt = "<"
        for t, _ in fields:
            base, _, n = t.partition("[")
            fmt += _CODES[base] * (int(n[:-1]) if n else 1)
        for row in rows:
            items.append((row[0], _ulog_message("D", struct.pack("<H", msg_id) + struct.pack(fmt, *row))))
    for _, b in sorted(items, key=lambda x: x[0]):
        out += b
    path.write_bytes(bytes(out))


@pytest.fixture()
def synthetic_ulog(tmp_path):
    """Five seconds of a known flight: level turn at 0.1 rad/s, 18 m/s TAS, wind 3 m/s from the west."""
    t0 = 5_000_000
    rows_imu, rows_att, rows_air, rows_baro, rows_gps, rows_wind = [], [], [], [], [], []
    truth = {"yaw": [], "pos": []}
    lat0, lon0 = 47.3977, 8.5456
    m_lat = 111132.954 - 559.822 * math.cos(2 * math.radians(lat0))
    m_lon = 111412.84 * math.cos(math.radians(lat0))
    for k in range(250):  # 50 Hz
        t = t0 + k * 20_000
        rows_imu.append((t, 0.0, 0.0, 0.1, 0.0, 0.0, -9.81))
        if k % 5 == 0:  # 10 Hz
            yaw = -3.0 + 0.1 * k * 0.02
            q = Rotation.from_euler("ZYX", [yaw, 0.05, 0.2]).as_quat()  # x, y, z, w
            rows_att.append((t, q[3], q[0], q[1], q[2]))
            truth["yaw"].append(yaw)
            rows_air.append((t, 18.0, 17.5))
            rows_baro.append((t, 540.0, 95000.0))
            north, east = 15.0 * k * 0.02, 5.0 * k * 0.02
            truth["pos"].append((north, east, -2.0))
            rows_gps.append((t, int(round((lat0 + north / m_lat) * 1e7)), int(round((lon0 + east / m_lon) * 1e7)),
                             int(round(490.0 * 1000 + 2000)), 15.0, 5.0, -0.5, True, 3, 12))
            rows_wind.append((t, 0.0, 3.0))  # air moving east: wind FROM the west
    # the first GNSS row (at t0) is the origin: its altitude is 492 m
    topics = [
        ("sensor_combined", [("uint64_t", "timestamp"), ("float[3]", "gyro_rad"), ("float[3]", "accelerometer_m_s2")],
         rows_imu),
        ("vehicle_attitude", [("uint64_t", "timestamp"), ("float[4]", "q")], rows_att),
        ("airspeed_validated", [("uint64_t", "timestamp"), ("float", "true_airspeed_m_s"),
                                ("float", "equivalent_airspeed_m_s")], rows_air),
        ("vehicle_air_data", [("uint64_t", "timestamp"), ("float", "baro_alt_meter"), ("float", "baro_pressure_pa")],
         rows_baro),
        ("vehicle_gps_position", [("uint64_t", "timestamp"), ("int32_t", "lat"), ("int32_t", "lon"), ("int32_t", "alt"),
                                  ("float", "vel_n_m_s"), ("float", "vel_e_m_s"), ("float", "vel_d_m_s"),
                                  ("bool", "vel_ned_valid"), ("uint8_t", "fix_type"), ("uint8_t", "satellites_used")],
         rows_gps),
        ("wind", [("uint64_t", "timestamp"), ("float", "windspeed_north"), ("float", "windspeed_east")], rows_wind),
    ]
    path = tmp_path / "flight.ulg"
    _write_ulog(path, topics)
    return path, truth, t0


def test_ulog_reads_every_topic_with_its_units(synthetic_ulog):
    path, truth, t0 = synthetic_ulog
    flog = read_log(path)
    rep = flog.report
    assert rep.ok, rep.warnings
    assert rep.counts == {"ImuSample": 250, "AttitudeSample": 50, "AirspeedSample": 50, "BaroSample": 50,
                          "GnssSample": 50, "AutopilotWind": 50}
    assert rep.t0_boot_us == t0 and flog.duration_s == pytest.approx(4.98)
    att = flog.of_type(AttitudeSample)
    np.testing.assert_allclose(angle_diff([a.yaw_rad for a in att], truth["yaw"]), 0.0, atol=1e-6)
    assert att[0].roll_rad == pytest.approx(0.2, abs=1e-6) and att[0].pitch_rad == pytest.approx(0.05, abs=1e-6)
    imu = flog.of_type(ImuSample)
    np.testing.assert_allclose(imu[3].gyro_b_rad_s, [0.0, 0.0, 0.1], atol=1e-7)
    assert imu[3].t_us == 60_000
    air = flog.of_type(AirspeedSample)[0]
    assert air.tas_m_s == pytest.approx(18.0) and math.isnan(air.eas_m_s)  # PX4 logs TAS: no conversion
    baro = flog.of_type(BaroSample)[0]
    assert baro.alt_m == pytest.approx(float(pressure_altitude_m(95000.0)))
    gnss = flog.of_type(GnssSample)
    pos = np.array([g.pos_ned_m for g in gnss])
    np.testing.assert_allclose(pos, np.array(truth["pos"]) - [0.0, 0.0, -2.0], atol=0.05)
    np.testing.assert_allclose(gnss[7].vel_ned_m_s, [15.0, 5.0, -0.5])
    assert gnss[0].n_sats == 12 and rep.origin_alt_m == pytest.approx(492.0)
    wind = flog.of_type(AutopilotWind)[0]
    assert wind.speed_m_s == pytest.approx(3.0)
    assert math.degrees(wind.wind_from_rad) == pytest.approx(270.0)  # from the west
    np.testing.assert_allclose(wind.wind_ned_m_s, [0.0, 3.0], atol=1e-12)


def test_truncated_ulog_gives_the_readable_part_and_a_warning(synthetic_ulog, tmp_path):
    path, _, _ = synthetic_ulog
    data = path.read_bytes()
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(data[: len(data) - 7])  # inside the last message
    flog = read_log(cut)
    assert any("truncated" in w for w in flog.report.warnings)
    assert len(flog) == len(read_log(path)) - 1
