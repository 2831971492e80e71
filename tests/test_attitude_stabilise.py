"""Attitude buffer (interpolation, gyro integration, bias filter) and the virtual nadir camera's sampling map."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from common.samples import AttitudeSample, ImuSample
from gsoe import quat
from gsoe.attitude import AttitudeBuffer
from gsoe.rotation import R_nb_from_euler
from gsoe.stabilise import PatchSampler, VirtualNadirCamera, _interp_matrix

RATE_HZ = 300
T_END_S = 4.0


def _truth(t_s: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw histories of a banked, pitching, turning aircraft (rad)."""
    roll = 0.6 * np.sin(0.9 * t_s)
    pitch = 0.2 * np.sin(1.3 * t_s + 0.4)
    yaw = 0.45 * t_s + 0.1
    return np.column_stack([roll, pitch, yaw])


def _body_rates(t_s: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    rates = []
    for t in t_s:
        a0 = _truth(np.array([t - eps]))[0]
        a1 = _truth(np.array([t + eps]))[0]
        R0 = Rotation.from_euler("ZYX", a0[::-1])
        R1 = Rotation.from_euler("ZYX", a1[::-1])
        rates.append((R0.inv() * R1).as_rotvec() / (2 * eps))
    return np.array(rates)


def _fill(buf: AttitudeBuffer, gyro_bias: np.ndarray, att_noise_rad: float, rng: np.random.Generator,
          bias_update_every_s: float = 0.0, bias_window_s: float = 1.0, t_end_s: float = T_END_S) -> None:
    """Stream samples in time order; optionally feed the bias filter as the TM cycles do."""
    t = np.arange(0.0, t_end_s, 1.0 / RATE_HZ)
    att = _truth(t)
    rates = _body_rates(t)
    next_update = bias_window_s
    for ti, a, w in zip(t, att, rates, strict=True):
        t_us = int(round(ti * 1e6))
        buf.push_imu(ImuSample(t_us, w + gyro_bias, np.zeros(3)))
        n = rng.normal(0.0, att_noise_rad, 3)
        buf.push_attitude(AttitudeSample(t_us, a[0] + n[0], a[1] + n[1], a[2] + n[2]))
        if bias_update_every_s > 0 and ti >= next_update:
            buf.update_bias(int((ti - bias_window_s) * 1e6), t_us)
            next_update += bias_update_every_s


def _rot(q) -> Rotation:
    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w])


def test_quaternion_helpers_match_scipy():
    rng = np.random.default_rng(5)
    for _ in range(50):
        a, b = Rotation.random(random_state=rng), Rotation.random(random_state=rng)
        qa = quat.from_matrix(a.as_matrix())
        qb = quat.from_matrix(b.as_matrix())
        assert (_rot(quat.mul(qa, qb)).inv() * (a * b)).magnitude() < 1e-9
        np.testing.assert_allclose(quat.to_matrix(qa), a.as_matrix(), atol=1e-12)
        rv = rng.normal(0.0, 1.0, 3)
        assert (_rot(quat.from_rotvec(*rv)).inv() * Rotation.from_rotvec(rv)).magnitude() < 1e-9
        np.testing.assert_allclose(quat.to_rotvec(quat.from_rotvec(*rv)), Rotation.from_rotvec(rv).as_rotvec(),
                                   atol=1e-9)
        e = rng.uniform([-3, -1.5, -3], [3, 1.5, 3])
        q = quat.from_euler321(*e)
        assert (_rot(q).inv() * Rotation.from_euler("ZYX", e[::-1])).magnitude() < 1e-9
        np.testing.assert_allclose(quat.to_euler321(q), e, atol=1e-9)
        assert quat.angle(quat.mul(quat.conj(qa), qb)) == pytest.approx((a.inv() * b).magnitude(), abs=1e-9)
        mid = quat.slerp(qa, qb, 0.3)
        from scipy.spatial.transform import Slerp
        ref = Slerp([0, 1], Rotation.concatenate([a, b]))([0.3])[0]
        assert (_rot(mid).inv() * ref).magnitude() < 1e-9


def test_attitude_interpolation_and_gyro_relative_rotation():
    buf = AttitudeBuffer(horizon_s=10.0, gyro_bias_tau_s=0.0)
    _fill(buf, np.zeros(3), 0.0, np.random.default_rng(0))
    t0, t1 = 1.2345, 1.9
    truth0 = Rotation.from_euler("ZYX", _truth(np.array([t0]))[0][::-1])
    truth1 = Rotation.from_euler("ZYX", _truth(np.array([t1]))[0][::-1])
    est0 = _rot(buf.attitude_at(int(t0 * 1e6)))
    assert (est0.inv() * truth0).magnitude() < np.deg2rad(0.01)
    rel = _rot(buf.relative_rotation(int(t0 * 1e6), int(t1 * 1e6), use_gyro=True))
    assert (rel.inv() * (truth0.inv() * truth1)).magnitude() < np.deg2rad(0.02)
    assert buf.attitude_at(int(10e6)) is None  # outside the buffer: unknown, not a guess


def test_gyro_relative_rotation_beats_noisy_ahrs_and_bias_filter_converges():
    rng = np.random.default_rng(3)
    bias = np.deg2rad([0.3, -0.2, 0.25])
    buf = AttitudeBuffer(horizon_s=10.0, gyro_bias_tau_s=4.0)
    _fill(buf, bias, np.deg2rad(0.1), rng, bias_update_every_s=1.0, t_end_s=25.0)
    np.testing.assert_allclose(buf.gyro_bias_b_rad_s, bias, atol=np.deg2rad(0.1))
    t0, t1 = 23.2, 23.5
    truth_rel = (Rotation.from_euler("ZYX", _truth(np.array([t0]))[0][::-1]).inv()
                 * Rotation.from_euler("ZYX", _truth(np.array([t1]))[0][::-1]))
    err_ahrs = (_rot(buf.relative_rotation(int(t0 * 1e6), int(t1 * 1e6), use_gyro=False)).inv() * truth_rel).magnitude()
    err_gyro = (_rot(buf.relative_rotation(int(t0 * 1e6), int(t1 * 1e6), use_gyro=True)).inv() * truth_rel).magnitude()
    assert err_gyro < np.deg2rad(0.05)
    assert err_gyro < err_ahrs


def test_nonfinite_and_out_of_order_samples_rejected():
    buf = AttitudeBuffer()
    assert buf.push_attitude(AttitudeSample(10, 0.0, 0.0, 0.0))
    assert not buf.push_attitude(AttitudeSample(20, float("nan"), 0.0, 0.0))
    assert not buf.push_attitude(AttitudeSample(5, 0.0, 0.0, 0.0))
    assert buf.push_imu(ImuSample(10, np.zeros(3), np.zeros(3)))
    assert not buf.push_imu(ImuSample(20, np.array([np.inf, 0, 0]), np.zeros(3)))


def test_interp_matrix_reproduces_linear_functions():
    for n, step in ((19, 9), (121, 8), (73, 8), (10, 20)):
        nodes, A = _interp_matrix(n, step)
        assert nodes[0] == 0 and nodes[-1] == n - 1
        np.testing.assert_allclose(A @ (3.0 * nodes + 1.0), 3.0 * np.arange(n) + 1.0, atol=1e-12)


@pytest.mark.parametrize("roll_deg,pitch_deg,dyaw_deg",
                         [(0, 0, 0), (45, 0, 0), (-45, 10, 0), (-30, 10, 30), (20, -20, -60)])
def test_coarse_grid_map_matches_exact_projection(camera, roll_deg, pitch_deg, dyaw_deg):
    """The interpolated sampling map stays within 0.05 px of projecting every pixel's ray exactly."""
    sampler = PatchSampler(camera, 121, 73, (60.0, 36.0), 8)
    yaw0 = np.deg2rad(37.0)
    R_nb = R_nb_from_euler(np.deg2rad(roll_deg), np.deg2rad(pitch_deg), yaw0 + np.deg2rad(dyaw_deg))
    R_cn = camera.R_bc.T @ R_nb.T
    scale = 1.0 / 351.86
    mx, my, ok = sampler.sample_map(R_cn, yaw0, scale)
    assert ok
    uu, vv = np.meshgrid(np.arange(121.0), np.arange(73.0))
    c, s = np.cos(yaw0), np.sin(yaw0)
    fwd, right = (36.0 - vv) * scale, (uu - 60.0) * scale
    rays_n = np.stack([c * fwd - s * right, s * fwd + c * right, np.ones_like(fwd)], axis=-1).reshape(-1, 3)
    px, valid = camera.project(rays_n @ R_cn.T)
    assert valid.all()
    err = np.hypot(mx.ravel() - px[:, 0], my.ravel() - px[:, 1])
    assert err.max() < 0.05


def test_nadir_pixel_is_projection_of_down(camera):
    vcam = VirtualNadirCamera(camera, (121, 73), (60.0, 36.0), 19, 0.0, 8)
    for roll, pitch in ((0.3, 0.1), (-0.7, -0.3)):
        R_nb = Rotation.from_euler("ZYX", [1.0, pitch, roll])
        mx, my, ok = vcam.base.sample_map(vcam.R_cn(R_nb.as_matrix()), 1.0, 1.0 / vcam.focal_px)
        down_c = vcam.R_cn(R_nb.as_matrix()) @ np.array([0.0, 0.0, 1.0])
        px, _ = camera.project(down_c[None])
        assert mx[36, 60] == pytest.approx(px[0, 0], abs=0.02)
        assert my[36, 60] == pytest.approx(px[0, 1], abs=0.02)


def _fill_delayed(buf: AttitudeBuffer, latency_s: float, att_noise_rad: float, rng: np.random.Generator,
                  t_end_s: float, ahrs_every: int = 6) -> None:
    """Gyro on time at RATE_HZ; the AHRS at RATE_HZ / ahrs_every reports the (noisy) attitude of ``latency_s`` ago."""
    t = np.arange(0.0, t_end_s, 1.0 / RATE_HZ)
    rates = _body_rates(t)
    att_late = _truth(t - latency_s)
    for k, (ti, w) in enumerate(zip(t, rates, strict=True)):
        t_us = int(round(ti * 1e6))
        buf.push_imu(ImuSample(t_us, w, np.zeros(3)))
        if k % ahrs_every == 0:
            a = att_late[k] + rng.normal(0.0, att_noise_rad, 3)
            buf.push_attitude(AttitudeSample(t_us, a[0], a[1], a[2]))


def _err_deg(q, t_s: float) -> float:
    truth = Rotation.from_euler("ZYX", _truth(np.array([t_s]))[0][::-1])
    return float(np.degrees((_rot(q).inv() * truth).magnitude()))


def test_ahrs_latency_estimated_and_compensated():
    latency_s = 0.06
    buf = AttitudeBuffer(horizon_s=10.0, gyro_bias_tau_s=0.0)
    _fill_delayed(buf, latency_s, np.deg2rad(0.3), np.random.default_rng(5), t_end_s=40.0)
    assert abs(buf.ahrs_latency_s - latency_s) < 0.005
    times = np.arange(35.0, 39.5, 0.37)
    raw = [_err_deg(buf.attitude_at(int(t * 1e6)), t) for t in times]
    comp = [_err_deg(buf.compensated_at(int(t * 1e6), smooth=False), t) for t in times]
    smooth = [_err_deg(buf.compensated_at(int(t * 1e6), smooth=True), t) for t in times]
    # the truth turns at up to ~35 deg/s: 60 ms of lag is about 2 deg; the noise alone (3 axes of 0.3 deg) ~0.5 deg
    assert np.mean(raw) > 1.0
    assert np.mean(comp) < 0.8
    assert np.mean(smooth) < 0.25 < np.mean(comp)


def test_latency_known_or_absent_is_not_invented():
    with pytest.raises(ValueError, match="latency_s"):
        AttitudeBuffer(latency_s=-0.1)
    buf = AttitudeBuffer(horizon_s=10.0, gyro_bias_tau_s=0.0)
    _fill_delayed(buf, 0.0, np.deg2rad(0.3), np.random.default_rng(6), t_end_s=30.0)
    assert buf.ahrs_latency_s < 0.005
    fixed = AttitudeBuffer(horizon_s=10.0, gyro_bias_tau_s=0.0, latency_s=0.04)
    _fill_delayed(fixed, 0.04, 0.0, np.random.default_rng(7), t_end_s=12.0)
    assert fixed.ahrs_latency_s == 0.04
    assert _err_deg(fixed.compensated_at(int(11.0e6), smooth=False), 11.0) < 0.05
