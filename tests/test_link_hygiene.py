"""Link hygiene (issue 23, nav.hygiene): telemetry only from the autopilot's system and component (configured or
learnt from its heartbeat), ground-station commands only when addressed to the companion, designated pixels inside
the image, and a warning when the ground-station link is unsigned."""

from __future__ import annotations

import hashlib
import logging
from typing import Any

import pytest

from common.samples import GnssSample, ImuSample
from nav.hygiene import AutopilotSenders, addressed_to, pixel_in_image
from nav.link import LinkConfig, TelemetryGuard
from nav.signing import CommandEndpoint
from tests.polling import gather
from tests.test_link import free_udp_port

ARDUPLANE_HB = {"type": 1, "autopilot": 3}           # MAV_TYPE_FIXED_WING, MAV_AUTOPILOT_ARDUPILOTMEGA
GCS_HB = {"type": 6, "autopilot": 8}                 # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID
CAMERA_HB = {"type": 30, "autopilot": 3}             # MAV_TYPE_CAMERA naming an autopilot: still not one


def gps(t_ms: int) -> dict[str, Any]:
    return {"fix_type": 3, "satellites_visible": 12, "time_usec": t_ms * 1000, "lat": 473980000, "lon": 85460000,
            "alt": 588000, "vel": 2000, "cog": 3000, "h_acc": 1000, "v_acc": 1500, "vel_acc": 100}


def scaled_imu(t_ms: int, az_mg: int = -1000) -> dict[str, Any]:
    return {"time_boot_ms": t_ms, "xacc": 0, "yacc": 0, "zacc": az_mg, "xgyro": 0, "ygyro": 0, "zgyro": 10,
            "xmag": 0, "ymag": 0, "zmag": 0}


def highres_imu(t_ms: int) -> dict[str, Any]:
    return {"time_usec": t_ms * 1000, "xacc": 30.0, "yacc": 30.0, "zacc": 30.0, "xgyro": 3.0, "ygyro": 3.0,
            "zgyro": 3.0, "xmag": 0.0, "ymag": 0.0, "zmag": 0.0, "abs_pressure": 1000.0, "diff_pressure": 0.0,
            "pressure_alt": 0.0, "temperature": 20.0, "fields_updated": 0xFFFF}


def guard(**cfg: Any) -> TelemetryGuard:
    clock = iter(range(1_000_000, 100_000_000, 1000))
    return TelemetryGuard(LinkConfig(**cfg), clock=lambda: next(clock))


def test_the_autopilot_is_learnt_from_its_heartbeat_not_a_gcs_or_camera():
    s = AutopilotSenders()
    assert not s.known and "no heartbeat" in s.check("ATTITUDE", 1, 1)
    s.heartbeat(255, 190, **{"autopilot": GCS_HB["autopilot"], "mav_type": GCS_HB["type"]})
    s.heartbeat(1, 100, autopilot=CAMERA_HB["autopilot"], mav_type=CAMERA_HB["type"])
    assert not s.known
    s.heartbeat(1, 1, autopilot=3, mav_type=1)
    assert (s.system_id, s.component_id) == (1, 1)
    s.heartbeat(2, 1, autopilot=3, mav_type=1)                      # a second autopilot changes nothing
    assert (s.system_id, s.component_id) == (1, 1)
    assert s.check("GPS_RAW_INT", 1, 1) == ""
    assert "component 1/200" in s.check("GPS_RAW_INT", 1, 200)
    assert "system 2" in s.check("ATTITUDE", 2, 1)
    # an external tracker is a component of the vehicle: any component of the autopilot's system
    assert s.check("CAMERA_TRACKING_IMAGE_STATUS", 1, 100) == ""
    assert s.check("CAMERA_TRACKING_IMAGE_STATUS", 2, 100) != ""


def test_configured_ids_are_known_from_the_start_and_a_configured_system_is_waited_for():
    s = AutopilotSenders(7, 1)
    assert s.known and s.check("ATTITUDE", 7, 1) == "" and s.check("ATTITUDE", 1, 1) != ""
    s = AutopilotSenders(7, 0)
    s.heartbeat(1, 1, autopilot=3, mav_type=1)                      # not the configured system
    s.discovered(1, [1])
    assert not s.known
    s.discovered(7, [1, 191])
    assert (s.system_id, s.component_id) == (7, 1)


def test_the_guard_takes_telemetry_only_from_the_autopilot():
    """GPS_RAW_INT claiming the autopilot's system from another component (the issue's case) is refused and counted;
    so is everything before the autopilot's heartbeat."""
    g = guard()
    assert g.message("GPS_RAW_INT", gps(100), (1, 1)) is None          # no heartbeat yet
    assert g.message("HEARTBEAT", ARDUPLANE_HB, (1, 1)) is None
    assert isinstance(g.message("GPS_RAW_INT", gps(200), (1, 1)), GnssSample)
    assert g.message("GPS_RAW_INT", gps(300), (1, 200)) is None
    assert isinstance(g.message("GPS_RAW_INT", gps(400), (1, 1)), GnssSample)
    assert g.rejected == {"gnss:autopilot not known yet (no heartbeat)": 1,
                          "gnss:from component 1/200, not the autopilot's 1/1": 1}


def test_a_foreign_imu_message_does_not_take_over_the_imu_stream():
    """The link prefers HIGHRES_IMU over SCALED_IMU; one from a foreign component must not silence the autopilot's
    SCALED_IMU (it is refused before the preference sees it)."""
    g = guard(autopilot_system_id=1, autopilot_component_id=1)
    assert isinstance(g.message("SCALED_IMU", scaled_imu(100), (1, 1)), ImuSample)
    assert g.message("HIGHRES_IMU", highres_imu(110), (1, 200)) is None
    s = g.message("SCALED_IMU", scaled_imu(120), (1, 1))
    assert isinstance(s, ImuSample) and s.accel_b_m_s2[2] == pytest.approx(-9.80665)
    assert g.used["imu"] == "SCALED_IMU"


def test_addressed_to_and_pixels_in_the_image():
    class Cmd:
        def __init__(self, ts: int, tc: int) -> None:
            self.target_system, self.target_component = ts, tc

    assert addressed_to(Cmd(1, 191), 1, 191)
    assert not addressed_to(Cmd(1, 1), 1, 191) and not addressed_to(Cmd(2, 191), 1, 191)
    assert not addressed_to(Cmd(0, 0), 1, 191)                          # a broadcast is not ours to act on
    assert addressed_to(object(), 1, 191)                               # no target fields: telemetry
    assert pixel_in_image((0.0, 0.0), (800, 600)) and pixel_in_image((799.5, 599.9), (800, 600))
    for bad in [(800.0, 10.0), (10.0, 600.0), (-0.1, 5.0), (1e9, -1e9), (float("nan"), 1.0), (1.0,)]:
        assert not pixel_in_image(bad, (800, 600)), bad


@pytest.mark.parametrize("signed", [True, False], ids=["signed", "unsigned"])
def test_commands_for_another_target_are_dropped(signed):
    """Signed or not, only commands addressed to the companion's own system and component come out."""
    key = hashlib.sha256(b"gsoe hygiene key").digest() if signed else None
    port = free_udp_port()
    companion = CommandEndpoint(f"udpin:127.0.0.1:{port}", key, source_system=1, source_component=191)
    gcs = CommandEndpoint(f"udpout:127.0.0.1:{port}", key, source_system=255, source_component=190)
    try:
        for marker, (ts, tc) in enumerate([(1, 191), (1, 1), (2, 191), (0, 0), (1, 0), (1, 191)]):
            gcs.conn.mav.command_long_send(ts, tc, 31010, 0, float(marker), 0, 0, 0, 0, 0, 0)
        cmds = [m for m in gather(companion.poll) if m.get_type() == "COMMAND_LONG"]
        assert [c.param1 for c in cmds] == [0.0, 5.0]
        assert companion.stats.not_for_us == 4
    finally:
        companion.close()
        gcs.close()


def test_an_unsigned_ground_station_link_warns_at_start(caplog):
    port = free_udp_port()
    with caplog.at_level(logging.WARNING, logger="nav.signing"):
        plain = CommandEndpoint(f"udpin:127.0.0.1:{port}", None)
    plain.close()
    assert any("NOT signed" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="nav.signing"):
        signed = CommandEndpoint(f"udpin:127.0.0.1:{free_udp_port()}", bytes(range(32)))
    signed.close()
    assert not any("NOT signed" in r.getMessage() for r in caplog.records)
