"""EKF step cost, for ``gsoe bench``: predict + all updates of one camera frame, on synthetic steady flight.

:func:`bench_ekf_step` returns figures (microseconds); printing them is the command line's job.
"""

from __future__ import annotations

import dataclasses
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
    accumulate into a covariance prediction at the measurements' stamp, or earlier every ``cfg.predict_period_s``)
    + one optical step + one airspeed sample (with the synthetic sideslip) + one baro sample; GNSS is off (the
    outage case the estimator is for).

    Returns a dict: ``frame_us_median``, ``frame_us_mean``, ``frame_us_p95`` (the whole frame), the medians of its
    parts ``imu_us_per_frame`` (all IMU pushes and predictions of the frame), ``optical_us``, ``airspeed_us``
    (airspeed + sideslip updates), ``baro_us``, and ``n_frames``, ``imu_per_frame``, ``covariance_predictions`` (per
    frame, counted).
    """
    if n < 1:
        raise ValueError(f"n: must be >= 1, got {n}")
    cfg = dataclasses.replace(cfg or EkfConfig(), fusion_delay_s=0.0)
    imu_per_frame = max(1, round(imu_rate_hz / camera_rate_hz))
    imu_dt_us = round(1e6 / imu_rate_hz)
    v = np.array([airspeed_m_s, 0.0, 0.0])
    ekf = NavEkf(cfg, t_us=0, pos_ned_m=[0.0, 0.0, -height_m], vel_ned_m_s=v)
    gyro = np.zeros(3)
    f_b = np.array([0.0, 0.0, -9.80665])
    q = MatchQuality(psr=15.0, texture_std=30.0, ssd_per_px=10.0, valid=True)
    gsd = height_m / focal_px
    n_warm = min(50, n)
    parts: dict[str, list[float]] = {"frame": [], "imu": [], "optical": [], "airspeed": [], "baro": []}
    cycle, base_t, base_x = 0, 0, 0.0
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
        t_imu0 = time.perf_counter_ns()
        for sample, att in imu:
            ekf.predict(sample, att)
        t_imu1 = time.perf_counter_ns()
        x_n = airspeed_m_s * t / 1e6
        k = i % cycle_frames
        if k == 0:
            cycle, base_t, base_x = i // cycle_frames, t, x_n
        step = GsoeStep(t_us=t, base_t_us=base_t, cycle_id=cycle, step=k, dx_px=0.0, dy_px=(x_n - base_x) / gsd,
                        base_yaw_rad=0.0, yaw_rad=0.0, gsd_m_px=gsd, height_agl_m=height_m, focal_px=focal_px,
                        rel_rot_rad=0.0, quality=q, valid=True, new_cycle=k == 0)
        t0 = time.perf_counter_ns()
        ekf.fuse_optical(step)
        t1 = time.perf_counter_ns()
        ekf.fuse_airspeed(t, airspeed_m_s)
        t2 = time.perf_counter_ns()
        ekf.fuse_baro(t, height_m)
        t3 = time.perf_counter_ns()
        if i >= n_warm:
            parts["frame"].append((t3 - t_imu0) / _NS_PER_US)
            parts["imu"].append((t_imu1 - t_imu0) / _NS_PER_US)
            parts["optical"].append((t1 - t0) / _NS_PER_US)
            parts["airspeed"].append((t2 - t1) / _NS_PER_US)
            parts["baro"].append((t3 - t2) / _NS_PER_US)
    frame = np.array(parts["frame"])
    st = ekf.status()
    if not (st["optical"].n_fused > 0 and st["airspeed"].n_fused > 0 and st["baro"].n_fused > 0):
        raise RuntimeError(f"benchmark flight did not fuse every aid: { {k: v.reason for k, v in st.items()} }")
    return {
        "n_frames": n,
        "imu_per_frame": imu_per_frame,
        "covariance_predictions": (ekf.covariance_predictions - n_pred0) / n,
        "frame_us_median": float(np.median(frame)),
        "frame_us_mean": float(np.mean(frame)),
        "frame_us_p95": float(np.percentile(frame, 95)),
        "imu_us_per_frame": float(np.median(parts["imu"])),
        "optical_us": float(np.median(parts["optical"])),
        "airspeed_us": float(np.median(parts["airspeed"])),
        "baro_us": float(np.median(parts["baro"])),
    }
