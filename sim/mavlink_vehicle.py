"""The simulator acting as the vehicle: an ArduPlane-like MAVLink endpoint over UDP on 127.0.0.1 (pymavlink).

What it speaks (MAVLink 2, ``ardupilotmega`` dialect, system 1 / component 1):

============================  =======  ====================================================================
message                       rate Hz  content
============================  =======  ====================================================================
HEARTBEAT                     1        MAV_TYPE_FIXED_WING, MAV_AUTOPILOT_ARDUPILOTMEGA, custom mode GUIDED (15)
ATTITUDE                      50       the AHRS attitude sample (its own stamp) and the mean gyro rates
RAW_IMU, SCALED_IMU           50       mean accelerometer (mG) and gyro (mrad/s) over the period, FRD
SCALED_PRESSURE               10       static pressure (hPa, ISA at the baro altitude), airspeed dynamic pressure
VFR_HUD                       10       pitot airspeed, groundspeed, heading, baro altitude, climb
GPS_RAW_INT                   5        each receiver sample: fix, satellites, position, velocity, accuracies
                                       (fix type 1 / 0 satellites in an outage)
GLOBAL_POSITION_INT           10       the autopilot's position: last fix, altitude from the baro over home
CAMERA_TRACKING_IMAGE_STATUS  10       the tracking-camera hook (below), only with a target
============================  =======  ====================================================================

Every sensor sample carries its own stamp on the vehicle clock (``time_boot``): the simulation time.

Dynamics (``VehicleConfig.dynamics``)
    ``"jsbsim"``: :class:`sim.dynamics.FlightDynamics` (the project's JSBSim Talon-class airframe, the wind of
    :mod:`sim.wind`), flown by :class:`sim.autopilot.Autopilot` in heading hold, sensed by
    :class:`sim.sensors.SensorSuite` with the true sensor errors drawn from a scenario's distributions
    (``VehicleConfig.scenario``, default ``paper_sil``; its mission and GNSS outages are not used, its wind is
    replaced by ``wind_ned_m_s`` at every height, turbulence on request).  This is the SIL vehicle.
    With ``fly_scenario`` (``--fly-scenario``) it flies the scenario itself instead, as ``gsoe sim`` does
    (:func:`sim.flight.build_flight`: the mission from its start state, in AUTO mode, so heading commands are
    refused; its wind with shear, turbulence and gusts; its GNSS outages; its ground texture; run_flight's
    seeding from ``--seed``, so that ``gsoe sim`` on the same seed flies the same truth with the same sensor errors).
    ``"kinematic"``: :class:`KinematicPlane`, a coordinated-turn point mass at constant airspeed and height in a
    steady wind, with ideal airspeed and baro and white IMU/GNSS noise: a light vehicle for link tests.

Commands
    ``COMMAND_LONG`` ``MAV_CMD_GUIDED_CHANGE_HEADING`` (43002, heading type 0/1, param2 heading deg, param3 lateral
    acceleration limit m/s^2) is flown in GUIDED mode (ACK ACCEPTED): the JSBSim autopilot's heading hold at the
    configured height and airspeed (its own 45 deg roll limit; param3 is not applied there), the kinematic plane's
    bank-limited heading hold (param3 applied).  Heading type 0 (course) is flown as a heading, as ArduPlane without
    GNSS has no course to close the loop on.  ``MAV_CMD_REQUEST_MESSAGE`` for AUTOPILOT_VERSION is answered with
    :data:`VEHICLE_FIRMWARE` (the ArduPlane whose behaviour the vehicle follows).  Other commands are acknowledged
    UNSUPPORTED.  Every received message
    is counted, the last one of each type kept, and every value the companion sent is checked
    (:func:`received_problems`): the summary lists anything non-finite or out of range that reached the vehicle.

Camera frames (belly camera, rendered by :class:`sim.render.CameraRenderer` over :data:`DEFAULT_TEXTURE` or the
given ``texture``, only the region around the nadir the optical estimator samples; the rest of the frame is black)
are streamed over TCP on 127.0.0.1 to one client at a time, ``frame_latency_s`` after their exposure (a camera
pipeline's delay), in the frame-stream format of :mod:`common.framestream` (a 24-byte header: magic, exposure
time ``t_us`` on the vehicle clock, width, height, channels; then the uint8 image).  A slow client drops frames
rather than stalling the vehicle.

Tracking-camera hook (documented test hook, used by the SIL guidance tests)
    With ``target_ned_m`` set, the vehicle plays an external video tracker: the target's true position is
    projected into a *forward tracking camera* (the configured camera's lens mounted looking forward,
    ``tracking_depression_deg`` below the body x axis: :func:`gsoe.camera.forward_camera`) at the true attitude,
    seeded pixel noise of ``tracker_noise_px`` is added, and the result is sent as MAVLink
    ``CAMERA_TRACKING_IMAGE_STATUS`` (tracking status ACTIVE, mode POINT, ``point_x``/``point_y`` normalised 0..1:
    ``x = (column + 0.5) / width``) at ``TRACK`` rate; when the target is outside that camera's image the status
    is IDLE with a NaN point.  It stands for an image tracker (the companion's ``[companion.tracking] source =
    "mavlink"``): rendering a forward camera at 2 km for a template tracker is beyond this simulator's budget, and
    the belly fisheye only sees about 100 m ahead.

GNSS outages: the windows ``gnss_outages_s`` and, with ``gnss_outage_range_m`` > 0 and a target, from the moment
the aircraft first comes within that horizontal range of the target until the end ("GNSS denied from 2 km out").

Faults (``VehicleConfig.faults``, each ``(kind, start_s, end_s)`` on the simulation clock), for the fault tests:
``frozen_frames`` (the last image again with new stamps), ``black_frames``, ``saturated_frames``,
``wrong_size_frames`` (half size), ``corrupt_frames`` (blocks of random bytes in the image), ``corrupt_stream``
(one garbage header, so the client must resynchronise by reconnecting), ``camera_off`` (the frame server closes,
connections are refused), ``link_silence`` (no MAVLink sent, received messages discarded), ``bad_telemetry``
(ATTITUDE, VFR_HUD and SCALED_PRESSURE carry NaN, infinite or out-of-range values in turn, SCALED_IMU a 32 g
acceleration), ``time_backwards`` (the vehicle clock steps back ``time_jump_s`` for the window: every stamp,
frames included), ``gnss_jump`` (a good fix ``gnss_jump_m`` north of the truth: spoofing), ``mavlink_fuzz``
(``fuzz_count`` random MAVLink frames spread over the window, sent to the companion from the vehicle's socket:
random bytes, and well-formed messages of random types with random field values).

A ground station (``gcs_url``) receives the vehicle's telemetry and everything the companion sends the vehicle, as
an autopilot routes MAVLink between its links.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import socket
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from common.angles import angle_diff, wrap_2pi, wrap_360, wrap_pi
from common.atmosphere import KELVIN_AT_0_C, LAPSE_K_M, RHO0_KG_M3, T0_K, eas_to_tas_ratio, isa_pressure_pa
from common.framestream import encode_frame
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
from sim.sensors import CameraFrame, SensorReadings
from sim.truth import TruthState

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402  (MAVLINK20 must be set before import)

log = logging.getLogger(__name__)

GRAVITY_M_S2 = 9.80665
EARTH_RADIUS_M = 6371008.8  # mean Earth radius: local flat-earth conversion of NED offsets to lat/lon
#: the ArduPlane version the vehicle answers AUTOPILOT_VERSION with (an ArduPlane 4.x: baro clamp 35 degC)
VEHICLE_FIRMWARE = (4, 5, 7)
ARDUPLANE_MODE_GUIDED = 15
ARDUPLANE_MODE_AUTO = 10
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4
UINT16_UNKNOWN = 65535
# Ground texture of the SIL flights: textured along any track (about 98 % valid matches at 100 m AGL); the paper_sil
# scenario's "mosaic" has long low-texture stretches where the optical estimate rightly goes invalid.
DEFAULT_TEXTURE = "forest_road"
# Stabilised base image footprint -> rendered region: the cone around the nadir the estimator samples (half the
# base image's diagonal over the virtual focal length) grown by this factor, plus a margin in pixels.
ROI_CONE_FACTOR = 1.4
ROI_MARGIN_PX = 8
ROI_RING_RAYS = 24
# After overflight: the closest approach is final once the range has grown this far past it.
PASS_MARGIN_M = 50.0
# Plausibility limits for what the companion sends (a value beyond them reaching the vehicle is a defect).
MAX_SPEED_M_S = 100.0
MAX_DRIFT_DEG = 90.0
# Bad-telemetry fault: out-of-range values the companion must reject.
BAD_ROLL_RAD = 10.0
BAD_AIRSPEED_M_S = 400.0
BAD_PRESSURE_HPA = 5.0        # ~36 km pressure altitude
BAD_ACCEL_MG = 32000          # 32 g
FAULT_KINDS = ("frozen_frames", "black_frames", "saturated_frames", "wrong_size_frames", "corrupt_frames",
               "corrupt_stream", "camera_off", "link_silence", "bad_telemetry", "time_backwards", "gnss_jump",
               "mavlink_fuzz")
OUTPUT_TYPES = ("NAMED_VALUE_FLOAT", "VISION_SPEED_ESTIMATE", "VISION_POSITION_DELTA", "ODOMETRY", "WIND_COV", "WIND",
                "STATUSTEXT", "COMMAND_LONG", "DEBUG_VECT")


@dataclass(frozen=True)
class Fault:
    """A fault injected between ``start_s`` and ``end_s`` (simulation clock); kinds in :data:`FAULT_KINDS`."""

    kind: str
    start_s: float
    end_s: float

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"fault kind {self.kind!r} unknown (known: {', '.join(FAULT_KINDS)})")
        if not (math.isfinite(self.start_s) and math.isfinite(self.end_s) and 0.0 <= self.start_s < self.end_s):
            raise ValueError(f"fault {self.kind}: need 0 <= start_s < end_s, got {self.start_s}, {self.end_s}")

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.end_s


@dataclass(frozen=True)
class VehicleConfig:
    """Vehicle simulation settings (units in the names; see the module docstring for what each part does)."""

    dynamics: Literal["kinematic", "jsbsim"] = "kinematic"
    scenario: str = "paper_sil"
    turbulence: bool = False
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
    gnss_alt_acc_m: float = 2.0
    gnss_outages_s: tuple[tuple[float, float], ...] = ()
    gnss_outage_range_m: float = 0.0
    target_ned_m: tuple[float, float] | None = None
    tracking_depression_deg: float = 10.0
    tracker_noise_px: float = 0.5
    texture: str | None = None
    frame_noise_std: float | None = None
    frame_latency_s: float = 0.04
    faults: tuple[Fault, ...] = ()
    time_jump_s: float = 1.0
    gnss_jump_m: float = 300.0
    fuzz_count: int = 10_000
    config_path: str | None = None
    fly_scenario: bool = False
    truth_log_dir: str | None = None
    rates_hz: dict[str, float] = field(default_factory=lambda: {
        "HEARTBEAT": 1.0, "ATTITUDE": 50.0, "IMU": 50.0, "SCALED_PRESSURE": 10.0, "VFR_HUD": 10.0,
        "GPS_RAW_INT": 5.0, "GLOBAL_POSITION_INT": 10.0, "FRAME": 30.0, "TRACK": 10.0})

    def __post_init__(self) -> None:
        checks = {"tas_m_s": (5.0, 60.0), "height_agl_m": (10.0, 3000.0), "dt_s": (1e-4, 0.05),
                  "frame_latency_s": (0.0, 1.0), "tracker_noise_px": (0.0, 100.0), "time_jump_s": (0.0, 3600.0),
                  "gnss_outage_range_m": (0.0, 1e6), "tracking_depression_deg": (-45.0, 89.0)}
        for name, (lo, hi) in checks.items():
            v = getattr(self, name)
            if not (math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"VehicleConfig.{name} must be in [{lo}, {hi}], got {v!r}")
        if self.gnss_outage_range_m > 0 and self.target_ned_m is None:
            raise ValueError("VehicleConfig.gnss_outage_range_m needs target_ned_m")
        if self.fly_scenario and self.dynamics != "jsbsim":
            raise ValueError("VehicleConfig.fly_scenario needs dynamics = 'jsbsim'")


# ------------------------------------------------------------------------------------------------ dynamics
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


class Plant(Protocol):
    """Dynamics plus sensors: one :meth:`step` of :attr:`dt_s` gives the truth and the sensor samples due."""

    dt_s: float
    texture: str
    frame_noise_std: float
    exposure_s: float

    def step(self) -> tuple[TruthState, SensorReadings]: ...

    def command_heading(self, heading_rad: float, accel_limit_m_s2: float) -> None: ...


class _Every:
    """Samples due at ``rate_hz`` on the simulation clock (the first at t = 0)."""

    def __init__(self, rate_hz: float) -> None:
        self.period_s = 1.0 / rate_hz if rate_hz > 0 else math.inf
        self.next_s = 0.0

    def due(self, t_s: float) -> bool:
        if t_s + 1e-9 < self.next_s:
            return False
        self.next_s += self.period_s
        if self.next_s < t_s:
            self.next_s = t_s + self.period_s
        return True


class KinematicPlant:
    """:class:`KinematicPlane` with ideal airspeed and baro, white gyro/accelerometer noise and GNSS noise."""

    def __init__(self, cfg: VehicleConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng
        self.plane = KinematicPlane(cfg)
        self.dt_s = cfg.dt_s
        self.texture = cfg.texture or DEFAULT_TEXTURE
        self.frame_noise_std = 1.0 if cfg.frame_noise_std is None else cfg.frame_noise_std
        self.exposure_s = 0.0
        r = cfg.rates_hz
        self._sched = {k: _Every(r.get(src, 0.0)) for k, src in (
            ("imu", "IMU"), ("ahrs", "ATTITUDE"), ("airspeed", "VFR_HUD"), ("baro", "SCALED_PRESSURE"),
            ("gnss", "GPS_RAW_INT"), ("frame", "FRAME"))}
        self._frames = 0

    def command_heading(self, heading_rad: float, accel_limit_m_s2: float) -> None:
        self.plane.command_heading(heading_rad, accel_limit_m_s2)

    def step(self) -> tuple[TruthState, SensorReadings]:
        c = self.cfg
        self.plane.step(self.dt_s)
        tr = self.plane.truth()
        t, us = tr.t_s, tr.t_us
        imu = ahrs = tas = baro = gnss = frame = None
        if self._sched["imu"].due(t):
            imu = ImuSample(us, tr.rates_b_rad_s + self.rng.normal(0.0, c.gyro_noise_rad_s, 3),
                            tr.accel_b_m_s2 + self.rng.normal(0.0, c.accel_noise_m_s2, 3))
        if self._sched["ahrs"].due(t):
            ahrs = AttitudeSample(us, tr.roll_rad, tr.pitch_rad, float(wrap_pi(tr.yaw_rad)))
        if self._sched["airspeed"].due(t):
            tas = AirspeedSample(us, tr.tas_m_s)
        if self._sched["baro"].due(t):
            baro = BaroSample(us, tr.height_agl_m)
        if self._sched["gnss"].due(t):
            pos = tr.pos_ned_m + np.append(self.rng.normal(0.0, c.gnss_pos_noise_m, 2), 0.0)
            vel = tr.vel_ned_m_s + np.append(self.rng.normal(0.0, c.gnss_vel_noise_m_s, 2), 0.0)
            gnss = GnssSample(us, pos, vel, True, 14, c.gnss_pos_noise_m, c.gnss_vel_noise_m_s)
        if self._sched["frame"].due(t):
            frame = CameraFrame(self._frames, t, 0.0, us)
            self._frames += 1
        return tr, SensorReadings(imu, ahrs, tas, baro, gnss, frame)


class JsbsimPlant:
    """JSBSim dynamics, the simulator's autopilot in heading hold and the scenario's sensor models; with
    ``cfg.fly_scenario`` the scenario's own flight (:func:`sim.flight.build_flight` with ``seed``)."""

    def __init__(self, cfg: VehicleConfig, rng: np.random.Generator, seed: int = 0) -> None:
        from sim.autopilot import Autopilot
        from sim.dynamics import DynamicsParams, FlightDynamics
        from sim.flight import build_flight, wind_params
        from sim.scenario import load_scenario, scenario_with_overrides
        from sim.sensors import SensorSuite

        self.cfg = cfg
        self._frames_on = cfg.rates_hz.get("FRAME", 30.0) > 0
        if cfg.fly_scenario:
            scn = load_scenario(cfg.scenario)
            flight = build_flight(scn, seed)
            self.scenario = scn
            self.dt_s = scn.dt_s
            self.texture = cfg.texture or scn.terrain.texture
            self.frame_noise_std = scn.camera.noise_std if cfg.frame_noise_std is None else cfg.frame_noise_std
            self.exposure_s = scn.camera.exposure_s
            self.dyn, self.autopilot, self.sensors = flight.dyn, flight.autopilot, flight.sensors
            self._truth = self.dyn.truth()
            return
        wn, we = cfg.wind_ned_m_s
        speed = math.hypot(wn, we)
        overrides: dict[str, Any] = {
            "wind.speed_m_s": speed, "wind.from_deg": float(wrap_360(math.degrees(math.atan2(-we, -wn)))),
            "wind.ref_height_m": min(cfg.height_agl_m, 100.0), "wind.shear": False, "wind.gusts": False,
            "wind.turbulence": cfg.turbulence, "sensors.gnss.outages": [],
            "camera.rate_hz": cfg.rates_hz.get("FRAME", 30.0),
        }
        if cfg.rates_hz.get("FRAME", 30.0) <= 0:
            overrides["camera.rate_hz"] = 1.0
        scn = scenario_with_overrides(load_scenario(cfg.scenario), overrides)
        self.scenario = scn
        self.dt_s = scn.dt_s
        self.texture = cfg.texture or DEFAULT_TEXTURE
        self.frame_noise_std = scn.camera.noise_std if cfg.frame_noise_std is None else cfg.frame_noise_std
        self.exposure_s = scn.camera.exposure_s
        rng_dyn, rng_sens = rng.spawn(2)
        self.dyn = FlightDynamics(DynamicsParams(dt_s=scn.dt_s), wind_params(scn), rng_dyn)
        trim = self.dyn.trim(cfg.start_ned_m[0], cfg.start_ned_m[1], cfg.height_agl_m, cfg.tas_m_s,
                             math.radians(cfg.start_yaw_deg))
        self.autopilot = Autopilot(trim=trim)
        self.autopilot.set_heading_command(math.radians(cfg.start_yaw_deg), cfg.height_agl_m, cfg.tas_m_s)
        self.sensors = SensorSuite(scn.sensors, scn.camera, rng_sens)
        self._truth = self.dyn.truth()

    def command_heading(self, heading_rad: float, accel_limit_m_s2: float) -> None:
        self.autopilot.set_heading_command(heading_rad, self.cfg.height_agl_m, self.cfg.tas_m_s)

    def step(self) -> tuple[TruthState, SensorReadings]:
        cmd = self.autopilot.update(self._truth, self.dt_s)
        self._truth = self.dyn.step(cmd)
        r = self.sensors.step(self._truth)
        if not self._frames_on and r.frame is not None:
            r = SensorReadings(r.imu, r.ahrs, r.airspeed, r.baro, r.gnss, None)
        return self._truth, r


# ------------------------------------------------------------------------------------------------ helpers
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
    return isa_pressure_pa(alt_amsl_m) / 100.0


AIR_ISA_OFFSET_K = 5.0  # the vehicle's air: ISA + 5 K (20 degC at sea level), the ISA lapse above


def air_temperature_k(alt_amsl_m: float) -> float:
    """The air temperature the vehicle flies in and its baro reports (SCALED_PRESSURE ``temperature``)."""
    return T0_K - LAPSE_K_M * alt_amsl_m + AIR_ISA_OFFSET_K


def eas_per_tas(alt_amsl_m: float) -> float:
    """Equivalent over true airspeed in the air the vehicle reports (ISA pressure and :func:`air_temperature_k` at
    ``alt_amsl_m``): VFR_HUD carries the equivalent airspeed, as ArduPilot's does."""
    p_pa = isa_pressure_pa(alt_amsl_m)
    return 1.0 / float(eas_to_tas_ratio(p_pa, (p_pa, air_temperature_k(alt_amsl_m))))


def _finite(*vals: Any) -> bool:
    try:
        return all(math.isfinite(float(v)) for v in vals)
    except (TypeError, ValueError):
        return False


def true_drift_deg(tr: TruthState) -> float:
    """The true drift (course over ground minus heading), degrees in [-180, 180)."""
    course = math.atan2(float(tr.vel_ned_m_s[1]), float(tr.vel_ned_m_s[0]))
    return math.degrees(float(angle_diff(course, tr.yaw_rad)))


def received_problems(msg: dict[str, Any]) -> list[str]:
    """What is wrong with a message the companion sent (``to_dict`` form): non-finite or out-of-range values."""
    kind = msg.get("mavpackettype", "")
    out: list[str] = []
    if kind == "NAMED_VALUE_FLOAT":
        name, v = str(msg.get("name", "")), msg.get("value", math.nan)
        limits = {"GSOE_DRIFT": (-MAX_DRIFT_DEG, MAX_DRIFT_DEG), "GSOE_ATA": (0.0, 360.0), "GSOE_Q": (0.0, 1.0),
                  "GSOE_GNSS": (0.0, 2.0), "GSOE_VALID": (0.0, 1.0)}
        lo, hi = limits.get(name, (-math.inf, math.inf))
        if not _finite(v) or not lo <= float(v) <= hi:
            out.append(f"{name}={v!r}")
    elif kind == "VISION_SPEED_ESTIMATE":
        vals = [msg.get("x", math.nan), msg.get("y", math.nan), msg.get("z", math.nan)]
        cov = list(msg.get("covariance", []))
        if not _finite(*vals, *cov):
            out.append("non-finite velocity or covariance")
        elif math.hypot(float(vals[0]), float(vals[1])) > MAX_SPEED_M_S or abs(float(vals[2])) > MAX_SPEED_M_S:
            out.append(f"speed out of range {vals}")
        elif len(cov) == 9 and float(np.min(np.linalg.eigvalsh(np.array(cov).reshape(3, 3)))) < -1e-9:
            out.append("covariance not positive semi-definite")
    elif kind == "VISION_POSITION_DELTA":
        dt = float(msg.get("time_delta_usec", 0)) / 1e6
        pd = list(msg.get("position_delta", []))
        conf = msg.get("confidence", math.nan)
        if not (_finite(*pd, conf) and len(pd) == 3 and dt > 0.0):
            out.append(f"VISION_POSITION_DELTA {pd!r} dt {dt!r} confidence {conf!r}")
        elif math.hypot(float(pd[0]), float(pd[1])) / dt > MAX_SPEED_M_S or not 0.0 <= float(conf) <= 100.0:
            out.append(f"VISION_POSITION_DELTA out of range {pd!r} dt {dt!r} confidence {conf!r}")
    elif kind == "ODOMETRY":
        vel = [msg.get(k, math.nan) for k in ("vx", "vy", "vz")]
        q = list(msg.get("q", []))
        if not (_finite(*vel, *q) and len(q) == 4) or abs(math.hypot(*(float(v) for v in q)) - 1.0) > 1e-3:
            out.append(f"ODOMETRY velocity {vel!r} q {q!r}")
        elif math.hypot(float(vel[0]), float(vel[1])) > MAX_SPEED_M_S:
            out.append(f"ODOMETRY speed out of range {vel!r}")
    elif kind == "WIND":
        d, s, sz = (msg.get(k, math.nan) for k in ("direction", "speed", "speed_z"))
        if not _finite(d, s, sz) or not (0.0 <= float(d) < 360.0 and 0.0 <= float(s) <= MAX_SPEED_M_S):
            out.append(f"WIND {d!r} {s!r} {sz!r}")
    elif kind == "WIND_COV":
        keys = ("wind_x", "wind_y", "wind_z", "var_horiz", "var_vert", "wind_alt", "horiz_accuracy", "vert_accuracy")
        vals = [msg.get(k, math.nan) for k in keys]
        if not _finite(*vals):
            out.append(f"WIND_COV non-finite {vals}")
        elif min(float(msg["var_horiz"]), float(msg["horiz_accuracy"]), float(msg["var_vert"]),
                 float(msg["vert_accuracy"])) < 0.0 or math.hypot(float(msg["wind_x"]), float(msg["wind_y"])) > \
                MAX_SPEED_M_S:
            out.append(f"WIND_COV out of range {vals}")
    elif kind == "COMMAND_LONG" and msg.get("command") == mavutil.mavlink.MAV_CMD_GUIDED_CHANGE_HEADING:
        p1, p2, p3 = (msg.get(k, math.nan) for k in ("param1", "param2", "param3"))
        if not _finite(p1, p2, p3) or int(p1) not in (0, 1) or not 0.0 <= float(p2) < 360.0 or float(p3) <= 0.0:
            out.append(f"heading command {p1!r} {p2!r} {p3!r}")
    elif kind == "DEBUG_VECT":
        if not _finite(msg.get("x", math.nan), msg.get("y", math.nan), msg.get("z", math.nan)):
            out.append("DEBUG_VECT non-finite")
    return out


def nadir_roi(camera: Any, R_nb: NDArray[np.float64], half_angle_rad: float, margin_px: int
              ) -> tuple[int, int, int, int] | None:
    """Bounding box (x0, y0, x1, y1; end exclusive) of the raw pixels within ``half_angle_rad`` of the nadir."""
    az = np.linspace(0.0, 2.0 * math.pi, ROI_RING_RAYS, endpoint=False)
    s, c = math.sin(half_angle_rad), math.cos(half_angle_rad)
    rays_n = np.vstack([np.column_stack([s * np.cos(az), s * np.sin(az), np.full(az.size, c)]), [0.0, 0.0, 1.0]])
    rays_c = rays_n @ R_nb @ camera.R_bc  # (R_bc^T R_nb^T r)^T for every row
    px, ok = camera.project(rays_c)
    if not ok.any():
        return None
    w, h = camera.size_px
    p = px[ok]
    x0 = max(0, int(np.floor(p[:, 0].min())) - margin_px)
    y0 = max(0, int(np.floor(p[:, 1].min())) - margin_px)
    x1 = min(w, int(np.ceil(p[:, 0].max())) + 1 + margin_px)
    y1 = min(h, int(np.ceil(p[:, 1].max())) + 1 + margin_px)
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


class BellyCamera:
    """Renders the belly camera's frames (only the nadir region the optical estimator samples)."""

    def __init__(self, texture: str, seed: int, noise_std: float, exposure_s: float, rng: np.random.Generator,
                 config_path: str | None = None, mount_yaw_error_deg: float = 0.0) -> None:
        """``mount_yaw_error_deg``: the physical camera is turned this much further (clockwise, about the body z axis)
        than the configuration's ``mount_rpy_deg`` says: the mount error a calibration flight finds."""
        from gsoe.camera import CameraModel
        from pipeline.config import load_gsoe_config
        from sim.render import CameraRenderer
        from sim.textures import GroundWorld

        gsoe_cfg, _ = load_gsoe_config(config_path)
        r, p, y = gsoe_cfg.camera.mount_rpy_deg
        self.camera = CameraModel.from_config(replace(gsoe_cfg.camera, mount_rpy_deg=(r, p, y + mount_yaw_error_deg)))
        self.renderer = CameraRenderer(self.camera, GroundWorld.from_name(texture, seed=seed))
        s = gsoe_cfg.stab
        focal = s.focal_px if s.focal_px > 0 else gsoe_cfg.camera.fx_px
        self.half_angle_rad = min(math.radians(80.0), ROI_CONE_FACTOR * math.atan(
            0.5 * math.hypot(s.base_cross_px, s.base_along_px) / focal))
        self.noise_std = noise_std
        self.exposure_s = exposure_s
        self.rng = rng

    def render(self, truth: TruthState) -> NDArray[np.uint8]:
        from gsoe.rotation import R_nb_from_euler

        R_nb = R_nb_from_euler(truth.roll_rad, truth.pitch_rad, truth.yaw_rad)
        roi = nadir_roi(self.camera, R_nb, self.half_angle_rad, ROI_MARGIN_PX)
        if roi is None:
            w, h = self.camera.size_px
            return np.zeros((h, w), np.uint8)
        return self.renderer.render(truth.pos_ned_m, R_nb, roi=roi, exposure_s=self.exposure_s,
                                    vel_ned_m_s=truth.vel_ned_m_s, rates_b_rad_s=truth.rates_b_rad_s,
                                    noise_std=self.noise_std, rng=self.rng)


class FrameServer:
    """TCP server on 127.0.0.1 sending frames to one client (see the module docstring for the format)."""

    def __init__(self, port: int = 0) -> None:
        self._srv: socket.socket | None = None
        self.port = port
        self._open()
        self._client: socket.socket | None = None
        self.sent = 0
        self.dropped = 0

    def _open(self) -> None:
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", self.port))
        srv.listen(1)
        srv.setblocking(False)
        self.port = int(srv.getsockname()[1])
        self._srv = srv

    @property
    def listening(self) -> bool:
        return self._srv is not None

    def stop_listening(self) -> None:
        """Camera unplugged: drop the client and refuse connections until :meth:`start_listening`."""
        self._drop()
        if self._srv is not None:
            self._srv.close()
            self._srv = None

    def start_listening(self) -> None:
        if self._srv is None:
            self._open()

    def _drop(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def _accept(self) -> None:
        if self._srv is None:
            return
        try:
            conn, _ = self._srv.accept()
        except (BlockingIOError, OSError):
            return
        self._drop()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 22)
        self._client = conn

    def send_bytes(self, payload: bytes) -> None:
        self._accept()
        if self._client is None:
            return
        try:
            self._client.settimeout(0.05)
            self._client.sendall(payload)
            self.sent += 1
        except (TimeoutError, BlockingIOError):
            self.dropped += 1  # a torn frame: the stream is resynchronised by reconnecting
            self._drop()
        except OSError:
            self._drop()

    def send(self, t_us: int, image: NDArray[np.uint8]) -> None:
        self.send_bytes(encode_frame(t_us, image))

    def close(self) -> None:
        self.stop_listening()


def random_mavlink_message(rng: np.random.Generator) -> Any:
    """A well-formed MAVLink message of a random type whose fields hold random values (NaN, inf, extremes)."""
    classes = list(mavutil.mavlink.mavlink_map.values())
    cls = classes[int(rng.integers(len(classes)))]
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    args = [_random_field(rng, ftype, lengths.get(name, 0)) for name, ftype in zip(cls.fieldnames, cls.fieldtypes,
                                                                                     strict=True)]
    return cls(*args)


_INT_RANGES = {"int8_t": (-128, 127), "uint8_t": (0, 255), "int16_t": (-32768, 32767), "uint16_t": (0, 65535),
               "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1), "int64_t": (-2**63, 2**63 - 1),
               "uint64_t": (0, 2**64 - 1)}
_SPECIAL_FLOATS = (math.nan, math.inf, -math.inf, 1e38, -1e38, 0.0)


def _random_field(rng: np.random.Generator, ftype: str, array_len: int) -> Any:
    base = ftype.split("[")[0]
    if base == "char":
        n = max(array_len, 1)
        return bytes(rng.integers(32, 127, int(rng.integers(0, n + 1)), dtype=np.uint8))
    if array_len:
        return [_random_field(rng, base, 0) for _ in range(array_len)]
    if base in ("float", "double"):
        if rng.random() < 0.3:
            return _SPECIAL_FLOATS[int(rng.integers(len(_SPECIAL_FLOATS)))]
        return float(rng.normal(0.0, 10.0 ** rng.integers(0, 6)))
    lo, hi = _INT_RANGES.get(base, (0, 255))
    if base.endswith("64_t"):
        return int(rng.integers(0, 2**62)) * (1 if lo == 0 or rng.random() < 0.5 else -1)
    return int(rng.integers(lo, hi, endpoint=True))


# ------------------------------------------------------------------------------------------------ the vehicle
class MavlinkVehicle:
    """The vehicle endpoint.  ``url`` is a pymavlink URL, normally ``udpout:127.0.0.1:PORT`` (the companion
    listens there with ``udpin://127.0.0.1:PORT``)."""

    def __init__(self, url: str, cfg: VehicleConfig, rng: np.random.Generator, *, frames: bool = False,
                 frame_server: FrameServer | None = None, gcs_url: str | None = None, seed: int = 0) -> None:
        self.cfg = cfg
        rng_plant, self.rng_noise, rng_cam, self.rng_fuzz = rng.spawn(4)
        self.plant: Plant = (JsbsimPlant(cfg, rng_plant, seed) if cfg.dynamics == "jsbsim"
                             else KinematicPlant(cfg, rng_plant))
        self.conn = mavutil.mavlink_connection(url, source_system=1, source_component=1, dialect="ardupilotmega")
        self.gcs = mavutil.mavlink_connection(gcs_url, source_system=1, source_component=1,
                                              dialect="ardupilotmega") if gcs_url else None
        self.frame_server = frame_server
        self.camera: BellyCamera | None = None
        if frames:
            self.camera = BellyCamera(self.plant.texture, seed, self.plant.frame_noise_std, self.plant.exposure_s,
                                      rng_cam, cfg.config_path)
        self.tracking_camera: Any = None
        if cfg.target_ned_m is not None:
            from gsoe.camera import CameraModel, forward_camera
            from pipeline.config import load_gsoe_config

            cam = CameraModel.from_config(load_gsoe_config(cfg.config_path)[0].camera)
            self.tracking_camera = forward_camera(cam, math.radians(cfg.tracking_depression_deg))
        self.mode = ARDUPLANE_MODE_AUTO if cfg.fly_scenario else ARDUPLANE_MODE_GUIDED
        self.truth_log: Any = None
        if cfg.truth_log_dir is not None:  # truth.csv, the records gsoe sim writes, at every camera exposure
            from common.logio import RunLog
            from sim.run import _truth_record

            self.truth_log = RunLog(cfg.truth_log_dir)
            self._truth_record = _truth_record
        self.received: dict[str, int] = {}
        self.last: dict[str, dict[str, Any]] = {}
        self.bad_data = 0
        self.named_values: dict[str, float] = {}
        self.heading_commands: list[tuple[float, float]] = []  # (t_s, heading_deg)
        self.output_times: dict[str, list[float]] = {}
        self.version_requests: list[float] = []      # when AUTOPILOT_VERSION was asked for (simulation clock, s)
        self.statustexts: list[tuple[float, str]] = []
        self.problems: list[tuple[float, str]] = []
        self.drift_pairs: list[tuple[float, float, float]] = []  # (t_s, received deg, true deg)
        self.wind_pairs: list[tuple[float, float, float, float, float]] = []  # t, speed, from deg, true both
        self.track_sent = 0
        self._next: dict[str, float] = {k: 0.0 for k in cfg.rates_hz}
        self._last_fix: tuple[float, float] | None = None
        self._truth: TruthState | None = None
        self._imu_acc: list[ImuSample] = []
        self._gyro_mean = np.zeros(3)
        self._ahrs: AttitudeSample | None = None
        self._tas: AirspeedSample | None = None
        self._baro: BaroSample | None = None
        self._frames: deque[tuple[float, int, NDArray[np.uint8]]] = deque()
        self._last_image: NDArray[np.uint8] | None = None
        self._outage_since_s: float | None = None
        self.miss_m = math.inf
        self.miss_t_s = math.nan
        self.passed = False
        self.crashed = ""
        self.track: list[list[float]] = []
        self._fuzz_sent = 0
        self._corrupt_stream_done: set[int] = set()

    # ---------------------------------------------------------------- state
    @property
    def truth(self) -> TruthState:
        if self._truth is None:
            raise RuntimeError("the vehicle has not stepped yet")
        return self._truth

    @property
    def t_s(self) -> float:
        return self._truth.t_s if self._truth is not None else 0.0

    def fault(self, kind: str, t_s: float | None = None) -> Fault | None:
        t = self.t_s if t_s is None else t_s
        return next((f for f in self.cfg.faults if f.kind == kind and f.active(t)), None)

    def clock_offset_us(self) -> int:
        return -int(round(self.cfg.time_jump_s * 1e6)) if self.fault("time_backwards") else 0

    def gnss_out(self, t_s: float) -> bool:
        if any(a <= t_s < b for a, b in self.cfg.gnss_outages_s):
            return True
        return self._outage_since_s is not None and t_s >= self._outage_since_s

    def _update_target(self, tr: TruthState) -> None:
        tgt = self.cfg.target_ned_m
        if tgt is None:
            return
        rng = math.hypot(tgt[0] - tr.pos_ned_m[0], tgt[1] - tr.pos_ned_m[1])
        if self.cfg.gnss_outage_range_m > 0 and self._outage_since_s is None and rng <= self.cfg.gnss_outage_range_m:
            self._outage_since_s = tr.t_s
            log.info("GNSS outage starts at t=%.1f s, %.0f m from the target", tr.t_s, rng)
        if rng < self.miss_m:
            self.miss_m, self.miss_t_s = rng, tr.t_s
        elif rng > self.miss_m + PASS_MARGIN_M and not self.passed:
            self.passed = True
            log.info("target passed: closest approach %.2f m at t=%.1f s", self.miss_m, self.miss_t_s)

    # ---------------------------------------------------------------- sending
    def _due(self, name: str, t_s: float) -> bool:
        rate = self.cfg.rates_hz.get(name, 0.0)
        if rate <= 0.0 or t_s + 1e-9 < self._next[name]:
            return False
        self._next[name] += 1.0 / rate
        if self._next[name] < t_s:
            self._next[name] = t_s + 1.0 / rate
        return True

    def _send(self, msg: Any) -> None:
        self.conn.mav.send(msg)
        if self.gcs is not None:
            self.gcs.write(msg.get_msgbuf())

    def send_telemetry(self, tr: TruthState) -> None:
        m = self.conn.mav
        c = self.cfg
        t = tr.t_s
        off = self.clock_offset_us()
        bad = self.fault("bad_telemetry") is not None
        bad_kind = int(self.rng_noise.integers(3)) if bad else -1  # 0 NaN, 1 inf, 2 out of range
        if self._due("HEARTBEAT", t):
            ml = mavutil.mavlink
            flags = (ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | ml.MAV_MODE_FLAG_SAFETY_ARMED
                     | ml.MAV_MODE_FLAG_GUIDED_ENABLED)
            self._send(m.heartbeat_encode(ml.MAV_TYPE_FIXED_WING, ml.MAV_AUTOPILOT_ARDUPILOTMEGA, flags, self.mode,
                                          ml.MAV_STATE_ACTIVE))
        if self._imu_acc and self._due("IMU", t):
            us = self._imu_acc[-1].t_us + off
            gyro = np.mean([s.gyro_b_rad_s for s in self._imu_acc], axis=0)
            acc = np.mean([s.accel_b_m_s2 for s in self._imu_acc], axis=0)
            self._imu_acc.clear()
            self._gyro_mean = gyro
            acc_mg = np.clip(np.round(acc / GRAVITY_M_S2 * 1000.0), -32768, 32767).astype(int)
            gyro_mrad = np.clip(np.round(gyro * 1000.0), -32768, 32767).astype(int)
            if bad:
                acc_mg[2] = -BAD_ACCEL_MG
            self._send(m.raw_imu_encode(max(us, 0), *acc_mg.tolist(), *gyro_mrad.tolist(), 0, 0, 0))
            self._send(m.scaled_imu_encode(max(us // 1000, 0), *acc_mg.tolist(), *gyro_mrad.tolist(), 0, 0, 0))
        a = self._ahrs
        if a is not None and self._due("ATTITUDE", t):
            roll = (math.nan, math.inf, BAD_ROLL_RAD)[bad_kind] if bad else a.roll_rad
            p, q, r = self._gyro_mean
            self._send(m.attitude_encode(max((a.t_us + off) // 1000, 0), roll, a.pitch_rad,
                                         float(wrap_pi(a.yaw_rad)), float(p), float(q), float(r)))
        baro_alt = self._baro.alt_m if self._baro is not None else c.height_agl_m
        alt_amsl = c.ref_alt_amsl_m + baro_alt
        if self._baro is not None and self._due("SCALED_PRESSURE", t):
            tas = self._tas.tas_m_s if self._tas is not None else tr.tas_m_s
            press = (math.nan, math.inf, BAD_PRESSURE_HPA)[bad_kind] if bad else isa_pressure_hpa(alt_amsl)
            q_hpa = 0.5 * RHO0_KG_M3 * tas**2 / 100.0
            temp_cdeg = int(round(100.0 * (air_temperature_k(alt_amsl) - KELVIN_AT_0_C)))
            self._send(m.scaled_pressure_encode(max((self._baro.t_us + off) // 1000, 0), press, q_hpa, temp_cdeg))
        gs = float(np.hypot(*tr.vel_ned_m_s[:2]))
        if self._tas is not None and self._due("VFR_HUD", t):
            tas = (math.nan, -math.inf, BAD_AIRSPEED_M_S)[bad_kind] if bad else self._tas.tas_m_s
            yaw = self._ahrs.yaw_rad if self._ahrs is not None else tr.yaw_rad
            self._send(m.vfr_hud_encode(tas * eas_per_tas(alt_amsl), gs, int(round(math.degrees(yaw))) % 360, 50,
                                        alt_amsl, -float(tr.vel_ned_m_s[2])))
        if self._due("GLOBAL_POSITION_INT", t) and self._last_fix is not None:
            lat, lon = self._last_fix
            v = tr.vel_ned_m_s
            self._send(m.global_position_int_encode(max((tr.t_us + off) // 1000, 0), int(lat * 1e7), int(lon * 1e7),
                                                    int(alt_amsl * 1000), int(baro_alt * 1000), int(v[0] * 100),
                                                    int(v[1] * 100), int(v[2] * 100),
                                                    int(round(math.degrees(tr.yaw_rad) * 100)) % 36000))
        if self.tracking_camera is not None and self._due("TRACK", t):
            self._send_track(tr)

    def _send_gnss(self, g: GnssSample, tr: TruthState) -> None:
        c = self.cfg
        m = self.conn.mav
        us = max(g.t_us + self.clock_offset_us(), 0)
        if self.gnss_out(tr.t_s) or not g.fix_ok:
            self._send(m.gps_raw_int_encode(us, 1, 0, 0, 0, UINT16_UNKNOWN, UINT16_UNKNOWN, UINT16_UNKNOWN,
                                            UINT16_UNKNOWN, 0))
            return
        pos = np.array(g.pos_ned_m, dtype=float)
        if self.fault("gnss_jump"):
            pos[0] += c.gnss_jump_m
        vel = g.vel_ned_m_s
        lat, lon = ned_to_lat_lon(float(pos[0]), float(pos[1]), c.ref_lat_deg, c.ref_lon_deg)
        self._last_fix = (lat, lon)
        alt_amsl = c.ref_alt_amsl_m - float(pos[2])
        cog = int(round(math.degrees(math.atan2(vel[1], vel[0])) % 360.0 * 100)) % 36000
        self._send(m.gps_raw_int_encode(us, 3, int(lat * 1e7), int(lon * 1e7), int(alt_amsl * 1000), 80, 120,
                                        int(float(np.hypot(vel[0], vel[1])) * 100), cog, g.n_sats,
                                        alt_ellipsoid=0, h_acc=int(g.h_acc_m * 1000),
                                        v_acc=int(c.gnss_alt_acc_m * 1000), vel_acc=int(g.v_acc_m_s * 1000),
                                        hdg_acc=0))

    def _send_track(self, tr: TruthState) -> None:
        from gsoe.rotation import R_nb_from_euler

        ml = mavutil.mavlink
        cam = self.tracking_camera
        assert self.cfg.target_ned_m is not None
        rel = np.array([self.cfg.target_ned_m[0], self.cfg.target_ned_m[1], 0.0]) - tr.pos_ned_m
        R_nb = R_nb_from_euler(tr.roll_rad, tr.pitch_rad, tr.yaw_rad)
        px, ok = cam.project((cam.R_bc.T @ (R_nb.T @ rel)).reshape(1, 3))
        w, h = cam.size_px
        if ok[0]:
            p = px[0] + self.rng_noise.normal(0.0, self.cfg.tracker_noise_px, 2)
            x, y = float(np.clip((p[0] + 0.5) / w, 0.0, 1.0)), float(np.clip((p[1] + 0.5) / h, 0.0, 1.0))
            status = ml.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
        else:
            x = y = math.nan
            status = ml.CAMERA_TRACKING_STATUS_FLAGS_IDLE
        nan = math.nan
        self._send(self.conn.mav.camera_tracking_image_status_encode(
            status, ml.CAMERA_TRACKING_MODE_POINT, ml.CAMERA_TRACKING_TARGET_DATA_IN_STATUS, x, y, nan, nan, nan,
            nan, nan))
        self.track_sent += 1

    # ---------------------------------------------------------------- frames
    def _queue_frame(self, tr: TruthState, f: CameraFrame) -> None:
        if self.camera is None or self.frame_server is None:
            return
        image = self.camera.render(tr)
        self._frames.append((tr.t_s + self.cfg.frame_latency_s, f.t_us + self.clock_offset_us(), image))

    def _deliver_frames(self, t_s: float) -> None:
        srv = self.frame_server
        if srv is None:
            return
        if self.fault("camera_off", t_s):
            if srv.listening:
                log.info("fault: camera off at t=%.1f s", t_s)
                srv.stop_listening()
        elif not srv.listening:
            srv.start_listening()
            log.info("fault cleared: camera on at t=%.1f s", t_s)
        while self._frames and self._frames[0][0] <= t_s + 1e-9:
            _, t_us, image = self._frames.popleft()
            if not srv.listening:
                continue
            image = self._faulty_image(t_s, image)
            cs = self.fault("corrupt_stream", t_s)
            if cs is not None and id(cs) not in self._corrupt_stream_done:
                self._corrupt_stream_done.add(id(cs))
                srv.send_bytes(self.rng_fuzz.integers(0, 256, 4096, dtype=np.uint8).tobytes())
                continue
            srv.send(t_us, image)

    def _faulty_image(self, t_s: float, image: NDArray[np.uint8]) -> NDArray[np.uint8]:
        if self.fault("frozen_frames", t_s) and self._last_image is not None:
            return self._last_image
        if self.fault("black_frames", t_s):
            return np.zeros_like(image)
        if self.fault("saturated_frames", t_s):
            return np.full_like(image, 255)
        if self.fault("wrong_size_frames", t_s):
            return np.ascontiguousarray(image[::2, ::2])
        if self.fault("corrupt_frames", t_s):
            out = image.copy()
            h = out.shape[0]
            for _ in range(4):
                r0 = int(self.rng_fuzz.integers(0, h - 16))
                out[r0:r0 + 16] = self.rng_fuzz.integers(0, 256, out[r0:r0 + 16].shape, dtype=np.uint8)
            return out
        self._last_image = image
        return image

    # ---------------------------------------------------------------- receiving
    def poll(self, discard: bool = False) -> None:
        """Handle every message waiting on the socket (never blocks, never raises on garbage)."""
        t = self.t_s
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
            if discard:
                continue
            if self.gcs is not None:
                self.gcs.write(msg.get_msgbuf())
            self.received[kind] = self.received.get(kind, 0) + 1
            d = msg.to_dict()
            self.last[kind] = d
            for p in received_problems(d):
                self.problems.append((t, f"{kind}: {p}"))
                log.warning("invalid value from the companion: %s %s", kind, p)
            if kind in OUTPUT_TYPES:
                key = f"{kind}:{msg.name}" if kind == "NAMED_VALUE_FLOAT" else kind
                self.output_times.setdefault(key, []).append(round(t, 3))
            if kind == "COMMAND_LONG":
                self._command(msg)
            elif kind == "NAMED_VALUE_FLOAT":
                self.named_values[str(msg.name)] = float(msg.value)
                if str(msg.name) == "GSOE_DRIFT" and self._truth is not None:
                    self.drift_pairs.append((round(t, 3), float(msg.value), true_drift_deg(self._truth)))
            elif kind == "WIND" and self._truth is not None:
                w = self._truth.wind_ned_m_s
                self.wind_pairs.append((round(t, 3), float(msg.speed), float(msg.direction),
                                        float(np.hypot(w[0], w[1])), float(wrap_360(math.degrees(
                                            math.atan2(-w[1], -w[0]))))))
            elif kind == "STATUSTEXT":
                self.statustexts.append((round(t, 3), str(msg.text)))

    def _command(self, msg: Any) -> None:
        if msg.target_system not in (0, 1):
            return
        result = MAV_RESULT_UNSUPPORTED
        if msg.command == mavutil.mavlink.MAV_CMD_GUIDED_CHANGE_HEADING:
            if self.mode != ARDUPLANE_MODE_GUIDED:
                result = MAV_RESULT_FAILED
            elif not (_finite(msg.param1, msg.param2, msg.param3) and 0.0 <= msg.param2 < 360.0
                      and int(msg.param1) in (0, 1)):
                result = MAV_RESULT_DENIED
            else:
                # heading type 0 (course over ground) is flown as a heading: like ArduPlane without GNSS, the
                # vehicle has no course to close the loop on.
                self.plant.command_heading(math.radians(msg.param2), max(msg.param3, 0.05))
                self.heading_commands.append((round(self.t_s, 3), float(msg.param2)))
                result = MAV_RESULT_ACCEPTED
        elif msg.command == mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE and \
                int(msg.param1) == mavutil.mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            result = MAV_RESULT_ACCEPTED
            self.version_requests.append(round(self.t_s, 3))
        self._send(self.conn.mav.command_ack_encode(msg.command, result))
        if result == MAV_RESULT_ACCEPTED and msg.command == mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE:
            major, minor, patch = VEHICLE_FIRMWARE
            version = major << 24 | minor << 16 | patch << 8 | mavutil.mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL
            self._send(self.conn.mav.autopilot_version_encode(0, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0))

    def _fuzz(self, f: Fault) -> None:
        """Send this step's share of the fault's random MAVLink frames to the companion."""
        frac = min(1.0, (self.t_s - f.start_s + self.plant.dt_s) / (f.end_s - f.start_s))
        due = int(math.ceil(self.cfg.fuzz_count * frac))
        while self._fuzz_sent < min(due, self.cfg.fuzz_count):
            self._fuzz_sent += 1
            if self.rng_fuzz.random() < 0.5:
                n = int(self.rng_fuzz.integers(1, 280))
                junk = self.rng_fuzz.integers(0, 256, n, dtype=np.uint8).tobytes()
                self.conn.write(b"\xfd" + junk if self.rng_fuzz.random() < 0.5 else junk)
                continue
            try:
                self.conn.mav.send(random_mavlink_message(self.rng_fuzz))
            except Exception as e:  # a value pymavlink cannot pack: send raw bytes instead
                log.debug("fuzz message not packable: %s", e)
                self.conn.write(self.rng_fuzz.integers(0, 256, 64, dtype=np.uint8).tobytes())

    # ---------------------------------------------------------------- running
    def step(self) -> TruthState:
        tr, r = self.plant.step()
        self._truth = tr
        t = tr.t_s
        self._update_target(tr)
        if r.imu is not None:
            self._imu_acc.append(r.imu)
        if r.ahrs is not None:
            self._ahrs = r.ahrs
        if r.airspeed is not None:
            self._tas = r.airspeed
        if r.baro is not None:
            self._baro = r.baro
        if r.frame is not None:
            self._queue_frame(tr, r.frame)
            if self.truth_log is not None:
                self.truth_log.write("truth", self._truth_record(tr))
        self._deliver_frames(t)
        silent = self.fault("link_silence") is not None
        if not silent:
            self.send_telemetry(tr)
            if r.gnss is not None:
                self._send_gnss(r.gnss, tr)
        self.poll(discard=silent)
        fz = self.fault("mavlink_fuzz")
        if fz is not None and not silent:
            self._fuzz(fz)
        if not self.track or t - self.track[-1][0] >= 1.0:
            self.track.append([round(t, 3), *np.round(tr.pos_ned_m, 2).tolist(), round(tr.yaw_rad, 4)])
        return tr

    def run(self, duration_s: float, realtime: bool = True, stop: Callable[[TruthState], bool] | None = None,
            stop_after_pass: bool = False) -> None:
        """Fly for ``duration_s`` (wall-clock paced when ``realtime``), or until ``stop(truth)`` or, with
        ``stop_after_pass``, until the target has been passed."""
        from sim.dynamics import DynamicsError

        start = time.monotonic()
        dt = self.plant.dt_s
        n = int(round(duration_s / dt))
        for i in range(n):
            try:
                truth = self.step()
            except DynamicsError as e:
                self.crashed = str(e)
                log.error("the flight ended: %s", e)
                return
            if (stop is not None and stop(truth)) or (stop_after_pass and self.passed):
                return
            if realtime:
                lag = start + (i + 1) * dt - time.monotonic()
                if lag > 0:
                    time.sleep(lag)

    def summary(self) -> dict[str, Any]:
        return {"received": self.received, "last": self.last, "bad_data": self.bad_data,
                "heading_commands": self.heading_commands, "named_values": self.named_values,
                "frames_sent": self.frame_server.sent if self.frame_server else 0,
                "pos_ned_m": self.truth.pos_ned_m.tolist() if self._truth is not None else None,
                "yaw_deg": math.degrees(self.truth.yaw_rad) if self._truth is not None else None,
                "t_s": self.t_s, "dynamics": self.cfg.dynamics, "output_times": self.output_times,
                "version_requests": self.version_requests,
                "statustexts": self.statustexts, "problems": self.problems,
                "miss_m": self.miss_m if math.isfinite(self.miss_m) else None,
                "miss_t_s": self.miss_t_s if math.isfinite(self.miss_t_s) else None, "passed": self.passed,
                "gnss_outage_start_s": self._outage_since_s, "track_sent": self.track_sent, "crashed": self.crashed,
                "faults": [[f.kind, f.start_s, f.end_s] for f in self.cfg.faults], "fuzz_sent": self._fuzz_sent,
                "drift_pairs": self.drift_pairs, "wind_pairs": self.wind_pairs,
                "track": self.track}

    def close(self) -> None:
        self.conn.close()
        if self.gcs is not None:
            self.gcs.close()
        if self.frame_server is not None:
            self.frame_server.close()
        if self.truth_log is not None:
            self.truth_log.close()


# ------------------------------------------------------------------------------------------------ CLI
def _pair(text: str) -> tuple[float, float]:
    try:
        a, b = text.split(",")
        return float(a), float(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A,B, got {text!r}") from None


def _fault(text: str) -> Fault:
    try:
        kind, a, b = text.split(":")
        return Fault(kind, float(a), float(b))
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"expected KIND:START_S:END_S, got {text!r} ({e})") from None


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.mavlink_vehicle --connect udpout:127.0.0.1:PORT [...]``: run the vehicle as a process."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", required=True, help="pymavlink URL, e.g. udpout:127.0.0.1:14540")
    ap.add_argument("--duration-s", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dynamics", choices=("kinematic", "jsbsim"), default="kinematic")
    ap.add_argument("--scenario", default="paper_sil", help="jsbsim: scenario whose sensor models are used")
    ap.add_argument("--fly-scenario", action="store_true",
                    help="jsbsim: fly --scenario itself (mission, wind, GNSS outages, texture) seeded as gsoe sim")
    ap.add_argument("--truth-log", help="write the truth (truth.csv, as gsoe sim logs it) to this folder")
    ap.add_argument("--turbulence", action="store_true", help="jsbsim: the scenario's Dryden turbulence on")
    ap.add_argument("--tas-m-s", type=float, default=20.0)
    ap.add_argument("--height-agl-m", type=float, default=100.0)
    ap.add_argument("--start-ned-m", type=_pair, default=(0.0, 0.0))
    ap.add_argument("--start-yaw-deg", type=float, default=0.0)
    ap.add_argument("--wind-ned-m-s", type=_pair, default=(0.0, 0.0), help="velocity of the air N,E (blowing to)")
    ap.add_argument("--gnss-outage-s", type=_pair, action="append", default=[], help="START,END (repeatable)")
    ap.add_argument("--target-ned-m", type=_pair, help="target on the ground (tracking-camera hook, miss distance)")
    ap.add_argument("--gnss-outage-range-m", type=float, default=0.0, help="GNSS denied from this range to target")
    ap.add_argument("--tracking-depression-deg", type=float, default=10.0)
    ap.add_argument("--tracker-noise-px", type=float, default=0.5)
    ap.add_argument("--stop-after-pass", action="store_true", help="end the run once the target has been passed")
    ap.add_argument("--fault", type=_fault, action="append", default=[], help="KIND:START_S:END_S (repeatable)")
    ap.add_argument("--fuzz-count", type=int, default=10_000)
    ap.add_argument("--gcs", help="pymavlink URL of a ground station (telemetry and the companion's messages)")
    ap.add_argument("--summary", help="write a JSON summary of what the vehicle received here at the end")
    ap.add_argument("--frame-port", type=int, help="stream rendered camera frames on this TCP port (0: any)")
    ap.add_argument("--frame-hz", type=float, default=30.0)
    ap.add_argument("--frame-latency-s", type=float, default=0.04)
    ap.add_argument("--texture", help=f"ground texture of sim.textures (default: {DEFAULT_TEXTURE})")
    ap.add_argument("--config", help="configuration file (camera) shared with the companion")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    rates = dict(VehicleConfig().rates_hz, FRAME=args.frame_hz)
    cfg = VehicleConfig(dynamics=args.dynamics, scenario=args.scenario, turbulence=args.turbulence,
                        tas_m_s=args.tas_m_s, height_agl_m=args.height_agl_m, start_ned_m=args.start_ned_m,
                        start_yaw_deg=args.start_yaw_deg, wind_ned_m_s=args.wind_ned_m_s,
                        gnss_outages_s=tuple(args.gnss_outage_s), gnss_outage_range_m=args.gnss_outage_range_m,
                        target_ned_m=args.target_ned_m, tracking_depression_deg=args.tracking_depression_deg,
                        tracker_noise_px=args.tracker_noise_px, texture=args.texture,
                        frame_latency_s=args.frame_latency_s, faults=tuple(args.fault), fuzz_count=args.fuzz_count,
                        config_path=args.config, fly_scenario=args.fly_scenario, truth_log_dir=args.truth_log,
                        rates_hz=rates)
    rng = np.random.default_rng(args.seed)
    server = None
    if args.frame_port is not None:
        server = FrameServer(args.frame_port)
        log.info("camera frames on tcp 127.0.0.1:%d", server.port)
    veh = MavlinkVehicle(args.connect, cfg, rng, frames=server is not None, frame_server=server, gcs_url=args.gcs,
                         seed=args.seed)

    def _term(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _term)
    try:
        veh.run(args.duration_s, stop_after_pass=args.stop_after_pass)
    except KeyboardInterrupt:
        pass
    finally:
        if args.summary:
            tmp = args.summary + ".tmp"
            with open(tmp, "w") as fh:
                json.dump(veh.summary(), fh)
            os.replace(tmp, args.summary)
        veh.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
