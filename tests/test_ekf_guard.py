"""The EKF divergence guard (pipeline.guard, issue 23): a filter pushed into divergence by in-range IMU spikes that
pass the plausibility tests (switched off here) is detected, nothing it says is valid while it is diverged, it is
restarted from GNSS (or, with GNSS withheld, from air data at the last healthy position and wind), and within 5 s of
clean data its estimate is valid and close to the truth again; the EKF's own reset of position and velocity to
GNSS after continuous rejection is reported; a clean flight never trips the guard.

The truth is test_pipeline's analytic straight, level flight (position = v t, level attitude along the course,
specific force -g, still air), with optical steps synthesised from it (the template's migration at the base
snapshot's ground sample distance, no noise), so the estimate is checked against numbers known exactly.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, GsoeStep, ImuSample, MatchQuality
from pipeline.guard import DivergenceGuard
from pipeline.navpipeline import NavPipeline, PipelineConfig
from tests.test_pipeline import HEIGHT_M, US, VEL_NE_M_S, Flight, make

G = 9.80665
FOCAL_PX = 300.0
CYCLE_FRAMES = 10
FRAME_EVERY = 10               # IMU samples per camera frame (10 Hz)
RECOVERY_S = 5.0
#: the plausibility tests off: the spikes must reach the EKF
NO_PLAUSIBILITY = {"imu_max_accel_step_m_s2": 0.0, "imu_max_gyro_step_rad_s": 0.0, "gyro_ahrs_max_diff_rad_s": 0.0}


class GuardedFlight(Flight):
    """test_pipeline's flight plus optical steps from the truth, an IMU whose specific force can be replaced
    (``spike``: t_us -> specific force or None), fixes that can be moved (``fix_offset``), and, at every IMU
    sample, the estimate checked: what is valid must be within ``valid_tol`` of the truth."""

    def __init__(self, pipe: NavPipeline, gnss: bool = True) -> None:
        super().__init__(pipe, gnss)
        self.spike: Any = lambda t_us: None
        self.fix_offset = (np.zeros(3), np.zeros(3))
        self.base_k: int | None = None
        self.cycle = 0
        self.worst_valid_vel_err = 0.0
        self.wrong_valid_s = 0.0       # how long the estimate was valid with a velocity off by more than 1 m/s
        self.valid_at: list[tuple[float, bool]] = []

    def truth_pos(self, t_us: int) -> np.ndarray:
        return np.array([*(VEL_NE_M_S * t_us / US), -HEIGHT_M])

    def fix(self, t_us: int) -> GnssSample:
        dp, dv = self.fix_offset
        return GnssSample(t_us, self.truth_pos(t_us) + dp, np.array([*VEL_NE_M_S, 0.0]) + dv, True, 12,
                          h_acc_m=1.0, v_acc_m_s=0.2)

    def step(self, k: int) -> GsoeStep:
        """The template's migration since the cycle's base (cross track 0, along track the distance flown)."""
        assert self.base_k is not None
        t_us, base_us = self.t_us(k), self.t_us(self.base_k)
        gsd = HEIGHT_M / FOCAL_PX
        along_px = float(np.hypot(*VEL_NE_M_S)) * (t_us - base_us) / US / gsd
        n = (k - self.base_k) // FRAME_EVERY
        q = MatchQuality(psr=8.0 if n else math.inf, texture_std=30.0, ssd_per_px=10.0, valid=True)
        return GsoeStep(t_us=t_us, base_t_us=base_us, cycle_id=self.cycle, step=n, dx_px=0.0, dy_px=along_px,
                        base_yaw_rad=self.yaw, yaw_rad=self.yaw, gsd_m_px=gsd, height_agl_m=HEIGHT_M,
                        focal_px=FOCAL_PX, rel_rot_rad=0.0, quality=q, valid=True, new_cycle=n == 0)

    def run(self, seconds: float, imu: bool = True) -> None:
        p = self.pipe
        for _ in range(round(seconds * 100)):
            self.k += 1
            k, t_us = self.k, self.t_us(self.k)
            f = self.spike(t_us)
            p.on_imu(ImuSample(t_us, np.zeros(3), np.array([0.0, 0.0, -G]) if f is None else np.asarray(f)))
            p.on_attitude(AttitudeSample(t_us, 0.0, 0.0, self.yaw))
            if k % 10 == 0:
                p.on_airspeed(AirspeedSample(t_us, float(np.hypot(*VEL_NE_M_S))))
                p.on_baro(BaroSample(t_us, HEIGHT_M))
            if self.gnss and k % 20 == 0:
                p.on_gnss(self.fix(t_us))
            if k % FRAME_EVERY == 0:
                steps = []
                if self.base_k is not None and k - self.base_k >= CYCLE_FRAMES * FRAME_EVERY:
                    steps.append(self.step(k))           # the cycle's last step; this frame is the next base
                    self.base_k, self.cycle = None, self.cycle + 1
                if self.base_k is None:
                    self.base_k = k
                steps.append(self.step(k))
                p.on_steps(steps)
            e = p.estimate()
            valid = e is not None and e.valid
            self.valid_at.append((t_us / US, valid))
            if valid:
                err = float(np.hypot(*(np.asarray(e.vel_ned_m_s[:2]) - VEL_NE_M_S)))
                self.worst_valid_vel_err = max(self.worst_valid_vel_err, err)
                self.wrong_valid_s += 0.01 * (err > 1.0)

    def valid_again_after(self, t0_s: float) -> float | None:
        """Seconds after ``t0_s`` until the estimate was last invalid (None: invalid at the end)."""
        after = [(t, v) for t, v in self.valid_at if t >= t0_s]
        if not after[-1][1]:
            return None
        last_bad = max((t for t, v in after if not v), default=t0_s)
        return last_bad - t0_s


def guarded(gsoe_config: Any, camera: Any, **pcfg: Any) -> tuple[NavPipeline, GuardedFlight, list[Any]]:
    rows: list[Any] = []
    pipe = make(gsoe_config, camera, sink=lambda s, r: rows.append((s, r)), **{**NO_PLAUSIBILITY, **pcfg})
    return pipe, GuardedFlight(pipe), rows


def spiked(fl: GuardedFlight, clean_s: float = 8.0, n: int = 6) -> float | None:
    """``n`` IMU samples from now with the issue's accepted spikes (155 m/s^2 forward and sideways), then
    ``clean_s`` of clean data; returns how long after the spikes the estimate was last invalid (None: to the end).
    The estimate is the one the guard judges: the wrong velocity (9.6 m/s off) must not be valid for long."""
    t0_us = fl.t_us(fl.k + 1)
    fl.spike = lambda t_us: (150.0, -120.0, -G) if t_us < t0_us + n * US // 100 else None
    fl.run(0.1)
    fl.spike = lambda t_us: None
    fl.run(clean_s)
    assert fl.wrong_valid_s <= 0.2, fl.wrong_valid_s
    return fl.valid_again_after(t0_us / US + 0.1)


def test_a_clean_flight_never_trips_the_guard_and_its_estimate_is_valid(gsoe_config, camera):
    pipe, fl, _ = guarded(gsoe_config, camera)
    fl.run(30.0)
    assert pipe.status.ekf_diverged == {} and pipe.status.ekf_resets == {} and pipe.drain_events() == []
    e = pipe.estimate()
    assert e is not None and e.valid, e.invalid_reason
    np.testing.assert_allclose(e.vel_ned_m_s[:2], VEL_NE_M_S, atol=0.2)
    assert fl.worst_valid_vel_err < 0.5


def test_imu_spikes_diverge_the_filter_which_is_restarted_from_gnss_and_valid_within_5_s(gsoe_config, camera):
    pipe, fl, rows = guarded(gsoe_config, camera)
    fl.run(20.0)
    assert pipe.estimate().valid
    back = spiked(fl)
    assert sum(pipe.status.ekf_diverged.values()) == 1, pipe.status
    assert pipe.status.ekf_resets == {"GNSS": 1}, pipe.status
    ev = pipe.drain_events()
    assert [x.kind for x in ev] == ["diverged", "reset"] and all(len(x.text) <= 50 for x in ev)
    assert ev[0].t_us < 21.5 * US and ev[1].t_us - ev[0].t_us < 0.5 * US
    assert [r["kind"] for s, r in rows if s == "ekf_events"] == ["diverged", "reset"]
    # the velocity 9.6 m/s off was valid only until the first refusals were seen (0.15 s here; spiked() checks),
    # not for the second until the divergence is declared, nor after it; valid again 1.6 s after the spikes
    assert back is not None and back < RECOVERY_S, back
    e = pipe.estimate()
    np.testing.assert_allclose(e.vel_ned_m_s[:2], VEL_NE_M_S, atol=0.3)
    np.testing.assert_allclose(e.pos_ne_m, fl.truth_pos(e.t_us)[:2], atol=5.0)


def test_with_gnss_withheld_the_filter_restarts_from_air_data_at_the_last_healthy_position(gsoe_config, camera):
    pipe, fl, _ = guarded(gsoe_config, camera)
    fl.run(20.0)
    pipe.gnss_enabled = False                  # the GNSS monitor says the fixes are not healthy
    fl.run(2.0)
    back = spiked(fl)
    assert pipe.status.ekf_resets == {"air data": 1}, pipe.status
    assert [x.kind for x in pipe.drain_events()] == ["diverged", "reset"]
    assert back is not None and back < RECOVERY_S, back
    e = pipe.estimate()
    np.testing.assert_allclose(e.vel_ned_m_s[:2], VEL_NE_M_S, atol=0.5)
    # placed at the last healthy estimate (before the spikes) and flown on the optical steps since
    np.testing.assert_allclose(e.pos_ne_m, fl.truth_pos(e.t_us)[:2], atol=10.0)


def test_a_spoofed_fix_after_a_divergence_is_not_what_the_filter_restarts_from(gsoe_config, camera):
    """While the filter is dropped the GNSS monitor has no estimate to judge fixes by: fixes whose velocity is 15 m/s
    off the air data (TAS along the heading plus the last healthy wind), arriving from the spikes on, are refused as
    restart points; the filter restarts from air data at the last healthy position, and once the fixes are right
    again it goes on with them."""
    pipe, fl, _ = guarded(gsoe_config, camera)
    fl.run(20.0)
    fl.fix_offset = (np.array([500.0, 0.0, 0.0]), np.array([0.0, 15.0, 0.0]))
    spiked(fl, clean_s=4.0)                   # (no valid velocity 1 m/s off: spiked() checks)
    assert pipe.status.restart_fixes_refused >= 5, pipe.status
    # with the fixes still "healthy" (no monitor here) the refused GNSS velocity drops the air-data filter again
    # (issue 23's rule); it is restarted from air data every time, never from the spoofer
    assert set(pipe.status.ekf_resets) == {"air data"}, pipe.status
    e = pipe.estimate()
    if e is not None:
        np.testing.assert_allclose(e.pos_ne_m, fl.truth_pos(e.t_us)[:2], atol=20.0)   # not the spoofer's 500 m
    fl.fix_offset = (np.zeros(3), np.zeros(3))
    fl.run(5.0)
    e = pipe.estimate()
    assert e is not None and e.valid, pipe.status
    np.testing.assert_allclose(e.pos_ne_m, fl.truth_pos(e.t_us)[:2], atol=5.0)
    np.testing.assert_allclose(e.vel_ned_m_s[:2], VEL_NE_M_S, atol=0.3)


def test_a_fix_far_from_a_filter_that_drifted_still_restarts_it(gsoe_config, camera):
    """The filter itself may be what went wrong (a biased optical scale carries it hundreds of metres off before the
    guard sees it): a fix 300 m from the last healthy estimate, with a velocity that fits the air data, restarts it."""
    pipe, fl, _ = guarded(gsoe_config, camera)
    fl.run(20.0)
    fl.fix_offset = (np.array([300.0, 0.0, 0.0]), np.zeros(3))    # the truth as the EKF sees it: 300 m off
    spiked(fl, clean_s=4.0)
    assert pipe.status.restart_fixes_refused == 0 and pipe.status.ekf_resets == {"GNSS": 1}, pipe.status


def test_a_genuine_fix_after_a_divergence_restarts_the_filter_even_after_a_long_drop(gsoe_config, camera):
    """The restart tolerance grows with the time since the last healthy estimate: fixes that come back 30 s into
    a drop (GNSS withheld, no air data start: ``ekf_start = "gnss"``) still restart the filter."""
    pipe, fl, _ = guarded(gsoe_config, camera, ekf_start="gnss")
    fl.run(20.0)
    fl.gnss = False
    spiked(fl, clean_s=30.0)
    assert pipe.estimate() is None or not pipe.estimate().valid
    fl.gnss = True
    fl.run(3.0)
    assert pipe.status.ekf_resets == {"GNSS": 1} and pipe.status.restart_fixes_refused == 0, pipe.status
    assert pipe.estimate().valid


@pytest.mark.parametrize("field,value,test", [
    ("vel_ned_m_s", (80.0, 0.0, 0.0), "ground speed"),
    ("vel_ned_m_s", (20.0, 0.0, -45.0), "vertical speed"),
    ("height_m", -3872.0, "height"),
    ("pos_ne_m", (math.nan, 0.0), "non-finite state"),
])
def test_the_bounds_name_what_is_beyond_the_airframe(gsoe_config, camera, field, value, test):
    pipe, fl, _ = guarded(gsoe_config, camera)
    fl.run(5.0)
    e = pipe.estimate()
    g = DivergenceGuard(PipelineConfig())
    assert g.bounds(e) == ""
    bad = dataclasses.replace(e, **{field: np.array(value) if isinstance(value, tuple) else value})
    assert g.bounds(bad).startswith(test)
    assert DivergenceGuard(PipelineConfig(guard_max_ground_speed_m_s=0.0, guard_max_vertical_speed_m_s=0.0,
                                          guard_max_height_m=0.0)).bounds(bad) == ("" if test != "non-finite state"
                                                                                  else test)


def test_fixes_that_stay_off_the_estimate_reset_its_position_and_velocity_and_say_so(gsoe_config, camera):
    """The receiver is right and the EKF wrong (here: the fixes jump 300 m and 4 m/s and stay there; the guard's
    aid test off): after ``[ekf] gnss_reset_after_s`` of rejection the position and the velocity are the fixes',
    reported as resets."""
    pipe, fl, rows = guarded(gsoe_config, camera, guard_all_fail_s=0.0)
    fl.run(20.0)
    dp, dv = np.array([300.0, -200.0, 0.0]), np.array([0.0, 4.0, 0.0])
    fl.fix_offset = (dp, dv)
    fl.run(6.0)
    assert pipe.status.ekf_diverged == {}
    assert pipe.status.ekf_resets.get("gnss_pos") == 1 and pipe.status.ekf_resets.get("gnss_vel") == 1
    texts = [x.text for x in pipe.drain_events()]
    assert "GSOE EKF position reset to GNSS" in texts and "GSOE EKF velocity reset to GNSS" in texts
    assert [r["reason"].split(" (")[0] for s, r in rows if s == "ekf_events"] == [
        "EKF position reset to GNSS", "EKF velocity reset to GNSS"]
    e = pipe.estimate()
    np.testing.assert_allclose(e.pos_ne_m, fl.truth_pos(e.t_us)[:2] + dp[:2], atol=10.0)


def test_a_refused_healthy_gnss_velocity_makes_the_estimate_suspect_then_restarts_the_filter(gsoe_config, camera):
    """With the guard on, the GNSS velocity refused (here: the fixes' velocity 4 m/s off, the optical steps and the
    airspeed agreeing with the state) makes the estimate invalid at once and restarts the filter from GNSS after
    ``guard_all_fail_s``, well before the EKF's own 5 s reset."""
    pipe, fl, _ = guarded(gsoe_config, camera)
    fl.run(20.0)
    fl.fix_offset = (np.zeros(3), np.array([0.0, 4.0, 0.0]))
    fl.run(0.5)
    e = pipe.estimate()
    assert not e.valid and e.invalid_reason == "EKF suspect: GNSS velocity refused", e.invalid_reason
    fl.run(1.5)
    assert pipe.status.ekf_diverged == {"GNSS velocity refused": 1} and pipe.status.ekf_resets == {"GNSS": 1}
    ev = pipe.drain_events()
    assert ev[0].t_us < 21.5 * US and ev[0].text.startswith("GSOE EKF diverged: GNSS velocity refused")


class CompanionFeed:
    """The flight's samples through the companion's estimator (GNSS monitor + pipeline), as the link gives them:
    fixes with their altitude above mean sea level (home at 0 m), the home report after the first baro sample."""

    def __init__(self, est: Any) -> None:
        self.est = est
        self.home_sent = False

    def __getattr__(self, name: str) -> Any:        # on_imu, on_attitude, on_airspeed, on_steps, estimate
        if name in ("on_imu", "on_attitude", "on_airspeed"):
            return self.est.feed
        return getattr(self.est.pipe, name)

    def on_baro(self, s: Any) -> None:
        from nav.link import HomeReading
        self.est.feed(s)
        if not self.home_sent:
            self.est.feed(HomeReading(s.t_us, HEIGHT_M, HEIGHT_M))
            self.home_sent = True

    def on_gnss(self, s: GnssSample) -> None:
        self.est.feed(dataclasses.replace(s, alt_msl_m=float(-s.pos_ned_m[2])))


def test_a_healthy_receiver_that_disagrees_with_the_ekf_resets_it_through_the_companion(gsoe_config, camera):
    """The issue's late start: no fix for the first 14 s, so the EKF starts from air data at the origin, 180 m from
    the truth; the receiver's consistent track is never a jump, the monitor passes it after its recovery wait, the
    EKF refuses it for ``gnss_reset_after_s`` and then resets its position to it, and the companion announces it."""
    from nav.companion import CompanionConfig, CompanionEstimator
    from pipeline.config import load_gsoe_config

    raw = load_gsoe_config()[1]
    raw = {**raw, "ekf": {**raw["ekf"], "valid_drift_sigma_max_deg": 30.0}}
    est = CompanionEstimator(gsoe_config, camera, raw, CompanionConfig())
    fl = GuardedFlight(est.pipe, gnss=False)
    fl.pipe = CompanionFeed(est)              # type: ignore[assignment]
    fl.run(14.0)
    assert est.pipe.status.ekf_started == "air data (no GNSS fix)"
    e = est.pipe.estimate()
    assert np.hypot(*(e.pos_ne_m - fl.truth_pos(e.t_us)[:2])) > 150.0
    fl.gnss = True
    fl.run(14.0)
    assert est.monitor.jumps == 0 and est.monitor.state.name == "GNSS_OK"
    assert est.pipe.status.ekf_resets.get("gnss_pos") == 1, est.pipe.status
    assert est.pipe.status.ekf_diverged == {}
    e = est.pipe.estimate()
    assert e.valid, e.invalid_reason
    np.testing.assert_allclose(e.pos_ne_m, fl.truth_pos(e.t_us)[:2], atol=5.0)
    np.testing.assert_allclose(e.vel_ned_m_s[:2], VEL_NE_M_S, atol=0.3)

    # what the companion makes of the pipeline's events: a line in events.csv and a STATUSTEXT each
    from types import SimpleNamespace

    from nav.companion import Companion
    app = Companion.__new__(Companion)
    sent: list[tuple[str, str]] = []
    logged: list[tuple[str, str]] = []
    app.link = SimpleNamespace(send_statustext=lambda text, severity: sent.append((text, severity)))
    app._event = lambda kind, detail, level, t_us: logged.append((kind, detail))  # type: ignore[method-assign]
    app.pipe = est.pipe
    est.pipe.drain()                            # the frames' results (outputs, guidance) are not this test's
    app._handle_results()
    assert sent == [("GSOE EKF position reset to GNSS", "warning")]
    assert len(logged) == 1 and logged[0][0] == "ekf" and logged[0][1].startswith("reset: EKF position reset")


def test_replay_metrics_count_the_samples_the_pipeline_rejected(tmp_path):
    """``gsoe replay``'s metrics.json carries the plausibility rejections by kind and reason, the same counts as its
    ``samples_rejected`` log (a rate-jump threshold of 0.05 rad/s makes some: the log's own has none)."""
    import json

    from common.configfile import DEFAULT_CONFIG
    from common.logio import read_log
    from nav.replay import run_replay
    from tests.conftest import shared_data
    from tests.test_replay import SHORT

    text = DEFAULT_CONFIG.read_text().replace("imu_max_gyro_step_rad_s = 3.0", "imu_max_gyro_step_rad_s = 0.05")
    cfg = tmp_path / "config.toml"
    cfg.write_text(text.replace('file = "', f'file = "{DEFAULT_CONFIG.parent}/'))
    out = tmp_path / "out"
    run_replay(shared_data("flightlogs", SHORT), out_dir=out, config_path=cfg, plots=False)
    m = json.loads((out / "metrics.json").read_text())
    r = read_log(out / "samples_rejected.csv")
    want: dict[str, int] = {}
    for kind, reason in zip(r["kind"], r["reason"], strict=True):
        want[f"{kind}: {reason}"] = want.get(f"{kind}: {reason}", 0) + 1
    assert want and m["samples_rejected"] == want


@pytest.mark.parametrize("xy", ["1e9,-1e9", "800,10", "10,600", "-0.5,10", "nan,10"])
def test_a_target_pixel_outside_the_image_is_a_setup_error(tmp_path, xy):
    """``gsoe companion --target-px``: the pixel must lie in the 800x600 image, like a ground station's."""
    from tests.test_companion_cli import TIMEOUT_S, gsoe

    p = gsoe("companion", "--connect", "udpin://127.0.0.1:14999", "--camera", "/nonexistent/video.avi",
             f"--target-px={xy}", "--log-dir", str(tmp_path / "log"), cwd=tmp_path)
    _, err = p.communicate(timeout=TIMEOUT_S)
    lines = [ln for ln in err.splitlines() if ln.startswith("gsoe companion:")]
    assert p.returncode == 2 and len(lines) == 1 and "--target-px" in lines[0] and "outside" in lines[0], err
    assert not (tmp_path / "log").exists()
