"""``gsoe calibrate-mount LOGDIR``: the camera mount's yaw correction learnt in a flight with GNSS and turns
(:mod:`nav.mount_calibration`); with ``--camera FILE`` the corrected ``mount_rpy_deg`` line for that camera file.
Exit 0 with a calibration, 1 when the flight did not pin it down, 2 on a missing or unreadable log."""

from __future__ import annotations

import argparse
import sys


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("logdir", help="a run folder with ekf.csv (gsoe sim, or a companion's logs) of a flight with GNSS "
                   "and turns")
    p.add_argument("--camera", help="the camera file the flight used: print its corrected mount_rpy_deg")


def run(args: argparse.Namespace) -> int:
    from nav.mount_calibration import MAX_SIGMA_DEG, mount_yaw_from_log

    try:
        cal = mount_yaw_from_log(args.logdir)
    except ValueError as e:
        print(f"gsoe calibrate-mount: {e}", file=sys.stderr)
        return 2
    print(f"camera mount yaw: add {cal.correction_deg:+.2f} deg (sigma {cal.sigma_deg:.2f} deg, the estimate at "
          f"t = {cal.t_s:.1f} s of {cal.n_valid} valid ones)")
    if not cal.usable:
        print(f"gsoe calibrate-mount: sigma above {MAX_SIGMA_DEG} deg: not calibrated (fly turns with GNSS)",
              file=sys.stderr)
        return 1
    if args.camera:
        from pipeline.config import load_camera

        r, p, y = load_camera(args.camera).mount_rpy_deg
        print(f"{args.camera}: mount_rpy_deg = [{r:.2f}, {p:.2f}, {y + cal.correction_deg:.2f}]")
    print(f"then [ekf] init_opt_rot_sigma_deg = {max(cal.sigma_deg, 0.1):.2f} (the optical rotation held near it)")
    return 0
