"""Guidance geometry against analytic cases, drift correction against the wind triangle, and the tracker."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gsoe.camera import CameraModel
from gsoe.config import CameraConfig
from gsoe.rotation import R_nb_from_euler
from nav.guidance import (
    HEADING_TYPE_HEADING,
    MAV_CMD_GUIDED_CHANGE_HEADING,
    GuidanceConfig,
    TargetGuidance,
    change_heading_command_fields,
    forward_camera,
    heading_command,
    locate_target,
)
from nav.tracker import TemplateTracker, TemplateTrackerConfig

CFG = GuidanceConfig()


def _pinhole() -> CameraModel:
    cfg = CameraConfig(model="pinhole", width_px=640, height_px=480, fx_px=400.0, fy_px=400.0, cx_px=320.0,
                       cy_px=240.0, dist=(0.0, 0.0, 0.0, 0.0, 0.0), hfov_deg=77.3, vfov_deg=61.9)
    return CameraModel.from_config(cfg)


def _pixel_of_ground_point(camera: CameraModel, rel_ned: np.ndarray, roll: float, pitch: float, yaw: float):
    ray_b = R_nb_from_euler(roll, pitch, yaw).T @ rel_ned
    ray_c = camera.R_bc.T @ ray_b
    px, ok = camera.project(ray_c.reshape(1, 3))
    assert ok[0]
    return px[0]


@pytest.mark.parametrize("att_deg", [(0, 0, 0), (12, -4, 70), (-25, 8, 250)])
def test_locate_ground_point_round_trip_belly_fisheye(camera, att_deg):
    roll, pitch, yaw = np.deg2rad(att_deg)
    h = 100.0
    rel = np.array([30.0, -40.0, h])
    px = _pixel_of_ground_point(camera, rel, roll, pitch, yaw)
    fix = locate_target(0, px, camera, roll, pitch, yaw, h, CFG)
    assert fix.valid
    np.testing.assert_allclose(fix.rel_ne_m, rel[:2], atol=0.05)
    assert fix.range_m == pytest.approx(50.0, abs=0.05)
    assert fix.bearing_rad == pytest.approx(math.atan2(-40.0, 30.0) % (2 * math.pi), abs=1e-3)


def test_forward_camera_principal_point_is_at_depression_along_heading():
    cam = forward_camera(_pinhole(), math.radians(10.0))
    yaw = math.radians(135.0)
    fix = locate_target(5, (320.0, 240.0), cam, 0.0, 0.0, yaw, 100.0, CFG)
    assert fix.valid
    expected_range = 100.0 / math.tan(math.radians(10.0))
    assert fix.range_m == pytest.approx(expected_range, rel=1e-6)
    assert fix.bearing_rad == pytest.approx(yaw, abs=1e-9)
    assert fix.depression_rad == pytest.approx(math.radians(10.0), abs=1e-9)
    # image right of centre = right of the nose = clockwise
    right = locate_target(5, (420.0, 240.0), cam, 0.0, 0.0, yaw, 100.0, CFG)
    assert right.bearing_rad > yaw


def test_rays_above_horizon_and_bad_inputs_are_invalid():
    cam = forward_camera(_pinhole(), 0.0)
    above = locate_target(0, (320.0, 100.0), cam, 0.0, 0.0, 0.0, 100.0, CFG)  # upper half of a level camera
    assert not above.valid and "horizon" in above.reason
    for args in [((np.nan, 10.0), 0.0, 100.0), ((320.0, 400.0), np.nan, 100.0), ((320.0, 400.0), 0.0, -5.0),
                 ((5000.0, 400.0), 0.0, 100.0)]:
        px, roll, h = args
        fix = locate_target(0, px, cam, roll, 0.0, 0.0, h, CFG)
        assert not fix.valid and fix.reason
        assert np.all(np.isnan(fix.rel_ne_m))


def _ground_velocity(heading: float, tas: float, wind_ne: np.ndarray) -> np.ndarray:
    return tas * np.array([math.cos(heading), math.sin(heading)]) + wind_ne


def test_drift_correction_puts_the_ground_track_on_the_target():
    tas, wind = 20.0, np.array([0.0, 8.0])  # wind blowing to the east (from 270 deg)
    # truth from the wind triangle: the heading whose ground track points north
    true_heading = -math.asin(8.0 / 20.0)
    drift = 0.0 - true_heading  # course - heading
    rel = np.array([2000.0, 0.0])
    from nav.guidance import TargetFix
    fix = TargetFix(0, rel, 0.0, 2000.0, 0.05, True)
    cmd = heading_command(fix, 0.0, drift, math.radians(0.5), True, CFG)
    assert cmd.valid and cmd.drift_applied
    v = _ground_velocity(cmd.heading_rad, tas, wind)
    assert math.atan2(v[1], v[0]) == pytest.approx(0.0, abs=1e-9)
    # without correction the nose points at the target and the track is off by the drift
    plain = heading_command(fix, 0.0, drift, 0.0, True, GuidanceConfig(correct_drift=False))
    assert plain.heading_rad == pytest.approx(0.0) and not plain.drift_applied
    v = _ground_velocity(plain.heading_rad, tas, wind)
    assert math.degrees(math.atan2(v[1], v[0])) == pytest.approx(math.degrees(math.atan2(8.0, 20.0)), abs=1e-6)


def test_heading_saturations_and_validity():
    from nav.guidance import TargetFix
    fix = TargetFix(0, np.array([0.0, 500.0]), math.pi / 2, 500.0, 0.2, True)
    big = heading_command(fix, math.pi / 2, math.radians(60.0), 0.01, True, CFG)
    assert big.drift_used_rad == pytest.approx(math.radians(CFG.max_drift_deg))
    assert "saturated" in big.reason
    unsure = heading_command(fix, math.pi / 2, 0.2, math.radians(10.0), True, CFG)
    assert not unsure.drift_applied and unsure.heading_rad == pytest.approx(math.pi / 2)
    nan_drift = heading_command(fix, math.pi / 2, math.nan, 0.01, True, CFG)
    assert nan_drift.valid and not nan_drift.drift_applied
    reversal = heading_command(fix, math.radians(270.0), 0.0, 0.01, True, GuidanceConfig(max_heading_change_deg=90))
    assert reversal.heading_rad == pytest.approx(0.0, abs=1e-9) or reversal.heading_rad == pytest.approx(math.pi)
    assert "heading change saturated" in reversal.reason
    assert not heading_command(fix, math.nan, 0.0, 0.0, True, CFG).valid


def test_terminal_hold_after_target_leaves_the_view():
    cam = forward_camera(_pinhole(), math.radians(10.0))
    g = TargetGuidance(cam, CFG)
    h = 100.0
    # target 120 m ahead, a bit to the right: valid fix within hold range
    px = _pixel_of_ground_point(cam, np.array([120.0, 10.0, h]), 0.0, 0.0, 0.0)
    fix, cmd = g.step(0, px, 0.0, 0.0, 0.0, h, 0.0, 0.0, False)
    assert fix.valid and cmd.valid and not cmd.terminal
    fix2, cmd2 = g.step(100_000, None, 0.0, 0.0, 0.0, h, 0.0, 0.0, False)
    assert not fix2.valid and cmd2.valid and cmd2.terminal
    assert cmd2.course_rad == pytest.approx(cmd.course_rad)
    # lost far away: nothing to send
    g2 = TargetGuidance(cam, CFG)
    far = _pixel_of_ground_point(cam, np.array([500.0, 0.0, h]), 0.0, 0.0, 0.0)
    g2.step(0, far, 0.0, 0.0, 0.0, h, 0.0, 0.0, False)
    assert not g2.step(100_000, None, 0.0, 0.0, 0.0, h, 0.0, 0.0, False)[1].valid


def test_command_long_fields():
    from nav.guidance import HeadingCommand
    cmd = HeadingCommand(0, math.radians(359.9999999999), 0.0, 0.0, False, False, True)
    f = change_heading_command_fields(cmd, CFG, 1, 1)
    assert f["command"] == MAV_CMD_GUIDED_CHANGE_HEADING and f["param1"] == HEADING_TYPE_HEADING
    assert 0.0 <= f["param2"] < 360.0 and f["param3"] == CFG.accel_limit_m_s2
    with pytest.raises(ValueError):
        change_heading_command_fields(HeadingCommand(0, math.nan, 0.0, 0.0, False, False, False, "x"), CFG, 1, 1)


def _texture(rng: np.random.Generator, h: int = 480, w: int = 640) -> np.ndarray:
    img = rng.normal(128.0, 40.0, (h, w)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(img, (0, 0), 2.0), 0, 255).astype(np.uint8)


def test_template_tracker_follows_a_subpixel_shift():
    rng = np.random.default_rng(1)
    base = _texture(rng)
    trk = TemplateTracker(TemplateTrackerConfig())
    assert trk.designate(0, base, (300.0, 200.0))
    shift = (7.3, -4.6)
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    moved = cv2.warpAffine(base, M, (base.shape[1], base.shape[0]), flags=cv2.INTER_CUBIC)
    res = trk.update(33_333, moved)
    assert res.valid and res.score > 0.9
    assert res.xy_px[0] == pytest.approx(307.3, abs=0.3)
    assert res.xy_px[1] == pytest.approx(195.4, abs=0.3)


def test_template_tracker_loses_and_drops_on_bad_frames():
    rng = np.random.default_rng(2)
    base = _texture(rng)
    trk = TemplateTracker(TemplateTrackerConfig(max_lost_frames=3))
    assert not trk.designate(0, np.zeros_like(base), (300.0, 200.0))  # no texture
    assert trk.designate(0, base, (300.0, 200.0))
    for i, bad in enumerate([np.zeros_like(base), np.full_like(base, 255), _texture(rng), None, base[:, :, None] * 0]):
        res = trk.update(i + 1, bad)  # type: ignore[arg-type]
        assert not res.valid and res.reason
    assert not trk.active


def test_command_id_matches_pymavlink_dialect():
    from pymavlink.dialects.v20 import ardupilotmega

    assert MAV_CMD_GUIDED_CHANGE_HEADING == ardupilotmega.MAV_CMD_GUIDED_CHANGE_HEADING
    assert HEADING_TYPE_HEADING == ardupilotmega.HEADING_TYPE_HEADING


def test_external_tracker_reports_pixels_while_fresh_and_active():
    from nav.tracker import ExternalTracker

    t = ExternalTracker((640, 480), max_age_s=0.5)
    assert not t.active and not t.update(0).valid
    t.push(1_000_000, 0.5, 0.25, True)
    r = t.update(1_200_000)
    assert t.active and r.valid and r.xy_px == pytest.approx((319.5, 119.5))  # pixel centres at integers
    assert not t.update(1_600_001).valid  # too old
    assert "old" in t.update(900_000).reason  # report from the future of this query
    t.push(2_000_000, math.nan, math.nan, False)
    assert not t.active and not t.update(2_000_001).valid
    # the hook's encoding (x = (column + 0.5) / width) round-trips through the tracker
    col, row = 123.25, 301.5
    t.push(3_000_000, (col + 0.5) / 640, (row + 0.5) / 480, True)
    assert t.update(3_000_000).xy_px == pytest.approx((col, row))
