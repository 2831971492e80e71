"""``gsoe replay LOG [--gnss-off-at S] [--out DIR] [--overwrite] [--config FILE] [--optical-sigma-px X] [--seed N]
[--no-optical]``: replay a real flight log (.tlog, .bin, .ulg) through the navigation EKF (see :mod:`nav.replay`).
A folder that holds another run's logs is refused unless ``--overwrite`` (:func:`common.logio.claim_run_folder`).

Without a camera in the log the optical measurements are synthesised from GNSS ground velocity (said so in the
output); they keep running after ``--gnss-off-at`` (they play the camera), only GNSS fusion stops.  ``--no-optical``
dead-reckons on IMU and air data only.  Exit codes: 0 done (problems of the log, e.g. a truncated file, are printed
and kept in ``metrics.json``: the readable part was replayed), 2 the log cannot be replayed or an option is bad,
1 an unexpected failure (reported in one line; ``-v`` logs the traceback).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

log = logging.getLogger(__name__)

HEADLINE = ("optical_source", "optical_steps", "optical_noise_sigma_px_mean", "ekf_start_s",
            "wind_rmse_vs_autopilot_m_s", "wind_rmse_vs_autopilot_before_gnss_off_m_s",
            "wind_rmse_vs_autopilot_after_gnss_off_m_s", "autopilot_wind_speed_mean_m_s", "ekf_wind_speed_mean_m_s",
            "pos_error_rms_with_gnss_m", "gnss_off_at_s", "dr_duration_s", "dr_distance_m", "dr_error_m",
            "dr_error_pct_of_distance", "dr_max_error_m")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="flight log: .tlog (MAVLink telemetry), .bin (ArduPilot DataFlash) or .ulg (PX4)")
    p.add_argument("--gnss-off-at", type=float, default=None, metavar="S",
                   help="stop fusing GNSS position and velocity S seconds after the log's start and dead-reckon "
                        "(the synthetic optical steps keep running)")
    p.add_argument("--out", default="out/replay", help="output folder (default out/replay)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the logs of an earlier run in --out (without it such a folder is refused)")
    p.add_argument("--config", default=None, help="configuration file (default config/default.toml)")
    p.add_argument("--optical-sigma-px", type=float, default=None, metavar="X",
                   help="pixel noise (1 sigma per axis) of the synthetic optical steps (default: [replay] "
                        "optical_sigma_px; 0 there means the EKF's optical noise model)")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic optical noise (default 0)")
    p.add_argument("--no-optical", action="store_true",
                   help="no synthetic optical measurements: dead-reckon on IMU and air data only")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures and report.html")


def run(args: argparse.Namespace) -> int:
    from common.logio import claim_run_folder
    from nav.logreader import LogFormatError
    from nav.replay import OPTICAL_SOURCE_SYNTHETIC, ReplayError, run_replay

    if not Path(args.log).is_file():                # before the output folder is claimed (and maybe cleared)
        raise FileNotFoundError(2, "no such log file", args.log)
    out = claim_run_folder(Path(args.out), overwrite=args.overwrite)
    try:
        result = run_replay(args.log, out_dir=out, config_path=args.config, gnss_off_at_s=args.gnss_off_at,
                            optical=not args.no_optical, optical_sigma_px=args.optical_sigma_px, seed=args.seed,
                            plots=not args.no_plots)
    except (ReplayError, LogFormatError) as e:
        print(f"gsoe replay: {e}", file=sys.stderr)
        return 2
    except (FileNotFoundError, KeyboardInterrupt):
        raise                                      # cli.main reports these
    except Exception as e:  # noqa: BLE001 - a bad log must end in one clear line, never a traceback
        log.debug("replay failed", exc_info=True)
        print(f"gsoe replay: unexpected failure while replaying {args.log}: {type(e).__name__}: {e}",
              file=sys.stderr)
        return 1
    m = result.metrics
    files = "metrics.json, CSV logs" + ("" if args.no_plots else ", plots, report.html")
    print(f"gsoe replay: {Path(args.log).name} ({m['log_format']}, {m['log_duration_s']:.1f} s), wrote {out}/ "
          f"({files})")
    if m["log_warnings"]:
        print("  the log is damaged or incomplete; the readable part was replayed:")
        for w in m["log_warnings"]:
            print(f"    {w}")
    if m["optical_source"] == OPTICAL_SOURCE_SYNTHETIC:
        print("  NOTE: no camera in the log; the optical measurements are SYNTHETIC (GNSS ground velocity plus pixel "
              "noise) and keep running after --gnss-off-at")
    for k in HEADLINE:
        if k in m and m[k] is not None:
            v = m[k]
            print(f"  {k:44s} {v:.4g}" if isinstance(v, float) and math.isfinite(v) else f"  {k:44s} {v}")
    for w in m["warnings"]:
        if w not in m["log_warnings"]:
            print(f"  warning: {w}")
    return 0
