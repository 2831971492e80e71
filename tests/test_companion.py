"""The companion app: bad frames, a fuzz of 10^4 random frames and telemetry samples through the pipeline, and the
crash-safe log under kill -9.  (The SIL over MAVLink with two processes is tests/test_companion_e2e.py, the faults
injected by the vehicle are tests/test_companion_faults.py.)"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from common.logio import read_log
from nav.companion import check_frame

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
    comp = subprocess.Popen([PY, "-m", "cli", "companion", "--connect", f"udpin://127.0.0.1:{udp}", "--camera",
                             camera, "--log-dir", str(tmp_path / "log"), "--duration-s", str(duration_s)],
                            cwd=ROOT, env=env, stdout=open(tmp_path / "companion.out", "w"),
                            stderr=open(tmp_path / "companion.log", "w"))
    return veh, comp


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


# ------------------------------------------------------------------------------------------------ fuzz
FUZZ_FRAMES = 10_000
FUZZ_TELEMETRY = 10_000
FRAME_DT_US = 33_333
CLOCK_OFFSET_US = 5_000_000
BAD_FLOATS = (math.nan, math.inf, -math.inf, 1e30, -1e30, -1.0, 0.0, 1e6)


def _bad_float(rng: np.random.Generator, good: float) -> float:
    return good if rng.random() < 0.4 else float(BAD_FLOATS[int(rng.integers(len(BAD_FLOATS)))]) * (
        1.0 if rng.random() < 0.5 else rng.normal(0.0, 100.0))


def _fuzz_frame(rng: np.random.Generator, real, last, camera):
    """A random bad frame; ``real()`` renders a good one (for corrupting), ``last`` is the previous frame."""
    w, h = camera.size_px
    k = int(rng.integers(10))
    if k == 0:
        return None
    if k == 1:
        return rng.integers(0, 256, (h, w), dtype=np.uint8)
    if k == 2:
        return np.zeros((h, w), np.uint8)
    if k == 3:
        return np.full((h, w, 3), 255, np.uint8)
    if k == 4:
        return rng.integers(0, 256, (int(rng.integers(1, 2 * h)), int(rng.integers(1, 2 * w))), dtype=np.uint8)
    if k == 5:
        return rng.random((h, w)).astype(np.float32)
    if k == 6 and last is not None:
        return last  # frozen
    if k == 7:
        out = real()
        r0 = int(rng.integers(0, h - 32))
        out[r0:r0 + 32] = rng.integers(0, 256, (32, w), dtype=np.uint8)
        return out
    if k == 8:
        return "garbage"
    return rng.integers(0, 256, (h, w, int(rng.integers(2, 5))), dtype=np.uint8)


def test_fuzz_10k_frames_and_telemetry_samples_never_crash_nor_send_invalid_values(gsoe_config, camera):
    """A flight over textured ground (GNSS, then GNSS lost) with 10^4 random frames (noise, black, saturated, wrong
    size/type/channels, frozen, corrupted, None) and 10^4 random telemetry samples (NaN, infinities, out of range,
    time backwards or far ahead, malformed GNSS and tracker reports) mixed into it: no exception, every estimate
    that passes the link's gate encodes to finite in-range MAVLink values (checked by the vehicle's own validator),
    and after the fuzz the estimate is valid again."""
    from nav.companion import CompanionEstimator, companion_config_from_raw
    from nav.guidance import TargetGuidance, change_heading_command_fields, forward_camera
    from nav.link import (
        TelemetryGuard,
        TrackReading,
        check_estimate,
        encode_outputs,
        status_values,
    )
    from nav.tracker import ExternalTracker
    from pipeline.config import load_gsoe_config
    from sim.mavlink_vehicle import BellyCamera, KinematicPlant, VehicleConfig, isa_pressure_hpa, received_problems

    rng = np.random.default_rng(2024)
    _, raw = load_gsoe_config()
    cfg = companion_config_from_raw(raw)
    now = [0]
    guard = TelemetryGuard(cfg.link, clock=lambda: now[0])
    est = CompanionEstimator(gsoe_config, camera, raw, cfg)
    fwd = forward_camera(camera, math.radians(10.0))
    tracker = ExternalTracker(fwd.size_px, 0.5)
    guidance = TargetGuidance(fwd, cfg.guidance)
    vcfg = VehicleConfig(start_yaw_deg=30.0, wind_ned_m_s=(0.0, 8.0), rates_hz={
        "IMU": 50.0, "ATTITUDE": 50.0, "VFR_HUD": 10.0, "SCALED_PRESSURE": 10.0, "GPS_RAW_INT": 5.0, "FRAME": 30.0})
    plant = KinematicPlant(vcfg, np.random.default_rng(1))
    belly = BellyCamera("forest_road", 0, 2.0, 0.0, np.random.default_rng(2))
    ref_alt = vcfg.ref_alt_amsl_m
    checked = {"sent": 0, "withheld": 0, "commands": 0}
    last_frame = None
    clean_s, gnss_until_s = 8.0, 6.0
    n_fuzz_frames = n_fuzz_tel = 0

    def feed(s) -> None:
        if s is None:
            return
        if isinstance(s, TrackReading):
            tracker.push(s.t_us, s.x_norm, s.y_norm, s.active)
        else:
            est.feed(s)

    def random_telemetry(t_us: int) -> None:
        k = int(rng.integers(8))
        vus = int(t_us + rng.choice([0, -2_000_000, -100_000, 10**9, -t_us]))
        if k == 0:
            feed(guard.attitude(_bad_float(rng, 5.0), _bad_float(rng, 2.0), _bad_float(rng, 90.0), vus))
        elif k == 1:
            g = [_bad_float(rng, 0.01) for _ in range(3)]
            a = [_bad_float(rng, -9.8) for _ in range(3)]
            feed(guard.imu(tuple(g), tuple(a), vus))  # type: ignore[arg-type]
        elif k == 2:
            feed(guard.airspeed(_bad_float(rng, 20.0)))
        elif k == 3:
            feed(guard.baro(_bad_float(rng, 950.0), vus))
        elif k == 4:
            feed(guard.home(_bad_float(rng, 588.0), _bad_float(rng, 100.0)))
        elif k == 5:
            i32 = (-2**31, 2**31)
            fields = {"fix_type": int(rng.integers(0, 7)), "satellites_visible": int(rng.integers(0, 256)),
                      "time_usec": vus, "lat": int(rng.integers(*i32)), "lon": int(rng.integers(*i32)),
                      "alt": int(rng.integers(*i32)), "vel": int(rng.integers(0, 65536)),
                      "cog": int(rng.integers(0, 65536)), "h_acc": int(rng.integers(0, 2**32))}
            if rng.random() < 0.2:
                fields.pop("lat")
            feed(guard.gps_raw_int(fields))
        elif k == 6:
            feed(guard.tracking({"tracking_status": int(rng.integers(0, 4)), "tracking_mode": int(rng.integers(0, 3)),
                                 "point_x": _bad_float(rng, 0.5), "point_y": _bad_float(rng, 0.5)}))
        else:
            feed(guard.tracking({"point_x": None}))

    def check_outputs() -> None:
        out = est.output(now[0])
        for name, v in status_values(out, False).items():
            assert received_problems({"mavpackettype": "NAMED_VALUE_FLOAT", "name": name, "value": v}) == []
        if check_estimate(out, cfg.link):
            checked["withheld"] += 1
            return
        checked["sent"] += 1
        for mname, fields in encode_outputs(out, cfg.link, {"named", "vision", "wind"}).values():
            assert received_problems({"mavpackettype": mname, **fields}) == [], (mname, fields)

    def guide(t_us: int, att) -> None:
        if att is None or not guidance.due(t_us):
            return
        res = tracker.update(t_us)
        out = est.output(now[0])
        _, cmd = guidance.step(t_us, res.xy_px if res.valid else None, att.roll_rad, att.pitch_rad, att.yaw_rad,
                               out.height_agl_m, out.drift_rad, out.drift_sigma_rad, out.valid)
        if cmd.valid:
            checked["commands"] += 1
            f = change_heading_command_fields(cmd, cfg.guidance, 1, 1)
            assert received_problems({"mavpackettype": "COMMAND_LONG", **f}) == [], f

    t_s = 0.0
    last_att = None
    fuzz_done_s = math.inf
    while t_s < fuzz_done_s + clean_s:
        tr, r = plant.step()
        t_s = tr.t_s
        now[0] = tr.t_us + CLOCK_OFFSET_US + int(rng.integers(0, 2000))
        fuzzing = clean_s < t_s and (n_fuzz_frames < FUZZ_FRAMES or n_fuzz_tel < FUZZ_TELEMETRY)
        if not fuzzing and t_s > clean_s and math.isinf(fuzz_done_s):
            fuzz_done_s = t_s
        if r.ahrs is not None:
            a = r.ahrs
            feed(guard.attitude(math.degrees(a.roll_rad), math.degrees(a.pitch_rad), math.degrees(a.yaw_rad),
                                a.t_us))
            last_att = a
        if r.imu is not None:
            feed(guard.imu(tuple(r.imu.gyro_b_rad_s), tuple(r.imu.accel_b_m_s2), r.imu.t_us))
        if r.airspeed is not None:
            feed(guard.airspeed(r.airspeed.tas_m_s))
        if r.baro is not None:
            feed(guard.baro(isa_pressure_hpa(ref_alt + r.baro.alt_m), r.baro.t_us))
            feed(guard.home(ref_alt + r.baro.alt_m, r.baro.alt_m))
        if r.gnss is not None:
            g = r.gnss
            lat = 47.397742 + math.degrees(g.pos_ned_m[0] / 6371008.8)
            lon = 8.545594 + math.degrees(g.pos_ned_m[1] / (6371008.8 * math.cos(math.radians(47.397742))))
            speed = math.hypot(g.vel_ned_m_s[0], g.vel_ned_m_s[1])
            cog = math.degrees(math.atan2(g.vel_ned_m_s[1], g.vel_ned_m_s[0])) % 360.0
            good = t_s < gnss_until_s
            feed(guard.gps_raw_int({"fix_type": 3 if good else 1, "satellites_visible": 14 if good else 0,
                                    "time_usec": g.t_us, "lat": int(lat * 1e7), "lon": int(lon * 1e7),
                                    "alt": int((ref_alt + 100.0) * 1000), "vel": int(speed * 100),
                                    "cog": int(cog * 100) % 36000, "h_acc": 1500, "v_acc": 2000, "vel_acc": 150}))
        if fuzzing:
            for _ in range(int(rng.integers(0, 3))):
                if n_fuzz_tel < FUZZ_TELEMETRY:
                    random_telemetry(tr.t_us)
                    n_fuzz_tel += 1
        if r.frame is None:
            continue
        guide(now[0], last_att)
        if fuzzing and n_fuzz_frames < FUZZ_FRAMES and rng.random() < 0.85:
            n_fuzz_frames += 1
            frame = _fuzz_frame(rng, lambda tr=tr: belly.render(tr), last_frame, camera)
        else:
            frame = belly.render(tr)
        last_frame = frame if isinstance(frame, np.ndarray) else last_frame
        gray, _ = check_frame(frame, camera)
        t_frame = r.frame.t_us + CLOCK_OFFSET_US + int(rng.choice([0, 0, 0, -10**6, 10**6])) if fuzzing else \
            r.frame.t_us + CLOCK_OFFSET_US
        if gray is not None:
            est.pipe.on_frame(t_frame, gray)
        est.tick(now[0])
        check_outputs()
    assert n_fuzz_frames == FUZZ_FRAMES and n_fuzz_tel == FUZZ_TELEMETRY
    assert sum(guard.rejected.values()) > 1000  # the guard refused the impossible values ...
    assert checked["sent"] > 300 and checked["withheld"] > 100  # ... and both branches of the gate were exercised
    final = est.output(now[0])
    assert check_estimate(final, cfg.link) == "", final.reason  # valid again after the fuzz
    assert est.quality > 0.8


def test_optical_quality_falls_to_zero_over_featureless_ground(gsoe_config, camera):
    """Over textured ground the matches are valid; over flat ground no cycle runs, and the quality the ground
    station sees falls to 0 instead of keeping the last textured value."""
    from nav.companion import CompanionEstimator, companion_config_from_raw
    from pipeline.config import load_gsoe_config
    from tests.still_camera import still_frames

    raw = load_gsoe_config()[1]
    est = CompanionEstimator(gsoe_config, camera, raw, companion_config_from_raw(raw))
    w, h = camera.size_px
    textured = np.random.default_rng(5).integers(0, 256, (h, w), dtype=np.uint8)
    flat = np.full((h, w), 90, np.uint8)
    for k, t_us, samples in still_frames(90):   # level and still: the same textured view, a perfect match
        for att, imu in samples:
            est.feed(att)
            est.feed(imu)
        est.pipe.on_frame(t_us, textured if k < 45 else flat)
        if k == 44:
            assert est.quality > 0.9
    assert est.pipe.gsoe.featureless and est.quality == 0.0
