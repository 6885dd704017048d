"""The robot's reduced dynamic model (docs/model.md), in plain floats for the hot path.

    H * d(eta)/dt + h(eta) = Bbar * tau,   eta = (v, omega),   tau = (tau_L, tau_R)

with H = [[m + k, mbar], [mbar, I]], h = [-m_x omega^2, m_x v omega] and
Bbar = [[1/r_L, 1/r_R], [-L/r_L, R/r_R]]. The seed report's own I and h are wrong (it
drops m_L L^2 + m_R R^2 and every Coriolis term); `Dynamics.from_params(p, seed_report=True)`
reproduces its model only so the seed's method can be benchmarked against ours.
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


@dataclass(frozen=True, slots=True)
class Dynamics:
    """The lumped coefficients of the reduced model, precomputed once per parameter set.

    The model is linear in (m_k, mbar, I, m_x): the adaptive law estimates exactly these.
    """

    m_k: float  # m + k: translational mass plus the wheels' spin inertia seen at A
    mbar: float  # coupling between forward and yaw motion
    I: float  # yaw inertia about A, wheels' spin included
    m_x: float  # first moment of mass along body x about A
    L: float
    R: float
    r_L: float
    r_R: float

    @classmethod
    def from_params(cls, p: RobotParams, seed_report: bool = False) -> "Dynamics":
        """Lump `p` into the model's coefficients (docs/model.md); `seed_report` keeps its errors."""
        k = p.I_wL / p.r_L**2 + p.I_wR / p.r_R**2 + p.I_w3 / p.r_3**2
        m = p.m_p + p.m_L + p.m_R + p.m_3
        mbar = -p.m_p * p.d_yc - p.m_L * p.L + p.m_R * p.R - p.L * p.I_wL / p.r_L**2 + p.R * p.I_wR / p.r_R**2
        inertia = (
            p.I_p + p.m_p * (p.d_xc**2 + p.d_yc**2) + p.I_L + p.I_R + p.I_3 + p.m_3 * p.H**2
            + p.L**2 * p.I_wL / p.r_L**2 + p.R**2 * p.I_wR / p.r_R**2
        )
        m_x = p.m_p * p.d_xc + p.m_3 * p.H
        if seed_report:
            m_x = 0.0
        else:
            inertia += p.m_L * p.L**2 + p.m_R * p.R**2
        return cls(m_k=m + k, mbar=mbar, I=inertia, m_x=m_x, L=p.L, R=p.R, r_L=p.r_L, r_R=p.r_R)

    def mass_matrix(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return ((self.m_k, self.mbar), (self.mbar, self.I))

    def forward(self, v: float, w: float, tau_l: float, tau_r: float) -> tuple[float, float]:
        """Accelerations (dv/dt, domega/dt) produced by wheel torques at state (v, omega)."""
        f_v = tau_l / self.r_L + tau_r / self.r_R + self.m_x * w * w
        f_w = -self.L * tau_l / self.r_L + self.R * tau_r / self.r_R - self.m_x * v * w
        det = self.m_k * self.I - self.mbar * self.mbar
        return (self.I * f_v - self.mbar * f_w) / det, (self.m_k * f_w - self.mbar * f_v) / det

    def inverse(self, v: float, w: float, v_dot: float, w_dot: float) -> tuple[float, float]:
        """Wheel torques (tau_L, tau_R) that produce accelerations (v_dot, w_dot) at (v, w)."""
        # Generalised forces: F = H eta_dot + h, then solve Bbar tau = F.
        f_v = self.m_k * v_dot + self.mbar * w_dot - self.m_x * w * w
        f_w = self.mbar * v_dot + self.I * w_dot + self.m_x * v * w
        # Bbar = [[1/rL, 1/rR], [-L/rL, R/rR]]: u_l = tau_l/rL, u_r = tau_r/rR.
        track = self.L + self.R
        u_l = (self.R * f_v - f_w) / track
        u_r = (self.L * f_v + f_w) / track
        return u_l * self.r_L, u_r * self.r_R

    def kinetic_energy(self, v: float, w: float) -> float:
        """0.5 eta^T H eta: the whole robot's kinetic energy (wheels' spin included)."""
        return 0.5 * self.m_k * v * v + self.mbar * v * w + 0.5 * self.I * w * w


def forward_dynamics(params: RobotParams, eta: tuple[float, float], tau: tuple[float, float]) -> tuple[float, float]:
    """(dv/dt, domega/dt) of the true model (docs/model.md) for state eta and wheel torques tau."""
    return Dynamics.from_params(params).forward(eta[0], eta[1], tau[0], tau[1])


def inverse_dynamics(params: RobotParams, eta: tuple[float, float], eta_dot: tuple[float, float]) -> tuple[float, float]:
    """Wheel torques (tau_L, tau_R) in N m that give accelerations eta_dot at state eta."""
    return Dynamics.from_params(params).inverse(eta[0], eta[1], eta_dot[0], eta_dot[1])


def wheel_rates(params: RobotParams, v: float, w: float) -> tuple[float, float, float]:
    """Spin rates (rad/s) of the left, right and front wheels for body speeds (v, omega)."""
    return (v - params.L * w) / params.r_L, (v + params.R * w) / params.r_R, v / params.r_3
