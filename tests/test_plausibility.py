"""Plausibility of IMU and attitude samples (pipeline.plausibility): a clean, turning flight passes untouched;
isolated in-range spikes of specific force and rate, an AHRS jump and a gyro that disagrees with the AHRS are
rejected with their reason; a genuine lasting step is accepted after it is confirmed; and in the pipeline one
spoofed SCALED_IMU-like sample (15 g, 30 rad/s per axis, inside the link's ranges) no longer moves the velocity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.samples import AttitudeSample, ImuSample
from pipeline.navpipeline import PipelineConfig
from pipeline.plausibility import SamplePlausibility, ahrs_body_rate, euler_rates_to_body
from tests.test_pipeline import Flight, make

G = 9.80665
IMU_HZ = 240
ATT_EVERY = 4  # attitude at 60 Hz
US = 1_000_000
TAS_M_S = 20.0


def turning_flight(seconds: float, rng: np.random.Generator) -> list[ImuSample | AttitudeSample]:
    """A coordinated flight whose turn rate swings between +-0.3 rad/s (banks up to 31 deg, a roll rate of
    0.4 rad/s), with IMU noise (0.05 m/s^2 plus vibration 0.3 m/s^2, 0.005 rad/s) and AHRS noise (0.1 deg); samples
    in arrival order (an attitude sample after the IMU sample of its stamp)."""
    out: list[ImuSample | AttitudeSample] = []
    n = round(seconds * IMU_HZ)
    for k in range(n):
        t = k / IMU_HZ
        w = 2 * math.pi / 20.0
        yaw_rate = 0.3 * math.sin(w * t)
        yaw = 0.3 * (1 - math.cos(w * t)) / w
        roll = math.atan(TAS_M_S * yaw_rate / G)
        droll = (TAS_M_S * 0.3 * w * math.cos(w * t) / G) * math.cos(roll) ** 2
        gyro = np.array(euler_rates_to_body(roll, 0.0, droll, 0.0, yaw_rate)) + rng.normal(0.0, 0.005, 3)
        acc = np.array([0.0, 0.0, -G / math.cos(roll)]) + rng.normal(0.0, 0.05, 3) + rng.normal(0.0, 0.3, 3)
        t_us = k * US // IMU_HZ
        out.append(ImuSample(t_us, gyro, acc))
        if k % ATT_EVERY == 0:
            e = rng.normal(0.0, math.radians(0.1), 3)
            out.append(AttitudeSample(t_us, roll + e[0], e[1], yaw + e[2]))
    return out


def feed(p: SamplePlausibility, samples: list[ImuSample | AttitudeSample]) -> list[bool]:
    return [p.imu(s) if isinstance(s, ImuSample) else p.attitude(s) for s in samples]


def test_body_rates_of_the_ahrs_match_the_euler_kinematics():
    a = AttitudeSample(0, 0.3, 0.1, 3.1)
    b = AttitudeSample(20_000, 0.31, 0.1, -3.13)              # yaw wraps through +-pi: +0.053 rad in 20 ms
    p, q, r = ahrs_body_rate(a, b) or (math.nan,) * 3
    droll, dyaw = 0.5, (2 * math.pi - 6.23) / 0.02
    roll = 0.305
    assert p == pytest.approx(droll - dyaw * math.sin(0.1))
    assert q == pytest.approx(dyaw * math.sin(roll) * math.cos(0.1))
    assert r == pytest.approx(dyaw * math.cos(roll) * math.cos(0.1))
    assert ahrs_body_rate(b, a) is None


def test_a_clean_turning_flight_is_never_rejected():
    p = SamplePlausibility(PipelineConfig())
    ok = feed(p, turning_flight(60.0, np.random.default_rng(1)))
    assert all(ok) and p.status.rejected == {} and p.status.reanchored == {}
    assert p.status.accepted == {"imu": 60 * IMU_HZ, "attitude": 60 * IMU_HZ // ATT_EVERY}


@pytest.mark.parametrize("gyro,accel,reason", [
    ((30.0, 30.0, 30.0), (150.0, 150.0, 150.0), "imu: specific force jump"),   # the spoofed SCALED_IMU
    ((0.0, 0.0, 0.0), (0.0, 0.0, 25.0), "imu: specific force jump"),            # 2.5 g on one axis
    ((0.0, 6.0, 0.0), (0.0, 0.0, -G), "imu: rate jump"),
])
def test_an_isolated_imu_spike_is_rejected_and_the_stream_goes_on(gyro, accel, reason):
    samples = turning_flight(5.0, np.random.default_rng(2))
    i = next(i for i, s in enumerate(samples) if isinstance(s, ImuSample) and s.t_us >= 2 * US)
    t = samples[i].t_us
    samples.insert(i + 1, ImuSample(t + 1000, np.array(gyro), np.array(accel)))   # between two genuine samples
    p = SamplePlausibility(PipelineConfig())
    ok = feed(p, samples)
    assert ok.count(False) == 1 and not ok[i + 1]
    assert p.status.rejected == {reason: 1}
    assert p.status.last_rejected_t_us == t + 1000


def test_a_gyro_that_disagrees_with_the_ahrs_rate_is_rejected():
    """A rate offset of 3.5 rad/s that creeps in below the jump threshold is caught by the AHRS comparison."""
    cfg = PipelineConfig(imu_max_gyro_step_rad_s=0.0)                   # the jump test off: only the AHRS test
    samples = turning_flight(5.0, np.random.default_rng(3))
    i = next(i for i, s in enumerate(samples) if isinstance(s, ImuSample) and s.t_us >= 2 * US)
    s = samples[i]
    assert isinstance(s, ImuSample)
    samples[i] = ImuSample(s.t_us, s.gyro_b_rad_s + np.array([3.5, 0.0, 0.0]), s.accel_b_m_s2)
    p = SamplePlausibility(cfg)
    ok = feed(p, samples)
    assert not ok[i] and ok.count(False) == 1
    assert p.status.rejected == {"imu: gyro disagrees with the AHRS rate": 1}


def test_an_ahrs_jump_is_rejected_and_the_next_attitude_accepted():
    samples = turning_flight(5.0, np.random.default_rng(4))
    idx = [i for i, s in enumerate(samples) if isinstance(s, AttitudeSample) and s.t_us >= 2 * US]
    s = samples[idx[0]]
    assert isinstance(s, AttitudeSample)
    samples[idx[0]] = AttitudeSample(s.t_us, s.roll_rad + 0.5, s.pitch_rad, s.yaw_rad)   # 0.5 rad in 17 ms
    p = SamplePlausibility(PipelineConfig())
    ok = feed(p, samples)
    assert not ok[idx[0]] and ok[idx[1]] and ok.count(False) == 1
    assert p.status.rejected == {"attitude: attitude rate disagrees with the gyro": 1}


def test_a_lasting_step_is_accepted_once_confirmed():
    """The specific force steps by 3 g and stays (a catapult): the first two samples of the step are rejected, the
    third confirms it and everything after is accepted against the new reference."""
    cfg = PipelineConfig()
    p = SamplePlausibility(cfg)
    ok = [p.imu(ImuSample(k * 4000, np.zeros(3), np.array([0.0, 0.0, -G]))) for k in range(1, 50)]
    ok += [p.imu(ImuSample(k * 4000, np.zeros(3), np.array([30.0, 0.0, -G]))) for k in range(50, 100)]
    assert all(ok[:49]) and ok[49:52] == [False, False, True] and all(ok[52:])
    assert p.status.rejected == {"imu: specific force jump": cfg.plausibility_confirm_samples - 1}
    assert p.status.reanchored == {"imu": 1}


def test_scattered_garbage_is_never_confirmed():
    """Consecutive rejected samples that do not agree with each other (a burst of random values) stay rejected."""
    rng = np.random.default_rng(5)
    p = SamplePlausibility(PipelineConfig())
    assert p.imu(ImuSample(4000, np.zeros(3), np.array([0.0, 0.0, -G])))
    bad = [p.imu(ImuSample(4000 * (k + 2), rng.uniform(-30, 30, 3), rng.uniform(-150, 150, 3))) for k in range(200)]
    assert not any(bad) and p.status.reanchored == {}


def test_stamps_that_do_not_increase_are_rejected_and_a_gap_restarts_the_comparison():
    p = SamplePlausibility(PipelineConfig(plausibility_max_gap_s=0.5))
    assert p.imu(ImuSample(1_000_000, np.zeros(3), np.array([0.0, 0.0, -G])))
    assert not p.imu(ImuSample(1_000_000, np.zeros(3), np.array([0.0, 0.0, -G])))
    assert p.attitude(AttitudeSample(1_000_000, 0.0, 0.0, 0.0))
    assert not p.attitude(AttitudeSample(900_000, 0.0, 0.0, 0.0))
    assert p.status.rejected == {"imu: stamp not increasing": 1, "attitude: stamp not increasing": 1}
    # 0.6 s later (a link loss) anything in range starts afresh
    assert p.imu(ImuSample(1_600_001, np.array([0.0, 2.0, 0.0]), np.array([0.0, 0.0, -3 * G])))


def test_thresholds_of_zero_switch_the_tests_off():
    p = SamplePlausibility(PipelineConfig(imu_max_accel_step_m_s2=0.0, imu_max_gyro_step_rad_s=0.0,
                                          gyro_ahrs_max_diff_rad_s=0.0))
    assert p.imu(ImuSample(4000, np.zeros(3), np.array([0.0, 0.0, -G])))
    assert p.imu(ImuSample(8000, np.full(3, 30.0), np.full(3, 150.0)))
    assert p.attitude(AttitudeSample(8000, 0.0, 0.0, 0.0)) and p.attitude(AttitudeSample(12000, 1.0, 0.0, 0.0))
    assert p.status.rejected == {}


@pytest.mark.parametrize("checks", [True, False], ids=["plausibility on", "plausibility off"])
def test_one_spoofed_imu_sample_in_range_does_not_move_the_velocity(gsoe_config, camera, checks):
    """Issue 23, item 2: one SCALED_IMU-like sample of 15.3 g and 30 rad/s per axis (inside the link's 16 g and
    35 rad/s) between genuine samples.  Without the plausibility tests it moves the EKF's velocity by metres per
    second; with them it is rejected, logged, and the velocity stays within 0.1 m/s."""
    records: list[tuple[str, dict]] = []
    off = {} if checks else {"imu_max_accel_step_m_s2": 0.0, "imu_max_gyro_step_rad_s": 0.0,
                             "gyro_ahrs_max_diff_rad_s": 0.0}
    pipe = make(gsoe_config, camera, sink=lambda stream, r: records.append((stream, r)), **off)
    f = Flight(pipe)
    f.run(20.0)
    t_us = f.t_us(f.k) + 5000
    pipe.on_imu(ImuSample(t_us, np.full(3, 30.0), np.full(3, 15.3 * G)))
    f.run(0.3)
    e = pipe.estimate()
    assert e is not None
    err = float(np.max(np.abs(np.asarray(e.vel_ned_m_s[:2]) - [15.0, 10.0])))
    rejected = [r for s, r in records if s == "samples_rejected"]
    if checks:
        assert err < 0.1, err
        assert pipe.plausibility.status.rejected == {"imu: specific force jump": 1}
        assert rejected == [{"t_us": t_us, "kind": "imu", "reason": "specific force jump",
                             "excess": pytest.approx(15.3 * G + G)}]
    else:
        assert err > 1.0, err                     # the harm the tests prevent
        assert not rejected


def test_without_a_gyro_an_ahrs_jump_is_judged_against_the_ahrs_own_rate():
    """The IMU stream lost (a link that dropped it): a jumped attitude still cannot pass."""
    p = SamplePlausibility(PipelineConfig())
    ok = [p.attitude(AttitudeSample(k * 20_000, 0.01 * k, 0.0, 0.5)) for k in range(1, 20)]   # 0.5 rad/s roll
    ok.append(p.attitude(AttitudeSample(20 * 20_000, 0.2 + 0.6, 0.0, 0.5)))                   # +0.6 rad in 20 ms
    ok.append(p.attitude(AttitudeSample(21 * 20_000, 0.21, 0.0, 0.5)))
    assert all(ok[:19]) and ok[19:] == [False, True]
    assert p.status.rejected == {"attitude: attitude rate jump (no gyro to compare)": 1}


def test_a_burst_of_spoofed_attitudes_never_takes_over():
    """Three spoofed attitudes (random jumps) between every two genuine ones, for 5 s: consecutive rejections, but
    they never agree with each other, so none is accepted and every genuine sample is."""
    rng = np.random.default_rng(8)
    genuine = turning_flight(8.0, np.random.default_rng(9))
    p = SamplePlausibility(PipelineConfig())
    spoofs_ok = []
    genuine_ok = []
    for s in genuine:
        if isinstance(s, ImuSample):
            p.imu(s)
            continue
        genuine_ok.append(p.attitude(s))
        if 2 * US <= s.t_us < 7 * US:
            for k in range(3):
                j = rng.uniform(0.2, 1.5) * rng.choice([-1.0, 1.0])
                axis = int(rng.integers(3))
                spoofs_ok.append(p.attitude(AttitudeSample(
                    s.t_us + 1000 * (k + 1), s.roll_rad + j * (axis == 0), s.pitch_rad + 0.5 * j * (axis == 1),
                    s.yaw_rad + j * (axis == 2))))
    assert not any(spoofs_ok) and len(spoofs_ok) == 3 * 5 * IMU_HZ // ATT_EVERY
    assert all(genuine_ok) and p.status.reanchored == {}


def test_a_lasting_ahrs_step_is_accepted_once_confirmed():
    """The AHRS re-converges: its yaw steps by 0.3 rad and stays.  Two samples are refused, the third confirms."""
    cfg = PipelineConfig()
    p = SamplePlausibility(cfg)
    for k in range(1, 50):
        assert p.imu(ImuSample(k * 20_000 - 1000, np.zeros(3), np.array([0.0, 0.0, -G])))
        assert p.attitude(AttitudeSample(k * 20_000, 0.0, 0.0, 1.0))
    ok = []
    for k in range(50, 60):
        p.imu(ImuSample(k * 20_000 - 1000, np.zeros(3), np.array([0.0, 0.0, -G])))
        ok.append(p.attitude(AttitudeSample(k * 20_000, 0.0, 0.0, 1.3)))
    assert ok == [False, False] + [True] * 8
    assert p.status.reanchored == {"attitude": 1}


def test_a_repeated_spoof_that_replaces_the_imu_stream_is_never_confirmed_and_locks_nothing_out():
    """The fuzz flight of seed 5: the issue's SCALED_IMU (15.3 g, 30 rad/s per axis) arrives five times in a row in
    place of the genuine samples (the link dropped those: same stamps).  The run agrees with itself but not with the
    AHRS, so it is never confirmed; the attitude and the genuine IMU samples after it are all accepted."""
    p = SamplePlausibility(PipelineConfig())
    accel, spoof_gyro, spoof_acc = np.array([0.0, 0.0, -G]), np.full(3, 30.0), np.full(3, 15.3 * G)
    imu_ok, att_ok = [], []
    for k in range(1, 60):
        t = k * 20_000
        spoofed = 20 <= k < 25
        imu_ok.append(p.imu(ImuSample(t - 1000, spoof_gyro if spoofed else np.zeros(3),
                                      spoof_acc if spoofed else accel)))
        att_ok.append(p.attitude(AttitudeSample(t, 0.0, 0.0, 0.5)))
    assert imu_ok[19:24] == [False] * 5 and all(imu_ok[:19]) and all(imu_ok[24:])
    assert all(att_ok) and p.status.reanchored == {}
