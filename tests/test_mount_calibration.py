"""Camera-mount yaw calibration from a flight's own ``ekf.csv`` (:mod:`nav.mount_calibration`, ``gsoe
calibrate-mount``), against the simulator's truth: the estimator given a camera file whose mount yaw is 2 deg off the
camera that took the pictures learns, with GNSS and the paper flight's turns, the correction that brings it back."""

from __future__ import annotations

from pathlib import Path

import pytest

from cli.main import main
from nav.mount_calibration import mount_yaw_from_log
from sim.run import run_flight
from sim.scenario import load_scenario, scenario_with_overrides

MOUNT_YAW_ERROR_DEG = 2.0


@pytest.fixture(scope="module")
def flown(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("mount")
    scn = scenario_with_overrides(load_scenario("paper_sil"), {
        "camera.gsoe_overrides.camera.mount_rpy_deg": [0.0, 0.0, MOUNT_YAW_ERROR_DEG], "duration_s": 200.0})
    run_flight(scn, seed=1, out_dir=out, log_detail="reports")
    return out


def test_the_learnt_correction_brings_the_mount_back_to_the_true_one(flown):
    cal = mount_yaw_from_log(flown)
    assert cal.usable and cal.sigma_deg < 0.5, cal
    # the camera file says +2 deg, the camera is at 0: the correction is -2 deg, within 0.5 deg and 3 sigma
    err_deg = MOUNT_YAW_ERROR_DEG + cal.correction_deg
    assert abs(err_deg) < max(0.5, 3.0 * cal.sigma_deg), cal


def test_the_command_prints_the_corrected_camera_line_and_exits_0(flown, capsys):
    cam = Path(__file__).resolve().parents[1] / "config" / "camera" / "paper_fisheye_800x600.toml"
    assert main(["calibrate-mount", str(flown), "--camera", str(cam)]) == 0
    out = capsys.readouterr().out
    assert "mount_rpy_deg = [0.00, 0.00, " in out and "init_opt_rot_sigma_deg" in out


def test_a_folder_without_the_estimate_is_a_clear_error(tmp_path, capsys):
    assert main(["calibrate-mount", str(tmp_path / "nowhere")]) == 2
    (tmp_path / "ekf.csv").write_text("t_us,opt_rot_rad,valid\n1000,0.01,1\n")
    assert main(["calibrate-mount", str(tmp_path)]) == 2
    assert "opt_rot_sigma_rad" in capsys.readouterr().err
