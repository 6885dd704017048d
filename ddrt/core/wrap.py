"""Wrap-around arithmetic used on both sides of the hardware boundary: angles and the
microcontroller's signed 32-bit counters. One definition each, so the estimator, the
controller, the path and the drivers agree on the edge cases."""

from __future__ import annotations

import math

TWO_PI = 2.0 * math.pi


def wrap_angle(a: float) -> float:
    """Angle in (-pi, pi]."""
    a = math.fmod(a + math.pi, TWO_PI)
    if a <= 0.0:
        a += TWO_PI
    return a - math.pi


def wrap_i32(x: int) -> int:
    """`x` as a signed 32-bit integer (two's complement wrap)."""
    return ((x + 0x80000000) & 0xFFFFFFFF) - 0x80000000
