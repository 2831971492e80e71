"""Reports people read (issue 22): ``report.html`` opens with the goal table, then the figures (innovations and test
ratios per aid source, NEES with its bounds, wind speed and direction with sigma, velocity error, GNSS outages
shaded); no series in the page; SI units; ``gsoe report LOGDIR`` on a companion's logs; ``gsoe sim --log reports``
thins the per-step streams so that a 2000 s flight stays under 50 MB."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from common.logio import Decimator, RunLog, read_log
from sim.logreport import GNSS_GAP_S, gnss_unused_intervals

ROOT = Path(__file__).resolve().parent.parent
LOG_BUDGET_BYTES_2000_S = 50e6
SIM_S = 45.0


def test_decimator_thins_per_stream_and_key_and_keeps_every_change_of_key():
    got: list[tuple[str, dict]] = []
    d = Decimator(lambda s, r: got.append((s, dict(r))), {"imu": 0.1, "aid_status": 0.2},
                  {"aid_status": ("source", "rejected")})
    for i in range(100):  # 10 ms steps, 1 s
        t = i * 10_000
        d("imu", {"t_us": t})
        d("gnss", {"t_us": t})
        for src in ("optical", "baro"):
            d("aid_status", {"t_us": t, "source": src, "rejected": int(src == "optical" and i == 55)})
    kinds = [s for s, _ in got]
    assert kinds.count("imu") == 10 and kinds.count("gnss") == 100
    aid = [(r["source"], r["rejected"], r["t_us"]) for s, r in got if s == "aid_status"]
    assert sum(1 for a in aid if a[0] == "baro") == 5
    assert ("optical", 1, 550_000) in aid  # the rejection is written though the source wrote 0.15 s before
    assert d.dropped["imu"] == 90


def _companion_like_folder(folder: Path) -> None:
    """A companion's streams (no truth): 300 s at 10 Hz, circling at 20 m/s in a 5 m/s wind from the west, GNSS not
    used from 100 s to 200 s, the EKF drifting 1 m in that outage."""
    log = RunLog(folder)
    rng = np.random.default_rng(3)
    for i in range(3000):
        t = i * 0.1
        t_us = 10_000_000 + int(t * 1e6)
        yaw = 0.02 * t
        vn, ve = 20 * math.cos(yaw) + 0.0, 20 * math.sin(yaw) + 5.0
        n, e = 1000 * math.sin(yaw), -1000 * math.cos(yaw) + 5.0 * t
        outage = 100 <= t < 200
        err = 0.01 * (t - 100) if outage else 0.0
        log.write("ekf", {"t_us": t_us, "pos_n_m": n + err, "pos_n_sigma_m": 2.0 + err, "pos_e_m": e,
                          "pos_e_sigma_m": 2.0 + err, "height_agl_m": 100.0, "vel_n_m_s": vn + rng.normal(0, 0.1),
                          "vel_n_sigma_m_s": 0.2, "vel_e_m_s": ve + rng.normal(0, 0.1), "vel_e_sigma_m_s": 0.2,
                          "wind_n_m_s": 0.0, "wind_n_sigma_m_s": 0.3, "wind_e_m_s": 5.0, "wind_e_sigma_m_s": 0.3,
                          "wind_speed_m_s": 5.0 + rng.normal(0, 0.1), "wind_speed_sigma_m_s": 0.3,
                          "wind_from_rad": math.radians(270 + rng.normal(0, 2)), "wind_from_sigma_rad": 0.05,
                          "drift_rad": 0.1, "drift_sigma_rad": 0.01, "valid": True, "invalid_reason": ""})
        if i % 2 == 0:
            log.write("gnss", {"t_us": t_us, "pos_n_m": n, "pos_e_m": e, "pos_d_m": -100.0, "vel_n_m_s": vn,
                               "vel_e_m_s": ve, "vel_d_m_s": 0.0, "fix_ok": not outage, "fused": not outage})
        for src, scale in (("optical", 0.5), ("airspeed", 0.3)):
            r = rng.normal(0, scale)
            log.write("aid_status", {"source": src, "t_us": t_us, "innov_0": r, "innov_var_0": scale**2,
                                     "innov_1": np.nan, "innov_var_1": np.nan, "innov_2": np.nan,
                                     "innov_var_2": np.nan, "test_ratio": r * r / (9 * scale**2),
                                     "fused": 1, "rejected": 0})
        log.write("airspeed", {"t_us": t_us, "tas_m_s": 20.0})
        log.write("outputs", {"t_us": t_us, "sent": True})
    log.close()


def _check_page(folder: Path) -> str:
    page = (folder / "report.html").read_text()
    first_img = page.index("<img")
    assert page.index("<h2>Goals</h2>") < first_img
    assert "km/h" not in page and "np.float64" not in page
    assert not re.search(r"\[[-0-9.e, ]{200,}\]", page), "a series in the page"
    for src in re.findall(r"<img src='([^']+)'", page):
        assert (folder / src).is_file(), src
    return page


def test_gsoe_report_on_a_companions_logs(tmp_path):
    folder = tmp_path / "flight"
    _companion_like_folder(folder)
    gnss = read_log(folder / "gnss.csv")
    out = gnss_unused_intervals(gnss, 10_000_000 + 299.9e6)
    assert len(out) == 1 and abs(out[0][1] - out[0][0] - 100.2e6) < 0.3e6
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "cli", "report", str(folder)], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    page = _check_page(folder)
    for fig in ("trajectory.png", "position_error.png", "velocity_error.png", "wind.png", "aid_sources.png",
                "altitude_airspeed.png"):
        assert f"src='{fig}'" in page, fig
    assert "GNSS not used (shaded in every plot): 100-200 s" in page
    m = json.loads((folder / "metrics.json").read_text())
    assert m["gnss_unused_s"] == pytest.approx(100.2, abs=GNSS_GAP_S)
    assert m["dr_error_m"] == pytest.approx(1.0, abs=0.05)       # the EKF's 1 m, against the first fix after
    assert m["dr_distance_m"] == pytest.approx(2000, rel=0.1)     # 100 s at about 20 m/s
    assert m["valid_frac"] == 1.0
    r = subprocess.run([sys.executable, "-m", "cli", "report", str(tmp_path / "nothing")], env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr


@pytest.fixture(scope="module")
def thinned_sim(tmp_path_factory):
    from sim.run import run_flight
    from sim.scenario import load_scenario, scenario_with_overrides

    out = tmp_path_factory.mktemp("sim")
    scn = scenario_with_overrides(load_scenario("paper_sil_outage"),
                                  {"sensors.gnss.outages": [{"start_s": 20.0, "length_s": 15.0}]})
    metrics = run_flight(scn, seed=1, duration_s=SIM_S, out_dir=out, log_detail="reports")
    return out, metrics


def test_sim_report_opens_with_the_goals_and_shows_the_new_plots(thinned_sim):
    out, metrics = thinned_sim
    page = _check_page(out)
    for fig in ("aid_sources.png", "nees.png", "wind.png", "velocity_error.png", "position_error.png",
                "trajectory.png", "tm_cycle.png"):
        assert f"src='{fig}'" in page, fig
    assert "GNSS not used (shaded in every plot): 20-35 s" in page
    assert "NEES inside its 95 % chi-square interval" in page
    assert math.isfinite(metrics["dr_error_pct_of_distance"])


def test_thinned_sim_logs_keep_a_2000_s_flight_under_50_mb(thinned_sim):
    out, _ = thinned_sim
    size = sum(p.stat().st_size for p in out.glob("*.csv"))
    assert size / SIM_S * 2000.0 < LOG_BUDGET_BYTES_2000_S, size
    ekf, aid = read_log(out / "ekf.csv"), read_log(out / "aid_status.csv")
    assert np.all(np.diff(ekf["t_us"]) >= 0.2e6 - 1)
    assert {"optical", "airspeed", "baro", "gnss_pos"} <= set(aid["source"].astype(str))


def test_mcap_export_holds_every_stream_with_its_columns_and_units(tmp_path):
    pytest.importorskip("mcap")
    from mcap.reader import make_reader

    from sim.mcap_export import export_mcap, unit_of

    folder = tmp_path / "flight"
    _companion_like_folder(folder)
    path = export_mcap(folder)
    csvs = {p.stem: read_log(p) for p in folder.glob("*.csv")}
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
        assert counts == {f"/gsoe/{k}": int(np.sum(v["t_us"] >= 0)) for k, v in csvs.items()}
        last_t = -1
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            assert msg.log_time >= last_t  # written in time order
            last_t = msg.log_time
            if channel.topic == "/gsoe/ekf" and msg.log_time == 10_000_000 * 1000:
                rec = json.loads(msg.data)
                props = json.loads(schema.data)["properties"]
                assert set(rec) == set(csvs["ekf"]) == set(props)
                assert rec["pos_e_m"] == csvs["ekf"]["pos_e_m"][0] and props["wind_n_m_s"]["description"] == "m/s"
    assert unit_of("drift_sigma_rad") == "rad" and unit_of("accel_bias_x_m_s2") == "m/s^2"
