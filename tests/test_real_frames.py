"""``gsoe replay-frames``: image sequences through the navigation pipeline against their reference velocity.

A generic CSV sequence rendered here (known truth), its reader's checks, and the CLIF 2007 sequence (reads
``../shared/data``; skipped when absent)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cli.cmd_calibrate import camera_toml
from cli.main import main
from gsoe.camera import CameraModel
from gsoe.rotation import R_bc_from_mount, R_nb_from_euler
from nav.imageseq import SequenceError, read_clif2007, read_csv_sequence
from nav.replay_frames import run_replay_frames
from sim.render import CameraRenderer
from sim.textures import GroundWorld
from tests.conftest import shared_data
from tests.turning_flight import OBLIQUE, turning_flight

HEIGHT_M = 300.0


def _write_sequence(folder, n_frames: int, rng: np.random.Generator, quaternion: bool) -> None:
    """A turning flight at 10 m/s, 25 deg of bank, frames 0.5-1.2 s apart, as PNGs and a sequence CSV (camera
    quaternions or Euler angles), with the true velocity as reference."""
    cam = CameraModel.from_config(OBLIQUE)
    renderer = CameraRenderer(cam, GroundWorld.from_name("town_river"))
    R_bc = R_bc_from_mount(*np.radians(OBLIQUE.mount_rpy_deg))
    speed = 10.0
    att_cols = "qw_nc,qx_nc,qy_nc,qz_nc" if quaternion else "roll_deg,pitch_deg,yaw_deg"
    lines = ["# rendered over the town tile", f"t_us,image,{att_cols},height_agl_m,vn_m_s,ve_m_s,vd_m_s"]
    for k, t_s, pos, roll, pitch, yaw in turning_flight(rng, n_frames, HEIGHT_M, speed, 25.0):
        R_nb = R_nb_from_euler(roll, pitch, yaw)
        name = f"f{k:03d}.png"
        cv2.imwrite(str(folder / name), renderer.render(pos, R_nb, noise_std=1.0, rng=rng))
        if quaternion:
            x, y, z, w = (float(v) for v in Rotation.from_matrix(R_nb @ R_bc).as_quat())
            att = f"{w!r},{x!r},{y!r},{z!r}"
        else:
            att = f"{math.degrees(roll)!r},{math.degrees(pitch)!r},{math.degrees(yaw)!r}"
        v = f"{speed * math.cos(yaw)!r},{speed * math.sin(yaw)!r},0.0"
        lines.append(f"{1_000_000_000 + int(round(t_s * 1e6))},{name},{att},{HEIGHT_M},{v}")
    (folder / "seq.csv").write_text("\n".join(lines) + "\n")


def test_csv_sequence_through_the_cli_matches_the_true_velocity(tmp_path, capsys):
    _write_sequence(tmp_path, 20, np.random.default_rng(3), quaternion=True)
    cam_file = tmp_path / "oblique.toml"
    cam_file.write_text(camera_toml(OBLIQUE, ["test camera"]))
    out = tmp_path / "out"
    rc = main(["replay-frames", str(tmp_path / "seq.csv"), "--camera", str(cam_file), "--profile",
               "low_rate_oblique", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 20 and m["pairs"] == 19
    assert m["accepted_frac"] >= 0.9
    # the reference is the mean of the two frames' velocities, the chord's to 0.01 % in this 2 deg/s turn
    assert m["speed_abs_err_p95_pct"] < 0.3 and m["course_abs_err_p95_deg"] < 0.2
    pairs = (out / "pairs.csv").read_text().splitlines()
    assert len(pairs) == 20 and pairs[0].startswith("t_us,k,dt_s,")
    assert (out / "gsoe.csv").exists()


def test_csv_reader_euler_and_camera_quaternion_agree(tmp_path):
    rng = np.random.default_rng(4)
    (tmp_path / "e").mkdir()
    (tmp_path / "q").mkdir()
    _write_sequence(tmp_path / "e", 3, rng, quaternion=False)
    _write_sequence(tmp_path / "q", 3, np.random.default_rng(4), quaternion=True)
    a = read_csv_sequence(tmp_path / "e" / "seq.csv", OBLIQUE)
    b = read_csv_sequence(tmp_path / "q" / "seq.csv", OBLIQUE)
    assert [f.t_us for f in a.frames] == [f.t_us for f in b.frames] and a.frames[0].t_us == 0
    for fa, fb in zip(a.frames, b.frames, strict=True):
        Ra = R_nb_from_euler(fa.attitude.roll_rad, fa.attitude.pitch_rad, fa.attitude.yaw_rad)
        Rb = R_nb_from_euler(fb.attitude.roll_rad, fb.attitude.pitch_rad, fb.attitude.yaw_rad)
        assert np.allclose(Ra, Rb, atol=1e-9)
        assert fa.height_agl_m == HEIGHT_M and np.all(np.isfinite(fa.ref_vel_ned_m_s))


_HEAD = "t_us,image,roll_deg,pitch_deg,yaw_deg,height_agl_m\n"


@pytest.mark.parametrize(("text", "error"), [
    ("t_us,image,height_agl_m\n0,a.png,100\n", "roll_deg, pitch_deg, yaw_deg or the camera quaternion"),
    ("t_us,image,roll_deg,pitch_deg,yaw_deg\n0,a.png,0,0,0\n", "missing column.*height_agl_m"),
    (_HEAD + "5,a.png,0,0,0,100\n5,b.png,0,0,0,100\n", "line 3: t_us not increasing"),
    (_HEAD + "0,a.png,0,x,0,100\n", "line 2"),
])
def test_csv_reader_names_what_is_wrong(tmp_path, text, error):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(SequenceError, match=error):
        read_csv_sequence(p, OBLIQUE)


@pytest.fixture(scope="module")
def clif():
    return read_clif2007(shared_data("real_frames", "clif2007"))


@pytest.fixture(scope="module")
def clif_run(clif):
    return run_replay_frames(clif, profile="low_rate_oblique")


def test_clif2007_camera_and_ground_from_the_bundle_adjustment(clif):
    assert len(clif.frames) == 250 and clif.camera is not None
    cam = clif.camera
    assert cam.model == "pinhole" and cam.fx_px == pytest.approx(3582.86, abs=0.1)
    assert (cam.width_px, cam.height_px) == (668, 1004)
    # the mount: image x forward, the optical axis 9 deg to the right of the INS frame's z (so 7-27 deg off
    # vertical at the INS roll of 16-35 deg); one mount explains every bundle-adjusted camera within 3.3 deg
    assert cam.mount_rpy_deg[2] == pytest.approx(-92.0, abs=1.0)
    assert cam.mount_rpy_deg[1] == pytest.approx(-9.0, abs=1.0)
    assert clif.info["mount_spread_median_deg"] < 1.3 and clif.info["mount_spread_max_deg"] < 3.5
    # the bundle adjustment's frame is turned 1.29 deg from true north (UTM grid convergence at 83.0 W, 40.0 N)
    assert clif.info["krtd_frame_turn_deg"] == pytest.approx(-1.29, abs=0.05)
    # its ground: about 104 m on the INS altitude's datum, so 2707 m below the aircraft (not 2570: see nav.imageseq)
    assert 95.0 < clif.info["ground_level_m"] < 115.0
    assert clif.info["height_agl_median_m"] == pytest.approx(2707.0, abs=10.0)


def test_clif2007_optical_ground_velocity_against_the_ins(clif_run):
    """Acceptance of issue 21: median speed error <= 2 %, median course error <= 1 deg over the accepted pairs,
    at least 80 % accepted.  Figures reached (profile low_rate_oblique): 246 of 249 pairs, speed error median
    -0.18 % (of its magnitude 1.17 %, p95 5.6 %), course error median 0.38 deg (of its magnitude 0.69 deg, p95
    2.6 deg).  The per-pair scatter is the INS attitude's: ORB + homography through the same camera and attitude
    scatters the same way (the two agree to 0.4 % RMS per pair)."""
    m = clif_run.metrics
    assert m["pairs"] == 249
    assert m["accepted_frac"] >= 0.98
    assert abs(m["speed_err_median_pct"]) < 0.5
    assert m["speed_abs_err_median_pct"] < 1.3 and m["speed_abs_err_p95_pct"] < 6.5
    assert 0.2 < m["course_err_median_deg"] < 0.5
    assert m["course_abs_err_median_deg"] < 0.8 and m["course_abs_err_p95_deg"] < 3.0
    # with the map's ground level (240 m MSL) every speed would be 2570 / 2707 of this: 5 % short
    assert m["sequence_info"]["ground_level_m"] < 115.0


def _orb_velocity(seq, k: int, orb, matcher, feats: dict) -> np.ndarray | None:
    """Frame pair (k-1, k): the image centre of frame k-1 carried into frame k by an ORB + RANSAC homography, both
    pixels put on the ground with their frame's attitude, height and camera: the aircraft's mean velocity, NE."""
    cam = CameraModel.from_config(seq.camera)

    def get(i):
        if i not in feats:
            feats[i] = orb.detectAndCompute(cv2.imread(str(seq.frames[i].image), cv2.IMREAD_GRAYSCALE), None)
        return feats[i]

    (kp0, d0), (kp1, d1) = get(k - 1), get(k)
    m = matcher.match(d0, d1)
    p0 = np.float32([kp0[x.queryIdx].pt for x in m])
    p1 = np.float32([kp1[x.trainIdx].pt for x in m])
    H, inl = cv2.findHomography(p0, p1, cv2.RANSAC, 2.0)
    if H is None or inl.sum() < 50:
        return None
    c0 = np.array([(cam.size_px[0] - 1) / 2.0, (cam.size_px[1] - 1) / 2.0])
    c1 = cv2.perspectiveTransform(c0.reshape(1, 1, 2), H).reshape(2)

    def ground(px, f):
        a = f.attitude
        ray = R_nb_from_euler(a.roll_rad, a.pitch_rad, a.yaw_rad) @ cam.R_bc @ cam.unproject(np.array([px]))[0]
        return f.height_agl_m * ray[:2] / ray[2]

    f0, f1 = seq.frames[k - 1], seq.frames[k]
    return (ground(c0, f0) - ground(c1, f1)) / ((f1.t_us - f0.t_us) / 1e6)


def test_clif2007_matcher_agrees_with_orb_and_a_homography(clif, clif_run):
    """Matcher scale on real frames: the template matcher's per-pair velocity against an independent measurement
    through the same camera, attitude and height (ORB features, RANSAC homography, the image centre carried from
    one frame to the next).  Both see the INS attitude's scatter; their difference is the matchers' own.  Reached:
    speed difference median -0.11 % (no 1-5 % long reading here), 0.43 % RMS; course -0.01 deg, 0.24 deg RMS."""
    orb, matcher, feats = cv2.ORB.create(1000), cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True), {}
    d_speed, d_course = [], []
    for p in clif_run.pairs:
        if not p.accepted:
            continue
        v = _orb_velocity(clif, p.k, orb, matcher, feats)
        if v is None:
            continue
        d_speed.append(100.0 * (np.hypot(*p.vel_ne_m_s) / np.hypot(*v) - 1.0))
        d_course.append(math.degrees(math.remainder(math.atan2(p.vel_ne_m_s[1], p.vel_ne_m_s[0])
                                                    - math.atan2(v[1], v[0]), math.tau)))
    ds, dc = np.array(d_speed), np.array(d_course)
    assert len(ds) >= 240
    assert abs(np.median(ds)) < 0.4 and np.sqrt(np.mean(ds ** 2)) < 0.8
    assert abs(np.median(dc)) < 0.15 and np.sqrt(np.mean(dc ** 2)) < 0.4
