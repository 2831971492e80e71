"""Benchmark of the companion at 30 Hz: per-frame latency (frame read to outputs handed to the link), CPU, RSS.

``python -m nav.bench_companion [--seconds 30] [--frame-hz 30]`` starts the simulated vehicle
(:mod:`sim.mavlink_vehicle`, rendering the belly camera's frames in its own process) and runs the companion in this
process against it over MAVLink on 127.0.0.1, then prints the median and 95th percentile latency from
``outputs.csv``, the companion process's CPU use (user + system time over wall time, all its threads: MAVSDK
link, camera reader, estimators) and its peak resident memory.
"""

from __future__ import annotations

import argparse
import logging
import resource
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--frame-hz", type=float, default=30.0)
    ap.add_argument("--config", help="configuration file (default: config/default.toml)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from nav.companion import Companion
    from nav.configfile import load_gsoe_config
    from nav.logio import read_log

    udp, tcp = _free_port(socket.SOCK_DGRAM), _free_port(socket.SOCK_STREAM)
    veh = subprocess.Popen([sys.executable, "-m", "sim.mavlink_vehicle", "--connect", f"udpout:127.0.0.1:{udp}",
                            "--duration-s", str(args.seconds + 15), "--frame-port", str(tcp), "--frame-hz",
                            str(args.frame_hz), "--wind-ned-m-s", "0,8"], cwd=ROOT, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    try:
        time.sleep(1.5)
        gsoe_cfg, raw = load_gsoe_config(args.config)
        with tempfile.TemporaryDirectory() as tmp:
            app = Companion(f"udpin://127.0.0.1:{udp}", f"sim://127.0.0.1:{tcp}", gsoe_cfg, raw, tmp)
            timer = threading.Timer(args.seconds + 5.0, app.request_stop)
            timer.start()
            r0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
            status = app.run(args.seconds)
            r1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
            timer.cancel()
            out = read_log(Path(tmp) / "outputs.csv")
    finally:
        veh.terminate()
        veh.wait(timeout=10)
    lat_ms = np.asarray(out.get("latency_us", []), dtype=float) / 1000.0
    cpu = (r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime) / (w1 - w0)
    print(f"frames processed: {status['frames']} in {w1 - w0:.1f} s ({status['frames'] / (w1 - w0):.1f} Hz), "
          f"optical steps: {status['steps']}, outputs sent: {status['outputs_sent']}")
    if lat_ms.size:
        print(f"latency frame read -> outputs handed to link: median {np.median(lat_ms):.2f} ms, "
              f"p95 {np.percentile(lat_ms, 95):.2f} ms, max {np.max(lat_ms):.2f} ms")
    print(f"CPU: {100 * cpu:.1f} % of one core (all companion threads)")
    print(f"peak RSS: {r1.ru_maxrss / 1024:.1f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
