"""The robot's wiring as config: how it is wired and fixed in software (`hal.wiring`, applied by
hal/wiring.py), and the simulated robot miswired on purpose (`sim.wiring`, sim_hal/wiring.py).
`ddrt commission` measures the first on a robot the second can break (docs/commissioning.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ddrt.params.decl import Section, setting


@dataclass(frozen=True)
class WiringConfig(Section):
    """How the robot's motors and sensors are wired, fixed in software (hal/wiring.py applies
    it to every backend's reads and writes); `ddrt commission` measures it. The defaults are
    a robot wired as documented (docs/hardware.md)."""

    motor_left_inverted: bool = setting(
        False, doc="The left wheel's motor turns backwards for a forward duty: its duty is negated.")
    motor_right_inverted: bool = setting(
        False, doc="The right wheel's motor turns backwards for a forward duty: its duty is negated.")
    motors_swapped: bool = setting(
        False,
        doc="The left wheel's motor is on the right output and the other way round: the two duties are "
            "exchanged (after the inversions, which belong to the wheels).")
    encoder_sign: Literal[1, -1] = setting(
        1, doc="`-1`: the front encoder counts down going forward (its count is negated, wrapping as a signed "
               "32-bit counter).")
    gyro_sign: Literal[1, -1] = setting(
        1, doc="`-1`: the gyro is mounted upside down (its raw yaw rate is negated).")

    @property
    def identity(self) -> bool:
        """True when nothing needs fixing (no wrapper is put around the backend)."""
        return (not self.motor_left_inverted and not self.motor_right_inverted and not self.motors_swapped
                and self.encoder_sign == 1 and self.gyro_sign == 1)


@dataclass(frozen=True)
class SimWiring(Section):
    """Fault injection: the simulated robot wired wrongly (what `ddrt commission` finds and
    fixes in hal.wiring). All false: wired right."""

    left_motor_reversed: bool = setting(False, doc="The left motor turns backwards for a forward duty.")
    right_motor_reversed: bool = setting(False, doc="The right motor turns backwards for a forward duty.")
    motors_swapped: bool = setting(
        False,
        doc="The left output drives the right motor and the right output the left one (reversals apply to the "
            "motors, after the swap).")
    encoder_reversed: bool = setting(False, doc="The front encoder counts down going forward.")
    gyro_upside_down: bool = setting(False, doc="The gyro's z axis points down: its yaw rate reads negated.")
