"""Monte Carlo campaigns: seeded draws, local pool vs Dask, resume, crash isolation, re-fly, aggregation, report.

The campaign mechanics run twice: with :func:`fake_run_flight` (a fast stand-in with ``run_flight``'s signature
whose errors are known functions of the scenario, so the aggregation and the cause analysis can be checked against
that truth) and with the real :func:`sim.run.run_flight` (skipped only while ``sim/run.py`` does not exist).
"""

from __future__ import annotations

import json
import math
import os
import shlex
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import stats as sps

from common.config import ConfigError
from common.metrics import nees_bounds
from sim.mc_report import write_report
from sim.montecarlo import (
    DEFAULT_GOALS,
    RunRecord,
    _diff,
    _nees_summary,
    _plain,
    code_fingerprint,
    draw_run_params,
    is_timing_key,
    load_campaign_spec,
    load_spec,
    read_records,
    rerun_commands,
    run_campaign,
    run_one,
    run_path,
    run_seed,
    scenario_features,
    scenario_for_run,
    write_run_scenario,
)
from sim.scenario import TEXTURES, Scenario, load_scenario

ROOT = Path(__file__).resolve().parent.parent
HAVE_REAL_RUNNER = (ROOT / "sim" / "run.py").exists()
FAKE_RUNNER = "tests.test_montecarlo:fake_run_flight"
REAL_RUNNER = "sim.run:run_flight"
# The fake flight's error model (the truth the cause analysis must recover).
FAKE_LOW_TEXTURES = ("uniform_grass", "water")
FAKE_LOW_TEXTURE_DRIFT_DEG = 2.0
FAKE_DRIFT_PER_WIND_DEG = 0.01
FAKE_NEES_DOF = 4
SHORT_FLIGHT_S = 30.0
CAMPAIGN_FLIGHT_S = 15.0  # real flights in the default suite: 6 of them, about 5 s each on this machine


def fake_run_flight(scn: Scenario, *, seed: int, duration_s: float | None = None, out_dir: Path | None = None,
                    progress: bool = False) -> dict[str, object]:
    """Stand-in for ``sim.run.run_flight``: deterministic in (scenario, seed), errors known functions of the
    scenario; a consistent filter's NEES (chi-square with FAKE_NEES_DOF dof) once per second."""
    rng = np.random.default_rng(seed)
    dur = scn.duration_s if duration_s is None else duration_s
    low = scn.terrain.texture in FAKE_LOW_TEXTURES
    wind = scn.wind.speed_m_s
    t = np.arange(1.0, dur + 0.5, 1.0)
    nees = rng.chisquare(FAKE_NEES_DOF, t.size)
    lo, hi = nees_bounds(FAKE_NEES_DOF)
    drift = 0.1 + FAKE_DRIFT_PER_WIND_DEG * wind + (FAKE_LOW_TEXTURE_DRIFT_DEG if low else 0.0) + 0.05 * rng.random()
    m: dict[str, object] = {
        "drift_mae_deg": drift, "drift_p95_deg": 2.5 * drift, "heading_coverage": 0.5 if low else 1.0,
        "wind_speed_rmse_m_s": 0.1 + 0.02 * wind, "wind_dir_rmse_deg": 2.0 + 10.0 / max(wind, 0.5),
        "dr_error_pct_of_distance": 0.5 + rng.random(), "nees_in_bounds_frac": float(np.mean((nees >= lo) &
                                                                                            (nees <= hi))),
        "baseline_drift_mae_deg": 2.0 * drift, "baseline_heading_coverage": 0.9,
        "frames": int(dur * scn.camera.rate_hz), "sim_s": dur, "wall_s": 0.01, "realtime_factor": dur / 0.01,
        "nees_t_s": t, "nees_series": nees, "nees_dof": FAKE_NEES_DOF,
        "drift_err_by_heading_deg": rng.normal(0.0, drift, 36),
    }
    if out_dir is not None:
        Path(out_dir, "metrics.json").write_text(json.dumps({k: v for k, v in m.items()
                                                             if not isinstance(v, np.ndarray)}))
    return m


def write_spec(path: Path, *, runner: str, n_runs: int = 4, duration_s: float = SHORT_FLIGHT_S,
               extra: str = "", params: str | None = None) -> Path:
    default_params = """
"wind.speed_m_s" = { dist = "uniform", low = 0.0, high = 12.0 }
"wind.from_deg" = { dist = "uniform", low = 0.0, high = 360.0 }
"terrain.texture" = { dist = "choice", values = ["town_river", "farmland", "mosaic", "water"] }
"mc.mean_agl_m" = { dist = "uniform", low = 75.0, high = 230.0 }
"sensors.ahrs.latency_s" = { dist = "uniform", low = 0.0, high = 0.1 }
"camera.exposure_s" = { dist = "loguniform", low = 0.0005, high = 0.02 }
"mc.camera_focal_error_frac" = { dist = "normal", mean = 0.0, std = 0.01, low = -0.03, high = 0.03 }
"mc.gnss_outage_start_frac" = { dist = "uniform", low = 0.2, high = 0.4 }
"mc.gnss_outage_length_frac" = { dist = "uniform", low = 0.3, high = 0.5 }
"""
    path.write_text(f"""
name = "test"
base_scenario = "paper_sil"
base_seed = 11
n_runs = {n_runs}
duration_s = {duration_s}
runner = "{runner}"
{extra}
[fixed]
"wind.ref_height_m" = 100.0
[params]
{default_params if params is None else params}
""")
    return path


# --------------------------------------------------------------------------------------------------------------
# Spec and draws


def test_default_spec_covers_the_issue_parameters() -> None:
    spec = load_spec()
    assert spec.base.name == "paper_sil" and spec.n_runs == 100 and spec.duration_s == 600.0
    assert spec.runner == REAL_RUNNER and spec.goals == DEFAULT_GOALS
    p = spec.params
    assert (p["wind.speed_m_s"].low, p["wind.speed_m_s"].high) == (0.0, 12.0)
    assert set(p["terrain.texture"].values or ()) == set(TEXTURES)
    for key in ("wind.from_deg", "wind.turbulence_scale", "wind.gust_amplitude_m_s", "mc.mean_airspeed_m_s",
                "sensors.ahrs.latency_s", "camera.exposure_s", "sensors.imu.gyro_bias_std_deg_s",
                "mc.camera_focal_error_frac", "mc.gnss_outage_start_frac", "mc.gnss_outage_length_frac"):
        assert key in p, key
    # The heights flown over the campaign span 50-300 m above ground.
    lo = scenario_for_run(spec, {"mc.mean_agl_m": p["mc.mean_agl_m"].low})
    hi = scenario_for_run(spec, {"mc.mean_agl_m": p["mc.mean_agl_m"].high})
    heights_lo = [w.height_m for w in lo.mission.waypoints]
    heights_hi = [w.height_m for w in hi.mission.waypoints]
    assert 50.0 <= min(heights_lo) <= 55.0 and 295.0 <= max(heights_hi) <= 300.0


@pytest.mark.parametrize(("params", "extra", "field"), [
    ('"wind.speed_m_s" = { dist = "uniform", low = 0.0, high = 45.0 }', "", 'params."wind.speed_m_s"'),
    ('"wind.speed_m_s" = { dist = "uniform", low = 5.0, high = 1.0 }', "", 'params."wind.speed_m_s".high'),
    ('"wind.speedx" = { dist = "uniform", low = 0.0, high = 1.0 }', "", 'params."wind.speedx"'),
    ('"wind.speed_m_s" = { dist = "normal", mean = 1.0, std = 1.0 }', "", 'params."wind.speed_m_s".low'),
    ('"wind.speed_m_s" = { dist = "gamma", low = 0.0, high = 1.0 }', "", 'params."wind.speed_m_s".dist'),
    ('"camera.exposure_s" = { dist = "loguniform", low = 0.0, high = 0.01 }', "", 'params."camera.exposure_s".low'),
    ('"terrain.texture" = { dist = "choice", values = ["mosaic", "lava"] }', "", 'params."terrain.texture"'),
    ('"terrain.texture" = { dist = "choice", values = ["mosaic"], weights = [1.0, 2.0] }', "",
     'params."terrain.texture".weights'),
    ('"mc.gnss_outage_start_s" = { dist = "uniform", low = 10.0, high = 20.0 }', "",
     'params."mc.gnss_outage_length_s"'),
    ('"mc.altitude" = { dist = "uniform", low = 10.0, high = 20.0 }', "", 'params."mc.altitude"'),
    ('"mc.mean_agl_m" = { dist = "uniform", low = 5.0, high = 20.0 }', "", 'params."mc.mean_agl_m"'),
    ("", "n_runs = 0", "n_runs"),
    ("", 'runner = "no_colon"', "runner"),
    ("", "bogus = 1", "bogus"),
])
def test_spec_errors_name_the_field(tmp_path: Path, params: str, extra: str, field: str) -> None:
    spec = write_spec(tmp_path / "bad.toml", runner=FAKE_RUNNER, params=params)
    if extra:  # replaces the line of the same key, or adds one
        key = extra.split(" = ")[0]
        lines = [ln for ln in spec.read_text().splitlines() if not ln.startswith(f"{key} = ")]
        spec.write_text("\n".join([extra, *lines]) + "\n")
    with pytest.raises(ConfigError) as e:
        load_spec(spec)
    assert field in str(e.value), str(e.value)
    assert str(spec) in str(e.value)


def test_draws_are_seeded_per_run_and_per_key(tmp_path: Path) -> None:
    spec = load_spec(write_spec(tmp_path / "s.toml", runner=FAKE_RUNNER))
    a = draw_run_params(spec, 11, 3)
    assert a == draw_run_params(spec, 11, 3)
    assert a != draw_run_params(spec, 11, 4) and a != draw_run_params(spec, 12, 3)
    assert run_seed(11, 3) == run_seed(11, 3) != run_seed(11, 4)
    # Removing one key leaves the other draws unchanged.
    fewer = load_spec(write_spec(tmp_path / "f.toml", runner=FAKE_RUNNER, params="""
"wind.from_deg" = { dist = "uniform", low = 0.0, high = 360.0 }
"mc.mean_agl_m" = { dist = "uniform", low = 75.0, high = 230.0 }"""))
    b = draw_run_params(fewer, 11, 3)
    assert b == {k: a[k] for k in b}
    # Each draw follows its distribution: 2000 draws of the uniform agree with scipy's uniform (KS test).
    x = [draw_run_params(fewer, 11, i)["mc.mean_agl_m"] for i in range(2000)]
    assert sps.kstest(x, sps.uniform(loc=75.0, scale=155.0).cdf).pvalue > 1e-3


def test_run_scenario_applies_the_draws(tmp_path: Path) -> None:
    spec = load_spec(write_spec(tmp_path / "s.toml", runner=FAKE_RUNNER, duration_s=600.0))
    params = draw_run_params(spec, 11, 2)
    scn = scenario_for_run(spec, params)
    feats = scenario_features(scn)
    assert feats["mean_agl_m"] == pytest.approx(params["mc.mean_agl_m"])
    assert scn.wind.speed_m_s == params["wind.speed_m_s"] and scn.wind.ref_height_m == 100.0
    (outage,) = scn.sensors.gnss.outages
    assert outage.start_s == pytest.approx(600.0 * params["mc.gnss_outage_start_frac"])
    assert outage.length_s == pytest.approx(600.0 * params["mc.gnss_outage_length_frac"])
    fx = spec.camera.fx_px * (1.0 + params["mc.camera_focal_error_frac"])
    assert scn.camera.gsoe_overrides["camera"]["fx_px"] == pytest.approx(fx)
    # Relative altitude changes of the mission are kept (heights scale about the ground).
    base_h = np.array([w.height_m for w in spec.base.mission.waypoints])
    h = np.array([w.height_m for w in scn.mission.waypoints])
    assert np.allclose(h / base_h, h[0] / base_h[0])
    # The scenario file written for `gsoe sim` loads back to exactly the same scenario.
    path = write_run_scenario(spec, params, 600.0, tmp_path / "scn" / "run_00002.toml")
    assert load_scenario(path) == scn


def test_nees_is_averaged_across_runs_against_chi_square_bounds() -> None:
    def recs(scale: float, n: int = 12, n_t: int = 200) -> list[RunRecord]:
        out = []
        for i in range(n):
            rng = np.random.default_rng([5, i])
            e = scale * rng.chisquare(3, n_t)
            out.append(RunRecord(index=i, base_seed=5, run_seed=i, duration_s=float(n_t), status="ok",
                                 metrics={"nees_t_s": list(np.arange(n_t, dtype=float)), "nees_series": list(e),
                                          "nees_dof": 3, "nees_in_bounds_frac": 0.9}))
        return out

    consistent = _nees_summary(recs(1.0))["series"]
    assert consistent["bounds"] == pytest.approx(list(nees_bounds(3, 12)))
    # The average of 12 chi-square(3) runs lies in the 95 % interval about 95 % of the time (binomial, 200 steps).
    assert consistent["avg_in_bounds_frac"] >= 0.88
    overconfident = _nees_summary(recs(3.0))["series"]
    assert overconfident["avg_in_bounds_frac"] <= 0.05
    assert "no NEES time series" in _nees_summary([RunRecord(0, 5, 0, 1.0, "ok")])["note"]


# --------------------------------------------------------------------------------------------------------------
# Aggregation, cause analysis and report against the fake flight's known error model


def test_summary_goals_causes_and_report(tmp_path: Path) -> None:
    params = """
"wind.speed_m_s" = { dist = "uniform", low = 0.0, high = 12.0 }
"terrain.texture" = { dist = "choice", values = ["town_river", "farmland", "mosaic", "water", "uniform_grass"] }
"sensors.ahrs.latency_s" = { dist = "uniform", low = 0.0, high = 0.1 }
"""
    goals = """
[[goals]]
name = "coverage_mean"
metric = "heading_coverage"
op = ">="
threshold = 0.99
stat = "mean"
[[goals]]
name = "drift_median"
metric = "drift_mae_deg"
op = "<="
threshold = 0.3
[[goals]]
name = "wind_dir"
metric = "wind_dir_rmse_deg"
op = "<="
threshold = 5.0
min_wind_m_s = 3.0
"""
    spec = load_spec(write_spec(tmp_path / "s.toml", runner=FAKE_RUNNER, n_runs=40, params=params, extra=goals))
    assert [g.name for g in spec.goals] == ["coverage_mean", "drift_median", "wind_dir"]
    out = tmp_path / "camp"
    run_campaign(spec, out, workers=0, progress=False)
    write_report(out)
    recs = read_records(out)
    summary = json.loads((out / "summary.json").read_text())
    assert [r.index for r in recs] == list(range(40)) and summary["campaign"]["n_failed"] == 0

    drift = np.array([r.metrics["drift_mae_deg"] for r in recs])
    s = summary["metrics"]["drift_mae_deg"]
    assert s["median"] == pytest.approx(np.median(drift)) and s["p95"] == pytest.approx(np.percentile(drift, 95))
    assert s["worst_run"] == int(np.argmax(drift)) and s["worst"] == pytest.approx(drift.max())
    cov = summary["metrics"]["heading_coverage"]
    assert cov["higher_is_better"] and cov["worst"] == pytest.approx(0.5)
    # Goals: the fraction of runs meeting each, against the fake's error model.
    goals = {g["name"]: g for g in summary["goals"]}
    low = np.array([r.features["texture"] in FAKE_LOW_TEXTURES for r in recs])
    assert goals["drift_median"]["frac_runs_meeting"] == pytest.approx(np.mean(drift <= 0.3))
    assert goals["drift_median"]["value"] == pytest.approx(np.median(drift))
    assert goals["coverage_mean"]["frac_runs_meeting"] == pytest.approx(np.mean(~low))
    assert goals["coverage_mean"]["value"] == pytest.approx(np.mean(np.where(low, 0.5, 1.0)))
    windy = [r for r in recs if r.features["wind_speed_m_s"] >= 3.0]
    assert goals["wind_dir"]["n_eligible"] == len(windy)
    assert goals["wind_dir"]["value"] == pytest.approx(np.median([r.metrics["wind_dir_rmse_deg"]
                                                                        for r in windy]))
    # EKF vs baseline: the fake baseline's drift is twice the EKF's in every run.
    assert summary["ekf_vs_baseline"]["drift_mae_deg"]["ekf_better_frac"] == 1.0
    # The missed heading-coverage goal is traced to the texture, not to the latency (which does not matter).
    assert not goals["coverage_mean"]["met"] and 0.0 < np.mean(low) < 1.0
    effects = summary["causes"]["coverage_mean"]["effects"]
    assert effects[0]["param"] == "terrain.texture" and effects[0]["shared"]
    assert {c for c, v in effects[0]["categories"].items() if v["bad_frac"] == 1.0} == set(FAKE_LOW_TEXTURES)
    lat = next(e for e in effects if e["param"] == "sensors.ahrs.latency_s")
    assert not lat["shared"]
    # NEES from the series of a consistent (fake) filter: inside the bounds most of the time.
    assert summary["nees"]["series"]["avg_in_bounds_frac"] >= 0.8
    assert len(summary["drift_by_heading"]["median_abs"]) == 36
    # Report: every figure it references exists; the worst runs carry re-fly commands and scenario files.
    html = (out / "report.html").read_text()
    for img in ("mc_distributions.png", "mc_vs_wind.png", "mc_vs_altitude.png", "mc_vs_texture.png",
                "mc_drift_vs_heading.png", "mc_nees.png", "mc_cause_coverage_mean.png"):
        assert f"src='{img}'" in html and (out / img).stat().st_size > 0, img
    worst = summary["worst_runs"][0]["index"]
    assert f"gsoe montecarlo --only {worst} --out" in html
    assert load_scenario(out / "scenarios" / f"run_{worst:05d}.toml") == scenario_for_run(
        spec, recs[worst].params, SHORT_FLIGHT_S)


# --------------------------------------------------------------------------------------------------------------
# Failures: raised in the run, and a worker process that dies


def test_failures_are_recorded_without_stopping_the_campaign(tmp_path: Path) -> None:
    spec = load_spec(write_spec(tmp_path / "s.toml", runner=FAKE_RUNNER, n_runs=5,
                                extra="fail_runs = [1]\ncrash_runs = [3]"))
    out = tmp_path / "camp"
    res = run_campaign(spec, out, workers=2, progress=False)
    assert res.failed == [1, 3] and res.flown == [0, 1, 2, 3, 4]
    recs = {r.index: r for r in read_records(out)}
    assert recs[1].status == "failed" and "InjectedFailure" in recs[1].error
    assert "raise InjectedFailure" in recs[1].traceback and recs[1].params == draw_run_params(spec, 11, 1)
    assert recs[3].status == "failed" and recs[3].error.startswith("WorkerDied")
    assert recs[3].params == draw_run_params(spec, 11, 3)
    # The runs that shared the pool with the dying worker are intact and equal to runs flown in this process.
    for i in (0, 2, 4):
        assert recs[i].status == "ok"
        assert recs[i].deterministic() == RunRecord.from_dict(run_one(spec, 11, i).to_dict()).deterministic()
    assert not list((out / "runs").glob(".*"))  # no markers or temporary files left


# --------------------------------------------------------------------------------------------------------------
# Local pool vs Dask, resume, re-fly: with the fake and with the real flight


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The same 4-run campaign (run 2 fails on purpose) flown on the local pool, interrupted after runs 0 and 3
    and resumed, and on a Dask LocalCluster; with the real flight (the fake one until sim/run.py exists)."""
    kind = "real" if HAVE_REAL_RUNNER else "fake"
    tmp = tmp_path_factory.mktemp(f"mc_{kind}")
    spec = load_spec(write_spec(tmp / "spec.toml", runner=REAL_RUNNER if kind == "real" else FAKE_RUNNER,
                                n_runs=4, duration_s=CAMPAIGN_FLIGHT_S, extra="fail_runs = [2]"))
    local = tmp / "local"
    # An interrupted campaign: only runs 0 and 3 were flown ...
    first = run_campaign(spec, local, indices=[0, 3], workers=2, progress=False)
    stamps = {i: run_path(local, i).stat().st_mtime_ns for i in (0, 3)}
    texts = {i: run_path(local, i).read_text() for i in (0, 3)}
    # ... then resumed: the rest is flown, the finished runs are not.
    resumed = run_campaign(spec, local, workers=2, resume=True, progress=False)
    write_report(local)
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        dask = run_campaign(spec, tmp / "dask", indices=[0, 1, 2], scheduler=cluster.scheduler_address,
                            progress=False)
    return {"spec": spec, "local": local, "dask_dir": tmp / "dask", "first": first, "resumed": resumed,
            "dask": dask, "stamps": stamps, "texts": texts, "kind": kind}


def test_resume_flies_only_the_missing_runs(campaigns: Mapping[str, Any]) -> None:
    c = campaigns
    assert c["first"].flown == [0, 3]
    assert c["resumed"].flown == [1, 2] and c["resumed"].skipped == [0, 3]
    for i in (0, 3):
        assert run_path(c["local"], i).stat().st_mtime_ns == c["stamps"][i]
        assert run_path(c["local"], i).read_text() == c["texts"][i]
    camp = json.loads((c["local"] / "campaign.json").read_text())
    assert [s["flown"] for s in camp["sessions"]] == [2, 2]
    assert all(s["host"]["python_loop_ns"] > 0 for s in camp["sessions"])   # each session's throughput has its host
    summary = json.loads((c["local"] / "summary.json").read_text())
    assert summary["campaign"]["n_records"] == 4 and summary["campaign"]["missing_runs"] == []
    assert (c["local"] / "report.html").exists()


def test_local_pool_and_dask_give_identical_runs(campaigns: Mapping[str, Any]) -> None:
    c = campaigns
    local = read_records(c["local"])
    dask = read_records(c["dask_dir"])
    assert [r.index for r in local] == [0, 1, 2, 3] and [r.index for r in dask] == [0, 1, 2]
    for a, b in zip(local, dask, strict=False):
        assert a.deterministic() == b.deterministic(), (a.index, _diff(a.deterministic(), b.deterministic()))
    assert {r.worker for r in dask} != {r.worker for r in local[:3]}  # really flown by other processes
    ok = [r for r in local if r.status == "ok"]
    assert len(ok) == 3 and all(math.isfinite(r.peak_rss_mb) and r.peak_rss_mb > 0 for r in local)
    if c["kind"] == "real":
        for r in ok:
            assert r.metrics["sim_s"] == pytest.approx(CAMPAIGN_FLIGHT_S, abs=0.1)
            assert "drift_mae_deg" in r.metrics and "frames" in r.metrics


def test_injected_failure_is_recorded_on_both_backends(campaigns: Mapping[str, Any]) -> None:
    c = campaigns
    for d in (c["local"], c["dask_dir"]):
        rec = read_records(d)[2]
        assert rec.status == "failed" and "InjectedFailure" in rec.error and "Traceback" in rec.traceback
        assert rec.params == draw_run_params(c["spec"], 11, 2)
    assert c["resumed"].failed == [2] and c["dask"].failed == [2]


def test_refly_one_run_reproduces_it_bit_for_bit(campaigns: Mapping[str, Any], capsys: pytest.CaptureFixture
                                                 ) -> None:
    from cli.main import main

    c = campaigns
    assert load_campaign_spec(c["local"]) == c["spec"]
    code = main(["montecarlo", "--only", "1", "--out", str(c["local"])])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "identical to the campaign's record" in text
    again = read_records(c["local"])[1]
    redo = RunRecord.from_dict(json.loads((c["local"] / "reflown" / "run_00001" / "record.json").read_text()))
    assert redo.deterministic() == again.deterministic()
    timing = {k for k in redo.metrics if is_timing_key(k)}
    assert {"wall_s", "realtime_factor"} <= timing
    assert {k: v for k, v in redo.metrics.items() if k not in timing} == {
        k: v for k, v in again.metrics.items() if k not in timing}
    assert (c["local"] / "reflown" / "run_00001" / "metrics.json").exists()  # the flight wrote its outputs
    # a second re-flight starts a fresh folder: the first one's files are kept beside it, not appended to
    first = {f.name: f.read_bytes() for f in (c["local"] / "reflown" / "run_00001").iterdir() if f.is_file()}
    assert main(["montecarlo", "--only", "1", "--out", str(c["local"])]) == 0
    text = capsys.readouterr().out
    assert "identical to the campaign's record" in text and "flown by code" not in text
    assert again.code == redo.code == code_fingerprint() and len(again.code) == 16
    kept = c["local"] / "reflown" / "run_00001.old1"
    assert {f.name: f.read_bytes() for f in kept.iterdir() if f.is_file()} == first
    csvs = list((c["local"] / "reflown" / "run_00001").glob("*.csv"))
    assert csvs or c["kind"] != "real"                                          # the simulator writes CSV logs
    for f in csvs:
        assert f.read_bytes().count(b"\n") == first[f.name].count(b"\n"), f.name


def test_code_fingerprint_follows_the_files_and_a_refly_names_other_code(campaigns: Mapping[str, Any],
                                                                         capsys: pytest.CaptureFixture,
                                                                         tmp_path: Path) -> None:
    """The fingerprint is the SHA-256 of the packages' and config's files (recomputed here from the files, and it
    moves when one byte of one of them does), and a re-flight of a record flown by other code says so."""
    import hashlib

    from cli.main import main
    from sim import montecarlo as mc

    root = Path(mc.__file__).resolve().parent.parent
    files = sorted(f for pkg in mc.CODE_PACKAGES for f in (root / pkg).rglob("*")
                   if f.is_file() and "__pycache__" not in f.parts and f.suffix != ".pyc")
    assert any(f.name == "ekf.py" for f in files) and any(f.name == "default.toml" for f in files)

    def digest(changed: Path | None) -> str:
        h = hashlib.sha256()
        for f in files:
            h.update(f.relative_to(root).as_posix().encode() + b"\0")
            h.update(f.read_bytes() + (b"#" if f == changed else b""))
        return h.hexdigest()[:16]

    assert code_fingerprint() == digest(None)
    assert digest(files[0]) != digest(None)
    # a record flown by other code: the re-flight still compares, and names the code
    c = campaigns
    path = run_path(c["local"], 2)
    original = path.read_text()
    rec = json.loads(original)
    rec["code"] = "0123456789abcdef"
    path.write_text(json.dumps(rec))
    try:
        main(["montecarlo", "--only", "2", "--out", str(c["local"])])
    finally:
        path.write_text(original)                  # the module's other tests read this campaign
    text = capsys.readouterr().out
    assert "flown by code 0123456789abcdef" in text and code_fingerprint() in text


def test_gsoe_sim_command_of_the_report_reflies_the_run(campaigns: Mapping[str, Any],
                                                         capsys: pytest.CaptureFixture) -> None:
    from cli.main import main

    c = campaigns
    if c["kind"] != "real":
        pytest.skip("the gsoe sim command exists for the real flight only")
    rec = read_records(c["local"])[3]
    scn_file = write_run_scenario(c["spec"], rec.params, rec.duration_s, c["local"] / "scenarios" / "run_00003.toml")
    argv = shlex.split(rerun_commands(c["local"], c["spec"], rec, scn_file)[0])
    assert argv[:2] == ["gsoe", "sim"]
    assert main([*argv[1:], "--no-progress"]) == 0, capsys.readouterr()
    out = Path(argv[argv.index("--out") + 1])
    flown = _plain(json.loads((out / "metrics.json").read_text()))
    keys = {k for k in rec.metrics if not is_timing_key(k)}
    assert {k: flown.get(k) for k in keys} == {k: rec.metrics[k] for k in keys}


# --------------------------------------------------------------------------------------------------------------
# Command line


def test_cli_campaign_resume_guard_and_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from cli.main import main

    spec = write_spec(tmp_path / "s.toml", runner=FAKE_RUNNER, n_runs=3, extra="fail_runs = [1]")
    out = tmp_path / "camp"
    args = ["montecarlo", "--spec", str(spec), "--out", str(out), "--workers", "0", "--no-progress"]
    assert main(args) == 1  # a run failed
    text = capsys.readouterr().out
    assert "3 runs flown" in text and "report:" in text
    assert main(args) == 2  # the folder already holds a campaign
    assert "--resume" in capsys.readouterr().err
    assert main([*args, "--resume", "-n", "5"]) == 1  # extends the campaign by runs 3 and 4
    assert "2 runs flown, 3 already done" in capsys.readouterr().out
    assert main([*args, "--resume", "--retry-failed"]) == 1  # flies the failed run 1 again (it fails again)
    assert "1 runs flown, 4 already done" in capsys.readouterr().out
    sessions = json.loads((out / "campaign.json").read_text())["sessions"]
    assert [(s["flown"], s["failed"]) for s in sessions] == [(3, 1), (2, 0), (1, 1)]
    assert main([*args, "--resume", "--seed", "12"]) == 2  # another seed cannot resume this campaign
    assert "base_seed" in capsys.readouterr().err
    assert main(["montecarlo", "--only", "1"]) == 2
    with pytest.raises(SystemExit):
        main(["montecarlo", "--duration", "-5"])
    bad = write_spec(tmp_path / "bad.toml", runner=FAKE_RUNNER,
                     params='"wind.speed_m_s" = { dist = "uniform", low = 0.0, high = 99.0 }')
    assert main(["montecarlo", "--spec", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert 'params."wind.speed_m_s"' in capsys.readouterr().err


# --------------------------------------------------------------------------------------------------------------
# The issue's campaign (slow, informative)


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_REAL_RUNNER, reason="sim/run.py (run_flight) does not exist yet")
def test_fifty_run_campaign_meets_the_accuracy_goals(tmp_path: Path) -> None:
    spec = load_spec().with_options(n_runs=50)
    out = Path(os.environ.get("GSOE_MC_SLOW_OUT", tmp_path / "mc50"))
    run_campaign(spec, out, resume=out.exists(), progress=False)
    write_report(out)
    summary = json.loads((out / "summary.json").read_text())
    missed = [g for g in summary["goals"] if not g["met"]]
    detail = "; ".join(f"{g['name']}: {g['stat']}({g['metric']}) = {g['value']} vs {g['op']} {g['threshold']} "
                       f"[{(summary['causes'].get(g['name'], {}).get('effects') or [{}])[0].get('finding', '')}]"
                       for g in missed)
    assert summary["campaign"]["n_failed"] == 0, summary["campaign"]["failed_runs"]
    assert not missed, f"goals missed (report: {out / 'report.html'}): {detail}"
