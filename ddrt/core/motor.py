"""A brushed DC gearmotor, referred to the wheel: duty and speed in, torque out, and back.

Electrical time constant (L/R, about a millisecond) is neglected: the current follows the
voltage within one plant step. All constants are at the wheel (after the gearbox):

    i        = (duty * V - K * w) / R_a
    tau_net  = K * i - b * w - tau_c * tanh(w / w_s)

with K = k_t * G = k_e * G (N m/A = V s/rad). The Coulomb term is smoothed over `w_s` so a
fixed-step integrator does not chatter at rest; w_s is small (0.02 rad/s) against any speed
the robot drives at.

Default numbers, for a 12 V, 300 rpm (no load) gearmotor like the seed's RKI-1188 (the seed
gives no datasheet figures; these are assumptions, written down so they can be replaced):
- no-load speed 300 rpm = 31.4 rad/s at 12 V   -> K = 12 / 31.4 = 0.382 V s/rad
- stall torque assumed 1.2 N m (about 12 kgf cm, typical of 37 mm 300 rpm gearmotors)
                                                -> R_a = K * V / stall = 3.82 ohm (3.1 A stall)
- no-load current assumed 0.15 A               -> friction at no-load 0.057 N m, split into
  Coulomb 0.03 N m and viscous 0.027 / 31.4 = 0.00086 N m s/rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Mapping


# Magnitudes no gearmotor of a wheeled robot reaches (SI units, at the wheel): they catch a
# typo or a unit slip before the model feeds it forward.
_BOUNDS = {"supply_v": 1000.0, "resistance_ohm": 1000.0, "k_nm_per_a": 100.0, "viscous_nms": 10.0,
           "coulomb_nm": 100.0, "coulomb_smoothing_rad_s": 100.0}


@dataclass(frozen=True)
class MotorParams:
    """One gearmotor and its driver, referred to the wheel shaft (SI units)."""

    supply_v: float = 12.0  # driver supply voltage (V)
    resistance_ohm: float = 3.82  # armature resistance R_a
    k_nm_per_a: float = 0.382  # torque constant at the wheel = back-EMF constant (V s/rad)
    viscous_nms: float = 0.00086  # viscous friction b at the wheel (N m s/rad)
    coulomb_nm: float = 0.03  # Coulomb friction tau_c at the wheel (N m)
    coulomb_smoothing_rad_s: float = 0.02  # w_s: speed over which Coulomb friction builds up

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"MotorParams.{f.name}: expected a finite number, got {value!r}")
            if f.name in ("supply_v", "resistance_ohm", "k_nm_per_a", "coulomb_smoothing_rad_s") and value <= 0:
                raise ValueError(f"MotorParams.{f.name}: must be > 0, got {value!r}")
            if value < 0:
                raise ValueError(f"MotorParams.{f.name}: must be >= 0, got {value!r}")
            if value > _BOUNDS[f.name]:
                raise ValueError(f"MotorParams.{f.name}: {value!r} is beyond any gearmotor this controller is "
                                 f"for (at most {_BOUNDS[f.name]:g})")
            object.__setattr__(self, f.name, float(value))

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> "MotorParams":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(mapping) - known)
        if unknown:
            raise ValueError(f"MotorParams: unknown key(s) {', '.join(unknown)}")
        return cls(**dict(mapping))

    @property
    def stall_torque_nm(self) -> float:
        return self.k_nm_per_a * self.supply_v / self.resistance_ohm

    @property
    def no_load_speed_rad_s(self) -> float:
        return self.supply_v / self.k_nm_per_a

    @property
    def back_emf_damping_nms(self) -> float:
        """K^2 / R_a: the damping the motor gives for free when driven by a voltage."""
        return self.k_nm_per_a * self.k_nm_per_a / self.resistance_ohm


class Motor:
    """Forward and inverse motor model with the constants of `MotorParams` cached as floats."""

    __slots__ = ("params", "_v", "_r", "_k", "_b", "_tc", "_ws")

    def __init__(self, params: MotorParams) -> None:
        self.params = params
        self._v = params.supply_v
        self._r = params.resistance_ohm
        self._k = params.k_nm_per_a
        self._b = params.viscous_nms
        self._tc = params.coulomb_nm
        self._ws = params.coulomb_smoothing_rad_s

    def friction(self, wheel_speed: float) -> float:
        """Friction torque (N m) opposing rotation at `wheel_speed` rad/s."""
        return self._b * wheel_speed + self._tc * math.tanh(wheel_speed / self._ws)

    def electromagnetic_torque(self, duty: float, wheel_speed: float) -> float:
        """Torque the armature produces before friction (N m at the wheel)."""
        return self._k * (duty * self._v - self._k * wheel_speed) / self._r

    def torque(self, duty: float, wheel_speed: float) -> float:
        """Net torque at the wheel (N m) for `duty` in [-1, 1] at `wheel_speed` (rad/s)."""
        if not (-1.0 <= duty <= 1.0):
            raise ValueError(f"duty {duty!r} is outside [-1, 1]")
        return self.electromagnetic_torque(duty, wheel_speed) - self.friction(wheel_speed)

    def duty_for_torque(self, torque: float, wheel_speed: float, emf_speed: float | None = None,
                        friction_speed: float | None = None) -> tuple[float, bool]:
        """Duty that yields net `torque` at `wheel_speed`; returns (duty, saturated).

        The duty is NOT clipped: `saturated` is True when |duty| > 1 and the caller decides how
        to limit it (the controller scales both wheels together). `emf_speed` (default
        `wheel_speed`) is the speed whose back-EMF is fed forward: passing the reference speed
        rather than the measured one keeps the motor's own damping about the reference.
        `friction_speed` (default `wheel_speed`) likewise picks the speed friction is
        compensated at.
        """
        ws = wheel_speed if emf_speed is None else emf_speed
        fs = wheel_speed if friction_speed is None else friction_speed
        drive = torque + self.friction(fs)
        duty = (self._r * drive / self._k + self._k * ws) / self._v
        return duty, not (-1.0 <= duty <= 1.0)
