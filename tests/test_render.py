"""Camera renderer and ground textures against independent truth (camera.project, analytic means, the tile)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from gsoe.rotation import R_nb_from_euler
from sim.render import CameraRenderer
from sim.render_kernels import _mirror_fold
from sim.textures import TEXTURE_DIR, TEXTURE_NAMES, GroundWorld, intensity_from_bgr, mirror_wrap, read_bgr

MARKER_BG_DN = 230.0  # bright ground with a dark marker: the sky (200 DN) is never mistaken for the marker
MARKER_DN = 20.0
MARKER_SIGMA_M = 0.15
MARKER_M_PER_PX = 0.04
MARKER_TILE_PX = 2048
MARKER_OFFSET_TEXELS = (200, 300)  # (north, east) of the tile centre
MARKER_NE_M = (8.0, 12.0)  # the same in metres: 200 and 300 texels of 4 cm
NEAR_BLACK_DN = 8.0  # the town tile's valid data never goes this dark over an area (its darkest 0.01 % is 17 DN)


def _euler_deg(roll: float, pitch: float, yaw: float) -> np.ndarray:
    return R_nb_from_euler(*np.deg2rad([roll, pitch, yaw]))


@pytest.fixture(scope="module")
def marker_world() -> GroundWorld:
    """A bright tile with one dark Gaussian marker 200 texels north and 300 east of the tile centre."""
    c = (MARKER_TILE_PX - 1) / 2.0
    col, row = c + MARKER_OFFSET_TEXELS[1], c - MARKER_OFFSET_TEXELS[0]
    yy, xx = np.mgrid[0:MARKER_TILE_PX, 0:MARKER_TILE_PX]
    r2 = ((xx - col) ** 2 + (yy - row) ** 2) * MARKER_M_PER_PX**2
    img = MARKER_BG_DN + (MARKER_DN - MARKER_BG_DN) * np.exp(-0.5 * r2 / MARKER_SIGMA_M**2)
    world = GroundWorld.from_array(img.astype(np.float32), MARKER_M_PER_PX)
    # the map convention (origin at the tile centre, columns east, rows south) by hand
    np.testing.assert_allclose(world.texel_to_ground(col, row), MARKER_NE_M, atol=1e-12)
    return world


@pytest.fixture(scope="module")
def marker_renderer(camera, marker_world) -> CameraRenderer:
    return CameraRenderer(camera, marker_world)


@pytest.fixture(scope="module")
def town_renderer(camera) -> CameraRenderer:
    return CameraRenderer(camera, GroundWorld.from_name("town_river"))


def _blob_centroid(img: np.ndarray, half: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Weighted centroid (x, y) and covariance of the dark marker blob around the darkest pixel."""
    y, x = np.unravel_index(np.argmin(img), img.shape)
    win = MARKER_BG_DN - img[y - half : y + half + 1, x - half : x + half + 1]
    wts = np.where(win > 0.05 * win.max(), win, 0.0)
    yy, xx = np.mgrid[-half : half + 1, -half : half + 1]
    m = wts.sum()
    cx, cy = (wts * xx).sum() / m, (wts * yy).sum() / m
    cov = np.array([[(wts * (xx - cx) ** 2).sum(), (wts * (xx - cx) * (yy - cy)).sum()],
                    [(wts * (xx - cx) * (yy - cy)).sum(), (wts * (yy - cy) ** 2).sum()]]) / m
    return np.array([x + cx, y + cy]), cov


@pytest.mark.parametrize(
    ("rpy_deg", "target_px"),
    [
        ((0.0, 0.0, 0.0), (400.0, 300.0)),
        ((0.0, 0.0, 0.0), (640.0, 120.0)),
        ((45.0, 0.0, 10.0), (420.0, 330.0)),
        ((-45.0, 0.0, 250.0), (300.0, 200.0)),
        ((0.0, 20.0, -60.0), (520.0, 420.0)),
        ((0.0, -20.0, 120.0), (150.0, 500.0)),
        ((30.0, -15.0, 200.0), (700.0, 80.0)),
    ],
)
def test_marker_lands_where_camera_projects_it(camera, marker_renderer, rpy_deg, target_px):
    height_m = 20.0
    R_nb = _euler_deg(*rpy_deg)
    # place the aircraft so that the marker appears near target_px
    marker_ned = np.array([*MARKER_NE_M, 0.0])
    ray_n = R_nb @ camera.R_bc @ camera.unproject(np.array([target_px]))[0]
    pos = marker_ned - ray_n * (height_m / ray_n[2])
    assert pos[2] == pytest.approx(-height_m)
    img = marker_renderer.render_intensity(pos, R_nb)
    got, _ = _blob_centroid(img)
    # independent truth: the forward projection of the ground point through the calibrated model
    expect, valid = camera.project((camera.R_bc.T @ R_nb.T @ (marker_ned - pos))[None])
    assert valid[0]
    assert np.linalg.norm(got - expect[0]) < 0.1, (got, expect[0])


def test_motion_blur_spreads_marker_by_the_travel(camera, marker_renderer):
    """Blur of a nadir marker flying north: the along-track variance grows by that of the sub-sample offsets."""
    height_m, speed_m_s, exposure_s = 20.0, 20.0, 0.02
    pos = np.array([*MARKER_NE_M, -height_m])
    sharp = marker_renderer.render_intensity(pos, np.eye(3))
    blurred = marker_renderer.render_intensity(pos, np.eye(3), exposure_s=exposure_s,
                                               vel_ned_m_s=[speed_m_s, 0.0, 0.0])
    c0, cov0 = _blob_centroid(sharp, half=14)
    c1, cov1 = _blob_centroid(blurred, half=14)
    n = marker_renderer.blur_subsamples
    travel_px = speed_m_s * exposure_s * camera.focal_px / height_m
    added_var_px2 = travel_px**2 * (n**2 - 1) / (12 * n**2)  # variance of n equally spaced offsets
    assert cov1[1, 1] - cov0[1, 1] == pytest.approx(added_var_px2, rel=0.1)  # along track: image rows (north up)
    assert cov1[0, 0] == pytest.approx(cov0[0, 0], rel=0.05)  # cross track unchanged
    np.testing.assert_allclose(c1, c0, atol=0.1)  # the pose is the mid-exposure pose
    # zero exposure or no motion: no blur
    np.testing.assert_array_equal(marker_renderer.render_intensity(pos, np.eye(3), exposure_s=0.0,
                                                                   vel_ned_m_s=[20.0, 0, 0]), sharp)


def test_roi_render_equals_full_render(town_renderer):
    pos = np.array([35.0, -12.0, -120.0])
    R_nb = _euler_deg(30.0, -10.0, 75.0)
    kw = {"exposure_s": 0.004, "vel_ned_m_s": [15.0, 8.0, 0.5], "rates_b_rad_s": [0.3, -0.1, 0.5], "gain": 1.3}
    full = town_renderer.render(pos, R_nb, **kw)
    for roi in ((320, 240, 480, 360), (0, 0, 7, 5), (793, 590, 800, 600), (100, 0, 101, 600)):
        x0, y0, x1, y1 = roi
        part = town_renderer.render(pos, R_nb, roi=roi, **kw)
        assert part.shape == full.shape
        np.testing.assert_array_equal(part[y0:y1, x0:x1], full[y0:y1, x0:x1])
        outside = np.ones(part.shape, bool)
        outside[y0:y1, x0:x1] = False
        assert not part[outside].any()
    assert full.std() > 10.0  # the frame really shows the town


def test_town_river_world_has_no_nodata(town_renderer):
    world = town_renderer.world
    rng = np.random.default_rng(3)
    grid = np.arange(200) * 0.1
    near_black = []
    for n0, e0 in rng.uniform(-20_000.0, 20_000.0, size=(25, 2)):
        vals = world.sample(n0 + grid[:, None], e0 + grid[None, :])
        near_black.append(vals < NEAR_BLACK_DN)
    near_black = np.array(near_black)
    # no dark *area* (a 5 x 5 block all near-black) anywhere: thin real shadows are allowed, no-data is not
    blocks = [cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)) for m in near_black]
    assert not any(b.any() for b in blocks)
    assert near_black.mean() < 1e-3
    # the same check on the uncropped tile finds its no-data corner (the check can fail)
    raw = read_bgr(TEXTURE_DIR / "oam_town_river_10cm.tif")
    raw_world = GroundWorld.from_array(intensity_from_bgr(raw), 0.1)
    raw_vals = raw_world.sample(*np.meshgrid(np.arange(-1024, 1024) * 0.1, np.arange(-1024, 1024) * 0.1))
    assert (raw_vals < NEAR_BLACK_DN).mean() > 0.1
    # a high wide view over the town never shows a dark area either
    frame = town_renderer.render_intensity([400.0, -900.0, -300.0], _euler_deg(40.0, 10.0, 33.0))
    assert not cv2.erode((frame < NEAR_BLACK_DN).astype(np.uint8), np.ones((5, 5), np.uint8)).any()


def test_mipmapping_prevents_aliasing(camera):
    """A checkerboard of 2 cm squares seen from 100 m averages to its analytic mean; unfiltered it aliases."""
    lo, hi = 0.0, 255.0
    checker = np.where((np.add.outer(np.arange(512), np.arange(512)) % 2) == 0, lo, hi).astype(np.float32)
    world = GroundWorld.from_array(checker, 0.02)
    pos, R_nb = np.array([3.3, 7.1, -100.0]), _euler_deg(5.0, -3.0, 17.0)
    roi = (200, 150, 600, 450)
    x0, y0, x1, y1 = roi
    mean = (lo + hi) / 2.0
    filtered = CameraRenderer(camera, world).render_intensity(pos, R_nb, roi=roi)
    assert abs(filtered.mean() - mean) < 0.5
    assert filtered.std() < 1.0
    aliased = CameraRenderer(camera, world, mipmap=False).render_intensity(pos, R_nb, roi=roi)
    assert aliased.std() > 30.0

    def block_mean_error(img: np.ndarray) -> float:  # moire: 20 x 20 px block means wander from the true mean
        blocks = img[: (y1 - y0) // 20 * 20, : (x1 - x0) // 20 * 20].reshape((y1 - y0) // 20, 20, -1, 20)
        return float(np.abs(blocks.mean(axis=(1, 3)) - mean).max())

    assert block_mean_error(filtered) < 0.5
    assert block_mean_error(aliased) > 10.0


def test_noise_is_seeded_and_has_the_requested_std(town_renderer):
    pos, R_nb = np.array([0.0, 0.0, -100.0]), _euler_deg(0.0, 0.0, 0.0)
    a = town_renderer.render(pos, R_nb, noise_std=3.0, rng=np.random.default_rng(7))
    b = town_renderer.render(pos, R_nb, noise_std=3.0, rng=np.random.default_rng(7))
    c = town_renderer.render(pos, R_nb, noise_std=3.0, rng=np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert (a != c).mean() > 0.5
    clean = town_renderer.render_intensity(pos, R_nb)
    inside = (clean > 20) & (clean < 235)  # away from clipping
    diff = a.astype(np.float64) - clean
    assert diff[inside].std() == pytest.approx(np.sqrt(3.0**2 + 1.0 / 12.0), rel=0.05)  # noise + rounding
    assert abs(diff[inside].mean()) < 0.05
    bright = town_renderer.render(pos, R_nb, gain=1.2)
    ok = clean < 200
    np.testing.assert_allclose(bright[ok], np.rint(1.2 * clean[ok]), atol=1)


def test_compiled_mirror_fold_is_the_textures_fold():
    """The renderer kernel's scalar fold is sim.textures.mirror_wrap (the tile's definition), edges included."""
    rng = np.random.default_rng(2)
    size = 56
    u = np.concatenate([rng.uniform(-5000.0, 5000.0, 2000), np.arange(-3 * size, 3 * size + 1) - 0.5])
    ref = mirror_wrap(u, size)
    got = np.array([_mirror_fold(float(x), size) for x in u])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    assert got.min() >= -0.5 and got.max() <= size - 0.5


def test_world_is_the_mirror_tiled_tile():
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 255, size=(40, 56)).astype(np.float32)
    world = GroundWorld.from_array(img, 0.5)
    w, h = world.tile_px
    assert (w, h) == (56, 40)  # 8 | 56 and 8 | 40: no padding needed
    rows, cols = np.mgrid[0:h, 0:w]
    for ku, kv in ((0, 0), (1, 0), (-1, 2), (3, -5)):
        for mirror_u, mirror_v in ((False, False), (True, False), (False, True), (True, True)):
            cu = (2 * w - 1 - cols if mirror_u else cols) + 2 * w * ku
            rv = (2 * h - 1 - rows if mirror_v else rows) + 2 * h * kv
            n, e = world.texel_to_ground(cu, rv)
            np.testing.assert_allclose(world.sample(n, e), img, atol=1e-2)
    # continuous across a fold: half a texel either side of the edge gives the edge texel
    n, e = world.texel_to_ground(np.array([w - 0.75, w - 0.25]), np.array([3.0, 3.0]))
    np.testing.assert_allclose(world.sample(n, e), img[3, w - 1], atol=1e-2)


def test_textures_by_name(camera):
    with pytest.raises(ValueError, match="valid names: town_river"):
        GroundWorld.from_name("grass")
    assert GroundWorld.from_name("noise", seed=4) is GroundWorld.from_name("noise", seed=4)  # cached
    a = GroundWorld.from_name("noise", seed=4).level(0)
    b = GroundWorld.from_name("noise", seed=5).level(0)
    assert not np.array_equal(a, b)
    # texture where the estimator looks (19 x 19 px windows of a 100 m nadir frame): rich vs nearly none
    pos, R_nb, roi = np.array([0.0, 0.0, -100.0]), np.eye(3), (300, 200, 500, 400)

    def local_std(name: str) -> float:
        img = CameraRenderer(camera, GroundWorld.from_name(name, seed=1)).render_intensity(pos, R_nb, roi=roi)
        mu = cv2.blur(img, (19, 19))
        return float(np.median(np.sqrt(np.maximum(cv2.blur(img * img, (19, 19)) - mu * mu, 0.0))))

    assert local_std("noise") > 10.0
    assert local_std("uniform_grass") < 1.0
    assert local_std("water") < 1.0
    for name in ("dry_grassland", "forest_road", "farmland"):
        world = GroundWorld.from_name(name)
        assert world.level(0).min() > 0.0 and world.n_levels > 5
    assert set(TEXTURE_NAMES) >= {"mosaic", "town_river"}


def test_bad_inputs_are_rejected(town_renderer):
    R = np.eye(3)
    with pytest.raises(ValueError, match=r"pos_ned_m\[2\] must be negative"):
        town_renderer.render([0, 0, 5.0], R)
    with pytest.raises(ValueError, match="pos_ned_m"):
        town_renderer.render([0, np.nan, -5.0], R)
    with pytest.raises(ValueError, match="not a rotation"):
        town_renderer.render([0, 0, -50.0], 2 * R)
    for roi in ((10, 10, 5, 20), (0, 0, 801, 600), (-1, 0, 10, 10), (0.5, 0, 10, 10)):
        with pytest.raises(ValueError, match="roi"):
            town_renderer.render([0, 0, -50.0], R, roi=roi)
    with pytest.raises(ValueError, match="needs rng"):
        town_renderer.render([0, 0, -50.0], R, noise_std=2.0)
    with pytest.raises(ValueError, match="gain"):
        town_renderer.render([0, 0, -50.0], R, gain=0.0)
    with pytest.raises(ValueError, match="exposure_s"):
        town_renderer.render([0, 0, -50.0], R, exposure_s=-0.01)
    with pytest.raises(ValueError, match="m_per_px"):
        GroundWorld.from_array(np.zeros((16, 16)), 0.0)
    with pytest.raises(ValueError, match="non-finite"):
        GroundWorld.from_array(np.full((16, 16), np.nan), 0.1)
    with pytest.raises(ValueError, match="no colour"):
        town_renderer.render_color([0, 0, -50.0], R)


def test_render_cli_writes_png(tmp_path, capsys):
    from cli.main import main

    out = tmp_path / "frame.png"
    rc = main(["render", "--texture", "noise", "--alt-m", "100", "--north-m", "5", "--east-m", "-3",
               "--roll-deg", "20", "--pitch-deg", "-5", "--yaw-deg", "45", "--seed", "2", "--out", str(out)])
    assert rc == 0
    img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert img.shape == (600, 800) and img.dtype == np.uint8 and img.std() > 5
    out_c = tmp_path / "colour.png"
    assert main(["render", "--texture", "water", "--color", "--out", str(out_c)]) == 0
    assert cv2.imread(str(out_c), cv2.IMREAD_UNCHANGED).shape == (600, 800, 3)
    capsys.readouterr()
    assert main(["render", "--texture", "nope", "--out", str(out)]) == 2
    assert "valid names" in capsys.readouterr().err
    assert main(["render", "--texture", "noise", "--alt-m", "0", "--out", str(out)]) == 2
    assert "--alt-m" in capsys.readouterr().err
    assert main(["render", "--texture", "noise", "--out", str(tmp_path / "x.jpg")]) == 2


def test_sensor_noise_is_gaussian_with_the_requested_sigma(camera):
    """The table-sampled noise on flat ground: standard deviation, the normal's 1-, 2- and 3-sigma fractions and
    tails (scipy's normal CDF as the truth), and seeded reproducibility."""
    from scipy.stats import norm

    renderer = CameraRenderer(camera, GroundWorld.from_name("uniform_grass", seed=1))
    pos, roi = np.array([0.0, 0.0, -100.0]), (200, 100, 600, 500)
    clean = renderer.render_intensity(pos, np.eye(3), roi=roi)
    sigma = 6.0
    imgs = [renderer.render(pos, np.eye(3), roi=roi, noise_std=sigma, rng=np.random.default_rng(s)) for s in (1, 2)]
    x0, y0, x1, y1 = roi
    z = np.concatenate([(im[y0:y1, x0:x1].astype(np.float64) - clean).ravel() for im in imgs]) / sigma
    # rounding to whole DN adds a uniform(-0.5, 0.5) DN error: variance 1/12 DN^2
    assert np.std(z) == pytest.approx(math.sqrt(1.0 + 1.0 / (12 * sigma**2)), rel=0.01)
    for k in (1.0, 2.0, 3.0):
        assert np.mean(np.abs(z) <= k) == pytest.approx(norm.cdf(k) - norm.cdf(-k), abs=0.005), k
    assert np.mean(np.abs(z) > 4.0) < 3.0 * 2.0 * norm.sf(4.0)
    again = renderer.render(pos, np.eye(3), roi=roi, noise_std=sigma, rng=np.random.default_rng(1))
    np.testing.assert_array_equal(again, imgs[0])
