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
- the EKF divergence guard (:mod:`pipeline.guard`): a state beyond the airframe's bounds, or every aid source
  refused for ``guard_all_fail_s``, drops the filter (no estimate, so nothing valid is sent) and the start policy
  above starts it again: from the next usable GNSS fix while GNSS is enabled (a GNSS monitor's verdict) whose
  velocity agrees with the air data (``guard_restart_speed_tol_m_s``: a spoofed velocity is not what it restarts
  from), else, or when none came within ``guard_gnss_wait_s``, from air data, placed at the last
  healthy estimate's position and wind; the EKF's own reset of position/velocity to GNSS after continuous
  rejection is reported the same way.  Each is logged, counted in :attr:`NavPipeline.status`, written to the
  ``ekf_events`` stream and handed out by :meth:`NavPipeline.drain_events` (the companion sends them as
  STATUSTEXT);
- validity: the EKF's gate (``[ekf] valid_*``), the estimate's age (``max_estimate_age_s``) and the guard's
  bounds, nothing else;
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
from fusion.ekf import REASON_RESET_TO_MEAS, NavEkf, NavEstimate
from fusion.state import S
from gsoe.baseline import BaselineEstimate, PaperBaseline
from gsoe.camera import CameraModel
from gsoe.config import GsoeConfig
from gsoe.cycle import GsoeEstimator
from gsoe.stabilise import Frame
from pipeline import records as rec
from pipeline.guard import DivergenceGuard, GuardEvent, reason_test
from pipeline.plausibility import SamplePlausibility

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
Sink = Callable[[str, dict[str, Any]], None]
Healthy = tuple[NavEstimate, NDArray[np.float64], NDArray[np.float64]]
HEALTHY_EVERY_US = 100_000  # healthy states kept one per this, ...
HEALTHY_KEPT = 100          # ... this many (10 s)
#: what a restart after a divergence carries over from the last healthy filter: all but position and velocity
CARRIED_STATES = tuple(f for f in S.fields if not f.startswith(("pos_", "vel_", "base_pos_")))


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
    # the EKF divergence guard (pipeline.guard; a bound of 0 switches its test off):
    # a ground speed above this (m/s) is beyond the airframe: its top speed plus the strongest wind it flies in
    guard_max_ground_speed_m_s: Annotated[float, In(0.0, 1000.0)] = 60.0
    # a vertical speed above this (m/s, up or down) is beyond the airframe
    guard_max_vertical_speed_m_s: Annotated[float, In(0.0, 1000.0)] = 30.0
    # the height above the origin's ground level (m) must lie within these (0 as the upper bound: no height test)
    guard_min_height_m: Annotated[float, In(-1e5, 0.0)] = -500.0
    guard_max_height_m: Annotated[float, In(0.0, 1e5)] = 10_000.0
    # every aid sample refused by its innovation gate for this long (s), none fused: the state is what is wrong
    guard_all_fail_s: Annotated[float, In(0.0, 600.0)] = 1.0
    # ... with at least this many aid sources refused
    guard_min_failing_sources: Annotated[int, In(1, 20)] = 2
    # after a divergence, a healthy GNSS fix is awaited this long (s; while GNSS is enabled) before air data
    guard_gnss_wait_s: Annotated[float, In(0.0, 600.0)] = 1.0
    # ... and a fix restarts the filter only with a velocity this close (m/s) to the air data's (TAS along the
    # heading plus the last healthy wind): a spoofed velocity is not what the filter restarts from
    guard_restart_speed_tol_m_s: Annotated[float, In(0.0, 1000.0)] = 10.0


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
    ekf_started: str = ""           # how the EKF first started ("" not yet)
    ekf_start_t_us: int = -1
    ekf_diverged: dict[str, int] = field(default_factory=dict)  # divergences (pipeline.guard) by test
    ekf_resets: dict[str, int] = field(default_factory=dict)    # restarts after them, resets to GNSS, by source
    last_ekf_event: str = ""        # the last divergence or reset, with its reason
    gnss_used: int = 0
    gnss_withheld: int = 0
    restart_fixes_refused: int = 0  # fixes after a divergence whose velocity disagrees with the air data
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
        self.guard = DivergenceGuard(cfg)
        self._events: list[GuardEvent] = []
        self._diverged = ""                 # why the filter was dropped, until it starts again
        self._diverged_us = 0
        # recorded estimates that were valid with no aid failing, with the filter's state and covariance, one per
        # HEALTHY_EVERY_US at most; after a divergence the start policy restarts from ``_restart_from``
        self._healthy: deque[Healthy] = deque(maxlen=HEALTHY_KEPT)
        self._restart_from: Healthy | None = None
        self._gnss_wait_us = round(cfg.guard_gnss_wait_s * US_PER_S)
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
        """The EKF's estimate with the one validity gate applied (None before the EKF starts and while it is
        dropped after a divergence)."""
        if self.ekf is None:
            return None
        e = self.ekf.estimate()
        if not e.valid:
            return e
        age_us = self._now_us - e.t_us
        if age_us > self._age_us:
            return dataclasses.replace(e, valid=False,
                                       invalid_reason=f"estimate stale ({age_us / US_PER_S:.1f} s old: no IMU)")
        beyond = self.guard.bounds(e)
        if beyond:
            return dataclasses.replace(e, valid=False, invalid_reason=f"EKF diverged: {beyond}")
        suspect = self.guard.suspect
        if suspect:
            return dataclasses.replace(e, valid=False, invalid_reason=f"EKF suspect: {suspect}")
        return e

    def why_no_estimate(self) -> str:
        if self.ekf_cfg is None:
            return "EKF disabled"
        waiting = "GNSS fix" + (" or air data" if self.cfg.ekf_start == "gnss_or_air_data" else "")
        if self._diverged:
            return f"EKF diverged ({self._diverged}), restarting from a {waiting}"
        return f"EKF waiting for a {waiting}"

    def drain_events(self) -> list[GuardEvent]:
        """The EKF's divergences and resets since the last call, in order (module docstring)."""
        out, self._events = self._events, []
        return out

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

    def _start(self, t_us: int, pos_ned_m: NDArray[np.float64], vel_ned_m_s: NDArray[np.float64], how: str,
               wind_ne_m_s: NDArray[np.float64] | None = None) -> None:
        assert self.ekf_cfg is not None
        self.ekf = NavEkf(self.ekf_cfg, t_us=int(t_us), pos_ned_m=pos_ned_m, vel_ned_m_s=vel_ned_m_s,
                          wind_ne_m_s=wind_ne_m_s)
        self.guard.restart()
        if self._diverged and self._restart_from is not None:
            _, x, P = self._restart_from
            self.ekf.take_states(CARRIED_STATES, x, P)
        if self._diverged:
            self._ekf_event(t_us, "reset", f"EKF restarted from {how} after it diverged ({self._diverged})",
                            f"GSOE EKF reset from {how}", how)
            self._diverged = ""
        if not self.status.ekf_started:
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
        good = self._restart_from if self._diverged else None
        wind = np.array(good[0].wind_ne_m_s[:2]) if good is not None else None
        if good is not None and not self._fix_fits(s, vel, wind):
            return False
        self._start(s.t_us, np.array(s.pos_ned_m, dtype=float), vel,
                    "GNSS" if self._diverged else "the first GNSS fix", wind_ne_m_s=wind)
        return True

    def _fix_fits(self, s: GnssSample, vel: NDArray[np.float64], wind: NDArray[np.float64] | None) -> bool:
        """Whether a fix after a divergence has a velocity within ``guard_restart_speed_tol_m_s`` of the air data's
        (TAS along the heading plus the last healthy wind; no airspeed yet: any); if not, it is counted and logged.
        Its position is not judged against the last healthy estimate, which may be what diverged (a biased optical
        scale carries it hundreds of metres off): position jumps are the GNSS monitor's, on the receiver's own
        track."""
        if not (math.isfinite(self._tas_m_s) and self._att is not None and wind is not None):
            return True
        vel_off_m_s = float(np.hypot(*(vel[:2] - self._air_data_vel_ne(self._att, wind))))
        if vel_off_m_s <= self.cfg.guard_restart_speed_tol_m_s:
            return True
        self.status.restart_fixes_refused += 1
        if self.status.restart_fixes_refused == 1 or self.status.restart_fixes_refused % 50 == 0:
            log.warning("GNSS fix at t=%d us not used to restart the EKF: its velocity %.1f m/s from the air data "
                        "(%d such fixes)", s.t_us, vel_off_m_s, self.status.restart_fixes_refused)
        return False

    def _maybe_start_from_air_data(self) -> None:
        """Air data: TAS along the AHRS heading, the baro's height; at the origin in still air, or after a
        divergence at the last healthy estimate's position (carried on at its velocity) and in its wind (when no
        healthy fix came within ``guard_gnss_wait_s``, or at once while GNSS is withheld)."""
        if self.cfg.ekf_start != "gnss_or_air_data" or self._t_first_us is None or self._att is None:
            return
        if self._diverged:
            if self.gnss_enabled and self._now_us - self._diverged_us < self._gnss_wait_us:
                return
        elif self._now_us - self._t_first_us < self._air_wait_us:
            return
        h = self.baro_height_m
        if not (math.isfinite(self._tas_m_s) and math.isfinite(h)):
            return
        pos_ne, wind = np.zeros(2), None
        good = self._restart_from if self._diverged else None
        if good is not None:
            e = good[0]
            dt_s = (self._now_us - e.t_us) / US_PER_S
            pos_ne = np.array(e.pos_ne_m, dtype=float) + dt_s * np.array(e.vel_ned_m_s[:2], dtype=float)
            wind = np.array(e.wind_ne_m_s, dtype=float)[:2]
        vel_ne = self._air_data_vel_ne(self._att, wind)
        self._start(self._now_us, np.array([*pos_ne, -h]), np.array([*vel_ne, 0.0]),
                    "air data" if self._diverged else "air data (no GNSS fix)", wind_ne_m_s=wind)

    def _air_data_vel_ne(self, att: AttitudeSample, wind_ne_m_s: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """The ground velocity (m/s, N/E) the air data give: the TAS along the AHRS heading plus the wind (none: still
        air); what an air-data start starts from and what a restart fix's velocity is judged against."""
        yaw = att.yaw_rad
        air_ne = self._tas_m_s * np.array([math.cos(yaw), math.sin(yaw)])
        return air_ne + wind_ne_m_s if wind_ne_m_s is not None else air_ne

    def _ekf_event(self, t_us: int, kind: str, reason: str, text: str, key: str) -> None:
        """A divergence or reset (module docstring): logged, counted, written and queued for the caller."""
        counts = self.status.ekf_diverged if kind == "diverged" else self.status.ekf_resets
        counts[key] = counts.get(key, 0) + 1
        self.status.last_ekf_event = reason
        log.warning("%s at t=%d us", reason, t_us)
        ev = GuardEvent.make(t_us, kind, reason, text)
        self._events.append(ev)
        if self._sink is not None:
            self._sink("ekf_events", ev.as_record())

    def _diverge(self, e: NavEstimate, why: str) -> NavEstimate:
        """The filter has diverged: dropped (nothing valid is sent until the start policy starts it again)."""
        self._ekf_event(e.t_us, "diverged", f"EKF diverged: {why}", f"GSOE EKF diverged: {why}", reason_test(why))
        # the state to restart from: healthy a whole failing window before the first refusal (the refusals come a
        # little after the state went wrong, and a state recorded in between is wrong already)
        first_us = self.guard.failing_since_us
        before_us = (e.t_us if first_us is None else first_us) - round(self.cfg.guard_all_fail_s * US_PER_S)
        # (none recorded since the last restart: the one before still stands, the newest healthy state known)
        self._restart_from = next((h for h in reversed(self._healthy) if h[0].t_us <= before_us),
                                  self._healthy[0] if self._healthy else self._restart_from)
        self._healthy.clear()
        self.ekf = None
        self._last_estimate = None
        self._diverged, self._diverged_us = why, self._now_us
        return dataclasses.replace(e, valid=False, invalid_reason=f"EKF diverged: {why}")

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
        """The estimate now, judged by the divergence guard and written to ``ekf.csv`` with the aid sources that
        changed since the last record; a reset of position or velocity to GNSS is reported."""
        assert self.ekf is not None
        e = self.ekf.estimate()
        self._last_ekf_record_us = t_us
        status = self.ekf.status()
        wants = self._wants
        if self._sink is not None and (wants is None or wants("ekf", e.t_us)):
            self._sink("ekf", e.as_record())
        for name, st in status.items():
            if st.t_us == self._aid_written.get(name):
                continue
            self._aid_written[name] = st.t_us
            if st.reason == REASON_RESET_TO_MEAS:
                assert self.ekf_cfg is not None
                what = "position" if name == "gnss_pos" else "velocity"
                self._ekf_event(st.t_us, "reset", f"EKF {what} reset to GNSS (refused for "
                                f"{self.ekf_cfg.gnss.reset_after_s:g} s while the fixes were healthy)",
                                f"GSOE EKF {what} reset to GNSS", name)
            if self._sink is not None and (wants is None or wants("aid_status", st.t_us, st.source, st.rejected)):
                self._sink("aid_status", st.as_record())
        why = self.guard.check(e, status)
        if why:
            return self._diverge(e, why)
        self._last_estimate = e
        if (e.valid and not self.guard.failing
                and (not self._healthy or e.t_us - self._healthy[-1][0].t_us >= HEALTHY_EVERY_US)):
            self._healthy.append((e, self.ekf.x, self.ekf.P))
        return e


def pipeline_config_from_raw(raw: dict[str, Any], profile: str | None = None) -> PipelineConfig:
    """``[pipeline]`` of a loaded configuration file (defaults where it is absent), with ``profile`` applied."""
    return build(PipelineConfig, with_profile(raw.get("pipeline", {}), profile, "pipeline"), "pipeline")
