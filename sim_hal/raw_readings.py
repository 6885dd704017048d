"""How the simulated sensors turn the plant's true state into the raw numbers hardware gives.

Kept apart from the integrator so the quantisation, wrapping and saturation rules (the
parts a driver or estimator gets wrong) can be tested on their own.
"""

from __future__ import annotations

import math

from ddrt.core.wrap import wrap_i32

INT16_MIN = -32768
INT16_MAX = 32767


def encoder_count(angle_rad: float, counts_per_rev: int, offset: int = 0) -> int:
    """Raw counter value for a wheel turned `angle_rad` from where the count was `offset`."""
    return wrap_i32(math.floor(angle_rad * counts_per_rev / (2.0 * math.pi)) + offset)


def gyro_raw(rate_dps: float, lsb_per_dps: float) -> int:
    """Quantise a rate (deg/s) to the gyro's int16 output, saturating at the int16 limits."""
    raw = round(rate_dps * lsb_per_dps)
    if raw > INT16_MAX:
        return INT16_MAX
    if raw < INT16_MIN:
        return INT16_MIN
    return raw


def lowpass_coefficient(cutoff_hz: float, sample_hz: float) -> float:
    """Gain `a` of y += a (x - y): the discrete first-order filter with the same pole."""
    return 1.0 - math.exp(-2.0 * math.pi * cutoff_hz / sample_hz)
