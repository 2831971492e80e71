"""What a scenario flies: its wind, the JSBSim dynamics trimmed at the mission's start, the autopilot on the
mission and the sensor suite, built from the scenario and a seed.

``gsoe sim`` (:func:`sim.run.run_flight`) and the SIL vehicle flying a scenario (``python -m sim.mavlink_vehicle
--dynamics jsbsim --scenario NAME --fly-scenario``) both build their flight here, so that one scenario and seed give
both the same truth and the same sensor errors.  The seeding: ``rng = numpy.random.default_rng(seed)``, then
``rng_dyn, rng_sens, rng_cam = rng.spawn(3)`` (turbulence and gusts; the sensors' true errors and noise; the
rendered frames' noise); the ground texture is ``GroundWorld.from_name(scn.terrain.texture, seed=seed)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.autopilot import Autopilot, Waypoint
from sim.dynamics import DynamicsParams, FlightDynamics
from sim.scenario import Scenario
from sim.sensors import SensorSuite
from sim.wind import LIGHT_W20_M_S, WindParams

# Milspec W20 (wind speed at 20 ft) per scenario severity: light 15 kt, moderate 30 kt, severe 45 kt.
SEVERITY_W20_M_S = {"light": LIGHT_W20_M_S, "moderate": 2.0 * LIGHT_W20_M_S, "severe": 3.0 * LIGHT_W20_M_S}


def wind_params(scn: Scenario) -> WindParams:
    """The wind field of ``scn`` (steady wind with shear, Dryden turbulence, discrete gusts)."""
    w = scn.wind
    return WindParams(
        speed_m_s=w.speed_m_s, from_rad=w.from_rad, ref_height_m=w.ref_height_m, shear=w.shear,
        roughness_m=w.roughness_m, turbulence=w.turbulence,
        turbulence_w20_m_s=SEVERITY_W20_M_S[w.turbulence_severity], turbulence_scale=w.turbulence_scale,
        gusts=w.gusts, gust_amplitude_m_s=w.gust_amplitude_m_s, gust_length_m=w.gust_length_m,
        gust_rate_hz=1.0 / w.gust_interval_s if w.gusts and w.gust_interval_s > 0 else 0.0,
        turbulence_rate_hz=w.turbulence_rate_hz,
    )


@dataclass(frozen=True)
class Flight:
    """One scenario's plant: step it with ``truth = dyn.step(autopilot.update(truth, scn.dt_s))`` and
    ``sensors.step(truth)``; ``rng_cam`` is the generator of the rendered frames' noise."""

    dyn: FlightDynamics
    autopilot: Autopilot
    sensors: SensorSuite
    rng_cam: np.random.Generator


def build_flight(scn: Scenario, seed: int) -> Flight:
    """The dynamics (trimmed at ``scn.mission.start``), the autopilot flying ``scn.mission`` and the sensors of
    ``scn``, seeded from ``seed`` (module docstring)."""
    rng = np.random.default_rng(seed)
    rng_dyn, rng_sens, rng_cam = rng.spawn(3)
    dyn = FlightDynamics(DynamicsParams(dt_s=scn.dt_s), wind_params(scn), rng_dyn)
    st = scn.mission.start
    trim = dyn.trim(st.north_m, st.east_m, st.height_m, st.airspeed_m_s, st.yaw_rad)
    ap = Autopilot(trim=trim)
    ap.set_mission([Waypoint(w.north_m, w.east_m, w.height_m, w.airspeed_m_s) for w in scn.mission.waypoints],
                   loop=scn.mission.loop)
    return Flight(dyn, ap, SensorSuite(scn.sensors, scn.camera, rng_sens), rng_cam)


__all__ = ["Flight", "SEVERITY_W20_M_S", "build_flight", "wind_params"]
