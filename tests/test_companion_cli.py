"""The companion's command line and camera sources (issue 22).

Command line: one URL syntax for both links (:mod:`nav.urls`), each fatal setup error (a URL, the configuration, a
--set key of a table the companion does not read, the camera file, the signing key, a video at another size than
the camera file) ends ``gsoe companion`` with exit code 2 and one line naming it (no traceback); a clean stop exits
0 and the periodic status is one readable line; ``gsoe sim --list-scenarios`` and an unknown scenario's message.
Camera sources (:mod:`nav.camera_sources`): a recorded video at another resolution is refused at open, a video file
is paced at its own timestamps (or read as fast as it decodes) and finishes at its end, no GStreamer offer without
GStreamer, picamera2 (a stand-in module) opened at the calibrated size or refused."""

from __future__ import annotations

import importlib.machinery
import os
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.logio import read_log
from nav.camera_sources import (
    CameraSetupError,
    CaptureSource,
    PicameraSource,
    VideoFileSource,
    gstreamer_available,
    open_source,
    source_help,
)
from nav.companion import CameraThread, CompanionConfig
from nav.urls import ACCEPTED, LinkUrlError, parse_link_url

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable
SIZE = (800, 600)  # the default camera file's
CAMERA_FILE = ROOT / "config" / "camera" / "paper_fisheye_800x600.toml"
TIMEOUT_S = 90


# ------------------------------------------------------------------------------------------------ URLs
@pytest.mark.parametrize("url, mavsdk, pymavlink", [
    ("udpin://0.0.0.0:14540", "udpin://0.0.0.0:14540", "udpin:0.0.0.0:14540"),
    ("udpout://127.0.0.1:14550", "udpout://127.0.0.1:14550", "udpout:127.0.0.1:14550"),
    ("tcpout://localhost:5760", "tcpout://localhost:5760", "tcp:localhost:5760"),
    ("tcpin://0.0.0.0:5760", "tcpin://0.0.0.0:5760", "tcpin:0.0.0.0:5760"),
    ("serial:///dev/ttyAMA0:921600", "serial:///dev/ttyAMA0:921600", "/dev/ttyAMA0,921600"),
    ("serial:///dev/ttyUSB0", "serial:///dev/ttyUSB0:57600", "/dev/ttyUSB0,57600"),
    # pymavlink's and MAVSDK's older spellings mean the same
    ("udpin:127.0.0.1:14550", "udpin://127.0.0.1:14550", "udpin:127.0.0.1:14550"),
    ("udp://:14540", "udpin://0.0.0.0:14540", "udpin:0.0.0.0:14540"),
    ("tcp:127.0.0.1:5762", "tcpout://127.0.0.1:5762", "tcp:127.0.0.1:5762"),
])
def test_one_url_syntax_for_both_links(url, mavsdk, pymavlink):
    u = parse_link_url(url)
    assert (u.mavsdk, u.pymavlink) == (mavsdk, pymavlink)
    assert parse_link_url(u.mavsdk) == u  # the canonical form reads back the same


@pytest.mark.parametrize("url", ["", "14540", "udpin://0.0.0.0", "udpin://0.0.0.0:0", "udpin://0.0.0.0:65536",
                                 "udpin://0.0.0.0:port", "foo://a:1", "udpin://bad host:1", "serial://ttyUSB0",
                                 "serial:///dev/ttyUSB0:12", "http://example.com:80", "udpin://999.1.1.1:5"])
def test_invalid_urls_are_refused_with_the_accepted_forms(url):
    with pytest.raises(LinkUrlError) as e:
        parse_link_url(url, "--connect")
    assert str(e.value).startswith(f"--connect {url!r}: ") and ACCEPTED in str(e.value)


# ------------------------------------------------------------------------------------------------ videos
def write_video(path: Path, size: tuple[int, int], n: int, fps: float) -> Path:
    w, h = size
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    rng = np.random.default_rng(0)
    for _ in range(n):
        vw.write(rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    vw.release()
    return path


def test_a_video_at_another_resolution_is_refused_at_open(tmp_path):
    video = write_video(tmp_path / "vga.avi", (640, 480), 5, 30.0)
    for make in (lambda: VideoFileSource(str(video), SIZE, False, time.monotonic_ns),
                 lambda: CaptureSource(str(video), SIZE, 30.0, 0.0, time.monotonic_ns)):  # a device's path
        with pytest.raises(CameraSetupError, match="gives 640x480 frames, the camera file is calibrated for 800x600"):
            make()


def test_a_video_file_is_paced_at_its_own_timestamps_and_finishes(tmp_path):
    fps = 25.0
    video = write_video(tmp_path / "ok.avi", SIZE, 6, fps)
    src = open_source(str(video), SIZE, 0.0, 0.0, False, lambda: time.monotonic_ns() // 1000)
    stamps = []
    while (shot := src.read()) is not None:
        assert shot[1].shape[:2] == (SIZE[1], SIZE[0])
        stamps.append(shot[0])
    src.close()
    assert src.finished and src.why == "end of video file"
    assert len(stamps) == 6
    assert np.allclose(np.diff(stamps), 1e6 / fps, atol=1.0)  # the file's own times, not when they were read
    fast = open_source(str(video), SIZE, 0.0, 0.0, True, lambda: time.monotonic_ns() // 1000)
    n = 0
    while fast.read() is not None:
        n += 1
    assert n == 6 and fast.finished


def test_the_camera_thread_reads_a_video_file_once_and_does_not_reopen_it(tmp_path):
    video = write_video(tmp_path / "ok.avi", SIZE, 4, 50.0)
    cfg = CompanionConfig(camera_reconnect_s=0.05)
    thread = CameraThread(str(video), cfg, size_px=SIZE)
    events = []
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and "end of video file" not in events:
        thread.latest(0.05)
        while not thread.events.empty():
            events.append(thread.events.get()[1])
    thread.stop()
    assert events == ["opened", "end of video file"]
    assert thread.frames == 4


def test_no_gstreamer_offer_without_gstreamer():
    has = "GStreamer:                   YES" in cv2.getBuildInformation() or gstreamer_available()
    assert ("GStreamer" in source_help()) == has
    if not has:
        with pytest.raises(CameraSetupError, match="no GStreamer"):
            open_source("videotestsrc ! videoconvert ! appsink", SIZE, 30.0, 0.0, False, time.monotonic_ns)


class _FakeRequest:
    def __init__(self, size):
        w, h = size
        self.yuv = np.zeros((h * 3 // 2, w), np.uint8)
        self.yuv[:h] = 7

    def make_array(self, _name):
        return self.yuv

    def get_metadata(self):
        return {"SensorTimestamp": time.clock_gettime_ns(time.CLOCK_BOOTTIME) - 5_000_000}

    def release(self):
        pass


def _fake_picamera2(granted):
    class Picamera2:
        def __init__(self, index):
            self.index = index

        def create_video_configuration(self, main, controls):
            self.asked = (main, controls)
            return {"main": {**main, "size": granted or main["size"]}}

        def configure(self, _config):
            pass

        def start(self):
            pass

        def capture_request(self):
            return _FakeRequest(granted or SIZE)

        def stop(self):
            pass

        def close(self):
            pass

    mod = types.ModuleType("picamera2")
    mod.Picamera2 = Picamera2
    mod.__spec__ = importlib.machinery.ModuleSpec("picamera2", None)
    return mod


def test_picamera2_source_at_the_calibrated_size_or_a_clear_error(monkeypatch):
    monkeypatch.delitem(sys.modules, "picamera2", raising=False)
    if "picamera2" not in sys.modules and not source_help().count("picam"):
        with pytest.raises(CameraSetupError, match="needs picamera2, which is not installed"):
            open_source("picam://0", SIZE, 30.0, 0.0, False, time.monotonic_ns)
    monkeypatch.setitem(sys.modules, "picamera2", _fake_picamera2(None))
    src = open_source("picam://0", SIZE, 30.0, 0.0, False, lambda: time.monotonic_ns() // 1000)
    assert isinstance(src, PicameraSource)
    now_us = time.monotonic_ns() // 1000
    t_us, gray = src.read()
    assert gray.shape == (SIZE[1], SIZE[0]) and int(gray.max()) == 7  # the Y plane only
    assert 0 < now_us - t_us < 1_000_000  # the sensor's stamp (5 ms before the request) on the companion's clock
    src.close()
    monkeypatch.setitem(sys.modules, "picamera2", _fake_picamera2((640, 480)))
    with pytest.raises(CameraSetupError, match="gives 640x480 frames"):
        open_source("picam://0", SIZE, 30.0, 0.0, False, time.monotonic_ns)


# ------------------------------------------------------------------------------------------------ gsoe companion
def gsoe(*args: str, cwd: Path) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([PY, "-m", "cli", *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def test_each_fatal_setup_error_exits_2_with_one_line(tmp_path):
    vga = write_video(tmp_path / "vga.avi", (640, 480), 3, 30.0)
    bad_key = tmp_path / "empty.key"
    bad_key.write_bytes(b"")
    base = ["companion", "--connect", "udpin://127.0.0.1:14999", "--camera", "/nonexistent/video.avi",
            "--duration-s", "1"]
    cases = {
        "--connect": (["--connect", "udpin:localhost"], "--connect 'udpin:localhost': no port; accepted: udpin://"),
        "--gcs": (["--gcs", "udp://host:99999"], "--gcs 'udp://host:99999': port '99999' is not a number"),
        "--set table": (["--set", "replay.gnss_off_at_s=1"], "--set replay.gnss_off_at_s: the companion does not "
                                                             "read [replay]"),
        "--set value": (["--set", "companion.camera_fps=-1"], "--set companion.camera_fps: must be in [0.0, 1000.0]"),
        "--set ekf": (["--set", "ekf.nonsense=1"], "ekf.nonsense: unknown key"),
        "--config": (["--config", str(tmp_path / "missing.toml")], "missing.toml: file not found"),
        "camera file": (["--set", 'camera.file="/nonexistent/camera.toml"'], "camera.toml: file not found"),
        "signing key": (["--signing-key", str(bad_key)], "empty signing key file"),
        "video size": (["--camera", str(vga)], "gives 640x480 frames, the camera file is calibrated for 800x600"),
    }
    procs = {k: gsoe(*base, *extra, "--log-dir", str(tmp_path / f"log-{i}"), cwd=tmp_path)
             for i, (k, (extra, _)) in enumerate(cases.items())}
    for name, p in procs.items():
        try:
            out, err = p.communicate(timeout=TIMEOUT_S)
        finally:
            if p.poll() is None:
                p.kill()
        want = cases[name][1]
        assert p.returncode == 2, (name, err)
        assert "Traceback" not in err, (name, err)
        lines = [ln for ln in err.splitlines() if ln.startswith("gsoe companion:")]
        assert len(lines) == 1 and want in lines[0], (name, err)
        assert not (tmp_path / f"log-{list(cases).index(name)}").exists(), name  # refused before logging


def test_clean_stop_exits_0_with_readable_status_lines(tmp_path):
    args = ["companion", "--connect", "udpin://127.0.0.1:14998", "--camera", "/nonexistent/video.avi",
            "--set", "companion.status_s=0.5", "--log-dir", str(tmp_path / "log")]
    timed = gsoe(*args, "--duration-s", "2", cwd=tmp_path)
    stopped = gsoe(*args[:-1], str(tmp_path / "log2"), cwd=tmp_path)
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline and not (tmp_path / "log2").exists():
            time.sleep(0.1)
        time.sleep(1.5)
        stopped.send_signal(signal.SIGTERM)
        results = [p.communicate(timeout=TIMEOUT_S) for p in (timed, stopped)]
    finally:
        for p in (timed, stopped):
            if p.poll() is None:
                p.kill()
    assert timed.returncode == 0 and stopped.returncode == 0, results
    err = results[0][1]
    status = [ln.split("status: ", 1)[1] for ln in err.splitlines() if " status: " in ln]
    assert status, err
    assert status[0].startswith("link DOWN | GNSS DENIED | camera CLOSED "), status[0]
    assert "{" not in status[0]


def test_sim_lists_scenarios_and_names_them_for_an_unknown_one(tmp_path):
    listing = gsoe("sim", "--list-scenarios", cwd=tmp_path)
    unknown = gsoe("sim", "no_such_flight", "--out", str(tmp_path / "out"), cwd=tmp_path)
    out, err = listing.communicate(timeout=TIMEOUT_S)
    assert listing.returncode == 0, err
    names = [ln.split()[0] for ln in out.splitlines()]
    assert "paper_sil" in names and "gnss_outage" in names
    out, err = unknown.communicate(timeout=TIMEOUT_S)
    assert unknown.returncode == 2 and "Traceback" not in err
    assert err.strip().splitlines() == [f"gsoe sim: configuration error: no_such_flight: unknown scenario; known: "
                                        f"{', '.join(names)} (or a path to a scenario file)"]


def test_status_line_reads_as_one_line():
    from nav.companion import status_line

    before = {"frames": 300}
    s = {"connected": True, "gnss": "GNSS_OK", "camera_open": True, "frames": 450, "frames_rejected": {"frozen": 2},
         "frames_stale": 1, "steps": 440, "estimator_errors": 0, "outputs_sent": 900,
         "outputs_suppressed": {"estimate invalid": 12}, "commands": 0, "track_reports": 0,
         "telemetry_rejected": {}, "sent": {}, "send_errors": {}, "send_latency_ms": {}}
    line = status_line(s, before, 5.0)
    assert line == ("link up | GNSS OK | camera open 30.0 fps | frames 450 (rejected 2: frozen 2, stale 1) | "
                    "EKF steps 440 | estimates sent 900, withheld 12 (estimate invalid 12)")


def test_set_camera_file_is_applied(tmp_path):
    """``--set camera.file=...`` takes effect: a 640x480 video is refused against the default 800x600 camera file
    and accepted (the companion runs and stops cleanly) with a 640x480 camera file."""
    vga = write_video(tmp_path / "vga.avi", (640, 480), 30, 30.0)
    cam = tmp_path / "vga_camera.toml"
    cam.write_text(CAMERA_FILE.read_text().replace("width_px = 800", "width_px = 640")
                   .replace("height_px = 600", "height_px = 480").replace("cx_px = 400.0", "cx_px = 320.0")
                   .replace("cy_px = 300.0", "cy_px = 240.0"))
    p = gsoe("companion", "--connect", "udpin://127.0.0.1:14997", "--camera", str(vga), "--duration-s", "2",
             "--set", f'camera.file="{cam}"', "--log-dir", str(tmp_path / "log"), cwd=tmp_path)
    try:
        out, err = p.communicate(timeout=TIMEOUT_S)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err
    assert "calibrated for" not in err and "frame rejected" not in err, err
    events = read_log(tmp_path / "log" / "events.csv")
    assert "opened" in list(events["detail"]), events
