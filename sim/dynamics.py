"""Flight dynamics of the simulated mini-UAV: JSBSim with the project's own Talon-class aircraft.

The aircraft (``sim/aircraft/talon``: airframe, electric motor, propeller and flight-control system, with the
sources of its data) is loaded from this package, never from JSBSim's own aircraft folder.  The wind is the
simulator's :class:`sim.wind.WindField`, written into JSBSim's steady-wind properties before every step (JSBSim's
own turbulence stays off, so that a run is reproducible from its seed).

Frames and units as in :mod:`gsoe`.  Truth conventions of :class:`sim.truth.TruthState`:

position
    Flat-earth NED relative to the reference point ``(ref_lat_rad, ref_lon_rad)`` on flat ground at elevation 0:
    north and east from JSBSim's geodetic latitude and longitude through the WGS84 radii of curvature at the
    reference latitude (an equirectangular map, exact along the reference parallel and every meridian; its east
    scale departs from the ground velocity's by tan(lat0) d_north / R, 1.9e-4 per km north of the reference at
    50 deg), down = -height above the ground (``position/h-agl-ft``; JSBSim's terrain is at elevation 0).
velocity
    JSBSim's ground velocity in the local NED frame.
attitude, rates
    3-2-1 Euler angles (yaw wrapped to [-pi, pi)); body rates relative to the Earth (what a gyro of our flat,
    non-rotating Earth measures; JSBSim's Earth rotates, 7.3e-5 rad/s, which this leaves out).
specific force
    JSBSim's ``accelerations/a-pilot-*`` at the eye point, which the aircraft file puts at the CG: FRD, gravity
    excluded, so level unaccelerated flight reads ``(g sin(theta), 0, -g cos(theta))``.  JSBSim evaluates it
    from the forces at the start of the step, so it lags the rest of the state by one step (``dt_s``).
air data
    TAS, alpha and beta computed here from the ground velocity, the attitude and the total wind, all at the end
    of the step (JSBSim's own air data lag by one step); the same wind is the one JSBSim flies the next step in.

Cost (the loop runs 240 times per simulated second): the property nodes are looked up once; a step writes the
commands only when the autopilot hands over a new :class:`ControlCommand` (it holds them between its loop
updates), writes the wind, reads 15 values and builds the truth with one array (its vectors are views of it) and
one named tuple.  JSBSim's own step (about 6 us, after the aircraft file dropped four contact points that never
touch in a flight) is the floor.

Trim: JSBSim's ``simulation/do_simple_trim`` cannot trim this aircraft (it evaluates with integration suspended,
which freezes the propeller's speed, so thrust does not follow the throttle) and it resets the wind.  We solve the
steady straight-and-level, wings-level state ourselves (alpha, beta, throttle, elevator, aileron, rudder that zero
the six body accelerations) with ``scipy.optimize.root``, evaluating JSBSim with its integrators frozen so that
the propeller and the servos settle, then start the flight in the steady wind with the same air-relative state.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Final

import numpy as np
from scipy.optimize import root

from common.angles import wrap_pi
from common.config import In, Validated, require
from sim.truth import TruthState
from sim.wind import WindField, WindParams

FT_M: Final = 0.3048
AIRCRAFT_ROOT: Final = Path(__file__).resolve().parent / "aircraft"
"""JSBSim root of our aircraft: ``<root>/<name>/<name>.xml`` with ``engine/`` and ``systems/`` beside it."""
WGS84_A_M: Final = 6378137.0
WGS84_E2: Final = 6.69437999014e-3
STANDARD_G_M_S2: Final = 9.80665

_INTEGRATORS: Final = (
    "simulation/integrator/rate/rotational",
    "simulation/integrator/rate/translational",
    "simulation/integrator/position/rotational",
    "simulation/integrator/position/translational",
)
_TRIM_X0: Final = (0.03, 0.3, 0.0, 0.0, 0.0, 0.0)
"""Trim unknowns' start: alpha (rad), throttle, elevator, beta (rad), aileron, rudder."""
_TRIM_FD_EPS: Final = 1e-5
"""Relative finite-difference step of the trim solver's Jacobian."""
_TRIM_ALPHA_LIMITS_RAD: Final = (math.radians(-10.0), math.radians(12.0))
"""Linear range of the lift curve (the aircraft file's <alphalimits>): a trim outside it is a stall."""
_TRIM_BETA_LIMIT_RAD: Final = math.radians(10.0)


class DynamicsError(RuntimeError):
    """The dynamics cannot go on: no trim at the request, non-physical state, or ground impact."""


@dataclass(frozen=True)
class DynamicsParams(Validated):
    """How the dynamics run (SI units, radians).

    ``dt_s`` is the step (default 1/240 s, so 240 Hz IMU samples exist).  ``ref_lat_rad``/``ref_lon_rad`` locate
    the NED origin on the WGS84 ellipsoid (flat ground at elevation 0 around it).  ``aircraft`` names a folder of
    :data:`AIRCRAFT_ROOT`.  ``trim_settle_steps`` is how many frozen JSBSim steps each trim evaluation runs so that
    the propeller speed and the servos settle; ``trim_tolerance`` the largest body acceleration (m/s^2, rad/s^2)
    a trim may leave.  ``ground_clearance_m``: a height above the ground below which the flight counts as having
    hit the ground.  ``max_specific_force_m_s2``: a specific force above it is taken as a numerical blow-up.
    """

    dt_s: Annotated[float, In(1e-4, 0.05)] = 1.0 / 240.0
    ref_lat_rad: Annotated[float, In(-math.radians(85.0), math.radians(85.0))] = math.radians(50.0)
    ref_lon_rad: Annotated[float, In(-math.pi, math.pi)] = math.radians(20.0)
    aircraft: str = "talon"
    trim_settle_steps: Annotated[int, In(10, 100000)] = 240
    trim_tolerance: Annotated[float, In(1e-12, 1e-1)] = 1e-6
    ground_clearance_m: Annotated[float, In(0.0, 100.0)] = 0.3
    max_specific_force_m_s2: Annotated[float, In(1.0, 1e4)] = 30.0 * STANDARD_G_M_S2

    def __post_init__(self) -> None:
        super().__post_init__()
        require((AIRCRAFT_ROOT / self.aircraft / f"{self.aircraft}.xml").is_file(), "aircraft",
                f"no aircraft file {self.aircraft!r} under {AIRCRAFT_ROOT}")


@dataclass(frozen=True, slots=True)
class ControlCommand:
    """Normalised commands to the aircraft's flight-control system (the aircraft's FCS mixes the V-tail).

    ``aileron_norm`` in [-1, 1], + rolls right; ``elevator_norm`` in [-1, 1], + pitches nose up;
    ``rudder_norm`` in [-1, 1], + yaws nose right; ``throttle_norm`` in [0, 1].  Out-of-range or non-finite
    values raise ``ValueError`` (the caller saturates).
    """

    aileron_norm: float
    elevator_norm: float
    rudder_norm: float
    throttle_norm: float

    def __post_init__(self) -> None:
        for name in ("aileron_norm", "elevator_norm", "rudder_norm"):
            v = getattr(self, name)
            if not (-1.0 <= v <= 1.0):  # also false for NaN
                raise ValueError(f"ControlCommand.{name} must be in [-1, 1], got {v!r}")
        if not (0.0 <= self.throttle_norm <= 1.0):
            raise ValueError(f"ControlCommand.throttle_norm must be in [0, 1], got {self.throttle_norm!r}")


def _radii_m(lat_rad: float) -> tuple[float, float]:
    """WGS84 meridian and prime-vertical radii of curvature at ``lat_rad``."""
    s2 = math.sin(lat_rad) ** 2
    w = math.sqrt(1.0 - WGS84_E2 * s2)
    return WGS84_A_M * (1.0 - WGS84_E2) / w**3, WGS84_A_M / w


class FlightDynamics:
    """One simulated aircraft: :meth:`trim` once, then :meth:`step` with commands; :meth:`truth` is the state."""

    def __init__(self, params: DynamicsParams, wind: WindParams, rng: np.random.Generator) -> None:
        import jsbsim  # deferred: keeps importing this module light

        if not isinstance(params, DynamicsParams):
            raise TypeError(f"params must be DynamicsParams, got {type(params).__name__}")
        self.params = params
        self.wind = WindField(wind, rng)
        if "JSBSIM_DEBUG" not in os.environ:
            jsbsim.FGJSBBase().debug_lvl = 0  # no banner and no load report unless the user asks for them
        self._jsbsim = jsbsim
        fdm = jsbsim.FGFDMExec(root_dir=str(AIRCRAFT_ROOT))
        fdm.set_aircraft_path(".")
        fdm.set_engine_path(f"{params.aircraft}/engine")
        fdm.set_systems_path(f"{params.aircraft}/systems")
        if not fdm.load_model(params.aircraft):
            raise DynamicsError(f"JSBSim could not load aircraft {params.aircraft!r} from {AIRCRAFT_ROOT}")
        fdm.set_dt(params.dt_s)
        self._fdm = fdm
        self._integrator_defaults = {k: fdm[k] for k in _INTEGRATORS}
        fdm["atmosphere/turb-type"] = 0
        self._r_m, self._r_n = _radii_m(params.ref_lat_rad)
        self._max_force2 = params.max_specific_force_m_s2**2
        self._cos_lat0 = math.cos(params.ref_lat_rad)
        pm = fdm.get_property_manager()

        def node(name: str):  # a JSBSim property node
            n = pm.get_node(name)
            if n is None:
                raise DynamicsError(f"JSBSim property {name!r} missing in aircraft {params.aircraft!r}")
            return n

        self._in = [node(n) for n in (
            "position/lat-geod-rad", "position/long-gc-rad", "position/h-agl-ft",
            "velocities/v-north-fps", "velocities/v-east-fps", "velocities/v-down-fps",
            "attitude/phi-rad", "attitude/theta-rad", "attitude/psi-rad",
            "velocities/p-rad_sec", "velocities/q-rad_sec", "velocities/r-rad_sec",
            "accelerations/a-pilot-x-ft_sec2", "accelerations/a-pilot-y-ft_sec2", "accelerations/a-pilot-z-ft_sec2",
        )]
        self._cmd_nodes = [node(n) for n in (
            "fcs/aileron-cmd-norm", "fcs/elevator-cmd-norm", "fcs/rudder-cmd-norm", "fcs/throttle-cmd-norm")]
        self._wind_nodes = [node(n) for n in (
            "atmosphere/wind-north-fps", "atmosphere/wind-east-fps", "atmosphere/wind-down-fps")]
        self._accel_nodes = [node(n) for n in (
            "accelerations/udot-ft_sec2", "accelerations/vdot-ft_sec2", "accelerations/wdot-ft_sec2",
            "accelerations/pdot-rad_sec2", "accelerations/qdot-rad_sec2", "accelerations/rdot-rad_sec2")]
        self._getters = [n.get_double_value for n in self._in]
        self._cmd_setters = [n.set_double_value for n in self._cmd_nodes]
        self._wind_setters = [n.set_double_value for n in self._wind_nodes]
        self._last_cmd: ControlCommand | None = None  # the command JSBSim holds (set again only when it changes)
        self._steps = 0
        self._truth: TruthState | None = None
        self._trim_command: ControlCommand | None = None
        self._tas_m_s = 0.0

    # ------------------------------------------------------------------------------------------------------------
    @property
    def dt_s(self) -> float:
        return self.params.dt_s

    @property
    def t_s(self) -> float:
        """Simulation time since the trim (s)."""
        return self._steps * self.params.dt_s

    @property
    def trim_command(self) -> ControlCommand:
        """The commands of the last trim (what the autopilot starts from)."""
        if self._trim_command is None:
            raise RuntimeError("FlightDynamics.trim() has not been called")
        return self._trim_command

    def _freeze(self, frozen: bool) -> None:
        for k in _INTEGRATORS:
            self._fdm[k] = 0 if frozen else self._integrator_defaults[k]

    def _set_commands(self, aileron: float, elevator: float, rudder: float, throttle: float) -> None:
        sa, se, sr, st = self._cmd_setters
        sa(aileron)
        se(elevator)
        sr(rudder)
        st(throttle)
        self._last_cmd = None

    def _set_wind(self, wn_m_s: float, we_m_s: float, wd_m_s: float) -> None:
        sn, se, sd = self._wind_setters
        sn(wn_m_s / FT_M)
        se(we_m_s / FT_M)
        sd(wd_m_s / FT_M)

    def _latlon(self, north_m: float, east_m: float) -> tuple[float, float]:
        p = self.params
        return p.ref_lat_rad + north_m / self._r_m, p.ref_lon_rad + east_m / (self._r_n * self._cos_lat0)

    # ------------------------------------------------------------------------------------------------------------
    def _trim_residual(self, x: np.ndarray, lat: float, lon: float, height_m: float, airspeed_m_s: float,
                       yaw_rad: float, settle_steps: int) -> np.ndarray:
        """Body accelerations of the frozen aircraft at trim unknowns ``x`` (still air, wings level, gamma 0)."""
        alpha, throttle, elevator, beta, aileron, rudder = (float(v) for v in x)
        fdm = self._fdm
        self._freeze(False)
        fdm["ic/lat-geod-rad"] = lat
        fdm["ic/long-gc-rad"] = lon
        fdm["ic/h-agl-ft"] = height_m / FT_M
        fdm["ic/psi-true-rad"] = yaw_rad
        fdm["ic/vt-fps"] = airspeed_m_s / FT_M
        fdm["ic/gamma-rad"] = 0.0
        fdm["ic/alpha-rad"] = alpha
        fdm["ic/beta-rad"] = beta
        fdm["ic/phi-rad"] = 0.0
        for r in ("ic/p-rad_sec", "ic/q-rad_sec", "ic/r-rad_sec"):
            fdm[r] = 0.0
        self._set_commands(aileron, elevator, rudder, throttle)
        fdm.run_ic()
        self._set_wind(0.0, 0.0, 0.0)
        self._freeze(True)
        for _ in range(settle_steps):
            fdm.run()
        acc = np.array([n.get_double_value() for n in self._accel_nodes])
        acc[:3] *= FT_M
        return acc

    def trim(self, north_m: float, east_m: float, height_m: float, airspeed_m_s: float,
             yaw_rad: float) -> ControlCommand:
        """Start (or restart) the flight in steady straight-and-level flight; returns the trim commands.

        ``height_m`` above the ground, ``airspeed_m_s`` true airspeed, ``yaw_rad`` heading.  The wind field is
        reset (time 0) and the aircraft starts with the trimmed air-relative state in the wind at its height.
        Raises ``ValueError`` on bad input and :class:`DynamicsError` when the aircraft cannot fly that state
        (below the stall or above what full throttle gives).
        """
        for name, v in (("north_m", north_m), ("east_m", east_m), ("height_m", height_m),
                        ("airspeed_m_s", airspeed_m_s), ("yaw_rad", yaw_rad)):
            if not math.isfinite(v):
                raise ValueError(f"trim: {name} must be finite, got {v!r}")
        if not (self.params.ground_clearance_m < height_m <= 10000.0):
            raise ValueError(f"trim: height_m must be in ({self.params.ground_clearance_m}, 10000], got {height_m}")
        if not (1.0 <= airspeed_m_s <= 100.0):
            raise ValueError(f"trim: airspeed_m_s must be in [1, 100], got {airspeed_m_s}")
        if max(abs(north_m), abs(east_m)) > 1e6:
            raise ValueError(f"trim: north_m/east_m must be within 1000 km of the reference, got {north_m}, {east_m}")
        lat, lon = self._latlon(north_m, east_m)
        yaw = float(wrap_pi(yaw_rad))
        settle = self.params.trim_settle_steps

        def fun(x: np.ndarray) -> np.ndarray:
            return self._trim_residual(x, lat, lon, height_m, airspeed_m_s, yaw, settle)

        fun(np.array(_TRIM_X0))  # spin the propeller up from rest at low throttle before the solver moves it
        sol = root(fun, np.array(_TRIM_X0), method="hybr", options={"xtol": 1e-12, "eps": _TRIM_FD_EPS})
        x = sol.x
        resid = np.abs(self._trim_residual(x, lat, lon, height_m, airspeed_m_s, yaw, 2 * settle)).max()
        alpha, throttle, elevator, beta, aileron, rudder = (float(v) for v in x)
        problems = []
        if not (sol.success and resid <= self.params.trim_tolerance):
            problems.append(f"solver did not converge (largest residual acceleration {resid:.3g})")
        if not (_TRIM_ALPHA_LIMITS_RAD[0] <= alpha <= _TRIM_ALPHA_LIMITS_RAD[1]):
            problems.append(f"alpha {math.degrees(alpha):.1f} deg is outside the lift curve's linear range (stall)")
        if not (0.0 <= throttle <= 1.0):
            problems.append(f"needs throttle {throttle:.3f} outside [0, 1]")
        if abs(beta) > _TRIM_BETA_LIMIT_RAD or max(abs(elevator), abs(aileron), abs(rudder)) > 1.0:
            problems.append("needs control deflections beyond their travel")
        if problems:
            raise DynamicsError(f"cannot trim at airspeed {airspeed_m_s} m/s, height {height_m} m: "
                                + "; ".join(problems))
        cmd = ControlCommand(aileron_norm=aileron, elevator_norm=elevator, rudder_norm=rudder,
                             throttle_norm=throttle)

        # Start in the wind with the trimmed air-relative state: ground velocity = air velocity + steady wind.
        self.wind.reset()
        wn, we, wd, sn, se = self.wind.advance(0.0, 0.0, height_m, airspeed_m_s)
        ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
        v_air_b = airspeed_m_s * np.array([ca * cb, sb, sa * cb])
        ct, st, cy, sy = math.cos(alpha), math.sin(alpha), math.cos(yaw), math.sin(yaw)  # theta = alpha, phi = 0
        r_nb = np.array([[ct * cy, -sy, st * cy], [ct * sy, cy, st * sy], [-st, 0.0, ct]])
        v_ground = r_nb @ v_air_b + np.array([sn, se, 0.0])
        fdm = self._fdm
        self._freeze(False)
        fdm["ic/lat-geod-rad"] = lat
        fdm["ic/long-gc-rad"] = lon
        fdm["ic/h-agl-ft"] = height_m / FT_M
        fdm["ic/phi-rad"] = 0.0
        fdm["ic/theta-rad"] = alpha
        fdm["ic/psi-true-rad"] = yaw
        fdm["ic/vn-fps"] = float(v_ground[0]) / FT_M
        fdm["ic/ve-fps"] = float(v_ground[1]) / FT_M
        fdm["ic/vd-fps"] = float(v_ground[2]) / FT_M
        for r in ("ic/p-rad_sec", "ic/q-rad_sec", "ic/r-rad_sec"):
            fdm[r] = 0.0
        self._set_commands(aileron, elevator, rudder, throttle)
        fdm.run_ic()  # resets JSBSim's wind: set ours after it
        self._set_wind(wn, we, wd)
        self._steps = 0
        self._trim_command = cmd
        self._last_cmd = cmd
        self._tas_m_s = airspeed_m_s
        self._truth = self._read_truth([g() for g in self._getters], wn, we, wd, sn, se)
        return cmd

    # ------------------------------------------------------------------------------------------------------------
    def step(self, cmd: ControlCommand) -> TruthState:
        """Fly one step of ``dt_s`` with ``cmd``; returns the truth at the end of the step.

        The commands are written to JSBSim only when ``cmd`` is a different object from the last one (a
        :class:`ControlCommand` is immutable, so an autopilot that holds its output between its own updates costs
        no property writes).  Raises :class:`DynamicsError` when the aircraft hits the ground or the state stops
        being physical; the flight then needs a new :meth:`trim`.
        """
        if self._truth is None:
            raise RuntimeError("FlightDynamics.trim() must be called before step()")
        if cmd is not self._last_cmd:
            if not isinstance(cmd, ControlCommand):
                raise TypeError(f"cmd must be a ControlCommand, got {type(cmd).__name__}")
            self._set_commands(cmd.aileron_norm, cmd.elevator_norm, cmd.rudder_norm, cmd.throttle_norm)
            self._last_cmd = cmd
        self._fdm.run()
        self._steps += 1
        state = [g() for g in self._getters]
        dt = self.params.dt_s
        try:
            wn, we, wd, sn, se = self.wind.advance(self._steps * dt, dt, state[2] * FT_M, self._tas_m_s)
            self._set_wind(wn, we, wd)  # the wind of the next step, at the new state
            truth = self._read_truth(state, wn, we, wd, sn, se)
        except (DynamicsError, ValueError) as e:
            self._truth = None  # the flight is over: step() now asks for a new trim
            raise DynamicsError(str(e)) from e
        self._truth = truth
        self._tas_m_s = truth.tas_m_s
        return truth

    def truth(self) -> TruthState:
        """The truth after the last :meth:`step` (or at the trim)."""
        if self._truth is None:
            raise RuntimeError("FlightDynamics.trim() must be called before truth()")
        return self._truth

    def _read_truth(self, state: list[float], wn: float, we: float, wd: float, sn: float, se: float) -> TruthState:
        """The truth from JSBSim's ``state`` (the values of the nodes ``_in``, JSBSim units) and the total
        (``wn, we, wd``) and steady (``sn, se``) wind, in m/s.

        Cost: the state's vectors are views of one array built per step (one allocation instead of six), and the
        named tuple is built by ``_make`` (no keyword handling).
        """
        (lat, lon, h_ft, vn_f, ve_f, vd_f, phi, theta, psi, p, q, r, ax_f, ay_f, az_f) = state
        p0 = self.params
        height = h_ft * FT_M
        vn, ve, vd = vn_f * FT_M, ve_f * FT_M, vd_f * FT_M
        # air-relative velocity in the body frame: R_bn (v - w)
        an, ae, ad = vn - wn, ve - we, vd - wd
        cf, sf, ct, st, cp, sp = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta), math.cos(psi), \
            math.sin(psi)
        u = ct * cp * an + ct * sp * ae - st * ad
        v = (sf * st * cp - cf * sp) * an + (sf * st * sp + cf * cp) * ae + sf * ct * ad
        w = (cf * st * cp + sf * sp) * an + (cf * st * sp - sf * cp) * ae + cf * ct * ad
        tas = math.sqrt(u * u + v * v + w * w)
        alpha = math.atan2(w, u)
        beta = math.asin(max(-1.0, min(1.0, v / tas))) if tas > 0.0 else 0.0
        ax, ay, az = ax_f * FT_M, ay_f * FT_M, az_f * FT_M
        t = self._steps * p0.dt_s
        # a sum is finite only if every term is (NaN and inf propagate)
        if not math.isfinite(lat + lon + height + vn + ve + vd + phi + theta + psi + p + q + r + tas + ax + ay + az):
            raise DynamicsError(f"non-finite state at t={t:.3f} s")
        f2 = ax * ax + ay * ay + az * az
        if f2 > self._max_force2:
            raise DynamicsError(f"specific force {math.sqrt(f2):.0f} m/s^2 at t={t:.3f} s exceeds "
                                f"{p0.max_specific_force_m_s2:.0f} m/s^2: numerical blow-up or impact")
        if height < p0.ground_clearance_m:
            raise DynamicsError(f"the aircraft hit the ground at t={t:.3f} s (height {height:.2f} m)")
        north = (lat - p0.ref_lat_rad) * self._r_m
        east = (lon - p0.ref_lon_rad) * self._r_n * self._cos_lat0
        buf = np.array((north, east, -height, vn, ve, vd, p, q, r, ax, ay, az, wn, we, wd, sn, se, 0.0))
        # TruthState._make takes the fields in their declared order (tests/test_dynamics.py checks each one)
        return TruthState._make((
            t,  # t_s
            buf[0:3],  # pos_ned_m
            buf[3:6],  # vel_ned_m_s
            phi,  # roll_rad
            theta,  # pitch_rad
            float(wrap_pi(psi)),  # yaw_rad
            buf[6:9],  # rates_b_rad_s
            buf[9:12],  # accel_b_m_s2
            tas,  # tas_m_s
            alpha,  # alpha_rad
            beta,  # beta_rad
            buf[12:15],  # wind_ned_m_s
            buf[15:18],  # wind_steady_ned_m_s
            height,  # height_agl_m
        ))
