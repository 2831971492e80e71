"""Video-tracking guidance with drift correction: put the aircraft's ground track, not its nose, on the target.

Pure geometry (no I/O).  Frames and names as in :mod:`gsoe`.

Pipeline
--------
1. :func:`locate_target`: the tracker's pixel in the raw image of a calibrated camera (:class:`gsoe.camera.CameraModel`,
   whose ``R_bc`` may be the belly fisheye or a forward-looking tracking camera, see
   :func:`gsoe.camera.forward_camera`) is unprojected to a unit ray, rotated to NED with the AHRS attitude and
   intersected with flat ground ``height_agl_m`` below the aircraft.  The result is the target's horizontal offset
   from the aircraft (``rel_ne_m``), its bearing (clockwise from north) and ground range.  Rays that do not point
   below the horizon by at least ``min_depression_deg`` are invalid: their ground intersection is far away and
   ill-conditioned.
2. :func:`heading_command`: the desired course over ground is the bearing to the target (pure pursuit of the ground
   track).  With the drift angle ``drift_rad`` (positive when the ground track lies clockwise of the heading, so
   ``course = heading + drift``) the heading that flies that course is ``heading = course - drift``.  Without a
   valid drift the command falls back to ``heading = course`` (nose on target, the situation the paper improves
   on) and says so.  The drift is saturated to ``max_drift_deg``; near overflight (``freeze_range_m``) the
   bearing is ill-conditioned, and once the target leaves the camera's field close in (``hold_range_m``) it is
   unobservable: then the last desired course is held.

What is sent to the autopilot (see :func:`change_heading_command_fields`)
-------------------------------------------------------------------------
ArduPlane in GUIDED mode accepts ``MAV_CMD_GUIDED_CHANGE_HEADING`` (43002, ardupilotmega.xml) as a COMMAND_LONG:
``param1`` the heading type (0 course over ground, 1 vehicle heading), ``param2`` the target in degrees [0, 360),
``param3`` the lateral acceleration limit (m/s^2). We send **heading type 1 (vehicle heading)** with ``heading =
course - drift``: during a GNSS outage the autopilot's own course over ground is not observable (its EKF has no GNSS
velocity), so asking it to hold a course would hand it a quantity it cannot measure, whereas the heading comes from
its compass/ AHRS and the drift that turns a course into a heading is exactly what the companion estimates. A
reposition target (``MAV_CMD_DO_REPOSITION``) is not used for the same reason: it needs the autopilot to know its own
position.
The command is idempotent, so it is re-sent at the guidance rate; a lost packet costs one period.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from numpy.typing import NDArray

from common.angles import angle_diff, wrap_2pi
from common.config import In, Validated
from gsoe.camera import CameraModel
from gsoe.camera import forward_camera as forward_camera  # re-exported: the tracking camera
from gsoe.rotation import R_nb_from_euler

# MAVLink constants (common.xml / ardupilotmega.xml); named here so nav/ code reads without magic numbers.
MAV_CMD_GUIDED_CHANGE_HEADING = 43002
HEADING_TYPE_COURSE_OVER_GROUND = 0
HEADING_TYPE_HEADING = 1


@dataclass(frozen=True)
class GuidanceConfig(Validated):
    """``[companion.guidance]``: geometry gates and saturations of the heading command.

    ``min_depression_deg``: the target ray must point at least this far below the horizon (else invalid);
    ``max_range_m``: farther ground intersections are invalid; ``freeze_range_m``: below this ground range the
    desired course is frozen (bearing ill-conditioned at overflight); ``hold_range_m``: when the target is lost
    (e.g. it passed below the camera's field) within this range of its last fix, the last course is held;
    ``max_drift_deg``: drift magnitude
    saturation; ``max_drift_sigma_deg``: a drift whose one-sigma exceeds this is not applied;
    ``max_heading_change_deg``: the command stays within this of the current heading (one bad track cannot
    command a reversal); ``accel_limit_m_s2``: lateral acceleration limit sent as ``param3``;
    ``rate_hz``: command rate; ``correct_drift``: apply the drift (off only to measure the uncorrected baseline).
    """

    min_depression_deg: Annotated[float, In(0.0, 89.0)] = 1.0
    max_range_m: Annotated[float, In(1.0, 1e5)] = 5000.0
    freeze_range_m: Annotated[float, In(0.0, 1e4)] = 10.0
    hold_range_m: Annotated[float, In(0.0, 1e5)] = 150.0
    max_drift_deg: Annotated[float, In(0.0, 89.0)] = 35.0
    max_drift_sigma_deg: Annotated[float, In(0.0, 90.0)] = 5.0
    max_heading_change_deg: Annotated[float, In(1.0, 180.0)] = 120.0
    accel_limit_m_s2: Annotated[float, In(0.05, 100.0)] = 5.0
    rate_hz: Annotated[float, In(0.1, 100.0)] = 5.0
    correct_drift: bool = True


@dataclass(frozen=True, slots=True)
class TargetFix:
    """The target's position relative to the aircraft on flat ground.

    ``rel_ne_m``: (north, east) offset from the aircraft to the target (m); ``bearing_rad``: clockwise from north,
    [0, 2 pi); ``range_m``: horizontal distance; ``depression_rad``: angle of the ray below the horizon.
    ``valid`` false with ``reason`` when the geometry is unusable (then the numbers are NaN).
    """

    t_us: int
    rel_ne_m: NDArray[np.float64]
    bearing_rad: float
    range_m: float
    depression_rad: float
    valid: bool
    reason: str = ""


@dataclass(frozen=True, slots=True)
class HeadingCommand:
    """A heading command for the autopilot.

    ``heading_rad`` (clockwise from north, [0, 2 pi)) is what is sent; ``course_rad`` the desired course over
    ground; ``drift_used_rad`` the (saturated) drift subtracted (0 when not applied); ``drift_applied`` whether the
    drift was valid and applied; ``terminal`` whether the course was frozen near overflight.
    """

    t_us: int
    heading_rad: float
    course_rad: float
    drift_used_rad: float
    drift_applied: bool
    terminal: bool
    valid: bool
    reason: str = ""


def _invalid_fix(t_us: int, reason: str) -> TargetFix:
    nan = float("nan")
    return TargetFix(t_us, np.full(2, nan), nan, nan, nan, False, reason)


def locate_target(
    t_us: int,
    pixel_xy: tuple[float, float] | NDArray[np.float64],
    camera: CameraModel,
    roll_rad: float,
    pitch_rad: float,
    yaw_rad: float,
    height_agl_m: float,
    config: GuidanceConfig,
) -> TargetFix:
    """Ground offset, bearing and range of the target seen at ``pixel_xy`` (column, row) in the raw image."""
    px = np.asarray(pixel_xy, dtype=np.float64).reshape(-1)
    values = [*px.tolist(), roll_rad, pitch_rad, yaw_rad, height_agl_m]
    if px.size != 2 or not all(math.isfinite(v) for v in values):
        return _invalid_fix(t_us, "non-finite pixel, attitude or height")
    w, h = camera.size_px
    if not (-0.5 <= px[0] <= w - 0.5 and -0.5 <= px[1] <= h - 0.5):
        return _invalid_fix(t_us, f"pixel ({px[0]:.1f}, {px[1]:.1f}) outside the {w}x{h} image")
    if height_agl_m <= 0.0:
        return _invalid_fix(t_us, f"height above ground {height_agl_m:.1f} m is not positive")
    ray_c = camera.unproject(px.reshape(1, 2))[0]
    ray_n = R_nb_from_euler(roll_rad, pitch_rad, yaw_rad) @ (camera.R_bc @ ray_c)
    depression = math.asin(max(-1.0, min(1.0, float(ray_n[2]))))
    if depression < math.radians(config.min_depression_deg):
        return _invalid_fix(t_us, f"target ray {math.degrees(depression):.1f} deg below horizon "
                                  f"(< {config.min_depression_deg} deg)")
    scale = height_agl_m / float(ray_n[2])
    rel = ray_n[:2] * scale
    rng = float(math.hypot(rel[0], rel[1]))
    if rng > config.max_range_m:
        return _invalid_fix(t_us, f"ground range {rng:.0f} m > {config.max_range_m:.0f} m")
    bearing = float(wrap_2pi(math.atan2(rel[1], rel[0])))
    return TargetFix(t_us, rel, bearing, rng, depression, True)


def heading_command(
    fix: TargetFix,
    current_yaw_rad: float,
    drift_rad: float,
    drift_sigma_rad: float,
    drift_valid: bool,
    config: GuidanceConfig,
    held_course_rad: float | None = None,
) -> HeadingCommand:
    """Heading that flies the ground track onto the target: ``heading = course - drift``.

    ``held_course_rad``: the previous desired course, held when the fix is closer than ``freeze_range_m`` or
    invalid (the caller passes it only while a hold is allowed, see :class:`TargetGuidance`).  Invalid (nothing to
    send) when there is neither a usable fix nor a course to hold, or the yaw is not finite.
    """
    nan = float("nan")
    if not math.isfinite(current_yaw_rad):
        return HeadingCommand(fix.t_us, nan, nan, 0.0, False, False, False, "current heading not finite")
    terminal = False
    if fix.valid and fix.range_m >= config.freeze_range_m:
        course = fix.bearing_rad
    elif held_course_rad is not None and math.isfinite(held_course_rad):
        course = float(held_course_rad)
        terminal = True
    else:
        return HeadingCommand(fix.t_us, nan, nan, 0.0, False, False, False, fix.reason or "no course to hold")

    reasons: list[str] = []
    applied = False
    drift_used = 0.0
    if not config.correct_drift:
        reasons.append("drift correction off")
    elif not (drift_valid and math.isfinite(drift_rad) and math.isfinite(drift_sigma_rad)):
        reasons.append("drift invalid: nose on target")
    elif drift_sigma_rad > math.radians(config.max_drift_sigma_deg):
        reasons.append(f"drift sigma {math.degrees(drift_sigma_rad):.1f} deg > {config.max_drift_sigma_deg} deg")
    else:
        limit = math.radians(config.max_drift_deg)
        drift_used = max(-limit, min(limit, drift_rad))
        if drift_used != drift_rad:
            reasons.append("drift saturated")
        applied = True
    heading = course - drift_used
    change = float(angle_diff(heading, current_yaw_rad))
    max_change = math.radians(config.max_heading_change_deg)
    if abs(change) > max_change:
        heading = current_yaw_rad + math.copysign(max_change, change)
        reasons.append("heading change saturated")
    if terminal:
        reasons.append("terminal: course held")
    return HeadingCommand(fix.t_us, float(wrap_2pi(heading)), float(wrap_2pi(course)), drift_used, applied,
                          terminal, True, "; ".join(reasons))


def change_heading_command_fields(cmd: HeadingCommand, config: GuidanceConfig, target_system: int,
                                  target_component: int) -> dict[str, float | int]:
    """COMMAND_LONG fields of ``MAV_CMD_GUIDED_CHANGE_HEADING`` (heading type: vehicle heading) for ``cmd``."""
    if not cmd.valid or not math.isfinite(cmd.heading_rad):
        raise ValueError(f"refusing to encode an invalid heading command ({cmd.reason})")
    heading_deg = math.degrees(cmd.heading_rad) % 360.0
    if heading_deg >= 360.0:  # float rounding of values just below 360
        heading_deg = 0.0
    return {
        "target_system": target_system, "target_component": target_component,
        "command": MAV_CMD_GUIDED_CHANGE_HEADING, "confirmation": 0,
        "param1": float(HEADING_TYPE_HEADING), "param2": heading_deg, "param3": config.accel_limit_m_s2,
        "param4": 0.0, "param5": 0.0, "param6": 0.0, "param7": 0.0,
    }


class TargetGuidance:
    """Stateful wrapper: holds the last desired course for the terminal phase and rate-limits commands."""

    def __init__(self, camera: CameraModel, config: GuidanceConfig) -> None:
        self.camera = camera
        self.config = config
        self._held_course: float | None = None
        self._last_range_m = math.inf
        self._last_cmd_t_us: int | None = None

    def reset(self) -> None:
        self._held_course = None
        self._last_range_m = math.inf
        self._last_cmd_t_us = None

    def due(self, t_us: int) -> bool:
        """True when a command is due at ``t_us`` (``rate_hz``)."""
        period_us = 1e6 / self.config.rate_hz
        return self._last_cmd_t_us is None or t_us - self._last_cmd_t_us >= period_us or t_us < self._last_cmd_t_us

    def step(self, t_us: int, pixel_xy: tuple[float, float] | NDArray[np.float64] | None, roll_rad: float,
             pitch_rad: float, yaw_rad: float, height_agl_m: float, drift_rad: float, drift_sigma_rad: float,
             drift_valid: bool) -> tuple[TargetFix, HeadingCommand]:
        """Locate the target (``None``: not tracked this frame) and compute the command."""
        if pixel_xy is None:
            fix = _invalid_fix(t_us, "target not tracked")
        else:
            fix = locate_target(t_us, pixel_xy, self.camera, roll_rad, pitch_rad, yaw_rad, height_agl_m, self.config)
        if fix.valid:
            self._last_range_m = fix.range_m
        hold = self._held_course if self._last_range_m < self.config.hold_range_m else None
        cmd = heading_command(fix, yaw_rad, drift_rad, drift_sigma_rad, drift_valid, self.config, hold)
        if cmd.valid:
            self._held_course = cmd.course_rad
            self._last_cmd_t_us = t_us
        return fix, cmd
