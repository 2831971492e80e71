"""Fly the optical estimator alone over rendered frames of a scripted flight (tests and ``gsoe bench``).

Ideal or noisy IMU/AHRS samples are generated from the :class:`sim.trajectory.ScriptedFlight` truth; frames are
rendered at the frame rate (only the region the estimator reads, unless ``full_frame``); every step is returned
with the truth it should be compared with.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from common.samples import AttitudeSample, GsoeStep, ImuSample
from gsoe.camera import CameraModel
from gsoe.config import GsoeConfig
from gsoe.cycle import GsoeEstimator
from sim.render import CameraRenderer
from sim.trajectory import ScriptedFlight
from sim.truth import TruthState

ROI_MARGIN_PX = 12


@dataclass
class OpticalRun:
    steps: list[GsoeStep] = field(default_factory=list)
    truth_at_step: list[TruthState] = field(default_factory=list)
    truth_at_base: list[TruthState] = field(default_factory=list)
    frames: int = 0
    featureless_bases: int = 0   # bases the estimator found featureless (no cycle started)


def fly_optical(flight: ScriptedFlight, cfg: GsoeConfig, camera: CameraModel, renderer: CameraRenderer, *,
                rate_hz: float = 30.0, imu_rate_hz: float = 300.0, att_noise_rad: float = 0.0,
                gyro_noise_rad_s: float = 0.0, rng: np.random.Generator | None = None, full_frame: bool = False,
                t_start_s: float = 0.0, t_end_s: float | None = None) -> OpticalRun:
    """Run :class:`GsoeEstimator` over the flight; ``rng`` is required when any noise is set."""
    if (att_noise_rad > 0 or gyro_noise_rad_s > 0) and rng is None:
        raise ValueError("noise needs rng, a numpy.random.Generator")
    est = GsoeEstimator(cfg, camera)
    out = OpticalRun()
    t_end = flight.duration_s if t_end_s is None else t_end_s
    dt_imu = 1.0 / imu_rate_hz
    t_imu = t_start_s
    t_frame = t_start_s + 0.05
    truth_by_t: dict[int, TruthState] = {}
    while t_frame <= t_end:
        while t_imu <= t_frame + 1e-9:
            tr = flight.truth(t_imu)
            t_us = int(round(t_imu * 1e6))
            gyro = tr.rates_b_rad_s + (rng.normal(0.0, gyro_noise_rad_s, 3)
                                       if rng is not None and gyro_noise_rad_s > 0 else 0.0)
            est.push_imu(ImuSample(t_us, gyro, tr.accel_b_m_s2))
            n = rng.normal(0.0, att_noise_rad, 3) if rng is not None and att_noise_rad > 0 else np.zeros(3)
            est.push_attitude(AttitudeSample(t_us, tr.roll_rad + n[0], tr.pitch_rad + n[1], tr.yaw_rad + n[2]))
            t_imu += dt_imu
        tr = flight.truth(t_frame)
        t_us = int(round(t_frame * 1e6))
        R = Rotation.from_euler("ZYX", [tr.yaw_rad, tr.pitch_rad, tr.roll_rad])
        roi = None if full_frame else est.raw_roi(R.as_matrix(), ROI_MARGIN_PX)
        image = renderer.render(tr.pos_ned_m, R.as_matrix(), roi=roi)
        truth_by_t[t_us] = tr
        for s in est.process_frame(t_us, image, tr.height_agl_m):
            out.steps.append(s)
            out.truth_at_step.append(tr)
            out.truth_at_base.append(truth_by_t[s.base_t_us])
        out.frames += 1
        t_frame += 1.0 / rate_hz
    out.featureless_bases = est.n_featureless_bases
    return out
