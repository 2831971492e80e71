"""A real image sequence through the navigation pipeline (``gsoe replay-frames``), against its reference velocity.

What is fed (frames and units as in :mod:`gsoe`; the sequence's clock)
    One :class:`pipeline.navpipeline.NavPipeline` per run, the one every driver feeds.  For each frame, in time
    order: its attitude (``on_attitude``), its height above ground as a baro sample on a ground level of 0
    (``on_baro``: the optical estimator takes the baro's height while no EKF runs), then the image (``on_frame``),
    read from its file as 8-bit grey.  The optical steps come out of ``drain()``.  The EKF runs only where the
    other sensors exist: these sequences carry no IMU, air data or GNSS, so the pipeline is built with
    ``ekf_cfg=None``, and with the ``[pipeline.profiles.frames_only]`` profile (a frame comes with its own attitude
    sample and waits for nothing; no gyro to compensate the AHRS with).

Estimator settings
    ``config/default.toml``'s ``[stab]``, ``[match]``, ``[cycle]``, ``[integrity]``, with a profile of
    ``[replay_frames.profiles.<name>]`` on top (tables ``stab``, ``match``, ``cycle``); the camera is the
    sequence's own (CLIF) or the one given.

Per frame pair (frames k-1 and k, both in one TM cycle)
    The optical ground velocity is the difference of the two steps' accumulated migrations times the cycle's ground
    sample distance, over the frames' time difference, rotated from the cycle's base heading into NED::

        d_fwd, d_right = (dy_k - dy_k-1) * gsd, (dx_k - dx_k-1) * gsd
        v_n = (d_fwd cos(psi0) - d_right sin(psi0)) / dt,   v_e = (d_fwd sin(psi0) + d_right cos(psi0)) / dt

    A pair is *accepted* when frame k's step is valid (the base step of a new cycle counts as valid for frame k-1).
    The reference is the mean of the two frames' reference velocities (the INS velocity at each exposure; over a
    pair that is the chord's velocity to 0.1 % in CLIF's turns).  Errors: the speed error ``|v| / |v_ref| - 1``
    (percent), the course error (deg, wrapped), the vector error (m/s); pairs slower than
    ``[replay_frames] speed_min_m_s`` get no speed or course error.

Outputs (``out_dir``)
    ``pairs.csv`` (one record per pair, :mod:`common.logio` format), ``gsoe.csv`` (the optical steps),
    ``metrics.json`` (the figures below, the sequence's notes and the settings used).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from numpy.typing import NDArray

from common.angles import angle_diff
from common.config import ConfigError, In, Validated, build, to_dict, with_profile
from common.logio import RunLog
from common.samples import BaroSample, GsoeStep
from gsoe.camera import CameraModel
from gsoe.config import CameraConfig, GsoeConfig
from nav.imageseq import ImageSequence
from pipeline.config import load_gsoe_config
from pipeline.navpipeline import NavPipeline, pipeline_config_from_raw

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
#: The pipeline profile of a sequence without an IMU (``[pipeline.profiles.frames_only]``).
PIPELINE_PROFILE = "frames_only"
#: The estimator sections a ``[replay_frames.profiles.<name>]`` may hold.
PROFILE_SECTIONS = ("stab", "match", "cycle")
#: Percentiles reported.
P95 = 95.0


@dataclass(frozen=True)
class ReplayFramesConfig(Validated):
    """``[replay_frames]`` of the configuration file (its ``profiles`` are read by :func:`estimator_config`)."""

    # pairs slower than this (reference, m/s) get no course or relative speed error
    speed_min_m_s: Annotated[float, In(0.0, 100.0)] = 1.0


@dataclass(frozen=True, slots=True)
class FramePair:
    """One frame pair's optical velocity against the reference (module docstring); nan where there is none."""

    k: int                      # index of the later frame
    t_us: int
    dt_s: float
    cycle_id: int               # -1: no step of one cycle covers both frames
    accepted: bool
    vel_ne_m_s: NDArray[np.float64]
    ref_vel_ne_m_s: NDArray[np.float64]
    speed_err_pct: float
    course_err_deg: float
    vel_err_m_s: float
    psr: float

    def as_record(self) -> dict[str, Any]:
        v, r = self.vel_ne_m_s, self.ref_vel_ne_m_s
        return {"t_us": self.t_us, "k": self.k, "dt_s": self.dt_s, "cycle_id": self.cycle_id,
                "accepted": self.accepted, "vel_n_m_s": v[0], "vel_e_m_s": v[1], "ref_vel_n_m_s": r[0],
                "ref_vel_e_m_s": r[1], "speed_m_s": math.hypot(v[0], v[1]), "ref_speed_m_s": math.hypot(r[0], r[1]),
                "speed_err_pct": self.speed_err_pct, "course_err_deg": self.course_err_deg,
                "vel_err_m_s": self.vel_err_m_s, "psr": self.psr}


@dataclass(frozen=True)
class ReplayFramesResult:
    metrics: dict[str, Any]
    pairs: tuple[FramePair, ...]
    steps: tuple[GsoeStep, ...]


def estimator_config(camera: CameraConfig, config_path: str | Path | None = None,
                     profile: str | None = None) -> tuple[GsoeConfig, dict[str, Any]]:
    """The optical estimator's config for a sequence: the file's sections with ``[replay_frames.profiles.<profile>]``
    on top, and ``camera``; also the raw mapping."""
    _, raw = load_gsoe_config(config_path)
    table = raw.get("replay_frames", {})
    top: dict[str, Any] = {}
    if profile is not None:
        top = with_profile(table, profile, "replay_frames")
        top = {k: v for k, v in top.items() if k in PROFILE_SECTIONS}
    data: dict[str, Any] = {}
    for name in ("stab", "match", "cycle", "integrity"):
        section = dict(raw.get(name, {}))
        extra = top.get(name, {})
        if not isinstance(extra, dict):
            raise ConfigError(f"replay_frames.profiles.{profile}.{name}", "must be a table")
        data[name] = {**section, **extra}
    data["camera"] = dataclasses.asdict(camera)
    return build(GsoeConfig, data, ""), raw


def _replay_config(raw: dict[str, Any]) -> ReplayFramesConfig:
    table = with_profile(raw.get("replay_frames", {}), None, "replay_frames")
    return build(ReplayFramesConfig, table, "replay_frames")


def read_grey(path: Path) -> NDArray[np.uint8]:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise FileNotFoundError(2, "not a readable image", str(path))
    return np.asarray(img)


def run_replay_frames(seq: ImageSequence, *, out_dir: str | Path | None = None,
                      config_path: str | Path | None = None, profile: str | None = None,
                      camera: CameraConfig | None = None) -> ReplayFramesResult:
    """Feed ``seq`` through the pipeline and compare each frame pair with the reference (module docstring).

    ``camera``: the camera when the sequence has none of its own (a generic CSV); ``profile``: the estimator
    profile (``[replay_frames.profiles.<profile>]``) or None.
    """
    cam_cfg = seq.camera or camera
    if cam_cfg is None:
        raise ConfigError("camera", f"sequence {seq.name!r} has no camera of its own: give a camera file")
    gsoe_cfg, raw = estimator_config(cam_cfg, config_path, profile)
    rcfg = _replay_config(raw)
    pcfg = pipeline_config_from_raw(raw, PIPELINE_PROFILE)
    runlog = RunLog(out_dir) if out_dir is not None else None

    def sink(stream: str, record: dict[str, Any]) -> None:
        if runlog is not None and stream == "gsoe":
            runlog.write(stream, record)

    pipe = NavPipeline(gsoe_cfg, None, pcfg, CameraModel.from_config(cam_cfg), sink=sink)
    by_frame: list[list[GsoeStep]] = [[] for _ in seq.frames]
    index = {f.t_us: k for k, f in enumerate(seq.frames)}
    try:
        for f in seq.frames:
            pipe.on_attitude(f.attitude)
            pipe.on_baro(BaroSample(t_us=f.t_us, alt_m=f.height_agl_m))
            pipe.on_frame(f.t_us, read_grey(f.image))
            for r in pipe.drain():
                by_frame[index[r.t_us]].extend(r.steps)
        pairs = frame_pairs(seq, by_frame, rcfg.speed_min_m_s)
        if runlog is not None:
            for p in pairs:
                runlog.write("pairs", p.as_record())
    finally:
        if runlog is not None:
            runlog.close()
    metrics = pair_metrics(pairs)
    metrics.update({
        "sequence": seq.name, "frames": len(seq.frames), "profile": profile or "",
        "duration_s": (seq.frames[-1].t_us - seq.frames[0].t_us) / US_PER_S if seq.frames else 0.0,
        "frames_processed": pipe.status.frames, "frames_no_step": pipe.status.frames_no_step,
        "steps": pipe.status.steps, "steps_valid": pipe.status.steps_valid,
        "notes": list(seq.notes), "sequence_info": dict(seq.info), "camera": to_dict(cam_cfg),
        "stab": to_dict(gsoe_cfg.stab), "match": to_dict(gsoe_cfg.match), "cycle": to_dict(gsoe_cfg.cycle),
    })
    if out_dir is not None:
        from common.report import write_metrics

        write_metrics(out_dir, metrics)
    return ReplayFramesResult(metrics=metrics, pairs=tuple(pairs),
                              steps=tuple(s for steps in by_frame for s in steps))


def frame_pairs(seq: ImageSequence, by_frame: list[list[GsoeStep]], speed_min_m_s: float) -> list[FramePair]:
    """One :class:`FramePair` per consecutive pair of frames (module docstring)."""
    out = []
    nan2 = np.full(2, math.nan)
    for k in range(1, len(seq.frames)):
        f0, f1 = seq.frames[k - 1], seq.frames[k]
        dt_s = (f1.t_us - f0.t_us) / US_PER_S
        ref = 0.5 * (f0.ref_vel_ned_m_s[:2] + f1.ref_vel_ned_m_s[:2])
        prev = {s.cycle_id: s for s in by_frame[k - 1]}
        cur = next((s for s in by_frame[k] if not s.new_cycle and s.cycle_id in prev), None)
        if cur is None:
            out.append(FramePair(k, f1.t_us, dt_s, -1, False, nan2.copy(), ref, math.nan, math.nan, math.nan,
                                 math.nan))
            continue
        p = prev[cur.cycle_id]
        accepted = bool(cur.valid and p.valid)
        vel = nan2.copy()
        if accepted:
            d_fwd = (cur.dy_px - p.dy_px) * cur.gsd_m_px
            d_right = (cur.dx_px - p.dx_px) * cur.gsd_m_px
            c, s = math.cos(cur.base_yaw_rad), math.sin(cur.base_yaw_rad)
            vel = np.array([d_fwd * c - d_right * s, d_fwd * s + d_right * c]) / dt_s
        speed_err = course_err = vel_err = math.nan
        ref_speed = math.hypot(ref[0], ref[1])
        if accepted and np.all(np.isfinite(ref)) and np.all(np.isfinite(vel)):
            vel_err = float(np.hypot(*(vel - ref)))
            if ref_speed >= speed_min_m_s:
                speed_err = 100.0 * (math.hypot(vel[0], vel[1]) / ref_speed - 1.0)
                course_err = math.degrees(float(angle_diff(math.atan2(vel[1], vel[0]), math.atan2(ref[1], ref[0]))))
        out.append(FramePair(k, f1.t_us, dt_s, cur.cycle_id, accepted, vel, ref, speed_err, course_err, vel_err,
                             cur.quality.psr))
    return out


def _stat(values: list[float], fn: Any) -> float:
    a = np.asarray([v for v in values if math.isfinite(v)])
    return float(fn(a)) if a.size else math.nan


def pair_metrics(pairs: list[FramePair]) -> dict[str, Any]:
    """Figures over the accepted pairs: medians (signed, and of the magnitude) and 95th percentiles of the
    magnitude of the speed and course errors, the vector error's RMS, and the accepted fraction."""
    acc = [p for p in pairs if p.accepted]
    se = [p.speed_err_pct for p in acc]
    ce = [p.course_err_deg for p in acc]
    ve = [p.vel_err_m_s for p in acc]
    return {
        "pairs": len(pairs), "pairs_accepted": len(acc),
        "accepted_frac": len(acc) / len(pairs) if pairs else math.nan,
        "pairs_with_reference": sum(1 for p in acc if math.isfinite(p.speed_err_pct)),
        "speed_err_median_pct": _stat(se, np.median),
        "speed_abs_err_median_pct": _stat(se, lambda a: np.median(np.abs(a))),
        "speed_abs_err_p95_pct": _stat(se, lambda a: np.percentile(np.abs(a), P95)),
        "course_err_median_deg": _stat(ce, np.median),
        "course_abs_err_median_deg": _stat(ce, lambda a: np.median(np.abs(a))),
        "course_abs_err_p95_deg": _stat(ce, lambda a: np.percentile(np.abs(a), P95)),
        "vel_err_rms_m_s": _stat(ve, lambda a: np.sqrt(np.mean(a * a))),
    }
