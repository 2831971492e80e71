"""What a flight log itself says about the replay's assumptions (``python -m nav.replay_checks LOG``).

The replay profile (``[ekf.profiles.telemetry_replay]``, docs/real-data.md) rests on measurements of the log, made
here from the log's samples alone (:mod:`nav.logreader`), independent of the EKF:

* GNSS velocity against GNSS position: the mean of ``d(pos)/dt - vel`` (m/s, N/E), the drift between the two that a
  filter trusting the velocity over the position integrates;
* the receiver lag the autopilot's own position shows: the shift of its ``GLOBAL_POSITION_INT`` track that brings
  it closest to the ``GPS_RAW_INT`` fixes (tlog only; ArduPilot fuses each fix at its stamp less the lag);
* the airspeed scale from the wind triangle ``v_gnss = tas / (1 + tas_scale) [cos(psi + d), sin(psi + d)] + wind``
  with a constant wind and heading offset ``d`` over windows of the flight (least squares, soft-L1 loss): whether the
  log pins one scale or the scale takes the wind's variation;
* the difference between two wind estimates split along and across the heading (a scale error shows along it, a
  heading or sideslip error across).
"""

from __future__ import annotations

import argparse
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from common.samples import AirspeedSample, AttitudeSample, GnssSample
from nav.logreader import FlightLog, local_ned_m, read_log

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
#: Airspeed below which a sample says nothing about the wind triangle (on the ground).
TRIANGLE_MIN_TAS_M_S = 8.0


@dataclass(frozen=True)
class TriangleFit:
    """A wind-triangle fit over ``t_s`` (from, to; s): ``tas_scale`` (measured / air-relative speed - 1) and its
    one-sigma, the constant wind (N/E, m/s), the heading offset ``d`` (rad) and the residual's RMS (m/s, per axis)."""

    t_s: tuple[float, float]
    tas_scale: float
    tas_scale_sigma: float
    wind_ne_m_s: tuple[float, float]
    heading_offset_rad: float
    residual_rms_m_s: float


def _fixes(gnss: Sequence[GnssSample]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    ok = [g for g in gnss if g.fix_ok and np.all(np.isfinite(g.vel_ned_m_s[:2]))]
    return (np.array([g.t_us for g in ok], dtype=float) / US_PER_S, np.array([g.pos_ned_m[:2] for g in ok]),
            np.array([g.vel_ned_m_s[:2] for g in ok]))


def yaw_at(att: Sequence[AttitudeSample], t_s: NDArray[np.float64]) -> NDArray[np.float64]:
    """The logged yaw (rad, unwrapped) interpolated to ``t_s``."""
    ta = np.array([a.t_us for a in att], dtype=float) / US_PER_S
    return np.interp(t_s, ta, np.unwrap([a.yaw_rad for a in att]))


def gnss_velocity_drift_m_s(gnss: Sequence[GnssSample]) -> NDArray[np.float64]:
    """Mean of ``d(pos)/dt - vel`` between consecutive fixes (N/E, m/s): how fast the GNSS position leaves the
    integral of the GNSS velocity."""
    t, p, v = _fixes(gnss)
    if t.size < 3:
        return np.full(2, math.nan)
    dpdt = np.diff(p, axis=0) / np.diff(t)[:, None]
    v_mid = 0.5 * (v[1:] + v[:-1])
    return np.asarray(np.mean(dpdt - v_mid, axis=0))


def wind_triangle_fit(air: Sequence[AirspeedSample], gnss: Sequence[GnssSample], att: Sequence[AttitudeSample],
                      t_s: tuple[float, float], gnss_delay_s: float = 0.0) -> TriangleFit | None:
    """Fit the scale, a constant wind and a heading offset to the airspeed samples in ``t_s`` (module docstring);
    GNSS velocity interpolated to each sample after moving the fixes ``gnss_delay_s`` back.  ``None`` with fewer
    than 10 samples."""
    tg, _, vg = _fixes(gnss)
    tg = tg - gnss_delay_s
    ta = np.array([a.t_us for a in air], dtype=float) / US_PER_S
    tas = np.array([a.tas_m_s for a in air])
    sel = (ta >= max(t_s[0], tg[0] if tg.size else math.inf)) & (ta <= min(t_s[1], tg[-1] if tg.size else -math.inf))
    sel &= tas >= TRIANGLE_MIN_TAS_M_S
    if sel.sum() < 10:
        return None
    ta, tas = ta[sel], tas[sel]
    v = np.column_stack([np.interp(ta, tg, vg[:, i]) for i in range(2)])
    psi = yaw_at(att, ta)

    def residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
        k, wn, we, d = p
        return np.concatenate([v[:, 0] - k * tas * np.cos(psi + d) - wn, v[:, 1] - k * tas * np.sin(psi + d) - we])

    fit = least_squares(residual, np.array([1.0, 0.0, 0.0, 0.0]), loss="soft_l1", f_scale=1.0)
    rms = float(np.sqrt(np.mean(fit.fun**2)))
    cov = np.linalg.pinv(fit.jac.T @ fit.jac) * rms**2
    k = float(fit.x[0])
    return TriangleFit(t_s=(float(ta[0]), float(ta[-1])), tas_scale=1.0 / k - 1.0,
                       tas_scale_sigma=math.sqrt(max(float(cov[0, 0]), 0.0)) / k**2,
                       wind_ne_m_s=(float(fit.x[1]), float(fit.x[2])), heading_offset_rad=float(fit.x[3]),
                       residual_rms_m_s=rms)


def along_cross_heading(d_ne: NDArray[np.float64], yaw_rad: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                                                          NDArray[np.float64]]:
    """Vectors (N/E, shape (K, 2)) split along the heading ``yaw_rad`` and across it (positive to the right)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return d_ne[:, 0] * c + d_ne[:, 1] * s, -d_ne[:, 0] * s + d_ne[:, 1] * c


def autopilot_position_lag_s(path: str, flight: FlightLog, lags_s: NDArray[np.float64]
                             ) -> tuple[float, float] | None:
    """The lag (s) in ``lags_s`` at which the autopilot's ``GLOBAL_POSITION_INT`` track, shifted that much earlier,
    is closest to the GNSS fixes, and that horizontal RMS distance (m); ``None`` for a log without them (DataFlash,
    ULog, no boot clock)."""
    rep = flight.report
    if (rep.log_format != "tlog" or rep.t0_boot_us is None or rep.origin_lat_deg is None
            or rep.origin_lon_deg is None or rep.origin_alt_m is None):
        return None
    origin = (rep.origin_lat_deg, rep.origin_lon_deg, rep.origin_alt_m)
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(path)
    rows = []
    while (m := conn.recv_match(type="GLOBAL_POSITION_INT", blocking=False)) is not None:
        rows.append((m.time_boot_ms * 1000 - rep.t0_boot_us, m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3))
    conn.close()
    if len(rows) < 10:
        return None
    a = np.array(rows, dtype=float)
    order = np.argsort(a[:, 0], kind="stable")
    a = a[order]
    t_ap = a[:, 0] / US_PER_S
    ned = local_ned_m(a[:, 1], a[:, 2], a[:, 3], origin)
    tg, pg, _ = _fixes(flight.of_type(GnssSample))
    inside = (tg > t_ap[0] + float(np.max(lags_s))) & (tg < t_ap[-1] + float(np.min(lags_s)))
    rms = [float(np.sqrt(np.mean((np.interp(tg[inside] - lag, t_ap, ned[:, 0]) - pg[inside, 0]) ** 2
                                 + (np.interp(tg[inside] - lag, t_ap, ned[:, 1]) - pg[inside, 1]) ** 2)))
           for lag in lags_s]
    best = int(np.argmin(rms))
    return float(lags_s[best]), rms[best]


def main(argv: Sequence[str] | None = None) -> int:
    """Print the log's checks (module docstring) and the replay's wind against the autopilot's, along and across
    the heading."""
    ap = argparse.ArgumentParser(prog="python -m nav.replay_checks", description=__doc__.split("\n")[0])
    ap.add_argument("log")
    ap.add_argument("--window-s", type=float, default=40.0, help="wind-triangle fit windows (s)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from nav.replay import ReplayConfig, run_replay

    flight = read_log(args.log, ReplayConfig().baro_temp_clamp_c)
    gnss, air, att = flight.of_type(GnssSample), flight.of_type(AirspeedSample), flight.of_type(AttitudeSample)
    delay_s = ReplayConfig().gnss_delay_s
    dn, de = gnss_velocity_drift_m_s(gnss)
    print(f"GNSS d(pos)/dt - vel: N {dn:+.3f} E {de:+.3f} m/s")
    lag = autopilot_position_lag_s(args.log, flight, np.round(np.arange(0.0, 0.5001, 0.01), 2))
    if lag is not None:
        print(f"autopilot position closest to the GNSS fixes at a lag of {lag[0]:.2f} s ({lag[1]:.2f} m RMS)")
    span = (flight.samples[0].t_us / US_PER_S, flight.samples[-1].t_us / US_PER_S)
    whole = wind_triangle_fit(air, gnss, att, span, delay_s)
    starts = np.arange(span[0], span[1] - 0.5 * args.window_s, 0.75 * args.window_s)
    windows = [wind_triangle_fit(air, gnss, att, (t0, t0 + args.window_s), delay_s)
               for t0 in starts] if starts.size > 1 else []
    for f in [whole, *windows]:
        if f is not None:
            print(f"wind triangle {f.t_s[0]:5.0f}-{f.t_s[1]:4.0f} s: tas_scale {100 * f.tas_scale:+5.1f} "
                  f"+- {100 * f.tas_scale_sigma:.1f} %, wind N {f.wind_ne_m_s[0]:+.2f} E {f.wind_ne_m_s[1]:+.2f} "
                  f"m/s, heading offset {math.degrees(f.heading_offset_rad):+.1f} deg, residual "
                  f"{f.residual_rms_m_s:.2f} m/s")
    res = run_replay(args.log, plots=False)
    E, W = res.series["ekf"], res.series["autopilot_wind"]
    sel = (W["t_s"] >= res.metrics["wind_compare_from_s"]) & (W["t_s"] <= E["t_s"][-1])
    t = W["t_s"][sel]
    if t.size:
        d = np.column_stack([np.interp(t, E["t_s"], E["wn"]) - W["wn"][sel],
                             np.interp(t, E["t_s"], E["we"]) - W["we"][sel]])
        along, cross = along_cross_heading(d, yaw_at(att, t))
        print(f"replay wind - autopilot's: RMS {math.sqrt(float(np.mean(along**2 + cross**2))):.3f} m/s; along "
              f"the heading mean {along.mean():+.2f} RMS {math.sqrt(float(np.mean(along**2))):.2f}, across mean "
              f"{cross.mean():+.2f} RMS {math.sqrt(float(np.mean(cross**2))):.2f} m/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
