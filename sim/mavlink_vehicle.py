"""The simulator acting as the vehicle: an ArduPlane-like MAVLink endpoint over UDP on 127.0.0.1 (pymavlink).

What it speaks (MAVLink 2, ``ardupilotmega`` dialect, system 1 / component 1):

=====================  =======  =========================================================================
message                rate Hz  content
=====================  =======  =========================================================================
HEARTBEAT              1        MAV_TYPE_FIXED_WING, MAV_AUTOPILOT_ARDUPILOTMEGA, custom mode GUIDED (15)
ATTITUDE               50       roll/pitch/yaw and body rates
RAW_IMU, SCALED_IMU    50       accelerometer (mG) and gyro (mrad/s), FRD; RAW_IMU carries ``time_usec``
SCALED_PRESSURE        10       static pressure (hPa, ISA at the baro altitude), airspeed differential pressure
VFR_HUD                10       airspeed, groundspeed, heading, altitude, climb
GPS_RAW_INT            5        fix type, satellites, position, velocity, accuracy (fix 1 / 0 sats in an outage)
GLOBAL_POSITION_INT    10       the autopilot's position (held from the last fix during an outage)
=====================  =======  =========================================================================

It accepts ``COMMAND_LONG`` ``MAV_CMD_GUIDED_CHANGE_HEADING`` (43002, heading type 1 = vehicle heading, param3 =
lateral acceleration limit m/s^2) in GUIDED mode and flies it (ACK ACCEPTED); other commands are acknowledged
UNSUPPORTED, as an autopilot does for what it does not implement.  Every received message is counted and the last
one of each type kept (:attr:`MavlinkVehicle.received`), so tests can check what the companion sent.

Dynamics: until the JSBSim model of :mod:`sim` is wired in, the vehicle flies :class:`KinematicPlane`, a
coordinated-turn point mass at constant airspeed and height in a steady wind (bank-limited heading hold).  It is
the vehicle for link tests and for the closed-loop guidance test, not a flight-dynamics model.

Camera frames (when a ``frame_source`` is given) are streamed over TCP on 127.0.0.1 to one client at a time, each
as a 24-byte little-endian header ``<4sqIIi``: magic ``b"GSOF"``, exposure time ``t_us`` (int64, vehicle clock =
``time_boot`` of the MAVLink messages), width, height, channels (1 gray, 3 BGR), followed by ``width * height *
channels`` bytes (uint8, row-major).  A slow client drops frames rather than stalling the vehicle.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gsoe.angles import angle_diff, wrap_2pi, wrap_pi
from sim.truth import TruthState

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402  (MAVLINK20 must be set before import)

log = logging.getLogger(__name__)

GRAVITY_M_S2 = 9.80665
EARTH_RADIUS_M = 6371008.8  # mean Earth radius: local flat-earth conversion of NED offsets to lat/lon
ISA_P0_HPA = 1013.25
ISA_T0_K = 288.15
ISA_LAPSE_K_M = 0.0065
ISA_EXP = 5.25588
AIR_DENSITY_KG_M3 = 1.225
ARDUPLANE_MODE_GUIDED = 15
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4
FRAME_MAGIC = b"GSOF"
FRAME_HEADER = struct.Struct("<4sqIIi")


@dataclass(frozen=True)
class VehicleConfig:
    """Vehicle simulation settings (units in the names)."""

    tas_m_s: float = 20.0
    height_agl_m: float = 100.0
    start_ned_m: tuple[float, float] = (0.0, 0.0)
    start_yaw_deg: float = 0.0
    wind_ned_m_s: tuple[float, float] = (0.0, 0.0)
    max_bank_deg: float = 35.0
    roll_rate_deg_s: float = 60.0
    heading_gain_1_s: float = 0.6
    ref_lat_deg: float = 47.397742
    ref_lon_deg: float = 8.545594
    ref_alt_amsl_m: float = 488.0
    dt_s: float = 0.01
    gyro_noise_rad_s: float = 0.002
    accel_noise_m_s2: float = 0.05
    gnss_pos_noise_m: float = 1.0
    gnss_vel_noise_m_s: float = 0.1
    gnss_outages_s: tuple[tuple[float, float], ...] = ()
    rates_hz: dict[str, float] = field(default_factory=lambda: {
        "HEARTBEAT": 1.0, "ATTITUDE": 50.0, "IMU": 50.0, "SCALED_PRESSURE": 10.0, "VFR_HUD": 10.0,
        "GPS_RAW_INT": 5.0, "GLOBAL_POSITION_INT": 10.0, "FRAME": 30.0})


class KinematicPlane:
    """Coordinated-turn point mass: constant TAS and height, heading driven by a bank-limited heading hold.

    The commanded lateral acceleration is ``heading_gain * tas * heading_error``, limited by the command's
    acceleration limit and ``g tan(max_bank)``; the bank follows at ``roll_rate_deg_s``; the yaw rate is
    ``g tan(bank) / tas``.  Without a command the plane holds its heading.
    """

    def __init__(self, cfg: VehicleConfig) -> None:
        self.cfg = cfg
        self.t_s = 0.0
        self.pos_ned_m = np.array([cfg.start_ned_m[0], cfg.start_ned_m[1], -cfg.height_agl_m])
        self.yaw_rad = math.radians(cfg.start_yaw_deg)
        self.roll_rad = 0.0
        self.yaw_rate_rad_s = 0.0
        self.roll_rate_rad_s = 0.0
        self.heading_cmd_rad: float | None = None
        self.accel_limit_m_s2 = math.inf
        self.wind_ned_m_s = np.array([cfg.wind_ned_m_s[0], cfg.wind_ned_m_s[1], 0.0])

    def command_heading(self, heading_rad: float, accel_limit_m_s2: float) -> None:
        self.heading_cmd_rad = heading_rad
        self.accel_limit_m_s2 = accel_limit_m_s2

    @property
    def air_vel_ned_m_s(self) -> NDArray[np.float64]:
        return self.cfg.tas_m_s * np.array([math.cos(self.yaw_rad), math.sin(self.yaw_rad), 0.0])

    @property
    def vel_ned_m_s(self) -> NDArray[np.float64]:
        return self.air_vel_ned_m_s + self.wind_ned_m_s

    def step(self, dt_s: float) -> None:
        c = self.cfg
        bank_max = math.radians(c.max_bank_deg)
        if self.heading_cmd_rad is None:
            bank_cmd = 0.0
        else:
            err = float(angle_diff(self.heading_cmd_rad, self.yaw_rad))
            a_max = min(self.accel_limit_m_s2, GRAVITY_M_S2 * math.tan(bank_max))
            a_cmd = max(-a_max, min(a_max, c.heading_gain_1_s * c.tas_m_s * err))
            bank_cmd = math.atan(a_cmd / GRAVITY_M_S2)
        max_droll = math.radians(c.roll_rate_deg_s) * dt_s
        droll = max(-max_droll, min(max_droll, bank_cmd - self.roll_rad))
        self.roll_rate_rad_s = droll / dt_s
        self.roll_rad += droll
        self.yaw_rate_rad_s = GRAVITY_M_S2 * math.tan(self.roll_rad) / c.tas_m_s
        self.pos_ned_m = self.pos_ned_m + self.vel_ned_m_s * dt_s
        self.yaw_rad = float(wrap_2pi(self.yaw_rad + self.yaw_rate_rad_s * dt_s))
        self.t_s += dt_s

    def truth(self) -> TruthState:
        phi = self.roll_rad
        # body rates of a level coordinated turn: yaw rate about the vertical seen in the banked body frame
        rates_b = np.array([self.roll_rate_rad_s, self.yaw_rate_rad_s * math.sin(phi),
                            self.yaw_rate_rad_s * math.cos(phi)])
        accel_b = np.array([0.0, 0.0, -GRAVITY_M_S2 / math.cos(phi)])  # lift only: specific force along -z_b
        return TruthState(t_s=self.t_s, pos_ned_m=self.pos_ned_m.copy(), vel_ned_m_s=self.vel_ned_m_s,
                          roll_rad=phi, pitch_rad=0.0, yaw_rad=self.yaw_rad, rates_b_rad_s=rates_b,
                          accel_b_m_s2=accel_b, tas_m_s=self.cfg.tas_m_s, alpha_rad=0.0, beta_rad=0.0,
                          wind_ned_m_s=self.wind_ned_m_s.copy(), wind_steady_ned_m_s=self.wind_ned_m_s.copy(),
                          height_agl_m=float(-self.pos_ned_m[2]))


def ned_to_lat_lon(n_m: float, e_m: float, ref_lat_deg: float, ref_lon_deg: float) -> tuple[float, float]:
    """Flat-earth conversion of a local NED offset to latitude/longitude (degrees)."""
    lat = ref_lat_deg + math.degrees(n_m / EARTH_RADIUS_M)
    lon = ref_lon_deg + math.degrees(e_m / (EARTH_RADIUS_M * math.cos(math.radians(ref_lat_deg))))
    return lat, lon


def lat_lon_to_ne(lat_deg: float, lon_deg: float, ref_lat_deg: float, ref_lon_deg: float) -> tuple[float, float]:
    """Inverse of :func:`ned_to_lat_lon`."""
    n = math.radians(lat_deg - ref_lat_deg) * EARTH_RADIUS_M
    e = math.radians(lon_deg - ref_lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(ref_lat_deg))
    return n, e


def isa_pressure_hpa(alt_amsl_m: float) -> float:
    return ISA_P0_HPA * (1.0 - ISA_LAPSE_K_M * alt_amsl_m / ISA_T0_K) ** ISA_EXP


class FrameServer:
    """TCP server on 127.0.0.1 sending frames to one client (see the module docstring for the format)."""

    def __init__(self, port: int = 0) -> None:
        self._srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._srv.bind(("127.0.0.1", port))
        self._srv.listen(1)
        self._srv.setblocking(False)
        self.port = int(self._srv.getsockname()[1])
        self._client: socket.socket | None = None
        self.sent = 0
        self.dropped = 0

    def _accept(self) -> None:
        try:
            conn, _ = self._srv.accept()
        except BlockingIOError:
            return
        if self._client is not None:
            self._client.close()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 22)
        self._client = conn

    def send(self, t_us: int, image: NDArray[np.uint8]) -> None:
        self._accept()
        if self._client is None:
            return
        h, w = image.shape[:2]
        ch = 1 if image.ndim == 2 else image.shape[2]
        payload = FRAME_HEADER.pack(FRAME_MAGIC, t_us, w, h, ch) + np.ascontiguousarray(image).tobytes()
        try:
            self._client.settimeout(0.05)
            self._client.sendall(payload)
            self.sent += 1
        except (TimeoutError, BlockingIOError):
            self.dropped += 1  # a torn frame: the stream is resynchronised by reconnecting
            self._client.close()
            self._client = None
        except OSError:
            self._client.close()
            self._client = None

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        self._srv.close()


class MavlinkVehicle:
    """The vehicle endpoint.  ``url`` is a pymavlink URL, normally ``udpout:127.0.0.1:PORT`` (the companion
    listens there with ``udpin://127.0.0.1:PORT``)."""

    def __init__(self, url: str, cfg: VehicleConfig, rng: np.random.Generator,
                 frame_source: Callable[[TruthState], NDArray[np.uint8]] | None = None,
                 frame_server: FrameServer | None = None) -> None:
        self.cfg = cfg
        self.rng = rng
        self.plane = KinematicPlane(cfg)
        self.conn = mavutil.mavlink_connection(url, source_system=1, source_component=1, dialect="ardupilotmega")
        self.frame_source = frame_source
        self.frame_server = frame_server
        self.mode = ARDUPLANE_MODE_GUIDED
        self.received: dict[str, int] = {}
        self.last: dict[str, dict[str, Any]] = {}
        self.bad_data = 0
        self.named_values: dict[str, float] = {}
        self.heading_commands: list[tuple[float, float]] = []  # (t_s, heading_deg)
        self._next: dict[str, float] = {k: 0.0 for k in cfg.rates_hz}
        self._last_fix: tuple[float, float, float] | None = None

    def gnss_out(self, t_s: float) -> bool:
        return any(a <= t_s < b for a, b in self.cfg.gnss_outages_s)

    # ---------------------------------------------------------------- sending
    def _due(self, name: str, t_s: float) -> bool:
        rate = self.cfg.rates_hz.get(name, 0.0)
        if rate <= 0.0 or t_s + 1e-9 < self._next[name]:
            return False
        self._next[name] += 1.0 / rate
        if self._next[name] < t_s:
            self._next[name] = t_s + 1.0 / rate
        return True

    def send_telemetry(self, truth: TruthState) -> None:
        m = self.conn.mav
        c = self.cfg
        t = truth.t_s
        ms = int(t * 1000)
        us = truth.t_us
        if self._due("HEARTBEAT", t):
            ml = mavutil.mavlink
            flags = (ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | ml.MAV_MODE_FLAG_SAFETY_ARMED
                     | ml.MAV_MODE_FLAG_GUIDED_ENABLED)
            m.heartbeat_send(ml.MAV_TYPE_FIXED_WING, ml.MAV_AUTOPILOT_ARDUPILOTMEGA, flags, self.mode,
                             ml.MAV_STATE_ACTIVE)
        if self._due("ATTITUDE", t):
            p, q, r = truth.rates_b_rad_s
            m.attitude_send(ms, truth.roll_rad, truth.pitch_rad, float(wrap_pi(truth.yaw_rad)), p, q, r)
        if self._due("IMU", t):
            gyro = truth.rates_b_rad_s + self.rng.normal(0.0, c.gyro_noise_rad_s, 3)
            acc = truth.accel_b_m_s2 + self.rng.normal(0.0, c.accel_noise_m_s2, 3)
            acc_mg = np.clip(np.round(acc / GRAVITY_M_S2 * 1000.0), -32768, 32767).astype(int)
            gyro_mrad = np.clip(np.round(gyro * 1000.0), -32768, 32767).astype(int)
            m.raw_imu_send(us, *acc_mg.tolist(), *gyro_mrad.tolist(), 0, 0, 0)
            m.scaled_imu_send(ms, *acc_mg.tolist(), *gyro_mrad.tolist(), 0, 0, 0)
        alt_amsl = c.ref_alt_amsl_m - float(truth.pos_ned_m[2])
        if self._due("SCALED_PRESSURE", t):
            q_hpa = 0.5 * AIR_DENSITY_KG_M3 * truth.tas_m_s**2 / 100.0
            m.scaled_pressure_send(ms, isa_pressure_hpa(alt_amsl), q_hpa, 2000)
        gs = float(np.hypot(*truth.vel_ned_m_s[:2]))
        if self._due("VFR_HUD", t):
            m.vfr_hud_send(truth.tas_m_s, gs, int(round(math.degrees(truth.yaw_rad))) % 360, 50, alt_amsl,
                           -float(truth.vel_ned_m_s[2]))
        out = self.gnss_out(t)
        if self._due("GPS_RAW_INT", t):
            if out:
                m.gps_raw_int_send(us, 1, 0, 0, 0, 65535, 65535, 65535, 65535, 0)
            else:
                pos = truth.pos_ned_m[:2] + self.rng.normal(0.0, c.gnss_pos_noise_m, 2)
                vel = truth.vel_ned_m_s[:2] + self.rng.normal(0.0, c.gnss_vel_noise_m_s, 2)
                lat, lon = ned_to_lat_lon(float(pos[0]), float(pos[1]), c.ref_lat_deg, c.ref_lon_deg)
                self._last_fix = (lat, lon, alt_amsl)
                cog = int(round(math.degrees(math.atan2(vel[1], vel[0])) % 360.0 * 100)) % 36000
                m.gps_raw_int_send(us, 3, int(lat * 1e7), int(lon * 1e7), int(alt_amsl * 1000), 80, 120,
                                   int(float(np.hypot(*vel)) * 100), cog, 14,
                                   h_acc=int(c.gnss_pos_noise_m * 1500), v_acc=2000,
                                   vel_acc=int(c.gnss_vel_noise_m_s * 1500), hdg_acc=0)
        if self._due("GLOBAL_POSITION_INT", t) and self._last_fix is not None:
            lat, lon, alt = self._last_fix
            v = truth.vel_ned_m_s
            m.global_position_int_send(ms, int(lat * 1e7), int(lon * 1e7), int(alt * 1000),
                                       int(c.height_agl_m * 1000), int(v[0] * 100), int(v[1] * 100),
                                       int(v[2] * 100), int(round(math.degrees(truth.yaw_rad) * 100)) % 36000)
        if self.frame_source is not None and self.frame_server is not None and self._due("FRAME", t):
            self.frame_server.send(us, self.frame_source(truth))

    # ---------------------------------------------------------------- receiving
    def poll(self) -> None:
        """Handle every message waiting on the socket (never blocks, never raises on garbage)."""
        while True:
            try:
                msg = self.conn.recv_match(blocking=False)
            except Exception as e:  # pymavlink raises on some malformed input; a vehicle must survive it
                self.bad_data += 1
                log.debug("malformed MAVLink input: %s", e)
                continue
            if msg is None:
                return
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.bad_data += 1
                continue
            self.received[kind] = self.received.get(kind, 0) + 1
            self.last[kind] = msg.to_dict()
            if kind == "COMMAND_LONG":
                self._command(msg)
            elif kind == "NAMED_VALUE_FLOAT":
                self.named_values[str(msg.name)] = float(msg.value)

    def _command(self, msg: Any) -> None:
        if msg.target_system not in (0, 1):
            return
        result = MAV_RESULT_UNSUPPORTED
        if msg.command == mavutil.mavlink.MAV_CMD_GUIDED_CHANGE_HEADING:
            if self.mode != ARDUPLANE_MODE_GUIDED:
                result = MAV_RESULT_FAILED
            elif not (0.0 <= msg.param2 < 360.0) or int(msg.param1) not in (0, 1):
                result = MAV_RESULT_DENIED
            else:
                # heading type 0 (course over ground) is flown as a heading: the kinematic autopilot, like ArduPlane
                # without GNSS, has no course to close the loop on.
                self.plane.command_heading(math.radians(msg.param2), max(msg.param3, 0.05))
                self.heading_commands.append((self.plane.t_s, float(msg.param2)))
                result = MAV_RESULT_ACCEPTED
        self.conn.mav.command_ack_send(msg.command, result)

    # ---------------------------------------------------------------- running
    def step(self) -> TruthState:
        self.plane.step(self.cfg.dt_s)
        truth = self.plane.truth()
        self.send_telemetry(truth)
        self.poll()
        return truth

    def run(self, duration_s: float, realtime: bool = True,
            stop: Callable[[TruthState], bool] | None = None) -> list[TruthState]:
        """Fly for ``duration_s`` (wall-clock paced when ``realtime``); returns the truth at every step."""
        history: list[TruthState] = []
        start = time.monotonic()
        n = int(round(duration_s / self.cfg.dt_s))
        for i in range(n):
            truth = self.step()
            history.append(truth)
            if stop is not None and stop(truth):
                break
            if realtime:
                lag = start + (i + 1) * self.cfg.dt_s - time.monotonic()
                if lag > 0:
                    time.sleep(lag)
        return history

    def summary(self) -> dict[str, Any]:
        return {"received": self.received, "last": self.last, "bad_data": self.bad_data,
                "heading_commands": self.heading_commands, "named_values": self.named_values,
                "frames_sent": self.frame_server.sent if self.frame_server else 0,
                "pos_ned_m": self.plane.pos_ned_m.tolist(), "yaw_deg": math.degrees(self.plane.yaw_rad)}

    def close(self) -> None:
        self.conn.close()
        if self.frame_server is not None:
            self.frame_server.close()


def render_frame_source(texture: str, seed: int, roi: tuple[int, int, int, int] | None, noise_std: float,
                        rng: np.random.Generator, config_path: str | None = None
                        ) -> Callable[[TruthState], NDArray[np.uint8]]:
    """Frames of the calibrated belly camera over ``texture`` rendered by :class:`sim.render.CameraRenderer`.

    ``roi`` (x0, y0, x1, y1) renders only that rectangle (the rest is black): the estimator reads only the
    stabilised patch around the nadir, and a full 800x600 fisheye frame costs ~30 ms here.
    """
    from gsoe.camera import CameraModel
    from gsoe.rotation import R_nb_from_euler
    from nav.configfile import load_gsoe_config
    from sim.render import CameraRenderer
    from sim.textures import GroundWorld

    gsoe_cfg, _ = load_gsoe_config(config_path)
    renderer = CameraRenderer(CameraModel.from_config(gsoe_cfg.camera), GroundWorld.from_name(texture, seed=seed))

    def source(truth: TruthState) -> NDArray[np.uint8]:
        R_nb = R_nb_from_euler(truth.roll_rad, truth.pitch_rad, truth.yaw_rad)
        return renderer.render(truth.pos_ned_m, R_nb, roi=roi, noise_std=noise_std, rng=rng)

    return source


def _pair(text: str) -> tuple[float, float]:
    a, b = text.split(",")
    return float(a), float(b)


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.mavlink_vehicle --connect udpout:127.0.0.1:PORT [...]``: run the vehicle as a process."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", required=True, help="pymavlink URL, e.g. udpout:127.0.0.1:14540")
    ap.add_argument("--duration-s", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start-ned-m", type=_pair, default=(0.0, 0.0))
    ap.add_argument("--start-yaw-deg", type=float, default=0.0)
    ap.add_argument("--wind-ned-m-s", type=_pair, default=(0.0, 0.0))
    ap.add_argument("--gnss-outage-s", type=_pair, action="append", default=[], help="START,END (repeatable)")
    ap.add_argument("--summary", help="write a JSON summary of what the vehicle received here at the end")
    ap.add_argument("--frame-port", type=int, help="stream rendered camera frames on this TCP port (0: any)")
    ap.add_argument("--frame-hz", type=float, default=30.0)
    ap.add_argument("--texture", default="farmland", help="ground texture of sim.textures")
    ap.add_argument("--frame-roi", default="250,150,550,450", help="X0,Y0,X1,Y1 rendered region ('full': all)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    rates = dict(VehicleConfig().rates_hz, FRAME=args.frame_hz)
    cfg = VehicleConfig(start_ned_m=args.start_ned_m, start_yaw_deg=args.start_yaw_deg,
                        wind_ned_m_s=args.wind_ned_m_s, gnss_outages_s=tuple(args.gnss_outage_s), rates_hz=rates)
    rng = np.random.default_rng(args.seed)
    source = server = None
    if args.frame_port is not None:
        roi = None if args.frame_roi == "full" else tuple(int(v) for v in args.frame_roi.split(","))
        source = render_frame_source(args.texture, args.seed, roi, 1.0, rng)  # type: ignore[arg-type]
        server = FrameServer(args.frame_port)
        log.info("camera frames on tcp 127.0.0.1:%d", server.port)
    veh = MavlinkVehicle(args.connect, cfg, rng, source, server)
    try:
        veh.run(args.duration_s)
    except KeyboardInterrupt:
        pass
    finally:
        if args.summary:
            with open(args.summary, "w") as fh:
                json.dump(veh.summary(), fh)
        veh.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
