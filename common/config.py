"""The configuration machinery every package uses: frozen dataclasses built from plain mappings.

A configuration is a tree of frozen dataclasses.  :func:`build` turns a plain mapping (what ``tomllib`` gives)
into one, rejecting unknown keys, wrong types and out-of-range values with a :class:`ConfigError` whose message
starts with the dotted name of the bad field (``stab.template_px: must be odd, got 18``).  Reading files is the
caller's business (:mod:`common.configfile`); this module is pure.

A field's range is declared once, on the field, and checked by one validator however the dataclass is made
(:func:`build`, direct construction, ``dataclasses.replace``)::

    @dataclass(frozen=True)
    class StabConfig(Validated):
        template_px: Annotated[int, In(3, 201, odd=True, doc="template side, px")] = 19

:class:`Validated` runs :func:`check_fields` in ``__post_init__``; a class with rules that tie fields together
overrides ``__post_init__``, calls ``super().__post_init__()`` first and states those rules as code with
:func:`require`.  Ranges shared by several fields are module-level aliases (``Gain = Annotated[float, In(0, 100)]``).
The annotations are resolved in the module's namespace (as :func:`build` resolves them), so config classes and
their aliases live at module level.

Degrees appear here (``*_deg``) because configuration is an edge; code reads the ``*_rad`` attributes, declared
with :class:`Radians` (``noise_rad = Radians("noise_deg")``).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from collections.abc import Mapping
from typing import Annotated, Any, Literal, TypeVar, get_args, get_origin

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


@dataclasses.dataclass(frozen=True, slots=True)
class In:
    """The declared range of a numeric config field: ``Annotated[float, In(lo, hi)]``; see the module docstring.

    ``lo``, ``hi``: bounds, both closed unless ``lo_open`` (:data:`FINITE`: any finite number); ``odd``: the value
    must be an odd integer; ``doc``: what the field is, in one line with its unit, where its name and the class
    docstring do not say it.  A field whose type is ``int`` must hold an integer; a tuple field has each element
    checked (``dist[2]``); ``None`` (an optional field left unset) passes.
    """

    lo: float
    hi: float
    lo_open: bool = False
    odd: bool = False
    doc: str = ""

    def check(self, value: Any, name: str, *, integer: bool = False) -> None:
        """Raise :class:`ConfigError` naming ``name`` unless ``value`` is inside the range (also usable on its own,
        for a value that is not a field, e.g. a command's argument)."""
        if value is None:
            return
        if isinstance(value, tuple):
            for i, v in enumerate(value):
                self.check(v, f"{name}[{i}]", integer=integer)
            return
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ConfigError(name, f"must be a number, got {value!r}")
        if integer and not isinstance(value, numbers.Integral):
            raise ConfigError(name, f"must be an integer, got {value!r}")
        if self.lo == -math.inf and self.hi == math.inf:
            require(math.isfinite(value), name, f"must be finite, got {value!r}")
        in_range(value, self.lo, self.hi, name, lo_open=self.lo_open)  # type: ignore[arg-type]
        require(not self.odd or value % 2 == 1, name, f"must be odd, got {value}")


FINITE = In(-math.inf, math.inf)
"""The range of a field that may take any finite value."""

_FieldCheck = tuple[str, In, bool]
_FIELD_CHECKS: dict[type, tuple[_FieldCheck, ...]] = {}


def _is_int_type(tp: Any) -> bool:
    if tp is int:
        return True
    if get_origin(tp) is tuple:
        args = [a for a in get_args(tp) if a is not Ellipsis]
        return bool(args) and all(a is int for a in args)
    return False


def field_ranges(cls: type) -> tuple[_FieldCheck, ...]:
    """``(field name, In, integer)`` of every field of dataclass ``cls`` with a declared range (cached per class)."""
    checks = _FIELD_CHECKS.get(cls)
    if checks is None:
        hints = typing.get_type_hints(cls, include_extras=True)
        found: list[_FieldCheck] = []
        for f in dataclasses.fields(cls):
            tp = hints[f.name]
            if get_origin(tp) is Annotated:
                base, *extras = get_args(tp)
                found.extend((f.name, x, _is_int_type(base)) for x in extras if isinstance(x, In))
        checks = _FIELD_CHECKS[cls] = tuple(found)
    return checks


def check_fields(obj: Any) -> None:
    """Check every field of dataclass instance ``obj`` against its declared :class:`In` range, in field order."""
    for name, rng, integer in field_ranges(type(obj)):
        rng.check(getattr(obj, name), name, integer=integer)


class Radians:
    """A read-only attribute of a config class: one of its degrees fields in radians (configuration speaks degrees,
    code reads radians)::

        noise_deg: Annotated[float, In(0.0, 10.0)] = 0.1
        noise_rad = Radians("noise_deg")

    Not a dataclass field (no annotation); a name that is not a field of the class is refused when the class is
    made."""

    __slots__ = ("deg_field",)

    def __init__(self, deg_field: str) -> None:
        self.deg_field = deg_field

    def __set_name__(self, owner: type, name: str) -> None:
        if self.deg_field not in getattr(owner, "__annotations__", {}):
            raise TypeError(f"{owner.__name__}.{name}: Radians of {self.deg_field!r}, not a field of the class")

    @typing.overload
    def __get__(self, obj: None, owner: type | None = None) -> Radians: ...

    @typing.overload
    def __get__(self, obj: object, owner: type | None = None) -> float: ...

    def __get__(self, obj: object | None, owner: type | None = None) -> Radians | float:
        return self if obj is None else math.radians(getattr(obj, self.deg_field))


class Validated:
    """Base of the config dataclasses: construction checks every field's declared range (:func:`check_fields`).

    A subclass with cross-field rules overrides ``__post_init__`` and calls ``super().__post_init__()`` first.
    """

    __slots__ = ()

    def __post_init__(self) -> None:
        check_fields(self)


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


PROFILES_KEY = "profiles"


def with_profile(table: Any, profile: str | None, where: str) -> dict[str, Any]:
    """A configuration table with its named profile applied: ``[where.profiles.<profile>]`` on top of ``[where]``
    (tables merged key by key), the ``profiles`` table itself removed.  An unknown profile is a
    :class:`ConfigError` naming the known ones; ``profile`` None gives the table as it is."""
    if not isinstance(table, Mapping):
        raise ConfigError(where, f"must be a table, got {type(table).__name__}")
    profiles = table.get(PROFILES_KEY, {})
    if not isinstance(profiles, Mapping):
        raise ConfigError(f"{where}.{PROFILES_KEY}", f"must be a table, got {type(profiles).__name__}")
    base = {k: v for k, v in table.items() if k != PROFILES_KEY}
    if profile is None:
        return base
    if profile not in profiles:
        raise ConfigError(f"{where}.{PROFILES_KEY}", f"no profile {profile!r} (known: {', '.join(sorted(profiles))})")
    return _merge(base, profiles[profile], f"{where}.{PROFILES_KEY}.{profile}")


def _merge(base: Mapping[str, Any], top: Any, where: str) -> dict[str, Any]:
    if not isinstance(top, Mapping):
        raise ConfigError(where, f"must be a table, got {type(top).__name__}")
    out = dict(base)
    for k, v in top.items():
        out[k] = _merge(out[k], v, f"{where}.{k}") if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) \
            else v
    return out
