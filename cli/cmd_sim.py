"""``gsoe sim [SCENARIO] [--duration S] [--seed N] [--out DIR] [--overwrite]``: fly a simulated scenario and report.

A folder that holds another run's logs is refused unless ``--overwrite`` (:func:`common.logio.claim_run_folder`)."""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

os.environ.setdefault("JSBSIM_DEBUG", "0")

DEFAULT_SCENARIO = "paper_sil_outage"
HEADLINE = ("drift_mae_deg", "drift_p95_deg", "drift_mae_vs_gnss_deg", "heading_coverage", "wind_speed_rmse_m_s",
            "wind_dir_rmse_deg", "nees_in_bounds_frac", "dr_error_pct_of_distance", "baseline_drift_mae_deg",
            "baseline_drift_mae_vs_gnss_deg", "baseline_heading_coverage", "baseline_wind_speed_rmse_m_s",
            "frames", "sim_s", "wall_s", "realtime_factor")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", default=DEFAULT_SCENARIO,
                   help=f"scenario name in config/scenarios or a TOML path (default: {DEFAULT_SCENARIO}; the paper's "
                   "flight: paper_sil; --list-scenarios)")
    p.add_argument("--duration", type=float, default=None, help="flight length in seconds (default: scenario's)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: scenario's)")
    p.add_argument("--out", default="out/sim", help="output folder (default out/sim)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the logs of an earlier run in --out (without it such a folder is refused)")
    p.add_argument("--config", default=None, help="estimator configuration (default config/default.toml)")
    p.add_argument("--full-frame", action="store_true", help="render whole frames instead of the estimator's ROI")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--list-scenarios", action="store_true", help="list the named scenarios and exit")
    p.add_argument("--log", choices=("reports", "full"), default="reports",
                   help="reports (default): the per-step streams thinned to what the reports plot (2000 s in about "
                   "30 MB); full: every sample and step")


def run(args: argparse.Namespace) -> int:
    from common.logio import claim_run_folder
    from sim.run import run_flight
    from sim.scenario import load_scenario, scenario_descriptions

    if args.list_scenarios:
        for name, text in scenario_descriptions().items():
            print(f"{name:16s} {text}{'  (default)' if name == DEFAULT_SCENARIO else ''}")
        return 0
    scn = load_scenario(args.scenario)
    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        print(f"gsoe sim: --duration must be > 0, got {args.duration}")
        return 2
    seed = scn.seed if args.seed is None else args.seed
    out = claim_run_folder(Path(args.out), overwrite=args.overwrite)
    metrics = run_flight(scn, seed=seed, duration_s=args.duration, out_dir=out, progress=not args.no_progress,
                         config_path=args.config, full_frame=args.full_frame, log_detail=args.log)
    print(f"gsoe sim: {scn.name}, seed {seed}, wrote {out}/ (metrics.json, report.html, plots, CSV logs)")
    for k in HEADLINE:
        if k in metrics:
            v = metrics[k]
            print(f"  {k:32s} {v:.4g}" if isinstance(v, float) else f"  {k:32s} {v}")
    print("  time split [s]: " + json.dumps(metrics.get("time_split_s", {})))
    if metrics.get("interrupted"):
        print("gsoe sim: interrupted; the partial logs in the output folder are readable")
        return 130
    if metrics.get("crashed"):
        print(f"gsoe sim: the flight stopped early: {metrics['crashed']}")
        return 1
    return 0
