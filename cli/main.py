"""The ``gsoe`` command line.  Each subcommand lives in its own module with ``add_arguments(parser)`` and
``run(args) -> int``; modules are imported only when their subcommand runs, so one heavy dependency never slows
the others down."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys

from common.config import ConfigError

# subcommand -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "calibrate": ("cli.cmd_calibrate", "calibrate a camera from chessboard images and write a camera file"),
    "calibrate-mount": ("cli.cmd_calibrate_mount", "the camera mount's yaw correction learnt in a flight (ekf.csv)"),
    "render": ("cli.cmd_render", "render one raw fisheye camera frame to PNG"),
    "bench": ("cli.cmd_bench", "benchmark the per-frame optical pipeline, renderer and EKF step"),
    "sim": ("cli.cmd_sim", "fly a simulated scenario (default: the paper's SIL flight) and report"),
    "replay": ("cli.cmd_replay", "replay a real flight log (.tlog, .bin, .ulg) through the EKF"),
    "replay-frames": ("cli.cmd_replay_frames", "a real image sequence through the optical pipeline, against its "
                                               "reference velocity"),
    "companion": ("cli.cmd_companion", "run the companion app next to an autopilot"),
    "sitl-camera": ("cli.cmd_sitl_camera", "render the belly camera of a plane flown by ArduPlane SITL (its "
                                           "SIM_STATE) as the simulator's frame stream"),
    "montecarlo": ("cli.cmd_montecarlo", "run a seeded Monte Carlo campaign of simulated flights"),
    "report": ("cli.cmd_report", "the flight report (report.html) of a run folder: gsoe sim, gsoe replay or a "
                                 "companion's logs"),
}


# subcommand -> (the pyproject extra that installs what it needs, modules of that extra it imports)
EXTRAS: dict[str, tuple[str, tuple[str, ...]]] = {
    "companion": ("companion", ("mavsdk", "pymavlink")),
    "render": ("sim", ("numba",)),
    "bench": ("sim", ("numba",)),
    "sim": ("sim", ("jsbsim", "numba", "tqdm", "matplotlib")),
    "sitl-camera": ("sim", ("numba", "pymavlink")),
    "montecarlo": ("mc", ("jsbsim", "numba", "dask", "distributed", "tomli_w")),
    "replay": ("report", ("matplotlib", "pymavlink")),
    "report": ("report", ("matplotlib",)),
}


def _available() -> dict[str, tuple[str, str]]:
    return {k: v for k, v in SUBCOMMANDS.items() if importlib.util.find_spec(v[0]) is not None}


def missing_extra(command: str) -> str | None:
    """What to install for ``command`` when a module of its extra is not importable (None: all there)."""
    extra, modules = EXTRAS.get(command, ("", ()))
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if not missing:
        return None
    return f"needs the [{extra}] extra (missing: {', '.join(missing)}): pip install 'gsoe-nav[{extra}]'"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="gsoe", description="Ground Speed Optical Estimator navigation module")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (mod_name, help_text) in _available().items():
        need = missing_extra(name)
        sp = sub.add_parser(name, help=help_text + (f" [not installed: gsoe-nav[{EXTRAS[name][0]}]]" if need else ""))
        if name == chosen:
            if need:
                print(f"gsoe {name}: {need}", file=sys.stderr)
                return 2
            importlib.import_module(mod_name).add_arguments(sp)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    module = importlib.import_module(SUBCOMMANDS[args.command][0])
    try:
        return int(module.run(args) or 0)
    except ConfigError as e:
        print(f"gsoe {args.command}: configuration error: {e}", file=sys.stderr)
        return 2
    except FileNotFoundError as e:
        print(f"gsoe {args.command}: file not found: {e.filename or e}", file=sys.stderr)
        return 2
    except (FileExistsError, NotADirectoryError) as e:  # an output folder in use (common.logio.claim_run_folder)
        print(f"gsoe {args.command}: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # any other path the command cannot use (a folder for a file, no permission)
        print(f"gsoe {args.command}: {e.strerror or e}{f': {e.filename}' if e.filename else ''}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gsoe {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
