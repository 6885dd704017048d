"""Every config key with its declaration, walked once from the section classes: the list the
reference (docs/reference/config.md), the reload policy, the Foxglove parameters and the
tests all read, so none keeps a list of its own.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass
from typing import Any, Iterator, get_args, get_origin

from ddrt.params.decl import RESTART, Decl, Section, decl_of, field_items
from ddrt.config.schema import field_types

ROOT_MODE = RESTART  # a field that declares nothing, anywhere up its chain, waits for a restart
ITEM = "[]"  # a key inside each item of a list of sections: sim.events.payloads[].at_s


@dataclass(frozen=True)
class Key:
    """One config key: where it is, what it declares, how it reloads, what it takes by default."""

    key: str
    decl: Decl
    mode: str
    hint: Any  # the field's type
    default: Any  # dataclasses.MISSING: required
    section: type | None  # the section class a key holds (itself, or each item of its list), else None
    owner: type  # the class the field is declared in
    name: str  # the field's name in its class
    parent: str  # the key of the section this key is in ("" at the top level)


def section_mode(owner: type, inherited: str) -> str:
    """The mode a section's fields take unless they declare their own."""
    declared = owner.APPLY if isinstance(owner, type) and issubclass(owner, Section) else None
    return declared or inherited


def mode_of(f: dataclasses.Field, inherited: str) -> str:
    """Field `f`'s reload mode: its own declaration's, else `inherited` (its section's)."""
    decl = decl_of(f)
    return decl.reload if decl is not None and decl.reload is not None else inherited


def key_of(prefix: str, f: dataclasses.Field) -> str:
    """Field `f`'s dotted key under `prefix` (a declaration may name the key itself: robot.motor)."""
    decl = decl_of(f)
    if decl is not None and decl.name is not None:
        return decl.name
    return f"{prefix}.{f.name}" if prefix else f.name


def is_section(value: Any) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


def section_in(hint: Any) -> tuple[type | None, bool]:
    """The section class a field's type holds, directly, as Optional, or as each item of a
    tuple (then the flag is True); (None, False) for a value."""
    if dataclasses.is_dataclass(hint):
        return hint, False
    origin = get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        for arg in get_args(hint):
            if dataclasses.is_dataclass(arg):
                return arg, False
    if origin is tuple:
        args = get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis and dataclasses.is_dataclass(args[0]):
            return args[0], True
    return None, False


def _default(f: dataclasses.Field, within: Any) -> Any:
    if within is not None:
        return dict(field_items(within))[f]
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def declared_keys(cls: type, prefix: str = "", inherited: str = ROOT_MODE, within: Any = None) -> Iterator[Key]:
    """Every key of section `cls` (and of the sections it holds), depth first in field order.
    `within`: the enclosing field's default, whose values are this section's defaults. A field
    without a declaration raises TypeError: every key is declared."""
    hints = field_types(cls)
    mode_here = section_mode(cls, inherited)
    for f in dataclasses.fields(cls):
        if not f.compare or not f.init:
            continue  # not a setting (where a config came from)
        decl = decl_of(f)
        if decl is None:
            raise TypeError(f"{cls.__name__}.{f.name}: a config key without a declaration (use setting(...))")
        key = key_of(prefix, f)
        mode = mode_of(f, mode_here)
        default = _default(f, within)
        section, listed = section_in(hints[f.name])
        yield Key(key, decl, mode, hints[f.name], default, section, cls, f.name, prefix)
        if section is not None:
            inner_default = default if is_section(default) else None
            yield from declared_keys(section, key + ITEM if listed else key, mode, None if listed else inner_default)
