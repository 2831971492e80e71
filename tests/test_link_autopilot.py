"""The link against a stock autopilot's message set: rates asked for and granted, the IMU messages ArduPlane and PX4
actually send, true airspeed from the equivalent one, the autopilot's clock on every sample, and the velocity
outputs (body-frame forms carry no heading of their own)."""

from __future__ import annotations

import dataclasses
import math
import os
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from common.atmosphere import eas_to_tas_ratio, pressure_altitude_m
from common.samples import AirspeedSample, AttitudeSample, BaroSample, ImuSample
from gsoe.rotation import R_nb_from_euler
from nav.link import (
    MAV_FRAME_BODY_FRD,
    MAV_FRAME_LOCAL_FRD,
    CompanionLink,
    LinkConfig,
    OutputEstimate,
    TelemetryGuard,
    body_velocity,
    encode_outputs,
    quat_from_euler,
    rates_text,
    vision_confidence,
)
from tests.polling import wait_for

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

G = 9.80665
US = 1_000_000


class Clock:
    """The companion's clock for a guard under test."""

    def __init__(self, t_us: int = 5_000_000_000) -> None:
        self.t_us = t_us

    def __call__(self) -> int:
        return self.t_us


def guard(**kw: Any) -> tuple[TelemetryGuard, Clock]:
    clock = Clock()
    return TelemetryGuard(LinkConfig(**kw), clock=clock), clock


def scaled_imu(t_ms: int, acc_mg: tuple[int, int, int], gyro_mrad: tuple[int, int, int]) -> dict[str, Any]:
    return {"time_boot_ms": t_ms, "xacc": acc_mg[0], "yacc": acc_mg[1], "zacc": acc_mg[2], "xgyro": gyro_mrad[0],
            "ygyro": gyro_mrad[1], "zgyro": gyro_mrad[2], "xmag": 0, "ymag": 0, "zmag": 0, "temperature": 3000}


def raw_imu(t_us: int, acc_mg: tuple[int, int, int], gyro_mrad: tuple[int, int, int]) -> dict[str, Any]:
    f = scaled_imu(0, acc_mg, gyro_mrad)
    f.pop("time_boot_ms")
    return {**f, "time_usec": t_us, "id": 0}


def test_arduplane_imu_messages_make_one_stream_in_si_units():
    """ArduPlane streams RAW_IMU (mG, mrad/s), SCALED_IMU2 and SCALED_IMU3 together: RAW_IMU alone is used, scaled
    to m/s^2 and rad/s; HIGHRES_IMU (float SI), once it arrives, takes over."""
    g, clock = guard()
    s = g.message("RAW_IMU", raw_imu(61_184_683, (10, -20, -1001), (1, 2, -3)))
    assert isinstance(s, ImuSample)
    np.testing.assert_allclose(s.accel_b_m_s2, np.array([10, -20, -1001]) * G / 1000)
    np.testing.assert_allclose(s.gyro_b_rad_s, [0.001, 0.002, -0.003])
    clock.t_us += 1000
    assert g.message("SCALED_IMU2", scaled_imu(61_185, (0, 0, -1000), (0, 0, 0))) is None
    assert g.message("SCALED_IMU3", scaled_imu(61_185, (0, 0, -1000), (0, 0, 0))) is None
    clock.t_us += 20_000
    hi = {"time_usec": 61_210_000, "xacc": 0.5, "yacc": 0.0, "zacc": -9.8, "xgyro": 0.01, "ygyro": 0.0,
          "zgyro": 0.02, "fields_updated": 0x1FFF}
    s = g.message("HIGHRES_IMU", hi)
    assert isinstance(s, ImuSample) and s.accel_b_m_s2[0] == 0.5 and s.gyro_b_rad_s[2] == 0.02
    clock.t_us += 20_000
    assert g.message("RAW_IMU", raw_imu(61_230_000, (0, 0, -1000), (0, 0, 0))) is None  # HIGHRES_IMU is in use
    assert g.used["imu"] == "HIGHRES_IMU"
    # HIGHRES_IMU silent for source_timeout_s: back to RAW_IMU
    clock.t_us += int(LinkConfig().source_timeout_s * US) + 1
    assert isinstance(g.message("RAW_IMU", raw_imu(62_300_000, (0, 0, -1000), (0, 0, 0))), ImuSample)
    # an update without new accelerometer and gyro data is no sample
    assert g.message("HIGHRES_IMU", {**hi, "time_usec": 62_400_000, "fields_updated": 1 << 9}) is None
    # PX4's RAW_IMU scaling is configurable
    g2, _ = guard(raw_imu_accel_scale_m_s2=0.01, raw_imu_gyro_scale_rad_s=0.002)
    s = g2.message("RAW_IMU", raw_imu(1000, (100, 0, 0), (10, 0, 0)))
    assert s is not None and s.accel_b_m_s2[0] == pytest.approx(1.0) and s.gyro_b_rad_s[0] == pytest.approx(0.02)


def test_attitude_from_attitude_quaternion_and_baro_from_altitude_px4():
    g, _ = guard()
    roll, pitch, yaw = 0.2, -0.1, 2.5
    w, x, y, z = quat_from_euler(roll, pitch, yaw)
    s = g.message("ATTITUDE_QUATERNION", {"time_boot_ms": 1000, "q1": w, "q2": x, "q3": y, "q4": z,
                                          "rollspeed": 0.0, "pitchspeed": 0.0, "yawspeed": 0.0})
    assert isinstance(s, AttitudeSample)
    assert (s.roll_rad, s.pitch_rad, s.yaw_rad) == pytest.approx((roll, pitch, yaw), abs=1e-6)
    b = g.message("ALTITUDE", {"time_usec": 1_010_000, "altitude_monotonic": 612.5, "altitude_amsl": 612.0,
                               "altitude_local": 100.0, "altitude_relative": 100.0, "altitude_terrain": math.nan,
                               "bottom_clearance": math.nan})
    assert isinstance(b, BaroSample) and b.alt_m == 612.5
    assert g.message("ALTITUDE", {"time_usec": 1_020_000, "altitude_monotonic": None}) is None  # NaN: rejected


def test_equivalent_airspeed_is_made_true_with_the_baro_air_density():
    """VFR_HUD carries ArduPilot's equivalent airspeed; at 934 hPa and 30.6 degC (ArduPlane SITL at 680 m) the
    true airspeed is 6.9 % higher; with the ISA temperature 3.4 %."""
    g, clock = guard()
    assert g.message("VFR_HUD", {"airspeed": 21.0, "groundspeed": 0, "heading": 0, "throttle": 0, "alt": 0,
                                 "climb": 0}) is None  # no air density before the first baro report
    assert g.rejected == {"airspeed:no air density yet (no baro)": 1}
    g.message("SCALED_PRESSURE", {"time_boot_ms": 2000, "press_abs": 933.87, "press_diff": 0.0,
                                  "temperature": 3056, "temperature_press_diff": 0})
    clock.t_us += 10_000
    s = g.message("VFR_HUD", {"airspeed": 21.0, "groundspeed": 0, "heading": 0, "throttle": 0, "alt": 0, "climb": 0})
    assert isinstance(s, AirspeedSample)
    assert s.eas_m_s == 21.0 and s.tas_m_s == pytest.approx(21.0 / 0.9351, rel=2e-3)
    assert s.t_us == g.link_clock.newest_us()  # VFR_HUD has no stamp: the newest autopilot stamp
    g_isa, _ = guard(air_temperature="isa")
    g_isa.message("SCALED_PRESSURE", {"time_boot_ms": 2000, "press_abs": 933.87, "press_diff": 0.0,
                                      "temperature": 3056, "temperature_press_diff": 0})
    s = g_isa.message("VFR_HUD", {"airspeed": 21.0, "groundspeed": 0, "heading": 0, "throttle": 0, "alt": 0,
                                  "climb": 0})
    assert s is not None and s.tas_m_s == pytest.approx(21.0 / 0.9675, rel=2e-3)
    # sea level in the ISA: TAS = EAS
    assert float(eas_to_tas_ratio(101325.0)) == pytest.approx(1.0, rel=1e-6)


def test_a_warm_baro_is_clamped_and_the_air_cools_with_height_as_ardupilot_takes_it():
    """ArduPilot's EAS2TAS: the baro's temperature at the ground at most 35 degC (4.x), the ISA lapse above it.  A
    board baro reading 55 degC at 1000 hPa, then 500 m higher (still 55 degC): the density of 35 - 3.25 degC."""
    g, clock = guard()
    vfr = {"airspeed": 20.0, "groundspeed": 0, "heading": 0, "throttle": 0, "alt": 0, "climb": 0}
    g.message("SCALED_PRESSURE", {"time_boot_ms": 2000, "press_abs": 1000.0, "press_diff": 0.0,
                                  "temperature": 5500, "temperature_press_diff": 0})
    clock.t_us += 10_000
    s = g.message("VFR_HUD", vfr)
    assert s is not None and s.tas_m_s == pytest.approx(20.0 * math.sqrt(1.225 / (1e5 / (287.053 * 308.15))),
                                                         rel=1e-4)
    # a glitch (2000 hPa: 5.6 km below sea level) is neither the air's pressure nor the new ground
    g.message("SCALED_PRESSURE", {"time_boot_ms": 2500, "press_abs": 2000.0, "press_diff": 0.0,
                                  "temperature": 2000, "temperature_press_diff": 0})
    clock.t_us += 10_000
    s2 = g.message("VFR_HUD", vfr)
    assert s2 is not None and s2.tas_m_s == s.tas_m_s
    p_up_hpa = 1013.25 * (1.0 - 0.0065 * (float(pressure_altitude_m(1e5)) + 500.0) / 288.15) ** 5.25588
    g.message("SCALED_PRESSURE", {"time_boot_ms": 3000, "press_abs": p_up_hpa, "press_diff": 0.0,
                                  "temperature": 5500, "temperature_press_diff": 0})
    clock.t_us += 10_000
    s = g.message("VFR_HUD", vfr)
    rho_up = 100.0 * p_up_hpa / (287.053 * (308.15 - 3.25))
    assert s is not None and s.tas_m_s == pytest.approx(20.0 * math.sqrt(1.225 / rho_up), rel=1e-4)


def test_the_autopilots_version_sets_the_clamp_an_ardupilot_3_took_25_degc():
    """ArduPilot 3.x clamped the baro's temperature at 25 degC, 4.x at 35 degC: once the autopilot's HEARTBEAT names
    ArduPilot and its AUTOPILOT_VERSION says 3.9.11, a 55 degC baro stands for 25 degC air, taken again for the
    reference already held (in either order of the two messages); a PX4 (autopilot type 12) keeps the configured
    clamp; a version that is not three small integers changes nothing."""
    vfr = {"airspeed": 20.0, "groundspeed": 0, "heading": 0, "throttle": 0, "alt": 0, "climb": 0}
    hb_ardupilot = {"type": 1, "autopilot": 3, "base_mode": 0, "custom_mode": 0, "system_status": 4}

    def tas(g: TelemetryGuard, clock: Clock) -> float:
        clock.t_us += 10_000
        s = g.message("VFR_HUD", vfr, (1, 1))
        assert s is not None
        return s.tas_m_s

    def tas_at(temp_c: float) -> float:
        return 20.0 * math.sqrt(1.225 / (1e5 / (287.053 * (273.15 + temp_c))))

    for version_first in (False, True):
        g, clock = guard()
        if version_first:
            g.firmware_version(3, 9, 11)
        g.message("HEARTBEAT", hb_ardupilot, (1, 1))
        g.message("SCALED_PRESSURE", {"time_boot_ms": 2000, "press_abs": 1000.0, "press_diff": 0.0,
                                      "temperature": 5500, "temperature_press_diff": 0}, (1, 1))
        if not version_first:
            assert g.baro_temp_clamp_c == 35.0 and tas(g, clock) == pytest.approx(tas_at(35.0), rel=1e-4)
            g.firmware_version(3, 9, 11)
        assert g.firmware == "ArduPilot 3.9.11" and g.baro_temp_clamp_c == 25.0
        assert tas(g, clock) == pytest.approx(tas_at(25.0), rel=1e-4)
        g.firmware_version(4, 5, 7)                                   # an update in flight: the 4.x clamp again
        assert g.baro_temp_clamp_c == 35.0 and tas(g, clock) == pytest.approx(tas_at(35.0), rel=1e-4)
    g, clock = guard(baro_temp_clamp_c=30.0)
    g.message("HEARTBEAT", {**hb_ardupilot, "autopilot": 12}, (1, 1))
    g.firmware_version(1, 15, 4)
    assert g.baro_temp_clamp_c == 30.0 and g.firmware == "autopilot type 12 1.15.4"
    g, clock = guard()
    g.message("HEARTBEAT", hb_ardupilot, (1, 1))
    g.firmware_version(3, -1, 2)
    g.firmware_version(300, 1, 2)
    assert g.baro_temp_clamp_c == 35.0 and g.firmware == "" and not g.version_known
    # the message itself: flight_sw_version = major << 24 | minor << 16 | patch << 8 | type; garbage (major 0
    # included) is counted and changes nothing, a foreign sender's is refused
    for bad in ({}, {"flight_sw_version": "x"}, {"flight_sw_version": -1}, {"flight_sw_version": 2**40},
                {"flight_sw_version": 0}, {"flight_sw_version": None}):
        assert g.message("AUTOPILOT_VERSION", bad, (1, 1)) is None
    assert g.rejected["version:malformed AUTOPILOT_VERSION"] == 6 and not g.version_known
    v382 = (3 << 24) | (8 << 16) | (2 << 8) | 255
    g.message("AUTOPILOT_VERSION", {"flight_sw_version": v382}, (7, 1))
    assert not g.version_known and any(k.startswith("version:from system 7") for k in g.rejected)
    g.message("AUTOPILOT_VERSION", {"flight_sw_version": v382}, (1, 1))
    assert g.firmware == "ArduPilot 3.8.2" and g.baro_temp_clamp_c == 25.0


def test_samples_run_on_the_autopilot_clock_at_its_rate():
    """A SITL at --speedup 5: the autopilot's stamps advance five times faster than the companion's clock; the
    samples' times advance with the stamps (the estimator's physics runs on the autopilot's time), start at the
    companion's clock and map back to the autopilot's clock exactly."""
    g, clock = guard()
    t0 = clock.t_us
    times = []
    for i in range(200):
        clock.t_us = t0 + i * 4_000  # 4 ms of companion time ...
        s = g.message("ATTITUDE", {"time_boot_ms": 100_000 + 20 * i, "roll": 0.0, "pitch": 0.0, "yaw": 0.0,
                                   "rollspeed": 0.0, "pitchspeed": 0.0, "yawspeed": 0.0})  # ... 20 ms of autopilot's
        assert s is not None
        times.append(s.t_us)
    assert times[0] == t0 and np.all(np.diff(times) == 20_000)
    lc = g.link_clock
    assert lc.to_vehicle_us(times[-1]) == (100_000 + 20 * 199) * 1000
    clock.t_us += 2_000
    assert lc.now_us() == times[-1] + 2_000  # the link silent: time still passes
    # a stray stamp from far back is refused; a reboot (stamps carrying on from the jump) re-synchronises
    clock.t_us += 2_000
    att = {"roll": 0.0, "pitch": 0.0, "yaw": 0.0, "rollspeed": 0.0, "pitchspeed": 0.0, "yawspeed": 0.0}
    assert g.message("ATTITUDE", {**att, "time_boot_ms": 1000}) is None
    assert g.rejected["attitude:time jumped back"] == 1
    assert g.message("ATTITUDE", {**att, "time_boot_ms": 104_000}) is not None
    out = [g.message("ATTITUDE", {**att, "time_boot_ms": 500 + 20 * k}) for k in range(6)]
    assert out[:4] == [None] * 4 and all(isinstance(s, AttitudeSample) for s in out[4:])
    assert out[4].t_us > times[-1] and out[5].t_us - out[4].t_us == 20_000
    # a stamp far ahead of the others (another time base) is refused
    assert g.message("ATTITUDE", {**att, "time_boot_ms": 10_000_000}) is None


def _autopilot_stream(seconds: float) -> list[tuple[int, str, dict[str, Any]]]:
    """What ArduPlane sends, in its order: (send time on its clock in us, message, fields); attitude and IMU at 50 Hz,
    baro and VFR_HUD (no stamp of its own) at 10 Hz."""
    att = {"roll": 0.01, "pitch": 0.02, "rollspeed": 0.0, "pitchspeed": 0.0, "yawspeed": 0.0}
    out: list[tuple[int, str, dict[str, Any]]] = []
    for k in range(round(seconds * 50)):
        t_ms = 60_000 + 20 * k
        out.append((t_ms * 1000, "ATTITUDE", {**att, "time_boot_ms": t_ms, "yaw": 0.001 * k}))
        out.append((t_ms * 1000 + 100, "RAW_IMU", raw_imu(t_ms * 1000 + 100, (10, -20, -1001), (1, 2, -3 + k % 7))))
        if k % 5 == 0:
            out.append((t_ms * 1000 + 200, "SCALED_PRESSURE", {"time_boot_ms": t_ms, "press_abs": 934.0 - 0.01 * k,
                                                               "press_diff": 0.0, "temperature": 3000,
                                                               "temperature_press_diff": 0}))
            out.append((t_ms * 1000 + 300, "VFR_HUD", {"airspeed": 20.0 + 0.01 * k, "groundspeed": 0, "heading": 0,
                                                       "throttle": 0, "alt": 0, "climb": 0}))
    return out


def _received(stream: list[tuple[int, str, dict[str, Any]]], arrival_us: Any) -> list[tuple[str, Any]]:
    """The samples a fresh guard makes of ``stream`` when message i arrives at companion time ``arrival_us(i, sent)``
    (the companion's clock 5 000 s ahead of the autopilot's)."""
    g, clock = guard()
    samples = []
    for i, (sent_us, name, fields) in enumerate(stream):
        clock.t_us = 5_000_000_000 + arrival_us(i, sent_us)
        s = g.message(name, fields)
        if s is not None:
            samples.append((name, s))
    return samples


def test_a_bursty_link_gives_the_samples_of_a_prompt_one():
    """A telemetry radio holds messages back and releases them in bursts: every message of a second arriving at once
    at its end (up to 1 s late), after a prompt first one.  The samples are those of the prompt link (5 ms of
    latency) exactly: the same times (the autopilot's stamps, VFR_HUD's the newest before it), the same values."""
    stream = _autopilot_stream(6.0)
    prompt = _received(stream, lambda i, sent: sent + 5_000)
    bursty = _received(stream, lambda i, sent: sent + 5_000 if i == 0 else (sent // US + 1) * US + 5_000)
    assert len(prompt) == len(stream) and len(bursty) == len(prompt)
    for (name_p, p), (name_b, b) in zip(prompt, bursty, strict=True):
        assert name_p == name_b and p.t_us == b.t_us, (name_p, p, b)
        for field in dataclasses.fields(p):
            np.testing.assert_array_equal(getattr(p, field.name), getattr(b, field.name))
    # and the times are the autopilot's: 20 ms apart at 50 Hz, whatever the arrival
    att_t = [s.t_us for name, s in bursty if name == "ATTITUDE"]
    assert set(np.diff(att_t)) == {20_000}


def estimate(**kw: Any) -> OutputEstimate:
    args: dict[str, Any] = dict(t_us=10_000_000, valid=True, drift_rad=math.radians(10.0),
                                drift_sigma_rad=0.01, ata_rad=0.0, vel_ne_m_s=np.array([20.0, 0.0]),
                                vel_cov_ne=np.diag([0.04, 0.09]), wind_ne_m_s=np.array([0.0, 5.0]),
                                wind_cov_ne=np.diag([0.25, 0.25]), height_agl_m=100.0, quality=0.9, gnss_state=2,
                                vel_d_m_s=0.5, vel_d_var=0.04, roll_rad=0.3, pitch_rad=0.05, heading_rad=0.0)
    args.update(kw)
    return OutputEstimate(**args)


@pytest.mark.parametrize("heading_deg", [0.0, 73.0, -140.0])
def test_body_frame_velocity_carries_no_heading(heading_deg):
    """The same heading-aligned velocity (ground speed 21 m/s, 12 deg of drift) at any heading gives the same
    VISION_POSITION_DELTA: the body-frame velocity depends on roll, pitch and the drift only."""
    psi, drift, vg = math.radians(heading_deg), math.radians(12.0), 21.0
    course = psi + drift
    est = estimate(vel_ne_m_s=vg * np.array([math.cos(course), math.sin(course)]), heading_rad=psi,
                   vel_cov_ne=np.diag([0.04, 0.04]))
    cfg = LinkConfig(velocity_message="vision_position_delta")
    name, f = encode_outputs(est, cfg, {"vision"}, t_offset_us=4_000_000, vision_delta_us=100_000)["vision"]
    assert name == "VISION_POSITION_DELTA" and f["time_usec"] == 6_000_000 and f["time_delta_usec"] == 100_000
    v_h = np.array([vg * math.cos(drift), vg * math.sin(drift), 0.5])
    expected = R_nb_from_euler(0.3, 0.05, 0.0).T @ v_h * 0.1
    np.testing.assert_allclose(f["position_delta"], expected, atol=1e-9)
    assert f["confidence"] == vision_confidence(0.2, cfg) == 75  # sigma 0.2 m/s in [0.1, 0.5] m/s


def test_odometry_is_the_body_velocity_with_the_estimate_attitude():
    est = estimate()
    cfg = LinkConfig(velocity_message="odometry")
    name, f = encode_outputs(est, cfg, {"vision"})["vision"]
    assert name == "ODOMETRY" and (f["frame_id"], f["child_frame_id"]) == (MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD)
    assert all(math.isnan(f[k]) for k in ("x", "y", "z")) and math.isnan(f["pose_covariance"][0])
    w, x, y, z = f["q"]
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    v_n = R @ np.array([f["vx"], f["vy"], f["vz"]])  # what ArduPilot does with it: q * v
    np.testing.assert_allclose(v_n, [20.0, 0.0, 0.5], atol=1e-9)
    v_b, cov_b = body_velocity(est, cfg)
    assert f["velocity_covariance"][0] == pytest.approx(cov_b[0, 0]) and f["velocity_covariance"][11] == \
        pytest.approx(cov_b[2, 2])
    # without the attitude no body-frame velocity is sent
    assert "vision" not in encode_outputs(estimate(roll_rad=math.nan), cfg, {"vision"})
    # the NED form needs none
    vse = encode_outputs(estimate(roll_rad=math.nan), LinkConfig(velocity_message="vision_speed_estimate"),
                         {"vision"})["vision"]
    assert vse[0] == "VISION_SPEED_ESTIMATE" and (vse[1]["x"], vse[1]["y"]) == (20.0, 0.0)


def test_rates_text_fits_a_statustext():
    granted = {"attitude": ("ATTITUDE", 40.0), "imu": ("HIGHRES_IMU", 40.0), "baro": ("SCALED_PRESSURE", 10.0),
               "airspeed": ("VFR_HUD", 10.0), "gnss": ("GPS_RAW_INT", 5.0), "home": ("GLOBAL_POSITION_INT", 5.0)}
    text = rates_text(granted)
    assert text == "GSOE Hz ATT 40 IMU 40 BARO 10 AIR 10 GPS 5 POS 5" and len(text) <= 50


# ------------------------------------------------------------------------------------------------ over MAVLink
class StockAutopilot:
    """An ArduPlane-like autopilot on UDP (pymavlink): streams nothing useful until asked, refuses intervals
    faster than ``max_hz`` (COMMAND_ACK DENIED and a STATUSTEXT, as ArduPlane does above 0.8 x SCHED_LOOP_RATE),
    streams what was granted; its clock runs ``speedup`` times faster than the wall clock."""

    def __init__(self, port: int, max_hz: float = 40.0, speedup: float = 3.0) -> None:
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1,
                                               dialect="ardupilotmega")
        self.max_hz = max_hz
        self.speedup = speedup
        self.rates: dict[int, float] = {}
        self.requests: list[tuple[int, float, int]] = []
        self.statustexts: list[str] = []
        self.outputs: dict[str, Any] = {}
        self._next: dict[int, float] = {}
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def boot_s(self) -> float:
        return 60.0 + (time.monotonic() - self._t0) * self.speedup

    def _run(self) -> None:
        ml = mavutil.mavlink
        m = self.conn.mav
        next_hb = 0.0
        while not self._stop.is_set():
            t = self.boot_s()
            if t >= next_hb:
                m.heartbeat_send(ml.MAV_TYPE_FIXED_WING, ml.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, ml.MAV_STATE_ACTIVE)
                next_hb = t + 1.0
            for mid, hz in list(self.rates.items()):
                if t >= self._next.get(mid, 0.0):
                    self._next[mid] = t + 1.0 / hz
                    self._stream(mid, t)
            while (msg := self.conn.recv_match(blocking=False)) is not None:
                if msg.get_type() == "COMMAND_LONG" and msg.command == ml.MAV_CMD_SET_MESSAGE_INTERVAL:
                    mid, hz = int(msg.param1), 1e6 / msg.param2
                    ok = hz <= self.max_hz + 1e-6
                    if ok:
                        self.rates[mid] = hz
                    else:
                        m.statustext_send(ml.MAV_SEVERITY_WARNING, b"Requested rate too fast")
                    m.command_ack_send(msg.command, ml.MAV_RESULT_ACCEPTED if ok else ml.MAV_RESULT_DENIED)
                    self.requests.append((mid, hz, 0 if ok else 2))
                elif msg.get_type() == "STATUSTEXT":
                    self.statustexts.append(str(msg.text))
                elif msg.get_type() in ("ODOMETRY", "VISION_POSITION_DELTA", "VISION_SPEED_ESTIMATE"):
                    self.outputs[msg.get_type()] = msg.to_dict()
            time.sleep(0.002)

    def _stream(self, mid: int, t: float) -> None:
        m = self.conn.mav
        ms, us = int(t * 1000), int(t * 1e6)
        if mid == 30:
            m.attitude_send(ms, 0.1, 0.02, 1.0, 0.0, 0.0, 0.0)
        elif mid == 105:
            m.highres_imu_send(us, 0.1, 0.0, -9.8, 0.0, 0.0, 0.01, 0, 0, 0, 934.0, 0.0, 680.0, 30.0, 0x1FFF)
        elif mid == 29:
            m.scaled_pressure_send(ms, 933.87, 0.5, 3056)
        elif mid == 74:
            m.vfr_hud_send(21.0, 22.0, 57, 50, 680.0, 0.0)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=5)
        self.conn.close()


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def stock() -> Iterator[tuple[StockAutopilot, CompanionLink]]:
    port = free_udp_port()
    ap = StockAutopilot(port)
    link = CompanionLink(f"udpin://127.0.0.1:{port}", LinkConfig(connect_timeout_s=10.0))
    assert link.start(), "MAVSDK did not discover the autopilot"
    yield ap, link
    link.stop()
    ap.stop()


def test_rates_are_asked_refused_rates_fall_back_and_the_grant_is_announced(stock):
    ap, link = stock
    assert wait_for(lambda: len(link.stats.rates_granted) == 6 and any(
        t.startswith("GSOE Hz") for t in ap.statustexts), 15.0)
    g = link.stats.rates_granted
    assert g["attitude"] == ("ATTITUDE", pytest.approx(40.0)) and g["imu"] == ("HIGHRES_IMU", pytest.approx(40.0))
    assert g["baro"] == ("SCALED_PRESSURE", 10.0) and g["airspeed"] == ("VFR_HUD", 10.0)
    # 50 Hz asked first and refused (DENIED), then 40 Hz granted
    att = [(round(hz, 3), r) for mid, hz, r in ap.requests if mid == 30]
    assert att[:2] == [(50.0, 2), (40.0, 0)]
    assert "GSOE Hz ATT 40 IMU 40 BARO 10 AIR 10 GPS 5 POS 5" in ap.statustexts


def test_granted_streams_arrive_on_the_autopilot_clock(stock):
    """At speedup 3 one second of the companion's clock brings three seconds of the autopilot's stamps, and the
    samples' times span those three seconds (the estimator runs on the autopilot's time); the true airspeed is the
    equivalent one made true."""
    ap, link = stock
    assert wait_for(lambda: link.stats.rates_granted.get("attitude", ("", 0))[1] > 0, 15.0)
    time.sleep(1.0)
    while not link.samples.empty():
        link.samples.get_nowait()
    t0 = time.monotonic()
    time.sleep(1.0)
    got = []
    while not link.samples.empty():
        got.append(link.samples.get_nowait())
    wall_s = time.monotonic() - t0
    att = [s.t_us for s in got if isinstance(s, AttitudeSample)]
    assert len(att) > 80  # 3 s of the autopilot's time at 40 Hz (less the fake's scheduling jitter)
    assert (att[-1] - att[0]) / 1e6 == pytest.approx(ap.speedup * wall_s, abs=0.5)
    assert np.all(np.diff(att) > 0)
    imu = [s for s in got if isinstance(s, ImuSample)]
    assert imu and imu[-1].accel_b_m_s2[2] == pytest.approx(-9.8)
    tas = [s for s in got if isinstance(s, AirspeedSample)]
    assert tas and tas[-1].tas_m_s == pytest.approx(21.0 / 0.9351, rel=3e-3)
    # the samples' clock and the autopilot's differ by the one offset
    lc = link.guard.link_clock
    assert abs(lc.to_vehicle_us(att[-1]) / 1e6 - ap.boot_s()) < 1.0


@pytest.mark.parametrize("message", ["odometry", "vision_position_delta", "vision_speed_estimate"])
def test_each_velocity_message_reaches_the_autopilot(stock, message):
    """Including ODOMETRY's unknown (NaN) position and rates: MAVSDK's JSON takes them as null."""
    ap, link = stock
    cfg = LinkConfig(velocity_message=message)
    name, fields = encode_outputs(estimate(), cfg, {"vision"})["vision"]
    import asyncio

    asyncio.run_coroutine_threadsafe(link._send_one(name, fields), link._loop).result(timeout=5)
    assert wait_for(lambda: name in ap.outputs, 5.0), name
    got = ap.outputs[name]
    if name == "ODOMETRY":
        assert math.isnan(got["x"]) and math.isnan(got["pose_covariance"][0]) and math.isnan(got["rollspeed"])
        assert got["vx"] == pytest.approx(fields["vx"], rel=1e-6) and got["child_frame_id"] == MAV_FRAME_BODY_FRD
    elif name == "VISION_POSITION_DELTA":
        np.testing.assert_allclose(got["position_delta"], fields["position_delta"], rtol=1e-6)
    else:
        assert (got["x"], got["y"]) == pytest.approx((20.0, 0.0))


def test_gnss_loss_reports_with_a_frozen_time_still_arrive():
    """After SIM_GPS1_ENABLE 0 ArduPlane sends GPS_RAW_INT with fix type 1 and its last fix's time_usec: each one is
    a no-fix report (stamped with the newest autopilot time), not a rejected sample."""
    g, clock = guard()
    fix = {"fix_type": 6, "satellites_visible": 10, "time_usec": 61_828_000, "lat": -353632621,
           "lon": 1491652370, "alt": 584090, "vel": 2000, "cog": 9000, "h_acc": 300, "v_acc": 300, "vel_acc": 100}
    assert g.message("GPS_RAW_INT", fix).fix_ok
    for k in range(3):
        clock.t_us += 200_000
        g.message("ATTITUDE", {"time_boot_ms": 62_000 + 200 * k, "roll": 0.0, "pitch": 0.0, "yaw": 0.0})
        s = g.message("GPS_RAW_INT", {**fix, "fix_type": 1, "satellites_visible": 0})
        assert s is not None and not s.fix_ok and s.fix_type == 1 and s.t_us == g.link_clock.newest_us()
    assert not any(k.startswith("gnss") for k in g.rejected)
