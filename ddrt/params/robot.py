"""The robot's geometry and mass properties as the `robot:` (and `plant:`) sections give them.

Plain validated data: the dynamic model (ddrt/core/model.py) derives its coefficients from
them, the config reads them, the simulator builds its plant from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Mapping

from ddrt.params.decl import Section, check_declared, field_items, setting

# Magnitudes no wheeled robot of this kind reaches: metres, wheel radii, kilograms, kg m^2.
LENGTH_M, RADIUS_M, MASS_KG, INERTIA_KGM2 = 10.0, 1.0, 1000.0, 1000.0


@dataclass(frozen=True)
class RobotParams(Section):
    """Geometry and mass properties of the robot, SI units, names as in the seed report.

    Body frame: origin A mid rear axle, x forward, y left. Left wheel at (0, +L), right at
    (0, -R), front omni-wheel at (H, 0), platform centre of mass at (d_xc, d_yc). I_p is about
    the platform's own centre of mass; I_L, I_R, I_3 are each wheel's yaw inertia about its own
    centre; I_wL, I_wR, I_w3 are spin inertias about the axles.
    """

    H: float = setting(unit="m", gt=0, le=LENGTH_M, doc="Distance along x from A to the front omni-wheel.")
    L: float = setting(unit="m", gt=0, le=LENGTH_M, doc="Distance from A to the left wheel's centre (at y = +L).")
    R: float = setting(unit="m", gt=0, le=LENGTH_M, doc="Distance from A to the right wheel's centre (at y = -R).")
    r_L: float = setting(unit="m", gt=0, le=RADIUS_M, doc="Left wheel radius.")
    r_R: float = setting(unit="m", gt=0, le=RADIUS_M, doc="Right wheel radius.")
    r_3: float = setting(
        unit="m", gt=0, le=RADIUS_M,
        doc="Front omni-wheel radius; the encoder is on this wheel, so odometry scales with it.")
    d_xc: float = setting(
        unit="m", ge=-LENGTH_M, le=LENGTH_M,
        doc="x of the platform's centre of mass, within twice the robot's wheelbase and track of A.")
    d_yc: float = setting(
        unit="m", ge=-LENGTH_M, le=LENGTH_M, doc="y of the platform's centre of mass, within twice the half track.")
    m_p: float = setting(unit="kg", gt=0, le=MASS_KG, doc="Platform mass (wheels excluded).")
    m_L: float = setting(unit="kg", gt=0, le=MASS_KG, doc="Left wheel assembly mass.")
    m_R: float = setting(unit="kg", gt=0, le=MASS_KG, doc="Right wheel assembly mass.")
    m_3: float = setting(unit="kg", gt=0, le=MASS_KG, doc="Front omni-wheel assembly mass.")
    I_p: float = setting(
        unit="kg m^2", gt=0, le=INERTIA_KGM2, doc="Platform yaw inertia about its own centre of mass.")
    I_L: float = setting(
        unit="kg m^2", gt=0, le=INERTIA_KGM2, doc="Left wheel assembly's yaw inertia about its own centre.")
    I_R: float = setting(
        unit="kg m^2", gt=0, le=INERTIA_KGM2, doc="Right wheel assembly's yaw inertia about its own centre.")
    I_3: float = setting(
        unit="kg m^2", gt=0, le=INERTIA_KGM2, doc="Front wheel assembly's yaw inertia about its own centre.")
    I_wL: float = setting(unit="kg m^2", gt=0, le=INERTIA_KGM2, doc="Left wheel's spin inertia about its axle.")
    I_wR: float = setting(unit="kg m^2", gt=0, le=INERTIA_KGM2, doc="Right wheel's spin inertia about its axle.")
    I_w3: float = setting(unit="kg m^2", gt=0, le=INERTIA_KGM2, doc="Front wheel's spin inertia about its axle.")

    def __post_init__(self) -> None:
        # Parameters are also built in code (identification, the estimate, tests), not only read
        # by the config's walker: each is checked against its declaration here too.
        for f, value in field_items(self):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"RobotParams.{f.name}: expected a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"RobotParams.{f.name}: must be finite, got {value!r}")
            object.__setattr__(self, f.name, float(value))
        check_declared(self, "RobotParams")
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
