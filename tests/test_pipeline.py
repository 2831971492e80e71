"""The one navigation pipeline: EKF start policy, frame hold, validity with the estimate's age, GNSS withheld,
heights from the ground level, the log streams.  The truth is a straight, level flight at constant velocity in still
air (analytic: position = v t, level attitude along the course, specific force -g)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from common.config import ConfigError
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
from fusion.config import ekf_config_from_raw
from pipeline.config import load_gsoe_config
from pipeline.navpipeline import NavPipeline, PipelineConfig, pipeline_config_from_raw

VEL_NE_M_S = np.array([15.0, 10.0])
HEIGHT_M = 120.0
IMU_HZ = 100
US = 1_000_000


class Flight:
    """Feeds a pipeline the analytic flight's samples: IMU and attitude at 100 Hz, airspeed and baro at 10 Hz,
    GNSS at 5 Hz (optional), stamped on one clock."""

    def __init__(self, pipe: NavPipeline, gnss: bool = True, ground_alt_m: float = 0.0) -> None:
        self.pipe = pipe
        self.gnss = gnss
        self.ground_alt_m = ground_alt_m
        self.k = 0
        self.yaw = math.atan2(VEL_NE_M_S[1], VEL_NE_M_S[0])

    def t_us(self, k: int) -> int:
        return k * US // IMU_HZ

    def fix(self, t_us: int) -> GnssSample:
        t = t_us / US
        return GnssSample(t_us, np.array([*(VEL_NE_M_S * t), -HEIGHT_M]), np.array([*VEL_NE_M_S, 0.0]), True, 12,
                          h_acc_m=1.0, v_acc_m_s=0.2)

    def run(self, seconds: float, imu: bool = True) -> None:
        for _ in range(round(seconds * IMU_HZ)):
            self.k += 1
            t_us = self.t_us(self.k)
            if imu:
                self.pipe.on_imu(ImuSample(t_us, np.zeros(3), np.array([0.0, 0.0, -9.80665])))
                self.pipe.on_attitude(AttitudeSample(t_us, 0.0, 0.0, self.yaw))
            else:
                self.pipe.poll(t_us)
            if self.k % 10 == 0:
                self.pipe.on_airspeed(AirspeedSample(t_us, float(np.hypot(*VEL_NE_M_S))))
                self.pipe.on_baro(BaroSample(t_us, self.ground_alt_m + HEIGHT_M))
            if self.gnss and self.k % 20 == 0:
                self.pipe.on_gnss(self.fix(t_us))


def make(gsoe_config: Any, camera: Any, sink: Any = None, **pcfg: Any) -> NavPipeline:
    """A pipeline with the default EKF, except that a straight flight's drift may be valid: without turns the
    heading's bias is not observable and the drift sigma stays above the default gate."""
    raw = load_gsoe_config()[1]
    ekf = {**raw.get("ekf", {}), "valid_drift_sigma_max_deg": 30.0}
    return NavPipeline(gsoe_config, ekf_config_from_raw(ekf), PipelineConfig(**pcfg), camera, sink=sink)


def test_ekf_starts_at_the_first_usable_fix_once_attitude_is_known(gsoe_config, camera):
    pipe = make(gsoe_config, camera)
    f = Flight(pipe)
    pipe.on_gnss(f.fix(0))                       # no attitude yet: not a start
    assert pipe.ekf is None and pipe.estimate() is None
    f.run(0.5)
    assert pipe.ekf is not None and pipe.status.ekf_started == "the first GNSS fix"
    assert pipe.status.ekf_start_t_us == f.t_us(20)
    f.run(20.0)
    e = pipe.estimate()
    assert e is not None and e.valid, e.invalid_reason
    np.testing.assert_allclose(e.vel_ned_m_s[:2], VEL_NE_M_S, atol=0.3)
    np.testing.assert_allclose(e.pos_ne_m, VEL_NE_M_S * f.t_us(f.k) / US, atol=5.0)


@pytest.mark.parametrize("policy", ["gnss_or_air_data", "gnss"])
def test_without_a_fix_the_ekf_starts_from_air_data_only_if_configured(gsoe_config, camera, policy):
    """Heights are the baro's above the ground level the source gives (500 m pressure altitude here)."""
    pipe = make(gsoe_config, camera, ekf_start=policy, air_data_start_wait_s=2.0)
    pipe.on_ground_level(500.0)
    f = Flight(pipe, gnss=False, ground_alt_m=500.0)
    f.run(1.5)
    assert pipe.ekf is None
    f.run(1.0)
    if policy == "gnss":
        assert pipe.ekf is None and "GNSS" in pipe.why_no_estimate()
        return
    assert pipe.status.ekf_started == "air data (no GNSS fix)"
    e = pipe.estimate()
    assert e is not None
    # started at the origin, flown since at the ground velocity
    np.testing.assert_allclose(e.pos_ne_m, VEL_NE_M_S * (e.t_us - pipe.status.ekf_start_t_us) / US, atol=1.0)
    assert abs(e.height_m - HEIGHT_M) < 2.0
    np.testing.assert_allclose(e.vel_ned_m_s[:2], VEL_NE_M_S, atol=0.5)   # TAS along the heading, no wind


def test_estimate_is_invalid_when_stale_and_valid_again_with_data(gsoe_config, camera):
    pipe = make(gsoe_config, camera, max_estimate_age_s=0.5)
    f = Flight(pipe)
    f.run(20.0)
    e = pipe.estimate()
    assert e is not None and e.valid, e.invalid_reason
    f.run(1.0, imu=False)                        # the clock goes on, no IMU: the estimate ages
    e = pipe.estimate()
    assert e is not None and not e.valid and "stale" in e.invalid_reason
    f.run(3.0)
    e = pipe.estimate()
    assert e is not None and e.valid, e.invalid_reason


def test_a_frame_waits_for_attitude_then_is_processed_late_without_it(gsoe_config, camera):
    pipe = make(gsoe_config, camera, attitude_wait_s=0.05)
    f = Flight(pipe)
    f.run(1.0)
    w, h = camera.size_px
    img = np.random.default_rng(3).integers(0, 256, (h, w), dtype=np.uint8)
    t_frame = f.t_us(f.k) + 5_000                # 5 ms after the newest samples
    pipe.on_frame(t_frame, img)
    assert pipe.frames_pending == 1 and pipe.drain() == []
    f.run(0.01)                                   # samples reach the exposure: processed, not late
    res = pipe.drain()
    assert [r.t_us for r in res] == [t_frame] and pipe.status.frames_late == 0
    t2 = f.t_us(f.k) + 5_000
    pipe.on_frame(t2, img)
    pipe.poll(t2 + 40_000)                        # no attitude: still waiting
    assert pipe.frames_pending == 1
    pipe.poll(t2 + 50_000)                        # the wait is over: processed without attitude covering it
    assert pipe.frames_pending == 0 and pipe.status.frames_late == 1
    pipe.on_frame(t2 + 2 * US, img)               # stamped far ahead of every sample: refused
    assert pipe.frames_pending == 0 and pipe.status.errors["frame stamped ahead of the samples"] == 1


def test_withheld_fixes_are_logged_not_fused_and_the_streams_have_their_columns(gsoe_config, camera):
    rows: dict[str, list[dict[str, Any]]] = {}
    pipe = make(gsoe_config, camera, sink=lambda s, r: rows.setdefault(s, []).append(r))
    f = Flight(pipe)
    f.run(5.0)
    pipe.gnss_enabled = False
    f.run(2.0)
    used = pipe.status.gnss_used                  # the first fix started the EKF; the others were fused
    assert pipe.aid_status()["gnss_pos"].n_fused == used - 1 == 24
    assert pipe.status.gnss_withheld == 10
    assert [r["fused"] for r in rows["gnss"][-10:]] == [False] * 10 and rows["gnss"][-11]["fused"]
    for stream in ("imu", "attitude", "airspeed", "baro", "gnss", "ekf", "aid_status"):
        assert rows[stream] and all(list(r) == list(rows[stream][0]) for r in rows[stream]), stream
        assert next(iter(rows[stream][0])) == "t_us" or stream == "aid_status"
    assert rows["baro"][0]["height_m"] == pytest.approx(HEIGHT_M)


def test_pipeline_config_profiles_and_ranges():
    raw = {"pipeline": {"attitude_wait_s": 0.1, "profiles": {"slow": {"attitude_wait_s": 0.5}}}}
    assert pipeline_config_from_raw(raw).attitude_wait_s == 0.1
    assert pipeline_config_from_raw(raw, "slow").attitude_wait_s == 0.5
    with pytest.raises(ConfigError, match="no profile 'fast'"):
        pipeline_config_from_raw(raw, "fast")
    with pytest.raises(ConfigError, match="pipeline.attitude_wait_s"):
        pipeline_config_from_raw({"pipeline": {"attitude_wait_s": -1.0}})
    with pytest.raises(ConfigError, match="pipeline.attitude_wai"):
        pipeline_config_from_raw({"pipeline": {"attitude_wai": 0.1}})
