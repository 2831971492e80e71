"""Simulated sensors: configured statistics on long seeded runs, against synthetic truth sequences built here."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from common.angles import angle_diff, wrap_pi
from sim.scenario import (
    AhrsConfig,
    AirspeedConfig,
    BaroConfig,
    CameraSimConfig,
    GnssConfig,
    ImuConfig,
    OutageConfig,
    SensorsConfig,
    load_scenario,
)
from sim.sensors import (
    Ahrs,
    Airspeed,
    Baro,
    CameraClock,
    Gnss,
    Imu,
    SensorErrors,
    SensorSuite,
    draw_sensor_errors,
)
from sim.truth import TruthState

Z3 = np.zeros(3)
G_FRD = np.array([0.0, 0.0, -9.80665])  # specific force of level unaccelerated flight, FRD


def truth(t_s: float, **kw: object) -> TruthState:
    base: dict[str, object] = dict(
        t_s=t_s, pos_ned_m=np.array([0.0, 0.0, -100.0]), vel_ned_m_s=np.array([20.0, 0.0, 0.0]), roll_rad=0.0,
        pitch_rad=0.0, yaw_rad=0.0, rates_b_rad_s=Z3, accel_b_m_s2=G_FRD, tas_m_s=20.0, alpha_rad=0.0,
        beta_rad=0.0, wind_ned_m_s=Z3, wind_steady_ned_m_s=Z3, height_agl_m=100.0,
    )
    base.update(kw)
    return TruthState(**base)  # type: ignore[arg-type]


def zero_errors(**kw: object) -> SensorErrors:
    base: dict[str, object] = dict(
        gyro_bias_b_rad_s=Z3.copy(), gyro_scale=Z3.copy(), accel_bias_b_m_s2=Z3.copy(), accel_scale=Z3.copy(),
        ahrs_bias_rad=Z3.copy(), airspeed_scale=0.0, baro_bias_m=0.0, baro_drift_rate_m_s=0.0,
        camera_timestamp_offset_s=0.0,
    )
    base.update(kw)
    return SensorErrors(**base)  # type: ignore[arg-type]


def increment_var_ratio(x: np.ndarray, lag: int, expected_var_per_step: float) -> float:
    """Variance of lag-``lag`` increments of the random walk(s) ``x`` (samples x axes) over ``lag`` times the
    per-step variance: 1 for a random walk with that step variance."""
    d = x[lag:] - x[:-lag]
    return float(np.mean(d**2) / (lag * expected_var_per_step))


# --------------------------------------------------------------------------------------------------------------
# IMU

QUIET_IMU = ImuConfig(rate_hz=200.0, gyro_bias_std_deg_s=0.0, gyro_bias_walk_deg_s_sqrt_s=0.0, gyro_scale_std=0.0,
                      accel_bias_std_m_s2=0.0, accel_bias_walk_m_s2_sqrt_s=0.0, accel_scale_std=0.0)


def test_imu_white_noise_matches_density_times_sqrt_rate() -> None:
    cfg = dataclasses.replace(QUIET_IMU, gyro_noise_density_deg_s_sqrt_hz=0.02, accel_noise_density_m_s2_sqrt_hz=0.005)
    imu = Imu(cfg, zero_errors(), np.random.default_rng(11))
    rates = np.array([0.1, -0.2, 0.05])
    n = 40_000
    g = np.empty((n, 3))
    a = np.empty((n, 3))
    for k in range(n):
        s = imu.sample(truth(k / cfg.rate_hz, rates_b_rad_s=rates))
        g[k], a[k] = s.gyro_b_rad_s, s.accel_b_m_s2
    sg = math.radians(0.02) * math.sqrt(200.0)
    sa = 0.005 * math.sqrt(200.0)
    np.testing.assert_allclose(np.std(g - rates, axis=0), sg, rtol=0.03)
    np.testing.assert_allclose(np.std(a - G_FRD, axis=0), sa, rtol=0.03)
    assert np.all(np.abs(np.mean(g - rates, axis=0)) < 4 * sg / math.sqrt(n))
    assert np.all(np.abs(np.mean(a - G_FRD, axis=0)) < 4 * sa / math.sqrt(n))
    # white: neighbouring samples uncorrelated
    assert abs(np.corrcoef(g[1:, 0], g[:-1, 0])[0, 1]) < 0.03


def test_imu_applies_the_runs_bias_and_scale() -> None:
    cfg = dataclasses.replace(QUIET_IMU, gyro_noise_density_deg_s_sqrt_hz=0.0, accel_noise_density_m_s2_sqrt_hz=0.0)
    err = zero_errors(gyro_bias_b_rad_s=np.array([0.01, -0.02, 0.003]), gyro_scale=np.array([0.01, 0.0, -0.02]),
                      accel_bias_b_m_s2=np.array([0.1, 0.0, -0.05]), accel_scale=np.array([0.0, 0.02, 0.01]))
    imu = Imu(cfg, err, np.random.default_rng(0))
    w = np.array([0.5, -0.3, 0.2])
    f = np.array([1.0, -2.0, -9.0])
    s = imu.sample(truth(0.0, rates_b_rad_s=w, accel_b_m_s2=f))
    np.testing.assert_allclose(s.gyro_b_rad_s, (1 + err.gyro_scale) * w + err.gyro_bias_b_rad_s, atol=1e-12)
    np.testing.assert_allclose(s.accel_b_m_s2, (1 + err.accel_scale) * f + err.accel_bias_b_m_s2, atol=1e-12)
    np.testing.assert_allclose(imu.gyro_bias_b_rad_s, err.gyro_bias_b_rad_s)


def test_imu_bias_random_walk_grows_like_sqrt_t() -> None:
    walk_g, walk_a = 0.002, 0.004  # deg/s/sqrt(s), m/s^2/sqrt(s)
    cfg = dataclasses.replace(QUIET_IMU, gyro_noise_density_deg_s_sqrt_hz=0.0, accel_noise_density_m_s2_sqrt_hz=0.0,
                              gyro_bias_walk_deg_s_sqrt_s=walk_g, accel_bias_walk_m_s2_sqrt_s=walk_a)
    imu = Imu(cfg, zero_errors(), np.random.default_rng(5))
    n = 200_000  # 1000 s at 200 Hz
    dt = 1.0 / cfg.rate_hz
    g = np.empty((n, 3))
    a = np.empty((n, 3))
    t0 = truth(0.0, accel_b_m_s2=Z3)
    for k in range(n):
        s = imu.sample(t0._replace(t_s=k * dt))
        g[k], a[k] = s.gyro_b_rad_s, s.accel_b_m_s2
    np.testing.assert_array_equal(g[0], 0.0)  # starts at the drawn (here zero) turn-on bias
    for lag in (1, 10, 100, 1000):  # 5 ms to 5 s
        assert increment_var_ratio(g, lag, math.radians(walk_g) ** 2 * dt) == pytest.approx(1.0, abs=0.15), lag
        assert increment_var_ratio(a, lag, walk_a**2 * dt) == pytest.approx(1.0, abs=0.15), lag


def test_drawn_errors_have_the_configured_distribution() -> None:
    cfg = SensorsConfig(
        imu=ImuConfig(gyro_bias_std_deg_s=0.5, accel_bias_std_m_s2=0.08, gyro_scale_std=0.01, accel_scale_std=0.02),
        ahrs=AhrsConfig(bias_std_deg=0.4, yaw_bias_std_deg=2.0),
        airspeed=AirspeedConfig(scale_error_std=0.03),
        baro=BaroConfig(bias_std_m=3.0, drift_rate_std_m_s=0.004),
    )
    cam = CameraSimConfig(timestamp_offset_s=0.02, timestamp_offset_std_s=0.005)
    rng = np.random.default_rng(2024)
    draws = [draw_sensor_errors(cfg, rng, cam) for _ in range(4000)]

    def check(values: np.ndarray, mean: float, std: float) -> None:
        n = values.shape[0]
        np.testing.assert_allclose(np.std(values, axis=0), std, rtol=0.06)
        assert np.all(np.abs(np.mean(values, axis=0) - mean) < 4 * std / math.sqrt(n))

    check(np.array([d.gyro_bias_b_rad_s for d in draws]), 0.0, math.radians(0.5))
    check(np.array([d.accel_bias_b_m_s2 for d in draws]), 0.0, 0.08)
    check(np.array([d.gyro_scale for d in draws]), 0.0, 0.01)
    check(np.array([d.accel_scale for d in draws]), 0.0, 0.02)
    ahrs = np.array([d.ahrs_bias_rad for d in draws])
    check(ahrs[:, :2], 0.0, math.radians(0.4))
    check(ahrs[:, 2], 0.0, math.radians(2.0))
    check(np.array([d.airspeed_scale for d in draws]), 0.0, 0.03)
    check(np.array([d.baro_bias_m for d in draws]), 0.0, 3.0)
    check(np.array([d.baro_drift_rate_m_s for d in draws]), 0.0, 0.004)
    check(np.array([d.camera_timestamp_offset_s for d in draws]), 0.02, 0.005)
    # independent axes
    assert abs(np.corrcoef(ahrs[:, 0], ahrs[:, 1])[0, 1]) < 0.06
    # plain form for logs
    d = draws[0].to_dict()
    assert d["gyro_bias_b_rad_s"] == pytest.approx(list(draws[0].gyro_bias_b_rad_s))


# --------------------------------------------------------------------------------------------------------------
# AHRS


def test_ahrs_noise_and_bias() -> None:
    cfg = AhrsConfig(rate_hz=50.0, noise_deg=0.3, latency_s=0.0)
    bias = np.radians([0.5, -0.4, 2.0])
    ahrs = Ahrs(cfg, zero_errors(ahrs_bias_rad=bias), np.random.default_rng(3))
    att = np.array([0.2, -0.1, 3.1])  # yaw near +pi: reported yaw wraps
    n = 20_000
    out = np.empty((n, 3))
    for k in range(n):
        s = ahrs.sample(truth(k / 50.0, roll_rad=att[0], pitch_rad=att[1], yaw_rad=att[2]))
        out[k] = s.roll_rad, s.pitch_rad, s.yaw_rad
    assert np.all((out[:, 2] >= -math.pi) & (out[:, 2] < math.pi))
    err = np.array(angle_diff(out, att))
    np.testing.assert_allclose(np.std(err, axis=0), math.radians(0.3), rtol=0.04)
    np.testing.assert_allclose(np.mean(err, axis=0), bias, atol=4 * math.radians(0.3) / math.sqrt(n))


@pytest.mark.parametrize("latency_s", [0.0, 0.07, 0.25])
def test_ahrs_reports_the_attitude_of_latency_ago(latency_s: float) -> None:
    dt = 1.0 / 240.0
    cfg = AhrsConfig(rate_hz=50.0, noise_deg=0.05, bias_std_deg=0.0, yaw_bias_std_deg=0.0, latency_s=latency_s)
    ahrs = Ahrs(cfg, zero_errors(), np.random.default_rng(8))
    amp, f_hz, yaw_rate = math.radians(30.0), 0.5, math.radians(40.0)

    def roll(t: float | np.ndarray) -> float | np.ndarray:
        return amp * np.sin(2 * np.pi * f_hz * t)

    def yaw(t: float | np.ndarray) -> float | np.ndarray:
        return wrap_pi(2.5 + yaw_rate * t)  # crosses +-pi many times

    t_rep, r_rep, y_rep = [], [], []
    for k in range(240 * 60):
        t = k * dt
        tr = truth(t, roll_rad=float(roll(t)), yaw_rad=float(yaw(t)))
        ahrs.push(tr)
        if ahrs.due(t):
            s = ahrs.sample(tr)
            assert s.t_us == tr.t_us  # stamped when reported
            t_rep.append(t)
            r_rep.append(s.roll_rad)
            y_rep.append(s.yaw_rad)
    t_a = np.array(t_rep)
    assert len(t_a) == 50 * 60  # 50 Hz over 60 s (t = 60 s itself is not simulated)
    keep = t_a > 1.0  # after the history covers the latency

    def cost(lag: float) -> float:
        return float(np.sum(np.array(angle_diff(np.array(r_rep)[keep], roll(t_a[keep] - lag))) ** 2))

    lag_hat = minimize_scalar(cost, bounds=(-0.5, 0.5), method="bounded", options={"xatol": 1e-6}).x
    assert lag_hat == pytest.approx(latency_s, abs=1e-3)
    yaw_err = np.array(angle_diff(np.array(y_rep)[keep], yaw(t_a[keep])))
    assert np.mean(yaw_err) == pytest.approx(-yaw_rate * latency_s, abs=math.radians(0.01))


# --------------------------------------------------------------------------------------------------------------
# Air data


def test_airspeed_noise_and_scale() -> None:
    cfg = AirspeedConfig(rate_hz=50.0, noise_m_s=0.4)
    air = Airspeed(cfg, zero_errors(airspeed_scale=0.03), np.random.default_rng(4))
    v = np.array([air.sample(truth(k / 50.0, tas_m_s=20.0)).tas_m_s for k in range(20_000)])
    assert np.std(v) == pytest.approx(0.4, rel=0.03)
    assert np.mean(v) == pytest.approx(20.0 * 1.03, abs=4 * 0.4 / math.sqrt(v.size))


def test_baro_noise_offset_and_drift_rate() -> None:
    cfg = BaroConfig(rate_hz=25.0, noise_m=0.7, walk_m_sqrt_s=0.0)
    baro = Baro(cfg, zero_errors(baro_bias_m=1.5, baro_drift_rate_m_s=0.01), np.random.default_rng(6))
    t = np.arange(25_000) / 25.0
    h = 100.0 + 5.0 * np.sin(0.01 * t)
    alt = np.array(
        [baro.sample(truth(ti, pos_ned_m=np.array([0.0, 0.0, -hi]))).alt_m for ti, hi in zip(t, h, strict=True)]
    )
    resid = alt - h - (1.5 + 0.01 * t)
    assert np.std(resid) == pytest.approx(0.7, rel=0.03)
    assert abs(np.mean(resid)) < 4 * 0.7 / math.sqrt(t.size)
    slope, offset = np.polyfit(t, alt - h, 1)
    assert slope == pytest.approx(0.01, abs=4e-5)
    assert offset == pytest.approx(1.5, abs=0.05)


def test_baro_random_walk_grows_like_sqrt_t() -> None:
    cfg = BaroConfig(rate_hz=50.0, noise_m=0.0, walk_m_sqrt_s=0.05)
    baro = Baro(cfg, zero_errors(), np.random.default_rng(7))
    n = 100_000
    err = np.array([[baro.sample(truth(k / 50.0)).alt_m - 100.0] for k in range(n)])
    assert err[0, 0] == 0.0
    for lag in (1, 10, 100, 500):
        assert increment_var_ratio(err, lag, 0.05**2 / 50.0) == pytest.approx(1.0, abs=0.2), lag


# --------------------------------------------------------------------------------------------------------------
# GNSS


def test_gnss_white_noise_rate_and_outages() -> None:
    outages = (OutageConfig(start_s=300.0, length_s=100.0), OutageConfig(start_s=700.0, length_s=50.0))
    cfg = GnssConfig(rate_hz=5.0, pos_noise_m=1.5, alt_noise_m=3.0, vel_noise_m_s=0.2, outages=outages)
    gnss = Gnss(cfg, np.random.default_rng(9))
    dt = 1.0 / 240.0
    samples = []
    pos = np.array([100.0, -50.0, -120.0])
    vel = np.array([15.0, 10.0, -1.0])
    for k in range(int(1000.0 / dt) + 1):
        t = k * dt
        if gnss.due(t):
            samples.append((t, gnss.sample(truth(t, pos_ned_m=pos, vel_ned_m_s=vel))))
    assert len(samples) == 5 * 1000 + 1
    t_s = np.array([t for t, _ in samples])
    inside = ((t_s >= 300.0) & (t_s < 400.0)) | ((t_s >= 700.0) & (t_s < 750.0))
    assert inside.sum() == 5 * 150
    for (_, s), out in zip(samples, inside, strict=True):
        assert s.fix_ok is (not out)
        if out:
            assert np.all(np.isnan(s.pos_ned_m)) and np.all(np.isnan(s.vel_ned_m_s)) and s.n_sats == 0
            assert s.h_acc_m == math.inf
    ok = [s for _, s in samples if s.fix_ok]
    p = np.array([s.pos_ned_m for s in ok]) - pos
    v = np.array([s.vel_ned_m_s for s in ok]) - vel
    np.testing.assert_allclose(np.std(p, axis=0), [1.5, 1.5, 3.0], rtol=0.05)
    np.testing.assert_allclose(np.std(v, axis=0), 0.2, rtol=0.05)
    assert np.all(np.abs(np.mean(p, axis=0)) < 4 * np.array([1.5, 1.5, 3.0]) / math.sqrt(len(ok)))
    assert abs(np.corrcoef(p[1:, 0], p[:-1, 0])[0, 1]) < 0.05  # white when pos_corr_time_s = 0


def test_gnss_gauss_markov_position_error() -> None:
    tau = 20.0
    cfg = GnssConfig(rate_hz=5.0, pos_noise_m=2.0, alt_noise_m=2.0, pos_corr_time_s=tau)
    gnss = Gnss(cfg, np.random.default_rng(10))
    n = 100_000  # 20 000 s = 1000 correlation times
    e = np.array([gnss.sample(truth(k / 5.0, pos_ned_m=Z3)).pos_ned_m for k in range(n)])
    # stationary std, pooled over the three axes (about 1000 independent stretches per axis)
    assert np.std(e) == pytest.approx(2.0, rel=0.06)
    for lag_s, tol in ((0.2, 0.005), (5.0, 0.04), (20.0, 0.08)):  # tolerances: ~3 sigma of the estimate
        lag = int(round(lag_s * 5.0))
        rho = np.mean([np.corrcoef(e[lag:, i], e[:-lag, i])[0, 1] for i in range(3)])
        assert rho == pytest.approx(math.exp(-lag_s / tau), abs=tol), lag_s


# --------------------------------------------------------------------------------------------------------------
# Camera clock, scheduling, reproducibility


def test_camera_clock_rate_offset_and_exposure() -> None:
    cfg = CameraSimConfig(rate_hz=25.0, exposure_s=0.004, timestamp_offset_s=0.02)
    cam = CameraClock(cfg, zero_errors(camera_timestamp_offset_s=0.02))
    dt = 1.0 / 240.0
    frames = [cam.frame(k * dt) for k in range(2400) if cam.due(k * dt)]
    assert len(frames) == 250  # 25 Hz over 10 s (2400 steps of 1/240 s)
    assert [f.index for f in frames] == list(range(250))
    t = np.array([f.t_s for f in frames])
    np.testing.assert_allclose(np.diff(t).mean(), 0.04, rtol=1e-3)
    # each frame lies on the first dynamics step at or after k / rate
    assert np.all((t - np.arange(250) / 25.0 >= -1e-9) & (t - np.arange(250) / 25.0 < dt + 1e-9))
    for f in frames:
        assert f.t_us - f.t_s * 1e6 == pytest.approx(0.02e6, abs=1.0)
        assert f.exposure_end_s - f.exposure_start_s == pytest.approx(0.004)


def test_suite_sample_counts_follow_the_rates() -> None:
    scn = load_scenario("paper_sil")
    suite = SensorSuite(scn.sensors, scn.camera, np.random.default_rng(1))
    counts = dict.fromkeys(("imu", "ahrs", "airspeed", "baro", "gnss", "frame"), 0)
    n_steps = int(round(10.0 / scn.dt_s))  # 10 s
    for k in range(n_steps):
        r = suite.step(truth(k * scn.dt_s))
        for name in counts:
            counts[name] += getattr(r, name) is not None
    s = scn.sensors
    expected = {"imu": s.imu.rate_hz, "ahrs": s.ahrs.rate_hz, "airspeed": s.airspeed.rate_hz, "baro": s.baro.rate_hz,
                "gnss": s.gnss.rate_hz, "frame": scn.camera.rate_hz}
    assert counts == {k: int(round(10.0 * v)) for k, v in expected.items()}


def _run(seed: int, n: int = 2400) -> list[np.ndarray]:
    scn = load_scenario("paper_sil")
    suite = SensorSuite(scn.sensors, scn.camera, np.random.default_rng(seed))
    out = []
    for k in range(n):
        r = suite.step(truth(k * scn.dt_s, roll_rad=0.3 * math.sin(k * 0.01), rates_b_rad_s=np.array([0.1, 0, 0])))
        row = [r.imu.gyro_b_rad_s, r.imu.accel_b_m_s2] if r.imu else []
        if r.ahrs:
            row.append(np.array([r.ahrs.roll_rad, r.ahrs.pitch_rad, r.ahrs.yaw_rad]))
        if r.gnss:
            row.append(r.gnss.pos_ned_m)
        if r.baro:
            row.append(np.array([r.baro.alt_m]))
        out.append(np.concatenate(row))
    return out


def test_same_seed_same_samples_different_seed_different() -> None:
    a, b, c = _run(42), _run(42), _run(43)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))


def test_suite_per_step_noise_has_the_configured_statistics() -> None:
    """Through SensorSuite.step (the per-step path, noise drawn in blocks of NOISE_BLOCK_ROWS), over many blocks."""
    imu = dataclasses.replace(QUIET_IMU, rate_hz=240.0, gyro_noise_density_deg_s_sqrt_hz=0.02,
                              accel_noise_density_m_s2_sqrt_hz=0.005)
    cfg = SensorsConfig(imu=imu, ahrs=AhrsConfig(rate_hz=50.0, noise_deg=0.2, bias_std_deg=0.0, yaw_bias_std_deg=0.0,
                                                 latency_s=0.0),
                        airspeed=AirspeedConfig(rate_hz=50.0, noise_m_s=0.3, scale_error_std=0.0))
    suite = SensorSuite(cfg, CameraSimConfig(), np.random.default_rng(31))
    rates = np.array([0.2, -0.1, 0.05])
    dt, n = 1.0 / 240.0, 240 * 250  # 250 s: 29 IMU noise blocks
    gyro, accel, att, tas = [], [], [], []
    for k in range(n):
        r = suite.step(truth(k * dt, rates_b_rad_s=rates, roll_rad=0.1, pitch_rad=0.05, yaw_rad=1.0))
        assert r.imu is not None  # the IMU samples at every step at 240 Hz
        gyro.append(r.imu.gyro_b_rad_s)
        accel.append(r.imu.accel_b_m_s2)
        if r.ahrs is not None:
            att.append((r.ahrs.roll_rad, r.ahrs.pitch_rad, r.ahrs.yaw_rad))
        if r.airspeed is not None:
            tas.append(r.airspeed.tas_m_s)
    g = np.array(gyro) - rates
    a = np.array(accel) - G_FRD
    e_att = np.array(angle_diff(np.array(att), np.array([0.1, 0.05, 1.0])))
    e_tas = np.array(tas) - 20.0
    for err, std in ((g, math.radians(0.02) * math.sqrt(240.0)), (a, 0.005 * math.sqrt(240.0)),
                     (e_att, math.radians(0.2)), (e_tas, 0.3)):
        m = err.shape[0]
        np.testing.assert_allclose(np.std(err, axis=0), std, rtol=0.03)
        assert np.all(np.abs(np.mean(err, axis=0)) < 4 * std / math.sqrt(m))
    assert len(att) == len(tas) == 50 * 250
    assert abs(np.corrcoef(g[1:, 0], g[:-1, 0])[0, 1]) < 0.03  # white across the block boundaries too
