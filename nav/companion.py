"""The companion app's loop: camera + autopilot link -> GSOE + EKF -> GNSS monitor -> outputs, guidance and log.

One synchronous loop (the link's asyncio runs in its own thread, the camera reads in its own thread):

1. drain the link's validated telemetry samples: attitude and IMU go to the optical estimator's attitude buffer
   and to the EKF's prediction, airspeed and baro to the EKF, GNSS to the :class:`GnssMonitor` and, while the
   monitor says ``GNSS_OK``, to the EKF; an external tracker's reports go to the guidance;
2. take the newest camera frame (stamped at capture minus ``camera_latency_s`` on the companion's clock, or, for
   the simulator's stream, at its exposure time mapped from the vehicle's clock); reject unusable frames (None,
   wrong size, wrong type, frozen: identical to the previous one on a grid of every 4th pixel, stamp not
   increasing) with a counted, logged
   reason; hold it until attitude and IMU samples cover its exposure time (at most ``attitude_wait_s``, then the
   attitude buffer extrapolates), so that attitude is matched to the exposure;
3. run the optical estimator on it (attitude interpolated to the exposure time), fuse its steps in the EKF;
4. send the EKF's estimate to the autopilot (after every frame, and between frames at the fastest output rate)
   while it is valid (:func:`nav.link.check_estimate` says why not; an
   estimate older than ``max_estimate_age_s``, e.g. while no IMU arrives, is invalid), announce every change of
   validity (STATUSTEXT, at most one per ``announce_min_interval_s``; the ``GSOE_VALID`` named value carries the
   live state), and every divergence and reset of the EKF (:mod:`pipeline.guard`: STATUSTEXT and ``events.csv``);
5. track the designated target (the belly camera's template tracker, or an external tracker over MAVLink,
   ``[companion.tracking]``) and send the heading command (:mod:`nav.guidance`);
6. log every input, estimate and output through :class:`common.logio.RunLog` (append-only, flushed at least every
   ``log_flush_s`` <= 1 s, so ``kill -9`` loses at most that), and every state change (camera lost/opened, link
   lost/restored, estimate valid/invalid with its reason, telemetry rejected, GNSS state) to ``events.csv``; each
   new offset of the samples' clock (per telemetry kind: ``t_us = autopilot us + offset_us``, :mod:`nav.link`) to
   ``clock_sync.csv``, so that the log can be set against the vehicle's own time.

Nothing in the loop may end it except a stop request: bad frames, bad telemetry, a dead link (MAVSDK reconnects by
itself; the first connection is retried every ``reconnect_s``), a lost camera (reopened every
``camera_reconnect_s``) and estimator exceptions are counted, logged and survived.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import socket
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from common.config import ConfigError, In, Validated, build
from common.framestream import FRAME_HEADER_SIZE, decode_header, decode_image
from common.logio import RunLog
from common.samples import AirspeedSample, AttitudeSample, BaroSample, GnssSample, ImuSample
from fusion.config import ekf_config_from_raw
from gsoe.camera import CameraModel
from gsoe.config import GsoeConfig
from nav.camera_sources import FrameSource, open_source
from nav.gnss_monitor import Announcement, Consistency, GnssMonitor, GnssMonitorConfig, GnssState
from nav.guidance import GuidanceConfig, TargetGuidance, change_heading_command_fields, forward_camera
from nav.hygiene import pixel_in_image
from nav.link import (
    CompanionLink,
    HomeReading,
    LinkConfig,
    OutputEstimate,
    TrackReading,
    now_us,
)
from nav.tracker import ExternalTracker, TemplateTracker, TemplateTrackerConfig
from pipeline.navpipeline import NavPipeline, Sink, pipeline_config_from_raw

log = logging.getLogger(__name__)

SIM_SCHEME = "sim://"
MAV_CMD_USER_1 = 31010  # ground station -> companion: designate the target at pixel (param1, param2)
MAX_FRAMES_IN_PIPELINE = 8  # frames handed to the pipeline and not yet processed, kept for the tracker
HOME_BARO_MAX_SKEW_US = 200_000  # a home report and a baro sample this close in time give the baro's ground level
STATUSTEXT_MAX_CHARS = 50
#: the frozen-frame test compares every FROZEN_STRIDE-th pixel of every FROZEN_STRIDE-th row with the previous frame
FROZEN_STRIDE = 4


@dataclass(frozen=True)
class TrackingConfig(Validated):
    """``[companion.tracking]``: where the target's pixel comes from and which camera it refers to.

    ``source``: ``"camera"`` (the default template tracker on the companion's own camera frames, designated with
    ``--target-px`` or by the ground station) or ``"mavlink"`` (an external video tracker's
    CAMERA_TRACKING_IMAGE_STATUS, :class:`nav.tracker.ExternalTracker`).  ``mount``: the camera the pixel belongs
    to: ``"belly"`` (the calibrated camera as mounted) or ``"forward"`` (the same lens looking forward,
    ``forward_depression_deg`` below the body x axis, :func:`nav.guidance.forward_camera`).  ``max_age_s``: an
    external tracker's report older than this is not used.
    """

    source: Literal["camera", "mavlink"] = "camera"
    mount: Literal["belly", "forward"] = "belly"
    forward_depression_deg: Annotated[float, In(-45.0, 89.0)] = 10.0
    max_age_s: Annotated[float, In(0.0, 60.0, lo_open=True)] = 0.5


@dataclass(frozen=True)
class CompanionConfig(Validated):
    """``[companion]`` of the configuration file (sub-tables ``link``, ``gnss``, ``guidance``, ``tracker``).

    ``camera_latency_s``: exposure-to-capture delay of the camera stack, subtracted from the capture time;
    ``frame_timeout_s``: no frame for this long = camera lost (reopened every ``reconnect_s``); ``reconnect_s``:
    retry period of the camera and of the autopilot link; ``log_flush_s``: log flush interval (at most 1 s);
    ``status_s``: period of the one-line status in the log; ``max_frame_age_s``: frames older than this when
    processed are skipped (the loop fell behind); ``use_ekf``: run the EKF.  When a frame is processed, how long
    it waits for attitude, how the EKF starts and when an estimate is stale are the pipeline's (``[pipeline]``).
    ``camera_fps``: the frame rate asked of a camera device (0: the device's own; the size asked is the camera
    file's, :mod:`nav.camera_sources`); ``video_pacing``: a video file as the camera is read at its own timestamps
    (``"own_timestamps"``) or as fast as it decodes (``"as_fast_as_possible"``, stamped when read).
    """

    camera_latency_s: Annotated[float, In(0.0, 5.0)] = 0.0
    frame_timeout_s: Annotated[float, In(0.01, 60.0)] = 1.0
    reconnect_s: Annotated[float, In(0.05, 600.0)] = 2.0
    log_flush_s: Annotated[float, In(0.01, 1.0)] = 0.5
    status_s: Annotated[float, In(0.1, 3600.0)] = 5.0
    max_frame_age_s: Annotated[float, In(0.01, 60.0)] = 0.5
    use_ekf: bool = True
    camera_fps: Annotated[float, In(0.0, 1000.0)] = 0.0
    video_pacing: Literal["own_timestamps", "as_fast_as_possible"] = "own_timestamps"
    camera_reconnect_s: Annotated[float, In(0.01, 600.0)] = 0.5
    announce_min_interval_s: Annotated[float, In(0.0, 3600.0)] = 2.0
    link: LinkConfig = field(default_factory=LinkConfig)
    gnss: GnssMonitorConfig = field(default_factory=GnssMonitorConfig)
    guidance: GuidanceConfig = field(default_factory=GuidanceConfig)
    tracker: TemplateTrackerConfig = field(default_factory=TemplateTrackerConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)


def companion_config_from_raw(raw: dict[str, Any]) -> CompanionConfig:
    """Build ``[companion]`` (absent: defaults); errors name ``companion.<field>``."""
    section = raw.get("companion", {})
    if not isinstance(section, dict):
        raise ConfigError("companion", "must be a table")
    return build(CompanionConfig, section, "companion")


# ------------------------------------------------------------------------------------------------ camera
class SimFrameClient:
    """Reads the simulator's TCP frame stream (``sim://HOST:PORT``, format :mod:`common.framestream`);
    ``read()`` -> (vehicle_t_us, frame) | None."""

    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        self._sock = socket.create_connection((host, port), timeout=timeout_s)
        self._sock.settimeout(timeout_s)

    def _exact(self, n: int) -> bytes | None:
        buf = bytearray()
        while len(buf) < n:
            chunk = self._sock.recv(n - len(buf))
            if not chunk:
                return None
            buf += chunk
        return bytes(buf)

    def read(self) -> tuple[int, NDArray[np.uint8]] | None:
        """The next frame, or None when the stream ended; ``OSError`` on a corrupt header (reconnect to resync)."""
        head = self._exact(FRAME_HEADER_SIZE)
        if head is None:
            return None
        header = decode_header(head)  # CorruptFrameStream, an OSError, when it is not a header
        data = self._exact(header.payload_size)
        if data is None:
            return None
        return header.t_us, decode_image(header, data)

    def close(self) -> None:
        self._sock.close()


class CameraThread:
    """Reads frames from ``source`` in a thread; keeps only the newest (a slow loop skips frames, never lags).

    ``source``: a device index (``"0"``), a video file, an RTSP URL, ``picam://N``, a GStreamer pipeline where
    OpenCV has GStreamer (:mod:`nav.camera_sources`: opened at ``size_px``, the camera file's size; a video file is
    not reopened at its end), or ``sim://HOST:PORT``.
    ``latest()`` returns ``(t_us, frame, from_vehicle_clock, captured_us)``:
    the exposure time, the image, whether ``t_us`` is on the vehicle's clock, and when the frame was read.  A lost
    camera is reopened every ``camera_reconnect_s``; openings and losses are queued in :attr:`events`.
    """

    def __init__(self, source: str, cfg: CompanionConfig, clock: Callable[[], int] = now_us,
                 size_px: tuple[int, int] = (0, 0)) -> None:
        self.source = source
        self.cfg = cfg
        self.size_px = size_px
        self.clock = clock
        self._slot: queue.Queue[tuple[int, Any, bool, int]] = queue.Queue(maxsize=1)
        self.events: queue.Queue[tuple[int, str]] = queue.Queue()
        self._stop = threading.Event()
        self.frames = 0
        self.failures = 0
        self.opened = False
        self._thread = threading.Thread(target=self._run, name="camera", daemon=True)
        self._thread.start()

    def _open(self) -> Any:
        if self.source.startswith(SIM_SCHEME):
            host, port = self.source[len(SIM_SCHEME):].rsplit(":", 1)
            return SimFrameClient(host, int(port), self.cfg.frame_timeout_s)
        return open_source(self.source, self.size_px, self.cfg.camera_fps, self.cfg.camera_latency_s,
                           self.cfg.video_pacing == "as_fast_as_possible", self.clock)

    def _run(self) -> None:
        reported = False
        while not self._stop.is_set():
            try:
                cap = self._open()
            except (OSError, ValueError) as e:
                self.failures += 1
                if not reported:
                    log.warning("camera %s: %s; retrying every %.1f s", self.source, e, self.cfg.camera_reconnect_s)
                    self.events.put((self.clock(), f"cannot open: {e}"))
                    reported = True
                self._stop.wait(self.cfg.camera_reconnect_s)
                continue
            reported = False
            self.opened = True
            log.info("camera %s opened", self.source)
            self.events.put((self.clock(), "opened"))
            try:
                why = self._read_loop(cap)
            finally:
                self.opened = False
                cap.close()
            if getattr(cap, "finished", False):
                log.info("camera %s: %s", self.source, why)
                self.events.put((self.clock(), why))
                return
            if not self._stop.is_set():
                log.warning("camera %s lost (%s); reopening every %.1f s", self.source, why,
                            self.cfg.camera_reconnect_s)
                self.events.put((self.clock(), f"lost: {why}"))
                self._stop.wait(self.cfg.camera_reconnect_s)

    def _read_loop(self, cap: SimFrameClient | FrameSource) -> str:
        while not self._stop.is_set():
            try:
                if isinstance(cap, SimFrameClient):
                    got = cap.read()
                    if got is None:
                        return "stream closed"
                    item: tuple[int, Any, bool, int] = (got[0], got[1], True, self.clock())
                else:
                    shot = cap.read()
                    if shot is None:
                        return cap.why or "no frame"
                    item = (shot[0], shot[1], False, self.clock())
            except (OSError, cv2.error, ValueError) as e:
                self.failures += 1
                return f"read failed: {e}"
            self.frames += 1
            try:
                self._slot.get_nowait()
            except queue.Empty:
                pass
            self._slot.put_nowait(item)
        return "stopped"

    def latest(self, timeout_s: float) -> tuple[int, Any, bool, int] | None:
        try:
            return self._slot.get(timeout=timeout_s) if timeout_s > 0 else self._slot.get_nowait()
        except queue.Empty:
            return None

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=3.0)


def _counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(d.items(), key=lambda kv: -kv[1]))


def status_line(s: dict[str, Any], before: dict[str, Any], dt_s: float) -> str:
    """:meth:`Companion.status` as one readable line: link, GNSS, camera, frame rate since the last line, what was
    sent and withheld (and why), and what was rejected."""
    rate = (s["frames"] - before.get("frames", 0)) / dt_s if dt_s > 0 else math.nan
    rejected = sum(s["frames_rejected"].values())
    withheld = sum(s["outputs_suppressed"].values())
    parts = [f"link {'up' if s['connected'] else 'DOWN'}", f"GNSS {str(s['gnss']).removeprefix('GNSS_')}",
             f"camera {'open' if s['camera_open'] else 'CLOSED'} {rate:.1f} fps",
             f"frames {s['frames']} (rejected {rejected}{': ' + _counts(s['frames_rejected']) if rejected else ''}"
             f", stale {s['frames_stale']})", f"EKF steps {s['steps']}",
             f"estimates sent {s['outputs_sent']}, withheld {withheld}"
             + (f" ({_counts(s['outputs_suppressed'])})" if withheld else "")]
    telemetry = sum(s["telemetry_rejected"].values())
    if telemetry:
        parts.append(f"telemetry rejected {telemetry} ({_counts(s['telemetry_rejected'])})")
    if s["estimator_errors"]:
        parts.append(f"estimator errors {s['estimator_errors']}")
    if s["commands"]:
        parts.append(f"heading commands {s['commands']}")
    return " | ".join(parts)


def check_frame(frame: Any, camera: CameraModel) -> tuple[NDArray[np.uint8] | None, str]:
    """The frame as a gray uint8 image of the camera's size, or None and why not."""
    if frame is None:
        return None, "no frame"
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8:
        return None, f"not a uint8 image ({type(frame).__name__} {getattr(frame, 'dtype', '')})"
    w, h = camera.size_px
    if frame.ndim == 3 and frame.shape[2] == 3:
        if frame.shape[:2] != (h, w):
            return None, f"size {frame.shape[1]}x{frame.shape[0]} != calibrated {w}x{h}"
        return np.asarray(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), dtype=np.uint8), ""
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    if frame.ndim != 2:
        return None, f"unexpected shape {frame.shape}"
    if frame.shape != (h, w):
        return None, f"size {frame.shape[1]}x{frame.shape[0]} != calibrated {w}x{h}"
    return frame, ""


# ------------------------------------------------------------------------------------------------ estimator
class CompanionEstimator:
    """The navigation pipeline behind the companion's inputs: the link's samples routed into it, GNSS through the
    :class:`GnssMonitor` (a fix reaches the EKF only while the monitor says ``GNSS_OK``), heights referred to the
    autopilot's home, and the pipeline's estimate mapped onto what the link sends."""

    def __init__(self, gsoe_cfg: GsoeConfig, camera: CameraModel, raw: dict[str, Any], cfg: CompanionConfig,
                 sink: Sink | None = None) -> None:
        ekf_cfg = ekf_config_from_raw(raw.get("ekf", {})) if cfg.use_ekf else None
        self.pipe = NavPipeline(gsoe_cfg, ekf_cfg, pipeline_config_from_raw(raw), camera, sink=sink)
        self.monitor = GnssMonitor(cfg.gnss)
        self.home_amsl_m = math.nan
        self._baro: BaroSample | None = None
        self._ground_set = False

    def feed(self, s: Any) -> list[Announcement]:
        """One validated telemetry sample; returns the GNSS monitor's state changes."""
        pipe = self.pipe
        if isinstance(s, AttitudeSample):
            pipe.on_attitude(s)
        elif isinstance(s, ImuSample):
            pipe.on_imu(s)
        elif isinstance(s, AirspeedSample):
            pipe.on_airspeed(s)
        elif isinstance(s, BaroSample):
            self._baro = s
            pipe.on_baro(s)
        elif isinstance(s, GnssSample):
            return self._gnss(s)
        elif isinstance(s, HomeReading):
            self._home(s)
        return []

    def tick(self, now_us: int) -> list[Announcement]:
        """Advance the clock without a sample (GNSS timeout, frames past their wait, the EKF's air-data start)."""
        ann = self.monitor.tick(now_us)
        self.pipe.gnss_enabled = self.monitor.state == GnssState.GNSS_OK
        self.pipe.poll(now_us)
        return ann

    def _home(self, s: HomeReading) -> None:
        """The home elevation (GNSS heights are referred to it) and, once, the baro's ground level: the baro
        altitude less the autopilot's height above home, read together."""
        self.home_amsl_m = s.alt_amsl_m - s.rel_alt_m
        b = self._baro
        if not self._ground_set and b is not None and abs(s.t_us - b.t_us) <= HOME_BARO_MAX_SKEW_US:
            self.pipe.on_ground_level(b.alt_m - s.rel_alt_m)
            self._ground_set = True
            log.info("baro ground level %.1f m (pressure altitude)", b.alt_m - s.rel_alt_m)

    def _gnss(self, s: GnssSample) -> list[Announcement]:
        """A fix from the link (north/east from its first fix): its height referred to home, then the monitor's
        verdict decides whether the pipeline may use it."""
        d = -(s.alt_msl_m - self.home_amsl_m)
        s = dataclasses.replace(s, pos_ned_m=np.array([s.pos_ned_m[0], s.pos_ned_m[1], d]))
        ann = self.monitor.update(s, self.consistency())
        self.pipe.gnss_enabled = self.monitor.state == GnssState.GNSS_OK
        self.pipe.on_gnss(s)
        return ann

    def consistency(self) -> Consistency | None:
        """What the estimate and air data expect of a GNSS report now (position jump and velocity checks)."""
        pipe = self.pipe
        e = pipe.estimate()
        if e is None:
            return None
        pos_sigma = float(np.max(np.asarray(e.pos_ne_sigma_m, dtype=float)[:2]))
        air_vel = None
        air_sigma = 0.0
        att, tas = pipe.attitude, pipe.tas_m_s
        if att is not None and math.isfinite(tas) and pipe.ekf_cfg is not None:
            yaw = att.yaw_rad - float(e.yaw_bias_rad)
            air_vel = tas * np.array([math.cos(yaw), math.sin(yaw)]) + np.asarray(e.wind_ne_m_s, dtype=float)[:2]
            air_sigma = math.sqrt(float(np.max(np.asarray(e.wind_ne_sigma_m_s, dtype=float)[:2])) ** 2
                                  + pipe.ekf_cfg.tas_sigma_m_s ** 2 + (tas * float(e.heading_sigma_rad)) ** 2)
        return Consistency(pred_pos_ne_m=np.asarray(e.pos_ne_m, dtype=float)[:2], pred_pos_sigma_m=pos_sigma,
                           air_vel_ne_m_s=air_vel, air_vel_sigma_m_s=air_sigma, tas_m_s=float(tas))

    @property
    def quality(self) -> float:
        return self.pipe.quality

    def output(self, t_us: int) -> OutputEstimate:
        """The estimate as the link sends it (invalid, with the reason, before the EKF starts)."""
        e = self.pipe.estimate()
        if e is None:
            nan = math.nan
            z2 = np.full(2, nan)
            return OutputEstimate(t_us, False, nan, nan, nan, z2, np.full((2, 2), nan), z2, np.full((2, 2), nan),
                                  nan, self.quality, int(self.monitor.state), reason=self.pipe.why_no_estimate(),
                                  home_amsl_m=self.home_amsl_m)
        return estimate_to_output(e, int(self.monitor.state), self.quality, self.home_amsl_m, self.pipe.attitude)


def estimate_to_output(e: Any, gnss_state: int, quality: float, home_amsl_m: float = math.nan,
                       attitude: AttitudeSample | None = None) -> OutputEstimate:
    """Map :class:`fusion.ekf.NavEstimate` onto what the link sends (``attitude``: the last AHRS sample, whose roll
    and pitch put the velocity into the body frame)."""
    nan = math.nan
    roll, pitch = (attitude.roll_rad, attitude.pitch_rad) if attitude is not None else (nan, nan)
    vel = np.asarray(e.vel_ned_m_s, dtype=float)
    vs = np.asarray(e.vel_ned_sigma_m_s, dtype=float)
    ws = np.asarray(e.wind_ne_sigma_m_s, dtype=float)
    cov = np.asarray(e.cov_pvw, dtype=float)
    vel_cov = cov[2:4, 2:4].copy() if cov.shape == (6, 6) else np.diag(vs[:2] ** 2)
    wind_cov = cov[4:6, 4:6].copy() if cov.shape == (6, 6) else np.diag(ws[:2] ** 2)
    return OutputEstimate(
        t_us=int(e.t_us), valid=bool(e.valid), drift_rad=float(e.drift_rad), drift_sigma_rad=float(e.drift_sigma_rad),
        ata_rad=float(e.ata_rad), vel_ne_m_s=vel[:2].copy(), vel_cov_ne=vel_cov,
        wind_ne_m_s=np.asarray(e.wind_ne_m_s, dtype=float)[:2].copy(), wind_cov_ne=wind_cov,
        height_agl_m=float(e.height_agl_m), quality=quality, gnss_state=gnss_state, vel_d_m_s=float(vel[2]),
        vel_d_var=float(vs[2] ** 2), reason=str(e.invalid_reason), home_amsl_m=home_amsl_m, roll_rad=float(roll),
        pitch_rad=float(pitch), heading_rad=float(e.heading_rad))


# ------------------------------------------------------------------------------------------------ the app
@dataclass
class Counters:
    frames: int = 0
    frames_rejected: dict[str, int] = field(default_factory=dict)
    frames_stale: int = 0
    steps: int = 0
    estimator_errors: int = 0
    outputs_sent: int = 0
    outputs_suppressed: dict[str, int] = field(default_factory=dict)
    commands: int = 0
    track_reports: int = 0


@dataclass
class _Given:
    """A frame handed to the pipeline: kept until the pipeline has processed it (for the tracker and latency)."""

    t_us: int
    frame: Any
    capture_us: int


def tracking_camera(camera: CameraModel, cfg: TrackingConfig) -> CameraModel:
    """The camera the tracker's pixels refer to (``[companion.tracking] mount``)."""
    if cfg.mount == "forward":
        return forward_camera(camera, math.radians(cfg.forward_depression_deg))
    return camera


class Companion:
    """The companion app.  ``run()`` loops until :meth:`request_stop` (or ``duration_s``)."""

    def __init__(self, connect_url: str, camera_source: str, gsoe_cfg: GsoeConfig, raw: dict[str, Any],
                 log_dir: str, target_px: tuple[float, float] | None = None, gcs_url: str | None = None,
                 signing_key: bytes | None = None) -> None:
        self.cfg = companion_config_from_raw(raw)
        self.camera = CameraModel.from_config(gsoe_cfg.camera)
        self.runlog = RunLog(log_dir, flush_interval_s=self.cfg.log_flush_s)
        self.destroy_link_native = True
        self.link = CompanionLink(connect_url, self.cfg.link)
        self.estimator = CompanionEstimator(gsoe_cfg, self.camera, raw, self.cfg, sink=self._log)
        self.pipe = self.estimator.pipe
        self.monitor = self.estimator.monitor
        self.tracking_camera = tracking_camera(self.camera, self.cfg.tracking)
        self.guidance = TargetGuidance(self.tracking_camera, self.cfg.guidance)
        self.tracker: TemplateTracker | ExternalTracker
        if self.cfg.tracking.source == "mavlink":
            self.tracker = ExternalTracker(self.tracking_camera.size_px, self.cfg.tracking.max_age_s)
        else:
            self.tracker = TemplateTracker(self.cfg.tracker)
        self.target_px = target_px
        self.camera_thread = CameraThread(camera_source, self.cfg, size_px=self.camera.size_px)
        self.counters = Counters()
        self._stop = threading.Event()
        self._last_att: AttitudeSample | None = None
        self._last_suppress_log: dict[str, float] = {}
        self._link_thread: threading.Thread | None = None
        self._given: deque[_Given] = deque(maxlen=MAX_FRAMES_IN_PIPELINE)
        self._last_frame_t_us: int | None = None
        self._last_crc: int | None = None
        self._was_valid: bool | None = None
        self._last_announce = -math.inf
        self._link_up: bool | None = None
        self._rejected_seen: dict[str, int] = {}
        self._offsets_logged: dict[str, int] = {}
        self._guiding = False
        self._last_output = -math.inf
        lc = self.cfg.link
        self._output_period_s = 1.0 / max(lc.named_values_hz, lc.vision_speed_hz, lc.wind_hz)
        self.gcs: Any = None
        if gcs_url:
            from nav.signing import CommandEndpoint

            self.gcs = CommandEndpoint(gcs_url, signing_key, lc.system_id, lc.component_id)

    def _log(self, stream: str, record: dict[str, Any]) -> None:
        """Write a record (the log formats numpy scalars as numbers: :class:`common.logio.CsvStream`)."""
        self.runlog.write(stream, record)

    def _event(self, kind: str, detail: str, level: int = logging.INFO, t_us: int | None = None) -> None:
        """A state change: logged and written to ``events.csv``."""
        log.log(level, "%s: %s", kind, detail)
        self._log("events", {"t_us": now_us() if t_us is None else t_us, "kind": kind, "detail": detail})

    def request_stop(self) -> None:
        self._stop.set()

    # ---------------------------------------------------------------- link management
    def _ensure_link(self) -> None:
        up = self.link.stats.connected
        if up != self._link_up:
            if self._link_up is not None or up:
                self._event("link", "connected" if up else "lost", logging.INFO if up else logging.WARNING)
            self._link_up = up
        if self._link_thread is not None and (self._link_thread.is_alive() or self.link.started):
            return

        def connect() -> None:
            if not self.link.start(self.cfg.reconnect_s):
                log.info("autopilot not found on %s; retrying", self.link.url)

        self._link_thread = threading.Thread(target=connect, name="link-connect", daemon=True)
        self._link_thread.start()

    # ---------------------------------------------------------------- inputs
    def _drain_telemetry(self) -> None:
        while True:
            try:
                s = self.link.samples.get_nowait()
            except queue.Empty:
                return
            try:
                if isinstance(s, TrackReading):
                    self._track_report(s)
                    continue
                if isinstance(s, AttitudeSample):
                    self._last_att = s
                for ann in self.estimator.feed(s):
                    self._announce(ann.t_us, ann.old, ann.new, ann.reason, ann.text)
            except Exception as e:  # the estimators must not take the loop down
                self.counters.estimator_errors += 1
                log.exception("estimator failed on %s: %s", type(s).__name__, e)
            self._handle_results()

    def _announce(self, t_us: int, old: GnssState, new: GnssState, reason: str, text: str) -> None:
        self._log("gnss_state", {"t_us": t_us, "old": int(old), "new": int(new), "name": new.name,
                                 "reason": reason})
        self._event("gnss", f"{old.name} -> {new.name}: {reason}", logging.WARNING if new > old else logging.INFO,
                    t_us)
        self.link.send_statustext(text, "warning" if new > old else "info")

    def _track_report(self, r: TrackReading) -> None:
        self.counters.track_reports += 1
        if not isinstance(self.tracker, ExternalTracker):
            return
        self.tracker.push(r.t_us, r.x_norm, r.y_norm, r.active)
        self._guide(r.t_us, None)

    # ---------------------------------------------------------------- frames
    def _take_frame(self, item: tuple[int, Any, bool, int]) -> None:
        """Check a new frame and hand it to the pipeline (which holds it until attitude covers its exposure)."""
        t_us, frame, vehicle_clock, capture_us = item
        if vehicle_clock:
            sync = self.link.guard._sync.get("attitude")
            if sync is None or sync.offset_us is None:
                self._reject_frame("no clock sync with the vehicle yet")
                return
            t_us = t_us + sync.offset_us
        else:  # the companion's clock onto the samples' (the autopilot's) clock
            t_us = self.link.from_companion_us(t_us)
        gray, why = check_frame(frame, self.camera)
        if gray is None:
            self._reject_frame(why)
            return
        if self._last_frame_t_us is not None and t_us <= self._last_frame_t_us:
            self._reject_frame(f"stamp not increasing ({t_us - self._last_frame_t_us} us)")
            return
        # a sparse grid, not the whole frame (on the capture-to-output path): a camera that repeats its frame
        # repeats it, and a live frame's noise changes it
        crc = zlib.crc32(np.ascontiguousarray(gray[::FROZEN_STRIDE, ::FROZEN_STRIDE]).data)
        if crc == self._last_crc:
            self._reject_frame("frozen frame (identical to the previous one)")
            return
        self._last_crc = crc
        if self.link.now_us() - t_us > self.cfg.max_frame_age_s * 1e6:
            self.counters.frames_stale += 1
            return
        self._last_frame_t_us = t_us
        self.counters.frames += 1
        self._given.append(_Given(t_us, frame, capture_us))
        self.pipe.on_frame(t_us, gray)
        self._handle_results()

    def _handle_results(self) -> None:
        """The EKF's divergences and resets announced; outputs and guidance for every frame the pipeline
        processed."""
        for ev in self.pipe.drain_events():
            self._event("ekf", f"{ev.kind}: {ev.reason}", logging.WARNING, ev.t_us)
            self.link.send_statustext(ev.text, "warning")
        for res in self.pipe.drain():
            g = None
            while self._given and self._given[0].t_us <= res.t_us:
                g = self._given.popleft()
            given = g if g is not None and g.t_us == res.t_us else None
            self.counters.steps += len(res.steps)
            self._outputs(res.t_us, given.capture_us if given is not None else None)
            if given is not None and isinstance(self.tracker, TemplateTracker):
                self._guide(res.t_us, given.frame)

    def _reject_frame(self, why: str) -> None:
        key = why.split(" (")[0]
        n = self.counters.frames_rejected.get(key, 0) + 1
        self.counters.frames_rejected[key] = n
        if n == 1 or n % 100 == 0:
            log.warning("frame rejected: %s (%d so far)", why, n)
        self._log("frames_rejected", {"t_us": now_us(), "reason": why})

    def _outputs(self, t_us: int, capture_us: int | None) -> None:
        """Send the estimate (after every frame; between frames at the fastest output rate, so a camera failure
        does not silence the outputs the EKF can still stand behind, nor the status values)."""
        self._last_output = time.monotonic()
        out = self._output()
        reason = self.link.send_estimate(out, capture_us)
        sent_us = now_us()
        valid = not reason
        if reason:
            key = reason.split(" (")[0]
            self.counters.outputs_suppressed[key] = self.counters.outputs_suppressed.get(key, 0) + 1
            last = self._last_suppress_log.get(key, -math.inf)
            if time.monotonic() - last > self.cfg.status_s:
                log.info("not sending the estimate: %s", reason)
                self._last_suppress_log[key] = time.monotonic()
        else:
            self.counters.outputs_sent += 1
        if valid != self._was_valid and reason != "not connected":
            self._validity_changed(valid, reason)
        self._log("outputs", {"t_us": t_us, "sent": valid, "reason": reason,
                              "drift_rad": out.drift_rad, "drift_sigma_rad": out.drift_sigma_rad,
                              "ata_rad": out.ata_rad, "vel_n_m_s": out.vel_ne_m_s[0], "vel_e_m_s": out.vel_ne_m_s[1],
                              "wind_n_m_s": out.wind_ne_m_s[0], "wind_e_m_s": out.wind_ne_m_s[1],
                              "quality": out.quality, "gnss_state": int(self.monitor.state),
                              "latency_us": sent_us - capture_us if capture_us is not None else None})

    def _output(self) -> OutputEstimate:
        return self.estimator.output(self.link.now_us())

    def _validity_changed(self, valid: bool, reason: str) -> None:
        first = self._was_valid is None
        self._was_valid = valid
        if first and not valid:
            self._event("estimate", f"invalid: {reason}")
            return
        self._event("estimate", "valid" if valid else f"invalid: {reason}",
                    logging.INFO if valid else logging.WARNING)
        now = time.monotonic()
        if now - self._last_announce >= self.cfg.announce_min_interval_s:
            self._last_announce = now
            text = "GSOE estimate valid" if valid else f"GSOE invalid: {reason}"
            self.link.send_statustext(text[:STATUSTEXT_MAX_CHARS], "info" if valid else "warning")

    # ---------------------------------------------------------------- guidance
    def _guide(self, t_us: int, frame: Any) -> None:
        if frame is not None and self.target_px is not None and not self.tracker.active:
            if self.tracker.designate(t_us, frame, self.target_px):
                log.info("target designated at %s", self.target_px)
                self.target_px = None
        if (not self.tracker.active and not self._guiding) or not self.guidance.due(t_us) or self._last_att is None:
            return
        res = self.tracker.update(t_us, frame)
        out = self._output()
        a = self._last_att
        fix, cmd = self.guidance.step(t_us, res.xy_px if res.valid else None, a.roll_rad, a.pitch_rad, a.yaw_rad,
                                      out.height_agl_m, out.drift_rad, out.drift_sigma_rad, out.valid)
        self._log("guidance", {"t_us": t_us, "track_valid": res.valid, "track_x_px": res.xy_px[0],
                               "track_y_px": res.xy_px[1], "range_m": fix.range_m,
                               "bearing_rad": fix.bearing_rad, "heading_cmd_rad": cmd.heading_rad,
                               "course_cmd_rad": cmd.course_rad, "drift_used_rad": cmd.drift_used_rad,
                               "drift_applied": cmd.drift_applied, "valid": cmd.valid,
                               "reason": cmd.reason or fix.reason or res.reason})
        if cmd.valid:
            self._guiding = True
            self.link.send_heading_command(change_heading_command_fields(
                cmd, self.cfg.guidance, self.link.target_system, self.link.target_component))
            self.counters.commands += 1

    def _gcs_commands(self) -> None:
        """Ground-station commands on the companion's own (optionally signed) link."""
        if self.gcs is None:
            return
        for msg in self.gcs.poll():
            if msg.get_type() != "COMMAND_LONG" or msg.command != MAV_CMD_USER_1:
                continue
            xy = (float(msg.param1), float(msg.param2))
            ok = pixel_in_image(xy, self.camera.size_px)       # the endpoint passes only commands addressed to us
            if ok:
                self.tracker.drop()
                self.guidance.reset()
                self._guiding = False
                self.target_px = xy
                log.info("ground station designated the target at %s", xy)
            self.gcs.conn.mav.command_ack_send(MAV_CMD_USER_1, 0 if ok else 2, 0, 0, msg.get_srcSystem(),
                                               msg.get_srcComponent())

    # ---------------------------------------------------------------- loop
    def _housekeeping(self) -> None:
        while True:
            try:
                t, what = self.camera_thread.events.get_nowait()
            except queue.Empty:
                break
            self._event("camera", what, logging.INFO if what == "opened" else logging.WARNING, t)
        rej = self.link.guard.rejected
        for key, n in list(rej.items()):
            if n != self._rejected_seen.get(key, 0):
                self._event("telemetry_rejected", f"{key}: {n - self._rejected_seen.get(key, 0)} more ({n} total)",
                            logging.WARNING)
                self._rejected_seen[key] = n
        for kind, sync in list(self.link.guard._sync.items()):  # samples' t_us = autopilot us + offset_us
            if sync.offset_us is not None and sync.offset_us != self._offsets_logged.get(kind):
                self._offsets_logged[kind] = sync.offset_us
                self._log("clock_sync", {"t_us": self.link.now_us(), "kind": kind, "offset_us": sync.offset_us})

    def status(self) -> dict[str, Any]:
        return {"connected": self.link.stats.connected, "gnss": self.monitor.state.name,
                "camera_open": self.camera_thread.opened, **dataclasses.asdict(self.counters),
                "telemetry_rejected": dict(self.link.guard.rejected), "sent": dict(self.link.stats.sent),
                "autopilot_firmware": self.link.guard.firmware, "baro_temp_clamp_c": self.link.guard.baro_temp_clamp_c,
                "send_errors": dict(self.link.stats.send_errors),
                "send_latency_ms": {k: {"n": len(v), "median": float(np.median(v)) / 1000.0}
                                    for k, v in self.link.stats.send_latency_us.items() if len(v)}}

    def run(self, duration_s: float | None = None) -> dict[str, Any]:
        start = time.monotonic()
        self._status_before: dict[str, Any] = {}
        self._status_t = start
        last_status = last_flush = last_house = start
        frame_wait_s = min(0.05, self.cfg.frame_timeout_s)
        poll_s = 0.002
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if duration_s is not None and now - start >= duration_s:
                    break
                self._ensure_link()
                self._drain_telemetry()
                self._gcs_commands()
                for ann in self.estimator.tick(self.link.now_us()):
                    self._announce(ann.t_us, ann.old, ann.new, ann.reason, ann.text)
                self._handle_results()
                item = self.camera_thread.latest(poll_s if self.pipe.frames_pending else frame_wait_s)
                if item is not None:
                    self._drain_telemetry()
                    self._take_frame(item)
                if time.monotonic() - self._last_output >= self._output_period_s:
                    self._outputs(self.link.now_us(), None)
                if now - last_house >= min(1.0, self.cfg.log_flush_s):
                    last_house = now
                    self._housekeeping()
                if now - last_flush >= self.cfg.log_flush_s:
                    last_flush = now
                    self.runlog.flush()
                if now - last_status >= self.cfg.status_s:
                    last_status = now
                    log.info("status: %s", status_line(self.status(), self._status_before, now - self._status_t))
                    self._status_before, self._status_t = self.status(), now
        finally:
            self.close()
        return self.status()

    def close(self) -> None:
        """Stop the camera, close the logs (so nothing logged can be lost), then the ground-station and autopilot
        links; with ``destroy_link_native`` false the native MAVSDK instance is left to the process's exit."""
        self.camera_thread.stop()
        self._housekeeping()
        self.runlog.close()
        if self.gcs is not None:
            self.gcs.close()
        self.link.stop(destroy_native=self.destroy_link_native)
