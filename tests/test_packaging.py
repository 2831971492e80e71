"""Packaging (issue 22): the wheel carries its default config (``common/config_data``, read through
importlib.resources), the extras split by role, and the companion runs with only ``[companion]``.

Default suite: the built wheel holds every file of ``config/`` and declares the extras; the companion's modules
import, and ``gsoe companion --help`` answers, with the simulator's, Monte Carlo's and the reports' packages made
unimportable; a command whose extra is missing says which one to install.  Slow: the wheel installed with only
``[companion]`` into a fresh venv runs ``gsoe companion --help`` and flies a short SIL pair against the simulated
vehicle (from this tree's venv, as a companion computer would next to a simulator)."""

from __future__ import annotations

import email
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest

from common.logio import read_log

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable
# the packages the companion must run without (what [sim], [mc] and [report] bring)
NOT_ON_A_COMPANION = ("jsbsim", "numba", "dask", "distributed", "tqdm", "pyulog", "tomli_w", "matplotlib")
BLOCK = f"""
import sys, importlib.abc
class _Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {NOT_ON_A_COMPANION!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked by the test)", name=name)
        return None
sys.meta_path.insert(0, _Block())
import importlib.util
_find = importlib.util.find_spec
importlib.util.find_spec = lambda n, *a: None if n.split('.')[0] in {NOT_ON_A_COMPANION!r} else _find(n, *a)
"""


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    # a copy of the tree: setuptools builds in place, and a stale build/ of the checkout would go into the wheel
    src = tmp_path_factory.mktemp("src") / "gsoe-nav"
    shutil.copytree(ROOT, src, symlinks=True, ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "dist", "out", "logs", "runs", "*.egg-info", "__pycache__", ".*_cache", "tests"))
    r = subprocess.run([PY, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out), str(src)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = out.glob("gsoe_nav-*.whl")
    return whl


def test_wheel_carries_the_config_folder_and_declares_the_extras(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    config = ROOT / "config"
    wanted = {f"common/config_data/{p.relative_to(config).as_posix()}" for p in config.rglob("*.toml")}
    assert "common/config_data/default.toml" in wanted
    assert wanted <= names, sorted(wanted - names)
    assert any(n.startswith("sim/aircraft/") for n in names) and any(n.startswith("sim/data/") for n in names)
    meta_name = next(n for n in names if n.endswith(".dist-info/METADATA"))
    meta = email.message_from_bytes(zipfile.ZipFile(wheel).read(meta_name))
    extras = set(meta.get_all("Provides-Extra") or [])
    assert {"companion", "sim", "mc", "report", "gcs", "dev"} <= extras
    reqs = meta.get_all("Requires-Dist") or []
    core = [r for r in reqs if "extra ==" not in r]
    assert not [r for r in core if r.split(">")[0].split("[")[0].strip() in NOT_ON_A_COMPANION + ("mavsdk",)], core
    companion = {r.split(">")[0].strip() for r in reqs if 'extra == "companion"' in r}
    assert {"numpy", "scipy", "opencv-python-headless", "mavsdk", "pymavlink", "filterpy"} <= companion


def _blocked(code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([PY, "-c", BLOCK + code], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def test_companion_imports_and_answers_help_without_the_sim_packages(tmp_path):
    r = _blocked("import nav.companion, nav.signing, nav.gcs_display, cli.cmd_companion\n"
                 "from common.configfile import CONFIG_DIR; assert (CONFIG_DIR / 'default.toml').is_file()\n"
                 "from pipeline.config import load_gsoe_config; load_gsoe_config()\n"
                 "import sys; print(sorted(m for m in sys.modules if m.split('.')[0] == 'sim'))\n"
                 "from cli.main import main; sys.exit(main(['companion', '--help']))", tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "[]" in r.stdout and "--connect" in r.stdout


def test_a_command_without_its_extra_names_the_extra_to_install(tmp_path):
    r = _blocked("from cli.main import main; import sys; sys.exit(main(['sim', '--duration', '5']))", tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "gsoe sim: needs the [sim] extra (missing: jsbsim, numba, tqdm, matplotlib): pip install 'gsoe-nav[sim]'"]
    r = _blocked("from cli.main import main; import sys; sys.exit(main(['--help']))", tmp_path)
    assert r.returncode == 0 and "[not installed: gsoe-nav[mc]]" in r.stdout


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
def test_wheel_with_only_the_companion_extra_flies_a_sil_pair(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([PY, "-m", "venv", str(venv)], check=True, timeout=120)
    vpy = venv / "bin" / "python"
    r = subprocess.run([str(vpy), "-m", "pip", "install", "-q", f"{wheel}[companion]"], capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([str(vpy), "-c", "import importlib.util as u; "
                        f"print([m for m in {NOT_ON_A_COMPANION[:-1]!r} if u.find_spec(m)])"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr  # matplotlib comes with filterpy: not checked
    gsoe = venv / "bin" / "gsoe"
    r = subprocess.run([str(gsoe), "companion", "--help"], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "--connect" in r.stdout, r.stderr
    r = subprocess.run([str(vpy), "-c", "from common.configfile import CONFIG_DIR; print(CONFIG_DIR)"], cwd=tmp_path,
                       env=env, capture_output=True, text=True, timeout=60)
    assert str(venv) in r.stdout, r.stdout  # the wheel's own config, not this tree's

    udp, tcp = _free_port(socket.SOCK_DGRAM), _free_port(socket.SOCK_STREAM)
    duration_s = 25.0
    veh = subprocess.Popen([PY, "-m", "sim.mavlink_vehicle", "--connect", f"udpout:127.0.0.1:{udp}", "--duration-s",
                            str(duration_s + 8), "--wind-ned-m-s", "0,6", "--frame-hz", "15", "--frame-port", str(tcp),
                            "--summary", str(tmp_path / "vehicle.json")], cwd=ROOT,
                           env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.DEVNULL,
                           stderr=open(tmp_path / "vehicle.log", "w"))
    comp = None
    try:
        time.sleep(1.5)
        comp = subprocess.Popen([str(gsoe), "companion", "--connect", f"udpin://127.0.0.1:{udp}", "--camera",
                                 f"sim://127.0.0.1:{tcp}", "--log-dir", str(tmp_path / "log"), "--duration-s",
                                 str(duration_s)], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                                stderr=open(tmp_path / "companion.log", "w"), text=True)
        out, _ = comp.communicate(timeout=duration_s + 60)
    finally:
        for p in (comp, veh):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(timeout=10)
    assert comp.returncode == 0, (tmp_path / "companion.log").read_text()[-3000:]
    status = json.loads(out)
    assert status["frames"] > 100 and status["steps"] > 50, status
    outputs = read_log(tmp_path / "log" / "outputs.csv")
    assert outputs["sent"].astype(bool).sum() > 50
