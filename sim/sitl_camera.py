"""The belly camera of a plane flown by a real autopilot's simulator: ArduPlane SITL's truth in, rendered frames out.

``python -m sim.sitl_camera --connect tcp:127.0.0.1:5762 --frame-port 5600`` (or ``gsoe sitl-camera``) connects to
ArduPlane SITL over MAVLink (pymavlink; its SERIAL2 by default, so that SERIAL0 stays the ground station's and
SERIAL1 the companion's), asks for ``SIM_STATE`` (the simulator's true position, velocity and attitude) and
``ATTITUDE`` at ``--truth-hz`` with MAV_CMD_SET_MESSAGE_INTERVAL (refused rates retried at 0.8 times themselves, as
the companion's link does), and renders the belly camera from that truth with the simulator's own renderer
(:class:`sim.mavlink_vehicle.BellyCamera`: :class:`sim.render.CameraRenderer` over a :class:`sim.textures.GroundWorld`,
the camera of the configuration file, only the nadir region the optical estimator samples).  The frames are served
in the simulator's frame-stream format (:mod:`common.framestream`, :class:`sim.mavlink_vehicle.FrameServer`: TCP on
127.0.0.1, one client), so the companion reads them as it reads the simulated vehicle's camera:
``gsoe companion --camera sim://127.0.0.1:PORT``.  The attitude the companion estimates with is ArduPlane's AHRS
over its own MAVLink link, as on a real plane; only the pixels come from here.

Time: neither ``SIM_STATE`` nor ``SIMSTATE`` carries a stamp.  ArduPilot sends one scheduler loop's messages
together, ATTITUDE before SIM_STATE, so a truth sample is stamped with the ``time_boot_ms`` of the ATTITUDE
received just before it (measured against ArduPlane SITL 4.7: the AHRS roll matches the truth's with 0.1 deg RMS at
that pairing, 0.3 deg one loop, 25 ms, either side).  A frame's exposure time ``t_us`` in the stream is that stamp:
the autopilot's clock.

Geometry: north/east from the first truth sample's latitude/longitude (``lat_int``/``lon_int``, 1e-7 deg: the float
fields hold only about a metre), down from the ground's altitude, ``--ground-amsl-m`` or the first sample's altitude
(the plane waits on the runway: ArduPlane SITL's ground is flat at home's altitude).  ``SIMSTATE`` (ArduPilot's
dialect) is used when ``SIM_STATE`` does not come; it has no velocity, which only the motion blur of the exposure
needs.

Experiment hook: ``--oracle-velocity-hz HZ`` also sends ArduPlane the truth's own body-frame ground velocity as
VISION_POSITION_DELTA at that rate (confidence ``--oracle-confidence``), what a perfect companion would send: the
floor of what ArduPlane's EKF makes of a body-frame velocity (:mod:`sim.sitl_mission` ``--oracle``).

A frame is rendered for the first truth sample at or after each ``1 / --frame-hz`` of the autopilot's clock; a
truth sample older than ``--max-lag-s`` of wall-clock time when it is read (the bridge fell behind) is skipped, so a
slow renderer drops frames rather than lagging.  ``--truth-log DIR`` writes every truth sample to ``DIR/truth.csv``
(:mod:`common.logio`).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sim.mavlink_vehicle import DEFAULT_TEXTURE, EARTH_RADIUS_M, BellyCamera, FrameServer
from sim.truth import TruthState

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402  (MAVLINK20 must be set before import)

log = logging.getLogger(__name__)

MAV_CMD_SET_MESSAGE_INTERVAL = 511
MSG_ATTITUDE = 30
MSG_SIM_STATE = 108
MSG_SIMSTATE = 164
RATE_FALLBACK = 0.8          # a refused rate is asked again at this fraction of itself ...
RATE_MIN_FRACTION = 0.25     # ... down to this fraction of the wanted rate
ACK_TIMEOUT_S = 2.0
HEARTBEAT_TIMEOUT_S = 60.0
CAMERA_NOISE_STD = 2.0       # grey levels, as the SIL scenario's camera
CAMERA_EXPOSURE_S = 0.002
MIN_RENDER_HEIGHT_M = 0.3    # the camera's lowest height over the ground (the plane on its wheels)


@dataclass(frozen=True, slots=True)
class SitlTruth:
    """One truth sample of the SITL: ``t_us`` on the autopilot's clock, latitude/longitude/altitude (AMSL), NED
    velocity, attitude (3-2-1 Euler, rad) and body rates (FRD, rad/s)."""

    t_us: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    vel_ned_m_s: NDArray[np.float64]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rates_b_rad_s: NDArray[np.float64]


def truth_from_message(msg: dict[str, Any], t_us: int) -> SitlTruth | None:
    """A truth sample of a SIM_STATE or SIMSTATE message (``to_dict`` form) stamped ``t_us``; None if not finite."""
    kind = msg.get("mavpackettype")
    if kind == "SIM_STATE":
        lat = msg["lat_int"] / 1e7 if msg.get("lat_int") else float(msg["lat"])
        lon = msg["lon_int"] / 1e7 if msg.get("lon_int") else float(msg["lon"])
        vel = np.array([msg["vn"], msg["ve"], msg["vd"]], dtype=float)
        alt = float(msg["alt"])
    elif kind == "SIMSTATE":
        lat, lon = msg["lat"] / 1e7, msg["lng"] / 1e7
        vel = np.full(3, math.nan)
        alt = math.nan  # SIMSTATE has no altitude: the caller keeps the last SIM_STATE's
    else:
        return None
    s = SitlTruth(t_us, float(lat), float(lon), alt, vel, float(msg["roll"]), float(msg["pitch"]), float(msg["yaw"]),
                  np.array([msg["xgyro"], msg["ygyro"], msg["zgyro"]], dtype=float))
    if not all(math.isfinite(v) for v in (s.lat_deg, s.lon_deg, s.roll_rad, s.pitch_rad, s.yaw_rad)):
        return None
    return s


class LocalFrame:
    """North/east/down of latitude/longitude/altitude relative to an origin on the ground (flat earth)."""

    def __init__(self, lat_deg: float, lon_deg: float, ground_amsl_m: float) -> None:
        self.lat0, self.lon0, self.ground_amsl_m = lat_deg, lon_deg, ground_amsl_m
        self._k_e = EARTH_RADIUS_M * math.cos(math.radians(lat_deg))

    def ned(self, lat_deg: float, lon_deg: float, alt_m: float) -> NDArray[np.float64]:
        return np.array([math.radians(lat_deg - self.lat0) * EARTH_RADIUS_M,
                         math.radians(lon_deg - self.lon0) * self._k_e, -(alt_m - self.ground_amsl_m)])


def truth_state(s: SitlTruth, frame: LocalFrame) -> TruthState:
    """The :class:`TruthState` the renderer takes (air data unknown: NaN); the camera kept at least
    :data:`MIN_RENDER_HEIGHT_M` above the ground (the renderer needs it above the plane: on the runway)."""
    pos = frame.ned(s.lat_deg, s.lon_deg, s.alt_m)
    pos[2] = min(pos[2], -MIN_RENDER_HEIGHT_M)
    vel = np.nan_to_num(s.vel_ned_m_s)
    nan = math.nan
    return TruthState(t_s=s.t_us / 1e6, pos_ned_m=pos, vel_ned_m_s=vel, roll_rad=s.roll_rad, pitch_rad=s.pitch_rad,
                      yaw_rad=s.yaw_rad, rates_b_rad_s=s.rates_b_rad_s, accel_b_m_s2=np.full(3, nan), tas_m_s=nan,
                      alpha_rad=nan, beta_rad=nan, wind_ned_m_s=np.full(3, nan), wind_steady_ned_m_s=np.full(3, nan),
                      height_agl_m=float(-pos[2]))


def truth_record(s: SitlTruth, frame: LocalFrame) -> dict[str, Any]:
    pos = frame.ned(s.lat_deg, s.lon_deg, s.alt_m)
    return {"t_us": s.t_us, "lat_deg": s.lat_deg, "lon_deg": s.lon_deg, "alt_m": s.alt_m, "pos_n_m": pos[0],
            "pos_e_m": pos[1], "pos_d_m": pos[2], "vel_n_m_s": s.vel_ned_m_s[0], "vel_e_m_s": s.vel_ned_m_s[1],
            "vel_d_m_s": s.vel_ned_m_s[2], "roll_rad": s.roll_rad, "pitch_rad": s.pitch_rad, "yaw_rad": s.yaw_rad}


class TruthStamper:
    """Pairs each SIM_STATE/SIMSTATE with the autopilot time of the ATTITUDE sent just before it (module docstring)."""

    def __init__(self) -> None:
        self.att_us: int | None = None
        self.last_us: int | None = None
        self.unpaired = 0

    def attitude(self, time_boot_ms: int) -> None:
        self.att_us = int(time_boot_ms) * 1000

    def stamp(self) -> int | None:
        """The stamp of a truth message received now; None when no ATTITUDE came since the last one paired."""
        t = self.att_us
        if t is None or (self.last_us is not None and t <= self.last_us):
            self.unpaired += 1
            return None
        self.last_us = t
        return t


def request_interval(conn: Any, msg_id: int, rate_hz: float, target: tuple[int, int]) -> float:
    """Ask for ``msg_id`` at ``rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL), falling back as the module docstring says;
    returns the rate granted (0: refused or unanswered)."""
    hz = rate_hz
    while hz >= rate_hz * RATE_MIN_FRACTION - 1e-9:
        conn.mav.command_long_send(target[0], target[1], MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e6 / hz,
                                   0, 0, 0, 0, 0)
        end = time.monotonic() + ACK_TIMEOUT_S
        result = None
        while time.monotonic() < end:
            ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
            if ack is not None and ack.command == MAV_CMD_SET_MESSAGE_INTERVAL:
                result = int(ack.result)
                break
        if result == 0:
            return hz
        if result is None or result == mavutil.mavlink.MAV_RESULT_UNSUPPORTED:
            return 0.0
        hz *= RATE_FALLBACK
    return 0.0


class SitlCamera:
    """The bridge (module docstring).  ``run()`` until :meth:`request_stop` or ``duration_s``."""

    def __init__(self, url: str, server: FrameServer, *, frame_hz: float = 20.0, truth_hz: float = 40.0,
                 texture: str = DEFAULT_TEXTURE, seed: int = 0, config_path: str | None = None,
                 ground_amsl_m: float | None = None, max_lag_s: float = 0.25, truth_log_dir: str | None = None,
                 noise_std: float = CAMERA_NOISE_STD, oracle_velocity_hz: float = 0.0,
                 oracle_confidence: int = 100, mount_yaw_error_deg: float = 0.0) -> None:
        self.url = url
        self.server = server
        self.frame_period_us = round(1e6 / frame_hz)
        self.truth_hz = truth_hz
        self.ground_amsl_m = ground_amsl_m
        self.max_lag_s = max_lag_s
        rng = np.random.default_rng(seed)
        self.camera = BellyCamera(texture, seed, noise_std, CAMERA_EXPOSURE_S, rng, config_path, mount_yaw_error_deg)
        self.stamper = TruthStamper()
        self.frame: LocalFrame | None = None
        self.truth_log: Any = None
        if truth_log_dir is not None:
            from common.logio import RunLog

            self.truth_log = RunLog(truth_log_dir)
        self._next_frame_us: int | None = None
        self._last_alt = math.nan
        self._stop = False
        self._conn: Any = None
        self.oracle_period_us = round(1e6 / oracle_velocity_hz) if oracle_velocity_hz > 0 else 0
        self.oracle_confidence = oracle_confidence
        self._oracle_last_us: int | None = None
        self.granted: dict[str, float] = {}
        self.counts = {"truth": 0, "frames": 0, "skipped_late": 0, "render_s": 0.0}

    def request_stop(self) -> None:
        self._stop = True

    def connect(self) -> Any:
        end = time.monotonic() + HEARTBEAT_TIMEOUT_S
        while True:  # the SITL opens its SERIAL2 port only once its SERIAL0 has a client
            try:
                conn = mavutil.mavlink_connection(self.url, source_system=255, source_component=195,
                                                  dialect="ardupilotmega", autoreconnect=True)
                break
            except OSError as e:
                if time.monotonic() > end or self._stop:
                    raise TimeoutError(f"cannot connect to {self.url}: {e}") from e
                time.sleep(0.5)
        hb = conn.wait_heartbeat(timeout=max(end - time.monotonic(), 1.0))
        if hb is None:
            raise TimeoutError(f"no heartbeat on {self.url} within {HEARTBEAT_TIMEOUT_S:.0f} s")
        target = (conn.target_system, conn.target_component or 1)
        for name, mid in (("ATTITUDE", MSG_ATTITUDE), ("SIM_STATE", MSG_SIM_STATE)):
            self.granted[name] = request_interval(conn, mid, self.truth_hz, target)
            log.info("%s granted at %.3g Hz", name, self.granted[name])
        return conn

    def run(self, duration_s: float | None = None) -> dict[str, Any]:
        conn = self._conn = self.connect()
        start = time.monotonic()
        try:
            while not self._stop and (duration_s is None or time.monotonic() - start < duration_s):
                msg = conn.recv_match(blocking=True, timeout=0.5)
                if msg is None:
                    continue
                kind = msg.get_type()
                if kind == "ATTITUDE":
                    self.stamper.attitude(msg.time_boot_ms)
                elif kind in ("SIM_STATE", "SIMSTATE"):
                    if kind == "SIMSTATE" and self.granted.get("SIM_STATE", 0.0) > 0.0:
                        continue
                    self._truth(msg.to_dict(), float(getattr(msg, "_timestamp", time.time())))
        finally:
            conn.close()
            self.server.close()
            if self.truth_log is not None:
                self.truth_log.close()
        return {**self.counts, "granted": self.granted, "unpaired": self.stamper.unpaired,
                "frames_sent": self.server.sent, "frames_dropped": self.server.dropped}

    def _truth(self, d: dict[str, Any], received_unix_s: float) -> None:
        t_us = self.stamper.stamp()
        if t_us is None:
            return
        s = truth_from_message(d, t_us)
        if s is None:
            return
        if math.isnan(s.alt_m):
            s = SitlTruth(s.t_us, s.lat_deg, s.lon_deg, self._last_alt, s.vel_ned_m_s, s.roll_rad, s.pitch_rad,
                          s.yaw_rad, s.rates_b_rad_s)
        self._last_alt = s.alt_m
        if not math.isfinite(s.alt_m):
            return
        if self.frame is None:
            ground = s.alt_m if self.ground_amsl_m is None else self.ground_amsl_m
            self.frame = LocalFrame(s.lat_deg, s.lon_deg, ground)
            log.info("local frame at %.7f, %.7f, ground %.2f m AMSL", s.lat_deg, s.lon_deg, ground)
        self.counts["truth"] += 1
        if self.oracle_period_us:
            self._oracle(s)
        if self.truth_log is not None:
            self.truth_log.write("truth", truth_record(s, self.frame))
        if self._next_frame_us is not None and s.t_us < self._next_frame_us:
            return
        self._next_frame_us = (s.t_us // self.frame_period_us + 1) * self.frame_period_us
        if time.time() - received_unix_s > self.max_lag_s:
            self.counts["skipped_late"] += 1
            return
        t0 = time.perf_counter()
        try:
            image = self.camera.render(truth_state(s, self.frame))
        except ValueError as e:  # a pose the renderer refuses: no frame, the stream goes on
            self.counts["render_errors"] = self.counts.get("render_errors", 0) + 1
            log.warning("frame at %d us not rendered: %s", s.t_us, e)
            return
        self.counts["render_s"] += time.perf_counter() - t0
        self.server.send(s.t_us, image)
        self.counts["frames"] += 1


    def _oracle(self, s: SitlTruth) -> None:
        """The truth's body-frame ground velocity as VISION_POSITION_DELTA (module docstring)."""
        last = self._oracle_last_us
        if last is not None and s.t_us - last < self.oracle_period_us:
            return
        self._oracle_last_us = s.t_us
        if last is None or not np.all(np.isfinite(s.vel_ned_m_s)):
            return
        from gsoe.rotation import R_nb_from_euler

        dt_us = s.t_us - last
        v_b = R_nb_from_euler(s.roll_rad, s.pitch_rad, s.yaw_rad).T @ s.vel_ned_m_s
        self._conn.mav.vision_position_delta_send(s.t_us, dt_us, [0.0, 0.0, 0.0],
                                                  [float(v) * dt_us / 1e6 for v in v_b], float(self.oracle_confidence))
        self.counts["oracle_sent"] = self.counts.get("oracle_sent", 0) + 1


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--connect", default="tcp:127.0.0.1:5762",
                    help="pymavlink URL of the SITL (default: its SERIAL2, tcp:127.0.0.1:5762)")
    ap.add_argument("--frame-port", type=int, default=0, help="TCP port of the frame stream on 127.0.0.1 (0: any)")
    ap.add_argument("--frame-hz", type=float, default=20.0, help="frames per second of the autopilot's clock")
    ap.add_argument("--truth-hz", type=float, default=40.0, help="SIM_STATE and ATTITUDE rate to ask for")
    ap.add_argument("--texture", default=DEFAULT_TEXTURE, help="ground texture (sim.textures)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the texture and the camera noise")
    ap.add_argument("--config", help="configuration file (the camera), shared with the companion")
    ap.add_argument("--ground-amsl-m", type=float, help="the ground's altitude (default: the first truth sample's)")
    ap.add_argument("--max-lag-s", type=float, default=0.25, help="truth read later than this is not rendered")
    ap.add_argument("--truth-log", help="write truth.csv (every truth sample) to this folder")
    ap.add_argument("--duration-s", type=float, help="stop after this long (default: until stopped)")
    ap.add_argument("--port-file", help="write the frame port to this file once listening")
    ap.add_argument("--oracle-velocity-hz", type=float, default=0.0,
                    help="experiment: send the truth's body-frame velocity (VISION_POSITION_DELTA) at this rate")
    ap.add_argument("--oracle-confidence", type=int, default=100, help="its confidence (0-100)")
    ap.add_argument("--mount-yaw-error-deg", type=float, default=0.0,
                    help="render with the camera turned this much further in yaw than its file says (a mount error)")


def run(args: argparse.Namespace) -> int:
    server = FrameServer(args.frame_port)
    log.info("camera frames on tcp 127.0.0.1:%d", server.port)
    if args.port_file:
        tmp = args.port_file + ".tmp"
        with open(tmp, "w") as fh:
            fh.write(str(server.port))
        os.replace(tmp, args.port_file)
    bridge = SitlCamera(args.connect, server, frame_hz=args.frame_hz, truth_hz=args.truth_hz, texture=args.texture,
                        seed=args.seed, config_path=args.config, ground_amsl_m=args.ground_amsl_m,
                        max_lag_s=args.max_lag_s, truth_log_dir=args.truth_log,
                        oracle_velocity_hz=args.oracle_velocity_hz, oracle_confidence=args.oracle_confidence,
                        mount_yaw_error_deg=args.mount_yaw_error_deg)

    def _term(signum: int, _frame: object) -> None:
        bridge.request_stop()

    signal.signal(signal.SIGTERM, _term)
    signal.signal(signal.SIGINT, _term)
    summary = bridge.run(args.duration_s)
    log.info("sitl camera: %s", summary)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(ap)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return run(args)


if __name__ == "__main__":
    raise SystemExit(main())
