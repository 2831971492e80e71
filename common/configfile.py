"""Reading configuration files (TOML): the project's config folder, parsing with file-named errors, relative paths."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from common.config import ConfigError

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
