"""Configuration files and ``--set`` overrides that are wrong give one clear :class:`ConfigError`, never a traceback
(issue 23): unreadable files, misspelt tables, out-of-range overrides."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from common.config import ConfigError
from common.configfile import CONFIG_DIR, DEFAULT_CONFIG, known_tables, parse_override, read_toml
from pipeline.config import load_gsoe_config

ROOT = Path(__file__).resolve().parent.parent
CAMERA_FILE = CONFIG_DIR / "camera" / "paper_fisheye_800x600.toml"
# Bytes that are not UTF-8 (a binary file given as the configuration).
RANDOM_BYTES = bytes(range(128, 256)) + b"\x00\xff[stab]\n\xfe"


def _config(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cfg.toml"
    p.write_text(f'[camera]\nfile = "{CAMERA_FILE}"\n{text}')
    return p


def test_random_bytes_name_the_file(tmp_path: Path) -> None:
    p = tmp_path / "binary.toml"
    p.write_bytes(RANDOM_BYTES)
    with pytest.raises(ConfigError, match="not a TOML file: not UTF-8") as ei:
        load_gsoe_config(p)
    assert ei.value.field_path == str(p)


def test_a_folder_as_the_config_names_it(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="is a folder, not a TOML file") as ei:
        load_gsoe_config(tmp_path)
    assert ei.value.field_path == str(tmp_path)


def test_an_unreadable_camera_file_names_that_file(tmp_path: Path) -> None:
    cam = tmp_path / "camera.toml"
    cam.write_bytes(RANDOM_BYTES)
    p = tmp_path / "cfg.toml"
    p.write_text(f'[camera]\nfile = "{cam}"\n')
    with pytest.raises(ConfigError, match="not UTF-8") as ei:
        load_gsoe_config(p)
    assert ei.value.field_path == str(cam)
    p.write_text("[camera]\nfile = 5\n")
    with pytest.raises(ConfigError, match=r"camera\.file: must be a string"):
        load_gsoe_config(p)


@pytest.mark.parametrize(("table", "close"), [("ekff", "ekf"), ("stabb", "stab"), ("companoin", "companion")])
def test_a_misspelt_table_is_refused_naming_the_known_ones(tmp_path: Path, table: str, close: str) -> None:
    p = _config(tmp_path, f"[{table}]\nx = 1\n")
    with pytest.raises(ConfigError) as ei:
        load_gsoe_config(p)
    assert ei.value.field_path == f"{p}: {table}"
    msg = str(ei.value)
    assert f"unknown table (did you mean [{close}]?)" in msg
    for known in ("camera", "stab", "match", "cycle", "integrity", "pipeline", "companion", "ekf", "replay"):
        assert known in msg


def test_every_table_of_the_default_file_is_known_and_a_caller_can_add_its_own(tmp_path: Path) -> None:
    assert set(read_toml(DEFAULT_CONFIG)) == set(known_tables())
    assert "replay" in known_tables()  # read by nav.replay; documented in config/default.toml
    p = _config(tmp_path, "[my_tool]\nx = 1\n")
    with pytest.raises(ConfigError, match="my_tool: unknown table"):
        load_gsoe_config(p)
    assert load_gsoe_config(p, tables=["my_tool"])[1]["my_tool"] == {"x": 1}


def test_set_is_validated_like_the_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as ei:
        load_gsoe_config(overrides=[parse_override("stab.template_px=-5")])
    assert str(ei.value) == "--set stab.template_px: must be in [3, 201], got -5"
    with pytest.raises(ConfigError, match=r"^--set stab\.templat_px: unknown key"):
        load_gsoe_config(overrides=[parse_override("stab.templat_px=21")])
    with pytest.raises(ConfigError, match=r"^--set ekff\.gate_baro_nis: unknown table \(did you mean \[ekf\]\?\)"):
        load_gsoe_config(overrides=[parse_override("ekff.gate_baro_nis=9.0")])
    with pytest.raises(ConfigError, match=r"^--set stab\.template_px\.x: template_px is not a table"):
        load_gsoe_config(overrides=[parse_override("stab.template_px.x=1")])
    # an override that is fine is applied to the optical config and to the mapping other packages read
    cfg, raw = load_gsoe_config(overrides=[parse_override("stab.template_px=21"),
                                           parse_override("companion.guidance.correct_drift=false")])
    assert cfg.stab.template_px == 21 and raw["companion"]["guidance"]["correct_drift"] is False
    # a bad value of the file itself still names the file
    p = _config(tmp_path, "[stab]\ntemplate_px = 18\n")
    with pytest.raises(ConfigError, match=rf"^{p}: stab\.template_px: must be odd, got 18$"):
        load_gsoe_config(p, overrides=[parse_override("match.psr_min=4.0")])


def _gsoe(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "cli", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120)


@pytest.mark.parametrize("kind", ["folder", "binary", "misspelt"])
def test_gsoe_sim_with_a_bad_config_exits_with_one_line(tmp_path: Path, kind: str) -> None:
    if kind == "folder":
        cfg = tmp_path
    elif kind == "binary":
        cfg = tmp_path / "binary.toml"
        cfg.write_bytes(RANDOM_BYTES)
    else:
        cfg = _config(tmp_path, "[ekff]\ngate_baro_nis = 9.0\n")
    r = _gsoe("sim", "--duration", "1", "--out", str(tmp_path / "out"), "--no-progress", "--config", str(cfg))
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gsoe sim: configuration error: ") and str(cfg) in lines[0], lines
