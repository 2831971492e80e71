"""``gsoe companion --connect URL --camera SOURCE [--config FILE] [--log-dir DIR]``: run next to an autopilot.

``--connect``: a MAVSDK connection URL (``udpin://0.0.0.0:14540``, ``serial:///dev/ttyAMA0:921600``, ...).
``--camera``: a device index, a video file, a GStreamer pipeline or RTSP URL (anything ``cv2.VideoCapture``
opens), or ``sim://127.0.0.1:PORT`` for the simulator's frame stream (``python -m sim.mavlink_vehicle``).
``--target-px X,Y`` designates a target to track and fly to (video-tracking guidance); a ground station can
designate one later over ``--gcs URL`` (COMMAND_LONG MAV_CMD_USER_1, param1/param2 = pixel), signed with
``--signing-key FILE`` (then unsigned commands are refused).  ``--set DOTTED.KEY=VALUE`` (repeatable) overrides one
value of any table of the configuration file, written as in TOML (``--set companion.guidance.correct_drift=false``,
``--set 'companion.tracking.source="mavlink"'``, ``--set stab.template_px=21``), checked as the file's own values.
Stops cleanly on SIGINT/SIGTERM; ``kill -9`` loses at most the last ``[companion] log_flush_s`` of the log.
A ``--log-dir`` that holds another run's logs is never appended to: the companion logs into the next free
``DIR-2``, ``DIR-3``, ... beside it (it must not refuse to fly), or replaces them with ``--overwrite``
(:func:`common.logio.claim_run_folder`).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from common.config import ConfigError
from common.configfile import parse_override

log = logging.getLogger(__name__)


def _pair(text: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in pixels, got {text!r}") from None
    return a, b


def _setting(text: str) -> tuple[list[str], Any]:
    try:
        return parse_override(text)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--connect", required=True, help="MAVSDK connection URL, e.g. udpin://0.0.0.0:14540")
    parser.add_argument("--camera", required=True, help="camera index, file, GStreamer/RTSP URL or sim://HOST:PORT")
    parser.add_argument("--config", help="configuration file (default: config/default.toml)")
    parser.add_argument("--log-dir", help="log folder (default: logs/companion-<UTC time>); one holding another run's "
                        "logs gives DIR-2, DIR-3, ...")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the logs of an earlier run in --log-dir instead of logging beside them")
    parser.add_argument("--target-px", type=_pair, help="designate a target at X,Y (raw image pixels)")
    parser.add_argument("--gcs", help="the companion's own link for ground-station commands (pymavlink URL)")
    parser.add_argument("--signing-key", help="MAVLink 2 signing key file for --gcs (unsigned commands refused)")
    parser.add_argument("--duration-s", type=float, help="stop after this long (default: run until stopped)")
    parser.add_argument("--set", type=_setting, action="append", default=[], dest="settings",
                        help="override a configuration value: DOTTED.KEY=TOML_VALUE (repeatable)")


def run(args: argparse.Namespace) -> int:
    from common.logio import claim_run_folder
    from nav.companion import Companion
    from pipeline.config import load_gsoe_config

    gsoe_cfg, raw = load_gsoe_config(args.config, overrides=args.settings)
    asked = Path(args.log_dir or Path("logs") / time.strftime("companion-%Y%m%dT%H%M%SZ", time.gmtime()))
    log_dir = str(claim_run_folder(asked, overwrite=args.overwrite, numbered=True))
    if Path(log_dir) != asked:
        log.warning("log folder %s holds the logs of another run: logging to %s", asked, log_dir)
    key = None
    if args.signing_key:
        from nav.signing import load_key

        key = load_key(args.signing_key)
    app = Companion(args.connect, args.camera, gsoe_cfg, raw, log_dir, target_px=args.target_px, gcs_url=args.gcs,
                    signing_key=key)

    def _stop(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping", signum)
        app.request_stop()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    app.destroy_link_native = False
    status = app.run(args.duration_s)
    print(json.dumps(status, indent=1, default=str), flush=True)
    # The logs are closed.  Leave without running native destructors: the MAVSDK binding has been seen to
    # segfault when torn down while its receive threads are busy, which would turn a clean stop into a crash.
    logging.shutdown()
    sys.stderr.flush()
    os._exit(0)
