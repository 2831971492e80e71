"""A flight's figures from its logs: ``ekf.csv`` (with ``baseline.csv`` and ``gnss.csv``) set against a
``truth.csv`` by :func:`sim.run.compute_metrics`, the function that makes ``gsoe sim``'s figures, whoever flew it:
``gsoe sim``'s own log folder, or the companion's log folder against the SIL vehicle's truth
(``python -m sim.mavlink_vehicle ... --truth-log DIR``; tests/test_measured_flown.py).

Clocks: the truth is stamped on the vehicle's clock (the simulation time), and so are ``gsoe sim``'s logs.  The
companion stamps its logs on its own monotonic clock, a vehicle stamp mapped as ``t_companion = t_vehicle +
offset`` (:class:`nav.link.ClockSync`), and logs every new offset per telemetry kind in ``clock_sync.csv``; a
companion stamp is mapped back with the offset of :data:`CLOCK_KIND` in force at that stamp (the attitude's, which
also stamps the camera frames).

Positions: the companion's NED origin is its first 3D fix; its positions are shifted into the vehicle's frame by
that origin (each logged fix's latitude/longitude against the vehicle's reference, less the fix's logged position).

NEES: ``ekf.csv`` holds per-axis sigmas, not the 6x6 covariance of ``[pos_ne, vel_ne, wind_ne]``, so the NEES from
a log is on the diagonal covariance (``gsoe sim``'s own ``metrics.json`` has the full one).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common import metrics as M
from common.angles import angle_diff
from common.logio import read_log
from sim.run import SETTLE_S, US_PER_S, _Series, compute_metrics

CLOCK_KIND = "attitude"
_SIGMA_COLUMNS = ("pos_n_sigma_m", "pos_e_sigma_m", "vel_n_sigma_m_s", "vel_e_sigma_m_s", "wind_n_sigma_m_s",
                  "wind_e_sigma_m_s")


def vehicle_time_us(t_us: NDArray[np.float64], clock_sync: dict[str, Any], kind: str = CLOCK_KIND
                    ) -> NDArray[np.float64]:
    """Companion stamps ``t_us`` mapped to the vehicle's clock with the ``kind`` offsets of ``clock_sync.csv`` (the
    offset logged last at or before each stamp; the first one before it was logged)."""
    sel = np.asarray(clock_sync["kind"]) == kind
    if not sel.any():
        raise ValueError(f"clock_sync.csv has no {kind!r} offset")
    t_log = np.asarray(clock_sync["t_us"], dtype=float)[sel]
    off = np.asarray(clock_sync["offset_us"], dtype=float)[sel]
    idx = np.clip(np.searchsorted(t_log, t_us, side="right") - 1, 0, off.size - 1)
    return np.asarray(t_us, dtype=float) - off[idx]


def origin_ne_m(gnss: dict[str, Any], ref_lat_deg: float, ref_lon_deg: float) -> tuple[float, float]:
    """Where a log's NED origin lies in the vehicle's frame (reference ``ref_lat_deg``/``ref_lon_deg``): the median
    over its fixes of (the fix's latitude/longitude in the vehicle's frame - the fix's logged position)."""
    from sim.mavlink_vehicle import lat_lon_to_ne

    ok = (np.asarray(gnss["fix_ok"]) > 0.5) & np.isfinite(gnss["lat_deg"]) & np.isfinite(gnss["pos_n_m"])
    if not ok.any():
        raise ValueError("gnss.csv has no fix")
    ne = np.array([lat_lon_to_ne(la, lo, ref_lat_deg, ref_lon_deg)
                   for la, lo in zip(gnss["lat_deg"][ok], gnss["lon_deg"][ok], strict=True)])
    return (float(np.median(ne[:, 0] - gnss["pos_n_m"][ok])), float(np.median(ne[:, 1] - gnss["pos_e_m"][ok])))


def series_from_logs(log_dir: str | Path, truth_csv: str | Path,
                     ref_lat_lon_deg: tuple[float, float] | None = None) -> _Series:
    """The in-memory series :func:`sim.run.compute_metrics` takes, read from a log folder and a truth log (module
    docstring: a folder with ``clock_sync.csv`` is a companion's, and then needs the vehicle's reference
    ``ref_lat_lon_deg``)."""
    folder = Path(log_dir)
    T = read_log(truth_csv)
    E = read_log(folder / "ekf.csv")
    B = read_log(folder / "baseline.csv") if (folder / "baseline.csv").exists() else {}
    G = read_log(folder / "gnss.csv") if (folder / "gnss.csv").exists() else {}
    origin = (0.0, 0.0)
    if (folder / "clock_sync.csv").exists():
        if ref_lat_lon_deg is None:
            raise ValueError(f"{folder} is a companion's log: the vehicle's reference latitude/longitude is needed")
        clock = read_log(folder / "clock_sync.csv")

        def to_s(t_us: NDArray[np.float64]) -> list[float]:
            return (vehicle_time_us(np.asarray(t_us, dtype=float), clock) / US_PER_S).tolist()

        if G:
            origin = origin_ne_m(G, *ref_lat_lon_deg)
    else:
        def to_s(t_us: NDArray[np.float64]) -> list[float]:
            return (np.asarray(t_us, dtype=float) / US_PER_S).tolist()

    s = _Series()
    s.truth.update({"t_s": (np.asarray(T["t_us"], dtype=float) / US_PER_S).tolist(),  # on the vehicle's clock
                    **{k: np.asarray(T[c], dtype=float).tolist() for k, c in (
                        ("n", "pos_n_m"), ("e", "pos_e_m"), ("d", "pos_d_m"), ("vn", "vel_n_m_s"),
                        ("ve", "vel_e_m_s"), ("vd", "vel_d_m_s"), ("roll", "roll_rad"), ("pitch", "pitch_rad"),
                        ("yaw", "yaw_rad"), ("tas", "tas_m_s"), ("beta", "beta_rad"), ("wn", "wind_n_m_s"),
                        ("we", "wind_e_m_s"), ("wsn", "wind_steady_n_m_s"), ("wse", "wind_steady_e_m_s"),
                        ("h", "height_agl_m"))}})
    if E:
        s.ekf.update({"t_s": to_s(E["t_us"]), "n": (E["pos_n_m"] + origin[0]).tolist(),
                      "e": (E["pos_e_m"] + origin[1]).tolist(),
                      **{k: np.asarray(E[c], dtype=float).tolist() for k, c in (
                          ("drift", "drift_rad"), ("drift_sigma", "drift_sigma_rad"), ("wn", "wind_n_m_s"),
                          ("we", "wind_e_m_s"), ("wn_sigma", "wind_n_sigma_m_s"), ("we_sigma", "wind_e_sigma_m_s"),
                          ("ws", "wind_speed_m_s"), ("wd", "wind_from_rad"), ("n_sigma", "pos_n_sigma_m"),
                          ("e_sigma", "pos_e_sigma_m"), ("valid", "valid"), ("heading", "heading_rad"),
                          ("vn", "vel_n_m_s"), ("ve", "vel_e_m_s"))}})
        sig = np.column_stack([np.asarray(E[c], dtype=float) for c in _SIGMA_COLUMNS])
        s.ekf_cov_pvw = [np.diag(row**2) for row in sig]
    if B:
        s.baseline.update({"t_s": to_s(B["t_us"]), **{k: np.asarray(B[c], dtype=float).tolist() for k, c in (
            ("drift", "drift_rad"), ("heading", "heading_rad"), ("released", "released"),
            ("ws", "wind_speed_m_s"), ("wd", "wind_from_rad"), ("gs", "ground_speed_m_s"))}})
    if G:
        s.gnss.update({"t_s": to_s(G["t_us"]), "n": (G["pos_n_m"] + origin[0]).tolist(),
                       "e": (G["pos_e_m"] + origin[1]).tolist(), "ok": np.asarray(G["fix_ok"], dtype=float).tolist()})
    s.trim()
    return s


def drift_mae_settled_deg(series: _Series, settle_s: float = SETTLE_S) -> float:
    """The EKF's drift MAE (deg) over its valid estimates after ``settle_s`` (``compute_metrics``'s
    ``drift_mae_deg`` is over the whole flight; its wind figures are the ones taken after the settle time)."""
    T, E = series.arrays("truth"), series.arrays("ekf")
    ok = (E["valid"] > 0.5) & np.isfinite(E["drift"]) & (E["t_s"] > settle_s)
    if not ok.any() or T["t_s"].size < 2:
        return float("nan")
    true_drift = M.true_drift_rad(T["vn"], T["ve"], T["yaw"])
    truth = np.asarray(angle_diff(M.interp_angle(E["t_s"][ok], T["t_s"], true_drift + np.pi), np.pi))
    return float(np.mean(M.abs_angle_errors_deg(E["drift"][ok], truth)))


def metrics_from_logs(log_dir: str | Path, truth_csv: str | Path, outages_s: list[tuple[float, float]],
                      ref_lat_lon_deg: tuple[float, float] | None = None) -> dict[str, Any]:
    """:func:`sim.run.compute_metrics` of a log folder against a truth log, plus ``drift_mae_settled_deg``;
    ``outages_s`` the GNSS outages ``(start_s, end_s)`` on the truth's clock.  The NEES is on the diagonal
    covariance (module docstring)."""
    series = series_from_logs(log_dir, truth_csv, ref_lat_lon_deg)
    out = compute_metrics(series, outages_s)
    out["drift_mae_settled_deg"] = drift_mae_settled_deg(series)
    return out


__all__ = ["CLOCK_KIND", "drift_mae_settled_deg", "metrics_from_logs", "origin_ne_m", "series_from_logs",
           "vehicle_time_us"]
