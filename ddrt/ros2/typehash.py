"""RIHS01 type hashes (REP-2011), computed from the type descriptions, never typed in.

ROS 2 (from Iron) announces each topic's type hash in the endpoint's USER_DATA
(`typehash=RIHS01_<hex>;`) and `ros2 topic info -v` shows it. The hash is the SHA-256 of the
type's description, `type_description_interfaces/msg/TypeDescription`, written as JSON:
the type and every type it refers to (sorted by name), each a name and its fields, a field a
name and its type (type ID, array capacity, string bound, nested type name), no default
values; `json.dumps`'s default separators (", " and ": "), keys in the message's order.
"""

from __future__ import annotations

import hashlib
import json
from functools import lru_cache
from typing import Any

from ddrt.ros2.interfaces import Field, dependencies, fields_of

# type_description_interfaces/msg/FieldType: the scalar IDs, and what an array, a bounded or
# an unbounded sequence adds to them.
TYPE_IDS = {"nested": 1, "int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8,
            "uint64": 9, "float32": 10, "float64": 11, "char": 13, "bool": 15, "byte": 16, "string": 17,
            "bounded_string": 21}
KIND_OFFSET = {"single": 0, "array": 48, "bounded": 96, "sequence": 144}


def field_type(f: Field) -> dict[str, Any]:
    if f.nested:
        base = TYPE_IDS["nested"]
    elif f.base == "string" and f.string_bound:
        base = TYPE_IDS["bounded_string"]
    else:
        base = TYPE_IDS[f.base]
    return {"type_id": base + KIND_OFFSET[f.kind], "capacity": f.size, "string_capacity": f.string_bound,
            "nested_type_name": f.base if f.nested else ""}


def individual_description(type_name: str) -> dict[str, Any]:
    return {"type_name": type_name,
            "fields": [{"name": f.name, "type": field_type(f)} for f in fields_of(type_name)]}


def type_description(type_name: str) -> dict[str, Any]:
    """The TypeDescription of `type_name`, without default values (what is hashed)."""
    return {"type_description": individual_description(type_name),
            "referenced_type_descriptions": [individual_description(t) for t in dependencies(type_name)]}


@lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """"RIHS01_<64 hex digits>" for a message of ddrt.ros2.interfaces.MESSAGES."""
    text = json.dumps(type_description(type_name))
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def user_data(type_name: str) -> bytes:
    """An endpoint's USER_DATA as ROS 2's middlewares write it."""
    return f"typehash={type_hash(type_name)};".encode("ascii")
