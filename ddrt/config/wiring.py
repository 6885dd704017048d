"""The robot's wiring as config: how it is wired and fixed in software (`hal.wiring`, applied by
hal/wiring.py), and the simulated robot miswired on purpose (`sim.wiring`, sim_hal/wiring.py).
`ddrt commission` measures the first on a robot the second can break (docs/commissioning.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class WiringConfig:
    """How the robot's motors and sensors are wired, fixed in software (hal/wiring.py applies
    it to every backend's reads and writes); `ddrt commission` measures it. The defaults are
    a robot wired as documented (docs/hardware.md)."""

    motor_left_inverted: bool = False  # the left wheel's motor turns backwards for a forward duty
    motor_right_inverted: bool = False
    motors_swapped: bool = False  # the left wheel's motor is on the right output
    encoder_sign: Literal[1, -1] = 1  # -1: the front encoder counts down going forward
    gyro_sign: Literal[1, -1] = 1  # -1: the gyro is mounted upside down (z axis down)

    @property
    def identity(self) -> bool:
        """True when nothing needs fixing (no wrapper is put around the backend)."""
        return (not self.motor_left_inverted and not self.motor_right_inverted and not self.motors_swapped
                and self.encoder_sign == 1 and self.gyro_sign == 1)


@dataclass(frozen=True)
class SimWiring:
    """Fault injection: the simulated robot wired wrongly (what `ddrt commission` finds and
    fixes in hal.wiring). All false: wired right (today's robot)."""

    left_motor_reversed: bool = False  # the left motor turns backwards for a forward duty
    right_motor_reversed: bool = False
    motors_swapped: bool = False  # the left duty drives the right motor and the other way
    encoder_reversed: bool = False  # the front encoder counts down going forward
    gyro_upside_down: bool = False  # the gyro's z axis points down: yaw rate reads negated
