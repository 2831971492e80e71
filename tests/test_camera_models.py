"""Any calibrated camera: pinhole or fisheye, any mount (an oblique camera), the view-centred ROI of the optical
estimator on rendered frames, and ``gsoe calibrate --model pinhole`` from rendered chessboard images."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from cli.main import main
from common.samples import AttitudeSample
from gsoe.camera import CameraModel
from gsoe.config import CameraConfig, CycleConfig, GsoeConfig, StabConfig
from gsoe.cycle import GsoeEstimator
from gsoe.rotation import R_bc_from_mount, R_nb_from_euler
from nav.imageseq import mount_rpy_deg_from_R_bc
from pipeline.config import load_camera
from sim.render import CameraRenderer
from sim.textures import GroundWorld
from tests.turning_flight import OBLIQUE, turning_flight


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.0), (0.0, -9.0, -92.0), (170.0, 60.0, -150.0), (-30.0, 27.0, 90.0)])
def test_mount_is_any_rotation_and_round_trips(rpy):
    R_bc = R_bc_from_mount(*np.radians(rpy))
    back = mount_rpy_deg_from_R_bc(R_bc)
    assert np.allclose(R_bc_from_mount(*np.radians(back)), R_bc, atol=1e-12)
    cam = CameraModel.from_config(CameraConfig(**{**OBLIQUE.__dict__, "mount_rpy_deg": rpy}))
    assert np.allclose(cam.R_bc, R_bc)


def _fly(cfg: GsoeConfig, camera: CameraConfig, rng: np.random.Generator, n_frames: int, height_m: float,
         speed_m_s: float, roll_deg: float) -> list[tuple[bool, float]]:
    """Frames at irregular intervals (0.5-1.2 s) from a turning aircraft over the town tile; returns per frame pair
    (valid, error of the measured nadir displacement in m)."""
    cam = CameraModel.from_config(camera)
    renderer = CameraRenderer(cam, GroundWorld.from_name("town_river"))
    est = GsoeEstimator(cfg, cam, ahrs_latency_s=0.0)
    steps, track = [], []
    for p in turning_flight(rng, n_frames, height_m, speed_m_s, roll_deg):
        t_us = int(round(p.t_s * 1e6))
        img = renderer.render(p.pos_ned_m, R_nb_from_euler(p.roll_rad, p.pitch_rad, p.yaw_rad), noise_std=1.0, rng=rng)
        est.push_attitude(AttitudeSample(t_us, p.roll_rad, p.pitch_rad, p.yaw_rad))
        steps.append(est.process_frame(t_us, img, height_m))
        track.append(p.pos_ned_m[:2])
    out = []
    for k in range(1, n_frames):
        prev = {s.cycle_id: s for s in steps[k - 1]}
        cur = next((s for s in steps[k] if not s.new_cycle and s.cycle_id in prev), None)
        if cur is None:
            out.append((False, math.nan))
            continue
        p = prev[cur.cycle_id]
        fwd, right = (cur.dy_px - p.dy_px) * cur.gsd_m_px, (cur.dx_px - p.dx_px) * cur.gsd_m_px
        c, s = math.cos(cur.base_yaw_rad), math.sin(cur.base_yaw_rad)
        d = np.array([fwd * c - right * s, fwd * s + right * c])
        out.append((bool(cur.valid and p.valid), float(np.linalg.norm(d - (track[k] - track[k - 1])))))
    return out


def test_view_centred_roi_measures_the_nadir_migration_of_an_oblique_narrow_camera():
    """The camera never sees the nadir (25 deg bank, 9 deg mount: 20-30 deg off vertical, 11 x 16 deg field);
    frames 0.5-1.2 s apart with 30-60 px of motion: the base image around the image centre's ground point, templates
    cut where the base's centre is predicted, per-second step prediction.  Every accepted pair's displacement is
    the aircraft's to a few cm (0.18 m/px)."""
    cfg = GsoeConfig(camera=OBLIQUE,
                     stab=StabConfig(base_cross_px=161, base_along_px=161, template_px=51, roi_centre="view"),
                     cycle=CycleConfig(max_cycle_s=60.0, data_filter=False, step_gate_px=20.0,
                                       step_prediction="per_second"))
    pairs = _fly(cfg, OBLIQUE, np.random.default_rng(1), 25, 300.0, 12.0, 25.0)
    valid = [e for ok, e in pairs if ok]
    assert len(valid) >= 0.85 * len(pairs)
    assert max(valid) < 0.05, valid
    # the paper's nadir ROI cannot work with this camera: its base image is never inside the frame
    nadir = GsoeConfig(camera=OBLIQUE, stab=StabConfig(base_cross_px=161, base_along_px=161, template_px=51))
    assert not any(ok for ok, _ in _fly(nadir, OBLIQUE, np.random.default_rng(1), 4, 300.0, 12.0, 25.0))


def test_view_centred_roi_with_an_oblique_fisheye():
    """The paper's fisheye mounted 35 deg to the left: the same view-centred cycle, 30 Hz-like steady motion."""
    from pipeline.config import load_gsoe_config

    fish = load_gsoe_config()[0].camera
    cam = CameraConfig(**{**fish.__dict__, "mount_rpy_deg": (-35.0, 0.0, 0.0)})
    cfg = GsoeConfig(camera=cam, stab=StabConfig(roi_centre="view"),
                     cycle=CycleConfig(step_prediction="per_second", step_gate_px=3.0))
    pairs = _fly(cfg, cam, np.random.default_rng(2), 12, 100.0, 12.0, 0.0)
    valid = [e for ok, e in pairs if ok]
    assert len(valid) >= 0.8 * len(pairs)
    # fisheye off-axis: 0.29 m/px at the view point; a tenth of a pixel
    assert np.median(valid) < 0.03 and max(valid) < 0.1, valid


def _subpixel_rays(cam: CameraModel) -> list[np.ndarray]:
    """Unit rays of a 2x2 grid of sub-pixel samples of every pixel (one array per sub-pixel offset)."""
    w, h = cam.size_px
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    return [cam.unproject(np.column_stack([uu.ravel() + du, vv.ravel() + dv]))
            for du, dv in ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25))]


def _board_image(cam: CameraModel, sub_rays: list[np.ndarray], R_cb: np.ndarray, t_c: np.ndarray,
                 square: float) -> np.ndarray:
    """A chessboard (8x6 inner corners, a white margin of one square) seen by ``cam``, 2x2 supersampled; the
    board's frame has its first inner corner at the origin, x along a row, z out of the board."""
    w, h = cam.size_px
    acc = np.zeros((h, w))
    for rays in sub_rays:
        r_b = rays @ R_cb            # rows: R_cb^T ray
        o_b = -R_cb.T @ t_c
        s = -o_b[2] / r_b[:, 2]
        x = o_b[0] + s * r_b[:, 0]
        y = o_b[1] + s * r_b[:, 1]
        i, j = np.floor(x / square) + 1, np.floor(y / square) + 1       # squares 0..8 x 0..6
        on_board = (i >= 0) & (i <= 8) & (j >= 0) & (j <= 6)
        margin = (i >= -1) & (i <= 9) & (j >= -1) & (j <= 7)
        val = np.where(on_board, np.where((i + j) % 2 == 0, 30.0, 225.0), np.where(margin, 225.0, 120.0))
        acc += np.where(s > 0, val, 120.0).reshape(h, w)
    return (acc / len(sub_rays)).round().astype(np.uint8)


def test_calibrate_cli_pinhole_from_rendered_boards(tmp_path, capsys):
    truth = CameraConfig(model="pinhole", width_px=640, height_px=480, fx_px=520.0, fy_px=522.0, cx_px=322.0,
                         cy_px=236.0, dist=(-0.18, 0.05, 0.0008, -0.0005, 0.0), hfov_deg=63.0, vfov_deg=49.0)
    cam = CameraModel.from_config(truth)
    rng = np.random.default_rng(5)
    sub_rays = _subpixel_rays(cam)
    paths = []
    while len(paths) < 10:
        R, _ = cv2.Rodrigues(rng.uniform(-0.5, 0.5, 3))
        centre = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-1.0, 1.0), rng.uniform(9.0, 13.0)])
        t = centre - R @ np.array([3.5, 2.5, 0.0])        # the board's middle at ``centre``
        corners = (np.mgrid[0:8, 0:6].T.reshape(-1, 2)).astype(float)
        _, valid = cam.project(np.column_stack([corners, np.zeros(len(corners))]) @ R.T + t)
        if not valid.all():
            continue
        p = tmp_path / f"board{len(paths)}.png"
        cv2.imwrite(str(p), _board_image(cam, sub_rays, R, t, 1.0))
        paths.append(p)
    out = tmp_path / "cam.toml"
    rc = main(["calibrate", *map(str, paths), "--board", "8x6", "--model", "pinhole", "--out", str(out),
               "--mount-rpy-deg", "0", "-9", "-92"])
    assert rc == 0, capsys.readouterr().err
    got = load_camera(out)
    assert got.model == "pinhole" and got.mount_rpy_deg == (0.0, -9.0, -92.0)
    assert got.fx_px == pytest.approx(truth.fx_px, rel=0.01) and got.fy_px == pytest.approx(truth.fy_px, rel=0.01)
    assert got.cx_px == pytest.approx(truth.cx_px, abs=3.0) and got.cy_px == pytest.approx(truth.cy_px, abs=3.0)
    assert got.dist[0] == pytest.approx(truth.dist[0], abs=0.03)
    assert got.rms_px is not None and got.rms_px < 0.3
    # the calibrated model puts rays where the true one does across the image
    fitted = CameraModel.from_config(got)
    px = np.column_stack([rng.uniform(10, 630, 200), rng.uniform(10, 470, 200)])
    back, ok = fitted.project(cam.unproject(px))
    assert ok.all() and np.max(np.linalg.norm(back - px, axis=1)) < 1.0
