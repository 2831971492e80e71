"""Ground-station display: the state built from the companion's messages, and the MAVProxy module run headless.

The headless test starts MAVProxy (a separate process, its console on a pipe) with ``module load
nav.gcs_mavproxy``, listening where the simulated vehicle forwards its telemetry and everything the companion sends
it (as an autopilot routes MAVLink to its ground-station link); then it flies a short SIL (vehicle and companion as
processes) with a GNSS outage and a camera failure, and compares the module's state (``gsoe json``) with what the
vehicle received.
"""

from __future__ import annotations

import json
import math
import os
import queue
import socket
import subprocess
import sys
import threading
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from nav.bench_companion import ROOT, free_port, sil_flight  # noqa: E402
from nav.gcs_display import MAV_COMP_ID_ONBOARD_COMPUTER, GsoeGroundState  # noqa: E402


def _as_received(msg: mavlink.MAVLink_message, src_component: int = MAV_COMP_ID_ONBOARD_COMPUTER):
    """``msg`` packed by a sender with that component id and parsed back, as a ground station receives it."""
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=src_component)
    buf = msg.pack(sender)
    parser = mavlink.MAVLink(None)
    out = parser.parse_buffer(buf)
    assert out and len(out) == 1
    return out[0]


def _named(name: str, value: float, comp: int = MAV_COMP_ID_ONBOARD_COMPUTER):
    return _as_received(mavlink.MAVLink_named_value_float_message(0, name.encode(), value), comp)


def test_state_holds_the_values_and_the_sigmas():
    st = GsoeGroundState()
    st.update(_as_received(mavlink.MAVLink_wind_message(270.0, 8.0, 0.0)), 1.0)
    st.update(_as_received(mavlink.MAVLink_wind_cov_message(0, 0.0, 8.0, 0.0, 0.4, 5.0, 588.0, 0.3, 5.0)), 1.0)
    for name, v in (("GSOE_DRIFT", 21.5), ("GSOE_ATA", 21.5), ("GSOE_Q", 0.97), ("GSOE_GNSS", 2.0),
                    ("GSOE_VALID", 1.0)):
        st.update(_named(name, v), 1.0)
    assert (st.wind_speed_m_s, st.wind_from_deg) == (8.0, 270.0)
    assert (st.wind_n_m_s, st.wind_e_m_s) == (0.0, 8.0)
    assert st.wind_speed_sigma_m_s == pytest.approx(0.3)
    assert st.wind_from_sigma_deg == pytest.approx(math.degrees(0.4 / 8.0))  # cross-wind sigma over speed
    assert st.drift_deg == pytest.approx(21.5) and st.ata_deg == pytest.approx(21.5)
    assert st.quality == pytest.approx(0.97) and st.gnss_state == "GNSS_DENIED" and st.valid is True
    lines = st.lines()
    assert "8.0+-0.3 m/s from 270+-3 deg" in lines["GSOEWind"]
    assert "+21.5" in lines["GSOEDrift"] and "valid" in lines["GSOEState"]


def test_warns_when_the_estimate_goes_invalid_gnss_changes_or_the_companion_goes_silent():
    st = GsoeGroundState(stale_s=3.0)
    assert st.update(_named("GSOE_VALID", 1.0), 0.0) == []
    assert st.update(_named("GSOE_GNSS", 0.0), 0.0) == []
    assert st.update(_named("GSOE_GNSS", 2.0), 0.5) == ["GSOE GNSS state GNSS_OK -> GNSS_DENIED"]
    warn = st.update(_named("GSOE_VALID", 0.0), 1.0)
    assert warn and "INVALID" in warn[0] and st.valid is False
    assert st.update(_named("GSOE_VALID", 1.0), 2.0) == ["GSOE estimate valid again"]
    assert st.check(4.0) == []
    silent = st.check(5.5)
    assert silent and "silent" in silent[0] and st.stale and "STALE" in st.lines()["GSOEState"]
    assert st.check(9.0) == []  # said once
    text = mavlink.MAVLink_statustext_message(4, b"GSOE invalid: estimate invalid (drift sigma)")
    assert st.update(_as_received(text), 9.5) == ["GSOE invalid: estimate invalid (drift sigma)"]


def test_only_the_companion_component_counts_and_garbage_is_ignored():
    st = GsoeGroundState()
    st.update(_as_received(mavlink.MAVLink_wind_message(90.0, 3.0, 0.0), src_component=1), 0.0)  # autopilot's WIND
    assert math.isnan(st.wind_speed_m_s)
    st.update(_named("GSOE_DRIFT", float("nan")), 0.0)
    st.update(_as_received(mavlink.MAVLink_wind_message(float("inf"), 3.0, 0.0)), 0.0)
    assert math.isnan(st.drift_deg) and math.isnan(st.wind_speed_m_s)
    assert json.dumps(st.as_dict())  # NaN-free JSON
    any_comp = GsoeGroundState(source_component=0)
    any_comp.update(_as_received(mavlink.MAVLink_wind_message(90.0, 3.0, 0.0), src_component=1), 0.0)
    assert any_comp.wind_speed_m_s == 3.0


class _Console:
    """MAVProxy's console on pipes: send commands, read lines."""

    def __init__(self, port: int, tmp) -> None:
        pytest.importorskip("MAVProxy")
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        self.p = subprocess.Popen(
            [sys.executable, "-m", "MAVProxy.mavproxy", f"--master=udpin:127.0.0.1:{port}", "--nowait",
             f"--state-basedir={tmp}", "--default-modules=", "--cmd=module load nav.gcs_mavproxy"],
            cwd=tmp, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: queue.Queue[str] = queue.Queue()
        self.all: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.all.append(line)
            self.lines.put(line)

    def send(self, cmd: str) -> None:
        assert self.p.stdin is not None
        self.p.stdin.write(cmd + "\n")
        self.p.stdin.flush()

    def wait_for(self, prefix: str, timeout_s: float = 15.0) -> str:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                continue
            if prefix in line:
                return line
        raise AssertionError(f"MAVProxy never printed {prefix!r}: {''.join(self.all[-40:])}")

    def close(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(timeout=10)


def test_mavproxy_module_headless_holds_what_the_companion_sent(tmp_path):
    port = free_port(socket.SOCK_DGRAM)
    con = _Console(port, tmp_path)
    try:
        con.wait_for("Loaded module nav.gcs_mavproxy")
        flight = sil_flight(tmp_path / "sil", duration_s=30.0, vehicle_args=[
            "--wind-ned-m-s", "0,8", "--start-yaw-deg", "30", "--gnss-outage-s", "12,1000",
            "--fault", "camera_off:17:21", "--gcs", f"udpout:127.0.0.1:{port}"])
        con.send("gsoe json")
        state = json.loads(con.wait_for("GSOE_STATE ").split("GSOE_STATE ", 1)[1])
    finally:
        con.close()
    v = flight.vehicle
    nv = v["named_values"]
    assert state["counts"].get("WIND", 0) > 10 and state["counts"].get("NAMED_VALUE_FLOAT", 0) > 50
    # the module holds the last values the companion sent (the vehicle forwarded each message it received)
    assert state["drift_deg"] == pytest.approx(nv["GSOE_DRIFT"], abs=1e-4)
    assert state["ata_deg"] == pytest.approx(nv["GSOE_ATA"], abs=1e-3)
    assert state["quality"] == pytest.approx(nv["GSOE_Q"], abs=1e-6)
    assert state["wind_speed_m_s"] == pytest.approx(v["last"]["WIND"]["speed"], abs=1e-4)
    assert state["wind_from_deg"] == pytest.approx(v["last"]["WIND"]["direction"], abs=1e-3)
    assert state["wind_speed_sigma_m_s"] == pytest.approx(v["last"]["WIND_COV"]["horiz_accuracy"], abs=1e-4)
    assert state["gnss_state"] == "GNSS_DENIED"
    # and these are the truth's: 8 m/s from the west
    assert state["wind_speed_m_s"] == pytest.approx(8.0, abs=1.5)
    assert abs((state["wind_from_deg"] - 270.0 + 180.0) % 360.0 - 180.0) < 10.0
    # the camera failure during the GNSS outage made the estimate invalid: the module warned, then saw it recover
    warnings = state["warnings"]
    assert any("INVALID" in w for w in warnings), warnings
    assert any("valid again" in w for w in warnings), warnings
