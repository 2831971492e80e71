"""The optical estimator end to end over rendered fisheye frames, against the scripted flight's exact truth."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from common.angles import angle_diff, circular_mean
from common.samples import AttitudeSample, ImuSample
from gsoe.cycle import GsoeEstimator, chord_drift_rad
from sim.optical_run import OpticalRun, fly_optical
from sim.render import CameraRenderer
from sim.textures import GroundWorld
from sim.trajectory import ScriptedFlight, Segment
from tests.still_camera import still_frames

TURN_RATE_RAD_S = math.radians(30.0)


@pytest.fixture(scope="module")
def renderer(camera):
    return CameraRenderer(camera, GroundWorld.from_name("forest_road"))


def _cycle_ends(run: OpticalRun) -> list[int]:
    """Index of the last valid step of every cycle (the one the paper's filter reports)."""
    last: dict[int, int] = {}
    for i, s in enumerate(run.steps):
        if s.valid and not s.new_cycle:
            last[s.cycle_id] = i
    return sorted(last.values())


def _errors(run: OpticalRun) -> tuple[np.ndarray, np.ndarray]:
    """Chord-drift errors (deg) and ground-speed relative errors of every cycle's last valid step."""
    d_err, v_err = [], []
    for i in _cycle_ends(run):
        s, tr, tb = run.steps[i], run.truth_at_step[i], run.truth_at_base[i]
        d = tr.pos_ned_m[:2] - tb.pos_ned_m[:2]
        true_drift = angle_diff(math.atan2(d[1], d[0]), circular_mean([tb.yaw_rad, tr.yaw_rad]))
        d_err.append(math.degrees(angle_diff(chord_drift_rad(s), true_drift)))
        dt = (s.t_us - s.base_t_us) / 1e6
        gs = math.hypot(s.dx_px, s.dy_px) * s.gsd_m_px / dt
        v_err.append(gs / (np.linalg.norm(d) / dt) - 1.0)
    return np.array(d_err), np.array(v_err)


@pytest.mark.parametrize("geometry", ["paper", "long_trailing"])
@pytest.mark.parametrize("turning", [False, True])
def test_drift_and_ground_speed_on_textured_ground(gsoe_config, camera, renderer, geometry, turning):
    cfg = gsoe_config
    if geometry == "long_trailing":
        cfg = dataclasses.replace(cfg, stab=dataclasses.replace(cfg.stab, base_cross_px=73, base_along_px=121,
                                                                template_start="trailing"))
    segs = [Segment(6.0, TURN_RATE_RAD_S)] if turning else [Segment(6.0)]
    flight = ScriptedFlight([Segment(1.5)] + segs, tas_m_s=18.0, height_m=100.0, yaw0_rad=math.radians(20.0),
                            wind_ned_m_s=(-3.0, 6.0, 0.0), ramp_s=1.0)
    run = fly_optical(flight, cfg, camera, renderer, t_start_s=1.6 if turning else 0.0)
    d_err, v_err = _errors(run)
    assert len(d_err) >= 5
    # the crab angle is large (about 20 deg): an estimator that ignored the migration direction would fail
    assert np.mean(np.abs(d_err)) < 0.5, d_err
    assert np.max(np.abs(v_err)) < 0.02, v_err


def test_stabilised_view_matches_level_view(gsoe_config, camera, renderer):
    """Rolled, pitched and yawed frames give the same nadir base image as level flight (NCC > 0.97)."""
    est = GsoeEstimator(gsoe_config, camera)
    pos = np.array([35.0, -20.0, -100.0])
    yaw0 = math.radians(30.0)
    level = Rotation.from_euler("ZYX", [yaw0, 0.0, 0.0])
    ref = est.vcam.sample_base(renderer.render(pos, level.as_matrix()), level.as_matrix(), yaw0)
    assert ref.valid
    for roll, pitch, dyaw in ((45, 0, 0), (-45, 0, 0), (0, 20, 0), (0, -20, 0), (30, 10, 25), (-20, -15, -40)):
        R = Rotation.from_euler("ZYX", [yaw0 + math.radians(dyaw), math.radians(pitch), math.radians(roll)])
        patch = est.vcam.sample_base(renderer.render(pos, R.as_matrix()), R.as_matrix(), yaw0)
        assert patch.valid
        ncc = cv2.matchTemplate(patch.image, ref.image, cv2.TM_CCOEFF_NORMED)[0, 0]
        assert ncc > 0.97, (roll, pitch, dyaw, ncc)


def test_gyro_composed_rotation_beats_two_noisy_attitudes(gsoe_config, camera, renderer):
    """White AHRS noise of 0.1 deg per sample: composing the template's rotation from the base attitude and the
    integrated gyro keeps the drift error small; two independent noisy attitudes do not."""
    flight = ScriptedFlight([Segment(6.0)], tas_m_s=20.0, height_m=100.0, wind_ned_m_s=(0.0, 5.0, 0.0))
    maes = {}
    for use_gyro in (True, False):
        cfg = dataclasses.replace(gsoe_config, stab=dataclasses.replace(gsoe_config.stab, use_gyro=use_gyro),
                                  cycle=dataclasses.replace(gsoe_config.cycle, data_filter=False))
        run = fly_optical(flight, cfg, camera, renderer, att_noise_rad=math.radians(0.1),
                          gyro_noise_rad_s=math.radians(0.01), rng=np.random.default_rng(7))
        d_err, _ = _errors(run)
        maes[use_gyro] = float(np.mean(np.abs(d_err)))
    assert maes[True] < 0.5
    assert maes[False] > 2.0 * maes[True], maes


def test_uniform_ground_gives_no_confident_answers_and_is_reported_featureless(gsoe_config, camera):
    renderer = CameraRenderer(camera, GroundWorld.from_name("uniform_grass", seed=1))
    flight = ScriptedFlight([Segment(2.0)], tas_m_s=20.0, height_m=100.0)
    run = fly_optical(flight, gsoe_config, camera, renderer)
    assert not any(s.valid for s in run.steps if not s.new_cycle)
    # every base is featureless, so no cycle runs; a base is tried every featureless_retry_s (0.1 s: 3 frames)
    frames_per_try = math.ceil(gsoe_config.cycle.featureless_retry_s * 30.0 - 1e-9)
    assert abs(run.featureless_bases - run.frames / frames_per_try) <= 1.0, (run.featureless_bases, run.frames)
    every = dataclasses.replace(gsoe_config, cycle=dataclasses.replace(gsoe_config.cycle, featureless_retry_s=0.0))
    run0 = fly_optical(flight, every, camera, renderer)
    assert run0.featureless_bases == run0.frames and not run0.steps


def test_featureless_base_starts_no_cycle_and_texture_is_retried_after_the_interval(gsoe_config, camera):
    """Ten frames of flat ground, then texture: bases are tried at frames 0, 3, 6, 9 (every 0.1 s at 30 Hz) and
    none starts a cycle; the textured ground starts one at frame 12, the first try after frame 9's."""
    est = GsoeEstimator(gsoe_config, camera)
    w, h = camera.size_px
    flat = np.full((h, w), 120, np.uint8)
    textured = np.random.default_rng(3).integers(0, 256, (h, w), dtype=np.uint8)
    first_cycle = None
    for k, t_us, samples in still_frames(16):
        for att, imu in samples:
            est.push_imu(imu)
            est.push_attitude(att)
        steps = est.process_frame(t_us, flat if k < 10 else textured, 100.0)
        if k < 10:
            assert steps == [] and est.featureless, k
        if first_cycle is None and any(s.new_cycle for s in steps):
            first_cycle = k
    assert est.n_featureless_bases == 4
    assert first_cycle == 12 and not est.featureless


@pytest.mark.parametrize("known", [True, False])
def test_ahrs_latency_is_removed_from_the_base_heading(gsoe_config, camera, known):
    """An AHRS 80 ms late labels a cycle in a 20 deg/s turn 1.6 deg off; the estimator takes the latency out
    (given, or estimated from the gyro over alternating turns), so the base heading matches the truth's."""
    latency_s = 0.08
    turn = math.radians(20.0)
    flight = ScriptedFlight([Segment(1.0)] + [Segment(2.5, turn if k % 2 else -turn) for k in range(12)],
                            tas_m_s=18.0, height_m=100.0, ramp_s=0.5)
    est = GsoeEstimator(gsoe_config, camera, ahrs_latency_s=latency_s if known else None)
    w, h = camera.size_px
    image = np.random.default_rng(3).integers(0, 256, (h, w), dtype=np.uint8)  # the heading test needs no scene
    t_imu, t_att, t_frame = 0.0, 0.0, 0.6
    steps = []
    while t_frame < flight.duration_s - 0.1:
        while t_imu <= t_frame + 1e-9:
            tr = flight.truth(t_imu)
            est.push_imu(ImuSample(int(round(t_imu * 1e6)), tr.rates_b_rad_s, tr.accel_b_m_s2))
            if t_imu >= t_att - 1e-9:  # the 50 Hz AHRS reports the attitude of latency_s ago
                late = flight.truth(max(0.0, t_imu - latency_s))
                est.push_attitude(AttitudeSample(int(round(t_imu * 1e6)), late.roll_rad, late.pitch_rad, late.yaw_rad))
                t_att += 0.02
            t_imu += 1.0 / 300.0
        steps += [s for s in est.process_frame(int(round(t_frame * 1e6)), image, 100.0) if s.new_cycle]
        t_frame += 1.0 / 30.0
    late_steps = [s for s in steps if s.base_t_us > 20e6]
    assert len(late_steps) >= 10
    err = [abs(math.degrees(angle_diff(s.base_yaw_rad, flight.truth(s.base_t_us / 1e6).yaw_rad))) for s in late_steps]
    raw = [abs(math.degrees(angle_diff(flight.truth(s.base_t_us / 1e6 - latency_s).yaw_rad,
                                       flight.truth(s.base_t_us / 1e6).yaw_rad))) for s in late_steps]
    assert np.mean(raw) > 0.7
    assert np.mean(err) < 0.1, (np.mean(err), est.buffer.ahrs_latency_s)
    assert abs(est.buffer.ahrs_latency_s - latency_s) < (1e-9 if known else 0.005)
