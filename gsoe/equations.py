"""The paper's equations (2-3, 9-21) as pure, vectorised functions, in SI units and radians.

Conventions as in :mod:`gsoe`: headings, tracks and wind directions clockwise from north; wind direction is where
the wind blows *from*; the template migration ``dx_px`` is cross track (positive to the right of the base
heading), ``dy_px`` along track (positive forward).  Every function takes scalars or numpy arrays (broadcast) and
returns a float for scalar input, an array otherwise.  Undefined results (a direction of a zero vector, a ground
sample distance at a non-positive height) are nan, never a made-up number.

Which metric pixel size the project uses
    :func:`gsd_nadir_m_px` (``h / f``, the virtual nadir camera's ground sample distance; :mod:`gsoe.stabilise`
    resamples the fisheye frame into exactly that pinhole camera).  The paper's eq. 10-11
    (:func:`pixel_size_paper_m`) is kept as a reference: it assumes a pinhole mapping across the whole field
    *and*, as printed, divides the half-width ``h tan(FOV / 2)`` by the full image width, so for a true pinhole
    camera it gives half the ground size of a pixel; for the project's fisheye (fx = 351.86 px, HFOV 110 deg over
    800 px) it is 1.59x too small across and 1.78x along (VFOV 87.5 deg over 600 px).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.angles import angle_diff, wrap_2pi, wrap_pi

FloatOrArray = float | NDArray[np.float64]


def _out(a: NDArray[np.float64]) -> FloatOrArray:
    return float(a) if np.ndim(a) == 0 else a


def _f(x: ArrayLike) -> NDArray[np.float64]:
    return np.asarray(x, dtype=np.float64)


def _direction(north: NDArray[np.float64], east: NDArray[np.float64]) -> NDArray[np.float64]:
    """Direction clockwise from north of (north, east) in [0, 2 pi); nan for a zero vector."""
    with np.errstate(invalid="ignore"):
        d = np.asarray(wrap_2pi(np.arctan2(east, north)), dtype=np.float64)
    return np.where(np.hypot(north, east) > 0.0, d, np.nan)


# ---------------------------------------------------------------------------------------------------------------
# eq. 2-3: the paper's cropping point


def nadir_pixel_paper(roll_rad: ArrayLike, pitch_rad: ArrayLike, width_px: ArrayLike, height_px: ArrayLike,
                      hfov_rad: ArrayLike, vfov_rad: ArrayLike) -> tuple[FloatOrArray, FloatOrArray]:
    """Paper eq. 2-3: where the nadir ray meets the image, from roll and pitch only.

    ``x_stab = W/2 (tan(roll) / tan(HFOV/2) + 1)``, ``y_stab = H/2 (tan(pitch) / tan(VFOV/2) + 1)``.

    Image axes assumed: those of the camera frame ``c`` of :mod:`gsoe` (the nominal belly mounting): ``x_stab`` is
    the column, growing to the right wing (positive roll, right wing down, moves the nadir right), ``y_stab`` the
    row, growing towards the tail (positive pitch, nose up, moves the nadir towards the tail), both measured from
    the image's top-left corner with the principal point at (W/2, H/2).  Compared with a pinhole camera of focal
    lengths ``fx = (W/2) / tan(HFOV/2)``, ``fy = (H/2) / tan(VFOV/2)``, eq. 2 is exact for any pitch, but eq. 3
    misses a factor ``1 / cos(roll)``: the exact row is ``H/2 (tan(pitch) / (cos(roll) tan(VFOV/2)) + 1)``
    (:func:`nadir_pixel_pinhole`): eq. 3 falls short by ``(1 / cos(roll) - 1)`` of its own offset from the centre,
    41 % in a 45 deg bank.  A fisheye follows neither (its radius is not ``f tan``).
    """
    w, h = _f(width_px), _f(height_px)
    x = 0.5 * w * (np.tan(_f(roll_rad)) / np.tan(0.5 * _f(hfov_rad)) + 1.0)
    y = 0.5 * h * (np.tan(_f(pitch_rad)) / np.tan(0.5 * _f(vfov_rad)) + 1.0)
    return _out(x), _out(y)


def nadir_pixel_pinhole(roll_rad: ArrayLike, pitch_rad: ArrayLike, width_px: ArrayLike, height_px: ArrayLike,
                        hfov_rad: ArrayLike, vfov_rad: ArrayLike) -> tuple[FloatOrArray, FloatOrArray]:
    """The exact nadir pixel of the pinhole camera eq. 2-3 describe (same axes and arguments as
    :func:`nadir_pixel_paper`): the nadir ray in the body frame is ``(-sin(pitch), sin(roll) cos(pitch),
    cos(roll) cos(pitch))``, so ``x = W/2 + fx tan(roll)`` and ``y = H/2 + fy tan(pitch) / cos(roll)``."""
    w, h = _f(width_px), _f(height_px)
    roll, pitch = _f(roll_rad), _f(pitch_rad)
    x = 0.5 * w * (np.tan(roll) / np.tan(0.5 * _f(hfov_rad)) + 1.0)
    y = 0.5 * h * (np.tan(pitch) / (np.cos(roll) * np.tan(0.5 * _f(vfov_rad))) + 1.0)
    return _out(x), _out(y)


# ---------------------------------------------------------------------------------------------------------------
# eq. 9: drift


def drift_rad(dx_px: ArrayLike, dy_px: ArrayLike) -> FloatOrArray:
    """Paper eq. 9 with ``atan2``: drift = atan2(dx, dy) in [-pi, pi).

    ``dx_px`` cross track (right positive), ``dy_px`` along track (forward positive), see :mod:`gsoe`.  Positive
    when the ground track lies clockwise of the heading.  Nan when the template has not moved (dx = dy = 0).
    """
    dx, dy = _f(dx_px), _f(dy_px)
    d = np.asarray(wrap_pi(np.arctan2(dx, dy)), dtype=np.float64)
    return _out(np.where(np.hypot(dx, dy) > 0.0, d, np.nan))


def displacement_px(drift_rad: ArrayLike, travel_px: ArrayLike) -> tuple[FloatOrArray, FloatOrArray]:
    """Inverse of eq. 9: the (dx_px, dy_px) of a migration of length ``travel_px`` at drift ``drift_rad``."""
    d, t = _f(drift_rad), _f(travel_px)
    return _out(t * np.sin(d)), _out(t * np.cos(d))


# ---------------------------------------------------------------------------------------------------------------
# eq. 10-11: metric pixel size


def pixel_size_paper_m(height_m: ArrayLike, fov_rad: ArrayLike, template_px: ArrayLike,
                       image_px: ArrayLike) -> FloatOrArray:
    """Paper eq. 10-11 as printed: ``h tan(FOV/2) template_px / image_px`` (m).

    With (HFOV, image width) it is eq. 10, with (VFOV, image height) eq. 11; ``template_px`` is the span of pixels
    (the paper uses the template size).  A reference only: see the module docstring for why the project uses
    :func:`gsd_nadir_m_px` instead.
    """
    h, n = _f(height_m), _f(image_px)
    with np.errstate(divide="ignore", invalid="ignore"):
        v = h * np.tan(0.5 * _f(fov_rad)) * _f(template_px) / n
    return _out(np.where(n > 0.0, v, np.nan))


def gsd_nadir_m_px(height_agl_m: ArrayLike, focal_px: ArrayLike) -> FloatOrArray:
    """Ground sample distance of a level pinhole camera looking straight down (the virtual nadir camera):
    ``h / f`` metres per pixel at the image centre over flat ground.  Nan for a non-positive height or focal
    length."""
    h, f = _f(height_agl_m), _f(focal_px)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = h / f
    return _out(np.where((h > 0.0) & (f > 0.0), g, np.nan))


# ---------------------------------------------------------------------------------------------------------------
# eq. 12-17: track angle and wind triangle


def ata_rad(beta_rad: ArrayLike, yaw_rad: ArrayLike, drift_rad: ArrayLike) -> FloatOrArray:
    """Paper eq. 12, the actual tracking angle: ``ATA = beta + psi + delta``, wrapped to [0, 2 pi).

    As printed, eq. 12 adds the sideslip ``beta`` to the heading ``psi``: the air-velocity direction.  It is the
    ground track when ``delta`` is the drift measured from that air-velocity direction.  The drift of the optical
    estimator (eq. 9 in the stabilised frame) is measured from the *heading* (the nose, ``base_yaw_rad``); then
    the ground track is ``psi + delta``: call with ``beta_rad = 0``.
    """
    return _out(np.asarray(wrap_2pi(_f(beta_rad) + _f(yaw_rad) + _f(drift_rad)), dtype=np.float64))


def air_velocity_ne_m_s(tas_m_s: ArrayLike, beta_rad: ArrayLike,
                        yaw_rad: ArrayLike) -> tuple[FloatOrArray, FloatOrArray]:
    """Paper eq. 14-15: the air-relative velocity (north, east) = TAS (cos, sin)(beta + psi) (level flight)."""
    tas, a = _f(tas_m_s), _f(beta_rad) + _f(yaw_rad)
    return _out(tas * np.cos(a)), _out(tas * np.sin(a))


def ground_velocity_ne_m_s(gs_m_s: ArrayLike, track_rad: ArrayLike) -> tuple[FloatOrArray, FloatOrArray]:
    """Paper eq. 16-17: the ground velocity (north, east) = GS (cos, sin)(ATA)."""
    gs, t = _f(gs_m_s), _f(track_rad)
    return _out(gs * np.cos(t)), _out(gs * np.sin(t))


def wind_triangle(tas_m_s: ArrayLike, beta_rad: ArrayLike, yaw_rad: ArrayLike, gs_m_s: ArrayLike,
                  ata_rad: ArrayLike) -> tuple[FloatOrArray, FloatOrArray]:
    """Paper eq. 13-17: wind from the air and ground velocity vectors.

    ``(A - C) + (B - D) i`` is the air vector minus the ground vector (north + i east), i.e. minus the wind
    velocity: it points to where the wind comes *from*.  Returns ``(wind_speed_m_s, wind_from_rad)``, the
    direction clockwise from north in [0, 2 pi), nan when there is no wind.
    """
    a, b = air_velocity_ne_m_s(tas_m_s, beta_rad, yaw_rad)
    c, d = ground_velocity_ne_m_s(gs_m_s, ata_rad)
    n, e = _f(a) - _f(c), _f(b) - _f(d)
    return _out(np.hypot(n, e)), _out(_direction(n, e))


def wind_ne_m_s(wind_speed_m_s: ArrayLike, wind_from_rad: ArrayLike) -> tuple[FloatOrArray, FloatOrArray]:
    """Inverse of the wind triangle's output: the velocity of the air (north, east), i.e. where it blows *to*
    (as ``wind_ned_m_s`` in :mod:`sim.truth`)."""
    s, f = _f(wind_speed_m_s), _f(wind_from_rad)
    return _out(-s * np.cos(f)), _out(-s * np.sin(f))


def speed_and_track(north_m_s: ArrayLike, east_m_s: ArrayLike) -> tuple[FloatOrArray, FloatOrArray]:
    """Speed and direction (clockwise from north, [0, 2 pi), nan at zero speed) of a (north, east) velocity."""
    n, e = _f(north_m_s), _f(east_m_s)
    return _out(np.hypot(n, e)), _out(_direction(n, e))


# ---------------------------------------------------------------------------------------------------------------
# eq. 18-21: GNSS drift


def gnss_drift_rad(pos_n_m: ArrayLike, pos_e_m: ArrayLike, yaw_rad: ArrayLike) -> NDArray[np.float64]:
    """Paper eq. 18-21: drift from consecutive positions and the heading, one value per step (N - 1 values).

    ``delta_x = cos(psi) dN + sin(psi) dE`` (along the heading), ``delta_y = -sin(psi) dN + cos(psi) dE`` (to its
    right), drift = ``atan2(delta_y, delta_x)`` in [-pi, pi) (the paper's atan, made four-quadrant), positive when
    the track lies clockwise of the heading (as :func:`drift_rad`).

    ``yaw_rad`` is a scalar, one heading per step (N - 1) or one per position (N); with one per position the
    heading of step n is the circular midpoint of psi(n - 1) and psi(n): the chord of a steady turn points along
    the mid-interval tangent, so the drift stays exact while turning.  A step without motion gives nan.
    """
    n, e = _f(pos_n_m), _f(pos_e_m)
    if n.ndim != 1 or n.shape != e.shape:
        raise ValueError(f"pos_n_m and pos_e_m must be 1-D of equal length, got {n.shape} and {e.shape}")
    if n.size < 2:
        return np.empty(0)
    dn, de = np.diff(n), np.diff(e)
    psi = _f(yaw_rad)
    if psi.ndim == 1 and psi.size == n.size:
        psi = psi[:-1] + 0.5 * np.asarray(angle_diff(psi[1:], psi[:-1]), dtype=np.float64)
    elif not (psi.ndim == 0 or (psi.ndim == 1 and psi.size == n.size - 1)):
        raise ValueError(f"yaw_rad must be a scalar or have {n.size} or {n.size - 1} values, got {psi.shape}")
    c, s = np.cos(psi), np.sin(psi)
    along = c * dn + s * de
    right = -s * dn + c * de
    return np.atleast_1d(np.asarray(drift_rad(right, along), dtype=np.float64))
