"""The companion in the SIL over MAVLink: the per-frame benchmark and the closed-loop guidance figure.

``python -m nav.bench_companion perf [--seconds 40] [--frame-hz 30]``
    Starts the simulated vehicle (:mod:`sim.mavlink_vehicle`: JSBSim, the scenario's sensor models, belly-camera
    frames rendered in its own process, GNSS lost after ``--outage-after-s`` so the estimate is optical) pinned to
    one core, and runs the companion (real optical estimator + EKF + link) in this process pinned to another core,
    against it over MAVLink on 127.0.0.1.  Prints the per-frame latency from frame capture (the frame read from
    the camera stream) to outputs sent (the MAVSDK send of the velocity message completed), median and 95th
    percentile, and to outputs handed to the link; the companion's CPU use (user + system time over wall time,
    all its threads: MAVSDK, camera reader, estimators) as a fraction of its one core; its peak resident memory.

``python -m nav.bench_companion guidance [--start-m 2300] [--outage-range-m 2000]``
    The closed-loop video-tracking guidance figure of issue 5 over the real stack: a target on the ground, the
    JSBSim aircraft at 100 m AGL and 20 m/s TAS in an 8 m/s crosswind, GNSS denied from 2 km out; the target's
    pixel comes from the vehicle's tracking-camera hook (a forward camera, see :mod:`sim.mavlink_vehicle`), the
    drift from the companion's EKF.  Flies it twice, with drift correction (``heading = course - drift``) and
    without (nose on the target), and prints the miss distance at overflight (closest horizontal approach) of each.

:func:`sil_flight` runs one such flight with the vehicle and the companion as separate processes (the SIL tests
use it).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from common.hostref import describe, host_reference
from common.procs import STOP_GRACE_S, SilFlight, free_port, sil_results, stop_process

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable
VEHICLE_START_S = 1.0      # head start of the vehicle process before the companion starts
TRACKING_SETTINGS = ('companion.tracking.source="mavlink"', 'companion.tracking.mount="forward"')

log = logging.getLogger(__name__)


def sil_flight(out_dir: Path, *, duration_s: float, vehicle_args: Sequence[str] = (),
               companion_settings: Sequence[str] = (), frames: bool = True, stop_after_pass: bool = False,
               cpu: tuple[int | None, int | None] = (None, None)) -> SilFlight:
    """Run the vehicle (``python -m sim.mavlink_vehicle``) and the companion (``python -m cli companion``) as two
    processes on random free ports of 127.0.0.1 (MAVLink: companion ``udpin``, vehicle ``udpout``; frames: TCP)
    for at most ``duration_s`` of vehicle time; returns both sides' results.  ``cpu`` pins (vehicle, companion) to
    one core each when given."""
    out_dir.mkdir(parents=True, exist_ok=True)
    udp, tcp = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    veh_cmd = [PY, "-m", "sim.mavlink_vehicle", "--connect", f"udpout:127.0.0.1:{udp}", "--duration-s",
               str(duration_s), "--summary", str(out_dir / "vehicle.json"), *vehicle_args]
    if frames:
        veh_cmd += ["--frame-port", str(tcp)]
    if stop_after_pass:
        veh_cmd += ["--stop-after-pass"]
    comp_cmd = [PY, "-m", "cli", "companion", "--connect", f"udpin://127.0.0.1:{udp}", "--camera",
                f"sim://127.0.0.1:{tcp}" if frames else "/nonexistent/video.avi", "--log-dir", str(out_dir / "log")]
    for s in companion_settings:
        comp_cmd += ["--set", s]
    with open(out_dir / "vehicle.log", "w") as vlog, open(out_dir / "companion.log", "w") as clog, \
            open(out_dir / "companion.out", "w") as cout:
        veh = subprocess.Popen(veh_cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=vlog)
        comp: subprocess.Popen[bytes] | None = None
        try:
            if cpu[0] is not None:
                os.sched_setaffinity(veh.pid, {cpu[0]})
            time.sleep(VEHICLE_START_S)
            comp = subprocess.Popen(comp_cmd, cwd=ROOT, env=env, stdout=cout, stderr=clog)
            if cpu[1] is not None:
                os.sched_setaffinity(comp.pid, {cpu[1]})
            try:
                veh.wait(timeout=duration_s + 60.0)
            except subprocess.TimeoutExpired:
                log.warning("vehicle did not finish in time")
        finally:
            if comp is not None:
                stop_process(comp)
            stop_process(veh)
    return SilFlight(*sil_results(out_dir, comp), out_dir)


def guidance_vehicle_args(start_m: float, outage_range_m: float, wind_e_m_s: float = 8.0,
                          seed: int = 0) -> list[str]:
    """The guidance scenario: start ``start_m`` south of the target (offset 80 m west), heading north, 100 m AGL,
    20 m/s, crosswind from the west, GNSS denied from ``outage_range_m`` out."""
    return ["--dynamics", "jsbsim", "--seed", str(seed), "--tas-m-s", "20", "--height-agl-m", "100",
            f"--start-ned-m=-{start_m:.1f},-80", "--start-yaw-deg", "0", "--wind-ned-m-s", f"0,{wind_e_m_s}",
            "--target-ned-m", "0,0", "--gnss-outage-range-m", str(outage_range_m)]


def guidance_figure(out_dir: Path, start_m: float = 2300.0, outage_range_m: float = 2000.0,
                    seed: int = 0) -> dict[str, Any]:
    """Fly the guidance scenario with and without drift correction; miss distances and what supports them."""
    res: dict[str, Any] = {}
    duration = start_m / 15.0 + 30.0
    for name, correct in (("corrected", True), ("uncorrected", False)):
        f = sil_flight(out_dir / name, duration_s=duration,
                       vehicle_args=guidance_vehicle_args(start_m, outage_range_m, seed=seed),
                       companion_settings=[*TRACKING_SETTINGS,
                                           f"companion.guidance.correct_drift={'true' if correct else 'false'}"],
                       stop_after_pass=True)
        v = f.vehicle
        pairs = np.array(v.get("drift_pairs", []), dtype=float).reshape(-1, 3)
        t_out = v.get("gnss_outage_start_s")
        during = pairs[pairs[:, 0] >= t_out] if t_out is not None and pairs.size else pairs[:0]
        err = np.abs((during[:, 1] - during[:, 2] + 180.0) % 360.0 - 180.0) if during.size else np.zeros(0)
        res[name] = {"miss_m": v.get("miss_m"), "passed": v.get("passed"), "outage_start_s": t_out,
                     "heading_commands": len(v.get("heading_commands", [])), "problems": v.get("problems", []),
                     "drift_err_median_deg": float(np.median(err)) if err.size else None,
                     "drift_err_p95_deg": float(np.percentile(err, 95)) if err.size else None,
                     "crashed": v.get("crashed", "")}
    return res


def perf(seconds: float, frame_hz: float, outage_after_s: float, config: str | None) -> dict[str, Any]:
    """Run the companion in this process on one core against the vehicle on another; the figures."""
    from common.configfile import apply_overrides, parse_override
    from common.logio import read_log
    from nav.companion import Companion
    from pipeline.config import load_gsoe_config

    host = host_reference()          # before the vehicle starts: the quiet host
    cores = sorted(os.sched_getaffinity(0))
    veh_core, comp_core = (cores[0], cores[1]) if len(cores) > 1 else (cores[0], cores[0])
    udp, tcp = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    veh = subprocess.Popen([PY, "-m", "sim.mavlink_vehicle", "--connect", f"udpout:127.0.0.1:{udp}", "--duration-s",
                            str(seconds + 30), "--frame-port", str(tcp), "--frame-hz", str(frame_hz),
                            "--dynamics", "jsbsim", "--wind-ned-m-s", "0,8", "--gnss-outage-s",
                            f"{outage_after_s},1e9"], cwd=ROOT, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    os.sched_setaffinity(veh.pid, {veh_core})
    os.sched_setaffinity(0, {comp_core})
    try:
        time.sleep(VEHICLE_START_S)
        gsoe_cfg, raw = load_gsoe_config(config)
        raw = apply_overrides(raw, [parse_override("companion.status_s=3600.0")])
        with tempfile.TemporaryDirectory() as tmp:
            app = Companion(f"udpin://127.0.0.1:{udp}", f"sim://127.0.0.1:{tcp}", gsoe_cfg, raw, tmp)
            timer = threading.Timer(seconds + 20.0, app.request_stop)
            timer.start()
            r0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
            status = app.run(seconds)
            r1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
            timer.cancel()
            out = read_log(Path(tmp) / "outputs.csv")
            send_lat = np.asarray(app.link.stats.send_latency_us.get("vision", []), dtype=float) / 1000.0
    finally:
        veh.send_signal(signal.SIGINT)
        veh.wait(timeout=STOP_GRACE_S)
    sent = np.asarray(out.get("sent", []), dtype=float) > 0.5
    hand_ms = np.asarray(out.get("latency_us", []), dtype=float)[sent] / 1000.0
    wall = w1 - w0
    cpu = (r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime) / wall
    return {"wall_s": wall, "frames": status["frames"], "frame_rate_hz": status["frames"] / wall,
            "steps": status["steps"], "outputs_sent": status["outputs_sent"],
            "outputs_suppressed": status["outputs_suppressed"],
            "latency_sent_ms": _stats(send_lat), "latency_handed_ms": _stats(hand_ms),
            "cpu_one_core_frac": cpu, "peak_rss_mb": r1.ru_maxrss / 1024.0, "companion_core": comp_core,
            "vehicle_core": veh_core, "host": host}


def _stats(a: np.ndarray) -> dict[str, float]:
    if not a.size:
        return {"n": 0}
    return {"n": int(a.size), "median": float(np.median(a)), "p95": float(np.percentile(a, 95)),
            "max": float(np.max(a))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    p = sub.add_parser("perf", help="latency, CPU and memory at the frame rate")
    p.add_argument("--seconds", type=float, default=40.0)
    p.add_argument("--frame-hz", type=float, default=30.0)
    p.add_argument("--outage-after-s", type=float, default=15.0, help="GNSS lost from this vehicle time on")
    p.add_argument("--config", help="configuration file (default: config/default.toml)")
    g = sub.add_parser("guidance", help="closed-loop miss distance with and without drift correction")
    g.add_argument("--start-m", type=float, default=2300.0)
    g.add_argument("--outage-range-m", type=float, default=2000.0)
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--out", help="folder for the runs' logs (default: a temporary folder)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.what == "perf":
        r = perf(args.seconds, args.frame_hz, args.outage_after_s, args.config)
        hs, ls = r["latency_handed_ms"], r["latency_sent_ms"]
        print(f"frames processed: {r['frames']} in {r['wall_s']:.1f} s ({r['frame_rate_hz']:.1f} Hz), optical steps: "
              f"{r['steps']}, estimates sent: {r['outputs_sent']}, withheld: {r['outputs_suppressed']}")
        if ls.get("n"):
            print(f"latency capture -> velocity message sent: median {ls['median']:.2f} ms, "
                  f"p95 {ls['p95']:.2f} ms, max {ls['max']:.2f} ms ({ls['n']} sends)")
        if hs.get("n"):
            print(f"latency capture -> outputs handed to the link: median {hs['median']:.2f} ms, "
                  f"p95 {hs['p95']:.2f} ms, max {hs['max']:.2f} ms")
        print(f"CPU: {100 * r['cpu_one_core_frac']:.1f} % of one core (core {r['companion_core']}, all companion "
              f"threads; vehicle on core {r['vehicle_core']})")
        print(f"peak RSS: {r['peak_rss_mb']:.1f} MB")
        print(describe(r["host"]))
        return 0
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="gsoe-guidance-"))
    res = guidance_figure(out, args.start_m, args.outage_range_m, args.seed)
    print(json.dumps(res, indent=1))
    c, u = res["corrected"]["miss_m"], res["uncorrected"]["miss_m"]
    if c is not None and u is not None:
        print(f"miss distance at overflight: with drift correction {c:.2f} m, without {u:.2f} m "
              f"(ratio {u / max(c, 1e-9):.1f}); logs in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
