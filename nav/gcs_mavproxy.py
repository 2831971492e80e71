"""MAVProxy module: the companion's wind (speed and direction with their sigma), drift, ATA, GSOE quality and GNSS
state on MAVProxy's console status bar, and a spoken/printed warning when the estimate goes invalid.

Install MAVProxy without its GUI dependencies (they pull the non-headless OpenCV next to ours)::

    pip install --no-deps MAVProxy pymavlink pyserial

Load it (the repository must be importable, e.g. installed with ``pip install -e .``)::

    mavproxy.py --master=udpin:0.0.0.0:14550 --cmd="module load nav.gcs_mavproxy"

Commands: ``gsoe`` or ``gsoe status`` prints the display lines; ``gsoe json`` prints one line ``GSOE_STATE
{...}`` with the whole state (:meth:`nav.gcs_display.GsoeGroundState.as_dict`); ``gsoe set stale_s 5`` /
``gsoe set source_component 0`` change the settings (0: accept the values from any component).  The state itself
is :class:`nav.gcs_display.GsoeGroundState` (tested without MAVProxy).
"""

from __future__ import annotations

import json
import time
from typing import Any

from MAVProxy.modules.lib import mp_module, mp_settings

from nav.gcs_display import MAV_COMP_ID_ONBOARD_COMPUTER, GsoeGroundState

STATUS_ROW = 6  # console status-bar row of the three GSOE lines
MODULE_NAME = "gsoe"


class GsoeModule(mp_module.MPModule):
    """Feeds every MAVLink packet to a :class:`GsoeGroundState`, shows it, and warns."""

    def __init__(self, mpstate: Any) -> None:
        super().__init__(mpstate, MODULE_NAME, "GSOE wind, drift and GNSS state display", public=True)
        self.gsoe_settings = mp_settings.MPSettings([("stale_s", float, 3.0),
                                                     ("source_component", int, MAV_COMP_ID_ONBOARD_COMPUTER)])
        self.state = GsoeGroundState(source_component=MAV_COMP_ID_ONBOARD_COMPUTER, stale_s=3.0)
        self.add_command(MODULE_NAME, self.cmd_gsoe, "GSOE display", ["status", "json", "set (GSOESETTING)"])

    def _warn(self, texts: list[str]) -> None:
        for text in texts:
            self.say(text)

    def _show(self) -> None:
        for name, text in self.state.lines().items():
            invalid = self.state.valid is False or self.state.stale
            self.console.set_status(name, text, row=STATUS_ROW, fg="red" if invalid else "darkgreen")

    def mavlink_packet(self, m: Any) -> None:
        before = sum(self.state.counts.values())
        self._warn(self.state.update(m, time.monotonic()))
        if sum(self.state.counts.values()) != before:
            self._show()

    def idle_task(self) -> None:
        texts = self.state.check(time.monotonic())
        if texts:
            self._warn(texts)
            self._show()

    def cmd_gsoe(self, args: list[str]) -> None:
        if not args or args[0] == "status":
            for text in self.state.lines().values():
                print(text)
        elif args[0] == "json":
            print("GSOE_STATE " + json.dumps(self.state.as_dict()), flush=True)
        elif args[0] == "set":
            self.gsoe_settings.command(args[1:])
            self.state.stale_s = float(self.gsoe_settings.stale_s)
            self.state.source_component = int(self.gsoe_settings.source_component)
        else:
            print("usage: gsoe <status|json|set>")


def init(mpstate: Any) -> GsoeModule:
    """MAVProxy's module entry point."""
    return GsoeModule(mpstate)
