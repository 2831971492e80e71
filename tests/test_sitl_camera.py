"""The SITL camera bridge: SIM_STATE truth stamped with the autopilot's clock, rendered, served as the frame stream
the companion reads (here against a scripted autopilot on TCP; the real ArduPlane flight is
tests/test_arduplane_sitl.py)."""

from __future__ import annotations

import math
import os
import socket
import threading
import time

import numpy as np
import pytest

from nav.companion import SimFrameClient
from sim.mavlink_vehicle import FrameServer
from sim.sitl_camera import LocalFrame, SitlCamera, TruthStamper, truth_from_message, truth_state

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

LAT0, LON0, GROUND = -35.3632621, 149.1652370, 584.09


def sim_state(lat: float, lon: float, alt: float, roll: float = 0.0, yaw: float = 0.3,
              vel: tuple[float, float, float] = (20.0, 5.0, 0.0)) -> dict:
    return {"mavpackettype": "SIM_STATE", "q1": 1.0, "q2": 0.0, "q3": 0.0, "q4": 0.0, "roll": roll, "pitch": 0.02,
            "yaw": yaw, "xacc": 0.0, "yacc": 0.0, "zacc": -9.8, "xgyro": 0.0, "ygyro": 0.0, "zgyro": 0.05,
            "lat": float(np.float32(lat)), "lon": float(np.float32(lon)), "alt": alt, "std_dev_horz": 0.0,
            "std_dev_vert": 0.0, "vn": vel[0], "ve": vel[1], "vd": vel[2], "lat_int": round(lat * 1e7),
            "lon_int": round(lon * 1e7)}


def test_truth_uses_the_integer_position_and_a_local_ground_frame():
    """SIM_STATE's float latitude holds about a metre; lat_int/lon_int a centimetre: the frame uses those."""
    lat = LAT0 + math.degrees(37.25 / 6371008.8)
    s = truth_from_message(sim_state(lat, LON0, GROUND + 100.0), 123_000_000)
    assert s is not None and s.t_us == 123_000_000
    frame = LocalFrame(LAT0, LON0, GROUND)
    n, e, d = frame.ned(s.lat_deg, s.lon_deg, s.alt_m)
    assert n == pytest.approx(37.25, abs=0.02) and e == pytest.approx(0.0, abs=0.02) and d == pytest.approx(-100.0)
    tr = truth_state(s, frame)
    assert tr.height_agl_m == pytest.approx(100.0) and tr.yaw_rad == pytest.approx(0.3)
    # on the runway the camera stays just above the ground plane (the renderer needs it above)
    assert truth_state(truth_from_message(sim_state(LAT0, LON0, GROUND - 0.05), 1), frame).pos_ned_m[2] < 0.0
    # SIMSTATE (ArduPilot's dialect) has no altitude and no velocity
    ss = {"mavpackettype": "SIMSTATE", "roll": 0.0, "pitch": 0.0, "yaw": 1.0, "xacc": 0.0, "yacc": 0.0,
          "zacc": -9.8, "xgyro": 0.0, "ygyro": 0.0, "zgyro": 0.0, "lat": round(LAT0 * 1e7), "lng": round(LON0 * 1e7)}
    s2 = truth_from_message(ss, 5)
    assert s2 is not None and math.isnan(s2.alt_m) and np.all(np.isnan(s2.vel_ned_m_s))
    assert truth_from_message({**sim_state(LAT0, LON0, GROUND), "roll": math.nan}, 1) is None


def test_truth_is_stamped_with_the_attitude_of_the_same_loop():
    st = TruthStamper()
    assert st.stamp() is None  # no ATTITUDE yet
    st.attitude(61_184)
    assert st.stamp() == 61_184_000
    assert st.stamp() is None  # a second truth sample for the same ATTITUDE is not paired
    st.attitude(61_209)
    assert st.stamp() == 61_209_000 and st.unpaired == 2


class ScriptedSitl:
    """A TCP 'SITL' (pymavlink tcpin): heartbeats, accepts message intervals, streams ATTITUDE then SIM_STATE of a
    plane flying north at 20 m/s, 100 m over the ground, each loop's pair with one time_boot_ms."""

    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}", source_system=1, source_component=1,
                                               dialect="ardupilotmega")
        self.stamps_ms: list[int] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        ml = mavutil.mavlink
        t_ms = 100_000
        granted: set[int] = set()
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                if now > next_hb:
                    self.conn.mav.heartbeat_send(ml.MAV_TYPE_FIXED_WING, ml.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)
                    next_hb = now + 0.5
                while (m := self.conn.recv_match(blocking=False)) is not None:
                    if m.get_type() == "COMMAND_LONG" and m.command == ml.MAV_CMD_SET_MESSAGE_INTERVAL:
                        granted.add(int(m.param1))
                        self.conn.mav.command_ack_send(m.command, ml.MAV_RESULT_ACCEPTED)
                if {30, 108} <= granted:
                    t_ms += 25
                    n = 20.0 * (t_ms - 100_000) / 1000.0
                    lat = LAT0 + math.degrees(n / 6371008.8)
                    self.conn.mav.attitude_send(t_ms, 0.0, 0.02, 0.0, 0.0, 0.0, 0.0)
                    self.conn.mav.sim_state_send(1, 0, 0, 0, 0.0, 0.02, 0.0, 0, 0, -9.8, 0, 0, 0, float(lat),
                                                 float(LON0), GROUND + 100.0, 0, 0, 20.0, 0.0, 0.0,
                                                 round(lat * 1e7), round(LON0 * 1e7))
                    self.stamps_ms.append(t_ms)
            except OSError:
                pass  # no client yet
            time.sleep(0.025)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=5)
        self.conn.close()


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_bridge_serves_rendered_frames_on_the_autopilot_clock(gsoe_config, camera):
    port = free_tcp_port()
    sitl = ScriptedSitl(port)
    server = FrameServer(0)
    bridge = SitlCamera(f"tcp:127.0.0.1:{port}", server, frame_hz=20.0, truth_hz=40.0, ground_amsl_m=GROUND)
    th = threading.Thread(target=bridge.run, kwargs={"duration_s": 8.0}, daemon=True)
    th.start()
    try:
        client = None
        end = time.monotonic() + 8.0
        while client is None and time.monotonic() < end:
            try:
                client = SimFrameClient("127.0.0.1", server.port, 2.0)
            except OSError:
                time.sleep(0.1)
        assert client is not None
        frames = []
        while len(frames) < 8 and time.monotonic() < end:
            got = client.read()
            if got is not None:
                frames.append(got)
        client.close()
    finally:
        bridge.request_stop()
        th.join(timeout=10)
        sitl.stop()
    assert bridge.granted == {"ATTITUDE": 40.0, "SIM_STATE": 40.0}
    assert len(frames) >= 5
    stamps = [t for t, _ in frames]
    assert all(t % 1000 == 0 and t // 1000 in sitl.stamps_ms for t in stamps)  # the autopilot's time_boot_ms
    assert all(d % 50_000 == 0 for d in np.diff(stamps[1:])), np.diff(stamps)  # 20 Hz of the autopilot clock
    w, h = camera.size_px
    img = frames[-1][1]
    assert img.shape == (h, w) and img.dtype == np.uint8
    cy, cx = h // 2, w // 2
    assert img[cy - 20:cy + 20, cx - 20:cx + 20].std() > 3.0  # the ground under the plane is rendered
