"""Teleop from a Foxglove client: a Twist-like JSON message -> (v, omega), or why not.

The Teleop panel publishes geometry_msgs/Twist as JSON when the server offers the json
encoding: {"linear": {"x": v, ...}, "angular": {"z": omega, ...}}. Anything else (not
JSON, not an object, a missing, non-numeric or non-finite field, an oversized message) is
refused with a reason that names the field; the caller drops it and logs (rate-limited).
Limits on the values themselves are the velocity mode's (ddrt.service.handlers.drive).
"""

from __future__ import annotations

import json
import logging
from typing import Any

from ddrt.params.numbers import finite_float

TOPICS = ("/teleop", "/cmd_vel")
MAX_BYTES = 4096
log = logging.getLogger("ddrt.viz.teleop")


def parse_twist(data: bytes) -> tuple[float, float]:
    """(linear.x, angular.z) of one message, or ValueError naming what is wrong."""
    if len(data) > MAX_BYTES:
        raise ValueError(f"message of {len(data)} bytes, more than {MAX_BYTES}")
    try:
        doc = json.loads(data, parse_constant=_no_constant)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise ValueError(f"not JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"expected an object with linear and angular, got {type(doc).__name__}")
    return _component(doc, "linear", "x"), _component(doc, "angular", "z")


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number")


def _component(doc: dict[str, Any], part: str, axis: str) -> float:
    vec = doc.get(part)
    if not isinstance(vec, dict):
        raise ValueError(f"{part}: expected an object, got {type(vec).__name__}")
    value = vec.get(axis, 0.0)
    return finite_float(value, f"{part}.{axis}")


class DropLog:
    """Warn about the first few refused messages, then one line per `every` (a flood of garbage
    must not become a flood of log lines)."""

    def __init__(self, first: int = 5, every: int = 1000, what: str = "foxglove teleop: message dropped") -> None:
        self.first, self.every, self.what = first, every, what
        self.count = 0

    def drop(self, why: str) -> None:
        self.count += 1
        if self.count <= self.first or self.count % self.every == 0:
            log.warning("%s (%d so far): %s", self.what, self.count, why)
