"""The simulated aircraft's autopilot: attitude loops, energy split, L1 waypoint guidance and heading hold.

It flies the simulator's truth (this autopilot is part of the plant of the software-in-the-loop simulation, not
the navigation module under test), so it reads a :class:`sim.truth.TruthState` and returns a
:class:`sim.dynamics.ControlCommand`.

Structure
---------
inner loops
    roll: ``p_cmd = k (phi_cmd - phi) - psi_dot sin(theta)`` (limited; the second term is the body roll rate of a
    steady coordinated turn), aileron = PI on the roll-rate error plus a feed-forward;
    pitch: ``q_cmd = k (theta_cmd - theta) + q_turn`` (the coordinated-turn pitch rate ``psi_dot sin(phi)``),
    elevator = PI on the pitch-rate error plus a feed-forward; yaw: rudder = PI on sideslip plus a yaw damper
    about the coordinated-turn yaw rate.  Surface gains scale with ``(airspeed_ref / airspeed)^2`` (dynamic
    pressure).  Integrators start at the trim commands and stop integrating while their output saturates
    (anti-windup).
energy split
    pitch flies the climb rate (``climb_cmd = k (h_cmd - h)`` within the climb/sink limits, PI on the climb-rate
    error, plus the flight-path feed-forward ``asin(climb_cmd / V)`` and the turn's extra angle of attack);
    throttle flies the airspeed (PI, plus a feed-forward on the commanded climb rate, the power a climb needs).
    Roll is limited to +-``roll_limit_rad`` (45 deg) and pitch to +-``pitch_limit_rad`` (20 deg).
lateral guidance
    L1 (S. Park, J. Deyst, J. P. How, "A new nonlinear guidance logic for trajectory tracking", AIAA GNC 2004):
    lateral acceleration ``a = 2 V^2 sin(eta) / L1`` toward the point of the leg ``L1 = damping period V / pi``
    ahead, on the ground velocity (so it flies ground tracks in wind); roll = ``atan(a / g)``.  A waypoint is
    reached within ``waypoint_radius_m``, within the turn-anticipation distance ``R tan(turn / 2)`` (R the turn
    radius at the roll limit) or when the aircraft passes the line through the waypoint normal to the leg.
    Missions loop.  Heading hold (``set_heading_command``) commands roll from the heading error; roll hold
    (``set_roll_command``) holds a bank angle, both with height and airspeed hold.

Rates
-----
As on a real autopilot the loops run at their own rates, not at the dynamics step, and their outputs are held
(zero-order hold) until they run again: the lateral guidance and the energy split (roll and pitch commands,
throttle) at ``guidance_rate_hz`` (50 Hz), the attitude and rate loops (surface commands) at
``attitude_rate_hz`` (50 Hz).  ArduPlane does the same: its scheduler runs the attitude and rate controllers
(``stabilize``) in the main loop, whose default rate for planes is 50 Hz (``SCHEDULER_DEFAULT_LOOP_RATE`` in
``AP_Scheduler.cpp``), TECS at 50 Hz and the L1 navigation at 10 Hz (``Plane.cpp``'s scheduler table); hobby
servos take a new pulse every 20 ms (50 Hz) and ours lag 0.04 s (the aircraft file), which smooths the steps of
the hold.  A loop runs at the first call at or after each multiple of its period on the autopilot's clock (the
sum of the ``dt_s`` it was given), so its rate is exact on average whatever the dynamics step; its integrators
integrate over the time since its previous run.  A mode change makes the guidance run at the next call.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Final, Literal

import numpy as np

from common.angles import wrap_pi
from common.config import In, Validated, require
from sim.dynamics import STANDARD_G_M_S2, ControlCommand
from sim.truth import TruthState

G_M_S2: Final = STANDARD_G_M_S2
SCHEDULE_TOLERANCE_S: Final = 1e-9
"""A loop is due when the autopilot's clock is within this of its scheduled time (absorbs the rounding of a clock
summed from steps)."""

Mode = Literal["idle", "mission", "heading", "roll"]
Gain = Annotated[float, In(0.0, 100.0)]
"""A loop gain or feed-forward (normalised command per rad, rad/s, m or m/s)."""
_HEIGHT_M = In(1.0, 10000.0)
_AIRSPEED_M_S = In(5.0, 60.0)
_RateHz = Annotated[float, In(1.0, 10000.0)]
_RateLimitRadS = Annotated[float, In(0.05, 10.0)]
_VerticalSpeedMS = Annotated[float, In(0.1, 20.0)]
_Throttle = Annotated[float, In(0.0, 1.0)]


@dataclass(frozen=True)
class Waypoint(Validated):
    """A mission waypoint: NED position of the point (height above the ground) and the airspeed to fly to it."""

    north_m: Annotated[float, In(-1e6, 1e6)]
    east_m: Annotated[float, In(-1e6, 1e6)]
    height_m: Annotated[float, _HEIGHT_M]
    airspeed_m_s: Annotated[float, _AIRSPEED_M_S]


@dataclass(frozen=True)
class AutopilotGains(Validated):
    """Gains and limits (SI units, radians; surface gains in normalised command per rad or rad/s)."""

    roll_limit_rad: Annotated[float, In(math.radians(5.0), math.radians(75.0))] = math.radians(45.0)
    pitch_limit_rad: Annotated[float, In(math.radians(2.0), math.radians(45.0))] = math.radians(20.0)
    roll_rate_limit_rad_s: _RateLimitRadS = math.radians(90.0)
    pitch_rate_limit_rad_s: _RateLimitRadS = math.radians(60.0)
    # roll: attitude -> rate -> aileron
    roll_kp: Gain = 3.5
    roll_rate_kp: Gain = 0.15
    roll_rate_ki: Gain = 0.15
    roll_rate_ff: Gain = 0.42
    # pitch: attitude -> rate -> elevator
    pitch_kp: Gain = 3.0
    pitch_rate_kp: Gain = 0.25
    pitch_rate_ki: Gain = 0.5
    pitch_rate_ff: Gain = 0.1
    # yaw: sideslip PI and yaw damper
    beta_kp: Gain = 1.5
    beta_ki: Gain = 1.0
    yaw_damper_kp: Gain = 0.15
    # surface gains are for this airspeed and scale with its square over the actual one's
    airspeed_ref_m_s: Annotated[float, _AIRSPEED_M_S] = 20.0
    gain_scale_min: Annotated[float, In(0.01, 1.0)] = 0.3
    gain_scale_max: Annotated[float, In(1.0, 100.0)] = 3.0
    # height -> climb rate -> pitch
    height_kp: Gain = 0.3
    climb_rate_max_m_s: _VerticalSpeedMS = 3.0
    sink_rate_max_m_s: _VerticalSpeedMS = 2.5
    climb_kp: Gain = 0.06
    climb_ki: Gain = 0.03
    pitch_turn_ff_rad: Gain = 0.06
    # airspeed -> throttle
    airspeed_kp: Gain = 0.12
    airspeed_ki: Gain = 0.05
    throttle_climb_ff: Gain = 0.08
    throttle_min: _Throttle = 0.0
    throttle_max: _Throttle = 1.0
    # lateral guidance
    l1_period_s: Annotated[float, In(1.0, 100.0)] = 11.0
    l1_damping: Annotated[float, In(0.1, 2.0)] = 0.75
    heading_kp: Gain = 1.0
    waypoint_radius_m: Annotated[float, In(0.0, 10000.0)] = 15.0
    integrator_limit: Annotated[float, In(0.0, 1.0)] = 0.5
    # loop rates (see the module docstring): outer loops (guidance, energy) and inner loops (attitude, rates)
    guidance_rate_hz: _RateHz = 50.0
    attitude_rate_hz: _RateHz = 50.0

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.throttle_min < self.throttle_max, "throttle_max", "must be above throttle_min")
        require(self.guidance_rate_hz <= self.attitude_rate_hz, "guidance_rate_hz",
                f"the outer loops must not run faster than the inner ones (attitude_rate_hz = {self.attitude_rate_hz})")


def _clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


class _PI:
    """PI with a clamped integrator that stops integrating while the output saturates (anti-windup)."""

    __slots__ = ("kp", "ki", "i", "i_min", "i_max")

    def __init__(self, kp: float, ki: float, i0: float, i_min: float, i_max: float) -> None:
        self.kp, self.ki, self.i, self.i_min, self.i_max = kp, ki, i0, i_min, i_max

    def update(self, err: float, dt: float, extra: float, scale: float, lo: float, hi: float) -> float:
        """``extra + scale * (kp err) + i``, clipped to [lo, hi]; ``i`` integrates ``scale * ki * err``."""
        p_term = extra + scale * self.kp * err
        out = p_term + self.i
        if lo < out < hi or (out >= hi and err < 0.0) or (out <= lo and err > 0.0):
            i = self.i + scale * self.ki * err * dt
            self.i = i = self.i_min if i < self.i_min else self.i_max if i > self.i_max else i  # _clip, written out
            out = p_term + i
        return lo if out < lo else hi if out > hi else out


class _LoopClock:
    """Schedule of one loop of period ``period_s``: due at the first call at or after each multiple of the period."""

    __slots__ = ("period_s", "next_s", "last_s")

    def __init__(self, rate_hz: float) -> None:
        self.period_s = 1.0 / rate_hz
        self.next_s = -math.inf
        self.last_s: float | None = None

    def run(self, t_s: float, dt_s: float) -> float:
        """Mark a run at ``t_s``; returns the time to integrate over (since the previous run; at the first run the
        interval the output will be held, one period or one step if longer)."""
        dt = max(self.period_s, dt_s) if self.last_s is None else t_s - self.last_s
        self.last_s = t_s
        self.next_s = (math.floor((t_s + SCHEDULE_TOLERANCE_S) / self.period_s) + 1.0) * self.period_s
        return dt


class Autopilot:
    """Autopilot of the simulated aircraft; call :meth:`update` every dynamics step.

    ``trim`` is the trim command of :meth:`sim.dynamics.FlightDynamics.trim`; the integrators start there so the
    hand-over is smooth.  Until a mode is set the autopilot holds wings level at the height and airspeed of the
    first truth it sees.
    """

    def __init__(self, gains: AutopilotGains | None = None, trim: ControlCommand | None = None) -> None:
        g = gains if gains is not None else AutopilotGains()
        if not isinstance(g, AutopilotGains):
            raise TypeError(f"gains must be AutopilotGains, got {type(g).__name__}")
        t = trim if trim is not None else ControlCommand(0.0, 0.0, 0.0, 0.5)
        self.gains = g
        lim = g.integrator_limit
        self._roll_pi = _PI(g.roll_rate_kp, g.roll_rate_ki, t.aileron_norm, -lim, lim)
        self._pitch_pi = _PI(g.pitch_rate_kp, g.pitch_rate_ki, t.elevator_norm, -lim, lim)
        self._yaw_pi = _PI(g.beta_kp, g.beta_ki, t.rudder_norm, -lim, lim)
        self._speed_pi = _PI(g.airspeed_kp, g.airspeed_ki, t.throttle_norm, g.throttle_min, g.throttle_max)
        self._climb_pi: _PI | None = None  # its integrator starts at the first truth's pitch
        self._mode: Mode = "idle"
        self._waypoints: list[Waypoint] = []
        self._loop = True
        self._index = 0
        self._leg_start: tuple[float, float] | None = None
        self._heading_cmd = 0.0
        self._roll_hold = 0.0
        self._height_cmd: float | None = None
        self._airspeed_cmd: float | None = None
        self.waypoints_reached = 0
        self.roll_cmd_rad = 0.0
        self.pitch_cmd_rad = 0.0
        self.climb_cmd_m_s = 0.0
        self._throttle = t.throttle_norm
        self._clock_s = 0.0
        self._guidance_clock = _LoopClock(g.guidance_rate_hz)
        self._attitude_clock = _LoopClock(g.attitude_rate_hz)
        self._cmd: ControlCommand | None = None  # the held surface and throttle command

    # ------------------------------------------------------------------------------------------------------------
    @property
    def mode(self) -> Mode:
        return self._mode

    @property
    def waypoint_index(self) -> int:
        """Index of the waypoint being flown to (mission mode)."""
        return self._index

    @property
    def height_cmd_m(self) -> float | None:
        return self._height_cmd

    @property
    def airspeed_cmd_m_s(self) -> float | None:
        return self._airspeed_cmd

    def set_mission(self, waypoints: Sequence[Waypoint], loop: bool = True) -> None:
        """Fly ``waypoints`` in order (looping back to the first when ``loop``; otherwise it flies on along the last
        leg after the last waypoint); the first leg starts where the aircraft is at the next :meth:`update`."""
        wps = list(waypoints)
        if len(wps) < 2:
            raise ValueError(f"a mission needs at least 2 waypoints, got {len(wps)}")
        for i, w in enumerate(wps):
            if not isinstance(w, Waypoint):
                raise TypeError(f"waypoints[{i}] must be a Waypoint, got {type(w).__name__}")
        self._waypoints = wps
        self._loop = loop
        self._index = 0
        self._leg_start = None
        self._mode = "mission"
        self.waypoints_reached = 0
        self._guidance_clock.next_s = -math.inf

    def set_heading_command(self, yaw_rad: float, height_m: float | None = None,
                            airspeed_m_s: float | None = None) -> None:
        """Hold heading ``yaw_rad``; height and airspeed are held at the given values (None: keep the current
        commands)."""
        if not math.isfinite(yaw_rad):
            raise ValueError(f"yaw_rad must be finite, got {yaw_rad!r}")
        self._set_targets(height_m, airspeed_m_s)
        self._heading_cmd = float(wrap_pi(yaw_rad))
        self._mode = "heading"
        self._guidance_clock.next_s = -math.inf

    def set_roll_command(self, roll_rad: float, height_m: float | None = None,
                         airspeed_m_s: float | None = None) -> None:
        """Hold bank angle ``roll_rad`` (limited to the roll limit) with height and airspeed hold."""
        if not math.isfinite(roll_rad):
            raise ValueError(f"roll_rad must be finite, got {roll_rad!r}")
        self._set_targets(height_m, airspeed_m_s)
        self._roll_hold = _clip(roll_rad, -self.gains.roll_limit_rad, self.gains.roll_limit_rad)
        self._mode = "roll"
        self._guidance_clock.next_s = -math.inf

    def _set_targets(self, height_m: float | None, airspeed_m_s: float | None) -> None:
        if height_m is not None:
            _HEIGHT_M.check(height_m, "height_m")
            self._height_cmd = float(height_m)
        if airspeed_m_s is not None:
            _AIRSPEED_M_S.check(airspeed_m_s, "airspeed_m_s")
            self._airspeed_cmd = float(airspeed_m_s)

    # ------------------------------------------------------------------------------------------------------------
    def _l1_roll(self, truth: TruthState) -> float:
        g = self.gains
        pn, pe, _ = truth.pos_ned_m.tolist()
        if self._leg_start is None:
            self._leg_start = (pn, pe)
        wp = self._waypoints[self._index]
        vn, ve, _ = truth.vel_ned_m_s.tolist()
        gs = max(math.hypot(vn, ve), 1.0)
        # waypoint switching: acceptance radius, turn anticipation, or passing the normal through the waypoint
        while True:
            an, ae = self._leg_start
            bn, be = wp.north_m, wp.east_m
            leg = math.hypot(bn - an, be - ae)
            tn, te = ((bn - an) / leg, (be - ae) / leg) if leg > 1e-6 else (vn / gs, ve / gs)
            dist = math.hypot(bn - pn, be - pe)
            nxt = self._next_index()
            anticipation = 0.0
            if nxt is not None:
                w2 = self._waypoints[nxt]
                dn, de = w2.north_m - bn, w2.east_m - be
                turn = abs(math.atan2(tn * de - te * dn, tn * dn + te * de))  # angle between the legs
                radius = gs * gs / (G_M_S2 * math.tan(g.roll_limit_rad))
                anticipation = radius * math.tan(min(turn, math.radians(150.0)) / 2.0)
            passed = (pn - bn) * tn + (pe - be) * te > 0.0
            if nxt is not None and (dist < max(g.waypoint_radius_m, anticipation) or passed):
                self.waypoints_reached += 1
                self._leg_start = (bn, be)
                self._index = nxt
                wp = self._waypoints[nxt]
                continue
            break
        self._height_cmd = wp.height_m
        self._airspeed_cmd = wp.airspeed_m_s
        # L1 reference point on the leg
        l1 = max(g.l1_damping * g.l1_period_s * gs / math.pi, 1.0)
        rn, re = pn - an, pe - ae
        along = rn * tn + re * te
        cross = tn * re - te * rn  # positive right of the leg
        if abs(cross) < l1:
            ahead = along + math.sqrt(l1 * l1 - cross * cross)
        else:
            ahead = along
        refn, refe = an + tn * ahead - pn, ae + te * ahead - pe
        eta = math.atan2(vn * refe - ve * refn, vn * refn + ve * refe)  # from the ground velocity to the L1 vector
        eta = _clip(eta, -math.pi / 2.0, math.pi / 2.0)
        dist_ref = max(math.hypot(refn, refe), 1.0)
        accel = 2.0 * gs * gs * math.sin(eta) / dist_ref
        return math.atan(accel / G_M_S2)

    def _next_index(self) -> int | None:
        n = self._index + 1
        if n < len(self._waypoints):
            return n
        return 0 if self._loop else None

    def update(self, truth: TruthState, dt_s: float) -> ControlCommand:
        """Commands for the next ``dt_s`` from the truth now.

        Each loop runs when it is due (see the module docstring); in between the last command is returned (the
        same object, so :meth:`sim.dynamics.FlightDynamics.step` need not write it again).
        """
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f"dt_s must be finite and > 0, got {dt_s!r}")
        t = self._clock_s
        self._clock_s = t + dt_s
        gc, ac = self._guidance_clock, self._attitude_clock
        if t >= gc.next_s - SCHEDULE_TOLERANCE_S:
            self._guidance(truth, gc.run(t, dt_s))
        if self._cmd is None or t >= ac.next_s - SCHEDULE_TOLERANCE_S:
            self._cmd = self._attitude(truth, ac.run(t, dt_s))
        return self._cmd

    def _guidance(self, truth: TruthState, dt_s: float) -> None:
        """Outer loops: roll command (lateral mode), pitch command (climb rate) and throttle (airspeed)."""
        g = self.gains
        phi, theta = truth.roll_rad, truth.pitch_rad
        tas = max(truth.tas_m_s, 1.0)
        height = truth.height_agl_m
        if self._height_cmd is None:
            self._height_cmd = height
        if self._airspeed_cmd is None:
            self._airspeed_cmd = tas
        if self._climb_pi is None:
            self._climb_pi = _PI(g.climb_kp, g.climb_ki, theta, -g.pitch_limit_rad, g.pitch_limit_rad)

        # lateral: roll command
        if self._mode == "mission":
            roll_cmd = self._l1_roll(truth)
        elif self._mode == "heading":
            turn_rate = g.heading_kp * float(wrap_pi(self._heading_cmd - truth.yaw_rad))
            roll_cmd = math.atan(tas * turn_rate / G_M_S2)
        elif self._mode == "roll":
            roll_cmd = self._roll_hold
        else:
            roll_cmd = 0.0
        roll_cmd = _clip(roll_cmd, -g.roll_limit_rad, g.roll_limit_rad)

        # longitudinal: climb rate -> pitch, airspeed -> throttle
        climb_cmd = _clip(g.height_kp * (self._height_cmd - height), -g.sink_rate_max_m_s, g.climb_rate_max_m_s)
        climb = -float(truth.vel_ned_m_s[2])
        cphi = max(math.cos(phi), math.cos(g.roll_limit_rad))
        ff = math.asin(_clip(climb_cmd / tas, -1.0, 1.0)) + g.pitch_turn_ff_rad * (1.0 / cphi - 1.0)
        pitch_cmd = self._climb_pi.update(climb_cmd - climb, dt_s, ff, 1.0, -g.pitch_limit_rad, g.pitch_limit_rad)
        self._throttle = self._speed_pi.update(self._airspeed_cmd - tas, dt_s, g.throttle_climb_ff * climb_cmd, 1.0,
                                               g.throttle_min, g.throttle_max)
        self.roll_cmd_rad, self.pitch_cmd_rad, self.climb_cmd_m_s = roll_cmd, pitch_cmd, climb_cmd

    def _attitude(self, truth: TruthState, dt_s: float) -> ControlCommand:
        """Inner loops: attitude -> rates -> surfaces, toward the held roll and pitch commands."""
        g = self.gains
        phi, theta = truth.roll_rad, truth.pitch_rad
        p, q, r = truth.rates_b_rad_s.tolist()
        tas = max(truth.tas_m_s, 1.0)
        roll_cmd, pitch_cmd = self.roll_cmd_rad, self.pitch_cmd_rad
        scale = _clip((g.airspeed_ref_m_s / tas) ** 2, g.gain_scale_min, g.gain_scale_max)
        psi_dot = G_M_S2 * math.tan(phi) / tas  # coordinated-turn yaw rate
        sphi, cphi, stheta, ctheta = math.sin(phi), math.cos(phi), math.sin(theta), math.cos(theta)
        p_cmd = _clip(g.roll_kp * (roll_cmd - phi) - psi_dot * stheta, -g.roll_rate_limit_rad_s,
                      g.roll_rate_limit_rad_s)
        q_cmd = _clip(g.pitch_kp * (pitch_cmd - theta) + psi_dot * sphi * ctheta,
                      -g.pitch_rate_limit_rad_s, g.pitch_rate_limit_rad_s)
        r_turn = psi_dot * cphi * ctheta
        aileron = self._roll_pi.update(p_cmd - p, dt_s, scale * g.roll_rate_ff * p_cmd, scale, -1.0, 1.0)
        elevator = self._pitch_pi.update(q_cmd - q, dt_s, scale * g.pitch_rate_ff * q_cmd, scale, -1.0, 1.0)
        rudder = self._yaw_pi.update(truth.beta_rad, dt_s, -scale * g.yaw_damper_kp * (r - r_turn), scale,
                                     -1.0, 1.0)
        return ControlCommand(aileron_norm=aileron, elevator_norm=elevator, rudder_norm=rudder,
                              throttle_norm=self._throttle)

    def waypoints_array(self) -> np.ndarray:
        """The mission as an (N, 4) array of north_m, east_m, height_m, airspeed_m_s (for logs and plots)."""
        return np.array([[w.north_m, w.east_m, w.height_m, w.airspeed_m_s] for w in self._waypoints]).reshape(-1, 4)
