"""The optical pipeline's per-frame shortcuts (issue 24) against the general paths they replace: the camera-to-
heading rotation from quaternions against scipy's matrices, the lens-field test on the template grid's four corner
rays against :meth:`CameraModel.project` of every ray, and the remembered gyro value at a cycle's base time against
a fresh lookup."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.spatial.transform import Rotation

from gsoe import quat
from gsoe.camera import CameraModel
from gsoe.stabilise import VirtualNadirCamera


def _vcam(camera: CameraModel) -> VirtualNadirCamera:
    return VirtualNadirCamera(camera, (121, 73), (60.0, 36.0), 19, 0.0, 8)


def test_heading_rotation_from_quaternions_is_the_matrix_chain(camera):
    """R_hc = R_z(yaw)^T R_nb R_bc, with a mount that is not the identity."""
    rng = np.random.default_rng(24)
    mounted = CameraModel.from_config(dataclasses.replace(camera.config, mount_rpy_deg=(3.0, -7.0, 20.0)))
    for cam in (camera, mounted):
        vcam = _vcam(cam)
        for _ in range(50):
            rpy = rng.uniform([-1.0, -0.6, -math.pi], [1.0, 0.6, math.pi])
            yaw_base = float(rng.uniform(-math.pi, math.pi))
            R_nb = Rotation.from_euler("ZYX", rpy[::-1]).as_matrix()
            R_z = Rotation.from_euler("z", yaw_base).as_matrix()
            expected = R_z.T @ R_nb @ cam.R_bc
            got = vcam.R_hc(quat.from_euler321(*rpy), yaw_base)
            np.testing.assert_allclose(got, expected, atol=1e-12)
            # and the matrix path of the base image agrees
            np.testing.assert_allclose(vcam.template.R_hc(vcam.R_cn(R_nb), yaw_base), expected, atol=1e-12)


def test_corner_field_test_decides_as_every_ray(camera):
    """Grids at steep attitudes and far offsets, lenses whose field is narrower than the image corners or wider than
    a half-space (where every ray is tested): the lean projection returns pixels exactly when every ray projects
    inside the image, and the same pixels."""
    rng = np.random.default_rng(7)
    narrow = dataclasses.replace(camera, max_off_axis_rad=math.radians(35.0))
    wide = dataclasses.replace(camera, max_off_axis_rad=math.radians(100.0))
    outcomes = {True: 0, False: 0}
    for cam in (camera, narrow, wide):
        sampler = _vcam(cam).template
        for _ in range(400):
            rpy = rng.uniform([-1.3, -1.3, -math.pi], [1.3, 1.3, math.pi])
            R_hc = Rotation.from_euler("ZYX", rpy[::-1]).as_matrix() @ cam.R_bc
            offset = (float(rng.uniform(-600, 600)), float(rng.uniform(-600, 600)))
            nodes = sampler._nodes_fr + offset
            rays_h = np.column_stack([nodes / cam.config.fx_px, np.ones(len(nodes))])
            rays_c = rays_h @ R_hc
            px_all, inside = cam.project(rays_c)
            got = cam.project_in_frame(rays_c, sampler._corners)
            assert (got is not None) == bool(inside.all())
            if got is not None:
                np.testing.assert_allclose(got, px_all, atol=1e-9)
            outcomes[got is not None] += 1
    assert min(outcomes.values()) > 50, outcomes


def test_relative_rotation_from_a_remembered_start_is_the_fresh_one():
    """A cycle asks for the rotation since its base time every frame; the remembered gyro value at that time gives
    bit for bit what a buffer asked once gives, as samples arrive and the oldest are dropped (horizon 0.5 s)."""
    from common.samples import ImuSample
    from gsoe.attitude import AttitudeBuffer

    rng = np.random.default_rng(3)
    gyro = rng.normal(0.0, 0.3, (900, 3))
    asked, fresh_buf = AttitudeBuffer(horizon_s=0.5), AttitudeBuffer(horizon_s=0.5)
    t0_us = 1_005_000                                   # between two samples (300 Hz)
    for k, w in enumerate(gyro):
        s = ImuSample(k * 3333, w, np.zeros(3))
        asked.push_imu(s)
        fresh_buf.push_imu(s)
        t1_us = k * 3333
        if t1_us > t0_us:
            got = asked.relative_rotation(t0_us, t1_us)
            fresh = AttitudeBuffer(horizon_s=0.5)
            fresh._gyro, fresh._att = fresh_buf._gyro, fresh_buf._att
            assert got == fresh.relative_rotation(t0_us, t1_us)
    # t0 has left the horizon: no rotation from the memory either
    assert asked.relative_rotation(t0_us, 899 * 3333) is None


def test_a_scale_without_ground_gives_an_invalid_patch_not_an_error(camera):
    """A height ratio that is zero (underflow), negative or NaN reaches the sampler as a scale without ground: the
    template is an invalid patch and does not fit; a normal ratio samples a valid one."""
    vcam = _vcam(camera)
    frame = np.full(camera.size_px[::-1], 128, np.uint8)
    for ratio in (0.0, -1.0, math.nan):
        assert not vcam.sample_template(frame, quat.IDENTITY, 0.0, ratio).valid
        assert not vcam.template_fits(quat.IDENTITY, 0.0, ratio, (0.0, 0.0))
    assert vcam.sample_template(frame, quat.IDENTITY, 0.0, 1.0).valid
