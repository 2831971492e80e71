"""Scalar unit quaternions for the per-sample hot path (attitude buffer, TM cycle).

:class:`scipy.spatial.transform.Rotation` is the project's rotation library and the reference these functions are
tested against (``tests/test_attitude_stabilise.py``); but one scalar ``Rotation`` operation costs 50-150 us of
array handling, and the attitude buffer does one per IMU sample (240-300 Hz) and several per frame, which alone
would take a Raspberry Pi's frame budget.  These few functions work on plain ``(w, x, y, z)`` float tuples
(Hamilton convention, ``q_ab`` rotates frame-``b`` vectors into frame ``a``), a few microseconds each.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Quat = tuple[float, float, float, float]
IDENTITY: Quat = (1.0, 0.0, 0.0, 0.0)
_SMALL_ANGLE_RAD = 1e-8


def mul(a: Quat, b: Quat) -> Quat:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def conj(q: Quat) -> Quat:
    """Inverse of a unit quaternion."""
    return (q[0], -q[1], -q[2], -q[3])


def from_rotvec(x: float, y: float, z: float) -> Quat:
    a = math.sqrt(x * x + y * y + z * z)
    if a < _SMALL_ANGLE_RAD:
        return (1.0, 0.5 * x, 0.5 * y, 0.5 * z)
    s = math.sin(0.5 * a) / a
    return (math.cos(0.5 * a), x * s, y * s, z * s)


def to_rotvec(q: Quat) -> tuple[float, float, float]:
    w, x, y, z = q if q[0] >= 0 else (-q[0], -q[1], -q[2], -q[3])
    n = math.sqrt(x * x + y * y + z * z)
    if n < _SMALL_ANGLE_RAD:
        return (2.0 * x, 2.0 * y, 2.0 * z)
    a = 2.0 * math.atan2(n, w)
    return (x * a / n, y * a / n, z * a / n)


def angle(q: Quat) -> float:
    """Rotation angle in [0, pi]."""
    n = math.sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return 2.0 * math.atan2(n, abs(q[0]))


def normalize(q: Quat) -> Quat:
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def slerp(a: Quat, b: Quat, t: float) -> Quat:
    """Shortest-path spherical interpolation from ``a`` (t = 0) to ``b`` (t = 1)."""
    d = mul(conj(a), b)
    rx, ry, rz = to_rotvec(d)
    return normalize(mul(a, from_rotvec(rx * t, ry * t, rz * t)))


def from_euler321(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Quat:
    """``q_nb`` from 3-2-1 Euler angles (yaw about z, pitch about y, roll about x)."""
    cr, sr = math.cos(0.5 * roll_rad), math.sin(0.5 * roll_rad)
    cp, sp = math.cos(0.5 * pitch_rad), math.sin(0.5 * pitch_rad)
    cy, sy = math.cos(0.5 * yaw_rad), math.sin(0.5 * yaw_rad)
    return (cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy)


def to_euler321(q: Quat) -> tuple[float, float, float]:
    """(roll_rad, pitch_rad, yaw_rad) of ``q_nb``."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def yaw(q: Quat) -> float:
    """yaw_rad of ``q_nb`` (the third angle of :func:`to_euler321`, ``atan2(R[1, 0], R[0, 0])`` of its matrix)."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def to_matrix(q: Quat) -> NDArray[np.float64]:
    w, x, y, z = q
    # one flat tuple (one array from nine floats is about half the cost of one from nested rows)
    return np.array((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))).reshape(3, 3)


def from_matrix(R: NDArray[np.float64]) -> Quat:
    """Unit quaternion of a rotation matrix (Shepperd's method)."""
    m = np.asarray(R, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    return normalize((float(q[0]), float(q[1]), float(q[2]), float(q[3])))
