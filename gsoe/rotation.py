"""Rotations between the frames of :mod:`gsoe` (NED ``n``, FRD body ``b``, camera ``c``, stabilised ``s``).

Built on :class:`scipy.spatial.transform.Rotation`; only the frame bookkeeping is ours.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

# Nominal belly camera: x_c = y_b, y_c = -x_b, z_c = z_b (columns are the camera axes in body coordinates).
R_BC_NOMINAL: NDArray[np.float64] = np.array(
    [[0.0, -1.0, 0.0],
     [1.0, 0.0, 0.0],
     [0.0, 0.0, 1.0]]
)


def R_nb_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> NDArray[np.float64]:
    """Body-to-NED rotation from 3-2-1 Euler angles (yaw, pitch, roll): ``R_z(yaw) R_y(pitch) R_x(roll)``, written
    out (a per-frame hot path; ``scipy``'s ``Rotation.from_euler("ZYX", ...)`` is the reference in the tests)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def euler_from_R_nb(R_nb: NDArray[np.float64]) -> tuple[float, float, float]:
    """(roll_rad, pitch_rad, yaw_rad) of a body-to-NED rotation."""
    yaw, pitch, roll = Rotation.from_matrix(R_nb).as_euler("ZYX")
    return float(roll), float(pitch), float(yaw)


def R_z(yaw_rad: float) -> NDArray[np.float64]:
    """Rotation about the down axis by ``yaw_rad`` (the NED-from-heading-frame rotation)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def R_bc_from_mount(mount_roll_rad: float, mount_pitch_rad: float, mount_yaw_rad: float) -> NDArray[np.float64]:
    """Camera-to-body rotation: the nominal belly mounting followed by a small body-frame misalignment."""
    return R_nb_from_euler(mount_roll_rad, mount_pitch_rad, mount_yaw_rad) @ R_BC_NOMINAL
