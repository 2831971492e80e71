"""Reading configuration files (TOML) into the validated dataclasses of :mod:`gsoe.config`."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from gsoe.config import CameraConfig, ConfigError, GsoeConfig, build

CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
DEFAULT_CONFIG = CONFIG_DIR / "default.toml"


def read_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; a missing or malformed file raises :class:`ConfigError` naming the file."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(str(p), "file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(str(p), f"not valid TOML: {e}") from None


def resolve(path: str | Path, base: Path) -> Path:
    """A path from a config file, relative to that file's folder (or to ``config/``)."""
    p = Path(path)
    if p.is_absolute():
        return p
    for root in (base, CONFIG_DIR):
        if (root / p).exists():
            return root / p
    return base / p


def load_camera(path: str | Path) -> CameraConfig:
    try:
        return build(CameraConfig, read_toml(path), "camera")
    except ConfigError as e:
        raise ConfigError(f"{path}: {e.field_path}", str(e).split(": ", 1)[1]) from None


def load_gsoe_config(path: str | Path | None = None) -> tuple[GsoeConfig, dict[str, Any]]:
    """Load ``[camera]`` (``file = ...``), ``[stab]``, ``[match]``, ``[cycle]``, ``[integrity]``.

    Returns the validated optical config and the raw mapping (other packages build their own sections from it).
    """
    p = Path(path) if path is not None else DEFAULT_CONFIG
    raw = read_toml(p)
    gsoe_keys = {"camera", "stab", "match", "cycle", "integrity"}
    data = {k: v for k, v in raw.items() if k in gsoe_keys}
    cam = data.get("camera", {})
    if not isinstance(cam, dict) or "file" not in cam:
        raise ConfigError(f"{p}: camera.file", "missing (path of the camera file)")
    extra = set(cam) - {"file"}
    if extra:
        raise ConfigError(f"{p}: camera.{sorted(extra)[0]}", "unknown key (only 'file' belongs here)")
    camera = load_camera(resolve(cam["file"], p.parent))
    data = {**data, "camera": camera.__dict__}
    try:
        return build(GsoeConfig, data, ""), raw
    except ConfigError as e:
        raise ConfigError(f"{p}: {e.field_path}", str(e).split(": ", 1)[1]) from None
