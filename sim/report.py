"""Figures and report of a simulated flight (``metrics.json``, PNG plots like the paper's figures, ``report.html``)."""

from __future__ import annotations

import html
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from common import metrics as M
from common.report import PAGE_CSS, REPORT_FILE, SavedFigures, figures_html, metrics_rows_html, write_metrics
from gsoe.equations import gnss_drift_rad

if TYPE_CHECKING:
    from sim.run import _Series
    from sim.scenario import Scenario

def gnss_drift_series(G: dict[str, np.ndarray], T: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The GNSS drift of a flight record (paper eq. 18-21): consecutive good fixes of ``G`` and the true heading of
    ``T`` at the later one; (times in s, drift in rad), empty with fewer than two good fixes."""
    ok = G["ok"] > 0.5 if G["t_s"].size else np.zeros(0, bool)
    if ok.sum() < 2:
        return np.zeros(0), np.zeros(0)
    t, n, e = G["t_s"][ok], G["n"][ok], G["e"][ok]
    yaw = M.interp_angle(t[1:], T["t_s"], T["yaw"])
    d = np.asarray(gnss_drift_rad(n, e, yaw))
    return t[1:], d


def write_report(out_dir: Path, scn: Scenario, series: _Series, metrics: dict[str, Any]) -> None:
    """``metrics.json`` and ``report.html`` of a simulated flight: the report of its logs
    (:func:`sim.logreport.build_report`, the same as ``gsoe report``), followed by the figures only the simulator
    has (the sample distance, one template-matching cycle, the drift per heading, from the run's memory)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_metrics(out_dir, metrics)
    figures = SavedFigures(out_dir)
    plt, save, figs = figures.plt, figures.save, figures.figs

    T = series.arrays("truth")
    B = series.arrays("baseline")
    E = series.arrays("ekf")
    G = series.arrays("gnss")

    if T["t_s"].size < 2 or not (out_dir / "ekf.csv").is_file():
        _write_html(out_dir, scn, metrics, figs)
        return
    # fig. 8: sample distance
    gs = np.hypot(T["vn"], T["ve"])
    rate = float(scn.camera.rate_hz)
    fig, ax = plt.subplots(figsize=(8, 3))
    ax.plot(T["t_s"], gs / rate, "k-", lw=0.8, label="ground distance per frame [m]")
    ax.plot(T["t_s"], T["h"] / _focal(metrics), "b-", lw=0.8, label="ground sample distance [m/px]")
    ax.set_xlabel("time [s]")
    ax.legend()
    save(fig, "sample_distance.png", "GSOE sample distance (paper fig. 8)")
    # fig. 9: merged TM cycle
    cf = series.cycle_figure
    if cf is not None and cf["path"]:
        from matplotlib.patches import Rectangle

        fig, ax = plt.subplots(figsize=(6, 4))
        ax.imshow(cf["base"], cmap="gray", vmin=0, vmax=255)
        u0, v0 = cf["ref_uv"]
        path = np.array(cf["path"])
        ax.plot(u0 + path[:, 0], v0 - path[:, 1], "r.-", ms=4)
        half = 9.5
        for dx, dy in path[:: max(1, len(path) // 4)]:
            ax.add_patch(Rectangle((u0 + dx - half, v0 - dy - half), 2 * half, 2 * half,
                                   fill=False, ec="y", lw=0.7))
        ax.set_title(f"TM cycle {cf['cycle_id']} at t = {cf['t_s']:.1f} s (forward is up)")
        save(fig, "tm_cycle.png", "One template-matching cycle merged into one image (paper fig. 9)")
    # fig. 10: median drift per heading
    true_drift = M.true_drift_rad(T["vn"], T["ve"], T["yaw"])
    fig, ax = plt.subplots(figsize=(8, 4))
    c, m = M.median_per_heading_deg(T["yaw"], true_drift)
    ax.plot(c, m, "k.", ms=3, label="truth")
    if G["t_s"].size and (G["ok"] > 0.5).sum() > 2:
        tg, dg = gnss_drift_series(G, T)
        c, m = M.median_per_heading_deg(M.interp_angle(tg, T["t_s"], T["yaw"]), dg)
        ax.plot(c, m, ".", color="0.6", ms=3, label="GNSS (eq. 18-21)")
    if B["t_s"].size:
        ok = B["released"] > 0.5
        c, m = M.median_per_heading_deg(B["heading"][ok], B["drift"][ok])
        ax.plot(c, m, "r.", ms=3, label="optical, paper chain")
    if E["t_s"].size:
        ok = E["valid"] > 0.5
        c, m = M.median_per_heading_deg(E["heading"][ok], E["drift"][ok])
        ax.plot(c, m, "b.", ms=3, label="EKF")
    ax.set_xlabel("heading [deg]")
    ax.set_ylabel("median drift [deg]")
    ax.legend()
    save(fig, "drift_vs_heading.png", "Median drift per 1-deg heading bin (paper fig. 10)")
    from sim.logreport import build_report

    build_report(out_dir, title=f"Simulated flight: {scn.name} (seed {metrics.get('seed', '?')})",
                 subtitle=scn.description, extra_figs=figs)


def _focal(metrics: dict[str, Any]) -> float:
    return float(metrics.get("focal_px", 351.86))


def _write_html(out_dir: Path, scn: Scenario, metrics: dict[str, Any], figs: list[tuple[str, str]]) -> None:
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>gsoe sim {html.escape(scn.name)}</title>"
            f"<style>{PAGE_CSS}</style></head><body>"
            f"<h1>Simulated flight: {html.escape(scn.name)}</h1><p>{html.escape(scn.description)}</p>"
            f"<h2>Metrics</h2><table>{metrics_rows_html(metrics)}</table><h2>Figures</h2>{figures_html(figs)}"
            "</body></html>")
    (out_dir / REPORT_FILE).write_text(page)
