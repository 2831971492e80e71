"""A level, still aircraft for the optical estimator's frame-by-frame tests: the attitude and IMU samples (300 Hz,
level, heading 0.3 rad, zero rates, specific force -g) that precede each camera frame (30 Hz from 0.5 s)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from common.samples import AttitudeSample, ImuSample

IMU_RATE_HZ = 300
FRAME_RATE_HZ = 30.0
FIRST_FRAME_US = 500_000
HEADING_RAD = 0.3


def still_frames(n_frames: int) -> Iterator[tuple[int, int, list[tuple[AttitudeSample, ImuSample]]]]:
    """``(k, t_us, samples)`` per frame ``k``: its exposure stamp and the samples to push before it (up to just
    past the exposure, so the attitude at the exposure is known)."""
    fed = 0
    for k in range(n_frames):
        t_us = FIRST_FRAME_US + int(round(k * 1e6 / FRAME_RATE_HZ))
        upto = t_us * IMU_RATE_HZ // 1_000_000 + 2
        samples = []
        for j in range(fed, upto):
            tj = int(round(j * 1e6 / IMU_RATE_HZ))
            samples.append((AttitudeSample(tj, 0.0, 0.0, HEADING_RAD),
                            ImuSample(tj, np.zeros(3), np.array([0.0, 0.0, -9.81]))))
        fed = upto
        yield k, t_us, samples
