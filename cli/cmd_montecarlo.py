"""``gsoe montecarlo [-n N] [--scenario BASE] [--spec FILE] [--duration S] [--scheduler ADDR] [--workers K]
[--out DIR] [--resume [--retry-failed]] [--only I] [--seed BASE_SEED]``

Flies a seeded Monte Carlo campaign of simulated flights (:mod:`sim.montecarlo`) on a local process pool (all
cores by default) or on a Dask cluster (``--scheduler tcp://HOST:PORT``), writing each run to ``DIR/runs`` as it
finishes, then ``DIR/summary.json`` and ``DIR/report.html``.  ``--resume`` completes an interrupted campaign (or
extends it with a larger ``-n``) without re-flying finished runs; with nothing left to fly it re-aggregates.
``--retry-failed`` (with ``--resume``) flies the runs recorded as failed again.
``--only I`` re-flies run ``I`` of the campaign in ``DIR`` alone (its spec, seed and duration from
``DIR/campaign.json``), with logs and plots in ``DIR/reflown/run_0000I``, and checks that its record matches the
campaign's bit for bit.

Exit status: 0 done (all runs ok; re-fly identical), 1 some runs failed or the re-fly differs, 2 bad input.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path
from typing import Any

from cli.argtypes import int_at_least, positive_float
from common.hostref import describe

log = logging.getLogger(__name__)

DEFAULT_OUT_ROOT = Path("out") / "montecarlo"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-n", "--runs", dest="n_runs", type=int_at_least(1), default=None,
                        help="number of runs (default: the spec's n_runs)")
    parser.add_argument("--scenario", default=None, help="base scenario name or file (default: the spec's)")
    parser.add_argument("--spec", default=None,
                        help="campaign spec (config/montecarlo/*.toml name or path; default: default)")
    parser.add_argument("--duration", type=positive_float, default=None,
                        help="each flight's length in seconds (default: the spec's, else the base scenario's)")
    parser.add_argument("--scheduler", default=None, help="Dask scheduler address tcp://HOST:PORT (default: local)")
    parser.add_argument("--workers", type=int_at_least(0), default=None,
                        help="local worker processes (default: all cores; 0 flies in this process)")
    parser.add_argument("--out", type=Path, default=None, help="campaign folder (default out/montecarlo/NAME-seedS)")
    parser.add_argument("--resume", action="store_true", help="complete the campaign in --out, skipping finished runs")
    parser.add_argument("--retry-failed", action="store_true",
                        help="with --resume: fly the runs recorded as failed again")
    parser.add_argument("--only", type=int_at_least(0), default=None, metavar="I",
                        help="re-fly run I of the campaign in --out alone and compare with its record")
    parser.add_argument("--seed", type=int_at_least(0), default=None, help="base seed (default: the spec's)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _fail(message: str) -> int:
    print(f"gsoe montecarlo: {message}", file=sys.stderr)
    return 2


def _print_goals(summary: dict[str, Any]) -> None:
    for g in summary["goals"]:
        value = g["value"]
        shown = "n/a" if value is None or not math.isfinite(value) else f"{value:.4g}"
        frac = g["frac_runs_meeting"]
        frac_s = "n/a" if frac is None or not math.isfinite(frac) else f"{frac:.0%}"
        print(f"  {'met   ' if g['met'] else 'MISSED'} {g['name']:<18} {g['stat']}({g['metric']}) = {shown} "
              f"{g['op']} {g['threshold']:g}   runs meeting: {frac_s}")
    tp = summary["throughput"]
    print(f"  throughput: {tp['sim_s_per_wall_s']:.3g} sim s per wall s, projected 100 x 600 s campaign "
          f"{tp['projected_wall_s_100x600']:.0f} s; max worker peak RSS {tp['peak_rss_mb_max']:.0f} MB"
          if tp["sim_s_per_wall_s"] is not None and tp["peak_rss_mb_max"] is not None else "  throughput: n/a")
    hosts = [s["host"] for s in tp.get("sessions", []) if isinstance(s.get("host"), dict)]
    if hosts:
        print(f"  {describe(hosts[-1])}")


def _refly(args: argparse.Namespace) -> int:
    from sim.montecarlo import (
        CAMPAIGN_FILE,
        code_fingerprint,
        load_campaign_spec,
        load_spec,
        read_record,
        refly,
        run_path,
    )

    if args.out is None:
        return _fail("--only needs --out DIR, the campaign folder")
    if (args.out / CAMPAIGN_FILE).exists():
        spec = load_campaign_spec(args.out)
        given = [o for o in ("spec", "scenario", "duration", "seed", "n_runs") if getattr(args, o) is not None]
        if given:
            log.warning("--only uses the spec, seed and duration of %s; ignoring %s", args.out / CAMPAIGN_FILE,
                        ", ".join(f"--{g}" for g in given))
    else:
        spec = load_spec(args.spec, base_scenario=args.scenario).with_options(
            n_runs=args.n_runs, base_seed=args.seed, duration_s=args.duration)
    rec, diffs = refly(args.out, args.only, spec=spec)
    where = args.out / "reflown" / f"run_{args.only:05d}"
    print(f"run {rec.index} (seed {rec.run_seed}): {rec.status}{': ' + rec.error if rec.error else ''}; "
          f"wall {rec.wall_s:.1f} s; outputs in {where}")
    if diffs is None:
        print("no campaign record of this run to compare with")
        return 0 if rec.status == "ok" else 1
    flown_by = read_record(run_path(args.out, args.only)).code
    if flown_by != code_fingerprint():
        print(f"note: the campaign's record was flown by code {flown_by or '(not recorded)'}, this re-flight by "
              f"{code_fingerprint()}: differences may come from the code")
    if diffs:
        print(f"DIFFERS from the campaign's record in: {', '.join(diffs)}")
        return 1
    print("identical to the campaign's record (timing fields excepted)")
    return 0


def run(args: argparse.Namespace) -> int:
    from sim.mc_report import write_report
    from sim.montecarlo import load_campaign_spec, load_spec, read_campaign, run_campaign

    if args.only is not None:
        return _refly(args)
    if args.scheduler is not None and not args.scheduler.strip():
        return _fail("--scheduler must be an address such as tcp://HOST:PORT")
    camp = read_campaign(args.out) if args.resume and args.out is not None else None
    n_runs = args.n_runs
    if camp is not None and n_runs is None:
        n_runs = int(camp["spec"]["n_runs"])  # resuming keeps the campaign's size unless -n changes it
    if camp is not None and args.spec is None and args.scenario is None:
        # Resuming without a spec: continue with the campaign's own spec.
        spec = load_campaign_spec(args.out).with_options(n_runs=n_runs, base_seed=args.seed,
                                                         duration_s=args.duration)
    else:
        spec = load_spec(args.spec, base_scenario=args.scenario).with_options(
            n_runs=n_runs, base_seed=args.seed, duration_s=args.duration)
    out = args.out if args.out is not None else DEFAULT_OUT_ROOT / f"{spec.name}-seed{spec.base_seed}"
    if args.scheduler is not None and args.workers is not None:
        log.warning("--workers is ignored with --scheduler (the Dask cluster has its own workers)")
    if args.retry_failed and not args.resume:
        return _fail("--retry-failed needs --resume")
    result = run_campaign(spec, out, scheduler=args.scheduler, workers=args.workers, resume=args.resume,
                          retry_failed=args.retry_failed, progress=not args.no_progress)
    report = write_report(out)
    import json

    summary = json.loads((out / "summary.json").read_text())
    print(f"campaign {spec.name!r}: {len(result.flown)} runs flown, {len(result.skipped)} already done, "
          f"{len(result.failed)} failed this session, {result.wall_s:.1f} s on {result.backend} "
          f"({result.workers} workers)")
    _print_goals(summary)
    print(f"report: {report}")
    return 1 if summary["campaign"]["n_failed"] else 0
