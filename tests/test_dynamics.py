"""Physics sanity of the simulator: JSBSim Talon-class aircraft, wind field and autopilot.

Every check compares the simulator against an independent answer: steady-flight physics (coordinated-turn rate,
the wind triangle, gravity), the analytic shapes of the wind model, or the command signs of the aircraft file.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import pytest

from common.angles import angle_diff
from common.config import ConfigError
from sim.autopilot import Autopilot, AutopilotGains, Waypoint
from sim.dynamics import ControlCommand, DynamicsError, DynamicsParams, FlightDynamics
from sim.truth import TruthState
from sim.wind import WindField, WindParams, dryden_sigmas_scales

G = 9.81
HEIGHT_M = 100.0
AIRSPEED_M_S = 20.0


@dataclass
class Flight:
    truths: list[TruthState]
    autopilot: Autopilot

    def arr(self, f) -> np.ndarray:
        return np.array([f(t) for t in self.truths])


def fly(wind: WindParams, seconds: float, setup, seed: int = 1, yaw_rad: float = 0.0) -> Flight:
    fd = FlightDynamics(DynamicsParams(), wind, np.random.default_rng(seed))
    trim = fd.trim(0.0, 0.0, HEIGHT_M, AIRSPEED_M_S, yaw_rad)
    ap = Autopilot(AutopilotGains(), trim)
    setup(ap)
    truth = fd.truth()
    out = []
    for _ in range(int(round(seconds / fd.dt_s))):
        truth = fd.step(ap.update(truth, fd.dt_s))
        out.append(truth)
    return Flight(out, ap)


# ----------------------------------------------------------------------------------------------------------------
# trim and aircraft conventions


@pytest.mark.parametrize("airspeed", [15.0, 20.0, 28.0])
def test_trims_across_the_envelope(airspeed: float) -> None:
    fd = FlightDynamics(DynamicsParams(), WindParams(), np.random.default_rng(0))
    cmd = fd.trim(0.0, 0.0, HEIGHT_M, airspeed, 0.3)
    t = fd.truth()
    assert 0.0 < cmd.throttle_norm < 1.0
    assert t.tas_m_s == pytest.approx(airspeed, abs=1e-6)
    assert abs(t.pitch_rad - t.alpha_rad) < 1e-6  # level: flight-path angle zero
    # one second open loop: still level and at speed (the trim is a true equilibrium)
    for _ in range(240):
        t = fd.step(cmd)
    assert abs(t.vel_ned_m_s[2]) < 0.05
    assert t.tas_m_s == pytest.approx(airspeed, abs=0.02)


def test_trim_alpha_falls_with_speed_and_limits_are_reported() -> None:
    fd = FlightDynamics(DynamicsParams(), WindParams(), np.random.default_rng(0))
    alphas = []
    for v in (15.0, 20.0, 28.0):
        fd.trim(0.0, 0.0, HEIGHT_M, v, 0.0)
        alphas.append(fd.truth().alpha_rad)
    assert alphas[0] > alphas[1] > alphas[2]
    # lift: L = W at C_L = 0.15 + 4.5 alpha (the aircraft file's linear lift curve, 3.5 kg, 0.42 m^2)
    rho = 1.225 * (1.0 - 2.25577e-5 * HEIGHT_M) ** 4.2559
    cl = 3.5 * G / (0.5 * rho * 20.0**2 * 0.42)
    assert alphas[1] == pytest.approx((cl - 0.15) / 4.5, abs=0.01)
    with pytest.raises(DynamicsError, match="stall|converge"):
        fd.trim(0.0, 0.0, HEIGHT_M, 9.0, 0.0)
    with pytest.raises(DynamicsError, match="throttle|converge"):
        fd.trim(0.0, 0.0, HEIGHT_M, 40.0, 0.0)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_positive_commands_give_positive_body_rates(axis: int) -> None:
    fd = FlightDynamics(DynamicsParams(), WindParams(), np.random.default_rng(0))
    trim = fd.trim(0.0, 0.0, HEIGHT_M, AIRSPEED_M_S, 0.0)
    surfaces = [trim.aileron_norm, trim.elevator_norm, trim.rudder_norm]
    surfaces[axis] += 0.2
    cmd = ControlCommand(surfaces[0], surfaces[1], surfaces[2], trim.throttle_norm)
    for _ in range(48):  # 0.2 s
        t = fd.step(cmd)
    rates = t.rates_b_rad_s
    assert rates[axis] > 0.05
    assert rates[axis] == max(rates, key=abs)


# ----------------------------------------------------------------------------------------------------------------
# flight physics under the autopilot


@pytest.fixture(scope="module")
def straight() -> Flight:
    wind = WindParams(speed_m_s=5.0, from_rad=math.radians(45.0))
    return fly(wind, 30.0, lambda ap: ap.set_heading_command(0.0, HEIGHT_M, AIRSPEED_M_S))


def test_straight_flight_holds_height_and_airspeed(straight: Flight) -> None:
    h = straight.arr(lambda t: t.height_agl_m)
    tas = straight.arr(lambda t: t.tas_m_s)
    assert np.abs(h - HEIGHT_M).max() < 3.0
    assert np.abs(tas - AIRSPEED_M_S).max() < 1.0
    assert np.abs(straight.arr(lambda t: t.roll_rad)).max() < math.radians(5.0)


def test_specific_force_in_level_flight(straight: Flight) -> None:
    late = straight.truths[-1200:]
    f = np.array([t.accel_b_m_s2 for t in late]).mean(axis=0)
    theta = float(np.mean([t.pitch_rad for t in late]))
    phi = float(np.mean([t.roll_rad for t in late]))
    # an ideal accelerometer in unaccelerated flight reads minus gravity in the body frame
    ct = math.cos(theta)
    expected = np.array([G * math.sin(theta), -G * ct * math.sin(phi), -G * ct * math.cos(phi)])
    np.testing.assert_allclose(f, expected, atol=0.05)
    np.testing.assert_allclose(f, [0.0, 0.0, -G], atol=0.6)


@pytest.mark.parametrize("roll_deg", [30.0, 45.0])
def test_coordinated_turn_rate(roll_deg: float) -> None:
    fl = fly(WindParams(), 40.0, lambda ap: ap.set_roll_command(math.radians(roll_deg), HEIGHT_M, AIRSPEED_M_S))
    late = fl.truths[15 * 240:]
    t = np.array([x.t_s for x in late])
    yaw = np.unwrap([x.yaw_rad for x in late])
    rate = np.polyfit(t, yaw, 1)[0]
    roll = float(np.mean([x.roll_rad for x in late]))
    tas = float(np.mean([x.tas_m_s for x in late]))
    assert roll == pytest.approx(math.radians(roll_deg), abs=math.radians(1.0))
    assert rate == pytest.approx(G * math.tan(roll) / tas, rel=0.05)
    assert max(abs(x.beta_rad) for x in late) < math.radians(1.0)  # coordinated
    assert max(abs(x.height_agl_m - HEIGHT_M) for x in late) < 3.0  # no stall, height held


def test_true_drift_equals_wind_triangle() -> None:
    wind = WindParams(speed_m_s=6.0, from_rad=math.radians(60.0), shear=True)
    fl = fly(wind, 35.0, lambda ap: ap.set_heading_command(math.radians(-20.0), HEIGHT_M, AIRSPEED_M_S))
    late = fl.truths[20 * 240:]
    errs, drifts = [], []
    for t in late:
        course = math.atan2(t.vel_ned_m_s[1], t.vel_ned_m_s[0])
        drift = angle_diff(course, t.yaw_rad)
        air_dir = t.yaw_rad + t.beta_rad
        gn = t.tas_m_s * math.cos(air_dir) + t.wind_steady_ned_m_s[0]
        ge = t.tas_m_s * math.sin(air_dir) + t.wind_steady_ned_m_s[1]
        drift_triangle = angle_diff(math.atan2(ge, gn), t.yaw_rad)
        errs.append(float(angle_diff(drift, drift_triangle)))
        drifts.append(float(drift))
    assert min(abs(d) for d in drifts) > math.radians(5.0)  # a real crosswind, so the check can fail
    assert max(abs(e) for e in errs) < math.radians(0.1)
    # the truth's steady wind is the sheared wind at the aircraft's height, blowing from 60 deg
    w = late[-1].wind_steady_ned_m_s
    assert math.atan2(-w[1], -w[0]) == pytest.approx(math.radians(60.0), abs=1e-9)
    assert np.hypot(w[0], w[1]) > 6.0


def test_square_mission_with_45_degree_turns() -> None:
    # a 400 m square away from the start point, one side climbing to 120 m at 22 m/s; flown once round and back
    # to its first corner
    wps = [Waypoint(300.0, 100.0, HEIGHT_M, AIRSPEED_M_S), Waypoint(300.0, 500.0, 120.0, 22.0),
           Waypoint(-100.0, 500.0, 120.0, 22.0), Waypoint(-100.0, 100.0, HEIGHT_M, AIRSPEED_M_S)]
    wind = WindParams(speed_m_s=5.0, from_rad=math.radians(45.0))
    fl = fly(wind, 120.0, lambda ap: ap.set_mission(wps))
    assert fl.autopilot.waypoints_reached >= 5  # the mission loops
    roll = np.abs(fl.arr(lambda t: t.roll_rad))
    assert roll.max() >= math.radians(40.0)
    assert roll.max() <= math.radians(47.0)
    pos = fl.arr(lambda t: t.pos_ned_m)
    h = fl.arr(lambda t: t.height_agl_m)
    lead = 3 * 240  # 3 s before the closest approach the aircraft still flies to that waypoint (its height)
    for w in wps:
        d = np.hypot(pos[:, 0] - w.north_m, pos[:, 1] - w.east_m)
        i = int(np.argmin(d))
        assert d[i] < 30.0
        assert h[i - lead] == pytest.approx(w.height_m, abs=3.0)
    assert h.max() < 124.0
    tas = fl.arr(lambda t: t.tas_m_s)
    assert np.abs(tas - 22.0).min() < 0.5


def test_autopilot_loops_run_at_their_rates_and_hold_their_outputs() -> None:
    dt, seconds = 1.0 / 240.0, 10.0
    ap = Autopilot(AutopilotGains(guidance_rate_hz=20.0, attitude_rate_hz=60.0))
    ap.set_heading_command(0.5, HEIGHT_M, AIRSPEED_M_S)
    z3 = np.zeros(3)
    cmds, roll_cmds = [], []
    for k in range(int(round(seconds / dt))):
        # a truth that changes every step (yaw and roll rate), so every guidance run gives a new roll command
        truth = TruthState(t_s=k * dt, pos_ned_m=np.array([20.0 * k * dt, 0.0, -HEIGHT_M]),
                           vel_ned_m_s=np.array([20.0, 0.0, 0.0]), roll_rad=0.0, pitch_rad=0.03,
                           yaw_rad=0.4 + 1e-4 * k, rates_b_rad_s=np.array([0.01 * math.sin(k), 0.0, 0.0]),
                           accel_b_m_s2=z3, tas_m_s=AIRSPEED_M_S, alpha_rad=0.03, beta_rad=0.0, wind_ned_m_s=z3,
                           wind_steady_ned_m_s=z3, height_agl_m=HEIGHT_M)
        cmds.append(ap.update(truth, dt))
        roll_cmds.append(ap.roll_cmd_rad)
    # a new command object each time the attitude loops run, the same object in between (zero-order hold)
    new_cmd = sum(1 for a, b in zip([None, *cmds[:-1]], cmds, strict=True) if a is not b)
    assert new_cmd == int(60.0 * seconds)
    new_roll = sum(1 for a, b in zip([None, *roll_cmds[:-1]], roll_cmds, strict=True) if a != b)
    assert new_roll == int(20.0 * seconds)
    assert len({id(c) for c in cmds}) == new_cmd


def test_multi_rate_autopilot_flies_the_mission_of_an_every_step_autopilot() -> None:
    """The default loop rates (50 Hz) against loops run at every dynamics step (240 Hz): same 2.4 km mission."""
    wps = [Waypoint(300.0, 100.0, HEIGHT_M, AIRSPEED_M_S), Waypoint(300.0, 500.0, 120.0, 22.0),
           Waypoint(-100.0, 500.0, 120.0, 22.0), Waypoint(-100.0, 100.0, HEIGHT_M, AIRSPEED_M_S)]
    wind = WindParams(speed_m_s=5.0, from_rad=math.radians(45.0))
    every_step = 1.0 / DynamicsParams().dt_s
    flights = []
    for gains in (AutopilotGains(), AutopilotGains(guidance_rate_hz=every_step, attitude_rate_hz=every_step)):
        fd = FlightDynamics(DynamicsParams(), wind, np.random.default_rng(1))
        ap = Autopilot(gains, fd.trim(0.0, 0.0, HEIGHT_M, AIRSPEED_M_S, 0.0))
        ap.set_mission(wps)
        truth, pos = fd.truth(), []
        for _ in range(int(round(120.0 / fd.dt_s))):
            truth = fd.step(ap.update(truth, fd.dt_s))
            pos.append(truth.pos_ned_m)
        flights.append((ap.waypoints_reached, np.array(pos)))
    (reached_a, pos_a), (reached_b, pos_b) = flights
    assert AutopilotGains().attitude_rate_hz < every_step / 4  # the comparison is between different rates
    assert reached_a == reached_b >= 5
    assert np.hypot(*(pos_a[:, :2] - pos_b[:, :2]).T).max() < 2.0
    assert np.abs(pos_a[:, 2] - pos_b[:, 2]).max() < 0.5


def test_truth_fields_are_jsbsim_state() -> None:
    fd = FlightDynamics(DynamicsParams(), WindParams(speed_m_s=5.0, from_rad=1.0, turbulence=True),
                        np.random.default_rng(4))
    cmd = fd.trim(100.0, -50.0, HEIGHT_M, AIRSPEED_M_S, 0.5)
    roll_in = ControlCommand(cmd.aileron_norm + 0.05, cmd.elevator_norm, cmd.rudder_norm, cmd.throttle_norm)
    truths = [fd.step(roll_in) for _ in range(121)]
    prev, t = truths[-2], truths[-1]
    fdm, ft = fd._fdm, 0.3048
    assert t.t_s == pytest.approx(121 * fd.dt_s)
    np.testing.assert_allclose(t.rates_b_rad_s, [fdm["velocities/p-rad_sec"], fdm["velocities/q-rad_sec"],
                                                 fdm["velocities/r-rad_sec"]], rtol=0, atol=1e-15)
    np.testing.assert_allclose(t.accel_b_m_s2, [fdm[f"accelerations/a-pilot-{a}-ft_sec2"] * ft for a in "xyz"],
                               rtol=1e-15)
    np.testing.assert_allclose(t.vel_ned_m_s, [fdm[f"velocities/v-{a}-fps"] * ft for a in ("north", "east", "down")],
                               rtol=1e-15)
    assert (t.roll_rad, t.pitch_rad) == (fdm["attitude/phi-rad"], fdm["attitude/theta-rad"])
    assert t.yaw_rad == pytest.approx(float(angle_diff(fdm["attitude/psi-rad"], 0.0)), abs=1e-15)
    assert t.height_agl_m == pytest.approx(fdm["position/h-agl-ft"] * ft, rel=1e-15) == -t.pos_ned_m[2]
    wind_jsbsim = [fdm[f"atmosphere/wind-{a}-fps"] * ft for a in ("north", "east", "down")]
    np.testing.assert_allclose(t.wind_ned_m_s, wind_jsbsim, rtol=1e-12)
    assert t.tas_m_s == pytest.approx(float(np.linalg.norm(t.vel_ned_m_s - t.wind_ned_m_s)), rel=1e-12)
    assert np.linalg.norm(t.wind_ned_m_s - t.wind_steady_ned_m_s) > 0.0  # turbulence on top of the steady wind
    # the position is the integral of the velocity: over the last step (5.7 cm) within JSBSim's integration scheme
    np.testing.assert_allclose(t.pos_ned_m - prev.pos_ned_m, 0.5 * (t.vel_ned_m_s + prev.vel_ned_m_s) * fd.dt_s,
                               rtol=0.0, atol=5e-5)
    # immutable
    with pytest.raises(AttributeError):
        t.tas_m_s = 1.0  # type: ignore[misc]
    assert t._replace(t_s=1.0).t_s == 1.0 and t.t_s != 1.0


# ----------------------------------------------------------------------------------------------------------------
# wind field


def test_shear_profile_and_direction() -> None:
    p = WindParams(speed_m_s=5.0, from_rad=math.radians(90.0), ref_height_m=6.0, roughness_m=0.05)
    wf = WindField(p, np.random.default_rng(0))
    np.testing.assert_allclose(wf.steady_ned(6.0), [0.0, -5.0, 0.0], atol=1e-12)  # from the east: blows west
    ratio = math.log(100.0 / 0.05) / math.log(6.0 / 0.05)
    assert wf.steady_speed_m_s(100.0) == pytest.approx(5.0 * ratio, rel=1e-12)
    assert wf.steady_speed_m_s(0.01) == 0.0
    flat = WindField(WindParams(speed_m_s=5.0, shear=False), np.random.default_rng(0))
    assert flat.steady_speed_m_s(300.0) == 5.0


def test_dryden_turbulence_statistics_and_reproducibility() -> None:
    p = WindParams(speed_m_s=0.0, from_rad=0.0, turbulence=True, turbulence_w20_m_s=10.0)
    h, v, dt, n = 10.0, 20.0, 0.02, 150_000
    a = WindField(p, np.random.default_rng(42))
    b = WindField(p, np.random.default_rng(42))
    c = WindField(p, np.random.default_rng(43))
    wa = np.array([a.update(i * dt, dt, h, v).turbulence_ned_m_s for i in range(1, n + 1)])
    wb = np.array([b.update(i * dt, dt, h, v).turbulence_ned_m_s for i in range(1, 2001)])
    wc = np.array([c.update(i * dt, dt, h, v).turbulence_ned_m_s for i in range(1, 2001)])
    np.testing.assert_array_equal(wa[:2000], wb)
    assert not np.allclose(wa[:2000], wc)
    sig_uv, sig_w, l_uv, l_w = dryden_sigmas_scales(h, 10.0)
    # MIL-F-8785C at 10 m (32.8 ft): sigma_w = 0.1 W20, sigma_u = sigma_w / (0.177 + 0.000823 h_ft)^0.4
    assert sig_w == pytest.approx(1.0)
    assert sig_uv == pytest.approx(1.0 / (0.177 + 0.000823 * 10.0 / 0.3048) ** 0.4)
    std = wa.std(axis=0)
    np.testing.assert_allclose(std, [sig_uv, sig_uv, sig_w], rtol=0.1)
    # the longitudinal component is first-order Gauss-Markov: autocorrelation exp(-V tau / L_u)
    u = wa[:, 0] - wa[:, 0].mean()
    lag = int(round(l_uv / v / dt))
    rho = float(np.dot(u[:-lag], u[lag:]) / np.dot(u, u))
    assert rho == pytest.approx(math.exp(-1.0), abs=0.08)


def test_turbulence_variance_does_not_depend_on_step() -> None:
    p = WindParams(turbulence=True, turbulence_w20_m_s=10.0)
    for dt in (0.001, 0.3):
        wf = WindField(p, np.random.default_rng(5))
        w = np.array([wf.update(i * dt, dt, 3.0, 25.0).turbulence_ned_m_s[2] for i in range(1, 40_001)])
        assert w.std() == pytest.approx(1.0, rel=0.1)


def test_lower_turbulence_filter_rate_interpolates_between_exact_samples() -> None:
    """At ``turbulence_rate_hz`` the filters step once per period; the wind in between is the straight line between
    the two samples, which are the exact discretisation (the same as stepping the filters by the period)."""
    p = WindParams(turbulence=True, turbulence_w20_m_s=10.0, turbulence_rate_hz=50.0)
    h, v = 60.0, 20.0
    fine, coarse = WindField(p, np.random.default_rng(8)), WindField(p, np.random.default_rng(8))
    w0 = fine.update(0.0, 0.0, h, v).turbulence_ned_m_s
    np.testing.assert_array_equal(coarse.update(0.0, 0.0, h, v).turbulence_ned_m_s, w0)
    a = np.array([fine.update(k * 0.004, 0.004, h, v).turbulence_ned_m_s for k in range(1, 501)])  # 5 per period
    b = np.array([w0] + [coarse.update(k * 0.02, 0.02, h, v).turbulence_ned_m_s for k in range(1, 101)])
    frac = np.arange(1, 6)[:, None] / 5.0
    expected = np.concatenate([b[m] + frac * (b[m + 1] - b[m]) for m in range(100)])
    np.testing.assert_allclose(a, expected, rtol=0.0, atol=1e-12)
    assert np.abs(np.diff(b, axis=0)).max() > 0.01  # the samples do move


def test_turbulence_statistics_at_a_lower_filter_rate() -> None:
    p = WindParams(turbulence=True, turbulence_w20_m_s=10.0, turbulence_rate_hz=50.0)
    h, v, dt, n = 10.0, 20.0, 1.0 / 240.0, 240 * 2400
    wf = WindField(p, np.random.default_rng(21))
    w = np.array([wf.advance(i * dt, dt, h, v)[:3] for i in range(1, n + 1)])  # no steady wind: all turbulence
    sig_uv, sig_w, l_uv, _ = dryden_sigmas_scales(h, 10.0)
    np.testing.assert_allclose(w.std(axis=0), [sig_uv, sig_uv, sig_w], rtol=0.1)
    u = w[:, 0] - w[:, 0].mean()
    lag = int(round(l_uv / v / dt))
    assert float(np.dot(u[:-lag], u[lag:]) / np.dot(u, u)) == pytest.approx(math.exp(-1.0), abs=0.08)


def test_one_minus_cosine_gust() -> None:
    p = WindParams(gusts=True, gust_times_s=(1.0,), gust_amplitude_m_s=4.0, gust_length_m=20.0)
    wf = WindField(p, np.random.default_rng(3))
    v, dt = 20.0, 0.01
    t = np.arange(1, 401) * dt
    g = np.array([wf.update(float(x), dt, 50.0, v).gust_ned_m_s for x in t])
    mag = np.linalg.norm(g, axis=1)
    duration = 2.0 * 20.0 / v
    expected = np.where((t >= 1.0) & (t <= 1.0 + duration), 2.0 * (1.0 - np.cos(2 * np.pi * (t - 1.0) / duration)), 0.0)
    np.testing.assert_allclose(mag, expected, atol=1e-9)
    direction = g[np.argmax(mag)] / mag.max()
    np.testing.assert_allclose(g[mag > 0.1] / mag[mag > 0.1, None], np.broadcast_to(direction, g[mag > 0.1].shape),
                               atol=1e-12)


def test_turbulent_flight_is_reproducible_per_seed() -> None:
    wind = WindParams(speed_m_s=5.0, from_rad=1.0, turbulence=True, gusts=True, gust_rate_hz=0.5)
    runs = [fly(wind, 8.0, lambda ap: ap.set_heading_command(0.0, HEIGHT_M, AIRSPEED_M_S), seed=s) for s in (9, 9, 10)]
    pos = [r.arr(lambda t: t.pos_ned_m) for r in runs]
    turb = runs[0].arr(lambda t: t.wind_ned_m_s - t.wind_steady_ned_m_s)
    assert turb.std(axis=0).min() > 0.1
    np.testing.assert_array_equal(pos[0], pos[1])
    assert np.abs(pos[0] - pos[2]).max() > 0.01


# ----------------------------------------------------------------------------------------------------------------
# hygiene and bad input


def test_no_files_in_cwd_and_no_banner(tmp_path, monkeypatch, capfd) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("JSBSIM_DEBUG", raising=False)
    fd = FlightDynamics(DynamicsParams(), WindParams(turbulence=True), np.random.default_rng(0))
    cmd = fd.trim(0.0, 0.0, HEIGHT_M, AIRSPEED_M_S, 0.0)
    for _ in range(240):
        fd.step(cmd)
    assert os.listdir(tmp_path) == []
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_bad_input_is_rejected_with_names() -> None:
    with pytest.raises(ConfigError, match="speed_m_s"):
        WindParams(speed_m_s=-1.0)
    with pytest.raises(ConfigError, match="ref_height_m"):
        WindParams(ref_height_m=0.01, roughness_m=0.05)
    with pytest.raises(ConfigError, match=r"gust_times_s\[1\]"):
        WindParams(gust_times_s=(1.0, float("nan")))
    with pytest.raises(ConfigError, match="turbulence_rate_hz"):
        WindParams(turbulence_rate_hz=0.0)
    with pytest.raises(ConfigError, match="attitude_rate_hz"):
        AutopilotGains(attitude_rate_hz=float("nan"))
    with pytest.raises(ConfigError, match="guidance_rate_hz"):
        AutopilotGains(guidance_rate_hz=100.0, attitude_rate_hz=50.0)
    with pytest.raises(ConfigError, match="dt_s"):
        DynamicsParams(dt_s=0.0)
    with pytest.raises(ConfigError, match="aircraft"):
        DynamicsParams(aircraft="no_such_plane")
    with pytest.raises(ConfigError, match="height_m"):
        Waypoint(0.0, 0.0, -5.0, 20.0)
    with pytest.raises(ValueError, match="throttle_norm"):
        ControlCommand(0.0, 0.0, 0.0, 1.5)
    with pytest.raises(ValueError, match="aileron_norm"):
        ControlCommand(float("nan"), 0.0, 0.0, 0.5)
    fd = FlightDynamics(DynamicsParams(), WindParams(), np.random.default_rng(0))
    with pytest.raises(RuntimeError, match="trim"):
        fd.step(ControlCommand(0.0, 0.0, 0.0, 0.5))
    with pytest.raises(ValueError, match="airspeed_m_s"):
        fd.trim(0.0, 0.0, HEIGHT_M, float("nan"), 0.0)
    ap = Autopilot()
    with pytest.raises(ValueError, match="at least 2"):
        ap.set_mission([Waypoint(0.0, 0.0, 100.0, 20.0)])
