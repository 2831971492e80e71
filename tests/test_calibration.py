"""Camera calibration: the real fisheye set (tests/data/fisheye_calib) and synthetic boards of a known camera."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from cli.main import main
from gsoe.calibration import (
    MIN_BOARDS,
    CalibrationError,
    board_object_points,
    calibrate,
    fields_of_view_deg,
    find_board,
    reprojection_errors,
)
from gsoe.camera import CameraModel
from gsoe.config import CameraConfig
from pipeline.config import load_camera

CALIB_DIR = Path(__file__).resolve().parent / "data" / "fisheye_calib"
IMAGES = sorted(CALIB_DIR.glob("*.png"))
BOARD = (8, 6)
SIZE = (1920, 1208)
# Boards left out of the calibration: two that reach well off-centre (up to 700 and 640 px from the centre), where
# a wrong model shows; the boards kept still cover the field out to 860 px.
HELD_OUT = (1, 6)


def _gray(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, path
    return np.asarray(img)


@pytest.fixture(scope="module")
def real_corners() -> list[np.ndarray]:
    assert len(IMAGES) == 10
    corners = [find_board(_gray(p), BOARD) for p in IMAGES]
    assert all(c is not None for c in corners), "every image of the set shows the whole board"
    return corners  # type: ignore[return-value]


def _split(corners: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    kept = [c for i, c in enumerate(corners) if i not in HELD_OUT]
    return kept, [corners[i] for i in HELD_OUT]


@pytest.fixture(scope="module")
def real_result(real_corners):
    return calibrate(_split(real_corners)[0], BOARD, 1.0, SIZE, "fisheye")


def test_corners_agree_with_the_sector_based_detector(real_corners):
    # independent detector: OpenCV's sector-based findChessboardCornersSB (sub-pixel on its own)
    checked = 0
    for path, ours in zip(IMAGES[:4], real_corners[:4], strict=True):
        ok, sb = cv2.findChessboardCornersSB(_gray(path), BOARD, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        if not ok:
            continue
        sb = sb.reshape(-1, 2)
        if np.linalg.norm(sb[0] - ours[0]) > np.linalg.norm(sb[-1] - ours[0]):
            sb = sb[::-1]  # the two detectors may start the corner order at opposite ends
        assert np.median(np.linalg.norm(sb - ours, axis=1)) < 0.5
        checked += 1
    assert checked >= 2


def test_real_fisheye_set_calibrates_below_1_5_px(real_result, real_corners):
    r = real_result
    assert r.rms_px < 1.5
    assert len(r.per_image_rms_px) == len(IMAGES) - len(HELD_OUT) - len(r.rejected_indices)
    assert max(r.per_image_rms_px) < 2.5
    cam = r.camera
    # the set's documented behaviour: fx about 690 px, principal point near the image centre
    assert 640.0 < cam.fx_px < 740.0 and abs(cam.fy_px / cam.fx_px - 1.0) < 0.02
    assert abs(cam.cx_px - SIZE[0] / 2) < 0.05 * SIZE[0] and abs(cam.cy_px - SIZE[1] / 2) < 0.05 * SIZE[1]
    # a lens of about 160 deg horizontal field
    assert 140.0 < cam.hfov_deg < 185.0 and 80.0 < cam.vfov_deg < cam.hfov_deg
    # the returned per-image errors are what the camera and the returned poses give
    obj = board_object_points(BOARD, 1.0)
    model = CameraModel.from_config(cam)
    j = 0
    proj, _ = cv2.fisheye.projectPoints(obj.reshape(1, -1, 3), r.rvecs[j], r.tvecs[j], model.K, model.D)
    err = proj.reshape(-1, 2) - _split(real_corners)[0][r.used_indices[j]]
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) == pytest.approx(r.per_image_rms_px[j], rel=1e-9)


def test_boards_left_out_reproject_within_a_few_pixels(real_result, real_corners):
    kept, held_out = _split(real_corners)
    held = reprojection_errors(real_result.camera, held_out, BOARD, 1.0)
    assert len(held) == len(HELD_OUT)
    assert all(np.isfinite(held)) and max(held) < 3.0
    # the measure discriminates: the same boards under a pinhole model fitted to the same views, or under the
    # calibrated fisheye without its distortion, reproject several times worse
    pinhole = calibrate(kept, BOARD, 1.0, SIZE, "pinhole").camera
    assert min(reprojection_errors(pinhole, held_out, BOARD, 1.0)) > 3 * max(held)
    no_dist = dataclasses.replace(real_result.camera, dist=(0.0, 0.0, 0.0, 0.0))
    assert min(reprojection_errors(no_dist, held_out, BOARD, 1.0)) > 3 * max(held)
    # a board beyond the field the calibration covered is reported as not measurable, not as a number
    inner = calibrate([c for i, c in enumerate(real_corners) if i not in (2, 6)], BOARD, 1.0, SIZE).camera
    assert np.isnan(reprojection_errors(inner, [real_corners[2]], BOARD, 1.0)[0])


def _synthetic_views(cam: CameraModel, rng: np.random.Generator, n: int, noise_px: float) -> list[np.ndarray]:
    """Corners of a 8x6 board seen by ``cam`` from ``n`` random poses that keep it whole in the image."""
    obj = board_object_points(BOARD, 1.0)
    obj_c = obj - obj.mean(axis=0)
    views: list[np.ndarray] = []
    while len(views) < n:
        rvec = rng.uniform(-0.6, 0.6, 3)
        R, _ = cv2.Rodrigues(rvec)
        centre = np.array([rng.uniform(-5, 5), rng.uniform(-4, 4), rng.uniform(4.5, 8.0)])
        pts_c = obj_c @ R.T + centre
        px, valid = cam.project(pts_c)
        if not valid.all():
            continue
        views.append(px + rng.normal(0.0, noise_px, px.shape))
    return views


def test_synthetic_fisheye_recovers_the_true_camera(camera):
    # truth: the paper's camera file (fields of view 110 x 87.5 deg by construction)
    truth = camera.config
    rng = np.random.default_rng(7)
    noise_px = 0.2
    views = _synthetic_views(camera, rng, 15, noise_px)
    r = calibrate(views[:12], BOARD, 1.0, (truth.width_px, truth.height_px), "fisheye")
    cam = r.camera
    assert cam.fx_px == pytest.approx(truth.fx_px, rel=0.01)
    assert cam.fy_px == pytest.approx(truth.fy_px, rel=0.01)
    assert cam.cx_px == pytest.approx(truth.cx_px, abs=2.0) and cam.cy_px == pytest.approx(truth.cy_px, abs=2.0)
    assert cam.hfov_deg == pytest.approx(truth.hfov_deg, abs=0.5)
    assert cam.vfov_deg == pytest.approx(truth.vfov_deg, abs=0.5)
    assert r.fov_note is None
    # Euclidean RMS of isotropic noise sigma is sqrt(2) sigma (less the few fitted parameters' share)
    assert 0.8 * np.sqrt(2) * noise_px < r.rms_px < 1.1 * np.sqrt(2) * noise_px
    held = reprojection_errors(cam, views[12:], BOARD, 1.0)
    assert max(held) < 2.0 * np.sqrt(2) * noise_px
    # the fitted camera projects rays where the true one does, across the field
    fitted = CameraModel.from_config(cam)
    px = np.column_stack([rng.uniform(20, 780, 200), rng.uniform(20, 580, 200)])
    back, valid = fitted.project(camera.unproject(px))
    assert valid.all() and np.max(np.linalg.norm(back - px, axis=1)) < 1.5


def test_synthetic_pinhole_recovers_the_true_camera():
    truth = CameraConfig(model="pinhole", width_px=800, height_px=600, fx_px=500.0, fy_px=502.0, cx_px=405.0,
                         cy_px=296.0, dist=(-0.12, 0.03, 0.0005, -0.0003, 0.0), hfov_deg=90.0, vfov_deg=70.0)
    cam_true = CameraModel.from_config(truth)
    rng = np.random.default_rng(11)
    views = _synthetic_views(cam_true, rng, 12, 0.1)
    r = calibrate(views, BOARD, 1.0, (800, 600), "pinhole")
    assert r.camera.fx_px == pytest.approx(truth.fx_px, rel=0.01)
    assert r.camera.cx_px == pytest.approx(truth.cx_px, abs=3.0)
    assert r.camera.dist[0] == pytest.approx(truth.dist[0], abs=0.02)
    assert r.rms_px < 0.3
    # fields of view from the truth's own rays at the image edges
    edges = np.array([[0.0, truth.cy_px], [800.0, truth.cy_px], [truth.cx_px, 0.0], [truth.cx_px, 600.0]])
    rays = cam_true.unproject(edges)
    hfov_true = np.degrees(np.arccos(rays[0] @ rays[1]))
    vfov_true = np.degrees(np.arccos(rays[2] @ rays[3]))
    assert r.camera.hfov_deg == pytest.approx(hfov_true, abs=0.5)
    assert r.camera.vfov_deg == pytest.approx(vfov_true, abs=0.5)
    h, v, note = fields_of_view_deg("pinhole", (800, 600), cam_true.K, cam_true.D)
    assert (h, v, note) == (pytest.approx(hfov_true, abs=1e-3), pytest.approx(vfov_true, abs=1e-3), None)


def test_too_few_boards_is_an_error(real_corners):
    with pytest.raises(CalibrationError, match=f"at least {MIN_BOARDS}"):
        calibrate(real_corners[: MIN_BOARDS - 1], BOARD, 1.0, SIZE)
    with pytest.raises(CalibrationError, match="corners"):
        calibrate([c[:-1] for c in real_corners], BOARD, 1.0, SIZE)
    # a blank image has no board
    assert find_board(np.full((480, 640), 128, np.uint8), BOARD) is None


def test_cli_writes_a_loadable_camera_file(tmp_path, real_corners, capsys):
    out = tmp_path / "cam" / "fisheye.toml"
    rc = main(["calibrate", *map(str, IMAGES), "--board", "8x6", "--square", "1", "--model", "fisheye",
               "--out", str(out), "--holdout", "2"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "RMS reprojection error" in text and "held-out" in text and IMAGES[-1].name in text
    cam = load_camera(out)
    # the CLI holds out the last two images: same calibration as the library call on the first eight
    lib = calibrate(real_corners[:-2], BOARD, 1.0, SIZE, "fisheye")
    assert cam.fx_px == pytest.approx(lib.camera.fx_px, rel=1e-9)
    assert cam.dist == pytest.approx(lib.camera.dist, rel=1e-9)
    assert cam.rms_px == pytest.approx(lib.rms_px, rel=1e-9) and cam.rms_px < 1.5
    model = CameraModel.from_config(cam)
    rng = np.random.default_rng(3)
    # inside the calibrated part of the field (the boards reach about 860 px from the centre)
    ang = rng.uniform(0, 2 * np.pi, 300)
    rad = rng.uniform(0, 550, 300)
    px = np.column_stack([cam.cx_px + rad * np.cos(ang), cam.cy_px + rad * np.sin(ang)])
    back, valid = model.project(model.unproject(px))
    assert valid.all()
    np.testing.assert_allclose(back, px, atol=1e-3)


def test_cli_refuses_too_few_boards_and_bad_files(tmp_path, capsys):
    out = tmp_path / "cam.toml"
    rc = main(["calibrate", *map(str, IMAGES[: MIN_BOARDS - 1]), "--board", "8x6", "--out", str(out)])
    assert rc == 1 and not out.exists()
    assert "refusing" in capsys.readouterr().err
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    rc = main(["calibrate", str(IMAGES[0]), str(tmp_path / "missing.png"), str(junk), "--board", "8x6",
               "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists()
    assert "missing.png: file not found" in err and "junk.png: not an image" in err
    # all found, but 8 - 4 held out leaves fewer than MIN_BOARDS
    rc = main(["calibrate", *map(str, IMAGES[:8]), "--board", "8x6", "--out", str(out), "--holdout", "4"])
    assert rc == 1 and not out.exists()
