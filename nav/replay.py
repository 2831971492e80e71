"""Replay of a real flight log through the navigation EKF (``gsoe replay``).

What is fed (frames and units as in :mod:`gsoe`; times on the log's clock, :mod:`nav.logreader`)
    The log's samples go into :class:`fusion.ekf.NavEkf` in time order: every IMU sample (``predict``) with the AHRS
    attitude *interpolated* to the IMU stamp (spherical linear interpolation between the two logged attitudes that
    bracket it; telemetry logs carry attitude at 2-4 Hz, the EKF wants it within ``ekf.att_max_age_s`` of each IMU
    sample; a replay is offline, so interpolating towards the next sample is allowed), true airspeed, barometric
    altitude and GNSS position and velocity.  The EKF starts at the first valid GNSS fix (position and horizontal
    velocity finite, attitude available); the local NED origin is the log's first 3-D fix.  Baro altitudes are
    shifted so that they equal the GNSS height at that instant (the EKF's ``baro_bias`` takes the drift after it).

Optical measurements: a stand-in from GNSS velocity
    No current log has camera data.  Unless ``optical=False`` (``--no-optical``), a *virtual camera* is synthesised
    from GNSS ground velocity, and the report and ``metrics.json`` say so (``optical_source =
    "synthetic_from_gnss_velocity"``).  It runs the cycle logic of :class:`gsoe.cycle.GsoeEstimator` without images:
    frames at ``cycle.rate_hz``; a cycle's base step (``new_cycle``) at its first frame; each later frame reports the
    horizontal GNSS velocity integrated (trapezoid, velocity interpolated linearly between fixes) since the base
    frame, rotated into the base frame's heading (the AHRS yaw at the base frame) and divided by the ground sample
    distance ``h_base / focal_px`` of the base frame, plus Gaussian pixel noise drawn from the caller's seeded
    generator; a cycle ends when the template's next predicted position would leave the base image (the
    ``stab``/``cycle`` geometry), after ``cycle.max_cycle_s``, and no frame is produced outside the stabilisable
    attitude range (``stab.roll_limit_deg``/``pitch_limit_deg``), below ``replay.min_camera_height_m`` or where the
    GNSS velocity has a gap.  The noise is ``replay.optical_sigma_px`` per axis and step (independent), or, when that
    is 0, the EKF's own optical noise model for the step
    (:meth:`fusion.measurements.OpticalDisplacement.noise_sigma_px`, whose defaults are fitted to the simulated
    camera's pixel errors against truth) at nominal match quality.
    The height ``h`` of the virtual camera is the baro altitude above a flat ground whose level is the *take-off
    point*: the baro altitude where the log shows the aircraft on the ground (GNSS ground speed below
    ``replay.on_ground_speed_m_s`` and airspeed below ``ekf.tas_min_m_s``) before it flew (else after it landed).
    A log that starts and ends in the air has no take-off point; then, and when that reference gives implausible
    heights (below ``min_camera_height_m`` or above ``max_camera_height_m``), the lowest altitude of the flight is
    assumed to be ``replay.lowest_height_agl_m`` above the ground: a fixed height, followed by the baro altitude
    from there.  The EKF is initialised with the terrain height of the same reference, so the stand-in's scale is
    consistent with the filter's height (a real camera would also be subject to the unknown real terrain).

GNSS outage (``gnss_off_at_s``, seconds from the start of the log)
    From then on GNSS position and velocity are *not fused*: the run dead-reckons on IMU, air data and the optical
    stand-in.  The stand-in keeps running from GNSS velocity: it plays the camera, which would still see the ground
    (GNSS velocity is its source, not an aid the filter sees); its noise is independent of the GNSS fixes the track is
    compared with, but its source is GNSS, so the dead-reckoning figure measures how well the filter integrates
    noisy displacement measurements through its height/scale and heading states, not a real camera.  With
    ``optical=False`` the run dead-reckons on IMU and air data only (wind held from before the outage).  The
    dead-reckoned track is compared with the (unfused) GNSS track: ``dr_error_m`` is the horizontal distance between
    the EKF position (interpolated to the fix time) and the last GNSS fix, ``dr_distance_m`` the length of the GNSS
    track from ``gnss_off_at_s`` to that fix.

Configuration profile ``telemetry_replay`` (``[ekf.profiles.telemetry_replay]`` and
``[pipeline.profiles.telemetry_replay]`` in ``config/default.toml``, where each setting says why; the ``[replay.ekf]``
table overrides the EKF's on top)
    Telemetry carries 10 Hz IMU and 2-4 Hz attitude, and the autopilot's WIND is a steady-wind estimate: the profile
    raises the acceleration noise, makes the wind one random walk as ArduPilot's, weights the airspeed as gusty, turns
    the lift-model angle of attack off, and takes the log's attitude as given (docs/ekf-tuning.md); like ArduPilot's
    EKF it takes the log's calibrated airspeed as exact (no scale learnt), fuses the zero-sideslip pseudo-measurement
    (the log's airframe is not the simulator's) and GNSS position as white noise (docs/real-data.md; what a log says
    about these: :mod:`nav.replay_checks`).
    GNSS samples are moved back by ``replay.gnss_delay_s`` (0.2 s, ArduPilot's default GPS lag): logged fixes carry
    the time they reached the autopilot (docs/real-data.md: what the ALFA log says of the lag).

Wind against the autopilot
    The EKF's wind (velocity of the air, N/E) is interpolated to the time of every autopilot wind sample (MAVLink
    WIND, DataFlash NKF2/XKF2 VWN/VWE, ULog ``wind``) from ``replay.wind_settle_s`` after the EKF started to the end
    of its output; ``wind_rmse_vs_autopilot_m_s`` is the RMS length of the vector difference.  The autopilot's
    estimate is another filter's answer, not truth.

Outputs (``out_dir``)
    ``metrics.json``, ``ekf.csv``/``aid_status.csv`` (:mod:`common.logio`, one record per IMU sample), ``gsoe.csv`` (the
    synthetic optical steps), ``gnss.csv``, ``autopilot_wind.csv``, ``wind.png``, ``track.png``,
    ``position_error.png`` and ``report.html``.

Bad input
    Whatever :func:`nav.logreader.read_log` could read is replayed; its warnings are carried into the metrics and the
    report.  A log without a GNSS fix, IMU or attitude, or with less than ``replay.min_span_s`` of data after the
    first fix raises :class:`ReplayError` with a message naming what is missing.
"""

from __future__ import annotations

import dataclasses
import html
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import cumulative_trapezoid
from scipy.spatial.transform import Rotation, Slerp

from common import metrics as M
from common.angles import angle_diff
from common.atmosphere import ARDUPILOT_3_BARO_TEMP_CLAMP_C
from common.config import ConfigError, In, Validated, build, require
from common.logio import RunLog
from common.samples import AttitudeSample, GsoeStep, ImuSample, MatchQuality
from fusion.config import EkfConfig, ekf_config_from_raw
from fusion.ekf import NavEstimate
from fusion.measurements import OpticalDisplacement
from gsoe.camera import CameraModel
from gsoe.config import GsoeConfig
from gsoe.cycle import base_reference_px
from nav.logreader import AirspeedSample, AutopilotWind, BaroSample, FlightLog, GnssSample, read_log
from pipeline.config import load_gsoe_config
from pipeline.navpipeline import NavPipeline, pipeline_config_from_raw

log = logging.getLogger(__name__)

US_PER_S = 1_000_000
OPTICAL_SOURCE_SYNTHETIC = "synthetic_from_gnss_velocity"
OPTICAL_SOURCE_NONE = "none"
#: CSV streams (:mod:`common.logio`) a replay writes into its output folder.
CSV_STREAMS = ("ekf", "aid_status", "gsoe", "gnss", "autopilot_wind", "samples_rejected", "ekf_events")

#: the configuration profile a replay of telemetry runs with (``[ekf.profiles.*]``, ``[pipeline.profiles.*]``)
REPLAY_PROFILE = "telemetry_replay"

class ReplayError(ValueError):
    """The log cannot be replayed (no GNSS fix, no IMU or attitude, too little data, bad option); the message says
    what is missing."""


@dataclass(frozen=True)
class ReplayConfig(Validated):
    """Replay settings (``[replay]`` table of the configuration file; every field optional).

    ``wind_settle_s``: the wind comparison starts this long after the EKF started (its wind converges first).
    ``gnss_delay_s``: receiver lag: a GNSS sample is used at its log stamp minus this (module docstring).
    ``min_span_s``: at least this much IMU data after the first usable GNSS fix, else the log is "not enough data".
    ``att_max_gap_s``: attitude is interpolated only between logged samples at most this far apart (IMU samples and
    camera frames in longer gaps are skipped).  ``gnss_max_gap_s``: the same for the GNSS velocity behind the optical
    stand-in.  ``on_ground_speed_m_s``: GNSS ground speed below which (with the airspeed below ``ekf.tas_min_m_s``)
    the aircraft counts as on the ground, for the take-off point.  ``lowest_height_agl_m``: without a usable take-off
    point, the height above flat ground assumed at the lowest altitude of the log.  ``min_camera_height_m`` /
    ``max_camera_height_m``: the virtual camera produces no frame below the first; a take-off reference that puts
    the flight outside [min, max] is implausible and replaced by the assumption.  ``optical_sigma_px``: one-sigma
    pixel noise per axis added to each synthetic step (0: the EKF's optical noise model for that step).
    ``baro_temp_clamp_c``: the clamp of the baro temperature taken as air temperature (degC,
    :mod:`common.atmosphere`) for a log that does not name its firmware (the shared ALFA logs do not; they are
    ArduPilot 3.x: 25 degC); a log that names an ArduPilot version gets that version's clamp.
    """

    wind_settle_s: Annotated[float, In(0.0, 3600.0)] = 20.0
    gnss_delay_s: Annotated[float, In(0.0, 5.0)] = 0.2
    min_span_s: Annotated[float, In(0.1, 3600.0)] = 5.0
    att_max_gap_s: Annotated[float, In(1e-3, 60.0)] = 1.0
    gnss_max_gap_s: Annotated[float, In(1e-3, 60.0)] = 1.0
    on_ground_speed_m_s: Annotated[float, In(0.0, 50.0)] = 3.0
    lowest_height_agl_m: Annotated[float, In(1.0, 10000.0)] = 30.0
    min_camera_height_m: Annotated[float, In(0.1, 10000.0)] = 10.0
    max_camera_height_m: Annotated[float, In(1.0, 100000.0)] = 3000.0
    optical_sigma_px: Annotated[float, In(0.0, 100.0)] = 0.0
    baro_temp_clamp_c: Annotated[float, In(-40.0, 85.0)] = ARDUPILOT_3_BARO_TEMP_CLAMP_C

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.max_camera_height_m > self.min_camera_height_m, "max_camera_height_m",
                "must be larger than min_camera_height_m")


def replay_configs_from_raw(raw: Mapping[str, Any]) -> tuple[ReplayConfig, EkfConfig]:
    """The replay settings and the EKF configuration a replay runs with, from a whole configuration mapping.

    The EKF configuration is ``[ekf]`` with its profile :data:`REPLAY_PROFILE` on top and then the ``[replay.ekf]``
    table (any :class:`~fusion.config.EkfConfig` key); errors name ``replay.<field>`` or ``ekf.<field>``.
    """
    table = raw.get("replay", {})
    if not isinstance(table, Mapping):
        raise ConfigError("replay", f"must be a table, got {type(table).__name__}")
    overrides = table.get("ekf", {})
    if not isinstance(overrides, Mapping):
        raise ConfigError("replay.ekf", f"must be a table, got {type(overrides).__name__}")
    rcfg = build(ReplayConfig, {k: v for k, v in table.items() if k != "ekf"}, "replay")
    ekf = raw.get("ekf", {})
    return rcfg, ekf_config_from_raw({"ekf": ekf}, replay_profile(raw, "ekf"), overrides=overrides)


def replay_profile(raw: Mapping[str, Any], table: str) -> str | None:
    """:data:`REPLAY_PROFILE` when ``[table.profiles]`` of the configuration holds it; otherwise None, with a
    warning (a configuration file of one's own without it replays with the table as it is)."""
    t = raw.get(table, {})
    profiles = t.get("profiles", {}) if isinstance(t, Mapping) else {}
    if isinstance(profiles, Mapping) and REPLAY_PROFILE in profiles:
        return REPLAY_PROFILE
    log.warning("the configuration has no [%s.profiles.%s]: replaying with [%s] as it is", table, REPLAY_PROFILE,
                table)
    return None


@dataclass
class ReplayResult:
    """What a replay produced: ``metrics`` (also in ``metrics.json``), time series for figures and tests
    (``series[name][column]``, arrays; times ``t_s`` from the log's start) and the optical steps fed."""

    metrics: dict[str, Any]
    series: dict[str, dict[str, NDArray[np.float64]]]
    steps: list[GsoeStep] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------------------------------------------
# Interpolation helpers


def _bracketed(t_src_us: NDArray[np.int64], t_query_us: NDArray[np.int64], max_gap_us: int) -> NDArray[np.bool_]:
    """Queries inside the span of ``t_src_us`` whose bracketing samples are at most ``max_gap_us`` apart."""
    if t_src_us.size == 0:
        return np.zeros(t_query_us.shape, dtype=bool)
    hi = np.clip(np.searchsorted(t_src_us, t_query_us, side="left"), 0, t_src_us.size - 1)
    lo = np.clip(hi - 1, 0, t_src_us.size - 1)
    exact = t_src_us[hi] == t_query_us
    inside = (t_query_us >= t_src_us[0]) & (t_query_us <= t_src_us[-1])
    return inside & (exact | (t_src_us[hi] - t_src_us[lo] <= max_gap_us))


class AttitudeTrack:
    """Logged AHRS attitudes, interpolated (slerp) to any stamp inside a gap of at most ``max_gap_us``."""

    def __init__(self, atts: Sequence[AttitudeSample], max_gap_us: int) -> None:
        t = np.array([a.t_us for a in atts], dtype=np.int64)
        keep = np.concatenate([[True], np.diff(t) > 0]) if t.size else np.zeros(0, bool)
        t = t[keep]
        if t.size < 2:
            raise ReplayError(f"the log has {t.size} attitude sample(s) with distinct times: at least 2 are needed")
        euler = np.array([(a.yaw_rad, a.pitch_rad, a.roll_rad) for a, k in zip(atts, keep, strict=True) if k])
        self.t_us = t
        self._slerp = Slerp(t.astype(float), Rotation.from_euler("ZYX", euler))
        self._max_gap_us = max_gap_us

    def at(self, t_us: NDArray[np.int64]) -> tuple[Rotation | None, NDArray[np.bool_]]:
        """Interpolated ``R_nb`` at the stamps where ``ok``; ``None`` when no stamp is ok."""
        ok = _bracketed(self.t_us, t_us, self._max_gap_us)
        if not ok.any():
            return None, ok
        return self._slerp(t_us[ok].astype(float)), ok


def _euler(rot: Rotation) -> NDArray[np.float64]:
    """(roll, pitch, yaw) rows of 3-2-1 Euler angles, radians."""
    return np.asarray(rot.as_euler("ZYX"))[:, ::-1]


# --------------------------------------------------------------------------------------------------------------
# The optical stand-in


@dataclass(frozen=True)
class HeightReference:
    """Flat ground for the virtual camera: ``ground_alt_m`` on the scale of the altitude source (baro ISA altitude,
    or GNSS height when the log has no baro), and how it was chosen."""

    ground_alt_m: float
    source: str


def height_reference(alt_t_us: NDArray[np.int64], alt_m: NDArray[np.float64], gnss: Sequence[GnssSample],
                     air: Sequence[AirspeedSample], t_span_us: tuple[int, int], cfg: ReplayConfig,
                     tas_min_m_s: float) -> HeightReference:
    """Choose the ground level of the virtual camera (see the module docstring): the take-off (else landing) point
    from on-ground GNSS samples, or the assumption that the lowest altitude flown is ``lowest_height_agl_m`` high."""
    t0, t1 = t_span_us
    in_span = (alt_t_us >= t0) & (alt_t_us <= t1)
    flown = alt_m[in_span] if in_span.any() else alt_m
    fixes = [g for g in gnss if g.fix_ok and np.all(np.isfinite(g.vel_ned_m_s[:2]))]
    if fixes and alt_m.size:
        tg = np.array([g.t_us for g in fixes], dtype=np.int64)
        speed = np.array([math.hypot(g.vel_ned_m_s[0], g.vel_ned_m_s[1]) for g in fixes])
        slow = speed < cfg.on_ground_speed_m_s
        if air:
            ta = np.array([a.t_us for a in air], dtype=float)
            tas = np.interp(tg.astype(float), ta, np.array([a.tas_m_s for a in air]))
            slow &= tas < tas_min_m_s
        airborne = np.flatnonzero(~slow)
        candidates: list[tuple[NDArray[np.bool_], str]] = []
        if airborne.size:
            idx = np.arange(tg.size)
            candidates = [(slow & (idx < airborne[0]), "take-off point"),
                          (slow & (idx > airborne[-1]), "landing point")]
        for mask, what in candidates:
            if mask.any():
                ground = float(np.median(np.interp(tg[mask].astype(float), alt_t_us.astype(float), alt_m)))
                h_max = float(np.max(flown)) - ground
                if cfg.min_camera_height_m <= h_max <= cfg.max_camera_height_m:
                    return HeightReference(ground, f"{what}: {int(mask.sum())} on-ground GNSS samples")
                return _assumed_ground(flown, cfg, f"{what} gives an implausible height of {h_max:.0f} m")
    return _assumed_ground(flown, cfg, "no take-off or landing in the log")


def _assumed_ground(flown: NDArray[np.float64], cfg: ReplayConfig, why: str) -> HeightReference:
    if flown.size == 0:
        return HeightReference(math.nan, f"{why}; no altitude data")
    return HeightReference(float(np.min(flown)) - cfg.lowest_height_agl_m,
                           f"assumed ({why}): lowest altitude of the log {cfg.lowest_height_agl_m:g} m above flat "
                           f"ground")


def synthesise_optical_steps(frame_t_us: NDArray[np.int64], vel_ne_m_s: NDArray[np.float64],
                             vel_ok: NDArray[np.bool_], R_nb: Rotation | None, att_ok: NDArray[np.bool_],
                             height_m: NDArray[np.float64], gsoe_cfg: GsoeConfig, ekf_cfg: EkfConfig,
                             sigma_px: float, min_height_m: float, rng: np.random.Generator) -> list[GsoeStep]:
    """Optical steps of a virtual camera that sees the ground move with ``vel_ne_m_s``.

    Parameters
    ----------
    frame_t_us
        Frame exposure times (µs), increasing, shape (K,).
    vel_ne_m_s
        Ground velocity north/east at the frames (m/s), shape (K, 2); used where ``vel_ok``.
    R_nb, att_ok
        Body-to-NED attitude at the frames where ``att_ok`` (``R_nb`` holds ``att_ok.sum()`` rotations).
    height_m
        Height of the camera above the ground at the frames (m), shape (K,).
    sigma_px
        One-sigma pixel noise per axis (> 0), or 0 for the EKF's optical noise model of each step.
    rng
        The run's seeded generator (the only source of randomness).

    Returns the steps in time order, with the cycle logic of :class:`gsoe.cycle.GsoeEstimator` (see the module
    docstring); a cycle's last step and the next cycle's base step share a frame.
    """
    k_n = frame_t_us.size
    if k_n == 0 or R_nb is None:
        return []
    stab = gsoe_cfg.stab
    focal = stab.focal_px if stab.focal_px > 0 else gsoe_cfg.camera.fx_px
    u0, v0 = base_reference_px(gsoe_cfg)
    half = (stab.template_px - 1) / 2.0 + gsoe_cfg.cycle.edge_margin_px
    u_lim = (half, stab.base_cross_px - 1 - half)
    v_lim = (half, stab.base_along_px - 1 - half)
    max_cycle_us = int(gsoe_cfg.cycle.max_cycle_s * US_PER_S)
    roll_lim, pitch_lim = math.radians(stab.roll_limit_deg), math.radians(stab.pitch_limit_deg)
    quats = np.full((k_n, 4), np.nan)
    quats[att_ok] = R_nb.as_quat()
    euler = np.full((k_n, 3), np.nan)
    euler[att_ok] = _euler(R_nb)
    usable = (vel_ok & att_ok & np.isfinite(height_m) & (height_m >= min_height_m)
              & (np.abs(euler[:, 0]) <= roll_lim) & (np.abs(euler[:, 1]) <= pitch_lim))
    # position from the integrated velocity (a cycle never spans an unusable frame, so the zeros put where the
    # velocity is unknown never enter a displacement)
    v = np.where(vel_ok[:, None], vel_ne_m_s, 0.0)
    pos = cumulative_trapezoid(v, (frame_t_us - frame_t_us[0]) / US_PER_S, axis=0, initial=0.0)
    nominal = MatchQuality(psr=ekf_cfg.optical_psr_ref, texture_std=math.nan, ssd_per_px=math.nan, valid=True)
    base_q = MatchQuality(psr=math.inf, texture_std=math.nan, ssd_per_px=math.nan, valid=True)
    steps: list[GsoeStep] = []
    cycle_id = -1
    base_k = -1
    n_step = 0
    last_xy = (u0, v0)

    def start(k: int) -> None:
        nonlocal cycle_id, base_k, n_step, last_xy
        cycle_id += 1
        base_k, n_step, last_xy = k, 0, (u0, v0)
        h = float(height_m[k])
        steps.append(GsoeStep(t_us=int(frame_t_us[k]), base_t_us=int(frame_t_us[k]), cycle_id=cycle_id, step=0,
                              dx_px=0.0, dy_px=0.0, base_yaw_rad=float(euler[k, 2]), yaw_rad=float(euler[k, 2]),
                              gsd_m_px=h / focal, height_agl_m=h, focal_px=focal, rel_rot_rad=0.0, quality=base_q,
                              valid=True, new_cycle=True))

    for k in range(k_n):
        if not usable[k]:
            base_k = -1                       # camera lost: the next usable frame starts a new cycle
            continue
        if base_k < 0:
            start(k)
            continue
        n_step += 1
        psi = float(euler[base_k, 2])
        c, s = math.cos(psi), math.sin(psi)
        dn, de = pos[k] - pos[base_k]
        gsd = float(height_m[base_k]) / focal
        rel = _rotation_angle_between(quats[base_k], quats[k])
        clean = GsoeStep(t_us=int(frame_t_us[k]), base_t_us=int(frame_t_us[base_k]), cycle_id=cycle_id, step=n_step,
                         dx_px=(-s * dn + c * de) / gsd, dy_px=(c * dn + s * de) / gsd, base_yaw_rad=psi,
                         yaw_rad=float(euler[k, 2]), gsd_m_px=gsd, height_agl_m=float(height_m[base_k]),
                         focal_px=focal, rel_rot_rad=rel, quality=nominal, valid=True, new_cycle=False)
        sig = sigma_px if sigma_px > 0 else math.hypot(*OpticalDisplacement.noise_sigma_px(clean, ekf_cfg))
        noise = rng.normal(0.0, sig, size=2)
        dx, dy = clean.dx_px + float(noise[0]), clean.dy_px + float(noise[1])
        steps.append(GsoeStep(t_us=clean.t_us, base_t_us=clean.base_t_us, cycle_id=cycle_id, step=n_step, dx_px=dx,
                              dy_px=dy, base_yaw_rad=psi, yaw_rad=clean.yaw_rad, gsd_m_px=gsd,
                              height_agl_m=clean.height_agl_m, focal_px=focal, rel_rot_rad=rel, quality=nominal,
                              valid=True, new_cycle=False))
        xy = (u0 + dx, v0 - dy)
        step_xy = (xy[0] - last_xy[0], xy[1] - last_xy[1])
        last_xy = xy
        nxt = (xy[0] + step_xy[0], xy[1] + step_xy[1])
        at_edge = not (u_lim[0] <= nxt[0] <= u_lim[1] and v_lim[0] <= nxt[1] <= v_lim[1])
        if at_edge or frame_t_us[k] - frame_t_us[base_k] >= max_cycle_us:
            start(k)
    return steps


def _rotation_angle_between(qa: NDArray[np.float64], qb: NDArray[np.float64]) -> float:
    """Angle (rad) of the rotation from attitude ``qa`` to ``qb`` (scipy's scalar-last unit quaternions):
    ``2 atan2(|v|, |w|)`` of ``qa^-1 qb``, accurate for small angles."""
    x1, y1, z1, w1 = -qa[0], -qa[1], -qa[2], qa[3]
    x2, y2, z2, w2 = qb
    w = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    x = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    y = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    z = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
    return 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), abs(w))


# --------------------------------------------------------------------------------------------------------------
# The replay


@dataclass
class _Inputs:
    imu: list[ImuSample]
    att: list[AttitudeSample]
    air: list[AirspeedSample]
    baro: list[BaroSample]
    gnss: list[GnssSample]
    wind: list[AutopilotWind]


def _split(flight: FlightLog, gnss_delay_us: int) -> _Inputs:
    """The log's samples by type; GNSS samples moved to their measurement time (stamp minus the receiver lag)."""
    gnss = [dataclasses.replace(g, t_us=int(g.t_us) - gnss_delay_us) for g in flight.of_type(GnssSample)]
    return _Inputs(imu=flight.of_type(ImuSample), att=flight.of_type(AttitudeSample),
                   air=flight.of_type(AirspeedSample), baro=flight.of_type(BaroSample),
                   gnss=gnss, wind=flight.of_type(AutopilotWind))


def _usable_fix(g: GnssSample) -> bool:
    return bool(g.fix_ok and np.all(np.isfinite(g.pos_ned_m)) and np.all(np.isfinite(g.vel_ned_m_s[:2])))


def run_replay(log_path: str | Path, *, out_dir: str | Path | None = None, config_path: str | Path | None = None,
               gnss_off_at_s: float | None = None, optical: bool = True, optical_sigma_px: float | None = None,
               seed: int = 0, plots: bool = True) -> ReplayResult:
    """Replay ``log_path`` through the EKF (module docstring) and return (and, with ``out_dir``, write) the results.

    ``gnss_off_at_s``: seconds from the log's start after which GNSS is no longer fused (``None``: never).
    ``optical``: feed the synthetic optical stand-in.  ``optical_sigma_px``: its pixel noise (``None``: the
    ``[replay]`` config's).  ``seed``: seeds the generator of that noise.  ``plots``: write the PNG figures and
    ``report.html`` (with ``out_dir``).  Raises :class:`ReplayError` (bad options, log without the needed data),
    :class:`nav.logreader.LogFormatError` (not a log file), ``FileNotFoundError`` and
    :class:`gsoe.config.ConfigError`.
    """
    gsoe_cfg, raw = load_gsoe_config(config_path)
    rcfg, ekf_cfg = replay_configs_from_raw(raw)
    if optical_sigma_px is not None:
        if not (math.isfinite(optical_sigma_px) and optical_sigma_px > 0):
            raise ReplayError(f"--optical-sigma-px must be a positive number of pixels, got {optical_sigma_px!r}")
        sigma_px = float(optical_sigma_px)
    else:
        sigma_px = rcfg.optical_sigma_px
    if gnss_off_at_s is not None and not math.isfinite(gnss_off_at_s):
        raise ReplayError(f"--gnss-off-at must be a finite number of seconds, got {gnss_off_at_s!r}")

    flight = read_log(log_path, rcfg.baro_temp_clamp_c)
    report = flight.report
    warnings = list(report.warnings)
    what = f"{Path(log_path).name}"
    if not flight.samples:
        raise ReplayError(f"{what}: nothing readable in this log ({'; '.join(report.warnings) or 'no samples'})")
    inp = _split(flight, round(rcfg.gnss_delay_s * US_PER_S))
    missing = [name for name, lst in (("IMU", inp.imu), ("attitude", inp.att)) if not lst]
    if missing:
        raise ReplayError(f"{what}: the log has no {' and no '.join(missing)} samples: the EKF cannot be driven")
    fixes = [g for g in inp.gnss if _usable_fix(g)]
    if not fixes:
        raise ReplayError(f"{what}: the log has no valid GNSS fix ({len(inp.gnss)} GNSS samples): the EKF cannot be "
                          f"initialised and there is no track to compare with")
    try:
        atts = AttitudeTrack(inp.att, round(rcfg.att_max_gap_s * US_PER_S))
    except ReplayError as e:
        raise ReplayError(f"{what}: {e}") from None
    t_att_lo, t_att_hi = int(atts.t_us[0]), int(atts.t_us[-1])
    init = next((g for g in fixes if t_att_lo <= g.t_us <= t_att_hi), None)
    if init is None:
        raise ReplayError(f"{what}: no GNSS fix lies within the attitude data "
                          f"({t_att_lo / US_PER_S:.1f}-{t_att_hi / US_PER_S:.1f} s)")
    t_init = int(init.t_us)
    t_imu_end = min(int(inp.imu[-1].t_us), t_att_hi)
    span_s = (t_imu_end - t_init) / US_PER_S
    if span_s < rcfg.min_span_s:
        raise ReplayError(f"{what}: not enough data: {max(span_s, 0.0):.2f} s of IMU and attitude after the first "
                          f"GNSS fix at {t_init / US_PER_S:.2f} s (need at least replay.min_span_s = "
                          f"{rcfg.min_span_s:g} s)")
    t_last_fix = int(fixes[-1].t_us)
    t_off: int | None = None
    if gnss_off_at_s is not None:
        t_off = round(gnss_off_at_s * US_PER_S)
        if not t_init < t_off < min(t_last_fix, t_imu_end):
            raise ReplayError(
                f"--gnss-off-at {gnss_off_at_s:g} s: must lie after the EKF's start at the first GNSS fix "
                f"({t_init / US_PER_S:.1f} s) and before the last GNSS fix within the IMU data "
                f"({min(t_last_fix, t_imu_end) / US_PER_S:.1f} s), so that there is a track to compare with")

    # IMU with the attitude interpolated to its stamps
    t_imu = np.array([s.t_us for s in inp.imu], dtype=np.int64)
    R_imu, ok_imu = atts.at(t_imu)
    eul_imu = np.full((t_imu.size, 3), np.nan)
    if R_imu is not None:
        eul_imu[ok_imu] = _euler(R_imu)
    n_imu_no_att = int((~ok_imu & (t_imu > t_init) & (t_imu <= t_imu_end)).sum())
    if n_imu_no_att:
        warnings.append(f"{n_imu_no_att} IMU samples lie in attitude gaps longer than replay.att_max_gap_s: skipped")

    # altitude source for baro fusion and the camera height
    if len(inp.baro) >= 2:
        alt_t = np.array([b.t_us for b in inp.baro], dtype=np.int64)
        alt_v = np.array([b.alt_m for b in inp.baro])
        alt_source = "baro"
    else:
        alt_t = np.array([g.t_us for g in fixes], dtype=np.int64)
        alt_v = np.array([-g.pos_ned_m[2] for g in fixes])
        alt_source = "gnss"
        warnings.append("fewer than 2 baro samples: no baro fusion; the optical stand-in's height follows GNSS")
    alt_at_init = float(np.interp(t_init, alt_t, alt_v))
    height_ref_at_init = -float(init.pos_ned_m[2])
    baro_offset_m = alt_at_init - height_ref_at_init

    # optical stand-in
    steps: list[GsoeStep] = []
    href: HeightReference | None = None
    if optical:
        href = height_reference(alt_t, alt_v, inp.gnss, inp.air, (t_init, t_imu_end), rcfg, ekf_cfg.tas_min_m_s)
        period_us = round(US_PER_S / gsoe_cfg.cycle.rate_hz)
        t_frames = np.arange(t_init + period_us, min(t_imu_end, t_last_fix) + 1, period_us, dtype=np.int64)
        tg = np.array([g.t_us for g in fixes], dtype=np.int64)
        vg = np.array([g.vel_ned_m_s[:2] for g in fixes])
        vel_ok = _bracketed(tg, t_frames, round(rcfg.gnss_max_gap_s * US_PER_S))
        vel = np.column_stack([np.interp(t_frames, tg, vg[:, i]) for i in range(2)])
        R_f, att_ok = atts.at(t_frames)
        h_f = np.interp(t_frames, alt_t, alt_v) - href.ground_alt_m
        rng = np.random.default_rng(seed)
        steps = synthesise_optical_steps(t_frames, vel, vel_ok, R_f, att_ok, h_f, gsoe_cfg, ekf_cfg, sigma_px,
                                         rcfg.min_camera_height_m, rng)
        if not steps:
            warnings.append("the optical stand-in produced no step (attitude range, height or GNSS gaps)")
        h_init = float(np.interp(t_init, alt_t, alt_v)) - href.ground_alt_m
    else:
        h_init = rcfg.lowest_height_agl_m
    # The pipeline's NED origin lies at ground level: the log's heights (origin at its first 3-D fix) move down by
    # the ground's height there, and the baro's ground level is its altitude at the start less the camera height.
    shift_d_m = height_ref_at_init - h_init if math.isfinite(h_init) else 0.0
    ground_alt_m = alt_at_init - (h_init if math.isfinite(h_init) else height_ref_at_init)

    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        for name in CSV_STREAMS:                 # RunLog appends: a rerun into the same folder starts afresh
            (Path(out_dir) / f"{name}.csv").unlink(missing_ok=True)
    runlog = RunLog(out_dir) if out_dir is not None else None
    pipe = NavPipeline(gsoe_cfg, ekf_cfg, pipeline_config_from_raw(raw, replay_profile(raw, "pipeline")),
                       CameraModel.from_config(gsoe_cfg.camera), sink=_replay_sink(runlog))
    if alt_source == "baro":
        pipe.on_ground_level(ground_alt_m)
    rec: dict[str, list[float]] = {k: [] for k in (
        "t_s", "n", "e", "h", "n_sigma", "e_sigma", "wn", "we", "wn_sigma", "we_sigma", "valid")}

    def record(e: NavEstimate | None) -> None:
        if e is None or (rec["t_s"] and e.t_us / US_PER_S <= rec["t_s"][-1]):
            return
        for k, v in (("t_s", e.t_us / US_PER_S), ("n", e.pos_ne_m[0]), ("e", e.pos_ne_m[1]),
                     ("h", e.height_m + shift_d_m), ("n_sigma", e.pos_ne_sigma_m[0]), ("e_sigma", e.pos_ne_sigma_m[1]),
                     ("wn", e.wind_ne_m_s[0]), ("we", e.wind_ne_m_s[1]), ("wn_sigma", e.wind_ne_sigma_m_s[0]),
                     ("we_sigma", e.wind_ne_sigma_m_s[1]), ("valid", float(e.valid))):
            rec[k].append(float(v))

    att0 = atts.at(np.array([t_init], dtype=np.int64))[0]
    assert att0 is not None
    r0, p0, y0 = _euler(att0)[0]
    try:
        # the log from the fix the EKF starts at, in time order (ties: the EKF orders same-stamp samples itself)
        pipe.on_attitude(AttitudeSample(t_us=t_init, roll_rad=float(r0), pitch_rad=float(p0), yaw_rad=float(y0)))
        for t, kind, payload in _events(inp, steps, ok_imu, eul_imu, t_init, t_imu_end, alt_source == "baro"):
            if kind == "imu":
                pipe.on_attitude(payload[1])
                pipe.on_imu(payload[0])
                record(pipe.estimate())
            elif kind == "gnss":
                pipe.gnss_enabled = t_off is None or t < t_off
                g = payload
                pipe.on_gnss(dataclasses.replace(g, pos_ned_m=g.pos_ned_m + np.array([0.0, 0.0, shift_d_m])))
            elif kind == "baro":
                pipe.on_baro(payload)
            elif kind == "air":
                pipe.on_airspeed(payload)
            elif kind == "optical":
                pipe.on_steps([payload])
        if runlog is not None:
            for w in inp.wind:
                wn, we = w.wind_ned_m_s
                runlog.write("autopilot_wind", {"t_us": w.t_us, "wind_n_m_s": wn, "wind_e_m_s": we,
                                                "wind_from_rad": w.wind_from_rad, "speed_m_s": w.speed_m_s})
    finally:
        if runlog is not None:
            runlog.close()
    if pipe.ekf is None:
        raise ReplayError(f"{what}: the EKF did not start ({pipe.why_no_estimate()})")
    ekf = pipe.ekf

    series: dict[str, dict[str, NDArray[np.float64]]] = {"ekf": {k: np.array(v) for k, v in rec.items()}}
    series["gnss"] = {"t_s": np.array([g.t_us for g in fixes]) / US_PER_S,
                      "n": np.array([g.pos_ned_m[0] for g in fixes]),
                      "e": np.array([g.pos_ned_m[1] for g in fixes])}
    series["autopilot_wind"] = {"t_s": np.array([w.t_us for w in inp.wind], dtype=float) / US_PER_S,
                                "wn": np.array([w.wind_ned_m_s[0] for w in inp.wind]),
                                "we": np.array([w.wind_ned_m_s[1] for w in inp.wind])}
    metrics: dict[str, Any] = {
        "log": str(log_path), "log_format": report.log_format, "log_duration_s": flight.duration_s,
        "optical_source": OPTICAL_SOURCE_SYNTHETIC if optical else OPTICAL_SOURCE_NONE,
        "optical_sigma_px": sigma_px if optical and sigma_px > 0 else ("ekf_noise_model" if optical else None),
        "optical_height_reference": href.source if href is not None else None,
        "optical_steps": len(steps), "optical_cycles": len({s.cycle_id for s in steps}),
        "seed": seed, "gnss_off_at_s": gnss_off_at_s, "ekf_start_s": t_init / US_PER_S,
        "n_samples": {**report.counts, "GsoeStep": len(steps)}, "sources": dict(report.sources),
        "aid_fused": {k: {"fused": s.n_fused, "rejected": s.n_rejected} for k, s in ekf.status().items()},
        "samples_rejected": dict(pipe.plausibility.status.rejected),   # pipeline.plausibility, by kind: reason
        "baro_offset_m": baro_offset_m,
        "gnss_delay_s": rcfg.gnss_delay_s,
        "eas_to_tas_air_temp_c": report.air_temp_c,        # None: the ISA atmosphere's (nav.logreader)
        "log_firmware": report.firmware or None,            # None: the log names no firmware
        "baro_temp_clamp_c": report.baro_temp_clamp_c,      # the log's firmware's, else [replay] baro_temp_clamp_c
        "ekf_replay_profile": REPLAY_PROFILE,
        "log_warnings": list(report.warnings),
    }
    moving = [s for s in steps if not s.new_cycle]
    if moving:
        sig = [math.hypot(*OpticalDisplacement.noise_sigma_px(s, ekf_cfg)) if sigma_px == 0 else sigma_px
               for s in moving]
        metrics["optical_noise_sigma_px_mean"] = float(np.mean(sig))
        metrics["optical_gsd_m_px_mean"] = float(np.mean([s.gsd_m_px for s in moving]))
    if not inp.air:
        warnings.append("no airspeed in the log: the wind is not observable from air data")
    metrics.update(_wind_metrics(series, t_init / US_PER_S + rcfg.wind_settle_s, t_off, warnings))
    metrics.update(_dr_metrics(series, t_off))
    metrics["pos_error_rms_with_gnss_m"] = _pos_error_rms(series, t_init / US_PER_S,
                                                          t_off / US_PER_S if t_off is not None else math.inf)
    metrics["warnings"] = warnings
    result = ReplayResult(metrics=metrics, series=series, steps=steps, warnings=warnings)
    if out_dir is not None:
        write_outputs(Path(out_dir), result, plots=plots)
    return result


def _replay_sink(runlog: RunLog | None) -> Any:
    """The pipeline's log streams a replay keeps (the log's own IMU, attitude and air data are not copied)."""
    if runlog is None:
        return None
    keep = set(CSV_STREAMS)

    def sink(stream: str, record: dict[str, Any]) -> None:
        if stream in keep:
            runlog.write(stream, record)
    return sink


def _events(inp: _Inputs, steps: list[GsoeStep], ok_imu: NDArray[np.bool_], eul_imu: NDArray[np.float64],
            t_init: int, t_imu_end: int, with_baro: bool) -> list[tuple[int, str, Any]]:
    """The log's samples from the EKF's first fix on, in time order; each IMU sample with the attitude
    interpolated to its stamp (offline, so the next logged attitude may be used)."""
    events: list[tuple[int, int, str, Any]] = []
    for i, s in enumerate(inp.imu):
        if ok_imu[i] and t_init < s.t_us <= t_imu_end:
            att = AttitudeSample(t_us=int(s.t_us), roll_rad=float(eul_imu[i, 0]), pitch_rad=float(eul_imu[i, 1]),
                                 yaw_rad=float(eul_imu[i, 2]))
            events.append((int(s.t_us), 0, "imu", (s, att)))
    events += [(int(g.t_us), 1, "gnss", g) for g in inp.gnss if g.t_us >= t_init]
    if with_baro:
        events += [(int(b.t_us), 2, "baro", b) for b in inp.baro if b.t_us >= t_init]
    events += [(int(a.t_us), 3, "air", a) for a in inp.air if a.t_us >= t_init]
    events += [(st.t_us, 4, "optical", st) for st in steps]
    events.sort(key=lambda e: (e[0], e[1]))
    return [(t, kind, payload) for t, _, kind, payload in events]


# --------------------------------------------------------------------------------------------------------------
# Figures of merit


def _wind_metrics(series: dict[str, dict[str, NDArray[np.float64]]], t_from_s: float, t_off: int | None,
                  warnings: list[str]) -> dict[str, Any]:
    E, W = series["ekf"], series["autopilot_wind"]
    out: dict[str, Any] = {"wind_rmse_vs_autopilot_m_s": math.nan, "wind_compare_from_s": t_from_s,
                           "wind_compared_samples": 0}
    if W["t_s"].size == 0:
        warnings.append("no autopilot wind estimate in the log: wind_rmse_vs_autopilot_m_s is not computed")
        return out
    sel = (W["t_s"] >= t_from_s) & (W["t_s"] <= E["t_s"][-1])
    if not sel.any():
        warnings.append(f"no autopilot wind sample after the settle time ({t_from_s:.1f} s)")
        return out
    t = W["t_s"][sel]
    dn = np.interp(t, E["t_s"], E["wn"]) - W["wn"][sel]
    de = np.interp(t, E["t_s"], E["we"]) - W["we"][sel]
    err = np.hypot(dn, de)
    ws_ekf = np.hypot(np.interp(t, E["t_s"], E["wn"]), np.interp(t, E["t_s"], E["we"]))
    ws_ap = np.hypot(W["wn"][sel], W["we"][sel])
    dir_err = np.degrees(np.abs(angle_diff(M.wind_from_rad(np.interp(t, E["t_s"], E["wn"]),
                                                           np.interp(t, E["t_s"], E["we"])),
                                           M.wind_from_rad(W["wn"][sel], W["we"][sel]))))
    out.update(wind_rmse_vs_autopilot_m_s=M.rmse(err), wind_compared_samples=int(sel.sum()),
               wind_speed_rmse_vs_autopilot_m_s=M.rmse(ws_ekf - ws_ap),
               wind_dir_rmse_vs_autopilot_deg=M.rmse(dir_err),
               autopilot_wind_speed_mean_m_s=float(np.mean(ws_ap)), ekf_wind_speed_mean_m_s=float(np.mean(ws_ekf)))
    if t_off is not None:
        dr = t >= t_off / US_PER_S
        out["wind_rmse_vs_autopilot_before_gnss_off_m_s"] = M.rmse(err[~dr])
        out["wind_rmse_vs_autopilot_after_gnss_off_m_s"] = M.rmse(err[dr])
    return out


def _horizontal_error(series: dict[str, dict[str, NDArray[np.float64]]], sel: NDArray[np.bool_]
                      ) -> NDArray[np.float64]:
    E, G = series["ekf"], series["gnss"]
    t = G["t_s"][sel]
    return np.hypot(np.interp(t, E["t_s"], E["n"]) - G["n"][sel], np.interp(t, E["t_s"], E["e"]) - G["e"][sel])


def _pos_error_rms(series: dict[str, dict[str, NDArray[np.float64]]], t0_s: float, t1_s: float) -> float:
    G, E = series["gnss"], series["ekf"]
    sel = (G["t_s"] >= t0_s) & (G["t_s"] < t1_s) & (G["t_s"] <= E["t_s"][-1])
    return M.rmse(_horizontal_error(series, sel)) if sel.any() else math.nan


def _dr_metrics(series: dict[str, dict[str, NDArray[np.float64]]], t_off: int | None) -> dict[str, Any]:
    out: dict[str, Any] = {"dr_error_m": math.nan, "dr_distance_m": math.nan, "dr_error_pct_of_distance": math.nan,
                           "dr_max_error_m": math.nan, "dr_duration_s": math.nan}
    if t_off is None:
        return out
    G, E = series["gnss"], series["ekf"]
    t_off_s = t_off / US_PER_S
    sel = (G["t_s"] >= t_off_s) & (G["t_s"] <= E["t_s"][-1])
    if not sel.any():
        return out
    err = _horizontal_error(series, sel)
    dist = M.path_length_m(np.concatenate([[np.interp(t_off_s, G["t_s"], G["n"])], G["n"][sel]]),
                           np.concatenate([[np.interp(t_off_s, G["t_s"], G["e"])], G["e"][sel]]))
    out.update(dr_error_m=float(err[-1]), dr_distance_m=dist, dr_max_error_m=float(np.max(err)),
               dr_duration_s=float(G["t_s"][sel][-1] - t_off_s),
               dr_error_pct_of_distance=100.0 * float(err[-1]) / dist if dist > 0 else math.nan)
    return out


# --------------------------------------------------------------------------------------------------------------
# Output files


def write_outputs(out_dir: Path, result: ReplayResult, *, plots: bool = True) -> None:
    """``metrics.json`` and, with ``plots``, the figures and ``report.html`` (the CSV streams are written during the
    run)."""
    from common.report import write_metrics

    out_dir.mkdir(parents=True, exist_ok=True)
    write_metrics(out_dir, result.metrics)
    if plots:
        figs = _plots(out_dir, result)
        _write_html(out_dir, result.metrics, figs)


def _plots(out_dir: Path, result: ReplayResult) -> list[tuple[str, str]]:
    from common.report import SavedFigures

    figures = SavedFigures(out_dir)
    plt, save, figs = figures.plt, figures.save, figures.figs
    E, G, W = result.series["ekf"], result.series["gnss"], result.series["autopilot_wind"]
    t_off = result.metrics.get("gnss_off_at_s")

    def shade(ax: Any) -> None:
        if t_off is not None:
            ax.axvspan(t_off, E["t_s"][-1], color="r", alpha=0.08, lw=0)

    fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for i, (key, sk, label) in enumerate((("wn", "wn_sigma", "north"), ("we", "we_sigma", "east"))):
        ax[i].fill_between(E["t_s"], E[key] - E[sk], E[key] + E[sk], color="b", alpha=0.2, lw=0)
        ax[i].plot(E["t_s"], E[key], "b-", lw=0.8, label="EKF +- 1 sigma")
        if W["t_s"].size:
            ax[i].plot(W["t_s"], W[key], "k.", ms=2, label="autopilot (log)")
        ax[i].axvline(result.metrics["wind_compare_from_s"], color="0.5", ls=":", lw=0.8)
        shade(ax[i])
        ax[i].set_ylabel(f"wind {label} [m/s]")
    ax[0].legend(fontsize=7)
    ax[1].set_xlabel("time from log start [s]")
    save(fig, "wind.png", "Wind (velocity of the air): EKF with its 1-sigma band vs the autopilot's estimate; "
                          "compared after the dotted line; GNSS not fused in the shaded part")

    fig, ax = plt.subplots(figsize=(7, 6))
    ax.plot(G["e"], G["n"], ".", ms=1.5, color="0.5", label="GNSS")
    ax.plot(E["e"], E["n"], "b-", lw=0.8, label="EKF")
    if t_off is not None and E["t_s"].size:
        k = int(np.searchsorted(E["t_s"], t_off))
        ax.plot(E["e"][k:], E["n"][k:], "r-", lw=0.9, label="EKF, GNSS not fused")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", "datalim")
    ax.legend()
    save(fig, "track.png", "Track, top view: EKF vs GNSS (local NED from the first fix)")

    sel = (G["t_s"] >= E["t_s"][0]) & (G["t_s"] <= E["t_s"][-1])
    fig, ax = plt.subplots(figsize=(8, 3))
    if sel.any():
        ax.plot(G["t_s"][sel], _horizontal_error(result.series, sel), "b-", lw=0.8,
                label="horizontal error vs GNSS")
    ax.plot(E["t_s"], np.hypot(E["n_sigma"], E["e_sigma"]), "b:", lw=0.8, label="1-sigma (EKF)")
    shade(ax)
    ax.set_yscale("log")
    ax.set_xlabel("time from log start [s]")
    ax.set_ylabel("[m]")
    ax.legend(fontsize=7)
    save(fig, "position_error.png", "EKF position vs GNSS (GNSS not fused in the shaded part)")
    return figs


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.4g}"
    return str(v)


def _write_html(out_dir: Path, metrics: dict[str, Any], figs: list[tuple[str, str]]) -> None:
    optical = metrics["optical_source"]
    if optical == OPTICAL_SOURCE_SYNTHETIC:
        sig = metrics["optical_sigma_px"]
        noise = (f"{sig:g} px" if isinstance(sig, float) else
                 f"the EKF's optical noise model, mean {_fmt(metrics.get('optical_noise_sigma_px_mean', math.nan))} px")
        note = ("The log has no camera. The optical measurements are SYNTHETIC: a virtual camera's template "
                f"displacements computed from GNSS ground velocity with added pixel noise ({noise} per axis), camera "
                f"height from the baro altitude; ground reference: {metrics['optical_height_reference']}. They keep "
                "running after GNSS fusion stops (the camera would still see the ground), so the dead-reckoning "
                "figures measure the filter's integration of noisy displacements, not a real camera. The EKF runs "
                f"with the replay profile {metrics['ekf_replay_profile']} on top of [ekf].")
    else:
        note = "No optical measurements: the run dead-reckons on IMU and air data only after GNSS fusion stops."
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(_fmt(v))}</td></tr>"
                   for k, v in sorted(metrics.items()) if k != "warnings")
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in metrics.get("warnings", [])) or "<li>none</li>"
    imgs = "".join(f'<figure><img src="{n}" alt="{html.escape(c)}"><figcaption>{html.escape(c)}</figcaption>'
                   f"</figure>" for n, c in figs)
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>gsoe replay</title>"
            "<style>body{font-family:sans-serif;max-width:1000px;margin:auto}td{padding:2px 8px}"
            "img{max-width:100%}.note{background:#fff4d6;padding:8px}</style></head><body>"
            f"<h1>Replay of {html.escape(Path(str(metrics['log'])).name)}</h1>"
            f"<p class='note'><b>Optical source: {html.escape(optical)}.</b> {html.escape(note)}</p>"
            f"<h2>Warnings</h2><ul>{warn}</ul><h2>Metrics</h2><table>{rows}</table><h2>Figures</h2>{imgs}"
            "</body></html>")
    (out_dir / "report.html").write_text(page)
