"""Conventions, config validation and the camera model against independent truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.angles import angle_diff, angle_diff_deg, circular_mean, wrap_2pi, wrap_pi
from common.config import ConfigError, build
from gsoe.camera import CameraModel
from gsoe.config import CameraConfig, StabConfig
from gsoe.rotation import R_BC_NOMINAL, R_nb_from_euler


def test_wrap_helpers_cross_zero_and_pi():
    assert angle_diff(np.deg2rad(359.0), np.deg2rad(1.0)) == pytest.approx(np.deg2rad(-2.0))
    assert angle_diff_deg(-179.0, 179.0) == pytest.approx(2.0)
    assert wrap_pi(3 * np.pi) == pytest.approx(-np.pi)
    assert wrap_2pi(-0.5) == pytest.approx(2 * np.pi - 0.5)
    assert circular_mean(np.deg2rad([350.0, 10.0])) == pytest.approx(0.0, abs=1e-12)


def test_rotation_is_ned_frd():
    # 90 deg yaw: body forward points east
    R = R_nb_from_euler(0.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # positive pitch: nose up (forward axis gains a negative down component)
    R = R_nb_from_euler(0.0, 0.2, 0.0)
    assert (R @ [1, 0, 0])[2] < 0
    # positive roll: right wing down
    R = R_nb_from_euler(0.2, 0.0, 0.0)
    assert (R @ [0, 1, 0])[2] > 0
    # nominal camera: image right = right wing, image up = nose, optical axis = down
    np.testing.assert_allclose(R_BC_NOMINAL @ [1, 0, 0], [0, 1, 0])
    np.testing.assert_allclose(R_BC_NOMINAL @ [0, -1, 0], [1, 0, 0])
    np.testing.assert_allclose(R_BC_NOMINAL @ [0, 0, 1], [0, 0, 1])


def test_euler_matrix_matches_scipy():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    for roll, pitch, yaw in rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi], size=(200, 3)):
        ref = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
        np.testing.assert_allclose(R_nb_from_euler(roll, pitch, yaw), ref, atol=1e-14)


@pytest.mark.parametrize("model", ["fisheye", "pinhole"])
def test_project_unproject_round_trip(camera, model):
    cfg = camera.config
    if model == "pinhole":
        dist = (-0.05, 0.01, 0.001, -0.001, 0.0)
        cfg = dataclasses.replace(cfg, model="pinhole", fx_px=280.0, fy_px=280.0, dist=dist)
    cam = CameraModel.from_config(cfg)
    rng = np.random.default_rng(1)
    px = np.column_stack([rng.uniform(5, 795, 500), rng.uniform(5, 595, 500)])
    rays = cam.unproject(px)
    back, valid = cam.project(rays)
    assert valid.all()
    np.testing.assert_allclose(back, px, atol=1e-4)


def test_fisheye_field_of_view_matches_config(camera):
    # independent truth: the Kannala-Brandt radius r = f * theta * (1 + k1 theta^2) at the half fields
    for half_deg, axis in ((54.0, 0), (43.0, 1)):
        t = np.deg2rad(half_deg)
        ray = np.array([np.sin(t), 0.0, np.cos(t)]) if axis == 0 else np.array([0.0, np.sin(t), np.cos(t)])
        px, valid = camera.project(ray[None])
        expect = camera.config.fx_px * t * (1 + camera.config.dist[0] * t**2)
        centre = (camera.config.cx_px, camera.config.cy_px)[axis]
        assert px[0, axis] - centre == pytest.approx(expect, abs=1e-6)
    # behind the camera is invalid, not a number
    _, valid = camera.project(np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]))
    assert not valid.any()


def test_config_errors_name_the_field(camera):
    good = dataclasses.asdict(camera.config)
    for key, bad in (("fx_px", -3.0), ("model", "kb8"), ("dist", [0.1, 0.2]), ("width_px", 12.5)):
        with pytest.raises(ConfigError, match=f"camera.{key}"):
            build(CameraConfig, {**good, key: bad}, "camera")
    with pytest.raises(ConfigError, match="camera.colour"):
        build(CameraConfig, {**good, "colour": True}, "camera")
    with pytest.raises(ConfigError, match="stab.template_px: must be odd"):
        build(StabConfig, {"template_px": 18}, "stab")


def test_config_file_errors(tmp_path):
    from pipeline.config import load_gsoe_config

    with pytest.raises(ConfigError, match="file not found"):
        load_gsoe_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text('[camera]\nfile = "camera/paper_fisheye_800x600.toml"\n[cycle]\nrate_hz = 0.0\n')
    with pytest.raises(ConfigError, match="cycle.rate_hz"):
        load_gsoe_config(bad)
