"""The robot's geometry and mass properties as the `robot:` (and `plant:`) sections give them.

Plain validated data: the dynamic model (ddrt/core/model.py) derives its coefficients from
them, the config reads them, the simulator builds its plant from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Mapping

# Fields that must be strictly positive; d_xc and d_yc may take any finite value.
# Magnitudes no wheeled robot of this kind reaches: metres, wheel radii, kilograms, kg m^2.
_BOUNDS = {"length": 10.0, "r": 1.0, "m": 1000.0, "I": 1000.0}
_POSITIVE = (
    "H", "L", "R", "r_L", "r_R", "r_3", "m_p", "m_L", "m_R", "m_3",
    "I_p", "I_L", "I_R", "I_3", "I_wL", "I_wR", "I_w3",
)


@dataclass(frozen=True)
class RobotParams:
    """Geometry and mass properties of the robot, SI units, names as in the seed report.

    Body frame: origin A mid rear axle, x forward, y left. Left wheel at (0, +L), right at
    (0, -R), front omni-wheel at (H, 0), platform centre of mass at (d_xc, d_yc). I_p is about
    the platform's own centre of mass; I_L, I_R, I_3 are each wheel's yaw inertia about its own
    centre; I_wL, I_wR, I_w3 are spin inertias about the axles.
    """

    H: float
    L: float
    R: float
    r_L: float
    r_R: float
    r_3: float
    d_xc: float
    d_yc: float
    m_p: float
    m_L: float
    m_R: float
    m_3: float
    I_p: float
    I_L: float
    I_R: float
    I_3: float
    I_wL: float
    I_wR: float
    I_w3: float

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"RobotParams.{f.name}: expected a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"RobotParams.{f.name}: must be finite, got {value!r}")
            if f.name in _POSITIVE and value <= 0.0:
                raise ValueError(f"RobotParams.{f.name}: must be > 0, got {value!r}")
            bound = _BOUNDS[f.name[0] if f.name[0] in "mI" else ("r" if f.name.startswith("r_") else "length")]
            if abs(value) > bound:
                raise ValueError(f"RobotParams.{f.name}: {value!r} is beyond any wheeled robot this controller "
                                 f"is for (at most {bound:g} in SI units)")
            object.__setattr__(self, f.name, float(value))
        # The platform's centre of mass lies over the robot (generously: within twice its
        # wheelbase and track), not metres beside it.
        half_track = max(self.L, self.R)
        reach = 2.0 * (self.H + half_track)
        if abs(self.d_yc) > 2.0 * half_track or not -reach <= self.d_xc <= reach:
            raise ValueError(f"RobotParams.d_xc: the platform's centre of mass ({self.d_xc:g}, {self.d_yc:g}) m "
                             f"lies outside the robot (H = {self.H:g} m, L = {self.L:g} m, R = {self.R:g} m)")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> "RobotParams":
        """Build from a mapping that may hold other keys too (they are ignored)."""
        missing = [n for n in cls.names() if n not in mapping]
        if missing:
            raise ValueError(f"RobotParams: missing field(s) {', '.join(missing)}")
        return cls(**{n: mapping[n] for n in cls.names()})

    def mirrored(self) -> "RobotParams":
        """The mirror image through the body x axis (left and right swapped, d_yc negated)."""
        return RobotParams(
            H=self.H, L=self.R, R=self.L, r_L=self.r_R, r_R=self.r_L, r_3=self.r_3,
            d_xc=self.d_xc, d_yc=-self.d_yc, m_p=self.m_p, m_L=self.m_R, m_R=self.m_L,
            m_3=self.m_3, I_p=self.I_p, I_L=self.I_R, I_R=self.I_L, I_3=self.I_3,
            I_wL=self.I_wR, I_wR=self.I_wL, I_w3=self.I_w3,
        )
