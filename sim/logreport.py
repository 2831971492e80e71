"""The flight report of any run folder (``gsoe sim``, ``gsoe replay``, a companion's flight logs): ``report.html``.

The page opens with the goal table (each goal metric, its goal and whether this flight meets it: the Monte Carlo
campaign's goals of :mod:`sim.montecarlo` applied to one flight), then the figures, then the other scalar metrics in
a folded table.  Series are never written into the page: they stay in ``metrics.json`` and the CSV logs, linked
from it.  Every figure is in SI units (m, m/s, s, degrees for angles at the edge) and shades the stretches where no
GNSS fix was fused (the outages: gaps of more than :data:`GNSS_GAP_S` between fused fixes in ``gnss.csv``).

Figures (each drawn when its logs are there):

- trajectory (top view): EKF, truth, GNSS fixes; the EKF track inside an outage in red;
- horizontal position error and its 1-sigma: against ``truth.csv``, else against the GNSS fixes (fused or not);
- velocity error north/east with the EKF's 1-sigma band: against truth, else against the GNSS velocity;
- wind speed and direction (the direction the wind comes from) with 1-sigma bands, against the truth (total and
  steady wind) or the autopilot's estimate (``autopilot_wind.csv`` of a replay);
- drift over time with its sigma, against the truth;
- NEES over time (position, velocity and wind N/E, 6 degrees of freedom) with its 95 % chi-square interval: the
  in-memory series of ``metrics.json`` (full covariance) where present, else from the logged sigmas and truth;
- innovations with their 1-sigma and test ratios per aid source (``aid_status.csv``), rejected samples marked;
- height above ground and true airspeed.

Without ``metrics.json`` the table is computed from the logs: estimate validity, the time GNSS was not fused, the
dead-reckoning error at the end of each outage (the EKF position against the first fix after it, in % of the
distance flown in it), wind against the autopilot's, and the drift and wind errors against a ``truth.csv``.
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.angles import angle_diff
from common.logio import read_log
from common.report import METRICS_FILE, PAGE_CSS, REPORT_FILE, SavedFigures, fmt_value, write_metrics

US_PER_S = 1_000_000
GNSS_GAP_S = 2.0  # no fused fix for longer than this: GNSS not in use (shaded)
NEES_DOF = 6
NEES_BOUNDS_95 = (1.2373442457, 14.4493753744)  # chi-square 6 dof, 2.5 % and 97.5 % quantiles
MAX_PLOT_POINTS = 20_000  # a series is thinned to at most this many points per line
SERIES_FILE = "report_series.json"
OUTAGE_COLOUR = "tab:red"
OUTAGE_ALPHA = 0.1
POS_ERROR_FLOOR_M = 0.01  # the position error's log axis starts here (the first fix is the EKF's own start)


@dataclass(frozen=True)
class Goal:
    """A goal metric of one flight: ``key`` of the metrics, ``op`` ``"<="`` or ``">="``, ``target``."""

    key: str
    op: str
    target: float
    text: str
    unit: str


# The Monte Carlo campaign's goals (sim.montecarlo.DEFAULT_GOALS), for one flight.
GOALS: tuple[Goal, ...] = (
    Goal("drift_mae_deg", "<=", 0.3, "EKF drift MAE vs truth (the paper: 0.96 deg)", "deg"),
    Goal("drift_p95_deg", "<=", 1.0, "EKF drift error, 95th percentile", "deg"),
    Goal("heading_coverage", ">=", 0.99, "heading coverage (1-deg bins with a drift estimate)", ""),
    Goal("wind_speed_rmse_m_s", "<=", 0.3, "wind speed RMSE vs the 5 s mean wind", "m/s"),
    Goal("wind_dir_rmse_deg", "<=", 5.0, "wind direction RMSE", "deg"),
    Goal("dr_error_pct_of_distance", "<=", 1.0, "dead-reckoning error at the end of the GNSS outage", "% of distance"),
    Goal("nees_in_bounds_frac", ">=", 0.90, "NEES inside its 95 % chi-square interval", "fraction of steps"),
    Goal("wind_vs_autopilot_rmse_m_s", "<=", 1.0, "wind vs the autopilot's estimate, RMS of the vector difference",
         "m/s"),
)
# other figures shown above the folded table when present
HEADLINE = {"valid_frac": "estimate valid, fraction of the EKF records",
            "gnss_unused_s": "time without a fused GNSS fix [s]",
            "dr_error_m": "position error at the first fix after the outage [m]",
            "dr_distance_m": "distance flown without GNSS [m]",
            "pos_error_m_final": "position error vs truth at the end of the outage [m]",
            "pos_error_m_max": "largest position error vs truth in the outage [m]",
            "frames": "camera frames", "realtime_factor": "simulated seconds per second of computing",
            "sim_s": "simulated time [s]", "duration_s": "length of the log [s]"}


# ------------------------------------------------------------------------------------------------ reading
def _stream(folder: Path, name: str) -> dict[str, Any]:
    p = folder / f"{name}.csv"
    return read_log(p) if p.is_file() else {}


def _t_s(d: Mapping[str, Any], t0_us: float) -> NDArray[np.float64]:
    return (np.asarray(d["t_us"], dtype=float) - t0_us) / US_PER_S


def gnss_unused_intervals(gnss: Mapping[str, Any], t_end_us: float, gap_s: float = GNSS_GAP_S
                          ) -> list[tuple[float, float]]:
    """Where no GNSS fix was fused for longer than ``gap_s`` (``t_us`` intervals), up to ``t_end_us``; before the
    first fused fix is not an outage (the filter had not started on GNSS)."""
    if not gnss or "fused" not in gnss:
        return []
    ok = (np.asarray(gnss["fused"], dtype=float) > 0.5) & (np.asarray(gnss["fix_ok"], dtype=float) > 0.5)
    t = np.asarray(gnss["t_us"], dtype=float)[ok]
    if t.size == 0:
        return []
    edges = np.append(t, max(t_end_us, t[-1]))
    gaps = np.diff(edges)
    return [(float(edges[i]), float(edges[i + 1])) for i in np.flatnonzero(gaps > gap_s * US_PER_S)]


def _thin(*arrays: NDArray[Any]) -> list[NDArray[Any]]:
    n = arrays[0].size
    if n <= MAX_PLOT_POINTS:
        return list(arrays)
    step = int(math.ceil(n / MAX_PLOT_POINTS))
    return [a[::step] for a in arrays]


@dataclass
class FlightLogs:
    """The streams of a run folder, on one time axis: seconds from the first EKF record."""

    folder: Path
    ekf: dict[str, Any]
    truth: dict[str, Any]
    gnss: dict[str, Any]
    aid: dict[str, Any]
    airspeed: dict[str, Any]
    autopilot_wind: dict[str, Any]
    metrics: dict[str, Any]
    t0_us: float
    outages_us: list[tuple[float, float]]

    @classmethod
    def read(cls, folder: str | Path) -> FlightLogs:
        f = Path(folder)
        ekf = _stream(f, "ekf")
        if not ekf:
            raise FileNotFoundError(f"{f}: no ekf.csv (not a run folder of gsoe sim, gsoe replay or the companion)")
        metrics = json.loads((f / METRICS_FILE).read_text()) if (f / METRICS_FILE).is_file() else {}
        t0 = float(np.asarray(ekf["t_us"], dtype=float)[0])
        gnss = _stream(f, "gnss")
        return cls(f, ekf, _stream(f, "truth"), gnss, _stream(f, "aid_status"), _stream(f, "airspeed"),
                   _stream(f, "autopilot_wind"), metrics, t0,
                   gnss_unused_intervals(gnss, float(np.asarray(ekf["t_us"], dtype=float)[-1])))

    @property
    def kind(self) -> str:
        if self.truth:
            return "simulated flight"
        if (self.folder / "outputs.csv").is_file():
            return "companion flight"
        return "replayed flight log"

    def t(self, d: Mapping[str, Any]) -> NDArray[np.float64]:
        return _t_s(d, self.t0_us)

    @property
    def outages_s(self) -> list[tuple[float, float]]:
        return [((a - self.t0_us) / US_PER_S, (b - self.t0_us) / US_PER_S) for a, b in self.outages_us]

    def truth_at(self, key: str, t_s: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.interp(t_s, self.t(self.truth), np.asarray(self.truth[key], dtype=float))


def _true_drift(T: Mapping[str, Any]) -> NDArray[np.float64]:
    course = np.arctan2(np.asarray(T["vel_e_m_s"], dtype=float), np.asarray(T["vel_n_m_s"], dtype=float))
    return np.asarray(angle_diff(course, np.asarray(T["yaw_rad"], dtype=float)), dtype=float)


def _interp_angle(t: NDArray[np.float64], tp: NDArray[np.float64], a: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.arctan2(np.interp(t, tp, np.sin(a)), np.interp(t, tp, np.cos(a)))


# ------------------------------------------------------------------------------------------------ metrics
def metrics_from_logs(L: FlightLogs) -> dict[str, Any]:
    """The figures a folder without ``metrics.json`` gets (module docstring)."""
    E = L.ekf
    t = L.t(E)
    out: dict[str, Any] = {"duration_s": float(t[-1] - t[0]) if t.size else math.nan}
    valid = np.asarray(E["valid"], dtype=float) > 0.5
    out["valid_frac"] = float(valid.mean()) if valid.size else math.nan
    out["gnss_unused_s"] = float(sum(b - a for a, b in L.outages_s))
    dr = _dead_reckoning(L)
    out.update(dr)
    if L.autopilot_wind:
        ta = L.t(L.autopilot_wind)
        sel = valid & (t >= ta[0]) & (t <= ta[-1])
        if sel.any():
            dn = np.asarray(E["wind_n_m_s"])[sel] - np.interp(t[sel], ta, L.autopilot_wind["wind_n_m_s"])
            de = np.asarray(E["wind_e_m_s"])[sel] - np.interp(t[sel], ta, L.autopilot_wind["wind_e_m_s"])
            out["wind_vs_autopilot_rmse_m_s"] = float(np.sqrt(np.mean(dn**2 + de**2)))
    if L.truth:
        ok = valid & np.isfinite(np.asarray(E["drift_rad"], dtype=float))
        td = _interp_angle(t[ok], L.t(L.truth), _true_drift(L.truth))
        err = np.degrees(np.abs(np.asarray(angle_diff(np.asarray(E["drift_rad"])[ok], td))))
        if err.size:
            out["drift_mae_deg"] = float(err.mean())
            out["drift_p95_deg"] = float(np.percentile(err, 95))
        nees = _nees_from_sigmas(L)
        if nees is not None and nees[1].size:
            lo, hi = NEES_BOUNDS_95
            out["nees_in_bounds_frac"] = float(np.mean((nees[1] >= lo) & (nees[1] <= hi)))
    return out


def _dead_reckoning(L: FlightLogs) -> dict[str, float]:
    """The EKF's position error against the first fix after each outage, and the distance flown in it (EKF
    velocity integrated); the longest outage's figures."""
    G, E = L.gnss, L.ekf
    if not G or not L.outages_us:
        return {}
    tg = np.asarray(G["t_us"], dtype=float)
    ok = np.asarray(G["fix_ok"], dtype=float) > 0.5
    te = np.asarray(E["t_us"], dtype=float)
    best: dict[str, float] = {}
    for a, b in sorted(L.outages_us, key=lambda ab: ab[0] - ab[1]):
        after = np.flatnonzero(ok & (tg >= b) & (tg <= b + GNSS_GAP_S * US_PER_S))
        if after.size == 0:
            continue
        i = after[0]
        t_fix = tg[i]
        # the EKF just before the fix is fused (its record at the fix may already hold it)
        before = te < t_fix
        if not before.any():
            continue
        j = int(np.flatnonzero(before)[-1])
        dt_s = (t_fix - te[j]) / US_PER_S  # carried to the fix's time with the EKF's velocity
        err = math.hypot(float(E["pos_n_m"][j] + E["vel_n_m_s"][j] * dt_s - G["pos_n_m"][i]),
                         float(E["pos_e_m"][j] + E["vel_e_m_s"][j] * dt_s - G["pos_e_m"][i]))
        seg = (te >= a) & (te <= te[j])
        gs = np.hypot(np.asarray(E["vel_n_m_s"], dtype=float)[seg], np.asarray(E["vel_e_m_s"], dtype=float)[seg])
        dist = float(np.trapezoid(gs, te[seg] / US_PER_S)) if seg.sum() > 1 else math.nan
        best = {"dr_error_m": err, "dr_distance_m": dist, "dr_outage_s": (b - a) / US_PER_S,
                "dr_error_pct_of_distance": 100.0 * err / dist if dist > 0 else math.nan}
        break
    return best


def _nees_from_sigmas(L: FlightLogs) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """NEES on the diagonal covariance of the logged sigmas (position, velocity, wind N/E) against truth."""
    E, T = L.ekf, L.truth
    if not T:
        return None
    t = L.t(E)
    valid = np.asarray(E["valid"], dtype=float) > 0.5
    terms = []
    for est, sig, tru in (("pos_n_m", "pos_n_sigma_m", "pos_n_m"), ("pos_e_m", "pos_e_sigma_m", "pos_e_m"),
                          ("vel_n_m_s", "vel_n_sigma_m_s", "vel_n_m_s"), ("vel_e_m_s", "vel_e_sigma_m_s", "vel_e_m_s"),
                          ("wind_n_m_s", "wind_n_sigma_m_s", "wind_n_m_s"),
                          ("wind_e_m_s", "wind_e_sigma_m_s", "wind_e_m_s")):
        e = np.asarray(E[est], dtype=float) - L.truth_at(tru, t)
        terms.append((e / np.asarray(E[sig], dtype=float)) ** 2)
    nees = np.sum(terms, axis=0)
    ok = valid & np.isfinite(nees)
    return t[ok], nees[ok]


# ------------------------------------------------------------------------------------------------ figures
class _Figures(SavedFigures):
    """The figures of a flight's logs, into its folder."""

    def __init__(self, L: FlightLogs) -> None:
        super().__init__(L.folder)
        self.L = L

    def shade(self, *axes: Any) -> None:
        for ax in axes:
            for i, (a, b) in enumerate(self.L.outages_s):
                ax.axvspan(a, b, color=OUTAGE_COLOUR, alpha=OUTAGE_ALPHA, lw=0,
                           label="GNSS not used" if i == 0 else None)

    def all(self) -> list[tuple[str, str]]:
        for draw in (self.trajectory, self.position_error, self.velocity_error, self.wind, self.drift, self.nees,
                     self.aid_sources, self.height_airspeed):
            draw()
        return self.figs

    def trajectory(self) -> None:
        L, E = self.L, self.L.ekf
        fig, ax = self.plt.subplots(figsize=(7, 6))
        if L.truth:
            ax.plot(*_thin(np.asarray(L.truth["pos_e_m"]), np.asarray(L.truth["pos_n_m"])), "k-", lw=1, label="truth")
        t = L.t(E)
        ax.plot(*_thin(np.asarray(E["pos_e_m"]), np.asarray(E["pos_n_m"])), "b-", lw=0.8, label="EKF")
        for i, (a, b) in enumerate(L.outages_s):
            sel = (t >= a) & (t <= b)
            ax.plot(np.asarray(E["pos_e_m"])[sel], np.asarray(E["pos_n_m"])[sel], "-", color=OUTAGE_COLOUR, lw=1.2,
                    label="EKF, GNSS not used" if i == 0 else None)
            if sel.any():
                k = np.flatnonzero(sel)
                ax.plot(E["pos_e_m"][k[0]], E["pos_n_m"][k[0]], "o", color=OUTAGE_COLOUR, ms=5, mfc="none")
        G = L.gnss
        if G:
            ok = np.asarray(G["fix_ok"], dtype=float) > 0.5
            ax.plot(np.asarray(G["pos_e_m"])[ok], np.asarray(G["pos_n_m"])[ok], ".", ms=1, color="0.6",
                    label="GNSS fixes")
        ax.set_xlabel("east [m]")
        ax.set_ylabel("north [m]")
        ax.set_aspect("equal", "datalim")
        ax.legend(fontsize=8)
        self.save(fig, "trajectory.png", "Trajectory, top view; the EKF track where no GNSS fix was used in red "
                  "(circle: where it starts)")

    def position_error(self) -> None:
        L, E = self.L, self.L.ekf
        t = L.t(E)
        if L.truth:
            ref = "truth"
            tt = t
            dn = np.asarray(E["pos_n_m"]) - L.truth_at("pos_n_m", t)
            de = np.asarray(E["pos_e_m"]) - L.truth_at("pos_e_m", t)
        elif L.gnss:
            ref = "GNSS fixes (used or not)"
            G = L.gnss
            ok = np.asarray(G["fix_ok"], dtype=float) > 0.5
            tt = L.t(G)[ok]
            dn = np.interp(tt, t, E["pos_n_m"]) - np.asarray(G["pos_n_m"])[ok]
            de = np.interp(tt, t, E["pos_e_m"]) - np.asarray(G["pos_e_m"])[ok]
        else:
            return
        fig, ax = self.plt.subplots(figsize=(9, 3.2))
        ax.plot(*_thin(tt, np.hypot(dn, de)), "b-", lw=0.8, label=f"horizontal error vs {ref}")
        ax.plot(*_thin(t, np.hypot(np.asarray(E["pos_n_sigma_m"]), np.asarray(E["pos_e_sigma_m"]))), "b:", lw=0.8,
                label="EKF 1-sigma")
        ax.set_yscale("log")
        ax.set_ylim(bottom=POS_ERROR_FLOOR_M)
        self.shade(ax)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("position error [m]")
        ax.legend(fontsize=8)
        self.save(fig, "position_error.png", f"Horizontal position error vs {ref}, with the EKF's 1-sigma")

    def velocity_error(self) -> None:
        L, E = self.L, self.L.ekf
        t = L.t(E)
        fig, axes = self.plt.subplots(2, 1, figsize=(9, 4.5), sharex=True)
        for ax, axis in zip(axes, ("n", "e"), strict=True):
            est = np.asarray(E[f"vel_{axis}_m_s"], dtype=float)
            sig = np.asarray(E[f"vel_{axis}_sigma_m_s"], dtype=float)
            if L.truth:
                ref, tt = "truth", t
                err = est - L.truth_at(f"vel_{axis}_m_s", t)
            elif L.gnss:
                ref = "GNSS velocity"
                ok = np.asarray(L.gnss["fix_ok"], dtype=float) > 0.5
                tt = L.t(L.gnss)[ok]
                err = np.interp(tt, t, est) - np.asarray(L.gnss[f"vel_{axis}_m_s"], dtype=float)[ok]
            else:
                plt = self.plt
                plt.close(fig)
                return
            ts, ss = _thin(t, sig)
            ax.fill_between(ts, -ss, ss, color="b", alpha=0.15, lw=0, label="EKF +-1 sigma")
            ax.plot(*_thin(tt, err), "b-", lw=0.6, label=f"EKF - {ref}")
            # the scale of the flight, not of the filter's first second (its initial sigma of several m/s)
            finite = np.abs(err[np.isfinite(err)])
            if finite.size:
                lim = max(4.0 * float(np.nanmedian(sig)), float(np.percentile(finite, 99.95)) * 1.2, 0.1)
                ax.set_ylim(-lim, lim)
            ax.set_ylabel(f"velocity error {'north' if axis == 'n' else 'east'} [m/s]")
            self.shade(ax)
        axes[0].legend(fontsize=8)
        axes[1].set_xlabel("time [s]")
        self.save(fig, "velocity_error.png", f"Velocity error vs {ref} with the EKF's 1-sigma band")

    def wind(self) -> None:
        L, E = self.L, self.L.ekf
        t = L.t(E)
        valid = np.asarray(E["valid"], dtype=float) > 0.5
        fig, axes = self.plt.subplots(2, 1, figsize=(9, 5), sharex=True)
        spd, spd_s = np.asarray(E["wind_speed_m_s"], dtype=float), np.asarray(E["wind_speed_sigma_m_s"], dtype=float)
        frm, frm_s = np.asarray(E["wind_from_rad"], dtype=float), np.asarray(E["wind_from_sigma_rad"], dtype=float)
        # directions around their median, unwrapped there (a wind from the north stays one band, not 0 and 360)
        centre = float(np.degrees(np.arctan2(np.median(np.sin(frm[valid])), np.median(np.cos(frm[valid]))))
                       ) % 360.0 if valid.any() else 0.0

        def around(deg: NDArray[np.float64]) -> NDArray[np.float64]:
            return centre + (np.asarray(deg, dtype=float) - centre + 180.0) % 360.0 - 180.0

        tv, s, ss, f, fs = _thin(t[valid], spd[valid], spd_s[valid], around(np.degrees(frm[valid])),
                                 np.degrees(frm_s[valid]))
        axes[0].fill_between(tv, s - ss, s + ss, color="b", alpha=0.2, lw=0)
        axes[0].plot(tv, s, "b-", lw=0.8, label="EKF +-1 sigma", zorder=3)  # above the references
        axes[1].fill_between(tv, f - fs, f + fs, color="b", alpha=0.2, lw=0)
        axes[1].plot(tv, f, "b.", ms=1, zorder=3)
        ref = ""
        if L.truth:
            ref = "truth"
            tt = L.t(L.truth)
            for key_n, key_e, style, label in (("wind_n_m_s", "wind_e_m_s", dict(color="0.6", lw=0.5), "truth (total)"),
                                               ("wind_steady_n_m_s", "wind_steady_e_m_s", dict(color="k", lw=0.8),
                                                "truth (steady)")):
                vn, ve = np.asarray(L.truth[key_n], dtype=float), np.asarray(L.truth[key_e], dtype=float)
                # the wind state is the velocity of the air; it comes from the opposite direction
                axes[0].plot(*_thin(tt, np.hypot(vn, ve)), label=label, **style)
                axes[1].plot(*_thin(tt, around(np.degrees(np.arctan2(-ve, -vn)))), ".", ms=0.5,
                             color=style["color"])
        elif L.autopilot_wind:
            ref = "the autopilot's estimate"
            A = L.autopilot_wind
            ta = L.t(A)
            vn, ve = np.asarray(A["wind_n_m_s"], dtype=float), np.asarray(A["wind_e_m_s"], dtype=float)
            axes[0].plot(ta, np.hypot(vn, ve), "k-", lw=0.8, label="autopilot")
            axes[1].plot(ta, around(np.degrees(np.arctan2(-ve, -vn))), "k.", ms=1)
        axes[0].set_ylabel("wind speed [m/s]")
        axes[1].set_ylabel("wind from [deg]")
        axes[1].set_xlabel("time [s]")
        # the scale of the flight's wind and its usual sigma, not of the filter's first seconds
        for ax, (vals, sig) in zip(axes, ((s, ss), (f, fs)), strict=True):
            lines = [np.asarray(ln.get_ydata(), dtype=float) for ln in ax.get_lines()]
            data = np.concatenate([vals, *lines]) if lines else vals
            data = data[np.isfinite(data)]
            if data.size:
                pad = 2.0 * float(np.nanmedian(sig)) + 0.05 * float(np.ptp(data)) + 0.1
                ax.set_ylim(float(np.percentile(data, 0.5)) - pad, float(np.percentile(data, 99.5)) + pad)
        self.shade(*axes)
        axes[0].legend(fontsize=8)
        self.save(fig, "wind.png", "Wind speed and the direction it comes from, EKF with 1-sigma bands"
                  + (f" vs {ref}" if ref else ""))

    def drift(self) -> None:
        L, E = self.L, self.L.ekf
        t = L.t(E)
        valid = np.asarray(E["valid"], dtype=float) > 0.5
        d, ds = np.degrees(np.asarray(E["drift_rad"], dtype=float)), np.degrees(np.asarray(E["drift_sigma_rad"]))
        fig, ax = self.plt.subplots(figsize=(9, 3.2))
        tv, dv, sv = _thin(t[valid], d[valid], ds[valid])
        ax.fill_between(tv, dv - sv, dv + sv, color="b", alpha=0.2, lw=0)
        ax.plot(tv, dv, "b-", lw=0.6, label="EKF +-1 sigma")
        if L.truth:
            ax.plot(*_thin(L.t(L.truth), np.degrees(_true_drift(L.truth))), "k-", lw=0.5, label="truth")
        ax.set_ylabel("drift [deg]")
        ax.set_xlabel("time [s]")
        self.shade(ax)
        ax.legend(fontsize=8)
        self.save(fig, "drift.png", "Drift angle (course minus heading), EKF with 1-sigma"
                  + (" vs truth" if L.truth else ""))

    def nees(self) -> None:
        L = self.L
        m = L.metrics
        if m.get("nees_series") and m.get("nees_t_s"):
            t = np.asarray(m["nees_t_s"], dtype=float) - (L.t0_us / US_PER_S if L.truth else 0.0)
            nees = np.asarray(m["nees_series"], dtype=float)
            src = "full covariance, metrics.json"
        else:
            got = _nees_from_sigmas(L)
            if got is None:
                return
            t, nees = got
            src = "diagonal of the logged sigmas"
        lo, hi = NEES_BOUNDS_95
        fig, ax = self.plt.subplots(figsize=(9, 3.2))
        ax.plot(*_thin(t, nees), "b.", ms=1.5, label=f"NEES ({src})")
        ax.axhline(lo, color="k", ls="--", lw=0.8, label="95 % chi-square interval (6 dof)")
        ax.axhline(hi, color="k", ls="--", lw=0.8)
        ax.axhline(NEES_DOF, color="0.5", lw=0.5)
        ax.set_yscale("log")
        ax.set_ylabel("NEES (pos, vel, wind N/E)")
        ax.set_xlabel("time [s]")
        self.shade(ax)
        inside = float(np.mean((nees >= lo) & (nees <= hi))) if nees.size else math.nan
        ax.set_title(f"{100 * inside:.1f} % of the points inside the interval", fontsize=9)
        ax.legend(fontsize=8, loc="upper right")
        self.save(fig, "nees.png", "Normalised estimation error squared over time with its 95 % bounds")

    def aid_sources(self) -> None:
        L, A = self.L, self.L.aid
        if not A:
            return
        src = np.asarray(A["source"]).astype(str)
        var0 = np.asarray(A["innov_var_0"], dtype=float)
        names = [s for s in dict.fromkeys(src) if np.isfinite(var0[src == s]).any()]
        if not names:
            return
        t_all = L.t(A)
        fig, axes = self.plt.subplots(len(names), 2, figsize=(11, 1.9 * len(names) + 0.6), sharex=True,
                                      squeeze=False)
        for row, name in enumerate(names):
            sel = (src == name) & (np.asarray(A["t_us"], dtype=float) >= 0)
            t = t_all[sel]
            rejected = np.asarray(A["rejected"], dtype=float)[sel] > 0.5
            ax = axes[row, 0]
            for k, colour in zip(range(3), ("b", "g", "m"), strict=True):
                col = f"innov_{k}"
                if col not in A:
                    continue
                v = np.asarray(A[col], dtype=float)[sel]
                var = np.asarray(A[f"innov_var_{k}"], dtype=float)[sel]
                if not np.isfinite(v).any():
                    continue
                ts, vs, sd = _thin(t, v, np.sqrt(var))
                gap = np.append(np.diff(ts) > GNSS_GAP_S, False)  # no band drawn across a gap in the samples
                sd = np.where(gap | np.roll(gap, 1), np.nan, sd)
                ax.fill_between(ts, -sd, sd, color=colour, alpha=0.12, lw=0)
                ax.plot(ts, vs, ".", color=colour, ms=1, label=f"component {k}")
            ax.set_ylabel(f"{name}\ninnovation", fontsize=8)
            ax2 = axes[row, 1]
            tr = np.asarray(A["test_ratio"], dtype=float)[sel]
            ax2.plot(*_thin(t[~rejected], tr[~rejected]), "b.", ms=1, label="fused")
            if rejected.any():
                ax2.plot(t[rejected], tr[rejected], "r.", ms=2, label="rejected")
            ax2.axhline(1.0, color="k", ls="--", lw=0.8)
            ax2.set_yscale("log")
            ax2.set_ylabel("test ratio", fontsize=8)
            self.shade(ax, ax2)
            if row == 0:
                ax2.legend(fontsize=7, loc="upper right")
        axes[-1, 0].set_xlabel("time [s]")
        axes[-1, 1].set_xlabel("time [s]")
        self.save(fig, "aid_sources.png", "Innovations per aid source with their 1-sigma band (left; units of each "
                  "source: px, m/s, rad, m) and test ratios (right; above 1 rejected)")

    def height_airspeed(self) -> None:
        L, E = self.L, self.L.ekf
        fig, axes = self.plt.subplots(2, 1, figsize=(9, 4.2), sharex=True)
        t = L.t(E)
        axes[0].plot(*_thin(t, np.asarray(E["height_agl_m"], dtype=float)), "b-", lw=0.8, label="EKF")
        if L.truth:
            axes[0].plot(*_thin(L.t(L.truth), np.asarray(L.truth["height_agl_m"], dtype=float)), "k-", lw=0.6,
                         label="truth")
        axes[0].set_ylabel("height above ground [m]")
        axes[0].legend(fontsize=8)
        if L.airspeed:
            axes[1].plot(*_thin(L.t(L.airspeed), np.asarray(L.airspeed["tas_m_s"], dtype=float)), "k-", lw=0.6,
                         label="measured")
        elif L.truth:
            axes[1].plot(*_thin(L.t(L.truth), np.asarray(L.truth["tas_m_s"], dtype=float)), "k-", lw=0.6)
        axes[1].set_ylabel("true airspeed [m/s]")
        axes[1].set_xlabel("time [s]")
        self.shade(*axes)
        self.save(fig, "altitude_airspeed.png", "Height above ground and true airspeed")


# ------------------------------------------------------------------------------------------------ page
def _goal_rows(metrics: Mapping[str, Any], applies: Sequence[str]) -> str:
    """One row per goal in ``applies``: its value, goal and verdict (``n/a`` when this run does not measure it: too
    short for the settle time, no outage, no truth)."""
    rows = []
    for g in GOALS:
        if g.key not in applies:
            continue
        v = metrics.get(g.key)
        num = float(v) if isinstance(v, int | float) and not isinstance(v, bool) else math.nan
        ok = math.isfinite(num) and (num <= g.target if g.op == "<=" else num >= g.target)
        verdict = "met" if ok else ("not met" if math.isfinite(num) else "n/a: not measured in this run")
        colour = "#cfc" if ok else ("#fcc" if math.isfinite(num) else "#eee")
        rows.append(f"<tr><td>{html.escape(g.text)}</td><td class=n>{html.escape(fmt_value(num))}</td>"
                    f"<td>{html.escape(g.unit)}</td><td>{html.escape(g.op)} {g.target:g}</td>"
                    f"<td style='background:{colour}'>{verdict}</td></tr>")
    return "".join(rows)


def _scalar(v: Any) -> bool:
    return isinstance(v, int | float | str | bool) or v is None


def write_page(folder: Path, title: str, subtitle: str, metrics: Mapping[str, Any], figs: Sequence[tuple[str, str]],
               outages_s: Sequence[tuple[float, float]], applies: Sequence[str] | None = None) -> Path:
    """``report.html``: goal table, headline figures, figures, the other scalar metrics folded, links to the
    series (module docstring)."""
    goal_keys = {g.key for g in GOALS}
    head = [(f"{text} ({k})", metrics[k]) for k, text in HEADLINE.items() if k in metrics and _scalar(metrics[k])]
    rest = {k: v for k, v in metrics.items() if _scalar(v) and k not in goal_keys and k not in HEADLINE}
    series = sorted(k for k, v in metrics.items() if not _scalar(v))
    outage_text = ("; ".join(f"{a:.0f}-{b:.0f} s" for a, b in outages_s) if outages_s else "none")
    logs = sorted(p.name for p in folder.glob("*.csv"))
    links = " ".join(f"<a href='{html.escape(n)}'>{html.escape(n)}</a>" for n in logs)
    goals = _goal_rows(metrics, [g.key for g in GOALS] if applies is None else applies)
    page = (
        "<!doctype html><html><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)}</title><style>{PAGE_CSS}table{{border-collapse:collapse}}"
        "td,th{border-bottom:1px solid #ddd;text-align:left}td.n{text-align:right;font-family:monospace}"
        "figure{margin:1em 0}figcaption{color:#444;font-size:90%}</style></head><body>"
        f"<h1>{html.escape(title)}</h1><p>{html.escape(subtitle)}</p>"
        "<h2>Goals</h2>"
        + (f"<table><tr><th>metric</th><th>value</th><th>unit</th><th>goal</th><th></th></tr>{goals}</table>"
           if goals else "<p>No goal metric in this run (they need a truth or a GNSS outage).</p>")
        + "<table>" + "".join(f"<tr><td>{html.escape(k)}</td><td class=n>{html.escape(fmt_value(v))}</td></tr>"
                              for k, v in head) + "</table>"
        + f"<p>GNSS not used (shaded in every plot): {html.escape(outage_text)}.</p>"
        + "<h2>Figures</h2>"
        + "".join(f"<figure><img src='{html.escape(n)}' alt='{html.escape(c)}'><figcaption>{html.escape(c)}"
                  "</figcaption></figure>" for n, c in figs)
        + "<h2>Data</h2><details><summary>All scalar metrics</summary><table>"
        + "".join(f"<tr><td>{html.escape(k)}</td><td class=n>{html.escape(fmt_value(v))}</td></tr>"
                  for k, v in sorted(rest.items()))
        + "</table></details>"
        + (f"<p>Series ({html.escape(', '.join(series))}): <a href='{METRICS_FILE}'>{METRICS_FILE}</a>.</p>"
           if series else "")
        + f"<p>Logs: {links}</p></body></html>")
    p = folder / REPORT_FILE
    p.write_text(page)
    return p


def build_report(folder: str | Path, *, title: str | None = None, subtitle: str = "",
                 extra_figs: Sequence[tuple[str, str]] = ()) -> Path:
    """Read a run folder's logs, draw the figures and write ``report.html`` (module docstring); ``extra_figs``
    (already in the folder) follow the standard ones.  A folder without ``metrics.json`` gets one computed from
    its logs."""
    L = FlightLogs.read(folder)
    metrics = dict(L.metrics)
    derived = metrics_from_logs(L)
    if not L.metrics:
        metrics = derived
        write_metrics(L.folder, metrics)
    else:
        # the run's own dead-reckoning figures (gsoe sim: against truth) are not mixed with the ones against GNSS
        own_dr = isinstance(metrics.get("dr_error_pct_of_distance"), int | float)
        for k in ("valid_frac", "gnss_unused_s", "dr_error_m", "dr_distance_m", "wind_vs_autopilot_rmse_m_s"):
            if k in derived and k not in metrics and not (own_dr and k.startswith("dr_")):
                metrics[k] = derived[k]
    figs = _Figures(L).all() + list(extra_figs)
    name = title or f"{L.kind.capitalize()}: {L.folder.name}"
    truth_goals = ("drift_mae_deg", "drift_p95_deg", "heading_coverage", "wind_speed_rmse_m_s", "wind_dir_rmse_deg",
                   "nees_in_bounds_frac")
    applies = [g.key for g in GOALS if g.key in metrics
               or (g.key in truth_goals and bool(L.truth)) or g.key == "dr_error_pct_of_distance"
               or (g.key == "wind_vs_autopilot_rmse_m_s" and bool(L.autopilot_wind))]
    return write_page(L.folder, name, subtitle or f"{L.kind}, {L.folder}", metrics, figs, L.outages_s, applies)
