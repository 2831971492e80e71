"""``gsoe replay-frames SOURCE [--camera FILE] [--profile NAME] [--ground-level-m H] [--out DIR] [--overwrite]
[--config FILE]``: a real image sequence through the navigation pipeline, each frame pair's optical ground
velocity against the sequence's reference velocity (see :mod:`nav.replay_frames`).

``SOURCE`` is a CSV file (the generic format of :mod:`nav.imageseq`; ``--camera`` gives its camera file, default
the configuration's camera) or the CLIF 2007 folder (``jpg/``, ``pos/``, ``krtd/``; its camera comes from the
bundle-adjusted cameras; profile ``low_rate_oblique`` unless ``--profile`` says otherwise, ``--profile none`` for
the plain configuration).  Writes ``pairs.csv``, ``gsoe.csv`` and ``metrics.json`` into ``--out``.
Exit codes: 0 done, 2 the sequence or an option is unusable, 1 an unexpected failure.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

log = logging.getLogger(__name__)

HEADLINE = ("frames", "pairs", "pairs_accepted", "accepted_frac", "speed_err_median_pct", "speed_abs_err_median_pct",
            "speed_abs_err_p95_pct", "course_err_median_deg", "course_abs_err_median_deg", "course_abs_err_p95_deg",
            "vel_err_rms_m_s")
CLIF_PROFILE = "low_rate_oblique"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="a sequence CSV (nav/imageseq.py) or the CLIF 2007 folder (jpg/, pos/, krtd/)")
    p.add_argument("--camera", default=None, help="camera file of a CSV sequence (default: the configuration's)")
    p.add_argument("--profile", default=None,
                   help="estimator profile, [replay_frames.profiles.NAME] (CLIF default low_rate_oblique; "
                        "'none' for the plain configuration)")
    p.add_argument("--ground-level-m", type=float, default=None, metavar="H",
                   help="CLIF: the ground's level on the INS altitude's datum (default: from the bundle adjustment)")
    p.add_argument("--out", default="out/replay_frames", help="output folder (default out/replay_frames)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the logs of an earlier run in --out (without it such a folder is refused)")
    p.add_argument("--config", default=None, help="configuration file (default config/default.toml)")


def run(args: argparse.Namespace) -> int:
    from common.logio import claim_run_folder
    from nav.imageseq import SequenceError, read_clif2007, read_csv_sequence
    from nav.replay_frames import run_replay_frames
    from pipeline.config import load_camera, load_gsoe_config

    src = Path(args.source)
    if not src.exists():
        raise FileNotFoundError(2, "no such sequence", str(src))
    try:
        if src.is_dir():
            seq = read_clif2007(src, ground_level_m=args.ground_level_m)
            camera = None
            profile = CLIF_PROFILE if args.profile is None else args.profile
        else:
            camera = load_camera(args.camera) if args.camera else load_gsoe_config(args.config)[0].camera
            seq = read_csv_sequence(src, camera)
            profile = args.profile
    except SequenceError as e:
        print(f"gsoe replay-frames: {e}", file=sys.stderr)
        return 2
    profile = None if profile in (None, "", "none") else profile
    out = claim_run_folder(Path(args.out), overwrite=args.overwrite)
    result = run_replay_frames(seq, out_dir=out, config_path=args.config, profile=profile, camera=camera)
    m = result.metrics
    print(f"gsoe replay-frames: {seq.name} ({m['frames']} frames, {m['duration_s']:.1f} s, profile "
          f"{m['profile'] or 'none'}), wrote {out}/ (pairs.csv, gsoe.csv, metrics.json)")
    for note in m["notes"]:
        print(f"  {note}")
    for k in HEADLINE:
        v = m.get(k)
        print(f"  {k:28s} {v:.4g}" if isinstance(v, float) and math.isfinite(v) else f"  {k:28s} {v}")
    return 0
