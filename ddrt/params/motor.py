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
from dataclasses import dataclass
from typing import Any, Mapping

from ddrt.params.decl import Section, check_declared, field_items, setting
from ddrt.params.numbers import from_known_keys


# Magnitudes no gearmotor of a wheeled robot reaches (SI units, at the wheel): they catch a
# typo or a unit slip before the model feeds it forward.
@dataclass(frozen=True)
class MotorParams(Section):
    """One gearmotor and its driver, referred to the wheel shaft (SI units)."""

    supply_v: float = setting(
        12.0, unit="V", gt=0, le=1000.0,
        doc="Driver supply voltage: duty 1 puts this across the armature. When the hardware measures the "
            "supply (a protocol-v2 MCU, the simulator), the measured, filtered voltage replaces it in the motor "
            "model, the controller's limits and a starting path's profile (ddrt/loop/power.py); this value is "
            "used until the first reading, and readings outside 0.25 to 2 times it are rejected as implausible.")
    resistance_ohm: float = setting(3.82, unit="ohm", gt=0, le=1000.0, doc="Armature resistance R_a.")
    k_nm_per_a: float = setting(
        0.382, unit="N m/A (= V s/rad)", gt=0, le=100.0,
        doc="Torque constant at the wheel, equal to the back-EMF constant.")
    viscous_nms: float = setting(0.00086, unit="N m s/rad", ge=0, le=10.0, doc="Viscous friction b at the wheel.")
    coulomb_nm: float = setting(0.03, unit="N m", ge=0, le=100.0, doc="Coulomb (dry) friction tau_c at the wheel.")
    coulomb_smoothing_rad_s: float = setting(
        0.02, unit="rad/s", gt=0, le=100.0,
        doc="Wheel speed over which Coulomb friction builds up (tanh), so the integrator does not chatter at "
            "rest.")

    def __post_init__(self) -> None:
        # Also built in code (identification, tests): checked against the declarations here too.
        for f, value in field_items(self):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"MotorParams.{f.name}: expected a finite number, got {value!r}")
            object.__setattr__(self, f.name, float(value))
        check_declared(self, "MotorParams")

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
