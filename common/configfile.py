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


def parse_override(text: str) -> tuple[list[str], Any]:
    """``DOTTED.KEY=VALUE`` (the value written as in TOML: ``a.b=1.5``, ``a.c=false``, ``'a.d="text"'``) as
    ``(["DOTTED", "KEY"], value)``; :class:`ConfigError` when it is not one."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError(text, "expected DOTTED.KEY=VALUE")
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        raise ConfigError(key.strip(), f"{value!r} is not a TOML value (strings need quotes)") from None
    return key.strip().split("."), parsed


def apply_overrides(raw: dict[str, Any], overrides: list[tuple[list[str], Any]]) -> dict[str, Any]:
    """``raw`` (a parsed config file) with each ``(path, value)`` of :func:`parse_override` set, tables created as
    needed; the values are validated when the config is built from ``raw``."""
    for path, value in overrides:
        node = raw
        for part in path[:-1]:
            nxt = node.setdefault(part, {})
            if not isinstance(nxt, dict):
                raise ConfigError(".".join(path), f"{part} is not a table")
            node = nxt
        node[path[-1]] = value
    return raw
