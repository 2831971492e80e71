"""``gsoe calibrate IMAGES... --board 8x6 --square SIZE --model fisheye|pinhole --out FILE [--holdout N]
[--mount-rpy-deg R P Y]``

Reads chessboard images, finds the boards (:func:`gsoe.calibration.find_board`), calibrates
(:func:`gsoe.calibration.calibrate`), prints the RMS and per-image reprojection errors (and those of the last
``N`` boards, held out of the calibration), and writes a camera file in the format of
``config/camera/*.toml`` (loadable by :func:`pipeline.config.load_camera`), with the mount given by
``--mount-rpy-deg`` (a board calibration does not observe it).  Exit status: 0 written, 1 too few
boards or the calibration failed, 2 bad input (missing or unreadable image, mixed image sizes).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from cli.argtypes import int_at_least, positive_float
from common.config import ConfigError
from gsoe.calibration import MIN_BOARDS, CalibrationError, calibrate, find_board, reprojection_errors
from gsoe.config import CameraConfig

log = logging.getLogger(__name__)


def _board(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"board must be COLSxROWS of inner corners, e.g. 8x6, got {text!r}") from None
    if cols < 2 or rows < 2:
        raise argparse.ArgumentTypeError(f"board needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", type=Path, help="chessboard images (any format OpenCV reads)")
    parser.add_argument("--board", type=_board, required=True, help="inner corners COLSxROWS, e.g. 8x6")
    parser.add_argument("--square", type=positive_float, default=1.0,
                        help="square side (any unit; only scales the board poses), default 1")
    parser.add_argument("--model", choices=("fisheye", "pinhole"), default="fisheye", help="camera model")
    parser.add_argument("--out", type=Path, required=True, help="camera file to write (TOML)")
    parser.add_argument("--holdout", type=int_at_least(0), default=0,
                        help="leave the last N found boards out of the calibration and report their errors")
    parser.add_argument("--focal-guess", type=positive_float, default=None,
                        help="fisheye starting focal length in pixels (default: image width / pi)")
    parser.add_argument("--mount-rpy-deg", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("R", "P", "Y"),
                        help="the camera's mount on top of the nominal belly mounting (roll, pitch, yaw, deg; any "
                             "rotation, e.g. an oblique camera), written to the camera file; default 0 0 0")


def camera_toml(camera: CameraConfig, header: list[str]) -> str:
    """The camera file text (``config/camera/*.toml`` format) with ``header`` lines as comments."""
    def num(v: float) -> str:
        return repr(float(v))

    lines = [f"# {h}" for h in header]
    lines += [
        f'model = "{camera.model}"',
        f"width_px = {camera.width_px}",
        f"height_px = {camera.height_px}",
        f"fx_px = {num(camera.fx_px)}",
        f"fy_px = {num(camera.fy_px)}",
        f"cx_px = {num(camera.cx_px)}",
        f"cy_px = {num(camera.cy_px)}",
        f"dist = [{', '.join(num(d) for d in camera.dist)}]",
        f"hfov_deg = {num(camera.hfov_deg)}",
        f"vfov_deg = {num(camera.vfov_deg)}",
        f"mount_rpy_deg = [{', '.join(num(a) for a in camera.mount_rpy_deg)}]",
    ]
    if camera.rms_px is not None:
        lines.append(f"rms_px = {num(camera.rms_px)}")
    return "\n".join(lines) + "\n"


def _fail(code: int, message: str) -> int:
    print(f"gsoe calibrate: {message}", file=sys.stderr)
    return code


def run(args: argparse.Namespace) -> int:
    board: tuple[int, int] = args.board
    board_txt = f"{board[0]}x{board[1]}"
    # Read every image first, so that all bad paths are reported together.
    images: list[tuple[Path, np.ndarray]] = []
    bad: list[str] = []
    for path in args.images:
        if not path.is_file():
            bad.append(f"{path}: file not found")
            continue
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            bad.append(f"{path}: not an image OpenCV can read")
            continue
        images.append((path, img))
    if bad:
        return _fail(2, "cannot read " + "; ".join(bad))
    sizes = {(img.shape[1], img.shape[0]) for _, img in images}
    if len(sizes) != 1:
        return _fail(2, f"all images must have the same size, got {sorted(sizes)}")
    image_size = sizes.pop()

    found: list[tuple[Path, np.ndarray]] = []
    for path, img in images:
        corners = find_board(img, board)
        if corners is None:
            print(f"  {path.name}: no {board_txt} board found, skipped")
        else:
            found.append((path, corners))
    need = MIN_BOARDS + args.holdout
    if len(found) < need:
        held = f" plus {args.holdout} held out, {need} in all" if args.holdout else ""
        return _fail(1, f"only {len(found)} of {len(images)} images show a {board_txt} board; "
                        f"calibration needs at least {MIN_BOARDS}{held}; refusing to write {args.out}")
    cal_set = found[: len(found) - args.holdout]
    held_set = found[len(found) - args.holdout:]
    try:
        result = calibrate([c for _, c in cal_set], board, args.square, image_size, args.model,
                           focal_guess_px=args.focal_guess, mount_rpy_deg=tuple(args.mount_rpy_deg))
    except (CalibrationError, ConfigError) as e:
        return _fail(1, f"calibration failed: {e}; refusing to write {args.out}")

    cam = result.camera
    print(f"{args.model} calibration from {len(result.used_indices)} of {len(images)} images "
          f"({image_size[0]}x{image_size[1]}, board {board_txt}, square {args.square:g})")
    print(f"RMS reprojection error: {result.rms_px:.3f} px")
    print("per-image RMS (px):")
    for i, err in zip(result.used_indices, result.per_image_rms_px, strict=True):
        print(f"  {cal_set[i][0].name}: {err:.3f}")
    for i in result.rejected_indices:
        print(f"  {cal_set[i][0].name}: left out (ill-conditioned for the solver)")
    if held_set:
        held_err = reprojection_errors(cam, [c for _, c in held_set], board, args.square)
        print("held-out boards, RMS (px) with the calibrated intrinsics:")
        for (path, _), err in zip(held_set, held_err, strict=True):
            print(f"  {path.name}: {err:.3f}" if math.isfinite(err) else
                  f"  {path.name}: not measurable (beyond the calibrated field, or pose not solvable)")
    print(f"fx {cam.fx_px:.2f} fy {cam.fy_px:.2f} cx {cam.cx_px:.2f} cy {cam.cy_px:.2f} px; "
          f"dist [{', '.join(f'{d:.5f}' for d in cam.dist)}]; hfov {cam.hfov_deg:.1f} vfov {cam.vfov_deg:.1f} deg")
    if result.fov_note:
        print(f"note: {result.fov_note}")

    header = [
        f"Camera file written by `gsoe calibrate` ({args.model} model, {len(result.used_indices)} boards "
        f"{board_txt}, square {args.square:g}).",
        f"Images: {', '.join(p.name for p, _ in cal_set)}.",
        f"RMS reprojection error {result.rms_px:.3f} px.  mount_rpy_deg is not observed by a board calibration "
        "(--mount-rpy-deg).",
    ]
    if result.fov_note:
        header.append(f"Note: {result.fov_note}.")
    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(camera_toml(cam, header))
    except OSError as e:
        return _fail(2, f"cannot write {args.out}: {e.strerror or e}")
    print(f"wrote {args.out}")
    log.debug("camera %s", cam)
    return 0
