"""Runs never mix (issue 23): ``gsoe sim``, ``gsoe replay`` and the companion claim their output folder through
common.logio.claim_run_folder: a folder holding another run's logs is refused (sim, replay) or left alone for a
numbered one beside it (companion), and ``--overwrite`` replaces the earlier run's files instead of appending."""

from __future__ import annotations

import hashlib
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cli.main import main
from common.logio import RunFolderInUse, claim_run_folder, read_log

ROOT = Path(__file__).resolve().parent.parent


def snapshot(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder`` (relative path -> digest)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def earlier_run(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "ekf.csv").write_text("t_us,vel_n_m_s\n0,1.0\n")
    (folder / "metrics.json").write_text("{}\n")
    (folder / "report.html").write_text("<html></html>\n")
    (folder / "wind.png").write_bytes(b"\x89PNG")
    (folder / "notes.txt").write_text("the user's own file\n")
    (folder / "sub").mkdir()
    (folder / "sub" / "imu.csv").write_text("t_us\n0\n")


def test_a_fresh_or_foreign_folder_is_used_as_it_is(tmp_path):
    assert claim_run_folder(tmp_path / "a" / "b") == tmp_path / "a" / "b" and (tmp_path / "a" / "b").is_dir()
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "notes.txt").write_text("x")                  # not a run's logs
    assert claim_run_folder(tmp_path / "c") == tmp_path / "c"


def test_another_runs_logs_are_refused_untouched(tmp_path):
    d = tmp_path / "out"
    earlier_run(d)
    before = snapshot(d)
    with pytest.raises(RunFolderInUse, match="holds the logs of another run .*--overwrite"):
        claim_run_folder(d)
    assert snapshot(d) == before


def test_overwrite_deletes_only_the_earlier_runs_files(tmp_path):
    d = tmp_path / "out"
    earlier_run(d)
    assert claim_run_folder(d, overwrite=True) == d
    assert sorted(snapshot(d)) == ["notes.txt", "sub/imu.csv"]     # the run's top-level outputs gone, the rest kept


def test_numbered_gives_the_next_free_folder_beside(tmp_path):
    d = tmp_path / "log"
    earlier_run(d)
    before = snapshot(d)
    assert claim_run_folder(d, numbered=True) == tmp_path / "log-2"
    earlier_run(tmp_path / "log-2")
    (tmp_path / "log-3").write_text("a file, not a folder")
    assert claim_run_folder(d, numbered=True) == tmp_path / "log-4"
    assert snapshot(d) == before


def test_a_file_is_not_a_folder(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(NotADirectoryError):
        claim_run_folder(tmp_path / "f")


def test_a_second_gsoe_sim_into_the_same_folder_is_refused_and_the_first_run_is_unchanged(tmp_path, capsys):
    out = tmp_path / "sim"
    args = ["sim", "--duration", "1", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    before = snapshot(out)
    assert "ekf.csv" in before and "metrics.json" in before
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"gsoe sim: {out} holds the logs of another run"), err
    assert snapshot(out) == before                                  # byte for byte
    # --overwrite: a new run, not appended to the first: the same seed writes the same streams again, and time
    # never goes backwards in them
    assert main([*args, "--overwrite"]) == 0
    again = snapshot(out)
    for name in ("ekf.csv", "imu.csv", "gnss.csv"):
        assert again[name] == before[name], name
        assert np.all(np.diff(read_log(out / name)["t_us"]) >= 0)


def test_gsoe_replay_refuses_a_folder_with_another_runs_logs(tmp_path, capsys):
    out = tmp_path / "replay"
    earlier_run(out)
    before = snapshot(out)
    log = tmp_path / "flight.tlog"
    log.write_bytes(b"")
    assert main(["replay", str(log), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds the logs of another run" in err[0]
    assert snapshot(out) == before
    # a log that does not exist is reported before --overwrite clears anything
    assert main(["replay", str(tmp_path / "missing.tlog"), "--out", str(out), "--overwrite"]) == 2
    assert snapshot(out) == before


def test_the_companion_logs_beside_a_folder_that_holds_another_run(tmp_path):
    """The companion (no autopilot on its port, no camera) into a --log-dir with an earlier run's logs: it logs
    into LOG-2 and leaves LOG byte for byte as it was."""
    log_dir = tmp_path / "log"
    earlier_run(log_dir)
    before = snapshot(log_dir)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "cli", "companion", "--connect", f"udpin://127.0.0.1:{port}",
                             "--camera", str(tmp_path / "no_camera.avi"), "--log-dir", str(log_dir),
                             "--duration-s", "1.5"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == 0, err.decode()[-2000:]
    assert f"logging to {tmp_path / 'log-2'}" in err.decode()
    assert snapshot(log_dir) == before
    assert (tmp_path / "log-2" / "events.csv").is_file()
