"""Fault injection: a simulated robot wired wrongly (`sim.wiring`), the faults `ddrt commission`'s
wiring step must find and fix (hal.wiring, hal/wiring.py).

Applied by SimHal at its boundary, between the duties written to it and the plant's motors and
between the plant's sensors and the samples it returns, as a miswired harness sits between the
driver board and the robot.
"""

from __future__ import annotations

from dataclasses import dataclass

from ddrt.config.wiring import SimWiring


def _neg32(count: int) -> int:
    return ((-count + 2**31) % 2**32) - 2**31


def _neg16(raw: int) -> int:
    return max(-32768, min(32767, -raw))


@dataclass(frozen=True)
class WiringFaults:
    """The miswiring of one simulated robot; `faulty` is False for a robot wired right."""

    left_reversed: bool = False
    right_reversed: bool = False
    swapped: bool = False
    encoder_reversed: bool = False
    gyro_upside_down: bool = False

    @classmethod
    def from_config(cls, w: SimWiring) -> "WiringFaults":
        return cls(w.left_motor_reversed, w.right_motor_reversed, w.motors_swapped, w.encoder_reversed,
                   w.gyro_upside_down)

    @property
    def faulty(self) -> bool:
        return self.left_reversed or self.right_reversed or self.swapped or self.encoder_reversed or self.gyro_upside_down

    def motors(self, out_l: float, out_r: float) -> tuple[float, float]:
        """The duties the (left, right) motors get from the driver's (left, right) outputs."""
        left, right = (out_r, out_l) if self.swapped else (out_l, out_r)
        return (-left if self.left_reversed else left), (-right if self.right_reversed else right)

    def encoder(self, count: int) -> int:
        return _neg32(count) if self.encoder_reversed else count

    def wheels(self, left: int, right: int) -> tuple[int, int]:
        """The (left, right) channels' counts from the (left, right) wheels' encoders: each
        encoder sits on its motor and shares its harness, so it is reversed and swapped with it."""
        left = _neg32(left) if self.left_reversed else left
        right = _neg32(right) if self.right_reversed else right
        return (right, left) if self.swapped else (left, right)

    def gyro(self, raw: int) -> int:
        return _neg16(raw) if self.gyro_upside_down else raw
