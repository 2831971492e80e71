"""``report.html`` of a Monte Carlo campaign: figures (matplotlib Agg PNGs next to it) and tables.

Reads the campaign folder written by :func:`sim.montecarlo.run_campaign` (``campaign.json``, ``runs/*.json``,
``summary.json``) and writes ``report.html`` with: the goals and the fraction of runs meeting each; EKF vs baseline
side by side; error distributions; errors against wind speed, altitude and texture; drift error against heading;
NEES over time against its chi-square bounds (when the runs report a NEES series); throughput and memory; the worst
runs with the commands that re-fly each (their scenario files are written to ``scenarios/``); the failed runs; and
for every missed goal the parameters its bad runs share.  Every figure copes with missing metrics (it says so).
"""

from __future__ import annotations

import html
import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from sim.montecarlo import (  # noqa: E402
    SUMMARY_FILE,
    MonteCarloSpec,
    RunRecord,
    load_campaign_spec,
    metric_value,
    read_records,
    rerun_commands,
    write_run_scenario,
    write_summary,
)

log = logging.getLogger(__name__)

REPORT_FILE = "report.html"
FIG_DPI = 90
HIST_BINS = 20
# The metrics whose distributions the report shows (EKF, with the baseline overlaid where it exists).
DISTRIBUTION_METRICS: tuple[str, ...] = ("drift_mae_deg", "drift_p95_deg", "heading_coverage", "wind_speed_rmse_m_s",
                                         "wind_dir_rmse_deg", "dr_error_pct_of_distance", "nees_in_bounds_frac",
                                         "pos_error_m_max", "wall_s", "peak_rss_mb")
# Errors plotted against the run's conditions.
CONDITION_METRICS: tuple[str, ...] = ("drift_mae_deg", "wind_speed_rmse_m_s", "wind_dir_rmse_deg",
                                      "dr_error_pct_of_distance")
N_CAUSE_FINDINGS = 6
N_CAUSE_PLOTS = 3


def _finite(values: Sequence[float]) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    return a[np.isfinite(a)]


def _save(fig: Any, out_dir: Path, name: str) -> str:
    fig.tight_layout()
    fig.savefig(out_dir / name, dpi=FIG_DPI)
    plt.close(fig)
    return name


def _goal_threshold(summary: Mapping[str, Any], metric: str) -> list[tuple[float, str]]:
    return [(float(g["threshold"]), f"goal ({g['stat']})") for g in summary["goals"] if g["metric"] == metric]


def _fig_distributions(recs: Sequence[RunRecord], summary: Mapping[str, Any], out: Path) -> str | None:
    keys = [k for k in DISTRIBUTION_METRICS if _finite([metric_value(r, k) for r in recs]).size]
    if not keys:
        return None
    ncol = 3
    nrow = int(math.ceil(len(keys) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.0 * nrow), squeeze=False)
    for ax, k in zip(axes.flat, keys, strict=False):
        ekf = _finite([metric_value(r, k) for r in recs])
        base = _finite([metric_value(r, f"baseline_{k}") for r in recs])
        goals = _goal_threshold(summary, k)
        span = np.concatenate([ekf, base, [th for th, _ in goals]])
        lo, hi = float(span.min()), float(span.max())
        bins = np.linspace(lo, hi if hi > lo else lo + 1.0, HIST_BINS + 1)
        ax.hist(ekf, bins=bins, alpha=0.7, label="EKF" if base.size else None)
        if base.size:
            ax.hist(base, bins=bins, alpha=0.5, label="baseline")
        for th, label in goals:
            ax.axvline(th, color="k", ls="--", lw=1, label=label)
        ax.set_title(k, fontsize=9)
        ax.set_ylabel("runs")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(keys):]:
        ax.set_visible(False)
    return _save(fig, out, "mc_distributions.png")


def _fig_vs_feature(recs: Sequence[RunRecord], feature: str, label: str, out: Path, name: str) -> str | None:
    x = np.array([float(r.features.get(feature, math.nan)) if isinstance(r.features.get(feature), int | float)
                  else math.nan for r in recs])
    keys = [k for k in CONDITION_METRICS if _finite([metric_value(r, k) for r in recs]).size]
    if not keys or not np.isfinite(x).any():
        return None
    fig, axes = plt.subplots(1, len(keys), figsize=(4.0 * len(keys), 3.2), squeeze=False)
    for ax, k in zip(axes[0], keys, strict=True):
        ax.scatter(x, [metric_value(r, k) for r in recs], s=14, label="EKF")
        b = np.array([metric_value(r, f"baseline_{k}") for r in recs])
        if np.isfinite(b).any():
            ax.scatter(x, b, s=14, marker="x", alpha=0.7, label="baseline")
            ax.legend(fontsize=7)
        ax.set_xlabel(label)
        ax.set_title(k, fontsize=9)
    return _save(fig, out, name)


def _fig_vs_texture(recs: Sequence[RunRecord], out: Path) -> str | None:
    tex = sorted({str(r.features.get("texture")) for r in recs if r.features.get("texture") is not None})
    keys = [k for k in CONDITION_METRICS if _finite([metric_value(r, k) for r in recs]).size]
    if not tex or not keys:
        return None
    fig, axes = plt.subplots(1, len(keys), figsize=(4.0 * len(keys), 3.6), squeeze=False)
    for ax, k in zip(axes[0], keys, strict=True):
        data = [_finite([metric_value(r, k) for r in recs if r.features.get("texture") == t]) for t in tex]
        pos = [j for j, d in enumerate(data) if d.size]
        if pos:
            ax.boxplot([data[j] for j in pos], positions=pos)
        for j, t in enumerate(tex):
            n_missing = sum(1 for r in recs if r.features.get("texture") == t and not math.isfinite(metric_value(r, k)))
            if n_missing:
                ax.annotate(f"{n_missing} n/a", (j, 0), xycoords=("data", "axes fraction"), ha="center", fontsize=7,
                            color="tab:red")
        ax.set_xticks(range(len(tex)), tex, rotation=45, ha="right", fontsize=7)
        ax.set_xlim(-0.5, len(tex) - 0.5)
        ax.set_title(k, fontsize=9)
    return _save(fig, out, "mc_vs_texture.png")


def _fig_heading(summary: Mapping[str, Any], out: Path) -> str | None:
    h = summary.get("drift_by_heading")
    if not h:
        return None
    c = np.asarray(h["bin_centres_deg"], dtype=float)
    med = np.array([math.nan if v is None else v for v in h["median_abs"]], dtype=float)
    p95 = np.array([math.nan if v is None else v for v in h["p95_abs"]], dtype=float)
    fig, ax = plt.subplots(figsize=(8, 3.2))
    ax.plot(c, med, label="median over runs")
    ax.plot(c, p95, label="p95 over runs", alpha=0.7)
    ax.set_xlabel("heading (deg)")
    ax.set_ylabel("|drift error| (deg)")
    ax.set_xlim(0, 360)
    ax.set_title(f"drift error vs heading ({h['key']}, {h['n_runs']} runs)", fontsize=9)
    ax.legend(fontsize=7)
    return _save(fig, out, "mc_drift_vs_heading.png")


def _fig_nees(summary: Mapping[str, Any], recs: Sequence[RunRecord], out: Path) -> str | None:
    s = summary["nees"].get("series")
    if s:
        t = np.asarray(s["t_s"], dtype=float)
        avg = np.array([math.nan if v is None else v for v in s["avg_nees"]], dtype=float)
        lo, hi = s["bounds"]
        fig, ax = plt.subplots(figsize=(8, 3.2))
        ax.plot(t, avg, lw=1, label=f"NEES averaged over {s['n_runs']} runs")
        ax.axhline(lo, color="k", ls="--", lw=1, label=f"{s['confidence']:.0%} chi-square bounds")
        ax.axhline(hi, color="k", ls="--", lw=1)
        ax.axhline(s["dof"], color="tab:green", lw=1, alpha=0.6, label=f"dof = {s['dof']}")
        ax.set_yscale("log")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("average NEES")
        ax.set_title(f"NEES consistency: average inside bounds {s['avg_in_bounds_frac']:.1%} of the time",
                     fontsize=9)
        ax.legend(fontsize=7)
        return _save(fig, out, "mc_nees.png")
    fr = _finite([metric_value(r, "nees_in_bounds_frac") for r in recs])
    if not fr.size:
        return None
    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.hist(fr, bins=HIST_BINS)
    for th, label in _goal_threshold(summary, "nees_in_bounds_frac"):
        ax.axvline(th, color="k", ls="--", lw=1, label=label)
    ax.set_xlabel("fraction of steps with NEES inside the 95 % bounds")
    ax.set_ylabel("runs")
    ax.set_title("per-run NEES consistency (no NEES time series in the run metrics)", fontsize=9)
    return _save(fig, out, "mc_nees.png")


def _fig_causes(recs: Sequence[RunRecord], summary: Mapping[str, Any], out: Path) -> dict[str, str]:
    figs: dict[str, str] = {}
    for goal, cause in summary["causes"].items():
        effects = cause["effects"][:N_CAUSE_PLOTS]
        if not effects:
            continue
        bad_set = set(cause["bad_runs"])
        elig = [r for r in recs if r.index in set(cause["eligible_runs"])]
        fig, axes = plt.subplots(1, len(effects), figsize=(3.8 * len(effects), 3.2), squeeze=False)
        for ax, eff in zip(axes[0], effects, strict=True):
            key = eff["param"]
            if eff["kind"] == "numeric":
                bad = _finite([r.params.get(key, math.nan) for r in elig if r.index in bad_set])
                good = _finite([r.params.get(key, math.nan) for r in elig if r.index not in bad_set])
                ax.boxplot([good, bad])
                ax.set_xticks([1, 2], [f"meet ({good.size})", f"miss ({bad.size})"])
            else:
                cats = list(eff["categories"])
                ax.bar(range(len(cats)), [eff["categories"][c]["bad_frac"] for c in cats])
                ax.set_xticks(range(len(cats)), cats, rotation=45, ha="right", fontsize=7)
                ax.set_ylabel("fraction of runs missing")
            ax.set_title(f"{key}\np = {eff['p_value']:.2g}", fontsize=8)
        fig.suptitle(f"goal {goal}: {cause['comparison']}", fontsize=9)
        figs[goal] = _save(fig, out, f"mc_cause_{goal}.png")
    return figs


# --------------------------------------------------------------------------------------------------------------
# HTML


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "n/a" if not math.isfinite(v) else f"{v:.4g}"
    return html.escape(str(v))


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]], raw_cols: Sequence[int] = ()) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{c if j in raw_cols else _fmt(c)}</td>" for j, c in enumerate(r))
                   + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _img(name: str | None, what: str) -> str:
    if name is None:
        return f"<p class='na'>No data for {html.escape(what)} (the run metrics lack it).</p>"
    return f"<img src='{html.escape(name)}' alt='{html.escape(what)}'>"


def _worst_rows(out_dir: Path, spec: MonteCarloSpec, summary: Mapping[str, Any], recs: Sequence[RunRecord]
                ) -> list[list[Any]]:
    by_index = {r.index: r for r in recs}
    rows = []
    for w in summary["worst_runs"]:
        rec = by_index[w["index"]]
        scn_file: Path | None = None
        if rec.params or not spec.params:
            try:
                scn_file = write_run_scenario(spec, rec.params, rec.duration_s,
                                              out_dir / "scenarios" / f"run_{rec.index:05d}.toml")
            except Exception as e:  # noqa: BLE001 - the re-fly command via --only still works
                log.warning("cannot write the scenario file of run %d: %s", rec.index, e)
        cmds = "<br>".join(f"<code>{html.escape(c)}</code>" for c in rerun_commands(out_dir, spec, rec, scn_file))
        f = rec.features
        rows.append([rec.index, rec.status if rec.status == "ok" else f"failed: {rec.error}",
                     metric_value(rec, "drift_mae_deg"), metric_value(rec, "baseline_drift_mae_deg"),
                     metric_value(rec, "wind_speed_rmse_m_s"), f.get("wind_speed_m_s"), f.get("mean_agl_m"),
                     f.get("texture"), rec.run_seed, cmds])
    return rows


_CSS = """body{font-family:sans-serif;margin:1.5em;max-width:1400px} table{border-collapse:collapse;margin:0.5em 0}
td,th{border:1px solid #bbb;padding:2px 6px;font-size:13px;text-align:right} th{background:#eee}
td:first-child,th:first-child{text-align:left} .pass{color:#070} .fail{color:#b00;font-weight:bold}
.na{color:#777} img{max-width:100%} code{font-size:12px;white-space:pre-wrap}"""


def write_report(out_dir: str | Path) -> Path:
    """Write ``report.html`` (and its PNGs) for the campaign in ``out_dir``; returns the report's path."""
    out = Path(out_dir)
    spec = load_campaign_spec(out)
    summary_path = out / SUMMARY_FILE
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else write_summary(out, spec)
    recs = read_records(out, spec.n_runs)
    c, tp = summary["campaign"], summary["throughput"]

    parts = [f"<html><head><meta charset='utf-8'><title>Monte Carlo: {html.escape(c['name'])}</title>"
             f"<style>{_CSS}</style></head><body>",
             f"<h1>Monte Carlo campaign {html.escape(c['name'])}</h1><p>{html.escape(c['description'])}</p>",
             _table(["base scenario", "base seed", "runs planned", "records", "ok", "failed", "missing",
                     "flight (s)", "runner"],
                    [[c["base_scenario"], c["base_seed"], c["n_runs"], c["n_records"], c["n_ok"], c["n_failed"],
                      len(c["missing_runs"]), c["duration_s"], c["runner"]]])]

    parts.append("<h2>Goals</h2>")
    rows: list[list[Any]] = []
    for g in summary["goals"]:
        verdict = "<span class='pass'>met</span>" if g["met"] else "<span class='fail'>missed</span>"
        cond = f" (wind &ge; {g['min_wind_m_s']:g} m/s)" if g["min_wind_m_s"] else ""
        rows.append([html.escape(g["name"]) + cond, html.escape(g["description"]),
                     f"{g['stat']}({html.escape(g['metric'])}) {html.escape(g['op'])} {g['threshold']:g}",
                     _fmt(g["value"]), verdict, _fmt(g["frac_runs_meeting"]), f"{g['n_with_value']}/{g['n_eligible']}"])
    parts.append(_table(["goal", "what", "requirement", "value", "verdict", "fraction of runs meeting",
                         "runs with value / eligible"], rows, raw_cols=(0, 1, 2, 3, 4, 5, 6)))
    tput_ok = "<span class='pass'>met</span>" if tp["throughput_goal_met"] else "<span class='fail'>missed</span>"
    parts.append(_table(
        ["campaign wall (s)", "runs flown", "sim s / wall s", "runs / hour", "mean run wall (s)",
         "projected 100 x 600 s (s)", "goal <= 900 s", "max worker peak RSS (MB)", "workers"],
        [[tp["campaign_wall_s"], tp["runs_flown_in_sessions"], tp["sim_s_per_wall_s"], tp["runs_per_hour"],
          tp["run_wall_s_mean"], tp["projected_wall_s_100x600"], tput_ok, tp["peak_rss_mb_max"],
          len(tp["peak_rss_mb_by_worker"])]], raw_cols=(6,)))

    parts.append("<h2>EKF vs baseline</h2>")
    rows = [[k, v["ekf"]["median"], v["baseline"]["median"], v["ekf"]["p95"], v["baseline"]["p95"],
             v["ekf"]["worst"], v["baseline"]["worst"], v["ekf_better_frac"]]
            for k, v in summary["ekf_vs_baseline"].items()]
    parts.append(_table(["metric", "EKF median", "baseline median", "EKF p95", "baseline p95", "EKF worst",
                         "baseline worst", "runs where EKF is better"], rows) if rows
                 else "<p class='na'>No baseline_* metrics in the runs.</p>")

    parts.append("<h2>Error distributions</h2>")
    parts.append(_img(_fig_distributions(recs, summary, out), "error distributions"))
    parts.append("<h2>Errors vs conditions</h2>")
    parts.append(_img(_fig_vs_feature(recs, "wind_speed_m_s", "steady wind speed (m/s)", out, "mc_vs_wind.png"),
                      "errors vs wind speed"))
    parts.append(_img(_fig_vs_feature(recs, "mean_agl_m", "mean height above ground (m)", out, "mc_vs_altitude.png"),
                      "errors vs altitude"))
    parts.append(_img(_fig_vs_texture(recs, out), "errors vs texture"))
    parts.append("<h2>Drift error vs heading</h2>")
    parts.append(_img(_fig_heading(summary, out), "drift error per heading (drift_err_by_heading_deg)"))
    parts.append("<h2>NEES consistency</h2>")
    n = summary["nees"]
    parts.append(f"<p>Per-run fraction of steps inside the 95 % bounds: mean {_fmt(n['in_bounds_frac_mean'])}, median "
                 f"{_fmt(n['in_bounds_frac_median'])} ({n['n_runs_with_frac']} runs). {html.escape(n.get('note', ''))}"
                 "</p>")
    parts.append(_img(_fig_nees(summary, recs, out), "NEES"))

    parts.append("<h2>Why goals are missed: parameters the bad runs share</h2>")
    cause_figs = _fig_causes(recs, summary, out)
    if not summary["causes"]:
        parts.append("<p>Every goal is met.</p>")
    for goal, cause in summary["causes"].items():
        parts.append(f"<h3>{html.escape(goal)}</h3><p>{html.escape(cause['comparison'])}: {cause['n_bad']} bad vs "
                     f"{cause['n_good']} other runs.</p>")
        effects = cause["effects"][:N_CAUSE_FINDINGS]
        if not effects:
            parts.append("<p class='na'>Too few runs on one side to compare parameters.</p>")
            continue
        rows = [[e["param"], e["finding"], e["p_value"], e.get("auc"), e["shared"]] for e in effects]
        parts.append(_table(["parameter", "finding", "p-value", "AUC (numeric)", "shared by the bad runs"], rows))
        if goal in cause_figs:
            parts.append(_img(cause_figs[goal], f"parameters of goal {goal}"))

    parts.append("<h2>Worst runs</h2><p>Ranked by drift_mae_deg (failed runs and runs without a value first). Each "
                 "command re-flies the run alone with its logs and plots; <code>gsoe montecarlo --only</code> also "
                 "checks that it reproduces the campaign's record bit for bit.</p>")
    parts.append(_table(["run", "status", "drift MAE (deg)", "baseline drift MAE", "wind RMSE (m/s)", "wind (m/s)",
                         "mean AGL (m)", "texture", "seed", "re-fly"], _worst_rows(out, spec, summary, recs),
                        raw_cols=(9,)))
    failed = [r for r in recs if r.status != "ok"]
    if failed:
        parts.append("<h2>Failed runs</h2>")
        rows = [[r.index, r.error, f"<details><summary>traceback</summary><pre>{html.escape(r.traceback)}</pre>"
                 f"</details>"] for r in failed]
        parts.append(_table(["run", "error", "traceback"], rows, raw_cols=(2,)))

    parts.append("<h2>All metrics</h2>")
    rows = [[k, s["mean"], s["median"], s["p95"], s["worst"], s["worst_run"], s["n"], s["n_missing"]]
            for k, s in {**summary["metrics"], **summary["conditional"]}.items()]
    parts.append(_table(["metric", "mean", "median", "p95", "worst", "worst run", "runs", "missing"], rows))
    parts.append("</body></html>")
    path = out / "report.html"
    tmp = path.with_name(".report.html.tmp")
    tmp.write_text("\n".join(parts), encoding="utf-8")
    tmp.replace(path)
    return path
