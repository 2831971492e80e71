"""EKF step cost, for ``gsoe bench``: predict + all updates of one camera frame, on synthetic steady flight.

:func:`bench_ekf_step` returns figures (microseconds); printing them is the command line's job.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from common.samples import AttitudeSample, GsoeStep, ImuSample, MatchQuality
from fusion.config import EkfConfig
from fusion.ekf import NavEkf

_NS_PER_US = 1_000.0


def bench_ekf_step(n: int = 2000, *, cfg: EkfConfig | None = None, imu_rate_hz: float = 240.0,
                   camera_rate_hz: float = 30.0, height_m: float = 100.0, airspeed_m_s: float = 20.0,
                   focal_px: float = 351.86, cycle_frames: int = 10) -> dict[str, Any]:
    """Time ``n`` camera frames of the EKF flying straight and level at ``airspeed_m_s`` (no wind).

    One frame = the IMU samples of one camera period (``imu_rate_hz / camera_rate_hz`` calls to ``predict``, which
    accumulate into a covariance prediction at the measurements' stamp, or earlier every
    ``cfg.timing.predict_period_s``)
    + one optical step + one airspeed sample (with the synthetic sideslip) + one baro sample; GNSS is off (the
    outage case the estimator is for).

    Returns a dict: ``frame_us_median``, ``frame_us_mean``, ``frame_us_p95`` (the whole frame), the medians of its
    parts ``imu_us_per_frame`` (all IMU pushes and predictions of the frame), ``optical_us``, ``airspeed_us``
    (airspeed + sideslip updates), ``baro_us``, and ``n_frames``, ``imu_per_frame``, ``covariance_predictions`` (per
    frame, counted).
    """
    if n < 1:
        raise ValueError(f"n: must be >= 1, got {n}")
    cfg = (cfg or EkfConfig()).replace(timing={"fusion_delay_s": 0.0})
    imu_per_frame = max(1, round(imu_rate_hz / camera_rate_hz))
    imu_dt_us = round(1e6 / imu_rate_hz)
    ekf = NavEkf(cfg, t_us=0, pos_ned_m=[0.0, 0.0, -height_m], vel_ned_m_s=[airspeed_m_s, 0.0, 0.0])
    gyro = np.zeros(3)
    f_b = np.array([0.0, 0.0, -9.80665])
    n_warm = min(50, n)
    parts: dict[str, list[float]] = {"frame": [], "imu": [], "optical": [], "airspeed": [], "baro": []}
    base = (0, 0, 0.0)                                    # the cycle: id, base time (µs), base north (m)
    n_pred0 = 0
    t = 0
    for i in range(n + n_warm):
        if i == n_warm:
            n_pred0 = ekf.covariance_predictions
        # the samples are built before the clock runs: the figures are the filter's cost, not the caller's
        imu = []
        for _ in range(imu_per_frame):
            t += imu_dt_us
            imu.append((ImuSample(t, gyro, f_b), AttitudeSample(t, 0.0, 0.0, 0.0)))
        k = i % cycle_frames
        if k == 0:
            base = (i // cycle_frames, t, airspeed_m_s * t / 1e6)
        step = _step(t, base, k, airspeed_m_s, height_m, focal_px)
        t_imu0 = time.perf_counter_ns()
        for sample, att in imu:
            ekf.predict(sample, att)
        t0 = time.perf_counter_ns()
        ekf.fuse_optical(step)
        t1 = time.perf_counter_ns()
        ekf.fuse_airspeed(t, airspeed_m_s)
        t2 = time.perf_counter_ns()
        ekf.fuse_baro(t, height_m)
        t3 = time.perf_counter_ns()
        if i >= n_warm:
            for key, a, b in (("frame", t_imu0, t3), ("imu", t_imu0, t0), ("optical", t0, t1),
                              ("airspeed", t1, t2), ("baro", t2, t3)):
                parts[key].append((b - a) / _NS_PER_US)
    return _figures(ekf, parts, n, imu_per_frame, (ekf.covariance_predictions - n_pred0) / n)


def _step(t: int, base: tuple[int, int, float], k: int, airspeed_m_s: float, height_m: float,
          focal_px: float) -> GsoeStep:
    """Step ``k`` of the cycle ``base`` (id, base time, base north) at ``t``: straight north at the airspeed."""
    q = MatchQuality(psr=15.0, texture_std=30.0, ssd_per_px=10.0, valid=True)
    gsd = height_m / focal_px
    cycle, base_t, base_x = base
    return GsoeStep(t_us=t, base_t_us=base_t, cycle_id=cycle, step=k, dx_px=0.0,
                    dy_px=(airspeed_m_s * t / 1e6 - base_x) / gsd, base_yaw_rad=0.0, yaw_rad=0.0, gsd_m_px=gsd,
                    height_agl_m=height_m, focal_px=focal_px, rel_rot_rad=0.0, quality=q, valid=True,
                    new_cycle=k == 0)


def _figures(ekf: NavEkf, parts: dict[str, list[float]], n: int, imu_per_frame: int,
             covariance_predictions: float) -> dict[str, Any]:
    frame = np.array(parts["frame"])
    st = ekf.status()
    if not (st["optical"].n_fused > 0 and st["airspeed"].n_fused > 0 and st["baro"].n_fused > 0):
        raise RuntimeError(f"benchmark flight did not fuse every aid: { {k: v.reason for k, v in st.items()} }")
    return {
        "n_frames": n,
        "imu_per_frame": imu_per_frame,
        "covariance_predictions": covariance_predictions,
        "frame_us_median": float(np.median(frame)),
        "frame_us_mean": float(np.mean(frame)),
        "frame_us_p95": float(np.percentile(frame, 95)),
        "imu_us_per_frame": float(np.median(parts["imu"])),
        "optical_us": float(np.median(parts["optical"])),
        "airspeed_us": float(np.median(parts["airspeed"])),
        "baro_us": float(np.median(parts["baro"])),
    }
