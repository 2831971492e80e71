"""``gsoe report LOGDIR``: the flight report (``report.html`` and its figures) of any run folder: ``gsoe sim``,
``gsoe replay`` or a companion's flight logs (:mod:`sim.logreport`).  A folder without ``metrics.json`` gets one
computed from its logs.  ``--mcap`` also writes the logs as one MCAP file for Foxglove or PlotJuggler
(:mod:`sim.mcap_export`)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("logdir", help="a run folder holding ekf.csv (and gnss.csv, aid_status.csv, truth.csv, ...)")
    p.add_argument("--title", help="the page's title (default: the kind of run and the folder's name)")
    p.add_argument("--mcap", action="store_true", help="also write LOGDIR/flight.mcap (every CSV stream, JSON "
                   "messages; opens in Foxglove and PlotJuggler)")


def run(args: argparse.Namespace) -> int:
    import importlib.util
    import sys

    from sim.logreport import build_report

    if args.mcap and importlib.util.find_spec("mcap") is None:
        print("gsoe report: --mcap needs the mcap package: pip install 'gsoe-nav[report]'", file=sys.stderr)
        return 2
    folder = Path(args.logdir)
    if not folder.is_dir():
        raise FileNotFoundError(2, "no such folder", str(folder))
    page = build_report(folder, title=args.title)
    print(f"gsoe report: wrote {page}")
    if args.mcap:
        from sim.mcap_export import export_mcap

        print(f"gsoe report: wrote {export_mcap(folder)}")
    return 0
