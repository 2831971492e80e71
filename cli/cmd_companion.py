"""``gsoe companion --connect URL --camera SOURCE [--config FILE] [--log-dir DIR]``: run next to an autopilot.

``--connect`` (the autopilot) and ``--gcs`` (ground-station commands) take one URL syntax (:mod:`nav.urls`):
``udpin://HOST:PORT``, ``udpout://HOST:PORT``, ``tcpin://HOST:PORT``, ``tcpout://HOST:PORT``,
``serial://DEVICE[:BAUD]``; a URL that is none of them is refused at once, naming the accepted forms.
``--camera``: a device index or ``/dev/videoN``, a video file (paced at its own timestamps, or
``--as-fast-as-possible``), an RTSP URL, ``picam://N`` (picamera2), a GStreamer pipeline where OpenCV has it, or
``sim://127.0.0.1:PORT`` for the simulator's frame stream (``python -m sim.mavlink_vehicle``); a source that cannot
give the camera file's size is refused at start (:mod:`nav.camera_sources`).
``--target-px X,Y`` designates a target to track and fly to (video-tracking guidance); a ground station can
designate one later over ``--gcs URL`` (COMMAND_LONG MAV_CMD_USER_1, param1/param2 = pixel), signed with
``--signing-key FILE`` (then unsigned commands are refused).  ``--set DOTTED.KEY=VALUE`` (repeatable) overrides one
value of any table of the configuration file, written as in TOML (``--set companion.guidance.correct_drift=false``,
``--set 'companion.tracking.source="mavlink"'``, ``--set stab.template_px=21``), checked as the file's own values.
A key of a table the companion does not read is refused.  Exit codes: 0 after a clean stop (SIGINT, SIGTERM,
``--duration-s``), 2 on a setup error (a URL, the configuration, the camera file, the camera source, the signing
key: one line naming it), 1 when the loop itself failed.  Stops cleanly on SIGINT/SIGTERM; ``kill -9`` loses at
most the last ``[companion] log_flush_s`` of the log.
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
from common.configfile import DEFAULT_CONFIG, parse_override

log = logging.getLogger(__name__)
# the tables of the configuration the companion reads (a --set key elsewhere would change nothing)
READ_TABLES = ("camera", "stab", "match", "cycle", "integrity", "pipeline", "ekf", "companion")


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
    from nav.camera_sources import source_help

    parser.add_argument("--connect", required=True, help="the autopilot: udpin://HOST:PORT, udpout://HOST:PORT, "
                        "tcpin://HOST:PORT, tcpout://HOST:PORT or serial://DEVICE[:BAUD]")
    parser.add_argument("--camera", required=True, help=source_help())
    parser.add_argument("--as-fast-as-possible", action="store_true",
                        help="a video file as --camera: read it as fast as it decodes, stamped when read (default: "
                        "paced at its frame rate, stamped with its own timestamps)")
    parser.add_argument("--config", help="configuration file (default: config/default.toml)")
    parser.add_argument("--log-dir", help="log folder (default: logs/companion-<UTC time>); one holding another run's "
                        "logs gives DIR-2, DIR-3, ...")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the logs of an earlier run in --log-dir instead of logging beside them")
    parser.add_argument("--target-px", type=_pair, help="designate a target at X,Y (raw image pixels)")
    parser.add_argument("--gcs", help="the companion's own link for ground-station commands (the same URL forms "
                        "as --connect)")
    parser.add_argument("--signing-key", help="MAVLink 2 signing key file for --gcs (unsigned commands refused)")
    parser.add_argument("--duration-s", type=float, help="stop after this long (default: run until stopped)")
    parser.add_argument("--set", type=_setting, action="append", default=[], dest="settings",
                        help="override a configuration value: DOTTED.KEY=TOML_VALUE (repeatable)")


def run(args: argparse.Namespace) -> int:
    from common.logio import claim_run_folder
    from fusion.config import ekf_config_from_raw
    from gsoe.camera import CameraModel
    from nav.camera_sources import CameraSetupError, check_source_at_start
    from nav.companion import Companion, companion_config_from_raw
    from nav.hygiene import pixel_in_image
    from nav.urls import LinkUrlError, parse_link_url
    from pipeline.config import load_gsoe_config
    from pipeline.navpipeline import pipeline_config_from_raw

    def setup_error(what: object) -> int:
        print(f"gsoe companion: {what}", file=sys.stderr)
        return 2

    try:
        connect = parse_link_url(args.connect, "--connect")
        gcs = parse_link_url(args.gcs, "--gcs") if args.gcs else None
    except LinkUrlError as e:
        return setup_error(e)
    for path, _ in args.settings:
        if path[0] not in READ_TABLES:
            raise ConfigError(f"--set {'.'.join(path)}", f"the companion does not read [{path[0]}] (it reads "
                              f"{', '.join(f'[{t}]' for t in READ_TABLES)})")
    if args.as_fast_as_possible:
        args.settings.append((["companion", "video_pacing"], "as_fast_as_possible"))
    gsoe_cfg, raw = load_gsoe_config(args.config, overrides=args.settings)
    where = {".".join(p).split("[")[0] for p, _ in args.settings}

    def named(e: ConfigError) -> ConfigError:  # an error in a --set value names the option
        by_set = any(e.field_path == k or e.field_path.startswith(k + ".") for k in where)
        return ConfigError(f"--set {e.field_path}" if by_set else f"{args.config or DEFAULT_CONFIG}: {e.field_path}",
                           str(e).split(": ", 1)[1])

    try:  # every table the companion reads, checked before anything starts
        cfg = companion_config_from_raw(raw)
        if cfg.use_ekf:
            ekf_config_from_raw(raw.get("ekf", {}))
        pipeline_config_from_raw(raw)
    except ConfigError as e:
        raise named(e) from None
    key = None
    if args.signing_key:
        from nav.signing import load_key

        try:
            key = load_key(args.signing_key)
        except (OSError, ValueError) as e:
            return setup_error(f"--signing-key {args.signing_key}: {getattr(e, 'strerror', None) or e}")
    size_px = CameraModel.from_config(gsoe_cfg.camera).size_px
    if args.target_px is not None and not pixel_in_image(args.target_px, size_px):
        x, y = args.target_px
        return setup_error(f"--target-px {x:g},{y:g}: outside the camera's {size_px[0]}x{size_px[1]} image "
                           f"(0 <= x < {size_px[0]}, 0 <= y < {size_px[1]})")
    try:
        check_source_at_start(args.camera, size_px, cfg.camera_fps)
    except CameraSetupError as e:
        return setup_error(e)
    asked = Path(args.log_dir or Path("logs") / time.strftime("companion-%Y%m%dT%H%M%SZ", time.gmtime()))
    log_dir = str(claim_run_folder(asked, overwrite=args.overwrite, numbered=True))
    if Path(log_dir) != asked:
        log.warning("log folder %s holds the logs of another run: logging to %s", asked, log_dir)
    app = Companion(connect.mavsdk, args.camera, gsoe_cfg, raw, log_dir, target_px=args.target_px,
                    gcs_url=gcs.pymavlink if gcs else None, signing_key=key)

    def _stop(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping", signum)
        app.request_stop()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    app.destroy_link_native = False
    code = 0
    try:
        status = app.run(args.duration_s)
    except Exception as e:  # the loop survives bad inputs; what escapes it is a failure of the companion itself
        log.exception("the companion stopped on an error: %s", e)
        status, code = app.status(), 1
    print(json.dumps(status, indent=1, default=str), flush=True)
    # The logs are closed.  Leave without running native destructors: the MAVSDK binding has been seen to
    # segfault when torn down while its receive threads are busy, which would turn a clean stop into a crash.
    logging.shutdown()
    sys.stderr.flush()
    os._exit(code)
