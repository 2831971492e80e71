"""One simulated flight: JSBSim dynamics, wind, sensors, rendered camera, the optical estimator, the paper's
baseline chain and the EKF, all on the simulation clock, with every figure measured against the truth.

:func:`run_flight` is what ``gsoe sim`` and the Monte Carlo campaign call.  The loop, per dynamics step:

1. the autopilot flies the scenario's mission; JSBSim advances one step and returns the truth;
2. the sensor suite samples what is due (IMU, AHRS, pitot, baro, GNSS, camera exposure);
3. IMU/AHRS samples feed the optical estimator's attitude buffer and the EKF prediction; pitot, baro and GNSS
   are fused; a camera exposure is queued as an on-demand frame that renders, with motion blur, noise and gain,
   only the raw pixels the estimator samples (the whole frame up front with ``full_frame``);
4. a queued frame is processed once the attitude and gyro samples cover its timestamp; each optical step goes
   to the baseline (paper 2.4-2.7) and to the EKF.

Truth, sensor samples and estimates are kept in memory for the metrics and, with ``out_dir``, written as the CSV
streams of :mod:`common.logio` (the truth and estimator outputs once per camera frame, sensors at their own rates).
Ctrl-C stops the flight cleanly: the logs written so far stay readable and the metrics say ``interrupted``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from common import metrics as M
from common.angles import angle_diff
from common.logio import Decimator, RunLog
from common.samples import GsoeStep
from fusion.config import ekf_config_from_raw
from gsoe.camera import CameraModel
from gsoe.rotation import R_nb_from_euler
from pipeline.config import load_gsoe_config
from pipeline.navpipeline import FrameResult, NavPipeline, pipeline_config_from_raw
from sim.flight import build_flight, wind_params
from sim.render import CameraRenderer
from sim.report import gnss_drift_series
from sim.scenario import Scenario, gsoe_config_for
from sim.textures import GroundWorld
from sim.truth import TruthState

log = logging.getLogger(__name__)

# Wind and drift figures are taken after this much flight, once the first turns have made the wind observable.
SETTLE_S = 60.0
# Wind figures compare with the total wind the aircraft flies in, averaged over this window (the turbulence's
# long-wavelength part is real wind an estimator should follow; its fast part is not observable).
WIND_TRUTH_WINDOW_S = 5.0
# The dead-reckoning error is read this long before an outage ends (before a returning fix is fused).
OUTAGE_END_GUARD_S = 0.5
# NEES state: position N/E, velocity N/E, wind N/E.
NEES_DOF = 6
US_PER_S = 1_000_000
# gsoe sim --log reports (the default of the command line): the shortest time between two written records of each
# per-step stream (per aid source, and per fused/rejected, in aid_status.csv); the other streams are written whole.
REPORT_LOG_PERIODS_S = {"imu": 0.1, "attitude": 0.1, "airspeed": 0.1, "baro": 0.1, "truth": 0.1, "ekf": 0.2,
                        "aid_status": 0.2, "gsoe": 0.1}
REPORT_LOG_KEYS = {"aid_status": ("source", "rejected")}


@dataclass
class _Series:
    """In-memory record of a flight for the metrics and plots."""

    truth: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in (
        "t_s", "n", "e", "d", "vn", "ve", "vd", "roll", "pitch", "yaw", "tas", "beta", "wn", "we", "wsn", "wse",
        "h")})
    baseline: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in (
        "t_s", "drift", "heading", "released", "ws", "wd", "gs")})
    ekf: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in (
        "t_s", "drift", "drift_sigma", "wn", "we", "wn_sigma", "we_sigma", "ws", "wd", "n", "e", "n_sigma",
        "e_sigma", "valid", "heading", "vn", "ve")})
    #: per EKF record: the 6x6 covariance of [pos_ne, vel_ne, wind_ne] (the NEES is computed after the flight)
    ekf_cov_pvw: list[np.ndarray] = field(default_factory=list)
    gnss: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in ("t_s", "n", "e", "ok")})
    gsd: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in ("t_s", "gsd")})
    steps_valid: int = 0
    cycle_figure: dict[str, Any] | None = None

    def trim(self) -> None:
        """Cut every series to its shortest column (an interrupt can land between the appends of one record)."""
        for name in ("truth", "baseline", "ekf", "gnss", "gsd"):
            cols: dict[str, list[float]] = getattr(self, name)
            n = min(len(v) for v in cols.values())
            for v in cols.values():
                del v[n:]
        del self.ekf_cov_pvw[len(self.ekf["t_s"]):]

    def arrays(self, name: str) -> dict[str, np.ndarray]:
        return {k: np.asarray(v, dtype=float) for k, v in getattr(self, name).items()}


def _truth_record(tr: TruthState) -> dict[str, Any]:
    return {
        "t_us": tr.t_us, "pos_n_m": tr.pos_ned_m[0], "pos_e_m": tr.pos_ned_m[1], "pos_d_m": tr.pos_ned_m[2],
        "vel_n_m_s": tr.vel_ned_m_s[0], "vel_e_m_s": tr.vel_ned_m_s[1], "vel_d_m_s": tr.vel_ned_m_s[2],
        "roll_rad": tr.roll_rad, "pitch_rad": tr.pitch_rad, "yaw_rad": tr.yaw_rad, "tas_m_s": tr.tas_m_s,
        "alpha_rad": tr.alpha_rad, "beta_rad": tr.beta_rad,
        "wind_n_m_s": tr.wind_ned_m_s[0], "wind_e_m_s": tr.wind_ned_m_s[1], "wind_d_m_s": tr.wind_ned_m_s[2],
        "wind_steady_n_m_s": tr.wind_steady_ned_m_s[0], "wind_steady_e_m_s": tr.wind_steady_ned_m_s[1],
        "height_agl_m": tr.height_agl_m,
        "drift_rad": float(angle_diff(math.atan2(tr.vel_ned_m_s[1], tr.vel_ned_m_s[0]), tr.yaw_rad)),
    }


class _FrameSource:
    """A camera exposure rendered on demand, only the regions the estimator samples (:data:`gsoe.stabilise.Frame`).

    Each call renders the requested region with the exposure's motion blur, noise and gain; the render time is
    booked to the ``render`` timer (and taken out of the estimator's).  A region is written into ``frame_buf``, one
    frame-sized array shared by the flight's frames (the estimator reads the region it asked for at once; outside
    it the array holds older pixels, as :data:`gsoe.stabilise.Frame` allows); the whole frame (no region) is a
    new array."""

    def __init__(self, renderer: CameraRenderer, truth: TruthState, R_nb: np.ndarray, exposure_s: float,
                 noise_std: float, gain: float, rng: np.random.Generator, timers: _Timers,
                 frame_buf: np.ndarray) -> None:
        self._renderer = renderer
        self._buf = frame_buf
        self._pos = truth.pos_ned_m
        self._vel = truth.vel_ned_m_s
        self._rates = truth.rates_b_rad_s
        self._R_nb = R_nb
        self._exposure_s = exposure_s
        self._noise_std = noise_std
        self._gain = gain
        self._rng = rng
        self._timers = timers

    def __call__(self, roi: tuple[int, int, int, int] | None = None) -> np.ndarray:
        t0 = time.perf_counter()
        img = self._renderer.render(self._pos, self._R_nb, roi=roi, exposure_s=self._exposure_s,
                                    vel_ned_m_s=self._vel, rates_b_rad_s=self._rates, noise_std=self._noise_std,
                                    gain=self._gain, rng=self._rng, out=None if roi is None else self._buf)
        dt = time.perf_counter() - t0
        self._timers.s["render"] += dt
        self._timers.s["gsoe"] -= dt
        return img


class _Timers:
    def __init__(self) -> None:
        self.s: dict[str, float] = {k: 0.0 for k in ("dynamics", "sensors", "render", "gsoe", "ekf", "log")}

    def add(self, key: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.s[key] += t1 - t0
        return t1


def run_flight(scn: Scenario, *, seed: int, duration_s: float | None = None, out_dir: Path | None = None,
               progress: bool = False, config_path: str | Path | None = None, full_frame: bool = False,
               log_detail: str = "full") -> dict[str, Any]:
    """Fly ``scn`` with ``seed``; returns the metrics dict (also written to ``out_dir/metrics.json``).

    ``log_detail``: ``"full"`` logs every sample and step; ``"reports"`` thins the per-step streams to
    :data:`REPORT_LOG_PERIODS_S` (what the reports plot; a 2000 s flight in about 30 MB instead of 220 MB).  The
    metrics are computed in memory from every step either way."""
    if log_detail not in ("full", "reports"):
        raise ValueError(f"log_detail must be 'full' or 'reports', got {log_detail!r}")
    wall0 = time.perf_counter()
    base_cfg, raw = load_gsoe_config(config_path)
    gcfg = gsoe_config_for(scn, base_cfg)
    ekf_cfg = ekf_config_from_raw(raw.get("ekf", {}))
    pcfg = pipeline_config_from_raw(raw)
    # The physical camera is the configuration's camera file; the estimator uses the scenario's view of it
    # (``camera.gsoe_overrides.camera``), so a Monte Carlo run can give the estimator a calibration error.
    camera = CameraModel.from_config(gcfg.camera)
    true_camera = CameraModel.from_config(base_cfg.camera)
    duration = scn.duration_s if duration_s is None else float(duration_s)
    if not (duration > 0 and math.isfinite(duration)):
        raise ValueError(f"duration_s must be > 0, got {duration_s!r}")
    # dynamics, autopilot and sensors as the SIL vehicle builds them for a scenario (sim.flight: the seeding)
    flight = build_flight(scn, seed)
    dyn, ap, sensors, rng_cam = flight.dyn, flight.autopilot, flight.sensors, flight.rng_cam
    world = GroundWorld.from_name(scn.terrain.texture, seed=seed)
    renderer = CameraRenderer(true_camera, world)
    frame_buf = np.zeros((renderer.height_px, renderer.width_px), np.uint8)
    runlog = RunLog(out_dir) if out_dir is not None else None
    log_write: Any = None
    if runlog is not None:
        log_write = runlog.write if log_detail == "full" else Decimator(runlog.write, REPORT_LOG_PERIODS_S,
                                                                         REPORT_LOG_KEYS)
    series = _Series()
    timers = _Timers()
    # the simulated baro is a height above the reference point, which lies at ground level: ground level 0
    pipe = NavPipeline(gcfg, ekf_cfg, pcfg, camera, sink=log_write, timers=timers.s)
    in_outage: list[tuple[float, float]] = [(o.start_s, o.start_s + o.length_s) for o in scn.sensors.gnss.outages]
    n_steps = int(round(duration / scn.dt_s))
    truth = dyn.truth()
    interrupted = False
    crashed = ""
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=int(duration), unit="sim s", desc=f"gsoe sim {scn.name}", dynamic_ncols=True)
    last_bar_s = 0

    def _capture_cycle(s: GsoeStep) -> None:
        """Keep one TM cycle (base image and template path) after the settle time for the merged figure."""
        fig = series.cycle_figure
        if s.new_cycle:
            if fig is not None and fig.get("done"):
                return
            if fig is not None and len(fig["path"]) >= 8:
                fig["done"] = True
                return
            if s.t_us / US_PER_S > min(SETTLE_S, 0.25 * duration) and pipe.gsoe.cycle_base is not None:
                series.cycle_figure = {"base": pipe.gsoe.cycle_base.copy(), "ref_uv": pipe.gsoe.ref_uv, "path": [],
                                       "cycle_id": s.cycle_id, "t_s": s.t_us / US_PER_S}
        elif fig is not None and not fig.get("done") and s.cycle_id == fig["cycle_id"] and s.valid:
            fig["path"].append((s.dx_px, s.dy_px))

    # OpenCV's worker threads only spin (sched_yield) on the small images here: ~35 % more CPU for no speed, which
    # a Monte Carlo pool of one process per core pays twice.  One thread for the flight, restored afterwards.
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for _ in range(n_steps):
            t0 = time.perf_counter()
            cmd = ap.update(truth, scn.dt_s)
            truth = dyn.step(cmd)
            t0 = timers.add("dynamics", t0)
            r = sensors.step(truth)
            timers.add("sensors", t0)
            if r.imu is not None:
                pipe.on_imu(r.imu)
            if r.ahrs is not None:
                pipe.on_attitude(r.ahrs)
            if r.airspeed is not None:
                pipe.on_airspeed(r.airspeed)
            if r.baro is not None:
                pipe.on_baro(r.baro)
            if r.gnss is not None:
                g = r.gnss
                pipe.on_gnss(g)
                series.gnss["t_s"].append(g.t_us / US_PER_S)
                series.gnss["n"].append(float(g.pos_ned_m[0]))
                series.gnss["e"].append(float(g.pos_ned_m[1]))
                series.gnss["ok"].append(float(g.fix_ok))
            if r.frame is not None:
                t0 = time.perf_counter()
                R_nb = R_nb_from_euler(truth.roll_rad, truth.pitch_rad, truth.yaw_rad)
                source = _FrameSource(renderer, truth, R_nb, r.frame.exposure_s, scn.camera.noise_std,
                                      scn.camera.gain, rng_cam, timers, frame_buf)
                image = source() if full_frame else source
                t0 = timers.add("render", t0)
                _record_truth(series, truth, log_write)
                timers.add("log", t0)
                pipe.on_frame(r.frame.t_us, image)
            pipe.poll(truth.t_us)
            for res in pipe.drain():
                _record_result(series, res, _capture_cycle)
            if bar is not None and int(truth.t_s) > last_bar_s:
                bar.update(int(truth.t_s) - last_bar_s)
                last_bar_s = int(truth.t_s)
    except KeyboardInterrupt:
        interrupted = True
        log.warning("interrupted at t = %.1f s: the logs written so far are kept", truth.t_s)
    except Exception as e:  # a crashed flight still reports what it measured
        crashed = f"{type(e).__name__}: {e}"
        log.exception("flight stopped at t = %.1f s", truth.t_s)
    finally:
        cv2.setNumThreads(cv_threads)
        if bar is not None:
            bar.close()
        if runlog is not None:
            runlog.close()
    wall = time.perf_counter() - wall0
    series.trim()
    out = compute_metrics(series, in_outage)
    frames = pipe.status.frames
    out.update(
        scenario=scn.name, seed=seed, frames=frames, sim_s=truth.t_s, wall_s=wall,
        realtime_factor=truth.t_s / wall if wall > 0 else math.nan,
        time_split_s={k: round(v, 3) for k, v in timers.s.items()}, interrupted=interrupted, crashed=crashed,
        optical_valid_frac=pipe.status.steps_valid / max(1, frames),   # frames with a valid match
        gyro_bias_true_deg_s=np.degrees(sensors.imu.gyro_bias_b_rad_s).tolist(),
        gyro_bias_est_deg_s=np.degrees(pipe.gsoe.buffer.gyro_bias_b_rad_s).tolist(),
        sensor_errors=sensors.errors.to_dict(),
        pipeline={"ekf_started": pipe.status.ekf_started, "frames_late": pipe.status.frames_late,
                  "estimator_errors": pipe.status.estimator_errors,
                  "samples_rejected": dict(pipe.plausibility.status.rejected),    # pipeline.plausibility
                  "ekf_diverged": dict(pipe.status.ekf_diverged), "ekf_resets": dict(pipe.status.ekf_resets)},
    )
    if out_dir is not None:
        from sim.report import write_report

        write_report(out_dir, scn, series, out)
    return out


def _record_result(series: _Series, res: FrameResult, capture_cycle: Callable[[GsoeStep], None]) -> None:
    """Record what one processed frame gave: the baseline's cycles and the EKF's estimate after the frame."""
    for s in res.steps:
        capture_cycle(s)
    for b in res.baseline:
        B = series.baseline
        for key, v in (("t_s", b.t_us / US_PER_S), ("drift", b.drift_rad), ("heading", b.heading_rad),
                       ("released", float(b.released)), ("ws", b.wind_speed_m_s), ("wd", b.wind_from_rad),
                       ("gs", b.ground_speed_m_s)):
            B[key].append(v)
    e = res.estimate
    if e is None:
        return
    E = series.ekf
    for key, v in (("t_s", e.t_us / US_PER_S), ("drift", e.drift_rad), ("drift_sigma", e.drift_sigma_rad),
                   ("wn", e.wind_ne_m_s[0]), ("we", e.wind_ne_m_s[1]), ("wn_sigma", e.wind_ne_sigma_m_s[0]),
                   ("we_sigma", e.wind_ne_sigma_m_s[1]), ("ws", e.wind_speed_m_s), ("wd", e.wind_from_rad),
                   ("n", e.pos_ne_m[0]), ("e", e.pos_ne_m[1]), ("n_sigma", e.pos_ne_sigma_m[0]),
                   ("e_sigma", e.pos_ne_sigma_m[1]), ("valid", float(e.valid)), ("heading", e.heading_rad),
                   ("vn", e.vel_ned_m_s[0]), ("ve", e.vel_ned_m_s[1])):
        E[key].append(float(v))
    series.ekf_cov_pvw.append(e.cov_pvw)


def _record_truth(series: _Series, tr: TruthState, log_write: Any) -> None:
    """Record the truth at one camera frame."""
    T = series.truth
    for key, v in (("t_s", tr.t_s), ("n", tr.pos_ned_m[0]), ("e", tr.pos_ned_m[1]), ("d", tr.pos_ned_m[2]),
                   ("vn", tr.vel_ned_m_s[0]), ("ve", tr.vel_ned_m_s[1]), ("vd", tr.vel_ned_m_s[2]),
                   ("roll", tr.roll_rad), ("pitch", tr.pitch_rad), ("yaw", tr.yaw_rad), ("tas", tr.tas_m_s),
                   ("beta", tr.beta_rad), ("wn", tr.wind_ned_m_s[0]), ("we", tr.wind_ned_m_s[1]),
                   ("wsn", tr.wind_steady_ned_m_s[0]), ("wse", tr.wind_steady_ned_m_s[1]), ("h", tr.height_agl_m)):
        T[key].append(float(v))
    if log_write is not None and (not hasattr(log_write, "wants") or log_write.wants("truth", tr.t_us)):
        log_write("truth", _truth_record(tr))


def _nees(E: dict[str, np.ndarray], T: dict[str, np.ndarray], cov_pvw: list[np.ndarray]) -> np.ndarray:
    """NEES of every EKF record's [pos_ne, vel_ne, wind_ne] against the truth interpolated to the record's own time
    (NaN where the covariance is singular)."""
    n = E["t_s"].size
    if n == 0 or T["t_s"].size == 0:
        return np.full(n, math.nan)
    t = E["t_s"]
    err = np.stack([E[k] - np.interp(t, T["t_s"], T[k]) for k in ("n", "e", "vn", "ve", "wn", "we")], axis=1)
    P = np.asarray(cov_pvw[:n], dtype=float)
    out = np.full(n, math.nan)
    ok = np.isfinite(P).all(axis=(1, 2)) & np.isfinite(err).all(axis=1)
    ok[ok] = np.linalg.det(P[ok]) > 0.0
    if ok.any():
        out[ok] = np.einsum("ij,ij->i", err[ok], np.linalg.solve(P[ok], err[ok][..., None])[..., 0])
    return out


def compute_metrics(series: _Series, outages: list[tuple[float, float]]) -> dict[str, Any]:
    """All figures of ``metrics.json`` (EKF keys bare, the paper's chain with a ``baseline_`` prefix)."""
    T = series.arrays("truth")
    B = series.arrays("baseline")
    E = series.arrays("ekf")
    E["nees"] = _nees(E, T, series.ekf_cov_pvw)
    G = series.arrays("gnss")
    out: dict[str, Any] = {}
    if T["t_s"].size < 2:
        return out
    true_drift = M.true_drift_rad(T["vn"], T["ve"], T["yaw"])
    from scipy.ndimage import uniform_filter1d

    dt_frame = float(np.median(np.diff(T["t_s"])))
    win = max(1, int(round(WIND_TRUTH_WINDOW_S / dt_frame)))
    T["wmn"] = uniform_filter1d(T["wn"], win, mode="nearest")
    T["wme"] = uniform_filter1d(T["we"], win, mode="nearest")
    wind_truth_from = M.wind_from_rad(T["wmn"], T["wme"])
    wind_truth_speed = np.hypot(T["wmn"], T["wme"])
    steady_speed = np.hypot(T["wsn"], T["wse"])

    def truth_at(t_q: np.ndarray, key: str) -> np.ndarray:
        return np.interp(t_q, T["t_s"], T[key])

    def drift_truth_at(t_q: np.ndarray) -> np.ndarray:
        return np.asarray(angle_diff(M.interp_angle(t_q, T["t_s"], true_drift + np.pi), np.pi))

    # GNSS drift (paper eq. 18-21): consecutive fixes and the heading at the later one
    gnss_drift_t, gnss_drift = gnss_drift_series(G, T)

    def block(prefix: str, t_q: np.ndarray, drift: np.ndarray, valid: np.ndarray, heading: np.ndarray,
              ws: np.ndarray, wd: np.ndarray) -> None:
        ok = valid & np.isfinite(drift)
        err = M.abs_angle_errors_deg(drift[ok], drift_truth_at(t_q[ok]))
        s = M.summary(err, f"{prefix}drift")
        out[f"{prefix}drift_mae_deg"] = s[f"{prefix}drift_mae"]
        out[f"{prefix}drift_median_deg"] = s[f"{prefix}drift_median"]
        out[f"{prefix}drift_p95_deg"] = s[f"{prefix}drift_p95"]
        out[f"{prefix}drift_max_deg"] = s[f"{prefix}drift_max"]
        if gnss_drift_t.size and ok.any():
            idx = np.clip(np.searchsorted(gnss_drift_t, t_q[ok]), 0, gnss_drift_t.size - 1)
            near = np.abs(gnss_drift_t[idx] - t_q[ok]) < 0.5
            out[f"{prefix}drift_mae_vs_gnss_deg"] = float(np.mean(M.abs_angle_errors_deg(
                drift[ok][near], gnss_drift[idx][near]))) if near.any() else math.nan
        else:
            out[f"{prefix}drift_mae_vs_gnss_deg"] = math.nan
        out[f"{prefix}heading_coverage"] = M.heading_coverage(T["yaw"][T["t_s"] > 5.0], heading[ok])
        settled = ok & (t_q > SETTLE_S) & np.isfinite(ws)
        if settled.any():
            true_ws = np.interp(t_q[settled], T["t_s"], wind_truth_speed)
            true_wd = M.interp_angle(t_q[settled], T["t_s"], wind_truth_from)
            out[f"{prefix}wind_speed_rmse_m_s"] = M.rmse(ws[settled] - true_ws)
            out[f"{prefix}wind_speed_rmse_vs_steady_m_s"] = M.rmse(
                ws[settled] - np.interp(t_q[settled], T["t_s"], steady_speed))
            out[f"{prefix}wind_speed_mae_m_s"] = float(np.mean(np.abs(ws[settled] - true_ws)))
            # the same against the instantaneous total wind, and the floor of the windowed truth: what an estimate
            # equal to the instantaneous wind would score against it (the turbulence inside the window)
            inst_ws = np.interp(t_q[settled], T["t_s"], np.hypot(T["wn"], T["we"]))
            out[f"{prefix}wind_speed_rmse_vs_inst_m_s"] = M.rmse(ws[settled] - inst_ws)
            out[f"{prefix}wind_speed_truth_floor_m_s"] = M.rmse(inst_ws - true_ws)
            strong = true_ws >= 1.0
            dir_err = np.degrees(np.asarray(angle_diff(wd[settled][strong], true_wd[strong])))
            out[f"{prefix}wind_dir_rmse_deg"] = M.rmse(dir_err) if strong.any() else math.nan
            out[f"{prefix}wind_dir_mae_deg"] = float(np.mean(np.abs(dir_err))) if strong.any() else math.nan
        else:
            out[f"{prefix}wind_speed_rmse_m_s"] = math.nan
            out[f"{prefix}wind_dir_rmse_deg"] = math.nan
        out[f"{prefix}n_estimates"] = int(ok.sum())

    if B["t_s"].size:
        block("baseline_", B["t_s"], B["drift"], B["released"] > 0.5, B["heading"], B["ws"], B["wd"])
    if E["t_s"].size:
        block("", E["t_s"], E["drift"], E["valid"] > 0.5, E["heading"], E["ws"], E["wd"])
        # wind per axis and its consistency with the reported sigma
        settled = E["t_s"] > SETTLE_S
        if settled.any():
            en = E["wn"][settled] - truth_at(E["t_s"][settled], "wmn")
            ee = E["we"][settled] - truth_at(E["t_s"][settled], "wme")
            out["wind_ne_rmse_m_s"] = [M.rmse(en), M.rmse(ee)]
            out["wind_within_3sigma_frac"] = float(np.mean(
                (np.abs(en) <= 3 * E["wn_sigma"][settled]) & (np.abs(ee) <= 3 * E["we_sigma"][settled])))
        lo, hi = M.nees_bounds(NEES_DOF)
        nees = E["nees"][np.isfinite(E["nees"])]
        out["nees_in_bounds_frac"] = float(np.mean((nees >= lo) & (nees <= hi))) if nees.size else math.nan
        out["nees_mean"] = float(np.mean(nees)) if nees.size else math.nan
        out["nees_dof"] = NEES_DOF
        # NEES at 1 Hz (for run-averaged consistency plots) and the drift error per 10-deg heading bin
        fin = np.isfinite(E["nees"])
        if fin.any():
            grid = np.arange(math.ceil(E["t_s"][fin][0]), math.floor(E["t_s"][fin][-1]) + 1.0)
            out["nees_t_s"] = grid.tolist()
            out["nees_series"] = np.interp(grid, E["t_s"][fin], E["nees"][fin]).round(4).tolist()
        ok = (E["valid"] > 0.5) & np.isfinite(E["drift"])
        if ok.any():
            err = np.degrees(np.asarray(angle_diff(E["drift"][ok], drift_truth_at(E["t_s"][ok]))))
            centres, med = M.median_per_heading_deg(E["heading"][ok], np.radians(np.abs(err)), bin_deg=10.0)
            out["drift_err_by_heading_deg"] = {"heading_deg": centres.tolist(),
                                               "abs_err_median_deg": [None if not np.isfinite(v) else round(v, 4)
                                                                      for v in med]}
        out.update(_outage_metrics(E, T, outages))
    return out


def _outage_metrics(E: dict[str, np.ndarray], T: dict[str, np.ndarray], outages: list[tuple[float, float]]
                    ) -> dict[str, Any]:
    out: dict[str, Any] = {}
    errs: list[np.ndarray] = []
    pct: list[float] = []
    for t0, t1 in outages:
        # up to just before the first returning fix is fused (the figure is the dead-reckoning error)
        sel = (E["t_s"] >= t0) & (E["t_s"] < t1 - OUTAGE_END_GUARD_S)
        if sel.sum() < 2:
            continue
        tn = truth_n = np.interp(E["t_s"][sel], T["t_s"], T["n"])
        te = np.interp(E["t_s"][sel], T["t_s"], T["e"])
        err = np.hypot(E["n"][sel] - tn, E["e"][sel] - te)
        errs.append(err)
        dist = M.path_length_m(truth_n, te)
        if dist > 0:
            pct.append(100.0 * float(err[-1]) / dist)
    if errs:
        allerr = np.concatenate(errs)
        out.update(pos_error_m_mean=float(np.mean(allerr)), pos_error_m_max=float(np.max(allerr)),
                   pos_error_m_final=float(errs[-1][-1]))
        out["dr_error_pct_of_distance"] = float(np.max(pct)) if pct else math.nan
    else:
        out.update(pos_error_m_mean=math.nan, pos_error_m_max=math.nan, pos_error_m_final=math.nan,
                   dr_error_pct_of_distance=math.nan)
    return out


__all__ = ["run_flight", "compute_metrics", "wind_params"]
