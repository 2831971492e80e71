"""Hostile MAVLink traffic against the companion (issue 23): seeded bursts of mixed packets on 127.0.0.1, what the
companion then sends, and how fast its estimate is valid again.

A fuzz flight runs the simulated vehicle (:mod:`sim.mavlink_vehicle`, the kinematic plane with rendered belly-camera
frames, a steady crosswind) and the companion (``python -m cli companion``) as two processes, as the SIL tests do,
and a :class:`HostileStation` in the calling process.  The vehicle forwards its telemetry and everything the
companion sends it to the station (its ``--gcs`` port, as an autopilot routes MAVLink to a ground station); the
station injects its bursts straight into the companion's MAVLink port from a socket of its own.  A burst is
``n_packets`` spread evenly over ``[start_s, end_s)`` of the vehicle's clock, drawn from a generator seeded with
the burst's seed, in this mix (:data:`MIX`):

``random_bytes``
    1-279 random bytes, half of them starting with the MAVLink 2 start byte 0xFD.
``truncated``
    a genuine packet of the vehicle (the newest of a random telemetry type) cut short at a random length.
``bit_flipped``
    a genuine packet with 1-4 random bits flipped (its checksum fails unless a flip hits it just so).
``random_message``
    a well-formed message of a random type of the ``ardupilotmega`` dialect with random field values (NaN, inf,
    extremes; :func:`sim.mavlink_vehicle.random_mavlink_message`), from the autopilot's system and component.
``spoofed_imu``
    SCALED_IMU from the autopilot's ids, stamped with the vehicle's current time, with an in-range but impossible
    value: the issue's 15.3 g and 30 rad/s on every axis, or a random specific force up to 15 g and rates up to
    30 rad/s.
``spoofed_attitude``
    ATTITUDE from the autopilot's ids at the vehicle's current time with roll, pitch or yaw jumped by 0.2-1.5 rad.
``foreign_sender``
    a genuine telemetry message re-sent from another system or component (1/200, 2/1, 255/190), its values
    shifted: what link hygiene must refuse.

What is measured, on the vehicle's clock (the station reads it from the forwarded ATTITUDE): every
VISION_SPEED_ESTIMATE the companion sent (it sends one only for a valid estimate) with its stated covariance against
the truth's ground velocity (the vehicle's GLOBAL_POSITION_INT), and the ``GSOE_VALID`` status value.  A burst's
recovery time is how long after its end ``GSOE_VALID`` reports 0 for the last time before the next burst (0 when it
never did); ``None`` when it never came back.

``python -m sim.fuzz --seeds 20 [--packets 10000] [--out DIR]`` flies the seeds in flights of five bursts each and
prints each burst's recovery time, their distribution, and the largest velocity error sent as valid with its
stated sigma.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import select
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.logio import claim_run_folder
from common.procs import SilFlight, free_port, sil_results, stop_process

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402  (MAVLINK20 must be set before import)

from sim.mavlink_vehicle import random_mavlink_message  # noqa: E402

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable
GRAVITY_M_S2 = 9.80665
AUTOPILOT_IDS = (1, 1)
COMPANION_IDS = (1, 191)
FOREIGN_IDS = ((1, 200), (2, 1), (255, 190))
#: packet kinds and their shares of a burst (module docstring)
MIX: dict[str, float] = {"random_bytes": 0.2, "truncated": 0.15, "bit_flipped": 0.15, "random_message": 0.25,
                         "spoofed_imu": 0.08, "spoofed_attitude": 0.07, "foreign_sender": 0.1}
#: genuine telemetry the station keeps the newest packet of, to truncate, flip and re-send
GENUINE_TYPES = ("ATTITUDE", "SCALED_IMU", "RAW_IMU", "GPS_RAW_INT", "VFR_HUD", "SCALED_PRESSURE",
                 "GLOBAL_POSITION_INT", "HEARTBEAT")
ISSUE_SPOOF_ACCEL_G = 15.3
ISSUE_SPOOF_GYRO_RAD_S = 30.0
TICK_S = 0.002              # the station's loop period
#: the companion's settings in a fuzz flight: the velocity as VISION_SPEED_ESTIMATE (north/east with its covariance),
#: what the station compares with the truth
FUZZ_SETTINGS = ('companion.link.velocity_message="vision_speed_estimate"',)
VEHICLE_START_S = 1.0       # the vehicle's head start before the companion


@dataclass(frozen=True)
class Burst:
    """``n_packets`` hostile packets over ``[start_s, end_s)`` of the vehicle's clock, drawn with ``seed``."""

    start_s: float
    end_s: float
    n_packets: int
    seed: int


@dataclass
class StationRecord:
    """What the station saw, on the vehicle's clock (s)."""

    sent: dict[str, int] = field(default_factory=dict)             # packets injected per kind
    velocity: list[tuple[float, float, float, float, float, float, float, float]] = field(default_factory=list)
    valid: list[tuple[float, float]] = field(default_factory=list)  # (t_s, GSOE_VALID)
    vehicle_t_s: float = 0.0


def _flip_bits(buf: bytes, rng: np.random.Generator) -> bytes:
    b = bytearray(buf)
    for _ in range(int(rng.integers(1, 5))):
        i = int(rng.integers(len(b)))
        b[i] ^= 1 << int(rng.integers(8))
    return bytes(b)


class PacketMaker:
    """The mix of :data:`MIX` from one seeded generator; ``genuine`` holds the vehicle's newest packets and
    messages by type, ``t_boot_ms`` its clock (both kept up to date by the station)."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.kinds = list(MIX)
        p = np.array([MIX[k] for k in self.kinds])
        self.p = p / p.sum()
        ml = mavutil.mavlink
        self.mav_autopilot = ml.MAVLink(None, srcSystem=AUTOPILOT_IDS[0], srcComponent=AUTOPILOT_IDS[1])
        self.mav_foreign = [ml.MAVLink(None, srcSystem=s, srcComponent=c) for s, c in FOREIGN_IDS]

    def packet(self, genuine: dict[str, tuple[bytes, Any]], t_boot_ms: int) -> tuple[str, bytes]:
        rng = self.rng
        kind = self.kinds[int(rng.choice(len(self.kinds), p=self.p))]
        if kind in ("truncated", "bit_flipped", "foreign_sender") and not genuine:
            kind = "random_bytes"
        if kind == "random_bytes":
            junk = rng.integers(0, 256, int(rng.integers(1, 280)), dtype=np.uint8).tobytes()
            return kind, (b"\xfd" + junk[1:] if rng.random() < 0.5 else junk)
        if kind in ("truncated", "bit_flipped"):
            names = sorted(genuine)
            buf = genuine[names[int(rng.integers(len(names)))]][0]
            if kind == "truncated":
                return kind, buf[:int(rng.integers(1, len(buf)))]
            return kind, _flip_bits(buf, rng)
        if kind == "random_message":
            try:
                return kind, bytes(random_mavlink_message(rng).pack(self.mav_autopilot))
            except Exception:  # a value pymavlink cannot pack: raw bytes instead
                return "random_bytes", rng.integers(0, 256, 64, dtype=np.uint8).tobytes()
        if kind == "spoofed_imu":
            return kind, self._spoofed_imu(t_boot_ms)
        if kind == "spoofed_attitude":
            att = genuine.get("ATTITUDE")
            return kind, self._spoofed_attitude(att[1] if att is not None else None, t_boot_ms)
        return kind, self._foreign(genuine)

    def _spoofed_imu(self, t_boot_ms: int) -> bytes:
        rng = self.rng
        if rng.random() < 0.5:       # the issue's packet
            acc_mg = np.full(3, int(ISSUE_SPOOF_ACCEL_G * 1000))
            gyro_mrad = np.full(3, int(ISSUE_SPOOF_GYRO_RAD_S * 1000))
        else:
            acc_mg = rng.integers(-15_000, 15_001, 3)
            gyro_mrad = rng.integers(-30_000, 30_001, 3)
        msg = mavutil.mavlink.MAVLink_scaled_imu_message(t_boot_ms, *acc_mg.tolist(), *gyro_mrad.tolist(), 0, 0, 0)
        return bytes(msg.pack(self.mav_autopilot))

    def _spoofed_attitude(self, att: Any, t_boot_ms: int) -> bytes:
        rng = self.rng
        r, p, y = (float(att.roll), float(att.pitch), float(att.yaw)) if att is not None else (0.0, 0.0, 0.0)
        jump = float(rng.uniform(0.2, 1.5)) * (1.0 if rng.random() < 0.5 else -1.0)
        axis = int(rng.integers(3))
        r, p, y = (r + jump * (axis == 0), float(np.clip(p + jump * (axis == 1), -1.5, 1.5)),
                   math.remainder(y + jump * (axis == 2), 2 * math.pi))
        msg = mavutil.mavlink.MAVLink_attitude_message(t_boot_ms, r, p, y, 0.0, 0.0, 0.0)
        return bytes(msg.pack(self.mav_autopilot))

    def _foreign(self, genuine: dict[str, tuple[bytes, Any]]) -> bytes:
        rng = self.rng
        names = [n for n in ("ATTITUDE", "SCALED_IMU", "GPS_RAW_INT", "VFR_HUD") if n in genuine]
        msg = genuine[names[int(rng.integers(len(names)))]][1] if names else None
        mav = self.mav_foreign[int(rng.integers(len(self.mav_foreign)))]
        if msg is None:
            return bytes(mavutil.mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(mav))
        d = msg.to_dict()
        d.pop("mavpackettype", None)
        if "lat" in d:
            d["lat"] += 27_000                       # ~300 m north
        for k in ("roll", "xacc", "airspeed"):
            if k in d:
                d[k] = d[k] + (0.5 if k == "roll" else 5000 if k == "xacc" else 10.0)
        new = type(msg)(**d)
        return bytes(new.pack(mav))


class HostileStation:
    """The ground-station side of a fuzz flight (module docstring): reads the vehicle's forwarded stream on
    ``listen_port`` and injects the bursts into the companion's ``target_port``; run it in a thread with
    :meth:`run` until :meth:`stop`."""

    def __init__(self, listen_port: int, target_port: int, bursts: Sequence[Burst]) -> None:
        self.rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.rx.bind(("127.0.0.1", listen_port))
        self.rx.setblocking(False)
        self.tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.tx.bind(("127.0.0.1", 0))
        self.target = ("127.0.0.1", target_port)
        self.bursts = sorted(bursts, key=lambda b: b.start_s)
        self.makers = [PacketMaker(np.random.default_rng(b.seed)) for b in self.bursts]
        self.done = [0] * len(self.bursts)
        self.rec = StationRecord()
        self._parser = mavutil.mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._genuine: dict[str, tuple[bytes, Any]] = {}
        self._truth_vel: tuple[float, float] | None = None
        self._t_boot_ms = 0
        self._stop = threading.Event()
        self.errors: deque[str] = deque(maxlen=20)

    def stop(self) -> None:
        self._stop.set()

    def run(self) -> None:
        try:
            while not self._stop.is_set():
                select.select([self.rx], [], [], TICK_S)
                self._receive()
                self._inject()
        finally:
            self.rx.close()
            self.tx.close()

    def _receive(self) -> None:
        while True:
            try:
                data = self.rx.recv(65536)
            except (BlockingIOError, OSError):
                return
            try:
                msgs = self._parser.parse_buffer(data) or []
            except Exception as e:  # noqa: BLE001 - the vehicle's stream is ours; note and go on
                self.errors.append(str(e))
                continue
            for m in msgs:
                self._seen(m)

    def _seen(self, m: Any) -> None:
        kind = m.get_type()
        src = (m.get_srcSystem(), m.get_srcComponent())
        if src == AUTOPILOT_IDS:
            if kind in GENUINE_TYPES:
                self._genuine[kind] = (bytes(m.get_msgbuf()), m)
            if kind == "ATTITUDE":
                self._t_boot_ms = int(m.time_boot_ms)
                self.rec.vehicle_t_s = self._t_boot_ms / 1000.0
            elif kind == "GLOBAL_POSITION_INT":
                self._truth_vel = (m.vx / 100.0, m.vy / 100.0)
        elif src == COMPANION_IDS:
            t = self.rec.vehicle_t_s
            if kind == "VISION_SPEED_ESTIMATE" and self._truth_vel is not None:
                c = list(m.covariance)
                self.rec.velocity.append((t, float(m.x), float(m.y), c[0], c[4], c[1], *self._truth_vel))
            elif kind == "NAMED_VALUE_FLOAT" and str(m.name) == "GSOE_VALID":
                self.rec.valid.append((t, float(m.value)))

    def _inject(self) -> None:
        t = self.rec.vehicle_t_s
        for i, b in enumerate(self.bursts):
            if t < b.start_s or self.done[i] >= b.n_packets:
                continue
            frac = min(1.0, (t - b.start_s) / (b.end_s - b.start_s))
            due = min(b.n_packets, int(math.ceil(frac * b.n_packets)))
            maker = self.makers[i]
            while self.done[i] < due:
                self.done[i] += 1
                kind, buf = maker.packet(self._genuine, self._t_boot_ms)
                self.rec.sent[kind] = self.rec.sent.get(kind, 0) + 1
                try:
                    self.tx.sendto(buf, self.target)
                except OSError as e:
                    self.errors.append(str(e))


# ------------------------------------------------------------------------------------------------ flights
@dataclass(frozen=True)
class FuzzFlight(SilFlight):
    """One fuzz flight's results: the SIL flight's, its bursts and what the hostile station recorded."""

    bursts: list[Burst]
    station: StationRecord

    def recovery_s(self) -> list[float | None]:
        """Per burst: seconds after its end until ``GSOE_VALID`` last left 0 (before the next burst or the end)."""
        v = np.array(self.station.valid, dtype=float).reshape(-1, 2)
        out: list[float | None] = []
        ends = [b.end_s for b in self.bursts]
        nexts = [b.start_s for b in self.bursts[1:]] + [math.inf]
        for end, nxt in zip(ends, nexts, strict=True):
            win = v[(v[:, 0] >= end) & (v[:, 0] < nxt)]
            if not win.size:
                out.append(None)
                continue
            zeros = np.flatnonzero(win[:, 1] < 0.5)
            if not zeros.size:
                out.append(0.0)
            elif zeros[-1] == len(win) - 1:
                out.append(None)                         # invalid to the end of the window: never came back
            else:
                out.append(float(win[zeros[-1] + 1, 0] - end))
        return out

    def velocity_errors(self) -> NDArray[np.float64]:
        """Rows (t_s, error_n, error_e, sigma_n, sigma_e, normalised error) of every VISION_SPEED_ESTIMATE sent,
        the normalised error the larger of the two axes' |error| / sigma."""
        a = np.array(self.station.velocity, dtype=float).reshape(-1, 8)
        en, ee = a[:, 1] - a[:, 6], a[:, 2] - a[:, 7]
        sn, se = np.sqrt(np.maximum(a[:, 3], 0.0)), np.sqrt(np.maximum(a[:, 4], 0.0))
        z = np.maximum(np.abs(en) / np.maximum(sn, 1e-9), np.abs(ee) / np.maximum(se, 1e-9))
        return np.column_stack([a[:, 0], en, ee, sn, se, z])



def fuzz_flight(out_dir: Path, bursts: Sequence[Burst], *, duration_s: float, vehicle_args: Sequence[str] = (),
                companion_settings: Sequence[str] = (), companion_delay_s: float = VEHICLE_START_S,
                frame_hz: float = 15.0) -> FuzzFlight:
    """Fly the vehicle for ``duration_s`` of its clock with the companion started ``companion_delay_s`` after it
    (negative: the companion first, the vehicle ``-companion_delay_s`` later) and the bursts injected; all on
    random free ports of 127.0.0.1, every process stopped by its id at the end."""
    out_dir = claim_run_folder(out_dir)
    udp, tcp, gcs = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM), free_port(socket.SOCK_DGRAM)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    veh_cmd = [PY, "-m", "sim.mavlink_vehicle", "--connect", f"udpout:127.0.0.1:{udp}", "--duration-s",
               str(duration_s), "--summary", str(out_dir / "vehicle.json"), "--gcs", f"udpout:127.0.0.1:{gcs}",
               "--frame-port", str(tcp), "--frame-hz", str(frame_hz), "--wind-ned-m-s", "0,8",
               "--start-yaw-deg", "30", *vehicle_args]
    comp_cmd = [PY, "-m", "cli", "companion", "--connect", f"udpin://127.0.0.1:{udp}", "--camera",
                f"sim://127.0.0.1:{tcp}", "--log-dir", str(out_dir / "log")]
    for s in (*FUZZ_SETTINGS, *companion_settings):
        comp_cmd += ["--set", s]
    station = HostileStation(gcs, udp, bursts)
    thread = threading.Thread(target=station.run, name="hostile-station", daemon=True)
    thread.start()
    procs: list[subprocess.Popen[bytes]] = []
    comp: subprocess.Popen[bytes] | None = None
    veh: subprocess.Popen[bytes] | None = None
    with open(out_dir / "vehicle.log", "w") as vlog, open(out_dir / "companion.log", "w") as clog, \
            open(out_dir / "companion.out", "w") as cout:
        try:
            starts: list[tuple[list[str], Any, Any]] = [(veh_cmd, vlog, None), (comp_cmd, clog, cout)]
            wait = companion_delay_s
            if companion_delay_s < 0:
                starts, wait = starts[::-1], -companion_delay_s
            for i, (cmd, err, out) in enumerate(starts):
                if i:
                    time.sleep(wait)
                p = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out or subprocess.DEVNULL, stderr=err)
                procs.append(p)
                if cmd is veh_cmd:
                    veh = p
                else:
                    comp = p
            assert veh is not None
            try:
                veh.wait(timeout=duration_s + 60.0)
            except subprocess.TimeoutExpired:
                log.warning("vehicle did not finish in time")
        finally:
            for p in reversed(procs):
                stop_process(p)
            station.stop()
            thread.join(timeout=5.0)
    (out_dir / "station.json").write_text(json.dumps({"sent": station.rec.sent, "valid": station.rec.valid,
                                                      "velocity": station.rec.velocity,
                                                      "bursts": [b.__dict__ for b in bursts],
                                                      "errors": list(station.errors)}))
    return FuzzFlight(*sil_results(out_dir, comp), out_dir, list(bursts), station.rec)


def schedule(seeds: Sequence[int], n_packets: int, *, first_s: float = 12.0, burst_s: float = 5.0,
             clean_s: float = 10.0) -> tuple[list[Burst], float]:
    """Bursts for ``seeds`` one after another (each ``burst_s`` long, ``clean_s`` of clean data after it), and the
    flight's length."""
    bursts = []
    t = first_s
    for s in seeds:
        bursts.append(Burst(t, t + burst_s, n_packets, int(s)))
        t += burst_s + clean_s
    return bursts, t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="fuzz flights: recovery times and the largest velocity error sent")
    ap.add_argument("--seeds", type=int, default=20, help="bursts, seeded 1..N")
    ap.add_argument("--packets", type=int, default=10_000, help="packets per burst")
    ap.add_argument("--per-flight", type=int, default=5, help="bursts per flight")
    ap.add_argument("--out", default="out/fuzz", help="output folder (a new one: it must hold no run's logs)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    root = claim_run_folder(Path(args.out))
    seeds = list(range(1, args.seeds + 1))
    rec: list[tuple[int, float | None]] = []
    worst: tuple[float, ...] | None = None       # the largest error in m/s
    worst_z: tuple[float, ...] | None = None     # the largest error in sigmas
    problems = 0
    for k in range(0, len(seeds), args.per_flight):
        group = seeds[k:k + args.per_flight]
        bursts, end = schedule(group, args.packets)
        f = fuzz_flight(root / f"flight_{k // args.per_flight + 1:02d}", bursts, duration_s=end)
        problems += len(f.vehicle.get("problems", []))
        for s, r in zip(group, f.recovery_s(), strict=True):
            rec.append((s, r))
            print(f"seed {s:3d}: recovery {'never' if r is None else f'{r:.2f} s'}", flush=True)
        ve = f.velocity_errors()
        if ve.size:
            i = int(np.argmax(np.hypot(ve[:, 1], ve[:, 2])))
            if worst is None or math.hypot(ve[i, 1], ve[i, 2]) > math.hypot(worst[1], worst[2]):
                worst = tuple(ve[i])
            j = int(np.argmax(ve[:, 5]))
            if worst_z is None or ve[j, 5] > worst_z[5]:
                worst_z = tuple(ve[j])
        print(f"  flight {k // args.per_flight + 1}: companion rc {f.companion_rc}, problems "
              f"{len(f.vehicle.get('problems', []))}, sent {f.station.sent}", flush=True)
    back = np.array([x for _, x in rec if x is not None], dtype=float)
    print(f"recovery over {len(rec)} seeds: never {sum(x is None for _, x in rec)}, median {np.median(back):.2f} s, "
          f"p90 {np.percentile(back, 90):.2f} s, max {back.max():.2f} s; zero (never invalid) {int(np.sum(back == 0))}")
    for what, w in (("in m/s", worst), ("in sigmas", worst_z)):
        if w is not None:
            t, en, ee, sn, se, z = w
            print(f"largest velocity error sent as valid ({what}): {math.hypot(en, ee):.2f} m/s at t={t:.1f} s "
                  f"(north {en:+.2f} sigma {sn:.2f}, east {ee:+.2f} sigma {se:.2f}; {z:.1f} sigma)")
    print(f"non-finite or out-of-range values received by the vehicle: {problems}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
