"""Loading the estimators' configuration from a TOML file: the optical estimator's sections and the camera file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from common.config import ConfigError, build
from common.configfile import DEFAULT_CONFIG, read_toml, resolve
from gsoe.config import CameraConfig, GsoeConfig


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
