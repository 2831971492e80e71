"""The pymavlink vehicle <-> MAVSDK companion link on 127.0.0.1, exchanging real MAVLink messages."""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
from nav.guidance import GuidanceConfig, HeadingCommand, change_heading_command_fields
from nav.link import (
    CompanionLink,
    LinkConfig,
    OutputEstimate,
    check_estimate,
    wind_from_deg,
)
from sim.mavlink_vehicle import VEHICLE_FIRMWARE, MavlinkVehicle, VehicleConfig
from tests.polling import wait_for


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def estimate(t_us: int, **kw) -> OutputEstimate:
    args = dict(valid=True, drift_rad=math.radians(12.5), drift_sigma_rad=math.radians(0.8),
                ata_rad=math.radians(40.0), vel_ne_m_s=np.array([15.0, 12.0]), vel_cov_ne=np.diag([0.09, 0.16]),
                wind_ne_m_s=np.array([0.0, 8.0]), wind_cov_ne=np.diag([0.25, 0.25]), height_agl_m=100.0,
                quality=0.9, gnss_state=2)
    args.update(kw)
    return OutputEstimate(t_us, **args)  # type: ignore[arg-type]


class VehicleThread:
    def __init__(self, port: int, cfg: VehicleConfig) -> None:
        self.vehicle = MavlinkVehicle(f"udpout:127.0.0.1:{port}", cfg, np.random.default_rng(7))
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        dt = self.vehicle.cfg.dt_s
        t0 = time.monotonic()
        i = 0
        while not self._stop.is_set():
            self.vehicle.step()
            i += 1
            lag = t0 + i * dt - time.monotonic()
            if lag > 0:
                time.sleep(lag)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=5)
        self.vehicle.close()


@pytest.fixture(scope="module")
def pair() -> Iterator[tuple[VehicleThread, CompanionLink, int]]:
    port = free_udp_port()
    veh = VehicleThread(port, VehicleConfig(start_yaw_deg=30.0, wind_ned_m_s=(0.0, 8.0)))
    link = CompanionLink(f"udpin://127.0.0.1:{port}", LinkConfig(connect_timeout_s=10.0,
                                                                 velocity_message="vision_speed_estimate"))
    assert link.start(), "MAVSDK did not discover the simulated autopilot"
    yield veh, link, port
    link.stop()
    veh.stop()


def drain(link: CompanionLink, seconds: float) -> list:
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            out.append(link.samples.get(timeout=0.05))
        except Exception:
            pass
    return out


def test_telemetry_arrives_as_validated_samples(pair):
    veh, link, _ = pair
    samples = drain(link, 1.5)
    kinds = {type(s) for s in samples}
    assert {AttitudeSample, ImuSample, AirspeedSample, BaroSample, GnssSample} <= kinds
    att = [s for s in samples if isinstance(s, AttitudeSample)]
    assert len(att) > 30  # 50 Hz stream
    assert all(np.diff([a.t_us for a in att]) > 0)
    yaw_truth = veh.vehicle.truth.yaw_rad
    assert math.cos(att[-1].yaw_rad - yaw_truth) > math.cos(math.radians(3.0))
    imu = [s for s in samples if isinstance(s, ImuSample)][-1]
    assert imu.accel_b_m_s2[2] == pytest.approx(-9.81, abs=0.3)  # SCALED_IMU mG converted to m/s^2
    tas = [s for s in samples if isinstance(s, AirspeedSample)][-1]
    assert tas.tas_m_s == pytest.approx(20.0, abs=0.01)
    gnss = [s for s in samples if isinstance(s, GnssSample)][-1]
    assert gnss.fix_type == 3 and np.all(np.isfinite(gnss.vel_ned_m_s[:2]))
    truth_v = veh.vehicle.truth.vel_ned_m_s[:2]
    np.testing.assert_allclose(gnss.vel_ned_m_s[:2], truth_v, atol=0.6)
    # the link asked for the autopilot's version (MAV_CMD_REQUEST_MESSAGE) and took its ArduPilot 4.x clamp
    assert wait_for(lambda: link.guard.version_known, 5.0)
    assert link.guard.firmware == "ArduPilot {}.{}.{}".format(*VEHICLE_FIRMWARE)
    assert link.guard.baro_temp_clamp_c == 35.0


def test_valid_outputs_reach_the_vehicle(pair):
    veh, link, _ = pair
    est = estimate(10_000_000)
    assert link.send_estimate(est) == ""
    v = veh.vehicle
    assert wait_for(lambda: {"NAMED_VALUE_FLOAT", "VISION_SPEED_ESTIMATE", "WIND_COV", "WIND"} <= set(v.received))
    vse = v.last["VISION_SPEED_ESTIMATE"]
    assert (vse["x"], vse["y"]) == pytest.approx((15.0, 12.0))
    assert vse["covariance"][0] == pytest.approx(0.09) and vse["covariance"][4] == pytest.approx(0.16)
    wind = v.last["WIND"]
    assert wind["speed"] == pytest.approx(8.0) and wind["direction"] == pytest.approx(270.0)  # blowing from west
    assert v.last["WIND_COV"]["wind_y"] == pytest.approx(8.0)
    assert wait_for(lambda: v.received.get("NAMED_VALUE_FLOAT", 0) >= 4)


def test_named_values_carry_the_numbers(pair):
    veh, link, _ = pair
    assert link.send_estimate(estimate(20_000_000, drift_rad=math.radians(-7.0), ata_rad=math.radians(-20.0))) == ""
    nv = veh.vehicle.named_values
    assert wait_for(lambda: nv.get("GSOE_DRIFT") == pytest.approx(-7.0, abs=1e-4))
    assert wait_for(lambda: nv.get("GSOE_ATA") == pytest.approx(340.0, abs=1e-3))
    assert nv.get("GSOE_GNSS") == 2.0 and nv.get("GSOE_Q") == pytest.approx(0.9)


def test_invalid_or_uncertain_estimates_are_not_sent(pair):
    veh, link, _ = pair
    v = veh.vehicle
    time.sleep(0.5)
    before = dict(v.received)
    t = 30_000_000
    bad = [
        estimate(t, valid=False, reason="optical quality low"),
        estimate(t + 1_000_000, drift_rad=math.nan),
        estimate(t + 2_000_000, vel_ne_m_s=np.array([np.inf, 0.0])),
        estimate(t + 3_000_000, drift_rad=math.radians(95.0)),
        estimate(t + 5_000_000, wind_cov_ne=np.array([[1.0, 2.0], [2.0, 1.0]])),  # not PSD
    ]
    drift_before = len(v.output_times.get("NAMED_VALUE_FLOAT:GSOE_DRIFT", []))
    reasons = [link.send_estimate(e) for e in bad]
    assert all(reasons), reasons
    time.sleep(0.5)
    for kind in ("VISION_SPEED_ESTIMATE", "WIND_COV", "WIND"):
        assert v.received.get(kind, 0) == before.get(kind, 0), kind
    assert len(v.output_times.get("NAMED_VALUE_FLOAT:GSOE_DRIFT", [])) == drift_before
    # the status values still go out, saying the estimate is withheld
    assert v.named_values["GSOE_VALID"] == 0.0 and v.named_values["GSOE_GNSS"] == 2.0


def test_heading_command_is_acknowledged_and_flown(pair):
    veh, link, _ = pair
    cmd = HeadingCommand(0, math.radians(120.0), math.radians(120.0), 0.0, False, False, True)
    link.send_heading_command(change_heading_command_fields(cmd, GuidanceConfig(), link.target_system, 1))
    assert wait_for(lambda: bool(link.stats.acks), 5.0)
    assert link.stats.acks[-1].get("result") == 0
    assert veh.vehicle.heading_commands and veh.vehicle.heading_commands[-1][1] == pytest.approx(120.0)
    assert wait_for(lambda: abs(math.degrees(veh.vehicle.truth.yaw_rad) - 120.0) < 3.0, 15.0)


def test_garbage_bytes_do_not_break_either_side(pair):
    veh, link, port = pair
    rng = np.random.default_rng(3)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(300):
            junk = rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8).tobytes()
            s.sendto(junk, ("127.0.0.1", port))  # to the companion's MAVSDK port
            if b"\xfd" not in junk[:1]:
                s.sendto(b"\xfd" + junk, ("127.0.0.1", port))
    # and to the vehicle's socket (the port pymavlink's udpout bound)
    vport = veh.vehicle.conn.port.getsockname()[1]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(300):
            s.sendto(rng.integers(0, 256, 64, dtype=np.uint8).tobytes(), ("127.0.0.1", vport))
    assert wait_for(lambda: veh.vehicle.bad_data > 0)
    drain(link, 0.3)
    fresh = drain(link, 1.0)
    assert sum(isinstance(s, AttitudeSample) for s in fresh) > 20
    assert veh.thread.is_alive()
    assert link.send_estimate(estimate(90_000_000)) == ""


def test_check_estimate_and_wind_direction_convention():
    cfg = LinkConfig()
    assert check_estimate(estimate(0), cfg) == ""
    assert "vertical" in check_estimate(estimate(0, vel_d_m_s=500.0), cfg)
    assert wind_from_deg(np.array([-5.0, 0.0])) == pytest.approx(0.0)  # blowing south: from north
    assert wind_from_deg(np.array([0.0, -5.0])) == pytest.approx(90.0)  # blowing west: from east


def test_telemetry_guard_rejects_nan_out_of_range_and_backwards_time():
    from nav.link import TelemetryGuard

    clock = iter(range(1_000_000, 10_000_000, 1000))
    g = TelemetryGuard(LinkConfig(), clock=lambda: next(clock))
    assert g.attitude(1.0, 2.0, 3.0, 1000) is not None
    assert g.attitude(math.nan, 2.0, 3.0, 2000) is None
    assert g.attitude(1.0, 95.0, 3.0, 3000) is None  # pitch beyond 90 deg
    assert g.attitude(1.0, 2.0, 3.0, 500) is None  # time backwards (within the reboot threshold)
    assert g.imu((0.0, 0.0, 100.0), (0.0, 0.0, -9.8), 4000) is None  # 100 rad/s gyro
    assert g.imu((0.0, 0.0, 0.1), (0.0, math.inf, -9.8), 5000) is None
    assert g.airspeed(-3.0) is None and g.airspeed(math.nan) is None and g.airspeed(21.0) is not None
    assert g.baro(-1.0, 6000) is None and g.baro(1000.0, 7000) is not None
    assert g.gps_raw_int({"fix_type": 3}) is None  # malformed
    assert g.rejected["attitude:not finite"] == 1 and g.rejected["attitude:time not increasing"] == 1
    assert sum(g.rejected.values()) == 9


def test_status_values_and_wind_cov_fields():
    from nav.link import encode_outputs, status_values, wind_sigmas

    est = estimate(0, wind_cov_ne=np.array([[0.09, 0.0], [0.0, 0.25]]), home_amsl_m=488.0)
    assert status_values(est, True) == {"GSOE_Q": 0.9, "GSOE_GNSS": 2.0, "GSOE_VALID": 1.0}
    assert status_values(estimate(0, quality=math.nan), False)["GSOE_Q"] == 0.0
    wc = encode_outputs(est, LinkConfig(), {"wind"})["wind_cov"][1]
    # the wind blows east (0, 8): its speed sigma is the east sigma 0.5; var_horiz the RMS of the axis sigmas
    assert wc["horiz_accuracy"] == pytest.approx(0.5)
    assert wc["var_horiz"] == pytest.approx(math.sqrt((0.09 + 0.25) / 2))
    assert wc["wind_alt"] == pytest.approx(588.0)  # AMSL: home 488 m + 100 m
    assert wc["vert_accuracy"] == LinkConfig().unknown_vertical_sigma_m_s > 0.0  # never a claimed exact 0
    assert wind_sigmas(np.array([0.01, 0.0]), np.eye(2))[0] == pytest.approx(1.0)  # calm: RMS sigma


def test_tracking_reports_are_validated():
    from nav.link import TelemetryGuard

    g = TelemetryGuard(LinkConfig(), clock=lambda: 5)
    ok = g.tracking({"tracking_status": 1, "tracking_mode": 1, "point_x": 0.25, "point_y": 0.75})
    assert ok is not None and ok.active and (ok.x_norm, ok.y_norm) == (0.25, 0.75)
    idle = g.tracking({"tracking_status": 0, "tracking_mode": 1, "point_x": None, "point_y": None})
    assert idle is not None and not idle.active and math.isnan(idle.x_norm)
    assert g.tracking({"tracking_status": 1, "tracking_mode": 1, "point_x": 1.5, "point_y": 0.5}) is None
    assert g.tracking({"tracking_status": 1, "tracking_mode": 1, "point_x": math.nan, "point_y": 0.5}) is None
    assert g.tracking({"tracking_status": 1}) is None
    assert g.rejected == {"tracking:point not finite or outside the image": 2, "tracking:malformed": 1}


@pytest.mark.parametrize("att_deg", [(0, 0, 0), (30, 5, 100), (-45, -10, 250), (0, 20, 10)])
def test_vehicle_renders_every_pixel_the_estimator_samples(gsoe_config, camera, att_deg):
    """The vehicle renders only a region around the nadir: it must contain the estimator's own sampling region."""
    from gsoe.cycle import GsoeEstimator
    from gsoe.rotation import R_nb_from_euler
    from sim.mavlink_vehicle import ROI_MARGIN_PX, BellyCamera, nadir_roi

    belly = BellyCamera("forest_road", 0, 0.0, 0.0, np.random.default_rng(0))
    R_nb = R_nb_from_euler(*np.deg2rad(att_deg))
    need = GsoeEstimator(gsoe_config, camera).raw_roi(R_nb, 0)
    have = nadir_roi(camera, R_nb, belly.half_angle_rad, ROI_MARGIN_PX)
    assert need is not None and have is not None
    assert have[0] <= need[0] and have[1] <= need[1] and have[2] >= need[2] and have[3] >= need[3], (have, need)


def test_vehicle_flags_every_invalid_value_it_receives():
    from sim.mavlink_vehicle import received_problems

    def nv(name, value):
        return {"mavpackettype": "NAMED_VALUE_FLOAT", "name": name, "value": value}

    good = [nv("GSOE_DRIFT", -12.0), nv("GSOE_ATA", 359.9), nv("GSOE_Q", 1.0), nv("GSOE_VALID", 0.0),
            {"mavpackettype": "WIND", "direction": 270.0, "speed": 8.0, "speed_z": 0.0},
            {"mavpackettype": "VISION_SPEED_ESTIMATE", "x": 1.0, "y": 2.0, "z": 0.0,
             "covariance": [0.1, 0, 0, 0, 0.1, 0, 0, 0, 25.0]},
            {"mavpackettype": "COMMAND_LONG", "command": 43002, "param1": 1.0, "param2": 12.0, "param3": 5.0}]
    bad = [nv("GSOE_DRIFT", math.nan), nv("GSOE_DRIFT", 95.0), nv("GSOE_ATA", 360.5), nv("GSOE_Q", 1.5),
           {"mavpackettype": "WIND", "direction": 360.0, "speed": 8.0, "speed_z": 0.0},
           {"mavpackettype": "WIND", "direction": 90.0, "speed": math.inf, "speed_z": 0.0},
           {"mavpackettype": "VISION_SPEED_ESTIMATE", "x": 1.0, "y": 2.0, "z": 0.0,
            "covariance": [0.1, 1.0, 0, 1.0, 0.1, 0, 0, 0, 25.0]},
           {"mavpackettype": "VISION_SPEED_ESTIMATE", "x": 500.0, "y": 2.0, "z": 0.0, "covariance": [0.0] * 9},
           {"mavpackettype": "COMMAND_LONG", "command": 43002, "param1": 1.0, "param2": 360.0, "param3": 5.0}]
    assert all(received_problems(m) == [] for m in good)
    assert all(received_problems(m) for m in bad)
