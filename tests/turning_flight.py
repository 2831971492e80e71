"""A turning flight for camera tests: the poses at irregular frame times, and the narrow oblique camera they look
through (tests/test_camera_models.py and tests/test_real_frames.py render the frames)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from gsoe.config import CameraConfig

# A narrow oblique pinhole camera like CLIF's (image x forward, 9 deg to the right of the belly), scaled down.
OBLIQUE = CameraConfig(model="pinhole", width_px=320, height_px=480, fx_px=1700.0, fy_px=1700.0, cx_px=160.0,
                       cy_px=240.0, dist=(0.0, 0.0, 0.0, 0.0, 0.0), hfov_deg=10.8, vfov_deg=16.1,
                       mount_rpy_deg=(0.0, -9.0, -92.0))
TURN_RATE_RAD_S = math.radians(2.0)  # to the left (yaw decreasing)
STEPS_PER_FRAME = 100  # integration steps of the position between two frames


class Pose(NamedTuple):
    """The aircraft at one frame: time, NED position (a copy), attitude."""

    k: int
    t_s: float
    pos_ned_m: NDArray[np.float64]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


def turning_flight(rng: np.random.Generator, n_frames: int, height_m: float, speed_m_s: float,
                   roll_deg: float) -> Iterator[Pose]:
    """Frames 0.5-1.2 s apart (drawn from ``rng`` before each frame after the first, so a caller drawing from the
    same generator between frames keeps its sequence) from an aircraft at ``height_m`` over flat ground, flying
    ``speed_m_s`` along its yaw (from 0.3 rad) while it turns at :data:`TURN_RATE_RAD_S`, banked ``roll_deg``,
    with a pitch of 5 deg that wobbles by 0.01 rad."""
    pos, yaw, roll, t_s = np.array([0.0, 0.0, -height_m]), 0.3, math.radians(roll_deg), 0.0
    for k in range(n_frames):
        if k:
            dt = rng.uniform(0.5, 1.2)
            for _ in range(STEPS_PER_FRAME):
                pos += np.array([math.cos(yaw), math.sin(yaw), 0.0]) * speed_m_s * dt / STEPS_PER_FRAME
                yaw -= TURN_RATE_RAD_S * dt / STEPS_PER_FRAME
            t_s += dt
        yield Pose(k, t_s, pos.copy(), roll, math.radians(5.0) + 0.01 * math.sin(k), yaw)
