"""Link hygiene: who may send the companion what (issue 23; the threat model is docs/security.md).

- **Telemetry only from the autopilot.**  The autopilot link (:mod:`nav.link`) takes a sample only from the
  autopilot's own system and component: configured (``[companion.link] autopilot_system_id``,
  ``autopilot_component_id``) or, where 0, learnt from its HEARTBEAT (the first one whose ``autopilot`` field is not
  MAV_AUTOPILOT_INVALID and whose ``type`` is not a ground station or an onboard controller; MAVSDK itself connects
  to the first such system, and what it has seen of it, one component or MAV_COMP_ID_AUTOPILOT1 among them, is
  taken at once).  Until the autopilot is known nothing is taken.  An external video tracker's
  CAMERA_TRACKING_IMAGE_STATUS may come from any component of the autopilot's system (a MAVLink camera is a
  component of the vehicle), never from another system.
- **Commands only when addressed to us.**  A ground-station command (COMMAND_LONG, COMMAND_INT, or any message with
  target fields) is taken only when its ``target_system`` and ``target_component`` are the companion's own ids
  exactly: a command for another system or component, or a broadcast (0), is not ours to act on or acknowledge.
- **Designated pixels in the image.**  A target designated by pixel must lie inside the camera's image,
  ``0 <= x < width`` and ``0 <= y < height`` (raw image pixels).

These are consistency checks, not authentication: a sender that claims the autopilot's ids passes them.  Only
MAVLink 2 signing tells a genuine sender from an impostor (docs/security.md).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

log = logging.getLogger(__name__)

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
MAV_COMP_ID_AUTOPILOT1 = 1
#: HEARTBEAT ``type`` values of components that are not an autopilot even when they name one
NOT_AUTOPILOT_TYPES = frozenset({6, 18, 26, 27, 30})  # GCS, ONBOARD_CONTROLLER, GIMBAL, ADSB, CAMERA
TRACKER_MESSAGES = frozenset({"CAMERA_TRACKING_IMAGE_STATUS"})


def flight_sw_version(value: Any) -> tuple[int, int, int] | None:
    """AUTOPILOT_VERSION's ``flight_sw_version`` (major << 24 | minor << 16 | patch << 8 | release type) as (major,
    minor, patch); None for a damaged field (not a uint32, or major 0: no release is numbered so)."""
    try:
        v = int(value)
    except (TypeError, ValueError, OverflowError):
        return None
    if not 0 <= v < 2**32 or v >> 24 == 0:
        return None
    return (v >> 24) & 0xFF, (v >> 16) & 0xFF, (v >> 8) & 0xFF


class AutopilotSenders:
    """The autopilot's (system, component), configured or learnt from its HEARTBEAT (module docstring).

    ``system_id``/``component_id``: the configured ids, 0 to learn them.  :meth:`heartbeat` learns;
    :meth:`check` says why a message may not be taken ("" when it may).
    """

    def __init__(self, system_id: int = 0, component_id: int = 0) -> None:
        self.configured = (int(system_id), int(component_id))
        self.system_id: int | None = int(system_id) or None
        self.component_id: int | None = int(component_id) or None

    @property
    def known(self) -> bool:
        return self.system_id is not None and self.component_id is not None

    def heartbeat(self, system_id: int, component_id: int, autopilot: int, mav_type: int) -> None:
        """A HEARTBEAT from ``system_id``/``component_id``: the autopilot's ids are learnt from the first one of an
        autopilot that matches what is configured."""
        if self.known or int(autopilot) == MAV_AUTOPILOT_INVALID or int(mav_type) in NOT_AUTOPILOT_TYPES:
            return
        want_sys, want_comp = self.configured
        if (want_sys and int(system_id) != want_sys) or (want_comp and int(component_id) != want_comp):
            return
        self.system_id, self.component_id = int(system_id), int(component_id)
        log.info("autopilot is system %d, component %d (learnt from its heartbeat); telemetry from any other sender "
                 "is refused", self.system_id, self.component_id)

    def discovered(self, system_id: int, component_ids: Sequence[int]) -> None:
        """MAVSDK found the autopilot's system (by its heartbeat) with these components: when that tells the
        autopilot's component (MAV_COMP_ID_AUTOPILOT1 among them, or the only one), it is known at once."""
        comps = [int(c) for c in component_ids]
        comp = MAV_COMP_ID_AUTOPILOT1 if MAV_COMP_ID_AUTOPILOT1 in comps else comps[0] if len(comps) == 1 else 0
        want_sys, want_comp = self.configured
        if self.known or not comp or (want_sys and int(system_id) != want_sys) or (want_comp and comp != want_comp):
            return
        self.system_id, self.component_id = int(system_id), comp
        log.info("autopilot is system %d, component %d (MAVSDK's discovery by heartbeat); telemetry from any other "
                 "sender is refused", self.system_id, self.component_id)

    def check(self, name: str, system_id: int, component_id: int) -> str:
        """'' when message ``name`` from ``system_id``/``component_id`` may be taken, else why not."""
        if not self.known:
            return "autopilot not known yet (no heartbeat)"
        if int(system_id) != self.system_id:
            return f"from system {int(system_id)}, not the autopilot's {self.system_id}"
        if name in TRACKER_MESSAGES:
            return ""
        if int(component_id) != self.component_id:
            return f"from component {int(system_id)}/{int(component_id)}, not the autopilot's " \
                   f"{self.system_id}/{self.component_id}"
        return ""


def addressed_to(msg: Any, system_id: int, component_id: int) -> bool:
    """Whether a received message (pymavlink) is for ``system_id``/``component_id``: true for a message without
    target fields (telemetry, HEARTBEAT), else only when its targets are exactly these (a broadcast 0 is not)."""
    ts = getattr(msg, "target_system", None)
    tc = getattr(msg, "target_component", None)
    return (ts is None or int(ts) == int(system_id)) and (tc is None or int(tc) == int(component_id))


def pixel_in_image(xy: Sequence[float], size_px: Sequence[int]) -> bool:
    """Whether pixel ``xy`` (x right, y down, raw image pixels) lies inside an image of ``size_px`` (width,
    height)."""
    if len(xy) != 2:
        return False
    x, y = float(xy[0]), float(xy[1])
    w, h = size_px
    return math.isfinite(x) and math.isfinite(y) and 0.0 <= x < w and 0.0 <= y < h
