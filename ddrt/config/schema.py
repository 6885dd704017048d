"""Turn a plain mapping (parsed YAML) into typed, frozen dataclasses, or say exactly what is wrong.

One small walker serves every config section: the dataclass's field types and each field's
declaration (`setting(...)`, ddrt/params/decl.py: unit, bounds, reload mode, description)
are the schema. Errors name the dotted key and the value ("controller.inner.kp: must be >= 0,
got -1.0") so the caller only has to prefix the file name.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from typing import Any, Collection, Literal, Mapping, TypeVar, get_args, get_origin, get_type_hints

from ddrt.errors import DdrtError
from ddrt.params.decl import (
    APPLY_MODES, LIVE, NEXT_PATH, RESTART, Decl, Section, decl_of, field_items, setting,
)
from ddrt.params.numbers import finite_float
from ddrt.config.yamlio import shorten

__all__ = ["APPLY_MODES", "LIVE", "NEXT_PATH", "RESTART", "ConfigError", "Decl", "Section", "build", "convert",
           "decl_of", "field_items", "field_types", "setting", "validate_tree", "FLOAT_MAX", "FLOAT_MIN", "INT_LIMIT"]

T = TypeVar("T")

# The largest whole number a key takes: beyond it a value is a typo, and arithmetic on it
# would overflow a float or a C long somewhere downstream.
INT_LIMIT = 2**63 - 1
# Every number a key takes is 0 or within [FLOAT_MIN, FLOAT_MAX] in magnitude: no robot, gain,
# time or distance needs more, and squares, products and inverses of such numbers stay far
# from the float range (1e308) where arithmetic overflows to inf or underflows to 0.
FLOAT_MIN = 1e-12
FLOAT_MAX = 1e12


class ConfigError(DdrtError, ValueError):
    """A config value is missing, unknown or invalid; the message names the key."""


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _is_optional(tp: Any) -> tuple[bool, Any]:
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) < len(get_args(tp)):
            return True, args[0] if len(args) == 1 else typing.Union[tuple(args)]
    return False, tp


def convert(tp: Any, value: Any, where: str) -> Any:
    """`value` as type `tp` (a field type the walker knows), or ConfigError naming `where`."""
    return _convert(tp, value, where)


def _convert(tp: Any, value: Any, where: str, default: Any = None) -> Any:
    """`default`: the field's default; a section's missing keys take its values."""
    optional, inner = _is_optional(tp)
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{where}: must not be empty")
    tp = inner
    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return build(tp, value, where, base=default if isinstance(default, tp) else None)
    if tp is Any:
        return value
    if origin is Literal:
        choices = get_args(tp)
        if not isinstance(value, (str, int, float, bool)) or value not in choices:
            raise ConfigError(f"{where}: must be one of {', '.join(map(repr, choices))}, got {shorten(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {shorten(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected a whole number, got {shorten(value)}")
        if abs(value) > INT_LIMIT:
            raise ConfigError(f"{where}: out of range, got {shorten(value)}")
        return value
    if tp is float:
        try:
            number = finite_float(value, where, shorten(value))
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if number != 0.0 and not FLOAT_MIN <= abs(number) <= FLOAT_MAX:
            raise ConfigError(f"{where}: out of range, got {number:g} (a number is 0 or between "
                              f"{FLOAT_MIN:g} and {FLOAT_MAX:g} in magnitude)")
        return number
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected text, got {shorten(value)}")
        return value
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {shorten(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {shorten(value)}")
        return dict(value)
    if origin in (typing.Union, types.UnionType):
        errors = []
        for option in get_args(tp):
            try:
                return _convert(option, value, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0])
    raise TypeError(f"schema: unsupported type {tp!r} at {where}")


def _field_default(f: dataclasses.Field) -> Any:
    """What field `f` is when its key is missing: its own default (None if it has none)."""
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


@functools.cache
def field_types(cls: type) -> dict[str, Any]:
    """A section class's field types, resolved once: typing.get_type_hints compiles every
    string annotation again on each call (40 % of loading a config)."""
    return get_type_hints(cls)


def build(cls: type[T], mapping: Any, where: str = "", *, ignore: Collection[str] = (), base: T | None = None) -> T:
    """Build dataclass `cls` from `mapping`, rejecting unknown keys and bad values.

    Missing keys take the field's default; a field without default is required. A section
    inside a section starts from its field's default instead (`base`), so its missing keys take
    that; `base` also gives a section defaults of the moment (SensorsConfig.for_backend). Each
    value given is checked against its field's declaration (`setting`: bounds, choices, the
    shape of a text) and the error names the key and the value. After the fields are set, a
    Section's `validate(where)` checks the rules between them.
    Keys in `ignore` are allowed in `mapping` and left to the caller (e.g. robot.motor). A
    class may name keys it no longer takes in `MOVED: ClassVar[dict[str, str]]`, key -> what
    to write instead; such a key is an error that says so.
    """
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"{where or 'config'}: expected a mapping, got {shorten(mapping)}")
    hints = field_types(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    moved: Mapping[str, str] = cls.MOVED if issubclass(cls, Section) else {}
    for key in mapping:
        if key in moved:
            raise ConfigError(f"{_join(where, key)}: no longer a key: {moved[key]}")
    unknown = sorted(k if isinstance(k, str) and len(k) <= 60 else shorten(k) for k in mapping
                     if k not in names and k not in ignore)
    if unknown:
        known = ", ".join(sorted(names | set(ignore)))
        raise ConfigError(f"{_join(where, unknown[0])}: unknown key (known: {known})")
    based = dict(field_items(base)) if base is not None else {}
    kwargs: dict[str, Any] = {}
    missing: list[str] = []  # all of them in one error: a section is not filled in one run per key
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        key = _join(where, f.name)
        if f.name in mapping:
            default = based[f] if f in based else _field_default(f)
            value = _convert(hints[f.name], mapping[f.name], key, default)
            decl = decl_of(f)
            problem = None if decl is None or value is None else decl.check(value, key)
            if problem is not None:
                raise ConfigError(problem)
            kwargs[f.name] = value
        elif base is not None:
            kwargs[f.name] = based[f]
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            missing.append(key)
    if missing:
        raise ConfigError(f"{', '.join(missing)}: missing (required)")
    try:
        obj = cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        # "MotorParams.supply_v: must be > 0" -> "robot.motor.supply_v: must be > 0"
        text = str(exc)
        head, sep, reason = text.partition(": ")
        if sep and head.startswith(cls.__name__ + "."):
            raise ConfigError(f"{_join(where, head[len(cls.__name__) + 1:])}: {reason}") from None
        raise ConfigError(f"{where or cls.__name__}: {text}") from None
    if isinstance(obj, Section):
        obj.validate(where)
    return obj


def validate_tree(obj: Any, where: str = "") -> None:
    """Run every section's `validate(where)` in a tree of built dataclasses, innermost first."""
    for f, value in field_items(obj):
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            validate_tree(value, _join(where, f.name))
    if isinstance(obj, Section):
        obj.validate(where)
