"""Camera calibration from chessboard views (paper 2.1): corners, intrinsics, distortion, fields of view.

Pure: takes images and corner arrays, returns a :class:`gsoe.config.CameraConfig`; reading image files and
writing the camera file is :mod:`cli.cmd_calibrate`'s business.  The numerical work is OpenCV's
(``cv2.findChessboardCorners`` + ``cv2.cornerSubPix``, falling back to ``cv2.findChessboardCornersSB``;
``cv2.fisheye.calibrate`` for the Kannala-Brandt fisheye model, ``cv2.calibrateCamera`` for the pinhole
radial-tangential model; ``cv2.fisheye.solvePnP`` / ``cv2.solvePnP`` for boards left out of the calibration).

Conventions
    ``board = (cols, rows)`` counts the *inner* corners (OpenCV's ``patternSize``; "8x6" means 8 per row,
    6 rows).  ``square_size`` is the side of one square in any length unit (it only scales the board poses,
    never the intrinsics).  ``image_size = (width_px, height_px)``.  Corner arrays are ``(N, 2)`` float64 pixel
    coordinates (OpenCV convention: the centre of the top-left pixel is (0, 0)), in the order OpenCV returns
    them (row by row).  Reprojection errors are Euclidean: ``rms_px = sqrt(mean(|projected - detected|^2))``.
Fisheye start
    ``cv2.fisheye.calibrate`` is a local optimiser; started from OpenCV's own focal guess it can diverge or stop
    on an ill-conditioned board (``CALIB_CHECK_COND``).  We start it from an equidistant lens whose
    ``FISHEYE_GUESS_FIELD_RAD`` (180 deg) spans the image width, principal point at the image centre, and let it
    refine everything (``CALIB_USE_INTRINSIC_GUESS | CALIB_RECOMPUTE_EXTRINSIC | CALIB_FIX_SKEW``).  When OpenCV
    still reports a board as ill-conditioned, that board is dropped, reported in
    :attr:`CalibrationResult.rejected_indices`, and the calibration repeated, as long as ``MIN_BOARDS`` remain.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from common.config import ConfigError
from gsoe.camera import CameraModel
from gsoe.config import CameraConfig

#: Fewest boards :func:`calibrate` accepts (OpenCV recommends 10 or more well spread views; fewer than this
#: leaves the eight fisheye parameters poorly constrained).
MIN_BOARDS = 5
#: The fisheye focal guess is ``width_px / FISHEYE_GUESS_FIELD_RAD``: an equidistant lens (``r = f * theta``)
#: whose 180 deg field spans the image width (OpenCV's own fallback focal, ``max(w, h) / pi``).
FISHEYE_GUESS_FIELD_RAD = math.pi
#: Fraction of the smallest distance between neighbouring corners used as the ``cornerSubPix`` half-window,
#: so that the search window never reaches the next corner ...
SUBPIX_WINDOW_FRACTION = 0.4
#: ... clipped to this range of half-windows, pixels.
SUBPIX_HALF_WINDOW_MIN_PX = 2
SUBPIX_HALF_WINDOW_MAX_PX = 11
#: A ray unprojected from an image edge must project back within this distance to count (pixels); a larger miss
#: means the calibrated model cannot be inverted there (see :func:`fields_of_view_deg`).
EDGE_ROUND_TRIP_TOL_PX = 0.5
# Optimiser stopping rules (iterations, step size).
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
_CALIB_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-10)
_ILL_CONDITIONED = re.compile(r"Ill-conditioned matrix for input array (\d+)")

Model = Literal["fisheye", "pinhole"]


class CalibrationError(ValueError):
    """Calibration cannot give a trustworthy camera (too few boards, solver failure, unusable result)."""


def _flag(name: str) -> int:
    """A ``cv2.fisheye`` calibration flag: OpenCV 4 keeps them in ``cv2.fisheye``, OpenCV 5 in ``cv2``."""
    return int(getattr(cv2.fisheye, name, getattr(cv2, name)))


def board_object_points(board: tuple[int, int], square_size: float) -> NDArray[np.float64]:
    """Board corners in the board's own frame, shape (cols * rows, 3), z = 0, in the order OpenCV finds them."""
    cols, rows = _check_board(board)
    if not (math.isfinite(square_size) and square_size > 0):
        raise CalibrationError(f"square size must be a positive number, got {square_size!r}")
    obj = np.zeros((cols * rows, 3))
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_size
    return obj


def _check_board(board: tuple[int, int]) -> tuple[int, int]:
    if len(board) != 2 or min(int(board[0]), int(board[1])) < 2:
        raise CalibrationError(f"board must be (cols, rows) of inner corners, each >= 2, got {board!r}")
    return int(board[0]), int(board[1])


def find_board(gray: NDArray[Any], board: tuple[int, int]) -> NDArray[np.float64] | None:
    """Sub-pixel chessboard corners in an 8-bit grayscale image, shape (cols * rows, 2), or None if not found.

    ``cv2.findChessboardCorners`` (adaptive threshold) refined by ``cv2.cornerSubPix`` with a window sized from
    the corner spacing; when it finds nothing, ``cv2.findChessboardCornersSB`` (slower, sub-pixel itself).
    """
    cols, rows = _check_board(board)
    img: NDArray[Any] = np.asarray(gray)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY))
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"find_board needs an 8-bit grayscale image, got shape {img.shape} dtype {img.dtype}")
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(img, (cols, rows), flags=flags)
    if found:
        pts = corners.reshape(-1, 2)
        grid = pts.reshape(rows, cols, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
                      np.linalg.norm(np.diff(grid, axis=1), axis=2).min())
        half = int(np.clip(np.floor(spacing * SUBPIX_WINDOW_FRACTION), SUBPIX_HALF_WINDOW_MIN_PX,
                           SUBPIX_HALF_WINDOW_MAX_PX))
        refined = cv2.cornerSubPix(img, corners.astype(np.float32), (half, half), (-1, -1), _SUBPIX_CRITERIA)
        return refined.reshape(-1, 2).astype(np.float64)
    found, corners = cv2.findChessboardCornersSB(img, (cols, rows), flags=cv2.CALIB_CB_EXHAUSTIVE)
    if found:
        return corners.reshape(-1, 2).astype(np.float64)
    return None


@dataclass(frozen=True)
class CalibrationResult:
    """Outcome of :func:`calibrate`.

    ``camera`` is the calibrated camera file content (``rms_px`` filled in, ``mount_rpy_deg`` as given).
    ``per_image_rms_px[i]`` and the board pose ``rvecs[i]``/``tvecs[i]`` (board frame to camera frame ``c``,
    Rodrigues vector and translation in ``square_size`` units) belong to the input board ``used_indices[i]``;
    ``rejected_indices`` are the input boards OpenCV found ill-conditioned and that were left out.
    ``fov_note`` is set when the fields of view could not be taken from the model everywhere (see
    :func:`fields_of_view_deg`).
    """

    camera: CameraConfig
    rms_px: float
    per_image_rms_px: tuple[float, ...]
    used_indices: tuple[int, ...]
    rejected_indices: tuple[int, ...]
    rvecs: tuple[NDArray[np.float64], ...]
    tvecs: tuple[NDArray[np.float64], ...]
    fov_note: str | None = None


def _as_points(image_points: Sequence[NDArray[np.float64]], n_corners: int) -> list[NDArray[np.float64]]:
    out = []
    for i, p in enumerate(image_points):
        a = np.asarray(p, dtype=np.float64).reshape(-1, 2)
        if a.shape[0] != n_corners:
            raise CalibrationError(f"board {i}: {a.shape[0]} corners given, the board has {n_corners}")
        if not np.all(np.isfinite(a)):
            raise CalibrationError(f"board {i}: corner coordinates must be finite")
        out.append(a)
    return out


def _project(model: str, obj: NDArray[np.float64], rvec: NDArray[np.float64], tvec: NDArray[np.float64],
             K: NDArray[np.float64], D: NDArray[np.float64]) -> NDArray[np.float64]:
    if model == "fisheye":
        img, _ = cv2.fisheye.projectPoints(obj.reshape(1, -1, 3), rvec, tvec, K, D)
    else:
        img, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, D)
    return np.asarray(img, dtype=np.float64).reshape(-1, 2)


def _rms(err: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def _run_fisheye(obj: NDArray[np.float64], pts: list[NDArray[np.float64]], image_size: tuple[int, int],
                 focal_guess_px: float) -> tuple[NDArray[np.float64], NDArray[np.float64], list[int], list[int],
                                                 list[NDArray[np.float64]], list[NDArray[np.float64]]]:
    width, height = image_size
    used = list(range(len(pts)))
    rejected: list[int] = []
    flags = (_flag("CALIB_USE_INTRINSIC_GUESS") | _flag("CALIB_RECOMPUTE_EXTRINSIC") | _flag("CALIB_CHECK_COND")
             | _flag("CALIB_FIX_SKEW"))
    while True:
        K0 = np.array([[focal_guess_px, 0.0, width / 2.0], [0.0, focal_guess_px, height / 2.0], [0.0, 0.0, 1.0]])
        D0 = np.zeros((4, 1))
        try:
            _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(
                [obj.reshape(1, -1, 3)] * len(used), [pts[i].reshape(1, -1, 2) for i in used], (width, height),
                K0, D0, flags=flags, criteria=_CALIB_CRITERIA)
        except cv2.error as e:
            m = _ILL_CONDITIONED.search(str(e))
            if m is None or int(m.group(1)) >= len(used):
                raise CalibrationError(f"OpenCV fisheye calibration failed: {_cv_message(e)}") from None
            rejected.append(used.pop(int(m.group(1))))
            if len(used) < MIN_BOARDS:
                raise CalibrationError(
                    f"fisheye calibration: boards {sorted(rejected)} are ill-conditioned for the solver and only "
                    f"{len(used)} remain (need {MIN_BOARDS}); take more views, or give a better focal guess"
                ) from None
            continue
        return (np.asarray(K, dtype=np.float64), np.asarray(D, dtype=np.float64).reshape(-1), used, rejected,
                [np.asarray(r, dtype=np.float64) for r in rvecs], [np.asarray(t, dtype=np.float64) for t in tvecs])


def _cv_message(e: cv2.error) -> str:
    text = str(e).strip()
    return text.split("error:", 1)[-1].strip() if "error:" in text else text


def fields_of_view_deg(model: Model, image_size: tuple[int, int], K: NDArray[np.float64],
                       D: NDArray[np.float64]) -> tuple[float, float, str | None]:
    """Nominal fields of view of a calibrated camera: ``(hfov_deg, vfov_deg, note)``.

    ``hfov_deg`` is the sum of the off-axis angles of the rays through the left and right image edges on the
    principal row (``vfov_deg``: top and bottom edges on the principal column); for fields below 180 deg that is
    the angle between the two rays.  The rays come from :meth:`gsoe.camera.CameraModel.unproject` and must
    project back onto their edge point (``EDGE_ROUND_TRIP_TOL_PX``).  An edge beyond the reach of the boards can
    lie where the fitted fisheye polynomial has turned over and cannot be inverted; that edge's angle is then the
    equidistant one, ``|u - c| / f`` (the model's leading term), and ``note`` says so (otherwise ``None``).
    """
    width, height = image_size
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    dist = tuple(float(d) for d in np.asarray(D).reshape(-1))
    # Provisional camera: the fields of view are what we are computing, any valid number serves meanwhile.
    provisional = CameraConfig(model=model, width_px=width, height_px=height, fx_px=fx, fy_px=fy, cx_px=cx,
                               cy_px=cy, dist=dist, hfov_deg=90.0, vfov_deg=90.0)
    cam = CameraModel.from_config(provisional)
    edges = np.array([[0.0, cy], [float(width), cy], [cx, 0.0], [cx, float(height)]])
    rays = cam.unproject(edges)
    with np.errstate(invalid="ignore"):
        back = _project(model, rays, np.zeros(3), np.zeros(3), cam.K, cam.D)
    miss = np.linalg.norm(back - edges, axis=1)
    invertible = np.all(np.isfinite(rays), axis=1) & (miss <= EDGE_ROUND_TRIP_TOL_PX) & (rays[:, 2] > 0)
    off_axis = np.arccos(np.clip(rays[:, 2], -1.0, 1.0))
    equidistant = np.array([cx / fx, (width - cx) / fx, cy / fy, (height - cy) / fy])
    theta = np.where(invertible, off_axis, equidistant)
    note = None
    if not np.all(invertible):
        names = [n for n, ok in zip(("left", "right", "top", "bottom"), invertible, strict=True) if not ok]
        note = (f"the calibrated {model} model cannot be inverted at the {'/'.join(names)} image edge (beyond the "
                f"boards, where the fitted polynomial turns over): the equidistant angle |u - c| / f is used there")
    return math.degrees(theta[0] + theta[1]), math.degrees(theta[2] + theta[3]), note


def calibrate(image_points: Sequence[NDArray[np.float64]], board: tuple[int, int], square_size: float,
              image_size: tuple[int, int], model: Model = "fisheye", *, focal_guess_px: float | None = None,
              mount_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> CalibrationResult:
    """Calibrate a camera from the corners of ``len(image_points)`` chessboard views.

    Parameters
    ----------
    image_points : sequence of (cols * rows, 2) arrays
        Detected corners per view (from :func:`find_board`), pixels.
    board : (cols, rows)
        Inner corners of the board.
    square_size : float
        Square side (any unit; sets the unit of the board poses only).
    image_size : (width_px, height_px)
    model : "fisheye" | "pinhole"
        ``cv2.fisheye`` Kannala-Brandt (4 coefficients) or OpenCV radial-tangential (5 coefficients).
    focal_guess_px : float, optional
        Fisheye starting focal length; default ``width_px / FISHEYE_GUESS_FIELD_RAD``.  Unused for pinhole
        (``cv2.calibrateCamera`` initialises itself from the board homographies).
    mount_rpy_deg : (roll, pitch, yaw) degrees
        Copied into the camera file (calibration from boards does not observe the mounting).

    Raises
    ------
    CalibrationError
        Fewer than ``MIN_BOARDS`` views, the solver failed, or the result is not a valid camera.
    """
    cols, rows = _check_board(board)
    obj = board_object_points((cols, rows), square_size)
    pts = _as_points(image_points, cols * rows)
    if len(pts) < MIN_BOARDS:
        raise CalibrationError(f"{len(pts)} boards given, calibration needs at least {MIN_BOARDS}")
    width, height = int(image_size[0]), int(image_size[1])
    if width < 16 or height < 16:
        raise CalibrationError(f"image size must be (width, height) in pixels, got {image_size!r}")
    if model == "fisheye":
        f0 = width / FISHEYE_GUESS_FIELD_RAD if focal_guess_px is None else float(focal_guess_px)
        if not (math.isfinite(f0) and f0 > 0):
            raise CalibrationError(f"focal guess must be a positive number of pixels, got {focal_guess_px!r}")
        K, D, used, rejected, rvecs, tvecs = _run_fisheye(obj, pts, (width, height), f0)
    elif model == "pinhole":
        try:
            _, K_cv, D_cv, rv, tv = cv2.calibrateCamera([obj.astype(np.float32)] * len(pts),
                                                        [p.astype(np.float32) for p in pts], (width, height),
                                                        None, None, criteria=_CALIB_CRITERIA)
        except cv2.error as e:
            raise CalibrationError(f"OpenCV pinhole calibration failed: {_cv_message(e)}") from None
        K = np.asarray(K_cv, dtype=np.float64)
        D = np.asarray(D_cv, dtype=np.float64).reshape(-1)[:5]
        used, rejected = list(range(len(pts))), []
        rvecs = [np.asarray(r, dtype=np.float64) for r in rv]
        tvecs = [np.asarray(t, dtype=np.float64) for t in tv]
    else:
        raise CalibrationError(f"model must be 'fisheye' or 'pinhole', got {model!r}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(D))):
        raise CalibrationError("calibration diverged (non-finite intrinsics)")

    errors = [_project(model, obj, rvecs[j], tvecs[j], K, D) - pts[i] for j, i in enumerate(used)]
    per_image = tuple(_rms(e) for e in errors)
    rms = _rms(np.concatenate(errors))
    hfov, vfov, fov_note = fields_of_view_deg(model, (width, height), K, D)
    try:
        camera = CameraConfig(model=model, width_px=width, height_px=height, fx_px=float(K[0, 0]),
                              fy_px=float(K[1, 1]), cx_px=float(K[0, 2]), cy_px=float(K[1, 2]),
                              dist=tuple(float(d) for d in D), hfov_deg=hfov, vfov_deg=vfov,
                              mount_rpy_deg=tuple(float(a) for a in mount_rpy_deg), rms_px=rms)  # type: ignore[arg-type]
    except ConfigError as e:
        raise CalibrationError(f"calibration gave an invalid camera: {e}") from None
    return CalibrationResult(camera=camera, rms_px=rms, per_image_rms_px=per_image, used_indices=tuple(used),
                             rejected_indices=tuple(rejected), fov_note=fov_note,
                             rvecs=tuple(np.asarray(r, dtype=np.float64).reshape(3) for r in rvecs),
                             tvecs=tuple(np.asarray(t, dtype=np.float64).reshape(3) for t in tvecs))


def reprojection_errors(camera: CameraConfig, image_points: Sequence[NDArray[np.float64]],
                        board: tuple[int, int], square_size: float) -> list[float]:
    """RMS reprojection error (pixels) of each board under a fixed, already calibrated camera.

    Each board's pose is solved with the camera held fixed (``cv2.fisheye.solvePnP`` or ``cv2.solvePnP``,
    iterative), then its corners are projected back; use it on boards left out of the calibration to see how
    the intrinsics generalise.  A board gets ``nan`` when its pose cannot be solved, or when some of its corners
    lie where the camera model cannot be inverted (they do not project back within ``EDGE_ROUND_TRIP_TOL_PX``
    of themselves: the board reaches beyond the field the calibration covered).
    """
    cols, rows = _check_board(board)
    obj = board_object_points((cols, rows), square_size)
    pts = _as_points(image_points, cols * rows)
    cam = CameraModel.from_config(camera)
    out: list[float] = []
    for p in pts:
        with np.errstate(invalid="ignore"):
            back = _project(camera.model, cam.unproject(p), np.zeros(3), np.zeros(3), cam.K, cam.D)
        if not np.all(np.linalg.norm(back - p, axis=1) <= EDGE_ROUND_TRIP_TOL_PX):
            out.append(float("nan"))
            continue
        try:
            if camera.model == "fisheye":
                ok, rvec, tvec = cv2.fisheye.solvePnP(obj.reshape(-1, 1, 3), p.reshape(-1, 1, 2), cam.K, cam.D)
            else:
                ok, rvec, tvec = cv2.solvePnP(obj, p, cam.K, cam.D)
        except cv2.error:
            ok = False
        if not ok:
            out.append(float("nan"))
            continue
        out.append(_rms(_project(camera.model, obj, np.asarray(rvec, np.float64), np.asarray(tvec, np.float64),
                                 cam.K, cam.D) - p))
    return out
