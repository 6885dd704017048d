"""The robot's wiring, fixed in software: one wrapper every backend's reads and writes pass through.

A motor wired backwards, two motors on each other's outputs, an encoder that counts down going
forward or a gyro mounted upside down are facts about one robot, measured by `ddrt commission`
and written to `hal.wiring` (ddrt.config.sections.WiringConfig). `open_hal` (hal/registry.py)
puts `WiredHal` around whichever backend the config chooses when, and only when, the wiring is
not the documented one, so the controller, the estimator and the daemon never know and a robot
wired as documented runs with no wrapper at all.
"""

from __future__ import annotations

from typing import Any

from ddrt.config.wiring import WiringConfig
from hal.base import Hal, Sample

_INT16_MIN, _INT16_MAX = -32768, 32767


def negate_count(count: int) -> int:
    """-count on a counter that wraps like a signed 32-bit integer (-(-2**31) is itself)."""
    return ((-count + 2**31) % 2**32) - 2**31


def negate_gyro(raw: int) -> int:
    """-raw for an int16 reading (-(-32768) saturates at 32767, as the part itself would)."""
    return max(_INT16_MIN, min(_INT16_MAX, -raw))


class WiredHal(Hal):
    """`inner` as a correctly wired robot: duties are inverted and swapped on the way out,
    encoder and gyro readings sign-corrected on the way in. The drive wheels' counts follow
    their motors' fixes: a wheel's encoder sits on its motor's shaft and shares its harness, so
    with `motors_swapped` the left wheel's counts arrive on the right channel (swapped back),
    and an inverted motor's counts run backwards too (negated), as with mirror-mounted motors
    (docs/commissioning.md). Everything else (info, clock,
    the simulated robot's truth, fault counters, fault injection) is the inner backend's."""

    def __init__(self, inner: Hal, wiring: WiringConfig) -> None:
        self.inner = inner
        self.wiring = wiring
        self.info = inner.info
        self.robot = inner.robot
        self.owns_time = inner.owns_time
        self._l_sign = -1.0 if wiring.motor_left_inverted else 1.0
        self._r_sign = -1.0 if wiring.motor_right_inverted else 1.0
        self._swap = wiring.motors_swapped
        self._enc_flip = wiring.encoder_sign == -1
        self._gyro_flip = wiring.gyro_sign == -1
        self._wheels = inner.info.wheel_counts_per_rev > 0

    def read(self) -> Sample:
        s = self.inner.read()
        if self._enc_flip:
            s.encoder_count = negate_count(s.encoder_count)
        if self._gyro_flip:
            s.gyro_z_raw = negate_gyro(s.gyro_z_raw)
        if self._wheels:
            left, right = (s.count_right, s.count_left) if self._swap else (s.count_left, s.count_right)
            s.count_left = negate_count(left) if self._l_sign < 0.0 else left
            s.count_right = negate_count(right) if self._r_sign < 0.0 else right
        return s

    def _write(self, duty_l: float, duty_r: float) -> None:
        left, right = self._l_sign * duty_l, self._r_sign * duty_r  # the wheels' motors ...
        if self._swap:
            self.inner.write(right, left)  # ... on the outputs they are wired to
        else:
            self.inner.write(left, right)

    def stop(self) -> None:
        self.inner.stop()

    def _close(self) -> None:
        self.inner.close()  # set before anything in the constructor can fail

    @property
    def fault_counters(self) -> dict[str, int] | None:
        return self.inner.fault_counters

    def advance_to_wall_clock(self) -> None:
        self.inner.advance_to_wall_clock()

    def __getattr__(self, name: str) -> Any:
        # Only reached for what WiredHal does not define: the inner backend's own clock
        # (now, sleep_until, paced) and fault injection (freeze), unchanged.
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)


def wire(hal: Hal, wiring: WiringConfig) -> Hal:
    """`hal` itself for the documented wiring, else `hal` behind a `WiredHal`."""
    return hal if wiring.identity else WiredHal(hal, wiring)
