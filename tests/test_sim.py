"""`gsoe sim`: outputs, accuracy against the simulator's truth, reproducibility, ROI vs full-frame rendering."""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import uniform_filter1d

from cli.main import main
from common.configfile import DEFAULT_CONFIG as DEFAULT_TOML
from common.logio import read_log
from fusion.config import ekf_config_from_raw
from pipeline.config import load_gsoe_config
from sim.dynamics import AIRCRAFT_ROOT
from sim.run import WIND_TRUTH_WINDOW_S, run_flight
from sim.scenario import load_scenario, scenario_with_overrides

EXPECTED_FILES = ("metrics.json", "report.html", "trajectory.png", "altitude_airspeed.png", "sample_distance.png",
                  "tm_cycle.png", "drift_vs_heading.png", "wind.png", "position_error.png", "truth.csv", "gsoe.csv",
                  "ekf.csv", "baseline.csv", "imu.csv", "attitude.csv", "airspeed.csv", "baro.csv", "gnss.csv",
                  "aid_status.csv")


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    rc = main(["sim", "paper_sil", "--duration", "120", "--seed", "3", "--out", str(out), "--no-progress"])
    assert rc == 0
    return out


def test_short_paper_sil_writes_every_output(short_run):
    for name in EXPECTED_FILES:
        assert (short_run / name).is_file(), name
    m = json.loads((short_run / "metrics.json").read_text())
    for key in ("drift_mae_deg", "drift_mae_vs_gnss_deg", "drift_p95_deg", "heading_coverage", "wind_speed_rmse_m_s",
                "wind_dir_rmse_deg", "frames", "sim_s", "wall_s", "realtime_factor", "baseline_drift_mae_deg",
                "nees_in_bounds_frac"):
        assert key in m, key
    assert m["sim_s"] == pytest.approx(120.0, abs=0.01)
    assert m["frames"] > 0.95 * 120 * 30


def test_short_paper_sil_optical_drift_within_paper_sil_level(short_run):
    """The paper's SIL level: optical drift MAE vs the simulator's true drift below 1 deg."""
    m = json.loads((short_run / "metrics.json").read_text())
    assert m["baseline_drift_mae_deg"] < 1.0
    assert m["drift_mae_deg"] < 1.0


def test_log_is_columnar_and_matches_truth(short_run):
    truth = read_log(short_run / "truth.csv")
    gsoe = read_log(short_run / "gsoe.csv")
    assert np.all(np.diff(truth["t_us"]) > 0)
    assert {"dx_px", "dy_px", "psr", "valid", "cycle_id"} <= set(gsoe)
    # the truth's own drift column is course minus heading
    course = np.arctan2(truth["vel_e_m_s"], truth["vel_n_m_s"])
    d = (course - truth["yaw_rad"] - truth["drift_rad"] + np.pi) % (2 * np.pi) - np.pi
    assert np.max(np.abs(d)) < 1e-9


def test_roi_rendering_gives_the_same_result_as_full_frames():
    """Rendering only what the estimator reads changes nothing (noise off: its draws depend on the region)."""
    scn = scenario_with_overrides(load_scenario("paper_sil"), {"camera.noise_std": 0.0})
    roi = run_flight(scn, seed=5, duration_s=6.0)
    full = run_flight(scn, seed=5, duration_s=6.0, full_frame=True)
    for key in ("baseline_drift_mae_deg", "drift_mae_deg", "frames", "optical_valid_frac"):
        assert roi[key] == full[key], key


def test_same_seed_same_flight():
    scn = load_scenario("paper_sil")
    a = run_flight(scn, seed=11, duration_s=8.0)
    b = run_flight(scn, seed=11, duration_s=8.0)
    c = run_flight(scn, seed=12, duration_s=8.0)
    assert a["drift_mae_deg"] == b["drift_mae_deg"] and a["sensor_errors"] == b["sensor_errors"]
    assert a["sensor_errors"] != c["sensor_errors"]


def test_short_paper_sil_ekf_acceptance(short_run):
    """Issue 4 on a short paper_sil run: the EKF beats the paper's chain on drift, holds the wind after the first
    turns, covers the headings flown and is consistent (NEES of position, velocity and wind)."""
    m = json.loads((short_run / "metrics.json").read_text())
    assert m["drift_mae_deg"] <= 0.5
    assert m["drift_mae_deg"] < m["baseline_drift_mae_deg"]
    # error of the wind after the first minute (turns) against the total wind averaged over 5 s
    assert m["wind_speed_mae_m_s"] <= 0.5
    assert m["wind_dir_mae_deg"] <= 10.0
    assert m["heading_coverage"] >= 0.95
    assert m["nees_in_bounds_frac"] >= 0.8


def test_side_force_sideslip_of_the_default_config_tracks_the_simulated_airframe(short_run):
    """The EKF's side-force sideslip (``2 m f_y / (rho S C_Ybeta V^2)`` with the default config's airframe, from the
    logged accelerometer low-passed as the EKF does) against JSBSim's true sideslip of the flight: it explains most
    of the sideslip that the zero-sideslip assumption leaves as error."""
    cfg = ekf_config_from_raw(load_gsoe_config(None)[1])
    imu, truth = read_log(short_run / "imu.csv"), read_log(short_run / "truth.csv")
    t_imu = imu["t_us"] * 1e-6
    a = np.minimum(1.0, np.diff(t_imu, prepend=t_imu[0]) / cfg.sideslip_accel_tau_s)
    f_y = _ema(imu["accel_y_m_s2"], a)
    t = truth["t_us"] * 1e-6
    sel = t > 10.0
    beta = truth["beta_rad"][sel]
    beta_model = cfg.sideslip_accel_gain_m * np.interp(t[sel], t_imu, f_y) / truth["tas_m_s"][sel] ** 2
    rms = float(np.sqrt(np.mean(beta**2)))
    rms_err = float(np.sqrt(np.mean((beta_model - beta) ** 2)))
    assert np.degrees(rms) > 0.3                       # the flight has sideslip to explain
    assert rms_err < 0.6 * rms, (np.degrees(rms), np.degrees(rms_err))     # zero sideslip: 1.0 * rms


def test_lift_angle_of_attack_of_the_default_config_tracks_the_simulated_airframe(short_run):
    """The EKF's lift-model angle of attack (``-2 m f_z / (rho S C_Lalpha V^2) - C_L0 / C_Lalpha`` with the default
    config's airframe, from the logged accelerometer low-passed as the EKF does) against JSBSim's true angle of attack
    of the flight: it follows the angle's changes (turns, gusts) to a fraction of their size, without any fitting."""
    cfg = ekf_config_from_raw(load_gsoe_config(None)[1])
    imu, truth = read_log(short_run / "imu.csv"), read_log(short_run / "truth.csv")
    t_imu = imu["t_us"] * 1e-6
    f_z = _ema(imu["accel_z_m_s2"], np.minimum(1.0, np.diff(t_imu, prepend=t_imu[0]) / cfg.sideslip_accel_tau_s))
    t = truth["t_us"] * 1e-6
    sel = t > 10.0
    alpha = truth["alpha_rad"][sel]
    alpha_model = (-cfg.aoa_accel_gain_m * np.interp(t[sel], t_imu, f_z) / truth["tas_m_s"][sel] ** 2
                   - cfg.aoa_zero_lift_rad)
    spread = float(np.std(alpha))
    rms_err = float(np.sqrt(np.mean((alpha_model - alpha) ** 2)))
    assert np.degrees(spread) > 0.3                    # the flight has angle-of-attack changes to explain
    assert rms_err < 0.5 * spread, (np.degrees(spread), np.degrees(rms_err))
    assert np.degrees(abs(np.mean(alpha_model - alpha))) < 0.5


def _talon_lift_curve() -> tuple[float, float]:
    """``(C_L0, C_Lalpha per rad)`` of the simulated Talon, read from its JSBSim file (the table's 0 and 5 deg
    rows: the linear range)."""
    root = ET.parse(AIRCRAFT_ROOT / "talon" / "talon.xml").getroot()
    fn = next(f for f in root.iter("function") if f.get("name") == "aero/talon/cl-alpha")
    rows = dict(tuple(float(v) for v in line.split()) for line in fn.findtext(".//tableData").strip().splitlines())
    return rows[0.0], (rows[5.0] - rows[0.0]) / math.radians(5.0)


PAPER_SIL_AIRSPEED_M_S = 20.0
"""The paper_sil mission's typical airspeed (its waypoints ask 18-24 m/s)."""


@pytest.mark.slow  # a 300 s flight (three for the vertical wind)
def test_aoa_offset_learns_a_wrong_lift_model_offset(tmp_path):
    """A config whose zero-lift coefficient is 0.1 above the airframe's (read from the simulator's JSBSim file, the
    independent truth) makes the lift-model angle read ``0.1 / C_Lalpha`` (1.3 deg) low at every attitude: the
    ``aoa_ofs`` state must take it, rather than a vertical wind that the flight does not have (the truth's mean
    vertical wind is 0).  Checked: the mean of the offset after the first turns against ``-0.1 / C_Lalpha``, and the
    vertical wind's mean error against the 0.44 m/s of vertical air velocity the offset is worth at 20 m/s.
    Measured: offset -1.45 deg against -1.27, vertical wind 0.08 m/s off on average."""
    cl0, cla = _talon_lift_curve()
    cfg = ekf_config_from_raw(load_gsoe_config(None)[1])
    assert cfg.aoa_lift_coef_zero == pytest.approx(cl0) and cfg.aoa_lift_slope_per_rad == pytest.approx(cla, rel=0.01)
    wrong = _config_with(tmp_path, "wrong_cl0", aoa_lift_coef_zero=repr(cl0 + 0.1))
    run_flight(load_scenario("paper_sil"), seed=3, duration_s=240.0, out_dir=tmp_path, config_path=wrong)
    ekf, truth = _arrays(tmp_path)
    t, tt = ekf["t_us"] * 1e-6, truth["t_us"] * 1e-6
    sel = t > 120.0
    expect = -0.1 / cla
    ofs = float(np.mean(ekf["aoa_ofs_rad"][sel]))
    assert abs(ofs - expect) < 0.25 * abs(expect), (np.degrees(ofs), np.degrees(expect))
    wd_err = float(np.mean(ekf["wind_d_m_s"][sel] - np.interp(t[sel], tt, truth["wind_d_m_s"])))
    assert abs(wd_err) < 0.3 * PAPER_SIL_AIRSPEED_M_S * abs(expect), wd_err




@pytest.mark.slow  # a 300 s flight (three for the vertical wind)
def test_side_force_offset_removes_the_ahrs_roll_error_from_the_sideslip(tmp_path):
    """An AHRS roll error ``d_phi`` rotates gravity into the filter's body y axis, and the accelerometer-bias state
    takes ``g d_phi`` of it, which the accelerometer never read: the side-force sideslip ``k (f_y - b_y)`` is then
    off by about the roll error.  With the ``side_force_ofs`` state the filter's reading ``k (f_y - b_y - ofs)``
    matches JSBSim's true sideslip on average (the independent truth), while the same reading without the offset
    is off by more than the roll error (computed from the same flight: the test has teeth).  Measured: a 2.2 deg
    roll error, 2.4 deg off without the offset, -0.33 deg with it; the offset pinned at 0 fails this test."""
    scn = scenario_with_overrides(load_scenario("paper_sil"), {"sensors.ahrs.bias_std_deg": 2.0})
    run_flight(scn, seed=SFO_SEED, duration_s=240.0, out_dir=tmp_path)
    cfg = ekf_config_from_raw(load_gsoe_config(None)[1])
    imu, truth = read_log(tmp_path / "imu.csv"), read_log(tmp_path / "truth.csv")
    ekf, att = read_log(tmp_path / "ekf.csv"), read_log(tmp_path / "attitude.csv")
    t_truth, t_att = truth["t_us"] * 1e-6, att["t_us"] * 1e-6
    roll_err = float(np.median(att["roll_rad"] - np.interp(t_att, t_truth, truth["roll_rad"])))
    assert abs(np.degrees(roll_err)) > 1.0                  # the seed draws a roll error worth correcting
    t_imu = imu["t_us"] * 1e-6
    f_y = _ema(imu["accel_y_m_s2"], np.minimum(1.0, np.diff(t_imu, prepend=t_imu[0]) / cfg.sideslip_accel_tau_s))
    t = ekf["t_us"] * 1e-6
    sel = t > 120.0                                         # after the first loops of turns
    k = cfg.sideslip_accel_gain_m / np.interp(t[sel], t_truth, truth["tas_m_s"]) ** 2
    f_sel = np.interp(t[sel], t_imu, f_y) - ekf["accel_bias_y_m_s2"][sel]
    beta = np.interp(t[sel], t_truth, truth["beta_rad"])
    err_with = float(np.mean(k * (f_sel - ekf["side_force_ofs_m_s2"][sel]) - beta))
    err_without = float(np.mean(k * f_sel - beta))
    assert abs(err_without) > 0.6 * abs(roll_err), (np.degrees(err_without), np.degrees(roll_err))
    assert abs(err_with) < 0.25 * abs(roll_err), (np.degrees(err_with), np.degrees(roll_err))


# paper_sil with a 2 deg AHRS tilt-error sigma: this seed draws a +2.0 deg roll error
SFO_SEED = 3


def _vertical_wind_in_banks(folder):
    """The EKF's and the truth's vertical wind while banked more than 20 deg, after the first minute."""
    ekf, truth = _arrays(folder)
    t, tt = ekf["t_us"] * 1e-6, truth["t_us"] * 1e-6
    sel = (t > 60.0) & (np.abs(np.interp(t, tt, truth["roll_rad"])) > np.radians(20.0))
    return ekf["wind_d_m_s"][sel], np.interp(t[sel], tt, truth["wind_d_m_s"])


def _config_with(tmp_path, name: str, **values: object) -> Path:
    """The default config with ``[ekf]`` keys replaced (TOML literals), written under ``tmp_path``."""
    text = DEFAULT_TOML.read_text()
    text = text.replace('file = "camera/', f'file = "{DEFAULT_TOML.parent.as_posix()}/camera/')
    for key, value in values.items():
        text, n = re.subn(rf"(?m)^{key} = \S+", f"{key} = {value}", text)
        assert n == 1, key
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


@pytest.mark.slow  # a 300 s flight (three for the vertical wind)
def test_vertical_wind_state_follows_the_vertical_gusts_and_improves_the_wind(tmp_path):
    """In a bank the body y axis takes ``sin(phi)`` of the vertical air velocity, so a vertical gust reads as
    sideslip; with the vertical wind held at 0 (``wind_d_sigma_ratio = 0``, the PX4/ArduPilot model) the sideslip
    puts it into the cross-heading wind.  The same paper_sil flight in moderate Dryden turbulence (turns at 45 deg
    of bank) flown three times against JSBSim's true wind: with the ``wind_d`` state and the lift-model angle of
    attack (the default), with the state but no angle of attack (the sideslip in banks is then all that sees the
    vertical wind), and with neither.  The state follows the true vertical wind in banks (measured correlation 0.93
    with the angle of attack, 0.61 without), and the wind speed error against the windowed truth falls with each
    (measured 0.264, 0.283 and 0.375 m/s; with the state pinned at 0 the runs are the same flight)."""
    scn = scenario_with_overrides(load_scenario("paper_sil"),
                                  {"wind.turbulence_severity": "moderate", "wind.turbulence_scale": 0.6})
    m_with = run_flight(scn, seed=WD_SEED, duration_s=300.0, out_dir=tmp_path / "with")
    no_aoa = _config_with(tmp_path, "no_aoa", aoa_fusion="false")
    m_no_aoa = run_flight(scn, seed=WD_SEED, duration_s=300.0, out_dir=tmp_path / "no_aoa", config_path=no_aoa)
    off = _config_with(tmp_path, "no_vertical_wind", aoa_fusion="false", wind_d_sigma_ratio="0.0")
    m_without = run_flight(scn, seed=WD_SEED, duration_s=300.0, out_dir=tmp_path / "without", config_path=off)
    wd_est, wd_true = _vertical_wind_in_banks(tmp_path / "with")
    wd_no_aoa, _ = _vertical_wind_in_banks(tmp_path / "no_aoa")
    wd_off, _ = _vertical_wind_in_banks(tmp_path / "without")
    assert wd_true.size > 500 and np.std(wd_true) > 0.5           # banked flight in vertical gusts
    assert not np.any(wd_off)                                      # off: pinned at 0
    corr, corr_no_aoa = np.corrcoef(wd_est, wd_true)[0, 1], np.corrcoef(wd_no_aoa, wd_true)[0, 1]
    assert corr > 0.8 and corr_no_aoa > 0.3 and corr > corr_no_aoa + 0.1, (corr, corr_no_aoa)
    w = [m["wind_speed_rmse_m_s"] for m in (m_with, m_no_aoa, m_without)]
    assert w[0] < 0.97 * w[1] and w[1] < 0.95 * w[2], w


# paper_sil in moderate turbulence (scale 0.6): vertical gusts of 0.8 m/s rms in the banks
WD_SEED = 6


def _ema(x: np.ndarray, a: np.ndarray) -> np.ndarray:
    """First-order low-pass with per-sample gain ``a`` (the EKF's recursion, written out independently)."""
    y = np.empty_like(x)
    y[0] = x[0]
    for i in range(1, x.size):
        y[i] = y[i - 1] + a[i] * (x[i] - y[i - 1])
    return y


def _arrays(folder):
    return read_log(folder / "ekf.csv"), read_log(folder / "truth.csv")


HARD = [
    ("strong_wind", {}),
    ("low_texture", {"terrain.texture": "water", "sensors.gnss.outages": [{"start_s": 40.0, "length_s": 200.0}]}),
]


@pytest.fixture(scope="module", params=HARD, ids=[h[0] for h in HARD])
def hard_run(request, tmp_path_factory):
    name, overrides = request.param
    out = tmp_path_factory.mktemp(name)
    m = run_flight(scenario_with_overrides(load_scenario(name), overrides), seed=2, duration_s=100.0, out_dir=out)
    ekf, truth = read_log(out / "ekf.csv"), read_log(out / "truth.csv")
    return name, m, ekf, truth


def test_hard_scenarios_no_nan_and_invalid_flagged(hard_run):
    name, m, ekf, truth = hard_run
    assert not m["crashed"]
    valid = ekf["valid"] > 0.5
    for key in ("pos_n_m", "pos_e_m", "vel_n_m_s", "vel_e_m_s", "wind_n_m_s", "wind_e_m_s", "drift_rad",
                "drift_sigma_rad", "wind_n_sigma_m_s"):
        assert np.all(np.isfinite(ekf[key][valid])), key
    t = ekf["t_us"]
    if name == "low_texture":
        # over water with GNSS lost the optical aid is gone: the drift's sigma grows, and the estimate says so
        before = (t > 20e6) & (t < 40e6)
        during = (t > 60e6) & (t < 100e6)
        assert np.median(ekf["drift_sigma_rad"][during]) > 1.5 * np.median(ekf["drift_sigma_rad"][before])


def test_hard_scenarios_wind_error_bounded_by_sigma(hard_run):
    name, m, ekf, truth = hard_run
    valid = ekf["valid"] > 0.5
    t = ekf["t_us"]
    late = valid & (t > 30e6)
    # against the total wind averaged over WIND_TRUTH_WINDOW_S (as the metrics): the fast turbulence is not
    # observable through the wind triangle
    win = int(round(WIND_TRUTH_WINDOW_S / np.median(np.diff(truth["t_us"] * 1e-6))))
    for key, sig in (("wind_n_m_s", "wind_n_sigma_m_s"), ("wind_e_m_s", "wind_e_sigma_m_s")):
        smooth = uniform_filter1d(truth[key], win, mode="nearest")
        err = ekf[key][late] - np.interp(t[late], truth["t_us"], smooth)
        assert np.mean(np.abs(err) <= 3.0 * ekf[sig][late]) >= 0.9, key


def test_ten_minute_gnss_outage_dead_reckoning_within_two_percent():
    scn = scenario_with_overrides(load_scenario("gnss_outage"),
                                  {"sensors.gnss.outages": [{"start_s": 100.0, "length_s": 600.0}]})
    m = run_flight(scn, seed=5, duration_s=705.0)
    assert m["dr_error_pct_of_distance"] <= 2.0
    assert m["pos_error_m_max"] < 0.02 * 600 * 18.0


def test_ctrl_c_leaves_a_readable_partial_log(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    # The child gets SIGINT's default disposition: a suite started as a background job of a non-interactive shell
    # runs with SIGINT ignored, the child would inherit that, and Python then never raises KeyboardInterrupt (the
    # flight ran to its end with the interrupt sent).
    proc = subprocess.Popen([sys.executable, "-m", "cli", "sim", "--duration", "2000", "--out", str(tmp_path),
                             "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120.0
        gsoe_log = tmp_path / "gsoe.csv"
        while (not gsoe_log.exists() or gsoe_log.stat().st_size == 0) and time.monotonic() < deadline \
                and proc.poll() is None:
            time.sleep(0.2)
        time.sleep(2.0)
        assert proc.poll() is None, "the flight ended before it could be interrupted"
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, out
    assert "interrupted" in out
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["interrupted"] is True and 0 < m["sim_s"] < 2000
    truth = read_log(tmp_path / "truth.csv")
    assert truth["t_us"].size > 10 and np.all(np.isfinite(truth["t_us"]))
