"""One check for "a finite real number" on values that came from outside (a config file, a
socket request, a Foxglove message): bools and text are refused, an integer beyond the float
range is refused rather than overflowing, NaN and infinities are refused. The caller's `where`
names the key or field, so the message tells the user what to fix. Likewise one check that a
mapping from outside holds only a dataclass's fields (`from_known_keys`)."""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any, Mapping, TypeVar

# |x|, |y| of a pose from outside (a socket request, a fix) beyond this is no place on a floor.
POSE_BOUND_M = 1e6

T = TypeVar("T")


def finite_float(value: object, where: str, shown: str | None = None, unit: str = "") -> float:
    """float(value), or ValueError naming `where` (and the `unit` expected). `shown`: how to
    print the value (a bounded repr; by default the type's name and a short repr)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        text = shown if shown is not None else _short(value)
        raise ValueError(f"{where}: expected a number{' in ' + unit if unit else ''}, got {text}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond the float range
        text = shown if shown is not None else f"a {value.bit_length()}-bit integer"
        raise ValueError(f"{where}: too large for a number, got {text}") from None
    if not math.isfinite(number):
        raise ValueError(f"{where}: must be finite, got {shown if shown is not None else number}")
    return number


def _short(value: object) -> str:
    r = repr(value)
    return f"{type(value).__name__} {r if len(r) <= 40 else r[:37] + '...'}"


def from_known_keys(cls: type[T], mapping: Mapping[str, Any]) -> T:
    """cls(**mapping) for a dataclass `cls`, or ValueError naming the keys it does not have
    (a typo in a config is an error, not a default silently kept)."""
    known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(mapping) - known)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown key(s) {', '.join(unknown)}")
    return cls(**dict(mapping))
