"""Simulation scenarios: what the simulated world and the simulated sensors are (``config/scenarios/*.toml``).

A scenario is a tree of frozen dataclasses built with :func:`gsoe.config.build`, so unknown keys, wrong types and
out-of-range values are rejected with a :class:`~gsoe.config.ConfigError` that names the dotted field
(``wind.speed_m_s: must be in [0.0, 30.0], got 45.0``).  Angles in files are degrees (``*_deg``); code reads the
``*_rad`` properties.  The sensor sections hold the *distributions* of the true sensor errors of a run (the draws
are :func:`sim.sensors.draw_sensor_errors`); what the estimators assume lives in ``config/`` (STYLE section 8).

File layout (every section but ``[mission]`` has defaults)::

    name, description, duration_s, seed, dt_s, extends
    [terrain]            texture, ground, ground_elevation_m
    [mission]            loop;  [mission.start] north_m east_m height_m airspeed_m_s yaw_deg
    [[mission.waypoints]] north_m east_m height_m airspeed_m_s
    [wind]               speed_m_s, ref_height_m, from_deg, shear, roughness_m, turbulence, ...
    [sensors.imu] [sensors.ahrs] [sensors.airspeed] [sensors.baro] [sensors.gnss]
    [camera]             rate_hz, exposure_s, timestamp_offset_s, ...;  [camera.gsoe_overrides.stab] ...

``extends = "paper_sil"`` starts from another scenario file: tables are merged key by key, everything else
(numbers, strings, arrays such as the waypoint list) is replaced.

Heights are above the mission's reference point on the ground (flat terrain at ``ground_elevation_m``); positions
are local NED north/east metres from that point (see :mod:`gsoe`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import numpy as np
from numpy.typing import NDArray

from common.config import ConfigError, In, Radians, Validated, build, require, to_dict
from common.configfile import CONFIG_DIR, read_toml
from gsoe.config import CameraConfig, CycleConfig, GsoeConfig, IntegrityConfig, MatchConfig, StabConfig

SCENARIO_DIR = CONFIG_DIR / "scenarios"

Texture = Literal["town_river", "dry_grassland", "forest_road", "farmland", "mosaic", "noise", "uniform_grass", "water"]
TEXTURES: tuple[str, ...] = get_args(Texture)

# Ranges (documented limits of what the simulator is meant to fly; values beyond them are almost certainly typos).
DT_MIN_S = 1.0 / 2000.0
DT_MAX_S = 1.0 / 50.0
DURATION_MAX_S = 86_400.0
SEED_MAX = 2**63 - 1
MISSION_EXTENT_M = 50_000.0  # |north|, |east| of any mission point
HEIGHT_MIN_M = 10.0
HEIGHT_MAX_M = 3_000.0
AIRSPEED_MIN_M_S = 8.0
AIRSPEED_MAX_M_S = 60.0
MAX_WAYPOINTS = 10_000
# Shortest horizontal leg between consecutive mission points.  A fixed-wing mini-UAV turns on a radius of tens of
# metres, so a shorter leg cannot be flown and is almost certainly a typo (or a duplicated waypoint).
MIN_LEG_M = 10.0
WIND_MAX_M_S = 30.0
# Slowest Dryden filter rate: ten samples per second resolve the spectra's corners (V / L < 1 Hz above 10 ft).
TURBULENCE_RATE_MIN_HZ = 10.0
# A sensor may not sample faster than the dynamics step; this tolerance absorbs 1/dt_s rounding.
RATE_TOLERANCE = 1e-6
# Nesting depth of ``extends`` chains (guards against cycles as well).
MAX_EXTENDS_DEPTH = 8

# Ranges shared by several fields.
_NorthEastM = Annotated[float, In(-MISSION_EXTENT_M, MISSION_EXTENT_M)]
_HeightM = Annotated[float, In(HEIGHT_MIN_M, HEIGHT_MAX_M)]
_AirspeedMS = Annotated[float, In(AIRSPEED_MIN_M_S, AIRSPEED_MAX_M_S)]
_SensorRateHz = Annotated[float, In(1.0, 1_000.0)]


# --------------------------------------------------------------------------------------------------------------
# Sections


@dataclass(frozen=True)
class TerrainConfig(Validated):
    """Ground under the aircraft: the texture the renderer drapes over flat ground at ``ground_elevation_m``.

    ``ground_elevation_m`` is the flat ground's height relative to the mission's reference point (positive up).
    """

    texture: Texture = "mosaic"
    ground: Literal["flat"] = "flat"
    ground_elevation_m: Annotated[float, In(-1_000.0, 1_000.0)] = 0.0


@dataclass(frozen=True)
class StartConfig(Validated):
    """Initial state: position (north/east from the reference point, height above it), true airspeed, heading."""

    north_m: _NorthEastM = 0.0
    east_m: _NorthEastM = 0.0
    height_m: _HeightM = 100.0
    airspeed_m_s: _AirspeedMS = 20.0
    yaw_deg: Annotated[float, In(-360.0, 360.0)] = 0.0

    yaw_rad = Radians("yaw_deg")


@dataclass(frozen=True)
class WaypointConfig(Validated):
    """One mission waypoint: position, height above the reference point, commanded true airspeed on the leg to it."""

    north_m: _NorthEastM
    east_m: _NorthEastM
    height_m: _HeightM
    airspeed_m_s: _AirspeedMS


@dataclass(frozen=True)
class MissionConfig(Validated):
    """The flight plan: start state and the waypoints flown in order (from the last back to the first if ``loop``)."""

    waypoints: tuple[WaypointConfig, ...]
    start: StartConfig = field(default_factory=StartConfig)
    loop: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        n = len(self.waypoints)
        require(1 <= n <= MAX_WAYPOINTS, "waypoints", f"must hold 1 to {MAX_WAYPOINTS} waypoints, got {n}")
        require(not self.loop or n >= 2, "loop", "a looping mission needs at least 2 waypoints")
        pts = [(self.start.north_m, self.start.east_m)] + [(w.north_m, w.east_m) for w in self.waypoints]
        for i in range(n):
            leg = math.hypot(pts[i + 1][0] - pts[i][0], pts[i + 1][1] - pts[i][1])
            src = "start" if i == 0 else f"waypoints[{i - 1}]"
            require(leg >= MIN_LEG_M, f"waypoints[{i}]",
                    f"leg from {src} is {leg:.1f} m long, shorter than {MIN_LEG_M} m")
        if self.loop:
            leg = math.hypot(pts[1][0] - pts[-1][0], pts[1][1] - pts[-1][1])
            require(leg >= MIN_LEG_M, f"waypoints[{n - 1}]",
                    f"closing leg back to waypoints[0] is {leg:.1f} m long, shorter than {MIN_LEG_M} m")

    @property
    def waypoints_ned_m(self) -> NDArray[np.float64]:
        """Waypoints as NED positions, shape (N, 3) (down = -height)."""
        return np.array([[w.north_m, w.east_m, -w.height_m] for w in self.waypoints], dtype=np.float64)

    @property
    def airspeeds_m_s(self) -> NDArray[np.float64]:
        return np.array([w.airspeed_m_s for w in self.waypoints], dtype=np.float64)


@dataclass(frozen=True)
class WindConfig(Validated):
    """True wind field.

    Steady wind ``speed_m_s`` at ``ref_height_m`` above ground, blowing *from* ``from_deg`` (clockwise from north).
    ``shear``: the speed follows a logarithmic profile with surface roughness ``roughness_m`` (otherwise it is the
    same at every height).  ``turbulence``: Dryden turbulence (JSBSim milspec) of ``turbulence_severity`` with its
    intensities multiplied by ``turbulence_scale``; its shaping filters are advanced at ``turbulence_rate_hz``
    (the default, the default dynamics rate, steps them at every dynamics step; a lower rate interpolates between
    filter samples, see :mod:`sim.wind`).  ``gusts``: discrete (1 - cos) gusts of ``gust_amplitude_m_s``
    peak and ``gust_length_m`` length, starting at exponentially distributed intervals of mean ``gust_interval_s``.
    """

    speed_m_s: Annotated[float, In(0.0, WIND_MAX_M_S)] = 0.0
    ref_height_m: Annotated[float, In(1.0, 100.0)] = 6.0
    from_deg: Annotated[float, In(0.0, 360.0)] = 0.0
    shear: bool = True
    roughness_m: Annotated[float, In(1e-4, 3.0)] = 0.03
    turbulence: bool = False
    turbulence_severity: Literal["light", "moderate", "severe"] = "light"
    turbulence_scale: Annotated[float, In(0.0, 5.0)] = 1.0
    turbulence_rate_hz: Annotated[float, In(TURBULENCE_RATE_MIN_HZ, 1.0 / DT_MIN_S)] = 240.0
    gusts: bool = False
    gust_amplitude_m_s: Annotated[float, In(0.0, 20.0)] = 2.0
    gust_length_m: Annotated[float, In(1.0, 2_000.0)] = 100.0
    gust_interval_s: Annotated[float, In(1.0, 1e5)] = 60.0

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.roughness_m < self.ref_height_m, "roughness_m", "must be below ref_height_m")

    from_rad = Radians("from_deg")

    @property
    def steady_ned_m_s(self) -> NDArray[np.float64]:
        """The steady wind at ``ref_height_m`` as the velocity of the air in NED (it blows *to* ``from + 180``)."""
        a = self.from_rad
        return np.array([-self.speed_m_s * math.cos(a), -self.speed_m_s * math.sin(a), 0.0])


@dataclass(frozen=True)
class ImuConfig(Validated):
    """IMU (gyro + accelerometer, body FRD), per axis.

    White noise as a density (``*_noise_density_*``, the std of a sample is density * sqrt(rate_hz)); the turn-on
    bias of a run is drawn from N(0, ``*_bias_std_*``), then walks with ``*_bias_walk_*`` (std of the change after
    one second); the scale-factor error of a run is drawn from N(0, ``*_scale_std``) (a fraction).
    """

    rate_hz: Annotated[float, In(100.0, 2_000.0)] = 240.0
    gyro_noise_density_deg_s_sqrt_hz: Annotated[float, In(0.0, 1.0)] = 0.01
    gyro_bias_std_deg_s: Annotated[float, In(0.0, 10.0)] = 0.2
    gyro_bias_walk_deg_s_sqrt_s: Annotated[float, In(0.0, 0.1)] = 5e-4
    gyro_scale_std: Annotated[float, In(0.0, 0.1)] = 0.002
    accel_noise_density_m_s2_sqrt_hz: Annotated[float, In(0.0, 1.0)] = 0.004
    accel_bias_std_m_s2: Annotated[float, In(0.0, 2.0)] = 0.05
    accel_bias_walk_m_s2_sqrt_s: Annotated[float, In(0.0, 0.1)] = 5e-4
    accel_scale_std: Annotated[float, In(0.0, 0.1)] = 0.002

    gyro_noise_density_rad_s_sqrt_hz = Radians("gyro_noise_density_deg_s_sqrt_hz")
    gyro_bias_std_rad_s = Radians("gyro_bias_std_deg_s")
    gyro_bias_walk_rad_s_sqrt_s = Radians("gyro_bias_walk_deg_s_sqrt_s")


@dataclass(frozen=True)
class AhrsConfig(Validated):
    """AHRS attitude (roll, pitch, yaw).

    White noise ``noise_deg`` per angle; a constant bias per run drawn from N(0, ``bias_std_deg``) for roll and
    pitch and N(0, ``yaw_bias_std_deg``) for yaw (heading from a magnetometer is usually worse); the reported
    attitude is the one of ``latency_s`` before the sample's stamp.
    """

    rate_hz: _SensorRateHz = 50.0
    noise_deg: Annotated[float, In(0.0, 10.0)] = 0.1
    bias_std_deg: Annotated[float, In(0.0, 10.0)] = 0.3
    yaw_bias_std_deg: Annotated[float, In(0.0, 30.0)] = 1.0
    latency_s: Annotated[float, In(0.0, 1.0)] = 0.01

    noise_rad = Radians("noise_deg")
    bias_std_rad = Radians("bias_std_deg")
    yaw_bias_std_rad = Radians("yaw_bias_std_deg")


@dataclass(frozen=True)
class AirspeedConfig(Validated):
    """Pitot true airspeed: white noise ``noise_m_s``, a scale-factor error per run from N(0, ``scale_error_std``)."""

    rate_hz: _SensorRateHz = 50.0
    noise_m_s: Annotated[float, In(0.0, 10.0)] = 0.3
    scale_error_std: Annotated[float, In(0.0, 0.5)] = 0.02


@dataclass(frozen=True)
class BaroConfig(Validated):
    """Barometric height above the reference point.

    White noise ``noise_m``; a turn-on offset per run from N(0, ``bias_std_m``) (0: zeroed at the reference point);
    a constant drift rate per run (weather) from N(0, ``drift_rate_std_m_s``); and a random walk whose std after one
    second is ``walk_m_sqrt_s``.
    """

    rate_hz: _SensorRateHz = 25.0
    noise_m: Annotated[float, In(0.0, 50.0)] = 0.5
    bias_std_m: Annotated[float, In(0.0, 500.0)] = 0.0
    drift_rate_std_m_s: Annotated[float, In(0.0, 1.0)] = 0.002
    walk_m_sqrt_s: Annotated[float, In(0.0, 5.0)] = 0.02


@dataclass(frozen=True)
class OutageConfig(Validated):
    """A GNSS outage: no fix from ``start_s`` for ``length_s`` seconds (simulation time)."""

    start_s: Annotated[float, In(0.0, DURATION_MAX_S)]
    length_s: Annotated[float, In(0.0, DURATION_MAX_S, lo_open=True)]

    @property
    def end_s(self) -> float:
        return self.start_s + self.length_s


@dataclass(frozen=True)
class GnssConfig(Validated):
    """GNSS position and velocity (NED, relative to the reference point).

    Position errors are first-order Gauss-Markov per axis with stationary std ``pos_noise_m`` (north, east) and
    ``alt_noise_m`` (down) and correlation time ``pos_corr_time_s`` (0: white); velocity noise is white,
    ``vel_noise_m_s`` per axis.  Inside an outage window the receiver reports no fix.
    """

    rate_hz: Annotated[float, In(0.1, 100.0)] = 5.0
    pos_noise_m: Annotated[float, In(0.0, 100.0)] = 1.0
    alt_noise_m: Annotated[float, In(0.0, 100.0)] = 2.0
    pos_corr_time_s: Annotated[float, In(0.0, 10_000.0)] = 0.0
    vel_noise_m_s: Annotated[float, In(0.0, 10.0)] = 0.1
    n_sats: Annotated[int, In(4, 64)] = 12
    outages: tuple[OutageConfig, ...] = ()

    def in_outage(self, t_s: float) -> bool:
        """True when ``t_s`` lies inside an outage window ``[start_s, end_s)``."""
        return any(o.start_s <= t_s < o.end_s for o in self.outages)


@dataclass(frozen=True)
class SensorsConfig(Validated):
    imu: ImuConfig = field(default_factory=ImuConfig)
    ahrs: AhrsConfig = field(default_factory=AhrsConfig)
    airspeed: AirspeedConfig = field(default_factory=AirspeedConfig)
    baro: BaroConfig = field(default_factory=BaroConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)


_GSOE_SECTIONS: dict[str, type] = {
    "camera": CameraConfig,
    "stab": StabConfig,
    "match": MatchConfig,
    "cycle": CycleConfig,
    "integrity": IntegrityConfig,
}


@dataclass(frozen=True)
class CameraSimConfig(Validated):
    """The simulated camera.

    Frames are exposed at ``rate_hz`` for ``exposure_s`` (motion blur); the stamp a frame carries is its true
    mid-exposure time plus ``timestamp_offset_s`` plus a per-run draw from N(0, ``timestamp_offset_std_s``).
    ``noise_std`` is the image noise std in grey levels (0-255) and ``gain`` multiplies the rendered intensity.
    ``gsoe_overrides`` holds tables ``stab``, ``match``, ``cycle``, ``integrity`` or ``camera`` whose keys replace
    those of the optical estimator's configuration for this scenario (see :func:`gsoe_config_for`).
    """

    rate_hz: Annotated[float, In(1.0, 120.0)] = 30.0
    exposure_s: Annotated[float, In(0.0, 0.1)] = 0.002
    timestamp_offset_s: Annotated[float, In(-0.5, 0.5)] = 0.0
    timestamp_offset_std_s: Annotated[float, In(0.0, 0.5)] = 0.0
    noise_std: Annotated[float, In(0.0, 100.0)] = 2.0
    gain: Annotated[float, In(0.05, 20.0)] = 1.0
    gsoe_overrides: Any = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.exposure_s <= 1.0 / self.rate_hz, "exposure_s", "must not exceed the frame period 1/rate_hz")
        ov = self.gsoe_overrides
        require(isinstance(ov, Mapping), "gsoe_overrides", f"must be a table, got {type(ov).__name__}")
        for section, values in ov.items():
            cls = _GSOE_SECTIONS.get(section)
            require(cls is not None, f"gsoe_overrides.{section}",
                    f"unknown section (known: {', '.join(sorted(_GSOE_SECTIONS))})")
            require(isinstance(values, Mapping), f"gsoe_overrides.{section}", "must be a table")
            known = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
            for key in values:
                require(key in known, f"gsoe_overrides.{section}.{key}",
                        f"unknown key (known: {', '.join(sorted(known))})")
        rate = ov.get("cycle", {}).get("rate_hz")
        require(rate is None or rate == self.rate_hz, "gsoe_overrides.cycle.rate_hz",
                f"the TM rate is the camera rate (camera.rate_hz = {self.rate_hz}); got {rate!r}")
        # Own a private deep copy: the caller's mapping cannot change a frozen scenario afterwards.
        object.__setattr__(self, "gsoe_overrides", copy.deepcopy(dict(ov)))


@dataclass(frozen=True)
class Scenario(Validated):
    """One simulated flight: world, mission, wind, sensors and camera, plus run length, seed and dynamics step."""

    name: str
    mission: MissionConfig
    description: str = ""
    duration_s: Annotated[float, In(0.0, DURATION_MAX_S, lo_open=True)] = 600.0
    seed: Annotated[int, In(0, SEED_MAX)] = 0
    dt_s: Annotated[float, In(DT_MIN_S, DT_MAX_S)] = 1.0 / 240.0
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    wind: WindConfig = field(default_factory=WindConfig)
    sensors: SensorsConfig = field(default_factory=SensorsConfig)
    camera: CameraSimConfig = field(default_factory=CameraSimConfig)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(bool(self.name.strip()), "name", "must not be empty")
        max_rate = (1.0 / self.dt_s) * (1.0 + RATE_TOLERANCE)
        rates = {
            "sensors.imu.rate_hz": self.sensors.imu.rate_hz,
            "sensors.ahrs.rate_hz": self.sensors.ahrs.rate_hz,
            "sensors.airspeed.rate_hz": self.sensors.airspeed.rate_hz,
            "sensors.baro.rate_hz": self.sensors.baro.rate_hz,
            "sensors.gnss.rate_hz": self.sensors.gnss.rate_hz,
            "camera.rate_hz": self.camera.rate_hz,
        }
        for key, rate in rates.items():
            require(rate <= max_rate, key, f"{rate} Hz exceeds the dynamics rate 1/dt_s = {1.0 / self.dt_s:.6g} Hz")

    @property
    def n_steps(self) -> int:
        """Number of dynamics steps in the run."""
        return int(math.ceil(self.duration_s / self.dt_s - RATE_TOLERANCE))


# --------------------------------------------------------------------------------------------------------------
# Building, loading, overriding


def build_scenario(data: Mapping[str, Any]) -> Scenario:
    """Validated :class:`Scenario` from a plain mapping (what ``tomllib`` gives); errors name the dotted field."""
    return build(Scenario, data, "")


def scenario_names() -> list[str]:
    """The named scenarios (``config/scenarios/*.toml``), sorted."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def scenario_descriptions() -> dict[str, str]:
    """Each named scenario's ``description`` (with ``extends``, the file's own or else its parent's)."""
    out = {}
    for name in scenario_names():
        raw = _read_raw(SCENARIO_DIR / f"{name}.toml", 0)
        out[name] = str(raw.get("description", ""))
    return out


def scenario_path(path_or_name: str | Path) -> Path:
    """A bare name (``"paper_sil"``) is ``config/scenarios/<name>.toml``; anything else is a path.  An unknown name
    raises :class:`ConfigError` listing the known ones."""
    p = Path(path_or_name)
    if p.suffix == "" and len(p.parts) == 1:
        path = SCENARIO_DIR / f"{p.name}.toml"
        if not path.is_file():
            raise ConfigError(str(path_or_name), f"unknown scenario; known: {', '.join(scenario_names())} "
                              "(or a path to a scenario file)")
        return path
    return p


def _deep_merge(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in top.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def _read_raw(path: Path, depth: int) -> dict[str, Any]:
    raw = read_toml(path)
    parent = raw.pop("extends", None)
    if parent is None:
        return raw
    if not isinstance(parent, str):
        raise ConfigError(f"{path}: extends", f"must be a scenario name or path, got {parent!r}")
    if depth >= MAX_EXTENDS_DEPTH:
        raise ConfigError(f"{path}: extends", f"chain deeper than {MAX_EXTENDS_DEPTH} (a cycle?)")
    ppath = scenario_path(parent)
    if not ppath.is_absolute() and ppath.parent != SCENARIO_DIR:
        ppath = path.parent / ppath
    return _deep_merge(_read_raw(ppath, depth + 1), raw)


def load_scenario(path_or_name: str | Path) -> Scenario:
    """Read and validate a scenario file; errors are ``ConfigError("<file>: <dotted.field>", ...)``."""
    path = scenario_path(path_or_name)
    raw = _read_raw(path, 0)
    try:
        return build_scenario(raw)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e.field_path}", str(e).split(": ", 1)[1]) from None


_KEY_PART = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)$")


def _split_key(key: str) -> list[str | int]:
    parts: list[str | int] = []
    for piece in key.split("."):
        m = _KEY_PART.match(piece)
        if m is None:
            raise ConfigError(key, "malformed override key (expected dotted names with optional [index])")
        parts.append(m.group(1))
        parts.extend(int(i) for i in re.findall(r"\[(\d+)\]", m.group(2)))
    return parts


def _set_path(tree: dict[str, Any], key: str, value: Any) -> None:
    parts = _split_key(key)
    node: Any = tree
    where = ""
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        where = f"{where}[{part}]" if isinstance(part, int) else (f"{where}.{part}" if where else part)
        if isinstance(part, int):
            if not isinstance(node, list) or part >= len(node):
                raise ConfigError(where, "no such list element")
            if last:
                node[part] = value
            else:
                node = node[part]
            continue
        if not isinstance(node, dict):
            raise ConfigError(where, "parent is not a table")
        if last:
            node[part] = value
        else:
            if part not in node:
                # An unknown section: build() rejects it with the list of known keys.
                node[part] = {}
            node = node[part]


def _listify(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _listify(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_listify(v) for v in obj]
    return obj


def scenario_with_overrides(scn: Scenario, overrides: Mapping[str, Any]) -> Scenario:
    """A new validated scenario with dotted keys replaced (Monte Carlo draws).

    Keys are dotted field names with optional list indices: ``"wind.speed_m_s"``, ``"terrain.texture"``,
    ``"mission.waypoints[3].height_m"``, ``"sensors.gnss.outages"`` (a whole list of ``{start_s, length_s}``),
    ``"camera.gsoe_overrides.stab.template_start"``.  Unknown keys and bad values raise :class:`ConfigError`
    naming the field; ``scn`` is unchanged.
    """
    tree = _listify(to_dict(scn))
    for key, value in overrides.items():
        _set_path(tree, key, copy.deepcopy(value))
    return build_scenario(tree)


def gsoe_config_for(scn: Scenario, base: GsoeConfig) -> GsoeConfig:
    """The optical estimator's configuration for ``scn``: ``base`` with the scenario's ``gsoe_overrides`` applied and
    the TM rate set to the camera rate.  Errors name ``camera.gsoe_overrides.<section>.<key>``."""
    tree = _listify(to_dict(base))
    for section, values in scn.camera.gsoe_overrides.items():
        tree[section] = {**tree[section], **values}
    tree["cycle"]["rate_hz"] = scn.camera.rate_hz
    try:
        return build(GsoeConfig, tree, "")
    except ConfigError as e:
        raise ConfigError(f"camera.gsoe_overrides.{e.field_path}", str(e).split(": ", 1)[1]) from None
