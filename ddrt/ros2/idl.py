"""The DDS types of ddrt.ros2.interfaces' messages, as cyclonedds IDL dataclasses.

Generated from the .msg table (one class per message, once per process), named as ROS 2
names them on the wire (`nav_msgs::msg::dds_::Odometry_`), declared @final with XCDR1 data
representation (what ROS 2's middlewares send). Every field has a zero default, so a message
is built with only the fields that matter: `msg("geometry_msgs/msg/Vector3")(x=1.0)`.
Imports cyclonedds: only the bridge's process loads this module.
"""

from __future__ import annotations

import types as pytypes
from dataclasses import dataclass, field
from typing import Any

from cyclonedds.idl import IdlStruct, annotations as annotate, types as t

from ddrt.ros2.interfaces import MESSAGES, Field, dds_type_name, fields_of

SCALARS: dict[str, Any] = {"bool": bool, "byte": t.byte, "char": t.uint8, "int8": t.int8, "uint8": t.uint8,
                           "int16": t.int16, "uint16": t.uint16, "int32": t.int32, "uint32": t.uint32,
                           "int64": t.int64, "uint64": t.uint64, "float32": t.float32, "float64": t.float64,
                           "string": str}
ZERO: dict[str, Any] = {"bool": False, "string": "", "float32": 0.0, "float64": 0.0}

_CLASSES: dict[str, type] = {}


def _member(f: Field) -> tuple[Any, Any]:
    """(annotation, dataclass field with its zero default) for one .msg field."""
    if f.nested:
        base: Any = msg(f.base)
        zero: Any = base
    elif f.base == "string" and f.string_bound:
        base, zero = t.bounded_str[f.string_bound], ""
    else:
        base = SCALARS[f.base]
        zero = ZERO.get(f.base, 0)
    if f.kind == "array":
        n = f.size
        make = (lambda: [base() for _ in range(n)]) if f.nested else (lambda: [zero] * n)
        return t.array[base, n], field(default_factory=make)
    if f.kind in ("sequence", "bounded"):
        ann = t.sequence[base, f.size] if f.kind == "bounded" else t.sequence[base]
        return ann, field(default_factory=list)
    if f.nested:
        return base, field(default_factory=base)
    return base, field(default=zero)


def msg(type_name: str) -> type:
    """The IDL dataclass of `type_name` ("nav_msgs/msg/Odometry"), built on first use."""
    cls = _CLASSES.get(type_name)
    if cls is not None:
        return cls
    if type_name not in MESSAGES:
        raise KeyError(f"{type_name}: not one of the bridge's message types")
    members = {f.name: _member(f) for f in fields_of(type_name)}

    def body(ns: dict[str, Any]) -> None:
        ns["__annotations__"].update({k: ann for k, (ann, _) in members.items()})
        ns.update({k: default for k, (_, default) in members.items()})
        ns["__module__"] = __name__

    short = type_name.rsplit("/", 1)[1]
    cls = pytypes.new_class(short, (IdlStruct,), {"typename": dds_type_name(type_name)}, body)
    cls = annotate.final(dataclass(cls))
    _CLASSES[type_name] = cls
    return cls
