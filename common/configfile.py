"""Reading configuration files (TOML): the project's config folder, parsing with file-named errors, relative paths,
the known top-level tables and ``--set`` overrides.

The config folder (``config/`` in the repository: ``default.toml``, ``camera/``, ``scenarios/``, ``montecarlo/``) is
read through :mod:`importlib.resources` as the package data ``common/config_data`` (a link to ``config/`` in the
source tree, a copy in a built wheel), so ``pip install gsoe-nav`` carries its defaults."""

from __future__ import annotations

import difflib
import functools
import importlib.resources
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from common.config import ConfigError


def _config_dir() -> Path:
    """The project's config folder, as package data of :mod:`common` (``common/config_data``): in the source tree
    a link to the repository's ``config/`` (resolved, so messages name ``config/...``), in an installed wheel the
    copy the wheel carries.  Wheels install unzipped, so it is always a real folder."""
    data = importlib.resources.files("common").joinpath("config_data")
    return Path(str(data)).resolve()


CONFIG_DIR = _config_dir()
DEFAULT_CONFIG = CONFIG_DIR / "default.toml"


def read_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; a file that is missing, unreadable (a folder, no permission), not UTF-8 text or not valid
    TOML raises :class:`ConfigError` naming the file."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(str(p), "file not found") from None
    except IsADirectoryError:
        raise ConfigError(str(p), "is a folder, not a TOML file") from None
    except OSError as e:
        raise ConfigError(str(p), f"cannot be read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(str(p), f"not a TOML file: not UTF-8 text (byte {e.start})") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(str(p), f"not valid TOML: {e}") from None


@functools.cache
def _default_tables() -> frozenset[str]:
    return frozenset(read_toml(DEFAULT_CONFIG))


def known_tables(extra: Iterable[str] = ()) -> frozenset[str]:
    """The top-level tables a configuration file may hold: those of ``config/default.toml`` (which documents every
    table the packages read) and ``extra``, the tables a caller reads beyond them."""
    return _default_tables() | frozenset(extra)


def check_table(name: str, where: str, extra: Iterable[str] = ()) -> None:
    """Refuse a top-level key that is not a known table (a misspelt ``[ekff]`` would otherwise be ignored and its
    values silently replaced by the defaults); the :class:`ConfigError` is named ``where``."""
    known = known_tables(extra)
    if name not in known:
        close = difflib.get_close_matches(name, sorted(known), n=1)
        hint = f" (did you mean [{close[0]}]?)" if close else ""
        raise ConfigError(where, f"unknown table{hint}; known: {', '.join(sorted(known))}")


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
