"""One gearmotor and its driver, referred to the wheel, as the config gives it (ddrt/core/motor.py
is the model that uses these numbers).

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

from ddrt.params.numbers import from_known_keys


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
        return from_known_keys(cls, mapping)

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
