"""The paper's equations (2-3, 9-21) against hand-computed cases and independent models."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.angles import angle_diff
from gsoe.camera import CameraModel
from gsoe.config import CameraConfig
from gsoe.equations import (
    air_velocity_ne_m_s,
    ata_rad,
    displacement_px,
    drift_rad,
    gnss_drift_rad,
    gsd_nadir_m_px,
    nadir_pixel_paper,
    nadir_pixel_pinhole,
    pixel_size_paper_m,
    speed_and_track,
    wind_ne_m_s,
    wind_triangle,
)
from gsoe.rotation import R_nb_from_euler

D = math.radians
W_PX, H_PX, HFOV, VFOV = 800, 600, D(110.0), D(87.5)


# ---------------------------------------------------------------------------------------------------------------
# eq. 9


def test_drift_hand_cases():
    assert drift_rad(1.0, 1.0) == pytest.approx(D(45.0))  # as far right as forward
    assert drift_rad(-3.0, 4.0) == pytest.approx(D(-36.86989764584402))  # atan(-3/4)
    assert drift_rad(5.0, -5.0) == pytest.approx(D(135.0))  # backwards: atan would say -45
    assert drift_rad(-5.0, -5.0) == pytest.approx(D(-135.0))
    assert drift_rad(0.0, -2.0) == pytest.approx(-math.pi)  # straight back: the [-pi, pi) end
    assert math.isnan(drift_rad(0.0, 0.0))  # no motion, no direction
    out = drift_rad(np.array([1.0, 0.0, -1e-12]), np.array([0.0, 3.0, -1.0]))
    np.testing.assert_allclose(out, [D(90.0), 0.0, -math.pi], atol=1e-9)


def test_drift_inverse_round_trip():
    d = np.deg2rad([-179.0, -30.0, 0.0, 12.5, 179.0])
    dx, dy = displacement_px(d, 27.0)
    np.testing.assert_allclose(np.hypot(dx, dy), 27.0)
    np.testing.assert_allclose(angle_diff(drift_rad(dx, dy), d), 0.0, atol=1e-12)


# ---------------------------------------------------------------------------------------------------------------
# eq. 2-3


def test_nadir_pixel_paper_hand_cases():
    assert nadir_pixel_paper(0.0, 0.0, W_PX, H_PX, HFOV, VFOV) == pytest.approx((400.0, 300.0))
    # 400 (tan 10 / tan 55 + 1), 300 (tan 5 / tan 43.75 + 1)
    assert nadir_pixel_paper(D(10.0), D(5.0), W_PX, H_PX, HFOV, VFOV) == pytest.approx(
        (449.38619243273007, 327.41755506629136))
    assert nadir_pixel_paper(D(-20.0), D(-12.0), W_PX, H_PX, HFOV, VFOV) == pytest.approx(
        (298.0581193131404, 233.38815568302124))


def _pinhole_camera() -> CameraModel:
    fx = (W_PX / 2) / math.tan(HFOV / 2)
    fy = (H_PX / 2) / math.tan(VFOV / 2)
    cfg = CameraConfig(model="pinhole", width_px=W_PX, height_px=H_PX, fx_px=fx, fy_px=fy, cx_px=W_PX / 2,
                       cy_px=H_PX / 2, dist=(0.0, 0.0, 0.0, 0.0, 0.0), hfov_deg=110.0, vfov_deg=87.5)
    return CameraModel.from_config(cfg)


@pytest.mark.parametrize("roll_deg", [-45.0, -20.0, 0.0, 15.0, 45.0])
@pytest.mark.parametrize("pitch_deg", [-20.0, -5.0, 0.0, 10.0, 20.0])
def test_eq2_3_against_the_nadir_ray_through_a_pinhole_camera(roll_deg, pitch_deg):
    """Independent truth: the nadir ray (NED down) rotated into the body by the 3-2-1 attitude, into the camera
    by the belly mounting, projected by OpenCV through a pinhole camera with eq. 2-3's fields of view.

    Eq. 2 (column) is exact for any pitch.  Eq. 3 (row) is exact only wings level: the nadir ray's camera-frame
    slope along the image rows is tan(pitch) / cos(roll), so eq. 3 misses (H/2) tan(pitch) / tan(VFOV/2) *
    (1 / cos(roll) - 1), 41 % of its own offset in a 45 deg bank."""
    cam = _pinhole_camera()
    roll, pitch = D(roll_deg), D(pitch_deg)
    for yaw in (0.0, D(137.0)):  # the nadir pixel does not depend on heading
        down_b = R_nb_from_euler(roll, pitch, yaw).T @ np.array([0.0, 0.0, 1.0])
        px, valid = cam.project((cam.R_bc.T @ down_b)[None])
        assert valid[0]
        x_true, y_true = px[0]
        x_eq, y_eq = nadir_pixel_paper(roll, pitch, W_PX, H_PX, HFOV, VFOV)
        assert x_eq == pytest.approx(x_true, abs=1e-6)
        deviation = (H_PX / 2) * math.tan(pitch) / math.tan(VFOV / 2) * (1.0 / math.cos(roll) - 1.0)
        assert y_true - y_eq == pytest.approx(deviation, abs=1e-6)
        assert nadir_pixel_pinhole(roll, pitch, W_PX, H_PX, HFOV, VFOV) == pytest.approx((x_true, y_true), abs=1e-6)


# ---------------------------------------------------------------------------------------------------------------
# eq. 10-11 and the ground sample distance


def test_pixel_size_hand_cases():
    # 100 m, HFOV 110 deg, 19 px of 800: 100 tan(55 deg) 19 / 800
    assert pixel_size_paper_m(100.0, HFOV, 19, 800) == pytest.approx(3.391851516012521)
    # VFOV 87.5 deg, 19 px of 600
    assert pixel_size_paper_m(100.0, VFOV, 19, 600) == pytest.approx(3.0314238504735584)
    assert gsd_nadir_m_px(100.0, 351.86) == pytest.approx(0.2842039447507531)
    assert math.isnan(gsd_nadir_m_px(-1.0, 351.86)) and math.isnan(gsd_nadir_m_px(100.0, 0.0))
    np.testing.assert_allclose(gsd_nadir_m_px(np.array([50.0, 200.0]), 400.0), [0.125, 0.5])


def _ground_gsd_from_camera(cam: CameraModel, height_m: float) -> tuple[float, float]:
    """Metres per pixel at the image centre of a level camera looking down, from the camera model itself:
    unproject pixels +-1 px about the principal point and intersect the rays with the ground."""
    cx, cy = cam.config.cx_px, cam.config.cy_px
    rays = cam.unproject(np.array([[cx - 1, cy], [cx + 1, cy], [cx, cy - 1], [cx, cy + 1]]))
    ground = rays[:, :2] / rays[:, 2:3] * height_m  # level camera: z_c is down, the ground is at z = h
    return (float(np.linalg.norm(ground[1] - ground[0]) / 2), float(np.linalg.norm(ground[3] - ground[2]) / 2))


def test_paper_pixel_size_against_the_camera_model_gsd(camera):
    """Which metric pixel size the project uses, and why.

    The project uses ``gsd_nadir_m_px = h / f`` (f: the virtual nadir camera's focal length, by default the raw
    camera's fx = 351.86 px): the stabiliser resamples the fisheye frame into exactly that level pinhole camera,
    and this test checks h / f against the calibrated (cv2.fisheye) model's own ground footprint at the centre.
    The paper's eq. 10-11 is not used: it assumes a pinhole mapping across the whole field, which the fisheye
    violates, and as printed it divides the half-width h tan(FOV/2) by the *full* image width, so even for a
    true pinhole camera it is half the ground size of a pixel.  For the project's fisheye it comes out 1.59x too
    small across (HFOV 110 deg over 800 px) and 1.78x along (VFOV 87.5 deg over 600 px): a ground speed from it
    would be 37-44 % low.
    """
    h = 100.0
    gsd = gsd_nadir_m_px(h, camera.config.fx_px)
    gx, gy = _ground_gsd_from_camera(camera, h)
    assert gx == pytest.approx(gsd, rel=1e-3) and gy == pytest.approx(gsd, rel=1e-3)
    cfg = camera.config
    paper_x = pixel_size_paper_m(h, math.radians(cfg.hfov_deg), 1, cfg.width_px)
    paper_y = pixel_size_paper_m(h, math.radians(cfg.vfov_deg), 1, cfg.height_px)
    assert gsd / paper_x == pytest.approx(1.592, abs=2e-3)
    assert gsd / paper_y == pytest.approx(1.781, abs=2e-3)
    # the factor of two of the printed formula, for the pinhole camera it describes
    pin = _pinhole_camera()
    pgx, pgy = _ground_gsd_from_camera(pin, h)
    assert pgx / pixel_size_paper_m(h, HFOV, 1, W_PX) == pytest.approx(2.0, rel=1e-4)
    assert pgy / pixel_size_paper_m(h, VFOV, 1, H_PX) == pytest.approx(2.0, rel=1e-4)


# ---------------------------------------------------------------------------------------------------------------
# eq. 12-17


def test_ata_hand_cases_and_wrap():
    assert ata_rad(D(2.0), D(350.0), D(15.0)) == pytest.approx(D(7.0))  # 367 deg wraps to 7
    assert ata_rad(0.0, D(10.0), D(-20.0)) == pytest.approx(D(350.0))  # -10 deg wraps to 350
    assert ata_rad(0.0, D(-170.0), D(-15.0)) == pytest.approx(D(175.0))  # across +-180
    out = ata_rad(0.0, np.deg2rad([0.0, 359.0]), np.deg2rad([0.0, 1.0]))
    assert np.all((out >= 0.0) & (out < 2 * math.pi))
    np.testing.assert_allclose(angle_diff(out, 0.0), 0.0, atol=1e-12)


def test_wind_triangle_hand_cases():
    # heading north at 20 m/s, ground speed 15 m/s along the heading: 5 m/s head wind, from the north
    assert wind_triangle(20.0, 0.0, 0.0, 15.0, 0.0) == pytest.approx((5.0, 0.0))
    # heading east at 20 m/s, a 5 m/s wind from the north pushes the track south: GS sqrt(425), ATA 90 + atan(1/4)
    speed, wfrom = wind_triangle(20.0, 0.0, D(90.0), math.sqrt(425.0), D(90.0) + math.atan(0.25))
    assert speed == pytest.approx(5.0) and angle_diff(wfrom, 0.0) == pytest.approx(0.0, abs=1e-12)
    assert 0.0 <= wfrom < 2 * math.pi
    # TAS 22, beta 3, heading 200, GS 18, ATA 190 deg: A-C = -2.52457, B-D = -5.47042 (eq. 14-17 by hand)
    speed, wfrom = wind_triangle(22.0, D(3.0), D(200.0), 18.0, D(190.0))
    assert speed == pytest.approx(6.024857565959018) and wfrom == pytest.approx(D(245.2269396327385))
    # wind from 359 deg (across north): tail wind component on a northerly heading, slightly from the left
    air_n, air_e = air_velocity_ne_m_s(20.0, 0.0, 0.0)
    wn, we = wind_ne_m_s(4.0, D(359.0))
    gs, track = speed_and_track(air_n + wn, air_e + we)
    speed, wfrom = wind_triangle(20.0, 0.0, 0.0, gs, track)
    assert speed == pytest.approx(4.0) and wfrom == pytest.approx(D(359.0))
    # no wind: speed 0, direction undefined
    speed, wfrom = wind_triangle(20.0, 0.0, D(30.0), 20.0, D(30.0))
    assert speed == pytest.approx(0.0, abs=1e-12) and math.isnan(wfrom)


def test_wind_triangle_round_trip():
    """Ground velocity built from a known wind and air velocity; the wind recovered through the optical drift.

    The camera's drift is measured from the nose (heading), so the ground track is psi + delta: eq. 12 with
    beta = 0.  Eq. 12 as printed (beta + psi + delta) is right when delta is measured from the air-velocity
    direction psi + beta; mixing the two (beta added to a nose-relative drift) rotates the track by beta and
    gives a wrong wind, shown at the end."""
    rng = np.random.default_rng(11)
    n = 200
    tas = rng.uniform(15.0, 30.0, n)
    beta = np.deg2rad(rng.uniform(-4.0, 4.0, n))
    yaw = np.deg2rad(rng.uniform(-180.0, 360.0, n))  # beyond [0, 360) on purpose
    w_speed = rng.uniform(0.5, 12.0, n)
    w_from = np.deg2rad(rng.uniform(0.0, 360.0, n))
    an, ae = air_velocity_ne_m_s(tas, beta, yaw)
    wn, we = wind_ne_m_s(w_speed, w_from)
    gs, track = speed_and_track(an + wn, ae + we)
    drift_nose = angle_diff(track, yaw)  # what the camera measures
    speed, wfrom = wind_triangle(tas, beta, yaw, gs, ata_rad(0.0, yaw, drift_nose))
    np.testing.assert_allclose(speed, w_speed, rtol=1e-9)
    np.testing.assert_allclose(angle_diff(wfrom, w_from), 0.0, atol=1e-9)
    assert np.all((wfrom >= 0.0) & (wfrom < 2 * math.pi))
    drift_air = angle_diff(track, yaw + beta)  # drift from the air-velocity direction
    speed2, wfrom2 = wind_triangle(tas, beta, yaw, gs, ata_rad(beta, yaw, drift_air))
    np.testing.assert_allclose(speed2, w_speed, rtol=1e-9)
    np.testing.assert_allclose(angle_diff(wfrom2, w_from), 0.0, atol=1e-9)
    # mixing: the printed eq. 12 on a nose-relative drift; the error vector is GS * 2 sin(beta / 2)
    wn3, we3 = wind_ne_m_s(*wind_triangle(tas, beta, yaw, gs, ata_rad(beta, yaw, drift_nose)))
    err = np.hypot(wn3 - wn, we3 - we)
    np.testing.assert_allclose(err, gs * 2.0 * np.abs(np.sin(beta / 2.0)), rtol=1e-6, atol=1e-9)


# ---------------------------------------------------------------------------------------------------------------
# eq. 18-21


def test_gnss_drift_hand_cases():
    # heading north, moving north-east: 45 deg right
    np.testing.assert_allclose(gnss_drift_rad([0.0, 1.0, 2.0], [0.0, 1.0, 2.0], 0.0), [D(45.0)] * 2)
    # heading east, moving 10 m east and 1 m south: delta_x = 10, delta_y = 1, atan(1/10) = 5.7106 deg right
    assert gnss_drift_rad([0.0, -1.0], [0.0, 10.0], D(90.0))[0] == pytest.approx(D(5.710593137499643))
    # heading 350, track 10 (across north): +20
    tr = D(10.0)
    assert gnss_drift_rad([0.0, math.cos(tr)], [0.0, math.sin(tr)], D(350.0))[0] == pytest.approx(D(20.0))
    # heading 179, track 181 = -179 (across +-180): +2
    tr = D(181.0)
    assert gnss_drift_rad([0.0, math.cos(tr)], [0.0, math.sin(tr)], D(179.0))[0] == pytest.approx(D(2.0))
    # flying backwards relative to the heading: atan2 keeps the quadrant (atan would give 0)
    assert abs(gnss_drift_rad([0.0, -1.0], [0.0, 0.0], 0.0)[0]) == pytest.approx(math.pi)
    # no motion: nan; one position: no steps
    assert math.isnan(gnss_drift_rad([3.0, 3.0], [4.0, 4.0], 0.0)[0])
    assert gnss_drift_rad([1.0], [2.0], 0.0).size == 0


def test_gnss_drift_agrees_with_optical_drift_convention():
    """Eq. 20-21 and eq. 9 say the same thing: the track's angle clockwise of the heading."""
    rng = np.random.default_rng(12)
    yaw = np.deg2rad(rng.uniform(0.0, 360.0, 50))
    true_drift = np.deg2rad(rng.uniform(-60.0, 60.0, 50))
    track = yaw + true_drift
    pos_n = np.concatenate([[0.0], np.cumsum(np.cos(track))])
    pos_e = np.concatenate([[0.0], np.cumsum(np.sin(track))])
    np.testing.assert_allclose(angle_diff(gnss_drift_rad(pos_n, pos_e, yaw), true_drift), 0.0, atol=1e-12)
    dx, dy = displacement_px(true_drift, 10.0)
    np.testing.assert_allclose(angle_diff(drift_rad(dx, dy), true_drift), 0.0, atol=1e-12)


def test_gnss_drift_in_a_steady_turn_uses_the_mid_heading():
    """Zero-drift circle flown through north (headings 350 -> 10 deg across 0): with one heading per position the
    mid-interval heading makes eq. 20-21 exact; the heading at the step's end alone would read minus half the
    turn per step."""
    step = D(4.0)
    yaw = D(350.0) + step * np.arange(8)  # crosses 360
    radius = 100.0
    centre_n, centre_e = 0.0, 0.0
    # clockwise circle: position angle from the centre = heading - 90 deg
    pos_n = centre_n + radius * np.cos(yaw - math.pi / 2)
    pos_e = centre_e + radius * np.sin(yaw - math.pi / 2)
    yaw_wrapped = np.mod(yaw, 2 * math.pi)
    np.testing.assert_allclose(gnss_drift_rad(pos_n, pos_e, yaw_wrapped), 0.0, atol=1e-12)
    end_heading = gnss_drift_rad(pos_n, pos_e, yaw_wrapped[1:])
    np.testing.assert_allclose(end_heading, -step / 2, atol=1e-12)


def test_gnss_drift_bad_shapes_raise():
    with pytest.raises(ValueError):
        gnss_drift_rad([0.0, 1.0], [0.0, 1.0, 2.0], 0.0)
    with pytest.raises(ValueError):
        gnss_drift_rad([0.0, 1.0, 2.0], [0.0, 1.0, 2.0], [0.0, 0.1, 0.2, 0.3])
