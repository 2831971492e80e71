"""A small kinematic truth generator and EKF runner for the fusion tests (independent of ``sim``).

The aircraft flies a 2-D coordinated-turn trajectory (piecewise constant turn rate, constant horizontal airspeed)
with a gentle sinusoidal climb/descent, in a wind that is constant or drifts linearly.  Positions are integrated
exactly per grid interval; the IMU delivers the mean of the exact specific force and body rates, in the true body
frame, over the interval each sample ends (as the SIL vehicle's averaging does).  Sensors add seeded errors (IMU
noise and bias, AHRS noise and bias, pitot noise and scale error, baro noise/bias/drift, GNSS noise); the optical
steps are synthesised from the true positions in the frame of the *true* base heading (the camera is body-fixed and
the optical estimator de-rotates it with the same AHRS attitude it labels the cycle with, so an AHRS heading error
cancels in the image and only shows as ``base_yaw_rad - true heading``), at the base snapshot's true ground sample
distance, plus matcher noise and a relative-attitude pixel error, in cycles that restart every ``cycle_frames``
frames (the last frame of a cycle is the next cycle's base, as in :mod:`gsoe.cycle`).  What the filter assumes is
:class:`fusion.config.EkfConfig`; the values here are the "true" errors (STYLE section 8).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.constants import g as G
from scipy.spatial.transform import Rotation

from common.angles import angle_diff
from common.samples import AttitudeSample, GsoeStep, ImuSample, MatchQuality
from fusion.config import EkfConfig
from fusion.consistency import nees
from fusion.ekf import NavEkf
from fusion.measurements import OpticalDisplacement

Arr = NDArray[np.float64]


@dataclass(frozen=True)
class TruthConfig:
    duration_s: float = 120.0
    grid_hz: int = 600
    imu_div: int = 6        # 100 Hz
    ahrs_div: int = 12      # 50 Hz
    tas_div: int = 12       # 50 Hz
    baro_div: int = 24      # 25 Hz
    gnss_div: int = 120     # 5 Hz
    cam_div: int = 20       # 30 Hz
    airspeed_h_m_s: float = 20.0
    height_m: float = 100.0
    height_amp_m: float = 8.0
    height_period_s: float = 50.0
    alpha_rad: float = 0.03
    yaw0_deg: float = 10.0
    # (duration_s, turn_rate_deg_s), repeated to fill the flight
    segments: tuple[tuple[float, float], ...] = ((15.0, 0.0), (12.0, 15.0), (15.0, 0.0), (12.0, -15.0))
    wind_ne_m_s: tuple[float, float] = (-3.5, -3.5)        # 4.95 m/s from 45 deg
    wind_rate_ne_m_s2: tuple[float, float] = (0.0, 0.0)
    terrain_h_m: float = 0.0
    cycle_frames: int = 10
    focal_px: float = 351.86
    # true sensor errors
    accel_noise_m_s2: float = 0.05
    accel_bias_std_m_s2: float = 0.03
    ahrs_noise_deg: float = 0.1
    ahrs_rp_bias_std_deg: float = 0.2
    ahrs_yaw_bias_deg: float = 1.0
    tas_noise_m_s: float = 0.3
    tas_scale_err: float = 0.01
    baro_noise_m: float = 0.5
    baro_bias_m: float = 1.0
    baro_drift_m_s: float = 0.002
    gnss_pos_noise_m: float = 1.0
    gnss_alt_noise_m: float = 2.0
    gnss_vel_noise_m_s: float = 0.1
    match_noise_px: float = 0.3
    optical_rot_deg: float = 0.0    # the optical frame's own heading error (the optical estimator's gyro bias)
    att_rel_noise_deg: float = 0.03
    psr: float = 15.0
    # the AHRS heading reports the heading of ``t - ahrs_yaw_latency_s`` (roll and pitch on time: this truth's roll
    # steps at turn entries are not the integral of its gyro, so only the heading, which is, is delayed)
    ahrs_yaw_latency_s: float = 0.0
    seed: int = 0


@dataclass
class Flight:
    cfg: TruthConfig
    t_us: NDArray[np.int64]
    pos: Arr          # (N, 3) NED
    vel: Arr          # (N, 3)
    wind: Arr         # (N, 2)
    yaw: Arr
    events: list[tuple[int, int, str, Any]] = field(default_factory=list)   # (t_us, order, kind, payload)

    def index(self, t_us: int) -> int:
        return int(round(t_us * self.cfg.grid_hz / 1e6))


def make_flight(cfg: TruthConfig) -> Flight:
    rng = np.random.default_rng(cfg.seed)
    n = int(round(cfg.duration_s * cfg.grid_hz)) + 1
    dt = 1.0 / cfg.grid_hz
    t = np.arange(n) * dt
    t_us = np.round(t * 1e6).astype(np.int64)
    # turn rate, piecewise constant per grid interval
    rate = np.zeros(n)
    edges, k = [], 0.0
    while k < cfg.duration_s:
        for d, r in cfg.segments:
            edges.append((k, k + d, math.radians(r)))
            k += d
    for a, b, r in edges:
        rate[(t >= a - 1e-9) & (t < b - 1e-9)] = r
    psi = math.radians(cfg.yaw0_deg) + np.concatenate([[0.0], np.cumsum(rate[:-1] * dt)])
    V = cfg.airspeed_h_m_s
    # exact horizontal air displacement per interval (psi linear within an interval)
    r0 = rate[:-1]
    p0, p1 = psi[:-1], psi[1:]
    straight = np.abs(r0) < 1e-12
    safe = np.where(straight, 1.0, r0)
    dN = np.where(straight, V * np.cos(p0) * dt, V * (np.sin(p1) - np.sin(p0)) / safe)
    dE = np.where(straight, V * np.sin(p0) * dt, -V * (np.cos(p1) - np.cos(p0)) / safe)
    w0 = np.asarray(cfg.wind_ne_m_s, float)
    wr = np.asarray(cfg.wind_rate_ne_m_s2, float)
    wind = w0[None, :] + wr[None, :] * t[:, None]
    wdisp = w0[None, :] * dt + wr[None, :] * (t[1:, None] ** 2 - t[:-1, None] ** 2) / 2.0
    pos = np.zeros((n, 3))
    pos[1:, 0] = np.cumsum(dN + wdisp[:, 0])
    pos[1:, 1] = np.cumsum(dE + wdisp[:, 1])
    om = 2 * math.pi / cfg.height_period_s
    h = cfg.height_m + cfg.height_amp_m * np.sin(om * t)
    pos[:, 2] = -h
    vd = -cfg.height_amp_m * om * np.cos(om * t)
    ad = cfg.height_amp_m * om**2 * np.sin(om * t)
    vel = np.column_stack([V * np.cos(psi) + wind[:, 0], V * np.sin(psi) + wind[:, 1], vd])
    acc = np.column_stack([-V * np.sin(psi) * rate + wr[0], V * np.cos(psi) * rate + wr[1], ad])
    roll = np.arctan(V * rate / G)
    pitch = np.arctan2(-vd, V) + cfg.alpha_rad
    rot = Rotation.from_euler("ZYX", np.column_stack([psi, pitch, roll]))
    f_b = rot.inv().apply(acc - np.array([0.0, 0.0, G]))
    gyro_b = rot.inv().apply(np.column_stack([np.zeros(n), np.zeros(n), rate]))
    tas = np.sqrt(V**2 + vd**2)

    fl = Flight(cfg, t_us, pos, vel, wind, psi)
    ev = fl.events
    ba = rng.normal(0.0, cfg.accel_bias_std_m_s2, 3)
    rp_bias = np.radians(rng.normal(0.0, cfg.ahrs_rp_bias_std_deg, 2))
    yb = math.radians(cfg.ahrs_yaw_bias_deg)
    an = math.radians(cfg.ahrs_noise_deg)
    lag = int(round(cfg.ahrs_yaw_latency_s * cfg.grid_hz))
    # the attitude at t_k is the one the interval before it ended with (the bank steps with the turn rate at the
    # grid's instants; an IMU sample stamped t_k is that interval's mean)
    roll_ahrs = np.concatenate([roll[:1], roll[:-1]])
    for k in range(0, n, cfg.ahrs_div):
        e = rng.normal(0.0, an, 3)
        ev.append((int(t_us[k]), 0, "att", AttitudeSample(int(t_us[k]), float(roll_ahrs[k] + rp_bias[0] + e[0]),
                                                           float(pitch[k] + rp_bias[1] + e[1]),
                                                           float(psi[max(k - lag, 0)] + yb + e[2]))))
    for k in range(cfg.imu_div, n, cfg.imu_div):
        span = slice(k - cfg.imu_div, k)            # the grid intervals the sample ends (their rates: forward)
        ev.append((int(t_us[k]), 1, "imu", ImuSample(int(t_us[k]), gyro_b[span].mean(axis=0),
                                                     f_b[span].mean(axis=0) + ba
                                                     + rng.normal(0.0, cfg.accel_noise_m_s2, 3))))
    for k in range(cfg.tas_div, n, cfg.tas_div):
        ev.append((int(t_us[k]), 2, "tas", float(tas[k] * (1 + cfg.tas_scale_err) + rng.normal(0, cfg.tas_noise_m_s))))
    for k in range(cfg.baro_div, n, cfg.baro_div):
        b = cfg.baro_bias_m + cfg.baro_drift_m_s * t[k]
        ev.append((int(t_us[k]), 2, "baro", float(h[k] + b + rng.normal(0, cfg.baro_noise_m))))
    for k in range(cfg.gnss_div, n, cfg.gnss_div):
        pn = pos[k] + rng.normal(0, 1, 3) * [cfg.gnss_pos_noise_m, cfg.gnss_pos_noise_m, cfg.gnss_alt_noise_m]
        vn = vel[k] + rng.normal(0, cfg.gnss_vel_noise_m_s, 3)
        ev.append((int(t_us[k]), 2, "gnss", (pn, vn)))
    # optical cycles
    f = cfg.focal_px
    sm, sa = cfg.match_noise_px, f * math.radians(cfg.att_rel_noise_deg)
    frames = list(range(0, n, cfg.cam_div))
    L = cfg.cycle_frames
    base: dict[str, Any] = {}
    for j, k in enumerate(frames):
        if j % L == 0:
            if base:                      # last step of the previous cycle at this frame
                ev.append((int(t_us[k]), 2, "optical", _step(fl, base, k, rng, sm, sa, rot, j - base["j"])))
            yaw_rep = float(psi[k] + yb + rng.normal(0.0, an))
            base = {"k": k, "j": j, "cycle": j // L, "yaw": yaw_rep,
                    "yaw_true": float(psi[k]) + math.radians(cfg.optical_rot_deg),
                    "h": float(h[k] - cfg.terrain_h_m)}
            ev.append((int(t_us[k]), 2, "optical", _step(fl, base, k, rng, 0.0, 0.0, rot, 0)))
        else:
            ev.append((int(t_us[k]), 2, "optical", _step(fl, base, k, rng, sm, sa, rot, j - base["j"])))
    ev.sort(key=lambda e: (e[0], e[1]))
    return fl


def _step(fl: Flight, base: dict[str, Any], k: int, rng: np.random.Generator, sm: float, sa: float,
          rot: Rotation, n_step: int) -> GsoeStep:
    c, s = math.cos(base["yaw_true"]), math.sin(base["yaw_true"])
    d = fl.pos[k, :2] - fl.pos[base["k"], :2]
    gsd = base["h"] / fl.cfg.focal_px
    along, cross = c * d[0] + s * d[1], -s * d[0] + c * d[1]
    noise = rng.normal(0.0, 1.0, 2) * sm + rng.normal(0.0, 1.0, 2) * sa if n_step > 0 else np.zeros(2)
    rel = float((rot[base["k"]].inv() * rot[k]).magnitude())
    q = MatchQuality(psr=fl.cfg.psr if n_step > 0 else math.inf, texture_std=30.0, ssd_per_px=10.0, valid=True)
    return GsoeStep(t_us=int(fl.t_us[k]), base_t_us=int(fl.t_us[base["k"]]), cycle_id=int(base["cycle"]),
                    step=n_step, dx_px=float(cross / gsd + noise[0]), dy_px=float(along / gsd + noise[1]),
                    base_yaw_rad=base["yaw"], yaw_rad=float(fl.yaw[k]), gsd_m_px=gsd, height_agl_m=base["h"],
                    focal_px=fl.cfg.focal_px, rel_rot_rad=rel, quality=q, valid=True, new_cycle=n_step == 0)


def filter_config(truth: TruthConfig | None = None, **overrides: dict[str, Any]) -> EkfConfig:
    """The default EKF configuration with what differs in this truth from the simulator the defaults are sized
    for: the optical error model (white matcher noise ``match_noise_px`` and white relative-attitude error
    ``att_rel_noise_deg``, no gyro-bias drift), a smooth wind without turbulence (slow wind random walk), a
    small kinematic sideslip (no side-force aerodynamics: the IMU's lateral specific force carries no sideslip, so
    the zero-sideslip pseudo-measurement, ``airframe.side_force_coef_per_rad`` 0), no lift aerodynamics either (the
    normal specific force is the kinematic one at a constant angle of attack, so no lift-model angle of attack,
    ``aoa.enabled`` off), white GNSS errors and a 1 % pitot scale error to learn; no fusion delay (samples are fed
    in time order); plus ``overrides`` (per section: ``airspeed={"scale_update_fraction": 1.0}``)."""
    t = truth or TruthConfig()
    base = EkfConfig().replace(
        timing={"fusion_delay_s": 0.0},
        optical={"match_sigma_px": t.match_noise_px, "psr_ref": t.psr, "att_rel_sigma_deg": t.att_rel_noise_deg,
                 "att_rel_sigma_per_rad": 0.0, "att_rel_sigma_deg_per_s": 0.0},
        wind={"mean_rw_m_s_per_rt_s": 0.05, "turb_sigma_m_s": 0.05, "turb_sigma_min_m_s": 0.05,
              "turb_adapt_time_s": 0.0},
        sideslip={"sigma_deg": 5.0}, airframe={"side_force_coef_per_rad": 0.0}, aoa={"enabled": False},
        gnss={"pos_corr_time_s": 0.0}, init={"tas_scale_sigma": max(abs(t.tas_scale_err), 1e-3)},
        airspeed={"scale_update_fraction": 0.03})
    return base.replace(**overrides)


# --------------------------------------------------------------------------------------------------------------
@dataclass
class RunResult:
    t_s: Arr
    pos_err: Arr       # (M, 2)
    vel_err: Arr       # (M, 2)
    wind_err: Arr      # (M, 2)
    drift_err_rad: Arr
    nees_pvw: Arr
    nees_blocks: Arr   # (M, 3): 2-dof NEES of position, velocity, wind
    sigmas: Arr        # (M, 6): one-sigma of pos_ne, vel_ne, wind_ne
    valid: NDArray[np.bool_]
    dist_m: Arr        # distance flown since start
    statuses: list[dict[str, Any]]
    ekf: NavEkf
    step_status: dict[tuple[int, int], Any] = field(default_factory=dict)   # (cycle, step) -> optical AidStatus


def run_ekf(fl: Flight, cfg: EkfConfig | None = None, *, optical: bool = True, gnss_until_s: float | None = None,
            naive_velocity: bool = False, corrupt: Callable[[GsoeStep], GsoeStep] | None = None,
            record_div: int = 60, init_seed: int = 100, event_filter: Callable[[Sequence[Any]], bool] | None = None,
            ) -> RunResult:
    """Feed a flight's events into a fresh EKF in time order and record errors every ``record_div`` grid samples."""
    cfg = cfg or filter_config(fl.cfg)
    rng = np.random.default_rng(init_seed)
    p0 = fl.pos[0] + np.array([3.0, -3.0, 2.0]) * rng.normal(0.0, 1.0, 3)
    v0 = fl.vel[0] + rng.normal(0.0, 1.0, 3)
    ekf = NavEkf(cfg, t_us=0, pos_ned_m=p0, vel_ned_m_s=v0, terrain_h_m=0.0)
    att = None
    prev: GsoeStep | None = None
    rec_t, pe, ve, we, de, ne, nb, sg, va, dist, sts = [], [], [], [], [], [], [], [], [], [], []
    step_status: dict[tuple[int, int], Any] = {}
    pending: deque[tuple[tuple[int, int], int]] = deque()   # optical steps pushed, status not yet known
    seg = np.linalg.norm(np.diff(fl.pos[:, :2], axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    next_rec = 0
    for ev in fl.events:
        t, _, kind, payload = ev
        if event_filter is not None and not event_filter(ev):
            continue
        if kind == "att":
            att = payload
        elif kind == "imu":
            if att is not None:
                ekf.predict(payload, att)
        elif kind == "tas":
            ekf.fuse_airspeed(t, payload)
        elif kind == "baro":
            ekf.fuse_baro(t, payload)
        elif kind == "gnss":
            if gnss_until_s is None or t < gnss_until_s * 1e6:
                ekf.fuse_gnss(t, payload[0], payload[1])
        elif kind == "optical" and optical:
            step = corrupt(payload) if corrupt is not None else payload
            if naive_velocity:
                _fuse_naive(ekf, prev, step)
                prev = step
            else:
                ekf.fuse_optical(step)
                pending.append(((step.cycle_id, step.step), step.t_us))
        # a step's status is final once the filter has passed its stamp (steps are processed in time order);
        # two steps at one stamp (a cycle's last step and the next base) share a status row: keep neither
        while pending and ekf.t_us >= pending[0][1]:
            key, ts = pending.popleft()
            st = ekf.status()["optical"]
            if st.t_us == ts and not (pending and pending[0][1] == ts):
                step_status[key] = st
            elif pending and pending[0][1] == ts:
                pending.popleft()
        k = fl.index(t)
        if k >= next_rec and kind == "imu":
            next_rec = k + record_div
            est = ekf.estimate()
            kk = fl.index(est.t_us)
            e_p = est.pos_ne_m - fl.pos[kk, :2]
            e_v = est.vel_ned_m_s[:2] - fl.vel[kk, :2]
            e_w = est.wind_ne_m_s - fl.wind[kk]
            course = math.atan2(fl.vel[kk, 1], fl.vel[kk, 0])
            drift_true = float(angle_diff(course, fl.yaw[kk]))
            rec_t.append(est.t_us / 1e6)
            pe.append(e_p)
            ve.append(e_v)
            we.append(e_w)
            de.append(float(angle_diff(est.drift_rad, drift_true)))
            ne.append(nees(np.concatenate([e_p, e_v, e_w]), est.cov_pvw))
            C = est.cov_pvw
            nb.append([nees(e_p, C[0:2, 0:2]), nees(e_v, C[2:4, 2:4]), nees(e_w, C[4:6, 4:6])])
            sg.append(np.sqrt(np.diag(C)))
            va.append(est.valid)
            dist.append(cum[kk])
            sts.append(ekf.status())
    return RunResult(np.array(rec_t), np.array(pe), np.array(ve), np.array(we), np.array(de), np.array(ne),
                     np.array(nb), np.array(sg), np.array(va), np.array(dist), sts, ekf, step_status)


def naive_velocity_ne(prev: GsoeStep | None, step: GsoeStep, yaw_bias_rad: float) -> tuple[Arr, float] | None:
    """The naive per-frame velocity (m/s, N/E) from one-frame pixel differences and its time step (s), or None."""
    if prev is None or prev.cycle_id != step.cycle_id or step.step == 0:
        return None
    dt = (step.t_us - prev.t_us) / 1e6
    v_s = np.array([step.dx_px - prev.dx_px, step.dy_px - prev.dy_px]) * step.gsd_m_px / dt   # (cross, along)
    psi = step.base_yaw_rad - yaw_bias_rad
    c, s = math.cos(psi), math.sin(psi)
    return np.array([c * v_s[1] - s * v_s[0], s * v_s[1] + c * v_s[0]]), dt


def _fuse_naive(ekf: NavEkf, prev: GsoeStep | None, step: GsoeStep) -> None:
    from fusion.state import S

    r = naive_velocity_ne(prev, step, float(ekf.x[S.yaw_bias][0]))
    if r is None:
        return
    v, dt = r
    m, a = OpticalDisplacement.noise_sigma_px(step, ekf.cfg)
    sigma = math.sqrt(2.0 * (m * m + a * a)) * step.gsd_m_px / dt   # honest per-frame difference noise
    ekf.fuse_gnss(step.t_us, None, v, vel_sigma_ne_m_s=sigma)
