"""Loading the estimators' configuration from a TOML file: the optical estimator's sections and the camera file."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from common.config import ConfigError, build
from common.configfile import DEFAULT_CONFIG, apply_overrides, check_table, read_toml, resolve
from gsoe.config import CameraConfig, GsoeConfig


def load_camera(path: str | Path) -> CameraConfig:
    """A camera file (``config/camera/*.toml``); errors name the file."""
    data = read_toml(path)
    try:
        return build(CameraConfig, data, "camera")
    except ConfigError as e:
        raise ConfigError(f"{path}: {e.field_path}", str(e).split(": ", 1)[1]) from None


def load_gsoe_config(path: str | Path | None = None, *, overrides: Sequence[tuple[Sequence[str], Any]] = (),
                     tables: Iterable[str] = ()) -> tuple[GsoeConfig, dict[str, Any]]:
    """Load ``[camera]`` (``file = ...``), ``[stab]``, ``[match]``, ``[cycle]``, ``[integrity]``.

    ``overrides``: ``--set`` values (:func:`common.configfile.parse_override`) applied to the file's mapping before
    anything is validated, so they pass the same checks as the file's own values.  Every top-level table must be
    one of :func:`common.configfile.known_tables` (with ``tables``, those the caller reads beyond
    ``config/default.toml``'s).  Errors name the file, or ``--set KEY`` for an override.
    Returns the validated optical config and the raw mapping with the overrides (other packages build their own
    sections from it).
    """
    p = Path(path) if path is not None else DEFAULT_CONFIG
    raw = read_toml(p)
    tables = tuple(tables)
    for name in raw:
        check_table(name, f"{p}: {name}", tables)
    set_keys = [".".join(key) for key, _ in overrides]
    for key in set_keys:
        check_table(key.split(".")[0], f"--set {key}", tables)
    try:
        apply_overrides(raw, [(list(key), value) for key, value in overrides])
    except ConfigError as e:
        raise ConfigError(f"--set {e.field_path}", str(e).split(": ", 1)[1]) from None

    def named(e: ConfigError) -> ConfigError:
        by_set = any(e.field_path == k or e.field_path.startswith((k + ".", k + "[")) for k in set_keys)
        return ConfigError(f"--set {e.field_path}" if by_set else f"{p}: {e.field_path}", str(e).split(": ", 1)[1])

    gsoe_keys = {"camera", "stab", "match", "cycle", "integrity"}
    data = {k: v for k, v in raw.items() if k in gsoe_keys}
    cam = data.get("camera", {})
    if not isinstance(cam, dict) or "file" not in cam:
        raise named(ConfigError("camera.file", "missing (path of the camera file)"))
    if not isinstance(cam["file"], str):
        raise named(ConfigError("camera.file", f"must be a string (path of the camera file), got {cam['file']!r}"))
    extra = set(cam) - {"file"}
    if extra:
        raise named(ConfigError(f"camera.{sorted(extra)[0]}", "unknown key (only 'file' belongs here)"))
    camera = load_camera(resolve(cam["file"], p.parent))
    data = {**data, "camera": camera.__dict__}
    try:
        return build(GsoeConfig, data, ""), raw
    except ConfigError as e:
        raise named(e) from None
