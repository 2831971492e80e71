"""The navigation pipeline: sensor samples in, the optical steps, the EKF's estimate and per-source status out.

Every driver feeds this one object and does nothing else between samples and estimate: ``gsoe sim`` (the simulator's
sensors), ``gsoe companion`` (the autopilot link and the camera), ``gsoe replay`` (a flight log) and the Monte Carlo
runner (through ``gsoe sim``).  What it owns, each decided here once:

- coupling the optical estimator's attitude buffer to the AHRS and IMU samples, after their plausibility tests
  (:mod:`pipeline.plausibility`: in range but impossible for the airframe, rejected and counted by reason);
- holding a frame until attitude and IMU samples cover its exposure, at most ``attitude_wait_s`` of the pipeline's
  clock (the newest sample or :meth:`NavPipeline.poll` time), after which the attitude buffer extrapolates;
- the EKF start policy: at the first usable GNSS fix once attitude is known; with ``ekf_start = "gnss_or_air_data"``
  also from air data (position at the origin, ground velocity = TAS along the heading, height from the baro) when
  no usable fix came within ``air_data_start_wait_s`` of the first sample;
- heights: the NED origin lies at ground level (home); the baro is referred to the ground level the source gives
  (:meth:`NavPipeline.on_ground_level`, the baro altitude of the ground at the origin; 0 when the baro already is
  a height above it); the optical estimator takes the EKF's height above ground (before the EKF, the baro's);
- the optical steps into the EKF and into the paper's baseline chain;
- validity: the EKF's gate (``[ekf] valid_*``) and the estimate's age (``max_estimate_age_s``), nothing else;
- the log records, one builder per stream (:mod:`pipeline.records`), written through the caller's ``sink``.

Times are ``t_us`` of one clock (the simulation's, the companion's monotonic clock, or the log's).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray

from common.config import In, Validated, build, with_profile
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, GsoeStep, ImuSample
from fusion.config import EkfConfig
from fusion.ekf import NavEkf, NavEstimate
from gsoe.baseline import BaselineEstimate, PaperBaseline
from gsoe.camera import CameraModel
from gsoe.config import GsoeConfig
from gsoe.cycle import GsoeEstimator
from gsoe.stabilise import Frame
from pipeline import records as rec
from pipeline.plausibility import SamplePlausibility

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
Sink = Callable[[str, dict[str, Any]], None]


@dataclass(frozen=True)
class PipelineConfig(Validated):
    """``[pipeline]`` of the configuration file (profiles: ``[pipeline.profiles.<name>]``)."""

    # a frame waits at most this long (s) for attitude and IMU samples to cover its exposure
    attitude_wait_s: Annotated[float, In(0.0, 5.0)] = 0.05
    # what may start the EKF: a usable GNSS fix only, or also air data
    ekf_start: Literal["gnss", "gnss_or_air_data"] = "gnss_or_air_data"
    # no usable fix this long (s) after the first sample: the EKF starts from air data
    air_data_start_wait_s: Annotated[float, In(0.0, 3600.0)] = 10.0
    # a frame stamped more than this (s) after the pipeline's clock is refused (a wrong camera clock)
    max_frame_ahead_s: Annotated[float, In(0.0, 60.0)] = 0.5
    # an estimate older than this (s) on the pipeline's clock is invalid
    max_estimate_age_s: Annotated[float, In(0.01, 60.0)] = 0.5
    # ekf.csv between frames at most this often (s of the pipeline's clock)
    ekf_record_period_s: Annotated[float, In(0.0, 60.0)] = 0.1
    # optical quality = the valid fraction of this many last steps
    quality_window_steps: Annotated[int, In(1, 10_000)] = 30
    # the EKF's attitude: "compensated" (AHRS latency removed and noise averaged with the gyro) or "ahrs" (as given)
    attitude_source: Literal["compensated", "ahrs"] = "compensated"
    # plausibility of IMU and attitude samples (pipeline.plausibility; a threshold of 0 switches its test off):
    # largest change of the specific force (m/s^2, any axis) from the last accepted IMU sample
    imu_max_accel_step_m_s2: Annotated[float, In(0.0, 1000.0)] = 20.0
    # largest change of the body rate (rad/s, any axis) from the last accepted IMU sample
    imu_max_gyro_step_rad_s: Annotated[float, In(0.0, 100.0)] = 3.0
    # largest difference (rad/s, any axis) between the gyro and the AHRS attitude's rate
    gyro_ahrs_max_diff_rad_s: Annotated[float, In(0.0, 100.0)] = 3.0
    # a stream silent this long (s; a link loss) starts afresh: its next sample is compared with none
    plausibility_max_gap_s: Annotated[float, In(0.0, 60.0)] = 0.5
    # this many consecutive rejected samples that agree with each other are a genuine change: the last is accepted
    plausibility_confirm_samples: Annotated[int, In(2, 1000)] = 3


@dataclass(frozen=True, slots=True)
class FrameResult:
    """What one processed frame (or one batch of steps from :meth:`NavPipeline.on_steps`) gave."""

    t_us: int
    steps: tuple[GsoeStep, ...]
    baseline: tuple[BaselineEstimate, ...]
    estimate: NavEstimate | None


@dataclass
class PipelineStatus:
    """Counters of the pipeline (the EKF's per-source records are :meth:`NavPipeline.aid_status`)."""

    frames: int = 0
    frames_late: int = 0            # processed after ``attitude_wait_s`` without attitude/IMU covering them
    frames_no_step: int = 0
    steps: int = 0
    steps_valid: int = 0
    estimator_errors: int = 0
    ekf_started: str = ""           # how the EKF started ("" not yet)
    ekf_start_t_us: int = -1
    gnss_used: int = 0
    gnss_withheld: int = 0
    errors: dict[str, int] = field(default_factory=dict)


def _usable_fix(s: GnssSample) -> bool:
    return bool(s.fix_ok and np.all(np.isfinite(s.pos_ned_m)) and np.all(np.isfinite(s.vel_ned_m_s[:2])))


def _sigma(v: float) -> float | None:
    return float(v) if math.isfinite(v) and v > 0 else None


class NavPipeline:
    """The one pipeline (module docstring).  Build it once per flight; push samples in time order per source."""

    def __init__(self, gsoe_cfg: GsoeConfig, ekf_cfg: EkfConfig | None, cfg: PipelineConfig, camera: CameraModel,
                 *, sink: Sink | None = None, timers: dict[str, float] | None = None) -> None:
        self.cfg = cfg
        self.ekf_cfg = ekf_cfg
        self.gsoe = GsoeEstimator(gsoe_cfg, camera)
        self.baseline = PaperBaseline(gsoe_cfg.integrity)
        self.ekf: NavEkf | None = None
        self.status = PipelineStatus()
        #: GNSS fixes reach the EKF only while this is true (an outage test, a GNSS monitor's verdict)
        self.gnss_enabled = True
        #: the baro altitude of the ground level at the NED origin (m)
        self.ground_alt_m = 0.0
        self._sink = sink
        # a sink may say which records it would drop (common.logio.Decimator.wants): those are not built
        self._wants: Callable[..., bool] | None = getattr(sink, "wants", None)
        #: IMU and attitude samples that are in range but implausible for the airframe never reach GSOE or the EKF
        self.plausibility = SamplePlausibility(cfg, sink)
        self.timers = timers if timers is not None else {"gsoe": 0.0, "ekf": 0.0}
        self.timers.setdefault("gsoe", 0.0)
        self.timers.setdefault("ekf", 0.0)
        self._att: AttitudeSample | None = None
        self._imu_held: ImuSample | None = None
        self._tas_m_s = math.nan
        self._baro_alt_m = math.nan
        self._t_first_us: int | None = None
        self._now_us = -(2**62)
        self._newest_att_us = -(2**62)
        self._newest_imu_us = -(2**62)
        self._pending: deque[tuple[int, Frame]] = deque()
        self._results: list[FrameResult] = []
        self._recent_valid: deque[bool] = deque(maxlen=cfg.quality_window_steps)
        self._last_ekf_record_us = -(2**62)
        self._aid_written: dict[str, int] = {}
        self._last_estimate: NavEstimate | None = None
        self._compensated = cfg.attitude_source == "compensated"
        self._wait_us = round(cfg.attitude_wait_s * US_PER_S)
        self._ahead_us = round(cfg.max_frame_ahead_s * US_PER_S)
        self._air_wait_us = round(cfg.air_data_start_wait_s * US_PER_S)
        self._age_us = round(cfg.max_estimate_age_s * US_PER_S)
        self._record_us = round(cfg.ekf_record_period_s * US_PER_S)

    # ------------------------------------------------------------------------------------------------ inputs
    def on_imu(self, s: ImuSample) -> None:
        """An IMU sample: into the attitude buffer now; the EKF predicts with it once the samples stamped up to
        ``s.t_us`` are in (an AHRS sample of the same stamp, or any later sample), so that its attitude uses them."""
        self._write("imu", rec.imu_record, s)
        if not self.plausibility.imu(s):
            return
        t0 = time.perf_counter()
        if self.gsoe.push_imu(s):
            self._newest_imu_us = max(self._newest_imu_us, s.t_us)
        self.timers["gsoe"] += time.perf_counter() - t0
        self._predict_held()
        self._imu_held = s
        self._advance(s.t_us, predict=False)

    def on_attitude(self, s: AttitudeSample) -> None:
        self._write("attitude", rec.attitude_record, s)
        if not self.plausibility.attitude(s):
            return
        t0 = time.perf_counter()
        if self.gsoe.push_attitude(s):
            self._newest_att_us = max(self._newest_att_us, s.t_us)
            self._att = s
        self.timers["gsoe"] += time.perf_counter() - t0
        self._advance(s.t_us)

    def on_airspeed(self, s: AirspeedSample) -> None:
        self._flush_to(s.t_us)
        self._write("airspeed", rec.airspeed_record, s)
        if not math.isfinite(s.tas_m_s):
            return
        self._tas_m_s = s.tas_m_s
        self.baseline.set_airspeed(s.tas_m_s)
        if self.ekf is not None:
            t0 = time.perf_counter()
            self.ekf.fuse_airspeed(s.t_us, s.tas_m_s)
            self.timers["ekf"] += time.perf_counter() - t0
        self._advance(s.t_us)

    def on_baro(self, s: BaroSample) -> None:
        self._flush_to(s.t_us)
        if self._sink is not None and (self._wants is None or self._wants("baro", s.t_us)):
            self._sink("baro", rec.baro_record(s, self.ground_alt_m))
        if not math.isfinite(s.alt_m):
            return
        self._baro_alt_m = s.alt_m
        if self.ekf is not None:
            t0 = time.perf_counter()
            self.ekf.fuse_baro(s.t_us, s.alt_m - self.ground_alt_m)
            self.timers["ekf"] += time.perf_counter() - t0
        self._advance(s.t_us)

    def on_ground_level(self, baro_alt_m: float) -> None:
        """The baro altitude of the ground level at the NED origin (home); ignored unless finite."""
        if math.isfinite(baro_alt_m):
            self.ground_alt_m = float(baro_alt_m)

    def on_gnss(self, s: GnssSample) -> None:
        self._flush_to(s.t_us)
        t0 = time.perf_counter()
        used = self.gnss_enabled and s.fix_ok and self.ekf_cfg is not None
        if used and self.ekf is None:
            used = self._start_from_fix(s)
        elif used and self.ekf is not None:
            used = self._fuse_gnss(s)
        self.status.gnss_used += int(used)
        self.status.gnss_withheld += int(s.fix_ok and not self.gnss_enabled)
        self.timers["ekf"] += time.perf_counter() - t0
        if self._sink is not None:
            self._sink("gnss", rec.gnss_record(s, used))
        self._advance(s.t_us)

    def on_frame(self, t_us: int, image: Frame) -> None:
        """A camera frame exposed at ``t_us`` (raw pixels, or a callable giving them region by region); it is
        processed once attitude and IMU cover ``t_us`` or ``attitude_wait_s`` later."""
        why = ""
        if self._pending and t_us <= self._pending[-1][0]:
            why = "frame stamp not increasing"
        elif t_us - self._now_us > self._ahead_us and self._t_first_us is not None:
            why = "frame stamped ahead of the samples"
        if why:
            self.status.errors[why] = self.status.errors.get(why, 0) + 1
            return
        self._pending.append((int(t_us), image))
        self._process_ready()

    def on_steps(self, steps: Sequence[GsoeStep]) -> None:
        """Optical steps from a source that has no pixels (a log's stand-in, a recorded ``gsoe.csv``)."""
        if steps:
            self._take_steps(steps[-1].t_us, list(steps))

    def poll(self, now_us: int) -> None:
        """Advance the pipeline's clock without a sample (frames past their wait are processed; the EKF may start
        from air data)."""
        self._advance(now_us)

    # ------------------------------------------------------------------------------------------------ outputs
    def drain(self) -> list[FrameResult]:
        """The frames processed since the last call, in order."""
        out, self._results = self._results, []
        return out

    @property
    def now_us(self) -> int:
        """The pipeline's clock: the newest sample or poll time."""
        return self._now_us

    @property
    def quality(self) -> float:
        """Fraction of valid optical matches over the last ``quality_window_steps`` steps (0 without any)."""
        return float(np.mean(self._recent_valid)) if self._recent_valid else 0.0

    @property
    def attitude(self) -> AttitudeSample | None:
        """The last AHRS attitude."""
        return self._att

    @property
    def tas_m_s(self) -> float:
        """The last true airspeed (nan before any)."""
        return self._tas_m_s

    @property
    def frames_pending(self) -> int:
        """Frames waiting for attitude and IMU to cover their exposure."""
        return len(self._pending)

    def estimate(self) -> NavEstimate | None:
        """The EKF's estimate with the one validity gate applied (None before the EKF starts)."""
        if self.ekf is None:
            return None
        e = self.ekf.estimate()
        age_us = self._now_us - e.t_us
        if e.valid and age_us > self._age_us:
            return dataclasses.replace(e, valid=False,
                                       invalid_reason=f"estimate stale ({age_us / US_PER_S:.1f} s old: no IMU)")
        return e

    def why_no_estimate(self) -> str:
        if self.ekf_cfg is None:
            return "EKF disabled"
        return "EKF waiting for a GNSS fix" + (" or air data" if self.cfg.ekf_start == "gnss_or_air_data" else "")

    def aid_status(self) -> dict[str, Any]:
        return self.ekf.status() if self.ekf is not None else {}

    @property
    def baro_height_m(self) -> float:
        """The last baro altitude above the ground level (nan before any)."""
        return self._baro_alt_m - self.ground_alt_m

    # ------------------------------------------------------------------------------------------------ inside
    def _write(self, stream: str, build: Callable[[Any], dict[str, Any]], s: Any) -> None:
        if self._sink is not None and (self._wants is None or self._wants(stream, s.t_us)):
            self._sink(stream, build(s))

    def _predict_held(self) -> None:
        """The EKF's prediction with the held IMU sample (the attitude at its stamp, module docstring)."""
        s, self._imu_held = self._imu_held, None
        if s is None or self.ekf is None or self._att is None:
            return
        t0 = time.perf_counter()
        # the attitude the optical frames use too: AHRS latency removed, noise averaged (gsoe.attitude)
        att = self.gsoe.fusion_attitude(s.t_us) if self._compensated else None
        self.ekf.predict(s, att or self._att)
        if s.t_us - self._last_ekf_record_us >= self._record_us and not self._pending:
            self._record_ekf(s.t_us)
        self.timers["ekf"] += time.perf_counter() - t0

    def _flush_to(self, t_us: int) -> None:
        if self._imu_held is not None and t_us >= self._imu_held.t_us:
            self._predict_held()

    def _advance(self, t_us: int, predict: bool = True) -> None:
        """The pipeline's clock reaches ``t_us``: a held IMU sample is predicted with, the EKF may start, frames
        whose wait is over are processed."""
        if predict:
            self._flush_to(t_us)
        if t_us > self._now_us:
            self._now_us = t_us
        if self._t_first_us is None:
            self._t_first_us = t_us
        if self.ekf is None and self.ekf_cfg is not None:
            self._maybe_start_from_air_data()
        if self._pending:
            self._process_ready()

    def _start(self, t_us: int, pos_ned_m: NDArray[np.float64], vel_ned_m_s: NDArray[np.float64], how: str) -> None:
        assert self.ekf_cfg is not None
        self.ekf = NavEkf(self.ekf_cfg, t_us=int(t_us), pos_ned_m=pos_ned_m, vel_ned_m_s=vel_ned_m_s)
        self.status.ekf_started = how
        self.status.ekf_start_t_us = int(t_us)
        log.info("EKF started from %s at t=%d us, pos %s m, vel %s m/s", how, t_us, np.round(pos_ned_m, 1),
                 np.round(vel_ned_m_s, 1))

    def _start_from_fix(self, s: GnssSample) -> bool:
        if self._att is None or not _usable_fix(s):
            return False
        vel = np.array(s.vel_ned_m_s, dtype=float)
        if not math.isfinite(vel[2]):
            vel[2] = 0.0
        self._start(s.t_us, np.array(s.pos_ned_m, dtype=float), vel, "the first GNSS fix")
        return True

    def _maybe_start_from_air_data(self) -> None:
        if self.cfg.ekf_start != "gnss_or_air_data" or self._t_first_us is None:
            return
        if self._now_us - self._t_first_us < self._air_wait_us or self._att is None:
            return
        h = self.baro_height_m
        if not (math.isfinite(self._tas_m_s) and math.isfinite(h)):
            return
        yaw = self._att.yaw_rad
        self._start(self._now_us, np.array([0.0, 0.0, -h]),
                    np.array([self._tas_m_s * math.cos(yaw), self._tas_m_s * math.sin(yaw), 0.0]),
                    "air data (no GNSS fix)")

    def _fuse_gnss(self, s: GnssSample) -> bool:
        assert self.ekf is not None
        pos = s.pos_ned_m if np.all(np.isfinite(s.pos_ned_m)) else None
        vel: NDArray[np.float64] | None = s.vel_ned_m_s      # 2-D when the down component is unknown
        if not np.all(np.isfinite(s.vel_ned_m_s)):
            vel = s.vel_ned_m_s[:2] if np.all(np.isfinite(s.vel_ned_m_s[:2])) else None
        if pos is None and vel is None:
            return False
        self.ekf.fuse_gnss(s.t_us, pos, vel, pos_sigma_ne_m=_sigma(s.h_acc_m), pos_sigma_d_m=_sigma(s.alt_acc_m),
                           vel_sigma_ne_m_s=_sigma(s.v_acc_m_s))
        return True

    def _covered(self, t_us: int) -> bool:
        return self._newest_att_us >= t_us and self._newest_imu_us >= t_us

    def _process_ready(self) -> None:
        while self._pending:
            t_us, image = self._pending[0]
            late = self._now_us - t_us >= self._wait_us
            if not (self._covered(t_us) or late):
                return
            self._pending.popleft()
            self.status.frames_late += int(late and not self._covered(t_us))
            self._process_frame(t_us, image)

    def _frame_height_m(self) -> float:
        e = self._last_estimate
        return e.height_agl_m if e is not None else self.baro_height_m

    def _process_frame(self, t_us: int, image: Frame) -> None:
        self.status.frames += 1
        t0 = time.perf_counter()
        try:
            steps = self.gsoe.process_frame(t_us, image, float(self._frame_height_m()))
        except Exception as e:  # a bad frame must not take the pipeline down
            self.status.estimator_errors += 1
            log.exception("optical estimator failed at t=%d us: %s", t_us, e)
            steps = []
        self.timers["gsoe"] += time.perf_counter() - t0
        if not steps:
            self.status.frames_no_step += 1
            if self.gsoe.featureless:
                self._recent_valid.append(False)   # featureless ground: no cycle runs, a frame without a match
        self._take_steps(t_us, steps)

    def _take_steps(self, t_us: int, steps: list[GsoeStep]) -> None:
        t0 = time.perf_counter()
        base: list[BaselineEstimate] = []
        for s in steps:
            self.status.steps += 1
            if not s.new_cycle:
                self._recent_valid.append(bool(s.valid))
                self.status.steps_valid += int(s.valid)
            self._write("gsoe", rec.step_record, s)
            b = self.baseline.update(s)
            if b is not None:
                base.append(b)
                self._write("baseline", rec.baseline_record, b)
            if self.ekf is not None:
                self.ekf.fuse_optical(s)
        e = self._record_ekf(t_us) if self.ekf is not None else None
        self.timers["ekf"] += time.perf_counter() - t0
        self._results.append(FrameResult(t_us, tuple(steps), tuple(base), e))

    def _record_ekf(self, t_us: int) -> NavEstimate:
        """The estimate now, written to ``ekf.csv`` with the aid sources that changed since the last record."""
        assert self.ekf is not None
        e = self.ekf.estimate()
        self._last_estimate = e
        self._last_ekf_record_us = t_us
        if self._sink is not None:
            wants = self._wants
            if wants is None or wants("ekf", e.t_us):
                self._sink("ekf", e.as_record())
            for name, st in self.ekf.status().items():
                if st.t_us != self._aid_written.get(name):
                    self._aid_written[name] = st.t_us
                    if wants is None or wants("aid_status", st.t_us, st.source, st.rejected):
                        self._sink("aid_status", st.as_record())
        return e


def pipeline_config_from_raw(raw: dict[str, Any], profile: str | None = None) -> PipelineConfig:
    """``[pipeline]`` of a loaded configuration file (defaults where it is absent), with ``profile`` applied."""
    return build(PipelineConfig, with_profile(raw.get("pipeline", {}), profile, "pipeline"), "pipeline")
