"""The companion app: bad frames, SIL over MAVLink with two processes, crash-safe log under kill -9."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nav.companion import check_frame
from nav.logio import read_log

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_check_frame_rejects_bad_frames_and_accepts_good_ones(camera):
    w, h = camera.size_px
    good_gray = np.zeros((h, w), np.uint8)
    good_bgr = np.full((h, w, 3), 255, np.uint8)  # saturated is a valid frame: GSOE's quality gates judge it
    assert check_frame(good_gray, camera)[0] is not None
    gray, _ = check_frame(good_bgr, camera)
    assert gray is not None and gray.shape == (h, w)
    for bad in [None, np.zeros((h // 2, w), np.uint8), np.zeros((h, w), np.float32), np.zeros((h, w, 4), np.uint8),
                "not an image", np.zeros((h, w, 3, 1), np.uint8), np.zeros((h + 1, w, 3), np.uint8)]:
        img, why = check_frame(bad, camera)
        assert img is None and why


def start_pair(tmp_path: Path, duration_s: float, outage: str | None, frames: bool = True):
    udp = free_port(socket.SOCK_DGRAM)
    tcp = free_port(socket.SOCK_STREAM)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    veh_cmd = [PY, "-m", "sim.mavlink_vehicle", "--connect", f"udpout:127.0.0.1:{udp}", "--duration-s",
               str(duration_s + 8), "--wind-ned-m-s", "0,8", "--summary", str(tmp_path / "vehicle.json"),
               "--frame-hz", "15"]
    if frames:
        veh_cmd += ["--frame-port", str(tcp)]
    if outage:
        veh_cmd += ["--gnss-outage-s", outage]
    veh = subprocess.Popen(veh_cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                           stderr=open(tmp_path / "vehicle.log", "w"))
    time.sleep(1.5)
    camera = f"sim://127.0.0.1:{tcp}" if frames else "/nonexistent/video.avi"
    comp = subprocess.Popen([PY, "-m", "nav.cli", "companion", "--connect", f"udpin://127.0.0.1:{udp}", "--camera",
                             camera, "--log-dir", str(tmp_path / "log"), "--duration-s", str(duration_s)],
                            cwd=ROOT, env=env, stdout=open(tmp_path / "companion.out", "w"),
                            stderr=open(tmp_path / "companion.log", "w"))
    return veh, comp


def test_sil_over_mavlink_two_processes(tmp_path):
    veh, comp = start_pair(tmp_path, 18.0, outage="11,1000")
    try:
        assert comp.wait(timeout=60) == 0, (tmp_path / "companion.log").read_text()[-3000:]
        veh.send_signal(signal.SIGINT)
        veh.wait(timeout=20)
    finally:
        for p in (comp, veh):
            if p.poll() is None:
                p.kill()
    summary = json.loads((tmp_path / "vehicle.json").read_text())
    got = summary["received"]
    # outputs reached the vehicle through MAVSDK
    for kind in ("NAMED_VALUE_FLOAT", "VISION_SPEED_ESTIMATE", "WIND_COV", "WIND", "STATUSTEXT"):
        assert got.get(kind, 0) > 0, (kind, got)
    for name, value in summary["named_values"].items():
        assert math.isfinite(value), name
    last = summary["last"]
    vse = last["VISION_SPEED_ESTIMATE"]
    assert all(math.isfinite(v) for v in [vse["x"], vse["y"], vse["z"], *vse["covariance"]])
    # the wind estimated while GNSS was available: the vehicle flies in 8 m/s from the west
    assert last["WIND"]["speed"] == pytest.approx(8.0, abs=2.0)
    assert abs(((last["WIND"]["direction"] - 270.0) + 180.0) % 360.0 - 180.0) < 20.0
    log_dir = tmp_path / "log"
    states = read_log(log_dir / "gnss_state.csv")
    assert "GNSS_OK" in list(states["name"]) and states["name"][-1] == "GNSS_DENIED"
    t_denied = states["t_us"][-1]
    out = read_log(log_dir / "outputs.csv")
    sent = out["sent"] == 1
    assert sent.sum() > 10
    # never a NaN sent; nothing sent without a reason recorded when suppressed
    for col in ("drift_rad", "ata_rad", "vel_n_m_s", "vel_e_m_s", "wind_n_m_s", "wind_e_m_s"):
        assert np.all(np.isfinite(out[col][sent])), col
    assert all(r for r in out["reason"][~sent])
    # the frames reached the companion and were processed
    status = json.loads((tmp_path / "companion.out").read_text())
    assert status["frames"] > 50 and summary["frames_sent"] > 50
    assert status["connected"] is True
    assert np.any(out["t_us"] > t_denied)


def test_log_survives_kill_9_losing_at_most_one_second(tmp_path):
    veh, comp = start_pair(tmp_path, 60.0, outage=None, frames=False)
    try:
        log_dir = tmp_path / "log"
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (log_dir / "attitude.csv").exists():
            time.sleep(0.2)
        time.sleep(3.0)
        kill_us = time.monotonic_ns() // 1000
        comp.send_signal(signal.SIGKILL)
        comp.wait(timeout=10)
    finally:
        for p in (comp, veh):
            if p.poll() is None:
                p.kill()
    att = read_log(tmp_path / "log" / "attitude.csv")
    assert len(att["t_us"]) > 50
    lost_s = (kill_us - att["t_us"][-1]) / 1e6
    assert lost_s <= 1.0, f"last logged attitude {lost_s:.2f} s before kill -9"
    assert np.all(np.diff(att["t_us"]) > 0)
