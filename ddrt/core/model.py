"""The robot's reduced dynamic model (docs/model.md), in plain floats for the hot path.

    H * d(eta)/dt + h(eta) = Bbar * tau,   eta = (v, omega),   tau = (tau_L, tau_R)

with H = [[m + k, mbar], [mbar, I]], h = [-m_x omega^2, m_x v omega] and
Bbar = [[1/r_L, 1/r_R], [-L/r_L, R/r_R]]. The seed report's own I and h are wrong (it
drops m_L L^2 + m_R R^2 and every Coriolis term); `Dynamics.from_params(p, seed_report=True)`
reproduces its model only so the seed's method can be benchmarked against ours.
"""

from __future__ import annotations

from dataclasses import dataclass

from ddrt.params.robot import RobotParams

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
