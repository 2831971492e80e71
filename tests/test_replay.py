"""``gsoe replay``: real ArduPlane logs through the EKF, compared with the autopilot's wind and the GNSS track.

The flight-log tests read ``../shared/data/flightlogs`` (skipped when absent).  What they measure:

* wind: RMS length of (EKF wind - ArduPilot's WIND message) at every WIND sample from 20 s after the EKF's start
  (and from its start: the wind reset from the first airspeed sample) to the end of the 157 s engine-failure log,
  with GNSS fused throughout (issue 21 acceptance: <= 0.8 m/s; reached 0.44, from the start 0.50, its first 10 s 0.97);
* position with GNSS fused: RMS horizontal distance from the log's GNSS fixes (issue 21: <= 1 m; reached 0.53);
* dead reckoning: GNSS no longer fused from 100 s; horizontal distance between the EKF position and the GNSS fix at
  the log's end, relative to the length of the GNSS track flown meanwhile (~800 m in ~56 s).  With the synthetic
  optical stand-in (GNSS velocity + pixel noise) this measures the filter's integration of the displacements; with
  ``--no-optical`` it is IMU and air data only.
"""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cli.main import main
from common.logio import read_log as read_csv_stream
from fusion.measurements import OpticalDisplacement
from fusion.state import S
from nav.logreader import AirspeedSample, GnssSample
from nav.replay import (
    OPTICAL_SOURCE_NONE,
    OPTICAL_SOURCE_SYNTHETIC,
    ReplayConfig,
    height_reference,
    replay_configs_from_raw,
    run_replay,
    synthesise_optical_steps,
)
from pipeline.config import load_gsoe_config
from tests.conftest import shared_data

SHORT = "alfa_carbonZ_2018-07-18-16-37-39_1.tlog"
LONG = "alfa_carbonZ_2018-07-30-17-36-35_engine_failure.tlog"
DATAFLASH = "arduplane_3.8.2_truncated.BIN"
GNSS_OFF_S = 100.0


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    """The 157 s log through the CLI, GNSS fused throughout, every output written."""
    out = tmp_path_factory.mktemp("replay_full")
    rc = main(["replay", str(shared_data("flightlogs", LONG)), "--out", str(out), "--seed", "3"])
    return rc, out, json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def dr_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("replay_dr")
    res = run_replay(shared_data("flightlogs", LONG), out_dir=out, gnss_off_at_s=GNSS_OFF_S, seed=3, plots=False)
    return res, out


# --------------------------------------------------------------------------------------------------------------
# the virtual camera against analytic displacements (no data needed)


def _straight_flight(yaw_rad: float, vel_ne: tuple[float, float], height_m: float, duration_s: float = 3.0):
    cfg, raw = load_gsoe_config()
    _, ekf_cfg = replay_configs_from_raw(raw)
    period = round(1e6 / cfg.cycle.rate_hz)
    t = np.arange(0, int(duration_s * 1e6), period, dtype=np.int64)
    rot = Rotation.from_euler("ZYX", np.tile([yaw_rad, 0.0, 0.0], (t.size, 1)))
    vel = np.tile(vel_ne, (t.size, 1)).astype(float)
    ok = np.ones(t.size, bool)
    return cfg, ekf_cfg, t, vel, ok, rot, np.full(t.size, height_m)


@pytest.mark.parametrize(("yaw_deg", "vel_ne"), [(0.0, (15.0, 2.0)), (90.0, (2.0, 15.0)), (225.0, (-10.0, -12.0))])
def test_synthetic_steps_are_the_ground_displacement_over_the_gsd(yaw_deg, vel_ne):
    h = 100.0
    cfg, ekf_cfg, t, vel, ok, rot, hh = _straight_flight(math.radians(yaw_deg), vel_ne, h)
    steps = synthesise_optical_steps(t, vel, ok, rot, ok, hh, cfg, ekf_cfg, 1e-9, 10.0, np.random.default_rng(0))
    moving = [s for s in steps if not s.new_cycle]
    assert len(moving) > 50
    focal = cfg.camera.fx_px if cfg.stab.focal_px == 0 else cfg.stab.focal_px
    psi = math.radians(yaw_deg)
    for s in moving:
        dt = (s.t_us - s.base_t_us) * 1e-6
        dn, de = vel_ne[0] * dt, vel_ne[1] * dt
        # independent model: the EKF's optical measurement of a state displaced by (dn, de) at height h
        x = np.zeros(S.dim)
        x[S.pos_ne] = (dn, de)
        x[S.base_pos_d] = -h
        z = OpticalDisplacement(focal_px=focal, base_yaw_rad=psi).predict(x)
        assert s.dx_px == pytest.approx(z[0], abs=1e-6)
        assert s.dy_px == pytest.approx(z[1], abs=1e-6)
        assert s.gsd_m_px == pytest.approx(h / focal)
        assert s.base_yaw_rad == pytest.approx(float(np.angle(np.exp(1j * psi))))
    # the forward (dy) component is the ground speed along the heading
    along = vel_ne[0] * math.cos(psi) + vel_ne[1] * math.sin(psi)
    assert moving[0].dy_px == pytest.approx(along / cfg.cycle.rate_hz / (h / focal), rel=1e-3)


def test_cycles_end_where_the_template_would_leave_the_base_image():
    h = 100.0
    cfg, ekf_cfg, t, vel, ok, rot, hh = _straight_flight(0.0, (15.0, 0.0), h)
    steps = synthesise_optical_steps(t, vel, ok, rot, ok, hh, cfg, ekf_cfg, 1e-9, 10.0, np.random.default_rng(0))
    per_frame_px = 15.0 / cfg.cycle.rate_hz / (h / cfg.camera.fx_px)
    # centre start: the template's centre may travel (along_px - 1)/2 - (template_px - 1)/2 - edge margin forward
    room = (cfg.stab.base_along_px - 1) / 2 - (cfg.stab.template_px - 1) / 2 - cfg.cycle.edge_margin_px
    expected = math.ceil(room / per_frame_px) - 1
    ids = [s.cycle_id for s in steps if not s.new_cycle]
    counts = np.bincount(ids)[:-1]                       # the last cycle is cut by the end of the data
    assert counts.size >= 3
    assert np.all(counts == expected)
    bases = [s for s in steps if s.new_cycle]
    assert all(b.dx_px == 0.0 and b.dy_px == 0.0 and b.t_us == b.base_t_us for b in bases)


def test_no_steps_beyond_the_roll_limit_or_below_the_camera_height():
    cfg, ekf_cfg, t, vel, ok, rot, hh = _straight_flight(0.0, (15.0, 0.0), 100.0)
    roll = np.where(np.arange(t.size) < t.size // 2, 0.0, math.radians(cfg.stab.roll_limit_deg + 5))
    rot = Rotation.from_euler("ZYX", np.column_stack([np.zeros(t.size), np.zeros(t.size), roll]))
    steps = synthesise_optical_steps(t, vel, ok, rot, ok, hh, cfg, ekf_cfg, 0.1, 10.0, np.random.default_rng(0))
    assert steps and max(s.t_us for s in steps) < t[t.size // 2]
    low = synthesise_optical_steps(t, vel, ok, rot, ok, np.full(t.size, 5.0), cfg, ekf_cfg, 0.1, 10.0,
                                   np.random.default_rng(0))
    assert low == []


def test_noise_comes_from_the_seeded_generator_with_the_requested_sigma():
    cfg, ekf_cfg, t, vel, ok, rot, hh = _straight_flight(0.0, (15.0, 0.0), 100.0, duration_s=30.0)
    args = (t, vel, ok, rot, ok, hh, cfg, ekf_cfg, 0.5, 10.0)
    a = synthesise_optical_steps(*args, np.random.default_rng(7))
    b = synthesise_optical_steps(*args, np.random.default_rng(7))
    c = synthesise_optical_steps(*args, np.random.default_rng(8))
    assert [s.dx_px for s in a] == [s.dx_px for s in b]
    assert [s.dx_px for s in a] != [s.dx_px for s in c]
    # the difference from the analytic displacement (15 m/s north, heading north, 100 m) is the drawn noise
    gsd = 100.0 / cfg.camera.fx_px
    noise = np.array([(s.dx_px, s.dy_px - 15.0 * (s.t_us - s.base_t_us) * 1e-6 / gsd) for s in a if not s.new_cycle])
    assert noise.shape[0] > 300
    assert np.std(noise, axis=0) == pytest.approx([0.5, 0.5], rel=0.1)


def test_height_reference_uses_the_take_off_point_else_the_assumption():
    cfg = ReplayConfig()
    t = np.arange(0, 200_000_000, 1_000_000, dtype=np.int64)
    alt = np.where(t < 20_000_000, 300.0, 380.0)                     # 20 s on the ground, then 80 m up
    speed = np.where(t < 20_000_000, 0.2, 16.0)
    gnss = [GnssSample(t_us=int(ti), pos_ned_m=np.zeros(3), vel_ned_m_s=np.array([v, 0.0, 0.0]), fix_ok=True,
                       n_sats=10, lat_deg=0.0, lon_deg=0.0, alt_msl_m=0.0) for ti, v in zip(t, speed, strict=True)]
    air = [AirspeedSample(t_us=int(ti), tas_m_s=0.5 if v < 1 else 16.0, eas_m_s=math.nan)
           for ti, v in zip(t, speed, strict=True)]
    ref = height_reference(t, alt, gnss, air, (int(t[0]), int(t[-1])), cfg, tas_min_m_s=6.0)
    assert ref.ground_alt_m == pytest.approx(300.0)
    assert "take-off" in ref.source
    airborne = height_reference(t[30:], alt[30:], gnss[30:], air[30:], (int(t[30]), int(t[-1])), cfg, 6.0)
    assert airborne.ground_alt_m == pytest.approx(380.0 - cfg.lowest_height_agl_m)
    assert "assumed" in airborne.source


# --------------------------------------------------------------------------------------------------------------
# the ALFA logs


def test_wind_and_position_match_ardupilot_and_gnss(full_run):
    rc, out, m = full_run
    assert rc == 0
    assert m["optical_source"] == OPTICAL_SOURCE_SYNTHETIC
    assert m["wind_compared_samples"] > 200
    # the comparison discriminates: ArduPilot's wind is ~2.5 m/s, so a zero (or wrong-way) estimate fails it
    assert m["autopilot_wind_speed_mean_m_s"] > 2.0
    assert m["wind_rmse_vs_autopilot_m_s"] <= 0.5                     # issue 21: 0.8; reached 0.440 (seed 3)
    assert m["pos_error_rms_with_gnss_m"] <= 0.6                       # issue 21: 1 m; reached 0.530
    assert m["eas_to_tas_air_temp_c"] == 25.0                          # ArduPilot's cap of the baro's 55 C
    assert m["n_samples"]["GsoeStep"] == m["optical_steps"] > 4000
    for name in ("metrics.json", "ekf.csv", "aid_status.csv", "gsoe.csv", "gnss.csv", "autopilot_wind.csv",
                 "wind.png", "track.png", "position_error.png", "report.html"):
        assert (out / name).stat().st_size > 0, name
    assert "synthetic_from_gnss_velocity" in (out / "report.html").read_text()
    ekf = read_csv_stream(out / "ekf.csv")
    assert ekf["t_us"].size > 1000 and np.all(np.isfinite(ekf["wind_n_m_s"]))
    # over the whole flight, from the EKF's start: the wind starts from the wind triangle at the first airspeed
    # sample (0.28 s after the start; fusion/aid/airspeed.py)
    ap = read_csv_stream(out / "autopilot_wind.csv")
    t_ekf = ekf["t_us"].astype(float)
    sel = (ap["t_us"] >= t_ekf[0]) & (ap["t_us"] <= t_ekf[-1])
    err = np.hypot(np.interp(ap["t_us"][sel], t_ekf, ekf["wind_n_m_s"]) - ap["wind_n_m_s"][sel],
                   np.interp(ap["t_us"][sel], t_ekf, ekf["wind_e_m_s"]) - ap["wind_e_m_s"][sel])
    assert sel.sum() > 250
    assert math.sqrt(float(np.mean(err**2))) <= 0.55                  # reached 0.497
    first = ap["t_us"][sel] < t_ekf[0] + 10e6
    assert math.sqrt(float(np.mean(err[first] ** 2))) <= 1.1          # reached 0.97


def test_dead_reckoning_after_gnss_off(dr_run):
    res, out = dr_run
    m = res.metrics
    assert m["gnss_off_at_s"] == GNSS_OFF_S
    assert m["dr_distance_m"] > 500.0 and m["dr_duration_s"] > 50.0
    assert np.isfinite(m["dr_error_m"])
    assert m["dr_error_m"] <= 0.005 * m["dr_distance_m"]              # 3.1 m of 806 (seed 3)
    # GNSS really stopped: no GNSS fusion after the switch-off (receiver lag: stamps move 0.2 s back)
    st = read_csv_stream(out / "aid_status.csv")
    for src in ("gnss_pos", "gnss_vel"):
        assert np.nanmax(st["t_last_fuse_us"][st["source"] == src]) < GNSS_OFF_S * 1e6
    assert m["wind_rmse_vs_autopilot_after_gnss_off_m_s"] <= 1.0


def test_dead_reckoning_on_imu_and_air_data_only():
    res = run_replay(shared_data("flightlogs", LONG), gnss_off_at_s=GNSS_OFF_S, optical=False)
    m = res.metrics
    assert m["optical_source"] == OPTICAL_SOURCE_NONE and m["optical_steps"] == 0
    assert np.isfinite(m["dr_error_m"])
    assert m["dr_error_m"] <= 0.05 * m["dr_distance_m"]


def test_short_log_replays(tmp_path):
    res = run_replay(shared_data("flightlogs", SHORT), out_dir=tmp_path, plots=False)
    m = res.metrics
    assert m["log_duration_s"] == pytest.approx(30.3, abs=0.5)
    assert math.isfinite(m["wind_rmse_vs_autopilot_m_s"]) and m["wind_compared_samples"] > 10
    assert m["wind_rmse_vs_autopilot_m_s"] <= 0.45                    # reached 0.384
    assert m["pos_error_rms_with_gnss_m"] <= 0.3                      # reached 0.222
    assert m["n_samples"]["ImuSample"] > 250 and m["log_warnings"] == []


def test_truncated_log_replays_the_readable_part(tmp_path):
    src = shared_data("flightlogs", LONG)
    cut = tmp_path / "cut.tlog"
    data = src.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.4) + 3])       # torn inside a frame
    res = run_replay(cut, out_dir=tmp_path / "out", plots=False)
    m = res.metrics
    assert m["log_warnings"], "the truncation must be reported"
    assert 30.0 < m["log_duration_s"] < 100.0
    assert res.series["ekf"]["t_s"][-1] == pytest.approx(m["log_duration_s"], abs=1.0)
    assert math.isfinite(m["wind_rmse_vs_autopilot_m_s"])
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["log_warnings"] == m["log_warnings"]


def test_garbage_and_unusable_logs_exit_2_with_a_clear_message(tmp_path, capsys):
    garbage = tmp_path / "garbage.tlog"
    garbage.write_bytes(np.random.default_rng(1).integers(0, 256, 20000, dtype=np.uint8).tobytes())
    assert main(["replay", str(garbage), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err
    assert "nothing readable" in err and "Traceback" not in err
    assert main(["replay", str(shared_data("flightlogs", DATAFLASH)), "--out", str(tmp_path / "o2")]) == 2
    assert "not enough data" in capsys.readouterr().err
    assert main(["replay", str(tmp_path / "missing.tlog"), "--out", str(tmp_path / "o4")]) == 2
    assert main(["replay", str(shared_data("flightlogs", SHORT)), "--gnss-off-at", "500",
                 "--out", str(tmp_path / "o3")]) == 2
    assert "--gnss-off-at" in capsys.readouterr().err


def test_log_without_gnss_exits_2(tmp_path, capsys):
    from pymavlink import mavutil

    src = shared_data("flightlogs", SHORT)
    conn = mavutil.mavlink_connection(str(src))
    frames = []
    while (msg := conn.recv_match()) is not None:
        if msg.get_type() not in ("GPS_RAW_INT", "BAD_DATA"):
            frames.append(struct.pack(">Q", round(msg._timestamp * 1e6)) + bytes(msg.get_msgbuf()))
    conn.close()
    no_gnss = tmp_path / "no_gnss.tlog"
    no_gnss.write_bytes(b"".join(frames))
    assert main(["replay", str(no_gnss), "--out", str(tmp_path / "o")]) == 2
    assert "no valid GNSS fix" in capsys.readouterr().err


def test_bad_replay_config_names_the_field(tmp_path):
    from common.config import ConfigError

    with pytest.raises(ConfigError, match="replay.wind_settle_s"):
        replay_configs_from_raw({"replay": {"wind_settle_s": -1.0}})
    with pytest.raises(ConfigError, match="ekf.wind_rw_m_s_per_rt_s"):
        replay_configs_from_raw({"replay": {"ekf": {"wind_rw_m_s_per_rt_s": "fast"}}})
    rcfg, ekf = replay_configs_from_raw({"ekf": {"baro_sigma_m": 2.5}, "replay": {"ekf": {"tas_sigma_m_s": 0.7}}})
    assert ekf.baro_sigma_m == 2.5 and ekf.tas_sigma_m_s == 0.7 and rcfg == ReplayConfig()

