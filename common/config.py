"""The configuration machinery every package uses: frozen dataclasses built from plain mappings.

A configuration is a tree of frozen dataclasses.  :func:`build` turns a plain mapping (what ``tomllib`` gives)
into one, rejecting unknown keys, wrong types and out-of-range values with a :class:`ConfigError` whose message
starts with the dotted name of the bad field (``stab.template_px: must be odd, got 18``).  Reading files is the
caller's business (:mod:`common.configfile`); this module is pure.

Degrees appear here (``*_deg``) because configuration is an edge; code reads the ``*_rad`` properties.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from typing import Any, Literal, TypeVar, get_args, get_origin

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range; the message names it."""

    def __init__(self, field_path: str, message: str) -> None:
        super().__init__(f"{field_path}: {message}")
        self.field_path = field_path


def require(cond: bool, field_name: str, message: str) -> None:
    """Raise ``ConfigError(field_name, message)`` unless ``cond``; used in ``__post_init__`` validators."""
    if not cond:
        raise ConfigError(field_name, message)


def in_range(value: float, lo: float, hi: float, field_name: str, *, lo_open: bool = False) -> None:
    ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    bracket = "(" if lo_open else "["
    require(ok, field_name, f"must be in {bracket}{lo}, {hi}], got {value!r}")


def _coerce(tp: Any, value: Any, path: str) -> Any:
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        allowed = get_args(tp)
        if value not in allowed:
            raise ConfigError(path, f"must be one of {list(allowed)}, got {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(a, value, path)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(path, f"invalid value {value!r}")
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, Mapping):
            raise ConfigError(path, f"must be a table, got {type(value).__name__}")
        return build(tp, value, path)
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, list | tuple):
            raise ConfigError(path, f"must be a list, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, f"{path}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(path, f"must have {len(args)} elements, got {len(value)}")
        return tuple(_coerce(a, v, f"{path}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(path, f"must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, f"must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(path, f"must be a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ConfigError(path, f"must be finite, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(path, f"must be a string, got {value!r}")
        return value
    raise ConfigError(path, f"unsupported type {tp!r}")


def build(cls: type[T], data: Mapping[str, Any], where: str = "") -> T:
    """Build dataclass ``cls`` from ``data``; errors name the field as ``where.field``."""
    if not isinstance(data, Mapping):
        raise ConfigError(where or cls.__name__, f"must be a table, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    hints = typing.get_type_hints(cls)

    def full(name: str) -> str:
        return f"{where}.{name}" if where else name

    for key in data:
        if key not in fields:
            raise ConfigError(full(key), f"unknown key (known: {', '.join(sorted(fields))})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name in data:
            kwargs[name] = _coerce(hints[name], data[name], full(name))
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(full(name), "missing")
    try:
        return cls(**kwargs)
    except ConfigError as e:
        if where and not e.field_path.startswith(where + "."):
            raise ConfigError(full(e.field_path), str(e).split(": ", 1)[1]) from None
        raise


def to_dict(obj: Any) -> dict[str, Any]:
    """Plain-dict form of a config dataclass (for logs and metrics)."""
    return dataclasses.asdict(obj)
