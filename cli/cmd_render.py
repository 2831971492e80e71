"""``gsoe render``: write one rendered raw camera frame to PNG, for looking at.

Example: ``gsoe render --texture town_river --alt-m 100 --roll-deg 30 --out /tmp/frame.png``.  The camera is the
one of the configuration (``--config``, default ``config/default.toml``); the aircraft is at ``--north-m``,
``--east-m`` (NED, metres from the world origin, the centre of the texture tile) and ``--alt-m`` above the flat
ground, with the 3-2-1 Euler attitude ``--roll-deg``, ``--pitch-deg``, ``--yaw-deg``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cv2
import numpy as np

# Euler limits of the 3-2-1 sequence (pitch beyond +-90 deg is not a distinct attitude).
_PITCH_LIMIT_DEG = 90.0
_ANGLE_LIMIT_DEG = 360.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from sim.textures import TEXTURE_NAMES

    parser.add_argument("--texture", required=True, help=f"ground texture: {', '.join(TEXTURE_NAMES)}")
    parser.add_argument("--alt-m", type=float, default=100.0, help="height above the ground (m, > 0)")
    parser.add_argument("--north-m", type=float, default=0.0, help="north position (m)")
    parser.add_argument("--east-m", type=float, default=0.0, help="east position (m)")
    parser.add_argument("--roll-deg", type=float, default=0.0, help="roll (deg, right wing down positive)")
    parser.add_argument("--pitch-deg", type=float, default=0.0, help="pitch (deg, nose up positive, |pitch| < 90)")
    parser.add_argument("--yaw-deg", type=float, default=0.0, help="heading (deg, clockwise from north)")
    parser.add_argument("--config", default=None, help="configuration file (default config/default.toml)")
    parser.add_argument("--seed", type=int, default=0, help="seed of procedural textures (>= 0)")
    parser.add_argument("--color", action="store_true", help="write a colour picture instead of intensity")
    parser.add_argument("--out", required=True, help="output PNG file")


def _fail(message: str) -> int:
    print(f"gsoe render: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from gsoe.camera import CameraModel
    from gsoe.rotation import R_nb_from_euler
    from pipeline.config import load_gsoe_config
    from sim.render import CameraRenderer
    from sim.textures import TEXTURE_NAMES, GroundWorld

    if args.texture not in TEXTURE_NAMES:
        return _fail(f"unknown texture {args.texture!r}; valid names: {', '.join(TEXTURE_NAMES)}")
    for name in ("alt_m", "north_m", "east_m", "roll_deg", "pitch_deg", "yaw_deg"):
        if not math.isfinite(getattr(args, name)):
            return _fail(f"--{name.replace('_', '-')} must be finite, got {getattr(args, name)}")
    if args.alt_m <= 0:
        return _fail(f"--alt-m must be > 0 (height above the ground), got {args.alt_m}")
    if abs(args.pitch_deg) >= _PITCH_LIMIT_DEG:
        return _fail(f"--pitch-deg must be within (-90, 90), got {args.pitch_deg}")
    for name in ("roll_deg", "yaw_deg"):
        if abs(getattr(args, name)) > _ANGLE_LIMIT_DEG:
            return _fail(f"--{name.replace('_', '-')} must be within [-360, 360], got {getattr(args, name)}")
    if args.seed < 0:
        return _fail(f"--seed must be >= 0, got {args.seed}")
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        return _fail(f"--out must be a .png file, got {args.out!r}")
    if not out.parent.is_dir():
        return _fail(f"--out: folder {str(out.parent)!r} does not exist")

    config, _ = load_gsoe_config(args.config)
    camera = CameraModel.from_config(config.camera)
    world = GroundWorld.from_name(args.texture, seed=args.seed, color=args.color)
    renderer = CameraRenderer(camera, world)
    pos_ned_m = np.array([args.north_m, args.east_m, -args.alt_m])
    R_nb = R_nb_from_euler(*np.deg2rad([args.roll_deg, args.pitch_deg, args.yaw_deg]))
    image = renderer.render_color(pos_ned_m, R_nb) if args.color else renderer.render(pos_ned_m, R_nb)
    if not cv2.imwrite(str(out), image):
        return _fail(f"could not write {str(out)!r}")
    h, w = image.shape[:2]
    print(f"wrote {out} ({w}x{h}, texture {args.texture}, height {args.alt_m:g} m)")
    return 0
