"""``gsoe sitl-camera --connect tcp:127.0.0.1:5762 --frame-port PORT``: the belly camera of a plane flown by
ArduPlane SITL, rendered from its SIM_STATE truth and served as the simulator's frame stream (:mod:`sim.sitl_camera`);
the companion reads it with ``--camera sim://127.0.0.1:PORT``."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from sim.sitl_camera import add_arguments as add

    add(parser)


def run(args: argparse.Namespace) -> int:
    from sim.sitl_camera import run as run_bridge

    return run_bridge(args)
