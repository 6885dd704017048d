"""Strict JSON lines, the control socket's framing both ways: one JSON value per line, and no
NaN or Infinity (they are not JSON), and no key twice in one object.

A request that holds one is refused with an error naming the field (`strict_loads` marks
them, `find_non_finite` says where); a reply that would hold one goes out with null there
and lists where in "non_finite" (`encode_reply`); a client refuses a reply that holds one
(`decode_strict`). The server (ddrt/service/ctlserver.py), the client
(ddrt/service/ctlclient.py) and `--stats-json` (ddrt/service/status.py) all encode here.
"""

from __future__ import annotations

import json
import math
from typing import Any

from ddrt.errors import DdrtError


class NonFinite:
    """What a NaN, Infinity or out-of-range number in a request parses to."""

    __slots__ = ("token",)

    def __init__(self, token: str) -> None:
        self.token = token


class DuplicateKey(DdrtError, ValueError):
    """An object gives the same key twice: which value was meant is not for the server to guess."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise DuplicateKey(f"duplicate key {key!r}: each key at most once per object")
            seen.add(key)
    return obj


def strict_loads(line: bytes | str) -> tuple[Any, bool]:
    """json.loads that turns NaN, Infinity, -Infinity and 1e999 into NonFinite markers and
    refuses an object with a duplicate key (DuplicateKey, a ValueError naming it: the config's
    YAML reader refuses them too); returns (value, whether a non-finite number was found), so
    a clean request costs no second walk."""
    found = False

    def constant(token: str) -> NonFinite:
        nonlocal found
        found = True
        return NonFinite(token)

    def number(token: str) -> float | NonFinite:
        value = float(token)
        return value if math.isfinite(value) else constant(token)

    value = json.loads(line, parse_constant=constant, parse_float=number, object_pairs_hook=_unique_keys)
    return (value, found)


def find_non_finite(obj: Any) -> tuple[str, str] | None:
    """(where, token) of the first NonFinite in a parsed request, e.g. ("pose[1]", "NaN")."""
    stack: list[tuple[Any, str]] = [(obj, "")]
    while stack:
        item, where = stack.pop()
        if isinstance(item, NonFinite):
            return where or "the request", item.token
        if isinstance(item, dict):
            stack.extend((v, f"{where}.{k}" if where else str(k)) for k, v in reversed(item.items()))
        elif isinstance(item, list):
            stack.extend((v, f"{where}[{i}]") for i, v in reversed(list(enumerate(item))))
    return None


def finite_or_null(obj: Any, where: str = "", found: list[str] | None = None) -> Any:
    """A copy of `obj` with every NaN/Infinity float replaced by None; their paths go to `found`."""
    if isinstance(obj, float):
        if math.isfinite(obj):
            return obj
        if found is not None:
            found.append(where)
        return None
    if isinstance(obj, dict):
        return {k: finite_or_null(v, f"{where}.{k}" if where else str(k), found) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v, f"{where}[{i}]", found) for i, v in enumerate(obj)]
    return obj


def encode_line(obj: Any) -> bytes:
    """One strict JSON line; ValueError if `obj` holds NaN or Infinity."""
    return (json.dumps(obj, allow_nan=False) + "\n").encode()


def encode_reply(reply: dict[str, Any]) -> bytes:
    """One strict JSON line. A non-finite float goes out as null, listed in "non_finite"."""
    try:
        return encode_line(reply)
    except ValueError:
        found: list[str] = []
        clean = finite_or_null(reply, "", found)
        clean["non_finite"] = found
        return encode_line(clean)


def error_line(message: str, request_id: Any = None) -> bytes:
    """`{"ok": false, "error": message}` as a line, with the request's "id" when it had one."""
    reply: dict[str, Any] = {"ok": False, "error": message}
    if request_id is not None:
        reply["id"] = request_id
    return encode_reply(reply)


def _reject_constant(token: str) -> Any:
    raise ValueError(f"{token} is not JSON")


def decode_strict(line: bytes | str) -> Any:
    """json.loads that refuses NaN and Infinity (ValueError)."""
    return json.loads(line, parse_constant=_reject_constant)
