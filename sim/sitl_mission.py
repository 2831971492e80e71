"""A GNSS-denied AUTO mission of ArduPlane SITL flown on the companion's estimate, and its figures.

``python -m sim.sitl_mission --duration 600 [--speedup 2] [--out DIR] [--velocity-message NAME] [--compare-dr]``

What one flight does (:func:`fly_mission`), every process in its own folder under ``DIR``, bound to 127.0.0.1,
stopped by its own id at the end, the whole flight bounded in time:

1. ArduPlane SITL (``../shared/tools/ardupilot/arduplane``, the model ``plane``, its ``plane.parm`` defaults plus
   :func:`sitl_parameters`: wind ``SIM_WIND_SPD``/``SIM_WIND_DIR``, SERIAL1 for the companion, external navigation
   in EKF source set 2; the same parameters ``docs/ardupilot.md`` lists), SERIAL0 for this harness (a ground station
   over TCP), SERIAL1 ``udpclient`` to the companion, SERIAL2 for the camera bridge;
2. the camera bridge (:mod:`sim.sitl_camera`: the belly camera rendered from ArduPlane's SIM_STATE truth) and the
   companion (``gsoe companion --connect udpin://... --camera sim://...``, the SITL plane's airframe in
   ``[ekf]``: :data:`SITL_AIRFRAME`, and :data:`SITL_COMPANION`);
3. a mission: take-off to ``alt_m`` above home, then a racetrack (``leg_m`` x ``width_m``, laps repeated with
   DO_JUMP); arm, AUTO;
4. ``gnss_on_s`` after take-off (the plane above ``takeoff_done_m``) the GNSS goes off (``SIM_GPS1_ENABLE 0``) and,
   with external navigation, the EKF source set is switched to 2 (MAV_CMD_SET_EKF_SOURCE_SET); the flight goes on for
   ``denied_s`` of the autopilot's clock;
5. meanwhile this harness logs (CSV, :mod:`common.logio`) ArduPlane's position (GLOBAL_POSITION_INT), attitude,
   EKF status (EKF_STATUS_REPORT) and the simulator's truth (SIM_STATE, stamped with the ATTITUDE sent just before
   it in the same scheduler loop), and what the companion sends that ArduPlane forwards (its named values, WIND,
   velocity messages, STATUSTEXT).

:func:`mission_metrics` turns the logs into ``metrics.json``: how long after take-off the companion's estimate was
valid, its drift error against the truth while GNSS was on, ArduPlane's position error against the truth over the
GNSS-denied leg (and as a fraction of the distance flown in it), ArduPlane's heading error, the companion's wind
against ``SIM_WIND_*`` in that leg.  ``--compare-dr`` flies the same mission again without external navigation
(ArduPlane dead-reckoning alone, the companion connected but sending no velocity) and reports the ratio.

Time is the autopilot's (``time_boot_ms``) throughout; a message without a stamp (WIND, STATUSTEXT) gets the newest
stamp received before it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.angles import wrap_360, wrap_pi
from common.logio import RunLog, read_log
from common.procs import free_port, stop_process
from common.report import write_metrics

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402  (MAVLINK20 must be set before import)

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
AP_DIR = Path(os.environ.get("GSOE_ARDUPILOT_DIR", ROOT.parent / "shared" / "tools" / "ardupilot"))
ARDUPLANE = AP_DIR / "arduplane"
PLANE_PARM = AP_DIR / "plane.parm"
PY = sys.executable
HOME = (-35.363262, 149.165237, 584.0, 353.0)  # ArduPilot's CMAC test field: lat, lon, alt AMSL, runway heading
EARTH_RADIUS_M = 6371008.8
SERIAL0_TCP_BASE = 5760   # + 10 x instance: the ground station's port (SERIAL2's is in the SITL's log)
MAV_CMD_SET_EKF_SOURCE_SET = 42007
MAV_CMD_SET_MESSAGE_INTERVAL = 511
ARDUPLANE_MODE_AUTO = 10
FORCE_ARM_MAGIC = 21196
PROCESS_START_TIMEOUT_S = 60.0
SITL_CONNECT_TIMEOUT_S = 20.0  # ArduPlane SITL: its SERIAL0 open and accepting, else it is started again
SITL_START_ATTEMPTS = 3
EKF_READY_TIMEOUT_S = 120.0   # autopilot seconds for the EKF to use the GNSS after boot
LIFTOFF_M = 2.0               # truth height over the ground that counts as airborne
#: the SITL plane's airframe (ArduPilot libraries/SITL/SIM_Plane.h: the 2 kg model, last_letter's coefficients;
#: its aerodynamics use the sea-level density) for the companion's sideslip and angle of attack models
SITL_AIRFRAME = {"ekf.airframe_mass_kg": 2.0, "ekf.airframe_wing_area_m2": 0.45,
                 "ekf.sideslip_side_force_coef_per_rad": -0.98, "ekf.air_density_kg_m3": 1.225,
                 "ekf.aoa_lift_slope_per_rad": 6.9, "ekf.aoa_lift_coef_zero": 0.56}
#: what the companion assumes of this autopilot's sensors and camera (the figures: docs/ardupilot.md):
#: - ArduPlane SITL's pitot, made true with the baro's air density, is exact: its scale pinned;
#: - ArduPlane's heading without GNSS wanders a few degrees over a lap, and the companion's heading is ArduPlane's
#:   less its yaw-bias estimate: the yaw bias walks fast enough to follow it;
#: - the camera mount is exact (the bridge renders with the companion's own camera file), as a calibrated mount is
#:   (``gsoe calibrate-mount``): the optical-rotation state held at 0 +- 0.1 deg, so that it does not take
#:   ArduPlane's heading error on a straight route
SITL_COMPANION = {"ekf.init_tas_scale_sigma": 0.002, "ekf.yaw_bias_rw_deg_per_rt_s": 0.05,
                  "ekf.init_opt_rot_sigma_deg": 0.1, "ekf.opt_rot_rw_deg_per_rt_s": 0.002}
#: what the harness asks for on its own link (SERIAL0), Hz
HARNESS_RATES = {"SIM_STATE": 10.0, "ATTITUDE": 10.0, "GLOBAL_POSITION_INT": 10.0, "EKF_STATUS_REPORT": 2.0,
                 "GPS_RAW_INT": 2.0, "VFR_HUD": 2.0}
MSG_IDS = {"SIM_STATE": 108, "ATTITUDE": 30, "GLOBAL_POSITION_INT": 33, "EKF_STATUS_REPORT": 193, "GPS_RAW_INT": 24,
           "VFR_HUD": 74}
COMPANION_COMPONENT = 191
RC_MID_PWM = 1500             # RC7 in the middle: EKF source set 2 (RC7_OPTION 90)
RC_OVERRIDE_IGNORE = 65535    # RC_CHANNELS_OVERRIDE: leave this channel alone
RC_OVERRIDE_PERIOD_S = 0.5


@dataclass(frozen=True)
class MissionSpec:
    """One flight (units in the names; module docstring).  ``extnav``: the companion's velocity reaches ArduPlane's
    EKF (source set 2 after the GNSS loss); false: ArduPlane dead-reckons alone (the companion sends no velocity)."""

    denied_s: float = 600.0
    gnss_on_s: float = 120.0
    speedup: float = 2.0
    wind_speed_m_s: float = 5.0
    wind_from_deg: float = 270.0
    alt_m: float = 100.0
    leg_m: float = 1200.0
    width_m: float = 500.0
    extnav: bool = True
    velocity_message: str = "vision_position_delta"
    frame_hz: float = 20.0
    viso_delay_ms: int = 50
    viso_vel_m_nse: float = 0.3
    vis_verr_min_m_s: float = 0.1
    vis_verr_max_m_s: float = 0.5
    companion_settings: tuple[str, ...] = ()
    oracle_confidence: int = -1  # >= 0: experiment, the bridge sends the truth's body velocity (sim.sitl_camera)
    source_switch: str = "command"  # "command": MAV_CMD_SET_EKF_SOURCE_SET; "rc": RC7 (RC7_OPTION 90) to mid
    ap_params: tuple[tuple[str, float], ...] = ()  # more ArduPlane parameters (experiments; override the above)
    route: str = "racetrack"  # "racetrack": laps of leg_m x width_m; "transit": a straight line away from home
    mount_yaw_error_deg: float = 0.0  # the bridge's camera turned this much further than the companion's file says
    mount_calibrated: bool = True  # false: the companion's optical rotation is free to learn the mount (a calibration
    #                                flight, gsoe calibrate-mount); true: held as after a calibration (SITL_COMPANION)
    timeout_factor: float = 3.0  # the flight is given up after this many times its nominal wall-clock length

    @property
    def flight_s(self) -> float:
        """Autopilot seconds from AUTO to the end (take-off about 40 s)."""
        return 60.0 + self.gnss_on_s + self.denied_s


def sitl_parameters(spec: MissionSpec) -> dict[str, float]:
    """ArduPlane parameters the flight sets on top of the model's defaults (docs/ardupilot.md lists each one)."""
    return {
        "ARMING_CHECK": 0,                 # SITL only: no pre-arm checks (no RC, no calibrations)
        "SCHED_LOOP_RATE": 50,             # ArduPlane's default: message rates above 0.8 x 50 Hz are refused
        "SIM_WIND_SPD": spec.wind_speed_m_s,
        "SIM_WIND_DIR": spec.wind_from_deg,
        "SIM_WIND_TURB": 0,
        "SERIAL1_PROTOCOL": 2,             # MAVLink 2 to the companion
        "SERIAL1_BAUD": 921,               # 921600 baud (ignored by SITL's UDP)
        "VISO_TYPE": 1,                    # visual odometry over MAVLink
        "VISO_DELAY_MS": spec.viso_delay_ms,
        "VISO_VEL_M_NSE": spec.viso_vel_m_nse,
        "EK3_VIS_VERR_MIN": spec.vis_verr_min_m_s,
        "EK3_VIS_VERR_MAX": spec.vis_verr_max_m_s,
        "EK3_SRC2_POSXY": 0,               # source set 2: no horizontal position ...
        "EK3_SRC2_VELXY": 6,               # ... external-navigation velocity ...
        "EK3_SRC2_POSZ": 1,                # ... baro height ...
        "EK3_SRC2_VELZ": 0,                # ... no vertical velocity ...
        "EK3_SRC2_YAW": 1,                 # ... compass heading
        "RC7_OPTION": 90,                  # RC7 low/middle/high: EKF source set 1/2/3
        **dict(spec.ap_params),
    }


#: parameters the flight sets while flying (the GNSS loss)
IN_FLIGHT_PARAMETERS = ("SIM_GPS1_ENABLE",)


def companion_settings(spec: MissionSpec) -> list[str]:
    """The companion's ``--set`` overrides for the flight."""
    held = SITL_COMPANION if spec.mount_calibrated else {k: v for k, v in SITL_COMPANION.items() if "opt_rot" not in k}
    out = [f"{k}={v}" for k, v in {**SITL_AIRFRAME, **held}.items()]
    out += [f'companion.link.velocity_message="{spec.velocity_message}"',
            f"companion.link.vision_speed={'true' if spec.extnav and spec.oracle_confidence < 0 else 'false'}",
            f"companion.link.ap_vis_verr_min_m_s={spec.vis_verr_min_m_s}",
            f"companion.link.ap_vis_verr_max_m_s={spec.vis_verr_max_m_s}"]
    return out + list(spec.companion_settings)


# ------------------------------------------------------------------------------------------------ geometry
def ne_of(lat_deg: Any, lon_deg: Any, lat0_deg: float, lon0_deg: float) -> tuple[Any, Any]:
    """North/east (m) of latitudes/longitudes (scalars or arrays) from an origin (flat earth)."""
    return (np.radians(np.asarray(lat_deg) - lat0_deg) * EARTH_RADIUS_M,
            np.radians(np.asarray(lon_deg) - lon0_deg) * EARTH_RADIUS_M * math.cos(math.radians(lat0_deg)))


def lat_lon_of(n_m: float, e_m: float, lat0_deg: float, lon0_deg: float) -> tuple[float, float]:
    return (lat0_deg + math.degrees(n_m / EARTH_RADIUS_M),
            lon0_deg + math.degrees(e_m / (EARTH_RADIUS_M * math.cos(math.radians(lat0_deg)))))


def route_points(spec: MissionSpec) -> tuple[list[tuple[float, float]], bool]:
    """The mission's waypoints after the take-off (north, east from home, m) and whether they repeat (DO_JUMP)."""
    if spec.route == "transit":
        psi = math.radians(HOME[3])
        return [(d * math.cos(psi), d * math.sin(psi)) for d in (1000.0, 10000.0, 20000.0, 30000.0)], False
    return racetrack(spec), True


def racetrack(spec: MissionSpec) -> list[tuple[float, float]]:
    """The racetrack's corners (north, east from home, m): legs along the runway heading, offset to its left, so
    that the crosswind of a west wind lies across the long legs."""
    psi = math.radians(HOME[3])
    fwd, left = np.array([math.cos(psi), math.sin(psi)]), np.array([math.sin(psi), -math.cos(psi)])
    start = 600.0 * fwd
    corners = [start, start + spec.leg_m * fwd, start + spec.leg_m * fwd + spec.width_m * left,
               start + spec.width_m * left]
    return [(float(c[0]), float(c[1])) for c in corners]


# ------------------------------------------------------------------------------------------------ processes
def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_instance(rng: np.random.Generator) -> int:
    """A SITL instance number whose TCP ports (SERIAL0, SERIAL2) are free."""
    for _ in range(200):
        i = int(rng.integers(5, 300))
        if all(_port_free(SERIAL0_TCP_BASE + 10 * i + k) for k in (0, 2)):
            return i
    raise RuntimeError("no free SITL instance ports")


@contextlib.contextmanager
def started(cmd: Sequence[str], cwd: Path, log_path: Path, sig: int = signal.SIGINT
            ) -> Iterator[subprocess.Popen[bytes]]:
    """A process in its own folder, its output in ``log_path``, stopped by its id on leaving."""
    cwd.mkdir(parents=True, exist_ok=True)
    with open(log_path, "wb") as fh:
        p = subprocess.Popen(list(cmd), cwd=cwd, stdout=fh, stderr=subprocess.STDOUT,
                             env=dict(os.environ, PYTHONPATH=str(ROOT)))
        try:
            yield p
        finally:
            stop_process(p, sig)


# ------------------------------------------------------------------------------------------------ the ground station
class GroundStation:
    """The harness's MAVLink link to ArduPlane (SERIAL0): commands, parameters, mission, and the flight's logs."""

    def __init__(self, url: str, runlog: RunLog, timeout_s: float = PROCESS_START_TIMEOUT_S) -> None:
        end = time.monotonic() + timeout_s
        while True:  # the SITL listens only once it has started
            try:
                self.conn = mavutil.mavlink_connection(url, source_system=255, source_component=190,
                                                       dialect="ardupilotmega", autoreconnect=True)
                break
            except OSError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.2)
        self.runlog = runlog
        self.t_us = 0          # the autopilot's clock: the newest stamp received
        self.statustexts: list[tuple[int, str]] = []
        self.last: dict[str, Any] = {}
        self._att_us: int | None = None
        self._truth_us: int | None = None

    def wait_heartbeat(self, timeout_s: float) -> None:
        if self.conn.wait_heartbeat(timeout=timeout_s) is None:
            raise TimeoutError("no heartbeat from ArduPlane")

    # -------------------------------------------------------------- receiving
    def pump(self, timeout_s: float = 0.1) -> Any:
        """Read and log one message (None when none came within ``timeout_s``)."""
        msg = self.conn.recv_match(blocking=True, timeout=timeout_s)
        if msg is None:
            return None
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return None
        comp = msg.get_srcComponent()
        if hasattr(msg, "time_boot_ms") and comp == 1 and kind not in ("NAMED_VALUE_FLOAT",):
            self.t_us = max(self.t_us, int(msg.time_boot_ms) * 1000)
        self.last[kind] = msg
        w = self.runlog.write
        t = self.t_us
        if comp == COMPANION_COMPONENT:
            self._companion(msg, kind, t)
            return msg
        if kind == "ATTITUDE":
            self._att_us = int(msg.time_boot_ms) * 1000
            w("ap_attitude", {"t_us": self._att_us, "roll_rad": msg.roll, "pitch_rad": msg.pitch, "yaw_rad": msg.yaw})
        elif kind == "SIM_STATE":
            if self._att_us is None or self._att_us == self._truth_us:
                return msg
            self._truth_us = self._att_us
            w("truth", {"t_us": self._att_us, "lat_deg": msg.lat_int / 1e7, "lon_deg": msg.lon_int / 1e7,
                        "alt_m": msg.alt, "vel_n_m_s": msg.vn, "vel_e_m_s": msg.ve, "vel_d_m_s": msg.vd,
                        "roll_rad": msg.roll, "pitch_rad": msg.pitch, "yaw_rad": msg.yaw})
        elif kind == "GLOBAL_POSITION_INT":
            w("ap_position", {"t_us": int(msg.time_boot_ms) * 1000, "lat_deg": msg.lat / 1e7,
                              "lon_deg": msg.lon / 1e7, "alt_m": msg.alt / 1000.0,
                              "rel_alt_m": msg.relative_alt / 1000.0, "vel_n_m_s": msg.vx / 100.0,
                              "vel_e_m_s": msg.vy / 100.0})
        elif kind == "EKF_STATUS_REPORT":
            w("ekf_status", {"t_us": t, "flags": msg.flags, "velocity_variance": msg.velocity_variance,
                             "pos_horiz_variance": msg.pos_horiz_variance, "compass_variance": msg.compass_variance})
        elif kind == "GPS_RAW_INT":
            w("gps", {"t_us": t, "fix_type": msg.fix_type, "lat_deg": msg.lat / 1e7, "lon_deg": msg.lon / 1e7})
        elif kind == "WIND":
            w("ap_wind", {"t_us": t, "from_deg": msg.direction, "speed_m_s": msg.speed})
        elif kind == "STATUSTEXT":
            self.statustexts.append((t, str(msg.text)))
            w("statustext", {"t_us": t, "component": comp, "text": str(msg.text)})
            log.info("ArduPlane: %s", msg.text)
        return msg

    def _companion(self, msg: Any, kind: str, t: int) -> None:
        w = self.runlog.write
        if kind == "NAMED_VALUE_FLOAT":
            w("companion_named", {"t_us": t, "time_boot_ms": msg.time_boot_ms, "name": str(msg.name),
                                  "value": msg.value})
        elif kind == "WIND":
            w("companion_wind", {"t_us": t, "from_deg": msg.direction, "speed_m_s": msg.speed})
        elif kind == "VISION_POSITION_DELTA":
            d = msg.position_delta
            w("companion_velocity", {"t_us": t, "time_usec": msg.time_usec, "kind": kind,
                                     "dt_s": msg.time_delta_usec / 1e6, "x": d[0], "y": d[1], "z": d[2],
                                     "confidence": msg.confidence})
        elif kind == "VISION_SPEED_ESTIMATE":
            w("companion_velocity", {"t_us": t, "time_usec": msg.usec, "kind": kind, "dt_s": 0.0, "x": msg.x,
                                     "y": msg.y, "z": msg.z, "confidence": -1})
        elif kind == "ODOMETRY":
            w("companion_velocity", {"t_us": t, "time_usec": msg.time_usec, "kind": kind, "dt_s": 0.0, "x": msg.vx,
                                     "y": msg.vy, "z": msg.vz, "confidence": msg.quality})
        elif kind == "STATUSTEXT":
            self.statustexts.append((t, f"companion: {msg.text}"))
            w("statustext", {"t_us": t, "component": COMPANION_COMPONENT, "text": str(msg.text)})
            log.info("companion: %s", msg.text)

    def run_for(self, seconds: float) -> None:
        """Pump for ``seconds`` of the autopilot's clock."""
        end = self.t_us + int(seconds * 1e6)
        while self.t_us < end:
            self.pump()

    def wait_until(self, cond: Any, timeout_ap_s: float, what: str) -> None:
        end = self.t_us + int(timeout_ap_s * 1e6)
        wall_end = time.monotonic() + max(timeout_ap_s, 30.0) * 2
        while not cond():
            if self.t_us > end or time.monotonic() > wall_end:
                raise TimeoutError(f"{what}: not within {timeout_ap_s:.0f} s")
            self.pump()

    # -------------------------------------------------------------- commands
    def command(self, cmd: int, *params: float, timeout_s: float = 5.0) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        for _ in range(3):
            self.conn.mav.command_long_send(self.conn.target_system, 1, cmd, 0, *p)
            end = time.monotonic() + timeout_s / 3
            while time.monotonic() < end:
                m = self.pump(0.1)
                if m is not None and m.get_type() == "COMMAND_ACK" and m.command == cmd:
                    return int(m.result)
        return -1

    def set_param(self, name: str, value: float, timeout_s: float = 5.0) -> bool:
        for _ in range(3):
            self.conn.mav.param_set_send(self.conn.target_system, 1, name.encode(), float(value),
                                         mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
            end = time.monotonic() + timeout_s / 3
            while time.monotonic() < end:
                m = self.pump(0.1)
                if m is not None and m.get_type() == "PARAM_VALUE" and m.param_id == name:
                    return abs(m.param_value - value) < 1e-3 * max(1.0, abs(value))
        return False

    def rc7_override(self, pwm: int) -> None:
        ignore = RC_OVERRIDE_IGNORE
        self.conn.mav.rc_channels_override_send(self.conn.target_system, 1, ignore, ignore, ignore, ignore, ignore,
                                                ignore, pwm, ignore)

    def request_rates(self, rates: dict[str, float]) -> None:
        for name, hz in rates.items():
            self.command(MAV_CMD_SET_MESSAGE_INTERVAL, MSG_IDS[name], 1e6 / hz)

    def upload_mission(self, spec: MissionSpec) -> None:
        ml = mavutil.mavlink
        lat0, lon0 = HOME[0], HOME[1]
        items: list[tuple[int, float, float, float, float]] = [(ml.MAV_CMD_NAV_WAYPOINT, 0, 0, 0, 0)]
        items.append((ml.MAV_CMD_NAV_TAKEOFF, 15.0, 0, 0, spec.alt_m))
        points, repeat = route_points(spec)
        for n, e in points:
            items.append((ml.MAV_CMD_NAV_WAYPOINT, 0, n, e, spec.alt_m))
        if repeat:
            items.append((ml.MAV_CMD_DO_JUMP, 2, -1, 0, 0))
        ts = self.conn.target_system
        self.conn.mav.mission_count_send(ts, 1, len(items), 0)
        end = time.monotonic() + 30.0
        while time.monotonic() < end:
            r = self.pump(0.2)
            if r is None:
                continue
            kind = r.get_type()
            if kind == "MISSION_ACK":
                if r.type != 0:
                    raise RuntimeError(f"mission refused: MISSION_ACK {r.type}")
                return
            if kind not in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
                continue
            cmd, p1, n, e, alt = items[r.seq]
            if cmd == ml.MAV_CMD_DO_JUMP:
                self.conn.mav.mission_item_int_send(ts, 1, r.seq, ml.MAV_FRAME_GLOBAL_RELATIVE_ALT, cmd, 0, 1, p1, n,
                                                    0, 0, 0, 0, 0, 0)
                continue
            lat, lon = lat_lon_of(n, e, lat0, lon0)
            self.conn.mav.mission_item_int_send(ts, 1, r.seq, ml.MAV_FRAME_GLOBAL_RELATIVE_ALT, cmd, 0, 1, p1, 0, 0,
                                                0, int(lat * 1e7), int(lon * 1e7), alt, 0)
        raise TimeoutError("mission upload did not finish")

    def close(self) -> None:
        self.conn.close()


# ------------------------------------------------------------------------------------------------ one flight
def fly_mission(spec: MissionSpec, out_dir: Path, seed: int = 0) -> dict[str, Any]:
    """Fly one mission (module docstring) into ``out_dir``; returns :func:`mission_metrics` (also written to
    ``out_dir/metrics.json``)."""
    if not ARDUPLANE.exists():
        raise FileNotFoundError(ARDUPLANE)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, os.getpid()])  # flights at once: other instances, other ports
    companion_udp = free_port(socket.SOCK_DGRAM)
    parm = out_dir / "mission.parm"
    parm.write_text("".join(f"{k} {v}\n" for k, v in sitl_parameters(spec).items()))
    (out_dir / "spec.json").write_text(json.dumps(asdict(spec), indent=1))
    home = ",".join(str(v) for v in HOME)
    ap_cmd = [str(ARDUPLANE), "--model", "plane", "--speedup", f"{spec.speedup:g}", "--defaults",
              f"{PLANE_PARM},{parm}", "--home", home, "--serial1", f"udpclient:127.0.0.1:{companion_udp}"]
    port_file = out_dir / "bridge" / "frame_port"
    bridge_cmd = [PY, "-m", "sim.sitl_camera", "--frame-hz",
                  f"{spec.frame_hz:g}", "--port-file", str(port_file), "--seed", str(seed)]
    if spec.oracle_confidence >= 0 and spec.extnav:
        bridge_cmd += ["--oracle-velocity-hz", "10", "--oracle-confidence", str(spec.oracle_confidence)]
    if spec.mount_yaw_error_deg:
        bridge_cmd += ["--mount-yaw-error-deg", f"{spec.mount_yaw_error_deg:g}"]
    wall_limit_s = spec.timeout_factor * (spec.flight_s / spec.speedup + 120.0)
    t_start = time.monotonic()
    runlog = RunLog(out_dir / "harness")
    ok = False
    try:
        with arduplane_started(ap_cmd, out_dir, rng, runlog) as gcs:
            try:
                gcs.wait_heartbeat(PROCESS_START_TIMEOUT_S)
                gcs.request_rates(HARNESS_RATES)
                serial2 = _serial_port(out_dir / "arduplane.log", 2, PROCESS_START_TIMEOUT_S)
                bridge_cmd += ["--connect", f"tcp:127.0.0.1:{serial2}"]
                with started(bridge_cmd, out_dir / "bridge", out_dir / "bridge.log"):
                    frame_port = _wait_port(port_file, PROCESS_START_TIMEOUT_S)
                    comp_cmd = [PY, "-m", "cli", "companion", "--connect", f"udpin://127.0.0.1:{companion_udp}",
                                "--camera", f"sim://127.0.0.1:{frame_port}", "--log-dir", str(out_dir / "companion")]
                    for s in companion_settings(spec):
                        comp_cmd += ["--set", s]
                    with started(comp_cmd, out_dir / "companion_run", out_dir / "companion.log"):
                        _fly(gcs, spec, runlog, t_start, wall_limit_s)
                        ok = True
            finally:
                gcs.close()
    finally:
        runlog.close()
    metrics = mission_metrics(out_dir, spec)
    metrics["completed"] = ok
    metrics["wall_s"] = time.monotonic() - t_start
    write_metrics(out_dir, metrics)
    return metrics


@contextlib.contextmanager
def arduplane_started(cmd: Sequence[str], out_dir: Path, rng: np.random.Generator, runlog: RunLog
                      ) -> Iterator[GroundStation]:
    """ArduPlane SITL (``cmd`` without its ``-I``) on a free instance, and the ground station connected to its
    SERIAL0.  A SITL that exits, or whose SERIAL0 accepts no connection within :data:`SITL_CONNECT_TIMEOUT_S`
    (seen in two-worker test runs: the port listening, every connection refused), is stopped and started again on
    another instance, :data:`SITL_START_ATTEMPTS` times at most."""
    log_path = out_dir / "arduplane.log"
    for attempt in range(1, SITL_START_ATTEMPTS + 1):
        inst = free_instance(rng)
        with started([*cmd, f"-I{inst}"], out_dir / "arduplane", log_path, signal.SIGTERM) as p:
            try:
                port = _serial_port(log_path, 0, SITL_CONNECT_TIMEOUT_S, p)
                gcs = GroundStation(f"tcp:127.0.0.1:{port}", runlog, SITL_CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError) as e:
                tail = log_path.read_text(errors="replace").strip().splitlines()[-3:]
                log.warning("ArduPlane SITL instance %d (attempt %d of %d): %s; its log ends %s", inst, attempt,
                            SITL_START_ATTEMPTS, e, tail)
                if attempt == SITL_START_ATTEMPTS:
                    raise
                continue
            yield gcs
            return


def _serial_port(sitl_log: Path, serial: int, timeout_s: float, process: subprocess.Popen[bytes] | None = None
                 ) -> int:
    """The TCP port the SITL opened for SERIAL``serial`` (its log says ``SERIALn on TCP port P``)."""
    pat = re.compile(rf"SERIAL{serial} on TCP port (\d+)")
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        m = pat.search(sitl_log.read_text(errors="replace")) if sitl_log.exists() else None
        if m:
            return int(m.group(1))
        if process is not None and process.poll() is not None:
            raise TimeoutError(f"the SITL exited ({process.returncode}) before it opened SERIAL{serial}")
        time.sleep(0.2)
    raise TimeoutError(f"the SITL opened no TCP port for SERIAL{serial} within {timeout_s:.0f} s")


def _wait_port(path: Path, timeout_s: float) -> int:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if path.exists():
            return int(path.read_text().strip())
        time.sleep(0.1)
    raise TimeoutError(f"{path} not written within {timeout_s:.0f} s")


def _fly(gcs: GroundStation, spec: MissionSpec, runlog: RunLog, t_start: float, wall_limit_s: float) -> None:
    def check_wall() -> None:
        if time.monotonic() - t_start > wall_limit_s:
            raise TimeoutError(f"flight exceeded its wall-clock limit of {wall_limit_s:.0f} s")

    gcs.wait_until(lambda: any("using GPS" in s for _, s in gcs.statustexts) and gcs.t_us > 0, EKF_READY_TIMEOUT_S,
                   "EKF using GPS")
    gcs.run_for(5.0)
    gcs.upload_mission(spec)
    if gcs.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, FORCE_ARM_MAGIC) != 0:
        raise RuntimeError("ArduPlane refused to arm")
    if gcs.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, ARDUPLANE_MODE_AUTO) != 0:
        raise RuntimeError("ArduPlane refused AUTO")
    runlog.write("events", {"t_us": gcs.t_us, "event": "auto"})
    gcs.wait_until(lambda: "GLOBAL_POSITION_INT" in gcs.last and gcs.last["GLOBAL_POSITION_INT"].relative_alt
                   > 0.9e3 * spec.alt_m, 180.0, "take-off to the mission altitude")
    runlog.write("events", {"t_us": gcs.t_us, "event": "at_altitude"})
    end_on = gcs.t_us + int(spec.gnss_on_s * 1e6)
    while gcs.t_us < end_on:
        gcs.pump()
        check_wall()
    if not gcs.set_param(IN_FLIGHT_PARAMETERS[0], 0):
        raise RuntimeError("SIM_GPS1_ENABLE not set")
    runlog.write("events", {"t_us": gcs.t_us, "event": "gnss_off"})
    rc = spec.extnav and spec.source_switch == "rc"
    if spec.extnav and not rc:
        r = gcs.command(MAV_CMD_SET_EKF_SOURCE_SET, 2)
        runlog.write("events", {"t_us": gcs.t_us, "event": f"source_set_2 ack {r}"})
    elif rc:
        runlog.write("events", {"t_us": gcs.t_us, "event": "source_set_2 rc7"})
    end = gcs.t_us + int(spec.denied_s * 1e6)
    next_rc = 0.0
    while gcs.t_us < end:
        if rc and time.monotonic() >= next_rc:  # an override lapses after RC_OVERRIDE_TIME: keep it up
            gcs.rc7_override(RC_MID_PWM)
            next_rc = time.monotonic() + RC_OVERRIDE_PERIOD_S
        gcs.pump()
        check_wall()
    runlog.write("events", {"t_us": gcs.t_us, "event": "end"})
    runlog.flush()


# ------------------------------------------------------------------------------------------------ figures
def _interp_angle(t: NDArray[np.float64], tt: NDArray[np.float64], a: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.asarray(wrap_pi(np.interp(t, tt, np.unwrap(a))), dtype=float)


def mission_metrics(out_dir: Path, spec: MissionSpec) -> dict[str, Any]:
    """The flight's figures from the harness logs (module docstring); missing logs give empty sections."""
    h = out_dir / "harness"
    m: dict[str, Any] = {"spec": asdict(spec)}
    try:
        truth = read_log(h / "truth.csv")
        events = read_log(h / "events.csv")
    except (FileNotFoundError, ValueError) as e:
        m["error"] = f"no flight log: {e}"
        return m
    ev = {str(k).split(" ")[0]: float(t) for k, t in zip(events["event"], events["t_us"], strict=True)}
    tt = np.asarray(truth["t_us"], dtype=float)
    order = np.argsort(tt)
    tt = tt[order]
    tr = {k: np.asarray(v, dtype=float)[order] for k, v in truth.items() if k != "t_us"}
    lat0, lon0 = HOME[0], HOME[1]
    tn, te = ne_of(tr["lat_deg"], tr["lon_deg"], lat0, lon0)
    ground = float(np.median(tr["alt_m"][: max(5, len(tt) // 50)]))
    airborne = tt[(tr["alt_m"] - ground) > LIFTOFF_M]
    liftoff = float(airborne[0]) if airborne.size else math.nan
    m["times_s"] = {k: ev.get(k, math.nan) / 1e6 for k in ("auto", "at_altitude", "gnss_off", "end")}
    m["times_s"]["liftoff"] = liftoff / 1e6
    true_course = np.arctan2(tr["vel_e_m_s"], tr["vel_n_m_s"])
    true_drift = np.asarray(wrap_pi(true_course - tr["yaw_rad"]), dtype=float)
    m["companion"] = _companion_figures(h, spec, tt, true_drift, tr, ev, liftoff)
    m["denied"] = _denied_figures(h, tt, tn, te, tr, ev)
    return m


def _companion_figures(h: Path, spec: MissionSpec, tt: NDArray[np.float64], true_drift: NDArray[np.float64],
                       tr: dict[str, NDArray[np.float64]], ev: dict[str, float], liftoff: float) -> dict[str, Any]:
    out: dict[str, Any] = {}
    try:
        named = read_log(h / "companion_named.csv")
    except (FileNotFoundError, ValueError):
        return {"error": "the companion sent nothing ArduPlane forwarded"}
    names = np.asarray(named["name"]).astype(str)
    t_recv = np.asarray(named["t_us"], dtype=float)
    valid = (names == "GSOE_VALID") & (np.asarray(named["value"], dtype=float) > 0.5)
    first_valid = float(t_recv[valid][0]) if valid.any() else math.nan
    out["first_valid_s"] = first_valid / 1e6
    out["valid_after_liftoff_s"] = (first_valid - liftoff) / 1e6
    out["valid_after_auto_s"] = (first_valid - ev.get("auto", math.nan)) / 1e6
    sel = names == "GSOE_DRIFT"
    t_d = np.asarray(named["time_boot_ms"], dtype=float)[sel] * 1000.0
    drift = np.radians(np.asarray(named["value"], dtype=float)[sel])
    airborne_speed = np.hypot(tr["vel_n_m_s"], tr["vel_e_m_s"]) > 10.0
    gnss_off = ev.get("gnss_off", math.inf)
    on = (t_d > ev.get("at_altitude", liftoff)) & (t_d < gnss_off) & (t_d > tt[0]) & (t_d < tt[-1])
    if on.any():
        err = np.degrees(np.asarray(wrap_pi(drift[on] - _interp_angle(t_d[on], tt, true_drift)), dtype=float))
        fast = np.interp(t_d[on], tt, airborne_speed.astype(float)) > 0.5
        err = err[fast]
        out["drift_gnss_on"] = {"n": int(err.size), "mean_abs_deg": float(np.mean(np.abs(err))),
                                "mean_deg": float(np.mean(err)), "rms_deg": float(np.sqrt(np.mean(err ** 2))),
                                "p95_abs_deg": float(np.percentile(np.abs(err), 95))}
    off = (t_d > gnss_off) & (t_d < tt[-1])
    if off.any():
        err = np.degrees(np.asarray(wrap_pi(drift[off] - _interp_angle(t_d[off], tt, true_drift)), dtype=float))
        out["drift_denied"] = {"n": int(err.size), "mean_abs_deg": float(np.mean(np.abs(err))),
                               "mean_deg": float(np.mean(err))}
    try:
        wind = read_log(h / "companion_wind.csv")
    except (FileNotFoundError, ValueError):
        return out
    tw = np.asarray(wind["t_us"], dtype=float)
    for leg, sel_w in (("gnss_on", (tw > ev.get("at_altitude", math.inf)) & (tw < gnss_off)),
                       ("denied", tw > gnss_off + 30e6)):
        if not sel_w.any():
            continue
        sp = np.asarray(wind["speed_m_s"], dtype=float)[sel_w]
        fr = np.asarray(wind["from_deg"], dtype=float)[sel_w]
        dir_err = (fr - spec.wind_from_deg + 180.0) % 360.0 - 180.0
        out[f"wind_{leg}"] = {"n": int(sp.size), "speed_mean_m_s": float(np.mean(sp)),
                              "speed_err_mean_abs_m_s": float(np.mean(np.abs(sp - spec.wind_speed_m_s))),
                              "speed_err_mean_m_s": float(np.mean(sp - spec.wind_speed_m_s)),
                              "from_mean_deg": float(wrap_360(spec.wind_from_deg + np.mean(dir_err))),
                              "dir_err_mean_abs_deg": float(np.mean(np.abs(dir_err))),
                              "dir_err_mean_deg": float(np.mean(dir_err))}
    return out


def _denied_figures(h: Path, tt: NDArray[np.float64], tn: NDArray[np.float64], te: NDArray[np.float64],
                    tr: dict[str, NDArray[np.float64]], ev: dict[str, float]) -> dict[str, Any]:
    t_off, t_end = ev.get("gnss_off", math.nan), ev.get("end", math.nan)
    if not (math.isfinite(t_off) and math.isfinite(t_end)):
        return {}
    try:
        pos = read_log(h / "ap_position.csv")
        att = read_log(h / "ap_attitude.csv")
    except (FileNotFoundError, ValueError):
        return {}
    tp = np.asarray(pos["t_us"], dtype=float)
    an, ae = ne_of(np.asarray(pos["lat_deg"], dtype=float), np.asarray(pos["lon_deg"], dtype=float), HOME[0],
                   HOME[1])
    sel = (tp >= t_off) & (tp <= t_end) & (tp >= tt[0]) & (tp <= tt[-1])
    if not sel.any():
        return {}
    err = np.hypot(np.asarray(an)[sel] - np.interp(tp[sel], tt, tn), np.asarray(ae)[sel] - np.interp(tp[sel], tt, te))
    seg = (tt >= t_off) & (tt <= t_end)
    dist = float(np.sum(np.hypot(np.diff(tn[seg]), np.diff(te[seg]))))
    ta = np.asarray(att["t_us"], dtype=float)
    sa = (ta >= t_off) & (ta <= t_end) & (ta >= tt[0]) & (ta <= tt[-1])
    hdg = np.degrees(np.asarray(wrap_pi(np.asarray(att["yaw_rad"], dtype=float)[sa]
                                        - _interp_angle(ta[sa], tt, tr["yaw_rad"])), dtype=float))
    t_rel = (tp[sel] - t_off) / 1e6
    series = []
    for k in range(0, int(t_rel[-1]) + 1, 10):
        i = int(np.searchsorted(t_rel, k))
        if i < t_rel.size:
            j = int(np.searchsorted((ta[sa] - t_off) / 1e6, k))
            h_k = round(float(hdg[min(j, hdg.size - 1)]), 2) if hdg.size else None
            series.append([k, round(float(err[i]), 1), h_k])
    out: dict[str, Any] = {"duration_s": (t_end - t_off) / 1e6, "distance_flown_m": dist,
                           "ap_pos_err_end_m": float(err[-1]), "ap_pos_err_max_m": float(np.max(err)),
                           "ap_pos_err_end_pct_of_distance": 100.0 * float(err[-1]) / max(dist, 1.0),
                           "ap_heading_err_mean_deg": float(np.mean(hdg)) if hdg.size else None,
                           "ap_heading_err_mean_abs_deg": float(np.mean(np.abs(hdg))) if hdg.size else None,
                           "ap_heading_err_end_deg": float(hdg[-1]) if hdg.size else None,
                           "ap_heading_err_max_abs_deg": float(np.max(np.abs(hdg))) if hdg.size else None,
                           "series_t_err_m_heading_err_deg": series}
    with contextlib.suppress(FileNotFoundError, ValueError):
        st = read_log(h / "statustext.csv")
        texts = [str(x) for x in st["text"]]
        out["ekf_messages"] = sorted({x for x in texts if "EKF3" in x or "fusing" in x or "odometry" in x.lower()})
    return out


# ------------------------------------------------------------------------------------------------ command line
def compare(with_extnav: dict[str, Any], dr_alone: dict[str, Any]) -> dict[str, Any]:
    a, b = with_extnav.get("denied", {}), dr_alone.get("denied", {})
    ea, eb = a.get("ap_pos_err_end_m"), b.get("ap_pos_err_end_m")
    return {"extnav_err_end_m": ea, "dr_alone_err_end_m": eb,
            "improvement_factor": (eb / ea) if ea and eb else None}


def _param(text: str) -> tuple[str, float]:
    try:
        name, value = text.split("=")
        return name.strip().upper(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="GNSS-denied leg, autopilot seconds")
    ap.add_argument("--gnss-on-s", type=float, default=120.0, help="flight with GNSS after take-off")
    ap.add_argument("--speedup", type=float, default=2.0, help="SITL --speedup (the companion must keep up)")
    ap.add_argument("--velocity-message", default=MissionSpec.velocity_message,
                    choices=("vision_position_delta", "vision_speed_estimate", "odometry"))
    ap.add_argument("--compare-dr", action="store_true", help="fly again with ArduPlane dead-reckoning alone")
    ap.add_argument("--no-extnav", action="store_true", help="only the dead-reckoning flight")
    ap.add_argument("--viso-delay-ms", type=int, default=MissionSpec.viso_delay_ms)
    ap.add_argument("--viso-vel-m-nse", type=float, default=MissionSpec.viso_vel_m_nse)
    ap.add_argument("--set", action="append", default=[], dest="settings", help="companion --set override")
    ap.add_argument("--oracle", type=int, default=-1, metavar="CONFIDENCE",
                    help="experiment: the truth's body velocity instead of the companion's, at this confidence")
    ap.add_argument("--source-switch", choices=("command", "rc"), default="command",
                    help="switch to EKF source set 2 by MAV_CMD_SET_EKF_SOURCE_SET or by RC7 (RC7_OPTION 90)")
    ap.add_argument("--param", action="append", default=[], type=_param, dest="ap_params",
                    help="experiment: another ArduPlane parameter NAME=VALUE (repeatable)")
    ap.add_argument("--route", choices=("racetrack", "transit"), default="racetrack",
                    help="laps of a racetrack, or a straight line away from home")
    ap.add_argument("--mount-yaw-error-deg", type=float, default=0.0,
                    help="the camera bridge renders the camera turned this much further in yaw than its file says")
    ap.add_argument("--calibration-flight", action="store_true",
                    help="leave the companion's optical rotation free (a flight for gsoe calibrate-mount)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/sitl_mission")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    spec = MissionSpec(denied_s=args.duration, gnss_on_s=args.gnss_on_s, speedup=args.speedup,
                       velocity_message=args.velocity_message, extnav=not args.no_extnav,
                       viso_delay_ms=args.viso_delay_ms, viso_vel_m_nse=args.viso_vel_m_nse,
                       companion_settings=tuple(args.settings), oracle_confidence=args.oracle,
                       source_switch=args.source_switch, ap_params=tuple(args.ap_params), route=args.route,
                       mount_yaw_error_deg=args.mount_yaw_error_deg, mount_calibrated=not args.calibration_flight)
    out = Path(args.out)
    results: dict[str, Any] = {}
    results["extnav" if spec.extnav else "dr_alone"] = fly_mission(spec, out / ("extnav" if spec.extnav
                                                                                else "dr_alone"), args.seed)
    if args.compare_dr and spec.extnav:
        results["dr_alone"] = fly_mission(replace(spec, extnav=False), out / "dr_alone", args.seed)
        results["comparison"] = compare(results["extnav"], results["dr_alone"])
        write_metrics(out, results)
    print(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
